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
- Bumps (:class:`StallDetector`): a wheel whose duty says it surely travelled more than a
  clock without its counter changing is not turning as commanded — the chair is pressed
  against something the map did not hold.
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
    # a wheel surely turned this many clocks by its duty without one is stalled: a bump (0
    # disables, else at least 1: a stall shows only after a whole clock). "Surely": its duty's
    # speed less a deadband, times a fraction (a weak motor), through at most a first-order lag
    # (StallDetector). Margins measured in docs/daemon.md "Bumps"
    bump_clocks: float = setting(1.25, 0.0, 10.0)
    bump_lag_s: float = setting(0.3, 0.0, 2.0)  # the longest lag of a wheel behind its duty
    bump_speed_fraction: float = setting(0.8, 0.05, 1.0)  # of its duty's speed a wheel reaches
    bump_deadband_duty: float = setting(0.05, 0.0, 0.5)  # may not turn a wheel (static friction)
    # after a bump, requests whose wheel velocities lie within this angle of the bumped ones
    # (in the (left, right) plane: forward arcs after a forward bump) are refused; below 90°:
    # a turn in place is not the same direction as a straight move
    bump_same_direction_deg: float = setting(45.0, 1.0, 89.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.bump_clocks == 0 or self.bump_clocks >= 1.0,
            "bump_clocks",
            "must be 0 (off) or at least 1 (a stalled wheel shows only after a whole clock)",
        )
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
    """Wheel clock counters → pose and per-update motion increments (exact arcs).

    A counter says where a wheel is only to a clock (31.4 mm): taken as it stands, the heading
    jumps by up to 31.4 mm / track (3°) each time one wheel's hole passes before the other's,
    and whatever the map placed by it (a doorway's jambs a metre away) moves sideways by 5 cm.
    So between counter changes each wheel is carried on from the hole it last passed at the
    slower of its last two holes' pace and the speed it is driven at (``targets_mm_s``, 0 when
    it is told to stop or to turn the other way), never past the next hole (it would have
    counted) — the next counter change sets it exactly on that hole again.
    """

    def __init__(self, settings: MotionSettings, history: int = 256) -> None:
        self.settings = settings
        self.pose = np.zeros(3)
        self._last: tuple[int, int] | None = None
        self._hist: deque[tuple[float, int, int]] = deque(maxlen=history)
        self._pos = [0.0, 0.0]  # estimated wheel travel, mm
        self._edge: list[tuple[float, float, int] | None] = [None, None]  # (t, hole mm, sign)
        self._rate = [0.0, 0.0]  # pace of the last two holes, mm/s (0: unknown)

    def reset(self) -> None:
        self._last = None
        self._hist.clear()
        self._edge = [None, None]
        self._rate = [0.0, 0.0]

    def update(
        self,
        left_clocks: int,
        right_clocks: int,
        t_s: float,
        targets_mm_s: tuple[float, float] = (0.0, 0.0),
    ) -> tuple[float, float, float]:
        """New counter values at time ``t_s`` (and the wheel speeds the controller drives
        towards now) → (dx mm, dy mm, dθ rad) since the last update.

        The increment is in the robot frame at the previous pose (what ``FreeSpaceMap.move``
        takes). The first update only sets the reference and returns zeros.
        """
        t = float(t_s)
        clocks = (int(left_clocks), int(right_clocks))
        hist = self._hist
        hist.append((t, *clocks))
        # only what the speed estimate reads is kept: the window and the sample before it
        since = t - float(self.settings.speed_window_s)
        while len(hist) > 2 and hist[1][0] < since:
            hist.popleft()
        mpc = self.settings.mm_per_clock
        if self._last is None:
            self._last = clocks
            self._pos = [c * mpc for c in clocks]
            return 0.0, 0.0, 0.0
        new = [0.0, 0.0]
        for k in (0, 1):
            c, c0 = clocks[k], self._last[k]
            if c != c0:
                sign = 1 if c > c0 else -1
                hole = (c if sign > 0 else c + 1) * mpc  # the hole just passed
                edge = self._edge[k]
                self._rate[k] = 0.0
                if edge is not None and edge[2] == sign and t > edge[0]:
                    self._rate[k] = abs(hole - edge[1]) / (t - edge[0])
                self._edge[k] = (t, hole, sign)
                new[k] = hole
                continue
            edge = self._edge[k]
            target = float(targets_mm_s[k])
            if edge is None or target * edge[2] <= 0.0:
                new[k] = self._pos[k]  # no pace known, told to stop or to reverse: hold
                continue
            rate = self._rate[k]
            if abs(target) < 0.5 * rate:  # told to slow down: it will, soon
                rate = abs(target)
            ahead = edge[1] + edge[2] * min(rate * (t - edge[0]), 0.97 * mpc)
            lo, hi = c * mpc, (c + 1) * mpc  # the counter says the wheel is in here
            new[k] = min(max(ahead, lo), hi)
            # never back against the way it is going
            new[k] = max(new[k], self._pos[k]) if edge[2] > 0 else min(new[k], self._pos[k])
        self._last = clocks
        dl, dr = new[0] - self._pos[0], new[1] - self._pos[1]
        self._pos = new
        if dl == 0.0 and dr == 0.0:
            return 0.0, 0.0, 0.0
        dx, dy, dth = arc_displacement(dl, dr, self.settings.track_mm)
        self.pose = integrate_arc(self.pose, dl, dr, self.settings.track_mm)
        return float(dx), float(dy), float(dth)

    def wheel_speeds(self) -> tuple[float, float]:
        """Clock-based (left, right) wheel speeds, mm/s (:func:`window_speed`)."""
        if len(self._hist) < 2:
            return 0.0, 0.0
        h = np.asarray(self._hist, dtype=np.float64)  # the window (update keeps no more)
        w, m = self.settings.speed_window_s, self.settings.mm_per_clock
        return window_speed(h[:, 0], h[:, 1], w, m), window_speed(h[:, 0], h[:, 2], w, m)


