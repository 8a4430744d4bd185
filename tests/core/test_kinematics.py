"""Kinematics eqs. 3.8–3.15 and odometry against closed-form arcs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omnid.core.kinematics import (
    MM_PER_CLOCK,
    arc_displacement,
    body_twist,
    clocks_to_mm,
    integrate_arc,
    turn_radius_mm,
    wheel_speeds,
    window_speed,
)

TRACK = 560.0


def test_mm_per_clock_is_thesis_value():
    assert pytest.approx(31.4) == MM_PER_CLOCK
    assert clocks_to_mm([15, -3]).tolist() == pytest.approx([471.0, -94.2])


def test_turning_left_speeds_up_the_right_wheel():
    vl, vr = wheel_speeds(200.0, 0.5, TRACK)
    assert float(vl) == pytest.approx(200.0 - 0.5 * 280.0)
    assert float(vr) == pytest.approx(200.0 + 0.5 * 280.0)
    assert float(turn_radius_mm(vl, vr, TRACK)) == pytest.approx(400.0)  # eq. 3.10, R = v/ω


def test_turn_radius_straight_and_in_place():
    assert np.isinf(turn_radius_mm(100.0, 100.0, TRACK))
    assert float(turn_radius_mm(-100.0, 100.0, TRACK)) == 0.0


@given(st.floats(-300, 300, allow_nan=False), st.floats(-2, 2, allow_nan=False))
@settings(max_examples=50, deadline=None)
def test_wheel_speeds_and_body_twist_are_inverse(v, w):
    vl, vr = wheel_speeds(v, w, TRACK)
    v2, w2 = body_twist(vl, vr, TRACK)
    assert float(v2) == pytest.approx(v, abs=1e-9)
    assert float(w2) == pytest.approx(w, abs=1e-12)


def test_straight_travel():
    pose = integrate_arc([100.0, 50.0, math.pi / 2], 300.0, 300.0, TRACK)
    assert pose.tolist() == pytest.approx([100.0, 350.0, math.pi / 2])


def test_turn_in_place_keeps_position():
    quarter = math.pi / 2 * TRACK / 2  # each wheel's travel for a quarter turn
    pose = integrate_arc([0.0, 0.0, 0.0], -quarter, quarter, TRACK)
    assert pose.tolist() == pytest.approx([0.0, 0.0, math.pi / 2], abs=1e-9)


@pytest.mark.parametrize("radius", [300.0, 1000.0, -700.0])
@pytest.mark.parametrize("angle", [0.1, 1.0, 3.0])
def test_arc_matches_closed_form_circle(radius, angle):
    # a circle of signed radius R about (0, R): after turning by angle φ (sign of R),
    # the position is (R sin φ, R (1 − cos φ)) with φ = s/R.
    s = abs(radius) * angle
    phi = s / radius
    dl = s * (radius - TRACK / 2) / radius
    dr = s * (radius + TRACK / 2) / radius
    pose = integrate_arc([0.0, 0.0, 0.0], dl, dr, TRACK)
    assert pose[0] == pytest.approx(radius * math.sin(phi), abs=1e-9)
    assert pose[1] == pytest.approx(radius * (1 - math.cos(phi)), abs=1e-9)
    assert pose[2] == pytest.approx(phi, abs=1e-12)


def test_arc_split_into_steps_equals_one_step():
    # exact integration: many small steps of a constant arc end where one big step ends
    pose = np.zeros(3)
    for _ in range(37):
        pose = integrate_arc(pose, 10.0, 17.0, TRACK)
    one = integrate_arc(np.zeros(3), 370.0, 629.0, TRACK)
    assert pose == pytest.approx(one, abs=1e-9)


def test_integrate_arc_broadcasts_and_wraps():
    poses = np.array([[0.0, 0.0, 3.0], [1.0, 1.0, -3.0]])
    out = integrate_arc(poses, [0.0, 0.0], [400.0, -400.0], TRACK)
    assert out.shape == (2, 3)
    assert np.all(np.abs(out[:, 2]) <= math.pi)


def test_arc_displacement_small_angle_is_stable():
    dx, dy, _dth = arc_displacement(100.0, 100.0 + 1e-12, TRACK)
    assert float(dx) == pytest.approx(100.0)
    assert abs(float(dy)) < 1e-9


def test_window_speed_constant_motion():
    # 150 mm/s → one clock every 0.2093 s; status sampled every 20 ms
    t = np.arange(0, 2.0, 0.02)
    clocks = np.floor(t * 150.0 / MM_PER_CLOCK)
    est = window_speed(t, clocks, window_s=1.0)
    assert est == pytest.approx(150.0, rel=0.12)


def test_window_speed_backward_and_stopped():
    t = np.arange(0, 2.0, 0.02)
    clocks = -np.floor(t * 200.0 / MM_PER_CLOCK)
    assert window_speed(t, clocks, 1.0) == pytest.approx(-200.0, rel=0.12)
    assert window_speed(t, np.full_like(t, 7.0), 1.0) == 0.0
    assert window_speed([], [], 1.0) == 0.0


def test_window_speed_decays_after_wheel_stops():
    t = np.arange(0, 3.0, 0.02)
    moving = t < 1.0
    clocks = np.where(moving, np.floor(t * 250.0 / MM_PER_CLOCK), np.floor(250.0 / MM_PER_CLOCK))
    est = window_speed(t[t < 2.0], clocks[t < 2.0], window_s=1.5)
    assert est < 60.0  # one clock per ≥ 0.5 s since the last edge
