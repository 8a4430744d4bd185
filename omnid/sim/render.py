"""Synthetic stereo captures: known 3-D laser dots drawn as realistic mask/base image pairs.

Used by the tests (known answers), the tools (experiments, benchmarks), ``omnid scene``, the
calibration demo and the closed-loop simulator. Everything is seeded: the same arguments and
``rng`` seed give the same images.

What a capture holds (thesis 5.1): the *mask* frame is the scene with the laser off, the *base*
frame the same scene with the laser on, each with its own sensor noise. Modelled effects:

- **Dots** (:class:`SpotModel`): the optical blur of each dot — a round Gaussian of 1–3 px, or
  stretched radially/tangentially toward the mirror's rim, or a flatter wide top — whose light
  is the beam's power (the grating's envelope, :class:`~omnid.sim.laser.LaserProjector`) times
  the surface's shading (:func:`surface_shading`: distance and orientation) times an albedo
  factor; bright dots saturate at 255. Every deterministic part of a spot is point-symmetric
  about the projection of the 3-D dot centre, so that projection is each dot's true centre
  (see :class:`SpotModel` for what the random parts do to it). Round Gaussians are integrated
  over each pixel's area (erf), other shapes sampled with the pixel's box folded into their
  covariance.
- **Sparkle halos**: a broad dim glow around each dot, broken into speckle grains (the laser's
  coherent light scattered by the floor), which makes false local maxima between dots; and
  **speckle** grains on the dots themselves.
- **Ghosts**: dim blurred copies of some dots a few pixels away (reflections) — not laser dots.
- **Scene**: smooth texture inside the mirror disk, dark outside it (the camera sees the mirror).
- **Flicker**: the illumination changes between mask and base (mains flicker, auto exposure), so
  the subtracted image keeps a faint copy of the scene.
- **Sensor noise**: Gaussian read noise plus optional shot noise growing with the signal.
- **Colour**: optional BGR frames with a green laser (strong in G, weak cross-talk in B and R).

:func:`random_spots` draws a spot model from one of the families of :data:`SPOT_KINDS`; its
ranges are in :class:`SpotSpread` and docs/laser.md.

Pixel convention: pixel (i, j) covers [i − 0.5, i + 0.5] × [j − 0.5, j + 0.5]; positions are
(row, col) px.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.config import require
from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.core.spotfit import erf
from omnid.core.types import StereoCapture
from omnid.errors import InputError
from omnid.sim.world import LaserHits

#: Gray level outside the mirror disk (the dark camera housing).
OUTSIDE_DISK_LEVEL = 3.0


SpotKind = Literal["gaussian", "halo", "saturated", "rim", "speckle", "mixed"]
#: The spot-model families :func:`random_spots` draws from (``mixed``: every effect at random).
SPOT_KINDS: tuple[SpotKind, ...] = ("gaussian", "halo", "saturated", "rim", "speckle", "mixed")


@dataclass(frozen=True)
class SpotModel:
    """How one laser dot images in a camera: size, shape, brightness, halo, speckle, ghosts.

    Sizes are px, brightness gray levels of the continuous image before the sensor rounds and
    clips it (a peak above 255 minus the scene saturates: the flat top of a clipped spot).

    Shape: the optical blur of the camera–mirror pair, an elliptical profile
    ``exp(−(q²/2)^profile_power)`` with ``q²`` the Mahalanobis distance under the covariance
    ``σ_r² e_r e_rᵀ + σ_t² e_t e_tᵀ`` (e_r radial from the mirror centre, e_t tangential):
    σ_r = σ·(1 + rim_radial·ρ²), σ_t = σ·(1 + rim_tangential·ρ²) with ρ the distance from the
    mirror centre over the disk radius (the curved mirror's astigmatism grows with the square of
    the field), σ = ``sigma_px`` times a per-dot factor (1 ± ``sigma_jitter``, uniform: focus and
    surface differ between dots). ``profile_power`` 1 is a Gaussian, above 1 a flatter, wider top
    (a multimode or defocused beam). The light of a dot is conserved when the mirror stretches it.

    Brightness: ``peak_gray`` is the peak of a reference dot — a beam of the laser's median
    power (the exposure is set for the pattern), unstretched, on a horizontal surface at the
    installation's floor depth — times a per-dot albedo factor (1 ± ``peak_jitter``). With ``shading`` each dot's light is also scaled by
    :func:`surface_shading` (closer surfaces are brighter, walls seen face-on brighter than the
    floor seen obliquely); the beam's own power (the grating's envelope) always scales it.

    Truth: every deterministic part of a spot — the elliptical profile, the ring-shaped halo,
    the clipping of its top — is point-symmetric about the image of the 3-D dot centre, so the
    model's expected intensity centroid is exactly that projected point, and it is the truth a
    detector is scored against. The random parts (speckle grains on the dot and in its halo,
    sensor noise) move the centroid of one realised spot away from it; that displacement is part
    of the centre error and is irreducible (``tools/bench_detect.py`` reports it per model as the
    "floor": the centroid error of the noise-free realised spots). Ghosts are separate dim spots
    a few px away (reflections), not part of any dot.

    Halo: a ring-shaped glow around each dot (``halo_fraction`` of its peak, ring radius about
    ``halo_sigma_px``), broken into speckle grains of contrast ``halo_speckle`` — the light the
    floor scatters sideways. Speckle: multiplicative grains of contrast ``speckle_contrast`` and
    size ``speckle_grain_px`` (1 σ of their correlation) on the dot itself.
    """

    kind: str = "gaussian"  # the family it was drawn from (a label for reports)
    sigma_px: float = 1.3  # blur sigma at the mirror centre
    sigma_jitter: float = 0.15  # relative spread of sigma between dots
    rim_radial: float = 0.0  # relative growth of the radial sigma at the disk rim
    rim_tangential: float = 0.0  # relative growth of the tangential sigma at the disk rim
    profile_power: float = 1.0  # 1 Gaussian; > 1 a flatter top
    peak_gray: float = 150.0  # peak of the reference dot, gray levels (> 255: saturates)
    peak_jitter: float = 0.25  # relative spread of brightness between dots (albedo)
    shading: bool = False  # scale by surface_shading (distance and surface orientation)
    halo_fraction: float = 0.0  # sparkle halo brightness relative to the dot peak
    halo_sigma_px: float = 4.0  # size of the sparkle halo
    halo_speckle: float = 0.6  # relative spread of the halo's grains (0 = smooth)
    speckle_contrast: float = 0.0  # relative spread of the speckle grains on the dot
    speckle_grain_px: float = 1.0  # correlation sigma of those grains
    ghost_fraction: float = 0.0  # share of dots that throw a ghost reflection
    ghost_peak_fraction: float = 0.25  # ghost brightness relative to its dot
    ghost_offset_px: tuple[float, float] = (3.0, 6.0)  # ghost distance from its dot, min/max

    def __post_init__(self) -> None:
        require(0.3 <= self.sigma_px <= 8.0, "sigma_px", "must be in [0.3, 8] px")
        require(0.0 <= self.sigma_jitter < 0.9, "sigma_jitter", "must be in [0, 0.9)")
        for name in ("rim_radial", "rim_tangential"):
            require(-0.5 < getattr(self, name) <= 3.0, name, "must be in (−0.5, 3]")
        require(0.5 <= self.profile_power <= 5.0, "profile_power", "must be in [0.5, 5]")
        require(0.0 <= self.peak_gray <= 1.0e5, "peak_gray", "must be in [0, 1e5] gray levels")
        require(0.0 <= self.peak_jitter < 1.0, "peak_jitter", "must be in [0, 1)")
        for name in ("halo_fraction", "ghost_fraction", "ghost_peak_fraction"):
            require(0.0 <= getattr(self, name) <= 1.0, name, "must be in [0, 1]")
        require(0.5 <= self.halo_sigma_px <= 20.0, "halo_sigma_px", "must be in [0.5, 20] px")
        for name in ("halo_speckle", "speckle_contrast"):
            require(0.0 <= getattr(self, name) <= 2.0, name, "must be in [0, 2]")
        require(0.3 <= self.speckle_grain_px <= 5.0, "speckle_grain_px", "must be in [0.3, 5]")
        lo, hi = self.ghost_offset_px
        require(0.0 <= lo <= hi <= 50.0, "ghost_offset_px", "must be (min, max) in [0, 50] px")

    @classmethod
    def realistic(cls, **changes: Any) -> SpotModel:
        """The spots of :meth:`RenderOptions.realistic`: sparkle halos and a few ghosts."""
        base: dict[str, Any] = {
            "kind": "halo",
            "halo_fraction": 0.05,
            "halo_speckle": 0.3,
            "ghost_fraction": 0.03,
        }
        base.update(changes)
        return cls(**base)

    @property
    def isotropic_gaussian(self) -> bool:
        """A round Gaussian everywhere (drawn exactly, pixel-area integrated)."""
        return self.rim_radial == 0.0 and self.rim_tangential == 0.0 and self.profile_power == 1.0

    def reach_px(self) -> float:
        """How far from its centre a dot's own light reaches (profile, halo, ghost), px."""
        grow = 1.0 + max(self.rim_radial, self.rim_tangential, 0.0)
        spot = 4.0 * self.sigma_px * (1.0 + self.sigma_jitter) * grow
        ghost = max(self.ghost_offset_px) + 1.6 * spot if self.ghost_fraction > 0 else 0.0
        halo = 4.0 * self.halo_sigma_px if self.halo_fraction > 0 else 0.0
        return max(spot, halo, ghost)


