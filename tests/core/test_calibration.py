"""Automatic calibration of the rig and the laser on synthetic captures with known answers."""

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
from omnid.experiments import rigs as ev
from omnid.sim.installation import installation_captures, render_world
from omnid.sim.laser import LaserProjector
from omnid.sim.render import render_capture
from omnid.sim.world import Box, RigMount, World

H = 1100.0
LASER = LaserProjector()


@pytest.fixture(scope="module")
def rig() -> StereoRig:
    return misaligned_rig()


@pytest.fixture(scope="module")
def captures(rig: StereoRig):
    return installation_captures(rig, LASER, seed=1)


@pytest.fixture(scope="module")
def calib(rig: StereoRig, captures) -> Calibration:
    floor, extras = captures
    return calibrate_from_capture(floor, H, 200.0, extras=list(extras.values()))


def test_recovers_centres_scale_rotation_and_the_laser(rig, calib) -> None:
    for got, want in ((calib.rig.cam1, rig.cam1), (calib.rig.cam2, rig.cam2)):
        assert abs(got.center_row_px - want.center_row_px) < 0.2
        assert abs(got.center_col_px - want.center_col_px) < 0.2
        assert abs(got.f_over_k_px / want.f_over_k_px - 1) < 0.003  # 0.3 %
        assert abs(got.rotation_rad - want.rotation_rad) < math.radians(0.1)
    r = calib.residuals
    assert r["row_rms_px"] < 0.3 and r["disparity_rms_px"] < 0.3 and r["inlier_fraction"] > 0.95
    las = calib.laser
    assert las is not None and las.source_known
    assert math.dist(las.source_mm, LASER.source_mm) < 2.0  # the source, mm
    assert all(0 < s < 5.0 for s in las.source_sigma_mm)
    # every beam the floor shows: each true floor dot seen by a camera is a calibrated beam
    true_floor = LASER.on_plane(H)
    d = np.hypot(*(las.floor_mm[:, None, :2] - true_floor[None, :, :2]).transpose(2, 0, 1))
    assert np.median(d.min(axis=1)) < 1.0  # mm
    assert r["extra_matched_fraction"] > 0.8 and r["extra_track_rms_px"] < 0.2


def test_calibration_over_random_rigs_and_lasers(random_installations) -> None:
    """Rates over 10 random rigs (cameras ±6 px, f/K ±4 %, roll ±1.5°; random lasers, one with
    its source near the mirror plane, one in it with a grid uniform in angle): every one
    calibrates, and the source comes out within 2 mm on at least 9 of 10."""
    errors = [
        math.dist(cal.laser.source_mm, case.laser.source_mm)  # type: ignore[attr-defined]
        for case, cal in random_installations
    ]
    assert len(errors) == 10 and sum(e < 2.0 for e in errors) >= 9, errors


def test_in_plane_source_with_a_grid_uniform_in_angle_calibrates() -> None:
    """The case the lattice calibration refused (inlier fraction 0.53)."""
    case = ev.rig_case(9, seed=0)
    assert case.kind == "in_plane_angle"
    cal = ev.calibrate_case(case, seed=0)
    assert cal.residuals["inlier_fraction"] > 0.9  # type: ignore[attr-defined]
    assert abs(cal.laser.source_mm[2]) < 2.0  # type: ignore[attr-defined]


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
    assert data["format_version"] == 2
    back = Calibration.load(path)
    assert back.rig == calib.rig
    np.testing.assert_allclose(back.col_coeffs, calib.col_coeffs)
    np.testing.assert_allclose(back.control_pairs_px, calib.control_pairs_px, atol=1e-3)
    assert back.laser is not None and calib.laser is not None
    np.testing.assert_allclose(back.laser.floor_mm, calib.laser.floor_mm, atol=1e-3)
    assert back.laser.source_mm == calib.laser.source_mm and back.laser.source_known
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_an_older_calibration_file_says_recalibrate(calib: Calibration, tmp_path: Path) -> None:
    data = calib.to_mapping()
    data["format_version"] = 1
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="recalibrate") as info:
        Calibration.load(path)
    assert len(str(info.value).splitlines()) == 1


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda d: d["cam1"].__setitem__("f_over_k_px", "big"), "cam1.f_over_k_px"),
        (lambda d: d.pop("floor_depth_mm"), "floor_depth_mm"),
        (lambda d: d.__setitem__("format_version", 7), "format_version"),
        (lambda d: d.__setitem__("col_coeffs", [1.0, 2.0]), "col_coeffs"),
        (lambda d: d["cam2"].__setitem__("f_over_k_px", -3.0), "cam2"),
        (lambda d: d.__setitem__("colour", 1), "colour"),
        (lambda d: d["laser"].__setitem__("floor_sigma_mm", [1.0]), "laser.floor_sigma_mm"),
        (lambda d: d["laser"].__setitem__("source_mm", [0, 0, 5000.0]), "laser"),
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


def test_refuses_wrong_depth() -> None:
    floor, _ = installation_captures(misaligned_rig(800.0), LASER, seed=4)
    with pytest.raises(CalibrationError):
        calibrate_from_capture(floor, H, 200.0)  # told 1100 mm, really 800 mm


def test_refuses_a_scene_that_is_not_a_floor(rig: StereoRig) -> None:
    m = RigMount()
    platform = Box(m.x_offset_mm + 200, m.x_offset_mm + 3000, -3000.0, 0.0, 280.0)  # left half
    cap = render_world(rig, LASER, World((platform,)), m, seed=5)
    with pytest.raises(CalibrationError, match="residuals|pair"):
        calibrate_from_capture(cap, H, 200.0)


def test_floor_alone_leaves_the_source_unknown(rig, captures) -> None:
    cal = calibrate_from_capture(captures[0], H, 200.0)
    assert cal.laser is not None and not cal.laser.source_known


def test_refuses_extras_that_show_nothing_off_the_floor(rig, captures) -> None:
    floor, _ = captures
    with pytest.raises(CalibrationError, match="off the floor"):
        calibrate_from_capture(floor, H, 200.0, extras=[floor])


def test_thesis_polynomials_three_step_refinement() -> None:
    """Eqs. 6.12/6.13 from 20 control pairs reach the other floor dots within 0.6 px."""
    rig = StereoRig.nominal()
    rng = np.random.default_rng(7)
    truth = rig.project(LASER.on_plane(H))
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
    xyz = LASER.on_plane(H)
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
