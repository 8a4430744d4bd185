"""Stereo camera sources, chosen by URL (docs/interfaces.md "Cameras").

Every source is a :class:`StereoFrameSource`: ``await read_pair() -> (img1, img2, t_s)`` and
``await flush()``. The base class owns the open/closed state and the deadline (a source that
delivers nothing within ``timeout_s`` raises :class:`~omnid.errors.DeviceTimeout`); backends
implement only ``_read_pair_blocking`` or ``_read_pair_async``.

=================================  ==========================================================
URL                                backend
=================================  ==========================================================
``v4l2:///dev/video0,/dev/video2``  two V4L2 devices through ``cv2.VideoCapture`` (grabbed in a
                                   worker thread; resolution, exposure, buffer size settings)
``replay:///dir``                  image pairs ``<stem>_1.<ext>``/``<stem>_2.<ext>`` (sorted by
                                   stem), or two videos ``cam1.*``/``cam2.*``; ``?loop=1`` loops
``sim+unix:///path.sock``          the simulator frame server (wire format in interfaces.md)
``sim:``                           an in-process callable (:func:`open_camera` ``frame_fn=``)
=================================  ==========================================================

Timestamps: ``t_s`` is the capture time on the monotonic clock. For V4L2 it is the drivers'
buffer timestamps (``CAP_PROP_POS_MSEC``: ``CLOCK_MONOTONIC`` in current drivers, taken when
the frame was captured) averaged over the two cameras, where both are plausible (inside the
read's own window, or up to a second before it: the driver's queue); otherwise — a driver with
another clock, or none — ``time.monotonic()`` when both frames had been grabbed, which is late
by the transfer (:func:`pair_time`). For ``sim+unix`` the simulator's own ``t_s``, which is the
clock the simulated daemon runs on.

Frozen frames: a live sensor's noise makes every frame differ from the one before it, so a
device source (V4L2, and the simulator's frame server, which stands in for one) that delivers a
frame byte for byte equal to its previous one is frozen — a stuck driver re-delivering its last
buffer, or nothing in view (the lens covered, the scene fully dark or saturated) — and the read
raises :class:`~omnid.errors.DeviceError`: the daemon treats it as a camera failure (reopens the
source; the speed cap applies meanwhile). Replayed files and in-process sources may repeat a
still image and are not checked.

``flush()`` makes sure the next pair was captured after the call — the thesis takes the mask
(laser off) and base (laser on) captures in sequence (4.1.4), so a base frame must not be a
frame the driver had queued before the laser was switched on. For V4L2 the driver's queue
(``buffer_size`` frames) is drained by grabbing and discarding that many frames per camera; the
simulator and the in-process source render on request, so they hold no stale frames.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np
from numpy.typing import NDArray

from omnid.config import Settings, setting
from omnid.errors import ConfigError, DeviceClosed, DeviceError, DeviceTimeout, ProtocolError

log = logging.getLogger(__name__)

Image = NDArray[np.uint8]
FramePair = tuple[Image, Image, float]

SIM_HEADER = struct.Struct("<4sdII")
SIM_MAGIC = b"OMNF"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


@dataclass(frozen=True)
class CameraSettings(Settings):
    """Camera source settings; ``url`` picks the backend (see the module docstring)."""

    url: str = "v4l2:///dev/omnid-camera1,/dev/omnid-camera2"  # udev names (etc/udev)
    timeout_s: float = setting(1.0, 0.01, 10.0)
    width_px: int = setting(640, 16, 8192)
    height_px: int = setting(480, 16, 8192)
    fps: float = setting(30.0, 1.0, 240.0)
    # device units (cv2.CAP_PROP_EXPOSURE); None = auto
    exposure: float | None = setting(None, -100000.0, 100000.0)
    buffer_size: int = setting(1, 1, 32)  # frames the driver may queue (cv2.CAP_PROP_BUFFERSIZE)
    grayscale: bool = True
    # the longest exposure of a frame, s (the capture cycle keeps laser switches out of it)
    exposure_s: float = setting(0.008, 0.0001, 0.5)
    # the middle of a frame's exposure is this long before its timestamp, s; subtracted from
    # every timestamp. A V4L2 driver's buffer stamp marks the start of the exposure (uvcvideo;
    # then −exposure/2) or the end of the frame (then the readout), depending on the driver;
    # without a usable stamp the pair is stamped when the read returned (readout + transfer)
    frame_latency_s: float = setting(0.0, -0.5, 1.0)


def _gray(img: Any, grayscale: bool) -> Image:
    arr = np.asarray(img)
    if grayscale and arr.ndim == 3:
        import cv2

        arr = cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(arr, dtype=np.uint8)


class StereoFrameSource:
    """Base class: open/closed state, deadlines; backends implement the raw read."""

    name = "camera"
    #: a frame equal to the same camera's previous one is a fault (module docstring)
    detects_frozen = False

    def __init__(self, settings: CameraSettings | None = None) -> None:
        self.settings = settings or CameraSettings()
        self._closed = False
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None
        self._pending: asyncio.Future[Any] | None = None
        self._previous: tuple[Image, Image] | None = None
        self.frames_read = 0
        self.timeouts = 0
        self.frozen = 0  # reads refused as frozen

    # --- backends override one of these ---------------------------------------------------
    def _read_pair_blocking(self) -> FramePair:  # pragma: no cover - abstract
        raise NotImplementedError

    async def _read_pair_async(self) -> FramePair:
        """Default: run the blocking read in this source's own worker thread."""
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix=f"omnid-{self.name}"
            )
        loop = asyncio.get_running_loop()
        if self._pending is None or self._pending.done():
            self._pending = loop.run_in_executor(self._executor, self._read_pair_blocking)
        # a grab that overran its deadline keeps running; the next call waits on it rather than
        # queueing another blocking call behind it
        pending = self._pending
        result = await asyncio.shield(pending)
        self._pending = None
        return result

    def _flush_blocking(self) -> None:
        """Discard frames captured before now (default: nothing is queued)."""

    def _close(self) -> None:
        """Release the backend's resources."""

    # --- public API -----------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    async def read_pair(self) -> FramePair:
        """Next stereo pair ``(img1, img2, t_s)``; raises DeviceTimeout after ``timeout_s``."""
        if self._closed:
            raise DeviceClosed(f"{self.name}: camera source is closed")
        try:
            img1, img2, t_s = await asyncio.wait_for(
                self._read_pair_async(), self.settings.timeout_s
            )
        except TimeoutError as exc:
            self.timeouts += 1
            raise DeviceTimeout(
                f"{self.name}: no frames within {self.settings.timeout_s:g} s"
            ) from exc
        if self.detects_frozen:
            self._refuse_frozen(img1, img2)
        self.frames_read += 1
        return img1, img2, t_s

    def _refuse_frozen(self, img1: Image, img2: Image) -> None:
        """DeviceError if either camera's frame equals its previous one, byte for byte."""
        previous, self._previous = self._previous, (img1.copy(), img2.copy())
        if previous is None:
            return
        for i, (before, now) in enumerate(zip(previous, (img1, img2), strict=True), 1):
            if before.shape == now.shape and np.array_equal(before, now):
                self.frozen += 1
                raise DeviceError(
                    f"{self.name}: camera {i} delivered the same frame twice, byte for byte: "
                    "frozen (a stuck driver) or nothing in view (lens covered, dark or saturated)"
                )

    def reopens(self, before: StereoFrameSource | None) -> None:
        """This source opens again the device ``before`` read (closed after a failure): its
        first frame is compared with the last one ``before`` delivered or refused, so that a
        device still stuck on its buffer stays frozen across the reopen."""
        if before is not None and self.detects_frozen and self._previous is None:
            self._previous = before._previous

    async def flush(self) -> None:
        """Make the next :meth:`read_pair` return frames captured after this call."""
        if self._closed:
            raise DeviceClosed(f"{self.name}: camera source is closed")
        if type(self)._flush_blocking is StereoFrameSource._flush_blocking:
            return
        if self._pending is not None and not self._pending.done():
            # an overrunning grab still holds the device; wait for it (bounded)
            try:
                await asyncio.wait_for(asyncio.shield(self._pending), self.settings.timeout_s)
            except TimeoutError as exc:
                self.timeouts += 1
                raise DeviceTimeout(
                    f"{self.name}: flush waited {self.settings.timeout_s:g} s"
                ) from exc
            self._pending = None
        loop = asyncio.get_running_loop()
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1)
        fut = loop.run_in_executor(self._executor, self._flush_blocking)
        try:
            await asyncio.wait_for(asyncio.shield(fut), self.settings.timeout_s * 2)
        except TimeoutError as exc:
            self.timeouts += 1
            self._pending = fut
            raise DeviceTimeout(
                f"{self.name}: flush took over {self.settings.timeout_s * 2:g} s"
            ) from exc

    async def close(self) -> None:
        """Release devices and the worker thread; further reads raise DeviceClosed."""
        if self._closed:
            return
        self._closed = True
        executor, self._executor = self._executor, None
        if executor is None:
            self._close()
            return
        # released in the worker thread, after a grab that overran its deadline and still runs:
        # never concurrently with it (cv2.VideoCapture is not thread-safe) and never on the
        # event loop (a stalled USB device can block the release); waited for a bounded time
        fut = asyncio.get_running_loop().run_in_executor(executor, self._close)
        executor.shutdown(wait=False)
        try:
            await asyncio.wait_for(asyncio.shield(fut), self.settings.timeout_s)
        except TimeoutError:
            log.warning(
                "%s: a grab still runs after %g s; the camera is released when it ends",
                self.name,
                self.settings.timeout_s,
            )

    async def __aenter__(self) -> StereoFrameSource:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


