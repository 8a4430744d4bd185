"""The simulated world: boxes and drop-offs on a floor, and the laser dots they catch.

World frame: x, y on the floor (y **left**), heights ``h`` up from the floor, mm. A chair pose is
``(x_mm, y_mm, theta_rad)`` of the robot frame (wheel-axle midpoint, x forward, θ CCW) in the
world. The vision rig sits ``RigMount.x_offset_mm`` ahead of the axle midpoint with its mirrors
``RigMount.height_mm`` above the floor; its frame is the one of SPEC §2 (X forward, Y right along
the baseline, Z down from the mirror plane), so a rig point (X, Y, Z) is the robot-frame point
(X + x_offset, −Y) at height h = H − Z (the inverse of ``occupancy.rig_to_robot``).

:func:`cast_laser` follows each beam of a :class:`~omnid.sim.laser.LaserProjector` from the laser's
source (near the baseline's midpoint, but not in the mirror plane: SPEC §2) to the first surface it
meets —
the floor, the lowered floor of a :class:`DropOff` (or the pit's far wall), a box top or a box side
— and then asks, for each mirror, whether the dot is inside that mirror's disk and whether the line
from the dot to the mirror is blocked by a box or by the ground at a drop-off edge. Everything is
vectorised over rays (slab tests against all boxes at once).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.config import require
from omnid.core.geometry import StereoRig
from omnid.core.triangulate import TriangulationMethod
from omnid.core.types import PointClass, PointCloud
from omnid.sim.laser import LaserProjector, LaserRays

#: Boxes reach this far below the floor so that a box standing in a pit rests on its bottom
#: (the floor itself stops every ray and sight line long before it matters elsewhere), mm.
_BOX_FOOT_MM = 1.0e4
#: Segment overlaps shorter than this fraction of the segment are grazing contacts, not blocks.
_GRAZE = 1.0e-6


def _finite(*pairs: tuple[str, float]) -> None:
    for key, value in pairs:
        require(math.isfinite(value), key, "must be a finite number")


def _check_region(region: Any, extent: str) -> None:
    """An axis-aligned region's bounds are finite and ordered, and its ``extent`` (height or
    depth, mm) is positive."""
    names = ("x_min_mm", "x_max_mm", "y_min_mm", "y_max_mm", extent)
    _finite(*((n, getattr(region, n)) for n in names))
    require(region.x_max_mm > region.x_min_mm, "x_max_mm", "must exceed x_min_mm")
    require(region.y_max_mm > region.y_min_mm, "y_max_mm", "must exceed y_min_mm")
    require(getattr(region, extent) > 0, extent, "must be positive")


@dataclass(frozen=True)
class Box:
    """An obstacle (or a wall: a tall thin box) standing on the floor, axis-aligned, mm."""

    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    height_mm: float

    def __post_init__(self) -> None:
        _check_region(self, "height_mm")


@dataclass(frozen=True)
class DropOff:
    """A region where the floor lies ``depth_mm`` lower (stairs down, a kerb, a ramp edge), mm."""

    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    depth_mm: float

    def __post_init__(self) -> None:
        _check_region(self, "depth_mm")


@dataclass(frozen=True)
class World:
    """A static world: boxes on the floor and drop-off regions (not overlapping each other)."""

    boxes: tuple[Box, ...] = ()
    dropoffs: tuple[DropOff, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "boxes", tuple(self.boxes))
        object.__setattr__(self, "dropoffs", tuple(self.dropoffs))

    def floor_height_mm(self, xy_mm: ArrayLike) -> NDArray[np.float64]:
        """Height of the floor surface under world points (N, 2): 0, or −depth in a drop-off."""
        q = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        h = np.zeros(len(q))
        for d in self.dropoffs:
            inside = (q[:, 0] >= d.x_min_mm) & (q[:, 0] <= d.x_max_mm)
            inside &= (q[:, 1] >= d.y_min_mm) & (q[:, 1] <= d.y_max_mm)
            h[inside] = -d.depth_mm
        return h

    def _box_array(self) -> NDArray[np.float64]:
        """Boxes as (B, 2, 3) lower/upper corners (x, y, h), mm."""
        if not self.boxes:
            return np.zeros((0, 2, 3))
        return np.array(
            [
                [[b.x_min_mm, b.y_min_mm, -_BOX_FOOT_MM], [b.x_max_mm, b.y_max_mm, b.height_mm]]
                for b in self.boxes
            ],
            dtype=np.float64,
        )

    def _pit_array(self) -> NDArray[np.float64]:
        """Drop-offs as (P, 2, 3) lower/upper corners (x, y, h) of the empty pit volume, mm."""
        if not self.dropoffs:
            return np.zeros((0, 2, 3))
        return np.array(
            [
                [[d.x_min_mm, d.y_min_mm, -d.depth_mm], [d.x_max_mm, d.y_max_mm, 0.0]]
                for d in self.dropoffs
            ],
            dtype=np.float64,
        )


@dataclass(frozen=True)
class RigMount:
    """Where the vision rig sits on the chair: ``x_offset_mm`` ahead of the axle midpoint,
    mirrors ``height_mm`` above the floor (= the floor depth H of SPEC §2)."""

    x_offset_mm: float = 300.0
    height_mm: float = 1100.0

    def __post_init__(self) -> None:
        _finite(("x_offset_mm", self.x_offset_mm), ("height_mm", self.height_mm))
        require(self.height_mm > 0, "height_mm", "must be positive")


@dataclass(frozen=True)
class LaserHits:
    """Where the laser dots fall, one row per beam of the laser (in its beam order).

    xyz         (N, 3) dot positions in the rig frame (SPEC §2), mm
    visible1    (N,) inside mirror 1's disk and not occluded between the dot and mirror 1
    visible2    (N,) likewise for mirror 2
    truth       (N,) :class:`PointClass` codes (uint8): floor, obstacle (a box), drop-off (lowered
                floor or a pit wall)
    pixels      (N, 4) ideal image positions r1, c1, r2, c2 of the dots, px (NaN where none)
    brightness  (N,) relative power of each beam (the grating's order envelope), 1 on its axis
    normal      (N, 3) unit normal of the surface each dot lies on, rig frame, pointing to the
                side the beam came from (up, (0, 0, −1), on the floor and box tops)
    """

    xyz: NDArray[np.float64]
    visible1: NDArray[np.bool_]
    visible2: NDArray[np.bool_]
    truth: NDArray[np.uint8]
    pixels: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))
    brightness: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    normal: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self) -> None:
        n = len(self.xyz)
        if len(self.brightness) != n:
            object.__setattr__(self, "brightness", np.ones(n))
        if len(self.normal) != n:
            object.__setattr__(self, "normal", np.tile([0.0, 0.0, -1.0], (n, 1)))

    @property
    def visible(self) -> NDArray[np.bool_]:
        """(N,) seen by both mirrors — the dots a stereo pair can triangulate."""
        return self.visible1 & self.visible2

    def __len__(self) -> int:
        return len(self.xyz)


def _pose(pose: ArrayLike) -> tuple[float, float, float]:
    p = np.asarray(pose, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"pose must be finite (x_mm, y_mm, theta_rad), got {pose!r}")
    return float(p[0]), float(p[1]), float(p[2])


def rig_to_world(xyz_rig_mm: ArrayLike, pose: ArrayLike, mount: RigMount) -> NDArray[np.float64]:
    """Rig-frame points (N, 3) mm → world (x, y, h) mm for the chair at ``pose``."""
    px, py, th = _pose(pose)
    p = np.asarray(xyz_rig_mm, dtype=np.float64).reshape(-1, 3)
    xr = p[:, 0] + mount.x_offset_mm
    yr = -p[:, 1]
    c, s = math.cos(th), math.sin(th)
    return np.column_stack([px + c * xr - s * yr, py + s * xr + c * yr, mount.height_mm - p[:, 2]])


def world_to_rig(xyh_world_mm: ArrayLike, pose: ArrayLike, mount: RigMount) -> NDArray[np.float64]:
    """World (x, y, h) points (N, 3) mm → rig-frame (X, Y, Z) mm for the chair at ``pose``."""
    px, py, th = _pose(pose)
    q = np.asarray(xyh_world_mm, dtype=np.float64).reshape(-1, 3)
    c, s = math.cos(th), math.sin(th)
    dx, dy = q[:, 0] - px, q[:, 1] - py
    xr = c * dx + s * dy
    yr = -s * dx + c * dy
    return np.column_stack([xr - mount.x_offset_mm, -yr, mount.height_mm - q[:, 2]])


def _directions_to_world(d_rig: NDArray[np.float64], theta_rad: float) -> NDArray[np.float64]:
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    dx, dy = d_rig[:, 0], -d_rig[:, 1]
    return np.column_stack([c * dx - s * dy, s * dx + c * dy, -d_rig[:, 2]])


def _slab(
    origin: NDArray[np.float64], direction: NDArray[np.float64], boxes: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Slab test of N rays against B axis-aligned boxes.

    Returns (t_near, t_far) (B, N) of the ray parameter where each ray enters and leaves each box
    (t_near > t_far: missed). Box-major and axis by axis, so every array is contiguous along the
    rays: numpy reduces a short last axis slowly, and this runs for every ray of every capture.
    """
    t_near = np.full((len(boxes), len(origin)), -np.inf)
    t_far = np.full((len(boxes), len(origin)), np.inf)
    for axis in range(3):
        d = direction[:, axis]
        inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
        o = origin[:, axis]
        lo = (boxes[:, 0, axis, None] - o) * inv
        hi = (boxes[:, 1, axis, None] - o) * inv
        np.maximum(t_near, np.minimum(lo, hi), out=t_near)
        np.minimum(t_far, np.maximum(lo, hi), out=t_far)
    return t_near, t_far


def _blocked(
    start: NDArray[np.float64], end: NDArray[np.float64], boxes: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """(N,) True where the segment start→end passes through the inside of any box."""
    if len(boxes) == 0 or len(start) == 0:
        return np.zeros(len(start), dtype=bool)
    tn, tf = _slab(start, end - start, boxes)
    lo = np.maximum(tn, 0.0)
    hi = np.minimum(tf, 1.0)
    return np.any(hi - lo > _GRAZE, axis=0)


Laser = LaserProjector | LaserRays


def laser_rays(laser: Laser) -> LaserRays:
    """The beams of a laser description: a projector or its rays."""
    return laser if isinstance(laser, LaserRays) else laser.rays()


def cast_laser(
    world: World,
    pose: ArrayLike,
    mount: RigMount,
    laser: Laser,
    rig: StereoRig,
) -> LaserHits:
    """Cast every beam of ``laser`` into ``world`` with the chair at ``pose``.

    Each beam starts at the laser's source and stops at the first of: the floor (h = 0), the
    lowered floor or the far wall of a drop-off pit, a box top or a box side. A dot is visible in
    mirror i (at rig (0, Y_i, 0)) when its image lies inside that mirror's disk and the segment
    from the dot to the mirror passes through no box and does not go below the floor (a drop-off's
    near edge hides the pit bottom right behind it).
    """
    px, py, th = _pose(pose)
    rays = laser_rays(laser)
    d_rig = rays.directions
    n = len(d_rig)
    origin_w = rig_to_world(rays.origin_mm[None, :], (px, py, th), mount)[0]
    if not origin_w[2] > 0:
        raise ValueError("cast_laser: the laser's source must be above the floor")
    o = np.broadcast_to(origin_w, (n, 3)).copy()
    d = _directions_to_world(d_rig, th)

    # Floor at h = 0 (every ray points down, so every ray meets it).
    t_floor = origin_w[2] / -d[:, 2]  # d[:, 2] < 0 (h decreases along the ray)
    t = t_floor.copy()
    truth = np.full(n, PointClass.FLOOR, dtype=np.uint8)

    # Drop-off pits: a ray entering the pit volume through its open top leaves it at its far
    # side — the bottom or a wall — and that is where the dot is.
    pits = world._pit_array()
    if len(pits):
        tn, tf = _slab(o, d, pits)
        enters = (tn <= tf) & (np.abs(tn - t_floor) <= 1e-6 * origin_w[2])  # (P, N)
        if np.any(enters):
            k = np.argmax(enters, axis=0)
            hit = enters.any(axis=0)
            t = np.where(hit, tf[k, np.arange(n)], t)
            truth[hit] = PointClass.DROPOFF

    # Boxes: the first entry in front of the ray and before the floor hit wins.
    boxes = world._box_array()
    if len(boxes):
        tn, tf = _slab(o, d, boxes)
        valid = (tn <= tf) & (tn > 0)  # (B, N)
        tn = np.where(valid, tn, np.inf)
        tb = tn.min(axis=0)
        first = tb < t
        t = np.where(first, tb, t)
        truth[first] = PointClass.OBSTACLE

    hit_w = o + t[:, None] * d
    xyz = world_to_rig(hit_w, (px, py, th), mount)
    normal_w = _face_normals(hit_w, d, truth, boxes, pits)
    normal = _directions_to_rig(normal_w, th)
    pixels = rig.project(xyz)

    mirrors_rig = [np.array([[0.0, rig.cam1.y_mm, 0.0]]), np.array([[0.0, rig.cam2.y_mm, 0.0]])]
    vis = []
    for cam, m_rig, rc in zip(
        (rig.cam1, rig.cam2), mirrors_rig, (pixels[:, :2], pixels[:, 2:]), strict=True
    ):
        m_w = rig_to_world(m_rig, (px, py, th), mount)[0]
        end = np.broadcast_to(m_w, (n, 3))
        seen = cam.in_disk(rc)
        seen &= ~_blocked(hit_w, end, boxes)
        seen &= ~_under_ground(hit_w, end, pits)
        vis.append(seen)
    return LaserHits(
        xyz, vis[0], vis[1], truth, pixels, np.asarray(rays.brightness, np.float64), normal
    )


def _face_normals(
    hit_w: NDArray[np.float64],
    d: NDArray[np.float64],
    truth: NDArray[np.uint8],
    boxes: NDArray[np.float64],
    pits: NDArray[np.float64],
) -> NDArray[np.float64]:
    """World-frame unit normals (N, 3) of the faces the rays ``d`` stopped on at ``hit_w``.

    Every face is axis-aligned; the face is the box (or pit) face nearest the hit point, and
    its normal points against the ray (out of a box, into a pit's open volume).
    """
    normal = np.zeros((len(hit_w), 3))
    normal[:, 2] = 1.0  # the floor and every horizontal face the rays come down on
    for code, solids in ((PointClass.OBSTACLE, boxes), (PointClass.DROPOFF, pits)):
        idx = np.flatnonzero(truth == code)
        if len(idx) == 0 or len(solids) == 0:
            continue
        q = hit_w[idx]
        # Distance of each hit to each face of each solid (S, n, 6); the nearest face wins.
        gaps = np.concatenate(
            [np.abs(q[None] - solids[:, None, 0]), np.abs(q[None] - solids[:, None, 1])], axis=2
        )
        inside = np.all(
            (q[None] >= solids[:, None, 0] - 1e-6) & (q[None] <= solids[:, None, 1] + 1e-6),
            axis=2,
        )
        gaps = np.where(inside[:, :, None], gaps, np.inf).reshape(len(solids), len(idx), 6)
        flat = gaps.transpose(1, 0, 2).reshape(len(idx), -1).argmin(axis=1)
        axis = flat % 6 % 3
        n_face = np.zeros((len(idx), 3))
        n_face[np.arange(len(idx)), axis] = -np.sign(d[idx, axis])
        normal[idx] = n_face
    return normal


def _directions_to_rig(d_world: NDArray[np.float64], theta_rad: float) -> NDArray[np.float64]:
    """World-frame directions (x, y, h) → rig frame (X, Y, Z) for a chair heading
    ``theta_rad`` (the inverse of :func:`_directions_to_world`)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    dx, dy = d_world[:, 0], d_world[:, 1]
    return np.column_stack([c * dx + s * dy, -(-s * dx + c * dy), -d_world[:, 2]])


def _under_ground(
    start: NDArray[np.float64], end: NDArray[np.float64], pits: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """(N,) True where a sight line from a dot below floor level leaves its pit through a wall
    (i.e. it would have to pass through the ground at the drop-off edge)."""
    below = start[:, 2] < -1e-9
    if len(pits) == 0 or not np.any(below):
        return np.zeros(len(start), dtype=bool)
    direction = end - start
    tn, tf = _slab(start, direction, pits)
    # Exit point of the pit volume; it is through the open top only if its height is ~0.
    inside = (tn <= tf + 1e-9) & (tf >= 0)
    tf_any = np.where(inside, tf, np.inf).min(axis=0)
    exit_h = start[:, 2] + np.where(np.isfinite(tf_any), tf_any, 0.0) * direction[:, 2]
    return below & np.isfinite(tf_any) & (exit_h < -1e-6)


def as_world(boxes: Sequence[Box] = (), dropoffs: Sequence[DropOff] = ()) -> World:
    """A :class:`World` from any sequences of boxes and drop-offs."""
    return World(tuple(boxes), tuple(dropoffs))


def observe(
    hits: LaserHits,
    rig: StereoRig,
    pixel_sigma_px: float = 0.2,
    rng: np.random.Generator | int = 0,
    floor_depth_mm: float | None = None,
    method: TriangulationMethod = "best",
) -> tuple[PointCloud, NDArray[np.uint8]]:
    """A noisy measured cloud of the dots both mirrors see, and their truth classes.

    A stand-in for render → detect → match when only the geometry matters (tests of
    classification and mapping, the fast simulator path): project each visible dot, add Gaussian
    pixel noise of ``pixel_sigma_px`` to r1, c1, r2, c2, and triangulate with
    :func:`omnid.core.triangulate.triangulate` (``method``), which also gives each point's
    covariance. ``classes`` of the returned cloud are all FLOOR — classification is the caller's.
    """
    from omnid.core.triangulate import triangulate

    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    keep = hits.visible
    truth = hits.truth[keep]
    pix = rig.project(hits.xyz[keep])
    pix = pix + gen.normal(0.0, pixel_sigma_px, pix.shape)
    xyz, cov = triangulate(rig, pix, method=method, pixel_sigma_px=pixel_sigma_px)
    H = rig.floor_depth_mm if floor_depth_mm is None else floor_depth_mm
    cloud = PointCloud(
        np.asarray(xyz, dtype=np.float64),
        np.asarray(cov, dtype=np.float64),
        pix,
        np.zeros(len(pix), dtype=np.uint8),
        float(H),
    )
    return cloud, truth
