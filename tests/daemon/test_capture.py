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
    c = CaptureCycle(CaptureSettings("stationary", period_s=0.5), start_s=0.0)
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
    c = CaptureCycle(CaptureSettings("stationary", period_s=0.5, laser_timeout_s=0.2), start_s=1.0)
    c.poll(1.0)
    c.on_laser_report(True, 1.1)
    assert c.poll(1.19) == []
    (fail,) = c.poll(1.2)
    assert isinstance(fail, CaptureFailure) and fail.kind == "laser"
    assert "laser off within 0.2 s" in fail.message
    assert c.laser_on and not c.capturing and not c.wants_frame()
    assert c.next_poll_s == pytest.approx(1.5) and c.failures == 1


def test_no_frame_in_time_or_a_camera_error_fails_the_cycle():
    c = CaptureCycle(CaptureSettings("stationary", period_s=0.2, frame_timeout_s=0.3), start_s=0.0)
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
    c = CaptureCycle(CaptureSettings("stationary", period_s=0.5), start_s=0.0)
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


def test_settings_come_from_the_configuration():
    cfg = OmnidConfig()
    p = cfg.perception
    s = CaptureSettings.from_config(cfg)
    assert (s.period_s, s.laser_timeout_s, s.frame_timeout_s, s.flush_frames) == (
        p.period_s,
        p.laser_timeout_s,
        p.frame_timeout_s,
        p.flush_frames,
    )
    assert s.policy == p.capture
    assert s.frame_period_s == pytest.approx(1.0 / cfg.camera.fps)
    assert (s.exposure_s, s.laser_latency_s) == (cfg.camera.exposure_s, p.laser_switch_latency_s)
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
        "did not report the laser" in why for _, why in r.perception_errors
    )
    assert core.perception_time_s is None


class _Bench:
    """A camera at ``fps`` (exposure ``exposure_s``, delivered ``readout_s`` after its middle,
    random phase), a relay that follows the cycle's requests after ``relay_s`` (the command
    path included), replies every 20 ms, and the clocks of a chair at ``speed_mm_s`` — all on
    a 1 ms clock around one :class:`CaptureCycle` (as the daemon and the simulator drive it)."""

    def __init__(self, settings: CaptureSettings, relay_s: float, seed: int = 0, **kw) -> None:
        rng = np.random.default_rng(seed)
        self.cycle = CaptureCycle(settings, start_s=0.0)
        self.relay_s = relay_s
        self.fps = kw.get("fps", 30.0)
        self.exposure_s = kw.get("exposure_s", 0.008)
        self.readout_s = kw.get("readout_s", 0.006)
        self.drop = kw.get("drop", 0.0)
        self.speed = kw.get("speed_mm_s", 0.0)
        self.reports = kw.get("reports", True)
        self.phase = float(rng.uniform(0, 1 / self.fps))
        self.rng = rng
        self.requests: list[tuple[float, bool]] = [(-1.0, True)]
        self.jobs: list[CaptureJob] = []
        self.failures: list[CaptureFailure] = []

    def light(self, t: float) -> bool:
        state = False
        for r, on in self.requests:
            if r + self.relay_s <= t:
                state = on
        return state

    def lit(self, t0: float, t1: float) -> float:
        ts = np.linspace(t0, t1, 41)
        return float(np.mean([self.light(t) for t in ts]))

    def run(self, seconds: float, late_s: float = 0.0) -> None:
        """Poll every 1 ms tick; with ``late_s`` only when a reply or frame came or the
        cycle's :attr:`~CaptureCycle.next_poll_s` is due, and then ``late_s`` late (an event
        loop on a busy computer)."""
        c = self.cycle
        k = 0
        due = 0.0
        for i in range(int(seconds * 1000) + 1):
            now = i / 1000
            if self.reports and i % 20 == 0:
                clocks = int(self.speed * now / (471.0 / 15.0))

                class St:
                    laser_on = self.light(now)
                    timestamp_s = now
                    left_clocks = right_clocks = clocks

                c.on_status(St)
                due = min(due, now)
            while self.phase + k / self.fps + self.readout_s <= now:
                t = self.phase + k / self.fps
                k += 1
                if self.rng.uniform() < self.drop:
                    continue
                half = self.exposure_s / 2
                c.on_frame(Frame(t, None, self.lit(t - half, t + half)))
                due = min(due, now)
            if late_s > 0 and now + 1e-9 < min(due, c.next_poll_s) + late_s:
                continue
            due = float("inf")
            before = c.laser_on
            for out in c.poll(now):
                (self.jobs if isinstance(out, CaptureJob) else self.failures).append(out)
            if c.laser_on != before:
                self.requests.append((now, c.laser_on))


def _stream(**changes) -> CaptureSettings:
    return CaptureSettings(**{"policy": "stream", "laser_latency_s": 0.018, **changes})


