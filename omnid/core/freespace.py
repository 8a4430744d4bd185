"""The free-space map: where the chair may drive, remembered as it moves (thesis 7.1.2, 7.2.2).

The thesis takes the floor-level dots as the free area and the rest as obstacles, one capture at
a time. omnid keeps a local map instead (SPEC §3), so an obstacle the chair has turned away from
— out of the laser's forward field — still blocks it:

- ``update`` rasterises one classified cloud. Free area is not just the cells under floor dots:
  neighbouring dots are joined into triangles, and every triangle whose three corners are floor
  dots, with no edge longer than ``free_max_edge_mm``, is floor the laser has swept — FREE. A
  triangle with a drop-off corner (and no obstacle corner) spans the place where the floor goes
  missing: dots beyond an edge fall lower and land farther, so between the last floor dot and the
  first lowered one lies floor that was never seen — it is marked DROPOFF, never free (filled
  twice: with the lowered dots where they landed, and where their rays crossed floor level).
  Stronger still, a lowered dot's laser ray crossed floor level somewhere nearer without meeting
  floor: the cells along the ray from that crossing to the dot are DROPOFF, however deep the drop
  (7.2.2 extended to missing floor). Obstacle dots, and triangles of neighbouring obstacle dots
  (a box top), mark OBSTACLE (dots optionally inflated). Cells this cloud does not cover keep
  what they had.
- Triangles come from the laser lattice (``neighbours="lattice"``): the source sits at the rig
  origin, so a dot's slopes (X/Z, Y/Z) name its ray whatever it hit, and the dots fall into rows
  of the projector's lattice; adjacent rows are stitched into triangle strips, and each run of
  strip triangles of one kind is filled as one polygon. That replaced a Delaunay triangulation
  (``cv2.Subdiv2D``) and one polygon per triangle, 5–10x the cost; Delaunay remains for clouds
  without lattice rows and as ``neighbours="delaunay"``.
- ``move`` applies the robot's motion. The map is stored in an *anchor* frame (the robot frame
  at some earlier pose) together with the current robot pose in it; a move only updates that
  pose, and the grid is resampled (``cv2.warpAffine``, nearest neighbour) only when the chair has
  travelled ``reanchor_distance_mm`` from the anchor. Resampling at every small step would round
  each step away — a chair creeping at 10 mm per cycle over 50 mm cells would never see its map
  move. Queries transform their points exactly into the anchor frame.
- ``grid`` is the map as an :class:`OccupancyGrid` in the current robot frame (x forward, y left,
  origin at the axle midpoint), rebuilt on demand.
- What is remembered. Everything seen stays until a capture contradicts it, until the chair has
  travelled ``forget_after_travel_mm`` since the cell was last seen (odometry can no longer keep
  it in place) or — optionally — after ``forget_after_s``. The chair's own trail is seen too:
  :meth:`FreeSpaceMap.occupy` marks the unknown cells wholly under the footprint FREE (the
  chair stands there). Nothing else is free: at start-up the map holds only what the first
  capture shows and the cells under the chair.
- Drop-offs need evidence (a phantom must not stop the chair): a drop-off dot counts only with
  ``dropoff_min_points`` − 1 others within ``dropoff_cluster_mm`` at a depth within
  ``dropoff_depth_tolerance_mm`` of its own (a lower floor is flat, phantoms scatter), and a
  cell becomes DROPOFF
  only when ``dropoff_confirm_captures`` captures in a row say so; before that it is UNKNOWN
  (in doubt: not free, not yet a drop-off). Obstacles likewise (``obstacle_confirm_captures``):
  a phantom of one capture's wrong pairing is doubt, not a wall.
- Exact obstacle evidence: besides the cells, the map keeps the obstacle dots themselves (anchor
  frame and height, one per ``point_spacing_mm``, at most ``obstacle_points_max``; per cell those
  of the captures that saw it within ``point_memory_travel_mm`` of travel) for as long as their cell stays OBSTACLE. :meth:`FreeSpaceMap.blocking_evidence` gives the safety layer those points
  where they exist and the cell centres (with their half-diagonal) elsewhere, transformed
  exactly into the robot frame — no cell quantisation and no resampling error where the laser
  saw the thing (a doorway's jambs, a wall beside the chair).
- Rays carve: a laser ray that reached its dot passed through everything before it. A kept
  obstacle point within ``carve_tolerance_mm`` of a later capture's ray, well before that ray's
  dot, was not there (a phantom of a wrong pairing lies exactly on a ray: the lattice's one-row
  ambiguity puts a whole row on a false plane); it is dropped, and a cell that loses its last
  point becomes UNKNOWN (the ray says nothing of the floor below it), as does a cell filled
  between obstacle dots that no kept point could have made any more. The kept points tested are
  those anywhere between the source and the dots. This reaches where interpolated floor cannot:
  the band right in front of the footrests, which no floor dot of a standing chair ever lands
  in.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.config import Settings, require, setting, setting_range
from omnid.core.occupancy import CellState, GridSettings, OccupancyGrid, rig_to_robot
from omnid.core.types import PointClass, PointCloud

_UNSEEN = 255  # observation layer: this update says nothing about the cell
# Per-dot flags of the lattice fill (combined over a triangle's corners).
_F_FLOOR, _F_OBSTACLE, _F_DROPOFF, _F_LOW, _F_INSIDE, _F_INSIDE_C = 1, 2, 4, 8, 16, 32
# Flags of PointClass FLOOR, OBSTACLE, DROPOFF; a code beyond them has none of the three.
_CLASS_FLAGS = np.array([_F_FLOOR, _F_OBSTACLE, _F_DROPOFF, 0], dtype=np.uint8)
_CLASS_FLAGS.setflags(write=False)
_FAR_MM = 1e9  # points farther than this (or not finite) are ignored
_NO_CLASS = np.uint8(len(_CLASS_FLAGS) - 1)  # a dot that is evidence of nothing (flags 0)
_TURN_REACH_MM = 1000.0  # a heading error of dθ moves a cell this far away by dθ·this
_SHIFT = 4  # fractional bits of the fixed-point polygon corners given to cv2.fillPoly


@dataclass(frozen=True)
class FreeSpaceSettings(Settings):
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
    forget_after_travel_mm remembered cells not seen again while the chair travelled this far
                           become UNKNOWN (0: never): odometry error grows with travel
                           (translation + heading change × 1 m), and a remembered wall that
                           drifted by more than the footprint's margin is not where the map says
    reanchor_distance_mm   travel from the anchor pose before the stored grid is resampled
    neighbours             how dots are joined into triangles: "lattice" (strips between the
                           rows of the laser lattice, found from the dots' ray slopes; clouds
                           without rows fall back to Delaunay) or "delaunay" (always)
    dropoff_min_points     a drop-off dot counts only with this many (itself included) within
                           ``dropoff_cluster_mm`` at depths within ``dropoff_depth_tolerance_mm``
    dropoff_confirm_captures  captures in a row that must call a cell a drop-off before it is one
    obstacle_confirm_captures  likewise for an obstacle
    obstacle_points_max    exact obstacle points kept (0: cells only)
    point_spacing_mm       one kept point per this lattice spacing (the newest)
    point_memory_travel_mm a cell seen again keeps the points it was given within this much
                           travel, beside the new capture's, and loses older ones
    carve_tolerance_mm     a kept obstacle point this close to a later ray, well before the
                           ray's dot, is dropped (0: no carving)
    register_max_step_mm   each cloud's obstacle dots are aligned with the kept points to
                           correct the odometry's pose (:meth:`FreeSpaceMap.update`); a
                           correction larger than this (position, or heading × 1 m) is not
                           trusted and not applied (0: no registration)
    register_match_mm      a dot pairs with the nearest kept point within this distance
    register_min_pairs     fewer pairs than this: no correction
    """

    grid: GridSettings = field(default_factory=GridSettings)
    free_max_edge_mm: float = setting(250.0, 1.0, 2000.0)
    dropoff_max_edge_mm: float = setting(600.0, 0.0, 5000.0)
    obstacle_max_edge_mm: float = setting(200.0, 0.0, 2000.0)
    obstacle_inflation_mm: float = setting(0.0, 0.0, 500.0)
    forget_after_s: float = setting(0.0, 0.0, 3600.0)
    clear_after_contradictions: int = setting(3, 1, 100)
    # odometry assumed to drift by at most 0.25 % of travel: 50 mm (the margin) after 20 m
    forget_after_travel_mm: float = setting(20000.0, 0.0, 1.0e6)
    reanchor_distance_mm: float = setting(1000.0, 0.0, 100000.0)
    neighbours: str = "lattice"
    # a drop-off: 3 dots within 250 mm (two lattice steps at 1.2 m) whose depths agree within
    # 40 mm (a lower floor is flat; phantoms of a wrong pairing scatter), in 2 captures in a row
    dropoff_min_points: int = setting(3, 1, 50)
    dropoff_cluster_mm: float = setting(250.0, 10.0, 2000.0)
    dropoff_depth_tolerance_mm: float = setting(40.0, 1.0, 1000.0)
    dropoff_confirm_captures: int = setting(2, 1, 20)
    # a wrong pairing's phantom rarely survives the next capture (the chair moved, the geometry
    # that made it is gone); a real thing is seen again and again as the chair approaches
    obstacle_confirm_captures: int = setting(2, 1, 20)
    obstacle_points_max: int = setting(20000, 0, 1000000)
    point_spacing_mm: float = setting(10.0, 1.0, 100.0)
    # 0.25 % odometry drift (above): 1 mm after 400 mm. A capture's dots fall anywhere on a
    # face; the next may hit the same cell 40 mm farther back, and taking only its points
    # moved a 60 mm threshold's edge back by that until a later capture hit the edge again
    point_memory_travel_mm: float = setting(400.0, 0.0, 5000.0)
    # below half the thinnest obstacle worth keeping (a 40 mm post: a ray that close would have
    # hit it), above the ray's own error (dot noise, the laser a centimetre off the rig origin)
    carve_tolerance_mm: float = setting(15.0, 0.0, 100.0)
    register_max_step_mm: float = setting(0.0, 0.0, 500.0)
    register_match_mm: float = setting(40.0, 1.0, 500.0)
    register_min_pairs: int = setting(30, 3, 100000)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.neighbours in ("lattice", "delaunay"),
            "neighbours",
            f"must be 'lattice' or 'delaunay', not {self.neighbours!r}",
        )
        # the stored (anchor) grid is itself a GridSettings, held to the same bounds
        x_max = next(f for f in fields(GridSettings) if f.name == "x_max_mm")
        _, high = setting_range(x_max) or (0.0, math.inf)
        half = anchor_half_mm(self)
        require(
            half <= high,
            "reanchor_distance_mm",
            f"the stored map spans ±(the grid's farthest edge + reanchor_distance_mm + "
            f"grid.resolution_mm) = ±{half:g} mm; at most ±{high:g}",
        )


