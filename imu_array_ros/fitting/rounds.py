"""The trajectory rounds of a fit with timing terms: the timing terms read the motion's time derivatives
through a trajectory held fixed (:meth:`~imu_array_ros.fitting.problem.Problem.freeze`) while the optimiser runs;
the fit is the fixed point where that trajectory is the one of the motion found (package docstring,
Approximation).  The loop before stopped after 3 plain re-freezes, far from it on real captures with reading
rates (a 3-term refit 23.7 log-likelihood and 5.5 std from where 10 rounds ended), and reported the
log-likelihood on the trajectory of an earlier motion.

:func:`timing_rounds` iterates to a stated criterion instead: after each round the trajectory is rebuilt from the
motion found and the problem linearised there (the self-consistent point); the fit has converged when one
Gauss-Newton step of that problem moves no parameter by ``ROUND_STD`` of its standard deviation or more and
would gain less than ``ROUND_GAIN`` log-likelihood (or the caller's ``cost_tolerance``, if larger).  Far from the
fixed point (a step of ``NEAR_STD`` std or more) a round is ``FAR_ITERATIONS`` optimiser steps on the held
trajectory (it is only an approximate problem); near it, the round is solved to ROUND_STD / 5, and the
trajectory held next is the motion's (optionally extrapolated from the rounds so far: Anderson acceleration of
the fixed-point map trajectory -> motion found, depth ``ANDERSON_DEPTH``, off by default, measured).  A round whose
optimiser takes no step (its own tests met, the gain left being the motion's) polishes the motion at fixed
parameters instead; before, such a round repeated unchanged to the cap (a real time-offset refit: 56 rounds,
``converged`` False).  At most
``TIMING_ROUNDS`` rounds and ``BUDGET`` x max_iterations optimiser steps: a fit that reaches a cap unconverged
says so (``converged`` False), and the result is always the linearisation on the motion's own trajectory (its
log-likelihood, its Cramer-Rao bound).  Measured: benchmarks/results/timing_rounds.md.

:func:`motion_rounds` is the same fixed point for the motion alone (every term held: ``fit_motion``, and the start
of ``fit_terms``): rounds of (hold the motion's trajectory, ``MOTION_ROUND_STEPS`` Gauss-Newton step on the motion:
solving the held trajectory's problem further bought nothing, the next round re-freezes) until one Gauss-Newton step
of the motion-only problem at the motion's own trajectory moves no sample's motion by ROUND_STD of its standard
deviation (the norm of the sample's whitened step bounds every coordinate's) and would gain less than ROUND_GAIN
log-likelihood over the recording (:func:`motion_gap`); at most TIMING_ROUNDS rounds.  The loop before stopped
after two rounds; on a real capture with sample clocks and reading rates that left the log-likelihood of a
60-s window tens of millions from the fixed point (benchmarks/results/fit_motion_rounds.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.fitting.gauge import Gauge
from imu_array_ros.fitting.optimiser import inverse, levenberg_marquardt
from imu_array_ros.fitting.problem import Linearization, Problem
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["TIMING_ROUNDS", "ROUND_STD", "ROUND_GAIN", "ANDERSON_DEPTH", "MOTION_ROUND_STEPS", "RoundLog",
           "timing_rounds", "fixed_point_gap", "motion_gap", "motion_rounds"]

#: at most this many trajectory rounds (re-freeze and optimise again) after the first optimisation
TIMING_ROUNDS = 60
#: converged when the self-consistent problem's Gauss-Newton step moves every parameter by less than this many std
ROUND_STD = 0.05
#: ... and gains less than this log-likelihood (or the caller's cost_tolerance when larger)
ROUND_GAIN = 0.05
#: Gauss-Newton steps of the motion on each held trajectory in :func:`motion_rounds` (before 2026-11-29: to the
#: optimiser's tolerance; benchmarks/results/discovery_speed.md: the same rounds, a third of the passes)
MOTION_ROUND_STEPS = 1
#: a round whose self-consistent step exceeds this many std is far from the fixed point: FAR_ITERATIONS steps
NEAR_STD = 1.0
FAR_ITERATIONS = 3
#: at most BUDGET x max_iterations optimiser steps in all the rounds together
BUDGET = 6
#: rounds remembered by the Anderson extrapolation of the held trajectory (0: plain re-freezing, the default: on the
#: real 3-term refit of benchmarks/results/timing_rounds.md depth 3 took more steps than plain rounds, which converge
#: within 2-3 near rounds once each round is solved to ROUND_STD / 5)
ANDERSON_DEPTH = 0


@dataclass
class RoundLog:
    """Per round: the re-freeze's cost rise (the cost at the motion found with its own trajectory less the cost
    with the trajectory held), the self-consistent Gauss-Newton step (largest parameter step / std, predicted
    log-likelihood gain), the cost after the round's optimisation and its iterations; whether extrapolated."""

    rise: list = field(default_factory=list)
    step_std: list = field(default_factory=list)
    gain: list = field(default_factory=list)
    cost: list = field(default_factory=list)
    iterations: list = field(default_factory=list)
    extrapolated: list = field(default_factory=list)


