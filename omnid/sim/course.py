"""The built-in course: a walled room with three boxes, a wide and a narrow passage, and stairs.

World frame (``omnid.sim.world``): x, y on the floor with y to the left, mm. The chair starts at
the origin facing +x. Layout, seen from above (x up the page)::

    x = 6000  ───────────── wall ──────────────
    x = 3900  ═════════════ narrow ════════════   partition B x 3800–3900, narrow gap y −225…225
                  [box 3]                         (x 2200–2500, y −1100…−700, 500 mm tall)
      ░░stairs down 170 mm░░                      (drop-off x 2000–3800, y −2200…−1700)
    x = 2000  ═════════════ wide ══════════════   partition A x 1900–2000, wide gap y −550…550
              [box 2]                             (x 1300–1700, y −1100…−600, 600 mm)
                          [box 1]                 (x 800–1200, y 550…950, 400 mm)
    x = 0            chair ▲ (start)
    x = −1300 ───────────── wall ──────────────
              y = −2200 (right)        y = +2200 (left)

The chair (700 mm wide, plus the daemon's 50 mm margin on a 50 mm map grid) fits through the
wide gap but not the narrow one; driving straight on from the start leads through the wide gap
to the narrow one, which the daemon must refuse; to the right of that room are the stairs, and
box 3 stands beside the way to them (the demo story: :func:`omnid.sim.story.demo_story`).
"""

from __future__ import annotations

from dataclasses import dataclass

from omnid.sim.rider import HeadScript, KeyScript, head_script
from omnid.sim.world import Box, DropOff, World

WALL_MM = 100.0
WALL_HEIGHT_MM = 1000.0


@dataclass(frozen=True)
class Course:
    """A world with a start pose and a short description of what is in it."""

    name: str
    world: World
    start_pose: tuple[float, float, float]
    x_range_mm: tuple[float, float]
    y_range_mm: tuple[float, float]
    labels: tuple[tuple[str, float, float], ...] = ()  # (text, x_mm, y_mm) for drawings


def walls(x_min: float, x_max: float, y_min: float, y_max: float) -> tuple[Box, ...]:
    """Four walls enclosing the floor rectangle (walls stand just outside it)."""
    t, h = WALL_MM, WALL_HEIGHT_MM
    return (
        Box(x_min - t, x_max + t, y_min - t, y_min, h),  # right
        Box(x_min - t, x_max + t, y_max, y_max + t, h),  # left
        Box(x_min - t, x_min, y_min, y_max, h),  # back
        Box(x_max, x_max + t, y_min, y_max, h),  # front
    )


def builtin_course() -> Course:
    """The demo course described in the module docstring."""
    x0, x1, y0, y1 = -1300.0, 6000.0, -2200.0, 2200.0
    pa0, pa1 = 1900.0, 2000.0  # partition A, wide gap
    pb0, pb1 = 3800.0, 3900.0  # partition B, narrow gap
    wide, narrow = (-550.0, 550.0), (-225.0, 225.0)
    partitions = (
        Box(pa0, pa1, y0, wide[0], WALL_HEIGHT_MM),
        Box(pa0, pa1, wide[1], y1, WALL_HEIGHT_MM),
        Box(pb0, pb1, y0, narrow[0], WALL_HEIGHT_MM),
        Box(pb0, pb1, narrow[1], y1, WALL_HEIGHT_MM),
    )
    boxes = (
        Box(800.0, 1200.0, 550.0, 950.0, 400.0),
        Box(1300.0, 1700.0, -1100.0, -600.0, 600.0),
        Box(2200.0, 2500.0, -1100.0, -700.0, 500.0),
    )
    stairs = DropOff(pa1, pb0, y0, -1700.0, 170.0)
    world = World(boxes=(*boxes, *partitions, *walls(x0, x1, y0, y1)), dropoffs=(stairs,))
    return Course(
        name="builtin",
        world=world,
        start_pose=(0.0, 0.0, 0.0),
        x_range_mm=(x0 - WALL_MM, x1 + WALL_MM),
        y_range_mm=(y0 - WALL_MM, y1 + WALL_MM),
        labels=(
            ("box 1", 1000.0, 750.0),
            ("box 2", 1500.0, -850.0),
            ("box 3", 2350.0, -900.0),
            ("wide passage", 1700.0, 0.0),
            ("narrow passage", 4100.0, 0.0),
            ("stairs down", 2900.0, -1950.0),
        ),
    )


def empty_room(length_mm: float = 4000.0, width_mm: float = 3000.0) -> Course:
    """A walled empty room ``length_mm`` long; the chair starts 1 m from the back wall (its rear
    reaches 750 mm behind the axle), facing the front wall ``length_mm − 1000`` mm ahead."""
    x0, x1 = -1000.0, length_mm - 1000.0
    y0, y1 = -width_mm / 2.0, width_mm / 2.0
    return Course(
        name="empty-room",
        world=World(boxes=walls(x0, x1, y0, y1)),
        start_pose=(0.0, 0.0, 0.0),
        x_range_mm=(x0 - WALL_MM, x1 + WALL_MM),
        y_range_mm=(y0 - WALL_MM, y1 + WALL_MM),
    )


def box_ahead() -> Course:
    """A walled room 6 m long with one box (600 mm tall) straight ahead: its near face 2 m in
    front of the chair's axle (1.6 m in front of its footrests)."""
    x0, x1, y0, y1 = -1000.0, 5000.0, -2000.0, 2000.0
    box = Box(2000.0, 2400.0, -400.0, 400.0, 600.0)
    return Course(
        name="box-ahead",
        world=World(boxes=(box, *walls(x0, x1, y0, y1))),
        start_pose=(0.0, 0.0, 0.0),
        x_range_mm=(x0 - WALL_MM, x1 + WALL_MM),
        y_range_mm=(y0 - WALL_MM, y1 + WALL_MM),
        labels=(("box", 2200.0, 0.0),),
    )


def demo_rider() -> HeadScript:
    """The demo's rider: straight on through the wide passage towards the stairs (the daemon must
    stop the chair before them), turn left, forward towards box 3 (must stop again), then rest."""
    return head_script(
        [
            ("neutral", 1.0),
            ("forward", 32.0),
            ("neutral", 1.0),
            ("left", 10.0),
            ("neutral", 0.5),
            ("forward", 12.0),
            ("stop", 1.0),
            ("neutral", 1.0),
        ]
    )


def demo_keys() -> KeyScript:
    """The same ride as :func:`demo_rider` on the keyboard."""
    return KeyScript(((1.3, "forward"), (34.6, "left"), (45.6, "forward"), (58.1, "stop")))


COURSES = {"builtin": builtin_course, "empty-room": empty_room, "box-ahead": box_ahead}


def get_course(name: str) -> Course:
    """A named course (``builtin``, ``empty-room`` or ``box-ahead``)."""
    try:
        return COURSES[name]()
    except KeyError:
        from omnid.errors import InputError

        raise InputError(f"unknown course {name!r} (known: {', '.join(COURSES)})") from None
