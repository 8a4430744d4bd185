"""Test doubles for the daemon's fault tests: a free-floor map (test side, as in
daemon_helpers) and a chair whose wheels follow duty, reporting through the real
ControlUnitStatus."""

from __future__ import annotations

import math

from omnid.core.kinematics import MM_PER_CLOCK
from omnid.core.occupancy import CellState, GridSettings, OccupancyGrid
from omnid.devices import cu_codec as codec
from omnid.devices.control_unit import ControlUnitStatus


class FreeFloor(OccupancyGrid):
    """Free floor everywhere, whatever it is told (unseen space plays no part)."""

    def __init__(self, settings: GridSettings | None = None) -> None:
        super().__init__(settings or GridSettings(resolution_mm=50.0))
        self.states[:] = CellState.FREE

    def update(self, cloud, rig_x_offset_mm=0.0, now_s=None, source_mm=None) -> None:
        pass

    def move(self, dx_mm, dy_mm, dtheta_rad) -> None:
        pass


class Chair:
    """Wheels follow the applied duty at once (251 mm/s at duty 1) unless ``blocked`` (forward
    held by an obstacle) or the unit is ``refusing`` (it brakes); statuses are real
    ``ControlUnitStatus`` values built from real reply frames."""

    def __init__(self) -> None:
        self.travel = [5.0, 12.0]
        self.seq = 0
        self.blocked = False
        self.refusing = False
        self.duty = (0.0, 0.0)

    def apply(self, cmd, dt: float) -> None:
        self.duty = (
            (0.0, 0.0) if (self.refusing or not cmd.enable) else (cmd.left_duty, cmd.right_duty)
        )
        if self.refusing:
            return
        if self.blocked and (cmd.left_duty > 0 or cmd.right_duty > 0):
            return
        for i, d in enumerate(self.duty):
            self.travel[i] += d * 251.0 * dt

    def status(self, t: float, faults: int = 0) -> ControlUnitStatus:
        self.seq = (self.seq + 1) & 0xFF
        c = [math.floor(v / MM_PER_CLOCK) for v in self.travel]
        rep = codec.ReplyFrame(
            seq=self.seq,
            left_clocks=c[0],
            right_clocks=c[1],
            left_applied_pm=round(self.duty[0] * 1000),
            right_applied_pm=round(self.duty[1] * 1000),
            state=codec.STATE_DRIVE_ENABLED if any(self.duty) else 0,
            faults=faults,
            rx_errors=0,
        )
        return ControlUnitStatus.from_reply(rep, c[0], c[1], t)
