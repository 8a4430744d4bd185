"""An emulated control unit: speaks ``docs/protocol.md`` on a real pty (or an in-process pipe).

It applies the commanded duties to a *plant* — anything with ``step(left_duty, right_duty, dt_s)``
and ``clocks() -> (left, right)`` (total clocks, + forward); the default :class:`MotorPlant` is a
first-order motor model (30 rpm at full duty, 15 clocks per turn, wheel circumference 471 mm,
thesis 4.3.2.2–4.3.2.3) and the simulator passes the chair's dynamics instead. It switches the
laser relay with a small delay, enforces the unit's own motor-stop watchdog and the command
freshness rules of protocol version 2 (a stale, replayed or endlessly repeated command brakes;
after power-up, a watchdog trip or such a brake, ENABLE is obeyed only after a zero frame), and
injects faults: ``drop_replies``, ``corrupt_replies``, ``stall``, ``die`` (close the pty =
unplug), ``recover``.

Time is integrated lazily from an injectable monotonic ``clock`` at every received byte chunk
and every query, so no ticking thread is needed and the simulator can run it on its own clock.

Bench use: ``omnid emulate control-unit --pty`` prints the pty path and serves until interrupted.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import logging
import math
import os
import random
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

from omnid.devices import cu_codec as codec
from omnid.devices.pty import PtyPort
from omnid.devices.transport import LoopTransport
from omnid.errors import DeviceError
from omnid.logs import LogThrottle

__all__ = ["ControlUnitEmulator", "MotorPlant", "Plant", "WireSpy", "add_arguments", "run"]

log = logging.getLogger(__name__)

CLOCKS_PER_TURN = 15
WHEEL_CIRCUMFERENCE_MM = 471.0
_MAX_STEP_S = 0.005


class Plant(Protocol):
    """What the emulator drives: the wheels (a motor model, or the simulator's chair)."""

    def step(self, left_duty: float, right_duty: float, dt_s: float) -> None: ...

    def clocks(self) -> tuple[int, int]: ...


class MotorPlant:
    """Two first-order DC motors: wheel speed follows ``duty · full_duty_rpm`` with ``time_constant_s``.

    ``clocks()`` counts holes passed: floor(turns · 15), + forward (thesis 4.3.2.3).
    """

    def __init__(self, full_duty_rpm: float = 30.0, time_constant_s: float = 0.15) -> None:
        self.full_duty_rpm = full_duty_rpm
        self.time_constant_s = time_constant_s
        self.speed_rps = [0.0, 0.0]  # wheel turns per second
        self.turns = [0.0, 0.0]

    def step(self, left_duty: float, right_duty: float, dt_s: float) -> None:
        """Advance ``dt_s`` seconds with the duties held (exact first-order solution)."""
        a = math.exp(-dt_s / self.time_constant_s)
        for i, duty in enumerate((left_duty, right_duty)):
            target = duty * self.full_duty_rpm / 60.0
            v0 = self.speed_rps[i]
            # exact integral of v(t) = target + (v0 - target) e^{-t/τ}
            self.turns[i] += target * dt_s + (v0 - target) * self.time_constant_s * (1 - a)
            self.speed_rps[i] = target + (v0 - target) * a

    def clocks(self) -> tuple[int, int]:
        return (
            math.floor(self.turns[0] * CLOCKS_PER_TURN),
            math.floor(self.turns[1] * CLOCKS_PER_TURN),
        )


def _wrap32(v: int) -> int:
    return ((v + 2**31) % 2**32) - 2**31


class ControlUnitEmulator:
    """The control unit of ``docs/protocol.md``, served on a pty or fed bytes directly.

    Parameters
    ----------
    plant:
        The wheels; default :class:`MotorPlant`.
    clock:
        Monotonic time source, s (the simulator may pass its own).
    laser_delay_s:
        Relay switching delay; the reply reports the relay, not the request (10 ms: within
        the shipped ``perception.laser_switch_latency_s``, 18 ms with the command path).
    laser_jitter_s:
        Each switch takes a further uniform 0…``laser_jitter_s`` (drawn from ``seed``).
    default_watchdog_s:
        Watchdog used when a command says ``WATCHDOG_MS = 0``.
    clock_offset:
        Initial raw value of both counters (set near 2**31 to exercise wrap-around).
    """

    def __init__(
        self,
        plant: Plant | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        laser_delay_s: float = 0.01,
        laser_jitter_s: float = 0.0,
        seed: int = 0,
        default_watchdog_s: float = 0.25,
        clock_offset: int = 0,
        name: str = "cu-emulator",
    ) -> None:
        self.plant: Plant = plant if plant is not None else MotorPlant()
        self._clock = clock
        self.laser_delay_s = laser_delay_s
        self.laser_jitter_s = laser_jitter_s
        self._laser_rng = random.Random(seed)
        self._laser_delay_now = laser_delay_s
        #: (t_s, on): when the relay actually switched (for the simulator's exposure model)
        self.laser_switches: deque[tuple[float, bool]] = deque(maxlen=256)
        self.default_watchdog_s = default_watchdog_s
        self.clock_offset = clock_offset
        self.name = name
        self._throttle = LogThrottle(log, interval_s=5.0, clock=clock)
        self._lock = threading.RLock()
        self._parser = codec.FrameParser(accept=(codec.TYPE_COMMAND,))
        self._t = clock()
        self._duty = (0.0, 0.0)
        self._enabled = False
        self._laser_request = False
        self._laser_on = False
        self._laser_change_t = self._t
        self._last_cmd_t: float | None = None
        self._watchdog_s = default_watchdog_s
        self._latched = codec.FAULT_RESET
        self._armed = False  # ENABLE is obeyed only after a zero frame (power-up, trips)
        self._cycle: int | None = None  # the newest command cycle seen, and since when
        self._cycle_since = self._t
        self.stale_refusals = 0
        self.last_refusal = ""
        self._injected_faults = 0
        self._rx_errors_seen = 0
        self.watchdog_trips = 0
        self.commands_received = 0
        self.replies_sent = 0
        # fault injection
        self._drop = 0  # replies still to drop; -1 = all
        self._corrupt = 0
        self._stalled = False
        self._dead = False
        self._pty: PtyPort | None = None
        self._pipe: LoopTransport | None = None
        self._pipe_task: asyncio.Task[None] | None = None

    # -- time ----------------------------------------------------------------------------
    def _advance(self, now: float) -> None:
        """Integrate the plant up to ``now``, applying the watchdog and the laser relay delay."""
        if now <= self._t:
            return
        if self._last_cmd_t is not None:
            trip_t = self._last_cmd_t + self._watchdog_s
            if trip_t < now:
                self._integrate(max(trip_t, self._t))
                self._trip_watchdog(trip_t)
        self._integrate(now)
        if (
            self._laser_on != self._laser_request
            and now - self._laser_change_t >= self._laser_delay_now
        ):
            self._laser_on = self._laser_request
            self.laser_switches.append(
                (self._laser_change_t + self._laser_delay_now, self._laser_on)
            )

    def _integrate(self, until: float) -> None:
        dt = until - self._t
        left, right = self._duty if self._enabled else (0.0, 0.0)
        while dt > 1e-12:
            h = min(dt, _MAX_STEP_S)
            self.plant.step(left, right, h)
            dt -= h
        self._t = max(self._t, until)

    def _trip_watchdog(self, at: float) -> None:
        self._duty = (0.0, 0.0)
        self._enabled = False
        if self._laser_request:
            self._laser_request = False
            self._laser_change_t = at
            self._laser_delay_now = self.laser_delay_s
        self._latched |= codec.FAULT_WATCHDOG
        self._armed = False
        self.watchdog_trips += 1
        self._last_cmd_t = None
        self._throttle.info("watchdog", "%s: watchdog tripped, motors stopped", self.name)

    # -- protocol ------------------------------------------------------------------------
    def handle_bytes(self, data: bytes) -> bytes:
        """Feed bytes from the master; returns the reply bytes to send (possibly empty)."""
        with self._lock:
            now = self._clock()
            self._advance(now)
            if self._stalled or self._dead:
                return b""
            out = bytearray()
            before = self._parser.crc_errors + self._parser.malformed
            frames = self._parser.feed(data)
            rejected = self._parser.crc_errors + self._parser.malformed - before
            if rejected:
                self._rx_errors_seen += rejected
                self._latched |= codec.FAULT_RX_ERROR
            for frame in frames:
                assert isinstance(frame, codec.CommandFrame)
                out += self._obey(frame, now)
            return bytes(out)

    def _refusal(self, cmd: codec.CommandFrame, now: float) -> str:
        """Why an ENABLE command must not drive (protocol "Freshness"), or ""."""
        max_age_s = (cmd.max_age_ms or codec.MAX_AGE_DEFAULT_MS) / 1000
        if not self._armed:
            return "ENABLE before a zero frame (after power-up, a watchdog trip or a refusal)"
        if cmd.age_ms / 1000 > max_age_s:
            return f"command {cmd.age_ms} ms old > {max_age_s * 1000:.0f} ms"
        if self._cycle is not None:
            ahead = codec.cycle_ahead(self._cycle, cmd.cycle)
            if ahead < 0:
                return f"cycle {cmd.cycle} older than {self._cycle} (replayed)"
            if ahead == 0 and now - self._cycle_since > max_age_s:
                return (
                    f"cycle {cmd.cycle} repeated for {(now - self._cycle_since) * 1000:.0f} ms "
                    f"> {max_age_s * 1000:.0f} ms"
                )
        return ""

    def _obey(self, cmd: codec.CommandFrame, now: float) -> bytes:
        self.commands_received += 1
        self._last_cmd_t = now
        self._watchdog_s = cmd.watchdog_ms / 1000 if cmd.watchdog_ms else self.default_watchdog_s
        drive = cmd.enabled
        if drive:
            why = self._refusal(cmd, now)
            if why:
                drive = False
                self._armed = False
                self._latched |= codec.FAULT_STALE_COMMAND
                self.stale_refusals += 1
                self.last_refusal = why
                self._throttle.warning("stale", "%s: command refused: %s", self.name, why)
        else:
            self._armed = True
        if not cmd.enabled:
            # a stop re-arms and re-synchronises: a restarted master counts from its own cycle
            if self._cycle != cmd.cycle:
                self._cycle, self._cycle_since = cmd.cycle, now
        elif self._cycle is None or codec.cycle_ahead(self._cycle, cmd.cycle) > 0:
            self._cycle, self._cycle_since = cmd.cycle, now
        self._enabled = drive
        self._duty = (cmd.left_duty, cmd.right_duty) if self._enabled else (0.0, 0.0)
        want_laser = bool(cmd.flags & codec.FLAG_LASER_ON)
        if want_laser != self._laser_request:
            self._laser_request = want_laser
            self._laser_change_t = now
            jitter = self._laser_rng.uniform(0.0, self.laser_jitter_s) if self.laser_jitter_s else 0
            self._laser_delay_now = self.laser_delay_s + jitter
        if self._drop:
            self._drop -= 1 if self._drop > 0 else 0
            return b""
        reply = codec.encode_reply(self._reply(cmd.seq))
        self.replies_sent += 1
        if self._corrupt:
            self._corrupt -= 1 if self._corrupt > 0 else 0
            b = bytearray(reply)
            b[len(b) // 2] ^= 0x10  # one flipped bit: the CRC must catch it
            reply = bytes(b)
        return reply

    def _reply(self, seq: int) -> codec.ReplyFrame:
        left, right = self.plant.clocks()
        faults = self._latched | self._injected_faults
        self._latched = 0
        l_app, r_app = self._duty if self._enabled else (0.0, 0.0)
        return codec.ReplyFrame(
            seq=seq,
            left_clocks=_wrap32(self.clock_offset + left),
            right_clocks=_wrap32(self.clock_offset + right),
            left_applied_pm=round(l_app * codec.DUTY_FULL_SCALE),
            right_applied_pm=round(r_app * codec.DUTY_FULL_SCALE),
            state=(codec.STATE_LASER_IS_ON if self._laser_on else 0)
            | (codec.STATE_DRIVE_ENABLED if self._enabled else 0),
            faults=faults,
            rx_errors=self._rx_errors_seen & 0xFF,
        )

    # -- observation (for tests and the simulator) ----------------------------------------
    def _now(self) -> None:
        with self._lock:
            self._advance(self._clock())

    @property
    def laser_on(self) -> bool:
        """The laser relay as actually switched, now."""
        with self._lock:
            self._now()
            return self._laser_on

    @property
    def applied_duty(self) -> tuple[float, float]:
        """Duties the drivers apply now (0 after brake or watchdog)."""
        with self._lock:
            self._now()
            return self._duty if self._enabled else (0.0, 0.0)

    @property
    def clocks(self) -> tuple[int, int]:
        """The plant's clock counters now (unwrapped, without ``clock_offset``)."""
        with self._lock:
            self._now()
            return self.plant.clocks()

    @property
    def rx_errors(self) -> int:
        return self._rx_errors_seen

    # -- fault injection -------------------------------------------------------------------
    def drop_replies(self, count: int | None = None) -> None:
        """Obey commands but send no reply: the next ``count`` replies, or all (None)."""
        self._drop = -1 if count is None else count

    def corrupt_replies(self, count: int | None = None) -> None:
        """Flip one bit in the next ``count`` replies (all if None): CRC errors at the master."""
        self._corrupt = -1 if count is None else count

    def inject_faults(self, faults: int) -> None:
        """Report these fault bits in every reply until ``recover`` (e.g. overcurrent)."""
        self._injected_faults = faults

    def stall(self) -> None:
        """Stop processing and answering (a hung unit); its watchdog still stops the motors."""
        self._stalled = True

    def die(self) -> None:
        """Unplug: close the pty master, so the driver's port reads fail."""
        self._dead = True
        if self._pty is not None:
            self._pty.unplug()
        if self._pipe is not None:
            self._pipe.close()

    def recover(self) -> None:
        """Clear every injected fault; after ``die`` a fresh pty appears at the same link path."""
        with self._lock:
            self._drop = self._corrupt = self._injected_faults = 0
            self._stalled = False
            self._parser.reset()
            if self._dead:
                self._dead = False
                if self._pty is not None:
                    self._pty.replug()

    # -- serving ---------------------------------------------------------------------------
    def _on_pty_data(self, data: bytes) -> None:
        out = self.handle_bytes(data)
        if out and self._pty is not None:
            self._pty.write(out)

    def open_pty(self, link_path: str | os.PathLike[str] | None = None) -> str:
        """Serve on a new pty; returns the path to configure as the driver's port.

        With ``link_path`` the path is a symlink that ``die``/``recover`` re-point (replug).
        """
        if self._pty is not None:
            raise DeviceError(f"{self.name}: already serving on {self._pty.path}")
        self._pty = PtyPort(self._on_pty_data, link_path=link_path, name=self.name)
        return self._pty.open()

    @property
    def path(self) -> str | None:
        return self._pty.path if self._pty is not None else None

    def serve_pipe(self, end: LoopTransport) -> asyncio.Task[None]:
        """Serve on one end of :func:`omnid.devices.transport.pipe_pair` (same event loop)."""
        self._pipe = end

        async def loop() -> None:
            while end.is_open:
                try:
                    data = await end.read_some(256, 0.5)
                except DeviceError:
                    return
                out = self.handle_bytes(data) if data else b""
                if out and end.is_open:
                    with contextlib.suppress(DeviceError):
                        await end.write(out)

        self._pipe_task = asyncio.get_running_loop().create_task(loop(), name=self.name)
        return self._pipe_task

    def close(self) -> None:
        """Stop serving."""
        if self._pty is not None:
            self._pty.close()
            self._pty = None
        if self._pipe is not None:
            self._pipe.close()
        if self._pipe_task is not None:
            self._pipe_task.cancel()

    def __enter__(self) -> ControlUnitEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WireSpy:
    """Records every command frame an emulated unit receives, with the monotonic time its bytes
    arrived — the bench's spy on the control-unit wire (``tools/fault_figures.py``, tests).

    It wraps ``emulator.handle_bytes`` and decodes the stream with its own parser, so it sees the
    frames even while the unit is stalled or dead. ``frames`` is bounded (``max_frames``).
    """

    def __init__(self, emulator: ControlUnitEmulator, max_frames: int = 200_000) -> None:
        self.frames: collections.deque[tuple[float, codec.CommandFrame]] = collections.deque(
            maxlen=max_frames
        )
        self._parser = codec.FrameParser(accept=(codec.TYPE_COMMAND,))
        inner = emulator.handle_bytes

        def spy(data: bytes) -> bytes:
            t = time.monotonic()
            for f in self._parser.feed(data):
                if isinstance(f, codec.CommandFrame):
                    self.frames.append((t, f))
            return inner(data)

        emulator.handle_bytes = spy  # type: ignore[method-assign]

    def after(self, t_s: float) -> list[tuple[float, codec.CommandFrame]]:
        """The frames received at or after monotonic ``t_s``, oldest first."""
        return [(t, f) for t, f in list(self.frames) if t >= t_s]

    def first_zero_after(self, t_s: float) -> float | None:
        """Time of the first zero-duty frame at or after ``t_s`` (None: none yet)."""
        for t, f in self.after(t_s):
            if f.left_duty_pm == 0 and f.right_duty_pm == 0:
                return t
        return None


# -- ``omnid emulate control-unit`` -----------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``omnid emulate control-unit``."""
    parser.add_argument(
        "--pty", action="store_true", help="serve on a new pseudo-terminal (default)"
    )
    parser.add_argument("--link", metavar="PATH", help="also make PATH a symlink to the pty")
    parser.add_argument("--rpm", type=float, default=30.0, help="wheel rpm at full duty (30)")
    parser.add_argument(
        "--laser-delay-s", type=float, default=0.02, help="laser relay switching delay (0.02 s)"
    )
    parser.add_argument(
        "--status-every-s", type=float, default=1.0, help="print state every N s (0: never)"
    )


def run(args: argparse.Namespace) -> int:
    """Serve an emulated control unit on a pty until interrupted; prints the path first."""
    emu = ControlUnitEmulator(MotorPlant(full_duty_rpm=args.rpm), laser_delay_s=args.laser_delay_s)
    path = emu.open_pty(args.link)
    print(path, flush=True)
    try:
        while True:
            time.sleep(args.status_every_s if args.status_every_s > 0 else 3600)
            if args.status_every_s > 0:
                l_clk, r_clk = emu.clocks
                ld, rd = emu.applied_duty
                print(
                    f"commands={emu.commands_received} duty=({ld:+.2f},{rd:+.2f}) "
                    f"clocks=({l_clk},{r_clk}) laser={'on' if emu.laser_on else 'off'} "
                    f"watchdog_trips={emu.watchdog_trips} rx_errors={emu.rx_errors}",
                    flush=True,
                )
    except KeyboardInterrupt:
        return 0
    finally:
        emu.close()
