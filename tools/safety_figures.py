"""Safety figures of the daemon core on the simulator (docs/benchmarks/simulation.md).

Three measurements, all closed loop (``ControlCore`` with its default configuration, control
unit = emulator through the codec, rider through the joystick or GS311 emulator):

1. stopping distance vs speed — straight at a wall at 25/50/75/100 % of the core's
   ``motion.max_speed_mm_s``: the speed at the first stop/limit reason, the distance travelled
   from then to standstill, the final clearance against the config's promise, contacts;
2. false stops per minute of free driving — a random joystick rider in a large empty room; at
   every control step each reason is checked against the simulator's truth (a reason whose
   zone holds no box or drop-off by truth is false);
3. time from each injected fault to zero wheel speed.

Usage: ``python tools/safety_figures.py [--perception pipeline|truth] [--free-minutes M]``.
Prints one table per measurement and the wall time each took.

``--suite`` runs the safety scenario suite instead (:mod:`omnid.sim.suite`: a thin post, a
threshold, a trench, a wall and an edge approached obliquely, turning beside seen and unseen
walls, doorways 780–900 mm, a corridor, a wall at 150 mm, reversing into the unseen, dense
clutter), each with both riders and ``--seeds`` seeds, and prints the safety table of
docs/benchmarks.md, one row per scenario and rider::

    python tools/safety_figures.py --suite --perception pipeline --seeds 4 --clutter-minutes 10
    python tools/safety_figures.py --suite --set unknown_policy=creep --set escape_speed_mm_s=40
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from omnid.sim.chair import Chair
from omnid.sim.course import WALL_MM, Course, walls
from omnid.sim.results import clearance_mm, footprint_perimeter
from omnid.sim.rider import JoystickScript, head_script, random_ride
from omnid.sim.scenario import make_core
from omnid.sim.simulator import Fault, SimResult, SimSettings, Simulator
from omnid.sim.world import World

STANDSTILL_MM_S = 2.0  # "wheels at zero": both slower than this (as the scenario suite)
ZONE_REASONS = ("obstacle_stop", "dropoff_stop", "slow_zone", "approach")
FAULT_KINDS = (
    "tilt_unplugged",
    "camera_stopped",
    "cu_silent",
    "cu_corrupt",
    "perception_exception",
)


def room(x_front_mm: float, half_width_mm: float = 2000.0, x_back_mm: float = -1000.0) -> Course:
    """An empty walled room; the chair starts at the origin facing +x, the front wall's face at
    ``x_front_mm``."""
    x0, x1, y0, y1 = x_back_mm, x_front_mm, -half_width_mm, half_width_mm
    return Course(
        "safety",
        World(boxes=walls(x0, x1, y0, y1)),
        (0.0, 0.0, 0.0),
        (x0 - WALL_MM, x1 + WALL_MM),
        (y0 - WALL_MM, y1 + WALL_MM),
    )


def truth_clearance_mm(course: Course, poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance (mm) from the chair's true footprint at each pose (N, 3) to the nearest box or
    drop-off of the world."""
    w = course.world
    rects = np.array(
        [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm) for b in (*w.boxes, *w.dropoffs)],
        dtype=np.float64,
    ).reshape(-1, 4)
    chair = Chair(pose=(0.0, 0.0, 0.0))
    out = np.empty(len(poses))
    for i, (x, y, th) in enumerate(poses):
        chair.x_mm, chair.y_mm, chair.theta_rad = float(x), float(y), float(th)
        out[i] = clearance_mm(footprint_perimeter(chair, per_side=8), rects)
    return out


# -- 1. stopping distance vs speed ---------------------------------------------------------------


@dataclass
class StopRow:
    fraction: float
    speed_at_reason_mm_s: float
    first_reason: str
    t_reason_s: float
    travel_to_standstill_mm: float
    time_to_standstill_s: float
    final_clearance_mm: float
    min_clearance_mm: float
    contacts: int
    wall_s: float


