"""PolledLink, the base of the polled device links: period grid, back-off, wake-up, stop.

A minimal link ("ping": write one byte, wait for its echo) runs over a real pty echo device and
over in-process pipes, so the base is tested without the control-unit or tilt codecs.
Timing tolerances are generous (2-core CI under load): assertions bound counts, not instants.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
from collections.abc import Callable

import pytest

from omnid.devices.link import LinkHealth, PolledLink, require_reconnect
from omnid.devices.pty import PtyPort
from omnid.devices.transport import LoopTransport, Transport, open_transport, pipe_pair
from omnid.errors import ConfigError, DeviceError


class PingLink(PolledLink[LinkHealth]):
    device_name = "ping"
    task_name = "ping-link"
    _log = logging.getLogger("tests.ping")

    def __init__(
        self,
        factory: Callable[[], Transport],
        period_s: float = 0.01,
        reconnect_initial_s: float = 0.01,
        reconnect_max_s: float = 0.04,
    ) -> None:
        super().__init__(
            factory,
            LinkHealth(),
            period_s=period_s,
            reconnect_initial_s=reconnect_initial_s,
            reconnect_max_s=reconnect_max_s,
        )
        self.exchanges: list[float] = []
        self.answers = 0
        self.farewells = 0
        self.stopped = False
        self.wake_during_exchange = False

    async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
        t = self._transport
        assert t is not None
        self.exchanges.append(time.monotonic())
        if self.wake_during_exchange and len(self.exchanges) <= 2:
            self._wake_up()
        t.reset_input()
        await t.write(b"?")
        got = await t.read_some(1, 0.05) == b"?"
        self.answers += got
        return got

    async def _farewell(self, transport: Transport) -> None:
        self.farewells += 1

    def _on_stopped(self) -> None:
        self.stopped = True


async def wait_for(cond: Callable[[], bool], timeout_s: float = 3.0) -> None:
    async with asyncio.timeout(timeout_s):
        while not cond():
            await asyncio.sleep(0.002)


def test_polls_on_the_period_grid_over_a_real_pty(echo_pty: PtyPort):
    async def main() -> tuple[int, float, PingLink]:
        link = PingLink(lambda: open_transport(echo_pty.path), period_s=0.02)
        await link.start()
        await wait_for(lambda: link.answers >= 1)
        n0, t0 = len(link.exchanges), time.monotonic()
        await asyncio.sleep(0.4)
        n, dt = len(link.exchanges) - n0, time.monotonic() - t0
        await link.stop()
        return n, dt, link

    n, dt, link = asyncio.run(main())
    # one exchange per 20 ms period: never faster than the grid, and not far behind it
    assert dt / 0.02 * 0.5 <= n <= dt / 0.02 + 2, (n, dt)
    assert link.farewells == 1 and link.stopped and not link._health.connected
    assert link._health.port_errors == 0 and link._health.reconnects == 0


def test_open_failures_back_off_exponentially_up_to_the_maximum():
    opens: list[float] = []

    def factory() -> Transport:
        opens.append(time.monotonic())
        raise DeviceError("nothing there")

    async def main() -> LinkHealth:
        link = PingLink(factory, reconnect_initial_s=0.01, reconnect_max_s=0.04)
        await link.start()
        await wait_for(lambda: len(opens) >= 6)
        await link.stop()
        return link._health

    h = asyncio.run(main())
    gaps = [b - a for a, b in itertools.pairwise(opens)]
    nominal = [0.01, 0.02, 0.04, 0.04, 0.04]
    for gap, want in zip(gaps, nominal, strict=False):
        assert gap >= want * 0.9, (gaps, nominal)  # waits never end early (load only adds)
    assert h.last_error == "nothing there" and not h.connected and h.reconnects == 0


def test_port_error_drops_reconnects_and_resets_back_off():
    devices: list[LoopTransport] = []  # the far ends: closing one is the adapter vanishing

    def factory() -> Transport:
        ours, device = pipe_pair(f"pipe{len(devices)}")
        devices.append(device)
        return ours

    class WriteOnlyLink(PingLink):
        async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
            t = self._transport
            assert t is not None
            self.exchanges.append(time.monotonic())
            await t.write(b"?")  # raises DeviceClosed once the device end is gone
            self.answers += 1
            return True

    async def main() -> tuple[WriteOnlyLink, float]:
        link = WriteOnlyLink(factory, reconnect_initial_s=0.01, reconnect_max_s=1.0)
        await link.start()
        await wait_for(lambda: link.answers >= 2)
        devices[-1].close()
        await wait_for(lambda: link._health.reconnects == 1 and link.answers >= 4)
        assert link._health.connected
        devices[-1].close()  # again, after the device answered: back-off restarts at 10 ms
        t0 = time.monotonic()
        await wait_for(lambda: link._health.reconnects == 2)
        reopen_s = time.monotonic() - t0
        await link.stop()
        return link, reopen_s

    link, reopen_s = asyncio.run(main())
    h = link._health
    assert h.port_errors == 2 and h.reconnects == 2 and len(devices) == 3
    assert "pipe1:a: peer closed" in h.last_error  # the DeviceError text, naming the port
    assert reopen_s < 0.5  # one 10 ms back-off, not a chain doubling towards 1 s


def test_unexpected_exception_is_logged_and_the_task_survives(caplog):
    class BuggyLink(PingLink):
        async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
            self.exchanges.append(time.monotonic())
            if len(self.exchanges) == 1:
                raise ZeroDivisionError("bug")
            return await super()._exchange(loop)

    async def main() -> BuggyLink:
        link = BuggyLink(lambda: LoopTransport())
        await link.start()
        await wait_for(lambda: link.answers >= 2)
        assert link._task is not None and not link._task.done()
        await link.stop()
        return link

    link = asyncio.run(main())
    h = link._health
    assert h.port_errors == 1 and h.reconnects == 1
    assert h.last_error.startswith("internal error: ZeroDivisionError")
    assert "ping link: unexpected error" in caplog.text


def test_stop_wakes_a_long_sleep_at_once_and_a_stuck_task_is_cancelled():
    class StuckLink(PingLink):
        async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
            self.exchanges.append(time.monotonic())
            if len(self.exchanges) > 1:
                await asyncio.sleep(3600)  # a wedged exchange ignores the stop flag
            return True

    async def main() -> tuple[float, float]:
        link = PingLink(lambda: LoopTransport(), period_s=10.0)
        await link.start()
        await wait_for(lambda: len(link.exchanges) == 1)
        t0 = time.monotonic()
        await link.stop()  # the task sleeps 10 s until the next period: woken, not awaited
        quick = time.monotonic() - t0
        stuck = StuckLink(lambda: LoopTransport(), period_s=0.01)
        stuck.stop_timeout_s = 0.1  # type: ignore[misc]
        await stuck.start()
        await wait_for(lambda: len(stuck.exchanges) == 2)
        t0 = time.monotonic()
        await stuck.stop()
        assert stuck._task is None and stuck._transport is None and stuck.stopped
        return quick, time.monotonic() - t0

    quick, stuck_s = asyncio.run(main())
    assert quick < 0.5
    assert 0.1 <= stuck_s < 1.0


def test_wake_up_during_an_exchange_is_not_lost():
    async def main() -> list[float]:
        link = PingLink(lambda: LoopTransport(), period_s=10.0)
        link.wake_during_exchange = True  # e.g. an urgent command set while a reply is awaited
        # (only in the first two: loop:// answers without yielding, so a wake-up in every
        # exchange would never let this coroutine run)
        await link.start()
        await wait_for(lambda: len(link.exchanges) >= 3, timeout_s=2.0)
        await link.stop()
        return link.exchanges

    ex = asyncio.run(main())
    assert ex[2] - ex[0] < 1.0  # each wake-up ended the 10 s wait instead of being cleared


def test_stop_after_the_task_died_logs_it(caplog):
    class DoomedLink(PingLink):
        def _connect(self) -> bool:
            raise RuntimeError("boom")  # outside the loop's handlers: the task dies

    async def main() -> None:
        link = DoomedLink(lambda: LoopTransport())
        await link.start()
        await wait_for(lambda: link._task is not None and link._task.done())
        await link.stop()
        assert link.stopped

    with caplog.at_level(logging.ERROR, "tests.ping"):
        asyncio.run(main())
    assert "ping link task had failed" in caplog.text and "boom" in caplog.text


def test_require_reconnect_names_the_key():
    require_reconnect(0.05, 1.0)
    with pytest.raises(ConfigError, match="reconnect_initial_s"):
        require_reconnect(0.0, 1.0)
    with pytest.raises(ConfigError, match="reconnect_max_s"):
        require_reconnect(0.5, 0.1)
