"""Bumps: a wheel that does not turn as its duty says (clocks against duty) stops the chair and
refuses that direction until the rider asks for something else."""

from __future__ import annotations

import math

import numpy as np
import pytest
from daemon_helpers import FreeFloor, Status, Stick, arm

from omnid.core.kinematics import MM_PER_CLOCK
from omnid.daemon.config import OmnidConfig
from omnid.daemon.core import ControlCore
from omnid.daemon.motion import MotionSettings, StallDetector
from omnid.daemon.rider import JoystickSettings, RiderSettings, TiltSettings
from omnid.daemon.safety import Reason

S = MotionSettings()
DT = 0.02


class Wheel:
    """A first-order wheel (gain, lag τ, static-friction deadband) counting clocks from a random
    hole phase; ``stalled`` holds it still."""

    def __init__(self, gain: float, tau_s: float, deadband: float, phase_mm: float) -> None:
        self.gain, self.tau, self.deadband = gain, tau_s, deadband
        self.v = 0.0
        self.travel = phase_mm
        self.stalled = False

    def step(self, duty: float, dt: float) -> None:
        if self.stalled:
            self.v = 0.0
            return
        u = 0.0 if abs(duty) <= self.deadband else self.gain * duty * 235.5
        a = math.exp(-dt / self.tau)
        self.travel += u * dt + (self.v - u) * self.tau * (1 - a)
        self.v = u + (self.v - u) * a

    @property
    def clocks(self) -> int:
        return math.floor(self.travel / MM_PER_CLOCK)


def drive(det: StallDetector, wheels, duties, t0: float, t1: float) -> tuple[float, list]:
    """Statuses every DT from t0 to t1 with the given duty function of time; returns the first
    time a wheel is reported stalled (inf if never) and the flags."""
    for t in np.arange(t0, t1, DT):
        d = duties(float(t))
        flags = det.on_status(wheels[0].clocks, wheels[1].clocks, float(t), d)
        if any(flags):
            return float(t), list(flags)
        for w, dk in zip(wheels, d, strict=True):
            w.step(dk, DT)
    return math.inf, [False, False]


def test_free_wheels_of_any_plausible_motor_never_stall():
    """Random motors (gain 0.9-1.1 of the calibrated one, lag 0.08-0.3 s, deadband up to 0.05
    duty), random duty profiles (steps, ramps, reversals, tiny duties): never a bump."""
    rng = np.random.default_rng(5)
    for _ in range(60):
        det = StallDetector(S)
        wheels = [
            Wheel(rng.uniform(0.9, 1.1), rng.uniform(0.08, 0.3), rng.uniform(0, 0.05),
                  rng.uniform(0, MM_PER_CLOCK))
            for _ in range(2)
        ]  # fmt: skip
        knots = np.sort(rng.uniform(0, 20, 12))
        levels = rng.choice([-0.5, -0.2, 0.0, 0.06, 0.2, 0.5, 0.8, 1.0], (12, 2))

        def duties(t: float, knots=knots, levels=levels) -> tuple[float, float]:
            i = int(np.searchsorted(knots, t))
            return tuple(levels[min(i, 11)])  # type: ignore[return-value]

        t, _ = drive(det, wheels, duties, 0.0, 20.0)
        assert t == math.inf


@pytest.mark.parametrize("duty", [0.2, 0.5, 1.0])
def test_a_stalled_wheel_is_found_within_a_clock_and_a_tenth_of_its_sure_travel(duty):
    det = StallDetector(S)
    left = Wheel(1.0, 0.15, 0.0, 7.0)
    right = Wheel(1.0, 0.15, 0.0, 20.0)
    t_stall = 3.0
    t, flags = drive(det, [left, right], lambda t: (duty, duty), 0.0, t_stall)
    assert t == math.inf
    right.stalled = True  # the right wheel is held, the left turns on
    t, flags = drive(det, [left, right], lambda t: (duty, duty), t_stall, t_stall + 5.0)
    assert flags == [False, True]
    sure = det.duty_speed_mm_s(duty, S.right_gain)
    assert t - t_stall <= S.bump_clocks * MM_PER_CLOCK / sure + 2 * DT


def test_no_status_no_duty_no_bump():
    det = StallDetector(S)
    w = [Wheel(1.0, 0.15, 0.0, 0.0), Wheel(1.0, 0.15, 0.0, 0.0)]
    w[0].stalled = w[1].stalled = True
    # duty zero for a long time: nothing is asked, nothing is stalled
    assert drive(det, w, lambda t: (0.0, 0.0), 0.0, 5.0)[0] == math.inf
    # duty given but a silent link: the gap between statuses counts at most 0.1 s
    det.on_status(0, 0, 5.0, (1.0, 1.0))
    assert det.on_status(0, 0, 9.0, (1.0, 1.0)) == (False, False)


