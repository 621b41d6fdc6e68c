"""Which IMUs of a pooled finding carry the effect: narrowing a scope to the IMUs the data put it on.

A pooled hypothesis (a shared value on a group, or every IMU its own value: :mod:`.scopes`) passes when the
pooled evidence of its IMUs does, so an effect on two IMUs of eight passes at the eight-IMU scope: a finding
on six IMUs without the effect.  After a pooled finding's exact refit (each IMU of the scope its own value,
:func:`.confirm.confirm`), this module asks which IMUs carry it:

1. **The fewest IMUs that explain it**: from the pooled fit's own values (their changes from the model
   discovery started from) and their Cramér-Rao bound, the Wald statistic of "the term only on the IMUs C,
   nothing on the others" (asymptotically twice the log-likelihood that restriction loses).  C is the smallest
   set for which (a) that test accepts at alpha and (b) every IMU of C is needed given the others of C (the
   Wald test of its own value given them, p < alpha / G: Bonferroni over the scope's G IMUs); the lowest
   statistic among sets of that size.  Every set is tried on scopes of up to :data:`EXHAUSTIVE` IMUs, larger
   ones are grown greedily then pruned.  The pooled fit's values are coupled by the motion (a value common to
   the IMUs is nearly absorbed by it), so an IMU's value given *every* other IMU free says little about it:
   hence the joint restriction, not one test per IMU.  When the effect is on C, an IMU outside C is kept only
   when the true set is rejected by (a), so at most about alpha per pooled finding.  When a gauge freedom of
   the fit moves the term's values on the scope (a value common to identically oriented IMUs, absorbed by the
   motion and held by the fit), "nothing on IMU k" depends on the gauge: the values are re-expressed in every
   gauge that puts one IMU of the scope at its starting value and the sparsest representation is taken;
   other sets as small and as adequate are named (the data hardly tell them apart).  A gauge of more
   dimensions than one IMU's parameters (an accelerometer bias on a planar array: a common bias and
   omega_dot x r_k) can hide sets no single-IMU re-expression reaches ("b on 0, 2" is "-b on 1, 3"): on scopes
   of at most :data:`GAUGE_SEARCH_MAX` IMUs every subset is also tested with one value shared up to the gauge
   (:func:`shared_sets`), kept when it has no more IMUs than the own-value set (on larger scopes: when the
   own-value set has more than one IMU, i.e. more values), and the sets whose shared
   value fits as well are named as equivalents.  On larger scopes (gauge or near-gauge alike: a value common
   to the IMUs only weakly observed) the candidates are both sides of every split of the IMUs sorted along
   the leading direction of their whitened, gauge-free values (:mod:`.subset_split`), tested by the same
   statistic (:func:`shared_statistics`); of the adequate ones only those within 2 ln(1/alpha) of the lowest
   statistic count.
2. **Is the subset adequate?** The restriction is tested again by the exact likelihood ratio of the refit
   with only C free against the pooled fit, chi-square with the difference in free parameters, at alpha.
   When one value shared by the whole scope is adequate (its tie test accepts at alpha), it explains the data
   with as few parameters: the scope is narrowed only when one value on C is more likely by a factor 1/alpha
   (2 delta log-likelihood >= 2 ln(1/alpha), 9.2 at 1 %).  So an effect truly on every IMU, some of whose own
   values are too uncertain to be needed, stays on every IMU.
3. **Re-confirmed on C**: one shared value on C when the tie test over C accepts one (p >= alpha), else every
   IMU of C its own value; its gain must pass the step's level as the pooled one did.  The scope is then
   named after C: a geometry group's name when C is one ("top shared"), else the IMUs' names
   ("imu_02,imu_03 shared" / "... own"; one IMU: "imu_3 own", the figures of the pooled test kept).

Nothing is narrowed when no proper subset passes (a) and (b) (every IMU is needed, or the pooled evidence is
all there is), or when an IMU of the scope already holds an earlier finding of the same term.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import numpy as np
import scipy.stats

from imu_array_ros.discovery.subset_split import split_sets
from imu_array_ros.model.terms import REGISTRY

__all__ = ["term_indexes", "wald", "restricted", "Representation", "Proposal", "propose", "scope_label",
           "is_own", "carriers", "gauge_basis", "shared_sets", "shared_statistics",
           "EIG_RTOL", "EXHAUSTIVE", "GAUGE_SEARCH_MAX"]

#: scopes of at most this many IMUs: every subset is tried (smallest first); larger ones are grown greedily
EXHAUSTIVE = 10
#: scopes of at most this many IMUs whose term a gauge freedom moves: every subset (2^G) is also tried with one
#: value shared by it, up to the gauge (:func:`shared_sets`)
GAUGE_SEARCH_MAX = 8
#: eigenvalue of a Jacobi-scaled covariance, relative to its largest, below which a direction is not identified
EIG_RTOL = 1e-10


def is_own(scope: str) -> bool:
    """Whether a pooled scope's label is an every-IMU-its-own-value scope ("all own", "top own", ...)."""
    return scope.endswith(" own")


