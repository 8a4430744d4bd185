"""``omnid run``: the daemon — one asyncio process around :class:`~omnid.daemon.core.ControlCore`.

Tasks:

- control loop at ``control.rate_hz`` on the monotonic clock, drift-free: deadlines are
  ``t0 + k·period``; a late cycle runs at once and a cycle more than one period late is skipped
  (counted), never bunched. Each cycle: joystick poll → ``core.step(now)`` →
  ``ControlUnitLink.set_command``. The link's own task sends the latest command every
  ``control_unit.command_period_s``; its replies arrive through ``core.on_status``. The core
  stops the chair when no status came for ``control.status_timeout_s``, and at once when the
  port is gone (``core.link_ok``).
- perception (``perception.enabled``): the capture cycle :class:`~omnid.daemon.capture.CaptureCycle`
  (the same state machine the simulator drives) is told the laser state of every control-unit
  reply and fed camera frames; it decides the laser bit of the next command and which frames
  make a job (the thesis' cycle: laser off → reported off → flushed mask pair → laser on →
  reported on → flushed base pair). Each job is perceived in a separate **worker process**
  (:mod:`omnid.daemon.perception_worker`: no GIL shared with the control loop; exceptions,
  crashes and hangs cost one cycle and restart the worker) → ``core.on_perception(cloud,
  t_base)``. While frames are taken ``core.capturing`` caps the speed
  (``perception.capture_policy: limit``); the cloud is placed by odometry anyway.
  A missing or invalid calibration file refuses the start (one line naming the file); with
  ``perception.enabled: false`` the daemon runs and refuses forward motion (no free space seen).
- rider inputs: teleop keyboard socket; GS311 tilt sensor (:class:`TiltSensorLink`, readings
  pushed into the core; neutral pose per ``rider.tilt.neutral_calibration_s``); joystick
  (:class:`JoystickLink`, polled each cycle; opened again every second while absent at start,
  after that the link reopens it itself). A source
  enabled but silent is a stop (rider mux).
- systemd: READY=1 once the links run, WATCHDOG=1 from the control loop (so a hung loop is
  restarted), STATUS= once per ``service.status_period_s``.
- start: :func:`omnid.daemon.preflight.preflight` — the same checks ``omnid run --check``
  prints (calibration loads, ports, camera URL, teleop socket); an error refuses the start in
  one line naming the key and the file.
- signals: SIGTERM/SIGINT → stop at the emergency rate, send stop commands, close, exit 0;
  SIGHUP → reload the configuration: the file is read and validated in a helper thread with a
  timeout (``service.reload_timeout_s``), never on the event loop; an invalid or slow file is
  refused and the old one stays; ``READY=1`` always follows ``RELOADING=1``; device and
  perception settings apply at the next start.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omnid.daemon.capture import CaptureCycle, CaptureFailure, CaptureSettings, Frame
from omnid.daemon.config import ConfigHolder, OmnidConfig
from omnid.daemon.core import ControlCore
from omnid.daemon.service import Notifier
from omnid.devices.control_unit import ControlUnitLink, WheelCommand

log = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """Timing of the control loop and the perception cycle (s), for STATUS= and the benchmark."""

    cycles: int = 0
    skipped: int = 0
    lateness_s: list[float] = field(default_factory=list)
    perception_cycles: int = 0
    perception_errors: int = 0
    perception_s: list[float] = field(default_factory=list)  # perceive in the worker, wall
    perception_latency_s: list[float] = field(default_factory=list)  # base frame → in the map
    capture_s: list[float] = field(default_factory=list)  # laser off → base pair in hand
    mask_to_base_s: list[float] = field(default_factory=list)  # mask pair → base pair

    def record(self, late_s: float) -> None:
        self.cycles += 1
        if len(self.lateness_s) < 200_000:
            self.lateness_s.append(late_s)

    def note(self, series: list[float], value_s: float) -> None:
        if len(series) < 100_000:
            series.append(value_s)


def frame_time(t_cam_s: float, t_req_s: float, t_got_s: float) -> float:
    """Capture time of a frame pair on this process's monotonic clock.

    V4L2 sources stamp pairs with ``time.monotonic()`` at the grab (inside the read); the
    simulator's frame server stamps its own virtual clock, which is not ours. A stamp outside
    the read's own window is therefore replaced by the window's midpoint.
    """
    if t_req_s - 0.2 <= t_cam_s <= t_got_s + 0.01:
        return t_cam_s
    return 0.5 * (t_req_s + t_got_s)


class Daemon:
    """Owns the core, the device links and the tasks (see the module docstring)."""

    def __init__(
        self, holder: ConfigHolder, notifier: Notifier | None = None, calibration: Any = None
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
        self.capture_cycle = CaptureCycle(
            CaptureSettings.from_config(holder.config.perception), start_s=time.monotonic()
        )
        self._capture_wake = asyncio.Event()  # a laser report arrived

    @property
    def config(self) -> OmnidConfig:
        return self.core.config

    # ---- inputs -------------------------------------------------------------------------
    def _on_status(self, status: Any) -> None:
        self.core.on_status(status)
        self.capture_cycle.on_laser_report(bool(status.laser_on), float(status.timestamp_s))
        self._capture_wake.set()

    def _on_tilt(self, reading: Any) -> None:
        before = self.core.mux.tilt.active
        self.core.on_tilt(reading)
        if self.core.mux.tilt.active is not before:
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

            self.tilt = TiltSensorLink(cfg.tilt_sensor, on_reading=self._on_tilt)
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
    def _cycle(self, now: float, urgent: bool = False) -> None:
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
                    log.warning("control unit link back")
            else:
                log.error(
                    "control unit link lost (%s): wheels stop once no status for %.2f s",
                    self.link.health.last_error,
                    self.config.control.status_timeout_s,
                )
        # a port that is gone stops at once; missed replies stop after status_timeout_s (the
        # unit's own watchdog time), so one noisy exchange on the bus does not brake the chair
        self.core.link_ok = self.link.health.connected
        js = self.joystick
        if js is not None:
            reading = js.latest
            if reading is not None:
                self.core.on_joystick(reading)
        cmd = self.core.step(now)
        self.link.set_command(cmd, urgent=urgent)

    async def control_loop(self) -> None:
        period = self.config.control.period_s
        t0 = time.monotonic()
        k = 0
        next_status = t0
        next_watchdog = t0
        wd = self.notifier.watchdog_s
        while not self._stop.is_set():
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
                        self._cycle(now, urgent=True)
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
            self._cycle(now)
            self._last_cycle_s = now
            if wd is not None and now >= next_watchdog:
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
        return Frame(frame_time(float(t_cam), t_req, time.monotonic()), (img1, img2))

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

    def _apply_capture(self) -> None:
        """The capture cycle's laser and ``capturing`` requests into the core (whose next cycle
        puts the laser bit on the wire)."""
        cycle = self.capture_cycle
        self.core.laser_on = cycle.laser_on
        self.core.capturing = cycle.capturing

    async def _capture_wait(self, until_s: float) -> None:
        """Sleep until ``until_s``, a laser report or a stop request, whichever comes first."""
        rest = until_s - time.monotonic()
        if rest <= 0.0:
            return
        self._capture_wake.clear()
        waits = [asyncio.ensure_future(e.wait()) for e in (self._capture_wake, self._stop)]
        try:
            await asyncio.wait(waits, timeout=min(rest, 1.0), return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()

    async def perception_loop(self) -> None:
        from omnid.daemon.capture import pipeline_arguments
        from omnid.daemon.perception_worker import PerceptionFailed, PerceptionWorker
        from omnid.devices.camera import open_camera
        from omnid.errors import DeviceError

        cfg = self.config
        p = cfg.perception
        method, settings = pipeline_arguments(cfg)
        self.worker = PerceptionWorker(
            self.calibration,
            method,
            settings,
            timeout_s=p.worker_timeout_s,
            nice=p.worker_nice,
        )
        self._closers.append(self.worker.close)
        await self.worker.start()
        cycle = self.capture_cycle
        camera: Any = None

        async def close_camera() -> None:
            nonlocal camera
            if camera is not None:
                with contextlib.suppress(Exception):
                    await camera.close()
                camera = None

        while not self._stop.is_set():
            try:
                for out in cycle.poll(time.monotonic()):
                    if isinstance(out, CaptureFailure):
                        self._perception_error(out.kind, out.message)
                        if out.kind == "camera":
                            await close_camera()
                        continue
                    self.stats.note(self.stats.capture_s, time.monotonic() - out.started_s)
                    if out.masks:
                        self.stats.note(self.stats.mask_to_base_s, out.t_s - out.masks[0].t_s)
                    cap = out.stereo_capture()
                    if self.recording is not None:
                        self.recording.on_capture(cap)  # rate-limited, encoded off the loop
                    w0 = time.monotonic()
                    cloud = await self.worker.perceive(cap)
                    t_done = time.monotonic()
                    self.core.on_perception(cloud, out.t_s)
                    self.stats.note(self.stats.perception_s, t_done - w0)
                    self.stats.note(self.stats.perception_latency_s, time.monotonic() - out.t_s)
                    self.stats.perception_cycles += 1
                    if self.stats.perception_errors and self.stats.perception_cycles == 1:
                        log.info("perception running (%d dots)", len(cloud))
                self._apply_capture()
                if not cycle.wants_frame():
                    await self._capture_wait(cycle.next_poll_s)
                    continue
                try:
                    if camera is None:
                        camera = open_camera(cfg.camera)
                    if cycle.flush_needed:
                        await camera.flush()
                    rest = max(cycle.frame_deadline_s - time.monotonic(), 0.001)
                    cycle.on_frame(await asyncio.wait_for(self._read(camera), rest))
                except TimeoutError as exc:
                    if isinstance(exc, DeviceError):
                        cycle.frame_failed(str(exc))
                    # else: past the cycle's frame deadline; its next poll says so
                except (DeviceError, OSError) as exc:
                    cycle.frame_failed(f"{type(exc).__name__}: {exc}")
            except PerceptionFailed as exc:
                self._perception_error("worker", exc)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # a bug here must not end perception for good
                self._perception_error("internal", exc)
                log.debug("perception cycle exception", exc_info=True)
                await self._capture_wait(time.monotonic() + 0.01)
        await close_camera()

    # ---- life cycle ---------------------------------------------------------------------
    def _on_sighup(self) -> None:
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
            ok, why = await self.holder.reload_off_loop(self.config.service.reload_timeout_s)
            if not ok:
                status = f"reload refused: {why}"
                return False
            self._swap_core()
            status = "reloaded"
            log.info(
                "configuration reloaded (device and perception settings apply at the next start)"
            )
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
        new.odometry, new.motion.ramp.v_mm_s = old.odometry, old.motion.ramp.v_mm_s
        new.motion.ramp.omega_rad_s = old.motion.ramp.omega_rad_s
        new.laser_on, new.capturing, new.rearm_after = old.laser_on, old.capturing, old.rearm_after
        new.link_ok = old.link_ok
        if new.config.rider == old.config.rider:
            new.mux = old.mux
        elif old.config.rider.tilt.neutral_calibration_s > 0 and not old.mux.tilt.calibrating:
            # keep the neutral pose measured at start across a reload
            new.mux.tilt.calibrating = False
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
            self._tasks.append(asyncio.create_task(self.control_loop(), name="control"))
            if self.config.perception.enabled:
                self._tasks.append(asyncio.create_task(self.perception_loop(), name="perception"))
            self.notifier.ready("running")
            log.info("omnid running at %.0f Hz", self.config.control.rate_hz)
            await self._stop.wait()
            for t in self._tasks:
                if t.done() and not t.cancelled() and t.exception() is not None:
                    log.error("task %s failed: %r", t.get_name(), t.exception())
        finally:
            self.notifier.stopping("stopping the chair")
            await self._shutdown()
        return 0

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
        while time.monotonic() < end:
            self.core.link_ok = self.link.status is not None
            cmd = self.core.step(time.monotonic())
            self.link.set_command(cmd)
            if cmd.left_duty == 0.0 and cmd.right_duty == 0.0:
                break
            await asyncio.sleep(period)
        self.link.set_command(WheelCommand.stop())
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
) -> int:
    """Load the configuration and calibration (errors name file and key) and run until
    SIGTERM; ``stats_out``: write :class:`LoopStats` there as JSON at exit; ``record`` /
    ``view``: the command line's ``--record FILE`` / ``--view HOST:PORT`` (over ``record.*``)."""
    from omnid.daemon.preflight import preflight

    holder = ConfigHolder(config_path)
    if record or view:
        import dataclasses

        from omnid.record.session import with_overrides

        cfg = holder.config
        holder.config = dataclasses.replace(cfg, record=with_overrides(cfg.record, record, view))
    checks = preflight(holder.config, config_path)
    checks.raise_first_error(config_path)
    for warning in checks.warnings:
        log.warning("%s: %s", warning.what, warning.detail)
    daemon_ref: list[Daemon] = []

    async def amain() -> int:
        d = Daemon(holder, calibration=checks.calibration)
        daemon_ref.append(d)
        return await d.run()

    rc = asyncio.run(amain())
    if daemon_ref and daemon_ref[0].stats.cycles:
        st = daemon_ref[0].stats
        lat = sorted(st.lateness_s)
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
            import dataclasses
            import json

            Path(stats_out).write_text(json.dumps(dataclasses.asdict(st)))
    return rc
