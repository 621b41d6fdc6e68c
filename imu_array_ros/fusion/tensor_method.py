"""Angular-acceleration-tensor method, the baseline of skog2016 (Appendix).

``s_i = s + W r_i`` with ``W = Omega_w^2 + Omega_{omega_dot}`` (eq. 30);
``Y = X R`` solved by least squares ignoring that W has 6 degrees of
freedom (eq. 31-34), then omega_dot from W's antisymmetric part (eq. 35) and
omega, up to sign, from ``omega omega^T = (W + W^T)/2 - tr(W + W^T)/4 I``
(eq. 36).  The sign is taken from the gyroscopes (all readings, saturated
ones included).  Needs at least 4 accelerometer triads spanning 3-D.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.errors import IdentifiabilityError
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.linear import LinearArrayModel

__all__ = ["tensor_method"]


def tensor_method(samples: ImuSamples, model: LinearArrayModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """omega, omega_dot, s (each (N, 3), array frame) by the tensor method.

    Accelerometer readings are first mapped to the array frame with the
    model's calibration (``A_i^{-1} (y_i - b_i)``).  All IMUs must be present.
    """
    r = model.positions
    k = len(r)
    rr = np.vstack([np.ones(k), r.T])  # R (4, K), eq. 32
    if np.linalg.matrix_rank(rr) < 4:
        raise IdentifiabilityError("tensor method: accelerometer positions must span 3-D (skog2016 Appendix)")
    acc = np.linalg.solve(model.acc_matrix[None], (samples.accel - model.acc_bias)[..., None])[..., 0]  # (N,K,3)
    # X_hat = Y R^T (R R^T)^{-1}  (eq. 34), for all samples at once
    pinv = np.linalg.solve(rr @ rr.T, rr).T  # (K, 4)
    x = np.einsum("nki,kj->nij", acc, pinv)  # (N, 3, 4)
    s = x[:, :, 0]
    w = x[:, :, 1:]
    omega_dot = np.stack([w[:, 2, 1] - w[:, 1, 2], w[:, 0, 2] - w[:, 2, 0], w[:, 1, 0] - w[:, 0, 1]], axis=1) / 2.0
    sym = 0.5 * (w + np.swapaxes(w, 1, 2))
    ww = sym - 0.5 * np.trace(sym, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    vals, vecs = np.linalg.eigh(ww)
    omega = vecs[:, :, 2] * np.sqrt(np.clip(vals[:, 2], 0.0, None))[:, None]
    gyro_mean = np.einsum("kji,nkj->ni", model.gyro_matrix, samples.gyro - model.gyro_bias) / k
    sign = np.where(np.einsum("ni,ni->n", omega, gyro_mean) < 0, -1.0, 1.0)
    return omega * sign[:, None], omega_dot, s
