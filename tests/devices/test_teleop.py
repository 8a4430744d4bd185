"""Keyboard teleop: key decoding, the socket server's protocol and permissions, the client."""

from __future__ import annotations

import asyncio
import os
import stat
import subprocess
import sys

import pytest

from omnid.config import from_mapping
from omnid.devices.teleop import KeyCommand, KeyDecoder, TeleopServer, TeleopSettings, run_client
from omnid.errors import ConfigError, DeviceError

UP, DOWN, RIGHT, LEFT = b"\x1b[A", b"\x1b[B", b"\x1b[C", b"\x1b[D"


def test_key_decoder_arrows_split_sequences_and_noise():
    d = KeyDecoder()
    assert d.feed(UP + LEFT + b"x" + RIGHT) == ["forward", "left", "right"]
    assert d.feed(b"\x1b") == []  # split escape sequence waits
    assert d.feed(b"[") == []
    assert d.feed(b"B ") == ["stop", "stop"]
    assert d.feed(b"\x1bOA") == ["forward"]  # application cursor mode
    assert d.feed(b"\x1b[Z\x1bq") == ["quit"]  # unknown sequence skipped, then q
    assert d.feed(b"\x03") == ["quit"]


def test_settings_refuse_world_access_and_unknown_group(tmp_path):
    with pytest.raises(ConfigError, match="teleop.mode"):
        from_mapping(TeleopSettings, {"mode": 0o666}, "teleop")

    async def go():
        srv = TeleopServer(TeleopSettings(socket_path=str(tmp_path / "s"), group="no-such-grp"))
        with pytest.raises(ConfigError, match="no-such-grp"):
            await srv.start()

    asyncio.run(go())


