"""A long recording is searched on an evenly spread subsample of its time blocks first (issue 23, speed), and an
effect too weak for the subsample is still found on the whole recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.discovery.blocks import search_rungs, time_blocks
from imu_array_ros.discovery.discover import SUBSAMPLE_SHARE, DiscoveryOptions, discover

#: 3,000 samples x 8 IMUs with a budget of 6,000 readings: every 4th block, every 2nd, the whole recording
BUDGET = 6_000
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.icosahedron import simulate_icosahedron

CORNERS = str(Path(__file__).resolve().parents[1] / "config" / "mimu4444bt_corners.yaml")


def test_the_subsamples_are_every_kth_block_from_the_first_within_the_budget_then_halving_k():
    blocks = time_blocks((np.arange(6000) * 1e7).astype(np.int64), 0.5)  # 60 s at 100 Hz: 120 blocks of 50
    assert search_rungs(blocks, 8, None, 4, 0) == []
    assert search_rungs(blocks, 8, 48_000, 4, 0) == []  # within the budget
    assert search_rungs(blocks, 8, 10_000, 4) == []  # 48,000 readings: not long enough for subsamples to pay
    rungs = search_rungs(blocks, 8, 10_000, 4, 0)
    assert [k for _, _, k in rungs] == [5, 2]  # then the whole recording
    index, renumbered, k = rungs[0]
    assert index[0] == 0  # the first block: drifts and clocks count from the first stamp
    assert set(blocks[index]) == set(range(0, 120, 5)) and len(index) == 24 * 50
    assert len(index) * 8 <= 10_000
    np.testing.assert_array_equal(renumbered, np.repeat(np.arange(24), 50))
    assert set(blocks[rungs[1][0]]) == set(range(0, 120, 2))
    assert search_rungs(blocks, 8, 1_000, 4, 0) == []  # 120 / 48 blocks: fewer than two per fold


@pytest.fixture(scope="module")
def nominal():
    return SensorModel.from_description(load_description(CORNERS))


def _recording(nominal, weak: float, seed: int):
    """Still poses then twisting at 100 Hz (3,000 samples): a strong accelerometer bias on imu_3 and a weak one
    (x axis, ``weak`` m/s^2) on imu_6."""
    v = nominal.terms["accelerometer_bias"].values.copy()
    v[2], v[5] = (0.05, -0.03, 0.04), (weak, 0.0, 0.0)
    samples, _, _ = simulate_icosahedron(nominal.with_terms(accelerometer_bias=v), np.random.default_rng(seed),
                                         rate_hz=100.0, still_s=0.5, transition_s=0.5, twist_s=10.0)
    return samples


def _options(budget):
    return DiscoveryOptions(terms=("accelerometer_bias",), search_readings=budget, ladder_from=0, empirical=False,
                            heldout=budget is not None)


def test_strong_effects_are_found_on_the_subsample_and_scored_on_the_blocks_it_left_out(nominal):
    s = _recording(nominal, 0.0, seed=5)
    lines = []
    d = discover(s, nominal, options=_options(BUDGET), progress=lines.append)
    subs = d.settings["search_subsamples"]
    assert [r["every_kth_block"] for r in subs] == [4, 2] and d.settings["searched_on"] == "every 4th time block"
    assert [(f.effect, f.sensor) for f in d.findings] == [("accelerometer_bias", "imu_3")]
    f = d.findings[0]
    assert np.all(np.abs(f.values - [0.05, -0.03, 0.04]) < 4 * f.std)  # the subsample's CRB: honest std
    assert f.std[0] > 1.6 * _whole_std(nominal, s)  # ~2x the whole recording's: a quarter of the samples
    m = d.settings["candidates_per_step"]
    assert d.level_per_step[0] == pytest.approx(0.01 * SUBSAMPLE_SHARE / 2 / m[0])
    assert d.heldout["samples"] == len(s.stamps) - subs[0]["samples"] and d.heldout["delta_loglik"] > 100
    assert "blocks it left out" in d.heldout["method"]
    assert any("fitted on a subsample, every 4th time block" in n for n in d.notes)
    looks = [line for line in lines if line.startswith("looking at")]  # it ran out: the larger ones were scored
    assert len(looks) == 2 and "every 2nd time block" in looks[0] and "the whole recording" in looks[1]


def _whole_std(nominal, s):
    from imu_array_ros.fitting.engine import fit_terms

    fit = fit_terms(s, nominal, ["accelerometer_bias"], imus=["imu_3"], sandwich=False)
    return float(fit.std["accelerometer_bias"][2, 0])


@pytest.mark.parametrize("weak, where, share", [(0.0085, "every 2nd time block", SUBSAMPLE_SHARE / 2),
                                                (0.0050, "the whole recording", 1 - SUBSAMPLE_SHARE)])
def test_an_effect_too_weak_for_the_subsample_is_found_on_a_larger_one(nominal, weak, where, share):
    s = _recording(nominal, weak, seed=6)
    d = discover(s, nominal, options=_options(BUDGET), progress=lambda text: None)
    assert [(f.effect, f.sensor) for f in d.findings] == [("accelerometer_bias", "imu_3"),
                                                           ("accelerometer_bias", "imu_6")]
    assert d.settings["searched_on"] == where
    found = d.findings[1]
    assert abs(found.values[0] - weak) < 4 * found.std[0]
    # the look at the larger samples spends its own part of alpha at the step the subsample ran out on
    assert d.level_per_step[1] == pytest.approx(0.01 * share / d.settings["candidates_per_step"][1])
    if where == "the whole recording":
        assert "even time blocks" in d.heldout["method"]  # the whole recording was fitted: the two-fold check
    else:
        assert d.heldout["samples"] == len(s.stamps) - d.settings["search_subsamples"][1]["samples"]


@pytest.mark.parametrize("options", [_options(None), DiscoveryOptions(terms=("accelerometer_bias",), empirical=False,
                                                                     heldout=False)])
def test_the_whole_recording_when_the_budget_is_off_or_the_recording_short_of_the_ladder(nominal, options):
    s = _recording(nominal, 0.0, seed=5)  # 24,000 readings: within the default ladder_from
    d = discover(s, nominal, options=options, progress=lambda text: None)
    assert d.settings["search_subsamples"] == [] and d.settings["searched_on"] == "the whole recording"
    assert d.level_per_step[0] == pytest.approx(0.01 / d.settings["candidates_per_step"][0])
