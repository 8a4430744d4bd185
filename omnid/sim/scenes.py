"""Named static scenes, laid out in the rig frame with the chair at the origin.

Every scene is a :class:`Scene`: a :class:`~omnid.sim.world.World`, the chair pose (0, 0, 0) and
the :class:`~omnid.sim.world.RigMount`. Positions below are given the way the thesis gives them —
distance ahead of the vision system (rig X, mm) and across it (rig Y, right positive) — and turned
into world coordinates (x = X + x_offset, y = −Y) by :func:`rig_rect`.

- ``horizontal_<Z>``: the Table 7.4 horizontal planes, a large flat table top whose surface lies
  Z = 680 / 800 / 930 mm below the mirrors, its near edge 450 mm ahead of the vision axis (7.2.2,
  Fig. 7.6a); Z = 1100 mm is the bare floor.
- ``vertical_<X>``: the Table 7.4 vertical planes, a wall facing the chair X = 550, 750, 1050,
  1150, 1450, 1750 mm ahead (Fig. 7.6b).
- ``three_boxes``: three obstacles on the floor (7.2.2, Fig. 7.10; the figure's dimensions are
  lost, so these are plausible household objects: 300x200x150, 250x300x250 and 200x200x100 mm).
- ``dropoff``: the floor falls 200 mm (a kerb / the first step of a stair) 1000 mm ahead.
- ``passage``: two obstacles leaving a 900 mm wide passage straight ahead.
- ``floor``: nothing but the floor.

For the installer's extra captures (SPEC §6: "a wall or a box ahead, of unknown size and
place") :func:`extra_scene` also draws ``wall`` and ``box`` scenes at random
(:func:`random_wall`, :func:`random_box`); ``random`` is either.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from omnid.core.geometry import StereoRig
from omnid.errors import InputError
from omnid.sim.world import Box, DropOff, Laser, LaserHits, RigMount, World, cast_laser

#: Table 7.4: depths of the horizontal planes below the mirrors, mm.
HORIZONTAL_PLANE_DEPTHS_MM = (680.0, 800.0, 930.0, 1100.0)
#: Table 7.4: distances of the vertical planes ahead of the vision system, mm.
VERTICAL_PLANE_DISTANCES_MM = (550.0, 750.0, 1050.0, 1150.0, 1450.0, 1750.0)
#: 7.2.2: the near side of the horizontal plane lies 450 mm ahead of the vision axis.
HORIZONTAL_PLANE_NEAR_MM = 450.0


@dataclass(frozen=True)
class Scene:
    """A named world with the chair standing at ``pose`` (robot frame in the world)."""

    name: str
    world: World
    mount: RigMount = field(default_factory=RigMount)
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    description: str = ""


def rig_rect(
    x_near_mm: float, x_far_mm: float, y_a_mm: float, y_b_mm: float, mount: RigMount
) -> tuple[float, float, float, float]:
    """A rectangle given in the rig frame (X from near to far ahead of the vision axis, rig Y
    between ``y_a_mm`` and ``y_b_mm``; rig Y is positive to the chair's right) → world
    (x_min, x_max, y_min, y_max), mm, for the chair at the origin."""
    lo, hi = min(y_a_mm, y_b_mm), max(y_a_mm, y_b_mm)
    return (x_near_mm + mount.x_offset_mm, x_far_mm + mount.x_offset_mm, -hi, -lo)


def _box(x0: float, x1: float, y0: float, y1: float, h: float, mount: RigMount) -> Box:
    return Box(*rig_rect(x0, x1, y0, y1, mount), height_mm=h)


def floor(mount: RigMount | None = None) -> Scene:
    """Nothing but the floor."""
    return Scene("floor", World(), mount or RigMount(), description="empty floor")


def horizontal_plane(depth_mm: float, mount: RigMount | None = None) -> Scene:
    """Table 7.4 horizontal plane ``depth_mm`` below the mirrors (1100 mm: the floor itself)."""
    m = mount or RigMount()
    height = m.height_mm - depth_mm
    name = f"horizontal_{depth_mm:g}"
    if height <= 0.5:
        return Scene(name, World(), m, description=f"floor at depth {m.height_mm:g} mm")
    plane = _box(
        HORIZONTAL_PLANE_NEAR_MM, HORIZONTAL_PLANE_NEAR_MM + 2000.0, -1000, 1000, height, m
    )
    return Scene(name, World((plane,)), m, description=f"horizontal plane at depth {depth_mm:g} mm")


def vertical_plane(distance_mm: float, mount: RigMount | None = None) -> Scene:
    """Table 7.4 vertical plane (a wall 2000 mm wide, 1000 mm high) ``distance_mm`` ahead."""
    m = mount or RigMount()
    wall = _box(distance_mm, distance_mm + 20.0, -1000, 1000, 1000.0, m)
    return Scene(
        f"vertical_{distance_mm:g}",
        World((wall,)),
        m,
        description=f"vertical plane {distance_mm:g} mm ahead",
    )


def three_boxes(mount: RigMount | None = None) -> Scene:
    """Three obstacles on the floor ahead (thesis Fig. 7.10, dimensions assumed)."""
    m = mount or RigMount()
    boxes = (
        _box(600, 900, -450, -250, 150.0, m),  # left front (rig Y negative = chair's left)
        _box(1000, 1250, -150, 150, 250.0, m),  # centre
        _box(700, 900, 250, 450, 100.0, m),  # right
    )
    return Scene("three_boxes", World(boxes), m, description="three boxes on the floor")


def dropoff(mount: RigMount | None = None, distance_mm: float = 1000.0) -> Scene:
    """The floor drops 200 mm ``distance_mm`` ahead, across the whole view (a kerb, a stair)."""
    m = mount or RigMount()
    pit = DropOff(*rig_rect(distance_mm, distance_mm + 3000.0, -3000, 3000, m), depth_mm=200.0)
    return Scene("dropoff", World((), (pit,)), m, description="200 mm drop-off ahead")


def passage(mount: RigMount | None = None, width_mm: float = 900.0) -> Scene:
    """Two obstacles 400 mm high leaving a passage ``width_mm`` wide straight ahead."""
    m = mount or RigMount()
    half = width_mm / 2.0
    boxes = (
        _box(700, 1300, -half - 400, -half, 400.0, m),
        _box(700, 1300, half, half + 400, 400.0, m),
    )
    return Scene("passage", World(boxes), m, description=f"passage {width_mm:g} mm wide")


def random_wall(rng: np.random.Generator, mount: RigMount | None = None) -> Scene:
    """A wall facing the chair 500–1500 mm ahead, 1.2–3 m wide (its middle up to 400 mm to
    either side), 0.6–1.2 m high, turned by up to ±15° about the vertical."""
    m = mount or RigMount()
    x = float(rng.uniform(500.0, 1500.0))
    width = float(rng.uniform(1200.0, 3000.0))
    mid = float(rng.uniform(-400.0, 400.0))
    height = float(rng.uniform(600.0, 1200.0))
    turn = float(rng.uniform(-15.0, 15.0))
    # A turned wall is a staircase of thin boxes (the world is axis-aligned), 50 mm a step.
    steps = max(int(width // 50.0), 1)
    ys = mid - width / 2.0 + (np.arange(steps) + 0.5) * (width / steps)
    xs = x + (ys - mid) * np.tan(np.radians(turn))
    half = width / steps / 2.0
    boxes = tuple(
        _box(float(xk), float(xk) + 30.0, float(yk) - half, float(yk) + half, height, m)
        for xk, yk in zip(xs, ys, strict=True)
    )
    return Scene(
        "wall",
        World(boxes),
        m,
        description=f"wall {x:.0f} mm ahead, {width:.0f} mm wide, turned {turn:+.1f}°",
    )


def random_box(rng: np.random.Generator, mount: RigMount | None = None) -> Scene:
    """A box 600–1300 mm ahead (near side), 300–900 mm deep, 300–1000 mm wide (its middle up
    to 400 mm to either side), 100–500 mm high."""
    m = mount or RigMount()
    x = float(rng.uniform(600.0, 1300.0))
    depth = float(rng.uniform(300.0, 900.0))
    width = float(rng.uniform(300.0, 1000.0))
    mid = float(rng.uniform(-400.0, 400.0))
    height = float(rng.uniform(100.0, 500.0))
    box = _box(x, x + depth, mid - width / 2.0, mid + width / 2.0, height, m)
    return Scene(
        "box",
        World((box,)),
        m,
        description=f"box {x:.0f} mm ahead, {width:.0f} x {depth:.0f} x {height:.0f} mm",
    )


#: The names :func:`extra_scene` draws at random (besides every named scene).
RANDOM_EXTRAS = ("wall", "box", "random")


def extra_scene(name: str, rng: np.random.Generator, mount: RigMount | None = None) -> Scene:
    """A scene for an installer's extra capture: ``wall`` or ``box`` drawn with ``rng``,
    ``random`` (either), or any named scene of :func:`get_scene`."""
    if name == "random":
        name = "wall" if rng.uniform() < 0.5 else "box"
    if name == "wall":
        return random_wall(rng, mount)
    if name == "box":
        return random_box(rng, mount)
    return get_scene(name)


def floor_hits(rig: StereoRig, laser: Laser, mount: RigMount | None = None) -> LaserHits:
    """The laser's dots on the empty floor at the rig's floor depth (the installer's capture
    for calibration), the chair at the origin of a ``mount`` of that height."""
    m = mount or RigMount()
    if m.height_mm != rig.floor_depth_mm:
        m = RigMount(x_offset_mm=m.x_offset_mm, height_mm=rig.floor_depth_mm)
    sc = floor(m)
    return cast_laser(sc.world, sc.pose, sc.mount, laser, rig)


def _registry() -> dict[str, Callable[[], Scene]]:
    reg: dict[str, Callable[[], Scene]] = {
        "floor": floor,
        "three_boxes": three_boxes,
        "dropoff": dropoff,
        "passage": passage,
    }
    for z in HORIZONTAL_PLANE_DEPTHS_MM:
        reg[f"horizontal_{z:g}"] = partial(horizontal_plane, z)
    for x in VERTICAL_PLANE_DISTANCES_MM:
        reg[f"vertical_{x:g}"] = partial(vertical_plane, x)
    return reg


def scene_names() -> list[str]:
    """Names accepted by :func:`get_scene`."""
    return list(_registry())


def get_scene(name: str) -> Scene:
    """The named scene; an unknown name raises :class:`InputError` listing the known ones."""
    reg = _registry()
    if name not in reg:
        raise InputError(f"scene {name!r}: unknown (known: {', '.join(reg)})")
    return reg[name]()
