"""Laser dot detection in a mask/base image pair (thesis chapter 5).

Interface shared by every method::

    detect_dots(mask, base, method="best" | "thesis", params=DetectionParams()) -> (N, 3) float64

Each row is (row_px, col_px, strength): the dot centre in image coordinates and its
brightness in the subtracted image (gray levels). An image with no dots gives an empty (0, 3)
array, never an exception.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from omnid.errors import InputError

DetectionMethod = Literal["thesis", "best"]


@dataclass(frozen=True)
class DetectionParams:
    """Thresholds of the detectors (gray levels unless stated)."""

    block_px: int = 21  # thesis 5.1: block threshold window (and step)
    block_coefficient: float = 1.5  # thesis 5.1: threshold = coefficient · block mean
    min_peak: float = 20.0  # brightest pixel must exceed this
    ring_e1: float = 1.0  # thesis 5.4: E1..E3 on ring-average differences
    ring_e2: float = 1.0
    ring_e3: float = 1.0
    e4: float = 5.0  # thesis 5.4: CircularAverage − SquareAverage ≥ E4


def to_gray(image: NDArray) -> NDArray[np.float32]:
    """8-bit gray or BGR image → float32 gray. For BGR the green channel (the laser's) is used."""
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] == 3:
        return arr[:, :, 1].astype(np.float32)
    if arr.ndim == 2:
        return arr.astype(np.float32)
    raise InputError(f"expected a gray (H, W) or BGR (H, W, 3) image, got shape {arr.shape}")


def subtract(mask: NDArray, base: NDArray) -> NDArray[np.float32]:
    """The *subtracted* image base − mask, negative values clipped to 0 (thesis 5.1)."""
    if np.shape(mask) != np.shape(base):
        raise InputError(f"mask and base differ in shape: {np.shape(mask)} vs {np.shape(base)}")
    return np.maximum(to_gray(base) - to_gray(mask), 0.0)


def _detect_best(mask: NDArray, base: NDArray, params: DetectionParams) -> NDArray[np.float64]:
    sub = subtract(mask, base)
    smooth = cv2.GaussianBlur(sub, (5, 5), 1.0)
    local_max = cv2.dilate(smooth, np.ones((5, 5), np.uint8))
    peaks = (smooth >= local_max) & (smooth > params.min_peak)
    rows, cols = np.nonzero(peaks)
    h, w = sub.shape
    ok = (rows >= 2) & (rows < h - 2) & (cols >= 2) & (cols < w - 2)
    rows, cols = rows[ok], cols[ok]
    if len(rows) == 0:
        return np.zeros((0, 3))
    # Intensity-weighted centroid over a 5x5 window, background (window minimum) removed.
    off = np.arange(-2, 3)
    win = sub[rows[:, None, None] + off[None, :, None], cols[:, None, None] + off[None, None, :]]
    win = win - win.min(axis=(1, 2), keepdims=True)
    total = win.sum(axis=(1, 2))
    dr = (win.sum(axis=2) * off).sum(axis=1) / total
    dc = (win.sum(axis=1) * off).sum(axis=1) / total
    return np.column_stack([rows + dr, cols + dc, smooth[rows, cols]]).astype(np.float64)


def detect_dots(
    mask: NDArray,
    base: NDArray,
    method: DetectionMethod = "best",
    params: DetectionParams | None = None,
) -> NDArray[np.float64]:
    """Dot centres (N, 3) as (row_px, col_px, strength) in one camera's mask/base pair."""
    p = params or DetectionParams()
    if method == "best":
        return _detect_best(mask, base, p)
    raise ValueError(f"unknown detection method {method!r} (known: thesis, best)")
