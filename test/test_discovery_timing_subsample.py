"""On a long recording discovery's timing stage tests the clocks it found on the subsample the search starts on
(issue 23 item 7, speed): no motion fit of the whole recording under the clocked model before the search, the
same clocks found and used; the held-out check then scores the blocks half-way between the searched ones, each
model fitted on them alone, instead of fitting the whole recording under the model the search started from."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.discovery import discover as discover_module
from imu_array_ros.discovery import finish as finish_module
from imu_array_ros.discovery import heldout as heldout_module
from imu_array_ros.discovery import timing as timing_module
from imu_array_ros.discovery.blocks import search_rungs, time_blocks
from imu_array_ros.discovery.discover import DiscoveryOptions, discover
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_twist
from imu_array_ros.timing.delays import reading_delays
from imu_array_ros.timing.session import active_clocks, session_weights

from conftest import gyro_chip_clocks

CORNERS = str(Path(__file__).resolve().parents[1] / "config" / "mimu4444bt_corners.yaml")
#: 20 s at 62.5 Hz x 8 IMUs = 10,000 readings: every 4th block (10 of 40), every 2nd, the whole recording
BUDGET = 3_000


@pytest.fixture(scope="module")
def recording():
    nominal = SensorModel.from_description(load_description(CORNERS))
    rng = np.random.default_rng(11)
    k = nominal.n_imus
    clock = gyro_chip_clocks(k, rng)
    bias = nominal.terms["gyroscope_bias"].values.copy()
    bias[2] = (0.01, -0.01, 0.005)  # a strong effect, found on the first subsample
    true = nominal.with_terms(gyroscope_sample_clock=clock, gyroscope_bias=bias,
                              time_offset=np.column_stack([np.full(k, -1.6e-3), np.zeros(k)]))
    samples, _ = simulate_twist(true, 20.0, 62.5, rng, start_ns=10**9)
    return nominal, samples


def test_the_clocks_are_tested_on_the_first_subsample_and_held_out_on_the_blocks_between(
        recording, monkeypatch):
    nominal, samples = recording
    fits, lines = [], []
    real = discover_module.fit_motion

    def counted(s, model, *args, **kwargs):  # every motion fit: how many samples, clocked or not, at which stage
        fits.append((len(s.stamps), bool(active_clocks(model)), len(lines)))
        return real(s, model, *args, **kwargs)
    for module in (discover_module, finish_module, timing_module, heldout_module):
        monkeypatch.setattr(module, "fit_motion", counted)
    opts = DiscoveryOptions(terms=("gyroscope_bias",), empirical=False, max_findings=1, search_readings=BUDGET,
                            ladder_from=0)
    d = discover(samples, nominal, options=opts, progress=lines.append)
    first = search_rungs(time_blocks(samples.stamps, opts.block_s), nominal.n_imus, BUDGET, opts.folds, 0)[0][0]
    t = d.timing
    assert t.used and sorted({f.k for f in t.findings if f.sensor == "gyroscope"}) == list(range(8))
    scoring = next(i for i, line in enumerate(lines) if line.startswith("scoring"))
    before = [(n, clocked) for n, clocked, at in fits if at <= scoring]
    assert (len(samples.stamps), False) in before  # the input model's motion of the whole recording (baseline)
    assert (len(first), True) in before  # the clocks' gain on the first subsample
    assert (len(samples.stamps), True) not in before  # ... and no clocked fit of the whole recording
    whole_clocked = [at for n, clocked, at in fits if n == len(samples.stamps) and clocked]
    assert len(whole_clocked) == 1 and whole_clocked[0] > scoring  # once, after the search, under the findings
    np.testing.assert_array_equal(t.on, first)
    assert t.to_dict()["loglik_on"] == f"every 4th time block ({len(first)} samples)"
    assert [(f.effect, f.sensor) for f in d.findings] == [("gyroscope_bias", "imu_3")]
    assert d.settings["searched_on"] == "every 4th time block"
    # held out: the blocks half-way between the searched ones (2, 6, 10, ...), each model fitted on them alone
    between = np.flatnonzero(time_blocks(samples.stamps, opts.block_s) % 4 == 2)
    assert d.heldout["samples"] == len(between) and "every 4th time block from the 3rd" in d.heldout["method"]
    assert [n for n, clocked, at in fits if at > scoring and n == len(between)] == [len(between)] * 2
    assert d.heldout["delta_loglik"] > 100  # the bias the search found on the others


def test_the_evidence_plot_reuses_the_searchs_reading_delays(recording, monkeypatch):
    """The timing evidence (the clearest clock's relative reading delays under the input model) is the clock
    search's first look, not a second fusion and delay pass of the whole recording: the same arrays."""
    nominal, samples = recording
    calls = []
    monkeypatch.setattr(timing_module, "reading_delays", lambda *a, **k: calls.append(1) or reading_delays(*a, **k))
    t = timing_module.timing_stage(samples, nominal)
    assert t.used and not calls
    ev = t.evidence
    t0 = int(samples.stamps[0])
    delays = reading_delays(samples, nominal, ModelFusion(nominal, t0_ns=t0).fuse(samples)[0], t0_ns=t0,
                            sensor=ev["sensor"])
    k = nominal.names.index(ev["imu"])
    use = session_weights(delays)[:, k] > 0
    np.testing.assert_array_equal(ev["delay"], delays.relative()[use, k])
