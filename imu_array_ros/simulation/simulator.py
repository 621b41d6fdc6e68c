"""Simulated array measurements (skog2016 eq. 1-5 through the sensor model).

``simulate_measurements`` evaluates the rigid-body specific force at every
accelerometer position (skog2016 eq. 1), maps it and the angular velocity
into each sensor frame with the (true) linear sensor model of
:mod:`imu_array_ros.model.sensor_model`, adds white Gaussian noise and clips at
the sensors' clip levels (``accelerometer_clip``/``gyroscope_clip``, default the ranges).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.kinematics import specific_force_at
from imu_array_ros.simulation.motion import TwistTrajectory, random_motion
from imu_array_ros.model.samples import ImuSamples, MotionTruth
from imu_array_ros.model.sensor_model import ErrorTerm, LinearArrayModel, apply_terms

__all__ = ["simulate_measurements", "simulate_twist", "simulate_random"]


def simulate_measurements(model: LinearArrayModel, truth: MotionTruth, rng: np.random.Generator,
                          *, noise: bool = True, saturate: bool = True) -> ImuSamples:
    """Measurements of every IMU for the given motion; (N, K, 3) in sensor frames."""
    f = specific_force_at(truth.specific_force, truth.omega, truth.omega_dot, model.positions)
    acc = np.einsum("kij,nkj->nki", model.acc_matrix, f) + model.acc_bias
    gyr = np.einsum("kij,nj->nki", model.gyro_matrix, truth.omega) + model.gyro_bias
    if noise:
        acc = acc + rng.normal(size=acc.shape) * model.acc_std
        gyr = gyr + rng.normal(size=gyr.shape) * model.gyro_std
    if saturate:
        acc = np.clip(acc, -model.acc_clip, model.acc_clip)
        gyr = np.clip(gyr, -model.gyro_clip, model.gyro_clip)
    return ImuSamples(truth.stamps, acc, gyr, model.names)


def _true_model(desc: ArrayDescription, terms) -> LinearArrayModel:
    return LinearArrayModel.from_description(apply_terms(desc, terms or ()))


def simulate_twist(desc: ArrayDescription, duration: float, rate_hz: float, rng: np.random.Generator, *,
                   terms: list[ErrorTerm] | None = None, rms_rate: float = np.deg2rad(600.0),
                   start_ns: int = 0) -> tuple[ImuSamples, MotionTruth]:
    """Hand-twisting recording of ``duration`` s at ``rate_hz``, stamps from ``start_ns`` (ns since the epoch).

    The motion and the measurements do not depend on ``start_ns``; only the stamps move.
    """
    n = int(round(duration * rate_hz))
    stamps = int(start_ns) + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    truth = TwistTrajectory.random(rng, rms_rate=rms_rate).sample(stamps)
    return simulate_measurements(_true_model(desc, terms), truth, rng), truth


def simulate_random(desc: ArrayDescription, n: int, omega_norm: float, omega_dot_norm: float, rng: np.random.Generator,
                    *, terms: list[ErrorTerm] | None = None, rate_hz: float = 1000.0,
                    start_ns: int = 0) -> tuple[ImuSamples, MotionTruth]:
    """Independent samples with set |omega|, |omega_dot| (carlsson2017 Monte Carlo), stamps from ``start_ns``."""
    truth = random_motion(n, omega_norm, omega_dot_norm, rng, rate_hz=rate_hz, start_ns=start_ns)
    return simulate_measurements(_true_model(desc, terms), truth, rng), truth
