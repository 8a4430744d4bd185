"""Motion control: comfort ramps, per-wheel speed PI on the clock estimate, odometry (thesis 4.3).

Pipeline of one control cycle::

    allowed twist (v, ω) ──ramp──► ramped twist ──eqs. 3.8/3.9──► wheel targets (mm/s)
        ──feedforward·gain + PI(target − clock speed)──► signed PWM duty per wheel in [-1, 1]

- Ramps (:class:`TwistRamp`): speeding up at ``accel_mm_s2``, slowing at ``decel_mm_s2`` (braking
  may be harder than accelerating), and at ``emergency_decel_mm_s2`` when the stop comes from the
  safety layer or a fault. Turn rate likewise.
- Feedback (:class:`WheelPI`): the feedforward duty is target / ``full_duty_speed_mm_s`` times a
  per-wheel gain — the thesis found its two motors needed individual calibration (4.3.2.2) — and
  a PI on the clock-based wheel speed (:func:`omnid.core.kinematics.window_speed`) trims the rest.
  Anti-windup: the integral is clamped and frozen while the output saturates in the error's
  direction. A zero target with a stopped ramp gives exactly zero duty and clears the integral.
- Odometry (:class:`Odometry`): clock counter differences → wheel travel → exact arc
  (:func:`omnid.core.kinematics.arc_displacement`); the increments feed ``FreeSpaceMap.move``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from omnid.config import Settings, require, setting
from omnid.core.kinematics import (
    MM_PER_CLOCK,
    arc_displacement,
    integrate_arc,
    wheel_speeds,
    window_speed,
)


@dataclass(frozen=True)
class MotionSettings(Settings):
    """Chair geometry, speed limits, ramps and wheel feedback gains."""

    track_mm: float = setting(
        560.0, 200.0, 1500.0
    )  # distance between the drive wheels (L, eqs. 3.8–3.12)
    mm_per_clock: float = setting(MM_PER_CLOCK, 1.0, 200.0)  # 471 mm / 15 holes (thesis 4.3.2.3)
    # 32 rpm · 471 mm ≈ 251 mm/s at full duty (table 4.3)
    max_speed_mm_s: float = setting(240.0, 10.0, 2000.0)
    max_reverse_speed_mm_s: float = setting(100.0, 10.0, 1000.0)
    max_turn_rate_rad_s: float = setting(0.6, 0.05, 3.0)
    accel_mm_s2: float = setting(250.0, 10.0, 3000.0)  # comfort
    decel_mm_s2: float = setting(400.0, 10.0, 5000.0)  # rider-asked slowing
    emergency_decel_mm_s2: float = setting(1200.0, 10.0, 10000.0)  # safety / fault stop
    angular_accel_rad_s2: float = setting(1.0, 0.05, 20.0)
    angular_decel_rad_s2: float = setting(2.0, 0.05, 20.0)
    emergency_angular_decel_rad_s2: float = setting(5.0, 0.05, 50.0)
    full_duty_speed_mm_s: float = setting(
        251.0, 10.0, 3000.0
    )  # wheel speed at duty 1 (feedforward)
    left_gain: float = setting(1.0, 0.2, 5.0)  # per-wheel feedforward calibration
    right_gain: float = setting(1.0, 0.2, 5.0)
    kp_per_mm_s: float = setting(0.0015, 0.0, 0.1)  # duty per mm/s of speed error
    ki_per_mm: float = setting(0.003, 0.0, 0.1)  # duty per mm of integrated error
    integral_limit: float = setting(0.25, 0.0, 1.0)  # |integral term| ≤ this (duty)
    speed_window_s: float = setting(0.6, 0.05, 5.0)  # clock speed estimate window

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.decel_mm_s2 >= self.accel_mm_s2,
            "decel_mm_s2",
            "must be at least accel_mm_s2 (braking may be harder, never softer)",
        )
        require(
            self.emergency_decel_mm_s2 >= self.decel_mm_s2,
            "emergency_decel_mm_s2",
            "must be at least decel_mm_s2",
        )
        require(
            self.emergency_angular_decel_rad_s2 >= self.angular_decel_rad_s2,
            "emergency_angular_decel_rad_s2",
            "must be at least angular_decel_rad_s2",
        )


def _ramp(current: float, target: float, dt_s: float, up: float, down: float) -> float:
    """Move ``current`` toward ``target``: at rate ``up`` away from 0, at ``down`` toward 0."""
    if current != 0.0 and (
        target == 0.0 or math.copysign(1.0, target) != math.copysign(1.0, current)
    ):
        # slowing down, possibly through zero: reach 0 first
        nxt = current - math.copysign(min(abs(current), down * dt_s), current)
        if nxt != 0.0 or target == 0.0:
            return nxt
        return _ramp(0.0, target, dt_s - abs(current) / down, up, down)
    if abs(target) >= abs(current):
        return current + math.copysign(min(abs(target - current), up * dt_s), target - current)
    return current - math.copysign(min(abs(current - target), down * dt_s), current - target)


class TwistRamp:
    """Rate-limited body twist (see the module docstring)."""

    def __init__(self, settings: MotionSettings) -> None:
        self.settings = settings
        self.v_mm_s = 0.0
        self.omega_rad_s = 0.0

    def reset(self) -> None:
        self.v_mm_s = 0.0
        self.omega_rad_s = 0.0

    def step(
        self, v_mm_s: float, omega_rad_s: float, dt_s: float, emergency: bool
    ) -> tuple[float, float]:
        """Advance by ``dt_s`` toward the target twist; returns the ramped (v, ω)."""
        s = self.settings
        v = min(max(v_mm_s, -s.max_reverse_speed_mm_s), s.max_speed_mm_s)
        w = min(max(omega_rad_s, -s.max_turn_rate_rad_s), s.max_turn_rate_rad_s)
        dt = max(0.0, dt_s)
        vdown = s.emergency_decel_mm_s2 if emergency else s.decel_mm_s2
        wdown = s.emergency_angular_decel_rad_s2 if emergency else s.angular_decel_rad_s2
        self.v_mm_s = _ramp(self.v_mm_s, v, dt, s.accel_mm_s2, vdown)
        self.omega_rad_s = _ramp(self.omega_rad_s, w, dt, s.angular_accel_rad_s2, wdown)
        return self.v_mm_s, self.omega_rad_s


class WheelPI:
    """Feedforward + PI on one wheel's speed, output a signed duty in [-1, 1]."""

    def __init__(self, gain: float, settings: MotionSettings) -> None:
        self.gain = gain
        self.settings = settings
        self.integral = 0.0

    def reset(self) -> None:
        self.integral = 0.0

    def step(self, target_mm_s: float, measured_mm_s: float, dt_s: float) -> float:
        s = self.settings
        if target_mm_s == 0.0:
            self.integral = 0.0
            return 0.0
        ff = self.gain * target_mm_s / s.full_duty_speed_mm_s
        err = target_mm_s - measured_mm_s
        unclamped = ff + s.kp_per_mm_s * err + self.integral
        saturated_same_way = abs(unclamped) >= 1.0 and math.copysign(
            1.0, unclamped
        ) == math.copysign(1.0, err)
        if not saturated_same_way:
            self.integral += s.ki_per_mm * err * dt_s
            self.integral = min(max(self.integral, -s.integral_limit), s.integral_limit)
        duty = ff + s.kp_per_mm_s * err + self.integral
        # never drive a wheel against its own target direction (no plugging)
        if duty * target_mm_s < 0:
            duty = 0.0
        return float(min(max(duty, -1.0), 1.0))


