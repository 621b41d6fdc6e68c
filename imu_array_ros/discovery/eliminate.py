"""Backward elimination: after the greedy forward steps, every finding re-tested given all the others.

A finding was admitted given the findings *before* it.  One found later can take over its signature (a
constant bias found first, then the bias's drift: the drift from the recording's first stamp carries a
mean, which the bias had absorbed; with both in, the bias is no longer needed).  So, at the last joint
exact fit (every finding's parameters together with the motion), each finding is tested given all the
others by the Wald test of its parameters' change from the model discovery started from, with the fit's
Cramér-Rao bound: W = d^T C^-1 d, chi-square with the number of identified parameters -- asymptotically
the likelihood ratio of the joint fit with and without it.  A pooled finding is tested on its shared
value when the tie test accepts one (:func:`~.scopes.tie_test`), else on every IMU's values.

The finding with the largest p-value among those no longer significant at the level they were admitted
at (the Bonferroni level of their step) is dropped, the others refitted exactly without it, and the test
repeated until every finding left passes.  Each drop is reported (``rejected``, reason given).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.confirm import only_imus, update_finding
from imu_array_ros.discovery.scopes import tie_test
from imu_array_ros.discovery.subset import is_own, term_indexes, wald
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

__all__ = ["wald_given_others", "backward_eliminate"]


def wald_given_others(fit, f, base: SensorModel, alpha: float) -> tuple[float, int, float]:
    """(W, dof, p) of finding ``f`` (discover.Finding) given every other parameter of the joint ``fit``:
    its parameters' change from ``base`` (the model discovery started from) against the fit's CRB."""
    imus = list(f.imus)
    if f.scope != "imu" and not is_own(f.scope):
        tie = tie_test(fit, f.effect, imus, base.names, base.terms[f.effect].values[imus])
        if tie["p"] >= alpha:  # one shared value: test it (its covariance: the GLS mean's)
            d, sd = np.asarray(tie["values"]), np.asarray(tie["std"])
            cov_phi = _shared_covariance(fit, f.effect, imus)
            return wald(d, cov_phi if cov_phi is not None else np.diag(sd ** 2))
    idx = term_indexes(fit, f.effect, imus)
    d = fit.theta[idx] - np.asarray(base.terms[f.effect].values[imus], dtype=float).reshape(-1)
    return wald(d, fit.covariance[np.ix_(idx, idx)])


def _shared_covariance(fit, term: str, imus) -> np.ndarray | None:
    """Covariance of the GLS shared value of ``term`` over ``imus`` (as :func:`~.scopes.tie_test` forms it)."""
    p = REGISTRY[term].dim()
    idx = term_indexes(fit, term, imus)
    cov = fit.covariance[np.ix_(idx, idx)]
    keep = np.diag(cov) > 0
    if not keep.any():
        return None
    t = np.tile(np.eye(p), (len(imus), 1))[keep]
    w = np.linalg.pinv(cov[np.ix_(keep, keep)], hermitian=True)
    return np.linalg.pinv(t.T @ w @ t, hermitian=True)


def backward_eliminate(samples, start: SensorModel, findings: list, fit, motion, levels, alpha: float,
                       say=lambda text: None):
    """Drop, one at a time, the findings no longer significant given all the others (module docstring).

    start: the model the forward search started from (findings' values are changes from it); findings:
    discover.Finding list; fit: the last joint exact fit of all of them (FitResult); levels: the Bonferroni
    level of every step (finding.step - 1 indexes it).  Returns (kept findings, dropped [dict], fit or None,
    model, motion): the model and motion of the refit without the dropped ones (unchanged when none is)."""
    kept, dropped, current = list(findings), [], fit.model if fit is not None else start
    while kept and fit is not None:
        tests = [(f, *wald_given_others(fit, f, start, alpha)) for f in kept]
        weak = [(p, f, stat, dof) for f, stat, dof, p in tests if not p < levels[f.step - 1]]
        if not weak:
            break
        p, f, stat, dof = max(weak, key=lambda x: x[0])
        level = levels[f.step - 1]
        reason = (f"dropped after the forward search: given the other findings its parameters' Wald test "
                  f"(joint exact fit, CRB) gives {stat:.3g} on {dof} dof, p = {p:.3g} >= {level:.2g}, the level "
                  f"it was admitted at")
        say(f"backward: {f.effect} on {f.sensor} no longer needed given the others (p {p:.2g}); dropped")
        dropped.append({"effect": f.effect, "sensors": list(f.candidate.sensors), "scope": f.scope,
                        "step": f.step, "reason": reason, "statistic": stat, "dof": dof, "p": p})
        f.candidate.accepted = False
        f.candidate.note = reason
        kept.remove(f)
        reset = start.terms[f.effect].values[list(f.imus)]
        v = fit.model.terms[f.effect].values.copy()
        v[list(f.imus)] = reset
        base = fit.model.with_terms(**{f.effect: v})
        if not kept:
            fit, current = None, base
            break
        only = only_imus([(g.effect, g.imus) for g in kept])
        imus = sorted({k for ks in only.values() for k in ks})
        try:
            fit = fit_terms(samples, base, list(only), imus=imus, only=only, motion0=motion, max_iterations=30,
                            sandwich=False)
        except CalibrationError as err:  # keep the forward result rather than fail the whole discovery
            kept.append(f)
            dropped.pop()
            f.candidate.accepted = True
            f.candidate.note = f"backward elimination could not refit without it: {err}"
            fit = None
            break
        current = fit.model
        motion = np.where(np.isfinite(fit.motion), fit.motion, motion)
        for g in kept:
            update_finding(g, fit, start, alpha)
    return kept, dropped, fit, current, motion
