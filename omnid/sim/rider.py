"""Scripted riders: head motion for the tilt sensor and key presses for the keyboard.

A head-motion script is a list of ``(t_s, roll_deg, pitch_deg)`` key poses, played linearly in
between (the GS311 emulator's format, docs/interfaces.md). The thesis' tilt commands (4.2.2;
SPEC §3) are read from it by four thresholds: roll < −T → forward, roll > +T → stop,
pitch < −T → right, pitch > +T → left. :func:`head_script` writes such a script from a readable
list of ``(command, hold_s)`` steps, with the head moving between poses in ``move_s`` so the
rider's motion is smooth, as a head is.

A key script is a list of ``(t_s, command)`` presses (``forward``, ``left``, ``right``,
``stop``), the keyboard option of the thesis.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from omnid.errors import InputError

COMMANDS = ("forward", "left", "right", "stop", "neutral")

#: Head pose (roll_deg, pitch_deg) that expresses each command (SPEC §3 sign conventions).
POSES_DEG: dict[str, tuple[float, float]] = {
    "neutral": (0.0, 0.0),
    "forward": (-1.0, 0.0),
    "stop": (1.0, 0.0),
    "right": (0.0, -1.0),
    "left": (0.0, 1.0),
}


@dataclass(frozen=True)
class HeadScript:
    """Head pose over time: key poses ``(t_s, roll_deg, pitch_deg)``, linear in between.

    Before the first key pose the head is at the first pose; after the last, at the last.
    """

    keys: tuple[tuple[float, float, float], ...]

    def __post_init__(self) -> None:
        if not self.keys:
            raise InputError("head script: needs at least one (t_s, roll_deg, pitch_deg) pose")
        times = [k[0] for k in self.keys]
        if any(not all(math.isfinite(v) for v in k) for k in self.keys):
            raise InputError("head script: every value must be a finite number")
        if any(b < a for a, b in itertools.pairwise(times)):
            raise InputError("head script: times must not decrease")

    @property
    def duration_s(self) -> float:
        return self.keys[-1][0]

    def at(self, t_s: float) -> tuple[float, float]:
        """(roll_deg, pitch_deg) at time ``t_s``."""
        k = np.asarray(self.keys, dtype=np.float64)
        return float(np.interp(t_s, k[:, 0], k[:, 1])), float(np.interp(t_s, k[:, 0], k[:, 2]))

    def as_list(self) -> list[tuple[float, float, float]]:
        """The GS311 emulator's script format."""
        return [tuple(map(float, k)) for k in self.keys]  # type: ignore[misc]


def head_script(
    steps: Sequence[tuple[str, float]],
    tilt_deg: float = 20.0,
    move_s: float = 0.3,
    start_s: float = 0.0,
) -> HeadScript:
    """A head script from ``(command, hold_s)`` steps: move to the command's pose in ``move_s``,
    hold it ``hold_s``. ``tilt_deg`` is how far the rider tilts (beyond the daemon's threshold).
    """
    keys: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)]
    t = max(0.0, start_s)
    if t > 0:
        keys.append((t, 0.0, 0.0))
    for command, hold_s in steps:
        if command not in POSES_DEG:
            raise InputError(
                f"head script: unknown command {command!r} (known: {', '.join(COMMANDS)})"
            )
        if not (math.isfinite(hold_s) and hold_s >= 0):
            raise InputError(f"head script: hold time of {command!r} must be ≥ 0, got {hold_s!r}")
        roll, pitch = POSES_DEG[command]
        t += move_s
        keys.append((t, roll * tilt_deg, pitch * tilt_deg))
        t += hold_s
        keys.append((t, roll * tilt_deg, pitch * tilt_deg))
    return HeadScript(tuple(keys))


