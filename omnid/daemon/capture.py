"""The capture cycle: one state machine that decides when the laser switches and which camera
frames become a perception job — driven by ``omnid run`` and by the simulator alike.

:class:`CaptureCycle` does no I/O and reads no clock. Its driver feeds it what happened and asks
it what to do:

* inputs — :meth:`~CaptureCycle.on_status` (every control-unit reply: the laser as the unit has
  *actually* switched it, the wheel clocks, the reply's time; :meth:`~CaptureCycle.on_laser_report`
  is the laser part alone), :meth:`~CaptureCycle.on_frame` (a stereo frame pair with its
  capture time), :meth:`~CaptureCycle.frame_failed` (the camera raised);
* outputs — :attr:`~CaptureCycle.laser_on` (what the next command to the control unit must ask
  for; a change should go out at once), :attr:`~CaptureCycle.capturing` (frames are being taken:
  the core caps the speed under ``perception.capture_policy: limit``),
  :meth:`~CaptureCycle.wants_frame` / :attr:`~CaptureCycle.flush_needed` (read a pair now; drop
  queued frames first), :attr:`~CaptureCycle.next_poll_s` and :meth:`~CaptureCycle.poll` (time
  passes: the jobs and failures that are due).

``omnid.daemon.run.Daemon.perception_loop`` drives it with the monotonic clock, the control-unit
link and a camera source; ``omnid.sim.simulator.Simulator`` with its virtual clock, the emulated
control unit and simulated cameras. Both therefore run the same cycle, with the same timeouts
and the same failures.

Policies (``perception.capture``):

* ``stream`` (default) — depth at the camera's frame rate while driving. The laser is on but
  for every ``mask_every_frames``-th frame of the cameras' clock (a mask): it is asked off at the
  end of the last exposure that leaves it ``laser_latency_s`` (the hardware's worst case from
  request to light, configuration) to go out before the mask's exposure, and on again when the
  mask's exposure ends. A frame is *on* (a base) or *off* (a mask) only when every request that
  could still affect its exposure is older than ``laser_latency_s``; frames exposed while the
  light may be switching are not used (with a laser fast enough to switch between two
  exposures, none: at 30 frames/s and one mask in three, 20 clouds/s). Each base frame becomes a
  job with the masks before and after it (``mask_bracketing``: what the motion compensation of
  the floor misses — the parallax of edges off the floor — lies on either side in the two, and
  :func:`~omnid.core.motion_compensation.compensated_mask` takes the brighter) or the one before,
  each at most ``max_mask_age_s`` away, and the
  wheels' motion from each mask to the base (:mod:`omnid.core.motion_compensation`), so that
  the masks can be moved to the base's pose before subtraction. The control unit's replies check the
  timing: a reply that contradicts what the requests imply (a laser slower than configured, a
  relay that failed, the unit's watchdog) fails the cycle and no frame is used until replies
  agree again; a request not confirmed within ``laser_timeout_s`` likewise. Mislabelled frames
  can only cost dots, never add them: a base without light shows no dots, a mask with light
  removes dots from its base.
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
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.motion_compensation import Motion, relative_motion
from omnid.core.types import StereoCapture

CapturePolicy = Literal["stream", "stationary", "snapshot"]
CAPTURE_POLICIES: tuple[str, ...] = ("stream", "stationary", "snapshot")
Image = NDArray[np.uint8]

#: Slack on either side of an exposure for errors of the frames' timestamps, s.
FRAME_TIME_GUARD_S = 0.002
#: Wheel-clock samples kept for the motion between frames, s.
MOTION_HISTORY_S = 2.0


@dataclass(frozen=True)
class CaptureSettings:
    """How the cycle runs (s). Built from an ``OmnidConfig`` by :meth:`from_config`."""

    policy: CapturePolicy = "stream"
    period_s: float = 0.5  # stationary/snapshot: a new cycle starts at most this often
    laser_timeout_s: float = 0.5  # the control unit must report a switch within this
    frame_timeout_s: float = 1.0  # a wanted frame pair must arrive within this
    flush_frames: bool = True  # stationary: frames queued before a laser switch are dropped
    frame_period_s: float = 1.0 / 30.0  # the cameras' frame clock
    exposure_s: float = 0.008  # longest exposure of a frame
    laser_latency_s: float = 0.018  # stream: request → light switched, worst case
    laser_min_switch_s: float = 0.0  # stream: the laser may switch again only after this
    mask_every_frames: int = 3  # stream: every n-th frame of the clock is a mask
    mask_bracketing: bool = True  # stream: a base waits for the next mask (both are used)
    max_mask_age_s: float = 0.3  # stream: a mask this far from its base is not used
    mm_per_clock: float = 471.0 / 15.0  # the wheels' travel per clock (motion between frames)
    track_mm: float = 560.0

    def __post_init__(self) -> None:
        require(self.policy in CAPTURE_POLICIES, "policy", f"one of {', '.join(CAPTURE_POLICIES)}")
        for name in (
            "period_s",
            "laser_timeout_s",
            "frame_timeout_s",
            "frame_period_s",
            "exposure_s",
            "max_mask_age_s",
            "mm_per_clock",
            "track_mm",
        ):
            require(getattr(self, name) > 0, name, "must be positive")
        require(self.laser_latency_s >= 0, "laser_latency_s", "must not be negative")
        require(self.laser_min_switch_s >= 0, "laser_min_switch_s", "must not be negative")
        require(self.exposure_s < self.frame_period_s, "exposure_s", "must be below the period")
        require(self.mask_every_frames >= 2, "mask_every_frames", "must be ≥ 2")

    @classmethod
    def from_config(cls, config: Any, **changes: Any) -> CaptureSettings:
        """The settings an ``OmnidConfig`` gives (``perception``, ``camera``, ``motion``)."""
        p, cam, m = config.perception, config.camera, config.motion
        values: dict[str, Any] = {
            "policy": p.capture,
            "period_s": float(p.period_s),
            "laser_timeout_s": float(p.laser_timeout_s),
            "frame_timeout_s": float(p.frame_timeout_s),
            "flush_frames": bool(p.flush_frames),
            "frame_period_s": 1.0 / float(cam.fps),
            "exposure_s": float(cam.exposure_s),
            "laser_latency_s": float(p.laser_switch_latency_s),
            "laser_min_switch_s": float(p.laser_min_switch_interval_s),
            "mask_every_frames": int(p.mask_every_frames),
            "mask_bracketing": bool(p.mask_bracketing),
            "max_mask_age_s": float(p.mask_max_age_s),
            "mm_per_clock": float(m.mm_per_clock),
            "track_mm": float(m.track_mm),
        }
        values.update(changes)
        return cls(**values)


@dataclass(frozen=True)
class Frame:
    """One stereo frame pair as the camera delivered it.

    ``t_s`` is its capture time (the middle of its exposure) on the driver's monotonic clock.
    ``images`` are the two gray8 images, or None when the source renders them only on demand
    (the simulator, which keeps in ``source`` what it needs to render them; truth perception
    needs no images).
    """

    t_s: float
    images: tuple[Image, Image] | None = None
    source: Any = None


@dataclass(frozen=True)
class CaptureJob:
    """Frames for one perception call: a base pair (laser on) and its mask pairs (laser off;
    none under ``snapshot``), with the chair's motion from each mask to the base (robot frame
    at the mask, for :func:`omnid.core.motion_compensation.floor_motion_affine`; None: not
    known). ``started_s``: when the cycle began (the laser-off request)."""

    base: Frame
    masks: tuple[Frame, ...]
    started_s: float
    mask_motions: tuple[Motion | None, ...] = ()

    @property
    def t_s(self) -> float:
        """Capture time of the base pair: the cloud is placed by the odometry at this time."""
        return self.base.t_s

    def stereo_capture(self) -> StereoCapture:
        """The job as the pipeline's :class:`StereoCapture` (base + first mask images, as
        taken; :func:`omnid.daemon.perception_worker.job_capture` compensates the motion)."""
        if self.base.images is None or not self.masks or self.masks[0].images is None:
            raise ValueError("capture job: images are needed for a StereoCapture")
        (m1, m2), (b1, b2) = self.masks[0].images, self.base.images
        return StereoCapture(m1, b1, m2, b2, timestamp_s=self.base.t_s)


@dataclass(frozen=True)
class CaptureFailure:
    """A cycle that gave no job: ``kind`` ``laser`` (the control unit did not report the
    switch in time, or reported one the requests do not explain) or ``camera`` (no frame pair
    in time, or the camera raised)."""

    kind: Literal["laser", "camera"]
    message: str
    t_s: float


Phase = Literal["idle", "wait_off", "mask", "wait_on", "base", "snapshot", "stream"]
Output = CaptureJob | CaptureFailure


class CaptureCycle:
    """The capture state machine (see the module docstring)."""

    def __init__(self, settings: CaptureSettings | None = None, start_s: float = 0.0) -> None:
        self.settings = settings or CaptureSettings()
        s = self.settings
        self.laser_on = True
        self.capturing = False
        self.phase: Phase = "stream" if s.policy == "stream" else "idle"
        self.cycles = 0  # jobs emitted
        self.failures = 0
        self.ignored_frames = 0  # delivered while none was wanted (or not usable)
        self.masks_taken = 0
        self.frame_requests = 0  # counts the frames wanted one at a time (a flush for each)
        self._next_s = start_s  # the next cycle (or mask) starts no earlier than this
        self._started_s = start_s
        self._phase_s = start_s
        self._switch_s = start_s  # when the laser was last asked to change
        self._report: tuple[bool, float] | None = None  # latest (laser_on, t_s) reported
        self._mask: Frame | None = None
        self._frame: Frame | None = None
        self._frame_error: str | None = None
        # stream
        self._requests: deque[tuple[float, bool]] = deque([(start_s, True)], maxlen=64)
        self._frames: deque[Frame] = deque(maxlen=8)
        self._trusted = False  # a reply has confirmed the laser timing since the last doubt
        self._laser_error: str | None = None
        self._unconfirmed_s: float | None = start_s  # oldest request no reply has confirmed
        self._last_frame_t: float | None = None
        self._k_last = 0  # index of the latest frame on the cameras' clock
        self._mask_phase = 0  # mask frames: index ≡ this (mod mask_every_frames)
        self._mask_k = 0  # the planned mask frame
        self._off_at_s: float | None = None  # planned laser-off request
        self._on_at_s: float | None = None  # planned laser-on request
        self._waiting: list[tuple[Frame, Frame | None]] = []  # bases and their earlier mask
        self._samples: deque[tuple[float, int, int]] = deque()

    # -- inputs -------------------------------------------------------------------------
    def on_status(self, status: Any) -> None:
        """A control-unit reply (``ControlUnitStatus``): laser report and wheel clocks."""
        t = float(status.timestamp_s)
        self.on_laser_report(bool(status.laser_on), t)
        samples = self._samples
        if samples and t < samples[-1][0]:
            return
        samples.append((t, int(status.left_clocks), int(status.right_clocks)))
        while samples and samples[0][0] < t - MOTION_HISTORY_S:
            samples.popleft()

    def on_laser_report(self, laser_on: bool, t_s: float) -> None:
        """A control-unit reply at ``t_s`` said the laser is (actually) ``laser_on``."""
        last = self._report
        if last is None or t_s >= last[1]:
            self._report = (bool(laser_on), float(t_s))
        if self.settings.policy == "stream":
            self._check_report(bool(laser_on), float(t_s))

    def on_frame(self, frame: Frame) -> None:
        """A frame pair arrived (it is used at the next :meth:`poll`)."""
        if self.settings.policy == "stream":
            self._frames.append(frame)
        elif self.wants_frame():
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
        if self.phase == "stream":
            return True
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
        """The latest time :meth:`poll` must run for the timeouts, switches and cycle starts
        to be kept."""
        s = self.settings
        if self.phase == "stream":
            times = [self.frame_deadline_s]
            for t in (self._off_at_s, self._on_at_s):
                if t is not None:
                    times.append(t)
            if self._unconfirmed_s is not None:
                times.append(self._unconfirmed_s + s.laser_timeout_s + s.laser_latency_s)
            return min(times)
        if self.phase == "idle":
            return self._next_s
        if self.phase in ("wait_off", "wait_on"):
            return self._phase_s + s.laser_timeout_s
        return self.frame_deadline_s

    def motion_between(self, t0_s: float, t1_s: float) -> Motion | None:
        """The chair's motion from ``t0_s`` to ``t1_s`` by the wheel clocks (robot frame at
        ``t0_s``), or None when the replies do not cover ``t0_s``."""
        samples = self._samples
        if not samples or samples[0][0] > t0_s:
            return None
        s = self.settings
        return relative_motion(t0_s, t1_s, np.asarray(samples), s.mm_per_clock, s.track_mm)

    def poll(self, now_s: float) -> list[Output]:
        """Advance to ``now_s``: start a due cycle, take reported switches and arrived frames,
        apply the timeouts. Returns the jobs and failures that result (usually none)."""
        out: list[Output] = []
        s = self.settings
        if s.policy == "stream":
            self._stream(now_s, s, out)
            return out
        for _ in range(8):  # a few transitions may fall due at once; each is bounded
            before = self.phase
            self._advance(now_s, s, out)
            if self.phase == before or out:
                break
        return out

    # -- stationary and snapshot ----------------------------------------------------------
    def _enter(self, phase: Phase, now_s: float) -> None:
        self.phase, self._phase_s = phase, now_s
        self._frame, self._frame_error = None, None
        if phase in ("mask", "base", "snapshot"):
            self.frame_requests += 1

    def _reported(self, on: bool) -> bool:
        r = self._report
        return r is not None and r[0] == on and r[1] > self._switch_s

    def _fail(self, out: list[Output], kind: Any, msg: str, now: float) -> None:
        self.failures += 1
        out.append(CaptureFailure(kind, msg, now))
        if self.settings.policy != "stream":
            self._finish(now)

    def _finish(self, now_s: float) -> None:
        self.capturing = False
        self.laser_on = True
        self._mask = None
        self._next_s = max(self._started_s + self.settings.period_s, now_s)
        self._enter("idle", now_s)

    def _advance(self, now: float, s: CaptureSettings, out: list[Output]) -> None:
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
        motions = tuple(self.motion_between(m.t_s, frame.t_s) for m in masks)
        self.cycles += 1
        out.append(CaptureJob(frame, masks, self._started_s, motions))
        self._finish(now)

    # -- stream ---------------------------------------------------------------------------
    def _light_at(self, a_s: float, b_s: float) -> bool | None:
        """The laser's certain state over [a_s, b_s] given the requests and the latency, or
        None when a request could still be taking effect during it."""
        lat = self.settings.laser_latency_s
        state: bool | None = None
        for t, on in self._requests:
            if t <= a_s - lat:
                state = on
            elif t < b_s:  # a request at the very end of the exposure cannot reach it
                return None
        return state

    def _request(self, on: bool, now_s: float) -> None:
        self.laser_on = on
        self._switch_s = now_s
        self._requests.append((now_s, on))
        if self._unconfirmed_s is None:
            self._unconfirmed_s = now_s

    def _doubt(self, message: str) -> None:
        if self._laser_error is None:
            self._laser_error = message
        self._trusted = False
        self._mask = None
        self._waiting = []

    def _check_report(self, on: bool, t_s: float) -> None:
        expected = self._light_at(t_s, t_s)
        if expected is None:
            return
        if expected != on:
            self._doubt(
                f"control unit reports the laser {'on' if on else 'off'} at t={t_s:.3f} s; "
                f"asked {'on' if expected else 'off'} more than "
                f"{self.settings.laser_latency_s:g} s before (perception.laser_switch_latency_s)"
            )
            return
        self._trusted = True
        since = self._unconfirmed_s
        lat = self.settings.laser_latency_s
        if since is not None and t_s >= since + lat:
            last = self._requests[-1][0]
            self._unconfirmed_s = None if t_s >= last + lat else last

    def _exposure(self, t_s: float) -> tuple[float, float]:
        half = 0.5 * self.settings.exposure_s + FRAME_TIME_GUARD_S
        return t_s - half, t_s + half

    def _frame_t(self, k: int) -> float:
        """Predicted capture time of frame ``k`` (the cameras' clock, from the latest frame)."""
        assert self._last_frame_t is not None
        return self._last_frame_t + (k - self._k_last) * self.settings.frame_period_s

    def _plan_mask(self, now: float, s: CaptureSettings) -> None:
        """Choose the next mask frame (every ``mask_every_frames``-th frame of the clock, the
        first that can still be made dark) and when to ask for the laser off: at the end of
        the last exposure that leaves the light ``laser_latency_s`` to go out before the
        mask's (or at once, when no exposure ends in time)."""
        earliest = max(now, self._switch_s + s.laser_min_switch_s)
        n = s.mask_every_frames
        m = self._k_last + 1
        m += (self._mask_phase - m) % n
        for _ in range(4):
            latest = self._exposure(self._frame_t(m))[0] - s.laser_latency_s
            if latest >= earliest:
                ends = [self._exposure(self._frame_t(i))[1] for i in range(m - n, m)]
                fits = [b for b in ends if earliest <= b <= latest]
                self._off_at_s, self._mask_k = (max(fits) if fits else earliest), m
                return
            m += n

    def _stream(self, now: float, s: CaptureSettings, out: list[Output]) -> None:
        if self._laser_error is not None:
            self.failures += 1
            out.append(CaptureFailure("laser", self._laser_error, now))
            self._laser_error = None
        u = self._unconfirmed_s
        if u is not None and now - u + 1e-9 >= s.laser_timeout_s + s.laser_latency_s:
            self._unconfirmed_s = now
            self._doubt(
                f"control unit did not report the laser switched within {s.laser_timeout_s:g} s"
            )
            self.failures += 1
            out.append(CaptureFailure("laser", str(self._laser_error), now))
            self._laser_error = None
        frames, self._frames = sorted(self._frames, key=lambda f: f.t_s), deque(maxlen=8)
        for f in frames:
            self._take(f, s, out)
        if frames:
            self._phase_s = now
        elif now - self._phase_s + 1e-9 >= s.frame_timeout_s:
            self._phase_s = now
            self._fail(out, "camera", f"no frame pair within {s.frame_timeout_s:g} s", now)
        if self._frame_error is not None:
            msg, self._frame_error = self._frame_error, None
            self._fail(out, "camera", msg, now)
        self._flush_waiting(now, s, out, self._last_frame_t)
        self._schedule(now, s)

    def _schedule(self, now: float, s: CaptureSettings) -> None:
        if self._last_frame_t is None:
            return
        if self._off_at_s is None and self._on_at_s is None and self.laser_on:
            self._plan_mask(now, s)
        if self._off_at_s is not None and now + 1e-9 >= self._off_at_s and self.laser_on:
            self._off_at_s = None
            # A poll later than the planned frame allows (the window between the exposure
            # before it and the latest request is ~3 ms at 30 frames/s) switches off anyway:
            # the first frame the light can still leave wholly dark becomes the mask, the one
            # it spoils is not used. Planning the next mask instead took none at all from a
            # loop that is always a few ms late.
            m = self._mask_k
            while self._exposure(self._frame_t(m))[0] < now + s.laser_latency_s:
                m += 1
            self._mask_k, self._mask_phase = m, m % s.mask_every_frames
            self._request(False, now)
            end = self._exposure(self._frame_t(m))[1]
            self._on_at_s = max(end, now + s.laser_min_switch_s)
        if self._on_at_s is not None and now + 1e-9 >= self._on_at_s:
            self._on_at_s = None
            self._request(True, now)

    def _take(self, f: Frame, s: CaptureSettings, out: list[Output]) -> None:
        """Label one delivered frame and use it: a mask completes the waiting bases' jobs, a
        base waits for the next mask (or goes at once without ``mask_bracketing``)."""
        if self._last_frame_t is None:
            self._last_frame_t, self._k_last = f.t_s, 0
            self._mask_phase = 1 % s.mask_every_frames
        elif f.t_s > self._last_frame_t:
            self._k_last += max(1, round((f.t_s - self._last_frame_t) / s.frame_period_s))
            self._last_frame_t = f.t_s
        light = self._light_at(*self._exposure(f.t_s)) if self._trusted else None
        if light is None:
            self.ignored_frames += 1
            return
        if not light:
            self.masks_taken += 1
            self._flush_waiting(f.t_s, s, out, None, f)
            self._mask = f
            return
        mask = self._mask
        if mask is not None and f.t_s - mask.t_s > s.max_mask_age_s:
            mask = None
        if not s.mask_bracketing:
            if mask is None:
                self.ignored_frames += 1
            else:
                self._emit(f, (mask,), out)
            return
        self._waiting.append((f, mask))

    def _flush_waiting(
        self,
        now: float,
        s: CaptureSettings,
        out: list[Output],
        t_latest: float | None,
        next_mask: Frame | None = None,
    ) -> None:
        """Emit the bases waiting for a mask: bracketed by ``next_mask``, or — once a frame
        after the mask they waited for has come (``t_latest``) — with the earlier mask alone."""
        keep: list[tuple[Frame, Frame | None]] = []
        patience = (s.mask_every_frames + 0.5) * s.frame_period_s
        for base, prev in self._waiting:
            masks = tuple(
                m
                for m in (prev, next_mask)
                if m is not None and abs(m.t_s - base.t_s) <= s.max_mask_age_s
            )
            if next_mask is not None or (t_latest is not None and t_latest - base.t_s > patience):
                if masks:
                    self._emit(base, masks, out)
                else:
                    self.ignored_frames += 1
            else:
                keep.append((base, prev))
        self._waiting = keep

    def _emit(self, base: Frame, masks: tuple[Frame, ...], out: list[Output]) -> None:
        self.cycles += 1
        motions = tuple(self.motion_between(m.t_s, base.t_s) for m in masks)
        out.append(CaptureJob(base, masks, masks[0].t_s, motions))


def pipeline_arguments(config: Any) -> tuple[str, Any]:
    """``(method, omnid.core.pipeline.PerceptionSettings)`` for ``perceive`` as ``config`` (an
    ``OmnidConfig``, or None for the defaults) configures it: ``perception.method`` and the
    ``detection`` parameters. The daemon's worker and the simulator both use this."""
    from omnid.core.pipeline import PerceptionSettings

    if config is None:
        return "best", PerceptionSettings()
    return str(config.perception.method), PerceptionSettings(detection=config.detection)
