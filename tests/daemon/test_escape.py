"""Escape moves: a chair in a pocket may creep out by moves that open the gap, never into a box.

Default footprint (front 350, rear 750, width 700 mm, margin 50 mm); 25 mm cells. Escapes are
off by default (``escape_speed_mm_s: 0``, main's stop rule); these tests switch them on at the
proposed 40 mm/s.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnid.core.occupancy import CellState, GridSettings, OccupancyGrid
from omnid.daemon.safety import Reason, SafetyLayer, SafetySettings

# the escape rule per twist: softening (which checks other twists by the same rules) off
S = SafetySettings(escape_speed_mm_s=40.0, soften=False)
SMALL = GridSettings(
    resolution_mm=25.0, x_min_mm=-1500.0, x_max_mm=1500.0, y_min_mm=-1500.0, y_max_mm=1500.0
)
Rect = tuple[float, float, float, float]  # x0, x1, y0, y1 (mm)


def rasterize(boxes: list[Rect], pose: tuple[float, float, float] = (0.0, 0.0, 0.0)):
    """A free robot-frame grid for the chair at ``pose`` (world), cells whose centre lies in a
    world box marked OBSTACLE."""
    g = OccupancyGrid(SMALL)
    g.states[:] = CellState.FREE
    xs, ys = g.cell_centers()
    cx, cy = np.meshgrid(xs, ys, indexing="ij")
    x, y, th = pose
    wx = x + math.cos(th) * cx - math.sin(th) * cy
    wy = y + math.sin(th) * cx + math.cos(th) * cy
    for x0, x1, y0, y1 in boxes:
        g.states[(wx >= x0) & (wx <= x1) & (wy >= y0) & (wy <= y1)] = CellState.OBSTACLE
    return g


# the pocket: a box over the front-left corner, inside the margin (gap 37.5 mm to the nearest
# cell centre), one behind the right rear (62.5 mm), one ahead on the right (112.5 mm)
POCKET: list[Rect] = [
    (375.0, 600.0, 250.0, 600.0),
    (-1000.0, -800.0, -500.0, -150.0),
    (450.0, 700.0, -500.0, -250.0),
]


def test_pocket_turning_or_reversing_away_creeps_driving_into_a_box_is_refused():
    g = rasterize(POCKET)
    layer = SafetyLayer(S)
    for v, w in [(200.0, 0.0), (150.0, 0.4), (150.0, -0.4), (-100.0, 0.0), (0.0, -0.5)]:
        d = layer.check(g, v, w, perception_age_s=0.1)
        assert d.stopped and Reason.OBSTACLE_STOP in d.reasons, (v, w, d)
    for v, w in [(0.0, 0.5), (-100.0, 0.3)]:
        d = layer.check(g, v, w, perception_age_s=0.1)
        assert not d.stopped and Reason.ESCAPE in d.reasons, (v, w, d)
        assert Reason.OBSTACLE_STOP not in d.reasons
        assert abs(d.v_mm_s) <= S.escape_speed_mm_s + 1e-9
        assert abs(d.omega_rad_s) <= S.escape_turn_rad_s + 1e-9
        assert d.v_mm_s * v >= 0 and d.omega_rad_s * w >= 0  # the rider's path, only slower


def test_escape_keeps_the_other_rules():
    g = rasterize(POCKET)
    layer = SafetyLayer(S)
    stale = layer.check(g, -100.0, 0.3, perception_age_s=None)
    assert Reason.ESCAPE in stale.reasons  # reversing away needs no fresh map ...
    assert layer.check(g, 150.0, 0.4, perception_age_s=None).stopped  # ... forward does
    off = SafetyLayer(SafetySettings())  # the default: no escapes, main's stop rule
    assert off.check(g, 0.0, 0.5, perception_age_s=0.1).stopped
    drop = rasterize([])
    xs, ys = drop.cell_centers()
    # a drop-off edge over the front-left corner, inside the margin: backing off it is allowed,
    # any move whose first contact is the drop-off stays a drop-off refusal
    drop.states[np.ix_(xs > 375.0, ys > 250.0)] = CellState.DROPOFF
    d = layer.check(drop, 100.0, 0.0, perception_age_s=0.1)
    assert d.stopped and d.reasons == (Reason.DROPOFF_STOP,)


def test_wall_ahead_still_stops_forward_at_the_stop_distance():
    g = rasterize([(450.0, 600.0, -1000.0, 1000.0)])  # 100 mm ahead of the bumper
    d = SafetyLayer(S).check(g, 200.0, 0.0, perception_age_s=0.1)
    assert d.stopped and d.reasons == (Reason.OBSTACLE_STOP,)


def footprint_distance(boxes: list[Rect], pose: tuple[float, float, float]) -> float:
    """True distance (mm) from the chair (no margin) at ``pose`` to the nearest box: box
    outlines sampled every 2 mm, each point's distance from the rotated footprint rectangle."""
    x, y, th = pose
    best = math.inf
    for x0, x1, y0, y1 in boxes:
        nx, ny = int((x1 - x0) / 2) + 1, int((y1 - y0) / 2) + 1
        bx = np.concatenate([np.linspace(x0, x1, nx)] * 2 + [np.full(ny, x0), np.full(ny, x1)])
        by = np.concatenate([np.full(nx, y0), np.full(nx, y1)] + [np.linspace(y0, y1, ny)] * 2)
        c, s = math.cos(th), math.sin(th)
        rx, ry = c * (bx - x) + s * (by - y), -s * (bx - x) + c * (by - y)
        ex = np.maximum(np.maximum(-S.footprint_rear_mm - rx, rx - S.footprint_front_mm), 0.0)
        ey = np.maximum(np.abs(ry) - 0.5 * S.footprint_width_mm, 0.0)
        best = min(best, float(np.hypot(ex, ey).min()))
    return best


