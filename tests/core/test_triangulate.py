"""Triangulation: both methods invert the projection, the covariance matches the scatter, and the
thesis' ill-conditioning near X = 0 is reported rather than hidden."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.core.triangulate import ray_residual_px, triangulate
from omnid.errors import InputError


def _misaligned_rig() -> StereoRig:
    """Centres off the image middle, different scales and small rotations (what calibration finds)."""
    cam1 = MirrorCamera(236.2, 322.9, -100.0, f_over_k_px=106.9, rotation_rad=0.021)
    cam2 = MirrorCamera(242.7, 315.4, 100.0, f_over_k_px=110.4, rotation_rad=-0.013)
    return StereoRig(cam1, cam2, 1100.0)


def _points(rng: np.random.Generator, n: int, min_abs_x_mm: float = 0.0) -> np.ndarray:
    X = rng.uniform(min_abs_x_mm, 2000.0, n) * rng.choice([-1.0, 1.0], n)
    Y = rng.uniform(-1500.0, 1500.0, n)
    Z = rng.uniform(400.0, 1100.0, n)
    return np.column_stack([X, Y, Z])


def test_thesis_method_inverts_ideal_projection(nominal_rig, rng):
    P = _points(rng, 500, min_abs_x_mm=20.0)
    xyz, cov = triangulate(nominal_rig, nominal_rig.project(P), method="thesis")
    np.testing.assert_allclose(xyz, P, rtol=1e-9, atol=1e-9)
    assert np.isfinite(cov).all()


@pytest.mark.parametrize(
    "rig", [StereoRig.nominal(), _misaligned_rig()], ids=["ideal", "misaligned"]
)
def test_best_method_inverts_projection_everywhere(rig, rng):
    P = _points(rng, 500)
    P[:50, 0] = 0.0  # on the plane beside the baseline, where the thesis formula is 0/0
    xyz, cov = triangulate(rig, rig.project(P), method="best")
    np.testing.assert_allclose(xyz, P, rtol=1e-9, atol=1e-8)
    assert cov.shape == (500, 3, 3)
    assert np.isfinite(cov).all()
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2))  # symmetric
    assert (np.linalg.eigvalsh(cov) > 0).all()


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-2500, 2500),
    y=st.floats(-2500, 2500),
    z=st.floats(200, 3000),
)
def test_best_inverts_projection_property(x, y, z):
    rig = _misaligned_rig()
    xyz, _ = triangulate(rig, rig.project([[x, y, z]]), method="best")
    np.testing.assert_allclose(xyz[0], [x, y, z], rtol=1e-8, atol=1e-7)


def test_thesis_is_undefined_on_the_baseline_plane_and_says_so(nominal_rig):
    # Integer centre makes x1 = x2 = 0 exactly for X = 0: eq. 6.5 is 0/0.
    rig = StereoRig(MirrorCamera(240.0, 320.0, -100.0), MirrorCamera(240.0, 320.0, 100.0), 1100.0)
    xyz, cov = triangulate(rig, rig.project([[0.0, 400.0, 900.0]]), method="thesis")
    assert not np.isfinite(xyz).all()
    assert np.isnan(cov).all()
    best, best_cov = triangulate(rig, rig.project([[0.0, 400.0, 900.0]]), method="best")
    np.testing.assert_allclose(best[0], [0.0, 400.0, 900.0], atol=1e-9)
    assert np.isfinite(best_cov).all()


def test_thesis_is_ill_conditioned_near_the_baseline_plane_best_is_not(nominal_rig):
    P = np.array([[30.0, 400.0, 900.0]])
    px = nominal_rig.project(P) + np.array([0.5, 0.0, 0.0, 0.0])  # half a pixel on r1
    thesis, thesis_cov = triangulate(nominal_rig, px, method="thesis")
    best, best_cov = triangulate(nominal_rig, px, method="best")
    assert np.abs(thesis - P).max() > 100.0  # mm: half a pixel throws it far off
    assert np.abs(best - P).max() < 10.0
    # The covariance flags it: the thesis' predicted spread is far larger than ours.
    assert np.trace(thesis_cov[0]) > 20 * np.trace(best_cov[0])


def test_best_covariance_matches_monte_carlo_scatter(rng):
    rig = _misaligned_rig()
    P = np.array([[900.0, -350.0, 800.0]])
    sigma = 0.3
    px = rig.project(P)
    noisy = px + rng.normal(0.0, sigma, (20000, 4))
    xyz, _ = triangulate(rig, noisy, method="best")
    _, cov = triangulate(rig, px, method="best", pixel_sigma_px=sigma)
    emp = np.cov(xyz.T)
    # 20000 samples: the sample variance is within a few % of the truth; first order adds ~1%.
    np.testing.assert_allclose(np.diag(emp), np.diag(cov[0]), rtol=0.08)
    corr_emp = emp[0, 2] / math.sqrt(emp[0, 0] * emp[2, 2])
    corr = cov[0, 0, 2] / math.sqrt(cov[0, 0, 0] * cov[0, 2, 2])
    assert abs(corr_emp - corr) < 0.05


def test_thesis_covariance_matches_monte_carlo_scatter(nominal_rig, rng):
    P = np.array([[900.0, -350.0, 800.0]])
    sigma = 0.1
    px = nominal_rig.project(P)
    xyz, _ = triangulate(nominal_rig, px + rng.normal(0.0, sigma, (20000, 4)), method="thesis")
    _, cov = triangulate(nominal_rig, px, method="thesis", pixel_sigma_px=sigma)
    np.testing.assert_allclose(np.var(xyz, axis=0), np.diag(cov[0]), rtol=0.08)


def test_best_scatter_is_smaller_than_thesis_scatter(nominal_rig, rng):
    P = _points(rng, 400, min_abs_x_mm=200.0)
    px = nominal_rig.project(P) + rng.normal(0.0, 0.5, (400, 4))
    err_thesis = np.abs(triangulate(nominal_rig, px, method="thesis")[0] - P).mean(axis=0)
    err_best = np.abs(triangulate(nominal_rig, px, method="best")[0] - P).mean(axis=0)
    assert np.all(err_best < err_thesis)


def test_points_behind_the_mirrors_give_nan(nominal_rig):
    px = nominal_rig.project([[500.0, 0.0, 800.0]])
    swapped = px[:, [2, 3, 0, 1]]  # negative disparity: the rays meet above the mirror plane
    xyz, cov = triangulate(nominal_rig, swapped, method="best")
    assert np.isnan(xyz).all()
    assert np.isnan(cov).all()


def test_ray_residual_zero_for_true_pairs_and_measures_row_disagreement(nominal_rig, rng):
    px = nominal_rig.project(_points(rng, 100))
    np.testing.assert_allclose(ray_residual_px(nominal_rig, px), 0.0, atol=1e-9)
    shifted = px + np.array([0.0, 0.0, 3.0, 0.0])
    np.testing.assert_allclose(ray_residual_px(nominal_rig, shifted), 3.0 / math.sqrt(2.0))
    # Column errors only change the depth, never the residual (one redundant equation: rows).
    np.testing.assert_allclose(
        ray_residual_px(nominal_rig, px + np.array([0.0, 2.0, 0.0, -1.0])), 0.0, atol=1e-9
    )
    # Under isotropic noise σ the residual is σ·|N(0,1)|: mean square σ².
    sigma = 0.4
    res = ray_residual_px(_misaligned_rig(), _misaligned_rig().project(_points(rng, 20000)))
    assert res.max() < 1e-8
    noisy = _misaligned_rig().project(_points(rng, 20000)) + rng.normal(0, sigma, (20000, 4))
    ms = float(np.mean(ray_residual_px(_misaligned_rig(), noisy) ** 2))
    assert ms == pytest.approx(sigma**2, rel=0.05)


def test_vectorised_equals_point_by_point(nominal_rig, rng):
    px = nominal_rig.project(_points(rng, 20, min_abs_x_mm=100.0)) + rng.normal(0, 0.3, (20, 4))
    for method in ("thesis", "best"):
        xyz, cov = triangulate(nominal_rig, px, method=method)
        for i in range(len(px)):
            xi, ci = triangulate(nominal_rig, px[i], method=method)
            np.testing.assert_allclose(xi[0], xyz[i], rtol=1e-12)
            np.testing.assert_allclose(ci[0], cov[i], rtol=1e-12)


def test_empty_input_and_bad_input(nominal_rig):
    for method in ("thesis", "best"):
        xyz, cov = triangulate(nominal_rig, np.zeros((0, 4)), method=method)
        assert xyz.shape == (0, 3) and cov.shape == (0, 3, 3)
    assert ray_residual_px(nominal_rig, np.zeros((0, 4))).shape == (0,)
    with pytest.raises(InputError, match=r"\(N, 4\)"):
        triangulate(nominal_rig, np.zeros((5, 3)))
    with pytest.raises(InputError, match="pixel_sigma_px"):
        triangulate(nominal_rig, np.zeros((1, 4)), pixel_sigma_px=-1.0)
    with pytest.raises(ValueError, match="unknown triangulation method"):
        triangulate(nominal_rig, np.zeros((1, 4)), method="magic")  # type: ignore[arg-type]
