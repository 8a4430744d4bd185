"""The laser dot-matrix projector (thesis 4.4, 6.3.1.3; SPEC §2).

:class:`LaserModel` is what omnid knows of the laser: what calibration learned from the
installer's captures (the floor dot of every beam and the source they all leave from), with no
assumed pattern law or source position. Each beam images as a straight track in each camera,
which makes the laser a third view for matching (:mod:`omnid.core.matching`).
(The old idealisation, a regular slope lattice from the frame origin, lives on only in the
simulator, as :func:`omnid.sim.laser.ideal_lattice`, for comparison.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

# --------------------------------------------------------------------------------------------
# The laser as calibration learns it: one source, one floor point per beam (SPEC §2)
# --------------------------------------------------------------------------------------------

#: Where the installer's laser is assumed to be before the captures say otherwise, mm: the
#: baseline's midpoint in the mirror plane (SPEC §2: "roughly" there), and how far off it may be
#: (1 σ per axis: a few cm sideways, up to ±150 mm above or below the mirror plane).
SOURCE_PRIOR_MM = (0.0, 0.0, 0.0)
SOURCE_PRIOR_SIGMA_MM = (40.0, 40.0, 100.0)


#: A beam is doubled (:meth:`LaserModel.doubled`) when another beam's floor dot lies nearer than
#: this share of the pattern's typical spacing: on 12 random rigs the twins calibration learned
#: lie 0.21–0.48 of it apart, the nearest regular neighbours at 0.64 or more (the default and
#: the dense laser: 0.69–0.72).
DOUBLED_SHARE = 0.5


@dataclass(frozen=True)
class LaserModel:
    """The laser as the installer's captures show it: a source O and the floor dot of each beam.

    Beam k is the line through ``source_mm`` and ``floor_mm[k]`` (its dot on the floor, depth
    H below the mirrors). Write a beam point at depth Z as Z·(s + c/Z, 1) with the beam's slope
    s = (P_xy − O_xy)/(H − O_Z) and c = O_xy − O_Z·s (where the beam crosses the mirror plane):
    with u = 1/Z its image in camera i (ideal offsets, SPEC §2) is *affine in u*::

        x_i = −F_i·(s_X + c_X·u),   y_i = F_i·(s_Y + (c_Y − Y_i)·u)

    — a straight track through the floor dot's image (u = 1/H) and the laser's epipole
    e_i = F_i·(−O_X, O_Y − Y_i)/O_Z (u = 1/O_Z). When the captures could not fix O,
    ``source_known`` is False and ``source_mm`` is the prior (:data:`SOURCE_PRIOR_MM`) with
    ``source_sigma_mm`` its spread: tracks then are uncertain away from the floor.

    Attributes
    ----------
    floor_depth_mm
        H, mm.
    floor_mm
        (K, 3) floor dot P_k of each beam, mm (Z = H).
    floor_sigma_mm
        (K,) 1-σ error of each floor dot across the beam (per axis), mm.
    source_mm, source_sigma_mm
        The source O and its 1-σ error per axis, mm.
    source_known
        Whether captures off the floor fixed O (else it is the prior).
    """

    floor_depth_mm: float
    floor_mm: NDArray[np.float64]
    floor_sigma_mm: NDArray[np.float64]
    source_mm: tuple[float, float, float] = SOURCE_PRIOR_MM
    source_sigma_mm: tuple[float, float, float] = SOURCE_PRIOR_SIGMA_MM
    source_known: bool = False

    def __post_init__(self) -> None:
        p = np.asarray(self.floor_mm, dtype=np.float64).reshape(-1, 3)
        s = np.broadcast_to(np.asarray(self.floor_sigma_mm, dtype=np.float64), (len(p),)).copy()
        if not (np.isfinite(p).all() and np.isfinite(s).all() and (s >= 0).all()):
            raise ValueError("LaserModel: floor points and their sigmas must be finite")
        o = tuple(float(v) for v in self.source_mm)
        so = tuple(float(v) for v in self.source_sigma_mm)
        if len(o) != 3 or len(so) != 3 or not all(map(math.isfinite, o + so)):
            raise ValueError("LaserModel: source_mm and source_sigma_mm need 3 finite numbers")
        if not o[2] < self.floor_depth_mm - 1.0:
            raise ValueError("LaserModel: the source must lie above the floor")
        p.setflags(write=False)
        s.setflags(write=False)
        object.__setattr__(self, "floor_mm", p)
        object.__setattr__(self, "floor_sigma_mm", s)
        object.__setattr__(self, "source_mm", o)
        object.__setattr__(self, "source_sigma_mm", so)

    def __len__(self) -> int:
        return len(self.floor_mm)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LaserModel):
            return NotImplemented
        return (
            self.floor_depth_mm == other.floor_depth_mm
            and np.array_equal(self.floor_mm, other.floor_mm)
            and np.array_equal(self.floor_sigma_mm, other.floor_sigma_mm)
            and self.source_mm == other.source_mm
            and self.source_sigma_mm == other.source_sigma_mm
            and self.source_known == other.source_known
        )

    __hash__ = None  # type: ignore[assignment]

    def slopes(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(s, c): (K, 2) slope (X/Z, Y/Z per mm of depth) and (K, 2) mirror-plane crossing, mm."""
        o = np.asarray(self.source_mm)
        s = (self.floor_mm[:, :2] - o[None, :2]) / (self.floor_depth_mm - o[2])
        c = o[None, :2] - o[2] * s
        return s, c

    def directions(self) -> NDArray[np.float64]:
        """(K, 3) unit direction of each beam (pointing down)."""
        d = self.floor_mm - np.asarray(self.source_mm)[None, :]
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def point_at(self, beam: NDArray[np.intp], inv_depth: NDArray[np.float64]) -> NDArray:
        """(N, 3) points of beams ``beam`` at inverse depths ``inv_depth`` (1/mm), mm."""
        s, c = self.slopes()
        z = 1.0 / inv_depth
        return np.column_stack([s[beam] * z[:, None] + c[beam], z])

    def doubled(self, share: float = DOUBLED_SHARE) -> NDArray[np.bool_]:
        """(K,) which beams have a twin: another beam whose floor dot lies nearer than
        ``share`` of the pattern's typical spacing (the median of every beam's distance to its
        nearest other beam, on the floor, mm). A grating's beams are spaced by its pitch; a
        doubled beam (a flaw of the grating, or two sources) is a pair far closer, which the
        detector sees as one maximum wherever its spots are larger than half their distance."""
        p = self.floor_mm[:, :2]
        k = len(p)
        if k < 3:
            return np.zeros(k, dtype=bool)
        nearest = np.empty(k)
        for a in range(0, k, 256):  # (256 x K distances at a time)
            d = np.hypot(
                p[a : a + 256, None, 0] - p[None, :, 0], p[a : a + 256, None, 1] - p[None, :, 1]
            )
            d[np.arange(len(d)), np.arange(a, a + len(d))] = np.inf  # (not its own neighbour)
            nearest[a : a + 256] = d.min(axis=1)
        return np.asarray(nearest < share * float(np.median(nearest)), dtype=bool)

    def with_source(
        self, source_mm: tuple[float, float, float], sigma_mm: tuple[float, float, float]
    ) -> LaserModel:
        """The same beams from a source found by calibration."""
        return LaserModel(
            self.floor_depth_mm, self.floor_mm, self.floor_sigma_mm, source_mm, sigma_mm, True
        )
