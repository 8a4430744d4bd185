"""Laser dot detection in a mask/base image pair (thesis chapter 5).

Interface shared by every method::

    detect_dots(mask, base, method="best" | "thesis", params=DetectionParams()) -> (N, 3) float64

Each row is (row_px, col_px, strength): the dot centre in image coordinates (pixel (i, j)
covers [i − 0.5, i + 0.5] × [j − 0.5, j + 0.5]) and its brightness in the subtracted image
(gray levels). An image with no dots gives an empty (0, 3) array, never an exception. Images
are 8-bit (or 16-bit / float) gray (H, W) or BGR (H, W, 3); anything else raises
:class:`~omnid.errors.InputError`.

``method="thesis"`` is the thesis algorithm (5.1–5.4), vectorised, with integer centres:

1. *subtracted* = base − mask, negatives clipped to 0 (5.1);
2. 3x3 mean smoothing (pixels outside the image count as 0);
3. enhancement: the image is tiled by ``block_px`` squares stepped by ``block_px`` (the last row
   and column of tiles are cut by the image edge and averaged over the pixels they hold); a
   pixel below ``block_coefficient`` · its tile's mean becomes 0;
4. circular-neighbourhood model (5.3–5.4): for every 8x8 window whose 12x12 grown square lies
   in the image, the window's brightest pixel — the first maximum in row-major scan order,
   as a scan with ``argmax`` finds it — must be its pixel (4, 4) (1-based; (3, 3) 0-based)
   and exceed ``min_peak_gray``; then the ring averages must satisfy E1–E3 and the square
   test E4 (below). The centre is that pixel.

Ring membership (the thesis's Figure 5.4 is lost): with the window centre at (3.5, 3.5)
(0-based, between the four middle pixels), ring k ∈ {1, 2, 3, 4} holds the pixels whose
city-block distance ``|r − 3.5| + |c − 3.5|`` equals k. These hold 4, 8, 12 and 16 pixels, as
the thesis states, and their unions are the digital disks of diameter 2, 4, 6 and 8 (a square
with 0, 1, 3 and 6 pixels cut from each corner); the 24 corner pixels of the 8x8 window are in
no ring. See :data:`RING_MASKS`.

For exactness (so that any transcription of the algorithm finds the *same* dots) the smoothed
image is held as 3x3 *sums* (integers, i.e. 9 × the mean) and every test is written on integer
sums; thresholds are still in gray levels of the mean.

``method="best"`` finds sub-pixel centres robust to colour, noise, halos and flicker; see
:func:`_detect_best`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from omnid.config import Settings, require, setting
from omnid.core import spotfit, spotshape
from omnid.core.arrays import clip, kth_smallest, median, quartiles
from omnid.errors import InputError

DetectionMethod = Literal["thesis", "best"]

#: City-block distance of each pixel of the 8x8 window from its centre (3.5, 3.5) (0-based).
_RING_INDEX = (np.abs(np.arange(8) - 3.5)[:, None] + np.abs(np.arange(8) - 3.5)[None, :]).astype(
    np.int64
)
#: RING_MASKS[k - 1] — the 8x8 boolean mask of circular neighbourhood k (4, 8, 12, 16 pixels).
RING_MASKS = np.stack([np.equal(_RING_INDEX, k) for k in (1, 2, 3, 4)])
#: The pixel of the 8x8 window that must be the brightest: (4, 4) 1-based, (3, 3) 0-based.
WINDOW_CENTRE = 3
WINDOW_PX = 8
SQUARE_GROW_PX = 2


@dataclass(frozen=True)
class DetectionParams(Settings):
    """Thresholds of the detectors (gray levels of the subtracted image unless stated).

    Thesis method (chapter 5): ``block_px``, ``block_coefficient``, ``min_peak_gray`` and
    ``ring_e1_gray`` … ``e4_gray`` (the thesis took E1 = E2 = E3). Best method: the ``best_*``
    fields and ``bgr_weights``.
    """

    block_px: int = setting(21, 3, 255)  # 5.1: enhancement tile size and step, px
    block_coefficient: float = setting(1.5, 0.01, 50.0)  # 5.1: threshold = coefficient · tile mean
    min_peak_gray: float = setting(
        20.0, 0.0, 65535.0
    )  # 5.4: the window's brightest pixel must exceed this
    ring_e1_gray: float = setting(1.0, -255.0, 255.0)  # 5.4: 12-ring average − 16-ring average ≥ E1
    ring_e2_gray: float = setting(1.0, -255.0, 255.0)  # 5.4: 8-ring average − 12-ring average ≥ E2
    ring_e3_gray: float = setting(1.0, -255.0, 255.0)  # 5.4: 4-ring average − 8-ring average ≥ E3
    e4_gray: float = setting(5.0, -255.0, 255.0)  # 5.4: CircularAverage − SquareAverage ≥ E4
    # colour → gray for the laser (B, G, R)
    bgr_weights: tuple[float, float, float] = setting((0.0, 1.0, 0.0), -10.0, 10.0)
    best_min_peak_gray: float = setting(
        10.0, 0.0, 65535.0
    )  # a dot's smoothed peak above local background ≥ this
    best_snr: float = setting(
        6.0, 0.0, 100.0
    )  # … and ≥ this many noise sigmas of the subtracted image
    best_relative_peak: float = setting(
        0.3, 0.0, 0.99
    )  # … and ≥ this share of the brightest peak near it
    best_relative_radius_px: int = setting(5, 1, 20)  # "near": within this radius, px
    best_background_radius_px: int = setting(
        5, 2, 20
    )  # local background: min filter of this radius, px
    best_min_contrast: float = setting(
        0.12, 0.0, 0.99
    )  # compact: the peak's own curvature predicts (peak − ring 3 px out) / peak ≥ this
    # (0.12: spots up to σ ≈ 5.8 px along their flatter axis pass, smooth bumps do not)

    def __post_init__(self) -> None:
        super().__post_init__()
        w = self.bgr_weights
        require(
            len(w) == 3 and all(np.isfinite(x) for x in w) and sum(w) > 0,
            "bgr_weights",
            f"must be three finite weights (B, G, R) with a positive sum, got {w}",
        )


_EMPTY_SHAPE = (0, 3)
_ALLOWED_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


#: The defaults, built (and range-checked) once: detect_dots runs per frame.
_DEFAULT_PARAMS = DetectionParams()


def _empty() -> NDArray[np.float64]:
    return np.zeros(_EMPTY_SHAPE, dtype=np.float64)


def _check_image(image: object, name: str) -> NDArray:
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name}: expected a numpy image array, got {type(image).__name__}")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise InputError(
            f"{name}: expected a gray (H, W) or BGR (H, W, 3) image, got shape {image.shape}"
        )
    if image.dtype.type not in _ALLOWED_DTYPES:
        raise InputError(
            f"{name}: expected dtype uint8, uint16, float32 or float64, got {image.dtype}"
        )
    if image.dtype.kind == "f" and image.size and not np.isfinite(image).all():
        raise InputError(f"{name}: image holds NaN or infinite values")
    return image


def _check_pair(mask: object, base: object) -> tuple[NDArray, NDArray]:
    m = _check_image(mask, "mask")
    b = _check_image(base, "base")
    if m.shape != b.shape:
        raise InputError(f"mask and base differ in shape: {m.shape} vs {b.shape}")
    if m.dtype != b.dtype:
        raise InputError(f"mask and base differ in dtype: {m.dtype} vs {b.dtype}")
    return m, b


def to_gray(
    image: NDArray, bgr_weights: tuple[float, float, float] = (0.0, 1.0, 0.0)
) -> NDArray[np.float32]:
    """Gray or BGR image → float32 gray; BGR channels are combined with ``bgr_weights``
    (normalised to sum 1; the default takes the green channel, the laser's)."""
    arr = np.asarray(image)
    if arr.ndim == 2:
        return arr.astype(np.float32)
    if arr.ndim == 3 and arr.shape[2] == 3:
        w = np.asarray(bgr_weights, dtype=np.float64)
        w = w / w.sum()
        nz = np.flatnonzero(w)
        if len(nz) == 1:
            return (arr[:, :, nz[0]] * np.float32(w[nz[0]])).astype(np.float32)
        out = cv2.transform(arr.astype(np.float32), w.reshape(1, 3).astype(np.float32))
        return np.asarray(out, dtype=np.float32)
    raise InputError(f"expected a gray (H, W) or BGR (H, W, 3) image, got shape {arr.shape}")


def subtract(mask: NDArray, base: NDArray) -> NDArray[np.float32]:
    """The *subtracted* image base − mask, negative values clipped to 0 (thesis 5.1)."""
    m, b = _check_pair(mask, base)
    return np.maximum(to_gray(b) - to_gray(m), 0.0)


# --------------------------------------------------------------------------------------------
# Thesis method (chapter 5), vectorised.


def _thesis_gray(image: NDArray) -> NDArray[np.int64]:
    """The thesis's gray image: integer gray levels (BGR → standard luma, floats rounded)."""
    if image.ndim == 3:
        src = image if image.dtype in (np.uint8, np.uint16) else image.astype(np.float32)
        image = cv2.cvtColor(src, cv2.COLOR_BGR2GRAY)
    if image.dtype.kind == "f":
        return np.rint(image).astype(np.int64)
    return image.astype(np.int64)


def thesis_smoothed_sums(sub: NDArray[np.int64]) -> NDArray[np.int64]:
    """3x3 sums of the subtracted image (= 9 × the 3x3 mean, thesis 5.1), zeros outside."""
    p = np.pad(sub, 1)
    h, w = sub.shape
    out = np.zeros_like(sub)
    for dr in range(3):
        for dc in range(3):
            out += p[dr : dr + h, dc : dc + w]
    return out


def thesis_enhance(s9: NDArray[np.int64], block_px: int, coefficient: float) -> NDArray[np.int64]:
    """Block threshold (thesis 5.1): zero every pixel below ``coefficient`` · its tile's mean.

    ``s9`` holds 3x3 sums; a pixel is kept iff ``s9 · n ≥ coefficient · tile_sum`` with ``n``
    the tile's pixel count (the mean comparison, multiplied out so that it is exact).
    """
    h, w = s9.shape
    r_starts = np.arange(0, h, block_px)
    c_starts = np.arange(0, w, block_px)
    tile_sum = np.add.reduceat(np.add.reduceat(s9, r_starts, axis=0), c_starts, axis=1)
    r_len = np.diff(np.append(r_starts, h))
    c_len = np.diff(np.append(c_starts, w))
    tile_n = r_len[:, None] * c_len[None, :]
    thresh = coefficient * tile_sum.astype(np.float64)
    thr_px = np.repeat(np.repeat(thresh, r_len, axis=0), c_len, axis=1)
    n_px = np.repeat(np.repeat(tile_n, r_len, axis=0), c_len, axis=1)
    keep = (s9 * n_px).astype(np.float64) >= thr_px
    return np.where(keep, s9, 0)


def _window_kernels() -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Kernels over the 8x8 window of the pixels before / after (3, 3) in row-major order."""
    order = np.arange(WINDOW_PX * WINDOW_PX).reshape(WINDOW_PX, WINDOW_PX)
    c = WINDOW_CENTRE * WINDOW_PX + WINDOW_CENTRE
    return (order < c).astype(np.uint8), (order > c).astype(np.uint8)


def _detect_thesis(mask: NDArray, base: NDArray, p: DetectionParams) -> NDArray[np.float64]:
    sub = np.maximum(_thesis_gray(base) - _thesis_gray(mask), 0)
    h, w = sub.shape
    g = SQUARE_GROW_PX
    lo = WINDOW_CENTRE + g  # first centre row/col whose 12x12 square lies in the image
    hi_r = h - (WINDOW_PX - 1 - WINDOW_CENTRE) - g  # one past the last
    hi_c = w - (WINDOW_PX - 1 - WINDOW_CENTRE) - g
    if hi_r <= lo or hi_c <= lo:
        return _empty()
    enh = thesis_enhance(thesis_smoothed_sums(sub), p.block_px, p.block_coefficient)
    # Brightest-pixel test: first row-major maximum of the window at (3, 3), i.e. strictly
    # above every pixel before it and not below any after it. Values are integers < 2**24,
    # exact in float32, so cv2's max filters are exact.
    e32 = enh.astype(np.float32)
    before, after = _window_kernels()
    anchor = (WINDOW_CENTRE, WINDOW_CENTRE)  # (x, y) = (col, row) of the kernel's centre pixel
    max_before = cv2.dilate(
        e32, before, anchor=anchor, borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    max_after = cv2.dilate(e32, after, anchor=anchor, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    cand = (e32 > max_before) & (e32 >= max_after) & (enh > 9.0 * p.min_peak_gray)
    cand[:lo, :] = False
    cand[hi_r:, :] = False
    cand[:, :lo] = False
    cand[:, hi_c:] = False
    rows, cols = np.nonzero(cand)
    if len(rows) == 0:
        return _empty()
    keep = _thesis_model_test(enh, rows, cols, p)
    rows, cols = rows[keep], cols[keep]
    strength = enh[rows, cols] / 9.0
    return np.column_stack([rows, cols, strength]).astype(np.float64)


def _thesis_model_test(
    enh: NDArray[np.int64], rows: NDArray[np.intp], cols: NDArray[np.intp], p: DetectionParams
) -> NDArray[np.bool_]:
    """E1–E4 of thesis 5.4 for the windows centred (at (3, 3)) on the candidate pixels."""
    off = np.arange(WINDOW_PX) - WINDOW_CENTRE
    win = enh[rows[:, None, None] + off[None, :, None], cols[:, None, None] + off[None, None, :]]
    sums = [(win * m).sum(axis=(1, 2)) for m in RING_MASKS]  # rings of 4, 8, 12, 16 px
    a4, a8, a12, a16 = (s / float(m.sum()) for s, m in zip(sums, RING_MASKS, strict=True))
    g = SQUARE_GROW_PX
    soff = np.arange(-WINDOW_CENTRE - g, WINDOW_PX - WINDOW_CENTRE + g)
    sq = enh[rows[:, None, None] + soff[None, :, None], cols[:, None, None] + soff[None, None, :]]
    n_sq = float(len(soff) ** 2)
    square_avg = sq.sum(axis=(1, 2)) / n_sq
    circular_avg = (a4 + a8 + a12 + a16) / 4.0
    return (
        ((a12 - a16) / 9.0 >= p.ring_e1_gray)
        & ((a8 - a12) / 9.0 >= p.ring_e2_gray)
        & ((a4 - a8) / 9.0 >= p.ring_e3_gray)
        & ((circular_avg - square_avg) / 9.0 >= p.e4_gray)
    )


# --------------------------------------------------------------------------------------------
# Best method: sub-pixel centres.


def _laser_difference(mask: NDArray, base: NDArray, weights: tuple[float, float, float]) -> NDArray:
    """Signed base − mask in the laser's gray (see :func:`to_gray`), gray levels.

    8-bit images whose laser gray is one channel give exact int16 (half the memory traffic
    of float32, and integers let :func:`_noise_sigma` count instead of sort); others float32.
    """
    if mask.dtype == np.uint8:
        if mask.ndim == 2:
            return np.subtract(base, mask, dtype=np.int16)
        nz = np.flatnonzero(np.asarray(weights, dtype=np.float64))
        if len(nz) == 1:
            k = int(nz[0])
            return np.subtract(base[:, :, k], mask[:, :, k], dtype=np.int16)
    return to_gray(base, weights) - to_gray(mask, weights)


def _laser_gray(image: NDArray, weights: tuple[float, float, float]) -> NDArray:
    """The laser's gray of one frame (the channel or combination :func:`_laser_difference`
    subtracts), uint8 for an 8-bit single-channel laser gray, else float32."""
    if image.dtype == np.uint8:
        if image.ndim == 2:
            return image
        nz = np.flatnonzero(np.asarray(weights, dtype=np.float64))
        if len(nz) == 1:
            return image[:, :, int(nz[0])]
    return to_gray(image, weights)


#: Frame pixels darker than this (gray) say nothing about the flicker gain.
_FLICKER_MIN_GRAY = 16.0
#: A flicker gain smaller than this is left alone.
_FLICKER_MIN_GAIN = 0.003


def _flicker_gain(d: NDArray, mask_gray: NDArray, noise: float) -> float:
    """The illumination change from mask to base as a gain g: the subtracted image holds
    g · mask besides the laser (mains flicker, auto exposure). The median of d / mask over a
    subsample of rows (24), where the mask is lit; the laser's dots are too few to move it.
    0 when the copy stays within two noise sigmas (g · the lit scene's mean): then it holds no
    edge the local background (:func:`_background_half`) and the compactness test would not
    deal with anyway."""
    step = max(d.shape[0] // 24, 1)
    m = mask_gray[::step].astype(np.float32)
    lit = m >= np.float32(_FLICKER_MIN_GRAY)
    if np.count_nonzero(lit) < 64:
        return 0.0
    m_lit = m[lit]
    ratio = d[::step][lit] / m_lit
    mid = len(ratio) // 2
    gain = float(kth_smallest(ratio, mid))
    return gain if abs(gain) * float(m_lit.mean()) >= 2.0 * noise else 0.0


def _clutter(small: NDArray[np.float32], bg_half: NDArray[np.float32], mask_gray: NDArray) -> float:
    """The spread of the subtracted image about its local background at the dots' scale, gray
    levels: sensor noise and whatever of the scene the two frames do not share.

    Measured at half resolution (``small`` = pyrDown of the subtracted image, whose 5x5 kernel
    divides white noise by 128/35 = 3.66, about what the σ = 1 px smoothing of the
    candidates does: 3.5), on every 8th row, where the mask frame sees the scene (not the dark
    housing, which holds no noise), from the lower half of the values only — the dots stand
    above the background, never below it: (median − 25th percentile) / 0.6745. 0 with too
    few samples.
    """
    lit = mask_gray[::16, ::2][: (small.shape[0] + 7) // 8, : small.shape[1]] >= _HOUSING_GRAY
    res = (small[::8] - bg_half[::8])[: lit.shape[0], : lit.shape[1]][lit]
    if res.size < 64:
        return 0.0
    q25, q50 = quartiles(res)
    return float(q50 - q25) / 0.6745


def _noise_sigma(d: NDArray) -> float:
    """Robust noise sigma of an image, gray levels: MAD of horizontal neighbour differences
    (on a subsample of rows), divided by √2 for the difference of two samples.

    The dark, saturated or constant parts say nothing about noise: zero differences are left
    out. Integer images take the median from a histogram (same value as ``np.median``).
    """
    rows = d[:: max(d.shape[0] // 64, 1)]
    if rows.shape[1] < 2:
        return 0.0
    if d.dtype.kind == "i":
        # (|a − b| of the int16 difference images in one OpenCV pass, ~2x numpy's two)
        diff = cv2.absdiff(rows[:, 1:], rows[:, :-1])
        # The histogram of the differences saturated to 8 bits (OpenCV's: ~2x np.bincount)
        # is exact below 255, where the median nearly always lies; else they are counted.
        u8 = cv2.convertScaleAbs(diff)
        counts = cv2.calcHist([u8], [0], None, [256], [0, 256]).ravel().astype(np.int64)
        counts[:1] = 0
        n = int(counts.sum())  # (saturation moves counts between bins, never out)
        if n < 16:
            return 0.0
        cum = np.cumsum(counts)
        # np.median: the mean of the sorted values at (n − 1) // 2 and n // 2.
        if np.searchsorted(cum, n // 2 + 1) >= 255:
            counts = np.bincount(diff.ravel())
            counts[:1] = 0
            cum = np.cumsum(counts)
        mad = 0.5 * float(np.searchsorted(cum, (n - 1) // 2 + 1) + np.searchsorted(cum, n // 2 + 1))
    else:
        flat = (rows[:, 1:] - rows[:, :-1]).ravel()
        flat = flat[flat != 0]
        if flat.size < 16:
            return 0.0
        mad = float(np.median(np.abs(flat)))
    return float(mad * 1.4826 / np.sqrt(2.0))  # a Python float: keeps float32 math float32


#: Half-size of the box mean that takes back the min filter's bias (31x31), px.
_BIAS_RADIUS_PX = 15
#: Images smaller than this (either side, px) are processed whole, without the box.
_MIN_PYRAMID_PX = 32
#: A place is active (inside the processed box) if it stands this share of the detection
#: threshold above the background at half resolution.
_ACTIVE_SHARE = 0.6


def _background_half(
    small: NDArray[np.float32], radius_px: int, noise: float
) -> NDArray[np.float32]:
    """Local background (flicker leaves a faint scene in the subtracted image) at half
    resolution, from ``small`` = ``cv2.pyrDown`` of the subtracted image, gray levels.

    The dots are brighter than their surroundings and at most ~2·radius_px across, so a min
    filter of that radius (on the pyramid's Gaussian-smoothed pixels, which tames the noise's
    downward bias) lands between them; a box mean of the same size smooths the resulting
    staircase. The min filter still sits a couple of noise sigmas below the true background,
    so the local mean (31 px) of what is left over, with dot light (and its lack) clipped out,
    is added back. The background is smooth, so half resolution loses nothing but time.
    """
    k = radius_px | 1  # ±radius at half resolution is a little wider, with the pyramid blur
    eroded = cv2.erode(small, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    low = cv2.blur(eroded, (k, k))
    # Noise of pyrDown's output: its 5x5 kernel's squared weights sum to (35/128)².
    lim = 2.0 * max(noise * 35.0 / 128.0, 0.25)
    # (into the min filter's array: a fresh one of the image's size costs page faults)
    rest = np.subtract(small, low, out=eroded, dtype=np.float32)
    np.clip(rest, -lim, lim, out=rest)  # (one SIMD pass: ~5x np.maximum's with a scalar)
    k_bias = 2 * (_BIAS_RADIUS_PX // 2) + 1
    bias = cv2.blur(rest, (k_bias, k_bias))
    return np.add(low, bias, out=bias, dtype=np.float32)


def _box_of(
    active: NDArray[np.uint8], margin_px: int, shape: tuple[int, int]
) -> tuple[int, int, int, int] | None:
    """Even-aligned full-resolution box (r0, r1, c0, c1) — rows r0 … r1 − 1, columns c0 …
    c1 − 1 — around the nonzero pixels of a half-resolution mask, widened by ``margin_px``;
    None if there are none."""
    x, y, bw, bh = cv2.boundingRect(active)
    if bw == 0 or bh == 0:
        return None
    m = margin_px + (margin_px & 1)
    return (
        max(2 * y - m, 0),
        min(2 * (y + bh) + m, shape[0]),
        max(2 * x - m, 0),
        min(2 * (x + bw) + m, shape[1]),
    )


#: Spot sizes the matched filter follows (sigma, px): the estimate is clipped to this range.
_SPOT_SIGMA_RANGE_PX = (0.8, 3.5)
#: In an image of spots larger than this (sigma, px) every dot is fitted (spotfit): their
#: neighbours overlap them.
_FIT_ALL_FROM_PX = 1.5
#: ... and a dot with at least this many clipped pixels starts from their middle.
_CLIPPED_FIT_PX = 8
#: A neighbour whose light moves a filtered maximum by less than this is left alone, px.
_COUPLING_PX = 0.01
#: Fixed-point iterations of the neighbours' pull (:func:`_neighbour_pull`): with 6 the close
#: dots of a dense laser converge (4 left ~7 % of them to the fit, as accurate on average and
#: ~1 ms per camera).
_PULL_ITERATIONS = 6
#: A pull larger than this (px) is left to the fit.
_PULL_MAX_PX = 0.75
#: With more candidates than this, the relative test looks at the square's maximum first.
_SQUARE_FIRST_FROM = 300
#: Two maxima are two dots if the image dips between them by this share of the dimmer.
_SADDLE_DEPTH = 0.05
#: ... looked for up to this many filtered sigmas apart.
_SADDLE_REACH = 3.0
#: With fewer unclipped dots than this, the spot size comes from a censored fit.
_MIN_UNCLIPPED = 16
#: How many of the brightest dots that fit uses.
_SIZE_FIT_SAMPLE = 48
#: The compactness test's ring: the predicted contrast 3 px from a peak (thesis-sized dots).
_RING_PX = 3.0
#: ... and a flat top's: the median of a ring this many image spot sizes out must be this far
#: below it.
_FAR_RING = 2.5
_FAR_CONTRAST = 0.9
#: Outside the mirror's disk the camera sees its dark housing (SPEC §6): a mask-frame pixel
#: darker than this (gray) is not the scene.
_HOUSING_GRAY = 12.0
#: Two spots of a blob are split apart only this many image spot sigmas apart or more: closer,
#: two round spots are one maximum of any smoothing (one observation: captures of the same
#: pair split it or not by their noise, and calibration and the scene would disagree).
_SPLIT_MIN_SIGMAS = 2.0
#: Spots larger than this (sigma, px) get their own matched filter for the centres.
_MATCHED_FROM_PX = 1.5
#: The 3x3 neighbourhood of a peak and the least-squares solve of a quadratic through it:
#: ln F ≈ a + b_r·r + b_c·c + q_r·r² + q_c·c² + q_rc·r·c on the matched-filtered image F.
_Q_OFF_R, _Q_OFF_C = (a.ravel() for a in np.meshgrid((-1, 0, 1), (-1, 0, 1), indexing="ij"))
_Q_DESIGN = np.column_stack(
    [np.ones(9), _Q_OFF_R, _Q_OFF_C, _Q_OFF_R**2, _Q_OFF_C**2, _Q_OFF_R * _Q_OFF_C]
).astype(np.float64)
_Q_SOLVE32 = np.linalg.pinv(_Q_DESIGN).T.astype(np.float32)  # (9, 6): log values @ this


def _log_quadratic(
    f: NDArray, rows: NDArray[np.intp], cols: NDArray[np.intp]
) -> tuple[
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.bool_],
]:
    """Sub-pixel maximum of ``f`` near each peak pixel from a quadratic fitted to ln f on its
    3x3 neighbourhood (a Gaussian's logarithm is exactly quadratic, so on a smoothed spot this
    is the maximum of the smoothed image). Returns (row, col, the smoothed spot's variance
    px² — the mean over the two axes —, the larger of its two principal variances, and
    whether the quadratic is a maximum within 1 px)."""
    vals = _windows(f, rows, cols, 1)
    top = vals[4:5]
    logs = np.log(np.maximum(vals, np.float32(1e-3) * np.maximum(top, np.float32(1e-3))))
    _, br, bc, qr, qc, qrc = (_Q_SOLVE32.T @ logs).astype(np.float64)
    det = 4.0 * qr * qc - qrc * qrc
    ok = (qr < 0) & (qc < 0) & (det > 1e-12)
    safe = np.where(ok, det, 1.0)
    dr = -(2.0 * qc * br - qrc * bc) / safe
    dc = -(2.0 * qr * bc - qrc * br) / safe
    ok &= (np.abs(dr) <= 1.0) & (np.abs(dc) <= 1.0)
    mean_var = np.where(ok, -1.0 / np.minimum(qr + qc, -1e-9), np.inf)  # −1/(2·mean(q_r, q_c))
    # The flatter principal curvature of the quadratic form [[q_r, q_rc/2], [q_rc/2, q_c]].
    flat = 0.5 * (qr + qc) + np.sqrt(0.25 * (qr - qc) ** 2 + 0.25 * qrc * qrc)
    max_var = np.where(ok & (flat < 0), -0.5 / np.minimum(flat, -1e-12), np.inf)
    return rows + clip(dr, -1, 1), cols + clip(dc, -1, 1), mean_var, max_var, ok


def _spot_sigma(mean_var: NDArray[np.float64], peak: NDArray) -> float:
    """The image's spot size (Gaussian sigma, px) from the curvature of the σ = 1 px smoothed
    image at its peaks (``mean_var`` of :func:`_log_quadratic`): a spot of sigma σ there has
    the variance σ² + 1 + 1/12 (the smoothing and the pixel's own box). The median over the
    bright peaks — at least half as bright as the brightest few per cent, so that grains and
    a changing scene's bumps, however many, do not count — ; a clipped or flat top reads wider,
    which is what its matched filter should be."""
    if len(peak) > 1:
        top = np.partition(peak, int(0.95 * (len(peak) - 1)))[int(0.95 * (len(peak) - 1))]
        mean_var = mean_var[peak >= 0.5 * top]
    good = mean_var[np.isfinite(mean_var)]
    if len(good) == 0:
        return 1.3
    sigma2 = median(good) - 1.0 - 1.0 / 12.0
    lo, hi = _SPOT_SIGMA_RANGE_PX
    return float(np.clip(math.sqrt(max(sigma2, lo * lo)), lo, hi))


def _clipped_sigma(
    d: NDArray[np.float32],
    saturated: NDArray[np.bool_] | None,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    centre: NDArray,
    ok: NDArray[np.bool_],
    start_px: float,
) -> float:
    """The spot size when the sensor clipped the tops: the median sigma of the censored
    least-squares fit (:func:`~omnid.core.spotfit.fit_spots`) of the brightest
    :data:`_SIZE_FIT_SAMPLE` peaks, whose clipped pixels only bound the light from below."""
    lo, hi = _SPOT_SIGMA_RANGE_PX
    k = np.flatnonzero(ok)
    if len(k) == 0:
        return start_px
    k = k[np.argsort(centre[k])[-_SIZE_FIT_SAMPLE:]]
    start = float(np.clip(start_px, lo, 2.5))
    peak = centre[k] * (start * start + 1.0) / (start * start)
    _, _, _, s = spotfit.fit_spots(d, saturated, rows[k], cols[k], start, peak, start=(r[k], c[k]))
    return float(np.clip(np.median(s), lo, hi))


def _detect_best(
    mask: NDArray,
    base: NDArray,
    p: DetectionParams,
    learned_shape: bool = False,
    split_blends: bool | NDArray[np.bool_] = False,
) -> NDArray[np.float64]:
    """Sub-pixel dot centres.

    1. gray: the laser's channel combination (``bgr_weights``), signed base − mask;
    2. local background (flicker) estimated at half resolution, see :func:`_background_half`;
       the noise sigma (:func:`_noise_sigma`) and the clutter about that background
       (:func:`_clutter`: a changed scene) set the detection threshold;
    3. only the box around the places standing 0.6 · threshold above that background at half
       resolution is processed further (the laser dots usually cover a part of the mirror disk
       only: the pattern is thrown to the front). A dot the whole frame would show has its
       smoothed peak above the threshold, and ≥ ~0.69 of that at half resolution (the pyramid
       samples every other pixel), so only a lone dot barely above the threshold, outside the
       box of all the others, can be lost to the box;
    4. the illumination change between the frames (:func:`_flicker_gain`) is taken out as
       gain · mask when it stands above the noise (it copies the scene, sharp edges and all);
    5. candidates: local maxima (3x3) of a σ = 1 px smoothed copy above that threshold;
       compact (``best_min_contrast``: the contrast 3 px out that each peak's own curvature
       predicts, or for a flat top a ring a few spot sizes out, :func:`_ring_contrast`), at
       least ``best_relative_peak`` of the brightest value within
       ``best_relative_radius_px`` (more for large spots; rejects speckle grains in a dot's
       halo and dim ghosts), and for wide or clipped tops not a mere bump on a brighter
       maximum's top (:func:`_one_spot`). The spot size σ is measured from the same
       curvatures (:func:`_spot_sigma`; from a censored fit where the sensor clipped every
       top);
    6. centre: the maximum of the matched-filtered image (:func:`_log_quadratic`; the 1 px
       smoothing for spots up to 1.5 px, a Gaussian of σ beyond) — for a Gaussian spot the
       least-squares (maximum-likelihood) centre, and for any spot that is point-symmetric
       about its centre (flat, clipped or stretched tops, halos) the centre itself. A
       neighbour's light pulls a filtered maximum toward it: for small spots the pull is
       solved for (:func:`_neighbour_pull`), and dots it does not resolve are fitted
       (:func:`~omnid.core.spotfit.fit_spots`: a Gaussian and a plane per dot, every
       neighbour's light taken out, clipped pixels as lower bounds); in an image of spots
       larger than 1.5 px every dot is fitted, those with a clipped top from the middle of
       their clipped pixels. Dots the mirror's rim cuts are fitted on the pixels that see
       them (:func:`_refine`).

    Cost: the full frame is touched only by the subtraction (int16 for 8-bit input), the
    noise estimate (a few rows) and one pyramid step; every other filter runs at half
    resolution or inside the box, and the per-dot work is vectorised over the candidates.
    """
    full = _laser_difference(mask, base, p.bgr_weights)
    h_img, w_img = full.shape
    noise = _noise_sigma(full)
    small = np.asarray(cv2.pyrDown(full), dtype=np.float32)
    mask_gray = _laser_gray(mask, p.bgr_weights)
    gain = _flicker_gain(full, mask_gray, noise)
    flicker: NDArray[np.float32] | None = None  # the scene's copy in the subtracted image
    clip = None if base.dtype.kind == "f" else float(np.iinfo(base.dtype).max)
    if abs(gain) >= _FLICKER_MIN_GAIN:
        # The scene's copy, sharp edges (the mirror's rim) and all, taken out exactly; where
        # the base frame clips, the copy is only what was left below the clip level.
        if clip is not None and float(mask_gray.max()) * (1.0 + gain) > clip:
            m = mask_gray.astype(np.float32)
            flicker = np.minimum(np.float32(gain) * m, np.float32(clip) - m)
            small -= np.asarray(cv2.pyrDown(flicker), dtype=np.float32)
        else:
            small -= np.float32(gain) * np.asarray(cv2.pyrDown(mask_gray), dtype=np.float32)
    bg_half = _background_half(small, p.best_background_radius_px, noise)
    # The σ = 1 px smoothing divides white noise by about 2·√π·σ = 3.5; the scene the two
    # frames do not share (motion, a changed scene, frames of different cameras) adds clutter.
    spread = max(noise / 3.5, _clutter(small, bg_half, mask_gray))
    threshold = max(p.best_min_peak_gray, p.best_snr * spread)
    # The laser only adds light: a background below zero is the scene's change (a moved
    # mask's edge, something gone), not a floor to measure dots from — above it its own edge
    # would stand out like a row of dots.
    # (np.maximum(bg_half, 0.0) to the bit, ~2x faster: the clip keeps −0.0, + 0.0 makes it 0.0)
    np.clip(bg_half, 0.0, np.inf, out=bg_half)
    bg_half += 0.0
    if min(h_img, w_img) < _MIN_PYRAMID_PX:
        r0, r1, c0, c1 = 0, h_img, 0, w_img
    else:
        # (``small`` is not needed after this: the difference is taken in place)
        active = (np.subtract(small, bg_half, out=small) > _ACTIVE_SHARE * threshold).view(np.uint8)
        box = _box_of(active, 8 + p.best_relative_radius_px, (h_img, w_img))
        if box is None:
            return _empty()
        r0, r1, c0, c1 = box
    sub = full[r0:r1, c0:c1].astype(np.float32)
    if flicker is not None:
        sub -= flicker[r0:r1, c0:c1]
    elif abs(gain) >= _FLICKER_MIN_GAIN:
        sub -= np.float32(gain) * mask_gray[r0:r1, c0:c1].astype(np.float32)
    h, w = sub.shape
    # pyrUp puts half-resolution pixel i at full-resolution pixel 2i, as pyrDown took it.
    part = bg_half[r0 // 2 : (r1 + 1) // 2 + 1, c0 // 2 : (c1 + 1) // 2 + 1]
    d = sub - cv2.pyrUp(part)[:h, :w]
    sm = cv2.GaussianBlur(d, (7, 7), 1.0)
    rows, cols = _local_maxima(sm, threshold, 3, (r0, r1, c0, c1), (h_img, w_img))
    centre = sm[rows, cols]
    r, c, mean_var, max_var, ok = _log_quadratic(sm, rows, cols)
    cand = np.arange(len(rows))  # (which of these the filters below keep)
    # A top within 1 px of a clipped pixel of the base frame is flattened by the sensor, by
    # the laser if the scene itself (the mask frame) was not clipped there.
    saturated = _saturated(base, p.bgr_weights, (r0, r1, c0, c1))
    clipped: NDArray[np.bool_] = np.zeros(len(rows), dtype=bool)
    if saturated is not None:
        # (maxima lie ≥ 1 px inside the box)
        clipped = np.asarray(_windows(saturated, rows, cols, 1).any(axis=0))
        k = np.flatnonzero(clipped)
        clipped[k] = ~_clipped_near(mask, p.bgr_weights, rows[k] + r0, cols[k] + c0)
    # The blur is measured where the sensor did not clip; where it clipped (nearly) every dot,
    # by the censored fit of the brightest of them.
    if np.count_nonzero(~clipped) >= _MIN_UNCLIPPED:
        sigma = _spot_sigma(mean_var[~clipped], centre[~clipped])
    else:
        sigma = _clipped_sigma(
            d, saturated, rows, cols, r, c, centre, ok, _spot_sigma(mean_var, centre)
        )
    spread2 = sigma * sigma + 1.0 + 1.0 / 12.0  # a spot's variance after the σ = 1 smoothing
    if p.best_min_contrast > 0:
        # A dot is compact: its smoothed peak falls off in every direction. The contrast
        # against a ring 3 px out is predicted from the peak's own flatter curvature (a
        # Gaussian of variance v falls to exp(−R²/2v) at R), so that neighbours overlapping a
        # large spot on that ring do not fail it; an edge (the mirror's rim under flicker), a
        # plateau or a smooth bump of a changing scene is flat along it. A flat top (a
        # multimode beam) is flat too, but it falls to the background within a few of the
        # image's spot sizes: the median of a ring there (:func:`_ring_contrast`) tells. A top
        # the laser clipped has no curvature to judge by; it is a dot's (it saturated).
        compact = max_var <= _RING_PX**2 / (-2.0 * math.log(1.0 - p.best_min_contrast))
        compact |= clipped & np.isfinite(mean_var)
        flat = np.flatnonzero(ok & ~compact)
        if len(flat):
            far = _ring_contrast(sm, rows[flat], cols[flat], centre[flat], math.sqrt(spread2))
            compact[flat[far >= _FAR_CONTRAST]] = True
        ok &= compact
    rows, cols, centre, r, c, clipped = _take(ok, rows, cols, centre, r, c, clipped)
    cand = cand[ok]
    if p.best_relative_peak > 0 and len(rows):
        rad = max(p.best_relative_radius_px, round(1.6 * math.sqrt(spread2)))
        src, off = sm, rad
        if min(rows.min(), cols.min()) < rad or rows.max() >= h - rad or cols.max() >= w - rad:
            # Near the image's edge the neighbourhood holds only the pixels in the image.
            src = cv2.copyMakeBorder(sm, rad, rad, rad, rad, cv2.BORDER_CONSTANT, value=-np.inf)
            off = 0
        ok = np.ones(len(rows), dtype=bool)
        ask = np.arange(len(rows))
        if len(rows) > _SQUARE_FIRST_FROM:
            # The disk lies in its square, whose maximum is one separable filter: a peak that
            # passes against the square passes against the disk.
            square = cv2.dilate(sm, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * rad + 1,) * 2))
            ask = np.flatnonzero(centre < p.best_relative_peak * square[rows, cols])
        near = _windows(src, rows[ask] + (rad - off), cols[ask] + (rad - off), rad, disk=True)
        ok[ask] = centre[ask] >= p.best_relative_peak * near.max(axis=0)
        rows, cols, centre, r, c, clipped = _take(ok, rows, cols, centre, r, c, clipped)
        cand = cand[ok]
    # Wide or clipped tops can hold several maxima of the 1 px smoothing: one spot. (The
    # maxima on a clipped top are all next to its clipped pixels.)
    some = np.arange(len(rows)) if sigma > _MATCHED_FROM_PX else np.flatnonzero(clipped)
    if len(some) > 1:
        reach = math.ceil(_SADDLE_REACH * math.sqrt(spread2))
        ok = np.ones(len(rows), dtype=bool)
        ok[some] = _one_spot(sm, r[some], c[some], centre[some], reach)
        rows, cols, centre, r, c, clipped = _take(ok, rows, cols, centre, r, c, clipped)
        cand = cand[ok]
    if len(rows) == 0:
        return _empty()
    # Two beams closer than the smoothing resolves (a doubled beam) are one maximum — split
    # where two spots explain the light better than any one spot (:func:`_split_blends`):
    # everywhere (``split_blends`` True: calibration), or where the image's boolean mask
    # ``split_blends`` says (perception: near the tracks of the laser's doubled beams).
    pair = fixed = np.zeros(len(rows), dtype=bool)
    n_blobs = len(rows)
    blob_r, blob_c, blob_rows, blob_cols = r, c, rows, cols  # (as one dot: the pull's view)
    region = None
    split_all = bool(split_blends) if np.ndim(split_blends) == 0 else False  # (numpy bools too)
    if np.ndim(split_blends) != 0:
        region = np.asarray(split_blends, dtype=bool)
        if region.shape != (h_img, w_img):
            raise InputError(
                f"split region is {region.shape[1]}x{region.shape[0]} px, "
                f"the image {w_img}x{h_img} px"
            )
        region = region[r0:r1, c0:c1]
    if split_all or region is not None:  # (the region's candidates: _split_blends picks them)
        rows, cols, centre, r, c, clipped, pair, fixed = _split_blends(
            d,
            saturated,
            sm,
            (rows, cols, centre, r, c, clipped),
            (mean_var[cand], max_var[cand]),
            sigma,
            p.best_relative_peak,
            noise,
            region,
        )
    fixed_r, fixed_c = r[fixed], c[fixed]
    pair_r, pair_c = r[pair], c[pair]
    # Dots the mirror's rim cuts (the housing outside the mirror is dark in the mask frame) are
    # centred on the pixels that see them.
    cut = _cut_by_rim(_laser_gray(mask, p.bgr_weights), rows + r0, cols + c0)
    # Centres: the maximum of the matched-filtered image. The σ = 1 px smoothing is within a
    # few per cent of the matched filter's efficiency for spots up to 1.5 px; larger spots get
    # their own (candidates stay those of the 1 px smoothing, which keeps close spots apart).
    smooth_px = 1.0
    top_rows, top_cols = rows, cols
    if sigma > _MATCHED_FROM_PX:
        smooth_px = float(min(sigma, _SPOT_SIGMA_RANGE_PX[1]))
        sm = cv2.GaussianBlur(d, (0, 0), smooth_px)
        # The 1 px smoothing breaks a flat (or stretched flat) top into maxima anywhere on
        # it; the matched filter has one, at the spot's centre: climb to it.
        top_rows, top_cols = rows, cols
        rows, cols = _climb(sm, rows, cols, math.ceil(2.0 * smooth_px))
        moved = (rows != top_rows) | (cols != top_cols)
        r, c = np.where(moved, rows, r), np.where(moved, cols, c)
        rm, cm, _, _, ok = _log_quadratic(sm, rows, cols)
        r, c = np.where(ok, rm, r), np.where(ok, cm, c)  # else keep the 1 px filter's
        r[pair], c[pair] = pair_r, pair_c  # (one maximum of the two: they start from the test's)
    filtered_var = sigma * sigma + smooth_px * smooth_px + 1.0 / 12.0
    # A neighbour's light pulls a filtered maximum toward it: taken back to first order where
    # the pull is small; where it is not, the dots are fitted (with their neighbours' light
    # taken out, see spotfit), and so are all the dots of an image of large spots (whose
    # neighbours always overlap) and every dot whose top the laser clipped (its maximum is
    # wherever the scene under it is darkest; it starts from the middle of its clipped pixels).
    if sigma > _FIT_ALL_FROM_PX:
        fit = np.ones(len(r), dtype=bool)
    else:
        if pair.any():
            # The neighbours' pulls as without the split (a blob's two spots pull a
            # neighbour as the one blob does, to first order); a split blend's two spots are
            # fitted jointly against the light of their neighbours held where the pull puts
            # them (below), not refitted with them.
            blob = np.flatnonzero(pair[:n_blobs])
            pr_, pc_ = r[:n_blobs].copy(), c[:n_blobs].copy()
            tr_, tc_ = rows[:n_blobs].copy(), cols[:n_blobs].copy()
            pr_[blob], pc_[blob] = blob_r[blob], blob_c[blob]
            tr_[blob], tc_[blob] = blob_rows[blob], blob_cols[blob]
            pull_r, pull_c, fit_blobs = _neighbour_pull(
                pr_, pc_, sm[tr_, tc_], filtered_var, (h, w)
            )
            extra = len(r) - n_blobs
            pull_r = np.concatenate([pull_r, np.zeros(extra)])
            pull_c = np.concatenate([pull_c, np.zeros(extra)])
            fit = np.concatenate([fit_blobs, np.ones(extra, dtype=bool)])
            fit[blob] = True
            pull_r[pair], pull_c[pair] = 0.0, 0.0
        else:
            pull_r, pull_c, fit = _neighbour_pull(r, c, sm[rows, cols], filtered_var, (h, w))
        r[~fit] -= pull_r[~fit]
        c[~fit] -= pull_c[~fit]
    if saturated is not None and clipped.any() and sigma > _FIT_ALL_FROM_PX:
        k = np.flatnonzero(clipped)
        rk, ck, area = _clipped_tops(saturated, top_rows, top_cols, k)
        # (a top 2.5 px or more from the filtered maximum is two tops run together, or
        # cut: the maximum stays the start)
        wide = (area >= _CLIPPED_FIT_PX) & (np.hypot(rk - r[k], ck - c[k]) <= 2.5)
        r[k[wide]], c[k[wide]] = rk[wide], ck[wide]
    if fit.any():
        k = np.flatnonzero(fit)
        free = None
        if pair.any() and not fit.all():
            # (a split pair's neighbours that the pull resolved: held, their light taken out)
            held_px = 2.0 * spotfit.window_half_px(sigma) * math.sqrt(2.0)
            dr_, dc_ = r[pair][:, None] - r[None, :], c[pair][:, None] - c[None, :]
            held = ((dr_ * dr_ + dc_ * dc_) <= held_px * held_px).any(axis=0) & ~fit
            k = np.flatnonzero(fit | held)
            free = fit[k]
        peak = centre[k] * spread2 / (sigma * sigma)  # the spot's own peak from the smoothed
        # Fitted on the subtracted image: near large, dense spots the local background
        # (a min filter) holds their light; each fit has its own plane for what is left.
        fr, fc, fpeak, fs = spotfit.fit_spots(
            sub, saturated, rows[k], cols[k], sigma, peak, start=(r[k], c[k]), free=free
        )
        # A fit that wandered off, or whose size ran to its bound (no spot of the image's
        # size there: a neighbour's light or a shape the Gaussian does not fit), keeps its start.
        moved = np.hypot(fr - r[k], fc - c[k]) <= 1.5
        moved &= fs < 0.999 * spotfit.window_half_px(sigma) / 2.0
        r[k[moved]], c[k[moved]] = fr[moved], fc[moved]
        if sigma > _FIT_ALL_FROM_PX and len(k) == len(r):
            fpk = np.where(moved, fpeak, peak)
            fsg = np.where(moved, fs, sigma)
            r, c = _asymmetric_light(sub, d, saturated, rows, cols, r, c, fpk, fsg, sigma, noise)
    if learned_shape and sigma > _FIT_ALL_FROM_PX:
        # Experimental (not the default; docs/benchmarks/detection.md): every dot refitted
        # with the profile learned from the image's isolated dots, jointly with its neighbours.
        valid = None if saturated is None else ~saturated
        r, c, *_ = spotshape.fit_dots(
            sub,
            valid,
            r,
            c,
            centre * spread2 / (sigma * sigma),
            sigma,
            noise,
            spotfit.window_half_px(sigma),
        )
    # (a blob whose second spot is no dot keeps the test's centre of its first)
    r[fixed], c[fixed] = fixed_r, fixed_c
    if cut.any():
        k = np.flatnonzero(cut & ~pair & ~fixed)
        r[k], c[k] = _refine(d, top_rows[k], top_cols[k])
    return np.column_stack([r + r0, c + c0, centre.astype(np.float64)])


#: Light beside a dot that is not point-symmetric about it (:func:`_asymmetric_light`) is
#: another source where the residual's matched filter stands this many of its noise sigmas
#: above its mirror image through the dot ...
_ASYM_SNR = 6.0
#: ... and this share of the dot's own matched-filtered peak (the spot model's own mismatch,
#: a speckled halo's grains, scales with the dot).
_ASYM_SHARE = 0.1


def _asymmetric_light(
    sub: NDArray[np.float32],
    d: NDArray[np.float32],
    saturated: NDArray[np.bool_] | None,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    peak: NDArray[np.float64],
    spot_sigma: NDArray[np.float64],
    sigma: float,
    noise: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Refit the dots beside which light is left that no dot explains and that is not
    point-symmetric about the dot (a ghost reflection, an undetected neighbour): the fit is
    unbiased for any point-symmetric spot, so only such light moves a centre. The light is
    found in the residual of the fitted dots' model (matched-filtered with the image's spot
    size), at least one spot sigma from the dot and within its window, standing above the
    residual at its mirror position through the dot by :data:`_ASYM_SNR` noise sigmas and
    :data:`_ASYM_SHARE` of the dot; each such source is fitted as one more (free) spot with
    the dots within reach of it (their neighbours held), and dropped: it is no dot.
    Clipped tops and the pixels around them, where the model is only a bound, are not read.

    ``r``, ``c``, ``peak``, ``spot_sigma``: the fitted dots (px, gray levels of the profile's
    peak, px); ``d``: the background-free image the residual is taken of, ``sub`` the one
    the dots were fitted on."""
    h_img, w_img = d.shape
    half = spotfit.window_half_px(sigma)
    size = 2 * half + 1
    r0 = np.rint(r).astype(np.intp) - half
    c0 = np.rint(c).astype(np.intp) - half
    gr, _, _ = spotfit.window_gaussian((r0 - r)[:, None], size, spot_sigma[:, None], False)
    gc, _, _ = spotfit.window_gaussian((c0 - c)[:, None], size, spot_sigma[:, None], False)
    mass = peak * 2.0 * math.pi * spot_sigma * spot_sigma
    tiles = mass[:, None, None] * gr[:, :, None] * gc[:, None, :]
    wide = w_img + 2 * size
    off = np.arange(size)
    flat = ((r0 + size)[:, None, None] + off[None, :, None]) * wide + (
        (c0 + size)[:, None, None] + off[None, None, :]
    )
    model = np.bincount(flat.ravel(), tiles.ravel(), (h_img + 2 * size) * wide)
    model = model.reshape(h_img + 2 * size, wide)
    res = d - model[size : size + h_img, size : size + w_img].astype(np.float32)
    if saturated is not None and saturated.any():
        # (a clipped top says nothing about the shape, nor does the model's edge around it)
        grow = 2 * math.ceil(sigma) + 1
        near_clip = cv2.dilate(saturated.view(np.uint8), np.ones((grow, grow), np.uint8))
        res[near_clip.view(bool)] = 0.0
    res_s = cv2.GaussianBlur(res, (0, 0), sigma)
    # white noise through a unit-peak Gaussian of σ: noise / (2 √π σ); √2 for the difference
    # of two such values
    level = _ASYM_SNR * math.sqrt(2.0) * noise / (2.0 * math.sqrt(math.pi) * sigma)
    # residual maxima (3x3) above the level
    dil = cv2.dilate(res_s, np.ones((3, 3), np.uint8))
    mr, mc = np.nonzero((res_s >= dil) & (res_s > level))
    if len(mr) == 0:
        return r, c
    # the dot each maximum lies beside: nearest within its window, ≥ 1 spot sigma away
    pi, pj = spotfit.near_pairs(
        np.concatenate([mr.astype(np.float64), r]),
        np.concatenate([mc.astype(np.float64), c]),
        float(half),
        sort=False,
    )
    m = len(mr)
    sel = (pi < m) & (pj >= m)
    pi, pj = pi[sel], pj[sel] - m
    if len(pi) == 0:
        return r, c
    dr, dc = mr[pi] - r[pj], mc[pi] - c[pj]
    dist = np.hypot(dr, dc)
    ok = dist >= sigma
    # its mirror through the dot (sub-pixel: a residual ring's slope would pass for asymmetry)
    mirror = _bilinear(res_s, r[pj] - dr, c[pj] - dc)
    dot_s = peak[pj] * spot_sigma[pj] ** 2 / (spot_sigma[pj] ** 2 + sigma * sigma)
    ok &= res_s[mr[pi], mc[pi]] - mirror > np.maximum(level, _ASYM_SHARE * dot_s)
    if not ok.any():
        return r, c
    g = np.unique(pi[ok])
    gr_, gc_ = mr[g].astype(np.float64), mc[g].astype(np.float64)
    # the dots within reach of a source: refitted with it; their neighbours held
    reach = 2.0 * half
    near = (np.abs(r[:, None] - gr_[None, :]) <= reach) & (
        np.abs(c[:, None] - gc_[None, :]) <= reach
    )
    free_dots: NDArray[np.bool_] = np.asarray(near.any(axis=1))
    fi = np.flatnonzero(free_dots)
    # their neighbours, held where they are: their light taken out of the refitted windows
    held = (np.abs(r[:, None] - r[None, fi]) <= reach) & (np.abs(c[:, None] - c[None, fi]) <= reach)
    k = np.flatnonzero(free_dots | held.any(axis=1))
    g_peak = res_s[mr[g], mc[g]] * 2.0  # (the residual's smoothed peak of a spot of σ)
    free: NDArray[np.bool_] = np.concatenate([free_dots[k], np.ones(len(g), dtype=bool)])
    fr, fc, _, fs = spotfit.fit_spots(
        sub,
        saturated,
        np.concatenate([rows[k], mr[g]]),
        np.concatenate([cols[k], mc[g]]),
        sigma,
        np.concatenate([peak[k], g_peak]),
        start=(np.concatenate([r[k], gr_]), np.concatenate([c[k], gc_])),
        free=free,
    )
    nk = len(k)
    fr, fc, fs = fr[:nk], fc[:nk], fs[:nk]
    moved = free[:nk] & (np.hypot(fr - r[k], fc - c[k]) <= 1.5) & (fs < 0.999 * half / 2.0)
    r, c = r.copy(), c.copy()
    r[k[moved]], c[k[moved]] = fr[moved], fc[moved]
    return r, c


def _pairs_near(
    k: NDArray[np.intp], r: NDArray[np.float64], c: NDArray[np.float64], reach_px: float
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """(a, j): dot k[a] and another dot j at most ``reach_px`` apart (Euclidean), every such
    pair: all pairs tested at once for a few dots k, else from the grid of
    :func:`~omnid.core.spotfit.near_pairs`."""
    if len(k) * len(r) <= 20000:
        dr, dc = r[k][:, None] - r[None, :], c[k][:, None] - c[None, :]
        close = dr * dr + dc * dc <= reach_px * reach_px
        close[np.arange(len(k)), k] = False
        a, j = np.nonzero(close)
        return a.astype(np.intp), j.astype(np.intp)
    i, j = spotfit.near_pairs(r, c, reach_px, sort=False)
    local = np.full(len(r), -1, dtype=np.intp)
    local[k] = np.arange(len(k))
    a = local[i]
    keep = (a >= 0) & (np.hypot(r[i] - r[j], c[i] - c[j]) <= reach_px)
    return a.compress(keep), j.compress(keep)


def _own_curvature(
    sm: NDArray,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    top: NDArray,
    filtered_var: float,
    k: NDArray[np.intp],
    pairs: tuple[NDArray[np.intp], NDArray[np.intp]],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The principal variances (long, short; px²) of the smoothed light of dots ``k`` at their
    maxima, its neighbours' light taken out, and the long axis (len(k), 2); ``pairs`` (a, j):
    dot k[a] and a neighbour j (:func:`_pairs_near`).

    The 3x3 log-quadratic of ``sm`` gives the Hessian of ln f at the maximum, i.e. H(f)/f
    (the gradient vanishes there). Each neighbour j, a Gaussian of the filtered variance v
    with its smoothed peak ``top`` at its own maximum, adds e_j·(x xᵀ/v² − I/v) to H(f) and
    e_j to f at the distance x from it (e_j its light there); both are taken out, so a
    neighbour 4 px away does not make a round spot look elongated."""
    vals = _windows(sm, rows[k], cols[k], 1)
    t = vals[4:5]
    logs = np.log(np.maximum(vals, np.float32(1e-3) * np.maximum(t, np.float32(1e-3))))
    _, _, _, qr, qc, qrc = (_Q_SOLVE32.T @ logs).astype(np.float64)
    f = np.abs(top[k]).astype(np.float64)
    hrr, hcc, hrc = 2.0 * qr * f, 2.0 * qc * f, qrc * f
    a, j = pairs
    xr = r[k].take(a) - r.take(j)
    xc = c[k].take(a) - c.take(j)
    e = np.abs(top.take(j)).astype(np.float64) * np.exp((xr * xr + xc * xc) * (-0.5 / filtered_var))
    inv_v, inv_v2 = 1.0 / filtered_var, 1.0 / (filtered_var * filtered_var)
    n = len(k)
    hrr -= np.bincount(a, weights=e * (xr * xr * inv_v2 - inv_v), minlength=n)
    hcc -= np.bincount(a, weights=e * (xc * xc * inv_v2 - inv_v), minlength=n)
    hrc -= np.bincount(a, weights=e * (xr * xc * inv_v2), minlength=n)
    own = np.maximum(f - np.bincount(a, weights=e, minlength=n), 0.05 * f)
    hrr, hcc, hrc = hrr / own, hcc / own, hrc / own
    mid = 0.5 * (hrr + hcc)
    rad = np.sqrt(0.25 * (hrr - hcc) ** 2 + hrc * hrc)
    flat, steep = mid + rad, mid - rad
    v_long = np.where(flat < 0, -1.0 / np.minimum(flat, -1e-12), np.inf)
    v_short = -1.0 / np.minimum(steep, -1e-12)
    # the eigenvector of the flatter curvature
    ar, ac = hrc, flat - hrr
    norm = np.hypot(ar, ac)
    degenerate = norm < 1e-12
    ar = np.where(degenerate, 1.0, ar / np.where(degenerate, 1.0, norm))
    ac = np.where(degenerate, 0.0, ac / np.where(degenerate, 1.0, norm))
    return v_long, v_short, np.column_stack([ar, ac])


@functools.lru_cache(maxsize=64)
def _blend_elongation(filtered_var: float, separation_px: float, relative_peak: float) -> float:
    """How elongated (long over short principal variance, as :func:`_log_quadratic` measures
    it on the 3x3 pixels around the maximum) the smoothed light of the least separable blend
    looks: two round spots of filtered variance ``filtered_var`` ``separation_px`` apart, the
    dimmer ``relative_peak`` of the brighter. (To second order v / (1 − w(1 − w)·d²/v) with w
    the dimmer's share of the light at the maximum; the 3x3 fit also sees the fourth order,
    which makes a blend look rounder.) The least over the pair's orientation."""
    half = 6
    g = np.arange(-half, half + 1, dtype=np.float64)
    rr, cc = np.meshgrid(g, g, indexing="ij")
    least = math.inf
    for angle in np.linspace(0.0, math.pi / 4.0, 4):
        er, ec = math.cos(angle), math.sin(angle)
        # the maximum: along the axis, by a fine search between the two spots
        t = np.linspace(-0.5, 1.5, 2001) * separation_px
        prof = np.exp(-(t**2) / (2 * filtered_var)) + relative_peak * np.exp(
            -((t - separation_px) ** 2) / (2 * filtered_var)
        )
        t0 = float(t[np.argmax(prof)])
        ar, ac = rr + t0 * er - np.rint(t0 * er), cc + t0 * ec - np.rint(t0 * ec)
        img = np.exp(-(ar**2 + ac**2) / (2 * filtered_var)) + relative_peak * np.exp(
            -((ar - separation_px * er) ** 2 + (ac - separation_px * ec) ** 2) / (2 * filtered_var)
        )
        # (the sampled maximum is at the grid's centre pixel or next to it)
        k = np.unravel_index(int(np.argmax(img)), img.shape)
        _, _, mean_var, max_var, ok = _log_quadratic(
            img.astype(np.float32), np.array([k[0]]), np.array([k[1]])
        )
        if ok[0]:
            min_var = 1.0 / (2.0 / mean_var[0] - 1.0 / max_var[0])
            least = min(least, float(max_var[0] / min_var))
    return least if math.isfinite(least) else 1.0


def _split_blends(
    d: NDArray[np.float32],
    saturated: NDArray[np.bool_] | None,
    sm: NDArray,
    candidates: _Candidates,
    curvature: tuple[NDArray[np.float64], NDArray[np.float64]],
    sigma: float,
    relative_peak: float,
    noise: float,
    region: NDArray[np.bool_] | None = None,
) -> tuple[
    NDArray[np.intp],
    NDArray[np.intp],
    NDArray,
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.bool_],
    NDArray[np.bool_],
    NDArray[np.bool_],
]:
    """The candidates with every blend of two spots split in two, which dots came from a
    split (to be fitted jointly, :func:`~omnid.core.spotfit.fit_spots`, from the test's
    centres), and which keep the test's centre (a blob whose second spot is no dot).

    Screen (every dot, from the 3x3 curvature its maximum already has): a blend of two
    round spots of filtered variance v, d apart with shares w and 1 − w of the light at its
    maximum, is as wide as one spot across the line between them and flatter along it: its
    long-axis variance is v / (1 − w(1 − w)·d²/v) to second order. Dots whose own light
    (neighbours taken out, :func:`_own_curvature`) is at least as elongated as the least
    separable blend the detector would split — :data:`_SPLIT_MIN_SIGMAS` apart, the dimmer
    ``relative_peak`` of the brighter — are tested (on the random rigs' floors ~1 % of dots).

    Test (:func:`~omnid.core.spotfit.blend_test`): one stretched spot against two round
    spots of the image's size, by the likelihood ratio at the detector's noise (or the
    window's residual, where larger) less the information criterion's price of the two-spot
    family's extra parameters. Split where two spots win, their best separation lies inside
    the family and at least :data:`_SPLIT_MIN_SIGMAS` σ (closer two spots are one maximum of
    any smoothing: no capture resolves them the same way twice), and both are dots by the
    detector's own rule: the dimmer's smoothed peak ≥ ``relative_peak`` of the brighter's. A
    blob that two spots explain but whose dimmer one is not a dot (a ghost reflection, a
    halo's grain) keeps one dot, at the brighter spot's centre.

    ``candidates``: (rows, cols, smoothed peak, sub-pixel row, col, clipped) as
    :func:`_take` keeps them; ``curvature``: their (mean, larger principal) variances from
    :func:`_log_quadratic` of ``sm`` (every candidate's quadratic a maximum); ``region``
    (``sm``'s shape): only candidates whose maximum lies in it are tested (None: all)."""
    rows, cols, centre, r, c, clipped = candidates
    n = len(rows)
    none = np.zeros(n, dtype=bool)
    if n == 0:
        return rows, cols, centre, r, c, clipped, none, none
    h, w = sm.shape
    spread2 = sigma * sigma + 1.0 + 1.0 / 12.0  # a spot's variance after the σ = 1 smoothing
    # (the image's spot size to 0.01 px: one threshold per size, computed once)
    s_key = round(sigma, 2)
    elongation = _blend_elongation(
        s_key * s_key + 1.0 + 1.0 / 12.0, _SPLIT_MIN_SIGMAS * s_key, relative_peak
    )
    # (the raw curvatures first: a neighbour only ever adds elongation to them)
    mean_var, max_var = curvature
    min_var = 1.0 / np.maximum(2.0 / mean_var - 1.0 / max_var, 1e-12)
    elongated = max_var >= elongation * min_var
    if region is not None:
        elongated &= region[rows, cols]
    ask = np.flatnonzero(elongated)
    if len(ask) == 0:
        return rows, cols, centre, r, c, clipped, none, none
    # the neighbours whose light reaches a candidate's test window (and its 3x3 curvature)
    scale = math.sqrt(sigma * sigma + 1.0 / 12.0)
    reach = spotfit.window_half_px(sigma) * math.sqrt(2.0) + 3.0 * scale
    a, j = _pairs_near(ask, r, c, reach)
    v_long, v_short, axis = _own_curvature(sm, rows, cols, r, c, centre, spread2, ask, (a, j))
    keep = v_long >= elongation * v_short
    if not keep.any():
        return rows, cols, centre, r, c, clipped, none, none
    ask, axis = ask[keep], axis[keep]
    renumber = np.cumsum(keep) - 1
    kept = keep[a]
    a, j = renumber[a[kept]], j[kept]
    valid = None if saturated is None else ~saturated
    # the other dots, round spots of the image's size (their peak from the smoothed one),
    # are taken out of each window
    peak = np.abs(centre).astype(np.float64) * spread2 / (sigma * sigma + 1.0 / 12.0)
    test = spotfit.blend_test(
        d, r[ask], c[ask], axis, sigma, noise, valid, (a, r[j], c[j], peak[j])
    )
    two = (test.evidence > 0) & test.interior & (test.separation >= _SPLIT_MIN_SIGMAS)
    if not two.any():
        return rows, cols, centre, r, c, clipped, none, none
    cen = test.centres
    ir = np.rint(cen[:, :, 0]).astype(np.intp)
    ic = np.rint(cen[:, :, 1]).astype(np.intp)
    two &= np.all((ir >= 3) & (ir < h - 3) & (ic >= 3) & (ic < w - 3), axis=1)
    peaks = test.peaks
    bright = np.argmax(peaks, axis=1)
    dim_ok = peaks.min(axis=1) >= relative_peak * peaks.max(axis=1)
    k_two, k_one = ask[two & dim_ok], ask[two & ~dim_ok]
    rows, cols = rows.copy(), cols.copy()
    r, c, centre = r.copy(), c.copy(), centre.astype(np.float64, copy=True)
    # the smoothed peak of a fitted spot: its peak · var / (var + 1) after the σ = 1 smoothing
    to_smoothed = (sigma * sigma + 1.0 / 12.0) / spread2
    fixed = np.zeros(n, dtype=bool)
    if len(k_one):
        sel = two & ~dim_ok
        cb = cen[sel, bright[sel]]
        r[k_one], c[k_one] = cb[:, 0], cb[:, 1]
        fixed[k_one] = True
    if len(k_two) == 0:
        return rows, cols, centre, r, c, clipped, none, fixed
    sel = two & dim_ok
    cen, ir, ic, pk = cen[sel], ir[sel], ic[sel], peaks[sel] * to_smoothed
    rows[k_two], cols[k_two] = ir[:, 0], ic[:, 0]
    r[k_two], c[k_two] = cen[:, 0, 0], cen[:, 0, 1]
    centre[k_two] = pk[:, 0]
    pair = np.zeros(n + len(k_two), dtype=bool)
    pair[k_two] = True
    pair[n:] = True
    return (
        np.concatenate([rows, ir[:, 1]]),
        np.concatenate([cols, ic[:, 1]]),
        np.concatenate([centre, pk[:, 1]]),
        np.concatenate([r, cen[:, 1, 0]]),
        np.concatenate([c, cen[:, 1, 1]]),
        np.concatenate([clipped, clipped[k_two]]),
        pair,
        np.concatenate([fixed, np.zeros(len(k_two), dtype=bool)]),
    )


def _ring_contrast(
    sm: NDArray,
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    top: NDArray,
    spot_px: float,
) -> NDArray[np.float64]:
    """1 − (the median of 8 points on a ring :data:`_FAR_RING` image spot sizes ``spot_px``
    out, 3 to 10 px) / the peak: how far each peak falls within a few spot sizes (up to 3 of
    the 8 points may fall on neighbours)."""
    radius = min(max(_FAR_RING * spot_px, 3.0), 10.0)
    pad = math.ceil(radius) + 1
    h, w = sm.shape
    if min(rows.min(), cols.min()) >= pad and rows.max() < h - pad and cols.max() < w - pad:
        big, pad = sm, 0  # every ring inside: no border needed
    else:
        big = cv2.copyMakeBorder(sm, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    ang = np.arange(8) * (math.pi / 4.0)
    # (8, n): one bilinear look-up for the whole ring
    ring_r = (rows + pad)[None, :] + np.array([[radius * math.sin(a)] for a in ang])
    ring_c = (cols + pad)[None, :] + np.array([[radius * math.cos(a)] for a in ang])
    ring = _bilinear(big, ring_r, ring_c)
    return np.asarray(1.0 - np.median(ring, axis=0) / np.maximum(top, 1e-6), dtype=np.float64)


_Candidates = tuple[
    NDArray[np.intp],
    NDArray[np.intp],
    NDArray,
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.bool_],
]


def _take(
    ok: NDArray[np.bool_],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    centre: NDArray,
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    clipped: NDArray[np.bool_],
) -> _Candidates:
    """The candidates ``ok`` keeps: peak pixel, smoothed peak, sub-pixel centre, clipped."""
    return rows[ok], cols[ok], centre[ok], r[ok], c[ok], clipped[ok]


def _clipped_tops(
    saturated: NDArray[np.bool_],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
    k: NDArray[np.intp],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp]]:
    """The centroid (row, col) of the clipped top (the 8-connected region of clipped pixels)
    next to the peak pixel of each dot ``k`` of all the peaks ``rows``, ``cols``, and its
    area: a clipped top is point-symmetric about the dot's centre, as the spot is. A region
    next to no peak of ``k`` or next to two peaks (two dots' tops run together) gets area 0."""
    _, labels, stats, cents = cv2.connectedComponentsWithStats(
        saturated.view(np.uint8), connectivity=8, ltype=cv2.CV_32S
    )
    lab = _windows(labels, rows, cols, 1).max(axis=0)  # (maxima lie ≥ 1 px inside)
    shared = np.bincount(lab, minlength=len(stats)) > 1
    mine = lab[k]
    area = np.where((mine > 0) & ~shared[mine], stats[mine, cv2.CC_STAT_AREA], 0)
    return cents[mine, 1].astype(np.float64), cents[mine, 0].astype(np.float64), area


def _one_spot(
    sm: NDArray,
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    top: NDArray,
    reach_px: int,
) -> NDArray[np.bool_]:
    """(n,) False for maxima that are only a bump on a brighter one's top: two maxima at most
    ``reach_px`` apart (per axis) are two dots only if the smoothed image ``sm`` dips between
    them — somewhere on the segment (at ¼, ½ and ¾) below (1 − :data:`_SADDLE_DEPTH`) of the
    dimmer one. Two equal Gaussian spots 2.5 filtered sigmas apart dip by 12 %; the maxima
    a clipped, flat or grainy top breaks into do not."""
    keep = np.ones(len(r), dtype=bool)
    i, j = spotfit.near_pairs(r, c, reach_px, sort=False)
    sel = (top[i] < top[j]) | ((top[i] == top[j]) & (i > j))  # i: the dimmer of the pair
    i, j = i.compress(sel), j.compress(sel)
    if len(i) == 0:
        return keep
    t = np.array([0.25, 0.5, 0.75])[:, None]
    low = _bilinear(sm, r[i] + t * (r[j] - r[i]), c[i] + t * (c[j] - c[i])).min(axis=0)
    keep[i[low >= (1.0 - _SADDLE_DEPTH) * top[i]]] = False
    return keep


def _climb(
    f: NDArray, rows: NDArray[np.intp], cols: NDArray[np.intp], steps: int
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Each peak pixel moved uphill on ``f`` (to the largest of its 3x3 neighbours, at most
    ``steps`` times, staying ≥ 1 px inside) to the local maximum of ``f`` it belongs to.

    A climb counts only if it ends on a maximum of ``f`` nearer to its own peak than to any
    other peak (in its Voronoi cell): one that heads for another dot's maximum — ``f``
    blurs close dots into one — or does not arrive stays where it was."""
    h, w = f.shape
    r, c = rows.copy(), cols.copy()
    live = np.arange(len(r))
    for _ in range(steps):
        best = _windows(f, r[live], c[live], 1).argmax(axis=0)
        moving = best != 4
        live = live[moving]
        if len(live) == 0:
            break
        dr, dc = np.divmod(best[moving], 3)
        r[live] = clip(r[live] + dr - 1, 1, h - 2)
        c[live] = clip(c[live] + dc - 1, 1, w - 2)
    moved = np.flatnonzero((r != rows) | (c != cols))
    if len(moved) == 0:
        return r, c
    back = np.zeros(len(r), dtype=bool)
    back[live] = True  # still climbing
    if len(rows) > 1:
        tree = cKDTree(np.column_stack([rows, cols]).astype(np.float64))
        _, own = tree.query(np.column_stack([r[moved], c[moved]]).astype(np.float64))
        back[moved[own != moved]] = True
    r[back], c[back] = rows[back], cols[back]
    return r, c


def _bilinear(img: NDArray, r: NDArray, c: NDArray) -> NDArray:
    """``img`` at sub-pixel (row, col) points inside it, bilinear."""
    r = clip(r, 0.0, img.shape[0] - 1.001)
    c = clip(c, 0.0, img.shape[1] - 1.001)
    r0, c0 = r.astype(np.intp), c.astype(np.intp)
    fr, fc = r - r0, c - c0
    w = img.shape[1]
    flat = np.ascontiguousarray(img).ravel()  # (gathers of flat indices: ~2x 2-D indexing)
    at = r0 * w + c0
    top = np.take(flat, at) * (1.0 - fc) + np.take(flat, at + 1) * fc
    at += w
    bottom = np.take(flat, at) * (1.0 - fc) + np.take(flat, at + 1) * fc
    return np.asarray(top * (1.0 - fr) + bottom * fr)


def _cut_by_rim(
    mask_gray: NDArray, rows: NDArray[np.intp], cols: NDArray[np.intp]
) -> NDArray[np.bool_]:
    """(n,) dots with a pixel of the dark housing (mask frame below :data:`_HOUSING_GRAY`)
    within 2 px: their light is cut by the mirror's rim. Peaks lie ≥ 3 px inside the image."""
    if len(rows) == 0:
        return np.zeros(0, dtype=bool)
    return np.asarray(_windows(mask_gray, rows, cols, 2).min(axis=0) < _HOUSING_GRAY)


def _neighbour_pull(
    r: NDArray[np.float64],
    c: NDArray[np.float64],
    top: NDArray,
    filtered_var: float,
    shape: tuple[int, int],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """How far each dot's filtered maximum is pulled by its neighbours' light (row, col, px),
    and which dots (with the neighbours pulling them) this does not resolve, to be fitted.

    For Gaussian spots of filtered variance v the filtered image is Σ_j A_j e_j(x) with
    e_j(x) = exp(−|x − c_j|²/2v); at the maximum p_i of dot i its gradient vanishes and its
    value is the smoothed peak:

        Σ_j A_j e_j(p_i) (c_j − p_i) = 0,   Σ_j A_j e_j(p_i) = top_i,

    solved for every centre c_i and amplitude A_i by fixed-point iteration
    (:data:`_PULL_ITERATIONS`, from c = p, A = top: the first step is the first-order pull
    Σ_j (top_j / top_i) e_j(p_i) (p_j − p_i)). A dot whose centre is still moving, or moved
    more than :data:`_PULL_MAX_PX`, is left to the fit. Only the dots with another dot
    within the distance where a twice as bright neighbour would move it by
    :data:`_COUPLING_PX` (:func:`_pull_reach_px`; found by :func:`~omnid.core.spotfit.near_pairs`)
    are paired, so well separated dots cost one pass.
    """
    n = len(r)
    pull_r, pull_c = np.zeros(n), np.zeros(n)
    unresolved = np.zeros(n, dtype=bool)
    if n < 2:
        return pull_r, pull_c, unresolved
    half = round(_pull_reach_px(filtered_var))
    i, j = spotfit.near_pairs(r, c, half + 1)
    # The dots with another dot within ``half`` px per axis (rounded to pixels), and the
    # pairs among them.
    ri, ci = np.rint(r).astype(np.intp), np.rint(c).astype(np.intp)
    near = (np.abs(ri[i] - ri[j]) <= half) & (np.abs(ci[i] - ci[j]) <= half)
    is_close = np.zeros(n, dtype=bool)
    is_close[i.compress(near)] = True
    close = np.flatnonzero(is_close)
    both = is_close[i] & is_close[j]
    if not both.any():
        return pull_r, pull_c, unresolved
    local = np.cumsum(is_close) - 1  # index among the close dots
    i, j = np.take(local, i.compress(both)), np.take(local, j.compress(both))
    m = len(close)
    pr, pc = r[close], c[close]
    t = np.abs(top[close]).astype(np.float64)
    t = np.maximum(t, 1e-6)
    cr, cc, amp = pr.copy(), pc.copy(), t.copy()
    neg_inv2v = -1.0 / (2.0 * filtered_var)
    pr_i, pc_i, floor_t = np.take(pr, i), np.take(pc, i), 0.05 * t  # (loop invariants)
    step = np.zeros(m)
    last = _PULL_ITERATIONS - 1
    for it in range(_PULL_ITERATIONS):
        dr, dc = np.take(cr, j) - pr_i, np.take(cc, j) - pc_i
        # neighbour j's light at p_i
        q = dr * dr
        q += dc * dc
        q *= neg_inv2v
        lj = np.take(amp, j) * np.exp(q, out=q)
        sum_l = np.bincount(i, weights=lj, minlength=m)
        sum_r = np.bincount(i, weights=np.multiply(lj, dr, out=dr), minlength=m)
        sum_c = np.bincount(i, weights=np.multiply(lj, dc, out=dc), minlength=m)
        if it == 0:  # (c = p: each dot's own light at p is its amplitude, exp(0) = 1)
            own, a_own = np.ones(m), np.maximum(amp, floor_t)
        else:
            er, ec = cr - pr, cc - pc
            er *= er
            ec *= ec
            er += ec
            er *= neg_inv2v
            own = np.exp(er, out=er)
            a_own = np.maximum(amp * own, floor_t)
        new_r, new_c = pr - sum_r / a_own, pc - sum_c / a_own
        if it == last:  # only the last step is judged (and its amplitudes are not needed)
            step = np.hypot(new_r - cr, new_c - cc)
            cr, cc = new_r, new_c
            break
        cr, cc = new_r, new_c
        amp = np.maximum(t - sum_l, floor_t) / np.maximum(own, 1e-3)
    pull_r[close], pull_c[close] = pr - cr, pc - cc
    bad = (step > _COUPLING_PX) | (np.hypot(pr - cr, pc - cc) > _PULL_MAX_PX)
    if bad.any():
        hit = bad[i]
        unresolved[close[i[hit]]] = True
        unresolved[close[j[hit]]] = True
    return pull_r, pull_c, unresolved


def _pull_reach_px(filtered_var: float, ratio: float = 2.0) -> float:
    """The distance beyond which a neighbour ``ratio`` times as bright no longer moves a
    filtered maximum by :data:`_COUPLING_PX`."""
    d = math.sqrt(filtered_var)  # the pull peaks at one filtered sigma, then falls
    while ratio * d * math.exp(-d * d / (2.0 * filtered_var)) > _COUPLING_PX:
        d += 0.1
    return d


def _local_maxima(
    sm: NDArray,
    threshold: float,
    margin_px: int,
    box: tuple[int, int, int, int],
    shape: tuple[int, int],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Local maxima (3x3) of ``sm`` above ``threshold`` at least ``margin_px`` inside the image
    (``sm`` covers ``box`` = (r0, r1, c0, c1) of an image of ``shape``)."""
    h, w = sm.shape
    r0, r1, c0, c1 = box
    peaks = sm >= cv2.dilate(sm, np.ones((3, 3), np.uint8))
    peaks &= sm > threshold
    m = margin_px
    # at least 1 px inside ``sm`` too: the sub-pixel fit reads each peak's 3x3 neighbourhood
    peaks[: max(m - r0, 1), :] = False
    peaks[h - max(m - (shape[0] - r1), 1) :, :] = False
    peaks[:, : max(m - c0, 1)] = False
    peaks[:, w - max(m - (shape[1] - c1), 1) :] = False
    flat = np.flatnonzero(peaks)  # (much faster than np.nonzero on a 2-D mask)
    rows, cols = np.divmod(flat, w)
    return rows, cols


def _clipped_near(
    base: NDArray,
    weights: tuple[float, float, float],
    rows: NDArray[np.intp],
    cols: NDArray[np.intp],
) -> NDArray[np.bool_]:
    """(n,) whether the laser's channel of ``base`` reaches the sensor's largest value in the 3x3
    pixels around each (row, col) — at least 1 px inside the image — (all False for float
    images: no clip level)."""
    if base.dtype.kind == "f" or len(rows) == 0:
        return np.zeros(len(rows), dtype=bool)
    gray = _laser_gray(base, weights)
    top = np.iinfo(base.dtype).max
    return np.asarray(_windows(gray, rows, cols, 1).max(axis=0) >= top)


def _saturated(
    base: NDArray, weights: tuple[float, float, float], box: tuple[int, int, int, int]
) -> NDArray[np.bool_] | None:
    """Pixels of the box where the laser's channel of the base frame is clipped (the sensor's
    largest value), or None where none is (and for images without a clip level: float)."""
    if base.dtype.kind == "f":
        return None
    top = np.iinfo(base.dtype).max
    r0, r1, c0, c1 = box
    part = base[r0:r1, c0:c1]
    if part.ndim == 3:
        nz = np.flatnonzero(np.asarray(weights, dtype=np.float64))
        clipped = np.any(part[:, :, nz] >= top, axis=2)
        return clipped if clipped.any() else None
    if cv2.minMaxLoc(part)[1] < top:
        return None
    return part >= top


@functools.lru_cache(maxsize=16)
def _disk(radius_px: int) -> NDArray[np.bool_]:
    """The (2r + 1)² boolean disk of cv2.MORPH_ELLIPSE: the neighbourhood of the relative test."""
    k = 2 * radius_px + 1
    return np.asarray(cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)), dtype=bool)


@functools.lru_cache(maxsize=32)
def _window_offsets(half_px: int, width_px: int, disk: bool) -> NDArray[np.intp]:
    """Flat-index offsets (row-major) of the (2·half + 1)² window — only its
    :func:`_disk` pixels if ``disk`` — in a C-contiguous image ``width_px`` wide."""
    off = np.arange(-half_px, half_px + 1)
    dr, dc = np.repeat(off, len(off)), np.tile(off, len(off))
    if disk:
        inside = _disk(half_px).ravel()
        dr, dc = dr[inside], dc[inside]
    flat = (dr * width_px + dc).astype(np.intp)
    flat.setflags(write=False)
    return flat


def _windows(
    img: NDArray, rows: NDArray[np.intp], cols: NDArray[np.intp], half_px: int, disk: bool = False
) -> NDArray:
    """(k, n) pixel values of the (2·half + 1)² windows (row-major; only the disk's pixels if
    ``disk``) around n points whose windows lie inside ``img``: one gather of flat indices
    (a strided view, a BGR image's channel, is indexed per axis). Window pixels run along
    the first axis: numpy reduces over a short last axis ~50x slower."""
    if img.flags.c_contiguous:
        w = img.shape[1]
        return img.ravel()[_window_offsets(half_px, w, disk)[:, None] + (rows * w + cols)]
    k = 2 * half_px + 1
    flat = _window_offsets(half_px, k, disk)
    dr, dc = np.divmod(flat + half_px * (k + 1), k)
    return img[(dr - half_px)[:, None] + rows, (dc - half_px)[:, None] + cols]


#: Offsets of the 5x5 fitting window and its design matrix [1, r, c, r² + c²] (25, 4).
_FIT_OFF = np.arange(-2, 3)
_FIT_R, _FIT_C = (
    a.ravel().astype(np.float64) for a in np.meshgrid(_FIT_OFF, _FIT_OFF, indexing="ij")
)
_FIT_X = np.column_stack([np.ones(25), _FIT_R, _FIT_C, _FIT_R**2 + _FIT_C**2])
#: Outer products of the design matrix's rows (25, 16): weights @ this = the normal matrices.
_FIT_XX = (_FIT_X[:, :, None] * _FIT_X[:, None, :]).reshape(25, 16)


def _refine(
    d: NDArray[np.float32], rows: NDArray[np.intp], cols: NDArray[np.intp]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Sub-pixel centres of dots the mirror's rim cuts: an isotropic Gaussian fitted to the
    5x5 pixels around each peak that see it.

    ``ln I = a + b·r + c·c + e·(r² + c²)`` solved by least squares weighted by I² (the log's
    noise is ~σ/I; pixels below 5 % of the window's brightest are left out), all dots at once
    through one batched solve of their 4x4 normal equations. The centre is (−b/2e, −c/2e), kept within ±1 px of
    the peak pixel. A Gaussian's logarithm is quadratic on whatever part of it is seen, so the
    cut does not move the centre (a smoothed image would spread the cut into it); the detector
    used it for every dot before the spot models (~1.5x the Cramér–Rao bound on round spots).
    """
    # Weights and logs in float32 (ample for 0.01 px; the sums below are float64).
    vals = np.asarray(_windows(d, rows, cols, 2), dtype=np.float32)  # (25, n)
    top = vals.max(axis=0)
    weight = np.where(vals > np.float32(0.05) * top, vals * vals, np.float32(0.0))
    logs = np.log(np.maximum(vals, np.float32(1e-3) * np.maximum(top, np.float32(1e-3))))
    # Normal equations XᵀWX + εI, one 4x4 system per dot (the dots the rim cuts are few:
    # one batched solve).
    normal = (_FIT_XX.T @ weight).T.reshape(-1, 4, 4)
    normal[:, np.arange(4), np.arange(4)] += 1e-9
    rhs = (_FIT_X.T @ (weight * logs)).T
    try:
        coef = np.linalg.solve(normal, rhs[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:  # numerically singular (a window of one lit pixel)
        coef = (np.linalg.pinv(normal) @ rhs[:, :, None])[:, :, 0]
    _, b, c, e = coef.T
    curv = np.where(e < 0, e, -1e-9)  # a peak must curve down
    dr = clip(-b / (2.0 * curv), -1.0, 1.0)
    dc = clip(-c / (2.0 * curv), -1.0, 1.0)
    return rows + dr, cols + dc


def detect_dots(
    mask: NDArray,
    base: NDArray,
    method: DetectionMethod = "best",
    params: DetectionParams | None = None,
    split_where: bool | NDArray[np.bool_] = False,
) -> NDArray[np.float64]:
    """Dot centres (N, 3) as (row_px, col_px, strength) in one camera's mask/base pair.

    ``split_where`` (``best`` only): where a maximum that two spots explain better than one —
    two beams closer than the smoothing resolves, a doubled beam — is split into two dots:
    nowhere (False), everywhere (True: what calibration learns the beams from; it costs
    1.4–2.6x the detection), or in the pixels an image-shaped boolean mask marks (perception:
    near the image tracks of the beams calibration found doubled,
    :func:`omnid.core.pipeline.split_regions`).

    Raises :class:`~omnid.errors.InputError` for arrays that are not images of one shape and
    dtype (or a ``split_where`` mask of another shape), and ``ValueError`` for an unknown
    method. No dots (or an empty image) → (0, 3).
    """
    p = params or _DEFAULT_PARAMS
    m, b = _check_pair(mask, base)
    if m.shape[0] == 0 or m.shape[1] == 0:
        return _empty()
    if method == "best":
        return _detect_best(m, b, p, split_blends=split_where)
    if method == "thesis":
        return _detect_thesis(m, b, p)
    raise ValueError(f"unknown detection method {method!r} (known: thesis, best)")
