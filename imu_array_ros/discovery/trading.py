"""Whether a confirmed candidate trades with the earlier findings instead of explaining new physics.

A candidate refitted exactly together with every finding so far (:func:`.confirm.confirm`) can gain by moving
the earlier findings' values along a direction of its parameters the earlier terms can nearly produce: on a
recording where the candidate's signature is almost a combination of theirs, its value is then set by what the
library lacks rather than by the candidate's own physics (on the real capture exp_1 a gyroscope gain of +0.107
on every IMU, found after the accelerometers' per-axis offsets, is such a trade: without the offsets the same
fit gives gains of 0.97-1.01).  The gain in log-likelihood cannot tell it: the trade fits the data better.

The test reads the joint fit's Cramér-Rao information (the motion profiled out), so it depends on the design of
the recording, not on the size of the residual (on the real captures the residual is ~30 noise stds, and every
change, true or not, moves the earlier findings by tens of their standard errors):

- **Canonical directions.** Let C be the candidate's parameters and E the earlier findings'.  With E held,
  C's information is J_CC; with E free (profiled), it is S_C = J_CC - J_CE J_EE^-1 J_EC.  In coordinates
  whitened by S_C, J_CC has eigenvalues VIF_i = 1 / (1 - rho_i^2), rho_i the canonical correlations of C's
  signature with E's, VIF_i the variance inflation of that direction of C by E.
- **Where the evidence is.** C's evidence given E (the Wald statistic of its change, the first-order twice log-
  likelihood gain) is sum_i z_i^2 over those directions.  The *traded share* is the part of it on directions with
  rho_i^2 >= :data:`CONFOUNDED_RHO2` (VIF >= 10, the textbook bound of severe collinearity: more than 90 % of
  that direction of C's signature is a change of the earlier findings).
- **Decision.** When the traded share is at least :data:`TRADED_SHARE` (most of the evidence), the candidate is
  not reported: on this recording it is indistinguishable from a change of the earlier findings it trades with
  (named: those whose information takes the most of C's estimate).

False rejections: a true effect is rejected only when most of its own evidence lies on directions 90 %
predictable from the earlier findings' terms on this recording; pure noise adds about 1 per direction to the
traded part (not its VIF), so a weak true effect (evidence >= the step's chi-square level, tens) is not pushed
over the share by a few confounded directions.  An earlier finding biased by a missing true partner is moved by
the partner's refit (item 4 of the issue) whatever the partner's correlation: that shift alone is not read.
Neither bound was tuned on a recording (both are fixed conventions); measured in docs/discovery.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.discovery.subset import term_indexes

__all__ = ["Trade", "trading", "traded_share", "CONFOUNDED_RHO2", "TRADED_SHARE"]

#: squared canonical correlation from which a direction of the candidate counts as a change of earlier findings
CONFOUNDED_RHO2 = 0.9
#: share of the candidate's evidence on such directions from which it is not reported
TRADED_SHARE = 0.5
#: relative eigenvalue below which a direction is not identified (held by the fit's gauge or null)
_RTOL = 1e-10


@dataclass
class Trade:
    """share: the candidate's evidence on confounded directions / all of it; evidence: its Wald statistic given
    the earlier findings; rho_max: the largest canonical correlation; confounded: directions with rho^2 >=
    CONFOUNDED_RHO2; partners: the earlier findings (effect, sensor) it trades with, most first; traded: share
    >= TRADED_SHARE."""

    share: float
    evidence: float
    rho_max: float
    confounded: int
    dims: int
    partners: list
    traded: bool

    def reason(self) -> str:
        names = " and ".join(f"{e} on {s}" for e, s in self.partners) or "the earlier findings"
        return (f"indistinguishable from {names} on this recording: {100 * self.share:.0f} % of its evidence "
                f"given them (Wald {self.evidence:.4g}) lies on {self.confounded} of its {self.dims} directions that "
                f"are at least {100 * CONFOUNDED_RHO2:.0f} % a change of their values (canonical correlation up to "
                f"{self.rho_max:.4f}, variance inflation >= {1 / (1 - CONFOUNDED_RHO2):.0f}); >= "
                f"{100 * TRADED_SHARE:.0f} % means its values trade with theirs rather than explain new physics")


def _sym_pinv(a: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    ok = w > _RTOL * max(w.max(initial=0.0), 0.0)
    return (v[:, ok] / w[ok]) @ v[:, ok].T


def traded_share(cov: np.ndarray, change: np.ndarray, groups) -> tuple[float, float, np.ndarray, np.ndarray, list]:
    """(share, evidence, rho^2 per direction, the estimate's part on the confounded directions, each earlier
    group's part of it) of a candidate whose parameters are the first ``len(change)`` of ``cov`` (the joint
    covariance of the candidate's and the earlier findings' identified parameters, the earlier ones in
    consecutive ``groups`` of the given sizes); ``change``: the candidate's estimate less its starting value."""
    scale = np.sqrt(np.diag(cov))
    corr = cov / np.outer(scale, scale)
    info = _sym_pinv(corr)  # information of the scaled parameters, C first
    n = len(change)
    c_hat = np.asarray(change, dtype=float) / scale[:n]
    lam, u = np.linalg.eigh(corr[:n, :n])  # C's joint covariance (E free) = R R^T, R = U sqrt(lam)
    ok = lam > _RTOL * lam.max()
    r = u[:, ok] * np.sqrt(lam[ok])
    z = (u[:, ok].T @ c_hat) / np.sqrt(lam[ok])  # whitened by S_C: sum z^2 = the Wald statistic given E
    vif, v = np.linalg.eigh(r.T @ info[:n, :n] @ r)  # J_CC in those coordinates: eigenvalues 1 / (1 - rho^2)
    rho2 = 1.0 - 1.0 / np.maximum(vif, 1.0)
    zi2 = (v.T @ z) ** 2
    evidence = float(zi2.sum())
    bad = rho2 >= CONFOUNDED_RHO2
    share = float(zi2[bad].sum() / evidence) if evidence > 0 else 0.0
    d = r @ (v[:, bad] @ (v[:, bad].T @ z))  # the estimate's part on the confounded directions (scaled)
    parts, off = [], n
    for size in groups:  # each earlier finding's part of J_CE J_EE^-1 J_EC along it
        x = info[off:off + size, :n] @ d
        parts.append(float(x @ _sym_pinv(info[off:off + size, off:off + size]) @ x) if size else 0.0)
        off += size
    return share, evidence, rho2, d * scale[:n], parts


