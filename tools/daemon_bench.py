"""The bench the fault and memory tools share: the real ``omnid run`` process, the control-unit
and GS311 emulators on ptys (in this process), a spy on the control-unit wire, optionally a
frame server showing a rendered empty floor (perception on, calibrated by ``omnid calibrate``).

Used by ``tools/fault_figures.py`` and ``tools/rss_soak.py``; not a test fixture (the tests
build what they need themselves).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant, WireSpy
from omnid.devices.emulators.gs311 import Gs311Emulator, HeadMotion
from omnid.sim.render import LiveSensor

FLOOR_MM = 1100.0
NEUTRAL = (0.0, 0.0)
LEFT = (0.0, 20.0)  # pitch > +12°: turn left (in place: allowed without perception)
FORWARD = (-20.0, 0.0)  # roll < -12°: forward (needs a fresh map of free floor)


def wait_for(pred: Callable[[], bool], timeout_s: float, step_s: float = 0.002) -> float | None:
    """Monotonic time when ``pred()`` first held, or None after ``timeout_s``."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return time.monotonic()
        time.sleep(step_s)
    return time.monotonic() if pred() else None


def calibrated_floor(directory: Path) -> tuple[Path, Any]:
    """The installer's captures (empty floor, a box, a wall; nominal rig, the simulator's
    physical laser) and ``omnid calibrate`` run on them; returns (calibration, floor capture)."""
    from omnid.core.geometry import StereoRig
    from omnid.sim.installation import calibrate_installation_cli

    return calibrate_installation_cli(StereoRig.nominal(floor_depth_mm=FLOOR_MM), directory, seed=3)


def _merge(into: dict[str, Any], extra: dict[str, Any]) -> None:
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v


class DaemonBench:
    """Emulators, spy, optional frame server and the daemon process (see the module docstring).

    ``frames_gone``: set it to True and the frame server stops answering (each request waits
    until it is cleared) — the cameras deliver nothing. ``extra``: configuration merged over the
    bench's own (nested mappings).
    """

    def __init__(self, perception: bool = False, extra: dict[str, Any] | None = None) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="omnid-bench-"))
        self.cu = ControlUnitEmulator(MotorPlant())
        self.spy = WireSpy(self.cu)
        self.cu.open_pty(self.dir / "ttyCU")
        self.gs = Gs311Emulator([(0.0, *NEUTRAL)], noise_deg=0.1)
        self.gs.open_pty(link_path=str(self.dir / "ttyTilt"))
        self.perception = perception
        self.frames_gone = False
        self.server: Any = None
        self.proc: subprocess.Popen[bytes] | None = None
        self.notify: socket.socket | None = None
        self.log_path = self.dir / "omnid.log"
        self.notifications: list[tuple[float, str]] = []
        self._drain: threading.Thread | None = None
        self._lock = threading.Lock()
        config: dict[str, Any] = {
            "control_unit": {"port": str(self.dir / "ttyCU")},
            "tilt_sensor": {"port": str(self.dir / "ttyTilt")},
            "teleop": {"socket_path": str(self.dir / "teleop.sock")},
            "rider": {"tilt": {"neutral_calibration_s": 0.0}},
        }
        if perception:
            from omnid.sim.frame_server import FrameServer

            calib, cap = calibrated_floor(self.dir)

            sensor = LiveSensor(seed=1)  # fresh read noise per frame: no frozen camera

            def provider() -> tuple[float, Any, Any]:
                while self.frames_gone:
                    time.sleep(0.005)
                on = self.cu.laser_on
                return (
                    time.monotonic(),
                    sensor(cap.base1 if on else cap.mask1),
                    sensor(cap.base2 if on else cap.mask2),
                )

            sock = self.dir / "frames.sock"
            self.server = FrameServer(str(sock), provider)
            self.server.__enter__()
            config["camera"] = {"url": f"sim+unix://{sock}"}
            config["perception"] = {"calibration_path": str(calib)}
        else:
            config["perception"] = {"enabled": False}
            # nothing is ever seen: turning in place sweeps unknown space, allowed at creep speed
            config["safety"] = {"unknown_policy": "creep"}
        _merge(config, extra or {})
        self.config = self.dir / "omnid.yaml"
        self.config.write_text(yaml.safe_dump(config))

    # -- the daemon process --------------------------------------------------------------------
    def start(self, timeout_s: float = 30.0) -> float:
        """Start ``omnid run --inject-faults`` as systemd would; returns seconds to READY=1."""
        t0 = time.monotonic()
        if self.notify is None:
            self.notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self.notify.bind(str(self.dir / "notify.sock"))
            self.notify.settimeout(timeout_s)
        ready = len(self.notifications)
        env = dict(os.environ, NOTIFY_SOCKET=str(self.dir / "notify.sock"), WATCHDOG_USEC="2000000")
        log = open(self.log_path, "ab")  # noqa: SIM115 - the child writes into it until it ends
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "omnid.cli",
                "run",
                "--config",
                str(self.config),
                "--inject-faults",
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=log,
        )
        log.close()
        while self._drain is None:
            msg = self.notify.recv(4096).decode()
            if msg.startswith("READY=1"):
                break
        end = t0 + timeout_s
        while self._drain is not None and not any(
            m.startswith("READY=1") for _, m in self.notifications[ready:]
        ):
            if time.monotonic() > end:
                raise TimeoutError("the daemon did not report READY=1")
            time.sleep(0.01)
        ready_s = time.monotonic() - t0
        if self._drain is None:  # keep reading WATCHDOG=1 and STATUS= (a full queue drops them)
            self._drain = threading.Thread(target=self._drain_notify, daemon=True)
            self._drain.start()
        return ready_s

    def _drain_notify(self) -> None:
        sock = self.notify
        while sock is not None:
            try:
                msg = sock.recv(4096).decode()
            except OSError:
                return
            with self._lock:
                self.notifications.append((time.monotonic(), msg))
                del self.notifications[:-1000]

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def stop(self) -> int | None:
        """SIGTERM, wait; returns the exit status."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=15.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)
        return self.proc.returncode

    def close(self) -> None:
        self.stop()
        if self.server is not None:
            self.frames_gone = False
            with contextlib.suppress(Exception):
                self.server.__exit__(None, None, None)
        if self.notify is not None:
            sock, self.notify = self.notify, None
            sock.close()
        self.gs.close()
        self.cu.close()

    def __enter__(self) -> DaemonBench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the rider and the wheels --------------------------------------------------------------
    def head(self, angles: tuple[float, float]) -> None:
        self.gs.motion = HeadMotion([(0.0, *angles)])

    def moving(self) -> bool:
        left, right = self.cu.applied_duty
        return abs(left) > 0.02 or abs(right) > 0.02

    def driving_frames(self, t0_s: float, t1_s: float) -> int:
        """Frames between ``t0_s`` and ``t1_s`` that asked the wheels to move."""
        return sum(
            1
            for t, f in self.spy.after(t0_s)
            if t <= t1_s and f.enabled and (f.left_duty_pm or f.right_duty_pm)
        )

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")
