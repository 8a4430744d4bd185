"""Rectilinear mirror–camera model and the stereo rig (thesis 3.1.2.2, 6.1; SPEC §2).

Frame of the vision system: origin midway between the two mirror axes, in the mirror plane;
X forward, Y lateral along the baseline, Z vertical **positive downward** (depth below the
mirrors, mm). Mirror 1 sits at Y = -D/2, mirror 2 at Y = +D/2.

The rectilinear mirror (eq. 3.6 with tan α = ξ/f) gives tan δ = K·ξ/f with the mirror constant
K = tan δr / tan αr (eq. 6.8). Hence a world point P = (X, Y, Z) is imaged at

    s   = (f/K) / Z            pixels per mm on the horizontal plane at depth Z
    x_i = -s · X               row offset from the mirror centre (forward is up in the image)
    y_i =  s · (Y - Y_i)       column offset from the mirror centre

and each camera may in addition be rotated about its mirror axis by ``rotation_rad`` (the image
offsets are the ideal ones rotated by that angle). ``f/K`` is the only scale: the thesis measured
about 10.80 mm per pixel on a floor 1170 mm below the mirrors, i.e. f/K ≈ 108.3 px.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: tan δr / tan αr with δr = 80°, αr = 26.565° (thesis 6.1, eq. 6.8).
MIRROR_CONSTANT_K = math.tan(math.radians(80.0)) / math.tan(math.radians(26.565))
#: Default f/K in pixels (10.80 mm/px at 1170 mm depth).
DEFAULT_F_OVER_K_PX = 108.3
DEFAULT_BASELINE_MM = 200.0
DEFAULT_FLOOR_DEPTH_MM = 1100.0
DEFAULT_IMAGE_SHAPE = (480, 640)
#: Radius of the mirror's bright disk in a 640x480 image (px); outside it the image is dark.
DEFAULT_DISK_RADIUS_PX = 235.0


def _as_points(xyz: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(xyz, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr.reshape(1, -1)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {arr.shape}")
    return arr


def _as_pixels(rc: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(rc, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr.reshape(1, -1)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"expected pixels of shape (N, 2) as (row, col), got {arr.shape}")
    return arr


@dataclass(frozen=True)
class MirrorCamera:
    """One camera–mirror pair: where its mirror centre is in the image and how it maps the world.

    Attributes
    ----------
    center_row_px, center_col_px
        Image position of the mirror axis (r_m, c_m), px.
    y_mm
        Lateral position of the mirror axis in the rig frame (−D/2 for mirror 1, +D/2 for 2), mm.
    f_over_k_px
        Focal length over the mirror constant, px (s = (f/K)/Z px per mm at depth Z).
    rotation_rad
        Rotation of the image about the mirror axis, rad (positive turns +row toward +col).
    disk_radius_px
        Radius of the mirror's visible disk, px; pixels farther from the centre see nothing.
    image_shape
        (rows, cols) of the camera image, px.
    """

    center_row_px: float
    center_col_px: float
    y_mm: float
    f_over_k_px: float = DEFAULT_F_OVER_K_PX
    rotation_rad: float = 0.0
    disk_radius_px: float = DEFAULT_DISK_RADIUS_PX
    image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE

    def __post_init__(self) -> None:
        for name in (
            "center_row_px",
            "center_col_px",
            "y_mm",
            "f_over_k_px",
            "rotation_rad",
            "disk_radius_px",
        ):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"MirrorCamera.{name} must be finite")
        if self.f_over_k_px <= 0 or self.disk_radius_px <= 0:
            raise ValueError("MirrorCamera.f_over_k_px and disk_radius_px must be positive")

    @property
    def f_px(self) -> float:
        """Effective focal length f = K·(f/K), px."""
        return self.f_over_k_px * MIRROR_CONSTANT_K

    def _rotate(self, x: NDArray[np.float64], y: NDArray[np.float64], sign: float):
        ca, sa = math.cos(self.rotation_rad), math.sin(sign * self.rotation_rad)
        return ca * x - sa * y, sa * x + ca * y

    def project(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """World points (N, 3) mm → image positions (N, 2) as (row, col) px.

        Points at Z ≤ 0 (at or above the mirror plane) have no image and give NaN.
        """
        p = _as_points(xyz)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(z > 0, self.f_over_k_px / z, np.nan)
        x0 = -s * p[:, 0]
        y0 = s * (p[:, 1] - self.y_mm)
        x, y = self._rotate(x0, y0, +1.0)
        return np.column_stack([x + self.center_row_px, y + self.center_col_px])

    def ideal_offsets(self, rc: ArrayLike) -> NDArray[np.float64]:
        """Image positions (N, 2) px → offsets (x, y) from the mirror centre with rotation undone, px."""
        q = _as_pixels(rc)
        x, y = self._rotate(q[:, 0] - self.center_row_px, q[:, 1] - self.center_col_px, -1.0)
        return np.column_stack([x, y])

    def ray_slopes(self, rc: ArrayLike) -> NDArray[np.float64]:
        """Image positions (N, 2) → ray slopes (X/Z, (Y − Y_i)/Z), dimensionless.

        The viewing ray of a pixel is {(0, Y_i, 0) + Z·(X/Z, (Y−Y_i)/Z, 1) : Z > 0}.
        """
        return self.slopes_of_offsets(self.ideal_offsets(rc))

    def slopes_of_offsets(self, off: NDArray[np.float64]) -> NDArray[np.float64]:
        """Ideal offsets (N, 2) px (:meth:`ideal_offsets`) → ray slopes (N, 2) (:meth:`ray_slopes`)."""
        return np.column_stack([-off[:, 0], off[:, 1]]) / self.f_over_k_px

    def ray_directions(self, rc: ArrayLike) -> NDArray[np.float64]:
        """Image positions (N, 2) → unit direction vectors (N, 3) of the viewing rays."""
        sl = self.ray_slopes(rc)
        d = np.column_stack([sl, np.ones(len(sl))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def incidence_angle(self, rc: ArrayLike) -> NDArray[np.float64]:
        """Incidence angle δ of each pixel's ray from the vertical, rad (tan δ = K·ξ/f, eq. 6.8)."""
        off = self.ideal_offsets(rc)
        xi = np.hypot(off[:, 0], off[:, 1])
        return np.arctan(xi / self.f_over_k_px)

    def in_disk(self, rc: ArrayLike, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """True where an image position lies inside the mirror disk (shrunk by ``margin_px``)
        and inside the image."""
        q = _as_pixels(rc)
        r = np.hypot(q[:, 0] - self.center_row_px, q[:, 1] - self.center_col_px)
        rows, cols = self.image_shape
        inside = (q[:, 0] >= margin_px) & (q[:, 0] <= rows - 1 - margin_px)
        inside &= (q[:, 1] >= margin_px) & (q[:, 1] <= cols - 1 - margin_px)
        return inside & (r <= self.disk_radius_px - margin_px) & np.isfinite(r)


@dataclass(frozen=True)
class StereoRig:
    """The two camera–mirror pairs and the depth of the floor below the mirrors."""

    cam1: MirrorCamera
    cam2: MirrorCamera
    floor_depth_mm: float = DEFAULT_FLOOR_DEPTH_MM

    def __post_init__(self) -> None:
        if not (self.cam2.y_mm > self.cam1.y_mm):
            raise ValueError("StereoRig: mirror 2 must lie at larger Y than mirror 1")
        if not (math.isfinite(self.floor_depth_mm) and self.floor_depth_mm > 0):
            raise ValueError("StereoRig.floor_depth_mm must be positive")

    @classmethod
    def nominal(
        cls,
        baseline_mm: float = DEFAULT_BASELINE_MM,
        floor_depth_mm: float = DEFAULT_FLOOR_DEPTH_MM,
        f_over_k_px: float = DEFAULT_F_OVER_K_PX,
        image_shape: tuple[int, int] = DEFAULT_IMAGE_SHAPE,
        disk_radius_px: float = DEFAULT_DISK_RADIUS_PX,
    ) -> StereoRig:
        """An ideal rig: both mirror centres in the image middle, equal scale, no rotation."""
        rows, cols = image_shape
        centre = ((rows - 1) / 2.0, (cols - 1) / 2.0)
        cam = MirrorCamera(
            centre[0], centre[1], -baseline_mm / 2.0, f_over_k_px, 0.0, disk_radius_px, image_shape
        )
        return cls(cam, replace(cam, y_mm=baseline_mm / 2.0), floor_depth_mm)

    @property
    def baseline_mm(self) -> float:
        """Distance D between the mirror axes, mm."""
        return self.cam2.y_mm - self.cam1.y_mm

    def project(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """World points (N, 3) mm → matched image positions (N, 4) as (r1, c1, r2, c2) px."""
        return np.hstack([self.cam1.project(xyz), self.cam2.project(xyz)])

    def visible(self, pixels: ArrayLike, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """True where a (r1, c1, r2, c2) row is inside both mirror disks."""
        q = np.asarray(pixels, dtype=np.float64).reshape(-1, 4)
        return self.cam1.in_disk(q[:, :2], margin_px) & self.cam2.in_disk(q[:, 2:], margin_px)
