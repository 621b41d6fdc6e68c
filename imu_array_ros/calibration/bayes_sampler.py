"""Running the PmMH chains of :mod:`imu_array_ros.calibration.bayes`: tuning, parallel chains, diagnostics.

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

Chains run in parallel: worker processes by default (``scheduler=None``), a
Dask ``LocalCluster`` (``"local"``), an existing Dask scheduler (its
address), or in this process (``"serial"``).  Each round is one task per
chain, carrying the chain's state (theta, random numbers, generator), so the
same code runs anywhere and reports progress between rounds.
"""

from __future__ import annotations

import contextlib
import os
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from imu_array_ros.calibration.bayes import (BayesProblem, ChainState, ChunkResult, Laplace, initial_state,
                                             loglik_variance, run_chunk)
from imu_array_ros.errors import CalibrationError

__all__ = ["SamplerSettings", "BayesPosterior", "ChainRunner", "sample_posterior", "choose_draws", "arviz",
           "laplace_agreement", "install_scores",
           "PROPOSALS"]

#: proposal of theta: "laplace": Gaussian random walk with the Laplace covariance (scaled);
#: "isotropic": sigma_q I (carlsson2021 eq. 27)
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


def arviz():
    """ArviZ, imported without its refactoring notice."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz as az
    return az


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


# --------------------------------------------------------------------------- where the chains run


def _run_task(problem, state, n_iter):  # a top-level function: picklable for processes and Dask
    return run_chunk(problem, state, n_iter)


_INSTALLED: dict = {}


def _install(problem) -> None:
    _INSTALLED["problem"] = problem


def _run_installed(state, n_iter):
    return run_chunk(_INSTALLED["problem"], state, n_iter)


@contextlib.contextmanager
def _one_thread_blas():
    """Worker processes inherit one BLAS/OpenMP thread each (chains, not threads, use the cores)."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    old = {k: os.environ.get(k) for k in keys}
    os.environ.update({k: "1" for k in keys})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class ChainRunner:
    """Runs one round (a chunk per chain) at a time, where ``scheduler`` says (module docstring).

    Use as a context manager; :meth:`run` (states, n_iter) -> ChunkResults in order.
    """

    def __init__(self, problem: BayesProblem, scheduler: str | None = None, workers: int | None = None,
                 chains: int = 2):
        self.problem = problem
        self.scheduler = scheduler
        self.workers = 1 if scheduler == "serial" else max(1, min(chains, workers or os.cpu_count() or 1))
        self._stack = contextlib.ExitStack()
        self._pool = self._client = self._problem_future = None

    @property
    def kind(self) -> str:
        if self.scheduler in (None, "processes"):
            return "serial" if self.workers == 1 else "processes"
        return "serial" if self.scheduler == "serial" else "dask"

    def __enter__(self) -> "ChainRunner":
        kind = self.kind
        if kind == "processes":
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            with _one_thread_blas():
                self._pool = self._stack.enter_context(ProcessPoolExecutor(
                    self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_install,
                    initargs=(self.problem,)))
                # start the workers now, while the environment says one thread
                list(self._pool.map(_noop, range(self.workers)))
        elif kind == "dask":
            self._client = self._stack.enter_context(_dask_client(self.scheduler, self.workers))
            self._problem_future = self._client.scatter(self.problem, broadcast=True)
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def run(self, states: list[ChainState], n_iter: int) -> list[ChunkResult]:
        kind = self.kind
        if kind == "serial":
            return [run_chunk(self.problem, s, n_iter) for s in states]
        if kind == "processes":
            futures = [self._pool.submit(_run_installed, s, n_iter) for s in states]
            return [f.result() for f in futures]
        futures = [self._client.submit(_run_task, self._problem_future, s, n_iter, pure=False) for s in states]
        return self._client.gather(futures)


def _noop(_):
    return None


