"""Shared pieces of the scenario suite: courses, riders and the promises the config makes."""

from __future__ import annotations

import math

from omnid.sim.course import WALL_MM, Course, walls
from omnid.sim.rider import HeadScript, head_script
from omnid.sim.world import Box, DropOff, World


def make_core(joystick: bool = False) -> object:
    from omnid.sim.scenario import make_core as _make

    return _make(joystick=joystick)


def room(
    boxes: tuple[Box, ...] = (), dropoffs: tuple[DropOff, ...] = (), length_mm: float = 6000.0
) -> Course:
    """A walled room 4 m wide, ``length_mm`` long; the chair starts 1 m from the back wall."""
    x0, x1, y0, y1 = -1000.0, length_mm - 1000.0, -2000.0, 2000.0
    world = World(boxes=(*boxes, *walls(x0, x1, y0, y1)), dropoffs=dropoffs)
    return Course(
        "scenario",
        world,
        (0.0, 0.0, 0.0),
        (x0 - WALL_MM, x1 + WALL_MM),
        (y0 - WALL_MM, y1 + WALL_MM),
    )


def forward_rider(hold_s: float, start_s: float = 0.5) -> HeadScript:
    return head_script([("neutral", start_s), ("forward", hold_s)])


STANDSTILL_MM_S = 2.0  # "wheels at zero": both slower than this


def brake_time_s(core: object, speed_mm_s: float | None = None) -> float:
    """Emergency braking from top speed, plus the motors' first-order lag (τ = 0.15 s) running
    out from that speed to :data:`STANDSTILL_MM_S` (τ·ln(v/tol)), s."""
    m = core.config.motion  # type: ignore[attr-defined]
    v = m.max_speed_mm_s if speed_mm_s is None else speed_mm_s
    return v / m.emergency_decel_mm_s2 + 0.15 * math.log(v / STANDSTILL_MM_S)


def finite(x: float) -> bool:
    return math.isfinite(x)
