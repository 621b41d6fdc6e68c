"""Confirming a candidate by an exact refit (the engine's ``fit_terms`` with ``only``), and a finding's
values from the latest joint fit, at one IMU or at a pooled scope (:mod:`.scopes`).

A pooled candidate is fitted with each IMU's own value: the engine has no tie of parameters across IMUs,
and adding one would thread a linear map through its gauge search, identifiability check and covariances.
Instead the per-IMU values are tested for one shared value (:func:`~.scopes.tie_test`, a Wald test with
the exact fit's CRB, asymptotically the likelihood ratio of the tied fit) and the shared value is their
generalised least-squares mean, which is asymptotically the tied maximum-likelihood estimate.

A confirmed pooled candidate is then narrowed to the IMUs that carry it (:mod:`.subset`): the fewest IMUs of
the scope whose own values explain the pooled fit (Wald test at alpha), the exact likelihood ratio of the
refit on those IMUs only against the pooled one, and the re-confirmation of the narrowed finding at the
step's level.

A confirmed, plausible candidate whose evidence given the earlier findings lies mostly on directions those
findings' terms can nearly produce is not reported (:mod:`.trading`): its values trade with theirs.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.stats

from imu_array_ros.calibration.guards import implausible
from imu_array_ros.discovery.explain import BIC_GAP, Candidate
from imu_array_ros.discovery.nested import carried, upgrade_of
from imu_array_ros.discovery.scopes import geometry_groups, tie_test
from imu_array_ros.discovery.subset import is_own, propose, scope_label, term_indexes
from imu_array_ros.discovery.trading import trading
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

#: how confirm's reason starts when the exact fit is physically implausible (discovery then stops adding terms)
IMPLAUSIBLE = "implausible"
#: how confirm's reason starts when the candidate trades with earlier findings (:mod:`.trading`)
TRADES = "indistinguishable from"

__all__ = ["confirm", "settle_ties", "tied", "both_found", "rejection", "only_imus", "update_finding", "refit",
           "COST_TOLERANCE", "IMPLAUSIBLE", "TRADES", "TIE_MAX"]

#: at most this many candidates of one tie are confirmed exactly (the first-ranked included)
TIE_MAX = 3

#: an exact refit says its iteration and cost at most this often (s): on a whole capture one takes minutes
PROGRESS_S = 30.0

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


def _ticker(say, label: str):
    """A fit_terms progress callback that says ``label``'s iteration and cost at most every PROGRESS_S."""
    if say is None:
        return None
    last = [time.monotonic()]

    def tick(iteration: int, cost: float) -> None:
        if time.monotonic() - last[0] >= PROGRESS_S:
            last[0] = time.monotonic()
            say(f"{label}: iteration {iteration}, cost {cost:.8g}")
    return tick


def refit(samples, current: SensorModel, pairs, motion, *, cost_tolerance: float | None = None, progress=None):
    """The exact joint fit of the findings [(term, IMU indexes)] from ``current`` with the motion (``motion`` its
    start), each term free on its IMUs only; CRB std (no sandwich).  Raises CalibrationError when it fails."""
    only = only_imus(pairs)
    imus = sorted({k for ks in only.values() for k in ks})
    return fit_terms(samples, current, list(only), imus=imus, only=only, motion0=motion, max_iterations=30,
                     sandwich=False, cost_tolerance=cost_tolerance, progress=progress)


