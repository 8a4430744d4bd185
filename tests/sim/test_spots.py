"""Spot models: every family is centred on the projected dot, conserves light, and its random
draws stay inside their spread; shading follows the étendue of the mirror model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from omnid.core.geometry import MirrorCamera, StereoRig
from omnid.errors import ConfigError, InputError
from omnid.sim.laser import LaserProjector
from omnid.sim.render import (
    SPOT_KINDS,
    RenderOptions,
    SpotModel,
    SpotSpread,
    laser_image,
    random_spots,
    render_camera_pair,
    render_hits,
    surface_shading,
)
from omnid.sim.rigs import misaligned_rig
from omnid.sim.scenes import dropoff, three_boxes
from omnid.sim.world import cast_laser

CAM = StereoRig.nominal().cam1


def spread_dots(n: int, rng: np.random.Generator, cam: MirrorCamera = CAM) -> np.ndarray:
    """``n`` dots on a 40 px grid over the whole disk, each shifted by a random sub-pixel
    offset: far enough apart that each dot's light can be summed on its own."""
    g = np.arange(-200, 201, 40, dtype=float)
    rr, cc = np.meshgrid(g, g, indexing="ij")
    centre = np.array([cam.center_row_px, cam.center_col_px])
    pts = np.column_stack([rr.ravel(), cc.ravel()]) + centre
    pts = pts[cam.in_disk(pts, 25.0)][:n]
    return pts + rng.uniform(-0.5, 0.5, pts.shape)


def centroids(img: np.ndarray, pts: np.ndarray, half: int = 18) -> np.ndarray:
    """Centroid of ``img`` in the (2·half + 1)² window around each point (row, col)."""
    out = []
    for r, c in np.rint(pts).astype(int):
        win = img[r - half : r + half + 1, c - half : c + half + 1].astype(np.float64)
        rr, cc = np.mgrid[-half : half + 1, -half : half + 1]
        m = win.sum()
        out.append([r + (win * rr).sum() / m, c + (win * cc).sum() / m])
    return np.array(out)


DETERMINISTIC = {
    "round Gaussian σ 1": SpotModel(sigma_px=1.0),
    "round Gaussian σ 3": SpotModel(sigma_px=3.0, sigma_jitter=0.0),
    "stretched at the rim": SpotModel(sigma_px=1.2, rim_radial=1.0, rim_tangential=0.3),
    "flat top": SpotModel(sigma_px=1.6, profile_power=2.0, peak_gray=900.0),
    "smooth halo": SpotModel(halo_fraction=0.15, halo_speckle=0.0),
}


@pytest.mark.parametrize("spots", DETERMINISTIC.values(), ids=DETERMINISTIC.keys())
def test_deterministic_spots_are_centred_on_the_projected_point(spots: SpotModel) -> None:
    """The truth of a dot is its projection: every deterministic shape is symmetric about it,
    so the centroid of the light is there (to 5e-3 px: a flat top's sampling; measured 2.7e-3)."""
    rng = np.random.default_rng(1)
    pts = spread_dots(60, rng)
    img = laser_image(CAM, pts, spots, rng)
    err = np.hypot(*(centroids(img, pts) - pts).T)
    assert err.max() < (5e-3 if spots.profile_power > 1 else 2e-4)


def test_light_is_conserved_when_the_mirror_stretches_a_spot() -> None:
    rng = np.random.default_rng(2)
    pts = spread_dots(60, rng)
    round_ = SpotModel(sigma_px=1.3, sigma_jitter=0.0, peak_jitter=0.0)
    stretched = dataclasses.replace(round_, rim_radial=1.0, rim_tangential=0.4)
    a = laser_image(CAM, pts, round_, 0)
    b = laser_image(CAM, pts, stretched, 0)
    assert b.sum() == pytest.approx(a.sum(), rel=1e-3)
    # ... and the spots near the rim are longer radially than across, those at the centre not.
    rho = np.hypot(pts[:, 0] - CAM.center_row_px, pts[:, 1] - CAM.center_col_px)
    outer = pts[np.argmax(rho)]
    r, c = np.rint(outer).astype(int)
    win = b[r - 12 : r + 13, c - 12 : c + 13].astype(np.float64)
    rr, cc = np.mgrid[-12:13, -12:13] - (outer - [r, c])[:, None, None]
    e = (outer - [CAM.center_row_px, CAM.center_col_px]) / rho.max()
    radial = (rr * e[0] + cc * e[1]) ** 2
    across = (rr * e[1] - cc * e[0]) ** 2
    assert (win * radial).sum() > 1.5 * (win * across).sum()


