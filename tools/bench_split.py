"""Benchmark: what splitting the blends near learned doubled beams costs ``perceive``, ONE core.

Random rigs of the evaluation (``omnid.experiments.rigs.rig_case(r, seed)``, calibrated on
their floor and extras as the tests' ``random_installations`` are): those whose laser model
holds doubled beams get split regions (``pipeline.split_regions``), the others none. Per rig,
its empty floor (capture seed ``--capture-seed``) is perceived with
``PerceptionSettings(split_doubled=True)`` (the default) and ``False``, the two called in turn
``--repeats`` times in this process (the machine's load falls on both alike; the machine may
be shared: prefer the ratios). Everything runs with cv2.setNumThreads(1) and one BLAS thread.

Printed per rig: the doubled beams the model holds, min and median ms of each setting, their
ratios; then, from a second pass with the pieces timed (the wrappers' overhead is not in the
first figures), the mean ms per ``perceive`` (both cameras) inside the split
(``detect._split_blends``), its one-vs-two test (``spotfit.blend_test``) and every
``spotfit.fit_spots`` call (with the split: the split pairs' joint fit and the dots the
neighbour pull does not resolve; without: the latter only), and how many blobs were tested.
The load average before and after.

Run from the repository root:  python tools/bench_split.py [--rigs 10] [--repeats 40]
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omnid.core import detect, spotfit  # noqa: E402
from omnid.core.pipeline import PerceptionSettings, perceive  # noqa: E402
from omnid.experiments import rigs as ev  # noqa: E402
from omnid.experiments.machine import load_average, one_core  # noqa: E402
from omnid.sim.world import World  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_perception_core import interleaved  # noqa: E402

#: The pieces timed in the second pass: (module, function name).
PIECES = ((detect, "_split_blends"), (spotfit, "blend_test"), (spotfit, "fit_spots"))


def pieces(run: Callable[[], object], repeats: int) -> dict[str, float]:
    """Mean ms per call of ``run`` spent in each of :data:`PIECES` (and ``tested``: blobs
    given to ``blend_test``), each piece wrapped by a timer for the pass."""
    spent = {name: 0.0 for _, name in PIECES}
    spent["tested"] = 0.0
    saved = [(mod, name, getattr(mod, name)) for mod, name in PIECES]

    def timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            if name == "blend_test":
                spent["tested"] += len(args[1])
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[name] += time.perf_counter() - t0

        return call

    try:
        for mod, name, fn in saved:
            setattr(mod, name, timed(name, fn))
        for _ in range(repeats):
            run()
    finally:
        for mod, name, fn in saved:
            setattr(mod, name, fn)
    return {k: (v if k == "tested" else 1e3 * v) / repeats for k, v in spent.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rigs", type=int, default=10, help="rigs 0 .. N-1 (10)")
    ap.add_argument("--seed", type=int, default=1, help="draws the rigs (1, as the tests)")
    ap.add_argument("--capture-seed", type=int, default=11, help="the floor capture's seed")
    ap.add_argument("--repeats", type=int, default=40, help="perceive calls per setting")
    args = ap.parse_args()
    print(one_core(cv2))
    on, off = PerceptionSettings(split_doubled=True), PerceptionSettings(split_doubled=False)
    print(
        f"{'rig':>3} {'doubled':>7} | {'split min':>9} {'med':>6} | {'off min':>7} {'med':>6} | "
        f"{'ratio min':>9} {'med':>5} | split in: {'split':>5} {'test':>5} {'fits':>5} "
        f"{'blobs':>5} | off: {'fits':>5}"
    )
    ratios: dict[bool, list[float]] = {True: [], False: []}
    for r in range(args.rigs):
        case = ev.rig_case(r, seed=args.seed)
        calib = ev.calibrate_case(case, seed=args.seed)
        doubled = 0 if calib.laser is None else int(np.count_nonzero(calib.laser.doubled()))
        _, cap = ev.capture(case, World(), seed=args.capture_seed)

        def run(settings: PerceptionSettings, cap=cap, calib=calib) -> Callable[[], object]:
            return lambda: perceive(cap, calib, "best", settings)

        (s_lo, s_med), (o_lo, o_med) = interleaved(run(on), run(off), args.repeats)
        p_on = pieces(run(on), max(args.repeats // 4, 5))
        p_off = pieces(run(off), max(args.repeats // 4, 5))
        ratios[doubled > 0].append(s_lo / o_lo)
        print(
            f"{r:3d} {doubled:7d} | {s_lo:9.2f} {s_med:6.2f} | {o_lo:7.2f} {o_med:6.2f} | "
            f"{s_lo / o_lo:9.3f} {s_med / o_med:5.3f} | ms       "
            f"{p_on['_split_blends']:5.2f} {p_on['blend_test']:5.2f} {p_on['fit_spots']:5.2f} "
            f"{p_on['tested']:5.1f} |      {p_off['fit_spots']:5.2f}",
            flush=True,
        )
    for has, name in ((True, "with"), (False, "without")):
        if ratios[has]:
            print(
                f"rigs {name} doubled beams: split / off {min(ratios[has]):.3f}–"
                f"{max(ratios[has]):.3f}x (min), median {float(np.median(ratios[has])):.3f}x"
            )
    print(f"load average after: {load_average()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
