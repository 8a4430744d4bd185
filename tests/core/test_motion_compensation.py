"""Motion between frames (omnid.core.motion_compensation): wheel travel between clock edges, the
chair's motion, the floor's image motion, and the compensated mask."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnid.core.geometry import StereoRig
from omnid.core.kinematics import integrate_arc
from omnid.core.motion_compensation import (
    compensated_mask,
    disk_mask,
    floor_motion_affine,
    moved_rig_points,
    relative_motion,
    warp_image,
    wheel_travel_mm,
)
from omnid.sim.rigs import misaligned_rig

MM_PER_CLOCK = 471.0 / 15.0


def _replies(
    speed_l: float, speed_r: float, seconds: float, period_s: float = 0.02, t0: float = 0.0
):
    """(N, 3) t_s, left, right clock counters of a chair whose wheels turn at constant speeds
    (mm/s), reported every ``period_s`` (whole clocks, as the control unit counts them)."""
    t = t0 + np.arange(0.0, seconds, period_s)
    left = np.floor(speed_l * (t - t0) / MM_PER_CLOCK + 0.37)
    right = np.floor(speed_r * (t - t0) / MM_PER_CLOCK + 0.61)
    return np.column_stack([t, left, right])


def test_travel_between_clock_edges_is_interpolated_to_a_few_mm():
    """At 240 mm/s a clock (31.4 mm) passes every 131 ms; replies every 20 ms place each edge
    within 10 ms, so the travel at any moment is known to ~2.4 mm, not to a whole clock."""
    rep = _replies(240.0, 240.0, 3.0)
    q = np.linspace(0.5, 2.9, 200)
    travel = wheel_travel_mm(q, rep[:, 0], rep[:, 1], MM_PER_CLOCK)
    truth = 240.0 * q + (0.37 - 1.0) * MM_PER_CLOCK + MM_PER_CLOCK  # counter offset at t = 0
    err = (travel - travel[0]) - (truth - truth[0])
    assert np.max(np.abs(err)) < 6.0


def test_travel_stops_short_of_the_next_clock_when_the_wheel_stops():
    rep = _replies(200.0, 200.0, 1.0)
    still = np.column_stack(
        [np.arange(1.0, 3.0, 0.02), np.full(100, rep[-1, 1]), np.full(100, rep[-1, 2])]
    )
    rep = np.vstack([rep, still])
    a, b = wheel_travel_mm(np.array([2.0, 2.9]), rep[:, 0], rep[:, 1], MM_PER_CLOCK)
    assert a == pytest.approx(b)  # standing: no motion between two times
    assert wheel_travel_mm(np.array([-1.0]), rep[:, 0], rep[:, 1], MM_PER_CLOCK)[0] == 0.0


@pytest.mark.parametrize("vl, vr", [(240.0, 240.0), (160.0, 240.0), (-120.0, 120.0)])
def test_relative_motion_is_the_exact_arc_of_the_wheels(vl, vr):
    rep = _replies(vl, vr, 3.0)
    t0, t1 = 1.23, 1.49
    dx, dy, dth = relative_motion(t0, t1, rep, MM_PER_CLOCK, 560.0)
    dl, dr = vl * (t1 - t0), vr * (t1 - t0)
    expect = integrate_arc(np.zeros(3), dl, dr, 560.0)
    assert dx == pytest.approx(expect[0], abs=8.0)
    assert dy == pytest.approx(expect[1], abs=3.0)
    assert dth == pytest.approx(expect[2], abs=0.02)
    assert relative_motion(0.0, 1.0, np.zeros((0, 3)), MM_PER_CLOCK, 560.0) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    "rig", [StereoRig.nominal(), misaligned_rig()], ids=["nominal", "misaligned"]
)
@pytest.mark.parametrize("motion", [(60.0, 0.0, 0.0), (20.0, 5.0, 0.04), (0.0, 0.0, -0.08)])
def test_the_floor_moves_in_the_image_by_the_affine_map_of_the_chairs_motion(rig, motion):
    """Floor points seen before the motion land, under the map, where they are seen after it."""
    rng = np.random.default_rng(3)
    H = rig.floor_depth_mm
    pts = np.column_stack(
        [rng.uniform(-800, 1500, 50), rng.uniform(-1200, 1200, 50), np.full(50, H)]
    )
    for cam in (rig.cam1, rig.cam2):
        A = floor_motion_affine(cam, motion, 300.0, H)
        before = cam.project(pts)[:, ::-1]
        after = cam.project(moved_rig_points(pts, motion, 300.0))[:, ::-1]
        mapped = before @ A[:, :2].T + A[:, 2]
        np.testing.assert_allclose(mapped, after, atol=1e-3)  # px (float32 fit)


def test_a_moved_texture_is_compensated_and_the_disk_edge_stays():
    """A textured floor shifted by the motion: the warped mask matches the later frame (to the
    interpolation), the dark housing around the disk is not moved into it."""
    rig = StereoRig.nominal()
    cam = rig.cam1
    rows, cols = cam.image_shape
    rr, cc = np.mgrid[0:rows, 0:cols].astype(np.float64)
    s = cam.f_over_k_px / rig.floor_depth_mm

    def floor_image(shift_mm: float) -> np.ndarray:  # world x under each pixel, moved back
        x = -(rr - cam.center_row_px) / s + shift_mm
        y = (cc - cam.center_col_px) / s
        img = 90 + 40 * np.sin(x / 37.0) * np.cos(y / 53.0)
        disk = disk_mask(cam, 0.0) == 255
        return np.where(disk, img, 3.0).round().astype(np.uint8)

    earlier, later = floor_image(0.0), floor_image(40.0)  # the chair drove 40 mm forward
    disk = disk_mask(cam)
    A = floor_motion_affine(cam, (40.0, 0.0, 0.0), 300.0, rig.floor_depth_mm)
    warped = warp_image(earlier, A, disk)
    inner = disk_mask(cam, 12.0) == 255
    raw = np.abs(later.astype(int) - earlier)[inner].mean()
    comp = np.abs(later.astype(int) - warped)[inner].mean()
    assert comp < 0.1 * raw and comp < 1.0
    outside = disk == 0
    assert np.array_equal(warped[outside], earlier[outside])


def test_the_brighter_of_two_masks_covers_an_edge_that_moved_either_way():
    base = np.zeros((40, 40), np.uint8)
    base[:, 20:] = 200  # an edge at column 20 in the base
    before, after = np.zeros_like(base), np.zeros_like(base)
    before[:, 18:] = 200  # seen 2 px to one side before ...
    after[:, 22:] = 200  # ... and 2 px to the other after (parallax)
    m = compensated_mask([before, after], [None, None])
    assert np.all(m >= base)  # base − mask leaves no bright residue
    single = compensated_mask([after], [np.array([[1.0, 0, 0], [0, 1.0, 0]])])
    assert single[0, 21] == 200  # one moved mask: grey-dilated by a pixel
    assert np.array_equal(compensated_mask([base], [None]), base)
    with pytest.raises(ValueError):
        compensated_mask([], [])
    assert math.isclose(float(disk_mask(rig_cam := StereoRig.nominal().cam1).max()), 255.0)
    assert disk_mask(rig_cam).shape == rig_cam.image_shape
