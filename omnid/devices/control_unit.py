"""The control-unit link: wheel commands out, clock counters and faults back (SPEC §4).

:class:`ControlUnitLink` is the asyncio driver. Its own task sends a frame every
``command_period_s``, matches each reply to its command by sequence number, unwraps the int32
wheel clock counters into Python ints, counts errors (timeouts, CRC, sequence), and reconnects
with back-off when the port disappears (USB adapter unplugged). Wire format:
``docs/protocol.md`` via :mod:`omnid.devices.cu_codec`.

Freshness (:class:`FreshnessGate`): a frame carries the latest :class:`WheelCommand` only while a
live control cycle computed it within the last two command periods (``max_command_age_s``);
otherwise — no command yet, the control loop dead or late, the link itself stalled, the link
unhealthy — the frame is zero duty with ENABLE cleared. Every frame carries the command's cycle
number and age, so the unit refuses a stale or endlessly repeated command by itself too.

Fail safe: the link is *unhealthy* when the port is gone or ``max_missed_replies`` replies in a row
were missing or rejected. The moment that happens the link sends a zero frame,
:attr:`ControlUnitLink.status` returns ``None``, ``health.healthy`` is False and a warning is
logged, so the daemon stops the chair; the unit's own watchdog stops the motors if our frames
stop reaching it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from omnid.config import Settings, require, setting
from omnid.devices import cu_codec as codec
from omnid.devices.link import LinkHealth, PolledLink, require_reconnect
from omnid.devices.transport import Rs485Options, Transport, open_transport
from omnid.errors import DeviceError, ProtocolError

__all__ = [
    "ControlUnitHealth",
    "ControlUnitLink",
    "ControlUnitSettings",
    "ControlUnitStatus",
    "FreshnessGate",
    "WheelCommand",
]

log = logging.getLogger(__name__)

#: clocks per second no wheel reaches, driven or pushed (200 = 6.3 m/s; the motors: ≈ 8): a
#: larger counter change since the previous reply is a unit reset (docs/protocol.md)
MAX_CLOCK_RATE_HZ = 200.0
#: allowance for the reply timing in that bound, s
CLOCK_SLACK_S = 0.1


@dataclass(frozen=True)
class WheelCommand:
    """What the daemon wants the unit to do. Duties are signed, in [-1, 1] (negative = backward).

    ``enable=False`` brakes: the unit switches both motors off whatever the duties say.
    """

    left_duty: float = 0.0
    right_duty: float = 0.0
    laser_on: bool = False
    enable: bool = False

    def __post_init__(self) -> None:
        for name in ("left_duty", "right_duty"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ProtocolError(f"WheelCommand.{name}: expected a number, got {v!r}")
            if not (math.isfinite(v) and -1.0 <= v <= 1.0):
                raise ProtocolError(f"WheelCommand.{name}: {v!r} is not a duty in [-1, 1]")

    @classmethod
    def stop(cls, laser_on: bool = False) -> WheelCommand:
        """Both motors off (brake), laser as given."""
        return cls(0.0, 0.0, laser_on=laser_on, enable=False)

    def to_frame(
        self,
        seq: int,
        watchdog_ms: int = 0,
        cycle: int = 0,
        age_ms: int = 0,
        max_age_ms: int = 0,
    ) -> codec.CommandFrame:
        """The protocol frame for this command (``docs/protocol.md``, command payload)."""
        lmag, lrev = codec.duty_to_wire(self.left_duty)
        rmag, rrev = codec.duty_to_wire(self.right_duty)
        flags = (
            (codec.FLAG_LEFT_REVERSE if lrev else 0)
            | (codec.FLAG_RIGHT_REVERSE if rrev else 0)
            | (codec.FLAG_LASER_ON if self.laser_on else 0)
            | (codec.FLAG_ENABLE if self.enable else 0)
        )
        return codec.CommandFrame(seq, lmag, rmag, flags, watchdog_ms, cycle, age_ms, max_age_ms)


class FreshnessGate:
    """Which command a frame may carry (``docs/protocol.md``, "Freshness").

    :meth:`submit` is called by the control cycle with each command and the monotonic time it
    was computed; :meth:`frame` builds the next frame. It carries that command, numbered with
    its cycle and stamped with its age, only while it is at most ``max_age_s`` old, the link is
    healthy and the previous frame went out at most ``max_age_s`` ago; otherwise it is zero
    duty with ENABLE cleared (laser as last asked): no command yet, a dead or late control loop,
    a sender that stalled (the first frame after any stall is zero), an unhealthy link.
    Shared by :class:`ControlUnitLink` and the simulator's emulated control unit, so both put
    the same frames on the wire.
    """

    def __init__(self, max_age_s: float, watchdog_ms: int = 0) -> None:
        self.max_age_s = max_age_s
        self.watchdog_ms = watchdog_ms
        # below the saturated age (255 = "255 ms or more"): a command older than the byte can
        # say must fail the unit's check, not pass it as 255 <= 255
        self._max_age_ms = min(codec.AGE_SATURATED_MS - 1, max(1, round(max_age_s * 1000)))
        self.command = WheelCommand.stop()
        self.computed_s: float | None = None
        self.cycle = 0
        self._last_frame_s: float | None = None
        self.frames = 0
        self.zeroed_frames = 0  # frames sent as zero although a command asked to drive
        self.last_zero_reason = ""

    def submit(self, cmd: WheelCommand, computed_s: float) -> None:
        """A control cycle computed ``cmd`` at monotonic time ``computed_s``."""
        self.command = cmd
        self.computed_s = float(computed_s)
        self.cycle = (self.cycle + 1) % codec.CYCLE_MODULUS

    def age_s(self, now_s: float) -> float:
        """Age of the latest command at ``now_s`` (inf before the first)."""
        return math.inf if self.computed_s is None else now_s - self.computed_s

    def frame(self, seq: int, now_s: float, healthy: bool = True) -> codec.CommandFrame:
        """The frame to send now (see the class docstring)."""
        cmd = self.command
        age = self.age_s(now_s)
        gap = math.inf if self._last_frame_s is None else now_s - self._last_frame_s
        self._last_frame_s = now_s
        self.frames += 1
        reason = ""
        if age > self.max_age_s:
            reason = f"command {age * 1000:.0f} ms old"
        elif gap > self.max_age_s:
            reason = f"previous frame {gap * 1000:.0f} ms ago (sender stalled)"
        elif not healthy:
            reason = "link unhealthy"
        if reason and (cmd.enable or cmd.left_duty or cmd.right_duty):
            self.zeroed_frames += 1
            self.last_zero_reason = reason
        if reason:
            cmd = WheelCommand.stop(laser_on=cmd.laser_on)
        age_ms = codec.AGE_SATURATED_MS if not math.isfinite(age) else round(age * 1000)
        return cmd.to_frame(
            seq,
            self.watchdog_ms,
            cycle=self.cycle,
            age_ms=min(max(age_ms, 0), codec.AGE_SATURATED_MS),
            max_age_ms=self._max_age_ms,
        )


@dataclass(frozen=True)
class ControlUnitStatus:
    """One reply of the unit, with the wheel clock counters unwrapped into unbounded ints.

    ``left_clocks`` / ``right_clocks``: clocks since the link first heard the unit (31.4 mm of
    wheel travel each, + forward). ``laser_on``: the relay as actually switched. ``faults``: the
    protocol's fault bits (``cu_codec.FAULT_*``). ``timestamp_s``: monotonic receive time, s.
    """

    seq: int
    left_clocks: int
    right_clocks: int
    laser_on: bool
    faults: int
    timestamp_s: float
    left_applied_duty: float = 0.0
    right_applied_duty: float = 0.0
    drive_enabled: bool = False

    @property
    def fault_names(self) -> tuple[str, ...]:
        return codec.fault_names(self.faults)

    @classmethod
    def from_reply(
        cls, rep: codec.ReplyFrame, left_clocks: int, right_clocks: int, timestamp_s: float
    ) -> ControlUnitStatus:
        """The status a decoded reply gives, with clock counters already unwrapped."""
        return cls(
            seq=rep.seq,
            left_clocks=left_clocks,
            right_clocks=right_clocks,
            laser_on=bool(rep.state & codec.STATE_LASER_IS_ON),
            faults=rep.faults,
            timestamp_s=timestamp_s,
            left_applied_duty=rep.left_applied_pm / codec.DUTY_FULL_SCALE,
            right_applied_duty=rep.right_applied_pm / codec.DUTY_FULL_SCALE,
            drive_enabled=bool(rep.state & codec.STATE_DRIVE_ENABLED),
        )


@dataclass(frozen=True)
class ControlUnitSettings(Settings):
    """Settings of the control-unit link (section ``control_unit`` of the daemon's YAML).

    ``port``: a device path (``/dev/serial/by-id/...``) or ``loop://``. ``unit_watchdog_s`` is sent
    in every command (the unit stops the motors after that long without one).
    """

    port: str = "/dev/omnid-control-unit"  # the udev name (etc/udev)
    baudrate: int = setting(115200, 9600, 921600)
    command_period_s: float = setting(0.02, 0.005, 0.2)
    # a reply later than this counts as missed (a reply takes ≈ 5.3 ms at 115200 baud)
    reply_timeout_s: float = setting(0.010, 0.002, 0.1)
    unit_watchdog_s: float = setting(0.25, 0.02, 2.0)  # protocol: WATCHDOG_MS 20–2000
    max_missed_replies: int = setting(2, 1, 3)
    rs485: Rs485Options | None = None
    reconnect_initial_s: float = setting(0.05, 0.01, 10.0)
    reconnect_max_s: float = setting(1.0, 0.01, 60.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(bool(self.port), "port", "must name a device path or loop://")
        require(
            self.baudrate in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600),
            "baudrate",
            f"{self.baudrate} is not a standard rate (9600 … 921600)",
        )
        require(
            self.reply_timeout_s < self.command_period_s,
            "reply_timeout_s",
            "must be shorter than command_period_s",
        )
        require(
            self.unit_watchdog_s >= 2 * self.command_period_s,
            "unit_watchdog_s",
            "must be at least two command periods, or the unit trips between commands",
        )
        require_reconnect(self.reconnect_initial_s, self.reconnect_max_s)

    @property
    def max_command_age_s(self) -> float:
        """The oldest command a frame may carry: two command periods (docs/protocol.md)."""
        return 2.0 * self.command_period_s


@dataclass
class ControlUnitHealth(LinkHealth):
    """How the link is doing; a snapshot is returned by :attr:`ControlUnitLink.health`.

    ``connected``, ``port_errors``, ``reconnects`` and ``last_error`` come from
    :class:`~omnid.devices.link.LinkHealth`.
    """

    healthy: bool = False
    last_reply_age_s: float | None = None
    commands_sent: int = 0
    replies_ok: int = 0
    timeouts: int = 0
    crc_errors: int = 0
    malformed: int = 0
    seq_errors: int = 0
    late_bytes_discarded: int = 0
    unsent_bytes_discarded: int = 0  # old frames the line had not carried (0 where uncounted)
    consecutive_missed: int = 0
    unit_faults: int = 0
    unit_rx_errors: int = 0
    zeroed_frames: int = 0  # frames sent as zero because the command was stale / link unhealthy
    fault_history: list[str] = field(default_factory=list)

    def copy(self) -> ControlUnitHealth:
        return ControlUnitHealth(**{**self.__dict__, "fault_history": list(self.fault_history)})


class ControlUnitLink(PolledLink[ControlUnitHealth]):
    """Asyncio driver of the control unit (see module docstring).

    ``on_status`` (optional) is called in the event loop with each new status.
    ``transport_factory`` (optional, for in-process emulators) replaces :func:`open_transport`.
    The task, period grid, reconnect back-off and stop come from
    :class:`~omnid.devices.link.PolledLink`.
    """

    device_name = "control unit"
    task_name = "control-unit-link"
    _log = log

    def __init__(
        self,
        settings: ControlUnitSettings,
        on_status: Callable[[ControlUnitStatus], None] | None = None,
        transport_factory: Callable[[], Transport] | None = None,
    ) -> None:
        super().__init__(
            transport_factory
            or (
                lambda: open_transport(
                    settings.port, baudrate=settings.baudrate, rs485=settings.rs485
                )
            ),
            ControlUnitHealth(),
            period_s=settings.command_period_s,
            reconnect_initial_s=settings.reconnect_initial_s,
            reconnect_max_s=settings.reconnect_max_s,
        )
        self.settings = settings
        self._on_status = on_status
        self._gate = FreshnessGate(
            settings.max_command_age_s, round(settings.unit_watchdog_s * 1000)
        )
        self._parser = codec.FrameParser(accept=(codec.TYPE_REPLY,))
        self._seq = 0
        self._status: ControlUnitStatus | None = None
        self._last_raw: tuple[int, int] | None = None
        self._unwrapped = (0, 0)
        self._last_reply_t: float | None = None

    # -- public API (start/stop: PolledLink) ---------------------------------------------
    def set_command(
        self, cmd: WheelCommand, urgent: bool = False, computed_s: float | None = None
    ) -> None:
        """Make ``cmd``, computed by a control cycle at monotonic ``computed_s`` (default: now),
        the command the next frames carry while it is fresh (:class:`FreshnessGate`);
        ``urgent``: send it now (the period grid stays; a rider's new command need not wait up
        to a period)."""
        if not isinstance(cmd, WheelCommand):
            raise TypeError(f"set_command expects a WheelCommand, got {type(cmd).__name__}")
        self._gate.submit(cmd, time.monotonic() if computed_s is None else computed_s)
        if urgent:
            self._wake_up()

    def stop_now(self) -> None:
        """Send a zero frame at once (a fault: the control loop failed or is gone)."""
        self.set_command(WheelCommand.stop(laser_on=self._gate.command.laser_on), urgent=True)

    @property
    def command(self) -> WheelCommand:
        """The latest command the control cycle submitted (frames carry it only while fresh)."""
        return self._gate.command

    @property
    def gate(self) -> FreshnessGate:
        return self._gate

    @property
    def status(self) -> ControlUnitStatus | None:
        """The latest status while the link is healthy; ``None`` when it is not (stop the chair).

        Also ``None`` (logged once) when the link task is not running or the newest reply is
        older than ``unit_watchdog_s`` — by then the unit has stopped the motors by itself — so a
        stuck or dead task cannot leave a stale status looking healthy.
        """
        st = self._status
        if st is None or not self._health.healthy:
            return None
        age_s = time.monotonic() - st.timestamp_s
        if self._task is None or self._task.done():
            self._set_unhealthy("link task not running")
            return None
        if age_s > self.settings.unit_watchdog_s:
            self._set_unhealthy(f"newest reply {age_s * 1000:.0f} ms old (link task stuck?)")
            return None
        return st

    @property
    def last_status(self) -> ControlUnitStatus | None:
        """The latest status ever received (also while unhealthy), for diagnostics and odometry."""
        return self._status

    @property
    def health(self) -> ControlUnitHealth:
        """A snapshot of connection state, last reply age and error counters."""
        self.status  # noqa: B018 - applies the task/age rule to ``healthy``
        h = self._health.copy()
        h.zeroed_frames = self._gate.zeroed_frames
        if self._last_reply_t is not None:
            h.last_reply_age_s = time.monotonic() - self._last_reply_t
        return h

    # -- internals -----------------------------------------------------------------------
    def _next_frame(self) -> codec.CommandFrame:
        self._seq = (self._seq + 1) & 0xFF
        return self._gate.frame(self._seq, time.monotonic(), healthy=self._health.healthy)

    def _set_unhealthy(self, reason: str, warn: bool = True) -> None:
        h = self._health
        h.last_error = reason
        if h.healthy:
            h.healthy = False
            h.fault_history.append(reason)
            del h.fault_history[:-20]
            if warn:
                self._throttle.warning("unhealthy", "control unit link unhealthy: %s", reason)
            self._wake_up()  # the next frame (zero: unhealthy) goes out now

    def _missed(self, reason: str) -> None:
        h = self._health
        h.consecutive_missed += 1
        h.last_error = reason
        if h.healthy and h.consecutive_missed >= self.settings.max_missed_replies:
            self._set_unhealthy(f"{h.consecutive_missed} replies missed in a row ({reason})")

    def _accept(self, rep: codec.ReplyFrame, now: float) -> None:
        h = self._health
        raw = (rep.left_clocks, rep.right_clocks)
        if self._last_raw is None:
            self._unwrapped = raw
        else:
            dl = codec.unwrap_int32(self._last_raw[0], raw[0])
            dr = codec.unwrap_int32(self._last_raw[1], raw[1])
            # RESET is reported once: if that reply was lost, counters restarted near 0 are
            # recognised by a change no wheel can make in the time since the previous reply
            since_s = 0.0 if self._last_reply_t is None else max(now - self._last_reply_t, 0.0)
            limit = MAX_CLOCK_RATE_HZ * (since_s + CLOCK_SLACK_S)
            if rep.faults & codec.FAULT_RESET:
                self._throttle.warning(
                    "reset", "control unit reset: clock counters restarted, odometry rebased"
                )
            elif max(abs(dl), abs(dr)) > limit:
                self._throttle.warning(
                    "reset",
                    "control unit clock counters jumped by (%d, %d) in %.0f ms: taken as a "
                    "reset whose RESET reply was lost, odometry rebased",
                    dl,
                    dr,
                    since_s * 1000,
                )
            else:
                self._unwrapped = (self._unwrapped[0] + dl, self._unwrapped[1] + dr)
        self._last_raw = raw
        if rep.faults & ~codec.FAULT_RESET and rep.faults != h.unit_faults:
            self._throttle.warning(
                f"faults {rep.faults}",
                "control unit faults: %s",
                ", ".join(codec.fault_names(rep.faults)),
            )
        h.unit_faults = rep.faults
        h.unit_rx_errors = rep.rx_errors
        h.replies_ok += 1
        h.consecutive_missed = 0
        self._last_reply_t = now
        self._status = ControlUnitStatus.from_reply(rep, *self._unwrapped, now)
        if not h.healthy:
            h.healthy = True
            self._throttle.info("healthy", "control unit link healthy (seq %d)", rep.seq)
        if self._on_status is not None:
            try:
                self._on_status(self._status)
            except Exception:
                if self._throttle.error("callback", "control unit on_status callback failed"):
                    log.debug("on_status", exc_info=True)

    def _sync_parser_counters(self) -> None:
        h, p = self._health, self._parser
        h.crc_errors, h.malformed = p.crc_errors, p.malformed

    # -- PolledLink hooks ----------------------------------------------------------------
    def _on_open(self) -> None:
        self._parser.reset()

    def _port_error_reason(self, exc: DeviceError) -> str:
        return f"port error: {exc}"

    def _port_lost(self, port_name: str, reason: str) -> None:
        self._set_unhealthy(reason)

    def _before_stop(self) -> None:
        self._gate.submit(WheelCommand.stop(), time.monotonic())

    async def _farewell(self, transport: Transport) -> None:
        """A final stop command (best effort: the unit's watchdog stops the motors anyway)."""
        with contextlib.suppress(DeviceError, TimeoutError):
            async with asyncio.timeout(0.1):
                transport.reset_output()
                await transport.write(codec.encode_command(self._next_frame()))

    def _on_stopped(self) -> None:
        self._set_unhealthy("link stopped", warn=False)

    async def _exchange(self, loop: asyncio.AbstractEventLoop) -> bool:
        """One command → reply exchange; bookkeeping of every outcome. True: the unit answered."""
        t = self._transport
        assert t is not None
        h = self._health
        # Half duplex: whatever is still in the input is a late (part of a) reply to an earlier
        # command. Drop it, so that its tail cannot be parsed as a CRC error against this command.
        h.late_bytes_discarded += t.reset_input()
        # Nor may an older command that the line has not carried yet (adapter or unit not
        # reading) go out after this one: only the frame computed now is queued.
        h.unsent_bytes_discarded += t.reset_output()
        self._parser.reset()
        frame = self._next_frame()
        seq = frame.seq
        await t.write(codec.encode_command(frame))
        h.commands_sent += 1
        deadline = loop.time() + self.settings.reply_timeout_s
        crc_before = self._parser.crc_errors + self._parser.malformed
        got = False
        while not got:
            # at the deadline still take what is already buffered: a reply that came in time
            # while this task waited for the event loop is not a missed one
            remaining = deadline - loop.time()
            data = await t.read_some(256, max(remaining, 0.0))
            if not data:
                break
            for rep in self._parser.feed(data):
                if rep.seq == seq and isinstance(rep, codec.ReplyFrame):
                    self._accept(rep, time.monotonic())
                    got = True
                else:
                    h.seq_errors += 1
        self._sync_parser_counters()
        if not got:
            if self._parser.crc_errors + self._parser.malformed > crc_before:
                self._missed(f"reply to seq {seq} rejected (CRC/format)")
            else:
                h.timeouts += 1
                self._missed(
                    f"no reply to seq {seq} within {self.settings.reply_timeout_s * 1000:.0f} ms"
                )
            self._parser.reset()
        return got
