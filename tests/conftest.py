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


# The long runs (closed loops, the soak, the real daemon against its emulators) first: with
# pytest-xdist the last minute is then not one worker finishing a long test alone.
_LONG_FIRST = (
    "tests/scenarios/",
    "tests/sim/test_simulator.py",
    "tests/record/test_bench.py",
    "tests/daemon/test_daemon_system.py",
    "tests/sim/test_sim_camera.py",
    "tests/core/test_matching.py",  # its random-rigs fixture takes ~15 s to build
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    def rank(item: pytest.Item) -> int:
        path = item.nodeid.split("::", 1)[0]
        return next((k for k, p in enumerate(_LONG_FIRST) if path.startswith(p)), len(_LONG_FIRST))

    items.sort(key=rank)  # stable: the order within each group is kept


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
