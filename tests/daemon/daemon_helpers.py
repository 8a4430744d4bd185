"""Helpers of the daemon tests: value types standing in for device readings, a simple map.

``RecordingMap`` stands in for ``omnid.core.freespace.FreeSpaceMap`` (owned by the map
engineer) until it lands on main: it marks the classified points of each cloud and records the
motions it is given, which is all the core's contract needs of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnid.core.occupancy import CellState, GridSettings, OccupancyGrid, rig_to_robot
from omnid.core.types import PointClass, PointCloud


@dataclass(frozen=True)
class Tilt:
    roll_deg: float
    pitch_deg: float
    timestamp_s: float


@dataclass(frozen=True)
class Stick:
    forward: float
    turn: float
    timestamp_s: float


@dataclass(frozen=True)
class Status:
    seq: int
    left_clocks: int
    right_clocks: int
    laser_on: bool
    faults: int
    timestamp_s: float
    left_applied_duty: float = 0.0  # as the unit reports it applies (0: not driving)
    right_applied_duty: float = 0.0


class RecordingMap(OccupancyGrid):
    """Keeps the classified points in continuous robot-frame coordinates and rasterizes them."""

    def __init__(self, settings: GridSettings | None = None) -> None:
        super().__init__(settings or GridSettings(resolution_mm=50.0))
        self.moves: list[tuple[float, float, float]] = []
        self.clouds: list[PointCloud] = []
        self.points = np.zeros((0, 2))
        self.point_states = np.zeros(0, np.int8)

    def _raster(self) -> None:
        self.states[:] = CellState.UNKNOWN
        for state in (CellState.FREE, CellState.DROPOFF, CellState.OBSTACLE):
            self.mark(self.points[self.point_states == state], state)

    def update(
        self, cloud: PointCloud, rig_x_offset_mm: float = 0.0, now_s=None, source_mm=None
    ) -> None:
        self.clouds.append(cloud)
        code = {
            PointClass.FLOOR: CellState.FREE,
            PointClass.OBSTACLE: CellState.OBSTACLE,
            PointClass.DROPOFF: CellState.DROPOFF,
        }
        states = np.array([code[PointClass(int(c))] for c in cloud.classes], np.int8)
        self.points = np.concatenate([self.points, rig_to_robot(cloud.xyz, rig_x_offset_mm)])
        self.point_states = np.concatenate([self.point_states, states])
        self._raster()

    def move(self, dx_mm: float, dy_mm: float, dtheta_rad: float) -> None:
        self.moves.append((dx_mm, dy_mm, dtheta_rad))
        x, y = self.points[:, 0] - dx_mm, self.points[:, 1] - dy_mm
        c, s = np.cos(dtheta_rad), np.sin(dtheta_rad)
        self.points = np.column_stack([c * x + s * y, -s * x + c * y])
        self._raster()


class FreeFloor(OccupancyGrid):
    """A map that holds free floor everywhere, whatever it is told: the chair has seen (or the
    test says so) every cell around it, so that unseen space plays no part."""

    def __init__(self, settings: GridSettings | None = None) -> None:
        super().__init__(settings or GridSettings(resolution_mm=50.0))
        self.states[:] = CellState.FREE

    def update(
        self, cloud: PointCloud, rig_x_offset_mm: float = 0.0, now_s=None, source_mm=None
    ) -> None:
        pass

    def move(self, dx_mm: float, dy_mm: float, dtheta_rad: float) -> None:
        pass


def arm(core, t_s: float = -0.02) -> None:
    """The rider at rest once before a test drives (a continuous source must be seen at rest
    since start before it may drive: ``omnid.daemon.arming``)."""
    core.on_tilt(Tilt(0.0, 0.0, t_s))
    core.on_joystick(Stick(0.0, 0.0, t_s))
    core.step(t_s)


def floor_cloud(obstacle_x_mm: float | None = None, floor_depth_mm: float = 1100.0) -> PointCloud:
    """Floor dots on a 50 mm lattice ahead of the rig, optionally a wall row at X = obstacle."""
    xs = np.arange(-400.0, 3000.0, 50.0)
    ys = np.arange(-1500.0, 1500.0, 50.0)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xyz = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, floor_depth_mm)])
    classes = np.zeros(len(xyz), np.uint8)
    if obstacle_x_mm is not None:
        far = xyz[:, 0] >= obstacle_x_mm
        xyz[far, 2] = floor_depth_mm - 300.0
        classes[far] = PointClass.OBSTACLE
    n = len(xyz)
    return PointCloud(
        xyz=xyz,
        cov=np.zeros((n, 3, 3)),
        pixels=np.zeros((n, 4)),
        classes=classes,
        floor_depth_mm=floor_depth_mm,
    )


def faulty_perceive(capture, calib, method, settings) -> PointCloud:
    """A perceive stand-in for the worker-process tests, steered by mask1[0, 0]:
    1 hangs, 2 kills the process, 3 raises, anything else returns one floor point whose x is
    base1[0, 0] (so a reply can be matched to its request)."""
    import os
    import time

    code = int(capture.mask1[0, 0])
    if code == 1:
        time.sleep(3600)
    if code == 2:
        os._exit(3)
    if code == 3:
        raise ValueError("bad capture")
    return one_floor_point(float(capture.base1[0, 0]))


def half_reply_perceive(capture, calib, method, settings) -> PointCloud:
    """A perceive stand-in for a worker that freezes while it answers: it writes the start of a
    1 MB reply to its pipe to the daemon (the one socket the child holds) and then hangs."""
    import os
    import stat
    import struct
    import time

    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        try:
            if stat.S_ISSOCK(os.fstat(fd).st_mode):
                os.write(fd, struct.pack("!i", 1_000_000) + b"C" * 100)
        except OSError:
            continue
    time.sleep(3600)
    raise AssertionError("unreachable")


def blas_threads_perceive(capture, calib, method, settings) -> PointCloud:
    """A perceive stand-in that reports, as its one point's x, the most threads any OpenBLAS
    in the worker process may use (0: none loaded)."""
    from omnid.daemon.perception_worker import blas_threads

    return one_floor_point(float(max(blas_threads(), default=0)))


def one_floor_point(x_mm: float) -> PointCloud:
    """A cloud of one floor point at (x_mm, 0, 1100) mm: what the perceive stand-ins reply."""
    return PointCloud(
        xyz=np.array([[x_mm, 0.0, 1100.0]]),
        cov=np.zeros((1, 3, 3)),
        pixels=np.zeros((1, 4)),
        classes=np.zeros(1, np.uint8),
        floor_depth_mm=1100.0,
    )
