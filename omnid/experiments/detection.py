"""Dot detection scored over the spot models: random rigs, random lasers, random spots.

One *case* is a capture of a named scene on a rig drawn with :func:`~omnid.sim.rigs.random_rig`,
lit by a laser drawn with :func:`~omnid.sim.laser.random_laser`, its dots imaged by a spot
model of one family drawn with :func:`~omnid.sim.render.random_spots`, under the realistic
sensor (read and shot noise, 3 % flicker). The truth of each dot is the projection of its 3-D
centre (docs/laser.md). Scoring, per camera:

    recall      true dots ≥ 4 px inside the mirror disk with a detection within 1.5 px
    false dots  detections (≥ 4 px inside the disk) with no true dot within 1.5 px, plus
                second detections of one dot
    centre RMS  over the matched dots that are *isolated*: no other true dot within
                2.5 · the spot sigma (a doubled beam closer than that images as one blob; it
                is found, but no single centre is its truth)

Used by ``tools/bench_detect.py`` and the detection tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.core.types import StereoCapture
from omnid.sim.laser import random_laser
from omnid.sim.render import (
    SPOT_KINDS,
    RenderOptions,
    SpotKind,
    SpotModel,
    hits_flux,
    laser_image,
    mean_spot,
    random_spots,
    render_hits,
)
from omnid.sim.rigs import random_rig
from omnid.sim.scenes import get_scene
from omnid.sim.specs import stream
from omnid.sim.world import LaserHits, cast_laser

#: Dots this close to the mirror disk's edge lose light to it: not scored, px.
EDGE_MARGIN_PX = 4.0
#: A detection within this of a true dot finds it, px.
MATCH_TOL_PX = 1.5
#: Scenes the cases alternate between.
CASE_SCENES = ("floor", "three_boxes")


@dataclass(frozen=True)
class Case:
    """One capture with its truth: rig, laser hits, spot model."""

    kind: str
    index: int
    rig: StereoRig
    hits: LaserHits
    spots: SpotModel
    capture: StereoCapture

    def truth(self, camera: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """True centres (K, 2) px of the dots camera 1 or 2 sees (≥ the edge margin inside its
        disk), and which of them are isolated (see the module doc)."""
        cam = self.rig.cam1 if camera == 1 else self.rig.cam2
        vis = self.hits.visible1 if camera == 1 else self.hits.visible2
        cols = slice(0, 2) if camera == 1 else slice(2, 4)
        t = self.hits.pixels[vis][:, cols]
        t = t[cam.in_disk(t, EDGE_MARGIN_PX)]
        return t, isolated(t, self.spots)


def isolated(truth: NDArray[np.float64], spots: SpotModel) -> NDArray[np.bool_]:
    """(K,) true dots with no other within 2.5 spot sigmas (the largest the model makes)."""
    if len(truth) < 2:
        return np.ones(len(truth), dtype=bool)
    grow = 1.0 + max(spots.rim_radial, spots.rim_tangential, 0.0)
    blend = max(3.0, 2.5 * spots.sigma_px * grow)
    d = np.hypot(truth[:, None, 0] - truth[None, :, 0], truth[:, None, 1] - truth[None, :, 1])
    np.fill_diagonal(d, np.inf)
    return np.asarray(d.min(axis=1) >= blend)


def without_grains(spots: SpotModel) -> SpotModel:
    """The same spot model without its random parts (speckle grains on the dots and in their
    halos): every spot point-symmetric about its projected centre."""
    return replace(spots, speckle_contrast=0.0, halo_speckle=0.0)


def has_grains(spots: SpotModel) -> bool:
    """Whether the model's spots carry speckle grains (on the dot or in a halo)."""
    return spots.speckle_contrast > 0 or (spots.halo_fraction > 0 and spots.halo_speckle > 0)


def case(kind: SpotKind, index: int, grains: bool = True) -> Case:
    """The ``index``-th case of spot family ``kind`` (deterministic: the seed is derived from
    both, with one stream per drawn thing); ``grains=False``: the same rig, laser, scene and
    spot model :func:`without_grains` (the sensor's noise is another draw)."""
    seed = 1000 * SPOT_KINDS.index(kind) + index
    rig = random_rig(stream(seed, "rig"))
    laser = random_laser(stream(seed, "laser"))
    spots = random_spots(stream(seed, "spots"), kind)
    if not grains:
        spots = without_grains(spots)
    scene = get_scene(CASE_SCENES[index % len(CASE_SCENES)])
    hits = cast_laser(scene.world, scene.pose, scene.mount, laser, rig)
    capture = render_hits(rig, hits, seed, RenderOptions.realistic(spots=spots))
    return Case(kind, index, rig, hits, spots, capture)


