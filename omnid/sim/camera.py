"""The simulated cameras: a free-running frame clock, exposures, dropped frames, and a scene
whose texture is fixed to the world, so that a chair in motion sees its floor move between
frames while its laser dots (fixed to the chair) do not.

What is modelled, and why it matters for depth at the frame rate:

* **Frame clock** — frame k is exposed around t_k = phase + k / fps (the phase is random per
  run: the cameras free-run, nothing aligns them with the control loop), for ``exposure_s``;
  it is delivered ``readout_s`` after the middle of its exposure and carries t_k as its capture
  time. A share ``drop_rate`` of frames is lost (USB hiccups, a busy driver).
* **Laser timing** — each frame shows the laser dots scaled by the share of its exposure during
  which the laser was actually lit (the control unit's relay history, switch latency included):
  a frame taken while the relay switched shows dim dots.
* **Motion between frames** — each frame is rendered at the chair's pose at t_k. The scene
  texture is a function of the world point each pixel sees (floor, box tops and sides, the
  bottom of a drop-off), found by casting the pixel's viewing ray (SPEC §2: a pinhole at the
  mirror axis) on a coarse grid. Texture: a smooth random field (as ``render.py``'s scene) plus
  fine detail, or square tiles with grout lines; pre-blurred to a floor pixel's footprint.

Not modelled: motion blur within an exposure (at 240 mm/s and 8 ms: 0.2 px on the floor),
rolling shutter, auto-exposure, specular highlights, moving shadows.

The dots' shapes, halos and ghosts come from :func:`omnid.sim.render.laser_image` (the spot
model of ``render.py``).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.sim.render import (
    OUTSIDE_DISK_LEVEL,
    RenderOptions,
    disk_mask,
    hits_flux,
    laser_image,
    sensor_image,
)
from omnid.sim.world import LaserHits, RigMount, World

Pose = tuple[float, float, float]
Image = NDArray[np.uint8]


@dataclass(frozen=True)
class CameraModel:
    """Timing and scene of the simulated cameras (s, mm, gray levels)."""

    fps: float = 30.0
    exposure_s: float = 0.008
    readout_s: float = 0.006  # middle of the exposure → frame pair delivered
    drop_rate: float = 0.0  # share of frame pairs lost
    phase_s: float | None = None  # frame clock phase; None: drawn from the seed
    texture: Literal["smooth", "tiles"] = "smooth"
    # where the texture is fixed: "world" — on the floor, the drop-off bottoms and the boxes
    # (their sides and tops move with a parallax the floor's motion compensation does not
    # follow); "floor" — on the floor and drop-off bottoms only, boxes a uniform gray;
    # "camera" — in the image (the scene does not move when the chair does: no motion residue,
    # what render.py draws; the cheapest)
    textured: Literal["world", "floor", "camera"] = "world"
    texture_level: float = 70.0  # mean gray of the scene
    texture_contrast: float = 25.0  # amplitude of the coarse texture (as render.py's scene)
    texture_detail: float = 6.0  # amplitude of the fine texture (grain ~ 3 floor px)
    tile_mm: float = 300.0
    grout_mm: float = 10.0
    grout_gray: float = 35.0  # grout this much darker than the tile
    grid_px: int = 4  # the viewing rays are cast on a grid this coarse

    def __post_init__(self) -> None:
        require(0 < self.fps <= 240, "fps", "must be in (0, 240]")
        require(0 < self.exposure_s < 1.0 / self.fps, "exposure_s", "must be in (0, 1/fps)")
        require(self.readout_s >= self.exposure_s / 2, "readout_s", "must be ≥ exposure_s/2")
        require(0 <= self.drop_rate < 1, "drop_rate", "must be in [0, 1)")
        require(self.texture in ("smooth", "tiles"), "texture", "must be smooth or tiles")
        require(
            self.textured in ("world", "floor", "camera"),
            "textured",
            "must be world, floor or camera",
        )
        require(1 <= self.grid_px <= 16, "grid_px", "must be in 1..16")

    @property
    def period_s(self) -> float:
        return 1.0 / self.fps


@dataclass(frozen=True)
class SimFrame:
    """What the simulated camera knows of one frame pair (rendered only when it is used)."""

    index: int
    t_s: float  # middle of the exposure: the capture time
    pose: Pose  # the chair's pose at t_s
    lit: float  # share of the exposure with the laser lit, [0, 1]
    seed: int
    world: int = 0  # the version of the world it was exposed in (worlds change: hazards)

    @property
    def laser(self) -> bool:
        """Any laser light in this frame."""
        return self.lit > 0.0


class SceneTexture:
    """Gray levels fixed to world points (x, y, h) mm: a 2-D texture image over the world's
    floor extent, sampled at (x + 0.7·h, y − 0.7·h) so that box sides are textured too.

    The image is a function of the model's texture settings, the extent and the seed: it is
    built when first sampled (a run without rendered frames never needs it), once per process
    for each such set (read-only, shared by every simulator that asks for the same one; a
    texture takes ~0.5 s and 20 MB)."""

    def __init__(
        self,
        model: CameraModel,
        extent_mm: tuple[float, float, float, float],
        seed: int,
        texel_mm: float = 5.0,
        floor_px_mm: float = 10.0,
    ) -> None:
        self.texel_mm = texel_mm
        self.x0, self.y0 = extent_mm[0], extent_mm[2]
        look = (
            model.texture,
            model.texture_level,
            model.texture_contrast,
            model.texture_detail,
            model.tile_mm,
            model.grout_mm,
            model.grout_gray,
        )
        self._key = (look, tuple(extent_mm), int(seed), texel_mm, floor_px_mm)

    @property
    def image(self) -> NDArray[np.float32]:
        """The texture image (rows: y, columns: x, one texel per ``texel_mm``), gray levels."""
        return _texture_image(*self._key)

    def texel_coordinates(
        self, x_mm: NDArray[np.float64], y_mm: NDArray[np.float64], h_mm: NDArray[np.float64]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Texture image coordinates (col, row) of world points (x, y, h) mm."""
        u = (x_mm + 0.7 * h_mm - self.x0) / self.texel_mm
        v = (y_mm - 0.7 * h_mm - self.y0) / self.texel_mm
        return u.astype(np.float32), v.astype(np.float32)

    def sample_texels(self, u: NDArray[np.float32], v: NDArray[np.float32]) -> NDArray[np.float32]:
        """Gray levels at texture coordinates (bilinear, wrapping at the edges)."""
        out = cv2.remap(self.image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        return np.asarray(out, dtype=np.float32)


@functools.lru_cache(maxsize=3)
def _texture_image(
    look: tuple[str, float, float, float, float, float, float],
    extent_mm: tuple[float, ...],
    seed: int,
    texel_mm: float,
    floor_px_mm: float,
) -> NDArray[np.float32]:
    """The texture image of :class:`SceneTexture` (``look``: the model's texture, level,
    contrast, detail, tile, grout width and grout gray)."""
    texture, level, contrast, detail, tile_mm, grout_mm, grout_gray = look
    x0, x1, y0, y1 = extent_mm
    cols = math.ceil((x1 - x0) / texel_mm) + 2
    rows = math.ceil((y1 - y0) / texel_mm) + 2
    rng = np.random.default_rng(seed)

    def field(cell_mm: float) -> NDArray[np.float32]:
        n = max(2, int(cell_mm / texel_mm))
        coarse = rng.standard_normal((rows // n + 3, cols // n + 3)).astype(np.float32)
        big = cv2.resize(
            coarse, ((cols // n + 3) * n, (rows // n + 3) * n), interpolation=cv2.INTER_CUBIC
        )
        return np.asarray(big[:rows, :cols], dtype=np.float32)

    # in place (20 MB arrays): the same sums as level + contrast·coarse + detail·fine
    img = field(245.0)
    img *= np.float32(contrast)
    img += np.float32(level)
    fine = field(30.0)
    fine *= np.float32(detail)
    img += fine
    if texture == "tiles":
        xs = x0 + texel_mm * np.arange(cols, dtype=np.float64)[None, :]
        ys = y0 + texel_mm * np.arange(rows, dtype=np.float64)[:, None]
        half = tile_mm / 2

        def cover(d: NDArray[np.float64]) -> NDArray[np.float64]:  # area-sampled grout
            return np.clip((grout_mm / 2 - d) / texel_mm + 0.5, 0.0, 1.0)

        gx = cover(np.abs(((xs + half) % tile_mm) - half))
        gy = cover(np.abs(((ys + half) % tile_mm) - half))
        img = img - grout_gray * np.maximum(gx, gy).astype(np.float32)
    # pre-filter to a floor pixel's footprint (the mirror images the floor at a uniform
    # ~10 mm per px): sampling then does not alias
    sigma = 0.4 * floor_px_mm / texel_mm
    image = np.asarray(cv2.GaussianBlur(img, (0, 0), sigma), dtype=np.float32)
    image.flags.writeable = False
    return image


class _CameraRays:
    """The viewing rays of one camera on a coarse grid (slopes X/Z, (Y − Y_i)/Z), and what of
    the image does not change between frames: the mirror disk, its bounding box, and which grid
    nodes the disk's pixels interpolate from (only those rays are cast: the rest of the image
    is the dark housing whatever the pose)."""

    def __init__(self, cam: MirrorCamera, grid_px: int) -> None:
        rows, cols = cam.image_shape
        require(rows % grid_px == 0 and cols % grid_px == 0, "grid_px", "must divide the image")
        self.cam = cam
        self.shape = (rows, cols)
        self.grid_shape = (rows // grid_px, cols // grid_px)
        self.disk = disk_mask(cam)
        #: bands of rows covering the disk, each (rows, cols, the disk in them): only these
        #: are sampled, everything else in the image is housing whatever the pose
        self.bands = _disk_bands(self.disk, _DISK_BANDS)
        self.nodes = np.flatnonzero(_nodes_used(self.disk, grid_px, self.grid_shape).ravel())
        # node j stands for pixel j·step + (step − 1)/2: where cv2.resize puts it
        half = (grid_px - 1) / 2
        gr = np.arange(self.grid_shape[0], dtype=np.float64) * grid_px + half
        gc = np.arange(self.grid_shape[1], dtype=np.float64) * grid_px + half
        rr, cc = np.meshgrid(gr, gc, indexing="ij")
        grid_rc = np.column_stack([rr.ravel(), cc.ravel()])[self.nodes]
        sl = cam.ray_slopes(grid_rc)
        self.sx, self.sy = sl[:, 0], sl[:, 1]
        self._minus_sy = -self.sy
        self._by_sx = np.argsort(self.sx, kind="stable")  # the rays in order of X/Z
        self._sx_sorted = self.sx[self._by_sx]

    def _rays_near(
        self, corners: NDArray[np.float64], depths_mm: tuple[float, float]
    ) -> NDArray[np.intp]:
        """Indices of the rays that may pass through a region: ``corners`` (4, 2) of its
        rectangle relative to the mirror in rig axes (X, Y), mm, between two depths (> 0) —
        those whose slopes lie in the bounding box of the corners' slopes at both depths,
        widened a little (a superset: the slab test decides)."""
        slopes = np.concatenate([corners / depths_mm[0], corners / depths_mm[1]])
        lo, hi = slopes.min(axis=0), slopes.max(axis=0)
        pad = 1e-9 + 1e-6 * (hi - lo)
        lo, hi = lo - pad, hi + pad
        i0, i1 = np.searchsorted(self._sx_sorted, (lo[0], hi[0]))
        near = self._by_sx[i0 : i1 + 1]
        sy = self.sy[near]
        return near[(sy >= lo[1]) & (sy <= hi[1])]

    def on_grid(self, values: NDArray[np.float32]) -> NDArray[np.float32]:
        """The grid (rows, cols) with ``values`` at the cast nodes, 0 at the others."""
        g = np.zeros(self.grid_shape[0] * self.grid_shape[1], dtype=np.float32)
        g[self.nodes] = values
        return g.reshape(self.grid_shape)

    def world_hits(
        self, pose: Pose, mount: RigMount, boxes: NDArray[np.float64], pits: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """World (x, y, h) of the first surface each cast grid ray (``nodes``) meets (floor,
        box, pit)."""
        H = mount.height_mm
        px, py, th = pose
        c, s = math.cos(th), math.sin(th)
        # point at depth Z on the ray: world xy = a + Z·b (rig → robot: x = X + offset, y = −Y)
        ox, oy = mount.x_offset_mm, -self.cam.y_mm
        ax, ay = px + c * ox - s * oy, py + s * ox + c * oy
        bx = c * self.sx - s * self._minus_sy
        by = s * self.sx + c * self._minus_sy
        z = np.full(len(bx), H)
        if len(bx) == 0:
            return ax + z * bx, ay + z * by, H - z
        # a slope of exactly 0 (a ray along a world axis) is rare: without one, the slab tests
        # skip their b = 0 branch
        nonzero = bool(np.all(bx != 0) and np.all(by != 0))
        # the rays' xy extent between depth Z0 and H: a box outside it is met by no ray
        bx_lo, bx_hi, by_lo, by_hi = bx.min(), bx.max(), by.min(), by.max()
        with np.errstate(divide="ignore", invalid="ignore"):
            for x0, x1, y0, y1, hgt in boxes:
                z0 = max(H - hgt, 0.0)
                if (
                    ax + max(z0 * bx_hi, H * bx_hi) < x0
                    or ax + min(z0 * bx_lo, H * bx_lo) > x1
                    or ay + max(z0 * by_hi, H * by_hi) < y0
                    or ay + min(z0 * by_lo, H * by_lo) > y1
                ):
                    continue
                if z0 > 0:  # only the rays whose slopes can reach the box are tested
                    dx = np.array([x0, x0, x1, x1]) - ax
                    dy = np.array([y0, y1, y0, y1]) - ay
                    rig_xy = np.column_stack([c * dx + s * dy, s * dx - c * dy])
                    ray = self._rays_near(rig_xy, (z0, H))
                    if len(ray) == 0:
                        continue
                    bxr, byr, zr = bx[ray], by[ray], z[ray]
                else:
                    ray, bxr, byr, zr = None, bx, by, z
                zin, zout = _slab(ax, bxr, x0, x1, H - hgt, H, nonzero)
                zin2, zout2 = _slab(ay, byr, y0, y1, zin, zout, nonzero)
                hit = (zin2 <= zout2) & (zin2 < zr) & (zin2 >= 0)
                if ray is None:
                    np.copyto(z, zin2, where=hit)
                else:
                    z[ray[hit]] = zin2[hit]
            if len(pits):
                floor = z >= H
                fx, fy = ax + H * bx, ay + H * by
            for x0, x1, y0, y1, depth in pits:
                inside = floor & (fx >= x0) & (fx <= x1) & (fy >= y0) & (fy <= y1)
                if not np.any(inside):
                    continue
                _, zout = _slab(ax, bx, x0, x1, H, H + depth, nonzero)
                _, zout2 = _slab(ay, by, y0, y1, H, zout, nonzero)
                z = np.where(inside, np.clip(zout2, H, H + depth), z)
        return ax + z * bx, ay + z * by, H - z


#: Bands of rows the disk is cut into for sampling (fewer pixels outside it are sampled).
_DISK_BANDS = 12


def _disk_bands(
    disk: NDArray[np.bool_], count: int
) -> tuple[tuple[slice, slice, NDArray[np.bool_]], ...]:
    """``count`` bands of rows covering ``disk``: (rows, the disk's columns in them, the disk
    within that box)."""
    rows = np.flatnonzero(disk.any(axis=1))
    if len(rows) == 0:
        return ()
    edges = np.linspace(rows[0], rows[-1] + 1, min(count, len(rows)) + 1).astype(int)
    out = []
    for top, bottom in itertools.pairwise(edges):
        cols = np.flatnonzero(disk[top:bottom].any(axis=0))
        box = (slice(int(top), int(bottom)), slice(int(cols[0]), int(cols[-1]) + 1))
        out.append((*box, np.ascontiguousarray(disk[box])))
    return tuple(out)


@functools.lru_cache(maxsize=8)
def _camera_rays(cam: MirrorCamera, grid_px: int) -> _CameraRays:
    """The rays of ``cam`` on the grid (read-only after construction: built once per camera)."""
    return _CameraRays(cam, grid_px)


def _nodes_used(disk: NDArray[np.bool_], grid_px: int, grid_shape: tuple[int, int]) -> NDArray:
    """(grid rows, grid cols) bool: the grid nodes whose values a pixel of ``disk`` takes when
    the grid is resized to the image (cv2.resize, bilinear: each pixel blends the 2 x 2 nodes
    around it, the one at or before it and the next), widened by two nodes on every side: the
    image's pixels in the disk are then exactly those of a fully cast grid."""

    def around(n_px: int, n_grid: int) -> NDArray[np.int64]:
        src = np.floor((np.arange(n_px) + 0.5) / grid_px - 0.5).astype(np.int64)
        return np.clip(src, 0, n_grid - 1)

    used = np.zeros(grid_shape, dtype=bool)
    rows, cols = np.nonzero(disk)
    r0 = around(disk.shape[0], grid_shape[0])[rows]
    c0 = around(disk.shape[1], grid_shape[1])[cols]
    used[r0, c0] = True
    widened = used.copy()
    for dr in range(-2, 3):
        for dc in range(-2, 3):
            sr = slice(max(dr, 0), grid_shape[0] + min(dr, 0))
            tr = slice(max(-dr, 0), grid_shape[0] + min(-dr, 0))
            sc = slice(max(dc, 0), grid_shape[1] + min(dc, 0))
            tc = slice(max(-dc, 0), grid_shape[1] + min(-dc, 0))
            widened[tr, tc] |= used[sr, sc]
    return widened


def _slab(
    a: float,
    b: NDArray[np.float64],
    lo: float,
    hi: float,
    zin: NDArray[np.float64] | float,
    zout: NDArray[np.float64] | float,
    nonzero: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Narrow the depth interval [zin, zout] of rays a + Z·b to where lo ≤ a + Z·b ≤ hi
    (``nonzero``: no slope in ``b`` is 0)."""
    t0 = (lo - a) / b
    t1 = (hi - a) / b
    if nonzero:
        return np.maximum(zin, np.minimum(t0, t1)), np.minimum(zout, np.maximum(t0, t1))
    near = np.where(b != 0, np.minimum(t0, t1), np.where((a >= lo) & (a <= hi), -np.inf, np.inf))
    far = np.where(b != 0, np.maximum(t0, t1), np.where((a >= lo) & (a <= hi), np.inf, -np.inf))
    return np.maximum(zin, near), np.minimum(zout, far)


class SimCamera:
    """The stereo cameras of a simulated rig: which frames exist when, and what they show."""

    def __init__(
        self,
        model: CameraModel,
        rig: StereoRig,
        mount: RigMount,
        world: World,
        extent_mm: tuple[float, float, float, float],
        seed: int = 0,
        render_options: RenderOptions | None = None,
    ) -> None:
        self.model = model
        self.rig = rig
        self.mount = mount
        self._rng = np.random.default_rng(seed + 104729)
        phase = model.phase_s
        self.phase_s = float(self._rng.uniform(0, model.period_s)) if phase is None else phase
        self.options = render_options or RenderOptions()
        self.texture = SceneTexture(model, extent_mm, seed + 15485863)
        self._rays = (_camera_rays(rig.cam1, model.grid_px), _camera_rays(rig.cam2, model.grid_px))
        self._geometry: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
        self.world_version = 0
        self.set_world(world)
        self._fixed_scene: list[NDArray[np.float32] | None] = [None, None]
        self._next_index = 0
        self.frames = 0
        self.dropped = 0

    def set_world(self, world: World) -> int:
        """The world changed (a hazard appeared): frames exposed from now on show the new one
        (a frame keeps the version it was exposed in). Returns the new version."""
        boxes = np.array(
            [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm, b.height_mm) for b in world.boxes],
            dtype=np.float64,
        ).reshape(-1, 5)
        pits = np.array(
            [(d.x_min_mm, d.x_max_mm, d.y_min_mm, d.y_max_mm, d.depth_mm) for d in world.dropoffs],
            dtype=np.float64,
        ).reshape(-1, 5)
        self.world_version = len(self._geometry)
        self._geometry.append((boxes, pits))
        self._boxes, self._pits = boxes, pits
        return self.world_version

    def exposure_mid_s(self, index: int) -> float:
        return self.phase_s + index * self.model.period_s

    def delivered_until(
        self,
        now_s: float,
        pose_at: Callable[[float], Pose],
        lit_share: Callable[[float, float], float],
    ) -> list[SimFrame]:
        """The frame pairs delivered up to ``now_s`` (each once, dropped ones left out)."""
        m = self.model
        out: list[SimFrame] = []
        while self.exposure_mid_s(self._next_index) + m.readout_s <= now_s + 1e-9:
            k = self._next_index
            self._next_index += 1
            t = self.exposure_mid_s(k)
            seed = int(self._rng.integers(1 << 31))
            if m.drop_rate > 0 and self._rng.uniform() < m.drop_rate:
                self.dropped += 1
                continue
            lit = lit_share(t - m.exposure_s / 2, t + m.exposure_s / 2)
            out.append(SimFrame(k, t, pose_at(t), lit, seed, self.world_version))
            self.frames += 1
        return out

    def skip_until(self, now_s: float) -> None:
        """Frames before ``now_s`` were not needed: the clock moves on without delivering them."""
        while self.exposure_mid_s(self._next_index) + self.model.readout_s <= now_s + 1e-9:
            self._next_index += 1

    def scene(self, cam_index: int, pose: Pose, world: int | None = None) -> NDArray[np.float32]:
        """The gray scene camera ``cam_index`` (0, 1) sees at ``pose`` in world version
        ``world`` (default: the latest), without laser or noise (``textured: camera``: the same
        whatever the pose)."""
        if self.model.textured == "camera":
            fixed = self._fixed_scene[cam_index]
            if fixed is None:
                fixed = self._world_scene(cam_index, (0.0, 0.0, 0.0), "floor", 0)
                self._fixed_scene[cam_index] = fixed
            return fixed.copy()
        version = self.world_version if world is None else world
        return self._world_scene(cam_index, pose, self.model.textured, version)

    def _world_scene(
        self, cam_index: int, pose: Pose, textured: str, world: int
    ) -> NDArray[np.float32]:
        rays = self._rays[cam_index]
        boxes, pits = self._geometry[world]
        x, y, h = rays.world_hits(pose, self.mount, boxes, pits)
        rows, cols = rays.shape
        u, v = self.texture.texel_coordinates(x, y, h)

        def full(a: NDArray[np.float32]) -> NDArray[np.float32]:  # grid → every pixel, bilinear
            out = cv2.resize(rays.on_grid(a), (cols, rows), interpolation=cv2.INTER_LINEAR)
            return np.asarray(out, dtype=np.float32)

        map_u, map_v = full(u), full(v)
        on_box = full((h > 1.0).astype(np.float32)) if textured == "floor" else None
        out = np.full((rows, cols), OUTSIDE_DISK_LEVEL, dtype=np.float32)
        for band in rays.bands:  # only the disk is sampled: the rest is housing
            box = band[:2]
            gray = self.texture.sample_texels(map_u[box], map_v[box])
            if on_box is not None:  # above the floor: a box, uniform gray
                gray = np.where(on_box[box] > 0.5, np.float32(self.model.texture_level), gray)
            np.copyto(out[box], gray, where=band[2])
        return out

    def render(self, frame: SimFrame, hits: LaserHits) -> tuple[Image, Image]:
        """The two images of ``frame``: the world scene at its pose, the laser dots each mirror
        sees (:func:`omnid.sim.render.laser_image`: the spot model; :func:`~omnid.sim.render.hits_flux`:
        the beams' power and, with ``spots.shading``, the surfaces' shading) scaled by the frame's lit share, and sensor noise (read noise plus
        shot noise, ``RenderOptions.noise_sigma`` / ``shot_noise_gain``), rounded and clipped."""
        rng = np.random.default_rng(frame.seed)
        opts = self.options
        out: list[Image] = []
        flux_all = hits_flux(hits, self.rig, opts.spots) * frame.lit  # (N, 2)
        for i, (cam, vis) in enumerate(
            ((self.rig.cam1, hits.visible1), (self.rig.cam2, hits.visible2))
        ):
            signal = self.scene(i, frame.pose, frame.world)
            if frame.lit > 0 and np.any(vis):
                xyz = hits.xyz[vis]
                signal += laser_image(cam, cam.project(xyz), opts.spots, rng, flux_all[vis, i])
            out.append(sensor_image(signal, opts, rng))
        return out[0], out[1]
