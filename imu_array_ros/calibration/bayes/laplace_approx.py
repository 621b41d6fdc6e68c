"""The Laplace (Gaussian / Cramér-Rao) approximation of the position posterior.

The maximum-likelihood positions on the same samples and their Cramér-Rao covariance
(:func:`~imu_array_ros.calibration.geometry.calibrate_geometry`), combined with the prior, and
moved by one Newton step on the -T/2 log|H^T Omega H| term of the marginal likelihood (eq. 23)
that the profile likelihood leaves out.  The sampler starts its chains from it, shapes its
proposals by it, and reports where the chains disagree with it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from imu_array_ros.calibration.bayes.problem import BayesProblem
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["Laplace", "laplace", "sample_gyro_std", "logdet_correction"]


@dataclass
class Laplace:
    """Gaussian approximation of the posterior: mean (d,), covariance (d, d); the ML (BCD/joint)
    estimate and its Cramér-Rao covariance it combines with the prior."""

    mean: np.ndarray
    covariance: np.ndarray
    ml: np.ndarray
    crb: np.ndarray


def sample_gyro_std(problem: BayesProblem) -> np.ndarray:
    """(K, 3) gyroscope noise std that gives the ML/CRB of :func:`laplace` the information about omega
    that eq. 30 gives the likelihood on average: the sample covariance S_t of the K gyroscopes is used as
    the covariance of omega itself, so K gyroscopes of std s per axis with K / s^2 = mean_t (S_t^-1)_jj
    carry the same (time-averaged) information (the sample covariance varies with t, the model's
    noise does not: an approximation, as the Laplace one is)."""
    cov = problem.chol @ problem.chol.transpose(0, 2, 1)
    info = np.linalg.inv(cov).mean(axis=0)
    k = len(problem.positions)
    return np.tile(np.sqrt(k / np.diag(info)), (k, 1))


def laplace(problem: BayesProblem, samples: ImuSamples, model: SensorModel, *, method: str = "joint") -> Laplace:
    """The ML estimate of the positions on the same samples
    (:func:`~imu_array_ros.calibration.geometry.calibrate_geometry`, with the same noise; with eq. 30's
    sample covariance, the gyroscope std of :func:`sample_gyro_std`) and its CRB, combined with a Gaussian
    prior (precisions add); with a uniform prior the CRB alone, its mean clipped into the box.  The mean
    then takes the :func:`logdet_correction` step."""
    from imu_array_ros.calibration.geometry import calibrate_geometry

    m = model
    if problem.accel_std is not None:
        m = replace(model, acc_std=np.asarray(problem.accel_std, dtype=float))
    if problem.omega_covariance == "sample":
        m = replace(m, gyro_std=sample_gyro_std(problem))
    geo = calibrate_geometry(samples, m, reference=problem.reference, method=method, min_excitation=0.0)
    # the geometry result keeps the reference at its position only up to the common shift: re-anchor
    pos = geo.positions - geo.positions[problem.reference] + problem.positions[problem.reference]
    ml = problem.theta_of(pos)
    idx = (3 * problem.free[:, None] + np.arange(3)).reshape(-1)
    crb = geo.covariance[np.ix_(idx, idx)]
    crb = 0.5 * (crb + crb.T)
    pr = problem.prior
    if pr.kind == "gaussian":
        info = np.linalg.inv(crb) + np.diag(1.0 / pr.std ** 2)
        cov = np.linalg.inv(info)
        mean = cov @ (np.linalg.solve(crb, ml) + pr.mean / pr.std ** 2)
    else:
        cov, mean = crb, ml
    mean = logdet_correction(problem, mean, cov)
    if pr.kind == "uniform":
        mean = np.clip(mean, pr.mean - pr.std, pr.mean + pr.std)
    return Laplace(mean=mean, covariance=0.5 * (cov + cov.T), ml=ml, crb=crb)


def logdet_correction(problem: BayesProblem, mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``mean`` (d,) moved by one Newton step on -T/2 log|H^T Omega H|.

    The ML estimate maximises the profile likelihood (motion fitted); the posterior's marginal
    likelihood integrates the linear motion out, which adds -T/2 log|H^T Omega H| (eq. 23; exponent
    -1/2, not the -1 eq. 25-26 print), a function of the positions that pulls towards a smaller array.
    One Newton step on the sum, from the Gaussian combination of ML and prior (where the rest of the
    gradient is zero), with the Laplace covariance ``cov`` (d, d) as the inverse Hessian.  (One step
    only: repeating it with this term's gradient alone would add the same shift again.)"""
    t, d = problem.n_samples, len(mean)
    h = 1e-7
    grad = np.empty(d)
    for j in range(d):  # d small (3 per IMU); quadratic() is one product
        e = np.zeros(d)
        e[j] = h
        up, down = problem.quadratic(mean + e), problem.quadratic(mean - e)
        if up is None or down is None:
            return mean
        grad[j] = (up[3] - down[3]) / (2 * h)
    return mean + cov @ (-0.5 * t * grad)
