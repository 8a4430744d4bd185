"""``ControlCore``: rider mux → safety → ramps and wheel PI, with odometry feeding the map.

Synchronous and clock-injected (docs/interfaces.md): the caller passes monotonic times, so the
asyncio daemon runs it in real time and the simulator faster than real time. Every fault path
ends in zero wheel velocity, logged with its reason; "zero" means duty 0 and ``enable=False`` in
the same cycle (the unit brakes), ramps and wheel PI integrators reset:

- rider input silent/stale/invalid (per source, see :mod:`omnid.daemon.rider`) → zero;
- control-unit status missing or older than ``control.status_timeout_s`` → zero (without
  feedback nothing can be regulated);
- a stopping control-unit fault flag → zero;
- the control-unit link unhealthy (``link_ok`` False, set by the daemon from the link's health:
  port gone or ``max_missed_replies`` replies missed) → zero at once;
- a stall: more than two command periods since the previous cycle → zero, and motion needs
  rider input newer than the stall (:mod:`omnid.daemon.arming`);
- an exception inside a cycle → zero;
- perception missing, stale, or older than ``safety.perception_max_travel_mm`` of travel → no
  forward motion (:mod:`omnid.daemon.safety`); the camera lost (``camera_ok`` False, set by the
  daemon) → at most ``safety.camera_lost_speed_mm_s`` at once;
- a bump — a wheel asked to turn whose clock counter does not move
  (:class:`~omnid.daemon.motion.StallDetector`) → duty 0 at once (the wheels are pressed against
  something: no ramp), and requests in the same direction (wheel velocities within
  ``motion.bump_same_direction_deg`` of the bumped ones) are refused (reason ``bump``) until the
  rider asks for something else — stop, centre, or another direction.

With ``control.rearm_after_fault`` (on in the shipped etc/omnid.yaml), after a fault the chair
does not resume by itself when the fault clears: motion stays refused (``rearm_wait``) until the
source that was driving has been seen live and at rest (:class:`~omnid.daemon.arming.Arming`),
so a command the rider held through the fault does not restart the wheels unannounced.

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
from omnid.core.pipeline import HealthSettings
from omnid.core.types import PointCloud
from omnid.daemon.arming import Arming
from omnid.daemon.config import OmnidConfig
from omnid.daemon.motion import MotionController, Odometry, StallDetector
from omnid.daemon.rider import JoystickSample, RiderDemand, RiderMux, TiltSample
from omnid.daemon.safety import Reason, ReasonLog, SafetyDecision, SafetyLayer
from omnid.devices.control_unit import WheelCommand
from omnid.devices.cu_codec import (
    FAULT_OVERCURRENT_LEFT,
    FAULT_OVERCURRENT_RIGHT,
    FAULT_STALE_COMMAND,
    FAULT_UNDERVOLTAGE,
    FAULT_WATCHDOG,
)

log = logging.getLogger(__name__)

#: Control-unit fault bits that stop the chair (docs/protocol.md). STALE_COMMAND: the unit
#: refused an ENABLE and braked — driving on would wind the wheel controller up against
#: wheels that do not turn, and the unit re-arms on any zero frame, so the daemon stops and
#: waits for the rider's re-arm. RESET (first reply after power-up) and RX_ERROR (a rejected
#: frame, which the unit ignored) are informational: the link's health and the unit's own
#: watchdog already cover a bus that keeps failing.
STOPPING_FAULTS = (
    FAULT_WATCHDOG
    | FAULT_OVERCURRENT_LEFT
    | FAULT_OVERCURRENT_RIGHT
    | FAULT_UNDERVOLTAGE
    | FAULT_STALE_COMMAND
)


#: A capture whose dots fit the calibration less than this (share on a calibrated laser beam,
#: ``PointCloud.calibration_fit``) means the rig was knocked: the pipeline's own threshold.
_MIN_CALIBRATION_FIT = HealthSettings().min_explained
# this many dots off the floor without a beam make a capture unusable (a ghost or two pair by
# chance; an obstacle lights dozens)
_MIN_NOT_UNDERSTOOD = 3


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
    @property
    def left_applied_duty(self) -> float: ...
    @property
    def right_applied_duty(self) -> float: ...


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
        self.bump_times: deque[float] = deque(maxlen=64)  # the latest bumps' times, s
        self.map: WorldMap = world_map if world_map is not None else default_map(config)
        self.laser_on = True  # what the perception cycle asks for (off for mask frames)
        self.capturing = False  # True while mask/base frames are being taken
        self.halt = False  # shutting down: stop at the emergency rate whatever the rider asks
        self.status: StatusSample | None = None
        # stopping fault bits of every reply since the last cycle: WATCHDOG and STALE_COMMAND
        # come in one reply only, and two replies between cycles (an urgent frame and the
        # regular one) would otherwise let the second hide the first
        self._unit_faults_since_step = 0
        self.perception_time_s: float | None = None
        # captures in a row did not fit the calibration (the rig was knocked): no forward motion
        self.calibration_lost = False
        self.misfit_clouds = 0  # clouds in a row that did not fit the calibration
        # the last capture had dots no known beam explains (floor-only calibration): not used
        self.not_understood = False
        self.last_report: CycleReport | None = None
        self._last_step_s: float | None = None
        # (t, x, y, θ, path length): odometry for late perception and the travel bound
        self._poses: deque[tuple[float, float, float, float, float]] = deque()
        self._log = ReasonLog(log, config.safety.log_interval_s)
        self.fault_count = 0
        self.link_ok = True  # the daemon clears it while the control-unit link is unhealthy
        self.camera_ok = True  # the daemon clears it while the cameras deliver nothing
        self.arming = Arming(config.control.rearm_after_fault, config.safety.log_interval_s)
        self.path_mm = 0.0  # odometry path length of the axle midpoint since start
        self._perception_path_mm = 0.0  # path length at the newest perception's capture ...
        self._perception_path_t: float | None = None  # ... for this perception time
        self._live_inputs: set[str] = set()  # continuous rider sources live last cycle

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

    def on_input_lost(self, source: str, now_s: float) -> None:
        """The device of rider source ``source`` says it is gone (port lost, readings stale) at
        monotonic ``now_s``: the source is stale from now (an input of its own, so that a
        recording replays it). Back, it drives only once seen at rest, even when the loss falls in
        a loop stall (which otherwise excuses a source gone quiet)."""
        self.mux.on_lost(source)
        self.arming.on_lost(source)

    def on_status(self, status: StatusSample) -> None:
        """A control-unit reply: odometry, the map's motion, the wheel speed estimate."""
        prev = self.status
        self.status = status
        self._unit_faults_since_step |= int(status.faults) & STOPPING_FAULTS
        if prev is not None and status.timestamp_s < prev.timestamp_s:
            return  # out of order: keep time monotonic
        # the duty the unit says it applies from now on, not the one the core asked for: a unit
        # that refused a command (stale, watchdog, not armed) holds its wheels at rest, and a
        # wheel at rest under duty 0 is no bump
        self.stall.on_status(
            int(status.left_clocks),
            int(status.right_clocks),
            float(status.timestamp_s),
            (float(status.left_applied_duty), float(status.right_applied_duty)),
        )
        dx, dy, dth = self.odometry.update(
            int(status.left_clocks),
            int(status.right_clocks),
            float(status.timestamp_s),
            self.motion.targets_mm_s,
        )
        if dx or dy or dth:
            self.map.move(dx, dy, dth)
            self.path_mm += math.hypot(dx, dy)
        occupy = getattr(self.map, "occupy", None)
        if occupy is not None:  # the chair's own trail is seen free space
            sf = self.config.safety
            w = 0.5 * sf.footprint_width_mm
            occupy(-sf.footprint_rear_mm, sf.footprint_front_mm, -w, w)
        x, y, th = (float(v) for v in self.odometry.pose)
        self._poses.append((float(status.timestamp_s), x, y, th, self.path_mm))
        horizon = float(status.timestamp_s) - self.config.control.pose_history_s
        while self._poses and self._poses[0][0] < horizon:
            self._poses.popleft()

    def _pose_at(self, t_s: float) -> tuple[float, float, float, float] | None:
        """(x, y, θ, path length) at monotonic ``t_s`` from the odometry history."""
        best = None
        for t, x, y, th, path in self._poses:
            if t <= t_s:
                best = (x, y, th, path)
            else:
                break
        if best is None and self._poses:
            t, x, y, th, path = self._poses[0]
            best = (x, y, th, path) if t - t_s < 0.1 else None
        return best

    def on_perception(self, cloud: PointCloud, capture_time_s: float) -> None:
        """A perception result for frames taken at ``capture_time_s``: into the map, compensated
        for the motion since then."""
        fit = cloud.calibration_fit
        if math.isfinite(fit) and fit < _MIN_CALIBRATION_FIT:
            # garbage in: keep it out of the map; several in a row mean the rig was knocked —
            # refuse forward motion until a capture fits again (one alone is a bad frame: a
            # laser switching during the exposure, glare; it is only dropped)
            self.misfit_clouds += 1
            if (
                not self.calibration_lost
                and self.misfit_clouds >= self.config.perception.calibration_lost_clouds
            ):
                log.error(
                    "calibration_lost: only %.0f %% of the dots lie on a calibrated laser beam "
                    "in %d captures in a row: the rig has moved since calibration; forward "
                    "motion refused (recalibrate)",
                    100 * fit,
                    self.misfit_clouds,
                )
                self.calibration_lost = True
            elif not self.calibration_lost:
                log.info(
                    "perception: a capture does not fit the calibration (%.0f %% of the dots on "
                    "a beam): not used",
                    100 * fit,
                )
            return
        if math.isfinite(fit):
            self.misfit_clouds = 0
        if cloud.not_understood >= _MIN_NOT_UNDERSTOOD:
            # dots off the floor that no known beam explains (floor-only calibration): that area
            # is not free space, and the capture is kept out of the map — perception goes stale
            # and the freshness rule stops the chair, as with no capture
            if not self.not_understood:
                log.warning(
                    "perception: %d dots off the floor not understood (the laser's source is "
                    "unknown: recalibrate with --extra); such captures are not used",
                    cloud.not_understood,
                )
            self.not_understood = True
            return
        self.not_understood = False
        if self.calibration_lost and math.isfinite(fit):
            log.warning("calibration_lost cleared: %.0f %% of the dots fit again", 100 * fit)
            self.calibration_lost = False
        then = self._pose_at(capture_time_s)
        if then is None and self._poses:
            # older than the odometry history: where the chair was then is not known, and the
            # cloud placed as if taken here would put what it saw in the wrong place
            self._log.log(
                "perception_too_old",
                f"perception: a capture {self._poses[-1][0] - capture_time_s:.1f} s old is "
                "older than the odometry history (control.pose_history_s): not used",
                self._poses[-1][0],
            )
            return
        offset = self.config.perception.rig_x_offset_mm
        source = (0.0, 0.0, 0.0)  # the laser, where it was at the capture (current rig frame)
        if then is not None and self._poses:
            _, x1, y1, th1, _ = self._poses[-1]
            x0, y0, th0, _ = then
            c, s = math.cos(th0), math.sin(th0)
            dxw, dyw = x1 - x0, y1 - y0
            motion = (c * dxw + s * dyw, -s * dxw + c * dyw, th1 - th0)
            cloud = transform_cloud(cloud, *motion, offset)
            sx, sy, sz = (float(v) for v in transform_rig_xyz([0.0, 0.0, 0.0], *motion, offset)[0])
            source = (sx, sy, sz)
        try:
            self.map.update(cloud, offset, capture_time_s, source_mm=source)
        except Exception:
            # a map half updated is not known to be right: it is forgotten (turning and
            # reversing then meet unseen floor: refused) and no forward motion until a cloud
            # enters cleanly (the freshness rule, as with no perception yet)
            self.perception_time_s = None
            clear = getattr(self.map, "clear", None)
            if clear is not None:
                clear()
            raise
        if len(cloud) == 0:
            return  # no dots: no evidence that the way is clear, the map's age keeps growing
        if self.perception_time_s is None or capture_time_s > self.perception_time_s:
            self.perception_time_s = float(capture_time_s)

    def perception_travel_mm(self) -> float:
        """Path length driven since the newest perception was captured (inf: none yet, or
        older than the odometry history)."""
        t = self.perception_time_s
        if t is None:
            return math.inf
        if t != self._perception_path_t:
            at = self._pose_at(t)
            self._perception_path_t = t
            self._perception_path_mm = math.inf if at is None else at[3]
            if at is None and not self._poses:
                self._perception_path_mm = self.path_mm  # no odometry yet: nothing driven
        return self.path_mm - self._perception_path_mm

    # ---- the cycle ----------------------------------------------------------------------
    def _on_bump(self, stalled: tuple[bool, bool], now_s: float) -> None:
        """A stalled wheel: remember the direction the wheels were driven in, stop now."""
        vl, vr = self.motion.targets_mm_s
        norm = math.hypot(vl, vr)
        self.bump_count += 1
        self.bump_times.append(now_s)
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

    def _evidence(self) -> tuple[Any, object, Any]:
        """The map's exact blocking evidence near the chair, a key naming it (its version and
        the chair's pose in it) and its never-seen cells moved exactly into the robot frame, or
        (None, None, None) for a map that has none (a bare grid: its own cells then)."""
        get = getattr(self.map, "blocking_evidence", None)
        if get is None:
            return None, None, None
        sf = self.config.safety
        reach = sf.horizon_mm + self.safety.r_max_mm + self.grid.settings.resolution_mm
        key = (getattr(self.map, "version", None), getattr(self.map, "pose_in_anchor", None))
        # a view: the cells are moved into the robot frame only where a sweep reaches
        unknown = getattr(self.map, "unseen_cells", None) or getattr(
            self.map, "unknown_cells", None
        )
        return get(reach), key, None if unknown is None else unknown(reach)

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
            self.arming.on_fault("cycle_exception", now_s)
            return self._zero(now_s, RiderDemand(reason="fault"), Reason.FAULT)

    def fault(self, reason: str, now_s: float) -> WheelCommand:
        """A fault found outside the core (the daemon's control loop failed): zero now, and the
        re-arm rule as for any fault."""
        self.fault_count += 1
        self.arming.on_fault(reason, now_s)
        return self._zero(now_s, RiderDemand(reason="fault"), Reason.FAULT)

    def _zero(self, now_s: float, demand: RiderDemand, reason: Reason) -> WheelCommand:
        """Duty 0 with ENABLE cleared this cycle; ramps and wheel integrators reset."""
        self.motion.reset()
        cmd = WheelCommand(0.0, 0.0, laser_on=self.laser_on, enable=False)
        self.last_report = CycleReport(now_s, demand, None, cmd, (reason,))
        return cmd

    def _inputs_lost(self, now_s: float) -> list[str]:
        """Continuous rider sources (tilt, joystick) that were live last cycle and are not now."""
        r = self.config.rider
        live = {
            n for n in ("tilt", "joystick") if getattr(r, n).enabled and self.mux.is_live(n, now_s)
        }
        lost = sorted(self._live_inputs - live)
        self._live_inputs = live
        return lost

    def _step(self, now_s: float) -> WheelCommand:
        cfg = self.config
        prev = self._last_step_s
        gap = 0.0 if prev is None else now_s - prev
        dt = min(max(gap, 0.0), cfg.control.max_dt_s)
        self._last_step_s = now_s
        demand = self.mux.decide(now_s)
        if self.halt:
            demand = RiderDemand(stop=True, source="daemon", reason="shutdown_stale")
        self.arming.observe(self.mux, now_s)
        # inputs that went stale during a stall are the stall's doing, not a fault of their own
        lost = self._inputs_lost(now_s)
        loop_stalled = gap > cfg.control_unit.max_command_age_s + 1e-6
        if loop_stalled:
            # the loop did not run: whatever the wheels do was computed before the stall
            self.arming.on_stall(now_s)
            lost = []
            self._log.log(
                "stall",
                f"control loop stalled {gap * 1000:.0f} ms; wheels stopped, motion needs new "
                "rider input",
                now_s,
            )
        for name in lost:  # even in a cycle that stops for another fault (a silent unit):
            self.arming.on_lost(name)  # a reconnect must be seen at rest before it drives
        st = self.status
        unit_faults, self._unit_faults_since_step = self._unit_faults_since_step, 0
        if st is not None:
            unit_faults |= int(st.faults) & STOPPING_FAULTS  # the newest reply's, every cycle
        if (
            st is None
            or not self.link_ok
            or now_s - st.timestamp_s > cfg.control.status_timeout_s
            or unit_faults
        ):
            stopping = unit_faults
            reason = "control_unit_fault" if stopping else "status_stale"
            code = Reason.STATUS_STALE if reason == "status_stale" else Reason.FAULT
            self._log.log(reason, "no valid control-unit status; wheels stopped", now_s)
            if st is not None:  # start-up (no status yet) needs no re-arming
                self.arming.on_fault(reason, now_s)
            if st is None:
                self.odometry.reset()
            return self._zero(now_s, demand, code)
        if loop_stalled:
            self.arming.filter(demand, self.mux, now_s)  # a release is a release, even now
            ramp = self.motion.ramp
            v, w = ramp.v_mm_s, ramp.omega_rad_s
            cmd = self._zero(now_s, demand, Reason.FAULT)
            if gap < cfg.control_unit.unit_watchdog_s:
                # the unit kept the wheels going through the stall: resume from the ramp's
                # speed (integrators reset), not from a standstill the chair never reached
                ramp.v_mm_s, ramp.omega_rad_s = v, w
            return cmd
        for name in lost:
            self.arming.on_fault(f"{name}_lost", now_s)
        if (
            demand.stop
            and demand.source != "daemon"
            and demand.reason.endswith(("_stale", "_invalid"))
        ):
            self._log.log(demand.reason, "rider input lost; wheels stopped", now_s)
            return self._zero(now_s, demand, Reason.INPUT_STALE)
        reasons: list[Reason] = []
        m = cfg.motion
        emergency = False
        allowed = self.arming.filter(demand, self.mux, now_s)
        if allowed is not demand:
            reasons.append(Reason.FAULT)
            demand = allowed
        if demand.stop:
            v_req = w_req = 0.0
            if demand.reason.endswith("_stale"):  # shutdown: the emergency ramp
                reasons.append(Reason.INPUT_STALE)
                emergency = True
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
        if self.calibration_lost and v_req > 0:
            v_req = 0.0
            reasons.append(Reason.CALIBRATION_LOST)
        if not self.camera_ok:
            cap = cfg.safety.camera_lost_speed_mm_s
            if abs(v_req) > cap:
                v_req = math.copysign(cap, v_req)
                reasons.append(Reason.CAMERA_LOST)
            emergency = emergency or abs(self.motion.ramp.v_mm_s) > cap + 1e-9
        age = None if self.perception_time_s is None else now_s - self.perception_time_s
        if self.perception_travel_mm() > cfg.safety.perception_max_travel_mm:
            age = None  # driven too far on this map: as stale as an old one
        if bump_refused:
            decision = SafetyDecision(0.0, 0.0, 0.0, 0.0, (Reason.BUMP,))
        else:
            evidence, key, unseen = self._evidence()
            decision = self.safety.check(self.grid, v_req, w_req, age, now_s, evidence, key, unseen)
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
