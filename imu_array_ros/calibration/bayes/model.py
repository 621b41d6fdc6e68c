"""The sensor model as the paper's: affine in the motion, and the readings compensated by it.

With every term of :class:`~imu_array_ros.model.sensor_model.SensorModel` affine (gains,
misalignments, non-orthogonalities, biases and their drifts held at their calibrated values)
IMU k's accelerometer reads y_k = M_k f(r_k) + o_k and its gyroscope g_k = G_k omega + o'_k,
so the compensated readings

    z_k = M_k^-1 (y_k - o_k) = [omega]x^2 r_k + [omega_dot]x r_k + s + e_k,   e_k ~ N(0, M_k^-1 Sigma_k M_k^-T)
    w_k = G_k^-1 (g_k - o'_k) = omega + e'_k

are carlsson2021's array model (eq. 5) exactly, with 3x3 noise blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context

__all__ = ["affine_model", "compensate", "Compensated", "AFFINE_RTOL"]

#: relative mismatch above which the model is not affine in the motion (see affine_model)
AFFINE_RTOL = 1e-8


def affine_model(model: SensorModel, stamps) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(M_acc (K,3,3), o_acc (T,K,3), M_gyr (K,3,3), o_gyr (T,K,3)) with y = M f(r_k) + o, g = M' omega + o'.

    Read off the model itself (its prediction at rest and its Jacobian) and
    checked at a random motion; a model with a term that is not affine in the
    motion (time offsets, axis offsets, non-linearity, g-sensitivity not at
    their identity) raises :class:`CalibrationError` naming it.
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    t = len(stamps)
    zero = np.zeros((t, 3))
    ctx = motion_context(stamps, zero, zero, zero, model.rotations, derivatives=True)
    acc0, gyr0 = model.predict(ctx)
    jac = model.jacobians(motion_context(stamps[:1], zero[:1], zero[:1], zero[:1], model.rotations,
                                         derivatives=True), ())
    m_acc = jac.motion[0, :, 0:3, 6:9].copy()
    m_gyr = jac.motion[0, :, 3:6, 0:3].copy()
    # check: one random motion at every stamp against the affine form
    rng = np.random.default_rng(12345)
    w, wd, s = rng.normal(size=(3, t, 3)) * np.array([3.0, 30.0, 10.0])[:, None, None]
    ctx = motion_context(stamps, w, wd, s, model.rotations, derivatives=True)
    acc, gyr = model.predict(ctx)
    lever = skew(w) @ skew(w) + skew(wd)
    f = s[:, None, :] + np.einsum("tij,kj->tki", lever, model.positions)
    acc_aff = np.einsum("kij,tkj->tki", m_acc, f) + acc0
    gyr_aff = np.einsum("kij,tj->tki", m_gyr, w) + gyr0
    err = max(np.max(np.abs(acc - acc_aff)) / max(np.max(np.abs(acc)), 1.0),
              np.max(np.abs(gyr - gyr_aff)) / max(np.max(np.abs(gyr)), 1.0))
    if not np.isfinite(err) or err > AFFINE_RTOL:
        offending = [n for n in model.nonlinear_terms] + [
            n for n in ("gyroscope_g_sensitivity", "axis_offsets", "time_offset")
            if n in model.terms and not model.terms[n].is_identity and n not in model.nonlinear_terms]
        raise CalibrationError(
            "the Bayesian position calibration needs a sensor model affine in the motion; "
            f"{', '.join(offending) or 'a term'} is not (hold it at its identity, or calibrate with "
            "'calibrate fit' / 'calibrate geometry')")
    for label, m in (("accelerometer", m_acc), ("gyroscope", m_gyr)):
        if np.any(np.abs(np.linalg.det(m)) < 1e-6):
            raise CalibrationError(f"the {label} model of an IMU is singular (a gain near 0?)")
    return m_acc, acc0, m_gyr, gyr0


@dataclass(frozen=True)
class Compensated:
    """The readings in the paper's model (module docstring).

    accel: z (T, K, 3), m/s^2; gyro: w (T, K, 3), rad/s; accel_info: Omega_k = (M_k^-1 Sigma_k M_k^-T)^-1
    (K, 3, 3); gyro_cov: G_k^-1 Sigma'_k G_k^-T, the gyroscopes' noise covariance (K, 3, 3); accel_std:
    the accelerometer noise std (K, 3) Omega_k was formed with.
    """

    accel: np.ndarray
    gyro: np.ndarray
    accel_info: np.ndarray
    gyro_cov: np.ndarray
    accel_std: np.ndarray


def compensate(samples: ImuSamples, model: SensorModel, accel_std: float | None = None) -> Compensated:
    """The readings of ``samples`` compensated by the affine ``model`` (:func:`affine_model`), with their
    noise information; ``accel_std`` replaces the model's accelerometer noise std (m/s^2)."""
    k = model.n_imus
    m_acc, o_acc, m_gyr, o_gyr = affine_model(model, samples.stamps)
    inv_a, inv_g = np.linalg.inv(m_acc), np.linalg.inv(m_gyr)
    z = np.einsum("kij,tkj->tki", inv_a, samples.accel - o_acc)
    w = np.einsum("kij,tkj->tki", inv_g, samples.gyro - o_gyr)
    sa = model.acc_std if accel_std is None else np.full((k, 3), float(accel_std))
    cov_a = inv_a @ (sa[:, :, None] ** 2 * np.eye(3)) @ inv_a.transpose(0, 2, 1)
    om = np.linalg.inv(cov_a)
    om = 0.5 * (om + om.transpose(0, 2, 1))
    cov_g = inv_g @ (model.gyro_std[:, :, None] ** 2 * np.eye(3)) @ inv_g.transpose(0, 2, 1)
    return Compensated(accel=z, gyro=w, accel_info=om, gyro_cov=cov_g, accel_std=sa)
