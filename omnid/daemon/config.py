"""``OmnidConfig``: every module's settings in one validated tree (``etc/omnid.yaml``).

Read once at start with :func:`load_config` (unknown keys and bad values are refused with the
dotted key and the file named). On SIGHUP the daemon calls :meth:`ConfigHolder.reload`, which
keeps the running configuration when the new file is invalid and says why.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from omnid.config import from_mapping, load_yaml, require
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
class ControlSettings:
    """The fixed-rate control loop and its watchdogs."""

    rate_hz: float = 50.0
    status_timeout_s: float = 0.25  # no control-unit status this long → stop
    max_dt_s: float = 0.1  # a longer gap between cycles is treated as this (no ramp jumps)
    pose_history_s: float = 5.0  # odometry kept to compensate late perception results
    # after a control-unit fault or a cycle exception, motion waits until the rider's command
    # has been released once (the shipped etc/omnid.yaml: true). The default false keeps
    # clock-injected users (simulator scenarios) resuming with a held command
    rearm_after_fault: bool = False

    def __post_init__(self) -> None:
        require(1.0 <= self.rate_hz <= 500.0, "rate_hz", "must be in [1, 500]")
        require(0 < self.status_timeout_s <= 2.0, "status_timeout_s", "must be in (0, 2]")
        require(0 < self.max_dt_s <= 1.0, "max_dt_s", "must be in (0, 1]")
        require(self.pose_history_s > 0, "pose_history_s", "must be positive")

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class PerceptionSettings:
    """The perception cycle (laser off → mask pair → laser on → base pair → perceive)."""

    enabled: bool = True
    method: Literal["best", "thesis"] = "best"
    calibration_path: str = "/etc/omnid/calibration.yaml"
    period_s: float = 0.5  # start a new cycle at most this often
    laser_timeout_s: float = 0.5  # wait this long for the control unit to report the laser
    flush_frames: bool = True  # drop frames queued before the laser switched
    capture_policy: Literal["limit", "compensate"] = "limit"
    # speed cap while mask/base frames are taken ("limit"); measured harmless up to 240 mm/s
    # on tiled floors (tools/eval_capture_motion.py, docs/daemon.md): a margin for sharper,
    # specular floor texture than modelled
    capture_speed_mm_s: float = 80.0
    rig_x_offset_mm: float = 300.0  # rig origin ahead of the axle midpoint
    frame_timeout_s: float = 1.0
    worker_timeout_s: float = 1.0  # a perceive call longer than this: worker killed, restarted
    worker_nice: int = 10  # the worker process yields the CPU to the control loop (0 = as is)

    def __post_init__(self) -> None:
        require(self.period_s > 0, "period_s", "must be positive")
        require(self.worker_timeout_s > 0, "worker_timeout_s", "must be positive")
        require(0 <= self.worker_nice <= 19, "worker_nice", "must be in [0, 19]")
        require(self.laser_timeout_s > 0, "laser_timeout_s", "must be positive")
        require(self.capture_speed_mm_s >= 0, "capture_speed_mm_s", "must not be negative")
        require(self.frame_timeout_s > 0, "frame_timeout_s", "must be positive")


@dataclass(frozen=True)
class ServiceSettings:
    """systemd integration."""

    status_period_s: float = 1.0  # STATUS= line this often

    def __post_init__(self) -> None:
        require(self.status_period_s > 0, "status_period_s", "must be positive")


@dataclass(frozen=True)
class OmnidConfig:
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
    tilt_sensor: TiltSensorSettings = field(
        default_factory=lambda: TiltSensorSettings(port="/dev/omnid-tilt")
    )  # the GS311 link (used when rider.tilt.enabled)
    joystick_device: JoystickDeviceSettings = field(
        default_factory=JoystickDeviceSettings
    )  # the joystick link (used when rider.joystick.enabled)
    service: ServiceSettings = field(default_factory=ServiceSettings)
    record: RecordSettings = field(default_factory=RecordSettings)  # MCAP recording, live view


def load_config(path: str | Path) -> OmnidConfig:
    """Read and validate ``path``; :class:`ConfigError` names the file and the dotted key."""
    data = load_yaml(path)
    try:
        return from_mapping(OmnidConfig, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


class ConfigHolder:
    """The running configuration and its file; :meth:`reload` never leaves it invalid."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.config = load_config(self.path)

    def reload(self) -> tuple[bool, str]:
        """Re-read the file. Returns (True, "reloaded") or (False, reason); on failure the
        previous configuration stays in force."""
        try:
            new = load_config(self.path)
        except ConfigError as exc:
            log.error("configuration reload refused, keeping the running one: %s", exc)
            return False, str(exc)
        self.config = new
        log.info("configuration reloaded from %s", self.path)
        return True, "reloaded"
