"""Byte transports for device links, opened by URL the way pyserial's ``serial_for_url`` does.

A transport moves bytes and nothing else; framing lives in the codecs. Drivers (control unit,
tilt sensor) open one with :func:`open_transport` and use the asyncio methods::

    t = open_transport("/dev/ttyUSB0", baudrate=115200)          # a real port (or a pty path)
    t = open_transport("/dev/ttyUSB0", rs485=Rs485Options())    # kernel RS-485 mode, if supported
    t = open_transport("loop://")                                # loopback: writes come back (tests)
    a, b = pipe_pair()                                           # two in-process ends, crossed

    await t.write(b"...")
    data = await t.read_some(256, timeout_s=0.05)    # b"" when nothing arrived in time
    data = await t.read_exactly(8, timeout_s=0.05)   # DeviceTimeout when short
    t.reset_input()                                  # drop what came and was not read
    t.reset_output()                                 # drop what was written and not yet sent
    t.close()

Every OS-level failure (port missing, unplugged adapter, EIO from a pty whose master closed) is
raised as :class:`~omnid.errors.DeviceError` (``DeviceClosed`` once the link is gone) ``from`` the
original error, naming the port. Reads always have a timeout; the clock is the event loop's
(monotonic).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import os
import sys
import termios
from dataclasses import dataclass

from omnid.config import Settings, setting
from omnid.errors import DeviceClosed, DeviceError, DeviceTimeout

__all__ = [
    "FdTransport",
    "LoopTransport",
    "Rs485Options",
    "Transport",
    "open_transport",
    "pipe_pair",
]

_READ_CHUNK = 4096


@dataclass(frozen=True)
class Rs485Options(Settings):
    """Kernel RS-485 mode of a serial port (``serial.rs485.RS485Settings``), where the driver has it.

    ``rts_level_for_tx`` / ``rts_level_for_rx``: RTS (driver-enable) level while sending /
    receiving; ``delay_before_tx_s`` / ``delay_before_rx_s``: turn-around delays, s.
    """

    rts_level_for_tx: bool = True
    rts_level_for_rx: bool = False
    delay_before_tx_s: float = setting(0.0, 0.0, 0.1)
    delay_before_rx_s: float = setting(0.0, 0.0, 0.1)


class Transport:
    """A byte link. The base class owns the open/closed state and the timeouts.

    Backends implement ``_read_available`` (non-blocking, returns b"" when nothing is ready and
    raises ``DeviceClosed`` when the link is gone), ``_wait_readable`` and ``_write_raw``.
    """

    def __init__(self, name: str) -> None:
        self.name = name
        self._closed = False

    @property
    def is_open(self) -> bool:
        return not self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceClosed(f"{self.name}: not open")

    # -- backend hooks -------------------------------------------------------------------
    def _read_available(self, max_bytes: int) -> bytes:
        raise NotImplementedError

    async def _wait_readable(self) -> None:
        raise NotImplementedError

    async def _write_raw(self, data: bytes) -> None:
        raise NotImplementedError

    def _close_raw(self) -> None:
        """Release the backend's resources (idempotent)."""

    # -- public API ----------------------------------------------------------------------
    async def read_some(self, max_bytes: int, timeout_s: float) -> bytes:
        """Up to ``max_bytes`` bytes as soon as any are available; b"" if none within ``timeout_s``.

        Bytes that arrived in time but are noticed only when the timeout fires (the event loop
        ran the timeout before the readable callback) are returned, not lost to a "timeout".
        """
        self._check_open()
        data = self._read_available(max_bytes)
        if data:
            return data
        try:
            async with asyncio.timeout(timeout_s):
                while True:
                    await self._wait_readable()
                    self._check_open()
                    data = self._read_available(max_bytes)
                    if data:
                        return data
        except TimeoutError:
            return self._read_available(max_bytes) if not self._closed else b""

    async def read_exactly(self, n: int, timeout_s: float) -> bytes:
        """Exactly ``n`` bytes within ``timeout_s`` in total, else :class:`DeviceTimeout`."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        buf = bytearray()
        while len(buf) < n:
            remaining = deadline - loop.time()
            chunk = (
                await self.read_some(n - len(buf), max(remaining, 0.0)) if remaining > 0 else b""
            )
            if not chunk:
                raise DeviceTimeout(
                    f"{self.name}: {len(buf)} of {n} bytes within {timeout_s * 1000:.0f} ms"
                )
            buf += chunk
        return bytes(buf)

    async def write(self, data: bytes) -> None:
        """Send ``data`` completely (waits while the OS buffer is full)."""
        self._check_open()
        await self._write_raw(bytes(data))

    def reset_input(self) -> int:
        """Discard whatever has been received and not yet read; returns how many bytes that was.

        Never blocks (it reads only what is already there). A link that is gone is left for the
        next read or write to report.
        """
        dropped = 0
        with contextlib.suppress(DeviceError):
            while chunk := self._read_available(_READ_CHUNK):
                dropped += len(chunk)
        return dropped

    def reset_output(self) -> int:
        """Discard what was written and has not yet left (the OS's output queue).

        A control frame the line did not carry must not be sent after a newer one. Returns how
        many bytes were dropped where the OS can say (a serial port), else 0 (a pty; in-process
        ends, which have no queue). Never blocks; a link that is gone is left for the next read
        or write to report.
        """
        return 0

    def close(self) -> None:
        """Close the link; later reads and writes raise :class:`DeviceClosed`. Idempotent."""
        if not self._closed:
            self._closed = True
            self._close_raw()

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class FdTransport(Transport):
    """A transport over a non-blocking file descriptor (a serial port or pty opened by pyserial)."""

    def __init__(self, name: str, fd: int, owner: object | None = None) -> None:
        super().__init__(name)
        self._fd = fd
        self._owner = owner  # the pyserial object keeping the fd open (closed with us)
        os.set_blocking(fd, False)

    def _gone(self, exc: BaseException | None, what: str) -> DeviceClosed:
        self.close()
        return DeviceClosed(f"{self.name}: {what}")

    def _read_available(self, max_bytes: int) -> bytes:
        self._check_open()
        try:
            data = os.read(self._fd, max_bytes)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno in (errno.EIO, errno.ENXIO, errno.ENODEV, errno.EBADF):
                raise self._gone(exc, f"device disconnected ({exc.strerror})") from exc
            raise DeviceError(f"{self.name}: read failed ({exc.strerror})") from exc
        if not data:  # readable but EOF: the other end hung up
            raise self._gone(None, "device disconnected (end of file)")
        return data

    async def _wait_readable(self) -> None:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()

        def ready() -> None:
            if not fut.done():
                fut.set_result(None)

        loop.add_reader(self._fd, ready)
        try:
            await fut
        finally:
            with contextlib.suppress(ValueError, OSError):
                loop.remove_reader(self._fd)

    async def _wait_writable(self) -> None:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()

        def ready() -> None:
            if not fut.done():
                fut.set_result(None)

        loop.add_writer(self._fd, ready)
        try:
            async with asyncio.timeout(1.0):
                await fut
        except TimeoutError as exc:
            raise DeviceTimeout(f"{self.name}: write blocked for 1 s") from exc
        finally:
            with contextlib.suppress(ValueError, OSError):
                loop.remove_writer(self._fd)

    async def _write_raw(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            self._check_open()
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                await self._wait_writable()
                continue
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.ENXIO, errno.ENODEV, errno.EBADF):
                    raise self._gone(exc, f"device disconnected ({exc.strerror})") from exc
                raise DeviceError(f"{self.name}: write failed ({exc.strerror})") from exc
            view = view[n:]

    def reset_output(self) -> int:
        queued = 0
        with contextlib.suppress(OSError, termios.error):
            raw = fcntl.ioctl(self._fd, termios.TIOCOUTQ, b"\0\0\0\0")
            queued = int.from_bytes(raw, sys.byteorder, signed=True)
        with contextlib.suppress(OSError, termios.error):
            termios.tcflush(self._fd, termios.TCOFLUSH)
        return max(queued, 0)

    def _close_raw(self) -> None:
        close = getattr(self._owner, "close", None)
        if close is not None:
            with contextlib.suppress(Exception):
                close()
        else:
            with contextlib.suppress(OSError):
                os.close(self._fd)


class LoopTransport(Transport):
    """In-process byte pipe end. ``loop://`` is one end whose writes come back to itself."""

    def __init__(self, name: str = "loop://") -> None:
        super().__init__(name)
        self._rx = bytearray()
        self._event = asyncio.Event()
        self.peer: LoopTransport = self

    def _read_available(self, max_bytes: int) -> bytes:
        self._check_open()
        if not self._rx:
            if self.peer._closed and self.peer is not self:
                raise DeviceClosed(f"{self.name}: peer closed")
            return b""
        data = bytes(self._rx[:max_bytes])
        del self._rx[:max_bytes]
        return data

    async def _wait_readable(self) -> None:
        self._event.clear()
        if self._rx or (self.peer._closed and self.peer is not self):
            return
        await self._event.wait()

    def feed(self, data: bytes) -> None:
        """Deliver bytes to this end (what the peer's ``write`` does)."""
        if not self._closed:
            self._rx += data
            self._event.set()

    async def _write_raw(self, data: bytes) -> None:
        if self.peer._closed and self.peer is not self:
            raise DeviceClosed(f"{self.name}: peer closed")
        self.peer.feed(data)

    def _close_raw(self) -> None:
        self.peer._event.set()  # wake a reader waiting on the other end


def pipe_pair(name: str = "pipe") -> tuple[LoopTransport, LoopTransport]:
    """Two crossed in-process ends: what one writes the other reads (emulator in the same loop)."""
    a, b = LoopTransport(f"{name}:a"), LoopTransport(f"{name}:b")
    a.peer, b.peer = b, a
    return a, b


def open_transport(
    url: str,
    *,
    baudrate: int = 115200,
    rs485: Rs485Options | None = None,
) -> Transport:
    """Open the byte link named by ``url``: ``loop://`` or a device path (``/dev/ttyUSB0``, a pty).

    Raises :class:`DeviceError` naming the port (``from`` the OS error) when it cannot be opened,
    or when ``rs485`` is asked for and the port's driver has no kernel RS-485 mode.
    """
    if url == "loop://" or url.startswith("loop://"):
        return LoopTransport(url)
    path = url.removeprefix("serial://") if url.startswith("serial://") else url
    if "://" in path:
        raise DeviceError(f"{url}: unknown transport scheme (use a device path or loop://)")
    import serial  # pyserial; imported here so that tools without serial still import us

    try:
        port = serial.Serial(path, baudrate=baudrate, timeout=0, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DeviceError(f"{path}: cannot open ({exc})") from exc
    if rs485 is not None:
        import serial.rs485

        try:
            port.rs485_mode = serial.rs485.RS485Settings(
                rts_level_for_tx=rs485.rts_level_for_tx,
                rts_level_for_rx=rs485.rts_level_for_rx,
                delay_before_tx=rs485.delay_before_tx_s or None,
                delay_before_rx=rs485.delay_before_rx_s or None,
            )
        except (serial.SerialException, OSError, ValueError, NotImplementedError) as exc:
            port.close()
            raise DeviceError(f"{path}: kernel RS-485 mode not available ({exc})") from exc
    _make_reads_block_for_one_byte(port.fileno())
    return FdTransport(path, port.fileno(), owner=port)


def _make_reads_block_for_one_byte(fd: int) -> None:
    """VMIN=1, VTIME=0: with O_NONBLOCK an empty read is then EAGAIN, and 0 bytes means hang-up.

    pyserial's ``timeout=0`` sets VMIN=0, where "no data yet" and "unplugged" both read as b"".
    """
    import termios

    with contextlib.suppress(termios.error, OSError):
        attrs = termios.tcgetattr(fd)
        attrs[6][termios.VMIN] = 1
        attrs[6][termios.VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
