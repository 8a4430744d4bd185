"""The laser model calibration learns (omnid.core.laser): which beams are doubled."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core.laser import DOUBLED_SHARE, LaserModel

H = 1100.0


def _model(xy: np.ndarray) -> LaserModel:
    floor = np.column_stack([xy, np.full(len(xy), H)])
    return LaserModel(H, floor, np.full(len(xy), 0.5))


@pytest.mark.parametrize("seed", range(5))
def test_a_beam_doubled_by_a_close_twin_is_found_and_no_regular_neighbour(seed) -> None:
    """A jittered grid (pitch 40 mm, 8 % jitter) with a few beams repeated a fifth of a pitch
    away: exactly the twins are doubled, whatever the grid's rotation and the twins' place."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(-8, 9), np.arange(2, 14))
    grid = 40.0 * np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    grid += rng.normal(0.0, 0.08 * 40.0, grid.shape)
    a = rng.uniform(0, np.pi)
    grid = grid @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    k = rng.choice(len(grid), 4, replace=False)
    ang = rng.uniform(0, 2 * np.pi, 4)
    twins = grid[k] + 8.0 * np.column_stack([np.cos(ang), np.sin(ang)])
    m = _model(np.vstack([grid, twins]))
    expected = np.zeros(len(grid) + 4, dtype=bool)
    expected[k] = True
    expected[len(grid) :] = True
    assert np.array_equal(m.doubled(), expected)
    assert not _model(grid).doubled().any()


def test_doubled_is_relative_to_the_pattern_s_own_spacing() -> None:
    """A dense grid's regular neighbours are no twins; a pair at the share's edge is."""
    g = np.column_stack([np.arange(50) * 5.0, np.zeros(50)])  # 5 mm apart
    assert not _model(g).doubled().any()
    near = np.vstack([g, g[10] + [0.0, 0.9 * DOUBLED_SHARE * 5.0]])
    assert _model(near).doubled().sum() == 2
    far = np.vstack([g, g[10] + [0.0, 1.1 * DOUBLED_SHARE * 5.0]])
    assert not _model(far).doubled().any()
    assert not _model(g[:2]).doubled().any()  # too few beams to have a spacing
