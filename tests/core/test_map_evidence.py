"""What the map believes: the chair's trail, forgetting by travel, drop-offs and obstacles that
need evidence, exact obstacle points for the sweep, and rays that carve phantoms away."""

from __future__ import annotations

import math

import numpy as np

from omnid.core.classify import with_classes
from omnid.core.freespace import FreeSpaceMap, FreeSpaceSettings, classified
from omnid.core.geometry import StereoRig
from omnid.core.occupancy import CellState
from omnid.core.types import PointClass, PointCloud
from omnid.sim.laser import ideal_lattice
from omnid.sim.world import Box, DropOff, RigMount, World, cast_laser, observe

RIG = StereoRig.nominal()
LASER = ideal_lattice()
MOUNT = RigMount(x_offset_mm=300.0, height_mm=1100.0)
H = MOUNT.height_mm


def capture(world: World, seed: int = 0, pose=(0.0, 0.0, 0.0)) -> PointCloud:
    hits = cast_laser(world, pose, MOUNT, LASER, RIG)
    cloud, _truth = observe(hits, RIG, 0.2, seed, H)
    return with_classes(cloud)


def points(xyz, classes) -> PointCloud:
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    n = len(xyz)
    return PointCloud(
        xyz=xyz,
        cov=np.broadcast_to(np.eye(3) * 4.0, (n, 3, 3)).copy(),
        pixels=np.zeros((n, 4)),
        classes=np.asarray(classes, np.uint8),
        floor_depth_mm=H,
    )


def test_the_trail_is_free_and_nothing_else_is_at_start_up():
    m = FreeSpaceMap()
    assert m.occupy(-750.0, 350.0, -350.0, 350.0) > 0
    inside = np.array([[x, y] for x in range(-725, 350, 50) for y in range(-325, 350, 50)])
    assert np.all(m.state_at(inside) == CellState.FREE)
    beside = np.array([[0.0, 400.0], [0.0, -400.0], [-800.0, 0.0], [400.0, 0.0]])
    assert np.all(m.state_at(beside) == CellState.UNKNOWN)
    # a remembered obstacle under the footprint stays (the trail only claims the unseen)
    m.update(points([[200.0, 0.0, H - 300.0]] * 3, [PointClass.OBSTACLE] * 3), 0.0)
    m.update(points([[200.0, 0.0, H - 300.0]] * 3, [PointClass.OBSTACLE] * 3), 0.0)
    m.move(10.0, 0.0, 0.0)
    m.occupy(-750.0, 350.0, -350.0, 350.0)
    assert m.state_at([[190.0, 0.0]])[0] == CellState.OBSTACLE
    # the trail follows the chair
    m.move(500.0, 0.0, 0.0)
    m.occupy(-750.0, 350.0, -350.0, 350.0)
    assert m.state_at([[300.0, 0.0]])[0] == CellState.FREE


def test_remembered_cells_are_forgotten_after_the_travel_odometry_can_hold():
    m = FreeSpaceMap(FreeSpaceSettings(forget_after_travel_mm=3000.0))
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    cloud = capture(World((box,)))
    m.update(cloud, MOUNT.x_offset_mm)
    m.update(capture(World((box,)), seed=1), MOUNT.x_offset_mm)
    assert m.state_at([[1400.0, 0.0]])[0] == CellState.OBSTACLE
    for _ in range(20):  # 2 m forward and back twice: 4 m of travel, the box never seen again
        m.move(100.0 if _ % 10 < 5 else -100.0, 0.0, 0.0)
    m.update(PointCloud(floor_depth_mm=H), MOUNT.x_offset_mm)
    assert m.state_at([[1400.0, 0.0]])[0] == CellState.OBSTACLE  # 2 m: kept
    for _ in range(20):
        m.move(100.0 if _ % 10 < 5 else -100.0, 0.0, 0.0)
    m.update(PointCloud(floor_depth_mm=H), MOUNT.x_offset_mm)
    assert m.state_at([[1400.0, 0.0]])[0] == CellState.UNKNOWN  # 4 m: forgotten, not free


