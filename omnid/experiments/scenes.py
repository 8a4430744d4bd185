"""Perception on the simulator's scenes with a misaligned rig: captures, truth and scores.

Each scene of :mod:`omnid.sim.scenes` is ray-cast (:func:`omnid.sim.world.cast_laser`) and
rendered with cameras deliberately misaligned (mirror centres a few px off, f/K differing by a
few %, rotations of 1.5° and −1°). The rig is calibrated on the floor capture alone
and the installer's extra captures (:func:`calibrate_on_floor`), then a scene is perceived with ``best`` or ``thesis`` (each
with its own detector, matcher and triangulation) and scored against the ray-cast truth:

    matched   correct matches / dots visible in both cameras (target ≥ 95 %)
    wrong     wrong matches / dots visible in both cameras (target < 0.5 %)
    err X/Y/Z mean |error| per axis over the range ‖xyz‖ of the correctly matched dots, %
              (target ≤ 0.5 %; thesis Table 7.4: 2.0–4.1 % mean relative error, real data)
    class     correct classification of the correctly matched dots (target ≥ 99 %); a dot
              within the floor tolerance (15 mm) of the floor may be called floor

Used by ``tools/eval_scenes.py``, ``omnid experiment table74`` and ``omnid scene``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from omnid.core.calibration import Calibration
from omnid.core.geometry import StereoRig
from omnid.core.types import PointClass, PointCloud, StereoCapture
from omnid.sim.laser import LaserProjector
from omnid.sim.render import RenderOptions, render_hits
from omnid.sim.rigs import misaligned_rig
from omnid.sim.scenes import Scene, floor_hits, get_scene
from omnid.sim.world import LaserHits, cast_laser

METHODS: tuple[str, ...] = ("best", "thesis")


def scene_hits(scene: Scene, rig: StereoRig, laser: LaserProjector | None = None) -> LaserHits:
    """Where the dots of ``laser`` (default: the simulator's physical
    :class:`~omnid.sim.laser.LaserProjector`) fall in ``scene``, and which mirror sees each."""
    return cast_laser(scene.world, scene.pose, scene.mount, laser or LaserProjector(), rig)


def floor_capture(
    rig: StereoRig,
    seed: int,
    options: RenderOptions | None = None,
    laser: LaserProjector | None = None,
) -> StereoCapture:
    """The empty floor at the rig's floor depth, as ``omnid calibrate`` wants it."""
    return render_hits(rig, floor_hits(rig, laser or LaserProjector()), seed, options)


def calibrate_on_floor(
    rig: StereoRig,
    seed: int,
    laser: LaserProjector | None = None,
    options: RenderOptions | None = None,
) -> Calibration:
    """Calibration as the installer makes it: the empty floor plus the extra captures (a box
    and a wall ahead, :mod:`omnid.sim.installation`), no other knowledge of ``rig``."""
    from omnid.sim.installation import calibrate_installed

    cal: Calibration = calibrate_installed(
        rig, laser or LaserProjector(), seed=seed, options=options
    )
    return cal


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


@dataclass(frozen=True)
class SceneScore:
    """How one method did on one scene (see the module docstring)."""

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


@dataclass(frozen=True)
class SceneRun:
    """One perceived scene with its truth: the score, the cloud, the ray-cast hits, and for each
    point of the cloud the index of its true dot in ``hits`` (−1: a wrong match)."""

    score: SceneScore
    cloud: PointCloud
    hits: LaserHits
    truth_index: NDArray[np.intp]


