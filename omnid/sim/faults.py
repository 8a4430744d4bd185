"""Faults injected into a simulated run: what breaks, when, and how each part is told.

A :class:`Fault` is a kind and a virtual time window. :class:`FaultInjector` turns the faults
active at a time into the device adapters' own fault switches (the control-unit emulator's
``stall``/``corrupt_replies``, the tilt adapter's ``unplugged``); the camera and the vision
pipeline ask :meth:`FaultInjector.active` themselves.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from omnid.config import require

log = logging.getLogger(__name__)

FaultKind = Literal[
    "tilt_unplugged", "camera_stopped", "cu_silent", "cu_corrupt", "perception_exception"
]
FAULT_KINDS: tuple[str, ...] = (
    "tilt_unplugged",
    "camera_stopped",
    "cu_silent",
    "cu_corrupt",
    "perception_exception",
)


@dataclass(frozen=True)
class Fault:
    """A fault injected from ``start_s`` to ``end_s`` (virtual s):

    * ``tilt_unplugged`` — the GS311 adapter is pulled: no replies reach the tilt decoding;
    * ``camera_stopped`` — the cameras deliver no frames (a wanted frame pair never arrives and
      the capture cycle fails after its frame timeout);
    * ``cu_silent`` — the control unit hangs (the emulator's ``stall``: no replies, and its own
      watchdog stops the motors);
    * ``cu_corrupt`` — every reply has a flipped bit (CRC errors at the daemon);
    * ``perception_exception`` — the vision pipeline raises.
    """

    kind: FaultKind
    start_s: float
    end_s: float = math.inf

    def __post_init__(self) -> None:
        require(self.kind in FAULT_KINDS, "kind", f"must be one of {', '.join(FAULT_KINDS)}")
        require(self.end_s > self.start_s >= 0, "end_s", "must be after start_s ≥ 0")

    def active(self, now_s: float) -> bool:
        return self.start_s <= now_s < self.end_s


class InjectedFault(RuntimeError):
    """Raised by the simulated vision pipeline during a ``perception_exception`` fault."""


class FaultInjector:
    """Applies ``faults`` to a control-unit adapter and a tilt adapter as virtual time passes."""

    def __init__(self, faults: Sequence[Fault] = ()) -> None:
        self.faults = tuple(faults)
        self._active: set[str] = set()

    def active(self, kind: str) -> bool:
        """``kind`` is active (as of the last :meth:`apply`)."""
        return kind in self._active

    def apply(self, now_s: float, control_unit: Any, tilt: Any) -> None:
        """Switch the adapters' fault states to the faults active at ``now_s`` (logged)."""
        active: set[str] = {str(f.kind) for f in self.faults if f.active(now_s)}
        if active == self._active:
            return
        for name in sorted(active - self._active):
            log.warning("simulator: fault %s injected at t=%.2f s", name, now_s)
        for gone in sorted(self._active - active):
            log.warning("simulator: fault %s cleared at t=%.2f s", gone, now_s)
        emu = getattr(control_unit, "emulator", None)
        if emu is not None:
            if {"cu_silent", "cu_corrupt"} & (self._active - active):
                emu.recover()
            if "cu_silent" in active:
                emu.stall()
            if "cu_corrupt" in active:
                emu.corrupt_replies(None)
        elif hasattr(control_unit, "silent"):
            control_unit.silent = bool({"cu_silent", "cu_corrupt"} & active)
        if tilt is not None:
            tilt.unplugged = "tilt_unplugged" in active
        self._active = active
