"""Evaluate the perception pipeline on the simulator's scenes with a misaligned rig.

Each scene of :mod:`omnid.sim.scenes` is ray-cast (:func:`omnid.sim.world.cast_laser`) and
rendered with cameras deliberately misaligned (mirror centres a few px off, f/K differing by a
few %, rotations of 1.5° and −1°). The rig is calibrated on the floor capture alone
(:func:`calibrate_from_capture`), then every scene is perceived with ``best`` and ``thesis``
(each with its own detector, matcher and triangulation):

    matched   correct matches / dots visible in both cameras (target ≥ 95 %)
    wrong     wrong matches / dots visible in both cameras (target < 0.5 %)
    err X/Y/Z mean |error| per axis over the range ‖xyz‖ of the correctly matched dots, %
              (target ≤ 0.5 %; thesis Table 7.4: 2.0–4.1 % mean relative error, real data)
    class     correct classification of the correctly matched dots (target ≥ 99 %); a dot
              within the floor tolerance (15 mm) of the floor may be called floor

Run:  python tools/eval_scenes.py [--scenes three_boxes,dropoff] [--seed 0]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from omnid.core.calibration import Calibration, calibrate_from_capture
from omnid.core.classify import ClassifySettings
from omnid.core.geometry import StereoRig
from omnid.core.laser import DotPattern
from omnid.core.pipeline import PerceptionSettings, perceive
from omnid.core.types import PointClass, StereoCapture
from omnid.sim.render import RenderOptions, render_camera_pair
from omnid.sim.scenes import Scene, get_scene, scene_names
from omnid.sim.world import LaserHits, cast_laser


def misaligned_rig(floor_depth_mm: float = 1100.0) -> StereoRig:
    """Centres a few px off, f/K +3 % / −2 %, rotations +1.5° / −1° (as the tests use)."""
    nom = StereoRig.nominal(floor_depth_mm=floor_depth_mm)
    c1 = replace(
        nom.cam1,
        center_row_px=nom.cam1.center_row_px + 3.0,
        center_col_px=nom.cam1.center_col_px - 2.0,
        f_over_k_px=nom.cam1.f_over_k_px * 1.03,
        rotation_rad=math.radians(1.5),
    )
    c2 = replace(
        nom.cam2,
        center_row_px=nom.cam2.center_row_px - 2.0,
        center_col_px=nom.cam2.center_col_px + 4.0,
        f_over_k_px=nom.cam2.f_over_k_px * 0.98,
        rotation_rad=math.radians(-1.0),
    )
    return StereoRig(c1, c2, floor_depth_mm)


def render_hits(rig: StereoRig, hits: LaserHits, seed: int) -> StereoCapture:
    """Mask/base capture in which each camera shows only the dots it can see."""
    rng = np.random.default_rng(seed)
    opts = RenderOptions()
    m1, b1 = render_camera_pair(rig.cam1, rig.cam1.project(hits.xyz[hits.visible1]), opts, rng)
    m2, b2 = render_camera_pair(rig.cam2, rig.cam2.project(hits.xyz[hits.visible2]), opts, rng)
    return StereoCapture(m1, b1, m2, b2)


@dataclass(frozen=True)
class SceneScore:
    scene: str
    method: str
    visible: int
    correct: int
    wrong: int
    err_pct: tuple[float, float, float]
    class_ok: float
    ms: float

    @property
    def matched(self) -> float:
        return self.correct / max(self.visible, 1)

    @property
    def wrong_rate(self) -> float:
        return self.wrong / max(self.visible, 1)


def assign_truth(
    pixels: NDArray[np.float64], truth_px: NDArray[np.float64], tol_px: float = 1.5
) -> NDArray[np.intp]:
    """Index of the dot each match belongs to (both images within ``tol_px``), or −1."""
    if len(pixels) == 0 or len(truth_px) == 0:
        return np.full(len(pixels), -1, dtype=np.intp)
    d1 = np.hypot(
        pixels[:, None, 0] - truth_px[None, :, 0], pixels[:, None, 1] - truth_px[None, :, 1]
    )
    d2 = np.hypot(
        pixels[:, None, 2] - truth_px[None, :, 2], pixels[:, None, 3] - truth_px[None, :, 3]
    )
    d = np.where((d1 < tol_px) & (d2 < tol_px), d1 + d2, np.inf)
    best = np.argmin(d, axis=1)
    return np.where(np.isfinite(d[np.arange(len(d)), best]), best, -1).astype(np.intp)


def evaluate(
    scene: Scene, rig: StereoRig, calib: Calibration, method: str, seed: int
) -> SceneScore:
    hits = cast_laser(scene.world, scene.pose, scene.mount, DotPattern(), rig)
    cap = render_hits(rig, hits, seed)
    t0 = time.perf_counter()
    # each method with its own detector: the thesis' 8x8 circular model, or ours
    settings = PerceptionSettings(detection_method=method)  # type: ignore[arg-type]
    cloud = perceive(cap, calib, method, settings)  # type: ignore[arg-type]
    ms = 1e3 * (time.perf_counter() - t0)
    vis = hits.visible
    idx_vis = np.flatnonzero(vis)
    t = assign_truth(cloud.pixels, rig.project(hits.xyz[vis]))
    ok = t >= 0
    truth_idx = idx_vis[t[ok]]
    # a dot matched twice counts once as correct
    correct = len(np.unique(truth_idx))
    wrong = int((~ok).sum()) + (int(ok.sum()) - correct)
    err = np.abs(cloud.xyz[ok] - hits.xyz[truth_idx])
    rng_mm = np.linalg.norm(hits.xyz[truth_idx], axis=1, keepdims=True)
    err_pct = (
        tuple(float(v) for v in 100 * np.mean(err / rng_mm, axis=0)) if ok.any() else (0.0,) * 3
    )
    # A dot on an obstacle closer to the floor than the classifier's floor tolerance (the foot
    # of a wall) cannot be told from the floor: either answer counts as right there.
    tol = ClassifySettings().floor_tolerance_mm
    h_true = rig.floor_depth_mm - hits.xyz[truth_idx, 2]
    right = (cloud.classes[ok] == hits.truth[truth_idx]) | (
        (np.abs(h_true) <= tol) & (cloud.classes[ok] == PointClass.FLOOR)
    )
    class_ok = float(np.mean(right)) if ok.any() else 1.0
    return SceneScore(scene.name, method, int(vis.sum()), correct, wrong, err_pct, class_ok, ms)  # type: ignore[arg-type]


def calibrate_on_floor(rig: StereoRig, seed: int) -> Calibration:
    floor = get_scene("floor")
    hits = cast_laser(floor.world, floor.pose, floor.mount, DotPattern(), rig)
    return calibrate_from_capture(render_hits(rig, hits, seed), rig.floor_depth_mm, rig.baseline_mm)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scenes", default=",".join(scene_names()), help="comma-separated scene names")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rig = misaligned_rig()
    calib = calibrate_on_floor(rig, args.seed)
    r = calib.residuals
    print(
        f"calibration: f/K {calib.rig.cam1.f_over_k_px:.2f}/{calib.rig.cam2.f_over_k_px:.2f} px "
        f"(true {rig.cam1.f_over_k_px:.2f}/{rig.cam2.f_over_k_px:.2f}), row rms {r['row_rms_px']:.3f} px, "
        f"disparity rms {r['disparity_rms_px']:.3f} px, thesis col rms {r['thesis_col_rms_px']:.3f} px"
    )
    print(
        "| scene | method | visible | matched % | wrong % | err X % | err Y % | err Z % | class % | ms |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    totals: dict[str, list[SceneScore]] = {"best": [], "thesis": []}
    for name in args.scenes.split(","):
        scene = get_scene(name)
        for method in ("best", "thesis"):
            s = evaluate(scene, rig, calib, method, args.seed + 1)
            totals[method].append(s)
            ex, ey, ez = s.err_pct
            print(
                f"| {name} | {method} | {s.visible} | {100 * s.matched:.1f} | {100 * s.wrong_rate:.2f} "
                f"| {ex:.2f} | {ey:.2f} | {ez:.2f} | {100 * s.class_ok:.1f} | {s.ms:.1f} |"
            )
    for method, rows in totals.items():
        vis = sum(s.visible for s in rows)
        cor = sum(s.correct for s in rows)
        wr = sum(s.wrong for s in rows)
        w = np.array([s.correct for s in rows], dtype=float)
        err = np.array([s.err_pct for s in rows])
        cls = np.array([s.class_ok for s in rows])
        e = (w[:, None] * err).sum(axis=0) / max(w.sum(), 1)
        print(
            f"| **all** | {method} | {vis} | {100 * cor / vis:.1f} | {100 * wr / vis:.2f} | "
            f"{e[0]:.2f} | {e[1]:.2f} | {e[2]:.2f} | {100 * (w * cls).sum() / max(w.sum(), 1):.1f} | |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
