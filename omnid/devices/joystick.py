"""Hand joystick: Linux input events (evdev) or USB HID (hidapi), mapped to forward/turn.

The stick's two axes become ``JoystickReading(forward, turn, timestamp_s)`` in [-1, 1] (forward
positive = drive ahead, turn positive = turn left, CCW as the robot frame), with a dead zone
around the centre and the remaining travel rescaled so speed is proportional to deflection
(:func:`shape_axis`). :func:`discrete_command` gives the thesis' keyboard-like commands
(forward/left/right/stop, 4.2.1) from the same reading.

Backends, chosen by ``JoystickSettings.url``:

- ``evdev:///dev/input/eventN`` — reads ``struct input_event`` records directly from the
  character device (no extra dependency): on 64-bit Linux ``struct timeval`` (two longs), ``u16
  type``, ``u16 code``, ``s32 value`` = 24 bytes. :class:`EvdevParser` is fed bytes, returns
  events; axis state is committed on ``EV_SYN/SYN_REPORT``. After ``SYN_DROPPED`` (the kernel's
  buffer overran, events were lost) the stick is not valid until the next ``SYN_REPORT``,
  then counts as centred until it reports a new position.
- ``hid://VID:PID`` — hidapi, imported only when chosen; reports are read with a timeout and
  the axes taken from byte offsets given in the settings (``hid_x_byte``, ``hid_y_byte``).

Staleness: an evdev device only speaks when the stick moves, so a held stick is silent. The link
therefore vouches for the reading while the device is open and healthy (the reader task
refreshes its liveness every ``stale_after_s / 2``, and ``latest.timestamp_s`` is that time);
an unplugged device (read error, EOF) makes ``latest`` None at once, and a reader task that
stops running makes it None after ``stale_after_s``; the daemon's mux treats None as stop.
After a loss the link reopens the device with back-off (``reconnect_initial_s`` doubling up to
``reconnect_max_s``); a reopened stick counts as centred until it reports a new position.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal
from urllib.parse import urlsplit

from omnid.config import Settings, require, setting
from omnid.devices.link import require_reconnect
from omnid.errors import ConfigError, DeviceClosed, DeviceError
from omnid.logs import LogThrottle

log = logging.getLogger(__name__)
_THROTTLE = LogThrottle(log, interval_s=5.0)  # a flapping connector must not flood the journal

EV_SYN = 0x00
EV_KEY = 0x01
EV_ABS = 0x03
SYN_REPORT = 0
SYN_DROPPED = 3
ABS_X = 0x00
ABS_Y = 0x01

INPUT_EVENT = struct.Struct("llHHi")  # struct input_event, native layout (24 bytes on 64-bit)


@dataclass(frozen=True)
class JoystickReading:
    """Stick position: ``forward`` (+ ahead) and ``turn`` (+ left), each in [-1, 1]."""

    forward: float
    turn: float
    timestamp_s: float

    def __post_init__(self) -> None:
        for name in ("forward", "turn"):
            v = getattr(self, name)
            if not (math.isfinite(v) and -1.0 <= v <= 1.0):
                raise ValueError(f"JoystickReading.{name} must be finite in [-1, 1], got {v!r}")


@dataclass(frozen=True)
class JoystickSettings(Settings):
    """Joystick device and mapping settings."""

    url: str = "evdev:///dev/input/event0"
    dead_zone: float = setting(0.15, 0.0, 0.9)  # fraction of half-travel ignored around the centre
    command_threshold: float = setting(
        0.5, 0.01, 1.0
    )  # deflection that counts as a discrete command
    # raw range of both axes (evdev: overridden by EVIOCGABS when available)
    axis_min: int = setting(0, -(2**31), 2**31 - 1)
    axis_max: int = setting(255, -(2**31), 2**31 - 1)
    x_code: int = setting(ABS_X, 0, 0x3F)  # evdev ABS_* codes
    y_code: int = setting(ABS_Y, 0, 0x3F)
    forward_sign: int = setting(-1, -1, 1)  # stick pushed away gives low Y on most devices
    turn_sign: int = setting(-1, -1, 1)  # stick pushed right gives high X; turn + is left
    stale_after_s: float = setting(0.2, 0.01, 2.0)
    # after an unplug, retry opening with this back-off …
    reconnect_initial_s: float = setting(0.1, 0.01, 10.0)
    reconnect_max_s: float = setting(2.0, 0.01, 60.0)  # … doubling up to this
    hid_x_byte: int = setting(0, 0, 255)
    hid_y_byte: int = setting(1, 0, 255)
    hid_report_size: int = setting(64, 2, 1024)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.dead_zone < self.command_threshold,
            "command_threshold",
            "must exceed dead_zone",
        )
        require(self.axis_max > self.axis_min, "axis_max", "must be > axis_min")
        require(self.forward_sign in (-1, 1), "forward_sign", "must be 1 or -1")
        require(self.turn_sign in (-1, 1), "turn_sign", "must be 1 or -1")
        require_reconnect(self.reconnect_initial_s, self.reconnect_max_s)


def normalise(raw: float, lo: float, hi: float) -> float:
    """Raw axis value → [-1, 1] (centre of the range → 0), clipped."""
    v = (2.0 * (raw - lo) / (hi - lo)) - 1.0
    return min(1.0, max(-1.0, v))


def shape_axis(v: float, dead_zone: float) -> float:
    """Dead zone, then the rest of the travel rescaled to [0, 1]: proportional speed, no jump."""
    a = abs(v)
    if a <= dead_zone:
        return 0.0
    return math.copysign(min(1.0, (a - dead_zone) / (1.0 - dead_zone)), v)


Command = Literal["forward", "left", "right", "stop"]


def discrete_command(reading: JoystickReading, threshold: float) -> Command | None:
    """Thesis 4.2.1 commands from a stick: the dominant deflection past ``threshold``.

    Pulled back → ``stop``; no deflection past the threshold → None (no command).
    """
    f, t = reading.forward, reading.turn
    if max(abs(f), abs(t)) < threshold:
        return None
    if abs(f) >= abs(t):
        return "forward" if f > 0 else "stop"
    return "left" if t > 0 else "right"


class AxisMapper:
    """Raw axis values → :class:`JoystickReading` under the settings."""

    def __init__(self, settings: JoystickSettings) -> None:
        self.s = settings
        self.ranges = {
            settings.x_code: (settings.axis_min, settings.axis_max),
            settings.y_code: (settings.axis_min, settings.axis_max),
        }
        centre = (settings.axis_min + settings.axis_max) / 2.0
        self.raw = {settings.x_code: centre, settings.y_code: centre}

    def set_range(self, code: int, lo: int, hi: int) -> None:
        if hi > lo:
            self.ranges[code] = (lo, hi)
            self.raw[code] = (lo + hi) / 2.0

    def reading(self, timestamp_s: float) -> JoystickReading:
        s = self.s
        x = normalise(self.raw[s.x_code], *self.ranges[s.x_code])
        y = normalise(self.raw[s.y_code], *self.ranges[s.y_code])
        return JoystickReading(
            forward=s.forward_sign * shape_axis(y, s.dead_zone) + 0.0,
            turn=s.turn_sign * shape_axis(x, s.dead_zone) + 0.0,
            timestamp_s=timestamp_s,
        )


@dataclass(frozen=True)
class InputEvent:
    """One Linux ``struct input_event``."""

    time_s: float
    type: int
    code: int
    value: int


class EvdevParser:
    """Fed bytes from an event device, returns whole :class:`InputEvent` records."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[InputEvent]:
        self._buf += data
        n = len(self._buf) // INPUT_EVENT.size
        out = [
            InputEvent(sec + usec * 1e-6, typ, code, value)
            for sec, usec, typ, code, value in INPUT_EVENT.iter_unpack(
                bytes(self._buf[: n * INPUT_EVENT.size])
            )
        ]
        del self._buf[: n * INPUT_EVENT.size]
        return out


