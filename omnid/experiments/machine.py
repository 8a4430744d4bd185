"""What a benchmark prints about the machine it ran on (numbers are only comparable with it)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys


def one_core(cv2: object) -> str:
    """Put OpenCV on one thread (BLAS is limited by the caller's environment before numpy loads)
    and describe the machine: versions, threads, CPUs, the load average now."""
    import numpy as np

    cv2.setNumThreads(1)  # type: ignore[attr-defined, unused-ignore]
    threads = cv2.getNumThreads()  # type: ignore[attr-defined, unused-ignore]
    version = cv2.__version__  # type: ignore[attr-defined, unused-ignore]
    return (
        f"python {platform.python_version()}, numpy {np.__version__}, cv2 {version}, "
        f"one core (cv2 threads {threads}, BLAS threads 1), {platform.machine()}, "
        f"{os.cpu_count()} CPUs\nload average before: {load_average()}"
    )


def load_average() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


_BARE_LOOP = """
import asyncio, json, sys, time
async def main(seconds, period):
    t0, k, late = time.monotonic(), 0, []
    while time.monotonic() - t0 < seconds:
        deadline = t0 + k * period
        await asyncio.sleep(max(0.0, deadline - time.monotonic()))
        late.append(time.monotonic() - deadline)
        k += 1
    return late
print(json.dumps(asyncio.run(main(float(sys.argv[1]), float(sys.argv[2])))))
"""


def start_bare_loop(
    seconds: float, period_s: float = 0.02, prefix: tuple[str, ...] = ()
) -> subprocess.Popen[str]:
    """A reference process: an empty asyncio loop waking every ``period_s`` for ``seconds``,
    started now, so that a daemon's lateness is compared with this machine's at the same time.
    ``prefix``: a command to start it through (``REALTIME_PREFIX``: the daemon's scheduling)."""
    return subprocess.Popen(
        [*prefix, sys.executable, "-c", _BARE_LOOP, str(seconds), str(period_s)],
        stdout=subprocess.PIPE,
        text=True,
    )


# How systemd/omnid.service starts the daemon (CPUSchedulingPolicy=fifo, CPUSchedulingPriority=
# 20, CPUSchedulingResetOnFork=yes), for a benchmark run by root: real-time FIFO for the control
# loop's thread, while the perception worker and every other thread or child it starts run at
# the normal policy (reset on fork)
REALTIME_PREFIX = ("chrt", "--fifo", "--reset-on-fork", "20")


def bare_loop_lateness(proc: subprocess.Popen[str], seconds: float) -> list[float]:
    """The lateness (s) of each wake-up of a :func:`start_bare_loop` process, when it ends."""
    return list(json.loads(proc.communicate(timeout=seconds + 30)[0]))