@dataclass(frozen=True)
class RenderOptions:
    """How a capture is drawn: the scene, the sensor and the spots (:class:`SpotModel`).
    Intensities are 8-bit gray levels.

    The defaults are a clean capture; :meth:`realistic` adds halos, ghosts, flicker, shot noise.
    """

    spots: SpotModel = field(default_factory=SpotModel)
    background_level: float = 70.0  # mean gray inside the mirror disk
    background_texture: float = 25.0  # amplitude of the smooth scene texture
    noise_sigma: float = 2.0  # sensor read noise, gray levels (independent per frame)
    flicker: float = 0.0  # relative illumination change from mask to base
    color: bool = False  # BGR output with a green laser
    shot_noise_gain: float = 0.0  # extra noise variance per gray level of signal

    def __post_init__(self) -> None:
        require(0.0 <= self.background_level <= 255.0, "background_level", "must be in [0, 255]")
        require(0.0 <= self.background_texture <= 255.0, "background_texture", "must be ≥ 0")
        require(0.0 <= self.noise_sigma <= 50.0, "noise_sigma", "must be in [0, 50]")
        require(-0.5 < self.flicker < 1.0, "flicker", "must be in (−0.5, 1)")
        require(0.0 <= self.shot_noise_gain <= 10.0, "shot_noise_gain", "must be in [0, 10]")

    @classmethod
    def realistic(cls, spots: SpotModel | None = None, **changes: Any) -> RenderOptions:
        """Options for a realistic indoor capture (what the detection tests and benchmark use):
        read and shot noise, 3 % flicker, and ``spots`` (default :meth:`SpotModel.realistic`)."""
        base: dict[str, Any] = {
            "noise_sigma": 2.0,
            "flicker": 0.03,
            "shot_noise_gain": 0.05,
        }
        base.update(changes)
        return cls(spots=spots if spots is not None else SpotModel.realistic(), **base)