def spot_floor_px(spots: SpotModel, cam: MirrorCamera, seed: int = 0) -> float:
    """The irreducible centre error of a spot model, px: the RMS distance between the
    centroid of the noise-free light of isolated realised spots (their own halo included, no
    sensor, no neighbours) and the projected point. Zero for deterministic models; the speckle
    grains on a dot and in its halo move it."""
    rng = np.random.default_rng(seed)
    spots = replace(spots, ghost_fraction=0.0)
    half = math.ceil(spots.reach_px())
    step = 2 * half + 4
    g = np.arange(-cam.disk_radius_px, cam.disk_radius_px, step)
    rr, cc = np.meshgrid(g, g, indexing="ij")
    centre = np.array([cam.center_row_px, cam.center_col_px])
    pts = np.column_stack([rr.ravel(), cc.ravel()]) + centre
    pts = pts[cam.in_disk(pts, half + 2.0)]
    pts = pts + rng.uniform(-0.5, 0.5, pts.shape)
    img = laser_image(cam, pts, spots, rng)
    off = np.arange(-half, half + 1)
    errs = []
    for r, c in pts:
        r0, c0 = round(r), round(c)
        win = img[r0 - half : r0 + half + 1, c0 - half : c0 + half + 1].astype(np.float64)
        m = win.sum()
        errs.append([r0 + (win.sum(axis=1) @ off) / m - r, c0 + (win.sum(axis=0) @ off) / m - c])
    e = np.asarray(errs)
    return float(np.sqrt((e**2).sum(axis=1).mean()))


@dataclass(frozen=True)
class Score:
    """Detection against truth in one image: ``recall`` (0–1), ``false_dots``, the centre
    errors (M, 2) px of the isolated matched dots and their indices ``matched`` (M,) into the
    truth, and the number of true dots."""

    recall: float
    false_dots: int
    errors: NDArray[np.float64]
    dots: int
    matched: NDArray[np.intp] = field(default_factory=lambda: np.zeros(0, np.intp))

    def on(self, dots: NDArray[np.intp]) -> NDArray[np.float64]:
        """The errors of the matched dots among ``dots`` (truth indices)."""
        return self.errors[np.isin(self.matched, dots)]

    @property
    def rms_px(self) -> float:
        e = self.errors
        return float(np.sqrt((e**2).sum(axis=1).mean())) if len(e) else float("nan")


def score(
    found: NDArray[np.float64],
    truth: NDArray[np.float64],
    iso: NDArray[np.bool_],
    cam: MirrorCamera,
) -> Score:
    """Score detections ``found`` (N, ≥2) against ``truth`` (K, 2) (see the module doc)."""
    f = np.asarray(found, dtype=np.float64)
    if len(f):
        f = f[cam.in_disk(f[:, :2], EDGE_MARGIN_PX)]
    if len(truth) == 0:
        return Score(1.0, len(f), np.zeros((0, 2)), 0)
    if len(f) == 0:
        return Score(0.0, 0, np.zeros((0, 2)), len(truth))
    d = np.hypot(f[:, None, 0] - truth[None, :, 0], f[:, None, 1] - truth[None, :, 1])
    j = d.argmin(axis=1)
    near = d.min(axis=1) < MATCH_TOL_PX
    nearest = np.where(near[:, None], d, np.inf).argmin(axis=0)  # best detection per dot
    first = near & (nearest[j] == np.arange(len(f)))
    found_dot = np.zeros(len(truth), dtype=bool)
    found_dot[j[first]] = True
    false_dots = int((~near).sum() + (near & ~first).sum())
    keep = first & iso[j]
    errors = f[keep, :2] - truth[j[keep]]
    return Score(float(found_dot.mean()), false_dots, errors, len(truth), j[keep].astype(np.intp))


def pooled_rms(scores: list[Score] | list[NDArray[np.float64]]) -> float:
    """RMS over all the isolated matched dots of several images (scores or error arrays), px."""
    e = [s.errors if isinstance(s, Score) else s for s in scores]
    e = [x for x in e if len(x)]
    if not e:
        return float("nan")
    all_e = np.vstack(e)
    return float(np.sqrt((all_e**2).sum(axis=1).mean()))


#: The rendered sensor saturates here: a pixel rounding to 255 says only "≥ 254.5", gray.
_CLIP_GRAY = 254.5


