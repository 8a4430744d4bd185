"""``omnid run``: the daemon — one asyncio process around :class:`~omnid.daemon.core.ControlCore`.

Tasks:

- control loop at ``control.rate_hz`` on the monotonic clock, drift-free: deadlines are
  ``t0 + k·period``; a late cycle runs at once and a cycle more than one period late is skipped
  (counted), never bunched. Each cycle: ``core.step(now)`` → ``ControlUnitLink.set_command``.
  The link's own task sends the latest command every ``control_unit.command_period_s``; its
  replies arrive through ``core.on_status``.
- perception cycle (``perception.enabled``): laser off → wait until the control unit reports it
  off → flush stale frames → mask pair → laser on → wait until reported on → flush → base pair →
  ``perceive`` in a worker thread (``asyncio.to_thread``) so the control loop never waits →
  ``core.on_perception(cloud, t_base)``. While frames are taken, ``core.capturing`` caps the speed
  (``perception.capture_policy: limit``); the result is placed by odometry in any case.
- rider inputs: teleop keyboard socket; tilt sensor and joystick links when available. A source
  configured but absent stays silent, which the rider mux turns into a stop.
- systemd: READY=1 once the links run, WATCHDOG=1 from the control loop (so a hung loop is
  restarted), STATUS= once per ``service.status_period_s``.
- signals: SIGTERM/SIGINT → stop at the emergency rate, send stop commands, close, exit 0;
  SIGHUP → reload the configuration (an invalid file is refused, the old one stays).
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

from omnid.daemon.config import ConfigHolder, OmnidConfig
from omnid.daemon.core import ControlCore
from omnid.daemon.service import Notifier
from omnid.devices.control_unit import ControlUnitLink, WheelCommand

log = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """Timing of the control loop (s) for STATUS= and the benchmark."""

    cycles: int = 0
    skipped: int = 0
    lateness_s: list[float] = field(default_factory=list)
    perception_cycles: int = 0
    perception_errors: int = 0
    perception_s: list[float] = field(default_factory=list)

    def record(self, late_s: float) -> None:
        self.cycles += 1
        if len(self.lateness_s) < 200_000:
            self.lateness_s.append(late_s)


class Daemon:
    """Owns the core, the device links and the tasks (see the module docstring)."""

    def __init__(self, holder: ConfigHolder, notifier: Notifier | None = None) -> None:
        self.holder = holder
        self.notifier = notifier or Notifier()
        self.core = ControlCore(holder.config)
        self.link = ControlUnitLink(holder.config.control_unit, on_status=self._on_status)
        self.stats = LoopStats()
        self._stop = asyncio.Event()
        self._closers: list[Any] = []
        self._tasks: list[asyncio.Task[None]] = []
        self._last_cycle_s = time.monotonic()

    @property
    def config(self) -> OmnidConfig:
        return self.core.config

    # ---- inputs -------------------------------------------------------------------------
    def _on_status(self, status: Any) -> None:
        self.core.on_status(status)

    async def _start_inputs(self) -> None:
        cfg = self.config
        if cfg.rider.keyboard.enabled:
            from omnid.devices.teleop import TeleopServer

            def on_key(cmd: Any) -> None:
                self.core.on_key(cmd.command, cmd.timestamp_s)

            server = TeleopServer(cfg.teleop, on_command=on_key)
            Path(cfg.teleop.socket_path).parent.mkdir(parents=True, exist_ok=True)
            await server.start()
            self._closers.append(server.stop)
        if cfg.rider.tilt.enabled and cfg.inputs.tilt_url:
            await self._start_optional_link("tilt", "TiltSensorLink", self.core.on_tilt)
        if cfg.rider.joystick.enabled and cfg.inputs.joystick_url:
            await self._start_optional_link("joystick", "JoystickLink", self.core.on_joystick)

    async def _start_optional_link(self, module: str, cls_name: str, callback: Any) -> None:
        """Start a rider-input link if its driver is installed; if not, that source stays
        silent and the rider mux keeps the chair stopped (logged)."""
        try:
            mod = __import__(f"omnid.devices.{module}", fromlist=[cls_name])
            cls = getattr(mod, cls_name)
        except (ImportError, AttributeError) as exc:
            log.error(
                "%s input configured but its driver is unavailable (%s): chair stays "
                "stopped while %s is enabled",
                module,
                exc,
                module,
            )
            return
        try:
            link = cls.from_url(
                self.config.inputs.tilt_url
                if module == "tilt"
                else self.config.inputs.joystick_url,
                on_reading=callback,
            )
            await link.start()
        except Exception as exc:
            log.error("%s input failed to start (%s): chair stays stopped", module, exc)
            return
        self._closers.append(link.stop)

    # ---- the control loop ---------------------------------------------------------------
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
                try:
                    await asyncio.wait_for(self._stop.wait(), timeout=deadline - now)
                    break
                except TimeoutError:
                    pass
                now = time.monotonic()
            late = now - deadline
            if late > period:  # more than one period behind: skip, do not bunch cycles
                missed = int(late // period)
                self.stats.skipped += missed
                k += missed
                deadline = t0 + k * period
                late = now - deadline
            self.stats.record(late)
            cmd = self.core.step(now)
            self.link.set_command(cmd)
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
        return (
            f"rider={r.demand.reason} duty={r.command.left_duty:+.2f}/"
            f"{r.command.right_duty:+.2f} limits={reasons} skipped={self.stats.skipped}"
        )

    # ---- perception ---------------------------------------------------------------------
    async def _wait_laser(self, on: bool, timeout_s: float) -> bool:
        """Wait until the control unit reports the laser ``on``; False on timeout."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            st = self.link.status
            if st is not None and bool(st.laser_on) == on and st.timestamp_s >= end - timeout_s:
                return True
            await asyncio.sleep(0.005)
        return False

    async def perception_loop(self) -> None:
        cfg = self.config
        p = cfg.perception
        try:
            from omnid.core.calibration import Calibration  # type: ignore[import-not-found,unused-ignore]
            from omnid.core.pipeline import perceive  # type: ignore[import-not-found,unused-ignore]
            from omnid.core.types import StereoCapture
            from omnid.devices.camera import open_camera

            calib = Calibration.load(p.calibration_path)
            camera = open_camera(cfg.camera)
        except Exception as exc:
            log.error("perception unavailable (%s): no forward motion until it works", exc)
            return
        self._closers.append(camera.close)
        while not self._stop.is_set():
            started = time.monotonic()
            try:
                self.core.capturing = True
                self.core.laser_on = False
                await self._wait_laser(False, p.laser_timeout_s)
                if p.flush_frames:
                    await camera.flush()
                m1, m2, _ = await camera.read_pair()
                self.core.laser_on = True
                if not await self._wait_laser(True, p.laser_timeout_s):
                    raise TimeoutError("control unit did not report the laser on")
                if p.flush_frames:
                    await camera.flush()
                b1, b2, t_base = await camera.read_pair()
                self.core.capturing = False
                capture = StereoCapture(m1, b1, m2, b2, timestamp_s=t_base)
                w0 = time.perf_counter()
                cloud = await asyncio.wait_for(
                    asyncio.to_thread(perceive, capture, calib, p.method), timeout=5.0
                )
                self.stats.perception_s.append(time.perf_counter() - w0)
                self.core.on_perception(cloud, t_base)
                self.stats.perception_cycles += 1
            except Exception as exc:
                self.stats.perception_errors += 1
                if self.stats.perception_errors == 1 or self.stats.perception_errors % 50 == 0:
                    log.warning(
                        "perception cycle failed (%d so far): %s", self.stats.perception_errors, exc
                    )
            finally:
                self.core.capturing = False
                self.core.laser_on = True
            rest = p.period_s - (time.monotonic() - started)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), timeout=max(rest, 0.01))

    # ---- life cycle ---------------------------------------------------------------------
    def reload(self) -> bool:
        ok, why = self.holder.reload()
        if not ok:
            self.notifier.status(f"reload refused: {why}")
            return False
        old = self.core
        new = ControlCore(self.holder.config, world_map=old.map)
        new.status, new.perception_time_s = old.status, old.perception_time_s
        new.odometry, new.motion.ramp.v_mm_s = old.odometry, old.motion.ramp.v_mm_s
        new.motion.ramp.omega_rad_s = old.motion.ramp.omega_rad_s
        new.mux = old.mux if new.config.rider == old.config.rider else new.mux
        self.core = new
        log.info("configuration reloaded (device settings apply at the next start)")
        return True

    def request_stop(self) -> None:
        self._stop.set()

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, self.request_stop)
        loop.add_signal_handler(signal.SIGHUP, self.reload)
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
                await t
        period = self.config.control.period_s
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            cmd = self.core.step(time.monotonic())
            self.link.set_command(cmd)
            if cmd.left_duty == 0.0 and cmd.right_duty == 0.0:
                break
            await asyncio.sleep(period)
        self.link.set_command(WheelCommand.stop())
        await asyncio.sleep(2 * self.config.control_unit.command_period_s)
        for close in reversed(self._closers):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(close(), timeout=1.0)
        await self.link.stop()
        log.info("omnid stopped; wheels at zero")


def main(config_path: str) -> int:
    """Load the configuration (errors name file and key) and run until SIGTERM."""
    holder = ConfigHolder(config_path)
    daemon_ref: list[Daemon] = []

    async def amain() -> int:
        d = Daemon(holder)
        daemon_ref.append(d)
        return await d.run()

    rc = asyncio.run(amain())
    if daemon_ref and daemon_ref[0].stats.cycles:
        lat = sorted(daemon_ref[0].stats.lateness_s)
        p99 = lat[min(len(lat) - 1, math.ceil(0.99 * len(lat)) - 1)]
        log.info(
            "control loop: %d cycles, %d skipped, lateness p99 %.2f ms",
            daemon_ref[0].stats.cycles,
            daemon_ref[0].stats.skipped,
            1e3 * p99,
        )
    return rc