def evaluate(
    scene: Scene,
    rig: StereoRig,
    calib: Calibration,
    method: str,
    seed: int,
    laser: LaserProjector | None = None,
    options: RenderOptions | None = None,
) -> SceneRun:
    """Render ``scene`` on ``rig`` with ``laser`` (default :class:`LaserProjector`) and
    ``options``, perceive it with ``method`` (its own detector) and score it."""
    from omnid.core.classify import ClassifySettings
    from omnid.core.pipeline import PerceptionSettings, perceive

    hits = scene_hits(scene, rig, laser)
    cap = render_hits(rig, hits, seed, options)
    t0 = time.perf_counter()
    settings = PerceptionSettings(detection_method=None)  # each method with its own detector
    cloud = perceive(cap, calib, method, settings)  # type: ignore[arg-type]
    ms = 1e3 * (time.perf_counter() - t0)
    vis = hits.visible
    idx_vis = np.flatnonzero(vis)
    t = assign_truth(cloud.pixels, rig.project(hits.xyz[vis]))
    ok = t >= 0
    truth_index = np.where(ok, idx_vis[np.maximum(t, 0)], -1).astype(np.intp)
    truth_idx = truth_index[ok]
    # a dot matched twice counts once as correct
    correct = len(np.unique(truth_idx))
    wrong = int((~ok).sum()) + (int(ok.sum()) - correct)
    err = np.abs(cloud.xyz[ok] - hits.xyz[truth_idx])
    rng_mm = np.linalg.norm(hits.xyz[truth_idx], axis=1, keepdims=True)
    err_pct: tuple[float, float, float] = (0.0, 0.0, 0.0)
    if ok.any():
        e = 100 * np.mean(err / rng_mm, axis=0)
        err_pct = (float(e[0]), float(e[1]), float(e[2]))
    # A dot on an obstacle closer to the floor than the classifier's floor tolerance (the foot
    # of a wall) cannot be told from the floor: either answer counts as right there.
    tol = ClassifySettings().floor_tolerance_mm
    h_true = rig.floor_depth_mm - hits.xyz[truth_idx, 2]
    right = (cloud.classes[ok] == hits.truth[truth_idx]) | (
        (np.abs(h_true) <= tol) & (cloud.classes[ok] == PointClass.FLOOR)
    )
    class_ok = float(np.mean(right)) if ok.any() else 1.0
    score = SceneScore(scene.name, method, int(vis.sum()), correct, wrong, err_pct, class_ok, ms)
    return SceneRun(score, cloud, hits, truth_index)


def run_scenes(
    names: Sequence[str], seed: int = 0, methods: Sequence[str] = METHODS
) -> tuple[Calibration, StereoRig, list[SceneScore]]:
    """Calibrate the misaligned rig on the floor, then score every scene with every method."""
    rig = misaligned_rig()
    calib = calibrate_on_floor(rig, seed)
    scores = [
        evaluate(get_scene(name), rig, calib, method, seed + 1).score
        for name in names
        for method in methods
    ]
    return calib, rig, scores


def format_scores(calib: Calibration, rig: StereoRig, scores: Sequence[SceneScore]) -> str:
    """The calibration line and a Markdown table of the scores with per-method totals."""
    r = calib.residuals
    lines = [
        f"calibration: f/K {calib.rig.cam1.f_over_k_px:.2f}/{calib.rig.cam2.f_over_k_px:.2f} px "
        f"(true {rig.cam1.f_over_k_px:.2f}/{rig.cam2.f_over_k_px:.2f}), "
        f"row rms {r['row_rms_px']:.3f} px, disparity rms {r['disparity_rms_px']:.3f} px, "
        f"thesis col rms {r['thesis_col_rms_px']:.3f} px",
        "| scene | method | visible | matched % | wrong % | err X % | err Y % | err Z % "
        "| class % | ms |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in scores:
        ex, ey, ez = s.err_pct
        lines.append(
            f"| {s.scene} | {s.method} | {s.visible} | {100 * s.matched:.1f} "
            f"| {100 * s.wrong_rate:.2f} | {ex:.2f} | {ey:.2f} | {ez:.2f} "
            f"| {100 * s.class_ok:.1f} | {s.ms:.1f} |"
        )
    for method in dict.fromkeys(s.method for s in scores):
        rows = [s for s in scores if s.method == method]
        vis = sum(s.visible for s in rows)
        cor = sum(s.correct for s in rows)
        wr = sum(s.wrong for s in rows)
        w = np.array([s.correct for s in rows], dtype=float)
        err = np.array([s.err_pct for s in rows])
        cls = np.array([s.class_ok for s in rows])
        e = (w[:, None] * err).sum(axis=0) / max(w.sum(), 1)
        lines.append(
            f"| **all** | {method} | {vis} | {100 * cor / max(vis, 1):.1f} "
            f"| {100 * wr / max(vis, 1):.2f} | {e[0]:.2f} | {e[1]:.2f} | {e[2]:.2f} "
            f"| {100 * (w * cls).sum() / max(w.sum(), 1):.1f} | |"
        )
    return "\n".join(lines)