def term_indexes(fit, term: str, imus) -> np.ndarray:
    """Indexes into fit.theta / fit.covariance of ``term``'s parameters on ``imus`` (IMU-major)."""
    dims = [REGISTRY[t].dim() for t in fit.free]
    p, off, width = REGISTRY[term].dim(), sum(dims[:list(fit.free).index(term)]), sum(dims)
    names = list(fit.imus)
    return np.array([names.index(fit.model.names[k]) * width + off + i for k in imus for i in range(p)],
                    dtype=np.int64)


def _information(cov: np.ndarray):
    """(W, keep, rank): pseudo-inverse of ``cov`` on its identified directions (Jacobi-scaled eigenvalues
    above EIG_RTOL; held parameters, zero variance, left out), as a matrix over the kept entries."""
    keep = np.diag(cov) > 0
    if not keep.any():
        return np.zeros((0, 0)), keep, 0
    c = cov[np.ix_(keep, keep)]
    s = np.sqrt(np.diag(c))
    lam, vec = np.linalg.eigh(c / np.outer(s, s))
    ok = lam > EIG_RTOL * lam.max()
    q = vec[:, ok] / s[:, None]
    return q @ np.diag(1.0 / lam[ok]) @ q.T, keep, int(ok.sum())


def restricted(d: np.ndarray, cov: np.ndarray, t: np.ndarray, *, solution: bool = False):
    """Wald statistic of the linear restriction d = T phi (phi free) with the covariance of d, and its dof:
    min_phi (d - T phi)^T C^+ (d - T phi) on the identified directions of C; asymptotically twice the
    log-likelihood the restriction loses.  T (n, r); r = 0: d = 0.  solution: also the minimising phi (r,)
    (the GLS value; minimum-norm where T's columns are not identified), as a third element."""
    w, keep, rank = _information(cov)
    phi = np.zeros(t.shape[1])
    if rank == 0:
        return (0.0, 0, phi) if solution else (0.0, 0)
    x, tk = d[keep], t[keep]
    stat = float(x @ w @ x)
    if tk.shape[1]:
        info = tk.T @ w @ tk
        b = tk.T @ w @ x
        phi = np.linalg.pinv(info, hermitian=True) @ b
        stat -= float(b @ phi)
        rank -= int(np.linalg.matrix_rank(info)) if np.any(info) else 0
    out = max(stat, 0.0), max(rank, 0)
    return (*out, phi) if solution else out


def wald(d: np.ndarray, cov: np.ndarray) -> tuple[float, int, float]:
    """(W, dof, p) of d = 0 with the covariance of d (held parameters carry no information)."""
    stat, dof = restricted(d, cov, np.zeros((len(d), 0)))
    return stat, dof, float(scipy.stats.chi2.sf(stat, dof)) if dof > 0 else 1.0


@dataclass
class Representation:
    """The changes d (G p,) of a term on a scope's IMUs and their covariance, in one gauge: ``zero`` the
    scope's IMU put at its starting value by the gauge (None: the fit's own gauge)."""

    d: np.ndarray
    cov: np.ndarray
    zero: int | None = None


