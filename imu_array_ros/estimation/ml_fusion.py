"""Maximum-likelihood fusion of an inertial sensor array (skog2016 Sec. II-III).

Model (skog2016 eq. 3-5, with the calibrated sensor frames of
:mod:`imu_array_ros.model.sensor_model`): for accelerometer triad ``i``

    y_i - b_i = A_i ( s + Omega_w^2 r_i - Omega_{r_i} omega_dot ) + n_i

and for gyroscope triad ``j``: ``y_j - c_j = B_j omega + n_j``.

Reformulation used here.  ``Omega_w^2 r = M(r) q(omega)`` with ``q`` the six
quadratic monomials of omega (:func:`~imu_array_ros.model.kinematics.quadratic_monomials`),
so all accelerometer readings are *linear* in ``z = [q, omega_dot, s]`` (12):
``y_a - b = D z + n`` with a constant (3K x 12) matrix ``D`` fixed by geometry and
calibration.  With weights ``W = Q_a^{-1}`` (masked for missing/saturated axes)
every sample enters only through ``beta = D^T W (y_a - b)`` (12-vector), and with
``F = D^T W D`` split into the q- and phi=[omega_dot, s]-blocks:

* WLS for phi given omega (eq. 8):  ``phi(omega) = F_pp^{-1} beta_p - E q(omega)``,
  ``E = F_pp^{-1} F_pq``;
* concentrated cost (eq. 10-11), a quartic polynomial in omega whose
  coefficients ``F~ = F_qq - F_qp E`` depend on geometry only:
  ``J(omega) = q^T F~ q - 2 q^T beta~ + omega^T W_g omega - 2 omega^T g``,
  ``beta~ = beta_q - E^T beta_p``;
* Gauss-Newton on omega (eq. 12-13) with ``J_h = D_q dq/domega``:
  ``omega += (Jq^T F~ Jq + W_g)^{-1} (Jq^T (beta~ - F~ q) + g - W_g omega)``,
  started from the weighted gyro mean (incl. saturated readings, which carry
  the sign, Sec. III), with a backtracking safeguard;
* Cramér-Rao bound (eq. 14-15): the inverse Fisher information
  ``[[Jq^T F_qq Jq + W_g, Jq^T F_qp], [F_pq Jq, F_pp]]^{-1}`` evaluated at the
  estimate, computed blockwise by the Schur complement (eq. 20, 27).

Saturated gyroscope axes are dropped from the likelihood (Sec. III); their sign
only enters through the starting point.  Samples are grouped by the pattern of
valid accelerometer axes (IMU dropouts, saturation), each group sharing its
precomputed geometry; there is no per-sample Python loop.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from imu_array_ros.model.identifiability import check_identifiable
from imu_array_ros.errors import FusionError
from imu_array_ros.model.kinematics import centripetal_matrix, euler_matrix, quadratic_monomials, quadratic_monomials_jacobian
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.sensor_model import SATURATION_MARGIN, LinearArrayModel, unsaturated

__all__ = ["FusionConfig", "FusionStats", "MLFusion", "fuse", "inv_sym3", "solve_sym3"]

log = logging.getLogger(__name__)

_MAX_SKIPPED_STAMPS = 10  # stamps of skipped samples kept for the user


@dataclass(frozen=True)
class FusionConfig:
    """Tuning of the Gauss-Newton solver.

    max_iterations: Gauss-Newton iterations per sample.
    tolerance: stop when the step is below ``tolerance * (1 + |omega|)`` rad/s.
    saturation_margin: a raw reading with ``|y| >= margin * range`` is saturated.
    """

    max_iterations: int = 30
    tolerance: float = 1e-10
    saturation_margin: float = SATURATION_MARGIN


@dataclass
class FusionStats:
    """Counts of what the fusion did with its input (printed by the CLI)."""

    samples: int = 0
    fused: int = 0
    skipped_unidentifiable: int = 0
    incomplete_samples: int = 0
    saturated_gyro_samples: int = 0
    saturated_accel_samples: int = 0
    not_converged: int = 0
    patterns: int = 0
    skipped_stamps: list = field(default_factory=list, repr=False)

    def merge(self, other: "FusionStats") -> None:
        """Add ``other``'s counts to these (``patterns``: the larger; ``skipped_stamps``: the first 10)."""
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name == "patterns":
                setattr(self, f.name, max(a, b))
            elif isinstance(a, list):
                setattr(self, f.name, (a + b)[:_MAX_SKIPPED_STAMPS])
            else:
                setattr(self, f.name, a + b)


