"""Sub-pixel laser dot centres: every dot fitted at once as a sum of pixel-integrated Gaussians.

The model of a background-free image around the dots is

    I(x) = Σ_i A_i · T(x − c_i; σ_i)  +  b0_i + b_i · (x − c_i)   near dot i

with T the unit-light Gaussian of standard deviation σ_i (px) integrated over each pixel's
square (exact for the pixels of a Gaussian spot, not a point sample of it), A_i the dot's
light (gray levels · px²), c_i its centre and a plane b0 + b·(x − c) for what is left of the
local background near it (a neighbour's halo, the scene's flicker). Each dot is fitted in a
window of ±3 σ by weighted least squares (a Gaussian taper of 2 σ, so the weights fade out
before the window's edge), jointly with its neighbours: the current models of the neighbours
whose light reaches the window are taken out of its data (block-Jacobi Gauss–Newton over the
dots), so a close neighbour does not pull a centre toward it.

Why this estimator (docs/benchmarks/detection.md). For a Gaussian spot in sensor noise it is
the least-squares (maximum-likelihood) fit, at the Cramér–Rao bound within a few per cent.
For any other spot that is point-symmetric about its centre — a flat top, a clipped top, a
spot stretched by the mirror, a ring-shaped halo — the fit's fixed point is still the centre:
there the residual is even about c, the derivative of the model with respect to c is odd and
the taper is centred on c, so the normal equation of the shift is zero. The size σ_i is
fitted too, so window and taper follow the measured spot.

Cost: the template and the taper are separable, so every window sum is one small batched
matrix product or a product of 1-D sums, and a neighbour's share of those sums is a product
of two 1-D overlaps. Which neighbours matter is decided in closed form (:func:`_coupling_px`):
for spots small against their spacing none do, and the fit costs three passes of a few
vectorised operations per dot.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

#: Window half-size per spot sigma: the fit sees ±3 σ of each dot.
WINDOW_PER_SIGMA = 3.0
#: Gaussian taper of the fit's weights, in spot sigmas.
TAPER_PER_SIGMA = 2.0
#: Smallest and largest window half-size, px.
MIN_HALF_PX, MAX_HALF_PX = 2, 10
#: Gauss–Newton passes over all dots.
ITERATIONS = 3
#: Largest centre step per pass, px (a fit that wants more is not near a dot).
MAX_STEP_PX = 0.75
#: A neighbour is taken out of a dot's window when it would move that dot's centre by more
#: than this (closed-form estimate, :func:`_coupling_px`), px.
COUPLING_PX = 0.01

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)


def erf(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Error function, |error| ≤ 1.5e-7 (Abramowitz & Stegun 7.1.26); numpy has none."""
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (
        0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429)))
    )
    return s * (1.0 - poly * np.exp(-a * a))


