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
    * no phantom drop-off — a pair read under the floor needs a neighbour at its depth (a dot
      whose partner is hidden pairs with a nearer dot's image beside it, at an occluder's edge);
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
    from omnid.core.calibration import Calibration, LaserLattice
    from omnid.core.geometry import MirrorCamera

MatchMethod = Literal["thesis", "best"]
_NO_RAY = -(2**40)  # "ray not known" (ray indices run negative too)

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
    anchor_margin_px: float = 5.0  # best: a row end is the lattice end when one more dot
    # would lie this far inside the mirror disk
    dropoff_min_mm: float = 20.0  # best: a pair read this far under the floor (and 5 σ of
    # the disparity scatter) needs a neighbour (next ray of its row or same ray of the next
    # row) at the same depth
    phantom_margin_mm: float = 100.0  # best: a dot read this much nearer than a lower row's
    # dot of the same laser column, at the floor's shifted depth, is refused
    # best: a step along a row counts as one ray when within this × lattice step; None: from
    # the calibration's dot scatter (5·√2·σ over the step in px, at least 0.05)
    walk_tol: float | None = None
    thesis_search_px: float = 1.0  # thesis: neighbourhood searched for each n of eq. 6.16
    thesis_max_n: int | None = None  # thesis: upper limit of n; None = from min_depth_mm

    def __post_init__(self) -> None:
        require(self.row_tol_px > 0, "row_tol_px", "must be positive")
        require(self.min_depth_mm > 0, "min_depth_mm", "must be positive")
        require(self.dropoff_depth_mm >= 0, "dropoff_depth_mm", "must not be negative")
        require(0 < self.lattice_tol < 0.5, "lattice_tol", "must be in (0, 0.5)")
        require(self.anchor_margin_px >= 0, "anchor_margin_px", "must not be negative")
        require(self.walk_tol is None or 0 < self.walk_tol < 0.5, "walk_tol", "must be in (0, 0.5)")
        require(self.dropoff_min_mm > 0, "dropoff_min_mm", "must be positive")
        require(self.phantom_margin_mm > 0, "phantom_margin_mm", "must be positive")
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
    lat = calib.lattice
    if lat is None:
        return _match_best_no_lattice(calib, d1, d2, s)
    rig = calib.rig
    D = rig.baseline_mm
    H = rig.floor_depth_mm
    f = 0.5 * (rig.cam1.f_over_k_px + rig.cam2.f_over_k_px)
    p1 = rig.cam1.ray_slopes(d1[:, :2])  # (X/Z, (Y − Y1)/Z)
    p2 = rig.cam2.ray_slopes(d2[:, :2])
    tol_a = s.row_tol_px / f
    sb = lat.step_b
    # Laser row of each dot from its own camera (the row does not change with depth, SPEC §2).
    l1f = (p1[:, 0] - lat.a0) / lat.step_a
    l2f = (p2[:, 0] - lat.a0) / lat.step_a
    l1 = np.rint(l1f).astype(np.int64)
    l2 = np.rint(l2f).astype(np.int64)
    on1 = (np.abs(l1f - l1) <= s.lattice_tol) & (l1 >= lat.rows[0] - 1) & (l1 <= lat.rows[1] + 1)
    on2 = (np.abs(l2f - l2) <= s.lattice_tol) & (l2 >= lat.rows[0] - 1) & (l2 <= lat.rows[1] + 1)
    # Anchors: ray index of each dot implied by a lattice end visible in its camera, or −1.
    mult1 = _multiplicity(d1[:, 2], s.double_dot_ratio)
    mult2 = _multiplicity(d2[:, 2], s.double_dot_ratio)
    walk_tol = s.walk_tol
    sigma_px = float(calib.residuals.get("row_rms_px", 0.1)) if calib.residuals else 0.1
    if walk_tol is None:
        # a depth jump across a hidden ray can mimic one step to within a few hundredths, so
        # the walk is as strict as the dots' own scatter allows (0.1 px when unknown)
        walk_tol = min(0.25, max(0.05, 5.0 * math.sqrt(2.0) * sigma_px / (f * sb)))
    k1 = _anchor_labels(rig.cam1, p1, l1, on1, lat, s, mult1 > 1, walk_tol)
    k2 = _anchor_labels(rig.cam2, p2, l2, on2, lat, s, mult2 > 1, walk_tol)
    # Candidates: same laser row, disparity D/Z in the window, mid slope on a laser ray.
    lo, hi = D / (H + s.dropoff_depth_mm), D / s.min_depth_mm
    ids2 = np.flatnonzero(on2)
    key2 = l2[ids2] * 1000.0 + p2[ids2, 1]
    o2 = np.argsort(key2, kind="stable")
    ids2, key2 = ids2[o2], key2[o2]
    ids1 = np.flatnonzero(on1)
    key1 = l1[ids1] * 1000.0 + p1[ids1, 1]
    a_lo = np.searchsorted(key2, key1 - hi, side="left")
    a_hi = np.searchsorted(key2, key1 - lo, side="right")
    own, pos = _expand_ranges(a_lo, a_hi)
    i, j = ids1[own], ids2[pos]
    if len(i) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    disp = p1[i, 1] - p2[j, 1]  # D/Z
    b_mid = 0.5 * (p1[i, 1] + p2[j, 1])  # Y/Z: the slope of the laser ray, if the pair is true
    kb = (b_mid - lat.b0) / sb
    ray = np.rint(kb).astype(np.int64)
    res_b = np.abs(kb - ray)
    keep = (res_b <= s.lattice_tol) & (np.abs(p1[i, 0] - p2[j, 0]) <= tol_a)
    keep &= (ray >= lat.cols[0]) & (ray <= lat.cols[1])  # no dot comes from a ray that is not there
    i0, j0 = i[keep], j[keep]  # before the labels: for the phantom check
    # A dot whose camera shows the end of its laser row knows its ray: pairs against it go.
    keep &= (k1[i] == _NO_RAY) | (k1[i] == ray)
    keep &= (k2[j] == _NO_RAY) | (k2[j] == ray)
    i, j, disp, ray, res_b = i[keep], j[keep], disp[keep], ray[keep], res_b[keep]
    if len(i) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    c_floor = np.minimum(np.abs(disp - D / H) / max(hi - D / H, 1e-9), 1.0)
    c_row = np.minimum(np.abs(p1[i, 0] - p2[j, 0]) / tol_a, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.abs(np.log(np.maximum(d1[i, 2], 1e-3) / np.maximum(d2[j, 2], 1e-3)))
    c_bright = np.minimum(np.nan_to_num(ratio / math.log(2.0)), 1.0)
    c_lat = np.minimum(res_b / s.lattice_tol, 1.0)
    cost = 0.6 * c_floor + 0.2 * c_lat + 0.1 * c_row + 0.1 * c_bright
    # anchored pairs are certain; the rest carry the floor-first preference
    anchored = (k1[i] != _NO_RAY) | (k2[j] != _NO_RAY)
    gain = 1.0 - 0.01 * cost + 0.001 * anchored
    # Pairs fixed by the labels of both dots, with no rival, need no search.
    cnt_i = np.bincount(i, minlength=len(d1))
    cnt_j = np.bincount(j, minlength=len(d2))
    sure = (k1[i] != _NO_RAY) & (k2[j] != _NO_RAY) & (cnt_i[i] == 1) & (cnt_j[j] == 1)
    si, sj = i[sure], j[sure]
    rest = ~sure
    used_j = np.zeros(len(d2), dtype=bool)
    used_j[sj] = True
    rest &= ~used_j[j] | (mult2[j] > 1)
    slack = 0.3 * sb
    if rest.any() and sure.any():
        # the rest must keep the order of rays and camera-2 columns with the sure pairs
        skey = l1[si] * 1000.0 + p1[si, 1]
        so = np.argsort(skey)
        skey, sray, se2 = skey[so], ray[sure][so], p2[sj[so], 1]
        q = l1[i] * 1000.0 + p1[i, 1]
        pos = np.searchsorted(skey, q)
        left = np.maximum(pos - 1, 0)
        right = np.minimum(pos, len(skey) - 1)
        has_l = (pos > 0) & (np.rint(skey[left] / 1000.0) == l1[i])
        has_r = (pos < len(skey)) & (np.rint(skey[right] / 1000.0) == l1[i])
        e2c = p2[j, 1]
        rest &= ~has_l | ((ray > sray[left]) & (e2c > se2[left] - slack))
        rest &= ~has_r | ((ray < sray[right]) & (e2c < se2[right] + slack))
    if not rest.any():
        return si.astype(np.intp), sj.astype(np.intp)
    vi, vj = _row_viterbi(
        l1,
        p1[:, 1],
        i[rest],
        j[rest],
        ray[rest],
        p2[j[rest], 1],
        disp[rest],
        gain[rest],
        slack,
        2.0 * sb,
        mult2,
    )
    ci = np.concatenate([si, vi]).astype(np.intp)
    cj = np.concatenate([sj, vj]).astype(np.intp)
    suspect = _floor_phantom_suspects(p1[ci], p2[cj], lat, D / H, s.phantom_margin_mm, D)
    if suspect.any():
        # labels may be wrong here (a row end hidden by an obstacle looks like the lattice
        # end), so the floor reading is looked for among all candidates, labels ignored
        keep_h = _unambiguous(l1, p1[:, 1], p2[:, 1], i0, j0, ci, cj, suspect, sb, (-2.0,), D / H)
        ci, cj = ci[keep_h], cj[keep_h]
    # under the floor: deeper than dropoff_min_mm and than 5 σ of the disparity's scatter
    under = max(D / H - D / (H + s.dropoff_min_mm), 5.0 * math.sqrt(2.0) * sigma_px / f)
    keep_d = _dropoff_supported(p1[ci], p2[cj], lat, D / H - under)
    return ci[keep_d], cj[keep_d]


def _dropoff_supported(
    q1: NDArray[np.float64],
    q2: NDArray[np.float64],
    lat: LaserLattice,
    under_disp: float,
) -> NDArray[np.bool_]:
    """Which pairs to keep: a pair read under the floor (disparity D/Z below ``under_disp``)
    needs a neighbour that agrees.

    ``q1``, ``q2`` are the ray slopes (X/Z, Y/Z) of each pair's dots. A real drop-off is a
    surface: the next ray of its laser row or the same ray of the next row lands on it too, at
    a disparity within 0.3 lattice steps. A lone pair under the floor is a dot whose true
    partner is hidden, paired with the image of a nearer dot that lies just beside where the
    partner would be (at the edge of an occluder): a phantom drop-off (a false stop), so it
    is left unmatched.
    """
    keep = np.ones(len(q1), dtype=bool)
    if len(q1) == 0:
        return keep
    disp = q1[:, 1] - q2[:, 1]  # D/Z
    deep = disp < under_disp
    if not deep.any():
        return keep
    row = np.rint((q1[:, 0] - lat.a0) / lat.step_a).astype(np.int64)
    col = np.rint((0.5 * (q1[:, 1] + q2[:, 1]) - lat.b0) / lat.step_b).astype(np.int64)
    width = int(col.max() - col.min()) + 3
    key = (row - row.min() + 1) * width + (col - col.min() + 1)
    order = np.argsort(key, kind="stable")
    skey, sdisp = key[order], disp[order]
    supported = np.zeros(len(q1), dtype=bool)
    for off in (-1, 1, -width, width):
        q = key + off
        pos = np.clip(np.searchsorted(skey, q), 0, len(skey) - 1)
        hit = (skey[pos] == q) & (np.abs(sdisp[pos] - disp) < 0.3 * lat.step_b)
        hit &= sdisp[pos] < under_disp
        supported |= hit
    keep[deep & ~supported] = False
    return keep


def _floor_phantom_suspects(
    q1: NDArray[np.float64],
    q2: NDArray[np.float64],
    lat: LaserLattice,
    floor_disp: float,
    margin_mm: float,
    D: float,
) -> NDArray[np.bool_]:
    """Which pairs may be floor rows read two lattice steps off (phantom obstacles).

    ``q1``, ``q2`` are the ray slopes (X/Z, Y/Z) of each pair's dots. A pairing of floor dots
    shifted by two lattice steps reads as a flat surface at the depth where D/Z is the
    floor's D/H plus two steps (SPEC §2: about 576 mm high on the default rig). Obstacles
    stand on the floor, so along one laser column (rays of equal Y/Z) a dot of a farther row
    (larger X/Z) cannot lie nearer (smaller X) than a dot of a nearer row: that ray would have
    hit the obstacle under it. A pair at the floor's shifted depth that lies more than
    ``margin_mm`` nearer than a dot of a lower row of its column is therefore the floor read
    one step off on each camera, or a table top at that height over visible floor: which of
    the two, the caller decides from the rest of the row (:func:`_unambiguous`).
    """
    out = np.zeros(len(q1), dtype=bool)
    if len(q1) < 2:
        return out
    disp = q1[:, 1] - q2[:, 1]  # D/Z
    z = D / np.maximum(disp, 1e-9)
    x = q1[:, 0] * z  # forward distance X = (X/Z)·Z, mm
    col = np.rint((0.5 * (q1[:, 1] + q2[:, 1]) - lat.b0) / lat.step_b).astype(np.int64)
    row = np.rint((q1[:, 0] - lat.a0) / lat.step_a).astype(np.int64)
    order = np.lexsort((row, col))
    c_o, x_o = col[order], x[order]
    grp = np.cumsum(np.concatenate([[True], c_o[1:] != c_o[:-1]])) - 1
    big = float(np.max(np.abs(x_o))) * 4.0 + 1.0
    run = np.maximum.accumulate(x_o + grp * big) - grp * big
    prev = np.full(len(x_o), -np.inf)
    same = np.concatenate([[False], grp[1:] == grp[:-1]])
    prev[1:] = np.where(same[1:], run[:-1], -np.inf)
    band = np.abs(disp[order] - floor_disp - 2.0 * lat.step_b) < 0.3 * lat.step_b
    out[order] = band & (x_o < prev - margin_mm)
    return out


def _unambiguous(
    row1: NDArray[np.int64],
    e1: NDArray[np.float64],
    e2: NDArray[np.float64],
    cand_i: NDArray[np.intp],
    cand_j: NDArray[np.intp],
    ci: NDArray[np.intp],
    cj: NDArray[np.intp],
    free: NDArray[np.bool_],
    sb: float,
    shifts: tuple[float, ...] = (-2.0, 2.0),
    floor_disp: float | None = None,
) -> NDArray[np.bool_]:
    """Which chosen pairs to keep: runs of unlabelled pairs whose pairing is ambiguous go.

    A run is a stretch of chosen pairs marked ``free`` (here: no lattice label on its dots, or
    a phantom suspect) along one laser row, in camera-1 column order, with a continuous
    disparity (steps below half a lattice step). Pairing every camera-1 dot of the run (and of the one lattice step beyond each end)
    with the camera-2 dot two lattice steps over instead (disparity + each of ``shifts``
    steps: the same laser rays, another flat surface, SPEC §2) is its shifted reading. When the shifted reading is
    made of valid candidates, uses no dot of another chosen pair and pairs at least as many
    dots as the run, nothing in the row tells the two apart (the floor-first and smoothness
    preferences are guesses): the run is refused. With ``floor_disp`` (D/H), a run with floor
    pairs on both sides in its row is kept. An unmatched dot is safe; a whole row one
    lattice step off is a phantom obstacle (or a real one read as floor).
    """
    keep = np.ones(len(ci), dtype=bool)
    disp_c = e1[ci] - e2[cj]
    disp_a = e1[cand_i] - e2[cand_j]
    used1 = np.zeros(len(e1), dtype=bool)
    used2 = np.zeros(len(e2), dtype=bool)
    used1[ci] = True
    used2[cj] = True
    order = np.lexsort((e1[ci], row1[ci]))
    r_o, d_o, f_o = row1[ci][order], disp_c[order], free[order]
    brk = np.ones(len(order), dtype=bool)
    brk[1:] = (r_o[1:] != r_o[:-1]) | (np.abs(d_o[1:] - d_o[:-1]) > 0.5 * sb)
    if floor_disp is not None:
        # a suspect frees the pairs of its stretch of continuous disparity that lie at the
        # floor's shifted depth too: the ends of a row read one step off are no surer than its
        # middle (their neighbours beyond are hidden), but a real surface beside it stays
        seg = np.cumsum(brk) - 1
        band = np.abs(d_o - floor_disp - 2.0 * sb) < 0.3 * sb
        f_o = f_o | (band & (np.bincount(seg, weights=f_o.astype(np.float64))[seg] > 0))
    brk[1:] |= f_o[1:] != f_o[:-1]
    run_id = np.cumsum(brk) - 1
    cand_row = row1[cand_i]
    # a suspect run's shifted reading may lose a dot at each end to the pairs beside it
    slack_ends = 1 if floor_disp is not None else 0
    for rid in np.unique(run_id[f_o]):
        at = np.flatnonzero(run_id == rid)
        members = order[at]
        if floor_disp is not None and at[0] > 0 and at[-1] < len(order) - 1:
            # floor pairs on both sides in the row: a surface standing out of the floor (its
            # edges show as a gap and a merged dot), not the floor read one step off
            nb = order[[at[0] - 1, at[-1] + 1]]
            if (row1[ci[nb]] == row1[ci[members[0]]]).all() and (
                np.abs(disp_c[nb] - floor_disp) < 0.3 * sb
            ).all():
                continue
        ri, rj = ci[members], cj[members]
        row = row1[ri[0]]
        lo, hi = e1[ri].min() - 1.3 * sb, e1[ri].max() + 1.3 * sb
        xs = np.argsort(e1[ri])
        near = (cand_row == row) & (e1[cand_i] >= lo) & (e1[cand_i] <= hi)
        if not near.any():
            continue
        ni, nj, nd = cand_i[near], cand_j[near], disp_a[near]
        d_ref = np.interp(e1[ni], e1[ri][xs], disp_c[members][xs])
        own1 = np.isin(ni, ri)
        own2 = np.isin(nj, rj)
        avail = (own1 | ~used1[ni]) & (own2 | ~used2[nj])
        for shift in shifts:
            alt = avail & (np.abs(nd - d_ref - shift * sb) < 0.3 * sb)
            if not alt.any():
                continue
            n_alt = min(len(np.unique(ni[alt])), len(np.unique(nj[alt])))
            if n_alt >= len(ri) - slack_ends:
                keep[members] = False
                break
    return keep


def _anchor_labels(
    cam: MirrorCamera,
    p: NDArray[np.float64],
    row: NDArray[np.int64],
    on: NDArray[np.bool_],
    lat: LaserLattice,
    s: MatchSettings,
    double: NDArray[np.bool_],
    walk_tol: float,
) -> NDArray[np.int64]:
    """Laser ray index of each dot implied by the ends of its laser row, or ``_NO_RAY``.

    Where one ray step beyond a row's outermost dot still lies well inside the mirror disk, a dot
    there would have been seen, so the outermost dot is the end of the laser lattice (ray
    ``cols[0]`` on the left, ``cols[1]`` on the right) — unless it is hidden: an occluder's edge
    (a partition beside a gap) can hide the end ray from one camera only, and then a
    neighbouring row shows a dot one step beyond (the lattice goes on there at about the same
    depth); such an end is no anchor (taking it was a whole row one ray off in that camera,
    and with the other camera's end hidden the other way, a row read two steps off: SPEC §2). Counting lattice steps inward along the
    row (while the spacing stays a whole number of steps, i.e. the depth does not jump) gives
    the ray of each dot. Rows whose two ends disagree get no labels.
    """
    out = np.full(len(p), _NO_RAY, dtype=np.int64)
    ids = np.flatnonzero(on)
    if len(ids) == 0:
        return out
    sb = lat.step_b
    ids = ids[np.lexsort((p[ids, 1], row[ids]))]
    L, e, a = row[ids], p[ids, 1], p[ids, 0]
    n = len(ids)
    start = np.concatenate([[True], L[1:] != L[:-1]])
    end = np.concatenate([L[1:] != L[:-1], [True]])
    g = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    last = np.flatnonzero(end)
    step = np.zeros(n)
    step[1:] = (e[1:] - e[:-1]) / sb
    inc = np.rint(step)
    # The walk stops at a gap (a missing dot, or a depth jump of whole lattice steps) and at a
    # double-bright dot (two dots on top of each other: a surface one step nearer).
    bad = ~start & ((np.abs(step - inc) > walk_tol) | (inc != 1))
    dbl = double[ids]
    bad |= dbl
    bad[1:] |= dbl[:-1] & ~start[1:]
    inc[start] = 0.0
    csum = np.cumsum(inc)
    bcum = np.cumsum(bad)

    def beyond_inside(idx: NDArray[np.intp], direction: float) -> NDArray[np.bool_]:
        xyz = np.column_stack([a[idx], e[idx] + direction * sb + cam.y_mm, np.ones(len(idx))])
        return cam.in_disk(cam.project(xyz), margin_px=s.anchor_margin_px)

    # A neighbouring row with a dot one step beyond this row's end (±0.3 step: about the same
    # depth) shows the lattice going on there: this row's next dot is hidden, not missing.
    e0, span = e.min() - 2.0 * sb, e.max() - e.min() + 4.0 * sb
    key = L * 2.0 + (e - e0) / span  # ascending, like the dots: by row, then column slope

    def hidden_beyond(idx: NDArray[np.intp], direction: float) -> NDArray[np.bool_]:
        hit = np.zeros(len(idx), dtype=bool)
        for dr in (-1, 1):
            at = e[idx] + direction * sb - e0
            lo = (L[idx] + dr) * 2.0 + (at - 0.3 * sb) / span
            hi = (L[idx] + dr) * 2.0 + (at + 0.3 * sb) / span
            hit |= np.searchsorted(key, hi, side="right") > np.searchsorted(key, lo, side="left")
        return hit

    has_l = (beyond_inside(first, -1.0) & ~hidden_beyond(first, -1.0))[g]
    has_r = (beyond_inside(last, +1.0) & ~hidden_beyond(last, +1.0))[g]
    k_l = lat.cols[0] + (csum - csum[first][g])
    ok_l = has_l & (bcum - bcum[first][g] == 0)
    k_r = lat.cols[1] - (csum[last][g] - csum)
    ok_r = has_r & (bcum[last][g] - bcum == 0)
    k = np.where(ok_l, k_l, k_r).astype(np.int64)
    ok = ok_l | ok_r
    conflict = (ok_l & ok_r & (k_l != k_r)) | (ok & ((k < lat.cols[0]) | (k > lat.cols[1])))
    bad_row = np.zeros(len(first), dtype=bool)
    np.logical_or.at(bad_row, g[conflict], True)
    ok &= ~bad_row[g]
    k = np.where(ok & ~dbl, k, _NO_RAY)
    if not ok.all():
        _propagate_labels(k, e, csum, np.cumsum(start | bad) - 1, first, last, sb, lat)
    out[ids] = k
    return out


def _propagate_labels(
    k: NDArray[np.int64],
    e: NDArray[np.float64],
    csum: NDArray[np.float64],
    seg: NDArray[np.int64],
    first: NDArray[np.intp],
    last: NDArray[np.intp],
    sb: float,
    lat: LaserLattice,
) -> None:
    """Carry ray labels to rows whose ends the mirror disk hides, in place.

    A laser ray's dots in neighbouring rows lie at nearly the same column slope (the depth of a
    surface changes little from one row to the next), so a dot within 0.3 lattice steps of a
    labelled dot of the row before takes its ray; a regularly spaced run of dots takes the
    labels only when at least two such votes agree and none disagrees. Only rows with no label
    of their own are filled (a depth jump of exactly one lattice step would fool the vote).
    Sweeps forward, then back. ``k``, ``e``, ``csum`` and ``seg`` are sorted by (row, column slope).
    """
    n_rows = len(first)
    for order in (range(1, n_rows), range(n_rows - 2, -1, -1)):
        for r in order:
            a, b = first[r], last[r] + 1
            if (k[a:b] != _NO_RAY).any():
                continue  # only rows with no label at all: a row's own ends are surer
            nb = r - 1 if order.step == 1 else r + 1
            pa, pb = first[nb], last[nb] + 1
            lab = k[pa:pb] != _NO_RAY
            if lab.sum() < 2:
                continue
            pe, pk = e[pa:pb][lab], k[pa:pb][lab]
            q = np.clip(np.searchsorted(pe, e[a:b]), 1, len(pe) - 1)
            near = np.where(np.abs(pe[q - 1] - e[a:b]) < np.abs(pe[q] - e[a:b]), q - 1, q)
            close = (np.abs(pe[near] - e[a:b]) < 0.3 * sb) & (k[a:b] == _NO_RAY)
            for sg in np.unique(seg[a:b][k[a:b] == _NO_RAY]):
                m = (seg[a:b] == sg) & close
                votes = pk[near[m]] - csum[a:b][m]
                if len(votes) >= 2 and (votes == votes[0]).all():
                    sel = np.flatnonzero(seg[a:b] == sg) + a
                    lab_new = (votes[0] + csum[sel]).astype(np.int64)
                    if lab_new.min() >= lat.cols[0] and lab_new.max() <= lat.cols[1]:
                        k[sel] = lab_new


def _row_viterbi(
    row1: NDArray[np.int64],
    e1: NDArray[np.float64],
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    ray: NDArray[np.int64],
    e2: NDArray[np.float64],
    disp: NDArray[np.float64],
    gain: NDArray[np.float64],
    slack: float,
    disp_scale: float,
    mult2: NDArray[np.int64],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Best assignment along each laser row: a Viterbi pass over the camera-1 dots in column
    order, each either unmatched or paired with one of its candidates, all rows at once.

    Consecutive pairs must keep the order of laser rays (strictly) and of camera-2 columns
    (within ``slack``) and use different camera-2 dots unless that dot may stand for two
    (``mult2``); a change of disparity between neighbours costs a little (surfaces are mostly
    continuous). The unmatched state carries the last pair of its best path, so the order holds
    across unmatched dots too. Returns the chosen (i, j).
    """
    # camera-1 dots with candidates, in (row, column) order → grid (G rows, P positions)
    u, inv = np.unique(i, return_inverse=True)
    uo = np.lexsort((e1[u], row1[u]))
    rank = np.empty(len(u), dtype=np.int64)
    rank[uo] = np.arange(len(u))
    ur = row1[u][uo]
    rstart = np.concatenate([[True], ur[1:] != ur[:-1]])
    grp = np.cumsum(rstart) - 1
    pos_in_row = np.arange(len(u)) - np.flatnonzero(rstart)[grp]
    G, P = int(grp[-1]) + 1, int(pos_in_row.max()) + 1
    cg, cp = grp[rank[inv]], pos_in_row[rank[inv]]
    # candidates of each dot: slot 0..C−1, best gain first
    co = np.lexsort((-gain, rank[inv]))
    slot = np.empty(len(i), dtype=np.int64)
    first = np.concatenate([[True], rank[inv][co][1:] != rank[inv][co][:-1]])
    slot[co] = np.arange(len(co)) - np.maximum.accumulate(np.where(first, np.arange(len(co)), 0))
    C = int(slot.max()) + 1
    shape = (G, P, C + 1)
    W = np.full(shape, -np.inf)
    W[:, :, C] = 0.0
    K = np.full(shape, -(2**40), dtype=np.int64)
    E = np.full(shape, -np.inf)
    J = np.full(shape, -1, dtype=np.int64)
    Dv = np.full(shape, 1e9)  # no pair before: the first disparity step costs the same for all
    DB = np.zeros(shape, dtype=bool)
    W[cg, cp, slot] = gain
    K[cg, cp, slot] = ray
    E[cg, cp, slot] = e2
    J[cg, cp, slot] = j
    Dv[cg, cp, slot] = disp
    DB[cg, cp, slot] = mult2[j] > 1
    CID = np.full(shape, -1, dtype=np.int64)
    CID[cg, cp, slot] = np.arange(len(i))
    gi = np.arange(G)
    cidx = np.arange(C)[None, :]
    back = np.zeros(shape, dtype=np.int64)
    S = W[:, 0].copy()
    aK, aE, aJ, aD = K[:, 0].copy(), E[:, 0].copy(), J[:, 0].copy(), Dv[:, 0].copy()
    for t in range(1, P):
        k_t, e_t, j_t, d_t = (
            K[:, t, None, :C],
            E[:, t, None, :C],
            J[:, t, None, :C],
            Dv[:, t, None, :C],
        )
        compat = (aK[:, :, None] < k_t) & (aE[:, :, None] < e_t + slack)
        compat &= (aJ[:, :, None] != j_t) | DB[:, t, None, :C]
        jump = np.minimum(np.abs(aD[:, :, None] - d_t), disp_scale)
        tot = np.where(compat, S[:, :, None] - jump * (0.05 / disp_scale), -np.inf)
        am = np.argmax(tot, axis=1)  # (G, C)
        best = tot[gi[:, None], am, cidx]
        carry = np.argmax(S, axis=1)
        newS = np.empty_like(S)
        newS[:, :C] = W[:, t, :C] + best
        newS[:, C] = S[gi, carry]
        back[:, t, :C] = am
        back[:, t, C] = carry
        nK, nE, nJ, nD = K[:, t].copy(), E[:, t].copy(), J[:, t].copy(), Dv[:, t].copy()
        nK[:, C], nE[:, C], nJ[:, C], nD[:, C] = (
            aK[gi, carry],
            aE[gi, carry],
            aJ[gi, carry],
            aD[gi, carry],
        )
        S, aK, aE, aJ, aD = newS, nK, nE, nJ, nD
    state = np.argmax(S, axis=1)
    chosen = np.empty((P, G), dtype=np.int64)
    for t in range(P - 1, -1, -1):
        chosen[t] = CID[gi, t, state]
        state = back[gi, t, state]
    sel = chosen.ravel()
    sel = sel[sel >= 0]
    if len(sel) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    out_i, out_j = i[sel], j[sel]
    r = np.argsort(-gain[sel], kind="stable")
    out_i, out_j = out_i[r], out_j[r]
    keep = _occurrence(out_j) < mult2[out_j]
    return out_i[keep].astype(np.intp), out_j[keep].astype(np.intp)


def _match_best_no_lattice(
    calib: Calibration, d1: NDArray[np.float64], d2: NDArray[np.float64], s: MatchSettings
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """``best`` without a laser lattice (a calibration that found none): rows by clustering,
    rays ranked by the mid slope, the most dots per row chain (slower, and blind to the
    two-step ambiguity that the lattice ends resolve)."""
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
    b_mid = 0.5 * (p1[i, 1] + p2[j, 1])  # Y/Z: the slope of the laser ray, if the pair is true
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
