"""The safety layer: a command runs only if it is safe in the free-space map (thesis 4.1.2).

The chair's footprint (a rectangle in the robot frame, plus a margin ahead and behind and a
side margin left and right) is swept along the
commanded motion — a straight line, an arc or a turn in place, exactly as the wheels would move
it (:func:`omnid.core.kinematics.integrate_arc`) — over a look-ahead horizon, and checked
against an :class:`~omnid.core.occupancy.OccupancyGrid`. Obstacles and drop-offs both block.
The path parameter ``s`` is the travel of the footprint's fastest point (the axle midpoint on a
straight line, the farthest corner when turning in place), so one set of distances serves every
kind of motion. Each contact is met by the footprint's **leading face** — its front (margin
strip and corners included) driving forward, its rear reversing — or by its sides and trailing
face: the **swing** of a turn (a differential drive turns about its axle, so the tail 750 mm
behind it moves sideways at 750·ω whatever v is; a turn in place has no leading face). What the
leading face drives into is what the laser sees ahead now, approached head-on; a swing meets
what lies beside the chair, seen before, and closes only while the rider keeps turning. From
the first leading contact come:

- stop zone: ≤ ``stop_distance_mm`` → no motion in that direction, unless the move is
  an escape move (below) → at most ``escape_speed_mm_s`` / ``escape_turn_rad_s``;
- slow zone: ≤ ``slow_distance_mm`` → at most ``slow_speed_mm_s``;
- approach: time to reach the stop line ≥ ``approach_time_s``, and the chair can still brake
  before it at ``brake_decel_mm_s2``, but never slower than ``approach_min_speed_mm_s`` (so
  that it arrives at the stop line instead of creeping towards it ever slower);

and from the first swing contact only what physics asks: the fastest point no faster than it
can still stop ``swing_buffer_mm`` before it (``reaction_time_s`` at that speed, then
``brake_decel_mm_s2``; reason ``approach``), and no motion that way once it is within the
buffer plus the stopping distance from ``approach_min_speed_mm_s`` (stop zone, escape rule as
above). The buffer is for what the dots do not show: a thing is sampled by laser dots tens of
mm apart (a box corner lies between them), which the leading face's 150 mm hides. So a rider
correcting the heading in a door frame or beside a wall is not refused 150 mm of a corner's
travel (10° of turn) before the tail would reach the margin. (``clearance`` is the first contact
of either kind.) Further:

- unknown space: if more than ``unknown_max_fraction`` of the swept cells within
  ``unknown_distance_mm`` are unknown → at most ``unknown_speed_mm_s``;
- unseen space is not free (``unknown_policy``): the footprint's sweep into cells never seen —
  the tail swinging out in a turn, every reverse move, an arc beside the chair — is refused
  like an obstacle's stop zone (``refuse``, reason ``unknown_stop``), and the chair may only
  approach it as fast as it could still stop before it (reason ``unknown_ahead``) — split by
  face as above: ahead of the leading face by cell centres against the footprint itself and the
  stop zone; in a swing each cell by its whole extent against the footprint itself and the
  stopping distance (no buffer: the whole cell is taken), so it never enters one; with
  ``creep`` it is crossed at ``unknown_creep_speed_mm_s`` (``unknown_creep``). One band is
  crossed at creep speed under either policy: the ``front_blind_mm`` straight ahead of the
  footrests, which the laser cannot see from where the chair stands (its nearest dots fall
  farther out) — at start-up only driving into it shows what lies beyond; once the chair has
  moved that far the band lies in what the first capture saw;
- stale perception (no cloud, or older than ``perception_timeout_s``) → no forward motion.

Blocking evidence comes from the map (``FreeSpaceMap.blocking_evidence``): the obstacle dots
themselves where the laser saw them (exact, no cell quantisation) and cell centres grown by
their half-diagonal elsewhere; from a bare grid, every blocking cell is a grown centre.

Escape moves (a chair in a pocket between boxes must not be stranded): in the stop zone, a move
that does not close the gap to what is near is allowed at a creep speed. The gap is the smallest
distance from the footprint (without margin) to the blocking cells within
``margin_mm + stop_distance_mm`` (plus a cell and the step) of it; it is evaluated now and at
poses along the first ``escape_step_mm`` of the commanded motion, and the move is an escape if
it never drops by more than ``escape_tolerance_mm``. The margin is never traded: over the same
step no cell may come nearer than ``margin_mm`` (one already inside the margin: no nearer at
all), exactly per cell — the sweep's grown corners are too coarse for a chair wedged in a
corner. The control loop re-checks every cycle, so the creep ends where the gap would close
or the margin be reached. A move whose first contact is a drop-off is never an escape
(``dropoff_stop`` stays a refusal). Reason ``escape_creep``.

The most restrictive limit wins; the rider's v and ω are scaled by one factor, so the chair keeps
the path the rider asked for — except that, with ``soften`` on (the default), a limited turn (or a straight
request limited by a one-sided intrusion, ``soften_side_shift_mm``) is softened: a small set
of nearby twists (:meth:`SafetyLayer.soften_candidates`: gentler turns, less or no travel, a turn
in place with a forward component) is checked by all the same rules, and the allowed twist with
the most progress along the asked one, less its deviation from it, runs instead (reason
``softened``); the request's own scaled twist is one of the set, standing still scores 0. Cells under the chair itself (the footprint without its margin)
at the start are ignored: the vision system cannot see there, and the chair physically occupies
them. Cells inside the margin count: a motion that brings one nearer is refused at once.

Every limitation comes with :class:`Reason` codes and is logged (rate-limited per reason, see
:class:`ReasonLog`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum
from typing import Any, Literal, NamedTuple, overload

import numpy as np
from numpy.typing import NDArray

from omnid.config import Settings, require, setting
from omnid.core.freespace import UnseenCells
from omnid.core.kinematics import integrate_arc
from omnid.core.occupancy import CellState, GridSettings, OccupancyGrid

log = logging.getLogger(__name__)


class Reason(Enum):
    """Why the safety layer (or the core) limited or refused a command."""

    OBSTACLE_STOP = "obstacle_stop"
    DROPOFF_STOP = "dropoff_stop"
    SLOW_ZONE = "slow_zone"
    APPROACH = "approach"
    ESCAPE = "escape_creep"  # in the stop zone, but the move opens the gap: creep speed
    UNKNOWN_AHEAD = "unknown_ahead"
    UNKNOWN_STOP = "unknown_stop"  # the sweep would enter space never seen: refused
    UNKNOWN_CREEP = "unknown_creep"  # ... crossed at creep speed (policy creep, blind band)
    SOFTENED = "softened"  # the asked turn was limited: the nearest allowed twist runs instead
    BUMP = "bump"  # a wheel did not turn as commanded: stopped, that direction refused
    PERCEPTION_STALE = "perception_stale"
    CALIBRATION_LOST = "calibration_lost"  # the captures no longer fit the calibration
    CAMERA_LOST = "camera_lost"  # the cameras deliver nothing: speed capped until they do
    RIDER_STOP = "rider_stop"
    INPUT_STALE = "input_stale"
    STATUS_STALE = "status_stale"
    FAULT = "fault"


#: What each limit means to whoever reads the journal (a caregiver, the installer), logged
#: after the reason's code.
REASON_TEXT = {
    Reason.OBSTACLE_STOP: "an obstacle in the way",
    Reason.DROPOFF_STOP: "a step or drop-off in the way",
    Reason.SLOW_ZONE: "an obstacle or drop-off near the way",
    Reason.APPROACH: "closing in on what stops the chair",
    Reason.ESCAPE: "moving out of the stop zone, slowly",
    Reason.UNKNOWN_AHEAD: "much of the way not seen yet",
    Reason.UNKNOWN_STOP: (
        "the chair would move onto floor it has not seen (the tail in a turn, or reversing; "
        "after a start, drive forward a little first)"
    ),
    Reason.UNKNOWN_CREEP: "crossing floor not seen, slowly",
    Reason.SOFTENED: "the turn asked for runs gentler",
}


@dataclass(frozen=True)
class SafetySettings(Settings):
    """Footprint (mm, robot frame: axle midpoint origin), zones and limits."""

    # from the axle forward (drive wheels are at the front)
    footprint_front_mm: float = setting(350.0, 50.0, 2000.0)
    footprint_rear_mm: float = setting(750.0, 50.0, 2000.0)  # from the axle backward (castors)
    footprint_width_mm: float = setting(700.0, 200.0, 2000.0)
    margin_mm: float = setting(50.0, 0.0, 500.0)  # added ahead and behind
    # added left and right: a doorway 820 mm clear leaves 60 mm beside a 700 mm chair — the
    # side margin, the rider's aim and the seen points' noise must fit in it; openings narrower
    # than the chair plus both side margins are refused
    side_margin_mm: float = setting(25.0, 0.0, 500.0)
    # look-ahead along the path (fastest footprint point)
    horizon_mm: float = setting(2500.0, 200.0, 10000.0)
    stop_distance_mm: float = setting(150.0, 10.0, 2000.0)
    slow_distance_mm: float = setting(600.0, 10.0, 5000.0)
    slow_speed_mm_s: float = setting(100.0, 10.0, 1000.0)
    # time to the stop line must be at least this
    approach_time_s: float = setting(2.0, 0.1, 10.0)
    # the chair must be able to stop before the stop line
    brake_decel_mm_s2: float = setting(600.0, 50.0, 5000.0)
    # a request to the wheels braking: a control period plus the motors' lag (time constant
    # 0.1-0.2 s), rounded up; with brake_decel_mm_s2 the stopping distance a turn's swing (a
    # contact on the sides or the trailing face) needs instead of the stop zone
    reaction_time_s: float = setting(0.3, 0.0, 2.0)
    # ... and a swing stops this far (fastest point's travel) before what the sweep meets: what
    # the laser dots show of a thing is sampled (dots tens of mm apart, a box corner between
    # them) — the stop zone's 150 mm hid that; the margin covers the map's position error
    swing_buffer_mm: float = setting(25.0, 0.0, 500.0)
    # ... but it reaches the stop line: the approach cap never falls below this (fastest point;
    # room/T alone is an exponential approach that never arrives — a chair creeping ever slower
    # 10 mm from its stop line). Stopping from it takes under 1 mm at the emergency rate
    approach_min_speed_mm_s: float = setting(20.0, 0.0, 100.0)
    unknown_distance_mm: float = setting(1000.0, 0.0, 10000.0)
    unknown_max_fraction: float = setting(0.3, 0.0, 1.0)
    unknown_speed_mm_s: float = setting(120.0, 10.0, 1000.0)
    # sweeping into space never seen: "refuse" (like an obstacle's stop zone) or "creep"
    unknown_policy: Literal["refuse", "creep"] = "refuse"
    unknown_creep_speed_mm_s: float = setting(60.0, 5.0, 200.0)  # fastest footprint point
    # ahead of the footprint (margin included) the laser cannot see from where the chair stands:
    # rig offset + nearest dot − footprint front − margin (300 + 330 − 350 − 50 = 230), rounded
    # up; crossed at unknown_creep_speed_mm_s whatever the policy, and approached no faster
    # than the chair can slow to that by the stop line (0: refused like the rest)
    front_blind_mm: float = setting(250.0, 0.0, 2000.0)
    # perception older than this → no forward motion; perception.capture: stream delivers a
    # cloud every ~50 ms (a base waits ≤ 2 frames for its mask, ~90 ms to the map): 0.3 s is
    # 3 frame-pairs of margin; the stationary capture needs its period + ~0.2 s (1.5 s)
    perception_timeout_s: float = setting(0.3, 0.05, 5.0)
    # and no forward motion after this much travel since the newest perception's capture
    perception_max_travel_mm: float = setting(250.0, 10.0, 5000.0)
    # the cameras deliver nothing (perception.camera_silence_s): at most this speed at once
    camera_lost_speed_mm_s: float = setting(100.0, 0.0, 1000.0)
    log_interval_s: float = setting(2.0, 0.1, 600.0)  # one log line per reason at most this often
    # escape moves in the stop zone (see the module docstring); 0 speed disables them
    # |v| cap of an escape move (0: no escapes, main's rule)
    escape_speed_mm_s: float = setting(0.0, 0.0, 200.0)
    # |ω| cap: the farthest footprint corner at ≈ 45 mm/s
    escape_turn_rad_s: float = setting(0.05, 0.0, 1.0)
    # the short step (fastest point) the gap is evaluated over
    escape_step_mm: float = setting(30.0, 1.0, 200.0)
    escape_tolerance_mm: float = setting(
        2.0, 0.0, 50.0
    )  # gap decrease still counted as "not closing"
    # softening (module docstring): a limited turn may become the nearest allowed twist of a
    # small candidate set (gentler turns, turns with less or no travel, a turn in place with a
    # forward component of at most this, fastest point); off: the request is only scaled.
    # On by default: a joystick rider's small corrections in a door frame are refused as arcs
    # (the tail swings to a jamb) while the straight line is clear (docs/benchmarks.md)
    soften: bool = True
    soften_forward_mm_s: float = setting(100.0, 0.0, 300.0)
    # a limited straight forward request, when what limits it within the slow zone is a
    # one-sided intrusion (a door jamb), may be softened into forward arcs away from it: radius
    # slow_distance²/(2·shift) and that over √2 and 2 (a sideways shift of this over s = slow,
    # slow/2^¼, slow/√2 of travel: s²/2R), for intrusions the sharpest shifts clear. 60: the gap
    # beside this chair in an 820 mm door (docs/daemon.md); 0: straight requests only scaled
    soften_side_shift_mm: float = setting(60.0, 0.0, 300.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        require(
            self.escape_speed_mm_s <= self.slow_speed_mm_s,
            "escape_speed_mm_s",
            "must not exceed slow_speed_mm_s",
        )
        require(
            self.slow_distance_mm >= self.stop_distance_mm,
            "slow_distance_mm",
            "must not be below stop_distance_mm",
        )
        require(
            self.horizon_mm > self.slow_distance_mm,
            "horizon_mm",
            "must exceed slow_distance_mm",
        )


@dataclass(frozen=True)
class SafetyDecision:
    """The allowed twist and why it differs from the request."""

    v_mm_s: float
    omega_rad_s: float
    scale: float  # allowed / requested, in [0, 1]
    clearance_mm: float  # free travel of the fastest footprint point (inf: nothing in horizon)
    reasons: tuple[Reason, ...] = ()

    @property
    def stopped(self) -> bool:
        return self.scale == 0.0


class ReasonLog:
    """Logs each reason at most once per ``interval_s`` (counts what it suppressed)."""

    def __init__(self, logger: logging.Logger, interval_s: float) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self.suppressed = 0

    def log(self, reason: str, message: str, now_s: float, level: int = logging.WARNING) -> bool:
        last = self._last.get(reason)
        if last is not None and now_s - last < self.interval_s:
            self.suppressed += 1
            return False
        self._last[reason] = now_s
        self.logger.log(level, "%s: %s", reason, message)
        return True


def contact_path_s(
    px_mm: NDArray[np.float64],
    py_mm: NDArray[np.float64],
    v_mm_s: float,
    omega_rad_s: float,
    rect_mm: tuple[Any, Any, Any, Any],
    fast_speed_mm_s: float,
    horizon_mm: float,
) -> NDArray[np.float64]:
    """Path parameter s (mm) at which a rectangle moving with the robot first contains each point.

    The rectangle ``rect_mm`` = (x0, x1, y0, y1) is fixed in the robot frame; the robot moves
    with constant twist (v mm/s, ω rad/s), and s is the travel of a point moving at
    ``fast_speed_mm_s`` (the footprint's fastest point), so the heading after s is
    θ = ω·s / fast_speed. Seen from the robot, a point fixed in the world moves on a circle
    about the instantaneous centre of rotation (0, v/ω) by −θ (for ω = 0: straight back by
    s·sign(v)); its first crossing of the rectangle's edges comes from
    x = ρ·cos β, y = v/ω + ρ·sin β solved per edge (eight candidate angles). Points inside the
    rectangle at the start give 0; points that do not enter within ``horizon_mm`` give ``inf``.
    The bounds may be floats or arrays (N,) (one rectangle per point).
    """
    x0, x1, y0, y1 = rect_mm
    n = px_mm.shape[0]
    inside = (px_mm >= x0) & (px_mm <= x1) & (py_mm >= y0) & (py_mm <= y1)
    if omega_rad_s == 0.0:
        lane = (py_mm >= y0) & (py_mm <= y1)
        if v_mm_s > 0.0:
            s_mm = np.where(lane & (px_mm > x1), px_mm - x1, np.inf)
        elif v_mm_s < 0.0:
            s_mm = np.where(lane & (px_mm < x0), x0 - px_mm, np.inf)
        else:
            s_mm = np.full(n, np.inf)
    else:
        # Mirror y so that the chair turns left (the rectangle is symmetric in y only after
        # mirroring its bounds too).
        if omega_rad_s < 0.0:
            py_mm = -py_mm
            y0, y1 = -y1, -y0
        w = abs(omega_rad_s)
        r_mm = v_mm_s / w
        dy = py_mm - r_mm
        rho2 = px_mm * px_mm + dy * dy
        # Only points whose distance ρ from the centre of rotation lies between the rectangle's
        # nearest and farthest distance from it can ever enter it.
        far2 = np.maximum(x0 * x0, x1 * x1) + np.maximum((y0 - r_mm) ** 2, (y1 - r_mm) ** 2)
        near_x = np.maximum(np.maximum(x0, -x1), 0.0)
        near_y = np.maximum(np.maximum(y0 - r_mm, r_mm - y1), 0.0)
        sel = np.flatnonzero((rho2 <= far2) & (rho2 >= near_x * near_x + near_y * near_y))
        s_mm = np.full(n, np.inf)
        if sel.size:
            dx, dy, rho2 = px_mm[sel], dy[sel], rho2[sel]

            def pick(b: Any) -> Any:
                return b[sel] if np.ndim(b) else b

            ex = np.stack(np.broadcast_arrays(pick(x0), pick(x1), dx))[:2]  # edges x = x0, x1
            ey = np.stack(np.broadcast_arrays(pick(y0) - r_mm, pick(y1) - r_mm, dx))[:2]
            rx = np.sqrt(np.maximum(rho2 - ex * ex, 0.0))  # |y| where the circle meets x = X
            ry = np.sqrt(np.maximum(rho2 - ey * ey, 0.0))  # |x| where it meets y = Y
            okx = ex * ex <= rho2
            oky = ey * ey <= rho2
            lo_y, hi_y = ey[0], ey[1]
            lo_x, hi_x = ex[0], ex[1]
            # the 8 candidate crossing points q (relative to the centre of rotation)
            qx = np.concatenate([ex, ex, ry, -ry])
            qy = np.concatenate([rx, -rx, ey, ey])
            valid = np.concatenate(
                [
                    okx & (rx >= lo_y) & (rx <= hi_y),
                    okx & (-rx >= lo_y) & (-rx <= hi_y),
                    oky & (ry >= lo_x) & (ry <= hi_x),
                    oky & (-ry >= lo_x) & (-ry <= hi_x),
                ]
            )
            # the point reaches q after turning by φ (clockwise, as seen from the chair)
            phi = np.mod(np.arctan2(qx * dy - qy * dx, qx * dx + qy * dy), 2.0 * np.pi)
            first = np.where(valid, phi, np.inf).min(axis=0)
            s_mm[sel] = first * (fast_speed_mm_s / w)
    s_mm = np.where(s_mm <= horizon_mm, s_mm, np.inf)
    s_mm[inside] = 0.0
    return np.asarray(s_mm, dtype=np.float64)


#: Blocking evidence in the robot frame: points (N, 2) mm, how far around each point the thing
#: may extend (N,) mm (0 for an exact point, a cell's half-diagonal for a cell centre), and
#: which are drop-offs (N,) (``FreeSpaceMap.blocking_evidence``).
Evidence = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]

#: Never-seen cells in the robot frame: their centres (N, 2) mm and how far from its centre
#: anything in a cell may lie (mm, a cell's half-diagonal) (``FreeSpaceMap.unknown_cells``), or
#: the same as a view moved into the robot frame box by box (``FreeSpaceMap.unseen_cells``).
Unseen = tuple[NDArray[np.float64], float] | UnseenCells


class _ListedUnseen:
    """:class:`~omnid.core.freespace.UnseenCells`' interface over cells already in the robot
    frame (an :data:`Unseen` tuple)."""

    def __init__(self, xy: NDArray[np.float64], grow_mm: float) -> None:
        self._x, self._y = xy[:, 0], xy[:, 1]
        self.grow_mm = float(grow_mm)

    def within(
        self, x_min_mm: float, x_max_mm: float, y_min_mm: float, y_max_mm: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        x, y = self._x, self._y
        keep = (x >= x_min_mm) & (x <= x_max_mm) & (y >= y_min_mm) & (y <= y_max_mm)
        return x[keep], y[keep]


class _Sweep(NamedTuple):
    """A cached blocking sweep (:meth:`SafetyLayer._blocking_sweep`): the first contact (mm) and
    its state, the side intrusion (mm, :meth:`SafetyLayer._side_intrusion`), and the first
    contact of the leading face and of the swing with their states."""

    clearance_mm: float
    state: CellState | None
    side_mm: float
    lead_mm: float
    lead_state: CellState | None
    swing_mm: float
    swing_state: CellState | None


_NO_SWEEP = _Sweep(math.inf, None, 0.0, math.inf, None, math.inf, None)


def _first_contact(
    s_mm: NDArray[np.float64], drop: NDArray[np.bool_], tie_mm: float
) -> tuple[float, CellState | None]:
    """The first contact (mm, ``inf`` for none) and what it is: a drop-off if one lies within
    ``tie_mm`` of it."""
    if s_mm.size == 0:
        return math.inf, None
    k = int(np.argmin(s_mm))
    if not math.isfinite(s_mm[k]):
        return math.inf, None
    first = float(s_mm[k])
    tie = s_mm <= first + tie_mm
    return first, CellState.DROPOFF if np.any(drop[tie]) else CellState.OBSTACLE


def _unique(reasons: list[Reason]) -> tuple[Reason, ...]:
    """The reasons in order, each once."""
    out: list[Reason] = []
    for r in reasons:
        if r not in out:
            out.append(r)
    return tuple(out)


class SafetyLayer:
    """Checks requested twists against a grid (see the module docstring)."""

    def __init__(self, settings: SafetySettings) -> None:
        self.settings = settings
        s = settings
        m = s.margin_mm
        self._x0, self._x1 = -s.footprint_rear_mm - m, s.footprint_front_mm + m
        self._y0 = -0.5 * s.footprint_width_mm - s.side_margin_mm
        self._y1 = -self._y0
        # the chair itself (no margin): cells under it are not seen and not obstacles
        self._fx0, self._fx1 = -s.footprint_rear_mm, s.footprint_front_mm
        # a swing this near (fastest point's travel) is refused: the stopping distance from
        # the slowest speed the approach rules allow
        self._swing_refuse_mm = self.swing_stop_mm(s.approach_min_speed_mm_s)
        self._fy1 = 0.5 * s.footprint_width_mm
        self._fy0 = -self._fy1
        corners = np.array(
            [[self._x0, self._y0], [self._x0, self._y1], [self._x1, self._y0], [self._x1, self._y1]]
        )
        self.r_max_mm = float(np.max(np.hypot(corners[:, 0], corners[:, 1])))
        # radii (mm) of the arcs a limited straight request may be softened into: a sideways
        # shift of soften_side_shift_mm over s = slow, slow/2^¼, slow/√2 of travel (s²/2R); only
        # those wider than the farthest corner's radius, whose score (progress less deviation)
        # can be positive
        shift = s.soften_side_shift_mm
        self._arc_radii_mm: tuple[float, ...] = ()
        if shift > 0.0:
            radii = (s.slow_distance_mm**2 / (2.0 * shift) / k for k in (1.0, math.sqrt(2.0), 2.0))
            self._arc_radii_mm = tuple(r for r in radii if r > self.r_max_mm)
        # the sideways shift the sharpest of them makes over the slow zone's travel
        self._arc_shift_mm = (
            s.slow_distance_mm**2 / (2.0 * min(self._arc_radii_mm)) if self._arc_radii_mm else 0.0
        )
        self._pts_cache: tuple[float, NDArray[np.float64]] | None = None
        self._map_key: object = None  # the map content the caches below belong to
        # blocking evidence of the current map: x, y, grow (mm), drop-off
        self._blocking: (
            tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]
            | None
        ) = None
        # per twist: clearance, blocking state, side intrusion (:meth:`_side_intrusion`, mm),
        # and the first contact of the leading face and of the swing with their states
        self._sweeps: dict[tuple[float, float], _Sweep] = {}
        self._fractions: dict[tuple[float, float], float] = {}
        # per twist: unknown_clearance's (unseen, blind) and unknown_contacts' (leading, swing)
        self._unknown: dict[tuple[float, float], tuple[float, float, float, float]] = {}
        # the never-seen cells given to :meth:`check` (None: the grid's UNKNOWN cells)
        self._unseen: UnseenCells | _ListedUnseen | None = None
        self._unseen_key: object = None  # the evidence key the last check named them by
        self._centres_cache: (
            tuple[GridSettings, NDArray[np.float64], NDArray[np.float64]] | None
        ) = None
        self.log = ReasonLog(log, s.log_interval_s)

    def footprint_points(self, spacing_mm: float) -> NDArray[np.float64]:
        """Points (N, 2) mm on the footprint's outline (with margin) at ``spacing_mm``.

        The outline suffices: the footprint's interior at the start is ignored, and anything the
        moving footprint covers later has crossed its outline first (poses are sampled at half a
        cell along the path).
        """
        if self._pts_cache is not None and self._pts_cache[0] == spacing_mm:
            return self._pts_cache[1]
        nx = max(math.ceil((self._x1 - self._x0) / spacing_mm), 1) + 1
        ny = max(math.ceil((self._y1 - self._y0) / spacing_mm), 1) + 1
        xs = np.linspace(self._x0, self._x1, nx)
        ys = np.linspace(self._y0, self._y1, ny)
        pts = np.concatenate(
            [
                np.column_stack([xs, np.full(nx, self._y0)]),
                np.column_stack([xs, np.full(nx, self._y1)]),
                np.column_stack([np.full(ny, self._x0), ys]),
                np.column_stack([np.full(ny, self._x1), ys]),
            ]
        )
        self._pts_cache = (spacing_mm, pts)
        return pts

    def inside_footprint(self, xy_mm: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether robot-frame points (N, 2) lie in the current footprint (with margin)."""
        return (
            (xy_mm[:, 0] >= self._x0)
            & (xy_mm[:, 0] <= self._x1)
            & (xy_mm[:, 1] >= self._y0)
            & (xy_mm[:, 1] <= self._y1)
        )

    def sweep(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        evidence: Evidence | None = None,
        evidence_key: object = None,
    ) -> tuple[float, CellState | None, float]:
        """Sweep the footprint along the motion direction of (v, ω), analytically per point.

        Returns (clearance_mm, blocking state or None, unknown fraction within
        ``unknown_distance_mm``). Clearance is the path parameter s (travel of the fastest
        footprint point) at which the footprint first touches blocking evidence (``inf`` if
        none within the horizon): each piece is a point and the footprint is grown by how far
        the thing may extend around it (0 for an exact obstacle point, half a cell's diagonal
        for a cell centre), so "point inside the grown footprint" is "footprint touches it";
        the point's path relative to the chair is a circle about the instantaneous centre of
        rotation (a line when ω = 0), and its first crossing of the grown rectangle's edges is
        solved in closed form (:func:`contact_path_s`).

        ``evidence`` (robot frame, see :data:`Evidence`) comes from the map; without it every
        OBSTACLE/DROPOFF cell of ``grid`` is a grown cell centre. ``evidence_key`` names the
        evidence's content (the map's version and pose) so that results can be cached.

        The unknown fraction is that of the FREE/UNKNOWN cells the footprint newly covers before
        ``min(unknown_distance_mm, clearance)`` (0 for a motion no faster than
        ``unknown_speed_mm_s``, which it cannot cap). Results are cached per (map content, v, ω) (a
        standing chair with a held command costs a dictionary lookup). :meth:`sweep_reference`
        is the slow sampled sweep this is tested against.
        """
        b = self._blocking_sweep(grid, v_mm_s, omega_rad_s, evidence, evidence_key)
        unknown = self._sweep_unknown(grid, v_mm_s, omega_rad_s, b.clearance_mm)
        return b.clearance_mm, b.state, unknown

    def _blocking_sweep(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        evidence: Evidence | None,
        evidence_key: object,
    ) -> _Sweep:
        """:meth:`sweep`'s clearance and blocking state, for a straight forward twist the side
        intrusion of what it meets (:meth:`_side_intrusion`; 0 otherwise), and the first contact of the leading face
        and of the swing (:meth:`contacts`), cached together."""
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm  # speed of the fastest point
        if u <= 0.0:
            return _NO_SWEEP
        self._use_map(grid, evidence, evidence_key)
        cached = self._sweeps.get((v_mm_s, omega_rad_s))
        if cached is not None:
            return cached
        assert self._blocking is not None
        bx, by, grow, bdrop = self._blocking
        sb = self._contact(bx, by, grow, v_mm_s, omega_rad_s, u)
        h = 0.5 * grid.settings.resolution_mm * math.sqrt(2.0)
        clearance, state = _first_contact(sb, bdrop, h)
        side = 0.0
        if math.isfinite(clearance) and omega_rad_s == 0.0 and v_mm_s > 0.0:
            side = self._side_intrusion(by, grow, sb)
        lead = self._leading(bx, by, sb, v_mm_s, omega_rad_s, u)
        result = _Sweep(
            clearance,
            state,
            side,
            *_first_contact(sb[lead], bdrop[lead], h),
            *_first_contact(sb[~lead], bdrop[~lead], h),
        )
        if len(self._sweeps) >= 256:
            self._sweeps.clear()
        if self._map_key is not None:
            self._sweeps[(v_mm_s, omega_rad_s)] = result
        return result

    def contacts(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        evidence: Evidence | None = None,
        evidence_key: object = None,
    ) -> tuple[float, CellState | None, float, CellState | None]:
        """The sweep's blocking contacts split by the face that meets them: (first contact mm,
        state) of the **leading face** — the front (its margin strip and corners included)
        driving forward, the rear reversing, none turning in place — and of the **swing** (the
        sides and the trailing face). ``inf, None`` where there is none (cached with
        :meth:`sweep`)."""
        b = self._blocking_sweep(grid, v_mm_s, omega_rad_s, evidence, evidence_key)
        return b.lead_mm, b.lead_state, b.swing_mm, b.swing_state

    def _leading(
        self,
        px: NDArray[np.float64],
        py: NDArray[np.float64],
        s_mm: NDArray[np.float64],
        v_mm_s: float,
        omega_rad_s: float,
        u: float,
    ) -> NDArray[np.bool_]:
        """Which contacts ``s_mm`` of the points (robot frame now) the leading face meets: where
        the point lies, in the robot frame of the pose of contact, at or beyond the footprint's
        front (forward) or rear (reverse) without margins, so the margin strip counts as that face;
        none for a turn in place."""
        fin = np.isfinite(s_mm)
        if v_mm_s == 0.0 or not np.any(fin):
            return np.zeros(len(px), dtype=bool)
        s = np.where(fin, s_mm, 0.0)
        if omega_rad_s == 0.0:
            xc = px - s * math.copysign(1.0, v_mm_s)
        else:
            th = s * (omega_rad_s / u)
            r = v_mm_s / omega_rad_s
            xc = np.cos(th) * (px - r * np.sin(th)) + np.sin(th) * (py - r * (1.0 - np.cos(th)))
        ahead = xc >= self._fx1 - 1e-6 if v_mm_s > 0.0 else xc <= self._fx0 + 1e-6
        return np.asarray(fin & ahead)

    def swing_stop_mm(self, speed_mm_s: float) -> float:
        """Stopping distance (mm) of the fastest footprint point from ``speed_mm_s``: the
        reaction time at that speed, then braking at ``brake_decel_mm_s2``."""
        s = self.settings
        return speed_mm_s * s.reaction_time_s + speed_mm_s**2 / (2.0 * s.brake_decel_mm_s2)

    def _swing_cap(self, room_mm: float) -> float:
        """The speed (mm/s, fastest point) whose stopping distance is ``room_mm``."""
        s = self.settings
        a, t = s.brake_decel_mm_s2, s.reaction_time_s
        return a * (math.sqrt(t * t + 2.0 * max(room_mm, 0.0) / a) - t)

    def _side_intrusion(
        self, by: NDArray[np.float64], grow: NDArray[np.float64], s_mm: NDArray[np.float64]
    ) -> float:
        """What limits a straight forward move within the slow zone, as a side intrusion: the
        sideways shift (mm) that would clear every blocking point the straight sweep meets
        within ``slow_distance_mm`` — positive if all lie left (shift right), negative if all
        lie right, 0 if they lie on both sides (a door jamb each side, or something across the
        path: no one-sided shift clears it)."""
        near = s_mm <= self.settings.slow_distance_mm
        y, g = by[near], grow[near]
        if y.size == 0 or (np.any(y > 0.0) and np.any(y <= 0.0)):
            return 0.0
        if y[0] > 0.0:
            return float(np.max(self._y1 + g - y))
        return -float(np.max(self._y1 + g + y))

    def _contact_side(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        evidence: Evidence | None,
        evidence_key: object,
    ) -> float:
        """For a straight forward request: +1 if what limits it within the slow zone lies all
        left of the path and a sideways shift the sharpest candidate arc makes over the slow
        zone's travel (``_arc_shift_mm``) clears it, −1 likewise right, else 0 (after its
        sweep: :meth:`_side_intrusion`)."""
        if not self._arc_radii_mm or v_mm_s <= 0.0:
            return 0.0
        y = self._blocking_sweep(grid, v_mm_s, 0.0, evidence, evidence_key).side_mm
        if abs(y) > self._arc_shift_mm:
            return 0.0
        return float(np.sign(y))

    def _sweep_unknown(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float, clearance_mm: float
    ) -> float:
        """:meth:`sweep`'s unknown fraction (after :meth:`_blocking_sweep` for this map)."""
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm
        if u <= self.settings.unknown_speed_mm_s:  # the fraction caps only what is faster
            return 0.0
        cached = self._fractions.get((v_mm_s, omega_rad_s))
        if cached is not None and self._map_key is not None:
            return cached
        xs, ys = self._centres(grid)
        h = 0.5 * grid.settings.resolution_mm * math.sqrt(2.0)
        rect = (self._x0 - h, self._x1 + h, self._y0 - h, self._y1 + h)
        unknown = self._unknown_fraction(grid, xs, ys, v_mm_s, omega_rad_s, rect, u, clearance_mm)
        if len(self._fractions) >= 256:
            self._fractions.clear()
        if self._map_key is not None:
            self._fractions[(v_mm_s, omega_rad_s)] = unknown
        return unknown

    def _use_map(self, grid: OccupancyGrid, evidence: Evidence | None, key: object) -> None:
        """Make the caches belong to this map content (uncacheable: evidence without a key)."""
        map_key: object
        if self._unseen is not None and key != self._unseen_key:
            self._unseen = None  # the exact cells belong to the map content their key names
        if evidence is not None and key is None:
            map_key = None
        else:
            unseen = self._unseen is not None
            map_key = (grid.settings, grid.states.shape, grid.states.tobytes(), key, unseen)
        if map_key is not None and map_key == self._map_key and self._blocking is not None:
            return
        self._map_key = map_key
        self._sweeps.clear()
        self._fractions.clear()
        self._unknown.clear()
        if evidence is None:
            xs, ys = self._centres(grid)
            i, j = np.nonzero(grid.states >= CellState.OBSTACLE)  # OBSTACLE or DROPOFF
            h = 0.5 * grid.settings.resolution_mm * math.sqrt(2.0)
            self._blocking = (
                xs[i],
                ys[j],
                np.full(len(i), h),
                grid.states[i, j] == CellState.DROPOFF,
            )
        else:
            xy, grow, drop = evidence
            self._blocking = (
                np.asarray(xy[:, 0], dtype=np.float64),
                np.asarray(xy[:, 1], dtype=np.float64),
                np.asarray(grow, dtype=np.float64),
                np.asarray(drop, dtype=bool),
            )

    def _centres(self, grid: OccupancyGrid) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        if self._centres_cache is None or self._centres_cache[0] != grid.settings:
            self._centres_cache = (grid.settings, *grid.cell_centers())
        return self._centres_cache[1], self._centres_cache[2]

    def _contact(
        self,
        px: NDArray[np.float64],
        py: NDArray[np.float64],
        grow: NDArray[np.float64] | float,
        v_mm_s: float,
        omega_rad_s: float,
        u: float,
        margins: bool = True,
    ) -> NDArray[np.float64]:
        """Contact path parameter (mm) of each point, the footprint (with its margins, or
        without: ``margins=False``) grown by the point's own ``grow`` (mm); points under the
        chair itself (the footprint without its margin) ignored (see :func:`contact_path_s`)."""
        hz = self.settings.horizon_mm
        x0, x1, y0, y1 = (
            (self._x0, self._x1, self._y0, self._y1)
            if margins
            else (self._fx0, self._fx1, self._fy0, self._fy1)
        )
        rect = (x0 - grow, x1 + grow, y0 - grow, y1 + grow)
        s_mm = contact_path_s(px, py, v_mm_s, omega_rad_s, rect, u, hz)
        own = (px >= self._fx0) & (px <= self._fx1) & (py >= self._fy0) & (py <= self._fy1)
        band = np.flatnonzero((s_mm == 0.0) & ~own)
        if band.size:
            # Points overlapping the footprint's margin at the start (inside the margin, or
            # within their own grow of its edge) are inside the grown rectangle already. Each is
            # tested against the footprint grown (or shrunk, inside the margin) by its own
            # Chebyshev distance instead: in contact at once when the motion brings it nearer,
            # later when it draws away first and comes back. So a thing seen inside the margin
            # is never driven into (the margin is not traded), and never strands the chair.
            bx, by = px[band], py[band]
            g = np.maximum(np.maximum(x0 - bx, bx - x1), np.maximum(y0 - by, by - y1))
            g = g - 1e-9 * (np.abs(g) + 1.0)  # the point just outside its own rectangle
            grown = (x0 - g, x1 + g, y0 - g, y1 + g)
            s_mm[band] = contact_path_s(bx, by, v_mm_s, omega_rad_s, grown, u, hz)
        s_mm[own] = math.inf
        return s_mm

    def unknown_clearance(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float
    ) -> tuple[float, float]:
        """First contact (mm of the fastest point's travel) of the footprint's sweep with cells
        never seen: (anywhere but the blind band, in the blind band ahead of the footrests —
        only for forward moves; ``inf`` for none). Only as far as a speed cap could bind:
        ``stop_distance_mm`` plus the approach time (or braking distance) at this speed.

        UNKNOWN cells of ``grid`` (or, when the last :meth:`check` was given them, the map's
        exact never-seen cells, ``unseen``) and everything off it count, by their centres against the
        footprint itself (no margin: the margin is for the position error of things seen; the
        footprint never covers the centre of a cell never seen — the map's resolution). Cells
        whose centre lies under the chair are ignored (the map marks them FREE: the chair's own
        trail, by the same centre rule, so that retracing the trail finds it free). Call
        :meth:`sweep` (or :meth:`check`) first for this map content: the result is cached with
        the sweeps.
        """
        unseen, blind, _, _ = self._unknown_sweep(grid, v_mm_s, omega_rad_s)
        return unseen, blind

    def unknown_contacts(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float
    ) -> tuple[float, float]:
        """:meth:`unknown_clearance`'s never-seen cells outside the blind band split by the face
        that meets them (as :meth:`contacts`): (the leading face's first contact, by centres
        against the footprint itself as there; the swing's first contact, each cell by its whole
        extent — its centre grown by its half-diagonal, the cell however turned — against the
        footprint itself: the swing may come as near as its stopping distance, so the footprint
        never enters a cell never seen; one it surely overlaps now, its centre nearer than half
        a cell — its trail's edge — by its centre, so it enters no further than the cell's
        half). ``inf`` for none, or none within the reach."""
        _, _, lead, swing = self._unknown_sweep(grid, v_mm_s, omega_rad_s)
        return lead, swing

    def _unknown_sweep(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float
    ) -> tuple[float, float, float, float]:
        """:meth:`unknown_clearance` and :meth:`unknown_contacts` (cached together)."""
        s = self.settings
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm
        if u <= 0.0:
            return math.inf, math.inf, math.inf, math.inf
        cached = self._unknown.get((v_mm_s, omega_rad_s))
        if cached is not None and self._map_key is not None:
            return cached
        g = grid.settings
        res = g.resolution_mm
        h = 0.5 * res * math.sqrt(2.0)
        reach = s.stop_distance_mm + max(u * s.approach_time_s, u * u / (2 * s.brake_decel_mm_s2))
        reach = min(reach + res, s.horizon_mm)
        ss = np.linspace(0.0, reach, 9)
        th = ss * (omega_rad_s / u)
        if omega_rad_s == 0.0:
            ox, oy = ss * (v_mm_s / u), np.zeros_like(ss)
        else:
            r = v_mm_s / omega_rad_s
            ox, oy = r * np.sin(th), r * (1.0 - np.cos(th))
        # The swept footprint's bounding box: the corners along the path (the path between
        # samples bulges outwards by at most ``bulge``).
        cx = np.array([self._fx0, self._fx0, self._fx1, self._fx1])
        cy = np.array([self._fy0, self._fy1, self._fy0, self._fy1])
        c, sn = np.cos(th)[:, None], np.sin(th)[:, None]
        wx = ox[:, None] + c * cx - sn * cy
        wy = oy[:, None] + sn * cx + c * cy
        bulge = self.r_max_mm * (1.0 - math.cos(0.5 * abs(float(th[1] - th[0]))))
        # (and half a cell: the swing's contacts by the cells' extent, unknown_contacts)
        pad = 1.5 * res + bulge
        i0 = math.floor((wx.min() - pad - g.x_min_mm) / res)
        i1 = math.floor((wx.max() + pad - g.x_min_mm) / res) + 1
        j0 = math.floor((wy.min() - pad - g.y_min_mm) / res)
        j1 = math.floor((wy.max() + pad - g.y_min_mm) / res) + 1
        nx, ny = grid.states.shape
        sub = np.full((i1 - i0, j1 - j0), np.int8(CellState.UNKNOWN))  # off the grid: unseen
        a0, a1, b0, b1 = max(i0, 0), min(i1, nx), max(j0, 0), min(j1, ny)
        if a1 > a0 and b1 > b0:
            sub[a0 - i0 : a1 - i0, b0 - j0 : b1 - j0] = grid.states[a0:a1, b0:b1]
            if self._unseen is not None:
                sub[a0 - i0 : a1 - i0, b0 - j0 : b1 - j0] = CellState.FREE  # given exactly
        ii, jj = np.nonzero(sub == CellState.UNKNOWN)
        px = g.x_min_mm + (i0 + ii + 0.5) * res
        py = g.y_min_mm + (j0 + jj + 0.5) * res
        if self._unseen is not None:
            # the map's never-seen cells, moved into this frame exactly (a turned cell: its
            # extent within its half-diagonal); off the grid, as above, the grid's own cells
            ugrow = self._unseen.grow_mm
            bx0, bx1 = g.x_min_mm + i0 * res - ugrow, g.x_min_mm + i1 * res + ugrow
            by0, by1 = g.y_min_mm + j0 * res - ugrow, g.y_min_mm + j1 * res + ugrow
            ux, uy = self._unseen.within(bx0, bx1, by0, by1)
            px = np.concatenate([px, ux])
            py = np.concatenate([py, uy])
            h = max(h, float(ugrow))
        body = (self._fx0, self._fx1, self._fy0, self._fy1)
        s_mm = contact_path_s(px, py, v_mm_s, omega_rad_s, body, u, s.horizon_mm)
        s_mm[s_mm == 0.0] = math.inf  # under the chair now: its own trail
        blind = np.zeros(len(px), dtype=bool)
        if v_mm_s > 0.0 and s.front_blind_mm > 0.0:
            blind = (px > self._fx1) & (px <= self._x1 + s.front_blind_mm + h)
            blind &= np.abs(py) <= self._y1 + h
        lead = self._leading(px, py, s_mm, v_mm_s, omega_rad_s, u)
        swing = ~blind & ~lead
        # a cell's extent is its centre grown by its half-diagonal: the footprint turns along
        # the swing, so even a cell square to it now is turned against it later (half a cell
        # would miss its corners); against the footprint itself (the margin is for the position
        # error of things seen) (one that may overlap it now: no nearer than it is). A cell
        # the chair surely overlaps now (its centre nearer than half a cell: the disc inside
        # the cell, however turned, reaches under the chair) is its trail's edge — the map
        # frees a cell once its centre was under the chair, and in the robot frame exactly
        # (turned, offset) such cells reach under it: by its centre, as the leading face meets
        # cells (the map's resolution; else every swing towards it would be refused).
        sx, sy = px[swing], py[swing]
        s_ext = self._contact(sx, sy, h, v_mm_s, omega_rad_s, u, False)
        edge = self._rect_distance(sx, sy) < h / math.sqrt(2.0)
        s_ext[edge] = s_mm[swing][edge]
        found = (s_mm[~blind], s_mm[blind], s_mm[~blind & lead], s_ext)
        first = [float(x.min()) if x.size and x.min() <= reach else math.inf for x in found]
        result = (first[0], first[1], first[2], first[3])
        if self._map_key is not None:
            self._unknown[(v_mm_s, omega_rad_s)] = result
        return result

    def escape_gaps(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float
    ) -> NDArray[np.float64]:
        """Distances (mm) between the footprint without its margin and each piece of blocking
        evidence near it (an exact point, or a cell's centre), now and at 6 poses evenly along
        the first ``escape_step_mm`` (travel of the fastest footprint point) of the motion
        (v, ω): shape (7, N), row 0 = now. Near: within ``margin_mm + stop_distance_mm`` plus a
        cell and the step of the footprint now; points under the chair itself are ignored, as
        in :meth:`sweep`. Uses the evidence of the last :meth:`sweep`.
        """
        s = self.settings
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm
        if u <= 0.0 or self._blocking is None:
            return np.zeros((7, 0))
        bx, by, _, _ = self._blocking
        reach = s.margin_mm + s.stop_distance_mm + grid.settings.resolution_mm + s.escape_step_mm
        own = (bx >= self._fx0) & (bx <= self._fx1) & (by >= self._fy0) & (by <= self._fy1)
        near = np.flatnonzero((self._rect_distance(bx, by) <= reach) & ~own)
        px, py = bx[near], by[near]
        ss = np.linspace(0.0, s.escape_step_mm, 7)
        th = ss * (omega_rad_s / u)
        if omega_rad_s == 0.0:
            ox, oy = ss * (v_mm_s / u), np.zeros_like(ss)
        else:
            r = v_mm_s / omega_rad_s
            ox, oy = r * np.sin(th), r * (1.0 - np.cos(th))
        # each point in the robot frame of each pose: R(−θ)·(p − o)
        c, sn = np.cos(th)[:, None], np.sin(th)[:, None]
        dx, dy = px[None, :] - ox[:, None], py[None, :] - oy[:, None]
        return self._rect_distance(c * dx + sn * dy, -sn * dx + c * dy)

    def _rect_distance(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """Euclidean distance (mm) of robot-frame points from the footprint without margin."""
        ex = np.maximum(np.maximum(self._fx0 - x, x - self._fx1), 0.0)
        ey = np.maximum(np.maximum(self._fy0 - y, y - self._fy1), 0.0)
        return np.asarray(np.hypot(ex, ey), dtype=np.float64)

    def is_escape(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        evidence: Evidence | None = None,
        evidence_key: object = None,
    ) -> bool:
        """Whether a move in the stop zone is an escape move (module docstring), from
        :meth:`escape_gaps` over the first ``escape_step_mm``: the gap to the nearest cell never
        drops by more than ``escape_tolerance_mm`` (the move does not close on what is near),
        and no cell comes nearer than ``margin_mm`` — or, already inside the margin, any nearer
        (no tolerance: the margin is never traded, not even a little per control cycle)."""
        s = self.settings
        if s.escape_speed_mm_s <= 0.0:
            return False
        self._blocking_sweep(grid, v_mm_s, omega_rad_s, evidence, evidence_key)  # cached
        d = self.escape_gaps(grid, v_mm_s, omega_rad_s)
        if d.shape[1] == 0:
            return False  # nothing near, yet in the stop zone: not a pocket, keep the refusal
        tol = s.escape_tolerance_mm
        opens = bool(np.all(d.min(axis=1)[1:] >= d[0].min() - tol))
        keeps_margin = bool(np.all(d[1:] >= np.minimum(d[0], s.margin_mm)[None, :] - 1e-6))
        return opens and keeps_margin

    def _unknown_fraction(
        self,
        grid: OccupancyGrid,
        xs: NDArray[np.float64],
        ys: NDArray[np.float64],
        v_mm_s: float,
        omega_rad_s: float,
        rect: tuple[float, float, float, float],
        u: float,
        clearance_mm: float,
    ) -> float:
        """Fraction of UNKNOWN among the non-blocking cells first covered before
        ``min(unknown_distance_mm, clearance_mm)`` (the cells overlapping the start footprint's
        edge count as covered); only every other cell, each way, in the bounding box of the
        swept footprint up to there is looked at."""
        reach = min(self.settings.unknown_distance_mm, clearance_mm)
        if reach <= 0.0:
            return 0.0
        res = grid.settings.resolution_mm
        ss = np.linspace(0.0, reach, 9)
        th = ss * (omega_rad_s / u)
        if omega_rad_s == 0.0:
            ox, oy = ss * math.copysign(1.0, v_mm_s), np.zeros_like(ss)
        else:
            r = v_mm_s / omega_rad_s
            ox, oy = r * np.sin(th), r * (1.0 - np.cos(th))
        cx = np.array([rect[0], rect[0], rect[1], rect[1]])
        cy = np.array([rect[2], rect[3], rect[2], rect[3]])
        c, sn = np.cos(th)[:, None], np.sin(th)[:, None]
        wx = ox[:, None] + c * cx - sn * cy
        wy = oy[:, None] + sn * cx + c * cy
        g = grid.settings
        nx, ny = grid.states.shape
        i0 = max(int((wx.min() - res - g.x_min_mm) // res), 0)
        i1 = min(int((wx.max() + res - g.x_min_mm) // res) + 1, nx)
        j0 = max(int((wy.min() - res - g.y_min_mm) // res), 0)
        j1 = min(int((wy.max() + res - g.y_min_mm) // res) + 1, ny)
        if i1 <= i0 or j1 <= j0:
            return 0.0
        # Every other cell each way: a fraction for a speed cap needs no more, and it keeps the
        # cost of a turn in place (the whole circle about the chair) at a quarter.
        sub = grid.states[i0:i1:2, j0:j1:2]
        ii, jj = np.nonzero(sub <= CellState.FREE)  # UNKNOWN or FREE
        if ii.size == 0:
            return 0.0
        px, py = xs[i0 + 2 * ii], ys[j0 + 2 * jj]
        s_mm = contact_path_s(px, py, v_mm_s, omega_rad_s, rect, u, self.settings.horizon_mm)
        own = (px >= self._x0) & (px <= self._x1) & (py >= self._y0) & (py <= self._y1)
        swept = (s_mm <= reach) & (s_mm < clearance_mm) & ~own
        n = int(np.count_nonzero(swept))
        if n == 0:
            return 0.0
        return float(np.count_nonzero(sub[ii[swept], jj[swept]] == CellState.UNKNOWN) / n)

    def sweep_reference(
        self, grid: OccupancyGrid, v_mm_s: float, omega_rad_s: float
    ) -> tuple[float, CellState | None, float]:
        """The slow reference sweep: the footprint's outline at poses every half cell along the
        path, each outline point looked up in the grid (K×N lookups, 1–3 ms).

        Kept as the specification :meth:`sweep` is tested against. Returns (clearance_mm,
        blocking state or None, unknown fraction within ``unknown_distance_mm``); clearance is
        the path parameter s of the last free pose before the first blocked one (``inf`` if none
        within the horizon).
        """
        s = self.settings
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm  # speed of the fastest point
        if u <= 0.0:
            return math.inf, None, 0.0
        res = grid.settings.resolution_mm
        step = 0.5 * res
        ss = np.arange(step, s.horizon_mm + step, step)
        track = 2.0  # any positive track: the wheel travels below reproduce (v, ω) exactly
        ds = ss * (v_mm_s / u)
        dth = ss * (omega_rad_s / u)
        dl = ds - dth * track / 2
        dr = ds + dth * track / 2
        poses = integrate_arc(np.zeros(3), dl, dr, track)  # (K, 3)
        pts = self.footprint_points(0.5 * res)
        c, sn = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        wx = poses[:, 0, None] + c[:, None] * pts[None, :, 0] - sn[:, None] * pts[None, :, 1]
        wy = poses[:, 1, None] + sn[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1]
        flat = np.column_stack([wx.ravel(), wy.ravel()])
        states = grid.state_at(flat).reshape(wx.shape)
        own = self.inside_footprint(flat).reshape(wx.shape)
        blocked = ((states == CellState.OBSTACLE) | (states == CellState.DROPOFF)) & ~own
        hit_rows = np.nonzero(blocked.any(axis=1))[0]
        clearance, state = math.inf, None
        if hit_rows.size:
            k = int(hit_rows[0])
            clearance = float(ss[k] - step)  # last pose known free
            row_states = states[k][blocked[k]]
            state = (
                CellState.DROPOFF if np.any(row_states == CellState.DROPOFF) else CellState.OBSTACLE
            )
        near = (ss <= s.unknown_distance_mm)[:, None] & ~own
        if hit_rows.size:
            near &= (ss < ss[int(hit_rows[0])])[:, None]
        n_near = int(near.sum())
        unknown = float((states[near] == CellState.UNKNOWN).sum() / n_near) if n_near else 0.0
        return clearance, state, unknown

    def check(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        perception_age_s: float | None,
        now_s: float = 0.0,
        evidence: Evidence | None = None,
        evidence_key: object = None,
        unseen: Unseen | None = None,
    ) -> SafetyDecision:
        """The allowed twist for a requested (v mm/s, ω rad/s), given the map and its age (s).

        ``evidence`` / ``evidence_key``: the map's exact blocking evidence (see :meth:`sweep`).
        ``unseen``: the map's never-seen cells moved exactly into the robot frame (see
        :data:`Unseen`; named by ``evidence_key`` as well), which the unseen-space rules then
        use instead of the UNKNOWN cells of ``grid`` (space off ``grid`` is unseen either way;
        the unknown fraction, a share of points sampled at ``grid``'s centres, reads ``grid``).
        A limited turn is softened (module docstring, :meth:`soften`)."""
        if not (math.isfinite(v_mm_s) and math.isfinite(omega_rad_s)):
            return self._report(SafetyDecision(0.0, 0.0, 0.0, 0.0, (Reason.FAULT,)), now_s)
        if unseen is not None and evidence_key is None:
            raise ValueError("SafetyLayer.check: unseen cells need an evidence_key naming them")
        # kept until the next check: the caches are keyed on this map content, exact cells
        # included, so a later unknown_clearance for another request must read the same cells
        self._unseen = _ListedUnseen(*unseen) if isinstance(unseen, tuple) else unseen
        self._unseen_key = evidence_key
        return self._check(
            grid, v_mm_s, omega_rad_s, perception_age_s, now_s, evidence, evidence_key
        )

    def _check(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        perception_age_s: float | None,
        now_s: float,
        evidence: Evidence | None,
        evidence_key: object,
    ) -> SafetyDecision:
        """:meth:`check` after its input checks."""
        decision = self._limit(grid, v_mm_s, omega_rad_s, perception_age_s, evidence, evidence_key)
        # a straight forward request when what limits it within the slow zone is a side
        # intrusion a small shift clears (a door jamb); the arcs turn away from it
        if (
            decision.scale < 1.0
            and self.settings.soften
            and (
                omega_rad_s != 0.0
                or self._contact_side(grid, v_mm_s, evidence, evidence_key) != 0.0
            )
        ):
            decision = self.soften(
                grid, v_mm_s, omega_rad_s, decision, perception_age_s, evidence, evidence_key
            )
        return self._report(decision, now_s)

    def soften_candidates(
        self, v_mm_s: float, omega_rad_s: float, away_from: float = 0.0
    ) -> list[tuple[float, float]]:
        """The twists (mm/s, rad/s) a limited request may be softened into.

        A turn (v, ω ≠ 0): the same turn direction, never a reversed travel direction, never
        faster than asked — the turn at 1/2 and 1/4 of ω (a larger radius), an arc without its
        travel (a turn in place) or with half of it, an arc without its turn; a turn in place
        also with a forward component (``soften_forward_mm_s`` and half of it, fastest point) at
        ω and ω/2: its turn centre moved ahead so that the tail swings through less of what lies
        beside the chair.

        A straight forward request (v > 0, ω = 0): forward arcs each way whose radii shift the
        chair sideways by ``soften_side_shift_mm`` over the slow zone's travel (``_arc_radii_mm``),
        their fastest point no faster than asked (v·R/(R + r), r the farthest corner's radius) —
        the heading correction a rider a few degrees off a door's line needs; with
        ``away_from`` (the side, +1 left or −1 right, of what refuses the straight line) only
        those turning away from it. Reverse straight requests have none."""
        w = omega_rad_s
        if w == 0.0:
            if v_mm_s <= 0.0:
                return []
            r = self.r_max_mm
            out = []
            for radius in self._arc_radii_mm:
                v = v_mm_s * radius / (radius + r)
                out += [(v, w) for w in (v / radius, -v / radius) if w * away_from <= 0.0]
            return out
        out = [(v_mm_s, 0.5 * w), (v_mm_s, 0.25 * w)]
        if v_mm_s != 0.0:
            out += [(0.0, w), (0.5 * v_mm_s, w), (0.5 * v_mm_s, 0.5 * w), (v_mm_s, 0.0)]
        else:
            f = self.settings.soften_forward_mm_s
            if f > 0.0:
                out += [(f, w), (0.5 * f, w), (f, 0.5 * w), (0.5 * f, 0.5 * w)]
        return out

    def soften(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        limited: SafetyDecision,
        perception_age_s: float | None,
        evidence: Evidence | None = None,
        evidence_key: object = None,
    ) -> SafetyDecision:
        """The nearest allowed twist to a limited request: each of :meth:`soften_candidates` is
        checked exactly as a request would be (every rule applies to it), and the allowed twists
        — the request's own limited one among them — are scored by progress along the asked
        motion minus deviation from it, in mm/s of the footprint's motion (v, and ω times the
        farthest corner's radius): ``a·d̂ − |a − (a·d̂)·d̂|``. Standing still scores 0, so a
        candidate runs only if it moves the chair more the way the rider asked than aside; the
        request's own limited twist wins ties. Reason ``softened`` with the candidate's own.

        Only as many candidates are checked as can still win: the score is proportional to the
        scale a rule leaves (``score(k·a) = k·score(a)``), so a candidate's score unlimited bounds
        what it can reach. Candidates are checked best bound first, the rest are dropped once
        none of their bounds beats the best score found, and a candidate's rules stop as soon as
        its cap so far leaves it no chance (:meth:`_limit`'s ``beat_scale``). The choice is the
        one checking every candidate in turn would make (up to exact ties of score)."""
        r = self.r_max_mm
        dx, dy = v_mm_s, omega_rad_s * r
        norm = math.hypot(dx, dy)
        ux, uy = dx / norm, dy / norm

        def score(v: float, w: float) -> float:
            ax, ay = v, w * r
            p = ax * ux + ay * uy
            return p - math.hypot(ax - p * ux, ay - p * uy)

        best, best_score = limited, score(limited.v_mm_s, limited.omega_rad_s)
        side = (
            self._contact_side(grid, v_mm_s, evidence, evidence_key) if omega_rad_s == 0.0 else 0.0
        )
        candidates = self.soften_candidates(v_mm_s, omega_rad_s, side)
        bounded = [(score(v, w), v, w) for v, w in candidates]
        bounded.sort(key=lambda c: -c[0])  # stable: list order among equal bounds
        for bound, v, w in bounded:
            if bound <= best_score + 1e-6:
                break  # neither this candidate nor any after it can win
            d = self._limit(
                grid, v, w, perception_age_s, evidence, evidence_key, (best_score + 1e-6) / bound
            )
            if d is None:
                continue
            sc = bound * d.scale
            if d.scale > 0.0 and sc > best_score + 1e-6:
                best, best_score = d, sc
        if best is limited:
            return limited
        u = abs(v_mm_s) + abs(omega_rad_s) * r
        if omega_rad_s == 0.0:
            scale = min(1.0, best.v_mm_s / v_mm_s)  # of the asked forward speed
        else:
            scale = min(1.0, (abs(best.v_mm_s) + abs(best.omega_rad_s) * r) / u)
        return SafetyDecision(
            best.v_mm_s,
            best.omega_rad_s,
            scale,
            best.clearance_mm,
            _unique([Reason.SOFTENED, *best.reasons]),
        )

    @overload
    def _limit(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        perception_age_s: float | None,
        evidence: Evidence | None,
        evidence_key: object,
    ) -> SafetyDecision: ...

    @overload
    def _limit(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        perception_age_s: float | None,
        evidence: Evidence | None,
        evidence_key: object,
        beat_scale: float,
    ) -> SafetyDecision | None: ...

    def _limit(
        self,
        grid: OccupancyGrid,
        v_mm_s: float,
        omega_rad_s: float,
        perception_age_s: float | None,
        evidence: Evidence | None,
        evidence_key: object,
        beat_scale: float = -1.0,
    ) -> SafetyDecision | None:
        """The request (v, ω) scaled by the most restrictive rule (no softening, no logging).

        ``beat_scale`` (softening): ``None`` as soon as the rules checked so far leave a scale
        ≤ it — the rules only ever lower the scale, so the candidate cannot win; the dearer
        rules (escape gaps, unseen space, the unknown fraction) are then never evaluated."""
        s = self.settings
        u = abs(v_mm_s) + abs(omega_rad_s) * self.r_max_mm
        if u == 0.0:
            return SafetyDecision(0.0, 0.0, 1.0, math.inf)
        reasons: list[Reason] = []
        caps = [math.inf]
        beat_cap = beat_scale * u
        stale = perception_age_s is None or perception_age_s > s.perception_timeout_s
        if stale and v_mm_s > 0:
            reasons.append(Reason.PERCEPTION_STALE)
            caps.append(0.0)
            if beat_scale >= 0.0:
                return None
        b = self._blocking_sweep(grid, v_mm_s, omega_rad_s, evidence, evidence_key)
        clearance, lead, lead_state, swing, swing_state = (
            b.clearance_mm, b.lead_mm, b.lead_state, b.swing_mm, b.swing_state
        )  # fmt: skip
        lead_stop = lead <= s.stop_distance_mm
        swing_stop = swing <= s.swing_buffer_mm + self._swing_refuse_mm
        if lead_stop or swing_stop:
            drop = (lead_stop and lead_state is CellState.DROPOFF) or (
                swing_stop and swing_state is CellState.DROPOFF
            )
            escape_cap = u * min(
                s.escape_speed_mm_s / abs(v_mm_s) if v_mm_s else math.inf,
                s.escape_turn_rad_s / abs(omega_rad_s) if omega_rad_s else math.inf,
            )
            if beat_scale >= 0.0 and escape_cap <= beat_cap:
                return None  # not even as an escape move
            escape = not drop and self.is_escape(grid, v_mm_s, omega_rad_s, evidence, evidence_key)
            if escape:
                reasons.append(Reason.ESCAPE)
                caps.append(escape_cap)
            else:
                reasons.append(Reason.DROPOFF_STOP if drop else Reason.OBSTACLE_STOP)
                caps.append(0.0)
        else:
            if math.isfinite(lead):
                if lead <= s.slow_distance_mm and u > s.slow_speed_mm_s:
                    reasons.append(Reason.SLOW_ZONE)
                    caps.append(s.slow_speed_mm_s)
                cap = self._approach_cap(lead - s.stop_distance_mm)
                if u > cap:
                    reasons.append(Reason.APPROACH)
                    caps.append(cap)
            cap = self._swing_cap(swing - s.swing_buffer_mm)
            if u > cap:
                reasons.append(Reason.APPROACH)
                caps.append(cap)
        if min(caps) <= beat_cap:
            return None
        unseen, blind = self.unknown_clearance(grid, v_mm_s, omega_rad_s)
        creep = s.unknown_creep_speed_mm_s
        if s.unknown_policy == "creep":
            if unseen <= s.stop_distance_mm and u > creep:
                reasons.append(Reason.UNKNOWN_CREEP)
                caps.append(creep)
        else:
            unseen_lead, unseen_swing = self.unknown_contacts(grid, v_mm_s, omega_rad_s)
            if unseen_lead <= s.stop_distance_mm or unseen_swing <= self._swing_refuse_mm:
                reasons.append(Reason.UNKNOWN_STOP)
                caps.append(0.0)
            else:
                # no slow zone (nothing is known to be there), but it must stop before it
                cap = min(
                    self._approach_cap(unseen_lead - s.stop_distance_mm),
                    self._swing_cap(unseen_swing),
                )
                if u > cap:
                    reasons.append(Reason.UNKNOWN_AHEAD)
                    caps.append(cap)
        # the blind band is crossed at the creep speed, so it is approached no faster than the
        # chair can slow to it by the stop line (a cell that came into the band from the side,
        # in an arc or after a turn, would otherwise be met at the speed of free floor)
        room = max(0.0, blind - s.stop_distance_mm)
        cap = max(creep, self._approach_cap(room)) if blind < math.inf else u
        if u > cap:
            reasons.append(Reason.UNKNOWN_CREEP)
            caps.append(cap)
        if min(caps) <= beat_cap:
            return None
        unknown = self._sweep_unknown(grid, v_mm_s, omega_rad_s, clearance)
        if unknown > s.unknown_max_fraction and u > s.unknown_speed_mm_s:
            reasons.append(Reason.UNKNOWN_AHEAD)
            caps.append(s.unknown_speed_mm_s)
        if min(caps) <= beat_cap:
            return None
        scale = min(1.0, min(caps) / u)
        return SafetyDecision(
            v_mm_s * scale, omega_rad_s * scale, scale, clearance, _unique(reasons)
        )

    def _approach_cap(self, room_mm: float) -> float:
        """Speed cap (mm/s, fastest point) ``room_mm`` before the stop line: the time to reach it
        at least ``approach_time_s``, braking before it possible at ``brake_decel_mm_s2``, and
        never below ``approach_min_speed_mm_s`` (so the chair gets there)."""
        s = self.settings
        cap = min(room_mm / s.approach_time_s, math.sqrt(2.0 * s.brake_decel_mm_s2 * room_mm))
        return max(
            cap, min(s.approach_min_speed_mm_s, math.sqrt(2.0 * s.brake_decel_mm_s2 * room_mm))
        )

    def _report(self, d: SafetyDecision, now_s: float) -> SafetyDecision:
        for r in d.reasons:
            why = REASON_TEXT.get(r)
            self.log.log(
                r.value,
                (f"{why}: " if why else "")
                # rounded down: a slight limit reads 99 %, not a "limited to 100 %"
                + f"speed limited to {math.floor(100 * d.scale)}% "
                f"(clearance {d.clearance_mm:.0f} mm)",
                now_s,
            )
        return d
