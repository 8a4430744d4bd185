"""The daemon's camera reader (``Daemon._frame_reader``) against cameras that misbehave: a
frame server on a Unix socket (the ``sim+unix://`` wire format) that sends malformed frames,
and replay videos behind FIFOs that stand in for devices slow to open."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time

import numpy as np

from omnid.daemon.capture import CaptureCycle, CaptureFailure, CaptureSettings
from omnid.daemon.config import ConfigHolder
from omnid.daemon.run import Daemon
from omnid.sim.frame_server import encode_frame


class GarbledFrameServer:
    """Answers ``b"G"`` with a frame pair; the first ``bad`` answers have a corrupt header."""

    def __init__(self, path: str, bad: int = 1) -> None:
        self.bad = bad
        self.sent = 0
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(path)
        self._sock.listen(4)
        self._sock.settimeout(0.1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        rng = np.random.default_rng(0)  # sensor noise: a camera's frames are never identical
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            conn.settimeout(0.1)
            with conn:
                while not self._stop.is_set():
                    try:
                        if conn.recv(1) != b"G":
                            break
                    except TimeoutError:
                        continue
                    img = rng.integers(0, 256, (8, 8), dtype=np.uint8)
                    frame = encode_frame(time.monotonic(), img, img)
                    if self.sent < self.bad:
                        frame = b"JUNK" + frame[4:]
                    self.sent += 1
                    with contextlib.suppress(OSError):
                        conn.sendall(frame)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self._sock.close()


def test_a_malformed_frame_costs_a_frame_not_the_camera_reader(tmp_path):
    """A frame with a corrupt header (ProtocolError, a ValueError, not an OSError) ended the
    reader task for good, silently: no frame was read again until a restart. It must count as a
    camera failure (reported to the capture cycle) and the reader go on with the next frame."""
    sock = str(tmp_path / "frames.sock")
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        f"perception:\n  enabled: false\ncamera:\n  url: sim+unix://{sock}\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )
    server = GarbledFrameServer(sock, bad=1)

    async def go():
        d = Daemon(ConfigHolder(cfg), notifier=None)
        cycle = CaptureCycle(CaptureSettings(policy="stream"), start_s=time.monotonic())
        reader = asyncio.create_task(d._frame_reader(cycle))
        t_end = time.monotonic() + 2.0
        while d.stats.frames_read < 1 and not reader.done() and time.monotonic() < t_end:
            await asyncio.sleep(0.01)
        died = reader.exception() if reader.done() else None
        d._stop.set()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(reader, 2.0)
        failures = [o for o in cycle.poll(time.monotonic()) if isinstance(o, CaptureFailure)]
        return d.stats.frames_read, died, failures

    try:
        frames, died, failures = asyncio.run(go())
    finally:
        server.close()
    assert died is None, f"the camera reader died: {died!r}"
    assert frames >= 1
    assert any(f.kind == "camera" and "header" in f.message for f in failures), failures


def test_a_camera_slow_to_open_does_not_block_the_event_loop(tmp_path):
    """Opening the cameras (cv2.VideoCapture: a USB camera negotiating its format, a device
    resetting) ran on the event loop: the control loop and the control-unit link stood still
    until the open returned. Here two FIFOs stand in for such devices (replay videos whose
    bytes come only after 0.8 s): the event loop must keep running meanwhile, and an open
    slower than the camera's timeout is reported (a camera failure) but not abandoned."""
    import os

    import cv2

    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(5):
        writer.write(np.full((48, 64, 3), 20 * k, np.uint8))
    writer.release()
    data = video.read_bytes()
    cams = tmp_path / "cams"
    cams.mkdir()
    for i in (1, 2):
        os.mkfifo(cams / f"cam{i}.avi")

    def feed(path) -> None:
        time.sleep(0.8)  # the device answers late
        with open(path, "wb") as f:
            f.write(data)

    feeders = [
        threading.Thread(target=feed, args=(cams / f"cam{i}.avi",), daemon=True) for i in (1, 2)
    ]
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        f"perception:\n  enabled: false\ncamera:\n  url: replay://{cams}\n  timeout_s: 0.3\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )

    async def go():
        d = Daemon(ConfigHolder(cfg), notifier=None)
        cycle = CaptureCycle(CaptureSettings(policy="stream"), start_s=time.monotonic())
        gaps, failures = [], []
        for t in feeders:
            t.start()
        reader = asyncio.create_task(d._frame_reader(cycle))
        last = time.monotonic()
        t_end = last + 2.5
        while d.stats.frames_read < 1 and time.monotonic() < t_end:
            await asyncio.sleep(0.01)
            now = time.monotonic()
            gaps.append(now - last)
            last = now
            failures.extend(o for o in cycle.poll(now) if isinstance(o, CaptureFailure))
        d._stop.set()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(reader, 2.0)
        return d.stats.frames_read, max(gaps), failures

    frames, worst_gap, failures = asyncio.run(go())
    for t in feeders:
        t.join(2.0)
    assert frames >= 1
    assert worst_gap < 0.3, f"the event loop stood still for {worst_gap:.2f} s"
    assert any("not open within" in f.message for f in failures), failures


