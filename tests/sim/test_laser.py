"""The simulator's physical laser: grating laws, source off the mirror plane, imperfections."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from omnid.core.geometry import StereoRig
from omnid.errors import ConfigError
from omnid.sim.laser import LaserProjector, LaserSpread, ideal_lattice, random_laser
from omnid.sim.rigs import RigSpread, misaligned_rig, random_rig
from omnid.sim.world import Box, RigMount, World, cast_laser

PERFECT = dict(
    skew_rad=0.0, jitter_rad=0.0, missing_fraction=0.0, double_fraction=0.0, roll_rad=0.0
)


def beam_components(p: LaserProjector) -> np.ndarray:
    """Directions of ``p`` in its own beam frame (u, v, w)."""
    return p.rays().directions @ p.beam_frame().T


def test_ideal_lattice_is_the_old_slope_lattice() -> None:
    """Beams from the rig origin, row-major (forward index, lateral index), at the slopes
    (X/Z, Y/Z) = (forward_min_slope + step·l, step·(k − (cols − 1)/2))."""
    for args, depth in (((19, 25, 0.10, 0.30), 1100.0), ((5, 7, 0.2, 0.4), 900.0)):
        rows, cols, step, first = args
        lat = ideal_lattice(*args)
        sx, sy = np.meshgrid(
            first + step * np.arange(rows), step * (np.arange(cols) - (cols - 1) / 2), indexing="ij"
        )
        want = np.column_stack([sx.ravel() * depth, sy.ravel() * depth, np.full(sx.size, depth)])
        np.testing.assert_allclose(lat.on_plane(depth), want, atol=1e-9)
        np.testing.assert_array_equal(lat.rays().brightness, 1.0)
    with pytest.raises(ValueError, match="multiple"):
        ideal_lattice(forward_min_slope=0.25)


@pytest.mark.parametrize("law", ["sine", "angle", "slope"])
def test_grating_laws(law: str) -> None:
    p = LaserProjector(law=law, **PERFECT)  # type: ignore[arg-type]
    d = beam_components(p)
    m, n = p.rays().orders.T
    if law == "sine":  # direction cosines step by λ/d
        a, b = d[:, 0], d[:, 1]
    elif law == "angle":  # angles in the (u, w) and (v, w) planes step uniformly
        a, b = np.arctan2(d[:, 0], d[:, 2]), np.arctan2(d[:, 1], d[:, 2])
    else:  # slopes step uniformly
        a, b = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]
    np.testing.assert_allclose(a, m * p.pitch_u, atol=1e-12)
    np.testing.assert_allclose(b, n * p.pitch_v, atol=1e-12)


def test_only_the_ideal_lattice_is_regular_in_slope_on_the_floor() -> None:
    """A beam axis tilted forward makes every law irregular in slope (X/Z) along a row."""

    def step_ratio(p: LaserProjector) -> float:
        xyz = p.on_plane(1000.0)
        row = p.rays().orders[:, 1] == 0
        steps = np.diff(np.sort(xyz[row, 0] / 1000.0))
        return float(steps.max() / steps.min())

    assert step_ratio(ideal_lattice()) == pytest.approx(1.0)
    for law in ("sine", "angle", "slope"):
        p = LaserProjector(law=law, source_mm=(0.0, 0.0, 0.0), **PERFECT)  # type: ignore[arg-type]
        assert step_ratio(p) > 2.0


def test_source_off_the_mirror_plane_moves_dots_along_lines_through_the_epipole() -> None:
    """SPEC §2: a beam images as a straight line through e_i = (f/K)(−O_X, O_Y − Y_i)/O_Z."""
    src = (12.0, -7.0, -110.0)
    p = LaserProjector(source_mm=src)
    rig = StereoRig.nominal()
    for cam in (rig.cam1, rig.cam2):
        e = cam.f_over_k_px * np.array([-src[0], src[1] - cam.y_mm]) / src[2]
        e = e + np.array([cam.center_row_px, cam.center_col_px])
        tracks = np.stack([cam.project(p.on_plane(z)) for z in (400.0, 700.0, 1100.0)])
        v1 = tracks[0] - e
        v2 = tracks[2] - e
        v3 = tracks[1] - e
        cross13 = v1[:, 0] * v2[:, 1] - v1[:, 1] * v2[:, 0]
        cross23 = v3[:, 0] * v2[:, 1] - v3[:, 1] * v2[:, 0]
        scale = np.linalg.norm(v2, axis=1) ** 2
        assert np.max(np.abs(cross13) / scale) < 1e-9
        assert np.max(np.abs(cross23) / scale) < 1e-9
        # ... and the dots really move (they do not stay on their floor rows).
        assert np.median(np.abs(tracks[0, :, 0] - tracks[2, :, 0])) > 5.0


def test_every_beam_starts_at_the_source() -> None:
    p = LaserProjector(source_mm=(20.0, 15.0, 90.0))
    a, b = p.on_plane(600.0), p.on_plane(1100.0)
    o = np.array(p.source_mm)
    u, w = a - o, b - o
    cross = np.cross(u, w)
    assert np.max(np.linalg.norm(cross, axis=1) / np.linalg.norm(w, axis=1) ** 2) < 1e-12
    assert np.isnan(p.on_plane(50.0)).all()  # above the source: no beam reaches it


def test_imperfections() -> None:
    base = LaserProjector(**PERFECT)
    n_full = len(base.rays())
    missing = dataclasses.replace(base, missing_fraction=0.2, seed=3).rays()
    assert 0.7 * n_full < len(missing) < 0.9 * n_full
    doubled = dataclasses.replace(base, double_fraction=0.1, double_offset_rad=0.008).rays()
    twins = np.flatnonzero(doubled.twin >= 0)
    assert 0.05 * n_full < len(twins) < 0.15 * n_full
    cosang = np.sum(doubled.directions[twins] * doubled.directions[doubled.twin[twins]], axis=1)
    np.testing.assert_allclose(np.arccos(np.clip(cosang, -1, 1)), 0.008, rtol=1e-3)
    assert np.all(doubled.brightness[twins] < doubled.brightness[doubled.twin[twins]])
    # Brightness falls off with the angle from the axis.
    r = base.rays()
    theta = np.arccos(r.directions @ base.beam_frame()[2])
    order = np.argsort(theta)
    assert np.all(np.diff(r.brightness[order]) <= 1e-12)
    # The aperture cuts the orders outside the field.
    d = beam_components(base)
    assert np.max(np.abs(np.arctan2(d[:, 0], d[:, 2]))) <= base.field_rad[0] + 1e-12
    # Jitter and skew move beams off the perfect law.
    jit = dataclasses.replace(base, jitter_rad=0.0005).rays()
    assert 1e-4 < np.median(np.linalg.norm(jit.directions - r.directions, axis=1)) < 1e-3


def test_bad_parameters_are_refused_by_name() -> None:
    with pytest.raises(ConfigError, match="law"):
        LaserProjector(law="hologram")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="pitch_u"):
        LaserProjector(pitch_u=-0.1)
    with pytest.raises(ConfigError, match="source_mm"):
        LaserProjector(source_mm=(0.0, math.nan, 0.0))


def test_random_lasers_cover_the_floor_ahead_and_differ() -> None:
    """Over many draws: every laser lights the floor ahead in both cameras with separable dots,
    and the draws cover the spread (laws, sources above and below the mirror plane)."""
    spread = LaserSpread()
    laws, above, below = set(), 0, 0
    for seed in range(40):
        p = random_laser(seed)
        assert p == random_laser(seed)  # deterministic
        laws.add(p.law)
        x, y, z = p.source_mm
        assert abs(x) <= spread.source_x_mm and abs(y) <= spread.source_y_mm
        assert abs(z) <= spread.source_z_mm
        above += z < -20.0
        below += z > 20.0
        rig = random_rig(seed)
        pix = rig.project(p.on_plane(rig.floor_depth_mm))
        seen = rig.visible(pix)
        assert seen.sum() >= 100
        xs = p.on_plane(rig.floor_depth_mm)[seen, 0] / rig.floor_depth_mm
        assert np.percentile(xs, 5) < 0.6 and np.percentile(xs, 95) > 1.3  # near and far
    assert laws == {"sine", "angle", "slope"}
    assert above >= 8 and below >= 8


def test_random_rig_within_its_spread() -> None:
    nom = StereoRig.nominal()
    sp = RigSpread()
    rigs = [random_rig(s) for s in range(30)]
    for rig in rigs:
        for cam, ref in ((rig.cam1, nom.cam1), (rig.cam2, nom.cam2)):
            assert abs(cam.center_row_px - ref.center_row_px) <= sp.center_px
            assert abs(cam.f_over_k_px / ref.f_over_k_px - 1.0) <= sp.f_over_k_rel
            assert abs(cam.rotation_rad) <= sp.rotation_rad
    rots = [r.cam1.rotation_rad for r in rigs]
    assert max(rots) - min(rots) > sp.rotation_rad  # they really spread
    assert misaligned_rig().cam1.rotation_rad == pytest.approx(math.radians(1.5))


def test_cast_from_an_off_plane_source_lands_on_the_beams() -> None:
    p = LaserProjector(source_mm=(10.0, 20.0, -120.0))
    box = Box(900.0, 1300.0, -400.0, 400.0, 300.0)  # world frame, chair at the origin
    hits = cast_laser(World((box,)), (0.0, 0.0, 0.0), RigMount(), p, misaligned_rig())
    o = np.array(p.source_mm)
    d = (hits.xyz - o) / np.linalg.norm(hits.xyz - o, axis=1, keepdims=True)
    np.testing.assert_allclose(d, p.rays().directions, atol=1e-9)
    on_box = hits.truth == 1
    assert on_box.sum() > 10
    np.testing.assert_allclose(hits.xyz[on_box, 2].min(), 1100.0 - 300.0, atol=1e-6)
    np.testing.assert_allclose(hits.brightness, p.rays().brightness)


def test_the_simulator_casts_and_renders_the_laser_it_is_given() -> None:
    from omnid.sim.course import empty_room
    from omnid.sim.simulator import SimSettings, Simulator

    laser = LaserProjector(source_mm=(5.0, 10.0, -110.0))
    sim = Simulator(empty_room(), None, settings=SimSettings(perception="off"), laser=laser)
    hits = sim.laser_hits((0.0, 0.0, 0.0))
    want = cast_laser(sim.course.world, (0.0, 0.0, 0.0), sim.mount, laser, sim.rig)
    np.testing.assert_allclose(hits.xyz, want.xyz)
    cap = sim.render(laser_on=True, seed=1, pose=(0.0, 0.0, 0.0))
    diff = cap.base1.astype(float) - cap.mask1.astype(float)
    rc = np.rint(hits.pixels[hits.visible1 & sim.rig.cam1.in_disk(hits.pixels[:, :2], 3.0), :2])
    assert np.median(diff[rc[:, 0].astype(int), rc[:, 1].astype(int)]) > 60  # dots where cast
    # the default is a physical, non-ideal laser (issue 9: the learned-laser matcher)
    default = Simulator(empty_room(), None, settings=SimSettings(perception="off")).laser
    assert default == LaserProjector() and default != ideal_lattice()
