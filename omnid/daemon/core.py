"""``ControlCore``: rider mux → safety → ramps and wheel PI, with odometry feeding the map.

Synchronous and clock-injected (docs/interfaces.md): the caller passes monotonic times, so the
asyncio daemon runs it in real time and the simulator faster than real time. Every fault path
ends in zero wheel velocity, logged with its reason:

- rider input silent/stale (per source, see :mod:`omnid.daemon.rider`) → emergency ramp to 0;
- control-unit status missing or older than ``control.status_timeout_s`` → duty 0 at once and
  ``enable=False`` (without feedback nothing can be regulated; the control unit brakes);
- a control-unit fault flag → likewise;
- perception missing or stale → no forward motion (:mod:`omnid.daemon.safety`);
- the control-unit port is gone (``link_ok`` False, set by the daemon from the link's health)
  → likewise, at once rather than after ``status_timeout_s``;
- an exception inside a cycle → duty 0, ``enable=False``, controllers reset;
- a bump — a wheel asked to turn whose clock counter does not move
  (:class:`~omnid.daemon.motion.StallDetector`) → duty 0 at once (the wheels are pressed against
  something: no ramp), and requests in the same direction (wheel velocities within
  ``motion.bump_same_direction_deg`` of the bumped ones) are refused (reason ``bump``) until the
  rider asks for something else — stop, centre, or another direction.

With ``control.rearm_after_fault`` (on in the shipped etc/omnid.yaml), after a control-unit
fault or an exception the chair does not resume by itself when the link comes back: motion
stays refused (``rearm``) until the rider's demand has been idle or stop once, so a command the
rider held through the fault does not restart the wheels unannounced.

Perception results arrive late (they are computed in a worker thread while the chair moves):
the cloud is moved into the current robot frame by the odometry between its capture time and
now before it enters the map, so that obstacles land where they are.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from omnid.core.freespace import FreeSpaceMap
from omnid.core.kinematics import wheel_speeds
from omnid.core.occupancy import OccupancyGrid
from omnid.core.types import PointCloud
from omnid.daemon.config import OmnidConfig
from omnid.daemon.motion import MotionController, Odometry, StallDetector
from omnid.daemon.rider import JoystickSample, RiderDemand, RiderMux, TiltSample
from omnid.daemon.safety import Reason, ReasonLog, SafetyDecision, SafetyLayer
from omnid.devices.control_unit import WheelCommand
from omnid.devices.cu_codec import (
    FAULT_OVERCURRENT_LEFT,
    FAULT_OVERCURRENT_RIGHT,
    FAULT_UNDERVOLTAGE,
    FAULT_WATCHDOG,
)

log = logging.getLogger(__name__)

#: Control-unit fault bits that stop the chair (docs/protocol.md). RESET (first reply after
#: power-up) and RX_ERROR (a rejected frame, which the unit ignored) are informational: the link's
#: health and the unit's own watchdog already cover a bus that keeps failing.
STOPPING_FAULTS = (
    FAULT_WATCHDOG | FAULT_OVERCURRENT_LEFT | FAULT_OVERCURRENT_RIGHT | FAULT_UNDERVOLTAGE
)


class StatusSample(Protocol):
    """What the core reads of ``omnid.devices.control_unit.ControlUnitStatus``."""

    @property
    def left_clocks(self) -> int: ...
    @property
    def right_clocks(self) -> int: ...
    @property
    def laser_on(self) -> bool: ...
    @property
    def faults(self) -> int: ...
    @property
    def timestamp_s(self) -> float: ...


class WorldMap(Protocol):
    """What the core needs of ``omnid.core.freespace.FreeSpaceMap``."""

    def update(
        self,
        cloud: PointCloud,
        rig_x_offset_mm: float = 0.0,
        now_s: float | None = None,
        source_mm: tuple[float, float, float] | None = None,
    ) -> Any: ...
    def move(self, dx_mm: float, dy_mm: float, dtheta_rad: float) -> Any: ...


def _grid_of(world_map: Any) -> OccupancyGrid:
    if isinstance(world_map, OccupancyGrid):
        return world_map
    grid = getattr(world_map, "grid", None)
    if isinstance(grid, OccupancyGrid):
        return grid
    raise TypeError("the world map must be an OccupancyGrid or have one as .grid")


def default_map(config: OmnidConfig) -> FreeSpaceMap:
    """The free-space map of :mod:`omnid.core.freespace` with the configured settings."""
    return FreeSpaceMap(config.freespace)


@dataclass(frozen=True)
class CycleReport:
    """What one :meth:`ControlCore.step` decided (for logs, STATUS= and the benchmarks)."""

    now_s: float
    demand: RiderDemand
    decision: SafetyDecision | None
    command: WheelCommand
    reasons: tuple[Reason, ...]


def transform_cloud(
    cloud: PointCloud, dx_mm: float, dy_mm: float, dtheta_rad: float, rig_x_offset_mm: float
) -> PointCloud:
    """Re-express a rig-frame cloud after the robot moved by (dx, dy, dθ) (old robot frame).

    Rig → robot: x = X + offset, y = −Y (:func:`omnid.core.occupancy.rig_to_robot`); a point
    fixed in the world has new robot coordinates R(−dθ)·(p − d). Z (depth) is unchanged.
    """
    if len(cloud) == 0 or (dx_mm == 0.0 and dy_mm == 0.0 and dtheta_rad == 0.0):
        return cloud
    return replace(
        cloud, xyz=transform_rig_xyz(cloud.xyz, dx_mm, dy_mm, dtheta_rad, rig_x_offset_mm)
    )


def transform_rig_xyz(
    xyz: Any, dx_mm: float, dy_mm: float, dtheta_rad: float, rig_x_offset_mm: float
) -> Any:
    """Rig-frame points (N, 3) re-expressed after the robot moved (see :func:`transform_cloud`)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    x = xyz[:, 0] + rig_x_offset_mm - dx_mm
    y = -xyz[:, 1] - dy_mm
    c, s = math.cos(dtheta_rad), math.sin(dtheta_rad)
    xn, yn = c * x + s * y, -s * x + c * y
    return np.column_stack([xn - rig_x_offset_mm, -yn, xyz[:, 2]])


