"""The simulated chair: differential-drive dynamics, wheel clocks, footprint, collisions and falls.

This is the ``plant`` the control-unit emulator drives (docs/interfaces.md): it receives the PWM
duty the emulated control unit applies to each wheel, ``step(left_duty, right_duty, dt_s)``, and
reports the proximity-sensor counters, ``clocks() -> (left, right)``.

Model (thesis 3.3, 4.3.2; SPEC §1)
----------------------------------
* Each wheel's surface speed follows its duty with a first-order motor lag::

      dv/dt = (u − v) / τ,   u = gain · duty · v_max,   v_max = rpm_max / 60 · circumference

  Over a step of constant duty this has the exact solution v(t) = u + (v₀ − u)·e^(−t/τ), whose
  integral gives the wheel travel of the step in closed form (no Euler error).
* Wheel slip: a fraction ``slip`` of each wheel's travel does not move the chair (the wheel
  spins); the clocks count the wheel's rotation, not the chair's motion, as a real encoder does.
* Pose: the body twist of a differential drive (thesis eqs. 3.11, 3.12, with y to the **left**
  and θ counter-clockwise, so v = (v_L + v_R)/2 and ω = (v_R − v_L)/L) integrated as an exact
  circular arc per sub-step (eq. 3.14 with constant v, ω). Sub-steps are at most
  ``max_substep_s`` long, so even while the motors accelerate the arc error is negligible; with
  both wheels accelerating from rest under one time constant the curvature is constant and the
  path is an exact circle.
* Clocks: 15 holes per wheel disk and 471 mm wheel circumference (thesis 4.3.2.3): one clock per
  31.4 mm of wheel travel, counting up forward and down backward.

* Contact (with a ``world``): a box at least ``collision_height_mm`` tall stops the chair — a
  step whose end pose would overlap it is not taken, and both wheels stall (speed 0, no travel,
  no clocks), as drive wheels pressed against a wall do. The run goes on: the daemon has to
  notice the bump from the clocks, and the chair can drive away from the box. Each time the
  chair becomes blocked is logged (:attr:`Chair.bump_log`). Without a world the chair passes
  through boxes and only :meth:`Chair.contacts` tells of the overlap.

World frame: x, y on the floor (y left), θ counter-clockwise; the chair pose is the robot frame's
origin (the wheel-axle midpoint) in the world. The footprint is a rectangle around the axle,
mostly behind it: the drive wheels are the front wheels, free castors carry the rear (thesis
4.3.2.1), and the footrest overhangs the axle in front.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from omnid.config import require


@dataclass(frozen=True)
class ChairSettings:
    """Dimensions and motor model of the simulated chair (mm, s, rpm; duty in [-1, 1])."""

    track_mm: float = 560.0  # distance L between the drive wheels (thesis eq. 3.11)
    wheel_circumference_mm: float = 471.0  # thesis 4.3.2.3
    clocks_per_turn: int = 15  # holes per wheel disk, thesis 4.3.2.3
    max_rpm: float = 30.0  # wheel speed at full duty and gain 1 (thesis Table 4.3: 27–32 rpm)
    motor_time_constant_s: float = 0.15  # first-order lag of wheel speed behind duty
    left_gain: float = 1.0  # per-wheel gain (motor mismatch), 1 = nominal
    right_gain: float = 0.96
    left_slip: float = 0.0  # fraction of wheel travel lost to slip, [0, 1)
    right_slip: float = 0.0
    deadband_duty: float = 0.0  # |duty| below this does not turn the wheel (static friction)
    # Thesis 4.3.2.1: the drive wheels are at the front, free castors behind; the daemon's
    # safety footprint (omnid.daemon.safety) describes the same chair.
    footprint_front_mm: float = 350.0  # footprint reaches this far ahead of the axle
    footprint_rear_mm: float = 750.0  # ... and this far behind it
    footprint_width_mm: float = 700.0
    castor_x_mm: float = -650.0  # the free castors, behind the axle
    castor_y_mm: float = 250.0  # ... at ±this lateral offset
    com_x_mm: float = -200.0  # centre of mass on the centre line (rider and batteries)
    collision_height_mm: float = 15.0  # boxes lower than this are driven over
    fall_depth_mm: float = 30.0  # drop-offs shallower than this are driven over
    max_substep_s: float = 0.005

    def __post_init__(self) -> None:
        for name in (
            "track_mm",
            "wheel_circumference_mm",
            "max_rpm",
            "footprint_width_mm",
            "max_substep_s",
        ):
            require(getattr(self, name) > 0, name, "must be positive")
        require(self.clocks_per_turn >= 1, "clocks_per_turn", "must be at least 1")
        require(self.motor_time_constant_s >= 0, "motor_time_constant_s", "must be ≥ 0")
        for name in ("left_gain", "right_gain"):
            require(0 < getattr(self, name) <= 2, name, "must be in (0, 2]")
        for name in ("left_slip", "right_slip"):
            require(0 <= getattr(self, name) < 1, name, "must be in [0, 1)")
        require(0 <= self.deadband_duty < 1, "deadband_duty", "must be in [0, 1)")
        require(
            self.footprint_front_mm + self.footprint_rear_mm > 0,
            "footprint_front_mm",
            "footprint must have positive length",
        )

    @property
    def clock_mm(self) -> float:
        """Wheel travel per clock, mm (471 / 15 = 31.4 mm)."""
        return self.wheel_circumference_mm / self.clocks_per_turn

    @property
    def max_speed_mm_s(self) -> float:
        """Wheel surface speed at full duty and gain 1, mm/s."""
        return self.max_rpm / 60.0 * self.wheel_circumference_mm


class _Rect(Protocol):
    """Anything with an axis-aligned floor rectangle (``world.Box`` and ``world.DropOff``)."""

    @property
    def x_min_mm(self) -> float: ...
    @property
    def x_max_mm(self) -> float: ...
    @property
    def y_min_mm(self) -> float: ...
    @property
    def y_max_mm(self) -> float: ...


class _BoxLike(_Rect, Protocol):
    @property
    def height_mm(self) -> float: ...


class _DropLike(_Rect, Protocol):
    @property
    def depth_mm(self) -> float: ...


class _WorldLike(Protocol):
    """The part of ``omnid.sim.world.World`` the chair needs: its boxes and drop-offs."""

    @property
    def boxes(self) -> Sequence[_BoxLike]: ...
    @property
    def dropoffs(self) -> Sequence[_DropLike]: ...


@dataclass(frozen=True)
class Contact:
    """The chair touched something it must not: a box (``collision``) or a drop-off (``fall``).

    ``index`` is the box's (or drop-off's) position in the world's tuple; ``part`` names what
    touched it (``footprint``, ``centre of mass``, ``left front (drive) wheel``, ``left castor``, ...).
    """

    kind: Literal["collision", "fall"]
    index: int
    part: str


@dataclass(frozen=True)
class ChairState:
    """A snapshot of the chair: pose (mm, rad), wheel surface speeds (mm/s), wheel travel (mm)."""

    x_mm: float
    y_mm: float
    theta_rad: float
    left_speed_mm_s: float
    right_speed_mm_s: float
    left_travel_mm: float
    right_travel_mm: float


def _lag_step(v0: float, u: float, dt_s: float, tau_s: float) -> tuple[float, float]:
    """Exact first-order response over ``dt_s``: (speed at the end, distance travelled)."""
    if tau_s <= 0.0:
        return u, u * dt_s
    decay = math.exp(-dt_s / tau_s)
    return u + (v0 - u) * decay, u * dt_s + (v0 - u) * tau_s * (1.0 - decay)


def integrate_arc(
    x_mm: float, y_mm: float, theta_rad: float, dl_mm: float, dr_mm: float, track_mm: float
) -> tuple[float, float, float]:
    """Move a differential-drive pose by wheel travels ``dl_mm``, ``dr_mm`` along an exact arc.

    The body moves ds = (dl + dr)/2 and turns dθ = (dr − dl)/L (thesis eqs. 3.11, 3.12 with θ
    counter-clockwise), along the circle of radius R = ds/dθ (eq. 3.10), i.e. eq. 3.14 integrated
    in closed form for constant v and ω.
    """
    ds = 0.5 * (dl_mm + dr_mm)
    dth = (dr_mm - dl_mm) / track_mm
    if abs(dth) < 1e-12:
        return x_mm + ds * math.cos(theta_rad), y_mm + ds * math.sin(theta_rad), theta_rad
    radius = ds / dth
    th1 = theta_rad + dth
    return (
        x_mm + radius * (math.sin(th1) - math.sin(theta_rad)),
        y_mm - radius * (math.cos(th1) - math.cos(theta_rad)),
        th1,
    )


def _overlaps_aabb(
    corners: Sequence[Sequence[float]], axis_u: Sequence[float], rect: _Rect
) -> bool:
    """Separating-axis test of an oriented rectangle (4 corners, unit long axis) and an AABB.
    On plain floats: with 4 corners numpy's per-call overhead is the whole cost, and a
    blocked chair runs this 13 times a step (its bisection)."""
    xmin, xmax = float(rect.x_min_mm), float(rect.x_max_mm)
    ymin, ymax = float(rect.y_min_mm), float(rect.y_max_mm)
    xs = [float(c[0]) for c in corners]
    ys = [float(c[1]) for c in corners]
    if max(xs) <= xmin or min(xs) >= xmax or max(ys) <= ymin or min(ys) >= ymax:
        return False
    ux, uy = float(axis_u[0]), float(axis_u[1])
    for ax, ay in ((ux, uy), (-uy, ux)):
        a = [x * ax + y * ay for x, y in zip(xs, ys, strict=True)]
        b = [
            xmin * ax + ymin * ay,
            xmax * ax + ymin * ay,
            xmax * ax + ymax * ay,
            xmin * ax + ymax * ay,
        ]
        if max(a) <= min(b) or min(a) >= max(b):
            return False
    return True


def _inside(point: NDArray[np.float64], rect: _Rect) -> bool:
    return bool(
        rect.x_min_mm < point[0] < rect.x_max_mm and rect.y_min_mm < point[1] < rect.y_max_mm
    )


class Chair:
    """The simulated chair; ``step`` / ``clocks`` make it a control-unit emulator plant.

    ``wheel_phase_mm`` is each wheel's travel past its last hole at the start (the clock counters
    then start at 0). With a ``world``, its boxes block the chair (module docstring):
    ``blocked_by`` holds the
    boxes the last step pressed against, ``bump_log`` every start of a contact as
    ``(elapsed_s, box indices)``, ``press_log`` each ended contact as ``(start_s, end_s)``,
    ``elapsed_s`` the time the chair has been stepped.
    """

    def __init__(
        self,
        settings: ChairSettings | None = None,
        pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
        world: _WorldLike | None = None,
        wheel_phase_mm: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.settings = settings or ChairSettings()
        # where each wheel's next hole is at the start: a real disk stands anywhere
        self.wheel_phase_mm = (float(wheel_phase_mm[0]), float(wheel_phase_mm[1]))
        self.x_mm, self.y_mm, self.theta_rad = (float(v) for v in pose)
        self.left_speed_mm_s = 0.0
        self.right_speed_mm_s = 0.0
        self.left_travel_mm = 0.0
        self.right_travel_mm = 0.0
        self.left_duty = 0.0
        self.right_duty = 0.0
        self.world = world
        self.elapsed_s = 0.0
        self.blocked_by: tuple[int, ...] = ()
        self.bump_log: list[tuple[float, tuple[int, ...]]] = []
        # every contact as (start s, end s): how long the chair pressed against the box, until
        # a step (duty 0, or away from it) no longer pushed into it
        self.press_log: list[tuple[float, float]] = []
        s = self.settings
        w = s.footprint_width_mm / 2.0
        self._reach_mm = math.hypot(max(s.footprint_front_mm, s.footprint_rear_mm), w)
        self._free_mm = 0.0  # travel of any footprint point that cannot reach a box (≤ 0: check)

    # -- the plant contract -------------------------------------------------------------------

    def _target_speed(self, duty: float, gain: float) -> float:
        s = self.settings
        d = max(-1.0, min(1.0, float(duty))) if math.isfinite(duty) else 0.0
        if abs(d) <= s.deadband_duty:
            return 0.0
        return gain * d * s.max_speed_mm_s

    def step(self, left_duty: float, right_duty: float, dt_s: float) -> None:
        """Advance the chair by ``dt_s`` seconds with constant signed duties in [-1, 1].

        Non-finite duties are treated as 0 (a broken command stops the wheel, it never runs it);
        duties beyond ±1 saturate.
        """
        if not (math.isfinite(dt_s) and dt_s >= 0):
            raise ValueError(f"Chair.step: dt_s must be finite and ≥ 0, got {dt_s!r}")
        s = self.settings
        self.elapsed_s += dt_s
        before = (
            self.x_mm,
            self.y_mm,
            self.theta_rad,
            self.left_travel_mm,
            self.right_travel_mm,
        )
        self.left_duty, self.right_duty = float(left_duty), float(right_duty)
        ul = self._target_speed(left_duty, s.left_gain)
        ur = self._target_speed(right_duty, s.right_gain)
        n = max(1, math.ceil(dt_s / s.max_substep_s - 1e-9))
        h = dt_s / n
        for _ in range(n):
            self.left_speed_mm_s, dl = _lag_step(
                self.left_speed_mm_s, ul, h, s.motor_time_constant_s
            )
            self.right_speed_mm_s, dr = _lag_step(
                self.right_speed_mm_s, ur, h, s.motor_time_constant_s
            )
            self.left_travel_mm += dl
            self.right_travel_mm += dr
            self.x_mm, self.y_mm, self.theta_rad = integrate_arc(
                self.x_mm,
                self.y_mm,
                self.theta_rad,
                dl * (1.0 - s.left_slip),
                dr * (1.0 - s.right_slip),
                s.track_mm,
            )
        if self.world is not None:
            was_blocked = bool(self.blocked_by)
            self._block(before)
            if was_blocked and not self.blocked_by:
                self.press_log.append((self.bump_log[-1][0], self.elapsed_s))

    def _block(self, before: tuple[float, float, float, float, float]) -> None:
        """Cut the step just taken short where it pressed the footprint into a box (wheels
        stalled).

        The exact overlap test runs only when the footprint may have reached a box: after each
        test the distance to the nearest box bounds how far any footprint point can move
        (translation + turn · farthest corner) before the next one is needed.
        """
        x0, y0, th0, _, _ = before
        self._free_mm -= math.hypot(self.x_mm - x0, self.y_mm - y0)
        self._free_mm -= abs(self.theta_rad - th0) * self._reach_mm
        if self._free_mm > 0.0:
            self.blocked_by = ()
            return
        assert self.world is not None
        hit = self._pressed_boxes(self.world)
        if not hit:
            self.blocked_by = ()
            self._free_mm = self._box_distance(self.world)
            return
        if not self.blocked_by:
            self.bump_log.append((self.elapsed_s, hit))
        self.blocked_by = hit
        # The chair stops where it touches: the largest part of the step (interpolated, the step
        # is a few mm) that does not overlap, found by bisection to a 1/4096 of the step.
        after = (self.x_mm, self.y_mm, self.theta_rad, self.left_travel_mm, self.right_travel_mm)
        lo, hi = 0.0, 1.0
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            self._set_state(before, after, mid)
            if self._pressed_boxes(self.world):
                hi = mid
            else:
                lo = mid
        self._set_state(before, after, lo)
        self.left_speed_mm_s = self.right_speed_mm_s = 0.0

    def _set_state(
        self,
        a: tuple[float, float, float, float, float],
        b: tuple[float, float, float, float, float],
        f: float,
    ) -> None:
        x, y, th, tl, tr = (u + f * (v - u) for u, v in zip(a, b, strict=True))
        self.x_mm, self.y_mm, self.theta_rad = x, y, th
        self.left_travel_mm, self.right_travel_mm = tl, tr

    def _tall(self, world: _WorldLike) -> NDArray[np.float64]:
        """Rectangles (B', 4) of the boxes tall enough to stop the chair, remembered per world."""
        cached = getattr(self, "_tall_cache", None)
        if cached is not None and cached[0] is world:
            tall: NDArray[np.float64] = cached[1]
            return tall
        h = np.array([float(b.height_mm) for b in world.boxes], dtype=np.float64)
        tall = self._rects_of(world)[h >= self.settings.collision_height_mm]
        self._tall_cache = (world, tall)
        return tall

    def _pressed_boxes(self, world: _WorldLike) -> tuple[int, ...]:
        """Indices of the tall boxes the footprint overlaps now."""
        return tuple(
            c.index for c in self._box_contacts(world, self.footprint()) if c.kind == "collision"
        )

    def _box_distance(self, world: _WorldLike) -> float:
        """Distance (mm) between the footprint and the nearest tall box (0 when touching):
        for a convex polygon and a rectangle apart, the least of corner-to-other distances."""
        rects = self._tall(world)
        if len(rects) == 0:
            return math.inf
        corners = self.footprint()
        dx = np.maximum(np.maximum(rects[None, :, 0] - corners[:, None, 0], 0.0),
                        corners[:, None, 0] - rects[None, :, 1])  # fmt: skip
        dy = np.maximum(np.maximum(rects[None, :, 2] - corners[:, None, 1], 0.0),
                        corners[:, None, 1] - rects[None, :, 3])  # fmt: skip
        d1 = float(np.hypot(dx, dy).min())
        # the boxes' corners in the robot frame, against the footprint rectangle
        s = self.settings
        bx = np.concatenate([rects[:, 0], rects[:, 0], rects[:, 1], rects[:, 1]])
        by = np.concatenate([rects[:, 2], rects[:, 3], rects[:, 2], rects[:, 3]])
        c, sn = math.cos(self.theta_rad), math.sin(self.theta_rad)
        rx = c * (bx - self.x_mm) + sn * (by - self.y_mm)
        ry = -sn * (bx - self.x_mm) + c * (by - self.y_mm)
        w = s.footprint_width_mm / 2.0
        ex = np.maximum(np.maximum(-s.footprint_rear_mm - rx, rx - s.footprint_front_mm), 0.0)
        ey = np.maximum(np.abs(ry) - w, 0.0)
        return min(d1, float(np.hypot(ex, ey).min()))

    def clocks(self) -> tuple[int, int]:
        """Proximity-sensor counters (left, right): whole holes passed, signed (thesis 4.3.2.3)."""
        c = self.settings.clock_mm
        lp, rp = self.wheel_phase_mm
        return math.floor((self.left_travel_mm + lp) / c), math.floor(
            (self.right_travel_mm + rp) / c
        )

    # -- pose and geometry --------------------------------------------------------------------

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x_mm, y_mm, theta_rad) of the axle midpoint in the world."""
        return (self.x_mm, self.y_mm, self.theta_rad)

    def state(self) -> ChairState:
        return ChairState(
            self.x_mm,
            self.y_mm,
            self.theta_rad,
            self.left_speed_mm_s,
            self.right_speed_mm_s,
            self.left_travel_mm,
            self.right_travel_mm,
        )

    def to_world(self, xy_robot_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Robot-frame points (N, 2) mm → world (N, 2) mm at the current pose."""
        p = np.asarray(xy_robot_mm, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.theta_rad), math.sin(self.theta_rad)
        return np.column_stack(
            [self.x_mm + c * p[:, 0] - s * p[:, 1], self.y_mm + s * p[:, 0] + c * p[:, 1]]
        )

    def footprint(self) -> NDArray[np.float64]:
        """The footprint's corners (4, 2) in the world, mm, counter-clockwise from front-right."""
        s = self.settings
        w = s.footprint_width_mm / 2.0
        f, r = s.footprint_front_mm, -s.footprint_rear_mm
        x, y, c, sn = self.x_mm, self.y_mm, math.cos(self.theta_rad), math.sin(self.theta_rad)
        # as to_world, on plain floats (4 points: numpy's overhead would be the whole cost)
        return np.array(
            [
                [x + c * u - sn * v, y + sn * u + c * v]
                for u, v in ((f, -w), (f, w), (r, w), (r, -w))
            ],
            dtype=np.float64,
        )

    def support_points(self) -> dict[str, NDArray[np.float64]]:
        """World positions (2,) of the points that must stay on the floor, by name."""
        s = self.settings
        local = {
            "centre of mass": (s.com_x_mm, 0.0),
            "left front (drive) wheel": (0.0, s.track_mm / 2.0),
            "right front (drive) wheel": (0.0, -s.track_mm / 2.0),
            "left castor": (s.castor_x_mm, s.castor_y_mm),
            "right castor": (s.castor_x_mm, -s.castor_y_mm),
        }
        pts = self.to_world(np.array(list(local.values()), dtype=np.float64))
        return {name: pts[i] for i, name in enumerate(local)}

    def _rects_of(self, world: _WorldLike) -> NDArray[np.float64]:
        """The boxes' rectangles (B, 4: x0, x1, y0, y1), remembered per world."""
        cached = getattr(self, "_rects_cache", None)
        if cached is not None and cached[0] is world:
            rects: NDArray[np.float64] = cached[1]
            return rects
        rects = np.array(
            [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm) for b in world.boxes],
            dtype=np.float64,
        ).reshape(-1, 4)
        self._rects_cache = (world, rects)
        return rects

    def contacts(self, world: _WorldLike) -> list[Contact]:
        """Everything the chair touches at its current pose that it must not.

        A box at least ``collision_height_mm`` tall that overlaps the footprint is a collision;
        a drop-off at least ``fall_depth_mm`` deep under the centre of mass or any wheel is a
        fall. Touching is overlap of positive area (grazing an edge is not a contact).
        """
        s = self.settings
        out = self._box_contacts(world, self.footprint())
        for i in self.blocked_by if world is self.world else ():
            if all(c.index != i for c in out):
                out.append(Contact("collision", i, "footprint"))
        support = self.support_points()
        for i, drop in enumerate(world.dropoffs):
            if float(drop.depth_mm) < s.fall_depth_mm:
                continue
            for name, p in support.items():
                if _inside(p, drop):
                    out.append(Contact("fall", i, name))
                    break
        return out

    def _box_contacts(self, world: _WorldLike, corners: NDArray[np.float64]) -> list[Contact]:
        """Collisions of the footprint with ``corners`` (4, 2) with the world's tall boxes."""
        s = self.settings
        out: list[Contact] = []
        axis = (math.cos(self.theta_rad), math.sin(self.theta_rad))
        pts = corners.tolist()
        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        lo_x, hi_x, lo_y, hi_y = min(xs), max(xs), min(ys), max(ys)
        # Only boxes whose rectangle meets the footprint's bounding box can overlap it.
        for i, (x0, x1, y0, y1) in enumerate(self._rects_of(world).tolist()):
            if not (x0 < hi_x and x1 > lo_x and y0 < hi_y and y1 > lo_y):
                continue
            box = world.boxes[i]
            if float(box.height_mm) >= s.collision_height_mm and _overlaps_aabb(pts, axis, box):
                out.append(Contact("collision", i, "footprint"))
        return out
