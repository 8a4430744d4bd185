"""Value types shared across the numeric core: captures and point clouds."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray


class PointClass(IntEnum):
    """What a 3-D point is, relative to the floor (SPEC §6 ``class``)."""

    FLOOR = 0
    OBSTACLE = 1
    DROPOFF = 2

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class StereoCapture:
    """One stereo mask/base capture: four images of equal shape, 8-bit gray (H, W) or BGR (H, W, 3).

    ``mask`` frames are taken with the laser off, ``base`` frames with it on (thesis 5.1).
    ``timestamp_s`` is the monotonic time of the base frames, s.
    """

    mask1: NDArray[np.uint8]
    base1: NDArray[np.uint8]
    mask2: NDArray[np.uint8]
    base2: NDArray[np.uint8]
    timestamp_s: float = 0.0

    def __post_init__(self) -> None:
        shapes = {a.shape for a in (self.mask1, self.base1, self.mask2, self.base2)}
        if len(shapes) != 1:
            raise ValueError(
                f"StereoCapture: all four images must have one shape, got {sorted(shapes)}"
            )
        shape = next(iter(shapes))
        if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] != 3):
            raise ValueError(f"StereoCapture: expected (H, W) or (H, W, 3) images, got {shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of each image, px."""
        return (int(self.mask1.shape[0]), int(self.mask1.shape[1]))


def _empty(shape: tuple[int, ...], dtype: type = np.float64) -> NDArray:
    return np.zeros(shape, dtype=dtype)


@dataclass(frozen=True)
class PointCloud:
    """Triangulated laser dots in the rig frame (SPEC §2).

    xyz         (N, 3) X, Y, Z in mm (Z positive downward, depth below the mirrors)
    cov         (N, 3, 3) covariance of xyz, mm² (NaN where the method gives none)
    pixels      (N, 4) matched image positions r1, c1, r2, c2, px
    classes     (N,) :class:`PointClass` codes (uint8)
    floor_depth_mm  the floor's depth H, so that height h = H − Z
    calibration_fit  how well the capture fitted the calibration: the share of the dots both
                cameras detected that a calibrated laser beam explains (1 = all; NaN = not
                measured). A rig knocked out of calibration explains few (see
                :class:`omnid.core.pipeline.CalibrationHealth`).
    not_understood  dots that pair off the floor but that no known beam explains (a
                calibration that does not know the laser's source, and a capture that could
                not place it): their area is not free space, and no point is reported there
                (the daemon keeps such a capture out of its map: the area counts as unseen)
    """

    xyz: NDArray[np.float64] = field(default_factory=lambda: _empty((0, 3)))
    cov: NDArray[np.float64] = field(default_factory=lambda: _empty((0, 3, 3)))
    pixels: NDArray[np.float64] = field(default_factory=lambda: _empty((0, 4)))
    classes: NDArray[np.uint8] = field(default_factory=lambda: _empty((0,), np.uint8))
    floor_depth_mm: float = 1100.0
    calibration_fit: float = math.nan
    not_understood: int = 0

    def __post_init__(self) -> None:
        n = len(self.xyz)
        if (
            self.xyz.shape != (n, 3)
            or self.cov.shape != (n, 3, 3)
            or self.pixels.shape != (n, 4)
            or self.classes.shape != (n,)
        ):
            raise ValueError(
                "PointCloud: inconsistent shapes "
                f"xyz={self.xyz.shape} cov={self.cov.shape} pixels={self.pixels.shape} "
                f"classes={self.classes.shape}"
            )

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def height_mm(self) -> NDArray[np.float64]:
        """Height above the floor h = H − Z of each point, mm."""
        return self.floor_depth_mm - self.xyz[:, 2]

    def to_records(self) -> list[dict[str, float | str]]:
        """Plain dicts in the ``perceive --json`` layout (SPEC §6)."""
        labels = [PointClass(int(c)).label for c in self.classes]
        h = self.height_mm
        return [
            {
                "x": float(p[0]),
                "y": float(p[1]),
                "z": float(p[2]),
                "h": float(hh),
                "r1": float(q[0]),
                "c1": float(q[1]),
                "r2": float(q[2]),
                "c2": float(q[3]),
                "class": lab,
            }
            for p, hh, q, lab in zip(self.xyz, h, self.pixels, labels, strict=True)
        ]