def stopping_run(fraction: float, perception: str, seed: int) -> StopRow:
    core = make_core(joystick=True)
    cfg = core.config  # type: ignore[attr-defined]
    v = fraction * cfg.motion.max_speed_mm_s
    # The wall: far enough for ~4 s of cruising after the map has filled, then the stop.
    front = cfg.safety.footprint_front_mm
    x_wall = front + 1500.0 + 4.0 * v
    duration = 1.0 + (x_wall - front) / v + 25.0  # the approach limit creeps to the stop line
    stick = JoystickScript(((0.5, fraction, 0.0),))
    settings = SimSettings(perception=perception, seed=seed, record_seen=False)  # type: ignore[arg-type]
    course = room(x_wall, x_back_mm=-2500.0)  # the back wall far from the rear
    w0 = time.perf_counter()
    r = Simulator(course, core, settings, joystick=stick).run(duration)
    wall = time.perf_counter() - w0
    st = r.steps
    zone = r.reason_mask(*ZONE_REASONS)
    hit = np.flatnonzero((st[:, 1].astype(np.int64) & zone) != 0)
    if len(hit) == 0:
        return StopRow(fraction, math.nan, "none", math.nan, math.nan, math.inf, math.nan,
                       r.min_clearance_mm, len(r.contacts), wall)  # fmt: skip
    i = int(hit[0])
    t_reason = float(st[i, 0])
    took = r.time_to_standstill(t_reason, STANDSTILL_MM_S)
    traj = r.trajectory
    sel = (traj[:, 0] >= t_reason) & (traj[:, 0] <= t_reason + took + 1e-9)
    path = traj[sel, 1:3]
    travel = float(np.sum(np.hypot(*np.diff(path, axis=0).T))) if len(path) > 1 else 0.0
    final = float(truth_clearance_mm(course, traj[-1:, 1:4])[0])
    return StopRow(
        fraction,
        abs(float(st[i, 5])),
        "+".join(n for n in r.reasons_at(i) if n in ZONE_REASONS),
        t_reason,
        travel,
        took,
        final,
        r.min_clearance_mm,
        len(r.contacts),
        wall,
    )


# -- 2. false stops per minute ------------------------------------------------------------------


@dataclass
class FreeDrive:
    minutes: float
    distance_m: float
    steps: int
    counts: dict[str, tuple[int, int, int]]  # reason: (steps with it, false steps, false events)
    min_truth_clearance_mm: float
    contacts: int
    wall_s: float


def zone_of(reason: str, core: object) -> float:
    """How far ahead (mm of the fastest footprint point's travel, margin included) a reason
    claims something lies, at most."""
    cfg = core.config  # type: ignore[attr-defined]
    s = cfg.safety
    u_max = cfg.motion.max_speed_mm_s + cfg.motion.max_turn_rate_rad_s * core.safety.r_max_mm  # type: ignore[attr-defined]
    if reason in ("obstacle_stop", "dropoff_stop"):
        return float(s.stop_distance_mm)
    if reason == "slow_zone":
        return float(s.slow_distance_mm)
    if reason == "approach":  # u > min(room / T, sqrt(2 a room)) → room < max(u T, u²/2a)
        return float(s.stop_distance_mm + max(u_max * s.approach_time_s,
                                              u_max**2 / (2 * s.brake_decel_mm_s2)))  # fmt: skip
    return math.inf  # unknown_ahead, perception_stale, ...: no claim about an obstacle


def free_drive(minutes: float, perception: str, seed: int) -> tuple[FreeDrive, SimResult]:
    """A random joystick rider in a 40 m x 40 m empty room starting in its middle: in a few
    minutes at ≤ 240 mm/s the chair stays well over 1 m from every wall (checked)."""
    core = make_core(joystick=True)
    duration = 60.0 * minutes
    course = room(20000.0, half_width_mm=20000.0, x_back_mm=-20000.0)
    settings = SimSettings(perception=perception, seed=seed, record_seen=False)  # type: ignore[arg-type]
    w0 = time.perf_counter()
    r = Simulator(course, core, settings, joystick=random_ride(seed, duration)).run(duration)
    wall = time.perf_counter() - w0
    st = r.steps
    clear = truth_clearance_mm(course, st[:, 2:5])
    cell = float(core.grid.settings.resolution_mm)  # type: ignore[attr-defined]
    margin = float(core.config.safety.margin_mm)  # type: ignore[attr-defined]
    masks = st[:, 1].astype(np.int64)
    counts: dict[str, tuple[int, int, int]] = {}
    for name in r.reason_names:
        on = (masks & r.reason_mask(name)) != 0
        # false: by truth nothing lies within the reason's zone (one map cell of slack)
        false = on & (clear - margin - cell > zone_of(name, core))
        events = int(np.count_nonzero(np.diff(np.concatenate([[0], false.astype(np.int8)])) == 1))
        counts[name] = (int(on.sum()), int(false.sum()), events)
    fd = FreeDrive(
        minutes, r.distance_mm / 1000.0, len(st), counts, float(clear.min()), len(r.contacts), wall
    )
    return fd, r