def confirm(samples, current: SensorModel, accepted, c: Candidate, motion, level: float, model: SensorModel,
             alpha: float, say=None):
    """Exact refit of every finding so far plus ``c`` (the engine, ``only``: a pooled candidate with each IMU's
    own value); (FitResult, delta loglik) or a reason string when the exact likelihood ratio does not confirm
    the candidate.  A shared scope is confirmed by the gain of the shared value: the per-IMU fit's gain less
    half the tie test's statistic (the Wald approximation of the tied fit's likelihood ratio) when the tie
    test accepts one value at ``alpha``, else by the per-IMU fit's gain against a chi-square with all its
    parameters.  A confirmed pooled candidate is narrowed to the IMUs that carry it (:mod:`.subset`; ``c``'s
    scope, IMUs and sensors are then changed in place and its note says why), the fit returned the refit on
    them.  say(text): progress lines of the long exact fits.  A reason starting with IMPLAUSIBLE: the values are
    beyond the calibrations' bounds; with TRADES: its evidence is mostly a change of the earlier findings' values
    (:mod:`.trading`)."""
    pooled = bool(c.extends) and is_own(c.scope)  # a finding's value on every other IMU (.extend): it replaces it
    up = upgrade_of(c, accepted, model)  # c's term holds a finding's on its IMU (.nested): it replaces it
    gone = c.extends if pooled else (up[0] if up else None)
    pairs = [(f.effect, f.imus) for key, f in accepted.items() if key != gone]
    start = carried(current, model, accepted[up[0]].effect, c.effect, c.k, up[1]) if up else current
    try:
        fit = refit(samples, start, pairs + [(c.effect, c.imus)], motion, cost_tolerance=COST_TOLERANCE,
                     progress=_ticker(say, f"exact fit of {c.effect} on {c.sensor}"))
    except CalibrationError as err:
        return f"the exact fit failed: {err}"
    delta = fit.loglik_after - fit.loglik_before
    # how the candidate was tested before its narrowing (a pooled extension's score, a widening): kept in its note
    gain, dof, tie, tested = delta, c.dof, None, c.note if pooled else ""
    if pooled:  # the grown finding's IMUs each their own value too: every freed parameter but its one value
        dof = max(c.dof, _free(fit, c.effect, c.imus) - REGISTRY[c.effect].dim())
    if c.scope != "imu" and not is_own(c.scope):
        tie = tie_test(fit, c.effect, list(c.imus), model.names, model.terms[c.effect].values[list(c.imus)])
        if tie["p"] >= alpha and c.extends:  # against the grown finding's one value (the refit frees its IMUs')
            grown = list(accepted[c.extends].imus)
            had = (tie_test(fit, c.effect, grown, model.names, model.terms[c.effect].values[grown])["statistic"]
                   if len(grown) > 1 else 0.0)
            gain = delta - 0.5 * (tie["statistic"] - had)
        elif tie["p"] >= alpha:
            gain = delta - 0.5 * tie["statistic"]
        elif c.extends:  # one value on one more IMU (.extend): only as one value
            return (f"not confirmed by the exact fit: one value on {', '.join(c.sensors)} is not adequate (tie "
                    f"test p = {tie['p']:.3g} < alpha = {alpha:g})")
        else:
            dof = tie["dof"] + c.dof
            wide = _widen(samples, current, pairs, c, tie, motion, level, model, alpha, say)
            if wide is not None:
                fit, delta, dof = wide
                gain, tie, tested = delta, None, c.note
    need = 0.5 * scipy.stats.chi2.isf(level, dof)
    if not np.isfinite(gain) or gain < need:
        return (f"not confirmed by the exact fit: log-likelihood gain {gain:.3g} < {need:.3g} "
                f"(the score test's first-order gain was {c.delta_loglik:.3g})")
    c.exact_gain = float(gain)  # ties are ranked by it (settle_ties); the narrowing replaces it
    if c.extends and not pooled:
        c.note = (f"{c.note}: score test {c.statistic:.4g} on 1 dof; one value shared by all {len(c.imus)} (tie test "
                  f"p = {tie['p']:.3g} >= alpha = {alpha:g}); exact gain {gain:.4g} >= {need:.3g}")
    elif c.scope != "imu":
        narrowed = _narrow(samples, current, pairs, c, fit, float(delta), tie, motion, level, model, alpha, say)
        if narrowed is not None:
            fit, delta = narrowed
        if tested and c.note != tested:
            c.note = f"{tested}; then {c.note}"
    problem = implausible(fit.model, model)
    if problem is not None:  # never report what no real sensor has: the term stands in for something else
        return f"{IMPLAUSIBLE}: the exact fit takes {problem}"
    grown = accepted.get(gone) if gone else None  # its values move with the grown finding's by design
    new = tuple(k for k in c.imus if grown is None or k not in grown.imus)
    trade = trading(fit, current, [f for f in accepted.values() if f is not grown], c.effect, new)
    if trade is not None and trade.traded:  # its values trade with the earlier findings' (.trading)
        return trade.reason()
    if up:
        c.extends = up[0]
        c.note = (f"replaces {grown.effect} on {grown.sensor} (step {grown.step}), which {c.effect} holds: score test "
                  f"{c.statistic:.4g} on {c.dof} dof given it, exact gain {gain:.4g} >= {need:.3g} (refit from its "
                  f"change carried by {c.effect})")
    return fit, float(delta)


