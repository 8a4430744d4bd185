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

import cv2
import numpy as np
from numpy.typing import NDArray

from omnid.config import require
from omnid.core.arrays import median
from omnid.core.calibration import Calibration
from omnid.core.detect import DetectionParams, detect_dots
from omnid.core.laser import LaserModel
from omnid.core.matching import (
    MatchMethod,
    MatchSettings,
    TripleMatch,
    _tracks,
    match_dots,
    match_triples,
)
from omnid.core.types import PointCloud, StereoCapture
from omnid.errors import InputError

#: How far around a doubled beam's image track :func:`split_regions` reaches, px: its two dots
#: lie either side of the blend's maximum (the random gratings' twins ≤ 3.5 px apart on the
#: floor), and the detected maximum lies within a pixel of the true one.
SPLIT_TRACK_HALF_PX = 4


def split_regions(
    calib: Calibration, matching: MatchSettings | None = None
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]] | None:
    """Per camera, the pixels where the detector splits a blend of two spots
    (:func:`~omnid.core.detect.detect_dots`' ``split_where``): within
    :data:`SPLIT_TRACK_HALF_PX` of the image track of a beam the laser model holds as doubled
    (:meth:`~omnid.core.laser.LaserModel.doubled`), at every depth the matcher reads
    (``matching.near_depth_mm`` below the mirrors to ``dropoff_depth_mm`` under the floor), for
    every source within the box 2 σ about where calibration put it (an unknown source's prior
    spread moves the tracks away from the floor): each stretch of track between two depths is
    the convex hull of its ends for the box's centre and corners. None when no beam is doubled. Such
    twins are one maximum for the detector; splitting only there costs what a few blobs cost,
    where splitting everywhere costs 1.4–2.6x the detection. Cached per calibration."""
    laser = calib.laser
    if laser is None:
        return None
    m = matching or MatchSettings()
    key = (id(laser), calib.rig, m.near_depth_mm, m.dropoff_depth_mm)
    hit = _SPLIT_CACHE.get(key)
    if hit is not None and hit[0] is laser:
        return hit[1]
    beams = np.flatnonzero(laser.doubled())
    out: tuple[NDArray[np.bool_], NDArray[np.bool_]] | None = None
    if len(beams):
        h = calib.floor_depth_mm
        u = np.linspace(1.0 / m.near_depth_mm, 1.0 / (h + m.dropoff_depth_mm), 64)
        o, so = np.asarray(laser.source_mm), np.asarray(laser.source_sigma_mm)
        corners = np.array(np.meshgrid([-2.0, 2.0], [-2.0, 2.0], [-2.0, 2.0])).reshape(3, -1).T
        sources = [src for src in (o, *(o + corners * so)) if src[2] < h - 1.0]
        px = []  # (sources, beams, depths, 4) image positions
        for src in sources:
            model = laser.with_source((src[0], src[1], src[2]), laser.source_sigma_mm)
            pts = model.point_at(np.repeat(beams, len(u)), np.tile(u, len(beams)))
            px.append(calib.rig.project(pts).reshape(len(beams), len(u), 4))
        pos = np.stack(px)
        masks = []
        for cam, shape in ((0, calib.rig.cam1.image_shape), (1, calib.rig.cam2.image_shape)):
            img = np.zeros(tuple(shape), dtype=np.uint8)
            # each stretch of a track between two depths, swept over the source's spread: the
            # convex hull of its ends for every source drawn (the image moves smoothly with O)
            for k in range(len(beams)):
                for i in range(len(u) - 1):
                    q = pos[:, k, i : i + 2, 2 * cam : 2 * cam + 2].reshape(-1, 2)
                    q = q[np.isfinite(q).all(axis=1)]
                    if len(q):
                        hull = cv2.convexHull(np.rint(q[:, ::-1] * 16.0).astype(np.int32))
                        cv2.fillConvexPoly(img, hull, 1, cv2.LINE_8, 4)
            grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * SPLIT_TRACK_HALF_PX + 1,) * 2)
            masks.append(cv2.dilate(img, grow))
        out = (masks[0].astype(bool), masks[1].astype(bool))
    if len(_SPLIT_CACHE) > 8:
        _SPLIT_CACHE.clear()
    _SPLIT_CACHE[key] = (laser, out)
    return out


