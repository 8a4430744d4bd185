"""Perception over a distribution of rigs, lasers and scenes (issue 9: evaluate on distributions).

Every uncertain thing is drawn at random per rig: the cameras (:func:`omnid.sim.rigs.random_rig`:
centres ±6 px, f/K ±4 %, roll ±1.5°), the laser (:func:`omnid.sim.laser.random_laser`: source a
few cm off the midpoint and up to ±150 mm off the mirror plane, tilted axis, sine/angle/slope
grating law, pitch, skew, envelope, missing and doubled beams) and the render options. Two rig
classes are forced in, one rig in ten each: a *near-degenerate* laser (|O_Z| < 10 mm) and a source
*exactly in the mirror plane* with a grid uniform in angle.

Each rig is calibrated as an installer would: the empty floor plus ``extras`` captures (a box and a
wall standing ahead, drawn at random) — or the floor alone (``floor_only``). Then each scene class
is drawn at random per seed and perceived with the pipeline, and scored against the ray-cast truth:

    recall       dots seen by both cameras whose pair was reported right / those dots (dots
                 closer than :data:`MERGED_PX` in both images — a doubled beam — are one
                 dot: right if a point pairs any of them)
    obstacle, dropoff   the same over obstacle / drop-off dots only
    wrong        reported points from wrong pairs / reported points
    err X/Y/Z    mean |error| per axis over the range ‖xyz‖ of the right pairs, %
    class        reported points with the right class / reported points (a wrong pair counts as
                 wrongly classified; a dot within the floor tolerance of the floor may be floor)

:func:`summarise` gives, per scene class, the median and the worst decile over rigs. Used by
``tools/eval_rigs.py`` and the rate tests. Only stable interfaces are used (the simulator,
``calibrate_from_capture``, ``perceive``), so the same code scores an older pipeline too.
"""

from __future__ import annotations

import inspect
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from omnid.core.geometry import StereoRig
from omnid.core.types import PointClass, StereoCapture
from omnid.sim.laser import LaserProjector, random_laser
from omnid.sim.render import RenderOptions, render_hits
from omnid.sim.rigs import random_rig
from omnid.sim.scenes import rig_rect
from omnid.sim.world import Box, DropOff, LaserHits, RigMount, World, cast_laser

SCENE_CLASSES: tuple[str, ...] = (
    "floor",
    "raised",
    "wall",
    "boxes",
    "dropoff",
    "passage",
    "clutter",
)
#: A dot within this height of the floor may be called floor (the classifier's tolerance).
FLOOR_TOLERANCE_MM = 15.0


@dataclass(frozen=True)
class RigCase:
    """One installed rig: cameras, laser, render options, and its class."""

    index: int
    kind: str  # "random", "near_plane" (|O_Z| < 10 mm) or "in_plane_angle"
    rig: StereoRig
    laser: LaserProjector
    render: RenderOptions

    @property
    def mount(self) -> RigMount:
        return RigMount(height_mm=self.rig.floor_depth_mm)


def rig_case(index: int, seed: int = 0) -> RigCase:
    """Rig number ``index`` of the evaluation (deterministic in (index, seed))."""
    rng = np.random.default_rng([seed, index, 9])
    rig = random_rig(rng)
    laser = random_laser(rng)
    kind = "random"
    if index % 10 == 7:
        kind = "near_plane"
        x, y, _ = laser.source_mm
        laser = replace(laser, source_mm=(x, y, float(rng.uniform(-10.0, 10.0))))
    elif index % 10 == 9:
        kind = "in_plane_angle"
        x, y, _ = laser.source_mm
        laser = replace(laser, source_mm=(x, y, 0.0), law="angle")
    opts = RenderOptions.realistic() if rng.uniform() < 0.5 else RenderOptions()
    return RigCase(index, kind, rig, laser, opts)


def _box(mount: RigMount, x0: float, x1: float, y0: float, y1: float, h: float) -> Box:
    return Box(*rig_rect(x0, x1, y0, y1, mount), height_mm=h)


