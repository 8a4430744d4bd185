"""Floor / obstacle / drop-off classification on ray-cast clouds with realistic pixel noise."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core.classify import ClassifySettings, classify, floor_band_mm, with_classes
from omnid.core.geometry import StereoRig
from omnid.core.types import PointClass, PointCloud
from omnid.errors import ConfigError
from omnid.sim import scenes
from omnid.sim.laser import LaserProjector, random_laser
from omnid.sim.world import cast_laser, observe

RIG = StereoRig.nominal()
#: Sub-pixel dot centres: 0.2 px standard deviation per image coordinate (σ_Z ≈ 15 mm at the floor).
PIXEL_SIGMA_PX = 0.2


def _runs(method: str = "best"):
    """(true heights, truth, predicted) over every named scene, five lasers drawn at random
    and one noise seed each."""
    for seed in range(5):
        laser = random_laser(seed)
        for name in scenes.scene_names():
            sc = scenes.get_scene(name)
            hits = cast_laser(sc.world, sc.pose, sc.mount, laser, RIG)
            true_h = sc.mount.height_mm - hits.xyz[hits.visible, 2]
            cloud, truth = observe(hits, RIG, PIXEL_SIGMA_PX, seed, sc.mount.height_mm, method)
            yield name, true_h, truth, classify(cloud)


def test_classification_is_right_on_distinguishable_dots_and_never_calls_tall_things_floor():
    total = wrong = total_all = wrong_all = 0
    for name, true_h, truth, pred in _runs():
        # Dots low on a box side (true h < 60 mm, ~4 σ) are floor-level within the noise: no
        # classifier can tell them apart, so they are counted only in the overall figure.
        distinguishable = (truth == PointClass.FLOOR) | (np.abs(true_h) >= 60.0)
        total += int(distinguishable.sum())
        wrong += int((distinguishable & (pred != truth)).sum())
        total_all += len(truth)
        wrong_all += int((pred != truth).sum())
        # Safety: nothing 120 mm above or below the floor is ever free.
        tall = np.abs(true_h) >= 120.0
        assert not np.any(pred[tall] == PointClass.FLOOR), name
    assert total > 15_000
    assert wrong / total <= 0.01, f"{wrong} of {total} distinguishable dots misclassified"
    assert wrong_all / total_all <= 0.02, f"{wrong_all} of {total_all} dots misclassified"


def test_thesis_triangulation_covariance_classifies_nearly_as_well():
    # The thesis closed form (3 of 4 coordinates, eqs. 6.5-6.9) with its error model (6.10-6.11).
    total = wrong = 0
    for _name, true_h, truth, pred in _runs("thesis"):
        distinguishable = (truth == PointClass.FLOOR) | (np.abs(true_h) >= 60.0)
        total += int(distinguishable.sum())
        wrong += int((distinguishable & (pred != truth)).sum())
    assert wrong / total <= 0.01


def test_dropoff_and_floor_dots_of_the_dropoff_scene():
    sc = scenes.dropoff()
    hits = cast_laser(sc.world, sc.pose, sc.mount, LaserProjector(), RIG)
    cloud, truth = observe(hits, RIG, PIXEL_SIGMA_PX, 7, sc.mount.height_mm)
    pred = classify(cloud)
    assert (truth == PointClass.DROPOFF).sum() > 30
    assert np.mean(pred == truth) >= 0.99


def _cloud(h_mm, sigma_z_mm, floor_depth_mm=1100.0):
    h = np.asarray(h_mm, dtype=np.float64)
    n = len(h)
    xyz = np.column_stack([np.full(n, 800.0), np.zeros(n), floor_depth_mm - h])
    cov = np.zeros((n, 3, 3))
    cov[:, 2, 2] = np.asarray(sigma_z_mm, dtype=np.float64) ** 2
    return PointCloud(xyz, cov, np.zeros((n, 4)), np.zeros(n, np.uint8), floor_depth_mm)


def test_band_follows_each_points_uncertainty_not_one_threshold():
    s = ClassifySettings(sigma_factor=3.0, floor_tolerance_mm=10.0, max_band_mm=200.0)
    # Same height 50 mm: a precise point (σ 5 mm, band 25) is an obstacle, an uncertain one
    # (σ 20 mm, band 70) is floor.
    pred = classify(_cloud([50.0, 50.0, -50.0, -50.0], [5.0, 20.0, 5.0, 20.0]), s)
    assert pred.tolist() == [
        PointClass.OBSTACLE,
        PointClass.FLOOR,
        PointClass.DROPOFF,
        PointClass.FLOOR,
    ]
    np.testing.assert_allclose(floor_band_mm(_cloud([0.0, 0.0], [5.0, 20.0]), s), [25.0, 70.0])


def test_band_is_capped_and_nan_covariance_uses_the_default_sigma():
    s = ClassifySettings(sigma_factor=3.0, floor_tolerance_mm=10.0, default_sigma_mm=10.0)
    # σ 200 mm would give a 610 mm band; the 120 mm cap makes a 130 mm point an obstacle.
    assert classify(_cloud([130.0], [200.0]), s)[0] == PointClass.OBSTACLE
    cloud = _cloud([30.0, 50.0], [1.0, 1.0])
    nan_cov = PointCloud(cloud.xyz, np.full((2, 3, 3), np.nan), cloud.pixels, cloud.classes, 1100.0)
    assert classify(nan_cov, s).tolist() == [PointClass.FLOOR, PointClass.OBSTACLE]


def test_uncertain_points_never_become_free_beyond_the_cap():
    s = ClassifySettings(max_band_mm=80.0)
    assert classify(_cloud([100.0, -100.0], [500.0, 500.0]), s).tolist() == [
        PointClass.OBSTACLE,
        PointClass.DROPOFF,
    ]


def test_empty_and_nonfinite_inputs():
    assert classify(PointCloud()).shape == (0,)
    assert classify(PointCloud()).dtype == np.uint8
    bad = _cloud([0.0], [5.0])
    bad.xyz[0, 2] = np.nan
    assert classify(bad)[0] == PointClass.OBSTACLE
    c = with_classes(_cloud([0.0, 300.0], [5.0, 5.0]))
    assert c.classes.tolist() == [PointClass.FLOOR, PointClass.OBSTACLE]


def test_settings_are_validated():
    with pytest.raises(ConfigError, match="sigma_factor"):
        ClassifySettings(sigma_factor=-1.0)
    with pytest.raises(ConfigError, match="max_band_mm"):
        ClassifySettings(max_band_mm=0.0)
