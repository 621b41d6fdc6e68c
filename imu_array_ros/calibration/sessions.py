"""Several recordings of one array: device constants combined, session states kept per recording.

A MEMS IMU has two kinds of parameters (docs/description.md):

* **device constants** -- positions, gains, misalignments, non-orthogonalities, time offsets, clock rates: the
  same at every power-up.  Several recordings estimate them better than one.
* **session states** -- the turn-on biases of the accelerometers and gyroscopes (:data:`SESSION_TERMS`; the clock
  phases too, which are never written): new at every power-up.  On the real MIMU4444BT captures the biases moved
  13-14 times their within-recording std from one capture to the next, every other field 1-2 times.  What a
  description can say about them is their value at the last calibration and how much they change at a power-up
  (their *turn-on repeatability*); the fusion re-estimates the gyroscope biases whenever the array is still.

:func:`combine_calibrations` (what ``imu-array calibrate all REC1 REC2 ...`` runs after calibrating each
recording): each recording is calibrated on its own (its session states fitted with its device constants, every
recording in the same gauge: the reference IMU's held values), then

* a device constant is the inverse-variance weighted mean of the recordings' estimates, with the std of the
  weighted mean scaled by the Birge ratio sqrt(chi^2 / (R - 1)) where the estimates scatter more than their std
  (the std is never below what the scatter shows).  To first order this is the joint maximum likelihood of the
  device constants with the session states profiled out per recording (independent recordings: the
  log-likelihoods add, and each recording's is quadratic about its own estimate with the inverse covariance as
  curvature); correlations between parameters are left out (each parameter is combined on its own).
* a session state is written as the mean over the recordings (each power-up counts once) with the *turn-on
  repeatability* as its ``_std``: the std over the recordings, pooled (RMS) over the term's parameters -- with
  a few recordings one parameter's own spread has too few degrees of freedom to be its std (on the real
  captures: per-parameter spreads of exp_1-3 put exp_4-6's gyroscope biases at RMS z 35, the pooled one at 3.4).
  How far the next power-up's value may be from it.
  Its within-recording std and the ratio of the two go in the record.

With one recording the biases are that recording's (their ``_std`` the within-recording one) and the record says
that their turn-on repeatability is not measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from imu_array_ros.calibration.result import Calibration, SumScorer, provenance
from imu_array_ros.errors import CalibrationError

__all__ = ["SESSION_TERMS", "SessionCalibration", "combine_calibrations", "session_record"]

#: terms whose values are new at every power-up (written: the last value and the turn-on repeatability)
SESSION_TERMS = ("accelerometer_bias", "gyroscope_bias")


def _median(x) -> float | None:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else None


def session_record(cal: Calibration) -> dict:
    """The ``session_states`` entry of a one-recording calibration's record: which written terms are session
    states and that one recording does not measure their turn-on repeatability."""
    terms = [t for t in SESSION_TERMS if t in cal.std]
    if not terms:
        return {}
    return {"session_states": {
        t: {"written": "this recording's value", "std": "within-recording",
            "median_within_std": _median(cal.std[t]),
            "turn_on_repeatability": "not measured by one recording (calibrate all REC1 REC2 ... measures it)"}
        for t in terms}}


@dataclass
class SessionCalibration:
    """What :func:`combine_calibrations` did: the per-recording calibrations (``recordings``), their sources,
    and per term: ``within`` (R, K, P) each recording's std, ``values`` (R, K, P), ``spread`` (K, P) the std
    over the recordings, ``birge`` (K, P) sqrt(chi^2 / (R - 1)) of the device constants."""

    recordings: list[Calibration]
    sources: list[str]
    values: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    within: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    spread: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    birge: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def repeatability(self) -> dict[str, float | None]:
        """term -> median over its parameters of (spread over the recordings / within-recording std)."""
        out = {}
        for t, s in self.spread.items():
            within = self.within[t]
            fitted = np.isfinite(within).any(axis=0)  # held parameters: NaN in every recording
            w = np.full(within.shape[1:], np.nan)
            w[fitted] = np.nanmedian(within[:, fitted], axis=0)
            with np.errstate(divide="ignore", invalid="ignore"):
                out[t] = _median(np.where(w > 0, s / w, np.nan))
        return out


def _combine_constant(v: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, std, birge) of a device constant's estimates v (R, K, P) with stds s; parameters without a finite
    positive std in every recording (held: the same value in each) keep the first recording's value, std NaN."""
    ok = np.all(np.isfinite(s) & (s > 0), axis=0)
    w = np.where(ok, 1.0 / np.where(ok, s, 1.0) ** 2, 0.0)
    wsum = np.where(ok, w.sum(axis=0), 1.0)
    mean = np.where(ok, (w * v).sum(axis=0) / wsum, v[0])
    r = len(v)
    chi2 = (w * (v - mean) ** 2).sum(axis=0)
    birge = np.where(ok, np.sqrt(chi2 / max(r - 1, 1)), np.nan)
    std = np.where(ok, np.sqrt(1.0 / wsum) * np.maximum(1.0, np.nan_to_num(birge)), np.nan)
    return mean, std, birge