def drive(boxes: list[Rect], v: float, w: float, layer: SafetyLayer, length_mm: float):
    """Follow the command along its path in 5 mm steps of the fastest footprint point while the
    safety layer (on a grid rasterized at each pose) allows it: poses visited, last decision."""
    u = abs(v) + abs(w) * layer.r_max_mm
    pose = (0.0, 0.0, 0.0)
    poses = [pose]
    decision = None
    for _ in range(int(length_mm / 5.0)):
        decision = layer.check(rasterize(boxes, pose), v, w, perception_age_s=0.1)
        if decision.stopped:
            break
        x, y, th = pose
        ds, dth = 5.0 * v / u, 5.0 * w / u
        mid = th + 0.5 * dth  # exact enough for 5 mm steps
        pose = (x + ds * math.cos(mid), y + ds * math.sin(mid), th + dth)
        poses.append(pose)
    return poses, decision


def test_random_pockets_an_allowed_escape_never_takes_the_margin_along_200_mm():
    """Random boxes around the chair, random commands; for each one the safety layer first
    allows as an escape, the chair follows it (re-checked every 5 mm on the grid rasterized at
    its new pose, as the control loop re-checks each cycle on the odometry-moved map) for up to
    200 mm; the reference is the true geometry (box outlines, 2 mm). Asserted: the true gap
    never falls below min(its start value, margin) by more than a cell's half-diagonal (the
    grid only knows cell centres: a box edge may lie up to 17.7 mm nearer than its first
    centre) plus 1 mm. At least a few escapes must occur, and some must also be refused."""
    rng = np.random.default_rng(5)
    layer = SafetyLayer(S)
    tol = 0.5 * SMALL.resolution_mm * math.sqrt(2.0) + 1.0
    escapes = refused = 0
    for _ in range(40):
        boxes: list[Rect] = []
        for _ in range(rng.integers(2, 5)):
            # a box near one side of the chair, its near face 20-140 mm from the footprint
            side = rng.integers(4)
            gap = rng.uniform(20.0, 140.0)
            along = rng.uniform(-900.0, 500.0) if side < 2 else rng.uniform(-500.0, 300.0)
            size = rng.uniform(100.0, 400.0, 2)
            if side == 0:  # front
                x0 = S.footprint_front_mm + gap
                boxes.append((x0, x0 + size[0], along, along + size[1]))
            elif side == 1:  # rear
                x1 = -S.footprint_rear_mm - gap
                boxes.append((x1 - size[0], x1, along, along + size[1]))
            elif side == 2:  # left
                y0 = 0.5 * S.footprint_width_mm + gap
                boxes.append((along, along + size[0], y0, y0 + size[1]))
            else:  # right
                y1 = -0.5 * S.footprint_width_mm - gap
                boxes.append((along, along + size[0], y1 - size[1], y1))
        g = rasterize(boxes)
        for v, w in [(150.0, 0.0), (-100.0, 0.0), (0.0, 0.5), (0.0, -0.5)] + [
            (float(rng.uniform(-100.0, 200.0)), float(rng.uniform(-0.6, 0.6))) for _ in range(3)
        ]:
            d = layer.check(g, v, w, perception_age_s=0.1)
            if Reason.ESCAPE not in d.reasons:
                refused += d.stopped
                continue
            escapes += 1
            d0 = footprint_distance(boxes, (0.0, 0.0, 0.0))
            poses, _ = drive(boxes, v, w, layer, 200.0)
            worst = min(footprint_distance(boxes, p) for p in poses[1:]) if len(poses) > 1 else d0
            assert worst >= min(d0, S.margin_mm) - tol, (boxes, v, w, d0, worst, len(poses))
    assert escapes >= 10 and refused >= 10, (escapes, refused)


@pytest.mark.parametrize("bad", [{"escape_speed_mm_s": -1.0}, {"escape_step_mm": 0.0}])
def test_escape_settings_are_validated(bad):
    from omnid.errors import ConfigError

    with pytest.raises(ConfigError):
        SafetySettings(**bad)
