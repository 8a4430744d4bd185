"""A SIGHUP reload (Daemon._swap_core) builds a fresh ControlCore on the new configuration and
keeps what the chair has learned: a bump's refused direction and the stall detector, a rig out
of calibration. (It dropped the bump: the chair drove again, at once, into what it had bumped.)"""

from __future__ import annotations

import asyncio

import pytest
from chair_helpers import Chair, FreeFloor
from test_stale_command_fault import ride

from omnid.daemon.config import ConfigHolder
from omnid.daemon.core import ControlCore
from omnid.daemon.run import Daemon
from omnid.daemon.safety import Reason
from omnid.devices.joystick import JoystickReading

YAML = """\
perception:
  enabled: false
rider:
  tilt:
    enabled: false
  joystick:
    enabled: true
"""


def test_reload_keeps_the_bump_refusal(tmp_path):
    path = tmp_path / "omnid.yaml"
    path.write_text(YAML)
    d = Daemon(ConfigHolder(path), notifier=None)
    # the daemon's core on a free floor (no perception in this test)
    d.core = ControlCore(d.holder.config, world_map=FreeFloor(d.holder.config.freespace.grid))
    d.core.on_joystick(JoystickReading(0.0, 0.0, -0.02))
    d.core.step(-0.02)
    chair = Chair()
    ride(d.core, chair, 0.0, 3.0, 1.0)
    chair.blocked = True  # driven into something the map did not hold
    ride(d.core, chair, 3.0, 5.0, 1.0)
    assert d.core.bump_count == 1 and d.core.bump_direction is not None
    assert Reason.BUMP in d.core.last_report.reasons  # still refused: rider holds forward
    path.write_text(YAML + "service:\n  status_period_s: 2.0\n")  # an unrelated change
    old_core = d.core
    old_core.calibration_lost, old_core.misfit_clouds = True, 4  # (as a knocked rig leaves it)
    assert asyncio.run(d.reload())
    assert d.core is not old_core and d.core.stall is old_core.stall  # same motion settings
    assert d.core.calibration_lost and d.core.misfit_clouds == 4
    d.core.calibration_lost, d.core.misfit_clouds = False, 0
    cmds = ride(d.core, chair, 5.0, 5.2, 1.0)  # the rider still holds the stick forward
    driving = [c for c in cmds if c.enable and c.left_duty > 0]
    assert not driving, (
        f"after the reload {len(driving)}/{len(cmds)} cycles drive forward into the bumped "
        f"obstacle again (duty up to {max(c.left_duty for c in cmds):.2f}; bump_direction="
        f"{d.core.bump_direction})"
    )


class Slope(Chair):
    """A chair on a slope: a share of each wheel's duty-speed gained (downhill) or lost."""

    def __init__(self, gain: float) -> None:
        super().__init__()
        self.gain = gain

    def apply(self, cmd, dt: float) -> None:
        super().apply(cmd, dt)
        for i, d in enumerate(self.duty):
            self.travel[i] += self.gain * d * 251.0 * dt


@pytest.mark.parametrize("gain", [-0.25, 0.25], ids=["uphill", "downhill"])
def test_a_reload_of_an_unrelated_setting_changes_nothing_the_wheels_get(tmp_path, gain):
    """Two chairs on the same slope, the same rider; one daemon reloads (service.status_period_s
    changed) while driving. What its wheels get must not change: the wheel PI's integrators
    were reset by the new core, so downhill the duty jumped from 0.43 to 0.54 at once (the chair
    sped up) and uphill it fell from 0.71 to 0.54."""
    riders = []
    for name in ("steady", "reloaded"):
        folder = tmp_path / name
        folder.mkdir()
        path = folder / "omnid.yaml"
        path.write_text(YAML)
        d = Daemon(ConfigHolder(path), notifier=None)
        d.core = ControlCore(d.holder.config, world_map=FreeFloor(d.holder.config.freespace.grid))
        d.core.on_joystick(JoystickReading(0.0, 0.0, -0.02))
        d.core.step(-0.02)
        chair = Slope(gain)
        ride(d.core, chair, 0.0, 6.0, 0.6)
        riders.append((d, chair))
    (steady, steady_chair), (d, chair) = riders
    assert abs(steady.core.motion.left.integral) > 0.05  # the slope is being held
    d.holder.path.write_text(YAML + "service:\n  status_period_s: 2.0\n")
    assert asyncio.run(d.reload())
    a = ride(steady.core, steady_chair, 6.0, 7.0, 0.6)
    b = ride(d.core, chair, 6.0, 7.0, 0.6)
    jump = max(abs(x.left_duty - y.left_duty) for x, y in zip(a, b, strict=True))
    assert jump < 1e-9, (
        f"after the reload the wheels get up to {jump:.3f} duty more or less than without it "
        f"(first cycle {a[0].left_duty:.3f} → {b[0].left_duty:.3f})"
    )
