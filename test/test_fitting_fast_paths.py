"""The fitting engine's shortcuts for discovery's speed (issue 23 item 7) give the answers of the long way: a timing
round's optimiser that skips the linearisation at its last step (the next round re-freezes and linearises there),
and the batched inverse of the motion's Cholesky factors (:func:`~imu_array_ros.fitting.schur.inverse_lower`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import imu_array_ros.fitting.engine as engine
import imu_array_ros.fitting.rounds as rounds
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.fitting.optimiser import levenberg_marquardt
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.fitting.reading_rates import reading_rates
from imu_array_ros.fitting.schur import MOTION_RTOL, factor, inverse_lower

from conftest import clocked_twist_case

ROOT = Path(__file__).resolve().parents[1]
STAMPS = (np.arange(120) * 16_000_000).astype(np.int64)  # 120 reads at 62.5 Hz


@pytest.fixture(scope="module")
def case():
    """Sample clocks on 8 corner IMUs, hand-like twisting (test_timing_rounds.py's recording, another seed)."""
    return clocked_twist_case(470213, STAMPS)


def _fit(case, monkeypatch, last_lin: bool | None):
    """The time offsets' and gyroscope gains' refit as discovery confirms it (cost_tolerance), counting the
    linearisations; last_lin True: every optimiser call linearises at its last step (the long way)."""
    clocked, samples, motion = case
    count = [0]
    linearize = Problem.linearize

    def counted(self, *args, **kwargs):
        count[0] += 1
        return linearize(self, *args, **kwargs)
    monkeypatch.setattr(Problem, "linearize", counted)
    if last_lin is not None:
        def long_way(*args, **kwargs):
            kwargs["last_lin"] = last_lin
            return levenberg_marquardt(*args, **kwargs)
        monkeypatch.setattr(engine, "levenberg_marquardt", long_way)
        monkeypatch.setattr(rounds, "levenberg_marquardt", long_way)
    with reading_rates():
        fit = fit_terms(samples, clocked, ["time_offset", "gyroscope_gain"], motion0=motion, max_iterations=30,
                        sandwich=False, cost_tolerance=0.1)
    return fit, count[0]


def test_skipping_the_last_linearisation_of_a_round_changes_no_iterate(case, monkeypatch):
    long, n_long = _fit(case, monkeypatch, True)
    monkeypatch.undo()
    short, n_short = _fit(case, monkeypatch, None)
    assert short.iterations == long.iterations and short.converged == long.converged
    assert n_short < n_long  # the shortcut was taken
    assert np.array_equal(short.theta, long.theta)  # bit for bit
    assert np.array_equal(short.motion, long.motion, equal_nan=True)
    assert short.loglik_after == long.loglik_after and short.loglik_before == long.loglik_before
    assert np.array_equal(short.covariance, long.covariance)


def test_inverse_lower_is_the_inverse_of_the_cholesky_factors():
    rng = np.random.default_rng(905417)
    a = rng.normal(size=(300, 40, 15))
    a = np.matmul(a.transpose(0, 2, 1), a)
    a[:5] *= rng.uniform(1e-6, 1e6, size=(5, 1, 1))  # scales far apart
    low = np.linalg.cholesky(a)
    ref = np.linalg.inv(low)
    got = inverse_lower(low)
    assert np.all(np.triu(got, 1) == 0.0)
    scale = np.abs(ref).max(axis=(1, 2), keepdims=True)
    assert np.max(np.abs(got - ref) / scale) < 1e-12
    eye = np.broadcast_to(np.eye(15), a.shape)
    assert np.max(np.abs(np.matmul(got, low) - eye)) < 1e-12


def test_factor_matches_numpys_inverse_also_for_unidentified_samples():
    rng = np.random.default_rng(661032)
    j = rng.normal(size=(200, 48, 15))
    a = np.matmul(j.transpose(0, 2, 1), j)
    a[10] = np.outer(j[10, 0], j[10, 0])  # rank one: not identified (the ridge)
    a[20, 14, :] = a[20, :, 14] = 0.0  # a coordinate no reading informs (held)
    linv, ok, exact = factor(a)
    assert not ok[10] and not exact[10] and exact[20]
    d = np.sqrt(np.where(np.einsum("nii->ni", a) > 0, np.einsum("nii->ni", a), 1.0))
    for n in (0, 10, 20):  # the same matrix as before: inv of the Cholesky factor of the scaled (held, ridged) A
        an = a[n] / np.outer(d[n], d[n])
        if n == 20:
            an[14, 14] = 1.0
        if n == 10:
            an = an + np.eye(15)
        ref = np.linalg.inv(np.linalg.cholesky(an)) / d[n][None, :]
        assert np.allclose(linv[n], ref, rtol=1e-11, atol=1e-11 * np.abs(ref).max())
    assert MOTION_RTOL > 0


def test_backtracking_reaches_the_fixed_point_of_the_damped_path(case, monkeypatch):
    """Discovery's refits backtrack along the Gauss-Newton direction before damping (fitting.optimiser
    .backtracking): another path to the same fixed point, within the rounds' criterion (0.05 std per step) and the
    refit's cost tolerance; off by default.  The simulated recording's undamped steps are all accepted, so the first
    trial of every step (and its settled motion) is rejected here by force, as on the real exp_1 refit."""
    from imu_array_ros.fitting.optimiser import backtracking
    clocked, samples, motion = case
    run = dict(motion0=motion, max_iterations=30, sandwich=False, cost_tolerance=0.1)
    free = ["time_offset", "gyroscope_gain"]
    with reading_rates():
        plain = fit_terms(samples, clocked, free, **run)
        with backtracking(False):
            off = fit_terms(samples, clocked, free, **run)
    assert np.array_equal(off.theta, plain.theta)  # off by default
    linearize, residuals, pending = Problem.linearize, Problem.residuals, [0]

    def marked(self, model, motion, *, free=True, gauge_point=False):
        pending[0] = 2 if free and not gauge_point else pending[0]  # a step's trial and its settled motion
        return linearize(self, model, motion, free=free, gauge_point=gauge_point)

    def rejected(self, *args):
        r = residuals(self, *args)
        if pending[0]:
            pending[0] -= 1
            return r + 1e3
        return r
    monkeypatch.setattr(Problem, "linearize", marked)
    monkeypatch.setattr(Problem, "residuals", rejected)
    with reading_rates():
        damped = fit_terms(samples, clocked, free, **run)
        with backtracking():
            back = fit_terms(samples, clocked, free, **run)
    assert damped.converged and back.converged
    assert not np.array_equal(back.theta, damped.theta)  # the two paths differ
    for fit in (damped, back):
        sd = np.sqrt(np.diag(plain.covariance))
        fitted = sd > 0
        assert np.max(np.abs(fit.theta - plain.theta)[fitted] / sd[fitted]) < 0.1
        assert abs(fit.loglik_after - plain.loglik_after) < 0.5
