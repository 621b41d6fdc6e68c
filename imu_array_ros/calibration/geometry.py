"""Geometry calibration: the accelerometer positions from a few seconds of hand-twisting (carlsson2017).

Problem (carlsson2017 eq. 1-4, with the whole sensor model): every array
sample n has an unknown motion x_n = [omega, omega_dot, s]; accelerometer k
reads h_k(x_n, p_k) (rotated sensor frame, calibrated intrinsics: every term
of the :class:`~imu_array_ros.model.sensor_model.SensorModel`), the gyroscopes read
omega.  The positions p_k (the reference IMU's held: only relative positions
are observable) and the motion are estimated jointly by maximum likelihood.

Two solvers of the same problem:

* ``"bcd"`` -- block coordinate descent, carlsson2017 Alg. 1.  Alternate
  (a) the ML motion of every sample for the current positions, with the fusion
  core (:class:`~imu_array_ros.fusion.model_fusion.ModelFusion`, vectorised
  over samples) and (b) the least-squares positions for that motion.  Step (b)
  is eq. 9 generalised to the sensor model: with the weighted position Jacobian
  J_nk = W_k dh_k/dp_k (for the bare model J_nk = R_k^T C_n / sigma,
  C_n = [omega]x^2 + [omega_dot]x) and the weighted residual r_nk,
  p_k += (sum_n J_nk^T J_nk)^-1 sum_n J_nk^T r_nk, one 3x3 system per IMU (the
  same one for every IMU when their noise is equal and isotropic and their
  intrinsics orthogonal, as in the paper).  The readings are affine in p_k for
  every linear term, so this is the exact minimiser of step (b), O(N).
* ``"joint"`` -- the fitting engine (:func:`~imu_array_ros.fitting.engine.fit_terms`
  with ``free=["position"]``): Gauss-Newton on positions and motion together,
  the motion eliminated by the Schur complement, also O(N) per iteration.

Both end at the same stationary point of the likelihood; BCD converges
linearly (its rate is set by the coupling of motion and positions), the joint
solver quadratically, so ``"joint"`` is the default (``benchmarks/bench_geometry.py``
compares iterations, time and likelihood).  Whichever solves it, the
uncertainty written is the engine's sandwich covariance at the estimate
(:mod:`imu_array_ros.fitting.robust`: the Fisher information of the joint
problem, positions and every sample's motion unknown, with the scores' spread
measured over time blocks of the window), which holds when the model does not
fit to the noise level; the Cramér-Rao bound (carlsson2017 leaves it open) is
kept beside it (``position_crb``).

Samples: a sample with a missing or saturated reading is dropped (the BCD's
shared 3x3 system assumes every axis), and so is one with too little rotation
to carry information about the positions (||C_n||_F from the fused motion
below ``min_excitation`` rad/s^2 or below ``NOISE_FACTOR`` times what the fused
motion's own noise gives it -- at rest the fused omega_dot is noise -- and the
same test with the gyroscopes alone, ``select_rotating(..., gyroscopes=True)``:
with uncalibrated accelerometer biases a still array's fused omega_dot reads
~14 rad/s^2 on the MIMU4444BT captures, so still poses would pass as rotation
and pull the positions by centimetres).  What is left must determine the positions:
at least ``MIN_SAMPLES`` samples (with N = 2 the paper's RMSE does not fall
with iterations, Fig. 4), and sum_n C_n^T C_n well conditioned -- it is
singular when every sample turns about one fixed axis (omega parallel to
omega_dot), the positions along that axis then being invisible to the
accelerometers.  Otherwise :class:`~imu_array_ros.errors.CalibrationError`
names the missing motion; the engine's own identifiability test follows.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from imu_array_ros.calibration.result import fit_statistics, provenance
from imu_array_ros.calibration.scoring import loglik_constant, profile_window
from imu_array_ros.calibration.selection import MIN_EXCITATION, check_samples, require_rotation, select_rotating
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.reference import reference_index
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context, motion_derivative

__all__ = ["GeometryCalibration", "calibrate_geometry", "METHODS", "DEFAULT_METHOD",
           "MIN_EXCITATION"]

METHODS = ("joint", "bcd")
#: the solver used unless one is named (see the module docstring and benchmarks/results/geometry.md)
DEFAULT_METHOD = "joint"
#: BCD: converged when also the last iteration raised the log-likelihood by less than this
LOGLIK_GAIN = 1e-3
#: BCD: samples per chunk of the position step (bounds its memory: ~K x 0.6 kB per sample)
BCD_CHUNK = 4096
#: BCD: iteration cap when none is given (it converges linearly)
BCD_MAX_ITERATIONS = 500
#: joint solver: iteration cap when none is given
JOINT_MAX_ITERATIONS = 50


@dataclass
class GeometryCalibration:
    """The result of :func:`calibrate_geometry` (SI units).

    model: the input model with the calibrated positions; initial_positions
    (K, 3); position_std (K, 3): the sandwich (misfit-robust) standard
    deviation, 0 for the reference IMU (held: exact in the chosen gauge);
    position_crb (K, 3): the Cramér-Rao bound of the joint problem (what
    position_std would be if the model fitted to the noise level); std_kind:
    how position_std was estimated (block length); covariance (3K, 3K): the sandwich;
    loglik_before/after: log-likelihood of the window with the motion fitted
    (profiled out) at the initial and the calibrated positions; nis_before/after:
    sum of squared normalised residuals per degree of freedom (~1 for a model
    that fits); rms_before/after (K,): each accelerometer's residual RMS (m/s^2);
    history (BCD): (iteration, log-likelihood, largest position change m,
    positions (K, 3) at that iteration) per iteration; samples_total, samples_used, dropped: reason -> count; window_ns:
    first and last stamp of the window; used (N,): samples used.
    """

    model: SensorModel
    method: str
    reference: str
    initial_positions: np.ndarray
    position_std: np.ndarray
    covariance: np.ndarray = field(repr=False)
    position_crb: np.ndarray = field(default=None, repr=False)
    std_kind: str = "Cramer-Rao bound"
    loglik_before: float = float("nan")
    loglik_after: float = float("nan")
    nis_before: float = float("nan")
    nis_after: float = float("nan")
    rms_before: np.ndarray = field(default=None, repr=False)
    rms_after: np.ndarray = field(default=None, repr=False)
    iterations: int = 0
    converged: bool = False
    history: list = field(default_factory=list, repr=False)
    samples_total: int = 0
    samples_used: int = 0
    dropped: dict = field(default_factory=dict)
    window_ns: tuple = (0, 0)
    seconds: float = 0.0
    used: np.ndarray = field(default=None, repr=False)

    @property
    def positions(self) -> np.ndarray:
        return self.model.positions

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    def position_change(self) -> np.ndarray:
        """(K,) |calibrated - initial| per IMU, m."""
        return np.linalg.norm(self.positions - self.initial_positions, axis=1)

    def summary(self) -> str:
        """One line: samples used, largest position change, residual RMS before -> after, worst std."""
        change = self.position_change()
        worst = int(np.argmax(change))
        std = np.linalg.norm(self.position_std, axis=1)
        wstd = int(np.argmax(std))
        rms = lambda v: float(np.sqrt(np.mean(np.asarray(v) ** 2)))  # noqa: E731
        return (f"{self.method}: {self.samples_used} of {self.samples_total} samples used, "
                f"{self.iterations} iterations{'' if self.converged else ' (NOT converged)'}; "
                f"largest position change {change[worst] * 1e3:.3f} mm ({self.names[worst]}); "
                f"accelerometer residual RMS {rms(self.rms_before):.4g} -> {rms(self.rms_after):.4g} m/s^2; "
                f"worst std {std[wstd] * 1e6:.1f} um ({self.names[wstd]})")

    def record(self) -> dict:
        """The ``calibration:`` block of the written description."""
        f = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {
            "method": f"geometry ({self.method}): maximum likelihood of the accelerometer positions jointly with the "
                      f"motion (carlsson2017; {'block coordinate descent, Alg. 1' if self.method == 'bcd' else 'Schur-complement Gauss-Newton'}); "
                      f"position_std = {self.std_kind} (position_crb: the Cramer-Rao bound of the joint problem)",
            **provenance(),
            "position_crb": {n: [f(v) for v in row] for n, row in zip(self.names, self.position_crb)},
            "reference": self.reference,
            "window": {"first_stamp_ns": int(self.window_ns[0]), "last_stamp_ns": int(self.window_ns[1]),
                       "seconds": (int(self.window_ns[1]) - int(self.window_ns[0])) / 1e9},
            "samples_total": int(self.samples_total),
            "samples_used": int(self.samples_used),
            "samples_dropped": {k: int(v) for k, v in self.dropped.items()},
            **fit_statistics(self),
            "residual_rms_before": {n: f(v) for n, v in zip(self.names, self.rms_before)},
            "residual_rms_after": {n: f(v) for n, v in zip(self.names, self.rms_after)},
        }


# --------------------------------------------------------------------------- public entry points


def calibrate_geometry(samples: ImuSamples, model: SensorModel, *, reference=None, method: str = DEFAULT_METHOD,
                       max_iterations: int | None = None, tolerance: float = 1e-3,
                       min_excitation: float = MIN_EXCITATION, recenter: bool = True,
                       progress: Callable[[int, float], None] | None = None) -> GeometryCalibration:
    """Calibrate the accelerometer positions of ``model`` on a window of array samples.

    samples: stamps strictly increasing; raw readings in the sensor frames
    (NaN: missing).  reference: IMU (name or
    index) whose position is held (default the first); method: "joint" or
    "bcd"; tolerance: converged when every position step is below
    ``tolerance`` of its standard deviation (BCD: with the motion held, and
    the last iteration's log-likelihood gain below ``LOGLIK_GAIN``; joint: the
    engine's test, whose last gain is then ~tolerance^2 x parameters / 2); min_excitation: rad/s^2 (see the
    module docstring); recenter (BCD only): re-centre the common shift of the
    positions every iteration (an exact symmetry, absorbed by the specific
    force; False is the literal Alg. 1 with the reference held, whose common
    mode converges by only (K-1)/K per iteration); progress(iteration,
    log-likelihood) once per iteration.
    Raises :class:`CalibrationError` (one line) when the window cannot
    determine the positions.
    """
    t_start = time.perf_counter()
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    samples = check_samples(samples, model)
    ref = reference_index(model.names, reference)
    selection = select_rotating(samples, model, min_excitation, gyroscopes=True)
    require_rotation(selection)
    used = selection.used
    window, motion = samples.select(used), selection.motion[used]
    before = profile_window(window, model)
    if method == "joint":
        fit = fit_terms(window, model, ["position"], reference=ref, motion0=motion,
                        max_iterations=JOINT_MAX_ITERATIONS if max_iterations is None else max_iterations,
                        tolerance=tolerance, progress=_loglik_progress(progress, window, model))
        calibrated, iterations, converged, history = fit.model, fit.iterations, fit.converged, []
    else:
        calibrated, iterations, converged, history = _bcd(
            window, model, ref, BCD_MAX_ITERATIONS if max_iterations is None else max_iterations,
            tolerance, progress, recenter)
        # the Cramér-Rao bound at the BCD estimate: the engine's Fisher information, no iteration
        fit = fit_terms(window, calibrated, ["position"], reference=ref, max_iterations=0)
    after = profile_window(window, calibrated)
    robust = fit.std_robust.get("position", fit.std["position"])  # the CRB when too few samples for the sandwich
    std = np.where(np.isfinite(robust), robust, 0.0)
    crb = np.where(np.isfinite(fit.std["position"]), fit.std["position"], 0.0)
    dof = fit.dof
    return GeometryCalibration(
        model=calibrated, method=method, reference=model.names[ref], initial_positions=model.positions.copy(),
        position_std=std, position_crb=crb,
        covariance=fit.covariance if fit.sandwich is None else fit.covariance_robust,
        std_kind=fit.sandwich.describe() if fit.sandwich else "Cramer-Rao bound (too few samples for the sandwich)",
        loglik_before=before.loglik, loglik_after=after.loglik,
        nis_before=2 * before.cost / dof, nis_after=2 * after.cost / dof, rms_before=before.rms,
        rms_after=after.rms, iterations=iterations, converged=converged, history=history,
        samples_total=len(samples), samples_used=selection.n_used, dropped=selection.dropped,
        window_ns=(int(samples.stamps[0]), int(samples.stamps[-1])), seconds=time.perf_counter() - t_start, used=used)


def _loglik_progress(progress, samples: ImuSamples, model: SensorModel):
    """The engine reports its cost; turn it into the log-likelihood the BCD reports."""
    if progress is None:
        return None
    const = loglik_constant(model, samples.valid(model))
    return lambda it, cost: progress(it, const - cost)


# --------------------------------------------------------------------------- block coordinate descent


def _bcd(samples: ImuSamples, model: SensorModel, ref: int, max_iterations: int, tolerance: float, progress,
         recenter: bool = True):
    """carlsson2017 Alg. 1 (see the module docstring); returns (model, iterations, converged, history)."""
    stamps = samples.stamps
    valid = samples.valid(model)
    y = samples.readings
    w = np.where(valid, 1.0 / model.std[None], 0.0)
    fix = np.zeros(model.n_imus, dtype=bool)
    fix[ref] = True
    const = loglik_constant(model, valid)
    history, converged, iterations = [], False, 0
    for iterations in range(max_iterations + 1):
        fused, _ = ModelFusion(model).fuse(samples)  # (a) ML motion for the current positions
        if len(fused) != len(stamps):
            raise CalibrationError(f"the motion of {len(stamps) - len(fused)} samples is not identified at the "
                                   f"current positions (iteration {iterations}); the calibration diverged")
        wdd, sfd = motion_derivative(stamps, fused.omega_dot), motion_derivative(stamps, fused.specific_force)
        a, b, cost = np.zeros((model.n_imus, 3, 3)), np.zeros((model.n_imus, 3)), 0.0
        for lo in range(0, len(stamps), BCD_CHUNK):  # (b) eq. 9: one 3x3 system per IMU, summed by chunks
            sel = slice(lo, lo + BCD_CHUNK)
            ctx = motion_context(stamps[sel], fused.omega[sel], fused.omega_dot[sel], fused.specific_force[sel],
                                 model.rotations, t0_ns=int(stamps[0]), omega_ddot=wdd[sel],
                                 specific_force_dot=sfd[sel])
            jac = model.jacobians(ctx, ("position",), motion=False)
            r = w[sel] * np.where(valid[sel], y[sel] - jac.predicted, 0.0)
            jp = w[sel][..., None] * jac.params["position"]  # (n, K, 6, 3)
            a += np.einsum("nkri,nkrj->kij", jp, jp, optimize=True)
            b += np.einsum("nkri,nkr->ki", jp, r, optimize=True)
            cost += 0.5 * float(np.sum(r * r))
        step = np.linalg.solve(a, b[..., None])[..., 0]
        step = step - step[fix] if recenter else np.where(fix[:, None], 0.0, step)
        loglik = const - cost
        sd = np.sqrt(np.einsum("kii->ki", np.linalg.inv(a)))
        change = float(np.max(np.abs(step)))
        history.append((iterations, loglik, change, model.positions.copy()))
        if progress is not None:
            progress(iterations, loglik)
        gain = loglik - history[-2][1] if len(history) > 1 else np.inf
        if np.max(np.abs(step) / sd) < tolerance and gain < LOGLIK_GAIN:
            converged = True
            break
        if iterations == max_iterations:
            break
        model = model.with_terms(position=model.positions + step)
    return model, iterations, converged, history
