"""A Unix-socket server that hands simulated camera frames to ``omnid run`` in another process.

Wire format (docs/interfaces.md, ``sim+unix://``): the client sends one byte ``b"G"``; the server
replies with the header ``struct.pack("<4sdII", b"OMNF", t_s, rows, cols)``, then ``rows*cols``
bytes of camera 1 (gray8, row-major), then ``rows*cols`` bytes of camera 2. A connection may ask
any number of times. Any other request byte closes that connection (and is logged); the server
keeps serving others.

The server runs in its own thread, so it serves a simulator whose loop is synchronous. Frames
come from a ``provider`` callable returning ``(t_s, img1, img2)``; it is called once per request,
so a simulator can render the frame for the pose and laser state at that moment.

The server is a free-running camera (``frame_period_s``, default 30 frames/s): frame k is
exposed around t_k = t_start + k·period on the monotonic clock, a request is answered with the
next frame not yet sent, ``readout_s`` after the middle of its exposure (the request waits for
it), stamped t_k — so a client sees the frame rate, the capture time and the delay of a real
camera. A provider that takes an argument is called with t_k (to render the laser as it was
lit during that exposure). ``drop_rate`` loses that share of frames (the next one is sent).
``frame_period_s=None``: every request is answered at once with the provider's own stamp.

Codec and transport are apart: :func:`encode_frame` / :func:`decode_header` are plain bytes
functions; :class:`FrameServer` and :func:`fetch_frame` move them.
"""

from __future__ import annotations

import contextlib
import inspect
import logging
import math
import os
import random
import socket
import struct
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from omnid.errors import DeviceClosed, DeviceError, DeviceTimeout, ProtocolError

log = logging.getLogger(__name__)

MAGIC = b"OMNF"
REQUEST = b"G"
HEADER = struct.Struct("<4sdII")
#: Largest frame a client accepts (rows, cols), so a corrupt header cannot ask for gigabytes.
MAX_SIDE_PX = 4096

Frame = tuple[float, NDArray[np.uint8], NDArray[np.uint8]]
FrameProvider = Callable[..., Frame]


def encode_frame(t_s: float, img1: NDArray[np.uint8], img2: NDArray[np.uint8]) -> bytes:
    """Header + camera 1 + camera 2 as bytes; both images gray8 (rows, cols) of one shape."""
    a, b = np.asarray(img1), np.asarray(img2)
    if a.dtype != np.uint8 or b.dtype != np.uint8 or a.ndim != 2 or a.shape != b.shape:
        raise ValueError(
            f"frame images must be two gray8 arrays of one shape, got {a.dtype}{a.shape} "
            f"and {b.dtype}{b.shape}"
        )
    rows, cols = a.shape
    return HEADER.pack(MAGIC, float(t_s), rows, cols) + a.tobytes() + b.tobytes()


def decode_header(data: bytes) -> tuple[float, int, int]:
    """``(t_s, rows, cols)`` from the first ``HEADER.size`` bytes; ProtocolError if malformed."""
    if len(data) < HEADER.size:
        raise ProtocolError(f"frame header: need {HEADER.size} bytes, got {len(data)}")
    magic, t_s, rows, cols = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"frame header: bad magic {magic!r} (expected {MAGIC!r})")
    if not (0 < rows <= MAX_SIDE_PX and 0 < cols <= MAX_SIDE_PX):
        raise ProtocolError(f"frame header: implausible size {rows}x{cols}")
    return t_s, rows, cols


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            raise DeviceClosed(f"frame server closed the connection after {len(buf)}/{n} bytes")
        buf += chunk
    return bytes(buf)


def fetch_frame(path: str | os.PathLike[str], timeout_s: float = 2.0) -> Frame:
    """Ask the server at ``path`` for one frame (a fresh connection); for tools and tests.

    Raises DeviceError (cannot connect), DeviceTimeout (no full answer within ``timeout_s``),
    ProtocolError (malformed header).
    """
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(os.fspath(path))
        except OSError as exc:
            raise DeviceError(f"{path}: cannot connect to the frame server ({exc})") from exc
        return request_frame(sock)


def request_frame(sock: socket.socket) -> Frame:
    """One request/response on a connected socket (its timeout applies to each read)."""
    try:
        sock.sendall(REQUEST)
        t_s, rows, cols = decode_header(_recv_exact(sock, HEADER.size))
        body = _recv_exact(sock, 2 * rows * cols)
    except TimeoutError as exc:
        raise DeviceTimeout("frame server did not answer in time") from exc
    img1 = np.frombuffer(body, np.uint8, rows * cols).reshape(rows, cols).copy()
    img2 = np.frombuffer(body, np.uint8, rows * cols, rows * cols).reshape(rows, cols).copy()
    return t_s, img1, img2