def test_a_camera_reader_that_dies_counts_as_lost_cameras_until_it_reads_again(
    tmp_path, random_installations
):
    """The camera reader's task fails (a bug after a good read left nothing awaited and no
    error set): while its supervisor waits to start it again, nothing reads the cameras, so
    they count as lost (the speed cap), and the failure is counted as a perception error."""
    from omnid.daemon.run import run_supervised

    cfg = tmp_path / "omnid.yaml"
    calib = tmp_path / "calibration.yaml"
    random_installations[0][1].save(calib)  # a valid one (perception on); only the reader runs
    cfg.write_text(
        f"camera:\n  url: sim+unix://{tmp_path / 'frames.sock'}\n"
        f"perception:\n  calibration_path: {calib}\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )
    d = Daemon(ConfigHolder(cfg), notifier=None)
    assert d.config.perception.enabled and d._camera_ok(time.monotonic())
    runs = 0

    async def reader() -> None:
        nonlocal runs
        runs += 1
        if runs == 1:
            raise RuntimeError("a bug in the reader")
        await d._stop.wait()

    async def go() -> bool:
        task = asyncio.create_task(
            run_supervised("camera_reader", reader, d._stop.is_set, d._camera_reader_failed,
                           backoff_s=0.2)
        )  # fmt: skip
        while runs == 0:
            await asyncio.sleep(0.01)
        lost = not d._camera_ok(time.monotonic())  # during the backoff
        d._stop.set()
        await asyncio.wait_for(task, 2.0)
        return lost

    assert asyncio.run(go())
    assert d.stats.perception_errors == 1 and runs == 1  # stopped during the backoff


def test_a_frozen_camera_stays_refused_after_the_reader_opens_it_again(
    tmp_path, random_installations
):
    """A device that delivers the same frame twice is refused as frozen, and the reader closes
    and opens it again. The reopened source had forgotten the frame it refused: its first frame
    — the same stuck image — was taken as a fresh view (into the capture cycle, the speed cap
    lifted), then refused again, reopened, taken again: a frozen camera fed perception and
    counted as delivering every few tens of ms. After the first refusal no frame of a still
    frozen camera may reach the cycle, and the cameras stay lost."""
    from omnid.sim.frame_server import FrameServer

    sock = str(tmp_path / "frames.sock")
    cfg = tmp_path / "omnid.yaml"
    calib = tmp_path / "calibration.yaml"
    random_installations[0][1].save(calib)  # perception on (camera health judged); no worker
    cfg.write_text(
        f"camera:\n  url: sim+unix://{sock}\nperception:\n  calibration_path: {calib}\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )
    rng = np.random.default_rng(5)
    scene = rng.integers(0, 200, (24, 32)).astype(np.uint8)
    stuck = {"on": False}

    def provider():
        noisy = (scene + rng.integers(0, 3, scene.shape)).astype(np.uint8)
        return time.monotonic(), noisy, scene if stuck["on"] else noisy.copy()

    async def go():
        d = Daemon(ConfigHolder(cfg), notifier=None)
        cycle = CaptureCycle(CaptureSettings(policy="stream"), start_s=time.monotonic())
        reader = asyncio.create_task(d._frame_reader(cycle))
        t_end = time.monotonic() + 2.0
        while d.stats.frames_read < 3 and time.monotonic() < t_end:
            await asyncio.sleep(0.005)
        stuck["on"] = True
        t_end = time.monotonic() + 3.0
        while cycle.failures == 0 and time.monotonic() < t_end:  # the first refusal
            cycle.poll(time.monotonic())
            await asyncio.sleep(0.005)
        frames_at_refusal = d.stats.frames_read
        ok = []
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            await asyncio.sleep(0.005)
            ok.append(d._camera_ok(time.monotonic()))
        d._stop.set()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(reader, 2.0)
        return d.stats.frames_read - frames_at_refusal, ok

    with FrameServer(sock, provider, frame_period_s=None):
        taken, ok = asyncio.run(go())
    assert taken == 0, f"{taken} frames of a frozen camera taken after it was refused"
    assert not any(ok), "a frozen camera counted as delivering"


def test_a_frame_stamped_long_ago_on_our_clock_is_not_dated_now(tmp_path):
    """A camera whose stamps are on the daemon's monotonic clock (the frame server's, a V4L2
    driver's) and that then delivers a frame captured 1.5 s ago — a backlog after the reader
    stood still, a camera pipeline falling behind — had that frame dated at the read (a stamp
    older than the driver's 1 s queue was taken for a foreign clock): a 1.5 s old view entered
    as fresh, placed at the chair's pose of now. Once the source has stamped on our clock, an
    old stamp is an old frame and keeps its time."""
    from omnid.devices.camera import open_camera
    from omnid.sim.frame_server import FrameServer

    sock = str(tmp_path / "frames.sock")
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        f"perception:\n  enabled: false\ncamera:\n  url: sim+unix://{sock}\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )
    rng = np.random.default_rng(6)
    lag = {"s": 0.0}

    def provider():
        img = rng.integers(0, 256, (8, 8), dtype=np.uint8)
        return time.monotonic() - lag["s"], img, img.copy()

    async def go():
        d = Daemon(ConfigHolder(cfg), notifier=None)
        camera = open_camera(d.config.camera)
        try:
            for _ in range(3):  # on time: the source stamps on our clock
                await d._read(camera)
            lag["s"] = 1.5
            frame = await d._read(camera)
            return time.monotonic() - frame.t_s
        finally:
            await camera.close()

    with FrameServer(sock, provider, frame_period_s=None):
        age = asyncio.run(go())
    assert age >= 1.45, f"a frame captured 1.5 s ago dated {age:.3f} s old"


def test_a_frame_is_never_dated_after_the_read_that_returned_it(tmp_path):
    """``camera.frame_latency_s`` may be negative (a driver stamping the start of the exposure,
    its middle comes later) down to -0.5 s; subtracted from the stamp it dated a frame up to
    0.5 s after the read returned it — in the future, so that its cloud counted as fresh for
    that much longer than ``safety.perception_timeout_s``. A frame was captured before it was
    read: its time is at most the end of the read."""
    from omnid.devices.camera import open_camera
    from omnid.sim.frame_server import FrameServer

    sock = str(tmp_path / "frames.sock")
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        f"perception:\n  enabled: false\ncamera:\n  url: sim+unix://{sock}\n"
        "  frame_latency_s: -0.4\n"
        "rider:\n  tilt:\n    enabled: false\n  joystick:\n    enabled: false\n"
    )
    rng = np.random.default_rng(7)

    def provider():
        img = rng.integers(0, 256, (8, 8), dtype=np.uint8)
        return time.monotonic(), img, img.copy()

    async def go():
        d = Daemon(ConfigHolder(cfg), notifier=None)
        camera = open_camera(d.config.camera)
        try:
            ahead = []
            for _ in range(3):
                frame = await d._read(camera)
                ahead.append(frame.t_s - time.monotonic())
            return max(ahead)
        finally:
            await camera.close()

    with FrameServer(sock, provider, frame_period_s=None):
        ahead = asyncio.run(go())
    assert ahead <= 0.0, f"a frame dated {ahead:.3f} s in the future"
