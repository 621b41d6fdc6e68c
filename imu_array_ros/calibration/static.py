"""Static multi-pose calibration of the accelerometers (nilsson2014) and the gyroscope biases.

The array rests in P poses (the faces of an icosahedron, or any still poses;
:func:`~imu_array_ros.calibration.still.find_still_poses` finds them in a
recording and averages each).  At rest, IMU k's accelerometer reads
(nilsson2014 eq. 1-3, our sensor model with omega = omega_dot = 0)::

    y_nk = K_k L_k (I + [xi_k]x) R_k^T s_n + b_k + v_nk,     |s_n| = g,

with gain K (3), non-orthogonality L (3), bias b (3), misalignment xi (3; the
reference IMU's is 0: its axes define the array frame) and the unknown pose
s_n (2 degrees of freedom: its direction).  Its gyroscope reads its bias.

Methods:

* ``"ml"`` -- maximum likelihood with the one fitting engine
  (:func:`~imu_array_ros.fitting.engine.fit_terms`) and the static motion
  model (:class:`~imu_array_ros.fitting.motion_models.StaticMotion`: the
  pose nuisance of nilsson2014, profiled out by the Schur complement); the
  noise of a pose average is the description's noise / sqrt(samples
  averaged).  Started from the nominal values (the paper's) or from the PCA
  solution.  Robust: iteratively reweighted (Huber on each IMU's whitened
  residual in each pose, scale from the median), so that one bumped pose or
  one bad IMU reading does not pull the fit; the weights are reported.
  Standard deviations are the Cramér-Rao bound from the engine's Fisher
  information at the estimate; when the fit is worse than the noise explains
  (NIS > 1: real sensors), the written ``_std`` are scaled by sqrt(NIS) (the
  a-posteriori variance factor) and the calibration block says so.
* ``"pca"`` -- rupniewski's closed form (:mod:`~imu_array_ros.calibration.pca`),
  extended to biased accelerometers; its CRB at the estimate is reported too.

Terms can be switched off individually (``terms``): e.g. without
``accelerometer_misalignment`` it is nilsson2014's reduced calibration, each
IMU on its own ([6] in the paper).  The consistency figure of nilsson2014
Sec. IV -- the trace of the covariance across IMUs of the compensated forces,
averaged over the poses -- is :func:`consistency`; :func:`consistency_db`
compares two models on the same poses.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from imu_array_ros.calibration.result import fit_statistics
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_motion, fit_terms
from imu_array_ros.fitting.motion_models import StaticMotion
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.reference import reference_index
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms.triad import triad_matrix, triads_in_reference_frame

__all__ = ["ACCELEROMETER_TERMS", "STATIC_TERMS", "METHODS", "StaticCalibration", "calibrate_static",
           "compensate", "consistency", "consistency_db", "static_loglik", "PoseScorer", "reframe_accelerometers",
           "MIN_POSES", "HUBER"]

ACCELEROMETER_TERMS = ("accelerometer_gain", "accelerometer_nonorthogonality", "accelerometer_misalignment",
                       "accelerometer_bias")
#: what a static calibration fits by default: the accelerometers of nilsson2014 and the gyroscope biases
STATIC_TERMS = ACCELEROMETER_TERMS + ("gyroscope_bias",)
METHODS = ("ml", "pca")
#: nilsson2014: twelve non-coplanar poses for the full model, nine without the misalignment
MIN_POSES = {True: 12, False: 9}
#: Huber threshold on an IMU's whitened 3-axis residual norm in units of the robust scale (99 % of chi(3))
HUBER = 3.37
#: median of the chi distribution with 3 degrees of freedom (the whitened norm of pure noise)
_CHI3_MEDIAN = 1.5382
ROBUST_ITERATIONS = 10


@dataclass
class StaticCalibration:
    """What :func:`calibrate_static` estimated.

    model: the input model with the calibrated terms; terms: the terms fitted;
    std: term -> (K, 3) Cramér-Rao standard deviations (NaN: held or not
    fitted); variance_factor: max(1, NIS) (the written ``_std`` are std x its
    square root); specific_force (P, 3): the poses in the array frame;
    weights (P, K): robust weights (1: full weight); loglik/nis before (the
    input model, poses fitted) and after; residual_rms (K,) accelerometer
    residual RMS per IMU after (m/s^2, unweighted); consistency before/after
    (m/s^2)^2 (:func:`consistency`); skipped: IMUs without data (left as they
    were); held: parameters held to fix the frame.
    """

    model: SensorModel
    method: str
    reference: str
    terms: tuple[str, ...]
    std: dict[str, np.ndarray]
    variance_factor: float
    specific_force: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)
    loglik_before: float
    loglik_after: float
    nis_before: float
    nis_after: float
    residual_rms: np.ndarray = field(repr=False)
    consistency_before: float
    consistency_after: float
    poses: int
    iterations: int
    converged: bool
    skipped: list[str]
    held: list[str]
    gravity: float
    seconds: float
    initial: str

    @property
    def names(self) -> tuple[str, ...]:
        return self.model.names

    @property
    def improvement_db(self) -> float:
        return 10 * np.log10(self.consistency_before / self.consistency_after)

    def downweighted(self, threshold: float = 0.5) -> list[tuple[int, str, float]]:
        """(pose, IMU, weight) of the pose readings the robust fit kept below ``threshold`` weight."""
        idx = np.argwhere(self.weights < threshold)
        return [(int(p), self.names[k], float(self.weights[p, k])) for p, k in idx]

    def summary(self) -> str:
        """One line: poses, iterations, consistency before -> after, NIS, worst-fitting IMU."""
        worst = int(np.nanargmax(self.residual_rms))
        down = self.downweighted()
        return (f"{self.method}: {self.poses} poses, {len(self.names) - len(self.skipped)} IMUs"
                f"{f' ({len(self.skipped)} skipped: no data)' if self.skipped else ''}, "
                f"{self.iterations} iterations{'' if self.converged else ' (NOT converged)'}; consistency "
                f"{self.consistency_before:.3g} -> {self.consistency_after:.3g} (m/s^2)^2 "
                f"({self.improvement_db:+.1f} dB); NIS {self.nis_before:.3g} -> {self.nis_after:.3g}; "
                f"worst residual RMS {self.residual_rms[worst]:.3g} m/s^2 ({self.names[worst]})"
                f"{f'; {len(down)} pose readings down-weighted' if down else ''}")

    def written_std(self) -> dict[str, np.ndarray]:
        """The standard deviations written to the description: CRB x sqrt(variance factor)."""
        return {t: v * np.sqrt(self.variance_factor) for t, v in self.std.items()}

    def record(self) -> dict:
        """This stage's entry of the ``calibration:`` block."""
        f = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        how = {"ml": "maximum likelihood, poses profiled out (nilsson2014), robust (Huber) reweighting",
               "pca": "closed-form PCA (rupniewski), extended to biased accelerometers"}[self.method]
        return {
            "stage": "static",
            "method": f"static ({self.method}): {how}; _std = Cramer-Rao bound x sqrt(max(1, NIS))",
            "terms": list(self.terms),
            "reference": self.reference,
            "initial": self.initial,
            "gravity": self.gravity,
            "poses": int(self.poses),
            **fit_statistics(self),
            "variance_factor": f(self.variance_factor),
            "consistency_before": f(self.consistency_before),
            "consistency_after": f(self.consistency_after),
            "consistency_improvement_db": f(self.improvement_db),
            "residual_rms_after": {n: f(v) for n, v in zip(self.names, self.residual_rms)},
            "downweighted": [{"pose": p, "imu": n, "weight": round(w, 4)} for p, n, w in self.downweighted()],
            "skipped_imus": list(self.skipped),
            "held": list(self.held),
        }


