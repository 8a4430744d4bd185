"""What a simulated run produced (:class:`SimResult`), and the truth measures it is judged by.

:func:`clearance_mm` and :func:`footprint_perimeter` measure how close the chair's footprint
came to a box or a drop-off edge in the simulated world (truth, not what perception saw); the
run loop, ``omnid simulate --serve`` and the safety figures use them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from omnid.sim.chair import Chair, Contact
from omnid.sim.faults import Fault
from omnid.sim.story import StepRecord
from omnid.sim.world import World


@dataclass
class SimResult:
    """What happened in a run. Times are virtual seconds; ``timings`` are wall-clock figures."""

    duration_s: float
    trajectory: NDArray[np.float64]  # (N, 4) t_s, x_mm, y_mm, theta_rad
    commands: NDArray[np.float64]  # (M, 5) t_s, left_duty, right_duty, laser_on, enable
    contacts: list[tuple[float, Contact]]
    refusals: list[tuple[float, str]]
    seen: NDArray[np.float64]  # (K, 3) world x_mm, y_mm, PointClass code of non-floor points
    min_clearance_mm: float  # closest the footprint came to a box or a drop-off edge
    timings: dict[str, float] = field(default_factory=dict)
    wheel_speeds: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    # (N, 3) t_s, left, right wheel surface speed mm/s, every physics tick
    faults: tuple[Fault, ...] = ()
    perception_errors: list[tuple[float, str]] = field(default_factory=list)
    steps: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 7)))
    # (M, 7) every control step: t_s, reason bit mask (bit i = reason_names[i]), x_mm, y_mm,
    # theta_rad (true pose), mean wheel surface speed mm/s (true), rider's forward demand [-1, 1]
    reason_names: tuple[str, ...] = ()
    story: list[StepRecord] = field(default_factory=list)  # a reactive rider's steps

    def reasons_at(self, i: int) -> list[str]:
        """The reasons the controller gave at control step ``i`` (row of :attr:`steps`)."""
        mask = int(self.steps[i, 1])
        return [n for b, n in enumerate(self.reason_names) if mask >> b & 1]

    def reason_mask(self, *names: str) -> int:
        """The bit mask of ``names`` in :attr:`steps` (0 for a reason that never occurred)."""
        return sum(1 << b for b, n in enumerate(self.reason_names) if n in names)

    def time_to_standstill(self, t0_s: float, speed_tol_mm_s: float = 1.0) -> float:
        """Seconds from ``t0_s`` until both wheels turn slower than ``speed_tol_mm_s`` (and stay
        so for 0.1 s); ``inf`` if they never do."""
        w = self.wheel_speeds
        after = w[w[:, 0] >= t0_s - 1e-9]
        still = np.all(np.abs(after[:, 1:]) < speed_tol_mm_s, axis=1)
        for i in np.flatnonzero(still):
            t = after[i, 0]
            window = after[(after[:, 0] >= t) & (after[:, 0] <= t + 0.1)]
            if np.all(np.abs(window[:, 1:]) < speed_tol_mm_s) and len(window) > 1:
                return float(t - t0_s)
        return math.inf

    def max_speed_between(self, t0_s: float, t1_s: float) -> float:
        """Fastest wheel surface speed (mm/s, absolute) between the two times."""
        w = self.wheel_speeds
        sel = w[(w[:, 0] >= t0_s) & (w[:, 0] <= t1_s)]
        return float(np.abs(sel[:, 1:]).max()) if len(sel) else 0.0

    @property
    def collisions(self) -> list[tuple[float, Contact]]:
        return [c for c in self.contacts if c[1].kind == "collision"]

    @property
    def falls(self) -> list[tuple[float, Contact]]:
        return [c for c in self.contacts if c[1].kind == "fall"]

    @property
    def distance_mm(self) -> float:
        """Path length of the axle midpoint, mm."""
        if len(self.trajectory) < 2:
            return 0.0
        return float(np.sum(np.hypot(*np.diff(self.trajectory[:, 1:3], axis=0).T)))


def footprint_perimeter(chair: Chair, per_side: int = 6) -> NDArray[np.float64]:
    """Points (4·per_side, 2) along the edge of the chair's footprint, world mm."""
    c = chair.footprint()
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)[:, None]
    return np.vstack([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])


def clearance_mm(points: NDArray[np.float64], rects: NDArray[np.float64]) -> float:
    """Smallest distance from any point (N, 2) to any rectangle (R, 4: x0, x1, y0, y1), mm."""
    if len(rects) == 0:
        return math.inf
    dx = np.maximum(
        np.maximum(rects[None, :, 0] - points[:, None, 0], 0.0),
        points[:, None, 0] - rects[None, :, 1],
    )
    dy = np.maximum(
        np.maximum(rects[None, :, 2] - points[:, None, 1], 0.0),
        points[:, None, 1] - rects[None, :, 3],
    )
    return float(np.hypot(dx, dy).min())


def world_rects(world: World) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The boxes and the drop-offs of ``world`` as rectangles (R, 4: x0, x1, y0, y1), mm."""
    boxes = [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm) for b in world.boxes]
    drops = [(d.x_min_mm, d.x_max_mm, d.y_min_mm, d.y_max_mm) for d in world.dropoffs]
    return (
        np.array(boxes, dtype=np.float64).reshape(-1, 4),
        np.array(drops, dtype=np.float64).reshape(-1, 4),
    )


def chair_clearance_mm(
    chair: Chair, box_rects: NDArray[np.float64], drop_rects: NDArray[np.float64]
) -> float:
    """How near the chair is to a box (its footprint's edge) or a drop-off (its wheels and
    casters: the support points), mm; ``inf`` with neither in the world."""
    supports = np.array(list(chair.support_points().values()))
    return min(
        clearance_mm(footprint_perimeter(chair), box_rects), clearance_mm(supports, drop_rects)
    )