def fixed_point_gap(prob: Problem, lin: Linearization, gauge: Gauge) -> tuple[float, float]:
    """(largest parameter step / std, predicted log-likelihood gain) of one Gauss-Newton step of the joint
    problem linearised at ``lin``."""
    s_z, g_z = gauge.reduce(lin.S, lin.g)
    cov_z = inverse(s_z)
    step_z = cov_z @ g_z
    step = float(np.max(np.abs(step_z) / np.sqrt(np.diag(cov_z)), initial=0.0))
    gain = 0.5 * float(g_z @ step_z) + 0.5 * float(np.sum(lin.h[prob.used] ** 2))
    return step, gain


def motion_gap(prob: Problem, lin: Linearization) -> tuple[float, float]:
    """(largest norm of a sample's whitened motion step, predicted log-likelihood gain) of one Gauss-Newton step of
    the motion-only problem linearised at ``lin``, over the samples used whose step is exact
    (:attr:`~imu_array_ros.fitting.problem.Linearization.exact`; a ridge-held sample's step is not a step of the
    likelihood)."""
    h = lin.h[lin.exact & prob.used]
    squares = np.sum(h * h, axis=1)
    return float(np.sqrt(np.max(squares, initial=0.0))), 0.5 * float(np.sum(squares))


def motion_rounds(prob: Problem, model: SensorModel, motion: np.ndarray, *, rounds: int | None = None,
                  log: RoundLog | None = None):
    """The motion-only fit with every term of ``model`` held, from ``motion`` (the problem's coordinates); with
    timing terms, trajectory rounds to their fixed point (module docstring).  Returns (motion, lin, converged,
    rounds done): lin the motion-only linearisation at the motion (with timing terms on its own trajectory, which
    stays held); converged: whether :func:`motion_gap` at it meets (ROUND_STD, ROUND_GAIN).  Without timing terms
    one Gauss-Newton solve (:meth:`~imu_array_ros.fitting.problem.Problem.fit_motion`), as before the rounds."""
    if not prob.needs_derivatives:
        motion, lin = prob.fit_motion(model, motion)
        step, gain = motion_gap(prob, lin)
        return motion, lin, step < ROUND_STD and gain < ROUND_GAIN, 0
    rounds = TIMING_ROUNDS if rounds is None else rounds
    converged, lin = False, None
    for k in range(rounds + 1):
        before = None if lin is None else lin.cost
        prob.freeze(motion)  # the trajectory of the motion found: the self-consistent point
        lin = prob.linearize(model, motion, free=False)
        step, gain = motion_gap(prob, lin)
        if log is not None:
            log.rise.append(np.nan if before is None else lin.cost - before)
            log.step_std.append(step)
            log.gain.append(gain)
        if step < ROUND_STD and gain < ROUND_GAIN:
            converged = True
            break
        if k == rounds:
            break
        # the next round re-freezes at the motion found: a held trajectory's own fit is not worth solving further
        motion, lin = prob.fit_motion(model, motion, lin=lin, iterations=MOTION_ROUND_STEPS, last_lin=False)
        if log is not None:
            log.cost.append(np.nan if lin is None else lin.cost)
    return motion, lin, converged, k


