"""Perception in a separate process, so that it never holds the control loop's GIL.

``perceive`` (subtract, detect, match, triangulate, classify) is ~20 ms of numpy/OpenCV per
capture. Run in a thread of the daemon it competes with the 50 Hz control loop for the GIL
(measured: control-loop lateness p99 12.5 ms with a CPU-burning thread, docs/benchmarks/daemon.md);
in its own process it does not.

:class:`PerceptionWorker` owns one child process (``spawn`` start method: no fork of a
multi-threaded asyncio process) and a pipe to it:

- request (a capture job, :func:`encode_job`): ``struct.pack("<dIII", t_s, rows, cols, n)`` +
  n × ``struct.pack("<?ddd", known, dx_mm, dy_mm, dtheta_rad)`` (the chair's motion from each
  mask to the base) + base1, base2, then n mask pairs (gray8, row major) — 1.2 MB for 640x480
  with one mask, written from a helper thread so the event loop never blocks on the pipe. The
  child moves each mask to the base's pose (:func:`job_capture`) and perceives;
- reply: ``b"C"`` + the pickled :class:`~omnid.core.types.PointCloud`, or ``b"E"`` + a one-line
  error.

Faults never reach the control loop as a stall: an exception inside ``perceive`` comes back as
:class:`PerceptionFailed`; a child that dies (EOF) or does not answer within ``timeout_s`` is
killed and a fresh one is started for the next request; the caller sees
:class:`PerceptionFailed` at once and the daemon's perception simply grows stale (no forward
motion). The child runs at lower priority (``nice``), with numpy's OpenBLAS on one thread
(:func:`limit_blas_threads`), and exits when the daemon's end of the pipe closes.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import ctypes
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import re
import signal
import struct
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnid.core.motion_compensation import (
    Motion,
    compensated_mask,
    disk_mask,
    floor_motion_affine,
)
from omnid.core.types import PointCloud, StereoCapture
from omnid.errors import OmnidError
from omnid.logs import LogThrottle

log = logging.getLogger(__name__)
_THROTTLE = LogThrottle(log, interval_s=5.0)  # a worker crashing every cycle: one line per 5 s

REQUEST_HEADER = struct.Struct("<dIII")
MOTION_RECORD = struct.Struct("<?ddd")
PerceiveFn = Callable[..., PointCloud]
Image = NDArray[np.uint8]
Pair = tuple[Image, Image]


class PerceptionFailed(OmnidError, RuntimeError):
    """One perception request gave no cloud (exception, crash or timeout); the worker recovers."""


def _pipeline_perceive(capture: StereoCapture, calib: Any, method: str, settings: Any) -> Any:
    from omnid.core.pipeline import perceive

    return perceive(capture, calib, method, settings)  # type: ignore[arg-type]


def job_capture(
    base: Pair,
    masks: Sequence[Pair],
    motions: Sequence[Motion | None],
    rig: Any = None,
    rig_x_offset_mm: float = 0.0,
    t_s: float = 0.0,
) -> StereoCapture:
    """The :class:`StereoCapture` perception subtracts for a job: each camera's masks moved to
    the base frame's pose by the chair's motion (the floor's image motion,
    :func:`~omnid.core.motion_compensation.floor_motion_affine`, for the calibrated ``rig``;
    a motion of None, or no rig, leaves that mask as taken) and combined
    (:func:`~omnid.core.motion_compensation.compensated_mask`)."""
    if not masks:
        raise ValueError("capture job without a mask frame")
    out = []
    for i, cam in enumerate((None, None) if rig is None else (rig.cam1, rig.cam2)):
        affines = [
            None
            if m is None or cam is None or m == (0.0, 0.0, 0.0)
            else floor_motion_affine(cam, m, rig_x_offset_mm, rig.floor_depth_mm)
            for m in motions
        ]
        disk = None if cam is None or all(a is None for a in affines) else _disk(cam)
        out.append(compensated_mask([pair[i] for pair in masks], affines, disk))
    return StereoCapture(out[0], base[0], out[1], base[1], timestamp_s=t_s)


_DISKS: dict[Any, NDArray[np.uint8]] = {}


def _disk(cam: Any) -> NDArray[np.uint8]:
    """The mirror disk mask of ``cam`` (computed once per camera)."""
    disk = _DISKS.get(cam)
    if disk is None:
        if len(_DISKS) > 8:
            _DISKS.clear()
        disk = _DISKS[cam] = disk_mask(cam)
    return disk


def encode_job(
    t_s: float, base: Pair, masks: Sequence[Pair], motions: Sequence[Motion | None]
) -> bytes:
    """The request bytes for a job (gray8 images of one shape; a motion per mask)."""
    if len(masks) != len(motions):
        raise ValueError("perception request: one motion per mask pair")
    imgs = [np.ascontiguousarray(a, dtype=np.uint8) for pair in (base, *masks) for a in pair]
    if imgs[0].ndim != 2:
        raise ValueError(
            f"perception request: images must be gray8 (rows, cols), got {imgs[0].shape}"
        )
    rows, cols = imgs[0].shape
    if any(a.shape != (rows, cols) for a in imgs):
        raise ValueError("perception request: all images must have one shape")
    head = REQUEST_HEADER.pack(float(t_s), rows, cols, len(masks))
    recs = [
        MOTION_RECORD.pack(False, 0.0, 0.0, 0.0) if m is None else MOTION_RECORD.pack(True, *m)
        for m in motions
    ]
    return b"".join([head, *recs, *(a.tobytes() for a in imgs)])


def decode_job(data: bytes) -> tuple[float, Pair, list[Pair], list[Motion | None]]:
    """Inverse of :func:`encode_job` (zero-copy views of ``data``)."""
    t_s, rows, cols, n = REQUEST_HEADER.unpack_from(data)
    off = REQUEST_HEADER.size
    motions: list[Motion | None] = []
    for _ in range(n):
        known, dx, dy, dth = MOTION_RECORD.unpack_from(data, off)
        off += MOTION_RECORD.size
        motions.append((dx, dy, dth) if known else None)
    px = rows * cols
    if n < 1 or len(data) != off + 2 * (n + 1) * px:
        raise ValueError(f"perception request: {len(data)} bytes for {n} masks of {rows}x{cols}")
    a = np.frombuffer(data, np.uint8, 2 * (n + 1) * px, off).reshape(2 * (n + 1), rows, cols)
    masks = [(a[2 + 2 * i], a[3 + 2 * i]) for i in range(n)]
    return t_s, (a[0], a[1]), masks, motions


def encode_request(capture: StereoCapture) -> bytes:
    """The request bytes for ``capture`` (four gray8 images of one shape; no motion)."""
    return encode_job(
        capture.timestamp_s,
        (capture.base1, capture.base2),
        [(capture.mask1, capture.mask2)],
        [None],
    )


def decode_request(data: bytes) -> StereoCapture:
    """The capture a request holds, masks as taken (no motion compensation)."""
    t_s, base, masks, _ = decode_job(data)
    return job_capture(base, masks, [None] * len(masks), t_s=t_s)


# OpenBLAS as numpy's wheels bundle it (symbols prefixed and suffixed) or as a system library.
_OPENBLAS_PREFIXES = ("scipy_openblas", "openblas")
_OPENBLAS_SUFFIXES = ("64_", "")


def _openblas_call(what: str, *args: int) -> list[int]:
    """Call ``openblas_<what>`` in every OpenBLAS this process has loaded (Linux: read from
    /proc/self/maps); the return values, empty where there is none."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return []
    names = [f"{p}_{what}{s}" for p in _OPENBLAS_PREFIXES for s in _OPENBLAS_SUFFIXES]
    out = []
    for lib in sorted(set(re.findall(r"(/\S*openblas\S*\.so\S*)", maps))):
        try:
            dll = ctypes.CDLL(lib)
        except OSError:
            continue
        fn = next((f for f in (getattr(dll, n, None) for n in names) if f is not None), None)
        if fn is not None:
            out.append(int(fn(*args) or 0))
    return out


