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
of two 1-D overlaps. A neighbour is taken out of a dot's window when its light reaches it
(within twice the window's half-size per axis); for spots small against their spacing none
is, and the fit costs three passes of a few vectorised operations per dot.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from omnid.core.arrays import clip, stable_argsort

#: Window half-size per spot sigma: the fit sees ±3 σ of each dot.
WINDOW_PER_SIGMA = 3.0
#: Gaussian taper of the fit's weights, in spot sigmas.
TAPER_PER_SIGMA = 2.0
#: Smallest and largest window half-size, px.
MIN_HALF_PX, MAX_HALF_PX = 2, 10
#: Gauss–Newton passes over all dots, updated in turn (see :func:`fit_spots`) ...
ITERATIONS = 4
#: ... and for small spots, updated all at once (their neighbours overlap them little).
JACOBI_ITERATIONS = 2
#: Spots larger than this (sigma, px) overlap their neighbours so much that the dots are
#: updated in turn (Gauss–Seidel), not all at once (Jacobi: it oscillates there).
SEQUENTIAL_FROM_PX = 1.5
#: Largest centre step per pass, px (a fit that wants more is not near a dot).
MAX_STEP_PX = 0.75

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


def window_gaussian(
    u0: NDArray[np.float64], size: int, sigma: NDArray[np.float64], derivatives: bool = True
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`pixel_gaussian` on rows of ``size`` consecutive pixels, the first ``u0`` (n, 1)
    px from the centre, for ``sigma`` (n, 1): the pixels share their edges, so each edge's
    erf and density are evaluated once. Arrays (n, size)."""
    z = (u0 - 0.5 + np.arange(size + 1, dtype=np.float64)) / sigma  # the edges, in sigmas
    cdf = erf(z / _SQRT2)
    g = 0.5 * (cdf[:, 1:] - cdf[:, :-1])
    if not derivatives:
        zero = np.zeros_like(g)
        return g, zero, zero
    pdf = np.exp(-0.5 * z * z) * _INV_SQRT_2PI
    zp = z * pdf
    return g, (pdf[:, 1:] - pdf[:, :-1]) / sigma, -(zp[:, 1:] - zp[:, :-1]) / sigma


def window_half_px(sigma_px: float) -> int:
    """The fit's window half-size for spots of ``sigma_px``."""
    return int(min(max(math.ceil(WINDOW_PER_SIGMA * sigma_px), MIN_HALF_PX), MAX_HALF_PX))


#: :func:`near_pairs` tests all pairs of up to this many points.
_ALL_PAIRS_UP_TO = 64


def near_pairs(
    rows: NDArray, cols: NDArray, reach: float, sort: bool = True
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """All pairs (i, j), i ≠ j, of points at most ``reach`` px apart per axis (the maximum
    norm), both ways round, sorted by i; with ``sort`` the js of each i come in one fixed
    order (the grid's below: sums over them repeat to the last bit), without it in any.

    A grid of square cells of side ``reach``: two points that close lie in the same or in
    adjacent cells, so each point's candidates are the points of its 3x3 cells, found by
    a table of the points sorted by cell — a few vectorised passes, about 2.5x faster
    than a k-d tree's pairs for the ~10³ dots of an image. Up to :data:`_ALL_PAIRS_UP_TO`
    points: all n² pairs tested at once (the grid's passes cost more), the js of each i in
    ascending order.
    """
    empty = np.zeros(0, np.intp), np.zeros(0, np.intp)
    n = len(rows)
    if n < 2:
        return empty
    r = np.asarray(rows, dtype=np.float64)
    c = np.asarray(cols, dtype=np.float64)
    if n <= _ALL_PAIRS_UP_TO:
        close = (np.abs(r[:, None] - r) <= reach) & (np.abs(c[:, None] - c) <= reach)
        np.fill_diagonal(close, False)
        i, j = np.nonzero(close)
        return i.astype(np.intp, copy=False), j.astype(np.intp, copy=False)
    # (cells wider than ``reach`` are as good; at most ~1024 per axis keep the table small)
    r_min, c_min = r.min(), c.min()
    span = max(float(r.max() - r_min), float(c.max() - c_min))
    cell = max(float(reach), span / 1024.0, 1e-9)
    gr = np.floor((r - r_min) / cell).astype(np.int64) + 1
    gc = np.floor((c - c_min) / cell).astype(np.int64) + 1
    width = int(gc.max()) + 2
    key = gr * width + gc
    order = stable_argsort(key)
    per_cell = np.bincount(key, minlength=(int(gr.max()) + 2) * width)
    # cell_start[k]: the rank in ``order`` of cell k's first point (and one past the last cell)
    cell_start = np.zeros(len(per_cell) + 1, np.int64)
    np.cumsum(per_cell, out=cell_start[1:])
    # A point's candidates: three runs of ``order``, each the three adjacent cells of the row
    # of cells above, its own and below (i-major, each run in cell order).
    run_first = ((key - (width + 1))[:, None] + np.array([0, width, 2 * width])).ravel()
    lo = np.take(cell_start, run_first)
    count = np.take(cell_start, run_first + 3) - lo
    ends = np.cumsum(count)
    total = int(ends[-1])
    if total == 0:
        return empty
    pos = np.arange(total) - np.repeat(ends - count - lo, count)
    per_point = ends[2::3].copy()  # (the running count at each point's last run, differenced)
    per_point[1:] -= ends[2::3][:-1]
    i = np.repeat(np.arange(n, dtype=np.intp), per_point)
    j = np.take(order, pos)
    keep = np.abs(np.take(r, i) - np.take(r, j)) <= reach
    keep &= np.abs(np.take(c, i) - np.take(c, j)) <= reach
    keep &= i != j
    return i.compress(keep), j.compress(keep)


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
    iterations: int | None = None,
    free: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Fit every dot of a background-free ``image`` at once (see the module doc).

    ``rows``, ``cols``: each dot's peak pixel; ``start``: optional sub-pixel starting centres;
    ``sigma_px``: the starting spot sigma (it also sets the window); ``peak``: starting peak
    values, gray levels; ``free``: which dots are fitted (default all): the others are held
    at their start (round spots of ``sigma_px``), their light only taken out of the fitted
    dots' windows; ``saturated``: pixels whose value is only a lower bound (or None):
    each is replaced by the larger of its value and the current model there — the dot's,
    its plane's and its neighbours' light: the censored-data update —, so a clipped top carries
    the information it has and no more. Returns, per dot,
    the centre (row, col) px, the fitted peak (gray levels of the continuous profile,
    A / 2πσ²) and sigma (px).

    Each dot is updated against its neighbours' current models: all at once (Jacobi), or for
    spots larger than :data:`SEQUENTIAL_FROM_PX` in turn (Gauss–Seidel over four groups: the
    dots of a checkerboard of cells of the neighbour reach, so that no two dots of one group
    see each other), as where spots overlap strongly updating all at once oscillates.
    """
    n = len(rows)
    h = window_half_px(sigma_px)
    off = np.arange(-h, h + 1, dtype=np.float64)
    win_r = rows[:, None] + off[None, :]  # the window's pixel rows (n, size)
    win_c = cols[:, None] + off[None, :]
    # (the held dots' windows are never read: only the fitted dots' pixels are gathered)
    own = slice(None) if free is None else np.flatnonzero(free)
    o_rows, o_cols = rows[own], cols[own]
    if len(o_rows) and (
        min(o_rows.min(), o_cols.min()) >= h
        and o_rows.max() < image.shape[0] - h
        and o_cols.max() < image.shape[1] - h
    ):
        # (every window inside the image, as nearly always)
        rr = win_r[own].astype(np.intp)[:, :, None]
        cc_ = win_c[own].astype(np.intp)[:, None, :]
        win = image[rr, cc_].astype(np.float64)
        sat_all = None if saturated is None else saturated[rr, cc_]
    else:
        rr = clip(win_r[own].astype(np.intp), 0, image.shape[0] - 1)[:, :, None]
        cc_ = clip(win_c[own].astype(np.intp), 0, image.shape[1] - 1)[:, None, :]
        inside = ((win_r[own] >= 0) & (win_r[own] < image.shape[0]))[:, :, None]
        inside = inside & ((win_c[own] >= 0) & (win_c[own] < image.shape[1]))[:, None, :]
        win = np.where(inside, image[rr, cc_], 0.0).astype(np.float64)  # outside: nothing
        sat_all = None if saturated is None else saturated[rr, cc_] & inside
    if sat_all is not None and not sat_all.any():
        sat_all = None
    if free is not None:
        size = len(off)
        win_all = np.zeros((n, size, size))
        win_all[own] = win
        win = win_all
        if sat_all is not None:
            sat_full = np.zeros((n, size, size), dtype=bool)
            sat_full[own] = sat_all
            sat_all = sat_full
    if start is None:
        cr, cc = rows.astype(np.float64), cols.astype(np.float64)
    else:
        cr, cc = (np.asarray(a, dtype=np.float64).copy() for a in start)
    st = _FitState(
        win,
        sat_all,
        win_r,
        win_c,
        cr,
        cc,
        np.full(n, float(sigma_px)),
        np.asarray(peak, dtype=np.float64) * 2.0 * math.pi * sigma_px * sigma_px,
        (0.5 * sigma_px, h / 2.0),
    )
    # Every neighbour whose light (to ~3 σ) reaches a dot's window is taken out of it.
    reach = 2 * h
    pair_i, pair_j = near_pairs(cr, cc, reach)
    sequential = len(pair_i) > 0 and sigma_px > SEQUENTIAL_FROM_PX
    if not sequential:
        groups = [np.arange(n) if free is None else np.flatnonzero(free)]
        if free is not None:
            held = free[pair_i]  # (only the fitted dots' windows are updated)
            pair_i, pair_j = pair_i.compress(held), pair_j.compress(held)
    else:
        colour = (np.floor(cr / reach).astype(np.int64) % 2) * 2
        colour += np.floor(cc / reach).astype(np.int64) % 2
        if free is not None:
            colour[~free] = -1
        groups = [g for g in (np.flatnonzero(colour == k) for k in range(4)) if len(g)]
    if iterations is None:
        iterations = ITERATIONS if sequential and len(groups) > 1 else JACOBI_ITERATIONS
    for _ in range(iterations):
        for g in groups:
            if not sequential:
                _update(st, g, pair_i, pair_j)
            else:
                sel = np.isin(pair_i, g)
                _update(st, g, pair_i[sel], pair_j[sel])
    return st.cr, st.cc, st.mass / (2.0 * math.pi * st.s * st.s), st.s


class _FitState:
    """The dots' windows and their current fit (see :func:`fit_spots`)."""

    def __init__(
        self,
        win: NDArray[np.float64],
        sat: NDArray[np.bool_] | None,
        win_r: NDArray[np.float64],
        win_c: NDArray[np.float64],
        cr: NDArray[np.float64],
        cc: NDArray[np.float64],
        s: NDArray[np.float64],
        mass: NDArray[np.float64],
        s_range: tuple[float, float],
    ) -> None:
        n = len(cr)
        self.win, self.sat, self.win_r, self.win_c = win, sat, win_r, win_c
        self.cr, self.cc, self.s, self.mass = cr, cc, s, mass
        self.b0, self.br, self.bc = np.zeros(n), np.zeros(n), np.zeros(n)
        self.s_range = s_range


def _update(
    st: _FitState, k: NDArray[np.intp], pair_i: NDArray[np.intp], pair_j: NDArray[np.intp]
) -> None:
    """One Gauss–Newton step of the dots ``k`` against the current models of their neighbours
    (pairs (i, j), i in ``k``, sorted by i)."""
    n = len(k)
    win_r, win_c = st.win_r[k], st.win_c[k]
    cr, cc, s, mass = st.cr[k], st.cc[k], st.s[k], st.mass[k]
    b0, br, bc = st.b0[k], st.br[k], st.bc[k]
    local = np.full(len(st.cr), -1, np.intp)
    local[k] = np.arange(n)
    i, j = local[pair_i], pair_j
    p = len(i)
    # Every 1-D profile of the step in one call, stacked: the dots' own rows and columns (2n,
    # size), then each neighbour's rows and columns over the window it falls in (2p, size).
    u = np.concatenate([win_r, win_c]) - np.concatenate([cr, cc])[:, None]
    ur, uc = u[:n], u[n:]
    size = u.shape[1]
    s2 = np.concatenate([s, s])[:, None]
    sj = st.s[j, None]
    g, dg, sg = window_gaussian(
        np.concatenate([u[:, :1], win_r[i, :1] - st.cr[j, None], win_c[i, :1] - st.cc[j, None]]),
        size,
        np.concatenate([s2, sj, sj]),
    )
    gjr, gjc = g[2 * n : 2 * n + p], g[2 * n + p :]
    g, dg, sg = g[: 2 * n], dg[: 2 * n], sg[: 2 * n]
    gr, gc = g[:n], g[n:]
    wrc = np.exp(u * u * (-0.5 / (TAPER_PER_SIGMA * s2) ** 2))
    data = st.win[k]
    if st.sat is not None:
        sat = st.sat[k]
        hit = np.flatnonzero(sat.any(axis=(1, 2)))
        if len(hit):
            # A clipped pixel says "at least its value" about the whole model there — the
            # dot's own light, its plane and its neighbours' light — not about the dot alone.
            model = mass[hit, None, None] * gr[hit, :, None] * gc[hit, None, :]
            model += b0[hit, None, None] + br[hit, None, None] * ur[hit, :, None]
            model += bc[hit, None, None] * uc[hit, None, :]
            if p:
                model += _neighbour_light(i, j, hit, gjr, gjc, st, n)
            data = data.copy()
            data[hit] = np.where(sat[hit], np.maximum(data[hit], model), data[hit])
    # Per-axis vectors f ∈ {G, 1, ∂G/∂σ, ∂G/∂u, u}, rows then columns (2n, 5, size); every
    # basis is a sum of row ⊗ column products of them, so every weighted window sum is a
    # product of 1-D sums or of weighted row vectors · data · weighted column vectors.
    f = np.empty((2 * n, 5, size))  # (filled in place: np.stack costs more than the data)
    f[:, 0], f[:, 1], f[:, 2], f[:, 3], f[:, 4] = g, 1.0, sg, dg, u
    fw = f * wrc[:, None, :]
    frw, fcw = fw[:n], np.swapaxes(fw[n:], 1, 2)  # (n, 5, size), (n, size, 5)
    q = frw @ data @ fcw  # (n, 5, 5)
    if p:
        q -= _neighbour_sums(i, j, frw, fcw, gjr, gjc, st, n)
    pp = fw @ np.swapaxes(f, 1, 2)  # (2n, 5, 5) weighted 1-D sums of products: rows, columns
    pr, pc = pp[:n], pp[n:]
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
    step_r = clip(-d_r / safe, -MAX_STEP_PX, MAX_STEP_PX)
    step_c = clip(-d_c / safe, -MAX_STEP_PX, MAX_STEP_PX)
    s_min, s_max = st.s_range
    st.s[k] = clip(s * clip(1.0 + d_s / (safe * s), 0.75, 1.33), s_min, s_max)
    st.mass[k] = new_mass
    br, bc = br + d_br, bc + d_bc
    st.br[k], st.bc[k] = br, bc
    # The plane b0 + b·(x − c) re-expressed about the moved centre.
    st.b0[k] = b0 + d_b0 + br * step_r + bc * step_c
    st.cr[k], st.cc[k] = cr + step_r, cc + step_c


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


def _run_starts(i: NDArray[np.intp]) -> NDArray[np.intp]:
    """Where each run of equal values of the sorted, non-empty ``i`` starts."""
    new = np.empty(len(i), dtype=bool)
    new[0] = True
    np.not_equal(i[1:], i[:-1], out=new[1:])
    return np.flatnonzero(new)


def _neighbour_light(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    hit: NDArray[np.intp],
    gjr: NDArray[np.float64],
    gjc: NDArray[np.float64],
    st: _FitState,
    n: int,
) -> NDArray[np.float64]:
    """(len(hit), size, size): the current models of the neighbours j (indices into ``st``)
    rendered in the windows of those of the n dots i (pairs sorted by i) that are ``hit``,
    from each pair's row and column profiles ``gjr``, ``gjc`` (pairs, size): a model is
    separable, its light in a window the outer product of the two times its mass."""
    size = gjr.shape[1]
    out = np.zeros((len(hit), size, size))
    slot = np.full(n, -1, np.intp)
    slot[hit] = np.arange(len(hit))
    keep = slot[i] >= 0
    if not keep.any():
        return out
    i, j, gjr, gjc = i[keep], j[keep], gjr[keep], gjc[keep]
    light = st.mass[j, None, None] * gjr[:, :, None] * gjc[:, None, :]
    starts = _run_starts(i)
    out[slot[i[starts]]] = np.add.reduceat(light, starts, axis=0)
    return out


def _neighbour_sums(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    frw: NDArray[np.float64],
    fcw: NDArray[np.float64],
    gjr: NDArray[np.float64],
    gjc: NDArray[np.float64],
    st: _FitState,
    n: int,
) -> NDArray[np.float64]:
    """(n, 5, 5): what the current models of the neighbours j (indices into ``st``) add to the
    window sums of the dots i (indices into ``frw``, ``fcw``; pairs sorted by i), from each
    pair's row and column profiles ``gjr``, ``gjc`` (pairs, size): a model is separable, so
    each pair's share is an outer product of two 1-D overlaps."""
    vr = (frw[i] @ gjr[:, :, None])[:, :, 0]  # (pairs, 5)
    vc = (gjc[:, None, :] @ fcw[i])[:, 0, :]
    contrib = (st.mass[j, None, None] * vr[:, :, None] * vc[:, None, :]).reshape(len(i), 25)
    out = np.zeros((n, 25))
    starts = _run_starts(i)
    out[i[starts]] = np.add.reduceat(contrib, starts, axis=0)
    return out.reshape(n, 5, 5)


# --------------------------------------------------------------------------------------------
# One spot or two: the model selection that splits blends of two close spots
# --------------------------------------------------------------------------------------------

#: The hypotheses are on grids in units of the spot's sigma s (pixel-sampled: √(σ² + 1/12)):
#: spot positions along the blob's long axis, from its maximum, every :data:`BLEND_STEP` ...
BLEND_STEP = 0.2
BLEND_REACH = 4.0
#: ... two spots this far apart (the family's ends are not answers: "interior" below) ...
BLEND_SEPARATIONS = (1.0, 4.0)
#: ... and one spot centred on the maximum, stretched along the axis by these factors (a spot
#: the mirror's rim stretches).
BLEND_STRETCHES = np.arange(1.0, 3.01, 0.1)
#: Bins of the along-axis coordinate (units of s) the window's pixels are summed into: every
#: hypothesis's normal equations are then one small matrix product of these sums.
_BLEND_BIN = 0.1
_BLEND_BINS = np.arange(-6.5, 6.5 + 1e-9, _BLEND_BIN)  # (a window's corner: ≤ 6 s)
_BLEND_T = np.arange(-BLEND_REACH, BLEND_REACH + 1e-9, BLEND_STEP)
_BLEND_T_HALF = np.arange(-BLEND_REACH, BLEND_REACH + 1e-9, BLEND_STEP / 2.0)


def _kernel(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """exp(−x), C-ordered, with what is below 1e-30 set to 0 (denormals slow the products)."""
    k = np.exp(-x)
    k[k < 1e-30] = 0.0
    return np.ascontiguousarray(k, dtype=np.float64)


# exp(−(a − t)²/2) (a spot at t) and exp(−(a − t)²) (the product of two spots, about their
# midpoint), over the bins a (rows); the stretched spot's exp(−a²/2k²) and exp(−a²/k²)
_K_SPOT = _kernel(0.5 * (_BLEND_BINS[:, None] - _BLEND_T[None, :]) ** 2)
_K_PAIR = _kernel((_BLEND_BINS[:, None] - _BLEND_T_HALF[None, :]) ** 2)
_K_ONE = _kernel(0.5 * (_BLEND_BINS[:, None] / BLEND_STRETCHES[None, :]) ** 2)
_K_ONE2 = _kernel((_BLEND_BINS[:, None] / BLEND_STRETCHES[None, :]) ** 2)
# (side by side: the sums of w·R and w·R·y take the first, those of w·R² the second)
_K_LIGHT = np.ascontiguousarray(np.hstack([_K_ONE, _K_SPOT]))
_K_SQUARE = np.ascontiguousarray(np.hstack([_K_ONE2, _K_PAIR]))
_lo, _hi = (round(x / BLEND_STEP) for x in BLEND_SEPARATIONS)
# the pairs of positions on _BLEND_T at the allowed separations, t1 > 0 > t2: two spots that
# are one blob lie on both sides of its maximum
_ii = np.arange(len(_BLEND_T))
_sep_i = np.subtract.outer(_ii, _ii)
_PAIR_I1, _PAIR_I2 = (
    a.ravel()
    for a in np.nonzero(
        (_sep_i >= _lo)
        & (_sep_i <= _hi)
        & (_BLEND_T[:, None] > 0.5 * BLEND_STEP)
        & (_BLEND_T[None, :] < -0.5 * BLEND_STEP)
    )
)
del _ii, _sep_i
_PAIR_INTERIOR = (
    (_lo < _PAIR_I1 - _PAIR_I2)
    & (_hi > _PAIR_I1 - _PAIR_I2)
    & (_PAIR_I2 > 0)
    & (len(_BLEND_T) - 1 > _PAIR_I1)
)
_PAIR_SEP = (_PAIR_I1 - _PAIR_I2) * BLEND_STEP
_PAIR_OVERLAP = np.exp(-0.25 * _PAIR_SEP**2)
_PAIR_SUM = _PAIR_I1 + _PAIR_I2
_PAIR_T = np.column_stack([_BLEND_T[_PAIR_I1], _BLEND_T[_PAIR_I2]])
del _lo, _hi


@dataclass(frozen=True)
class BlendTest:
    """What :func:`blend_test` finds for n blobs: ``evidence`` (n,) for two spots (twice the
    log-likelihood ratio of the best two-spot over the best one-spot hypothesis, less the
    information criterion's price of two more parameters), ``centres`` (n, 2, 2) the two
    spots' (row, col) px, ``peaks`` (n, 2) their peaks (gray), ``separation`` (n,) their
    distance in spot sigmas, and ``interior`` (n,) whether that optimum lies inside the
    hypotheses (not at their edge: a distance the family does not hold)."""

    evidence: NDArray[np.float64]
    centres: NDArray[np.float64]
    peaks: NDArray[np.float64]
    separation: NDArray[np.float64]
    interior: NDArray[np.bool_]


def blend_test(
    image: NDArray[np.float32],
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    axis: NDArray[np.float64],
    sigma_px: float,
    noise_gray: float,
    valid: NDArray[np.bool_] | None = None,
    neighbours: tuple[NDArray[np.intp], NDArray, NDArray, NDArray] | None = None,
) -> BlendTest:
    """Is each blob (its maximum at sub-pixel ``r``, ``c`` of a background-free ``image``, its
    light elongated along the unit vector ``axis`` (n, 2)) one spot or two?

    Two families of the image's spot (round, Gaussian of ``sigma_px``; s² = σ² + 1/12 pixel
    sampled), each fitted by weighted least squares on the ±3 σ window, pixels ``valid``
    False (clipped) left out; amplitudes and a constant are linear, solved exactly for every
    hypothesis:

    - one spot centred on the maximum, stretched along ``axis`` by k (:data:`BLEND_STRETCHES`):
      a spot the mirror's rim stretches (1 nonlinear parameter);
    - two round spots on the line through the maximum along ``axis``, on both sides of it
      (two spots that are one blob), at positions t₁ > 0 > t₂ (:data:`BLEND_STEP` apart on
      ±:data:`BLEND_REACH` s, separations :data:`BLEND_SEPARATIONS`): two beams of a doubled
      beam, or a dot and its ghost (2).

    The other dots near each blob (``neighbours``: the blob's index, and the dot's row, col
    and peak), round spots of the image's size, are taken out of its window first: a
    neighbour's light is no second spot.

    Both models are a round Gaussian across the axis times a profile along it, so every sum
    of their normal equations is a sum over the window's pixels of a function of their
    along-axis coordinate: the pixels are binned along it once (:data:`_BLEND_BIN` s) and each
    hypothesis's sums are a product with fixed kernels — the two spots' cross term is a spot
    of half the variance at their midpoint. The evidence is (SSR₁ − SSR₂)/s_n² − 2 ln m: twice
    the log-likelihood ratio at the noise s_n (the sensor's ``noise_gray``, or the window's
    residual where that is larger: shot noise, speckle, halos), less the Bayesian information
    criterion's price of the two more parameters over the window's m pixels. The two spots'
    positions are the best hypothesis's, on the grid (:data:`BLEND_STEP` s; the joint fit
    that follows a split refines them).
    """
    n = len(r)
    half = window_half_px(sigma_px)
    size = 2 * half + 1
    off_r, off_c = _window_offsets(half)
    ir, ic = np.rint(r).astype(np.intp), np.rint(c).astype(np.intp)
    pr = clip(ir[:, None] + off_r, 0, image.shape[0] - 1)
    pc = clip(ic[:, None] + off_c, 0, image.shape[1] - 1)
    y = image[pr, pc].astype(np.float64)
    wt = np.ones_like(y) if valid is None else valid[pr, pc].astype(np.float64)
    m = y.shape[1]
    scale = math.sqrt(sigma_px * sigma_px + 1.0 / 12.0)
    if neighbours is not None and len(neighbours[0]):
        y -= _neighbours_in_windows(pr, pc, size, scale, neighbours)
    er, ec = axis[:, 0:1], axis[:, 1:2]
    dr, dc = pr - r[:, None], pc - c[:, None]
    along = (dr * er + dc * ec) / scale
    across = (dc * er - dr * ec) / scale
    rnd = np.exp(-0.5 * across * across)
    # the window binned along the axis: sums of w·R², w·R and w·R·y per bin
    nb = len(_BLEND_BINS)
    k = clip(np.rint((along - _BLEND_BINS[0]) / _BLEND_BIN).astype(np.intp), 0, nb - 1)
    flat = (k + nb * np.arange(n)[:, None]).ravel()
    wr = wt * rnd

    # one count of the three weights: w·R², w·R and w·R·y per bin (n, nb) each
    w_r = wr.ravel()
    hist = np.asarray(
        np.bincount(
            np.concatenate([flat, flat + n * nb, flat + 2 * n * nb]),
            weights=np.concatenate([w_r * rnd.ravel(), w_r, w_r * y.ravel()]),
            minlength=3 * n * nb,
        ),
        dtype=np.float64,
    ).reshape(3, n, nb)
    s0 = wt.sum(axis=1)
    sy = (wt * y).sum(axis=1)
    syy = (wt * y * y).sum(axis=1)
    base = syy - sy * sy / np.maximum(s0, 1e-12)  # the constant alone
    ks = len(BLEND_STRETCHES)
    light = hist[1:].reshape(2 * n, nb) @ _K_LIGHT  # Σ w g and Σ w g y, both families
    square = hist[0] @ _K_SQUARE  # Σ w g², and Σ w R² exp(−(a − t)²) on the half-step grid
    # one stretched spot: a' = Σ w g² − (Σ w g)²/S0, b' = Σ w g y − Σ w g · Sy / S0
    g1 = light[:n, :ks]
    a1 = square[:, :ks] - g1 * g1 / s0[:, None]
    b1 = light[n:, :ks] - g1 * (sy / s0)[:, None]
    ssr1_all = base[:, None] - np.where(
        (b1 > 0) & (a1 > 1e-12), b1 * b1 / np.maximum(a1, 1e-12), 0.0
    )
    ssr1 = ssr1_all.min(axis=1)
    # two round spots at t1 > 0 > t2 on the line
    gs, gy, gg = light[:n, ks:], light[n:, ks:], square[:, ks:]
    mean_s, mean_y = (1.0 / s0)[:, None], (sy / s0)[:, None]
    # each position's own terms, once (the hypotheses pair them)
    a_own = gg[:, ::2] - gs * gs * mean_s  # Σ w g_t² − (Σ w g_t)²/S0
    b_own = gy - gs * mean_y

    # every hypothesis's SSR and two amplitudes
    a11, a22 = a_own[:, _PAIR_I1], a_own[:, _PAIR_I2]
    a12 = _PAIR_OVERLAP * gg[:, _PAIR_SUM] - gs[:, _PAIR_I1] * gs[:, _PAIR_I2] * mean_s
    b_1, b_2 = b_own[:, _PAIR_I1], b_own[:, _PAIR_I2]
    det = a11 * a22 - a12 * a12
    ok = det > 1e-9 * np.maximum(a11 * a22, 1e-300)
    det = np.where(ok, det, 1.0)
    amp1 = (a22 * b_1 - a12 * b_2) / det
    amp2 = (a11 * b_2 - a12 * b_1) / det
    ssr2_all = np.where(
        ok & (amp1 > 0) & (amp2 > 0), base[:, None] - (amp1 * b_1 + amp2 * b_2), np.inf
    )
    best = np.argmin(ssr2_all, axis=1)
    rows = np.arange(n)
    ssr2 = ssr2_all[rows, best]
    s2 = np.maximum(noise_gray * noise_gray, np.minimum(ssr1, ssr2) / max(m - 5, 1))
    with np.errstate(invalid="ignore"):
        evidence = (ssr1 - ssr2) / np.maximum(s2, 1e-12) - 2.0 * math.log(m)
    evidence = np.where(np.isfinite(evidence), evidence, -np.inf)
    interior = _PAIR_INTERIOR[best] & np.isfinite(ssr2)
    t = _PAIR_T[best]  # (n, 2): t1, t2
    centres = np.column_stack([r, c])[:, None, :] + scale * t[:, :, None] * axis[:, None, :]
    return BlendTest(
        evidence,
        centres,
        np.column_stack([amp1[rows, best], amp2[rows, best]]),
        (t[:, 0] - t[:, 1]) * scale / sigma_px,
        interior,
    )


@functools.lru_cache(maxsize=16)
def _window_offsets(half: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The row and column offsets (1, size²; row-major) of a square window of ±``half`` px."""
    off = np.arange(-half, half + 1)
    rows, cols = np.repeat(off, len(off))[None, :], np.tile(off, len(off))[None, :]
    rows.flags.writeable = cols.flags.writeable = False  # (shared: read only)
    return rows, cols


def _neighbours_in_windows(
    pr: NDArray[np.intp],
    pc: NDArray[np.intp],
    size: int,
    scale: float,
    neighbours: tuple[NDArray[np.intp], NDArray, NDArray, NDArray],
) -> NDArray[np.float64]:
    """(n, size²): the light of round spots (pixel-sampled sigma ``scale``) of the
    ``neighbours`` (the blob's index, row, col, peak) in the blobs' square windows, whose pixels
    are ``pr``, ``pc`` (n, size²; row-major). A round spot is the outer product of a row and a
    column profile, so each neighbour costs 2·size exponentials, and each window's sum over its
    neighbours is one small matrix product (the neighbours padded to the most any blob has)."""
    ki, o_r, o_c, o_peak = neighbours
    n = len(pr)
    rows_px = pr[:, ::size]  # (n, size): the window's rows, then its columns
    cols_px = pc[:, :size]
    inv = -0.5 / (scale * scale)
    qr = rows_px[ki] - o_r[:, None]
    qc = cols_px[ki] - o_c[:, None]
    prof_r = o_peak[:, None] * np.exp(qr * qr * inv)
    prof_c = np.exp(qc * qc * inv)
    if len(ki) > 1 and bool(np.any(ki[1:] < ki[:-1])):
        order = np.argsort(ki, kind="stable")
        ki, prof_r, prof_c = ki[order], prof_r[order], prof_c[order]
    count = np.bincount(ki, minlength=n)
    slot = np.arange(len(ki)) - (np.cumsum(count) - count)[ki]
    pad_r = np.zeros((n, int(count.max()), size))
    pad_c = np.zeros_like(pad_r)
    pad_r[ki, slot] = prof_r
    pad_c[ki, slot] = prof_c
    return np.matmul(np.swapaxes(pad_r, 1, 2), pad_c).reshape(n, size * size)
