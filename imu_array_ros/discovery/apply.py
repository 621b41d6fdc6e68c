"""``discover --apply``: the findings of mismatch discovery as a calibration (the contract of
:mod:`imu_array_ros.calibration.result`).

Before anything is written the calibration passes the calibrations' checks
(:func:`~imu_array_ros.calibration.guards.check_calibration`), among them (c): the new model scores the recording at
least as well as the model discovery started from.  A score is the log-likelihood with every sample's motion at its
maximum-likelihood estimate (:func:`~imu_array_ros.calibration.scoring.window_loglik`): for a model with
non-linear terms a motion fit of the whole recording (on whole exp_3 ~14 CPU s, the --apply check's cost).  The
log-likelihood at *any* motion is at most that maximum, so the new model at discover's own ML motion of it
(:func:`motion_loglik`, one residual pass) is a lower bound of its score: when the bound already clears the start's
score, (c) holds for the score too and the fit is not needed.  Otherwise the new model is fitted and (c) decided on
its score, as before.  The start is always scored as before (the fusion's motion; a fit when it has non-linear
terms): both sides are log-likelihoods of the same samples under the two models, the new one's bounded from below.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imu_array_ros.calibration import scoring
from imu_array_ros.calibration.guards import check_calibration
from imu_array_ros.calibration.result import LOGLIK_TOLERANCE, Calibration, Installed, provenance
from imu_array_ros.discovery.threads import on_one_blas_thread, single_blas_thread
from imu_array_ros.fitting.problem import Problem
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["findings_calibration", "install_findings", "motion_loglik", "OnceScorer"]


def motion_loglik(samples: ImuSamples, model: SensorModel, motion: np.ndarray) -> float:
    """The log-likelihood of ``samples`` under ``model`` at one motion (N, 9) [omega, omega_dot, s] of every
    sample, the timing terms reading that motion's own trajectory, in the caller's reading-rates state (with them,
    each sample's rates at their least squares given the motion): the function of the motion whose maximum is the
    model's score (``fit_motion`` reports its value at the motion it ends on: the same problem and sum), so a lower
    bound of the score, in one residual pass.  Non-finite entries are taken as 0 (as the fused start does for a
    sample without a fused motion)."""
    prob = Problem(samples, model, ("position",), np.arange(model.n_imus))
    z = prob.check_motion(np.where(np.isfinite(motion), motion, 0.0))
    prob.freeze(z)
    r = prob.residuals(model, z, prob.derivatives(z))
    return prob.loglik(0.5 * float(np.sum(r * r)))


@dataclass
class OnceScorer:
    """:class:`~imu_array_ros.calibration.scoring.WindowScorer` that scores each model (object) once (the
    fits-better check asks for the start's score after the lower bound has)."""

    samples: ImuSamples
    done: list = field(default_factory=list, repr=False)

    def __call__(self, model: SensorModel) -> float:
        for known, value in self.done:
            if known is model:
                return value
        value = float(scoring.window_loglik(self.samples, model))
        self.done.append((model, value))
        return value


@on_one_blas_thread
def findings_calibration(discovery, samples: ImuSamples, source: str | None = None, *,
                         start: SensorModel | None = None) -> Calibration:
    """The description extended with the terms :func:`~imu_array_ros.discovery.discover.discover` found
    (values and Cramér-Rao std of the last joint fit, on the IMUs they were found on), scored on
    ``samples`` (the recording it ran on).  With no findings the model is the input's.  ``start``: the model
    discovery started from; the result then passes the calibrations' checks
    (:func:`~imu_array_ros.calibration.guards.check_calibration`: plausible values, fits the recording at least
    as well) or CalibrationError says why it is not installed.  The new model's score (a fit of the whole
    recording's motion) is computed at most once, kept in ``score`` for the install, on one BLAS thread as discover
    itself runs (:mod:`~imu_array_ros.discovery.threads`); not at all when its lower bound at discover's own ML
    motion of it (``discovery.after.motion``, :func:`motion_loglik`) already clears the start's score (module
    docstring): ``score`` is then None, and :func:`install_findings` computes it only to compare with a file."""
    d = discovery
    std = {}
    for name in sorted({f.effect for f in d.findings}):
        sd = np.full(d.model.terms[name].values.shape, np.nan)
        for f in d.findings:
            if f.effect == name:
                sd[list(f.imus)] = f.std if f.imu_std is None else f.imu_std
        std[name] = sd
    record = {
        "method": "imu-array discover: terms found by mismatch discovery, fitted by the engine (fit_terms); "
                  "*_std = Cramer-Rao bound",
        **provenance(),
        **({} if source is None else {"recording": str(source)}),
        "findings": [f"{f.effect} on {f.sensor}" for f in d.findings],
        "log_likelihood_before": float(d.baseline.loglik),
        "log_likelihood_after": float(d.after.loglik),
    }
    line = (f"{len(d.findings)} findings; log-likelihood {d.baseline.loglik:.8g} -> {d.after.loglik:.8g}")
    cal = Calibration(method="discover", model=d.model, std=std, record=record, scorer=OnceScorer(samples),
                      data="recording", summary_line=line, details=d)
    motion = getattr(d.after, "motion", None)
    if (start is not None and samples is not None and motion is not None and cal.model.nonlinear_terms
            and np.shape(motion) == (len(samples.stamps), 9)):
        bound = motion_loglik(samples, cal.model, motion)
        if np.isfinite(bound) and bound + cal.allowance >= cal.score_of(start) - LOGLIK_TOLERANCE:
            cal.score = bound  # check (c) on the bound: the score is at least that
            check_calibration(cal, start)
            cal.score = None  # a bound, not the score
            return cal
    cal.score = cal.score_of(cal.model)
    if start is not None:
        check_calibration(cal, start)
    return cal


def install_findings(cal: Calibration, desc: ArrayDescription, out: str | Path) -> Installed:
    """``cal.install(desc, out)`` on one BLAS thread (scoring a calibration on file is a whole-recording fit); the
    new model is scored only when a description on file is compared with it (``Calibration.install``)."""
    with single_blas_thread():
        return cal.install(desc, out)
