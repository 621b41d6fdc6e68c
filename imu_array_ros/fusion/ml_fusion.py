"""Maximum-likelihood fusion of an inertial sensor array (skog2016 Sec. II-III).

Model (skog2016 eq. 3-5, with the calibrated sensor frames of
:mod:`imu_array_ros.model.linear`): for accelerometer triad ``i``

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
only enters through the starting point.  Missing and saturated axes get zero
weight.  The geometry (``F~``, ``E``, ``F_pp^-1``) depends on which
accelerometer axes are valid: samples with the most common pattern share one
cached geometry; every other sample gets its own, stacked (M, ...) and used
by the same batched code, taken from a table of the patterns with up to two
whole IMUs missing or built by batched products (a Cholesky of the 6x6
``F_pp`` written out over all samples at once).  So the cost does not grow
with the number of distinct patterns, and there is no per-sample or
per-pattern Python loop.

This module holds :class:`FusionConfig`, :class:`FusionStats`, :class:`MLFusion`
(valid axes of each sample, ``beta`` and the gyro terms, grouping by pattern
with its geometry cache, estimate and blockwise CRB) and :func:`fuse`.  It
builds on :mod:`~imu_array_ros.fusion.validity` (sums over the valid axes,
invalid entries, patterns), :mod:`~imu_array_ros.fusion.pattern_geometry`
(``F~``, ``E``, ``F_pp^-1`` per pattern), :mod:`~imu_array_ros.fusion.gauss_newton`
(the solver) and :mod:`~imu_array_ros.fusion.batched_linalg` (batched 3x3
and 6x6 inverses).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields

import numpy as np

from imu_array_ros.fusion.batched_linalg import BLOCK, inv_sym3, row_times, solve_sym3, take_rows
from imu_array_ros.fusion.gauss_newton import gauss_newton, gauss_newton_one
from imu_array_ros.fusion.pattern_geometry import (
    Geometry,
    dropout_masks,
    dropout_table,
    shared_geometry,
    stacked_geometry,
)
from imu_array_ros.fusion.validity import Invalid, masked_product, pattern_summary, weight_sum
from imu_array_ros.model.identifiability import check_identifiable
from imu_array_ros.errors import FusionError
from imu_array_ros.model.kinematics import quadratic_monomials
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.linear import LinearArrayModel

__all__ = ["FusionConfig", "FusionStats", "MLFusion", "fuse"]

log = logging.getLogger(__name__)

_MAX_SKIPPED_STAMPS = 10  # stamps of skipped samples kept for the user


@dataclass(frozen=True)
class FusionConfig:
    """Tuning of the Gauss-Newton solver.

    max_iterations: Gauss-Newton iterations per sample.
    tolerance: stop when the step is below ``tolerance * (1 + |omega|)`` rad/s.

    Which readings are saturated is the model's rule (its clip levels, from the
    description; :meth:`LinearArrayModel.acc_unsaturated`), not a tuning knob.
    """

    max_iterations: int = 30
    tolerance: float = 1e-10


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


# --------------------------------------------------------------------------- covariance (Cramér-Rao bound)


def _covariance(out: np.ndarray, c_ww: np.ndarray, ej: np.ndarray, fpp_inv: np.ndarray) -> np.ndarray:
    """Write the (n, 9, 9) inverse Fisher information into ``out`` blockwise (skog2016 eq. 20, 27).

    c_ww (n, 3, 3) = (Jq^T F~ Jq + W_g)^-1, ej (n, 6, 3) = E Jq(omega), fpp_inv
    (6, 6) or (n, 6, 6): ``C_pw = -E Jq C_ww``, ``C_pp = F_pp^-1 - C_pw (E Jq)^T``.
    """
    with np.errstate(invalid="ignore", over="ignore"):  # rows of non-identifiable samples are dropped later
        out[:, :3, :3] = c_ww
        c_pw = out[:, 3:, :3]
        np.matmul(ej, c_ww, out=c_pw)
        np.negative(c_pw, out=c_pw)
        out[:, :3, 3:] = np.swapaxes(c_pw, 1, 2)
        c_pp = out[:, 3:, 3:]
        np.matmul(c_pw, np.ascontiguousarray(np.swapaxes(ej, 1, 2)), out=c_pp)  # contiguous: 10x faster
        np.subtract(fpp_inv, c_pp, out=c_pp)
    return out


_CHUNK = 8192  # samples per call of MLFusion._solve


class MLFusion:
    """ML fusion for one array model; caches the geometry of common patterns.

    Use :meth:`fuse` on batches (the CLI and the node call the same method; a
    single sample is a batch of one).  Angular quantities in rad/s and rad/s^2,
    specific force in m/s^2, all in the array frame.
    """

    def __init__(self, model: LinearArrayModel, config: FusionConfig | None = None) -> None:
        self.model = model
        self.config = config or FusionConfig()
        check_identifiable(model.positions, model.n_imus, where=f"array {model.frame_id!r}")
        k = model.n_imus
        self._D = np.ascontiguousarray(model.acc_design.reshape(3 * k, 12))  # sensor axes x z (exact per-axis lever arms)
        self._w_acc = (1.0 / model.acc_std**2).reshape(3 * k)
        self._WD = self._w_acc[:, None] * self._D  # (3K, 12): beta = (y - b) @ WD over valid axes
        # F = D^T W D of one sensor axis (3K, 144) and of one whole IMU (K, 144): F of any pattern is a sum of these
        self._F_axis = (self._w_acc[:, None, None] * self._D[:, :, None] * self._D[:, None, :]).reshape(3 * k, 144)
        self._F_imu = self._F_axis.reshape(k, 3, 144).sum(axis=1)
        self._V = model.gyro_matrix.reshape(3 * k, 3)  # gyro axis rows (sensor <- array)
        self._w_gyr = (1.0 / model.gyro_std**2).reshape(3 * k)
        self._WV = self._w_gyr[:, None] * self._V  # (3K, 3): g = (y - c) @ WV over valid axes
        self._Wg_axis = (self._w_gyr[:, None, None] * self._V[:, :, None] * self._V[:, None, :]).reshape(3 * k, 9)
        self._Wg_imu = self._Wg_axis.reshape(k, 3, 9).sum(axis=1)
        self._acc_bias = model.acc_bias.reshape(3 * k)
        self._gyr_bias = model.gyro_bias.reshape(3 * k)
        self._cache: dict[bytes, Geometry] = {}
        # patterns with up to two whole IMUs missing (one for arrays of more than 64 IMUs), see _dropout_table
        self._depth = 2 if k <= 64 else 1
        self._table_masks = dropout_masks(k, self._depth)  # (P, 3K)
        self._table: tuple[np.ndarray, Geometry] | None = None

    # ------------------------------------------------------------------ geometry

    def _geometry(self, mask: np.ndarray) -> Geometry:
        """Shared geometry of the pattern ``mask`` (3K,) bool of valid accelerometer axes (cached)."""
        key = np.packbits(mask).tobytes()
        geo = self._cache.get(key)
        if geo is not None:
            return geo
        geo = shared_geometry(self._D, self._w_acc, mask)
        if len(self._cache) < 64:
            self._cache[key] = geo
        return geo

    def _dropout_table(self) -> tuple[np.ndarray, Geometry]:
        """Per-sample geometry of the patterns ``self._table_masks`` (P, 3K), stacked (built once, in one batch).

        Rows: all IMUs valid (0); all but IMU i (1 + i); all but IMUs i < j
        (1 + K + pair index, see :func:`dropout_masks`).  Returns
        (ok (P,) bool, geometry (P, ...)); rows that are not identifiable are NaN.
        """
        if self._table is None:
            self._table = dropout_table(self._table_masks, self._F_imu, self._F_axis)
        return self._table

    # ------------------------------------------------------------------ public API

    def fuse(self, samples: ImuSamples) -> tuple[FusedSamples, FusionStats]:
        """Fuse N array samples.

        ``samples``: stamps (N,) int64 ns; accel, gyro (N, K, 3) raw readings in each IMU's
        sensor frame (m/s^2, rad/s), NaN where not available.  Returns the fused
        samples that were identifiable (others are skipped and counted in the stats).

        Samples with the most common pattern of valid accelerometer axes share
        one cached geometry.  All others get their own geometry, taken from a
        precomputed table when up to two whole IMUs are missing
        (:meth:`_dropout_table`) and built in one batch otherwise
        (:func:`~imu_array_ros.fusion.pattern_geometry.stacked_geometry`),
        so the cost does not grow with the number of distinct patterns (IMU
        dropouts, saturation).
        """
        m = self.model
        stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
        n, k = accel.shape[0], m.n_imus
        if accel.shape != (n, k, 3) or gyro.shape != (n, k, 3):
            raise FusionError(f"fusion: expected accel/gyro of shape (N, {k}, 3), got {accel.shape} / {gyro.shape}")
        stats = FusionStats(samples=n)
        ya = accel.reshape(n, 3 * k)
        yg = gyro.reshape(n, 3 * k)
        # one comparison pass each: NaN (missing) and saturated readings are both invalid
        acc_valid = m.acc_unsaturated(ya)
        gyr_valid = m.gyro_unsaturated(yg)
        incomplete = np.zeros(n, dtype=bool)

        # accelerometers: every sample enters through beta = D^T W (y - b) (12), zero weight on invalid axes
        inv_a = None
        if acc_valid.all():
            rows_a = np.empty(0, dtype=np.intp)  # samples with an invalid accelerometer axis
            beta = ya @ self._WD - self._acc_bias @ self._WD
        else:
            bad_a = ~acc_valid
            inv_a = Invalid.of(ya, bad_a)
            rows_a, incomplete = inv_a.rows, inv_a.missing.copy()
            stats.saturated_accel_samples = int(np.count_nonzero(inv_a.saturated))
            beta = masked_product(ya, bad_a, self._acc_bias, self._WD, inv_a.missing, dense=inv_a.flat is None)

        # gyroscopes: Wg = B^T W_g B (3, 3) and g = B^T W_g (y - c) over the valid axes
        Wg = self._Wg_imu.sum(axis=0).reshape(3, 3)  # all axes valid: the same for every sample
        Wg_rows = None  # per-sample Wg (n, 3, 3) when some sample has an invalid gyro axis
        gyr_all = np.ones(n, dtype=bool)  # samples with every gyro axis valid
        if gyr_valid.all():
            gvec = yg @ self._WV - self._gyr_bias @ self._WV
            omega0, ok0 = solve_sym3(np.broadcast_to(Wg, (n, 3, 3)), gvec)
        else:
            # the same invalid entries as the accelerometers (whole IMUs dropped): reuse their analysis
            same = (inv_a is not None and inv_a.flat is not None
                    and gyr_valid.size - np.count_nonzero(gyr_valid) == len(inv_a.flat)
                    and not np.take(gyr_valid, inv_a.flat).any())
            bad_g = bad_a if same else ~gyr_valid
            inv_g = Invalid.of(yg, bad_g, like=inv_a if same else None)
            rows_g = inv_g.rows
            gyr_all[rows_g] = False
            stats.saturated_gyro_samples = int(np.count_nonzero(inv_g.saturated))
            incomplete |= inv_g.missing
            gvec = masked_product(yg, bad_g, self._gyr_bias, self._WV, inv_g.missing, dense=inv_g.flat is None)
            omega0, ok0 = solve_sym3(np.broadcast_to(Wg, (n, 3, 3)), gvec)  # rows_g redone below
            # Wg summed over the valid IMUs (whole ones: an (R, K) product; partly valid ones axis by axis)
            if inv_g.partial.all():
                w0 = weight_sum(bad_g, self._Wg_axis, rows_g)
            else:
                w0 = (~inv_g.missing_imus(k)).astype(float) @ self._Wg_imu
                if inv_g.partial.any():
                    w0[inv_g.partial] = weight_sum(bad_g, self._Wg_axis, rows_g[inv_g.partial])
            w0 = w0.reshape(-1, 3, 3)
            Wg_rows = np.broadcast_to(Wg, (n, 3, 3)).copy()
            Wg_rows[rows_g] = w0
            # starting point: weighted mean of all present gyro readings; with saturated ones
            # included where there are any (they carry the sign of omega, skog2016 Sec. III)
            g0, sat = gvec[rows_g], inv_g.saturated[rows_g]
            if sat.any():
                si = rows_g[sat]
                absent = ~np.isfinite(yg)
                w0[sat] = weight_sum(absent, self._Wg_axis, si).reshape(-1, 3, 3)
                g0[sat] = masked_product(yg, absent, self._gyr_bias, self._WV, inv_g.missing, si, dense=False)
            omega0[rows_g], ok0[rows_g] = solve_sym3(w0, g0)
        stats.incomplete_samples = int(np.count_nonzero(incomplete))

        omega = np.full((n, 3), np.nan)
        phi = np.full((n, 6), np.nan)
        cov = np.empty((n, 9, 9))  # every row is either written below or dropped
        iters = np.zeros(n, dtype=np.int32)
        conv = np.zeros(n, dtype=bool)
        good = np.zeros(n, dtype=bool)

        # two groups: the most common pattern of valid accelerometer axes with its shared
        # geometry; all other samples with per-sample geometry, from the table of patterns
        # with up to two whole IMUs missing, else built
        groups = []
        if n and not rows_a.size:
            stats.patterns = 1
            geo = self._geometry(np.ones(3 * k, dtype=bool))
            if geo.ok:
                groups.append((geo, None, slice(None) if ok0.all() else np.flatnonzero(ok0)))  # no gyro start: skipped
        elif n:
            tix = np.zeros(n, dtype=np.intp)  # row of the pattern in self._table_masks, -1 if none; 0 = all valid
            tix[rows_a] = inv_a.table_index(k, self._depth)
            stats.patterns, mask, shared = pattern_summary(acc_valid, tix, self._table_masks)
            geo = self._geometry(mask)
            idx = np.flatnonzero(shared & ok0)
            if geo.ok and idx.size:
                groups.append((geo, None, idx))
            idx = np.flatnonzero(~shared & ok0)
            if idx.size:  # per-sample geometry: rows of the table, else built (appended to a copy of the table)
                t_ok, table = self._dropout_table()
                tix = tix[idx]
                built = np.flatnonzero(tix < 0)
                if built.size:
                    # geo: the kept (identifiable) rows
                    geo, keep = stacked_geometry(acc_valid[idx[built]], self._F_imu, self._F_axis)
                    p = len(t_ok)
                    table = Geometry(True, np.concatenate([table.TF, geo.TF]), np.concatenate([table.EF, geo.EF]))
                    t_ok = np.concatenate([t_ok, np.ones(len(keep), dtype=bool)])
                    tix[built] = -1
                    tix[built[keep]] = p + np.arange(len(keep))
                use = tix >= 0
                use[use] = t_ok[tix[use]]
                if use.any():
                    groups.append((table, tix[use], idx[use]))

        # each group: geometry (shared, or per sample with its rows ``src``, default in order) and samples
        out = (omega, phi, iters, conv, good, cov)
        for geo, src, idx in groups:  # in chunks of samples, so that the solver's temporaries stay in cache
            m_g = n if isinstance(idx, slice) else len(idx)
            for lo in range(0, m_g, _CHUNK):
                hi = min(lo + _CHUNK, m_g)
                rows = slice(lo, hi) if isinstance(idx, slice) else idx[lo:hi]
                part = geo.part(slice(lo, hi) if src is None else src[lo:hi])
                wg = Wg if Wg_rows is None or gyr_all[rows].all() else Wg_rows[rows]  # shared where possible
                self._solve(part, rows, beta[rows], omega0[rows], gvec[rows], wg, out)

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

    def _solve(self, geo: Geometry, rows, beta, omega0, gvec, wg, out) -> None:
        """Estimate and covariance of the samples ``rows`` (a slice or indices), written into ``out``.

        geo: their geometry (shared, or per sample (m, ...)); beta (m, 12), omega0
        (m, 3) starting points, gvec (m, 3), wg (3, 3) or (m, 3, 3); out = (omega,
        phi, iters, conv, good, cov), the (N, ...) outputs of :meth:`fuse`.
        """
        omega, phi, iters, conv, good, cov = out
        ef = row_times(beta[:, 6:], geo.EF)
        beta_t = beta[:, :6] - ef[:, :6]
        phi_lin = ef[:, 6:]
        cfg = self.config
        one = len(omega0) == 1 and geo.TF.ndim == 2 and wg.ndim == 2  # a live sample: in Python floats
        w_hat, it, cv, h = (gauss_newton_one if one else gauss_newton)(
            omega0, geo.TF, beta_t, wg, gvec, max_iterations=cfg.max_iterations, tolerance=cfg.tolerance)
        c_ww, ok = inv_sym3(h)
        ok &= np.isfinite(w_hat).all(1)
        ej = geo.e_jq(w_hat)
        q = quadratic_monomials(w_hat)
        ph = phi_lin - (q @ geo.E.T if geo.E.ndim == 2 else (geo.E @ q[:, :, None])[:, :, 0])
        fpp_inv = geo.Fpp_inv
        if not ok.all():
            rows = np.arange(len(omega))[rows][ok]
            w_hat, ph, c_ww, ej, it, cv = (a[ok] for a in (w_hat, ph, c_ww, ej, it, cv))
            fpp_inv = take_rows(fpp_inv, ok)
        omega[rows], phi[rows], iters[rows], conv[rows] = w_hat, ph, it, cv
        good[rows] = True
        # covariance in blocks of rows that stay in cache: in place for a slice of samples,
        # else through a small block and one scatter of whole rows per block
        m = len(c_ww)
        block = None if isinstance(rows, slice) else np.empty((min(m, BLOCK), 9, 9))
        for lo in range(0, m, BLOCK):
            hi = min(lo + BLOCK, m)
            part = (c_ww[lo:hi], ej[lo:hi], take_rows(fpp_inv, slice(lo, hi)))
            if block is None:
                _covariance(cov[rows.start + lo:rows.start + hi], *part)
            else:
                cov[rows[lo:hi]] = _covariance(block[:hi - lo], *part)


def fuse(samples: ImuSamples, model: LinearArrayModel, config: FusionConfig | None = None) -> tuple[FusedSamples, FusionStats]:
    """Fuse a whole :class:`ImuSamples` batch with the ML estimator (see module docstring)."""
    if tuple(samples.names) != tuple(model.names):
        raise FusionError(
            f"fusion: samples are for IMUs {list(samples.names)[:4]}..., model for {list(model.names)[:4]}..."
        )
    return MLFusion(model, config).fuse(samples)

