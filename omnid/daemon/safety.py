"""The safety layer: a command runs only if it is safe in the free-space map (thesis 4.1.2).

The chair's footprint (a rectangle in the robot frame, plus a margin) is swept along the
commanded motion — a straight line, an arc or a turn in place, exactly as the wheels would move
it (:func:`omnid.core.kinematics.integrate_arc`) — over a look-ahead horizon, and checked
against an :class:`~omnid.core.occupancy.OccupancyGrid`. Obstacles and drop-offs both block.
The path parameter ``s`` is the travel of the footprint's fastest point (the axle midpoint on a
straight line, the farthest corner when turning in place), so one set of distances serves every
kind of motion. From the first blocked ``s`` (``clearance``) come:

- stop zone: clearance ≤ ``stop_distance_mm`` → no motion in that direction;
- slow zone: clearance ≤ ``slow_distance_mm`` → at most ``slow_speed_mm_s``;
- approach: time to reach the stop line ≥ ``approach_time_s``, and the chair can still brake
  before it at ``brake_decel_mm_s2``;
- unknown space: if more than ``unknown_max_fraction`` of the swept cells within
  ``unknown_distance_mm`` are unknown → at most ``unknown_speed_mm_s``;
- stale perception (no cloud, or older than ``perception_timeout_s``) → no forward motion.

The most restrictive limit wins; the rider's v and ω are scaled by one factor, so the chair keeps
the path the rider asked for. Cells under the chair's own footprint at the start are ignored:
the vision system cannot see there, and the chair physically occupies them.

Every limitation comes with :class:`Reason` codes and is logged (rate-limited per reason, see
:class:`ReasonLog`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.kinematics import integrate_arc
from omnid.core.occupancy import CellState, OccupancyGrid

log = logging.getLogger(__name__)


class Reason(Enum):
    """Why the safety layer (or the core) limited or refused a command."""

    OBSTACLE_STOP = "obstacle_stop"
    DROPOFF_STOP = "dropoff_stop"
    SLOW_ZONE = "slow_zone"
    APPROACH = "approach"
    UNKNOWN_AHEAD = "unknown_ahead"
    PERCEPTION_STALE = "perception_stale"
    RIDER_STOP = "rider_stop"
    INPUT_STALE = "input_stale"
    STATUS_STALE = "status_stale"
    FAULT = "fault"


@dataclass(frozen=True)
class SafetySettings:
    """Footprint (mm, robot frame: axle midpoint origin), zones and limits."""

    footprint_front_mm: float = 350.0  # from the axle forward (drive wheels are at the front)
    footprint_rear_mm: float = 750.0  # from the axle backward (castors)
    footprint_width_mm: float = 700.0
    margin_mm: float = 50.0  # added on every side
    horizon_mm: float = 2500.0  # look-ahead along the path (fastest footprint point)
    stop_distance_mm: float = 150.0
    slow_distance_mm: float = 600.0
    slow_speed_mm_s: float = 100.0
    approach_time_s: float = 2.0  # time to the stop line must be at least this
    brake_decel_mm_s2: float = 600.0  # the chair must be able to stop before the stop line
    unknown_distance_mm: float = 1000.0
    unknown_max_fraction: float = 0.3
    unknown_speed_mm_s: float = 120.0
    perception_timeout_s: float = 1.5
    log_interval_s: float = 2.0  # one log line per reason at most this often

    def __post_init__(self) -> None:
        for name in (
            "footprint_front_mm",
            "footprint_rear_mm",
            "footprint_width_mm",
            "horizon_mm",
            "stop_distance_mm",
            "slow_speed_mm_s",
            "approach_time_s",
            "brake_decel_mm_s2",
            "unknown_speed_mm_s",
            "perception_timeout_s",
            "log_interval_s",
        ):
            require(getattr(self, name) > 0, name, "must be positive")
        require(self.margin_mm >= 0, "margin_mm", "must not be negative")
        require(
            self.slow_distance_mm >= self.stop_distance_mm,
            "slow_distance_mm",
            "must not be below stop_distance_mm",
        )
        require(
            self.horizon_mm > self.slow_distance_mm,
            "horizon_mm",
            "must exceed slow_distance_mm",
        )
        require(0 <= self.unknown_max_fraction <= 1, "unknown_max_fraction", "must be in [0, 1]")
        require(self.unknown_distance_mm >= 0, "unknown_distance_mm", "must not be negative")


@dataclass(frozen=True)
class SafetyDecision:
    """The allowed twist and why it differs from the request."""

    v_mm_s: float
    omega_rad_s: float
    scale: float  # allowed / requested, in [0, 1]
    clearance_mm: float  # free travel of the fastest footprint point (inf: nothing in horizon)
    reasons: tuple[Reason, ...] = ()

    @property
    def stopped(self) -> bool:
        return self.scale == 0.0


class ReasonLog:
    """Logs each reason at most once per ``interval_s`` (counts what it suppressed)."""

    def __init__(self, logger: logging.Logger, interval_s: float) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self.suppressed = 0

    def log(self, reason: str, message: str, now_s: float, level: int = logging.WARNING) -> bool:
        last = self._last.get(reason)
        if last is not None and now_s - last < self.interval_s:
            self.suppressed += 1
            return False
        self._last[reason] = now_s
        self.logger.log(level, "%s: %s", reason, message)
        return True


class SafetyLayer:
    """Checks requested twists against a grid (see the module docstring)."""

    def __init__(self, settings: SafetySettings) -> None:
        self.settings = settings
        s = settings
        m = s.margin_mm
        self._x0, self._x1 = -s.footprint_rear_mm - m, s.footprint_front_mm + m
        self._y0 = -0.5 * s.footprint_width_mm - m
        self._y1 = -self._y0
        corners = np.array(
            [[self._x0, self._y0], [self._x0, self._y1], [self._x1, self._y0], [self._x1, self._y1]]
        )
        self.r_max_mm = float(np.max(np.hypot(corners[:, 0], corners[:, 1])))
        self._pts_cache: tuple[float, NDArray[np.float64]] | None = None
        self.log = ReasonLog(log, s.log_interval_s)

    def footprint_points(self, spacing_mm: float) -> NDArray[np.float64]:
        """Points (N, 2) mm on the footprint's outline (with margin) at ``spacing_mm``.

        The outline suffices: the footprint's interior at the start is ignored, and anything the
        moving footprint covers later has crossed its outline first (poses are sampled at half a
        cell along the path).
        """
        if self._pts_cache is not None and self._pts_cache[0] == spacing_mm:
            return self._pts_cache[1]
        nx = max(math.ceil((self._x1 - self._x0) / spacing_mm), 1) + 1
        ny = max(math.ceil((self._y1 - self._y0) / spacing_mm), 1) + 1
        xs = np.linspace(self._x0, self._x1, nx)
        ys = np.linspace(self._y0, self._y1, ny)
        pts = np.concatenate(
            [
                np.column_stack([xs, np.full(nx, self._y0)]),
                np.column_stack([xs, np.full(nx, self._y1)]),
                np.column_stack([np.full(ny, self._x0), ys]),
                np.column_stack([np.full(ny, self._x1), ys]),
            ]
        )
        self._pts_cache = (spacing_mm, pts)
        return pts

    def inside_footprint(self, xy_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether robot-frame points (N, 2) lie in the current footprint (with margin)."""
        return (
            (xy_mm[:, 0] >= self._x0)
            & (xy_mm[:, 0] <= self._x1)
            & (xy_mm[:, 1] >= self._y0)
            & (xy_mm[:, 1] <= self._y1)
        )

    def sweep(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float
    ) -> tuple[float, CellState | None, float]:
        """Sweep the footprint along the motion direction of (v, ω).

        Returns (clearance_mm, blocking state or None, unknown fraction within
        ``unknown_distance_mm``). Clearance is the path parameter s of the first blocked pose
        (``inf`` if none within the horizon).
        """
        s = self.settings
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm  # speed of the fastest point
        if u <= 0.0:
            return math.inf, None, 0.0
        res = grid.settings.resolution_mm
        step = 0.5 * res
        ss = np.arange(step, s.horizon_mm + step, step)
        track = 2.0  # any positive track: the wheel travels below reproduce (v, ω) exactly
        ds = ss * (v_mm_s / u)
        dth = ss * (omega_rad_s / u)
        dl = ds - dth * track / 2
        dr = ds + dth * track / 2
        poses = integrate_arc(np.zeros(3), dl, dr, track)  # (K, 3)
        pts = self.footprint_points(0.5 * res)
        c, sn = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        wx = poses[:, 0, None] + c[:, None] * pts[None, :, 0] - sn[:, None] * pts[None, :, 1]
        wy = poses[:, 1, None] + sn[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1]
        flat = np.column_stack([wx.ravel(), wy.ravel()])
        states = grid.state_at(flat).reshape(wx.shape)
        own = self.inside_footprint(flat).reshape(wx.shape)
        blocked = ((states == CellState.OBSTACLE) | (states == CellState.DROPOFF)) & ~own
        hit_rows = np.nonzero(blocked.any(axis=1))[0]
        clearance, state = math.inf, None
        if hit_rows.size:
            k = int(hit_rows[0])
            clearance = float(ss[k] - step)  # last pose known free
            row_states = states[k][blocked[k]]
            state = (
                CellState.DROPOFF if np.any(row_states == CellState.DROPOFF) else CellState.OBSTACLE
            )
        near = (ss <= s.unknown_distance_mm)[:, None] & ~own
        if hit_rows.size:
            near &= (ss < ss[int(hit_rows[0])])[:, None]
        n_near = int(near.sum())
        unknown = float((states[near] == CellState.UNKNOWN).sum() / n_near) if n_near else 0.0
        return clearance, state, unknown

    def check(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        perception_age_s: float | None,
        now_s: float = 0.0,
    ) -> SafetyDecision:
        """The allowed twist for a requested (v mm/s, ω rad/s), given the map and its age (s)."""
        s = self.settings
        if not (math.isfinite(v_mm_s) and math.isfinite(omega_rad_s)):
            return self._report(SafetyDecision(0.0, 0.0, 0.0, 0.0, (Reason.FAULT,)), now_s)
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm
        if u == 0.0:
            return SafetyDecision(0.0, 0.0, 1.0, math.inf)
        reasons: list[Reason] = []
        caps = [math.inf]
        stale = perception_age_s is None or perception_age_s > s.perception_timeout_s
        if stale and v_mm_s > 0:
            reasons.append(Reason.PERCEPTION_STALE)
            caps.append(0.0)
        clearance, state, unknown = self.sweep(grid, v_mm_s, omega_rad_s)
        if clearance <= s.stop_distance_mm:
            reasons.append(
                Reason.DROPOFF_STOP if state is CellState.DROPOFF else Reason.OBSTACLE_STOP
            )
            caps.append(0.0)
        elif math.isfinite(clearance):
            room = clearance - s.stop_distance_mm
            if clearance <= s.slow_distance_mm and u > s.slow_speed_mm_s:
                reasons.append(Reason.SLOW_ZONE)
                caps.append(s.slow_speed_mm_s)
            cap = min(room / s.approach_time_s, math.sqrt(2.0 * s.brake_decel_mm_s2 * room))
            if u > cap:
                reasons.append(Reason.APPROACH)
                caps.append(cap)
        if unknown > s.unknown_max_fraction and u > s.unknown_speed_mm_s:
            reasons.append(Reason.UNKNOWN_AHEAD)
            caps.append(s.unknown_speed_mm_s)
        scale = min(1.0, min(caps) / u)
        decision = SafetyDecision(
            v_mm_s * scale, omega_rad_s * scale, scale, clearance, tuple(reasons)
        )
        return self._report(decision, now_s)

    def _report(self, d: SafetyDecision, now_s: float) -> SafetyDecision:
        for r in d.reasons:
            self.log.log(
                r.value,
                f"speed limited to {100 * d.scale:.0f}% (clearance {d.clearance_mm:.0f} mm)",
                now_s,
            )
        return d
