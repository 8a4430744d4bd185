"""Soak and speed figures of the simulator (prints numbers; no assertions).

    python tools/soak.py                       # 300 simulated s per configuration
    python tools/soak.py --duration-s 1800     # a longer soak
    python tools/soak.py --controller core     # the daemon core drives (when it is in the build)
    python tools/soak.py --rider --minutes 30 [--perception pipeline]
                                               # the half-hour soak: daemon core at its configured
                                               # rates, random joystick rider, cluttered room

Measures, in one run on this machine:

* the virtual-clock loop with perception off (the reference): simulated seconds per wall second;
* the same with ``truth`` perception (laser cast every 0.2 s) and the ratio to the reference;
* one rendered stereo frame pair (what the frame server and ``pipeline`` perception pay);
* frame-server round trips over a real Unix socket (640x480 pairs), frames per second;
* peak resident memory before and after the long run (a leak shows as growth).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from omnid.sim.course import builtin_course, empty_room
from omnid.sim.frame_server import FrameServer, fetch_frame
from omnid.sim.simulator import OpenLoopDriver, SimSettings, Simulator


def wander(duration_s: float) -> OpenLoopDriver:
    """Forward 4 s, spin 1.5 s, repeat (stays in a 8 m room: turns keep it from the walls)."""
    script = []
    t = 0.0
    while t < duration_s:
        script += [(t, 0.6, 0.6), (t + 4.0, -0.5, 0.5), (t + 5.5, -0.6, -0.6)]
        t += 9.5
    return OpenLoopDriver(script)


def run_once(perception: str, duration_s: float, controller: str) -> tuple[float, dict[str, float]]:
    course = empty_room(8000.0, 8000.0)
    if controller == "core":
        from omnid.sim.course import demo_rider
        from omnid.sim.scenario import make_core

        sim = Simulator(
            builtin_course(),
            make_core(),
            rider=demo_rider(),
            settings=SimSettings(perception=perception, stop_on_contact=False),  # type: ignore[arg-type]
        )
    else:
        sim = Simulator(
            course,
            wander(duration_s),
            settings=SimSettings(perception=perception, stop_on_contact=False),  # type: ignore[arg-type]
        )
    w0 = time.perf_counter()
    result = sim.run(duration_s)
    wall = time.perf_counter() - w0
    return wall, result.timings


def rider_soak(minutes: float, perception: str, seed: int) -> int:
    """The CI soak's setup (tests/scenarios/test_soak.py) for ``minutes``: prints wall time,
    distance, contacts, refusals and resident memory once per simulated minute."""
    import dataclasses

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "scenarios"))
    from test_soak import cluttered_room, soak_settings  # type: ignore[import-not-found]

    from omnid.sim.rider import random_ride
    from omnid.sim.scenario import make_core

    duration = 60.0 * minutes
    settings = dataclasses.replace(soak_settings(), perception=perception, seed=seed)  # type: ignore[arg-type]

    def progress(now_s: float, _sim: Simulator) -> None:
        if int(now_s) % 60 == 0 and now_s > 0:
            rss = int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 2**20
            print(
                f"  t={now_s / 60:4.0f} min  wall {time.perf_counter() - w0:6.1f} s  RSS {rss:.0f} MB"
            )

    sim = Simulator(
        cluttered_room(),
        make_core(joystick=True),
        settings,
        joystick=random_ride(seed, duration),
        progress=progress,
    )
    w0 = time.perf_counter()
    r = sim.run(duration)
    wall = time.perf_counter() - w0
    t = r.timings
    print(
        f"rider soak, {minutes:.0f} simulated min, perception {perception}: {wall:.1f} s wall "
        f"({duration / wall:.1f}x real time); control {t['control_steps']:.0f} steps "
        f"{t['control_step_mean_ms']:.2f} ms mean / {t['control_step_max_ms']:.1f} ms max; "
        f"perception {t['perception_cycles']:.0f} cycles {t['perception_mean_ms']:.1f} ms mean"
    )
    print(
        f"distance {r.distance_mm / 1000:.1f} m, collisions {len(r.collisions)}, falls "
        f"{len(r.falls)}, closest approach {r.min_clearance_mm:.0f} mm, refusals "
        f"{len(r.refusals)}, peak RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    ap.add_argument("--duration-s", type=float, default=300.0)
    ap.add_argument("--controller", choices=["open-loop", "core"], default="open-loop")
    ap.add_argument("--frames", type=int, default=100, help="frame-server round trips")
    ap.add_argument("--rider", action="store_true", help="the random-rider soak only")
    ap.add_argument("--minutes", type=float, default=30.0, help="rider soak length (30)")
    ap.add_argument("--perception", choices=["truth", "pipeline"], default="truth")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    if args.rider:
        return rider_soak(args.minutes, args.perception, args.seed)

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        f"simulated duration per configuration: {args.duration_s:.0f} s, "
        f"controller: {args.controller}"
    )
    wall_ref, _ = run_once("off", args.duration_s, args.controller)
    print(
        f"reference, perception off: {wall_ref:.2f} s wall, "
        f"{args.duration_s / wall_ref:.1f}x real time"
    )
    wall, t = run_once("truth", args.duration_s, args.controller)
    print(
        f"perception truth:          {wall:.2f} s wall, {args.duration_s / wall:.1f}x real time "
        f"({wall / wall_ref:.2f}x the reference's wall time); perception "
        f"{t['perception_mean_ms']:.2f} ms mean / {t['perception_max_ms']:.2f} ms max per cycle; "
        f"control step {t['control_step_mean_ms']:.3f} ms mean"
    )
    print(
        f"control unit: {'bytes through the codec (emulator)' if t.get('bytes_link') else 'direct model'}, "
        f"watchdog trips {int(t['watchdog_trips'])}"
    )
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    sim = Simulator(builtin_course(), OpenLoopDriver([(0.0, 0.0, 0.0)]))
    n = 20
    w0 = time.perf_counter()
    for _ in range(n):
        sim.render(laser_on=True)
    render_ms = (time.perf_counter() - w0) / n * 1e3
    print(
        f"render one stereo mask/base capture (640x480, laser on): {render_ms:.1f} ms "
        f"({render_ms / (1e3 * wall_ref / (args.duration_s / 0.01)):.0f}x one reference tick)"
    )

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "f.sock"
        a = np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8)
        with FrameServer(path, lambda: (0.0, a, a)):
            w0 = time.perf_counter()
            for _ in range(args.frames):
                fetch_frame(path)
            fps_static = args.frames / (time.perf_counter() - w0)
        with FrameServer(path, sim.frame):
            w0 = time.perf_counter()
            for _ in range(max(10, args.frames // 5)):
                fetch_frame(path)
            fps_render = max(10, args.frames // 5) / (time.perf_counter() - w0)
    print(
        f"frame server (new connection per frame, 2x640x480 gray8): {fps_static:.0f} frames/s "
        f"with a fixed image; {fps_render:.1f} frames/s rendering each from the simulator"
    )
    print(f"peak RSS: {rss0:.0f} MB before, {rss1:.0f} MB after the runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