def draw_scene(kind: str, mount: RigMount, rng: np.random.Generator) -> World:
    """A random scene of class ``kind`` (one of :data:`SCENE_CLASSES`) in the rig frame."""
    u = rng.uniform
    if kind == "floor":
        return World()
    if kind == "raised":  # a table top or platform, its near edge ahead
        x0 = u(400, 900)
        return World((_box(mount, x0, x0 + 2000, -1200, 1200, u(100, 600)),))
    if kind == "wall":
        x0 = u(500, 1800)
        return World((_box(mount, x0, x0 + 30, -2000, 2000, 1500),))
    if kind == "boxes":
        boxes = []
        for _ in range(int(rng.integers(1, 4))):
            x0, y0 = u(500, 1500), u(-700, 500)
            boxes.append(_box(mount, x0, x0 + u(150, 400), y0, y0 + u(150, 400), u(80, 450)))
        return World(tuple(boxes))
    if kind == "dropoff":
        x0 = u(600, 1500)
        y0 = u(-2500, -300)
        pit = DropOff(*rig_rect(x0, x0 + 3000, y0, 3000, mount), depth_mm=u(80, 300))
        return World((), (pit,))
    if kind == "passage":
        x0, half, h = u(600, 1200), u(350, 550), u(300, 800)
        return World(
            (
                _box(mount, x0, x0 + 500, -half - 600, -half, h),
                _box(mount, x0, x0 + 500, half, half + 600, h),
            )
        )
    if kind == "clutter":
        boxes = []
        for _ in range(int(rng.integers(6, 13))):
            x0, y0 = u(400, 1800), u(-900, 900)
            w, d = u(50, 250), u(50, 250)
            boxes.append(_box(mount, x0, x0 + d, y0, y0 + w, u(40, 350)))
        return World(tuple(boxes))
    raise ValueError(f"unknown scene class {kind!r} (known: {', '.join(SCENE_CLASSES)})")


def capture(case: RigCase, world: World, seed: int) -> tuple[LaserHits, StereoCapture]:
    """Ray-cast and render ``world`` on the case's rig and laser (each camera shows what it sees)."""
    hits = cast_laser(world, (0.0, 0.0, 0.0), case.mount, case.laser, case.rig)
    return hits, render_hits(case.rig, hits, seed, case.render, beam_light=False)


def installer_extras(case: RigCase, seed: int) -> list[StereoCapture]:
    """The installer's extra captures: a box 0.6–1.1 m ahead and a wall 0.9–1.5 m ahead."""
    rng = np.random.default_rng([seed, case.index, 17])
    m = case.mount
    x0, y0 = rng.uniform(600, 1100), rng.uniform(-400, 0)
    box = _box(m, x0, x0 + 400, y0, y0 + rng.uniform(300, 600), rng.uniform(300, 600))
    xw = rng.uniform(900, 1500)
    wall = _box(m, xw, xw + 30, -2000, 2000, 1500)
    return [
        capture(case, World((box,)), seed + 101)[1],
        capture(case, World((wall,)), seed + 102)[1],
    ]


def calibrate_case(case: RigCase, seed: int, floor_only: bool = False) -> Any:
    """The case's calibration from its floor capture (and the extras unless ``floor_only``);
    raises whatever calibration raises."""
    from omnid.core.calibration import calibrate_from_capture

    _, floor = capture(case, World(), seed + 100)
    rig = case.rig
    takes_extras = "extras" in inspect.signature(calibrate_from_capture).parameters
    if takes_extras and not floor_only:
        return calibrate_from_capture(
            floor, rig.floor_depth_mm, rig.baseline_mm, extras=installer_extras(case, seed)
        )
    return calibrate_from_capture(floor, rig.floor_depth_mm, rig.baseline_mm)


