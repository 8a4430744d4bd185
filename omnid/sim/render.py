"""Synthetic stereo captures: known 3-D laser dots drawn as realistic mask/base image pairs.

Used by the tests (known answers), the tools (experiments, benchmarks), the calibration demo
and the closed-loop simulator. Everything is seeded: the same arguments and ``rng`` seed give
the same images.

What a capture holds (thesis 5.1): the *mask* frame is the scene with the laser off, the *base*
frame the same scene with the laser on, each with its own sensor noise. Modelled effects:

- **Dots** are pixel-area-integrated Gaussians (the Gaussian's integral over each pixel's square,
  computed with erf), so a dot's true centre is exactly the centroid of its (untruncated) image:
  the truth is well defined at sub-pixel level. Size and brightness vary from dot to dot.
- **Sparkle halos**: a broad dim glow around each dot, broken into speckle grains (the laser's
  coherent light scattered by the floor), which makes false local maxima between dots.
- **Ghosts**: dim blurred copies of some dots a few pixels away (reflections) — not laser dots.
- **Scene**: smooth texture inside the mirror disk, dark outside it (the camera sees the mirror).
- **Flicker**: the illumination changes between mask and base (mains flicker, auto exposure), so
  the subtracted image keeps a faint copy of the scene.
- **Sensor noise**: Gaussian read noise plus optional shot noise growing with the signal.
- **Colour**: optional BGR frames with a green laser (strong in G, weak cross-talk in B and R).

Pixel convention: pixel (i, j) covers [i − 0.5, i + 0.5] × [j − 0.5, j + 0.5]; positions are
(row, col) px.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.core.types import StereoCapture

#: Gray level outside the mirror disk (the dark camera housing).
OUTSIDE_DISK_LEVEL = 3.0


@dataclass(frozen=True)
class RenderOptions:
    """How a capture is drawn. Intensities are 8-bit gray levels; sizes are px.

    The defaults are a clean capture; :meth:`realistic` adds halos, ghosts, flicker, shot noise.
    """

    spot_sigma_px: float = 1.3  # Gaussian sigma of a dot's image
    spot_sigma_jitter: float = 0.15  # relative spread of sigma between dots
    spot_peak: float = 150.0  # peak gray level a dot adds (of the continuous Gaussian)
    spot_peak_jitter: float = 0.25  # relative spread of peak between dots
    background_level: float = 70.0  # mean gray inside the mirror disk
    background_texture: float = 25.0  # amplitude of the smooth scene texture
    noise_sigma: float = 2.0  # sensor read noise, gray levels (independent per frame)
    flicker: float = 0.0  # relative illumination change from mask to base
    halo_fraction: float = 0.0  # sparkle halo brightness relative to the dot peak
    halo_sigma_px: float = 4.0  # size of the sparkle halo
    color: bool = False  # BGR output with a green laser
    speckle_contrast: float = 0.6  # relative spread of the halo's speckle grains (0 = smooth)
    ghost_fraction: float = 0.0  # share of dots that throw a ghost reflection
    ghost_peak_fraction: float = 0.25  # ghost brightness relative to its dot
    ghost_offset_px: tuple[float, float] = (3.0, 6.0)  # ghost distance from its dot, min/max
    shot_noise_gain: float = 0.0  # extra noise variance per gray level of signal

    @classmethod
    def realistic(cls, **changes: float | bool) -> RenderOptions:
        """Options for a realistic indoor capture (what the detection tests and benchmark use)."""
        base: dict[str, float | bool] = {
            "noise_sigma": 2.0,
            "flicker": 0.03,
            "halo_fraction": 0.05,
            "speckle_contrast": 0.3,
            "ghost_fraction": 0.03,
            "shot_noise_gain": 0.05,
        }
        base.update(changes)
        return cls(**base)  # type: ignore[arg-type]


def _erf(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Error function, |error| ≤ 1.5e-7 (Abramowitz & Stegun 7.1.26); numpy has none."""
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    poly = t * (
        0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429)))
    )
    return s * (1.0 - poly * np.exp(-a * a))


def _pixel_fractions(
    centre: NDArray[np.float64], sigma: NDArray[np.float64], start: NDArray[np.int64], width: int
) -> NDArray[np.float64]:
    """Share (N, width) of a 1-D Gaussian's mass falling in pixels start … start+width−1."""
    edges = start[:, None] - 0.5 + np.arange(width + 1)[None, :]
    cdf = 0.5 * _erf((edges - centre[:, None]) / (math.sqrt(2.0) * sigma[:, None]))
    return np.diff(cdf, axis=1)


