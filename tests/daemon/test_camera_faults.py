"""The daemon's camera reader (``Daemon._frame_reader``) against a camera that misbehaves: a
frame server on a Unix socket (the ``sim+unix://`` wire format) that sends malformed frames."""

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
        img = np.zeros((8, 8), np.uint8)
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