# --------------------------------------------------------------------------- the consistency figure


def compensate(accel: np.ndarray, model: SensorModel) -> np.ndarray:
    """(P, K, 3) forces in the array frame from static accelerometer readings (P, K, 3):
    R_k (K L (I + [xi]x))^-1 (y - b) per IMU (NaN stays NaN)."""
    full = np.linalg.inv(_accelerometer_maps(model))  # array <- sensor
    bias = model.terms["accelerometer_bias"].values
    return np.einsum("kij,pkj->pki", full, np.asarray(accel, dtype=float) - bias[None])


def _accelerometer_maps(model: SensorModel) -> np.ndarray:
    """(K, 3, 3) each accelerometer's reading of a static specific force in the array frame:
    K L (I + [xi]x) R_k^T (sensor <- array)."""
    t = model.terms
    return triad_matrix(t["accelerometer_gain"].values, t["accelerometer_nonorthogonality"].values,
                        t["accelerometer_misalignment"].values) @ np.swapaxes(model.rotations, 1, 2)


def consistency(accel: np.ndarray, model: SensorModel) -> float:
    """nilsson2014's figure: the trace of the covariance across IMUs of the compensated forces,
    averaged over the poses, (m/s^2)^2.  IMUs without a reading in a pose are left out of it."""
    u = compensate(accel, model)
    ok = np.isfinite(u).all(axis=2)  # (P, K)
    cnt = ok.sum(axis=1)
    if np.any(cnt < 2):
        raise CalibrationError("consistency needs at least two IMUs with readings in every pose")
    mean = np.nansum(np.where(ok[..., None], u, 0.0), axis=1) / cnt[:, None]
    dev = np.where(ok[..., None], u - mean[:, None], 0.0)
    return float(np.mean(np.sum(dev ** 2, axis=(1, 2)) / (cnt - 1)))