def _free(fit, term: str | None = None, imus=()) -> int:
    """Free (identified) parameters of ``fit``: all, or ``term``'s on ``imus``."""
    var = np.diag(fit.covariance)
    return int(np.sum((var if term is None else var[term_indexes(fit, term, imus)]) > 0))


def _widen(samples, current, pairs, c: Candidate, tie, motion, level, model, alpha, say=None):
    """(fit, delta, dof) of ``c``'s term with every IMU its own value, ``c`` changed in place to "all own", when
    one value shared by ``c``'s proper scope is rejected by its exact fit (``tie``) and every IMU's own value passes
    the step's ``level``; else None.  The scope came
    from the score test of one shared value, which the exact fit rejects: the carriers are not that group.  On a
    proper scope the IMUs outside it, held by the fit, fix what a value common to the IMUs would move (a gauge:
    a common time offset or accelerometer bias is absorbed by the fused motion; a near-gauge: a common
    accelerometer gain, only weakly observed), so the scope's values are relative to a mixture of carriers and
    non-carriers outside it and its narrowing cannot find the carriers (a time offset on 14 IMUs of 32 was
    reported on a side of 16 holding 7 of them, an accelerometer gain on 10 of 32 on a side holding 7).  On every
    IMU the narrowing (:mod:`.subset`) sees them all, up to the gauge."""
    term, n = c.effect, model.n_imus
    if len(c.imus) >= n or any(t == term for t, _ in pairs):
        return None
    every = tuple(range(n))
    try:
        fit_all = refit(samples, current, pairs + [(term, every)], motion, cost_tolerance=COST_TOLERANCE,
                         progress=_ticker(say, f"exact fit of {term} on every IMU"))
    except CalibrationError:
        return None
    free = _free(fit_all, term, every)
    delta = fit_all.loglik_after - fit_all.loglik_before
    if not np.isfinite(delta) or delta < 0.5 * scipy.stats.chi2.isf(level, max(free, 1)):
        return None  # too weak on every IMU's own values: the scope as tested stands
    label = scope_label(every, model.names, geometry_groups(model.positions, model.rotations), False)
    c.note = (f"tested at scope '{c.scope} ({', '.join(c.sensors)})': one shared value rejected by the exact fit "
              f"(tie test p = {tie['p']:.3g} < alpha = {alpha:g}), so its carriers are sought on every IMU (the "
              f"IMUs outside a scope hold what a value common to the IMUs would move; exact gain {delta:.4g} on "
              f"{free} free parameters)")
    c.scope, c.imus, c.sensors, c.k = label, every, tuple(model.names), 0
    c.sensor = f"{label} ({', '.join(model.names)})"
    return fit_all, float(delta), free


