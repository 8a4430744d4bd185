"""Stereo matching of laser dots between the two cameras (thesis 6.3.1.1–6.3.1.2; SPEC §2).

Interface::

    match_dots(calib, dots1 (N, 3), dots2 (M, 3), method="best" | "thesis") -> (K, 4) r1 c1 r2 c2
    match_dots_indexed(...) -> (pixels (K, 4), idx1 (K,), idx2 (K,))
    match_best_triples(calib, dots1, dots2) -> TripleMatch (with each pair's beam and depth)

``dots`` rows are (row_px, col_px, strength) as :func:`omnid.core.detect.detect_dots` gives
them. An empty input gives an empty (0, 4) result.

``thesis``
    The polynomial matcher of the thesis: the row polynomial eq. 6.12 (degree 1) and the
    11-term column polynomial eq. 6.13 map a camera-1 pixel to its camera-2 pixel on the floor;
    they are fitted by least squares (eqs. 6.14, 6.15) to control pixel pairs and refined in
    three steps (2 px, then 1 px search neighbourhoods, then the final coefficients). Points
    above the floor are searched with the integer n of eq. 6.16, n = 0, 1, 2, ..., removing the
    matched centres as n grows; dots left unmatched are dropped as noise.

``best`` — the laser as a third view
    Calibration learned every beam of the laser (:class:`~omnid.core.laser.LaserModel`); each
    beam images in both cameras as a straight track, affine in the inverse depth u = 1/Z:
    m(u) = α_k + β_k·u with m = (x1, y1, x2, y2) the ideal offsets. A *candidate* is a triple
    (camera-1 dot a, camera-2 dot b, beam k):

    1. stereo pairs (a, b) whose rays can meet (rows agree; a depth between ``near_depth_mm``
       and ``dropoff_depth_mm`` under the floor) — no laser needed;
    2. the beams such a point could lie on: the pair's point projected from the source onto the
       floor lands near beam k's floor point (within ``gate_sigma`` of its uncertainty);
    3. its least-squares u along the beam and the residual r (4 measurements, 1 unknown:
       χ² = |r|²/σ_t² with 3 degrees of freedom); σ_t combines the detector's noise (the
       calibration's measured scatter) with the track's own uncertainty (source and floor-point
       errors, growing away from the floor: much larger when the source is unknown);
    4. its weight: the log-likelihood ratio of "a and b are beam k's dot" against "a and b are
       unpaired detections and beam k is not seen":
       w = log((1−p)/p) − log ρ₁ρ₂ − 2 log(2πσ_t²) − log(L/(√(2π)σ_t)) − χ²/2, where p is
       ``beam_missing_probability``, ρ_i the density of unpaired detections per px²
       (``unpaired_fraction`` of the dots spread over the disk) and L the track's length in the
       4-D image space (the depth's prior is uniform along it).

    The answer is the one-to-one set of triples (each a, b and k at most once) of largest total
    weight — maximum likelihood — found exactly: a triple that outweighs the most its
    neighbours could give is in every optimum and is taken first (nearly all of them); what is
    left falls apart into small connected components, each solved by branch and bound
    (``exact_node_limit`` caps the search; :class:`TripleMatch` counts components where it was
    hit), the large ones by an integer program. No pattern law, no lattice, no
    per-scene rule: where the geometry leaves two readings (a source nearly in the mirror plane
    and a nearly regular pattern), the reading that explains more dots with smaller residuals
    wins, and the rest stays unmatched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.arrays import clip, stable_argsort

if TYPE_CHECKING:
    from omnid.core.calibration import Calibration
    from omnid.core.geometry import StereoRig
    from omnid.core.laser import LaserModel

MatchMethod = Literal["thesis", "best"]

__all__ = [
    "BeamTracks",
    "MatchMethod",
    "MatchSettings",
    "ThesisPolynomials",
    "TripleMatch",
    "col_design",
    "fit_thesis_polynomials",
    "match_best_triples",
    "match_dots",
    "match_dots_indexed",
    "match_triples",
    "predict_thesis",
    "stereo_candidates",
]


@dataclass(frozen=True)
class MatchSettings:
    """The matchers' few parameters (px, mm, probabilities), each with where its value comes from."""

    min_depth_mm: float = 250.0  # thesis: highest obstacle top considered (below the mirrors)
    # best: the nearest a dot can be, below the mirrors (their housing's underside): every
    # surface the cameras can see is inside the depth prior, so a tall thing close ahead
    # (a wall 400 mm away shows dots 200 mm below the mirrors) is read as itself — with 250
    # its dots had no true reading and paired with other dots into phantoms behind it
    # (tools/eval_rigs.py --approach)
    near_depth_mm: float = 100.0
    dropoff_depth_mm: float = 400.0  # deepest drop-off considered: this far below the floor
    # best: a triple whose residual exceeds this many σ per degree of freedom is no candidate
    # (χ² < 3·gate²: 5σ leaves a true triple out with probability ~1e-12 under the noise model)
    gate_sigma: float = 5.0
    # best: rows of a pair may differ by this much more than the noise explains, px (the
    # calibration's rotation error at the disk's rim: 0.02° × 235 px ≈ 0.1 px, doubled)
    row_slack_px: float = 0.2
    # best: share of a camera's detections that have no partner (seen by one camera only at
    # the rims and behind obstacles, ghosts); measured over the random rigs by
    # tools/eval_rigs.py: 3-8 % of the dots
    unpaired_fraction: float = 0.05
    # best: probability that a calibrated beam shows no pair in a capture (hidden, out of
    # view at its depth); it only shifts every weight by the same log-odds
    beam_missing_probability: float = 0.3
    # best: search nodes per conflict component before the best found is taken
    exact_node_limit: int = 20000
    thesis_search_px: float = 1.0  # thesis: neighbourhood searched for each n of eq. 6.16
    thesis_max_n: int | None = None  # thesis: upper limit of n; None = from min_depth_mm

    def __post_init__(self) -> None:
        require(self.min_depth_mm > 0, "min_depth_mm", "must be positive")
        require(self.near_depth_mm > 0, "near_depth_mm", "must be positive")
        require(self.dropoff_depth_mm >= 0, "dropoff_depth_mm", "must not be negative")
        require(self.gate_sigma > 1, "gate_sigma", "must exceed 1")
        require(self.row_slack_px >= 0, "row_slack_px", "must not be negative")
        require(0 < self.unpaired_fraction < 1, "unpaired_fraction", "must be in (0, 1)")
        require(
            0 < self.beam_missing_probability < 1,
            "beam_missing_probability",
            "must be in (0, 1)",
        )
        require(self.exact_node_limit >= 1, "exact_node_limit", "must be at least 1")
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
    ends = np.cumsum(cnt)
    owner = np.repeat(np.arange(len(lo)), cnt)
    # position = its rank among all + (lo − the owner's first rank), in place: each fresh
    # array of ~10⁴ costs page faults besides its pass
    pos = np.arange(int(ends[-1]) if len(ends) else 0, dtype=np.intp)
    pos += np.take(lo - (ends - cnt), owner)
    return owner, pos


