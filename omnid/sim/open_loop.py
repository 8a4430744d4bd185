"""An open-loop driver: a controller that plays fixed wheel duties and ignores its inputs."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from omnid.core.types import PointCloud


@dataclass(frozen=True)
class OpenLoopCommand:
    left_duty: float
    right_duty: float
    laser_on: bool = True
    enable: bool = True


class OpenLoopDriver:
    """A controller that ignores its inputs and plays ``[(t_s, left_duty, right_duty), ...]``
    (each held until the next). It is *not* a daemon: it shows what the chair does unguarded."""

    def __init__(self, script: Sequence[tuple[float, float, float]]) -> None:
        self.script = sorted((float(t), float(a), float(b)) for t, a, b in script)

    def step(self, now_s: float) -> OpenLoopCommand:
        left = right = 0.0
        for t, a, b in self.script:
            if t <= now_s:
                left, right = a, b
        return OpenLoopCommand(left, right)

    def on_status(self, status: Any) -> None:
        pass

    def on_tilt(self, reading: Any) -> None:
        pass

    def on_key(self, command: str, now_s: float) -> None:
        pass

    def on_joystick(self, reading: Any) -> None:
        pass

    def on_perception(self, cloud: PointCloud, capture_time_s: float) -> None:
        pass
