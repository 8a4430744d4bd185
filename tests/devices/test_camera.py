"""Camera sources: video files through cv2.VideoCapture, image-pair replay, the simulator socket."""

from __future__ import annotations

import asyncio
import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from omnid.devices.camera import (
    SIM_HEADER,
    CameraSettings,
    VideoCaptureSource,
    open_camera,
)
from omnid.errors import ConfigError, DeviceClosed, DeviceError, DeviceTimeout


def _frame(k: int, cam: int, shape=(48, 64)) -> np.ndarray:
    """A gray frame whose mean brightness encodes (frame index, camera): 20*k + 100*cam."""
    return np.full(shape, 20 * k + 100 * (cam - 1) + 10, np.uint8)


def _write_video(path: Path, cam: int, n: int) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    assert writer.isOpened()
    for k in range(n):
        writer.write(cv2.cvtColor(_frame(k, cam), cv2.COLOR_GRAY2BGR))
    writer.release()


def test_video_files_read_like_devices(tmp_path):
    for cam in (1, 2):
        _write_video(tmp_path / f"cam{cam}.avi", cam, 3)

    async def go():
        src = open_camera(CameraSettings(url=f"replay://{tmp_path}?loop=1", timeout_s=2.0))
        assert isinstance(src, VideoCaptureSource)
        seen = []
        t_prev = -1.0
        for _ in range(5):  # 3 frames, then loops back
            img1, img2, t_s = await src.read_pair()
            assert img1.shape == (48, 64) and img1.dtype == np.uint8
            assert t_s >= t_prev and abs(t_s - time.monotonic()) < 5.0
            t_prev = t_s
            seen.append((round((img1.mean() - 10) / 20), round((img2.mean() - 110) / 20)))
        await src.flush()
        await src.close()
        with pytest.raises(DeviceClosed):
            await src.read_pair()
        return seen

    # MJPG is lossy: brightness within ±3 levels still decodes the index exactly
    assert asyncio.run(go()) == [(0, 0), (1, 1), (2, 2), (0, 0), (1, 1)]


def test_video_without_loop_ends_with_device_error(tmp_path):
    for cam in (1, 2):
        _write_video(tmp_path / f"cam{cam}.avi", cam, 1)

    async def go():
        src = open_camera(f"replay://{tmp_path}")
        await src.read_pair()
        with pytest.raises(DeviceError, match="no frame"):
            await src.read_pair()
        await src.close()

    asyncio.run(go())


def test_image_pair_replay(tmp_path):
    for k in range(2):
        for cam in (1, 2):
            cv2.imwrite(str(tmp_path / f"cap{k:03d}_{cam}.png"), _frame(k, cam))
    cv2.imwrite(str(tmp_path / "orphan_1.png"), _frame(9, 1))  # no partner: ignored

    async def go():
        src = open_camera(f"replay://{tmp_path}")
        a = await src.read_pair()
        b = await src.read_pair()
        with pytest.raises(DeviceClosed, match="end of replay"):
            await src.read_pair()
        return a, b

    a, b = asyncio.run(go())
    assert np.array_equal(a[0], _frame(0, 1)) and np.array_equal(a[1], _frame(0, 2))
    assert np.array_equal(b[0], _frame(1, 1)) and np.array_equal(b[1], _frame(1, 2))


def test_missing_v4l2_device_and_bad_urls(tmp_path):
    with pytest.raises(DeviceError, match="/dev/video-nonexistent"):
        open_camera("v4l2:///dev/video-nonexistent,/dev/video-nonexistent2")
    with pytest.raises(ConfigError, match="two devices"):
        open_camera("v4l2:///dev/video0")
    with pytest.raises(ConfigError, match="unknown scheme"):
        open_camera("rtsp://camera")
    with pytest.raises(ConfigError, match="does not exist"):
        open_camera(f"replay://{tmp_path}/none")
    with pytest.raises(ConfigError, match="timeout_s"):
        CameraSettings(timeout_s=0)


async def _frame_server(path: str, rows: int, cols: int, hang_after: int | None = None):
    served = 0

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nonlocal served
        try:
            while (await reader.read(1)) == b"G":
                if hang_after is not None and served >= hang_after:
                    await asyncio.sleep(10)
                t_s = 100.0 + served
                img1 = np.full((rows, cols), served, np.uint8)
                img2 = (
                    (np.arange(rows * cols, dtype=np.uint32) + served)
                    .astype(np.uint8)
                    .reshape(rows, cols)
                )
                writer.write(SIM_HEADER.pack(b"OMNF", t_s, rows, cols))
                writer.write(img1.tobytes() + img2.tobytes())
                await writer.drain()
                served += 1
        finally:
            writer.close()

    return await asyncio.start_unix_server(handle, path)


