"""Motion between camera frames: the wheels' travel at any instant, and a mask frame moved to the
pose of a base frame.

The laser sits on the chair, so on a flat floor its dots stay put in the image while the chair
drives; what moves is the scene — the floor's texture — which the mask (laser off) must cancel
in the base (laser on) (thesis 5.1 subtracts frames taken standing still). Taken while driving,
the mask is therefore first moved to the base frame's pose:

* :func:`wheel_travel_mm` — how far each wheel had travelled at a given time. The control unit
  reports whole clocks (31.4 mm) about every 20 ms; each clock edge is placed between the two
  replies that saw it and the travel is interpolated linearly between edges (extrapolated after
  the last one until the next edge would have been due), so a frame 40 ms after a reply is not
  placed 31 mm wrong;
* :func:`relative_motion` — the exact-arc motion (eq. 3.14, :func:`arc_displacement`) between
  two times, in the robot frame at the first;
* :func:`floor_motion_affine` — the image motion of the floor under that chair motion: for a
  plane at depth Z the mirror camera maps the rig frame by a similarity (SPEC §2:
  x = −(f/K)/Z·X, y = (f/K)/Z·(Y − Y_i), then the camera's rotation), so a rigid motion of the
  floor is an affine map of the image;
* :func:`compensated_mask` — the mask(s) warped by those maps (bilinear), the brighter of
  the masks before and after the base taken pixel by pixel (see there why).

Only the floor (and anything at the floor's depth) is compensated exactly; an object nearer the
mirrors moves faster in the image (parallax) and leaves a residue proportional to its height and
the travel, which is why the masks are kept young.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from omnid.core.geometry import MirrorCamera
from omnid.core.kinematics import arc_displacement

Motion = tuple[float, float, float]  # dx mm, dy mm, dθ rad (robot frame at the earlier time)

#: An edge-to-edge interval longer than this is a standstill that ended: the wheel is taken to
#: have started moving at most this long before the edge that ended it (s).
MAX_EDGE_GAP_S = 0.5


def _edge_knots(
    times_s: NDArray[np.float64], counts: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Knots (time, count) of one wheel: each edge between replies i−1 and i placed evenly in
    (t_{i−1}, t_i]; a long standstill before an edge becomes a knot MAX_EDGE_GAP_S earlier."""
    kt: list[float] = [float(times_s[0])]
    kc: list[float] = [float(counts[0])]
    for i in range(1, len(times_s)):
        n = counts[i] - counts[i - 1]
        if n == 0:
            continue
        t0, t1 = float(times_s[i - 1]), float(times_s[i])
        steps = int(abs(n))
        sign = 1.0 if n > 0 else -1.0
        for k in range(1, steps + 1):
            t = t0 + (t1 - t0) * (k - 0.5) / steps
            if t - kt[-1] > MAX_EDGE_GAP_S:
                kt.append(t - MAX_EDGE_GAP_S)
                kc.append(kc[-1])
            kt.append(t)
            kc.append(float(counts[i - 1]) + sign * k)
    return np.asarray(kt), np.asarray(kc)


def wheel_travel_mm(
    t_s: ArrayLike,
    times_s: ArrayLike,
    counts: ArrayLike,
    mm_per_clock: float,
) -> NDArray[np.float64]:
    """Travel (mm, relative to the first sample) of one wheel at times ``t_s``.

    ``times_s``/``counts``: the wheel's clock counter (unwrapped, signed) as the control unit
    reported it, in time order. Between clock edges the travel is linear; after the last edge it
    goes on at the last edge-to-edge speed until the next edge would have been due, then stays
    (the wheel slowed: it is somewhere short of the next clock). Before the first sample it is 0.
    """
    ts = np.asarray(times_s, dtype=np.float64)
    cs = np.asarray(counts, dtype=np.float64)
    q = np.asarray(t_s, dtype=np.float64)
    if len(ts) == 0:
        return np.zeros(q.shape)
    kt, kc = _edge_knots(ts, cs)
    out = np.interp(q, kt, kc)
    if len(kt) >= 2 and kc[-1] != kc[-2]:
        dt = kt[-1] - kt[-2]
        speed = (kc[-1] - kc[-2]) / dt  # clocks per s (signed)
        after = q > kt[-1]
        lead = np.clip((q[after] - kt[-1]) * speed, -1.0, 1.0)
        out[after] = kc[-1] + lead * (1.0 - 1e-6)
    return (out - cs[0]) * mm_per_clock


def relative_motion(
    t0_s: float,
    t1_s: float,
    samples: ArrayLike,
    mm_per_clock: float,
    track_mm: float,
) -> Motion:
    """The chair's motion from ``t0_s`` to ``t1_s`` as (dx mm, dy mm, dθ rad) in the robot
    frame at ``t0_s`` (x forward, y left, θ counter-clockwise), from ``samples`` (N, 3) rows
    (t_s, left_clocks, right_clocks) of the control unit's replies; zeros without samples."""
    s = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
    if len(s) == 0:
        return 0.0, 0.0, 0.0
    q = np.array([t0_s, t1_s])
    left = wheel_travel_mm(q, s[:, 0], s[:, 1], mm_per_clock)
    right = wheel_travel_mm(q, s[:, 0], s[:, 2], mm_per_clock)
    dx, dy, dth = arc_displacement(left[1] - left[0], right[1] - right[0], track_mm)
    return float(dx), float(dy), float(dth)