@dataclass
class Proposal:
    """The IMUs (indexes) that carry a pooled finding's effect: p per IMU of its Wald test, the Wald statistic
    of "nothing on the others" (zero_stat, zero_dof) and of "one value on C, nothing on the others"
    (shared_stat) in the representation chosen; alternatives: other carrier sets as sparse and as adequate.
    in_gauge: C is the fewest IMUs one shared value on which explains the fit up to the gauge
    (:func:`shared_sets`; p then holds, per IMU, the p of C without it); equivalents: [(IMU indexes,
    statistic)] of the other sets whose shared value fits as well (within 2 ln(1/alpha)), the complement first."""

    imus: tuple[int, ...]
    p: dict = field(default_factory=dict)
    zero_stat: float = 0.0
    zero_dof: int = 0
    shared_stat: float = 0.0
    level: float = 0.0
    zero: int | None = None
    alternatives: list = field(default_factory=list)
    in_gauge: bool = False
    equivalents: list = field(default_factory=list)
    gauge: bool = True  # with in_gauge: a gauge freedom of the fit moves the term's values (large scopes: maybe not)


def representations(fit, term: str, imus, base: np.ndarray) -> list[Representation]:
    """The term's changes from ``base`` (G, p) on ``imus`` in the fit's gauge and, when a gauge freedom of
    the fit moves them, in the gauge that puts each IMU of the scope at zero (to first order the same
    readings: theta + D c for the fit's gauge directions D)."""
    idx = term_indexes(fit, term, imus)
    d = fit.theta[idx] - np.asarray(base, dtype=float).reshape(-1)
    cov = fit.covariance[np.ix_(idx, idx)]
    out = [Representation(d, cov)]
    gd = np.asarray(fit.gauge_directions)
    if gd.size == 0:
        return out
    ds = gd[idx]
    if np.linalg.norm(ds) < 1e-9 * max(np.linalg.norm(gd), 1e-300):
        return out
    p = REGISTRY[term].dim()
    for j in range(len(imus)):
        rows = slice(j * p, (j + 1) * p)
        dj = ds[rows]
        if np.linalg.matrix_rank(dj, tol=1e-9 * max(np.abs(ds).max(), 1e-300)) < p:
            continue  # the gauge cannot put every parameter of this IMU at zero
        a = np.eye(len(d))
        a[:, rows] -= ds @ np.linalg.pinv(dj)
        d2, cov2 = a @ d, a @ cov @ a.T
        d2[rows] = 0.0
        cov2[rows, :] = 0.0
        cov2[:, rows] = 0.0
        out.append(Representation(d2, cov2, j))
    return out


def gauge_basis(fit, idx) -> np.ndarray:
    """(n, r) orthonormal basis of how the fit's gauge freedoms move the parameters ``idx`` (r = 0: none does)."""
    gd = np.asarray(fit.gauge_directions)
    if gd.size == 0:
        return np.zeros((len(idx), 0))
    ds = gd[idx]
    if np.linalg.norm(ds) < 1e-9 * max(np.linalg.norm(gd), 1e-300):
        return np.zeros((len(idx), 0))
    u, s, _ = np.linalg.svd(ds, full_matrices=False)
    return u[:, s > 1e-9 * s.max()]


def shared_sets(d: np.ndarray, cov: np.ndarray, basis: np.ndarray, n_imus: int, p: int):
    """Every non-empty proper subset C of a scope's G IMUs with the Wald statistic of "one value shared by C (in
    each sensor's own frame), nothing on the others, up to the gauge" (:func:`shared_statistics`), vectorised
    over the 2^G - 2 sets.  Returns (sets (S, G) bool, statistic (S,), dof (S,))."""
    sets = ((np.arange(1, 2 ** n_imus - 1)[:, None] >> np.arange(n_imus)) & 1).astype(bool)
    return (sets,) + shared_statistics(d, cov, basis, p, sets)


