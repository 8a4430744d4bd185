"""The safety scenario suite: courses, riders and the truth measures a run is judged by.

Each :class:`Trial` is one course, one rider (``joystick`` or ``tilt``) and one seed; the seed
draws what is uncertain about the run — where the chair starts and how it is turned (within the
scenario's stated spread), the motors' gains and lag, the rider's timing — so a scenario is
judged on rates over seeds, never on one lucky run. :func:`run_trial` drives the daemon's own
``ControlCore`` (default configuration) on the simulator and measures, from the simulated
world's truth, never from what the daemon believed:

- contacts (each time the footprint pressed against a box: the simulator blocks the chair) and
  falls (a wheel or the centre of mass over a drop-off);
- false stops: the chair stood still (true wheel speed < 2 mm/s) while the rider asked to move,
  the daemon refused, and by truth the way was clear — the footprint grown by 50 mm could move
  500 mm (travel of its fastest point) in the asked direction without touching a box or a
  drop-off. Counted as events (runs of such control steps) and seconds;
- for a hazard ahead: how far the footprint stopped from it (truth); the time from the first
  stop reason (``obstacle_stop``, ``dropoff_stop``, ``unknown_stop``, ``bump``) to standstill;
  and the hazard's response time — from the moment the hazard both has a laser dot on it
  (truth) and lies within the distance at which the daemon's rules limit the chair at its
  current speed (the slow zone, or the stop line plus the approach and braking distance, plus
  the margin; measured on truth as the rules measure it, along the chair's current motion:
  how far the true footprint can travel before it touches the hazard) to the first command the
  safety layer limited (0 when the chair was already limited then);
- for a doorway, corridor or wall to drive along: whether the whole chair got through; its
  **safety stops** before it did — control steps where the rider asked to move and the safety
  layer limited the command to zero (``SafetyDecision.stopped``: ``obstacle_stop``,
  ``dropoff_stop``, ``unknown_stop``, ``perception_stale``, … or a ``bump``), counted as events
  (runs of such steps; "at the door" those that began with the true footprint within the slow
  zone, ``safety.slow_distance_mm``, of the passage) and seconds, with their reasons and the
  least true clearance to the passage at an event's start; the slowest forward speed the
  daemon allowed while any part of the chair was in the opening and the rider asked to go
  forward (and the true slowest speed there); and, apart, the **rider's own** pauses and
  turns in place in it (steps asking no travel: a head rider corrects its heading by stopping
  and turning in place, mean wheel speed 0 — not a stop of the daemon's).

Scenarios (:data:`SCENARIOS`): a thin post, a 60 mm threshold, a narrow trench, a wall and a
drop-off edge approached obliquely, turning beside a wall seen and one never seen, doorways of
780/820/850/900 mm, a 950 mm corridor, driving along a wall 150 mm away, reversing towards a box
never seen, and random riding in a dense room. ``tools/safety_figures.py --suite`` runs them all
(docs/benchmarks.md); ``tests/scenarios/test_safety_suite.py`` runs a small, fast subset.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.sim.chair import ChairSettings
from omnid.sim.course import WALL_MM, Course, walls
from omnid.sim.rider import JoystickScript, head_script, random_ride
from omnid.sim.story import Observation, ReactiveRider, Step, moved
from omnid.sim.world import Box, DropOff, World

RiderKind = Literal["joystick", "tilt"]
RIDERS: tuple[RiderKind, ...] = ("joystick", "tilt")
STANDSTILL_MM_S = 2.0  # "stood still": both wheels slower than this (truth)
CLEAR_TRAVEL_MM = 500.0  # a false stop: the footprint could have moved this far ...
CLEAR_SPARE_MM = 50.0  # ... with this much to spare
FOOTPRINT = (350.0, 750.0, 700.0)  # front, rear, width of the simulated chair (mm)


# -- courses --------------------------------------------------------------------------------


def _room(
    boxes: tuple[Box, ...] = (),
    dropoffs: tuple[DropOff, ...] = (),
    x_range: tuple[float, float] = (-1200.0, 5000.0),
    y_range: tuple[float, float] = (-2000.0, 2000.0),
    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
    name: str = "suite",
) -> Course:
    """A walled room; the chair starts at ``start`` (axle midpoint, heading)."""
    x0, x1 = x_range
    y0, y1 = y_range
    world = World(boxes=(*boxes, *walls(x0, x1, y0, y1)), dropoffs=dropoffs)
    return Course(name, world, start, (x0 - WALL_MM, x1 + WALL_MM), (y0 - WALL_MM, y1 + WALL_MM))


@dataclass(frozen=True)
class Trial:
    """One run to make: the course, who rides and how, and what to measure.

    ``hazard`` are indices into the world's boxes (``("box", i)``) or drop-offs
    (``("drop", i)``) whose approach is measured; ``opening`` is (x0_mm, x1_mm) of a doorway or
    corridor the chair should pass (world x, the chair heading +x).
    """

    scenario: str
    rider: RiderKind
    seed: int
    course: Course
    duration_s: float
    rider_input: Any  # a HeadScript, JoystickScript or ReactiveRider
    chair: ChairSettings
    hazard: tuple[tuple[str, int], ...] = ()
    opening: tuple[float, float] | None = None
    goal_x_mm: float | None = None  # the axle should get past this (a passage)
    response: bool = True  # measure the hazard response (not for a passage meant to be passed)
    config: dict[str, Any] = field(default_factory=dict)  # safety settings changed for this trial


def chair_for(seed: int) -> ChairSettings:
    """Motors as they come: gains 0.92–1.08 of the calibrated one (thesis table 4.3: 27–32 rpm),
    lag 0.1–0.2 s."""
    rng = np.random.default_rng([seed, 11])
    return ChairSettings(
        left_gain=float(rng.uniform(0.92, 1.08)),
        right_gain=float(rng.uniform(0.92, 1.08)),
        motor_time_constant_s=float(rng.uniform(0.1, 0.2)),
    )


def _jitter(seed: int, lateral_mm: float, heading_deg: float) -> tuple[float, float]:
    rng = np.random.default_rng([seed, 5])
    return float(rng.uniform(-lateral_mm, lateral_mm)), math.radians(
        float(rng.uniform(-heading_deg, heading_deg))
    )


# -- riders ---------------------------------------------------------------------------------


class LinePilot(ReactiveRider):
    """A rider who steers along a line through ``point`` with heading ``heading_rad``: the
    joystick with a pure-pursuit turn (look-ahead ``lookahead_mm``) and the stick forward, or
    the head — turn while the heading error exceeds ``turn_on_deg`` (until below
    ``turn_off_deg``), forward otherwise (the head commands are exclusive). For the first
    ``straight_mm`` it drives straight on (after start-up the chair has seen only what lies
    ahead: a turn's tail would sweep the unseen). Centres once the axle is past
    ``until_x_mm``.

    Like a person, it does not push against a refusal for ever: when the chair has stood still
    (moved < 5 mm and turned < 1.5°) for ``give_up_s`` while it asked to move, it lets go
    (neutral for ``let_go_s``) and tries again differently, as the daemon's last refusal says:
    after a refused turn in place, or a refusal for space never seen, it first drives straight
    on ``straight_on_mm`` (more comes into view, and a later turn's tail sweeps the chair's own
    trail); after any other refusal it backs off ``back_off_mm`` (the joystick; the head has no
    reverse) and from then on aims closer, at half its look-ahead (a near aim corrects a
    sideways offset that a far one leaves; once: repeated let-goes keep that aim).
    ``let_goes`` counts them; ``let_go_log`` says when, what was asked and refused
    (``"forward: refused joystick: obstacle_stop"``, the refusal recorded since the chair began
    to stand, or up to 1 s before: it brakes after it) and the retry (``"straight"``,
    ``"back"``, ``"none"``: the head, refused forward, only lets go and aims closer)."""

    def __init__(
        self,
        kind: RiderKind,
        point: tuple[float, float],
        heading_rad: float,
        until_x_mm: float,
        start_s: float = 1.0,
        lookahead_mm: float = 700.0,
        forward: float = 1.0,
        turn_on_deg: float = 4.5,
        turn_off_deg: float = 2.0,
        straight_mm: float = 0.0,
        give_up_s: float = 1.5,
        let_go_s: float = 0.7,
        back_off_mm: float = 100.0,
        straight_on_mm: float = 150.0,
    ) -> None:
        super().__init__((Step("follow the line", moved(1e9), 1e6),), start_s=start_s)
        self.kind = kind
        self.point = point
        self.heading = heading_rad
        self.until_x_mm = until_x_mm
        self.lookahead = lookahead_mm
        self.forward = forward
        self.on, self.off = math.radians(turn_on_deg), math.radians(turn_off_deg)
        self._head = "neutral"
        self._turning = 0
        self.straight_mm = straight_mm
        self._origin: tuple[float, float] | None = None
        self.give_up_s, self.let_go_s = give_up_s, let_go_s
        self.back_off_mm, self.straight_on_mm = back_off_mm, straight_on_mm
        self.let_goes = 0
        # each let-go: (t_s, what the rider asked and the daemon's refusal, the retry chosen)
        self.let_go_log: list[tuple[float, str, str]] = []
        self._aim_mm = lookahead_mm  # the look-ahead it started with
        self._still: tuple[float, float, float, float] | None = None  # pose, since (s)
        # the try-again after a let-go: (phase, until_s, pose where it began, the retry that
        # follows the release: "straight", "back" or "none")
        self._retry: tuple[str, float, tuple[float, float, float], str] | None = None

    def _asking(self) -> str | None:
        """What the rider asks now: "forward", "turn" or None (nothing)."""
        if self.kind == "joystick":
            fwd, turn = self._stick
            return "forward" if fwd > 0.0 else ("turn" if turn != 0.0 else None)
        return {"forward": "forward", "left": "turn", "right": "turn"}.get(self._head)

    def _hold(self, head: str, stick: tuple[float, float], now_s: float) -> None:
        """Ask ``stick`` (the joystick) or move the head to ``head`` (the tilt rider)."""
        if self.kind == "joystick":
            self._stick = stick
        elif self._head != head:
            self._set(head, (0.0, 0.0), now_s)
            self._head = head

    def _refused(self, obs: Observation) -> bool:
        """True once the chair has stood still for ``give_up_s`` while the rider asked."""
        x, y, th = obs.pose
        asking = self._asking()
        s = self._still
        if (
            asking is None
            or s is None
            or math.hypot(x - s[0], y - s[1]) > 5.0
            or abs(math.remainder(th - s[2], 2.0 * math.pi)) > math.radians(1.5)
        ):
            self._still = (x, y, th, obs.now_s)
            return False
        return obs.now_s - s[3] >= self.give_up_s

    def _try_again(self, obs: Observation) -> bool:
        """Play the let-go and what follows it; False once it is over."""
        assert self._retry is not None
        what, until_s, (x0, y0, _), after = self._retry
        x, y, _ = obs.pose
        gone = math.hypot(x - x0, y - y0)
        if x > self.until_x_mm:  # through: the line's end takes over
            self._retry = None
            return False
        if what == "release":
            if obs.now_s < until_s:
                return True
            if after == "straight" and self.straight_on_mm > 0:
                self._retry = ("straight", obs.now_s + 4.0, obs.pose, after)
            elif after == "back" and self.kind == "joystick" and self.back_off_mm > 0:
                self._retry = ("back", obs.now_s + 3.0, obs.pose, after)
            else:
                self._retry = None
                return False
            return self._try_again(obs)
        done = obs.now_s >= until_s or gone >= (
            self.back_off_mm if what == "back" else self.straight_on_mm
        )
        if done:
            self._retry = None
            self._still = None
            return False
        if what == "back":
            self._hold("neutral", (-0.5, 0.0), obs.now_s)
        else:
            self._hold("forward", (0.6, 0.0), obs.now_s)
        return True

    def observe(self, obs: Observation) -> None:
        if obs.now_s < self.start_s:
            return
        x, y, th = obs.pose
        if self._origin is None:
            self._origin = (x, y)
        if self._retry is not None and self._try_again(obs):
            return
        if self.give_up_s > 0 and x <= self.until_x_mm and self._refused(obs):
            self.let_goes += 1
            asked = self._asking()
            assert self._still is not None
            # the refusal that stopped it (recorded while it braked, up to a second before it
            # stood), not an older one
            since = self._still[3] - 1.0
            said = next((text for t, text in reversed(obs.refusals) if t >= since), "")
            if asked == "turn" or "unknown_stop" in said:
                # the way needs more seen, or the chair's own trail under its tail: straight on
                after = "straight"
            else:
                after = "back" if self.kind == "joystick" else "none"
                self.lookahead = min(self.lookahead, 0.5 * self._aim_mm)
            self.let_go_log.append((obs.now_s, f"{asked}: {said}", after))
            self._retry = ("release", obs.now_s + self.let_go_s, obs.pose, after)
            self._still = None
            self._turning = 0
            self._hold("neutral", (0.0, 0.0), obs.now_s)
            return
        if math.hypot(x - self._origin[0], y - self._origin[1]) < self.straight_mm:
            # after start-up only straight ahead is seen: the rider drives on before steering
            self._hold("forward", (self.forward, 0.0), obs.now_s)
            return
        if x > self.until_x_mm:
            if self._head != "neutral" or self._stick != (0.0, 0.0):
                self._set("neutral", (0.0, 0.0), obs.now_s)
                self._head = "neutral"
            return
        c, s = math.cos(self.heading), math.sin(self.heading)
        along = (x - self.point[0]) * c + (y - self.point[1]) * s
        ax = self.point[0] + (along + self.lookahead) * c
        ay = self.point[1] + (along + self.lookahead) * s
        err = math.remainder(math.atan2(ay - y, ax - x) - th, 2.0 * math.pi)
        if self.kind == "joystick":
            # a hand pushes a small correction past the stick's dead zone (0.1)
            turn = math.copysign(min(1.0, 0.12 + 3.0 * abs(err)), err) if abs(err) > 0.01 else 0.0
            fwd = max(0.35, self.forward * (1.0 - 1.2 * abs(err)))
            self._hold("forward", (fwd, turn), obs.now_s)
            return
        if self._turning == 0 and abs(err) > self.on:
            self._turning = 1 if err > 0 else -1
        elif self._turning != 0 and abs(err) < self.off:
            self._turning = 0
        self._hold({1: "left", -1: "right", 0: "forward"}[self._turning], (0.0, 0.0), obs.now_s)


def _straight(kind: RiderKind, hold_s: float, start_s: float = 0.5) -> Any:
    if kind == "tilt":
        return head_script([("neutral", start_s), ("forward", hold_s)])
    return JoystickScript(((start_s, 0.6, 0.0), (start_s + hold_s, 0.0, 0.0)))


def _turn(kind: RiderKind, direction: str, hold_s: float, start_s: float) -> Any:
    if kind == "tilt":
        return head_script([("neutral", start_s), (direction, hold_s)])
    w = 0.6 if direction == "left" else -0.6
    return JoystickScript(((start_s, 0.0, w), (start_s + hold_s, 0.0, 0.0)))


def random_head(seed: int, duration_s: float) -> Any:
    """A head-tilt rider's random commands: forward (most), left, right, a pause — the tilt
    has no reverse (thesis 4.2.2). The same draw as :func:`omnid.sim.rider.random_ride`."""
    rng = np.random.default_rng(seed)
    moves = (("forward", 0.5, 2.0, 10.0), ("left", 0.2, 1.0, 4.0), ("right", 0.2, 1.0, 4.0),
             ("neutral", 0.1, 0.5, 2.0))  # fmt: skip
    p = np.array([m[1] for m in moves])
    steps: list[tuple[str, float]] = [("neutral", 0.5)]
    t = 0.5
    while t < duration_s:
        name, _, lo, hi = moves[int(rng.choice(len(moves), p=p / p.sum()))]
        hold = float(rng.uniform(lo, hi))
        steps += [(name, hold), ("neutral", 0.3)]
        t += hold + 0.9
    return head_script(steps)


# -- the scenarios --------------------------------------------------------------------------


def _approach(
    name: str,
    kind: RiderKind,
    seed: int,
    boxes: tuple[Box, ...] = (),
    drops: tuple[DropOff, ...] = (),
    heading_deg: float = 0.0,
    duration_s: float = 30.0,
) -> Trial:
    lateral, dth = _jitter(seed, 30.0, 3.0)
    start = (0.0, lateral, math.radians(heading_deg) + dth)
    course = _room(boxes, drops, x_range=(-1200.0, 6000.0), y_range=(-2500.0, 2500.0),
                   start=start, name=name)  # fmt: skip
    hazard = tuple(("box", i) for i in range(len(boxes))) + tuple(
        ("drop", i) for i in range(len(drops))
    )
    return Trial(name, kind, seed, course, duration_s, _straight(kind, duration_s),
                 chair_for(seed), hazard=hazard)  # fmt: skip


def thin_post(kind: RiderKind, seed: int) -> Trial:
    """A 40 mm post 1.8 m ahead of the axle (on the chair's path)."""
    return _approach("thin post", kind, seed, boxes=(Box(1800.0, 1840.0, -20.0, 20.0, 800.0),))


def threshold(kind: RiderKind, seed: int) -> Trial:
    """A 60 mm high, 80 mm deep threshold across the room."""
    return _approach("60 mm threshold", kind, seed,
                     boxes=(Box(1800.0, 1880.0, -2500.0, 2500.0, 60.0),))  # fmt: skip


def trench(kind: RiderKind, seed: int) -> Trial:
    """A trench 150 mm wide and 150 mm deep across the room."""
    return _approach("narrow trench", kind, seed,
                     drops=(DropOff(1800.0, 1950.0, -2500.0, 2500.0, 150.0),))  # fmt: skip


def oblique_wall(kind: RiderKind, seed: int) -> Trial:
    """A wall across the room approached at 35°."""
    return _approach("wall at 35°", kind, seed,
                     boxes=(Box(2300.0, 2400.0, -2500.0, 2500.0, 1000.0),), heading_deg=35.0)  # fmt: skip


def oblique_edge(kind: RiderKind, seed: int) -> Trial:
    """A drop-off edge (stairs down, 170 mm) approached at 40°."""
    return _approach("edge at 40°", kind, seed,
                     drops=(DropOff(2300.0, 4500.0, -2500.0, 2500.0, 170.0),), heading_deg=40.0)  # fmt: skip


def _turn_trial(name: str, kind: RiderKind, seed: int, seen: bool) -> Trial:
    """A wall parallel to the chair 250 mm beside its left side (face at y = 600); the rider
    turns right in place, which swings the tail left into the wall. ``seen``: the chair first
    drove 1.5 m along it (the laser saw the wall ahead of it); else it starts beside it."""
    lateral, dth = _jitter(seed, 20.0, 2.0)
    wall = Box(-1500.0, 4000.0, 600.0, 700.0, 1000.0)
    start = (0.0 if not seen else -1500.0 + 750.0 + 150.0, lateral, dth)
    course = _room((wall,), x_range=(-1500.0, 5000.0), y_range=(-2500.0, 1500.0), start=start,
                   name=name)  # fmt: skip
    if kind == "tilt":
        steps = [("neutral", 0.5)] + ([("forward", 9.0), ("neutral", 1.0)] if seen else [])
        rider: Any = head_script([*steps, ("right", 12.0)])
    else:
        moves: list[tuple[float, float, float]] = []
        t = 0.5
        if seen:
            moves += [(t, 0.6, 0.0), (t + 10.0, 0.0, 0.0)]
            t += 11.0
        moves += [(t, 0.0, -0.6), (t + 12.0, 0.0, 0.0)]
        rider = JoystickScript(tuple(moves))
    return Trial(name, kind, seed, course, 25.0 if seen else 14.0, rider, chair_for(seed),
                 hazard=(("box", 0),))  # fmt: skip


def turn_unseen_wall(kind: RiderKind, seed: int) -> Trial:
    return _turn_trial("turn beside an unseen wall", kind, seed, seen=False)


def turn_seen_wall(kind: RiderKind, seed: int) -> Trial:
    return _turn_trial("turn beside a seen wall", kind, seed, seen=True)


def _passage(name: str, kind: RiderKind, seed: int, width_mm: float, depth_mm: float,
             heading_deg: float = 10.0, lateral_mm: float = 80.0) -> Trial:  # fmt: skip
    """A partition across the room at x = 3500 with an opening ``width_mm`` wide (clear), as
    deep as ``depth_mm`` (100: a door frame; 3000: a corridor). The chair starts 3.5 m before
    it, up to ``lateral_mm`` off its centre line and ``heading_deg`` off its axis; the rider
    drives 1.4 m straight (start-up: only what lies ahead is seen), then steers through (pure
    pursuit on the joystick, turn-then-go on the head)."""
    lateral, dth = _jitter(seed, lateral_mm, heading_deg)
    h = width_mm / 2.0
    x0, x1 = 3500.0, 3500.0 + depth_mm
    boxes = (Box(x0, x1, -2500.0, -h, 1000.0), Box(x0, x1, h, 2500.0, 1000.0))
    course = _room(boxes, x_range=(-1200.0, x1 + 2500.0), y_range=(-2500.0, 2500.0),
                   start=(0.0, lateral, dth), name=name)  # fmt: skip
    through = x1 + FOOTPRINT[1] + 100.0  # the rear clear of the far side
    rider = LinePilot(kind, (0.0, 0.0), 0.0, until_x_mm=through + 200.0, start_s=0.7,
                      straight_mm=1400.0)  # fmt: skip
    duration = 14.0 + (depth_mm + 4000.0) / 90.0
    return Trial(name, kind, seed, course, duration, rider, chair_for(seed),
                 hazard=(("box", 0), ("box", 1)), opening=(x0, x1), goal_x_mm=through,
                 response=False)  # fmt: skip


def doorway(width_mm: float) -> Callable[[RiderKind, int], Trial]:
    def make(kind: RiderKind, seed: int) -> Trial:
        return _passage(f"doorway {width_mm:.0f} mm", kind, seed, width_mm, 100.0)

    make.__doc__ = f"A doorway {width_mm:.0f} mm clear (100 mm frame), approached within ±10°."
    return make


def corridor(kind: RiderKind, seed: int) -> Trial:
    """A corridor 950 mm wide and 3 m long, approached within ±5°."""
    return _passage("corridor 950 mm", kind, seed, 950.0, 3000.0, heading_deg=5.0,
                    lateral_mm=50.0)  # fmt: skip


def along_wall(kind: RiderKind, seed: int) -> Trial:
    """A wall 150 mm beside the chair's right side (face at y = −500), 5 m long; the rider
    drives along it (the joystick holding the line, the head straight on), the first 1.4 m
    straight as in the passages (at start-up the floor beside the tail is unseen: a correction
    there swings the tail into it, refused)."""
    lateral, dth = _jitter(seed, 15.0, 1.5)
    wall = Box(-1500.0, 5000.0, -600.0, -500.0, 1000.0)
    course = _room((wall,), x_range=(-1200.0, 6000.0), y_range=(-600.0, 2500.0),
                   start=(0.0, lateral, dth), name="along a wall at 150 mm")  # fmt: skip
    rider = LinePilot(kind, (0.0, 0.0), 0.0, until_x_mm=4200.0, start_s=0.7, straight_mm=1400.0)
    return Trial("along a wall at 150 mm", kind, seed, course, 40.0, rider, chair_for(seed),
                 hazard=(("box", 0),), opening=(0.0, 3800.0), goal_x_mm=3800.0,
                 response=False)  # fmt: skip


def reverse_unseen(kind: RiderKind, seed: int) -> Trial:
    """A box 300 mm behind the chair's rear, never seen; the rider reverses (the joystick: the
    head has no reverse, so the head rider turns round in place instead — its tail sweeps the
    unseen floor behind, the box in it)."""
    lateral, dth = _jitter(seed, 30.0, 3.0)
    box = Box(-1450.0, -1050.0, -300.0, 300.0, 600.0)
    course = _room((box,), x_range=(-2500.0, 4000.0), start=(0.0, lateral, dth),
                   name="reversing into the unseen")  # fmt: skip
    if kind == "joystick":
        rider: Any = JoystickScript(((0.5, -0.7, 0.0), (8.0, 0.0, 0.0)))
    else:
        rider = head_script([("neutral", 0.5), ("left", 10.0)])
    return Trial("reversing into the unseen", kind, seed, course, 12.0, rider, chair_for(seed),
                 hazard=(("box", 0),))  # fmt: skip


#: The soak's room (tests/scenarios/test_soak.py): six boxes 300–800 mm tall and a sunken corner.
ROOM_BOXES = (
    Box(800.0, 1200.0, 600.0, 1000.0, 400.0),
    Box(1500.0, 1900.0, -1300.0, -800.0, 600.0),
    Box(2600.0, 3000.0, 200.0, 700.0, 300.0),
    Box(3600.0, 4200.0, -600.0, -200.0, 800.0),
    Box(-600.0, -300.0, 1300.0, 1700.0, 500.0),
    Box(4800.0, 5200.0, 1000.0, 1500.0, 500.0),
)
ROOM_DROP = DropOff(5600.0, 7000.0, -2000.0, -600.0, 170.0)


def dense_room() -> tuple[tuple[Box, ...], tuple[DropOff, ...]]:
    """Clutter: the soak's room and five more boxes, three of them 40 mm posts (eleven boxes,
    300–900 mm tall, and the sunken corner)."""
    boxes = (
        *ROOM_BOXES,
        Box(2000.0, 2040.0, 1400.0, 1440.0, 900.0),
        Box(3300.0, 3340.0, 1200.0, 1240.0, 900.0),
        Box(900.0, 1300.0, -1800.0, -1500.0, 450.0),
        Box(5600.0, 6000.0, 300.0, 800.0, 700.0),
        Box(200.0, 240.0, -1100.0, -1060.0, 900.0),
    )
    return boxes, (ROOM_DROP,)


# -- the soak's setup (tests/scenarios/test_soak.py, tools/bench_soften.py) ------------------

#: The soak's safety changes: escape moves at 40 mm/s (off by default: with them the chair creeps
#: out of the pocket between the first three boxes), crossing the unseen at creep speed (the
#: blind random rider strands the chair under ``refuse``), and the staleness limit of the
#: stationary capture it runs on (a cloud every 0.5 s).
SOAK_SAFETY: dict[str, Any] = {
    "escape_speed_mm_s": 40.0,
    "unknown_policy": "creep",
    "perception_timeout_s": 1.5,
}


def soak_course() -> Course:
    """The cluttered room of the soak: :data:`ROOM_BOXES` and :data:`ROOM_DROP` in a walled room
    8 m long and 4 m wide, the chair 1 m from its back wall."""
    return _room(ROOM_BOXES, (ROOM_DROP,), x_range=(-1000.0, 7000.0), name="soak")


def soak_core(safety_changes: dict[str, Any] | None = None) -> Any:
    """The daemon's ``ControlCore`` as the soak runs it: the default configuration with the
    joystick, :data:`SOAK_SAFETY` (then ``safety_changes``), and the thesis' stationary capture
    instead of the shipped stream (36 000 stream clouds in the half hour do not fit CI)."""
    from omnid.daemon.core import ControlCore
    from omnid.sim.scenario import make_core as base

    cfg = base(joystick=True).config
    safety = dataclasses.replace(cfg.safety, **{**SOAK_SAFETY, **(safety_changes or {})})
    perception = dataclasses.replace(cfg.perception, capture="stationary")
    return ControlCore(dataclasses.replace(cfg, safety=safety, perception=perception))


def soak_settings() -> Any:
    """The soak's simulator settings: truth perception (the default physical laser's dots with
    their true classes), the daemon's configured rates, nothing stored per frame."""
    from omnid.sim.simulator import SimSettings

    return SimSettings(
        perception="truth",
        physics_dt_s=0.02,
        tilt_period_s=0.02,
        record_period_s=0.2,
        record_seen=False,
        stop_on_contact=False,
    )


def clutter(kind: RiderKind, seed: int, duration_s: float = 600.0) -> Trial:
    """Random riding for ``duration_s`` in a dense room (:func:`dense_room`)."""
    boxes, drops = dense_room()
    rng = np.random.default_rng([seed, 3])
    start = (0.0, float(rng.uniform(-100, 100)), float(rng.uniform(-0.3, 0.3)))
    course = _room(boxes, drops, x_range=(-1000.0, 7000.0), y_range=(-2000.0, 2000.0),
                   start=start, name="dense clutter")  # fmt: skip
    rider = random_ride(seed, duration_s) if kind == "joystick" else random_head(seed, duration_s)
    return Trial("dense clutter", kind, seed, course, duration_s, rider, chair_for(seed))


SCENARIOS: dict[str, Callable[[RiderKind, int], Trial]] = {
    "thin post": thin_post,
    "60 mm threshold": threshold,
    "narrow trench": trench,
    "wall at 35°": oblique_wall,
    "edge at 40°": oblique_edge,
    "turn beside a seen wall": turn_seen_wall,
    "turn beside an unseen wall": turn_unseen_wall,
    "doorway 780 mm": doorway(780.0),
    "doorway 820 mm": doorway(820.0),
    "doorway 850 mm": doorway(850.0),
    "doorway 900 mm": doorway(900.0),
    "corridor 950 mm": corridor,
    "along a wall at 150 mm": along_wall,
    "reversing into the unseen": reverse_unseen,
    "dense clutter": clutter,
}


# -- running and measuring ------------------------------------------------------------------


@dataclass
class TrialResult:
    """The truth measures of one trial (see the module docstring). Distances mm, times s."""

    scenario: str
    rider: RiderKind
    seed: int
    perception: str
    duration_s: float
    contacts: int
    falls: int
    false_stops: int  # events
    false_stop_s: float
    false_stops_unseen: int  # of which refused for space never seen (unknown_stop)
    stop_clearance_mm: float  # footprint to the hazard where the chair ended (nan: no hazard)
    min_clearance_mm: float  # footprint to the hazard, closest in the run
    hazard_to_limit_s: float  # hazard seen and in range → first limited command (nan, inf)
    stop_to_standstill_s: float  # first stop reason → standstill (nan: none)
    passed: bool | None  # through the opening (None: no opening)
    min_speed_in_opening_mm_s: float  # true mean wheel speed, slowest in it (nan: never in it)
    # passages (module docstring): the safety layer's stops before the chair got through —
    # events, those that began with the true footprint within the slow zone of the passage
    # (at the door), seconds, the reasons (control steps with each), and the least true
    # clearance (mm) to the passage at an event's start (nan: none)
    safety_stops: int
    safety_stops_at_door: int
    safety_stop_s: float
    safety_stop_reasons: dict[str, int]
    safety_stop_clearance_mm: float
    min_allowed_in_opening_mm_s: float  # forward speed the daemon allowed, slowest in it
    rider_own_s: float  # in it, the rider asking no travel: a pause or a turn in place
    rider_let_goes: int  # times the rider let go of a refused request (LinePilot) and retried
    distance_m: float
    refusals: dict[str, int]  # control steps with each refusal reason
    false_stop_reasons: dict[str, int]  # control steps of false stops with each reason
    wall_s: float


#: The columns of ``_RecordingCore.trace`` (one row per control step).
TRACE_COLUMNS = ("t_s", "forward", "turn", "asked", "refused", "limited", "allowed_v_mm_s",
                 "decision_clearance_mm")  # fmt: skip


class _RecordingCore:
    """Mixin for ``ControlCore``: keeps, per control step (:data:`TRACE_COLUMNS`), the rider's
    (forward, turn), whether the rider asked to move, whether the safety layer refused the
    command (limited it to zero: a **safety stop**) or limited it, the forward speed it allowed
    (mm/s; 0 when it decided nothing) and its clearance (mm)."""

    def _record_init(self) -> None:
        self.trace: list[tuple[float, ...]] = []

    def step(self, now_s: float) -> Any:
        cmd = super().step(now_s)  # type: ignore[misc]
        rep = self.last_report  # type: ignore[attr-defined]
        dem, dec = rep.demand, rep.decision
        asked = (not dem.stop) and (dem.forward != 0.0 or dem.turn != 0.0)
        refused = asked and ((dec is not None and dec.stopped) or "bump" in _names(rep.reasons))
        limited = asked and dec is not None and dec.scale < 1.0 and bool(dec.reasons)
        v = dec.v_mm_s if dec is not None else 0.0
        clear = dec.clearance_mm if dec is not None else math.nan
        self.trace.append((now_s, dem.forward, dem.turn, asked, refused, limited, v, clear))
        return cmd


def _names(reasons: Any) -> set[str]:
    return {str(getattr(r, "value", r)) for r in reasons}


def make_core(kind: RiderKind, config_changes: dict[str, Any] | None = None) -> Any:
    """The daemon's ``ControlCore`` (default configuration; the rider's input enabled, the other
    off — a silent enabled source would stop the chair), with safety settings
    ``config_changes`` applied, recording its decisions."""
    from omnid.daemon.core import ControlCore
    from omnid.sim.scenario import make_core as base

    core = base(joystick=kind == "joystick", tilt=kind == "tilt")
    cfg = core.config
    if config_changes:
        cfg = dataclasses.replace(cfg, safety=dataclasses.replace(cfg.safety, **config_changes))

    class Core(_RecordingCore, ControlCore):
        pass

    c = Core(cfg)
    c._record_init()
    return c


def _rects(course: Course, which: tuple[tuple[str, int], ...] | None = None) -> NDArray[np.float64]:
    w = course.world
    items: list[Any] = []
    if which is None:
        items = [b for b in w.boxes if b.height_mm >= 15.0]
        items += [d for d in w.dropoffs if d.depth_mm >= 30.0]
    else:
        items = [w.boxes[i] if k == "box" else w.dropoffs[i] for k, i in which]
    return np.array([(r.x_min_mm, r.x_max_mm, r.y_min_mm, r.y_max_mm) for r in items],
                    dtype=np.float64).reshape(-1, 4)  # fmt: skip


def _outline(rects: NDArray[np.float64], step_mm: float = 10.0) -> NDArray[np.float64]:
    """Points every ``step_mm`` along the outlines of rectangles (R, 4)."""
    out = []
    for x0, x1, y0, y1 in rects:
        nx = max(int((x1 - x0) / step_mm), 1) + 1
        ny = max(int((y1 - y0) / step_mm), 1) + 1
        xs, ys = np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)
        out += [np.column_stack([xs, np.full(nx, y0)]), np.column_stack([xs, np.full(nx, y1)]),
                np.column_stack([np.full(ny, x0), ys]), np.column_stack([np.full(ny, x1), ys])]  # fmt: skip
    return np.vstack(out) if out else np.zeros((0, 2))


def footprint_clearance_mm(pose: Any, rects: NDArray[np.float64]) -> float:
    """Distance (mm) from the true footprint at ``pose`` to the nearest rectangle (0 inside)."""
    if len(rects) == 0:
        return math.inf
    front, rear, width = FOOTPRINT
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    # rectangle corners and footprint corners: convex-polygon distance
    fx = np.array([front, front, -rear, -rear])
    fy = np.array([-width / 2, width / 2, width / 2, -width / 2])
    cx, cy = x + c * fx - s * fy, y + s * fx + c * fy
    dx = np.maximum(
        np.maximum(rects[None, :, 0] - cx[:, None], 0.0), cx[:, None] - rects[None, :, 1]
    )
    dy = np.maximum(
        np.maximum(rects[None, :, 2] - cy[:, None], 0.0), cy[:, None] - rects[None, :, 3]
    )
    d1 = float(np.hypot(dx, dy).min())
    bx = np.concatenate([rects[:, 0], rects[:, 0], rects[:, 1], rects[:, 1]])
    by = np.concatenate([rects[:, 2], rects[:, 3], rects[:, 2], rects[:, 3]])
    rx, ry = c * (bx - x) + s * (by - y), -s * (bx - x) + c * (by - y)
    ex = np.maximum(np.maximum(-rear - rx, rx - front), 0.0)
    ey = np.maximum(np.abs(ry) - width / 2, 0.0)
    d2 = float(np.hypot(ex, ey).min())
    inside = np.any((rects[:, 0] < x) & (rects[:, 1] > x) & (rects[:, 2] < y) & (rects[:, 3] > y))
    return 0.0 if inside else min(d1, d2)


def path_clearance_mm(
    pose: Any,
    v_mm_s: float,
    omega_rad_s: float,
    outline: NDArray[np.float64],
    horizon_mm: float = 5000.0,
) -> float:
    """How far (mm, travel of the footprint's fastest point) the true footprint at ``pose`` can
    move on its current twist before it touches ``outline`` (points, world frame): the distance
    the safety layer's rules are written in (:func:`omnid.daemon.safety.contact_path_s`),
    measured on truth. ``inf`` at rest or when nothing lies on the way within ``horizon_mm``."""
    from omnid.daemon.safety import contact_path_s

    front, rear, width = FOOTPRINT
    u = abs(v_mm_s) + abs(omega_rad_s) * math.hypot(rear, width / 2)
    if u < 1.0 or len(outline) == 0:
        return math.inf
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    dx, dy = outline[:, 0] - x, outline[:, 1] - y
    px, py = c * dx + s * dy, -s * dx + c * dy
    rect = (-rear, front, -width / 2, width / 2)
    return float(np.min(contact_path_s(px, py, v_mm_s, omega_rad_s, rect, u, horizon_mm)))


def way_clear(
    pose: Any, forward: float, turn: float, outline: NDArray[np.float64], core: Any
) -> bool:
    """Whether, by truth, the footprint grown by :data:`CLEAR_SPARE_MM` could move
    :data:`CLEAR_TRAVEL_MM` (fastest point) in the rider's asked direction without touching
    any box or drop-off (``outline``: their outline points, world frame)."""
    from omnid.daemon.safety import contact_path_s

    m = core.config.motion
    v = forward * (m.max_speed_mm_s if forward >= 0 else m.max_reverse_speed_mm_s)
    w = turn * m.max_turn_rate_rad_s
    front, rear, width = FOOTPRINT
    g = CLEAR_SPARE_MM
    r_max = math.hypot(rear + g, width / 2 + g)
    u = abs(v) + abs(w) * r_max
    if u <= 0.0 or len(outline) == 0:
        return True
    x, y, th = pose
    c, s = math.cos(th), math.sin(th)
    dx, dy = outline[:, 0] - x, outline[:, 1] - y
    near = dx * dx + dy * dy <= (CLEAR_TRAVEL_MM + r_max + 100.0) ** 2
    px, py = c * dx[near] + s * dy[near], -s * dx[near] + c * dy[near]
    rect = (-rear - g, front + g, -width / 2 - g, width / 2 + g)
    hit = contact_path_s(px, py, v, w, rect, u, CLEAR_TRAVEL_MM)
    return not bool(np.any(np.isfinite(hit)))


def simulate(
    trial: Trial,
    core: Any,
    perception: str = "truth",
    sim_changes: dict[str, Any] | None = None,
) -> tuple[Any, Any, NDArray[np.float64], NDArray[np.float64], float]:
    """Run ``trial`` on the simulator with the daemon's ``core``: (simulator, result, the core's
    trace, the result's steps, wall s), the trace and the steps cut to the same length.
    ``sim_changes``: :class:`~omnid.sim.settings.SimSettings` fields, these defaults included."""
    import time

    from omnid.sim.rider import HeadScript
    from omnid.sim.settings import SimSettings
    from omnid.sim.simulator import Simulator

    fields: dict[str, Any] = dict(record_seen=False, stop_on_contact=False, record_period_s=0.1)
    fields.update(sim_changes or {})
    settings = SimSettings(perception=perception, seed=trial.seed, **fields)  # type: ignore[arg-type]
    kw: dict[str, Any] = {}
    if isinstance(trial.rider_input, JoystickScript):
        kw["joystick"] = trial.rider_input
    elif isinstance(trial.rider_input, (HeadScript, ReactiveRider)):
        kw["rider"] = trial.rider_input
    sim = Simulator(trial.course, core, settings, chair_settings=trial.chair, **kw)
    w0 = time.perf_counter()
    result = sim.run(trial.duration_s)
    wall = time.perf_counter() - w0
    trace = np.array(core.trace, dtype=np.float64).reshape(-1, len(TRACE_COLUMNS))
    st = result.steps
    n = min(len(trace), len(st))
    return sim, result, trace[:n], st[:n], wall


def false_stop_steps(
    trace: NDArray[np.float64], st: NDArray[np.float64], outline: NDArray[np.float64], core: Any
) -> NDArray[np.bool_]:
    """The control steps that are false stops (module docstring): the rider asked to move, the
    chair stood still, and by truth (:func:`way_clear`) the way was clear."""
    false = np.zeros(len(st), dtype=bool)
    for i in np.flatnonzero((trace[:, 4] > 0) & (np.abs(st[:, 5]) < STANDSTILL_MM_S)):
        false[i] = way_clear(st[i, 2:5], trace[i, 1], trace[i, 2], outline, core)
    return false


def _run_starts(mask: NDArray[np.bool_]) -> NDArray[np.intp]:
    """Indices where a run of True in ``mask`` begins (one per event of consecutive steps)."""
    return np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8)])) == 1)


