"""Stereo rigs "as installed": the one deliberately misaligned rig and a random draw of rigs.

Real mirrors are misaligned: each camera's mirror centre sits a few px off the image middle, its
scale f/K differs by a few per cent and the image is turned by a small angle about the mirror axis
(SPEC §2). Calibration (thesis 6.3) must find all of it out; nothing downstream may assume the
nominal rig.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from omnid.config import require
from omnid.core.geometry import DEFAULT_FLOOR_DEPTH_MM, StereoRig


def misaligned_rig(floor_depth_mm: float = DEFAULT_FLOOR_DEPTH_MM) -> StereoRig:
    """The rig of the README example: centres (+3, −2) and (−2, +4) px off, f/K +3 % / −2 %,
    rotations +1.5° / −1°."""
    nom = StereoRig.nominal(floor_depth_mm=floor_depth_mm)
    c1 = replace(
        nom.cam1,
        center_row_px=nom.cam1.center_row_px + 3.0,
        center_col_px=nom.cam1.center_col_px - 2.0,
        f_over_k_px=nom.cam1.f_over_k_px * 1.03,
        rotation_rad=math.radians(1.5),
    )
    c2 = replace(
        nom.cam2,
        center_row_px=nom.cam2.center_row_px - 2.0,
        center_col_px=nom.cam2.center_col_px + 4.0,
        f_over_k_px=nom.cam2.f_over_k_px * 0.98,
        rotation_rad=math.radians(-1.0),
    )
    return StereoRig(c1, c2, floor_depth_mm)


@dataclass(frozen=True)
class RigSpread:
    """How far an installed rig may be from the nominal one (each drawn uniformly in ±value).

    The defaults are issue 9's evaluation ranges: centres ±6 px, f/K ±4 %, roll ±1.5°.
    """

    center_px: float = 6.0
    f_over_k_rel: float = 0.04
    rotation_rad: float = math.radians(1.5)

    def __post_init__(self) -> None:
        require(self.center_px >= 0, "center_px", "must not be negative")
        require(0 <= self.f_over_k_rel < 0.5, "f_over_k_rel", "must be in [0, 0.5)")
        require(0 <= self.rotation_rad < 0.2, "rotation_rad", "must be in [0, 0.2)")


def random_rig(
    rng: np.random.Generator | int,
    floor_depth_mm: float = DEFAULT_FLOOR_DEPTH_MM,
    spread: RigSpread | None = None,
) -> StereoRig:
    """A rig drawn around the nominal one: each camera's centre, f/K and rotation independently
    uniform within ``spread``."""
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    sp = spread or RigSpread()
    nom = StereoRig.nominal(floor_depth_mm=floor_depth_mm)
    cams = []
    for cam in (nom.cam1, nom.cam2):
        dr, dc = gen.uniform(-sp.center_px, sp.center_px, 2)
        cams.append(
            replace(
                cam,
                center_row_px=cam.center_row_px + float(dr),
                center_col_px=cam.center_col_px + float(dc),
                f_over_k_px=cam.f_over_k_px * (1.0 + float(gen.uniform(-1, 1)) * sp.f_over_k_rel),
                rotation_rad=float(gen.uniform(-1, 1)) * sp.rotation_rad,
            )
        )
    return StereoRig(cams[0], cams[1], floor_depth_mm)
