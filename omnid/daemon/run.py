"""``omnid run``: the daemon — one asyncio process around :class:`~omnid.daemon.core.ControlCore`.

Tasks:

- control loop at ``control.rate_hz`` on the monotonic clock, drift-free: deadlines are
  ``t0 + k·period``; a late cycle runs at once and a cycle more than one period late is skipped
  (counted), never bunched. Each cycle: joystick poll → ``core.step(now)`` →
  ``ControlUnitLink.set_command(cmd, computed_s=now)``. The link's own task sends a frame every
  ``control_unit.command_period_s``, carrying the latest command only while it is at most two
  command periods old (:class:`~omnid.devices.control_unit.FreshnessGate`): a loop that dies
  or stalls puts zero on the wire by itself. Replies arrive through ``core.on_status``; the
  core stops the chair at once when the link is unhealthy (``core.link_ok``).
- supervision: each cycle runs under a guard — an exception is logged (rate-limited), a zero
  command goes out at once, the core's re-arm rule applies, and the loop goes on; after
  ``_MAX_FAILED_CYCLES`` failures in a row, or when the loop's task ends for any other reason
  than a stop request, the daemon sends zero and exits with status 70 for systemd to restart it.
  ``WATCHDOG=1`` is sent only by a healthy loop: its last cycle succeeded, on time, and the
  control-unit link's task runs.
- perception (``perception.enabled``): the capture cycle :class:`~omnid.daemon.capture.CaptureCycle`
  (the same state machine the simulator drives) is told the laser state of every control-unit
  reply and fed camera frames (a reader task); it decides the laser bit of the next command and
  which frames make a job: ``perception.capture: stationary`` the thesis' cycle (laser off →
  reported off → flushed mask pair → laser on → reported on → flushed base pair; while frames
  are taken ``core.capturing`` caps the speed, ``capture_policy: limit``), ``stream`` a job for
  every laser-on frame, the laser switched in step with the frames (a change goes on the wire
  at once: an extra control cycle) — docs/framerate.md. Each job is perceived in a separate
  **worker process** (:mod:`omnid.daemon.perception_worker`: no GIL shared with the control
  loop; the masks moved to the base's pose by the wheels' motion; exceptions, crashes and hangs
  cost one job and restart the worker) → ``core.on_perception(cloud, t_base)``, entered in a
  gap between control cycles; the cloud is placed by odometry at its capture time.
  A missing or invalid calibration file refuses the start (one line naming the file); with
  ``perception.enabled: false`` the daemon runs and refuses forward motion (no free space seen).
- rider inputs: teleop keyboard socket; GS311 tilt sensor (:class:`TiltSensorLink`, readings
  pushed into the core; neutral pose per ``rider.tilt.neutral_calibration_s``); joystick
  (:class:`JoystickLink`, polled each cycle; opened again every second while absent at start,
  after that the link reopens it itself). A source
  enabled but silent is a stop (rider mux).
- systemd: READY=1 once the links run, WATCHDOG=1 from a healthy control loop (so a hung or
  failing loop is restarted), STATUS= once per ``service.status_period_s``.
- camera health: a frame pair the perception loop waits for longer than
  ``perception.camera_silence_s``, or a camera error, clears ``core.camera_ok`` (speed capped at
  ``safety.camera_lost_speed_mm_s``) until a pair arrives; a timer runs a control cycle the
  moment the silence passes the threshold (the cap need not wait for the next 20 ms grid).
- ``--inject-faults`` (``tools/fault_figures.py`` only): SIGUSR1 kills the control loop's task,
  SIGUSR2 raises in one cycle, SIGRTMIN blocks the event loop for ``OMNID_INJECT_STALL_S``
  (2.2 s).
- start: :func:`omnid.daemon.preflight.preflight` — the same checks ``omnid run --check``
  prints (calibration loads, ports, camera URL, teleop socket); an error refuses the start in
  one line naming the key and the file.
- signals: SIGTERM/SIGINT → stop at the emergency rate, send stop commands, close, exit 0;
  SIGHUP → reload the configuration: the file is read and validated in a helper thread with a
  timeout (``service.reload_timeout_s``), never on the event loop; an invalid or slow file is
  refused and the old one stays; ``READY=1`` always follows ``RELOADING=1``. A file that
  changes what the daemon built at start (``omnid.daemon.config.RESTART_ONLY``: the loop rate,
  the device links, perception, the map, which rider inputs are open) is refused as a whole,
  naming the key: a reload applies all of the file or none of it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import signal
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from omnid.daemon.capture import CaptureCycle, CaptureFailure, CaptureSettings, Frame
from omnid.daemon.config import ConfigHolder, OmnidConfig, restart_only_refusal
from omnid.daemon.core import ControlCore
from omnid.daemon.service import Notifier
from omnid.devices.camera import MAX_BUFFER_AGE_S
from omnid.devices.control_unit import ControlUnitLink
from omnid.logs import LogThrottle

log = logging.getLogger(__name__)

#: A cloud is entered into the map only when the next control cycle is at least this far off
#: (an update takes ~1–4 ms); otherwise right after that cycle (s).
ENTER_MARGIN_S = 0.006


#: failed cycles in a row after which the daemon gives up (zero, exit 70: systemd restarts it)
_MAX_FAILED_CYCLES = 25
#: exit status when the control loop died (EX_SOFTWARE)
EXIT_LOOP_DIED = 70


class Samples:
    """The newest ``capacity`` values of a series (a ring buffer: memory stays bounded however
    long the daemon runs), with the count and maximum of all values ever added."""

    def __init__(self, capacity: int = 8192) -> None:
        self._buf = np.zeros(capacity)
        self.count = 0
        self.max = -math.inf

    def add(self, value: float) -> None:
        self._buf[self.count % len(self._buf)] = value
        self.count += 1
        self.max = max(self.max, value)

    def values(self) -> list[float]:
        """The kept values, oldest first."""
        n, cap = self.count, len(self._buf)
        if n <= cap:
            return self._buf[:n].tolist()
        i = n % cap
        return np.concatenate([self._buf[i:], self._buf[:i]]).tolist()

    def __len__(self) -> int:
        return min(self.count, len(self._buf))


@dataclass
class LoopStats:
    """Timing of the control loop and the perception cycle (s), for STATUS= and the benchmark;
    each series keeps its newest 8192 values."""

    cycles: int = 0
    skipped: int = 0
    failed_cycles: int = 0
    lateness_s: Samples = field(default_factory=Samples)
    perception_cycles: int = 0  # clouds entered into the map
    perception_errors: int = 0
    perception_s: Samples = field(default_factory=Samples)  # perceive in the worker, wall
    perception_latency_s: Samples = field(default_factory=Samples)  # base frame → in the map
    capture_s: Samples = field(default_factory=Samples)  # cycle start (stream: mask) → job
    mask_to_base_s: Samples = field(default_factory=Samples)  # mask pair → base pair
    frames_read: int = 0  # frame pairs the camera delivered
    jobs_superseded: int = 0  # jobs dropped for newer ones before the worker took them
    masks_taken: int = 0
    frames_ignored: int = 0  # stream: delivered while the laser's state was not known for sure
    perception_first_s: float | None = None  # monotonic time of the first and the last cloud
    perception_last_s: float | None = None

    def record(self, late_s: float) -> None:
        self.cycles += 1
        self.lateness_s.add(late_s)

    def note(self, series: Samples, value_s: float) -> None:
        series.add(value_s)

    def to_json(self) -> dict[str, Any]:
        """Plain data: counters as numbers, series as lists (oldest first)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.values() if isinstance(v, Samples) else v
        return out


