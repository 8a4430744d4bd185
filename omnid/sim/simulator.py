"""The closed-loop simulator: world + chair + control unit + rider + perception + daemon core.

Fast mode (:meth:`Simulator.run`) steps every part on one **virtual clock**, so a minute of riding
takes as long as the computation needs, not a minute — and stays honest, because every part reads
the same virtual time: the rider's head pose, the control unit's watchdog, the daemon core's
``step(now_s)`` and the capture time of each perception result. Perception's own computing time is
measured on the wall clock and charged as virtual latency (a result is delivered
``max(measured, perception_latency_s)`` after its capture), so a slow pipeline makes the chair
react late in the simulation exactly as it would on the chair.

Per physics tick (``physics_dt_s``, integer tick counts so rates never drift):

* the rider: head pose → ``controller.on_tilt`` every ``tilt_period_s``; key presses →
  ``controller.on_key``;
* perception: every ``perception_period_s`` the laser dots are cast at the chair pose
  (``world.cast_laser``) and, **if the control unit has actually switched the laser on**, turned
  into a point cloud — ``truth`` (the cast dots with their true classes, for fast tests) or
  ``pipeline`` (rendered mask/base captures through ``omnid.core.pipeline.perceive`` with a
  calibration made by ``calibrate_from_capture`` from a rendered floor capture);
* control: every ``control_period_s`` ``controller.step(now)`` → command → control unit →
  status → ``controller.on_status``;
* physics: the control unit applies its duties to the chair (the plant) for one tick;
* safety truth: the chair's footprint against the world (collisions, falls).

The controller is anything with the ``ControlCore`` contract (docs/interfaces.md); by default the
daemon's own ``omnid.daemon.core.ControlCore``. :class:`OpenLoopDriver` plays fixed duties
instead (for plant tests and for showing what happens without the daemon).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.geometry import StereoRig
from omnid.core.types import PointClass, PointCloud, StereoCapture
from omnid.devices.control_unit import ControlUnitStatus
from omnid.devices.joystick import JoystickReading
from omnid.devices.tilt import TiltReading
from omnid.errors import OmnidError
from omnid.sim.chair import Chair, ChairSettings, Contact
from omnid.sim.course import Course
from omnid.sim.laser import LaserProjector
from omnid.sim.rider import HeadScript, JoystickScript, KeyScript
from omnid.sim.rigs import misaligned_rig
from omnid.sim.story import Observation, ReactiveRider, StepRecord
from omnid.sim.world import Laser, RigMount, cast_laser, rig_to_world

log = logging.getLogger(__name__)

PerceptionMode = Literal["truth", "pipeline", "off"]


@dataclass(frozen=True)
class SimSettings:
    """Rates and models of a simulated run (s, mm)."""

    physics_dt_s: float = 0.01
    control_period_s: float | None = None  # None: the controller's control.rate_hz (else 0.05)
    tilt_period_s: float = 0.01
    perception_period_s: float | None = None  # None: the controller's perception.period_s (0.2)
    perception_latency_s: float = 0.1  # at least this long from capture to result
    perception: PerceptionMode = "truth"
    control_unit: Literal["emulator", "direct"] = "emulator"
    truth_noise_mm: float = 3.0  # Gaussian noise on truth-mode points (per axis)
    watchdog_s: float = 0.25  # the control unit stops the motors after this silence
    stop_on_contact: bool = True  # end the run at the first collision or fall
    record_period_s: float = 0.05
    seed: int = 0
    rig: Literal["misaligned", "nominal"] = "misaligned"  # the cameras as installed
    tilt_link: Literal["emulator", "direct"] = "emulator"  # head script through the GS311 codec
    tilt_noise_deg: float = 0.0  # Gaussian noise of the emulated sensor (head jitter)
    frame_interval_s: float = 1.0 / 30.0  # camera frame period: a flushed read waits this long
    laser_timeout_s: float = 0.5  # perception waits this long for the laser to be reported
    frame_timeout_s: float = 1.0  # and this long for a camera frame
    record_seen: bool = True  # keep every non-floor point perception reported (off for soaks)
    story_rest_s: float = 1.0  # a reactive rider's run ends this long after its story ended

    def __post_init__(self) -> None:
        for name in (
            "physics_dt_s",
            "control_period_s",
            "tilt_period_s",
            "perception_period_s",
            "watchdog_s",
            "record_period_s",
        ):
            v = getattr(self, name)
            require(v is None or v > 0, name, "must be positive")
        require(self.perception_latency_s >= 0, "perception_latency_s", "must be ≥ 0")
        require(self.truth_noise_mm >= 0, "truth_noise_mm", "must be ≥ 0")
        require(self.tilt_noise_deg >= 0, "tilt_noise_deg", "must be ≥ 0")
        require(self.story_rest_s >= 0, "story_rest_s", "must be ≥ 0")
        for name in ("frame_interval_s", "laser_timeout_s", "frame_timeout_s"):
            require(getattr(self, name) > 0, name, "must be positive")

    def for_controller(self, controller: Any) -> SimSettings:
        """These settings with unset periods taken from the controller's configuration (the
        daemon core's ``control.rate_hz`` and ``perception.period_s``) or the defaults."""
        cfg = getattr(controller, "config", None)
        control = self.control_period_s
        if control is None:
            control = float(cfg.control.period_s) if cfg is not None else 0.05
        perception = self.perception_period_s
        if perception is None:
            perception = float(cfg.perception.period_s) if cfg is not None else 0.2
        return dataclasses.replace(self, control_period_s=control, perception_period_s=perception)

    def ticks(self, period_s: float | None) -> int:
        """A period as a whole number of physics ticks (at least 1)."""
        require(period_s is not None, "period", "must be resolved (for_controller)")
        assert period_s is not None
        return max(1, round(period_s / self.physics_dt_s))


