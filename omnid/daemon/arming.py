"""Who may set the chair moving again after a fault or a stall (:class:`Arming`).

Two rules, both applied by :class:`~omnid.daemon.core.ControlCore` every cycle:

- **Re-arm after a fault** (``control.rearm_after_fault``). A fault — the control-unit link
  unhealthy or silent, a stopping fault bit, a lost rider input (a tilt sensor or joystick that
  was live and fell silent, stale or invalid), an exception in a cycle — stops the wheels at
  once. Motion stays refused (``rearm_wait``) until the fault has cleared *and* the source that
  was driving when it struck has been seen live and at rest after that (the head back inside
  its thresholds or in the stop pose, the stick centred, no motion key held). A source that is
  silent is not at rest: a tilt sensor that is still unplugged re-arms nothing. When nothing was
  driving, the fault's clearing re-arms.
- **Armed at start-up.** A continuous source (head tilt, joystick) drives only after it has
  been seen live and at rest once since the daemon started: a head still tilted, or a stick
  still pushed, when a restarted daemon comes up (systemd restarts one whose loop died) does not
  set the chair moving. (With the shipped neutral-pose calibration a tilted head cannot even
  calibrate.) The same holds after a reconnect: a continuous source that was lost (unplugged,
  silent, stale, invalid) must be seen live and at rest again before it drives, whether or not
  it was driving when it went — a stick replugged already pushed, a head back already tilted,
  does not set the chair moving.
- **A new live demand after a stall.** When the control loop has not run for longer than two
  command periods (the event loop stalled, the machine froze), the first command is zero
  (:meth:`ControlCore.step`) and motion needs input that arrived after the stall: a demand
  computed from a reading older than the stall does not restart the wheels.
"""

from __future__ import annotations

import logging
import math

from omnid.daemon.rider import RiderDemand, RiderMux
from omnid.logs import LogThrottle

__all__ = ["Arming"]

log = logging.getLogger(__name__)


class Arming:
    """The re-arm and stall rules of the module docstring; ``enabled``:
    ``control.rearm_after_fault`` (the stall rule always applies)."""

    def __init__(self, enabled: bool, log_interval_s: float = 2.0) -> None:
        self.enabled = enabled
        self.fault: str | None = None  # the fault that stopped the chair, until re-armed
        self.driver: str | None = None  # the source that was driving when it struck
        self.cleared_s: float | None = None  # when the fault cleared (None: still active)
        self.live_after_s = -math.inf  # motion needs input newer than this (after a stall)
        self._last_driver: str | None = None  # the source of the previous cycle's motion
        self._throttle = LogThrottle(log, log_interval_s)
        self.at_rest_seen: set[str] = set()  # continuous sources seen at rest since start
        self._relost: set[str] = set()  # sources lost since: the calibration no longer counts

    def on_fault(self, reason: str, now_s: float) -> None:
        """A fault is active in this cycle (called every cycle while it lasts)."""
        if not self.enabled:
            return
        if self.fault is None:
            self.fault = reason
            self.driver = self._last_driver
            who = f"{self.driver} must be released" if self.driver else "nothing was driving"
            log.warning("fault %s: wheels stopped; motion resumes once it clears (%s)", reason, who)
        self.cleared_s = None
        self._last_driver = None

    def on_lost(self, name: str) -> None:
        """Continuous source ``name`` was live and is not now: it must be seen at rest again
        before it drives (the start-up rule, after a reconnect)."""
        if name in _CONTINUOUS:
            self.at_rest_seen.discard(name)
            self._relost.add(name)

    def observe(self, mux: RiderMux, now_s: float) -> None:
        """Every cycle, whatever else happens: note the sources seen at rest (start-up rule)."""
        if len(self.at_rest_seen) < len(_CONTINUOUS):
            if mux.tilt.calibrated and "tilt" not in self._relost:
                # the neutral-pose calibration held the head still (at start, not after a loss)
                self.at_rest_seen.add("tilt")
            for name in _CONTINUOUS:
                if name not in self.at_rest_seen and mux.released(name, now_s, -math.inf):
                    self.at_rest_seen.add(name)
                    self._relost.discard(name)

    def on_stall(self, now_s: float) -> None:
        """The control loop did not run for too long: motion needs input newer than now."""
        self.live_after_s = now_s

    def filter(self, demand: RiderDemand, mux: RiderMux, now_s: float) -> RiderDemand:
        """The demand allowed in a cycle without an active fault: ``demand`` itself, or a stop
        (reason ``rearm_wait`` or ``stall_wait``) while a rule holds motion back."""
        if self.enabled:
            src = demand.source
            if demand.moving and src in _CONTINUOUS and src not in self.at_rest_seen:
                if src in self._relost:
                    self._throttle.warning(
                        "back", "motion refused until %s is released (it was lost and is back)", src
                    )
                else:
                    self._throttle.warning(
                        "start", "motion refused until %s has been seen at rest since start", src
                    )
                return RiderDemand(stop=True, source=src, reason="rearm_wait")
        if self.fault is not None:
            if self.cleared_s is None:
                self.cleared_s = now_s
            if self.driver is None or mux.released(self.driver, now_s, self.cleared_s):
                log.info(
                    "re-armed after %s (%s)",
                    self.fault,
                    f"{self.driver} released" if self.driver else "nothing was driving",
                )
                self.fault = self.driver = self.cleared_s = None
            elif demand.moving:
                self._throttle.warning(
                    "rearm",
                    "motion refused until %s is released (after %s)",
                    self.driver,
                    self.fault,
                )
                return RiderDemand(stop=True, source=demand.source, reason="rearm_wait")
        if demand.moving:
            t = mux.input_time_s(demand.source) if demand.source in _SOURCES else None
            if t is not None and t <= self.live_after_s:
                self._throttle.warning(
                    "stall", "motion refused: %s input is older than the stall", demand.source
                )
                return RiderDemand(stop=True, source=demand.source, reason="stall_wait")
        self._last_driver = demand.source if demand.moving else None
        return demand

    @property
    def waiting(self) -> bool:
        """A fault stopped the chair and it is not re-armed yet."""
        return self.fault is not None


_SOURCES = ("tilt", "joystick", "keyboard")
_CONTINUOUS = ("tilt", "joystick")
