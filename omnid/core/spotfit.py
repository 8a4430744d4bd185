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

import math

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


#: :func:`near_pairs` without ``sort`` tests all pairs of up to this many points.
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
    points without ``sort``: all n² pairs tested at once (the grid's passes cost more).
    """
    empty = np.zeros(0, np.intp), np.zeros(0, np.intp)
    n = len(rows)
    if n < 2:
        return empty
    r = np.asarray(rows, dtype=np.float64)
    c = np.asarray(cols, dtype=np.float64)
    if not sort and n <= _ALL_PAIRS_UP_TO:
        close = (np.abs(r[:, None] - r) <= reach) & (np.abs(c[:, None] - c) <= reach)
        np.fill_diagonal(close, False)
        i, j = np.nonzero(close)
        return i.astype(np.intp, copy=False), j.astype(np.intp, copy=False)
    # (cells wider than ``reach`` are as good; at most ~1024 per axis keep the table small)
    span = max(float(np.ptp(r)), float(np.ptp(c)))
    cell = max(float(reach), span / 1024.0, 1e-9)
    gr = np.floor((r - r.min()) / cell).astype(np.int64) + 1
    gc = np.floor((c - c.min()) / cell).astype(np.int64) + 1
    width = int(gc.max()) + 2
    key = gr * width + gc
    order = stable_argsort(key)
    per_cell = np.bincount(key, minlength=(int(gr.max()) + 2) * width)
    cell_start = np.cumsum(per_cell) - per_cell
    shifts = (np.arange(-1, 2)[:, None] * width + np.arange(-1, 2)[None, :]).ravel()
    target = (key[:, None] + shifts[None, :]).ravel()  # (n · 9), i-major
    lo = cell_start[target]
    count = per_cell[target]
    total = int(count.sum())
    if total == 0:
        return empty
    ends = np.cumsum(count)
    first = ends - count
    pos = np.arange(total) - np.repeat(first - lo, count)
    # (each point's candidates: the difference of the running count at its 9 cells' ends)
    per_point = np.diff(ends[8::9], prepend=0)
    i = np.repeat(np.arange(n, dtype=np.intp), per_point)
    j = order[pos].astype(np.intp)
    ri, rj, ci, cj = np.take(r, i), np.take(r, j), np.take(c, i), np.take(c, j)
    keep = (i != j) & (np.abs(ri - rj) <= reach) & (np.abs(ci - cj) <= reach)
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
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Fit every dot of a background-free ``image`` at once (see the module doc).

    ``rows``, ``cols``: each dot's peak pixel; ``start``: optional sub-pixel starting centres;
    ``sigma_px``: the starting spot sigma (it also sets the window); ``peak``: starting peak
    values, gray levels; ``saturated``: pixels whose value is only a lower bound (or None):
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
    rr = clip(win_r.astype(np.intp), 0, image.shape[0] - 1)[:, :, None]
    cc_ = clip(win_c.astype(np.intp), 0, image.shape[1] - 1)[:, None, :]
    inside = ((win_r >= 0) & (win_r < image.shape[0]))[:, :, None]
    inside = inside & ((win_c >= 0) & (win_c < image.shape[1]))[:, None, :]
    win = np.where(inside, image[rr, cc_], 0.0).astype(np.float64)  # outside the image: nothing
    sat_all: NDArray[np.bool_] | None = None
    if saturated is not None:
        sat_all = saturated[rr, cc_] & inside
        if not sat_all.any():
            sat_all = None
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
    if len(pair_i) == 0 or sigma_px <= SEQUENTIAL_FROM_PX:
        groups = [np.arange(n)]
    else:
        colour = (np.floor(cr / reach).astype(np.int64) % 2) * 2
        colour += np.floor(cc / reach).astype(np.int64) % 2
        groups = [g for g in (np.flatnonzero(colour == k) for k in range(4)) if len(g)]
    if iterations is None:
        iterations = ITERATIONS if len(groups) > 1 else JACOBI_ITERATIONS
    for _ in range(iterations):
        for g in groups:
            if len(groups) == 1:
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
    ur = win_r - cr[:, None]
    uc = win_c - cc[:, None]
    size = ur.shape[1]
    gr, dr, sr = window_gaussian(ur[:, :1], size, s[:, None])
    gc, dc, sc = window_gaussian(uc[:, :1], size, s[:, None])
    taper = -0.5 / (TAPER_PER_SIGMA * s[:, None]) ** 2
    wr, wc = np.exp(ur * ur * taper), np.exp(uc * uc * taper)
    data = st.win[k]
    local = np.full(len(st.cr), -1, np.intp)
    local[k] = np.arange(n)
    if st.sat is not None:
        sat = st.sat[k]
        hit = np.flatnonzero(sat.any(axis=(1, 2)))
        if len(hit):
            # A clipped pixel says "at least its value" about the whole model there — the
            # dot's own light, its plane and its neighbours' light — not about the dot alone.
            model = mass[hit, None, None] * gr[hit, :, None] * gc[hit, None, :]
            model += b0[hit, None, None] + br[hit, None, None] * ur[hit, :, None]
            model += bc[hit, None, None] * uc[hit, None, :]
            if len(pair_i):
                model += _neighbour_light(local[pair_i], pair_j, hit, win_r, win_c, st)
            data = data.copy()
            data[hit] = np.where(sat[hit], np.maximum(data[hit], model), data[hit])
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
        q -= _neighbour_sums(local[pair_i], pair_j, frw, fcw, win_r, win_c, st, n)
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


def _neighbour_profiles(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    win_r: NDArray[np.float64],
    win_c: NDArray[np.float64],
    st: _FitState,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The 1-D row and column profiles (pairs, size) of the neighbour j's current model over the
    window of the dot i, for each pair (a model is separable: the window's light is their outer
    product times the neighbour's mass)."""
    size = win_r.shape[1]
    sj = st.s[j, None]
    gjr = window_gaussian(win_r[i, :1] - st.cr[j, None], size, sj, derivatives=False)[0]
    gjc = window_gaussian(win_c[i, :1] - st.cc[j, None], size, sj, derivatives=False)[0]
    return gjr, gjc


def _neighbour_light(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    hit: NDArray[np.intp],
    win_r: NDArray[np.float64],
    win_c: NDArray[np.float64],
    st: _FitState,
) -> NDArray[np.float64]:
    """(len(hit), size, size): the current models of the neighbours j (indices into ``st``)
    rendered in the windows of the dots ``hit`` (indices into ``win_r``, ``win_c``, as the
    pairs' i; pairs sorted by i)."""
    size = win_r.shape[1]
    out = np.zeros((len(hit), size, size))
    slot = np.full(len(win_r), -1, np.intp)
    slot[hit] = np.arange(len(hit))
    keep = slot[i] >= 0
    if not keep.any():
        return out
    i, j = i[keep], j[keep]
    gjr, gjc = _neighbour_profiles(i, j, win_r, win_c, st)
    light = st.mass[j, None, None] * gjr[:, :, None] * gjc[:, None, :]
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    out[slot[i[starts]]] = np.add.reduceat(light, starts, axis=0)
    return out


def _neighbour_sums(
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    frw: NDArray[np.float64],
    fcw: NDArray[np.float64],
    win_r: NDArray[np.float64],
    win_c: NDArray[np.float64],
    st: _FitState,
    n: int,
) -> NDArray[np.float64]:
    """(n, 5, 5): what the current models of the neighbours j (indices into ``st``) add to the
    window sums of the dots i (indices into ``frw``, ``fcw``, ``win_r``, ``win_c``; pairs
    sorted by i). A model is separable, so each pair's share is an outer product of two 1-D
    overlaps."""
    gjr, gjc = _neighbour_profiles(i, j, win_r, win_c, st)
    vr = (frw[i] @ gjr[:, :, None])[:, :, 0]  # (pairs, 5)
    vc = (gjc[:, None, :] @ fcw[i])[:, 0, :]
    contrib = (st.mass[j, None, None] * vr[:, :, None] * vc[:, None, :]).reshape(len(i), 25)
    out = np.zeros((n, 25))
    starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
    out[i[starts]] = np.add.reduceat(contrib, starts, axis=0)
    return out.reshape(n, 5, 5)


# --------------------------------------------------------------------------------------------
# One spot or two: the model test that splits blends of two close beams
# --------------------------------------------------------------------------------------------

#: Levenberg-Marquardt passes of the one- and two-spot fits (:func:`two_spot_test`).
SPLIT_ITERATIONS = 20


def _one_spot_model(p: NDArray[np.float64], dr: NDArray, dc: NDArray) -> NDArray[np.float64]:
    """One spot of any elongation and flatness on a constant: p = (A, r, c, l11, l21, l22,
    ln power, b0); the inverse covariance is L Lᵀ, L = [[e^l11, 0], [l21, e^l22]], and the
    profile exp(−(q²/2)^power) (power 1: a Gaussian, above 1 a flatter top)."""
    u = dr - p[:, 1:2]
    v = dc - p[:, 2:3]
    a = np.exp(p[:, 3:4]) * u + p[:, 4:5] * v
    b = np.exp(p[:, 5:6]) * v
    q2 = 0.5 * (a * a + b * b)
    return np.asarray(p[:, 0:1] * np.exp(-(q2 ** np.exp(p[:, 6:7]))) + p[:, 7:8])


def _two_spot_model(p: NDArray[np.float64], dr: NDArray, dc: NDArray) -> NDArray[np.float64]:
    """Two round Gaussians of one size on a constant: p = (A1, r1, c1, A2, r2, c2, ln σ, b0)."""
    k = -0.5 * np.exp(-2.0 * p[:, 6:7])
    g1 = np.exp(k * ((dr - p[:, 1:2]) ** 2 + (dc - p[:, 2:3]) ** 2))
    g2 = np.exp(k * ((dr - p[:, 4:5]) ** 2 + (dc - p[:, 5:6]) ** 2))
    return np.asarray(p[:, 0:1] * g1 + p[:, 3:4] * g2 + p[:, 7:8])


def _levenberg_marquardt(
    model,
    p: NDArray[np.float64],
    data: NDArray[np.float64],
    dr: NDArray,
    dc: NDArray,
    censored: NDArray[np.bool_] | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least squares of ``model`` to ``data`` (n, m), every window at once (forward-difference
    Jacobian, one damping factor per window); a ``censored`` pixel (clipped: its value only
    bounds the light from below) has no residual where the model exceeds it. Returns the
    parameters and the residual sums."""

    def residual(q: NDArray[np.float64]) -> NDArray[np.float64]:
        res = model(q, dr, dc) - data
        if censored is not None:
            res = np.where(censored & (res > 0), 0.0, res)
        return np.asarray(res)

    p = p.copy()
    n, k = p.shape
    res = residual(p)
    cost = np.sum(res * res, axis=1)
    lam = np.full(n, 1e-2)
    eye = np.eye(k)
    for _ in range(SPLIT_ITERATIONS):
        jac = np.empty((n, data.shape[1], k))
        for j in range(k):
            step = 1e-4 * np.maximum(np.abs(p[:, j]), 1e-2)
            q = p.copy()
            q[:, j] += step
            jac[:, :, j] = (residual(q) - res) / step[:, None]
        jac = np.nan_to_num(jac, nan=0.0, posinf=0.0, neginf=0.0)
        jtj = np.einsum("nmk,nml->nkl", jac, jac)
        grad = np.einsum("nmk,nm->nk", jac, res)
        damp = jtj * (1.0 + lam[:, None, None] * eye) + 1e-9 * eye
        try:
            delta = np.linalg.solve(damp, -grad[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            delta = (np.linalg.pinv(damp) @ -grad[:, :, None])[:, :, 0]
        trial = p + delta
        res_t = residual(trial)
        cost_t = np.sum(res_t * res_t, axis=1)
        better = np.isfinite(cost_t) & (cost_t < cost)
        p[better], res[better], cost[better] = trial[better], res_t[better], cost_t[better]
        lam = np.where(better, lam * 0.3, lam * 10.0)
    return p, cost


def _split_windows(
    image: NDArray, r: NDArray[np.float64], c: NDArray[np.float64], sigma_px: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray, NDArray]:
    """The ±3 σ windows around each point: values (n, m), pixel offsets from the nearest
    pixel (n, m) row and column, and that pixel's row and column (n,)."""
    n = len(r)
    h = window_half_px(sigma_px)
    off = np.arange(-h, h + 1, dtype=np.float64)
    ir, ic = np.rint(r).astype(np.intp), np.rint(c).astype(np.intp)
    ones = np.ones_like(off)
    dr = np.broadcast_to((off[:, None] * ones[None, :]).ravel(), (n, off.size**2))
    dc = np.broadcast_to((ones[:, None] * off[None, :]).ravel(), (n, off.size**2))
    rr = clip(ir[:, None] + dr.astype(np.intp), 0, image.shape[0] - 1)
    cc = clip(ic[:, None] + dc.astype(np.intp), 0, image.shape[1] - 1)
    return image[rr, cc].astype(np.float64), dr, dc, ir, ic


def _excess(
    data: NDArray[np.float64], dr: NDArray[np.float64], dc: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The windows' light above their median: how much its long axis's variance exceeds the
    short one's, px² (two spots d apart with shares w and 1 − w: w(1 − w)·d²), and the long
    axis's angle (rad, from the row axis)."""
    w = np.maximum(data - np.median(data, axis=1, keepdims=True), 0.0)
    total = np.maximum(w.sum(axis=1), 1e-9)
    mr = (w * dr).sum(axis=1) / total
    mc = (w * dc).sum(axis=1) / total
    vrr = (w * (dr - mr[:, None]) ** 2).sum(axis=1) / total
    vcc = (w * (dc - mc[:, None]) ** 2).sum(axis=1) / total
    vrc = (w * (dr - mr[:, None]) * (dc - mc[:, None])).sum(axis=1) / total
    theta = 0.5 * np.arctan2(2.0 * vrc, vrr - vcc)
    return 2.0 * np.sqrt(0.25 * (vrr - vcc) ** 2 + vrc * vrc), theta


def light_excess_px2(
    image: NDArray[np.float32], r: NDArray[np.float64], c: NDArray[np.float64], sigma_px: float
) -> NDArray[np.float64]:
    """(n,) the long-axis variance excess of the light around each point (:func:`_excess`),
    px²: a cheap screen for :func:`two_spot_test`."""
    if len(r) == 0:
        return np.zeros(0)
    data, dr, dc, _, _ = _split_windows(image, r, c, sigma_px)
    return _excess(data, dr, dc)[0]


def two_spot_test(
    image: NDArray[np.float32],
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    sigma_px: float,
    saturated: NDArray[np.bool_] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Is each dot (sub-pixel centre ``r``, ``c`` in a background-free ``image``) one spot or
    the blend of two? Both models are fitted by least squares to the window of ±3 σ around it:

    - one spot of free elongation, orientation and flatness (:func:`_one_spot_model`): a spot
      the mirror's rim stretches, a flat (multimode) top;
    - two round Gaussians of one free size (:func:`_two_spot_model`): two beams a doubled
      beam's offset apart.

    Both have 8 parameters, so neither wins by its number of them. A blend and a stretched
    spot agree to second order (the same intensity covariance); they differ at fourth order —
    the blend is flatter along its long axis only, a flat top in every direction — which is
    what the residuals compare. Returns (the evidence for two, (n, 4) the two centres r1, c1,
    r2, c2, px, and (n, 2) their peaks). The evidence is (SSR_one − SSR_two) / s² with s² the
    per-pixel residual variance of the better model, i.e. twice the log-likelihood ratio at
    the window's own noise level (read noise, shot noise and speckle alike).
    """
    n = len(r)
    data, dr, dc, ir, ic = _split_windows(image, r, c, sigma_px)
    censored = None
    if saturated is not None:
        censored = _split_windows(saturated, r, c, sigma_px)[0] > 0.5
        if not censored.any():
            censored = None
    r0, c0 = r - ir, c - ic
    excess, theta = _excess(data, dr, dc)
    half = clip(np.sqrt(np.maximum(excess, 0.0)), 0.3 * sigma_px, 1.5 * sigma_px)
    er, ec = np.cos(theta), np.sin(theta)
    top = data.max(axis=1)
    s = float(sigma_px)
    p1 = np.column_stack(
        [
            top,
            r0,
            c0,
            np.full(n, -math.log(s)),
            np.zeros(n),
            np.full(n, -math.log(s)),
            np.zeros(n),
            np.zeros(n),
        ]
    )
    p2 = np.column_stack(
        [
            0.6 * top,
            r0 + half * er,
            c0 + half * ec,
            0.6 * top,
            r0 - half * er,
            c0 - half * ec,
            np.full(n, math.log(s)),
            np.zeros(n),
        ]
    )
    with np.errstate(over="ignore", invalid="ignore"):  # (a trial step may overflow: refused)
        _, ssr1 = _levenberg_marquardt(_one_spot_model, p1, data, dr, dc, censored)
        q2, ssr2 = _levenberg_marquardt(_two_spot_model, p2, data, dr, dc, censored)
    dof = max(data.shape[1] - p1.shape[1], 1)
    s2 = np.maximum(np.minimum(ssr1, ssr2) / dof, 1e-9)
    evidence = (ssr1 - ssr2) / s2
    centres = np.column_stack([q2[:, 1] + ir, q2[:, 2] + ic, q2[:, 4] + ir, q2[:, 5] + ic])
    return evidence, centres, q2[:, [0, 3]]
