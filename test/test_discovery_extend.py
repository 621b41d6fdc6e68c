"""A shared finding grown to a carrier outside the scope it was found at (:mod:`imu_array_ros.discovery.extend`).

A non-linearity with one value on the 32-grid's back half (16 IMUs, a geometry group) and on one front IMU: the
'back shared' scope is found first; the front carrier alone has too little evidence for the three-parameter test
of its own value to matter, but along the found value (one degree of freedom) it passes, and the finding is
grown to the 17 IMUs, one value.  On the back half alone nothing is grown.  Short simulated sessions (fixed
seeds) through the whole discovery.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.discovery.scopes import geometry_groups
from imu_array_ros.model.layouts import grid_array32
from imu_array_ros.model.sensor_model import SensorModel

from conftest import icosahedron_recording, with_change

TERM = "accelerometer_nonlinearity"
OPTIONS = DiscoveryOptions(terms=(TERM, "accelerometer_bias"), empirical=False, heldout=False, timing=False)
VALUE = np.array([1.0, -0.6, 0.8]) * 4e-5  # the front carrier alone: score ~19-21 (1 and 3 dof), evidence ~20


@pytest.fixture(scope="module")
def grid():
    nominal = SensorModel.from_description(grid_array32())
    return nominal, dict(geometry_groups(nominal.positions, nominal.rotations))["back"]


def _discover(nominal, imus, seed: int):
    s = icosahedron_recording(nominal, with_change(nominal, TERM, VALUE, imus), seed, twist_s=4.0, still_s=0.3,
                              transition_s=0.3)
    return discover(s, nominal, options=OPTIONS)


def test_a_carrier_outside_the_group_joins_its_shared_finding(grid):
    """Back half + imu_02 (front): one finding on exactly those 17 IMUs, one shared value within 3 std of the
    truth, its note saying it was put on imu_02 along the found value; before the extension (683064b) imu_02
    was a second finding with its own value."""
    nominal, back = grid
    imus = tuple(sorted(set(back) | {2}))
    d = _discover(nominal, imus, 5)
    assert [(f.effect, f.imus) for f in d.findings] == [(TERM, imus)]
    f = d.findings[0]
    assert f.shared and f.scope == f"{','.join(nominal.names[k] for k in imus)} shared"
    assert "put on imu_02 too (1 dof)" in f.candidate.note and "one value shared by all 17" in f.candidate.note
    assert np.all(np.abs(f.values - VALUE) < 3 * f.std), (f.values, f.std)
    assert any("grown to" in n for n in d.notes)


def test_a_group_finding_is_not_grown_without_another_carrier(grid):
    """The back half only: found as 'back shared', no IMU added (the one-dof tests of the 16 others are
    counted in the step's Bonferroni level like every candidate)."""
    nominal, back = grid
    d = _discover(nominal, back, 5)
    assert [(f.effect, f.imus, f.scope) for f in d.findings] == [(TERM, tuple(back), "back shared")]
    assert not any("grown to" in n for n in d.notes)