#: How long before a read a driver's buffer may have been captured (its queue of frames), s.
MAX_BUFFER_AGE_S = 1.0
#: Two cameras' stamps of one pair farther apart than this (s) are two exposure times, not one:
#: the cameras are not synchronised, and the stream capture's laser labels (one time per pair,
#: ± half an exposure and a 2 ms guard) may be off by the difference.
PAIR_SPREAD_WARN_S = 0.004


def pair_time(
    stamps_ms: list[float], t_before_s: float, t_grabbed_s: float, monotonic: bool = False
) -> float:
    """Capture time (monotonic s) of a frame pair from its buffers' timestamps ``stamps_ms``
    (``CAP_PROP_POS_MSEC``), read between ``t_before_s`` and ``t_grabbed_s``: their mean when
    every one lies between ``MAX_BUFFER_AGE_S`` before the read and its end (a monotonic
    stamp), else ``t_grabbed_s`` (0 before the first frame, a wall-clock or device clock).
    With ``monotonic`` (the drivers' stamps have been monotonic) an older stamp is an old
    buffer — one the driver held while nobody read — and is kept: stamped at the grab, a
    stale frame would look fresh."""
    t = [float(ms) / 1000.0 for ms in stamps_ms]
    lo = -math.inf if monotonic else t_before_s - MAX_BUFFER_AGE_S
    if t and all(math.isfinite(x) and lo <= x <= t_grabbed_s for x in t):
        return sum(t) / len(t)
    return t_grabbed_s