class FrameServer:
    """Serves frames from ``provider`` on the Unix socket ``path`` in a background thread.

    Use as a context manager, or ``start()`` / ``stop()``. ``stop`` closes the listening socket
    and every connection and removes the socket file. ``requests_served`` counts frames sent.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        provider: FrameProvider,
        client_timeout_s: float = 10.0,
        frame_period_s: float | None = 1.0 / 30.0,
        readout_s: float = 0.006,
        drop_rate: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.path = Path(path)
        self.provider = provider
        self.client_timeout_s = client_timeout_s
        self.frame_period_s = frame_period_s
        self.readout_s = readout_s
        self.drop_rate = drop_rate
        self._rng = random.Random(seed)
        self._t_start = time.monotonic()
        self._next_frame = 0
        self._clock_lock = threading.Lock()
        try:
            self._provider_takes_time = len(inspect.signature(provider).parameters) >= 1
        except (TypeError, ValueError):
            self._provider_takes_time = False
        self.frames_dropped = 0
        self.requests_served = 0
        self.errors = 0
        self._listener: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._conns: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._stopping = threading.Event()

    def start(self) -> FrameServer:
        if self.path.exists() or self.path.is_symlink():
            if not self.path.is_socket():
                raise DeviceError(
                    f"{self.path}: exists and is not a socket; refusing to replace it"
                )
            self.path.unlink()  # a stale socket from a previous run
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            listener.bind(os.fspath(self.path))
            listener.listen(4)
        except OSError as exc:
            listener.close()
            raise DeviceError(f"{self.path}: cannot listen ({exc})") from exc
        listener.settimeout(0.1)  # so the accept loop notices stop() promptly
        self._listener = listener
        self._stopping.clear()
        t = threading.Thread(target=self._accept_loop, name="frame-server", daemon=True)
        t.start()
        self._threads.append(t)
        log.info("frame server listening on %s", self.path)
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stopping.set()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        with self._lock:
            for c in list(self._conns):
                with contextlib.suppress(OSError):
                    c.shutdown(socket.SHUT_RDWR)
                c.close()
            self._conns.clear()
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        self._threads = [t for t in self._threads if t.is_alive()]
        with contextlib.suppress(OSError):
            if self.path.is_socket():
                self.path.unlink()

    def __enter__(self) -> FrameServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _accept_loop(self) -> None:
        while not self._stopping.is_set():
            listener = self._listener
            if listener is None:
                return
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # closed by stop()
            conn.settimeout(self.client_timeout_s)
            with self._lock:
                self._conns.add(conn)
            t = threading.Thread(target=self._serve, args=(conn,), name="frame-conn", daemon=True)
            t.start()
            self._threads = [x for x in self._threads if x.is_alive()] + [t]

    def _next(self) -> Frame:
        """The next frame: wait for the frame clock (if any), render, stamp."""
        period = self.frame_period_s
        if period is None:
            return self.provider()
        with self._clock_lock:  # one camera: connections share its frames
            now = time.monotonic()
            k = max(self._next_frame, math.ceil((now - self._t_start - self.readout_s) / period))
            while self.drop_rate > 0 and self._rng.random() < self.drop_rate:
                self.frames_dropped += 1
                k += 1
            self._next_frame = k + 1
            t_k = self._t_start + k * period
            wait = t_k + self.readout_s - now
            if wait > 0:
                time.sleep(wait)
            if self._provider_takes_time:
                _, img1, img2 = self.provider(t_k)
            else:
                _, img1, img2 = self.provider()
        return t_k, img1, img2

    def _serve(self, conn: socket.socket) -> None:
        try:
            while not self._stopping.is_set():
                try:
                    req = conn.recv(1)
                except TimeoutError:
                    continue  # an idle client is fine; keep the connection
                if not req:
                    return
                if req != REQUEST:
                    self.errors += 1
                    log.warning("frame server: unknown request byte %r; closing connection", req)
                    return
                try:
                    payload = encode_frame(*self._next())
                except Exception:
                    self.errors += 1
                    log.exception("frame server: the frame provider failed; closing connection")
                    return
                conn.sendall(payload)
                self.requests_served += 1
        except OSError as exc:
            if not self._stopping.is_set():
                log.info("frame server: client connection ended (%s)", exc)
        finally:
            with self._lock:
                self._conns.discard(conn)
            conn.close()