class Odometry:
    """Wheel clock counters → pose and per-update motion increments (exact arcs)."""

    def __init__(self, settings: MotionSettings, history: int = 256) -> None:
        self.settings = settings
        self.pose = np.zeros(3)
        self._last: tuple[int, int] | None = None
        self._hist: deque[tuple[float, int, int]] = deque(maxlen=history)

    def reset(self) -> None:
        self._last = None
        self._hist.clear()

    def update(self, left_clocks: int, right_clocks: int, t_s: float) -> tuple[float, float, float]:
        """New counter values at time ``t_s`` → (dx mm, dy mm, dθ rad) since the last update.

        The increment is in the robot frame at the previous pose (what ``FreeSpaceMap.move``
        takes). The first update only sets the reference and returns zeros.
        """
        self._hist.append((float(t_s), int(left_clocks), int(right_clocks)))
        if self._last is None:
            self._last = (int(left_clocks), int(right_clocks))
            return 0.0, 0.0, 0.0
        dl = (int(left_clocks) - self._last[0]) * self.settings.mm_per_clock
        dr = (int(right_clocks) - self._last[1]) * self.settings.mm_per_clock
        self._last = (int(left_clocks), int(right_clocks))
        if dl == 0.0 and dr == 0.0:
            return 0.0, 0.0, 0.0
        dx, dy, dth = arc_displacement(dl, dr, self.settings.track_mm)
        self.pose = integrate_arc(self.pose, dl, dr, self.settings.track_mm)
        return float(dx), float(dy), float(dth)

    def wheel_speeds(self) -> tuple[float, float]:
        """Clock-based (left, right) wheel speeds, mm/s (:func:`window_speed`)."""
        if len(self._hist) < 2:
            return 0.0, 0.0
        h = np.asarray(self._hist, dtype=np.float64)
        w, m = self.settings.speed_window_s, self.settings.mm_per_clock
        return window_speed(h[:, 0], h[:, 1], w, m), window_speed(h[:, 0], h[:, 2], w, m)


class MotionController:
    """Ramp + wheel PI: allowed twist and the measured wheel speeds → wheel duties."""

    def __init__(self, settings: MotionSettings) -> None:
        self.settings = settings
        self.ramp = TwistRamp(settings)
        self.left = WheelPI(settings.left_gain, settings)
        self.right = WheelPI(settings.right_gain, settings)

    def reset(self) -> None:
        self.ramp.reset()
        self.left.reset()
        self.right.reset()

    def step(
        self,
        v_mm_s: float,
        omega_rad_s: float,
        measured_mm_s: tuple[float, float],
        dt_s: float,
        emergency: bool = False,
    ) -> tuple[float, float]:
        """One cycle: (left, right) duty in [-1, 1] for the target twist."""
        v, w = self.ramp.step(v_mm_s, omega_rad_s, dt_s, emergency)
        vl, vr = wheel_speeds(v, w, self.settings.track_mm)
        return (
            self.left.step(float(vl), measured_mm_s[0], dt_s),
            self.right.step(float(vr), measured_mm_s[1], dt_s),
        )