@dataclass(frozen=True)
class SpotSpread:
    """The ranges :func:`random_spots` draws from, per family (uniform; px, gray levels).

    Common to all: the reference peak (an installer sets the exposure so that the pattern
    shows well: ``peak_gray`` for a dot of median beam power), the spread between dots, and
    ``shading`` on. Families:

    - ``gaussian``: round Gaussians of ``sigma_px`` 1–3 px (the issue's range);
    - ``halo``: smaller Gaussians with a speckled sparkle halo and a few ghosts;
    - ``saturated``: bright spots, clipped at 255 by the sensor, with a flatter, wider profile;
    - ``rim``: spots stretched radially (and a little tangentially) toward the mirror's rim;
    - ``speckle``: grains of the laser's coherent light on the dot itself;
    - ``mixed``: every effect, each present with probability one half, at random strength.
    """

    sigma_px: tuple[float, float] = (1.0, 3.0)
    small_sigma_px: tuple[float, float] = (1.0, 2.0)  # the families that add another effect
    sigma_jitter: tuple[float, float] = (0.0, 0.2)
    peak_gray: tuple[float, float] = (100.0, 230.0)
    peak_jitter: tuple[float, float] = (0.05, 0.3)
    # 1.2–2.2 times what the sensor can take above the scene (≈ 185 gray) for the median dot;
    # the brightest dots (envelope, shading, albedo) clip several times over.
    saturated_peak_gray: tuple[float, float] = (220.0, 400.0)
    # A flat top is the beam's footprint blurred by the optics: wide, and smooth at the pixel
    # scale (a sharper profile would alias: its pixels' centroid would leave its centre).
    saturated_sigma_px: tuple[float, float] = (1.5, 2.5)
    profile_power: tuple[float, float] = (1.0, 2.0)
    # A halo carries 0.05–4 times the dot's own light (a matt floor to a thick carpet).
    halo_fraction: tuple[float, float] = (0.02, 0.10)
    halo_sigma_px: tuple[float, float] = (2.5, 5.0)
    # Its grains are the same coherent speckle as the dot's, averaged by the pixels alike.
    halo_speckle: tuple[float, float] = (0.05, 0.2)
    ghost_fraction: tuple[float, float] = (0.0, 0.05)
    rim_radial: tuple[float, float] = (0.4, 1.0)
    rim_tangential: tuple[float, float] = (0.0, 0.4)
    # The camera's aperture spans many of the laser's objective speckles (a 2 mm footprint 1.5 m
    # away makes grains of λz/a ≈ 0.4 mm against an aperture of a few mm), so the grains left in
    # the image are weak: a contrast of 0.03–0.1, which moves a dot's centroid by 0.01–0.07 px.
    speckle_contrast: tuple[float, float] = (0.03, 0.1)
    speckle_grain_px: tuple[float, float] = (0.5, 1.0)


def random_spots(
    rng: np.random.Generator | int, kind: SpotKind | None = None, spread: SpotSpread | None = None
) -> SpotModel:
    """A spot model drawn from ``spread``: of family ``kind`` (default: a family at random)."""
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    s = spread or SpotSpread()
    if kind is None:
        kind = SPOT_KINDS[int(gen.integers(len(SPOT_KINDS)))]
    if kind not in SPOT_KINDS:
        raise InputError(f"spot model {kind!r}: unknown (known: {', '.join(SPOT_KINDS)})")

    def u(pair: tuple[float, float]) -> float:
        return float(gen.uniform(*pair))

    params: dict[str, Any] = {
        "kind": kind,
        "sigma_jitter": u(s.sigma_jitter),
        "peak_gray": u(s.peak_gray),
        "peak_jitter": u(s.peak_jitter),
        "shading": True,
        "sigma_px": u(s.sigma_px if kind == "gaussian" else s.small_sigma_px),
    }
    mixed = kind == "mixed"
    on = {k: (not mixed and kind == k) or (mixed and gen.uniform() < 0.5) for k in SPOT_KINDS}
    if on["halo"]:
        params.update(
            halo_fraction=u(s.halo_fraction),
            halo_sigma_px=u(s.halo_sigma_px),
            halo_speckle=u(s.halo_speckle),
            ghost_fraction=u(s.ghost_fraction),
        )
    if on["saturated"]:
        params.update(
            peak_gray=u(s.saturated_peak_gray),
            profile_power=u(s.profile_power),
            sigma_px=u(s.saturated_sigma_px),
        )
    if on["rim"]:
        params.update(rim_radial=u(s.rim_radial), rim_tangential=u(s.rim_tangential))
    if on["speckle"]:
        params.update(
            speckle_contrast=u(s.speckle_contrast), speckle_grain_px=u(s.speckle_grain_px)
        )
    return SpotModel(**params)