class ControlCore:
    """The daemon's decision-making, one synchronous :meth:`step` per control period."""

    def __init__(
        self, config: OmnidConfig | None = None, world_map: WorldMap | None = None
    ) -> None:
        config = config if config is not None else OmnidConfig()
        self.config = config
        self.mux = RiderMux(config.rider)
        self.safety = SafetyLayer(config.safety)
        self.motion = MotionController(config.motion)
        self.odometry = Odometry(config.motion)
        self.stall = StallDetector(config.motion)
        self.bump_direction: tuple[float, float] | None = None  # unit (left, right) of a bump
        self.bump_count = 0
        self.map: WorldMap = world_map if world_map is not None else default_map(config)
        self.laser_on = True  # what the perception cycle asks for (off for mask frames)
        self.capturing = False  # True while mask/base frames are being taken
        self.halt = False  # shutting down: stop at the emergency rate whatever the rider asks
        self.status: StatusSample | None = None
        self.perception_time_s: float | None = None
        self.last_report: CycleReport | None = None
        self._last_step_s: float | None = None
        self._poses: deque[tuple[float, float, float, float]] = deque()
        self._log = ReasonLog(log, config.safety.log_interval_s)
        self.fault_count = 0
        self.link_ok = True  # the daemon clears it while the control-unit link is unhealthy
        self.rearm_after: str | None = None  # a fault stopped the chair: wait for a release

    @property
    def grid(self) -> OccupancyGrid:
        """The map as a grid in the current robot frame (what the safety layer checks)."""
        return _grid_of(self.map)

    # ---- inputs -------------------------------------------------------------------------
    def on_tilt(self, reading: TiltSample) -> None:
        self.mux.on_tilt(reading)

    def on_joystick(self, reading: JoystickSample) -> None:
        self.mux.on_joystick(reading)

    def on_key(self, command: str, now_s: float) -> None:
        self.mux.on_key(command, now_s)

    def on_status(self, status: StatusSample) -> None:
        """A control-unit reply: odometry, the map's motion, the wheel speed estimate."""
        prev = self.status
        self.status = status
        if prev is not None and status.timestamp_s < prev.timestamp_s:
            return  # out of order: keep time monotonic
        self.stall.on_status(
            int(status.left_clocks),
            int(status.right_clocks),
            float(status.timestamp_s),
            self.motion.duties,
        )
        dx, dy, dth = self.odometry.update(
            int(status.left_clocks),
            int(status.right_clocks),
            float(status.timestamp_s),
            self.motion.targets_mm_s,
        )
        if dx or dy or dth:
            self.map.move(dx, dy, dth)
        occupy = getattr(self.map, "occupy", None)
        if occupy is not None:  # the chair's own trail is seen free space
            sf = self.config.safety
            w = 0.5 * sf.footprint_width_mm
            occupy(-sf.footprint_rear_mm, sf.footprint_front_mm, -w, w)
        x, y, th = (float(v) for v in self.odometry.pose)
        self._poses.append((float(status.timestamp_s), x, y, th))
        horizon = float(status.timestamp_s) - self.config.control.pose_history_s
        while self._poses and self._poses[0][0] < horizon:
            self._poses.popleft()

    def _pose_at(self, t_s: float) -> tuple[float, float, float] | None:
        best = None
        for t, x, y, th in self._poses:
            if t <= t_s:
                best = (x, y, th)
            else:
                break
        if best is None and self._poses:
            t, x, y, th = self._poses[0]
            best = (x, y, th) if t - t_s < 0.1 else None
        return best

    def on_perception(self, cloud: PointCloud, capture_time_s: float) -> None:
        """A perception result for frames taken at ``capture_time_s``: into the map, compensated
        for the motion since then."""
        then = self._pose_at(capture_time_s)
        offset = self.config.perception.rig_x_offset_mm
        source = (0.0, 0.0, 0.0)  # the laser, where it was at the capture (current rig frame)
        if then is not None and self._poses:
            _, x1, y1, th1 = self._poses[-1]
            x0, y0, th0 = then
            c, s = math.cos(th0), math.sin(th0)
            dxw, dyw = x1 - x0, y1 - y0
            motion = (c * dxw + s * dyw, -s * dxw + c * dyw, th1 - th0)
            cloud = transform_cloud(cloud, *motion, offset)
            sx, sy, sz = (float(v) for v in transform_rig_xyz([0.0, 0.0, 0.0], *motion, offset)[0])
            source = (sx, sy, sz)
        self.map.update(cloud, offset, capture_time_s, source_mm=source)
        if len(cloud) == 0:
            return  # no dots: no evidence that the way is clear, the map's age keeps growing
        if self.perception_time_s is None or capture_time_s > self.perception_time_s:
            self.perception_time_s = float(capture_time_s)

    # ---- the cycle ----------------------------------------------------------------------
    def _on_bump(self, stalled: tuple[bool, bool], now_s: float) -> None:
        """A stalled wheel: remember the direction the wheels were driven in, stop now."""
        vl, vr = self.motion.targets_mm_s
        norm = math.hypot(vl, vr)
        self.bump_count += 1
        wheels = " and ".join(n for n, k in zip(("left", "right"), stalled, strict=True) if k)
        asked = max(self.stall.asked_mm)
        self._log.log(
            "bump",
            f"{wheels} wheel asked for {asked:.0f} mm without a clock (wheels at "
            f"{vl:.0f}/{vr:.0f} mm/s): stopped; that direction is refused until the rider "
            "asks for something else",
            now_s,
            logging.ERROR,
        )
        if norm > 0.0:
            self.bump_direction = (vl / norm, vr / norm)
        self.stall.reset()

    def _same_direction(self, v_mm_s: float, omega_rad_s: float) -> bool:
        """Whether a requested twist drives the wheels the way they were driven at the bump."""
        if self.bump_direction is None:
            return False
        vl, vr = wheel_speeds(v_mm_s, omega_rad_s, self.config.motion.track_mm)
        norm = math.hypot(float(vl), float(vr))
        if norm == 0.0:
            return False
        cos = (float(vl) * self.bump_direction[0] + float(vr) * self.bump_direction[1]) / norm
        return cos >= math.cos(math.radians(self.config.motion.bump_same_direction_deg))

    def _evidence(self) -> tuple[Any, object]:
        """The map's exact blocking evidence near the chair and a key naming it (its version and
        the chair's pose in it), or (None, None) for a map that has none (a bare grid)."""
        get = getattr(self.map, "blocking_evidence", None)
        if get is None:
            return None, None
        sf = self.config.safety
        reach = sf.horizon_mm + self.safety.r_max_mm + self.grid.settings.resolution_mm
        key = (getattr(self.map, "version", None), getattr(self.map, "pose_in_anchor", None))
        return get(reach), key

    def step(self, now_s: float) -> WheelCommand:
        """One control cycle at monotonic time ``now_s``; never raises."""
        try:
            return self._step(float(now_s))
        except Exception as exc:  # fail safe: any bug in a cycle stops the chair
            self.fault_count += 1
            self._log.log(
                "cycle_exception",
                f"{type(exc).__name__}: {exc}; wheels stopped",
                now_s,
                logging.ERROR,
            )
            log.debug("cycle exception", exc_info=True)
            self.motion.reset()
            self.rearm_after = "cycle_exception"
            cmd = WheelCommand(0.0, 0.0, laser_on=self.laser_on, enable=False)
            self.last_report = CycleReport(
                now_s, RiderDemand(reason="fault"), None, cmd, (Reason.FAULT,)
            )
            return cmd

    def _step(self, now_s: float) -> WheelCommand:
        cfg = self.config
        dt = 0.0 if self._last_step_s is None else now_s - self._last_step_s
        dt = min(max(dt, 0.0), cfg.control.max_dt_s)
        self._last_step_s = now_s
        demand = self.mux.decide(now_s)
        if self.halt:
            demand = RiderDemand(stop=True, source="daemon", reason="shutdown_stale")
        st = self.status
        if (
            st is None
            or not self.link_ok
            or now_s - st.timestamp_s > cfg.control.status_timeout_s
            or st.faults & STOPPING_FAULTS
        ):
            stopping = 0 if st is None else st.faults & STOPPING_FAULTS
            reason = "control_unit_fault" if stopping else "status_stale"
            code = Reason.STATUS_STALE if reason == "status_stale" else Reason.FAULT
            self._log.log(reason, "no valid control-unit status; wheels stopped", now_s)
            if st is not None:  # start-up (no status yet) needs no re-arming
                self.rearm_after = reason
            self.motion.reset()
            if st is None:
                self.odometry.reset()
            cmd = WheelCommand(0.0, 0.0, laser_on=self.laser_on, enable=False)
            self.last_report = CycleReport(now_s, demand, None, cmd, (code,))
            return cmd
        reasons: list[Reason] = []
        m = cfg.motion
        emergency = False
        if self.rearm_after is not None and not cfg.control.rearm_after_fault:
            self.rearm_after = None
        if self.rearm_after is not None:
            if demand.moving:
                self._log.log(
                    "rearm",
                    f"motion refused until the rider releases the command (after "
                    f"{self.rearm_after})",
                    now_s,
                )
                demand = RiderDemand(stop=True, source=demand.source, reason="rearm_wait")
                reasons.append(Reason.FAULT)
            else:
                log.info("rider released after %s: motion allowed again", self.rearm_after)
                self.rearm_after = None
        if demand.stop:
            v_req = w_req = 0.0
            if demand.reason.endswith(("_stale", "_invalid")):  # silence, bad input, shutdown
                reasons.append(Reason.INPUT_STALE)
                emergency = True
                self._log.log(demand.reason, "rider input lost; stopping", now_s)
            elif demand.reason.endswith("_stop"):
                reasons.append(Reason.RIDER_STOP)
        else:
            top = m.max_speed_mm_s if demand.forward >= 0 else m.max_reverse_speed_mm_s
            v_req = demand.forward * top
            w_req = demand.turn * m.max_turn_rate_rad_s
        stalled = self.stall.stalled
        if any(stalled):
            self._on_bump(stalled, now_s)
        bump_refused = False
        if self.bump_direction is not None:
            if self._same_direction(v_req, w_req):
                bump_refused = True
                self._log.log("bump", "same direction as the bump refused", now_s)
            else:
                log.info("bump: the rider asked for something else; motion allowed again")
                self.bump_direction = None
        if self.capturing and cfg.perception.capture_policy == "limit":
            cap = cfg.perception.capture_speed_mm_s
            v_req = min(max(v_req, -cap), cap)
        age = None if self.perception_time_s is None else now_s - self.perception_time_s
        if bump_refused:
            decision = SafetyDecision(0.0, 0.0, 0.0, 0.0, (Reason.BUMP,))
        else:
            evidence, key = self._evidence()
            decision = self.safety.check(self.grid, v_req, w_req, age, now_s, evidence, key)
        reasons.extend(decision.reasons)
        if decision.scale < 1.0 and (decision.stopped or decision.reasons):
            # refused or limited: brake at the emergency rate if the chair is faster than allowed
            emergency = emergency or (
                abs(self.motion.ramp.v_mm_s) > abs(decision.v_mm_s) + 1e-9
                or abs(self.motion.ramp.omega_rad_s) > abs(decision.omega_rad_s) + 1e-9
            )
        measured = self.odometry.wheel_speeds()
        if any(stalled):  # pressed against something: no ramp, the duty goes to zero now
            self.motion.reset()
        left, right = self.motion.step(
            decision.v_mm_s, decision.omega_rad_s, measured, dt, emergency
        )
        moving = left != 0.0 or right != 0.0
        cmd = WheelCommand(left, right, laser_on=self.laser_on, enable=moving)
        self.last_report = CycleReport(now_s, demand, decision, cmd, tuple(reasons))
        return cmd
