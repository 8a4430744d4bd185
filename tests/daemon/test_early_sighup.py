"""A SIGHUP that arrives while the daemon is still starting (reading its file, opening the
ports) is kept and served once the daemon is up: a reload then reported READY=1 to systemd
before the daemon was running, and before the handler was in place the signal's default action
ended the process."""

from __future__ import annotations

import asyncio
import socket

from omnid.daemon.config import ConfigHolder
from omnid.daemon.run import Daemon
from omnid.daemon.service import Notifier
from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant


def test_a_reload_asked_while_starting_is_served_after_ready(tmp_path):
    emu = ControlUnitEmulator(MotorPlant())
    port = emu.open_pty()
    cfg = tmp_path / "omnid.yaml"
    base = (
        f"control_unit:\n  port: {port}\n"
        f"teleop:\n  socket_path: {tmp_path / 'teleop.sock'}\n"
        "perception:\n  enabled: false\n"
        "rider:\n  tilt:\n    enabled: false\n"
    )
    cfg.write_text(base + "safety:\n  stop_distance_mm: 300\n")
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp_path / "notify.sock"))
    notify.setblocking(False)
    messages: list[str] = []

    def drain() -> None:
        while True:
            try:
                messages.append(notify.recv(4096).decode())
            except BlockingIOError:
                return

    async def go() -> float:
        d = Daemon(
            ConfigHolder(cfg), notifier=Notifier({"NOTIFY_SOCKET": str(notify.getsockname())})
        )
        cfg.write_text(base + "safety:\n  stop_distance_mm: 450\n")  # edited, then SIGHUP ...
        d._on_sighup()  # ... while the daemon has not started yet
        task = asyncio.create_task(d.run())
        for _ in range(300):
            await asyncio.sleep(0.01)
            drain()
            if any("reloaded" in m for m in messages):
                break
        value = d.core.config.safety.stop_distance_mm
        d.request_stop()
        await asyncio.wait_for(task, 10.0)
        return value

    try:
        value = asyncio.run(go())
    finally:
        drain()
        notify.close()
        emu.close()
    up = next(i for i, m in enumerate(messages) if m.startswith("READY=1") and "running" in m)
    reloading = [i for i, m in enumerate(messages) if m.startswith("RELOADING=1")]
    assert reloading and min(reloading) > up, messages  # systemd hears "up" first ...
    assert any("reloaded" in m for m in messages[up + 1 :]), messages  # ... then the reload
    assert value == 450.0