# --------------------------------------------------------------------------- small batched linear algebra


def _cofactors_sym3(h: np.ndarray):
    a, b, c = h[..., 0, 0], h[..., 0, 1], h[..., 0, 2]
    d, e, f = h[..., 1, 1], h[..., 1, 2], h[..., 2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    det = a * c00 + b * c01 + c * c02
    return (c00, c01, c02, c11, c12, c22), det


def _positive_definite(h: np.ndarray, det: np.ndarray) -> np.ndarray:
    """True where symmetric 3x3 ``h`` is numerically positive definite: det > 1e-12 * diagonal product."""
    diag = h[..., 0, 0] * h[..., 1, 1] * h[..., 2, 2]
    return (det > 1e-12 * diag) & (diag > 0) & np.isfinite(det)


def inv_sym3(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of symmetric 3x3 matrices (..., 3, 3) by cofactors.

    Returns ``(inverse, ok)``; ``ok`` is False where ``h`` is not numerically
    positive definite (the inverse there is inf/nan and must not be used).
    """
    (c00, c01, c02, c11, c12, c22), det = _cofactors_sym3(h)
    out = np.empty_like(h)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        out[..., 0, 0] = c00 * inv_det
        out[..., 0, 1] = out[..., 1, 0] = c01 * inv_det
        out[..., 0, 2] = out[..., 2, 0] = c02 * inv_det
        out[..., 1, 1] = c11 * inv_det
        out[..., 1, 2] = out[..., 2, 1] = c12 * inv_det
        out[..., 2, 2] = c22 * inv_det
    return out, _positive_definite(h, det)


def solve_sym3(h: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``h x = r`` for symmetric 3x3 ``h`` (..., 3, 3), ``r`` (..., 3).

    Returns ``(x, ok)`` with ``ok`` as in :func:`inv_sym3` (x is 0 where not ok).
    """
    (c00, c01, c02, c11, c12, c22), det = _cofactors_sym3(h)
    ok = _positive_definite(h, det)
    safe = np.where(ok, det, 1.0)
    r0, r1, r2 = r[..., 0], r[..., 1], r[..., 2]
    x = np.stack(
        [c00 * r0 + c01 * r1 + c02 * r2, c01 * r0 + c11 * r1 + c12 * r2, c02 * r0 + c12 * r1 + c22 * r2], axis=-1
    ) / safe[..., None]
    x[~ok] = 0.0
    return x, ok


# --------------------------------------------------------------------------- geometry per validity pattern

#: dq/domega is linear in omega: Jq(omega) = sum_m omega_m _JQ_BASIS[m]  (3, 6, 3)
_JQ_BASIS = quadratic_monomials_jacobian(np.eye(3))


def _gn_matrix_coefficients(ft: np.ndarray) -> np.ndarray:
    """T (6, 9) with ``Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3)``.

    ``Jq^T F~ Jq = sum_{m,p} omega_m omega_p S_mp`` with ``S_mp = C_m^T F~ C_p``;
    grouping the terms by the monomials q = [x^2, y^2, z^2, xy, xz, yz].
    """
    s = np.einsum("mki,kl,plj->mpij", _JQ_BASIS, ft, _JQ_BASIS)
    rows = [s[0, 0], s[1, 1], s[2, 2], s[0, 1] + s[1, 0], s[0, 2] + s[2, 0], s[1, 2] + s[2, 1]]
    return np.stack(rows).reshape(6, 9)



@dataclass(frozen=True)
class _PatternGeometry:
    """Precomputed matrices for one pattern of valid accelerometer axes."""

    ok: bool
    G: np.ndarray | None = None  # (3K, 12) = W D, so beta = (y - b) @ G
    Ft: np.ndarray | None = None  # (6, 6) F~
    E: np.ndarray | None = None  # (6, 6) F_pp^{-1} F_pq
    Fpp_inv: np.ndarray | None = None  # (6, 6)
    T: np.ndarray | None = None  # (6, 9): Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3)
    EC: np.ndarray | None = None  # (3, 18): E Jq(omega) = (omega @ EC).reshape(6, 3)


class MLFusion:
    """ML fusion for one array model; caches the per-pattern geometry.

    Use :meth:`fuse` on batches (the CLI and the node call the same method; a
    single sample is a batch of one).  Angular quantities in rad/s and rad/s^2,
    specific force in m/s^2, all in the array frame.
    """

    def __init__(self, model: LinearArrayModel, config: FusionConfig | None = None) -> None:
        self.model = model
        self.config = config or FusionConfig()
        check_identifiable(model.positions, model.n_imus, where=f"array {model.frame_id!r}")
        k = model.n_imus
        r = model.positions
        d = np.concatenate([centripetal_matrix(r), euler_matrix(r), np.broadcast_to(np.eye(3), (k, 3, 3))], axis=2)
        self._D = np.einsum("kij,kjl->kil", model.acc_matrix, d).reshape(3 * k, 12)  # sensor axes x z
        self._w_acc = (1.0 / model.acc_std**2).reshape(3 * k)
        self._V = model.gyro_matrix.reshape(3 * k, 3)  # gyro axis rows (sensor <- array)
        self._w_gyr = (1.0 / model.gyro_std**2).reshape(3 * k)
        self._P = np.einsum("ai,aj->aij", self._V, self._V).reshape(3 * k, 9)
        self._acc_bias = model.acc_bias.reshape(3 * k)
        self._gyr_bias = model.gyro_bias.reshape(3 * k)
        self._cache: dict[bytes, _PatternGeometry] = {}

    # ------------------------------------------------------------------ geometry

    def _geometry(self, mask: np.ndarray) -> _PatternGeometry:
        key = np.packbits(mask).tobytes()
        geo = self._cache.get(key)
        if geo is not None:
            return geo
        wd = (self._w_acc * mask)[:, None] * self._D
        f = self._D.T @ wd
        fpp = f[6:, 6:]
        scale = np.sqrt(np.clip(np.diag(fpp), 0, None))
        geo = _PatternGeometry(ok=False)
        if np.all(scale > 0):
            fn = fpp / np.outer(scale, scale)
            if np.linalg.cond(fn) < 1e10:
                cf = cho_factor(fpp)
                e = cho_solve(cf, f[6:, :6])
                ft = f[:6, :6] - f[:6, 6:] @ e
                ft = 0.5 * (ft + ft.T)
                geo = _PatternGeometry(
                    ok=True, G=wd, Ft=ft, E=e, Fpp_inv=cho_solve(cf, np.eye(6)),
                    T=_gn_matrix_coefficients(ft), EC=np.einsum("ij,mjk->mik", e, _JQ_BASIS).reshape(3, 18),
                )
        if len(self._cache) < 4096:
            self._cache[key] = geo
        return geo

    # ------------------------------------------------------------------ public API

    def fuse(self, stamps: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> tuple[FusedSamples, FusionStats]:
        """Fuse N array samples.

        stamps (N,) int64 ns; accel, gyro (N, K, 3) raw readings in each IMU's
        sensor frame, NaN where not available.  Returns the fused samples that
        were identifiable (others are skipped and counted in the stats).
        """
        cfg = self.config
        m = self.model
        accel = np.asarray(accel, dtype=float)
        gyro = np.asarray(gyro, dtype=float)
        n, k = accel.shape[0], m.n_imus
        if accel.shape != (n, k, 3) or gyro.shape != (n, k, 3):
            raise FusionError(f"fusion: expected accel/gyro of shape (N, {k}, 3), got {accel.shape} / {gyro.shape}")
        stats = FusionStats(samples=n)
        ya = accel.reshape(n, 3 * k)
        yg = gyro.reshape(n, 3 * k)
        # one comparison pass each: NaN (missing) and saturated readings are both invalid
        acc_valid = unsaturated(ya, m.acc_range, cfg.saturation_margin)
        gyr_valid = unsaturated(yg, m.gyro_range, cfg.saturation_margin)
        all_acc = bool(acc_valid.all())
        all_gyr = bool(gyr_valid.all())
        if all_acc:
            acc_in = ya
        else:
            acc_present = np.isfinite(ya)
            stats.saturated_accel_samples = int(np.count_nonzero((acc_present & ~acc_valid).any(1)))
            acc_in = np.where(acc_valid, ya, 0.0)
        wv = self._w_gyr[:, None] * self._V  # (3K, 3)
        if all_gyr:
            gyr_present = None
            Wg = (self._w_gyr @ self._P).reshape(3, 3)  # the same for every sample
            gvec = yg @ wv - self._gyr_bias @ wv
            omega0, ok0 = solve_sym3(np.broadcast_to(Wg, (n, 3, 3)), gvec)
        else:
            gyr_present = np.isfinite(yg)
            stats.saturated_gyro_samples = int(np.count_nonzero((gyr_present & ~gyr_valid).any(1)))
            eg_all = np.where(gyr_present, yg - self._gyr_bias, 0.0)
            Wg = (gyr_valid @ (self._w_gyr[:, None] * self._P)).reshape(n, 3, 3)
            gvec = np.where(gyr_valid, eg_all, 0.0) @ wv
            # starting point: weighted mean of all present gyro readings, saturated
            # ones included (they carry the sign of omega, skog2016 Sec. III)
            W0 = (gyr_present @ (self._w_gyr[:, None] * self._P)).reshape(n, 3, 3)
            omega0, ok0 = solve_sym3(W0, eg_all @ wv)
        if not (all_acc and all_gyr):
            present = np.isfinite(ya).all(1) & (gyr_present.all(1) if gyr_present is not None else True)
            stats.incomplete_samples = int(np.count_nonzero(~present))

        omega = np.full((n, 3), np.nan)
        phi = np.full((n, 6), np.nan)
        cov = np.empty((n, 9, 9))  # every row is either written below or dropped
        iters = np.zeros(n, dtype=np.int32)
        conv = np.zeros(n, dtype=bool)
        good = np.zeros(n, dtype=bool)

        # group samples by their pattern of valid accelerometer axes
        if all_acc:
            groups = [(acc_valid[0], slice(None))] if n else []
        else:
            packed = np.packbits(acc_valid, axis=1)
            _, first, inverse = np.unique(packed, axis=0, return_index=True, return_inverse=True)
            inverse = inverse.ravel()
            order = np.argsort(inverse, kind="stable")
            bounds = np.searchsorted(inverse[order], np.arange(len(first) + 1))
            groups = [(acc_valid[first[g]], order[bounds[g]:bounds[g + 1]]) for g in range(len(first))]
        stats.patterns = len(groups)

        for mask, idx in groups:
            if isinstance(idx, slice):
                if not ok0.all():
                    idx = np.flatnonzero(ok0)
            else:
                idx = idx[ok0[idx]]  # no gyroscope reading at all: not identifiable
            geo = self._geometry(mask)
            if not geo.ok:
                continue
            ya_g = acc_in[idx]
            if ya_g.shape[0] == 0:
                continue
            beta = ya_g @ geo.G - (self._acc_bias * mask) @ geo.G  # (n, 12)
            beta_t = beta[:, :6] - beta[:, 6:] @ geo.E
            phi_lin = beta[:, 6:] @ geo.Fpp_inv
            wg = Wg if Wg.ndim == 2 else Wg[idx]
            w_hat, it, cv, h = self._gauss_newton(omega0[idx], geo, beta_t, wg, gvec[idx])
            c_ww, ok = inv_sym3(h)
            ok &= np.isfinite(w_hat).all(1)
            ej = (w_hat @ geo.EC).reshape(-1, 6, 3)  # E Jq(omega): Jq is linear in omega
            with np.errstate(invalid="ignore", over="ignore"):  # rows with ok == False are dropped below
                c_pw = -ej @ c_ww
                c_pp = geo.Fpp_inv - c_pw @ np.ascontiguousarray(np.swapaxes(ej, 1, 2))  # contiguous: 10x faster
            q = quadratic_monomials(w_hat)
            ph = phi_lin - q @ geo.E.T
            if not ok.all():
                idx = np.arange(n)[idx][ok]
                w_hat, ph, c_ww, c_pw, c_pp, it, cv = (a[ok] for a in (w_hat, ph, c_ww, c_pw, c_pp, it, cv))
            omega[idx], phi[idx], iters[idx], conv[idx] = w_hat, ph, it, cv
            good[idx] = True
            # covariance blocks written in place (no (n, 9, 9) temporary: its first touch costs page faults);
            # idx is slice(None) or an index array, both index cov the same way
            cov[idx, :3, :3] = c_ww
            cov[idx, 3:, :3] = c_pw
            cov[idx, :3, 3:] = np.swapaxes(c_pw, 1, 2)
            cov[idx, 3:, 3:] = c_pp

        stats.fused = int(np.count_nonzero(good))
        stats.skipped_unidentifiable = n - stats.fused
        stats.not_converged = int(np.count_nonzero(good & ~conv))
        if stats.skipped_unidentifiable:
            stats.skipped_stamps = np.asarray(stamps)[~good][:_MAX_SKIPPED_STAMPS].tolist()
        if stats.fused == n:
            fused = FusedSamples(np.asarray(stamps, dtype=np.int64), omega, phi[:, :3], phi[:, 3:], cov, iters, conv)
        else:
            fused = FusedSamples(
                stamps=np.asarray(stamps, dtype=np.int64)[good],
                omega=omega[good],
                omega_dot=phi[good, :3],
                specific_force=phi[good, 3:],
                covariance=cov[good],
                iterations=iters[good],
                converged=conv[good],
            )
        return fused, stats

    # ------------------------------------------------------------------ solver

    def _gauss_newton(self, omega0, geo: "_PatternGeometry", beta_t, Wg, g):
        """Gauss-Newton with step halving on the concentrated cost (skog2016 eq. 12-13).

        Uses that Jq(omega) is linear in omega, so the Gauss-Newton matrix
        ``Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3)`` with a constant T (6 x 9),
        and ``Jq^T v`` has a closed form.  ``Wg`` is (3, 3) shared or (n, 3, 3).
        Returns omega, iterations, converged, and the final Gauss-Newton matrix.
        """
        cfg = self.config
        Ft, T = geo.Ft, geo.T
        n = len(omega0)
        omega = omega0.copy()
        iters = np.zeros(n, dtype=np.int32)
        conv = np.zeros(n, dtype=bool)
        shared = Wg.ndim == 2

        def cost(w, q, bt, wg, gg):
            quad = np.einsum("ni,nij,nj->n", w, wg, w) if not shared else np.einsum("ni,ni->n", w @ wg, w)
            return np.einsum("ni,ni->n", q, q @ Ft - 2.0 * bt) + quad - 2.0 * np.einsum("ni,ni->n", w, gg)

        c_cur = cost(omega, quadratic_monomials(omega), beta_t, Wg, g)  # cost at the current iterate
        active = None  # None = all samples, else index array
        for it in range(cfg.max_iterations):
            if active is None:
                w, bt, wg, gg, c0 = omega, beta_t, Wg, g, c_cur
            else:
                if len(active) == 0:
                    break
                w, bt, gg, c0 = omega[active], beta_t[active], g[active], c_cur[active]
                wg = Wg if shared else Wg[active]
            q = quadratic_monomials(w)
            h = (q @ T).reshape(-1, 3, 3) + wg
            v = bt - q @ Ft
            rhs = _jq_transpose_times(w, v) + gg - (w @ wg if shared else np.einsum("nij,nj->ni", wg, w))
            step, ok = solve_sym3(h, rhs)
            new = w + step
            c1 = cost(new, quadratic_monomials(new), bt, wg, gg)
            worse = c1 > c0 + 1e-12 * np.abs(c0)
            t = 1.0
            for _ in range(8):  # backtracking: halve the step where the cost went up
                if not worse.any():
                    break
                t *= 0.5
                wi = np.flatnonzero(worse)
                cand = w[wi] + t * step[wi]
                cc = cost(cand, quadratic_monomials(cand), bt[wi], wg if shared else wg[wi], gg[wi])
                better = cc <= c0[wi] + 1e-12 * np.abs(c0[wi])
                new[wi[better]] = cand[better]
                c1[wi[better]] = cc[better]
                worse[wi[better]] = False
            if worse.any():
                new[worse] = w[worse]
                c1[worse] = c0[worse]
            size = np.abs(new - w).max(axis=1)
            done = (size <= cfg.tolerance * (1.0 + np.abs(new).max(axis=1))) | worse | ~ok
            if active is None:
                omega, c_cur = new, c1
                iters[:] = it + 1
                conv[done & ok] = True
                active = np.flatnonzero(~done)
            else:
                omega[active] = new
                c_cur[active] = c1
                iters[active] = it + 1
                conv[active[done & ok]] = True
                active = active[~done]
        q = quadratic_monomials(omega)
        h = (q @ T).reshape(-1, 3, 3) + Wg
        return omega, iters, conv, h


def _jq_transpose_times(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(dq/domega)^T v for (n, 3) omega and (n, 6) v, in closed form."""
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    return np.stack(
        [
            2 * x * v[:, 0] + y * v[:, 3] + z * v[:, 4],
            2 * y * v[:, 1] + x * v[:, 3] + z * v[:, 5],
            2 * z * v[:, 2] + x * v[:, 4] + y * v[:, 5],
        ],
        axis=1,
    )


def fuse(samples: ImuSamples, model: LinearArrayModel, config: FusionConfig | None = None) -> tuple[FusedSamples, FusionStats]:
    """Fuse a whole :class:`ImuSamples` batch with the ML estimator (see module docstring)."""
    if tuple(samples.names) != tuple(model.names):
        raise FusionError(
            f"fusion: samples are for IMUs {list(samples.names)[:4]}..., model for {list(model.names)[:4]}..."
        )
    return MLFusion(model, config).fuse(samples.stamps, samples.accel, samples.gyro)

