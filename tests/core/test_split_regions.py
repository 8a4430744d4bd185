"""Where perception splits blends (pipeline.split_regions): along the doubled beams' image
tracks at every depth the matcher reads, wherever the calibration's source may lie."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core.matching import MatchSettings
from omnid.core.pipeline import split_regions
from omnid.experiments import rigs as ev


def test_the_region_covers_the_doubled_beams_at_every_depth_the_matcher_reads(
    random_installations,
) -> None:
    """Near depths too: a wall 400 mm ahead shows its dots 150–250 mm below the mirrors."""
    near = MatchSettings().near_depth_mm
    missed = seen = 0
    for _case, calib in random_installations:
        reg = split_regions(calib)  # type: ignore[arg-type]
        if reg is None:
            continue
        las, rig = calib.laser, calib.rig  # type: ignore[attr-defined]
        beams = np.flatnonzero(las.doubled())
        for z in (near + 50.0, 200.0, 600.0, rig.floor_depth_mm + 300.0):
            pts = las.point_at(beams, np.full(len(beams), 1.0 / z))
            for cam, m in ((rig.cam1, reg[0]), (rig.cam2, reg[1])):
                rc = cam.project(pts)
                q = np.rint(rc[cam.in_disk(rc, 2.0)]).astype(int)
                seen += len(q)
                missed += int((~m[q[:, 0], q[:, 1]]).sum())
    assert seen > 50
    assert missed == 0


@pytest.mark.parametrize("floor_only", [False, True])
def test_the_true_twins_off_the_floor_lie_in_the_region_even_with_the_source_unknown(
    floor_only,
) -> None:
    """With the floor alone the source is the prior: the tracks of its 2 σ spread are drawn.
    Counted: the twins the model learned (their floor dot in the region), 400–800 mm deep."""
    seen = missed = 0
    for r in (0, 1, 2, 6, 7):
        case = ev.rig_case(r, seed=0)
        calib = ev.calibrate_case(case, 0, floor_only=floor_only)
        reg = split_regions(calib)
        if reg is None:
            continue
        b = np.flatnonzero(case.laser.rays().twin >= 0)
        floor = case.laser.on_plane(case.rig.floor_depth_mm)[b]
        for z in (400.0, 600.0, 800.0):
            xyz = case.laser.on_plane(z)[b]
            for cam, m in ((case.rig.cam1, reg[0]), (case.rig.cam2, reg[1])):
                f = cam.project(floor)
                learned = cam.in_disk(f, 3.0)
                fq = np.rint(f[learned]).astype(int)
                learned[learned] = m[fq[:, 0], fq[:, 1]]
                rc = cam.project(xyz)
                q = np.rint(rc[cam.in_disk(rc, 3.0) & learned]).astype(int)
                seen += len(q)
                missed += int((~m[q[:, 0], q[:, 1]]).sum())
    assert seen > 20
    assert missed <= 0.05 * seen
