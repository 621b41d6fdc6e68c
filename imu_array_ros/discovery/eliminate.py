"""Backward elimination: after the greedy forward steps, every finding re-tested given all the others.

A finding was admitted given the findings *before* it.  One found later can take over its signature (a
constant bias found first, then the bias's drift: the drift from the recording's first stamp carries a
mean, which the bias had absorbed; with both in, the bias is no longer needed).  So, at the last joint
exact fit (every finding's parameters together with the motion), each finding is tested given all the
others by the Wald test of its parameters' change from the model discovery started from, with the fit's
Cramér-Rao bound: W = d^T C^-1 d, chi-square with the number of identified parameters -- asymptotically
the likelihood ratio of the joint fit with and without it -- up to the fit's gauge freedoms: a change a gauge
freedom undoes (with the other free parameters) is no change (d = B c, c free; e.g. a time offset common to
every sensor, which the fit fixes by holding one sensor's at whatever value it was given).  A pooled finding
is tested on its shared value when the tie test accepts one (:func:`~.scopes.tie_test`), else on every IMU's
values.

The finding with the largest p-value among those no longer significant is dropped, the others refitted
exactly without it, and the test repeated until every finding left passes.  Each drop is reported
(``rejected``, reason given).  A finding is still significant at :func:`backward_level`: the larger of the
level it was admitted at (the Bonferroni level of its step, alpha over that step's candidates) and alpha over
the findings re-tested.  The re-test is of m hypotheses chosen before it, not a choice among the step's
candidates again: a finding the others make redundant has a p-value about uniform given them and is kept
with probability about alpha / m; at the admission level alone a true constant bias found before a true
drift of the same sensor, which takes three quarters of its information (their columns correlate 0.87), was
dropped at p = 8.6e-5 against 7.5e-5 (planar4, 40 s; both at oracle evidence >= 100).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.linalg
import scipy.special
import scipy.stats

from imu_array_ros.discovery.confirm import refit, update_finding
from imu_array_ros.discovery.nested import holds
from imu_array_ros.discovery.scopes import tie_test
from imu_array_ros.discovery.subset import gauge_basis, is_own, restricted, scope_label, term_indexes, wald
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

__all__ = ["wald_given_others", "backward_eliminate", "backward_level", "dropped_notes", "simplest_adequate"]


def wald_given_others(fit, f, base: SensorModel, alpha: float) -> tuple[float, int, float]:
    """(W, dof, p) of finding ``f`` (discover.Finding) given every other parameter of the joint ``fit``:
    its parameters' change from ``base`` (the model discovery started from) against the fit's CRB, up to the fit's
    gauge freedoms (a change the gauge can undo, with the other parameters, is no change)."""
    imus = list(f.imus)
    if f.scope != "imu" and not is_own(f.scope):
        tie = tie_test(fit, f.effect, imus, base.names, base.terms[f.effect].values[imus])
        if tie["p"] >= alpha:  # one shared value: test it (its covariance: the GLS mean's)
            d, sd = np.asarray(tie["values"]), np.asarray(tie["std"])
            cov_phi = _shared_covariance(fit, f.effect, imus)
            return wald(d, cov_phi if cov_phi is not None else np.diag(sd ** 2))
    idx = term_indexes(fit, f.effect, imus)
    d = fit.theta[idx] - np.asarray(base.terms[f.effect].values[imus], dtype=float).reshape(-1)
    # a gauge freedom's move is no change (the fit held one of the moved parameters at a value of its choosing:
    # e.g. a common time offset of every sensor, held on the reference IMU): d = B c, c free
    stat, dof = restricted(d, fit.covariance[np.ix_(idx, idx)], gauge_basis(fit, idx))
    return stat, dof, _p(stat, dof)


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


def backward_level(admitted: float, alpha: float, retested: int) -> float:
    """The level a finding admitted at ``admitted`` is re-tested at among ``retested`` findings (module
    docstring): the larger of ``admitted`` and alpha / retested."""
    return max(float(admitted), float(alpha) / max(int(retested), 1))


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
        weak = [(p, f, stat, dof) for f, stat, dof, p in tests
                if not p < backward_level(levels[f.step - 1], alpha, len(kept))]
        if not weak:
            break
        p, f, stat, dof = max(weak, key=lambda x: x[0])
        level = backward_level(levels[f.step - 1], alpha, len(kept))
        reason = (f"dropped after the forward search: given the other findings its parameters' Wald test "
                  f"(joint exact fit, CRB) gives {stat:.3g} on {dof} dof, p = {p:.3g} >= {level:.2g} (the larger "
                  f"of the level it was admitted at, {levels[f.step - 1]:.2g}, and alpha / {len(kept)} findings "
                  f"re-tested)")
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
        try:
            fit = refit(samples, base, [(g.effect, g.imus) for g in kept], motion)
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


def _restriction(fit, start: SensorModel, f, ks, t: np.ndarray):
    """(W, dof, phi) of the restriction "``f``'s term on each IMU of ``ks`` = T phi_k" (T (P, r); r = 0: nothing
    on them), its other IMUs free, up to the fit's gauge freedoms: the Wald test of the joint fit's changes of
    the term on ``f``'s IMUs, and the GLS phi (of ``ks``'s first IMU)."""
    imus = list(f.imus)
    p_dim, r = REGISTRY[f.effect].dim(), t.shape[1]
    idx = term_indexes(fit, f.effect, imus)
    d = fit.theta[idx] - np.asarray(start.terms[f.effect].values[imus], dtype=float).reshape(-1)
    x = np.hstack([scipy.linalg.block_diag(*[t if k in ks else np.eye(p_dim) for k in imus]),
                   gauge_basis(fit, idx)])  # a gauge freedom's move is no change
    stat, dof, sol = restricted(d, fit.covariance[np.ix_(idx, idx)], x, solution=True)
    first = sum(r if k in ks else p_dim for k in imus[:imus.index(ks[0])]) if len(ks) else 0
    return stat, dof, sol[first:first + r]


def _p(stat: float, dof: int) -> float:
    return float(scipy.stats.chi2.sf(stat, dof)) if dof > 0 else 1.0


def _simplest_change(fit, start: SensorModel, findings: list, terms, alpha: float):
    """(p, finding, IMUs, inner term or None, phi, W, dof) of the simplest adequate hypothesis
    (:func:`simplest_adequate`), else None: first the largest set of an own-scope finding's IMUs that carry
    nothing (added by each one's p, largest first, while the joint test accepts; at least one IMU kept), else
    the one IMU whose held term is adequate with the largest p."""
    covered = {(f.effect, k) for f in findings for k in f.imus}
    best = None
    for f in findings:
        if (f.scope != "imu" and not is_own(f.scope)) or len(f.imus) < 2:
            continue
        none = np.zeros((REGISTRY[f.effect].dim(), 0))
        alone = sorted(((_p(*_restriction(fit, start, f, [k], none)[:2]), k) for k in f.imus), reverse=True)
        drop, test, held = [], None, 0  # held: the dof of the joint test of ``drop``
        for p, k in alone[:-1]:
            stat, dof, _ = _restriction(fit, start, f, drop + [k], none)
            if p < alpha or _p(stat, dof) < alpha:
                break
            if dof == held:
                continue  # the gauge holds its values: nothing to test (the fit's choice, not a finding)
            drop, test, held = drop + [k], (_p(stat, dof), f, tuple(sorted(drop + [k])), None, None, stat, dof), dof
        if test is not None and (best is None or len(test[2]) > len(best[2])):
            best = test
    if best is not None:
        return best
    for f in findings:
        if f.scope != "imu" and not is_own(f.scope):
            continue
        for inner, t in holds(start, f.effect, terms):
            for k in f.imus:
                if (inner, k) in covered:
                    continue
                stat, dof, phi = _restriction(fit, start, f, [k], t[k])
                if dof > 0 and _p(stat, dof) >= alpha and (best is None or _p(stat, dof) > best[0]):
                    best = (_p(stat, dof), f, (k,), inner, phi, stat, dof)
    return best


def simplest_adequate(samples, start: SensorModel, findings: list, fit, motion, terms, alpha: float, make,
                      groups, current: SensorModel, say=lambda text: None):
    """Each IMU of a one-IMU or own-scope finding re-tested, at the joint exact fit, for the simpler hypotheses
    by the Wald test of the linear restriction with the fit's CRB (up to the gauge): nothing on a set of an
    own-scope finding's IMUs (the largest set the joint test accepts at ``alpha``, as the narrowing chooses
    carriers: several weak carriers are not dropped one by one), else a term its term holds (:mod:`.nested`) on
    one IMU (the largest p); the change is refitted exactly and the test repeated.  make(candidate, delta, step): a
    new finding (discover.Finding); fit: the last joint exact fit of ``findings`` (None: nothing is tested),
    ``current`` its model.  Returns (findings, changes [dict, as ``rejected``], fit, model, motion)."""
    changes = []
    while fit is not None:
        change = _simplest_change(fit, start, findings, terms, alpha)
        if change is None:
            break
        p, f, ks, inner, phi, stat, dof = change
        k, name = ks[0], ", ".join(start.names[j] for j in ks)
        what = f"{inner} on {name}" if inner else f"nothing on {name}"
        reason = (f"{f.effect} on {name} (step {f.step}, {f.sensor}) replaced by {what}: given the other findings "
                  f"the Wald test of that restriction (joint exact fit, CRB) gives {stat:.3g} on {dof} dof, "
                  f"p = {p:.3g} >= alpha = {alpha:g}: the simpler hypothesis is adequate")
        v = np.array(fit.model.terms[f.effect].values, dtype=float)
        v[list(ks)] = start.terms[f.effect].values[list(ks)]
        base = fit.model.with_terms(**{f.effect: v})
        kept = [g for g in findings if g is not f]
        rest = tuple(j for j in f.imus if j not in ks)
        if inner is not None:  # its change carried by the inner term (the restriction's GLS value)
            vi = np.array(base.terms[inner].values, dtype=float)
            vi[k] = vi[k] + phi.reshape(vi[k].shape)
            base = base.with_terms(**{inner: vi})
        pairs = [(g.effect, g.imus) for g in kept] + ([(f.effect, rest)] if rest else []) + (
            [(inner, (k,))] if inner else [])
        try:
            new_fit = refit(samples, base, pairs, motion)
        except CalibrationError as err:  # keep what the search found rather than fail the whole discovery
            say(f"simplest adequate: could not refit with {what} in place of {f.effect}: {err}")
            break
        say(f"simplest adequate: {f.effect} on {name} replaced by {what} (p {p:.2g})")
        changes.append({"effect": f.effect, "sensors": [start.names[j] for j in ks], "scope": f.scope,
                        "step": f.step, "reason": reason, "statistic": stat, "dof": dof, "p": p})
        if rest:
            _narrowed(f, rest, start, groups, reason)
            kept.append(f)
        if inner is not None:
            c = replace(f.candidate, effect=inner, k=k, sensor=name, scope="imu", imus=(k,), sensors=(name,),
                        equivalents=[], extends=(), note=reason)
            kept.append(make(c, 0.0, f.step))
        fit, current, findings = new_fit, new_fit.model, sorted(kept, key=lambda g: g.step)
        motion = np.where(np.isfinite(fit.motion), fit.motion, motion)
        for g in findings:
            update_finding(g, fit, start, alpha)
            if inner is not None and g.effect == inner and g.imus == (k,):  # its evidence: the Wald test given
                c, (w_stat, w_dof, w_p) = g.candidate, wald_given_others(fit, g, start, alpha)  # all the others
                ln_n = (c.delta_bic + c.statistic) / max(c.dof, 1)  # BIC's ln n, as the step's candidates had it
                g.exact_delta_loglik = c.exact_gain = c.delta_loglik = 0.5 * w_stat
                c.statistic, c.dof, c.lrt_p, c.delta_bic = w_stat, w_dof, w_p, w_dof * ln_n - w_stat
                c.log_p = float(scipy.stats.chi2.logsf(w_stat, max(w_dof, 1)))
                if not np.isfinite(c.log_p):  # underflow: the leading term of the asymptotic series
                    q = max(w_dof, 1)
                    c.log_p = float((q / 2 - 1) * np.log(w_stat / 2) - w_stat / 2 - scipy.special.gammaln(q / 2))
                c.robust_p = c.heldout = float("nan")  # not tested (null in report.json)
    return findings, changes, fit, current, motion


def _narrowed(f, rest: tuple, start: SensorModel, groups, reason: str) -> None:
    """Finding ``f`` (and its candidate) on the IMUs ``rest`` of its own scope only."""
    names = tuple(start.names[j] for j in rest)
    c = f.candidate
    if len(rest) == 1:
        f.scope, f.sensor, f.imu_values, f.imu_std, f.tie, f.shared = "imu", names[0], None, None, None, False
    else:
        label = scope_label(rest, start.names, groups, False)
        f.scope, f.sensor = label, f"{label} ({', '.join(names)})"
    f.imus, f.k = rest, rest[0]
    c.scope, c.sensor, c.imus, c.sensors, c.k = f.scope, f.sensor, rest, names, rest[0]
    c.note = f"{c.note}; then {reason}" if c.note else reason


def dropped_notes(dropped: list) -> list[str]:
    """The report's note on the findings :func:`backward_eliminate` dropped ([] when none)."""
    if not dropped:
        return []
    gone = "; ".join(f"{r['effect']} on {', '.join(r['sensors'])}" for r in dropped)
    return [f"backward elimination dropped {gone}: no longer significant given the other findings (see rejected)"]
