"""PLY export parses back; the top-down picture shows the map where it should."""

from __future__ import annotations

import cv2
import numpy as np

from omnid.core.export import CELL_BGR, parse_ply, ply_bytes, render_topdown
from omnid.core.freespace import FreeSpaceMap
from omnid.core.occupancy import CellState
from omnid.core.types import PointClass, PointCloud


def _cloud(rng: np.random.Generator, n: int = 40) -> PointCloud:
    xyz = rng.uniform([300, -800, 600], [2000, 800, 1300], (n, 3))
    classes = rng.integers(0, 3, n).astype(np.uint8)
    return PointCloud(xyz, np.zeros((n, 3, 3)), np.zeros((n, 4)), classes, 1100.0)


def test_ply_ascii_and_binary_parse_back(rng):
    cloud = _cloud(rng)
    for binary in (False, True):
        data = ply_bytes(cloud, binary=binary)
        assert data.startswith(b"ply\n")
        back = parse_ply(data)
        assert len(back) == len(cloud)
        np.testing.assert_allclose(back["x"], cloud.xyz[:, 0], atol=2e-3)
        np.testing.assert_allclose(back["z"], cloud.xyz[:, 2], atol=2e-3)
        np.testing.assert_array_equal(back["class"], cloud.classes)
        floor = cloud.classes == PointClass.FLOOR
        assert np.all(back["green"][floor] > back["red"][floor])
    empty = parse_ply(ply_bytes(PointCloud()))
    assert len(empty) == 0


def test_topdown_picture_colours_cells_and_is_pure(tmp_path):
    m = FreeSpaceMap()
    xyz = np.array([[1000.0, -500.0, 800.0]])  # robot (1000, 500): ahead and to the left
    cloud = PointCloud(
        xyz, np.zeros((1, 3, 3)), np.zeros((1, 4)), np.array([PointClass.OBSTACLE], np.uint8)
    )
    m.update(cloud, 0.0)
    m.update(cloud, 0.0)  # an obstacle is believed when two captures in a row show it
    cell_px = 4
    img = render_topdown(m, cell_px=cell_px)
    g = m.grid.settings
    nx, ny = m.grid.states.shape
    assert img.shape == (nx * cell_px, ny * cell_px, 3) and img.dtype == np.uint8
    # Forward is up, the chair's left is on the left.
    row = int((g.x_max_mm - 1025.0) / g.resolution_mm * cell_px)
    col = int((g.y_max_mm - 525.0) / g.resolution_mm * cell_px)
    assert tuple(img[row, col]) == CELL_BGR[CellState.OBSTACLE]
    assert tuple(img[5, img.shape[1] - 5]) == CELL_BGR[CellState.UNKNOWN]
    # Drawing the cloud and a path changes pixels but writes nothing.
    over = render_topdown(m, cloud, path_xy=[[0, 0], [1000, 0]])
    assert np.any(over != img)
    assert list(tmp_path.iterdir()) == []
    m.render_png(tmp_path / "map.png", cloud)
    back = cv2.imread(str(tmp_path / "map.png"))
    assert back is not None and back.shape == img.shape