def _pixel_fractions(
    centre: NDArray[np.float64], sigma: NDArray[np.float64], start: NDArray[np.int64], width: int
) -> NDArray[np.float64]:
    """Share (N, width) of a 1-D Gaussian's mass falling in pixels start … start+width−1."""
    edges = start[:, None] - 0.5 + np.arange(width + 1)[None, :]
    cdf = 0.5 * erf((edges - centre[:, None]) / (math.sqrt(2.0) * sigma[:, None]))
    return np.diff(cdf, axis=1)


def _accumulate(
    shape: tuple[int, int], r0: NDArray[np.int64], c0: NDArray[np.int64], vals: NDArray
) -> tuple[int, int, NDArray[np.float64]]:
    """Sum per-dot windows ``vals`` (N, w, w) whose first pixels are (r0, c0) into the smallest
    patch of an image of ``shape`` that holds them all: (first row, first column, patch).
    Summing into the patch instead of the whole frame keeps the cost proportional to the dots'
    area; the parts of windows outside the image are dropped."""
    rows, cols = shape
    width = vals.shape[1]
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


def _spot_patch(
    shape: tuple[int, int],
    pos: NDArray[np.float64],
    sig: NDArray[np.float64],
    amp: NDArray[np.float64],
) -> tuple[int, int, NDArray[np.float64]]:
    """Round Gaussian spots (already filtered to finite, on-image ones), each pixel holding the
    Gaussian's integral over its area, drawn into a patch (see :func:`_accumulate`)."""
    half = math.ceil(4.0 * float(sig.max()))
    width = 2 * half + 2
    r0 = np.floor(pos[:, 0]).astype(np.int64) - half
    c0 = np.floor(pos[:, 1]).astype(np.int64) - half
    pr = _pixel_fractions(pos[:, 0], sig, r0, width)
    pc = _pixel_fractions(pos[:, 1], sig, c0, width)
    mass = amp * 2.0 * math.pi * sig * sig
    vals = (mass[:, None] * pr)[:, :, None] * pc[:, None, :]
    return _accumulate(shape, r0, c0, vals)


#: Window half-sizes (px) the general spots are grouped by (one vectorised pass per group).
_HALF_SIZES = (3, 5, 7, 10, 14, 20, 28)


def _add_shaped_spots(
    img: NDArray,
    pos: NDArray[np.float64],
    cov: NDArray[np.float64],
    peak: NDArray[np.float64],
    power: float,
) -> None:
    """Add elliptical spots ``peak · exp(−(q²/2)^power)`` (q² = Mahalanobis distance under
    ``cov`` (N, 2, 2) px²) into ``img`` in place.

    The profile is sampled at pixel centres after adding the pixel's own box (variance 1/12
    per axis) to the covariance — its centroid stays the spot's centre exactly (the sampled
    profile is symmetric about it and smooth at the pixel scale) and its light is conserved.
    """
    shape = (img.shape[0], img.shape[1])
    eff = cov + np.eye(2) / 12.0
    det = eff[:, 0, 0] * eff[:, 1, 1] - eff[:, 0, 1] ** 2
    inv_a = (eff[:, 1, 1] / det).astype(np.float32)
    inv_b = (-eff[:, 0, 1] / det).astype(np.float32)
    inv_c = (eff[:, 0, 0] / det).astype(np.float32)
    # Light conserved: the peak falls as the pixel box and any stretch widen the spot.
    top_val = (peak * np.sqrt(np.linalg.det(cov)) / np.sqrt(det)).astype(np.float32)
    # Reach: 4 sigmas of a Gaussian (3 of a flatter profile) along the longest axis.
    longest = np.sqrt(
        0.5 * (eff[:, 0, 0] + eff[:, 1, 1])
        + np.sqrt(0.25 * (eff[:, 0, 0] - eff[:, 1, 1]) ** 2 + eff[:, 0, 1] ** 2)
    )
    need = (4.0 if power <= 1.2 else 3.0) * longest
    bucket = np.searchsorted(np.array(_HALF_SIZES, dtype=np.float64), need)
    bucket = np.minimum(bucket, len(_HALF_SIZES) - 1)
    for k in np.unique(bucket):
        sel = np.flatnonzero(bucket == k)
        half = _HALF_SIZES[int(k)]
        width = 2 * half + 1
        rc0 = np.rint(pos[sel]).astype(np.int64) - half
        span = np.arange(width, dtype=np.float32)
        dr = (rc0[:, 0] - pos[sel, 0]).astype(np.float32)[:, None] + span[None, :]  # (n, w)
        dc = (rc0[:, 1] - pos[sel, 1]).astype(np.float32)[:, None] + span[None, :]
        q = (
            inv_a[sel, None, None] * (dr * dr)[:, :, None]
            + (2.0 * inv_b[sel, None, None]) * (dr[:, :, None] * dc[:, None, :])
            + inv_c[sel, None, None] * (dc * dc)[:, None, :]
        )
        q *= np.float32(0.5)
        if power != 1.0:
            q = np.power(q, np.float32(power))
        vals = top_val[sel, None, None] * np.exp(-q)
        top, left, patch = _accumulate(shape, rc0[:, 0], rc0[:, 1], vals)
        img[top : top + patch.shape[0], left : left + patch.shape[1]] += patch


