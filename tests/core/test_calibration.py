"""Automatic calibration on synthetic floor captures with known misalignment."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from match_helpers import misaligned_rig

from omnid.core.calibration import Calibration, calibrate_from_capture, fit_mirror_disk
from omnid.core.geometry import StereoRig
from omnid.core.matching import fit_thesis_polynomials, predict_thesis
from omnid.errors import CalibrationError, ConfigError, InputError
from omnid.sim.laser import ideal_lattice
from omnid.sim.render import render_capture

# ideal_lattice(): today's `best` matcher and floor calibration assume the regular slope lattice
# (issue 9: laser-match switches this to a real laser when its matcher lands).

H = 1100.0


@pytest.fixture(scope="module")
def rig() -> StereoRig:
    return misaligned_rig()


@pytest.fixture(scope="module")
def calib(rig: StereoRig) -> Calibration:
    cap = render_capture(rig, ideal_lattice().on_plane(H), seed=1)
    return calibrate_from_capture(cap, H, 200.0)


def test_recovers_centres_scale_and_rotation(rig: StereoRig, calib: Calibration) -> None:
    for got, want in ((calib.rig.cam1, rig.cam1), (calib.rig.cam2, rig.cam2)):
        assert abs(got.center_row_px - want.center_row_px) < 0.2
        assert abs(got.center_col_px - want.center_col_px) < 0.2
        assert abs(got.f_over_k_px / want.f_over_k_px - 1) < 0.003  # 0.3 %
        assert abs(got.rotation_rad - want.rotation_rad) < math.radians(0.1)
        assert abs(got.disk_radius_px - want.disk_radius_px) < 1.0
    assert calib.floor_depth_mm == H
    assert calib.residuals["row_rms_px"] < 0.3
    assert calib.residuals["disparity_rms_px"] < 0.3
    assert calib.residuals["inlier_fraction"] > 0.95
    assert len(calib.control_pairs_px) > 300
    lat = calib.lattice
    assert lat is not None
    assert lat.step_b == pytest.approx(0.1, rel=0.01)  # ideal_lattice's step


def test_disk_fit_on_a_clipped_disk() -> None:
    img = np.full((480, 640), 3, np.uint8)
    rr, cc = np.mgrid[0:480, 0:640]
    img[np.hypot(rr - 250.0, cc - 300.0) <= 240.0] = 80  # clipped at top and bottom
    row, col, rad, rms = fit_mirror_disk(img)
    assert row == pytest.approx(250.0, abs=0.15)
    assert col == pytest.approx(300.0, abs=0.15)
    assert rad == pytest.approx(240.0, abs=0.6)
    assert rms < 1.0


def test_save_load_round_trip(calib: Calibration, tmp_path: Path) -> None:
    path = tmp_path / "calib.yaml"
    calib.save(path)
    data = yaml.safe_load(path.read_text())
    assert data["format_version"] == 1
    back = Calibration.load(path)
    assert back.rig == calib.rig
    np.testing.assert_allclose(back.col_coeffs, calib.col_coeffs)
    np.testing.assert_allclose(back.control_pairs_px, calib.control_pairs_px, atol=1e-3)
    assert back.lattice == calib.lattice
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda d: d["cam1"].__setitem__("f_over_k_px", "big"), "cam1.f_over_k_px"),
        (lambda d: d.pop("floor_depth_mm"), "floor_depth_mm"),
        (lambda d: d.__setitem__("format_version", 7), "format_version"),
        (lambda d: d.__setitem__("col_coeffs", [1.0, 2.0]), "col_coeffs"),
        (lambda d: d["cam2"].__setitem__("f_over_k_px", -3.0), "cam2"),
        (lambda d: d.__setitem__("colour", 1), "colour"),
    ],
)
def test_load_names_the_bad_key(calib: Calibration, tmp_path: Path, edit, key: str) -> None:
    data = calib.to_mapping()
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        Calibration.load(path)
    assert key in str(info.value) and str(path) in str(info.value)


def test_failed_save_leaves_old_file_intact(calib: Calibration, tmp_path: Path) -> None:
    target = tmp_path / "taken"
    target.mkdir()  # a directory cannot be replaced by a file
    with pytest.raises(InputError, match="taken: cannot write"):
        calib.save(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_refuses_capture_without_dots(rig: StereoRig) -> None:
    cap = render_capture(rig, np.zeros((0, 3)), seed=3)
    with pytest.raises(CalibrationError, match="dots"):
        calibrate_from_capture(cap, H, 200.0)


def test_refuses_wrong_depth(rig: StereoRig) -> None:
    cap = render_capture(misaligned_rig(800.0), ideal_lattice().on_plane(800.0), seed=4)
    with pytest.raises(CalibrationError):
        calibrate_from_capture(cap, H, 200.0)  # told 1100 mm, really 800 mm


def test_refuses_a_scene_that_is_not_a_floor(rig: StereoRig) -> None:
    pat = ideal_lattice()
    sl = pat.rays().slopes()
    depth = np.where(sl[:, 1] > 0.0, 820.0, H)  # the right half is a raised platform
    xyz = np.column_stack([sl * depth[:, None], depth])
    with pytest.raises(CalibrationError, match="residuals"):
        calibrate_from_capture(render_capture(rig, xyz, seed=5), H, 200.0)


def test_thesis_polynomials_three_step_refinement() -> None:
    """Eqs. 6.12/6.13 from 20 control pairs reach the other floor dots within 0.3 px."""
    rig = StereoRig.nominal()
    rng = np.random.default_rng(7)
    truth = rig.project(ideal_lattice().on_plane(H))
    truth = truth[rig.visible(truth)]
    noisy = truth + rng.normal(0, 0.1, truth.shape)
    control = noisy[rng.choice(len(noisy), 20, replace=False)]
    poly = fit_thesis_polynomials(control, noisy[:, :2], noisy[:, 2:])
    assert len(poly.pairs_px) > 0.95 * len(truth)
    pred = predict_thesis(poly.row_coeffs, poly.col_coeffs, truth[:, :2])
    assert np.max(np.abs(pred - truth[:, 2:])) < 0.6
    assert poly.col_rms_px < 0.3


def test_floor_angle_tables_match_the_geometry(calib: Calibration, rig: StereoRig) -> None:
    from omnid.core.calibration import floor_angle_tables

    theta1, theta2, delta = floor_angle_tables(calib)
    xyz = ideal_lattice().on_plane(H)
    px = rig.project(xyz)
    vis = rig.visible(px, margin_px=3.0)
    xyz, px = xyz[vis], px[vis]
    r1, c1 = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
    r2, c2 = np.rint(px[:, 2]).astype(int), np.rint(px[:, 3]).astype(int)
    want1 = np.arctan2(xyz[:, 0], xyz[:, 1] + 100.0)
    want2 = np.arctan2(xyz[:, 0], xyz[:, 1] - 100.0)
    want_d = np.arctan(np.hypot(xyz[:, 0], xyz[:, 1] + 100.0) / H)
    # angles read at the rounded pixel: within a pixel’s angular size (~1° at 60 px from centre)
    assert np.median(np.abs(theta1[r1, c1] - want1)) < np.radians(1.0)
    assert np.median(np.abs(theta2[r2, c2] - want2)) < np.radians(1.0)
    assert np.median(np.abs(delta[r1, c1] - want_d)) < np.radians(0.2)
    disk2 = calib.rig.cam2.in_disk(np.argwhere(np.ones((480, 640), bool)).astype(float))
    assert np.isfinite(theta2.ravel()[disk2]).mean() > 0.99  # neighbour averaging filled it
