"""The robot-centred free-space grid the safety layer queries (thesis 7.1.2, 7.2.2; SPEC §3).

Robot frame (used by the grid, the kinematics and the odometry): origin at the midpoint of the
drive-wheel axle on the floor, x forward, y **left**, heading θ counter-clockwise seen from above
(REP-103). The vision rig frame of SPEC §2 (X forward, Y right along the baseline, Z down) maps to
it by :func:`rig_to_robot` with the rig's mounting offset.

Cells hold a :class:`CellState`. Row index i runs along x, column j along y:
cell (i, j) covers x ∈ [x_min + i·res, x_min + (i+1)·res), y ∈ [y_min + j·res, ...).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.config import Settings, require, setting


class CellState(IntEnum):
    """What the map knows of a cell."""

    UNKNOWN = 0
    FREE = 1
    OBSTACLE = 2
    DROPOFF = 3


@dataclass(frozen=True)
class GridSettings(Settings):
    """Size and resolution of the robot-centred grid (mm)."""

    resolution_mm: float = setting(50.0, 5.0, 500.0)
    x_min_mm: float = setting(-2000.0, -20000.0, 20000.0)
    x_max_mm: float = setting(4000.0, -20000.0, 20000.0)
    y_min_mm: float = setting(-3000.0, -20000.0, 20000.0)
    y_max_mm: float = setting(3000.0, -20000.0, 20000.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(self.x_max_mm > self.x_min_mm, "x_max_mm", "must exceed x_min_mm")
        require(self.y_max_mm > self.y_min_mm, "y_max_mm", "must exceed y_min_mm")

    @property
    def shape(self) -> tuple[int, int]:
        """(cells along x, cells along y)."""
        nx = int(np.ceil((self.x_max_mm - self.x_min_mm) / self.resolution_mm))
        ny = int(np.ceil((self.y_max_mm - self.y_min_mm) / self.resolution_mm))
        return nx, ny


def rig_to_robot(xyz_rig_mm: ArrayLike, rig_x_offset_mm: float = 0.0) -> NDArray[np.float64]:
    """Rig-frame points (N, 3) → robot-frame (x, y) mm: x = X + offset, y = −Y."""
    p = np.asarray(xyz_rig_mm, dtype=np.float64).reshape(-1, 3)
    return np.column_stack([p[:, 0] + rig_x_offset_mm, -p[:, 1]])


class OccupancyGrid:
    """A robot-centred grid of :class:`CellState` values (int8 array ``states``)."""

    def __init__(self, settings: GridSettings | None = None) -> None:
        self.settings = settings or GridSettings()
        self.states: NDArray[np.int8] = np.full(self.settings.shape, CellState.UNKNOWN, np.int8)

    def cell_index(
        self, xy_mm: ArrayLike
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
        """Robot-frame points (N, 2) mm → (i, j, inside): cell indices and whether in the grid."""
        q = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        s = self.settings
        with np.errstate(invalid="ignore"):
            fi = np.floor((q[:, 0] - s.x_min_mm) / s.resolution_mm)
            fj = np.floor((q[:, 1] - s.y_min_mm) / s.resolution_mm)
        nx, ny = self.states.shape
        inside = (fi >= 0) & (fi < nx) & (fj >= 0) & (fj < ny)
        i = np.where(inside, fi, 0).astype(np.intp)
        j = np.where(inside, fj, 0).astype(np.intp)
        return i, j, inside

    def cell_centers(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """x (nx,) and y (ny,) of the cell centres, mm."""
        s = self.settings
        nx, ny = self.states.shape
        xs = s.x_min_mm + (np.arange(nx, dtype=np.float64) + 0.5) * s.resolution_mm
        ys = s.y_min_mm + (np.arange(ny, dtype=np.float64) + 0.5) * s.resolution_mm
        return xs.astype(np.float64), ys.astype(np.float64)

    def state_at(self, xy_mm: ArrayLike) -> NDArray[np.int8]:
        """State of the cell under each robot-frame point (N, 2) mm; UNKNOWN outside the grid."""
        i, j, inside = self.cell_index(xy_mm)
        return np.where(inside, self.states[i, j], np.int8(CellState.UNKNOWN)).astype(np.int8)

    def mark(self, xy_mm: ArrayLike, state: CellState) -> None:
        """Set the cells under robot-frame points (N, 2) mm to ``state`` (points outside: ignored)."""
        i, j, inside = self.cell_index(xy_mm)
        self.states[i[inside], j[inside]] = state
