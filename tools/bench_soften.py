"""Safety time of a closed-loop step: the CI soak's setup, timed per safety call (prints numbers).

    python tools/bench_soften.py                 # 2 simulated minutes, rider seed 7
    python tools/bench_soften.py --minutes 5 --seed 11

The setup is tests/scenarios/test_soak.py's (``omnid.sim.suite.soak_core`` and its course and
settings: truth perception, the default physical laser, the
cluttered room, the random joystick rider, escape moves at 40 mm/s, ``unknown_policy: creep``,
the stationary capture). ``SafetyLayer.check`` and ``SafetyLayer.soften`` are wrapped with a
``perf_counter`` timer (the same process, no profiler overhead); printed: wall time of the run,
control steps, the safety layer's total and per-step time, the softening share of it, how many
checks were softened and the candidates the softening evaluated (`_limit` calls inside it).
Timings on a shared machine are inflated by load: compare the ratios within one run, or runs
at the same load (the load average is printed).
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

from omnid.daemon.safety import Reason, SafetyLayer
from omnid.sim.rider import random_ride
from omnid.sim.simulator import Simulator
from omnid.sim.suite import soak_core, soak_course, soak_settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--minutes", type=float, default=2.0, help="simulated minutes (2)")
    ap.add_argument("--seed", type=int, default=7, help="rider seed (7, the CI soak's)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a safety setting (e.g. soften_side_shift_mm=0: straight requests not softened)",
    )
    args = ap.parse_args()
    duration_s = 60.0 * args.minutes

    totals = {"check": 0.0, "soften": 0.0}
    counts = {"check": 0, "soften": 0, "candidates": 0, "softened": 0}
    check0, soften0, limit0 = SafetyLayer.check, SafetyLayer.soften, SafetyLayer._limit
    in_soften = [False]

    def check(self, *a, **k):
        t = time.perf_counter()
        d = check0(self, *a, **k)
        totals["check"] += time.perf_counter() - t
        counts["check"] += 1
        counts["softened"] += Reason.SOFTENED in d.reasons
        return d

    def soften(self, *a, **k):
        t = time.perf_counter()
        in_soften[0] = True
        try:
            return soften0(self, *a, **k)
        finally:
            in_soften[0] = False
            totals["soften"] += time.perf_counter() - t
            counts["soften"] += 1

    def limit(self, *a, **k):
        counts["candidates"] += in_soften[0]
        return limit0(self, *a, **k)

    SafetyLayer.check, SafetyLayer.soften, SafetyLayer._limit = check, soften, limit  # type: ignore[method-assign]

    changes: dict[str, Any] = {}
    for item in args.set:
        key, _, value = item.partition("=")
        old = getattr(soak_core().config.safety, key)
        changes[key] = type(old)(value)
    core = soak_core(changes)
    sim = Simulator(
        soak_course(), core, soak_settings(), joystick=random_ride(args.seed, duration_s)
    )
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    result = sim.run(duration_s)
    wall = time.perf_counter() - t0
    steps = round(duration_s / core.config.control.period_s)
    print("settings:", " ".join(args.set) or "as the soak test")
    print(
        f"rider seed {args.seed}, {duration_s:.0f} simulated s, load {load0:.1f}..{os.getloadavg()[0]:.1f}"
    )
    print(f"run wall {wall:.2f} s, {steps} control steps, {result.distance_mm / 1000:.1f} m driven")
    print(
        f"safety check: {totals['check']:.2f} s total, {1e6 * totals['check'] / steps:.0f} us/step"
        f" ({counts['check']} checks)"
    )
    share = totals["soften"] / totals["check"] if totals["check"] else 0.0
    print(
        f"soften: {totals['soften']:.2f} s ({100 * share:.0f} % of safety), {counts['soften']} calls,"
        f" {counts['candidates']} candidates evaluated, {counts['softened']} checks softened"
    )


if __name__ == "__main__":
    main()
