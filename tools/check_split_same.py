"""Check: the detector's dots, blend split on and off, are the same as a reference tree's.

Renders camera images (the bench's floor + 300 mm box scene, ``RenderOptions.realistic()``) of
the default and the dense laser over nine capture seeds, runs ``detect._detect_best`` with ``split_blends`` False and True on every camera image, and writes
the dots to an ``.npz`` (``--save``) or compares them with one written earlier (``--compare``),
e.g. by another checkout (``PYTHONPATH=DIR python tools/check_split_same.py --save ref.npz``).
Prints, per setting, the images, the dots and the largest centre difference (px); fails (rc 1)
where a dot count differs or a centre moved more than ``--tol-px``. With ``--repeats N``, also
the detector's time on both cameras of each laser's seed-3 capture, split off and on: thread
time, min of N (one core), in turns — run it with each tree's ``PYTHONPATH`` alternately.

Run from the repository root:  python tools/check_split_same.py --save ref.npz | --compare ref.npz
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from omnid.core import detect  # noqa: E402
from omnid.core.geometry import StereoRig  # noqa: E402
from omnid.sim.laser import LaserProjector  # noqa: E402
from omnid.sim.render import RenderOptions, render_capture  # noqa: E402


def images() -> list[tuple[np.ndarray, np.ndarray]]:
    """(mask, base) camera images: 2 lasers × 9 capture seeds × 2 cameras = 36."""
    sys.path.insert(0, "tools")
    from bench_perception_core import LASERS, scene

    rig = StereoRig.nominal()
    opts = RenderOptions.realistic()
    out = []
    for name in ("default", "dense"):
        laser: LaserProjector = LASERS[name]()
        xyz = scene(rig, laser)
        for seed in range(9):
            cap = render_capture(rig, xyz, opts, seed=seed)
            out += [(cap.mask1, cap.base1), (cap.mask2, cap.base2)]
    return out


def thread_ms(images_: list[tuple[np.ndarray, np.ndarray]], repeats: int) -> tuple[float, float]:
    """Min thread time (ms) of the detector on all of ``images_``, split off and on, in turns."""
    params = detect.DetectionParams()
    best = {False: np.inf, True: np.inf}
    for _ in range(repeats + 1):  # (the first: warm-up)
        for split in (False, True):
            t0 = time.thread_time()
            for mask, base in images_:
                detect._detect_best(mask, base, params, split_blends=split)
            best[split] = min(best[split], 1e3 * (time.thread_time() - t0))
    return best[False], best[True]


def detections() -> dict[str, np.ndarray]:
    """Every image's dots (N, 3), split off and on, keyed ``off_<i>`` / ``on_<i>``."""
    params = detect.DetectionParams()
    out = {}
    for i, (mask, base) in enumerate(images()):
        for key, split in (("off", False), ("on", True)):
            out[f"{key}_{i}"] = detect._detect_best(mask, base, params, split_blends=split)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = ap.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", help="write the dots to this .npz")
    group.add_argument("--compare", help="compare the dots with this .npz")
    ap.add_argument("--tol-px", type=float, default=1e-9, help="largest centre difference, px")
    ap.add_argument("--repeats", type=int, default=0, help="also time the detector (min of N)")
    args = ap.parse_args(argv)
    if args.repeats:
        import cv2

        cv2.setNumThreads(1)
        caps = images()
        for name, first in (("default", 3 * 2), ("dense", 9 * 2 + 3 * 2)):
            off, on = thread_ms(caps[first : first + 2], args.repeats)
            print(f"{name} laser, both cameras: {off:.2f} ms, split {on:.2f} ms (+{on - off:.2f})")
    dots = detections()
    if args.save:
        np.savez(args.save, **dots)  # type: ignore[arg-type]
        print(f"{len(dots) // 2} images, {sum(len(v) for v in dots.values())} dots: {args.save}")
        return 0
    ref = np.load(args.compare)
    bad = 0
    for key in ("off", "on"):
        worst, rest, count, n_img = 0.0, 0.0, 0, 0
        for name, got in dots.items():
            if not name.startswith(key + "_"):
                continue
            if name not in ref:
                print(f"{name}: not in the reference {args.compare}")
                bad += 1
                continue
            want = ref[name]
            n_img += 1
            count += len(got)
            if got.shape != want.shape:
                print(f"{name}: {len(got)} dots, reference {len(want)}")
                bad += 1
                continue
            worst = max(worst, float(np.abs(got[:, :2] - want[:, :2]).max(initial=0.0)))
            rest = max(rest, float(np.abs(got[:, 2:] - want[:, 2:]).max(initial=0.0)))
        print(
            f"split {key}: {n_img} images, {count} dots, largest centre difference {worst:.1e} px"
            f" (the other columns: {rest:.1e})"
        )
        bad += worst > args.tol_px or rest > args.tol_px
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
