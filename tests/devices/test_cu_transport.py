"""Transports and the pty server: real pseudo-terminals, loopback and in-process pipes."""

from __future__ import annotations

import asyncio
import os

import pytest

from omnid.devices.pty import PtyPort
from omnid.devices.transport import open_transport, pipe_pair
from omnid.errors import DeviceClosed, DeviceError, DeviceTimeout


def run(coro):
    return asyncio.run(coro)


def test_loop_url_returns_what_was_written():
    async def main():
        t = open_transport("loop://")
        await t.write(b"hello")
        assert await t.read_exactly(5, 0.1) == b"hello"
        assert await t.read_some(10, 0.01) == b""
        t.close()
        with pytest.raises(DeviceClosed):
            await t.write(b"x")

    run(main())


def test_pipe_pair_crosses_and_reports_peer_close():
    async def main():
        a, b = pipe_pair()
        await a.write(b"ab")
        assert await b.read_exactly(2, 0.1) == b"ab"
        with pytest.raises(DeviceTimeout):
            await b.read_exactly(1, 0.02)
        a.close()
        with pytest.raises(DeviceClosed):
            await b.read_some(1, 0.1)

    run(main())


def test_pty_round_trip_through_stable_link(echo_pty: PtyPort):
    assert os.path.islink(echo_pty.path)

    async def main():
        t = open_transport(echo_pty.path, baudrate=115200)
        payload = bytes(range(256))  # raw mode: every byte value passes unchanged
        await t.write(payload)
        assert await t.read_exactly(256, 1.0) == payload
        t.close()

    run(main())


def test_unplug_is_seen_as_closed_and_replug_reopens_same_path(echo_pty: PtyPort):
    async def main():
        t = open_transport(echo_pty.path)
        old = echo_pty.slave_path
        echo_pty.unplug()
        with pytest.raises(DeviceClosed):
            await t.read_some(10, 1.0)
        with pytest.raises(DeviceError):
            open_transport(echo_pty.path)
        assert echo_pty.replug() == echo_pty.path
        assert echo_pty.slave_path is not None and old is not None
        t2 = open_transport(echo_pty.path)
        await t2.write(b"again")
        assert await t2.read_exactly(5, 1.0) == b"again"
        t2.close()

    run(main())


def test_missing_port_names_the_path(tmp_path):
    with pytest.raises(DeviceError, match="ttyNOPE"):
        open_transport(str(tmp_path / "ttyNOPE"))
    with pytest.raises(DeviceError, match="scheme"):
        open_transport("tcp://1.2.3.4:5")


def test_rs485_on_a_pty_is_refused_by_name(echo_pty: PtyPort):
    from omnid.devices.transport import Rs485Options

    with pytest.raises(DeviceError, match="RS-485"):
        open_transport(echo_pty.path, rs485=Rs485Options())


def test_pty_port_write_while_unplugged_is_dropped(tmp_path):
    port = PtyPort(lambda d: None, name="x")
    assert port.write(b"abc") == 0
    path = port.open()
    assert path.startswith("/dev/")
    port.close()
    port.close()