@dataclass(frozen=True)
class KeyScript:
    """Key presses ``(t_s, command)`` in time order."""

    presses: tuple[tuple[float, str], ...]

    def __post_init__(self) -> None:
        for t, c in self.presses:
            if c not in COMMANDS or c == "neutral":
                raise InputError(f"key script: unknown command {c!r} at {t} s")
        times = [p[0] for p in self.presses]
        if any(b < a for a, b in itertools.pairwise(times)):
            raise InputError("key script: times must not decrease")

    def between(self, t0_s: float, t1_s: float) -> list[tuple[float, str]]:
        """Presses with t0 < t ≤ t1."""
        return [(t, c) for t, c in self.presses if t0_s < t <= t1_s]


@dataclass(frozen=True)
class JoystickScript:
    """Stick positions ``(t_s, forward, turn)`` (each in [-1, 1]; + ahead, + left), each held
    until the next — a proportional hand control, the only rider input that can reverse."""

    moves: tuple[tuple[float, float, float], ...]
    _t: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.moves:
            raise InputError("joystick script: needs at least one (t_s, forward, turn) move")
        for t, f, w in self.moves:
            if not (math.isfinite(t) and -1.0 <= f <= 1.0 and -1.0 <= w <= 1.0):
                raise InputError(
                    f"joystick script: ({t}, {f}, {w}) must be finite, axes in [-1, 1]"
                )
        if any(b[0] < a[0] for a, b in itertools.pairwise(self.moves)):
            raise InputError("joystick script: times must not decrease")
        object.__setattr__(self, "_t", np.array([m[0] for m in self.moves]))

    @property
    def duration_s(self) -> float:
        return self.moves[-1][0]

    def at(self, t_s: float) -> tuple[float, float]:
        """(forward, turn) at ``t_s`` (centred before the first move)."""
        i = int(np.searchsorted(self._t, t_s, side="right")) - 1
        if i < 0:
            return 0.0, 0.0
        return self.moves[i][1], self.moves[i][2]


#: The random rider's moves: (name, probability, forward, turn, shortest hold s, longest hold s).
RANDOM_MOVES: tuple[tuple[str, float, float, float, float, float], ...] = (
    ("forward", 0.35, 0.8, 0.0, 2.0, 10.0),
    ("arc left", 0.08, 0.6, 0.4, 1.0, 4.0),
    ("arc right", 0.08, 0.6, -0.4, 1.0, 4.0),
    ("turn left in place", 0.14, 0.0, 0.6, 1.0, 4.0),
    ("turn right in place", 0.14, 0.0, -0.6, 1.0, 4.0),
    ("reverse", 0.05, -0.7, 0.0, 1.0, 3.0),
    ("reverse left", 0.05, -0.6, 0.5, 1.0, 3.0),
    ("reverse right", 0.05, -0.6, -0.5, 1.0, 3.0),
    ("stop", 0.06, 0.0, 0.0, 0.5, 2.0),
)


def random_ride(seed: int, duration_s: float) -> JoystickScript:
    """A rider's random commands for ``duration_s``: mostly forward, turns in place, arcs and
    short reversing out (what a rider does when the chair refuses to go on), a pause between
    moves as a hand does. Reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    p = np.array([m[1] for m in RANDOM_MOVES])
    moves: list[tuple[float, float, float]] = []
    t = 0.0
    while t < duration_s:
        _, _, fwd, turn, lo, hi = RANDOM_MOVES[int(rng.choice(len(RANDOM_MOVES), p=p / p.sum()))]
        moves.append((t, fwd, turn))
        t += float(rng.uniform(lo, hi))
        moves.append((t, 0.0, 0.0))
        t += 0.3
    return JoystickScript(tuple(moves))


def command_of(roll_deg: float, pitch_deg: float, threshold_deg: float) -> str:
    """The thesis' four-threshold reading of a head pose (4.2.2), for reports and tests."""
    if roll_deg < -threshold_deg:
        return "forward"
    if roll_deg > threshold_deg:
        return "stop"
    if pitch_deg < -threshold_deg:
        return "right"
    if pitch_deg > threshold_deg:
        return "left"
    return "neutral"