def run_trial(
    trial: Trial,
    perception: str = "truth",
    config_changes: dict[str, Any] | None = None,
    sim_changes: dict[str, Any] | None = None,
) -> TrialResult:
    """Run one trial with the daemon's core and measure it (see the module docstring);
    ``sim_changes``: further :class:`~omnid.sim.settings.SimSettings` fields (a slower
    perception worker: ``worker_period_s``)."""
    changes = {**trial.config, **(config_changes or {})}
    core = make_core(trial.rider, changes)
    sim, result, trace, st, wall = simulate(trial, core, perception, sim_changes)
    n = len(st)
    speed = np.abs(st[:, 5])
    poses = st[:, 2:5]
    everything = _rects(trial.course)
    outline = _outline(everything)
    false = false_stop_steps(trace, st, outline, core)
    starts = _run_starts(false)
    events = len(starts)
    unseen = sum("unknown_stop" in result.reasons_at(int(i)) for i in starts)
    period = float(np.median(np.diff(st[:, 0]))) if n > 1 else 0.02
    # hazards
    stop_clear_end = min_clear = math.nan
    to_limit = to_still = math.nan
    if trial.hazard:
        hz = _rects(trial.course, trial.hazard)
        stop_clear_end = footprint_clearance_mm(poses[-1], hz)
        min_clear = min(footprint_clearance_mm(p, hz) for p in poses[:: max(1, n // 400)])
        seen_s = _dot_times(sim, trial, result) if trial.response else np.zeros(0)
        sf = core.config.safety
        u = speed + 1e-9
        reach = np.where(u > sf.slow_speed_mm_s, sf.slow_distance_mm, 0.0)
        reach = np.maximum(reach, sf.stop_distance_mm + np.maximum(
            u * sf.approach_time_s, u * u / (2.0 * sf.brake_decel_mm_s2)))  # fmt: skip
        # the start: a dot on the hazard, and the hazard within reach along the chair's current
        # motion (how far the footprint can go before it touches it: an oblique wall 300 mm
        # from the footprint is 520 mm away along a 35° approach, and the rules limit on the
        # latter). The travel is never shorter than the nearest gap, so only the steps whose
        # gap is within reach are traced, in order, up to the first
        need: list[int] = []
        seen = np.isin(np.round(st[:, 0], 1), np.round(seen_s, 1))
        if np.any(seen):
            dt = np.gradient(st[:, 0]) if n > 1 else np.ones(n)
            omega = np.gradient(np.unwrap(poses[:, 2])) / np.maximum(dt, 1e-6) if n > 1 else dt * 0
            hz_outline = _outline(hz)
            for i in np.flatnonzero(seen):
                if footprint_clearance_mm(poses[i], hz) > reach[i] + sf.margin_mm:
                    continue
                travel = path_clearance_mm(poses[i], float(st[i, 5]), float(omega[i]), hz_outline)
                if travel <= reach[i] + sf.margin_mm:
                    need = [int(i)]
                    break
        limited = np.flatnonzero(trace[:, 5] > 0)
        if len(need):
            t_need = float(st[need[0], 0])
            earlier = limited[st[limited, 0] <= t_need + 1e-9]
            after = limited[st[limited, 0] >= t_need - 1e-9]
            if len(earlier) and st[earlier[-1], 0] >= t_need - 0.1:
                to_limit = 0.0  # limited already
            else:
                to_limit = float(st[after[0], 0] - t_need) if len(after) else math.inf
        stops = np.flatnonzero((st[:, 1].astype(np.int64) & result.reason_mask(
            "obstacle_stop", "dropoff_stop", "unknown_stop", "bump")) != 0)  # fmt: skip
        if len(stops):
            to_still = result.time_to_standstill(float(st[stops[0], 0]), STANDSTILL_MM_S)
    passed: bool | None = None
    min_in = min_allowed = stop_clear = math.nan
    n_stops, near_stops, stop_s, own_s = 0, 0, 0.0, 0.0
    stop_reasons: dict[str, int] = {}
    if trial.opening is not None and trial.goal_x_mm is not None:
        beyond = np.flatnonzero(poses[:, 0] > trial.goal_x_mm)
        passed = bool(len(beyond))
        until = int(beyond[0]) if passed else n  # the steps before the chair got through
        x0, x1 = trial.opening
        c = np.cos(poses[:, 2])
        front = poses[:, 0] + FOOTPRINT[0] * c
        rear = poses[:, 0] - FOOTPRINT[1] * c
        inside = (front > x0) & (rear < x1)
        inside[until:] = False
        # a safety stop: the rider asked to move and the safety layer limited it to zero
        refused = trace[:, 4] > 0
        refused[until:] = False
        stop_starts = _run_starts(refused)
        n_stops = len(stop_starts)
        stop_s = float(refused.sum()) * period
        for i in np.flatnonzero(refused):
            for r_name in result.reasons_at(int(i)):
                stop_reasons[r_name] = stop_reasons.get(r_name, 0) + 1
        if n_stops:
            hz_p = _rects(trial.course, trial.hazard)
            at = [footprint_clearance_mm(poses[int(i)], hz_p) for i in stop_starts]
            stop_clear = min(at)
            near_stops = sum(a <= core.config.safety.slow_distance_mm for a in at)
        if np.any(inside):
            min_in = float(speed[inside].min())
            # the rider's own: no travel asked (a pause, or a head rider's turn in place)
            own = inside & ((trace[:, 3] == 0) | (trace[:, 1] == 0.0))
            own_s = float(own.sum()) * period
            fwd = inside & (trace[:, 3] > 0) & (trace[:, 1] > 0.0)
            if np.any(fwd):
                min_allowed = float(trace[fwd, 6].min())
    refusal_counts: dict[str, int] = {}
    for i in np.flatnonzero(trace[:, 4] > 0):
        for name in result.reasons_at(int(i)):
            refusal_counts[name] = refusal_counts.get(name, 0) + 1
    false_reasons: dict[str, int] = {}
    for i in np.flatnonzero(false):
        for name in result.reasons_at(int(i)):
            false_reasons[name] = false_reasons.get(name, 0) + 1
    return TrialResult(
        trial.scenario, trial.rider, trial.seed, perception, result.duration_s,
        len(sim.chair.bump_log), len(result.falls), events, float(false.sum()) * period, unseen,
        stop_clear_end, min_clear, to_limit, to_still, passed, min_in, n_stops, near_stops, stop_s,
        stop_reasons, stop_clear, min_allowed, own_s,
        int(getattr(trial.rider_input, "let_goes", 0)),
        result.distance_mm / 1000.0, refusal_counts, false_reasons, wall,
    )  # fmt: skip


def _dot_times(sim: Any, trial: Trial, result: Any) -> NDArray[np.float64]:
    """The times (every 0.1 s of the run) at which a laser dot fell on a hazard (truth)."""
    from omnid.core.types import PointClass
    from omnid.sim.world import cast_laser, rig_to_world

    hz = _rects(trial.course, trial.hazard)
    traj = result.trajectory
    out: list[float] = []
    for t, x, y, th in traj[:: max(1, round(0.1 / max(sim.settings.record_period_s, 1e-3)))]:
        hits = cast_laser(trial.course.world, (x, y, th), sim.mount, sim.laser, sim.rig)
        vis = hits.visible & (hits.truth != PointClass.FLOOR)
        if not np.any(vis):
            continue
        w = rig_to_world(hits.xyz[vis], (x, y, th), sim.mount)
        on = np.zeros(len(w), dtype=bool)
        for x0, x1, y0, y1 in hz:
            on |= (
                (w[:, 0] >= x0 - 5)
                & (w[:, 0] <= x1 + 5)
                & (w[:, 1] >= y0 - 5)
                & (w[:, 1] <= y1 + 5)
            )
        if np.any(on):
            out.append(float(t))
    return np.array(out)