def test_an_obstacle_or_a_drop_off_needs_two_captures_in_a_row():
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    stairs = DropOff(1800.0, 4000.0, -3000.0, 3000.0, 170.0)
    world = World((box,), (stairs,))
    m = FreeSpaceMap()
    m.update(capture(world), MOUNT.x_offset_mm)
    probe = [[1400.0, 0.0], [2300.0, 600.0]]
    assert list(m.state_at(probe)) == [CellState.UNKNOWN, CellState.UNKNOWN]  # in doubt
    assert m.state_at([[1000.0, 0.0]])[0] == CellState.FREE
    m.update(capture(world, seed=1), MOUNT.x_offset_mm)
    assert list(m.state_at(probe)) == [CellState.OBSTACLE, CellState.DROPOFF]


def test_a_lone_drop_off_dot_is_no_evidence_a_consistent_cluster_is():
    floor = capture(World())
    m = FreeSpaceMap(FreeSpaceSettings(dropoff_confirm_captures=1))
    # one dot far below the floor among floor dots: a wrong pairing, not a hole
    xyz = floor.xyz.copy()
    cls = floor.classes.copy()
    k = int(np.argmin(np.abs(xyz[:, 0] - 1000.0) + np.abs(xyz[:, 1])))
    xyz[k] *= 1.3  # along its ray, 330 mm below the floor
    cls[k] = PointClass.DROPOFF
    m.update(classified(floor.__class__(xyz, floor.cov, floor.pixels, cls, H), cls), 300.0)
    assert not np.any(m.grid.states == CellState.DROPOFF)
    # a real edge: every dot beyond it lowered by 170 mm, consistently
    stairs = DropOff(1700.0, 4000.0, -3000.0, 3000.0, 170.0)
    m.update(capture(World((), (stairs,))), MOUNT.x_offset_mm)
    assert m.state_at([[2200.0, 0.0]])[0] == CellState.DROPOFF


def test_a_narrow_trench_between_seen_floor_is_a_drop_off_in_two_captures():
    # 150 mm wide, 150 mm deep: floor is seen on both sides of every ray that falls into it, so
    # one capture cannot tell it from a little cluster of phantoms; two captures in a row can
    trench = DropOff(1500.0, 1650.0, -3000.0, 3000.0, 150.0)
    world = World((), (trench,))
    m = FreeSpaceMap()
    m.update(capture(world, seed=0), MOUNT.x_offset_mm)
    m.update(capture(world, seed=1), MOUNT.x_offset_mm)
    across = np.array([[1575.0, y] for y in range(-300, 301, 100)])
    assert np.mean(m.state_at(across) == CellState.DROPOFF) >= 0.8
    assert not np.any(m.state_at(across) == CellState.FREE)
    # the floor before it stays free
    assert np.all(m.state_at([[1000.0, 0.0], [1000.0, 200.0]]) == CellState.FREE)


def test_blocking_evidence_gives_the_seen_obstacle_points_exactly():
    wall = Box(1500.0, 1600.0, -2000.0, 2000.0, 1000.0)  # robot x 1500: its face
    m = FreeSpaceMap()
    for seed in (0, 1):
        m.update(capture(World((wall,)), seed=seed), MOUNT.x_offset_mm)
    xy, grow, drop = m.blocking_evidence()
    exact = grow == 0.0
    assert exact.sum() > 10 and not np.any(drop)
    # the points lie on the face (to the triangulation noise), not on cell centres
    face = xy[exact]
    assert np.all(np.abs(face[:, 0] - 1500.0) < 40.0)
    assert len(np.unique(np.round(face[:, 0]))) > 20  # not quantised to cells
    # moved exactly with the chair (no resampling): 237 mm forward and 0.3 rad left
    m.move(237.0, 0.0, 0.0)
    m.move(0.0, 0.0, 0.3)
    xy2, grow2, _ = m.blocking_evidence()
    back = xy2[grow2 == 0.0]
    c, s = math.cos(0.3), math.sin(0.3)
    world_x = 237.0 + c * back[:, 0] - s * back[:, 1]
    assert np.all(np.abs(world_x - 1500.0) < 40.0)
    # and through a re-anchoring
    for _ in range(12):
        m.move(100.0, 0.0, 0.0)
    assert np.all(m.grid.states.shape)  # resampled grid still there
    # kept (one per 10 mm lattice site: a re-anchored lattice may merge a few neighbours)
    assert len(m.obstacle_points) >= 0.9 * len(face)


