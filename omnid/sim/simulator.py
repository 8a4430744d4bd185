"""The closed-loop simulator: world + chair + control unit + rider + perception + daemon core.

Fast mode (:meth:`Simulator.run`) steps every part on one **virtual clock**, so a minute of riding
takes as long as the computation needs, not a minute — and stays honest, because every part reads
the same virtual time: the rider's head pose, the control unit's watchdog, the daemon core's
``step(now_s)`` and the capture time of each perception result. Perception's own computing time is
measured on the wall clock and charged as virtual latency (a result is delivered
``max(measured, perception_latency_s)`` after its capture), so a slow pipeline makes the chair
react late in the simulation exactly as it would on the chair; ``perceive_time_s`` charges a
fixed time instead, so that a run is the same on a loaded machine (tests).

Per physics tick (``physics_dt_s``, integer tick counts so rates never drift):

* the rider: head pose → ``controller.on_tilt`` every ``tilt_period_s``; key presses →
  ``controller.on_key``;
* perception: the daemon's own capture cycle (:class:`omnid.daemon.capture.CaptureCycle`, the
  same state machine ``omnid run`` drives) is told the laser state of every control-unit reply
  and handed camera frames; its laser and ``capturing`` requests go to the controller. Each job
  it emits is turned into a point cloud — ``truth`` (the laser dots cast into the world at the
  frames' poses with their true classes, for fast tests) or ``pipeline`` (the frames rendered and
  run through ``omnid.core.pipeline.perceive`` with the controller's configured method and
  detection settings, and a calibration made by ``calibrate_from_capture`` from a rendered floor
  capture). A frame shows the laser as the control unit had actually switched it;
* control: every ``control_period_s`` ``controller.step(now)`` → command → control unit →
  status → ``controller.on_status`` (and the capture cycle's laser report);
* physics: the control unit applies its duties to the chair (the plant) for one tick;
* safety truth: the chair's footprint against the world (collisions, falls).

The parts live in their own modules: :mod:`omnid.sim.settings` (``SimSettings``),
:mod:`omnid.sim.faults` (``Fault``, ``FaultInjector``), :mod:`omnid.sim.adapters` (the control
unit and tilt sensor on the virtual clock), :mod:`omnid.sim.open_loop` (``OpenLoopDriver``) and
:mod:`omnid.sim.results` (``SimResult``, clearance). Their names are re-exported here.

The controller is anything with the ``ControlCore`` contract (docs/interfaces.md); by default the
daemon's own ``omnid.daemon.core.ControlCore``. A controller without ``laser_on``/``capturing``
attributes (a probe, :class:`OpenLoopDriver`) does not switch the laser: the cycle then takes
one frame every period with the laser as it is (policy ``snapshot``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.geometry import StereoRig
from omnid.core.types import PointClass, PointCloud, StereoCapture
from omnid.daemon.capture import CaptureCycle, CaptureFailure, CaptureJob, CaptureSettings, Frame
from omnid.devices.joystick import JoystickReading
from omnid.errors import OmnidError
from omnid.sim.adapters import (
    DirectControlUnit,
    DirectTiltSensor,
    EmulatedControlUnit,
    EmulatedTiltSensor,
    lit_share,
    make_control_unit,
    make_tilt_sensor,
)
from omnid.sim.camera import SimCamera, SimFrame
from omnid.sim.chair import Chair, ChairSettings, Contact
from omnid.sim.course import Course
from omnid.sim.faults import FAULT_KINDS, Fault, FaultInjector, FaultKind, InjectedFault
from omnid.sim.laser import LaserProjector
from omnid.sim.open_loop import OpenLoopCommand, OpenLoopDriver
from omnid.sim.results import SimResult, chair_clearance_mm, world_rects
from omnid.sim.rider import HeadScript, JoystickScript, KeyScript
from omnid.sim.rigs import misaligned_rig
from omnid.sim.settings import PerceptionMode, SimSettings
from omnid.sim.story import Observation, ReactiveRider
from omnid.sim.world import LaserHits, RigMount, World, cast_laser, rig_to_world

__all__ = [
    "FAULT_KINDS",
    "DirectControlUnit",
    "DirectTiltSensor",
    "EmulatedControlUnit",
    "EmulatedTiltSensor",
    "Fault",
    "FaultKind",
    "InjectedFault",
    "OpenLoopCommand",
    "OpenLoopDriver",
    "PerceptionMode",
    "SimResult",
    "SimSettings",
    "Simulator",
    "make_control_unit",
    "misaligned_rig",
]

log = logging.getLogger(__name__)

#: The laser's dots in a frame it did not light: none.
_NO_HITS = LaserHits(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool), np.zeros(0, np.uint8))

Pose = tuple[float, float, float]


class Simulator:
    """One simulated chair in one course, driven by a controller on a virtual clock.

    With ``perception="pipeline"`` the simulator first *installs* the chair
    (:meth:`install`): it renders a floor capture of an empty floor with the rig's cameras (by
    default deliberately misaligned, :func:`misaligned_rig`) and runs
    ``calibrate_from_capture`` on it; every perception job then renders its mask and base frames
    and runs ``pipeline.perceive`` with the controller's configured method and detection
    settings. The daemon never learns the
    true rig, only what calibration found.
    """

    def __init__(
        self,
        course: Course,
        controller: Any,
        settings: SimSettings | None = None,
        chair_settings: ChairSettings | None = None,
        rider: HeadScript | ReactiveRider | None = None,
        keys: KeyScript | None = None,
        mount: RigMount | None = None,
        rig: StereoRig | None = None,
        laser: LaserProjector | None = None,
        progress: Callable[[float, Simulator], None] | None = None,
        faults: Sequence[Fault] = (),
        joystick: JoystickScript | None = None,
        world_changes: Sequence[tuple[float, World]] = (),
    ) -> None:
        self.course = course
        self.controller = controller
        self.settings = (settings or SimSettings()).for_controller(controller)
        s = self.settings
        self.chair = Chair(
            chair_settings,
            pose=course.start_pose,
            world=course.world if s.contact == "block" else None,
        )
        self.rider = rider
        self.keys = keys
        self.joystick: JoystickScript | ReactiveRider | None = joystick
        self.reactive = rider if isinstance(rider, ReactiveRider) else None
        if self.reactive is not None:
            if joystick is not None:
                raise OmnidError("a reactive rider drives the joystick itself: give no joystick")
            self.joystick = self.reactive
        self.mount = mount or RigMount()
        if rig is None:
            h = self.mount.height_mm
            rig = (
                misaligned_rig(h) if s.rig == "misaligned" else StereoRig.nominal(floor_depth_mm=h)
            )
        self.rig = rig
        # the world's laser: a physical, non-ideal projector (perception never sees it;
        # calibration learns it from the installer's captures)
        self.laser = laser or LaserProjector()
        self.control_unit = make_control_unit(
            self.chair,
            s.control_unit,
            s.watchdog_s,
            float(s.control_period_s or 0.02),
            s.laser_delay_s,
            s.laser_jitter_s,
            s.seed,
        )
        self.tilt: EmulatedTiltSensor | DirectTiltSensor | None = None
        if rider is not None:
            self.tilt = make_tilt_sensor(rider, s.tilt_link, s.tilt_noise_deg, s.seed)
        self.faults = tuple(faults)
        self.injector = FaultInjector(self.faults)
        self.progress = progress
        self.now_s = 0.0
        self._rng = np.random.default_rng(s.seed)
        self.calibration: Any = None
        self.install_s = 0.0
        if s.perception == "pipeline":
            self.install()
        self._box_rects, self._drop_rects = world_rects(course.world)
        self.world_changes = sorted(world_changes, key=lambda c: c[0])
        self._worlds: dict[int, World] = {0: course.world}  # by version (SimFrame.world)
        x0, x1 = course.x_range_mm
        y0, y1 = course.y_range_mm
        assert s.camera is not None
        self.camera = SimCamera(
            s.camera, self.rig, self.mount, course.world, (x0 - 3000, x1 + 3000, y0 - 3000, y1 + 3000),
            seed=s.seed,
        )  # fmt: skip
        # the capture cycle of ``omnid run``; a controller that does not switch the laser gets
        # the snapshot policy (one frame every period, laser as it is)
        self.drives_laser = hasattr(controller, "capturing") and hasattr(controller, "laser_on")
        self.capture_cycle = CaptureCycle(self._capture_settings())
        self._read_since: float | None = None  # a triggered read (stationary) began then
        self._triggered = 0
        self._poses: deque[tuple[float, float, float, float]] = deque(maxlen=64)
        # the jobs the (one) worker takes next, oldest first: a mask completes up to
        # mask_every_frames − 1 of them at once; an older one beyond that is dropped
        self._waiting: deque[CaptureJob] = deque()
        self._waiting_max = max(1, self.capture_cycle.settings.mask_every_frames - 1)
        self._worker_free_s = 0.0
        self.superseded = 0  # jobs replaced by a newer one before the worker took them
        self.perceive_s = 0.0  # wall time of the last job's vision step (what the worker runs)
        self._rendered: dict[int, tuple[NDArray[np.uint8], NDArray[np.uint8]]] = {}
        # Laser hits per pose: a chair standing still (refused, resting) sees the same dots, so
        # truth perception casts them once per pose; fresh noise is drawn on every use.
        self._hits_cache: dict[tuple[float, ...], Any] = {}

    # -- installation -------------------------------------------------------------------------

    def install(self) -> Any:
        """Calibrate the rig as an installer would: a capture of the empty floor ``H`` below the
        mirrors and extra captures of a box and a wall ahead (laser on),
        :func:`omnid.sim.installation.calibrate_installed`; the result is what perception uses."""
        from omnid.sim.installation import calibrate_installed

        w0 = time.perf_counter()
        self.calibration = calibrate_installed(
            self.rig, self.laser, self.mount, seed=self.settings.seed
        )
        self.install_s = time.perf_counter() - w0
        return self.calibration

    # -- camera views -------------------------------------------------------------------------

    def laser_hits(
        self, pose: tuple[float, float, float] | None = None, world: int | None = None
    ) -> Any:
        """``cast_laser`` at ``pose`` (default: the chair's current pose) in world version
        ``world`` (default: the current one; a frame keeps the version it was exposed in),
        remembered for the last few distinct poses."""
        p = pose or self.chair.pose
        version = self.camera.world_version if world is None else world
        key = (version, *p)
        hits = self._hits_cache.get(key)
        if hits is None:
            hits = cast_laser(self._worlds[version], p, self.mount, self.laser, self.rig)
            if len(self._hits_cache) >= 64:
                self._hits_cache.pop(next(iter(self._hits_cache)))
            self._hits_cache[key] = hits
        return hits

    def render(
        self,
        laser_on: bool | None = None,
        seed: int | None = None,
        pose: tuple[float, float, float] | None = None,
    ) -> StereoCapture:
        """A mask/base capture at ``pose`` (default: now); the base shows dots only if the laser
        is on (by default: as the control unit has switched it)."""
        from omnid.sim.render import RenderOptions, hits_flux, render_camera_pair

        on = self.control_unit.laser_on if laser_on is None else laser_on
        hits = self.laser_hits(pose)
        rng = np.random.default_rng(self._rng.integers(1 << 31) if seed is None else seed)
        opts = RenderOptions()
        flux = hits_flux(hits, self.rig, opts.spots)
        images: list[NDArray[np.uint8]] = []
        for k, (cam, vis) in enumerate(
            ((self.rig.cam1, hits.visible1), (self.rig.cam2, hits.visible2))
        ):
            if not on:
                vis = np.zeros(len(hits), dtype=bool)
            # The scene a camera fixed to the chair sees stays the same between its frames
            # (a laser-off and a laser-on frame differ by the laser and the sensor's noise).
            scene_seed = int(self.settings.seed) * 2 + k + 1
            images.extend(
                render_camera_pair(
                    cam, cam.project(hits.xyz[vis]), opts, rng, flux[vis, k], scene_seed
                )
            )
        return StereoCapture(images[0], images[1], images[2], images[3], self.now_s)

    def frame(self) -> tuple[float, NDArray[np.uint8], NDArray[np.uint8]]:
        """What each camera sees now (the base images), for the frame server."""
        cap = self.render()
        return self.now_s, cap.base1, cap.base2

    # -- perception ---------------------------------------------------------------------------

    def _truth_cloud(
        self, pose: tuple[float, float, float] | None = None, world: int | None = None
    ) -> PointCloud:
        hits = self.laser_hits(pose, world)
        vis = hits.visible
        xyz = hits.xyz[vis]
        s = self.settings.truth_noise_mm
        if s > 0:
            xyz = xyz + self._rng.normal(0.0, s, xyz.shape)
        cov = np.broadcast_to(np.eye(3) * s * s, (len(xyz), 3, 3)).copy()
        return PointCloud(
            xyz=xyz,
            cov=cov,
            pixels=self.rig.project(xyz),
            classes=hits.truth[vis].astype(np.uint8),
            floor_depth_mm=self.mount.height_mm,
        )

    def capture(
        self,
        mask_pose: tuple[float, float, float],
        mask_laser: bool,
        base_pose: tuple[float, float, float],
        base_laser: bool,
    ) -> StereoCapture:
        """The mask and base frames of one cycle, each showing the laser as the control unit had
        actually switched it when the frame was taken. The camera's own scene (background,
        texture) is the same in both, as it is for a camera fixed to the chair."""
        seed = int(self._rng.integers(1 << 31))
        base = self.render(laser_on=base_laser, seed=seed, pose=base_pose)
        if not mask_laser:
            mask1, mask2 = base.mask1, base.mask2
        else:  # the laser was still on: the "mask" frames show dots
            lit = self.render(laser_on=True, seed=seed, pose=mask_pose)
            mask1, mask2 = lit.base1, lit.base2
        return StereoCapture(mask1, base.base1, mask2, base.base2, self.now_s)

    def _pipeline(self) -> tuple[str, Any]:
        """The matching method and pipeline settings the daemon would configure its worker with
        (the controller's ``perception.method`` and ``detection``; the defaults without one)."""
        from omnid.daemon.capture import pipeline_arguments

        return pipeline_arguments(getattr(self.controller, "config", None))

    def _perceive_capture(
        self, capture: StereoCapture | None, base_pose: Pose, base_laser: bool
    ) -> PointCloud:
        """The vision step the daemon's worker runs (timed by the caller)."""
        if self.injector.active("perception_exception"):
            raise InjectedFault("injected fault: the vision pipeline raised")
        on_capture = getattr(self.controller, "on_capture", None)  # a recording core
        if capture is not None and on_capture is not None:
            on_capture(capture)
        mode = self.settings.perception
        if mode == "off" or not base_laser or (mode == "pipeline" and capture is None):
            return PointCloud(floor_depth_mm=self.mount.height_mm)
        if mode == "truth":
            return self._truth_cloud(base_pose)
        from omnid.core.pipeline import perceive

        assert capture is not None
        method, settings = self._pipeline()
        cloud: PointCloud = perceive(capture, self.calibration, method, settings)  # type: ignore[arg-type]
        return cloud

    def perceive_job(self, job: CaptureJob) -> PointCloud:
        """The cloud of one capture job, as the daemon's worker would compute it, then the
        vision step. ``stream``: the frames as the simulated cameras took them
        (:class:`~omnid.sim.camera.SimCamera`: pose, laser light, the scene fixed to the world,
        noise), each mask moved to the base's pose by the job's motion
        (``perception.motion_compensation``). ``stationary``/``snapshot``: one render.py
        capture at the base's pose (the scene fixed to the camera: no motion residue; a
        ``snapshot`` job's mask is the same view without laser)."""
        base: SimFrame = job.base.source
        self.perceive_s = 0.0
        if self.injector.active("perception_exception"):
            raise InjectedFault("injected fault: the vision pipeline raised")
        mode = self.settings.perception
        if mode == "off" or not base.laser:
            return PointCloud(floor_depth_mm=self.mount.height_mm)
        if mode == "truth":
            return self._truth_cloud(base.pose, base.world)
        from omnid.core.pipeline import perceive
        from omnid.daemon.perception_worker import job_capture

        if self.capture_cycle.settings.policy != "stream":
            # one mask/base capture of render.py: the scene fixed to the camera, the same in
            # both (no motion residue), the mask drawn at the base's pose
            mask = job.masks[0].source if job.masks else None
            mask_pose = mask.pose if mask is not None else base.pose
            mask_lit = mask is not None and mask.laser
            capture = self.capture(mask_pose, mask_lit, base.pose, True)
        else:
            masks = [m.source for m in job.masks]
            motions = list(job.mask_motions)
            cfg = getattr(self.controller, "config", None)
            if cfg is not None and not cfg.perception.motion_compensation:
                motions = [None] * len(masks)
            offset = float(cfg.perception.rig_x_offset_mm) if cfg is not None else 0.0
            capture = job_capture(
                self._frame_images(base),
                [self._frame_images(m) for m in masks],
                motions,
                self.calibration.rig,
                offset,
                job.t_s,
            )
        on_capture = getattr(self.controller, "on_capture", None)  # a recording core
        if on_capture is not None:
            on_capture(capture)
        method, settings = self._pipeline()
        w0 = time.perf_counter()
        cloud: PointCloud = perceive(capture, self.calibration, method, settings)  # type: ignore[arg-type]
        self.perceive_s = time.perf_counter() - w0
        return cloud

    def _frame_images(self, frame: SimFrame) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
        """The rendered images of ``frame`` (a mask serves several base frames: kept)."""
        cache = self._rendered
        images = cache.get(frame.index)
        if images is None:
            # a frame the laser never lit shows no dot: its rays are not cast (half the frames
            # of the stream are masks; the images are the same without)
            hits = self.laser_hits(frame.pose, frame.world) if frame.lit > 0 else _NO_HITS
            images = self.camera.render(frame, hits)
            if len(cache) >= 8:
                cache.pop(next(iter(cache)))
            cache[frame.index] = images
        return images

    def perceive_now(self) -> PointCloud:
        """The point cloud the daemon would get from a capture at the current pose (laser as
        switched now, for mask and base)."""
        mode = self.settings.perception
        on = bool(self.control_unit.laser_on)
        if mode == "off" or not on:
            return PointCloud(floor_depth_mm=self.mount.height_mm)
        if mode == "truth":
            return self._truth_cloud()
        pose = self.chair.pose
        return self._perceive_capture(self.capture(pose, False, pose, on), pose, on)

    # -- the loop -----------------------------------------------------------------------------

    def _note_decision(self, now: float, out: list[tuple[float, str]], last: str) -> str:
        """Record a refusal when the daemon core's last cycle stopped a motion the rider asked
        for (``ControlCore.last_report``). A refusal repeated cycle after cycle (or flickering
        with a slow-down) is recorded once, again only when its text changes or after 5 s."""
        report = getattr(self.controller, "last_report", None)
        if report is None:
            return last
        demand, decision = report.demand, report.decision
        asked = not demand.stop and (demand.forward != 0.0 or demand.turn != 0.0)
        if not asked or decision is None or not decision.stopped:
            return last
        reasons = ", ".join(getattr(r, "value", str(r)) for r in report.reasons) or "stopped"
        text = f"refused {demand.reason.removeprefix('tilt_').removeprefix('key_')}: {reasons}"
        if text != last or not out or now - out[-1][0] > 5.0:
            out.append((now, text))
        return text

    def _capture_settings(self) -> CaptureSettings:
        """The capture cycle's settings: the controller's configuration (``perception``,
        ``camera``, ``motion``), with the period and laser timeout as the simulation settings
        resolved them; without a configuration the snapshot policy at the simulated cameras'
        rate."""
        s = self.settings
        assert s.perception_period_s is not None and s.laser_timeout_s is not None
        changes: dict[str, Any] = {
            "period_s": s.perception_period_s,
            "laser_timeout_s": s.laser_timeout_s,
        }
        cfg = getattr(self.controller, "config", None)
        if not self.drives_laser:
            changes["policy"] = "snapshot"
        if cfg is not None:
            return CaptureSettings.from_config(cfg, **changes)
        assert s.camera is not None
        return CaptureSettings(
            frame_timeout_s=s.frame_timeout_s,
            frame_period_s=s.camera.period_s,
            exposure_s=min(1.25 * s.camera.exposure_s, 0.9 * s.camera.period_s),
            **changes,
        )

    def run(self, duration_s: float) -> SimResult:
        """Simulate ``duration_s`` virtual seconds; returns the trajectory, contacts, refusals,
        what perception saw and timing figures."""
        require(duration_s > 0, "duration_s", "must be positive")
        s = self.settings
        dt = s.physics_dt_s
        n_ticks = round(duration_s / dt)
        k_ctrl, k_tilt = s.ticks(s.control_period_s), s.ticks(s.tilt_period_s)
        k_rec = s.ticks(s.record_period_s)
        ctl = self.controller
        joy_reading = JoystickReading
        last_pose: tuple[float, float, float] | None = None

        # Records preallocated for the whole run (no per-tick allocations; a soak's memory
        # figure then shows the daemon, not the recorder). Filled now, not np.empty: the kernel
        # commits a page only when it is first written, so empty records grew the resident
        # memory by 3.4 kB per simulated second (6 MB in a 30-minute soak) as they filled.
        traj = np.full((n_ticks // k_rec + 2, 4), np.nan)
        speeds = np.full((n_ticks + 1, 3), np.nan)
        # control steps: the 50 Hz grid plus the extra steps a laser switch runs at once (as
        # the daemon's control loop does): two per mask (or cycle); the records grow if needed
        cs = self.capture_cycle.settings
        gap = cs.mask_every_frames * cs.frame_period_s if cs.policy == "stream" else cs.period_s
        n_steps = n_ticks // k_ctrl + 1 + 2 * math.ceil(duration_s / gap) + 4
        cmds = np.full((n_steps, 5), np.nan)
        steps = np.full((n_steps, 7), np.nan)
        reason_bits: dict[str, int] = {}
        n_traj = n_speed = n_cmd = 0
        contacts: list[tuple[float, Contact]] = []
        seen: list[NDArray[np.float64]] = []
        pending: list[tuple[float, float, PointCloud, Pose]] = []
        t_perc: list[float] = []
        ctrl_n, ctrl_sum, ctrl_max = 0, 0.0, 0.0  # control-step wall times, s
        errors: list[tuple[float, str]] = []
        min_clear = math.inf
        refusals: list[tuple[float, str]] = []
        last_refusal = ""
        wall0 = time.perf_counter()
        last_progress = -math.inf

        def finish(job: CaptureJob) -> None:
            """The worker takes ``job`` now: the vision step's wall time (not the rendering,
            which stands for the cameras) is charged as virtual time."""
            try:
                cloud = self.perceive_job(job)
            except Exception as exc:  # as the daemon's perception loop: log, no result
                errors.append((now, f"{type(exc).__name__}: {exc}"))
                log.warning("perception cycle failed at t=%.2f s: %s", now, exc)
                return
            took = self.perceive_s if s.perceive_time_s is None else s.perceive_time_s
            t_perc.append(self.perceive_s)
            self._worker_free_s = now + max(took, s.worker_period_s)
            at = max(now + took, job.t_s + s.perception_latency_s)
            pending.append((at, job.t_s, cloud, job.base.source.pose))
            pending.sort(key=lambda p: p[0])

        def failed(failure: CaptureFailure) -> None:
            errors.append((now, failure.message))
            log.warning("perception cycle failed at t=%.2f s: %s", now, failure.message)

        def control(t: float) -> None:
            """One control cycle at ``t``: step, record, exchange with the control unit."""
            nonlocal cmds, steps, n_cmd, ctrl_n, ctrl_sum, ctrl_max, last_refusal
            if n_cmd == len(cmds):  # more extra cycles than foreseen: grow the records
                cmds = np.vstack([cmds, np.full_like(cmds, np.nan)])
                steps = np.vstack([steps, np.full_like(steps, np.nan)])
            w0 = time.perf_counter()
            command = ctl.step(t)
            took_ctrl = time.perf_counter() - w0
            ctrl_n, ctrl_sum = ctrl_n + 1, ctrl_sum + took_ctrl
            ctrl_max = max(ctrl_max, took_ctrl)
            last_refusal = self._note_decision(t, refusals, last_refusal)
            steps[n_cmd] = (t, self._reason_mask(reason_bits), *self.chair.pose, *self._speed())
            status = self.control_unit.exchange(command, t)
            if status is not None:
                ctl.on_status(status)
                self.capture_cycle.on_status(status)
            cmds[n_cmd] = (
                t,
                float(command.left_duty),
                float(command.right_duty),
                float(command.laser_on),
                float(command.enable),
            )
            n_cmd += 1

        for k in range(n_ticks + 1):
            now = k * dt
            self.now_s = now
            self.injector.apply(now, self.control_unit, self.tilt)
            while self.world_changes and self.world_changes[0][0] <= now + 1e-9:
                self.set_world(self.world_changes.pop(0)[1])
            if self.reactive is not None and k % k_tilt == 0:
                if (
                    self.reactive.done_s is not None
                    and now >= self.reactive.done_s + s.story_rest_s
                ):
                    break  # the story has ended: so does the run
                self.reactive.observe(Observation(now, self.chair.pose, self._speed()[0], refusals))
            if self.tilt is not None and k % k_tilt == 0:
                reading = self.tilt.poll(now)
                if reading is not None:
                    ctl.on_tilt(reading)
            if (
                self.joystick is not None
                and k % k_tilt == 0
                and not self.injector.active("tilt_unplugged")
            ):
                fwd, turn = self.joystick.at(now)
                ctl.on_joystick(joy_reading(fwd, turn, now))
            if self.keys is not None:
                for _, command in self.keys.between(now - dt, now):
                    ctl.on_key(command, now)
            # Deliver finished perception results (charged with their computing time).
            while pending and pending[0][0] <= now + 1e-9:
                _, t_cap, cloud, pose = pending.pop(0)
                ctl.on_perception(cloud, t_cap)
                keep = cloud.classes != PointClass.FLOOR
                if s.record_seen and np.any(keep):
                    w = rig_to_world(cloud.xyz[keep], pose, self.mount)
                    seen.append(np.column_stack([w[:, :2], cloud.classes[keep]]))
            if self._perception_step(now, finish, failed) or k % k_ctrl == 0:
                control(now)
            # a laser switch falls due between two ticks: asked at its time, and put on the wire
            # at once by an extra control cycle (as the daemon does), not at the next tick
            t_evt = now
            for _ in range(8):
                t_next = self.capture_cycle.next_poll_s
                if not t_evt < t_next < now + dt - 1e-9:
                    break
                t_evt = t_next
                if self._perception_poll(t_evt, failed):
                    control(t_evt)
            speeds[n_speed] = (now, self.chair.left_speed_mm_s, self.chair.right_speed_mm_s)
            n_speed += 1
            if k % k_rec == 0:
                traj[n_traj] = (now, *self.chair.pose)
                n_traj += 1
                min_clear = min(
                    min_clear, chair_clearance_mm(self.chair, self._box_rects, self._drop_rects)
                )
                if self.progress is not None and now - last_progress >= 1.0:
                    last_progress = now
                    self.progress(now, self)
            pose_now = self.chair.pose
            moved_now = pose_now != last_pose or bool(self.chair.blocked_by)
            found = self.chair.contacts(self.course.world) if moved_now else []
            last_pose = pose_now  # a chair that has not moved (nor pushed) touches nothing new
            new = [c for c in found if all(c != old for _, old in contacts)]
            if new:
                min_clear = 0.0
            for c in new:
                log.warning("simulated chair %s (%s) at t=%.2f s", c.kind, c.part, now)
                contacts.append((now, c))
            ending = [c for c in new if c.kind == "fall" or s.contact == "pass"]
            if ending and s.stop_on_contact:
                traj[n_traj] = (now, *self.chair.pose)
                n_traj += 1
                break
            if k < n_ticks:
                self.control_unit.advance(now, dt)
        wall = time.perf_counter() - wall0
        timings = {
            "wall_s": wall,
            "virtual_s": self.now_s,
            "realtime_factor": self.now_s / wall if wall > 0 else math.inf,
            "perception_mean_ms": 1e3 * float(np.mean(t_perc)) if t_perc else 0.0,
            "perception_max_ms": 1e3 * float(np.max(t_perc)) if t_perc else 0.0,
            "control_step_mean_ms": 1e3 * ctrl_sum / ctrl_n if ctrl_n else 0.0,
            "control_step_max_ms": 1e3 * ctrl_max,
            "control_steps": float(ctrl_n),
            "perception_cycles": float(len(t_perc)),
            "perception_errors": float(len(errors)),
            "install_s": self.install_s,
            "watchdog_trips": float(self.control_unit.watchdog_trips),
            "bytes_link": float(isinstance(self.control_unit, EmulatedControlUnit)),
            "tilt_bytes_link": float(isinstance(self.tilt, EmulatedTiltSensor)),
            "clouds_per_s": len(t_perc) / self.now_s if self.now_s > 0 else 0.0,
            "frames": float(self.camera.frames),
            "frames_dropped": float(self.camera.dropped),
            "masks": float(self.capture_cycle.masks_taken),
            "jobs_superseded": float(self.superseded),
            "frames_unused": float(self.capture_cycle.ignored_frames),
        }
        return SimResult(
            duration_s=self.now_s,
            trajectory=traj[:n_traj].copy(),
            commands=cmds[:n_cmd].copy(),
            contacts=contacts,
            refusals=refusals,
            seen=np.vstack(seen) if seen else np.zeros((0, 3)),
            min_clearance_mm=min_clear,
            timings=timings,
            wheel_speeds=speeds[:n_speed].copy(),
            faults=self.faults,
            perception_errors=errors,
            steps=steps[:n_cmd].copy(),
            reason_names=tuple(sorted(reason_bits, key=reason_bits.__getitem__)),
            story=list(self.reactive.log) if self.reactive is not None else [],
        )

    def _reason_mask(self, bits: dict[str, int]) -> float:
        """The controller's reasons of its last cycle as a bit mask; new names get new bits."""
        report = getattr(self.controller, "last_report", None)
        mask = 0
        for r in getattr(report, "reasons", ()) if report is not None else ():
            name = str(getattr(r, "value", r))
            if name not in bits:
                require(len(bits) < 52, "reasons", "more than 52 distinct reasons")
                bits[name] = len(bits)
            mask |= 1 << bits[name]
        return float(mask)

    def _speed(self) -> tuple[float, float]:
        """Mean wheel surface speed (mm/s, true) and the rider's forward demand now."""
        c = self.chair
        report = getattr(self.controller, "last_report", None)
        demand = getattr(report, "demand", None)
        fwd = float(getattr(demand, "forward", 0.0)) if demand is not None else 0.0
        return 0.5 * (c.left_speed_mm_s + c.right_speed_mm_s), fwd

    def set_world(self, world: World) -> None:
        """The world changes now (a hazard steps into view): frames exposed from now on, the
        contacts and the truth measures see the new one."""
        self.course = dataclasses.replace(self.course, world=world)
        self._worlds[self.camera.set_world(world)] = world
        self._box_rects, self._drop_rects = world_rects(world)

    def _pose_at(self, t_s: float) -> Pose:
        """The chair's true pose at ``t_s`` (linear between physics ticks)."""
        poses = self._poses
        if not poses or t_s >= poses[-1][0]:
            return self.chair.pose
        prev = poses[0]
        for cur in poses:
            if cur[0] >= t_s:
                if cur is prev or cur[0] <= prev[0]:
                    return cur[1], cur[2], cur[3]
                w = (t_s - prev[0]) / (cur[0] - prev[0])
                dth = math.remainder(cur[3] - prev[3], math.tau)
                return (
                    prev[1] + w * (cur[1] - prev[1]),
                    prev[2] + w * (cur[2] - prev[2]),
                    prev[3] + w * dth,
                )
            prev = cur
        return prev[1], prev[2], prev[3]

    def _lit_share(self, t0_s: float, t1_s: float) -> float:
        cu = self.control_unit
        return lit_share(cu.laser_switches, t0_s, t1_s, bool(cu.laser_on))

    def _poll(self, now: float, failed: Callable[[CaptureFailure], None]) -> None:
        for out in self.capture_cycle.poll(now):
            if isinstance(out, CaptureFailure):
                failed(out)
            else:
                self._queue(out)

    def _queue(self, job: CaptureJob) -> None:
        self._waiting.append(job)
        while len(self._waiting) > self._waiting_max:
            self._waiting.popleft()
            self.superseded += 1

    def _perception_poll(self, t: float, failed: Callable[[CaptureFailure], None]) -> bool:
        """The capture cycle polled between ticks (its laser requests fall due): True when its
        laser request changed."""
        cycle = self.capture_cycle
        before = cycle.laser_on
        for out in cycle.poll(t):
            if isinstance(out, CaptureFailure):
                failed(out)
            else:
                self._queue(out)
        if not self.drives_laser:
            return False
        self.controller.laser_on = cycle.laser_on
        self.controller.capturing = cycle.capturing
        return cycle.laser_on != before and cycle.settings.policy == "stream"

    def _perception_step(
        self,
        now: float,
        finish: Callable[[CaptureJob], None],
        failed: Callable[[CaptureFailure], None],
    ) -> bool:
        """One tick of the daemon's capture cycle against the simulated cameras; True when the
        cycle changed its laser request (the daemon then runs a control cycle at once).

        ``stream``: the cameras free-run (:class:`omnid.sim.camera.SimCamera`) and every frame
        delivered by now goes to the cycle. ``stationary``/``snapshot``: a triggered camera —
        a read that must follow a laser switch (the cycle's ``flush_needed``) is exposed when
        asked and delivered ``1/fps`` later, any other read returns at once; the frame shows
        the pose and the laser as switched when it is delivered. With the cameras stopped no
        frame comes. The one worker takes the queued jobs in order when it is free."""
        cycle = self.capture_cycle
        self._poses.append((now, *self.chair.pose))
        stopped = self.injector.active("camera_stopped")
        before = cycle.laser_on
        if cycle.settings.policy == "stream":
            if stopped:
                self.camera.skip_until(now)
            else:
                for f in self.camera.delivered_until(now, self._pose_at, self._lit_share):
                    cycle.on_frame(Frame(f.t_s, None, f))
            self._poll(now, failed)
        else:
            for _ in range(4):  # an immediate read is delivered in the same tick
                if not cycle.wants_frame():
                    self._read_since = None
                elif self._read_since is not None and not stopped:
                    wait = self.camera.model.period_s if cycle.flush_needed else 0.0
                    if now + 1e-9 >= self._read_since + wait:
                        self._read_since = None
                        on = bool(self.control_unit.laser_on)
                        self._triggered += 1
                        # (rendered by capture(), which draws its own seed)
                        version = self.camera.world_version
                        f = SimFrame(-self._triggered, now, self.chair.pose, float(on), 0, version)
                        cycle.on_frame(Frame(now, None, f))
                self._poll(now, failed)
                if not cycle.wants_frame() or self._read_since is not None:
                    break
                self._read_since = now
                if cycle.flush_needed:
                    break
        while self._waiting and now + 1e-9 >= self._worker_free_s:
            finish(self._waiting.popleft())
        if self.drives_laser:
            self.controller.laser_on = cycle.laser_on
            self.controller.capturing = cycle.capturing
            # stream: a switch timed to the frames goes out at once (the daemon's extra cycle);
            # stationary: with the next control cycle
            return cycle.laser_on != before and cycle.settings.policy == "stream"
        return False
