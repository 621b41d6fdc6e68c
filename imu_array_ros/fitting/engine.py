"""The fitting engine's entry points: maximum likelihood of sensor-model terms jointly with every sample's
motion (:func:`fit_terms`, :class:`FitResult`) and of the motion alone (:func:`fit_motion`); the score
test (:func:`score_blocks`) and the input check (:func:`check_terms`) are re-exported here.

The problem, the Schur complement, the Cramér-Rao bound, gauges, identifiability and the time-offset
approximation are explained in the package docstring (:mod:`imu_array_ros.fitting`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.gauge import GAUGE_ORDER, Gauge
from imu_array_ros.fitting.identifiability import NOISE_SHARE
from imu_array_ros.fitting.optimiser import inverse, levenberg_marquardt
from imu_array_ros.fitting.problem import Linearization, Problem, check_terms, keep_schur
from imu_array_ros.fitting.rounds import FAR_ITERATIONS, TIMING_ROUNDS, motion_gap, motion_rounds, timing_rounds
from imu_array_ros.fitting.robust import (HUBER_ROUNDS, RobustCovariance, blocked_covariance, huber_sigma,
                                          sample_influence)
from imu_array_ros.fitting.score import ScoreBlocks, score_blocks
from imu_array_ros.model.reference import imu_indexes, reference_index
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

__all__ = ["FitResult", "MotionFit", "ScoreBlocks", "fit_terms", "fit_motion", "score_blocks", "check_terms",
           "keep_schur", "GAUGE_ORDER", "NOISE_SHARE", "TIMING_ROUNDS"]



@dataclass
class FitResult:
    """What :func:`fit_terms` estimated (SI units).

    model: the input model with the estimate written into the free terms;
    free: the fitted terms; imus: names of the IMUs whose parameters were fitted;
    parameter_names (M,): "imu_03 accelerometer.gain[1]", fitted IMUs x free
    terms' parameters, IMU-major; theta (M,); covariance (M, M): the Cramér-Rao
    bound at the estimate in the chosen gauge (zero rows for held parameters);
    std: term -> (K, P) standard deviations, NaN where not fitted or held;
    held: names of the parameters held to fix the gauge; gauge: one line per
    fixed gauge direction; gauge_directions (M, q): orthonormal basis (SI
    units) of the gauge freedoms, to first order theta + gauge_directions @ c
    predicts the same readings for any c (the motion changing with it);
    loglik_before/after: log-likelihood at the initial parameters (motion
    fitted to them) and at the estimate; nis_before/after:
    sum of squared normalised residuals / degrees of freedom (valid axes -
    9 samples_used - estimated parameters), ~1 for a correct model;
    iterations, converged; samples_used (samples_dropped: no motion information);
    motion (N, 9) [omega, omega_dot, s] in the array frame (NaN where dropped);
    residuals (N, K, 6) normalised (y - h) / sigma, NaN on masked axes and dropped samples;
    covariance_robust (M, M), std_robust (term -> (K, P), NaN as for std): the sandwich covariance
    S^-1 B S^-1 with B the long-run covariance of the per-sample scores from time blocks, which holds when the
    model is not exact or the noise not white (:mod:`imu_array_ros.fitting.robust`; equal to the CRB to
    within its sampling noise when the model is exact); sandwich: how its blocks were chosen
    (:class:`~imu_array_ros.fitting.robust.RobustCovariance`: block_seconds, blocks, plateau; None when not
    computed: ``sandwich=False``, or fewer samples than max(32, 2 x parameters)); huber_rounds: reweighting rounds done (``robust="huber"``).
    """

    model: SensorModel
    free: tuple[str, ...]
    imus: tuple[str, ...]
    parameter_names: list[str]
    theta: np.ndarray
    covariance: np.ndarray
    std: dict[str, np.ndarray]
    held: list[str]
    gauge: list[str]
    gauge_directions: np.ndarray = field(repr=False)
    loglik_before: float
    loglik_after: float
    nis_before: float
    nis_after: float
    iterations: int
    converged: bool
    samples_used: int
    samples_dropped: int
    dof: int
    motion: np.ndarray = field(repr=False)
    residuals: np.ndarray = field(repr=False)
    covariance_robust: np.ndarray | None = field(default=None, repr=False)
    std_robust: dict[str, np.ndarray] = field(default_factory=dict)
    sandwich: RobustCovariance | None = None
    huber_rounds: int = 0


def fit_terms(samples: ImuSamples, model: SensorModel, free: Sequence[str], *, imus=None, reference=None,
              gauge: str = "reference", motion0=None, max_iterations: int = 50, tolerance: float = 1e-3,
              progress: Callable[[int, float], None] | None = None, motion_model=None, sigma=None,
              only: dict | None = None, t0_ns: int | None = None, robust: str | None = None,
              sandwich: bool = True, hold: Sequence[str] = (), cost_tolerance: float | None = None,
              keep_g: bool | None = None) -> FitResult:
    """Maximum likelihood of the ``free`` terms' parameters jointly with every sample's motion.

    samples: the readings (:class:`~imu_array_ros.model.samples.ImuSamples`: stamps (N,) int64 ns,
    accel, gyro (N, K, 3) in the sensor frames; NaN: missing; clipped readings are masked by
    ``model.valid``);
    model: the initial values of every term (the non-free terms are held);
    free: registry names of the terms to fit; imus: names or indexes of the
    IMUs whose parameters are fitted (default all; the others are held);
    reference: IMU (name or index, among ``imus``) whose parameters fix the
    gauge (default the first fitted IMU); gauge: "reference" (hold the
    reference's parameters, see :mod:`imu_array_ros.fitting`) or "mean" (keep the
    parameters' component along every gauge freedom, e.g. the centroid of the
    positions, at its initial value);
    motion0: (N, 9) initial [omega, omega_dot, s] (default: from the readings);
    tolerance: converged when every parameter step is below ``tolerance``
    standard deviations and the RMS motion step below ``tolerance`` of its own;
    progress(iteration, cost): called once per iteration, cost = sum of
    squared normalised residuals / 2;
    motion_model: how each sample's motion is parametrised
    (:mod:`~imu_array_ros.fitting.motion_models`; default
    :class:`~imu_array_ros.fitting.motion_models.RigidMotion`, any motion;
    :class:`~imu_array_ros.fitting.motion_models.StaticMotion` for poses at
    rest on gravity of known magnitude); sigma: (N, K, 6) standard deviations
    of the readings [acc, gyro] replacing the model's noise figures (e.g. of
    averages over still intervals, or robust reweighting); only: term -> IMUs
    (names or indexes) where that free term is fitted, the term held on the
    other IMUs of ``imus`` (e.g. the findings of mismatch discovery: one term
    on one IMU, another on another; default every free term on every fitted
    IMU; with ``only``, a gauge freedom left is fixed by holding parameters as
    with gauge="reference", whatever ``gauge`` says); t0_ns: the time origin of
    drifts and sample clocks (default the first stamp; give the recording's when
    ``samples`` are a part of it: a sample clock's phase counts from it); hold: parameter names
    (:attr:`FitResult.parameter_names`, e.g. "imu_1 gyroscope.gain[0]") held at their initial values, outside
    the gauge search (a refit that must keep an earlier fit's gauge: with timing terms the gauge freedoms of the
    other terms are no longer numerically null where the engine looks for them); robust: None or "huber": refit
    ``HUBER_ROUNDS`` times with the readings reweighted by Huber's weights on the residuals of the fit before
    (:func:`~imu_array_ros.fitting.robust.huber_sigma`, each axis' scale from its median absolute residual):
    readings far out count linearly instead of quadratically; nis/loglik "after" are then those of the
    reweighted problem; sandwich: compute ``covariance_robust`` (one more pass over the samples);
    cost_tolerance: also converged when a step lowers the cost (-log-likelihood) by less than this, and with
    timing terms the bound on the log-likelihood gain left at the rounds' fixed point when larger than
    ``ROUND_GAIN`` (:mod:`~imu_array_ros.fitting.rounds`; default None: the parameter and motion steps alone
    decide; discovery's confirming refits need only the likelihood).  With timing terms the fit runs trajectory
    rounds to their fixed point (:func:`~imu_array_ros.fitting.rounds.timing_rounds`): ``converged`` then says
    whether that criterion was met within ``TIMING_ROUNDS`` rounds, and loglik/nis "after" are those on the
    motion's own trajectory; keep_g: the
    linearisations keep G_n for the motion steps (fewer passes over the samples, the
    same steps to rounding; default None: as :func:`~imu_array_ros.fitting.problem.keep_schur` says, off
    outside it).  Raises
    :class:`CalibrationError` (one line) when the problem cannot be solved or
    identified.
    """
    if robust is not None:
        return _huber(samples, model, free, robust, dict(imus=imus, reference=reference, gauge=gauge,
                      max_iterations=max_iterations, tolerance=tolerance, progress=progress,
                      motion_model=motion_model, only=only, t0_ns=t0_ns, sandwich=sandwich, hold=hold,
                      cost_tolerance=cost_tolerance, keep_g=keep_g),
                      motion0, sigma)
    free = check_terms(free)
    if gauge not in ("reference", "mean"):
        raise CalibrationError(f"gauge must be 'reference' or 'mean', got {gauge!r}")
    fit = imu_indexes(model.names, imus, "imus")
    ref = _reference(model, fit, reference)
    prob = Problem(samples, model, free, fit, motion_model=motion_model, sigma=sigma, t0_ns=t0_ns, keep_g=keep_g)
    motion = prob.initial_motion(model) if motion0 is None else prob.check_motion(motion0)
    motion, lin, _, _ = motion_rounds(prob, model, motion)
    motion = prob.drop(~lin.ok, motion)
    prob.check_dof(prob.m)
    lin = prob.linearize(model, motion)  # with the free parameters, at the initial point
    gauge_fix = Gauge.find(prob, model, motion, lin, ref, gauge, _fixed(prob, model, only, hold))
    dof = prob.check_dof(gauge_fix.rank)
    before = lin.cost
    first = min(max_iterations, FAR_ITERATIONS) if prob.needs_derivatives else max_iterations  # on a held trajectory
    model, motion, lin, iterations, converged = levenberg_marquardt(prob, model, motion, lin, gauge_fix, first,
                                                                    tolerance, progress, cost_tolerance,
                                                                    last_lin=not prob.needs_derivatives)
    if prob.needs_derivatives:  # the timing terms' trajectory was held: rounds to its fixed point
        model, motion, lin, more, converged = timing_rounds(prob, model, motion, lin, gauge_fix, max_iterations,
                                                            tolerance, progress, cost_tolerance)
        iterations += more
    return _result(prob, model, motion, lin, gauge_fix, before, dof, iterations, converged, sandwich)


def _huber(samples, model, free, robust, options, motion0, sigma) -> FitResult:
    """fit_terms with Huber IRLS (:func:`~imu_array_ros.fitting.robust.huber_sigma`): a plain fit, then
    ``HUBER_ROUNDS`` refits from the last estimate with the readings reweighted on its residuals."""
    if robust != "huber":
        raise CalibrationError(f"robust must be None or 'huber', got {robust!r}")
    base = np.broadcast_to(model.std[None] if sigma is None else np.asarray(sigma, dtype=float),
                           (len(samples), model.n_imus, 6))
    res = fit_terms(samples, model, free, motion0=motion0, sigma=sigma, **options)
    first, current = res, base
    for _ in range(HUBER_ROUNDS):  # residuals normalised by the unweighted sigma, then reweighted
        current = huber_sigma(res.residuals * current / base, base)
        res = fit_terms(samples, res.model, free, motion0=np.nan_to_num(res.motion), sigma=current, **options)
    res.loglik_before, res.nis_before, res.huber_rounds = first.loglik_before, first.nis_before, HUBER_ROUNDS
    return res


class MotionFit(tuple):
    """What :func:`fit_motion` returns: the tuple (motion, loglik, residuals), unpacked as before, with how the
    fit ended: converged (the fixed-point criterion of :func:`~imu_array_ros.fitting.rounds.motion_rounds` met),
    rounds (trajectory rounds done; 0 without timing terms), step (largest norm of a sample's whitened
    Gauss-Newton step left) and gain (log-likelihood one more step would gain)."""

    converged: bool
    rounds: int
    step: float
    gain: float

    def __new__(cls, motion, loglik, residuals, converged, rounds, step, gain):
        out = super().__new__(cls, (motion, loglik, residuals))
        out.converged, out.rounds, out.step, out.gain = bool(converged), int(rounds), float(step), float(gain)
        return out

    @property
    def motion(self) -> np.ndarray:
        return self[0]

    @property
    def loglik(self) -> float:
        return self[1]

    @property
    def residuals(self) -> np.ndarray:
        return self[2]


def fit_motion(samples: ImuSamples, model: SensorModel, motion0=None, *, motion_model=None,
               sigma=None) -> MotionFit:
    """The ML motion of every sample with every term of ``model`` held (the engine's batched
    Gauss-Newton on each sample's motion coordinates, exact for the non-linear terms the fusion only
    compensates).  motion_model, sigma: as for :func:`fit_terms`.  With timing terms the timing terms read the
    motion through a held trajectory: trajectory rounds to their fixed point
    (:func:`~imu_array_ros.fitting.rounds.motion_rounds`, at most ``TIMING_ROUNDS``).

    Returns a :class:`MotionFit`: (motion (N, 9) [omega, omega_dot, s], log-likelihood over the valid axes,
    normalised residuals (N, K, 6), NaN on masked axes), and whether the criterion was met (``converged``).
    A sample whose motion is not identified keeps a ridge-regularised estimate; one identified but for
    coordinates no reading informs (a reading rate of an axis whose gyroscopes all saturate) its exact ML."""
    prob = Problem(samples, model, ("position",), np.arange(model.n_imus), motion_model=motion_model,
                   sigma=sigma)
    motion = prob.initial_motion(model) if motion0 is None else prob.check_motion(motion0)
    motion, lin, converged, rounds = motion_rounds(prob, model, motion)
    step, gain = motion_gap(prob, lin)
    return MotionFit(prob.expand(motion), prob.loglik(lin.cost), np.where(prob.valid, lin.r, np.nan), converged,
                     rounds, step, gain)


def _fixed(prob: Problem, model: SensorModel, only: dict | None, hold: Sequence[str] = ()) -> np.ndarray:
    """(M,) True for the parameters ``only`` holds (its term not fitted on that IMU), for the fields the
    engine never fits (``Field.fitted`` False: a clock's nominal period, a phase found by search) and for
    the parameters named in ``hold``."""
    fixed = np.zeros((len(prob.fit), prob.p), dtype=bool)
    offsets = prob.offsets
    for t in prob.free:
        col = offsets[t]
        for f in REGISTRY[t].fields:
            fixed[:, col:col + f.size] = not f.fitted
            col += f.size
    fixed = fixed.reshape(-1)
    if hold:
        names = {n: i for i, n in enumerate(prob.parameter_names())}
        unknown = [n for n in hold if n not in names]
        if unknown:
            raise CalibrationError(f"hold: {unknown[0]!r} is not a parameter of this fit")
        fixed[[names[n] for n in hold]] = True
    if fixed.all():
        raise CalibrationError(f"no parameter of {', '.join(prob.free)} is fitted by the engine")
    if not only:
        return fixed
    unknown = [t for t in only if t not in prob.free]
    if unknown:
        raise CalibrationError(f"only: term {unknown[0]!r} is not among the free terms ({', '.join(prob.free)})")
    offsets = prob.offsets
    for t, imus in only.items():
        on = set(imu_indexes(model.names, imus, f"only[{t!r}]").tolist())
        for j, k in enumerate(prob.fit):
            if k not in on:
                lo = j * prob.p + offsets[t]
                fixed[lo:lo + REGISTRY[t].dim()] = True
    if fixed.all():
        raise CalibrationError("only: no parameter left to fit")
    return fixed


def _reference(model: SensorModel, fit: np.ndarray, reference) -> int:
    """Position of the reference IMU within the fitted ones
    (:func:`~imu_array_ros.model.reference.reference_index`)."""
    return int(np.flatnonzero(fit == reference_index(model.names, reference, among=fit))[0])


def _result(prob: Problem, model: SensorModel, motion: np.ndarray, lin: Linearization, gauge: Gauge,
            before: float, dof: int, iterations: int, converged: bool, sandwich: bool = True) -> FitResult:
    """The FitResult at the estimate: the Cramér-Rao bound and the sandwich covariance in the gauge, NaN
    where held or not fitted."""
    s_z, _ = gauge.reduce(lin.S, lin.g)
    cov_z = inverse(s_z)
    cov = gauge.expand_covariance(cov_z)
    robust = None
    if sandwich and cov_z.size:
        z = gauge.basis if gauge.basis is not None else np.eye(prob.m)[:, gauge.keep]
        a = sample_influence(prob, model, motion, lin, z @ cov_z)
        robust = blocked_covariance(a[prob.used], prob.stamps[prob.used])
    cov_robust = None if robust is None else gauge.expand_covariance(robust.covariance)
    names = prob.parameter_names()
    mask = ~(prob.valid & prob.used[:, None, None])
    residuals = np.where(mask, np.nan, lin.r)
    motion = np.where(prob.used[:, None], prob.expand(motion), np.nan)
    return FitResult(model=model, free=prob.free, imus=tuple(model.names[k] for k in prob.fit),
                     parameter_names=names, theta=prob.values(model).reshape(-1), covariance=cov,
                     std=_stds(prob, model, gauge, cov),
                     held=[names[i] for i in gauge.held], gauge=gauge.lines, gauge_directions=gauge.directions,
                     loglik_before=prob.loglik(before), loglik_after=prob.loglik(lin.cost),
                     nis_before=2 * before / dof, nis_after=2 * lin.cost / dof, iterations=iterations,
                     converged=converged, samples_used=prob.n_used(), samples_dropped=prob.n - prob.n_used(),
                     dof=dof, motion=motion, residuals=residuals, covariance_robust=cov_robust,
                     std_robust={} if cov_robust is None else _stds(prob, model, gauge, cov_robust),
                     sandwich=robust)


def _stds(prob: Problem, model: SensorModel, gauge: Gauge, cov: np.ndarray) -> dict[str, np.ndarray]:
    """term -> (K, P) standard deviations from an (M, M) covariance, NaN where held or not fitted."""
    std_flat = np.sqrt(np.clip(np.diag(cov), 0.0, None)).reshape(len(prob.fit), prob.p)
    std_flat[np.unravel_index(np.array(gauge.held, dtype=int), std_flat.shape)] = np.nan
    if gauge.fixed is not None:
        std_flat.reshape(-1)[gauge.fixed] = np.nan
    std, col = {}, 0
    for t, size in zip(prob.free, prob.sizes):
        full = np.full((model.n_imus, size), np.nan)
        full[prob.fit] = std_flat[:, col:col + size]
        std[t] = full
        col += size
    return std
