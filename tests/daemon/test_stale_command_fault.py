"""Review finding: a control-unit reply with STALE_COMMAND (the unit refused to drive on our
ENABLE command and braked) is not a fault for the daemon.

docs/protocol.md ("FAULTS bits"): "The master treats WATCHDOG, OVERCURRENT_*, UNDERVOLTAGE and
STALE_COMMAND as faults that stop the chair until the rider re-arms it"; docs/daemon.md's
fail-safe table lists STALE_COMMAND among the stopping bits. omnid/daemon/core.py's
STOPPING_FAULTS leaves it out, so the core goes on commanding drive (and ramping up) while the
unit holds the wheels braked; when the unit obeys again the wheels get the ramped-up duty at once,
without a re-arm and without a ramp from standstill.
"""

from __future__ import annotations

import numpy as np
from chair_helpers import Chair, FreeFloor

from omnid.daemon.config import OmnidConfig
from omnid.daemon.core import ControlCore
from omnid.daemon.rider import JoystickSettings, RiderSettings, TiltSettings
from omnid.devices import cu_codec as codec
from omnid.devices.joystick import JoystickReading

DT = 0.02


def joystick_core() -> ControlCore:
    cfg = OmnidConfig(
        rider=RiderSettings(
            tilt=TiltSettings(enabled=False), joystick=JoystickSettings(enabled=True)
        )
    )
    core = ControlCore(cfg, world_map=FreeFloor(cfg.freespace.grid))
    core.on_joystick(JoystickReading(0.0, 0.0, -0.02))  # seen at rest once (start-up rule)
    core.step(-0.02)
    return core


def ride(core, chair, t0, t1, fwd, faults=0):
    out = []
    for t in np.arange(t0, t1, DT):
        t = float(t)
        core.on_joystick(JoystickReading(fwd, 0.0, t))
        core.on_status(chair.status(t, faults))
        core.perception_time_s = t  # fresh perception every cycle
        cmd = core.step(t)
        chair.apply(cmd, DT)
        out.append(cmd)
    return out


def test_stale_command_fault_bit_stops_the_chair_and_needs_rearm():
    core, chair = joystick_core(), Chair()
    ride(core, chair, 0.0, 0.4, 0.3)  # slow start: ramp part-way
    # the unit refuses our ENABLE commands (protocol "Freshness") and brakes: every reply
    # carries STALE_COMMAND while the rider keeps the stick where it is
    chair.refusing = True
    cmds = ride(core, chair, 0.4, 1.4, 1.0, faults=codec.FAULT_STALE_COMMAND)
    enabled = [c for c in cmds if c.enable]
    assert not enabled and core.arming.waiting, (
        f"{len(enabled)}/{len(cmds)} cycles after STALE_COMMAND replies still command "
        f"ENABLE (duty up to {max(c.left_duty for c in cmds):.2f}); arming.waiting="
        f"{core.arming.waiting}"
    )
