"""The misfit-robust (sandwich) covariance of the fitting engine (imu_array_ros/fitting/robust.py): the
per-sample scores add up to the reduced gradient, the time-block estimate of a long-run variance is right
for a correlated series with gaps, the sandwich equals the CRB when the model is exact and covers the truth
when the noise is time-correlated (where the CRB does not), and Huber reweighting resists outliers.

Monte Carlo: fixed seeds; each study has 10 recordings x 9 free coordinates = 90 z-scores, so a coverage of
95 % is measured to +- 2.3 % (binomial std, more with the correlation within a recording)."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.fitting.gauge import Gauge
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.fitting.robust import MIN_BLOCKS, blocked_covariance, huber_sigma, sample_influence
from imu_array_ros.simulation.perturb import perturb
from imu_array_ros.simulation.simulator import simulate_twist
from test_fit_terms import subset_model

#: four IMUs of the 32-IMU array (three positions free), recordings of SECONDS at RATE
IMUS, SECONDS, RATE, RUNS = (0, 3, 12, 15), 30.0, 100.0, 10


def ar1(rng: np.random.Generator, shape: tuple, rho: float, std: float) -> np.ndarray:
    """Stationary AR(1) noise along axis 0 with lag-1 correlation rho and marginal std ``std``."""
    e = rng.normal(size=shape) * std * np.sqrt(1 - rho ** 2)
    x = np.empty(shape)
    x[0] = rng.normal(size=shape[1:]) * std
    for i in range(1, shape[0]):
        x[i] = rho * x[i - 1] + e[i]
    return x


def relative_errors(res, truth):
    """Position errors relative to the reference (imu 0, held), (K-1, 3)."""
    est = res.model.positions - res.model.positions[0]
    return (est - (truth.positions - truth.positions[0]))[1:]


def monte_carlo(correlated: bool):
    """z-scores of the CRB and of the sandwich, and their std ratio, over RUNS recordings."""
    nominal = subset_model(IMUS)
    z_crb, z_rob, ratio, plateau = [], [], [], []
    for seed in range(RUNS):
        rng = np.random.default_rng(7000 + seed)
        truth = perturb(nominal, rng, {"position": 2e-3})
        samples, _ = simulate_twist(truth, SECONDS, RATE, rng)
        if correlated:  # unmodelled: AR(1) accelerometer noise, 3x the white noise the model assumes
            samples.accel += ar1(rng, samples.accel.shape, 0.8, 3 * float(nominal.acc_std[0, 0]))
        res = fit_terms(samples, nominal, ["position"])
        err = relative_errors(res, truth)
        z_crb.append(err / res.std["position"][1:])
        z_rob.append(err / res.std_robust["position"][1:])
        ratio.append(res.std_robust["position"][1:] / res.std["position"][1:])
        plateau.append(res.sandwich.plateau)
        assert res.sandwich.blocks >= MIN_BLOCKS
    return (np.concatenate(z_crb).ravel(), np.concatenate(z_rob).ravel(), np.concatenate(ratio).ravel(),
            np.array(plateau))


def test_scores_add_up_to_the_reduced_gradient(rng):
    """sum_n u_n = g_red at any point (here away from the optimum), in every gauge coordinate."""
    nominal = subset_model(IMUS)
    truth = perturb(nominal, rng, {"position": 2e-3, "gyroscope_gain": 1e-2})
    samples, motion = simulate_twist(truth, 1.0, RATE, rng)
    prob = Problem(samples, nominal, ("position", "gyroscope_gain"), np.arange(4))
    prob.chunk = 17
    x = np.concatenate([motion.omega, motion.omega_dot, motion.specific_force], axis=1)
    lin = prob.linearize(nominal, x)
    u = sample_influence(prob, nominal, x, lin, np.eye(prob.m))
    np.testing.assert_allclose(u.sum(axis=0), lin.g, rtol=1e-9, atol=1e-9 * np.abs(lin.g).max())
    assert np.abs(lin.g).max() > 0


def test_blocks_estimate_the_long_run_variance_with_gaps():
    """An AR(1) series (long-run variance (1 + rho) / (1 - rho) per sample) with a tenth of the samples
    dropped in runs: the block estimate is within its sampling noise of the truth; the per-sample (level-0)
    variance is far below it."""
    rho, n, reps = 0.9, 20000, 20
    est = []
    for seed in range(reps):
        rng = np.random.default_rng(seed)
        x = ar1(rng, (n, 2), rho, 1.0)
        stamps = np.arange(n, dtype=np.int64) * 10_000_000
        keep = np.ones(n, dtype=bool)
        for start in rng.integers(0, n - 200, 10):
            keep[start:start + 200] = False  # gaps: blocks are in time
        rc = blocked_covariance(x[keep], stamps[keep])
        truth = keep.sum() * (1 + rho) / (1 - rho)
        est.append(np.diag(rc.covariance) / truth)
        assert rc.plateau and rc.blocks >= MIN_BLOCKS
        assert rc.levels[0][2] == 1.0 and rc.levels[-1][2] > 5  # the plateau is far above level 0
    est = np.array(est)
    assert 0.85 < est.mean() < 1.1, est.mean()  # mean of 40 estimates, each with ~20 % noise


def test_sandwich_equals_the_crb_when_the_model_is_exact():
    """White noise, model exact: the sandwich std agrees with the CRB (ratio averaged over parameters) and both
    cover the truth with their 95 % intervals."""
    z_crb, z_rob, ratio, plateau = monte_carlo(correlated=False)
    assert 0.9 < ratio.mean() < 1.1, ratio.mean()
    assert 0.8 < np.sqrt(np.mean(z_rob ** 2)) < 1.25
    assert 0.90 <= np.mean(np.abs(z_rob) < 1.96) <= 0.98, np.mean(np.abs(z_rob) < 1.96)
    assert 0.90 <= np.mean(np.abs(z_crb) < 1.96) <= 0.98
    assert plateau.all()


def test_sandwich_covers_when_the_noise_is_time_correlated():
    """Unmodelled time-correlated noise: the CRB intervals miss most truths, the sandwich's cover 90-98 %."""
    z_crb, z_rob, ratio, _ = monte_carlo(correlated=True)
    assert np.mean(np.abs(z_crb) < 1.96) < 0.5, np.mean(np.abs(z_crb) < 1.96)
    assert 0.90 <= np.mean(np.abs(z_rob) < 1.96) <= 0.98, np.mean(np.abs(z_rob) < 1.96)
    assert ratio.mean() > 4


