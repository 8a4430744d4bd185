"""The simulator's frame server over a real Unix socket: round trip, protocol errors, shutdown."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

from omnid.errors import DeviceError, ProtocolError
from omnid.sim.frame_server import (
    HEADER,
    FrameServer,
    decode_header,
    encode_frame,
    fetch_frame,
    request_frame,
)


def _images(seed: int, shape=(48, 64)):
    rng = np.random.default_rng(seed)
    return (
        rng.integers(0, 256, shape, dtype=np.uint8),
        rng.integers(0, 256, shape, dtype=np.uint8),
    )


def test_encoding_is_the_documented_wire_format():
    a, b = _images(1, (3, 5))
    data = encode_frame(12.5, a, b)
    assert data[: HEADER.size] == struct.pack("<4sdII", b"OMNF", 12.5, 3, 5)
    assert data[HEADER.size : HEADER.size + 15] == a.tobytes()
    assert data[HEADER.size + 15 :] == b.tobytes()
    assert decode_header(data) == (12.5, 3, 5)


def test_malformed_headers_are_protocol_errors():
    with pytest.raises(ProtocolError, match="magic"):
        decode_header(struct.pack("<4sdII", b"XXXX", 0.0, 3, 5))
    with pytest.raises(ProtocolError, match="size"):
        decode_header(struct.pack("<4sdII", b"OMNF", 0.0, 0, 5))
    with pytest.raises(ValueError):
        encode_frame(0.0, np.zeros((3, 5), np.uint8), np.zeros((3, 4), np.uint8))


def test_round_trip_over_a_real_socket(tmp_path):
    counter = {"n": 0}

    def provider():
        counter["n"] += 1
        a, b = _images(counter["n"])
        return float(counter["n"]) * 0.1, a, b

    path = tmp_path / "frames.sock"
    with FrameServer(path, provider, frame_period_s=None) as server:
        t1, a1, b1 = fetch_frame(path)
        exp_a, exp_b = _images(1)
        assert t1 == pytest.approx(0.1)
        np.testing.assert_array_equal(a1, exp_a)
        np.testing.assert_array_equal(b1, exp_b)
        # One connection, several requests: each is a fresh frame.
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(2.0)
            s.connect(str(path))
            times = [request_frame(s)[0] for _ in range(3)]
        assert times == pytest.approx([0.2, 0.3, 0.4])
        deadline = time.monotonic() + 2.0  # the server counts after its sendall returns
        while server.requests_served < 4 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert server.requests_served == 4
    assert not path.exists()


def test_concurrent_clients_each_get_whole_frames(tmp_path):
    a, b = _images(7, (120, 160))
    path = tmp_path / "f.sock"
    results: list[bool] = []

    def client():
        for _ in range(5):
            _, x, y = fetch_frame(path)
            results.append(bool(np.array_equal(x, a) and np.array_equal(y, b)))

    with FrameServer(path, lambda: (0.0, a, b)):
        threads = [threading.Thread(target=client) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(10)
    assert results == [True] * 20


def test_bad_request_closes_only_that_connection(tmp_path):
    a, b = _images(3)
    path = tmp_path / "f.sock"
    with FrameServer(path, lambda: (1.0, a, b), frame_period_s=None) as server:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(2.0)
            s.connect(str(path))
            s.sendall(b"X")
            assert s.recv(16) == b""  # closed by the server
        assert fetch_frame(path)[0] == 1.0
        assert server.errors == 1


def test_failing_provider_closes_the_connection_and_the_server_survives(tmp_path):
    calls = {"n": 0}
    a, b = _images(4)

    def provider():
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("renderer broke")
        return 2.0, a, b

    path = tmp_path / "f.sock"
    with FrameServer(path, provider, frame_period_s=None) as server:
        with pytest.raises(DeviceError):
            fetch_frame(path)
        assert fetch_frame(path)[0] == 2.0
        assert server.errors == 1


def test_no_server_is_a_device_error_naming_the_socket(tmp_path):
    with pytest.raises(DeviceError, match=r"nothing\.sock"):
        fetch_frame(tmp_path / "nothing.sock", timeout_s=0.5)


def test_a_regular_file_is_not_replaced(tmp_path):
    p = tmp_path / "precious"
    p.write_text("keep me")
    with pytest.raises(DeviceError, match="not a socket"):
        FrameServer(p, lambda: (0.0, *_images(0))).start()
    assert p.read_text() == "keep me"


def test_frames_come_on_the_cameras_clock_with_their_exposure_time(tmp_path):
    """A free-running camera: frames at the period, stamped with the middle of their exposure
    (before the answer, by the readout), each frame sent once; dropped frames are skipped; a
    provider that takes an argument renders for that exposure time."""
    a, b = _images(5)
    asked: list[float] = []

    def provider(t_s):
        asked.append(t_s)
        return 0.0, a, b

    path = tmp_path / "clock.sock"
    period = 0.02
    srv = FrameServer(path, provider, frame_period_s=period, readout_s=0.004, drop_rate=0.3)
    with srv, socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(2.0)
        s.connect(str(path))
        got = []
        for _ in range(30):
            t_req = time.monotonic()
            t, _, _ = request_frame(s)
            got.append((t_req, t, time.monotonic()))
    stamps = np.array([t for _, t, _ in got])
    steps = np.diff(stamps) / period
    assert np.allclose(steps, np.round(steps), atol=1e-6) and steps.min() > 1.0 - 1e-6
    assert np.any(steps > 2.0 - 1e-6) and srv.frames_dropped > 0  # 30 % lost: some gaps
    assert all(t_got >= t + 0.004 - 1e-3 for _, t, t_got in got)  # after the readout
    assert asked == list(stamps)
