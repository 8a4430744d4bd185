"""Benchmark of the simulator's renderer: ms per rendered camera frame pair, now against a
reference revision of the code in the same run, and whether the frames are bit-identical.

What is rendered (the same frames for both revisions): a chair driving 2.4 m through the
passage scenario of tests/scenarios (a walled room, a partition with a 1300 mm gap; or the
demo course: boxes, two partitions, the stairs down), the deliberately misaligned rig, the default laser, at
``--frames`` poses; every third frame laser-off (a mask), one in five half lit. Per
configuration:

- ``stream/world``: :meth:`omnid.sim.camera.SimCamera.render` (the closed-loop simulator's
  frames: the scene fixed to the world, cast on the coarse ray grid) with the default camera
  model, as every pipeline scenario renders; ``stream/floor``, ``stream/tiles``: the other
  texture settings; ``stream/demo``: the demo course (the story test's world);
- ``stream/realistic``: realistic spots and sensor (halos, ghosts, shot noise);
- ``capture``: :func:`omnid.sim.render.render_hits` (render.py's mask/base pairs, the scene
  fixed to the camera and drawn from the seed: the installer's captures, the detection tests);
  ``capture/fixed``: :func:`~omnid.sim.render.render_camera_pair` with a fixed scene seed, as
  :meth:`omnid.sim.simulator.Simulator.render` draws the snapshot and stationary policies'
  captures and the frame server's frames.

Each revision runs in its own child process on one core (cv2.setNumThreads(1), one BLAS thread),
alternating ``--rounds`` times (the machine may be shared: the load average is printed; compare
the mins and the same-run ratio). The reference is ``git archive <--reference>`` of
``omnid/`` into a temporary directory.

Run from the repository root:
    python tools/bench_render.py [--reference REV] [--frames 40] [--rounds 3]
"""

from __future__ import annotations

import os

# One core: BLAS threads must be fixed before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The renderer before the simulator-speed work, for the same-run comparison.
DEFAULT_REFERENCE = "4d99317"


def _frames(n: int) -> list[tuple[tuple[float, float, float], float, int]]:
    """(pose, lit share, seed) of ``n`` frames along a slightly curving drive."""
    out = []
    for k in range(n):
        s = k / max(n - 1, 1)
        pose = (2400.0 * s, 40.0 * s * s, 0.03 * (s - 0.5))
        lit = 0.0 if k % 3 == 2 else (0.5 if k % 5 == 4 else 1.0)
        out.append((pose, lit, 1000 + k))
    return out