class VideoCaptureSource(StereoFrameSource):
    """Two ``cv2.VideoCapture`` streams, grabbed then retrieved together in a worker thread.

    ``api`` is ``cv2.CAP_V4L2`` for V4L2 devices; with ``cv2.CAP_ANY`` the same code reads two
    video files (used by the tests and by ``replay:`` with videos).
    """

    name = "v4l2"

    def __init__(
        self,
        specs: tuple[str, str],
        settings: CameraSettings | None = None,
        api: int | None = None,
        loop: bool = False,
        device: bool = True,
    ) -> None:
        super().__init__(settings)
        import cv2

        self._cv2 = cv2
        self.specs = specs
        self._loop = loop
        self._device = device
        self.detects_frozen = device  # a video file may hold a still
        self._stamped_by_drivers: bool | None = None  # which clock stamps the pairs (logged)
        self._spread_pairs = 0  # pairs whose two stamps lay apart (unsynchronised cameras)
        self._api = cv2.CAP_V4L2 if api is None else api
        self._caps = [self._open(spec) for spec in specs]

    def _open(self, spec: str) -> Any:
        cv2 = self._cv2
        target: str | int = int(spec) if spec.isdigit() else spec
        cap = cv2.VideoCapture(target, self._api)
        if not cap.isOpened():
            cap.release()
            raise DeviceError(f"{self.name}: cannot open camera {spec!r}")
        if self._device:
            s = self.settings
            wanted = [
                (cv2.CAP_PROP_FRAME_WIDTH, s.width_px, "width_px"),
                (cv2.CAP_PROP_FRAME_HEIGHT, s.height_px, "height_px"),
                (cv2.CAP_PROP_FPS, s.fps, "fps"),
                (cv2.CAP_PROP_BUFFERSIZE, s.buffer_size, "buffer_size"),
            ]
            if s.exposure is not None:
                wanted += [
                    (cv2.CAP_PROP_AUTO_EXPOSURE, 1, "exposure (manual mode)"),
                    (cv2.CAP_PROP_EXPOSURE, s.exposure, "exposure"),
                ]
            for prop, value, key in wanted:
                if not cap.set(prop, float(value)):
                    log.warning("%s: camera %s refused %s=%s", self.name, spec, key, value)
        return cap

    def _grab(self, i: int) -> None:
        cap = self._caps[i]
        if cap.grab():
            return
        if self._loop and not self._device:
            cap.set(self._cv2.CAP_PROP_POS_FRAMES, 0)
            if cap.grab():
                return
        raise DeviceError(f"{self.name}: camera {self.specs[i]!r} delivered no frame")

    def _read_pair_blocking(self) -> FramePair:
        # grab both first, then decode, so the two exposures are as close in time as possible
        t_before = time.monotonic()
        self._grab(0)
        self._grab(1)
        t_s = time.monotonic()
        if self._device:  # a file's "timestamp" is its position in the video
            pos = self._cv2.CAP_PROP_POS_MSEC
            stamps = [cap.get(pos) for cap in self._caps]
            t_grabbed = t_s
            t_s = pair_time(stamps, t_before, t_s, bool(self._stamped_by_drivers))
            self._note_stamps(stamps, t_s != t_grabbed)
        imgs = []
        for i, cap in enumerate(self._caps):
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise DeviceError(f"{self.name}: camera {self.specs[i]!r} frame not decodable")
            imgs.append(_gray(img, self.settings.grayscale))
        return imgs[0], imgs[1], t_s

    def _note_stamps(self, stamps_ms: list[float], from_drivers: bool) -> None:
        """Say once which clock stamps the pairs, and when the two cameras' stamps of a pair
        lie apart (not synchronised: every 300th such pair, ~10 s at 30 frames/s)."""
        if from_drivers != self._stamped_by_drivers:
            self._stamped_by_drivers = from_drivers
            log.info(
                "%s: frame pairs stamped %s",
                self.name,
                "by the drivers' buffer timestamps"
                if from_drivers
                else "when read (the drivers' timestamps are not on the monotonic clock)",
            )
        if from_drivers:
            spread_s = (max(stamps_ms) - min(stamps_ms)) / 1000.0
            if spread_s > PAIR_SPREAD_WARN_S:
                if self._spread_pairs % 300 == 0:
                    log.warning(
                        "%s: the cameras' frames of a pair were captured %.1f ms apart: they are "
                        "not synchronised (laser labels may be off by as much)",
                        self.name,
                        1000.0 * spread_s,
                    )
                self._spread_pairs += 1

    def _flush_blocking(self) -> None:
        if not self._device:
            return  # files hold no frames captured "before now"
        for _ in range(self.settings.buffer_size):
            for i in range(2):
                self._caps[i].grab()

    def _close(self) -> None:
        for cap in self._caps:
            cap.release()


