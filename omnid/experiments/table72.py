"""The synthetic experiment of thesis Table 7.2 (7.2.1), reproduced and extended.

``pixels`` variant (the thesis' experiment)
    Eight horizontal planes 400, 500, …, 1100 mm below the mirrors; points on a 100 mm grid
    (through the origin) whose images fall inside both mirror disks; baseline D = 200 mm,
    mirror 1 at Y = −100, mirror 2 at Y = +100. Each point is projected (SPEC §2), its pixel
    positions rounded to integers (image resolution), then uniform noise in (−1, 1) px is added to
    r1, then also c1, then r2, then c2 — cumulatively, as the thesis' columns ``r1``, ``r1-c1``,
    ``r1-c1-r2``, ``r1-c1-r2-c2`` read. Per plane and weighted over all points: the mean relative
    error |F̂ − F|/|F| of X, Y and Z in %, for the thesis' triangulation (eqs. 6.5, 6.6, 6.8) and
    for ours (``best``). A point whose true X (or Y) is 0 has no relative error on that axis and
    is left out of that axis' mean; non-finite estimates (the thesis formula's 0/0) are counted
    and reported, not averaged. The first-order bound of eq. 6.11 for ±0.5 px rounding is given
    beside the thesis' "without distortion" column.

``detected`` variant (ours)
    Each plane's dots are drawn as a realistic capture (:func:`omnid.sim.render.render_capture`),
    detected with each method of :func:`omnid.core.detect.detect_dots`, associated to the truth by
    the nearest projected position (≤ 1.5 px, in each camera; matching between cameras is not
    this experiment's business), and triangulated with each method. Reported: mean absolute error
    per axis in mm per plane and over the whole range, for every detector x triangulation pair.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from omnid.core.errormodel import max_relative_error
from omnid.core.geometry import MIRROR_CONSTANT_K, StereoRig
from omnid.core.triangulate import thesis_offsets, triangulate

#: Depths of the eight horizontal planes below the mirrors, mm (Table 7.2).
DEPTHS_MM: tuple[float, ...] = (400.0, 500.0, 600.0, 700.0, 800.0, 900.0, 1000.0, 1100.0)
#: "# of points" of Table 7.2 per plane, and the total.
THESIS_COUNTS: tuple[int, ...] = (194, 302, 460, 650, 878, 1130, 1386, 1582)
THESIS_TOTAL = 6582
#: Noise columns of Table 7.2; each adds U(−1, 1) px to one more coordinate (r1, c1, r2, c2).
COLUMNS: tuple[str, ...] = ("without distortion", "r1", "r1-c1", "r1-c1-r2", "r1-c1-r2-c2")
AXES = ("X", "Y", "Z")

#: Table 7.2 error rates in %, [plane (8 planes + weighted)][axis X,Y,Z][column].
THESIS_TABLE_PCT: NDArray[np.float64] = np.array(
    [
        [
            [1.24, 1.48, 1.96, 2.65, 2.54],
            [1.26, 1.45, 2.02, 2.54, 2.59],
            [7.62, 7.86, 7.58, 7.86, 8.01],
        ],
        [
            [1.66, 1.92, 2.45, 3.10, 3.72],
            [1.68, 1.88, 2.50, 3.10, 3.81],
            [5.33, 5.55, 5.47, 5.88, 6.54],
        ],
        [
            [1.78, 2.32, 2.89, 3.69, 3.79],
            [1.76, 2.30, 2.93, 3.69, 3.97],
            [3.96, 4.55, 4.56, 5.20, 4.82],
        ],
        [
            [2.42, 2.75, 3.40, 4.45, 4.82],
            [2.49, 2.71, 3.43, 4.39, 4.96],
            [3.66, 4.05, 4.23, 5.16, 5.56],
        ],
        [
            [3.04, 3.65, 4.18, 5.50, 6.69],
            [3.14, 3.63, 4.21, 5.53, 6.84],
            [3.74, 4.50, 4.67, 6.01, 7.03],
        ],
        [
            [3.27, 4.14, 5.15, 7.57, 7.08],
            [3.30, 4.13, 5.22, 7.63, 7.21],
            [3.72, 4.68, 5.41, 7.83, 7.29],
        ],
        [
            [3.45, 4.14, 5.12, 7.00, 7.28],
            [3.52, 4.11, 5.19, 7.05, 7.47],
            [3.77, 4.50, 5.31, 7.19, 7.35],
        ],
        [
            [3.97, 5.10, 6.02, 8.62, 8.60],
            [4.03, 5.08, 6.09, 8.71, 8.82],
            [4.27, 5.42, 6.20, 8.81, 8.73],
        ],
        [
            [3.12, 3.86, 4.68, 6.50, 6.69],
            [3.18, 3.84, 4.73, 6.53, 6.86],
            [4.07, 4.86, 5.37, 7.15, 7.26],
        ],
    ]
)

TRIANGULATION_METHODS: tuple[str, ...] = ("thesis", "best")


def plane_grid(
    rig: StereoRig, depth_mm: float, grid_step_mm: float = 100.0, margin_px: float = 0.0
) -> NDArray[np.float64]:
    """Grid points (N, 3) mm on the plane Z = ``depth_mm`` whose images (rounded to whole pixels)
    lie inside both mirror disks shrunk by ``margin_px``; the grid passes through the origin."""
    radius_px = max(rig.cam1.disk_radius_px, rig.cam2.disk_radius_px)
    reach_mm = radius_px * depth_mm / min(rig.cam1.f_over_k_px, rig.cam2.f_over_k_px)
    reach_mm += rig.baseline_mm + abs(rig.cam1.y_mm + rig.cam2.y_mm) + 2 * grid_step_mm
    k = int(np.ceil(reach_mm / grid_step_mm))
    g = grid_step_mm * np.arange(-k, k + 1, dtype=np.float64)
    X, Y = np.meshgrid(g, g, indexing="ij")
    P = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, float(depth_mm))])
    return P[rig.visible(np.rint(rig.project(P)), margin_px)]


@dataclass(frozen=True)
class PixelsResult:
    """Table 7.2 as measured. Rows of ``rel_error_pct``: one per plane, then the weighted row.

    rel_error_pct    (n_methods, n_depths + 1, 3 axes, n_columns) mean relative error, %
    bound_pct        (n_depths + 1, 3) mean eq. 6.11 bound for ±0.5 px rounding (thesis), %
    counts           (n_depths,) points per plane
    undefined        (n_methods, n_columns) non-finite estimates (left out of the means)
    """

    depths_mm: tuple[float, ...]
    methods: tuple[str, ...]
    counts: NDArray[np.int64]
    rel_error_pct: NDArray[np.float64]
    bound_pct: NDArray[np.float64]
    undefined: NDArray[np.int64]
    seed: int


def _rel_error_sums(
    est: NDArray[np.float64], truth: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """Per axis: sum of |est − truth|/|truth| over usable points, their count, non-finite rows."""
    finite = np.asarray(np.isfinite(est).all(axis=1), dtype=bool)
    use = finite[:, None] & (truth != 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(est - truth) / np.abs(truth)
    rel = np.where(use, rel, 0.0)
    return rel.sum(axis=0), use.sum(axis=0).astype(np.float64), int((~finite).sum())


def run_pixels(
    rig: StereoRig | None = None,
    seed: int = 0,
    depths_mm: Sequence[float] = DEPTHS_MM,
    grid_step_mm: float = 100.0,
) -> PixelsResult:
    """Run the ``pixels`` variant (the thesis' experiment) on ``rig`` (nominal D = 200 by default)."""
    rig = rig or StereoRig.nominal()
    rng = np.random.default_rng(seed)
    n_m, n_d, n_c = len(TRIANGULATION_METHODS), len(depths_mm), len(COLUMNS)
    sums = np.zeros((n_m, n_d, 3, n_c))
    cnts = np.zeros((n_m, n_d, 3, n_c))
    bsum = np.zeros((n_d, 3))
    bcnt = np.zeros((n_d, 3))
    undefined = np.zeros((n_m, n_c), dtype=np.int64)
    counts = np.zeros(n_d, dtype=np.int64)
    f1 = rig.cam1.f_over_k_px * MIRROR_CONSTANT_K
    for di, depth in enumerate(depths_mm):
        P = plane_grid(rig, depth, grid_step_mm)
        counts[di] = len(P)
        exact = rig.project(P)
        rounded = np.rint(exact)
        noise = rng.uniform(-1.0, 1.0, rounded.shape)
        bound = max_relative_error(thesis_offsets(rig, exact), 0.5, rig.baseline_mm, f1)
        ok = np.asarray(np.isfinite(bound).all(axis=1), dtype=bool)
        use = ok[:, None] & (P != 0.0)
        bsum[di] = np.where(use, bound, 0.0).sum(axis=0)
        bcnt[di] = use.sum(axis=0)
        for ci in range(n_c):
            px = rounded.copy()
            px[:, :ci] += noise[:, :ci]  # cumulative: r1, then c1, r2, c2
            for mi, method in enumerate(TRIANGULATION_METHODS):
                est, _ = triangulate(rig, px, method=method)  # type: ignore[arg-type]
                s, c, bad = _rel_error_sums(est, P)
                sums[mi, di, :, ci] = s
                cnts[mi, di, :, ci] = c
                undefined[mi, ci] += bad
    with np.errstate(invalid="ignore", divide="ignore"):
        per_plane = 100.0 * sums / cnts
        weighted = 100.0 * sums.sum(axis=1) / cnts.sum(axis=1)
        bound_pct = 100.0 * np.vstack([bsum / bcnt, bsum.sum(axis=0) / bcnt.sum(axis=0)])
    rel = np.concatenate([per_plane, weighted[:, None]], axis=1)
    return PixelsResult(
        tuple(float(d) for d in depths_mm),
        TRIANGULATION_METHODS,
        counts,
        rel,
        bound_pct,
        undefined,
        seed,
    )


def format_pixels(result: PixelsResult) -> str:
    """Markdown tables in the layout of Table 7.2, the thesis' own numbers in brackets."""
    lines: list[str] = []
    thesis_rows = {d: i for i, d in enumerate(DEPTHS_MM)}
    for mi, method in enumerate(result.methods):
        name = "thesis triangulation (eqs. 6.5, 6.6, 6.8)" if method == "thesis" else "ours (best)"
        lines.append(
            f"### Table 7.2 — {name}; seed {result.seed}; error rates in %, "
            "thesis' published value in [brackets]"
        )
        lines.append("")
        head = ["Depth [mm]", "# points [thesis]", "Axis", *COLUMNS]
        if method == "thesis":
            head.append("eq. 6.11 bound ±0.5 px")
        lines.append("| " + " | ".join(head) + " |")
        lines.append("|" + "---|" * len(head))
        n_rows = len(result.depths_mm) + 1
        for ri in range(n_rows):
            weighted = ri == len(result.depths_mm)
            if weighted:
                label, count = "weighted, all points", int(result.counts.sum())
                ti: int | None = len(DEPTHS_MM)
                tcount: int | None = THESIS_TOTAL
            else:
                depth = result.depths_mm[ri]
                label, count = f"{depth:.0f}", int(result.counts[ri])
                ti = thesis_rows.get(depth)
                tcount = THESIS_COUNTS[ti] if ti is not None else None
            for ai, axis in enumerate(AXES):
                first = ai == 0
                cells = [label if first else "", "", axis]
                if first:
                    cells[1] = f"{count} [{tcount}]" if tcount is not None else f"{count}"
                for ci in range(len(COLUMNS)):
                    v = result.rel_error_pct[mi, ri, ai, ci]
                    cell = f"{v:.2f}"
                    if ti is not None:
                        cell += f" [{THESIS_TABLE_PCT[ti, ai, ci]:.2f}]"
                    cells.append(cell)
                if method == "thesis":
                    cells.append(f"{result.bound_pct[ri, ai]:.2f}")
                lines.append("| " + " | ".join(cells) + " |")
        bad = ", ".join(
            f"{c}: {int(n)}" for c, n in zip(COLUMNS, result.undefined[mi], strict=True)
        )
        lines.append("")
        lines.append(f"Non-finite estimates (left out of the means): {bad}.")
        lines.append("")
    return "\n".join(lines)


@dataclass(frozen=True)
class DetectedResult:
    """The ``detected`` variant. Pipelines are (detector, triangulation) pairs.

    abs_error_mm   (n_pipelines, n_depths + 1, 3) mean |error| per axis, mm; last row = all planes
    found          (n_pipelines, n_depths) dots associated in both cameras (≤ 1.5 px) per plane
    truth_counts   (n_depths,) dots drawn (inside both disks) per plane
    undefined      (n_pipelines,) non-finite estimates, left out of the means
    """

    depths_mm: tuple[float, ...]
    pipelines: tuple[tuple[str, str], ...]
    abs_error_mm: NDArray[np.float64]
    found: NDArray[np.int64]
    truth_counts: NDArray[np.int64]
    undefined: NDArray[np.int64]
    notes: tuple[str, ...]
    seed: int


def associate(
    truth_rc: NDArray[np.float64], detected_rc: NDArray[np.float64], max_px: float = 1.5
) -> NDArray[np.int64]:
    """Index (N,) of the detection nearest each true image position, −1 if none within ``max_px``."""
    if len(truth_rc) == 0 or len(detected_rc) == 0:
        return np.full(len(truth_rc), -1, dtype=np.int64)
    d2 = ((truth_rc[:, None, :] - detected_rc[None, :, :]) ** 2).sum(axis=2)
    best = np.argmin(d2, axis=1)
    ok = d2[np.arange(len(truth_rc)), best] <= max_px * max_px
    return np.where(ok, best, -1).astype(np.int64)


def _detect(mask: NDArray, base: NDArray, method: str) -> NDArray[np.float64]:
    from omnid.core.detect import detect_dots

    return detect_dots(mask, base, method=method)[:, :2]  # type: ignore[arg-type]


def run_detected(
    rig: StereoRig | None = None,
    seed: int = 0,
    depths_mm: Sequence[float] = DEPTHS_MM,
    grid_step_mm: float = 100.0,
    detectors: Sequence[str] = ("thesis", "best"),
    max_assoc_px: float = 1.5,
) -> DetectedResult:
    """Run the ``detected`` variant: render, detect, associate to truth, triangulate, compare."""
    from omnid.sim.render import render_capture

    rig = rig or StereoRig.nominal()
    rng = np.random.default_rng(seed)
    pipelines = tuple((d, t) for d in detectors for t in TRIANGULATION_METHODS)
    n_p, n_d = len(pipelines), len(depths_mm)
    sums = np.zeros((n_p, n_d, 3))
    cnts = np.zeros((n_p, n_d))
    found = np.zeros((n_p, n_d), dtype=np.int64)
    undefined = np.zeros(n_p, dtype=np.int64)
    truth_counts = np.zeros(n_d, dtype=np.int64)
    notes: list[str] = []
    for di, depth in enumerate(depths_mm):
        # Keep dots whose whole spot lies inside both disks (4 px ≈ 3σ of the spot).
        P = plane_grid(rig, depth, grid_step_mm, margin_px=4.0)
        truth_counts[di] = len(P)
        capture = render_capture(rig, P, seed=rng)
        exact = rig.project(P)
        for det in detectors:
            d1 = _detect(capture.mask1, capture.base1, det)
            d2 = _detect(capture.mask2, capture.base2, det)
            i1 = associate(exact[:, :2], d1, max_assoc_px)
            i2 = associate(exact[:, 2:], d2, max_assoc_px)
            ok = (i1 >= 0) & (i2 >= 0)
            px = np.hstack([d1[i1[ok]], d2[i2[ok]]])
            for tri in TRIANGULATION_METHODS:
                pi = pipelines.index((det, tri))
                est, _ = triangulate(rig, px, method=tri)  # type: ignore[arg-type]
                finite = np.isfinite(est).all(axis=1)
                found[pi, di] = int(ok.sum())
                undefined[pi] += int((~finite).sum())
                sums[pi, di] = np.abs(est[finite] - P[ok][finite]).sum(axis=0)
                cnts[pi, di] = finite.sum()
    with np.errstate(invalid="ignore", divide="ignore"):
        per_plane = sums / cnts[:, :, None]
        overall = sums.sum(axis=1) / cnts.sum(axis=1)[:, None]
    return DetectedResult(
        tuple(float(d) for d in depths_mm),
        pipelines,
        np.concatenate([per_plane, overall[:, None]], axis=1),
        found,
        truth_counts,
        undefined,
        tuple(notes),
        seed,
    )


def format_detected(result: DetectedResult) -> str:
    """Markdown table: mean |error| per axis (mm) per plane and overall, per pipeline."""
    lines = [
        f"### Detected variant — rendered captures, seed {result.seed}; mean absolute error, mm",
        "",
    ]
    head = ["Depth [mm]", "dots"]
    for det, tri in result.pipelines:
        head.append(f"{det} det + {tri} tri: found, X / Y / Z")
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for ri in range(len(result.depths_mm) + 1):
        overall = ri == len(result.depths_mm)
        label = "all planes" if overall else f"{result.depths_mm[ri]:.0f}"
        dots = int(result.truth_counts.sum()) if overall else int(result.truth_counts[ri])
        cells = [label, str(dots)]
        for pi in range(len(result.pipelines)):
            n = int(result.found[pi].sum()) if overall else int(result.found[pi, ri])
            e = result.abs_error_mm[pi, ri]
            cells.append(f"{n}: {e[0]:.2f} / {e[1]:.2f} / {e[2]:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    try:
        ti = result.pipelines.index(("thesis", "thesis"))
        bi = result.pipelines.index(("best", "best"))
    except ValueError:
        pass
    else:
        ratio = result.abs_error_mm[ti, -1] / result.abs_error_mm[bi, -1]
        lines.append(
            "Thesis pipeline / best pipeline, mean |error| over all planes: "
            f"X {ratio[0]:.1f}x, Y {ratio[1]:.1f}x, Z {ratio[2]:.1f}x (goal ≥ 4x)."
        )
    bad = ", ".join(
        f"{d}+{t}: {int(n)}" for (d, t), n in zip(result.pipelines, result.undefined, strict=True)
    )
    lines.append(f"Non-finite estimates (left out of the means): {bad}.")
    for note in result.notes:
        lines.append(f"Note: {note}.")
    lines.append("")
    return "\n".join(lines)