# -- 3. faults ----------------------------------------------------------------------------------


@dataclass
class FaultRow:
    kind: str
    rider: str
    speed_at_fault_mm_s: float
    to_standstill_s: float
    travel_mm: float
    recovered: bool
    wall_s: float


def fault_run(kind: str, perception: str, seed: int, rider: str) -> FaultRow:
    core = make_core(joystick=rider == "joystick")
    t0, t1, end = 8.0, 11.0, 15.0
    settings = SimSettings(perception=perception, seed=seed, record_seen=False)  # type: ignore[arg-type]
    kw: dict[str, object] = {}
    if rider == "joystick":
        kw["joystick"] = JoystickScript(((0.5, 1.0, 0.0),))
    else:
        kw["rider"] = head_script([("neutral", 0.5), ("forward", 30.0)])
    sim = Simulator(room(12000.0), core, settings, faults=(Fault(kind, t0, t1),), **kw)  # type: ignore[arg-type]
    w0 = time.perf_counter()
    r = sim.run(end)
    wall = time.perf_counter() - w0
    took = r.time_to_standstill(t0, STANDSTILL_MM_S)
    w = r.wheel_speeds
    at = w[np.searchsorted(w[:, 0], t0), 1:]
    traj = r.trajectory
    sel = (traj[:, 0] >= t0) & (traj[:, 0] <= t0 + took + 1e-9)
    path = traj[sel, 1:3]
    travel = float(np.sum(np.hypot(*np.diff(path, axis=0).T))) if len(path) > 1 else 0.0
    return FaultRow(
        kind, rider, float(np.mean(np.abs(at))), took, travel,
        r.max_speed_between(t1, end) > 50.0, wall,
    )  # fmt: skip


# -- 4. the scenario suite -------------------------------------------------------------------


