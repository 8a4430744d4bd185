"""Rider commands: head tilt, joystick and keyboard, and the priority mux (thesis 4.1.1, 4.2; SPEC §5).

Head tilt (thesis 4.2.2) — four thresholds on the calibrated angles, a dead zone between them::

    roll  < −T  → forward        roll  > +T → stop
    pitch < −T  → right          pitch > +T → left

omnid adds what a rider who cannot use the hands needs so that an involuntary movement does not
drive the chair:

- a calibrated neutral pose (offsets subtracted before the thresholds, :func:`neutral_from_samples`):
  measured at start while the rider holds still for ``neutral_calibration_s`` (the headband sits
  differently each time it is put on), or — with ``neutral_calibration_s: 0`` — the stored
  ``roll_offset_deg``/``pitch_offset_deg`` (for a rider who cannot hold still for a few seconds).
  A calibration whose readings spread more than ``neutral_max_spread_deg`` (the head moved) or
  whose neutral lies beyond ``neutral_max_offset_deg`` (sensor badly mounted) is discarded and
  taken again; until one succeeds the tilt source asks for stop (``tilt_calibrating``);
- after a gap in the readings longer than ``timeout_s`` (sensor unplugged), any active command is
  dropped, so the head must again be held past its threshold for the dwell time;
- hysteresis: a command, once active, holds until its angle falls back inside ``release_deg``
  (< ``threshold_deg``), so noise around the threshold does not chatter;
- a dwell time: a motion command takes effect only after the head stayed past its threshold for
  ``dwell_s``;
- stop needs no dwell and always wins at once, in this source and across sources.

The mux (:class:`RiderMux`) takes the latest reading of each enabled source. A continuously
streaming source (tilt sensor, joystick) that is silent or stale for longer than its
``timeout_s`` counts as a stop — the chair must not keep a command nobody is confirming. Keyboard
presses are events: each holds for ``hold_s`` (terminal key repeat keeps it alive), then expires.
Any source's stop wins; otherwise the highest-priority source that asks for motion is obeyed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from enum import Enum
from typing import Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike

from omnid.config import Settings, require, setting

log = logging.getLogger(__name__)

SourceName = Literal["joystick", "keyboard", "tilt"]


class TiltSample(Protocol):
    """What the rider layer reads of a tilt reading (``omnid.devices.tilt.TiltReading``)."""

    @property
    def roll_deg(self) -> float: ...
    @property
    def pitch_deg(self) -> float: ...
    @property
    def timestamp_s(self) -> float: ...


class JoystickSample(Protocol):
    """What the rider layer reads of a joystick reading (``omnid.devices.joystick.JoystickReading``)."""

    @property
    def forward(self) -> float: ...
    @property
    def turn(self) -> float: ...
    @property
    def timestamp_s(self) -> float: ...


class Intent(Enum):
    """A discrete rider command (thesis 4.1.1)."""

    NONE = "none"  # dead zone: nothing asked
    STOP = "stop"
    FORWARD = "forward"
    LEFT = "left"
    RIGHT = "right"


@dataclass(frozen=True)
class TiltSettings(Settings):
    """Head-tilt interpretation. Angles in degrees, times in seconds."""

    enabled: bool = True
    threshold_deg: float = setting(12.0, 1.0, 45.0)  # thesis 4.2.2: T, to enter a command
    # hysteresis: an active command holds until |angle| < release
    release_deg: float = setting(8.0, 0.5, 45.0)
    # head must stay past T this long before a motion command acts
    dwell_s: float = setting(0.3, 0.0, 5.0)
    roll_offset_deg: float = setting(0.0, -45.0, 45.0)  # calibrated neutral pose
    pitch_offset_deg: float = setting(0.0, -45.0, 45.0)
    # no reading for this long → zero duty at once (the sensor reads every 10 ms); also the gap
    # after which the dwell restarts. The daemon's tilt link reports a lost or silent sensor
    # sooner (4 unanswered requests, ≈ 45 ms: tilt_sensor.stale_after_s); this is the backstop
    timeout_s: float = setting(0.1, 0.015, 1.0)
    forward_mode: Literal["hold", "latch"] = "hold"  # latch: forward holds until stop/turn
    forward_fraction: float = setting(0.6, 0.05, 1.0)  # of the maximum speed
    turn_fraction: float = setting(0.4, 0.05, 1.0)  # of the maximum turn rate
    # rider holds still this long at start; 0 = use the offsets as stored (the simulator's
    # scripted heads and clock-injected tests pass 0)
    neutral_calibration_s: float = setting(3.0, 0.0, 30.0)
    # readings farther than this from their median: retake
    neutral_max_spread_deg: float = setting(2.0, 0.1, 20.0)
    # a neutral farther than this from level: retake (below threshold_deg: a head held in a
    # command pose must not become the neutral)
    neutral_max_offset_deg: float = setting(10.0, 0.5, 45.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.release_deg <= self.threshold_deg, "release_deg", "must not exceed threshold_deg"
        )


@dataclass(frozen=True)
class JoystickSettings(Settings):
    """Proportional hand control; ``forward`` and ``turn`` (left positive) in [-1, 1]."""

    enabled: bool = False
    deadzone: float = setting(0.1, 0.0, 0.9)  # |axis| below this counts as centred
    timeout_s: float = setting(0.2, 0.015, 1.0)  # no reading for this long → stop


@dataclass(frozen=True)
class KeyboardSettings(Settings):
    """Arrow keys (thesis 4.2.1): up forward, left, right, down stop."""

    enabled: bool = True
    hold_s: float = setting(0.5, 0.05, 5.0)  # a press holds this long; key repeat renews it
    forward_fraction: float = setting(0.5, 0.05, 1.0)
    turn_fraction: float = setting(0.4, 0.05, 1.0)


@dataclass(frozen=True)
class RiderSettings(Settings):
    """All rider inputs and their priority (first wins among sources asking for motion)."""

    tilt: TiltSettings = field(default_factory=TiltSettings)
    joystick: JoystickSettings = field(default_factory=JoystickSettings)
    keyboard: KeyboardSettings = field(default_factory=KeyboardSettings)
    priority: tuple[SourceName, ...] = ("joystick", "keyboard", "tilt")

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            sorted(self.priority) == ["joystick", "keyboard", "tilt"],
            "priority",
            "must list joystick, keyboard and tilt once each",
        )


@dataclass(frozen=True)
class RiderDemand:
    """What the rider asks: fractions of the maximum speed / turn rate (turn > 0 is left)."""

    forward: float = 0.0
    turn: float = 0.0
    stop: bool = True  # an explicit or fail-safe stop (the chair brakes)
    source: str = "none"
    reason: str = "idle"

    @property
    def moving(self) -> bool:
        return not self.stop and (self.forward != 0.0 or self.turn != 0.0)


def neutral_from_samples(roll_deg: ArrayLike, pitch_deg: ArrayLike) -> tuple[float, float]:
    """Neutral head pose (roll, pitch offsets in degrees): the median of readings at rest.

    The median ignores a few involuntary movements during the calibration seconds.
    """
    r = np.asarray(roll_deg, dtype=np.float64).ravel()
    p = np.asarray(pitch_deg, dtype=np.float64).ravel()
    if r.size == 0 or p.size == 0:
        raise ValueError("neutral_from_samples: no readings")
    return float(np.median(r)), float(np.median(p))


class TiltInterpreter:
    """Thresholds with neutral offsets, hysteresis and dwell → the current :class:`Intent`."""

    def __init__(self, settings: TiltSettings) -> None:
        self.settings = settings
        self.roll_offset_deg = settings.roll_offset_deg
        self.pitch_offset_deg = settings.pitch_offset_deg
        self.active = Intent.NONE
        self._pending = Intent.NONE
        self._pending_since_s = 0.0
        self.last_timestamp_s: float | None = None
        self.calibrating = settings.neutral_calibration_s > 0
        self.calibrated = False  # a neutral pose was measured: the head was held still
        self.calibrations_failed = 0
        self._cal: list[tuple[float, float, float]] = []  # (t_s, roll, pitch) while calibrating

    def _calibrate(self, roll: float, pitch: float, t_s: float) -> None:
        """Collect raw readings at rest; set the neutral pose once ``neutral_calibration_s``
        of still readings are in (see the module docstring)."""
        s = self.settings
        if self._cal and t_s - self._cal[-1][0] > s.timeout_s:
            self._cal.clear()  # a gap (unplugged): start over
        if not (np.isfinite(roll) and np.isfinite(pitch)):
            self._cal.clear()
            return
        self._cal.append((t_s, roll, pitch))
        if t_s - self._cal[0][0] < s.neutral_calibration_s:
            return
        arr = np.asarray(self._cal)
        r0, p0 = neutral_from_samples(arr[:, 1], arr[:, 2])
        spread = float(max(np.max(np.abs(arr[:, 1] - r0)), np.max(np.abs(arr[:, 2] - p0))))
        self._cal.clear()
        if spread > s.neutral_max_spread_deg or max(abs(r0), abs(p0)) > s.neutral_max_offset_deg:
            self.calibrations_failed += 1
            log.warning(
                "tilt neutral-pose calibration retaken: head moved %.1f° (max %.1f°) or neutral "
                "(roll %.1f°, pitch %.1f°) beyond %.0f°; hold still",
                spread,
                s.neutral_max_spread_deg,
                r0,
                p0,
                s.neutral_max_offset_deg,
            )
            return
        self.set_neutral(r0, p0)
        self.calibrating = False
        self.calibrated = True
        log.info("tilt neutral pose calibrated: roll %.2f°, pitch %.2f°", r0, p0)

    @property
    def at_rest(self) -> bool:
        """No motion command active or pending (the head within its thresholds, or in the stop
        pose)."""
        return self.active in (Intent.NONE, Intent.STOP) and self._pending is Intent.NONE

    def set_neutral(self, roll_offset_deg: float, pitch_offset_deg: float) -> None:
        """Use a new calibrated neutral pose (degrees); clears any active command."""
        self.roll_offset_deg = float(roll_offset_deg)
        self.pitch_offset_deg = float(pitch_offset_deg)
        self.active = Intent.NONE
        self._pending = Intent.NONE

    def _past(self, intent: Intent, roll: float, pitch: float) -> float:
        """How far past its threshold the head is for ``intent`` (deg; ≤ 0: not past)."""
        s = self.settings
        limit = s.release_deg if intent is self.active else s.threshold_deg
        if intent is Intent.FORWARD:
            return -roll - limit
        if intent is Intent.STOP:
            return roll - limit
        if intent is Intent.RIGHT:
            return -pitch - limit
        if intent is Intent.LEFT:
            return pitch - limit
        return 0.0

    def update(self, roll_deg: float, pitch_deg: float, timestamp_s: float) -> Intent:
        """Feed one reading (raw angles, deg; monotonic time, s); returns the active intent."""
        s = self.settings
        prev = self.last_timestamp_s
        self.last_timestamp_s = float(timestamp_s)
        if self.calibrating:
            self._calibrate(float(roll_deg), float(pitch_deg), float(timestamp_s))
            return Intent.NONE
        if prev is not None and float(timestamp_s) - prev > s.timeout_s:
            # readings resume after a gap: nothing held over, the dwell starts afresh
            self.active, self._pending = Intent.NONE, Intent.NONE
        roll = float(roll_deg) - self.roll_offset_deg
        pitch = float(pitch_deg) - self.pitch_offset_deg
        if not (np.isfinite(roll) and np.isfinite(pitch)):
            self.active, self._pending = Intent.STOP, Intent.NONE
            return self.active
        if self._past(Intent.STOP, roll, pitch) > 0:
            # stop: no dwell, wins over everything
            self.active, self._pending = Intent.STOP, Intent.NONE
            return self.active
        motions = (Intent.FORWARD, Intent.RIGHT, Intent.LEFT)
        excess = {m: self._past(m, roll, pitch) for m in motions}
        held = [m for m in motions if excess[m] > 0]
        if self.active in held:
            candidate = self.active
        elif held:
            candidate = max(held, key=lambda m: excess[m])
        else:
            candidate = Intent.NONE
        if candidate is self.active:
            self._pending = Intent.NONE
            return self.active
        # the active command is no longer held
        if not (s.forward_mode == "latch" and self.active is Intent.FORWARD):
            self.active = Intent.NONE
        if candidate is Intent.NONE:
            self._pending = Intent.NONE
            return self.active
        if candidate is not self._pending:
            self._pending, self._pending_since_s = candidate, float(timestamp_s)
        if float(timestamp_s) - self._pending_since_s >= s.dwell_s:
            self.active, self._pending = candidate, Intent.NONE
        return self.active


_KEYS: dict[str, Intent] = {
    "up": Intent.FORWARD,
    "forward": Intent.FORWARD,
    "left": Intent.LEFT,
    "right": Intent.RIGHT,
    "down": Intent.STOP,
    "stop": Intent.STOP,
    "space": Intent.STOP,
}


def _intent_demand(intent: Intent, fwd: float, turn: float, source: str) -> RiderDemand | None:
    if intent is Intent.STOP:
        return RiderDemand(stop=True, source=source, reason=f"{source}_stop")
    if intent is Intent.FORWARD:
        return RiderDemand(forward=fwd, stop=False, source=source, reason=f"{source}_forward")
    if intent is Intent.LEFT:
        return RiderDemand(turn=turn, stop=False, source=source, reason=f"{source}_left")
    if intent is Intent.RIGHT:
        return RiderDemand(turn=-turn, stop=False, source=source, reason=f"{source}_right")
    return None


class RiderMux:
    """Latest input of each source → one :class:`RiderDemand` (see the module docstring)."""

    def __init__(self, settings: RiderSettings) -> None:
        self.settings = settings
        self.tilt = TiltInterpreter(settings.tilt)
        self._joystick: tuple[float, float, float] | None = None  # forward, turn, t_s
        self._key: tuple[Intent, float] | None = None  # intent, t_s
        self._lost: set[str] = set()  # sources whose device said it is gone, until they speak

    def on_lost(self, name: str) -> None:
        """The device of source ``name`` says it is gone (port lost, readings stale): the
        source counts as stale now, not only once its ``timeout_s`` has passed."""
        self._lost.add(name)

    def on_tilt(self, reading: TiltSample) -> None:
        self._lost.discard("tilt")
        self.tilt.update(reading.roll_deg, reading.pitch_deg, reading.timestamp_s)

    def on_joystick(self, reading: JoystickSample) -> None:
        self._lost.discard("joystick")
        fwd, turn = float(reading.forward), float(reading.turn)
        if not (np.isfinite(fwd) and np.isfinite(turn)):
            fwd, turn = float("nan"), float("nan")  # counted as a stop by decide()
        self._joystick = (fwd, turn, float(reading.timestamp_s))

    def on_key(self, command: str, now_s: float) -> None:
        """A key press: ``up``/``forward``, ``left``, ``right``, ``down``/``stop``/``space``."""
        intent = _KEYS.get(command.strip().lower())
        if intent is None:
            raise ValueError(f"unknown key command {command!r} (known: {', '.join(_KEYS)})")
        self._key = (intent, float(now_s))

    def _source_demand(self, name: str, now_s: float) -> RiderDemand | None:
        s = self.settings
        if name == "tilt":
            if not s.tilt.enabled:
                return None
            t = self.tilt.last_timestamp_s
            if t is None or now_s - t > s.tilt.timeout_s or "tilt" in self._lost:
                return RiderDemand(stop=True, source="tilt", reason="tilt_stale")
            if self.tilt.calibrating:
                return RiderDemand(stop=True, source="tilt", reason="tilt_calibrating")
            return _intent_demand(
                self.tilt.active, s.tilt.forward_fraction, s.tilt.turn_fraction, "tilt"
            )
        if name == "joystick":
            if not s.joystick.enabled:
                return None
            if (
                self._joystick is None
                or now_s - self._joystick[2] > s.joystick.timeout_s
                or "joystick" in self._lost
            ):
                return RiderDemand(stop=True, source="joystick", reason="joystick_stale")
            fwd, turn, _ = self._joystick
            if not (np.isfinite(fwd) and np.isfinite(turn)):
                return RiderDemand(stop=True, source="joystick", reason="joystick_invalid")
            dz = s.joystick.deadzone

            def shape(a: float) -> float:
                a = max(-1.0, min(1.0, a))
                return 0.0 if abs(a) <= dz else float(np.sign(a)) * (abs(a) - dz) / (1.0 - dz)

            f, t_ = shape(fwd), shape(turn)
            if f == 0.0 and t_ == 0.0:
                return None
            return RiderDemand(forward=f, turn=t_, stop=False, source="joystick", reason="joystick")
        if name == "keyboard":
            if not s.keyboard.enabled or self._key is None:
                return None
            intent, t = self._key
            if now_s - t > s.keyboard.hold_s or now_s < t - 1.0:
                return None
            return _intent_demand(
                intent, s.keyboard.forward_fraction, s.keyboard.turn_fraction, "keyboard"
            )
        raise ValueError(f"unknown source {name!r}")

    def source_demand(self, name: str, now_s: float) -> RiderDemand | None:
        """What source ``name`` alone asks at ``now_s`` (``None``: enabled and idle, or not
        enabled)."""
        return self._source_demand(name, now_s)

    def input_time_s(self, name: str) -> float | None:
        """Monotonic time of the newest input from source ``name`` (``None``: none yet)."""
        if name == "tilt":
            return self.tilt.last_timestamp_s
        if name == "joystick":
            return None if self._joystick is None else self._joystick[2]
        if name == "keyboard":
            return None if self._key is None else self._key[1]
        raise ValueError(f"unknown source {name!r}")

    def is_live(self, name: str, now_s: float) -> bool:
        """Source ``name`` is enabled and its input is fresh and valid (a continuous source that
        is silent, stale, invalid or still calibrating is not live; the keyboard, whose presses
        are events, always is)."""
        d = self._source_demand(name, now_s)
        return d is None or not d.reason.endswith(("_stale", "_invalid", "_calibrating"))

    def released(self, name: str, now_s: float, since_s: float) -> bool:
        """Source ``name`` is live and at rest or asking for stop, as seen in input newer than
        ``since_s`` (the keyboard: no motion key held) — what re-arms the chair after a fault.

        For the head tilt "at rest" means no command active or pending: a head still held past
        a threshold after the sensor came back is not a release, even before its dwell ends."""
        if name == "keyboard":
            d = self._source_demand(name, now_s)
            return d is None or not d.moving
        t = self.input_time_s(name)
        if t is None or t <= since_s or not self.is_live(name, now_s):
            return False
        if name == "tilt":
            return self.tilt.at_rest
        d = self._source_demand(name, now_s)
        return d is None or not d.moving

    def source_demands(self, now_s: float) -> dict[str, RiderDemand | None]:
        """Each source's own demand at ``now_s`` (None: disabled or idle), in priority order —
        what :meth:`decide` chooses from (for recordings and the live view)."""
        return {n: self._source_demand(n, now_s) for n in self.settings.priority}

    def decide(self, now_s: float) -> RiderDemand:
        """The demand at monotonic time ``now_s``: any stop wins, else the first source moving."""
        demands = [(n, self._source_demand(n, now_s)) for n in self.settings.priority]
        for _, d in demands:
            if d is not None and d.stop:
                return d
        for _, d in demands:
            if d is not None and d.moving:
                return d
        return RiderDemand()
