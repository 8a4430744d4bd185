"""Shared fixtures: seeded random generators and the nominal stereo rig."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core.geometry import StereoRig


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--soak-minutes",
        type=float,
        default=12.0,
        help="simulated minutes of tests/scenarios/test_soak.py (12; the half hour: 30)",
    )


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
