"""Growing a finding's one value to one more IMU: a carrier outside the scope the finding was tested at.

A shared effect on an arbitrary set of IMUs (a batch of chips, a group no geometry names) is found at the pooled
scope that holds most of its carriers and narrowed to those (:mod:`.subset`); a carrier outside that scope then
has only its own evidence, tested like any IMU's term with all its parameters at the step's Bonferroni level: an
effect on five IMUs of 32 was reported on the four the 'back' scope held (suite seed 116783, group 7).  Once the
value is known, whether IMU k carries it too is a question of one number: the term on k along the finding's
value v, c v, with c = 0 under "nothing on k".  Its score test has one degree of freedom (the same blocks and
tests as every candidate, :func:`~.explain.block_tests`, on the projection g_b v, v^T S_b v), so a carrier with a
few tens of evidence passes where the three-parameter test on k alone does not.

Every step adds, for every finding that holds one value (one IMU, or a pooled scope whose tie test accepts one
value) and every IMU outside it without the term, one such candidate; they are counted in the step's number of
candidates like every other, so the step's family-wise false-finding rate stays alpha.  A passing one is
confirmed by the exact refit of the finding on its IMUs plus k (:func:`~.confirm.confirm`): one value on all of
them must be adequate (tie test p >= alpha) and gain at the step's level on one degree of freedom; it then
replaces the finding it grows.

When every other carrier is too weak for its own one-dof test, their pooled evidence may not be: each such finding
also gets one **pooled** candidate, "c_k v on every IMU k outside it" (one number per IMU, up to K - 1 dof), scored
from the cross-IMU information along v that the score pass makes (``score_blocks(..., directions=...)``,
:func:`extension_directions`), with the dispersion form of the block-robust test (:func:`~.explain.block_tests`:
Hotelling's has no power at a dof near the number of blocks).  Its exact confirmation refits the term with every
IMU of it its own value (the grown finding's included), which must gain at the step's level on all the freed
parameters but the one value; it is then narrowed to the carriers like any pooled finding (:mod:`.subset`) and
replaces the finding it grows.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.drift import GIVEN, candidate_blocks
from imu_array_ros.discovery.explain import Candidate, block_tests
from imu_array_ros.discovery.scopes import Scope, scoped_blocks
from imu_array_ros.discovery.subset import scope_label

__all__ = ["extension_candidates", "extension_directions", "shared_change", "OWN_EXTENSION"]

#: how an "every other IMU its own value" extension says so in its sensor label (:mod:`.increment` reads it)
OWN_EXTENSION = "each its own value"


def shared_change(f, current, start) -> np.ndarray | None:
    """The one value (its change from the model discovery started from) a finding puts on its IMUs, or None when
    it has none (a pooled finding whose IMUs keep their own values)."""
    if f.scope == "imu":
        return (np.asarray(current.terms[f.effect].values[f.k], float)
                - np.asarray(start.terms[f.effect].values[f.k], float))
    return np.asarray(f.values, float) if f.shared else None


def extension_directions(accepted: dict, current, start, terms) -> list[tuple]:
    """[(finding key, term, v)] of the accepted findings holding one value v of a scored term (``terms``): the
    directions whose cross-IMU information the score pass makes for the pooled extension (module docstring)."""
    out = []
    for key, f in accepted.items():
        if f.effect in GIVEN or f.effect not in terms:
            continue
        v = shared_change(f, current, start)
        if v is not None and np.all(np.isfinite(v)) and np.any(v):
            out.append((key, f.effect, v))
    return out


def _pooled(sb, names, folds, fold_ids, have, n_obs, key, f, v, outside, step):
    """The candidate "c_k v on every IMU k of ``outside``" (one number each) of finding ``f`` (key ``key``), or
    None when ``sb`` has no information along v for it or the recording identifies none of the c_k."""
    d = next((i for i, (t, u) in enumerate(sb.directions) if t == f.effect and np.array_equal(u, v)), None)
    if d is None or sb.S_dir is None:
        return None
    out = list(outside)
    gb = sb.g[:, out, sb.columns(f.effect)] @ v
    Sb = sb.S_dir[:, d][:, out][:, :, out]
    r = block_tests(gb[have], Sb[have], folds[have], fold_ids, dispersion=True)  # up to K - 1 dof
    return None if r is None else _every_other(
        r, names, n_obs, key, f, out, step, f"along {f.sensor}'s value", lambda theta: np.outer(theta, v).reshape(-1),
        f"{f.effect}'s value on {f.sensor} as c_k times it on each of the {len(out)} other IMUs", "dispersion-robust")


def _own(sb, names, folds, fold_ids, have, n_obs, key, f, outside, step):
    """The candidate "every IMU of ``outside`` its own value" of finding ``f``'s term (the own scope less the
    finding's IMUs; same exact confirmation as :func:`_pooled`'s), or None when ``sb`` has no cross-IMU
    information of the term (own scopes not scored) or the recording identifies none of it."""
    if f.effect not in sb.S_cross:
        return None
    out = list(outside)
    gb, Sb = scoped_blocks(sb, f.effect, Scope("outside", "own", tuple(out)))
    r = block_tests(gb[have], Sb[have], folds[have], fold_ids)  # (K - 1) p dof: Hotelling, as the own scope
    return None if r is None else _every_other(
        r, names, n_obs, key, f, out, step, OWN_EXTENSION, lambda theta: theta,
        f"{f.effect} on {f.sensor}, then each of the {len(out)} other IMUs its own value", "block-robust")


def _every_other(r, names, n_obs, key, f, out, step, how, theta_of, what, robust):
    """The Candidate of a finding ``f`` (key ``key``) put on every IMU of ``out`` from its block tests ``r``
    (:func:`_pooled`, :func:`_own`): scope "all own" or "all but X own"; theta_of(theta): its parameter step."""
    stat, q, lrt_p, log_p, robust_p, heldout, theta = r
    imus = tuple(sorted(set(f.imus) | set(out)))
    left = [names[i] for i in range(len(names)) if i not in imus]
    label = f"all but {','.join(left)} own" if left else "all own"
    return Candidate(f.effect, imus[0], f"{label} ({len(imus)} IMUs, {how})", stat, q, lrt_p, robust_p, 0.5 * stat,
                     q * np.log(n_obs) - stat, heldout, theta_of(theta), log_p, step, scope=label, imus=imus,
                     sensors=tuple(names[i] for i in imus), extends=key,
                     note=f"{what}: score test {stat:.4g} on {q} dof, p = {lrt_p:.3g}, {robust} p = {robust_p:.3g}")


def _better(a, b):
    """Of two candidates of one hypothesis (the same key and exact confirmation), the one whose larger p-value
    (the one that decides whether it passes) is smaller; either when the other is None."""
    if a is None or b is None:
        return a if b is None else b
    worst = lambda c: max(c.lrt_p, c.robust_p if np.isfinite(c.robust_p) else 1.0)  # noqa: E731
    return a if worst(a) <= worst(b) else b


def extension_candidates(sb, names, folds: np.ndarray, accepted: dict, current, start, groups, *, exclude=(),
                         step: int = 0) -> list[Candidate]:
    """The candidates that put an accepted finding's one value on one more IMU (module docstring), scored from
    ``sb`` (given the findings); accepted: Candidate.key -> Finding; current / start: the model with the findings
    and the model discovery started from; groups: the geometry groups (scope labels); exclude: (term, IMU) pairs
    not to test (IMUs holding the term, ruled out)."""
    folds = np.asarray(folds)
    fold_ids = np.unique(folds)
    have = sb.counts > 0
    n_obs = max(sb.valid_axes, 2)
    out = []
    for key, effect, v in extension_directions(accepted, current, start, sb.offsets):
        f = accepted[key]
        members = set(f.imus)
        outside = [k for k in range(len(names)) if k not in members and (effect, k) not in exclude]
        if len(outside) > 1:
            pooled = _pooled(sb, names, folds, fold_ids, have, n_obs, key, f, v, outside, step)
            own = _own(sb, names, folds, fold_ids, have, n_obs, key, f, outside, step)
            out += [c for c in (_better(pooled, own),) if c is not None]
        for k in outside:
            gb, Sb = candidate_blocks(sb, f.effect, k)
            r = block_tests((gb @ v)[have, None], np.einsum("bpq,p,q->b", Sb, v, v)[have, None, None], folds[have],
                            fold_ids)
            if r is None:
                continue
            stat, q, lrt_p, log_p, robust_p, heldout, theta = r
            imus = tuple(sorted(members | {k}))
            label = scope_label(imus, names, groups, True)
            sensors = tuple(names[i] for i in imus)
            out.append(Candidate(f.effect, imus[0], f"{label} ({', '.join(sensors)})", stat, q, lrt_p, robust_p,
                                 0.5 * stat, q * np.log(n_obs) - stat, heldout, theta[0] * v, log_p, step,
                                 scope=label, imus=imus, sensors=sensors, extends=key,
                                 note=f"{f.effect}'s value on {f.sensor} put on {names[k]} too (1 dof)"))
    return out