def timing_rounds(prob: Problem, model: SensorModel, motion: np.ndarray, lin: Linearization, gauge: Gauge,
                  max_iterations: int, tolerance: float, progress, cost_tolerance: float | None, *,
                  rounds: int | None = None, depth: int | None = None,
                  log: RoundLog | None = None):
    """Rounds of (hold a trajectory, optimise) after the optimisation that gave (model, motion, lin) on the
    trajectory :attr:`Problem.frozen_motion`, to the fixed point (module docstring).  Returns (model, motion, lin,
    iterations, converged): lin the linearisation at the motion's own trajectory; converged: whether the criterion was
    met (a Gauss-Newton step at the returned point: the optimisers' own flags do not matter), False at the cap."""
    rounds = TIMING_ROUNDS if rounds is None else rounds
    depth = ANDERSON_DEPTH if depth is None else depth
    limit = max(ROUND_GAIN, cost_tolerance or 0.0)
    dim = prob.mm.dim
    held = prob.frozen_motion[:, :dim]
    xs, fs, scale = [], [], None
    iterations, converged = 0, False
    for k in range(rounds + 1):
        before = lin.cost
        prob.freeze(motion)  # the trajectory of the motion found: the self-consistent point
        lin = None  # memory: the last linearisation (and its G) goes before the next is made
        lin = prob.linearize(model, motion)
        step, gain = fixed_point_gap(prob, lin, gauge)
        if log is not None:
            log.rise.append(lin.cost - before)
            log.step_std.append(step)
            log.gain.append(gain)
        if step < ROUND_STD and gain < limit:
            converged = True
            break
        if k == rounds or iterations >= BUDGET * max_iterations:
            break
        near = step < NEAR_STD
        f = motion[:, :dim] - held
        if not near:
            xs, fs, scale = [], [], None
        elif scale is None:
            scale = np.sqrt(np.mean(f[prob.used] ** 2, axis=0))
            scale = np.where(scale > 0, scale, 1.0)
        if fs and np.linalg.norm(f / scale) > np.linalg.norm(fs[-1] / scale):
            xs, fs = [], []  # the extrapolation made things worse: restart from the plain re-freeze
        if near:
            xs, fs = (xs + [held])[-(depth + 1):], (fs + [f])[-(depth + 1):]
        extrapolate = near and depth > 0 and len(xs) > 1
        held = _anderson(xs, fs, scale, prob.used) if extrapolate else motion[:, :dim]
        if extrapolate:
            prob.freeze(np.concatenate([held, motion[:, dim:]], axis=1))
            lin = None
            lin = prob.linearize(model, motion)
        if log is not None:
            log.extrapolated.append(extrapolate)
        # far from the fixed point a round is an approximate problem: a few steps; near it, solved to well within
        # ROUND_STD so that the extrapolation sees the map, not the optimiser's leftovers
        model, motion, lin, more, _ = levenberg_marquardt(
            prob, model, motion, lin, gauge, max_iterations if near else min(max_iterations, FAR_ITERATIONS),
            ROUND_STD / 5 if near else tolerance, progress, None if near else cost_tolerance,
            last_lin=False)  # the next round re-freezes and linearises there: only the cost of its last step
        if not more:  # the optimiser saw nothing to do, the criterion's gain is the motion's: polish it at fixed
            motion, lin = prob.fit_motion(model, motion, lin=lin)  # parameters (else the rounds repeat to the cap)
        iterations += more
        if log is not None:
            log.cost.append(lin.cost)
            log.iterations.append(more)
    return model, motion, lin, iterations, converged


def _anderson(xs: list, fs: list, scale: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Anderson's extrapolation (type II, no damping) of the fixed point x = F(x) from the trajectories held
    ``xs`` and the motion changes ``fs`` = F(x) - x they gave; least squares on the used samples, columns
    divided by ``scale``."""
    df = np.stack([(b - a)[used] / scale for a, b in zip(fs[:-1], fs[1:])], axis=-1).reshape(-1, len(fs) - 1)
    gamma = np.linalg.lstsq(df, (fs[-1][used] / scale).reshape(-1), rcond=1e-10)[0]
    x = xs[-1] + fs[-1]
    for i, g in enumerate(gamma):
        x = x - g * ((xs[i + 1] - xs[i]) + (fs[i + 1] - fs[i]))
    return x