def consistency_db(accel: np.ndarray, model: SensorModel, baseline: SensorModel) -> float:
    """How much more consistent ``model`` makes the poses than ``baseline``, dB (positive: better)."""
    return float(10 * np.log10(consistency(accel, baseline) / consistency(accel, model)))


# --------------------------------------------------------------------------- re-expressing a frame


def reframe_accelerometers(model: SensorModel, reference: int | str) -> SensorModel:
    """``model`` with the accelerometer triads re-expressed in the array frame that the ``reference``
    IMU's accelerometer defines (its misalignment 0), exactly: what a static calibration with that
    reference estimates.  For comparing a true (simulated) model, or calibrations with other
    references, with an estimate.  Positions and gyroscopes are left alone."""
    ref = model.names.index(reference) if isinstance(reference, str) else int(reference)
    _, gain, l, xi = triads_in_reference_frame(_accelerometer_maps(model), model.rotations, ref)
    return model.with_terms(accelerometer_gain=gain, accelerometer_nonorthogonality=l,
                            accelerometer_misalignment=xi)


# --------------------------------------------------------------------------- calibration


def pose_samples(accel, gyro, model: SensorModel) -> ImuSamples:
    """The P pose averages (P, K, 3) as samples for the engine (one per second: the stamps carry no meaning
    with the static motion model)."""
    accel, gyro = np.asarray(accel, dtype=float), np.asarray(gyro, dtype=float)
    return ImuSamples(np.arange(len(accel), dtype=np.int64) * 1_000_000_000, accel, gyro, model.names)


def _sigma(model: SensorModel, counts: np.ndarray) -> np.ndarray:
    """(P, K, 6) noise of the pose averages: the description's noise / sqrt(samples averaged)."""
    c = np.asarray(counts, dtype=float)
    return model.std[None] / np.sqrt(np.where(c > 0, c, 1.0))[..., None]


def static_loglik(accel, gyro, counts, model: SensorModel, gravity: float = STANDARD_GRAVITY) -> float:
    """Log-likelihood of the pose averages under ``model`` with every pose fitted (how a calibration on
    file is compared with a new one on the same poses)."""
    return fit_motion(pose_samples(accel, gyro, model), model, motion_model=StaticMotion(gravity),
                      sigma=_sigma(model, counts))[1]


@dataclass
class PoseScorer:
    """A calibration's :class:`~imu_array_ros.calibration.result.Scorer` on still-pose averages:
    :func:`static_loglik` of (P, K, 3) ``accel`` and ``gyro`` averaged over ``counts`` (P, K) samples."""

    accel: np.ndarray
    gyro: np.ndarray
    counts: np.ndarray
    gravity: float = STANDARD_GRAVITY

    def __call__(self, model: SensorModel) -> float:
        return static_loglik(self.accel, self.gyro, self.counts, model, self.gravity)