def _spot_covariances(
    cam: MirrorCamera, pos: NDArray[np.float64], sig: NDArray[np.float64], spots: SpotModel
) -> NDArray[np.float64]:
    """Per-dot image covariances (N, 2, 2) px²: σ_r along the mirror's radius, σ_t across it,
    each growing with the square of the distance from the mirror centre (see SpotModel)."""
    d = pos - np.array([cam.center_row_px, cam.center_col_px])
    rho = np.hypot(d[:, 0], d[:, 1])
    frac2 = (rho / cam.disk_radius_px) ** 2
    s_r = sig * (1.0 + spots.rim_radial * frac2)
    s_t = sig * (1.0 + spots.rim_tangential * frac2)
    e = np.where(rho[:, None] > 1e-9, d / np.maximum(rho, 1e-9)[:, None], [1.0, 0.0])
    er = e[:, :, None] * e[:, None, :]
    et = np.eye(2)[None] - er
    return (s_r * s_r)[:, None, None] * er + (s_t * s_t)[:, None, None] * et


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
    spots: SpotModel,
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    """Sparkle halos: a ring-shaped glow around each dot, broken into speckle grains.

    The glow is ``e^(−r²/2s²) − e^(−r²/2(s/2)²)`` with ``s = halo_sigma_px`` (zero at the dot's
    centre, largest at r ≈ 0.96·s, i.e. between neighbouring dots), scaled so its largest
    value is ``halo_fraction`` · the dot's peak; the grains multiply it by (1 + speckle).
    """
    rows, cols = shape
    s1 = spots.halo_sigma_px
    s2 = 0.5 * s1
    r2 = 2.0 * math.log(s1 * s1 / (s2 * s2)) * s1 * s1 * s2 * s2 / (s1 * s1 - s2 * s2)
    ring_peak = math.exp(-r2 / (2 * s1 * s1)) - math.exp(-r2 / (2 * s2 * s2))
    # Impulses spread bilinearly over the 4 pixels around each dot centre (so the glow is
    # centred on the dot), then blurred; a blurred unit impulse peaks at 1/(2π s²).
    r0 = np.floor(pos[:, 0]).astype(np.int64)
    c0 = np.floor(pos[:, 1]).astype(np.int64)
    fr = pos[:, 0] - r0
    fc = pos[:, 1] - c0
    mass = amp * spots.halo_fraction / ring_peak
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
    if spots.halo_speckle <= 0:
        return glow
    grains = _randn(shape, rng)
    grains = cv2.GaussianBlur(grains, (0, 0), 0.8).astype(np.float32)
    grains *= spots.halo_speckle / max(float(grains.std()), 1e-6)
    return glow * np.maximum(1.0 + grains, 0.0)


def _randn(
    shape: tuple[int, int], rng: np.random.Generator, sigma: float = 1.0
) -> NDArray[np.float32]:
    """Normal float32 samples of standard deviation ``sigma`` from OpenCV's generator
    (``cv2.randn``: 4x faster than numpy's; it scales N(0, 1) samples in float32, so a sigma
    here is bit for bit a multiplication after), seeded from ``rng`` so that a capture stays a
    function of its seed. OpenCV's default generator is per thread, so concurrent renders do
    not disturb each other."""
    out = np.empty(shape, dtype=np.float32)
    cv2.setRNGSeed(int(rng.integers(1, 2**31 - 1)))
    cv2.randn(out, 0.0, sigma)  # type: ignore[call-overload, unused-ignore]  # (stubs want arrays, not floats)
    return out


def _noise(
    signal: NDArray[np.float32], options: RenderOptions, rng: np.random.Generator
) -> NDArray[np.float32]:
    shape = (signal.shape[0], signal.shape[1])
    if options.shot_noise_gain > 0:
        noise = _randn(shape, rng)
        var = np.float32(options.noise_sigma**2) + np.float32(options.shot_noise_gain) * np.maximum(
            signal, np.float32(0.0)
        )
        noise *= cv2.sqrt(var)
        return noise
    return _randn(shape, rng, options.noise_sigma)


def sensor_image(
    signal: NDArray[np.float32], options: RenderOptions, rng: np.random.Generator
) -> NDArray[np.uint8]:
    """What the sensor makes of the light ``signal`` (float32 gray levels): plus read and shot
    noise (``options``, drawn from ``rng``), rounded half to even and saturated to 0…255."""
    noise = _noise(signal, options, rng)
    return np.asarray(cv2.add(signal, noise, dtype=cv2.CV_8U), dtype=np.uint8)  # type: ignore[call-overload, unused-ignore]  # opencv 5.0 stubs only


class LiveSensor:
    """A still scene as a live sensor delivers it, frame after frame: each call adds fresh read
    noise (``noise_sigma`` gray levels, rounded), so no two frames are equal — as with a real
    camera, whose device sources refuse a repeated frame as frozen (``omnid.devices.camera``).
    For frame servers that serve fixed captures (tests, benchmarks)."""

    def __init__(self, seed: int = 0, noise_sigma: float = 0.7) -> None:
        self._rng = np.random.default_rng(seed)
        self._options = RenderOptions(noise_sigma=noise_sigma)

    def __call__(self, scene: NDArray[np.generic]) -> NDArray[np.uint8]:
        return sensor_image(np.asarray(scene, dtype=np.float32), self._options, self._rng)


