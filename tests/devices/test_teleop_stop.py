"""Review finding: the teleop socket's per-client rate limit refuses a "stop" line like any
other (omnid/devices/teleop.py, _serve: ``client.take(now)`` before ``handle_line``). After a
burst of key-repeat "forward" lines (a terminal or ssh session that delivers its queue at once)
the rider's stop is answered "error rate limit" and never reaches the core: the chair keeps the
last forward for keyboard.hold_s (0.5 s)."""

from __future__ import annotations

import asyncio

from omnid.devices.teleop import TeleopServer, TeleopSettings


def test_stop_is_never_rate_limited(tmp_path):
    async def main():
        got = []
        srv = TeleopServer(
            TeleopSettings(socket_path=str(tmp_path / "t.sock"), max_lines_per_s=50.0),
            got.append,
        )
        await srv.start()
        try:
            r, w = await asyncio.open_unix_connection(str(tmp_path / "t.sock"))
            w.write(b"forward\n" * 60 + b"stop\n")
            await w.drain()
            replies = [
                (await asyncio.wait_for(r.readline(), 2.0)).decode().strip() for _ in range(61)
            ]
            w.close()
            return replies, [c.command for c in got]
        finally:
            await srv.stop()

    replies, commands = asyncio.run(main())
    assert replies[-1] == "ok" and commands[-1] == "stop", (
        f"the stop after a burst got {replies[-1]!r}; last command handed to the core: "
        f"{commands[-1]!r}"
    )


def test_a_client_that_leaves_while_driving_stops_the_chair_at_once(tmp_path):
    """A terminal closed (ssh dropped, window shut) mid-press: without a stop the last forward
    held for keyboard.hold_s with nobody left to let go. A client that leaves while another
    drives, or after its own stop, sends nothing."""
    path = str(tmp_path / "t.sock")

    async def send(w, r, word):
        w.write(word.encode() + b"\n")
        await w.drain()
        assert (await asyncio.wait_for(r.readline(), 2.0)).strip() == b"ok"

    async def main():
        got = []
        srv = TeleopServer(TeleopSettings(socket_path=path), got.append)
        await srv.start()
        try:
            ra, wa = await asyncio.open_unix_connection(path)
            rb, wb = await asyncio.open_unix_connection(path)
            await send(wa, ra, "forward")
            wa.close()  # A leaves mid-press
            for _ in range(100):
                if got[-1].command == "stop":
                    break
                await asyncio.sleep(0.01)
            left_driving = [c.command for c in got]
            await send(wb, rb, "left")
            ra, wa = await asyncio.open_unix_connection(path)
            wa.close()  # A' leaves while B drives: B's key stands
            await send(wb, rb, "stop")
            wb.close()  # B leaves after its own stop: nothing more
            await asyncio.sleep(0.2)
            return left_driving, [c.command for c in got]
        finally:
            await srv.stop()

    left_driving, commands = asyncio.run(main())
    assert left_driving == ["forward", "stop"]
    assert commands == ["forward", "stop", "left", "stop"]
