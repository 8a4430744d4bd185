"""Automatic calibration of the rig and the laser from the installer's captures (thesis 6.3;
SPEC §§2, 6).

No manual clicking, and no assumed dot pattern: everything is found in one stereo mask/base
capture of an empty floor at a known depth H below the mirrors (baseline D known), plus any
number of ``--extra`` captures in which some dots fall on something else (a box, a wall).

1. **Mirror centres** — outside the mirror's disk the image is dark, so a circle fitted to the
   edge of the bright disk in each *mask* image gives the mirror centre (r_m, c_m) and radius.
2. **Floor registration** — on the floor, camera 2's dots are camera 1's under a similarity:
   o₂ = s·R(φ)·o₁ + t with s = F₂/F₁, φ = θ₂ − θ₁ and t = −R(θ₂)·(0, F₂·D/H) (rows agree, the
   disparity F·D/H runs along the baseline; SPEC §2). A search over (s, φ) with the translation
   voted in the window the f/K prior allows finds it robustly for any dot pattern; the winner
   must stand clear of any other translation (a periodic pattern would leave it ambiguous).
3. **Robust fit** — with pairs found, rows agree and the disparity equals D/H in slope units:
   with A_i = cos θ_i/(f/K)_i, B_i = sin θ_i/(f/K)_i both conditions are *linear* in
   (A1, B1, A2, B2), so RANSAC over pairs plus a final least-squares fit on the inliers gives
   f/K and θ of both cameras. The residuals (px) are kept in the calibration.
4. **Thesis matching polynomials** — the inlier pairs are the control pixel pairs of 6.3.1.1;
   eqs. 6.12/6.13 are fitted to them and refined in the thesis' three steps (2 px, then 1 px
   search neighbourhoods, then final coefficients), see :mod:`omnid.core.matching`.
5. **The laser's beams** — every floor dot is one beam's floor point P_k (triangulated from both
   cameras, or from one where the other camera's disk cannot show it), with its error.
6. **The laser's source** — the floor alone cannot place the source O (any O fits one plane).
   In an extra capture a dot whose stereo pair triangulates to Q off the floor lies on the line
   through O and its beam's floor point: every (pair, beam) hypothesis is a line that O must lie
   on; O is the point most lines pass through (a vote over the prior box, then weighted least
   squares over the inlier lines). Without extras, or when they show nothing off the floor, O
   stays the prior (``LaserModel.source_known`` False) and the matcher is told how uncertain
   the tracks are; :func:`source_advice` says what to capture.

A capture with no dots, that is not a single horizontal plane, or whose depth contradicts the
given one raises :class:`~omnid.errors.CalibrationError` with the residuals reached.
:class:`Calibration` is frozen and saved as versioned YAML (``format_version: 2``); ``save``
writes a temporary file and renames it, so a failure never leaves a half-written file.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from omnid.config import from_mapping, load_yaml, require
from omnid.core.detect import DetectionParams, detect_dots, to_gray
from omnid.core.geometry import DEFAULT_F_OVER_K_PX, MirrorCamera, StereoRig
from omnid.core.laser import SOURCE_PRIOR_MM, LaserModel
from omnid.core.types import StereoCapture
from omnid.errors import CalibrationError, ConfigError

FORMAT_VERSION = 2


# --------------------------------------------------------------------------------------------
# Settings and the calibration value type
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationSettings:
    """How :func:`calibrate_from_capture` works and what it accepts."""

    f_over_k_prior_px: float = DEFAULT_F_OVER_K_PX  # thesis: 10.80 mm/px at 1170 mm depth
    f_over_k_tolerance: float = 0.15  # accepted relative distance from the prior
    max_rotation_rad: float = math.radians(4.0)  # a mirror turned more than this: refuse
    min_pairs: int = 30  # fewer matched floor dots: refuse
    min_inlier_fraction: float = 0.8  # of the dots seen, the fraction pairing as one floor
    inlier_px: float = 0.8  # RANSAC inlier threshold on row/disparity residuals, px
    max_rms_px: float = 0.5  # refuse when the inliers' rms residual is larger, px
    ransac_iterations: int = 200
    seed: int = 0
    disk_threshold: float | None = None  # gray level of the disk edge; None = automatic
    # The laser's source: where it is searched (the prior box, mm, ± per axis around
    # SOURCE_PRIOR_MM: SPEC §2 "a few centimetres" sideways, "±150 mm" above or below, with room;
    # 200 mm lost one rig's source over tools/eval_rigs.py: 112 mm off),
    # how many off-floor dots must agree on it, and its vote cell.
    source_box_mm: tuple[float, float, float] = (100.0, 100.0, 250.0)
    min_source_dots: int = 12
    source_cell_mm: float = 5.0
    # Share of the extras' dots the learned laser must explain (the same matcher as perception;
    # true extras: 0.75-0.95 over the random rigs, another rig's captures: < 0.2)
    min_extra_explained: float = 0.5

    def __post_init__(self) -> None:
        require(self.f_over_k_prior_px > 0, "f_over_k_prior_px", "must be positive")
        require(0 < self.f_over_k_tolerance < 0.5, "f_over_k_tolerance", "must be in (0, 0.5)")
        require(0 < self.max_rotation_rad < 0.5, "max_rotation_rad", "must be in (0, 0.5)")
        require(self.min_pairs >= 6, "min_pairs", "must be at least 6")
        require(0 < self.min_inlier_fraction <= 1, "min_inlier_fraction", "must be in (0, 1]")
        require(self.inlier_px > 0, "inlier_px", "must be positive")
        require(self.max_rms_px > 0, "max_rms_px", "must be positive")
        require(self.ransac_iterations >= 1, "ransac_iterations", "must be at least 1")
        require(all(v > 0 for v in self.source_box_mm), "source_box_mm", "must be positive")
        require(self.min_source_dots >= 3, "min_source_dots", "must be at least 3")
        require(self.source_cell_mm > 0, "source_cell_mm", "must be positive")
        require(0 < self.min_extra_explained < 1, "min_extra_explained", "must be in (0, 1)")


@dataclass(frozen=True)
class Calibration:
    """Everything perception needs about the rig and the laser, found from the captures.

    Attributes
    ----------
    rig
        The :class:`StereoRig` (per-camera mirror centre, f/K, rotation; floor depth H).
    row_coeffs
        (l1, l2) of the thesis row polynomial, eq. 6.12 (pixels of camera 1 → camera 2).
    col_coeffs
        (k1 … k11) of the thesis column polynomial, eq. 6.13.
    control_pairs_px
        (K, 4) r1, c1, r2, c2 — the control pixel pairs the polynomials were fitted to, px.
    laser
        The learned :class:`~omnid.core.laser.LaserModel` (beams' floor points, source), or
        None (a calibration made without the laser, e.g. from known pairs in a test).
    residuals
        Named residuals reached (px, mm, fractions), e.g. ``row_rms_px``, ``disparity_rms_px``,
        ``source_line_rms_mm``.
    """

    rig: StereoRig
    row_coeffs: tuple[float, float]
    col_coeffs: tuple[float, ...]
    control_pairs_px: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))
    laser: LaserModel | None = None
    residuals: dict[str, float] = field(default_factory=dict)
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        if len(self.row_coeffs) != 2 or len(self.col_coeffs) != 11:
            raise ValueError("Calibration: need 2 row and 11 column polynomial coefficients")

    @property
    def floor_depth_mm(self) -> float:
        """Depth H of the floor below the mirrors, mm."""
        return self.rig.floor_depth_mm

    @property
    def baseline_mm(self) -> float:
        """Distance D between the mirror axes, mm."""
        return self.rig.baseline_mm

    @property
    def pixel_sigma_px(self) -> float:
        """The dots' measured scatter per image coordinate, px: the floor pairs' row residual
        over √2 (two cameras), at least 0.05 px (a real detector is never better)."""
        return max(0.05, float(self.residuals.get("row_rms_px", 0.1)) / math.sqrt(2.0))

    # -- YAML -------------------------------------------------------------------------------

    def to_mapping(self) -> dict[str, Any]:
        """Plain data in the ``format_version: 2`` layout."""

        def cam(c: MirrorCamera) -> dict[str, Any]:
            return {
                "center_row_px": float(c.center_row_px),
                "center_col_px": float(c.center_col_px),
                "y_mm": float(c.y_mm),
                "f_over_k_px": float(c.f_over_k_px),
                "rotation_rad": float(c.rotation_rad),
                "disk_radius_px": float(c.disk_radius_px),
                "image_shape": [int(c.image_shape[0]), int(c.image_shape[1])],
            }

        las = self.laser
        return {
            "format_version": FORMAT_VERSION,
            "floor_depth_mm": float(self.rig.floor_depth_mm),
            "cam1": cam(self.rig.cam1),
            "cam2": cam(self.rig.cam2),
            "row_coeffs": [float(v) for v in self.row_coeffs],
            "col_coeffs": [float(v) for v in self.col_coeffs],
            "control_pairs_px": [[round(float(v), 4) for v in p] for p in self.control_pairs_px],
            "laser": None
            if las is None
            else {
                "source_mm": [float(v) for v in las.source_mm],
                "source_sigma_mm": [float(v) for v in las.source_sigma_mm],
                "source_known": bool(las.source_known),
                "floor_xy_mm": [[round(float(v), 3) for v in p[:2]] for p in las.floor_mm],
                "floor_sigma_mm": [round(float(v), 4) for v in las.floor_sigma_mm],
            },
            "residuals": {k: float(v) for k, v in self.residuals.items()},
        }

    def save(self, path: str | Path) -> None:
        """Write the calibration as YAML, atomically (temporary file in the same folder, synced,
        renamed; permissions as the umask says). An unwritable place raises ``InputError``
        naming ``path``."""
        from omnid.io_images import write_bytes_atomic

        text = yaml.safe_dump(self.to_mapping(), sort_keys=False, default_flow_style=None)
        write_bytes_atomic(path, text.encode("utf-8"), fsync=True)

    @classmethod
    def from_mapping(cls, data: Any, source: str = "calibration") -> Calibration:
        """Build from plain data; :class:`ConfigError` names the offending key."""
        version = data.get("format_version") if isinstance(data, dict) else None
        if isinstance(version, int) and version < FORMAT_VERSION:
            raise ConfigError(
                f"format_version: {version} is an older calibration (it assumed a regular laser "
                f"lattice); recalibrate with `omnid calibrate` (format {FORMAT_VERSION})"
            )
        f = from_mapping(_CalibrationFile, data)
        if f.format_version != FORMAT_VERSION:
            raise ConfigError(
                f"format_version: unsupported version {f.format_version} (known: {FORMAT_VERSION})"
            )
        cams = []
        for name, c in (("cam1", f.cam1), ("cam2", f.cam2)):
            try:
                cams.append(
                    MirrorCamera(
                        c.center_row_px,
                        c.center_col_px,
                        c.y_mm,
                        c.f_over_k_px,
                        c.rotation_rad,
                        c.disk_radius_px,
                        c.image_shape,
                    )
                )
            except ValueError as exc:
                raise ConfigError(f"{name}: {exc}") from None
        try:
            rig = StereoRig(cams[0], cams[1], f.floor_depth_mm)
        except ValueError as exc:
            raise ConfigError(f"cam2.y_mm / floor_depth_mm: {exc}") from None
        if len(f.row_coeffs) != 2:
            raise ConfigError(f"row_coeffs: expected 2 numbers, got {len(f.row_coeffs)}")
        if len(f.col_coeffs) != 11:
            raise ConfigError(f"col_coeffs: expected 11 numbers, got {len(f.col_coeffs)}")
        pairs = np.array(f.control_pairs_px, dtype=np.float64).reshape(-1, 4)
        laser = None
        if f.laser is not None:
            lf = f.laser
            xy = np.array(lf.floor_xy_mm, dtype=np.float64).reshape(-1, 2)
            if len(lf.floor_sigma_mm) != len(xy):
                raise ConfigError(
                    f"laser.floor_sigma_mm: {len(lf.floor_sigma_mm)} values for {len(xy)} beams"
                )
            try:
                laser = LaserModel(
                    rig.floor_depth_mm,
                    np.column_stack([xy, np.full(len(xy), rig.floor_depth_mm)]),
                    np.array(lf.floor_sigma_mm, dtype=np.float64),
                    lf.source_mm,
                    lf.source_sigma_mm,
                    lf.source_known,
                )
            except ValueError as exc:
                raise ConfigError(f"laser: {exc}") from None
        return cls(
            rig=rig,
            row_coeffs=(f.row_coeffs[0], f.row_coeffs[1]),
            col_coeffs=tuple(f.col_coeffs),
            control_pairs_px=pairs,
            laser=laser,
            residuals=dict(f.residuals),
        )

    @classmethod
    def load(cls, path: str | Path) -> Calibration:
        """Read a calibration YAML file; a bad file raises :class:`ConfigError` naming file and key."""
        data = load_yaml(path)
        try:
            return cls.from_mapping(data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None


@dataclass(frozen=True)
class _CameraFile:
    center_row_px: float
    center_col_px: float
    y_mm: float
    f_over_k_px: float
    rotation_rad: float
    disk_radius_px: float
    image_shape: tuple[int, int]


@dataclass(frozen=True)
class _LaserFile:
    source_mm: tuple[float, float, float]
    source_sigma_mm: tuple[float, float, float]
    source_known: bool
    floor_xy_mm: tuple[tuple[float, float], ...]
    floor_sigma_mm: tuple[float, ...]


@dataclass(frozen=True)
class _CalibrationFile:
    format_version: int
    floor_depth_mm: float
    cam1: _CameraFile
    cam2: _CameraFile
    row_coeffs: tuple[float, ...]
    col_coeffs: tuple[float, ...]
    control_pairs_px: tuple[tuple[float, float, float, float], ...] = ()
    laser: _LaserFile | None = None
    residuals: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Step 1: the mirror disk
# --------------------------------------------------------------------------------------------


def fit_mirror_disk(
    image: NDArray, threshold: float | None = None
) -> tuple[float, float, float, float]:
    """Circle fitted to the edge of the bright mirror disk: (row_px, col_px, radius_px, rms_px).

    Outside the disk the image is dark. Edge points on the image border (where the disk is
    clipped) are ignored; the algebraic (Kåsa) fit is repeated once without outliers (> 3 MAD).
    Raises :class:`CalibrationError` when no disk is found.
    """
    gray = to_gray(image)
    if threshold is None:
        flat = np.sort(gray.ravel())
        dark_part = flat[: max(len(flat) // 5, 1)]
        dark = float(np.median(dark_part))
        noise = 1.4826 * float(np.median(np.abs(dark_part - dark))) + 0.5
        bright = float(np.median(flat[len(flat) // 2 :]))
        if bright - dark < 10.0:
            raise CalibrationError(
                f"no mirror disk: bright and dark parts differ by {bright - dark:.1f} gray levels"
            )
        # Just above the dark level: the disk edge is a step, so the binary disk does not move
        # with the brightness of the scene seen near the edge.
        threshold = dark + max(6.0 * noise, 0.1 * (bright - dark))
    bw0 = (gray > threshold).astype(np.uint8)
    bw = cv2.morphologyEx(bw0, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bw, connectivity=8)
    if n < 2:
        raise CalibrationError("no mirror disk: the mask image is dark everywhere")
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    blob = (labels == biggest).astype(np.uint8)
    contours, _ = cv2.findContours(blob, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = np.vstack([c.reshape(-1, 2) for c in contours]).astype(np.float64)  # (x=col, y=row)
    rows, cols = gray.shape
    keep = (pts[:, 0] > 1) & (pts[:, 0] < cols - 2) & (pts[:, 1] > 1) & (pts[:, 1] < rows - 2)
    pts = pts[keep]
    if len(pts) < 20:
        raise CalibrationError("no mirror disk: too little of its edge is inside the image")
    sel = np.ones(len(pts), dtype=bool)
    for _ in range(2):
        x, y = pts[sel, 0], pts[sel, 1]
        A = np.column_stack([2 * x, 2 * y, np.ones_like(x)])
        sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
        cx, cy = sol[0], sol[1]
        rad = math.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0))
        res = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy) - rad
        mad = float(np.median(np.abs(res[sel] - np.median(res[sel])))) + 1e-6
        sel = np.abs(res) <= max(3.0 * 1.4826 * mad, 1.0)
    rms = float(np.sqrt(np.mean(res[sel] ** 2)))
    # The contour runs along the outermost bright pixels: the edge lies half a pixel outside.
    return float(cy), float(cx), float(rad + 0.5), rms


# --------------------------------------------------------------------------------------------
# Step 2-4: rotation, scale, pairing and the robust linear fit
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Step 3: the robust linear fit of f/K and rotation
# --------------------------------------------------------------------------------------------


def _offsets(cam: MirrorCamera, rc: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.column_stack([rc[:, 0] - cam.center_row_px, rc[:, 1] - cam.center_col_px])


def _linear_system(
    uv1: NDArray[np.float64], uv2: NDArray[np.float64], d_over_h: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rows of A·(A1, B1, A2, B2) = b: rows agree, disparity = D/H (slope units)."""
    u1, v1, u2, v2 = uv1[:, 0], uv1[:, 1], uv2[:, 0], uv2[:, 1]
    z = np.zeros_like(u1)
    row_eq = np.column_stack([u1, v1, -u2, -v2])
    col_eq = np.column_stack([v1, -u1, -v2, u2])
    A = np.vstack([row_eq, col_eq])
    b = np.concatenate([z, np.full_like(u1, d_over_h)])
    return A, b


def _residuals_px(
    sol: NDArray[np.float64], uv1: NDArray[np.float64], uv2: NDArray[np.float64], d_over_h: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Row and disparity residuals (px at camera 1's scale) of the pairs under ``sol``."""
    A1, B1, A2, B2 = sol
    f1 = 1.0 / math.hypot(A1, B1)
    u1, v1, u2, v2 = uv1[:, 0], uv1[:, 1], uv2[:, 0], uv2[:, 1]
    row = (A1 * u1 + B1 * v1 - A2 * u2 - B2 * v2) * f1
    col = (-B1 * u1 + A1 * v1 + B2 * u2 - A2 * v2 - d_over_h) * f1
    return row, col


def _ransac_fit(
    uv1: NDArray[np.float64],
    uv2: NDArray[np.float64],
    d_over_h: float,
    settings: CalibrationSettings,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    rng = np.random.default_rng(settings.seed)
    sol = np.zeros(4)
    n = len(uv1)
    best_inl = np.zeros(n, dtype=bool)
    for _ in range(settings.ransac_iterations):
        pick = rng.choice(n, size=3, replace=False)
        A, b = _linear_system(uv1[pick], uv2[pick], d_over_h)
        sol = np.asarray(np.linalg.lstsq(A, b, rcond=None)[0], dtype=np.float64)
        if not np.all(np.isfinite(sol)) or math.hypot(sol[0], sol[1]) == 0:
            continue
        row, col = _residuals_px(sol, uv1, uv2, d_over_h)
        inl = np.hypot(row, col) < settings.inlier_px
        if inl.sum() > best_inl.sum():
            best_inl = inl
    if best_inl.sum() < 3:
        best_inl = np.ones(n, dtype=bool)
    for _ in range(3):  # least squares on the inliers, then re-select them
        A, b = _linear_system(uv1[best_inl], uv2[best_inl], d_over_h)
        sol = np.asarray(np.linalg.lstsq(A, b, rcond=None)[0], dtype=np.float64)
        row, col = _residuals_px(sol, uv1, uv2, d_over_h)
        new = np.hypot(row, col) < settings.inlier_px
        if new.sum() < 3 or np.array_equal(new, best_inl):
            break
        best_inl = new
    return sol, best_inl


def _mutual_nearest(
    p: NDArray[np.float64], q: NDArray[np.float64], tol: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index pairs (i, j) where q[j] is p[i]'s nearest and vice versa, closer than ``tol``."""
    if len(p) == 0 or len(q) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    d = np.hypot(p[:, None, 0] - q[None, :, 0], p[:, None, 1] - q[None, :, 1])
    j = np.argmin(d, axis=1)
    i_back = np.argmin(d, axis=0)
    i = np.arange(len(p))
    ok = (i_back[j] == i) & (d[i, j] < tol)
    return i[ok], j[ok]


# --------------------------------------------------------------------------------------------
# Step 2: registration of the two floor dot sets (no pattern assumed)
# --------------------------------------------------------------------------------------------


def _rotate(v: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    """Offsets (N, 2) (row, col) turned by ``angle`` (the :class:`MirrorCamera` convention)."""
    ca, sa = math.cos(angle), math.sin(angle)
    return np.column_stack([ca * v[:, 0] - sa * v[:, 1], sa * v[:, 0] + ca * v[:, 1]])


def _window_pairs(
    q1: NDArray[np.float64],
    o2: NDArray[np.float64],
    order2: NDArray[np.intp],
    row_lo: float,
    row_hi: float,
    col_lo: float,
    col_hi: float,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """All (i, j, o2[j] − q1[i]) whose difference lies in the window (``order2`` sorts o2 by row)."""
    rows2 = o2[order2, 0]
    lo = np.searchsorted(rows2, q1[:, 0] + row_lo, side="left")
    hi = np.searchsorted(rows2, q1[:, 0] + row_hi, side="right")
    cnt = np.maximum(hi - lo, 0)
    i = np.repeat(np.arange(len(q1)), cnt)
    start = np.repeat(np.cumsum(cnt) - cnt, cnt)
    j = order2[np.arange(int(cnt.sum())) - start + np.repeat(lo, cnt)]
    diff = o2[j] - q1[i]
    ok = (diff[:, 1] >= col_lo) & (diff[:, 1] <= col_hi)
    return i[ok], j[ok], diff[ok]


def _vote(
    o1: NDArray[np.float64],
    o2: NDArray[np.float64],
    order2: NDArray[np.intp],
    scale: float,
    angle: float,
    window: tuple[float, float, float],
) -> tuple[int, float, float]:
    """Votes for the best translation under (scale, angle): (votes, t_row, t_col).

    Differences o₂ − s·R(φ)·o₁ inside the window are counted in 0.5 px bins, summed over 2x2
    neighbouring bins (a 1 px kernel), one vote per camera-1 dot and bin pair at most."""
    row_hi, col_lo, col_hi = window
    q1 = _rotate(o1, angle) * scale
    _, _, diff = _window_pairs(q1, o2, order2, -row_hi, row_hi, col_lo, col_hi)
    if len(diff) == 0:
        return 0, 0.0, 0.0
    nr = math.ceil(2 * row_hi / 0.5) + 2
    nc = math.ceil((col_hi - col_lo) / 0.5) + 2
    br = np.floor((diff[:, 0] + row_hi) / 0.5).astype(np.int64)
    bc = np.floor((diff[:, 1] - col_lo) / 0.5).astype(np.int64)
    hist = np.bincount(br * nc + bc, minlength=nr * nc).reshape(nr, nc)
    box = hist[:-1, :-1] + hist[1:, :-1] + hist[:-1, 1:] + hist[1:, 1:]
    kr, kc = np.unravel_index(int(np.argmax(box)), box.shape)
    return int(box[kr, kc]), (kr + 1) * 0.5 - row_hi, (kc + 1) * 0.5 + col_lo


def _register_floor(
    o1: NDArray[np.float64],
    o2: NDArray[np.float64],
    d_over_h: float,
    s: CalibrationSettings,
) -> tuple[NDArray[np.intp], NDArray[np.intp], dict[str, float]]:
    """Pairs (i1, i2) of floor dots under the best similarity o₂ ≈ s·R(φ)·o₁ + t.

    The translation t is voted (:func:`_vote`) among the pairs whose difference lies in the
    window the priors allow (|t| = F₂·D/H within the f/K tolerance, turned by at most
    ``max_rotation_rad``), for (s, φ) on a grid: first with the dots near the centre only (a
    coarse grid suffices there), then around the ten best with all dots on a grid fine enough
    that the disk's rim moves by < 0.8 px between neighbours. Raises :class:`CalibrationError`
    when another translation comes close in votes (a pattern too regular to tell the disparity).
    """
    f_lo = s.f_over_k_prior_px * (1 - s.f_over_k_tolerance)
    f_hi = s.f_over_k_prior_px * (1 + s.f_over_k_tolerance)
    rot = s.max_rotation_rad
    window = (
        f_hi * d_over_h * math.sin(rot) + 1.0,
        -f_hi * d_over_h - 1.0,
        -f_lo * d_over_h * math.cos(rot) + 1.0,
    )
    order2 = np.argsort(o2[:, 0], kind="stable")
    r1 = np.hypot(o1[:, 0], o1[:, 1])
    radius = float(r1.max()) if len(o1) else 1.0
    # the two cameras' scales differ by no more than twice the per-camera tolerance allows
    s_span = min(2.0 * s.f_over_k_tolerance, 0.2)
    inner_r = max(min(radius, 110.0), float(np.sort(r1)[min(len(r1) - 1, 40)]))
    inner = r1 <= inner_r
    coarse = 0.8 / inner_r
    hyps: list[tuple[int, float, float, float, float]] = []
    for ang in np.arange(-2 * rot, 2 * rot + 1e-9, coarse):
        for sc in np.arange(1.0 - s_span, 1.0 + s_span + 1e-9, coarse):
            v, tr, tc = _vote(o1[inner], o2, order2, float(sc), float(ang), window)
            hyps.append((v, float(sc), float(ang), tr, tc))
    hyps.sort(key=lambda h: -h[0])
    fine = 0.8 / max(radius, 50.0)
    refined: list[tuple[int, float, float, float, float]] = []
    for _, sc0, ang0, _, _ in hyps[:10]:
        for ang in ang0 + np.arange(-coarse, coarse + 1e-9, fine):
            for sc in sc0 + np.arange(-coarse, coarse + 1e-9, fine):
                v, tr, tc = _vote(o1, o2, order2, float(sc), float(ang), window)
                refined.append((v, float(sc), float(ang), tr, tc))
    if not refined or (refined[0][0] == 0 and max(h[0] for h in refined) == 0):
        raise CalibrationError("no floor pairing: no dot of camera 2 lies where camera 1's would")
    refined.sort(key=lambda h: -h[0])
    votes, sc, ang, tr, tc = refined[0]
    # Any hypothesis with a clearly different translation that comes close in votes: ambiguous.
    rival = max((h[0] for h in refined[1:] if math.hypot(h[3] - tr, h[4] - tc) > 3.0), default=0)
    q1 = _rotate(o1, ang) * sc + np.array([tr, tc])
    i1, i2 = _mutual_nearest(q1, o2, 1.5)
    info = {"register_votes": float(votes), "register_rival_votes": float(rival)}
    if rival > 0.8 * votes:
        raise CalibrationError(
            f"the floor dots pair two ways ({votes} and {rival} votes): the pattern is too "
            "regular to tell the disparity; give the scale prior (f_over_k_prior_px) more exactly"
        )
    return i1, i2, info


# --------------------------------------------------------------------------------------------
# Step 5: the beams' floor points
# --------------------------------------------------------------------------------------------


def _floor_points(cam: MirrorCamera, rc: NDArray[np.float64], depth_mm: float) -> NDArray:
    """(N, 2) X, Y on the plane ``depth_mm`` below the mirrors seen at pixels ``rc`` of ``cam``."""
    sl = cam.ray_slopes(rc)
    return np.column_stack([sl[:, 0] * depth_mm, sl[:, 1] * depth_mm + cam.y_mm])


def _floor_beams(
    rig: StereoRig,
    rc1: NDArray[np.float64],
    rc2: NDArray[np.float64],
    i1: NDArray[np.intp],
    i2: NDArray[np.intp],
    sigma_px: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], int]:
    """Floor point (K, 3) and its σ (K,) mm of every beam the floor capture shows.

    A pair gives the mean of its two cameras' floor points; a dot seen by one camera only is a
    beam too when the other camera could not have shown it (its floor point images outside, or
    within 3 px of the rim of, that camera's disk) — elsewhere an unpaired dot is not trusted.
    Returns also the number of single-camera beams.
    """
    H = rig.floor_depth_mm
    f = 0.5 * (rig.cam1.f_over_k_px + rig.cam2.f_over_k_px)
    sig1 = sigma_px * H / f  # mm on the floor per px of centre error
    p1 = _floor_points(rig.cam1, rc1[i1], H)
    p2 = _floor_points(rig.cam2, rc2[i2], H)
    pts = [0.5 * (p1 + p2)]
    sig = [np.full(len(i1), sig1 / math.sqrt(2.0))]
    singles = 0
    for cam, other, rc, used in ((rig.cam1, rig.cam2, rc1, i1), (rig.cam2, rig.cam1, rc2, i2)):
        free = np.ones(len(rc), dtype=bool)
        free[used] = False
        if not free.any():
            continue
        xy = _floor_points(cam, rc[free], H)
        unseen = ~other.in_disk(other.project(np.column_stack([xy, np.full(len(xy), H)])), 3.0)
        pts.append(xy[unseen])
        sig.append(np.full(int(unseen.sum()), sig1))
        singles += int(unseen.sum())
    xy = np.vstack(pts)
    return np.column_stack([xy, np.full(len(xy), H)]), np.concatenate(sig), singles


# --------------------------------------------------------------------------------------------
# Step 6: the laser's source from the extra captures
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _OffFloor:
    """Stereo pairs of one capture read off the floor: Q (N, 3) mm, its σ (N,) mm, dot ids."""

    q: NDArray[np.float64]
    sigma_mm: NDArray[np.float64]
    dot1: NDArray[np.intp]


def _off_floor_pairs(
    rig: StereoRig, d1: NDArray[np.float64], d2: NDArray[np.float64], sigma_px: float
) -> _OffFloor:
    """Every stereo pair (rows agree, a plausible depth) that triangulates off the floor."""
    from omnid.core.matching import stereo_candidates
    from omnid.core.triangulate import triangulate

    i, j = stereo_candidates(rig, d1, d2, 4.0 * math.sqrt(2.0) * sigma_px + 0.3)
    xyz, cov = triangulate(rig, np.column_stack([d1[i, :2], d2[j, :2]]), "best", sigma_px)
    H = rig.floor_depth_mm
    sz = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
    near_floor = np.abs(xyz[:, 2] - H) <= np.maximum(10.0, 4.0 * sz)
    off = np.isfinite(xyz).all(axis=1) & (np.abs(xyz[:, 2] - H) > np.maximum(25.0, 5.0 * sz))
    # A dot that pairs at the floor is a floor dot: its other pairings are wrong, and they
    # would all point back at its own mirror (the line from its beam's floor point through
    # any point of its viewing ray is that ray).
    on_floor1 = np.zeros(len(d1), dtype=bool)
    on_floor2 = np.zeros(len(d2), dtype=bool)
    on_floor1[i[near_floor]] = True
    on_floor2[j[near_floor]] = True
    off &= ~on_floor1[i] & ~on_floor2[j]
    sig = np.sqrt(np.maximum(np.trace(cov, axis1=1, axis2=2), 0.0) / 3.0)
    return _OffFloor(xyz[off], sig[off], i[off].astype(np.intp))


def _source_lines(
    off: _OffFloor, floor_mm: NDArray[np.float64], H: float, box: NDArray[np.float64]
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(pair, beam) hypotheses whose line P_k → Q, extended upward, passes through the prior
    box of the source: the beams whose floor points the box's corners project to from Q."""
    corners = (
        np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
        * box[None, :]
        + np.asarray(SOURCE_PRIOR_MM)[None, :]
    )
    q = off.q
    above = q[:, 2] - corners[:, 2].max() > 20.0  # the source must lie above the dot
    out_p, out_k = [], []
    for n in np.flatnonzero(above):
        qq = q[n]
        lever = (H - qq[2]) / (qq[2] - corners[:, 2])
        proj = qq[None, :2] + lever[:, None] * (qq[None, :2] - corners[:, :2])
        lo, hi = proj.min(axis=0) - 30.0, proj.max(axis=0) + 30.0
        k = np.flatnonzero(
            (floor_mm[:, 0] >= lo[0])
            & (floor_mm[:, 0] <= hi[0])
            & (floor_mm[:, 1] >= lo[1])
            & (floor_mm[:, 1] <= hi[1])
        )
        out_p.append(np.full(len(k), n, dtype=np.intp))
        out_k.append(k.astype(np.intp))
    if not out_p:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    return np.concatenate(out_p), np.concatenate(out_k)


def _line_distance(
    o: NDArray[np.float64], q: NDArray[np.float64], p: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance (N,) mm of the point o from the lines through q[n] and p[n]."""
    u = p - q
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = o[None, :] - q
    return np.asarray(np.linalg.norm(w - np.sum(w * u, axis=1)[:, None] * u, axis=1))


def _fit_point_to_lines(
    q: NDArray[np.float64], p: NDArray[np.float64], weight: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Weighted least-squares point nearest the lines q→p, and the normal matrix's inverse."""
    u = p - q
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    proj = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
    A = np.einsum("n,nij->ij", weight, proj)
    b = np.einsum("n,nij,nj->i", weight, proj, q)
    inv = np.linalg.inv(A)
    return inv @ b, inv


#: Two readings of the laser's source this near (mm) are one: the vote's runner-up is sought
#: beyond it, and a runner-up refined back within it of the winner is dropped.
_DISTINCT_SOURCE_MM = 25.0


def source_candidates(
    rig: StereoRig,
    floor_mm: NDArray[np.float64],
    extras: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
    sigma_px: float,
    settings: CalibrationSettings | None = None,
) -> list[tuple[NDArray[np.float64], NDArray[np.float64], dict[str, float]]]:
    """The points the extras' dots' lines meet (see the module docstring, step 6), each
    refined as (O (3,), its 1-σ per axis (3,) mm, residuals): the vote's winner first, then
    the best point elsewhere (beyond 25 mm) when enough lines pass it too — another reading
    of the same dots (on one plane, a pairing shifted by a beam gives another plane from
    another source), for the caller to judge by how well each explains the captures.

    Raises :class:`CalibrationError` when the extras show fewer than ``min_source_dots`` dots
    off the floor, or when no point is passed by the lines of that many dots.
    """
    s = settings or CalibrationSettings()
    H = rig.floor_depth_mm
    box = np.asarray(s.source_box_mm, dtype=np.float64)
    qs, sigs, dots, ps, ks = [], [], [], [], []
    n_off = 0
    offset = 0
    for d1, d2 in extras:
        off = _off_floor_pairs(rig, d1, d2, sigma_px)
        n_off += len(np.unique(off.dot1))
        pair, k = _source_lines(off, floor_mm, H, box)
        qs.append(off.q[pair])
        sigs.append(off.sigma_mm[pair])
        dots.append(off.dot1[pair] + offset)  # dot ids unique over all extras
        ks.append(k)
        ps.append(floor_mm[k])
        offset += len(d1)
    q = np.vstack(qs) if qs else np.zeros((0, 3))
    if n_off < s.min_source_dots or len(q) == 0:
        raise CalibrationError(
            f"the extra captures show {n_off} dots off the floor (need {s.min_source_dots}): "
            "capture a box or a wall 0.5-1.5 m ahead, filling part of the view, and pass it "
            "with --extra DIR"
        )
    p = np.vstack(ps)
    sig_q = np.concatenate(sigs)
    dot = np.concatenate(dots)
    # Vote: each line crosses the box's Z slices; one vote per dot per cell.
    cell = s.source_cell_mm
    zs = np.arange(-box[2], box[2] + 1e-9, cell) + SOURCE_PRIOR_MM[2]
    t = (zs[None, :] - q[:, 2:3]) / (p[:, 2:3] - q[:, 2:3])  # (L, Z)
    ox = q[:, 0:1] + t * (p[:, 0:1] - q[:, 0:1]) - SOURCE_PRIOR_MM[0]
    oy = q[:, 1:2] + t * (p[:, 1:2] - q[:, 1:2]) - SOURCE_PRIOR_MM[1]
    nx = round(2 * box[0] / cell) + 1
    ny = round(2 * box[1] / cell) + 1
    ix = np.rint((ox + box[0]) / cell).astype(np.int64)
    iy = np.rint((oy + box[1]) / cell).astype(np.int64)
    iz = np.broadcast_to(np.arange(len(zs))[None, :], ix.shape)
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    cells = (iz[inside] * ny + iy[inside]) * nx + ix[inside]
    owner = np.broadcast_to(dot[:, None], ix.shape)[inside]
    key = np.unique(cells * (offset + 1) + owner)
    counts = np.bincount(key // (offset + 1), minlength=len(zs) * ny * nx).astype(np.float64)
    grid = counts.reshape(len(zs), ny, nx)
    # a 3x3x3 box sum: a point between cells collects its votes
    sm = grid.copy()
    for axis in range(3):
        sm = sm + np.roll(sm, 1, axis) + np.roll(sm, -1, axis)
    kz, ky, kx = np.unravel_index(int(np.argmax(sm)), sm.shape)
    # How clear the winner stands: the best vote elsewhere (beyond 25 mm) over the winner's. A
    # second point many lines also meet is another reading of the same dots (a pairing shifted
    # by one beam on a plane gives another plane, and another source, that fit as well).
    peak = float(sm[kz, ky, kx])
    rad = math.ceil(_DISTINCT_SOURCE_MM / cell)
    rest = sm.copy()
    rest[
        max(kz - rad, 0) : kz + rad + 1,
        max(ky - rad, 0) : ky + rad + 1,
        max(kx - rad, 0) : kx + rad + 1,
    ] = 0.0
    runner_up = float(rest.max()) / peak if peak > 0 else 1.0

    def cell_point(k: tuple[int, int, int]) -> NDArray[np.float64]:
        kz_, ky_, kx_ = k
        return np.array(
            [
                kx_ * cell - box[0] + SOURCE_PRIOR_MM[0],
                ky_ * cell - box[1] + SOURCE_PRIOR_MM[1],
                zs[kz_],
            ]
        )

    starts = [cell_point((int(kz), int(ky), int(kx)))]
    if runner_up > 0:
        second = np.unravel_index(int(np.argmax(rest)), rest.shape)
        starts.append(cell_point((int(second[0]), int(second[1]), int(second[2]))))
    found: list[tuple[NDArray[np.float64], NDArray[np.float64], dict[str, float]]] = []
    for n_start, o in enumerate(starts):
        refined = _refine_source(o, q, p, sig_q, dot, cell, s.min_source_dots)
        if refined is None:
            if n_start == 0:
                raise CalibrationError(
                    f"the {n_off} dots off the floor in the extra captures do not point back to "
                    f"one laser source (need {s.min_source_dots} dots that agree); are they "
                    "captures of this rig, with the laser unmoved since the floor capture?"
                )
            continue
        o, sigma_o, line_rms, n_in = refined
        if any(np.linalg.norm(o - f[0]) <= _DISTINCT_SOURCE_MM for f in found):
            continue  # (refined back to a point already found)
        info = {
            "source_dots": float(n_in),
            "source_off_floor_dots": float(n_off),
            "source_line_rms_mm": line_rms,
            "source_runner_up": runner_up,
        }
        found.append((o, sigma_o, info))
    return found


def locate_source(
    rig: StereoRig,
    floor_mm: NDArray[np.float64],
    extras: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
    sigma_px: float,
    settings: CalibrationSettings | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], dict[str, float]]:
    """The laser's source O (3,), its 1-σ per axis (3,) mm and residuals, from the dots (d1, d2)
    of extra captures (see the module docstring, step 6): the point most dots' lines meet.

    Raises :class:`CalibrationError` when the extras show fewer than ``min_source_dots`` dots
    off the floor, or when no point is passed by the lines of that many dots.
    """
    return source_candidates(rig, floor_mm, extras, sigma_px, settings)[0]


def _refine_source(
    o: NDArray[np.float64],
    q: NDArray[np.float64],
    p: NDArray[np.float64],
    sig_q: NDArray[np.float64],
    dot: NDArray[np.intp],
    cell: float,
    min_dots: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, int] | None:
    """From a voted point ``o``: each dot's nearest line, inliers within a shrinking tolerance,
    weighted least squares. (O, its 1-σ per axis, the lines' rms distance, inliers), or None
    when fewer than ``min_dots`` dots' lines pass it."""
    tol = 3.0 * cell
    inl = np.zeros(0, dtype=np.intp)
    inv = np.eye(3)
    w = np.ones(0)
    for _ in range(6):
        dist = _line_distance(o, q, p)
        lever = np.linalg.norm(o[None, :] - q, axis=1) / np.linalg.norm(p - q, axis=1)
        sig_line = np.maximum(sig_q * (1.0 + lever), 0.2)
        order = np.lexsort((dist / sig_line, dot))
        first = np.concatenate([[True], dot[order][1:] != dot[order][:-1]])
        cand = order[first]
        cand = cand[dist[cand] < np.maximum(tol, 4.0 * sig_line[cand])]
        if len(cand) < min_dots:
            break
        inl = cand
        w = 1.0 / sig_line[inl] ** 2
        o, inv = _fit_point_to_lines(q[inl], p[inl], w)
        tol = max(tol / 2.0, 1.0)
    if len(inl) < min_dots:
        return None
    dist = _line_distance(o, q[inl], p[inl])
    chi2 = float(np.sum(w * dist**2)) / max(len(inl) - 3, 1)
    sigma_o = np.sqrt(np.diag(inv) * max(chi2, 1.0))
    return o, sigma_o, float(np.sqrt(np.mean(dist**2))), len(inl)


def _beams_off_floor(
    rig: StereoRig,
    laser: LaserModel,
    extra_dots: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
    sigma_px: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Beams the floor capture could not show, learned from the extras: (K', 3) floor points
    and (K',) σ, mm.

    A beam that meets the floor outside both mirrors' views (or within 3 px of a disk's rim)
    can still light a box or a wall. An extra's dot that no known beam explains, whose only
    off-floor stereo pair gives Q, lies on the beam from the (now known) source through Q; that
    beam's floor point must lie where neither camera could have seen it on the floor — else the
    floor capture would show it, and the dot is something else (a ghost, a wrong pair).
    """
    from omnid.core.matching import MatchSettings, match_triples

    H = rig.floor_depth_mm
    o = np.asarray(laser.source_mm)
    so = float(np.linalg.norm(laser.source_sigma_mm))
    pts, sig = [], []
    for d1, d2 in extra_dots:
        m = match_triples(rig, laser, sigma_px, d1, d2, MatchSettings())
        off = _off_floor_pairs(rig, d1, d2, sigma_px)
        free = ~np.isin(off.dot1, m.i1)
        ids, counts = np.unique(off.dot1, return_counts=True)
        single = np.isin(off.dot1, ids[counts == 1])
        sel = free & single & (off.q[:, 2] > o[2] + 50.0)
        q, sq = off.q[sel], off.sigma_mm[sel]
        lever = (H - o[2]) / (q[:, 2] - o[2])
        floor_xy = o[None, :2] + (q[:, :2] - o[None, :2]) * lever[:, None]
        p3 = np.column_stack([floor_xy, np.full(len(q), H)])
        unseen = ~rig.cam1.in_disk(rig.cam1.project(p3), 3.0)
        unseen &= ~rig.cam2.in_disk(rig.cam2.project(p3), 3.0)
        pts.append(p3[unseen])
        sig.append((lever * sq + (lever - 1.0) * so)[unseen])
    if not pts:
        return np.zeros((0, 3)), np.zeros(0)
    p_all, s_all = np.vstack(pts), np.concatenate(sig)
    # the same beam in two extras: keep the better-determined copy
    keep = np.ones(len(p_all), dtype=bool)
    order = np.argsort(s_all)
    for n_, a in enumerate(order):
        if keep[a]:
            later = order[n_ + 1 :]
            close = np.hypot(*(p_all[later, :2] - p_all[a, :2]).T) < 3.0 * s_all[a] + 5.0
            keep[later[close]] = False
    return p_all[keep], s_all[keep]


def _detect(
    capture: StereoCapture, detection: DetectionParams | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    # every blend of two spots split: a doubled beam becomes two beams of the model (and
    # perception splits blends near their tracks only, pipeline.split_regions)
    return (
        detect_dots(capture.mask1, capture.base1, "best", detection, True),
        detect_dots(capture.mask2, capture.base2, "best", detection, True),
    )


def source_advice(calib: Calibration) -> str | None:
    """One line saying what to capture when the calibration could not place the laser's source
    (None when it did)."""
    if calib.laser is None or calib.laser.source_known:
        return None
    return (
        "the floor capture alone cannot place the laser's source, so obstacles are matched "
        "less surely: capture a box or a wall 0.5-1.5 m ahead and pass it with --extra DIR"
    )


def calibrate_from_capture(
    capture: StereoCapture,
    floor_depth_mm: float,
    baseline_mm: float,
    settings: CalibrationSettings | None = None,
    detection: DetectionParams | None = None,
    extras: Sequence[StereoCapture] = (),
) -> Calibration:
    """Calibrate the rig from one capture of an empty floor ``floor_depth_mm`` below the mirrors,
    and the laser from it and the ``extras`` (captures of the same rig with dots off the floor).

    See the module docstring for the steps. Raises :class:`CalibrationError` (with the residuals
    reached) when the capture has no dots, is not one horizontal plane, or its depth disagrees
    with ``floor_depth_mm`` beyond the scale prior, and when extras are given but do not place
    the laser's source.
    """
    from omnid.core import matching  # the thesis polynomial fit lives with the matcher

    s = settings or CalibrationSettings()
    if not (math.isfinite(floor_depth_mm) and floor_depth_mm > 0):
        raise CalibrationError(f"floor depth must be positive, got {floor_depth_mm} mm")
    if not (math.isfinite(baseline_mm) and baseline_mm > 0):
        raise CalibrationError(f"baseline must be positive, got {baseline_mm} mm")
    shape = capture.shape
    for n, extra in enumerate(extras, start=1):
        if extra.shape != shape:
            raise CalibrationError(
                f"extra capture {n} is {extra.shape[1]}x{extra.shape[0]} px, the floor capture "
                f"{shape[1]}x{shape[0]} px: not the same rig"
            )
    dots = _detect(capture, detection)
    centres = []
    for k, (mask, d) in enumerate(((capture.mask1, dots[0]), (capture.mask2, dots[1])), start=1):
        try:
            centres.append(fit_mirror_disk(mask, s.disk_threshold))
        except CalibrationError as exc:
            raise CalibrationError(f"camera {k}: {exc}") from None
        if len(d) < s.min_pairs:
            raise CalibrationError(
                f"camera {k}: only {len(d)} laser dots found (need {s.min_pairs}); "
                "is the laser on in the base image?"
            )
    d_over_h = baseline_mm / floor_depth_mm
    o1 = dots[0][:, :2] - np.array(centres[0][:2])
    o2 = dots[1][:, :2] - np.array(centres[1][:2])
    i1, i2, reg = _register_floor(o1, o2, d_over_h, s)
    if len(i1) < s.min_pairs:
        raise CalibrationError(
            f"only {len(i1)} floor dots pair up (need {s.min_pairs}); not an empty floor, or "
            f"not {floor_depth_mm:g} mm below the mirrors?"
        )
    uv1, uv2 = o1[i1], o2[i2]
    sol, inl = _ransac_fit(uv1, uv2, d_over_h, s)
    # Re-pair every dot under the fitted model (the registration's 1.5 px was a first guess).
    f1 = 1.0 / math.hypot(sol[0], sol[1])
    f2 = 1.0 / math.hypot(sol[2], sol[3])
    th1 = math.atan2(sol[1], sol[0])
    th2 = math.atan2(sol[3], sol[2])
    cams = [
        MirrorCamera(c[0], c[1], y, f, th, c[2], shape)
        for c, y, f, th in (
            (centres[0], -0.5 * baseline_mm, f1, th1),
            (centres[1], 0.5 * baseline_mm, f2, th2),
        )
    ]
    pred = cams[1].project(
        np.column_stack(
            [
                _floor_points(cams[0], dots[0][:, :2], floor_depth_mm),
                np.full(len(dots[0]), floor_depth_mm),
            ]
        )
    )
    i1, i2 = _mutual_nearest(pred, dots[1][:, :2], 3.0 * s.inlier_px)
    uv1, uv2 = o1[i1], o2[i2]
    sol, inl = _ransac_fit(uv1, uv2, d_over_h, s)
    row_res, col_res = _residuals_px(sol, uv1, uv2, d_over_h)
    f1 = 1.0 / math.hypot(sol[0], sol[1])
    f2 = 1.0 / math.hypot(sol[2], sol[3])
    th1 = math.atan2(sol[1], sol[0])
    th2 = math.atan2(sol[3], sol[2])
    # Of the dots seen, how many pair up as one floor: an empty floor pairs nearly all of them
    # (those both disks show: a dot near one disk's rim has no partner).
    frac = float(inl.sum()) / min(len(dots[0]), len(dots[1]))
    row_rms = float(np.sqrt(np.mean(row_res[inl] ** 2)))
    col_rms = float(np.sqrt(np.mean(col_res[inl] ** 2)))
    e = col_res[inl] * math.hypot(sol[0], sol[1]) + d_over_h
    with np.errstate(divide="ignore"):
        depth = baseline_mm / e
    depth_rms = float(np.sqrt(np.mean((depth - floor_depth_mm) ** 2)))
    residuals = {
        "row_rms_px": row_rms,
        "disparity_rms_px": col_rms,
        "depth_rms_mm": depth_rms,
        "inlier_fraction": frac,
        "pairs": float(len(i1)),
        "inliers": float(inl.sum()),
        "dots1": float(len(dots[0])),
        "dots2": float(len(dots[1])),
        **reg,
    }
    summary = ", ".join(f"{k}={v:.3g}" for k, v in residuals.items())
    if frac < s.min_inlier_fraction or row_rms > s.max_rms_px or col_rms > s.max_rms_px:
        raise CalibrationError(
            f"the floor capture is not one horizontal plane at {floor_depth_mm:g} mm "
            f"(residuals: {summary})"
        )
    for f in (f1, f2):
        if abs(f / s.f_over_k_prior_px - 1) > s.f_over_k_tolerance:
            raise CalibrationError(
                f"fitted f/K = {f:.1f} px is outside the prior {s.f_over_k_prior_px} px ± "
                f"{100 * s.f_over_k_tolerance:.0f}% (residuals: {summary})"
            )
    cam1 = MirrorCamera(*centres[0][:2], -0.5 * baseline_mm, f1, th1, centres[0][2], shape)
    cam2 = MirrorCamera(*centres[1][:2], 0.5 * baseline_mm, f2, th2, centres[1][2], shape)
    rig = StereoRig(cam1, cam2, floor_depth_mm)
    sigma_px = max(0.05, row_rms / math.sqrt(2.0))
    pi1, pi2 = i1[inl], i2[inl]
    floor_mm, floor_sig, singles = _floor_beams(
        rig, dots[0][:, :2], dots[1][:, :2], pi1, pi2, sigma_px
    )
    laser = LaserModel(floor_depth_mm, floor_mm, floor_sig)
    residuals.update({"beams": float(len(floor_mm)), "beams_one_camera": float(singles)})
    if extras:
        extra_dots = [_detect(x, detection) for x in extras]
        # The vote's winner, and its runner-up when there is one: two readings of the same
        # dots (on a plane, a pairing shifted by a beam gives another plane from another
        # source; their votes can tie). The reading under which the matcher explains more of
        # the extras' dots is kept (the winner on a tie).
        readings: list[tuple[float, int, LaserModel, dict[str, float], dict[str, float]]] = []
        for o, sig_o, info in source_candidates(rig, floor_mm, extra_dots, sigma_px, s):
            placed = laser.with_source(
                (float(o[0]), float(o[1]), float(o[2])),
                (float(sig_o[0]), float(sig_o[1]), float(sig_o[2])),
            )
            more, more_sig = _beams_off_floor(rig, placed, extra_dots, sigma_px)
            if len(more):
                placed = LaserModel(
                    floor_depth_mm,
                    np.vstack([placed.floor_mm, more]),
                    np.concatenate([placed.floor_sigma_mm, more_sig]),
                    placed.source_mm,
                    placed.source_sigma_mm,
                    True,
                )
            fit = _extra_fit(rig, placed, sigma_px, extra_dots)
            info = {**info, "beams_off_floor": float(len(more)), "beams": float(len(placed))}
            readings.append((fit["extra_matched_fraction"], -len(readings), placed, info, fit))
        _, _, laser, info, fit = max(readings, key=lambda t: (t[0], t[1]))
        residuals.update(info)
        residuals.update(fit)
        residuals["source_readings"] = float(len(readings))
        if residuals["extra_matched_fraction"] < s.min_extra_explained:
            raise CalibrationError(
                f"the extra captures do not fit the laser the floor shows (only "
                f"{100 * residuals['extra_matched_fraction']:.0f} % of their dots lie on a "
                "calibrated beam): are they captures of this rig, with the laser unmoved since "
                "the floor capture?"
            )
    # Thesis polynomials (6.12, 6.13) on the control pairs, refined in three steps.
    control = np.column_stack([dots[0][pi1, :2], dots[1][pi2, :2]])
    poly = matching.fit_thesis_polynomials(control, dots[0][:, :2], dots[1][:, :2])
    residuals.update(
        {
            "thesis_row_rms_px": poly.row_rms_px,
            "thesis_col_rms_px": poly.col_rms_px,
            "thesis_pairs": float(len(poly.pairs_px)),
        }
    )
    return Calibration(
        rig=rig,
        row_coeffs=poly.row_coeffs,
        col_coeffs=poly.col_coeffs,
        control_pairs_px=control,
        laser=laser,
        residuals=residuals,
    )


def _extra_fit(
    rig: StereoRig,
    laser: LaserModel,
    sigma_px: float,
    extra_dots: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
) -> dict[str, float]:
    """How the extras' dots fit the learned model: rms track residual of the matched dots (px)
    and the share of dots matched (the same matcher perception runs)."""
    from omnid.core.matching import MatchSettings, match_triples

    res, n_matched, n_dots = [], 0, 0
    for d1, d2 in extra_dots:
        m = match_triples(rig, laser, sigma_px, d1, d2, MatchSettings())
        res.append(m.residual_px)
        n_matched += len(m.i1)
        n_dots += min(len(d1), len(d2))
    r = np.concatenate(res) if res else np.zeros(0)
    return {
        "extra_track_rms_px": float(np.sqrt(np.mean(r**2))) if len(r) else 0.0,
        "extra_matched_fraction": n_matched / max(n_dots, 1),
    }


# --------------------------------------------------------------------------------------------
# The thesis' floor calibration tables (6.3.1.3), for comparison
# --------------------------------------------------------------------------------------------


def _fill_by_neighbours(values: NDArray[np.float64], inside: NDArray[np.bool_]) -> None:
    """Fill NaN pixels inside ``inside`` with the mean of their known 8-neighbours, repeatedly
    (the thesis' arithmetic average of the neighbours' angles), in place."""
    for _ in range(64):
        missing = np.isnan(values) & inside
        if not missing.any():
            return
        known = np.isfinite(values)
        total = cv2.boxFilter(np.where(known, values, 0.0), -1, (3, 3), normalize=False)
        count = cv2.boxFilter(known.astype(np.float64), -1, (3, 3), normalize=False)
        fill = missing & (count > 0)
        if not fill.any():
            return
        values[fill] = total[fill] / count[fill]


def floor_angle_tables(
    calib: Calibration,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per-pixel angle tables θ1 (camera 1), θ2 (camera 2) and δ (camera 1), rad (6.3.1.3).

    Every camera-1 pixel inside the mirror disk is placed on the floor by the equidistance
    principle, eqs. 6.17/6.18 (X = X_ref − R_r·(r − r_ref), Y = Y_ref + R_c·(c − c_ref) with the
    mirror centre as reference pixel, R = H/(f/K) mm per pixel, rotation undone; the column sign
    follows SPEC §2). θ_i is the angle of the floor point seen from mirror i against the Y axis,
    atan2(X, Y − Y_i); δ is its incidence angle, eq. 6.19 (δ = atan(√(X² + (Y − Y_1)²)/H)).
    θ2 is stored at the camera-2 pixel that eqs. 6.12/6.13 match to each camera-1 pixel
    (rounded to integers, as the thesis does); camera-2 pixels left unmatched get the average
    of their neighbours. Pixels outside the disks are NaN.
    """
    rig = calib.rig
    c1, c2 = rig.cam1, rig.cam2
    rows, cols = c1.image_shape
    rr, cc = np.mgrid[0:rows, 0:cols]
    rc = np.column_stack([rr.ravel(), cc.ravel()]).astype(np.float64)
    inside1 = c1.in_disk(rc).reshape(rows, cols)
    inside2 = c2.in_disk(rc).reshape(rows, cols)
    H = rig.floor_depth_mm
    off = c1.ideal_offsets(rc)
    R = H / c1.f_over_k_px  # mm per pixel on the floor (equidistance)
    X = 0.0 - R * off[:, 0]  # eq. 6.17, reference = the mirror centre (X_ref = 0)
    Y = c1.y_mm + R * off[:, 1]  # eq. 6.18, Y_ref = Y_1
    theta1 = np.arctan2(X, Y - c1.y_mm).reshape(rows, cols)
    delta = np.arctan(np.hypot(X, Y - c1.y_mm) / H).reshape(rows, cols)  # eq. 6.19
    theta1[~inside1] = np.nan
    delta[~inside1] = np.nan
    from omnid.core.matching import predict_thesis

    sel = inside1.ravel()
    q2 = np.rint(predict_thesis(calib.row_coeffs, calib.col_coeffs, rc[sel]))
    ok = (q2[:, 0] >= 0) & (q2[:, 0] < rows) & (q2[:, 1] >= 0) & (q2[:, 1] < cols)
    r2 = q2[ok, 0].astype(np.intp)
    k2 = q2[ok, 1].astype(np.intp)
    theta2 = np.full((rows, cols), np.nan)
    theta2[r2, k2] = np.arctan2(X[sel][ok], Y[sel][ok] - c2.y_mm)
    theta2[~inside2] = np.nan
    _fill_by_neighbours(theta2, inside2)
    return theta1, theta2, delta