def test_a_ray_through_a_kept_phantom_carves_it_a_real_box_stays():
    m = FreeSpaceMap(FreeSpaceSettings(obstacle_confirm_captures=1))
    # a phantom: one dot on a ray of the lattice, half way to the floor
    floor = capture(World())
    k = int(np.argmin(np.abs(floor.xyz[:, 0] - 1100.0) + np.abs(floor.xyz[:, 1])))
    phantom = floor.xyz[k] * 0.5
    m.update(points([phantom], [PointClass.OBSTACLE]), MOUNT.x_offset_mm)
    spot = [[phantom[0] + MOUNT.x_offset_mm, -phantom[1]]]
    assert m.state_at(spot)[0] == CellState.OBSTACLE
    m.update(floor, MOUNT.x_offset_mm)  # that ray reached the floor: it passed right through
    assert m.state_at(spot)[0] != CellState.OBSTACLE
    assert len(m.obstacle_points) == 0
    # a real box: the rays that reach it end on it, none passes through its points
    box = Box(1300.0, 1550.0, -200.0, 200.0, 250.0)
    for seed in range(3):
        m.update(capture(World((box,)), seed=seed), MOUNT.x_offset_mm)
    assert m.state_at([[1310.0, 0.0]])[0] == CellState.OBSTACLE
    assert len(m.obstacle_points) > 5


def test_a_phantom_between_the_mirrors_and_the_nearest_dots_is_carved_too():
    """A phantom on the steepest rays 380 mm ahead of the axle (the footprint's front margin,
    nearer than any dot lands) stopped the chair at clearance 0 for as long as it stood: the
    carving looked only near the dots, and a phantom patch's fill (cells with no dot of their
    own) outlived its carved dots. The rays pass through them on their way to the floor."""
    m = FreeSpaceMap()
    floor = capture(World())
    near = np.argsort(floor.xyz[:, 0] + 0.3 * np.abs(floor.xyz[:, 1]))[:3]
    ph = np.array([floor.xyz[k] * ((380.0 - MOUNT.x_offset_mm) / floor.xyz[k, 0]) for k in near])
    for _ in range(2):  # confirmed (two captures in a row)
        m.update(points(ph, [PointClass.OBSTACLE] * 3), MOUNT.x_offset_mm)
    spot = np.column_stack([ph[:, 0] + MOUNT.x_offset_mm, -ph[:, 1]])
    assert np.all(m.state_at(spot) == CellState.OBSTACLE)
    m.update(floor, MOUNT.x_offset_mm)
    assert np.all(m.state_at(spot) != CellState.OBSTACLE)
    assert len(m.obstacle_points) == 0
    # a phantom patch on the two nearest lattice rows: the fill between its dots (no dot of its
    # own, nothing else clears it there) goes with the dots that made it
    m = FreeSpaceMap()
    rx = floor.xyz[:, 0] + MOUNT.x_offset_mm
    patch = floor.xyz[(rx < rx.min() + 150.0) & (np.abs(floor.xyz[:, 1]) < 250.0)] * 0.6
    for _ in range(2):
        m.update(points(patch, [PointClass.OBSTACLE] * len(patch)), MOUNT.x_offset_mm)
    assert np.count_nonzero(m.grid.states == CellState.OBSTACLE) > len(patch)  # filled between
    m.update(floor, MOUNT.x_offset_mm)
    assert np.count_nonzero(m.grid.states == CellState.OBSTACLE) == 0


