"""Synthetic stereo captures: known 3-D laser dots drawn as realistic mask/base image pairs.

Used by the tests (known answers), the tools (experiments, benchmarks), the calibration demo
and the closed-loop simulator. Everything is seeded: the same arguments and ``rng`` seed give
the same images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.core.types import StereoCapture


@dataclass(frozen=True)
class RenderOptions:
    """How a capture is drawn. Intensities are 8-bit gray levels; sizes are px."""

    spot_sigma_px: float = 1.3  # Gaussian sigma of a dot's image
    spot_sigma_jitter: float = 0.15  # relative spread of sigma between dots
    spot_peak: float = 150.0  # peak gray level a dot adds
    spot_peak_jitter: float = 0.25  # relative spread of peak between dots
    background_level: float = 70.0  # mean gray inside the mirror disk
    background_texture: float = 25.0  # amplitude of the smooth scene texture
    noise_sigma: float = 2.0  # sensor noise, gray levels (independent per frame)
    flicker: float = 0.0  # relative illumination change from mask to base
    halo_fraction: float = 0.0  # sparkle halo brightness relative to the dot peak
    halo_sigma_px: float = 4.0  # size of the sparkle halo
    color: bool = False  # BGR output with a green laser


def _smooth_texture(shape: tuple[int, int], rng: np.random.Generator, cell_px: int = 24) -> NDArray:
    import cv2

    rows, cols = shape
    coarse = rng.standard_normal((rows // cell_px + 2, cols // cell_px + 2)).astype(np.float32)
    return cv2.resize(coarse, (cols, rows), interpolation=cv2.INTER_CUBIC)


def draw_spots(
    shape: tuple[int, int],
    rc: ArrayLike,
    sigma_px: ArrayLike,
    peak: ArrayLike,
) -> NDArray[np.float64]:
    """An image (float) of Gaussian spots centred at sub-pixel (row, col) positions."""
    img = np.zeros(shape, dtype=np.float64)
    pos = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    sig = np.broadcast_to(np.asarray(sigma_px, dtype=np.float64), (len(pos),))
    amp = np.broadcast_to(np.asarray(peak, dtype=np.float64), (len(pos),))
    rows, cols = shape
    for (r, c), s, a in zip(pos, sig, amp, strict=True):
        if not (np.isfinite(r) and np.isfinite(c)):
            continue
        half = int(np.ceil(4.0 * s))
        r0, r1 = max(int(np.floor(r)) - half, 0), min(int(np.floor(r)) + half + 2, rows)
        c0, c1 = max(int(np.floor(c)) - half, 0), min(int(np.floor(c)) + half + 2, cols)
        if r0 >= r1 or c0 >= c1:
            continue
        rr = np.arange(r0, r1)[:, None] - r
        cc = np.arange(c0, c1)[None, :] - c
        img[r0:r1, c0:c1] += a * np.exp(-(rr * rr + cc * cc) / (2.0 * s * s))
    return img


def render_camera_pair(
    cam: MirrorCamera,
    rc: ArrayLike,
    options: RenderOptions,
    rng: np.random.Generator,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Mask and base images of one camera for dots at image positions ``rc`` (N, 2) px."""
    shape = cam.image_shape
    pos = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    keep = cam.in_disk(pos) if len(pos) else np.zeros(0, dtype=bool)
    pos = pos[keep]
    n = len(pos)
    sig = options.spot_sigma_px * (1.0 + options.spot_sigma_jitter * rng.uniform(-1, 1, n))
    amp = options.spot_peak * (1.0 + options.spot_peak_jitter * rng.uniform(-1, 1, n))
    rr, cc = np.mgrid[0 : shape[0], 0 : shape[1]]
    disk = np.hypot(rr - cam.center_row_px, cc - cam.center_col_px) <= cam.disk_radius_px
    scene = options.background_level + options.background_texture * _smooth_texture(shape, rng)
    scene = np.where(disk, scene, 3.0)
    laser = draw_spots(shape, pos, sig, amp)
    if options.halo_fraction > 0:
        laser += draw_spots(shape, pos, options.halo_sigma_px, amp * options.halo_fraction)
    laser *= disk
    mask = scene + rng.normal(0.0, options.noise_sigma, shape)
    base = scene * (1.0 + options.flicker) + laser + rng.normal(0.0, options.noise_sigma, shape)
    mask_u8 = np.clip(np.rint(mask), 0, 255).astype(np.uint8)
    base_u8 = np.clip(np.rint(base), 0, 255).astype(np.uint8)
    if not options.color:
        return mask_u8, base_u8
    # Green laser on a grayish scene: B and R see the scene, G sees the scene plus the laser.
    scene_bgr = np.stack([mask_u8] * 3, axis=-1)
    base_g = base_u8
    base_br = np.clip(
        np.rint(
            scene * (1.0 + options.flicker)
            + 0.15 * laser
            + rng.normal(0.0, options.noise_sigma, shape)
        ),
        0,
        255,
    ).astype(np.uint8)
    return scene_bgr, np.stack([base_br, base_g, base_br], axis=-1)


def render_capture(
    rig: StereoRig,
    dots_xyz_mm: ArrayLike,
    options: RenderOptions | None = None,
    seed: int | np.random.Generator = 0,
) -> StereoCapture:
    """A stereo mask/base capture of laser dots at known 3-D positions (N, 3) mm.

    Dots outside a mirror's disk (or behind the mirror plane) are not drawn in that camera.
    """
    opts = options or RenderOptions()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    xyz = np.asarray(dots_xyz_mm, dtype=np.float64).reshape(-1, 3)
    m1, b1 = render_camera_pair(rig.cam1, rig.cam1.project(xyz), opts, rng)
    m2, b2 = render_camera_pair(rig.cam2, rig.cam2.project(xyz), opts, rng)
    return StereoCapture(m1, b1, m2, b2)
