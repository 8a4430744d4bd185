"""The capture cycle: one state machine that decides when the laser switches and which camera
frames become a perception job — driven by ``omnid run`` and by the simulator alike.

:class:`CaptureCycle` does no I/O and reads no clock. Its driver feeds it what happened and asks
it what to do:

* inputs — :meth:`~CaptureCycle.on_laser_report` (every control-unit reply: the laser as the
  unit has *actually* switched it, and the reply's time), :meth:`~CaptureCycle.on_frame` (a
  stereo frame pair with its capture time), :meth:`~CaptureCycle.frame_failed` (the camera
  raised);
* outputs — :attr:`~CaptureCycle.laser_on` (what the next command to the control unit must ask
  for), :attr:`~CaptureCycle.capturing` (frames are being taken: the core caps the speed under
  ``perception.capture_policy: limit``), :meth:`~CaptureCycle.wants_frame` /
  :attr:`~CaptureCycle.flush_needed` (read a pair now; drop queued frames first) and
  :meth:`~CaptureCycle.poll` (time passes: the jobs and failures that are due).

``omnid.daemon.run.Daemon.perception_loop`` drives it with the monotonic clock, the control-unit
link and a camera source; ``omnid.sim.simulator.Simulator`` with its virtual clock, the emulated
control unit and rendered frames. Both therefore run the same cycle, with the same timeouts
and the same failures.

Policies (``perception.capture``):

* ``stationary`` — the thesis' cycle (4.1.4, 5.1), every ``period_s``: laser off → wait until
  the control unit *reports* it off (at most ``laser_timeout_s``, else the cycle fails) → a
  mask pair exposed after that (``flush_frames``) → laser on → wait until reported on → a base
  pair → one job (base, mask). ``capturing`` is set from the laser-off request to the base
  pair.
* ``snapshot`` — for controllers that do not switch the laser (the simulator's probes): one
  frame pair every ``period_s``, the laser left as it is, a job without a mask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.types import StereoCapture

CapturePolicy = Literal["stationary", "snapshot"]
CAPTURE_POLICIES: tuple[str, ...] = ("stationary", "snapshot")
Image = NDArray[np.uint8]


@dataclass(frozen=True)
class CaptureSettings:
    """How the cycle runs (s). Built from ``perception.*`` by :meth:`from_config`."""

    policy: CapturePolicy = "stationary"
    period_s: float = 0.5  # a new cycle starts at most this often
    laser_timeout_s: float = 0.5  # the control unit must report a switch within this
    frame_timeout_s: float = 1.0  # a wanted frame pair must arrive within this
    flush_frames: bool = True  # frames queued before a laser switch are dropped

    def __post_init__(self) -> None:
        require(self.policy in CAPTURE_POLICIES, "policy", f"one of {', '.join(CAPTURE_POLICIES)}")
        for name in ("period_s", "laser_timeout_s", "frame_timeout_s"):
            require(getattr(self, name) > 0, name, "must be positive")

    @classmethod
    def from_config(cls, perception: Any, **changes: Any) -> CaptureSettings:
        """The settings of ``perception`` (an ``OmnidConfig.perception``), with ``changes``."""
        values: dict[str, Any] = {
            "policy": "stationary",
            "period_s": float(perception.period_s),
            "laser_timeout_s": float(perception.laser_timeout_s),
            "frame_timeout_s": float(perception.frame_timeout_s),
            "flush_frames": bool(perception.flush_frames),
        }
        values.update(changes)
        return cls(**values)


@dataclass(frozen=True)
class Frame:
    """One stereo frame pair as the camera delivered it.

    ``t_s`` is its capture time on the driver's monotonic clock. ``images`` are the two gray8
    images, or None when the source renders them only on demand (the simulator, which keeps in
    ``source`` the pose and laser state it would render; truth perception needs no images).
    """

    t_s: float
    images: tuple[Image, Image] | None = None
    source: Any = None


@dataclass(frozen=True)
class CaptureJob:
    """Frames for one perception call: a base pair (laser on) and its mask pairs (laser off;
    none under ``snapshot``). ``started_s``: when the cycle began (the laser-off request)."""

    base: Frame
    masks: tuple[Frame, ...]
    started_s: float

    @property
    def t_s(self) -> float:
        """Capture time of the base pair: the cloud is placed by the odometry at this time."""
        return self.base.t_s

    def stereo_capture(self) -> StereoCapture:
        """The job as the pipeline's :class:`StereoCapture` (base + first mask images)."""
        if self.base.images is None or not self.masks or self.masks[0].images is None:
            raise ValueError("capture job: images are needed for a StereoCapture")
        (m1, m2), (b1, b2) = self.masks[0].images, self.base.images
        return StereoCapture(m1, b1, m2, b2, timestamp_s=self.base.t_s)


@dataclass(frozen=True)
class CaptureFailure:
    """A cycle that gave no job: ``kind`` ``laser`` (the control unit did not report the
    switch in time) or ``camera`` (no frame pair in time, or the camera raised)."""

    kind: Literal["laser", "camera"]
    message: str
    t_s: float


Phase = Literal["idle", "wait_off", "mask", "wait_on", "base", "snapshot"]


