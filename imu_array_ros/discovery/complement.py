"""A finding's value shared by a set of IMUs against the opposite value shared by the others.

A gauge freedom of the fit -- a change every IMU's readings absorb into the fused motion, as a common shift of
every sensor's time offset -- makes "one value on C" and "the opposite value on the complement of C" the same
readings when the change lies along it, and nearly the same when the term's other directions are nearly absorbed
too (an accelerometer-only common delay on an array a few centimetres across).  The search reaches a shared finding
one IMU at a time (:mod:`.extend`) or by narrowing a pooled scope (:mod:`.subset`, which tries every subset of a
small scope, complements included); a finding it grew never met its complement.  Suite seed 613379, group 5: a
time offset on the 24 outer IMUs of the 32 was reported on inner ones, with nothing said of the 24.

:func:`complement_ties` (after the search, :mod:`.finish`): for each finding holding one value on 2..K-2 IMUs, the
term is refitted on every IMU (each its own value, the other findings with it) and, when a gauge freedom of that fit
moves the term, the Wald statistics of "one value on C, nothing elsewhere" and "one value on the complement, nothing
on C", both up to the gauge (:func:`~.subset.shared_statistics`), are compared: within 2 ln(1/alpha) (the ties'
rule, :func:`~.confirm.settle_ties`), the recording does not tell them apart and the report says so (an
"indistinguishable" entry with both as alternatives).  The finding is kept as found (the fewer IMUs)."""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.confirm import refit
from imu_array_ros.discovery.subset import gauge_basis, shared_statistics, term_indexes
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.terms import REGISTRY

__all__ = ["complement_ties"]


def complement_ties(samples, start, current, findings: list, motion, alpha: float, indist: list,
                    say=lambda text: None) -> int:
    """Append to ``indist`` an entry for each finding of ``findings`` (discover.Finding, changes from ``start``,
    fitted on ``samples`` with ``motion``; ``current`` the model with them and whatever else the search kept, the
    timing stage's clocks) whose complement fits as well up to the gauge (module docstring).  Returns the number
    of entries added."""
    k_all = start.n_imus
    names = list(start.names)
    added = 0
    for f in findings:
        imus = tuple(int(k) for k in f.imus)
        if f.scope == "imu" or not f.shared or not 2 <= len(imus) <= k_all - 2:
            continue
        if any(g is not f and g.effect == f.effect for g in findings):
            continue  # another finding of the term: "nothing elsewhere" would not hold
        comp = tuple(k for k in range(k_all) if k not in imus)
        other = [names[k] for k in comp]
        if any({"effect": f.effect, "sensors": other} in (e.get("alternatives") or []) for e in indist):
            continue  # already named (the narrowing tried every subset of a small scope)
        say(f"complement: {f.effect} on {len(imus)} IMUs against its complement ({len(comp)}), the term free on all")
        base = np.asarray(start.terms[f.effect].values, dtype=float)
        pairs = [(g.effect, g.imus) for g in findings if g is not f] + [(f.effect, tuple(range(k_all)))]
        try:  # from the current model, the clocks kept, the term back at its start on every IMU (.eliminate)
            full = refit(samples, current.with_terms(**{f.effect: base}), pairs, motion)
        except CalibrationError:
            continue
        idx = term_indexes(full, f.effect, range(k_all))
        basis = gauge_basis(full, idx)
        if basis.shape[1] == 0:
            continue  # no gauge freedom moves the term: the complement is another model
        p = REGISTRY[f.effect].dim()
        d = full.theta[idx] - base.reshape(-1)
        sets = np.zeros((2, k_all), dtype=bool)
        sets[0, list(imus)] = True
        sets[1, list(comp)] = True
        stat, dof = shared_statistics(d, full.covariance[np.ix_(idx, idx)], basis, p, sets)
        two = 2.0 * np.log(1.0 / alpha)
        if not stat[1] - stat[0] <= two:
            continue
        own = [names[k] for k in imus]
        indist.append({
            "effects": [f.effect, f.effect], "sensors": [f.sensor, f"the other {len(comp)} IMUs shared"],
            "reason": (f"one value shared by the other {len(comp)} IMUs fits as well up to the gauge (Wald statistic "
                       f"of the {f.effect} of every IMU against one value on them {stat[1]:.3g}, on the finding's "
                       f"{len(imus)} {stat[0]:.3g}, {int(dof[0])} dof; within 2 ln(1/alpha) = {two:.3g}; gauge: a "
                       f"change every IMU's readings absorb into the fused motion): the recording does not tell "
                       f"{f.effect} on these {len(imus)} from the opposite {f.effect} on the others"),
            "step": f.step, "statistics": [float(stat[0]), float(stat[1])],
            "alternatives": [{"effect": f.effect, "sensors": own}, {"effect": f.effect, "sensors": other}]})
        added += 1
    return added