def _median(xs: list[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return float(np.median(xs)) if xs else math.nan


def _fmt(x: float, unit: str = "", digits: int = 0) -> str:
    if math.isnan(x):
        return "—"
    if math.isinf(x):
        return "never"
    return f"{x:.{digits}f}{unit}"


def suite(args: argparse.Namespace) -> int:
    """Run the scenario suite (module docstring) and print its table."""
    from omnid.sim.suite import RIDERS, SCENARIOS, clutter, run_trial

    changes: dict[str, object] = {}
    for item in args.set:
        key, _, value = item.partition("=")
        flags = {"true": True, "false": False}
        changes[key] = flags[value.lower()] if value.lower() in flags else value \
            if not value.replace(".", "", 1).replace("-", "", 1).isdigit() else float(value)  # fmt: skip
    names = [n for n in SCENARIOS if not args.scenarios or n in args.scenarios.split(",")]
    sim_changes = (
        None if args.perceive_time_s is None else {"perceive_time_s": args.perceive_time_s}
    )
    print(f"suite: {len(names)} scenarios x {len(RIDERS)} riders x {args.seeds} seeds, "
          f"perception {args.perception}, safety changes {changes or 'none'}", flush=True)  # fmt: skip
    print("| scenario | rider | runs | contacts | falls | false stops (unseen) | per 10 min "
          "| closest (median, least) | stopped at | stop → standstill | hazard → first limit "
          "(median, worst) | through | safety stops before through (s; reasons at least clearance) "
          "| slowest allowed in it | rider's own pauses/turns in it, let-goes | wall |")  # fmt: skip
    print("| --- " * 16 + "|")
    failed = False
    w_all = time.perf_counter()
    for name in names:
        for rider in RIDERS:
            rows = []
            for seed in range(args.seeds):
                if name == "dense clutter":
                    trial = clutter(rider, seed, 60.0 * args.clutter_minutes)
                else:
                    trial = SCENARIOS[name](rider, seed)
                rows.append(run_trial(trial, args.perception, changes, sim_changes))
            minutes = sum(r.duration_s for r in rows) / 60.0
            fs = sum(r.false_stops for r in rows)
            fs_unseen = sum(r.false_stops_unseen for r in rows)
            contacts = sum(r.contacts for r in rows)
            falls = sum(r.falls for r in rows)
            failed |= falls > 0
            stops = [r.stop_clearance_mm for r in rows]
            closest = [r.min_clearance_mm for r in rows]
            lim = [r.hazard_to_limit_s for r in rows]
            still = [r.stop_to_standstill_s for r in rows]
            passed = [r for r in rows if r.passed is not None]
            through = stopped = allowed = own = "—"
            if passed:
                slowest = [r.min_speed_in_opening_mm_s for r in passed if r.passed]
                through = (f"{sum(bool(r.passed) for r in passed)}/{len(passed)} "
                           f"(true slowest {_fmt(min(slowest) if slowest else math.nan, ' mm/s')})")  # fmt: skip
                reasons: dict[str, int] = {}
                for r in passed:
                    for k, v in r.safety_stop_reasons.items():
                        reasons[k] = reasons.get(k, 0) + v
                clear = [r.safety_stop_clearance_mm for r in passed if r.safety_stops]
                stopped = (f"{sum(r.safety_stops for r in passed)}, at the door "
                           f"{sum(r.safety_stops_at_door for r in passed)} "
                           f"({sum(r.safety_stop_s for r in passed):.1f} s"
                           + (f"; {', '.join(sorted(reasons))} at "
                              f"{_fmt(min(clear), ' mm')}" if clear else "") + ")")  # fmt: skip
                fast = [r.min_allowed_in_opening_mm_s for r in passed
                        if not math.isnan(r.min_allowed_in_opening_mm_s)]  # fmt: skip
                allowed = _fmt(min(fast, default=math.nan), " mm/s")
                own = (f"{sum(r.rider_own_s for r in passed):.1f} s, "
                       f"let go {sum(r.rider_let_goes for r in passed)}")  # fmt: skip
            finite = [x for x in lim if math.isfinite(x)]
            print(
                f"| {name} | {rider} | {len(rows)} | {contacts} | {falls} "
                f"| {fs} ({fs_unseen}) | {10.0 * fs / minutes:.1f} "
                f"| {_fmt(_median(closest), ' mm')}, {_fmt(min(closest) if closest else math.nan, ' mm')} "
                f"| {_fmt(_median(stops), ' mm')} "
                f"| {_fmt(_median(still), ' s', 2)} "
                f"| {_fmt(_median(lim), ' s', 2)}, {_fmt(max(finite) if finite else math.nan, ' s', 2)} "
                f"| {through} | {stopped} | {allowed} | {own} | {sum(r.wall_s for r in rows):.0f} s |",
                flush=True,
            )  # fmt: skip
    print(f"\ntotal wall time {time.perf_counter() - w_all:.0f} s")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    ap.add_argument("--suite", action="store_true", help="run the scenario suite (docstring)")
    ap.add_argument("--seeds", type=int, default=3, help="suite: seeds per scenario and rider")
    ap.add_argument("--scenarios", default="", help="suite: comma list of scenario names")
    ap.add_argument("--clutter-minutes", type=float, default=10.0)
    ap.add_argument("--set", action="append", default=[], help="suite: safety KEY=VALUE")
    ap.add_argument(
        "--perceive-time-s",
        type=float,
        default=None,
        help="suite: charge this much virtual time per cloud instead of perceive's wall time, so "
        "that the runs are the same however loaded the machine is (SimSettings.perceive_time_s)",
    )
    ap.add_argument("--perception", choices=("pipeline", "truth"), default="pipeline")
    ap.add_argument("--fault-perception", choices=("pipeline", "truth"), default="pipeline")
    ap.add_argument("--free-minutes", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fractions", default="0.25,0.5,0.75,1.0")
    ap.add_argument("--skip", default="", help="comma list of stop,free,faults to skip")
    args = ap.parse_args(argv)
    if args.suite:
        import logging

        logging.disable(logging.ERROR)
        return suite(args)
    skip = set(filter(None, args.skip.split(",")))
    w_all = time.perf_counter()
    core = make_core()
    cfg = core.config  # type: ignore[attr-defined]
    print(
        f"config: max_speed {cfg.motion.max_speed_mm_s:.0f} mm/s, stop_distance "
        f"{cfg.safety.stop_distance_mm:.0f} mm, margin {cfg.safety.margin_mm:.0f} mm, slow zone "
        f"{cfg.safety.slow_distance_mm:.0f} mm at {cfg.safety.slow_speed_mm_s:.0f} mm/s, "
        f"emergency decel {cfg.motion.emergency_decel_mm_s2:.0f} mm/s², capture cap "
        f"{cfg.perception.capture_speed_mm_s:.0f} mm/s ({cfg.perception.capture_policy})"
    )
    failed = False
    if "stop" not in skip:
        print(f"\n1. stopping distance vs speed (perception {args.perception})")
        print("| speed | at first reason | reason | travel to standstill | time | final clearance "
              "| closest | contacts | wall |")  # fmt: skip
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for f in (float(x) for x in args.fractions.split(",")):
            row = stopping_run(f, args.perception, args.seed)
            failed |= row.contacts > 0 or row.final_clearance_mm < cfg.safety.margin_mm
            print(
                f"| {100 * f:.0f} % ({f * cfg.motion.max_speed_mm_s:.0f} mm/s) "
                f"| {row.speed_at_reason_mm_s:.0f} mm/s | {row.first_reason} "
                f"| {row.travel_to_standstill_mm:.0f} mm | {row.time_to_standstill_s:.2f} s "
                f"| {row.final_clearance_mm:.0f} mm | {row.min_clearance_mm:.0f} mm "
                f"| {row.contacts} | {row.wall_s:.1f} s |",
                flush=True,
            )
    if "free" not in skip:
        print(f"\n2. free driving, {args.free_minutes:g} min (perception {args.perception})")
        fd, _r = free_drive(args.free_minutes, args.perception, args.seed)
        print(
            f"distance {fd.distance_m:.1f} m, {fd.steps} control steps, closest wall "
            f"{fd.min_truth_clearance_mm:.0f} mm, contacts {fd.contacts}, wall {fd.wall_s:.1f} s"
        )
        print("| reason | steps with it | false steps | false events | false events/min |")
        print("| --- | --- | --- | --- | --- |")
        total = 0
        for name, (n, nf, ev) in sorted(fd.counts.items()):
            zone = zone_of(name, core)
            if math.isfinite(zone):
                total += ev
                print(f"| {name} (zone {zone:.0f} mm) | {n} | {nf} | {ev} "
                      f"| {ev / fd.minutes:.2f} |")  # fmt: skip
            else:
                print(f"| {name} (no obstacle claim) | {n} | — | — | — |")
        print(f"false stop/limit events per minute: {total / fd.minutes:.2f}")
        failed |= fd.contacts > 0
    if "faults" not in skip:
        print(f"\n3. fault → wheels at zero (< {STANDSTILL_MM_S:g} mm/s), perception "
              f"{args.fault_perception}")  # fmt: skip
        print("| fault | rider | speed at fault | to standstill | travel | recovered | wall |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        runs = [(k, "joystick") for k in FAULT_KINDS] + [("tilt_unplugged", "head tilt")]
        for kind, rider in runs:
            fr = fault_run(kind, args.fault_perception, args.seed, rider)
            failed |= not math.isfinite(fr.to_standstill_s)
            print(
                f"| {fr.kind} | {fr.rider} | {fr.speed_at_fault_mm_s:.0f} mm/s "
                f"| {fr.to_standstill_s:.2f} s | {fr.travel_mm:.0f} mm "
                f"| {'yes' if fr.recovered else 'no'} | {fr.wall_s:.1f} s |",
                flush=True,
            )
    print(f"\ntotal wall time {time.perf_counter() - w_all:.1f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
