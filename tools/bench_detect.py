"""Benchmark of laser dot detection on rendered 640x480 captures (~870 dots per camera).

Prints, on ONE core (cv2.setNumThreads(1), one BLAS thread), min and median of ``--repeats``
runs, and the load average (the machine may be shared: prefer the min and the ratios, which
are measured in the same run):

- the renderer (both cameras, realistic options), now and at ``--before``;
- per scene: the ``best`` detector now, ``best`` at ``--before`` (the code before the speed
  work, loaded from git), the vectorised thesis detector, and trackpy.locate on the same
  subtracted images, each with its accuracy (centre RMS vs truth, recall, false positives);
- the vectorised thesis detector against its direct loop transcription
  (tests/core/thesis_oracle.py): ratio and whether they find the same dots;
- with ``--instructions``: instructions per ``best`` detection (one camera) now and at
  ``--before``, counted by valgrind's callgrind (stable on a loaded machine; slow, ~1 min).

Run from the repository root:
    python tools/bench_detect.py [--repeats 30] [--before 3ee7d83] [--no-oracle] [--instructions]
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from omnid.core.detect import DetectionParams, detect_dots, to_gray  # noqa: E402
from omnid.core.geometry import StereoRig  # noqa: E402
from omnid.sim.laser import ideal_lattice  # noqa: E402
from omnid.sim.render import RenderOptions, SpotModel, render_capture, visible_truth  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
EDGE_MARGIN_PX = 4.0
#: The last commit before the speed work on the best detector and the renderer.
DEFAULT_BEFORE = "3ee7d83"


def score(found: np.ndarray, truth: np.ndarray, cam, tol_px: float = 1.5):
    """(recall, false positives, centre RMS px) with one-to-one nearest-neighbour matching."""
    found = found[cam.in_disk(found[:, :2], EDGE_MARGIN_PX)] if len(found) else found
    if len(found) == 0:
        return 0.0, 0, float("nan")
    d = np.hypot(found[:, None, 0] - truth[None, :, 0], found[:, None, 1] - truth[None, :, 1])
    j = d.argmin(axis=1)
    i = d.argmin(axis=0)
    mutual = (i[j] == np.arange(len(found))) & (d.min(axis=1) < tol_px)
    err = found[mutual, :2] - truth[j[mutual]]
    return mutual.sum() / len(truth), int((~mutual).sum()), float(np.sqrt((err**2).sum(1).mean()))


def timed(fn, repeats: int) -> tuple[float, float]:
    """(min, median) wall time of ``fn`` in ms over ``repeats`` runs after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * min(times), 1e3 * statistics.median(times)


