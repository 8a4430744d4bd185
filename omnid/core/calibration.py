"""Automatic calibration of the stereo rig from one floor capture (thesis 6.3; SPEC §§2, 6).

No manual clicking: everything is found in one stereo mask/base capture of an empty floor at a
known depth H below the mirrors, with the baseline D known.

1. **Mirror centres** — outside the mirror's disk the image is dark, so a circle fitted to the
   edge of the bright disk in each *mask* image gives the mirror centre (r_m, c_m) and radius.
2. **Rotation about the mirror axis** — the floor dots form a lattice whose rows are image rows
   in an aligned camera; the median direction of neighbour vectors (folded modulo 90°) gives
   each camera's rotation.
3. **Scale f/K and pairing** — after de-rotation, the row lattice step of each camera gives the
   ratio f2/f1. The floor dots of camera 2 are then displaced from those of camera 1 by the
   disparity (f/K)·D/H along the rows (SPEC §2), but the dot lattice is periodic, so the column
   shift is known only modulo one lattice step; the floor-first logic resolves it: the shift
   taken is the one whose f/K lies within ``f_over_k_tolerance`` of the prior (the thesis'
   10.80 mm/px at 1170 mm), and it must be the only one there.
4. **Robust fit** — with pairs found, rows agree and the disparity equals D/H in slope units:
   with A_i = cos θ_i/(f/K)_i, B_i = sin θ_i/(f/K)_i both conditions are *linear* in
   (A1, B1, A2, B2), so RANSAC over pairs plus a final least-squares fit on the inliers gives
   f/K and θ of both cameras. The residuals (px) are kept in the calibration.
5. **Thesis matching polynomials** — the inlier pairs are the control pixel pairs of 6.3.1.1;
   eqs. 6.12/6.13 are fitted to them and refined in the thesis' three steps (2 px, then 1 px
   search neighbourhoods, then final coefficients), see :mod:`omnid.core.matching`.
6. **Laser lattice** — the floor dots triangulate to the slopes (X/Z, Y/Z) of the laser rays;
   a regular lattice fitted to them lets the ``best`` matcher reject pairings that fall between
   laser rays.

A capture with no dots, that is not a single horizontal plane, or whose depth contradicts the
given one raises :class:`~omnid.errors.CalibrationError` with the residuals reached.
:class:`Calibration` is frozen and saved as versioned YAML (``format_version: 1``); ``save``
writes a temporary file and renames it, so a failure never leaves a half-written file.
"""

from __future__ import annotations

import math
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
from omnid.core.types import StereoCapture
from omnid.errors import CalibrationError, ConfigError

FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------
# Settings and the calibration value type
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationSettings:
    """How :func:`calibrate_from_capture` works and what it accepts."""

    f_over_k_prior_px: float = DEFAULT_F_OVER_K_PX  # thesis: 10.80 mm/px at 1170 mm depth
    f_over_k_tolerance: float = 0.15  # accepted relative distance from the prior
    min_pairs: int = 30  # fewer matched floor dots: refuse
    min_inlier_fraction: float = 0.8  # of the dots seen, the fraction pairing as one floor
    inlier_px: float = 0.8  # RANSAC inlier threshold on row/disparity residuals, px
    max_rms_px: float = 0.5  # refuse when the inliers' rms residual is larger, px
    ransac_iterations: int = 200
    seed: int = 0
    disk_threshold: float | None = None  # gray level of the disk edge; None = automatic

    def __post_init__(self) -> None:
        require(self.f_over_k_prior_px > 0, "f_over_k_prior_px", "must be positive")
        require(0 < self.f_over_k_tolerance < 0.5, "f_over_k_tolerance", "must be in (0, 0.5)")
        require(self.min_pairs >= 6, "min_pairs", "must be at least 6")
        require(0 < self.min_inlier_fraction <= 1, "min_inlier_fraction", "must be in (0, 1]")
        require(self.inlier_px > 0, "inlier_px", "must be positive")
        require(self.max_rms_px > 0, "max_rms_px", "must be positive")
        require(self.ransac_iterations >= 1, "ransac_iterations", "must be at least 1")


