"""A SIGHUP reload (Daemon._swap_core) builds a fresh ControlCore on the new configuration and
keeps what the chair has learned: a bump's refused direction and the stall detector, a rig out
of calibration. (It dropped the bump: the chair drove again, at once, into what it had bumped.)"""

from __future__ import annotations

import asyncio

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