def trading(fit, current, earlier, term: str, imus) -> Trade | None:
    """The :class:`Trade` figures of candidate ``term`` on ``imus`` at the joint exact ``fit`` of it and the
    ``earlier`` findings (objects with effect, imus, sensor); its change is read from ``current`` (the model the
    refit started from).  None without earlier findings or identified parameters."""
    earlier = list(earlier)
    if not earlier:
        return None
    cov = fit.covariance
    keep = np.diag(cov) > 0
    full_c = term_indexes(fit, term, imus)
    ic = full_c[keep[full_c]]
    groups = [term_indexes(fit, f.effect, f.imus) for f in earlier]
    groups = [g[keep[g]] for g in groups]
    if not ic.size or not sum(g.size for g in groups):
        return None
    idx = np.concatenate([ic, *groups])
    start = np.asarray(current.terms[term].values[list(imus)], dtype=float).reshape(-1)[keep[full_c]]
    share, evidence, rho2, _, parts = traded_share(cov[np.ix_(idx, idx)], fit.theta[ic] - start,
                                                   [g.size for g in groups])
    top = max(parts)
    partners = [(f.effect, f.sensor) for p, f in sorted(zip(parts, earlier), key=lambda t: -t[0])
                if top > 0 and p >= 0.5 * top]
    return Trade(share, evidence, float(np.sqrt(rho2.max())), int(np.sum(rho2 >= CONFOUNDED_RHO2)), len(rho2),
                 partners, share >= TRADED_SHARE)
