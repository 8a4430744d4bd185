"""The real daemon process, started as systemd would, against the control-unit emulator on a pty.

Perception is off (so forward is refused, turning in place is allowed), the rider uses the
keyboard teleop socket. Checks: READY=1 on $NOTIFY_SOCKET, a rider command reaches the wheels
through the real serial link, silence stops them, SIGTERM brings the chair to zero and exits 0,
SIGHUP with a broken file keeps running.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant


def wait_for(pred, timeout_s: float, step_s: float = 0.02) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(step_s)
    return pred()


@pytest.fixture
def emulator():
    emu = ControlUnitEmulator(MotorPlant())
    path = emu.open_pty()
    yield emu, path
    emu.close()


def test_daemon_drives_through_pty_and_stops_on_sigterm(tmp_path: Path, emulator):
    emu, pty_path = emulator
    teleop = tmp_path / "teleop.sock"
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        f"control_unit:\n  port: {pty_path}\n"
        f"teleop:\n  socket_path: {teleop}\n"
        "perception:\n  enabled: false\n"
        "rider:\n  tilt:\n    enabled: false\n"
        # nothing is ever seen: turning in place creeps into the unseen (refused under the
        # shipped policy, refuse)
        "safety:\n  unknown_policy: creep\n"
    )
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify_path = str(tmp_path / "notify.sock")
    notify.bind(notify_path)
    notify.settimeout(5.0)
    env = dict(os.environ, NOTIFY_SOCKET=notify_path, WATCHDOG_USEC="1000000")
    proc = subprocess.Popen(
        [sys.executable, "-m", "omnid.cli", "run", "--config", str(cfg)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        msgs = []
        while not any(m.startswith("READY=1") for m in msgs):
            msgs.append(notify.recv(4096).decode())
        assert wait_for(lambda: emu.commands_received > 10, 3.0)
        assert emu.applied_duty == (0.0, 0.0)  # nobody asked for anything

        client = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        client.connect(str(teleop))
        client.settimeout(2.0)

        def turning() -> bool:
            client.sendall(b"left\n")
            client.recv(64)
            left, right = emu.applied_duty
            return left < -0.05 and right > 0.05

        assert wait_for(turning, 4.0, step_s=0.1), emu.applied_duty
        # forward is refused: no perception has ever arrived
        t_end = time.monotonic() + 0.6
        while time.monotonic() < t_end:
            client.sendall(b"forward\n")
            client.recv(64)
            time.sleep(0.1)
        left, right = emu.applied_duty
        assert left <= 0.0 or right <= 0.0 or abs(left - right) > 0.05 or max(left, right) < 0.05
        # the keyboard falls silent: its press expires, the chair stops
        assert wait_for(lambda: emu.applied_duty == (0.0, 0.0), 3.0)

        # SIGHUP with a broken file: refused, daemon keeps running; READY=1 follows RELOADING=1
        good = cfg.read_text()
        for broken in (
            (good + "control:\n  rate_hz: nope\n").encode(),
            (good + "# caf\xe9\n").encode("latin-1"),
        ):
            cfg.write_bytes(broken)
            proc.send_signal(signal.SIGHUP)
            msgs = []
            while not any(m.startswith("READY=1") for m in msgs):
                msgs.append(notify.recv(4096).decode())
            assert any(m.startswith("RELOADING=1") for m in msgs), msgs
            assert "reload refused" in msgs[-1], msgs
            assert proc.poll() is None

        # turning again, then SIGTERM: wheels to zero before exit
        assert wait_for(turning, 4.0, step_s=0.1)
        client.close()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=8.0)
        assert rc == 0
        assert emu.applied_duty == (0.0, 0.0)
        err = proc.stderr.read() if proc.stderr else ""
        assert "reload refused" in err and "control.rate_hz" in err
        assert "is not UTF-8" in err and "Traceback" not in err
        assert "wheels at zero" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
        notify.close()


def test_check_lists_what_it_checked_and_refuses_what_run_refuses(tmp_path: Path):
    """`run --check` runs the start-up checks of `run`: the shipped file (and an empty one,
    which means the same) needs a calibration, so both are refused by both, in one line."""
    empty = tmp_path / "empty.yaml"
    empty.write_text("# defaults\n")
    shipped = Path(__file__).resolve().parents[2] / "etc" / "omnid.yaml"
    for cfg in (shipped, empty):
        check = subprocess.run(
            [sys.executable, "-m", "omnid.cli", "run", "--check", "--config", str(cfg)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert check.returncode == 2, check.stdout
        lines = check.stdout.splitlines()
        listed = {line.split()[1].rstrip(":") for line in lines[:-1]}
        assert {"perception.calibration_path", "control_unit.port", "camera.url"} <= listed
        assert "teleop.socket_path" in listed and "tilt_sensor.port" in listed
        assert lines[-1].startswith(f"{cfg}: refused")
        if cfg == empty:
            continue  # an empty file is the shipped one (tests/daemon/test_daemon_config.py)
        run = subprocess.run(
            [sys.executable, "-m", "omnid.cli", "run", "--config", str(cfg)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert run.returncode == 2
        assert run.stderr.strip().count("\n") == 0, run.stderr
        assert "perception.calibration_path" in run.stderr and str(cfg) in run.stderr
    ok = tmp_path / "ok.yaml"
    ok.write_text(
        f"perception:\n  enabled: false\ncontrol_unit:\n  port: loop://\n"
        f"teleop:\n  socket_path: {tmp_path / 'teleop.sock'}\nrider:\n  tilt:\n"
        "    enabled: false\n"
    )
    check = subprocess.run(
        [sys.executable, "-m", "omnid.cli", "run", "--check", "--config", str(ok)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert check.returncode == 0 and check.stdout.splitlines()[-1].startswith(f"{ok}: ok")


def test_bad_config_is_one_line_error(tmp_path: Path):
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text("safety:\n  stop_distance_mm: -1\n")
    out = subprocess.run(
        [sys.executable, "-m", "omnid.cli", "run", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0
    assert "safety.stop_distance_mm" in out.stderr and str(cfg) in out.stderr
