"""The (correlated) pseudo-marginal Metropolis-Hastings chain (carlsson2021 Alg. 1).

The chain moves on (theta, u) jointly, u (T, N, 3) the standard normal random numbers of the
likelihood estimate (:class:`~imu_array_ros.calibration.bayes.problem.BayesProblem`): the
pseudo-marginal target pi(theta, u) ~ p(theta) p_N(y | theta, u) phi(u), whose theta-marginal is the
posterior for any N, as p_N is unbiased.  ``rho = 0`` draws u afresh every iteration (plain PmMH,
Alg. 1); ``0 < rho < 1`` proposes u' = rho u + sqrt(1 - rho^2) eps (correlated pseudo-marginal,
Deligiannidis et al. 2018), a phi-reversible move, so the acceptance ratio and the target are the same
and the noise of the log-likelihood ratio shrinks with 1 - rho.

theta' comes from the random walk (eq. 27) or, with a fixed probability per iteration, from the
independence proposal (:mod:`~imu_array_ros.calibration.bayes.moves`).  Everything here is ROS-free
and picklable: a chunk runs wherever its state is sent (:mod:`~imu_array_ros.calibration.bayes.runners`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from imu_array_ros.calibration.bayes.moves import IndependenceT, RandomWalk
from imu_array_ros.calibration.bayes.problem import BayesProblem

__all__ = ["ChainState", "ChunkResult", "initial_state", "run_chunk"]


@dataclass
class ChainState:
    """Where a chain is: theta (d,), its random numbers u (T, N, 3), log-likelihood and log-prior, the
    random walk (its shape and step length), the independence proposal and the probability of proposing
    from it each iteration (None or 0: random walk only), the generator and the iterations run so far."""

    theta: np.ndarray
    u: np.ndarray
    loglik: float
    logprior: float
    walk: RandomWalk
    rng: np.random.Generator
    iterations: int = 0
    independence: IndependenceT | None = None
    independence_prob: float = 0.0


@dataclass
class ChunkResult:
    """One chunk of a chain: draws (M, d), loglik (M,), logprior (M,), accepted (M,) bool, independence
    (M,) bool (which proposal was made), the new state and the process time it took (s)."""

    draws: np.ndarray
    loglik: np.ndarray
    logprior: np.ndarray
    accepted: np.ndarray
    independence: np.ndarray
    state: ChainState
    cpu_seconds: float


def initial_state(problem: BayesProblem, theta0: np.ndarray, walk: RandomWalk, seed, *,
                  independence: IndependenceT | None = None, independence_prob: float = 0.0) -> ChainState:
    """A chain at theta0 with fresh random numbers (the first draws of its generator, seeded by ``seed``)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((problem.n_samples, problem.n_draws, 3))
    theta0 = np.asarray(theta0, dtype=float)
    return ChainState(theta=theta0, u=u, loglik=problem.loglik(theta0, u), logprior=problem.prior.logpdf(theta0),
                      walk=walk, rng=rng, independence=independence, independence_prob=float(independence_prob))


def run_chunk(problem: BayesProblem, state: ChainState, n_iter: int) -> ChunkResult:
    """``n_iter`` PmMH iterations (Alg. 1; correlated when problem.rho > 0) from ``state``.

    Each iteration proposes theta' from the random walk or, with probability ``state.independence_prob``
    decided independently of the state, from the independence proposal; the acceptance ratio carries the
    proposal's log correction; a mixture of two kernels that each leave the target invariant leaves it
    invariant.  u' as in the module docstring.

    The generator is used in this order (it fixes every chain): fresh u if N changed; the random walk's
    steps for the whole chunk; the chunk's log-uniforms; with the independence proposal, the chunk's
    choices and then its proposals; then, per iteration whose proposal has a finite prior, the new eps.
    """
    t0 = time.process_time()
    rng = state.rng
    d = problem.dim
    theta, u, ll, lp = state.theta.copy(), state.u, state.loglik, state.logprior
    if u.shape != (problem.n_samples, problem.n_draws, 3):  # N changed (tuning): fresh random numbers
        u = rng.standard_normal((problem.n_samples, problem.n_draws, 3))
        ll = problem.loglik(theta, u)
    rho, rho_c = problem.rho, np.sqrt(1.0 - problem.rho ** 2)
    draws = np.empty((n_iter, d))
    lls, lps = np.empty(n_iter), np.empty(n_iter)
    acc = np.zeros(n_iter, dtype=bool)
    walk, jump = state.walk, state.independence
    batches = {False: (walk, walk.draw(rng, n_iter))}
    logu = np.log(rng.random(n_iter))
    if jump is not None and state.independence_prob > 0:
        ind = rng.random(n_iter) < state.independence_prob
        batches[True] = (jump, jump.draw(rng, n_iter))
    else:
        ind = np.zeros(n_iter, dtype=bool)
    for i in range(n_iter):
        move, batch = batches[bool(ind[i])]
        prop = move.propose(theta, batch[i])
        lp_new = problem.prior.logpdf(prop)
        if np.isfinite(lp_new):
            eps = rng.standard_normal(u.shape)
            u_new = eps if rho == 0.0 else rho * u + rho_c * eps
            ll_new = problem.loglik(prop, u_new)
            log_ratio = (ll_new + lp_new) - (ll + lp)
            log_ratio += move.log_correction(theta, prop)
            if logu[i] < log_ratio:
                theta, u, ll, lp = prop, u_new, ll_new, lp_new
                acc[i] = True
        draws[i], lls[i], lps[i] = theta, ll, lp
    new = replace(state, theta=theta, u=u, loglik=ll, logprior=lp, iterations=state.iterations + n_iter)
    return ChunkResult(draws, lls, lps, acc, ind, new, time.process_time() - t0)
