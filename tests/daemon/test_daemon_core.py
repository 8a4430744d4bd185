"""ControlCore: the whole decision chain, clock-injected, and every fault path ending in stop."""

from __future__ import annotations

import math

import numpy as np
import pytest
from daemon_helpers import FreeFloor, RecordingMap, Status, Stick, Tilt, arm, floor_cloud

from omnid.core.kinematics import MM_PER_CLOCK
from omnid.daemon.config import OmnidConfig
from omnid.daemon.core import ControlCore, transform_cloud
from omnid.daemon.rider import JoystickSettings, RiderSettings, TiltSettings
from omnid.daemon.safety import Reason

DT = 0.02


def make_core(**rider) -> tuple[ControlCore, RecordingMap]:
    cfg = OmnidConfig(
        rider=RiderSettings(
            tilt=TiltSettings(dwell_s=0.1, neutral_calibration_s=0.0),
            joystick=JoystickSettings(enabled=False),
            **rider,
        )
    )
    m = RecordingMap(cfg.freespace.grid)
    core = ControlCore(cfg, world_map=m)
    arm(core)
    return core, m


class Chair:
    """Wheels follow duty instantly (251 mm/s at duty 1) and count clocks."""

    def __init__(self) -> None:
        self.travel = [0.0, 0.0]
        self.seq = 0

    def apply(self, cmd, dt: float) -> None:
        for i, d in enumerate((cmd.left_duty, cmd.right_duty)):
            self.travel[i] += d * 251.0 * dt

    def status(self, t: float, faults: int = 0) -> Status:
        self.seq += 1
        return Status(
            self.seq,
            math.floor(self.travel[0] / MM_PER_CLOCK),
            math.floor(self.travel[1] / MM_PER_CLOCK),
            False,
            faults,
            t,
        )


def run(
    core: ControlCore,
    chair: Chair,
    t0: float,
    t1: float,
    roll: float = -20.0,
    pitch: float = 0.0,
    perceive: bool = True,
    tilt: bool = True,
    status: bool = True,
):
    cmds = []
    for t in np.arange(t0, t1, DT):
        t = float(t)
        if tilt:
            core.on_tilt(Tilt(roll, pitch, t))
        if status:
            core.on_status(chair.status(t))
        if perceive:
            core.perception_time_s = t  # a fresh result every cycle (map unchanged)
        cmd = core.step(t)
        chair.apply(cmd, DT)
        cmds.append(cmd)
    return cmds


def free_map(m: RecordingMap) -> None:
    m.states[:] = 1


def test_forward_on_free_floor_ramps_up_then_stops_on_stale_tilt():
    core, m = make_core()
    free_map(m)
    chair = Chair()
    cmds = run(core, chair, 0.0, 2.0)
    assert cmds[0].left_duty == 0.0  # dwell + ramp: no jump
    assert cmds[-1].enable and cmds[-1].left_duty > 0.3
    assert cmds[-1].left_duty == pytest.approx(cmds[-1].right_duty, abs=0.1)
    # the tilt sensor falls silent: within the timeout + an emergency ramp, wheels at zero
    cmds = run(core, chair, 2.0, 3.0, tilt=False)
    assert core.last_report.reasons[0] is Reason.INPUT_STALE
    assert cmds[-1].left_duty == 0.0 and cmds[-1].right_duty == 0.0


def test_missing_or_stale_status_stops_at_once():
    core, m = make_core()
    free_map(m)
    chair = Chair()
    run(core, chair, 0.0, 2.0)
    t = 2.0 + core.config.control.status_timeout_s + 0.01
    core.on_tilt(Tilt(-20.0, 0.0, t))
    cmd = core.step(t)
    assert (cmd.left_duty, cmd.right_duty, cmd.enable) == (0.0, 0.0, False)
    assert core.last_report.reasons == (Reason.STATUS_STALE,)


def test_control_unit_fault_flag_stops():
    core, m = make_core()
    free_map(m)
    chair = Chair()
    run(core, chair, 0.0, 1.5)
    core.on_status(chair.status(1.5, faults=1))
    cmd = core.step(1.5)
    assert cmd.left_duty == 0.0 and not cmd.enable
    assert core.last_report.reasons == (Reason.FAULT,)


