"""Where the residuals exceed the noise by geometry: the rigid-body test of the accelerometer residual field.

Per sample, the accelerometer residuals in SI in the array frame
``e_k = R_k (r_acc,k * sigma_acc,k)`` of a rigid body are an affine field of the
position, ``e_k = s + C p_k`` with a general 3x3 C (12 unknowns; the fitted motion
only absorbs fields of that form).  The weighted least-squares fit of that field,
whitened by the sensor noise, leaves a non-affine sum of squares that is
chi-square with ``m - rank`` degrees of freedom (m valid accelerometer axes, rank
12 unless the valid positions are degenerate, e.g. coplanar: then the
unidentifiable directions of C are dropped).  Its ratio to the degrees of freedom
is 1 for a rigid array; an IMU whose accelerometer is off (bias, scale, position,
timing) carries most of the excess.  Ratio and z as in :mod:`~imu_array_ros.discovery.excess`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.discovery.excess import excess_ratio, excess_z
from imu_array_ros.util.jsontools import json_safe

__all__ = ["RigidTest", "rigid_body_test"]


@dataclass
class RigidTest:
    """Non-affine part of the accelerometer residual field (module docstring).

    ratio: observed / expected non-affine sum of squares over the tested samples;
    z: (O - E) / sqrt(2 E); by_imu (K,): each IMU's share of the observed
    non-affine sum of squares (sums to 1); imu_ratio (K,): per IMU observed /
    expected (expected = sum over its axes of 1 - hat-matrix diagonal);
    statistic (N,): whitened non-affine sum of squares per sample (NaN: not
    tested); dof (N,): its degrees of freedom (0: not tested); samples: tested samples.
    """

    ratio: float
    z: float
    by_imu: np.ndarray
    imu_ratio: np.ndarray
    statistic: np.ndarray
    dof: np.ndarray
    samples: int

    def to_dict(self, names=None) -> dict:
        names = list(names) if names is not None else [str(i) for i in range(len(self.by_imu))]
        return json_safe({"ratio": self.ratio, "z": self.z, "samples": self.samples,
                          "share_by_imu": dict(zip(names, self.by_imu)),
                          "ratio_by_imu": dict(zip(names, self.imu_ratio))})


def rigid_body_test(acc_residuals: np.ndarray, rotations: np.ndarray, positions: np.ndarray, acc_std: np.ndarray, *,
                    min_imus: int = 5, chunk: int = 2048) -> RigidTest:
    """Whitened non-affine part of the accelerometer residual field (module docstring).

    acc_residuals (N, K, 3) normalised (NaN masked); rotations (K, 3, 3) sensor -> array;
    positions (K, 3) m; acc_std (K, 3) m/s^2.  A sample is tested when at least
    ``min_imus`` IMUs have all three accelerometer axes valid (partially valid IMUs
    still enter the fit with their valid axes).  Batched: weighted normal equations
    (N, 12, 12) solved by eigendecomposition, so a rank-deficient geometry (coplanar
    valid positions) drops the unidentifiable directions instead of failing.
    """
    r = np.asarray(acc_residuals, dtype=float)
    n, k = r.shape[:2]
    rot = np.asarray(rotations, dtype=float)
    p = np.asarray(positions, dtype=float)
    sig = np.asarray(acc_std, dtype=float)
    # affine invariance: centre and scale the positions for conditioning
    p = p - p.mean(axis=0)
    scale = float(np.max(np.linalg.norm(p, axis=1))) or 1.0
    p = p / scale
    # design of the field in the array frame: e_k = [I, p_k0 I, p_k1 I, p_k2 I] theta
    a = np.concatenate([np.broadcast_to(np.eye(3), (k, 3, 3))] + [p[:, j, None, None] * np.eye(3) for j in range(3)],
                       axis=2)                                               # (K, 3, 12)
    # whitened (sensor axes, unit noise): r_k = diag(1/sigma_k) R_k^T e_k
    b = (np.swapaxes(rot, 1, 2) / sig[:, :, None]) @ a                       # (K, 3, 12)
    b = b.reshape(3 * k, 12)
    valid = np.isfinite(r)
    tested = valid.all(axis=2).sum(axis=1) >= min_imus
    w = (valid & tested[:, None, None]).reshape(n, 3 * k).astype(float)
    y = np.where(valid, r, 0.0).reshape(n, 3 * k)
    stat = np.full(n, np.nan)
    dof = np.zeros(n)
    obs_k = np.zeros(k)
    exp_k = np.zeros(k)
    for lo in range(0, n, chunk):
        sl = slice(lo, min(lo + chunk, n))
        ww, yy = w[sl], y[sl]
        if not ww.any():
            continue
        wb = ww[:, :, None] * b[None]                                        # (n, q, 12)
        g = np.swapaxes(wb, 1, 2) @ b                                        # (n, 12, 12)
        vals, vecs = np.linalg.eigh(g)
        keep = vals > 1e-9 * np.maximum(vals[:, -1:], 1e-300)
        inv = np.where(keep, 1.0 / np.where(keep, vals, 1.0), 0.0)
        rhs = (np.swapaxes(wb, 1, 2) @ yy[:, :, None])[..., 0]
        theta = (vecs @ (inv * (np.swapaxes(vecs, 1, 2) @ rhs[:, :, None])[..., 0])[:, :, None])[..., 0]
        res = ww * (yy - theta @ b.T)
        bv = b @ vecs                                                        # (n, q, 12)
        hat = ww * ((bv * bv) @ inv[:, :, None])[..., 0]
        d = ww.sum(axis=1) - keep.sum(axis=1)
        ok = tested[sl] & (d > 0)
        ssq = (res ** 2).sum(axis=1)
        stat[sl] = np.where(ok, ssq, np.nan)
        dof[sl] = np.where(ok, d, 0.0)
        obs_k += (res[ok] ** 2).reshape(-1, k, 3).sum(axis=(0, 2))
        exp_k += (ww[ok] - hat[ok]).reshape(-1, k, 3).sum(axis=(0, 2))
    o, e = float(np.nansum(stat)), float(dof.sum())
    return RigidTest(ratio=float(excess_ratio(o, e)), z=float(excess_z(o, e)),
                     by_imu=obs_k / o if o > 0 else np.full(k, np.nan),
                     imu_ratio=excess_ratio(obs_k, exp_k), statistic=stat, dof=dof,
                     samples=int(np.count_nonzero(dof > 0)))
