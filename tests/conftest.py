"""Shared fixtures: seeded random generators and the nominal stereo rig."""

from __future__ import annotations

import os

# One thread per test process, set before numpy and OpenCV load: the suite runs one pytest-xdist
# worker per core, and each library's own pool on top (OpenBLAS spin-waits, OpenCV splits every
# remap) cost a quarter more CPU for the same results. Processes the tests start inherit it.
for _var in (
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENCV_FOR_THREADS_NUM",
):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from omnid.core.geometry import StereoRig  # noqa: E402


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--soak-minutes",
        type=float,
        default=5.0,
        help="simulated minutes of tests/scenarios/test_soak.py (5 in CI; the half hour: 30)",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "slow(seconds): a long run (still part of CI) and about how long it takes on a 2-core "
        "machine, s: the suite starts it first, on the least loaded worker",
    )


def _seconds(item: pytest.Item) -> float:
    mark = item.get_closest_marker("slow")
    if mark is None:
        return 0.0
    return float(mark.kwargs["seconds"] if "seconds" in mark.kwargs else mark.args[0])


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the tests so that pytest-xdist starts every long run first, spread over its workers.

    ``--dist worksteal`` hands each of n workers one contiguous share of the collection and
    later moves the tail of the longest queue to an idle worker. So each long run (``slow(seconds)``) goes, longest first, to the head of the share
    with the least long-run time so far; the others keep their order behind them. Without it,
    the suite's last half-minute was one worker alone in a 25 s test."""
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    long_runs = sorted((it for it in items if _seconds(it) > 0), key=_seconds, reverse=True)
    if not long_runs:
        return
    rest = [it for it in items if _seconds(it) == 0]
    sizes, left = [], len(items)
    for k in range(workers):  # the shares' sizes as worksteal's first distribution cuts them
        sizes.append(left // (workers - k))
        left -= sizes[-1]
    heads: list[list[pytest.Item]] = [[] for _ in range(workers)]
    load = [0.0] * workers
    for it in long_runs:
        k = min((k for k in range(workers) if len(heads[k]) < sizes[k]), key=lambda k: load[k])
        heads[k].append(it)
        load[k] += _seconds(it)
    order: list[pytest.Item] = []
    for head, size in zip(heads, sizes, strict=True):
        take = size - len(head)
        order += head + rest[:take]
        rest = rest[take:]
    items[:] = order


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def nominal_rig() -> StereoRig:
    return StereoRig.nominal()


@pytest.fixture(scope="session")
def random_installations() -> list[tuple[object, object]]:
    """10 random rigs with random lasers (rig 7: source near the mirror plane; rig 9: in it,
    with a grid uniform in angle), each calibrated on its floor and extras: (RigCase,
    Calibration). Shared by the calibration and matching rate tests (calibrating is the cost)."""
    from omnid.experiments import rigs as ev

    out = []
    for r in range(10):
        case = ev.rig_case(r, seed=1)
        out.append((case, ev.calibrate_case(case, seed=1)))
    return out