def test_a_one_shot_fault_flag_in_a_reply_between_cycles_is_not_hidden_by_the_next():
    """WATCHDOG and STALE_COMMAND come in one reply only; two replies between cycles (an
    urgent frame's and the regular one's) let the second, clean, hide the first: the core
    drove on as if the unit had never stopped its wheels."""
    from omnid.devices.cu_codec import FAULT_STALE_COMMAND, FAULT_WATCHDOG

    for flag in (FAULT_WATCHDOG, FAULT_STALE_COMMAND):
        core, m = make_core()
        free_map(m)
        chair = Chair()
        run(core, chair, 0.0, 1.5)
        core.on_status(chair.status(1.505, faults=flag))
        core.on_status(chair.status(1.51))  # the next reply, before the cycle
        core.on_tilt(Tilt(-20.0, 0.0, 1.52))
        cmd = core.step(1.52)
        assert cmd.left_duty == 0.0 and not cmd.enable, flag
        assert core.last_report.reasons == (Reason.FAULT,)


def test_informational_control_unit_flags_do_not_stop():
    """RESET (first reply after power-up) and RX_ERROR (one rejected frame) are not faults."""
    from omnid.devices.cu_codec import FAULT_RESET, FAULT_RX_ERROR

    core, m = make_core()
    free_map(m)
    chair = Chair()
    run(core, chair, 0.0, 1.5)
    core.on_status(chair.status(1.5, faults=FAULT_RESET | FAULT_RX_ERROR))
    core.step(1.5)
    assert Reason.FAULT not in core.last_report.reasons
    assert Reason.STATUS_STALE not in core.last_report.reasons


def test_stale_perception_refuses_forward():
    core, m = make_core()
    free_map(m)
    cmds = run(core, Chair(), 0.0, 1.5, perceive=False)
    assert all(c.left_duty == 0.0 for c in cmds)
    assert Reason.PERCEPTION_STALE in core.last_report.reasons


def test_obstacle_stops_the_chair_before_it():
    core, _m = make_core()
    core = ControlCore(core.config)  # the real free-space map
    arm(core)
    chair = Chair()
    # wall 1500 mm ahead of the axle, seen in two captures (one would leave it in doubt)
    core.on_perception(floor_cloud(obstacle_x_mm=1200.0), 0.0)
    core.on_perception(floor_cloud(obstacle_x_mm=1200.0), 0.0)
    cmds = run(core, chair, 0.0, 15.0)
    travelled = 0.5 * (chair.travel[0] + chair.travel[1])
    s = core.config.safety
    front = s.footprint_front_mm + s.margin_mm
    assert cmds[-1].left_duty == 0.0 and cmds[-1].right_duty == 0.0
    assert core.last_report.decision.stopped
    assert Reason.OBSTACLE_STOP in core.last_report.reasons
    gap = 1500.0 - front - travelled
    # stopped inside the stop zone, not touching the wall (map cells and clocks: ±2 cells)
    assert 0.0 < gap <= s.stop_distance_mm + 2 * core.grid.settings.resolution_mm


def test_exception_in_cycle_fails_safe(caplog):
    core, m = make_core()
    free_map(m)
    chair = Chair()
    run(core, chair, 0.0, 1.5)

    def broken(*args, **kwargs):
        raise RuntimeError("broken map")

    core.safety.check = broken  # the safety check raises inside the cycle
    core.on_tilt(Tilt(-20.0, 0.0, 1.52))
    cmd = core.step(1.52)
    assert (cmd.left_duty, cmd.right_duty, cmd.enable) == (0.0, 0.0, False)
    assert core.fault_count == 1 and "cycle_exception" in caplog.text


def test_status_motion_moves_the_map():
    core, m = make_core()
    chair = Chair()
    chair.travel = [0.0, 0.0]
    core.on_status(chair.status(0.0))
    chair.travel = [10 * MM_PER_CLOCK, 10 * MM_PER_CLOCK]
    core.on_status(chair.status(0.1))
    assert m.moves == [pytest.approx((10 * MM_PER_CLOCK, 0.0, 0.0))]


