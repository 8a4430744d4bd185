"""ControlUnitLink against ControlUnitEmulator over real ptys: round trips, faults, recovery.

Detection is counted in command periods (commands sent between the fault and the unhealthy
flag), not wall time, so the assertions hold on a loaded CI machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from omnid.config import from_mapping
from omnid.devices import cu_codec as codec
from omnid.devices.control_unit import (
    ControlUnitHealth,
    ControlUnitLink,
    ControlUnitSettings,
    FreshnessGate,
    WheelCommand,
)
from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant, WireSpy
from omnid.devices.transport import LoopTransport, Transport, pipe_pair
from omnid.errors import ConfigError, DeviceClosed, DeviceError, ProtocolError

PERIOD_S = 0.01


def settings(port: str, **kw) -> ControlUnitSettings:
    base = dict(
        port=port,
        command_period_s=PERIOD_S,
        reply_timeout_s=0.008,
        unit_watchdog_s=0.1,
        reconnect_initial_s=0.01,
        reconnect_max_s=0.05,
    )
    base.update(kw)
    return ControlUnitSettings(**base)


async def wait_for(pred: Callable[[], bool], timeout_s: float = 10.0) -> None:
    """Poll ``pred`` until true; the deadline is generous (a loaded CI machine), not a claim."""
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.002)


class UnhealthyProbe(logging.Handler):
    """Notes ``commands_sent`` at the instant the link logs that it became unhealthy.

    The log call runs synchronously inside the link's task, so the count is exact however late
    the test's own polling gets to run on a busy machine.
    """

    def __init__(self, link: ControlUnitLink) -> None:
        super().__init__(logging.WARNING)
        self.link = link
        self.sent_at_unhealthy: list[int] = []

    def emit(self, record: logging.LogRecord) -> None:
        if "unhealthy" in record.getMessage():
            self.sent_at_unhealthy.append(self.link.health.commands_sent)


async def control_cycle(link: ControlUnitLink) -> None:
    """Stands in for the daemon's control loop: re-computes (re-submits) the latest command
    every 10 ms. Frames carry a command only while a live cycle keeps submitting it."""
    while True:
        link.set_command(link.command)
        await asyncio.sleep(0.01)


def with_link(
    emu: ControlUnitEmulator, path: str, body: Callable[[ControlUnitLink], Awaitable[None]], **kw
):
    async def main():
        link = ControlUnitLink(settings(path, **kw))
        await link.start()
        cycle = asyncio.create_task(control_cycle(link))
        try:
            await wait_for(lambda: link.health.healthy)
            await body(link)
        finally:
            cycle.cancel()
            await link.stop()

    asyncio.run(main())


@pytest.fixture
def emu(tmp_path: Path):
    e = ControlUnitEmulator(
        MotorPlant(full_duty_rpm=30.0, time_constant_s=0.02), laser_delay_s=0.02
    )
    e.open_pty(tmp_path / "ttyCU")
    yield e
    e.close()


def test_wheel_command_refuses_nan_and_out_of_range():
    for bad in (float("nan"), 1.01, -1.5, float("inf")):
        with pytest.raises(ProtocolError):
            WheelCommand(bad, 0.0)
    with pytest.raises(ProtocolError):
        WheelCommand(0.0, True)  # type: ignore[arg-type]
    assert WheelCommand(-1.0, 1.0).to_frame(3).flags & codec.FLAG_LEFT_REVERSE


def test_settings_are_validated_with_named_keys():
    with pytest.raises(ConfigError, match="reply_timeout_s"):
        ControlUnitSettings(reply_timeout_s=0.05, command_period_s=0.02)
    with pytest.raises(ConfigError, match="control_unit.baudrate"):
        from_mapping(ControlUnitSettings, {"baudrate": 1234}, "control_unit")
    s = from_mapping(ControlUnitSettings, {"port": "/dev/x", "rs485": {"delay_before_tx_s": 0.001}})
    assert s.rs485 is not None and s.rs485.delay_before_tx_s == 0.001


def test_round_trip_drives_wheels_counts_clocks_and_switches_laser(emu: ControlUnitEmulator):
    async def body(link: ControlUnitLink):
        st0 = link.status
        assert st0 is not None and not st0.laser_on
        link.set_command(WheelCommand(1.0, -0.5, laser_on=True, enable=True))

        def moved() -> bool:
            st = link.status
            # 30 rpm = 7.5 clocks/s at full duty: left forward, right backward at half speed
            return (
                st is not None
                and st.left_clocks - st0.left_clocks >= 2
                and st.right_clocks - st0.right_clocks <= -1
                and st.laser_on
            )

        await wait_for(moved)
        st = link.status
        assert st is not None
        assert st.left_applied_duty == 1.0 and st.right_applied_duty == -0.5
        assert emu.laser_on and emu.applied_duty == (1.0, -0.5)
        h = link.health
        # A pty never corrupts bytes. Replies may miss the 8 ms deadline on a busy machine; such
        # a late reply is dropped before the next command, never taken for it or blamed on it.
        assert h.crc_errors == 0 and h.malformed == 0
        assert h.seq_errors + (h.late_bytes_discarded > 0) <= h.timeouts
        assert h.replies_ok >= 10 and h.replies_ok + h.timeouts <= h.commands_sent
        link.set_command(WheelCommand.stop())
        await wait_for(lambda: emu.applied_duty == (0.0, 0.0) and not emu.laser_on)

    # a watchdog long enough that a scheduling gap on a busy machine cannot trip it here
    with_link(emu, emu.path or "", body, unit_watchdog_s=0.5)


def test_clock_counters_unwrap_across_int32_wrap(tmp_path: Path):
    emu = ControlUnitEmulator(
        MotorPlant(full_duty_rpm=600.0, time_constant_s=0.01), clock_offset=2**31 - 20
    )
    path = emu.open_pty(tmp_path / "ttyW")

    async def body(link: ControlUnitLink):
        st0 = link.status
        assert st0 is not None and st0.left_clocks == 2**31 - 20
        link.set_command(WheelCommand(1.0, 1.0, enable=True))  # 150 clocks/s
        await wait_for(lambda: (link.status.left_clocks if link.status else 0) > 2**31 + 20)
        st = link.status
        assert st is not None
        assert (
            st.left_clocks - st0.left_clocks == emu.clocks[0]
            or abs(st.left_clocks - st0.left_clocks - emu.clocks[0]) <= 3
        )  # emulator kept moving since the reply

    try:
        with_link(emu, path, body)
    finally:
        emu.close()


async def inject_when_steady(
    link: ControlUnitLink, probe: UnhealthyProbe, inject: Callable[[], None]
) -> int:
    """Inject a fault while the link is healthy with no miss pending; returns the period count.

    Periods = commands sent from the injection to the instant the link turned unhealthy (the
    probe's exact count). Nothing awaits between the check and the injection, so the first
    transition the probe sees is after the fault; a reply missed for load can only shorten it.
    """
    await wait_for(lambda: link.health.healthy and link.health.consecutive_missed == 0)
    fired = len(probe.sent_at_unhealthy)
    sent = link.health.commands_sent
    inject()
    await wait_for(lambda: not link.health.healthy)
    assert link.status is None  # visible at once: the daemon stops on None
    assert len(probe.sent_at_unhealthy) > fired, "the transition was not logged"
    return probe.sent_at_unhealthy[fired] - sent


@pytest.mark.parametrize("fault", ["stall", "corrupt", "drop"])
def test_silent_or_corrupt_unit_detected_within_3_periods_and_recovered(
    emu: ControlUnitEmulator, fault: str, caplog
):
    caplog.set_level(logging.WARNING, "omnid.devices.control_unit")

    async def body(link: ControlUnitLink):
        probe = UnhealthyProbe(link)
        logging.getLogger("omnid.devices.control_unit").addHandler(probe)
        try:
            link.set_command(WheelCommand(0.3, 0.3, enable=True))
            inject = {"stall": emu.stall, "corrupt": emu.corrupt_replies, "drop": emu.drop_replies}
            periods = await inject_when_steady(link, probe, inject[fault])
        finally:
            logging.getLogger("omnid.devices.control_unit").removeHandler(probe)
        assert 1 <= periods <= 3  # the reply in flight at the injection may still arrive
        if fault == "corrupt":  # every reply now fails its CRC, and each one is counted
            await wait_for(lambda: link.health.crc_errors >= 2)
        else:
            await wait_for(lambda: link.health.timeouts >= 2)
        assert link.status is None
        assert any("unhealthy" in r.message for r in caplog.records)
        emu.recover()
        await wait_for(lambda: link.health.healthy)
        assert link.status is not None
        if fault == "corrupt":  # bad replies are rejected by the master, not counted at the unit
            assert link.status.faults & codec.FAULT_RX_ERROR == 0

    with_link(emu, emu.path or "", body)


def test_unplug_replug_detected_within_3_periods_and_reconnected(emu: ControlUnitEmulator):
    async def body(link: ControlUnitLink):
        before = link.status
        assert before is not None
        probe = UnhealthyProbe(link)
        logging.getLogger("omnid.devices.control_unit").addHandler(probe)
        try:
            periods = await inject_when_steady(link, probe, emu.die)
        finally:
            logging.getLogger("omnid.devices.control_unit").removeHandler(probe)
        assert periods <= 3  # the first failed read or write drops the port at once
        await wait_for(lambda: not link.health.connected)
        await asyncio.sleep(0.1)  # stays down while unplugged: reconnect attempts back off
        h = link.health
        assert not h.connected and not h.healthy and h.port_errors >= 1 and h.reconnects == 0
        assert link.status is None
        emu.recover()
        await wait_for(lambda: link.health.healthy)
        h = link.health
        assert h.connected and h.reconnects == 1
        after = link.status
        assert after is not None and after.left_clocks >= before.left_clocks

    with_link(emu, emu.path or "", body)


def test_unit_watchdog_stops_motors_and_laser_when_commands_stop(emu: ControlUnitEmulator):
    async def body(link: ControlUnitLink):
        link.set_command(WheelCommand(0.8, 0.8, laser_on=True, enable=True))
        await wait_for(lambda: emu.laser_on and emu.applied_duty == (0.8, 0.8))
        task = link._task
        assert task is not None
        task.cancel()  # the master dies without a word: no stop command is sent
        trips0 = emu.watchdog_trips  # (a scheduling gap on a busy machine may have tripped it)
        # sleeps never end early: 0.15 s after the last command the 0.1 s watchdog has tripped
        await asyncio.sleep(0.1 + 0.05)
        assert emu.applied_duty == (0.0, 0.0)
        assert emu.watchdog_trips == trips0 + 1
        await asyncio.sleep(0.03)  # + the 0.02 s relay delay
        assert not emu.laser_on
        await asyncio.sleep(0.2)  # the wheels coast to a halt (tau 0.02 s: 10 τ) ...
        c0 = emu.clocks
        await asyncio.sleep(0.2)  # ... and stay there
        assert emu.clocks == c0 and emu.watchdog_trips == trips0 + 1

    with_link(emu, emu.path or "", body)


def test_watchdog_fault_reported_in_next_reply():
    # in-process pipe + injected clock: the unit's watchdog without wall-clock waiting
    now = [0.0]
    emu = ControlUnitEmulator(clock=lambda: now[0])

    def send(cycle: int, enable: bool = True) -> codec.ReplyFrame:
        cmd = WheelCommand(0.5, 0.5, enable=enable)
        wire = codec.encode_command(cmd.to_frame(cycle & 0xFF, watchdog_ms=250, cycle=cycle))
        rep = codec.decode_frame(emu.handle_bytes(wire))
        assert isinstance(rep, codec.ReplyFrame)
        return rep

    assert send(1, enable=False).faults & codec.FAULT_RESET  # the first reply carries RESET
    now[0] = 0.2
    rep = send(2)
    assert rep.faults == 0 and rep.left_applied_pm == 500
    now[0] = 0.46
    assert emu.applied_duty == (0.0, 0.0)
    rep = send(3)  # after the trip ENABLE needs a zero frame first: refused, latched
    assert rep.faults & codec.FAULT_WATCHDOG and rep.faults & codec.FAULT_STALE_COMMAND
    assert rep.left_applied_pm == 0
    send(4, enable=False)
    assert send(5).left_applied_pm == 500  # obeyed again


def test_unit_refuses_stale_replayed_and_endlessly_repeated_commands():
    """Protocol "Freshness", enforced by the unit itself: a master whose control loop died but
    whose link goes on sending the last command (the same cycle number) brakes after
    MAX_AGE_MS; so does a command sent too old or an older cycle than one already obeyed."""
    now = [0.0]
    emu = ControlUnitEmulator(clock=lambda: now[0])
    drive = WheelCommand(0.5, 0.5, enable=True)

    def send(cycle: int, age_ms: int = 0, cmd: WheelCommand = drive) -> codec.ReplyFrame:
        frame = cmd.to_frame(cycle & 0xFF, 250, cycle=cycle, age_ms=age_ms, max_age_ms=40)
        rep = codec.decode_frame(emu.handle_bytes(codec.encode_command(frame)))
        assert isinstance(rep, codec.ReplyFrame)
        return rep

    send(1, cmd=WheelCommand.stop())
    for k, t in enumerate((0.02, 0.04, 0.06)):
        now[0] = t
        assert send(2 + k).left_applied_pm == 500  # a new cycle every period: driving
    now[0] = 0.08
    assert send(4).left_applied_pm == 500  # the same cycle again, 20 ms on: still fresh
    now[0] = 0.11
    rep = send(4)  # ... 50 ms on: the master's control loop is not computing any more
    assert rep.left_applied_pm == 0 and rep.faults & codec.FAULT_STALE_COMMAND
    assert send(5).left_applied_pm == 0  # and not before a zero frame
    send(6, cmd=WheelCommand.stop())
    now[0] = 0.12
    assert send(7).left_applied_pm == 500
    assert send(8, age_ms=45).left_applied_pm == 0  # computed too long before it was sent
    send(9, cmd=WheelCommand.stop())
    assert send(10).left_applied_pm == 500
    assert send(3).left_applied_pm == 0  # an older cycle: replayed
    assert emu.stale_refusals == 4


def test_corrupted_command_is_ignored_and_counted_by_the_unit():
    now = [0.0]
    emu = ControlUnitEmulator(clock=lambda: now[0])
    good = codec.encode_command(WheelCommand(0.5, 0.5, enable=True).to_frame(9))
    bad = bytearray(good)
    bad[5] ^= 0x01
    assert emu.handle_bytes(bytes(bad)) == b""
    assert emu.applied_duty == (0.0, 0.0) and emu.rx_errors == 1
    rep = codec.decode_frame(emu.handle_bytes(good))
    assert isinstance(rep, codec.ReplyFrame)
    assert rep.seq == 9 and rep.rx_errors == 1 and rep.faults & codec.FAULT_RX_ERROR


def test_link_over_in_process_pipe():
    async def main():
        a, b = pipe_pair()
        emu = ControlUnitEmulator()
        emu.serve_pipe(b)
        link = ControlUnitLink(settings("pipe"), transport_factory=lambda: a)
        await link.start()
        await wait_for(lambda: link.health.healthy)
        link.set_command(WheelCommand(0.0, 0.0, laser_on=True, enable=True))
        await wait_for(lambda: bool(link.status and link.status.laser_on))
        await link.stop()
        emu.close()

    asyncio.run(main())


def test_missing_port_retries_with_backoff_and_stays_unhealthy(tmp_path: Path):
    async def main():
        link = ControlUnitLink(settings(str(tmp_path / "nothing")))
        await link.start()
        await asyncio.sleep(0.15)
        h = link.health
        assert not h.connected and not h.healthy and link.status is None
        assert "nothing" in h.last_error
        await link.stop()

    asyncio.run(main())


def test_late_partial_reply_is_dropped_before_the_next_command_not_blamed_on_it():
    """Regression (found by the load flake hunt): a reply that misses its deadline used to sit
    in the input and be parsed together with the next reply, counting a CRC error on a clean
    line (and, had it been the only reply, a miss blamed on the wrong command). The driver now
    discards stale input before each command, as a half-duplex master must.

    Same event loop for unit and link: the 10 ms reply deadline fires before the unit's 50 ms
    delay on any machine, and the late bytes land long before the next command (200 ms period).
    """

    async def main():
        a, b = pipe_pair()
        unit = ControlUnitEmulator()
        parser = codec.FrameParser(accept=(codec.TYPE_COMMAND,))
        late = 12  # the first 12 of 21 reply bytes: a frame cut short

        async def serve() -> None:
            n = 0
            while True:
                data = await b.read_some(64, 5.0)
                for frame in parser.feed(data):
                    n += 1
                    reply = unit.handle_bytes(codec.encode_command(frame))
                    if n == 3:
                        await asyncio.sleep(0.05)
                        reply = reply[:late]
                    await b.write(reply)

        server = asyncio.create_task(serve())
        link = ControlUnitLink(
            settings("pipe", command_period_s=0.2, reply_timeout_s=0.01, unit_watchdog_s=0.5),
            transport_factory=lambda: a,
        )
        await link.start()
        try:
            await wait_for(lambda: link.health.replies_ok >= 4)
            h = link.health
        finally:
            await link.stop()
            server.cancel()
        assert h.crc_errors == 0 and h.malformed == 0 and h.seq_errors == 0
        assert h.timeouts == 1 and h.healthy
        assert h.late_bytes_discarded == late

    asyncio.run(main())


class HangingEnd(LoopTransport):
    """A pipe end whose writes can be made to hang forever (a wedged USB adapter driver)."""

    hang = False

    async def _write_raw(self, data: bytes) -> None:
        if self.hang:
            await asyncio.Event().wait()
        await super()._write_raw(data)


def test_stuck_or_dead_link_task_never_leaves_a_stale_status(caplog):
    caplog.set_level(logging.WARNING, "omnid.devices.control_unit")

    async def main():
        a, b = HangingEnd("hang:a"), LoopTransport("hang:b")
        a.peer, b.peer = b, a
        emu = ControlUnitEmulator()
        emu.serve_pipe(b)
        s = settings("pipe", unit_watchdog_s=0.1)
        link = ControlUnitLink(s, transport_factory=lambda: a)
        await link.start()
        await wait_for(lambda: link.status is not None)
        a.hang = True  # the task now waits forever inside a write: no reply, no miss counted
        await wait_for(lambda: link.status is None)
        st = link.last_status
        assert st is not None and time.monotonic() - st.timestamp_s > s.unit_watchdog_s
        assert not link.health.healthy and link.health.timeouts == 0
        assert "old" in caplog.text
        await link.stop()  # gives up on the stuck task after its own timeout
        assert link.status is None
        emu.close()
        # a task that died (cancelled here) is caught at once, without waiting for the age
        a2, b2 = pipe_pair()
        emu = ControlUnitEmulator()
        emu.serve_pipe(b2)
        link2 = ControlUnitLink(s, transport_factory=lambda: a2)
        await link2.start()
        await wait_for(lambda: link2.status is not None)
        task = link2._task
        assert task is not None
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        assert link2.status is None and "task not running" in caplog.text
        await link2.stop()
        emu.close()

    asyncio.run(main())


class DeadOnArrival(LoopTransport):
    """A port that opens fine and fails every write (an adapter that enumerates but is dead)."""

    async def _write_raw(self, data: bytes) -> None:
        raise DeviceClosed(f"{self.name}: device disconnected (EIO)")


def test_port_that_opens_but_fails_at_once_is_retried_with_backoff_not_spun():
    """Regression: reopen followed by an instant write error used to loop without ever yielding,
    freezing the whole event loop (the daemon could not even stop). Now each failure backs off.
    """
    opens = 0

    def factory() -> Transport:
        nonlocal opens
        opens += 1
        if opens > 500:  # the old spin would get here without yielding; end it, then fail below
            raise DeviceError("gave up")
        return DeadOnArrival(f"dead{opens}")

    async def main():
        link = ControlUnitLink(settings("dead"), transport_factory=factory)
        await link.start()
        t0 = time.monotonic()
        ticks = 0
        for _ in range(20):  # the loop keeps running other tasks meanwhile
            await asyncio.sleep(0.01)
            ticks += 1
        h = link.health
        elapsed_s = time.monotonic() - t0
        await link.stop()
        return ticks, h, elapsed_s

    ticks, h, elapsed_s = asyncio.run(main())
    assert ticks == 20 and link_never_healthy(h)
    # back-off from 10 ms doubling to 50 ms: at most one reopen per 10 ms, never 500 at once
    assert 2 <= opens <= 2 + elapsed_s / 0.01, (opens, elapsed_s)
    assert h.port_errors == opens and "EIO" in h.last_error


def link_never_healthy(h: ControlUnitHealth) -> bool:
    return not h.healthy and h.replies_ok == 0


def test_gate_sends_a_command_only_while_fresh_and_zero_after_any_gap():
    gate = FreshnessGate(max_age_s=0.04, watchdog_ms=250)
    assert not gate.frame(1, 0.0).enabled  # nothing computed yet
    drive = WheelCommand(0.4, 0.4, enable=True)
    gate.submit(drive, 0.0)
    f = gate.frame(2, 0.01)
    assert f.enabled and f.left_duty_pm == 400 and f.cycle == 1 and f.age_ms == 10
    assert f.max_age_ms == 40 and f.watchdog_ms == 250
    assert gate.frame(3, 0.03).enabled  # 30 ms old: still fresh
    stale = gate.frame(4, 0.05)  # 50 ms old: nobody computed it again
    assert not stale.enabled and stale.left_duty_pm == 0 and stale.age_ms == 50
    gate.submit(drive, 0.06)
    assert gate.frame(5, 0.07).cycle == 2
    gate.submit(drive, 0.2)
    # fresh command, but the sender itself was silent 130 ms (a stalled event loop): zero first
    first = gate.frame(6, 0.2)
    assert not first.enabled and first.left_duty_pm == 0
    assert gate.frame(7, 0.21).enabled
    assert not gate.frame(8, 0.22, healthy=False).enabled  # link unhealthy: zero
    assert gate.zeroed_frames == 3


def test_a_command_older_than_the_age_byte_can_say_is_never_within_the_units_limit():
    """With a slow link (command period up to 0.2 s: the master's limit 400 ms) a command
    260–400 ms old goes out stamped 255 ms ("255 or more"); with the limit byte clipped to 255
    too the unit's backstop passed it (255 <= 255)."""
    from omnid.devices import cu_codec as codec

    gate = FreshnessGate(max_age_s=0.4)
    gate.frame(1, 0.0)
    gate.submit(WheelCommand(0.4, 0.4, enable=True), 0.0)
    gate.frame(2, 0.15)
    old = gate.frame(3, 0.3)  # 300 ms old: within the master's 400 ms
    assert old.enabled and old.age_ms == codec.AGE_SATURATED_MS
    assert old.age_ms > old.max_age_ms  # the unit refuses it


def test_link_zeroes_a_command_no_live_cycle_renews(emu: ControlUnitEmulator):
    """The control loop dies (no more submits) while the link task goes on: the wheels get
    zero within two command periods, from the link's frames, not from the unit's watchdog."""

    async def main():
        link = ControlUnitLink(settings(emu.path or "", unit_watchdog_s=0.5))
        await link.start()
        try:
            await wait_for(lambda: link.health.healthy)
            spy = WireSpy(emu)
            cycle = asyncio.create_task(control_cycle(link))
            link.set_command(WheelCommand(0.5, 0.5, enable=True))
            await wait_for(lambda: emu.applied_duty == (0.5, 0.5))
            cycle.cancel()  # the loop is gone; the link is not
            t_dead = time.monotonic()
            await wait_for(lambda: emu.applied_duty == (0.0, 0.0))
            zero_at = next(t for t, f in spy.frames if t >= t_dead and not f.enabled)
            assert zero_at - t_dead < 0.5  # generous (loaded machine); by design ≤ 2 periods
            n = emu.commands_received
            await asyncio.sleep(0.2)
            assert emu.commands_received > n  # frames keep flowing, all of them zero
            assert all(not f.enabled and f.left_duty_pm == 0 for _, f in spy.after(zero_at))
            assert emu.watchdog_trips == 0 and link.health.zeroed_frames > 0
        finally:
            await link.stop()

    asyncio.run(main())


def test_after_an_event_loop_stall_the_first_frame_is_zero(emu: ControlUnitEmulator):
    async def main():
        link = ControlUnitLink(settings(emu.path or "", unit_watchdog_s=0.25))
        await link.start()
        cycle = asyncio.create_task(control_cycle(link))
        try:
            await wait_for(lambda: link.health.healthy)
            spy = WireSpy(emu)
            link.set_command(WheelCommand(0.5, 0.5, enable=True))
            await wait_for(lambda: emu.applied_duty == (0.5, 0.5))
            time.sleep(0.6)  # the whole event loop stalls; the unit's watchdog stops the motors
            t_back = time.monotonic()
            assert emu.applied_duty == (0.0, 0.0) and emu.watchdog_trips == 1
            await wait_for(lambda: len(spy.after(t_back)) >= 3)
            first = spy.after(t_back)[0][1]
            assert not first.enabled and first.left_duty_pm == first.right_duty_pm == 0
            # the control cycle is alive again: the chair drives on (the core decides whether
            # the rider's demand is still live; here the stand-in re-submits it)
            await wait_for(lambda: emu.applied_duty == (0.5, 0.5))
            assert emu.stale_refusals == 0  # the unit was re-armed by that zero frame
        finally:
            cycle.cancel()
            await link.stop()

    asyncio.run(main())


def test_a_restarted_master_counting_from_zero_again_is_not_a_replay():
    now = [0.0]
    emu = ControlUnitEmulator(clock=lambda: now[0])

    def send(cycle: int, enable: bool = True) -> codec.ReplyFrame:
        cmd = WheelCommand(0.5, 0.5, enable=enable)
        rep = codec.decode_frame(
            emu.handle_bytes(codec.encode_command(cmd.to_frame(1, 250, cycle)))
        )
        assert isinstance(rep, codec.ReplyFrame)
        return rep

    send(900, enable=False)
    assert send(901).left_applied_pm == 500
    now[0] = 0.5  # the master died (watchdog), systemd restarted it: its cycles start again
    send(1, enable=False)
    now[0] = 0.52
    assert send(2).left_applied_pm == 500
    assert send(0).left_applied_pm == 0  # a frame older than the stop is still a replay


class AdapterWithTxQueue(LoopTransport):
    """A pipe end behind a serial adapter's transmit queue: while the line is held (``held``:
    flow control asserted, a USB adapter not scheduled), written bytes wait in ``queue``; when it
    is released they go out in order. ``reset_output`` discards the queue, as TCOFLUSH does on a
    real port. (On a pty nothing waits: the other side's buffer is the line.)"""

    held = False

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.queue = bytearray()

    async def _write_raw(self, data: bytes) -> None:
        self.queue += data
        if not self.held:
            self.release()

    def release(self) -> None:
        self.held = False
        data, self.queue = bytes(self.queue), bytearray()
        self.peer.feed(data)

    def reset_output(self) -> int:
        dropped = len(self.queue)
        self.queue.clear()
        return dropped


def test_frames_the_line_did_not_carry_are_never_sent_later():
    """A frame the line has not carried is discarded before the next one is written, not queued
    behind it. Without that, when the line moves again it delivers a backlog of old commands —
    forward duties no live cycle computed just now — one after the other.

    The line is held for 0.3 s (about 30 command periods) while the link sends a forward
    command, then released; the unit may see at most the one frame written last.
    """

    async def main() -> tuple[int, int, ControlUnitHealth]:
        adapter, unit_end = AdapterWithTxQueue("adapter"), LoopTransport("unit")
        adapter.peer, unit_end.peer = unit_end, adapter
        unit = ControlUnitEmulator()
        parser = codec.FrameParser(accept=(codec.TYPE_COMMAND,))

        async def serve() -> None:
            while True:
                data = await unit_end.read_some(256, 5.0)
                for frame in parser.feed(data):
                    await unit_end.write(unit.handle_bytes(codec.encode_command(frame)))

        server = asyncio.create_task(serve())
        link = ControlUnitLink(settings("adapter"), transport_factory=lambda: adapter)
        await link.start()
        cycle = asyncio.create_task(control_cycle(link))
        try:
            await wait_for(lambda: link.health.healthy)
            link.set_command(WheelCommand(left_duty=0.5, right_duty=0.5, enable=True))
            await wait_for(lambda: link.health.replies_ok >= 5)
            adapter.held = True
            sent_before = link.health.commands_sent
            await asyncio.sleep(0.3)
            sent_held = link.health.commands_sent - sent_before
            backlog = codec.FrameParser(accept=(codec.TYPE_COMMAND,)).feed(adapter.queue)
            adapter.release()
            await wait_for(lambda: link.health.healthy)  # and the link recovers
            return len(backlog), sent_held, link.health
        finally:
            cycle.cancel()
            server.cancel()
            await link.stop()

    delivered, sent_held, h = asyncio.run(main())
    assert sent_held >= 5  # the link kept sending while the line was held
    assert delivered <= 1, f"{delivered} frames of {sent_held} held ones reached the unit"
    assert h.unsent_bytes_discarded > 0


def test_urgent_commands_keep_the_period_grid_and_never_silence_the_link(
    emu: ControlUnitEmulator,
):
    """Urgent commands (a rider's key presses, each one sent at once) must not push the link's
    next regular frame further away: the period grid stays. Each urgent frame used to move the
    next grid point one period on, so a burst of them (kicks every 5 ms over 0.3 s) left the
    link silent for about as long as the burst lasted, and the unit's watchdog stopped the chair
    with the link healthy and the control loop computing a fresh command every cycle."""

    async def main() -> tuple[float, int]:
        link = ControlUnitLink(settings(emu.path or "", unit_watchdog_s=0.1))
        await link.start()
        cycle = asyncio.create_task(control_cycle(link))
        try:
            await wait_for(lambda: link.health.healthy)
            link.set_command(WheelCommand(0.3, 0.3, enable=True))
            await wait_for(lambda: emu.applied_duty == (0.3, 0.3))
            spy = WireSpy(emu)
            trips0 = emu.watchdog_trips
            end = time.monotonic() + 0.3
            while time.monotonic() < end:  # the rider's command changes: urgent, every 5 ms
                link.set_command(link.command, urgent=True)
                await asyncio.sleep(0.005)
            t_end = time.monotonic()
            await asyncio.sleep(0.3)  # the regular cycle goes on (control_cycle, not urgent)
            times = [t_end] + [t for t, _ in spy.after(t_end)]
            gap = max(b - a for a, b in itertools.pairwise(times))
            return gap, emu.watchdog_trips - trips0
        finally:
            cycle.cancel()
            await link.stop()

    gap, trips = asyncio.run(main())
    # a frame every 10 ms period; 80 ms allows for a loaded machine, not for a silent link
    assert gap < 0.08, f"no frame for {gap * 1000:.0f} ms after the urgent commands"
    assert trips == 0, "the unit's watchdog stopped the chair behind a healthy link"


def test_a_unit_reset_whose_reset_reply_was_lost_does_not_make_odometry_jump(caplog):
    """RESET is latched: reported once, in the reply to the next valid command. A unit that
    restarts (a brown-out under motor current) and whose first reply is lost (one corrupted
    reply, or one past its deadline on a busy machine) then answers with counters restarted
    near 0 and no RESET flag. The link used to unwrap that as travel: tens of thousands of
    clocks backwards in one reply (here 1.5 km), which the daemon's odometry turns into a jump
    of the chair's pose that throws every remembered obstacle out of the local map. A change no
    wheel can make in the time since the previous reply is a reset: rebased and logged."""
    caplog.set_level(logging.WARNING, "omnid.devices.control_unit")

    async def main() -> tuple[int, int, int, int]:
        a, b = pipe_pair()
        units = [ControlUnitEmulator(clock_offset=50_000)]  # a unit that has counted a while
        parser = codec.FrameParser(accept=(codec.TYPE_COMMAND,))

        async def serve() -> None:
            while True:
                data = await b.read_some(256, 5.0)
                for frame in parser.feed(data):
                    reply = units[-1].handle_bytes(codec.encode_command(frame))
                    if reply:
                        await b.write(reply)

        server = asyncio.create_task(serve())
        link = ControlUnitLink(settings("pipe"), transport_factory=lambda: a)
        await link.start()
        try:
            await wait_for(lambda: link.health.replies_ok >= 3)
            before = link.status
            assert before is not None and before.left_clocks == 50_000
            fresh = ControlUnitEmulator()  # power-up: counters at 0, RESET latched
            fresh.corrupt_replies(1)  # ... and its first reply, the one with RESET, is lost
            units.append(fresh)
            ok = link.health.replies_ok
            await wait_for(lambda: link.health.replies_ok >= ok + 3)
            after = link.status
            assert after is not None
            return before.left_clocks, after.left_clocks, before.right_clocks, after.right_clocks
        finally:
            await link.stop()
            server.cancel()

    l0, l1, r0, r1 = asyncio.run(main())
    assert abs(l1 - l0) <= 2 and abs(r1 - r0) <= 2, f"odometry jumped {l1 - l0}, {r1 - r0} clocks"
    assert "reset" in caplog.text