def test_huber_sigma_downweights_only_the_outliers():
    r = np.random.default_rng(3).normal(size=(1000, 2, 6)) * 2.0
    r[5, 0, 1] = 50.0
    r[:, 1, 5] = np.nan  # an axis masked throughout keeps its sigma
    sigma = np.full(r.shape, 0.1)
    out = huber_sigma(r, sigma)
    scale = out[:, 0, 0][np.abs(r[:, 0, 0]) < 1.0]
    np.testing.assert_allclose(scale, scale[0])
    assert 0.18 < scale[0] < 0.22  # the axis' robust scale (2 x sigma)
    assert out[5, 0, 1] > 2.5 * scale[0]  # 50 / 2 / 1.345 ~ 18.6 -> sqrt: 4.3x
    np.testing.assert_allclose(out[:, 1, 5], 0.1)


def test_huber_fit_resists_outliers():
    """1 % of the accelerometer readings hit by 2 m/s^2 spikes: the Huber fit's position errors are much
    smaller than the plain fit's, and close to what the clean recording gives."""
    nominal = subset_model(IMUS)
    rng = np.random.default_rng(11)
    truth = perturb(nominal, rng, {"position": 2e-3})
    samples, _ = simulate_twist(truth, 5.0, RATE, rng)
    clean = fit_terms(samples, nominal, ["position"])
    hit = rng.random(samples.accel.shape) < 0.01
    samples.accel = samples.accel + hit * rng.choice([-2.0, 2.0], size=hit.shape)
    plain = fit_terms(samples, nominal, ["position"])
    huber = fit_terms(samples, nominal, ["position"], robust="huber")
    rms = lambda res: float(np.sqrt(np.mean(relative_errors(res, truth) ** 2)))  # noqa: E731
    assert huber.huber_rounds == 3 and huber.converged
    assert rms(huber) < 0.5 * rms(plain), (rms(huber), rms(plain))
    assert rms(huber) < 1.6 * rms(clean), (rms(huber), rms(clean))


def test_sandwich_can_be_skipped_and_robust_must_be_known(rng):
    nominal = subset_model(IMUS)
    samples, _ = simulate_twist(nominal, 1.0, RATE, rng)
    res = fit_terms(samples, nominal, ["position"], sandwich=False)
    assert res.covariance_robust is None and res.std_robust == {} and res.sandwich is None
    from imu_array_ros.errors import CalibrationError
    with pytest.raises(CalibrationError, match="robust must be"):
        fit_terms(samples, nominal, ["position"], robust="tukey")


def test_sandwich_in_the_mean_gauge_is_the_reference_gauge_one_moved():
    """Gauge-invariant combinations (differences of positions) have the same sandwich variance in both gauges."""
    nominal = subset_model(IMUS)
    rng = np.random.default_rng(5)
    truth = perturb(nominal, rng, {"position": 2e-3})
    samples, _ = simulate_twist(truth, 5.0, RATE, rng)
    ref = fit_terms(samples, nominal, ["position"])
    mean = fit_terms(samples, nominal, ["position"], gauge="mean")
    d = np.zeros(12)
    d[3], d[9] = 1.0, -1.0  # imu 1 x - imu 3 x
    v_ref, v_mean = d @ ref.covariance_robust @ d, d @ mean.covariance_robust @ d
    assert abs(v_ref / v_mean - 1) < 0.05, (v_ref, v_mean)
    assert isinstance(Gauge, type)
