"""Stereo matching of laser dots between the two cameras (thesis 6.3.1.1–6.3.1.2; SPEC §2).

Interface::

    match_dots(calib, dots1 (N, 3), dots2 (M, 3), method="best" | "thesis") -> (K, 4) r1 c1 r2 c2
    match_dots_indexed(...) -> (pixels (K, 4), idx1 (K,), idx2 (K,))

``dots`` rows are (row_px, col_px, strength) as :func:`omnid.core.detect.detect_dots` gives
them. An empty input gives an empty (0, 4) result.

``thesis``
    The polynomial matcher of the thesis: the row polynomial eq. 6.12 (degree 1) and the
    11-term column polynomial eq. 6.13 map a camera-1 pixel to its camera-2 pixel on the floor;
    they are fitted by least squares (eqs. 6.14, 6.15) to control pixel pairs and refined in
    three steps (2 px, then 1 px search neighbourhoods, then the final coefficients). Points
    above the floor are searched with the integer n of eq. 6.16, n = 0, 1, 2, ..., removing the
    matched centres as n grows; dots left unmatched are dropped as noise.

``best``
    A one-to-one assignment with the calibrated model (rotation undone, each camera's f/K):

    * rows agree — the row slopes X/Z of both rays must agree within ``row_tol_px``; this is
      where the rays of the two cameras meet, so it is also the ray-residual test;
    * the disparity window — D/Z between a drop-off ``dropoff_depth_mm`` below the floor and an
      obstacle top at ``min_depth_mm`` below the mirrors;
    * the laser lattice — the mean lateral slope (e1 + e2)/2 = Y/Z of a true pair is the slope
      of a laser ray (the source sits midway between the mirrors), so a pairing shifted by one
      lattice step falls between rays and is rejected;
    * the remaining ambiguity — a pairing shifted by two lattice steps describes another flat
      surface at a wrong depth (SPEC §2). Along each laser row the assignment is a chain
      ordered by laser ray, camera-1 column and camera-2 column (the order of dots along a
      row); of all such chains the one matching the *most* dots wins (a shifted chain always
      leaves dots at its ends unmatched), and among equally long ones the nearest the floor
      (the thesis' floor-first rule), with the lattice, row and brightness agreement next.

    It is solved exactly per row by dynamic programming, vectorised over all rows at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require

if TYPE_CHECKING:
    from omnid.core.calibration import Calibration

MatchMethod = Literal["thesis", "best"]

__all__ = [
    "MatchMethod",
    "MatchSettings",
    "ThesisPolynomials",
    "col_design",
    "fit_thesis_polynomials",
    "match_dots",
    "match_dots_indexed",
    "predict_thesis",
]


@dataclass(frozen=True)
class MatchSettings:
    """Tolerances and the height window of the matchers (px, mm)."""

    row_tol_px: float = 1.5  # best: rows (ray slopes X/Z) of a pair must agree within this
    min_depth_mm: float = 250.0  # highest obstacle top considered: this far below the mirrors
    dropoff_depth_mm: float = 400.0  # deepest drop-off considered: this far below the floor
    lattice_tol: float = 0.25  # best: mid slope off a laser ray by at most this × lattice step
    double_dot_ratio: float = 1.35  # best: brighter than this × median = two merged dots
    thesis_search_px: float = 1.0  # thesis: neighbourhood searched for each n of eq. 6.16
    thesis_max_n: int | None = None  # thesis: upper limit of n; None = from min_depth_mm

    def __post_init__(self) -> None:
        require(self.row_tol_px > 0, "row_tol_px", "must be positive")
        require(self.min_depth_mm > 0, "min_depth_mm", "must be positive")
        require(self.dropoff_depth_mm >= 0, "dropoff_depth_mm", "must not be negative")
        require(0 < self.lattice_tol < 0.5, "lattice_tol", "must be in (0, 0.5)")
        require(self.thesis_search_px > 0, "thesis_search_px", "must be positive")
        require(self.thesis_max_n is None or self.thesis_max_n >= 0, "thesis_max_n", "must be >= 0")


def _empty() -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp]]:
    return np.zeros((0, 4)), np.zeros(0, np.intp), np.zeros(0, np.intp)


def _as_dots(dots: NDArray) -> NDArray[np.float64]:
    arr = np.asarray(dots, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, 3))
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise ValueError(f"expected dots of shape (N, 3) (row, col, strength), got {arr.shape}")
    if arr.shape[1] == 2:
        arr = np.column_stack([arr, np.ones(len(arr))])
    return arr


def _expand_ranges(
    lo: NDArray[np.intp], hi: NDArray[np.intp]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """All (owner, position) with lo[owner] <= position < hi[owner], vectorised."""
    cnt = np.maximum(hi - lo, 0)
    owner = np.repeat(np.arange(len(lo)), cnt)
    start = np.repeat(np.cumsum(cnt) - cnt, cnt)
    pos = np.arange(int(cnt.sum())) - start + np.repeat(lo, cnt)
    return owner, pos.astype(np.intp)


def _candidates_by_row(
    rows1: NDArray[np.float64], rows2: NDArray[np.float64], tol: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """All index pairs (i, j) with |rows1[i] − rows2[j]| <= tol (sorting, no N×M matrix)."""
    order = np.argsort(rows2, kind="stable")
    srt = rows2[order]
    lo = np.searchsorted(srt, rows1 - tol, side="left")
    hi = np.searchsorted(srt, rows1 + tol, side="right")
    i, pos = _expand_ranges(lo, hi)
    return i, order[pos]


# --------------------------------------------------------------------------------------------
# The thesis polynomials (eqs. 6.12–6.16)
# --------------------------------------------------------------------------------------------


def row_design(r: NDArray[np.float64]) -> NDArray[np.float64]:
    """A_r = [r 1] of eq. 6.14 (rows of camera-1 pixels)."""
    return np.column_stack([r, np.ones_like(r)])


def col_design(r: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray[np.float64]:
    """A_c = [r³ c³ r²c² r²c rc² r² c² rc r c 1] of eq. 6.15 (the 11 terms of eq. 6.13)."""
    return np.column_stack(
        [r**3, c**3, r**2 * c**2, r**2 * c, r * c**2, r**2, c**2, r * c, r, c, np.ones_like(r)]
    )


def _lstsq(A: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
    """Least-squares solution of A·x = y with column scaling (r³ and 1 differ by 10⁸)."""
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    sol, *_ = np.linalg.lstsq(A / scale, y, rcond=None)
    return np.asarray(sol / scale, dtype=np.float64)


def predict_thesis(
    row_coeffs: tuple[float, ...] | NDArray[np.float64],
    col_coeffs: tuple[float, ...] | NDArray[np.float64],
    rc1: NDArray[np.float64],
    n: float = 0.0,
) -> NDArray[np.float64]:
    """Camera-2 (y_r, y_c) px predicted for camera-1 pixels (N, 2): eq. 6.12 and eq. 6.16
    (eq. 6.13 when n = 0)."""
    q = np.asarray(rc1, dtype=np.float64).reshape(-1, 2)
    yr = row_design(q[:, 0]) @ np.asarray(row_coeffs, dtype=np.float64)
    yc = col_design(q[:, 0], q[:, 1]) @ np.asarray(col_coeffs, dtype=np.float64) - n
    return np.column_stack([yr, yc])


@dataclass(frozen=True)
class ThesisPolynomials:
    """Final coefficients of eqs. 6.12/6.13 and the pairs of the last refinement step."""

    row_coeffs: tuple[float, float]
    col_coeffs: tuple[float, ...]
    pairs_px: NDArray[np.float64]  # (K, 4) r1 c1 r2 c2
    row_rms_px: float
    col_rms_px: float


def _fit(pairs: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least-squares coefficients of eq. 6.14 (rows) and eq. 6.15 (columns) from pairs (K, 4)."""
    if len(pairs) < 11:
        raise ValueError(f"need at least 11 control pixel pairs for eq. 6.13, got {len(pairs)}")
    xr = _lstsq(row_design(pairs[:, 0]), pairs[:, 2])
    xc = _lstsq(col_design(pairs[:, 0], pairs[:, 1]), pairs[:, 3])
    return xr, xc