@dataclass(frozen=True)
class LaserLattice:
    """Regular lattice of laser ray slopes: a = a0 + step_a·l (X/Z), b = b0 + step_b·k (Y/Z).

    ``rows``/``cols`` give the index range (l_min, l_max), (k_min, k_max) seen on the floor.
    """

    a0: float
    step_a: float
    b0: float
    step_b: float
    rows: tuple[int, int]
    cols: tuple[int, int]


@dataclass(frozen=True)
class Calibration:
    """Everything perception needs about the rig, found from one floor capture.

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
    lattice
        The laser ray lattice (slopes) seen on the floor, or None.
    residuals
        Named residuals reached (px, mm, fractions), e.g. ``row_rms_px``, ``disparity_rms_px``.
    """

    rig: StereoRig
    row_coeffs: tuple[float, float]
    col_coeffs: tuple[float, ...]
    control_pairs_px: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))
    lattice: LaserLattice | None = None
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

    # -- YAML -------------------------------------------------------------------------------

    def to_mapping(self) -> dict[str, Any]:
        """Plain data in the ``format_version: 1`` layout."""

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

        lat = self.lattice
        return {
            "format_version": FORMAT_VERSION,
            "floor_depth_mm": float(self.rig.floor_depth_mm),
            "cam1": cam(self.rig.cam1),
            "cam2": cam(self.rig.cam2),
            "row_coeffs": [float(v) for v in self.row_coeffs],
            "col_coeffs": [float(v) for v in self.col_coeffs],
            "control_pairs_px": [[round(float(v), 4) for v in p] for p in self.control_pairs_px],
            "lattice": None
            if lat is None
            else {
                "a0": lat.a0,
                "step_a": lat.step_a,
                "b0": lat.b0,
                "step_b": lat.step_b,
                "rows": list(lat.rows),
                "cols": list(lat.cols),
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
        return cls(
            rig=rig,
            row_coeffs=(f.row_coeffs[0], f.row_coeffs[1]),
            col_coeffs=tuple(f.col_coeffs),
            control_pairs_px=pairs,
            lattice=f.lattice,
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
class _CalibrationFile:
    format_version: int
    floor_depth_mm: float
    cam1: _CameraFile
    cam2: _CameraFile
    row_coeffs: tuple[float, ...]
    col_coeffs: tuple[float, ...]
    control_pairs_px: tuple[tuple[float, float, float, float], ...] = ()
    lattice: LaserLattice | None = None
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


def _neighbour_vectors(rc: NDArray[np.float64]) -> NDArray[np.float64]:
    """Vectors (M, 2) (drow, dcol) from each dot to its 4 nearest neighbours, px."""
    if len(rc) < 5:
        return np.zeros((0, 2))
    d = rc[:, None, :] - rc[None, :, :]
    dist = np.hypot(d[..., 0], d[..., 1])
    np.fill_diagonal(dist, np.inf)
    idx = np.argsort(dist, axis=1)[:, :4]
    rows = np.arange(len(rc))[:, None]
    vec = -d[rows, idx].reshape(-1, 2)
    near = dist[rows, idx]
    spacing = float(np.median(near[:, 0]))
    near = near.ravel()
    return vec[(near > 0.6 * spacing) & (near < 1.5 * spacing)]


def lattice_rotation(rc: NDArray[np.float64]) -> float:
    """Rotation θ (rad) of a dot lattice seen in an image, per :class:`MirrorCamera` convention.

    An ideal lateral lattice step (0, dy) shows as (−sin θ·dy, cos θ·dy), a forward step as
    (cos θ·dx, sin θ·dx); either has image direction atan2(dr, dc) ≡ −θ modulo 90°.
    """
    vec = _neighbour_vectors(rc)
    if len(vec) == 0:
        raise CalibrationError(f"too few dots ({len(rc)}) to find the lattice orientation")
    ang = np.arctan2(vec[:, 0], vec[:, 1])
    folded = (ang + math.pi / 4) % (math.pi / 2) - math.pi / 4
    # circular median on the 90°-periodic angle: work with 4θ
    mean4 = math.atan2(np.mean(np.sin(4 * folded)), np.mean(np.cos(4 * folded))) / 4
    dev = (folded - mean4 + math.pi / 4) % (math.pi / 2) - math.pi / 4
    return -float(mean4 + np.median(dev))


def _lattice_steps(xy: NDArray[np.float64]) -> tuple[float, float]:
    """(row step, column step) px of an axis-aligned lattice of ideal offsets (x, y)."""
    vec = np.abs(_neighbour_vectors(xy))
    rows = vec[vec[:, 0] > vec[:, 1], 0]
    cols = vec[vec[:, 1] > vec[:, 0], 1]
    if len(rows) < 3 or len(cols) < 3:
        raise CalibrationError("the floor dots do not form a lattice (too few neighbours)")
    return float(np.median(rows)), float(np.median(cols))


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


def _fit_lattice(slopes: NDArray[np.float64]) -> LaserLattice | None:
    """Regular lattice (a0 + step_a·l, b0 + step_b·k) through the floor ray slopes, or None."""
    if len(slopes) < 6:
        return None
    try:
        step_a, step_b = _lattice_steps(slopes)
    except CalibrationError:
        return None
    out = []
    for axis, step in ((0, step_a), (1, step_b)):
        v = slopes[:, axis]
        ref = v[np.argmin(np.abs(v - np.median(v)))]
        idx = np.rint((v - ref) / step)
        A = np.column_stack([np.ones_like(idx), idx])
        (o, s), *_ = np.linalg.lstsq(A, v, rcond=None)
        idx = np.rint((v - o) / s)
        out.append((float(o), float(s), (int(idx.min()), int(idx.max()))))
    (a0, sa, rows), (b0, sb, cols) = out
    return LaserLattice(a0, sa, b0, sb, rows, cols)


def calibrate_from_capture(
    capture: StereoCapture,
    floor_depth_mm: float,
    baseline_mm: float,
    settings: CalibrationSettings | None = None,
    detection: DetectionParams | None = None,
) -> Calibration:
    """Calibrate the rig from one capture of an empty floor ``floor_depth_mm`` below the mirrors.

    See the module docstring for the steps. Raises :class:`CalibrationError` (with the residuals
    reached) when the capture has no dots, is not one horizontal plane, or its depth disagrees
    with ``floor_depth_mm`` beyond the scale prior.
    """
    from omnid.core import matching  # the thesis polynomial fit lives with the matcher

    s = settings or CalibrationSettings()
    if not (math.isfinite(floor_depth_mm) and floor_depth_mm > 0):
        raise CalibrationError(f"floor depth must be positive, got {floor_depth_mm} mm")
    if not (math.isfinite(baseline_mm) and baseline_mm > 0):
        raise CalibrationError(f"baseline must be positive, got {baseline_mm} mm")
    shape = capture.shape
    dots = []
    cams = []
    for k, (mask, base) in enumerate(
        ((capture.mask1, capture.base1), (capture.mask2, capture.base2)), start=1
    ):
        try:
            row, col, rad, _ = fit_mirror_disk(mask, s.disk_threshold)
        except CalibrationError as exc:
            raise CalibrationError(f"camera {k}: {exc}") from None
        d = detect_dots(mask, base, "best", detection)
        if len(d) < s.min_pairs:
            raise CalibrationError(
                f"camera {k}: only {len(d)} laser dots found (need {s.min_pairs}); "
                "is the laser on in the base image?"
            )
        y_mm = (-0.5 if k == 1 else 0.5) * baseline_mm
        theta = lattice_rotation(d[:, :2])
        cams.append(MirrorCamera(row, col, y_mm, s.f_over_k_prior_px, theta, rad, shape))
        dots.append(d)
    d_over_h = baseline_mm / floor_depth_mm
    xy1 = cams[0].ideal_offsets(dots[0][:, :2])
    xy2 = cams[1].ideal_offsets(dots[1][:, :2])
    r1, c1 = _lattice_steps(xy1)
    r2, c2 = _lattice_steps(xy2)
    ratio = 0.5 * (r1 / r2 + c1 / c2)  # f1/f2
    xy2s = xy2 * ratio
    # Column shift between the lattices: disparity = (f/K)·D/H, known modulo one column step.
    lo = s.f_over_k_prior_px * (1 - s.f_over_k_tolerance) * d_over_h
    hi = s.f_over_k_prior_px * (1 + s.f_over_k_tolerance) * d_over_h
    dr = xy1[:, None, 0] - xy2s[None, :, 0]
    dc = xy1[:, None, 1] - xy2s[None, :, 1]
    same_row = np.abs(dr) < 0.3 * r1
    cand = dc[same_row & (dc > lo - 0.3 * c1) & (dc < hi + 0.3 * c1)]
    if len(cand) < s.min_pairs:
        raise CalibrationError(
            f"no floor pairing: only {len(cand)} dot pairs have a disparity within "
            f"{lo:.1f}-{hi:.1f} px (f/K prior {s.f_over_k_prior_px} px ± "
            f"{100 * s.f_over_k_tolerance:.0f}%); wrong floor depth, or not a floor?"
        )
    hist, edges = np.histogram(cand, bins=np.arange(lo - 0.3 * c1, hi + 0.3 * c1 + 0.5, 0.5))
    peak = int(np.argmax(hist))
    near = cand[np.abs(cand - 0.5 * (edges[peak] + edges[peak + 1])) < 1.5]
    disparity = float(np.median(near))
    f_est = disparity / d_over_h
    if not (lo <= disparity <= hi):
        raise CalibrationError(
            f"floor disparity {disparity:.2f} px gives f/K = {f_est:.1f} px, outside "
            f"{s.f_over_k_prior_px} px ± {100 * s.f_over_k_tolerance:.0f}%: "
            f"is the floor really {floor_depth_mm:g} mm below the mirrors?"
        )
    i1, i2 = _mutual_nearest(xy1, xy2s + np.array([0.0, disparity]), 0.3 * min(r1, c1))
    if len(i1) < s.min_pairs:
        raise CalibrationError(
            f"only {len(i1)} floor dots pair up (need {s.min_pairs}); not an empty floor?"
        )
    uv1 = _offsets(cams[0], dots[0][i1, :2])
    uv2 = _offsets(cams[1], dots[1][i2, :2])
    sol, inl = _ransac_fit(uv1, uv2, d_over_h, s)
    row_res, col_res = _residuals_px(sol, uv1, uv2, d_over_h)
    f1 = 1.0 / math.hypot(sol[0], sol[1])
    f2 = 1.0 / math.hypot(sol[2], sol[3])
    th1 = math.atan2(sol[1], sol[0])
    th2 = math.atan2(sol[3], sol[2])
    # Of the dots seen, how many pair up as one floor: an empty floor pairs nearly all of them.
    frac = float(inl.sum()) / min(len(dots[0]), len(dots[1]))
    row_rms = float(np.sqrt(np.mean(row_res[inl] ** 2)))
    col_rms = float(np.sqrt(np.mean(col_res[inl] ** 2)))
    # depth of each inlier pair from its disparity: Z = D / (e1 - e2)
    e = col_res[inl] / f1 + d_over_h
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
    cam1 = MirrorCamera(
        cams[0].center_row_px,
        cams[0].center_col_px,
        -0.5 * baseline_mm,
        f1,
        th1,
        cams[0].disk_radius_px,
        shape,
    )
    cam2 = MirrorCamera(
        cams[1].center_row_px,
        cams[1].center_col_px,
        0.5 * baseline_mm,
        f2,
        th2,
        cams[1].disk_radius_px,
        shape,
    )
    rig = StereoRig(cam1, cam2, floor_depth_mm)
    # Laser ray slopes of the inlier floor dots: X/Z from the rows, Y/Z = mean of both columns.
    p1 = cam1.ray_slopes(dots[0][i1[inl], :2])
    p2 = cam2.ray_slopes(dots[1][i2[inl], :2])
    slopes = np.column_stack([0.5 * (p1[:, 0] + p2[:, 0]), 0.5 * (p1[:, 1] + p2[:, 1])])
    lattice = _fit_lattice(slopes)
    # Thesis polynomials (6.12, 6.13) on the control pairs, refined in three steps.
    control = np.column_stack([dots[0][i1[inl], :2], dots[1][i2[inl], :2]])
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
        lattice=lattice,
        residuals=residuals,
    )


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
