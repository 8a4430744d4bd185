"""The perception pipeline: one stereo capture → a classified point cloud (thesis ch. 5–7).

``perceive(capture, calib, method, settings)`` subtracts mask from base, detects the dots of
both cameras, matches them (:mod:`omnid.core.matching`), triangulates the pairs
(:mod:`omnid.core.triangulate`; ``best`` with each dot's laser beam as a third view) and
classifies each point as floor, obstacle or drop-off (:mod:`omnid.core.classify`). ``best``
also measures how well the capture fits the calibration (:class:`CalibrationHealth`, and
``PointCloud.calibration_fit``). Pure: no I/O, no globals; the daemon runs it in a worker.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.calibration import Calibration
from omnid.core.detect import DetectionParams, detect_dots
from omnid.core.matching import (
    MatchMethod,
    MatchSettings,
    _tracks,
    match_best_triples,
    match_dots,
)
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
    # measured scatter (:attr:`Calibration.pixel_sigma_px`, at least 0.05 px); for ``thesis``
    # 1/√12 ≈ 0.29 px (its centres are whole pixels).
    pixel_sigma_px: float | None = None
    classify: Any = None  # omnid.core.classify.ClassifySettings, or None for its defaults
    health: HealthSettings = field(default_factory=lambda: HealthSettings())

    def __post_init__(self) -> None:
        require(
            self.pixel_sigma_px is None or self.pixel_sigma_px > 0,
            "pixel_sigma_px",
            "must be positive",
        )


@dataclass(frozen=True)
class HealthSettings:
    """When a capture no longer fits the calibration (the rig was knocked).

    Over the random rigs and scenes of ``tools/eval_rigs.py`` the share of dots a beam explains
    is ≥ 0.80 in every capture (its lowest: near walls, where each camera sees dots the other
    cannot); a camera turned by 0.5° or shifted by 2 px leaves < 0.2. ``min_explained`` sits
    between, ``min_dots`` below which a capture says nothing (laser off, lens covered).
    """

    min_explained: float = 0.5
    min_dots: int = 20

    def __post_init__(self) -> None:
        require(0 < self.min_explained < 1, "min_explained", "must be in (0, 1)")
        require(self.min_dots >= 1, "min_dots", "must be at least 1")


@dataclass(frozen=True)
class CalibrationHealth:
    """How well one capture fits the calibration (``best`` only).

    explained       share of the dots both cameras detected that a calibrated beam explains:
                    2·(pairs matched) / (dots1 + dots2)
    residual_ratio  median of the matched triples' residual over the noise the calibration
                    measured (≈ 0.9 when the rig is as calibrated; it grows as the rig drifts)
    ok              explained ≥ ``min_explained``; True when fewer than ``min_dots`` dots were
                    detected (nothing to judge by: ``explained`` is NaN then)
    """

    explained: float
    residual_ratio: float
    dots: int
    ok: bool

    def describe(self) -> str:
        """One line for a person."""
        verdict = "fits the calibration" if self.ok else "does NOT fit the calibration"
        if math.isnan(self.explained):
            return f"too few dots ({self.dots}) to tell whether the capture fits the calibration"
        return (
            f"capture {verdict}: {100 * self.explained:.0f} % of {self.dots} dots on a "
            f"calibrated beam, residual {self.residual_ratio:.2f} x the calibrated noise"
        )


@dataclass(frozen=True)
class Perception:
    """What one run of the pipeline found: the classified cloud, and the dots each camera's
    detector found, (N, 3) rows (row_px, col_px, strength) — for the matched fraction — and,
    for ``best``, how well the capture fits the calibration."""

    cloud: PointCloud
    dots1: NDArray[np.float64]
    dots2: NDArray[np.float64]
    detection_method: str
    health: CalibrationHealth | None = None

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


def _health(
    n1: int, n2: int, matched: int, ratio: NDArray[np.float64], s: HealthSettings
) -> CalibrationHealth:
    dots = n1 + n2
    explained = 2.0 * matched / dots if dots else math.nan
    med = float(np.median(ratio)) if len(ratio) else math.nan
    judged = dots >= s.min_dots
    return CalibrationHealth(
        explained if judged else math.nan, med, dots, not judged or explained >= s.min_explained
    )


def perceive_detailed(
    capture: StereoCapture,
    calib: Calibration,
    method: MatchMethod = "best",
    settings: PerceptionSettings | None = None,
) -> Perception:
    """:func:`perceive`, also returning the dots each camera's detector found and the capture's
    calibration health (``best``)."""
    from omnid.core.classify import classify
    from omnid.core.triangulate import triangulate, triangulate_on_beams

    s = settings or PerceptionSettings()
    if method not in ("thesis", "best"):
        raise ValueError(f"unknown method {method!r} (known: thesis, best)")
    expected = tuple(calib.rig.cam1.image_shape)
    if capture.shape != expected:
        raise InputError(
            f"capture is {capture.shape[1]}x{capture.shape[0]} px but the calibration is for "
            f"{expected[1]}x{expected[0]} px"
        )
    if method == "best" and (calib.laser is None or not calib.laser.source_known):
        raise InputError(
            "the calibration does not know the laser's source (made from the floor alone, or "
            "an older file): recalibrate with `omnid calibrate ... --extra DIR` (a box or a wall "
            "0.5-1.5 m ahead)"
        )
    det = s.detection_method or method
    d1 = detect_dots(capture.mask1, capture.base1, det, s.detection)
    d2 = detect_dots(capture.mask2, capture.base2, det, s.detection)
    H = calib.floor_depth_mm
    health = None
    if method == "best":
        sigma = s.pixel_sigma_px or calib.pixel_sigma_px
        m = match_best_triples(calib, d1, d2, s.matching)
        health = _health(len(d1), len(d2), len(m.i1), m.residual_px / sigma, s.health)
        pixels = np.column_stack([d1[m.i1, :2], d2[m.i2, :2]])
        tr = _tracks(calib.rig, calib.laser)  # type: ignore[arg-type]
        xyz, cov = triangulate_on_beams(
            calib.rig,
            pixels,
            tr.slope[m.beam],
            tr.cross_mm[m.beam],
            tr.slope_sigma(m.beam, m.inv_depth),
            sigma,
        )
    else:
        pixels = match_dots(calib, d1, d2, method, s.matching)
        sigma = s.pixel_sigma_px or 1.0 / math.sqrt(12.0)
        xyz, cov = triangulate(calib.rig, pixels, method, sigma)
    fit = health.explained if health is not None else math.nan
    if len(pixels) == 0:
        return Perception(PointCloud(floor_depth_mm=H, calibration_fit=fit), d1, d2, det, health)
    ok = np.all(np.isfinite(xyz), axis=1) & (xyz[:, 2] > 0)
    cloud = PointCloud(
        xyz=xyz[ok],
        cov=cov[ok],
        pixels=pixels[ok],
        classes=np.zeros(int(ok.sum()), dtype=np.uint8),
        floor_depth_mm=H,
        calibration_fit=fit,
    )
    cloud = replace(cloud, classes=np.asarray(classify(cloud, s.classify), dtype=np.uint8))
    return Perception(cloud, d1, d2, det, health)
