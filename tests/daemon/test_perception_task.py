"""The perception task is supervised like its helpers: when setting it up fails (the worker
process cannot be started), the failure is logged and counted at once and the task is started
again, while the chair is held from forward motion by stale perception. Before, the task died
and said so only at shutdown."""

from __future__ import annotations

import asyncio
import logging

from omnid.daemon.config import ConfigHolder
from omnid.daemon.run import Daemon
from omnid.devices.emulators.control_unit import ControlUnitEmulator, MotorPlant


def test_a_worker_that_cannot_start_is_reported_at_once_and_retried(tmp_path, caplog):
    emu = ControlUnitEmulator(MotorPlant())
    port = emu.open_pty()
    cfg = tmp_path / "omnid.yaml"
    cfg.write_text(
        f"control_unit:\n  port: {port}\n"
        f"teleop:\n  socket_path: {tmp_path / 'teleop.sock'}\n"
        f"camera:\n  url: sim+unix://{tmp_path / 'no-frames.sock'}\n"
        "rider:\n  tilt:\n    enabled: false\n"
    )

    def unpicklable() -> None:  # a calibration the worker process cannot be handed
        return None

    async def go() -> tuple[int, bool]:
        d = Daemon(ConfigHolder(cfg), notifier=None, calibration=unpicklable)
        task = asyncio.create_task(d.run())
        for _ in range(300):
            await asyncio.sleep(0.01)
            if sum("perception task failed" in r.getMessage() for r in caplog.records) >= 2:
                break
        alive = not task.done()
        errors = d.stats.perception_errors
        d.request_stop()
        await asyncio.wait_for(task, 15.0)
        return errors, alive

    caplog.set_level(logging.INFO)
    try:
        errors, alive = asyncio.run(go())
    finally:
        emu.close()
    failed = [r for r in caplog.records if "perception task failed" in r.getMessage()]
    assert len(failed) >= 2, "the failure was not reported while running, or not retried"
    assert errors >= 2 and alive
