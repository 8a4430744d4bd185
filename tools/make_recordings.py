"""Write the small simulator recordings the test suite replays (tests/data/recordings/).

Run from the repository root:  python tools/make_recordings.py [--out tests/data/recordings]

``tests/record/test_replay.py`` replays each with this build's perception and safety layer and
expects every decision as recorded. When a change to the daemon's decisions is intended (a
new safety rule, a changed ramp), run this again and commit the new files with the change,
saying in the commit what the replay reported before (``omnid replay FILE``).

- ``demo_truth.mcap`` — the demo story's first 30 s (head tilt forward: the start-up creep
  into the band the laser cannot see, through the wide passage, slow zone and approach at the
  narrow one), truth perception;
- ``faults_truth.mcap`` — 8 s of driving with the control unit silent from 3 to 3.6 s and the
  tilt sensor unplugged from 5 to 5.5 s (stops, re-arming, fault events);
- ``pipeline_capture.mcap`` — 3 s of the rendered-camera pipeline with one recorded capture
  (this build's perception re-runs on its pixels).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path


def record(
    out: Path,
    name: str,
    duration_s: float,
    perception: str,
    capture_period_s: float,
    faults: tuple = (),
) -> Path:
    from omnid.record.session import SimRecording
    from omnid.sim.course import builtin_course
    from omnid.sim.scenario import make_core
    from omnid.sim.simulator import SimSettings, Simulator
    from omnid.sim.story import demo_story

    path = out / name
    path.unlink(missing_ok=True)
    core = make_core(joystick=True, tilt=True)
    # The thesis' stationary capture (a cloud every 0.5 s), not the shipped stream (18 a
    # second): the replay checks decisions, which the recorded clouds feed either way, and
    # the stream made the 30 s demo 3.1 MB instead of 0.9 MB
    cfg = core.config
    core = type(core)(
        dataclasses.replace(
            cfg,
            perception=dataclasses.replace(cfg.perception, capture="stationary"),
            safety=dataclasses.replace(cfg.safety, perception_timeout_s=1.5),
        )
    )
    rec = SimRecording(core, str(path), None, capture_period_s=capture_period_s)
    sim = Simulator(
        builtin_course(),
        rec.core,
        SimSettings(perception=perception, seed=0),  # type: ignore[arg-type]
        rider=demo_story(),
        faults=faults,
    )
    rec.attach(sim)
    sim.run(duration_s)
    rec.close()
    print(f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB)")
    return path


def main() -> None:
    from omnid.sim.simulator import Fault

    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="tests/data/recordings")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    logging.getLogger().addHandler(logging.NullHandler())  # warnings go to /log, not stderr
    record(out, "demo_truth.mcap", 30.0, "truth", 0.0)
    record(
        out,
        "faults_truth.mcap",
        8.0,
        "truth",
        0.0,
        (Fault("cu_silent", 3.0, 3.6), Fault("tilt_unplugged", 5.0, 5.5)),
    )
    record(out, "pipeline_capture.mcap", 3.0, "pipeline", 100.0)


if __name__ == "__main__":
    main()
