"""Check: the detector's dots, blend split on and off, are the same as a reference tree's.

Renders camera images (the bench's floor + 300 mm box scene, ``RenderOptions.realistic()``) of
the default and the dense laser over nine capture seeds, runs ``detect._detect_best`` with ``split_blends`` False and True on every camera image, and writes
the dots to an ``.npz`` (``--save``) or compares them with one written earlier (``--compare``),
e.g. by another checkout (``PYTHONPATH=DIR python tools/check_split_same.py --save ref.npz``).
Prints, per setting, the images, the dots and the largest centre difference (px); fails (rc 1)
where a dot count differs or a centre moved more than ``--tol-px``.

Run from the repository root:  python tools/check_split_same.py --save ref.npz | --compare ref.npz
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from omnid.core import detect
from omnid.core.geometry import StereoRig
from omnid.sim.laser import LaserProjector
from omnid.sim.render import RenderOptions, render_capture


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
    args = ap.parse_args(argv)
    dots = detections()
    if args.save:
        np.savez(args.save, **dots)  # type: ignore[arg-type]
        print(f"{len(dots) // 2} images, {sum(len(v) for v in dots.values())} dots: {args.save}")
        return 0
    ref = np.load(args.compare)
    bad = 0
    for key in ("off", "on"):
        worst, count, n_img = 0.0, 0, 0
        for name, got in dots.items():
            if not name.startswith(key + "_"):
                continue
            want = ref[name]
            n_img += 1
            count += len(got)
            if got.shape != want.shape:
                print(f"{name}: {len(got)} dots, reference {len(want)}")
                bad += 1
                continue
            worst = max(worst, float(np.abs(got[:, :2] - want[:, :2]).max(initial=0.0)))
        print(
            f"split {key}: {n_img} images, {count} dots, largest centre difference {worst:.1e} px"
        )
        bad += worst > args.tol_px
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
