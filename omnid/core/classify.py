"""Floor / obstacle / drop-off classification of triangulated dots (thesis 7.1.2, 7.2.2; SPEC §3).

The thesis marks a point as floor "according to the Z axis location within a threshold value"
(7.1.2) and takes every other point as an obstacle. omnid refines both halves:

- the band is per point, from its own uncertainty: a point is floor when its height above the
  floor, h = H − Z, satisfies |h| ≤ k·σ_h + tolerance, where σ_h = σ_Z = sqrt(cov[2, 2]) from the
  triangulation error model (eqs. 6.10–6.11) and the tolerance absorbs floor unevenness and
  calibration error of H. Far dots (large σ_Z) get a wider band than near ones, instead of one
  threshold that is too tight near and too loose far;
- points clearly below the floor are drop-offs (missing floor: stairs, kerbs), not obstacles;
- the band is capped (``max_band_mm``): a point so uncertain that it could be a kerb or a box is
  never called floor — for a wheelchair, "free" must be earned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.types import PointClass, PointCloud


@dataclass(frozen=True)
class ClassifySettings:
    """How far from the floor a dot may lie and still be floor.

    sigma_factor        k: how many standard deviations of h the floor band spans
    floor_tolerance_mm  fixed part of the band: floor unevenness, error of H, mm
    default_sigma_mm    σ_h used where the cloud's covariance is NaN (no error model), mm
    max_band_mm         the band never exceeds this, however uncertain the point, mm
    """

    sigma_factor: float = 3.0
    floor_tolerance_mm: float = 15.0
    default_sigma_mm: float = 20.0
    max_band_mm: float = 120.0

    def __post_init__(self) -> None:
        for key in ("sigma_factor", "floor_tolerance_mm", "default_sigma_mm", "max_band_mm"):
            value = getattr(self, key)
            require(math.isfinite(value) and value >= 0, key, "must be a finite number ≥ 0")
        require(self.max_band_mm > 0, "max_band_mm", "must be positive")


def floor_band_mm(
    cloud: PointCloud, settings: ClassifySettings | None = None
) -> NDArray[np.float64]:
    """(N,) half-width of the floor band of each point, mm: min(k·σ_h + tol, max_band)."""
    s = settings or ClassifySettings()
    if len(cloud) == 0:
        return np.zeros(0)
    var = cloud.cov[:, 2, 2]
    sigma = np.where(np.isfinite(var) & (var >= 0), np.sqrt(np.abs(var)), s.default_sigma_mm)
    return np.minimum(s.sigma_factor * sigma + s.floor_tolerance_mm, s.max_band_mm)


def classify(cloud: PointCloud, settings: ClassifySettings | None = None) -> NDArray[np.uint8]:
    """(N,) :class:`PointClass` codes: FLOOR where |h| ≤ band, OBSTACLE above it, DROPOFF below.

    h = H − Z with H = ``cloud.floor_depth_mm`` (SPEC §2). Points with a non-finite position are
    OBSTACLE: an unexplained return must not open free space.
    """
    n = len(cloud)
    if n == 0:
        return np.zeros(0, dtype=np.uint8)
    h = cloud.height_mm
    band = floor_band_mm(cloud, settings)
    out = np.full(n, PointClass.OBSTACLE, dtype=np.uint8)
    finite = np.isfinite(h)
    with np.errstate(invalid="ignore"):
        out[finite & (np.abs(h) <= band)] = PointClass.FLOOR
        out[finite & (h < -band)] = PointClass.DROPOFF
    return out


def with_classes(cloud: PointCloud, settings: ClassifySettings | None = None) -> PointCloud:
    """The same cloud with ``classes`` filled in by :func:`classify`."""
    return replace(cloud, classes=classify(cloud, settings))
