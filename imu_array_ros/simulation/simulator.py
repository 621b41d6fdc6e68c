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

__all__ = ["simulate_measurements", "simulate_trajectory", "simulate_twist", "simulate_random", "simulate_gaussian",
           "as_sensor_model", "simulate_same_motion"]


def as_sensor_model(model: SensorModel | ArrayDescription) -> SensorModel:
    """The sensor model of a description (a :class:`SensorModel` passes through)."""
    return model if isinstance(model, SensorModel) else SensorModel.from_description(model)


def simulate_measurements(model: SensorModel | ArrayDescription, truth: MotionTruth, rng: np.random.Generator,
                          *, noise: bool = True, saturate: bool = True, trajectory=None,
                          own_stamps: np.ndarray | None = None) -> ImuSamples:
    """Measurements of every IMU for the given motion; (N, K, 3) in sensor frames.

    ``trajectory``: the motion as a function of int64 ns time (``MotionContext.trajectory``; ``truth``
    must be its values at the stamps): used when the model is timed or ``own_stamps`` are given, then
    every reading is the exact motion at its true sample time.  ``own_stamps`` (N, K) int64: the stamp
    each IMU's message carried (IMUs that stamp their own messages); the readings are taken at them
    (plus the model's timing delays) and the samples carry them.
    """
    model = as_sensor_model(model)
    delays = None if own_stamps is None else (np.asarray(own_stamps, dtype=np.int64)
                                              - np.asarray(truth.stamps, dtype=np.int64)[:, None]) * 1e-9
    exact = trajectory is not None and (model.timed or own_stamps is not None)
    ctx = motion_context(truth.stamps, truth.omega, truth.omega_dot, truth.specific_force, model.rotations,
                         derivatives=True, stamp_delays=delays, trajectory=trajectory if exact else None)
    acc, gyr = model.predict(ctx)
    if noise:
        acc = acc + rng.normal(size=acc.shape) * model.acc_std
        gyr = gyr + rng.normal(size=gyr.shape) * model.gyro_std
    if saturate:
        acc = np.clip(acc, -model.acc_clip, model.acc_clip)
        gyr = np.clip(gyr, -model.gyro_clip, model.gyro_clip)
    return ImuSamples(truth.stamps, acc, gyr, model.names, own_stamps)


def simulate_trajectory(model: SensorModel | ArrayDescription, trajectory: TwistTrajectory, stamps: np.ndarray,
                        rng: np.random.Generator, *, own_stamps: np.ndarray | None = None, noise: bool = True,
                        saturate: bool = True, exact_timing: bool = True) -> tuple[ImuSamples, MotionTruth]:
    """A recording of ``trajectory`` at ``stamps`` (int64 ns, sorted; the motion's origin is the first).

    Untimed model and no ``own_stamps``, or ``exact_timing`` False: the truth is
    :meth:`TwistTrajectory.sample` at the stamps and the readings are shifted to their sample times to
    first order (the readings the fitting engine's linearisation assumes; the simulator before sample
    times were modelled, bit for bit).  Otherwise the truth and every reading, at its true sample time,
    come from :meth:`TwistTrajectory.function` (knots every 1 ms from the first stamp).
    """
    model = as_sensor_model(model)
    stamps = np.asarray(stamps, dtype=np.int64)
    if not exact_timing or (not model.timed and own_stamps is None):
        truth = trajectory.sample(stamps)
        return simulate_measurements(model, truth, rng, noise=noise, saturate=saturate, own_stamps=own_stamps), truth
    function = trajectory.function(int(stamps[0]))
    truth = function.truth(stamps)
    return simulate_measurements(model, truth, rng, noise=noise, saturate=saturate, trajectory=function,
                                 own_stamps=own_stamps), truth


def simulate_twist(model: SensorModel | ArrayDescription, duration: float, rate_hz: float, rng: np.random.Generator,
                   *, rms_rate: float = np.deg2rad(600.0), start_ns: int = 0,
                   exact_timing: bool = True) -> tuple[ImuSamples, MotionTruth]:
    """Hand-twisting recording of ``duration`` s at ``rate_hz``, stamps from ``start_ns`` (ns since the epoch)
    (:func:`simulate_trajectory`: a timed model reads the motion at every reading's true sample time unless
    ``exact_timing`` is False).

    The motion and the measurements do not depend on ``start_ns``; only the stamps move.
    """
    n = int(round(duration * rate_hz))
    stamps = int(start_ns) + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    return simulate_trajectory(model, TwistTrajectory.random(rng, rms_rate=rms_rate), stamps, rng,
                               exact_timing=exact_timing)


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
