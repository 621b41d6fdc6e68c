"""The kept Schur blocks (:func:`imu_array_ros.fitting.problem.keep_schur`, discovery's refits): the motion step
read from a linearisation's G_n is the step recomputed from the Jacobians, off by default (the calibrations
unchanged), bounded in memory, and a fit with them reaches the same estimate."""

from __future__ import annotations

import numpy as np

import imu_array_ros.fitting.problem as problem
from imu_array_ros.fitting.engine import fit_terms, keep_schur
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.model.terms import candidate_names
from imu_array_ros.simulation.motion import random_motion
from imu_array_ros.simulation.perturb import perturb
from imu_array_ros.simulation.simulator import simulate_measurements
from test_fit_terms import RATE, SUBSET, subset_model
from test_sensor_terms import SIZES

#: a timing term (derivatives along the trajectory), a geometric one and an intrinsic one
FREE = ("time_offset", "position", "gyroscope_gain")


def _recording(seed: int, n: int):
    rng = np.random.default_rng(seed)
    model = perturb(subset_model(SUBSET[:4]), rng, {t: SIZES[t] for t in candidate_names() if t != "position"})
    truth = random_motion(n, 6.0, 60.0, rng, rate_hz=RATE)
    motion = np.concatenate([truth.omega, truth.omega_dot, truth.specific_force], axis=1)
    return model, simulate_measurements(model, truth, rng), motion + rng.normal(0, 0.05, motion.shape)


def test_kept_g_gives_the_recomputed_motion_step():
    seed = int(np.random.default_rng().integers(1 << 30))
    model, samples, motion = _recording(seed, 40)
    fitted = np.array([1, 2, 3])
    steps = []
    for keep in (False, True):
        prob = Problem(samples, model, FREE, fitted, keep_g=keep)
        prob.chunk = 7  # several chunks
        lin = prob.linearize(model, motion)
        assert (lin.G is not None) == keep
        dtheta = np.linalg.lstsq(lin.S, lin.g, rcond=None)[0]
        steps.append(prob.motion_step(model, motion, lin, dtheta))
    assert np.all(steps[1] != 0)
    np.testing.assert_allclose(steps[1], steps[0], rtol=1e-9, atol=1e-12 * np.abs(steps[0]).max(),
                               err_msg=f"seed {seed}")


def test_off_by_default_on_in_the_context_and_bounded(monkeypatch):
    model, samples, motion = _recording(3, 12)
    fitted = np.array([0, 1])
    assert Problem(samples, model, FREE, fitted).linearize(model, motion).G is None
    with keep_schur():
        prob = Problem(samples, model, FREE, fitted)
        lin = prob.linearize(model, motion)
        assert lin.G.shape == (12, 9, prob.m)
        assert prob.linearize(model, motion, free=False).G is None  # nothing to keep for the motion alone
        assert prob.linearize(model, motion, gauge_point=True).G is None
        monkeypatch.setattr(problem, "KEEP_G_BYTES", 8 * 12 * 9 * prob.m - 1)  # one float short
        assert prob.linearize(model, motion).G is None
    assert Problem(samples, model, FREE, fitted).linearize(model, motion).G is None  # off again outside


def test_a_fit_with_kept_g_reaches_the_same_estimate():
    seed = int(np.random.default_rng().integers(1 << 30))
    model, samples, _ = _recording(seed, 60)
    start = model.with_terms(time_offset=np.zeros_like(model.terms["time_offset"].values))
    fits = [fit_terms(samples, start, ["time_offset"], keep_g=keep, sandwich=False,
                       max_iterations=8) for keep in (False, True)]
    sd = np.sqrt(np.diag(fits[0].covariance))
    est = sd > 0
    assert est.any()
    # the same Levenberg-Marquardt path to rounding: the estimates agree far inside their standard deviations
    np.testing.assert_array_less(np.abs(fits[1].theta - fits[0].theta)[est], 1e-6 * sd[est], err_msg=f"seed {seed}")
    assert abs(fits[1].loglik_after - fits[0].loglik_after) < 1e-6 * max(1.0, abs(fits[0].loglik_after))
