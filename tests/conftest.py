"""Shared fixtures: seeded random generators and the nominal stereo rig."""

from __future__ import annotations

import numpy as np
import pytest

from omnid.core.geometry import StereoRig


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def nominal_rig() -> StereoRig:
    return StereoRig.nominal()
