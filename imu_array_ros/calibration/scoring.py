"""How well a model explains a window of samples, with every sample's motion at its ML estimate.

A calibration is judged on the data it used: the log-likelihood of the readings
under a model with the unknown motion of every sample fitted (*profiled out*).
:func:`profile_window` computes it (and the cost, the per-IMU accelerometer
residual RMS and the motion); :func:`window_loglik` is just the number.  The
same figure scores a new calibration and the one on file, so an install never
replaces a calibration that fits the window better
(:mod:`imu_array_ros.calibration.result`).

The ML motion is the fusion's estimate when every term of the model is linear;
with a non-linear term (time offsets, ...) the fusion only compensates, so the
engine's motion-only Gauss-Newton refines it (:func:`~imu_array_ros.fitting.engine.fit_motion`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.fitting.engine import fit_motion
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context

__all__ = ["WindowProfile", "WindowScorer", "profile_window", "window_loglik", "loglik_constant"]


@dataclass
class WindowProfile:
    """A window under a model with the motion at its ML estimate: cost = sum of squared normalised
    residuals / 2; loglik; rms (K,) accelerometer residual RMS per IMU (m/s^2); motion (N, 9)."""

    cost: float
    loglik: float
    rms: np.ndarray
    motion: np.ndarray


def loglik_constant(model: SensorModel, valid: np.ndarray) -> float:
    """log p(y) minus the cost term: -sum log sigma - n/2 log 2 pi over the valid axes (N, K, 6)."""
    sigma = np.broadcast_to(model.std[None], valid.shape)[valid]
    return -float(np.sum(np.log(sigma))) - 0.5 * len(sigma) * np.log(2 * np.pi)


def profile_window(samples: ImuSamples, model: SensorModel) -> WindowProfile:
    """``samples`` under ``model`` with the motion at its ML estimate (module docstring)."""
    stamps = samples.stamps
    fused, _ = ModelFusion(model).fuse(samples)
    rows = np.searchsorted(stamps, fused.stamps)
    motion = np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1)
    if model.nonlinear_terms:
        start = np.zeros((len(stamps), 9))
        start[rows] = motion
        motion, loglik, r = fit_motion(samples, model, start)
        r = np.nan_to_num(r)
        valid = samples.valid(model)
    else:
        ctx = motion_context(fused.stamps, fused.omega, fused.omega_dot, fused.specific_force, model.rotations,
                             derivatives=True)
        acc, gyr = model.predict(ctx)
        y = samples.readings[rows]
        valid = model.valid(samples.accel[rows], samples.gyro[rows])
        r = np.where(valid, y - np.concatenate([acc, gyr], axis=2), 0.0) / model.std[None]
        loglik = loglik_constant(model, valid) - 0.5 * float(np.sum(r * r))
    cost = 0.5 * float(np.sum(r * r))
    raw = r * model.std[None]
    counts = np.maximum(valid[..., :3].sum(axis=(0, 2)), 1)
    rms = np.sqrt(np.sum(raw[..., :3] ** 2, axis=(0, 2)) / counts)
    return WindowProfile(cost, loglik, rms, motion)


def window_loglik(samples: ImuSamples, model: SensorModel) -> float:
    """Log-likelihood of ``samples`` under ``model`` with every sample's motion fitted."""
    return profile_window(samples, model).loglik


@dataclass
class WindowScorer:
    """A calibration's :class:`~imu_array_ros.calibration.result.Scorer` on a window of samples:
    :func:`window_loglik`."""

    samples: ImuSamples

    def __call__(self, model: SensorModel) -> float:
        return window_loglik(self.samples, model)
