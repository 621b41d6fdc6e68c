"""The posterior's target: the prior, the selected samples and the Rao-Blackwellised likelihood (carlsson2021).

The target is p(theta | y_1:T), theta the positions of every IMU but the reference (held: only
relative positions are observable), under the array model of the compensated readings
(:mod:`~imu_array_ros.calibration.bayes.model`).

Likelihood (eq. 26): the linear motion phi = [omega_dot, s] is marginalised analytically under a
flat prior (eq. 22-25) and omega numerically, by N draws from p(omega | gyroscopes) (26b) per time
sample::

    log p_N(y | theta) = sum_t logsumexp_n(-||z_t - h(omega_tn, theta)||^2_S / 2) - T log N - T/2 log|H^T Omega H|

Note the exponent of |H^T Omega H|: -1/2, the limit of the Gaussian normaliser |M_t|^-1/2 (eq. 19,
21); eq. 25-26 print the determinant without the square root (a paper erratum).  h(omega, r_k) =
([omega]x^2) r_k is linear in r_k and in the six monomials q(omega) = [wx^2, wy^2, wz^2, wx wy, wx wz,
wy wz], so the exponent is c_t - 2 q^T beta_t + q^T P q with c_t (T,), beta_t (T, 6) and P (6, 6)
computed once per theta from 3x3 blocks (S is never formed) and reused by every draw: a likelihood
costs O(T K) + O(T N).

The random numbers: omega_tn = mu_t + L_t u_tn with u (T, N, 3) standard normal (the chain moves on
(theta, u) jointly: :mod:`~imu_array_ros.calibration.bayes.chain`).  p(omega_t | gyroscopes) is the
noise model's posterior (26b, ``omega_covariance="model"``) or the gyroscopes' mean and sample
covariance at each t (eq. 30, ``"sample"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from imu_array_ros.calibration.bayes.model import compensate
from imu_array_ros.calibration.selection import MIN_EXCITATION, select_rotating, spread_evenly
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["Prior", "BayesProblem", "build_problem", "select_samples", "loglik_variance", "PRIOR_STD",
           "PACKAGE_SIZE", "OMEGA_COVARIANCES"]

#: carlsson2021 Sec. IV-A: prior standard deviation of each position coordinate, m
PRIOR_STD = 3e-3
#: carlsson2021 Fig. 1: an MPU-9150 package is 4 x 4 x 1 mm (the uniform prior's box)
PACKAGE_SIZE = (4e-3, 4e-3, 1e-3)
#: how p(omega | gyroscopes) is formed: "model": the noise model's posterior (26b);
#: "sample": mean and sample covariance of the gyroscopes at each t (eq. 30)
OMEGA_COVARIANCES = ("model", "sample")


@dataclass(frozen=True)
class Prior:
    """Prior on the free positions (d,) = (K-1)*3: ``kind`` "gaussian" N(mean, std^2) per coordinate
    or "uniform" on mean +- half_width (box)."""

    kind: str
    mean: np.ndarray
    std: np.ndarray  # gaussian: std; uniform: half width

    def logpdf(self, theta: np.ndarray) -> float:
        d = (np.asarray(theta) - self.mean) / self.std
        if self.kind == "uniform":
            return 0.0 if np.all(np.abs(d) <= 1.0) else -np.inf
        return -0.5 * float(d @ d)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        z = rng.uniform(-1, 1, (n, len(self.mean))) if self.kind == "uniform" else rng.normal(size=(n, len(self.mean)))
        return self.mean + z * self.std

    @property
    def covariance_diag(self) -> np.ndarray:
        """Per-coordinate prior variance (uniform: half_width^2 / 3)."""
        return self.std ** 2 / (3.0 if self.kind == "uniform" else 1.0)


@dataclass(frozen=True)
class BayesProblem:
    """The selected samples, compensated, and everything θ-independent (module docstring).

    names (K,); reference: index of the held IMU; free (K-1,) indices of the
    sampled ones; positions (K, 3) the starting positions (the reference's is
    held at its value); stamps (T,); wz (T, 3K) Omega_k z_tk; zz (T,)
    sum_k z^T Omega z; wsum (T, 3) sum_k Omega_k z_tk; omega_info (K, 3, 3)
    Omega_k; mu (T, 3), chol (T or 1, 3, 3): p(omega_t | gyroscopes) =
    N(mu_t, chol chol^T); prior; n_draws N; rho; coef, coef0, amat: the
    likelihood's coefficients (:func:`likelihood_coefficients`).
    """

    names: tuple
    reference: int
    free: np.ndarray
    positions: np.ndarray
    stamps: np.ndarray
    wz: np.ndarray = field(repr=False)
    zz: np.ndarray = field(repr=False)
    wsum: np.ndarray = field(repr=False)
    omega_info: np.ndarray = field(repr=False)
    mu: np.ndarray = field(repr=False)
    chol: np.ndarray = field(repr=False)
    prior: Prior = None
    n_draws: int = 16
    rho: float = 0.0
    omega_covariance: str = "model"
    accel_std: np.ndarray = field(default=None, repr=False)
    coef: np.ndarray = field(default=None, repr=False)
    coef0: np.ndarray = field(default=None, repr=False)
    amat: np.ndarray = field(default=None, repr=False)

    @property
    def dim(self) -> int:
        return 3 * len(self.free)

    @property
    def n_samples(self) -> int:
        return len(self.stamps)

    def with_(self, **kw) -> "BayesProblem":
        return replace(self, **kw)

    def full_positions(self, theta: np.ndarray) -> np.ndarray:
        """(K, 3) positions from the free coordinates theta (d,) (or (..., d) -> (..., K, 3))."""
        theta = np.asarray(theta, dtype=float)
        out = np.broadcast_to(self.positions, theta.shape[:-1] + self.positions.shape).copy()
        out[..., self.free, :] = theta.reshape(theta.shape[:-1] + (len(self.free), 3))
        return out

    def theta_of(self, positions: np.ndarray) -> np.ndarray:
        """Free coordinates (d,) of (K, 3) positions."""
        return np.asarray(positions, dtype=float)[self.free].reshape(-1)

    def omega_draws(self, u: np.ndarray) -> np.ndarray:
        """omega_tn = mu_t + L_t u_tn: u (..., T, N, 3) -> (..., T, N, 3)."""
        return self.mu[:, None, :] + np.einsum("tij,...tnj->...tni", self.chol, u) if len(self.chol) > 1 else \
            self.mu[:, None, :] + u @ self.chol[0].T

    def quadratic(self, theta: np.ndarray):
        """(c (T,), beta (T, 6), P (6, 6), log|G|) of the exponent at theta (module docstring), or None
        where G = H^T Omega H is singular.  Every matrix is a quadratic polynomial in the positions, so
        all of them are one product with the coefficients ``build_problem`` precomputed."""
        r = self.full_positions(theta)
        rr = (r[:, :, None] * r[:, None, :]).reshape(-1)
        m = np.concatenate([rr, r.reshape(-1)]) @ self.coef + self.coef0  # (108,)
        g, f, p1 = m[:36].reshape(6, 6), m[36:72].reshape(6, 6), m[72:].reshape(6, 6)
        try:
            low = np.linalg.cholesky(g)
        except np.linalg.LinAlgError:
            return None
        linv = np.linalg.inv(low)
        mats = (r @ self.amat).reshape(3 * len(r), 9)  # rows of [E_k | X_k^T], linear in r_k
        prod = self.wz @ mats  # (T, 9): sum_k E_k^T w_tk, sum_k X_k w_tk
        g0 = np.concatenate([prod[:, 6:9], self.wsum], axis=1)  # (T, 6)
        a = g0 @ linv.T
        fl = linv @ f
        c = self.zz - np.sum(a * a, axis=1)
        beta = prod[:, :6] - a @ fl
        p = p1 - fl.T @ fl
        return c, beta, 0.5 * (p + p.T), 2.0 * float(np.sum(np.log(np.diag(low))))

    def loglik(self, theta: np.ndarray, u: np.ndarray):
        """log p_N(y | theta, u) up to a theta-independent constant (module docstring); u (T, N, 3), or
        (R, T, N, 3) for R replicates of the random numbers at one theta (then (R,))."""
        quad = self.quadratic(theta)
        if quad is None:
            return np.full(u.shape[:-3], -np.inf) if u.ndim > 3 else -np.inf
        return _loglik(quad, _monomials(self.omega_draws(u)))

    def exact_loglik(self, theta: np.ndarray, omega: np.ndarray) -> float:
        """The same with omega known (T, 3): sum_t -||z_t - h||^2_S / 2 - T/2 log|G| (the N -> inf limit
        when the gyroscopes are exact); for tests."""
        quad = self.quadratic(theta)
        return _loglik(quad, _monomials(np.asarray(omega, dtype=float)[:, None, :]))


def loglik_variance(problem: BayesProblem, theta: np.ndarray, replicates: int, rng: np.random.Generator,
                    batch: int = 8) -> float:
    """Var[log p_N(y | theta)] over ``replicates`` independent sets of random numbers (the tuning of N)."""
    vals = []
    for lo in range(0, replicates, batch):
        r = min(batch, replicates - lo)
        vals.append(problem.loglik(theta, rng.standard_normal((r, problem.n_samples, problem.n_draws, 3))))
    return float(np.var(np.concatenate(vals), ddof=1))


# --------------------------------------------------------------------------- the exponent's algebra


def _monomial_matrix(r: np.ndarray) -> np.ndarray:
    """E(r) (K, 3, 6) with ([omega]x^2) r = E(r) q(omega), q = [wx^2, wy^2, wz^2, wx wy, wx wz, wy wz]."""
    rx, ry, rz = r[:, 0], r[:, 1], r[:, 2]
    z = np.zeros_like(rx)
    return np.stack([np.stack([z, -rx, -rx, ry, rz, z], axis=1),
                     np.stack([-ry, z, -ry, rx, z, rz], axis=1),
                     np.stack([-rz, -rz, z, z, rx, ry], axis=1)], axis=1)


def _monomials(w: np.ndarray) -> np.ndarray:
    """q(omega) (..., 6) of omega (..., 3)."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=-1)


