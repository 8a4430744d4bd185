"""3-D positions of matched laser dots from their two image positions (thesis 6.1; SPEC §2).

Two methods, same contract::

    triangulate(rig, pixels (N, 4) r1 c1 r2 c2 px, method="best" | "thesis", pixel_sigma_px=0.3)
        -> xyz (N, 3) mm, cov (N, 3, 3) mm²

``thesis``
    The thesis' closed form: X and Y from the intersection of the two horizontal lines through
    each mirror axis (eqs. 6.3–6.6), Z from mirror 1 alone (eqs. 6.8, 6.9), on the raw offsets
    from each camera's mirror centre (the thesis knows no camera rotation). It uses three of the
    four coordinates' information unevenly and is ill-conditioned near the plane X = 0 (beside
    the baseline): there the values come out ±inf/NaN or far off, and the covariance — first-order
    propagation of isotropic pixel noise through the analytic partials of eqs. 6.10/6.11, see
    :mod:`omnid.core.errormodel` — grows without bound, which is the honest flag.

``best``
    All four coordinates, weighted linear least squares. With ideal offsets (rotation undone,
    :meth:`MirrorCamera.ideal_offsets`) and ``a_i = (f/K)_i`` the projection of SPEC §2 reads::

        x_i = −a_i·p,   y_i = a_i·(q − Y_i·u),   p = X/Z, q = Y/Z, u = 1/Z

    — linear in θ = (p, q, u). Four equations, three unknowns, and the design matrix A depends on
    the rig only, so the estimate is one constant 3x4 matrix applied to every point:
    θ = (AᵀA)⁻¹Aᵀ·b. Then X = p/u, Y = q/u, Z = 1/u. With isotropic pixel noise σ this is the
    maximum-likelihood estimate; cov θ = σ²(AᵀA)⁻¹ is propagated to (X, Y, Z) through the
    Jacobian of (p/u, q/u, 1/u). Well conditioned everywhere in front of the mirrors, including
    X = 0. Points with u ≤ 0 (at or behind the mirror plane) give NaN.

    The one redundant equation measures whether the two viewing rays meet: the least-squares
    residual ‖b − Aθ‖ (px) is :func:`ray_residual_px`. For an ideal rig it is
    |r1 − r2|/√2 (the rows of a true pair agree); the matcher uses it to reject pairs whose rays
    do not meet (under the noise model it is σ·|N(0, 1)|).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.core.errormodel import thesis_jacobian, thesis_xyz
from omnid.core.geometry import MIRROR_CONSTANT_K, StereoRig
from omnid.errors import InputError

TriangulationMethod = Literal["thesis", "best"]

__all__ = [
    "TriangulationMethod",
    "best_design_matrix",
    "ray_residual_px",
    "thesis_offsets",
    "triangulate",
    "triangulate_on_beams",
]


def _as_pixels4(pixels: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(pixels, dtype=np.float64)
    if arr.ndim == 1 and arr.size == 4:
        arr = arr.reshape(1, 4)
    if arr.size == 0:
        return np.zeros((0, 4))
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise InputError(
            f"triangulate: expected pixels of shape (N, 4) r1 c1 r2 c2, got {arr.shape}"
        )
    return arr


def _check_sigma(pixel_sigma_px: float) -> float:
    sigma = float(pixel_sigma_px)
    if not (math.isfinite(sigma) and sigma >= 0.0):
        raise InputError(
            f"triangulate: pixel_sigma_px must be finite and ≥ 0, got {pixel_sigma_px}"
        )
    return sigma


def thesis_offsets(rig: StereoRig, pixels: ArrayLike) -> NDArray[np.float64]:
    """Raw offsets (N, 4) = (x1, y1, x2, y2) px from each camera's mirror centre (thesis 6.1).

    ``x_ip = r_i − r_mi``, ``y_ip = c_i − c_mi``; no rotation is undone (the thesis has none).
    """
    q = _as_pixels4(pixels)
    c1, c2 = rig.cam1, rig.cam2
    centre = np.array([c1.center_row_px, c1.center_col_px, c2.center_row_px, c2.center_col_px])
    return q - centre


def best_design_matrix(rig: StereoRig) -> NDArray[np.float64]:
    """The 4x3 design matrix A of the ``best`` method: (x1, y1, x2, y2) = A·(p, q, u)."""
    a1, a2 = rig.cam1.f_over_k_px, rig.cam2.f_over_k_px
    y1, y2 = rig.cam1.y_mm, rig.cam2.y_mm
    return np.array(
        [
            [-a1, 0.0, 0.0],
            [0.0, a1, -a1 * y1],
            [-a2, 0.0, 0.0],
            [0.0, a2, -a2 * y2],
        ]
    )


def _ideal_b(rig: StereoRig, q: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.hstack([rig.cam1.ideal_offsets(q[:, :2]), rig.cam2.ideal_offsets(q[:, 2:])])


def _triangulate_best(
    rig: StereoRig, q: NDArray[np.float64], sigma: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    A = best_design_matrix(rig)
    normal_inv = np.linalg.inv(A.T @ A)
    theta = _ideal_b(rig, q) @ (normal_inv @ A.T).T  # (N, 3) = (p, q, u)
    p, qq, u = theta[:, 0], theta[:, 1], theta[:, 2]
    front = u > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_u = np.where(front, 1.0 / u, np.nan)
    xyz = np.column_stack([p * inv_u, qq * inv_u, inv_u])
    # Jacobian of (p/u, q/u, 1/u) with respect to (p, q, u).
    n = len(q)
    G = np.zeros((n, 3, 3))
    G[:, 0, 0] = inv_u
    G[:, 1, 1] = inv_u
    G[:, 0, 2] = -xyz[:, 0] * inv_u
    G[:, 1, 2] = -xyz[:, 1] * inv_u
    G[:, 2, 2] = -inv_u * inv_u
    cov = (sigma * sigma) * np.einsum("nij,jk,nlk->nil", G, normal_inv, G)
    return xyz, cov


def _triangulate_thesis(
    rig: StereoRig, q: NDArray[np.float64], sigma: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    off = thesis_offsets(rig, q)
    d = rig.baseline_mm
    f1 = rig.cam1.f_over_k_px * MIRROR_CONSTANT_K  # f = K·(f/K), pixel focal length of camera 1
    xyz = thesis_xyz(off, d, f1)
    # The thesis puts the origin midway between the mirrors; keep that for an asymmetric rig too.
    xyz[:, 1] += 0.5 * (rig.cam1.y_mm + rig.cam2.y_mm)
    jac = thesis_jacobian(off, d, f1)
    with np.errstate(invalid="ignore", over="ignore"):
        cov = (sigma * sigma) * np.einsum("nab,ncb->nac", jac, jac)
    bad = ~np.isfinite(cov).all(axis=(1, 2))
    cov[bad] = np.nan
    return xyz, cov


def triangulate(
    rig: StereoRig,
    pixels: ArrayLike,
    method: TriangulationMethod = "best",
    pixel_sigma_px: float = 0.3,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Matched image positions (N, 4) r1 c1 r2 c2 px → xyz (N, 3) mm and cov (N, 3, 3) mm².

    ``pixel_sigma_px`` is the standard deviation of each image coordinate (isotropic, independent)
    used for the covariance. See the module docstring for the two methods; the thesis method
    implements eqs. 6.3–6.9 and takes its covariance from the error model (eqs. 6.10–6.11),
    NaN where that is undefined. An empty input gives arrays of shape (0, 3) and (0, 3, 3).
    """
    q = _as_pixels4(pixels)
    sigma = _check_sigma(pixel_sigma_px)
    if len(q) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    if method == "best":
        return _triangulate_best(rig, q, sigma)
    if method == "thesis":
        return _triangulate_thesis(rig, q, sigma)
    raise ValueError(f"unknown triangulation method {method!r} (known: thesis, best)")


