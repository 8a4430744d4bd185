"""``OmnidConfig``: every module's settings in one validated tree (``etc/omnid.yaml``).

Read once at start with :func:`load_config` (unknown keys, duplicate keys and values outside their
range are refused with the dotted key and the file named). The dataclass defaults are the shipped
``etc/omnid.yaml`` (``tests/daemon/test_daemon_config.py`` proves it). On SIGHUP the daemon calls
:meth:`ConfigHolder.reload_off_loop`, which reads the file in a helper thread with a timeout and
keeps the running configuration when the new file is invalid, saying why; the daemon refuses
as well a file that changes a key only a restart can apply (:data:`RESTART_ONLY`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from omnid.config import Settings, from_mapping, load_yaml, require, setting, to_mapping
from omnid.core.detect import DetectionParams
from omnid.core.freespace import FreeSpaceSettings
from omnid.daemon.motion import MotionSettings
from omnid.daemon.rider import RiderSettings
from omnid.daemon.safety import SafetySettings
from omnid.devices.camera import CameraSettings
from omnid.devices.control_unit import ControlUnitSettings
from omnid.devices.joystick import JoystickSettings as JoystickDeviceSettings
from omnid.devices.teleop import TeleopSettings
from omnid.devices.tilt import TiltSettings as TiltSensorSettings
from omnid.errors import ConfigError
from omnid.record.settings import RecordSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ControlSettings(Settings):
    """The fixed-rate control loop and its watchdogs."""

    rate_hz: float = setting(50.0, 1.0, 500.0)
    status_timeout_s: float = setting(0.25, 0.01, 2.0)  # no control-unit status this long → stop
    # a longer gap between cycles is treated as this (no ramp jumps)
    max_dt_s: float = setting(0.1, 0.005, 1.0)
    # odometry kept to compensate late perception results
    pose_history_s: float = setting(5.0, 0.5, 60.0)
    # after a fault (control unit, lost rider input, a cycle exception) motion waits until the
    # source that was driving has given a live neutral/stop once the fault has cleared. The
    # simulator's scripted riders turn it off (omnid.sim.scenario.make_core)
    rearm_after_fault: bool = True

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class PerceptionSettings(Settings):
    """The capture cycle (omnid.daemon.capture) and the perception worker."""

    enabled: bool = True
    method: Literal["best", "thesis"] = "best"
    calibration_path: str = "/etc/omnid/calibration.yaml"
    # stream: a cloud for every laser-on frame, the laser off for every mask_every_frames-th
    # (needs a laser that switches within laser_switch_latency_s); stationary: the thesis'
    # laser off → mask → laser on → base every period_s (with safety.perception_timeout_s
    # above period_s: docs/framerate.md)
    capture: Literal["stream", "stationary"] = "stream"
    period_s: float = setting(0.5, 0.01, 10.0)  # stationary: start a new cycle at most this often
    # stream: worst case from the laser request to the light switched (the command path plus
    # the relay); frames exposed while a request may still be taking effect are not used
    laser_switch_latency_s: float = setting(0.018, 0.0, 0.5)
    # stream: the laser is switched again no sooner than this after a switch (relay wear)
    laser_min_switch_interval_s: float = setting(0.0, 0.0, 1.0)
    # stream: every n-th frame of the cameras' clock is a mask (laser off): n − 1 clouds per n
    # frames when the laser switches within one gap between exposures
    mask_every_frames: int = setting(3, 2, 60)
    # stream: a base frame waits for the next mask and is subtracted against the brighter of
    # both (the parallax the floor's motion compensation misses lies on either side); false:
    # the earlier mask alone, dilated, up to mask_every_frames − 1 frame periods sooner
    mask_bracketing: bool = True
    mask_max_age_s: float = setting(
        0.3, 0.05, 5.0
    )  # stream: a mask farther from its base is unused
    # move each mask to its base frame's pose by the wheels' motion before subtracting
    motion_compensation: bool = True
    # the control unit must report a requested laser switch within this
    laser_timeout_s: float = setting(0.5, 0.01, 5.0)
    flush_frames: bool = True  # stationary: drop frames queued before the laser switched
    capture_policy: Literal["limit", "compensate"] = "limit"
    # stationary: speed cap while mask/base frames are taken ("limit"); measured harmless up to 240 mm/s
    # on tiled floors (tools/eval_capture_motion.py, docs/daemon.md): a margin for sharper,
    # specular floor texture than modelled
    capture_speed_mm_s: float = setting(80.0, 0.0, 500.0)
    rig_x_offset_mm: float = setting(300.0, -2000.0, 2000.0)  # rig origin ahead of the axle
    frame_timeout_s: float = setting(1.0, 0.01, 10.0)
    # a frame pair awaited this long (or a camera error) counts as the cameras lost: speed
    # capped at safety.camera_lost_speed_mm_s until a pair arrives (30 fps: 2.4 frame times)
    camera_silence_s: float = setting(0.08, 0.02, 2.0)
    # this many clouds in a row that do not fit the calibration (omnid.core.pipeline's
    # CalibrationHealth) mean the rig was knocked: calibration_lost, forward refused until one
    # fits; a shorter run (a frame the laser lit half, a glare) only keeps those clouds out of
    # the map, and perception staleness stops the chair if nothing usable follows
    calibration_lost_clouds: int = setting(3, 1, 100)
    # a perceive call longer than this: worker killed, restarted
    worker_timeout_s: float = setting(1.0, 0.05, 30.0)
    # the worker process yields the CPU to the control loop (0 = as is)
    worker_nice: int = setting(10, 0, 19)


@dataclass(frozen=True)
class ServiceSettings(Settings):
    """systemd integration."""

    status_period_s: float = setting(1.0, 0.1, 60.0)  # STATUS= line this often
    # SIGHUP: the file is read and validated off the event loop; longer than this is refused
    reload_timeout_s: float = setting(2.0, 0.1, 30.0)


@dataclass(frozen=True)
class OmnidConfig(Settings):
    """Everything ``omnid run`` reads from its configuration file."""

    control: ControlSettings = field(default_factory=ControlSettings)
    rider: RiderSettings = field(default_factory=RiderSettings)
    safety: SafetySettings = field(default_factory=SafetySettings)
    motion: MotionSettings = field(default_factory=MotionSettings)
    freespace: FreeSpaceSettings = field(default_factory=FreeSpaceSettings)  # map + its grid
    detection: DetectionParams = field(default_factory=DetectionParams)
    perception: PerceptionSettings = field(default_factory=PerceptionSettings)
    control_unit: ControlUnitSettings = field(default_factory=ControlUnitSettings)
    camera: CameraSettings = field(default_factory=CameraSettings)
    teleop: TeleopSettings = field(default_factory=TeleopSettings)
    # the GS311 link (used when rider.tilt.enabled)
    tilt_sensor: TiltSensorSettings = field(default_factory=TiltSensorSettings)
    joystick_device: JoystickDeviceSettings = field(
        default_factory=JoystickDeviceSettings
    )  # the joystick link (used when rider.joystick.enabled)
    service: ServiceSettings = field(default_factory=ServiceSettings)
    record: RecordSettings = field(default_factory=RecordSettings)  # MCAP recording, live view

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.control.period_s <= self.control_unit.command_period_s + 1e-9,
            "control.rate_hz",
            "one control period must not exceed control_unit.command_period_s (the link "
            "sends only commands computed within the last two command periods)",
        )
        # the capture cycle (built at start, perception on or off) keeps laser switches out of
        # every exposure: one must end within its frame
        require(
            self.camera.exposure_s < 1.0 / self.camera.fps,
            "camera.exposure_s",
            f"must be shorter than one frame (1/camera.fps = {1e3 / self.camera.fps:.1f} ms)",
        )
        if self.perception.enabled and self.perception.capture == "stationary":
            require(
                self.safety.perception_timeout_s > self.perception.period_s,
                "safety.perception_timeout_s",
                "must exceed perception.period_s with perception.capture: stationary (a "
                "cloud at most every period_s; 1.5 s with the shipped 0.5 s)",
            )


#: What ``omnid run`` builds its links, tasks and map from at start (the control loop's period,
#: the control-unit link, the cameras and the perception worker, the remembered map, the rider
#: devices it opened, the capture cycle's odometry, the recorder and its live view): none of these can take a new value while
#: it runs. A reload that changes one is refused as a whole, naming the key — applying the
#: rest would leave the core on values the links, the loop or the map do not use.
RESTART_ONLY = (
    "control.rate_hz",
    "rider.tilt.enabled",
    "rider.joystick.enabled",
    "rider.keyboard.enabled",
    "motion.mm_per_clock",
    "motion.track_mm",
    "freespace",
    "detection",
    "perception",
    "control_unit",
    "camera",
    "teleop",
    "tilt_sensor",
    "joystick_device",
    "record",
)


def _changed(old: object, new: object, key: str) -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        return [c for k in old for c in _changed(old[k], new[k], f"{key}.{k}")]
    return [] if old == new else [key]


def restart_only_changes(old: OmnidConfig, new: OmnidConfig) -> list[str]:
    """The full dotted keys of :data:`RESTART_ONLY` whose value differs between the two."""
    out: list[str] = []
    before, after = to_mapping(old), to_mapping(new)
    for key in RESTART_ONLY:
        a, b = before, after
        for part in key.split("."):
            a, b = a[part], b[part]
        out += _changed(a, b, key)
    return out


def restart_only_refusal(old: OmnidConfig, new: OmnidConfig) -> str | None:
    """Why a reload from ``old`` to ``new`` cannot apply (``None``: it can)."""
    keys = restart_only_changes(old, new)
    if not keys:
        return None
    more = f" (and {len(keys) - 1} more)" if len(keys) > 1 else ""
    return (
        f"{keys[0]}{more}: changed, and takes effect only at a restart (systemctl restart "
        "omnid); nothing of the new file applied"
    )


def load_config(path: str | Path, allow_empty: bool = True) -> OmnidConfig:
    """Read and validate ``path``; :class:`ConfigError` names the file and the dotted key. An
    empty file is the shipped configuration at start; ``allow_empty=False`` (a reload) refuses
    it: a file emptied by accident (an editor's truncated save) must not reset a tuned
    footprint or speed to the built-in defaults under a running chair."""
    data = load_yaml(path)
    if not allow_empty and not data:
        raise ConfigError(
            f"{path}: empty; a reload does not reset every setting to the built-in defaults "
            "(restart to start from them)"
        )
    try:
        return from_mapping(OmnidConfig, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


#: ``check(old, new)`` of a reload: why the new configuration cannot apply, or ``None``
Check = Callable[[OmnidConfig, OmnidConfig], str | None]


class ConfigHolder:
    """The running configuration and its file; a reload never leaves it invalid.

    :meth:`reload` reads in the calling thread (start-up, tests); :meth:`reload_off_loop` reads
    and validates in a helper thread with a timeout, so a slow or hostile file cannot hold the
    event loop (and with it the device links) — the file's size, nesting and aliases are
    limited by :func:`omnid.config.load_yaml` as well.
    """

    def __init__(
        self, path: str | Path, adjust: Callable[[OmnidConfig], OmnidConfig] | None = None
    ) -> None:
        self.path = Path(path)
        # the command line's overrides (``omnid run --record/--view``), applied to the file at
        # start and at every reload alike: a reload compares like with like and keeps them
        self._adjust = adjust or (lambda config: config)
        self.config = self._adjust(load_config(self.path))
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._reading: asyncio.Future[OmnidConfig] | None = None

    def _accept(self, new: OmnidConfig) -> tuple[bool, str]:
        self.config = new
        log.info("configuration reloaded from %s", self.path)
        return True, "reloaded"

    @staticmethod
    def _refuse(why: str) -> tuple[bool, str]:
        log.error("configuration reload refused, keeping the running one: %s", why)
        return False, why

    def _check(self, new: OmnidConfig, check: Check | None) -> tuple[bool, str]:
        new = self._adjust(new)
        why = None if check is None else check(self.config, new)
        return self._refuse(f"{self.path}: {why}") if why else self._accept(new)

    def reload(self, check: Check | None = None) -> tuple[bool, str]:
        """Re-read the file. Returns (True, "reloaded") or (False, reason); on failure the
        previous configuration stays in force. ``check(old, new)``: a reason to refuse the new
        one (the daemon's :func:`restart_only_refusal`), or ``None``."""
        try:
            new = load_config(self.path, allow_empty=False)
        except ConfigError as exc:
            return self._refuse(str(exc))
        return self._check(new, check)

    async def reload_off_loop(
        self, timeout_s: float, check: Check | None = None
    ) -> tuple[bool, str]:
        """:meth:`reload`, the file read and validated in a helper thread; a read that takes
        longer than ``timeout_s`` (or one still running from an earlier request) is refused."""
        if self._reading is not None and not self._reading.done():
            return self._refuse(f"{self.path}: the previous reload is still reading the file")
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix="omnid-config"
            )
        loop = asyncio.get_running_loop()
        self._reading = loop.run_in_executor(self._executor, load_config, self.path, False)
        try:
            new = await asyncio.wait_for(asyncio.shield(self._reading), timeout_s)
        except TimeoutError:
            return self._refuse(f"{self.path}: reading took longer than {timeout_s:g} s")
        except ConfigError as exc:
            return self._refuse(str(exc))
        return self._check(new, check)

    def close(self) -> None:
        """End the helper thread (a read still running finishes on its own)."""
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