@contextlib.contextmanager
def _dask_client(scheduler: str, workers: int):
    """A ``dask.distributed`` client: a new LocalCluster of ``workers`` single-threaded processes for
    ``"local"``, else the scheduler at that address."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover - a dependency
        raise CalibrationError("--scheduler needs dask.distributed (pip install 'dask[distributed]')") from None
    import logging

    logging.getLogger("distributed").setLevel(logging.ERROR)
    if scheduler == "local":
        with _one_thread_blas():
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
        with cluster, Client(cluster) as client:
            yield client
        return
    try:
        client = Client(scheduler, timeout=10)
    except (OSError, ValueError, TimeoutError) as err:
        raise CalibrationError(f"--scheduler {scheduler}: cannot connect to a Dask scheduler: {err}") from None
    with client:
        yield client


# --------------------------------------------------------------------------- the result


@dataclass
class BayesPosterior:
    """What :func:`sample_posterior` found.

    draws (C, M, d) after the warm-up; loglik, logprior (C, M); accepted (C, M);
    warmup: iterations per chain discarded; n_draws: N; acceptance (C,);
    scale (C,) final step scales; summary: ArviZ's table (pandas) of every
    coordinate; ess_bulk_min, ess_tail_min, rhat_max; seconds (wall) and
    cpu_seconds (every process's CPU time); var_loglik: the tuning table
    [(N, variance)]; laplace: the Gaussian approximation it started from.
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
        cov = self.covariance
        out = np.zeros((len(self.problem.names), 3, 3))
        for j, k in enumerate(self.problem.free):
            out[k] = cov[3 * j:3 * j + 3, 3 * j:3 * j + 3]
        return out

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
        from imu_array_ros.calibration.output import provenance

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


# --------------------------------------------------------------------------- diagnostics


def _diagnostics(draws: np.ndarray, extra: np.ndarray | None = None) -> tuple[float, float, float]:
    """(min bulk ESS, min tail ESS, max rank-normalised split R-hat) over the coordinates of draws
    (C, M, d) (and the extra (C, M) series for R-hat)."""
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


def _rw_acceptance(r: ChunkResult) -> float:
    """Acceptance rate of the random-walk proposals of a chunk (NaN: none made)."""
    rw = ~r.independence
    return float(r.accepted[rw].mean()) if rw.any() else float("nan")


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
        "the noise model: calibrate the intrinsics first (imu-array calibrate all), widen the accelerometer noise "
        "(--accel-std), or give --draws to run anyway (the chains will mix slowly)")


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
    lap_cov = laplace.covariance
    try:
        lap_chol = np.linalg.cholesky(lap_cov)
    except np.linalg.LinAlgError:
        raise CalibrationError("the Laplace covariance is not positive definite: the samples do not determine "
                               "every position (more samples, or rotation about more axes)") from None
    if settings.proposal == "laplace":
        shape = lap_chol
        scale0 = 2.38 / np.sqrt(d)
    else:  # eq. 27: sigma_q I, sigma_q starting at the typical Laplace std over sqrt(d)
        shape = np.eye(d)
        scale0 = 2.38 / np.sqrt(d) * float(np.sqrt(np.mean(np.diag(lap_cov))))
    starts = laplace.mean + 2.0 * rng.standard_normal((settings.chains, d)) @ lap_chol.T
    if problem.prior.kind == "uniform":
        pr = problem.prior
        starts = np.clip(starts, pr.mean - 0.999 * pr.std, pr.mean + 0.999 * pr.std)
    seeds = np.random.SeedSequence(settings.seed).spawn(settings.chains)
    states = [initial_state(problem, starts[c], shape, scale0, seeds[c]) for c in range(settings.chains)]
    ind_prob = settings.independence if settings.proposal == "laplace" else 0.0
    for s in states:
        s.ind_mean, s.ind_chol, s.ind_prob = laplace.mean, lap_chol, ind_prob
    cpu = 0.0
    warm_trace = []
    with ChainRunner(problem, settings.scheduler, settings.workers, settings.chains) as runner:
        say(f"chains: {settings.chains} on {runner.workers} {runner.kind} worker(s); N = {n_draws}, "
            f"rho = {settings.rho:g}, proposal {settings.proposal}")
        # ---- warm-up
        warm, pooled, rounds = 0, [], []
        while True:
            out = runner.run(states, settings.chunk)
            cpu += sum(r.cpu_seconds for r in out)
            warm += settings.chunk
            acc = np.array([_rw_acceptance(r) for r in out])
            draws = np.stack([r.draws for r in out])
            warm_trace.append(np.stack([r.loglik + r.logprior for r in out]))
            # R-hat over the second half of the whole warm-up so far (the window grows with it: a fixed
            # window shorter than a few autocorrelation times never agrees), thinned to bound memory
            thin = max(1, settings.chunk // WARMUP_KEEP)
            rounds.append((draws[:, ::thin], np.stack([r.loglik for r in out])[:, ::thin]))
            half = rounds[len(rounds) // 2:]
            _, _, rh = _diagnostics(np.concatenate([h[0] for h in half], axis=1),
                                    np.concatenate([h[1] for h in half], axis=1))
            states = [r.state for r in out]
            # step scale toward the target acceptance (Robbins-Monro on log scale)
            for s, a in zip(states, acc):
                s.scale *= float(np.exp(1.5 * (a - settings.target_acceptance)))
            if settings.proposal == "laplace":  # proposals toward the draws' moments, shrunk to Laplace's by
                # the draws' effective size (autocorrelated warm-up draws carry little: ESS, not their count)
                pooled.append(draws[:, draws.shape[1] // 2:])
                pooled = pooled[-4:]
                recent = np.concatenate(pooled, axis=1)
                n_eff, _, _ = _diagnostics(recent)
                w = n_eff / (n_eff + 10.0 * d)
                flat = recent.reshape(-1, d)
                cov = w * np.cov(flat, rowvar=False) + (1 - w) * lap_cov
                try:
                    new_shape = np.linalg.cholesky(cov)
                except np.linalg.LinAlgError:
                    new_shape = None
                if new_shape is not None:  # the scale is relative to the shape: kept
                    mean = w * flat.mean(axis=0) + (1 - w) * laplace.mean
                    for s in states:
                        s.proposal = new_shape
                        s.ind_mean, s.ind_chol = mean, new_shape
            ind_acc = np.mean([r.accepted[r.independence].mean() for r in out if r.independence.any()]) \
                if ind_prob > 0 else float("nan")
            say(f"warm-up: {warm} iterations per chain, random-walk acceptance {acc.min():.0%}-{acc.max():.0%}"
                f"{f', independence {ind_acc:.0%}' if ind_prob > 0 else ''}, R-hat {rh:.3f}")
            if warm >= settings.min_warmup and rh < WARMUP_RHAT and np.all((acc > 0.07) & (acc < 0.35)):
                break
            if warm >= settings.max_warmup:
                say(f"warning: warm-up stopped at {warm} iterations without the chains agreeing (R-hat {rh:.3f})")
                break
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
            ess, ess_tail, rh = _diagnostics(draws, lls)
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
        scale=np.array([s.scale for s in states]), summary=None, ess_bulk_min=ess, ess_tail_min=ess_tail,
        rhat_max=rh, converged=bool(ess >= settings.ess and rh <= settings.rhat),
        seconds=time.perf_counter() - t_wall, cpu_seconds=0.0, var_loglik=table, runner=runner.kind,
        warmup_trace=np.concatenate(warm_trace, axis=1))
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


def install_scores(post: BayesPosterior, samples, model, level: float = 0.99):
    """(score, new_score) for :func:`~imu_array_ros.calibration.output.install_calibration`: the window
    log-likelihood with the motion fitted (:func:`~imu_array_ros.calibration.scoring.window_loglik`) of a
    description, and the posterior mean's plus half the ``level`` chi-square quantile of the d coordinates:
    a calibration on file is kept only when it fits these samples better than any position in the
    posterior's ``level`` credible region would (the posterior mean is not the likelihood's maximum, so
    it is compared with that allowance, not bare)."""
    from scipy.stats import chi2

    from imu_array_ros.calibration.scoring import window_loglik
    from imu_array_ros.model.sensor_model import SensorModel

    new = window_loglik(samples, model.with_terms(position=post.positions_mean()))

    def score(previous) -> float:
        return window_loglik(samples, SensorModel.from_description(previous))

    return score, new + 0.5 * float(chi2.ppf(level, post.problem.dim))
