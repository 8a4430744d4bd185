"""The rectilinear mirror model against SPEC §2's closed forms and its own inverse."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from omnid.core.geometry import MIRROR_CONSTANT_K, MirrorCamera, StereoRig
from omnid.sim.laser import LaserProjector, ideal_lattice


def test_mirror_constant_matches_thesis():
    assert pytest.approx(11.34259, abs=2e-4) == MIRROR_CONSTANT_K


def test_projection_closed_form(nominal_rig):
    p = np.array([[500.0, 150.0, 1100.0]])
    r1, c1, r2, c2 = nominal_rig.project(p)[0]
    s = nominal_rig.cam1.f_over_k_px / 1100.0
    assert r1 - nominal_rig.cam1.center_row_px == pytest.approx(-s * 500.0)
    assert c1 - nominal_rig.cam1.center_col_px == pytest.approx(s * (150.0 + 100.0))
    assert c2 - nominal_rig.cam2.center_col_px == pytest.approx(s * (150.0 - 100.0))
    # rows agree, disparity depends on depth only
    assert r1 == pytest.approx(r2)
    assert (c2 - c1) == pytest.approx(-nominal_rig.cam1.f_over_k_px * 200.0 / 1100.0)


def test_rays_pass_through_the_point(rng):
    cam = MirrorCamera(231.0, 322.0, -100.0, 104.0, math.radians(3.0))
    pts = np.column_stack(
        [rng.uniform(-900, 900, 50), rng.uniform(-900, 900, 50), rng.uniform(400, 1200, 50)]
    )
    slopes = cam.ray_slopes(cam.project(pts))
    np.testing.assert_allclose(slopes[:, 0] * pts[:, 2], pts[:, 0], atol=1e-9)
    np.testing.assert_allclose(slopes[:, 1] * pts[:, 2], pts[:, 1] - cam.y_mm, atol=1e-9)


def test_incidence_angle_follows_eq_6_8():
    cam = MirrorCamera(240.0, 320.0, 0.0)
    # a pixel ξ px from the centre: tan δ = K ξ / f = ξ / (f/K)
    delta = cam.incidence_angle([[240.0 - 54.15, 320.0]])[0]
    assert math.tan(delta) == pytest.approx(54.15 / cam.f_over_k_px)


def test_points_at_or_above_mirror_have_no_image(nominal_rig):
    rc = nominal_rig.cam1.project([[100.0, 0.0, 0.0], [100.0, 0.0, -5.0]])
    assert np.isnan(rc).all()


def test_disk_visibility(nominal_rig):
    cam = nominal_rig.cam1
    inside = cam.in_disk(
        [
            [cam.center_row_px, cam.center_col_px],
            [cam.center_row_px - cam.disk_radius_px - 1, cam.center_col_px],
        ]
    )
    assert inside.tolist() == [True, False]


def test_laser_rows_do_not_depend_on_depth_only_for_a_source_in_the_mirror_plane(nominal_rig):
    """SPEC §2's special case: from a source on the baseline in the mirror plane a dot keeps
    its image row at every depth; from a source above the plane it does not."""
    pattern = ideal_lattice()
    near = nominal_rig.project(pattern.on_plane(500.0))
    far = nominal_rig.project(pattern.on_plane(1100.0))
    np.testing.assert_allclose(near[:, 0], far[:, 0])
    np.testing.assert_allclose(near[:, 2], far[:, 2])
    assert not np.allclose(near[:, 1], far[:, 1])
    real = LaserProjector(source_mm=(0.0, 0.0, -90.0))
    near = nominal_rig.project(real.on_plane(500.0))
    far = nominal_rig.project(real.on_plane(1100.0))
    assert np.median(np.abs(near[:, 0] - far[:, 0])) > 5.0


def test_invalid_camera_is_refused():
    with pytest.raises(ValueError):
        MirrorCamera(240.0, 320.0, 0.0, f_over_k_px=-1.0)
    cam = MirrorCamera(240.0, 320.0, -100.0)
    with pytest.raises(ValueError):
        StereoRig(cam, replace(cam, y_mm=-150.0))