def shared_statistics(d: np.ndarray, cov: np.ndarray, basis: np.ndarray, p: int, sets: np.ndarray):
    """The Wald statistic of "one value shared by C (in each sensor's own frame), nothing on the others, up to
    the gauge" for each row C of ``sets`` (S, G) bool: d = T_C phi + B c with phi and c free (B ``basis``,
    :func:`gauge_basis`), i.e. the changes' components across the gauge y = Q^T d (Q^T B = 0, so the statistic
    does not depend on the gauge the fit held) against Q^T T_C phi.  Returns (statistic (S,), dof (S,))."""
    g, r = sets.shape[1], basis.shape[1]
    q = np.linalg.svd(basis, full_matrices=True)[0][:, r:] if r else np.eye(len(d))
    w, keep, rank = _information(q.T @ cov @ q)
    if rank == 0:
        return np.zeros(len(sets)), np.zeros(len(sets), dtype=np.int64)
    x = (q.T @ d)[keep]
    a = np.einsum("sg,gpm->smp", sets.astype(float), q.reshape(g, p, -1))[:, keep, :]  # Q^T T_C
    b = np.einsum("smp,mn,n->sp", a, w, x)
    info = np.einsum("smp,mn,snq->spq", a, w, a)
    sc = np.sqrt(np.clip(np.einsum("spp->sp", info), 1e-300, None))  # Jacobi-scaled: parameters of any unit
    lam, vec = np.linalg.eigh(info / (sc[:, :, None] * sc[:, None, :]))
    ok = lam > EIG_RTOL * np.clip(lam.max(axis=1, keepdims=True), 0.0, None)
    z = np.einsum("spk,sp->sk", vec, b / sc)
    stat = float(x @ w @ x) - np.sum(np.where(ok, z ** 2 / np.where(ok, lam, 1.0), 0.0), axis=1)
    return np.clip(stat, 0.0, None), rank - ok.sum(axis=1)


def _shared_in_gauge(fit, term: str, imus, base, alpha: float):
    """The fewest IMUs of the scope one shared value on which explains the pooled fit up to the gauge
    (:func:`shared_sets`, accepted at ``alpha``), lowest statistic first, and the other sets (any size) whose
    shared value fits as well: statistic within 2 ln(1/alpha) of it (a likelihood ratio below 1/alpha), the
    complement's first.  On scopes of at most :data:`GAUGE_SEARCH_MAX` IMUs every subset is tried (None when no
    gauge freedom moves the term there); on larger ones, gauge or not, only both sides of every split along the
    values' leading direction (:func:`.subset_split.split_sets`), and of the adequate sets only those whose
    statistic is within 2 ln(1/alpha) of the lowest adequate one count (with (G - 1) p dof adequacy alone keeps
    sets far less likely than the best).  None when no proper subset is adequate.  Returns (C positions,
    statistic, dof, {position: p of C without it}, [(positions, statistic)], whether a gauge freedom moves the
    term)."""
    g, p = len(imus), REGISTRY[term].dim()
    idx = term_indexes(fit, term, imus)
    basis = gauge_basis(fit, idx)
    if g <= GAUGE_SEARCH_MAX and basis.shape[1] == 0:
        return None
    d = fit.theta[idx] - np.asarray(base, dtype=float).reshape(-1)
    cov = fit.covariance[np.ix_(idx, idx)]
    if g <= GAUGE_SEARCH_MAX:
        sets, stat, dof = shared_sets(d, cov, basis, g, p)
    else:  # too many subsets: both sides of every split along the values' leading direction (.subset_split)
        sets = split_sets(d, cov, basis, g, p, rtol=EIG_RTOL)
        stat, dof = shared_statistics(d, cov, basis, p, sets)
    pv = np.where(dof > 0, scipy.stats.chi2.sf(stat, np.maximum(dof, 1)), 1.0)
    size = sets.sum(axis=1)
    ok = np.flatnonzero(pv >= alpha)
    if ok.size == 0:
        return None
    if g > GAUGE_SEARCH_MAX:  # many dof: adequacy alone keeps sets far less likely than the best adequate one
        ok = ok[stat[ok] - stat[ok].min() < 2.0 * np.log(1.0 / alpha)]
    n = size[ok].min()
    best = ok[size[ok] == n][np.argmin(stat[ok][size[ok] == n])]
    c = tuple(int(j) for j in np.flatnonzero(sets[best]))
    code = {tuple(int(j) for j in np.flatnonzero(m)): i for i, m in enumerate(sets)}
    if len(c) > 1 and g > GAUGE_SEARCH_MAX:  # the set without each of its IMUs: not among the candidates
        less = np.repeat(sets[best][None, :], len(c), axis=0)
        less[np.arange(len(c)), list(c)] = False
        s1, d1 = shared_statistics(d, cov, basis, p, less)
        p1 = np.where(d1 > 0, scipy.stats.chi2.sf(s1, np.maximum(d1, 1)), 1.0)
        drop = {j: float(p1[i]) for i, j in enumerate(c)}
    else:
        drop = {j: float(pv[code[tuple(i for i in c if i != j)]]) if len(c) > 1 else 0.0 for j in c}
    close = [i for i in ok if i != best and stat[i] - stat[best] < 2.0 * np.log(1.0 / alpha)]
    comp = code.get(tuple(j for j in range(g) if j not in c))
    close.sort(key=lambda i: (i != comp, stat[i]))
    return c, float(stat[best]), int(dof[best]), drop, [(tuple(int(j) for j in np.flatnonzero(sets[i])),
                                                         float(stat[i])) for i in close], basis.shape[1] > 0