def _search(
    pred: NDArray[np.float64],
    rc2: NDArray[np.float64],
    radius_px: float,
    free1: NDArray[np.bool_],
    free2: NDArray[np.bool_],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Thesis neighbourhood search: camera-2 centres within ``radius_px`` (per axis) of the
    rounded prediction; each centre used once, nearest first."""
    ids1 = np.flatnonzero(free1)
    ids2 = np.flatnonzero(free2)
    if len(ids1) == 0 or len(ids2) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    target = np.rint(pred[ids1])  # the thesis rounds the polynomial's values to integer pixels
    a, b = _candidates_by_row(target[:, 0], rc2[ids2, 0], radius_px)
    close = np.abs(rc2[ids2[b], 1] - target[a, 1]) <= radius_px
    a, b = a[close], b[close]
    if len(a) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    dist = np.hypot(*(rc2[ids2[b]] - target[a]).T)
    order = np.argsort(dist, kind="stable")
    used1: set[int] = set()
    used2: set[int] = set()
    out1, out2 = [], []
    for k in order:
        i, j = int(ids1[a[k]]), int(ids2[b[k]])
        if i in used1 or j in used2:
            continue
        used1.add(i)
        used2.add(j)
        out1.append(i)
        out2.append(j)
    return np.array(out1, dtype=np.intp), np.array(out2, dtype=np.intp)


def fit_thesis_polynomials(
    control_px: NDArray[np.float64],
    rc1: NDArray[np.float64],
    rc2: NDArray[np.float64],
    neighbourhoods_px: tuple[float, ...] = (2.0, 1.0),
) -> ThesisPolynomials:
    """Eqs. 6.12/6.13 fitted to control pixel pairs (K, 4), refined in the thesis' three steps.

    Step 1 fits the control pairs and matches every camera-1 centre ``rc1`` to a camera-2
    centre ``rc2`` within 2 px of its prediction; step 2 refits on those pairs and searches
    within 1 px; step 3 refits on the step-2 pairs: the final coefficients (6.3.1.1).
    """
    c = np.asarray(control_px, dtype=np.float64).reshape(-1, 4)
    q1 = np.asarray(rc1, dtype=np.float64).reshape(-1, 2)[:, :2]
    q2 = np.asarray(rc2, dtype=np.float64).reshape(-1, 2)[:, :2]
    xr, xc = _fit(c)
    pairs = c
    for radius in neighbourhoods_px:
        pred = predict_thesis(xr, xc, q1)
        i, j = _search(pred, q2, radius, np.ones(len(q1), bool), np.ones(len(q2), bool))
        if len(i) < 11:
            break
        pairs = np.column_stack([q1[i], q2[j]])
        xr, xc = _fit(pairs)
    pred = predict_thesis(xr, xc, pairs[:, :2])
    return ThesisPolynomials(
        row_coeffs=(float(xr[0]), float(xr[1])),
        col_coeffs=tuple(float(v) for v in xc),
        pairs_px=pairs,
        row_rms_px=float(np.sqrt(np.mean((pred[:, 0] - pairs[:, 2]) ** 2))),
        col_rms_px=float(np.sqrt(np.mean((pred[:, 1] - pairs[:, 3]) ** 2))),
    )


def _thesis_max_n(calib: Calibration, s: MatchSettings) -> int:
    if s.thesis_max_n is not None:
        return s.thesis_max_n
    rig = calib.rig
    f = 0.5 * (rig.cam1.f_over_k_px + rig.cam2.f_over_k_px)
    fd = f * rig.baseline_mm
    return max(0, math.ceil(fd / s.min_depth_mm - fd / rig.floor_depth_mm))


def _match_thesis(
    calib: Calibration, d1: NDArray[np.float64], d2: NDArray[np.float64], s: MatchSettings
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Eq. 6.16 with n = 0, 1, ..., removing matched centres as n grows (6.3.1.2)."""
    free1 = np.ones(len(d1), dtype=bool)
    free2 = np.ones(len(d2), dtype=bool)
    base = predict_thesis(calib.row_coeffs, calib.col_coeffs, d1[:, :2])
    out1, out2 = [], []
    for n in range(_thesis_max_n(calib, s) + 1):
        if not free1.any() or not free2.any():
            break
        pred = base - np.array([0.0, float(n)])
        i, j = _search(pred, d2[:, :2], s.thesis_search_px, free1, free2)
        free1[i] = False
        free2[j] = False
        out1.append(i)
        out2.append(j)
    if not out1:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    return np.concatenate(out1), np.concatenate(out2)


# --------------------------------------------------------------------------------------------
# Our matcher
# --------------------------------------------------------------------------------------------


def _match_best(
    calib: Calibration, d1: NDArray[np.float64], d2: NDArray[np.float64], s: MatchSettings
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    rig = calib.rig
    D = rig.baseline_mm
    H = rig.floor_depth_mm
    f = 0.5 * (rig.cam1.f_over_k_px + rig.cam2.f_over_k_px)
    p1 = rig.cam1.ray_slopes(d1[:, :2])  # (X/Z, (Y − Y1)/Z)
    p2 = rig.cam2.ray_slopes(d2[:, :2])
    tol_a = s.row_tol_px / f
    i, j = _candidates_by_row(p1[:, 0], p2[:, 0], tol_a)
    disp = p1[i, 1] - p2[j, 1]  # D/Z
    lo, hi = D / (H + s.dropoff_depth_mm), D / s.min_depth_mm
    ok = (disp >= lo) & (disp <= hi)
    i, j, disp = i[ok], j[ok], disp[ok]
    a_mid = 0.5 * (p1[i, 0] + p2[j, 0])
    b_mid = 0.5 * (p1[i, 1] + p2[j, 1])  # Y/Z: the slope of the laser ray, if the pair is true
    lat = calib.lattice
    if lat is not None:
        la = (a_mid - lat.a0) / lat.step_a
        kb = (b_mid - lat.b0) / lat.step_b
        row_id = np.rint(la).astype(np.int64)
        ray_id = np.rint(kb).astype(np.int64)
        res_b = np.abs(kb - ray_id)
        keep = (res_b <= s.lattice_tol) & (np.abs(la - row_id) <= s.lattice_tol)
        keep &= (row_id >= lat.rows[0] - 1) & (row_id <= lat.rows[1] + 1)
        i, j, disp, b_mid, row_id, ray_id, res_b = (
            v[keep] for v in (i, j, disp, b_mid, row_id, ray_id, res_b)
        )
        c_lat = res_b / s.lattice_tol
        slack = 0.3 * lat.step_b
    else:
        # No lattice known: group by camera-1 row, rank rays by the mid slope.
        srt = np.sort(p1[:, 0])
        gaps = np.concatenate([[0], np.cumsum(np.diff(srt) > 2 * tol_a)])
        row_id = gaps[np.searchsorted(srt, p1[i, 0])].astype(np.int64)
        ray_id = np.zeros(len(i), dtype=np.int64)
        order = np.lexsort((b_mid, row_id))
        ray_id[order] = np.arange(len(order))
        c_lat = np.zeros(len(i))
        slack = 3.0 / f
    if len(i) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    c_floor = np.minimum(np.abs(disp - D / H) / max(hi - D / H, 1e-9), 1.0)
    c_row = np.minimum(np.abs(p1[i, 0] - p2[j, 0]) / tol_a, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.abs(np.log(np.maximum(d1[i, 2], 1e-3) / np.maximum(d2[j, 2], 1e-3)))
    c_bright = np.minimum(np.nan_to_num(ratio / math.log(2.0)), 1.0)
    cost = 0.6 * c_floor + 0.2 * np.minimum(c_lat, 1.0) + 0.1 * c_row + 0.1 * c_bright
    gain = 1.0 - 0.01 * cost  # one more pair always outweighs any cost difference
    e1, e2 = p1[i, 1], p2[j, 1]
    # A dot twice as bright as usual is two dots on top of each other (a surface one lattice
    # step nearer makes its dots land on their neighbours' floor positions): it may be used twice.
    mult1 = _multiplicity(d1[:, 2], s.double_dot_ratio)
    mult2 = _multiplicity(d2[:, 2], s.double_dot_ratio)
    return _chain_dp(row_id, ray_id, i, j, e1, e2, gain, slack, mult1, mult2)


def _multiplicity(strength: NDArray[np.float64], ratio: float) -> NDArray[np.int64]:
    """How many dots each detection may stand for: 2 where it is ``ratio`` × the median bright."""
    if len(strength) == 0:
        return np.zeros(0, dtype=np.int64)
    med = float(np.median(strength))
    return np.where(strength > ratio * med, 2, 1).astype(np.int64)


def _chain_dp(
    row_id: NDArray[np.int64],
    ray_id: NDArray[np.int64],
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    e1: NDArray[np.float64],
    e2: NDArray[np.float64],
    gain: NDArray[np.float64],
    slack: float,
    mult1: NDArray[np.int64],
    mult2: NDArray[np.int64],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Best chain of hypotheses per laser row (max total gain), all rows at once.

    A chain is ordered by laser ray (strictly) and by both cameras' column slopes (within
    ``slack``); consecutive members use different dots unless a dot may stand for two
    (``mult`` = 2). Returns the chosen (i, j).
    """
    order = np.lexsort((e1, ray_id, row_id))
    row_id, ray_id, i, j = row_id[order], ray_id[order], i[order], j[order]
    e1, e2, gain = e1[order], e2[order], gain[order]
    groups, start, counts = np.unique(row_id, return_index=True, return_counts=True)
    G, T = len(groups), int(counts.max())
    pos = np.arange(len(row_id)) - np.repeat(start, counts)
    g_of = np.repeat(np.arange(G), counts)

    def pad(v: NDArray, fill: float) -> NDArray:
        out = np.full((G, T), fill, dtype=np.float64)
        out[g_of, pos] = v
        return out

    K, I, J = pad(ray_id, np.inf), pad(i, -1), pad(j, -2)
    E1, E2, W = pad(e1, np.inf), pad(e2, np.inf), pad(gain, -np.inf)
    D1 = pad(mult1[i] > 1, 0.0) > 0
    D2 = pad(mult2[j] > 1, 0.0) > 0
    valid = np.zeros((G, T), dtype=bool)
    valid[g_of, pos] = True
    score = np.full((G, T), -np.inf)
    prev = np.full((G, T), -1, dtype=np.intp)
    gi = np.arange(G)
    for t in range(T):
        if t == 0:
            score[:, 0] = np.where(valid[:, 0], W[:, 0], -np.inf)
            continue
        compat = (
            (K[:, :t] < K[:, t : t + 1])
            & (E1[:, :t] < E1[:, t : t + 1] + slack)
            & (E2[:, :t] < E2[:, t : t + 1] + slack)
            & ((I[:, :t] != I[:, t : t + 1]) | D1[:, t : t + 1])
            & ((J[:, :t] != J[:, t : t + 1]) | D2[:, t : t + 1])
        )
        cand = np.where(compat, score[:, :t], -np.inf)
        am = np.argmax(cand, axis=1)
        bv = cand[gi, am]
        use = np.isfinite(bv)
        score[:, t] = np.where(valid[:, t], np.where(use, bv, 0.0) + W[:, t], -np.inf)
        prev[:, t] = np.where(use & valid[:, t], am, -1)
    cur = np.argmax(score, axis=1)
    cur = np.where(np.isfinite(score[gi, cur]), cur, -1)
    chosen = []
    while (cur >= 0).any():
        g = gi[cur >= 0]
        c = cur[cur >= 0]
        chosen.append(start[g] + c)
        cur[g] = prev[g, c]
    if not chosen:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    sel = np.concatenate(chosen)
    out_i, out_j = i[sel], j[sel]
    # Each dot is used at most as often as it may stand for dots (the chain allows near-ties in
    # column order): keep the best uses.
    rank = np.argsort(-gain[sel], kind="stable")
    out_i, out_j = out_i[rank], out_j[rank]
    keep = (_occurrence(out_i) < mult1[out_i]) & (_occurrence(out_j) < mult2[out_j])
    return out_i[keep].astype(np.intp), out_j[keep].astype(np.intp)


def _occurrence(ids: NDArray[np.intp]) -> NDArray[np.int64]:
    """0 for the first occurrence of each id in ``ids``, 1 for the second, ..."""
    order = np.argsort(ids, kind="stable")
    srt = ids[order]
    first = np.concatenate([[True], srt[1:] != srt[:-1]]) if len(srt) else np.zeros(0, bool)
    start = np.maximum.accumulate(np.where(first, np.arange(len(srt)), 0))
    occ = np.empty(len(ids), dtype=np.int64)
    occ[order] = np.arange(len(srt)) - start
    return occ


# --------------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------------


def match_dots_indexed(
    calib: Calibration,
    dots1: NDArray,
    dots2: NDArray,
    method: MatchMethod = "best",
    settings: MatchSettings | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp]]:
    """Matched pixels (K, 4) r1 c1 r2 c2 px and the indices into ``dots1`` and ``dots2``."""
    s = settings or MatchSettings()
    d1, d2 = _as_dots(dots1), _as_dots(dots2)
    if method not in ("thesis", "best"):
        raise ValueError(f"unknown matching method {method!r} (known: thesis, best)")
    if len(d1) == 0 or len(d2) == 0:
        return _empty()
    if method == "thesis":
        i, j = _match_thesis(calib, d1, d2, s)
    else:
        i, j = _match_best(calib, d1, d2, s)
    order = np.argsort(i, kind="stable")
    i, j = i[order], j[order]
    return np.column_stack([d1[i, :2], d2[j, :2]]), i, j


def match_dots(
    calib: Calibration,
    dots1: NDArray,
    dots2: NDArray,
    method: MatchMethod = "best",
    settings: MatchSettings | None = None,
) -> NDArray[np.float64]:
    """Matched image positions (K, 4) as (r1, c1, r2, c2) px; see the module docstring."""
    return match_dots_indexed(calib, dots1, dots2, method, settings)[0]
