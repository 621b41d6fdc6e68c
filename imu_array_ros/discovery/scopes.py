"""Hypotheses at several scopes, and tests given the findings so far.

A candidate term is tested on

* **one IMU** (its parameters alone, as before);
* **a group sharing one value** (every IMU of the array, or a group the geometry suggests: the top and the
  bottom side -- sign of z of the position about the centroid, or the sensor's z axis flipped --, the outer
  ring and the inner IMUs -- distance from the centroid above the median): one parameter vector tied across
  the group's IMUs *in each sensor's own frame* (a chip family shares its non-linearity in its own frame).
  Its score is the sum of the group's per-IMU scores (the direction moving every IMU's parameter equally)
  and its information sum_{k,l in G} S_kl, with the cross-IMU blocks the shared motion couples
  (:func:`~imu_array_ros.fitting.engine.score_blocks` ``groups``);
* **every IMU with its own value**: the joint test of all K x p parameters (``cross_terms``; arrays of at
  most :data:`OWN_MAX_IMUS` IMUs).

Every test is taken *given the findings so far*: their parameters are profiled out of the score and the
information (the efficient score: S_aa - S_aF S_FF^-1 S_Fa), so a weak effect whose signature the strong
one already in the model partly absorbed is tested with the information it has left -- the joint test of
the pair less the strong one's (a time offset on one IMU and a position error on another).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.stats

from imu_array_ros.fitting.engine import check_terms, score_blocks
from imu_array_ros.model.terms import REGISTRY

__all__ = ["Scope", "geometry_groups", "scopes_for", "scoped_blocks", "given_columns", "profile_given",
           "score_given", "tie_test", "OWN_MAX_IMUS", "GEOMETRY_TOL"]

#: the "every IMU its own value" scope is tested on arrays of at most this many IMUs (its information is
#: K x K blocks per time block)
OWN_MAX_IMUS = 16
#: spread (m) of z positions / centroid distances below which the geometry suggests no split
GEOMETRY_TOL = 1e-4


@dataclass(frozen=True)
class Scope:
    """label ("imu", "all shared", "top shared", "all own", ...); kind: "imu", "shared" or "own"; imus:
    the IMU indexes; group: index into ScoreBlocks.S_groups (shared scopes)."""

    label: str
    kind: str
    imus: tuple[int, ...]
    group: int = -1


def geometry_groups(positions: np.ndarray, rotations: np.ndarray) -> list[tuple[str, tuple[int, ...]]]:
    """[(name, IMU indexes)] of the groups the layout suggests: "top"/"bottom" (z of the position about
    the centroid, or else the sensor z axis pointing up or down in the array frame), the board's halves
    "front"/"back" and "left"/"right" (x and y of the position about the centroid, REP-103: x forward, y left;
    IMUs on the mid-line in neither) and "outer"/"inner" (distance from the centroid above the median, when
    the distances differ); each with 2..K-1 IMUs, a group the same as an earlier one named once."""
    p = np.asarray(positions, dtype=float)
    k = len(p)
    c = p - p.mean(axis=0)
    out = []
    z = c[:, 2]
    up = np.asarray(rotations)[:, 2, 2]
    if np.ptp(z) > GEOMETRY_TOL:
        side = z > 0
    else:
        side = up > 0
    out += [("top", side), ("bottom", ~side)]
    for axis, (plus, minus) in ((0, ("front", "back")), (1, ("left", "right"))):
        if np.ptp(c[:, axis]) > GEOMETRY_TOL:
            out += [(plus, c[:, axis] > GEOMETRY_TOL / 2), (minus, c[:, axis] < -GEOMETRY_TOL / 2)]
    d = np.linalg.norm(c, axis=1)
    if np.ptp(d) > GEOMETRY_TOL:
        outer = d > np.median(d)
        out += [("outer", outer), ("inner", ~outer)]
    groups, seen = [], set()
    for name, m in out:
        idx = tuple(int(i) for i in np.flatnonzero(m))
        if 2 <= len(idx) < k and idx not in seen:
            seen.add(idx)
            groups.append((name, idx))
    return groups


def scopes_for(n_imus: int, groups) -> tuple[list[Scope], list[tuple[int, ...]]]:
    """The pooled scopes of an array of n_imus IMUs with the geometry's ``groups``, and the IMU index
    groups score_blocks must sum (every IMU first)."""
    tied = [("all", tuple(range(n_imus)))] + list(groups)
    scopes = [Scope(f"{name} shared", "shared", imus, i) for i, (name, imus) in enumerate(tied)]
    if 2 <= n_imus <= OWN_MAX_IMUS:
        scopes.append(Scope("all own", "own", tuple(range(n_imus))))
    return scopes, [imus for _, imus in tied]


def scoped_blocks(sb, term: str, scope: Scope):
    """(g (B, d), S (B, d, d)) of ``term`` at a pooled ``scope`` from ``sb`` (ScoreBlocks scored with the
    scope's groups / cross terms, given findings already profiled out by :func:`profile_given`); an own scope:
    every IMU of it its own value (d = its IMUs x p, their cross-IMU blocks)."""
    cols = sb.columns(term)
    p = cols.stop - cols.start
    if scope.kind == "shared":
        return sb.g[:, list(scope.imus), cols].sum(axis=1), sb.S_groups[:, scope.group, cols, cols]
    imus = list(scope.imus)
    b, k = sb.g.shape[0], len(imus)
    S = sb.S_cross[term][:, imus][:, :, imus].transpose(0, 1, 3, 2, 4).reshape(b, k * p, k * p)
    return sb.g[:, imus, cols].reshape(b, k * p), S


def given_columns(offsets: dict, dims: dict, found) -> np.ndarray:
    """(F, 2) (IMU, column) of the parameters of ``found`` [(term, IMU indexes)] in a ScoreBlocks grid with
    these term offsets and dims."""
    out = [(k, offsets[t] + j) for t, imus in found if t in offsets for k in imus for j in range(dims[t])]
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def _projector(sff: np.ndarray) -> np.ndarray:
    """Pseudo-inverse of the total information of the given parameters on its identified directions."""
    d = np.sqrt(np.clip(np.diag(sff), 0.0, None))
    d = np.where(d > 0, d, np.inf)
    lam, vec = np.linalg.eigh(sff / np.outer(d, d))
    keep = lam > 1e-8 * max(lam.max(), 0.0)
    q = vec[:, keep] / d[:, None]
    return q @ np.diag(1.0 / lam[keep]) @ q.T


def _project(g, S, X, gF, SFF, W):
    """Per block: score and information of columns with the given parameters F profiled out; g (B, d), S
    (B, d, d), X (B, F, d) their cross information, gF (B, F), SFF (B, F, F), W: pinv of sum SFF."""
    A = X.sum(axis=0).T @ W  # (d, F): regression of the candidate's columns on F (total information)
    AX = A @ X
    S2 = S - AX - AX.transpose(0, 2, 1) + A @ SFF @ A.T
    return g - gF @ A.T, S2


def profile_given(sb, groups=(), *, inplace: bool = False):
    """``sb`` with the parameters ``sb.given`` profiled out of every candidate's score and information
    (per IMU, the pooled ``groups`` (IMU indexes, as scored) and the cross terms); ``sb`` itself when nothing
    is given.  inplace: overwrite ``sb``'s arrays (no second copy of them in memory)."""
    if sb.given is None:
        return sb
    kf, cf = sb.given[:, 0], sb.given[:, 1]
    gF, X = sb.g[:, kf, cf], sb.S_given  # (B, F), (B, F, K, P): copies / never written
    SFF = X[:, :, kf, cf]
    W = _projector(SFF.sum(axis=0))
    b, k, p = sb.g.shape
    g, S = (sb.g, sb.S) if inplace else (np.empty_like(sb.g), np.empty_like(sb.S))
    for i in range(k):  # IMU i's slice is read before it is written
        g[:, i], S[:, i] = _project(sb.g[:, i], sb.S[:, i], X[:, :, i], gF, SFF, W)
    s_groups = None
    if sb.S_groups is not None:
        s_groups = sb.S_groups if inplace else np.empty_like(sb.S_groups)
        for j in range(sb.S_groups.shape[1]):  # the group's score is re-summed from the projected g
            _, s_groups[:, j] = _project(np.zeros((b, p)), sb.S_groups[:, j], X[:, :, list(groups[j])].sum(axis=2),
                                       gF, SFF, W)
    cross = {}
    for t in list(sb.S_cross):
        cols = sb.columns(t)
        q = cols.stop - cols.start
        full = sb.S_cross[t].transpose(0, 1, 3, 2, 4).reshape(b, k * q, k * q)
        if inplace:
            sb.S_cross[t] = None  # the reshaped copy above replaces it
        _, s2 = _project(np.zeros((b, k * q)), full, X[:, :, :, cols].reshape(b, -1, k * q), gF, SFF, W)
        del full
        cross[t] = s2.reshape(b, k, q, k, q).transpose(0, 1, 3, 2, 4)
    s_dir = None
    if sb.S_dir is not None:
        s_dir = sb.S_dir if inplace else np.empty_like(sb.S_dir)
        for d, (t, v) in enumerate(sb.directions):  # along v: the cross information of c_k v with F
            _, s_dir[:, d] = _project(np.zeros((b, k)), sb.S_dir[:, d], X[:, :, :, sb.columns(t)] @ v, gF, SFF, W)
    return replace(sb, g=g, S=S, S_groups=s_groups, S_cross=cross, S_dir=s_dir)


def score_given(samples, model, terms, motion, blocks, groups, found, *, own_terms=(), directions=()):
    """score_blocks of ``terms`` with the pooled ``groups``, the cross-IMU blocks of ``own_terms`` and along
    ``directions`` [(term, v)], and the parameters of ``found`` [(term, IMU indexes)] profiled out
    (:func:`profile_given`)."""
    terms = check_terms(terms)
    dims = {t: REGISTRY[t].dim() for t in terms}
    offsets = dict(zip(terms, np.cumsum([0] + [dims[t] for t in terms])[:-1].tolist()))
    # on one BLAS thread: discover (its only caller) runs whole inside one (.threads)
    sb = score_blocks(samples, model, terms, motion, blocks, groups=groups, cross_terms=own_terms,
                      given=given_columns(offsets, dims, found), directions=directions)
    return profile_given(sb, groups, inplace=True)  # the unprofiled arrays are not kept


def tie_test(fit, term: str, imus, names, base: np.ndarray) -> dict:
    """Whether the exact fit's per-IMU values of ``term`` on ``imus`` (changes from ``base`` (G, p), the
    model discovery started from) are consistent with one shared value: the generalised least-squares
    value phi = (T^T W T)^-1 T^T W theta (T stacks G identities, W the inverse CRB of the G x p values, held
    ones left out) and the Wald statistic (theta - T phi)^T W (theta - T phi), chi-square with
    (values - p) dof when the values are equal -- asymptotically the likelihood ratio of the tied fit."""
    dims = [REGISTRY[t].dim() for t in fit.free]
    p, off = REGISTRY[term].dim(), sum(dims[:list(fit.free).index(term)])
    width = sum(dims)
    idx = np.array([list(fit.imus).index(names[k]) * width + off + i for k in imus for i in range(p)])
    theta = fit.theta[idx] - np.asarray(base, dtype=float).reshape(-1)
    cov = fit.covariance[np.ix_(idx, idx)]
    keep = np.diag(cov) > 0
    t = np.tile(np.eye(p), (len(imus), 1))[keep]
    w = np.linalg.pinv(cov[np.ix_(keep, keep)], hermitian=True)
    info = t.T @ w @ t
    cov_phi = np.linalg.pinv(info, hermitian=True)
    phi = cov_phi @ t.T @ w @ theta[keep]
    r = theta[keep] - t @ phi
    stat = float(r @ w @ r)
    dof = int(keep.sum() - np.linalg.matrix_rank(info))
    return {"values": phi, "std": np.sqrt(np.clip(np.diag(cov_phi), 0.0, None)), "statistic": stat, "dof": dof,
            "p": float(scipy.stats.chi2.sf(stat, dof)) if dof > 0 else 1.0}