FaultKind = Literal[
    "tilt_unplugged", "camera_stopped", "cu_silent", "cu_corrupt", "perception_exception"
]
FAULT_KINDS: tuple[str, ...] = (
    "tilt_unplugged",
    "camera_stopped",
    "cu_silent",
    "cu_corrupt",
    "perception_exception",
)


@dataclass(frozen=True)
class Fault:
    """A fault injected from ``start_s`` to ``end_s`` (virtual s):

    * ``tilt_unplugged`` — the GS311 adapter is pulled: no replies reach the tilt decoding;
    * ``camera_stopped`` — the cameras deliver no frames (a perception cycle waits
      ``frame_timeout_s`` and fails);
    * ``cu_silent`` — the control unit hangs (the emulator's ``stall``: no replies, and its own
      watchdog stops the motors);
    * ``cu_corrupt`` — every reply has a flipped bit (CRC errors at the daemon);
    * ``perception_exception`` — the vision pipeline raises.
    """

    kind: FaultKind
    start_s: float
    end_s: float = math.inf

    def __post_init__(self) -> None:
        require(self.kind in FAULT_KINDS, "kind", f"must be one of {', '.join(FAULT_KINDS)}")
        require(self.end_s > self.start_s >= 0, "end_s", "must be after start_s ≥ 0")

    def active(self, now_s: float) -> bool:
        return self.start_s <= now_s < self.end_s


class InjectedFault(RuntimeError):
    """Raised by the simulated vision pipeline during a ``perception_exception`` fault."""


