"""A small, fast subset of the safety scenario suite (``omnid.sim.suite``; the whole suite, both
riders, several seeds and pipeline perception: ``python tools/safety_figures.py --suite``,
docs/benchmarks.md). Truth perception unless a test says otherwise. Where the seeds are few,
each rider gets others: the rates over seeds are the tool's."""

from __future__ import annotations

import dataclasses

import pytest

from omnid.sim.suite import SCENARIOS, clutter, run_trial, way_clear


@pytest.mark.parametrize(("kind", "seeds"), [("joystick", (0, 1, 2)), ("tilt", (0,))])
@pytest.mark.slow(seconds=4)
def test_reversing_into_the_unseen_never_touches_the_box(kind, seeds):
    """A box 300 mm behind the chair, never seen: reversing is refused, whatever the seed; the
    head rider, who has no reverse, turns round in place and its tail is refused the same way."""
    for seed in seeds:
        r = run_trial(SCENARIOS["reversing into the unseen"](kind, seed))
        assert r.contacts == 0 and r.falls == 0, seed
        assert r.refusals.get("unknown_stop", 0) > 0
        assert r.min_clearance_mm > 250.0  # it never moved towards it


def test_with_the_creep_policy_reversing_into_the_unseen_is_a_noticed_bump():
    r = run_trial(SCENARIOS["reversing into the unseen"]("joystick", 0), "truth",
                  {"unknown_policy": "creep"})  # fmt: skip
    assert r.contacts == 1  # backed into it at creep speed, once: then refused (bump)
    assert r.refusals.get("bump", 0) > 0


@pytest.mark.parametrize(("kind", "seed"), [("joystick", 0), ("tilt", 1)])
@pytest.mark.slow(seconds=4)
def test_turning_beside_an_unseen_wall_never_swings_the_tail_into_it(kind, seed):
    r = run_trial(SCENARIOS["turn beside an unseen wall"](kind, seed))  # type: ignore[arg-type]
    assert r.contacts == 0
    assert r.refusals.get("unknown_stop", 0) > 0


@pytest.mark.parametrize(("width", "seed"), [(900, 0), (780, 0)])
@pytest.mark.slow(seconds=5)
def test_doorways_wider_than_the_chair_and_its_margins_are_passed_narrower_refused(width, seed):
    """Truth perception, the joystick steering through from 3.5 m off (±10°, ±80 mm): a 900 mm
    doorway is passed without a safety stop at the door; a 780 mm one (the chair 700 + 2 × 25 side margin +
    the rider's aim) is never touched. (One trial per test: the suite's workers share them.)
    Of the trial's 60 s, 32: the 900 mm door is passed by ~25 s; 26: the chair stands before
    the 780 mm one from ~21 s (and lets go at ~23 s)."""
    trial = dataclasses.replace(
        SCENARIOS[f"doorway {width} mm"]("joystick", seed),
        duration_s=32.0 if width == 900 else 26.0,
    )
    r = run_trial(trial)
    assert r.contacts == 0, seed
    if width == 900:
        # no safety stop at the door (the first steering after the straight start may be refused
        # for a moment, 1.7 m before it: the floor beside the tail at start-up was never seen)
        assert r.passed and r.safety_stops_at_door == 0, (seed, r.safety_stop_reasons)
        assert r.min_speed_in_opening_mm_s > 80.0 and r.min_allowed_in_opening_mm_s > 80.0
        assert r.rider_let_goes == 0  # never refused long enough to give up
    else:
        # the way refused at the jamb: the rider lets go of the stick after 1.5 s and backs off
        # to try again
        log = trial.rider_input.let_go_log
        assert r.rider_let_goes == len(log) >= 1
        assert any("obstacle_stop" in said and retry == "back" for _, said, retry in log), log


@pytest.mark.slow(seconds=8)
def test_a_thin_post_with_pipeline_perception_stops_the_chair_before_it():
    # the shipped stream capture on a worker perceiving at most 10 clouds/s (the suite's time;
    # as tests/scenarios/test_scenarios.py)
    slower = {"worker_period_s": 0.1, "perceive_time_s": 0.01}
    # the head rider (both riders: the tool); 20 s of the trial's 30: at rest before the post
    # from ~15 s (the same figures as 30 s)
    trial = dataclasses.replace(SCENARIOS["thin post"]("tilt", 0), duration_s=20.0)  # type: ignore[arg-type]
    r = run_trial(trial, "pipeline", sim_changes=slower)
    assert r.contacts == 0
    assert 100.0 < r.stop_clearance_mm < 400.0
    assert r.stop_to_standstill_s < 1.0


def test_false_stop_truth_check_sees_a_box_in_the_way_and_not_one_beside_it():
    from omnid.sim.suite import _outline, _rects

    trial = clutter("joystick", 0, 10.0)
    outline = _outline(_rects(trial.course))

    class _Cfg:  # the daemon's motion limits
        from omnid.daemon.motion import MotionSettings

        motion = MotionSettings()

    core = type("C", (), {"config": _Cfg()})()
    # box 1 is at x 800..1200, y 600..1000: straight ahead of a chair at (0, 800) facing +x
    assert not way_clear((0.0, 800.0, 0.0), 0.6, 0.0, outline, core)
    assert way_clear((0.0, -200.0, 0.0), 0.6, 0.0, outline, core)


def test_path_clearance_is_the_travel_to_contact_along_the_motion_not_the_nearest_gap():
    """The hazard response's clock starts on how far the true footprint can travel before it
    touches the hazard (the rules' distance), not on the nearest gap: a wall at 35° across the
    path is farther along the path than across; a wall beside the path is never reached."""
    import math

    import numpy as np

    from omnid.sim.suite import FOOTPRINT, _outline, footprint_clearance_mm, path_clearance_mm

    front = FOOTPRINT[0]
    ahead = np.array([[1000.0 + front, 1100.0 + front, -2000.0, 2000.0]])  # 1000 mm ahead
    assert path_clearance_mm((0.0, 0.0, 0.0), 200.0, 0.0, _outline(ahead, 5.0)) == (
        pytest.approx(1000.0, abs=6.0)
    )
    assert math.isinf(path_clearance_mm((0.0, 0.0, 0.0), 0.0, 0.0, _outline(ahead)))  # at rest
    assert math.isinf(path_clearance_mm((0.0, 0.0, 0.0), -80.0, 0.0, _outline(ahead)))  # backing
    beside = np.array([[-3000.0, 3000.0, 400.0, 500.0]])  # 50 mm beside the 700 mm chair
    assert footprint_clearance_mm((0.0, 0.0, 0.0), beside) == pytest.approx(50.0, abs=1.0)
    assert math.isinf(path_clearance_mm((0.0, 0.0, 0.0), 200.0, 0.0, _outline(beside)))
    # the same wall turned 35° to the heading: the nearest gap is smaller than the travel
    th = math.radians(35.0)
    pose = (0.0, 0.0, th)  # heading 35° toward a wall along x at y = 900
    wall = np.array([[-5000.0, 5000.0, 900.0, 1000.0]])
    near = footprint_clearance_mm(pose, wall)
    travel = path_clearance_mm(pose, 200.0, 0.0, _outline(wall, 5.0))
    assert travel > 1.5 * near
