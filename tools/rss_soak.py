"""Resident memory of the real daemon over a long run: flat after warm-up? (issue 10)

Run from the repository root (30 minutes of wall time, light CPU)::

    python tools/rss_soak.py [--minutes 30] [--warm-up-min 5] [--no-perception]

The bench (``tools/daemon_bench.py``): ``omnid run`` as systemd starts it, the control-unit
and GS311 emulators on ptys, a frame server showing a rendered empty floor (perception on in
its worker process, ``perception.period_s`` as shipped). A head-tilt rider loops through
forward, left, right and neutral; every 5 minutes a SIGHUP reloads the configuration and the
tilt sensor is unplugged for a second (fault paths exercised, not only the happy one).

Every 10 s it samples VmRSS of the daemon and of its children (the perception worker) from
/proc and the daemon's open file descriptors. Printed: the samples at the end of warm-up and at
the end, the least-squares slope after warm-up (MB per minute) for the daemon and the worker,
and the file-descriptor range. A flat run has |slope| well under 0.05 MB/min.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from daemon_bench import FORWARD, LEFT, NEUTRAL, DaemonBench

from omnid.devices.emulators.gs311 import HeadMotion


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            continue
    return out


def fd_count(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return -1


def slope_mb_per_min(samples: list[tuple[float, float]]) -> float:
    a = np.array([s for s in samples if s[1] == s[1]])
    if len(a) < 3:
        return float("nan")
    return float(np.polyfit(a[:, 0] / 60.0, a[:, 1], 1)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--warm-up-min", type=float, default=5.0)
    ap.add_argument("--sample-s", type=float, default=10.0)
    ap.add_argument("--no-perception", action="store_true")
    args = ap.parse_args()
    script = [
        (0.0, *NEUTRAL),
        (2.0, *NEUTRAL),
        (2.1, *FORWARD),
        (6.0, *FORWARD),
        (6.1, *NEUTRAL),
        (8.0, *NEUTRAL),
        (8.1, *LEFT),
        (11.0, *LEFT),
        (11.1, *NEUTRAL),
        (13.0, *NEUTRAL),
        (13.1, 0.0, -20.0),  # right
        (16.0, 0.0, -20.0),
        (16.1, *NEUTRAL),
        (18.0, *NEUTRAL),
    ]
    daemon: list[tuple[float, float]] = []
    worker: list[tuple[float, float]] = []
    fds: list[int] = []
    with DaemonBench(perception=not args.no_perception) as b:
        ready_s = b.start(timeout_s=60.0)
        assert b.proc is not None
        pid = b.proc.pid
        print(f"daemon pid {pid} ready after {ready_s:.1f} s", flush=True)
        b.gs.motion = HeadMotion(script, loop=True)
        t0 = time.monotonic()
        end = t0 + 60.0 * args.minutes
        next_fault = t0 + 300.0
        moved = 0
        while time.monotonic() < end and b.proc.poll() is None:
            now = time.monotonic() - t0
            daemon.append((now, rss_mb(pid)))
            kids = children(pid)
            worker.append((now, sum(rss_mb(k) for k in kids) if kids else float("nan")))
            fds.append(fd_count(pid))
            moved += int(b.moving())
            if time.monotonic() >= next_fault:
                next_fault += 300.0
                b.signal(signal.SIGHUP)
                b.gs.unplug()
                time.sleep(1.0)
                b.gs.replug()
            if len(daemon) % 30 == 0:
                print(
                    f"  t={now / 60:5.1f} min daemon {daemon[-1][1]:.1f} MB worker "
                    f"{worker[-1][1]:.1f} MB fds {fds[-1]}",
                    flush=True,
                )
            time.sleep(args.sample_s)
        alive = b.proc.poll() is None
        rc = b.stop()
        frames = len(b.spy.frames)
        log = b.log_text()
        trips, refusals = b.cu.watchdog_trips, b.cu.stale_refusals
    warm = 60.0 * args.warm_up_min
    d_after = [s for s in daemon if s[0] >= warm]
    w_after = [s for s in worker if s[0] >= warm]

    def at(samples: list[tuple[float, float]], t: float) -> float:
        return min(samples, key=lambda s: abs(s[0] - t))[1] if samples else float("nan")

    print(f"ran {daemon[-1][0] / 60:.1f} min, daemon alive to the end: {alive}, exit {rc}")
    print(
        f"  samples with the wheels turning: {moved} of {len(daemon)}; frames on the wire ≥ {frames}"
    )
    print(
        f"  daemon RSS: start {daemon[0][1]:.1f} MB, after warm-up {at(daemon, warm):.1f} MB, "
        f"end {daemon[-1][1]:.1f} MB, slope after warm-up {slope_mb_per_min(d_after):+.4f} MB/min"
    )
    print(
        f"  worker RSS: after warm-up {at(worker, warm):.1f} MB, end {worker[-1][1]:.1f} MB, "
        f"slope after warm-up {slope_mb_per_min(w_after):+.4f} MB/min"
    )
    total = [d + w for (_, d), (_, w) in zip(daemon, worker, strict=True) if w == w]
    if total:
        print(f"  daemon + worker: max {max(total):.1f} MB")
    print(f"  open file descriptors: {min(fds)} … {max(fds)}")
    # faults the daemon declared, by kind (the injected tilt unplugs are 1 per 5 min)
    kinds: dict[str, int] = {}
    for line in log.splitlines():
        if "omnid.daemon.arming: fault " in line:
            kind = line.split("fault ", 1)[1].split(":", 1)[0]
            kinds[kind] = kinds.get(kind, 0) + 1
    stalls = log.count("control loop stalled")
    injected = int(daemon[-1][0] // 300)
    print(
        f"  faults declared: {kinds or 'none'} ({injected} tilt unplugs injected); "
        f"control-loop stalls > 2 command periods: {stalls}; unit watchdog trips {trips}, "
        f"refused commands {refusals}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
