"""Uncertainty that holds when the model is not exact, and fits that large residuals do not drag.

Sandwich covariance
-------------------
The engine's estimate solves sum_n u_n(theta) = 0 with u_n the *profiled score* of sample n (the motion
x_n eliminated, :mod:`imu_array_ros.fitting`)::

    u_n = J_t,n^T r_n - G_n^T h_n        (M,),   sum_n u_n = g_red,

so to first order theta_hat - theta* = S^-1 sum_n u_n (in the gauge-reduced coordinates z of
:class:`~imu_array_ros.fitting.gauge.Gauge`; theta* the parameters the fit converges to with infinite data).
Its covariance is the sandwich (Huber 1967, White 1982)::

    Cov_robust = S^-1 B S^-1,     B = Var(sum_n u_n)  (the long-run covariance of the scores).

When the model is exact and the noise white, B = S (the information identity) and the sandwich is the
Cramér-Rao bound S^-1.  When it is not -- misfit that the residuals show as time-correlated structure, noise
that is not white, noise figures that are wrong -- B != S and only the sandwich is the spread of the estimate
over recordings of the same kind.  It does not see a bias: an unmodelled effect whose score has a non-zero
mean over the motion moves theta* away from the truth, in every recording alike.

B is estimated from the recording itself by **non-overlapping block sums in time** (batch means; Flyvbjerg &
Petersen 1989, J. Chem. Phys. 91, 461): with a_n = S^-1 u_n the influence of sample n on the estimate and
A_b = sum_{n in block b} a_n, blocks of duration T_j = 2^j dt (dt the median sample interval; a block is a
time interval, so dropped samples and gaps only thin a block out, they never join distant samples)::

    Cov_j = sum_b (A_b - w_b A)(A_b - w_b A)^T / (1 - sum_b w_b^2),    w_b = n_b / n,  A = sum_b A_b.

The centring and the factor make Cov_j unbiased for independent blocks of any sizes (1 / sum w_b^2 is the
effective number of blocks, n_eff).  Correlation that outlasts a block makes Cov_j too small; longer blocks
remove that bias but leave fewer blocks, so Cov_j gets noisier (relative std of a variance sqrt(2 / (n_eff -
1))).  The block length is chosen per parameter by the rule of Lee et al. (2011, Phys. Rev. E 83, 066706;
the rule of the ``pyblock`` package): the smallest level with (2^j)^3 >= 2 n (v_j / v_0)^2, v_j the
parameter's variance at level j, n the samples -- the block length that balances that bias (~ tau / T_j for a
correlation time tau) against the noise, found where v_j has reached its plateau.  The longest of the
parameters' lengths is used for the whole matrix (one block length, so the covariance stays positive
semi-definite), as long as at least max(``MIN_BLOCKS``, 2 R) effective blocks remain (R parameters); when a
parameter's rule is not
met within that limit the longest allowed length is used and ``plateau`` is False: the residuals are
correlated over a good part of the recording and the covariance is then still too small.  With fewer samples
than that the sandwich is not computed (the CRB is all there is).

A second, smaller bias: the scores are evaluated at the estimate, which is fitted to the same blocks.  The
centring above removes it exactly when every block carries the same share of the information; blocks whose
information differs in shape (the motion varies) leave a relative underestimate of about
(1 + d^2 R) / n_eff, d the relative spread of the blocks' information (the leverage of the blocks); hence
n_eff >= 2 R (e.g. ~10 % of variance, 5 % of std, for d = 0.5).

False coverage: with the plateau reached the variance is unbiased to O(tau / T) and carries n_eff - 1 degrees
of freedom, so a 95 % interval estimate +- 1.96 std covers with ~94 % (n_eff = 32; the Student t quantile
with n_eff - 1 degrees of freedom gives 95 %).  Without the plateau it covers less, by the correlation left
beyond the block length.

Newey-West with a data-driven bandwidth would do as well for equally spaced samples; blocks in time are used
because they need no equal spacing (the engine drops samples) and cost one cumulative sum per level.

Huber reweighting
-----------------
:func:`huber_sigma` turns the normalised residuals of a fit into per-reading standard deviations for the
engine's ``sigma`` argument: each axis' robust scale s (1.4826 x the median absolute residual over the
samples) and Huber's weight min(1, c / |r / s|) (c = ``HUBER_C``, 95 % efficiency under Gaussian noise):
sigma = sigma_0 s / sqrt(weight).  Iterated a few times (IRLS) it is the Huber M-estimate, in which a
reading far out (a knock, a saturated burst the clip test missed) counts linearly, not quadratically;
``fit_terms(..., robust="huber")`` does that.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.fitting.schur import g_per_imu

__all__ = ["RobustCovariance", "sample_influence", "blocked_covariance", "huber_sigma", "MIN_BLOCKS", "HUBER_C",
           "HUBER_ROUNDS"]

#: the fewest effective blocks a block length may leave (each variance then carries >= MIN_BLOCKS - 1 dof)
MIN_BLOCKS = 32
#: Huber's tuning constant, in robust standard deviations (95 % efficiency for Gaussian noise)
HUBER_C = 1.345
#: reweighting rounds of ``fit_terms(..., robust="huber")``
HUBER_ROUNDS = 3


@dataclass
class RobustCovariance:
    """The sandwich covariance in the gauge-reduced coordinates and how its blocks were chosen.

    covariance (R, R): S^-1 B S^-1; block_seconds: the block duration used; blocks: effective number of
    blocks at it (1 / sum w_b^2); plateau: every parameter's block rule was met with >= MIN_BLOCKS blocks;
    levels: (block seconds, effective blocks, median over parameters of v_j / v_0) per level tried.
    """

    covariance: np.ndarray = field(repr=False)
    block_seconds: float
    blocks: float
    plateau: bool
    levels: list = field(default_factory=list, repr=False)

    def describe(self) -> str:
        """'sandwich, blocks of 1.02 s (587 effective)' (with ', no plateau' when it was not reached)."""
        return (f"sandwich, blocks of {self.block_seconds:.3g} s ({self.blocks:.0f} effective)"
                f"{'' if self.plateau else ', no plateau (correlation outlasts the longest block: too small)'}")


def sample_influence(prob, model, motion: np.ndarray, lin, reduce: np.ndarray) -> np.ndarray:
    """(N, R) a_n = reduce^T u_n: the profiled score of every sample (:mod:`.robust`) mapped by ``reduce`` (M,
    R), e.g. (Z S_z^-1) for the influence on the gauge-reduced estimate; 0 for dropped samples.

    One pass over the samples at the point of ``lin`` (a :class:`~imu_array_ros.fitting.problem.Linearization`
    of ``prob`` at (model, motion)), chunk by chunk; sum_n u_n = lin.g."""
    out = np.zeros((prob.n, reduce.shape[1]))
    for lo, hi in prob.chunks():
        ctx = prob.context(model, motion, lin.derivs, lo, hi)
        jac = model.jacobians(ctx, prob.free)
        w = prob.w[lo:hi]
        cols = prob.rates(model, ctx)
        jx = prob.motion_jacobian(jac.motion[:, prob.cols], w[:, prob.cols], motion, slice(lo, hi),
                                  None if cols is None else cols[:, prob.cols])
        jt = prob.parameter_jacobian(jac, w)  # (n, K_fit, 6, P)
        gk = g_per_imu(jx, lin.linv[lo:hi], jt)[1]  # (n, K_fit, d, P)
        u = np.einsum("nkrp,nkr->nkp", jt, lin.r[lo:hi, prob.cols]) - np.einsum("nkip,ni->nkp", gk, lin.h[lo:hi])
        out[lo:hi] = u.reshape(hi - lo, -1) @ reduce
    return out


def blocked_covariance(a: np.ndarray, stamps: np.ndarray, min_blocks: int | None = None) -> RobustCovariance | None:
    """Covariance of sum_n a_n from time blocks (module docstring): a (n, R) per-sample influences, stamps (n,)
    int64 ns increasing (the samples used); min_blocks: the fewest effective blocks a level may leave (default
    max(``MIN_BLOCKS``, 2 R)).  None when even single samples are fewer than that (too few to estimate B)."""
    n, r = a.shape
    min_blocks = max(MIN_BLOCKS, 2 * r) if min_blocks is None else min_blocks
    t = np.asarray(stamps, dtype=np.int64) - int(stamps[0])
    steps = np.diff(t)
    dt = int(np.median(steps[steps > 0])) if np.any(steps > 0) else 1
    cum = np.concatenate([np.zeros((1, r)), np.cumsum(a, axis=0)])
    total = cum[-1]
    levels, covs = [], []
    for j in range(64):
        ids = t // (dt << j)
        starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
        ends = np.r_[starts[1:], n]
        w = (ends - starts) / n
        n_eff = 1.0 / float(np.sum(w * w))
        if n_eff < min_blocks:
            if not j:
                return None
            break
        dev = cum[ends] - cum[starts] - w[:, None] * total[None]
        covs.append(dev.T @ dev / max(1.0 - 1.0 / n_eff, 1e-12))
        levels.append(((dt << j) * 1e-9, n_eff))
        if len(starts) == 1:
            break
    v = np.array([np.diag(c) for c in covs])  # (levels, R)
    v0 = np.where(v[0] > 0, v[0], np.inf)
    ratio = v / v0
    size = 2.0 ** np.arange(len(covs))
    met = size[:, None] ** 3 >= 2 * n * ratio ** 2  # Lee et al. 2011, per parameter
    ok = met.any(axis=0) | (v[0] <= 0)
    first = np.where(met.any(axis=0), np.argmax(met, axis=0), 0)
    plateau = bool(ok.all())
    j = int(first.max(initial=0)) if plateau else len(covs) - 1
    rows = [(s, e, float(np.median(q)) if r else 1.0) for (s, e), q in zip(levels, ratio)]
    return RobustCovariance(covs[j], levels[j][0], levels[j][1], plateau, rows)


def huber_sigma(residuals: np.ndarray, sigma: np.ndarray, c: float = HUBER_C) -> np.ndarray:
    """(N, K, 6) reweighted standard deviations for the engine's ``sigma``: sigma s / sqrt(min(1, c / |r / s|)).

    residuals (N, K, 6): normalised residuals of the last fit (NaN where masked or dropped); sigma (N, K, 6):
    the standard deviations they were normalised with; s (K, 6): 1.4826 x each axis' median |r| (1 where an
    axis has no finite residual)."""
    with warnings.catch_warnings():  # an axis without any finite residual (masked throughout) gets scale 1
        warnings.simplefilter("ignore", RuntimeWarning)
        mad = np.nanmedian(np.abs(residuals), axis=0)
    scale = np.where(np.isfinite(mad) & (mad > 0), 1.4826 * mad, 1.0)
    z = np.abs(np.nan_to_num(residuals)) / scale[None]
    weight = np.minimum(1.0, c / np.maximum(z, 1e-300))
    return sigma * scale[None] / np.sqrt(weight)
