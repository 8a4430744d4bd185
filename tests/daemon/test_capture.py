"""The capture cycle (omnid.daemon.capture): one state machine for the daemon and the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.daemon.capture import (
    CaptureCycle,
    CaptureFailure,
    CaptureJob,
    CaptureSettings,
    Frame,
)
from omnid.daemon.config import OmnidConfig


def _frame(t: float, level: int = 0) -> Frame:
    img = np.full((4, 6), level, np.uint8)
    return Frame(t, (img, img + 1))


def test_stationary_cycle_switches_the_laser_and_waits_for_each_report():
    c = CaptureCycle(CaptureSettings(period_s=0.5), start_s=0.0)
    assert c.poll(0.0) == [] and not c.laser_on and c.capturing
    assert not c.wants_frame()
    c.on_laser_report(False, 0.0)  # a reply stamped at the request itself: not after it
    assert c.poll(0.01) == [] and not c.wants_frame()
    c.on_laser_report(True, 0.02)  # still on (the relay lags)
    assert c.poll(0.02) == [] and not c.wants_frame()
    c.on_laser_report(False, 0.04)
    c.poll(0.04)
    assert c.wants_frame() and c.flush_needed and c.frame_deadline_s == pytest.approx(1.04)
    c.on_frame(_frame(0.07, 10))
    assert c.poll(0.08) == [] and c.laser_on and c.capturing and not c.wants_frame()
    c.on_laser_report(False, 0.09)  # the old state, after the request: keep waiting
    assert c.poll(0.09) == [] and not c.wants_frame()
    c.on_laser_report(True, 0.1)
    c.poll(0.1)
    assert c.wants_frame()
    c.on_frame(_frame(0.13, 20))
    (job,) = c.poll(0.14)
    assert isinstance(job, CaptureJob)
    assert job.t_s == 0.13 and [m.t_s for m in job.masks] == [0.07] and job.started_s == 0.0
    cap = job.stereo_capture()
    assert cap.mask1[0, 0] == 10 and cap.base2[0, 0] == 21 and cap.timestamp_s == 0.13
    assert c.laser_on and not c.capturing and c.phase == "idle"
    assert c.next_poll_s == pytest.approx(0.5)  # the next cycle one period after this one began
    assert c.poll(0.49) == [] and c.poll(0.5) == [] and not c.laser_on


def test_a_laser_that_is_never_reported_fails_the_cycle_and_turns_it_back_on():
    c = CaptureCycle(CaptureSettings(period_s=0.5, laser_timeout_s=0.2), start_s=1.0)
    c.poll(1.0)
    c.on_laser_report(True, 1.1)
    assert c.poll(1.19) == []
    (fail,) = c.poll(1.2)
    assert isinstance(fail, CaptureFailure) and fail.kind == "laser"
    assert "laser off within 0.2 s" in fail.message
    assert c.laser_on and not c.capturing and not c.wants_frame()
    assert c.next_poll_s == pytest.approx(1.5) and c.failures == 1


def test_no_frame_in_time_or_a_camera_error_fails_the_cycle():
    c = CaptureCycle(CaptureSettings(period_s=0.2, frame_timeout_s=0.3), start_s=0.0)
    c.poll(0.0)
    c.on_laser_report(False, 0.05)
    c.poll(0.05)
    assert c.poll(0.34) == []
    (fail,) = c.poll(0.35)
    assert fail.kind == "camera" and "0.3 s" in fail.message  # type: ignore[union-attr]
    assert c.next_poll_s == pytest.approx(0.35)  # overdue: the next cycle starts at once
    c.poll(0.35)
    c.on_laser_report(False, 0.4)
    c.poll(0.4)
    c.frame_failed("DeviceError: camera unplugged")
    (fail,) = c.poll(0.41)
    assert fail.kind == "camera" and fail.message == "DeviceError: camera unplugged"  # type: ignore[union-attr]


def test_frames_nobody_asked_for_are_ignored():
    c = CaptureCycle(CaptureSettings(period_s=0.5), start_s=0.0)
    c.on_frame(_frame(0.0))
    c.poll(0.0)
    c.on_frame(_frame(0.01))  # laser not yet reported off: not a mask
    c.on_laser_report(False, 0.03)
    c.poll(0.03)
    assert c.wants_frame() and c.ignored_frames == 2


def test_snapshot_takes_one_unflushed_frame_per_period_and_leaves_the_laser_alone():
    c = CaptureCycle(CaptureSettings(policy="snapshot", period_s=0.2), start_s=0.0)
    c.poll(0.0)
    assert c.wants_frame() and not c.flush_needed and c.laser_on and not c.capturing
    c.on_frame(_frame(0.0))
    (job,) = c.poll(0.0)
    assert isinstance(job, CaptureJob) and job.masks == ()
    assert c.poll(0.1) == [] and not c.wants_frame()
    c.poll(0.2)
    assert c.wants_frame()


def test_settings_come_from_the_perception_configuration():
    p = OmnidConfig().perception
    s = CaptureSettings.from_config(p)
    assert (s.period_s, s.laser_timeout_s, s.frame_timeout_s, s.flush_frames) == (
        p.period_s,
        p.laser_timeout_s,
        p.frame_timeout_s,
        p.flush_frames,
    )
    with pytest.raises(ValueError, match="period_s"):
        CaptureSettings(period_s=0.0)


def test_the_simulator_drives_the_same_cycle_and_fails_as_the_daemon_does():
    """A control unit that never answers: the simulated daemon's perception cycle fails with
    the daemon's laser timeout (it used to take the mask frame anyway), and the chair gets no
    cloud."""
    from omnid.sim.course import empty_room
    from omnid.sim.scenario import make_core
    from omnid.sim.simulator import Fault, SimSettings, Simulator

    core = make_core()
    sim = Simulator(
        empty_room(), core, SimSettings(perception="truth"), faults=[Fault("cu_silent", 0.0)]
    )
    assert isinstance(sim.capture_cycle, CaptureCycle)
    r = sim.run(1.2)
    assert r.perception_errors and all(
        "did not report the laser off" in why for _, why in r.perception_errors
    )
    assert core.perception_time_s is None