def test_settings_range():
    from omnid.config import from_mapping
    from omnid.errors import ConfigError

    with pytest.raises(ConfigError, match="bump_clocks"):
        from_mapping(MotionSettings, {"bump_clocks": 0.5})
    assert from_mapping(MotionSettings, {"bump_clocks": 0}).bump_clocks == 0  # off


class Chair:
    """Wheels follow duty instantly (251 mm/s at duty 1) unless ``blocked``; count clocks."""

    def __init__(self) -> None:
        self.travel = [5.0, 12.0]
        self.seq = 0
        self.blocked = False
        self.refusing = False  # the unit does not obey (a stale command, its watchdog)
        self.duty = (0.0, 0.0)  # applied, as the unit reports it

    def apply(self, cmd, dt: float) -> None:
        self.duty = (0.0, 0.0) if self.refusing else (cmd.left_duty, cmd.right_duty)
        if self.refusing:
            return
        if self.blocked and (cmd.left_duty > 0 or cmd.right_duty > 0):
            return
        for i, d in enumerate((cmd.left_duty, cmd.right_duty)):
            self.travel[i] += d * 251.0 * dt

    def status(self, t: float) -> Status:
        self.seq += 1
        c = [math.floor(v / MM_PER_CLOCK) for v in self.travel]
        return Status(self.seq, c[0], c[1], False, 0, t, *self.duty)


def joystick_core() -> ControlCore:
    cfg = OmnidConfig(
        rider=RiderSettings(
            tilt=TiltSettings(enabled=False), joystick=JoystickSettings(enabled=True)
        )
    )
    core = ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid))
    arm(core)
    return core


def ride(core: ControlCore, chair: Chair, t0: float, t1: float, fwd: float, turn: float = 0.0):
    out = []
    for t in np.arange(t0, t1, DT):
        t = float(t)
        core.on_joystick(Stick(fwd, turn, t))
        core.on_status(chair.status(t))
        core.perception_time_s = t
        cmd = core.step(t)
        chair.apply(cmd, DT)
        out.append((t, cmd, core.last_report.reasons))
    return out


def test_a_bump_stops_at_once_and_refuses_that_direction_until_the_rider_asks_otherwise(caplog):
    core, chair = joystick_core(), Chair()
    ride(core, chair, 0.0, 4.0, 1.0)
    assert core.motion.ramp.v_mm_s > 200.0
    chair.blocked = True  # driven into something the map did not hold
    cycles = ride(core, chair, 4.0, 6.0, 1.0)
    first = next(i for i, (_, _, r) in enumerate(cycles) if Reason.BUMP in r)
    t_bump, cmd, _ = cycles[first]
    # found within the detector's bound at this speed, and that very command is duty 0
    sure = core.stall.duty_speed_mm_s(core.motion.duties[0] or 0.95, 1.0)
    assert t_bump - 4.0 <= S.bump_clocks * MM_PER_CLOCK / max(sure, 150.0) + 3 * DT
    assert cmd.left_duty == 0.0 and cmd.right_duty == 0.0
    assert all(c.left_duty == 0.0 and c.right_duty == 0.0 for _, c, _ in cycles[first:])
    assert core.bump_count == 1
    assert "bump" in caplog.text and "refused until the rider asks" in caplog.text
    # the same direction, or a forward arc, stays refused
    arc = ride(core, chair, 6.0, 7.0, 0.8, 0.3)
    assert all(c.left_duty == 0.0 for _, c, _ in arc)
    assert all(Reason.BUMP in r for _, _, r in arc)
    # asking for something else (reverse) is allowed at once, and clears the refusal
    back = ride(core, chair, 7.0, 8.0, -1.0)
    assert back[-1][1].left_duty < 0.0 and core.bump_direction is None
    assert core.bump_count == 1  # reversing away is not a bump


def test_wheels_a_refusing_unit_holds_at_rest_are_no_bump(caplog):
    """The detector weighs the clocks against the duty the unit reports it applies: a unit that
    refuses the core's commands (its watchdog, a stale command) stops its wheels, and that is
    not a bump (the omnid bench once logged one with the wheels asked for 60 mm/s)."""
    core, chair = joystick_core(), Chair()
    ride(core, chair, 0.0, 3.0, 0.3)
    chair.refusing = True
    cycles = ride(core, chair, 3.0, 6.0, 0.3)
    assert core.bump_count == 0 and not any(Reason.BUMP in r for _, _, r in cycles)
    assert "bump" not in caplog.text
    # the same chair obeying again and then blocked: the bump is found as before
    chair.refusing = False
    ride(core, chair, 6.0, 8.0, 0.3)
    chair.blocked = True
    cycles = ride(core, chair, 8.0, 11.0, 0.3)
    assert core.bump_count == 1 and any(Reason.BUMP in r for _, _, r in cycles)