def test_sim_unix_wire_format_and_timeout(tmp_path):
    sock = str(tmp_path / "frames.sock")

    async def go():
        server = await _frame_server(sock, 30, 40, hang_after=2)
        src = open_camera(CameraSettings(url=f"sim+unix://{sock}", timeout_s=0.2))
        img1, img2, t_s = await src.read_pair()
        assert t_s == 100.0 and img1.shape == (30, 40) and (img1 == 0).all()
        assert img2[1, 0] == 40 % 256
        await src.flush()
        _, _, t_s = await src.read_pair()
        assert t_s == 101.0
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="no frames within 0.2 s"):
            await src.read_pair()
        assert 0.15 < time.monotonic() - t0 < 5.0  # not early; the bound only says "no hang"
        await src.close()
        server.close()

    asyncio.run(go())


def test_sim_unix_server_gone_is_device_error(tmp_path):
    async def go():
        src = open_camera(f"sim+unix://{tmp_path}/absent.sock")
        with pytest.raises(DeviceError, match="cannot connect"):
            await src.read_pair()

    asyncio.run(go())


def test_in_process_sim_source_and_timeout():
    calls = []

    def frames():
        calls.append(1)
        return np.zeros((4, 5, 3), np.uint8), np.ones((4, 5), np.uint8), 7.5

    async def slow():
        await asyncio.sleep(5)
        return frames()

    async def go():
        src = open_camera(CameraSettings(url="sim:", timeout_s=0.1), frame_fn=frames)
        img1, _img2, t_s = await src.read_pair()
        assert img1.shape == (4, 5) and t_s == 7.5  # BGR converted to gray
        stuck = open_camera(CameraSettings(url="sim:", timeout_s=0.1), frame_fn=slow)
        with pytest.raises(DeviceTimeout):
            await stuck.read_pair()
        with pytest.raises(ConfigError, match="frame function"):
            open_camera("sim:")

    asyncio.run(go())
    assert len(calls) == 1


def test_sim_header_layout():
    assert SIM_HEADER.size == struct.calcsize("<4sdII") == 20


def test_device_mode_flush_drains_the_driver_queue(tmp_path, caplog):
    """The v4l2 code path on files: settings are applied (files refuse them: logged), and flush
    discards ``buffer_size`` queued frames per camera so the next pair is fresh."""
    for cam in (1, 2):
        _write_video(tmp_path / f"cam{cam}.avi", cam, 6)

    async def go():
        src = VideoCaptureSource(
            (str(tmp_path / "cam1.avi"), str(tmp_path / "cam2.avi")),
            CameraSettings(buffer_size=2, exposure=10.0),
            api=cv2.CAP_ANY,
        )
        img1, _, _ = await src.read_pair()
        await src.flush()
        after, _, _ = await src.read_pair()
        await src.close()
        return round((img1.mean() - 10) / 20), round((after.mean() - 10) / 20)

    with caplog.at_level("WARNING"):
        assert asyncio.run(go()) == (0, 3)
    assert "refused" in caplog.text


def test_image_pair_replay_loops(tmp_path):
    for k in range(2):
        for cam in (1, 2):
            cv2.imwrite(str(tmp_path / f"f{k}_{cam}.png"), _frame(k, cam))

    async def go():
        src = open_camera(f"replay://{tmp_path}?loop=1")
        return [round((float((await src.read_pair())[0].mean()) - 10) / 20) for _ in range(5)]

    assert asyncio.run(go()) == [0, 1, 0, 1, 0]


class _StalledDriver:
    """A simulated camera driver whose grab stalls until ``go`` is set (a USB camera that stops
    delivering), noting whether its resources are released while a grab still runs."""

    def __init__(self) -> None:
        import threading

        self.go = threading.Event()
        self.grabbing = False
        self.released: list[bool] = []  # for each release: was a grab running?

    def grab(self) -> tuple[np.ndarray, np.ndarray, float]:
        self.grabbing = True
        try:
            self.go.wait(5.0)
            img = np.zeros((4, 4), np.uint8)
            return img, img, time.monotonic()
        finally:
            self.grabbing = False

    def release(self) -> None:
        self.released.append(self.grabbing)


def test_a_stalled_grab_is_never_released_under_its_feet():
    """A grab that overran its deadline keeps running in the source's worker thread; closing the
    source then released the device at once on the event loop (cv2.VideoCapture.release()
    while another thread is inside grab(): not thread-safe, and a stalled USB device can block
    the release — the control loop with it). The release must wait for the grab, off the loop."""
    from omnid.devices.camera import StereoFrameSource

    driver = _StalledDriver()

    class Stalled(StereoFrameSource):
        def _read_pair_blocking(self):
            return driver.grab()

        def _close(self) -> None:
            driver.release()

    async def go() -> float:
        src = Stalled(CameraSettings(timeout_s=0.05))
        with pytest.raises(DeviceTimeout):
            await src.read_pair()
        assert driver.grabbing
        t0 = time.monotonic()
        await src.close()
        took = time.monotonic() - t0
        driver.go.set()  # the driver comes back: the grab ends, then the release
        t_end = time.monotonic() + 2.0
        while not driver.released and time.monotonic() < t_end:
            await asyncio.sleep(0.01)
        return took

    took = asyncio.run(go())
    assert driver.released == [False], f"released during a grab: {driver.released}"
    assert took < 0.5  # close does not wait for the stalled grab


