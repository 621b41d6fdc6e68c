"""discover's held-out check on a recording it searched whole refits the findings under the model the search
started from: with the sample clocks the timing stage found, not the input model without them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imu_array_ros.discovery import discover as discover_module
from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import gyro_chip_clocks

CORNERS = Path(__file__).resolve().parents[1] / "config" / "mimu4444bt_corners.yaml"


def test_the_held_out_check_refits_the_findings_with_the_clocks_found(monkeypatch):
    """MIMU-like gyroscope chip clocks (1 ms, +-3000 ppm, 62.5 Hz reads) and a gyroscope bias on imu_4: the
    timing stage finds the clocks, the search the bias; the held-out refit runs under the clocked model (before:
    the input model, so the reported held-out gain was the bias's without the clocks) and the bias gains there."""
    nominal = SensorModel.from_description(load_description(CORNERS))
    rng = np.random.default_rng(11)
    k = nominal.n_imus
    clock = gyro_chip_clocks(k, rng)
    bias = nominal.terms["gyroscope_bias"].values.copy()
    bias[3] += [0.004, -0.003, 0.002]
    true = nominal.with_terms(gyroscope_sample_clock=clock, gyroscope_bias=bias)
    samples, _ = simulate_twist(true, 20.0, 62.5, rng, start_ns=10**9)
    seen = []

    def spy(samples, model, findings, blocks, motion, residuals):
        seen.append(model)
        return heldout_gain(samples, model, findings, blocks, motion, residuals)

    heldout_gain = discover_module.heldout_gain
    monkeypatch.setattr(discover_module, "heldout_gain", spy)
    d = discover(samples, nominal, options=DiscoveryOptions(terms=("gyroscope_bias",), empirical=False,
                                                             max_findings=1))
    assert d.timing is not None and d.timing.used
    assert [(f.effect, f.imus) for f in d.findings] == [("gyroscope_bias", (3,))]
    assert len(seen) == 1
    clocks = seen[0].terms["gyroscope_sample_clock"].values
    assert np.all(clocks[:, 0] > 0), "the held-out refit ran without the clocks the timing stage found"
    assert d.heldout["delta_loglik"] > 10
