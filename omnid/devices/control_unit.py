"""Control-unit link (SPEC §4, docs/interfaces.md).

Only :class:`WheelCommand` is defined here so far, exactly per the contract, so that the daemon
can be built against it; the link, the status type and the codec belong to the device-link
owner and replace this file's remainder when they land.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class WheelCommand:
    """One command to the control unit: signed PWM duty per wheel in [-1, 1], laser, enable.

    Positive duty drives the wheel forward. ``enable=False`` asks the control unit to brake
    (both motors off) whatever the duties say. NaN and out-of-range duties are refused.
    """

    left_duty: float = 0.0
    right_duty: float = 0.0
    laser_on: bool = False
    enable: bool = False

    def __post_init__(self) -> None:
        for name in ("left_duty", "right_duty"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise ValueError(f"WheelCommand.{name}: expected a finite number, got {value!r}")
            if not -1.0 <= value <= 1.0:
                raise ValueError(f"WheelCommand.{name}: {value!r} is outside [-1, 1]")