def test_a_device_that_delivers_the_same_frame_twice_is_refused_as_frozen(tmp_path):
    """A live sensor's noise makes every frame differ; a frame equal byte for byte to the one
    before it is a stuck driver re-delivering its buffer (or a covered lens): a DeviceError
    naming the camera, which the daemon treats as a camera failure. A video file or an image
    replay may hold a still and is not refused."""
    from omnid.sim.frame_server import FrameServer

    rng = np.random.default_rng(4)
    scene = rng.integers(0, 200, (24, 32)).astype(np.uint8)
    frozen = {"cam": 0}

    def provider():
        noisy = (scene + rng.integers(0, 3, scene.shape)).astype(np.uint8)
        return (time.monotonic(), noisy, scene if frozen["cam"] else noisy.copy())

    sock = str(tmp_path / "frames.sock")

    async def go():
        src = open_camera(CameraSettings(url=f"sim+unix://{sock}", timeout_s=1.0))
        for _ in range(5):  # live: every frame differs
            await src.read_pair()
        frozen["cam"] = 1
        await src.read_pair()  # the first still frame differs from the live one before it
        with pytest.raises(DeviceError, match="camera 2 delivered the same frame twice"):
            await src.read_pair()
        assert src.frozen == 1
        await src.close()

    with FrameServer(sock, provider, frame_period_s=None):
        asyncio.run(go())

    still = np.full((16, 16), 90, np.uint8)
    for k in range(3):  # a replay of one still, looped: not a device
        cv2.imwrite(str(tmp_path / f"{k:03d}_1.png"), still)
        cv2.imwrite(str(tmp_path / f"{k:03d}_2.png"), still)

    async def replay():
        src = open_camera(f"replay://{tmp_path}")
        for _ in range(3):
            await src.read_pair()
        await src.close()

    asyncio.run(replay())


def test_pair_time_trusts_the_drivers_monotonic_stamps_and_nothing_else():
    """The V4L2 buffers' timestamps, when both are monotonic times from inside the read or the
    driver's queue before it, give the pair's time (their mean); anything else — 0 before the
    first frame, a wall-clock stamp, one camera's stamp after the read, NaN — falls back to the
    time the grabs ended."""
    from omnid.devices.camera import MAX_BUFFER_AGE_S, pair_time

    before, grabbed = 500.0, 500.04
    assert pair_time([499_990.0, 499_994.0], before, grabbed) == pytest.approx(499.992)
    old = (before - MAX_BUFFER_AGE_S + 0.01) * 1000.0  # queued, but within the queue's age
    assert pair_time([old, old], before, grabbed) == pytest.approx(old / 1000.0)
    for stamps in (
        [0.0, 0.0],
        [1.764e12, 1.764e12],  # the wall clock, ms since 1970
        [499_990.0, 500_100.0],  # after the read ended
        [(before - MAX_BUFFER_AGE_S - 0.01) * 1000.0, 499_990.0],  # older than any queue
        [float("nan"), 499_990.0],
        [],
    ):
        assert pair_time(stamps, before, grabbed) == grabbed, stamps
    # once the drivers' stamps were monotonic, an older one is a buffer held while nobody read:
    # it keeps its time (at the grab, a stale frame would look fresh)
    stale = (before - 2.5) * 1000.0
    assert pair_time([stale, stale], before, grabbed, monotonic=True) == pytest.approx(before - 2.5)
    assert pair_time([499_990.0, 500_100.0], before, grabbed, monotonic=True) == grabbed


def test_a_pair_stamped_apart_is_reported_as_unsynchronised_cameras(tmp_path, caplog):
    """Which clock stamps the pairs is said once: video files read on the device path have
    positions, not monotonic stamps (stamped when read); two cameras whose frames of a pair
    were captured more than PAIR_SPREAD_WARN_S apart are named unsynchronised (not every
    pair)."""
    import logging

    from omnid.devices.camera import PAIR_SPREAD_WARN_S

    for cam in (1, 2):
        _write_video(tmp_path / f"cam{cam}.avi", cam, 6)

    async def go():
        src = VideoCaptureSource(
            (str(tmp_path / "cam1.avi"), str(tmp_path / "cam2.avi")), api=cv2.CAP_ANY
        )
        for _ in range(3):
            await src.read_pair()
        await src.close()
        return src

    with caplog.at_level(logging.INFO, logger="omnid.devices.camera"):
        src = asyncio.run(go())
        src._note_stamps([1000.0, 1001.0], True)  # a driver's monotonic stamps, 1 ms apart
        apart = 1000.0 * (PAIR_SPREAD_WARN_S + 0.01)
        for _ in range(301):
            src._note_stamps([1000.0, 1000.0 + apart], True)
    said = [r.getMessage() for r in caplog.records]
    assert sum("stamped when read" in m for m in said) == 1  # three pairs, said once
    assert sum("stamped by the drivers' buffer timestamps" in m for m in said) == 1
    assert sum("not synchronised" in m for m in said) == 2  # the 1st and the 301st such pair