def calibrate_static(accel, gyro, counts, model: SensorModel, *, method: str = "ml",
                     terms: Sequence[str] = STATIC_TERMS, reference=None, gravity: float = STANDARD_GRAVITY,
                     initial: str = "nominal", robust: bool = True, max_iterations: int = 50,
                     progress: Callable[[int, float], None] | None = None) -> StaticCalibration:
    """Calibrate the static terms of ``model`` from P pose averages.

    accel, gyro (P, K, 3): mean readings of every IMU in every pose (sensor
    frames; NaN: the IMU had no valid reading there); counts (P, K): samples
    averaged.  method: "ml" or "pca"; terms: which terms to fit (a subset of
    :data:`STATIC_TERMS`; the others are held at their values in ``model``);
    reference: IMU (name or index) whose accelerometer axes define the array
    frame (default the first); initial: "nominal" (the model's values, as the
    paper) or "pca" (ML only); robust: Huber reweighting (ML only);
    progress(iteration, cost) per engine iteration.
    Raises :class:`CalibrationError` (one line) for too few or degenerate poses.
    """
    t_start = time.perf_counter()
    if method not in METHODS:
        raise CalibrationError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if initial not in ("nominal", "pca"):
        raise CalibrationError(f"initial must be 'nominal' or 'pca', got {initial!r}")
    terms = tuple(dict.fromkeys(terms))
    unknown = [t for t in terms if t not in STATIC_TERMS]
    if unknown or not terms:
        raise CalibrationError(f"static terms must be among {', '.join(STATIC_TERMS)}, got {', '.join(terms) or 'none'}")
    accel, gyro = np.asarray(accel, dtype=float), np.asarray(gyro, dtype=float)
    counts = np.asarray(counts)
    p, k = accel.shape[0], model.n_imus
    if accel.shape != (p, k, 3) or gyro.shape != (p, k, 3) or counts.shape != (p, k):
        raise CalibrationError(f"pose arrays must be (P, {k}, 3) and counts (P, {k}); got {accel.shape}, "
                               f"{gyro.shape}, {counts.shape}")
    needed = MIN_POSES["accelerometer_misalignment" in terms]
    if p < needed:
        raise CalibrationError(f"too few poses: {p} (at least {needed} non-coplanar poses are needed for "
                               f"{', '.join(terms)}; set the array down on more faces)")
    has = np.isfinite(accel).all(axis=2).sum(axis=0) >= needed  # (K,) IMUs with enough poses
    skipped = [model.names[i] for i in np.flatnonzero(~has)]
    if has.sum() < 1:
        raise CalibrationError(f"no IMU has readings in {needed} poses")
    ref = reference_index(model.names, reference)
    if not has[ref]:
        raise CalibrationError(f"the reference IMU {model.names[ref]} has readings in fewer than {needed} poses; "
                               "choose another reference")
    imus = np.flatnonzero(has)
    poses, sigma = pose_samples(accel, gyro, model), _sigma(model, counts)
    motion_model = StaticMotion(gravity)
    before = fit_motion(poses, model, motion_model=StaticMotion(gravity), sigma=sigma)
    start = model
    if method == "pca" or initial == "pca":
        start = _pca_start(accel, gyro, counts, model, terms, ref, gravity, imus)
    if method == "pca":
        # the CRB at the closed-form estimate (no iteration), for the written _std
        res = fit_terms(poses, start, terms, imus=imus, reference=ref, motion_model=motion_model,
                        sigma=sigma, max_iterations=0)
        weights = np.ones((p, k))
    else:
        res, weights = _ml(poses, start, terms, imus, ref, motion_model, sigma, robust,
                           max_iterations, progress)
    after_motion, after_loglik, resid = fit_motion(poses, res.model, motion_model=StaticMotion(gravity),
                                                   sigma=sigma)
    dof = max(res.dof, 1)
    acc_res = resid[..., :3] * sigma[..., :3]  # back to m/s^2
    ok = np.isfinite(acc_res)
    rms = np.sqrt(np.sum(np.where(ok, acc_res, 0.0) ** 2, axis=(0, 2)) / ok.sum(axis=(0, 2)).clip(1))
    rms[~ok.any(axis=(0, 2))] = np.nan
    nis_after = float(np.nansum(resid ** 2) / dof)
    nis_before = float(np.nansum(before[2] ** 2) / dof)
    std = {t: res.std[t] for t in terms}
    return StaticCalibration(
        model=res.model, method=method, reference=model.names[ref], terms=terms, std=std,
        variance_factor=max(1.0, nis_after), specific_force=after_motion[:, 6:9], weights=weights,
        loglik_before=before[1], loglik_after=after_loglik, nis_before=nis_before, nis_after=nis_after,
        residual_rms=rms, consistency_before=consistency(accel[:, has], _subset(model, has)),
        consistency_after=consistency(accel[:, has], _subset(res.model, has)), poses=p,
        iterations=res.iterations, converged=res.converged or method == "pca", skipped=skipped, held=res.held,
        gravity=float(gravity), seconds=time.perf_counter() - t_start,
        initial="pca" if (method == "pca" or initial == "pca") else "nominal")


