"""Fault paths of the control core, clock-injected: zero at once, re-arm only on a live release
of the driving source after the fault cleared, a new live demand after a stall, the perception
map bounded in travel as well as age, a speed cap when the cameras go quiet."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from daemon_helpers import FreeFloor, Status, Stick, Tilt, arm

from omnid.core.kinematics import MM_PER_CLOCK
from omnid.daemon.config import OmnidConfig
from omnid.daemon.core import ControlCore
from omnid.daemon.rider import JoystickSettings, RiderSettings, TiltSettings
from omnid.daemon.safety import Reason

DT = 0.02
FORWARD = (-20.0, 0.0)
NEUTRAL = (0.0, 0.0)


class Chair:
    """Wheels follow duty instantly (251 mm/s at duty 1) and count clocks."""

    def __init__(self) -> None:
        self.travel = [0.0, 0.0]

    def apply(self, cmd, dt: float) -> None:
        for i, d in enumerate((cmd.left_duty, cmd.right_duty)):
            self.travel[i] += d * 251.0 * dt

    def status(self, t: float) -> Status:
        left, right = (math.floor(x / MM_PER_CLOCK) for x in self.travel)
        return Status(0, left, right, True, 0, t)


def make_core(**safety) -> ControlCore:
    d = OmnidConfig()
    cfg = replace(
        d,
        rider=RiderSettings(
            tilt=TiltSettings(dwell_s=0.1, neutral_calibration_s=0.0),
            joystick=JoystickSettings(enabled=False),
        ),
        safety=replace(d.safety, **safety),
    )
    m = FreeFloor(cfg.freespace.grid)  # free everywhere, as far as the chair goes
    core = ControlCore(cfg, world_map=m)
    arm(core)
    return core


class Run:
    """Drives a core cycle by cycle: tilt readings, control-unit status, fresh perception."""

    def __init__(self, core: ControlCore) -> None:
        self.core = core
        self.chair = Chair()
        self.t = 0.0
        self.head = NEUTRAL
        self.tilt = True  # the sensor answers
        self.unit = True  # the control unit answers
        self.perceive = True

    def cycles(self, seconds: float):
        cmds = []
        for _ in range(round(seconds / DT)):
            self.t = round(self.t + DT, 6)
            if self.tilt:
                self.core.on_tilt(Tilt(*self.head, self.t))
            if self.unit:
                self.core.on_status(self.chair.status(self.t))
            if self.perceive:
                self.core.perception_time_s = self.t
            cmd = self.core.step(self.t)
            self.chair.apply(cmd, DT)
            cmds.append(cmd)
        return cmds


def moving(cmd) -> bool:
    return cmd.enable and (cmd.left_duty != 0.0 or cmd.right_duty != 0.0)


def test_lost_tilt_is_zero_at_once_and_a_head_still_tilted_does_not_restart():
    r = Run(make_core())
    r.head = FORWARD
    assert moving(r.cycles(1.0)[-1])
    r.tilt = False  # unplugged
    cmds = r.cycles(0.3)
    timeout = r.core.config.rider.tilt.timeout_s
    first_zero = next(i for i, c in enumerate(cmds) if not moving(c))
    assert (first_zero + 1) * DT <= timeout + DT + 1e-9  # zero duty, no ramp
    assert all(c.left_duty == 0.0 and not c.enable for c in cmds[first_zero:])
    r.tilt = True  # back, the head still forward: beyond its dwell, still no motion
    cmds = r.cycles(1.0)
    assert not any(moving(c) for c in cmds)
    assert r.core.last_report.demand.reason == "rearm_wait"
    r.head = NEUTRAL  # the rider releases ...
    r.cycles(0.2)
    r.head = FORWARD  # ... and asks again
    assert moving(r.cycles(0.6)[-1])


def test_unit_and_tilt_lost_together_stay_stopped_until_the_tilt_is_released():
    """Issue 10, finding 3: a stale tilt is not a release."""
    r = Run(make_core())
    r.head = FORWARD
    assert moving(r.cycles(1.0)[-1])
    r.tilt = r.unit = False
    lost = r.cycles(1.0)
    # zero once the mux's 100 ms backstop passed (the daemon's tilt link says it sooner)
    first = round(r.core.config.rider.tilt.timeout_s / DT) + 1
    assert not any(moving(c) for c in lost[first:])
    r.unit = True  # the unit is back first; the tilt port still closed
    assert not any(moving(c) for c in r.cycles(0.5))
    r.tilt = True  # the tilt too, the head still tilted
    assert not any(moving(c) for c in r.cycles(1.5))
    r.head = NEUTRAL
    r.cycles(0.2)
    r.head = FORWARD
    assert moving(r.cycles(0.6)[-1])


def test_link_unhealthy_is_zero_in_the_same_cycle_with_integrators_reset():
    r = Run(make_core())
    r.head = FORWARD
    r.cycles(1.0)
    r.core.link_ok = False
    cmd = r.cycles(DT)[-1]
    assert (cmd.left_duty, cmd.right_duty, cmd.enable) == (0.0, 0.0, False)
    m = r.core.motion
    assert m.left.integral == m.right.integral == 0.0 and m.ramp.v_mm_s == 0.0


def test_after_a_stall_the_first_command_is_zero_and_motion_needs_newer_input():
    core = make_core()
    r = Run(core)
    r.head = FORWARD
    assert moving(r.cycles(1.0)[-1])
    t_before = r.t
    # the loop stalls 0.5 s; the last reading the core has is from before the stall
    r.t = round(r.t + 0.5, 6)
    core.on_status(r.chair.status(r.t))
    core.perception_time_s = r.t
    cmd = core.step(r.t)
    assert (cmd.left_duty, cmd.enable) == (0.0, False)
    r.t = round(r.t + DT, 6)
    core.on_status(r.chair.status(r.t))
    assert core.mux.input_time_s("tilt") == t_before
    assert not moving(core.step(r.t))  # still only the pre-stall reading
    # readings flow again: a live demand (its dwell starts afresh after the gap) drives
    assert moving(r.cycles(0.6)[-1])


def test_a_sensor_that_says_it_is_gone_during_a_stall_must_rest_before_it_drives():
    """A stall excuses a source that merely went quiet (nobody read it); one whose device said
    it was gone (unplugged) during the stall is a reconnect: back with the head still forward it
    must first be seen at rest."""
    core = make_core()
    r = Run(core)
    r.head = FORWARD
    assert moving(r.cycles(1.0)[-1])
    core.on_input_lost("tilt", round(r.t + 0.2, 6))  # logged while the loop was stuck
    r.t = round(r.t + 0.5, 6)
    core.on_status(r.chair.status(r.t))
    core.perception_time_s = r.t
    assert not moving(core.step(r.t))
    assert not any(moving(c) for c in r.cycles(1.0))  # the head still forward: refused
    r.head = NEUTRAL
    r.cycles(0.1)
    r.head = FORWARD
    assert moving(r.cycles(0.6)[-1])


def test_a_map_is_used_for_a_bounded_travel_not_only_a_bounded_age():
    core = make_core(perception_timeout_s=5.0, perception_max_travel_mm=200.0)
    r = Run(core)
    r.head = FORWARD
    r.cycles(1.0)
    core.perception_time_s = r.t  # the last perception; then none for a while
    r.perceive = False
    travel0 = core.path_mm
    cmds = r.cycles(3.0)
    assert not moving(cmds[-1])
    assert Reason.PERCEPTION_STALE in core.last_report.reasons
    assert r.t - core.perception_time_s < 5.0  # refused by travel, not by age
    # stopped after about the allowed travel (+ the braking at the emergency rate)
    assert 200.0 <= core.path_mm - travel0 <= 200.0 + 60.0


def test_camera_lost_caps_the_speed_from_the_next_cycle():
    core = make_core(camera_lost_speed_mm_s=50.0)
    r = Run(core)
    r.head = FORWARD
    r.cycles(2.0)
    v0 = core.motion.ramp.v_mm_s
    assert v0 > 100.0
    core.camera_ok = False
    cmds = r.cycles(DT)
    assert core.motion.ramp.v_mm_s < v0  # slowing at once (emergency rate)
    assert Reason.CAMERA_LOST in core.last_report.reasons and moving(cmds[-1])
    r.cycles(0.5)
    assert abs(core.motion.ramp.v_mm_s - 50.0) < 1e-6
    core.camera_ok = True
    r.cycles(1.0)
    assert core.motion.ramp.v_mm_s > 100.0


def test_rearm_follows_the_source_that_was_driving():
    """The keyboard drove when the unit faulted: its key must expire; the tilt (idle) cannot
    re-arm it."""
    d = OmnidConfig()
    cfg = replace(
        d,
        rider=RiderSettings(
            tilt=TiltSettings(enabled=False), joystick=JoystickSettings(enabled=False)
        ),
    )
    core = ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid))
    t = 0.0
    ok = []
    for _ in range(30):
        t = round(t + DT, 6)
        core.on_status(Status(0, 0, 0, True, 0, t))
        core.perception_time_s = t
        core.on_key("left", t)
        ok.append(moving(core.step(t)))
    assert ok[-1]
    core.link_ok = False
    t = round(t + DT, 6)
    core.on_key("left", t)
    assert not moving(core.step(t))
    core.link_ok = True
    held = []
    for _ in range(np.ceil(1.0 / DT).astype(int)):  # the key held (repeated) through and after
        t = round(t + DT, 6)
        core.on_status(Status(0, 0, 0, True, 0, t))
        core.perception_time_s = t
        core.on_key("left", t)
        held.append(moving(core.step(t)))
    assert not any(held)
    assert core.arming.driver == "keyboard"


def test_a_head_tilted_when_the_daemon_starts_drives_only_after_a_rest():
    """A restarted daemon (systemd restarts one whose loop died) with the rider's head still
    tilted: nothing moves until the head has been seen at rest."""
    d = OmnidConfig()
    cfg = replace(
        d,
        rider=RiderSettings(
            tilt=TiltSettings(dwell_s=0.1, neutral_calibration_s=0.0),
            joystick=JoystickSettings(enabled=False),
        ),
    )
    m = FreeFloor(cfg.freespace.grid)
    r = Run(ControlCore(cfg, world_map=m))  # not armed: the first reading is already tilted
    r.head = FORWARD
    assert not any(moving(c) for c in r.cycles(1.5))
    assert r.core.last_report.demand.reason == "rearm_wait"
    r.head = NEUTRAL
    r.cycles(0.1)
    r.head = FORWARD
    assert moving(r.cycles(0.6)[-1])


def test_the_neutral_pose_calibration_counts_as_the_head_seen_at_rest():
    d = OmnidConfig()
    cfg = replace(
        d,
        rider=RiderSettings(
            tilt=TiltSettings(dwell_s=0.1, neutral_calibration_s=0.2),
            joystick=JoystickSettings(enabled=False),
        ),
    )
    r = Run(ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid)))
    r.head = NEUTRAL
    r.cycles(0.22)  # the calibration's last reading; the next one is already tilted
    assert r.core.mux.tilt.calibrated
    r.head = FORWARD
    assert moving(r.cycles(0.6)[-1])


@pytest.mark.parametrize("unit_silent_meanwhile", [False, True])
def test_a_stick_replugged_while_deflected_does_not_drive_until_centred(unit_silent_meanwhile):
    """The joystick is unplugged while idle (nothing driving) and comes back with the stick
    already pushed (a hand resting on it, a bag hooked on it): the chair must not lurch. The
    start-up rule (seen at rest before it drives) holds across a reconnect too."""
    d = OmnidConfig()
    cfg = replace(
        d,
        rider=RiderSettings(
            tilt=TiltSettings(enabled=False), joystick=JoystickSettings(enabled=True)
        ),
    )
    core = ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid))
    arm(core)
    t = 0.0

    def cycles(seconds: float, stick: tuple[float, float] | None, unit: bool = True) -> list:
        nonlocal t
        out = []
        for _ in range(round(seconds / DT)):
            t = round(t + DT, 6)
            if stick is not None:
                core.on_joystick(Stick(*stick, t))
            if unit:
                core.on_status(Status(0, 0, 0, True, 0, t))
            core.perception_time_s = t
            out.append(core.step(t))
        return out

    assert not any(moving(c) for c in cycles(0.5, (0.0, 0.0)))  # live, centred
    assert moving(cycles(0.5, (0.8, 0.0))[-1])  # it drives when pushed
    cycles(0.5, (0.0, 0.0))  # released: idle
    if unit_silent_meanwhile:
        # the control unit is silent (status stale) in the cycle that sees the stick go: the
        # loss is noted all the same, not lost under the other fault
        cycles(0.5, (0.0, 0.0), unit=False)
        core.on_input_lost("joystick", t)
        assert not any(moving(c) for c in cycles(0.5, None, unit=False))
        cycles(0.3, None)
    else:
        core.on_input_lost("joystick", t)  # unplugged (hidapi read error)
        assert not any(moving(c) for c in cycles(0.5, None))
    back = cycles(1.0, (0.8, 0.0))  # replugged, the stick already deflected
    assert not any(moving(c) for c in back)
    assert core.last_report.demand.reason == "rearm_wait"
    cycles(0.1, (0.0, 0.0))  # centred once
    assert moving(cycles(0.5, (0.8, 0.0))[-1])


def test_a_tilt_sensor_back_with_the_head_tilted_does_not_drive_until_at_rest():
    """The tilt sensor is lost while the head is neutral and comes back with the head held
    forward (the rider slumped while it was gone): not a fresh command, it must not drive
    before the head has been seen at rest again."""
    r = Run(make_core())
    r.head = NEUTRAL
    r.cycles(0.5)
    r.head = FORWARD
    assert moving(r.cycles(0.6)[-1])  # the head drives
    r.head = NEUTRAL
    r.cycles(0.6)  # idle again
    r.tilt = False
    r.core.on_input_lost("tilt", r.t)
    assert not any(moving(c) for c in r.cycles(0.5))
    r.tilt = True
    r.head = FORWARD
    assert not any(moving(c) for c in r.cycles(1.5))
    r.head = NEUTRAL
    r.cycles(0.1)
    r.head = FORWARD
    assert moving(r.cycles(0.6)[-1])
