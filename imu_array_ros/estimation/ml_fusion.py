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
only enters through the starting point.  Missing and saturated axes get zero
weight.  The geometry (``F~``, ``E``, ``F_pp^-1``) depends on which
accelerometer axes are valid: samples with the most common pattern share one
cached geometry; every other sample gets its own, stacked (M, ...) and used
by the same batched code, taken from a table of the patterns with up to two
whole IMUs missing or built by batched products (a Cholesky of the 6x6
``F_pp`` written out over all samples at once).  So the cost does not grow
with the number of distinct patterns, and there is no per-sample or
per-pattern Python loop.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields, replace

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from imu_array_ros.model.identifiability import check_identifiable
from imu_array_ros.errors import FusionError
from imu_array_ros.model.kinematics import centripetal_matrix, euler_matrix, quadratic_monomials, quadratic_monomials_jacobian
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.sensor_model import LinearArrayModel

__all__ = ["FusionConfig", "FusionStats", "MLFusion", "fuse", "inv_sym3", "solve_sym3"]

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



def _linear_map(fn) -> np.ndarray:
    """L (36, p) of a linear map on 6x6 matrices: ``fn(X).ravel() == X.ravel() @ L``."""
    return np.stack([np.ravel(fn(b)) for b in np.eye(36).reshape(36, 6, 6)])


#: T of many F~ at once: ``T = F~.reshape(M, 36) @ _T_MAP`` -> (M, 54) = (M, 6, 9)
_T_MAP = _linear_map(_gn_matrix_coefficients)

#: F_pp scaled to unit diagonal must have a condition number below this (else: not identifiable)
_MAX_COND = 1e10


@dataclass(frozen=True)
class _Geometry:
    """Precomputed matrices of the accelerometer part, for one pattern of valid axes.

    Shared by a group of samples (shapes as commented) or per sample (the same
    arrays stacked, with a leading (M,) axis).
    """

    ok: bool
    TF: np.ndarray | None = None  # (6, 15) [T | F~]: Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3), F~ (6, 6)
    EF: np.ndarray | None = None  # (6, 12) [E | F_pp^-1], E = F_pp^-1 F_pq
    EC: np.ndarray | None = None  # (3, 18): E Jq(omega) = (omega @ EC).reshape(6, 3); None per sample

    def part(self, rows) -> "_Geometry":
        """Itself if shared, else the per-sample geometry of ``rows`` (a slice: views; indices: a copy)."""
        return self if self.EC is not None else _Geometry(True, self.TF[rows], self.EF[rows])

    @property
    def E(self) -> np.ndarray:
        return self.EF[..., :6]

    @property
    def Fpp_inv(self) -> np.ndarray:
        return self.EF[..., 6:]


#: Jq(omega) = (omega @ _JQ_FLAT).reshape(6, 3)
_JQ_FLAT = _JQ_BASIS.reshape(3, 18)


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