class StallDetector:
    """Wheels that do not turn as commanded (a bump): clock counts against duty, per wheel.

    A wheel's duty asks for a speed: duty · ``full_duty_speed_mm_s`` / its feedforward gain,
    less ``bump_deadband_duty`` (static friction), times ``bump_speed_fraction`` (a motor may be
    weaker than calibrated). How fast the wheel gets there is not known: any first-order lag
    between none and ``bump_lag_s`` (the motor, the PI and the ramp). Between control-unit
    statuses the detector moves two bounding wheels by the duties given — one without lag, one
    with the longest — capped at the pace its last two counter changes showed, and keeps their
    signed travel since the wheel's counter last changed. The less of the two, in the direction
    the duty drives now, is what the wheel surely turned: a wheel trails the quick one when it
    speeds up, the slow one when it slows down, and after reversing the quick one went back
    first. One clock is 31.4 mm, so a wheel turning at least that surely changes its counter
    every clock; more than ``bump_clocks`` clocks of sure travel without a change is a stall.
    Both travels restart at every counter change and when the wheel comes to rest (from rest a
    wheel may need almost a whole clock before its next hole passes the sensor). A wheel the PI
    drives harder because it is held back is predicted faster, so a stall shows sooner.

    Driven by statuses, not control cycles: while no status arrives nothing is predicted (a
    silent link is the status timeout's business, not a bump); the duty of an interval is the
    one given at its start (the previous call's).

    What it cannot do: see a stall before the wheel has been asked for about a clock more than
    it did — the clock is the only wheel sensor (SPEC §1), 31.4 mm: about 200 ms at 240 mm/s and
    1.2 s at 40 mm/s when the contact comes right after a hole passed.
    """

    def __init__(self, settings: MotionSettings) -> None:
        self.settings = settings
        self.asked_mm = [0.0, 0.0]  # surely travelled since the counter last changed
        self.speed_mm_s = [0.0, 0.0]  # the slow (lagged) wheel's speed, signed
        self.stalled = (False, False)  # as of the latest status
        self._quick = [0.0, 0.0]  # signed travel of the unlagged wheel since the last change
        self._slow = [0.0, 0.0]  # ... and of the lagged one
        self._edge: list[tuple[float, float] | None] = [None, None]  # (t_s, signed mm/s)
        self._duty = (0.0, 0.0)
        self._last: tuple[int, int, float] | None = None

    def reset(self) -> None:
        self.asked_mm = [0.0, 0.0]
        self.speed_mm_s = [0.0, 0.0]
        self._quick = [0.0, 0.0]
        self._slow = [0.0, 0.0]
        self._edge = [None, None]
        self.stalled = (False, False)

    def duty_speed_mm_s(self, duty: float, gain: float) -> float:
        """The least speed (mm/s, signed) a free wheel given ``duty`` turns at, in the end."""
        s = self.settings
        d = max(abs(duty) - s.bump_deadband_duty, 0.0)
        return math.copysign(d * s.full_duty_speed_mm_s / gain * s.bump_speed_fraction, duty)

    def on_status(
        self, left_clocks: int, right_clocks: int, t_s: float, duties: tuple[float, float]
    ) -> tuple[bool, bool]:
        """A control-unit status at ``t_s``; ``duties`` are the ones just given (for the next
        interval). Returns (and keeps in :attr:`stalled`) which wheel is stalled."""
        s = self.settings
        t = float(t_s)
        clocks = (int(left_clocks), int(right_clocks))
        last, self._last = self._last, (*clocks, t)
        duty, self._duty = self._duty, (float(duties[0]), float(duties[1]))
        if last is None or s.bump_clocks <= 0:
            return self.stalled
        dt = min(max(t - last[2], 0.0), 0.1)  # a longer gap: the link's fault, not a bump
        tau = s.bump_lag_s
        decay = math.exp(-dt / tau) if tau > 0 else 0.0
        out = [False, False]
        for k, gain in enumerate((s.left_gain, s.right_gain)):
            u = self.duty_speed_mm_s(duty[k], gain)
            v0 = self.speed_mm_s[k]
            v1 = u + (v0 - u) * decay
            self.speed_mm_s[k] = v1
            turned = clocks[k] - last[k]
            edge = self._edge[k]
            if turned:
                rate = math.copysign(math.inf, turned)
                if edge is not None and edge[1] * turned > 0:
                    rate = turned * s.mm_per_clock / max(t - edge[0], 1e-3)
                self._edge[k] = (t, rate)
            if turned or (u == 0.0 and abs(v1) < 1.0):
                if not turned:
                    self._edge[k] = None
                self._quick[k] = self._slow[k] = self.asked_mm[k] = 0.0
                continue
            quick = u * dt
            if edge is not None and edge[1] * u > 0:
                quick = math.copysign(min(abs(quick), abs(edge[1]) * dt), u)
            self._quick[k] += quick
            self._slow[k] += u * dt + (v0 - u) * tau * (1.0 - decay)  # exact for the lag
            sign = math.copysign(1.0, u) if u != 0.0 else math.copysign(1.0, v1)
            self.asked_mm[k] = max(min(sign * self._quick[k], sign * self._slow[k]), 0.0)
            out[k] = self.asked_mm[k] > s.bump_clocks * s.mm_per_clock
        self.stalled = (out[0], out[1])
        return self.stalled


class MotionController:
    """Ramp + wheel PI: allowed twist and the measured wheel speeds → wheel duties."""

    def __init__(self, settings: MotionSettings) -> None:
        self.settings = settings
        self.ramp = TwistRamp(settings)
        self.left = WheelPI(settings.left_gain, settings)
        self.right = WheelPI(settings.right_gain, settings)
        self.targets_mm_s = (0.0, 0.0)  # the wheel targets of the last step
        self.duties = (0.0, 0.0)  # and the duties it gave

    def reset(self) -> None:
        self.ramp.reset()
        self.left.reset()
        self.right.reset()
        self.targets_mm_s = (0.0, 0.0)
        self.duties = (0.0, 0.0)

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
        self.targets_mm_s = (float(vl), float(vr))
        self.duties = (
            self.left.step(float(vl), measured_mm_s[0], dt_s),
            self.right.step(float(vr), measured_mm_s[1], dt_s),
        )
        return self.duties