def pixel_gaussian(
    u: NDArray[np.float64], sigma: NDArray[np.float64], derivatives: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The unit-area 1-D Gaussian of ``sigma`` integrated over pixels centred ``u`` px from its
    centre, G(u) = Φ((u + ½)/σ) − Φ((u − ½)/σ), with dG/du and dG/dσ (zeros unless
    ``derivatives``); arrays of the broadcast shape of u and sigma."""
    hi = (u + 0.5) / sigma
    lo = (u - 0.5) / sigma
    g = 0.5 * (erf(hi / _SQRT2) - erf(lo / _SQRT2))
    if not derivatives:
        z = np.zeros_like(g)
        return g, z, z
    p_hi = np.exp(-0.5 * hi * hi) * _INV_SQRT_2PI
    p_lo = np.exp(-0.5 * lo * lo) * _INV_SQRT_2PI
    return g, (p_hi - p_lo) / sigma, -(p_hi * hi - p_lo * lo) / sigma


def window_half_px(sigma_px: float) -> int:
    """The fit's window half-size for spots of ``sigma_px``."""
    return int(min(max(math.ceil(WINDOW_PER_SIGMA * sigma_px), MIN_HALF_PX), MAX_HALF_PX))


def _coupling_px(
    dist_px: NDArray[np.float64], sigma_px: float, ratio: NDArray[np.float64]
) -> NDArray[np.float64]:
    """How far (px) a neighbour ``dist_px`` away, ``ratio`` times as bright, would move a dot's
    fitted centre if left in its window: the 1-D continuous form of the fit's shift equation
    for Gaussians of ``sigma_px`` under the taper (an upper bound of the 2-D effect)."""
    s2 = sigma_px * sigma_px
    t2 = (TAPER_PER_SIGMA * sigma_px) ** 2
    w2 = 1.0 / (1.0 / t2 + 1.0 / s2)  # taper × template
    u2 = 1.0 / (1.0 / t2 + 2.0 / s2)  # taper × template²
    mu = dist_px * w2 / (w2 + s2)
    v = math.sqrt(w2 * s2 / (w2 + s2))
    return ratio * s2 * mu * v * np.exp(-(dist_px**2) / (2.0 * (w2 + s2))) / u2**1.5


def near_pairs(
    rows: NDArray, cols: NDArray, reach: int, sort: bool = True
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """All pairs (i, j), i ≠ j, of points at most ``reach`` px apart per axis (sorted by i if
    ``sort``): the points are binned in cells of ``reach`` px and each cell is paired with
    itself and the four cells after it (a sort and a few searches, not all n² distances)."""
    n = len(rows)
    empty = np.zeros(0, np.intp), np.zeros(0, np.intp)
    if n < 2:
        return empty
    cell = max(int(reach), 1)
    cr = np.floor(rows / cell).astype(np.int64)
    cc = np.floor(cols / cell).astype(np.int64)
    cc -= cc.min() - 1
    width = int(cc.max()) + 2
    key = cr * width + cc
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    parts_i, parts_j = [], []
    for dr, dc in ((0, 0), (0, 1), (1, -1), (1, 0), (1, 1)):
        want = key + dr * width + dc
        lo = np.searchsorted(sorted_key, want, "left")
        count = np.searchsorted(sorted_key, want, "right") - lo
        total = int(count.sum())
        if total == 0:
            continue
        parts_i.append(np.repeat(np.arange(n), count))
        parts_j.append(order[np.repeat(lo - (np.cumsum(count) - count), count) + np.arange(total)])
    if not parts_i:
        return empty
    i, j = np.concatenate(parts_i), np.concatenate(parts_j)
    keep = (i < j) | ((key[i] != key[j]) & (i != j))  # each unordered pair once, no self
    keep &= (np.abs(rows[i] - rows[j]) <= reach) & (np.abs(cols[i] - cols[j]) <= reach)
    i, j = i[keep], j[keep]
    i, j = np.concatenate([i, j]), np.concatenate([j, i])
    if sort:
        by_i = np.argsort(i, kind="stable")
        i, j = i[by_i], j[by_i]
    return i.astype(np.intp), j.astype(np.intp)


def _neighbour_pairs(
    rows: NDArray,
    cols: NDArray,
    reach: int,
    sigma_px: float,
    peak: NDArray[np.float64],
    sort: bool = True,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pairs (i, j), sorted by i if ``sort``, of dots (at ``rows``, ``cols``, px) at most
    ``reach`` px apart per axis where j's light would move i's centre by more than
    :data:`COUPLING_PX`."""
    i, j = near_pairs(rows, cols, reach, sort)
    if len(i) == 0:
        return i, j
    dist = np.hypot(rows[i] - rows[j], cols[i] - cols[j]).astype(np.float64)
    ratio = np.abs(peak[j]) / np.maximum(np.abs(peak[i]), 1e-9)
    strong = _coupling_px(dist, sigma_px, ratio) > COUPLING_PX
    return i[strong], j[strong]


#: The 7 basis functions of a dot's fit as sums of (row, column) index pairs into the per-axis
#: vectors {0: G, 1: 1, 2: ∂G/∂σ, 3: ∂G/∂u, 4: u}: light, constant, size, row shift, row
#: slope, column shift, column slope.
_BASIS: tuple[tuple[tuple[int, int], ...], ...] = (
    ((0, 0),),
    ((1, 1),),
    ((2, 0), (0, 2)),
    ((3, 0),),
    ((4, 1),),
    ((0, 3),),
    ((1, 4),),
)


_Q_INDEX = np.array([5 * a + b for terms in _BASIS for a, b in terms], np.intp)
_Q_ADD = np.zeros((len(_Q_INDEX), 7))
_Q_ADD[np.arange(len(_Q_INDEX)), [k for k, terms in enumerate(_BASIS) for _ in terms]] = 1.0


def fit_spots(
    image: NDArray[np.float32],
    saturated: NDArray[np.bool_] | None,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    sigma_px: float,
    peak: NDArray,
    start: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    iterations: int = ITERATIONS,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Fit every dot of a background-free ``image`` at once (see the module doc).

    ``rows``, ``cols``: each dot's peak pixel; ``start``: optional sub-pixel starting centres;
    ``sigma_px``: the starting spot sigma (it also sets the window); ``peak``: starting peak
    values, gray levels; ``saturated``: pixels whose value is only a lower bound (or None):
    each is replaced by the larger of its value and the current model (the censored-data
    update), so a clipped top carries the information it has and no more. Returns, per dot,
    the centre (row, col) px, the fitted peak (gray levels of the continuous profile,
    A / 2πσ²) and sigma (px).
    """
    n = len(rows)
    h = window_half_px(sigma_px)
    size = 2 * h + 1
    off = np.arange(-h, h + 1, dtype=np.float64)
    win_r = rows[:, None] + off[None, :]  # the window's pixel rows (n, size)
    win_c = cols[:, None] + off[None, :]
    rr = np.clip(win_r.astype(np.intp), 0, image.shape[0] - 1)[:, :, None]
    cc_ = np.clip(win_c.astype(np.intp), 0, image.shape[1] - 1)[:, None, :]
    inside = ((win_r >= 0) & (win_r < image.shape[0]))[:, :, None]
    inside = inside & ((win_c >= 0) & (win_c < image.shape[1]))[:, None, :]
    win = np.where(inside, image[rr, cc_], 0.0).astype(np.float64)  # outside the image: nothing
    sat_idx = np.zeros(0, np.intp)
    sat_win = np.zeros((0, size, size), bool)
    if saturated is not None:
        sat_all = saturated[rr, cc_] & inside
        sat_idx = np.flatnonzero(sat_all.any(axis=(1, 2)))
        sat_win = sat_all[sat_idx]
    if start is None:
        cr, cc = rows.astype(np.float64), cols.astype(np.float64)
    else:
        cr, cc = (np.asarray(a, dtype=np.float64).copy() for a in start)
    s_min, s_max = 0.5 * sigma_px, h / 2.0
    s = np.full(n, float(sigma_px))
    peak0 = np.asarray(peak, dtype=np.float64)
    mass = peak0 * 2.0 * math.pi * s * s
    b0, br, bc = np.zeros(n), np.zeros(n), np.zeros(n)
    pair_i, pair_j = _neighbour_pairs(cr, cc, 2 * h, sigma_px, peak0)
    for _ in range(iterations):
        ur = win_r - cr[:, None]
        uc = win_c - cc[:, None]
        gr, dr, sr = pixel_gaussian(ur, s[:, None])
        gc, dc, sc = pixel_gaussian(uc, s[:, None])
        taper = -0.5 / (TAPER_PER_SIGMA * s[:, None]) ** 2
        wr, wc = np.exp(ur * ur * taper), np.exp(uc * uc * taper)
        data = win
        if len(sat_idx):
            k = sat_idx
            own = mass[k, None, None] * gr[k, :, None] * gc[k, None, :]
            own += b0[k, None, None] + br[k, None, None] * ur[k, :, None]
            own += bc[k, None, None] * uc[k, None, :]
            data = win.copy()
            data[k] = np.where(sat_win, np.maximum(win[k], own), win[k])
        # Per-axis vectors f ∈ {G, 1, ∂G/∂σ, ∂G/∂u, u}; every basis is a sum of row ⊗ column
        # products of them, so every weighted window sum is a product of 1-D sums or of
        # weighted row vectors · data · weighted column vectors.
        one = np.ones_like(ur)
        fr = np.stack([gr, one, sr, dr, ur], axis=1)  # (n, 5, size)
        fc = np.stack([gc, one, sc, dc, uc], axis=1)
        frw = fr * wr[:, None, :]
        fcw = np.swapaxes(fc * wc[:, None, :], 1, 2)  # (n, size, 5)
        q = frw @ data @ fcw  # (n, 5, 5)
        if len(pair_i):
            q -= _neighbour_sums(pair_i, pair_j, frw, fcw, win_r, win_c, cr, cc, s, mass, n)
        pr = frw @ np.swapaxes(fr, 1, 2)  # (n, 5, 5) weighted 1-D sums of products, rows
        pc = np.swapaxes(fcw, 1, 2) @ np.swapaxes(fc, 1, 2)  # columns
        # The current model A·G⊗G + b0·1⊗1 + b_r·u⊗1 + b_c·1⊗u summed like the data: the
        # residual's sums, i.e. the exact gradient.
        q -= mass[:, None, None] * pr[:, :, 0, None] * pc[:, None, :, 0]
        q -= b0[:, None, None] * pr[:, :, 1, None] * pc[:, None, :, 1]
        q -= br[:, None, None] * pr[:, :, 4, None] * pc[:, None, :, 1]
        q -= bc[:, None, None] * pr[:, :, 1, None] * pc[:, None, :, 4]
        grad = q.reshape(n, 25)[:, _Q_INDEX] @ _Q_ADD  # (n, 7)
        d_mass, d_b0, d_s, d_r, d_br, d_c, d_bc = _gauss_newton_step(grad, pr, pc)
        new_mass = mass + d_mass
        safe = np.where(np.abs(new_mass) > 1e-9, new_mass, 1e-9)
        step_r = np.clip(-d_r / safe, -MAX_STEP_PX, MAX_STEP_PX)
        step_c = np.clip(-d_c / safe, -MAX_STEP_PX, MAX_STEP_PX)
        s = np.clip(s * np.clip(1.0 + d_s / (safe * s), 0.75, 1.33), s_min, s_max)
        mass = new_mass
        br, bc = br + d_br, bc + d_bc
        # The plane b0 + b·(x − c) re-expressed about the moved centre.
        b0 = b0 + d_b0 + br * step_r + bc * step_c
        cr, cc = cr + step_r, cc + step_c
    return cr, cc, mass / (2.0 * math.pi * s * s), s


def _gauss_newton_step(
    grad: NDArray[np.float64], pr: NDArray[np.float64], pc: NDArray[np.float64]
) -> tuple[NDArray[np.float64], ...]:
    """One Gauss–Newton step of every dot's 7 parameters (light, constant, size, row shift,
    row slope, column shift, column slope; the size and shifts scaled by the light) from the
    exact gradient ``grad`` (n, 7) and the per-axis weighted sums ``pr``, ``pc`` (n, 5, 5).

    The step solves the three blocks of the normal matrix that do not couple when the window
    is centred — even (light, constant, size) and, per axis, odd (shift, slope) — in closed
    form; the gradient being exact, the fixed point is the exact weighted least-squares fit.
    """
    # Even block: sums of (G⊗G, 1⊗1, ∂σ) products; ∂σ = ∂G/∂σ⊗G + G⊗∂G/∂σ.
    a = pr[:, 0, 0] * pc[:, 0, 0]
    b = pr[:, 0, 1] * pc[:, 0, 1]
    c = pr[:, 0, 2] * pc[:, 0, 0] + pr[:, 0, 0] * pc[:, 0, 2]
    d = pr[:, 1, 1] * pc[:, 1, 1]
    e = pr[:, 1, 2] * pc[:, 1, 0] + pr[:, 1, 0] * pc[:, 1, 2]
    f = pr[:, 2, 2] * pc[:, 0, 0] + 2.0 * pr[:, 0, 2] * pc[:, 0, 2] + pr[:, 0, 0] * pc[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    det = np.where(np.abs(det) > 1e-30, det, 1e-30)
    g0, g1, g2 = grad[:, 0], grad[:, 1], grad[:, 2]
    out = [
        (c00 * g0 + c01 * g1 + c02 * g2) / det,
        (c01 * g0 + c11 * g1 + c12 * g2) / det,
        (c02 * g0 + c12 * g1 + c22 * g2) / det,
    ]
    # Odd blocks: (∂G/∂u⊗G, u⊗1) for rows, (G⊗∂G/∂u, 1⊗u) for columns.
    for m11, m12, m22, gi, gj in (
        (pr[:, 3, 3] * pc[:, 0, 0], pr[:, 3, 4] * pc[:, 0, 1], pr[:, 4, 4] * pc[:, 1, 1], 3, 4),
        (pr[:, 0, 0] * pc[:, 3, 3], pr[:, 0, 1] * pc[:, 3, 4], pr[:, 1, 1] * pc[:, 4, 4], 5, 6),
    ):
        det2 = m11 * m22 - m12 * m12
        det2 = np.where(np.abs(det2) > 1e-30, det2, 1e-30)
        out.append((m22 * grad[:, gi] - m12 * grad[:, gj]) / det2)
        out.append((m11 * grad[:, gj] - m12 * grad[:, gi]) / det2)
    return tuple(out)


def _neighbour_sums(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    frw: NDArray[np.float64],
    fcw: NDArray[np.float64],
    win_r: NDArray[np.float64],
    win_c: NDArray[np.float64],
    cr: NDArray[np.float64],
    cc: NDArray[np.float64],
    s: NDArray[np.float64],
    mass: NDArray[np.float64],
    n: int,
) -> NDArray[np.float64]:
    """(n, 5, 5): what the current models of the neighbours j add to the window sums of the
    dots i (pairs sorted by i). A model is separable, so each pair's share is an outer product
    of two 1-D overlaps."""
    gjr = pixel_gaussian(win_r[i] - cr[j, None], s[j, None], derivatives=False)[0]
    gjc = pixel_gaussian(win_c[i] - cc[j, None], s[j, None], derivatives=False)[0]
    vr = (frw[i] @ gjr[:, :, None])[:, :, 0]  # (pairs, 5)
    vc = (gjc[:, None, :] @ fcw[i])[:, 0, :]
    contrib = (mass[j, None, None] * vr[:, :, None] * vc[:, None, :]).reshape(len(i), 25)
    out = np.zeros((n, 25))
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    out[i[starts]] = np.add.reduceat(contrib, starts, axis=0)
    return out.reshape(n, 5, 5)