def _loglik(quad, q: np.ndarray):
    """sum_t logsumexp_n(-e_tn / 2) - T log N - T/2 log|G| for q (..., T, N, 6); leading dims kept."""
    c, beta, p, logdet = quad
    e = c[:, None] + np.sum(q * (q @ p - 2.0 * beta[:, None, :]), axis=-1)  # (..., T, N)
    t, n = q.shape[-3], q.shape[-2]
    x = -0.5 * e
    if n == 1:
        lse = x[..., 0]
    else:
        mx = np.max(x, axis=-1)
        lse = mx + np.log(np.sum(np.exp(x - mx[..., None]), axis=-1))
    return np.sum(lse, axis=-1) - t * np.log(n) - 0.5 * t * logdet


def likelihood_coefficients(omega_info: np.ndarray):
    """Coefficients of G, F, P1 (module docstring) as polynomials in the positions: (coef (12K, 108),
    coef0 (108,)) with [vec(r_k r_k^T) for k, vec(r)] @ coef + coef0; and amat (3, 27) with
    r_k @ amat = the rows of [E(r_k) | X(r_k)^T] (3 x 9).  omega_info: Omega_k (K, 3, 3)."""
    k = len(omega_info)
    eye = np.eye(3)
    xb = skew(eye)  # X_i = [e_i]x, (3, 3, 3)
    eb = _monomial_matrix(eye)  # E_i = E(e_i), (3, 3, 6)
    om = omega_info
    # quadratic parts per k: (K, 3, 3, 108)
    g11 = -np.einsum("iab,kbc,jcd->kijad", xb, om, xb)
    ftop = np.einsum("iab,kbc,jcd->kijad", xb, om, eb)
    p1 = np.einsum("iba,kbc,jcd->kijad", eb, om, eb)
    quad = np.zeros((k, 3, 3, 3 * 36))
    quad[..., :36] = np.pad(g11, [(0, 0)] * 3 + [(0, 3), (0, 3)]).reshape(k, 3, 3, 36)
    quad[..., 36:72] = np.pad(ftop, [(0, 0)] * 3 + [(0, 3), (0, 0)]).reshape(k, 3, 3, 36)
    quad[..., 72:] = p1.reshape(k, 3, 3, 36)
    # linear parts per k: (K, 3, 108)
    g12 = np.einsum("iab,kbc->kiac", xb, om)  # X_i Omega_k (3x3) -> G[:3, 3:]; its transpose -> G[3:, :3]
    fbot = np.einsum("kab,ibc->kiac", om, eb)  # Omega_k E_i -> F[3:, :]
    lin = np.zeros((k, 3, 108))
    gl = np.zeros((k, 3, 6, 6))
    gl[:, :, :3, 3:] = g12
    gl[:, :, 3:, :3] = g12.transpose(0, 1, 3, 2)
    lin[..., :36] = gl.reshape(k, 3, 36)
    fl = np.zeros((k, 3, 6, 6))
    fl[:, :, 3:, :] = fbot
    lin[..., 36:72] = fl.reshape(k, 3, 36)
    g0 = np.zeros((6, 6))
    g0[3:, 3:] = om.sum(axis=0)
    coef = np.concatenate([quad.reshape(9 * k, 108), lin.reshape(3 * k, 108)], axis=0)
    coef0 = np.concatenate([g0.reshape(36), np.zeros(72)])
    amat = np.concatenate([eb, xb.transpose(0, 2, 1)], axis=2).reshape(3, 27)  # r_k @ amat: [E_k | X_k^T]
    return coef, coef0, amat