def test_late_perception_is_compensated_by_odometry():
    core, m = make_core()
    chair = Chair()
    core.on_status(chair.status(0.0))
    chair.travel = [20 * MM_PER_CLOCK] * 2  # 628 mm forward after the capture
    core.on_status(chair.status(0.5))
    cloud = floor_cloud(obstacle_x_mm=2000.0)
    core.on_perception(cloud, capture_time_s=0.0)
    got = m.clouds[-1]
    assert got.xyz[:, 0] == pytest.approx(cloud.xyz[:, 0] - 20 * MM_PER_CLOCK)
    assert core.perception_time_s == 0.0


def test_perception_older_than_the_odometry_history_is_not_entered():
    """A cloud whose capture the odometry history no longer covers (a worker restarted while
    its job waited: the job reaches the map seconds later) cannot be placed: it must not enter
    the map as if it had been taken where the chair is now. (It was entered unmoved: floor seen
    2 m back marked free ahead of the chair.)"""
    core, m = make_core()
    chair = Chair()
    history = core.config.control.pose_history_s
    steps = int(history / 0.1) + 10
    for k in range(steps + 1):  # creeping forward for longer than the history holds
        chair.travel = [k * MM_PER_CLOCK] * 2
        core.on_status(chair.status(0.1 * k))
    core.on_perception(floor_cloud(obstacle_x_mm=2000.0), capture_time_s=0.0)
    assert m.clouds == [], "a cloud the odometry cannot place was entered unmoved"
    assert core.perception_time_s is None


def test_transform_cloud_rotation_keeps_world_points():
    cloud = floor_cloud()
    moved = transform_cloud(cloud, 0.0, 0.0, math.pi / 2, rig_x_offset_mm=0.0)
    # robot turned left by 90°: a point ahead (x) is now on the right (y < 0 → rig Y > 0)
    i = np.argmax(cloud.xyz[:, 0])
    assert moved.xyz[i, 1] == pytest.approx(cloud.xyz[i, 0])
    assert moved.xyz[i, 0] == pytest.approx(-cloud.xyz[i, 1])


def test_joystick_source_drives_turn():
    cfg = OmnidConfig(
        rider=RiderSettings(
            tilt=TiltSettings(enabled=False), joystick=JoystickSettings(enabled=True)
        )
    )
    core = ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid))  # all around: seen free
    arm(core)
    chair = Chair()
    for t in np.arange(0.0, 1.0, DT):
        core.on_joystick(Stick(0.0, 1.0, float(t)))
        core.on_status(chair.status(float(t)))
        core.perception_time_s = float(t)
        cmd = core.step(float(t))
        chair.apply(cmd, DT)
    assert cmd.left_duty < 0 < cmd.right_duty  # turning left in place


def test_after_a_control_unit_fault_motion_waits_for_the_riders_release():
    from dataclasses import replace

    for rearm in (True, False):
        cfg = OmnidConfig(
            rider=RiderSettings(tilt=TiltSettings(enabled=False)),
            control=replace(OmnidConfig().control, rearm_after_fault=rearm),
        )
        core = ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid))  # seen all around
        t = 0.0
        core.on_status(Status(0, 0, 0, True, 0, t))
        core.on_perception(floor_cloud(), t)

        def turning(now: float, core: ControlCore = core) -> bool:
            core.on_status(Status(0, 0, 0, True, 0, now))
            core.on_key("left", now)
            cmd = core.step(now)
            return cmd.left_duty < 0.0 < cmd.right_duty

        assert any(turning(t + 0.02 * k) for k in range(1, 30))
        t += 0.6
        core.link_ok = False  # the link reports itself unhealthy: stop at once
        core.on_key("left", t)
        cmd = core.step(t)
        assert (cmd.left_duty, cmd.right_duty, cmd.enable) == (0.0, 0.0, False)
        core.link_ok = True
        resumed = any(turning(t + 0.02 * k) for k in range(1, 30))
        assert resumed is (not rearm)
        if rearm:  # the rider lets go once (key expires), then asks again: turning
            core.on_status(Status(0, 0, 0, True, 0, t + 1.5))
            core.step(t + 1.5)
            assert any(turning(t + 1.5 + 0.02 * k) for k in range(1, 30))


