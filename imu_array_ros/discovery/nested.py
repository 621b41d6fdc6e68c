"""Nested terms: a term whose values reproduce every value of another term on the same IMU.

``axis_offsets`` holds ``position``: every accelerometer axis at its own point holds every axis at one shifted
point.  Two hypotheses of one IMU that nest are not rivals but a simpler and a richer one, and discovery uses
the relation twice:

- **upgrade** (:func:`~.confirm.confirm`): a candidate that holds a finding's term on the finding's one IMU (the
  richer term, after the simpler was found) replaces that finding.  Both free at once cannot be identified (the
  exact fit fails), so the refit starts from the simpler finding's change carried by the richer term
  (:func:`carried`) and frees only the richer; its gain is tested on the extra parameters (the score test's dof).
- **simplify** (:func:`simplest_adequate`, after the backward elimination): each IMU of a finding is tested for
  the simpler hypotheses -- nothing (when the finding has other IMUs) or a term it holds -- by the Wald test of
  the linear restriction at the joint exact fit; the simplest one the test accepts at ``alpha`` replaces it (the
  carriers of a pooled finding are first chosen given only the findings before it; a later one can take over).

The relation is found numerically (:func:`nesting`): term A holds term B on IMU k when B's parameter Jacobian
lies in the span of A's on a fixed generic motion, J_B = J_A T_k, and A has more identified directions.  T_k maps
B's change to A's, exactly for the linear terms.  A new term needs no declaration here.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.sensor_model import SensorModel, motion_context

__all__ = ["nesting", "holds", "carried", "upgrade_of"]

#: samples of the generic motion the Jacobians are compared on (random, seeded: the relation is structural)
GENERIC_SAMPLES = 48
#: relative residual of J_B - J_A T below which B lies in A's span
SPAN_RTOL = 1e-9

_CACHE: dict = {}


def _generic_jacobians(model: SensorModel, terms) -> dict:
    """term -> (N, K, 6, P) parameter Jacobians of ``model`` on a fixed random motion (terms the model cannot
    differentiate there are left out)."""
    rng = np.random.default_rng(20140611)
    n = GENERIC_SAMPLES
    stamps = np.arange(n, dtype=np.int64) * 5_000_000
    ctx = motion_context(stamps, rng.normal(0.0, 2.0, (n, 3)), rng.normal(0.0, 10.0, (n, 3)),
                         rng.normal(0.0, 5.0, (n, 3)), model.rotations, derivatives=True)
    out = {}
    for t in terms:
        if t not in model.terms:
            continue
        try:
            out[t] = model.jacobians(ctx, free=[t], motion=False).params[t]
        except (ValueError, KeyError, TypeError, IndexError):  # a term that needs more than a motion context
            continue
    return out


def nesting(model: SensorModel, terms) -> dict:
    """{(outer, inner): T (K, P_outer, P_inner)} for every pair of ``terms`` in which ``outer`` holds ``inner``
    on every IMU of ``model`` (module docstring); cached per model geometry and term set."""
    key = (tuple(model.names), np.asarray(model.rotations).tobytes(), np.asarray(model.positions).tobytes(),
           tuple(sorted(terms)))
    if key in _CACHE:
        return _CACHE[key]
    jac = _generic_jacobians(model, terms)
    out = {}
    for outer, ja in jac.items():
        for inner, jb in jac.items():
            if outer == inner:
                continue
            maps = []
            for k in range(model.n_imus):
                a = ja[:, k].reshape(-1, ja.shape[-1])
                b = jb[:, k].reshape(-1, jb.shape[-1])
                nb = np.linalg.norm(b)
                if nb == 0.0:
                    break
                t = np.linalg.lstsq(a, b, rcond=None)[0]
                if (np.linalg.norm(a @ t - b) > SPAN_RTOL * nb
                        or np.linalg.matrix_rank(a) <= np.linalg.matrix_rank(b)):
                    break
                maps.append(t)
            else:
                out[(outer, inner)] = np.stack(maps)
    _CACHE[key] = out
    return out


def holds(model: SensorModel, outer: str, terms) -> list:
    """[(inner, T (K, P_outer, P_inner))] of the ``terms`` that ``outer`` holds, fewest parameters first."""
    nest = nesting(model, tuple(terms) + (outer,))
    return sorted(((i, t) for (o, i), t in nest.items() if o == outer), key=lambda x: x[1].shape[2])


def upgrade_of(c, accepted: dict, model: SensorModel):
    """(key, T (K, P_c, P_f)) of the accepted one-IMU finding on candidate ``c``'s IMU whose term ``c``'s term
    holds (``c`` would replace it), else None.  ``c``: a one-IMU Candidate; accepted: key -> discover.Finding."""
    if c.scope != "imu" or c.extends:
        return None
    for key, f in accepted.items():
        if f.scope == "imu" and f.k == c.k and f.effect != c.effect:
            nest = nesting(model, (c.effect, f.effect))
            if (c.effect, f.effect) in nest:
                return key, nest[(c.effect, f.effect)]
    return None


def carried(current: SensorModel, start: SensorModel, inner: str, outer: str, k: int, t: np.ndarray) -> SensorModel:
    """``current`` with ``inner`` on IMU ``k`` back at its ``start`` value and its change carried by ``outer``
    (T (K, P_outer, P_inner), :func:`nesting`): the same predictions for the linear terms."""
    vi = np.array(current.terms[inner].values, dtype=float)
    d = (vi[k] - np.asarray(start.terms[inner].values, dtype=float)[k]).reshape(-1)
    vi[k] = np.asarray(start.terms[inner].values, dtype=float)[k]
    vo = np.array(current.terms[outer].values, dtype=float)
    vo[k] = vo[k] + (t[k] @ d).reshape(vo[k].shape)
    return current.with_terms(**{inner: vi, outer: vo})