def _narrow(samples, current, pairs, c: Candidate, fit, delta: float, tie, motion, level, model, alpha,
            say=None):
    """(fit, delta) of ``c`` narrowed to the IMUs that carry it (:mod:`.subset`), ``c`` changed in place; None
    (``c`` as it was, its note saying why when a subset was tried) when the scope stands."""
    term, imus = c.effect, tuple(c.imus)
    if any(t == term and set(ks) & set(imus) for t, ks in pairs):
        return None  # an IMU of the scope already holds an earlier finding of this term
    prop = propose(fit, term, imus, model.terms[term].values[list(imus)], alpha)
    if prop is None:
        return None
    sub = prop.imus
    names = [model.names[k] for k in sub]
    how = (("one value shared by which, up to the fit's gauge freedoms," if prop.gauge else
            "one value shared by which,") if prop.in_gauge else "")
    tried = (f"narrowing to {', '.join(names)} (the fewest IMUs of the scope {how + ' ' if how else ''}the Wald test "
             f"at alpha = {alpha:g} accepts)")
    try:
        fit_c = refit(samples, current, pairs + [(term, sub)], motion, cost_tolerance=COST_TOLERANCE,
                       progress=_ticker(say, f"exact fit of {term} narrowed to {', '.join(names)}"))
    except CalibrationError as err:
        c.note = f"{tried}: the exact refit failed ({err}); the scope stands"
        return None
    delta_c = fit_c.loglik_after - fit_c.loglik_before
    base = model.terms[term].values[list(sub)]
    tie_c = tie_test(fit_c, term, list(sub), model.names, base) if len(sub) > 1 else None
    shared_c = tie_c is not None and tie_c["p"] >= alpha
    gain_c = delta_c - (0.5 * tie_c["statistic"] if shared_c else 0.0)
    n_c = _free(fit_c, term, sub)
    dof_c = (n_c - tie_c["dof"]) if shared_c else n_c
    if tie is None:  # an own scope: whether one shared value on all of it would do as well
        tie = tie_test(fit, term, list(imus), model.names, model.terms[term].values[list(imus)])
    if tie["p"] >= alpha:  # one shared value on the whole scope is adequate: C's must be more likely
        gap = gain_c - (delta - 0.5 * tie["statistic"])
        ok = (shared_c or len(sub) == 1) and gap >= np.log(1.0 / alpha)
        if shared_c or len(sub) == 1:
            why = (f"one value on {'them' if len(sub) > 1 else 'it'} is {'more' if gap >= 0 else 'less'} likely "
                   f"than one shared by all {len(imus)} (tie test p = {tie['p']:.3g}): 2 delta log-lik "
                   f"{2 * gap:.3g}, needed >= 2 ln(1/alpha) = {2 * np.log(1 / alpha):.3g}")
        else:
            why = (f"one value shared by all {len(imus)} is adequate (tie test p = {tie['p']:.3g}) and their values "
                   f"differ (tie test over them p = {tie_c['p']:.3g} < alpha)")
    else:
        lr, ddof = 2.0 * (delta - delta_c), _free(fit) - _free(fit_c)
        p_lr = float(scipy.stats.chi2.sf(lr, ddof)) if ddof > 0 else (1.0 if lr <= 0 else 0.0)
        ok = p_lr >= alpha
        why = (f"the refit with only them free loses 2 delta log-lik {lr:.3g} on {ddof} dof against the pooled "
               f"fit (exact likelihood ratio, p = {p_lr:.3g} {'>=' if ok else '<'} alpha = {alpha:g})")
    if not ok:
        c.note = f"{tried}: not adequate ({why}); the scope stands"
        return None
    need = 0.5 * scipy.stats.chi2.isf(level, max(dof_c, 1))
    if not np.isfinite(gain_c) or gain_c < need:
        c.note = f"{tried}: its gain {gain_c:.3g} < {need:.3g} (the step's level); the scope stands"
        return None
    old = f"{c.scope} ({', '.join(c.sensors)})"
    groups = geometry_groups(model.positions, model.rotations)
    label = scope_label(sub, model.names, groups, shared_c)  # one IMU: "imu_3 own" (its pooled figures kept)
    ps = ", ".join(f"{model.names[k]} {p:.2g}" for k, p in prop.p.items())
    whose = (("one value shared by which explains the pooled fit up to the fit's gauge freedoms (the values the "
              "fused motion absorbs; Wald test" if prop.gauge else
              "one value shared by which explains the pooled fit (Wald test") if prop.in_gauge else
             "whose own values explain the pooled fit (Wald test of nothing on the others")
    each = "the set without each: p = " if prop.in_gauge else "each given the others: p = "
    note = (f"tested at scope '{old}' (score test, statistic {c.statistic:.4g} on {c.dof} dof; exact gain "
            f"{delta:.4g}); carried by {', '.join(names)} only: the fewest IMUs of the scope {whose} "
            f"{prop.zero_stat:.3g} on {prop.zero_dof} dof, "
            f"p = {scipy.stats.chi2.sf(prop.zero_stat, max(prop.zero_dof, 1)):.3g} >= alpha = {alpha:g}; {each}{ps})"
            + (f" in the gauge that puts {model.names[prop.zero]} at its starting value" if prop.zero is not None
               else "")
            + f"; {why}; re-confirmed on them: gain {gain_c:.4g} >= {need:.3g}; reported as "
            f"'{label}'")
    c.equivalents = _equivalents(prop, term, model, groups, alpha)
    if c.equivalents:
        note += "; " + "; ".join(f"indistinguishable from {term} on {e['sensors'][0]}: {e['reason']}"
                                 for e in c.equivalents)
    c.note = note
    c.scope, c.imus, c.sensors, c.k = label, tuple(sub), tuple(names), int(sub[0])
    c.sensor = f"{label} ({', '.join(names)})"
    c.exact_gain = float(gain_c)
    return fit_c, float(delta_c)


