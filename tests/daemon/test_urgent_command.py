"""``ControlUnitLink.set_command(cmd, urgent=True)`` sends at once instead of at the next period
(the daemon uses it for a rider's new command; rider → wire ≤ 40 ms p99 needs it)."""

from __future__ import annotations

import asyncio
import time

from omnid.devices.control_unit import ControlUnitLink, ControlUnitSettings, WheelCommand
from omnid.devices.emulators.control_unit import ControlUnitEmulator
from omnid.devices.transport import pipe_pair


def test_urgent_command_goes_out_before_the_next_period():
    async def main() -> tuple[list[float], list[float]]:
        a, b = pipe_pair()
        emu = ControlUnitEmulator()
        emu.serve_pipe(b)
        link = ControlUnitLink(
            ControlUnitSettings(port="pipe", command_period_s=0.2, unit_watchdog_s=0.5),
            transport_factory=lambda: a,
        )
        await link.start()
        while not link.health.healthy:
            await asyncio.sleep(0.005)
        delays: dict[bool, list[float]] = {True: [], False: []}
        for k in range(6):
            urgent = k % 2 == 0
            await asyncio.sleep(0.03)  # well inside the 200 ms period
            duty = 0.1 * (k + 1)
            t0 = time.monotonic()
            link.set_command(WheelCommand(duty, duty, enable=True), urgent=urgent)
            while abs(emu.applied_duty[0] - duty) > 0.002 and time.monotonic() - t0 < 1.0:
                await asyncio.sleep(0.001)
            delays[urgent].append(time.monotonic() - t0)
        await link.stop()
        emu.close()
        return delays[True], delays[False]

    urgent, normal = asyncio.run(main())
    assert max(urgent) < 0.05, urgent
    assert min(normal) > 0.05, normal  # waited for the period grid
