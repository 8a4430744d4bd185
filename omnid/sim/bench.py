"""The simulated chair served in real time to a separate ``omnid run`` (the bench).

:class:`RealTimeChair` is one simulator whose chair is the motor plant of the control-unit
emulator on a pty, whose cameras render the same chair's view (laser dots only while that
emulated unit has switched the laser on) on a frame server's Unix socket, with a GS311
emulator (head at rest) on a second pty; stable ``--link`` paths survive restarts. It watches
the chair for collisions and falls. ``omnid bench`` adds the daemon (a child process), its
configuration and the calibration; ``omnid simulate --serve`` serves it alone.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)


class RealTimeChair:
    """See the module docstring. ``calibrate``: install the chair (a rendered floor capture
    through ``calibrate_from_capture``) so :meth:`save_calibration` can write it."""

    def __init__(
        self,
        course: str = "builtin",
        seed: int = 0,
        frames_path: str | Path = "/tmp/omnid-frames.sock",
        cu_link: str | Path | None = None,
        tilt_link: str | Path | None = None,
        calibrate: bool = False,
    ) -> None:
        from omnid.devices.emulators.control_unit import ControlUnitEmulator
        from omnid.sim.course import get_course
        from omnid.sim.simulator import SimSettings, Simulator

        self.course = get_course(course)
        settings = SimSettings(seed=seed, perception="pipeline" if calibrate else "truth")
        self.sim = Simulator(self.course, None, settings=settings)
        self.emu = ControlUnitEmulator(plant=self.sim.chair)
        self.frames_path = Path(frames_path)
        self.cu_link = cu_link
        self.tilt_link = tilt_link
        self.gs: Any = None
        self.server: Any = None
        self.t0 = time.monotonic()
        self.contacts: list[tuple[float, str]] = []
        self.closest_mm = math.inf
        from omnid.sim.results import world_rects

        self._boxes, self._drops = world_rects(self.course.world)
        self.cu_path = ""
        self.tilt_path = ""
        self._frames = 0

    def save_calibration(self, path: str | Path) -> None:
        self.sim.calibration.save(path)

    def _frame(self, t_s: float) -> Any:
        """The frame the free-running cameras exposed around ``t_s`` (monotonic, the frame
        server's clock): the chair's view (the plant advanced to now, a readout later), its
        laser dots dimmed by the share of the exposure the emulated relay was lit."""
        from omnid.sim.adapters import lit_share
        from omnid.sim.camera import SimFrame

        on = bool(self.emu.laser_on)  # advances the plant to now under the emulator's lock
        sim = self.sim
        half = 0.5 * sim.camera.model.exposure_s
        lit = lit_share(self.emu.laser_switches, t_s - half, t_s + half, on)
        sim.now_s = t_s - self.t0
        pose = sim.chair.pose
        self._frames += 1
        frame = SimFrame(self._frames, t_s, pose, lit, seed=self._frames)
        img1, img2 = sim.camera.render(frame, sim.laser_hits(pose))
        return t_s, img1, img2

    def start(self, tilt: bool = True) -> None:
        from omnid.sim.frame_server import FrameServer

        self.t0 = time.monotonic()
        self.cu_path = self.emu.open_pty(self.cu_link)
        if tilt:
            from omnid.devices.emulators.gs311 import Gs311Emulator

            self.gs = Gs311Emulator([(0.0, 0.0, 0.0)], noise_deg=0.2)
            self.tilt_path = self.gs.open_pty(self.tilt_link)
        self.server = FrameServer(self.frames_path, self._frame).start()

    def poll(self) -> list[str]:
        """Advance the plant to now; new contacts (described) since the last poll."""
        from omnid.sim.results import chair_clearance_mm

        _ = self.emu.clocks
        chair = self.sim.chair
        self.closest_mm = min(self.closest_mm, chair_clearance_mm(chair, self._boxes, self._drops))
        out = []
        for c in chair.contacts(self.course.world):
            text = f"{c.kind} ({c.part})"
            if all(text != old for _, old in self.contacts):
                self.contacts.append((time.monotonic() - self.t0, text))
                out.append(text)
        return out

    def status_line(self) -> str:
        chair = self.sim.chair
        x, y, th = chair.pose
        return (
            f"t={time.monotonic() - self.t0:6.1f} s chair ({x:.0f}, {y:.0f}) mm "
            f"{math.degrees(th):.1f}° speed {chair.left_speed_mm_s:.0f}/"
            f"{chair.right_speed_mm_s:.0f} mm/s laser {'on' if self.emu.laser_on else 'off'}"
        )

    def close(self) -> None:
        if self.server is not None:
            with contextlib.suppress(Exception):
                self.server.stop()
        if self.gs is not None:
            with contextlib.suppress(Exception):
                self.gs.close()
        with contextlib.suppress(Exception):
            self.emu.close()