def _equivalents(prop, term: str, model, groups, alpha: float) -> list:
    """[{"sensors": [scope], "names": [IMU names], "reason"}] of the other IMU sets the Proposal says fit as well as its own (the
    report's "indistinguishable" entries, :func:`settle_ties`)."""
    out, sub, n = [], set(prop.imus), model.n_imus
    two = 2.0 * np.log(1.0 / alpha)
    for imus, stat in prop.equivalents[:TIE_MAX - 1]:
        where = f"{scope_label(imus, model.names, groups, True)} ({', '.join(model.names[k] for k in imus)})"
        comp = not set(imus) & sub and len(set(imus) | sub) == n
        figures = f"Wald statistic {stat:.3g} against {prop.zero_stat:.3g}, within 2 ln(1/alpha) = {two:.3g}"
        if prop.gauge:
            why = (f"one value shared by these IMUs fits as well up to the gauge ({figures}; gauge: a common {term} "
                   "is absorbed by the fused motion"
                   + (f", so {term} on one set differs from the opposite value on its complement only by it"
                      if comp else ""))
        else:
            why = (f"one value shared by these IMUs fits as well ({figures}; no gauge freedom of the fit moves "
                   f"{term} here")
        why += "): the recording does not tell them apart"
        out.append({"sensors": [where], "names": [model.names[k] for k in imus], "reason": why})
    for imus in prop.alternatives[:TIE_MAX - 1]:
        where = f"{scope_label(imus, model.names, groups, False)} ({', '.join(model.names[k] for k in imus)})"
        out.append({"sensors": [where], "names": [model.names[k] for k in imus],
                    "reason": "a set as small whose own values the Wald test accepts as well: "
                                                  "the data hardly tell them apart"})
    return out


def rejection(c: Candidate, step: int, reason: str) -> dict:
    """The report's record of a candidate the exact fit did not confirm."""
    return {"effect": c.effect, "sensors": list(c.sensors), "scope": c.scope, "step": step, "reason": reason}


def tied(c: Candidate, passing: list, n_imus: int | None = None) -> list:
    """The passing candidates ranked after ``c`` whose scores tie with c's: the same dof and a BIC within
    ``BIC_GAP`` of c's (at most ``TIE_MAX`` - 1). The score test is a first-order approximation: within the gap
    it does not order them, and on mirror-image scopes (e.g. an array's top and bottom) rounding alone would.
    With ``n_imus``, the same term at the complementary scope (same dof) is tied whatever its BIC: the two
    differ only by a value common to every IMU, which the fused motion (nearly) absorbs."""
    after = passing[passing.index(c) + 1:]
    comp = set(range(n_imus)) - set(c.imus) if n_imus is not None else None

    def complement(o):
        return comp is not None and o.effect == c.effect and set(o.imus) == comp
    out = [o for o in after if o.dof == c.dof and o.delta_bic - c.delta_bic < BIC_GAP][:TIE_MAX - 1]
    return out + [o for o in after if o.dof == c.dof and complement(o) and o not in out]


