"""Joystick: dead zone and mapping, discrete commands, the evdev parser, a pty as event device."""

from __future__ import annotations

import asyncio
import os
import time
import tty

import pytest

from omnid.config import from_mapping
from omnid.devices.joystick import (
    ABS_X,
    ABS_Y,
    EV_ABS,
    EV_KEY,
    EV_SYN,
    INPUT_EVENT,
    SYN_DROPPED,
    SYN_REPORT,
    AxisMapper,
    EvdevParser,
    JoystickLink,
    JoystickReading,
    JoystickSettings,
    discrete_command,
    pack_event,
    shape_axis,
)
from omnid.errors import ConfigError, DeviceError


def test_shape_axis_dead_zone_and_proportional():
    assert shape_axis(0.1, 0.15) == 0.0
    assert shape_axis(-0.15, 0.15) == 0.0
    assert shape_axis(0.15 + 0.85 / 2, 0.15) == pytest.approx(0.5)
    assert shape_axis(-1.0, 0.15) == -1.0
    assert shape_axis(1.3, 0.15) == 1.0
    # continuous at the edge of the dead zone: no jump in speed
    assert shape_axis(0.1501, 0.15) < 1e-3


def test_mapper_orientation_and_range():
    m = AxisMapper(JoystickSettings(axis_min=0, axis_max=255, dead_zone=0.1))
    m.raw[ABS_Y] = 0  # pushed away
    m.raw[ABS_X] = 255  # pushed right
    r = m.reading(1.0)
    assert r.forward == 1.0 and r.turn == -1.0
    m.raw[ABS_Y] = 127.5 + 3  # noise around centre
    m.raw[ABS_X] = 127.5
    r = m.reading(2.0)
    assert r.forward == 0.0 and r.turn == 0.0 and r.timestamp_s == 2.0


def test_discrete_commands_follow_thesis_arrows():
    assert discrete_command(JoystickReading(0.9, 0.1, 0), 0.5) == "forward"
    assert discrete_command(JoystickReading(-0.9, 0.1, 0), 0.5) == "stop"
    assert discrete_command(JoystickReading(0.2, 0.8, 0), 0.5) == "left"
    assert discrete_command(JoystickReading(0.2, -0.8, 0), 0.5) == "right"
    assert discrete_command(JoystickReading(0.3, -0.3, 0), 0.5) is None


def test_reading_and_settings_validation():
    with pytest.raises(ValueError, match="forward"):
        JoystickReading(float("nan"), 0.0, 0.0)
    with pytest.raises(ValueError, match="turn"):
        JoystickReading(0.0, 1.5, 0.0)
    with pytest.raises(ConfigError, match="joystick.dead_zone"):
        from_mapping(JoystickSettings, {"dead_zone": 1.2}, "joystick")
    with pytest.raises(ConfigError, match="joystick.url"):
        JoystickLink(JoystickSettings(url="usb://x"))


def test_evdev_parser_on_byte_strings():
    data = pack_event(EV_ABS, ABS_X, -300, 12.25) + pack_event(EV_SYN, SYN_REPORT, 0, 12.5)
    assert INPUT_EVENT.size == 24
    p = EvdevParser()
    events = p.feed(data[:10]) + p.feed(data[10:30]) + p.feed(data[30:])
    assert [(e.type, e.code, e.value) for e in events] == [(EV_ABS, ABS_X, -300), (EV_SYN, 0, 0)]
    assert events[0].time_s == pytest.approx(12.25)