def _censored_information(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fisher information about the mean of a unit-variance Gaussian observation censored above
    at ``z`` standard deviations from its mean, relative to the uncensored one:
    Φ(z) − zφ(z) + φ(z)²/(1 − Φ(z)) (1 far below the clip, → 0 deep in it)."""
    z = np.clip(z, -12.0, 12.0)
    phi = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    cdf = 0.5 * (1.0 + np.vectorize(math.erf)(z / math.sqrt(2.0)))
    tail = np.maximum(1.0 - cdf, 1e-300)
    return np.clip(cdf - z * phi + phi * phi / tail, 0.0, 1.0)


def _grain_correlation(shape: tuple[int, int], grain_px: float) -> NDArray[np.float64]:
    """(P, P) correlation of a white field blurred by a Gaussian of ``grain_px`` between the
    pixels of a window of ``shape``: exp(−d²/4s²)."""
    rr, cc = np.indices(shape)
    r, c = rr.ravel().astype(np.float64), cc.ravel().astype(np.float64)
    d2 = (r[:, None] - r[None, :]) ** 2 + (c[:, None] - c[None, :]) ** 2
    return np.asarray(np.exp(-d2 / (4.0 * grain_px * grain_px)))


def _light(
    cam: MirrorCamera,
    spots: SpotModel,
    rc: NDArray[np.float64],
    sigma_px: float,
    peak_gray: float,
    window: tuple[tuple[int, int], tuple[int, int]],
) -> NDArray[np.float64]:
    """One dot's expected light (profile and halo) in ``window`` = (top_left, shape)."""
    return mean_spot(cam, rc, sigma_px, peak_gray, spots, window[0], window[1])[1]


def _spot_jacobian(
    cam: MirrorCamera,
    spots: SpotModel,
    p: NDArray[np.float64],
    sigma_px: float,
    peak_gray: float,
    window: tuple[tuple[int, int], tuple[int, int]],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """One dot's expected light in ``window``: (its profile, profile + halo, the derivatives
    (P, 4) of the latter with respect to row, col, brightness and blur σ)."""
    delta = 0.02
    dot, mu = mean_spot(cam, p, sigma_px, peak_gray, spots, window[0], window[1])
    dr, dc = np.array([delta, 0.0]), np.array([0.0, delta])

    def slope(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.float64]:
        return ((hi - lo) / (2 * delta)).ravel()

    a, s = peak_gray, sigma_px
    jac = np.column_stack(
        [
            slope(
                _light(cam, spots, p - dr, s, a, window), _light(cam, spots, p + dr, s, a, window)
            ),
            slope(
                _light(cam, spots, p - dc, s, a, window), _light(cam, spots, p + dc, s, a, window)
            ),
            mu.ravel() / max(a, 1e-9),
            slope(
                _light(cam, spots, p, s - delta, a, window),
                _light(cam, spots, p, s + delta, a, window),
            ),
        ]
    )
    return dot, mu, jac


def centre_bound_px(
    cs: Case,
    camera: int,
    options: RenderOptions | None = None,
    max_dots: int = 40,
    seed: int = 0,
    joint: bool = False,
) -> NDArray[np.float64]:
    """The Cramér–Rao lower bound of the centre error (px, √(var_row + var_col)) of up to
    ``max_dots`` isolated dots of one camera of a case (a random sample), from what made the
    image (all known here):

    - the dot's expected light (:func:`~omnid.sim.render.mean_spot`: its profile integrated
      over the pixels, stretch, flat top, its own halo ring), with a blur and albedo drawn as
      the renderer draws them; unknowns: centre (row, col), brightness, blur σ, a constant
      background under the dot;
    - the noise of the subtracted image base − mask per pixel: read noise² + shot gain ×
      signal, in both frames, and the rounding (1/12 each), the scene taken from the mask;
    - clipping: a pixel of the base frame at 255 is censored (only "≥ 254.5" is known), its
      information scaled by :func:`_censored_information`;
    - speckle grains (on the dot, in its halo): a multiplicative Gaussian field of the model's
      contrast and correlation, i.e. noise of covariance c²·μ_i μ_j ρ_ij added to the pixels'
      own (the bound is then the Gaussian one, F = Jᵀ C⁻¹ J, the covariance taken as known).

    ``joint=False``: the neighbours are known exactly (their light is not in the window) —
    what an ideal estimator reaches on a lone dot. ``joint=True``: every other dot whose
    centre lies in the window (±(3.5 σ + 4) px) is drawn there with its own unknown centre,
    brightness and blur, and the bound is that of the dot's centre with all of them unknown
    (the neighbours' light also raises the noise and the clipping): what crowding costs any
    estimator (slightly pessimistic: a neighbour's pixels outside the window are not used).
    A measured RMS above the joint bound is bias or inefficiency (model mismatch, neighbours
    not taken out, clipping handled suboptimally).
    """
    opts = options or RenderOptions.realistic(spots=cs.spots)
    spots = cs.spots
    cam = cs.rig.cam1 if camera == 1 else cs.rig.cam2
    vis = cs.hits.visible1 if camera == 1 else cs.hits.visible2
    cols = slice(0, 2) if camera == 1 else slice(2, 4)
    flux_all = hits_flux(cs.hits, cs.rig, spots)[vis, camera - 1]
    pix = cs.hits.pixels[vis][:, cols]
    in_image = cam.in_disk(pix)
    pix, flux_all = pix[in_image], flux_all[in_image]
    scored = cam.in_disk(pix, EDGE_MARGIN_PX)
    iso = isolated(pix[scored], spots)
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(scored)[iso]
    if len(idx) > max_dots:
        idx = np.sort(rng.choice(idx, max_dots, replace=False))
    sig_all = spots.sigma_px * (1.0 + spots.sigma_jitter * rng.uniform(-1, 1, len(pix)))
    amp_all = spots.peak_gray * (1.0 + spots.peak_jitter * rng.uniform(-1, 1, len(pix)))
    amp_all = amp_all * flux_all
    mask = np.asarray(cs.capture.mask1 if camera == 1 else cs.capture.mask2, dtype=np.float64)
    if mask.ndim == 3:
        mask = mask[..., 1]
    grow = 1.0 + max(spots.rim_radial, spots.rim_tangential, 0.0)
    halo_reach = 1.6 * spots.halo_sigma_px if spots.halo_fraction > 0 else 0.0
    grains = spots.speckle_contrast > 0 or (spots.halo_fraction > 0 and spots.halo_speckle > 0)
    h_max = (11 if grains else 16) + (3 if joint else 0)
    half = max(math.ceil(3.5 * spots.sigma_px * grow), math.ceil(halo_reach), 4)
    half = int(min(half + (4 if joint else 0), h_max))
    shape = (2 * half + 1, 2 * half + 1)
    corr_dot = _grain_correlation(shape, spots.speckle_grain_px) if grains else None
    corr_halo = _grain_correlation(shape, 0.8) if grains else None
    out = np.full(len(idx), np.nan)
    for n, k in enumerate(idx):
        p = pix[k]
        tl = (round(p[0]) - half, round(p[1]) - half)
        if tl[0] < 0 or tl[1] < 0 or tl[0] + shape[0] > mask.shape[0]:
            continue
        if tl[1] + shape[1] > mask.shape[1]:
            continue
        win = (tl, shape)
        dot, mu, J = _spot_jacobian(cam, spots, p, sig_all[k], amp_all[k], win)
        J = np.column_stack([J[:, :3], np.ones(J.shape[0]), J[:, 3]])
        if joint:
            near = np.flatnonzero(np.abs(pix - p).max(axis=1) <= half)
            for j in near[near != k]:
                dot_j, mu_j, J_j = _spot_jacobian(cam, spots, pix[j], sig_all[j], amp_all[j], win)
                dot, mu, J = dot + dot_j, mu + mu_j, np.column_stack([J, J_j])
        scene = mask[tl[0] : tl[0] + shape[0], tl[1] : tl[1] + shape[1]].ravel()
        lit = scene * (1.0 + opts.flicker)
        base_mean = lit + mu.ravel()
        var_base = opts.noise_sigma**2 + opts.shot_noise_gain * np.maximum(base_mean, 0) + 1 / 12
        var_mask = opts.noise_sigma**2 + opts.shot_noise_gain * np.maximum(scene, 0) + 1 / 12
        kept = _censored_information((_CLIP_GRAY - base_mean) / np.sqrt(var_base))
        var = (var_base + var_mask) / np.maximum(kept, 1e-9)
        if grains:
            assert corr_dot is not None and corr_halo is not None
            d = dot.ravel()
            glow = (mu - dot).ravel()
            cov = np.diag(var)
            cov += spots.speckle_contrast**2 * np.outer(d, d) * corr_dot
            cov += spots.halo_speckle**2 * np.outer(glow, glow) * corr_halo
            fisher = J.T @ np.linalg.solve(cov, J)
        else:
            fisher = (J / var[:, None]).T @ J
        try:
            inv = np.linalg.inv(fisher)
        except np.linalg.LinAlgError:
            continue
        out[n] = math.sqrt(max(inv[0, 0] + inv[1, 1], 0.0))
    return out[np.isfinite(out)]


def bound_rms_px(cs: Case, max_dots: int = 40, joint: bool = False) -> float:
    """The case's Cramér–Rao bound as an RMS over its isolated dots (both cameras), px — the
    figure to set next to the measured centre RMS (``joint``: see :func:`centre_bound_px`)."""
    b = np.concatenate(
        [centre_bound_px(cs, k, max_dots=max_dots, seed=k, joint=joint) for k in (1, 2)]
    )
    return float(np.sqrt(np.mean(b * b))) if len(b) else float("nan")
