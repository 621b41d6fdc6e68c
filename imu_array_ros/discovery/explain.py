"""Explain a mismatch with the sensor model's own terms: score tests, held-out blocks, greedy selection.

A *candidate* is one registered term (:data:`~imu_array_ros.model.terms.REGISTRY`)
on one IMU, every other parameter held.  From one pass of the fitting engine
(:func:`~imu_array_ros.fitting.engine.score_blocks`) at the current
model and its ML motion, each candidate c has, per time block b, a score g_b
and an information S_b with every sample's motion profiled out (Schur
complement: the part of the term's signature the motion cannot absorb).  With
g = sum g_b, S = sum S_b (rank q on the identifiable directions):

* **score (LRT) test**: T = g^T S^+ g, chi-square with q degrees of freedom
  when the term is absent; T / 2 is the log-likelihood the term gains to first
  order (the Rao score statistic, asymptotically the likelihood ratio);
* **block-robust test**: the sandwich variance of the block scores around the
  fit, u_b = g_b - S_b theta_hat, bias-reduced (CR2: each u_b scaled by
  (I - S_b S^-1)^-1/2), gives T_r = g^T V^+ g, referred to F(q, eta - q + 1)
  with eta the HTZ degrees of freedom (about the count of equally informative
  blocks, often far below B on rests-then-twist sessions); where eta leaves
  fewer than HTZ_MIN_DOF, the one-scale-factor (dispersion) form with
  Satterthwaite dof.  It stays calibrated when the residual is not white within
  a block (a sensor with coloured noise, a vibration), where the plain test
  would see structure everywhere;
* **held-out blocks**: blocks are dealt to ``folds`` interleaved folds;
  theta fitted on all folds but f (one Gauss-Newton step) must predict fold f:
  held-out gain sum_f [g_f^T theta_-f - theta_-f^T S_f theta_-f / 2] > 0;
* **BIC**: delta_bic = q ln(n) - T (n valid readings), negative when the term pays
  for its parameters.

Selection is greedy: at each step the candidate with the lowest BIC among
those passing both tests at the Bonferroni level ``alpha / m`` (m candidates
tested in that step) with a positive held-out gain is refitted exactly with the
engine together with every finding so far (:func:`fit_terms` with ``only``),
kept if the exact likelihood ratio confirms it, and the scores are recomputed
at the new model.  With ``alpha`` = 0.01 the probability of any false finding
on a recording the model already explains is at most 1 % (the first step's
family-wise error; later steps are conditional on true findings).  Testing each
candidate at the current estimate, the uncertainty of the findings already in
is ignored: that makes S larger than the efficient information, so the tests
are conservative, never liberal.

Confounded candidates (time offset vs position, gain vs nonlinearity, ...)
are told apart by the data when one explains clearly more (BIC gap >=
``BIC_GAP``) or adds information given the other; otherwise they are reported
together as indistinguishable, with the canonical correlation of their
projected signatures (1: the recording cannot separate them).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.special
import scipy.stats

from imu_array_ros.discovery.drift import GIVEN, candidate_blocks
from imu_array_ros.discovery.scopes import Scope, scoped_blocks

__all__ = ["Candidate", "evaluate_candidates", "evaluate_scopes", "confounded", "added_given", "scope_design",
           "block_tests", "increment_test", "BIC_GAP", "EIG_RTOL"]

#: BIC difference (2 ln Bayes factor) below which two candidates count as explaining equally well (Kass & Raftery:
#: >= 10 is "very strong" evidence for the better one)
BIC_GAP = 10.0
#: least denominator dof of the CR2 block-robust test's F reference (HTZ: eta - q + 1, eta ~ the count of equally
#: informative blocks) below which the dispersion form is used instead: at fewer the F tail is so heavy that
#: p < 1e-5 needs about 2x (20 dof) to 4000x (2 dof) the score chi-square's statistic (q = 1..9)
HTZ_MIN_DOF = 20.0
#: tolerance on the whitened block informations M_b = S^-1/2 S_b S^-1/2 being covariances (0 <= M_b <= I); a
#: candidate whose blocks' informations are not (some S_b indefinite: a signature the motion absorbs almost
#: wholly, its blocks' parts large and of either sign) gets Hotelling's F(q, B - q) on the plain sandwich,
#: whose small-sample corrections (CR2, HTZ, dispersion) assume them (with them: nan, a gate no evidence passes)
PSD_TOL = 1e-6
#: eigenvalue of a candidate's Jacobi-scaled information, relative to its largest, below which a direction is
#: not identified by the recording (left out of the test, the test's dof drops)
EIG_RTOL = 1e-8


@dataclass
class Candidate:
    """The evidence for one term on one IMU at one step of the selection.

    statistic T, dof q, lrt_p (chi-square), robust_p (block sandwich, F),
    delta_loglik = T / 2 (first order), delta_bic = q ln(n) - T, heldout:
    cross-validated gain in log-likelihood over the folds; theta (P,): the
    one-step estimate (SI units of the term's parameters); blocks: blocks
    with data; scope: "imu" or a pooled scope's label (:mod:`.scopes`), imus: its IMU indexes (k the first),
    sensor then names the scope.  exact_gain: the exact refit's log-likelihood gain of the hypothesis as
    reported (a shared scope's: the per-IMU fit's less half its tie statistic); equivalents: [{"sensors",
    "reason"}] other scopes of the term that fit as well (:func:`~.confirm.confirm`'s narrowing); extends: the
    key of an accepted finding whose one value this candidate puts on one more IMU (:mod:`.extend`), else ().
    """

    effect: str
    k: int
    sensor: str
    statistic: float
    dof: int
    lrt_p: float
    robust_p: float
    delta_loglik: float
    delta_bic: float
    heldout: float
    theta: np.ndarray = field(repr=False)
    log_p: float = 0.0
    step: int = 0
    accepted: bool = False
    note: str = ""
    scope: str = "imu"
    imus: tuple = ()
    sensors: tuple = ()
    exact_gain: float | None = None
    equivalents: list = field(default_factory=list)
    extends: tuple = ()  # the key of the shared finding this candidate grows by one IMU (:mod:`.extend`)

    def __post_init__(self):
        self.imus = tuple(self.imus) or (self.k,)
        self.sensors = tuple(self.sensors) or (self.sensor,)

    @property
    def added(self) -> set:
        """The IMUs the candidate puts its term on: an extension's beyond the finding it grows (:mod:`.extend`)."""
        return set(self.imus) - set(self.extends[2]) if self.extends else set(self.imus)

    @property
    def key(self) -> tuple:
        """(effect, scope, imus): identifies the hypothesis across steps."""
        return self.effect, self.scope, self.imus

    def passes(self, level: float) -> bool:
        return self.lrt_p < level and self.robust_p < level and self.heldout > 0.0

    def to_dict(self) -> dict:
        return {"effect": self.effect, "sensors": list(self.sensors), "scope": self.scope, "step": self.step,
                "accepted": self.accepted,
                "statistic": _num(self.statistic), "dof": self.dof, "lrt_p": _num(self.lrt_p),
                "robust_p": _num(self.robust_p), "delta_loglik": _num(self.delta_loglik),
                "delta_bic": _num(self.delta_bic), "heldout_delta_loglik": _num(self.heldout), "note": self.note}


def _num(x: float):
    return None if x is None or not np.isfinite(x) else float(x)


def _reduced(S: np.ndarray):
    """Basis Q (q, r) of the identified directions of S (Jacobi-scaled eigenvalues above EIG_RTOL), or None."""
    d = np.sqrt(np.clip(np.diag(S), 0.0, None))
    if not np.any(d > 0):
        return None
    d = np.where(d > 0, d, np.inf)
    lam, vec = np.linalg.eigh(S / np.outer(d, d))
    keep = lam > EIG_RTOL * max(lam.max(), 0.0)
    if not keep.any():
        return None
    return vec[:, keep] / d[:, None]  # columns: scaled back, so Q^T S Q = diag(lam[keep])


def evaluate_candidates(sb, names, folds: np.ndarray, *, terms=None, exclude=(), step: int = 0) -> list[Candidate]:
    """Every candidate (term x IMU) of ``sb`` (:class:`~imu_array_ros.fitting.engine.ScoreBlocks`) not in
    ``exclude`` ((term, k) pairs); folds (B,) fold of every block."""
    terms = sb.terms if terms is None else terms
    n_obs = max(sb.valid_axes, 2)
    folds = np.asarray(folds)
    fold_ids = np.unique(folds)
    have = sb.counts > 0
    out = []
    for t in terms:
        for k, name in enumerate(names):
            if (t, k) in exclude:
                continue
            gb, Sb = candidate_blocks(sb, t, k)  # bias_drift: tested given the IMU's biases (.drift)
            c = block_tests(gb[have], Sb[have], folds[have], fold_ids)
            if c is None:
                continue
            stat, q, lrt_p, log_p, robust_p, heldout, theta = c
            out.append(Candidate(t, k, name, stat, q, lrt_p, robust_p, 0.5 * stat, q * np.log(n_obs) - stat,
                                 heldout, theta, log_p, step))
    return out


def evaluate_scopes(sb, names, folds: np.ndarray, scopes: list[Scope], *, terms=None, exclude=(),
                    step: int = 0) -> list[Candidate]:
    """Every term of ``sb`` at every pooled scope (:mod:`.scopes`) not in ``exclude`` (Candidate.key
    triples), with the same tests as one IMU's; ``sb`` scored with the scopes' groups and cross terms. Terms
    tested given others (:data:`~.drift.GIVEN`) are tested on one IMU only."""
    terms = [t for t in (sb.terms if terms is None else terms) if t not in GIVEN]
    n_obs = max(sb.valid_axes, 2)
    folds = np.asarray(folds)
    fold_ids = np.unique(folds)
    have = sb.counts > 0
    out = []
    for sc in scopes:
        if sc.kind == "shared" and sb.S_groups is None:
            continue
        for t in terms:
            if (t, sc.label, sc.imus) in exclude or (sc.kind == "own" and t not in sb.S_cross):
                continue
            gb, Sb = scoped_blocks(sb, t, sc)
            c = block_tests(gb[have], Sb[have], folds[have], fold_ids)
            if c is None:
                continue
            stat, q, lrt_p, log_p, robust_p, heldout, theta = c
            sensors = tuple(names[k] for k in sc.imus)
            out.append(Candidate(t, sc.imus[0], f"{sc.label} ({', '.join(sensors)})", stat, q, lrt_p, robust_p,
                                 0.5 * stat, q * np.log(n_obs) - stat, heldout, theta, log_p, step,
                                 scope=sc.label, imus=sc.imus, sensors=sensors))
    return out


def _chi2_logsf(x: float, q: int) -> float:
    """ln P(chi^2_q > x), finite where scipy's underflows: the leading term of the incomplete gamma
    function's asymptotic series, ln Gamma(q/2, x/2) / Gamma(q/2) ~ (q/2 - 1) ln(x/2) - x/2 - ln Gamma(q/2)."""
    v = float(scipy.stats.chi2.logsf(x, q))
    if np.isfinite(v):
        return v
    return float((q / 2 - 1) * np.log(x / 2) - x / 2 - scipy.special.gammaln(q / 2))


def block_tests(gb: np.ndarray, Sb: np.ndarray, folds: np.ndarray, fold_ids: np.ndarray, *, dispersion=False):
    """(statistic, dof, lrt_p, log_p, robust_p, heldout, theta) of a candidate from its per-block score gb (B, P)
    and information Sb (B, P, P) (the module's tests), or None when the recording identifies no direction.

    The block-robust p-value (:func:`_robust_p`) is the CR2 sandwich's Hotelling test with HTZ degrees of
    freedom when those leave the F reference at least HTZ_MIN_DOF denominator dof, else (and always with
    ``dispersion``) the quasi-likelihood one: one scale factor phi for every direction instead of the full
    q x q sandwich, for a candidate whose information sits in too few blocks to estimate q x q (Hotelling's
    F(q, B - q) then has next to no power: 31 dof on 33 blocks passes at p < 0.07 with a score of 112)."""
    S = Sb.sum(axis=0)
    Q = _reduced(S)
    if Q is None:
        return None
    q = Q.shape[1]
    gr, Sr = gb @ Q, Q.T @ Sb @ Q  # per block, reduced coordinates
    g_, S_ = gr.sum(axis=0), Sr.sum(axis=0)
    z = np.linalg.solve(S_, g_)
    stat = float(g_ @ z)
    theta = Q @ z
    lrt_p = float(scipy.stats.chi2.sf(stat, q))
    log_p = _chi2_logsf(stat, q)
    robust_p = _robust_p(gr, Sr, z, dispersion) if len(gb) > 1 else float("nan")  # one block: cannot pass
    heldout = 0.0
    for fid in fold_ids:
        m = folds == fid
        gf, Sf = gr[m].sum(axis=0), Sr[m].sum(axis=0)
        th = np.linalg.lstsq(S_ - Sf, g_ - gf, rcond=None)[0]
        heldout += float(gf @ th - 0.5 * th @ Sf @ th)
    return stat, q, lrt_p, log_p, robust_p, heldout, theta


def _robust_p(gr: np.ndarray, Sr: np.ndarray, z: np.ndarray, dispersion: bool, tested: int = 0) -> float:
    """Block-robust p-value of the score g = sum_b gr_b (B blocks, q reduced dof, information Sr (B, q, q),
    z = S^-1 g); nan when it cannot be formed.  Blocks are the clusters of a cluster-robust test.

    Whitened (L L^T = S, w_b = L^-1 (g_b - S_b z), M_b = L^-1 S_b L^-T, sum_b M_b = I), the score's model
    covariance is I and, under the model, Cov(w_b, w_c) = delta_bc M_b - M_b M_c: a block holding a large share
    of the information (M_b near I on a direction) has a residual near 0 there.
    * CR2 + HTZ (Pustejovsky & Tipton 2018, J. Bus. Econ. Stat. 36:672): w~_b = (I - M_b)^-1/2 w_b, so that
      V = sum_b w~_b w~_b^T has expectation I under the model; T = g_w^T V^+ g_w; V is taken as Wishart with eta
      dof, eta = q (q + 1) / sum_st Var(V_st) (its total variance, exact for Gaussian scores:
      Var(V_st) = sum_bc Phi_bc,ss Phi_bc,tt + Phi_bc,st^2, Phi_bc = Cov(w~_b, w~_c)), and
      F = T (eta - q + 1) / (eta q) ~ F(q, eta - q + 1).  eta is about the count of equally informative
      blocks; equal blocks give back Hotelling's F(q, B - q) but for one dof.
    * dispersion: phi = sum_b |w_b|^2 / (q - sum_b tr M_b^2) (expectation 1), F = T_score / (q phi) ~ F(q, nu),
      nu = 2 E^2 / Var of phi's numerator (Satterthwaite; Var = 2 sum_bc |Cov(w_b, w_c)|_F^2; q (B - 1) when
      the blocks are alike).  It holds when the blocks' scores are coloured alike on the candidate's
      directions, not when only some are.  With ``dispersion`` (asked for by extend.py) nu is the nominal
      q (B - 1) as before: slightly liberal when a few blocks hold the information (2.3 % below 1 % on
      test_block_tests_null's draws, ad hoc), but extend's power was measured with it.
    ``tested`` > 0: only the last ``tested`` whitened coordinates J are tested, the others nuisance (Cholesky
    whitening with them first: g_w,J is the efficient score of J given the rest), every sum above restricted to
    J (V_JJ, Phi_bc,JJ, |w_b,J|^2, (M_b M_c)_JJ) with q -> |J| in the references (:func:`increment_test`).
    The choice depends on the design (Sr) only, never on the scores, so each branch's level is the test's."""
    b, q = gr.shape
    r = tested or q
    J = slice(q - r, q)
    Li = np.linalg.inv(np.linalg.cholesky(Sr.sum(axis=0)))
    M = Li @ Sr @ Li.T
    M = 0.5 * (M + np.swapaxes(M, 1, 2))
    w = (gr - Sr @ z) @ Li.T
    gw = (Li @ gr.sum(axis=0))[J]
    if not dispersion:
        lam, vec = np.linalg.eigh(M)
        if lam.min() < -PSD_TOL or lam.max() > 1.0 + PSD_TOL:  # some S_b is no covariance: Hotelling's, as before
            t = float(gw @ np.linalg.lstsq((w.T @ w)[J, J], gw, rcond=None)[0])
            return float(scipy.stats.f.sf(t * (b - r) / (r * (b - 1)), r, b - r)) if b > r + 1 else float("nan")
        lam = np.clip(lam, 0.0, 1.0)
        a = np.where(1.0 - lam > 1e-9, 1.0 / np.sqrt(np.maximum(1.0 - lam, 1e-300)), 0.0)  # pseudo-inverse root
        d, p = lam * a * a, lam * a  # eigenvalues of D_b = M_b (I - M_b)^-1 and P_b = M_b (I - M_b)^-1/2
        P = np.einsum("bij,bj,bkj->bik", vec, p, vec)
        D = np.einsum("bij,bj,bkj->bik", vec, d, vec)[:, J, J]
        PJ = P[:, J, :]
        R = np.einsum("bji,bjk->ik", PJ, PJ)  # sum_b P_b,.J P_b,J.
        G = PJ.reshape(b, -1) @ PJ.reshape(b, -1).T  # tr(P_b,J. P_c,.J); Phi_bc = delta_bc D_b - P_b P_c
        trd, trp = np.trace(D, axis1=1, axis2=2), np.diag(G)
        var = float(np.sum(trd ** 2) - 2 * np.sum(trd * trp) + np.sum(G * G) + np.sum(D * D)
                    - 2 * np.einsum("bij,bik,bkj->", D, PJ, np.swapaxes(PJ, 1, 2)) + np.sum(R * R))
        eta = r * (r + 1) / var if var > 0 else 0.0
        if eta - r + 1 >= HTZ_MIN_DOF:
            wt = np.einsum("bij,bj->bi", vec, a * np.einsum("bji,bj->bi", vec, w))[:, J]
            t = float(gw @ np.linalg.lstsq(wt.T @ wt, gw, rcond=None)[0])
            return float(scipy.stats.f.sf(t * (eta - r + 1) / (eta * r), r, eta - r + 1))
    MJ, MJJ = M[:, J, :], M[:, J, J]
    M2 = MJ @ np.swapaxes(MJ, 1, 2)  # (M_b^2)_JJ
    den = r - float(np.trace(M2, axis1=1, axis2=2).sum())
    R = np.einsum("bji,bjk->ik", MJ, MJ)  # sum_b M_b,.J M_b,J.
    var = 2 * (float(np.sum(MJJ * MJJ)) - 2 * float(np.einsum("bij,bji->", M2, MJJ)) + float(np.sum(R * R)))
    if den <= 0 or var <= 0:
        return float("nan")
    phi = float(np.sum(w[:, J] ** 2)) / den
    nu = 2 * den * den / var if not dispersion else r * (b - 1)  # asked for: the nominal dof, as extend.py measured
    return float(scipy.stats.f.sf(float(gw @ gw) / (r * phi), r, nu)) if phi > 0 else float("nan")


def increment_test(gb: np.ndarray, Sb: np.ndarray, nuisance: int):
    """(statistic, dof, robust_p) of what the last coordinates of block scores gb (B, n) and informations
    Sb (B, n, n) add to the first ``nuisance`` ones, or None when the recording identifies no direction of
    theirs beyond those.  The identified directions of the whole (as every candidate's, :func:`_reduced`) are
    made orthonormal in the information metric, the nuisance's identified directions first (their span in
    those), so the whole information is I and block-diagonal; the rest is the increment (the efficient score
    g_eta - S_eta,theta S_theta,theta^-1 g_theta in whitened coordinates).  statistic: its score statistic
    (T_joint - T_nuisance, chi-square on dof under no increment); robust_p: :func:`_robust_p` of the joint fit
    with only the increment tested (CR2 + HTZ, else the dispersion form with Satterthwaite dof; Hotelling's where
    some S_b is no covariance; nan when not formed): the residuals are the joint fit's, whose covariance the
    small-sample corrections are exact for, so the nuisance's estimation is accounted for."""
    S = Sb.sum(axis=0)
    Q = _reduced(S)
    if Q is None:
        return None
    W = Q / np.sqrt(np.einsum("ij,ik,kj->j", Q, S, Q))  # W^T S W = I
    Qs = _reduced(S[:nuisance, :nuisance]) if nuisance else None
    q_s = 0
    if Qs is not None:  # the nuisance's identified directions, unit-scaled, in W's coordinates
        Qs = Qs / np.sqrt(np.einsum("ij,ik,kj->j", Qs, S[:nuisance, :nuisance], Qs))
        u, sv, _ = np.linalg.svd(W.T @ S[:, :nuisance] @ Qs)
        q_s = int(np.sum(sv > 1e-6))
        W = W @ u
    r = W.shape[1] - q_s
    if r <= 0:
        return None
    gr, Sr = gb @ W, W.T @ Sb @ W
    Sr = 0.5 * (Sr + np.swapaxes(Sr, 1, 2))
    g_, S_ = gr.sum(axis=0), Sr.sum(axis=0)
    stat = float(g_[q_s:] @ np.linalg.solve(S_[q_s:, q_s:], g_[q_s:]))
    try:
        p = _robust_p(gr, Sr, np.linalg.solve(S_, g_), False, tested=r) if len(gb) > 1 else float("nan")
    except np.linalg.LinAlgError:  # not formed: an increment no robust test establishes
        p = float("nan")
    return stat, r, p


def confounded(sb, best: Candidate, others: list[Candidate], level: float) -> list[dict]:
    """Candidates on best's IMU that explain the recording as well as ``best`` and add nothing given it.

    For each passing alternative a on the same IMU: its BIC is within BIC_GAP of best's, and the joint
    score test of a given best (T_joint - T_best, chi-square with a's dof) is not significant at ``level``.
    Returns dicts {effect, statistic gap, correlation (largest canonical correlation of the two projected
    signatures under S), delta_bic_gap}.
    """
    out = []
    for a in others:
        if a.scope != "imu" or best.scope != "imu" or a.k != best.k or a.effect == best.effect \
                or not a.passes(level):
            continue
        gap = a.delta_bic - best.delta_bic
        if gap >= BIC_GAP:
            continue
        cb, ca = sb.columns(best.effect), sb.columns(a.effect)
        idx = np.r_[np.arange(cb.start, cb.stop), np.arange(ca.start, ca.stop)]
        S = sb.S[:, best.k][:, idx][:, :, idx].sum(axis=0)
        g = sb.g[:, best.k, idx].sum(axis=0)
        Q = _reduced(S)
        joint = float(g @ Q @ np.linalg.solve(Q.T @ S @ Q, Q.T @ g)) if Q is not None else best.statistic
        added = joint - best.statistic
        q_add = max(1, (Q.shape[1] if Q is not None else best.dof) - best.dof)
        if scipy.stats.chi2.sf(added, q_add) < level:
            continue  # a explains something best does not: a separate effect, tested in a later step
        out.append({"effect": a.effect, "delta_bic_gap": float(gap), "added_statistic": float(added),
                    "correlation": _canonical_correlation(S, cb.stop - cb.start)})
    return out


def scope_design(c: Candidate, imus: list, p: int) -> np.ndarray:
    """(len(imus) p, d): a candidate's d parameters -> the values of its term (p each) on ``imus`` (which hold
    its IMUs): each IMU of it its own value (scope "imu" or an own scope), or one value shared by them."""
    own = [[k] for k in c.imus] if c.scope == "imu" or c.scope.endswith(" own") else [list(c.imus)]
    a = np.zeros((len(imus), len(own), p, p))
    for j, ks in enumerate(own):
        a[[imus.index(k) for k in ks], j] = np.eye(p)
    return a.transpose(0, 2, 1, 3).reshape(len(imus) * p, len(own) * p)


def added_given(sb, best: Candidate, other: Candidate, tied=()) -> dict | None:
    """What ``other`` adds to ``best`` in the score test: {added_statistic, added_dof, correlation (largest
    canonical correlation of the two projected signatures)}, from the joint score and information of both in
    ``sb`` (the ScoreBlocks both were tested on); None when ``sb`` holds no information across the two.

    Held: the same IMU (its terms' blocks); the same term at any IMU, shared or own scopes when ``sb`` has that
    term's cross-IMU blocks (S_cross); two terms shared by the same group (S_groups, ``tied``: the groups' IMU
    indexes as scored); two extensions of one finding (:mod:`.extend`) one of which holds the other (its IMUs
    beyond the finding's include the other's, at least as many dof: the difference of their statistics).  Not:
    other extensions, terms tested given others (drift.GIVEN)."""
    if best.extends and best.extends == other.extends:
        nb, no = best.added, other.added  # the same finding grown: beyond its IMUs
        if nb <= no and other.dof >= best.dof or no <= nb and other.dof <= best.dof:
            return {"added_statistic": max(other.statistic - best.statistic, 0.0),
                    "added_dof": max(other.dof - best.dof, 0), "correlation": float("nan")}
    if best.extends or other.extends or best.effect in GIVEN or other.effect in GIVEN:
        return None
    cb, co = sb.columns(best.effect), sb.columns(other.effect)
    if best.scope == other.scope == "imu" and best.k == other.k:
        idx = np.r_[np.arange(cb.start, cb.stop), np.arange(co.start, co.stop)]
        g, S = sb.g[:, best.k, idx].sum(axis=0), sb.S[:, best.k][:, idx][:, :, idx].sum(axis=0)
    elif best.effect == other.effect and sb.S_cross.get(best.effect) is not None:
        kk, p = sb.g.shape[1], cb.stop - cb.start
        design = [scope_design(c, list(range(kk)), p) for c in (best, other)]  # -> every IMU's values (K p)
        a = np.hstack(design)
        full = sb.S_cross[best.effect].sum(axis=0).transpose(0, 2, 1, 3).reshape(kk * p, kk * p)
        g, S = a.T @ sb.g[:, :, cb].sum(axis=0).reshape(-1), a.T @ full @ a
        cb = slice(0, design[0].shape[1])
    elif (best.scope.endswith(" shared") and other.scope.endswith(" shared") and best.imus == other.imus
          and sb.S_groups is not None and tuple(best.imus) in [tuple(t) for t in tied]):
        j = [tuple(t) for t in tied].index(tuple(best.imus))
        idx = np.r_[np.arange(cb.start, cb.stop), np.arange(co.start, co.stop)]
        g, S = sb.g[:, list(best.imus)][:, :, idx].sum(axis=(0, 1)), sb.S_groups[:, j][:, idx][:, :, idx].sum(axis=0)
    else:
        return None
    Q = _reduced(S)
    joint = float(g @ Q @ np.linalg.solve(Q.T @ S @ Q, Q.T @ g)) if Q is not None else best.statistic
    return {"added_statistic": joint - best.statistic,
            "added_dof": (Q.shape[1] if Q is not None else best.dof) - best.dof,
            "correlation": _canonical_correlation(S, cb.stop - cb.start)}


def _canonical_correlation(S: np.ndarray, nb: int) -> float:
    """Largest canonical correlation between the first nb and the remaining coordinates under the metric S."""
    def inv_sqrt(a):
        lam, vec = np.linalg.eigh(a)
        keep = lam > EIG_RTOL * max(lam.max(), 1e-300)
        return vec[:, keep] / np.sqrt(lam[keep])
    a, b = inv_sqrt(S[:nb, :nb]), inv_sqrt(S[nb:, nb:])
    if a.size == 0 or b.size == 0:
        return float("nan")
    return float(np.clip(np.linalg.svd(a.T @ S[:nb, nb:] @ b, compute_uv=False).max(), 0.0, 1.0))