class ReplaySource(StereoFrameSource):
    """Image pairs from a directory: ``<stem>_1.<ext>`` and ``<stem>_2.<ext>``, sorted by stem."""

    name = "replay"

    def __init__(
        self,
        pairs: list[tuple[Path, Path]],
        settings: CameraSettings | None = None,
        loop: bool = False,
    ) -> None:
        super().__init__(settings)
        if not pairs:
            raise ConfigError("camera.url: replay directory holds no image pairs")
        self.pairs = pairs
        self._loop = loop
        self._index = 0

    @staticmethod
    def find_pairs(directory: Path) -> list[tuple[Path, Path]]:
        """Pairs ``(stem_1.ext, stem_2.ext)`` in ``directory``, sorted by stem."""
        ones = {}
        for p in sorted(directory.iterdir()):
            if p.suffix.lower() in IMAGE_SUFFIXES and p.stem.endswith("_1"):
                ones[p.stem[:-2]] = p
        pairs = []
        for stem, p1 in sorted(ones.items()):
            p2 = p1.with_name(f"{stem}_2{p1.suffix}")
            if p2.exists():
                pairs.append((p1, p2))
        return pairs

    def _read_pair_blocking(self) -> FramePair:
        import cv2

        if self._index >= len(self.pairs):
            if not self._loop:
                raise DeviceClosed(f"{self.name}: end of replay ({len(self.pairs)} pairs)")
            self._index = 0
        p1, p2 = self.pairs[self._index]
        self._index += 1
        flag = cv2.IMREAD_GRAYSCALE if self.settings.grayscale else cv2.IMREAD_COLOR
        imgs = []
        for p in (p1, p2):
            img = cv2.imread(str(p), flag)
            if img is None:
                raise DeviceError(f"{self.name}: cannot read image {p}")
            imgs.append(np.ascontiguousarray(img, dtype=np.uint8))
        return imgs[0], imgs[1], time.monotonic()


