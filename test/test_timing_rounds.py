"""The trajectory rounds of fit_terms with timing terms (fitting/rounds.py): the fit stops at the fixed point
where the trajectory the timing terms read is that of the motion found, reports the log-likelihood there, and says
when it did not get there."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import imu_array_ros.fitting.rounds as rounds
from imu_array_ros.fitting.engine import fit_motion, fit_terms
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.fitting.reading_rates import reading_rates
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

from conftest import clocked_twist_case

ROOT = Path(__file__).resolve().parents[1]
#: 120 reads at 62.5 Hz (the MIMU4444BT's)
STAMPS = (np.arange(120) * 16_000_000).astype(np.int64)


@pytest.fixture(scope="module")
def case():
    """Sample clocks on 8 corner IMUs, hand-like twisting plus motion faster than the reads follow (the
    recording of test_reading_rates.py, shorter): the time offsets' fit with reading rates, from the truth."""
    return clocked_twist_case(11, STAMPS)


def fit(case):
    clocked, samples, motion = case
    with reading_rates():
        return fit_terms(samples, clocked, ["time_offset"], motion0=motion, max_iterations=50, sandwich=False)


def test_the_fit_is_a_fixed_point_of_the_rounds_and_reports_its_own_likelihood(case):
    # the old loop (3 re-freezes) stopped 0.68 std from where many rounds end, and reported the log-likelihood on
    # the trajectory of an earlier motion: 117 above that of its own parameters
    clocked, samples, motion = case
    first = fit(case)
    assert first.converged
    with reading_rates():
        profile = fit_motion(samples, first.model, first.motion)[1]
        again = fit_terms(samples, first.model, ["time_offset"], motion0=first.motion, max_iterations=50,
                          sandwich=False)
    assert abs(first.loglik_after - profile) < 0.5, (first.loglik_after, profile)
    std = first.std["time_offset"]
    ok = np.isfinite(std) & (std > 0)
    moved = np.abs(again.model.terms["time_offset"].values - first.model.terms["time_offset"].values)[ok] / std[ok]
    assert np.max(moved) < 0.1 and abs(again.loglik_after - first.loglik_after) < 0.5, (np.max(moved),
                                                                                           again.loglik_after)


def test_a_fit_stopped_by_the_round_cap_says_it_did_not_converge(case, monkeypatch):
    monkeypatch.setattr(rounds, "TIMING_ROUNDS", 1)
    assert not fit(case).converged


def holed(samples):
    """``samples`` with every gyroscope's z axis missing on 20 samples: with reading rates the rate of that axis
    is a coordinate no reading informs (as where every gyroscope of an axis saturates on the real captures)."""
    gyro = samples.gyro.copy()
    gyro[40:60, :, 2] = np.nan
    return replace(samples, gyro=gyro)


@pytest.mark.parametrize("hole", [False, True])
def test_fit_motion_reaches_the_fixed_point_of_its_trajectory_rounds(case, hole):
    # before: two trajectory rounds and a ridge on samples with an uninformed coordinate; a second call from the
    # motion returned gained 795 log-likelihood (holed: 33,408, the ML itself 166,000 above the first call's)
    clocked, samples, _ = case
    samples = holed(samples) if hole else samples
    with reading_rates():
        first = fit_motion(samples, clocked)
        again = fit_motion(samples, clocked, first[0])
    assert abs(again[1] - first[1]) < rounds.ROUND_GAIN, (first[1], again[1])
    assert first.converged and first.rounds > 1 and first.step < rounds.ROUND_STD and first.gain < rounds.ROUND_GAIN
    assert again.converged and again.rounds == 0


def test_fit_motion_from_the_fits_motion_does_not_fall_below_the_fit(case):
    # before: 0.070 below the fit's log-likelihood (two rounds from the fit's motion)
    clocked, samples, _ = case
    first = fit(case)
    with reading_rates():
        profile = fit_motion(samples, first.model, first.motion)
    assert profile[1] > first.loglik_after - rounds.ROUND_GAIN, (profile[1], first.loglik_after)
    assert profile.converged


def test_fit_motion_without_timing_terms_is_one_gauss_newton_solve(case):
    # no trajectory: no rounds, the same numbers as the motion-only Gauss-Newton (as before the rounds)
    _, samples, _ = case
    corners = SensorModel.from_description(load_description(ROOT / "config/mimu4444bt_corners.yaml"))
    out = fit_motion(samples, corners)
    prob = Problem(samples, corners, ("position",), np.arange(corners.n_imus))
    motion, lin = prob.fit_motion(corners, prob.initial_motion(corners))
    assert out.rounds == 0 and not prob.needs_derivatives
    assert np.array_equal(out.motion, prob.expand(motion)) and out.loglik == prob.loglik(lin.cost)