@dataclass
class Score:
    """One perceived scene (counts, so that scores pool over seeds)."""

    rig: int
    kind: str
    scene: str
    visible: int = 0
    correct: int = 0
    reported: int = 0
    wrong: int = 0
    obstacle_visible: int = 0
    obstacle_correct: int = 0
    dropoff_visible: int = 0
    dropoff_correct: int = 0
    class_right: int = 0
    # dots the matcher reported as not understood (ambiguous, or no beam explains them), and
    # the clouds with at least 3 of them (the daemon keeps those out of its map: a stop)
    not_understood: int = 0
    clouds_withheld: int = 0
    clouds: int = 0
    err_sum: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    ms: list[float] = field(default_factory=list)

    def add(self, other: Score) -> None:
        for name in (
            "visible",
            "correct",
            "reported",
            "wrong",
            "obstacle_visible",
            "obstacle_correct",
            "dropoff_visible",
            "dropoff_correct",
            "class_right",
            "not_understood",
            "clouds_withheld",
            "clouds",
        ):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.err_sum = self.err_sum + other.err_sum
        self.ms.extend(other.ms)


def _truth_index(pixels: NDArray, truth_px: NDArray, tol_px: float = 1.5) -> NDArray[np.intp]:
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


#: Dots closer than this in both images are one dot (no detector resolves them), px.
MERGED_PX = 2.0


def _blobs(px: NDArray[np.float64]) -> NDArray[np.intp]:
    """(N,) blob label of each dot: dots within MERGED_PX of each other in both images share one."""
    n = len(px)
    lab = np.arange(n)
    if n < 2:
        return lab.astype(np.intp)
    d1 = np.hypot(px[:, None, 0] - px[None, :, 0], px[:, None, 1] - px[None, :, 1])
    d2 = np.hypot(px[:, None, 2] - px[None, :, 2], px[:, None, 3] - px[None, :, 3])
    close = (d1 < MERGED_PX) & (d2 < MERGED_PX)
    for a, b in zip(*np.nonzero(np.triu(close, 1)), strict=True):
        ra, rb = lab[a], lab[b]
        lab[lab == max(ra, rb)] = min(ra, rb)
    return np.unique(lab, return_inverse=True)[1].astype(np.intp)


def score_cloud(case: RigCase, scene: str, hits: LaserHits, cloud: Any, ms: float) -> Score:
    """Score a perceived cloud against the ray-cast truth (module docstring)."""
    rig = case.rig
    vis = hits.visible
    idx = np.flatnonzero(vis)
    truth_px = rig.project(hits.xyz[vis])
    t = _truth_index(cloud.pixels, truth_px)
    ok = t >= 0
    dot = idx[t[ok]]
    # Dots that no detector can tell apart (closer than MERGED_PX in both images: a doubled
    # beam, or two beams meeting at an occluding edge) are one dot seen by both cameras.
    blob = _blobs(truth_px)
    blob_of = np.full(len(hits.xyz), -1, dtype=np.intp)
    blob_of[idx] = blob
    uniq_blob = np.unique(blob_of[dot])
    truth = hits.truth
    first = np.unique(blob, return_index=True)[1]  # one member dot per blob
    sc = Score(case.index, case.kind, scene)
    sc.visible = len(first)
    sc.correct = len(uniq_blob)
    sc.reported = len(cloud)
    sc.wrong = int((~ok).sum()) + (int(ok.sum()) - len(np.unique(dot)))
    blob_cls = truth[idx[first]]
    for cls, vname, cname in (
        (PointClass.OBSTACLE, "obstacle_visible", "obstacle_correct"),
        (PointClass.DROPOFF, "dropoff_visible", "dropoff_correct"),
    ):
        setattr(sc, vname, int((blob_cls == cls).sum()))
        setattr(sc, cname, int((blob_cls[uniq_blob] == cls).sum()))
    if ok.any():
        err = np.abs(cloud.xyz[ok] - hits.xyz[dot])
        rng_mm = np.linalg.norm(hits.xyz[dot], axis=1, keepdims=True)
        sc.err_sum = np.sum(err / rng_mm, axis=0)
        h_true = rig.floor_depth_mm - hits.xyz[dot, 2]
        right = (cloud.classes[ok] == truth[dot]) | (
            (np.abs(h_true) <= FLOOR_TOLERANCE_MM) & (cloud.classes[ok] == PointClass.FLOOR)
        )
        sc.class_right = int(right.sum())
    nu = int(getattr(cloud, "not_understood", 0))
    sc.not_understood = nu
    sc.clouds_withheld = int(nu >= 3)
    sc.clouds = 1
    sc.ms.append(ms)
    return sc


