"""``discover --apply``'s fits-better check decided by a lower bound of the new model's score when it can be.

A score is the log-likelihood with every sample's motion at its ML estimate: for a model with non-linear terms a
motion fit of the whole recording (whole exp_3: the --apply check's one fit, ~14 CPU s).  The log-likelihood at any
motion is at most that maximum, so the new model at discover's own ML motion of it bounds its score from below;
when the bound clears the start's score, check (c) holds without the fit (:mod:`imu_array_ros.discovery.apply`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import imu_array_ros.calibration.scoring as scoring
from imu_array_ros.discovery.apply import findings_calibration
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.model.description import load_description

from conftest import clocked_twist_case

STAMPS = (np.arange(150) * 16_000_000).astype(np.int64)  # 150 reads at 62.5 Hz


@pytest.fixture(scope="module")
def case():
    """(start, found, samples, ML motion under found): sample clocks on 8 corner IMUs (non-linear terms: the
    scores are motion fits); found is the simulated model, start the same with imu_2's time offset 0.4 ms off."""
    found, samples, _ = clocked_twist_case(520917, STAMPS)
    offsets = found.terms["time_offset"].values.copy()
    offsets[1] += 4e-4
    start = found.with_terms(time_offset=offsets)
    return start, found, samples, fit_motion(samples, found).motion


def _discovery(found, after_motion):
    return SimpleNamespace(findings=[], model=found, baseline=SimpleNamespace(loglik=0.0),
                           after=SimpleNamespace(loglik=0.0, motion=after_motion))


def _fits(monkeypatch) -> list:
    """[model] of every score computed (scoring.window_loglik: a motion fit for these models)."""
    calls, score = [], scoring.window_loglik

    def counted(samples, model):
        calls.append(model)
        return score(samples, model)
    monkeypatch.setattr(scoring, "window_loglik", counted)
    return calls


def test_the_bound_is_the_fits_own_log_likelihood_and_below_it_elsewhere(case):
    from imu_array_ros.discovery.apply import motion_loglik

    start, found, samples, motion = case
    for model in (start, found):
        fit = fit_motion(samples, model, motion)
        assert motion_loglik(samples, model, fit.motion) == pytest.approx(fit.loglik, rel=1e-12, abs=1e-6)
        moved = fit.motion * (1 + 0.01 * np.cos(np.arange(len(motion))))[:, None]
        assert motion_loglik(samples, model, moved) < fit.loglik  # another motion: below the maximum
    assert motion_loglik(samples, found, motion) == pytest.approx(fit_motion(samples, found, motion).loglik,
                                                                  abs=0.5)


def test_a_bound_that_clears_the_start_needs_no_fit_of_the_new_model(case, monkeypatch, tmp_path):
    """Fails before the bound: the new model was fitted (scoring.window_loglik) for the check."""
    start, found, samples, motion = case
    fits = _fits(monkeypatch)
    cal = findings_calibration(_discovery(found, motion), samples, start=start)
    assert [m is start for m in fits] == [True]  # the start scored once, the new model never
    assert cal.score is None
    from imu_array_ros.discovery.apply import install_findings

    desc = load_description(root_corners())
    out = tmp_path / "out.yaml"
    install_findings(cal, desc, out)  # nothing on file: no score needed
    assert out.exists() and [m is start for m in fits] == [True]
    install_findings(cal, desc, out)  # a file to compare with: both scored now (the new model exactly)
    assert len(fits) == 3 and fits[1] is found and (out.parent / "out.yaml.bak").exists()


def test_a_bound_that_does_not_clear_falls_back_to_the_fit(case, monkeypatch):
    start, found, samples, motion = case
    fits = _fits(monkeypatch)
    far = motion + 5.0  # a motion far from the ML: its log-likelihood is below the start's score
    cal = findings_calibration(_discovery(found, far), samples, start=start)
    assert sorted(m is found for m in fits) == [False, True]  # the start and the new model, each once
    assert cal.score == pytest.approx(scoring.WindowScorer(samples)(found))


def test_a_worse_model_is_still_refused(case):
    start, found, samples, _ = case
    worse = fit_motion(samples, start).motion  # the worse model (the offset 0.4 ms off) at its own ML motion
    with pytest.raises(CalibrationError, match="worse"):
        findings_calibration(_discovery(start, worse), samples, start=found)


def root_corners():
    from pathlib import Path

    return Path(__file__).resolve().parents[1] / "config" / "mimu4444bt_corners.yaml"
