"""A reactive rider: a small state machine that watches what the chair did and moves on.

A timed script only fits one run: with real perception the chair stops earlier or later than the
script assumed, and the rider goes on tilting forward at a wall. A real rider reacts instead —
sees the chair stop, reads the refusal it announces, notices when the turn is done. The
:class:`ReactiveRider` does that from the simulator's own records (:class:`Observation`: the true
pose and speed, the refusals the simulator recorded from the daemon core's reports) and plays
one :class:`Step` after another, each ended by its condition or, at the latest, its timeout, so a
story always ends.

Inputs: the head (tilt commands ``forward``, ``left``, ``right``, ``stop``, ``neutral``, through
the GS311 emulator) wherever a step allows; the joystick only where the head cannot do it —
reversing (the thesis' tilt commands have no "back", 4.2.2).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from omnid.config import require
from omnid.errors import InputError
from omnid.sim.rider import POSES_DEG


@dataclass(frozen=True)
class Observation:
    """What the rider can tell at ``now_s``: the chair's pose (mm, rad) and mean wheel speed
    (mm/s), and every refusal recorded so far ``(t_s, text)``."""

    now_s: float
    pose: tuple[float, float, float]
    speed_mm_s: float
    refusals: Sequence[tuple[float, str]]


@dataclass(frozen=True)
class Until:
    """A step's end condition: ``test(now, at_start, refusals_before)`` → evidence text, or
    None while it does not hold. ``what`` says it in words (for reports)."""

    what: str
    test: Callable[[Observation, Observation, int], str | None]


def refused(*reasons: str) -> Until:
    """A refusal naming one of ``reasons`` recorded since the step began."""

    def test(now: Observation, start: Observation, n0: int) -> str | None:
        for t, text in now.refusals[n0:]:
            if any(reason in text for reason in reasons):
                return f"t = {t:.2f} s: {text}"
        return None

    return Until(f"refused ({' or '.join(reasons)})", test)


def past_x(x_mm: float) -> Until:
    """The axle is beyond ``x_mm`` (world x)."""

    def test(now: Observation, start: Observation, n0: int) -> str | None:
        return f"axle at x = {now.pose[0]:.0f} mm" if now.pose[0] > x_mm else None

    return Until(f"axle past x = {x_mm:.0f} mm", test)


def moved(distance_mm: float) -> Until:
    """The axle moved ``distance_mm`` (straight line) from where the step began."""

    def test(now: Observation, start: Observation, n0: int) -> str | None:
        d = math.hypot(now.pose[0] - start.pose[0], now.pose[1] - start.pose[1])
        return f"moved {d:.0f} mm" if d >= distance_mm else None

    return Until(f"moved {distance_mm:.0f} mm", test)


def heading(target_deg: float, tol_deg: float = 4.0) -> Until:
    """The heading is within ``tol_deg`` of ``target_deg`` (world, + left of +x)."""

    def test(now: Observation, start: Observation, n0: int) -> str | None:
        err = (math.degrees(now.pose[2]) - target_deg + 180.0) % 360.0 - 180.0
        return f"heading {math.degrees(now.pose[2]):.0f}°" if abs(err) <= tol_deg else None

    return Until(f"heading {target_deg:.0f}°", test)


@dataclass(frozen=True)
class Step:
    """One thing the rider does: hold ``head`` (a tilt command) and the stick at ``stick``
    ``(forward, turn)`` until ``until`` holds or ``timeout_s`` has passed, then relax (head
    neutral, stick centred) for ``settle_s``. ``expect`` marks the story's checked steps."""

    what: str
    until: Until
    timeout_s: float
    head: str = "neutral"
    stick: tuple[float, float] = (0.0, 0.0)
    settle_s: float = 1.0

    def __post_init__(self) -> None:
        if self.head not in POSES_DEG:
            raise InputError(f"story step {self.what!r}: unknown head command {self.head!r}")
        require(self.timeout_s > 0, "timeout_s", "must be positive")
        require(self.settle_s >= 0, "settle_s", "must be ≥ 0")
        require(all(-1.0 <= a <= 1.0 for a in self.stick), "stick", "axes must be in [-1, 1]")


@dataclass(frozen=True)
class StepRecord:
    """How a step went: begun at ``t0_s``, ended at ``t1_s``, ``ended`` ``"done"`` (its condition
    held; ``evidence`` says how) or ``"timeout"``."""

    what: str
    t0_s: float
    t1_s: float
    ended: str
    evidence: str
    pose_mm_rad: tuple[float, float, float]  # where the chair was when it ended


