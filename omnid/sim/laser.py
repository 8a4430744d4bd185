"""The simulator's physical laser: a source, a tilted beam axis and a fibre grating (SPEC §2).

This is the *world's* laser, not omnid's knowledge of it: perception must learn what it needs
from captures (calibration), never read it from here. Everything a real installation leaves
uncertain is a parameter, and :func:`random_laser` draws all of them.

Model. The laser sits at ``source_mm`` in the rig frame (SPEC §2: X forward, Y along the
baseline, Z down; the mirror plane is Z = 0, so a negative Z is above the mirrors). Its beam
axis w points down and forward, ``axis_tilt_rad`` from the vertical toward +X and
``axis_yaw_rad`` toward +Y. A fibre grating device (two crossed layers of fibres) splits the beam
into diffraction orders (m, n). In the beam frame (u forward across the axis, v sideways, both
turned by ``roll_rad`` about w) order (m, n) has pattern coordinates

    a = m·pitch_u + n·pitch_v·sin(skew),   b = n·pitch_v·cos(skew)

(``skew_rad``: the second fibre layer not exactly perpendicular to the first), and its direction
follows the grating law:

    "sine"   the grating equation sin θ = m·λ/d per axis: (a, b) are direction cosines along
             (u, v) and the w component is √(1 − a² − b²) (orders with a² + b² ≥ 1 do not exist)
    "angle"  uniform in angle per axis: direction ∝ (tan a, tan b, 1)
    "slope"  uniform in slope per axis: direction ∝ (a, b, 1) — the special case of a regular
             slope lattice (with the source at the rig origin and the axis vertical it is the old
             ``DotPattern``, :func:`ideal_lattice`)

Real patterns are not perfect: each beam's direction carries a small random error
(``jitter_rad``), a share of beams is missing (``missing_fraction``) or doubled by a close twin
(``double_fraction``, ``double_offset_rad`` apart, dimmer), and the brightness falls off with the
angle θ from the axis as exp(−(θ/envelope_rad)²) (the envelope of one fibre's own diffraction,
which weights the grating's orders; ``None``: all orders equally bright). The housing's aperture
passes only beams within ``field_rad`` = (half-angle along u, half-angle along v) of the axis,
each measured in the (u, w) and (v, w) planes.

Which parameters are plausible, and why the ranges of :class:`LaserSpread` are what they are, is
in docs/laser.md.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require

GratingLaw = Literal["sine", "angle", "slope"]
GRATING_LAWS: tuple[GratingLaw, ...] = ("sine", "angle", "slope")

#: Beams closer to horizontal than this (their Z component, unit direction) never reach the
#: floor within view and are not cast.
_MIN_DOWN = 0.05


@dataclass(frozen=True)
class LaserRays:
    """The beams a projector throws: one origin, one unit direction per beam.

    origin_mm   (3,) the source in the rig frame, mm
    directions  (N, 3) unit vectors (Z component > 0: down)
    brightness  (N,) relative beam power, 1 on the axis
    orders      (N, 2) diffraction orders (m, n) of each beam (a doubled beam repeats its twin's)
    twin        (N,) index of the beam a doubled beam was split from, −1 for ordinary beams
    """

    origin_mm: NDArray[np.float64]
    directions: NDArray[np.float64]
    brightness: NDArray[np.float64]
    orders: NDArray[np.int64]
    twin: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.directions)

    def slopes(self) -> NDArray[np.float64]:
        """(N, 2) each beam's (ΔX/ΔZ, ΔY/ΔZ): a dot ΔZ below the source lies at
        origin + ΔZ·(slope_x, slope_y, 1) (for a source at the rig origin, the old lattice's
        slopes X/Z, Y/Z)."""
        return self.directions[:, :2] / self.directions[:, 2:3]

    def on_plane(self, depth_mm: float) -> NDArray[np.float64]:
        """Dots (N, 3) mm the beams make on a horizontal plane ``depth_mm`` below the mirrors
        (NaN for a plane the beam cannot reach: at or above the source)."""
        o = self.origin_mm
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (float(depth_mm) - o[2]) / self.directions[:, 2]
        t = np.where(t > 0, t, np.nan)
        return o[None, :] + t[:, None] * self.directions


@dataclass(frozen=True)
class LaserProjector:
    """A laser and fibre grating device as mounted on the rig (mm, rad; see the module doc)."""

    source_mm: tuple[float, float, float] = (8.0, -6.0, -90.0)
    axis_tilt_rad: float = math.radians(41.0)
    axis_yaw_rad: float = 0.0
    roll_rad: float = math.radians(1.0)
    law: GratingLaw = "sine"
    pitch_u: float = 0.065  # per order along u: direction cosine (sine), rad (angle), slope
    pitch_v: float = 0.075  # likewise along v
    orders_u: tuple[int, int] = (-10, 10)  # inclusive range of m
    orders_v: tuple[int, int] = (-14, 14)  # inclusive range of n
    field_rad: tuple[float, float] = (math.radians(25.0), math.radians(48.0))  # aperture
    skew_rad: float = math.radians(0.5)
    envelope_rad: float | None = math.radians(45.0)  # brightness exp(−(θ/envelope)²); None: flat
    missing_fraction: float = 0.01
    double_fraction: float = 0.005
    double_offset_rad: float = 0.006  # angle between a doubled beam and its twin
    double_brightness: float = 0.6  # a twin's power relative to its beam
    jitter_rad: float = 0.0003  # per-beam direction error (1 σ per axis)
    seed: int = 0  # draws which beams are missing or doubled, and the jitter

    def __post_init__(self) -> None:
        src = tuple(float(v) for v in self.source_mm)
        require(len(src) == 3 and all(map(math.isfinite, src)), "source_mm", "must be 3 finite mm")
        object.__setattr__(self, "source_mm", src)
        require(self.law in GRATING_LAWS, "law", f"must be one of {', '.join(GRATING_LAWS)}")
        require(0 <= self.axis_tilt_rad < math.radians(80), "axis_tilt_rad", "must be in [0, 80°)")
        require(abs(self.axis_yaw_rad) < math.radians(30), "axis_yaw_rad", "must be within ±30°")
        require(abs(self.roll_rad) < math.pi, "roll_rad", "must be within ±π")
        require(abs(self.skew_rad) < math.radians(20), "skew_rad", "must be within ±20°")
        for name in ("pitch_u", "pitch_v"):
            v = getattr(self, name)
            require(math.isfinite(v) and 0 < v < 0.5, name, "must be in (0, 0.5)")
        for name in ("orders_u", "orders_v"):
            lo, hi = getattr(self, name)
            require(int(lo) <= int(hi) and hi - lo <= 400, name, "must be (low, high), low ≤ high")
        fu, fv = self.field_rad
        require(0 < fu < math.pi / 2 and 0 < fv < math.pi / 2, "field_rad", "must be in (0, 90°)")
        env = self.envelope_rad
        require(env is None or (math.isfinite(env) and env > 0), "envelope_rad", "must be > 0")
        for name in ("missing_fraction", "double_fraction"):
            require(0 <= getattr(self, name) < 0.5, name, "must be in [0, 0.5)")
        require(0 <= self.double_offset_rad < 0.05, "double_offset_rad", "must be in [0, 0.05)")
        require(0 < self.double_brightness <= 1, "double_brightness", "must be in (0, 1]")
        require(0 <= self.jitter_rad < 0.01, "jitter_rad", "must be in [0, 0.01)")

    def beam_frame(self) -> NDArray[np.float64]:
        """Rows u, v, w (3, 3): the pattern axes and the beam axis as rig-frame unit vectors."""
        t, y, r = self.axis_tilt_rad, self.axis_yaw_rad, self.roll_rad
        w = np.array([math.sin(t) * math.cos(y), math.sin(t) * math.sin(y), math.cos(t)])
        # u: forward across the axis (in the plane of w and +X, pointing forward-up); v = w × u.
        u = np.array([math.cos(t) * math.cos(y), math.cos(t) * math.sin(y), -math.sin(t)])
        v = np.cross(w, u)
        cr, sr = math.cos(r), math.sin(r)
        return np.array([cr * u + sr * v, -sr * u + cr * v, w])

    def rays(self) -> LaserRays:
        """Every beam that points down, with its brightness (computed once per projector)."""
        return _rays(self)

    def on_plane(self, depth_mm: float) -> NDArray[np.float64]:
        """Dots (N, 3) mm on a horizontal plane ``depth_mm`` below the mirrors."""
        return self.rays().on_plane(depth_mm)


def _directions(
    law: GratingLaw, a: NDArray[np.float64], b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Beam-frame directions (N, 3) (unnormalised) and which orders exist, per grating law."""
    if law == "sine":
        s = a * a + b * b
        exists = s < 1.0
        return np.column_stack([a, b, np.sqrt(np.clip(1.0 - s, 0.0, None))]), exists
    if law == "angle":
        exists = (np.abs(a) < math.radians(85)) & (np.abs(b) < math.radians(85))
        return np.column_stack([np.tan(a), np.tan(b), np.ones_like(a)]), exists
    return np.column_stack([a, b, np.ones_like(a)]), np.ones(len(a), dtype=bool)


@functools.lru_cache(maxsize=32)
def _rays(p: LaserProjector) -> LaserRays:
    rng = np.random.default_rng(p.seed)
    grid_m, grid_n = np.meshgrid(
        np.arange(p.orders_u[0], p.orders_u[1] + 1),
        np.arange(p.orders_v[0], p.orders_v[1] + 1),
        indexing="ij",
    )
    m, n = grid_m.ravel(), grid_n.ravel()
    a = np.asarray(m * p.pitch_u + n * p.pitch_v * math.sin(p.skew_rad), dtype=np.float64)
    b = np.asarray(n * p.pitch_v * math.cos(p.skew_rad), dtype=np.float64)
    d_beam, exists = _directions(p.law, a, b)
    d_beam = d_beam / np.linalg.norm(d_beam, axis=1, keepdims=True)
    # The grating is not perfect: every beam is off by a small random angle (small-angle
    # rotation: add a perpendicular offset and renormalise).
    jitter = rng.normal(0.0, p.jitter_rad, (len(d_beam), 2))
    if p.jitter_rad > 0:
        d_beam[:, :2] += jitter
        d_beam /= np.linalg.norm(d_beam, axis=1, keepdims=True)
    theta = np.arccos(np.clip(d_beam[:, 2], -1.0, 1.0))
    if p.envelope_rad is None:
        brightness = np.ones(len(theta))
    else:
        brightness = np.exp(-((theta / p.envelope_rad) ** 2))
    inside = (np.abs(np.arctan2(d_beam[:, 0], d_beam[:, 2])) <= p.field_rad[0]) & (
        np.abs(np.arctan2(d_beam[:, 1], d_beam[:, 2])) <= p.field_rad[1]
    )
    keep = exists & inside & (rng.uniform(size=len(m)) >= p.missing_fraction)
    doubled = keep & (rng.uniform(size=len(m)) < p.double_fraction)
    frame = p.beam_frame()
    d_rig = d_beam @ frame  # beam-frame components → rig frame (rows of frame are u, v, w)

    orders = np.column_stack([m, n]).astype(np.int64)
    idx = np.flatnonzero(keep)
    twins = np.flatnonzero(doubled)
    # A twin leaves at double_offset_rad from its beam, in a random direction across it.
    ang = rng.uniform(0.0, 2.0 * math.pi, len(twins))
    d_twin = d_rig[twins].copy()
    side1 = np.cross(d_twin, frame[2])
    side1 /= np.maximum(np.linalg.norm(side1, axis=1, keepdims=True), 1e-12)
    side2 = np.cross(d_twin, side1)
    d_twin += p.double_offset_rad * (np.cos(ang)[:, None] * side1 + np.sin(ang)[:, None] * side2)
    d_twin /= np.linalg.norm(d_twin, axis=1, keepdims=True)

    directions = np.vstack([d_rig[idx], d_twin])
    bright = np.concatenate([brightness[idx], brightness[twins] * p.double_brightness])
    ords = np.vstack([orders[idx], orders[twins]])
    # Twins point at their beam by its position in the output.
    position = np.full(len(m), -1, dtype=np.int64)
    position[idx] = np.arange(len(idx))
    twin = np.concatenate([np.full(len(idx), -1, dtype=np.int64), position[twins]])
    down = directions[:, 2] > _MIN_DOWN
    out = LaserRays(
        np.array(p.source_mm, dtype=np.float64),
        directions[down],
        bright[down],
        ords[down],
        _reindex(twin, down),
    )
    for arr in (out.origin_mm, out.directions, out.brightness, out.orders, out.twin):
        arr.setflags(write=False)
    return out


def _reindex(twin: NDArray[np.int64], keep: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Twin indices after dropping the beams where ``keep`` is False (a dropped twin → −1)."""
    new_pos = np.cumsum(keep) - 1
    t = twin[keep]
    valid = t >= 0
    valid[valid] = keep[t[valid]]
    return np.where(valid, new_pos[np.where(t >= 0, t, 0)], -1).astype(np.int64)


def ideal_lattice(
    rows: int = 19, cols: int = 25, step_slope: float = 0.10, forward_min_slope: float = 0.30
) -> LaserProjector:
    """The regular slope lattice from a source at the rig origin (the thesis' idealisation and
    omnid's old ``DotPattern``): rays (X/Z, Y/Z) = (forward_min_slope + step·l, step·(k − (cols−1)/2)).
    Only for comparison — a real laser is never this."""
    require(rows >= 1 and cols >= 1, "rows", "need at least one row and one column")
    first = forward_min_slope / step_slope
    if abs(first - round(first)) > 1e-9:
        raise ValueError("ideal_lattice: forward_min_slope must be a multiple of step_slope")
    lo = round(first)
    half = (cols - 1) / 2.0
    if cols % 2 == 0:
        raise ValueError("ideal_lattice: cols must be odd (the lattice is centred on Y = 0)")
    return LaserProjector(
        source_mm=(0.0, 0.0, 0.0),
        axis_tilt_rad=0.0,
        axis_yaw_rad=0.0,
        roll_rad=0.0,
        law="slope",
        pitch_u=step_slope,
        pitch_v=step_slope,
        orders_u=(lo, lo + rows - 1),
        orders_v=(-round(half), round(half)),
        field_rad=(math.radians(89.0), math.radians(89.0)),
        skew_rad=0.0,
        envelope_rad=None,
        missing_fraction=0.0,
        double_fraction=0.0,
        jitter_rad=0.0,
    )


@dataclass(frozen=True)
class LaserSpread:
    """The ranges :func:`random_laser` draws from (uniform unless said otherwise; mm, rad).

    Source: a few cm off the baseline's midpoint sideways and forward, up to ±150 mm above or
    below the mirror plane (SPEC §2). Axis, pitch, roll and skew: what a hand-mounted fibre
    grating plausibly gives with the dots still covering the floor ahead of the chair.
    """

    source_x_mm: float = 30.0
    source_y_mm: float = 30.0
    source_z_mm: float = 150.0
    axis_tilt_rad: tuple[float, float] = (math.radians(36.0), math.radians(46.0))
    axis_yaw_rad: float = math.radians(3.0)
    roll_rad: float = math.radians(4.0)
    laws: tuple[GratingLaw, ...] = GRATING_LAWS
    pitch_u: tuple[float, float] = (0.058, 0.075)
    pitch_v: tuple[float, float] = (0.065, 0.085)
    field_u_rad: tuple[float, float] = (math.radians(22.0), math.radians(28.0))
    field_v_rad: tuple[float, float] = (math.radians(42.0), math.radians(52.0))
    skew_rad: float = math.radians(2.0)
    envelope_rad: tuple[float, float] = (math.radians(40.0), math.radians(90.0))
    missing_fraction: tuple[float, float] = (0.0, 0.03)
    double_fraction: tuple[float, float] = (0.0, 0.02)
    double_offset_rad: tuple[float, float] = (0.003, 0.012)
    jitter_rad: tuple[float, float] = (0.0, 0.0008)


def random_laser(
    rng: np.random.Generator | int, spread: LaserSpread | None = None
) -> LaserProjector:
    """A laser drawn from ``spread`` (every parameter of :class:`LaserProjector` at random).

    The grating throws more orders than the aperture passes, as a real one does: the order
    range is chosen to fill the aperture under any law.
    """
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    s = spread or LaserSpread()
    law = s.laws[int(gen.integers(len(s.laws)))]
    pitch_u = float(gen.uniform(*s.pitch_u))
    pitch_v = float(gen.uniform(*s.pitch_v))
    field = (float(gen.uniform(*s.field_u_rad)), float(gen.uniform(*s.field_v_rad)))
    # Enough orders to fill the aperture under any law (the aperture cuts the rest).
    reach = {"sine": math.sin, "angle": lambda x: x, "slope": math.tan}[law]
    mu = math.ceil(reach(field[0]) / pitch_u) + 2
    mv = math.ceil(reach(field[1]) / pitch_v) + 2
    return LaserProjector(
        source_mm=(
            float(gen.uniform(-s.source_x_mm, s.source_x_mm)),
            float(gen.uniform(-s.source_y_mm, s.source_y_mm)),
            float(gen.uniform(-s.source_z_mm, s.source_z_mm)),
        ),
        axis_tilt_rad=float(gen.uniform(*s.axis_tilt_rad)),
        axis_yaw_rad=float(gen.uniform(-s.axis_yaw_rad, s.axis_yaw_rad)),
        roll_rad=float(gen.uniform(-s.roll_rad, s.roll_rad)),
        law=law,
        pitch_u=pitch_u,
        pitch_v=pitch_v,
        orders_u=(-mu, mu),
        orders_v=(-mv, mv),
        field_rad=field,
        skew_rad=float(gen.uniform(-s.skew_rad, s.skew_rad)),
        envelope_rad=float(gen.uniform(*s.envelope_rad)),
        missing_fraction=float(gen.uniform(*s.missing_fraction)),
        double_fraction=float(gen.uniform(*s.double_fraction)),
        double_offset_rad=float(gen.uniform(*s.double_offset_rad)),
        jitter_rad=float(gen.uniform(*s.jitter_rad)),
        seed=int(gen.integers(2**31)),
    )