def test_speckle_moves_single_spots_but_not_on_average() -> None:
    spots = SpotModel(sigma_px=1.6, speckle_contrast=0.1, speckle_grain_px=0.8)
    rng = np.random.default_rng(3)
    errs = []
    for _ in range(4):
        pts = spread_dots(90, rng)
        errs.append(centroids(laser_image(CAM, pts, spots, rng), pts) - pts)
    err = np.vstack(errs)
    rms = float(np.sqrt((err**2).sum(axis=1).mean()))
    assert 0.02 < rms < 0.12  # grains move the light of each dot a little (≈ 0.065 px)...
    assert np.all(np.abs(err.mean(axis=0)) < 3 * rms / np.sqrt(len(err)))  # ...without bias


def test_bright_spots_saturate_with_a_flat_top() -> None:
    rng = np.random.default_rng(4)
    pts = spread_dots(40, rng)
    spots = SpotModel(sigma_px=2.0, profile_power=1.5, peak_gray=800.0, peak_jitter=0.0)
    opts = RenderOptions(spots, background_texture=0.0)
    _, base = render_camera_pair(CAM, pts, opts, rng)
    r, c = np.rint(pts).astype(int).T
    tops = [(base[i - 3 : i + 4, j - 3 : j + 4] == 255).sum() for i, j in zip(r, c, strict=True)]
    assert min(tops) >= 9  # each dot's top is a plateau of clipped pixels


def test_random_spots_stay_in_their_spread_and_cover_every_family() -> None:
    s = SpotSpread()
    seen = set()
    for seed in range(60):
        m = random_spots(seed)
        assert m == random_spots(seed)  # deterministic
        seen.add(m.kind)
        assert m.shading
        assert s.sigma_px[0] <= m.sigma_px <= s.sigma_px[1]
        assert m.rim_radial == 0.0 or s.rim_radial[0] <= m.rim_radial <= s.rim_radial[1]
        assert 1.0 <= m.profile_power <= s.profile_power[1]
        assert m.speckle_contrast <= s.speckle_contrast[1]
    assert seen == set(SPOT_KINDS)
    sat = random_spots(5, "saturated")
    assert sat.peak_gray >= s.saturated_peak_gray[0] and sat.profile_power >= 1.0
    assert random_spots(5, "rim").rim_radial >= s.rim_radial[0]
    with pytest.raises(InputError, match="known"):
        random_spots(0, "blurry")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="sigma_px"):
        SpotModel(sigma_px=0.0)


def patch_image_area(cam: MirrorCamera, p: np.ndarray, n: np.ndarray, size: float = 0.5) -> float:
    """Image area (px²) of a tiny square of side ``size`` mm at ``p`` on a surface of normal n."""
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    corners = np.array([p + size * (i * a + j * b) for i, j in ((0, 0), (1, 0), (1, 1), (0, 1))])
    q = cam.project(corners)
    x, y = q[:, 0], q[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))