class _Restrictions:
    """Wald statistics of "the term only on the IMUs C (own values), nothing elsewhere" for many C, from one
    representation: the information is inverted once."""

    def __init__(self, rep: Representation, n_imus: int, p: int):
        self.w, keep, self.rank = _information(rep.cov)
        self.x = rep.d[keep]
        self.b = self.w @ self.x
        self.total = float(self.x @ self.b)
        pos = np.cumsum(keep) - 1  # index among the kept entries
        self.rows = [pos[j * p:(j + 1) * p][keep[j * p:(j + 1) * p]] for j in range(n_imus)]

    def __call__(self, inside) -> tuple[float, int]:
        r = np.concatenate([self.rows[j] for j in inside]) if len(inside) else np.zeros(0, dtype=np.int64)
        if r.size == 0:
            return self.total, self.rank
        info = self.w[np.ix_(r, r)]
        sc = np.sqrt(np.clip(np.diag(info), 1e-300, None))  # Jacobi-scaled: parameters of any unit
        lam, vec = np.linalg.eigh(info / np.outer(sc, sc))
        ok = lam > EIG_RTOL * max(lam.max(), 0.0)
        z = vec[:, ok].T @ (self.b[r] / sc)
        stat = self.total - float(z @ (z / lam[ok]))
        return max(stat, 0.0), self.rank - int(ok.sum())


def _adequate(stat: float, dof: int, alpha: float) -> bool:
    return dof <= 0 or scipy.stats.chi2.sf(stat, dof) >= alpha


def carriers(rep: Representation, n_imus: int, p: int, alpha: float):
    """The fewest IMUs whose own values explain the pooled fit: the smallest sets C for which the Wald test of
    "nothing on the other IMUs of the scope" accepts at ``alpha`` and every IMU of C is needed given the others
    of C (its own value's Wald test given them, p < alpha / G: Bonferroni over the scope's G IMUs), lowest
    statistic first; every set up to :data:`EXHAUSTIVE` IMUs, else grown greedily (the IMU that lowers the
    statistic most) then pruned.  Returns [(C positions, statistic, dof, {position: p given the others})] of
    the smallest such size (empty: no proper subset)."""
    wald_of = _Restrictions(rep, n_imus, p)
    level = alpha / n_imus

    def needed(c, stat, dof):
        ps = {}
        for j in c:
            s1, d1 = wald_of([i for i in c if i != j])
            ps[j] = float(scipy.stats.chi2.sf(s1 - stat, d1 - dof)) if d1 > dof else 1.0
        return ps if all(v < level for v in ps.values()) else None

    if n_imus <= EXHAUSTIVE:
        for size in range(1, n_imus):
            ok = []
            for c in combinations(range(n_imus), size):
                stat, dof = wald_of(c)
                if _adequate(stat, dof, alpha):
                    ps = needed(c, stat, dof)
                    if ps is not None:
                        ok.append((c, stat, dof, ps))
            if ok:
                return sorted(ok, key=lambda x: x[1])
        return []
    inside: list[int] = []
    stat, dof = wald_of(inside)
    while not _adequate(stat, dof, alpha) and len(inside) < n_imus - 1:
        stat, dof, j = min(wald_of(inside + [j]) + (j,) for j in range(n_imus) if j not in inside)
        inside.append(j)
    if not _adequate(stat, dof, alpha):
        return []
    pruned = True
    while pruned and len(inside) > 1:  # drop what the others no longer need
        pruned = False
        tries = sorted((wald_of([i for i in inside if i != j]) + (j,) for j in inside), key=lambda x: x[0])
        if tries and _adequate(tries[0][0], tries[0][1], alpha):
            stat, dof, j = tries[0]
            inside.remove(j)
            pruned = True
    c = tuple(sorted(inside))
    ps = needed(c, stat, dof)
    return [] if ps is None else [(c, stat, dof, ps)]