def ray_residual_px(rig: StereoRig, pixels: ArrayLike) -> NDArray[np.float64]:
    """How far (N,) px a matched pair is from rays that meet: ‖b − A·θ̂‖ of the ``best`` fit.

    Zero for a noise-free true pair; for an ideal rig it equals |r1 − r2|/√2. Under isotropic
    pixel noise σ it is distributed as σ·|N(0, 1)|, so e.g. 3σ is a sensible rejection bound.
    """
    q = _as_pixels4(pixels)
    if len(q) == 0:
        return np.zeros(0)
    A = best_design_matrix(rig)
    b = _ideal_b(rig, q)
    hat = A @ np.linalg.pinv(A)
    res = b - b @ hat.T
    return np.asarray(np.linalg.norm(res, axis=1), dtype=np.float64)


def triangulate_on_beams(
    rig: StereoRig,
    pixels: ArrayLike,
    slope: NDArray[np.float64],
    cross_mm: NDArray[np.float64],
    slope_sigma: NDArray[np.float64],
    pixel_sigma_px: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``best`` triangulation with each dot's laser beam as a third view: xyz (N, 3), cov (N, 3, 3).

    A dot of the beam with slope s and mirror-plane crossing c satisfies (p, q) = s + c·u in the
    unknowns θ = (p, q, u) of the ``best`` method (module docstring); the beam is known to
    ``slope_sigma`` (per axis, from the calibration's source and floor-point errors). Weighted
    least squares over the four image coordinates (σ = ``pixel_sigma_px``) and these two beam
    equations gives θ and cov θ = N⁻¹, propagated to (X, Y, Z) as in :func:`triangulate`. With
    a well-known beam the depth is fixed by the dot's slide along its track as well as by the
    disparity, which shrinks its error; with a poorly known one it falls back to plain stereo.
    """
    q = _as_pixels4(pixels)
    sigma = max(_check_sigma(pixel_sigma_px), 1e-6)
    n = len(q)
    if n == 0:
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    A = best_design_matrix(rig)
    b = _ideal_b(rig, q)
    wb = 1.0 / np.maximum(np.asarray(slope_sigma, dtype=np.float64), 1e-9) ** 2  # (N,)
    c = np.asarray(cross_mm, dtype=np.float64)
    s = np.asarray(slope, dtype=np.float64)
    cx, cy = c[:, 0], c[:, 1]
    # normal equations N·θ = rhs with the beam rows B = [[1, 0, −c_X], [0, 1, −c_Y]], B·θ = s:
    # N = AᵀA/σ² + w·BᵀB, rhs = Aᵀb/σ² + w·Bᵀs; N is symmetric 3x3, inverted in closed form
    # (cofactors: a batched LAPACK inverse costs ~10x more for these small systems)
    ata = (A.T @ A) / sigma**2
    n00 = ata[0, 0] + wb
    n01 = np.full(n, ata[0, 1])
    n02 = ata[0, 2] - wb * cx
    n11 = ata[1, 1] + wb
    n12 = ata[1, 2] - wb * cy
    n22 = ata[2, 2] + wb * (cx * cx + cy * cy)
    rhs = (b @ A) / sigma**2
    rhs[:, 0] += wb * s[:, 0]
    rhs[:, 1] += wb * s[:, 1]
    rhs[:, 2] -= wb * (cx * s[:, 0] + cy * s[:, 1])
    c00 = n11 * n22 - n12 * n12
    c01 = n02 * n12 - n01 * n22
    c02 = n01 * n12 - n02 * n11
    det = n00 * c00 + n01 * c01 + n02 * c02
    # N⁻¹ (symmetric), θ = N⁻¹·rhs and cov = G·N⁻¹·Gᵀ per point, one coordinate pair at a time
    # (batched 3x3 products, and numpy along short rows, cost ~5-10x more)
    i00, i01, i02 = c00 / det, c01 / det, c02 / det
    i11 = (n00 * n22 - n02 * n02) / det
    i12 = (n01 * n02 - n00 * n12) / det
    i22 = (n00 * n11 - n01 * n01) / det
    r0, r1, r2 = rhs[:, 0], rhs[:, 1], rhs[:, 2]
    p = i00 * r0 + i01 * r1 + i02 * r2
    qq = i01 * r0 + i11 * r1 + i12 * r2
    u = i02 * r0 + i12 * r1 + i22 * r2
    front = u > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_u = np.where(front, 1.0 / u, np.nan)
    x, y = p * inv_u, qq * inv_u
    xyz = np.column_stack([x, y, inv_u])
    # G = ∂(X, Y, Z)/∂(p, q, u) = [[1/u, 0, −X/u], [0, 1/u, −Y/u], [0, 0, −1/u²]]
    g02, g12, g22 = -x * inv_u, -y * inv_u, -inv_u * inv_u
    # M = G·N⁻¹, row by row
    m00, m01, m02 = inv_u * i00 + g02 * i02, inv_u * i01 + g02 * i12, inv_u * i02 + g02 * i22
    m11, m12 = inv_u * i11 + g12 * i12, inv_u * i12 + g12 * i22
    m22 = g22 * i22
    # cov = M·Gᵀ (upper triangle; symmetric)
    s00 = m00 * inv_u + m02 * g02
    s01 = m01 * inv_u + m02 * g12
    s02 = m02 * g22
    s11 = m11 * inv_u + m12 * g12
    s12 = m12 * g22
    s22 = m22 * g22
    cov = np.stack([s00, s01, s02, s01, s11, s12, s02, s12, s22], axis=1).reshape(n, 3, 3)
    return xyz, cov
