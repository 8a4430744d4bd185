"""The free-space map: free area from floor dots, obstacles, drop-off regions, memory under motion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnid.core.classify import with_classes
from omnid.core.freespace import FreeSpaceMap, FreeSpaceSettings, classified
from omnid.core.geometry import StereoRig
from omnid.core.laser import DotPattern
from omnid.core.occupancy import CellState, GridSettings
from omnid.core.types import PointClass, PointCloud
from omnid.errors import ConfigError
from omnid.sim import scenes
from omnid.sim.world import Box, RigMount, World, cast_laser, observe

RIG = StereoRig.nominal()
MOUNT = RigMount(x_offset_mm=300.0, height_mm=1100.0)
RES = 50.0


def scene_cloud(scene: scenes.Scene, seed: int = 0, truth_classes: bool = False):
    hits = cast_laser(scene.world, scene.pose, scene.mount, DotPattern(), RIG)
    cloud, truth = observe(hits, RIG, 0.2, seed, scene.mount.height_mm)
    return classified(cloud, truth) if truth_classes else with_classes(cloud)


def fresh(**kw) -> FreeSpaceMap:
    return FreeSpaceMap(FreeSpaceSettings(**kw))


def test_floor_dots_and_the_area_between_them_are_free():
    m = fresh()
    m.update(scene_cloud(scenes.floor(MOUNT)), MOUNT.x_offset_mm)
    # The lit floor: rig X 330..2310 (x 630..2610 robot), |Y| up to ~1.3 m; probe inside it,
    # on points between dots (dots lie on a 110 mm lattice).
    xs, ys = np.meshgrid(np.arange(700, 2200, 37.0), np.arange(-600, 600, 41.0))
    probe = np.column_stack([xs.ravel(), ys.ravel()])
    assert np.all(m.state_at(probe) == CellState.FREE)
    assert m.nearest_blocking_distance_mm(400.0, 2500.0) == math.inf
    # Behind the chair nothing was seen.
    assert np.all(m.state_at([[-500.0, 0.0], [0.0, 2000.0]]) == CellState.UNKNOWN)
    assert m.nearest_blocking_distance_mm(400.0, 2500.0, unknown_blocks=True) < 700.0


def test_box_ahead_blocks_the_corridor_at_its_near_side():
    # A box 1000..1250 mm ahead of the rig = robot x 1300..1550, across the path.
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    sc = scenes.Scene("box", World((box,)), MOUNT)
    m = fresh()
    m.update(scene_cloud(sc), MOUNT.x_offset_mm)
    d = m.nearest_blocking_distance_mm(300.0, 3000.0)
    assert 1300.0 - RES <= d <= 1300.0 + RES
    assert m.state_at([[1400.0, 0.0]])[0] == CellState.OBSTACLE
    # A corridor to the side of the box is clear; an arc turning into it is not.
    assert m.nearest_blocking_distance_mm(150.0, 3000.0, start_mm=0.0) <= d
    assert m.state_at([[1400.0, -800.0]])[0] == CellState.FREE


def test_map_remembers_an_obstacle_after_the_chair_turns_away():
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    m = fresh()
    m.update(scene_cloud(scenes.Scene("box", World((box,)), MOUNT)), MOUNT.x_offset_mm)
    before = m.nearest_blocking_distance_mm(300.0, 3000.0)
    # Turn 90° left on the spot: the box is now on the right (y < 0), 1300..1550 mm away.
    m.move(0.0, 0.0, math.pi / 2)
    assert m.state_at([[0.0, -1400.0]])[0] == CellState.OBSTACLE
    assert m.nearest_blocking_distance_mm(300.0, 3000.0) == math.inf
    # The laser now sees only empty floor in the new direction: the box is still remembered.
    m.update(scene_cloud(scenes.floor(MOUNT)), MOUNT.x_offset_mm)
    assert m.state_at([[0.0, -1400.0]])[0] == CellState.OBSTACLE
    # Turning back brings it in front again at the same distance.
    m.move(0.0, 0.0, -math.pi / 2)
    assert m.nearest_blocking_distance_mm(300.0, 3000.0) == pytest.approx(before, abs=RES)
    # The robot-frame grid agrees with the exact queries.
    g = m.grid
    xs, ys = g.cell_centers()
    cx, cy = np.meshgrid(xs, ys, indexing="ij")
    exact = m.state_at(np.column_stack([cx.ravel(), cy.ravel()])).reshape(g.states.shape)
    assert np.mean(exact == g.states) > 0.995


def test_many_small_moves_do_not_round_away():
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    m = fresh()
    m.update(scene_cloud(scenes.Scene("box", World((box,)), MOUNT)), MOUNT.x_offset_mm)
    before = m.nearest_blocking_distance_mm(300.0, 3000.0)
    for _ in range(100):  # 100 steps of 8 mm, far below a 50 mm cell
        m.move(8.0, 0.0, 0.0)
    after = m.nearest_blocking_distance_mm(300.0, 3000.0)
    assert after == pytest.approx(before - 800.0, abs=RES)
    for _ in range(150):  # beyond the re-anchoring distance, with a little turning on the way
        m.move(10.0, 0.0, 0.002)
        m.move(0.0, 0.0, -0.002)
    # 1500 mm more forward: the box (near side 1300 mm ahead at the start) is now behind the axle.
    assert m.state_at([[1350.0 - 2300.0, 0.0]])[0] == CellState.OBSTACLE


def test_region_beyond_a_dropoff_edge_is_never_free():
    sc = scenes.dropoff(MOUNT, distance_mm=1000.0)  # edge at robot x = 1300
    m = fresh()
    m.update(scene_cloud(sc), MOUNT.x_offset_mm)
    xs = np.arange(1300.0, 2600.0, 20.0)
    for y in (-400.0, 0.0, 400.0):
        states = m.state_at(np.column_stack([xs, np.full_like(xs, y)]))
        assert not np.any(states == CellState.FREE), y
    # The gap right behind the edge (no dot lands there) reads DROPOFF, not merely unknown.
    gap = m.state_at([[1330.0, 0.0], [1400.0, 0.0], [1450.0, 0.0]])
    assert np.all(gap == CellState.DROPOFF)
    d = m.nearest_blocking_distance_mm(350.0, 3000.0)
    # Blocked at the edge, or up to one dot spacing (110 mm) and a cell before it: conservative.
    assert 1300.0 - 110.0 - RES <= d <= 1300.0 + RES
    assert m.state_at([[1000.0, 0.0]])[0] == CellState.FREE


def test_unseen_cells_keep_their_state_and_seen_cells_are_updated():
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    m = fresh()
    m.update(scene_cloud(scenes.Scene("box", World((box,)), MOUNT)), MOUNT.x_offset_mm)
    m.update(PointCloud(), MOUNT.x_offset_mm)  # empty cloud
    assert m.state_at([[1400.0, 0.0]])[0] == CellState.OBSTACLE
    # The box was taken away and the laser sees bare floor there now.
    m.update(scene_cloud(scenes.floor(MOUNT)), MOUNT.x_offset_mm)
    assert m.state_at([[1400.0, 0.0]])[0] == CellState.FREE


def test_remembered_cells_age_out_when_asked():
    m = fresh(forget_after_s=1.0)
    m.update(scene_cloud(scenes.floor(MOUNT)), MOUNT.x_offset_mm, now_s=10.0)
    assert m.state_at([[1000.0, 0.0]])[0] == CellState.FREE
    m.update(PointCloud(), MOUNT.x_offset_mm, now_s=10.5)
    assert m.state_at([[1000.0, 0.0]])[0] == CellState.FREE
    m.update(PointCloud(), MOUNT.x_offset_mm, now_s=11.6)
    assert m.state_at([[1000.0, 0.0]])[0] == CellState.UNKNOWN


def test_obstacle_inflation_grows_blocked_cells():
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    cloud = scene_cloud(scenes.Scene("box", World((box,)), MOUNT), truth_classes=True)
    plain, fat = fresh(), fresh(obstacle_inflation_mm=150.0)
    plain.update(cloud, MOUNT.x_offset_mm)
    fat.update(cloud, MOUNT.x_offset_mm)
    n_plain = (plain.grid.states == CellState.OBSTACLE).sum()
    n_fat = (fat.grid.states == CellState.OBSTACLE).sum()
    assert n_fat > 2 * n_plain
    assert fat.nearest_blocking_distance_mm(300.0, 3000.0) < plain.nearest_blocking_distance_mm(
        300.0, 3000.0
    )


def test_passage_between_two_obstacles_is_open_but_narrow():
    m = fresh()
    m.update(scene_cloud(scenes.passage(MOUNT, width_mm=900.0)), MOUNT.x_offset_mm)
    assert m.nearest_blocking_distance_mm(300.0, 2500.0) == math.inf  # 600 wide fits in 900
    assert m.nearest_blocking_distance_mm(550.0, 2500.0) < 1100.0  # 1100 wide does not


def test_curved_and_reverse_corridors():
    m = fresh()
    # An obstacle dot placed directly, to the front-left.
    m.update(_obstacle_cloud([[800.0, 800.0]]), 0.0)
    assert m.nearest_blocking_distance_mm(200.0, 3000.0) == math.inf
    # Left turn of radius 800 mm passes (800, 800) after a quarter circle: s = π/2·800 ≈ 1257.
    d = m.nearest_blocking_distance_mm(200.0, 3000.0, curvature_per_mm=1.0 / 800.0)
    assert d == pytest.approx(math.pi / 2 * 800.0, abs=250.0)
    assert m.nearest_blocking_distance_mm(200.0, 3000.0, reverse=True) == math.inf
    m.update(_obstacle_cloud([[-700.0, 0.0]]), 0.0)
    assert m.nearest_blocking_distance_mm(200.0, 3000.0, reverse=True) == pytest.approx(
        700.0, abs=RES
    )


def _obstacle_cloud(xy_robot):
    xy = np.asarray(xy_robot, dtype=np.float64)
    n = len(xy)
    xyz = np.column_stack([xy[:, 0], -xy[:, 1], np.full(n, 800.0)])
    return PointCloud(
        xyz, np.zeros((n, 3, 3)), np.zeros((n, 4)), np.full(n, PointClass.OBSTACLE, np.uint8)
    )


def test_settings_validated_and_blocked_cells_listed():
    with pytest.raises(ConfigError, match="free_max_edge_mm"):
        FreeSpaceSettings(free_max_edge_mm=0.0)
    with pytest.raises(ConfigError, match="resolution_mm"):
        FreeSpaceSettings(grid=GridSettings(resolution_mm=-1.0))
    m = fresh()
    assert m.blocked_xy_mm().shape == (0, 2)
    m.update(_obstacle_cloud([[1000.0, 300.0]]), 0.0)
    np.testing.assert_allclose(m.blocked_xy_mm(), [[1025.0, 325.0]])
    with pytest.raises(ValueError, match="non-finite"):
        m.move(float("nan"), 0.0, 0.0)
