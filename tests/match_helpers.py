"""The deliberately misaligned stereo rig shared by the matching/calibration/CLI tests."""

from __future__ import annotations

from omnid.sim.rigs import misaligned_rig

__all__ = ["misaligned_rig"]