def frame_time(t_cam_s: float, t_req_s: float, t_got_s: float, own_clock: bool = False) -> float:
    """Capture time of a frame pair on this process's monotonic clock.

    V4L2 sources stamp pairs with the drivers' monotonic buffer timestamps, or
    ``time.monotonic()`` at the grab (inside the read: :func:`omnid.devices.camera.pair_time`); the
    simulator's frame server stamps its own virtual clock, which is not ours. A stamp outside
    the read's own window (or up to a driver queue's ``MAX_BUFFER_AGE_S`` before it) is
    therefore replaced by the window's midpoint — unless the source is known to stamp on our
    clock (``own_clock``: an earlier stamp of it was inside the window), when an older stamp
    is an old frame and is kept: dated at the read, a stale view would look fresh.
    """
    if t_req_s - MAX_BUFFER_AGE_S <= t_cam_s <= t_got_s + 0.01:
        return t_cam_s
    if own_clock and math.isfinite(t_cam_s) and t_cam_s < t_req_s:
        return t_cam_s
    return 0.5 * (t_req_s + t_got_s)


async def run_supervised(
    name: str,
    make: Callable[[], Awaitable[None]],
    stopping: Callable[[], bool],
    on_failure: Callable[[str, BaseException], None],
    backoff_s: float = 0.5,
    max_backoff_s: float = 5.0,
) -> None:
    """Run the helper coroutine ``make()`` until ``stopping()``: one that raises (a bug) or
    returns while the daemon runs is reported (``on_failure(name, exc)``: logged, counted) and
    started again after ``backoff_s``, doubling up to ``max_backoff_s`` while it keeps failing
    within a second. Without this a dead camera reader or perceiver left perception stale until
    a restart (safe: no forward motion, but silent). Cancelling this cancels the helper."""
    wait_s = backoff_s
    while not stopping():
        started = time.monotonic()
        try:
            await make()
            if stopping():
                return
            exc: BaseException = RuntimeError("returned while the daemon runs")
        except Exception as e:  # the helper's bug must not end perception for good
            exc = e
        log.error("%s task failed (%r): restarting it in %.1f s", name, exc, wait_s)
        log.debug("%s task exception", name, exc_info=exc)
        on_failure(name, exc)
        wait_s = backoff_s if time.monotonic() - started > 1.0 else wait_s
        await asyncio.sleep(wait_s)
        wait_s = min(2.0 * wait_s, max_backoff_s)


def _close_when_open(fut: asyncio.Future[Any]) -> None:
    """Done callback of a camera open nobody waits for any more: close the source it gave."""
    if not fut.cancelled() and fut.exception() is None:
        task = asyncio.ensure_future(fut.result().close())
        task.add_done_callback(lambda t: t.cancelled() or t.exception())


