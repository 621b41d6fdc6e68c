"""Running the PmMH chains: tuning N, warm-up, sampling to a target ESS and R-hat; comparing and installing.

:func:`sample_posterior` does what carlsson2021 Sec. III-C does by hand:

1. **N** (draws of omega per time sample): the smallest power of two whose
   Var[log p_N(y | theta)] at the Laplace mean is at most ``loglik_var``
   (paper: ~0.1; measured over ``VAR_REPLICATES`` sets of random numbers).
   If even ``MAX_DRAWS`` leaves it above ``UNTUNABLE`` times that, the data
   disagree with the noise model and :class:`CalibrationError` says so
   (a given ``n_draws`` skips the tuning).
2. **Starts**: ``chains`` (>= 2) points drawn from the Laplace approximation with
   twice its standard deviations (over-dispersed, as R-hat assumes).
3. **Warm-up** (discarded: the burn-in): rounds of ``chunk`` iterations per
   chain; after each, every chain's step scale moves toward the target
   acceptance (``target_acceptance``, within the paper's 7-23 %) and the
   proposal covariance toward the pooled draws' (shrunk to the Laplace one).
   It ends when the chains agree: split R-hat of every coordinate and of the
   log-likelihood over the second half of the whole warm-up so far (thinned) below ``WARMUP_RHAT`` and the
   acceptance within 7-35 %, after at least ``min_warmup`` iterations.  The
   kernel is then fixed, so the sampling rounds are plain (C)PmMH.
4. **Sampling** until the smallest bulk effective sample size over the
   coordinates reaches ``ess`` and the largest rank-normalised split R-hat is
   below ``rhat`` (ArviZ), or ``max_iterations`` per chain.

Chains run in parallel (:mod:`~imu_array_ros.calibration.bayes.runners`): worker processes by default
(``scheduler=None``), a Dask ``LocalCluster`` (``"local"``), an existing Dask scheduler (its address), or
in this process (``"serial"``), with the same draws everywhere.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from imu_array_ros.calibration.bayes.chain import ChunkResult, initial_state
from imu_array_ros.calibration.bayes.laplace_approx import Laplace
from imu_array_ros.calibration.bayes.moves import IndependenceT, RandomWalk
from imu_array_ros.calibration.bayes.posterior import BayesPosterior, arviz, chain_diagnostics
from imu_array_ros.calibration.bayes.problem import BayesProblem, loglik_variance
from imu_array_ros.calibration.bayes.runners import ChainRunner
from imu_array_ros.errors import CalibrationError

__all__ = ["SamplerSettings", "sample_posterior", "choose_draws", "laplace_agreement", "install_allowance",
           "PROPOSALS", "VAR_REPLICATES", "MAX_DRAWS", "UNTUNABLE", "WARMUP_RHAT", "WARMUP_KEEP", "AGREE_MEAN_Z",
           "AGREE_SD_RATIO"]

#: proposal of theta: "laplace": Gaussian random walk with the Laplace covariance (scaled), mixed with the
#: independence proposal; "isotropic": sigma_q I (carlsson2021 eq. 27)
PROPOSALS = ("laplace", "isotropic")
#: replicates of the log-likelihood estimate when tuning N
VAR_REPLICATES = 48
#: largest N tried
MAX_DRAWS = 1024
#: Var[log p_N] at N = MAX_DRAWS above UNTUNABLE x the target is an error, not a warning: with a
#: log-likelihood estimate of standard deviation >~ 1 a pseudo-marginal chain sticks for very long
#: (Doucet et al. 2015 put the optimum at 0.9-1.7 in variance); --draws runs anyway
UNTUNABLE = 10.0
#: split R-hat below which the warm-up counts as converged
WARMUP_RHAT = 1.05
#: draws per chain and warm-up round kept for the warm-up R-hat (thinned)
WARMUP_KEEP = 100


@dataclass
class SamplerSettings:
    """How :func:`sample_posterior` runs (module docstring); every default is the documented one.

    ``seed`` fixes the whole run (N tuning, starts, every chain's random numbers) whatever the scheduler.
    Two settings with one seed therefore share their random numbers (common random numbers: good for
    comparing costs, wrong for a two-sample test between the runs, which needs a seed per run).
    """

    chains: int = 4
    scheduler: str | None = None
    workers: int | None = None
    n_draws: int | None = None
    loglik_var: float = 0.1
    rho: float = 0.9
    proposal: str = "laplace"
    independence: float = 0.5
    target_acceptance: float = 0.2
    ess: float = 400.0
    rhat: float = 1.01
    chunk: int = 1000
    min_warmup: int = 2000
    max_warmup: int = 40000
    max_iterations: int = 400000
    seed: int = 0

    def check(self) -> None:
        if self.chains < 2:
            raise CalibrationError(f"chains {self.chains}: at least 2 are needed for R-hat")
        if self.proposal not in PROPOSALS:
            raise CalibrationError(f"proposal {self.proposal!r}: expected one of {', '.join(PROPOSALS)}")
        if not 0.0 <= self.rho < 1.0:
            raise CalibrationError(f"rho {self.rho}: must be in [0, 1)")
        if not 0.0 <= self.independence < 1.0:
            raise CalibrationError(f"independence {self.independence}: the probability must be in [0, 1)")
        if not 0.0 < self.target_acceptance < 1.0:
            raise CalibrationError(f"target acceptance {self.target_acceptance}: must be in (0, 1)")
        for name in ("chunk", "min_warmup", "max_warmup", "max_iterations"):
            if getattr(self, name) < 1:
                raise CalibrationError(f"{name} {getattr(self, name)}: must be >= 1")


# --------------------------------------------------------------------------- tuning N


def choose_draws(problem: BayesProblem, theta: np.ndarray, target: float, rng: np.random.Generator,
                 progress: Callable[[str], None] | None = None) -> tuple[int, list]:
    """Smallest power-of-two N with Var[log p_N] <= target at theta (capped at MAX_DRAWS); the table.

    N doubles from 1; when the variance, falling as 1/N, would need more than ``4 * MAX_DRAWS`` draws, the
    next measurement is at the cap (no time spent on the doublings in between).
    """
    table, n = [], 1
    while True:
        var = loglik_variance(problem.with_(n_draws=n), theta, VAR_REPLICATES, rng)
        table.append((n, var))
        if progress is not None:
            progress(f"tuning N: N = {n}, Var[log-likelihood estimate] = {var:.3g} (target {target:g})")
        if var <= target or n >= MAX_DRAWS:
            return n, table
        n = MAX_DRAWS if n * var / target > 4 * MAX_DRAWS else 2 * n


def _untunable(table: list, target: float) -> CalibrationError:
    """The error when even MAX_DRAWS draws leave the log-likelihood estimate too noisy to sample with."""
    n0, v0 = table[0]
    n1, v1 = table[-1]
    need = n1 * v1 / target
    return CalibrationError(
        f"the log-likelihood estimate is too noisy to sample: Var = {v1:.3g} at N = {n1} (target {target:g}; "
        f"{v0:.3g} at N = {n0}), so N ~ {need:.2g} draws per sample would be needed. The readings disagree with "
        "the noise model: calibrate the intrinsics first (the 'all' calibration), widen the accelerometer noise "
        "(accel_std), or give the draws per sample (n_draws) to run anyway (the chains will mix slowly)")


# --------------------------------------------------------------------------- the run


def _rw_acceptance(r: ChunkResult) -> float:
    """Acceptance rate of the random-walk proposals of a chunk (NaN: none made)."""
    rw = ~r.independence
    return float(r.accepted[rw].mean()) if rw.any() else float("nan")


def _initial_walk(proposal: str, lap_chol: np.ndarray, lap_cov: np.ndarray) -> RandomWalk:
    """The random walk the warm-up starts from: shaped by the Laplace covariance with 2.38 / sqrt(d), or
    (eq. 27) sigma_q I with sigma_q the typical Laplace std times 2.38 / sqrt(d)."""
    d = len(lap_chol)
    if proposal == "laplace":
        return RandomWalk(lap_chol, float(2.38 / np.sqrt(d)))
    return RandomWalk.isotropic(d, 2.38 / np.sqrt(d) * float(np.sqrt(np.mean(np.diag(lap_cov)))))


def _warm_up(runner: ChainRunner, states: list, settings: SamplerSettings, laplace: Laplace, say):
    """Rounds until the chains agree (module docstring, 3.); returns (states, warm-up iterations per chain,
    log-posterior trace (C, iterations), process CPU seconds of the rounds)."""
    d, lap_cov = len(laplace.mean), laplace.covariance
    mixing = states[0].independence is not None and states[0].independence_prob > 0
    cpu, warm, pooled, rounds, trace = 0.0, 0, [], [], []
    while True:
        out = runner.run(states, settings.chunk)
        cpu += sum(r.cpu_seconds for r in out)
        warm += settings.chunk
        acc = np.array([_rw_acceptance(r) for r in out])
        draws = np.stack([r.draws for r in out])
        trace.append(np.stack([r.loglik + r.logprior for r in out]))
        # R-hat over the second half of the whole warm-up so far (the window grows with it: a fixed
        # window shorter than a few autocorrelation times never agrees), thinned to bound memory
        thin = max(1, settings.chunk // WARMUP_KEEP)
        rounds.append((draws[:, ::thin], np.stack([r.loglik for r in out])[:, ::thin]))
        half = rounds[len(rounds) // 2:]
        _, _, rh = chain_diagnostics(np.concatenate([h[0] for h in half], axis=1),
                                     np.concatenate([h[1] for h in half], axis=1))
        states = [r.state for r in out]
        # step scale toward the target acceptance (Robbins-Monro on log scale)
        for s, a in zip(states, acc):
            s.walk = s.walk.rescaled(float(np.exp(1.5 * (a - settings.target_acceptance))))
        if settings.proposal == "laplace":  # proposals toward the draws' moments, shrunk to Laplace's by
            # the draws' effective size (autocorrelated warm-up draws carry little: ESS, not their count)
            pooled.append(draws[:, draws.shape[1] // 2:])
            pooled = pooled[-4:]
            recent = np.concatenate(pooled, axis=1)
            n_eff, _, _ = chain_diagnostics(recent)
            w = n_eff / (n_eff + 10.0 * d)
            flat = recent.reshape(-1, d)
            cov = w * np.cov(flat, rowvar=False) + (1 - w) * lap_cov
            try:
                new_shape = np.linalg.cholesky(cov)
            except np.linalg.LinAlgError:
                new_shape = None
            if new_shape is not None:  # the scale is relative to the shape: kept
                mean = w * flat.mean(axis=0) + (1 - w) * laplace.mean
                jump = IndependenceT(mean, new_shape) if mixing else None
                for s in states:
                    s.walk = s.walk.reshaped(new_shape)
                    if mixing:
                        s.independence = jump
        ind_acc = np.mean([r.accepted[r.independence].mean() for r in out if r.independence.any()]) \
            if mixing else float("nan")
        say(f"warm-up: {warm} iterations per chain, random-walk acceptance {acc.min():.0%}-{acc.max():.0%}"
            f"{f', independence {ind_acc:.0%}' if mixing else ''}, R-hat {rh:.3f}")
        if warm >= settings.min_warmup and rh < WARMUP_RHAT and np.all((acc > 0.07) & (acc < 0.35)):
            return states, warm, np.concatenate(trace, axis=1), cpu
        if warm >= settings.max_warmup:
            say(f"warning: warm-up stopped at {warm} iterations without the chains agreeing (R-hat {rh:.3f})")
            return states, warm, np.concatenate(trace, axis=1), cpu


def sample_posterior(problem: BayesProblem, laplace: Laplace, settings: SamplerSettings | None = None,
                     progress: Callable[[str], None] | None = None) -> BayesPosterior:
    """Tune, warm up and sample the posterior of ``problem`` (module docstring)."""
    settings = settings or SamplerSettings()
    settings.check()
    say = progress or (lambda text: None)
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    rng = np.random.default_rng(settings.seed)
    d = problem.dim
    if settings.n_draws is None:
        n_draws, table = choose_draws(problem, laplace.mean, settings.loglik_var, rng, say)
        if table[-1][1] > UNTUNABLE * settings.loglik_var:
            raise _untunable(table, settings.loglik_var)
        if table[-1][1] > settings.loglik_var:
            say(f"warning: Var[log-likelihood estimate] {table[-1][1]:.3g} > {settings.loglik_var:g} at the cap "
                f"N = {MAX_DRAWS}; the chains will mix slowly")
    else:
        n_draws, table = int(settings.n_draws), []
    problem = problem.with_(n_draws=n_draws, rho=settings.rho)
    try:
        lap_chol = np.linalg.cholesky(laplace.covariance)
    except np.linalg.LinAlgError:
        raise CalibrationError("the Laplace covariance is not positive definite: the samples do not determine "
                               "every position (more samples, or rotation about more axes)") from None
    walk = _initial_walk(settings.proposal, lap_chol, laplace.covariance)
    starts = laplace.mean + 2.0 * rng.standard_normal((settings.chains, d)) @ lap_chol.T
    if problem.prior.kind == "uniform":
        pr = problem.prior
        starts = np.clip(starts, pr.mean - 0.999 * pr.std, pr.mean + 0.999 * pr.std)
    seeds = np.random.SeedSequence(settings.seed).spawn(settings.chains)
    ind_prob = settings.independence if settings.proposal == "laplace" else 0.0
    jump = IndependenceT(laplace.mean, lap_chol) if ind_prob > 0 else None
    states = [initial_state(problem, starts[c], walk, seeds[c], independence=jump, independence_prob=ind_prob)
              for c in range(settings.chains)]
    with ChainRunner(problem, settings.scheduler, settings.workers, settings.chains) as runner:
        say(f"chains: {settings.chains} on {runner.workers} {runner.kind} worker(s); N = {n_draws}, "
            f"rho = {settings.rho:g}, proposal {settings.proposal}")
        states, warm, warm_trace, cpu = _warm_up(runner, states, settings, laplace, say)
        # ---- sampling with the kernel fixed
        parts, m = [], 0
        n_iter = settings.chunk
        while True:
            out = runner.run(states, n_iter)
            cpu += sum(r.cpu_seconds for r in out)
            parts.append(out)
            states = [r.state for r in out]
            m += n_iter
            draws = np.concatenate([np.stack([r.draws for r in o]) for o in parts], axis=1)
            lls = np.concatenate([np.stack([r.loglik for r in o]) for o in parts], axis=1)
            ess, ess_tail, rh = chain_diagnostics(draws, lls)
            done = ess >= settings.ess and rh <= settings.rhat
            say(f"sampling: {m} iterations per chain, ESS bulk {ess:.0f}/{settings.ess:g}, tail {ess_tail:.0f}, "
                f"R-hat {rh:.4f}")
            if done or m >= settings.max_iterations:
                break
            # the ESS-based estimate of what is missing, but at least half of what has run: when the ESS
            # is met and R-hat is not, rounds still grow geometrically (the diagnostics cover all draws,
            # so one-chunk rounds would cost quadratically)
            need = (settings.ess / max(ess, 1.0) - 1.0) * m * 1.2
            n_iter = int(min(max(settings.chunk, need, m / 2), 4 * m, settings.max_iterations - m))
            n_iter = max(settings.chunk, int(np.ceil(n_iter / settings.chunk)) * settings.chunk)
    # draws, lls and their diagnostics are the last round's, which covered every sampling round
    cat = lambda key: np.concatenate([np.stack([getattr(r, key) for r in o]) for o in parts], axis=1)  # noqa: E731
    lps, accepted, independence = cat("logprior"), cat("accepted"), cat("independence")
    post = BayesPosterior(
        problem=problem, settings=settings, laplace=laplace, draws=draws, loglik=lls, logprior=lps,
        accepted=accepted, independence=independence, warmup=warm, n_draws=n_draws,
        acceptance=np.array([a[~i].mean() if (~i).any() else np.nan for a, i in zip(accepted, independence)]),
        acceptance_independence=np.array([a[i].mean() if i.any() else np.nan for a, i in zip(accepted, independence)]),
        scale=np.array([s.walk.scale for s in states]), summary=None, ess_bulk_min=ess, ess_tail_min=ess_tail,
        rhat_max=rh, converged=bool(ess >= settings.ess and rh <= settings.rhat),
        seconds=time.perf_counter() - t_wall, cpu_seconds=0.0, var_loglik=table, runner=runner.kind,
        warmup_trace=warm_trace)
    az = arviz()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        post.summary = az.summary(post.inference_data(), var_names=["position"], round_to="none")
    own = time.process_time() - t_cpu
    post.cpu_seconds = own + (cpu if runner.kind != "serial" else 0.0)
    return post


# --------------------------------------------------------------------------- comparing and installing


#: the Laplace approximation "agrees" with the chains when every coordinate's mean differs by at most this
#: many posterior stds and every std ratio is within AGREE_SD_RATIO (the chains' own Monte Carlo error at
#: ESS 400 is ~0.05 std in the mean and ~4 % in the std)
AGREE_MEAN_Z = 0.5
AGREE_SD_RATIO = (0.8, 1.25)


def laplace_agreement(post: BayesPosterior) -> dict:
    """How the Laplace/CRB approximation compares with the chains, coordinate by coordinate."""
    sd = np.sqrt(np.diag(post.covariance))
    z = (post.laplace.mean - post.mean) / sd
    ratio = np.sqrt(np.diag(post.laplace.covariance)) / sd
    agrees = bool(np.max(np.abs(z)) <= AGREE_MEAN_Z and AGREE_SD_RATIO[0] <= ratio.min()
                  and ratio.max() <= AGREE_SD_RATIO[1])
    return {"max_abs_mean_z": float(np.max(np.abs(z))), "rms_mean_z": float(np.sqrt(np.mean(z ** 2))),
            "sd_ratio_min": float(ratio.min()), "sd_ratio_median": float(np.median(ratio)),
            "sd_ratio_max": float(ratio.max()), "agrees": agrees,
            "criterion": f"|mean difference| <= {AGREE_MEAN_Z} posterior std and Laplace/MCMC std ratio in "
                         f"[{AGREE_SD_RATIO[0]}, {AGREE_SD_RATIO[1]}] for every coordinate"}


def install_allowance(post: BayesPosterior, level: float = 0.99) -> float:
    """How much better than the posterior mean a calibration on file must fit the samples to be kept: half
    the ``level`` chi-square quantile of the d coordinates (the posterior mean is not the likelihood's
    maximum, so a file is kept only when it fits better than any position in the posterior's ``level``
    credible region would; :class:`~imu_array_ros.calibration.result.Calibration` ``allowance``)."""
    from scipy.stats import chi2

    return 0.5 * float(chi2.ppf(level, post.problem.dim))
