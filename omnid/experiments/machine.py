"""What a benchmark prints about the machine it ran on (numbers are only comparable with it)."""

from __future__ import annotations

import os
import platform


def one_core(cv2: object) -> str:
    """Put OpenCV on one thread (BLAS is limited by the caller's environment before numpy loads)
    and describe the machine: versions, threads, CPUs, the load average now."""
    import numpy as np

    cv2.setNumThreads(1)  # type: ignore[attr-defined]
    threads = cv2.getNumThreads()  # type: ignore[attr-defined]
    version = cv2.__version__  # type: ignore[attr-defined]
    return (
        f"python {platform.python_version()}, numpy {np.__version__}, cv2 {version}, "
        f"one core (cv2 threads {threads}, BLAS threads 1), {platform.machine()}, "
        f"{os.cpu_count()} CPUs\nload average before: {load_average()}"
    )


def load_average() -> str:
    """The 1, 5 and 15 minute load averages."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())