def test_server_protocol_permissions_and_stale_socket(tmp_path):
    path = tmp_path / "teleop.sock"
    got: list[KeyCommand] = []
    group = __import__("grp").getgrgid(os.getgid()).gr_name

    async def go():
        # a stale socket from a crashed run is replaced
        stale = TeleopServer(TeleopSettings(socket_path=str(path)))
        await stale.start()
        stale._server.close()  # simulate a crash: socket file left behind
        srv = TeleopServer(TeleopSettings(socket_path=str(path), group=group), got.append)
        await srv.start()
        st = path.stat()
        assert stat.S_ISSOCK(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o660
        assert st.st_gid == os.getgid()
        reader, writer = await asyncio.open_unix_connection(str(path))
        replies = []
        for line in (b"forward\n", b"  LEFT \n", b"ping\n", b"jump\n", b"stop\n"):
            writer.write(line)
            replies.append((await asyncio.wait_for(reader.readline(), 10.0)).decode().strip())
        writer.write(b"x" * 200 + b"\n")  # over max_line_bytes: refused, connection closed
        replies.append((await reader.readline()).decode().strip())
        assert await reader.read() == b""
        writer.close()
        await srv.stop()
        assert not path.exists()
        return replies, srv

    replies, srv = asyncio.run(go())
    assert replies[:3] == ["ok", "ok", "pong"]
    assert replies[3].startswith("error unknown command 'jump'")
    assert replies[4] == "ok" and replies[5] == "error line too long"
    assert [c.command for c in got] == ["forward", "left", "stop"]
    assert got[0].timestamp_s <= got[1].timestamp_s <= got[2].timestamp_s
    assert srv.latest == got[-1] and srv.errors == 2


def test_refuses_to_replace_a_regular_file(tmp_path):
    path = tmp_path / "not-a-socket"
    path.write_text("keep me")

    async def go():
        with pytest.raises(ConfigError, match="not a socket"):
            await TeleopServer(TeleopSettings(socket_path=str(path))).start()

    asyncio.run(go())
    assert path.read_text() == "keep me"


def test_client_sends_keys_over_a_real_socket(tmp_path):
    path = str(tmp_path / "t.sock")
    got: list[KeyCommand] = []
    lines: list[str] = []

    async def go():
        srv = TeleopServer(TeleopSettings(socket_path=path), got.append)
        await srv.start()
        r, w = os.pipe()
        os.set_blocking(r, False)
        client = asyncio.create_task(run_client(path, r, lines.append))
        os.write(w, UP + b"\x1b")  # second sequence split across writes
        await asyncio.sleep(0.05)
        os.write(w, b"[D" + RIGHT + b"zz" + DOWN + b"q" + UP)  # the key after q is not sent
        code = await asyncio.wait_for(client, 2.0)
        os.close(w)
        os.close(r)
        await srv.stop()
        return code

    assert asyncio.run(go()) == 0
    assert [c.command for c in got] == ["forward", "left", "right", "stop"]
    assert lines == ["forward: ok", "left: ok", "right: ok", "stop: ok"]


def test_client_reports_lost_server(tmp_path):
    path = str(tmp_path / "t.sock")

    async def go():
        with pytest.raises(DeviceError, match="cannot connect"):
            await run_client(path, 0)
        srv = TeleopServer(TeleopSettings(socket_path=path))
        await srv.start()
        r, w = os.pipe()
        os.set_blocking(r, False)
        lines: list[str] = []
        client = asyncio.create_task(run_client(path, r, lines.append))
        await asyncio.sleep(0.05)
        await srv.stop()
        os.write(w, UP)
        code = await asyncio.wait_for(client, 2.0)
        os.close(w)
        os.close(r)
        return code, lines

    code, lines = asyncio.run(go())
    assert code == 1 and "server" in lines[-1]


def test_teleop_command_line_end_to_end(tmp_path):
    """`omnid teleop` as a process with keys on stdin (not a tty: no raw mode needed)."""
    path = str(tmp_path / "t.sock")
    got: list[KeyCommand] = []

    async def go():
        srv = TeleopServer(TeleopSettings(socket_path=path), got.append)
        await srv.start()
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "omnid.cli",
            "teleop",
            "--socket",
            path,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        out, err = await asyncio.wait_for(proc.communicate(UP + LEFT + b"q"), 20)
        await srv.stop()
        return proc.returncode, out.decode(), err.decode()

    code, out, err = asyncio.run(go())
    assert code == 0, err
    # q quits with "left" the newest command: the server stops the chair for the gone client
    assert [c.command for c in got] == ["forward", "left", "stop"]
    assert "forward: ok" in out


def test_idle_clients_are_dropped_or_make_room_and_lines_are_rate_limited(tmp_path):
    """Four idle clients no longer lock everyone out; a flooding client cannot starve others."""

    async def go():
        s = TeleopSettings(
            socket_path=str(tmp_path / "t.sock"),
            max_clients=2,
            idle_timeout_s=1.0,
            evict_idle_s=0.2,
            max_lines_per_s=20.0,
        )
        got: list[KeyCommand] = []
        srv = TeleopServer(s, on_command=got.append)
        await srv.start()
        try:
            idle = [await asyncio.open_unix_connection(s.socket_path) for _ in range(2)]
            await asyncio.sleep(0.3)  # both idle longer than evict_idle_s
            r, w = await asyncio.open_unix_connection(s.socket_path)
            w.write(b"left\n")
            assert await asyncio.wait_for(r.readline(), 2.0) == b"ok\n"  # got a place
            assert srv.evicted == 1
            first = await asyncio.wait_for(idle[0][0].readline(), 2.0)
            assert first.startswith(b"error idle")  # the idlest was told why
            # a flood: 100 lines at once; about one second's budget is accepted
            w.write(b"left\n" * 100)
            replies = [await asyncio.wait_for(r.readline(), 2.0) for _ in range(100)]
            ok = sum(x == b"ok\n" for x in replies)
            assert 10 <= ok <= 30 and srv.rate_limited == 100 - ok
            # the other idle client is dropped after idle_timeout_s of silence
            line = await asyncio.wait_for(idle[1][0].readline(), 3.0)
            assert line == b"error idle timeout\n"
            assert await asyncio.wait_for(idle[1][0].read(), 2.0) == b""
            w.close()
            for _, iw in idle:
                iw.close()
        finally:
            await srv.stop()

    asyncio.run(go())