_SPLIT_CACHE: dict[
    tuple[int, Any, float, float],
    tuple[LaserModel, tuple[NDArray[np.bool_], NDArray[np.bool_]] | None],
] = {}


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
    # ``best``: split blends of two spots near the tracks of the beams the laser model holds
    # as doubled (:func:`split_regions`); False: never (for comparison)
    split_doubled: bool = True
    health: HealthSettings = field(default_factory=lambda: HealthSettings())
    source: SourceSettings = field(default_factory=lambda: SourceSettings())

    def __post_init__(self) -> None:
        require(
            self.pixel_sigma_px is None or self.pixel_sigma_px > 0,
            "pixel_sigma_px",
            "must be positive",
        )


@dataclass(frozen=True)
class SourceSettings:
    """When a calibration does not know the laser's source (floor only), the capture's own
    off-floor dots may place it — the same estimator as calibration's ``--extra`` captures
    (:func:`omnid.core.calibration.locate_source`) — accepted only on strong evidence:
    at least ``min_dots`` dots' lines meet in one point (the estimator's own test), its 1-σ is
    at most ``max_sigma_mm`` on every axis (the dots' lines are not nearly parallel: a well
    conditioned point), the lines pass it within ``max_line_rms_mm`` rms, and no other point
    (beyond 25 mm) gathers more than ``max_runner_up`` of its votes — a second meeting point is
    another reading of the same dots (on one plane, a pairing shifted by a beam gives another
    plane from another source). Over the random rigs of ``tools/eval_rigs.py --floor-only``
    right sources left a runner-up of 0.13-0.60, the one wrong source 0.94."""

    min_dots: int = 12
    max_sigma_mm: float = 6.0
    max_line_rms_mm: float = 3.0
    max_runner_up: float = 0.7

    def __post_init__(self) -> None:
        require(self.min_dots >= 3, "min_dots", "must be at least 3")
        require(self.max_sigma_mm > 0, "max_sigma_mm", "must be positive")
        require(self.max_line_rms_mm > 0, "max_line_rms_mm", "must be positive")
        require(0 < self.max_runner_up < 1, "max_runner_up", "must be in (0, 1)")


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
    # best with a calibration that does not know the source: where this capture placed it
    # ((x, y, z), σ (x, y, z) mm; None: known already, or not placed) and how many dots pair
    # off the floor without a beam to explain them (their area is not free space)
    source_estimate: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    not_understood: int = 0

    @property
    def matched_fraction(self) -> float:
        """Points of the cloud / dots found by the camera that found fewer (0 when none)."""
        n = min(len(self.dots1), len(self.dots2))
        return len(self.cloud) / n if n else 0.0


#: The defaults, built (and range-checked) once: perceive runs per frame.
_DEFAULT_SETTINGS = PerceptionSettings()


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
    med = median(ratio) if len(ratio) else math.nan
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

    s = settings or _DEFAULT_SETTINGS
    if method not in ("thesis", "best"):
        raise ValueError(f"unknown method {method!r} (known: thesis, best)")
    expected = tuple(calib.rig.cam1.image_shape)
    if capture.shape != expected:
        raise InputError(
            f"capture is {capture.shape[1]}x{capture.shape[0]} px but the calibration is for "
            f"{expected[1]}x{expected[0]} px"
        )
    if method == "best" and calib.laser is None:
        raise InputError("the calibration has no laser model: recalibrate with `omnid calibrate`")
    det = s.detection_method or method
    split1: bool | NDArray[np.bool_] = False
    split2: bool | NDArray[np.bool_] = False
    if det == "best" and s.split_doubled:
        regions = split_regions(calib, s.matching)
        if regions is not None:
            split1, split2 = regions
    d1 = detect_dots(capture.mask1, capture.base1, det, s.detection, split1)
    d2 = detect_dots(capture.mask2, capture.base2, det, s.detection, split2)
    H = calib.floor_depth_mm
    health = None
    source_estimate = None
    not_understood = 0
    if method == "best":
        sigma = s.pixel_sigma_px or calib.pixel_sigma_px
        laser = calib.laser
        assert laser is not None
        if laser.source_known:
            m = match_triples(calib.rig, laser, sigma, d1, d2, s.matching)
        else:
            m, laser, source_estimate, not_understood = _match_unknown_source(
                calib, laser, sigma, d1, d2, s
            )
        health = _health(len(d1), len(d2), len(m.i1), m.residual_px / sigma, s.health)
        # (np.take / np.compress: numpy indexes the rows of a 2-D array ~10x slower)
        pixels = np.hstack([np.take(d1[:, :2], m.i1, axis=0), np.take(d2[:, :2], m.i2, axis=0)])
        tr = _tracks(calib.rig, laser)
        xyz, cov = triangulate_on_beams(
            calib.rig,
            pixels,
            np.take(tr.slope, m.beam, axis=0),
            np.take(tr.cross_mm, m.beam, axis=0),
            tr.slope_sigma(m.beam, m.inv_depth),
            sigma,
        )
    else:
        pixels = match_dots(calib, d1, d2, method, s.matching)
        sigma = s.pixel_sigma_px or 1.0 / math.sqrt(12.0)
        xyz, cov = triangulate(calib.rig, pixels, method, sigma)
    fit = health.explained if health is not None else math.nan
    extra = (source_estimate, not_understood)
    if len(pixels) == 0:
        empty = PointCloud(floor_depth_mm=H, calibration_fit=fit, not_understood=not_understood)
        return Perception(empty, d1, d2, det, health, *extra)
    ok = np.all(np.isfinite(xyz), axis=1) & (xyz[:, 2] > 0)
    cloud = PointCloud(
        xyz=np.compress(ok, xyz, axis=0),
        cov=np.compress(ok, cov, axis=0),
        pixels=np.compress(ok, pixels, axis=0),
        classes=np.zeros(int(ok.sum()), dtype=np.uint8),
        floor_depth_mm=H,
        calibration_fit=fit,
        not_understood=not_understood,
    )
    cloud = replace(cloud, classes=np.asarray(classify(cloud, s.classify), dtype=np.uint8))
    return Perception(cloud, d1, d2, det, health, *extra)