def _spot_patch(
    shape: tuple[int, int],
    pos: NDArray[np.float64],
    sig: NDArray[np.float64],
    amp: NDArray[np.float64],
) -> tuple[int, int, NDArray[np.float64]]:
    """Spots (already filtered to finite, on-image ones) drawn into the smallest patch of an
    image of ``shape`` that holds them all: (first row, first column, patch). Summing into
    the patch instead of the whole frame keeps the cost proportional to the dots' area."""
    rows, cols = shape
    half = math.ceil(4.0 * float(sig.max()))
    width = 2 * half + 2
    r0 = np.floor(pos[:, 0]).astype(np.int64) - half
    c0 = np.floor(pos[:, 1]).astype(np.int64) - half
    pr = _pixel_fractions(pos[:, 0], sig, r0, width)
    pc = _pixel_fractions(pos[:, 1], sig, c0, width)
    mass = amp * 2.0 * math.pi * sig * sig
    vals = (mass[:, None] * pr)[:, :, None] * pc[:, None, :]
    top, left = max(int(r0.min()), 0), max(int(c0.min()), 0)
    bottom, right = min(int(r0.max()) + width, rows), min(int(c0.max()) + width, cols)
    ph, pw = bottom - top, right - left
    span = np.arange(width)
    uncut = top == r0.min() and left == c0.min()
    uncut = uncut and bottom - r0.max() >= width and right - c0.max() >= width
    if uncut:  # no spot is cut by the image's edge: plain flat indices
        grid = span[:, None] * pw + span[None, :]
        flat = ((r0 - top) * pw + (c0 - left))[:, None, None] + grid[None]
        patch = np.bincount(flat.ravel(), weights=vals.ravel(), minlength=ph * pw)
        return top, left, patch.astype(np.float64, copy=False).reshape(ph, pw)
    rr = r0[:, None, None] - top + span[None, :, None]
    cc = c0[:, None, None] - left + span[None, None, :]
    inside = (rr >= 0) & (rr < ph) & (cc >= 0) & (cc < pw)
    flat = np.broadcast_to(rr * pw, inside.shape) + cc
    patch = np.bincount(flat[inside], weights=vals[inside], minlength=ph * pw)
    return top, left, patch.astype(np.float64, copy=False).reshape(ph, pw)


