"""What the sampler found: the chains, their diagnostics (ArviZ), and the calibration record."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from imu_array_ros.calibration.bayes.laplace_approx import Laplace
from imu_array_ros.calibration.bayes.problem import BayesProblem
from imu_array_ros.util.extras import require

if TYPE_CHECKING:  # pragma: no cover - annotations only (the sampler imports this module)
    from imu_array_ros.calibration.bayes.sampler import SamplerSettings

__all__ = ["BayesPosterior", "chain_diagnostics", "arviz", "imu_covariances"]


def arviz():
    """ArviZ (the ``[bayes]`` extra; a one-line error naming it when missing), imported without its
    refactoring notice."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        return require("arviz", "bayes", "the Bayesian calibration's diagnostics")


def chain_diagnostics(draws: np.ndarray, extra: np.ndarray | None = None) -> tuple[float, float, float]:
    """(min bulk ESS, min tail ESS, max rank-normalised split R-hat) over the coordinates of draws
    (C, M, d) (and the extra (C, M) series for R-hat), by ArviZ."""
    az = arviz()
    data = {"theta": draws}
    if extra is not None:
        data["extra"] = extra
    idata = az.convert_to_dataset(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bulk = az.ess(idata, var_names=["theta"], method="bulk")["theta"].values
        tail = az.ess(idata, var_names=["theta"], method="tail")["theta"].values
        rhat = np.concatenate([np.ravel(v.values) for v in az.rhat(idata).data_vars.values()])
    return float(np.nanmin(bulk)), float(np.nanmin(tail)), float(np.nanmax(rhat))


def imu_covariances(problem: BayesProblem, cov: np.ndarray) -> np.ndarray:
    """(K, 3, 3) each IMU's block of the covariance (d, d) of the free coordinates (zeros for the reference)."""
    out = np.zeros((len(problem.names), 3, 3))
    for j, k in enumerate(problem.free):
        out[k] = cov[3 * j:3 * j + 3, 3 * j:3 * j + 3]
    return out


@dataclass
class BayesPosterior:
    """What :func:`~imu_array_ros.calibration.bayes.sampler.sample_posterior` found.

    draws (C, M, d) after the warm-up; loglik, logprior (C, M); accepted (C, M);
    independence (C, M) which proposal was made; warmup: iterations per chain
    discarded; n_draws: N; acceptance (C,) of the random walk,
    acceptance_independence (C,); scale (C,) final step scales; summary:
    ArviZ's table (pandas) of every coordinate; ess_bulk_min, ess_tail_min,
    rhat_max; seconds (wall) and cpu_seconds (every process's CPU time);
    var_loglik: the tuning table [(N, variance)]; laplace: the Gaussian
    approximation it started from; warmup_trace (C, warm-up iterations): the
    log posterior during the warm-up.
    """

    problem: BayesProblem = field(repr=False)
    settings: SamplerSettings
    laplace: Laplace = field(repr=False)
    draws: np.ndarray = field(repr=False)
    loglik: np.ndarray = field(repr=False)
    logprior: np.ndarray = field(repr=False)
    accepted: np.ndarray = field(repr=False)
    independence: np.ndarray = field(repr=False)
    warmup: int
    n_draws: int
    acceptance: np.ndarray
    acceptance_independence: np.ndarray
    scale: np.ndarray
    summary: object = field(repr=False)
    ess_bulk_min: float
    ess_tail_min: float
    rhat_max: float
    converged: bool
    seconds: float
    cpu_seconds: float
    var_loglik: list
    runner: str
    warmup_trace: np.ndarray = field(default=None, repr=False)

    @property
    def names(self) -> tuple:
        return self.problem.names

    @property
    def free_names(self) -> list[str]:
        return [self.problem.names[i] for i in self.problem.free]

    @property
    def flat(self) -> np.ndarray:
        """(C*M, d) every draw."""
        return self.draws.reshape(-1, self.draws.shape[-1])

    @property
    def mean(self) -> np.ndarray:
        return self.flat.mean(axis=0)

    @property
    def covariance(self) -> np.ndarray:
        return np.cov(self.flat, rowvar=False)

    def positions_mean(self) -> np.ndarray:
        """(K, 3) posterior mean positions (the reference's held)."""
        return self.problem.full_positions(self.mean)

    def positions_std(self) -> np.ndarray:
        """(K, 3) posterior std (0 for the reference)."""
        std = np.zeros_like(self.problem.positions)
        std[self.problem.free] = np.sqrt(np.diag(self.covariance)).reshape(-1, 3)
        return std

    def imu_covariances(self) -> np.ndarray:
        """(K, 3, 3) posterior covariance of each IMU's position (zeros for the reference)."""
        return imu_covariances(self.problem, self.covariance)

    def inference_data(self):
        """The chains as ArviZ InferenceData: posterior ``position`` (chain, draw, imu, axis) in metres,
        sample_stats ``lp`` (log posterior up to a constant), ``log_likelihood_estimate``, ``accepted``."""
        az = arviz()
        c, m, _ = self.draws.shape
        return az.from_dict(
            posterior={"position": self.draws.reshape(c, m, -1, 3)},
            sample_stats={"lp": self.loglik + self.logprior, "log_likelihood_estimate": self.loglik,
                          "accepted": self.accepted},
            coords={"imu": self.free_names, "axis": ["x", "y", "z"]},
            dims={"position": ["imu", "axis"]})

    def record(self) -> dict:
        """The ``calibration:`` block of the written description."""
        from imu_array_ros.calibration.result import provenance

        p, s = self.problem, self.settings
        cov = self.imu_covariances()
        return {
            "method": "bayes: posterior of the accelerometer positions by pseudo-marginal Metropolis-Hastings "
                      "(carlsson2021 Alg. 1; Rao-Blackwellised likelihood eq. 26, "
                      f"{'correlated (rho %g)' % p.rho if p.rho > 0 else 'independent'} random numbers); "
                      "position = posterior mean, position_std = posterior std",
            **provenance(),
            "reference": p.names[p.reference],
            "samples": int(p.n_samples),
            "window": {"first_stamp_ns": int(p.stamps[0]), "last_stamp_ns": int(p.stamps[-1])},
            "prior": {"kind": p.prior.kind, ("std" if p.prior.kind == "gaussian" else "half_width"):
                      ([float(v) for v in p.prior.std[:3]] if np.all(p.prior.std.reshape(-1, 3) == p.prior.std[:3])
                       else {p.names[k]: [float(v) for v in row]
                             for k, row in zip(p.free, p.prior.std.reshape(-1, 3))})},
            "accelerometer_noise_std": float(np.mean(p.accel_std)),
            "omega_covariance": p.omega_covariance,
            "draws_per_sample": int(self.n_draws),
            "chains": int(self.draws.shape[0]),
            "iterations_per_chain": int(self.draws.shape[1]),
            "warmup_per_chain": int(self.warmup),
            "proposal": s.proposal,
            "acceptance_random_walk": [round(float(a), 4) for a in self.acceptance],
            "acceptance_independence": [round(float(a), 4) if np.isfinite(a) else None
                                        for a in self.acceptance_independence],
            "ess_bulk_min": float(self.ess_bulk_min),
            "ess_tail_min": float(self.ess_tail_min),
            "rhat_max": float(self.rhat_max),
            "converged": bool(self.converged),
            "seconds": round(float(self.seconds), 2),
            "cpu_seconds": round(float(self.cpu_seconds), 2),
            "position_covariance": {p.names[k]: [[float(v) for v in row] for row in cov[k]] for k in p.free},
        }

    def summary_line(self) -> str:
        return (f"{self.draws.shape[0]} chains x {self.draws.shape[1]} draws after {self.warmup} warm-up, N = "
                f"{self.n_draws}, random-walk acceptance {np.min(self.acceptance):.0%}-{np.max(self.acceptance):.0%}"
                + (f", independence {np.nanmean(self.acceptance_independence):.0%}"
                   if np.isfinite(self.acceptance_independence).any() else "") + "; "
                f"ESS bulk >= {self.ess_bulk_min:.0f}, tail >= {self.ess_tail_min:.0f}, R-hat <= {self.rhat_max:.4f}"
                f"{'' if self.converged else ' (NOT converged)'}; {self.seconds:.1f} s wall, "
                f"{self.cpu_seconds:.1f} core-s")
