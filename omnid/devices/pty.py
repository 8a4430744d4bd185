"""Serve an emulated device on a real pseudo-terminal, with unplug and replug.

The driver under test opens the pty's slave side exactly as it would open ``/dev/ttyUSB0``; the
emulator sits on the master side. :class:`PtyPort` runs a reader thread on the master and hands
every chunk of received bytes to ``on_data(data)``; the emulator answers with :meth:`PtyPort.write`.

``link_path`` (optional) is a stable path — a symlink re-pointed at each new pty — so the driver's
configured port survives an unplug/replug the way a udev ``/dev/serial/by-id/...`` link does:

* :meth:`unplug` closes the master (and our slave handle): the driver's reads fail with EIO/EOF
  and re-opening the old path fails, as when a USB adapter is pulled out;
* :meth:`replug` creates a fresh pty and re-points ``link_path`` at it.

Writes to the master never block: when nobody drains the slave, bytes are dropped like on a
serial line with no listener.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import threading
import tty
from collections.abc import Callable
from pathlib import Path

from omnid.errors import DeviceClosed, DeviceError

__all__ = ["PtyPort"]

log = logging.getLogger(__name__)


class PtyPort:
    """The master side of a pty serving one emulated device.

    Parameters
    ----------
    on_data:
        Called from the reader thread with each chunk of bytes the driver wrote.
    link_path:
        Optional stable path (a symlink to the current slave) for unplug/replug tests.
    name:
        For log messages and thread names.
    """

    def __init__(
        self,
        on_data: Callable[[bytes], None],
        link_path: str | os.PathLike[str] | None = None,
        name: str = "pty",
    ) -> None:
        self._on_data = on_data
        self._link = Path(link_path) if link_path is not None else None
        self._name = name
        self._lock = threading.Lock()
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_path: str | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_dropped = 0

    # -- lifecycle -----------------------------------------------------------------------
    def open(self) -> str:
        """Create the pty and start serving; returns the path the driver should open."""
        with self._lock:
            if self._master is not None:
                raise DeviceError(f"{self._name}: already open")
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line discipline: a plain 8-bit serial line
            tty.setraw(master)
            os.set_blocking(master, False)
            self._master, self._slave = master, slave
            self._slave_path = os.ttyname(slave)
            if self._link is not None:
                tmp = self._link.with_name(self._link.name + ".tmp")
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
                os.symlink(self._slave_path, tmp)
                os.replace(tmp, self._link)  # atomic re-point
            self._stop = threading.Event()
            self._thread = threading.Thread(
                target=self._reader,
                args=(master, self._stop),
                name=f"{self._name}-reader",
                daemon=True,
            )
            self._thread.start()
        log.debug("%s: serving on %s", self._name, self.path)
        return self.path

    @property
    def path(self) -> str:
        """The path a driver opens: ``link_path`` if given, else the current slave device."""
        if self._link is not None:
            return str(self._link)
        if self._slave_path is None:
            raise DeviceClosed(f"{self._name}: not open")
        return self._slave_path

    @property
    def slave_path(self) -> str | None:
        """The current ``/dev/pts/N`` (None while unplugged)."""
        return self._slave_path

    @property
    def is_open(self) -> bool:
        return self._master is not None

    def unplug(self) -> None:
        """Close the master: the driver sees EIO/EOF and cannot re-open the old device."""
        with self._lock:
            thread = self._thread
            self._thread = None
            self._stop.set()
        if thread is not None and thread is not threading.current_thread():
            # The reader wakes every 50 ms to check ``stop``; the long bound is for a loaded
            # machine. Closing the fd under a live reader could hand it a reused fd number.
            thread.join(timeout=10.0)
            if thread.is_alive():
                log.warning("%s: reader thread did not stop within 10 s", self._name)
        with self._lock:  # writers hold the lock, so no fd is closed under them
            for fd in (self._master, self._slave):
                if fd is not None:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self._master = self._slave = None
            self._slave_path = None
        if self._link is not None:
            with contextlib.suppress(FileNotFoundError):
                self._link.unlink()  # like udev removing /dev/serial/by-id/... on unplug
        log.debug("%s: unplugged", self._name)

    def replug(self) -> str:
        """A fresh pty behind the same ``link_path`` (unplugs first if still open)."""
        if self._master is not None:
            self.unplug()
        return self.open()

    def close(self) -> None:
        """Stop serving and release the pty. Idempotent."""
        self.unplug()

    def __enter__(self) -> PtyPort:
        if self._master is None:
            self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- data ----------------------------------------------------------------------------
    def write(self, data: bytes) -> int:
        """Send bytes to the driver; returns how many were accepted (0 while unplugged)."""
        with self._lock:
            master = self._master
            if master is None:
                return 0
            try:
                n = os.write(master, data)
            except BlockingIOError:
                n = 0
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF):
                    return 0
                raise DeviceError(f"{self._name}: write failed ({exc.strerror})") from exc
        self.bytes_out += n
        self.bytes_dropped += len(data) - n
        return n

    def _reader(self, master: int, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
            except (OSError, ValueError):
                return
            if not ready or stop.is_set():
                continue
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                continue
            except OSError as exc:
                # EIO on the master: no process holds the slave open right now (we hold it, so
                # this only happens while closing). Keep polling unless asked to stop.
                if exc.errno == errno.EIO:
                    stop.wait(0.01)
                    continue
                return
            if not data:
                stop.wait(0.01)
                continue
            self.bytes_in += len(data)
            try:
                self._on_data(data)
            except Exception:  # an emulator bug must not kill the port silently
                log.exception("%s: on_data handler failed", self._name)