class CaptureCycle:
    """The capture state machine (see the module docstring)."""

    def __init__(self, settings: CaptureSettings | None = None, start_s: float = 0.0) -> None:
        self.settings = settings or CaptureSettings()
        self.laser_on = True
        self.capturing = False
        self.phase: Phase = "idle"
        self.cycles = 0
        self.failures = 0
        self.ignored_frames = 0  # frames delivered while none was wanted
        self._next_s = start_s  # the next cycle starts no earlier than this
        self._started_s = start_s
        self._phase_s = start_s
        self._switch_s = start_s  # when the laser was last asked to change
        self._report: tuple[bool, float] | None = None  # latest (laser_on, t_s) reported
        self._mask: Frame | None = None
        self._frame: Frame | None = None
        self._frame_error: str | None = None

    # -- inputs -------------------------------------------------------------------------
    def on_laser_report(self, laser_on: bool, t_s: float) -> None:
        """A control-unit reply at ``t_s`` said the laser is (actually) ``laser_on``."""
        last = self._report
        if last is None or t_s >= last[1]:
            self._report = (bool(laser_on), float(t_s))

    def on_frame(self, frame: Frame) -> None:
        """A frame pair arrived (it is used at the next :meth:`poll`)."""
        if self.wants_frame():
            self._frame = frame
        else:
            self.ignored_frames += 1

    def frame_failed(self, message: str) -> None:
        """The camera raised while a frame was wanted (the cycle fails at the next poll)."""
        if self.wants_frame():
            self._frame_error = message

    # -- outputs ------------------------------------------------------------------------
    def wants_frame(self) -> bool:
        """A frame pair is wanted now (and none has arrived yet)."""
        return self.phase in ("mask", "base", "snapshot") and self._frame is None

    @property
    def flush_needed(self) -> bool:
        """The wanted pair must be exposed after the laser switch: drop queued frames first."""
        return self.settings.flush_frames and self.phase in ("mask", "base")

    @property
    def frame_deadline_s(self) -> float:
        """The wanted pair must arrive before this (inf when none is wanted)."""
        if not self.wants_frame():
            return math.inf
        return self._phase_s + self.settings.frame_timeout_s

    @property
    def next_poll_s(self) -> float:
        """The latest time :meth:`poll` must run for the timeouts and cycle starts to be kept."""
        s = self.settings
        if self.phase == "idle":
            return self._next_s
        if self.phase in ("wait_off", "wait_on"):
            return self._phase_s + s.laser_timeout_s
        return self.frame_deadline_s

    def poll(self, now_s: float) -> list[CaptureJob | CaptureFailure]:
        """Advance to ``now_s``: start a due cycle, take reported switches and arrived frames,
        apply the timeouts. Returns the jobs and failures that result (usually none)."""
        out: list[CaptureJob | CaptureFailure] = []
        s = self.settings
        for _ in range(8):  # a few transitions may fall due at once; each is bounded
            before = self.phase
            self._advance(now_s, s, out)
            if self.phase == before or out:
                break
        return out

    # -- the transitions ----------------------------------------------------------------
    def _enter(self, phase: Phase, now_s: float) -> None:
        self.phase, self._phase_s = phase, now_s
        self._frame, self._frame_error = None, None

    def _reported(self, on: bool) -> bool:
        r = self._report
        return r is not None and r[0] == on and r[1] > self._switch_s

    def _fail(
        self, out: list[CaptureJob | CaptureFailure], kind: Any, msg: str, now: float
    ) -> None:
        self.failures += 1
        out.append(CaptureFailure(kind, msg, now))
        self._finish(now)

    def _finish(self, now_s: float) -> None:
        self.capturing = False
        self.laser_on = True
        self._mask = None
        self._next_s = max(self._started_s + self.settings.period_s, now_s)
        self._enter("idle", now_s)

    def _advance(
        self, now: float, s: CaptureSettings, out: list[CaptureJob | CaptureFailure]
    ) -> None:
        if self.phase == "idle":
            if now + 1e-9 < self._next_s:
                return
            self._started_s = now
            if s.policy == "snapshot":
                self._enter("snapshot", now)
                return
            self.capturing = True
            self.laser_on = False
            self._switch_s = now
            self._enter("wait_off", now)
            return
        if self.phase in ("wait_off", "wait_on"):
            on = self.phase == "wait_on"
            if self._reported(on):
                self._enter("base" if on else "mask", now)
            elif now - self._phase_s + 1e-9 >= s.laser_timeout_s:
                state = "on" if on else "off"
                self._fail(
                    out,
                    "laser",
                    f"control unit did not report the laser {state} within {s.laser_timeout_s:g} s",
                    now,
                )
            return
        # a frame is wanted: mask, base or snapshot
        if self._frame_error is not None:
            self._fail(out, "camera", self._frame_error, now)
            return
        frame = self._frame
        if frame is None:
            if now - self._phase_s + 1e-9 >= s.frame_timeout_s:
                self._fail(out, "camera", f"no frame pair within {s.frame_timeout_s:g} s", now)
            return
        if self.phase == "mask":
            self._mask = frame
            self.laser_on = True
            self._switch_s = now
            self._enter("wait_on", now)
            return
        masks = (self._mask,) if self._mask is not None else ()
        self.cycles += 1
        out.append(CaptureJob(frame, masks, self._started_s))
        self._finish(now)


def pipeline_arguments(config: Any) -> tuple[str, Any]:
    """``(method, omnid.core.pipeline.PerceptionSettings)`` for ``perceive`` as ``config`` (an
    ``OmnidConfig``, or None for the defaults) configures it: ``perception.method`` and the
    ``detection`` parameters. The daemon's worker and the simulator both use this."""
    from omnid.core.pipeline import PerceptionSettings

    if config is None:
        return "best", PerceptionSettings()
    return str(config.perception.method), PerceptionSettings(detection=config.detection)
