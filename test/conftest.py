"""Shared fixtures: arrays and recordings built from fixed seeds."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.model.layouts import grid_array32, planar_square4, tetrahedron4

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"

#: skog2016 Sec. V-A noise figures: sigma_s = 0.01 m/s^2, sigma_w = 1 deg/s.
SKOG2016_NOISE = dict(accelerometer_noise_std=0.01, gyroscope_noise_std=float(np.deg2rad(1.0)))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20161)


@pytest.fixture
def array32():
    return grid_array32()


@pytest.fixture
def planar4():
    return planar_square4(**SKOG2016_NOISE)


@pytest.fixture
def tetra4():
    return tetrahedron4(**SKOG2016_NOISE)