class Daemon:
    """Owns the core, the device links and the tasks (see the module docstring)."""

    def __init__(
        self,
        holder: ConfigHolder,
        notifier: Notifier | None = None,
        calibration: Any = None,
        inject_faults: bool = False,
    ) -> None:
        self.holder = holder
        self.notifier = notifier or Notifier()
        self.core = ControlCore(holder.config)
        self.link = ControlUnitLink(holder.config.control_unit, on_status=self._on_status)
        self.stats = LoopStats()
        if calibration is None and holder.config.perception.enabled:
            from omnid.daemon.preflight import preflight

            checks = preflight(holder.config, holder.path)
            checks.raise_first_error(holder.path)
            calibration = checks.calibration
        self.calibration = calibration
        self.recording: Any = None  # omnid.record.session.DaemonRecording (record.path/view)
        rec = holder.config.record
        if rec.enabled or rec.view:
            from omnid.errors import ConfigError
            from omnid.record.session import DaemonRecording

            try:
                self.recording = DaemonRecording(holder.config, self.calibration)
                self.core = self.recording.wrap(self.core)
            except (ConfigError, OSError) as exc:  # never a reason not to drive
                log.error("recording unavailable, the chair runs without it: %s", exc)
        self.tilt: Any = None
        self.joystick: Any = None
        self.worker: Any = None
        self._stop = asyncio.Event()
        self._wake = asyncio.Event()  # set by a stop request or a rider's new command
        self._kicked = False  # a rider's new command: run a cycle now, send it at once
        self._last_kick_s = 0.0
        self._closers: list[Any] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._last_cycle_s = time.monotonic()
        self._link_was_ok: bool | None = None  # None: not yet heard (start-up is not a loss)
        self._reload_task: asyncio.Task[bool] | None = None
        # a SIGHUP before the daemon is up (READY=1) is kept and served once it is: a reload
        # then would report READY too early, and before the handler a SIGHUP killed the process
        self.reload_pending = False
        self._up = False
        self.capture_cycle = CaptureCycle(
            CaptureSettings.from_config(holder.config), start_s=time.monotonic()
        )
        self._capture_wake = asyncio.Event()  # a laser report or a frame arrived
        self._frames_wanted = asyncio.Event()  # the cycle wants frames: the reader reads
        # the capture jobs the worker takes next, oldest first (a mask completes up to
        # mask_every_frames − 1 at once; beyond that the oldest is dropped)
        self._jobs: deque[Any] = deque()
        self._job_ready = asyncio.Event()
        self._camera_reset = False  # the cycle gave up on the camera: reopen it
        self._next_grid_s = time.monotonic()  # the control loop's next grid deadline
        self._cycle_done = asyncio.Event()  # set after every grid cycle
        self._throttle = LogThrottle(log, interval_s=5.0)
        self.exit_code = 0
        self._failed_in_a_row = 0
        self._inject_faults = inject_faults
        self._injected: str | None = None  # a fault to inject at the next cycle
        self._camera_wait_s: float | None = None  # since when a frame pair is awaited
        self._camera_failed = False
        self._camera_clock_ours = False  # a camera stamp was on our monotonic clock
        self._camera_timer: asyncio.TimerHandle | None = None  # fires at the silence limit
        self._joystick_live = False

    @property
    def config(self) -> OmnidConfig:
        return self.core.config

    # ---- inputs -------------------------------------------------------------------------
    def _on_status(self, status: Any) -> None:
        self.core.on_status(status)
        self.capture_cycle.on_status(status)
        self._capture_wake.set()

    def _on_tilt(self, reading: Any) -> None:
        before = self.core.mux.tilt.active
        self.core.on_tilt(reading)
        if self.core.mux.tilt.active is not before:
            self._kick()

    def _on_tilt_lost(self) -> None:
        """The tilt link lost its port or its readings went stale: a cycle now (zero)."""
        self.core.on_input_lost("tilt", time.monotonic())
        self._kick()

    def _kick(self) -> None:
        """A rider's command changed: the control loop runs an extra cycle at once and the link
        sends its result at once (rider → wire need not wait for two 20 ms grids)."""
        self._kicked = True
        self._wake.set()

    async def _start_inputs(self) -> None:
        cfg = self.config
        if cfg.rider.keyboard.enabled:
            from omnid.devices.teleop import TeleopServer

            def on_key(cmd: Any) -> None:
                self.core.on_key(cmd.command, cmd.timestamp_s)
                self._kick()

            server = TeleopServer(cfg.teleop, on_command=on_key)
            Path(cfg.teleop.socket_path).parent.mkdir(parents=True, exist_ok=True)
            await server.start()
            self._closers.append(server.stop)
        if cfg.rider.tilt.enabled:
            from omnid.devices.tilt import TiltSensorLink

            self.tilt = TiltSensorLink(
                cfg.tilt_sensor, on_reading=self._on_tilt, on_lost=self._on_tilt_lost
            )
            await self.tilt.start()  # opens (and re-opens after an unplug) in the background
            self._closers.append(self.tilt.stop)
            if cfg.rider.tilt.neutral_calibration_s > 0:
                log.info(
                    "tilt: hold the head still for %.1f s to calibrate its neutral pose",
                    cfg.rider.tilt.neutral_calibration_s,
                )
        if cfg.rider.joystick.enabled:
            from omnid.devices.joystick import JoystickLink

            self.joystick = JoystickLink(cfg.joystick_device)
            self._tasks.append(asyncio.create_task(self._joystick_keeper(), name="joystick"))
            self._closers.append(self.joystick.stop)

    async def _joystick_keeper(self) -> None:
        """Open the joystick, retrying every second while it is absent at start (a missing
        stick is a stop in the rider mux); once open, the link reopens it by itself."""
        failures = 0
        while not self._stop.is_set() and self.joystick is not None:
            try:
                await asyncio.wait_for(self.joystick.start(), timeout=2.0)
                log.info("joystick %s open", self.config.joystick_device.url)
                return
            except Exception as exc:
                failures += 1
                if failures == 1 or failures % 60 == 0:
                    log.warning("joystick unavailable (%s): rider input stops", exc)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), timeout=1.0)

    # ---- the control loop ---------------------------------------------------------------
    def _camera_ok(self, now: float) -> bool:
        """The cameras deliver: no error since the last pair, no pair awaited for longer than
        ``perception.camera_silence_s``."""
        if not self.config.perception.enabled:
            return True
        waiting = self._camera_wait_s
        silent = waiting is not None and now - waiting > self.config.perception.camera_silence_s
        return not (self._camera_failed or silent)

    def _cycle(self, now: float, urgent: bool = False) -> None:
        if self._injected == "cycle":
            self._injected = None
            raise RuntimeError("injected fault: an exception in a control cycle")
        healthy = self.link.status is not None
        if healthy != self._link_was_ok and (healthy or self._link_was_ok is not None):
            was = self._link_was_ok
            self._link_was_ok = healthy
            if self.recording is not None:
                self.recording.on_fault("control_unit_link", "back" if healthy else "lost", now)
            if healthy:
                if was is None:
                    log.info("control unit link up")
                else:
                    self._throttle.warning("link back", "control unit link back")
            else:
                self._throttle.error(
                    "link lost",
                    "control unit link lost (%s): wheels stopped",
                    self.link.health.last_error,
                )
        self.core.link_ok = healthy  # unhealthy (port gone, replies missed): zero at once
        camera_ok = self._camera_ok(now)
        if camera_ok != self.core.camera_ok:
            self.core.camera_ok = camera_ok
            if self.recording is not None:
                self.recording.on_fault("camera", "back" if camera_ok else "lost", now)
            if camera_ok:
                self._throttle.info("camera back", "cameras deliver again")
            else:
                self._throttle.warning(
                    "camera lost",
                    "cameras deliver nothing: speed capped at %.0f mm/s",
                    self.config.safety.camera_lost_speed_mm_s,
                )
        js = self.joystick
        if js is not None:
            reading = js.latest
            if reading is not None:
                self.core.on_joystick(reading)
            elif self._joystick_live:  # the link stopped vouching for it: lost now
                self.core.on_input_lost("joystick", now)
            self._joystick_live = reading is not None
        cmd = self.core.step(now)
        self.link.set_command(cmd, urgent=urgent, computed_s=now)

    def _guarded_cycle(self, now: float, urgent: bool = False) -> bool:
        """One cycle under the supervisor's guard; False if it failed (zero went out)."""
        try:
            self._cycle(now, urgent)
        except Exception as exc:
            self.stats.failed_cycles += 1
            self._failed_in_a_row += 1
            self.link.stop_now()  # zero on the wire at once, whatever state the cycle left
            if self.recording is not None:
                with contextlib.suppress(Exception):
                    self.recording.on_fault("control_cycle", repr(exc))
            with contextlib.suppress(Exception):
                self.core.fault("cycle_exception", now)
            if self._throttle.error(
                "cycle",
                "control cycle failed (%d so far): %r; wheels stopped",
                self.stats.failed_cycles,
                exc,
            ):
                log.debug("control cycle exception", exc_info=True)
            if self._failed_in_a_row >= _MAX_FAILED_CYCLES:
                log.critical(
                    "control loop failed %d cycles in a row: exiting for a restart",
                    self._failed_in_a_row,
                )
                self.exit_code = EXIT_LOOP_DIED
                self.request_stop()
            return False
        self._failed_in_a_row = 0
        return True

    def _loop_healthy(self, now: float, cycle_ok: bool, late_s: float) -> bool:
        """What WATCHDOG=1 vouches for: this cycle succeeded, on time, and the link task runs."""
        return (
            cycle_ok and late_s <= self.config.control_unit.max_command_age_s and self.link.running
        )

    def _inject(self, what: str) -> None:
        """A fault asked for by a signal under ``--inject-faults``."""
        log.warning("fault injection: %s", what)
        self._injected = what
        self._wake.set()

    def _control_loop_done(self, task: asyncio.Task[None]) -> None:
        """The supervisor: the control loop's task ended. Unless a stop was asked for, the
        wheels get zero at once and the daemon exits for systemd to restart it."""
        if self._stop.is_set():
            return
        exc = None if task.cancelled() else task.exception()
        log.critical("control loop died (%r): wheels stopped, exiting for a restart", exc)
        with contextlib.suppress(Exception):
            self.link.stop_now()
        self.exit_code = EXIT_LOOP_DIED
        self.request_stop()

    async def control_loop(self) -> None:
        period = self.config.control.period_s
        t0 = time.monotonic()
        k = 0
        next_status = t0
        next_watchdog = t0
        wd = self.notifier.watchdog_s
        while not self._stop.is_set():
            if self._injected == "die":
                raise RuntimeError("injected fault: the control loop dies")
            if self._injected == "stall":
                self._injected = None
                time.sleep(float(os.environ.get("OMNID_INJECT_STALL_S", "2.2")))
            deadline = t0 + k * period
            now = time.monotonic()
            if now < deadline:
                if not self._kicked:
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(self._wake.wait(), timeout=deadline - now)
                self._wake.clear()
                if self._stop.is_set():
                    break
                now = time.monotonic()
                if self._kicked and now < deadline:
                    self._kicked = False
                    if now - self._last_kick_s >= 0.005:  # a flood of lines: grid only
                        self._last_kick_s = now
                        self._guarded_cycle(now, urgent=True)
                    continue  # then on to the same deadline
                now = time.monotonic()
            late = now - deadline
            if late > period:  # more than one period behind: skip, do not bunch cycles
                missed = int(late // period)
                self.stats.skipped += missed
                k += missed
                deadline = t0 + k * period
                late = now - deadline
            self.stats.record(late)
            ok = self._guarded_cycle(now)
            self._last_cycle_s = now
            self._next_grid_s = t0 + (k + 1) * period  # perception enters clouds in the gaps
            self._cycle_done.set()
            if wd is not None and now >= next_watchdog and self._loop_healthy(now, ok, late):
                self.notifier.watchdog()
                next_watchdog = now + wd / 2
            if now >= next_status:
                self.notifier.status(self.status_line())
                next_status = now + self.config.service.status_period_s
            k += 1

    def status_line(self) -> str:
        r = self.core.last_report
        if r is None:
            return "starting"
        reasons = ",".join(x.value for x in r.reasons) or "ok"
        age = self.core.perception_time_s
        perc = "none" if age is None else f"{time.monotonic() - age:.1f}s"
        return (
            f"rider={r.demand.reason} duty={r.command.left_duty:+.2f}/"
            f"{r.command.right_duty:+.2f} limits={reasons} perception_age={perc} "
            f"skipped={self.stats.skipped}"
        )

    # ---- perception ---------------------------------------------------------------------
    async def _read(self, camera: Any) -> Frame:
        t_req = time.monotonic()
        img1, img2, t_cam = await camera.read_pair()
        t_got = time.monotonic()
        t = frame_time(float(t_cam), t_req, t_got, self._camera_clock_ours)
        if t == t_cam and t_req - MAX_BUFFER_AGE_S <= t <= t_got + 0.01:
            self._camera_clock_ours = True  # the camera stamps on our clock (as long as we run)
        # captured before it was read: a negative latency (a driver stamping the exposure's
        # start) or a stamp just after the read must not date it in the future (fresher)
        return Frame(min(t - self.config.camera.frame_latency_s, t_got), (img1, img2))

    def _perception_error(self, what: str, exc: BaseException | str) -> None:
        self.stats.perception_errors += 1
        if self.recording is not None:
            self.recording.on_fault(f"perception_{what}", str(exc))
        n = self.stats.perception_errors
        if n == 1 or n % 20 == 0:
            log.warning(
                "perception cycle failed (%s; %d so far): %s — no forward motion while stale",
                what,
                n,
                exc,
            )

    def _camera_reader_failed(self, what: str, exc: BaseException | str) -> None:
        """The camera reader's task failed: counted, and the cameras count as lost (speed cap)
        until it reads a pair again — nothing reads them meanwhile."""
        self._camera_failed = True
        self._perception_error(what, exc)

    def _apply_capture(self) -> None:
        """The capture cycle's laser and ``capturing`` requests into the core (whose next cycle
        puts the laser bit on the wire)."""
        cycle = self.capture_cycle
        self.core.laser_on = cycle.laser_on
        self.core.capturing = cycle.capturing

    async def _wait_any(self, events: list[asyncio.Event], timeout_s: float) -> None:
        """Until one of ``events`` (or a stop request) is set, at most ``timeout_s``."""
        if timeout_s <= 0.0:
            return
        waits = [asyncio.ensure_future(e.wait()) for e in (*events, self._stop)]
        try:
            await asyncio.wait(waits, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()

    async def _close_worker(self) -> None:
        if self.worker is not None:
            await self.worker.close()

    async def perception_loop(self) -> None:
        """The capture cycle's driver: it polls the cycle when a reply, a frame or one of the
        cycle's own deadlines comes, puts its laser request on the wire at once (an extra
        control cycle, as for a rider's command), and hands its jobs to the perceiver. Frames
        are read by :meth:`_frame_reader`, jobs perceived by :meth:`_perceiver` (both tasks)."""
        from omnid.daemon.capture import pipeline_arguments
        from omnid.daemon.perception_worker import PerceptionWorker

        cfg = self.config
        p = cfg.perception
        method, settings = pipeline_arguments(cfg)
        if self.worker is None:
            self._closers.append(self._close_worker)  # the newest worker, at shutdown
        else:  # a restart after a failed start: that worker goes first
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.worker.close(), 5.0)
        self.worker = PerceptionWorker(
            self.calibration,
            method,
            settings,
            timeout_s=p.worker_timeout_s,
            nice=p.worker_nice,
            rig_x_offset_mm=p.rig_x_offset_mm,
        )
        await self.worker.start()
        # the cycle starts now: its first laser request is the one the core has been sending
        cycle = self.capture_cycle = CaptureCycle(
            CaptureSettings.from_config(cfg), start_s=time.monotonic()
        )
        stopping = self._stop.is_set
        helpers = [
            asyncio.create_task(
                run_supervised(
                    "camera_reader", lambda: self._frame_reader(cycle), stopping,
                    self._camera_reader_failed,
                ),
                name="frames",
            ),
            asyncio.create_task(
                run_supervised("perceiver", self._perceiver, stopping, self._perception_error),
                name="perceive",
            ),
        ]  # fmt: skip
        try:
            while not self._stop.is_set():
                self._capture_wake.clear()
                try:
                    before = cycle.laser_on
                    for out in cycle.poll(time.monotonic()):
                        if isinstance(out, CaptureFailure):
                            self._perception_error(out.kind, out.message)
                            self._camera_reset |= out.kind == "camera"
                            continue
                        self._jobs.append(out)
                        while len(self._jobs) > max(1, cycle.settings.mask_every_frames - 1):
                            self._jobs.popleft()
                            self.stats.jobs_superseded += 1
                        self._job_ready.set()
                    self._apply_capture()
                    if cycle.laser_on != before and cycle.settings.policy == "stream":
                        self._kick()  # timed to the frames: the laser bit goes out now
                    if cycle.wants_frame():
                        self._frames_wanted.set()
                except Exception as exc:  # a bug here must not end perception for good
                    self._perception_error("internal", exc)
                    log.debug("perception cycle exception", exc_info=True)
                rest = min(cycle.next_poll_s - time.monotonic(), 0.1)
                await self._wait_any([self._capture_wake], max(rest, 0.0005))
        finally:
            for t in helpers:
                t.cancel()
            for t in helpers:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await t
            self.stats.masks_taken = cycle.masks_taken
            self.stats.frames_ignored = cycle.ignored_frames

    def _arm_camera_timer(self) -> None:
        """Run a control cycle as soon as the awaited pair is ``camera_silence_s`` late: the
        speed cap reaches the wire then, not up to a control period later."""
        if self._camera_timer is not None:
            self._camera_timer.cancel()
        waited_since = self._camera_wait_s

        def silent() -> None:
            self._camera_timer = None
            if self._camera_wait_s == waited_since and self.core.camera_ok:
                self._kick()

        self._camera_timer = asyncio.get_running_loop().call_later(
            self.config.perception.camera_silence_s + 0.001, silent
        )

    async def _frame_reader(self, cycle: CaptureCycle) -> None:
        """Read frame pairs while the cycle wants them (flushing the queue first where it
        asks); a camera that raises (whatever it raises: a malformed frame is a ProtocolError)
        is closed and opened again (after 0.05 … 1 s)."""
        import concurrent.futures

        from omnid.devices.camera import open_camera
        from omnid.errors import DeviceError, DeviceTimeout

        camera: Any = None
        closed: Any = None  # the source closed last: a reopened one continues its frames
        flushed = -1
        backoff = 0.05
        # cv2 opens and configures the devices synchronously (a USB camera negotiating its
        # format, a device resetting): in a thread of its own, never on the event loop. An
        # open that outlasts the camera's timeout fails the wait, not the open: the next
        # attempt waits on the same one
        pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="omnid-camera-open")
        opening: asyncio.Future[Any] | None = None
        open_wait_s = self.config.camera.timeout_s
        try:
            while not self._stop.is_set():
                if not cycle.wants_frame():
                    self._camera_wait_s = None  # none awaited: the cameras are not silent
                    self._frames_wanted.clear()
                    await self._wait_any([self._frames_wanted], 0.1)
                    continue
                try:
                    if self._camera_wait_s is None:
                        self._camera_wait_s = time.monotonic()  # camera health: awaited since
                        self._arm_camera_timer()
                    if self._camera_reset and camera is not None:
                        closed, camera = camera, None
                        await closed.close()
                    self._camera_reset = False
                    if camera is None:
                        if opening is None:
                            opening = asyncio.get_running_loop().run_in_executor(
                                pool, open_camera, self.config.camera
                            )
                        try:
                            camera = await asyncio.wait_for(asyncio.shield(opening), open_wait_s)
                        except TimeoutError:
                            raise DeviceTimeout(
                                f"camera: not open within {open_wait_s:g} s (still trying)"
                            ) from None
                        except BaseException:
                            if opening.done():
                                opening = None  # the open failed: a fresh one next time
                            raise
                        opening = None
                        camera.reopens(closed)  # still frozen after the reopen: refused
                    if cycle.flush_needed and flushed != cycle.frame_requests:
                        await camera.flush()
                        flushed = cycle.frame_requests
                    frame = await self._read(camera)
                    self._camera_wait_s, self._camera_failed = None, False
                    backoff = 0.05
                except Exception as exc:  # a device error, a malformed frame, a bug: reopen
                    self._camera_failed = True
                    cycle.frame_failed(f"{type(exc).__name__}: {exc}")
                    if not isinstance(exc, DeviceError):
                        log.debug("camera reader exception", exc_info=True)
                    self._capture_wake.set()
                    if camera is not None:
                        closed, camera = camera, None
                        with contextlib.suppress(Exception):
                            await closed.close()
                    await self._wait_any([], backoff)
                    backoff = min(2 * backoff, 1.0)
                    continue
                self.stats.frames_read += 1
                cycle.on_frame(frame)
                self._capture_wake.set()
        finally:
            if camera is not None:
                with contextlib.suppress(Exception):
                    await camera.close()
            if opening is not None:  # an open still running: close what it gives
                opening.add_done_callback(_close_when_open)
            pool.shutdown(wait=False)

    async def _perceiver(self) -> None:
        """Perceive the newest job in the worker, then enter the cloud into the map — in a gap
        between control cycles, so that the map update never makes a cycle late."""
        from omnid.daemon.perception_worker import PerceptionFailed

        p = self.config.perception
        while not self._stop.is_set():
            if not self._jobs:
                self._job_ready.clear()
                await self._wait_any([self._job_ready], 1.0)
                continue
            job = self._jobs.popleft()
            try:
                self.stats.note(self.stats.capture_s, time.monotonic() - job.started_s)
                if job.masks:
                    self.stats.note(self.stats.mask_to_base_s, job.t_s - job.masks[0].t_s)
                if self.recording is not None:
                    try:
                        self.recording.on_capture(job.stereo_capture())  # rate-limited
                    except Exception as exc:  # the recording's bug: the cloud is still made
                        self._throttle.error(
                            "record", "recording a capture failed (%r); perception goes on", exc
                        )
                motions = job.mask_motions if p.motion_compensation else ()
                motions = tuple(motions) or (None,) * len(job.masks)
                w0 = time.monotonic()
                cloud = await self.worker.perceive_job(
                    job.t_s,
                    job.base.images,
                    [m.images for m in job.masks],
                    motions,
                )
                t_done = time.monotonic()
            except PerceptionFailed as exc:
                self._perception_error("worker", exc)
                continue
            except Exception as exc:
                self._perception_error("internal", exc)
                log.debug("perceiver exception", exc_info=True)
                continue
            # a map update takes milliseconds: not just before a control cycle is due
            if self._next_grid_s - time.monotonic() < ENTER_MARGIN_S:
                self._cycle_done.clear()
                await self._wait_any([self._cycle_done], 2 * self.config.control.period_s)
            try:
                self.core.on_perception(cloud, job.t_s)
            except Exception as exc:  # a bug in the map update: this cloud is lost, not the task
                self._perception_error("map", exc)
                log.debug("map update exception", exc_info=True)
                continue
            now = time.monotonic()
            st = self.stats
            st.note(st.perception_s, t_done - w0)
            st.note(st.perception_latency_s, now - job.t_s)
            st.perception_cycles += 1
            st.perception_last_s = now
            if st.perception_first_s is None:
                st.perception_first_s = now
            if st.perception_errors and st.perception_cycles == 1:
                log.info("perception running (%d dots)", len(cloud))

    # ---- life cycle ---------------------------------------------------------------------
    def _on_sighup(self) -> None:
        if not self._up:
            log.info("SIGHUP while starting: the configuration is reloaded once running")
            self.reload_pending = True
            return
        if self._reload_task is not None and not self._reload_task.done():
            log.warning("SIGHUP ignored: a configuration reload is still running")
            return
        self._reload_task = asyncio.create_task(self.reload(), name="reload")

    async def reload(self) -> bool:
        """Re-read the configuration off the event loop (:meth:`ConfigHolder.reload_off_loop`)
        and swap in a new core that keeps the map, odometry, ramps and rider state. READY=1
        follows RELOADING=1 whatever happens."""
        self.notifier.reloading()
        status = "reload failed"
        try:
            ok, why = await self.holder.reload_off_loop(
                self.config.service.reload_timeout_s, check=restart_only_refusal
            )
            if not ok:
                status = f"reload refused: {why}"
                return False
            self._swap_core()
            status = "reloaded"
            log.info("configuration reloaded")
            return True
        except Exception:
            log.exception("configuration reload failed; the running configuration stays")
            return False
        finally:
            self.notifier.send("READY=1\nSTATUS=" + status.replace("\n", " "))

    def _swap_core(self) -> None:
        old = self.core
        new = ControlCore(self.holder.config, world_map=old.map)
        new.status, new.perception_time_s = old.status, old.perception_time_s
        new._unit_faults_since_step = old._unit_faults_since_step  # not yet seen by a cycle
        new.odometry, new.motion.ramp.v_mm_s = old.odometry, old.motion.ramp.v_mm_s
        # the pose and clock reference go on, measured with the new motion settings (the
        # speed window); mm_per_clock and track_mm are the same (RESTART_ONLY)
        new.odometry.settings = new.config.motion
        new.motion.ramp.omega_rad_s = old.motion.ramp.omega_rad_s
        # the wheel PI goes on where it was: its integrators hold what a slope or a load asks
        # (reset, the duty jumped by up to integral_limit — downhill, the chair sped up)
        lim = new.config.motion.integral_limit
        for pi, was in ((new.motion.left, old.motion.left), (new.motion.right, old.motion.right)):
            pi.integral = min(max(was.integral, -lim), lim)
        new.motion.targets_mm_s, new.motion.duties = old.motion.targets_mm_s, old.motion.duties
        new.laser_on, new.capturing = old.laser_on, old.capturing
        new.link_ok, new.camera_ok = old.link_ok, old.camera_ok
        new.path_mm, new._poses = old.path_mm, old._poses
        new._live_inputs, new._last_step_s = old._live_inputs, old._last_step_s
        new.arming = old.arming
        new.arming.enabled = new.config.control.rearm_after_fault
        # what the chair has learned about the world and itself outlives a reload: a bump's
        # refused direction, the rig knocked out of calibration, a shutdown under way
        new.bump_direction, new.bump_count = old.bump_direction, old.bump_count
        new.bump_times = old.bump_times
        if new.config.motion == old.config.motion:
            new.stall = old.stall
        new.calibration_lost, new.misfit_clouds = old.calibration_lost, old.misfit_clouds
        new.not_understood, new.halt = old.not_understood, old.halt
        if new.config.rider == old.config.rider:
            new.mux = old.mux
        elif old.config.rider.tilt.neutral_calibration_s > 0 and not old.mux.tilt.calibrating:
            # keep the neutral pose measured at start across a reload
            new.mux.tilt.calibrating = False
            new.mux.tilt.calibrated = old.mux.tilt.calibrated
            new.mux.tilt.set_neutral(old.mux.tilt.roll_offset_deg, old.mux.tilt.pitch_offset_deg)
        if self.recording is not None:
            self.core = self.recording.wrap(new)
            # replay goes on with the recorded start configuration: the reload is marked
            self.recording.on_fault("config_reloaded", "replay compares with the start config")
        else:
            self.core = new

    def request_stop(self) -> None:
        self._stop.set()
        self._wake.set()

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.request_stop)
        loop.add_signal_handler(signal.SIGHUP, self._on_sighup)
        if self._inject_faults:
            log.warning("fault injection enabled (tools/fault_figures.py): never on a chair")
            loop.add_signal_handler(signal.SIGUSR1, self._inject, "die")
            loop.add_signal_handler(signal.SIGUSR2, self._inject, "cycle")
            loop.add_signal_handler(signal.SIGRTMIN, self._inject, "stall")
        if self.config.perception.enabled:
            # heavy imports now, before the control loop runs (an import inside a task would
            # hold the event loop for hundreds of ms)
            import omnid.core.pipeline
            import omnid.daemon.perception_worker
            import omnid.devices.camera  # noqa: F401
        import gc

        gc.collect()
        gc.freeze()  # start-up objects leave the collector's scans: shorter GC pauses in the loop
        if self.recording is not None:
            self.recording.start()  # a file that cannot be written is logged, never fatal
        await self.link.start()
        try:
            await self._start_inputs()
            control = asyncio.create_task(self.control_loop(), name="control")
            control.add_done_callback(self._control_loop_done)
            self._tasks.append(control)
            if self.config.perception.enabled:
                # supervised as its helpers are: a failure setting it up (the worker process
                # not starting) is logged at once and retried, not found at shutdown
                perception = run_supervised(
                    "perception", self.perception_loop, self._stop.is_set, self._perception_error
                )
                self._tasks.append(asyncio.create_task(perception, name="perception"))
            self.notifier.ready("running")
            self._up = True
            if self.reload_pending:
                self.reload_pending = False
                self._on_sighup()
            log.info("omnid running at %.0f Hz", self.config.control.rate_hz)
            await self._stop.wait()
            for t in self._tasks:
                if t.done() and not t.cancelled() and t.exception() is not None:
                    log.error("task %s failed: %r", t.get_name(), t.exception())
        finally:
            self.notifier.stopping("stopping the chair")
            await self._shutdown()
        return self.exit_code

    async def _shutdown(self) -> None:
        """Bring the chair to a stop (emergency rate), then close everything."""
        self._stop.set()
        self.core.halt = True
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await asyncio.wait_for(t, timeout=2.0)
        period = self.config.control.period_s
        end = time.monotonic() + 2.0
        while time.monotonic() < end and self.exit_code == 0:  # a dead loop: zero, no ramp
            now = time.monotonic()
            self.core.link_ok = self.link.status is not None
            cmd = self.core.step(now)
            self.link.set_command(cmd, computed_s=now)
            if cmd.left_duty == 0.0 and cmd.right_duty == 0.0:
                break
            await asyncio.sleep(period)
        self.link.stop_now()
        await asyncio.sleep(2 * self.config.control_unit.command_period_s)
        for close in reversed(self._closers):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(close(), timeout=3.0)
        await self.link.stop()
        self.holder.close()
        log.info("omnid stopped; wheels at zero")
        if self.recording is not None:
            self.recording.close()