def test_a_cell_seen_again_keeps_its_recent_points_not_only_the_latest_captures():
    # Dots on one obstacle cell: two captures (an obstacle needs two) at its near side, the
    # next 40 mm farther back (the dots fall anywhere on a face). The near edge must stay where it was
    # seen until the chair has travelled point_memory_travel_mm; then the newest view wins.
    def face(x_mm: float) -> PointCloud:
        return points([[x_mm, y, H - 300.0] for y in (-10.0, 0.0, 10.0)], [PointClass.OBSTACLE] * 3)

    def nearest_mm(m: FreeSpaceMap) -> float:
        xy, grow, _ = m.blocking_evidence()
        return float(xy[grow == 0.0, 0].min())

    res = FreeSpaceSettings().grid.resolution_mm
    near_x = 20 * res + 5.0
    far_x = near_x + res - 10.0
    for memory_mm, after_two in ((400.0, near_x), (0.0, far_x)):
        m = FreeSpaceMap(FreeSpaceSettings(point_memory_travel_mm=memory_mm))
        i, j, _ = m._anchor.cell_index(np.array([[near_x, 0.0], [far_x, 0.0]]))
        assert i[0] == i[1] and j[0] == j[1]  # one cell
        m.update(face(near_x), 0.0)
        m.update(face(near_x), 0.0)
        m.update(face(far_x), 0.0)
        assert abs(nearest_mm(m) - after_two) < 1e-6, memory_mm
    # beyond the memory's travel the latest capture replaces what the cell had
    m.move(2 * res, 0.0, 0.0)
    m.move(400.0, 0.0, 0.0)
    m.update(face(far_x - 400.0 - 2 * res), 0.0)
    assert abs(nearest_mm(m) - (far_x - 400.0 - 2 * res)) < 1e-6


def _registered_pose(world: World, seed: int, odometry_error, register_mm: float = 30.0):
    """The map's pose after two captures at the start, a 200 mm drive ahead that the odometry
    gets wrong by ``odometry_error`` (dx, dy mm, dθ rad), and a capture from the true pose."""
    m = FreeSpaceMap(FreeSpaceSettings(register_max_step_mm=register_mm))
    for k in range(2):  # an obstacle is kept once two captures saw it
        m.update(capture(world, 3 * seed + k), MOUNT.x_offset_mm)
    ex, ey, eth = odometry_error
    m.move(200.0 + ex, ey, eth)
    m.update(capture(world, 3 * seed + 2, pose=(200.0, 0.0, 0.0)), MOUNT.x_offset_mm)
    return m.pose_in_anchor, m.registration


def test_registration_corrects_the_odometry_from_the_dots_over_seeds():
    """A wall ahead and one beside fix the chair's position and heading: each capture's dots,
    aligned with the points the map kept, undo the odometry's error (14 mm and 0.6° here) to
    within 5 mm and 0.1° (the dots themselves scatter ±20 mm in depth at 1.8 m)."""
    world = World(boxes=(Box(1800.0, 1900.0, -1500.0, 1500.0, 1000.0),
                         Box(700.0, 1800.0, 450.0, 550.0, 1000.0)))  # fmt: skip
    fixed = 0
    for seed in range(10):
        (x, y, th), reg = _registered_pose(world, seed, (-8.0, 12.0, math.radians(0.6)))
        fixed += reg.applied and abs(x - 200.0) < 5.0 and abs(y) < 3.0 and abs(th) < 0.002
    assert fixed >= 9, fixed
    (x, y, th), _ = _registered_pose(world, 0, (-8.0, 12.0, math.radians(0.6)), register_mm=0.0)
    assert (x, y) == (192.0, 12.0)  # without registration the odometry's pose stands


def test_registration_leaves_what_the_dots_cannot_tell_and_refuses_large_jumps():
    """A single wall across the way fixes the distance to it and the heading, not the position
    along it: that stays as the odometry had it (20 mm off), while the distance is corrected
    (10 mm) and the heading (0.5°) to within 0.3°. A correction larger than
    ``register_max_step_mm`` is a wrong pairing: not applied."""
    wall = World(boxes=(Box(1800.0, 1900.0, -1500.0, 1500.0, 1000.0),))
    ok = 0
    for seed in range(10):
        (x, y, th), reg = _registered_pose(wall, seed, (10.0, 20.0, math.radians(0.5)))
        ok += reg.applied and abs(x - 200.0) < 5.0 and abs(y - 20.0) < 1.0 and abs(th) < 0.005
    assert ok >= 9, ok
    (x, y, _), reg = _registered_pose(wall, 0, (25.0, 0.0, math.radians(2.0)))  # 2°: 35 mm
    assert not reg.applied and reg.pairs > 0 and (x, y) == (225.0, 0.0)