def _subset(model: SensorModel, keep: np.ndarray) -> SensorModel:
    """The model of the IMUs ``keep`` (bool (K,)), for the consistency figure."""
    from dataclasses import replace

    idx = np.flatnonzero(keep)
    terms = {n: t.with_values(t.values[idx]) for n, t in model.terms.items()}
    return replace(model, names=tuple(model.names[i] for i in idx), rotations=model.rotations[idx],
                   acc_std=model.acc_std[idx], gyro_std=model.gyro_std[idx], terms=terms)


def _ml(poses, start, terms, imus, ref, motion_model, sigma, robust, max_iterations, progress):
    """The engine's ML fit, iteratively reweighted (Huber) when ``robust``: returns (FitResult, weights)."""
    p, k = poses.accel.shape[:2]
    weights = np.ones((p, k))
    model, total = start, 0
    for _ in range(ROBUST_ITERATIONS if robust else 1):
        sig = sigma / np.sqrt(weights)[..., None]
        res = fit_terms(poses, model, terms, imus=imus, reference=ref, motion_model=motion_model,
                        sigma=sig, max_iterations=max_iterations, progress=progress)
        total += res.iterations
        if not robust:
            break
        r = np.nan_to_num(res.residuals[..., :3]) / np.sqrt(weights)[..., None]  # whitened by the noise alone
        norm = np.linalg.norm(r, axis=2)
        valid = np.isfinite(res.residuals[..., :3]).all(axis=2)
        scale = max(1.0, float(np.median(norm[valid])) / _CHI3_MEDIAN)
        new = np.where(valid, np.minimum(1.0, HUBER * scale / np.maximum(norm, 1e-300)), 1.0)
        model = res.model
        if np.max(np.abs(new - weights)) < 1e-3:
            break
        weights = new
    res.iterations = total
    return res, weights


def _pca_start(accel, gyro, counts, model, terms, ref, gravity, imus) -> SensorModel:
    """The model with the PCA solution in the accelerometer terms being fitted, and the count-weighted
    mean gyroscope reading as the gyroscope bias (when fitted)."""
    from imu_array_ros.calibration.pca import pca_array

    sub = np.zeros(model.n_imus, dtype=bool)
    sub[imus] = True
    sm = _subset(model, sub)
    sol = pca_array(accel[:, imus], sm, reference=int(np.flatnonzero(imus == ref)[0]), gravity=gravity)
    values = {}
    for t in terms:
        if t in sol.values:
            v = model.terms[t].values.copy()
            v[imus] = sol.values[t]
            values[t] = v
    if "gyroscope_bias" in terms:
        c = np.asarray(counts, dtype=float)[..., None] * np.isfinite(gyro)
        v = model.terms["gyroscope_bias"].values.copy()
        v[imus] = (np.nansum(c * np.nan_to_num(gyro), axis=0) / np.maximum(c.sum(axis=0), 1))[imus]
        values["gyroscope_bias"] = v
    return model.with_terms(**values)