@dataclass
class SimResult:
    """What happened in a run. Times are virtual seconds; ``timings`` are wall-clock figures."""

    duration_s: float
    trajectory: NDArray[np.float64]  # (N, 4) t_s, x_mm, y_mm, theta_rad
    commands: NDArray[np.float64]  # (M, 5) t_s, left_duty, right_duty, laser_on, enable
    contacts: list[tuple[float, Contact]]
    refusals: list[tuple[float, str]]
    seen: NDArray[np.float64]  # (K, 3) world x_mm, y_mm, PointClass code of non-floor points
    min_clearance_mm: float  # closest the footprint came to a box or a drop-off edge
    timings: dict[str, float] = field(default_factory=dict)
    wheel_speeds: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    # (N, 3) t_s, left, right wheel surface speed mm/s, every physics tick
    faults: tuple[Fault, ...] = ()
    perception_errors: list[tuple[float, str]] = field(default_factory=list)
    steps: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 7)))
    # (M, 7) every control step: t_s, reason bit mask (bit i = reason_names[i]), x_mm, y_mm,
    # theta_rad (true pose), mean wheel surface speed mm/s (true), rider's forward demand [-1, 1]
    reason_names: tuple[str, ...] = ()
    story: list[StepRecord] = field(default_factory=list)  # a reactive rider's steps

    def reasons_at(self, i: int) -> list[str]:
        """The reasons the controller gave at control step ``i`` (row of :attr:`steps`)."""
        mask = int(self.steps[i, 1])
        return [n for b, n in enumerate(self.reason_names) if mask >> b & 1]

    def reason_mask(self, *names: str) -> int:
        """The bit mask of ``names`` in :attr:`steps` (0 for a reason that never occurred)."""
        return sum(1 << b for b, n in enumerate(self.reason_names) if n in names)

    def time_to_standstill(self, t0_s: float, speed_tol_mm_s: float = 1.0) -> float:
        """Seconds from ``t0_s`` until both wheels turn slower than ``speed_tol_mm_s`` (and stay
        so for 0.1 s); ``inf`` if they never do."""
        w = self.wheel_speeds
        after = w[w[:, 0] >= t0_s - 1e-9]
        still = np.all(np.abs(after[:, 1:]) < speed_tol_mm_s, axis=1)
        for i in np.flatnonzero(still):
            t = after[i, 0]
            window = after[(after[:, 0] >= t) & (after[:, 0] <= t + 0.1)]
            if np.all(np.abs(window[:, 1:]) < speed_tol_mm_s) and len(window) > 1:
                return float(t - t0_s)
        return math.inf

    def max_speed_between(self, t0_s: float, t1_s: float) -> float:
        """Fastest wheel surface speed (mm/s, absolute) between the two times."""
        w = self.wheel_speeds
        sel = w[(w[:, 0] >= t0_s) & (w[:, 0] <= t1_s)]
        return float(np.abs(sel[:, 1:]).max()) if len(sel) else 0.0

    @property
    def collisions(self) -> list[tuple[float, Contact]]:
        return [c for c in self.contacts if c[1].kind == "collision"]

    @property
    def falls(self) -> list[tuple[float, Contact]]:
        return [c for c in self.contacts if c[1].kind == "fall"]

    @property
    def distance_mm(self) -> float:
        """Path length of the axle midpoint, mm."""
        if len(self.trajectory) < 2:
            return 0.0
        return float(np.sum(np.hypot(*np.diff(self.trajectory[:, 1:3], axis=0).T)))


# -- the control unit --------------------------------------------------------------------------


class DirectControlUnit:
    """The control unit's behaviour on the virtual clock, without the byte link.

    It applies the latest command's duties (zero unless ``enable``), switches the laser as told,
    stops both motors when no command arrived for ``watchdog_s`` (SPEC §4) and reports the
    plant's clocks. The simulator uses it until the control-unit emulator (bytes through the
    codec) is wired in.
    """

    def __init__(self, plant: Chair, watchdog_s: float = 0.25) -> None:
        self.plant = plant
        self.watchdog_s = watchdog_s
        self.laser_on = False
        self.left_duty = 0.0
        self.right_duty = 0.0
        self.last_command_s = -math.inf
        self.seq = 0
        self.watchdog_trips = 0
        self.silent = False  # a hung unit: takes no command, sends no reply

    def exchange(self, command: Any, now_s: float) -> Any:
        """Deliver one command at ``now_s``; return the reply (None while ``silent``)."""
        if self.silent:
            return None
        self.seq = (self.seq + 1) & 0xFFFF
        self.last_command_s = now_s
        on = bool(command.enable)
        self.left_duty = float(command.left_duty) if on else 0.0
        self.right_duty = float(command.right_duty) if on else 0.0
        self.laser_on = bool(command.laser_on)
        left, right = self.plant.clocks()
        return ControlUnitStatus(
            seq=self.seq,
            left_clocks=left,
            right_clocks=right,
            laser_on=self.laser_on,
            faults=0,
            timestamp_s=now_s,
        )

    def advance(self, now_s: float, dt_s: float) -> None:
        """Run the plant for ``dt_s`` from ``now_s`` (with the watchdog applied)."""
        if now_s - self.last_command_s > self.watchdog_s and (self.left_duty or self.right_duty):
            log.warning("control unit: no command for %.3f s; motors stopped", self.watchdog_s)
            self.watchdog_trips += 1
            self.left_duty = self.right_duty = 0.0
        self.plant.step(self.left_duty, self.right_duty, dt_s)


