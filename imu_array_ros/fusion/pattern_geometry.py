"""Geometry of the ML fusion per pattern of valid accelerometer axes (skog2016 eq. 8-11, 14-15).

The accelerometer readings are linear in ``z = [q(omega), omega_dot, s]``:
``y_a - b = D z + n`` (see :mod:`imu_array_ros.fusion.ml_fusion`).  For a
pattern of valid axes (zero weight on the others), ``F = D^T W D`` split into
the q- and phi = [omega_dot, s]-blocks gives all the solver needs that does not
depend on the sample: ``E = F_pp^-1 F_pq``, ``F~ = F_qq - F_qp E``, ``F_pp^-1``
and the Gauss-Newton coefficients ``T`` (``Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3)``),
held by :class:`Geometry`.  Built

* for one pattern shared by many samples: :func:`shared_geometry`;
* for M samples at once, each from its own pattern: :func:`stacked_geometry`
  (batched products and a batched 6x6 Cholesky, no loop over patterns);
* for the table of the patterns with up to two whole IMUs missing:
  :func:`dropout_masks`, :func:`dropout_table`.

A pattern is identifiable when ``F_pp`` has a positive diagonal and, scaled to
unit diagonal, a condition number below :data:`MAX_COND`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from imu_array_ros.fusion.batched_linalg import inv_spd6, row_times
from imu_array_ros.fusion.validity import valid_sum
from imu_array_ros.model.kinematics import quadratic_monomials_jacobian

__all__ = ["MAX_COND", "Geometry", "shared_geometry", "stacked_geometry", "dropout_masks", "dropout_table"]

#: dq/domega is linear in omega: Jq(omega) = sum_m omega_m _JQ_BASIS[m]  (3, 6, 3)
_JQ_BASIS = quadratic_monomials_jacobian(np.eye(3))

#: Jq(omega) = (omega @ _JQ_FLAT).reshape(6, 3)
_JQ_FLAT = _JQ_BASIS.reshape(3, 18)


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
MAX_COND = 1e10


@dataclass(frozen=True)
class Geometry:
    """Precomputed matrices of the accelerometer part, for one pattern of valid axes.

    Shared by a group of samples (shapes as commented) or per sample (the same
    arrays stacked, with a leading (M,) axis).
    """

    ok: bool
    TF: np.ndarray | None = None  # (6, 15) [T | F~]: Jq^T F~ Jq = (q(omega) @ T).reshape(3, 3), F~ (6, 6)
    EF: np.ndarray | None = None  # (6, 12) [E | F_pp^-1], E = F_pp^-1 F_pq
    EC: np.ndarray | None = None  # (3, 18): E Jq(omega) = (omega @ EC).reshape(6, 3); None per sample

    def part(self, rows) -> "Geometry":
        """Itself if shared, else the per-sample geometry of ``rows`` (a slice: views; indices: a copy)."""
        return self if self.EC is not None else Geometry(True, self.TF[rows], self.EF[rows])

    @property
    def E(self) -> np.ndarray:
        """E = F_pp^-1 F_pq, (6, 6) or (M, 6, 6)."""
        return self.EF[..., :6]

    @property
    def Fpp_inv(self) -> np.ndarray:
        """F_pp^-1, (6, 6) or (M, 6, 6)."""
        return self.EF[..., 6:]

    def e_jq(self, omega: np.ndarray) -> np.ndarray:
        """``E Jq(omega)`` (n, 6, 3) at omega (n, 3), rows matching the samples of this geometry."""
        if self.EC is not None:
            return row_times(omega, self.EC).reshape(-1, 6, 3)  # E Jq(omega): Jq is linear in omega
        return self.E @ (omega @ _JQ_FLAT).reshape(-1, 6, 3)  # per sample: E times Jq(omega)


def shared_geometry(d: np.ndarray, w: np.ndarray, mask: np.ndarray) -> Geometry:
    """Geometry of the pattern ``mask`` (3K,) bool of valid accelerometer axes, shared by its samples.

    d (3K, 12) the accelerometer rows ``D``, w (3K,) their weights (1 / std^2).
    Returns ``Geometry(ok=False)`` if the pattern is not identifiable.
    """
    f = d.T @ ((w * mask)[:, None] * d)
    fpp = f[6:, 6:]
    scale = np.sqrt(np.clip(np.diag(fpp), 0, None))
    geo = Geometry(ok=False)
    if np.all(scale > 0):
        fn = fpp / np.outer(scale, scale)
        if np.linalg.cond(fn) < MAX_COND:
            cf = cho_factor(fpp)
            e = cho_solve(cf, f[6:, :6])
            ft = f[:6, :6] - f[:6, 6:] @ e
            ft = 0.5 * (ft + ft.T)
            geo = Geometry(
                ok=True, TF=np.concatenate([_gn_matrix_coefficients(ft), ft], axis=1),
                EF=np.concatenate([e, cho_solve(cf, np.eye(6))], axis=1),
                EC=np.einsum("ij,mjk->mik", e, _JQ_BASIS).reshape(3, 18),
            )
    return geo


def stacked_geometry(valid: np.ndarray, f_imu: np.ndarray, f_axis: np.ndarray) -> tuple[Geometry, np.ndarray]:
    """Per-sample geometry of M samples from their own valid axes ``valid`` (M, 3K) bool.

    f_axis (3K, 144): ``F = D^T W D`` (12 x 12, flat) of each single sensor
    axis; f_imu (K, 144): of each whole IMU.  The matrices of
    :func:`shared_geometry`, stacked: ``F`` with zero weight on invalid axes
    (:func:`~imu_array_ros.fusion.validity.valid_sum`), ``F_pp`` inverted by a
    batched Cholesky (:func:`~imu_array_ros.fusion.batched_linalg.inv_spd6`),
    everything else by batched products, so the cost is linear in M whatever
    the number of distinct patterns.  Returns the geometry (M', ...) of the
    identifiable samples and their row indices (M',) into ``valid``.
    """
    m = valid.shape[0]
    f = valid_sum(valid, f_imu, f_axis).reshape(m, 12, 12)
    fpp_inv, ok = inv_spd6(f[:, 6:, 6:], MAX_COND)
    keep = np.flatnonzero(ok)
    if keep.size < m:
        f, fpp_inv = f[keep], fpp_inv[keep]
    e = fpp_inv @ f[:, 6:, :6]
    ft = f[:, :6, :6] - f[:, :6, 6:] @ e
    ft = 0.5 * (ft + np.swapaxes(ft, 1, 2))
    geo = Geometry(
        ok=True, TF=np.concatenate([(ft.reshape(-1, 36) @ _T_MAP).reshape(-1, 6, 9), ft], axis=2),
        EF=np.concatenate([e, fpp_inv], axis=2),
    )
    return geo, keep


def dropout_masks(k: int, depth: int) -> np.ndarray:
    """(P, 3K) bool valid axes of the patterns with up to ``depth`` (1 or 2) of K whole IMUs missing.

    Rows: all IMUs valid (0); all but IMU i (1 + i); with depth 2, all but IMUs
    i < j (1 + K + pair index in ``np.triu_indices(K, 1)`` order, see
    :meth:`~imu_array_ros.fusion.validity.Invalid.table_index`).
    """
    masks = [np.ones((1, k), dtype=bool), ~np.eye(k, dtype=bool)]
    if depth == 2:
        i, j = np.triu_indices(k, 1)
        pairs = np.ones((len(i), k), dtype=bool)
        pairs[np.arange(len(i)), i] = pairs[np.arange(len(i)), j] = False
        masks.append(pairs)
    return np.repeat(np.concatenate(masks), 3, axis=1)  # (P, 3K)


def dropout_table(masks: np.ndarray, f_imu: np.ndarray, f_axis: np.ndarray) -> tuple[np.ndarray, Geometry]:
    """Per-sample geometry of the patterns ``masks`` (P, 3K) bool (:func:`dropout_masks`), stacked, in one batch.

    f_imu, f_axis as in :func:`stacked_geometry`.  Returns (ok (P,) bool,
    geometry (P, ...)); rows that are not identifiable are NaN.
    """
    geo, keep = stacked_geometry(masks, f_imu, f_axis)
    ok = np.zeros(len(masks), dtype=bool)
    ok[keep] = True

    def full(a):
        out = np.full((len(masks),) + a.shape[1:], np.nan)
        out[keep] = a
        return out

    return ok, Geometry(True, full(geo.TF), full(geo.EF))