# --------------------------------------------------------------------------- building a problem


def select_samples(samples: ImuSamples, model: SensorModel, n_samples: int | None, *,
                   min_excitation: float | None = None):
    """Indices of the samples to use: complete (every reading valid), rotating by the fused motion and by the
    gyroscopes alone (:func:`~imu_array_ros.calibration.selection.select_rotating` with ``gyroscopes=True``:
    with uncalibrated accelerometer biases static poses would pass the first test), ``n_samples`` of them
    evenly spread in time (None: all).  Returns (indices, dropped reason -> count, usable count)."""
    threshold = MIN_EXCITATION if min_excitation is None else float(min_excitation)
    selection = select_rotating(samples, model, threshold, gyroscopes=True)
    idx = spread_evenly(selection, n_samples)
    usable = selection.n_used
    if len(idx) < 2:
        why = selection.dropped_text()
        raise CalibrationError(f"too few samples with rotation: {usable} usable of {len(samples)}"
                               f"{' (dropped: ' + why + ')' if why else ''}; twist the array by hand about at "
                               "least two axes")
    return idx, selection.dropped, usable


def build_problem(samples: ImuSamples, model: SensorModel, *, reference: int = 0, prior: Prior | None = None,
                  prior_kind: str = "gaussian", prior_std: float = PRIOR_STD, package=PACKAGE_SIZE,
                  accel_std: float | None = None, omega_covariance: str = "model", n_draws: int = 16,
                  rho: float = 0.0) -> BayesProblem:
    """The :class:`BayesProblem` of complete samples (T, K, 3) under ``model`` (module docstring).

    The prior is centred on the model's positions (the description's); ``accel_std`` replaces the
    accelerometer noise std (carlsson2021 Sec. IV-B sets it to 0.79 m/s^2 for the real array).
    """
    stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
    t, k = len(stamps), model.n_imus
    if accel.shape != (t, k, 3):
        raise CalibrationError(f"readings of shape {accel.shape}, expected {(t, k, 3)}")
    if not (np.all(np.isfinite(accel)) and np.all(np.isfinite(gyro))):
        raise CalibrationError("the Bayesian calibration needs complete samples (no missing or NaN reading)")
    if k < 2:
        raise CalibrationError("an array of one IMU has no relative positions to calibrate")
    if omega_covariance not in OMEGA_COVARIANCES:
        raise CalibrationError(f"omega covariance {omega_covariance!r}: expected one of {', '.join(OMEGA_COVARIANCES)}")
    if omega_covariance == "sample" and k < 4:
        raise CalibrationError("the sample covariance of the gyroscopes (eq. 30) needs at least 4 IMUs")
    if not 0.0 <= rho < 1.0:
        raise CalibrationError(f"rho {rho}: the correlation of the random numbers must be in [0, 1)")
    comp = compensate(samples, model, accel_std)
    z, w, om = comp.accel, comp.gyro, comp.accel_info
    wz = np.einsum("kij,tkj->tki", om, z)
    zz = np.einsum("tki,tki->t", z, wz)
    if omega_covariance == "model":  # (26b): the posterior of omega given the K gyroscopes
        info_g = np.linalg.inv(comp.gyro_cov)
        post = np.linalg.inv(np.sum(info_g, axis=0))
        mu = np.einsum("ij,tj->ti", post, np.einsum("kij,tkj->ti", info_g, w))
        chol = np.linalg.cholesky(0.5 * (post + post.T))[None]
    else:  # eq. 30: the gyroscopes' mean and sample covariance at each t
        mu = w.mean(axis=1)
        d = w - mu[:, None, :]
        cov = np.einsum("tki,tkj->tij", d, d) / (k - 1)
        try:
            chol = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise CalibrationError("the gyroscopes' sample covariance (eq. 30) is singular at some sample") from None
    positions = np.asarray(model.positions, dtype=float).copy()
    free = np.array([i for i in range(k) if i != reference])
    if prior is None:
        if prior_kind == "gaussian":
            prior = Prior("gaussian", positions[free].reshape(-1), np.full(3 * len(free), float(prior_std)))
        elif prior_kind == "uniform":
            half = np.tile(0.5 * np.asarray(package, dtype=float), len(free))
            prior = Prior("uniform", positions[free].reshape(-1), half)
        else:
            raise CalibrationError(f"prior {prior_kind!r}: expected gaussian or uniform")
    coef, coef0, amat = likelihood_coefficients(om)
    return BayesProblem(names=tuple(model.names), reference=int(reference), free=free, positions=positions,
                        stamps=stamps, coef=coef, coef0=coef0, amat=amat, wz=wz.reshape(t, 3 * k), zz=zz,
                        wsum=wz.sum(axis=1), omega_info=om, mu=mu, chol=chol, prior=prior, n_draws=int(n_draws),
                        rho=float(rho), omega_covariance=omega_covariance, accel_std=comp.accel_std)