def blas_threads() -> list[int]:
    """The thread count of each OpenBLAS loaded in this process."""
    return _openblas_call("get_num_threads")


def limit_blas_threads(n: int) -> None:
    """Let numpy's OpenBLAS use at most ``n`` threads from now on.

    OpenBLAS starts one thread per core and its idle threads spin: in the perception child a
    matrix product of a few hundred rows then ran on threads competing with the control loop
    for the chair computer's cores (measured ~20–25 ms instead of ~0.3 ms at load 6).
    Perception's products are small; one thread is faster and leaves the cores to the loop.
    """
    _openblas_call("set_num_threads", n)


def _worker_main(
    conn: multiprocessing.connection.Connection,
    fn: PerceiveFn,
    calib: Any,
    method: str,
    settings: Any,
    nice: int,
    rig_x_offset_mm: float = 0.0,
) -> None:
    """The child: answer requests until the parent's end of the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon handles Ctrl-C and stops us
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    limit_blas_threads(1)
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
            t_s, base, masks, motions = decode_job(data)
            rig = getattr(calib, "rig", None)
            capture = job_capture(base, masks, motions, rig, rig_x_offset_mm, t_s)
            cloud = fn(capture, calib, method, settings)
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
    rig_x_offset_mm:
        Where the rig sits ahead of the axle midpoint (for moving masks by the chair's motion).
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
        rig_x_offset_mm: float = 0.0,
    ) -> None:
        self.rig_x_offset_mm = rig_x_offset_mm
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
            args=(
                child,
                self.fn,
                self.calib,
                self.method,
                self.settings,
                self.nice,
                self.rig_x_offset_mm,
            ),
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

    def _encode_and_request(self, request: StereoCapture | tuple[Any, ...]) -> bytes:
        if isinstance(request, StereoCapture):
            payload = encode_request(request)
        else:
            payload = encode_job(*request)
        return self._blocking_request(payload)  # 1.2 MB copied off the loop

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
        # the whole exchange has the request's deadline: a child that stops reading (frozen,
        # thrashing) leaves a 1.2 MB send blocked on a full pipe, and one that freezes half-way
        # through its answer leaves recv_bytes waiting for the rest. A timer kills the child
        # just after the deadline (a slow perceive is the poll's to handle), which breaks the
        # pipe and ends the blocked call
        deadline = time.monotonic() + self.timeout_s
        proc = self._proc
        done, fired = threading.Event(), threading.Event()

        def stuck() -> None:
            if not done.is_set() and proc.is_alive():
                fired.set()
                proc.kill()

        timer = threading.Timer(self.timeout_s + 0.1, stuck)
        timer.daemon = True
        try:
            timer.start()
            try:
                conn.send_bytes(payload)
                if not conn.poll(max(deadline - time.monotonic(), 0.0)):
                    self.restarts += 1
                    self._kill(f"no answer within {self.timeout_s:g} s (hung)")
                    raise PerceptionFailed(f"perceive took longer than {self.timeout_s:g} s")
                return conn.recv_bytes()
            finally:
                done.set()
                timer.cancel()
        except (EOFError, OSError) as exc:
            self.restarts += 1
            if fired.is_set():
                self._kill(f"request not through within {self.timeout_s:g} s (hung)")
                raise PerceptionFailed(
                    f"perception worker hung: request not through within {self.timeout_s:g} s"
                ) from None
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
        return await self._perceive(capture)

    async def perceive_job(
        self,
        t_s: float,
        base: Pair,
        masks: Sequence[Pair],
        motions: Sequence[Motion | None],
    ) -> PointCloud:
        """The cloud of a capture job (base pair, mask pairs, the chair's motion from each mask
        to the base): the child moves the masks to the base's pose and perceives."""
        return await self._perceive((t_s, base, list(masks), list(motions)))

    async def _perceive(self, request: StereoCapture | tuple[Any, ...]) -> PointCloud:
        self.requests += 1
        loop = asyncio.get_running_loop()
        try:
            reply = await loop.run_in_executor(self._pool, self._encode_and_request, request)
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
