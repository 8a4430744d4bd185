"""The installer's captures, simulated: the empty floor plus ``--extra`` captures (SPEC §6).

``omnid calibrate`` learns the laser from what the installer captures: the empty floor, and
something standing in view — here a box 0.8–1.1 m ahead and a wall 1.3 m ahead, each its own
capture. :func:`installation_captures` renders them for a rig and a laser;
:func:`calibrate_installed` runs calibration on them (what the simulator, the experiments and
the demos install with). The simulator never hands the true rig or laser to perception.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from omnid.core.geometry import StereoRig
from omnid.core.types import StereoCapture
from omnid.sim.laser import LaserProjector
from omnid.sim.render import RenderOptions, render_hits
from omnid.sim.scenes import rig_rect
from omnid.sim.world import Box, RigMount, World, cast_laser

#: The installer's extra scenes, rig frame (X ahead, Y right), mm: (x0, x1, y0, y1, height).
EXTRA_SCENES: dict[str, tuple[float, float, float, float, float]] = {
    "box": (800.0, 1100.0, -300.0, 300.0, 450.0),
    "wall": (1300.0, 1330.0, -2500.0, 2500.0, 1500.0),
}


def _world(rect: tuple[float, float, float, float, float], mount: RigMount) -> World:
    x0, x1, y0, y1, h = rect
    return World((Box(*rig_rect(x0, x1, y0, y1, mount), height_mm=h),))


def render_world(
    rig: StereoRig,
    laser: Any,
    world: World,
    mount: RigMount,
    seed: int,
    options: RenderOptions | None = None,
) -> StereoCapture:
    """A capture of ``world`` with the chair at the origin; each camera shows what it sees,
    every dot of the reference light (:func:`~omnid.sim.render.render_hits`)."""
    hits = cast_laser(world, (0.0, 0.0, 0.0), mount, laser, rig)
    return render_hits(rig, hits, seed, options, beam_light=False)


def installation_captures(
    rig: StereoRig,
    laser: Any = None,
    mount: RigMount | None = None,
    seed: int = 0,
    options: RenderOptions | None = None,
) -> tuple[StereoCapture, dict[str, StereoCapture]]:
    """(floor capture, {name: extra capture}) for ``rig`` and ``laser`` (default
    :class:`~omnid.sim.laser.LaserProjector`), mirrors ``mount.height_mm`` above the floor."""
    m = mount or RigMount(height_mm=rig.floor_depth_mm)
    las = laser if laser is not None else LaserProjector()
    floor = render_world(rig, las, World(), m, seed + 7919, options)
    extras = {
        name: render_world(rig, las, _world(rect, m), m, seed + 7920 + n, options)
        for n, (name, rect) in enumerate(EXTRA_SCENES.items())
    }
    return floor, extras


def calibrate_installed(
    rig: StereoRig,
    laser: Any = None,
    mount: RigMount | None = None,
    seed: int = 0,
    options: RenderOptions | None = None,
) -> Any:
    """Calibration from the simulated installer's captures (floor + extras), nothing else.

    Everything in it is seeded, so the same arguments give the same calibration: it is computed
    once per process for each set of them (a :class:`~omnid.core.calibration.Calibration` is
    frozen; every simulator of the same installation shares it, as the rides of one installed
    chair do). Unhashable arguments (a laser given as its rays) are calibrated every time."""
    try:
        hash((rig, laser, mount, seed, options))
    except TypeError:
        return _calibrate_installed(rig, laser, mount, seed, options)
    return _calibrate_installed_once(rig, laser, mount, seed, options)


def _calibrate_installed(
    rig: StereoRig, laser: Any, mount: RigMount | None, seed: int, options: RenderOptions | None
) -> Any:
    from omnid.core.calibration import calibrate_from_capture

    floor, extras = installation_captures(rig, laser, mount, seed, options)
    return calibrate_from_capture(
        floor, rig.floor_depth_mm, rig.baseline_mm, extras=list(extras.values())
    )


_calibrate_installed_once = functools.lru_cache(maxsize=16)(_calibrate_installed)


def write_capture(capture: StereoCapture, directory: str | Path, prefix: str = "") -> Path:
    """Write ``{prefix}mask1.png … {prefix}base2.png`` into ``directory`` (created), each
    atomically (:func:`omnid.io_images.write_png`)."""
    from omnid.io_images import write_png

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("mask1", "base1", "mask2", "base2"):
        write_png(out / f"{prefix}{name}.png", getattr(capture, name))
    return out


def write_installation(
    rig: StereoRig,
    directory: str | Path,
    laser: Any = None,
    mount: RigMount | None = None,
    seed: int = 0,
    options: RenderOptions | None = None,
) -> list[Path]:
    """Write the floor capture as ``floor_*.png`` in ``directory`` and each extra as a folder
    ``extra_<name>/`` (``omnid calibrate --extra`` takes those); returns the extra folders."""
    floor, extras = installation_captures(rig, laser, mount, seed, options)
    out = write_capture(floor, directory, "floor_")
    return [write_capture(cap, out / f"extra_{name}") for name, cap in extras.items()]


def calibrate_installation_cli(
    rig: StereoRig, directory: str | Path, seed: int = 0, timeout_s: float = 120.0
) -> tuple[Path, StereoCapture]:
    """The installer's procedure end to end: :func:`write_installation` into ``directory``, then
    the real ``omnid calibrate`` (a child process) on the floor and the extras. Returns
    (``directory/calib.yaml``, the floor capture); RuntimeError with calibrate's message if it
    refuses."""
    import subprocess
    import sys

    out_dir = Path(directory)
    extras = write_installation(rig, out_dir, seed=seed)
    floor = installation_captures(rig, seed=seed)[0]
    calib = out_dir / "calib.yaml"
    names = ("mask1", "base1", "mask2", "base2")
    args = [a for n in names for a in (f"--{n}", str(out_dir / f"floor_{n}.png"))]
    args += [a for e in extras for a in ("--extra", str(e))]
    depth = f"{rig.floor_depth_mm:g}"
    run = subprocess.run(
        [sys.executable, "-m", "omnid.cli", "calibrate", *args, "--floor-depth-mm", depth,
         "--out", str(calib)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )  # fmt: skip
    if run.returncode != 0:
        raise RuntimeError(f"omnid calibrate failed: {run.stderr.strip()}")
    return calib, floor