def _box_around(
    pos: NDArray[np.float64], reach_px: float, shape: tuple[int, int]
) -> tuple[int, int, int, int]:
    """(top, left, bottom, right) of the dots' bounding box widened by ``reach_px``, in the image."""
    reach = math.ceil(reach_px) + 2
    top = max(int(np.floor(pos[:, 0].min())) - reach, 0)
    left = max(int(np.floor(pos[:, 1].min())) - reach, 0)
    bottom = min(int(np.ceil(pos[:, 0].max())) + reach + 1, shape[0])
    right = min(int(np.ceil(pos[:, 1].max())) + reach + 1, shape[1])
    return top, left, bottom, right


def _grains(
    shape: tuple[int, int], contrast: float, grain_px: float, rng: np.random.Generator
) -> NDArray[np.float32]:
    """Multiplicative speckle factors max(1 + contrast·g, 0), g correlated over ``grain_px``."""
    g = cv2.GaussianBlur(_randn(shape, rng), (0, 0), grain_px).astype(np.float32)
    g *= np.float32(contrast) / max(float(g.std()), 1e-6)
    g += np.float32(1.0)
    return np.maximum(g, np.float32(0.0))


def _laser_light(
    cam: MirrorCamera,
    pos: NDArray[np.float64],
    sig: NDArray[np.float64],
    amp: NDArray[np.float64],
    spots: SpotModel,
    disk: NDArray[np.bool_],
    rng: np.random.Generator,
) -> NDArray[np.float32]:
    """The laser's light in one camera image (float32 gray levels) for dots at ``pos`` (N, 2)
    inside the disk, each with its blur ``sig`` and unstretched peak ``amp`` (see SpotModel)."""
    shape = cam.image_shape
    n = len(pos)
    laser = np.zeros(shape, dtype=np.float32)
    if n == 0:
        return laser
    if spots.isotropic_gaussian:
        _add_spots(laser, pos, sig, amp)
    else:
        ok = np.isfinite(pos).all(axis=1)
        cov = _spot_covariances(cam, pos[ok], sig[ok], spots)
        stretch = np.sqrt(np.linalg.det(cov)) / (sig[ok] * sig[ok])
        _add_shaped_spots(laser, pos[ok], cov, amp[ok] / stretch, spots.profile_power)
    top, left, bottom, right = _box_around(pos, spots.reach_px(), shape)
    if bottom <= top or right <= left:
        return laser
    if spots.speckle_contrast > 0:
        box = (slice(top, bottom), slice(left, right))
        laser[box] *= _grains(
            (bottom - top, right - left), spots.speckle_contrast, spots.speckle_grain_px, rng
        )
    if spots.halo_fraction > 0:
        # The glow reaches ~4 halo sigmas: draw it (and its grains) in the box of the dots.
        t, lf, bt, rt = _box_around(pos, 4.0 * spots.halo_sigma_px, shape)
        laser[t:bt, lf:rt] += _halos((bt - t, rt - lf), pos - (t, lf), amp, spots, rng)
    if spots.ghost_fraction > 0:
        has_ghost = rng.uniform(size=n) < spots.ghost_fraction
        k = int(has_ghost.sum())
        lo, hi = spots.ghost_offset_px
        dist = rng.uniform(lo, hi, k)
        ang = rng.uniform(0.0, 2.0 * math.pi, k)
        gpos = pos[has_ghost] + np.column_stack([dist * np.sin(ang), dist * np.cos(ang)])
        gamp = amp[has_ghost] * spots.ghost_peak_fraction
        _add_spots(laser, gpos, 1.6 * sig[has_ghost], gamp)
    # Light outside the mirror disk is lost; the laser is nonzero only around the dots.
    laser[top:bottom, left:right] *= disk[top:bottom, left:right]
    return laser