class SimUnixSource(StereoFrameSource):
    """Frames from the simulator's frame server over a Unix socket (interfaces.md wire format)."""

    name = "sim+unix"
    detects_frozen = True  # the simulated device renders sensor noise into every frame

    def __init__(self, path: str, settings: CameraSettings | None = None) -> None:
        super().__init__(settings)
        self.path = path
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def _connect(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        if self._reader is None or self._writer is None:
            try:
                self._reader, self._writer = await asyncio.open_unix_connection(self.path)
            except OSError as exc:
                raise DeviceError(f"{self.name}: cannot connect to {self.path}: {exc}") from exc
        return self._reader, self._writer

    def _drop(self) -> None:
        if self._writer is not None:
            self._writer.close()
        self._reader = self._writer = None

    async def _read_pair_async(self) -> FramePair:
        reader, writer = await self._connect()
        try:
            writer.write(b"G")
            await writer.drain()
            header = await reader.readexactly(SIM_HEADER.size)
            magic, t_s, rows, cols = SIM_HEADER.unpack(header)
            if magic != SIM_MAGIC or rows * cols > 64 * 1024 * 1024:
                raise ProtocolError(f"{self.name}: bad frame header from {self.path}")
            body = await reader.readexactly(2 * rows * cols)
        except (OSError, asyncio.IncompleteReadError) as exc:
            self._drop()
            raise DeviceError(f"{self.name}: frame server {self.path} failed: {exc}") from exc
        except BaseException:
            self._drop()  # a timeout mid-frame leaves the stream unaligned: reconnect next time
            raise
        frames = np.frombuffer(body, dtype=np.uint8).reshape(2, rows, cols)
        return frames[0].copy(), frames[1].copy(), float(t_s)

    def _close(self) -> None:
        self._drop()


class CallableSource(StereoFrameSource):
    """In-process source: ``frame_fn() -> (img1, img2[, t_s])`` (the simulator, or a test)."""

    name = "sim"

    def __init__(
        self, frame_fn: Callable[[], tuple[Any, ...]], settings: CameraSettings | None = None
    ) -> None:
        super().__init__(settings)
        self.frame_fn = frame_fn

    async def _read_pair_async(self) -> FramePair:
        out = self.frame_fn()
        if asyncio.iscoroutine(out):
            out = await out
        img1, img2 = out[0], out[1]
        t_s = float(out[2]) if len(out) > 2 else time.monotonic()
        return _gray(img1, self.settings.grayscale), _gray(img2, self.settings.grayscale), t_s


def open_camera(
    settings: CameraSettings | str,
    frame_fn: Callable[[], tuple[Any, ...]] | None = None,
) -> StereoFrameSource:
    """Open the stereo source named by ``settings.url`` (or a bare URL string)."""
    if isinstance(settings, str):
        settings = CameraSettings(url=settings)
    parts = urlsplit(settings.url)
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    loop = query.get("loop", "0").lower() in ("1", "true", "yes")
    scheme = parts.scheme
    if scheme == "v4l2":
        specs = [s for s in parts.path.split(",") if s]
        if len(specs) != 2:
            raise ConfigError(f"camera.url: v4l2 needs two devices, got {settings.url!r}")
        return VideoCaptureSource((specs[0], specs[1]), settings)
    if scheme == "replay":
        directory = Path(parts.path)
        if not directory.is_dir():
            raise ConfigError(f"camera.url: replay directory {directory} does not exist")
        vids = [sorted(directory.glob(f"cam{i}.*")) for i in (1, 2)]
        if vids[0] and vids[1]:
            import cv2

            return VideoCaptureSource(
                (str(vids[0][0]), str(vids[1][0])),
                settings,
                api=cv2.CAP_ANY,
                loop=loop,
                device=False,
            )
        return ReplaySource(ReplaySource.find_pairs(directory), settings, loop=loop)
    if scheme == "sim+unix":
        return SimUnixSource(parts.path, settings)
    if scheme == "sim":
        if frame_fn is None:
            raise ConfigError("camera.url: 'sim:' needs an in-process frame function")
        return CallableSource(frame_fn, settings)
    raise ConfigError(
        f"camera.url: unknown scheme {scheme!r} in {settings.url!r} "
        "(known: v4l2, replay, sim+unix, sim)"
    )