@dataclass(frozen=True)
class Miss:
    """A dot seen by both cameras whose pair was not reported right (:func:`floor_misses`).

    sep_px       image separation from the nearest other visible dot, (camera 1, camera 2), px
    sep_sigma    the smaller of the two over the render's spot sigma
    twin         that neighbour is the dot's doubled-beam twin (or the dot is its twin)
    found_px     distance of each camera's nearest detected dot, (camera 1, camera 2), px
    blob         a reported point claims the neighbour (the blob was paired as the neighbour)
    blob_err     that point's largest per-axis error from this dot's true position, % of range
                 (NaN when no point claims the neighbour)
    """

    rig: int
    kind: str
    seed: int
    sep_px: tuple[float, float]
    sep_sigma: float
    twin: bool
    found_px: tuple[float, float]
    blob: bool
    blob_err: float


def floor_misses(case: RigCase, calib: Any, seeds: Sequence[int]) -> tuple[int, list[Miss]]:
    """(dots seen by both cameras, the misses) of the empty floor at each seed — the same
    captures :func:`evaluate_case` scores — with what lies next to each miss (:class:`Miss`)."""
    from omnid.core.pipeline import perceive_detailed

    twin_of = case.laser.rays().twin
    sigma = case.render.spots.sigma_px
    seen = 0
    out: list[Miss] = []
    for seed in seeds:
        rng = np.random.default_rng([seed, case.index, SCENE_CLASSES.index("floor")])
        hits, cap = capture(case, draw_scene("floor", case.mount, rng), seed * 1000 + case.index)
        per = perceive_detailed(cap, calib, "best")
        cloud = per.cloud
        idx = np.flatnonzero(hits.visible)
        px = case.rig.project(hits.xyz[idx])
        t = _truth_index(cloud.pixels, px)
        blob = _blobs(px)
        claimed = np.full(len(px), -1, dtype=np.intp)  # the reported point claiming each dot
        claimed[t[t >= 0]] = np.flatnonzero(t >= 0)
        got = set(blob[t[t >= 0]].tolist())
        d1 = np.hypot(px[:, None, 0] - px[None, :, 0], px[:, None, 1] - px[None, :, 1])
        d2 = np.hypot(px[:, None, 2] - px[None, :, 2], px[:, None, 3] - px[None, :, 3])
        np.fill_diagonal(d1, np.inf)
        np.fill_diagonal(d2, np.inf)
        first = np.unique(blob, return_index=True)[1]
        seen += len(first)
        for b, k in enumerate(first):
            if b in got:
                continue
            j = int(np.argmin(np.maximum(d1[k], d2[k])))
            q = claimed[j]
            err = math.nan
            if q >= 0:
                e = np.abs(cloud.xyz[q] - hits.xyz[idx[k]]) / np.linalg.norm(hits.xyz[idx[k]])
                err = 100.0 * float(np.max(e))
            found = tuple(
                float(np.min(np.hypot(d[:, 0] - p[0], d[:, 1] - p[1]))) if len(d) else math.inf
                for d, p in ((per.dots1, px[k, :2]), (per.dots2, px[k, 2:]))
            )
            out.append(
                Miss(
                    case.index,
                    case.kind,
                    seed,
                    (float(d1[k, j]), float(d2[k, j])),
                    float(min(d1[k, j], d2[k, j]) / sigma),
                    bool(twin_of[idx[k]] == idx[j] or twin_of[idx[j]] == idx[k]),
                    (found[0], found[1]),
                    bool(q >= 0),
                    err,
                )
            )
    return seen, out


