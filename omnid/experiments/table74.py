"""Thesis Table 7.4 (7.2.2) on rendered captures of a misaligned rig.

The thesis put a horizontal plane 680, 800, 930 and 1100 mm (the floor) below the mirrors, its
near side 450 mm ahead of the vision axis, and a vertical plane 550 … 1750 mm ahead, and reported
for the real laser dots on the plane the distribution of the relative error of the plane's own
axis: Z for the horizontal planes (|Ẑ − Z|/Z), X for the vertical ones (|X̂ − X|/X) — Table 7.4
— and for two of them the mean relative error of every axis (Table 7.5).

Here each layout is a scene of :mod:`omnid.sim.scenes`, ray-cast and rendered with the cameras
misaligned (:func:`omnid.experiments.scenes.misaligned_rig`); the rig is calibrated on an empty
floor capture alone, then every scene is perceived with each method (its own detector, matcher
and triangulation). The dots "on the plane" are those whose true position lies on the table top
or the wall face (for 1100 mm: floor dots under the footprint of the other horizontal planes,
450–2450 mm ahead, |Y| ≤ 1000 mm); statistics are over the correctly matched ones (a wrong
match has no true position to compare with; wrong matches are counted separately). Per-axis
means use |F̂ − F|/|F| over points with |F| ≥ 100 mm (a relative error near F = 0 is
meaningless). Matched / wrong / classified are over the whole scene, as
:func:`omnid.experiments.scenes.evaluate` defines them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from omnid.core.calibration import Calibration
from omnid.core.geometry import StereoRig
from omnid.experiments.scenes import (
    METHODS,
    SceneScore,
    calibrate_on_floor,
    evaluate,
    misaligned_rig,
)
from omnid.sim.scenes import (
    HORIZONTAL_PLANE_DEPTHS_MM,
    HORIZONTAL_PLANE_NEAR_MM,
    VERTICAL_PLANE_DISTANCES_MM,
    get_scene,
)

#: Rows of Table 7.4 (after the number of points), in the thesis' order.
STATISTICS: tuple[str, ...] = (
    "Minimum",
    "Lowest 25%",
    "Median",
    "Lowest 75%",
    "Maximum",
    "Mean",
    "Standard Deviation",
)
#: Table 7.4 as printed: plane → (# of data points, then the rows of STATISTICS), %.
THESIS_TABLE74: dict[str, tuple[float, ...]] = {
    "horizontal_680": (200, 0.03, 1.38, 3.29, 5.90, 17.45, 4.13, 3.57),
    "horizontal_800": (192, 0.02, 1.68, 3.14, 5.57, 14.26, 3.91, 2.98),
    "horizontal_930": (161, 0.01, 1.15, 3.02, 4.96, 13.28, 3.51, 2.81),
    "horizontal_1100": (159, 0.00, 1.53, 2.76, 4.30, 11.03, 3.14, 2.28),
    "vertical_550": (19, 0.00, 1.30, 2.27, 3.62, 5.57, 2.41, 1.53),
    "vertical_750": (46, 0.01, 0.64, 1.41, 2.34, 5.95, 1.78, 1.44),
    "vertical_1050": (56, 0.03, 1.06, 1.72, 3.40, 8.16, 2.26, 1.72),
    "vertical_1150": (56, 0.00, 1.19, 2.24, 3.03, 6.67, 2.18, 1.39),
    "vertical_1450": (51, 0.05, 0.89, 1.95, 2.98, 5.11, 2.17, 1.41),
    "vertical_1750": (37, 0.00, 0.82, 1.60, 3.12, 7.16, 2.02, 1.59),
}
#: Table 7.5: mean relative error of X, Y, Z, % (only these two planes are given).
THESIS_TABLE75_MEAN: dict[str, tuple[float, float, float]] = {
    "horizontal_1100": (2.31, 3.10, 3.14),
    "vertical_1450": (2.17, 2.71, 2.37),
}
#: Points with |F| below this are left out of axis F's relative error, mm.
MIN_AXIS_MM = 100.0


def plane_names() -> list[str]:
    """The ten Table 7.4 layouts, in the thesis' column order."""
    return [f"horizontal_{z:g}" for z in HORIZONTAL_PLANE_DEPTHS_MM] + [
        f"vertical_{x:g}" for x in VERTICAL_PLANE_DISTANCES_MM
    ]


def on_plane(name: str, xyz_mm: NDArray[np.float64], floor_depth_mm: float) -> NDArray[np.bool_]:
    """Which true dot positions (N, 3) lie on the plane of layout ``name``, and the axis (0 X,
    2 Z) whose error Table 7.4 reports is implied by the name."""
    kind, value = name.split("_")
    v = float(value)
    if kind == "vertical":
        return np.asarray(np.abs(xyz_mm[:, 0] - v) < 0.5, dtype=bool)
    near = HORIZONTAL_PLANE_NEAR_MM
    inside = (xyz_mm[:, 0] >= near) & (xyz_mm[:, 0] <= near + 2000.0)
    inside &= np.abs(xyz_mm[:, 1]) <= 1000.0
    return np.asarray(inside & (np.abs(xyz_mm[:, 2] - v) < 0.5), dtype=bool)


def plane_axis(name: str) -> int:
    """0 (X) for a vertical plane, 2 (Z) for a horizontal one."""
    return 0 if name.startswith("vertical") else 2