def combine_calibrations(cals: Sequence[Calibration], sources: Sequence[str | None]) -> Calibration:
    """One calibration from per-recording ones of the same IMUs, each in the same gauge (module docstring)."""
    cals = list(cals)
    if len(cals) < 2:
        raise CalibrationError("combining calibrations needs at least two recordings")
    names = cals[0].names
    if any(c.names != names for c in cals):
        raise CalibrationError("the recordings' calibrations are of different IMUs")
    terms = list(dict.fromkeys(t for c in cals for t in c.std))
    missing = [(t, i) for t in terms for i, c in enumerate(cals) if t not in c.std]
    if missing:
        t, i = missing[0]
        raise CalibrationError(f"recording {i + 1} ({sources[i]}) did not calibrate {t} (the others did): "
                               "each recording must calibrate the same terms; see its skipped stages")
    details = SessionCalibration(recordings=cals, sources=[str(s) for s in sources])
    model, std, rows = cals[0].model, {}, {}
    for t in terms:
        v = np.stack([c.model.terms[t].values for c in cals])
        s = np.stack([np.asarray(c.std[t], dtype=float) for c in cals])
        details.values[t], details.within[t] = v, s
        details.spread[t] = np.std(v, axis=0, ddof=1)
        if t in SESSION_TERMS:  # turn-on repeatability pooled over the term's parameters (2 dof each with
            # three recordings: one parameter's own spread is too uncertain to be its std)
            spread = details.spread[t]
            pooled = np.sqrt(np.nanmean(spread ** 2)) if np.isfinite(spread).any() else np.nan
            value, written = v.mean(axis=0), np.full_like(spread, pooled)
        else:
            value, written, details.birge[t] = _combine_constant(v, s)
        model = model.with_terms(**{t: value})
        std[t] = written
    repeat = details.repeatability()
    for t in terms:
        rows[t] = {"kind": "session state" if t in SESSION_TERMS else "device constant",
                   "median_within_std": _median(details.within[t]),
                   "median_spread_over_recordings": _median(details.spread[t]),
                   "median_spread_over_within_std": repeat[t]}
        if t in SESSION_TERMS:
            rows[t]["written"] = "mean over the recordings; _std = turn-on repeatability (std over the recordings)"
        else:
            rows[t]["written"] = ("inverse-variance weighted mean; _std = std of the mean x max(1, Birge ratio)")
            rows[t]["median_birge_ratio"] = _median(details.birge[t])
    record = {"method": f"calibrate all on {len(cals)} recordings: each calibrated on its own, device constants "
                        "combined (inverse-variance weighted, Birge-scaled), session states (biases) written as "
                        "their mean with the turn-on repeatability as _std",
              **provenance(), "recordings": [str(s) for s in sources], "terms": rows,
              "per_recording": [{k: v for k, v in c.record.items() if k != "previous"} for c in cals]}
    converged = all(c.converged for c in cals)
    worst = max((r for r in repeat.items() if r[0] not in SESSION_TERMS and r[1] is not None),
                key=lambda r: r[1], default=None)
    summary = (f"{len(cals)} recordings combined; device constants: " +
               (f"largest median spread/std {worst[1]:.3g} ({worst[0]})" if worst else "none") +
               "; session states: " + ", ".join(f"{t} turn-on repeatability {_median(details.spread[t]):.3g}"
                                                f" ({repeat[t]:.3g}x within-recording std)"
                                                for t in SESSION_TERMS if t in details.spread and repeat[t]))
    data = " and ".join(dict.fromkeys(c.data for c in cals))
    scorers = [c.scorer for c in cals if c.scorer is not None]
    return Calibration(method=cals[0].method, model=model, std=std, record=record,
                       scorer=SumScorer(scorers) if len(scorers) == len(cals) else None, data=data,
                       converged=converged, summary_line=summary, details=details)
