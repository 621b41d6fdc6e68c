"""fit_motion's trajectory rounds take one Gauss-Newton step of the motion on each held trajectory
(rounds.MOTION_ROUND_STEPS): the next round re-freezes at the motion found anyway, so solving the held problem to
the optimiser's tolerance only spent passes over the samples (on the whole of exp_3: the same 4 rounds, 5 instead of
14 linearisations, benchmarks/results/discovery_speed.md).  The fixed point and its criterion are unchanged."""

from __future__ import annotations

import numpy as np
import pytest

import imu_array_ros.fitting.rounds as rounds
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.fitting.problem import MOTION_ITERATIONS, Problem
from imu_array_ros.fitting.reading_rates import reading_rates

from conftest import clocked_twist_case

#: 120 reads at 62.5 Hz (the MIMU4444BT's)
STAMPS = (np.arange(120) * 16_000_000).astype(np.int64)


@pytest.fixture(scope="module")
def case():
    return clocked_twist_case(11, STAMPS)


def counted(monkeypatch):
    """Counts of the full passes over the samples: linearisations and residual passes."""
    n = {"linearize": 0, "residuals": 0}
    for name in n:
        method = getattr(Problem, name)

        def wrapper(self, *args, _method=method, _name=name, **kwargs):
            n[_name] += 1
            return _method(self, *args, **kwargs)
        monkeypatch.setattr(Problem, name, wrapper)
    return n


@pytest.mark.parametrize("start", ["readings", "truth scaled"])
def test_one_gauss_newton_step_per_round(case, monkeypatch, start):
    # before: each round solved its held trajectory to the optimiser's tolerance and linearised at the end, which
    # the next round's re-freeze discarded: more linearisations and residual passes than rounds + 1
    clocked, samples, motion = case
    n = counted(monkeypatch)
    with reading_rates():
        out = fit_motion(samples, clocked, None if start == "readings" else 1.01 * motion)
    assert out.converged and out.rounds >= 1
    assert n["linearize"] == out.rounds + 1, (n, out.rounds)  # one per held trajectory, the last the result's
    assert n["residuals"] == out.rounds, (n, out.rounds)  # one step's cost each (halvings: only their samples)


def test_the_same_fixed_point_as_solving_each_round(case, monkeypatch):
    clocked, samples, _ = case
    with reading_rates():
        one = fit_motion(samples, clocked)
        monkeypatch.setattr(rounds, "MOTION_ROUND_STEPS", MOTION_ITERATIONS)  # each held trajectory solved
        solved = fit_motion(samples, clocked)
    assert one.converged and solved.converged
    assert one.step < rounds.ROUND_STD and one.gain < rounds.ROUND_GAIN
    assert abs(one.loglik - solved.loglik) < rounds.ROUND_GAIN, (one.loglik, solved.loglik)
