"""``discover --apply``: the findings of mismatch discovery as a calibration (the contract of
:mod:`imu_array_ros.calibration.result`)."""

from __future__ import annotations

import numpy as np

from imu_array_ros.calibration.guards import check_calibration
from imu_array_ros.calibration.result import Calibration, provenance
from imu_array_ros.calibration.scoring import WindowScorer
from imu_array_ros.discovery.threads import on_one_blas_thread
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["findings_calibration"]


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
    cal = Calibration(method="discover", model=d.model, std=std, record=record, scorer=WindowScorer(samples),
                      data="recording", summary_line=line, details=d)
    cal.score = cal.score_of(cal.model)
    if start is not None:
        check_calibration(cal, start)
    return cal