class EmulatedControlUnit:
    """The project's control-unit emulator (``omnid.devices.emulators.control_unit``) on the
    virtual clock, every command and reply passing as bytes through the protocol codec.

    It is the same code that serves a pty on the bench: it enforces its own watchdog, switches
    the laser relay with its delay, and integrates the plant (the chair) lazily up to the clock.
    """

    def __init__(self, plant: Chair, watchdog_s: float = 0.25) -> None:
        from omnid.devices import cu_codec as codec  # type: ignore[attr-defined,unused-ignore]
        from omnid.devices.emulators.control_unit import (  # type: ignore[import-not-found,unused-ignore]
            ControlUnitEmulator,
        )

        self._codec = codec
        self._t = 0.0
        self.emulator = ControlUnitEmulator(
            plant=plant, clock=lambda: self._t, default_watchdog_s=watchdog_s
        )
        self._parser = codec.FrameParser(accept=(codec.TYPE_REPLY,))
        self._seq = 0
        self._raw: tuple[int, int] | None = None
        self._clocks = (0, 0)
        self.missed_replies = 0

    @property
    def laser_on(self) -> bool:
        return bool(self.emulator.laser_on)

    @property
    def watchdog_trips(self) -> int:
        return int(self.emulator.watchdog_trips)

    def exchange(self, command: Any, now_s: float) -> Any:
        """Encode ``command``, feed the bytes to the emulator at ``now_s``, decode its reply
        (None when it gives none)."""
        from omnid.devices.control_unit import (  # type: ignore[import-not-found,unused-ignore]
            ControlUnitStatus,
            WheelCommand,
        )

        codec = self._codec
        self._t = now_s
        self._seq = (self._seq + 1) & 0xFF
        cmd = WheelCommand(
            float(command.left_duty),
            float(command.right_duty),
            laser_on=bool(command.laser_on),
            enable=bool(command.enable),
        )
        reply = self.emulator.handle_bytes(codec.encode_command(cmd.to_frame(self._seq)))
        frames = [
            f
            for f in self._parser.feed(reply)
            if isinstance(f, codec.ReplyFrame) and f.seq == self._seq
        ]
        if not frames:
            self.missed_replies += 1
            return None
        rep = frames[-1]
        raw = (rep.left_clocks, rep.right_clocks)
        if self._raw is not None:
            self._clocks = (
                self._clocks[0] + codec.unwrap_int32(self._raw[0], raw[0]),
                self._clocks[1] + codec.unwrap_int32(self._raw[1], raw[1]),
            )
        else:
            self._clocks = raw
        self._raw = raw
        return ControlUnitStatus.from_reply(rep, *self._clocks, now_s)

    def advance(self, now_s: float, dt_s: float) -> None:
        """Let the emulator drive the plant up to ``now_s + dt_s``."""
        self._t = now_s + dt_s
        _ = self.emulator.clocks  # integrates the plant to the clock


def make_control_unit(plant: Chair, kind: str, watchdog_s: float) -> Any:
    """``emulator`` (bytes through the codec) or ``direct`` (the plant without a link)."""
    if kind == "emulator":
        return EmulatedControlUnit(plant, watchdog_s)
    return DirectControlUnit(plant, watchdog_s)


# -- open-loop driving ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Command:
    left_duty: float
    right_duty: float
    laser_on: bool = True
    enable: bool = True


class OpenLoopDriver:
    """A controller that ignores its inputs and plays ``[(t_s, left_duty, right_duty), ...]``
    (each held until the next). It is *not* a daemon: it shows what the chair does unguarded."""

    def __init__(self, script: Sequence[tuple[float, float, float]]) -> None:
        self.script = sorted((float(t), float(a), float(b)) for t, a, b in script)

    def step(self, now_s: float) -> _Command:
        left = right = 0.0
        for t, a, b in self.script:
            if t <= now_s:
                left, right = a, b
        return _Command(left, right)

    def on_status(self, status: Any) -> None:
        pass

    def on_tilt(self, reading: Any) -> None:
        pass

    def on_key(self, command: str, now_s: float) -> None:
        pass

    def on_joystick(self, reading: Any) -> None:
        pass

    def on_perception(self, cloud: PointCloud, capture_time_s: float) -> None:
        pass


# -- rider ----------------------------------------------------------------------------------------


