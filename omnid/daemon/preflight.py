"""What ``omnid run`` checks before it starts, shared with ``omnid run --check``.

:func:`preflight` inspects a validated :class:`~omnid.daemon.config.OmnidConfig` against the
machine: the calibration file loads (when perception is on), device names are well formed and
present, the camera URL names a known backend, the teleop socket can be created and its group
exists. Each finding is a :class:`Check`:

- ``error`` — ``omnid run`` refuses to start (one line naming the key and the file);
- ``warning`` — the daemon starts, and says what the rider will notice (a port absent now is
  opened as soon as it appears; perception off refuses forward motion);
- ``ok``.

``omnid run`` calls it before touching any device and ``omnid run --check`` prints every line,
so the two can never disagree about a file.
"""

from __future__ import annotations

import grp
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

from omnid.daemon.config import OmnidConfig
from omnid.errors import ConfigError

__all__ = ["Check", "Preflight", "preflight"]

Status = Literal["ok", "warning", "error"]


@dataclass(frozen=True)
class Check:
    """One finding: what was checked (a key or a file), its status and a one-line detail."""

    what: str
    status: Status
    detail: str

    def line(self) -> str:
        return f"{self.status:<7}  {self.what}: {self.detail}"


@dataclass
class Preflight:
    """All findings, and the calibration loaded on the way (``None`` when perception is off)."""

    checks: list[Check] = field(default_factory=list)
    calibration: Any = None

    @property
    def errors(self) -> list[Check]:
        return [c for c in self.checks if c.status == "error"]

    @property
    def warnings(self) -> list[Check]:
        return [c for c in self.checks if c.status == "warning"]

    def raise_first_error(self, source: str | Path) -> None:
        """:class:`ConfigError` ``"source: key: detail"`` for the first error, if any."""
        if self.errors:
            c = self.errors[0]
            raise ConfigError(f"{source}: {c.what}: {c.detail}")

    def add(self, what: str, status: Status, detail: str) -> None:
        self.checks.append(Check(what, status, detail))


def _serial_port(result: Preflight, key: str, url: str, retry_s: float) -> None:
    if url.startswith("loop://"):
        result.add(key, "ok", f"{url} (in-process loopback)")
        return
    path = url.removeprefix("serial://")
    if "://" in path:
        result.add(key, "error", f"{url!r}: unknown scheme (a device path or loop://)")
        return
    if os.path.exists(path):
        real = os.path.realpath(path)
        try:
            is_char = stat.S_ISCHR(os.stat(real).st_mode)
        except OSError:
            is_char = False
        if is_char:
            result.add(key, "ok", f"{path} present ({real})")
        else:
            result.add(key, "error", f"{path} is not a character device ({real})")
    else:
        result.add(
            key,
            "warning",
            f"{path} absent now: the link opens it when it appears (retried every ≤ "
            f"{retry_s:g} s); the wheels stay stopped until then",
        )


def _hid(result: Preflight, key: str, target: str) -> None:
    try:
        vid, pid = target.split(":")
        int(vid, 16), int(pid, 16)
    except ValueError:
        result.add(key, "error", f"expected hid://VID:PID in hex, got hid://{target}")
        return
    result.add(key, "ok", f"hid://{target} (opened at start; absent = rider input stops)")


def _camera(result: Preflight, config: OmnidConfig) -> None:
    url = config.camera.url
    parts = urlsplit(url)
    key = "camera.url"
    if parts.scheme == "v4l2":
        devices = [d for d in parts.path.split(",") if d]
        if len(devices) != 2:
            result.add(key, "error", f"v4l2 needs two devices, got {url!r}")
            return
        absent = [d for d in devices if d.startswith("/") and not os.path.exists(d)]
        if absent:
            result.add(
                key,
                "warning",
                f"{', '.join(absent)} absent now: perception fails (no forward motion) until "
                "the cameras appear",
            )
        else:
            result.add(key, "ok", f"{url}")
    elif parts.scheme == "replay":
        if Path(parts.path).is_dir():
            result.add(key, "ok", f"{url} (recorded frames)")
        else:
            result.add(key, "error", f"replay directory {parts.path} does not exist")
    elif parts.scheme == "sim+unix":
        if os.path.exists(parts.path):
            result.add(key, "ok", f"{url} (simulator frame server)")
        else:
            result.add(
                key,
                "warning",
                f"{parts.path} absent now: start `omnid simulate --serve {parts.path}`",
            )
    else:
        result.add(
            key,
            "error",
            f"unknown scheme {parts.scheme!r} in {url!r} (known: v4l2, replay, sim+unix)",
        )


