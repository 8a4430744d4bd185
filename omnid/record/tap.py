"""``RecordingCore``: the ``ControlCore`` contract with every input and decision recorded.

It wraps the daemon's own :class:`~omnid.daemon.core.ControlCore` (docs/interfaces.md) and is
used in its place by ``omnid run`` and by the simulator (``omnid demo`` / ``simulate``), so both
record the same topics from the same place and nothing else in either needs to know: inputs
(tilt, joystick, keys, control-unit status, perception results) are passed to the core, then
queued for the recorder with a sequence number that fixes their order for ``omnid replay``;
after each ``step`` the cycle's demand, safety decision, command and pose are queued.
Attribute reads and writes (``capturing``, ``laser_on``, ``link_ok``, ``halt``, ``mux``, ...)
go to the core. Recording never raises into the caller: a failure there is logged once and
the core's command is returned as computed.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from omnid.record.recorder import Recorder

log = logging.getLogger(__name__)

#: reasons that are faults of the chair's inputs or links (``/faults`` start/end events)
FAULT_REASONS = ("status_stale", "input_stale", "fault", "perception_stale")


class RecordingCore:
    """See the module docstring. ``rig_height_mm``: the mirrors' height above the floor (the
    ``base_link`` → ``rig`` transform)."""

    _own = frozenset(
        {
            "_core",
            "_rec",
            "_seq",
            "_faults",
            "_fault_count",
            "_failed",
            "_rig",
            "sim",
            "_sim_last_s",
            "_sim_start",
        }
    )

    def __init__(self, core: Any, recorder: Recorder, rig_height_mm: float = 1100.0) -> None:
        object.__setattr__(self, "_core", core)
        object.__setattr__(self, "_rec", recorder)
        object.__setattr__(self, "_seq", 0)
        object.__setattr__(self, "_faults", frozenset())
        object.__setattr__(self, "_fault_count", 0)
        object.__setattr__(self, "_failed", False)
        object.__setattr__(self, "_rig", (0.0, rig_height_mm))
        object.__setattr__(self, "sim", None)
        object.__setattr__(self, "_sim_last_s", -math.inf)
        object.__setattr__(self, "_sim_start", (0.0, 0.0, 0.0))

    # -- attribute pass-through ------------------------------------------------------------
    def __getattr__(self, name: str) -> Any:
        return getattr(self._core, name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self._own:
            object.__setattr__(self, name, value)
        else:
            setattr(self._core, name, value)

    @property
    def core(self) -> Any:
        """The wrapped core."""
        return self._core

    @property
    def recorder(self) -> Recorder:
        return self._rec

    def _next(self) -> int:
        seq = self._seq + 1
        object.__setattr__(self, "_seq", seq)
        return seq

    def _failure(self, exc: BaseException) -> None:
        if not self._failed:
            object.__setattr__(self, "_failed", True)
            log.error("recording failed (%r); the chair is not affected", exc)

    def _put(self, topic: str, t_s: float, payload: Any) -> None:
        """Record one message; a recording that fails costs the recording, never the input,
        the cloud or the capture it was handed with (the chair drives on)."""
        try:
            self._rec.put(topic, t_s, payload)
        except Exception as exc:
            self._failure(exc)

    # -- inputs ----------------------------------------------------------------------------
    def on_tilt(self, reading: Any) -> None:
        self._core.on_tilt(reading)
        self._put("tilt", reading.timestamp_s, (self._next(), reading))

    def on_joystick(self, reading: Any) -> None:
        self._core.on_joystick(reading)
        self._put("joystick", reading.timestamp_s, (self._next(), reading))

    def on_key(self, command: str, now_s: float) -> None:
        self._core.on_key(command, now_s)
        self._put("key", now_s, (self._next(), command))

    def on_input_lost(self, source: str, now_s: float) -> None:
        self._core.on_input_lost(source, now_s)
        self._put("input_lost", now_s, (self._next(), source))

    def on_status(self, status: Any) -> None:
        self._core.on_status(status)
        self._put("status", status.timestamp_s, (self._next(), status))

    def on_perception(self, cloud: Any, capture_time_s: float) -> None:
        self._core.on_perception(cloud, capture_time_s)
        self._put("cloud", self._rec.clock(), (self._next(), cloud, capture_time_s))

    def on_capture(self, capture: Any) -> None:
        """A stereo capture as taken (recorded at most every ``record.capture_period_s``)."""
        try:
            wanted = self._rec.wants_capture(capture.timestamp_s)
        except Exception as exc:
            self._failure(exc)
            return
        if wanted:
            self._put("capture", capture.timestamp_s, capture)

    def on_fault(self, name: str, detail: str, now_s: float | None = None) -> None:
        """An event the core does not see (a perception cycle failed, a link lost)."""
        t = self._rec.clock() if now_s is None else now_s
        self._put("fault", t, (name, "event", detail))

    # -- the cycle -------------------------------------------------------------------------
    def step(self, now_s: float) -> Any:
        core = self._core
        cmd = core.step(now_s)
        try:
            self._record_cycle(core, now_s)
        except Exception as exc:
            self._failure(exc)
        return cmd

    def _record_cycle(self, core: Any, now_s: float) -> None:
        rec = self._rec
        report = core.last_report
        if report is None:
            return
        age = None if core.perception_time_s is None else now_s - core.perception_time_s
        x, y, th = (float(v) for v in core.odometry.pose)
        rig = (float(core.config.perception.rig_x_offset_mm), self._rig[1])
        flags = (
            bool(core.capturing),
            bool(core.laser_on),
            bool(core.link_ok),
            bool(core.halt),
            bool(core.camera_ok),
        )
        sources = core.mux.source_demands(now_s)
        rec.put("cycle", now_s, (self._next(), report, sources, flags, age, (x, y, th), rig))
        faults = frozenset(r.value for r in report.reasons if r.value in FAULT_REASONS)
        if faults != self._faults:
            for name in sorted(faults - self._faults):
                rec.put("fault", now_s, (name, "start", report.demand.reason))
            for name in sorted(self._faults - faults):
                rec.put("fault", now_s, (name, "end", ""))
            object.__setattr__(self, "_faults", faults)
        if core.fault_count != self._fault_count:
            object.__setattr__(self, "_fault_count", core.fault_count)
            rec.put("fault", now_s, ("cycle_exception", "event", f"{core.fault_count} so far"))
        if rec.wants_map(now_s):
            g = core.grid
            s = g.settings
            rec.put("map", now_s, (g.states.copy(), s.x_min_mm, s.y_min_mm, s.resolution_mm))
        if self.sim is not None and now_s - self._sim_last_s >= 0.1 - 1e-9:
            object.__setattr__(self, "_sim_last_s", now_s)
            self._record_truth(now_s)
        if not rec.threaded:
            rec.pump()

    # -- the simulator's truth ---------------------------------------------------------------
    def attach_simulator(self, sim: Any) -> None:
        """Record ``sim``'s truth too (``/sim/*``: course, true pose, contacts, faults)."""
        object.__setattr__(self, "sim", sim)
        object.__setattr__(self, "_sim_start", tuple(float(v) for v in sim.chair.pose))
        w = sim.course.world
        boxes = [(b.x_min_mm, b.x_max_mm, b.y_min_mm, b.y_max_mm, b.height_mm) for b in w.boxes]
        drops = [(d.x_min_mm, d.x_max_mm, d.y_min_mm, d.y_max_mm, d.depth_mm) for d in w.dropoffs]
        self._rec.put("world", 0.0, (boxes, drops))

    def _record_truth(self, now_s: float) -> None:
        sim = self.sim
        chair = sim.chair
        contacts = len(chair.contacts(sim.course.world))
        active = [f.kind for f in getattr(sim, "faults", ()) if f.active(now_s)]
        speeds = (float(chair.left_speed_mm_s), float(chair.right_speed_mm_s))
        pose = tuple(float(v) for v in chair.pose)
        self._rec.put("sim", now_s, (pose, speeds, None, contacts, active, self._sim_start))
