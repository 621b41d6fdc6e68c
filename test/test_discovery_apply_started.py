"""``discover --apply``'s check starts its two whole-recording motion fits from discover's own ML motions.

The fits-better check scores the model discover started from and the model with the findings, each a motion fit of
the whole recording (helper-65's profile of whole exp_3: the check was 167 of 519 s).  Discover has already fitted
both motions (its first fit, its last); the check's fits start there (:class:`~imu_array_ros.discovery.apply.
StartedScorer`) rather than from the fusion: the same fit to the same criterion, so the same score to the fit's
tolerance (where a further step gains < ROUND_GAIN; the trajectory rounds' fixed point is met to a few times that),
in fewer linearisations."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import imu_array_ros.calibration.scoring as scoring
import imu_array_ros.discovery.apply as apply
from imu_array_ros.calibration.scoring import WindowScorer
from imu_array_ros.discovery.apply import findings_calibration
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.fitting.rounds import ROUND_GAIN

from conftest import clocked_twist_case

STAMPS = (np.arange(150) * 16_000_000).astype(np.int64)  # 150 reads at 62.5 Hz


@pytest.fixture(scope="module")
def case():
    """(start, found, samples, ML motion under start, ML motion under found): sample clocks on 8 corner IMUs
    (nonlinear terms: the scores are motion fits); the found model is the simulated one, the start the same with
    imu_2's time offset 0.4 ms off."""
    found, samples, _ = clocked_twist_case(520917, STAMPS)
    offsets = found.terms["time_offset"].values.copy()
    offsets[1] += 4e-4
    start = found.with_terms(time_offset=offsets)
    return start, found, samples, fit_motion(samples, start).motion, fit_motion(samples, found).motion


def _discovery(found, base_motion, after_motion):
    return SimpleNamespace(findings=[], model=found, baseline=SimpleNamespace(loglik=0.0, motion=base_motion),
                           after=SimpleNamespace(loglik=0.0, motion=after_motion))


def test_the_checks_fits_start_from_discovers_motions(case, monkeypatch, tmp_path):
    """Fails before StartedScorer: both scores were fitted from the fusion's motion (scoring.fit_motion)."""
    start, found, samples, base_motion, after_motion = case
    starts, fused = [], []

    def recording(target, into):
        def fit(samples, model, motion0=None, **kwargs):
            into.append((model, None if motion0 is None else np.array(motion0)))
            return target(samples, model, motion0, **kwargs)
        return fit
    monkeypatch.setattr(apply, "fit_motion", recording(fit_motion, starts), raising=False)
    monkeypatch.setattr(scoring, "fit_motion", recording(fit_motion, fused))
    cal = findings_calibration(_discovery(found, base_motion, after_motion), samples, start=start)
    assert not fused  # no fit from the fused motion
    assert [m is found for m, _ in starts] == [True, False]  # the new model (the score), then the start (the check)
    assert np.array_equal(starts[0][1], after_motion) and np.array_equal(starts[1][1], base_motion)
    assert cal.score == pytest.approx(float(fit_motion(samples, found, after_motion).loglik), abs=0)


def test_a_started_score_is_the_fused_starts_to_the_fits_tolerance(case, monkeypatch):
    from imu_array_ros.discovery.apply import StartedScorer

    start, found, samples, base_motion, after_motion = case
    count = [0]
    linearize = Problem.linearize

    def counted(self, *args, **kwargs):
        count[0] += 1
        return linearize(self, *args, **kwargs)
    monkeypatch.setattr(Problem, "linearize", counted)
    started = StartedScorer(samples, [(start, base_motion), (found, after_motion)])
    for model in (start, found):
        count[0] = 0
        fused = WindowScorer(samples)(model)
        n_fused = count[0]
        count[0] = 0
        value = started(model)
        assert count[0] < n_fused  # fewer linearisations: it starts at the optimum
        # the fit stops where a step would gain < ROUND_GAIN on the frozen trajectory; the fixed point of the rounds
        # is met to less than that: 0.13 apart here (of 2.2e5), as a start from the fusion and one from
        # initial_motion already are (the check's numbers were never closer)
        assert abs(value - fused) <= 10 * ROUND_GAIN
    assert started(found) > started(start) + 10  # the start's offset is a worse model of these samples
    other = start.with_terms()  # a model not discover's (a file on disk): the fused start, as WindowScorer
    assert started(other) == WindowScorer(samples)(other)


def test_without_a_motion_it_is_the_window_scorer(case):
    from imu_array_ros.discovery.apply import StartedScorer

    start, found, samples, _, _ = case
    started = StartedScorer(samples, [(start, None), (found, np.zeros((3, 9)))])  # none; another length
    assert started(start) == WindowScorer(samples)(start) and started(found) == WindowScorer(samples)(found)
