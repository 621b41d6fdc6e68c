"""Confirming a candidate by an exact refit (the engine's ``fit_terms`` with ``only``), and a finding's
values from the latest joint fit, at one IMU or at a pooled scope (:mod:`.scopes`).

A pooled candidate is fitted with each IMU's own value: the engine has no tie of parameters across IMUs,
and adding one would thread a linear map through its gauge search, identifiability check and covariances.
Instead the per-IMU values are tested for one shared value (:func:`~.scopes.tie_test`, a Wald test with
the exact fit's CRB, asymptotically the likelihood ratio of the tied fit) and the shared value is their
generalised least-squares mean, which is asymptotically the tied maximum-likelihood estimate.
"""

from __future__ import annotations

import numpy as np
import scipy.stats

from imu_array_ros.discovery.explain import Candidate
from imu_array_ros.discovery.scopes import tie_test
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["confirm", "only_imus", "update_finding", "COST_TOLERANCE"]

#: the exact refit stops when a step gains less log-likelihood than this: the decision reads the gain (>= half a
#: chi-square quantile, ~10-30), so the last steps that move the motion by < 1e-3 of its own sd gain nothing
#: (on the whole exp_3 capture they were ~7 of 19 iterations, each a pass over every sample)
COST_TOLERANCE = 0.1


def only_imus(pairs) -> dict:
    """term -> sorted IMU indexes from [(term, IMU indexes)]."""
    only: dict[str, set[int]] = {}
    for t, imus in pairs:
        only.setdefault(t, set()).update(imus)
    return {t: sorted(ks) for t, ks in only.items()}


def update_finding(f, fit, model: SensorModel, alpha: float) -> None:
    """A finding's (discover.Finding) values and std from a joint fit; for a pooled one also the tie test
    and its shared value (shared when the tie test's p >= alpha)."""
    v, sd = fit.model.terms[f.effect].values, fit.std[f.effect]
    if f.scope == "imu":
        f.values, f.std = v[f.k].copy(), sd[f.k].copy()
        return
    imus = list(f.imus)
    f.imu_values, f.imu_std = v[imus].copy(), sd[imus].copy()
    f.tie = tie_test(fit, f.effect, imus, model.names, model.terms[f.effect].values[imus])
    f.values, f.std = f.tie["values"], f.tie["std"]
    f.shared = f.tie["p"] >= alpha


def confirm(samples, current: SensorModel, accepted, c: Candidate, motion, level: float, model: SensorModel,
             alpha: float):
    """Exact refit of every finding so far plus ``c`` (the engine, ``only``: a pooled candidate with each IMU's
    own value); (FitResult, delta loglik) or a reason string when the exact likelihood ratio does not confirm
    the candidate.  A shared scope is confirmed by the gain of the shared value: the per-IMU fit's gain less
    half the tie test's statistic (the Wald approximation of the tied fit's likelihood ratio) when the tie
    test accepts one value at ``alpha``, else by the per-IMU fit's gain against a chi-square with all its
    parameters."""
    only = only_imus([(f.effect, f.imus) for f in accepted.values()] + [(c.effect, c.imus)])
    imus = sorted({k for ks in only.values() for k in ks})
    try:
        fit = fit_terms(samples, current, list(only), imus=imus,
                        only=only, motion0=motion, max_iterations=30, sandwich=False,
                        cost_tolerance=COST_TOLERANCE)  # CRB only: no sandwich pass
    except CalibrationError as err:
        return f"the exact fit failed: {err}"
    delta = fit.loglik_after - fit.loglik_before
    gain, dof = delta, c.dof
    if c.scope != "imu" and c.scope != "all own":
        tie = tie_test(fit, c.effect, list(c.imus), model.names, model.terms[c.effect].values[list(c.imus)])
        if tie["p"] >= alpha:
            gain = delta - 0.5 * tie["statistic"]
        else:
            dof = tie["dof"] + c.dof
    need = 0.5 * scipy.stats.chi2.isf(level, dof)
    if not np.isfinite(gain) or gain < need:
        return (f"not confirmed by the exact fit: log-likelihood gain {gain:.3g} < {need:.3g} "
                f"(the score test's first-order gain was {c.delta_loglik:.3g})")
    return fit, float(delta)
