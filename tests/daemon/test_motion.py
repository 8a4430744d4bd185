"""Ramps, wheel PI with clock feedback on a motor model, anti-windup, odometry vs arcs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnid.config import from_mapping
from omnid.core.kinematics import MM_PER_CLOCK
from omnid.daemon.motion import MotionController, MotionSettings, Odometry, TwistRamp, WheelPI
from omnid.errors import ConfigError

S = MotionSettings()
DT = 0.02


def test_ramp_accelerates_at_comfort_rate_and_brakes_harder():
    r = TwistRamp(S)
    v, _ = r.step(200.0, 0.0, DT, emergency=False)
    assert v == pytest.approx(S.accel_mm_s2 * DT)
    for _ in range(100):
        r.step(200.0, 0.0, DT, False)
    assert r.v_mm_s == 200.0
    v, _ = r.step(0.0, 0.0, DT, emergency=False)
    assert 200.0 - v == pytest.approx(S.decel_mm_s2 * DT)
    v2, _ = r.step(0.0, 0.0, DT, emergency=True)
    assert v - v2 == pytest.approx(S.emergency_decel_mm_s2 * DT)


def test_emergency_stop_time_from_full_speed():
    r = TwistRamp(S)
    r.v_mm_s, r.omega_rad_s = S.max_speed_mm_s, 0.3
    n = 0
    while r.v_mm_s != 0.0 or r.omega_rad_s != 0.0:
        r.step(0.0, 0.0, DT, emergency=True)
        n += 1
    assert n * DT <= S.max_speed_mm_s / S.emergency_decel_mm_s2 + DT


def test_ramp_reverses_through_zero_and_clamps_limits():
    r = TwistRamp(S)
    r.v_mm_s = 10.0
    v, _ = r.step(-500.0, 0.0, DT, False)  # 10 mm/s braked away in 0.025 s > DT
    assert v == pytest.approx(10.0 - S.decel_mm_s2 * DT)
    for _ in range(200):
        r.step(-500.0, 5.0, DT, False)
    assert r.v_mm_s == -S.max_reverse_speed_mm_s
    assert r.omega_rad_s == S.max_turn_rate_rad_s


def test_settings_refuse_softer_braking():
    with pytest.raises(ConfigError, match="decel_mm_s2"):
        from_mapping(MotionSettings, {"accel_mm_s2": 500, "decel_mm_s2": 300})


class Motor:
    """First-order wheel: speed → gain·duty·251 mm/s with time constant tau; counts clocks."""

    def __init__(self, gain: float, tau_s: float = 0.15) -> None:
        self.gain, self.tau = gain, tau_s
        self.speed = 0.0
        self.travel = 0.0

    def step(self, duty: float, dt: float) -> None:
        target = self.gain * duty * 251.0
        self.speed += (target - self.speed) * (1 - math.exp(-dt / self.tau))
        self.travel += self.speed * dt

    @property
    def clocks(self) -> int:
        return math.floor(self.travel / MM_PER_CLOCK)


def run_closed_loop(left_gain_true: float, seconds: float, v: float, w: float = 0.0):
    ctrl = MotionController(S)
    odo = Odometry(S)
    ml, mr = Motor(left_gain_true), Motor(1.0)
    t = 0.0
    for _ in range(int(seconds / DT)):
        odo.update(ml.clocks, mr.clocks, t)
        dl, dr = ctrl.step(v, w, odo.wheel_speeds(), DT)
        assert -1.0 <= dl <= 1.0 and -1.0 <= dr <= 1.0
        for _ in range(4):
            ml.step(dl, DT / 4)
            mr.step(dr, DT / 4)
        t += DT
    return ml, mr, ctrl


def test_pi_corrects_a_weak_motor():
    # the left motor gives 80 % of nominal speed: feedforward alone would leave it 20 % slow
    ml, mr, _ = run_closed_loop(0.8, 12.0, 150.0)
    assert ml.speed == pytest.approx(150.0, rel=0.1)
    assert mr.speed == pytest.approx(150.0, rel=0.1)
    assert ml.travel == pytest.approx(mr.travel, rel=0.08)  # goes straight


def test_anti_windup_bounds_integral_when_saturated():
    pi = WheelPI(1.0, S)
    for _ in range(500):  # motor stalled: error stays huge
        duty = pi.step(240.0, 0.0, DT)
    assert duty == 1.0
    assert abs(pi.integral) <= S.integral_limit


def test_zero_target_gives_exact_zero_duty_and_clears_integral():
    pi = WheelPI(1.0, S)
    pi.step(100.0, 50.0, DT)
    assert pi.integral != 0.0
    assert pi.step(0.0, 80.0, DT) == 0.0
    assert pi.integral == 0.0


def test_duty_never_opposes_target_direction():
    pi = WheelPI(1.0, S)
    assert pi.step(20.0, 200.0, DT) >= 0.0  # overspeed: coast, do not reverse


def test_odometry_matches_closed_form_arc():
    odo = Odometry(S)
    # constant arc: right wheel 3 clocks per update, left 1 → R = L(vl+vr)/(2(vr−vl))
    for k in range(40):
        odo.update(k, 3 * k, k * DT)
    dl, dr = 39 * MM_PER_CLOCK, 117 * MM_PER_CLOCK
    radius = S.track_mm * (dl + dr) / (2 * (dr - dl))
    phi = (dr - dl) / S.track_mm
    x, y, th = odo.pose
    assert th == pytest.approx(math.remainder(phi, 2 * math.pi), abs=1e-9)
    assert x == pytest.approx(radius * math.sin(phi), abs=1e-6)
    assert y == pytest.approx(radius * (1 - math.cos(phi)), abs=1e-6)


def test_odometry_increments_compose_to_pose():
    odo = Odometry(S)
    pose = np.zeros(3)
    rng = np.random.default_rng(3)
    cl = cr = 0
    odo.update(0, 0, 0.0)
    for k in range(1, 60):
        cl += int(rng.integers(-1, 3))
        cr += int(rng.integers(-1, 3))
        dx, dy, dth = odo.update(cl, cr, k * DT)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = np.array([pose[0] + c * dx - s * dy, pose[1] + s * dx + c * dy, pose[2] + dth])
    assert odo.pose[:2] == pytest.approx(pose[:2], abs=1e-6)
    assert math.remainder(odo.pose[2] - pose[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