def _selector(n_imus: int, p: int, inside, shared: bool) -> np.ndarray:
    """T of the restriction: the IMUs ``inside`` free (their own values, or one shared value), the others 0."""
    cols = p if shared else p * len(inside)
    t = np.zeros((n_imus * p, cols))
    for i, j in enumerate(inside):
        t[j * p:(j + 1) * p, (0 if shared else i * p):(0 if shared else i * p) + p] = np.eye(p)
    return t


def propose(fit, term: str, imus, base: np.ndarray, alpha: float) -> Proposal | None:
    """The IMUs that carry ``term``'s pooled finding on ``imus`` in the joint ``fit`` (module docstring, step 1):
    the smallest proper subset whose restriction the Wald test accepts at ``alpha`` (over the fit's gauge
    representations), or one as small or smaller with one value shared up to the gauge (:func:`shared_sets` on
    scopes of at most :data:`GAUGE_SEARCH_MAX` IMUs, :func:`.subset_split.split_sets` on larger ones, where it
    is also kept against own-value sets of two or more IMUs: fewer values), or None.  Positions in the
    Proposal are IMU indexes."""
    imus = list(imus)
    g, p = len(imus), REGISTRY[term].dim()
    found = []
    for rep in representations(fit, term, imus, base):
        zero = _gauge_zero(rep, g, p)
        for c, zs, zd, ps in carriers(rep, g, p, alpha):
            if zero is not None and len(c) == g - 1 and zero not in c:
                continue  # leaves out only the IMU the gauge puts at zero: on every IMU, up to the gauge
            found.append((len(c), zs, c, zd, rep, ps))
    gs = _shared_in_gauge(fit, term, imus, base, alpha)
    few = min((x[0] for x in found), default=0)
    # as few IMUs, fewer values; on a large scope (own-value sets searched greedily, in gauges that absorb one
    # IMU's value) any own-value set of two or more IMUs has more values than one shared value
    if gs is not None and (not found or len(gs[0]) <= few or (g > GAUGE_SEARCH_MAX and few > 1)):
        c, zs, zd, drop, close, gauge = gs
        return Proposal(tuple(imus[j] for j in c), {imus[j]: v for j, v in drop.items()}, zs, zd, zs, alpha,
                        in_gauge=True, equivalents=[(tuple(imus[j] for j in e), st) for e, st in close],
                        gauge=bool(gauge))
    if not found:
        return None
    found.sort(key=lambda x: (x[0], x[1]))
    n, zs, c, zd, rep, ps = found[0]
    ss, _ = restricted(rep.d, rep.cov, _selector(g, p, c, shared=True))
    alts = []
    for x in found[1:]:
        a = tuple(imus[j] for j in x[2])
        if x[0] == n and x[2] != c and a not in alts:
            alts.append(a)
    return Proposal(tuple(imus[j] for j in c), {imus[j]: v for j, v in ps.items()}, float(zs), int(zd),
                    float(ss), alpha / g, None if rep.zero is None else imus[rep.zero], [list(a) for a in alts])


def _gauge_zero(rep: Representation, g: int, p: int) -> int | None:
    """The scope position the representation's gauge holds at zero: ``rep.zero``, or in the fit's own gauge
    the one IMU whose parameters of the term are all held (no variance); None when there is none."""
    if rep.zero is not None:
        return rep.zero
    var = np.diag(rep.cov).reshape(g, p)
    held = [j for j in range(g) if not np.any(var[j] > 0)]
    return held[0] if len(held) == 1 else None


def scope_label(imus, names, groups, shared: bool) -> str:
    """A pooled scope's label for the IMU indexes ``imus``: the geometry group's name when they are one
    ([(name, IMU indexes)], :func:`.scopes.geometry_groups`), "all" when every IMU, else their names."""
    imus = tuple(sorted(imus))
    kind = "shared" if shared else "own"
    if imus == tuple(range(len(names))):
        return f"all {kind}"
    for name, group in groups:
        if tuple(sorted(group)) == imus:
            return f"{name} {kind}"
    return f"{','.join(names[k] for k in imus)} {kind}"