@dataclass(frozen=True)
class PlaneResult:
    """One layout perceived with one method.

    stats_pct     (7,) the STATISTICS of the plane axis' relative error, % (NaN: no points)
    points        correctly matched dots on the plane
    on_plane      dots on the plane seen by both cameras
    axis_mean_pct (3,) mean relative error of X, Y, Z over the same points, %
    score         matched / wrong / classified over the whole scene
    """

    name: str
    method: str
    stats_pct: NDArray[np.float64]
    points: int
    on_plane: int
    axis_mean_pct: NDArray[np.float64]
    score: SceneScore


def _stats(rel_pct: NDArray[np.float64]) -> NDArray[np.float64]:
    if len(rel_pct) == 0:
        return np.full(len(STATISTICS), np.nan)
    q = np.percentile(rel_pct, [0, 25, 50, 75, 100])
    return np.array([*q, rel_pct.mean(), rel_pct.std(ddof=1) if len(rel_pct) > 1 else 0.0])


def run_plane(name: str, rig: StereoRig, calib: Calibration, method: str, seed: int) -> PlaneResult:
    """Perceive layout ``name`` with ``method`` and measure Table 7.4's errors on its plane."""
    run = evaluate(get_scene(name), rig, calib, method, seed)
    hits = run.hits
    plane = on_plane(name, hits.xyz, rig.floor_depth_mm)
    ok = run.truth_index >= 0
    idx = run.truth_index[ok]
    est = run.cloud.xyz[ok]
    # one estimate per true dot (a dot matched twice counts once, its first match)
    _, first = np.unique(idx, return_index=True)
    idx, est = idx[first], est[first]
    keep = plane[idx]
    true = hits.xyz[idx[keep]]
    est = est[keep]
    a = plane_axis(name)
    rel = 100.0 * np.abs(est[:, a] - true[:, a]) / np.abs(true[:, a])
    means = np.full(3, np.nan)
    for k in range(3):
        use = np.abs(true[:, k]) >= MIN_AXIS_MM
        if use.any():
            means[k] = 100.0 * np.mean(np.abs(est[use, k] - true[use, k]) / np.abs(true[use, k]))
    return PlaneResult(
        name,
        method,
        _stats(rel),
        int(keep.sum()),
        int((plane & hits.visible).sum()),
        means,
        run.score,
    )


def run_table74(
    seed: int = 0,
    names: Sequence[str] | None = None,
    methods: Sequence[str] = METHODS,
    misaligned: bool = True,
) -> tuple[Calibration, StereoRig, list[PlaneResult]]:
    """Calibrate the rig (misaligned, or the nominal one) on the floor, then run every layout
    with every method."""
    rig = misaligned_rig() if misaligned else StereoRig.nominal()
    calib = calibrate_on_floor(rig, seed)
    results = [
        run_plane(name, rig, calib, method, seed + 1)
        for name in (names or plane_names())
        for method in methods
    ]
    return calib, rig, results


def _cell(value: float, thesis: float | None = None) -> str:
    text = "–" if not np.isfinite(value) else f"{value:.2f}"
    return text if thesis is None else f"{text} [{thesis:.2f}]"


def format_table74(calib: Calibration, rig: StereoRig, results: Sequence[PlaneResult]) -> str:
    """Markdown: Table 7.4's layout per method (ours [thesis]), then per-axis means (Table 7.5
    where the thesis has them) with matched / wrong / classified per layout."""
    names = list(dict.fromkeys(r.name for r in results))
    methods = list(dict.fromkeys(r.method for r in results))
    by = {(r.name, r.method): r for r in results}
    res = calib.residuals
    aligned = rig.cam1.rotation_rad == 0 and rig.cam2.rotation_rad == 0
    lines = [
        f"{'Nominal' if aligned else 'Misaligned'} rig calibrated on the empty floor: f/K {calib.rig.cam1.f_over_k_px:.2f}/"
        f"{calib.rig.cam2.f_over_k_px:.2f} px (true {rig.cam1.f_over_k_px:.2f}/"
        f"{rig.cam2.f_over_k_px:.2f}), row rms {res['row_rms_px']:.3f} px.",
        "",
    ]
    head = "| Error distributions, % | " + " | ".join(
        n.replace("horizontal_", "Z ").replace("vertical_", "X ") for n in names
    )
    for method in methods:
        lines += [
            f"### Table 7.4 layout, method `{method}`: relative error of the plane's axis "
            "(Z for horizontal, X for vertical planes), ours [thesis, real data]",
            "",
            head + " |",
            "|---|" + "---:|" * len(names),
        ]
        row = [f"{by[(n, method)].points} [{THESIS_TABLE74[n][0]:.0f}]" for n in names]
        lines.append("| # of data points | " + " | ".join(row) + " |")
        for k, stat in enumerate(STATISTICS):
            cells = [_cell(by[(n, method)].stats_pct[k], THESIS_TABLE74[n][k + 1]) for n in names]
            lines.append(f"| {stat} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += [
        "### Mean relative error per axis on the plane, % (thesis Table 7.5 in brackets), and "
        "matching over the whole scene",
        "",
        "| layout | method | on plane | matched there | X | Y | Z | matched % | wrong % "
        "| classified % |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for n in names:
        for method in methods:
            r = by[(n, method)]
            thesis = THESIS_TABLE75_MEAN.get(n)
            axes = [_cell(r.axis_mean_pct[k], thesis[k] if thesis else None) for k in range(3)]
            s = r.score
            lines.append(
                f"| {n} | {method} | {r.on_plane} | {r.points} | " + " | ".join(axes) + " | "
                f"{100 * s.matched:.1f} | {100 * s.wrong_rate:.2f} | {100 * s.class_ok:.1f} |"
            )
    return "\n".join(lines)
