"""Evaluate the perception pipeline on the simulator's scenes with a misaligned rig.

Thin wrapper over :mod:`omnid.experiments.scenes` (what is measured and the targets are
described there). Run:  python tools/eval_scenes.py [--scenes three_boxes,dropoff] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys

from omnid.experiments.scenes import format_scores, run_scenes
from omnid.sim.scenes import scene_names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", default=",".join(scene_names()), help="comma-separated scene names")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    calib, rig, scores = run_scenes(args.scenes.split(","), args.seed)
    print(format_scores(calib, rig, scores))
    return 0


if __name__ == "__main__":
    sys.exit(main())