class EmulatedTiltSensor:
    """The GS311 emulator (``omnid.devices.emulators.gs311``) on the virtual clock, read the way
    the tilt link reads it: the read-angles request ``0x50 0x50`` goes in as bytes, the reply
    bytes go through the codec's parser (``Gs311Parser`` with the link's default
    ``TiltSettings`` layout) and become a ``TiltReading`` — so the daemon core gets the angles
    the real link would decode, 12-bit quantisation and checksum included.

    ``unplugged`` (the ``tilt_unplugged`` fault) stops all replies, as a pulled adapter does.
    """

    def __init__(
        self, script: HeadScript | ReactiveRider, noise_deg: float = 0.0, seed: int = 0
    ) -> None:
        from omnid.devices import gs311_codec as codec
        from omnid.devices.emulators.gs311 import Gs311Emulator, HeadMotion
        from omnid.devices.tilt import TiltReading, TiltSettings

        self._t = 0.0
        self._codec = codec
        self._reading = TiltReading
        fmt = TiltSettings().format
        motion: HeadMotion | list[tuple[float, float, float]]
        if isinstance(script, ReactiveRider):
            motion = _live_head(HeadMotion, script)
        else:
            motion = script.as_list()
        self.emulator = Gs311Emulator(
            motion, fmt=fmt, noise_deg=noise_deg, seed=seed, clock=lambda: self._t
        )
        self.parser = codec.Gs311Parser(fmt)
        self.unplugged = False
        self.readings = 0

    def poll(self, now_s: float) -> Any:
        """One half-duplex request at ``now_s``: the decoded reading, or None (no valid reply)."""
        self._t = now_s
        if self.unplugged:
            return None
        self.parser.reset()
        frames = self.parser.feed(self.emulator.handle(self._codec.READ_ANGLES_REQUEST))
        if not frames:
            return None
        self.readings += 1
        f = frames[-1]
        return self._reading(f.roll_deg, f.pitch_deg, now_s)


def _live_head(base: Any, rider: ReactiveRider) -> Any:
    """A ``HeadMotion`` (the GS311 emulator's script) that reads a reactive rider's head."""

    class LiveHead(base):
        def __init__(self) -> None:
            super().__init__([(0.0, 0.0, 0.0)])

        def angles_at(self, t_s: float) -> tuple[float, float]:
            return rider.angles_at(t_s)

    return LiveHead()


class DirectTiltSensor:
    """The head script's angles without the byte link (for probes and tests of the script)."""

    def __init__(self, script: HeadScript | ReactiveRider) -> None:
        self.script = script
        self._reading = TiltReading
        self.unplugged = False

    def poll(self, now_s: float) -> Any:
        if self.unplugged:
            return None
        script = self.script
        if isinstance(script, ReactiveRider):
            roll, pitch = script.angles_at(now_s)
        else:
            roll, pitch = script.at(now_s)
        return self._reading(roll, pitch, now_s)


# -- perception ---------------------------------------------------------------------------------


def _perimeter(chair: Chair, per_side: int = 6) -> NDArray[np.float64]:
    c = chair.footprint()
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)[:, None]
    return np.vstack([c[i] + t * (c[(i + 1) % 4] - c[i]) for i in range(4)])


def _clearance(points: NDArray[np.float64], rects: NDArray[np.float64]) -> float:
    """Smallest distance from any point (N, 2) to any rectangle (R, 4: x0, x1, y0, y1), mm."""
    if len(rects) == 0:
        return math.inf
    dx = np.maximum(
        np.maximum(rects[None, :, 0] - points[:, None, 0], 0.0),
        points[:, None, 0] - rects[None, :, 1],
    )
    dy = np.maximum(
        np.maximum(rects[None, :, 2] - points[:, None, 1], 0.0),
        points[:, None, 1] - rects[None, :, 3],
    )
    return float(np.hypot(dx, dy).min())


@dataclass
class _Cycle:
    """The state of one perception cycle (mirrors ``omnid.daemon.run.Daemon.perception_loop``)."""

    phase: Literal["idle", "wait_off", "mask", "wait_on", "base"] = "idle"
    started_s: float = 0.0
    phase_s: float = 0.0
    mask_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mask_laser: bool = False
    next_s: float = 0.0  # the next cycle starts no earlier than this