def _raw_pty() -> tuple[int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    os.close(slave)  # the link opens it by path, like /dev/input/eventN
    return master, path


async def _until(cond, timeout_s=10.0):
    """Poll ``cond`` until true; the deadline is generous (a loaded CI machine), not a claim."""
    t_end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < t_end, "condition not reached"
        await asyncio.sleep(0.005)


def test_evdev_link_over_a_pty_and_unplug():
    master, path = _raw_pty()
    s = JoystickSettings(
        url=f"evdev://{path}", axis_min=-100, axis_max=100, dead_zone=0.1, stale_after_s=0.1
    )

    async def go():
        link = JoystickLink(s)
        await link.start()
        assert link.latest is not None and link.latest.forward == 0.0  # centred at start
        os.write(master, pack_event(EV_ABS, ABS_Y, -100) + pack_event(EV_KEY, 288, 1))
        await asyncio.sleep(0.05)
        assert link.latest.forward == 0.0  # not committed before SYN_REPORT
        os.write(master, pack_event(EV_ABS, ABS_X, 55) + pack_event(EV_SYN, SYN_REPORT, 0))
        await _until(lambda: link.latest is not None and link.latest.forward == 1.0)
        assert link.latest.turn == pytest.approx(-0.5)
        # a held stick sends nothing, yet stays valid while the device is healthy: the link
        # re-vouches for the position (fresh timestamps long after the last event)
        t_held = time.monotonic()
        await asyncio.sleep(0.3)
        await _until(lambda: link.latest is not None and link.latest.timestamp_s > t_held + 0.25)
        assert link.latest is not None and link.latest.forward == 1.0
        os.close(master)  # unplugged: reads fail with EIO
        await _until(lambda: not link.connected)
        assert link.latest is None  # None as soon as the link knows, not after staleness
        await link.stop()
        return link.errors

    errors = asyncio.run(go())
    assert errors == 1


def test_missing_event_device_names_it():
    async def go():
        link = JoystickLink(JoystickSettings(url="evdev:///dev/input/event-none"))
        with pytest.raises(DeviceError, match="event-none"):
            await link.start()

    asyncio.run(go())


def test_unplugged_joystick_reconnects_centred(tmp_path):
    """A pty behind a re-pointed link path stands in for /dev/input/by-id/...-event-joystick."""
    from omnid.devices.pty import PtyPort

    port = PtyPort(lambda data: None, link_path=tmp_path / "event-joystick", name="joy")
    port.open()
    s = JoystickSettings(
        url=f"evdev://{port.path}",
        axis_min=-100,
        axis_max=100,
        stale_after_s=0.1,
        reconnect_initial_s=0.02,
        reconnect_max_s=0.05,
    )

    async def go():
        link = JoystickLink(s)
        await link.start()
        port.write(pack_event(EV_ABS, ABS_Y, -100) + pack_event(EV_SYN, SYN_REPORT, 0))
        await _until(lambda: link.latest is not None and link.latest.forward == 1.0)
        port.unplug()
        await _until(lambda: link.latest is None)
        await asyncio.sleep(0.1)  # reopen attempts fail while unplugged
        port.replug()
        await _until(lambda: link.latest is not None)
        centred = link.latest
        port.write(pack_event(EV_ABS, ABS_X, -100) + pack_event(EV_SYN, SYN_REPORT, 0))
        await _until(lambda: link.latest is not None and link.latest.turn == 1.0)
        await link.stop()
        return centred, link.reconnects

    try:
        centred, reconnects = asyncio.run(go())
    finally:
        port.close()
    assert centred.forward == 0.0 and centred.turn == 0.0  # held stick does not carry over
    assert reconnects == 1


def test_syn_dropped_invalidates_the_stick_until_resynced():
    """SYN_DROPPED: the kernel's event buffer overran and events were lost — here the stick's
    return to the centre, which evdev never sends again. The held-forward position must not stay
    valid: the stick is not valid until the next SYN_REPORT, then counts as centred (as after a
    replug) until it reports a new position. (The link kept the lost forward position valid.)"""
    master, path = _raw_pty()
    s = JoystickSettings(
        url=f"evdev://{path}", axis_min=-100, axis_max=100, dead_zone=0.1, stale_after_s=0.1
    )

    async def go():
        link = JoystickLink(s)
        await link.start()
        os.write(master, pack_event(EV_ABS, ABS_Y, -100) + pack_event(EV_SYN, SYN_REPORT, 0))
        await _until(lambda: link.latest is not None and link.latest.forward == 1.0)
        # the return to centre (ABS_Y 0, SYN_REPORT) was lost in the overrun
        os.write(master, pack_event(EV_SYN, SYN_DROPPED, 0) + pack_event(EV_ABS, ABS_Y, -100))
        await _until(lambda: link.dropped_syncs == 1)
        lost = link.latest
        await asyncio.sleep(0.15)  # the link keeps vouching for the device: still not valid
        still_lost = link.latest
        events = link.events
        # the kernel's next SYN_REPORT closes the dropped packet (its events are partial)
        os.write(master, pack_event(EV_ABS, ABS_X, 10) + pack_event(EV_SYN, SYN_REPORT, 0))
        await _until(lambda: link.events >= events + 2 and link.latest is not None)
        resynced = link.latest
        os.write(master, pack_event(EV_ABS, ABS_X, -100) + pack_event(EV_SYN, SYN_REPORT, 0))
        await _until(lambda: link.latest is not None and link.latest.turn == 1.0)
        await link.stop()
        return lost, still_lost, resynced

    try:
        lost, still_lost, resynced = asyncio.run(go())
    finally:
        os.close(master)
    assert lost is None, f"after SYN_DROPPED the lost position stays valid: {lost}"
    assert still_lost is None
    assert resynced.forward == 0.0 and resynced.turn == 0.0
