"""The simulated cameras (omnid.sim.camera): frame clock, drops, laser timing, a world-fixed
scene that moves when the chair does — and the stream capture in the closed loop."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from omnid.core.types import PointClass
from omnid.sim.adapters import lit_share
from omnid.sim.camera import CameraModel, SimCamera, SimFrame
from omnid.sim.rigs import misaligned_rig
from omnid.sim.world import Box, RigMount, World


def _camera(model: CameraModel, world: World | None = None) -> SimCamera:
    return SimCamera(
        model, misaligned_rig(), RigMount(), world or World(), (-3000, 6000, -3000, 3000), seed=2
    )


def test_frames_come_on_a_free_running_clock_and_some_are_lost():
    cam = _camera(CameraModel(fps=30.0, drop_rate=0.2))
    frames = cam.delivered_until(10.0, lambda t: (t, 0.0, 0.0), lambda a, b: 1.0)
    steps = np.diff([f.t_s for f in frames]) * 30.0
    assert np.allclose(steps, np.round(steps), atol=1e-6) and steps.min() > 1 - 1e-6
    assert 0.15 < cam.dropped / (cam.dropped + cam.frames) < 0.25
    assert all(f.pose[0] == pytest.approx(f.t_s) for f in frames)  # the pose at the exposure
    assert cam.delivered_until(10.0, lambda t: (0.0, 0.0, 0.0), lambda a, b: 1.0) == []


def test_a_frame_shows_the_laser_by_the_share_of_its_exposure_it_was_lit():
    switches = [(0.105, True), (0.2, False)]
    assert lit_share(switches, 0.1, 0.11, False) == pytest.approx(0.5)
    assert lit_share(switches, 0.12, 0.13, False) == 1.0
    assert lit_share(switches, 0.21, 0.22, False) == 0.0
    assert lit_share([], 0.0, 1.0, True) == 1.0


def test_the_floor_moves_in_the_image_when_the_chair_drives_and_the_dots_do_not():
    cam = _camera(CameraModel(textured="world"))
    a, b = cam.scene(0, (0.0, 0.0, 0.0)), cam.scene(0, (60.0, 0.0, 0.0))
    inner = np.zeros_like(a, dtype=bool)
    inner[160:320, 220:420] = True
    moved = np.abs(a - b)[inner].mean()
    # the floor moved 60 mm back under the chair ≈ 6 px: the same texture 6 rows further down
    s = cam.rig.cam1.f_over_k_px / cam.mount.height_mm
    shift = round(60.0 * s)
    aligned = np.abs(b[160 + shift : 320 + shift, 220:420] - a[160:320, 220:420]).mean()
    assert moved > 3.0 and aligned < 0.35 * moved
    fixed = _camera(CameraModel(textured="camera"))
    assert np.array_equal(fixed.scene(0, (0.0, 0.0, 0.0)), fixed.scene(0, (60.0, 0.0, 0.2)))


def test_box_pixels_see_the_box_and_a_frame_keeps_the_world_it_was_exposed_in():
    cam = _camera(CameraModel(textured="world"))
    empty = cam.scene(0, (0.0, 0.0, 0.0))
    version = cam.set_world(World((Box(900.0, 1300.0, -300.0, 300.0, 500.0),)))
    with_box = cam.scene(0, (0.0, 0.0, 0.0))
    assert version == 1 and not np.array_equal(empty, with_box)
    assert np.array_equal(cam.scene(0, (0.0, 0.0, 0.0), world=0), empty)
    frame = SimFrame(0, 0.0, (0.0, 0.0, 0.0), 0.0, seed=1, world=0)
    assert frame.world == 0


@pytest.mark.parametrize("seed", [0, 1])
def test_stream_capture_in_the_closed_loop_at_full_speed(seed):
    """The daemon core with ``perception.capture: stream`` on the simulated cameras (30
    frames/s, a world-fixed texture, an 8–12 ms laser), joystick full forward past boxes
    beside the path: two clouds in three frames, nothing failed, no false obstacle point in
    the way, the chair at full speed and the masks moved by the wheels' motion."""
    from omnid.daemon.core import ControlCore
    from omnid.sim.course import Course, walls
    from omnid.sim.rider import JoystickScript
    from omnid.sim.scenario import make_core
    from omnid.sim.simulator import SimSettings, Simulator

    cfg = make_core(joystick=True).config
    cfg = dataclasses.replace(
        cfg,
        perception=dataclasses.replace(cfg.perception, capture="stream"),
        safety=dataclasses.replace(cfg.safety, perception_timeout_s=0.3),
    )
    core = ControlCore(cfg)
    boxes = (Box(1500.0, 1900.0, 950.0, 1400.0, 400.0), Box(2600.0, 3000.0, -1400.0, -950.0, 600.0))
    course = Course("side boxes", World(boxes + walls(-1000.0, 9000.0, -1700.0, 1700.0)),
                    (0.0, 0.0, 0.0), (-1000.0, 9000.0), (-1700.0, 1700.0))  # fmt: skip
    settings = SimSettings(
        perception="pipeline",
        seed=seed,
        laser_delay_s=0.008,
        laser_jitter_s=0.004,
        camera=CameraModel(exposure_s=0.0064, textured="world"),
        perceive_time_s=0.008,  # perceive's measured p50: the policy's rate, not this machine's
    )
    sim = Simulator(course, core, settings, joystick=JoystickScript(((0.0, 1.0, 0.0),)))
    false_in_path = []
    inner = sim.perceive_job

    def checked(job):  # type: ignore[no-untyped-def]
        cloud = inner(job)
        from omnid.sim.world import rig_to_world

        w = rig_to_world(cloud.xyz, job.base.source.pose, sim.mount)
        bad = (cloud.classes != PointClass.FLOOR) & (np.abs(w[:, 1]) < 700.0) & (w[:, 0] < 8000)
        false_in_path.append(int(bad.sum()))
        assert all(m is not None for m in job.mask_motions)
        return cloud

    sim.perceive_job = checked  # type: ignore[method-assign]
    # from start-up the chair creeps 250 mm (60 mm/s) through the band the laser cannot see
    # ahead of the footrests (safety.front_blind_mm), then speeds up: full speed from ~5 s
    r = sim.run(6.0)
    assert r.timings["clouds_per_s"] >= 15.0 and r.perception_errors == []
    assert r.contacts == [] and r.max_speed_between(5.0, 6.0) > 220.0
    assert sum(false_in_path) / len(false_in_path) < 0.05