def main(
    config_path: str,
    stats_out: str | None = None,
    record: str | None = None,
    view: str | None = None,
    inject_faults: bool = False,
) -> int:
    """Load the configuration and calibration (errors name file and key) and run until
    SIGTERM; ``stats_out``: write :class:`LoopStats` there as JSON at exit; ``record`` /
    ``view``: the command line's ``--record FILE`` / ``--view HOST:PORT`` (over ``record.*``)."""
    from omnid.daemon.preflight import preflight

    # from here a SIGHUP (a reload asked while the configuration, the ports and the calibration
    # are still being read) is noted, not the default action's end of the process
    early_hup: list[int] = []
    signal.signal(signal.SIGHUP, lambda signum, frame: early_hup.append(signum))
    overrides: Callable[[OmnidConfig], OmnidConfig] | None = None
    if record or view:
        import dataclasses

        from omnid.record.session import with_overrides

        def with_command_line(cfg: OmnidConfig) -> OmnidConfig:
            return dataclasses.replace(cfg, record=with_overrides(cfg.record, record, view))

        overrides = with_command_line
    holder = ConfigHolder(config_path, overrides)
    checks = preflight(holder.config, config_path)
    checks.raise_first_error(config_path)
    for warning in checks.warnings:
        log.warning("%s: %s", warning.what, warning.detail)
    daemon_ref: list[Daemon] = []

    async def amain() -> int:
        d = Daemon(holder, calibration=checks.calibration, inject_faults=inject_faults)
        d.reload_pending = bool(early_hup)

        def noted(signum: int, frame: object) -> None:
            d.reload_pending = True

        signal.signal(signal.SIGHUP, noted)  # until run() puts the loop's handler in
        daemon_ref.append(d)
        return await d.run()

    rc = asyncio.run(amain())
    if daemon_ref and daemon_ref[0].stats.cycles:
        st = daemon_ref[0].stats
        lat = sorted(st.lateness_s.values())
        p99 = lat[min(len(lat) - 1, math.ceil(0.99 * len(lat)) - 1)]
        log.info(
            "control loop: %d cycles, %d skipped, lateness p99 %.2f ms; perception: %d cycles, "
            "%d failed",
            st.cycles,
            st.skipped,
            1e3 * p99,
            st.perception_cycles,
            st.perception_errors,
        )
        if stats_out:
            import json

            Path(stats_out).write_text(json.dumps(st.to_json()))
    return rc
