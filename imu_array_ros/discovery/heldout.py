"""Held-out check of discovery's findings: refitted on half of the time blocks, scored on the other half; or, when
they were found on a subsample of a long recording's blocks, scored on the blocks it left out (all of them when the
whole recording's motion under the model the search started from is at hand, else the blocks half-way between the
searched ones, :func:`between_gain`)."""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.confirm import only_imus
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_motion, fit_terms
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["heldout_gain", "complement_gain", "between_gain", "HELDOUT_SCALE"]

#: held-out scale of the readings' sigma: samples of held-out blocks keep their motion but give the parameters
#: 1e-8 of their information
HELDOUT_SCALE = 1e4


def heldout_gain(samples, model: SensorModel, findings, blocks, base_motion, base_r) -> dict:
    """The findings refitted on even blocks scored on odd ones and vice versa (exact, motion re-estimated):
    log-likelihood of the held-out samples with and without them.  base_motion, base_r: the ML motion and
    normalised residuals of the recording under ``model`` (the baseline of step 1)."""
    only = only_imus([(f.effect, f.imus) for f in findings])
    imus = sorted({k for ks in only.values() for k in ks})
    half = (blocks % 2).astype(bool)
    gain, nis_b, nis_a, n_h = 0.0, [], [], 0
    for held in (half, ~half):
        sigma = np.broadcast_to(model.std, (len(blocks),) + model.std.shape).copy()
        sigma[held] *= HELDOUT_SCALE
        try:
            fit = fit_terms(samples, model, list(only), imus=imus, only=only,
                            sigma=sigma, motion0=base_motion, max_iterations=30, sandwich=False)
        except CalibrationError as err:
            return {"error": str(err)}
        _, _, r = fit_motion(samples, fit.model, np.where(np.isfinite(fit.motion), fit.motion, base_motion))
        a = np.nan_to_num(r[held]) ** 2
        b = np.nan_to_num(base_r[held]) ** 2
        gain += 0.5 * float(b.sum() - a.sum())
        n_h += int(held.sum())
        nis_b.append(b.sum())
        nis_a.append(a.sum())
    return {"delta_loglik": gain, "samples": n_h, "sum_r2_before": float(sum(nis_b)),
            "sum_r2_after": float(sum(nis_a)),
            "ratio_after_before": float(sum(nis_a) / sum(nis_b)) if sum(nis_b) > 0 else None,
            "method": "findings refitted on the even time blocks, scored on the odd ones, and vice versa; "
                      "the motion re-estimated in both"}


def complement_gain(after_r: np.ndarray, start_r: np.ndarray, searched: np.ndarray, label: str) -> dict:
    """Held-out check of findings fitted on a subsample (sample indexes ``searched``): the log-likelihood of the
    other samples under the findings (normalised residuals ``after_r`` (N, K, 6), motion re-estimated) against the
    model the search started from (``start_r``)."""
    held = np.ones(len(after_r), dtype=bool)
    held[searched] = False
    a = float((np.nan_to_num(after_r[held]) ** 2).sum())
    b = float((np.nan_to_num(start_r[held]) ** 2).sum())
    return {"delta_loglik": 0.5 * (b - a), "samples": int(held.sum()), "sum_r2_before": b, "sum_r2_after": a,
            "ratio_after_before": a / b if b > 0 else None,
            "method": f"findings fitted on {label} (the search's), scored on the blocks it left out; the motion "
                      f"re-estimated there, the model the search started from as the baseline"}


def between_gain(samples, found: SensorModel, start: SensorModel, motion, held: np.ndarray, label: str,
                 between: str) -> dict:
    """Held-out check of findings fitted on a subsample (``label``) when the whole recording's motion under the
    model the search started from is not at hand: the samples ``held`` (``between``: the blocks half-way between
    the searched ones, chosen by their place in time) fitted alone under the findings (model ``found``) and under
    ``start``, the motion re-estimated from ``motion`` (the whole recording's under ``found``); the log-likelihood
    of the two compared there, as :func:`complement_gain` does on every left-out block."""
    part = samples.select(held)
    a = float((np.nan_to_num(fit_motion(part, found, motion[held])[2]) ** 2).sum())
    b = float((np.nan_to_num(fit_motion(part, start, motion[held])[2]) ** 2).sum())
    return {"delta_loglik": 0.5 * (b - a), "samples": int(len(held)), "sum_r2_before": b, "sum_r2_after": a,
            "ratio_after_before": a / b if b > 0 else None,
            "method": f"findings fitted on {label} (the search's), scored on {between} (held out, each fitted alone "
                      f"under the findings and under the model the search started from, the motion re-estimated)"}
