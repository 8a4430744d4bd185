"""A deliberately misaligned stereo rig shared by the matching/calibration/CLI tests."""

from __future__ import annotations

import math
from dataclasses import replace

from omnid.core.geometry import StereoRig


def misaligned_rig(floor_depth_mm: float = 1100.0) -> StereoRig:
    """Centres a few px off, f/K differing by a few %, rotations of 1.5° and −1°."""
    nom = StereoRig.nominal(floor_depth_mm=floor_depth_mm)
    c1 = replace(
        nom.cam1,
        center_row_px=nom.cam1.center_row_px + 3.0,
        center_col_px=nom.cam1.center_col_px - 2.0,
        f_over_k_px=108.3 * 1.03,
        rotation_rad=math.radians(1.5),
    )
    c2 = replace(
        nom.cam2,
        center_row_px=nom.cam2.center_row_px - 2.0,
        center_col_px=nom.cam2.center_col_px + 4.0,
        f_over_k_px=108.3 * 0.98,
        rotation_rad=math.radians(-1.0),
    )
    return StereoRig(c1, c2, floor_depth_mm)
