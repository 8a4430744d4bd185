"""The learned-shape joint fit (omnid.core.spotshape) on synthetic spots with known centres."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core import spotshape


def _flat_tops(rng: np.random.Generator, clip: float | None):
    """A 200x200 image of elongated flat-topped spots (profile exp(−(q²/2)^1.6), radial-like
    orientation per spot) 9–10 px apart, read noise 2; their true centres."""
    g = np.arange(15, 190, 11.0)
    rr, cc = np.meshgrid(g, g, indexing="ij")
    truth = np.column_stack([rr.ravel(), cc.ravel()]) + rng.uniform(-0.5, 0.5, (rr.size, 2))
    y, x = np.mgrid[0:200, 0:200].astype(np.float64)
    img = np.zeros((200, 200))
    for (r, c), ang in zip(truth, rng.uniform(0, np.pi, len(truth)), strict=True):
        dr, dc = y - r, x - c
        u = np.cos(ang) * dr + np.sin(ang) * dc
        v = -np.sin(ang) * dr + np.cos(ang) * dc
        q2 = (u / 2.4) ** 2 + (v / 1.8) ** 2
        img += 180.0 * np.exp(-((0.5 * q2) ** 1.6))
    img += rng.normal(0.0, 2.0, img.shape)
    valid = None
    if clip is not None:
        valid = img < clip
        img = np.minimum(img, clip)
    return img.astype(np.float32), valid, truth


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_flat_elongated_spots_centred_with_the_learned_profile(seed):
    rng = np.random.default_rng(seed)
    img, _, truth = _flat_tops(rng, None)
    start = truth + rng.uniform(-0.4, 0.4, truth.shape)
    r, c, _, table, _ = spotshape.fit_dots(
        img, None, start[:, 0], start[:, 1], np.full(len(truth), 150.0), 2.0, 2.0, 5
    )
    err = np.hypot(r - truth[:, 0], c - truth[:, 1])
    assert np.sqrt((err**2).mean()) <= 0.05  # measured 0.01–0.02
    # The learned profile is flatter than a Gaussian at the top (a plateau) and falls to ~0.
    assert table is not None
    assert table[4] > np.exp(-0.5) + 0.05  # q = 1
    assert abs(table[-1]) < 0.05


def test_clipped_pixels_are_left_out_not_fitted():
    rng = np.random.default_rng(5)
    img, valid, truth = _flat_tops(rng, 120.0)
    start = truth + rng.uniform(-0.4, 0.4, truth.shape)
    args = (np.full(len(truth), 150.0), 2.0, 2.0, 5)
    r, c, *_ = spotshape.fit_dots(img, valid, start[:, 0], start[:, 1], *args)
    rms = np.sqrt(((r - truth[:, 0]) ** 2 + (c - truth[:, 1]) ** 2).mean())
    assert rms <= 0.08  # measured ≈ 0.02
