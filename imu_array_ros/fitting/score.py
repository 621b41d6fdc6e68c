"""Discovery's score test: score and Fisher information of candidate terms per time block and IMU, with
every sample's motion profiled out (the per-IMU blocks of the engine's Schur complement; theory:
:mod:`imu_array_ros.fitting`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.problem import Problem, check_terms
from imu_array_ros.fitting.schur import factor, g_per_imu, gram, per_imu
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

__all__ = ["ScoreBlocks", "score_blocks"]


@dataclass
class ScoreBlocks:
    """Score and Fisher information of candidate terms, per time block and IMU, with the motion profiled out.

    terms: the candidate terms; offsets: term -> first column in the per-IMU
    parameter vector (P = sum of the terms' sizes); g (B, K, P): score
    d loglik / d theta_k summed over block b (each IMU's parameters alone,
    every other held); S (B, K, P, P): the information of IMU k's parameters
    in block b with every sample's motion profiled out (the per-IMU diagonal
    block of the engine's Schur complement; block sums add up to it);
    counts (B,) samples per block; residuals (N, K, 6) normalised, NaN on
    masked axes and on samples that do not identify their motion; expected (N,
    K, 6): E[r^2] = 1 - leverage of each valid axis (leverage: what the fitted
    motion absorbs, 9 per sample), NaN where masked; cost: sum r^2 / 2;
    loglik: log-likelihood of the valid axes; valid_axes: their number.

    Cross-IMU information (the motion couples the IMUs; computed only when asked for):
    S_groups (B, G, P, P): the information of one parameter vector shared by the IMUs of each of ``groups``
    (its score is the sum of their g); S_cross: term -> (B, K, K, p, p) every IMU pair's information of that
    term (``cross_terms``); given (F, 2) (IMU, column) of chosen parameters and S_given (B, F, K, P) their
    information with every parameter (to profile them out of the tests); directions: ((term, v), ...) and
    S_dir (B, D, K, K) every IMU pair's information of that term along the one value v (p,) on each IMU: the
    term on IMU k as c_k v, one number per IMU (``directions``).
    """

    terms: tuple[str, ...]
    offsets: dict[str, int]
    g: np.ndarray
    S: np.ndarray
    counts: np.ndarray
    residuals: np.ndarray = field(repr=False)
    expected: np.ndarray = field(repr=False)
    cost: float = 0.0
    loglik: float = 0.0
    valid_axes: int = 0
    S_groups: np.ndarray | None = field(default=None, repr=False)
    S_cross: dict = field(default_factory=dict, repr=False)
    given: np.ndarray | None = None
    S_given: np.ndarray | None = field(default=None, repr=False)
    directions: tuple = ()
    S_dir: np.ndarray | None = field(default=None, repr=False)

    def columns(self, term: str) -> slice:
        return slice(self.offsets[term], self.offsets[term] + REGISTRY[term].dim())


def score_blocks(samples: ImuSamples, model: SensorModel, terms: Sequence[str], motion, blocks, *,
                 sigma=None, groups=(), cross_terms=(), given=(), directions=()) -> ScoreBlocks:
    """Score test ingredients of every term in ``terms`` on every IMU at (model, motion), by time block.

    ``motion`` (N, 9): the ML motion for ``model`` (:func:`~imu_array_ros.fitting.engine.fit_motion`);
    blocks (N,) non-decreasing block index 0..B-1 of every sample (contiguous
    blocks).  For the parameters theta_k of one IMU, g_k = J_t,k^T r -
    sum_n G_n,k^T h_n and S_kk = C_kk - sum_n G_n,k^T G_n,k (:mod:`imu_array_ros.fitting`)
    are the score and information of the one-step Gauss-Newton fit of theta_k
    with every sample's motion re-estimated: g^T S^-1 g is the Rao score
    statistic of adding the term to that IMU (chi-square under the model) and
    g^T S^-1 g / 2 the log-likelihood it gains to first order.  Per block, so
    that held-out blocks and a block-robust (sandwich) variance can be formed.

    groups: sequences of IMU indexes; cross_terms: terms of ``terms``; given: (IMU, column) pairs;
    directions: (term, v) pairs: the cross-IMU informations of :class:`ScoreBlocks` (S_kl = delta_kl C_kk -
    sum_n G_n,k^T G_n,l; along v: v^T S_kl v).
    """
    terms = check_terms(terms)
    k = model.n_imus
    prob = Problem(samples, model, terms, np.arange(k), sigma=sigma)
    blocks = np.asarray(blocks, dtype=np.int64).reshape(-1)
    if blocks.shape != (prob.n,) or blocks.min() < 0 or np.any(np.diff(blocks) < 0):
        raise CalibrationError("blocks must give a non-decreasing block index >= 0 for every sample")
    z = prob.check_motion(motion, model)
    derivs = prob.derivatives(z)
    nb, p = int(blocks[-1]) + 1, prob.p
    g, S = np.zeros((nb, k, p)), np.zeros((nb, k, p, p))
    res, expected = np.full_like(prob.y, np.nan), np.full_like(prob.y, np.nan)
    cost = 0.0
    groups = [np.asarray(gr, dtype=np.int64) for gr in groups]
    s_groups = np.zeros((nb, len(groups), p, p))
    offs = prob.offsets
    cross = {t: np.zeros((nb, k, k, REGISTRY[t].dim(), REGISTRY[t].dim())) for t in cross_terms}
    given = np.asarray(given, dtype=np.int64).reshape(-1, 2)
    s_given = np.zeros((nb, len(given), k, p))
    directions = tuple((t, np.asarray(v, dtype=float).reshape(REGISTRY[t].dim())) for t, v in directions)
    s_dir = np.zeros((nb, len(directions), k, k))
    mask = np.zeros(prob.y.shape, dtype=bool)
    for lo, hi, pieces in _chunks(blocks, prob.chunk):
        # per-sample quantities of the whole chunk at once (one Jacobian call), then per-block sums
        ctx = prob.context(model, z, derivs, lo, hi)
        jac = model.jacobians(ctx, terms)
        cols = prob.rates(model, ctx)
        linv, ok, _ = factor(gram(prob.motion_jacobian(jac.motion, prob.w[lo:hi], z, slice(lo, hi), cols)))
        w = prob.w[lo:hi] * ok[:, None, None]  # a sample that does not identify its motion tells nothing
        r = w * (prob.y[lo:hi] - jac.predicted - prob.rate_shift(cols, z, slice(lo, hi)))
        jx = prob.motion_jacobian(jac.motion, w, z, slice(lo, hi), cols)
        h = np.einsum("nij,nkrj,nkr->ni", linv, jx, r, optimize=True)
        jt = prob.parameter_jacobian(jac, w)
        mk, gk_all = g_per_imu(jx, linv, jt)  # (n, K, 6, 9): rows (L^-1 phi)^T; (n, K, 9, P) G_n,k
        for b, a, e in pieces:
            jk, gk, rb = per_imu(jt[a:e]), gk_all[a:e], r[a:e]
            gs = gk.transpose(1, 0, 2, 3).reshape(k, -1, p)
            ck = np.matmul(jk.transpose(0, 2, 1), jk)
            S[b] += ck - np.matmul(gs.transpose(0, 2, 1), gs)
            for i, gr in enumerate(groups):
                gg = gk[:, gr].sum(axis=1).reshape(-1, p)
                s_groups[b, i] += ck[gr].sum(axis=0) - gg.T @ gg
            for t, out in cross.items():
                c = slice(offs[t], offs[t] + REGISTRY[t].dim())
                gc = gk[..., c].transpose(1, 0, 2, 3).reshape(k, -1, c.stop - c.start)  # (K, n 9, p)
                out[b] -= np.matmul(gc.transpose(0, 2, 1)[:, None], gc[None])
                out[b, np.arange(k), np.arange(k)] += ck[:, c, c]
            for d, (t, v) in enumerate(directions):
                c = slice(offs[t], offs[t] + REGISTRY[t].dim())
                gv = (gk[..., c] @ v).transpose(1, 0, 2).reshape(k, -1)  # (K, n 9): G_n,k v
                s_dir[b, d] -= gv @ gv.T
                s_dir[b, d, np.arange(k), np.arange(k)] += np.einsum("kpq,p,q->k", ck[:, c, c], v, v)
            if len(given):
                gf = gk[:, given[:, 0], :, given[:, 1]]  # (F, n, 9)
                s_given[b] -= np.matmul(gf.reshape(len(given), -1)[None], gs).transpose(1, 0, 2)
                s_given[b, np.arange(len(given)), given[:, 0]] += ck[given[:, 0], given[:, 1]]
            g[b] += (np.matmul(jk.transpose(0, 2, 1), rb.transpose(1, 0, 2).reshape(k, -1, 1))[..., 0]
                     - np.einsum("nkip,ni->kp", gk, h[a:e]))
        valid = prob.valid[lo:hi] & ok[:, None, None]
        mask[lo:hi] = valid
        res[lo:hi] = np.where(valid, r, np.nan)
        expected[lo:hi] = np.where(valid, 1.0 - np.sum(mk * mk, axis=3), np.nan)
        cost += 0.5 * float(np.sum(r * r))
    return ScoreBlocks(terms, prob.offsets, g, S, np.bincount(blocks, minlength=nb), res, expected, cost,
                       prob.loglik(cost, mask), int(mask.sum()), s_groups if groups else None, cross,
                       given if len(given) else None, s_given if len(given) else None, directions,
                       s_dir if directions else None)


def _chunks(blocks: np.ndarray, chunk: int):
    """(lo, hi, [(block, a, e)]) spans of at most ``chunk`` samples made of whole blocks (a block longer than
    ``chunk`` split), with the block of every piece and its sample range relative to lo."""
    edges = np.flatnonzero(np.diff(blocks)) + 1
    starts, ends = np.r_[0, edges], np.r_[edges, len(blocks)]
    lo, pieces = 0, []
    for b, s0, e0 in zip(blocks[starts].tolist(), starts.tolist(), ends.tolist()):
        for s in range(s0, e0, chunk):
            e = min(s + chunk, e0)
            if pieces and e - lo > chunk:
                yield lo, s, pieces
                lo, pieces = s, []
            pieces.append((b, s - lo, e - lo))
    if pieces:
        yield lo, len(blocks), pieces
