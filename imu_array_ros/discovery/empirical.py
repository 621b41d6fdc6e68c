"""Empirical models of residual structure no physical term explains (sparse regression).

For one cell (IMU k, axis a) the normalised residual r_n (unit noise when the
model is right) is regressed on a library of motion features x_n (F,),

    r_n ~ x_n^T beta,

in the spirit of SINDy: sequentially thresholded least squares (STLSQ).  The
features are scaled on the training samples to unit root-mean-square (not
centred, so the constant "1" stays a plain bias term and a selected scaled
feature is exactly one selected SI feature); a ridge-regularised least-squares
fit ``(Z^T Z + lambda n I) beta = Z^T r`` (lambda = ``ridge``) is followed by
repeatedly dropping the features with ``|beta_j| < threshold`` (a scaled
coefficient is the RMS of the feature's contribution, in units of the noise
std), keeping at most ``max_terms`` largest, and refitting on the survivors
until the support is stable.

Score: with unit noise the Gaussian log-likelihood gain of a prediction is
``Delta l = 0.5 * sum (r^2 - (r - x^T beta)^2) = beta^T X^T r - 0.5 beta^T X^T X beta``,
so everything runs on per-fold Gram matrices (X_f^T X_f, X_f^T r_f), never per
sample.  ``heldout_delta_loglik`` sums Delta l over the held-out samples of
each fold with beta fitted (selection included) on the other folds.  With
``threshold=None`` it is chosen from the grid ``geomspace(2/sqrt(n), 1, 9)``
plus "no feature" by maximising that cross-validated gain.  The final model
is refitted on all samples at the chosen threshold (``delta_loglik`` is its
in-sample gain).

``improves`` is True when ``heldout_delta_loglik > 0.5 * chi2.ppf(level, p)``
(p the number of selected features, level 0.99): a held-out gain a likelihood-ratio
test with p extra parameters would call significant at 1 %, which the
held-out (already overfitting-penalised) gain of pure noise rarely reaches.
``share_explained`` = held-out sum-of-squares reduction ``2 heldout_delta_loglik``
over the cell's excess ``O - E`` (``E = sum E[r^2]``, or the sample count).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from imu_array_ros.fusion.residuals import AXES

__all__ = ["EmpiricalModel", "motion_features", "fit_empirical", "block_folds", "stlsq"]

_XYZ = ("x", "y", "z")
#: significance level of ``improves``
LEVEL = 0.99


def motion_features(motion: np.ndarray, stamps: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """(N, F) library of motion features and their F names.

    motion (N, 9) = [omega rad/s, omega_dot rad/s^2, s m/s^2] (array frame), stamps (N,) int64 ns.
    Features: "1"; omega_i, omega_dot_i, s_i; omega_i*omega_j (i <= j), omega_i*s_j,
    s_i*s_j (i <= j); "d/dt omega_dot_i" (omega_ddot, rad/s^3) and "d/dt s_i"
    (m/s^3) by np.gradient on the stamps in seconds; the one-sample delays
    "omega_i[n-1]" and "s_i[n-1]" (NaN in row 0).  A NaN motion row gives a NaN
    feature row (and NaN derivatives in its neighbours).
    """
    m = np.asarray(motion, dtype=float).reshape(-1, 9)
    n = len(m)
    w, wd, s = m[:, 0:3], m[:, 3:6], m[:, 6:9]
    cols, names = [np.ones(n)], ["1"]
    for block, base in ((w, "omega"), (wd, "omega_dot"), (s, "s")):
        cols += list(block.T)
        names += [f"{base}_{c}" for c in _XYZ]
    iu, ju = np.triu_indices(3)
    cols += list((w[:, iu] * w[:, ju]).T)
    names += [f"omega_{_XYZ[i]}*omega_{_XYZ[j]}" for i, j in zip(iu, ju)]
    ii, jj = np.indices((3, 3)).reshape(2, -1)
    cols += list((w[:, ii] * s[:, jj]).T)
    names += [f"omega_{_XYZ[i]}*s_{_XYZ[j]}" for i, j in zip(ii, jj)]
    cols += list((s[:, iu] * s[:, ju]).T)
    names += [f"s_{_XYZ[i]}*s_{_XYZ[j]}" for i, j in zip(iu, ju)]
    if n >= 2:
        t = (np.asarray(stamps, dtype=np.int64) - int(stamps[0])) * 1e-9
        with np.errstate(invalid="ignore", divide="ignore"):
            dwd, ds = np.gradient(wd, t, axis=0), np.gradient(s, t, axis=0)
    else:
        dwd = ds = np.full((n, 3), np.nan)
    cols += list(dwd.T) + list(ds.T)
    names += [f"d/dt omega_dot_{c}" for c in _XYZ] + [f"d/dt s_{c}" for c in _XYZ]
    lag = np.full((n, 6), np.nan)
    lag[1:] = np.concatenate([w, s], axis=1)[:-1]
    cols += list(lag.T)
    names += [f"omega_{c}[n-1]" for c in _XYZ] + [f"s_{c}[n-1]" for c in _XYZ]
    x = np.column_stack(cols)
    x[~np.isfinite(m).all(axis=1)] = np.nan
    return x, names


def block_folds(n: int, n_folds: int = 5, block: int | None = None) -> np.ndarray:
    """(n,) fold ids of interleaved time blocks: block b (``block`` samples each,
    default n // (10 n_folds)) goes to fold b mod n_folds."""
    block = max(1, int(block) if block is not None else n // (10 * n_folds))
    return (np.arange(n) // block) % n_folds


def stlsq(gram: np.ndarray, xty: np.ndarray, n: float, threshold: float, *, max_terms: int = 8,
          ridge: float = 1e-3, iterations: int = 20) -> np.ndarray:
    """Sequentially thresholded ridge least squares from the Gram matrix; (F,) coefficients on the raw features.

    gram = X^T X (F, F), xty = X^T r (F,), n samples.  Features are scaled to unit
    RMS (sqrt(diag(gram)/n)); ``threshold`` applies to the scaled coefficients;
    features that are zero on every sample are never selected.
    """
    f = len(xty)
    scale = np.sqrt(np.clip(np.diag(gram), 0.0, None) / max(n, 1.0))
    usable = scale > 0
    scale = np.where(usable, scale, 1.0)
    gs = gram / np.outer(scale, scale)
    bs = xty / scale
    support = usable.copy()
    beta = np.zeros(f)
    for _ in range(iterations):
        beta = np.zeros(f)
        idx = np.flatnonzero(support)
        if len(idx) == 0:
            break
        beta[idx] = np.linalg.solve(gs[np.ix_(idx, idx)] + ridge * n * np.eye(len(idx)), bs[idx])
        keep = np.abs(beta) >= threshold
        if np.count_nonzero(keep) > max_terms:
            keep[:] = False
            keep[np.argsort(-np.abs(beta))[:max_terms]] = True
        if np.array_equal(keep, support):
            break
        support = keep
    else:
        beta = np.zeros(f)
        idx = np.flatnonzero(support)
        if len(idx):
            beta[idx] = np.linalg.solve(gs[np.ix_(idx, idx)] + ridge * n * np.eye(len(idx)), bs[idx])
    beta = np.where(support, beta, 0.0)
    return beta / scale


def _gain(beta: np.ndarray, gram: np.ndarray, xty: np.ndarray) -> float:
    """0.5 * sum (r^2 - (r - X beta)^2) from the Gram matrix."""
    return float(beta @ xty - 0.5 * beta @ gram @ beta)


@dataclass
class EmpiricalModel:
    """A sparse empirical model of the residual of one cell.

    k: IMU index; axis: axis name (:data:`AXES`); features: selected feature names;
    columns: their indices in the library; coefficients (p,): residual units per
    feature unit (m/s^2 for acc axes, rad/s for gyro axes when ``std`` was given,
    else noise stds); delta_loglik: in-sample log-likelihood gain; heldout_delta_loglik:
    cross-validated gain; share_explained: held-out fraction of the cell's excess
    removed (NaN without excess); improves: heldout gain above ``significance``
    (0.5 chi2.ppf(0.99, p)); threshold: the STLSQ threshold used; n_samples: samples used.
    """

    k: int
    axis: str
    features: list[str]
    columns: list[int]
    coefficients: np.ndarray
    delta_loglik: float
    heldout_delta_loglik: float
    share_explained: float
    improves: bool
    threshold: float = float("nan")
    significance: float = float("nan")
    n_samples: int = 0
    fold_gains: list[float] = field(default_factory=list, repr=False)

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(N,) modelled residual (coefficient units) from the full (N, F) feature library."""
        x = np.asarray(features, dtype=float)
        return x[:, self.columns] @ self.coefficients if self.columns else np.zeros(len(x))

    def to_dict(self) -> dict:
        """JSON-friendly: plain floats and lists, None for NaN."""
        def num(v):
            v = float(v)
            return v if np.isfinite(v) else None
        return {"k": int(self.k), "axis": self.axis, "features": list(self.features),
                "coefficients": [num(c) for c in self.coefficients], "delta_loglik": num(self.delta_loglik),
                "heldout_delta_loglik": num(self.heldout_delta_loglik), "share_explained": num(self.share_explained),
                "improves": bool(self.improves), "threshold": num(self.threshold),
                "significance": num(self.significance), "n_samples": int(self.n_samples)}


def fit_empirical(residuals: np.ndarray, features: np.ndarray, names, cells, folds: np.ndarray, *,
                  std: np.ndarray | None = None, expected: np.ndarray | None = None,
                  threshold: float | None = None, max_terms: int = 8, ridge: float = 1e-3,
                  level: float = LEVEL) -> list[EmpiricalModel]:
    """Cross-validated sparse models of the residual of ``cells`` on the feature library.

    residuals (N, K, 6) normalised (NaN masked); features (N, F) with F ``names``
    (e.g. :func:`motion_features`); cells: (k, a) pairs; folds (N,) int fold ids
    >= 0 (-1: unused; e.g. :func:`block_folds`), at least two distinct; std (K, 6):
    noise std to express coefficients in SI; expected (N, K, 6): E[r^2] for
    ``share_explained`` (default 1 per sample); threshold: STLSQ threshold on the
    scaled coefficients (None: cross-validated, module docstring).  A sample is
    used when its residual and all its features are finite.  A cell with fewer than
    two folds or no more samples than features gets the empty model (no feature,
    gains 0, improves False).  One model per cell, in order.
    """
    r = np.asarray(residuals, dtype=float)
    x = np.asarray(features, dtype=float)
    folds = np.asarray(folds).astype(np.int64).reshape(len(r))
    names = list(names)
    if x.shape != (len(r), len(names)):
        raise ValueError(f"features must be (N, {len(names)}), got {x.shape}")
    feat_ok = np.isfinite(x).all(axis=1) & (folds >= 0)
    out = []
    for k, a in cells:
        k, a = int(k), int(a)
        y = r[:, k, a]
        ok = feat_ok & np.isfinite(y)
        xo, yo, fo = x[ok], y[ok], folds[ok]
        ids = np.unique(fo)
        grams = np.stack([xo[fo == f].T @ xo[fo == f] for f in ids]) if len(ids) else np.zeros((0,) + (len(names),) * 2)
        xtys = np.stack([xo[fo == f].T @ yo[fo == f] for f in ids]) if len(ids) else np.zeros((0, len(names)))
        counts = np.array([np.count_nonzero(fo == f) for f in ids], dtype=float)
        g_all, b_all, n_all = grams.sum(axis=0), xtys.sum(axis=0), float(counts.sum())
        if expected is not None:
            e = np.asarray(expected, dtype=float)[:, k, a][ok]
            excess = float(yo @ yo - np.nansum(e))
        else:
            excess = float(yo @ yo - n_all)

        def cv(thr):
            gains = []
            for i in range(len(ids)):
                beta = stlsq(g_all - grams[i], b_all - xtys[i], n_all - counts[i], thr, max_terms=max_terms,
                             ridge=ridge)
                gains.append(_gain(beta, grams[i], xtys[i]))
            return float(np.sum(gains)), gains

        if len(ids) < 2 or n_all <= len(names):  # nothing to validate: the empty model (gain 0)
            thr, heldout, gains = np.inf, 0.0, []
        elif threshold is not None:
            thr = float(threshold)
            heldout, gains = cv(thr)
        else:  # the empty model (gain 0) unless a threshold does better on held-out data
            thr, heldout, gains = np.inf, 0.0, [0.0] * len(ids)
            for t in np.geomspace(2.0 / np.sqrt(n_all), 1.0, 9):
                score, g = cv(t)
                if score > heldout:
                    thr, heldout, gains = float(t), score, g
        beta = stlsq(g_all, b_all, n_all, thr, max_terms=max_terms, ridge=ridge) if np.isfinite(thr) else \
            np.zeros(len(names))
        cols = [int(j) for j in np.flatnonzero(beta)]
        p = len(cols)
        bar = 0.5 * float(chi2.ppf(level, max(p, 1)))
        unit = float(np.asarray(std, dtype=float)[k, a]) if std is not None else 1.0
        out.append(EmpiricalModel(
            k=k, axis=AXES[a], features=[names[j] for j in cols], columns=cols,
            coefficients=beta[cols] * unit, delta_loglik=_gain(beta, g_all, b_all),
            heldout_delta_loglik=heldout, share_explained=2.0 * heldout / excess if excess > 0 else float("nan"),
            improves=bool(p > 0 and np.isfinite(heldout) and heldout > bar), threshold=float(thr),
            significance=bar, n_samples=int(n_all), fold_gains=[float(g) for g in gains]))
    return out