def _dots_in_disk(
    cam: MirrorCamera, rc: ArrayLike, flux: ArrayLike | None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """The dots (K, 2) inside the mirror disk, their flux (K,), and the disk's pixel mask."""
    pos = np.asarray(rc, dtype=np.float64).reshape(-1, 2)
    keep = cam.in_disk(pos) if len(pos) else np.zeros(0, dtype=bool)
    f = np.ones(len(pos)) if flux is None else np.broadcast_to(np.asarray(flux, float), len(pos))
    return pos[keep], f[keep], disk_mask(cam)


def disk_mask(cam: MirrorCamera) -> NDArray[np.bool_]:
    """(rows, cols) bool: the pixels inside the camera's mirror disk (read-only, computed once
    per camera)."""
    rows, cols = cam.image_shape
    return _disk_mask(rows, cols, cam.center_row_px, cam.center_col_px, cam.disk_radius_px)


@functools.lru_cache(maxsize=16)
def _disk_mask(
    rows: int, cols: int, center_row_px: float, center_col_px: float, radius_px: float
) -> NDArray[np.bool_]:
    """:func:`disk_mask`, by the camera's numbers."""
    dr = np.arange(rows, dtype=np.float32)[:, None] - np.float32(center_row_px)
    dc = np.arange(cols, dtype=np.float32)[None, :] - np.float32(center_col_px)
    disk = (dr * dr + dc * dc) <= np.float32(radius_px**2)
    disk.flags.writeable = False
    return disk


def _spot_draws(
    spots: SpotModel, flux: NDArray[np.float64], rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-dot blur sigma (px) and unstretched peak (gray levels), the first draws of a render."""
    n = len(flux)
    sig = spots.sigma_px * (1.0 + spots.sigma_jitter * rng.uniform(-1, 1, n))
    amp = spots.peak_gray * (1.0 + spots.peak_jitter * rng.uniform(-1, 1, n)) * flux
    return sig, amp


def laser_image(
    cam: MirrorCamera,
    rc: ArrayLike,
    spots: SpotModel,
    rng: np.random.Generator | int = 0,
    flux: ArrayLike | None = None,
) -> NDArray[np.float32]:
    """The laser's light alone (float32 gray levels, before the sensor's noise, rounding and
    clipping) in one camera for dots at image positions ``rc`` (N, 2) px, each of relative
    light ``flux`` — the spots :func:`render_camera_pair` adds to the scene."""
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    pos, f, disk = _dots_in_disk(cam, rc, flux)
    sig, amp = _spot_draws(spots, f, gen)
    return _laser_light(cam, pos, sig, amp, spots, disk, gen)


def mean_spot(
    cam: MirrorCamera,
    rc: ArrayLike,
    sigma_px: float,
    peak_gray: float,
    spots: SpotModel,
    top_left: tuple[int, int],
    shape: tuple[int, int],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The expected light of ONE dot at image position ``rc`` (row, col) px, of blur
    ``sigma_px`` and unstretched peak ``peak_gray`` (one realisation of :func:`_spot_draws`), in
    the window of ``shape`` whose first pixel is ``top_left``: (the dot's own profile, its
    profile plus its halo), float64 gray levels, drawn exactly as :func:`laser_image` draws them
    but without the random parts (speckle grains have mean 1; ghosts are other spots) and
    without the disk's edge. Used for the Cramér–Rao bound of the centre
    (:mod:`omnid.experiments.detection`)."""
    pos = np.asarray(rc, dtype=np.float64).reshape(1, 2)
    local = pos - np.asarray(top_left, dtype=np.float64)
    sig = np.array([sigma_px], dtype=np.float64)
    amp = np.array([peak_gray], dtype=np.float64)
    dot = np.zeros(shape, dtype=np.float64)
    if spots.isotropic_gaussian:
        _add_spots(dot, local, sig, amp)
    else:
        cov = _spot_covariances(cam, pos, sig, spots)
        stretch = np.sqrt(np.linalg.det(cov)) / (sig * sig)
        _add_shaped_spots(dot, local, cov, amp / stretch, spots.profile_power)
    total = dot.copy()
    if spots.halo_fraction > 0:
        smooth = SpotModel(
            halo_fraction=spots.halo_fraction, halo_sigma_px=spots.halo_sigma_px, halo_speckle=0.0
        )
        total += _halos(shape, local, amp, smooth, np.random.default_rng(0))
    return dot, total


def render_camera_pair(
    cam: MirrorCamera,
    rc: ArrayLike,
    options: RenderOptions,
    rng: np.random.Generator,
    flux: ArrayLike | None = None,
    scene_seed: int | None = None,
) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Mask and base images of one camera for dots at image positions ``rc`` (N, 2) px.

    ``flux`` (N,) scales each dot's light (the beam's power and :func:`surface_shading`; default
    1). ``scene_seed`` fixes the scene's texture (a camera fixed to the chair sees the same
    scene frame after frame; default: drawn from ``rng`` like everything else). Gray (H, W)
    uint8, or BGR (H, W, 3) uint8 when ``options.color``. Dots outside the mirror disk are not
    drawn; the part of a dot's light outside the disk is lost; the sensor rounds and clips at
    0 and 255.
    """
    pos, f, disk = _dots_in_disk(cam, rc, flux)
    spots = options.spots
    sig, amp = _spot_draws(spots, f, rng)
    if scene_seed is None:
        scene = _scene(disk, options.background_level, options.background_texture, rng)
    else:  # the same scene every time: drawn once
        scene = _fixed_scene(cam, options.background_level, options.background_texture, scene_seed)
    laser = _laser_light(cam, pos, sig, amp, spots, disk, rng)
    lit = scene if options.flicker == 0.0 else scene * np.float32(1.0 + options.flicker)
    if not options.color:
        mask = sensor_image(scene, options, rng)
        return mask, sensor_image(lit + laser, options, rng)
    # Green laser over a slightly tinted scene: each channel has its own gain and noise; the
    # laser is strong in G with a little cross-talk into B and R.
    tint = (0.9, 1.0, 1.1)
    cross = (0.12, 1.0, 0.18)
    masks = []
    bases = []
    for t, x in zip(tint, cross, strict=True):
        sc = scene * np.float32(t)
        sl = lit * np.float32(t) + laser * np.float32(x)
        masks.append(sensor_image(sc, options, rng))
        bases.append(sensor_image(sl, options, rng))
    return np.asarray(cv2.merge(masks), dtype=np.uint8), np.asarray(
        cv2.merge(bases), dtype=np.uint8
    )


def _scene(
    disk: NDArray[np.bool_], level: float, texture_gray: float, rng: np.random.Generator
) -> NDArray[np.float32]:
    """The scene a camera sees without laser (float32 gray levels): ``level`` plus a smooth
    texture of amplitude ``texture_gray`` inside the mirror ``disk``, the housing outside."""
    texture = _smooth_texture((disk.shape[0], disk.shape[1]), rng)
    return np.where(disk, level + texture_gray * texture, OUTSIDE_DISK_LEVEL).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _fixed_scene(
    cam: MirrorCamera, level: float, texture_gray: float, scene_seed: int
) -> NDArray[np.float32]:
    """:func:`_scene` of texture seed ``scene_seed`` (read-only: computed once per camera)."""
    scene = _scene(disk_mask(cam), level, texture_gray, np.random.default_rng(scene_seed))
    scene.flags.writeable = False
    return scene


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
    flux: ArrayLike | None = None,
) -> StereoCapture:
    """A stereo mask/base capture of laser dots at known 3-D positions (N, 3) mm, each of
    relative light ``flux`` (N,) (default 1: no beam envelope, no shading; see
    :func:`render_hits` for the laser's hits with both).

    Dots outside a mirror's disk (or behind the mirror plane) are not drawn in that camera.
    """
    opts = options or RenderOptions()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    xyz = np.asarray(dots_xyz_mm, dtype=np.float64).reshape(-1, 3)
    m1, b1 = render_camera_pair(rig.cam1, rig.cam1.project(xyz), opts, rng, flux)
    m2, b2 = render_camera_pair(rig.cam2, rig.cam2.project(xyz), opts, rng, flux)
    return StereoCapture(m1, b1, m2, b2)


def surface_shading(
    xyz_mm: ArrayLike, normal: ArrayLike, mirror_y_mm: float, floor_depth_mm: float
) -> NDArray[np.float64]:
    """Relative light (N,) a camera receives from laser dots at rig-frame points ``xyz_mm``
    (N, 3) on surfaces of unit ``normal`` (N, 3) (pointing to the open side), for the mirror at
    (0, ``mirror_y_mm``, 0): 1 for a dot on a horizontal surface at ``floor_depth_mm``.

    A dot's light is ρ·P (albedo, beam power) scattered like a Lambertian surface: its radiant
    intensity toward the mirror is ∝ n·v (v the unit vector from the dot to the mirror). What
    the camera collects of it follows from the mirror model (SPEC §2), a central projection
    x = −(f/K)·X/Z: a patch of area dA images to (f/K)²·(n·v)·dA / (Z²·cos θ) (θ the sight
    line's angle from the vertical, cos θ = Z/d), and radiance is conserved, so the light of a
    dot scales as (n·v)/cos θ · 1/Z². On horizontal surfaces n·v = cos θ: the light depends on
    the depth only (a uniformly lit floor images uniformly), ∝ (H/Z)²; a wall seen face-on is
    brighter than the floor seen obliquely at the same place. Dots facing away give 0.
    """
    p = np.asarray(xyz_mm, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normal, dtype=np.float64).reshape(-1, 3)
    v = np.column_stack([-p[:, 0], mirror_y_mm - p[:, 1], -p[:, 2]])
    d = np.linalg.norm(v, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        n_dot_v = np.einsum("ij,ij->i", n, v) / d
        cos_theta = p[:, 2] / d
        out = n_dot_v / cos_theta * (floor_depth_mm / p[:, 2]) ** 2
    return np.where(np.isfinite(out) & (p[:, 2] > 0), np.maximum(out, 0.0), 0.0)


def hits_flux(hits: LaserHits, rig: StereoRig, spots: SpotModel) -> NDArray[np.float64]:
    """Relative light (N, 2) of each hit in camera 1 and 2: the beam's power over the laser's
    median beam power (the exposure is set for the pattern: a dot of median power on the floor
    has ``spots.peak_gray``), times :func:`surface_shading` when ``spots.shading``."""
    b = np.asarray(hits.brightness, dtype=np.float64)
    if len(b):
        b = b / max(float(np.median(b)), 1e-12)
    if not spots.shading:
        return np.column_stack([b, b])
    return np.column_stack(
        [
            b * surface_shading(hits.xyz, hits.normal, cam.y_mm, rig.floor_depth_mm)
            for cam in (rig.cam1, rig.cam2)
        ]
    )


def render_hits(
    rig: StereoRig,
    hits: LaserHits,
    seed: int | np.random.Generator = 0,
    options: RenderOptions | None = None,
    beam_light: bool = True,
) -> StereoCapture:
    """Mask/base capture of cast laser hits: each camera shows the dots it sees
    (``visible1`` / ``visible2``), each with its beam's power and, with ``spots.shading``, the
    surface's shading (:func:`hits_flux`). ``beam_light=False``: every dot of the reference
    light instead (how the simulated installer's captures and the random-rig evaluation are
    rendered). The true centre of each dot is its projection ``rig.project(hits.xyz)``
    (= ``hits.pixels``)."""
    opts = options or RenderOptions()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    flux = hits_flux(hits, rig, opts.spots) if beam_light else None
    images: list[NDArray[np.uint8]] = []
    for k, (cam, vis) in enumerate(((rig.cam1, hits.visible1), (rig.cam2, hits.visible2))):
        light = None if flux is None else flux[vis, k]
        images.extend(render_camera_pair(cam, cam.project(hits.xyz[vis]), opts, rng, light))
    return StereoCapture(images[0], images[1], images[2], images[3])