@pytest.mark.parametrize("seed", range(6))
def test_stream_gives_two_clouds_in_three_frames_and_never_mixes_laser_states(seed):
    """30 frames/s, a 12 ms laser (configured worst case 18 ms), a mask every 3rd frame: 20
    jobs/s; every base frame wholly lit, every mask wholly dark, each base between the masks
    before and after it (at most 2 frames away); no failure."""
    b = _Bench(_stream(), relay_s=0.012, seed=seed)
    b.run(6.0)
    assert b.failures == []
    jobs = [j for j in b.jobs if j.t_s > 1.0]
    assert len(jobs) / 5.0 >= 19.0
    assert all(j.base.source == 1.0 for j in jobs)
    assert all(m.source == 0.0 for j in jobs for m in j.masks)
    assert all(len(j.masks) == 2 for j in jobs)
    for j in jobs:
        before, after = (m.t_s for m in j.masks)
        assert before < j.t_s < after and after - before < 3.5 / 30


@pytest.mark.parametrize("late_ms", [3, 6, 10])
def test_a_loop_that_polls_late_still_takes_masks_and_never_mixes_laser_states(late_ms):
    """The laser-off request for a mask has a ~3 ms window at 30 frames/s (after the
    exposure before it, 18 ms of latency before the mask's). A loop always later than that
    spoils the frame after the window instead: a job for every 3 frames or more, never none
    (it took none at all, silently, before), every base wholly lit, every mask wholly dark."""
    for seed in range(4):
        b = _Bench(_stream(), relay_s=0.012, seed=seed)
        b.run(4.0, late_s=late_ms / 1000)
        jobs = [j for j in b.jobs if j.t_s > 1.0]
        assert b.failures == [] and len(jobs) / 3.0 >= 7.0, (seed, len(jobs))
        assert all(j.base.source == 1.0 for j in jobs)
        assert all(m.source == 0.0 for j in jobs for m in j.masks)
        # a base subtracted against two masks lies between them (one before, one after)
        assert all(j.masks[0].t_s < j.t_s < j.masks[-1].t_s for j in jobs if len(j.masks) == 2)


def test_a_laser_too_slow_to_switch_between_frames_costs_the_frames_around_the_mask():
    """A 22 ms laser (configured 30 ms) cannot go dark between two exposures 33 ms apart: the
    frame before and after each mask are not used; with a mask every 6th frame, 3 of 6 are."""
    b = _Bench(_stream(laser_latency_s=0.03, mask_every_frames=6), relay_s=0.022, seed=3)
    b.run(4.0)
    jobs = [j for j in b.jobs if j.t_s > 1.0]
    assert b.failures == [] and len(jobs) / 3.0 >= 14.0
    assert all(j.base.source == 1.0 and all(m.source == 0.0 for m in j.masks) for j in jobs)


def test_without_bracketing_a_base_goes_at_once_with_the_mask_before_it():
    b = _Bench(_stream(mask_bracketing=False), relay_s=0.012, seed=5)
    b.run(3.0)
    jobs = [j for j in b.jobs if j.t_s > 1.0]
    assert len(jobs) / 2.0 >= 19.0
    assert all(len(j.masks) == 1 and j.masks[0].t_s < j.t_s for j in jobs)


def test_stream_motion_from_each_mask_to_the_base_follows_the_wheels():
    b = _Bench(_stream(), relay_s=0.012, seed=1, speed_mm_s=240.0)
    b.run(3.0)
    jobs = [j for j in b.jobs if j.t_s > 1.0]
    assert jobs
    for j in jobs:
        for m, motion in zip(j.masks, j.mask_motions, strict=True):
            dx, dy, dth = motion  # type: ignore[misc]
            expect = 240.0 * (j.t_s - m.t_s)
            assert dx == pytest.approx(expect, abs=15.0) and abs(dy) < 1e-6 and abs(dth) < 1e-9


def test_a_laser_slower_than_configured_fails_and_no_frame_is_used_until_replies_agree():
    b = _Bench(_stream(), relay_s=0.05, seed=2)
    b.run(2.0)
    assert b.failures and all(f.kind == "laser" for f in b.failures)
    assert "perception.laser_switch_latency_s" in b.failures[0].message
    for j in b.jobs:  # what was used is still never mixed
        assert j.base.source == 1.0 and all(m.source == 0.0 for m in j.masks)


def test_no_replies_means_no_job_and_a_laser_failure():
    b = _Bench(_stream(laser_timeout_s=0.3), relay_s=0.012, seed=0, reports=False)
    b.run(1.5)
    assert b.jobs == []
    assert b.failures and "did not report the laser" in b.failures[0].message


def test_dropped_frames_cost_clouds_not_correctness():
    b = _Bench(_stream(), relay_s=0.012, seed=4, drop=0.2)
    b.run(6.0)
    jobs = [j for j in b.jobs if j.t_s > 1.0]
    assert len(jobs) / 5.0 >= 12.0
    assert all(j.base.source == 1.0 and all(m.source == 0.0 for m in j.masks) for j in jobs)
    assert all(abs(j.t_s - m.t_s) <= 0.3 for j in jobs for m in j.masks)


def test_cameras_that_stop_fail_the_stream():
    b = _Bench(_stream(frame_timeout_s=0.5), relay_s=0.012, seed=0, drop=1.0)
    b.run(1.2)
    assert any(f.kind == "camera" for f in b.failures)