def _worker(frames: int, out_path: str) -> None:
    """Render every configuration (timed), write timings and image digests as JSON."""
    import cv2
    import numpy as np

    from omnid.experiments.machine import one_core
    from omnid.sim.camera import CameraModel, SimCamera, SimFrame
    from omnid.sim.course import WALL_MM, builtin_course, walls
    from omnid.sim.laser import LaserProjector
    from omnid.sim.render import RenderOptions, render_camera_pair, render_hits
    from omnid.sim.rigs import misaligned_rig
    from omnid.sim.world import Box, RigMount, World, cast_laser

    one_core(cv2)
    mount = RigMount()
    rig = misaligned_rig(mount.height_mm)
    laser = LaserProjector()
    x0, x1, y0, y1 = -1000.0, 5000.0, -2000.0, 2000.0
    partition = (
        Box(1100.0, 1200.0, -2000.0, -650.0, 1000.0),
        Box(1100.0, 1200.0, 650.0, 2000.0, 1000.0),
    )
    room = World(boxes=(*partition, *walls(x0, x1, y0, y1)))
    extent = (x0 - WALL_MM - 3000, x1 + WALL_MM + 3000, y0 - WALL_MM - 3000, y1 + WALL_MM + 3000)
    demo = builtin_course()
    (dx0, dx1), (dy0, dy1) = demo.x_range_mm, demo.y_range_mm
    demo_extent = (dx0 - 3000, dx1 + 3000, dy0 - 3000, dy1 + 3000)
    configs = {
        "stream/world": (CameraModel(), RenderOptions(), room, extent),
        "stream/floor": (CameraModel(textured="floor"), RenderOptions(), room, extent),
        "stream/tiles": (CameraModel(texture="tiles"), RenderOptions(), room, extent),
        "stream/demo": (CameraModel(), RenderOptions(), demo.world, demo_extent),
        "stream/realistic": (CameraModel(), RenderOptions.realistic(), room, extent),
        "capture": (None, RenderOptions(), room, extent),
        "capture/fixed": (None, RenderOptions(), room, extent),
    }
    plan = _frames(frames)
    result: dict[str, dict[str, object]] = {}
    for name, (model, options, world, box) in configs.items():
        hits = [cast_laser(world, pose, mount, laser, rig) for pose, _, _ in plan]
        digest = hashlib.sha256()
        per_frame: list[float] = []
        if model is not None:
            camera = SimCamera(model, rig, mount, world, box, seed=7, render_options=options)
            camera.render(SimFrame(0, 0.0, plan[0][0], 1.0, 1), hits[0])  # warm-up
            for k, ((pose, lit, seed), h) in enumerate(zip(plan, hits, strict=True)):
                frame = SimFrame(k, k / 30.0, pose, lit, seed)
                t0 = time.process_time()
                images = camera.render(frame, h)
                per_frame.append(time.process_time() - t0)
                for img in images:
                    digest.update(np.ascontiguousarray(img).tobytes())
        else:
            fixed = name == "capture/fixed"
            for k, ((_, _, seed), h) in enumerate(
                zip([plan[0], *plan], [hits[0], *hits], strict=True)
            ):
                t0 = time.process_time()
                if fixed:  # as Simulator.render: the camera's own scene, the same every time
                    rng = np.random.default_rng(seed)
                    shots: list[np.ndarray] = []
                    for i, (cam, vis) in enumerate(
                        ((rig.cam1, h.visible1), (rig.cam2, h.visible2))
                    ):
                        xyz = h.xyz[vis]
                        shots += render_camera_pair(
                            cam, cam.project(xyz), options, rng, None, i + 1
                        )
                else:
                    cap = render_hits(rig, h, seed, options)
                    shots = [cap.mask1, cap.base1, cap.mask2, cap.base2]
                if k == 0:  # warm-up
                    continue
                per_frame.append(time.process_time() - t0)
                for img in shots:
                    digest.update(np.ascontiguousarray(img).tobytes())
        ms = sorted(1e3 * t for t in per_frame)
        result[name] = {
            "mean_ms": sum(ms) / len(ms),
            "median_ms": ms[len(ms) // 2],
            "digest": digest.hexdigest(),
        }
    Path(out_path).write_text(json.dumps(result))


def _run(code_dir: Path, frames: int) -> dict[str, dict[str, object]]:
    with tempfile.NamedTemporaryFile(suffix=".json", delete=False) as f:
        out = f.name
    env = dict(os.environ, PYTHONPATH=str(code_dir))
    subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", out, "--frames", str(frames)],
        check=True,
        env=env,
        cwd=code_dir,
    )
    data: dict[str, dict[str, object]] = json.loads(Path(out).read_text())
    Path(out).unlink()
    return data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", default=DEFAULT_REFERENCE, help="git revision to compare with")
    ap.add_argument("--frames", type=int, default=40, help="frame pairs per configuration")
    ap.add_argument("--rounds", type=int, default=3, help="alternating runs of each revision")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker(args.frames, args.worker)
        return
    from omnid.experiments.machine import load_average

    print(f"load average before: {load_average()} ({os.cpu_count()} CPUs; one core per run)")
    with tempfile.TemporaryDirectory() as tmp:
        ref_dir = Path(tmp)
        archive = subprocess.run(
            ["git", "archive", args.reference, "omnid"], cwd=ROOT, check=True, capture_output=True
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(ref_dir)], input=archive, check=True)
        runs: dict[str, list[dict[str, dict[str, object]]]] = {"now": [], "reference": []}
        for _ in range(args.rounds):
            runs["reference"].append(_run(ref_dir, args.frames))
            runs["now"].append(_run(ROOT, args.frames))
    print(f"load average after: {load_average()}")
    print(f"{args.frames} frame pairs per configuration, {args.rounds} rounds; CPU ms per frame "
          f"pair (both cameras), min over rounds of the mean over frames")  # fmt: skip
    print(f"{'configuration':18s} {'reference':>10s} {'now':>8s} {'ratio':>6s}  frames")
    for name in runs["now"][0]:
        ref = min(float(r[name]["mean_ms"]) for r in runs["reference"])  # type: ignore[arg-type]
        now = min(float(r[name]["mean_ms"]) for r in runs["now"])  # type: ignore[arg-type]
        same = {r[name]["digest"] for r in runs["now"] + runs["reference"]}
        verdict = "bit-identical" if len(same) == 1 else "DIFFERENT"
        print(f"{name:18s} {ref:10.2f} {now:8.2f} {ref / now:6.2f}  {verdict}")
    print(f"reference: {args.reference}")


if __name__ == "__main__":
    main()
