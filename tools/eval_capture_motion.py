"""Motion during capture: what the chair's travel between the mask and the base frame costs.

Run from the repository root:  python tools/eval_capture_motion.py [--gap-s 0.08]

The laser sits on the chair, so on a flat floor the dots do not move with the chair; what moves
is the floor's own texture, which the mask (laser off) must cancel in the base (laser on). This
tool renders, for each chair speed, a base capture at the pose of the base frame and a mask
whose floor texture is shifted by ``speed · gap`` (the mask was taken that much earlier), on
two floors: a smooth world-anchored texture ("carpet") and a tiled floor (300 mm tiles, 10 mm
grout ``--grout-gray`` darker, area-sampled: sharp edges, the worst common case). Every dot that perception returns
is on the flat floor, so anything classified obstacle or drop-off is false. Reported per speed:
dots found, false obstacle/drop-off points, RMS height error of the floor points, and the same
at speed 0 as the reference of the run.
"""

from __future__ import annotations

import argparse

import numpy as np

FLOOR_MM = 1100.0


def floor_scene(
    cam, shift_mm: float, tiled: bool, rng_seed: int, grout_gray: float = 35.0
) -> np.ndarray:
    """Gray scene of the floor seen by ``cam`` with the world texture moved back by shift_mm."""
    rows, cols = cam.image_shape
    r = np.arange(rows, dtype=np.float64)[:, None] - cam.center_row_px
    c = np.arange(cols, dtype=np.float64)[None, :] - cam.center_col_px
    s = cam.f_over_k_px / FLOOR_MM  # px per mm on the floor (SPEC §2)
    x_mm = -r / s + shift_mm  # floor point under each pixel, in the world
    y_mm = c / s + cam.y_mm
    rng = np.random.default_rng(rng_seed)
    kx, ky = rng.uniform(0.004, 0.012, 2)
    smooth = 0.5 * np.sin(kx * x_mm + 1.3) * np.cos(ky * y_mm + 0.4)  # smooth world texture
    img = 70.0 + 25.0 * smooth
    if tiled:
        # grout 10 mm wide, area-sampled over the pixel's footprint (1/s mm): a binary line
        # would jump by whole pixels and make the result depend on aliasing, not on motion
        px_mm = 1.0 / s

        def cover(d_mm: np.ndarray) -> np.ndarray:
            return np.clip((5.0 - d_mm) / px_mm + 0.5, 0.0, 1.0)

        gx = cover(np.abs(((x_mm + 150.0) % 300.0) - 150.0))
        gy = cover(np.abs(((y_mm + 150.0) % 300.0) - 150.0))
        img = img - grout_gray * np.maximum(gx, gy)
    disk = r * r + c * c <= cam.disk_radius_px**2
    return np.where(disk, img, 3.0)


def capture_at(rig, pattern, shift_mm: float, tiled: bool, seed: int, grout_gray: float = 35.0):
    from omnid.core.types import StereoCapture
    from omnid.sim.render import draw_spots

    rng = np.random.default_rng(seed)
    dots = pattern.on_plane(FLOOR_MM)
    out = []
    for cam in (rig.cam1, rig.cam2):
        pos = cam.project(dots)
        pos = pos[cam.in_disk(pos)]
        sig = 1.3 * (1 + 0.15 * rng.uniform(-1, 1, len(pos)))
        amp = 150.0 * (1 + 0.25 * rng.uniform(-1, 1, len(pos)))
        laser = draw_spots(cam.image_shape, pos, sig, amp)
        base = floor_scene(cam, 0.0, tiled, 7, grout_gray) + laser
        mask = floor_scene(cam, -shift_mm, tiled, 7, grout_gray)
        noise = 2.0
        out.append(np.clip(mask + rng.normal(0, noise, mask.shape), 0, 255).astype(np.uint8).copy())
        out.append(np.clip(base + rng.normal(0, noise, base.shape), 0, 255).astype(np.uint8).copy())
    return StereoCapture(out[0], out[1], out[2], out[3])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--gap-s", type=float, default=0.08, help="mask → base interval, s")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--grout-gray", type=float, default=35.0, help="grout darker by, gray")
    a = ap.parse_args()
    from omnid.core.geometry import StereoRig
    from omnid.core.pipeline import perceive
    from omnid.core.types import PointClass
    from omnid.sim.installation import calibrate_installed
    from omnid.sim.laser import LaserProjector

    rig = StereoRig.nominal(floor_depth_mm=FLOOR_MM)
    pattern = LaserProjector()  # the simulator's physical laser
    calib = calibrate_installed(rig, pattern, seed=0)
    mm_per_px = FLOOR_MM / rig.cam1.f_over_k_px
    print(
        f"mask → base gap {a.gap_s * 1e3:.0f} ms; floor {mm_per_px:.1f} mm/px; {a.seeds} seeds; "
        f"grout {a.grout_gray:g} gray darker"
    )
    print("floor   speed mm/s  shift px   dots  false obst/drop   floor h rms mm")
    for tiled in (False, True):
        for v in (0.0, 40.0, 80.0, 120.0, 160.0, 240.0):
            shift = v * a.gap_s
            dots, false, hs = [], [], []
            for seed in range(a.seeds):
                cloud = perceive(
                    capture_at(rig, pattern, shift, tiled, 100 + seed, a.grout_gray), calib
                )
                dots.append(len(cloud))
                cls = cloud.classes
                false.append(int(np.sum(cls != PointClass.FLOOR)))
                fl = cls == PointClass.FLOOR
                hs.extend((FLOOR_MM - cloud.xyz[fl, 2]).tolist())
            h_rms = float(np.sqrt(np.mean(np.square(hs)))) if hs else float("nan")
            print(
                f"{'tiled' if tiled else 'carpet':6s}  {v:9.0f}  {shift / mm_per_px:8.2f}  "
                f"{np.mean(dots):5.0f}  {np.mean(false):15.1f}  {h_rms:14.2f}"
            )


if __name__ == "__main__":
    main()