class Simulator:
    """One simulated chair in one course, driven by a controller on a virtual clock.

    With ``perception="pipeline"`` the simulator first *installs* the chair
    (:meth:`install`): it renders a floor capture of an empty floor with the rig's cameras (by
    default deliberately misaligned, :func:`misaligned_rig`) and runs
    ``calibrate_from_capture`` on it; every perception cycle then renders mask and base frames
    and runs ``pipeline.perceive(capture, calibration, "best")``. The daemon never learns the
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
        pattern: Laser | None = None,
        progress: Callable[[float, Simulator], None] | None = None,
        faults: Sequence[Fault] = (),
        joystick: JoystickScript | None = None,
    ) -> None:
        self.course = course
        self.controller = controller
        self.settings = (settings or SimSettings()).for_controller(controller)
        s = self.settings
        self.chair = Chair(chair_settings, pose=course.start_pose)
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
        # the world's laser (never handed to perception; calibration learns it)
        self.pattern: Laser = pattern if pattern is not None else LaserProjector()
        self.control_unit = make_control_unit(self.chair, s.control_unit, s.watchdog_s)
        self.tilt: EmulatedTiltSensor | DirectTiltSensor | None = None
        if rider is not None:
            if s.tilt_link == "emulator":
                self.tilt = EmulatedTiltSensor(rider, s.tilt_noise_deg, s.seed)
            else:
                self.tilt = DirectTiltSensor(rider)
        self.faults = tuple(faults)
        self.progress = progress
        self.now_s = 0.0
        self._rng = np.random.default_rng(s.seed)
        self.calibration: Any = None
        self.install_s = 0.0
        if s.perception == "pipeline":
            self.install()
        box_rects = [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm) for b in course.world.boxes]
        drop_rects = [
            (d.x_min_mm, d.x_max_mm, d.y_min_mm, d.y_max_mm) for d in course.world.dropoffs
        ]
        self._box_rects = np.array(box_rects, dtype=np.float64).reshape(-1, 4)
        self._drop_rects = np.array(drop_rects, dtype=np.float64).reshape(-1, 4)
        self._last_status: Any = None
        self._active: set[str] = set()
        # Laser hits per pose: a chair standing still (refused, resting) sees the same dots, so
        # truth perception casts them once per pose; fresh noise is drawn on every use.
        self._hits_cache: dict[tuple[float, float, float], Any] = {}

    # -- installation -------------------------------------------------------------------------

    def install(self) -> Any:
        """Calibrate the rig as an installer would: a capture of the empty floor ``H`` below the
        mirrors and the extra captures of a box and a wall ahead (laser on),
        :func:`omnid.sim.installation.calibrate_installed`; the result is what perception uses."""
        from omnid.sim.installation import calibrate_installed

        w0 = time.perf_counter()
        self.calibration = calibrate_installed(
            self.rig, self.pattern, self.mount, seed=self.settings.seed
        )
        self.install_s = time.perf_counter() - w0
        return self.calibration

    # -- camera views -------------------------------------------------------------------------

    def laser_hits(self, pose: tuple[float, float, float] | None = None) -> Any:
        """``cast_laser`` at ``pose`` (default: the chair's current pose), remembered for the
        last few distinct poses (the world does not change during a run)."""
        key = pose or self.chair.pose
        hits = self._hits_cache.get(key)
        if hits is None:
            hits = cast_laser(self.course.world, key, self.mount, self.pattern, self.rig)
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
        from omnid.sim.render import RenderOptions, render_camera_pair

        on = self.control_unit.laser_on if laser_on is None else laser_on
        hits = self.laser_hits(pose)
        rng = np.random.default_rng(self._rng.integers(1 << 31) if seed is None else seed)
        opts = RenderOptions()
        images: list[NDArray[np.uint8]] = []
        for cam, vis in ((self.rig.cam1, hits.visible1), (self.rig.cam2, hits.visible2)):
            rc = cam.project(hits.xyz[vis]) if on else np.zeros((0, 2))
            images.extend(render_camera_pair(cam, rc, opts, rng))
        return StereoCapture(images[0], images[1], images[2], images[3], self.now_s)

    def frame(self) -> tuple[float, NDArray[np.uint8], NDArray[np.uint8]]:
        """What each camera sees now (the base images), for the frame server."""
        cap = self.render()
        return self.now_s, cap.base1, cap.base2

    # -- perception ---------------------------------------------------------------------------

    def _truth_cloud(self, pose: tuple[float, float, float] | None = None) -> PointCloud:
        hits = self.laser_hits(pose)
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

    def _perceive(self, capture: StereoCapture | None, base_pose: Any, base_laser: bool) -> Any:
        """The vision step the daemon's worker runs (timed by the caller)."""
        if "perception_exception" in self._active:
            raise InjectedFault("injected fault: the vision pipeline raised")
        mode = self.settings.perception
        if mode == "off" or not base_laser or (mode == "pipeline" and capture is None):
            return PointCloud(floor_depth_mm=self.mount.height_mm)
        if mode == "truth":
            return self._truth_cloud(base_pose)
        from omnid.core.pipeline import perceive

        assert capture is not None
        return perceive(capture, self.calibration, "best")

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
        cloud: PointCloud = self._perceive(self.capture(pose, False, pose, on), pose, on)
        return cloud

    # -- faults -------------------------------------------------------------------------------

    def _apply_faults(self, now: float) -> None:
        active: set[str] = {str(f.kind) for f in self.faults if f.active(now)}
        if active == self._active:
            return
        for name in sorted(active - self._active):
            log.warning("simulator: fault %s injected at t=%.2f s", name, now)
        for gone in sorted(self._active - active):
            log.warning("simulator: fault %s cleared at t=%.2f s", gone, now)
        emu = getattr(self.control_unit, "emulator", None)
        if emu is not None:
            if {"cu_silent", "cu_corrupt"} & (self._active - active):
                emu.recover()
            if "cu_silent" in active:
                emu.stall()
            if "cu_corrupt" in active:
                emu.corrupt_replies(None)
        if isinstance(self.control_unit, DirectControlUnit):
            self.control_unit.silent = bool({"cu_silent", "cu_corrupt"} & active)
        if self.tilt is not None:
            self.tilt.unplugged = "tilt_unplugged" in active
        self._active = active

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

    def _laser_reported(self, on: bool, since_s: float) -> bool:
        st = self._last_status
        return st is not None and bool(st.laser_on) == on and st.timestamp_s >= since_s

    def run(self, duration_s: float) -> SimResult:
        """Simulate ``duration_s`` virtual seconds; returns the trajectory, contacts, refusals,
        what perception saw and timing figures."""
        require(duration_s > 0, "duration_s", "must be positive")
        s = self.settings
        dt = s.physics_dt_s
        n_ticks = round(duration_s / dt)
        k_ctrl, k_tilt = s.ticks(s.control_period_s), s.ticks(s.tilt_period_s)
        k_perc, k_rec = s.ticks(s.perception_period_s), s.ticks(s.record_period_s)
        ctl = self.controller
        # A daemon core runs the real perception cycle (laser off → mask → laser on → base);
        # simple probes get a capture every period with the laser as it is.
        cycle = _Cycle() if hasattr(ctl, "capturing") and hasattr(ctl, "laser_on") else None
        joy_reading = JoystickReading
        last_pose: tuple[float, float, float] | None = None

        # Records preallocated for the whole run (no per-tick allocations; a soak's memory
        # figure then shows the daemon, not the recorder). Filled now, not np.empty: the kernel
        # commits a page only when it is first written, so empty records grew the resident
        # memory by 3.4 kB per simulated second (6 MB in a 30-minute soak) as they filled.
        traj = np.full((n_ticks // k_rec + 2, 4), np.nan)
        speeds = np.full((n_ticks + 1, 3), np.nan)
        cmds = np.full((n_ticks // k_ctrl + 1, 5), np.nan)
        steps = np.full((n_ticks // k_ctrl + 1, 7), np.nan)
        reason_bits: dict[str, int] = {}
        n_traj = n_speed = n_cmd = 0
        contacts: list[tuple[float, Contact]] = []
        seen: list[NDArray[np.float64]] = []
        pending: list[tuple[float, float, PointCloud, tuple[float, float, float]]] = []
        t_perc: list[float] = []
        ctrl_n, ctrl_sum, ctrl_max = 0, 0.0, 0.0  # control-step wall times, s
        errors: list[tuple[float, str]] = []
        min_clear = math.inf
        refusals: list[tuple[float, str]] = []
        last_refusal = ""
        wall0 = time.perf_counter()
        last_progress = -math.inf

        def finish(t_cap: float, pose: Any, cap: StereoCapture | None, laser: bool) -> None:
            w0 = time.perf_counter()
            try:
                cloud = self._perceive(cap, pose, laser)
            except Exception as exc:  # as the daemon's perception loop: log, no result
                errors.append((now, f"{type(exc).__name__}: {exc}"))
                log.warning("perception cycle failed at t=%.2f s: %s", now, exc)
                return
            took = time.perf_counter() - w0
            t_perc.append(took)
            pending.append((now + max(took, s.perception_latency_s), t_cap, cloud, pose))

        for k in range(n_ticks + 1):
            now = k * dt
            self.now_s = now
            self._apply_faults(now)
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
                and "tilt_unplugged" not in self._active
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
            if cycle is None:
                if k % k_perc == 0:
                    on = bool(self.control_unit.laser_on)
                    pose = self.chair.pose
                    cap = (
                        self.capture(pose, False, pose, on)
                        if s.perception == "pipeline" and on
                        else None
                    )
                    finish(now, pose, cap, on)
            else:
                self._perception_cycle(cycle, now, finish, errors)
            if k % k_ctrl == 0:
                w0 = time.perf_counter()
                command = ctl.step(now)
                took_ctrl = time.perf_counter() - w0
                ctrl_n, ctrl_sum = ctrl_n + 1, ctrl_sum + took_ctrl
                ctrl_max = max(ctrl_max, took_ctrl)
                last_refusal = self._note_decision(now, refusals, last_refusal)
                steps[n_cmd] = (
                    now,
                    self._reason_mask(reason_bits),
                    *self.chair.pose,
                    *self._speed(),
                )
                status = self.control_unit.exchange(command, now)
                if status is not None:
                    self._last_status = status
                    ctl.on_status(status)
                cmds[n_cmd] = (
                    now,
                    float(command.left_duty),
                    float(command.right_duty),
                    float(command.laser_on),
                    float(command.enable),
                )
                n_cmd += 1
            speeds[n_speed] = (now, self.chair.left_speed_mm_s, self.chair.right_speed_mm_s)
            n_speed += 1
            if k % k_rec == 0:
                traj[n_traj] = (now, *self.chair.pose)
                n_traj += 1
                min_clear = min(
                    min_clear,
                    _clearance(_perimeter(self.chair), self._box_rects),
                    _clearance(
                        np.array(list(self.chair.support_points().values())), self._drop_rects
                    ),
                )
                if self.progress is not None and now - last_progress >= 1.0:
                    last_progress = now
                    self.progress(now, self)
            pose_now = self.chair.pose
            found = self.chair.contacts(self.course.world) if pose_now != last_pose else []
            last_pose = pose_now  # a chair that has not moved touches nothing new
            new = [c for c in found if all(c != old for _, old in contacts)]
            if new:
                min_clear = 0.0
            for c in new:
                log.warning("simulated chair %s (%s) at t=%.2f s", c.kind, c.part, now)
                contacts.append((now, c))
            if new and s.stop_on_contact:
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

    def _perception_cycle(
        self,
        c: _Cycle,
        now: float,
        finish: Callable[[float, Any, StereoCapture | None, bool], None],
        errors: list[tuple[float, str]],
    ) -> None:
        """Advance the perception cycle of ``omnid run`` by one tick: laser off → wait until
        the control unit reports it off (at most ``laser_timeout_s``) → a flushed mask frame →
        laser on → wait until reported on → a flushed base frame → perceive. Frames take
        ``frame_interval_s``; with the cameras stopped a read fails after ``frame_timeout_s``."""
        s = self.settings
        ctl = self.controller
        camera_ok = "camera_stopped" not in self._active

        def fail(why: str) -> None:
            errors.append((now, why))
            log.warning("perception cycle failed at t=%.2f s: %s", now, why)
            ctl.capturing = False
            ctl.laser_on = True
            c.phase = "idle"
            c.next_s = max(c.started_s + float(s.perception_period_s or 0.0), now)

        if c.phase == "idle":
            if now + 1e-9 < c.next_s:
                return
            c.started_s = c.phase_s = now
            ctl.capturing = True
            ctl.laser_on = False
            c.phase = "wait_off"
        if c.phase == "wait_off":
            if self._laser_reported(False, c.phase_s) or now - c.phase_s >= s.laser_timeout_s:
                c.phase, c.phase_s = "mask", now  # run.py reads the mask even after a timeout
            else:
                return
        if c.phase == "mask":
            if not camera_ok:
                if now - c.phase_s >= s.frame_timeout_s:
                    fail("camera: no frame within frame_timeout_s")
                return
            if now - c.phase_s + 1e-9 < s.frame_interval_s:
                return
            c.mask_pose, c.mask_laser = self.chair.pose, bool(self.control_unit.laser_on)
            ctl.laser_on = True
            c.phase, c.phase_s = "wait_on", now
        if c.phase == "wait_on":
            if self._laser_reported(True, c.phase_s):
                c.phase, c.phase_s = "base", now
            elif now - c.phase_s >= s.laser_timeout_s:
                fail("control unit did not report the laser on")
                return
            else:
                return
        if c.phase == "base":
            if not camera_ok:
                if now - c.phase_s >= s.frame_timeout_s:
                    fail("camera: no frame within frame_timeout_s")
                return
            if now - c.phase_s + 1e-9 < s.frame_interval_s:
                return
            pose, laser = self.chair.pose, bool(self.control_unit.laser_on)
            ctl.capturing = False
            c.phase = "idle"
            c.next_s = max(c.started_s + float(s.perception_period_s or 0.0), now)
            cap = None
            if s.perception == "pipeline":
                cap = self.capture(c.mask_pose, c.mask_laser, pose, laser)
            finish(now, pose, cap, laser)