def anchor_half_mm(settings: FreeSpaceSettings) -> float:
    """Half the side of the stored square grid: the robot grid stays inside it however the
    chair turns and until it travels ``reanchor_distance_mm``."""
    g = settings.grid
    half = max(abs(g.x_min_mm), abs(g.x_max_mm), abs(g.y_min_mm), abs(g.y_max_mm))
    return half + settings.reanchor_distance_mm + g.resolution_mm


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


@dataclass(frozen=True)
class Registration:
    """What a cloud's registration did: ``outcome`` ("applied"; "too large", the correction
    refused; "too few pairs"), the pairs found and the correction of the chair's position (mm)
    and heading (rad) it measured."""

    outcome: str
    pairs: int = 0
    shift_mm: float = 0.0
    turn_rad: float = 0.0

    @property
    def applied(self) -> bool:
        return self.outcome == "applied"


class UnseenCells:
    """A map's never-seen cells within ``range_mm`` of the axle (:meth:`FreeSpaceMap.unseen_cells`),
    moved exactly into the robot frame of ``pose`` only where asked (:meth:`within`).

    ``anchor_xy``: the anchor grid's UNKNOWN cell centres (N, 2), anchor frame mm, in row order
    (x never decreases); ``beyond``: the anchor's lattice continued past its edges (M, 2), or
    None; ``grow_mm``: how far from its centre anything in a cell may lie (its half-diagonal)."""

    def __init__(
        self,
        anchor_xy: NDArray[np.float64],
        beyond: NDArray[np.float64] | None,
        pose: tuple[float, float, float],
        range_mm: float,
        grow_mm: float,
    ) -> None:
        self._xy, self._beyond = anchor_xy, beyond
        self._pose, self._range_mm = pose, range_mm
        self.grow_mm = grow_mm

    def within(
        self, x_min_mm: float, x_max_mm: float, y_min_mm: float, y_max_mm: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The cells whose robot-frame centre lies in the box (bounds included): (x, y) mm, in
        the order of :meth:`FreeSpaceMap.unknown_cells`, each moved by the same arithmetic —
        so a box cut of that array, bit for bit. Only the cells inside the box's outline in the
        anchor frame (padded by 1 mm against rounding) are moved."""
        x, y, th = self._pose
        c, sn = math.cos(th), math.sin(th)
        r = self._range_mm
        boxed = math.isfinite(x_min_mm + x_max_mm + y_min_mm + y_max_mm)
        lo_x, hi_x, lo_y, hi_y = x - r, x + r, -math.inf, math.inf
        if boxed:
            bx = np.array([x_min_mm, x_min_mm, x_max_mm, x_max_mm])
            by = np.array([y_min_mm, y_max_mm, y_min_mm, y_max_mm])
            ax, ay = x + c * bx - sn * by, y + sn * bx + c * by
            lo_x, hi_x = max(lo_x, float(ax.min()) - 1.0), min(hi_x, float(ax.max()) + 1.0)
            lo_y, hi_y = float(ay.min()) - 1.0, float(ay.max()) + 1.0
        # the centres come row by row: x never decreases
        k0 = int(np.searchsorted(self._xy[:, 0], max(x - r, lo_x), "left"))
        k1 = int(np.searchsorted(self._xy[:, 0], min(x + r, hi_x), "right"))
        xy = self._xy[k0:k1]
        parts = [xy[(xy[:, 1] >= lo_y) & (xy[:, 1] <= hi_y)] if boxed else xy]
        if self._beyond is not None:
            b = self._beyond
            if boxed:
                b = b[(b[:, 0] >= lo_x) & (b[:, 0] <= hi_x) & (b[:, 1] >= lo_y) & (b[:, 1] <= hi_y)]
            parts.append(b)
        xy = parts[0] if len(parts) == 1 else np.vstack(parts)
        dx, dy = xy[:, 0] - x, xy[:, 1] - y
        near = dx * dx + dy * dy <= r * r
        dx, dy = dx[near], dy[near]
        rx, ry = c * dx + sn * dy, -sn * dx + c * dy
        keep = (rx >= x_min_mm) & (rx <= x_max_mm) & (ry >= y_min_mm) & (ry <= y_max_mm)
        return rx[keep], ry[keep]


class FreeSpaceMap:
    """A remembered FREE / OBSTACLE / DROPOFF / UNKNOWN map around the chair (robot frame)."""

    def __init__(self, settings: FreeSpaceSettings | None = None) -> None:
        self.settings = settings or FreeSpaceSettings()
        g = self.settings.grid
        # The anchor grid is a square around the anchor pose, large enough that the robot grid
        # stays inside it however the chair turns and until it travels reanchor_distance_mm.
        half = anchor_half_mm(self.settings)
        self._anchor_settings = GridSettings(g.resolution_mm, -half, half, -half, half)
        self._anchor = OccupancyGrid(self._anchor_settings)
        shape = self._anchor.states.shape
        self._seen_s = np.full(shape, -np.inf)
        self._seen_travel = np.full(shape, -np.inf)  # self.travel_mm when last seen
        self._contradictions: NDArray[np.uint8] = np.zeros(shape, np.uint8)
        self._dropoff_seen: NDArray[np.uint8] = np.zeros(shape, np.uint8)  # captures in a row
        self._obstacle_seen: NDArray[np.uint8] = np.zeros(shape, np.uint8)
        self._from_points: NDArray[np.uint8] = np.zeros(shape, np.uint8)  # obstacle from dots
        # exact obstacle points: anchor x, y, height (mm) and the travel when seen (mm)
        self._points = np.zeros((0, 4))
        self._pose: tuple[float, float, float] = (0.0, 0.0, 0.0)  # robot in the anchor frame
        self._now_s = 0.0
        self.travel_mm = 0.0  # odometry travel so far (translation + |dθ| · 1 m)
        self.version = 0  # counts changes of the stored cells and points
        self._grid: OccupancyGrid | None = None
        self._strips: _Strips | None = None  # the last capture's lattice strips
        self._evidence: tuple[int, NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]
        self._evidence = (-1, np.zeros((0, 2)), np.zeros(0), np.zeros(0, bool))
        self._unknown: tuple[int, NDArray[np.float64]] = (-1, np.zeros((0, 2)))
        self._occupied: tuple[float, float, float] | None = None  # pose of the last occupy
        self.registration: Registration | None = None  # of the last cloud
        #: clouds registered, by outcome (:class:`Registration`)
        self.registrations: Counter[str] = Counter()

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
        self.travel_mm += math.hypot(dx_mm, dy_mm) + abs(dtheta_rad) * _TURN_REACH_MM
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
        self._seen_travel = cv2.warpAffine(
            self._seen_travel,
            M,
            (ny, nx),
            flags=flags,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=-1e300,
        )
        for name in ("_contradictions", "_dropoff_seen", "_obstacle_seen", "_from_points"):
            layer = cv2.warpAffine(
                getattr(self, name),
                M,
                (ny, nx),
                flags=flags,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=0,
            )
            setattr(self, name, np.asarray(layer, dtype=np.uint8))
        # the exact points move exactly: p' = R(−θ)·(p − t)
        x, y, th = self._pose
        c, sn = math.cos(th), math.sin(th)
        dx, dy = self._points[:, 0] - x, self._points[:, 1] - y
        self._points = np.column_stack([c * dx + sn * dy, -sn * dx + c * dy, self._points[:, 2:]])
        self._pose = (0.0, 0.0, 0.0)
        self._occupied = None
        # The cells were resampled (nearest neighbour, up to half a cell off), the points moved
        # exactly: an obstacle made by dots is where its points now fall, not where the
        # resampling put it (a cell the points left would block a doorway by 35 mm).
        grid = self._anchor
        pi, pj, inside = grid.cell_index(self._points[:, :2])
        with_points = np.zeros(grid.states.shape, dtype=np.bool_)
        with_points[pi[inside], pj[inside]] = True
        left = (self._from_points > 0) & ~with_points & (grid.states == CellState.OBSTACLE)
        grid.states[left] = CellState.UNKNOWN
        grid.states[with_points] = CellState.OBSTACLE
        self._from_points = with_points.astype(np.uint8)
        self._prune_points()
        self.version += 1

    # -- observations -------------------------------------------------------------------------

    def update(
        self,
        cloud: PointCloud,
        rig_x_offset_mm: float = 0.0,
        now_s: float | None = None,
        source_mm: tuple[float, float, float] | None = None,
    ) -> None:
        """Enter one classified cloud (rig frame, SPEC §2) seen from the current pose.

        ``rig_x_offset_mm`` is how far the rig origin sits ahead of the axle midpoint; ``now_s``
        (monotonic, s) stamps the cells this cloud covers, for ``forget_after_s``;
        ``source_mm`` is where the laser was when the frames were taken, in the cloud's rig
        frame (default the rig origin; a cloud moved by the odometry since its capture has its
        source moved with it), for carving.
        """
        import cv2

        if now_s is not None:
            self._now_s = float(now_s)
        self._grid = None
        self.version += 1
        st = self.settings
        if len(cloud) and st.register_max_step_mm > 0:
            self.registration = self._register(cloud, rig_x_offset_mm)
            self.registrations[self.registration.outcome] += 1
        if len(cloud):
            xy = _to_frame(self._pose, rig_to_robot(cloud.xyz, rig_x_offset_mm))
            # Finite and within 1000 km (NaN compares False): no overflow in any distance below.
            ok = (np.abs(xy[:, 0]) < _FAR_MM) & (np.abs(xy[:, 1]) < _FAR_MM)
            xyz, cls = cloud.xyz, cloud.classes
            if not ok.all():
                xy, cls, xyz = xy[ok], cls[ok], xyz[ok]
            H = cloud.floor_depth_mm
            sigma_z = _depth_sigma(cloud.cov, len(cloud))
            if not ok.all():
                sigma_z = sigma_z[ok]
            cls = self._dropoff_evidence(xy, xyz, cls, H, rig_x_offset_mm, sigma_z)
            # A ray that ended below the floor passed floor level at P·H/Z without meeting any
            # floor there: the floor is missing all along its path from that crossing to the dot.
            low = (cls == PointClass.DROPOFF) & (xyz[:, 2] > H)
            crossing = xyz[low] * (H / xyz[low, 2])[:, None]
            xy0 = _to_frame(self._pose, rig_to_robot(crossing, rig_x_offset_mm))
            segments = np.stack([xy0, xy[low]], axis=1)
            # The crossings also join the fill as drop-off corners (a lowered dot's triangles are
            # filled once at its dot and once at its crossing), so the strip between the last
            # floor dots and the first crossings reads DROPOFF too; their cells are drop-off dots.
            n_dots = len(xy)
            if st.carve_tolerance_mm > 0 and len(self._points):
                self._carve(xy, xyz, H, rig_x_offset_mm, source_mm or (0.0, 0.0, 0.0))
            is_obstacle = cls == PointClass.OBSTACLE
            obstacle_xyh = np.column_stack([xy[is_obstacle], H - xyz[is_obstacle, 2]])
            xy = np.vstack([xy, xy0])
            cls = np.concatenate([cls, np.full(len(xy0), PointClass.DROPOFF, np.uint8)])
            obs, direct_free, (r0, c0) = self._observation(xy, cls, cv2, segments, xyz, low, n_dots)
            # The observation covers only a window of the anchor grid (the cloud's bounding
            # box); the memory rules below work on that window.
            win = (slice(r0, r0 + obs.shape[0]), slice(c0, c0 + obs.shape[1]))
            states = self._anchor.states[win]
            seen = obs != _UNSEEN
            # Free area filled in between floor dots is an interpolation: it must not erase a
            # remembered obstacle or drop-off (a thin post can fall between the dots of one
            # capture). Only a floor dot landing in the cell itself clears it.
            held = (states == CellState.OBSTACLE) | (states == CellState.DROPOFF)
            # It does clear it once ``clear_after_contradictions`` captures in a row have filled
            # it as free, so a phantom or removed obstacle between dot columns cannot stay forever.
            contradicted = held & (obs == CellState.FREE) & ~direct_free
            counts = np.where(contradicted, self._contradictions[win] + 1, 0).astype(np.uint8)
            self._contradictions.fill(0)  # outside the window nothing is contradicted
            self._contradictions[win] = counts
            keep = contradicted & (counts < st.clear_after_contradictions)
            seen &= ~keep
            # A drop-off or an obstacle only after so many captures in a row: until then the cell
            # is in doubt (UNKNOWN), and what a cell already held stays.
            for state, need, counter in (
                (CellState.DROPOFF, st.dropoff_confirm_captures, self._dropoff_seen),
                (CellState.OBSTACLE, st.obstacle_confirm_captures, self._obstacle_seen),
            ):
                hit = obs == state
                prior = counter[win].astype(np.int32)
                confirmed = hit & ((prior + 1 >= need) | (states == state))
                doubt = hit & ~confirmed
                obs[doubt] = CellState.UNKNOWN
                seen &= ~(doubt & held)
                counter[win] = np.where(
                    hit, np.minimum(prior + 1, 255), np.where(seen, 0, prior)
                ).astype(np.uint8)
            states[seen] = obs[seen].astype(np.int8)
            self._seen_s[win][seen] = self._now_s
            self._seen_travel[win][seen] = self.travel_mm
            self._add_points(obstacle_xyh)
        forgot = False
        if st.forget_after_s > 0 and now_s is not None:
            stale = (self._now_s - self._seen_s) > st.forget_after_s
            forgot = bool(np.any(stale & (self._anchor.states != CellState.UNKNOWN)))
            self._anchor.states[stale] = CellState.UNKNOWN
        if st.forget_after_travel_mm > 0:
            far = (self.travel_mm - self._seen_travel) > st.forget_after_travel_mm
            forgot |= bool(np.any(far & (self._anchor.states != CellState.UNKNOWN)))
            self._anchor.states[far] = CellState.UNKNOWN
        if forgot or len(cloud):
            self._prune_points()

    def _register(self, cloud: PointCloud, rig_x_offset_mm: float) -> Registration:
        """Correct the pose by aligning the cloud's obstacle dots with the kept points.

        Odometry from wheel clocks drifts (15 holes a turn: a turn in place is uncertain by
        degrees), and a point kept from an earlier capture is placed by the odometry of then:
        seen from the drifted pose it lies off the wall it was on. The dots of this capture are
        placed by perception alone, relative to the chair now. Iterated closest points, point to
        line: each dot pairs with the nearest kept point within ``register_match_mm``, whose
        neighbours give the surface's normal there; the small rigid motion about the chair's
        position that best closes the pairs' gaps along their normals (least squares) is
        applied to the pose; three rounds. What the pairs cannot fix — the motion along a
        straight wall, where every position fits — is left as it was. A correction beyond
        ``register_max_step_mm`` (position, or heading × 1 m) is taken for a wrong pairing,
        not odometry: nothing is applied."""
        st = self.settings
        obstacle = cloud.classes == PointClass.OBSTACLE
        ref = self._points[:, :2]
        if int(obstacle.sum()) < st.register_min_pairs or len(ref) < st.register_min_pairs:
            return Registration("too few pairs")
        from scipy.spatial import cKDTree

        robot = rig_to_robot(cloud.xyz[obstacle], rig_x_offset_mm)
        tree = cKDTree(ref)
        pose = self._pose
        pairs = 0
        for _ in range(3):
            p = _to_frame(pose, robot)
            d, k = tree.query(p, distance_upper_bound=st.register_match_mm)
            ok = np.isfinite(d)
            pairs = int(ok.sum())
            if pairs < st.register_min_pairs:
                return Registration("too few pairs", pairs)
            p, q = p[ok], ref[k[ok]]
            n = _normals(tree, ref, q)
            x, y, th = pose
            # gap along the normal after a motion (tx, ty, dθ) about (x, y), to first order:
            # n·(p − q) + n·t + dθ·n·J(p − c), J(v) = (−v_y, v_x); dθ in mm at 1 m
            lever = (n[:, 1] * (p[:, 0] - x) - n[:, 0] * (p[:, 1] - y)) / _TURN_REACH_MM
            A = np.column_stack([n, lever])
            r = np.sum(n * (p - q), axis=1)
            # least squares in the directions the normals inform: a direction of the motion
            # that fewer than a tenth of the pairs' normals face (along a straight wall, or
            # the turn that a lone wall ahead cannot tell from a sideways shift) stays put
            lam, V = np.linalg.eigh(A.T @ A)
            inv = np.where(lam > 0.1 * pairs, 1.0 / np.maximum(lam, 1e-12), 0.0)
            step = -(V @ (inv * (V.T @ (A.T @ r))))
            dth = float(step[2]) / _TURN_REACH_MM
            pose = (x + float(step[0]), y + float(step[1]), math.remainder(th + dth, 2 * math.pi))
        x0, y0, th0 = self._pose
        shift = math.hypot(pose[0] - x0, pose[1] - y0)
        turn = abs(math.remainder(pose[2] - th0, 2.0 * math.pi))
        if max(shift, turn * _TURN_REACH_MM) > st.register_max_step_mm:
            return Registration("too large", pairs, shift, turn)
        self._pose = pose
        return Registration("applied", pairs, shift, turn)

    # -- the chair's trail --------------------------------------------------------------------

    def occupy(self, x0_mm: float, x1_mm: float, y0_mm: float, y1_mm: float) -> int:
        """The chair stands on the robot-frame rectangle [x0, x1] × [y0, y1] (its footprint):
        every UNKNOWN cell whose centre lies inside it becomes FREE and counts as seen now (the
        safety layer tests unseen cells by their centres against the footprint too, so that
        the chair finds its own trail free when it retraces it). Returns how many cells
        changed. Cheap to call at every status: it works only after the chair moved a quarter of
        a cell (or turned by as much at the footprint's far corner) since the last call."""
        res = self._anchor_settings.resolution_mm
        reach = max(abs(x0_mm), abs(x1_mm)) + max(abs(y0_mm), abs(y1_mm))
        last = self._occupied
        if last is not None:
            moved = math.hypot(self._pose[0] - last[0], self._pose[1] - last[1])
            turned = abs(math.remainder(self._pose[2] - last[2], 2.0 * math.pi)) * reach
            if moved + turned < 0.25 * res:
                return 0
        self._occupied = self._pose
        h = 0.0  # cell centres inside the footprint itself
        corners = _to_frame(
            self._pose, np.array([[x0_mm, y0_mm], [x0_mm, y1_mm], [x1_mm, y0_mm], [x1_mm, y1_mm]])
        )
        a = self._anchor_settings
        nx, ny = self._anchor.states.shape
        i0 = max(int((corners[:, 0].min() - a.x_min_mm) // res), 0)
        i1 = min(int((corners[:, 0].max() - a.x_min_mm) // res) + 1, nx)
        j0 = max(int((corners[:, 1].min() - a.y_min_mm) // res), 0)
        j1 = min(int((corners[:, 1].max() - a.y_min_mm) // res) + 1, ny)
        if i1 <= i0 or j1 <= j0:
            return 0
        xs = a.x_min_mm + (np.arange(i0, i1) + 0.5) * res
        ys = a.y_min_mm + (np.arange(j0, j1) + 0.5) * res
        x, y, th = self._pose
        c, sn = math.cos(th), math.sin(th)
        dx, dy = xs[:, None] - x, ys[None, :] - y
        rx, ry = c * dx + sn * dy, -sn * dx + c * dy  # cell centres in the robot frame
        under = (rx >= x0_mm + h) & (rx <= x1_mm - h) & (ry >= y0_mm + h) & (ry <= y1_mm - h)
        win = (slice(i0, i1), slice(j0, j1))
        states = self._anchor.states[win]
        new = under & (states == CellState.UNKNOWN)
        n = int(np.count_nonzero(new))
        if n:
            states[new] = CellState.FREE
            self._seen_s[win][new] = self._now_s
            self._seen_travel[win][new] = self.travel_mm
            self._grid = None
            self.version += 1
        return n

    # -- evidence -----------------------------------------------------------------------------

    def _dropoff_evidence(
        self,
        xy: NDArray[np.float64],
        xyz: NDArray[np.float64],
        cls: NDArray[np.uint8],
        floor_depth_mm: float,
        rig_x_offset_mm: float,
        sigma_z_mm: NDArray[np.float64],
    ) -> NDArray[np.uint8]:
        """``cls`` with the drop-off dots that are not evidence of a drop-off (module docstring)
        turned into dots of no class: alone (fewer than ``dropoff_min_points`` at one depth
        nearby). A lowered dot whose ray crossed floor level between this capture's floor dots
        is not set aside: a trench or a pit narrower than the lattice's reach looks exactly like
        that in one capture (the rule that did so kept a 150 mm trench FREE until 300 mm before
        it, docs/benchmarks.md); repetition over captures (``dropoff_confirm_captures``) tells.
        ``sigma_z_mm`` (N,): each dot's depth uncertainty."""
        drop = np.flatnonzero(cls == PointClass.DROPOFF)
        if len(drop) == 0:
            return cls
        depth = xyz[drop, 2] - floor_depth_mm
        # The lattice is angular: dots at depth Z lie Z/H times as far apart as on the floor.
        scale = np.maximum(xyz[drop, 2] / floor_depth_mm, 1.0)
        sig = sigma_z_mm[drop]
        ok = self._clustered(xy[drop], depth, scale, sig)
        if not np.all(ok) and np.any(ok):
            keep = np.flatnonzero(ok)
            ok[keep] = self._clustered(xy[drop[keep]], depth[keep], scale[keep], sig[keep])
        out = cls.copy()
        out[drop[~ok]] = _NO_CLASS
        return out

    def _clustered(
        self,
        xy: NDArray[np.float64],
        depth_mm: NDArray[np.float64],
        scale: NDArray[np.float64],
        sigma_mm: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """Which drop-off dots (M, 2) have ``dropoff_min_points`` − 1 others within
        ``dropoff_cluster_mm`` · ``scale`` (of either) at a consistent depth (mm below the
        floor): within ``dropoff_depth_tolerance_mm`` or three combined sigmas."""
        st = self.settings
        need = st.dropoff_min_points
        m = len(xy)
        if need <= 1:
            return np.ones(m, dtype=bool)
        if m < need:
            return np.zeros(m, dtype=bool)
        order = np.argsort(xy[:, 0], kind="stable")  # a band of x at a time bounds the work
        out = np.zeros(m, dtype=bool)
        r = st.dropoff_cluster_mm * scale
        r_max = float(r.max())
        xs = xy[order, 0]
        for lo in range(0, m, 512):
            idx = order[lo : lo + 512]
            j0 = int(np.searchsorted(xs, xy[idx, 0].min() - r_max))
            j1 = int(np.searchsorted(xs, xy[idx, 0].max() + r_max, side="right"))
            cand = order[j0:j1]
            d2 = (xy[idx, None, 0] - xy[None, cand, 0]) ** 2
            d2 += (xy[idx, None, 1] - xy[None, cand, 1]) ** 2
            reach = np.maximum(r[idx, None], r[None, cand])
            tol = np.maximum(
                st.dropoff_depth_tolerance_mm,
                3.0 * np.hypot(sigma_mm[idx, None], sigma_mm[None, cand]),
            )
            same = np.abs(depth_mm[idx, None] - depth_mm[None, cand]) <= tol
            out[idx] = ((d2 <= reach * reach) & same).sum(axis=1) >= need  # itself included
        return out

    def _add_points(self, xyh_anchor: NDArray[np.float64]) -> None:
        """Keep new obstacle dots (anchor x, y and height, mm) as exact evidence. A cell keeps
        the points of the captures that saw an obstacle in it within the last
        ``point_memory_travel_mm`` of travel: the nearest views and the least odometry between
        then and now (older views of the same face, placed by older odometry, would smear it by
        centimetres), but not only the latest, whose dots may have missed the cell's edge."""
        if self.settings.obstacle_points_max == 0 or len(xyh_anchor) == 0:
            return
        a = self._anchor
        if len(self._points):
            ni, nj, nin = a.cell_index(xyh_anchor[:, :2])
            fresh = np.zeros(a.states.shape, dtype=bool)
            fresh[ni[nin], nj[nin]] = True
            oi, oj, oin = a.cell_index(self._points[:, :2])
            recent = self.travel_mm - self._points[:, 3] < self.settings.point_memory_travel_mm
            keep = ~(oin & fresh[oi, oj]) | recent
            self._points = self._points[keep]
        stamp = np.full((len(xyh_anchor), 1), self.travel_mm)
        self._points = np.vstack([self._points, np.hstack([xyh_anchor, stamp])])
        ni, nj, nin = a.cell_index(xyh_anchor[:, :2])
        self._from_points[ni[nin], nj[nin]] = 1

    def _carve(
        self,
        xy: NDArray[np.float64],
        xyz: NDArray[np.float64],
        floor_depth_mm: float,
        rig_x_offset_mm: float,
        source_mm: tuple[float, float, float],
    ) -> None:
        """Drop the kept points this capture's rays passed through (module docstring); a cell
        left without points becomes UNKNOWN. ``xy`` (N, 2): the dots in the anchor frame,
        ``xyz`` (N, 3) in the rig frame."""
        st = self.settings
        tol = st.carve_tolerance_mm
        pts = self._points
        # the rays run from the source to the dots: the kept points to test lie anywhere between
        # (the box of the dots alone missed a phantom between the mirrors and the nearest dots,
        # in the band before the footrests — forever, the chair standing: docs/benchmarks.md)
        src = _to_frame(
            self._pose, np.array([[source_mm[0] + rig_x_offset_mm, -source_mm[1]]], np.float64)
        )
        ends = np.vstack([xy, src])
        lo, hi = ends.min(axis=0) - 200.0, ends.max(axis=0) + 200.0
        sel = np.flatnonzero(
            (pts[:, 0] >= lo[0])
            & (pts[:, 0] <= hi[0])
            & (pts[:, 1] >= lo[1])
            & (pts[:, 1] <= hi[1])
        )
        dots = xyz[(xyz[:, 2] > 1e-9) & (xyz[:, 2] < _FAR_MM)]
        if len(sel) == 0 or len(dots) == 0:
            return
        # kept points in this capture's rig frame: X = x − offset, Y = −y, Z = H − h
        x, y, th = self._pose
        c, sn = math.cos(th), math.sin(th)
        dx, dy = pts[sel, 0] - x, pts[sel, 1] - y
        rx, ry = c * dx + sn * dy, -sn * dx + c * dy
        src = np.asarray(source_mm, dtype=np.float64)
        rel = np.column_stack([rx - rig_x_offset_mm, -ry, floor_depth_mm - pts[sel, 2]]) - src
        ray = dots - src
        carved = np.zeros(len(sel), dtype=bool)
        below = np.flatnonzero(rel[:, 2] > tol)  # a ray goes down: nothing above the source
        if len(below) == 0:
            return
        # Candidate rays by slope: a ray passes within tol of a point at depth Z only if its
        # slope X/Z differs from the point's by at most (1 + (X/Z)²)·tol/Z (the exact 3-D
        # distance decides below).
        ray_u = ray[:, 0] / np.maximum(ray[:, 2], 1e-9)
        order = np.argsort(ray_u, kind="stable")
        us = ray_u[order]
        r = rel[below]
        pu = r[:, 0] / r[:, 2]
        w = 1.05 * (1.0 + pu * pu) * tol / r[:, 2]
        lo = np.searchsorted(us, pu - w)
        hi = np.searchsorted(us, pu + w, side="right")
        # a point so near the mirrors' plane that a tenth of the rays could pass it is left
        # alone (carving is for what the laser sweeps, well below the source)
        few = np.flatnonzero((hi - lo) <= max(8, len(order) // 5))
        below, r, lo, hi = below[few], r[few], lo[few], hi[few]
        width = int((hi - lo).max()) if len(few) else 0
        if width == 0:
            return
        length2 = np.einsum("ij,ij->i", ray, ray)
        for k in range(0, len(below), 256):
            rk, lk, hk = r[k : k + 256], lo[k : k + 256], hi[k : k + 256]
            slot = lk[:, None] + np.arange(width)[None, :]
            valid = slot < hk[:, None]
            cand = order[np.minimum(slot, len(order) - 1)]  # (m, width) ray indices
            d = ray[cand]  # (m, width, 3)
            l2 = length2[cand]
            t = np.einsum("mk,mwk->mw", rk, d) / l2  # along each ray: 0 source, 1 its dot
            perp2 = np.einsum("mk,mk->m", rk, rk)[:, None] - t * t * l2
            before = (t > 0.0) & ((1.0 - t) * np.sqrt(l2) > 3.0 * tol)
            carved[below[k : k + 256]] = np.any(valid & before & (perp2 < tol * tol), axis=1)
        if not np.any(carved):
            return
        gone = sel[carved]
        keep = np.ones(len(pts), dtype=bool)
        keep[gone] = False
        a = self._anchor
        gi, gj, inside = a.cell_index(pts[gone, :2])
        gi, gj = gi[inside], gj[inside]
        left = np.zeros(a.states.shape, dtype=bool)
        ki, kj, kin = a.cell_index(pts[keep, :2])
        left[ki[kin], kj[kin]] = True
        empty = ~left[gi, gj] & (a.states[gi, gj] == CellState.OBSTACLE)
        a.states[gi[empty], gj[empty]] = CellState.UNKNOWN
        self._points = pts[keep]
        self._unsupported(pts[gone, :2], left)

    def _unsupported(self, carved_xy: NDArray[np.float64], with_points: NDArray[np.bool_]) -> None:
        """Clear the obstacle cells filled between obstacle dots (a box top: no dot of their
        own) that the carved points ``carved_xy`` (anchor mm) could have made and no kept point
        still could: a triangle with no edge longer than ``obstacle_max_edge_mm`` lies within
        that of each of its corners, so a cell farther than that (plus its half-diagonal) from
        every kept point has lost every corner that filled it. Without this a phantom patch's
        fill outlived its carved dots in the band before the footrests, where no floor dot
        lands to clear it (the chair stood at obstacle_stop for as long as it stood)."""
        reach = self.settings.obstacle_max_edge_mm
        if reach <= 0.0 or len(carved_xy) == 0:
            return
        a = self._anchor
        res = a.settings.resolution_mm
        reach += 0.5 * res * math.sqrt(2.0)
        nx, ny = a.states.shape
        lo = np.floor(
            (carved_xy.min(axis=0) - reach - (a.settings.x_min_mm, a.settings.y_min_mm)) / res
        )
        hi = np.floor(
            (carved_xy.max(axis=0) + reach - (a.settings.x_min_mm, a.settings.y_min_mm)) / res
        )
        i0, j0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        i1, j1 = min(int(hi[0]) + 1, nx), min(int(hi[1]) + 1, ny)
        if i1 <= i0 or j1 <= j0:
            return
        win = (slice(i0, i1), slice(j0, j1))
        ii, jj = np.nonzero((a.states[win] == CellState.OBSTACLE) & ~with_points[win])
        if len(ii) == 0:
            return
        xs, ys = a.cell_centers()
        cx, cy = xs[ii + i0], ys[jj + j0]
        near = _any_within(cx, cy, carved_xy, reach)  # only those a carved point could have made
        if not np.any(near):
            return
        cx, cy, ii, jj = cx[near], cy[near], ii[near], jj[near]
        supported = _any_within(cx, cy, self._points[:, :2], reach)
        a.states[ii[~supported] + i0, jj[~supported] + j0] = CellState.UNKNOWN

    def _prune_points(self) -> None:
        """Drop the points whose cell is no longer an obstacle, one per ``point_spacing_mm``
        (the newest), at most ``obstacle_points_max`` (the newest)."""
        st = self.settings
        pts = self._points
        if len(pts) == 0:
            return
        i, j, inside = self._anchor.cell_index(pts[:, :2])
        keep = inside & (self._anchor.states[i, j] == CellState.OBSTACLE)
        pts = pts[keep]
        if len(pts):
            q = np.floor(pts[:, :2] / st.point_spacing_mm).astype(np.int64) + (1 << 30)
            key = (q[:, 0] << 32) | q[:, 1]
            # the last occurrence of each key: the newest point on that lattice site
            _, first_rev = np.unique(key[::-1], return_index=True)
            pts = pts[np.sort(len(pts) - 1 - first_rev)]
        self._points = pts[-st.obstacle_points_max :] if st.obstacle_points_max else pts[:0]

    @property
    def obstacle_points(self) -> NDArray[np.float64]:
        """The kept exact obstacle points (N, 2), robot frame, mm (heights not included)."""
        x, y, th = self._pose
        c, sn = math.cos(th), math.sin(th)
        dx, dy = self._points[:, 0] - x, self._points[:, 1] - y
        return np.column_stack([c * dx + sn * dy, -sn * dx + c * dy])

    def blocking_evidence(
        self, max_range_mm: float = math.inf
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
        """Where the chair must not go, exactly as known, within ``max_range_mm`` of the axle:
        (xy (N, 2) robot frame mm, grow (N,) mm, dropoff (N,) bool).

        An OBSTACLE cell that holds exact points is given by its points (grow 0); every other
        OBSTACLE or DROPOFF cell by its centre and half-diagonal (anything in the cell lies
        within ``grow`` of it). The points and cells are stored in the anchor frame and moved
        into the robot frame exactly (no resampling)."""
        if self._evidence[0] != self.version:
            a = self._anchor
            i, j = np.nonzero(a.states >= CellState.OBSTACLE)
            with_points = np.zeros(a.states.shape, dtype=bool)
            if len(self._points):
                pi, pj, inside = a.cell_index(self._points[:, :2])
                with_points[pi[inside], pj[inside]] = True
            cell = ~with_points[i, j]
            i, j = i[cell], j[cell]
            xs, ys = a.cell_centers()
            h = 0.5 * a.settings.resolution_mm * math.sqrt(2.0)
            xy = np.vstack([np.column_stack([xs[i], ys[j]]), self._points[:, :2]])
            grow = np.concatenate([np.full(len(i), h), np.zeros(len(self._points))])
            drop = np.concatenate(
                [a.states[i, j] == CellState.DROPOFF, np.zeros(len(self._points), bool)]
            )
            self._evidence = (self.version, xy, grow, drop)
        _, xy, grow, drop = self._evidence
        x, y, th = self._pose
        c, sn = math.cos(th), math.sin(th)
        dx, dy = xy[:, 0] - x, xy[:, 1] - y
        if math.isfinite(max_range_mm):
            near = dx * dx + dy * dy <= max_range_mm * max_range_mm
            dx, dy, grow, drop = dx[near], dy[near], grow[near], drop[near]
        robot = np.column_stack([c * dx + sn * dy, -sn * dx + c * dy])
        return robot, grow, drop

    def unknown_cells(self, max_range_mm: float = math.inf) -> tuple[NDArray[np.float64], float]:
        """The never-seen cells within ``max_range_mm`` of the axle: (their centres (N, 2),
        robot frame mm; the half-diagonal of a cell, mm — anything in a cell lies within it of
        the centre, however the cell is turned against the robot frame).

        The cells are the anchor grid's UNKNOWN cells, moved into the robot frame exactly (no
        resampling: :attr:`grid` is a nearest-neighbour view, in which a single never-seen cell
        may vanish and an unseen edge lies up to this half-diagonal off while the chair's
        heading differs from the anchor's). Beyond the anchor grid is unseen as well: where
        the range reaches past it, the anchor's lattice continued there is returned too (the
        anchor covers the robot grid's sides, not always its corners turned towards an axis,
        and a long horizon reaches farther). An infinite range is the robot grid's farthest
        corner. :meth:`unseen_cells` gives the same cells a box at a time."""
        view = self.unseen_cells(max_range_mm)
        return np.column_stack(view.within(-math.inf, math.inf, -math.inf, math.inf)), view.grow_mm

    def unseen_cells(self, max_range_mm: float = math.inf) -> UnseenCells:
        """:meth:`unknown_cells` as a view that moves them into the robot frame only box by box
        (:meth:`UnseenCells.within`): a control cycle's sweeps reach a few hundred of the ten
        thousand cells within its horizon."""
        if self._unknown[0] != self.version:
            a = self._anchor
            i, j = np.nonzero(a.states == CellState.UNKNOWN)
            xs, ys = a.cell_centers()
            self._unknown = (self.version, np.column_stack([xs[i], ys[j]]))
        if not math.isfinite(max_range_mm):
            g = self.settings.grid
            max_range_mm = math.hypot(
                max(abs(g.x_min_mm), abs(g.x_max_mm)), max(abs(g.y_min_mm), abs(g.y_max_mm))
            )
        x, y, _ = self._pose
        st = self._anchor_settings
        beyond = None
        if (
            x - max_range_mm < st.x_min_mm
            or x + max_range_mm > st.x_max_mm
            or y - max_range_mm < st.y_min_mm
            or y + max_range_mm > st.y_max_mm
        ):
            beyond = self._beyond_anchor(x, y, max_range_mm)
        grow = 0.5 * st.resolution_mm * math.sqrt(2.0)
        return UnseenCells(self._unknown[1], beyond, self._pose, max_range_mm, grow)

    def _beyond_anchor(self, x_mm: float, y_mm: float, range_mm: float) -> NDArray[np.float64]:
        """Centres (N, 2), anchor frame mm, of the anchor's lattice continued past its edges
        within the square of half-side ``range_mm`` round (``x_mm``, ``y_mm``): never seen."""
        a = self._anchor_settings
        res = a.resolution_mm
        nx, ny = self._anchor.states.shape
        i = np.arange(math.floor((x_mm - range_mm - a.x_min_mm) / res),
                      math.floor((x_mm + range_mm - a.x_min_mm) / res) + 1)  # fmt: skip
        j = np.arange(math.floor((y_mm - range_mm - a.y_min_mm) / res),
                      math.floor((y_mm + range_mm - a.y_min_mm) / res) + 1)  # fmt: skip
        ii, jj = np.meshgrid(i, j, indexing="ij")
        off = (ii < 0) | (ii >= nx) | (jj < 0) | (jj >= ny)
        return np.column_stack(
            [a.x_min_mm + (ii[off] + 0.5) * res, a.y_min_mm + (jj[off] + 0.5) * res]
        )

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
        xyz: NDArray[np.float64],
        low: NDArray[np.bool_],
        n_dots: int,
    ) -> tuple[NDArray[np.uint8], NDArray[np.bool_], tuple[int, int]]:
        """The cells one cloud speaks about, in a window of the anchor grid around the cloud:
        uint8 CellState values, _UNSEEN elsewhere; the mask of cells FREE because a floor dot
        lies in them (not by filling between dots); and the window's first (row, column).

        ``xy`` (N, 2): anchor-frame positions of the ``n_dots`` dots (rig positions ``xyz``,
        ``low``: lowered drop-off dots), followed by the floor-level crossings of the lowered
        dots' rays, in order; ``missing_floor`` (M, 2, 2): anchor-frame segments along which the
        floor is known to be missing (a lowered dot's ray from its crossing to the dot).
        """
        st = self.settings
        radius = math.ceil(st.obstacle_inflation_mm / self._anchor_settings.resolution_mm)
        pix = self._pixels(xy)
        # The window: the points' bounding box (it holds every triangle and ray segment between
        # them), grown by the inflation radius, clipped to the grid.
        rows, cols = self._anchor.states.shape
        pad = radius + 2
        if len(pix):
            lo = np.floor([pix[:, 0].min(), pix[:, 1].min()]) - pad
            hi = np.ceil([pix[:, 0].max(), pix[:, 1].max()]) + pad + 1
        else:
            lo = hi = np.zeros(2)
        c0, c1 = (int(np.clip(v, 0, cols)) for v in (lo[0], hi[0]))
        r0, r1 = (int(np.clip(v, 0, rows)) for v in (lo[1], hi[1]))
        shape = (max(r1 - r0, 0), max(c1 - c0, 0))
        obs = np.full(shape, _UNSEEN, dtype=np.uint8)
        if obs.size == 0:
            return obs, np.zeros(shape, dtype=bool), (r0, c0)
        offset = np.array([c0, r0], dtype=np.float64)
        pix = pix - offset
        inside = (
            (pix[:, 0] > -1) & (pix[:, 0] < shape[1]) & (pix[:, 1] > -1) & (pix[:, 1] < shape[0])
        )
        floor = cls == PointClass.FLOOR
        obstacle = cls == PointClass.OBSTACLE
        dropoff = cls == PointClass.DROPOFF
        lattice = st.neighbours == "lattice"
        if not (lattice and self._fill_lattice(obs, xy, cls, pix, inside, xyz, low, n_dots, cv2)):
            self._fill_delaunay(obs, xy, cls, pix, inside, cv2)

        cells = np.floor(pix + 0.5).astype(np.intp)  # the cell containing the point
        valid = (cells[:, 0] >= 0) & (cells[:, 0] < shape[1])
        valid &= (cells[:, 1] >= 0) & (cells[:, 1] < shape[0])
        fl = valid & floor
        # A floor dot's own cell is free unless this cloud already called it a drop-off.
        lin = cells[fl, 1] * shape[1] + cells[fl, 0]  # flat indices: cheaper than (row, col)
        flat = obs.reshape(-1)  # a view
        here = flat[lin]
        flat[lin] = np.where(here == CellState.DROPOFF, here, np.uint8(CellState.FREE))
        direct_free = np.zeros(shape, dtype=bool)
        direct_free.reshape(-1)[lin] = True
        if len(missing_floor):
            res = self._anchor_settings.resolution_mm
            seg = missing_floor[:, 1] - missing_floor[:, 0]
            k = max(2, math.ceil(float(np.linalg.norm(seg, axis=1).max()) / (0.5 * res)) + 1)
            t = np.linspace(0.0, 1.0, k)
            along = missing_floor[:, None, 0, :] + t[None, :, None] * seg[:, None, :]
            c = np.floor(self._pixels(along.reshape(-1, 2)) - offset + 0.5).astype(np.intp)
            ok = (c[:, 0] >= 0) & (c[:, 0] < shape[1]) & (c[:, 1] >= 0) & (c[:, 1] < shape[0])
            obs[c[ok, 1], c[ok, 0]] = int(CellState.DROPOFF)
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
        return obs, direct_free & (obs == CellState.FREE), (r0, c0)

    def _fill_lattice(
        self,
        obs: NDArray[np.uint8],
        xy: NDArray[np.float64],
        cls: NDArray[np.uint8],
        pix: NDArray[np.float64],
        inside: NDArray[np.bool_],
        xyz: NDArray[np.float64],
        low: NDArray[np.bool_],
        n_dots: int,
        cv2,
    ) -> bool:
        """Fill the triangles between the dots from the laser lattice's strips (see
        :func:`_lattice_strips`); False, touching nothing, when the dots show no lattice rows."""
        st = self.settings
        ray = (xyz[:, 2] > 1e-9) & (xyz[:, 2] < _FAR_MM)  # NaN compares False
        sel = np.flatnonzero(ray)
        if len(sel) < 4:
            return False
        z = xyz[sel, 2]
        u, v = xyz[sel, 0] / z, xyz[sel, 1] / z
        # The lattice changes little from capture to capture: the last strips usually still fit.
        strips = self._strips
        if strips is None or not strips.fits(u, v):
            strips = self._strips = _lattice_strips(u, v)
        if strips is None:
            return False
        if len(sel) < len(xyz):
            strips = replace(
                strips,
                tri=sel[strips.tri],
                a_chain=sel[strips.a_chain],
                b_chain=sel[strips.b_chain],
            )
        # Per-dot flags, combined over each triangle's corners with one AND and one OR.
        where_low = np.flatnonzero(low)
        inside_c = inside[:n_dots].copy()
        inside_c[where_low] = inside[n_dots : n_dots + len(where_low)]
        c = cls[:n_dots]
        flags = _CLASS_FLAGS[np.minimum(c, len(_CLASS_FLAGS) - 1)]
        flags |= low * np.uint8(_F_LOW)
        flags |= inside[:n_dots] * np.uint8(_F_INSIDE)
        flags |= inside_c * np.uint8(_F_INSIDE_C)
        t0, t1, t2 = strips.tri[:, 0], strips.tri[:, 1], strips.tri[:, 2]
        f0, f1, f2 = flags[t0], flags[t1], flags[t2]
        every, some = f0 & f1 & f2, f0 | f1 | f2
        near = (every & _F_INSIDE) > 0
        edges = _longest_edge(xy, t0, t1, t2)
        free_t = near & ((every & _F_FLOOR) > 0) & (edges <= st.free_max_edge_mm)
        no_obst = (some & _F_OBSTACLE) == 0
        drop_t = near & ((some & _F_DROPOFF) > 0) & no_obst & (edges <= st.dropoff_max_edge_mm)
        obst_t = near & ((every & _F_OBSTACLE) > 0) & (edges <= st.obstacle_max_edge_mm)
        value = np.zeros(len(t0), dtype=np.uint8)  # the three kinds exclude each other
        value[free_t] = CellState.FREE
        value[drop_t] = CellState.DROPOFF
        value[obst_t] = CellState.OBSTACLE
        free, drop, obst = int(CellState.FREE), int(CellState.DROPOFF), int(CellState.OBSTACLE)
        fixed = _fixed_point(pix)
        if len(where_low) == 0:
            _fill_strips(obs, strips, value, pix, fixed, (free, drop, obst), cv2)
            return True
        _fill_strips(obs, strips, value, pix, fixed, (free, drop), cv2)
        # Lowered dots stand in at their floor-level crossings in a second drop-off fill.
        xy_c = xy[:n_dots].copy()
        xy_c[where_low] = xy[n_dots : n_dots + len(where_low)]
        pix_c = pix[:n_dots].copy()
        pix_c[where_low] = pix[n_dots : n_dots + len(where_low)]
        drop_c = ((every & _F_INSIDE_C) > 0) & ((some & _F_LOW) > 0) & no_obst
        drop_c &= _longest_edge(xy_c, t0, t1, t2) <= st.dropoff_max_edge_mm
        fixed_c = _fixed_point(pix_c)
        _fill_strips(obs, strips, drop_c * np.uint8(drop), pix_c, fixed_c, (drop,), cv2)
        _fill_strips(obs, strips, (value == obst) * np.uint8(obst), pix, fixed, (obst,), cv2)
        return True

    def _fill_delaunay(
        self,
        obs: NDArray[np.uint8],
        xy: NDArray[np.float64],
        cls: NDArray[np.uint8],
        pix: NDArray[np.float64],
        inside: NDArray[np.bool_],
        cv2,
    ) -> None:
        """Fill the triangles between the dots from a Delaunay triangulation of all of them
        (crossings included as drop-off corners): for clouds without lattice rows."""
        st = self.settings
        tri = _delaunay(xy[inside]) if inside.sum() >= 3 else np.zeros((0, 3), dtype=np.intp)
        if len(tri) == 0:
            return
        idx = np.flatnonzero(inside)[tri]  # (T, 3) indices into xy
        edges = _longest_edge(xy, idx[:, 0], idx[:, 1], idx[:, 2])
        tcls = cls[idx]
        all_floor = np.all(tcls == PointClass.FLOOR, axis=1)
        any_drop = np.any(tcls == PointClass.DROPOFF, axis=1)
        any_obst = np.any(tcls == PointClass.OBSTACLE, axis=1)
        polys = _fixed_point(pix)[idx]  # (T, 3, 2)
        free_t = all_floor & (edges <= st.free_max_edge_mm)
        drop_t = any_drop & ~any_obst & (edges <= st.dropoff_max_edge_mm)
        obst_t = np.all(tcls == PointClass.OBSTACLE, axis=1) & (edges <= st.obstacle_max_edge_mm)
        for use, state in (
            (free_t, CellState.FREE),
            (drop_t, CellState.DROPOFF),
            (obst_t, CellState.OBSTACLE),
        ):
            if np.any(use):
                cv2.fillPoly(obs, list(polys[use]), int(state), cv2.LINE_8, _SHIFT)

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
        self._seen_travel[:] = -np.inf
        self._contradictions[:] = 0
        self._dropoff_seen[:] = 0
        self._obstacle_seen[:] = 0
        self._from_points[:] = 0
        self._points = np.zeros((0, 4))
        self._occupied = None
        self._grid = None
        self.version += 1

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


def _normals(
    tree: object, ref: NDArray[np.float64], at: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Unit normals (M, 2) of the point set ``ref`` at its points ``at``: the direction of
    least spread of each one's 12 nearest neighbours (``tree``: a cKDTree of ``ref``)."""
    _, k = tree.query(at, k=min(12, len(ref)))  # type: ignore[attr-defined]
    nb = ref[k]
    nb = nb - nb.mean(axis=1, keepdims=True)
    sxx = np.sum(nb[:, :, 0] ** 2, axis=1)
    syy = np.sum(nb[:, :, 1] ** 2, axis=1)
    sxy = np.sum(nb[:, :, 0] * nb[:, :, 1], axis=1)
    # the major axis of the 2x2 scatter is at angle φ = ½·atan2(2 sxy, sxx − syy); the normal
    # is perpendicular to it
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    return np.column_stack([-np.sin(phi), np.cos(phi)])


def _fixed_point(pix: NDArray[np.float64]) -> NDArray[np.int32]:
    """Pixel coordinates (N, 2) → cv2 fixed point with :data:`_SHIFT` fractional bits (clipped
    far outside any grid, so that nothing overflows)."""
    limit = float(1 << (30 - _SHIFT))
    return np.rint(np.clip(pix, -limit, limit) * (1 << _SHIFT)).astype(np.int32)


def _longest_edge(
    xy: NDArray[np.float64], t0: NDArray[np.intp], t1: NDArray[np.intp], t2: NDArray[np.intp]
) -> NDArray[np.float64]:
    """(T,) longest side, mm, of the triangles with corners ``t0``, ``t1``, ``t2`` (T,) (indices
    into points ``xy`` (N, 2))."""
    x, y = xy[:, 0], xy[:, 1]
    x0, x1, x2, y0, y1, y2 = x[t0], x[t1], x[t2], y[t0], y[t1], y[t2]
    d01 = (x1 - x0) ** 2 + (y1 - y0) ** 2
    d12 = (x2 - x1) ** 2 + (y2 - y1) ** 2
    d20 = (x0 - x2) ** 2 + (y0 - y2) ** 2
    return np.sqrt(np.maximum(np.maximum(d01, d12), d20))


def _depth_sigma(cov: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """Each point's depth (Z) standard deviation, mm, from its covariance (0 where unknown)."""
    if cov.shape[0] != n or n == 0:
        return np.zeros(n)
    var = np.asarray(cov[:, 2, 2], dtype=np.float64)
    return np.sqrt(np.where(np.isfinite(var) & (var > 0), var, 0.0))


def _any_within(
    x_mm: NDArray[np.float64], y_mm: NDArray[np.float64], pts: NDArray[np.float64], reach_mm: float
) -> NDArray[np.bool_]:
    """For each place (x_mm, y_mm): whether any of ``pts`` (M, 2) mm lies within ``reach_mm``.
    Only the points in the places' bounding box grown by the reach are compared, 1024 at a time
    (the places × points distances stay a few MB)."""
    hit = np.zeros(len(x_mm), dtype=bool)
    if len(x_mm) == 0:
        return hit
    box = (
        (pts[:, 0] >= x_mm.min() - reach_mm)
        & (pts[:, 0] <= x_mm.max() + reach_mm)
        & (pts[:, 1] >= y_mm.min() - reach_mm)
        & (pts[:, 1] <= y_mm.max() + reach_mm)
    )
    pts = pts[box]
    r2 = reach_mm * reach_mm
    for k in range(0, len(pts), 1024):
        q = pts[k : k + 1024]
        e2 = (x_mm[:, None] - q[None, :, 0]) ** 2 + (y_mm[:, None] - q[None, :, 1]) ** 2
        hit |= e2.min(axis=1) <= r2
    return hit


def _delaunay(xy: NDArray[np.float64]) -> NDArray[np.intp]:
    """Delaunay triangles (T, 3) of indices into 2-D points ``xy`` (N, 2) (cv2.Subdiv2D).
    The points are snapped to 1/16 mm first (exact in float32 on the map's scale): Subdiv2D
    builds a zero-area triangle from two points a rounding error apart (6e-24 mm) and then
    fails to locate the next point; snapped, they are one vertex."""
    import cv2

    pts = (np.round(xy * 16.0) / 16.0).astype(np.float32)
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


# -- the laser lattice ------------------------------------------------------------------------
#
# The laser source sits at the rig origin (SPEC §2), so a dot's slopes (X/Z, Y/Z) name its ray
# whatever it hit: in slope space the dots of one capture form the projector's lattice, rows of
# nearly equal X/Z. Neighbours come from that structure — adjacent rows stitched into triangle
# strips — instead of a Delaunay triangulation of every capture, and a run of strip triangles of
# one state is one polygon for cv2.fillPoly (a few dozen polygons instead of thousands).


def _row_breaks(u_sorted: NDArray[np.float64]) -> NDArray[np.bool_] | None:
    """Where sorted row slopes X/Z jump to the next lattice row: (N−1,) bool, or None when the
    slopes show no clear row structure (then the caller triangulates generally).

    Gaps between rows are a lattice step; gaps within a row are measurement noise, far smaller.
    The split is the cliff in the gaps sorted from large to small — the last ratio of ≥ 4
    between consecutive ones (among the larger half, so a row holds two dots on average) — which
    tolerates missing rows and outliers (several steps) above it.
    """
    gaps = np.diff(u_sorted)
    m = len(gaps)
    if m < 3:
        return None
    desc = np.sort(gaps)[::-1]
    floor = max(1e-3 * float(desc[0]), 1e-12)
    top = np.maximum(desc[: m // 2 + 1], floor)
    nxt = np.maximum(desc[1 : m // 2 + 2], floor)
    cliff = np.flatnonzero(top >= 4.0 * nxt)
    if len(cliff) == 0:
        return None
    k = int(cliff[-1])
    return gaps > math.sqrt(float(top[k]) * float(nxt[k]))


@dataclass(frozen=True)
class _Strips:
    """Triangle strips between adjacent lattice rows, in strip order.

    tri        (T, 3) point indices of each triangle
    strip      (T,) strip (row pair) of each triangle; consecutive triangles of one strip share
               an edge
    a_lo, a_hi (T,) ranks in ``a_chain`` of the near-row end points of the triangle's left and
               right rungs (the edges it shares with its strip neighbours)
    b_lo, b_hi (T,) likewise in ``b_chain`` for the far row
    a_chain    point indices of every strip's near row in order along the row, strip after strip
    b_chain    likewise for the far rows
    flip       (T,) −1.0 where the triangle's second edge runs along the far row, which turns
               its corner order the other way round than the near-row ones, else 1.0
    """

    tri: NDArray[np.intp]
    strip: NDArray[np.intp]
    a_lo: NDArray[np.intp]
    a_hi: NDArray[np.intp]
    b_lo: NDArray[np.intp]
    b_hi: NDArray[np.intp]
    a_chain: NDArray[np.intp]
    b_chain: NDArray[np.intp]
    flip: NDArray[np.float64]
    row_order: NDArray[np.intp]
    row_starts: NDArray[np.intp]
    a_same: NDArray[np.bool_]
    b_same: NDArray[np.bool_]

    def fits(self, u: NDArray[np.float64], v: NDArray[np.float64]) -> bool:
        """Whether these strips still triangulate dots at slopes ``u``, ``v`` (as many as they
        were built for): every row still lies apart from the next one by more than a row's own
        spread, and every row is still in order along v. Then the strips are a valid
        triangulation of the new dots whichever rays they are — no need to build them again.
        """
        if len(u) != len(self.row_order):
            return False
        if np.any(np.diff(v[self.a_chain])[self.a_same] <= 0):
            return False
        if np.any(np.diff(v[self.b_chain])[self.b_same] <= 0):
            return False
        us = u[self.row_order]
        lo = np.minimum.reduceat(us, self.row_starts)
        hi = np.maximum.reduceat(us, self.row_starts)
        return bool(np.all(lo[1:] - hi[:-1] > np.max(hi - lo)))


def _lattice_strips(u: NDArray[np.float64], v: NDArray[np.float64]) -> _Strips | None:
    """Triangle strips of dots at ray slopes u = X/Z (along rows), v = Y/Z; None without rows.

    Rows come from :func:`_row_breaks`; each pair of adjacent rows, both ordered by v, is
    stitched like a zipper: walking both rows in merged v order, every dot after the first of
    its row closes a triangle with its predecessor and the other row's latest dot. A pair of
    rows of a and b dots gives a + b − 2 triangles, O(N log N) in all.
    """
    n = len(u)
    order = np.argsort(u, kind="stable")
    breaks = _row_breaks(u[order])
    if breaks is None:
        return None
    row = np.empty(n, dtype=np.intp)
    row[order] = np.concatenate([[0], np.cumsum(breaks)])
    rows = int(row.max()) + 1
    if rows < 2:
        return None
    # Every dot joins the strip above its row (as a near-row dot, tag 0) and the strip below it
    # (as a far-row dot, tag 1); sorted by strip, then v.
    near = np.flatnonzero(row < rows - 1)
    far = np.flatnonzero(row > 0)
    strip = np.concatenate([row[near], row[far] - 1])
    tag = np.concatenate([np.zeros(len(near), np.int8), np.ones(len(far), np.int8)])
    pt = np.concatenate([near, far])
    vv = v[pt]
    lo, span = float(vv.min()), float(vv.max() - vv.min()) + 1.0
    o = np.argsort(strip * span + (vv - lo), kind="stable")  # near-row dot first on a tie
    strip, tag, pt = strip[o], tag[o], pt[o]
    m = len(pt)
    pos = np.arange(m)
    is_a = tag == 0
    start = np.searchsorted(strip, np.arange(rows - 1))[strip]  # first element of the strip
    last_a = np.maximum.accumulate(np.where(is_a, pos, -1))
    last_b = np.maximum.accumulate(np.where(is_a, -1, pos))
    a_pos, b_pos = np.flatnonzero(is_a), np.flatnonzero(~is_a)
    # First near-row and far-row element of each strip (every strip has dots of both rows).
    a_strip, b_strip = strip[a_pos], strip[b_pos]
    first_a = a_pos[np.concatenate([[True], a_strip[1:] != a_strip[:-1]])][strip]
    first_b = b_pos[np.concatenate([[True], b_strip[1:] != b_strip[:-1]])][strip]
    cur_a = np.where(last_a >= start, last_a, first_a)
    cur_b = np.where(last_b >= start, last_b, first_b)
    prev_a = np.concatenate([[-1], last_a[:-1]])
    prev_b = np.concatenate([[-1], last_b[:-1]])
    make_a = is_a & (prev_a >= start)  # a near-row dot after the first of its strip
    make_b = ~is_a & (prev_b >= start)
    k = np.flatnonzero(make_a | make_b)
    ka = make_a[k]
    # Rungs (near dot, far dot) on the left and right of each triangle, as merged positions.
    left_a = np.where(ka, prev_a[k], cur_a[k])
    left_b = np.where(ka, cur_b[k], prev_b[k])
    right_a = np.where(ka, k, cur_a[k])
    right_b = np.where(ka, cur_b[k], k)
    third = np.where(ka, cur_b[k], cur_a[k])
    tri = np.column_stack([pt[np.where(ka, prev_a[k], prev_b[k])], pt[k], pt[third]])
    rank_a = np.cumsum(is_a) - 1
    rank_b = np.cumsum(~is_a) - 1
    return _Strips(
        tri=tri.astype(np.intp),
        strip=strip[k],
        a_lo=rank_a[left_a],
        a_hi=rank_a[right_a],
        b_lo=rank_b[left_b],
        b_hi=rank_b[right_b],
        a_chain=pt[a_pos],
        b_chain=pt[b_pos],
        flip=np.where(ka, 1.0, -1.0),
        row_order=order,
        row_starts=np.flatnonzero(np.concatenate([[True], breaks])),
        a_same=a_strip[1:] == a_strip[:-1],
        b_same=b_strip[1:] == b_strip[:-1],
    )


def _fill_strips(
    obs: NDArray[np.uint8],
    s: _Strips,
    value: NDArray[np.uint8],
    pix: NDArray[np.float64],
    fixed: NDArray[np.int32],
    paint: tuple[int, ...],
    cv2,
) -> None:
    """Paint the triangles of ``s`` (corner pixels ``pix``, and the same in fixed point with
    :data:`_SHIFT` fractional bits, ``fixed``) into ``obs``: each with its ``value`` (T,)
    (0: not painted), the values in the order ``paint`` (a later one wins).

    Each run of consecutive triangles of one value in a strip, turned the strip's way, is one
    polygon (near row out, far row back). cv2.fillPoly fills several polygons even-odd, so
    polygons that overlap must not share a call: runs of odd and even strips (neighbours overlap
    where noise folds two rows) go in separate calls, and a triangle turned over or flat goes on
    its own.
    """
    used = np.flatnonzero(value)
    if len(used) == 0:
        return
    t0, t1, t2 = s.tri[:, 0][used], s.tri[:, 1][used], s.tri[:, 2][used]
    px, py = pix[:, 0], pix[:, 1]
    x0, x1, x2 = px[t0], px[t1], px[t2]
    y0, y1, y2 = py[t0], py[t1], py[t2]
    area2 = ((x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)) * s.flip[used]
    sign = 1.0 if float(np.sum(area2)) >= 0 else -1.0
    ok = sign * area2 > 1e-9
    # Turned-over triangles: by value, and in four calls so that no two neighbours share one.
    single = np.flatnonzero(~ok)
    single_polys = np.stack([fixed[t0[single]], fixed[t1[single]], fixed[t2[single]]], axis=1)
    single_group = (
        value[used[single]].astype(np.intp) * 4 + (s.strip[used[single]] % 2) * 2 + single % 2
    )
    by_group = np.argsort(single_group, kind="stable")
    single_polys, single_group = single_polys[by_group], single_group[by_group]
    t = used[ok]
    runs: list[NDArray[np.int32]] = []
    group = np.zeros(0, dtype=np.intp)
    if len(t):
        # A run breaks where the next good triangle is not the next one of the strip, or differs.
        tv = value[t]
        cont = (np.diff(t) == 1) & (s.strip[t[1:]] == s.strip[t[:-1]]) & (tv[1:] == tv[:-1])
        first = t[np.concatenate([[True], ~cont])]
        last = t[np.concatenate([~cont, [True]])]
        # Group the runs by value and strip parity: one fillPoly call per group.
        group = value[first].astype(np.intp) * 2 + s.strip[first] % 2
        by_group = np.argsort(group, kind="stable")
        first, last, group = first[by_group], last[by_group], group[by_group]
        a0, a1 = s.a_lo[first], s.a_hi[last]
        b0, b1 = s.b_lo[first], s.b_hi[last]
        len_a = a1 - a0 + 1
        length = len_a + (b1 - b0 + 1)
        ends = np.cumsum(length)
        starts = ends - length
        offset = np.arange(int(ends[-1]) if len(ends) else 0) - np.repeat(starts, length)
        in_a = offset < np.repeat(len_a, length)
        from_a = np.minimum(np.repeat(a0, length) + offset, len(s.a_chain) - 1)
        from_b = np.clip(np.repeat(b1 + len_a, length) - offset, 0, len(s.b_chain) - 1)
        idx = np.where(in_a, s.a_chain[from_a], s.b_chain[from_b])
        flat = fixed[idx]
        runs = [flat[i:j] for i, j in zip(starts.tolist(), ends.tolist(), strict=True)]
    top = 4 * max(paint) + 5
    bounds = np.searchsorted(group, np.arange(top)).tolist()
    single_bounds = np.searchsorted(single_group, np.arange(top)).tolist()
    for v in paint:
        for g in (2 * v, 2 * v + 1):
            if bounds[g + 1] > bounds[g]:
                cv2.fillPoly(obs, runs[bounds[g] : bounds[g + 1]], v, cv2.LINE_8, _SHIFT)
        for g in range(4 * v, 4 * v + 4):
            if single_bounds[g + 1] > single_bounds[g]:
                polys = list(single_polys[single_bounds[g] : single_bounds[g + 1]])
                cv2.fillPoly(obs, polys, v, cv2.LINE_8, _SHIFT)


def classified(cloud: PointCloud, classes: ArrayLike) -> PointCloud:
    """``cloud`` with its ``classes`` replaced (a convenience for callers and tests)."""
    return replace(cloud, classes=np.asarray(classes, dtype=np.uint8))
