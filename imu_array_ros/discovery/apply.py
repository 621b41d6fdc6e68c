"""``discover --apply``: the findings of mismatch discovery as a calibration (the contract of
:mod:`imu_array_ros.calibration.result`)."""

from __future__ import annotations

import numpy as np

from dataclasses import dataclass, field

from imu_array_ros.calibration import scoring
from imu_array_ros.calibration.guards import check_calibration
from imu_array_ros.calibration.result import Calibration, provenance
from imu_array_ros.discovery.threads import on_one_blas_thread
from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["findings_calibration", "StartedScorer"]


@dataclass
class StartedScorer:
    """:class:`~imu_array_ros.calibration.scoring.WindowScorer` (the log-likelihood of ``samples`` with every
    sample's motion at its ML estimate) whose motion fit of a model in ``starts`` [(model, motion (N, 9))] starts
    from that motion instead of the fused one: discover's own ML motions of the model it started from and of the
    model with the findings.  The same fit (``fit_motion`` to its criterion, in the caller's reading-rates state,
    on the same samples) from a start at its optimum rather than a pass of the fusion away: the score is the same
    maximum, to the fit's tolerance, in a few linearisations instead of a whole fit (whole exp_3: two of them,
    ~30 s, were the --apply check).  A model not in ``starts`` (a calibration on file), one with only linear terms
    (the fusion's motion is then exact) or a motion of another length: scored as WindowScorer does."""

    samples: ImuSamples
    starts: list = field(default_factory=list)

    def __call__(self, model: SensorModel) -> float:
        motion = next((m for known, m in self.starts if known is model), None)
        if (motion is None or not model.nonlinear_terms or self.samples is None
                or np.shape(motion) != (len(self.samples.stamps), 9)):
            return scoring.window_loglik(self.samples, model)
        start = np.where(np.isfinite(motion), motion, 0.0)  # as the fused start: zero where it has no motion
        return float(fit_motion(self.samples, model, start).loglik)


@on_one_blas_thread
def findings_calibration(discovery, samples: ImuSamples, source: str | None = None, *,
                         start: SensorModel | None = None) -> Calibration:
    """The description extended with the terms :func:`~imu_array_ros.discovery.discover.discover` found
    (values and Cramér-Rao std of the last joint fit, on the IMUs they were found on), scored on
    ``samples`` (the recording it ran on).  With no findings the model is the input's.  ``start``: the model
    discovery started from; the result then passes the calibrations' checks
    (:func:`~imu_array_ros.calibration.guards.check_calibration`: plausible values, fits the recording at least
    as well) or CalibrationError says why it is not installed.  The new model's score (a fit of the whole
    recording's motion) is computed once, kept in ``score`` for the install, and on one BLAS thread as discover
    itself runs (:mod:`~imu_array_ros.discovery.threads`)."""
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
    starts = [(m, getattr(s, "motion", None)) for m, s in ((start, d.baseline), (d.model, d.after))]
    cal = Calibration(method="discover", model=d.model, std=std, record=record, scorer=StartedScorer(samples, starts),
                      data="recording", summary_line=line, details=d)
    cal.score = cal.score_of(cal.model)
    if start is not None:
        check_calibration(cal, start)
    return cal