def settle_ties(c: Candidate, result, passing: list, confirm_one, step: int, say, notes: list, rejected: list, *,
                alpha: float = 0.01, indist: list | None = None, n_imus: int | None = None):
    """(candidate, result) kept among ``c`` (confirmed: ``result`` = (fit, gain)) and the candidates tied with it
    (:func:`tied`), each confirmed exactly by ``confirm_one(candidate)``: the largest exact log-likelihood gain
    of the hypothesis as reported wins (``Candidate.exact_gain``: a shared scope's shared value, not its
    per-IMU refit's gain, which holds the per-IMU values' fitted noise). A note says which were tied and what each gained; a tied candidate the exact fit does not confirm goes
    to ``rejected`` with its reason.  A confirmed one whose gain is within ln(1/alpha) of the kept one's (a
    likelihood ratio below 1/alpha: the recording does not tell them apart) is appended to ``indist`` (the
    report's "indistinguishable" entries) and named in the kept candidate's note: the finding may as well be it.
    So are the kept candidate's ``equivalents`` (the narrowing's sets that fit as well up to the gauge), each
    entry with ``alternatives`` (the kept hypothesis first) for the suite's scorer."""
    best, gains = c, [(c, _rank(c, result))]
    for o in tied(c, passing, n_imus):
        say(f"step {step}: {o.effect} on {o.sensor} scores as {c.effect} on {c.sensor} does (BIC within "
            f"{o.delta_bic - c.delta_bic:.2g}): testing it exactly too")
        r = confirm_one(o)
        if isinstance(r, str):
            o.note = r
            rejected.append(rejection(o, step, r))
            continue
        gains.append((o, _rank(o, r)))
        if gains[-1][1] > max(g for x, g in gains if x is best):
            best, result = o, r
    if len(gains) > 1:
        told = "; ".join(f"{o.effect} on {o.sensor} +{g:.4g}" for o, g in gains)
        notes.append(f"step {step}: the score test could not order {len(gains)} candidates (same dof, BIC within "
                     f"{BIC_GAP:g}); their exact log-likelihood gains: {told}; kept {best.effect} on {best.sensor}")
    top = max(g for x, g in gains if x is best)
    close = [(o, g) for o, g in gains if o is not best and top - g < np.log(1.0 / alpha)]
    for o, g in close:
        why = _alike(best, o, top - g, alpha, n_imus)
        if indist is not None:
            indist.append({"effects": [best.effect, o.effect], "sensors": [best.sensor, o.sensor], "reason": why,
                           "delta_loglik_gap": float(top - g), "step": step,
                           "alternatives": [{"effect": x.effect, "sensors": list(x.sensors)} for x in (best, o)]})
        best.note = (best.note + "; " if best.note else "") + f"indistinguishable from {o.effect} on {o.sensor}: {why}"
    for e in best.equivalents if indist is not None else ():  # the narrowing's sets that fit as well
        indist.append({"effects": [best.effect, best.effect], "sensors": [best.sensor, e["sensors"][0]],
                       "reason": e["reason"], "step": step,
                       "alternatives": [{"effect": best.effect, "sensors": list(best.sensors)},
                                        {"effect": best.effect, "sensors": list(e["names"])}]})
    return best, result


def both_found(indist: list, findings, notes: list) -> list:
    """``indist`` without the ties (entries with ``alternatives``) every alternative of which ``findings`` cover
    (the same term on each of its IMUs): "this or that" is untrue once both were found (a later step found the
    alternative too).  Each dropped tie is said in ``notes``."""
    covered = {(f.effect, s) for f in findings for s in f.candidate.sensors}
    keep = []
    for e in indist:
        alts = e.get("alternatives") or []
        if len(alts) > 1 and all((a["effect"], s) in covered for a in alts for s in a["sensors"]):
            notes.append(f"step {e.get('step', '?')}: {e['effects'][0]} on {e['sensors'][0]} and {e['effects'][1]} "
                         f"on {e['sensors'][1]} could not be told apart then; both were found, so no longer "
                         f"reported as indistinguishable")
            continue
        keep.append(e)
    return keep


def _rank(c: Candidate, result) -> float:
    """The exact log-likelihood gain a tie is settled by: of the hypothesis as reported (``c.exact_gain``: a
    shared scope's value, not its per-IMU fit's), else the refit's."""
    return float(result[1] if c.exact_gain is None else c.exact_gain)


def _alike(best: Candidate, o: Candidate, gap: float, alpha: float, n_imus: int | None) -> str:
    """Why two confirmed candidates of a tie are indistinguishable (their exact gains ``gap`` apart)."""
    why = (f"their exact log-likelihood gains differ by {gap:.3g} < ln(1/alpha) = {np.log(1.0 / alpha):.3g} (a "
           f"likelihood ratio below {1.0 / alpha:g}): the recording does not tell them apart")
    a, b = set(best.imus), set(o.imus)
    if best.effect == o.effect and n_imus is not None and not a & b and len(a | b) == n_imus:
        why += (f"; the two scopes are complements, so {best.effect} on one differs from the opposite value on "
                f"the other only by a value common to every IMU, which the motion nearly absorbs: what the data "
                f"fix is the difference between the two sides")
    return why
