"""The GS311 head-tilt sensor link (thesis 4.2.2, 4.2.2.1; SPEC §5).

:class:`TiltSensorLink` polls the sensor half-duplex: every ``poll_period_s`` (10 ms — the
sensor gives a reading every 0.01 s, Table 4.1) it discards stale input, sends the read-angles
command ``0x50 0x50`` and waits at most ``request_timeout_s`` for the ``0xA0`` reply
(:mod:`omnid.devices.gs311_codec`, whose docstring documents the assumed data layout).

Fail safe: :attr:`TiltSensorLink.latest` is the newest reading only while it is younger than
``stale_after_s``; otherwise it is ``None``. ``on_lost`` (optional) is called the moment the
port is lost, or the sensor has left as many requests in a row unanswered as fit in
``stale_after_s`` (4 at 10 ms: silent, or sending garbage), logged (rate-limited): the daemon
treats the rider's head input as lost — zero at once, a control cycle run then. Requests the
link did not send (the event loop stalled) are not held against the sensor. When the adapter disappears (USB unplugged: EIO/EOF) the port is
closed and reopened with exponential back-off (``reconnect_initial_s`` doubling up to
``reconnect_max_s``); counters in :attr:`TiltSensorLink.health` record every outcome.

Backends (``TiltSettings.port``): a device path (``/dev/ttyUSB1``, ``/dev/serial/by-id/...``,
a pty) or ``loop://`` through :func:`omnid.devices.transport.open_transport`; or
``hid://VID:PID`` when the USB adapter presents as HID (hidapi, imported only when chosen; each
report carries a length byte then the serial bytes, as CP2110-style bridges do).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from omnid.config import Settings, require, setting
from omnid.devices import gs311_codec as codec
from omnid.devices.link import LinkHealth, PolledLink, require_reconnect
from omnid.devices.transport import Transport, open_transport
from omnid.errors import ConfigError, DeviceClosed, DeviceError

__all__ = ["TiltHealth", "TiltReading", "TiltSensorLink", "TiltSettings"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TiltReading:
    """Head inclination: roll and pitch, deg, and the monotonic time the reply arrived, s."""

    roll_deg: float
    pitch_deg: float
    timestamp_s: float

    def __post_init__(self) -> None:
        for name in ("roll_deg", "pitch_deg", "timestamp_s"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"TiltReading.{name} must be finite, got {v!r}")


@dataclass(frozen=True)
class TiltSettings(Settings):
    """Settings of the tilt-sensor link (section ``tilt`` of the daemon's YAML).

    The last five keys describe the reply's data layout (see :mod:`omnid.devices.gs311_codec`),
    so a real unit can be matched without code changes.
    """

    port: str = "/dev/omnid-tilt"  # the udev name (etc/udev)
    baudrate: int = setting(115200, 1200, 3_000_000)
    poll_period_s: float = setting(0.01, 0.002, 0.5)
    request_timeout_s: float = setting(0.008, 0.001, 0.5)
    # the link stops vouching for a reading this old (and says so at once: on_lost)
    stale_after_s: float = setting(0.04, 0.004, 2.0)
    reconnect_initial_s: float = setting(0.05, 0.01, 10.0)
    reconnect_max_s: float = setting(1.0, 0.01, 60.0)
    hid_report_size: int = setting(64, 2, 1024)
    byte_order: Literal["big", "little"] = "big"
    deg_per_count: float = setting(90.0 / 4096.0, 1e-6, 1.0)
    roll_sign: int = setting(1, -1, 1)
    pitch_sign: int = setting(1, -1, 1)
    count_bits: int = setting(12, 8, 16)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(bool(self.port), "port", "must name a device path, loop:// or hid://VID:PID")
        require(
            self.request_timeout_s <= self.poll_period_s,
            "request_timeout_s",
            "must be at most poll_period_s (half duplex: one request at a time)",
        )
        require(
            self.stale_after_s >= 2 * self.poll_period_s,
            "stale_after_s",
            "must be at least two poll periods",
        )
        require_reconnect(self.reconnect_initial_s, self.reconnect_max_s)
        self.format  # validates the layout keys  # noqa: B018

    @property
    def format(self) -> codec.Gs311Format:
        """The reply layout these settings describe."""
        return codec.Gs311Format(
            byte_order=self.byte_order,
            deg_per_count=self.deg_per_count,
            roll_sign=self.roll_sign,
            pitch_sign=self.pitch_sign,
            count_bits=self.count_bits,
        )


@dataclass
class TiltHealth(LinkHealth):
    """How the link is doing; :attr:`TiltSensorLink.health` returns a snapshot.

    ``connected``, ``port_errors``, ``reconnects`` and ``last_error`` come from
    :class:`~omnid.devices.link.LinkHealth`.
    """

    valid: bool = False
    last_reading_age_s: float | None = None
    requests: int = 0
    replies_ok: int = 0
    timeouts: int = 0
    consecutive_timeouts: int = 0
    checksum_errors: int = 0
    range_errors: int = 0
    stale_episodes: int = 0
    unsent_bytes_discarded: int = 0  # requests the line had not carried when the next went out


class HidTransport(Transport):
    """Bytes through a USB-HID serial bridge (hidapi): report = length byte + data bytes."""

    def __init__(self, target: str, report_size: int) -> None:
        super().__init__(f"hid://{target}")
        try:
            import hid
        except ImportError as exc:
            raise DeviceError("tilt: the hid backend needs the hidapi package") from exc
        try:
            vid_s, pid_s = target.split(":")
            vid, pid = int(vid_s, 16), int(pid_s, 16)
        except ValueError:
            raise ConfigError(f"tilt.port: expected hid://VID:PID in hex, got {target!r}") from None
        self._dev: Any = hid.device()
        try:
            self._dev.open(vid, pid)
            self._dev.set_nonblocking(1)
        except (OSError, ValueError) as exc:
            raise DeviceError(f"{self.name}: cannot open ({exc})") from exc
        self._size = report_size

    def _read_available(self, max_bytes: int) -> bytes:
        self._check_open()
        try:
            report = self._dev.read(self._size)
        except (OSError, ValueError) as exc:
            self.close()
            raise DeviceClosed(f"{self.name}: device disconnected ({exc})") from exc
        if not report:
            return b""
        n = min(report[0], len(report) - 1)
        return bytes(report[1 : 1 + n])[:max_bytes]

    async def _wait_readable(self) -> None:
        await asyncio.sleep(0.0005)  # hidapi has no fd to wait on: poll briefly

    async def _write_raw(self, data: bytes) -> None:
        report = bytes([0, len(data)]) + data  # report id 0, length, data
        try:
            self._dev.write(report + bytes(self._size + 1 - len(report)))
        except (OSError, ValueError) as exc:
            self.close()
            raise DeviceClosed(f"{self.name}: device disconnected ({exc})") from exc

    def _close_raw(self) -> None:
        with contextlib.suppress(Exception):
            self._dev.close()


def open_tilt_transport(settings: TiltSettings) -> Transport:
    """The byte link named by ``settings.port`` (device path, ``loop://`` or ``hid://``)."""
    if settings.port.startswith("hid://"):
        return HidTransport(settings.port.removeprefix("hid://"), settings.hid_report_size)
    return open_transport(settings.port, baudrate=settings.baudrate)


class TiltSensorLink(PolledLink[TiltHealth]):
    """Asyncio driver of the GS311 (see module docstring).

    ``on_reading`` (optional) is called in the event loop with each new reading.
    ``transport_factory`` (optional, for in-process emulators) replaces the URL opener.
    ``clock`` is the monotonic clock readings are stamped with. The task, poll grid, reconnect
    back-off and stop come from :class:`~omnid.devices.link.PolledLink`.
    """

    device_name = "tilt sensor"
    task_name = "tilt-sensor-link"
    _log = log

    def __init__(
        self,
        settings: TiltSettings | None = None,
        on_reading: Callable[[TiltReading], None] | None = None,
        transport_factory: Callable[[], Transport] | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_lost: Callable[[], None] | None = None,
    ) -> None:
        s = settings or TiltSettings()
        super().__init__(
            transport_factory or (lambda: open_tilt_transport(s)),
            TiltHealth(),
            period_s=s.poll_period_s,
            reconnect_initial_s=s.reconnect_initial_s,
            reconnect_max_s=s.reconnect_max_s,
        )
        self.settings = s
        self._on_reading = on_reading
        self._on_lost = on_lost
        self._clock = clock
        self._parser = codec.Gs311Parser(s.format)
        self._reading: TiltReading | None = None
        self._was_valid = False
        self._silent_limit = max(1, math.ceil(s.stale_after_s / s.poll_period_s))

    # -- public API (start/stop: PolledLink) ---------------------------------------------
    @property
    def latest(self) -> TiltReading | None:
        """The newest reading if younger than ``stale_after_s``, else ``None`` (rider input = stop)."""
        r = self._reading
        if r is None or self._clock() - r.timestamp_s > self.settings.stale_after_s:
            return None
        return r

    @property
    def _sensor_lost(self) -> bool:
        """The sensor stopped answering: as many requests in a row unanswered as fit in
        ``stale_after_s`` (a stalled event loop sends no requests, so it is not the sensor's
        fault), or no reading for three times that (the link task itself stuck)."""
        r = self._reading
        if r is None:
            return False
        if self._health.consecutive_timeouts >= self._silent_limit:
            return True
        return self._clock() - r.timestamp_s > 3 * self.settings.stale_after_s

    @property
    def last_reading(self) -> TiltReading | None:
        """The newest reading ever received, however old (diagnostics, neutral-pose calibration)."""
        return self._reading

    @property
    def health(self) -> TiltHealth:
        """A snapshot of connection state, reading age and error counters."""
        h = dataclasses.replace(self._health)
        h.checksum_errors = self._parser.checksum_errors
        h.range_errors = self._parser.range_errors
        if self._reading is not None:
            h.last_reading_age_s = self._clock() - self._reading.timestamp_s
        h.valid = self.latest is not None
        return h

    # -- internals -----------------------------------------------------------------------
    def _note_stale(self) -> None:
        if self._was_valid:
            self._was_valid = False
            self._health.stale_episodes += 1
            age = self._clock() - self._reading.timestamp_s if self._reading else math.inf
            self._throttle.warning(
                "stale",
                "tilt sensor reading stale (%.0f ms old > %.0f ms): head input lost (%s)",
                age * 1000,
                self.settings.stale_after_s * 1000,
                self._health.last_error or "no reply",
            )
            self._lost()

    def _lost(self) -> None:
        if self._on_lost is not None:
            try:
                self._on_lost()
            except Exception:
                log.exception("tilt sensor on_lost callback failed")

    def _port_lost(self, port_name: str, reason: str) -> None:
        self._throttle.warning("port", "tilt sensor port %s lost: %s", port_name, reason)
        self._lost()

    # -- PolledLink hooks ----------------------------------------------------------------
    def _on_open(self) -> None:
        self._parser.reset()

    def _check_stale(self) -> None:
        if self._sensor_lost:
            self._note_stale()  # logs the transition and tells on_lost, even if nobody asks

    def _on_stopped(self) -> None:
        self._reading = None
        self._was_valid = False

    async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
        """One half-duplex request → reply; bookkeeping of every outcome. True: it answered."""
        t = self._transport
        assert t is not None
        h = self._health
        t.reset_input()  # a late reply to an earlier request must not pass for this one
        # nor may requests the line did not carry (adapter held) go out as a burst behind this
        # one, each answered: only the request of now is queued (as the control-unit link does)
        h.unsent_bytes_discarded += t.reset_output()
        self._parser.reset()
        await t.write(codec.READ_ANGLES_REQUEST)
        h.requests += 1
        deadline = loop.time() + self.settings.request_timeout_s
        while True:
            # at the deadline still take what is already buffered (a reply in time while this
            # task waited for the event loop)
            remaining = deadline - loop.time()
            data = await t.read_some(64, max(remaining, 0.0))
            if not data:
                break
            frames = self._parser.feed(data)
            if frames:
                f = frames[-1]
                self._reading = TiltReading(f.roll_deg, f.pitch_deg, self._clock())
                h.replies_ok += 1
                h.consecutive_timeouts = 0
                if not self._was_valid:
                    self._was_valid = True
                    self._throttle.info(
                        "valid",
                        "tilt sensor readings valid (roll %.1f°, pitch %.1f°)",
                        f.roll_deg,
                        f.pitch_deg,
                    )
                if self._on_reading is not None:
                    try:
                        self._on_reading(self._reading)
                    except Exception:
                        if self._throttle.error("callback", "tilt sensor on_reading failed"):
                            log.debug("on_reading", exc_info=True)
                return True
        h.timeouts += 1
        h.consecutive_timeouts += 1
        h.last_error = f"no valid reply within {self.settings.request_timeout_s * 1000:.0f} ms"
        if self._reading is None and h.consecutive_timeouts == self._silent_limit:
            # never had a reading: the stale warning would never fire, so say it here
            self._throttle.warning(
                "silent",
                "tilt sensor on %s not answering (%d requests, %s): head input ignored",
                t.name,
                h.consecutive_timeouts,
                h.last_error,
            )
        return False
