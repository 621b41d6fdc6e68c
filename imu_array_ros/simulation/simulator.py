"""Simulated array measurements through THE forward model.

``simulate_measurements`` evaluates :meth:`SensorModel.predict
<imu_array_ros.model.sensor_model.SensorModel.predict>` (every term of the model:
geometry, calibration, time offsets, g-sensitivity, ...) for the true motion,
adds white Gaussian noise with the model's standard deviations and clips at
the sensors' clip levels (``accelerometer_clip``/``gyroscope_clip``, default the
ranges).  The derivatives the ``time_offset`` term needs are those of
:func:`~imu_array_ros.model.sensor_model.motion_context` with ``derivatives=True``,
the same the fitting engine uses.  Bias drifts count from the first stamp.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.samples import FusedSamples, ImuSamples, MotionTruth
from imu_array_ros.simulation.motion import TwistTrajectory, gaussian_motion, random_motion

__all__ = ["simulate_measurements", "simulate_twist", "simulate_random", "simulate_gaussian", "as_sensor_model",
           "simulate_same_motion"]


def as_sensor_model(model: SensorModel | ArrayDescription) -> SensorModel:
    """The sensor model of a description (a :class:`SensorModel` passes through)."""
    return model if isinstance(model, SensorModel) else SensorModel.from_description(model)


def simulate_measurements(model: SensorModel | ArrayDescription, truth: MotionTruth, rng: np.random.Generator,
                          *, noise: bool = True, saturate: bool = True) -> ImuSamples:
    """Measurements of every IMU for the given motion; (N, K, 3) in sensor frames."""
    model = as_sensor_model(model)
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations,
                         derivatives=True)
    acc, gyr = model.predict(ctx)
    if noise:
        acc = acc + rng.normal(size=acc.shape) * model.acc_std
        gyr = gyr + rng.normal(size=gyr.shape) * model.gyro_std
    if saturate:
        acc = np.clip(acc, -model.acc_clip, model.acc_clip)
        gyr = np.clip(gyr, -model.gyro_clip, model.gyro_clip)
    return ImuSamples(truth.stamps, acc, gyr, model.names)


def simulate_twist(model: SensorModel | ArrayDescription, duration: float, rate_hz: float, rng: np.random.Generator,
                   *, rms_rate: float = np.deg2rad(600.0), start_ns: int = 0) -> tuple[ImuSamples, MotionTruth]:
    """Hand-twisting recording of ``duration`` s at ``rate_hz``, stamps from ``start_ns`` (ns since the epoch).

    The motion and the measurements do not depend on ``start_ns``; only the stamps move.
    """
    n = int(round(duration * rate_hz))
    stamps = int(start_ns) + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    truth = TwistTrajectory.random(rng, rms_rate=rms_rate).sample(stamps)
    return simulate_measurements(model, truth, rng), truth


def simulate_random(model: SensorModel | ArrayDescription, n: int, omega_norm: float, omega_dot_norm: float,
                    rng: np.random.Generator, *, rate_hz: float = 1000.0,
                    start_ns: int = 0) -> tuple[ImuSamples, MotionTruth]:
    """Independent samples with set |omega|, |omega_dot| (carlsson2017 Monte Carlo), stamps from ``start_ns``."""
    truth = random_motion(n, omega_norm, omega_dot_norm, rng, rate_hz=rate_hz, start_ns=start_ns)
    return simulate_measurements(model, truth, rng), truth


def simulate_gaussian(model: SensorModel | ArrayDescription, n: int, rng: np.random.Generator, *,
                      omega_std: float = np.deg2rad(1000.0), omega_dot_std: float = np.deg2rad(35000.0),
                      specific_force_std: float = 20.0, rate_hz: float = 1000.0,
                      start_ns: int = 0) -> tuple[ImuSamples, MotionTruth]:
    """Independent Gaussian motion samples (carlsson2021 Sec. IV-A defaults), measured without clipping
    (the paper's sensors never saturate)."""
    truth = gaussian_motion(n, omega_std, omega_dot_std, specific_force_std, rng, rate_hz=rate_hz,
                            start_ns=start_ns)
    return simulate_measurements(model, truth, rng, saturate=False), truth


def simulate_same_motion(fused: FusedSamples, model: SensorModel, rng: np.random.Generator,
                         like: ImuSamples | None = None) -> ImuSamples:
    """Simulated recording of the motion estimated in ``fused``, measured by ``model``.

    With ``like``, IMUs/axes missing there are missing here too, so both
    recordings are analysed on the same footing.
    """
    truth = MotionTruth(fused.stamps, fused.omega, fused.omega_dot, fused.specific_force)
    sim = simulate_measurements(model, truth, rng)
    if like is not None:
        idx = np.searchsorted(like.stamps, fused.stamps)
        missing = ~np.isfinite(like.accel[idx]) | ~np.isfinite(like.gyro[idx])
        sim.accel[missing] = np.nan
        sim.gyro[missing] = np.nan
    return sim
