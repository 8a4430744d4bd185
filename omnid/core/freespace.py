"""The free-space map: where the chair may drive, remembered as it moves (thesis 7.1.2, 7.2.2).

The thesis takes the floor-level dots as the free area and the rest as obstacles, one capture at
a time. omnid keeps a local map instead (SPEC §3), so an obstacle the chair has turned away from
— out of the laser's forward field — still blocks it:

- ``update`` rasterises one classified cloud. Free area is not just the cells under floor dots:
  the dots are joined by a Delaunay triangulation (``cv2.Subdiv2D``), and every triangle whose
  three corners are floor dots, with no edge longer than ``free_max_edge_mm``, is floor the laser
  has swept — FREE. A triangle with a drop-off corner (and no obstacle corner) spans the place
  where the floor goes missing: dots beyond an edge fall lower and land farther, so between the
  last floor dot and the first lowered one lies floor that was never seen — it is marked DROPOFF,
  never free. Stronger still, a lowered dot's laser ray crossed floor level somewhere nearer
  without meeting floor: the cells along the ray from that crossing to the dot are DROPOFF,
  however deep the drop (7.2.2 extended to missing floor). Obstacle dots, and triangles of
  neighbouring obstacle dots (a box top), mark OBSTACLE (dots optionally inflated). Cells this
  cloud does not cover keep what they had.
- ``move`` applies the robot's motion. The map is stored in an *anchor* frame (the robot frame
  at some earlier pose) together with the current robot pose in it; a move only updates that
  pose, and the grid is resampled (``cv2.warpAffine``, nearest neighbour) only when the chair has
  travelled ``reanchor_distance_mm`` from the anchor. Resampling at every small step would round
  each step away — a chair creeping at 10 mm per cycle over 50 mm cells would never see its map
  move. Queries transform their points exactly into the anchor frame.
- ``grid`` is the map as an :class:`OccupancyGrid` in the current robot frame (x forward, y left,
  origin at the axle midpoint), rebuilt on demand.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.config import require
from omnid.core.occupancy import CellState, GridSettings, OccupancyGrid, rig_to_robot
from omnid.core.types import PointClass, PointCloud

_UNSEEN = 255  # observation layer: this update says nothing about the cell


@dataclass(frozen=True)
class FreeSpaceSettings:
    """How clouds become map cells (mm, s).

    grid                   the robot-frame grid (extent, resolution)
    free_max_edge_mm       longest triangle edge between floor dots still filled as free
    dropoff_max_edge_mm    longest edge of a triangle with a drop-off corner filled as DROPOFF
    obstacle_max_edge_mm   longest edge of a triangle of obstacle dots filled as OBSTACLE
                           (a box top between its dots; gaps this narrow are impassable anyway)
    obstacle_inflation_mm  obstacle and drop-off dots also block cells this far around them
    clear_after_contradictions  a remembered OBSTACLE/DROPOFF cell that only the filling between
                           floor dots calls free (no dot in the cell) is cleared after this many
                           captures in a row say so; a floor dot in the cell clears it at once
    forget_after_s         remembered cells not seen again for this long become UNKNOWN
                           (0: never forget); needs ``now_s`` in :meth:`FreeSpaceMap.update`
    reanchor_distance_mm   travel from the anchor pose before the stored grid is resampled
    """

    grid: GridSettings = field(default_factory=GridSettings)
    free_max_edge_mm: float = 250.0
    dropoff_max_edge_mm: float = 600.0
    obstacle_max_edge_mm: float = 200.0
    obstacle_inflation_mm: float = 0.0
    forget_after_s: float = 0.0
    clear_after_contradictions: int = 3
    reanchor_distance_mm: float = 1000.0

    def __post_init__(self) -> None:
        for key in (
            "free_max_edge_mm",
            "dropoff_max_edge_mm",
            "obstacle_max_edge_mm",
            "obstacle_inflation_mm",
            "forget_after_s",
            "reanchor_distance_mm",
        ):
            value = getattr(self, key)
            require(math.isfinite(value) and value >= 0, key, "must be a finite number ≥ 0")
        require(self.free_max_edge_mm > 0, "free_max_edge_mm", "must be positive")
        require(self.clear_after_contradictions >= 1, "clear_after_contradictions", "must be ≥ 1")


def _affine(
    pose: tuple[float, float, float],
    dst: GridSettings,
    src: GridSettings,
) -> NDArray[np.float64]:
    """2x3 matrix mapping a dst-grid pixel (col j, row i) to the src-grid pixel it lies on, where
    the dst frame sits at ``pose`` (x, y, θ) in the src frame (for WARP_INVERSE_MAP)."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    r = dst.resolution_mm
    P = np.array(
        [[0.0, r, dst.x_min_mm + 0.5 * r], [r, 0.0, dst.y_min_mm + 0.5 * r], [0.0, 0.0, 1.0]]
    )
    T = np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])
    q = 1.0 / src.resolution_mm
    Q = np.array(
        [
            [0.0, q, -src.y_min_mm * q - 0.5],
            [q, 0.0, -src.x_min_mm * q - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    return (Q @ T @ P)[:2]


def _to_frame(pose: tuple[float, float, float], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Points (N, 2) in a frame at ``pose`` → the parent frame."""
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    return np.column_stack([x + c * xy[:, 0] - s * xy[:, 1], y + s * xy[:, 0] + c * xy[:, 1]])


class FreeSpaceMap:
    """A remembered FREE / OBSTACLE / DROPOFF / UNKNOWN map around the chair (robot frame)."""

    def __init__(self, settings: FreeSpaceSettings | None = None) -> None:
        self.settings = settings or FreeSpaceSettings()
        g = self.settings.grid
        # The anchor grid is a square around the anchor pose, large enough that the robot grid
        # stays inside it however the chair turns and until it travels reanchor_distance_mm.
        half = max(abs(g.x_min_mm), abs(g.x_max_mm), abs(g.y_min_mm), abs(g.y_max_mm))
        half += self.settings.reanchor_distance_mm + g.resolution_mm
        self._anchor_settings = GridSettings(g.resolution_mm, -half, half, -half, half)
        self._anchor = OccupancyGrid(self._anchor_settings)
        self._seen_s = np.full(self._anchor.states.shape, -np.inf)
        self._contradictions: NDArray[np.uint8] = np.zeros(self._anchor.states.shape, np.uint8)
        self._pose: tuple[float, float, float] = (0.0, 0.0, 0.0)  # robot in the anchor frame
        self._now_s = 0.0
        self._grid: OccupancyGrid | None = None

    # -- motion -------------------------------------------------------------------------------

    @property
    def pose_in_anchor(self) -> tuple[float, float, float]:
        """The current robot pose (x_mm, y_mm, θ_rad) in the anchor frame."""
        return self._pose

    def move(self, dx_mm: float, dy_mm: float, dtheta_rad: float) -> None:
        """The robot moved by (dx, dy) mm in its old frame and turned by ``dtheta_rad`` (CCW);
        remembered cells stay where they are in the world."""
        if not all(math.isfinite(v) for v in (dx_mm, dy_mm, dtheta_rad)):
            raise ValueError(f"FreeSpaceMap.move: non-finite motion {(dx_mm, dy_mm, dtheta_rad)}")
        x, y, th = self._pose
        c, s = math.cos(th), math.sin(th)
        th_new = math.remainder(th + dtheta_rad, 2.0 * math.pi)
        self._pose = (x + c * dx_mm - s * dy_mm, y + s * dx_mm + c * dy_mm, th_new)
        self._grid = None
        if math.hypot(self._pose[0], self._pose[1]) > self.settings.reanchor_distance_mm:
            self._reanchor()

    def _reanchor(self) -> None:
        """Resample the stored grid into a new anchor frame at the current robot pose."""
        import cv2

        a = self._anchor_settings
        M = _affine(self._pose, a, a)
        nx, ny = self._anchor.states.shape
        flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
        self._anchor.states = (
            cv2.warpAffine(
                self._anchor.states.view(np.uint8),
                M,
                (ny, nx),
                flags=flags,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=int(CellState.UNKNOWN),
            )
            .view(np.int8)
            .copy()
        )
        self._seen_s = cv2.warpAffine(
            self._seen_s,
            M,
            (ny, nx),
            flags=flags,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=-1e300,
        )
        self._contradictions = np.asarray(
            cv2.warpAffine(
                self._contradictions,
                M,
                (ny, nx),
                flags=flags,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0,
            ),
            dtype=np.uint8,
        )
        self._pose = (0.0, 0.0, 0.0)

    # -- observations -------------------------------------------------------------------------

    def update(
        self, cloud: PointCloud, rig_x_offset_mm: float = 0.0, now_s: float | None = None
    ) -> None:
        """Enter one classified cloud (rig frame, SPEC §2) seen from the current pose.

        ``rig_x_offset_mm`` is how far the rig origin sits ahead of the axle midpoint; ``now_s``
        (monotonic, s) stamps the cells this cloud covers, for ``forget_after_s``.
        """
        import cv2

        if now_s is not None:
            self._now_s = float(now_s)
        self._grid = None
        st = self.settings
        if len(cloud):
            xy = _to_frame(self._pose, rig_to_robot(cloud.xyz, rig_x_offset_mm))
            ok = np.all(np.isfinite(xy), axis=1)
            xy, cls = xy[ok], cloud.classes[ok]
            # A ray that ended below the floor passed floor level at P·H/Z without meeting any
            # floor there: the floor is missing all along its path from that crossing to the dot.
            xyz = cloud.xyz[ok]
            H = cloud.floor_depth_mm
            low = (cls == PointClass.DROPOFF) & (xyz[:, 2] > H)
            crossing = xyz[low] * (H / xyz[low, 2])[:, None]
            xy0 = _to_frame(self._pose, rig_to_robot(crossing, rig_x_offset_mm))
            segments = np.stack([xy0, xy[low]], axis=1)
            # The crossings also join the triangulation as drop-off corners, so the strip between
            # the last floor dots and the first crossings reads DROPOFF too.
            xy = np.vstack([xy, xy0])
            cls = np.concatenate([cls, np.full(len(xy0), PointClass.DROPOFF, np.uint8)])
            obs, direct_free = self._observation(xy, cls, cv2, segments)
            seen = obs != _UNSEEN
            # Free area filled in between floor dots is an interpolation: it must not erase a
            # remembered obstacle or drop-off (a thin post can fall between the dots of one
            # capture). Only a floor dot landing in the cell itself clears it.
            held = (self._anchor.states == CellState.OBSTACLE) | (
                self._anchor.states == CellState.DROPOFF
            )
            # It does clear it once ``clear_after_contradictions`` captures in a row have filled
            # it as free, so a phantom or removed obstacle between dot columns cannot stay forever.
            contradicted = held & (obs == CellState.FREE) & ~direct_free
            self._contradictions[contradicted] += 1
            self._contradictions[~contradicted] = 0
            keep = contradicted & (self._contradictions < st.clear_after_contradictions)
            seen &= ~keep
            self._anchor.states[seen] = obs[seen].astype(np.int8)
            self._seen_s[seen] = self._now_s
        if st.forget_after_s > 0 and now_s is not None:
            stale = (self._now_s - self._seen_s) > st.forget_after_s
            self._anchor.states[stale] = CellState.UNKNOWN

    def _pixels(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Anchor-frame points (N, 2) mm → continuous (col, row) pixel coordinates of cv2."""
        a = self._anchor_settings
        return np.column_stack(
            [
                (xy[:, 1] - a.y_min_mm) / a.resolution_mm - 0.5,
                (xy[:, 0] - a.x_min_mm) / a.resolution_mm - 0.5,
            ]
        )

    def _observation(
        self,
        xy: NDArray[np.float64],
        cls: NDArray[np.uint8],
        cv2,
        missing_floor: NDArray[np.float64],
    ) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
        """The cells one cloud speaks about: uint8 CellState values, _UNSEEN elsewhere; and the
        mask of cells FREE because a floor dot lies in them (not by filling between dots).

        ``missing_floor`` (M, 2, 2): anchor-frame segments along which the floor is known to be
        missing (a lowered dot's ray from its floor-level crossing to the dot).
        """
        st = self.settings
        shape = self._anchor.states.shape
        obs = np.full(shape, _UNSEEN, dtype=np.uint8)
        shift = 4
        scale = float(1 << shift)
        pix = self._pixels(xy)
        inside = (
            (pix[:, 0] > -1) & (pix[:, 0] < shape[1]) & (pix[:, 1] > -1) & (pix[:, 1] < shape[0])
        )
        floor = cls == PointClass.FLOOR
        obstacle = cls == PointClass.OBSTACLE
        dropoff = cls == PointClass.DROPOFF

        tri = _delaunay(xy[inside]) if inside.sum() >= 3 else np.zeros((0, 3), dtype=np.intp)
        if len(tri):
            idx = np.flatnonzero(inside)[tri]  # (T, 3) indices into xy
            corners = xy[idx]  # (T, 3, 2)
            edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
            tcls = cls[idx]
            all_floor = np.all(tcls == PointClass.FLOOR, axis=1)
            any_drop = np.any(tcls == PointClass.DROPOFF, axis=1)
            any_obst = np.any(tcls == PointClass.OBSTACLE, axis=1)
            polys = np.rint(pix[idx] * scale).astype(np.int32)  # (T, 3, 2)
            free_t = all_floor & (edges <= st.free_max_edge_mm)
            drop_t = any_drop & ~any_obst & (edges <= st.dropoff_max_edge_mm)
            obst_t = np.all(tcls == PointClass.OBSTACLE, axis=1) & (
                edges <= st.obstacle_max_edge_mm
            )
            if np.any(free_t):
                cv2.fillPoly(obs, list(polys[free_t]), int(CellState.FREE), cv2.LINE_8, shift)
            if np.any(drop_t):
                cv2.fillPoly(obs, list(polys[drop_t]), int(CellState.DROPOFF), cv2.LINE_8, shift)
            if np.any(obst_t):
                cv2.fillPoly(obs, list(polys[obst_t]), int(CellState.OBSTACLE), cv2.LINE_8, shift)

        cells = np.floor(pix + 0.5).astype(np.intp)  # the cell containing the point
        valid = (cells[:, 0] >= 0) & (cells[:, 0] < shape[1])
        valid &= (cells[:, 1] >= 0) & (cells[:, 1] < shape[0])
        fl = valid & floor
        # A floor dot's own cell is free unless this cloud already called it a drop-off.
        here = obs[cells[fl, 1], cells[fl, 0]]
        obs[cells[fl, 1], cells[fl, 0]] = np.where(here == CellState.DROPOFF, here, CellState.FREE)
        direct_free = np.zeros(shape, dtype=bool)
        direct_free[cells[fl, 1], cells[fl, 0]] = True
        if len(missing_floor):
            res = self._anchor_settings.resolution_mm
            seg = missing_floor[:, 1] - missing_floor[:, 0]
            k = max(2, math.ceil(float(np.linalg.norm(seg, axis=1).max()) / (0.5 * res)) + 1)
            t = np.linspace(0.0, 1.0, k)
            along = missing_floor[:, None, 0, :] + t[None, :, None] * seg[:, None, :]
            c = np.floor(self._pixels(along.reshape(-1, 2)) + 0.5).astype(np.intp)
            ok = (c[:, 0] >= 0) & (c[:, 0] < shape[1]) & (c[:, 1] >= 0) & (c[:, 1] < shape[0])
            obs[c[ok, 1], c[ok, 0]] = int(CellState.DROPOFF)
        radius = math.ceil(st.obstacle_inflation_mm / self._anchor_settings.resolution_mm)
        for mask_pts, state in (
            (valid & dropoff, CellState.DROPOFF),
            (valid & obstacle, CellState.OBSTACLE),
        ):
            if not np.any(mask_pts):
                continue
            layer = np.zeros(shape, dtype=np.uint8)
            layer[cells[mask_pts, 1], cells[mask_pts, 0]] = 1
            if radius > 0:
                kernel = cv2.getStructuringElement(
                    cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1)
                )
                layer = cv2.dilate(layer, kernel)
            obs[layer > 0] = int(state)
        return obs, direct_free & (obs == CellState.FREE)

    # -- queries ------------------------------------------------------------------------------

    def state_at(self, xy_mm: ArrayLike) -> NDArray[np.int8]:
        """:class:`CellState` (N,) under robot-frame points (N, 2) mm; UNKNOWN off the map."""
        q = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        return self._anchor.state_at(_to_frame(self._pose, q))

    def nearest_blocking_distance_mm(
        self,
        half_width_mm: float,
        max_range_mm: float,
        curvature_per_mm: float = 0.0,
        reverse: bool = False,
        start_mm: float = 0.0,
        unknown_blocks: bool = False,
    ) -> float:
        """Arc length along the robot's path to the first blocking cell within ``half_width_mm``
        of the path, mm; ``inf`` when the corridor is clear up to ``max_range_mm``.

        The path starts at the axle midpoint heading forward (``reverse``: backward) with constant
        curvature (1/mm, positive turns left, 0: straight). OBSTACLE and DROPOFF block; UNKNOWN
        blocks too with ``unknown_blocks``. Path samples before ``start_mm`` (under the chair
        itself) are not checked. Resolution: half a cell along and across the path.
        """
        res = self.settings.grid.resolution_mm
        step = 0.5 * res
        s = np.arange(start_mm, max_range_mm + step, step)
        lat = np.arange(-half_width_mm, half_width_mm + step, step)
        if reverse:
            s = -s
        k = curvature_per_mm
        if abs(k) < 1e-12:
            cx, cy, phi = s, np.zeros_like(s), np.zeros_like(s)
        else:
            phi = k * s
            cx, cy = np.sin(phi) / k, (1.0 - np.cos(phi)) / k
        px = cx[:, None] - np.sin(phi)[:, None] * lat[None, :]
        py = cy[:, None] + np.cos(phi)[:, None] * lat[None, :]
        states = self.state_at(np.column_stack([px.ravel(), py.ravel()])).reshape(px.shape)
        block = (states == CellState.OBSTACLE) | (states == CellState.DROPOFF)
        if unknown_blocks:
            block |= states == CellState.UNKNOWN
        rows = np.flatnonzero(block.any(axis=1))
        return float(abs(s[rows[0]])) if len(rows) else math.inf

    def blocked_xy_mm(self) -> NDArray[np.float64]:
        """Robot-frame centres (N, 2) mm of the OBSTACLE and DROPOFF cells of :attr:`grid`."""
        g = self.grid
        i, j = np.nonzero((g.states == CellState.OBSTACLE) | (g.states == CellState.DROPOFF))
        xs, ys = g.cell_centers()
        return np.column_stack([xs[i], ys[j]]) if len(i) else np.zeros((0, 2))

    @property
    def grid(self) -> OccupancyGrid:
        """The map in the current robot frame (resampled from the anchor grid on demand)."""
        if self._grid is None:
            import cv2

            g = OccupancyGrid(self.settings.grid)
            nx, ny = g.states.shape
            M = _affine(self._pose, g.settings, self._anchor_settings)
            g.states = (
                cv2.warpAffine(
                    self._anchor.states.view(np.uint8),
                    M,
                    (ny, nx),
                    flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=int(CellState.UNKNOWN),
                )
                .view(np.int8)
                .copy()
            )
            self._grid = g
        return self._grid

    def clear(self) -> None:
        """Forget everything (all cells UNKNOWN)."""
        self._anchor.states[:] = CellState.UNKNOWN
        self._seen_s[:] = -np.inf
        self._contradictions[:] = 0
        self._grid = None

    def render_png(self, path: str | Path, cloud: PointCloud | None = None) -> None:
        """Write a top-down picture of the map (see :func:`omnid.core.export.render_topdown`).

        The one convenience that touches the file system; callers that want bytes use
        ``render_topdown`` and ``cv2.imencode`` themselves.
        """
        import cv2

        from omnid.core.export import render_topdown

        ok, buf = cv2.imencode(".png", render_topdown(self, cloud))
        if not ok:  # pragma: no cover - cv2 fails only on unusable arrays
            raise ValueError("render_png: PNG encoding failed")
        Path(path).write_bytes(buf.tobytes())


def _delaunay(xy: NDArray[np.float64]) -> NDArray[np.intp]:
    """Delaunay triangles (T, 3) of indices into 2-D points ``xy`` (N, 2) (cv2.Subdiv2D)."""
    import cv2

    pts = xy.astype(np.float32)
    lo = pts.min(axis=0) - 10.0
    hi = pts.max(axis=0) + 10.0
    sub = cv2.Subdiv2D((float(lo[0]), float(lo[1]), float(hi[0] - lo[0]), float(hi[1] - lo[1])))
    sub.insert(np.ascontiguousarray(pts))  # type: ignore[call-overload]  # (N, 2) array is fine
    tri = np.asarray(sub.getTriangleList(), dtype=np.float32).reshape(-1, 3, 2)
    if len(tri) == 0:
        return np.zeros((0, 3), dtype=np.intp)
    # Map vertex coordinates back to point indices: float32 pairs viewed as one uint64 key.
    keys = np.ascontiguousarray(pts).view(np.uint64).ravel()
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    tkeys = np.ascontiguousarray(tri.reshape(-1, 2)).view(np.uint64).ravel()
    pos = np.searchsorted(sorted_keys, tkeys)
    pos = np.clip(pos, 0, len(sorted_keys) - 1)
    found = sorted_keys[pos] == tkeys  # False for the virtual outer vertices of Subdiv2D
    idx = order[pos].reshape(-1, 3)
    keep = found.reshape(-1, 3).all(axis=1)
    return idx[keep].astype(np.intp)


def classified(cloud: PointCloud, classes: ArrayLike) -> PointCloud:
    """``cloud`` with its ``classes`` replaced (a convenience for callers and tests)."""
    return replace(cloud, classes=np.asarray(classes, dtype=np.uint8))