def _match_unknown_source(
    calib: Calibration,
    laser: LaserModel,
    sigma_px: float,
    d1: NDArray[np.float64],
    d2: NDArray[np.float64],
    s: PerceptionSettings,
) -> tuple[
    TripleMatch,
    LaserModel,
    tuple[tuple[float, float, float], tuple[float, float, float]] | None,
    int,
]:
    """``best`` when calibration knows every beam's floor point but not the source (floor-only
    calibration): (triples, the laser model they were matched on, the source placed from this
    capture or None, dots not understood).

    1. Floor dots need no source: near the floor a beam's track is its floor dot's image
       (the source's error enters with the lever (H − Z)/(H − O_Z), nil at the floor), so the
       triple matcher is run on a thin depth band around the floor (4 σ of the floor's
       stereo depth: a few cm) — few hypotheses, fast.
    2. The dots left over that pair off the floor are the extras' problem: their lines from
       their beams' floor points meet at the source. :func:`locate_source` places it (the prior
       box bounds the hypotheses) and :class:`SourceSettings` judges the evidence; if it holds,
       the whole capture is matched on the beams from that source.
    3. Otherwise those dots are not understood: no point for them (never floor), counted.
    """
    from omnid.core.calibration import _off_floor_pairs, locate_source
    from omnid.errors import CalibrationError

    rig = calib.rig
    H = rig.floor_depth_mm
    f = 0.5 * (rig.cam1.f_over_k_px + rig.cam2.f_over_k_px)
    sigma_z = H * H * math.sqrt(2.0) * sigma_px / (f * rig.baseline_mm)
    band = max(4.0 * sigma_z, 10.0)
    floor_ms = replace(s.matching, near_depth_mm=H - band, dropoff_depth_mm=band)
    m = match_triples(rig, laser, sigma_px, d1, d2, floor_ms)
    rest1 = np.setdiff1d(np.arange(len(d1)), m.i1)
    rest2 = np.setdiff1d(np.arange(len(d2)), m.i2)
    if len(rest1) == 0 or len(rest2) == 0:
        return m, laser, None, 0
    r1, r2 = d1[rest1], d2[rest2]
    off = _off_floor_pairs(rig, r1, r2, sigma_px)
    n_off = len(np.unique(off.dot1))
    if n_off < s.source.min_dots:
        return m, laser, None, n_off
    from omnid.core.calibration import CalibrationSettings

    try:
        o, sig_o, info = locate_source(
            rig,
            laser.floor_mm,
            [(r1, r2)],
            sigma_px,
            CalibrationSettings(min_source_dots=s.source.min_dots),
        )
    except CalibrationError:
        return m, laser, None, n_off
    if (
        float(np.max(sig_o)) > s.source.max_sigma_mm
        or info["source_line_rms_mm"] > s.source.max_line_rms_mm
        or info["source_runner_up"] > s.source.max_runner_up
    ):
        return m, laser, None, n_off
    est = (
        (float(o[0]), float(o[1]), float(o[2])),
        (float(sig_o[0]), float(sig_o[1]), float(sig_o[2])),
    )
    placed = laser.with_source(*est)
    full = match_triples(rig, placed, sigma_px, d1, d2, s.matching)
    left = np.setdiff1d(off.dot1, np.searchsorted(rest1, np.intersect1d(rest1, full.i1)))
    return full, placed, est, len(left)
