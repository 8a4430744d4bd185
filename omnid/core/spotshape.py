"""Dot centres from a spot shape learned from the image: a joint fit of every dot.

Experimental: ``detect._detect_best(..., learned_shape=True)``, scored against the default in
``tools/bench_detect.py --learned-shape`` (docs/benchmarks/detection.md); not the default.

Model of the subtracted image near the dots (no profile of the renderer assumed: the shape's
free parts are measured on the image)::

    I(x) = Σ_i A_i · P(q_i(x))  +  b0_i + b_i · (x − c_i)   near dot i,
    q_i(x)² = (x − c_i)ᵀ S_i (x − c_i)

with c_i the centre (px), S_i the dot's own inverse covariance (size, elongation and
orientation per dot: the mirror stretches spots toward its rim, each along its own radius),
A_i its peak (gray levels), a plane for the local background, and P the image's radial
profile: a Gaussian for the first passes, then the table (in q², 0 … 6 dot sigmas) of the
mean normalised light of the isolated, unclipped dots of the image at each q — flat tops,
halo rings and whatever else the optics do, learned (:func:`_learn`). The spread of those
values about the mean per q (grains) is learned too; with ``weighted`` it enters each
pixel's variance (σ_n² + A²·spread(q)), so the grains pull less (on the measured cases it
helped speckle and hurt halos: off by default). Each pixel's weight also carries a taper of
2 dot sigmas and a Huber weight on the standardised residual. Pixels the sensor clipped carry
no value: they are left out (censored), not fitted.

Every dot is updated at once against its neighbours' current models (their sum is rendered
once per pass into a model image; a dot's data is the image less every other dot's model):
a joint fit of overlapping dots, block-Jacobi Gauss–Newton with damping. Everything is
vectorised over the dots: (n, window pixels, parameters) arrays, batched 9x9 solves — about
10–20 ms per camera for ~600 dots of σ ≈ 2 px, too slow for the frame rate as it stands.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

#: Gauss–Newton passes over all dots.
ITERATIONS = 4
#: Largest centre step per pass, px.
MAX_STEP_PX = 0.5
#: Taper of the weights, exp(−q²/TAPER_Q2): 2 spot sigmas (a neighbour left in a window by
#: a wrong model — an unresolved pair — pulls less; without it crowded cases lose 0.03 px).
TAPER_Q2 = 8.0
#: Huber threshold on the standardised residual.
HUBER_K = 2.0
#: Parameters per dot: peak, row, col, S_rr, S_rc, S_cc, b0, b_r, b_c.
_NPAR = 9


#: Nodes of the learned profile: q = 0, 0.25, … 6 (in the dot's own sigmas), tabled in q².
_Q_NODES = np.arange(0.0, 6.01, 0.25)
_U_NODES = _Q_NODES**2


def _profile(q2: NDArray, table: NDArray | None) -> tuple[NDArray, NDArray]:
    """The radial profile P at q² and dP/d(q²): a Gaussian, or the learned ``table`` (values at
    :data:`_U_NODES`, linear in q², 0 beyond)."""
    if table is None:
        p = np.exp(-0.5 * q2)
        return p, -0.5 * p
    u = np.minimum(q2, _U_NODES[-1])
    k = np.minimum(np.searchsorted(_U_NODES, u, side="right") - 1, len(_U_NODES) - 2)
    slope = np.diff(table) / np.diff(_U_NODES)
    p = table[k] + slope[k] * (u - _U_NODES[k])
    return p, np.where(q2 < _U_NODES[-1], slope[k], 0.0)


def _learn(q2: NDArray, y: NDArray, ok: NDArray) -> tuple[NDArray, NDArray]:
    """The mean profile and the spread (variance) of ``y`` (data / peak, neighbours and
    background taken out) per node of q, from the pixels ``ok``: binned, the mean scaled to
    1 at the centre, the spread per node."""
    q = np.sqrt(q2[ok])
    yy = y[ok]
    step = _Q_NODES[1]
    k = np.rint(q / step).astype(np.intp)
    keep = k < len(_Q_NODES)
    k, yy = k[keep], yy[keep]
    cnt = np.bincount(k, minlength=len(_Q_NODES)).astype(np.float64)
    s1 = np.bincount(k, weights=yy, minlength=len(_Q_NODES))
    s2 = np.bincount(k, weights=yy * yy, minlength=len(_Q_NODES))
    have = cnt >= 8
    mean = np.where(have, s1 / np.maximum(cnt, 1), 0.0)
    var = np.where(have, s2 / np.maximum(cnt, 1) - mean**2, 0.0)
    # Nodes without data: the Gaussian's value (the centre node always has data).
    gauss = np.exp(-0.5 * _U_NODES)
    mean = np.where(have, mean, gauss * (mean[0] if have[0] else 1.0))
    top = mean[0] if mean[0] > 0 else 1.0
    return mean / top, np.maximum(var, 0.0) / (top * top)


def fit_dots(
    image: NDArray[np.float32],
    valid: NDArray[np.bool_] | None,
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    peak: NDArray,
    sigma_px: float,
    noise_gray: float,
    half_px: int,
    learn_passes: int = 2,
    iterations: int = ITERATIONS,
    weighted: bool = False,
    learn_shape: bool = True,
) -> tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray | None, NDArray | None
]:
    """Fit every dot at once (see the module doc). ``image``: the subtracted image (float32);
    ``valid``: pixels with a value (False where clipped), or None; ``r``, ``c``: starting
    centres px; ``peak``: starting peaks; ``sigma_px``: starting size; ``half_px``: window
    half-size. ``learn_passes`` Gaussian passes, then the profile and its spread are learned
    on the isolated unclipped dots and ``iterations`` passes use them. Returns (row, col,
    peak, profile table, spread table)."""
    n = len(r)
    h_img, w_img = image.shape
    off = np.arange(-half_px, half_px + 1)
    size = len(off)
    cr, cc = r.astype(np.float64).copy(), c.astype(np.float64).copy()
    amp = np.maximum(np.asarray(peak, dtype=np.float64), 1e-3)
    s_rr = np.full(n, 1.0 / sigma_px**2)
    s_rc = np.zeros(n)
    s_cc = s_rr.copy()
    b0, br, bc = np.zeros(n), np.zeros(n), np.zeros(n)
    # Window anchored on the starting pixel (fixed, so the data do not change between passes).
    pr0 = np.rint(cr).astype(np.intp)
    pc0 = np.rint(cc).astype(np.intp)
    wr = np.broadcast_to(pr0[:, None, None] + off[None, :, None], (n, size, size))
    wc = np.broadcast_to(pc0[:, None, None] + off[None, None, :], (n, size, size))
    inside = (wr >= 0) & (wr < h_img) & (wc >= 0) & (wc < w_img)
    flat = (np.clip(wr, 0, h_img - 1) * w_img + np.clip(wc, 0, w_img - 1)).reshape(n, -1)
    data = image.ravel()[flat].astype(np.float64)
    ok = inside.reshape(n, -1)
    if valid is not None:
        ok = ok & valid.ravel()[flat]
    okf = ok.astype(np.float64)
    wrf = wr.reshape(n, -1).astype(np.float64)
    wcf = wc.reshape(n, -1).astype(np.float64)
    var_n = max(noise_gray, 0.5) ** 2
    # Isolated (no other dot's start within the window's reach) and unclipped: the dots the
    # shape is learned from.
    lone = ok.all(axis=1)
    if n > 1:
        dist, _ = cKDTree(np.column_stack([cr, cc])).query(np.column_stack([cr, cc]), k=2)
        lone &= dist[:, 1] > 2.0 * half_px
    table: NDArray | None = None
    spread: NDArray | None = None
    total_passes = learn_passes + iterations
    for it in range(total_passes):
        dr = wrf - cr[:, None]
        dc = wcf - cc[:, None]
        q2 = s_rr[:, None] * dr * dr + 2.0 * s_rc[:, None] * dr * dc + s_cc[:, None] * dc * dc
        p, dp = _profile(q2, table)
        own = amp[:, None] * p
        # Every dot's model, summed into one image: the neighbours' light in each window.
        total = np.bincount(flat.ravel(), weights=(own * okf).ravel(), minlength=h_img * w_img)
        others = total[flat] - own * okf
        bg = b0[:, None] + br[:, None] * dr + bc[:, None] * dc
        if it == learn_passes and learn_shape and np.count_nonzero(lone) >= 8:
            y = (data - others - bg) / amp[:, None]
            sel = np.broadcast_to(lone[:, None], ok.shape)
            table, spread = _learn(q2, y, sel)
            p, dp = _profile(q2, table)
            own = amp[:, None] * p
        resid = data - others - own - bg
        var = np.full_like(resid, var_n)
        if weighted and spread is not None:
            # The learned spread (grains) in gray levels², besides the sensor noise and the
            # shot noise (variance ∝ light: one gray level² per gray level, conservatively).
            var = var + (amp[:, None] ** 2) * _profile(q2, spread)[0]
        w = okf / var
        w = w * np.exp(-q2 / TAPER_Q2)
        z = np.abs(resid) * np.sqrt(w)
        w = w * np.where(z > HUBER_K, HUBER_K / np.maximum(z, 1e-12), 1.0)
        g = amp[:, None] * dp  # dM/d(q²)
        jac = np.empty((n, flat.shape[1], _NPAR))
        jac[:, :, 0] = p
        jac[:, :, 1] = -2.0 * g * (s_rr[:, None] * dr + s_rc[:, None] * dc) - br[:, None]
        jac[:, :, 2] = -2.0 * g * (s_rc[:, None] * dr + s_cc[:, None] * dc) - bc[:, None]
        jac[:, :, 3] = g * dr * dr
        jac[:, :, 4] = 2.0 * g * dr * dc
        jac[:, :, 5] = g * dc * dc
        jac[:, :, 6] = 1.0
        jac[:, :, 7] = dr
        jac[:, :, 8] = dc
        jw = jac * w[:, :, None]
        normal = np.einsum("npi,npj->nij", jw, jac)
        rhs = np.einsum("npi,np->ni", jw, resid)
        normal += np.eye(_NPAR)[None] * (
            1e-6 * np.trace(normal, axis1=1, axis2=2)[:, None, None] / _NPAR + 1e-9
        )
        step = np.linalg.solve(normal, rhs[:, :, None])[:, :, 0]
        step *= 0.7 if it < total_passes - 1 else 1.0
        amp = np.maximum(amp + step[:, 0], 1e-3)
        cr += np.clip(step[:, 1], -MAX_STEP_PX, MAX_STEP_PX)
        cc += np.clip(step[:, 2], -MAX_STEP_PX, MAX_STEP_PX)
        s_rr = np.clip(s_rr + step[:, 3], 0.02, 4.0)
        s_cc = np.clip(s_cc + step[:, 5], 0.02, 4.0)
        lim = 0.95 * np.sqrt(s_rr * s_cc)
        s_rc = np.clip(s_rc + step[:, 4], -lim, lim)
        b0 += step[:, 6]
        br += step[:, 7]
        bc += step[:, 8]
    return cr, cc, amp, table, spread