def format_misses(seen: int, misses: Sequence[Miss]) -> str:
    """The floor misses binned by separation (in spot sigmas): twins or not, the blob paired as
    the neighbour, and how far that point lies from the missed dot."""
    lines = [
        f"empty floor: {seen} dots seen by both cameras (merged blobs counted once), "
        f"{len(misses)} not paired right",
        "| separation from the nearest dot (spot sigmas) | misses | doubled-beam twin "
        "| each camera found a dot within 1.5 px | blob paired as the neighbour "
        "| its point's error from this dot, % of range (median / max) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    edges = (0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, math.inf)
    for lo, hi in itertools.pairwise(edges):
        sel = [m for m in misses if lo <= m.sep_sigma < hi]
        if not sel:
            continue
        errs = np.array([m.blob_err for m in sel if m.blob])
        err = f"{np.median(errs):.2f} / {errs.max():.2f}" if len(errs) else "–"
        lines.append(
            f"| {lo:.1f}–{hi:.1f} | {len(sel)} | {sum(m.twin for m in sel)} "
            f"| {sum(max(m.found_px) <= 1.5 for m in sel)} | {sum(m.blob for m in sel)} | {err} |"
        )
    return "\n".join(lines)


def evaluate_case(
    case: RigCase,
    calib: Any,
    scenes: Sequence[str],
    seeds: Sequence[int],
    perceive_fn: Callable[..., object] | None = None,
) -> list[Score]:
    """Perceive a random scene of each class at each seed; one pooled :class:`Score` per class."""
    from omnid.core.pipeline import perceive

    fn = perceive_fn or perceive
    out = []
    for scene in scenes:
        total = Score(case.index, case.kind, scene)
        for seed in seeds:
            rng = np.random.default_rng([seed, case.index, SCENE_CLASSES.index(scene)])
            world = draw_scene(scene, case.mount, rng)
            hits, cap = capture(case, world, seed * 1000 + case.index)
            t0 = time.perf_counter()
            cloud: Any = fn(cap, calib, "best")
            ms = 1e3 * (time.perf_counter() - t0)
            total.add(score_cloud(case, scene, hits, cloud, ms))
        out.append(total)
    return out


def refused_scores(case: RigCase, scenes: Sequence[str], seeds: Sequence[int]) -> list[Score]:
    """Scores of a rig whose calibration was refused: every dot missed."""
    out = []
    for scene in scenes:
        total = Score(case.index, case.kind, scene)
        for seed in seeds:
            rng = np.random.default_rng([seed, case.index, SCENE_CLASSES.index(scene)])
            hits = cast_laser(
                draw_scene(scene, case.mount, rng), (0, 0, 0), case.mount, case.laser, case.rig
            )
            sc = Score(case.index, case.kind, scene)
            sc.visible = int(hits.visible.sum())
            sc.obstacle_visible = int((hits.visible & (hits.truth == PointClass.OBSTACLE)).sum())
            sc.dropoff_visible = int((hits.visible & (hits.truth == PointClass.DROPOFF)).sum())
            total.add(sc)
        out.append(total)
    return out


def rates(sc: Score) -> dict[str, float]:
    """The rates of one pooled score (NaN where there was nothing to count)."""
    nan = math.nan
    return {
        "recall": sc.correct / sc.visible if sc.visible else nan,
        "obstacle": sc.obstacle_correct / sc.obstacle_visible if sc.obstacle_visible else nan,
        "dropoff": sc.dropoff_correct / sc.dropoff_visible if sc.dropoff_visible else nan,
        "wrong": sc.wrong / sc.reported if sc.reported else 0.0,
        "err": float(np.max(sc.err_sum)) / sc.correct if sc.correct else nan,
        "class": sc.class_right / sc.reported if sc.reported else nan,
    }


#: For each rate: whether larger is better (the worst decile is then the 10th percentile).
HIGHER_IS_BETTER = {
    "recall": True,
    "obstacle": True,
    "dropoff": True,
    "wrong": False,
    "err": False,
    "class": True,
}


def summarise(scores: Sequence[Score]) -> dict[str, dict[str, tuple[float, float]]]:
    """{scene class or "all": {rate: (median over rigs, worst decile over rigs)}}."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    groups: dict[str, dict[int, Score]] = {}
    for s in scores:
        for key in (s.scene, "all"):
            per_rig = groups.setdefault(key, {})
            if s.rig not in per_rig:
                per_rig[s.rig] = Score(s.rig, s.kind, key)
            per_rig[s.rig].add(s)
    for key, per_rig in groups.items():
        table = [rates(s) for s in per_rig.values()]
        out[key] = {}
        for name, higher in HIGHER_IS_BETTER.items():
            vals = np.array([r[name] for r in table], dtype=np.float64)
            vals = vals[np.isfinite(vals)]
            if len(vals) == 0:
                out[key][name] = (math.nan, math.nan)
                continue
            worst = np.percentile(vals, 10 if higher else 90)
            out[key][name] = (float(np.median(vals)), float(worst))
    return out


def pooled(scores: Sequence[Score]) -> dict[str, float]:
    """Rates pooled over every score (all rigs, scenes and seeds)."""
    total = Score(-1, "all", "all")
    for s in scores:
        total.add(s)
    r = rates(total)
    r["ms_median"] = float(np.median(total.ms)) if total.ms else math.nan
    return r


def format_summary(scores: Sequence[Score]) -> str:
    """A Markdown table: per scene class, median and worst decile of each rate over rigs."""
    summ = summarise(scores)
    head = "| scene | rigs | " + " | ".join(f"{n} % (med / worst 10 %)" for n in HIGHER_IS_BETTER)
    lines = [head + " |", "|---|---:|" + "---:|" * len(HIGHER_IS_BETTER)]
    n_rigs = {k: len({s.rig for s in scores if k in (s.scene, "all")}) for k in summ}
    for key in [*SCENE_CLASSES, "all"]:
        if key not in summ:
            continue
        cells = []
        for name in HIGHER_IS_BETTER:
            med, worst = summ[key][name]
            scale = 100.0
            digits = 3 if name in ("wrong", "err") else 1
            cells.append(f"{scale * med:.{digits}f} / {scale * worst:.{digits}f}")
        label = f"**{key}**" if key == "all" else key
        lines.append(f"| {label} | {n_rigs[key]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Closed-loop-like sweep: many poses driving up to a passage or a wall (phantom rate)
# --------------------------------------------------------------------------------------------

#: Scenes of the approach sweep: a partition across the way with a gap (the scenario suite's
#: "passage wider than the chair", 1000 mm tall) and a wall across the way, both high enough
#: to fill the laser's field near them.
APPROACH_SCENES: tuple[str, ...] = ("passage", "wall")


def approach_world(scene: str, mount: RigMount, front_mm: float, rng: np.random.Generator) -> World:
    """The sweep's scene with its near face ``front_mm`` ahead of the rig (a random gap width
    1100–1500 mm and a lateral offset of the gap of ±150 mm for ``passage``)."""
    if scene == "passage":
        half = 0.5 * float(rng.uniform(1100.0, 1500.0))
        dy = float(rng.uniform(-150.0, 150.0))
        return World(
            (
                _box(mount, front_mm, front_mm + 100.0, -2000.0, dy - half, 1000.0),
                _box(mount, front_mm, front_mm + 100.0, dy + half, 2000.0, 1000.0),
            )
        )
    if scene == "wall":
        return World((_box(mount, front_mm, front_mm + 100.0, -2000.0, 2000.0, 1000.0),))
    raise ValueError(f"unknown approach scene {scene!r} (known: {', '.join(APPROACH_SCENES)})")


@dataclass
class PhantomScore:
    """Wrong pairs over the clouds of one rig's approaches (a *phantom point* is a reported
    point from a wrong pair that is not floor: something the map keeps and the chair stops
    for; a *phantom row* is a cloud with at least :data:`PHANTOM_ROW_POINTS` of them)."""

    rig: int
    kind: str
    clouds: int = 0
    points: int = 0
    wrong: int = 0
    phantom_points: int = 0
    phantom_rows: int = 0
    worst_cloud: int = 0
    worst_front_mm: float = math.nan
    ms: list[float] = field(default_factory=list)

    def per_1000(self) -> float:
        return 1000.0 * self.phantom_points / self.clouds if self.clouds else math.nan


#: A cloud with this many phantom points holds a row of them (a whole row paired wrong).
PHANTOM_ROW_POINTS = 5


def phantom_points(case: RigCase, hits: LaserHits, cloud: Any) -> tuple[int, int]:
    """(wrong pairs, wrong pairs not classified floor) of one cloud against the truth."""
    vis = hits.visible
    truth_px = case.rig.project(hits.xyz[vis])
    t = _truth_index(cloud.pixels, truth_px)
    wrong = t < 0
    # a pair matched to a dot another pair also claims is wrong too (one of the two)
    ok_t = t[~wrong]
    _, first = np.unique(ok_t, return_index=True)
    dup = np.ones(len(ok_t), dtype=bool)
    dup[first] = False
    wrong_idx = np.concatenate([np.flatnonzero(wrong), np.flatnonzero(~wrong)[dup]])
    n_bad = int(np.sum(cloud.classes[wrong_idx] != PointClass.FLOOR))
    return len(wrong_idx), n_bad


def approach_fronts_mm(step_mm: float = 25.0) -> NDArray[np.float64]:
    """The near faces' distances ahead of the rig of one approach: 2000 mm down to 400 mm."""
    return np.arange(2000.0, 400.0 - 1e-9, -step_mm)