def _times(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Row vectors times matrices: x (n, i) @ a, with a (i, j) shared or (n, i, j) per row -> (n, j)."""
    if a.ndim == 2:
        return x @ a
    return np.matmul(x[:, None, :], a)[:, 0]


def _rows(a: np.ndarray, idx) -> np.ndarray:
    """``a`` itself if shared (2-D), else its rows ``idx``."""
    return a if a.ndim == 2 else a[idx]


def _inv_spd6(fpp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of M symmetric 6x6 matrices F_pp (M, 6, 6) and which of them are identifiable.

    Cholesky ``F_pp = L L^T`` and ``F_pp^-1 = L^-T L^-1`` written out entry by
    entry, each entry a length-M vector (loops over the 6 rows and columns only).
    Identifiable means what :meth:`MLFusion._geometry` tests: positive diagonal
    and ``cond(Fn) < 1e10`` for ``Fn`` = F_pp scaled to unit diagonal.  That is
    decided from ``max diag(Fn^-1) <= cond(Fn) <= 6 trace(Fn^-1)`` (the largest
    eigenvalue of Fn lies in [1, 6], the smallest in [1/trace(Fn^-1), 1/max diag(Fn^-1)]);
    only samples between the bounds get an exact (SVD) condition number.
    Returns ``(inverse (M, 6, 6), ok (M,) bool)``; the inverse is garbage where not ok.
    """
    a = np.ascontiguousarray(np.moveaxis(fpp, 0, -1))  # (6, 6, M): each entry contiguous over samples
    ok = np.ones(a.shape[-1], dtype=bool)
    lo = [[None] * 6 for _ in range(6)]  # L
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for j in range(6):
            piv = a[j, j] - sum(lo[j][k] * lo[j][k] for k in range(j)) if j else a[j, j].copy()
            ok &= piv > 0
            lo[j][j] = np.sqrt(np.where(piv > 0, piv, 1.0))
            rd = 1.0 / lo[j][j]
            for i in range(j + 1, 6):
                lo[i][j] = (a[i, j] - sum(lo[i][k] * lo[j][k] for k in range(j)) if j else a[i, j]) * rd
        ni = [[None] * 6 for _ in range(6)]  # N = L^-1, lower triangular
        for i in range(6):
            ni[i][i] = 1.0 / lo[i][i]
            for j in range(i):
                ni[i][j] = -sum(lo[i][k] * ni[k][j] for k in range(j, i)) * ni[i][i]
        inv = np.empty((6, 6) + a.shape[2:])
        for i in range(6):
            for j in range(i + 1):
                inv[i, j] = inv[j, i] = sum(ni[k][i] * ni[k][j] for k in range(i, 6))
        d = np.stack([a[i, i] for i in range(6)])  # (6, M)
        inv_n = np.stack([inv[i, i] for i in range(6)]) * d  # diagonal of Fn^-1
        ok &= (d > 0).all(axis=0) & np.isfinite(inv_n).all(axis=0) & (inv_n > 0).all(axis=0)
        lower, upper = inv_n.max(axis=0), 6.0 * inv_n.sum(axis=0)
    unsure = np.flatnonzero(ok & (upper >= _MAX_COND) & (lower < _MAX_COND))
    ok &= lower < _MAX_COND
    if unsure.size:
        scale = np.sqrt(d[:, unsure].T)
        ok[unsure] = np.linalg.cond(fpp[unsure] / (scale[:, :, None] * scale[:, None, :])) < _MAX_COND
    return np.ascontiguousarray(np.moveaxis(inv, -1, 0)), ok


def _valid_sum(valid: np.ndarray, per_imu: np.ndarray, per_axis: np.ndarray) -> np.ndarray:
    """Sum over the valid axes of per-axis terms: (M, 3K) bool -> (M, p).

    ``per_axis`` (3K, p) holds each axis' term, ``per_imu`` (K, p) the sum over
    an IMU's three axes; whole IMUs (the common case) go through the (M, K)
    product, partly valid IMUs (a saturated or missing single axis) add their
    axes one by one.
    """
    m, k = valid.shape[0], per_imu.shape[0]
    v3 = valid.reshape(m, k, 3)
    whole = v3[:, :, 0] & v3[:, :, 1] & v3[:, :, 2]  # (much faster than .all(axis=2))
    out = whole.astype(float) @ per_imu
    part = np.flatnonzero(((v3[:, :, 0] | v3[:, :, 1] | v3[:, :, 2]) & ~whole).any(axis=1))
    if 2 * part.size > m:  # mostly partly valid IMUs (e.g. saturated single axes): axis by axis for all
        return valid.astype(float) @ per_axis
    if part.size:
        out[part] += (v3[part] & ~whole[part, :, None]).reshape(len(part), 3 * k).astype(float) @ per_axis
    return out


_BLOCK = 512  # rows per block of :func:`_masked_product` and the covariance (their buffers stay in cache)
_CHUNK = 8192  # samples per call of MLFusion._solve


def _masked_product(y: np.ndarray, invalid: np.ndarray, bias: np.ndarray, mat: np.ndarray,
                    nonfinite: np.ndarray, rows: np.ndarray | None = None, dense: bool = True) -> np.ndarray:
    """``sum over the valid axes a of (y_a - bias_a) mat[a]`` for every sample, or for the samples ``rows``.

    y (n, a) raw readings, invalid (n, a) bool (every non-finite reading is
    invalid), bias (a,), mat (a, p), nonfinite (n,) bool: samples with a
    non-finite reading -> (n, p) or (len(rows), p).  Works through blocks of
    rows in reused buffers (in cache), with ``y`` set to the bias on the invalid
    axes; when ``dense`` (many invalid axes, e.g. saturated gyros) as
    ``(y - bias) * valid`` instead in blocks without non-finite readings (NaN *
    0 is NaN), which is branch-free and faster there.
    """
    n = y.shape[0] if rows is None else len(rows)
    out = np.empty((n, mat.shape[1]))
    shape = (min(n, _BLOCK), y.shape[1])
    buf, bad, keep = np.empty(shape), np.empty(shape, dtype=bool), np.empty(shape)
    bias_mat = bias @ mat
    for lo in range(0, n, _BLOCK):
        hi = min(lo + _BLOCK, n)
        b = buf[:hi - lo]
        if rows is None:
            np.copyto(b, y[lo:hi])
            m = invalid[lo:hi]
            clean = dense and not nonfinite[lo:hi].any()
        else:  # mode="clip": the indices are valid, and "raise" would buffer
            np.take(y, rows[lo:hi], axis=0, out=b, mode="clip")
            m = np.take(invalid, rows[lo:hi], axis=0, out=bad[:hi - lo], mode="clip")
            clean = dense and not nonfinite[rows[lo:hi]].any()
        if clean:
            b -= bias
            np.logical_not(m, out=bad[:hi - lo])
            np.copyto(keep[:hi - lo], bad[:hi - lo])
            b *= keep[:hi - lo]
            np.matmul(b, mat, out=out[lo:hi])
        else:
            np.copyto(b, bias, where=m)
            np.matmul(b, mat, out=out[lo:hi])
            out[lo:hi] -= bias_mat
    return out


def _weight_sum(invalid: np.ndarray, per_axis: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``sum over the valid axes a of per_axis[a]`` for the samples ``rows``: (R, p), invalid (n, a) bool."""
    n = len(rows)
    out = np.empty((n, per_axis.shape[1]))
    shape = (min(n, _BLOCK), invalid.shape[1])
    bad, keep = np.empty(shape, dtype=bool), np.empty(shape)
    for lo in range(0, n, _BLOCK):
        hi = min(lo + _BLOCK, n)
        m = bad[:hi - lo]
        np.take(invalid, rows[lo:hi], axis=0, out=m, mode="clip")
        np.logical_not(m, out=m)
        np.copyto(keep[:hi - lo], m)
        np.matmul(keep[:hi - lo], per_axis, out=out[lo:hi])
    return out


_SPARSE = 0.1  # share of invalid entries up to which _Invalid works entry by entry


@dataclass(frozen=True)
class _Invalid:
    """The invalid entries of an (n, 3K) array of readings, grouped by sample and IMU.

    rows (R,): sorted samples with an invalid axis; saturated, missing (n,) bool:
    some axis finite but invalid / not finite; per run of invalid axes of one
    IMU in one sample: ``run_pos`` (index into rows), ``run_imu``; ``first_run``
    (R,): each row's first run; ``partial`` (R,) bool: some IMU of that sample
    has only one or two invalid axes (else only whole IMUs are invalid).  With
    more than ``_SPARSE`` of all entries invalid, the runs are not worked out
    (every row counts as ``partial``, ``flat`` is None).
    """

    rows: np.ndarray
    saturated: np.ndarray
    missing: np.ndarray
    run_pos: np.ndarray
    run_imu: np.ndarray
    first_run: np.ndarray
    partial: np.ndarray
    flat: np.ndarray | None  # flat indices of the invalid entries

    @classmethod
    def of(cls, y: np.ndarray, invalid: np.ndarray, like: "_Invalid | None" = None) -> "_Invalid":
        """From y (n, 3K) raw readings and invalid (n, 3K) bool; works on the (few) invalid entries only.

        ``like``: the analysis of another array with the same invalid entries
        (accelerometers and gyroscopes of dropped IMUs): only the flags are redone.
        """
        n, a = invalid.shape
        if like is None and np.count_nonzero(invalid) > _SPARSE * invalid.size:  # e.g. most gyros saturated
            present = np.isfinite(y)
            rows = np.flatnonzero(invalid.any(axis=1))
            saturated = (present & invalid).any(axis=1)
            missing = ~present.all(axis=1)
            empty = np.empty(0, dtype=np.intp)
            return cls(rows, saturated, missing, empty, empty, np.zeros(len(rows), dtype=np.intp),
                       np.ones(len(rows), dtype=bool), None)
        flat = np.flatnonzero(invalid) if like is None else like.flat
        row = flat // a
        finite = np.isfinite(np.take(y, flat))
        saturated = np.zeros(n, dtype=bool)
        saturated[row[finite]] = True
        missing = np.zeros(n, dtype=bool)
        missing[row[~finite]] = True
        if like is not None:
            return replace(like, saturated=saturated, missing=missing)
        imu = (flat - row * a) // 3
        key = row * (a // 3) + imu  # sorted, like flat
        starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
        whole = np.diff(np.append(starts, len(key))) == 3
        run_row = row[starts]
        new_row = np.concatenate([[True], run_row[1:] != run_row[:-1]])
        run_pos = np.cumsum(new_row) - 1
        first_run = np.flatnonzero(new_row)
        partial = np.zeros(len(first_run), dtype=bool)
        partial[run_pos[~whole]] = True
        return cls(run_row[first_run], saturated, missing, run_pos, imu[starts], first_run, partial, flat)

    def missing_imus(self, k: int) -> np.ndarray:
        """(R, K) bool: IMUs with invalid axes, per row (all three of them where not ``partial``)."""
        out = np.zeros((len(self.rows), k), dtype=bool)
        out[self.run_pos, self.run_imu] = True
        return out

    def table_index(self, k: int, depth: int) -> np.ndarray:
        """(R,) row of :meth:`MLFusion._dropout_table` for each sample: 1 + i for IMU i missing,
        1 + K + pair index for IMUs i < j; -1 with partly invalid IMUs or more than ``depth`` missing."""
        if self.flat is None:
            return np.full(len(self.rows), -1)
        count = np.diff(np.append(self.first_run, len(self.run_imu)))
        first = self.run_imu[self.first_run]
        last = self.run_imu[self.first_run + count - 1]
        pair = first * (2 * k - first - 1) // 2 + (last - first - 1)
        index = np.where(count == 1, 1 + first, 1 + k + pair)
        return np.where(~self.partial & (count <= depth), index, -1)


def _distinct_rows(valid: np.ndarray) -> tuple[int, int, int]:
    """Distinct rows of ``valid`` (m, a) bool, m >= 1: their number, the most common one's count and a row index of it.

    One sort of the bit-packed rows (no loop over patterns).
    """
    m = len(valid)
    packed = np.packbits(valid, axis=1)
    pad = (-packed.shape[1]) % 8
    if pad:
        packed = np.concatenate([packed, np.zeros((m, pad), np.uint8)], axis=1)
    words = np.ascontiguousarray(packed).view(np.uint64)  # (m, w)
    order = np.lexsort(words.T[::-1])
    sw = words[order]
    first = np.ones(m, dtype=bool)
    first[1:] = (sw[1:] != sw[:-1]).any(axis=1)
    starts = np.flatnonzero(first)
    runs = np.diff(np.append(starts, m))
    top = int(np.argmax(runs))
    return len(starts), int(runs[top]), int(order[starts[top]])


def _pattern_summary(valid: np.ndarray, tix: np.ndarray, table_masks: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """Patterns of valid accelerometer axes and the most common one.

    valid (n, a) bool; tix (n,) the row of ``table_masks`` (P, a) that each
    sample's pattern equals, or -1.  Returns the number of distinct patterns,
    the most common pattern (a,) bool and (n,) bool which samples have it.
    Counting is by table row (``bincount``) plus one sort of the other rows'
    bit-packed patterns (:func:`_distinct_rows`): no loop over patterns.
    """
    in_table = tix >= 0
    counts = np.bincount(tix[in_table], minlength=len(table_masks))
    best = int(np.argmax(counts))
    patterns = int(np.count_nonzero(counts))
    rest = np.flatnonzero(~in_table)
    if rest.size:
        d, run, row = _distinct_rows(valid[rest])
        patterns += d
        if run > counts[best]:
            mask = valid[rest[row]]
            return patterns, mask, (valid == mask).all(axis=1)
    return patterns, table_masks[best], tix == best


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
        r = model.positions
        d = np.concatenate([centripetal_matrix(r), euler_matrix(r), np.broadcast_to(np.eye(3), (k, 3, 3))], axis=2)
        self._D = np.einsum("kij,kjl->kil", model.acc_matrix, d).reshape(3 * k, 12)  # sensor axes x z
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
        self._cache: dict[bytes, _Geometry] = {}
        # patterns with up to two whole IMUs missing (one for arrays of more than 64 IMUs), see _dropout_table
        self._depth = 2 if k <= 64 else 1
        masks = [np.ones((1, k), dtype=bool), ~np.eye(k, dtype=bool)]
        if self._depth == 2:
            i, j = np.triu_indices(k, 1)
            pairs = np.ones((len(i), k), dtype=bool)
            pairs[np.arange(len(i)), i] = pairs[np.arange(len(i)), j] = False
            masks.append(pairs)
        self._table_masks = np.repeat(np.concatenate(masks), 3, axis=1)  # (P, 3K)
        self._table: tuple[np.ndarray, _Geometry] | None = None

    # ------------------------------------------------------------------ geometry

    def _geometry(self, mask: np.ndarray) -> _Geometry:
        """Shared geometry of the pattern ``mask`` (3K,) bool of valid accelerometer axes (cached)."""
        key = np.packbits(mask).tobytes()
        geo = self._cache.get(key)
        if geo is not None:
            return geo
        f = self._D.T @ ((self._w_acc * mask)[:, None] * self._D)
        fpp = f[6:, 6:]
        scale = np.sqrt(np.clip(np.diag(fpp), 0, None))
        geo = _Geometry(ok=False)
        if np.all(scale > 0):
            fn = fpp / np.outer(scale, scale)
            if np.linalg.cond(fn) < _MAX_COND:
                cf = cho_factor(fpp)
                e = cho_solve(cf, f[6:, :6])
                ft = f[:6, :6] - f[:6, 6:] @ e
                ft = 0.5 * (ft + ft.T)
                geo = _Geometry(
                    ok=True, TF=np.concatenate([_gn_matrix_coefficients(ft), ft], axis=1),
                    EF=np.concatenate([e, cho_solve(cf, np.eye(6))], axis=1),
                    EC=np.einsum("ij,mjk->mik", e, _JQ_BASIS).reshape(3, 18),
                )
        if len(self._cache) < 64:
            self._cache[key] = geo
        return geo

    def _sample_geometry(self, valid: np.ndarray) -> tuple[_Geometry, np.ndarray]:
        """Per-sample geometry of M samples from their own valid axes ``valid`` (M, 3K) bool.

        The matrices of :meth:`_geometry`, stacked: ``F = D^T W D`` with zero
        weight on invalid axes (:func:`_valid_sum`), ``F_pp`` inverted by a
        batched Cholesky (:func:`_inv_spd6`), everything else by batched
        products, so the cost is linear in M whatever the number of distinct
        patterns.  Returns the geometry of the identifiable samples and their
        row indices into ``valid``.
        """
        m = valid.shape[0]
        f = _valid_sum(valid, self._F_imu, self._F_axis).reshape(m, 12, 12)
        fpp_inv, ok = _inv_spd6(f[:, 6:, 6:])
        keep = np.flatnonzero(ok)
        if keep.size < m:
            f, fpp_inv = f[keep], fpp_inv[keep]
        e = fpp_inv @ f[:, 6:, :6]
        ft = f[:, :6, :6] - f[:, :6, 6:] @ e
        ft = 0.5 * (ft + np.swapaxes(ft, 1, 2))
        geo = _Geometry(
            ok=True, TF=np.concatenate([(ft.reshape(-1, 36) @ _T_MAP).reshape(-1, 6, 9), ft], axis=2),
            EF=np.concatenate([e, fpp_inv], axis=2),
        )
        return geo, keep

    def _dropout_table(self) -> tuple[np.ndarray, _Geometry]:
        """Per-sample geometry of the patterns ``self._table_masks`` (P, 3K), stacked (built once, in one batch).

        Rows: all IMUs valid (0); all but IMU i (1 + i); all but IMUs i < j
        (1 + K + pair index, see :meth:`_Invalid.table_index`).  Returns
        (ok (P,) bool, geometry (P, ...)); rows that are not identifiable are NaN.
        """
        if self._table is None:
            masks = self._table_masks
            geo, keep = self._sample_geometry(masks)
            ok = np.zeros(len(masks), dtype=bool)
            ok[keep] = True

            def full(a):
                out = np.full((len(masks),) + a.shape[1:], np.nan)
                out[keep] = a
                return out

            self._table = ok, _Geometry(True, full(geo.TF), full(geo.EF))
        return self._table

    # ------------------------------------------------------------------ public API

    def fuse(self, stamps: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> tuple[FusedSamples, FusionStats]:
        """Fuse N array samples.

        stamps (N,) int64 ns; accel, gyro (N, K, 3) raw readings in each IMU's
        sensor frame (m/s^2, rad/s), NaN where not available.  Returns the fused
        samples that were identifiable (others are skipped and counted in the stats).

        Samples with the most common pattern of valid accelerometer axes share
        one cached geometry.  All others get their own geometry, taken from a
        precomputed table when up to two whole IMUs are missing
        (:meth:`_dropout_table`) and built in one batch otherwise
        (:meth:`_sample_geometry`), so the cost does not grow with the number
        of distinct patterns (IMU dropouts, saturation).
        """
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
            inv_a = _Invalid.of(ya, bad_a)
            rows_a, incomplete = inv_a.rows, inv_a.missing.copy()
            stats.saturated_accel_samples = int(np.count_nonzero(inv_a.saturated))
            beta = _masked_product(ya, bad_a, self._acc_bias, self._WD, inv_a.missing, dense=inv_a.flat is None)

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
            inv_g = _Invalid.of(yg, bad_g, like=inv_a if same else None)
            rows_g = inv_g.rows
            gyr_all[rows_g] = False
            stats.saturated_gyro_samples = int(np.count_nonzero(inv_g.saturated))
            incomplete |= inv_g.missing
            gvec = _masked_product(yg, bad_g, self._gyr_bias, self._WV, inv_g.missing, dense=inv_g.flat is None)
            omega0, ok0 = solve_sym3(np.broadcast_to(Wg, (n, 3, 3)), gvec)  # rows_g redone below
            # Wg summed over the valid IMUs (whole ones: an (R, K) product; partly valid ones axis by axis)
            if inv_g.partial.all():
                w0 = _weight_sum(bad_g, self._Wg_axis, rows_g)
            else:
                w0 = (~inv_g.missing_imus(k)).astype(float) @ self._Wg_imu
                if inv_g.partial.any():
                    w0[inv_g.partial] = _weight_sum(bad_g, self._Wg_axis, rows_g[inv_g.partial])
            w0 = w0.reshape(-1, 3, 3)
            Wg_rows = np.broadcast_to(Wg, (n, 3, 3)).copy()
            Wg_rows[rows_g] = w0
            # starting point: weighted mean of all present gyro readings; with saturated ones
            # included where there are any (they carry the sign of omega, skog2016 Sec. III)
            g0, sat = gvec[rows_g], inv_g.saturated[rows_g]
            if sat.any():
                si = rows_g[sat]
                absent = ~np.isfinite(yg)
                w0[sat] = _weight_sum(absent, self._Wg_axis, si).reshape(-1, 3, 3)
                g0[sat] = _masked_product(yg, absent, self._gyr_bias, self._WV, inv_g.missing, si, dense=False)
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
            stats.patterns, mask, shared = _pattern_summary(acc_valid, tix, self._table_masks)
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
                    geo, keep = self._sample_geometry(acc_valid[idx[built]])  # geo: the kept (identifiable) rows
                    p = len(t_ok)
                    table = _Geometry(True, np.concatenate([table.TF, geo.TF]), np.concatenate([table.EF, geo.EF]))
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

    def _solve(self, geo: _Geometry, rows, beta, omega0, gvec, wg, out) -> None:
        """Estimate and covariance of the samples ``rows`` (a slice or indices), written into ``out``.

        geo: their geometry (shared, or per sample (m, ...)); beta (m, 12), omega0
        (m, 3) starting points, gvec (m, 3), wg (3, 3) or (m, 3, 3); out = (omega,
        phi, iters, conv, good, cov), the (N, ...) outputs of :meth:`fuse`.
        """
        omega, phi, iters, conv, good, cov = out
        ef = _times(beta[:, 6:], geo.EF)
        beta_t = beta[:, :6] - ef[:, :6]
        phi_lin = ef[:, 6:]
        w_hat, it, cv, h = self._gauss_newton(omega0, geo.TF, beta_t, wg, gvec)
        c_ww, ok = inv_sym3(h)
        ok &= np.isfinite(w_hat).all(1)
        if geo.EC is not None:
            ej = _times(w_hat, geo.EC).reshape(-1, 6, 3)  # E Jq(omega): Jq is linear in omega
        else:  # per sample: E times Jq(omega)
            ej = geo.E @ (w_hat @ _JQ_FLAT).reshape(-1, 6, 3)
        q = quadratic_monomials(w_hat)
        ph = phi_lin - (q @ geo.E.T if geo.E.ndim == 2 else (geo.E @ q[:, :, None])[:, :, 0])
        fpp_inv = geo.Fpp_inv
        if not ok.all():
            rows = np.arange(len(omega))[rows][ok]
            w_hat, ph, c_ww, ej, it, cv = (a[ok] for a in (w_hat, ph, c_ww, ej, it, cv))
            fpp_inv = _rows(fpp_inv, ok)
        omega[rows], phi[rows], iters[rows], conv[rows] = w_hat, ph, it, cv
        good[rows] = True
        # covariance in blocks of rows that stay in cache: in place for a slice of samples,
        # else through a small block and one scatter of whole rows per block
        m = len(c_ww)
        block = None if isinstance(rows, slice) else np.empty((min(m, _BLOCK), 9, 9))
        for lo in range(0, m, _BLOCK):
            hi = min(lo + _BLOCK, m)
            part = (c_ww[lo:hi], ej[lo:hi], _rows(fpp_inv, slice(lo, hi)))
            if block is None:
                _covariance(cov[rows.start + lo:rows.start + hi], *part)
            else:
                cov[rows[lo:hi]] = _covariance(block[:hi - lo], *part)

    def _gauss_newton(self, omega0, TF, beta_t, Wg, g):
        """Gauss-Newton with step halving on the concentrated cost (skog2016 eq. 12-13).

        Uses that Jq(omega) is linear in omega, so the Gauss-Newton matrix
        ``Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3)`` with T (6 x 9), and
        ``Jq^T v`` has a closed form.  ``TF = [T | F~]`` is (6, 15) shared or
        (n, 6, 15) per sample, so one product gives both T and F~ terms at a
        point; ``Wg`` is (3, 3) shared or (n, 3, 3).
        Returns omega, iterations, converged, and the final Gauss-Newton matrix.
        """
        cfg = self.config
        n = len(omega0)
        omega = omega0.copy()
        iters = np.zeros(n, dtype=np.int32)
        conv = np.zeros(n, dtype=bool)
        shared = Wg.ndim == 2
        # omega^T Wg omega = q(omega) . wq: the gyro terms fold into beta~ (bt = beta~ - wq / 2), so
        # J = q^T (F~ q - 2 bt) - 2 omega^T g and the Gauss-Newton right-hand side is Jq^T (bt - F~ q) + g
        wf = Wg.reshape(-1, 9)
        wq = np.stack([wf[:, 0], wf[:, 4], wf[:, 8], 2 * wf[:, 1], 2 * wf[:, 2], 2 * wf[:, 5]], axis=1)
        beta_t = beta_t - 0.5 * wq

        def cost(w, q, qf, bt, gg):  # qf = F~ q
            return np.einsum("ni,ni->n", q, qf - 2.0 * bt) - 2.0 * np.einsum("ni,ni->n", w, gg)

        q = quadratic_monomials(omega)
        hf = _times(q, TF)  # (n, 15): [Jq^T F~ Jq (9) | F~ q (6)] at the current iterate
        c_cur = cost(omega, q, hf[:, 9:], beta_t, g)
        active = None  # None = all samples, else index array
        for it in range(cfg.max_iterations):
            if active is None:
                w, qa, hfa, bt, wg, gg, c0, tf = omega, q, hf, beta_t, Wg, g, c_cur, TF
            else:
                if len(active) == 0:
                    break
                w, qa, hfa, bt, gg, c0 = omega[active], q[active], hf[active], beta_t[active], g[active], c_cur[active]
                wg = Wg if shared else Wg[active]
                tf = _rows(TF, active)
            h = hfa[:, :9].reshape(-1, 3, 3) + wg
            step, ok = solve_sym3(h, _jq_transpose_times(w, bt - hfa[:, 9:]) + gg)
            new = w + step
            qn = quadratic_monomials(new)
            hfn = _times(qn, tf)
            c1 = cost(new, qn, hfn[:, 9:], bt, gg)
            worse = c1 > c0 + 1e-12 * np.abs(c0)
            t = 1.0
            for _ in range(8):  # backtracking: halve the step where the cost went up
                if not worse.any():
                    break
                t *= 0.5
                wi = np.flatnonzero(worse)
                cand = w[wi] + t * step[wi]
                qc = quadratic_monomials(cand)
                hfc = _times(qc, _rows(tf, wi))
                cc = cost(cand, qc, hfc[:, 9:], bt[wi], gg[wi])
                better = cc <= c0[wi] + 1e-12 * np.abs(c0[wi])
                wb = wi[better]
                new[wb], qn[wb], hfn[wb], c1[wb] = cand[better], qc[better], hfc[better], cc[better]
                worse[wb] = False
            if worse.any():
                new[worse], qn[worse], hfn[worse], c1[worse] = w[worse], qa[worse], hfa[worse], c0[worse]
            size = np.abs(new - w).max(axis=1)
            done = (size <= cfg.tolerance * (1.0 + np.abs(new).max(axis=1))) | worse | ~ok
            if active is None:
                omega, q, hf, c_cur = new, qn, hfn, c1
                iters[:] = it + 1
                conv[done & ok] = True
                if done.any():
                    active = np.flatnonzero(~done)
            else:
                omega[active], q[active], hf[active], c_cur[active] = new, qn, hfn, c1
                iters[active] = it + 1
                conv[active[done & ok]] = True
                active = active[~done]
        return omega, iters, conv, hf[:, :9].reshape(-1, 3, 3) + Wg


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