def test_shading_is_the_image_area_of_the_surface_under_the_mirror_model() -> None:
    """Radiance is conserved: a Lambertian dot's light in the image is ∝ the image area per
    unit surface area — computed here by projecting a tiny patch, independently of the formula."""
    H = 1100.0
    ref = patch_image_area(CAM, np.array([300.0, 0.0, H]), np.array([0.0, 0.0, -1.0]))
    rng = np.random.default_rng(6)
    for _ in range(40):
        p = np.array([rng.uniform(300, 2000), rng.uniform(-600, 600), rng.uniform(500, 1100)])
        normals = [np.array([0.0, 0.0, -1.0]), np.array([-1.0, 0.0, 0.0])]
        side = np.array([0.0, -np.sign(p[1] - CAM.y_mm), 0.0])
        for n in (*normals, side):
            want = patch_image_area(CAM, p, n) / ref
            got = surface_shading(p[None], n[None], CAM.y_mm, H)[0]
            assert got == pytest.approx(want, rel=2e-3)
    # A uniformly lit floor images uniformly; a floor at half the depth is four times brighter.
    floor = np.array([[300.0, 0.0, H], [2000.0, -500.0, H], [900.0, 700.0, 550.0]])
    up = np.tile([0.0, 0.0, -1.0], (3, 1))
    np.testing.assert_allclose(surface_shading(floor, up, CAM.y_mm, H), [1.0, 1.0, 4.0])
    # Facing away from the mirror: no light.
    assert surface_shading(floor[:1], -up[:1], CAM.y_mm, H)[0] == 0.0


def test_cast_hits_carry_the_normal_of_their_surface() -> None:
    rig = misaligned_rig()
    laser = LaserProjector()
    sc = three_boxes()
    hits = cast_laser(sc.world, sc.pose, sc.mount, laser, rig)
    floor = hits.truth == 0
    np.testing.assert_allclose(hits.normal[floor], np.tile([0, 0, -1.0], (floor.sum(), 1)))
    obst = hits.truth == 1
    up = np.isclose(hits.normal[obst, 2], -1.0)
    assert up.sum() > 10 and (~up).sum() > 3  # box tops and box sides
    # A side faces against the beam (toward the laser): the near sides face the chair (−X).
    d = hits.xyz - np.array(laser.source_mm)
    assert np.all(np.einsum("ij,ij->i", hits.normal[obst], d[obst]) < 0)
    assert np.all(np.linalg.norm(hits.normal, axis=1) == 1.0)
    sc = dropoff()
    hits = cast_laser(sc.world, sc.pose, sc.mount, laser, rig)
    pit = hits.truth == 2
    wall = pit & ~np.isclose(hits.normal[:, 2], -1.0)
    assert np.all(np.isclose(hits.xyz[pit & ~wall, 2], 1300.0))  # the lowered floor: up
    np.testing.assert_allclose(hits.normal[wall], np.tile([-1.0, 0, 0], (wall.sum(), 1)))


def test_rendered_dots_carry_the_beam_power_and_the_shading() -> None:
    """Through render_hits, a dot's light is its beam's power times its surface's shading."""
    rig = StereoRig.nominal()
    laser = LaserProjector(envelope_rad=0.5, jitter_rad=0.0)
    sc = three_boxes()
    hits = cast_laser(sc.world, sc.pose, sc.mount, laser, rig)
    spots = SpotModel(sigma_px=1.2, sigma_jitter=0.0, peak_jitter=0.0, peak_gray=100.0)
    for shading in (False, True):
        opts = RenderOptions(dataclasses.replace(spots, shading=shading), noise_sigma=0.0)
        cap = render_hits(rig, hits, 0, opts)
        diff = cap.base1.astype(float) - cap.mask1.astype(float)
        vis = hits.visible1 & rig.cam1.in_disk(hits.pixels[:, :2], 8.0)
        rc = np.rint(hits.pixels[vis, :2]).astype(int)
        # Light of each dot: the 5x5 sum (dots are ≥ 7 px apart, σ 1.2 px).
        light = np.array([diff[r - 2 : r + 3, c - 2 : c + 3].sum() for r, c in rc])
        want = hits.brightness[vis]
        if shading:
            want = want * surface_shading(
                hits.xyz[vis], hits.normal[vis], rig.cam1.y_mm, rig.floor_depth_mm
            )
        ratio = light / want
        lit = want > 0.2
        assert np.std(ratio[lit]) / np.mean(ratio[lit]) < 0.03