def evaluate_approach(
    case: RigCase,
    calib: Any,
    seed: int = 0,
    scenes: Sequence[str] = APPROACH_SCENES,
    step_mm: float = 25.0,
    perceive_fn: Callable[..., object] | None = None,
) -> PhantomScore:
    """Perceive the approach of each scene at every ``step_mm`` (each capture its own noise
    draw, as the stream's successive clouds are) and count phantom points."""
    from omnid.core.pipeline import perceive

    fn = perceive_fn or perceive
    sc = PhantomScore(case.index, case.kind)
    for k, scene in enumerate(scenes):
        rng = np.random.default_rng([seed, case.index, 31, k])
        world_rng_state = rng.bit_generator.state
        for n, front in enumerate(approach_fronts_mm(step_mm)):
            rng.bit_generator.state = world_rng_state  # the same scene all the way
            world = approach_world(scene, case.mount, float(front), rng)
            hits, cap = capture(case, world, seed * 100000 + case.index * 1000 + 500 * k + n)
            t0 = time.perf_counter()
            cloud: Any = fn(cap, calib, "best")
            sc.ms.append(1e3 * (time.perf_counter() - t0))
            wrong, bad = phantom_points(case, hits, cloud)
            sc.clouds += 1
            sc.points += len(cloud)
            sc.wrong += wrong
            sc.phantom_points += bad
            sc.phantom_rows += int(bad >= PHANTOM_ROW_POINTS)
            if bad > sc.worst_cloud:
                sc.worst_cloud, sc.worst_front_mm = bad, float(front)
    return sc


def summarise_phantoms(scores: Sequence[PhantomScore]) -> dict[str, float]:
    """Phantom points per 1000 clouds: median and worst decile over rigs, and pooled counts."""
    per = np.array([s.per_1000() for s in scores if s.clouds], dtype=np.float64)
    clouds = sum(s.clouds for s in scores)
    return {
        "rigs": float(len(per)),
        "clouds": float(clouds),
        "median_per_1000": float(np.median(per)) if len(per) else math.nan,
        "worst_decile_per_1000": float(np.percentile(per, 90)) if len(per) else math.nan,
        "pooled_per_1000": 1000.0 * sum(s.phantom_points for s in scores) / clouds
        if clouds
        else math.nan,
        "rows": float(sum(s.phantom_rows for s in scores)),
        "wrong_share": sum(s.wrong for s in scores) / max(sum(s.points for s in scores), 1),
    }
