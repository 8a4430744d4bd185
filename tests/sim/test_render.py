"""The renderer: truth is the centroid, images are seeded, realistic effects are where expected."""

from __future__ import annotations

import numpy as np

from omnid.core.geometry import StereoRig
from omnid.sim.laser import LaserProjector
from omnid.sim.render import (
    OUTSIDE_DISK_LEVEL,
    RenderOptions,
    draw_spots,
    render_capture,
    visible_truth,
)


def test_spot_centroid_is_the_true_centre_and_mass_is_conserved():
    rng = np.random.default_rng(0)
    pos = np.column_stack([rng.uniform(10, 30, 20), rng.uniform(10, 50, 20)])
    rr, cc = np.mgrid[0:40, 0:60]
    for (r, c), s in zip(pos, rng.uniform(0.8, 2.0, 20), strict=True):
        img = draw_spots((40, 60), [[r, c]], s, 100.0)
        assert abs((img * rr).sum() / img.sum() - r) < 1e-4
        assert abs((img * cc).sum() / img.sum() - c) < 1e-4
        assert abs(img.sum() - 100.0 * 2 * np.pi * s * s) < 1e-3 * img.sum()


def test_spots_off_the_image_and_nan_are_ignored():
    img = draw_spots((10, 10), [[np.nan, 3.0], [-50.0, 5.0], [5.0, 5.0]], 1.0, 50.0)
    assert img.shape == (10, 10)
    assert img.max() > 40
    assert draw_spots((10, 10), np.zeros((0, 2)), 1.0, 1.0).sum() == 0


def test_capture_is_seeded_and_dark_outside_the_disk():
    rig = StereoRig.nominal()
    xyz = LaserProjector().on_plane(rig.floor_depth_mm)
    a = render_capture(rig, xyz, RenderOptions.realistic(), seed=4)
    b = render_capture(rig, xyz, RenderOptions.realistic(), seed=4)
    c = render_capture(rig, xyz, RenderOptions.realistic(), seed=5)
    assert np.array_equal(a.base1, b.base1) and np.array_equal(a.mask2, b.mask2)
    assert not np.array_equal(a.base1, c.base1)
    corner = a.base1[:30, :30].astype(float)
    assert abs(corner.mean() - OUTSIDE_DISK_LEVEL) < 3.0
    centre = a.mask1[200:280, 280:360].astype(float)
    assert 40 < centre.mean() < 100


def test_colour_capture_puts_the_laser_in_green():
    rig = StereoRig.nominal()
    xyz = LaserProjector().on_plane(rig.floor_depth_mm)
    cap = render_capture(rig, xyz, RenderOptions.realistic(color=True), seed=1)
    assert cap.base1.shape == (480, 640, 3)
    diff = cap.base1.astype(float) - cap.mask1.astype(float)
    truth = np.rint(visible_truth(rig.cam1, rig.cam1.project(xyz), 5.0)).astype(int)
    at_dots = diff[truth[:, 0], truth[:, 1]]
    assert at_dots[:, 1].mean() > 80  # green
    assert at_dots[:, 0].mean() < 0.3 * at_dots[:, 1].mean()  # blue: cross-talk only
    assert at_dots[:, 2].mean() < 0.3 * at_dots[:, 1].mean()  # red


def test_flicker_leaves_a_faint_scene_in_the_difference():
    rig = StereoRig.nominal()
    opts = RenderOptions(flicker=0.1, noise_sigma=0.5)
    cap = render_capture(rig, np.zeros((0, 3)), opts, seed=2)
    diff = cap.base1.astype(float) - cap.mask1.astype(float)
    assert 4.0 < diff[200:280, 280:360].mean() < 10.0  # ≈ 0.1 · 70


def test_sensor_noise_has_the_set_sigma_and_is_independent_per_frame_and_seed():
    # Flat scene, no dots: what is left in the disk is the read noise (σ = 3 gray levels).
    rig = StereoRig.nominal()
    opts = RenderOptions(background_texture=0.0, noise_sigma=3.0)
    a = render_capture(rig, np.zeros((0, 3)), opts, seed=7)
    b = render_capture(rig, np.zeros((0, 3)), opts, seed=8)
    inner = (slice(150, 330), slice(230, 410))
    frames = [f[inner].astype(float) - 70.0 for f in (a.mask1, a.base1, a.mask2, b.mask1)]
    for f in frames:
        assert abs(f.std() - 3.0) < 0.1  # rounding to integers adds 1/12 to the variance
        assert abs(f.mean()) < 0.1
    # Mask and base, the two cameras, and two seeds do not share their noise.
    for i in range(len(frames)):
        for j in range(i + 1, len(frames)):
            assert abs(np.corrcoef(frames[i].ravel(), frames[j].ravel())[0, 1]) < 0.02