def _teleop(result: Preflight, config: OmnidConfig) -> None:
    t = config.teleop
    path = Path(t.socket_path)
    if t.group is not None:
        try:
            grp.getgrnam(t.group)
        except KeyError:
            result.add("teleop.group", "error", f"no such group {t.group!r}")
        else:
            result.add("teleop.group", "ok", f"{t.group}")
    if os.path.lexists(path) and not stat.S_ISSOCK(path.lstat().st_mode):
        result.add("teleop.socket_path", "error", f"{path} exists and is not a socket")
        return
    parent = path.parent
    existing = parent
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        result.add(
            "teleop.socket_path",
            "error",
            f"cannot create {path}: {existing} is not a writable directory",
        )
        return
    made = "" if parent.exists() else f" ({parent} is created at start)"
    result.add("teleop.socket_path", "ok", f"{path} can be created{made}")


def preflight(config: OmnidConfig, source: str | Path = "configuration") -> Preflight:
    """Every check ``omnid run`` makes before it starts (see the module docstring)."""
    from omnid.core.calibration import Calibration

    result = Preflight()
    n_keys = _count_keys(config)
    result.add(str(source), "ok", f"read and validated ({n_keys} keys, every number in range)")
    p = config.perception
    if p.enabled:
        path = Path(p.calibration_path)
        if not path.is_file():
            result.add(
                "perception.calibration_path",
                "error",
                f"{path} does not exist (write it with `omnid calibrate`, or set "
                "perception.enabled: false to run without forward motion)",
            )
        else:
            try:
                result.calibration = Calibration.load(path)
            except (ConfigError, OSError, ValueError) as exc:
                result.add("perception.calibration_path", "error", f"{exc}")
            else:
                result.add("perception.calibration_path", "ok", f"{path} loaded")
        _camera(result, config)
    else:
        creep = config.safety.unknown_policy == "creep"
        result.add(
            "perception.enabled",
            "warning",
            "false: no free space is ever seen, forward motion is refused"
            + (" (turns creep, stop works)" if creep else " (and every turn: only stop works)"),
        )
    cu = config.control_unit
    _serial_port(result, "control_unit.port", cu.port, cu.reconnect_max_s)
    r = config.rider
    if r.tilt.enabled:
        ts = config.tilt_sensor
        if ts.port.startswith("hid://"):
            _hid(result, "tilt_sensor.port", ts.port.removeprefix("hid://"))
        else:
            _serial_port(result, "tilt_sensor.port", ts.port, ts.reconnect_max_s)
        if r.tilt.neutral_calibration_s > 0:
            result.add(
                "rider.tilt.neutral_calibration_s",
                "ok",
                f"{r.tilt.neutral_calibration_s:g} s: the rider holds the head still at start",
            )
    if r.joystick.enabled:
        url = config.joystick_device.url
        if url.startswith("hid://"):
            _hid(result, "joystick_device.url", url.removeprefix("hid://"))
        elif url.startswith("evdev://"):
            dev = url.removeprefix("evdev://")
            if os.path.exists(dev):
                result.add("joystick_device.url", "ok", f"{dev} present")
            else:
                result.add(
                    "joystick_device.url",
                    "warning",
                    f"{dev} absent now: retried every second; an absent joystick stops the chair",
                )
        else:
            result.add("joystick_device.url", "error", f"{url!r}: expected evdev:// or hid://")
    if r.keyboard.enabled:
        _teleop(result, config)
    enabled = [n for n in ("tilt", "joystick", "keyboard") if getattr(r, n).enabled]
    if not enabled:
        result.add("rider", "warning", "no rider input is enabled: the chair never moves")
    return result


def _count_keys(obj: Any) -> int:
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return sum(_count_keys(getattr(obj, f.name)) for f in dataclasses.fields(obj))
    return 1
