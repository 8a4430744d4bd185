"""Differential-drive kinematics and wheel-clock odometry (thesis 3.3, eqs. 3.8–3.15; 4.3.2.3).

Frame: the robot frame of :mod:`omnid.core.occupancy` — origin at the wheel-axle midpoint, x
forward, y **left**, heading θ counter-clockwise (REP-103). The thesis measures its orientation
γ the other way round (eq. 3.11 gives w = (v_L − v_R)/L, positive when the chair turns right and
eq. 3.14 takes γ from the y axis); here ω = −w, so that a positive ω turns the chair left and

    v_L = v − ω·L/2,   v_R = v + ω·L/2          (eqs. 3.8, 3.9 with R = v/ω)
    v   = (v_L + v_R)/2                          (eq. 3.12)
    ω   = (v_R − v_L)/L                          (eq. 3.11, sign flipped to CCW)

with L the track (distance between the drive wheels), mm. Speeds are mm/s, angles rad.

Odometry integrates wheel travel over an interval assuming constant wheel speeds in it, i.e. an
exact circular arc (the closed form of eq. 3.14 for constant v, ω), not an Euler step. Wheel
travel comes from clocks: 15 holes per wheel disk and a 471 mm circumference give 31.4 mm per
clock (thesis 4.3.2.3); clocks count up forward and down backward.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

WHEEL_CIRCUMFERENCE_MM = 471.0
"""Drive wheel circumference, mm (thesis 4.3.2.3)."""
CLOCKS_PER_TURN = 15
"""Holes per wheel disk (thesis 4.3.2.3)."""
MM_PER_CLOCK = WHEEL_CIRCUMFERENCE_MM / CLOCKS_PER_TURN
"""Floor travel per clock, 31.4 mm (thesis 4.3.2.3)."""


def wheel_speeds(
    v_mm_s: ArrayLike, omega_rad_s: ArrayLike, track_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Left and right wheel speeds (mm/s) for the body twist (v mm/s, ω rad/s CCW).

    Eqs. 3.8 and 3.9: ω = v_L/(R + L/2) = v_R/(R − L/2) in the thesis' clockwise convention,
    i.e. v_L = v − ω·L/2 and v_R = v + ω·L/2 with ω counter-clockwise.
    """
    v = np.asarray(v_mm_s, dtype=np.float64)
    w = np.asarray(omega_rad_s, dtype=np.float64)
    half = 0.5 * float(track_mm)
    return v - w * half, v + w * half


