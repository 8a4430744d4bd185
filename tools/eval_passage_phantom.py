"""Closed-loop phantom check: the `best` matcher on captures of the scenario's partition.

The scenario of the former CI test ``test_passes_a_passage_wider_than_the_chair`` (a partition
with a centred 1300 mm gap; since stop 29 the demo story's wide passage and the 900 mm doorway
stand for it in CI) stopped the chair for nothing when floor rows seen through the gap were
paired two lattice steps off. This tool puts the partition where that test first had it,
x = 1800 mm across a 4 m room (the test later moved it to 1100 mm), renders it with the
simulator's installed rig (misaligned, calibrated on its floor capture) at poses along the
chair's path and counts, over all frames, wrong pairs (not the two images of one dot) and matched points
more than 50 mm off their true position, nearer (phantom obstacles) or deeper (phantom
drop-offs).

    python tools/eval_passage_phantom.py [--step-mm 25] [--seeds 3]
"""

from __future__ import annotations

import argparse

import numpy as np

from omnid.core.detect import detect_dots
from omnid.core.matching import match_dots
from omnid.core.triangulate import triangulate
from omnid.sim.course import walls
from omnid.sim.installation import calibrate_installed
from omnid.sim.laser import LaserProjector
from omnid.sim.render import RenderOptions, render_camera_pair
from omnid.sim.rigs import misaligned_rig
from omnid.sim.world import Box, RigMount, World, cast_laser

H = 1100.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step-mm", type=float, default=25.0)
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    rig = misaligned_rig(H)
    pat = LaserProjector()  # the simulator's physical laser
    calib = calibrate_installed(rig, pat, seed=0)
    world = World(
        boxes=(
            Box(1800.0, 1900.0, -2000.0, -650.0, 1000.0),
            Box(1800.0, 1900.0, 650.0, 2000.0, 1000.0),
            *walls(-1000.0, 5000.0, -2000.0, 2000.0),
        )
    )
    frames = bad_frames = visible = matched = wrong = off = off_under = 0
    worst = (0.0, 0)
    for x in np.arange(0.0, 1400.0, args.step_mm):
        for seed in range(args.seeds):
            hits = cast_laser(world, (float(x), 0.0, 0.0), RigMount(), pat, rig)
            rng = np.random.default_rng(seed)
            ims = []
            for cam, vis in ((rig.cam1, hits.visible1), (rig.cam2, hits.visible2)):
                ims.extend(
                    render_camera_pair(cam, cam.project(hits.xyz[vis]), RenderOptions(), rng)
                )
            px = match_dots(calib, detect_dots(ims[0], ims[1]), detect_dots(ims[2], ims[3]))
            xyz, _ = triangulate(calib.rig, px, "best", 0.1)
            t1, t2 = rig.cam1.project(hits.xyz), rig.cam2.project(hits.xyz)
            n1 = np.hypot(px[:, None, 0] - t1[None, :, 0], px[:, None, 1] - t1[None, :, 1]) < 1.5
            n2 = np.hypot(px[:, None, 2] - t2[None, :, 0], px[:, None, 3] - t2[None, :, 1]) < 1.5
            n1[:, ~hits.visible1] = False
            n2[:, ~hits.visible2] = False
            ok = (n1 & n2).any(axis=1)
            dist = np.linalg.norm(xyz[:, None] - hits.xyz[None], axis=2)
            err = np.where(n1, dist, np.inf).min(axis=1)
            true_z = hits.xyz[np.where(n1, dist, np.inf).argmin(axis=1), 2]
            w = int((~ok).sum())
            frames += 1
            bad_frames += w > 0
            visible += int(hits.visible.sum())
            matched += int(ok.sum())
            wrong += w
            off += int((err > 50.0).sum())
            off_under += int(((err > 50.0) & (xyz[:, 2] > true_z)).sum())
            worst = max(worst, (w / max(1, int(hits.visible.sum())), int(x)))
    print(f"frames {frames} (x 0..1400 mm every {args.step_mm:g} mm, {args.seeds} seeds)")
    print(f"visible {visible}, matched right {matched} ({100 * matched / visible:.1f} %)")
    print(f"wrong {wrong} ({100 * wrong / visible:.2f} %) in {bad_frames} frames")
    print(
        f"off > 50 mm {off} ({off - off_under} nearer, {off_under} deeper than the dot); "
        f"worst frame {100 * worst[0]:.1f} % wrong at x = {worst[1]} mm"
    )


if __name__ == "__main__":
    main()
