"""Perception in a separate process, so that it never holds the control loop's GIL.

``perceive`` (subtract, detect, match, triangulate, classify) is ~20 ms of numpy/OpenCV per
capture. Run in a thread of the daemon it competes with the 50 Hz control loop for the GIL
(measured: control-loop lateness p99 12.5 ms with a CPU-burning thread, docs/benchmarks/daemon.md);
in its own process it does not.

:class:`PerceptionWorker` owns one child process (``spawn`` start method: no fork of a
multi-threaded asyncio process) and a pipe to it:

- request: ``struct.pack("<dII", t_s, rows, cols)`` + mask1, base1, mask2, base2 (gray8, row
  major) — 1.2 MB for 640x480, written from a helper thread so the event loop never blocks on
  the pipe;
- reply: ``b"C"`` + the pickled :class:`~omnid.core.types.PointCloud`, or ``b"E"`` + a one-line
  error.

Faults never reach the control loop as a stall: an exception inside ``perceive`` comes back as
:class:`PerceptionFailed`; a child that dies (EOF) or does not answer within ``timeout_s`` is
killed and a fresh one is started for the next request; the caller sees
:class:`PerceptionFailed` at once and the daemon's perception simply grows stale (no forward
motion). The child runs at lower priority (``nice``) and exits when the daemon's end of the pipe
closes.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from omnid.core.types import PointCloud, StereoCapture
from omnid.errors import OmnidError
from omnid.logs import LogThrottle

log = logging.getLogger(__name__)
_THROTTLE = LogThrottle(log, interval_s=5.0)  # a worker crashing every cycle: one line per 5 s

REQUEST_HEADER = struct.Struct("<dII")
PerceiveFn = Callable[..., PointCloud]


class PerceptionFailed(OmnidError, RuntimeError):
    """One perception request gave no cloud (exception, crash or timeout); the worker recovers."""


def _pipeline_perceive(capture: StereoCapture, calib: Any, method: str, settings: Any) -> Any:
    from omnid.core.pipeline import perceive

    return perceive(capture, calib, method, settings)  # type: ignore[arg-type]


def encode_request(capture: StereoCapture) -> bytes:
    """The request bytes for ``capture`` (four gray8 images of one shape)."""
    imgs = [
        np.ascontiguousarray(a, dtype=np.uint8)
        for a in (capture.mask1, capture.base1, capture.mask2, capture.base2)
    ]
    if imgs[0].ndim != 2:
        raise ValueError(
            f"perception request: images must be gray8 (rows, cols), got {imgs[0].shape}"
        )
    rows, cols = imgs[0].shape
    head = REQUEST_HEADER.pack(float(capture.timestamp_s), rows, cols)
    return b"".join([head, *(a.tobytes() for a in imgs)])


def decode_request(data: bytes) -> StereoCapture:
    """Inverse of :func:`encode_request` (zero-copy views of ``data``)."""
    t_s, rows, cols = REQUEST_HEADER.unpack_from(data)
    n = rows * cols
    if len(data) != REQUEST_HEADER.size + 4 * n:
        raise ValueError(f"perception request: {len(data)} bytes for 4 images of {rows}x{cols}")
    a = np.frombuffer(data, np.uint8, 4 * n, REQUEST_HEADER.size).reshape(4, rows, cols)
    return StereoCapture(a[0], a[1], a[2], a[3], timestamp_s=t_s)


def _worker_main(
    conn: multiprocessing.connection.Connection,
    fn: PerceiveFn,
    calib: Any,
    method: str,
    settings: Any,
    nice: int,
) -> None:
    """The child: answer requests until the parent's end of the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon handles Ctrl-C and stops us
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    if nice:
        with contextlib.suppress(OSError):
            os.nice(nice)
    conn.send_bytes(b"R")
    while True:
        try:
            data = conn.recv_bytes()
        except (EOFError, OSError):
            return
        try:
            cloud = fn(decode_request(data), calib, method, settings)
            out = b"C" + pickle.dumps(cloud, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:
            text = f"{type(exc).__name__}: {exc}".replace("\n", " ")[:500]
            out = b"E" + text.encode("utf-8", "replace")
        try:
            conn.send_bytes(out)
        except (BrokenPipeError, OSError):
            return


class PerceptionWorker:
    """One perception child process with timeout, crash detection and restart.

    Parameters
    ----------
    calib, method, settings:
        Passed to ``fn(capture, calib, method, settings)`` in the child (pickled once, at start).
    timeout_s:
        A request not answered within this (after the child is up) kills the child.
    start_timeout_s:
        How long a fresh child may take to import numpy/OpenCV and report ready.
    nice:
        Niceness added in the child.
    fn:
        The perceive function (module level, picklable by reference); default
        :func:`omnid.core.pipeline.perceive`.
    """

    def __init__(
        self,
        calib: Any,
        method: str = "best",
        settings: Any = None,
        *,
        timeout_s: float = 1.0,
        start_timeout_s: float = 20.0,
        nice: int = 10,
        fn: PerceiveFn = _pipeline_perceive,
    ) -> None:
        self.calib, self.method, self.settings = calib, method, settings
        self.timeout_s, self.start_timeout_s, self.nice, self.fn = (
            timeout_s,
            start_timeout_s,
            nice,
            fn,
        )
        self._ctx = multiprocessing.get_context("spawn")
        self._proc: Any = None
        self._conn: multiprocessing.connection.Connection | None = None
        self._ready = False
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="omnid-perc-io")
        self.requests = 0
        self.failures = 0
        self.restarts = 0
        self.last_error = ""

    # -- process management ---------------------------------------------------------------
    def _spawn(self) -> None:
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(
            target=_worker_main,
            args=(child, self.fn, self.calib, self.method, self.settings, self.nice),
            name="omnid-perception",
            daemon=True,
        )
        proc.start()
        child.close()
        self._proc, self._conn, self._ready = proc, parent, False
        _THROTTLE.info("started", "perception worker started (pid %d)", proc.pid)

    def _kill(self, why: str) -> None:
        proc, conn = self._proc, self._conn
        self._proc, self._conn, self._ready = None, None, False
        if conn is not None:
            conn.close()
        if proc is not None:
            if proc.is_alive():
                proc.kill()
            proc.join(1.0)
            _THROTTLE.warning("stopped", "perception worker (pid %s) stopped: %s", proc.pid, why)

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    def _encode_and_request(self, capture: StereoCapture) -> bytes:
        return self._blocking_request(encode_request(capture))  # 1.2 MB copied off the loop

    def _blocking_request(self, payload: bytes) -> bytes:
        """In the I/O thread: (re)start the child if needed, send, wait with the timeout."""
        if self._proc is None or not self._proc.is_alive():
            if self._proc is not None:
                self.restarts += 1
                self._kill(f"exited with code {self._proc.exitcode}")
            self._spawn()
        conn = self._conn
        assert conn is not None
        if not self._ready:
            if not conn.poll(self.start_timeout_s):
                self._kill(f"not ready within {self.start_timeout_s:g} s")
                raise PerceptionFailed("perception worker did not start in time")
            try:
                if conn.recv_bytes() != b"R":
                    raise EOFError("unexpected greeting")
            except (EOFError, OSError) as exc:
                self._kill(f"failed at start ({exc})")
                raise PerceptionFailed("perception worker failed at start") from None
            self._ready = True
        try:
            conn.send_bytes(payload)
            if not conn.poll(self.timeout_s):
                self.restarts += 1
                self._kill(f"no answer within {self.timeout_s:g} s (hung)")
                raise PerceptionFailed(f"perceive took longer than {self.timeout_s:g} s")
            return conn.recv_bytes()
        except (EOFError, OSError) as exc:
            self.restarts += 1
            code = None if self._proc is None else self._proc.exitcode
            self._kill(f"crashed (exit code {code}, {type(exc).__name__})")
            raise PerceptionFailed(f"perception worker crashed (exit code {code})") from None

    # -- public API -----------------------------------------------------------------------
    async def start(self) -> None:
        """Start the child and wait until it is ready (imports done), bounded."""
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._pool, self._start_blocking)

    def _start_blocking(self) -> None:
        if self._proc is None:
            self._spawn()
        conn = self._conn
        assert conn is not None
        if not self._ready and conn.poll(self.start_timeout_s):
            with contextlib.suppress(EOFError, OSError):
                self._ready = conn.recv_bytes() == b"R"

    async def perceive(self, capture: StereoCapture) -> PointCloud:
        """The cloud of ``capture``; :class:`PerceptionFailed` on any failure (never hangs
        longer than ``timeout_s`` once the worker is up)."""
        self.requests += 1
        loop = asyncio.get_running_loop()
        try:
            reply = await loop.run_in_executor(self._pool, self._encode_and_request, capture)
        except PerceptionFailed as exc:
            self.failures += 1
            self.last_error = str(exc)
            raise
        if reply[:1] == b"C":
            cloud = pickle.loads(reply[1:])
            if not isinstance(cloud, PointCloud):
                self.failures += 1
                raise PerceptionFailed(f"worker sent a {type(cloud).__name__}, not a PointCloud")
            return cloud
        self.failures += 1
        self.last_error = reply[1:].decode("utf-8", "replace")
        raise PerceptionFailed(f"perceive failed: {self.last_error}")

    async def close(self) -> None:
        """Stop the child (its pipe closes; killed if it does not exit at once)."""
        loop = asyncio.get_running_loop()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(loop.run_in_executor(self._pool, self._close_blocking), 3.0)
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _close_blocking(self) -> None:
        proc, conn = self._proc, self._conn
        self._proc, self._conn = None, None
        if conn is not None:
            conn.close()
        if proc is not None:
            proc.join(0.5)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