@dataclass
class ReactiveRider:
    """Plays ``steps`` against observations (see the module docstring). Head pose moves to each
    command's pose in ``move_s`` (a head moves smoothly); ``tilt_deg`` past level (beyond the
    daemon's threshold). Call :meth:`observe` before reading :meth:`angles_at` / :meth:`at`."""

    steps: tuple[Step, ...]
    tilt_deg: float = 20.0
    move_s: float = 0.3
    start_s: float = 1.0  # sits still this long first
    log: list[StepRecord] = field(default_factory=list)
    done_s: float | None = None  # when the last step (and its settling) ended

    def __post_init__(self) -> None:
        require(len(self.steps) > 0, "steps", "needs at least one step")
        self._i = -1  # -1: before the first step
        self._settling_until: float | None = None
        self._t0 = 0.0
        self._start: Observation | None = None
        self._n0 = 0
        self._from = (0.0, 0.0)
        self._to = (0.0, 0.0)
        self._changed_s = 0.0
        self._stick = (0.0, 0.0)

    @property
    def done(self) -> bool:
        return self.done_s is not None

    @property
    def current(self) -> Step | None:
        """The step being played (None while sitting still, settling, or when done)."""
        if self._i < 0 or self._i >= len(self.steps) or self._settling_until is not None:
            return None
        return self.steps[self._i]

    def _set(self, head: str, stick: tuple[float, float], now_s: float) -> None:
        self._from = self.angles_at(now_s)
        r, p = POSES_DEG[head]
        self._to = (r * self.tilt_deg, p * self.tilt_deg)
        self._changed_s = now_s
        self._stick = stick

    def _begin(self, i: int, obs: Observation) -> None:
        self._i = i
        self._settling_until = None
        if i >= len(self.steps):
            self.done_s = obs.now_s
            self._set("neutral", (0.0, 0.0), obs.now_s)
            return
        st = self.steps[i]
        self._t0, self._start, self._n0 = obs.now_s, obs, len(obs.refusals)
        self._set(st.head, st.stick, obs.now_s)

    def observe(self, obs: Observation) -> None:
        """React to what the chair did by ``obs.now_s``."""
        if self.done:
            return
        if self._i < 0:
            if obs.now_s >= self.start_s:
                self._begin(0, obs)
            return
        if self._settling_until is not None:
            if obs.now_s >= self._settling_until:
                self._begin(self._i + 1, obs)
            return
        st = self.steps[self._i]
        assert self._start is not None
        evidence = st.until.test(obs, self._start, self._n0)
        timed_out = obs.now_s - self._t0 >= st.timeout_s
        if evidence is None and not timed_out:
            return
        ended = "done" if evidence is not None else "timeout"
        if evidence is None:
            evidence = f"no {st.until.what} within {st.timeout_s:.0f} s"
        self.log.append(StepRecord(st.what, self._t0, obs.now_s, ended, evidence, obs.pose))
        self._settling_until = obs.now_s + st.settle_s
        self._set("neutral", (0.0, 0.0), obs.now_s)

    def angles_at(self, t_s: float) -> tuple[float, float]:
        """Head pose (roll_deg, pitch_deg) at ``t_s`` (the GS311 emulator reads it)."""
        a = 1.0 if self.move_s <= 0 else min(1.0, max(0.0, (t_s - self._changed_s) / self.move_s))
        return (
            self._from[0] + a * (self._to[0] - self._from[0]),
            self._from[1] + a * (self._to[1] - self._from[1]),
        )

    def at(self, t_s: float) -> tuple[float, float]:
        """Joystick (forward, turn) now (the simulator's joystick reading)."""
        return self._stick


def demo_story(rear_mm: float = 750.0) -> ReactiveRider:
    """The demo in the built-in course (``omnid.sim.course``): through the wide passage (head),
    on until the narrow passage refuses (head), back away (joystick: the head has no reverse),
    turn right towards the stairs (head), forward until the stairs refuse (head), turn right
    towards box 3, seen on the way and now beside the chair outside the laser's field — refused
    from the map (head)."""
    return ReactiveRider(
        (
            Step(
                "through the wide passage",
                past_x(2000.0 + rear_mm),
                40.0,
                head="forward",
                settle_s=0.0,
            ),
            Step("on to the narrow passage", refused("obstacle_stop"), 25.0, head="forward"),
            # far enough for the front corners to turn clear of the partition (r = 495 mm)
            Step("back away", moved(120.0), 6.0, stick=(-0.5, 0.0), settle_s=0.5),
            Step("turn right, towards the stairs", heading(-90.0), 15.0, head="right"),
            Step("forward towards the stairs", refused("dropoff_stop"), 25.0, head="forward"),
            # box 3 beside it, the stairs' edge ahead, the floor beside them the laser never saw:
            # whichever the turn would reach first
            Step(
                "turn right, towards box 3",
                refused("obstacle_stop", "dropoff_stop", "unknown_stop"),
                10.0,
                head="right",
            ),
        )
    )
