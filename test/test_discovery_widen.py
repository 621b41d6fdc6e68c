"""A pooled finding whose shared value its exact fit rejects at a proper scope is sought on every IMU
(:func:`imu_array_ros.discovery.confirm.confirm`'s widening).

A time offset with one value on 14 IMUs of the 32-grid that form no geometry group: the pooled score test of one
shared value at a side of the grid (half of its IMUs carriers) passes first; its exact fit rejects one value
there, and the IMUs outside the side, held by the fit, mix carriers and non-carriers, so narrowing within the
side cannot find the carriers (before the widening: three findings on 26 IMUs, none of them the set).  With
every IMU free the gauge (a delay common to every sensor, absorbed by the fused motion) puts the carriers and the
others at two levels, and the split finds the 14, one shared value, their complement named as
indistinguishable.  A short simulated twist (fixed seed) through the whole discovery.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.model.layouts import grid_array32
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import with_change

TERM = "time_offset"
OPTIONS = DiscoveryOptions(terms=(TERM, "accelerometer_bias"), empirical=False, heldout=False, timing=False)
CARRIERS = (1, 2, 4, 5, 7, 8, 13, 16, 17, 19, 21, 24, 27, 31)
VALUE = np.array([-1.5e-5, -2e-6])  # accelerometer, gyroscope delay (s)


def test_a_gauge_moved_group_is_found_on_its_carriers():
    nominal = SensorModel.from_description(grid_array32())
    truth = with_change(nominal, TERM, VALUE, CARRIERS)
    samples, _ = simulate_twist(truth, 20.0, 100.0, np.random.default_rng(11))
    d = discover(samples, nominal, options=OPTIONS)
    assert [(f.effect, f.imus) for f in d.findings] == [(TERM, CARRIERS)]
    f = d.findings[0]
    assert f.shared, f.scope
    assert "sought on every IMU" in f.candidate.note
    assert np.all(np.abs(f.values - VALUE) < 3 * f.std), (f.values, f.std)
    rest = tuple(k for k in range(32) if k not in CARRIERS)
    named = [e for e in d.indistinguishable if any(", ".join(nominal.names[k] for k in rest) in s
                                                    for s in e["sensors"])]
    assert named, d.indistinguishable
