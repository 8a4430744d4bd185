"""The GS311 head-tilt sensor link (thesis 4.2.2, 4.2.2.1; SPEC §5).

:class:`TiltSensorLink` polls the sensor half-duplex: every ``poll_period_s`` (10 ms — the
sensor gives a reading every 0.01 s, Table 4.1) it discards stale input, sends the read-angles
command ``0x50 0x50`` and waits at most ``request_timeout_s`` for the ``0xA0`` reply
(:mod:`omnid.devices.gs311_codec`, whose docstring documents the assumed data layout).

Fail safe: :attr:`TiltSensorLink.latest` is the newest reading only while it is younger than
``stale_after_s``; otherwise it is ``None`` (logged once per episode) and the daemon treats the
rider's head input as stop. When the adapter disappears (USB unplugged: EIO/EOF) the port is
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

from omnid.config import require
from omnid.devices import gs311_codec as codec
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
class TiltSettings:
    """Settings of the tilt-sensor link (section ``tilt`` of the daemon's YAML).

    The last five keys describe the reply's data layout (see :mod:`omnid.devices.gs311_codec`),
    so a real unit can be matched without code changes.
    """

    port: str = "/dev/ttyUSB1"
    baudrate: int = 115200
    poll_period_s: float = 0.01
    request_timeout_s: float = 0.008
    stale_after_s: float = 0.1
    reconnect_initial_s: float = 0.05
    reconnect_max_s: float = 1.0
    hid_report_size: int = 64
    byte_order: Literal["big", "little"] = "big"
    deg_per_count: float = 90.0 / 4096.0
    roll_sign: int = 1
    pitch_sign: int = 1
    count_bits: int = 12

    def __post_init__(self) -> None:
        require(bool(self.port), "port", "must name a device path, loop:// or hid://VID:PID")
        require(1200 <= self.baudrate <= 3_000_000, "baudrate", "must be 1200 … 3000000")
        require(0.002 <= self.poll_period_s <= 0.5, "poll_period_s", "must be 0.002–0.5 s")
        require(
            0.001 <= self.request_timeout_s <= self.poll_period_s,
            "request_timeout_s",
            "must be ≥ 0.001 s and at most poll_period_s (half duplex: one request at a time)",
        )
        require(
            self.stale_after_s >= 2 * self.poll_period_s,
            "stale_after_s",
            "must be at least two poll periods",
        )
        require(self.reconnect_initial_s > 0, "reconnect_initial_s", "must be > 0")
        require(
            self.reconnect_max_s >= self.reconnect_initial_s,
            "reconnect_max_s",
            "must be ≥ reconnect_initial_s",
        )
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
class TiltHealth:
    """How the link is doing; :attr:`TiltSensorLink.health` returns a snapshot."""

    connected: bool = False
    valid: bool = False
    last_reading_age_s: float | None = None
    requests: int = 0
    replies_ok: int = 0
    timeouts: int = 0
    consecutive_timeouts: int = 0
    checksum_errors: int = 0
    range_errors: int = 0
    port_errors: int = 0
    reconnects: int = 0
    stale_episodes: int = 0
    last_error: str = ""


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


class TiltSensorLink:
    """Asyncio driver of the GS311 (see module docstring).

    ``on_reading`` (optional) is called in the event loop with each new reading.
    ``transport_factory`` (optional, for in-process emulators) replaces the URL opener.
    ``clock`` is the monotonic clock readings are stamped with.
    """

    def __init__(
        self,
        settings: TiltSettings | None = None,
        on_reading: Callable[[TiltReading], None] | None = None,
        transport_factory: Callable[[], Transport] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings or TiltSettings()
        self._on_reading = on_reading
        s = self.settings
        self._factory = transport_factory or (lambda: open_tilt_transport(s))
        self._clock = clock
        self._parser = codec.Gs311Parser(s.format)
        self._transport: Transport | None = None
        self._task: asyncio.Task[None] | None = None
        self._stopping = False
        self._wake = asyncio.Event()
        self._health = TiltHealth()
        self._reading: TiltReading | None = None
        self._was_valid = False
        self._silent_limit = max(1, math.ceil(s.stale_after_s / s.poll_period_s))

    # -- public API ----------------------------------------------------------------------
    async def start(self) -> None:
        """Start polling (returns at once; the port is opened in the background)."""
        if self._task is not None:
            return
        self._stopping = False
        self._task = asyncio.create_task(self._run(), name="tilt-sensor-link")

    async def stop(self) -> None:
        """Stop polling and close the port."""
        self._stopping = True
        if self._task is not None:
            self._wake.set()
            try:
                async with asyncio.timeout(1.0):
                    await self._task
            except TimeoutError:
                self._task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._task
            except Exception:
                log.exception("tilt sensor link task had failed")
            self._task = None
        self._drop_transport(None)
        self._reading = None
        self._was_valid = False

    @property
    def latest(self) -> TiltReading | None:
        """The newest reading if younger than ``stale_after_s``, else ``None`` (rider input = stop)."""
        r = self._reading
        if r is None:
            return None
        if self._clock() - r.timestamp_s > self.settings.stale_after_s:
            self._note_stale()
            return None
        return r

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
            log.warning(
                "tilt sensor reading stale (%.0f ms old > %.0f ms): head input ignored (%s)",
                age * 1000,
                self.settings.stale_after_s * 1000,
                self._health.last_error or "no reply",
            )

    def _connect(self) -> bool:
        try:
            self._transport = self._factory()
        except DeviceError as exc:
            self._health.last_error = str(exc)
            return False
        self._parser.reset()
        self._health.connected = True
        log.info("tilt sensor port %s open", self._transport.name)
        return True

    def _drop_transport(self, reason: str | None) -> None:
        if self._transport is not None:
            self._transport.close()
            if reason is not None:
                self._health.port_errors += 1
                self._health.last_error = reason
                log.warning("tilt sensor port %s lost: %s", self._transport.name, reason)
        self._transport = None
        self._health.connected = False

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        s = self.settings
        backoff = s.reconnect_initial_s
        ever_connected = False
        next_t = loop.time()
        while not self._stopping:
            if self._transport is None:
                if self._connect():
                    if ever_connected:
                        self._health.reconnects += 1
                    ever_connected = True
                    next_t = loop.time()
                else:
                    self.latest  # noqa: B018 - logs the stale transition while disconnected
                    await self._sleep(backoff)
                    backoff = min(backoff * 2, s.reconnect_max_s)
                    continue
            try:
                await self._exchange(loop)
            except DeviceError as exc:
                self._drop_transport(str(exc))
                # back off before reopening: a port that opens but fails at once must not
                # spin the event loop
                await self._sleep(backoff)
                backoff = min(backoff * 2, s.reconnect_max_s)
                continue
            except Exception as exc:  # a bug must not leave a stale reading looking valid
                log.exception("tilt sensor link: unexpected error")
                self._drop_transport(f"internal error: {exc!r}")
                # back off before reopening: a port that opens but fails at once must not
                # spin the event loop
                await self._sleep(backoff)
                backoff = min(backoff * 2, s.reconnect_max_s)
                continue
            self.latest  # noqa: B018 - logs the stale transition even if nobody asks
            if self._health.consecutive_timeouts == 0:
                backoff = s.reconnect_initial_s  # the device answered: a fresh back-off
            next_t += s.poll_period_s
            delay = next_t - loop.time()
            if delay < -s.poll_period_s:  # overran (loop blocked): restart the grid
                next_t = loop.time()
                delay = 0.0
            await self._sleep(max(delay, 0.0))

    async def _sleep(self, delay_s: float) -> None:
        self._wake.clear()
        if self._stopping:  # stop() may have set the wake-up before we cleared it
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(delay_s):
                await self._wake.wait()

    async def _exchange(self, loop: asyncio.AbstractEventLoop) -> None:
        """One half-duplex request → reply; bookkeeping of every outcome."""
        t = self._transport
        assert t is not None
        h = self._health
        t.reset_input()  # a late reply to an earlier request must not pass for this one
        self._parser.reset()
        await t.write(codec.READ_ANGLES_REQUEST)
        h.requests += 1
        deadline = loop.time() + self.settings.request_timeout_s
        while True:
            remaining = deadline - loop.time()
            data = await t.read_some(64, remaining) if remaining > 0 else b""
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
                    log.info(
                        "tilt sensor readings valid (roll %.1f°, pitch %.1f°)",
                        f.roll_deg,
                        f.pitch_deg,
                    )
                if self._on_reading is not None:
                    try:
                        self._on_reading(self._reading)
                    except Exception:
                        log.exception("tilt sensor on_reading callback failed")
                return
        h.timeouts += 1
        h.consecutive_timeouts += 1
        h.last_error = f"no valid reply within {self.settings.request_timeout_s * 1000:.0f} ms"
        if self._reading is None and h.consecutive_timeouts == self._silent_limit:
            # never had a reading: the stale warning would never fire, so say it here
            log.warning(
                "tilt sensor on %s not answering (%d requests, %s): head input ignored",
                t.name,
                h.consecutive_timeouts,
                h.last_error,
            )
