"""Chair dynamics against closed forms (straight line, arc, spin), clocks, collisions and falls."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest

from omnid.errors import ConfigError
from omnid.sim.chair import Chair, ChairSettings, integrate_arc

IDEAL = ChairSettings(motor_time_constant_s=0.0, left_gain=1.0, right_gain=1.0)


def run(chair: Chair, left: float, right: float, seconds: float, dt_s: float = 0.02) -> None:
    for _ in range(round(seconds / dt_s)):
        chair.step(left, right, dt_s)


def test_full_duty_speed_is_the_motor_rating():
    s = ChairSettings()
    assert s.clock_mm == pytest.approx(31.4)
    assert 27 / 60 * 471 <= s.max_speed_mm_s <= 32 / 60 * 471


def test_straight_line_without_lag_is_exact():
    chair = Chair(IDEAL, pose=(100.0, -50.0, math.radians(30)))
    run(chair, 0.5, 0.5, 2.0)
    d = 0.5 * IDEAL.max_speed_mm_s * 2.0
    assert chair.x_mm == pytest.approx(100 + d * math.cos(math.radians(30)), abs=1e-6)
    assert chair.y_mm == pytest.approx(-50 + d * math.sin(math.radians(30)), abs=1e-6)
    assert chair.theta_rad == pytest.approx(math.radians(30), abs=1e-12)


def test_straight_line_with_motor_lag_matches_first_order_response():
    s = ChairSettings(motor_time_constant_s=0.3, left_gain=1.0, right_gain=1.0)
    chair = Chair(s)
    run(chair, 1.0, 1.0, 1.0, dt_s=0.01)
    u, tau, t = s.max_speed_mm_s, 0.3, 1.0
    expected = u * t - u * tau * (1 - math.exp(-t / tau))
    assert chair.x_mm == pytest.approx(expected, rel=1e-9)
    assert chair.left_speed_mm_s == pytest.approx(u * (1 - math.exp(-t / tau)), rel=1e-9)
    assert chair.y_mm == pytest.approx(0.0, abs=1e-9)


def test_arc_with_lag_stays_on_the_circle_of_eq_3_10():
    # Both wheels start from rest with one time constant: constant curvature, exact circle.
    s = ChairSettings(motor_time_constant_s=0.2, left_gain=1.0, right_gain=1.0)
    chair = Chair(s)
    run(chair, 0.3, 0.6, 3.0)
    vl, vr, L = 0.3, 0.6, s.track_mm
    radius = L * (vl + vr) / (2 * (vr - vl))  # eq. 3.10 (CCW turn to the left)
    # The centre of the circle is at (0, R); every pose lies on it with heading tangent.
    assert math.hypot(chair.x_mm, chair.y_mm - radius) == pytest.approx(radius, abs=1e-6)
    assert chair.theta_rad == pytest.approx(math.atan2(chair.x_mm, radius - chair.y_mm), abs=1e-9)
    travelled = 0.5 * (chair.left_travel_mm + chair.right_travel_mm)
    assert chair.theta_rad == pytest.approx(travelled / radius, rel=1e-9)


def test_spin_in_place_turns_without_moving():
    chair = Chair(IDEAL)
    run(chair, -0.5, 0.5, 2.0)
    omega = 2 * 0.5 * IDEAL.max_speed_mm_s / IDEAL.track_mm
    assert (chair.x_mm, chair.y_mm) == pytest.approx((0.0, 0.0), abs=1e-9)
    assert chair.theta_rad == pytest.approx(omega * 2.0, rel=1e-9)


def test_gain_mismatch_makes_an_open_loop_chair_veer_right():
    chair = Chair(ChairSettings(motor_time_constant_s=0.0, left_gain=1.0, right_gain=0.95))
    run(chair, 1.0, 1.0, 3.0)
    assert chair.theta_rad < -0.05 and chair.y_mm < 0


def test_slip_moves_the_chair_less_than_the_clocks_count():
    s = ChairSettings(
        motor_time_constant_s=0.0, left_gain=1, right_gain=1, left_slip=0.2, right_slip=0.2
    )
    chair = Chair(s)
    run(chair, 1.0, 1.0, 2.0)
    wheel = s.max_speed_mm_s * 2.0
    assert chair.x_mm == pytest.approx(0.8 * wheel, rel=1e-9)
    assert chair.clocks()[0] == math.floor(wheel / s.clock_mm)


def test_clocks_count_up_forward_and_down_backward():
    chair = Chair(IDEAL)
    run(chair, 1.0, 1.0, 2.0)
    forward = chair.clocks()
    wheel = IDEAL.max_speed_mm_s * 2.0
    assert forward == (math.floor(wheel / 31.4), math.floor(wheel / 31.4))
    run(chair, -1.0, -1.0, 3.3)  # ends 1.3 s of full speed behind the start, off a hole edge
    back = chair.clocks()
    assert back == (math.floor(-1.3 * IDEAL.max_speed_mm_s / 31.4),) * 2
    assert back[0] < 0


def test_broken_duty_stops_the_wheel_and_overdrive_saturates():
    chair = Chair(IDEAL)
    run(chair, math.nan, 5.0, 1.0)
    assert chair.left_speed_mm_s == 0.0
    assert chair.right_speed_mm_s == pytest.approx(IDEAL.max_speed_mm_s)
    with pytest.raises(ValueError):
        chair.step(0.0, 0.0, -1.0)


def test_deadband_keeps_the_wheels_still():
    chair = Chair(ChairSettings(deadband_duty=0.05, motor_time_constant_s=0.0))
    run(chair, 0.04, -0.04, 1.0)
    assert chair.pose == (0.0, 0.0, 0.0)


def test_settings_are_checked():
    with pytest.raises(ConfigError, match="left_slip"):
        ChairSettings(left_slip=1.0)


def test_integrate_arc_quarter_circle():
    x, y, th = integrate_arc(
        0, 0, 0, math.pi / 2 * 1000 - 250 * math.pi / 2, math.pi / 2 * 1000 + 250 * math.pi / 2, 500
    )
    assert (x, y, th) == pytest.approx((1000.0, 1000.0, math.pi / 2), abs=1e-9)


# -- contacts: plain rectangles with the World's field names ---------------------------------


@dataclass(frozen=True)
class _Box:
    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    height_mm: float


@dataclass(frozen=True)
class _Drop:
    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    depth_mm: float


@dataclass(frozen=True)
class _World:
    boxes: tuple[_Box, ...] = ()
    dropoffs: tuple[_Drop, ...] = ()


def test_footprint_overlapping_a_box_is_a_collision():
    world = _World(boxes=(_Box(330, 800, -100, 100, 300),))
    assert [c.kind for c in Chair(IDEAL).contacts(world)] == ["collision"]
    assert Chair(IDEAL, pose=(-30.0, 0.0, 0.0)).contacts(world) == []


def test_rotated_footprint_corner_hits_a_box_its_bounding_box_test_would_miss_or_flag():
    # At 45° the front-left corner sweeps out; a box just beside the footprint's axis-aligned
    # bounding box corner must not count, a box on the corner must.
    chair = Chair(IDEAL, pose=(0.0, 0.0, math.pi / 4))
    corners = chair.footprint()
    far_x, far_y = corners[:, 0].max(), corners[:, 1].max()
    # Box at the bounding box's top-right corner: outside the rotated rectangle.
    assert (
        chair.contacts(_World(boxes=(_Box(far_x - 30, far_x + 100, far_y - 30, far_y + 100, 500),)))
        == []
    )
    # Box on the actual front-left corner.
    fl = corners[1]
    assert chair.contacts(
        _World(boxes=(_Box(fl[0] - 20, fl[0] + 20, fl[1] - 20, fl[1] + 20, 500),))
    )


def test_low_boxes_and_shallow_drops_are_driven_over():
    world = _World(boxes=(_Box(0, 300, -100, 100, 10),), dropoffs=(_Drop(0, 300, -500, 500, 20),))
    assert Chair(IDEAL).contacts(world) == []


def test_front_wheels_over_a_drop_off_is_a_fall():
    drop = _Drop(10, 2000, -1000, 1000, 200)  # front (drive) wheels at x = 0: still on the floor
    chair = Chair(IDEAL)
    assert chair.contacts(_World(dropoffs=(drop,))) == []  # the footrest overhangs: no fall
    run(chair, 0.2, 0.2, 0.5)  # 0.2·235.5·0.5 ≈ 24 mm forward: wheels over the edge
    contacts = chair.contacts(_World(dropoffs=(drop,)))
    assert [c.kind for c in contacts] == ["fall"]
    assert "front (drive) wheel" in contacts[0].part


def test_reversing_castors_over_a_drop_off_is_a_fall():
    drop = _Drop(-3000, -660, -1000, 1000, 200)  # castors at x = −650
    chair = Chair(IDEAL)
    assert chair.contacts(_World(dropoffs=(drop,))) == []
    run(chair, -0.2, -0.2, 0.5)
    assert [c.part for c in chair.contacts(_World(dropoffs=(drop,)))] == ["left castor"]


def test_a_box_blocks_the_chair_its_wheels_stall_and_it_can_drive_away():
    wall = _Box(1000.0, 1100.0, -2000.0, 2000.0, 800.0)
    world = _World(boxes=(wall,))
    chair = Chair(IDEAL, world=world)
    run(chair, 0.5, 0.5, 6.0, dt_s=0.01)  # 117.75 mm/s: the bumper (x + 350) reaches 1000 at 5.5 s
    front = chair.x_mm + IDEAL.footprint_front_mm
    assert 1000.0 - 2.0 < front <= 1000.0  # pressed against it, never into it
    assert chair.blocked_by == (0,)
    assert chair.left_speed_mm_s == 0.0 and chair.right_speed_mm_s == 0.0  # stalled
    assert [c.kind for c in chair.contacts(world)] == ["collision"]
    assert len(chair.bump_log) == 1 and 5.4 < chair.bump_log[0][0] < 5.6
    clocks = chair.clocks()
    run(chair, 0.5, 0.5, 1.0, dt_s=0.01)
    assert chair.clocks() == clocks  # a stalled wheel turns no hole past its sensor
    run(chair, -0.3, -0.3, 1.0, dt_s=0.01)  # backing away is free
    assert chair.blocked_by == () and chair.x_mm < front - IDEAL.footprint_front_mm - 50.0
    assert chair.clocks()[0] < clocks[0]
    run(chair, 0.5, 0.5, 2.0, dt_s=0.01)
    assert len(chair.bump_log) == 2  # a second contact is a second bump


def test_low_boxes_do_not_block_and_a_chair_without_a_world_passes_through():
    low = _World(boxes=(_Box(500.0, 600.0, -2000.0, 2000.0, 10.0),))
    chair = Chair(IDEAL, world=low)
    run(chair, 0.5, 0.5, 6.0)  # 706 mm
    assert chair.x_mm > 600.0 and chair.bump_log == []
    tall = _World(boxes=(_Box(500.0, 600.0, -2000.0, 2000.0, 500.0),))
    ghost = Chair(IDEAL)
    run(ghost, 0.5, 0.5, 12.0)  # 1413 mm: the rear (750 mm behind the axle) is past the box
    assert ghost.x_mm > 1350.0 and ghost.contacts(tall) == []  # far past it again


def test_a_turn_that_swings_the_tail_into_a_box_is_blocked():
    box = _Box(-900.0, -700.0, 420.0, 600.0, 500.0)  # beside the left rear corner
    world = _World(boxes=(box,))
    chair = Chair(IDEAL, world=world)
    run(chair, 0.3, -0.3, 3.0, dt_s=0.01)  # turning right in place swings the tail left
    assert chair.blocked_by == (0,)
    assert all(c.kind == "collision" for c in chair.contacts(world))
    assert not _overlap(chair, box)


def _overlap(chair: Chair, box: _Box) -> bool:
    from omnid.sim.chair import _overlaps_aabb

    axis = [math.cos(chair.theta_rad), math.sin(chair.theta_rad)]
    import numpy as np

    return _overlaps_aabb(chair.footprint(), np.array(axis), box)