def test_a_capture_that_does_not_fit_the_calibration_refuses_forward(caplog):
    """The rig knocked out of calibration (few dots on a calibrated beam in several captures in
    a row): the core says so, keeps the captures out of the map and refuses forward motion
    until a capture fits again; a single misfit capture is only kept out of the map."""
    from dataclasses import replace

    core, m = make_core()
    free_map(m)
    chair = Chair()
    run(core, chair, 0.0, 1.0)
    assert any(c.left_duty > 0 for c in run(core, chair, 1.0, 1.5))
    updates = len(m.clouds)
    n = core.config.perception.calibration_lost_clouds
    assert n >= 2
    # one misfit capture alone (a bad frame) is dropped, not taken for a knocked rig
    core.on_perception(replace(floor_cloud(), calibration_fit=0.1), 1.0)
    core.on_perception(replace(floor_cloud(), calibration_fit=0.95), 1.0)
    assert not core.calibration_lost and len(m.clouds) == updates + 1
    updates += 1
    for _ in range(n):
        core.on_perception(replace(floor_cloud(), calibration_fit=0.1), 1.5)
    cmds = run(core, chair, 1.5, 3.0)
    assert cmds[-1].left_duty == 0.0 and cmds[-1].right_duty == 0.0
    assert Reason.CALIBRATION_LOST in core.last_report.reasons
    assert "calibration_lost" in caplog.text
    assert len(m.clouds) == updates  # the misfit capture never reached the map
    core.on_perception(replace(floor_cloud(), calibration_fit=0.95), 3.0)
    assert any(c.left_duty > 0 for c in run(core, chair, 3.0, 4.5))


def test_a_capture_with_dots_not_understood_stays_out_of_the_map(caplog):
    """A floor-only calibration met an obstacle it cannot read (source unknown, not placed by
    the capture): the capture is kept out of the map, so the area is not taken as free and the
    chair stops as perception goes stale; a capture read in full is used again."""
    from dataclasses import replace

    core, m = make_core()
    free_map(m)
    chair = Chair()
    run(core, chair, 0.0, 1.0)
    assert any(c.left_duty > 0 for c in run(core, chair, 1.0, 1.5))
    updates, fresh = len(m.clouds), core.perception_time_s
    core.on_perception(replace(floor_cloud(), not_understood=40), 1.5)
    assert len(m.clouds) == updates and "not understood" in caplog.text
    assert core.perception_time_s == fresh  # not fresh perception: it goes stale
    cmds = run(core, chair, 1.5, 5.0, perceive=False)  # no usable capture since: stopped
    assert cmds[-1].left_duty == 0.0 and cmds[-1].right_duty == 0.0
    core.on_perception(replace(floor_cloud(), not_understood=1), 5.0)  # a ghost pair: used
    assert len(m.clouds) == updates + 1


def test_a_map_update_that_raises_forgets_the_map_and_refuses_until_a_clean_cloud():
    """A bug half way through the map's update (its cells written, then an exception): the
    map is not known to be right, so it is forgotten — everything unseen — and the core's
    perception is stale (no forward motion) until a cloud enters cleanly."""
    from omnid.core.freespace import FreeSpaceMap
    from omnid.core.occupancy import CellState

    class FailsWhenTold(FreeSpaceMap):
        fail = False

        def update(self, *args, **kwargs):
            super().update(*args, **kwargs)
            if self.fail:
                self.fail = False
                raise RuntimeError("a bug half way through the update")

    cfg = OmnidConfig(
        rider=RiderSettings(
            tilt=TiltSettings(dwell_s=0.1, neutral_calibration_s=0.0),
            joystick=JoystickSettings(enabled=False),
        )
    )
    m = FailsWhenTold(cfg.freespace)
    core = ControlCore(cfg, world_map=m)
    arm(core)
    core.on_perception(floor_cloud(), 0.0)
    assert core.perception_time_s == 0.0 and np.any(m.grid.states == CellState.FREE)
    m.fail = True
    with pytest.raises(RuntimeError):
        core.on_perception(floor_cloud(), 0.2)
    assert core.perception_time_s is None
    assert np.all(m.grid.states == CellState.UNKNOWN)  # forgotten, trail and all
    cmds = run(core, Chair(), 0.2, 1.0, perceive=False)
    assert all(c.left_duty == 0.0 and c.right_duty == 0.0 for c in cmds)
    assert Reason.PERCEPTION_STALE in core.last_report.reasons
    core.on_perception(floor_cloud(), 1.0)  # the next cloud enters cleanly
    assert core.perception_time_s == 1.0 and np.any(m.grid.states == CellState.FREE)
