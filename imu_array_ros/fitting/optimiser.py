"""The optimiser: Levenberg-Marquardt on the gauge-reduced Schur system, the motion following each step by
back-substitution, and by one Gauss-Newton step of each sample's motion at the new parameters when that alone
does not lower the cost (theory: :mod:`imu_array_ros.fitting`)."""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.gauge import Gauge
from imu_array_ros.fitting.problem import Linearization, Problem
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["levenberg_marquardt", "inverse", "CostOnly", "backtracking", "BACKTRACK_HALVINGS"]

#: with :func:`backtracking` on, an undamped step that raises the cost (its motion settled) is halved up to this
#: many times, down to 1/16 of the Gauss-Newton step, before the damping grows (chosen a priori, not tuned)
BACKTRACK_HALVINGS = 4
_BACKTRACK = contextvars.ContextVar("backtracking", default=False)


@contextlib.contextmanager
def backtracking(on: bool = True):
    """Inside (also as a decorator): :func:`levenberg_marquardt` backtracks along the Gauss-Newton direction
    (halving the step, :data:`BACKTRACK_HALVINGS` times at most) before it damps.  Damping turns the step towards
    the gradient and shrinks it most along the weakly determined directions, which are the ones a refit with
    timing terms must travel (a common gyroscope scale traded with the axis and time offsets): on discovery's
    gyroscope-gain refit of exp_1's moving phase every undamped step was rejected and the damped ones crept, 104
    linearisations; backtracking 50, the same fixed point to its tolerance.  Off by default (the calibrations'
    iterates unchanged); discovery turns it on."""
    token = _BACKTRACK.set(bool(on))
    try:
        yield
    finally:
        _BACKTRACK.reset(token)


@dataclass
class CostOnly:
    """What :func:`levenberg_marquardt` returns in place of the linearisation at its last step when the caller
    does not want it (``last_lin`` False): that point's cost, sum r^2 / 2 with the derivatives held."""

    cost: float


def levenberg_marquardt(prob: Problem, model: SensorModel, motion: np.ndarray, lin: Linearization, gauge: Gauge,
                        max_iterations: int, tolerance: float, progress, cost_tolerance: float | None = None, *,
                        last_lin: bool = True):
    """Levenberg-Marquardt on the reduced system (damping on S's diagonal, a step accepted when the cost
    drops); returns (model, motion, lin, iterations, converged).

    A trial step whose back-substituted motion (first order in the parameter step) raises the cost is judged
    again with each sample's motion moved by one Gauss-Newton step of its own at the new parameters
    (:func:`_settle_motion`, variable projection) before the damping grows: where the motion responds
    non-linearly to the parameters (time offsets x omega_dot, with reading rates) the undamped step is good but
    its first-order motion is not, and without this the damping crept along the valley for tens of
    iterations.  Steps that lower the cost as they are stay as before (bit-identical).

    lin: the linearisation at (model, motion); converged when every parameter step is below ``tolerance``
    standard deviations and the RMS motion step below ``tolerance`` of its own, or (``cost_tolerance`` given)
    when an accepted step lowered the cost by less than ``cost_tolerance`` (log-likelihood units: a caller that
    needs the likelihood, not the last digits of the estimate); progress(iteration, cost) or None.

    last_lin False: a caller that re-linearises at the returned point anyway (a timing round re-freezes the
    trajectory first, :func:`~imu_array_ros.fitting.rounds.timing_rounds`) gets, when the loop ends on a step
    (``max_iterations`` reached or ``cost_tolerance`` met), a :class:`CostOnly` (that step's cost) instead of the
    linearisation there: one pass over every sample less, the same iterates bit for bit."""
    lam, iterations, converged = 0.0, 0, False
    for _ in range(max_iterations):
        if progress is not None:
            progress(iterations, lin.cost)
        s_z, g_z = gauge.reduce(lin.S, lin.g)
        cov_z = inverse(s_z)
        step_z = cov_z @ g_z
        motion_rms = np.sqrt(np.mean(np.sum(lin.h[prob.used] ** 2, axis=1)))
        if np.max(np.abs(step_z) / np.sqrt(np.diag(cov_z)), initial=0.0) < tolerance and motion_rms < tolerance:
            converged = True
            break
        t, halvings = 1.0, BACKTRACK_HALVINGS if _BACKTRACK.get() else 0
        while True:
            dz = t * step_z if lam == 0 else _solve_damped(s_z, g_z, lam)
            dtheta = gauge.expand(dz)
            new_model = prob.with_values(model, prob.values(model).reshape(-1) + dtheta)
            new_motion = motion + prob.motion_step(model, motion, lin, dtheta)
            r = prob.residuals(new_model, new_motion, lin.derivs)  # the derivatives held, as in the step
            cost = 0.5 * float(np.sum(r * r))
            if cost > lin.cost:  # the first-order motion may be what fails: let the motion follow the step
                new_motion, cost = _settle_motion(prob, new_model, new_motion, r, lin.derivs)
            if cost <= lin.cost:
                lam = lam / 10 if lam > 1e-6 else 0.0
                break
            if lam == 0 and halvings:  # backtracking(): along the Gauss-Newton direction first
                t, halvings = 0.5 * t, halvings - 1
                continue
            lam = max(1e-4, 10 * lam)
            if lam > 1e8:  # no step lowers the cost: stalled short of the tolerance
                return model, motion, lin, iterations, False
        model, motion = new_model, new_motion
        iterations += 1
        drop = lin.cost - cost
        done = cost_tolerance is not None and drop < cost_tolerance
        lin = None  # memory: the last linearisation (and its G) goes before the next is made
        if not last_lin and (done or iterations == max_iterations):
            return model, motion, CostOnly(cost), iterations, done
        lin = prob.linearize(model, motion)
        if done:
            converged = True
            break
    return model, motion, lin, iterations, converged


def _settle_motion(prob: Problem, model: SensorModel, motion: np.ndarray, r: np.ndarray, derivs: tuple):
    """(motion, cost): one Gauss-Newton step of every sample's motion alone at ``model`` from ``motion`` (whose
    normalised residuals are ``r``), kept where it lowers that sample's cost; ``derivs`` the motion derivatives
    held (the problem's frozen ones, which the motion-only linearisation also reads)."""
    before = 0.5 * np.sum(r * r, axis=(1, 2))
    lin = prob.linearize(model, motion, free=False)
    trial = motion + prob.motion_step(model, motion, lin, None)
    r = prob.residuals(model, trial, derivs)
    after = 0.5 * np.sum(r * r, axis=(1, 2))
    better = after < before
    return np.where(better[:, None], trial, motion), float(np.sum(np.where(better, after, before)))


def inverse(s: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite matrix, Jacobi-scaled Cholesky."""
    if s.size == 0:
        return s.copy()
    d = np.sqrt(np.diag(s))
    d = np.where(d > 0, d, 1.0)
    try:
        factor = scipy.linalg.cho_factor(s / np.outer(d, d))
    except np.linalg.LinAlgError:
        raise CalibrationError("the free parameters are not identifiable at the current estimate "
                               "(Fisher information singular); record more varied motion") from None
    return scipy.linalg.cho_solve(factor, np.eye(len(s))) / np.outer(d, d)


def _solve_damped(s: np.ndarray, g: np.ndarray, lam: float) -> np.ndarray:
    """The step of the damped system (S + lam diag(S)) dz = g."""
    return np.linalg.solve(s + lam * np.diag(np.diag(s)), g)

