"""Laser ray casting in the simulated world: known answers for floor, boxes, occlusion, drop-offs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnid.core.geometry import StereoRig
from omnid.core.types import PointClass
from omnid.errors import ConfigError, InputError
from omnid.sim import scenes
from omnid.sim.laser import LaserProjector, LaserRays
from omnid.sim.world import (
    Box,
    DropOff,
    RigMount,
    World,
    cast_laser,
    rig_to_world,
    world_to_rig,
)

H = 1100.0
MOUNT = RigMount(x_offset_mm=300.0, height_mm=H)
RIG = StereoRig.nominal(floor_depth_mm=H)


LASER = LaserProjector()  # a real laser: source 90 mm above the mirror plane, axis tilted


def one_ray(slope_x: float) -> LaserRays:
    """The single beam (X/Z, Y/Z) = (slope_x, 0) from the rig origin."""
    d = np.array([[slope_x, 0.0, 1.0]]) / np.hypot(slope_x, 1.0)
    return LaserRays(np.zeros(3), d, np.ones(1), np.zeros((1, 2), np.int64), np.full(1, -1))


def test_bare_floor_dots_lie_on_their_rays_at_floor_depth():
    hits = cast_laser(World(), (0.0, 0.0, 0.0), MOUNT, LASER, RIG)
    assert len(hits) == len(LASER.rays())
    np.testing.assert_allclose(hits.xyz, LASER.on_plane(H), atol=1e-6)
    assert np.all(hits.truth == PointClass.FLOOR)
    # Most of the pattern is inside both mirror disks; the far corners are not.
    assert 0.8 * len(hits) < hits.visible.sum() < len(hits)
    np.testing.assert_allclose(hits.pixels, RIG.project(hits.xyz))


def test_box_top_at_known_height():
    # Ray slope 1.0: at depth Z it is X = Z ahead. A 300 mm box spanning X 700..900 catches it
    # at depth 800 mm, i.e. X = 800.
    box = Box(700 + 300, 900 + 300, -100, 100, 300.0)
    hits = cast_laser(World((box,)), (0, 0, 0), MOUNT, one_ray(1.0), RIG)
    np.testing.assert_allclose(hits.xyz[0], [800.0, 0.0, 800.0], atol=1e-6)
    assert hits.truth[0] == PointClass.OBSTACLE
    assert hits.visible1[0] and hits.visible2[0]


def test_box_side_hit_and_wall_scene():
    # A wall 550 mm ahead: a ray of slope 1.0 meets it at X = 550, Z = 550 (h = 550).
    sc = scenes.vertical_plane(550.0, MOUNT)
    hits = cast_laser(sc.world, sc.pose, sc.mount, one_ray(1.0), RIG)
    np.testing.assert_allclose(hits.xyz[0], [550.0, 0.0, 550.0], atol=1e-6)
    assert hits.truth[0] == PointClass.OBSTACLE
    full = cast_laser(sc.world, sc.pose, sc.mount, LASER, RIG)
    on_wall = full.truth == PointClass.OBSTACLE
    assert on_wall.sum() > 20
    np.testing.assert_allclose(full.xyz[on_wall, 0], 550.0, atol=1e-6)
    # Beams steep enough to reach the floor before X = 550 stay on the floor; only beams
    # passing beside the 2000 mm wide wall (|Y| > 1000 where they cross X = 550) reach farther.
    rays = LASER.rays()
    t = (550.0 - rays.origin_mm[0]) / rays.directions[:, 0]
    y_at_wall = rays.origin_mm[1] + t * rays.directions[:, 1]
    beside = np.abs(y_at_wall) > 1000.0
    assert np.all(full.xyz[~on_wall & ~beside, 0] <= 550.0 + 1e-6)


@pytest.mark.parametrize("depth", scenes.HORIZONTAL_PLANE_DEPTHS_MM)
def test_table_7_4_horizontal_planes(depth):
    sc = scenes.horizontal_plane(depth, MOUNT)
    hits = cast_laser(sc.world, sc.pose, sc.mount, LASER, RIG)
    top = np.isclose(hits.xyz[:, 2], depth)
    assert top.sum() > 60
    if depth < H:
        assert np.all(hits.truth[top] == PointClass.OBSTACLE)
        assert np.all(hits.xyz[top, 0] >= scenes.HORIZONTAL_PLANE_NEAR_MM - 1e-6)


def test_occlusion_between_dot_and_one_mirror():
    # Floor dot of the ray slope 1.0: P = (1100, 0, 1100). The sight line to mirror 1
    # (0, -100, 0) passes (550, -50, 550) halfway; a thin post there hides P from mirror 1 only,
    # while the laser ray itself (Y = 0) passes 50 mm beside the post.
    post_rig = (530.0, 570.0, -70.0, -30.0)  # X range, rig Y range
    post = Box(
        post_rig[0] + 300, post_rig[1] + 300, -post_rig[3], -post_rig[2], height_mm=H - 400.0
    )
    hits = cast_laser(World((post,)), (0, 0, 0), MOUNT, one_ray(1.0), RIG)
    np.testing.assert_allclose(hits.xyz[0], [1100.0, 0.0, 1100.0], atol=1e-6)
    assert hits.truth[0] == PointClass.FLOOR
    assert not hits.visible1[0]
    assert hits.visible2[0]
    # Without the post both mirrors see it.
    free = cast_laser(World(), (0, 0, 0), MOUNT, one_ray(1.0), RIG)
    assert free.visible1[0] and free.visible2[0]


def test_dropoff_depth_and_truth():
    sc = scenes.dropoff(MOUNT, distance_mm=1000.0)
    hits = cast_laser(sc.world, sc.pose, sc.mount, one_ray(1.5), RIG)
    # Slope 1.5: the floor would be met at X = 1650 > 1000, so the dot falls 200 mm lower.
    np.testing.assert_allclose(hits.xyz[0], [1.5 * (H + 200), 0.0, H + 200.0], atol=1e-6)
    assert hits.truth[0] == PointClass.DROPOFF
    near = cast_laser(sc.world, sc.pose, sc.mount, one_ray(0.5), RIG)
    np.testing.assert_allclose(near.xyz[0], [550.0, 0.0, H], atol=1e-6)
    assert near.truth[0] == PointClass.FLOOR


def test_dot_on_far_wall_of_a_trench():
    # Trench 200 mm deep from X 1000 to 1100: the slope-1.0 ray enters at X=1100? No — it meets
    # the floor level at X = 1100, the trench's far edge, so use slope 0.95: floor level at
    # X = 1045 inside the trench, then the far wall X = 1100 at Z = 1100/0.95 ≈ 1157.9.
    pit = DropOff(1000 + 300, 1100 + 300, -500, 500, 200.0)
    hits = cast_laser(World((), (pit,)), (0, 0, 0), MOUNT, one_ray(0.95), RIG)
    np.testing.assert_allclose(hits.xyz[0], [1100.0, 0.0, 1100.0 / 0.95], atol=1e-6)
    assert hits.truth[0] == PointClass.DROPOFF


def test_pit_bottom_hidden_by_the_side_edge_from_one_mirror():
    # A pit whose side edge runs at rig Y = -20: the sight line from the bottom dot
    # (1400, 0, 1500) to mirror 1 (0, -100, 0) crosses floor level at Y = -26.7, i.e. through the
    # ground beside the edge; the line to mirror 2 stays inside the pit. World y = -rig Y.
    pit = DropOff(800 + 300, 2000 + 300, -300, 20, 400.0)
    hits = cast_laser(World((), (pit,)), (0, 0, 0), MOUNT, one_ray(1.0), RIG)
    assert hits.truth[0] == PointClass.DROPOFF
    np.testing.assert_allclose(hits.xyz[0, 2], H + 400.0, atol=1e-6)
    assert not hits.visible1[0]
    assert hits.visible2[0]


def test_pose_rotation_and_translation_keep_rig_frame_hits():
    # The same box, seen from a chair turned by 90 degrees and moved, gives the same rig hits.
    box = Box(900, 1200, -200, 200, 250.0)
    a = cast_laser(World((box,)), (0, 0, 0), MOUNT, LASER, RIG)
    th = math.pi / 2
    pose = (500.0, -300.0, th)
    # Box corners rotated by +90 degrees about the origin ((x, y) -> (-y, x)), then shifted.
    rbox = Box(500 - 200, 500 + 200, -300 + 900, -300 + 1200, 250.0)
    b = cast_laser(World((rbox,)), pose, MOUNT, LASER, RIG)
    np.testing.assert_allclose(a.xyz, b.xyz, atol=1e-6)
    np.testing.assert_array_equal(a.truth, b.truth)
    np.testing.assert_array_equal(a.visible1, b.visible1)


def test_frame_transforms_invert_each_other(rng):
    pts = rng.uniform(-2000, 2000, (50, 3))
    pose = (123.0, -45.0, 0.7)
    back = world_to_rig(rig_to_world(pts, pose, MOUNT), pose, MOUNT)
    np.testing.assert_allclose(back, pts, atol=1e-9)
    # The rig origin sits x_offset ahead of the axle, H above the floor, and rig Y is the right.
    w = rig_to_world([[0, 0, 0], [0, 100, H]], (0, 0, 0), MOUNT)
    np.testing.assert_allclose(w, [[300, 0, H], [300, -100, 0]])


def test_settings_are_checked_and_scenes_are_named():
    with pytest.raises(ConfigError, match="height_mm"):
        Box(0, 1, 0, 1, -5.0)
    with pytest.raises(ConfigError, match="x_max_mm"):
        DropOff(5, 1, 0, 1, 100.0)
    with pytest.raises(InputError, match="nowhere"):
        scenes.get_scene("nowhere")
    for name in scenes.scene_names():
        sc = scenes.get_scene(name)
        hits = cast_laser(sc.world, sc.pose, sc.mount, LASER, RIG)
        assert hits.visible.sum() > 150, name
    sc = scenes.get_scene("passage")
    hits = cast_laser(sc.world, sc.pose, sc.mount, LASER, RIG)
    assert {PointClass.FLOOR, PointClass.OBSTACLE} <= set(hits.truth.tolist())