def pack_event(type_: int, code: int, value: int, time_s: float = 0.0) -> bytes:
    """Bytes of one ``struct input_event`` (for emulating a device and for tests)."""
    sec = int(time_s)
    return INPUT_EVENT.pack(sec, int((time_s - sec) * 1e6), type_, code, value)


def _eviocgabs(code: int) -> int:
    # _IOR('E', 0x40 + code, struct input_absinfo)  (6 x s32 = 24 bytes)
    return (2 << 30) | (24 << 16) | (ord("E") << 8) | (0x40 + code)


class JoystickLink:
    """Asyncio reader of one joystick; ``latest`` is the current reading or None.

    ``await start()`` opens the device (raises DeviceError naming it), ``await stop()`` closes
    it. Errors while running mark the link disconnected (``latest`` → None, logged) and the
    link reopens the device by itself with back-off.
    """

    def __init__(
        self, settings: JoystickSettings | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.settings = settings or JoystickSettings()
        self.clock = clock
        self.mapper = AxisMapper(self.settings)
        self._task: asyncio.Task[None] | None = None
        self._reading: JoystickReading | None = None
        self._alive_s = -math.inf
        self.connected = False
        self.events = 0
        self.errors = 0
        self.dropped_syncs = 0
        self.reconnects = 0
        parts = urlsplit(self.settings.url)
        if parts.scheme not in ("evdev", "hid"):
            raise ConfigError(f"joystick.url: unknown scheme {parts.scheme!r} (known: evdev, hid)")
        self._scheme = parts.scheme
        self._target = parts.path if parts.scheme == "evdev" else parts.netloc or parts.path

    @property
    def latest(self) -> JoystickReading | None:
        """Current stick reading, or None when the device is gone or silent past staleness."""
        if not self.connected or self._reading is None:
            return None
        if self.clock() - self._alive_s > self.settings.stale_after_s:
            return None
        # the device vouched for this position at _alive_s (a held stick sends no events)
        return dataclasses.replace(self._reading, timestamp_s=self._alive_s)

    async def start(self) -> None:
        if self._task is not None and not self._task.done():
            return
        runner = await self._opener()
        self._task = asyncio.create_task(self._supervise(runner), name="omnid-joystick")

    async def _opener(self) -> Callable[[], Any]:
        opener = self._open_evdev if self._scheme == "evdev" else self._open_hid
        # a (re)opened stick counts as centred until it reports otherwise: a stick held over
        # a replug must not start the chair without a fresh movement
        self.mapper = AxisMapper(self.settings)
        runner = await opener()
        self.connected = True
        self._alive_s = self.clock()
        self._reading = self.mapper.reading(self.clock())
        return runner

    async def _supervise(self, runner: Callable[[], Any]) -> None:
        """Run the reader; after a loss, reopen with exponential back-off until stopped."""
        s = self.settings
        while True:
            await runner()
            backoff = s.reconnect_initial_s
            while True:
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, s.reconnect_max_s)
                try:
                    runner = await self._opener()
                except DeviceError as exc:
                    log.debug("joystick reopen failed: %s", exc)
                    continue
                self.reconnects += 1
                _THROTTLE.info("back", "joystick %s back", self._target)
                break

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._task
            self._task = None
        self.connected = False

    def _lost(self, why: str) -> None:
        self.errors += 1
        if self.connected:
            _THROTTLE.warning("lost", "joystick %s lost: %s (rider input stops)", self._target, why)
        self.connected = False

    # --- evdev ----------------------------------------------------------------------------
    async def _open_evdev(self) -> Callable[[], Any]:
        path = self._target
        try:
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as exc:
            raise DeviceError(f"joystick {path}: cannot open ({exc.strerror})") from exc
        self._query_abs_ranges(fd)
        parser = EvdevParser()
        pending = dict(self.mapper.raw)
        dropped = False  # SYN_DROPPED seen: events are discarded up to the next SYN_REPORT

        async def run() -> None:
            nonlocal pending, dropped
            loop = asyncio.get_running_loop()
            ready = asyncio.Event()
            loop.add_reader(fd, ready.set)
            try:
                while True:
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(ready.wait(), self.settings.stale_after_s / 2)
                    ready.clear()
                    try:
                        data = os.read(fd, 4096)
                    except BlockingIOError:
                        self._alive_s = self.clock()
                        continue
                    except OSError as exc:
                        self._lost(exc.strerror or str(exc))
                        return
                    if not data:
                        self._lost("end of file")
                        return
                    self._alive_s = self.clock()
                    for ev in parser.feed(data):
                        self.events += 1
                        if ev.type == EV_SYN and ev.code == SYN_DROPPED:
                            # the kernel's buffer overran: events were lost (a return to the
                            # centre among them, which evdev never repeats), so the position is
                            # unknown — not valid until resynced at the next SYN_REPORT
                            self.dropped_syncs += 1
                            dropped = True
                            self._reading = None
                            _THROTTLE.warning(
                                "dropped",
                                "joystick %s: events dropped by the kernel (SYN_DROPPED): "
                                "rider input stops until resynced",
                                self._target,
                            )
                        elif dropped:
                            if ev.type == EV_SYN and ev.code == SYN_REPORT:
                                # resync as at (re)open: counts as centred until the stick
                                # reports a new position
                                dropped = False
                                self.mapper = AxisMapper(self.settings)
                                self._query_abs_ranges(fd)
                                pending = dict(self.mapper.raw)
                                self._reading = self.mapper.reading(self.clock())
                        elif ev.type == EV_ABS and ev.code in pending:
                            pending[ev.code] = ev.value
                        elif ev.type == EV_SYN and ev.code == SYN_REPORT:
                            self.mapper.raw.update(pending)
                            self._reading = self.mapper.reading(self.clock())
            finally:
                loop.remove_reader(fd)
                os.close(fd)

        return run

    def _query_abs_ranges(self, fd: int) -> None:
        """Take each axis' min/max from the kernel (EVIOCGABS) when fd is a real event device."""
        import fcntl

        for code in (self.settings.x_code, self.settings.y_code):
            buf = bytearray(24)
            try:
                fcntl.ioctl(fd, _eviocgabs(code), buf, True)
            except OSError:
                return  # not an event device (FIFO, pty in tests): keep the configured range
            _value, lo, hi, *_ = struct.unpack("6i", buf)
            self.mapper.set_range(code, lo, hi)

    # --- hidapi ---------------------------------------------------------------------------
    async def _open_hid(self) -> Callable[[], Any]:
        try:
            import hid
        except ImportError as exc:
            raise DeviceError("joystick: the hid backend needs the hidapi package") from exc
        try:
            vid_s, pid_s = self._target.split(":")
            vid, pid = int(vid_s, 16), int(pid_s, 16)
        except ValueError:
            raise ConfigError(
                f"joystick.url: expected hid://VID:PID in hex, got {self.settings.url!r}"
            ) from None
        dev = hid.device()
        try:
            dev.open(vid, pid)
        except (OSError, ValueError) as exc:
            raise DeviceError(f"joystick hid {self._target}: cannot open ({exc})") from exc
        s = self.settings
        timeout_ms = max(1, int(s.stale_after_s * 500))

        async def run() -> None:
            try:
                while True:
                    try:
                        report = await asyncio.to_thread(dev.read, s.hid_report_size, timeout_ms)
                    except (OSError, ValueError) as exc:
                        self._lost(str(exc))
                        return
                    self._alive_s = self.clock()
                    if report and len(report) > max(s.hid_x_byte, s.hid_y_byte):
                        self.events += 1
                        self.mapper.raw[s.x_code] = report[s.hid_x_byte]
                        self.mapper.raw[s.y_code] = report[s.hid_y_byte]
                        self._reading = self.mapper.reading(self.clock())
            finally:
                dev.close()

        return run

    def require_open(self) -> None:
        if not self.connected:
            raise DeviceClosed(f"joystick {self._target}: not connected")