def load_module_at(rev: str, path: str, name: str) -> types.ModuleType | None:
    """The module at ``path`` as it was at git revision ``rev`` (None outside a checkout)."""
    try:
        src = subprocess.run(
            ["git", "show", f"{rev}:{path}"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    mod = types.ModuleType(name)
    mod.__file__ = f"{rev}:{path}"
    sys.modules[name] = mod  # dataclasses look their module up
    exec(compile(src, mod.__file__, "exec"), mod.__dict__)
    return mod


def trackpy_locate(sub: np.ndarray, minmass: float) -> np.ndarray:
    import trackpy

    df = trackpy.locate(sub, 7, minmass=minmass, separation=5, engine="numba")
    return df[["y", "x", "mass"]].to_numpy(dtype=np.float64)


def scene() -> tuple[StereoRig, np.ndarray]:
    rig = StereoRig.nominal()
    return rig, ideal_lattice(30, 35, 0.07, 0.28).on_plane(rig.floor_depth_mm)


def count_mode(which: str, n: int, before: str) -> int:
    """Run ``n`` best detections of one camera (``which`` = now | before) or ``n`` realistic
    stereo renders (render | render_before), for instruction counting under callgrind."""
    cv2.setNumThreads(1)
    rig, xyz = scene()
    if which.startswith("render"):
        if which == "render_before":
            mod = load_module_at(before, "omnid/sim/render.py", "render_before")
            assert mod is not None
            opts, render = mod.RenderOptions.realistic(), mod.render_capture
        else:
            opts, render = RenderOptions.realistic(), render_capture
        render(rig, xyz, opts, seed=0)
        for _ in range(n):
            render(rig, xyz, opts, seed=0)
        return 0
    cap = render_capture(rig, xyz, RenderOptions.realistic(), seed=3)
    fn = detect_dots
    if which == "before":
        mod = load_module_at(before, "omnid/core/detect.py", "detect_before")
        assert mod is not None
        fn = mod.detect_dots
    fn(cap.mask1, cap.base1, "best")  # imports and first-call costs are not counted twice
    for _ in range(n):
        fn(cap.mask1, cap.base1, "best")
    return 0


def instructions(which: str, before: str, n: int = 10) -> float | None:
    """Instructions per best detection (one camera), from callgrind runs of n and 0 calls."""
    counts = []
    for k in (0, n):
        try:
            out = subprocess.run(
                [
                    "valgrind",
                    "--tool=callgrind",
                    "--callgrind-out-file=/dev/null",
                    sys.executable,
                    __file__,
                    "--count",
                    which,
                    str(k),
                    "--before",
                    before,
                ],
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=900,
            )
        except (OSError, subprocess.TimeoutExpired):
            return None
        m = re.search(r"Collected : (\d+)", out.stderr)
        if m is None:
            return None
        counts.append(int(m.group(1)))
    return (counts[1] - counts[0]) / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--before", default=DEFAULT_BEFORE, help="git revision to compare with")
    ap.add_argument("--no-oracle", action="store_true", help="skip the slow direct transcription")
    ap.add_argument("--no-trackpy", action="store_true")
    ap.add_argument("--instructions", action="store_true", help="count with valgrind (slow)")
    ap.add_argument("--count", nargs=2, metavar=("WHICH", "N"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.count:
        return count_mode(args.count[0], int(args.count[1]), args.before)
    cv2.setNumThreads(1)
    rig, xyz = scene()
    n_disk = [int(c.in_disk(c.project(xyz)).sum()) for c in (rig.cam1, rig.cam2)]
    print(
        f"python {platform.python_version()}, numpy {np.__version__}, cv2 {cv2.__version__}, "
        f"one core (cv2 threads {cv2.getNumThreads()}, BLAS threads 1), {platform.machine()}, "
        f"{os.cpu_count()} CPUs"
    )
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"dots: {len(xyz)} cast, in disk cam1/cam2: {n_disk}")
    old_detect = load_module_at(args.before, "omnid/core/detect.py", "detect_before")
    old_render = load_module_at(args.before, "omnid/sim/render.py", "render_before")
    print(f"before = {args.before}" + ("" if old_detect else " (not found: skipped)"))
    scenes = {
        "sensor (noise, shot, flicker)": RenderOptions.realistic(spots=SpotModel()),
        "sensor, BGR": RenderOptions.realistic(spots=SpotModel(), color=True),
        "realistic (+ speckled halos, ghosts)": RenderOptions.realistic(),
    }
    reps_render = max(args.repeats // 3, 5)
    print("\nrender_capture, both cameras:   min ms  median ms")
    for label, opts in (
        ("realistic", RenderOptions.realistic()),
        ("realistic BGR", RenderOptions.realistic(color=True)),
    ):
        lo, med = timed(lambda opts=opts: render_capture(rig, xyz, opts, seed=0), reps_render)
        line = f"  {label:14s} now    {lo:8.1f} {med:10.1f}"
        if old_render is not None:
            old_opts = old_render.RenderOptions.realistic(color=opts.color)
            lo_b, med_b = timed(
                lambda o=old_opts: old_render.render_capture(rig, xyz, o, seed=0), reps_render
            )
            line += f"   before {lo_b:8.1f} {med_b:10.1f}   before/now (min) {lo_b / lo:4.1f}x"
        print(line)

    trackpy_minmass = None
    if not args.no_trackpy:
        # Fair minmass: the one with the best recall − FP rate on a separate seed.
        cap = render_capture(rig, xyz, RenderOptions.realistic(), seed=99)
        sub = to_gray(cap.base1) - to_gray(cap.mask1)
        truth = visible_truth(rig.cam1, rig.cam1.project(xyz), EDGE_MARGIN_PX)
        best_q = -1.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for mm in (50, 100, 200, 300, 400, 600, 800):
                rec, fp, _ = score(trackpy_locate(sub, mm), truth, rig.cam1)
                q = rec - fp / len(truth)
                if q > best_q:
                    best_q, trackpy_minmass = q, mm
        print(
            f"\ntrackpy: diameter 7, separation 5, minmass {trackpy_minmass} (tuned on seed 99), "
            "numba engine, on the float subtracted image (its time excludes the subtraction)"
        )

    print(
        f"\n{'scene':38s} {'method':14s} {'min ms':>7s} {'med ms':>7s} "
        f"{'RMS px':>7s} {'recall':>7s} {'FP':>4s}   (both cameras)"
    )
    for name, opts in scenes.items():
        cap = render_capture(rig, xyz, opts, seed=3)
        pairs = [(cap.mask1, cap.base1, rig.cam1), (cap.mask2, cap.base2, rig.cam2)]
        truths = [visible_truth(c, c.project(xyz), EDGE_MARGIN_PX) for _, _, c in pairs]

        def run(fn, method, pairs=pairs):
            return lambda: [fn(m, b, method) for m, b, _ in pairs]

        rows = [("best", run(detect_dots, "best"))]
        if old_detect is not None:
            rows.append(("best before", run(old_detect.detect_dots, "best")))
        rows.append(("thesis", run(detect_dots, "thesis")))
        if trackpy_minmass is not None:
            subs = [to_gray(b) - to_gray(m) for m, b, _ in pairs]

            def run_tp(subs=subs):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    return [trackpy_locate(s, trackpy_minmass) for s in subs]

            rows.append(("trackpy", run_tp))
        mins = {}
        for label, fn in rows:
            reps = args.repeats if label != "trackpy" else max(args.repeats // 5, 3)
            lo, med = timed(fn, reps)
            mins[label] = lo
            res = [score(f, t, c) for f, t, (_, _, c) in zip(fn(), truths, pairs, strict=True)]
            rms = float(np.sqrt(np.mean([r[2] ** 2 for r in res])))
            rec = float(np.mean([r[0] for r in res]))
            fp = sum(r[1] for r in res)
            print(f"{name:38s} {label:14s} {lo:7.2f} {med:7.2f} {rms:7.3f} {rec:7.4f} {fp:4d}")
        ratios = [f"{k} / best {mins[k] / mins['best']:.1f}x" for k in mins if k != "best"]
        print(f"{'':38s} ratios of min times: {', '.join(ratios)}")

    if not args.no_oracle:
        sys.path.insert(0, str(ROOT / "tests" / "core"))
        from thesis_oracle import oracle_detect

        p = DetectionParams()
        cap = render_capture(rig, xyz, RenderOptions.realistic(), seed=3)
        t = time.perf_counter()
        slow = oracle_detect(
            cap.mask1,
            cap.base1,
            block_px=p.block_px,
            block_coefficient=p.block_coefficient,
            min_peak_gray=p.min_peak_gray,
            e1=p.ring_e1_gray,
            e2=p.ring_e2_gray,
            e3=p.ring_e3_gray,
            e4=p.e4_gray,
        )
        t_slow = 1e3 * (time.perf_counter() - t)
        t_fast, _ = timed(lambda: detect_dots(cap.mask1, cap.base1, "thesis"), args.repeats)
        t_best, _ = timed(lambda: detect_dots(cap.mask1, cap.base1, "best"), args.repeats)
        fast = detect_dots(cap.mask1, cap.base1, "thesis")
        same = np.array_equal(np.array(slow, dtype=np.float64).reshape(-1, 3), fast)
        print(
            f"\nthesis, one camera (realistic): direct transcription {t_slow:.0f} ms, vectorised "
            f"{t_fast:.2f} ms (min), ratio {t_slow / t_fast:.0f}x, same dots: {same} ({len(fast)}); "
            f"best {t_best:.2f} ms (min): transcription / best {t_slow / t_best:.0f}x"
        )
    if args.instructions:
        print()
        for label, which, which_before, n in (
            ("best detection, one camera", "now", "before", 10),
            ("realistic render, both cameras", "render", "render_before", 3),
        ):
            now = instructions(which, args.before, n)
            if now is None:
                print("instructions: valgrind not available")
                break
            line = f"instructions per {label} (callgrind): now {now / 1e6:.1f} M"
            before = instructions(which_before, args.before, n) if old_detect else None
            if before is not None:
                line += f", before {before / 1e6:.1f} M, before/now {before / now:.2f}x"
            print(line)
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