def body_twist(
    vl_mm_s: ArrayLike, vr_mm_s: ArrayLike, track_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Body twist (v mm/s, ω rad/s CCW) of the wheel speeds (mm/s).

    Eq. 3.12: v = (v_L + v_R)/2; eq. 3.11: ω = (v_R − v_L)/L (the thesis' w = (v_L − v_R)/L with
    the sign flipped to counter-clockwise). Eq. 3.15 is the same map written with wheel angular
    speeds (v_wheel = r·w_wheel).
    """
    vl = np.asarray(vl_mm_s, dtype=np.float64)
    vr = np.asarray(vr_mm_s, dtype=np.float64)
    return 0.5 * (vl + vr), (vr - vl) / float(track_mm)


def turn_radius_mm(vl_mm_s: ArrayLike, vr_mm_s: ArrayLike, track_mm: float) -> NDArray[np.float64]:
    """Signed radius of the instantaneous centre of curvature, mm (eq. 3.10).

    Positive: the centre is on the left (CCW turn). ``inf`` for straight motion (v_L = v_R),
    0 for turning in place. Eq. 3.10 reads R = L(v_L + v_R)/(2(v_L − v_R)) in the thesis'
    clockwise convention; here R = L(v_L + v_R)/(2(v_R − v_L)).
    """
    vl = np.asarray(vl_mm_s, dtype=np.float64)
    vr = np.asarray(vr_mm_s, dtype=np.float64)
    num = float(track_mm) * (vl + vr)
    den = 2.0 * (vr - vl)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(den != 0.0, num / np.where(den != 0.0, den, 1.0), np.inf)
    return np.asarray(r, dtype=np.float64)


def arc_displacement(
    dl_mm: ArrayLike, dr_mm: ArrayLike, track_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Motion (dx mm, dy mm, dθ rad) in the robot frame at the start of an exact arc.

    The wheels travel ``dl_mm`` and ``dr_mm`` at constant speeds: the axle midpoint travels
    s = (d_L + d_R)/2 along a circle and turns by dθ = (d_R − d_L)/L (eqs. 3.11, 3.12 integrated
    over the interval). The chord has length s·sin(dθ/2)/(dθ/2) and points along dθ/2, which is
    the closed-form solution of eq. 3.14 for constant v and ω; ``np.sinc`` keeps it exact and
    stable for straight motion (dθ → 0). This is what :meth:`FreeSpaceMap.move` takes.
    """
    dl = np.asarray(dl_mm, dtype=np.float64)
    dr = np.asarray(dr_mm, dtype=np.float64)
    s = 0.5 * (dl + dr)
    dth = (dr - dl) / float(track_mm)
    chord = s * np.sinc(dth / (2.0 * np.pi))  # np.sinc(x) = sin(πx)/(πx)
    return chord * np.cos(0.5 * dth), chord * np.sin(0.5 * dth), dth


def integrate_arc(
    pose: ArrayLike, dl_mm: ArrayLike, dr_mm: ArrayLike, track_mm: float
) -> NDArray[np.float64]:
    """New pose (…, 3) = (x mm, y mm, θ rad) after the wheels travel ``dl_mm``, ``dr_mm``.

    Exact arc integration of eq. 3.14 (see :func:`arc_displacement`); ``pose`` is (3,) or (N, 3)
    and broadcasts against the wheel travels. θ is wrapped to (−π, π].
    """
    p = np.asarray(pose, dtype=np.float64)
    dx, dy, dth = arc_displacement(dl_mm, dr_mm, track_mm)
    x, y, th = p[..., 0], p[..., 1], p[..., 2]
    c, s = np.cos(th), np.sin(th)
    out = np.stack(
        np.broadcast_arrays(x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(th + dth)),
        axis=-1,
    )
    return out.astype(np.float64)


def wrap_angle(theta_rad: ArrayLike) -> NDArray[np.float64]:
    """Angle wrapped to (−π, π], rad."""
    t = np.asarray(theta_rad, dtype=np.float64)
    return np.asarray(np.pi - np.mod(np.pi - t, 2.0 * np.pi), dtype=np.float64)


def clocks_to_mm(clocks: ArrayLike, mm_per_clock: float = MM_PER_CLOCK) -> NDArray[np.float64]:
    """Wheel travel in mm of a (signed) number of clocks (thesis 4.3.2.3: 471 mm / 15 = 31.4 mm)."""
    return np.asarray(clocks, dtype=np.float64) * float(mm_per_clock)


def window_speed(
    t_s: ArrayLike,
    clocks: ArrayLike,
    window_s: float,
    mm_per_clock: float = MM_PER_CLOCK,
) -> float:
    """Wheel speed (mm/s) from a history of clock counters sampled at times ``t_s`` (s).

    Clocks are coarse (31.4 mm, a few per second at full speed), so a plain difference over one
    control period is mostly 0 or ±1 clock. This estimate looks at the samples within
    ``window_s`` of the newest one and measures the time between counter *changes* (edges):

    - with two or more edges in the window: clocks between the first and the last edge divided
      by the time between them — the resolution no longer depends on the sampling period;
    - if the time since the last edge is already longer than the mean edge interval, the wheel
      is slowing down: the speed is bounded by one clock per time since the last edge;
    - with fewer than two edges: counter difference over the window (0 if it did not move).

    ``t_s`` must be increasing. An empty history gives 0.0.
    """
    t = np.asarray(t_s, dtype=np.float64).ravel()
    c = np.asarray(clocks, dtype=np.float64).ravel()
    if t.size < 2:
        return 0.0
    keep = t >= t[-1] - float(window_s)
    # keep one sample before the window too, so that an edge at the window's start is seen
    first = max(int(np.argmax(keep)) - 1, 0)
    t, c = t[first:], c[first:]
    edges = np.nonzero(np.diff(c))[0] + 1  # indices where the counter changed
    if edges.size >= 2:
        t_first, t_last = t[edges[0]], t[edges[-1]]
        dt = t_last - t_first
        dclk = c[edges[-1]] - c[edges[0]]
        speed = dclk * mm_per_clock / dt if dt > 0 else 0.0
        since = t[-1] - t_last
        if dt > 0 and since > dt / max(abs(dclk), 1.0):
            bound = mm_per_clock / since
            speed = float(np.sign(speed)) * min(abs(speed), bound)
        return float(speed)
    span = t[-1] - t[0]
    if span <= 0:
        return 0.0
    return float((c[-1] - c[0]) * mm_per_clock / span)