def moved_rig_points(
    xyz_rig_mm: ArrayLike, motion: Motion, rig_x_offset_mm: float
) -> NDArray[np.float64]:
    """World-fixed points (N, 3) in the rig frame before ``motion`` → in the rig frame after it.

    Rig → robot: x = X + offset, y = −Y; a world-fixed point has new robot coordinates
    R(−dθ)·(p − d) (as ``omnid.daemon.core.transform_cloud``); Z is unchanged.
    """
    p = np.asarray(xyz_rig_mm, dtype=np.float64).reshape(-1, 3)
    dx, dy, dth = motion
    x = p[:, 0] + rig_x_offset_mm - dx
    y = -p[:, 1] - dy
    c, s = math.cos(dth), math.sin(dth)
    xn, yn = c * x + s * y, -s * x + c * y
    return np.column_stack([xn - rig_x_offset_mm, -yn, p[:, 2]])


def floor_motion_affine(
    cam: MirrorCamera, motion: Motion, rig_x_offset_mm: float, depth_mm: float
) -> NDArray[np.float64]:
    """The (2, 3) affine map of image positions (col, row — OpenCV's x, y) of points at depth
    ``depth_mm`` in a frame taken before ``motion`` to their positions in a frame taken after."""
    h = float(depth_mm)
    ref = np.array([[0.0, 0.0, h], [600.0, 0.0, h], [0.0, 600.0, h]])
    before = cam.project(ref)[:, ::-1].astype(np.float32)  # (col, row)
    after = cam.project(moved_rig_points(ref, motion, rig_x_offset_mm))[:, ::-1]
    return np.asarray(cv2.getAffineTransform(before, after.astype(np.float32)), dtype=np.float64)


def disk_mask(cam: MirrorCamera, margin_px: float = 2.0) -> NDArray[np.uint8]:
    """255 inside the mirror's disk (shrunk by ``margin_px``), 0 outside — the part of a frame
    that sees the scene (the housing around it is fixed in the image)."""
    rows, cols = cam.image_shape
    dr = np.arange(rows, dtype=np.float32)[:, None] - np.float32(cam.center_row_px)
    dc = np.arange(cols, dtype=np.float32)[None, :] - np.float32(cam.center_col_px)
    inside = (dr * dr + dc * dc) <= np.float32(max(cam.disk_radius_px - margin_px, 0.0) ** 2)
    return np.where(inside, np.uint8(255), np.uint8(0)).astype(np.uint8)


def warp_image(
    image: NDArray[np.uint8],
    affine: NDArray[np.float64],
    disk: NDArray[np.uint8] | None = None,
) -> NDArray[np.uint8]:
    """``image`` moved by ``affine`` (bilinear). With ``disk`` (:func:`disk_mask`) only the
    scene inside the mirror disk moves: a pixel whose source lies outside the disk (the dark
    housing, or floor the earlier frame did not see) keeps its own value, so the disk's edge
    — fixed to the camera — still cancels."""
    rows, cols = image.shape[:2]
    flags = cv2.INTER_LINEAR
    out = cv2.warpAffine(image, affine, (cols, rows), flags=flags, borderMode=cv2.BORDER_REPLICATE)
    if disk is not None:
        src_in = cv2.warpAffine(disk, affine, (cols, rows), flags=flags, borderValue=0)
        out = np.where((src_in == 255) & (disk == 255), out, image)
    return np.asarray(out, dtype=np.uint8)


def compensated_mask(
    masks: Sequence[NDArray[np.uint8]],
    affines: Sequence[NDArray[np.float64] | None],
    disk: NDArray[np.uint8] | None = None,
) -> NDArray[np.uint8]:
    """The mask a base frame is subtracted against: each mask warped by its affine map (None:
    as taken; ``disk``: see :func:`warp_image`), then the pixelwise **maximum** of them.

    Why the maximum: the floor's motion is compensated exactly, but an edge off the floor (a
    box's silhouette, a wall) moves with parallax; in masks taken before and after the base it
    lies on either side of where the base shows it, so the brighter of the two covers it and
    the subtraction leaves no bright residue for the detector to take for a dot (an average
    would leave two half-bright ones). A laser dot is in neither mask and survives. A single
    moved mask is grey-dilated by one pixel instead (its residue lies on one side only). The
    price: the subtracted image is biased low by the local texture gradient, a few gray levels
    against dots of ~150."""
    if not masks:
        raise ValueError("compensated_mask: no mask")
    warped = [
        m if a is None else warp_image(m, a, disk) for m, a in zip(masks, affines, strict=True)
    ]
    if len(warped) == 1:
        if affines[0] is None:
            return warped[0]
        return np.asarray(cv2.dilate(warped[0], np.ones((3, 3), np.uint8)), dtype=np.uint8)
    out = warped[0]
    for m in warped[1:]:
        out = np.maximum(out, m)
    return np.asarray(out, dtype=np.uint8)