def _candidates_by_row(
    rows1: NDArray[np.float64], rows2: NDArray[np.float64], tol: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """All index pairs (i, j) with |rows1[i] − rows2[j]| <= tol (sorting, no N×M matrix)."""
    order = stable_argsort(rows2)
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
# Our matcher: the laser as a third view
# --------------------------------------------------------------------------------------------


def stereo_candidates(
    rig: StereoRig,
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    row_tol_px: float,
    min_depth_mm: float = 250.0,
    max_depth_mm: float | None = None,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index pairs (i, j) whose rays can meet: rows agree (ray slopes X/Z within
    ``row_tol_px``) and the disparity D/Z puts the point between ``min_depth_mm`` and
    ``max_depth_mm`` (default: 400 mm under the floor) below the mirrors."""
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    p1, p2 = rig.cam1.ray_slopes(d1[:, :2]), rig.cam2.ray_slopes(d2[:, :2])
    return _stereo_pairs(rig, p1, p2, row_tol_px, min_depth_mm, max_depth_mm)


def _stereo_pairs(
    rig: StereoRig,
    p1: NDArray[np.float64],
    p2: NDArray[np.float64],
    row_tol_px: float,
    min_depth_mm: float,
    max_depth_mm: float | None,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """:func:`stereo_candidates` of the two cameras' ray slopes ``p1``, ``p2`` (N, 2)."""
    f = 0.5 * (rig.cam1.f_over_k_px + rig.cam2.f_over_k_px)
    i, j = _candidates_by_row(p1[:, 0], p2[:, 0], row_tol_px / f)
    disp = np.take(p1[:, 1], i) - np.take(p2[:, 1], j)  # D/Z
    deep = max_depth_mm if max_depth_mm is not None else rig.floor_depth_mm + 400.0
    ok = (disp >= rig.baseline_mm / deep) & (disp <= rig.baseline_mm / min_depth_mm)
    return i.compress(ok).astype(np.intp, copy=False), j.compress(ok).astype(np.intp, copy=False)


@dataclass(frozen=True)
class BeamTracks:
    """Each beam's image in both cameras as an affine function of the inverse depth u = 1/Z:
    m(u) = alpha + beta·u with m = (x1, y1, x2, y2) ideal offsets, px (see
    :class:`~omnid.core.laser.LaserModel`), and what makes the tracks uncertain."""

    # (4, K): coordinate first (numpy works ~5x slower along short rows)
    alpha: NDArray[np.float64]  # (4, K) px
    beta: NDArray[np.float64]  # (4, K) px·mm
    slope: NDArray[np.float64]  # (K, 2) s
    cross_mm: NDArray[np.float64]  # (K, 2) c
    floor_sigma_mm: NDArray[np.float64]  # (K,)
    source_mm: NDArray[np.float64]  # (3,)
    source_sigma_mm: NDArray[np.float64]  # (3,)
    floor_depth_mm: float
    f_px: NDArray[np.float64]  # (4,) F of each coordinate's camera
    x_order: NDArray[np.intp]  # beams sorted by floor X
    floor_x_sorted: NDArray[np.float64]
    floor_mm: NDArray[np.float64]  # (K, 3)
    cell_x_mm: NDArray[np.float64]  # (K,) floor X in cell_order (the look-up's hot loop)
    cell_y_mm: NDArray[np.float64]  # (K,) floor Y in cell_order
    slope2: NDArray[np.float64]  # (K,) |s|² of each beam (for slope_sigma, per triple)
    stereo_solve: NDArray[np.float64]  # (3, 4) pinv(A): (p, q, u) of a pair = this · m
    # the floor points binned in square cells of ``_CELL_MM`` (bands of Y, then X), sorted by
    # (band, X): a disk's neighbours are a few short runs of this order (_beams_near)
    cell_order: NDArray[np.intp]  # (K,) beams sorted by (band, X)
    cell_start: NDArray[np.intp]  # (bands·cols + 1,) first position of each cell in that order
    x_rank: NDArray[np.intp]  # (K,) each beam's position in x_order
    cell_origin_mm: tuple[float, float]  # (min X, min Y) of the floor points
    cell_shape: tuple[int, int]  # (bands, cols)

    @classmethod
    def from_model(cls, rig: StereoRig, laser: LaserModel) -> BeamTracks:
        from omnid.core.triangulate import best_design_matrix

        s, c = laser.slopes()
        f1, f2 = rig.cam1.f_over_k_px, rig.cam2.f_over_k_px
        y1, y2 = rig.cam1.y_mm, rig.cam2.y_mm
        alpha = np.array([-f1 * s[:, 0], f1 * s[:, 1], -f2 * s[:, 0], f2 * s[:, 1]])
        beta = np.array([-f1 * c[:, 0], f1 * (c[:, 1] - y1), -f2 * c[:, 0], f2 * (c[:, 1] - y2)])
        fl = np.asarray(laser.floor_mm, dtype=np.float64)
        order = np.argsort(fl[:, 0], kind="stable").astype(np.intp)
        x_rank = np.empty(len(order), np.intp)
        x_rank[order] = np.arange(len(order))
        x0, y0 = float(fl[:, 0].min()), float(fl[:, 1].min())
        band = np.floor((fl[:, 1] - y0) / _CELL_MM).astype(np.intp)
        col = np.floor((fl[:, 0] - x0) / _CELL_MM).astype(np.intp)
        shape = (int(band.max()) + 1, int(col.max()) + 1)
        cell_order = np.lexsort((fl[:, 0], band)).astype(np.intp)
        cell = band * shape[1] + col
        counts = np.bincount(cell, minlength=shape[0] * shape[1])
        cell_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
        return cls(
            alpha,
            beta,
            s,
            c,
            np.asarray(laser.floor_sigma_mm),
            np.asarray(laser.source_mm, dtype=np.float64),
            np.asarray(laser.source_sigma_mm, dtype=np.float64),
            laser.floor_depth_mm,
            np.array([f1, f1, f2, f2]),
            order,
            laser.floor_mm[order, 0],
            np.asarray(laser.floor_mm),
            fl[cell_order, 0],
            fl[cell_order, 1],
            np.sum(s**2, axis=1),
            np.asarray(np.linalg.pinv(best_design_matrix(rig)), dtype=np.float64),
            cell_order,
            cell_start,
            x_rank,
            (x0, y0),
            shape,
        )

    def slope_sigma(self, beam: NDArray[np.intp], u: NDArray[np.float64]) -> NDArray:
        """(N,) 1-σ of the beam's slope s + c·u at inverse depth u (source and floor point
        errors; see :class:`~omnid.core.laser.LaserModel`), per axis."""
        H = self.floor_depth_mm
        oz = self.source_mm[2]
        so = self.source_sigma_mm
        s2 = self.slope2[beam]
        lever_o = (u * H - 1.0) / (H - oz)
        lever_p = (1.0 - oz * u) / (H - oz)
        var = lever_o**2 * (0.5 * (so[0] ** 2 + so[1] ** 2) + s2 * so[2] ** 2)
        var += (lever_p * self.floor_sigma_mm[beam]) ** 2
        return np.sqrt(var)


def _tracks(calib_rig: StereoRig, laser: LaserModel) -> BeamTracks:
    key = (id(laser), calib_rig)
    hit = _TRACK_CACHE.get(key)
    if hit is not None and hit[0] is laser:
        return hit[1]
    tr = BeamTracks.from_model(calib_rig, laser)
    if len(_TRACK_CACHE) > 8:
        _TRACK_CACHE.clear()
    _TRACK_CACHE[key] = (laser, tr)
    return tr


_TRACK_CACHE: dict[tuple[int, StereoRig], tuple[LaserModel, BeamTracks]] = {}


@dataclass(frozen=True)
class TripleMatch:
    """The chosen (camera-1 dot, camera-2 dot, beam) triples and how they fit.

    i1, i2, beam    (K,) indices into dots1, dots2 and the laser model's beams
    inv_depth       (K,) u = 1/Z of each triple's least-squares fit, 1/mm
    residual_px     (K,) rms residual per image coordinate of the fit, px
    sigma_px        (K,) the track's total 1-σ per coordinate (pixel noise and model), px
    candidates      triples considered (χ² under the gate)
    components      conflict components solved (a triple in every optimum counts as one);
                    ``largest`` triples in the largest one left to a search; ``inexact``
                    components whose search hit its node limit (greedy result)
    """

    i1: NDArray[np.intp]
    i2: NDArray[np.intp]
    beam: NDArray[np.intp]
    inv_depth: NDArray[np.float64]
    residual_px: NDArray[np.float64]
    sigma_px: NDArray[np.float64]
    candidates: int = 0
    components: int = 0
    largest: int = 0
    inexact: int = 0


def _empty_triples() -> TripleMatch:
    z = np.zeros(0, np.intp)
    f = np.zeros(0)
    return TripleMatch(z, z, z, f, f, f)


def _beams_near(
    tr: BeamTracks, x: NDArray[np.float64], y: NDArray[np.float64], radius: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(query, beam) for every beam whose floor point lies within ``radius`` of (``x``, ``y``), sorted
    by query, then by the beam's floor X. Searched in the cells the disk's bounding square
    touches (a superset, widened by ``_EPS_MM``), then tested exactly."""
    x0, y0 = tr.cell_origin_mm
    n_bands, n_cols = tr.cell_shape
    r = radius + _EPS_MM
    b_lo = clip(np.floor((y - r - y0) / _CELL_MM), 0, n_bands - 1).astype(np.intp)
    b_hi = clip(np.floor((y + r - y0) / _CELL_MM), 0, n_bands - 1).astype(np.intp)
    c_lo = clip(np.floor((x - r - x0) / _CELL_MM), 0, n_cols - 1).astype(np.intp)
    c_hi = clip(np.floor((x + r - x0) / _CELL_MM), 0, n_cols - 1).astype(np.intp)
    qb, band = _expand_ranges(b_lo, b_hi + 1)  # (query, band) pairs
    row = band * n_cols
    # one run per (query, band): the cells c_lo … c_hi lie next to each other in cell order
    own, pos = _expand_ranges(tr.cell_start[row + c_lo[qb]], tr.cell_start[row + c_hi[qb] + 1])
    q = np.take(qb, own)
    # dx² + dy² <= r², in place (fewer fresh arrays of ~10⁴: each costs page faults)
    dx = np.take(tr.cell_x_mm, pos)
    dx -= np.take(x, q)
    dy = np.take(tr.cell_y_mm, pos)
    dy -= np.take(y, q)
    dx *= dx
    dy *= dy
    dx += dy
    rq = np.take(radius, q)
    rq *= rq
    ok = dx <= rq
    q, k = q.compress(ok), np.take(tr.cell_order, pos.compress(ok))
    # (nearly sorted already: the merge sort runs through it)
    order = np.argsort(q * len(tr.x_rank) + tr.x_rank[k], kind="stable")
    return q[order], k[order]


#: Side of the square cells in which :func:`_beams_near` looks for floor points, mm (any size
#: gives the same answer; ≈ the radius of a typical search disk keeps the runs short).
_CELL_MM = 50.0
#: The cells searched are widened by this much, so rounding never loses a beam, mm.
_EPS_MM = 1e-6


def match_triples(
    rig: StereoRig,
    laser: LaserModel,
    sigma_px: float,
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    settings: MatchSettings | None = None,
) -> TripleMatch:
    """The most likely set of (camera-1 dot, camera-2 dot, beam) triples (module docstring)."""
    s = settings or MatchSettings()
    d1, d2 = _as_dots(d1), _as_dots(d2)
    if len(d1) == 0 or len(d2) == 0 or len(laser) == 0:
        return _empty_triples()
    tr = _tracks(rig, laser)
    H = rig.floor_depth_mm
    sig = float(sigma_px)
    # 1. stereo pairs whose rays can meet (the rows' test needs no laser model); the dots'
    # ideal offsets serve both the slopes and the triples below
    ideal1, ideal2 = rig.cam1.ideal_offsets(d1[:, :2]), rig.cam2.ideal_offsets(d2[:, :2])
    i, j = _stereo_pairs(
        rig,
        rig.cam1.slopes_of_offsets(ideal1),
        rig.cam2.slopes_of_offsets(ideal2),
        s.gate_sigma * math.sqrt(2.0) * sig + s.row_slack_px,
        s.near_depth_mm,
        H + s.dropoff_depth_mm,
    )
    if len(i) == 0:
        return _empty_triples()
    # (x1, y1, x2, y2) of each pair, coordinate first as below: numpy works ~5x slower along
    # short rows (and indexes the rows of a 2-D array ~10x slower)
    off1, off2 = ideal1.T, ideal2.T
    m = np.vstack([np.take(off1, i, axis=1), np.take(off2, j, axis=1)])  # (4, pairs)
    p_st, q_st, u_st = tr.stereo_solve @ m  # (p, q, u) of each pair
    # 2. the beams such a point could lie on: project it from the source onto the floor
    o = tr.source_mm
    z = 1.0 / u_st
    lever = (H - o[2]) / (z - o[2])
    x_fl = o[0] + (p_st * z - o[0]) * lever
    y_fl = o[1] + (q_st * z - o[1]) * lever
    f = float(np.mean(tr.f_px))
    s_abs = np.hypot(p_st, q_st)
    sz = z * z * math.sqrt(2.0) * sig / (f * rig.baseline_mm)
    sig_q = lever * np.hypot(sig * z / f, s_abs * sz)
    so = tr.source_sigma_mm
    sig_o = np.abs(lever - 1.0) * np.sqrt(0.5 * (so[0] ** 2 + so[1] ** 2) + s_abs**2 * so[2] ** 2)
    radius = s.gate_sigma * np.sqrt(sig_q**2 + sig_o**2 + np.max(tr.floor_sigma_mm) ** 2) + 1.0
    pq, k = _beams_near(tr, x_fl, y_fl, radius)
    if len(pq) == 0:
        return _empty_triples()
    # 3. each triple's least-squares depth along its beam and residual (3 degrees of freedom)
    # (in place, one scratch array: each fresh (4, triples) array costs page faults besides
    # its pass)
    r = np.take(m, pq, axis=1)
    r -= np.take(tr.alpha, k, axis=1)  # m − α
    be = np.take(tr.beta, k, axis=1)
    scratch = np.multiply(be, be)
    bb = np.sum(scratch, axis=0)
    u_lo = 1.0 / (H + s.dropoff_depth_mm)
    u_hi = 1.0 / max(s.near_depth_mm, o[2] + 1.0)
    u = clip(np.sum(np.multiply(r, be, out=scratch), axis=0) / bb, u_lo, u_hi)
    r -= np.multiply(be, u, out=scratch)  # the residual m − α − β·u
    sig_t = np.sqrt(sig * sig + (f * tr.slope_sigma(k, u)) ** 2)
    chi2 = np.sum(np.multiply(r, r, out=scratch), axis=0) / (sig_t * sig_t)
    # 4. weight: log-likelihood ratio of the triple against leaving its dots unpaired and its
    # beam unseen (module docstring); only triples worth taking enter the assignment
    n1, n2 = len(d1), len(d2)
    area1 = math.pi * rig.cam1.disk_radius_px**2
    area2 = math.pi * rig.cam2.disk_radius_px**2
    rho1 = max(s.unpaired_fraction * n1, 1.0) / area1
    rho2 = max(s.unpaired_fraction * n2, 1.0) / area2
    track_len = np.sqrt(bb) * (u_hi - u_lo)
    const = (
        math.log((1.0 - s.beam_missing_probability) / s.beam_missing_probability)
        - math.log(rho1 * rho2)
        - 2.0 * np.log(2.0 * math.pi * sig_t**2)
        - np.log(np.maximum(track_len, sig_t) / (math.sqrt(2.0 * math.pi) * sig_t))
    )
    w = const - 0.5 * chi2
    keep = (w > 0) & (chi2 < s.gate_sigma**2 * 3.0)
    pq_kept = pq.compress(keep)
    a_ids, b_ids, k_ids = np.take(i, pq_kept), np.take(j, pq_kept), k.compress(keep)
    w, u = w.compress(keep), u.compress(keep)
    chi2, sig_t = chi2.compress(keep), sig_t.compress(keep)
    if len(w) == 0:
        return _empty_triples()
    chosen, comps, largest, inexact = _max_weight_packing(
        a_ids, b_ids + n1, k_ids + n1 + n2, w, s.exact_node_limit
    )
    return TripleMatch(
        a_ids[chosen].astype(np.intp),
        b_ids[chosen].astype(np.intp),
        k_ids[chosen].astype(np.intp),
        u[chosen],
        np.sqrt(chi2[chosen] / 3.0) * sig_t[chosen],
        sig_t[chosen],
        len(w),
        comps,
        largest,
        inexact,
    )


def _components(nodes: NDArray[np.int64]) -> NDArray[np.int64]:
    """Connected-component label (T,) of triples that share a node (rows of ``nodes`` (T, 3))."""
    t = len(nodes)
    n_nodes = int(nodes.max()) + 1
    lab = np.arange(t, dtype=np.int64)
    while True:
        node_min = np.full(n_nodes, t, dtype=np.int64)
        for c in range(3):
            np.minimum.at(node_min, nodes[:, c], lab)
        new = np.minimum.reduce([node_min[nodes[:, c]] for c in range(3)])
        new = new[new]  # pointer jumping: follow labels to their roots
        if np.array_equal(new, lab):
            return lab
        lab = new


def _dominant_triples(
    nodes: NDArray[np.int64], w: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(triples in every maximum-weight packing, triples still open) of positive weights ``w``.

    A triple t conflicts with at most one chosen triple per node (the triples through one node
    exclude each other), so whatever a packing without t gains from t's neighbours is at most
    S_t = Σ over t's three nodes of the largest other weight there. If w_t > S_t, swapping t in
    for them strictly improves any packing without t: t is in every optimum, and its neighbours
    in none. Two such triples never share a node (each would outweigh the other), so all are
    taken at once; their neighbours are dropped, and the test repeats on what is left. Exact
    (nothing changes the optimum); it leaves the integer program only the truly contested
    triples.
    """
    t_all = len(w)
    if t_all == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    # Triples heaviest first (ties by index); their node entries sorted by node once (stable:
    # each node's triples stay heaviest first). Every round then only drops the entries of
    # the triples gone: what is left is still in that order, so no round sorts again.
    perm = stable_argsort(-w)
    wp, ndp = w[perm], np.take(nodes, perm, axis=0)
    flat = ndp.ravel()  # (3T,) entry e belongs to triple e // 3 (in perm's order)
    entry = stable_argsort(flat)
    e_node, e_trip = flat[entry], entry // 3
    e_w = wp[e_trip]
    alive = np.ones(t_all, dtype=bool)
    live = np.arange(t_all)  # the open triples (in perm's order), and below their entries
    s_e = np.empty(3 * t_all)  # per entry: the largest other weight at its node
    s_cols = [s_e[c::3] for c in range(3)]  # (per column: numpy is slow along short rows)
    nd_cols = [ndp[:, c] for c in range(3)]
    sure: list[NDArray[np.intp]] = []
    n_nodes = int(nodes.max()) + 1
    while True:
        first = np.concatenate([[True], e_node[1:] != e_node[:-1]])
        starts = np.flatnonzero(first)
        group = np.cumsum(first) - 1
        top1 = e_w[starts]
        sizes = np.diff(np.concatenate([starts, [len(e_node)]]))
        top2 = np.where(sizes > 1, e_w[np.minimum(starts + 1, len(e_node) - 1)], 0.0)
        s_e[entry] = np.where(first, top2[group], top1[group])
        s_t = s_cols[0][live] + s_cols[1][live] + s_cols[2][live]
        dom = np.take(wp, live) > s_t
        if not dom.any():
            break
        taken = live.compress(dom)
        sure.append(np.sort(perm[taken]))
        used = np.zeros(n_nodes, dtype=bool)
        for col in nd_cols:
            used[col[taken]] = True
        gone = used[nd_cols[0][live]] | used[nd_cols[1][live]] | used[nd_cols[2][live]]
        alive[live.compress(gone)] = False
        live = live.compress(~gone)
        if len(live) == 0:
            break
        # (the few triples left: only their entries go on, in the same order)
        keep = alive[e_trip]
        entry, e_node, e_trip = entry.compress(keep), e_node.compress(keep), e_trip.compress(keep)
        e_w = e_w.compress(keep)
    chosen = np.concatenate(sure) if sure else np.zeros(0, np.intp)
    return chosen.astype(np.intp), np.sort(perm[live])


def _max_weight_packing(
    a: NDArray[np.int64],
    b: NDArray[np.int64],
    k: NDArray[np.int64],
    w: NDArray[np.float64],
    node_limit: int,
) -> tuple[NDArray[np.intp], int, int, int]:
    """The set of triples of largest total weight using each node (a, b or k) at most once.

    The triples in every optimum are taken first (:func:`_dominant_triples`); what is left is
    split into connected components of the conflict graph; a lone triple is taken; a small
    component (≤ ``_SMALL`` triples) is solved exactly by branch and bound, the larger ones all
    together as one integer program (HiGHS through :func:`scipy.optimize.milp`, exact; its
    LP relaxation is nearly always integral here). Returns (chosen indices, components of
    what was left open (+ 1 per sure triple), largest such component, components not proven
    optimal).
    """
    nodes_all = np.column_stack([a, b, k]).astype(np.int64)
    sure, rest = _dominant_triples(nodes_all, w)
    chosen = [sure]
    if len(rest) == 0:
        return sure, len(sure), 1, 0
    nodes, w = np.take(nodes_all, rest, axis=0), w[rest]
    lab = _components(nodes)
    order = stable_argsort(lab)
    lab_s = lab[order]
    starts = np.flatnonzero(np.concatenate([[True], lab_s[1:] != lab_s[:-1]]))
    sizes = np.diff(np.concatenate([starts, [len(lab_s)]]))
    chosen.append(rest[order[starts[sizes == 1]]])
    inexact = 0
    big = []
    for st, sz in zip(starts[sizes > 1], sizes[sizes > 1], strict=True):
        idx = order[st : st + sz]
        if sz > _SMALL:
            big.append(idx)
            continue
        sel, exact = _solve_component(nodes[idx], w[idx], node_limit)
        chosen.append(rest[idx[sel]])
        inexact += 0 if exact else 1
    if big:
        idx = np.concatenate(big)
        sel, exact = _solve_milp(nodes[idx], w[idx])
        chosen.append(rest[idx[sel]])
        inexact += 0 if exact else len(big)
    out = np.concatenate(chosen).astype(np.intp)
    return out, len(sizes) + len(sure), int(sizes.max()), inexact


#: Components up to this many triples are searched exhaustively (branch and bound in Python,
#: microseconds); larger ones go to the integer program.
_SMALL = 10


def _solve_milp(
    nodes: NDArray[np.int64], w: NDArray[np.float64], time_limit_s: float = 1.0
) -> tuple[NDArray[np.intp], bool]:
    """Maximum-weight packing as a 0/1 integer program: max Σ w·x, each node in ≤ 1 chosen;
    not exact (False) when the solver ran out of ``time_limit_s`` (wall time)."""
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import csr_array

    t = len(w)
    uniq, inv = np.unique(nodes.ravel(), return_inverse=True)
    rows = inv.reshape(-1, 3)
    A = csr_array(
        (np.ones(3 * t), (rows.ravel(), np.repeat(np.arange(t), 3))), shape=(len(uniq), t)
    )
    res = milp(
        -w,
        constraints=LinearConstraint(A, -np.inf, 1.0),
        integrality=np.ones(t),
        bounds=Bounds(0.0, 1.0),
        options={"time_limit": time_limit_s},
    )
    if res.x is None:  # no solution in time: the greedy packing
        return _greedy(nodes, w), False
    return np.flatnonzero(res.x > 0.5).astype(np.intp), bool(res.status == 0)


def _greedy(nodes: NDArray[np.int64], w: NDArray[np.float64]) -> NDArray[np.intp]:
    used: set[int] = set()
    out = []
    for t in np.argsort(-w, kind="stable"):
        nd = {int(v) for v in nodes[t]}
        if not used & nd:
            used |= nd
            out.append(int(t))
    return np.array(out, dtype=np.intp)


def _solve_component(
    nodes: NDArray[np.int64], w: NDArray[np.float64], node_limit: int
) -> tuple[NDArray[np.intp], bool]:
    """Exact maximum-weight packing of one small component (branch and bound)."""
    order = np.argsort(-w, kind="stable")
    nd = [tuple(int(v) for v in nodes[t]) for t in order]
    ww = [float(w[t]) for t in order]
    n = len(ww)
    # greedy start
    used: set[int] = set()
    greedy = []
    for t in range(n):
        if not (used & set(nd[t])):
            used.update(nd[t])
            greedy.append(t)
    best_val = sum(ww[t] for t in greedy)
    best = list(greedy)
    suffix = [0.0] * (n + 1)
    for t in range(n - 1, -1, -1):
        suffix[t] = suffix[t + 1] + ww[t]
    count = 0
    exact = True
    stack: list[tuple[int, frozenset[int], float, tuple[int, ...]]] = [(0, frozenset(), 0.0, ())]
    while stack:
        t, taken, val, path = stack.pop()
        count += 1
        if count > node_limit:
            exact = False
            break
        # skip triples that conflict with what is taken
        while t < n and (taken & set(nd[t])):
            t += 1
        if t == n:
            if val > best_val + 1e-12:
                best_val, best = val, list(path)
            continue
        if val + suffix[t] <= best_val + 1e-12:
            continue
        stack.append((t + 1, taken, val, path))  # without triple t
        stack.append((t + 1, taken | set(nd[t]), val + ww[t], (*path, t)))  # with it
    return order[np.array(best, dtype=np.intp)].astype(np.intp), exact


def _match_best(
    calib: Calibration, d1: NDArray[np.float64], d2: NDArray[np.float64], s: MatchSettings
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    m = match_best_triples(calib, d1, d2, s)
    return m.i1, m.i2


def match_best_triples(
    calib: Calibration, dots1: NDArray, dots2: NDArray, settings: MatchSettings | None = None
) -> TripleMatch:
    """:func:`match_triples` with the calibration's rig, laser model and pixel noise."""
    if calib.laser is None:
        raise ValueError("the calibration has no laser model: recalibrate with `omnid calibrate`")
    return match_triples(
        calib.rig, calib.laser, calib.pixel_sigma_px, _as_dots(dots1), _as_dots(dots2), settings
    )


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
