"""The vectorised thesis detector (chapter 5) against a loop-by-loop transcription of the text."""

from __future__ import annotations

import numpy as np
import pytest
from thesis_oracle import oracle_detect

from omnid.core.detect import RING_MASKS, DetectionParams, detect_dots
from omnid.core.geometry import MirrorCamera
from omnid.sim.render import RenderOptions, SpotModel, render_camera_pair

SHAPE = (72, 96)  # small, so the slow oracle stays well under a second per image


def _oracle(mask, base, p: DetectionParams) -> np.ndarray:
    found = oracle_detect(
        mask,
        base,
        block_px=p.block_px,
        block_coefficient=p.block_coefficient,
        min_peak_gray=p.min_peak_gray,
        e1=p.ring_e1_gray,
        e2=p.ring_e2_gray,
        e3=p.ring_e3_gray,
        e4=p.e4_gray,
    )
    return np.array(found, dtype=np.float64).reshape(-1, 3)


def _scene(seed: int, options: RenderOptions, n: int = 45):
    rng = np.random.default_rng(seed)
    cam = MirrorCamera(SHAPE[0] / 2, SHAPE[1] / 2, 0.0, 108.3, 0.0, 200.0, SHAPE)
    rc = np.column_stack([rng.uniform(2, SHAPE[0] - 2, n), rng.uniform(2, SHAPE[1] - 2, n)])
    mask, base = render_camera_pair(cam, rc, options, rng)
    return mask, base, rc


def test_ring_membership_matches_the_thesis_counts():
    assert [int(m.sum()) for m in RING_MASKS] == [4, 8, 12, 16]
    assert not (RING_MASKS.sum(axis=0) > 1).any()  # rings are disjoint
    assert RING_MASKS[0][3, 3]  # the brightest pixel (4, 4) 1-based is in the inner ring


CASES = [
    ("clean", 1, RenderOptions(), DetectionParams()),
    ("noise+halo+ghost", 2, RenderOptions.realistic(noise_sigma=4.0), DetectionParams()),
    (
        "strong halos, texture, flicker",
        3,
        RenderOptions.realistic(
            spots=SpotModel.realistic(halo_fraction=0.2), flicker=0.1, background_texture=60.0
        ),
        DetectionParams(),
    ),
    (
        "looser thresholds",
        4,
        RenderOptions.realistic(noise_sigma=6.0, spots=SpotModel.realistic(halo_fraction=0.15)),
        DetectionParams(block_coefficient=0.8, min_peak_gray=5, e4_gray=0.0, ring_e1_gray=0.0),
    ),
    (
        "tight thresholds",
        5,
        RenderOptions.realistic(),
        DetectionParams(block_coefficient=2.5, ring_e3_gray=8.0, e4_gray=15.0),
    ),
]


@pytest.mark.parametrize(("name", "seed", "options", "params"), CASES, ids=[c[0] for c in CASES])
def test_vectorised_equals_direct_transcription(name, seed, options, params):
    mask, base, _ = _scene(seed, options)
    fast = detect_dots(mask, base, "thesis", params)
    slow = _oracle(mask, base, params)
    assert len(slow) > 5, "the scene should hold dots the oracle finds"
    np.testing.assert_array_equal(fast, slow)


def test_plateau_ties_follow_row_major_argmax():
    # Two equal brightest pixels side by side: the scan's argmax picks the first (left) one.
    mask = np.zeros((40, 40), np.uint8)
    base = mask.copy()
    base[15:24, 15:24] = 30
    base[17:22, 17:22] = 80
    base[18:21, 18:21] = 160
    base[19, 19] = base[19, 20] = 250
    p = DetectionParams(block_coefficient=1.0, e4_gray=0.0)
    fast = detect_dots(mask, base, "thesis", p)
    np.testing.assert_array_equal(fast, _oracle(mask, base, p))


def test_finds_rendered_dots_at_integer_centres(rng):
    mask, base, rc = _scene(7, RenderOptions(), n=30)
    found = detect_dots(mask, base, "thesis")
    inner = rc[
        (rc[:, 0] > 6) & (rc[:, 0] < SHAPE[0] - 7) & (rc[:, 1] > 6) & (rc[:, 1] < SHAPE[1] - 7)
    ]
    d = np.hypot(found[:, None, 0] - inner[None, :, 0], found[:, None, 1] - inner[None, :, 1])
    assert np.all(found[:, :2] == np.rint(found[:, :2]))
    # Integer centres: every found dot lies within ~1 px of a true one (pixel rounding + noise).
    assert np.all(d.min(axis=1) <= 1.2)
    # Most isolated dots are found (overlapping random dots may merge or fail the model).
    assert np.mean(d.min(axis=0) <= 1.2) >= 0.6
