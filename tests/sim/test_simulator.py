"""The closed-loop simulator on its virtual clock: contacts, laser honesty, latency, watchdog."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnid.core.types import PointClass, PointCloud
from omnid.sim.chair import ChairSettings
from omnid.sim.course import Course, builtin_course, empty_room
from omnid.sim.simulator import DirectControlUnit, OpenLoopDriver, SimSettings, Simulator
from omnid.sim.world import Box, DropOff, World

STRAIGHT = ChairSettings(right_gain=1.0)  # no gain mismatch: drives straight open loop


def _course(world: World) -> Course:
    return Course("test", world, (0.0, 0.0, 0.0), (-1000.0, 5000.0), (-2000.0, 2000.0))


def test_open_loop_chair_hits_the_wall_and_is_blocked_there_the_run_goes_on():
    sim = Simulator(empty_room(3500.0), OpenLoopDriver([(0.0, 1.0, 1.0)]), chair_settings=STRAIGHT)
    result = sim.run(30.0)
    assert [c.kind for _, c in result.contacts] == ["collision"]
    t_hit = result.contacts[0][0]
    # Front wall at x = 2500, footprint front 350 mm ahead of the axle: contact at x ≈ 2150 mm,
    # reached at full speed 235.5 mm/s after the motor lag (0.15 s) and one 50 ms command period
    # (the first frame on the wire is always zero: protocol "Freshness").
    assert result.trajectory[-1, 1] == pytest.approx(2150.0, abs=5.0)
    assert t_hit == pytest.approx(2150.0 / STRAIGHT.max_speed_mm_s + 0.15 + 0.05, abs=0.05)
    assert result.duration_s == pytest.approx(30.0)  # a contact is a blocked chair, not the end
    assert result.max_speed_between(t_hit + 0.05, 30.0) == 0.0  # the wheels stall against it
    assert result.min_clearance_mm == 0.0


def test_with_contact_pass_the_chair_drives_through_and_the_run_stops_at_the_contact():
    settings = SimSettings(contact="pass")
    sim = Simulator(
        empty_room(3500.0), OpenLoopDriver([(0.0, 1.0, 1.0)]), settings, chair_settings=STRAIGHT
    )
    result = sim.run(30.0)
    assert [c.kind for _, c in result.contacts] == ["collision"]
    assert result.duration_s == pytest.approx(result.contacts[0][0])


def test_open_loop_chair_falls_down_the_stairs():
    world = World(dropoffs=(DropOff(1000.0, 3000.0, -2000.0, 2000.0, 170.0),))
    result = Simulator(
        _course(world), OpenLoopDriver([(0.0, 0.8, 0.8)]), chair_settings=STRAIGHT
    ).run(20.0)
    assert [c.kind for _, c in result.falls] == ["fall"]
    # The front (drive) wheels on the axle go over the edge first.
    assert "front (drive) wheel" in result.falls[0][1].part
    assert result.trajectory[-1, 1] == pytest.approx(1000.0, abs=3.0)


def test_stopped_chair_in_the_builtin_course_touches_nothing():
    result = Simulator(builtin_course(), OpenLoopDriver([(0.0, 0.0, 0.0)])).run(2.0)
    assert result.contacts == [] and result.distance_mm == 0.0
    assert result.min_clearance_mm > 200.0


class _Probe(OpenLoopDriver):
    """Records what the simulator hands a controller, and when (virtual time)."""

    def __init__(self, laser_on: bool = True, duty: float = 0.0) -> None:
        super().__init__([(0.0, duty, duty)])
        self.laser_on = laser_on
        self.now = 0.0
        self.sim: Simulator | None = None
        self.clouds: list[tuple[float, float, PointCloud]] = []
        self.statuses: list = []

    def step(self, now_s):
        self.now = now_s
        cmd = super().step(now_s)
        return type(cmd)(cmd.left_duty, cmd.right_duty, laser_on=self.laser_on, enable=True)

    def on_status(self, status):
        self.statuses.append(status)

    def on_perception(self, cloud, capture_time_s):
        self.clouds.append((self.sim.now_s if self.sim else math.nan, capture_time_s, cloud))


def test_perception_sees_a_box_ahead_with_true_classes_and_latency():
    world = World(boxes=(Box(1500.0, 1800.0, -400.0, 400.0, 500.0),))
    probe = _Probe()
    settings = SimSettings(perception_latency_s=0.15, truth_noise_mm=0.0)
    sim = Simulator(_course(world), probe, settings=settings)
    probe.sim = sim
    sim.run(1.0)
    assert probe.clouds
    for delivered_at, captured_at, _ in probe.clouds:
        assert delivered_at - captured_at >= 0.15 - 1e-9
    # The first capture happened before the first command switched the laser on (t = 0 is the
    # same tick; perception runs first): it must be empty. Later ones see floor and the box.
    assert len(probe.clouds[0][2]) == 0
    cloud = probe.clouds[-1][2]
    obstacle = cloud.classes == PointClass.OBSTACLE
    assert np.count_nonzero(obstacle) > 20
    assert np.count_nonzero(cloud.classes == PointClass.FLOOR) > 50
    # Box face at world x = 1500: rig X = 1500 − 300 (rig mount offset).
    assert np.min(cloud.xyz[obstacle, 0]) == pytest.approx(1200.0, abs=1.0)


def test_laser_off_gives_no_dots_and_an_undotted_base_frame():
    probe = _Probe(laser_on=False)
    sim = Simulator(empty_room(), probe, settings=SimSettings(truth_noise_mm=0.0))
    probe.sim = sim
    sim.run(0.5)
    assert all(len(c) == 0 for _, _, c in probe.clouds)
    off = sim.render(seed=1)
    on = sim.render(laser_on=True, seed=1)
    diff_off = off.base1.astype(int) - off.mask1.astype(int)
    diff_on = on.base1.astype(int) - on.mask1.astype(int)
    assert diff_off.max() < 30  # sensor noise only
    assert np.count_nonzero(diff_on > 60) > 100  # the dots


def test_status_carries_the_plants_clocks():
    probe = _Probe(duty=0.5)
    sim = Simulator(empty_room(), probe, chair_settings=STRAIGHT)
    sim.run(2.0)
    assert [s.seq for s in probe.statuses] == list(range(1, len(probe.statuses) + 1))
    # A relay may take a moment after the first command (the emulator's: 20 ms).
    assert all(s.laser_on for s in probe.statuses[1:])
    clocks = [s.left_clocks for s in probe.statuses]
    assert clocks == sorted(clocks) and clocks[-1] >= 6  # 2 s at ~118 mm/s: ~7 clocks of 31.4
    assert abs(clocks[-1] - sim.chair.clocks()[0]) <= 1  # last reply is one tick old at most


def test_control_unit_watchdog_stops_a_silent_link():
    from omnid.sim.chair import Chair

    chair = Chair(STRAIGHT)
    cu = DirectControlUnit(chair, watchdog_s=0.25)
    cu.exchange(OpenLoopDriver([(0.0, 1.0, 1.0)]).step(0.0), 0.0)
    for k in range(100):  # 1 s with no further command
        cu.advance(k * 0.01, 0.01)
    assert cu.watchdog_trips == 1
    assert (cu.left_duty, cu.right_duty) == (0.0, 0.0)
    # Stopped after ~0.26 s of driving plus the lag run-out: well under 0.26 s·v_max + τ·v_max.
    assert chair.x_mm < STRAIGHT.max_speed_mm_s * (0.27 + 0.15)
    assert math.isclose(chair.left_speed_mm_s, 0.0, abs_tol=5.0)  # e^(−0.74/0.15) of full speed


def test_disabled_command_brakes_whatever_the_duties_say():
    from omnid.sim.chair import Chair

    chair = Chair(STRAIGHT)
    cu = DirectControlUnit(chair)

    class _Cmd:
        left_duty, right_duty, laser_on, enable = 1.0, 1.0, False, False

    cu.exchange(_Cmd(), 0.0)
    cu.advance(0.0, 0.1)
    assert chair.pose == (0.0, 0.0, 0.0)


def test_simulate_command_writes_a_report_with_the_crash(tmp_path, capsys):
    import cv2

    from omnid.cli import main

    out = tmp_path / "run"
    code = main(
        [
            "simulate",
            "--course",
            "empty-room",
            "--drive",
            "0:1:1",
            "--duration-s",
            "20",
            "--out",
            str(out),
            "--quiet",
        ]
    )
    assert code == 0
    report = (out / "report.md").read_text()
    assert "collisions: 1" in report and "collision (footprint)" in report
    png = cv2.imread(str(out / "course.png"))
    assert png is not None and png.shape[0] > 300 and png.shape[1] > 200
    assert "report:" in capsys.readouterr().out


def test_simulate_command_rejects_a_bad_drive_in_one_line(capsys):
    from omnid.cli import main

    assert main(["simulate", "--drive", "0:2:1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--drive '0:2:1'" in err[0]


def test_rider_head_script_reaches_the_controller_on_the_virtual_clock():
    from omnid.sim.rider import command_of, head_script

    script = head_script([("forward", 1.0), ("left", 0.5)], tilt_deg=20.0, move_s=0.2)

    class _TiltProbe(OpenLoopDriver):
        def __init__(self) -> None:
            super().__init__([(0.0, 0.0, 0.0)])
            self.readings: list = []

        def on_tilt(self, reading):
            self.readings.append(reading)

    probe = _TiltProbe()
    Simulator(empty_room(), probe, rider=script, settings=SimSettings(perception="off")).run(2.0)
    times = [r.timestamp_s for r in probe.readings]
    assert len(times) == 201 and times[1] - times[0] == pytest.approx(0.01)
    by_time = {round(r.timestamp_s, 2): r for r in probe.readings}
    assert command_of(by_time[0.1].roll_deg, by_time[0.1].pitch_deg, 12.0) == "neutral"
    # half-way through the 0.2 s move; through the GS311 codec: 12-bit counts of 90/4096 deg
    assert by_time[0.1].roll_deg == pytest.approx(-10.0, abs=90.0 / 4096.0)
    assert command_of(by_time[0.8].roll_deg, by_time[0.8].pitch_deg, 12.0) == "forward"
    assert command_of(by_time[1.6].roll_deg, by_time[1.6].pitch_deg, 12.0) == "left"


# -- closed loop with the daemon's core ----------------------------------------------------------


def _core():
    pytest.importorskip("omnid.daemon.core", reason="the daemon core has not landed in this tree")
    from omnid.sim.scenario import make_core

    return make_core()


def _story_run(
    perception: str, seed: int = 0, duration_s: float = 80.0, worker_period_s: float = 0.0
):
    from omnid.sim.scenario import make_core
    from omnid.sim.story import demo_story

    _core()
    core = make_core(joystick=True, tilt=True)  # head tilt; the joystick only to back away
    settings = SimSettings(
        perception=perception,  # type: ignore[arg-type]
        seed=seed,
        worker_period_s=worker_period_s,
        perceive_time_s=0.01,  # the same run on a loaded machine
    )
    return Simulator(builtin_course(), core, settings, rider=demo_story()).run(duration_s)


def test_reactive_rider_moves_on_after_a_timeout_when_the_chair_never_does():
    """A chair that refuses everything (the open-loop driver never moves): each step times out
    and the story still ends, with every step recorded as a timeout."""
    from omnid.sim.story import ReactiveRider, Step, moved, refused

    rider = ReactiveRider(
        (
            Step("forward", moved(100.0), 2.0, head="forward", settle_s=0.5),
            Step("back", refused("obstacle_stop"), 1.0, stick=(-0.5, 0.0), settle_s=0.5),
        ),
        start_s=0.5,
    )
    sim = Simulator(empty_room(), OpenLoopDriver([(0.0, 0.0, 0.0)]), rider=rider,
                    settings=SimSettings(perception="off"))  # fmt: skip
    result = sim.run(30.0)
    assert [(r.what, r.ended) for r in result.story] == [
        ("forward", "timeout"),
        ("back", "timeout"),
    ]
    assert result.story[0].t1_s == pytest.approx(2.5, abs=0.02)
    assert result.story[1].t0_s == pytest.approx(3.0, abs=0.02)
    assert result.duration_s == pytest.approx(4.0 + 0.5 + 1.0, abs=0.05)


@pytest.mark.slow(seconds=25)
def test_demo_story_with_pipeline_perception():
    """The demo as `omnid demo` runs it: wide passage passed, narrow refused, stop before the
    stairs, turn towards box 3 (outside the laser's field) refused, nothing touched; and the
    reactive rider's own behaviour: each step ended by what the chair did, the head driving,
    the joystick only backing away."""
    from omnid.sim.report import story_checks

    # Seeds 0 and 2 play the whole story; seed 1 still meets a phantom obstacle row in the
    # middle room (a false stop 2 m before the narrow passage: safe, but wrong) — see
    # docs/benchmarks/perception.md, "closed-loop phantom".
    # the shipped stream capture; a computer perceiving at most 10 clouds/s (half this one's
    # rate: the suite's time; `omnid demo` runs at the full rate and plays the same story)
    result = _story_run("pipeline", seed=0, duration_s=130.0, worker_period_s=0.1)
    # a turn's swing nears what is beside the chair to its stopping distance and buffer outside
    # the side margin (25 mm), not the 150 mm stop zone (measured 46 mm at box 3): the margin kept
    assert result.contacts == [] and result.min_clearance_mm > 25.0
    assert result.falls == []  # no wheel over the stairs' edge
    failed = [(what, ev) for what, ok, ev in story_checks(result) if not ok]
    assert failed == []
    # the reactive rider: every step ends by what the chair did (not by its timeout), in order;
    # the run ends 2 s after the last step (1 s settle + 1 s rest)
    assert [r.ended for r in result.story] == ["done"] * 6
    assert result.duration_s == pytest.approx(result.story[-1].t1_s + 1.0 + 1.0, abs=0.05)
    # the head drove (tilt reasons), the joystick only backed away
    backing = result.story[2]
    assert backing.what == "back away" and "moved" in backing.evidence
    fwd = result.steps[:, 6]
    t = result.steps[:, 0]
    assert np.all(fwd[(t > backing.t1_s + 0.5) | (t < backing.t0_s)] >= 0.0)
    assert np.any(fwd[(t >= backing.t0_s) & (t <= backing.t1_s)] < 0.0)


def test_every_control_step_records_the_cores_reasons():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
    from safety_figures import room  # type: ignore[import-not-found]

    from omnid.sim.rider import JoystickScript
    from omnid.sim.scenario import make_core

    core = make_core(joystick=True)
    stick = JoystickScript(((0.2, 1.0, 0.0),))
    course = room(1200.0)  # front wall 850 mm ahead of the footrests: inside the slow zone soon
    r = Simulator(course, core, SimSettings(perception="truth"), joystick=stick).run(4.0)
    # 50 Hz for 4 s, both ends, plus the extra cycles a laser switch runs at once
    grid = np.round(r.steps[:, 0] / 0.02, 6)
    assert set(np.arange(201.0)) <= set(grid) and r.steps.shape[1] == 7
    assert np.all(np.diff(r.steps[:, 0]) > 0)
    limited = r.steps[:, 1].astype(int) & r.reason_mask("slow_zone", "approach", "obstacle_stop")
    assert np.any(limited)  # limits are recorded, not only refusals
    i = int(np.flatnonzero(limited)[0])
    assert set(r.reasons_at(i)) & {"slow_zone", "approach", "obstacle_stop"}
    assert r.contacts == []
