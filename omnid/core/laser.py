"""The laser dot-matrix projector (thesis 4.4, 6.3.1.3; SPEC §2).

The laser and its fiber grating device sit midway between the two mirrors, in the mirror plane
(the frame origin), and throw a regular lattice of rays forward and down. A ray is given by its
slopes (X/Z, Y/Z); the dot it makes on a surface at depth Z lies at Z·(X/Z, Y/Z, 1). Because the
source lies on the baseline, a dot's image row does not depend on its depth — only its column
does, like the stereo disparity (which is what makes the lattice ambiguous by one step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class DotPattern:
    """A rectangular lattice of laser rays, given by their slopes (dimensionless).

    Rows of the lattice step forward (X/Z from ``forward_min_slope`` by ``step_slope``); columns
    step across (Y/Z centred on 0). The defaults give 19 x 25 = 475 dots, about 11 px apart in
    the image (f/K = 108.3 px), from 0.30·Z to 2.10·Z ahead of the mirrors.
    """

    rows: int = 19
    cols: int = 25
    step_slope: float = 0.10
    forward_min_slope: float = 0.30

    def __post_init__(self) -> None:
        if self.rows < 1 or self.cols < 1:
            raise ValueError("DotPattern needs at least one row and one column")
        if not (math.isfinite(self.step_slope) and self.step_slope > 0):
            raise ValueError("DotPattern.step_slope must be positive")

    def slopes(self) -> NDArray[np.float64]:
        """Ray slopes (rows·cols, 2) as (X/Z, Y/Z), row-major (forward index, lateral index)."""
        sx = self.forward_min_slope + self.step_slope * np.arange(self.rows)
        sy = self.step_slope * (np.arange(self.cols) - (self.cols - 1) / 2.0)
        gx, gy = np.meshgrid(sx, sy, indexing="ij")
        return np.column_stack([gx.ravel(), gy.ravel()])

    def directions(self) -> NDArray[np.float64]:
        """Unit direction vectors (rows·cols, 3) of the rays from the origin."""
        sl = self.slopes()
        d = np.column_stack([sl, np.ones(len(sl))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def on_plane(self, depth_mm: float) -> NDArray[np.float64]:
        """Dots (N, 3) mm made on a horizontal plane ``depth_mm`` below the mirrors."""
        sl = self.slopes()
        return np.column_stack([sl * depth_mm, np.full(len(sl), float(depth_mm))])
