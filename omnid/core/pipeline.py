"""The perception pipeline: one stereo capture → a classified point cloud (thesis ch. 5–7).

``perceive(capture, calib, method, settings)`` subtracts mask from base, detects the dots of
both cameras, matches them (:mod:`omnid.core.matching`), triangulates the pairs
(:mod:`omnid.core.triangulate`) and classifies each point as floor, obstacle or drop-off
(:mod:`omnid.core.classify`). Pure: no I/O, no globals; the daemon runs it in a worker thread.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.calibration import Calibration
from omnid.core.detect import DetectionParams, detect_dots
from omnid.core.matching import MatchMethod, MatchSettings, match_dots
from omnid.core.types import PointCloud, StereoCapture
from omnid.errors import InputError


@dataclass(frozen=True)
class PerceptionSettings:
    """Settings of each stage. ``detection_method`` None (the default) means: the same as the
    matching method, so ``thesis`` runs the thesis end to end (detector of 5.2–5.4, matching
    of 6.12–6.16, triangulation of 6.1–6.9) and ``best`` ours."""

    detection_method: Literal["thesis", "best"] | None = None
    detection: DetectionParams = field(default_factory=DetectionParams)
    matching: MatchSettings = field(default_factory=MatchSettings)
    # Image noise of a dot centre for the covariance, px. None: for ``best`` the calibration's
    # row residual (the dots' real scatter on this rig), at least 0.1 px; for ``thesis``
    # 1/√12 ≈ 0.29 px (its centres are whole pixels).
    pixel_sigma_px: float | None = None
    classify: Any = None  # omnid.core.classify.ClassifySettings, or None for its defaults

    def __post_init__(self) -> None:
        require(
            self.pixel_sigma_px is None or self.pixel_sigma_px > 0,
            "pixel_sigma_px",
            "must be positive",
        )


@dataclass(frozen=True)
class Perception:
    """What one run of the pipeline found: the classified cloud, and the dots each camera's
    detector found, (N, 3) rows (row_px, col_px, strength) — for the matched fraction."""

    cloud: PointCloud
    dots1: NDArray[np.float64]
    dots2: NDArray[np.float64]
    detection_method: str

    @property
    def matched_fraction(self) -> float:
        """Points of the cloud / dots found by the camera that found fewer (0 when none)."""
        n = min(len(self.dots1), len(self.dots2))
        return len(self.cloud) / n if n else 0.0


def perceive(
    capture: StereoCapture,
    calib: Calibration,
    method: MatchMethod = "best",
    settings: PerceptionSettings | None = None,
) -> PointCloud:
    """Classified laser dots (rig frame, mm) seen in ``capture`` with ``method`` matching and
    triangulation. An image without dots gives an empty cloud."""
    return perceive_detailed(capture, calib, method, settings).cloud


def perceive_detailed(
    capture: StereoCapture,
    calib: Calibration,
    method: MatchMethod = "best",
    settings: PerceptionSettings | None = None,
) -> Perception:
    """:func:`perceive`, also returning the dots each camera's detector found."""
    from omnid.core.classify import classify
    from omnid.core.triangulate import triangulate

    s = settings or PerceptionSettings()
    if method not in ("thesis", "best"):
        raise ValueError(f"unknown method {method!r} (known: thesis, best)")
    expected = tuple(calib.rig.cam1.image_shape)
    if capture.shape != expected:
        raise InputError(
            f"capture is {capture.shape[1]}x{capture.shape[0]} px but the calibration is for "
            f"{expected[1]}x{expected[0]} px"
        )
    det = s.detection_method or method
    d1 = detect_dots(capture.mask1, capture.base1, det, s.detection)
    d2 = detect_dots(capture.mask2, capture.base2, det, s.detection)
    pixels = match_dots(calib, d1, d2, method, s.matching)
    H = calib.floor_depth_mm
    if len(pixels) == 0:
        return Perception(PointCloud(floor_depth_mm=H), d1, d2, det)
    sigma = s.pixel_sigma_px
    if sigma is None:
        row_rms = float(calib.residuals.get("row_rms_px", 0.0))
        sigma = max(0.1, row_rms) if method == "best" else 1.0 / np.sqrt(12.0)
    xyz, cov = triangulate(calib.rig, pixels, method, sigma)
    ok = np.all(np.isfinite(xyz), axis=1) & (xyz[:, 2] > 0)
    cloud = PointCloud(
        xyz=xyz[ok],
        cov=cov[ok],
        pixels=pixels[ok],
        classes=np.zeros(int(ok.sum()), dtype=np.uint8),
        floor_depth_mm=H,
    )
    cloud = replace(cloud, classes=np.asarray(classify(cloud, s.classify), dtype=np.uint8))
    return Perception(cloud, d1, d2, det)
