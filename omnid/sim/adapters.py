"""Device adapters of the simulator: the control unit and the tilt sensor on the virtual clock.

Each part comes in two kinds, chosen by :class:`~omnid.sim.settings.SimSettings`:

* ``emulator`` (the default) — the project's own emulators (``omnid.devices.emulators``), every
  command and reply passing as bytes through the protocol codecs, exactly as on the bench;
* ``direct`` — the same behaviour without the byte link (for probes and fast tests).

A control-unit adapter has ``exchange(command, now_s) -> status | None``,
``advance(now_s, dt_s)`` (the plant runs), ``laser_on``, ``laser_switches`` (when the laser
actually switched: what the simulated cameras expose by) and ``watchdog_trips``; a tilt adapter
has ``poll(now_s) -> TiltReading | None`` and ``unplugged``.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from typing import Any

from omnid.devices.control_unit import ControlUnitStatus
from omnid.devices.tilt import TiltReading
from omnid.sim.chair import Chair
from omnid.sim.rider import HeadScript
from omnid.sim.story import ReactiveRider

log = logging.getLogger(__name__)


# -- the control unit --------------------------------------------------------------------------


class DirectControlUnit:
    """The control unit's behaviour on the virtual clock, without the byte link.

    It applies the latest command's duties (zero unless ``enable``), switches the laser as told,
    stops both motors when no command arrived for ``watchdog_s`` (SPEC §4) and reports the
    plant's clocks (``SimSettings.control_unit: direct``, for probes and fast tests).
    """

    def __init__(self, plant: Chair, watchdog_s: float = 0.25) -> None:
        self.plant = plant
        self.watchdog_s = watchdog_s
        self.laser_on = False
        self.left_duty = 0.0
        self.right_duty = 0.0
        self.last_command_s = -math.inf
        self.seq = 0
        self.watchdog_trips = 0
        self.silent = False  # a hung unit: takes no command, sends no reply
        self.laser_switches: deque[tuple[float, bool]] = deque(maxlen=256)  # (t_s, on)

    def exchange(self, command: Any, now_s: float) -> Any:
        """Deliver one command at ``now_s``; return the reply (None while ``silent``)."""
        if self.silent:
            return None
        self.seq = (self.seq + 1) & 0xFFFF
        self.last_command_s = now_s
        on = bool(command.enable)
        self.left_duty = float(command.left_duty) if on else 0.0
        self.right_duty = float(command.right_duty) if on else 0.0
        if bool(command.laser_on) != self.laser_on:
            self.laser_switches.append((now_s, bool(command.laser_on)))
        self.laser_on = bool(command.laser_on)
        left, right = self.plant.clocks()
        return ControlUnitStatus(
            seq=self.seq,
            left_clocks=left,
            right_clocks=right,
            laser_on=self.laser_on,
            faults=0,
            timestamp_s=now_s,
        )

    def advance(self, now_s: float, dt_s: float) -> None:
        """Run the plant for ``dt_s`` from ``now_s`` (with the watchdog applied)."""
        if now_s - self.last_command_s > self.watchdog_s and (self.left_duty or self.right_duty):
            log.warning("control unit: no command for %.3f s; motors stopped", self.watchdog_s)
            self.watchdog_trips += 1
            self.left_duty = self.right_duty = 0.0
        self.plant.step(self.left_duty, self.right_duty, dt_s)


class EmulatedControlUnit:
    """The project's control-unit emulator (``omnid.devices.emulators.control_unit``) on the
    virtual clock, every command and reply passing as bytes through the protocol codec.

    It is the same code that serves a pty on the bench: it enforces its own watchdog and the
    command freshness rules, switches the laser relay with its delay, and integrates the plant
    (the chair) lazily up to the clock. Frames are built by the driver's own
    :class:`~omnid.devices.control_unit.FreshnessGate` (cycle number, age, zero while the link
    would be unhealthy after ``max_missed_replies`` missed replies), as ``omnid run`` sends them.
    """

    def __init__(
        self,
        plant: Chair,
        watchdog_s: float = 0.25,
        command_period_s: float = 0.02,
        max_missed_replies: int = 2,
        laser_delay_s: float = 0.01,
        laser_jitter_s: float = 0.0,
        seed: int = 0,
    ) -> None:
        from omnid.devices import cu_codec as codec
        from omnid.devices.control_unit import FreshnessGate
        from omnid.devices.emulators.control_unit import ControlUnitEmulator

        self._codec = codec
        self._t = 0.0
        self.emulator = ControlUnitEmulator(
            plant=plant,
            clock=lambda: self._t,
            default_watchdog_s=watchdog_s,
            laser_delay_s=laser_delay_s,
            laser_jitter_s=laser_jitter_s,
            seed=seed,
        )
        self._parser = codec.FrameParser(accept=(codec.TYPE_REPLY,))
        self._seq = 0
        self._raw: tuple[int, int] | None = None
        self._clocks = (0, 0)
        self.missed_replies = 0
        self._missed_in_a_row = 0
        self._max_missed = max_missed_replies
        self.gate = FreshnessGate(2.0 * command_period_s)

    @property
    def laser_on(self) -> bool:
        return bool(self.emulator.laser_on)

    @property
    def watchdog_trips(self) -> int:
        return int(self.emulator.watchdog_trips)

    @property
    def laser_switches(self) -> deque[tuple[float, bool]]:
        """(t_s, on): when the emulated relay actually switched (delay and jitter included)."""
        return self.emulator.laser_switches

    def exchange(self, command: Any, now_s: float) -> Any:
        """Encode ``command``, feed the bytes to the emulator at ``now_s``, decode its reply
        (None when it gives none)."""
        from omnid.devices.control_unit import WheelCommand

        codec = self._codec
        self._t = now_s
        self._seq = (self._seq + 1) & 0xFF
        cmd = WheelCommand(
            float(command.left_duty),
            float(command.right_duty),
            laser_on=bool(command.laser_on),
            enable=bool(command.enable),
        )
        self.gate.submit(cmd, now_s)
        frame = self.gate.frame(self._seq, now_s, healthy=self._missed_in_a_row < self._max_missed)
        reply = self.emulator.handle_bytes(codec.encode_command(frame))
        frames = [
            f
            for f in self._parser.feed(reply)
            if isinstance(f, codec.ReplyFrame) and f.seq == self._seq
        ]
        if not frames:
            self.missed_replies += 1
            self._missed_in_a_row += 1
            return None
        self._missed_in_a_row = 0
        rep = frames[-1]
        raw = (rep.left_clocks, rep.right_clocks)
        if self._raw is not None:
            self._clocks = (
                self._clocks[0] + codec.unwrap_int32(self._raw[0], raw[0]),
                self._clocks[1] + codec.unwrap_int32(self._raw[1], raw[1]),
            )
        else:
            self._clocks = raw
        self._raw = raw
        return ControlUnitStatus.from_reply(rep, *self._clocks, now_s)

    def advance(self, now_s: float, dt_s: float) -> None:
        """Let the emulator drive the plant up to ``now_s + dt_s``."""
        self._t = now_s + dt_s
        _ = self.emulator.clocks  # integrates the plant to the clock


def make_control_unit(
    plant: Chair,
    kind: str,
    watchdog_s: float,
    command_period_s: float = 0.02,
    laser_delay_s: float = 0.01,
    laser_jitter_s: float = 0.0,
    seed: int = 0,
) -> Any:
    """``emulator`` (bytes through the codec, the relay's delay and jitter) or ``direct`` (the
    plant without a link; the laser switches at the command); ``command_period_s``: how often
    the controller sends (its freshness limit is two of them)."""
    if kind == "emulator":
        return EmulatedControlUnit(
            plant,
            watchdog_s,
            command_period_s,
            laser_delay_s=laser_delay_s,
            laser_jitter_s=laser_jitter_s,
            seed=seed,
        )
    return DirectControlUnit(plant, watchdog_s)


def lit_share(switches: Any, t0_s: float, t1_s: float, now_on: bool) -> float:
    """The share of [t0_s, t1_s] during which the laser was lit, from its switch history
    ``[(t_s, on), ...]`` (time order; each entry a change) and its state now (used when the
    history is empty)."""
    if t1_s <= t0_s:
        return 0.0
    state = (not switches[0][1]) if switches else now_on
    t, lit = t0_s, 0.0
    for ts, on in switches:
        if ts <= t0_s:
            state = on
            continue
        if ts >= t1_s:
            break
        if state:
            lit += ts - t
        state, t = on, ts
    if state:
        lit += t1_s - t
    return lit / (t1_s - t0_s)


# -- the tilt sensor ------------------------------------------------------------------------------


class EmulatedTiltSensor:
    """The GS311 emulator (``omnid.devices.emulators.gs311``) on the virtual clock, read the way
    the tilt link reads it: the read-angles request ``0x50 0x50`` goes in as bytes, the reply
    bytes go through the codec's parser (``Gs311Parser`` with the link's default
    ``TiltSettings`` layout) and become a ``TiltReading`` — so the daemon core gets the angles
    the real link would decode, 12-bit quantisation and checksum included.

    ``unplugged`` (the ``tilt_unplugged`` fault) stops all replies, as a pulled adapter does.
    """

    def __init__(
        self, script: HeadScript | ReactiveRider, noise_deg: float = 0.0, seed: int = 0
    ) -> None:
        from omnid.devices import gs311_codec as codec
        from omnid.devices.emulators.gs311 import Gs311Emulator, HeadMotion
        from omnid.devices.tilt import TiltSettings

        self._t = 0.0
        self._codec = codec
        self._reading = TiltReading
        fmt = TiltSettings().format
        motion: HeadMotion | list[tuple[float, float, float]]
        if isinstance(script, ReactiveRider):
            motion = _live_head(HeadMotion, script)
        else:
            motion = script.as_list()
        self.emulator = Gs311Emulator(
            motion, fmt=fmt, noise_deg=noise_deg, seed=seed, clock=lambda: self._t
        )
        self.parser = codec.Gs311Parser(fmt)
        self.unplugged = False
        self.readings = 0

    def poll(self, now_s: float) -> Any:
        """One half-duplex request at ``now_s``: the decoded reading, or None (no valid reply)."""
        self._t = now_s
        if self.unplugged:
            return None
        self.parser.reset()
        frames = self.parser.feed(self.emulator.handle(self._codec.READ_ANGLES_REQUEST))
        if not frames:
            return None
        self.readings += 1
        f = frames[-1]
        return self._reading(f.roll_deg, f.pitch_deg, now_s)


def _live_head(base: Any, rider: ReactiveRider) -> Any:
    """A ``HeadMotion`` (the GS311 emulator's script) that reads a reactive rider's head."""

    class LiveHead(base):
        def __init__(self) -> None:
            super().__init__([(0.0, 0.0, 0.0)])

        def angles_at(self, t_s: float) -> tuple[float, float]:
            return rider.angles_at(t_s)

    return LiveHead()


class DirectTiltSensor:
    """The head script's angles without the byte link (for probes and tests of the script)."""

    def __init__(self, script: HeadScript | ReactiveRider) -> None:
        self.script = script
        self._reading = TiltReading
        self.unplugged = False

    def poll(self, now_s: float) -> Any:
        if self.unplugged:
            return None
        script = self.script
        if isinstance(script, ReactiveRider):
            roll, pitch = script.angles_at(now_s)
        else:
            roll, pitch = script.at(now_s)
        return self._reading(roll, pitch, now_s)


def make_tilt_sensor(
    script: HeadScript | ReactiveRider, kind: str, noise_deg: float = 0.0, seed: int = 0
) -> EmulatedTiltSensor | DirectTiltSensor:
    """``emulator`` (the GS311 bytes through the codec) or ``direct`` (the script's angles)."""
    if kind == "emulator":
        return EmulatedTiltSensor(script, noise_deg, seed)
    return DirectTiltSensor(script)
