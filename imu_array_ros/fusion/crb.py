"""Cramér-Rao bound of the array fusion problem (skog2016 Sec. IV).

Written directly from eq. 13-15, independently of the algebra inside
:mod:`imu_array_ros.fusion.ml_fusion`, so that each can check the other
(the accelerometer rows come from the model's design D_k, which tests check
against eq. 13 for one lever arm per IMU):

    I(theta) = Phi^T Q^{-1} Phi,   Phi = [J_h  H],   theta = [omega, omega_dot, s]

with the sensor-frame calibrated rows ``A_i [A(omega, r_i), -Omega_{r_i}, I]`` for
accelerometer triad i (eq. 13, A(u, v) = Omega_u^T Omega_v + Omega_{v x u}) and
``[B_j, 0, 0]`` for gyroscope triad j.  Saturated or missing axes carry no
information (their rows are dropped, i.e. sigma -> infinity, Sec. IV-A).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import quadratic_monomials_jacobian
from imu_array_ros.model.linear import LinearArrayModel

__all__ = ["jacobian_rows", "fisher_information", "crb", "square_array_omega_information"]


def jacobian_rows(omega: np.ndarray, model: LinearArrayModel) -> tuple[np.ndarray, np.ndarray]:
    """Rows of Phi for every sensor axis: accelerometers (N, K, 3, 9), gyroscopes (K, 3, 9).

    The accelerometer rows are the model's design D_k (the calibrated A_k [A(omega, r_k),
    -Omega_{r_k}, I] of eq. 13 when each IMU has one lever arm) times d z / d theta.
    """
    omega = np.atleast_2d(np.asarray(omega, dtype=float))
    n, k = len(omega), model.n_imus
    dz = np.zeros((n, 12, 9))  # d z / d theta, z = [q(omega), omega_dot, s]
    dz[:, :6, :3] = quadratic_monomials_jacobian(omega)
    dz[:, 6:, 3:] = np.eye(6)
    acc_rows = np.einsum("kiz,nzt->nkit", model.acc_design, dz)
    gyr_rows = np.concatenate([model.gyro_matrix, np.zeros((k, 3, 6))], axis=2)
    return acc_rows, gyr_rows


def fisher_information(omega: np.ndarray, model: LinearArrayModel, acc_valid: np.ndarray | None = None,
                       gyro_valid: np.ndarray | None = None) -> np.ndarray:
    """Fisher information (N, 9, 9) at angular velocities ``omega`` (N, 3) (eq. 15).

    acc_valid, gyro_valid: optional (N, K, 3) bool masks of axes that carry
    information (not missing, not saturated).
    """
    acc_rows, gyr_rows = jacobian_rows(omega, model)
    n = acc_rows.shape[0]
    wa = np.broadcast_to(1.0 / model.acc_std**2, (n,) + model.acc_std.shape)
    wg = np.broadcast_to(1.0 / model.gyro_std**2, (n,) + model.gyro_std.shape)
    if acc_valid is not None:
        wa = wa * acc_valid
    if gyro_valid is not None:
        wg = wg * gyro_valid
    info = np.einsum("nkai,nka,nkaj->nij", acc_rows, wa, acc_rows)
    info += np.einsum("kai,nka,kaj->nij", gyr_rows, wg, gyr_rows)
    return info


def crb(omega: np.ndarray, model: LinearArrayModel, acc_valid=None, gyro_valid=None) -> np.ndarray:
    """Cramér-Rao bound (N, 9, 9): inverse Fisher information (eq. 14); inf where singular."""
    info = fisher_information(omega, model, acc_valid, gyro_valid)
    out = np.full_like(info, np.inf)
    ok = np.linalg.cond(info) < 1e14
    out[ok] = np.linalg.inv(info[ok])
    return out


def square_array_omega_information(omega: np.ndarray, alpha: float, n_acc: int, n_gyro: int, sigma_acc: float,
                                   sigma_gyro: float) -> np.ndarray:
    """Closed-form Fisher information of omega for square planar grids (skog2016 eq. 25).

    ``alpha`` is the grid spacing, ``n_acc`` in {4, 9, 16, ...}; pass
    ``n_gyro = 0`` (or sigma_gyro = inf) for saturated gyroscopes (eq. 26).
    """
    w = np.atleast_2d(np.asarray(omega, dtype=float))
    x, y, z = w[:, 0], w[:, 1], w[:, 2]
    m = np.stack(
        [
            np.stack([2 * x * x + y * y, x * y, 2 * x * z], -1),
            np.stack([x * y, 2 * y * y + x * x, 2 * y * z], -1),
            np.stack([2 * x * z, 2 * y * z, 4 * z * z], -1),
        ],
        -2,
    )
    gyro = 0.0 if (n_gyro == 0 or not np.isfinite(sigma_gyro)) else n_gyro / sigma_gyro**2
    return gyro * np.eye(3) + alpha**2 * (n_acc**2 - n_acc) / (6 * sigma_acc**2) * m