def _valid_spots(
    shape: tuple[int, int], rc: ArrayLike, sigma_px: ArrayLike, peak: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    rows, cols = shape
    pos = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    sig = np.broadcast_to(np.asarray(sigma_px, dtype=np.float64), (len(pos),))
    amp = np.broadcast_to(np.asarray(peak, dtype=np.float64), (len(pos),))
    ok = np.isfinite(pos).all(axis=1) & (sig > 0)
    ok &= (pos[:, 0] > -4 * sig) & (pos[:, 0] < rows + 4 * sig)
    ok &= (pos[:, 1] > -4 * sig) & (pos[:, 1] < cols + 4 * sig)
    return pos[ok], sig[ok], amp[ok]


def draw_spots(
    shape: tuple[int, int],
    rc: ArrayLike,
    sigma_px: ArrayLike,
    peak: ArrayLike,
) -> NDArray[np.float64]:
    """An image (float) of Gaussian spots centred at sub-pixel (row, col) positions.

    Each pixel holds the spot's integral over the pixel's area (``peak`` is the peak of the
    continuous Gaussian, so a pixel-centred spot's brightest pixel is slightly below it). The
    centroid of a spot's pixels is therefore its true centre. Spots are cut at 4·sigma.
    """
    img = np.zeros(shape, dtype=np.float64)
    _add_spots(img, rc, sigma_px, peak)
    return img


def _add_spots(img: NDArray, rc: ArrayLike, sigma_px: ArrayLike, peak: ArrayLike) -> None:
    """Add the spots of :func:`draw_spots` into ``img`` (float32 or float64) in place."""
    shape = (img.shape[0], img.shape[1])
    pos, sig, amp = _valid_spots(shape, rc, sigma_px, peak)
    if len(pos) == 0:
        return
    top, left, patch = _spot_patch(shape, pos, sig, amp)
    img[top : top + patch.shape[0], left : left + patch.shape[1]] += patch


def _smooth_texture(shape: tuple[int, int], rng: np.random.Generator, cell_px: int = 24) -> NDArray:
    rows, cols = shape
    coarse = rng.standard_normal((rows // cell_px + 2, cols // cell_px + 2)).astype(np.float32)
    return cv2.resize(coarse, (cols, rows), interpolation=cv2.INTER_CUBIC)


def _halos(
    shape: tuple[int, int],
    pos: NDArray[np.float64],
    amp: NDArray[np.float64],
    options: RenderOptions,
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    """Sparkle halos: a ring-shaped glow around each dot, broken into speckle grains.

    The glow is ``e^(−r²/2s²) − e^(−r²/2(s/2)²)`` with ``s = halo_sigma_px`` (zero at the dot's
    centre, largest at r ≈ 0.96·s, i.e. between neighbouring dots), scaled so its largest
    value is ``halo_fraction`` · the dot's peak; the grains multiply it by (1 + speckle).
    """
    rows, cols = shape
    s1 = options.halo_sigma_px
    s2 = 0.5 * s1
    r2 = 2.0 * math.log(s1 * s1 / (s2 * s2)) * s1 * s1 * s2 * s2 / (s1 * s1 - s2 * s2)
    ring_peak = math.exp(-r2 / (2 * s1 * s1)) - math.exp(-r2 / (2 * s2 * s2))
    # Impulses spread bilinearly over the 4 pixels around each dot centre (so the glow is
    # centred on the dot), then blurred; a blurred unit impulse peaks at 1/(2π s²).
    r0 = np.floor(pos[:, 0]).astype(np.int64)
    c0 = np.floor(pos[:, 1]).astype(np.int64)
    fr = pos[:, 0] - r0
    fc = pos[:, 1] - c0
    mass = amp * options.halo_fraction / ring_peak
    idx = []
    wts = []
    for dr, wr in ((0, 1.0 - fr), (1, fr)):
        for dc, wc in ((0, 1.0 - fc), (1, fc)):
            rr, cc = r0 + dr, c0 + dc
            ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
            idx.append((rr * cols + cc)[ok])
            wts.append((mass * wr * wc)[ok])
    impulses = (
        np.bincount(np.concatenate(idx), weights=np.concatenate(wts), minlength=rows * cols)
        .astype(np.float32)
        .reshape(rows, cols)
    )
    glow = np.float32(2 * math.pi * s1 * s1) * cv2.GaussianBlur(impulses, (0, 0), s1)
    glow -= np.float32(2 * math.pi * s2 * s2) * cv2.GaussianBlur(impulses, (0, 0), s2)
    np.maximum(glow, 0.0, out=glow)
    if options.speckle_contrast <= 0:
        return glow
    grains = _randn(shape, rng)
    grains = cv2.GaussianBlur(grains, (0, 0), 0.8).astype(np.float32)
    grains *= options.speckle_contrast / max(float(grains.std()), 1e-6)
    return glow * np.maximum(1.0 + grains, 0.0)


def _randn(shape: tuple[int, int], rng: np.random.Generator) -> NDArray[np.float32]:
    """Standard normal float32 samples from OpenCV's generator (``cv2.randn``: 4x faster than
    numpy's), seeded from ``rng`` so that a capture stays a function of its seed. OpenCV's
    default generator is per thread, so concurrent renders do not disturb each other."""
    out = np.empty(shape, dtype=np.float32)
    cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
    cv2.randn(out, 0.0, 1.0)  # type: ignore[call-overload]  # (stubs want arrays, not floats)
    return out


def _noise(
    signal: NDArray[np.float32], options: RenderOptions, rng: np.random.Generator
) -> NDArray[np.float32]:
    noise = _randn((signal.shape[0], signal.shape[1]), rng)
    if options.shot_noise_gain > 0:
        var = np.float32(options.noise_sigma**2) + np.float32(options.shot_noise_gain) * np.maximum(
            signal, np.float32(0.0)
        )
        noise *= cv2.sqrt(var)
        return noise
    noise *= np.float32(options.noise_sigma)
    return noise


def _to_u8(img: NDArray) -> NDArray[np.uint8]:
    """Round (half to even, as np.rint) and saturate to 0…255."""
    return np.asarray(cv2.add(img, 0.0, dtype=cv2.CV_8U), dtype=np.uint8)  # type: ignore[call-overload]


def render_camera_pair(
    cam: MirrorCamera,
    rc: ArrayLike,
    options: RenderOptions,
    rng: np.random.Generator,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Mask and base images of one camera for dots at image positions ``rc`` (N, 2) px.

    Gray (H, W) uint8, or BGR (H, W, 3) uint8 when ``options.color``. Dots outside the mirror
    disk are not drawn; the part of a dot's light outside the disk is lost.
    """
    shape = cam.image_shape
    rows, cols = shape
    pos = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    keep = cam.in_disk(pos) if len(pos) else np.zeros(0, dtype=bool)
    pos = pos[keep]
    n = len(pos)
    sig = options.spot_sigma_px * (1.0 + options.spot_sigma_jitter * rng.uniform(-1, 1, n))
    amp = options.spot_peak * (1.0 + options.spot_peak_jitter * rng.uniform(-1, 1, n))
    dr = np.arange(rows, dtype=np.float32)[:, None] - np.float32(cam.center_row_px)
    dc = np.arange(cols, dtype=np.float32)[None, :] - np.float32(cam.center_col_px)
    disk = (dr * dr + dc * dc) <= np.float32(cam.disk_radius_px**2)
    texture = _smooth_texture(shape, rng)
    scene = np.where(
        disk, options.background_level + options.background_texture * texture, OUTSIDE_DISK_LEVEL
    ).astype(np.float32)
    laser = np.zeros(shape, dtype=np.float32)
    _add_spots(laser, pos, sig, amp)
    if options.halo_fraction > 0 and n:
        # The glow reaches ~4 halo sigmas: draw it (and its grains) in the box of the dots.
        reach = math.ceil(4.0 * options.halo_sigma_px) + 2
        top = max(int(np.floor(pos[:, 0].min())) - reach, 0)
        left = max(int(np.floor(pos[:, 1].min())) - reach, 0)
        bottom = min(int(np.ceil(pos[:, 0].max())) + reach + 1, rows)
        right = min(int(np.ceil(pos[:, 1].max())) + reach + 1, cols)
        if bottom > top and right > left:
            laser[top:bottom, left:right] += _halos(
                (bottom - top, right - left), pos - (top, left), amp, options, rng
            )
    if options.ghost_fraction > 0 and n:
        has_ghost = rng.uniform(size=n) < options.ghost_fraction
        k = int(has_ghost.sum())
        lo, hi = options.ghost_offset_px
        dist = rng.uniform(lo, hi, k)
        ang = rng.uniform(0.0, 2.0 * math.pi, k)
        gpos = pos[has_ghost] + np.column_stack([dist * np.sin(ang), dist * np.cos(ang)])
        gamp = amp[has_ghost] * options.ghost_peak_fraction
        _add_spots(laser, gpos, 1.6 * sig[has_ghost], gamp)
    # Light outside the mirror disk is lost; the laser is nonzero only around the dots.
    if n:
        spread = 4.0 * max(options.halo_sigma_px, 1.6 * float(sig.max()))  # halo, ghost
        reach = math.ceil(spread + max(options.ghost_offset_px)) + 2
        top = max(int(np.floor(pos[:, 0].min())) - reach, 0)
        left = max(int(np.floor(pos[:, 1].min())) - reach, 0)
        bottom = min(int(np.ceil(pos[:, 0].max())) + reach + 1, rows)
        right = min(int(np.ceil(pos[:, 1].max())) + reach + 1, cols)
        laser[top:bottom, left:right] *= disk[top:bottom, left:right]
    lit = scene * np.float32(1.0 + options.flicker)
    if not options.color:
        mask = scene + _noise(scene, options, rng)
        base = lit + laser + _noise(lit + laser, options, rng)
        return _to_u8(mask), _to_u8(base)
    # Green laser over a slightly tinted scene: each channel has its own gain and noise; the
    # laser is strong in G with a little cross-talk into B and R.
    tint = (0.9, 1.0, 1.1)
    cross = (0.12, 1.0, 0.18)
    masks = []
    bases = []
    for t, x in zip(tint, cross, strict=True):
        sc = scene * np.float32(t)
        sl = lit * np.float32(t) + laser * np.float32(x)
        masks.append(_to_u8(sc + _noise(sc, options, rng)))
        bases.append(_to_u8(sl + _noise(sl, options, rng)))
    return np.asarray(cv2.merge(masks), dtype=np.uint8), np.asarray(
        cv2.merge(bases), dtype=np.uint8
    )


def visible_truth(cam: MirrorCamera, rc: ArrayLike, margin_px: float = 0.0) -> NDArray[np.float64]:
    """The true dot centres (K, 2) px that :func:`render_camera_pair` draws for positions ``rc``
    (those inside the mirror disk), optionally only those ``margin_px`` inside its edge."""
    pos = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    if len(pos) == 0:
        return np.zeros((0, 2))
    return pos[cam.in_disk(pos, margin_px)]


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
