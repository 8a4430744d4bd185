"""The thesis formulas (eqs. 6.5, 6.6, 6.8) and their analytic partials (eqs. 6.10, 6.11)."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core.errormodel import (
    max_relative_error,
    relative_error,
    thesis_jacobian,
    thesis_xyz,
)
from omnid.core.geometry import MIRROR_CONSTANT_K, StereoRig
from omnid.core.triangulate import thesis_offsets

D = 200.0
A_PX = 108.3
F1 = A_PX * MIRROR_CONSTANT_K


def _well_conditioned_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points clearly off the plane X = 0 and not right below mirror 1."""
    X = rng.uniform(300.0, 2000.0, n) * rng.choice([-1.0, 1.0], n)
    Y = rng.uniform(-1500.0, 1500.0, n)
    Z = rng.uniform(400.0, 1100.0, n)
    return np.column_stack([X, Y, Z])


def _offsets(rng: np.random.Generator, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    rig = StereoRig.nominal(f_over_k_px=A_PX, baseline_mm=D)
    P = _well_conditioned_points(rng, n)
    return P, thesis_offsets(rig, rig.project(P))


def test_thesis_formulas_invert_the_projection(rng):
    P, off = _offsets(rng)
    np.testing.assert_allclose(thesis_xyz(off, D, F1), P, rtol=1e-9)


def test_jacobian_matches_central_finite_differences(rng):
    _, off = _offsets(rng)
    jac = thesis_jacobian(off, D, F1)
    h = 1e-4  # px; central differences have O(h²) error
    for b in range(4):
        step = np.zeros(4)
        step[b] = h
        fd = (thesis_xyz(off + step, D, F1) - thesis_xyz(off - step, D, F1)) / (2 * h)
        np.testing.assert_allclose(jac[:, :, b], fd, rtol=1e-5, atol=1e-7)


def test_relative_error_eq_6_10_predicts_small_perturbations(rng):
    _, off = _offsets(rng)
    dv = rng.uniform(-0.01, 0.01, off.shape)  # px, small enough for first order
    F = thesis_xyz(off, D, F1)
    actual = (thesis_xyz(off + dv, D, F1) - F) / F
    predicted = relative_error(off, dv, D, F1)
    np.testing.assert_allclose(predicted, actual, rtol=2e-2, atol=1e-7)


def test_max_relative_error_eq_6_11_bounds_every_sign_pattern(rng):
    _, off = _offsets(rng, 50)
    bound = max_relative_error(off, 0.5, D, F1)
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * 4)).reshape(4, -1).T
    worst = np.zeros_like(bound)
    for s in signs:
        worst = np.maximum(worst, np.abs(relative_error(off, 0.5 * s, D, F1)))
    assert np.all(worst <= bound * (1 + 1e-12))
    # The bound is attained by the sign pattern that aligns every term (per axis).
    np.testing.assert_allclose(worst, bound, rtol=1e-12)


def test_rounding_error_stays_within_first_order_bound(rng):
    rig = StereoRig.nominal()
    P = _well_conditioned_points(rng, 300)
    px = rig.project(P)
    off_true = thesis_offsets(rig, px)
    off_round = thesis_offsets(rig, np.rint(px))
    F = thesis_xyz(off_true, D, F1)
    actual = np.abs((thesis_xyz(off_round, D, F1) - F) / F)
    bound = max_relative_error(off_true, 0.5, D, F1)
    # First order: allow 10% plus a small absolute slack for the second-order terms.
    assert np.all(actual <= 1.1 * bound + 1e-3)


def test_partials_blow_up_near_the_baseline_plane():
    # Δ = x1·y2 − x2·y1 = s²·X·D → 0 as X → 0; the largest partials (∂Y/∂r) grow like 1/X.
    rig = StereoRig.nominal()
    near = thesis_offsets(rig, rig.project([[5.0, 300.0, 800.0]]))
    far = thesis_offsets(rig, rig.project([[500.0, 300.0, 800.0]]))
    j_near = np.abs(thesis_jacobian(near, D, F1)).max()
    j_far = np.abs(thesis_jacobian(far, D, F1)).max()
    assert j_near > 20 * j_far  # X is 100x smaller


def test_zero_denominator_gives_non_finite_values_without_warnings():
    off = np.array([[0.0, 10.0, 0.0, -10.0]])  # x1 = x2 = 0: X = 0/0
    with np.errstate(all="raise"):
        xyz = thesis_xyz(off, D, F1)
        jac = thesis_jacobian(off, D, F1)
    assert not np.isfinite(xyz[0, 0])
    assert not np.isfinite(jac).all()


def test_rejects_wrong_shapes():
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        thesis_xyz(np.zeros((3, 3)), D, F1)
    assert thesis_jacobian(np.zeros((0, 4)), D, F1).shape == (0, 3, 4)
