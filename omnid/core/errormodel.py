"""The thesis' triangulation formulas and their error model (thesis 6.1–6.2, eqs. 6.3–6.11).

All functions work on image *offsets* from each mirror centre, in pixels, exactly as the thesis
writes them (6.1): ``x_ip = r_i − r_mi`` (row offset) and ``y_ip = c_i − c_mi`` (column offset).
With the conventions of SPEC §2 a world point (X, Y, Z) is imaged at ``x_i = −s·X``,
``y_i = s·(Y − Y_i)``, ``s = (f/K)/Z``, mirror 1 at ``Y_1 = −D/2`` and mirror 2 at ``Y_2 = +D/2``;
the formulas below invert that exactly.

The denominator of eqs. 6.5 and 6.6, ``Δ = x1·y2 − x2·y1 = s²·X·D``, vanishes for points on the
plane X = 0 (straight beside the baseline): there the thesis formulas are 0/0 and, close to it,
ill-conditioned — a small row error moves X, Y and Z a long way. Nothing here hides that: the
values come out as ±inf/NaN or very large, and the partial derivatives (hence the covariance of
:func:`omnid.core.triangulate.triangulate` with ``method="thesis"``) grow like 1/Δ².
Eq. 6.8 also divides by ξ1, the pixel distance from mirror 1's centre (0/0 right below mirror 1).

The partial derivatives are taken with respect to the image positions (r1, c1, r2, c2); since the
mirror centres are constants, ∂/∂r_i = ∂/∂x_ip and ∂/∂c_i = ∂/∂y_ip.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.core.geometry import MIRROR_CONSTANT_K

__all__ = [
    "max_relative_error",
    "relative_error",
    "thesis_jacobian",
    "thesis_xyz",
]


def _offsets(offsets: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(offsets, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr.reshape(1, -1)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(f"expected offsets of shape (N, 4) as (x1, y1, x2, y2), got {arr.shape}")
    return arr


def thesis_xyz(
    offsets: ArrayLike,
    baseline_mm: float,
    f1_px: float,
    mirror_constant: float = MIRROR_CONSTANT_K,
) -> NDArray[np.float64]:
    """X, Y, Z (N, 3) mm from image offsets (N, 4) = (x1, y1, x2, y2) px by the thesis' formulas.

    - eq. 6.5: ``X = D·x1·x2 / (x1·y2 − x2·y1)``
    - eq. 6.6: ``Y = D·(x1·y2 + x2·y1) / (2·(x2·y1 − x1·y2))``
    - eq. 6.9: ``ξ1 = sqrt(x1² + y1²)`` (pixel distance from mirror 1's centre)
    - eq. 6.8: ``Z = sqrt(X² + (Y + D/2)²) / tan(atan(tan δr · ξ1 / (tan αr · f)))`` with
      ``tan δr / tan αr = K`` (``mirror_constant``) and ``f = f1_px`` the pixel focal length of
      camera 1 (``f = K·(f/K)``). ``tan(atan(v)) = v`` for every real v, so it is computed as
      ``K·ξ1/f``.

    Y is measured from the midpoint of the mirrors (mirror 1 at −D/2). Division by zero gives
    ±inf or NaN (see the module docstring); no warning is raised.
    """
    o = _offsets(offsets)
    x1, y1, x2, y2 = o[:, 0], o[:, 1], o[:, 2], o[:, 3]
    d = float(baseline_mm)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = x1 * y2 - x2 * y1
        X = d * x1 * x2 / den  # eq. 6.5
        Y = d * (x1 * y2 + x2 * y1) / (2.0 * (x2 * y1 - x1 * y2))  # eq. 6.6
        xi1 = np.hypot(x1, y1)  # eq. 6.9
        tan_delta = mirror_constant * xi1 / f1_px  # eq. 6.8 (tan δ = K·ξ1/f)
        Z = np.hypot(X, Y + d / 2.0) / tan_delta  # eq. 6.8
    return np.column_stack([X, Y, Z])


def thesis_jacobian(
    offsets: ArrayLike,
    baseline_mm: float,
    f1_px: float,
    mirror_constant: float = MIRROR_CONSTANT_K,
) -> NDArray[np.float64]:
    """Analytic partial derivatives (N, 3, 4) of (X, Y, Z) with respect to (r1, c1, r2, c2), mm/px.

    ``J[n, a, b] = ∂F_a/∂v_b`` with F = (X, Y, Z) of eqs. 6.5, 6.6, 6.8 and v = (r1, c1, r2, c2),
    the derivatives the thesis leaves "not derived further here" (6.2). With Δ = x1·y2 − x2·y1:

    eq. 6.5::

        ∂X/∂x1 = −D·x2²·y1/Δ²   ∂X/∂y1 =  D·x1·x2²/Δ²
        ∂X/∂x2 =  D·x1²·y2/Δ²   ∂X/∂y2 = −D·x1²·x2/Δ²

    eq. 6.6::

        ∂Y/∂x1 =  D·x2·y1·y2/Δ²   ∂Y/∂y1 = −D·x1·x2·y2/Δ²
        ∂Y/∂x2 = −D·x1·y1·y2/Δ²   ∂Y/∂y2 =  D·x1·x2·y1/Δ²

    eq. 6.8 with ρ = sqrt(X² + W²), W = Y + D/2, a = f/K and ξ1 of eq. 6.9::

        Z = a·ρ/ξ1
        ∂Z/∂v = a·[(X·∂X/∂v + W·∂Y/∂v)/(ρ·ξ1) − ρ·∂ξ1/∂v/ξ1²],  ∂ξ1/∂x1 = x1/ξ1, ∂ξ1/∂y1 = y1/ξ1
    """
    o = _offsets(offsets)
    x1, y1, x2, y2 = o[:, 0], o[:, 1], o[:, 2], o[:, 3]
    d = float(baseline_mm)
    a = f1_px / mirror_constant
    xyz = thesis_xyz(o, d, f1_px, mirror_constant)
    X, Y = xyz[:, 0], xyz[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        den2 = (x1 * y2 - x2 * y1) ** 2
        jx = (
            np.stack(
                [-x2 * x2 * y1, x1 * x2 * x2, x1 * x1 * y2, -x1 * x1 * x2],
                axis=1,
            )
            * (d / den2)[:, None]
        )
        jy = (
            np.stack(
                [x2 * y1 * y2, -x1 * x2 * y2, -x1 * y1 * y2, x1 * x2 * y1],
                axis=1,
            )
            * (d / den2)[:, None]
        )
        W = Y + d / 2.0
        rho = np.hypot(X, W)
        xi1 = np.hypot(x1, y1)
        dxi = np.column_stack([x1 / xi1, y1 / xi1, np.zeros_like(x1), np.zeros_like(x1)])
        drho = (X[:, None] * jx + W[:, None] * jy) / rho[:, None]
        jz = a * (drho / xi1[:, None] - (rho / (xi1 * xi1))[:, None] * dxi)
    return np.stack([jx, jy, jz], axis=1)


def relative_error(
    offsets: ArrayLike,
    d_pixels: ArrayLike,
    baseline_mm: float,
    f1_px: float,
    mirror_constant: float = MIRROR_CONSTANT_K,
) -> NDArray[np.float64]:
    """Signed first-order relative error dF/F (N, 3) of (X, Y, Z) for pixel errors (N, 4), eq. 6.10.

    ``dF/F = Σ_v (∂F/∂v)/F · dv`` over v = (r1, c1, r2, c2); dimensionless (multiply by 100
    for %). ``d_pixels`` broadcasts against the points (a single (4,) row applies to all).
    """
    o = _offsets(offsets)
    dv = np.broadcast_to(np.asarray(d_pixels, dtype=np.float64), o.shape)
    jac = thesis_jacobian(o, baseline_mm, f1_px, mirror_constant)
    F = thesis_xyz(o, baseline_mm, f1_px, mirror_constant)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.einsum("nab,nb->na", jac, dv) / F


def max_relative_error(
    offsets: ArrayLike,
    abs_d_pixels: ArrayLike,
    baseline_mm: float,
    f1_px: float,
    mirror_constant: float = MIRROR_CONSTANT_K,
) -> NDArray[np.float64]:
    """Largest possible relative error |dF/F| (N, 3) for pixel errors bounded by |dv|, eq. 6.11.

    ``|dF/F| = Σ_v |(∂F/∂v)/F|·|dv|``; dimensionless. ``abs_d_pixels`` (N, 4) or (4,) are the
    bounds on |dr1|, |dc1|, |dr2|, |dc2| in px (e.g. 0.5 for integer rounding).
    """
    o = _offsets(offsets)
    dv = np.abs(np.broadcast_to(np.asarray(abs_d_pixels, dtype=np.float64), o.shape))
    jac = thesis_jacobian(o, baseline_mm, f1_px, mirror_constant)
    F = thesis_xyz(o, baseline_mm, f1_px, mirror_constant)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.einsum("nab,nb->na", np.abs(jac), dv) / np.abs(F)
