"""A pooled candidate is preferred over a simpler one it holds only when what it adds is itself block-robust.

The block-robust test of a pooled candidate (a term on several IMUs, own or shared values, or an extension of a
finding, :mod:`.extend`) is an omnibus: its statistic is the joint one, so a part that is not robust across the
recording's blocks rides on a part that is.  Gyroscope biases on the 10-block subsample of
test_discovery_timing_subsample: the bias on imu_3 (score 3819, 3 dof) passes; "all own" (24 dof) passes too,
carried by imu_3's signal, while the other 7 IMUs add ~207 on 21 dof (a near-gauge common body-frame bias) that
is not robust across blocks -- and BIC, which prefers the larger score, took "all own": 7 false findings.

So when a passing pooled candidate P holds a passing simpler candidate s of the same term (s's IMUs among P's,
fewer dof), P stays in the step only if its **increment** over s passes the block-robust test at the step's
level: the test of P's extra directions with s's parameters as nuisance (:func:`~.explain.increment_test`: the
efficient score of the increment, g_eta - S_eta,theta S_theta,theta^-1 g_theta, whose block residuals at the joint
fit get the same CR2 + HTZ small-sample machinery as every candidate's, restricted to the increment's
coordinates).  Otherwise P is left out of the step with a note; s is then taken and the rest of P is tested again
at the next step given it (an extension of the finding, :mod:`.extend`).  Pairs whose joint information the score
pass does not hold (a term without cross-IMU blocks, an extension against a non-extension) are not gated.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.discovery.explain import increment_test, scope_design
from imu_array_ros.discovery.extend import OWN_EXTENSION
from imu_array_ros.discovery.scopes import Scope, scoped_blocks

__all__ = ["increment_gate", "increment"]


def _pooled(c) -> bool:
    return bool(c.extends) or len(c.imus) > 1


def _holds(big, small) -> bool:
    """Whether ``small`` is a simpler candidate of ``big``'s term on IMUs among ``big``'s (fewer dof), both of
    one kind (extensions of the same finding, or neither an extension)."""
    return (small is not big and small.effect == big.effect and small.dof < big.dof
            and set(small.imus) <= set(big.imus) and small.extends == big.extends)


def increment(sb, small, big, directions: dict | None = None):
    """(statistic, dof, robust_p) of what ``big`` adds over ``small`` it holds (:func:`_holds`) in ``sb`` (the
    score blocks both were tested on, blocks with data only), or None when ``sb`` holds no joint information
    of the two or the recording identifies nothing beyond ``small``.  directions: finding key -> the one value v
    its extensions are along (:func:`~.extend.extension_directions`)."""
    have = sb.counts > 0
    cols = sb.columns(big.effect)
    p = cols.stop - cols.start
    if big.extends:
        v = (directions or {}).get(big.extends)
        out, k = sorted(big.added), sorted(small.added)  # beyond the finding both grow (_holds)
        if v is None or len(k) != 1 or small.dof != 1:
            return None
        if OWN_EXTENSION in big.sensor:
            if sb.S_cross.get(big.effect) is None:
                return None
            gb, Sb = scoped_blocks(sb, big.effect, Scope("outside", "own", tuple(out)))
            a_small = np.zeros((len(out) * p, 1))
            a_small[out.index(k[0]) * p:(out.index(k[0]) + 1) * p, 0] = v
        else:
            d = next((i for i, (t, u) in enumerate(sb.directions) if t == big.effect and np.array_equal(u, v)), None)
            if d is None or sb.S_dir is None:
                return None
            gb, Sb = sb.g[:, out, cols] @ v, sb.S_dir[:, d][:, out][:, :, out]
            a_small = np.eye(len(out))[:, [out.index(k[0])]]
        a_big = np.eye(gb.shape[1])
    else:
        if sb.S_cross.get(big.effect) is None:
            return None
        imus = list(big.imus)
        gb, Sb = scoped_blocks(sb, big.effect, Scope("union", "own", tuple(imus)))
        a_small, a_big = scope_design(small, imus, p), scope_design(big, imus, p)
    X = _extend_basis(a_small, a_big)
    if X is None:
        return None
    gb, Sb = gb[have], Sb[have]
    return increment_test(gb @ X, X.T @ Sb @ X, a_small.shape[1])


def _extend_basis(a_small: np.ndarray, a_big: np.ndarray) -> np.ndarray | None:
    """[a_small, E]: E an orthonormal basis of what span(a_big) adds to span(a_small) (both full column rank
    0/1-or-direction designs), or None when it adds nothing."""
    q, _ = np.linalg.qr(a_small)
    rest = a_big - q @ (q.T @ a_big)
    u, s, _ = np.linalg.svd(rest, full_matrices=False)
    keep = s > 1e-9 * max(1.0, np.abs(a_big).max())
    return np.hstack([a_small, u[:, keep]]) if keep.any() else None


def increment_gate(sb, passing: list, level: float, directions: dict | None = None) -> tuple[list, list]:
    """(the passing candidates a step may take, [(pooled candidate left out, the simpler one it holds,
    (statistic, dof, robust_p) of its increment)]): a pooled candidate whose increment over any passing simpler
    one it holds is not block-robust at ``level`` (robust p >= level or not formed) is left out."""
    kept, left = [], []
    for c in passing:
        fail = None
        for s in (passing if _pooled(c) else ()):
            if not _holds(c, s):
                continue
            t = increment(sb, s, c, directions)
            if t is not None and not t[2] < level:
                fail = (c, s, t)
                break
        (kept if fail is None else left).append(c if fail is None else fail)
    return kept, left
