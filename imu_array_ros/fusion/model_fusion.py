"""ML fusion with the whole sensor model: the linear solve plus compensation of the
terms that are not linear.

The fusion (:class:`~imu_array_ros.fusion.ml_fusion.MLFusion`) solves the
model's exact linear form (:class:`~imu_array_ros.model.linear.LinearArrayModel`:
positions, per-axis lever arms, misalignment, non-orthogonality, gain, bias).
The other terms (accelerometer nonlinearity, gyroscope g-sensitivity, time
offsets, bias drift) are *compensated on the readings*: with the motion
estimate x_hat of the previous pass,

    y_compensated = y - [h(x_hat) - h_linear(x_hat)]

where h is :meth:`SensorModel.predict <imu_array_ros.model.sensor_model.SensorModel.predict>`
with every term and h_linear with the non-linear terms at identity; then the
linear solve runs again.  The approximation: the correction is evaluated at the
estimate rather than the true motion, so its error is d(h - h_linear)/dx times
the estimation error -- e.g. g-sensitivity G (~1e-3 (rad/s)/(m/s^2)) times the
specific-force error, or a time offset times the error of ds/dt, which is
differentiated from the estimated specific force (central differences over the
stamps, :func:`~imu_array_ros.model.sensor_model.motion_context`).  Terms that need no
motion (drift, nonlinearity of the readings' own size) are exact up to the
same second-order effect.  The first pass fuses the raw readings; ``passes``
(default 2) further passes follow.  Saturation is decided on the raw readings:
saturated readings are passed on uncompensated, so every pass treats them as
saturated (their sign still starts the solver) rather than as missing.
With no non-linear term away from identity this is exactly one linear fusion.

Readings not sampled at their stamps (the timing terms: time offsets, sample clocks, stamp clocks,
and the own stamps of IMUs that stamp their messages themselves) are compensated the same way, but
exactly to the fused motion rather than to first order: h(x_hat) evaluates each reading at its true
sample time along the fused estimates
(:class:`~imu_array_ros.model.trajectory.MotionTrajectory`: local cubics over ~25 ms), so its error is
the delay times the noise of the estimate's local slope, far below the readings' noise.  The
fused estimate refers to the instant the model calls delay 0: the array stamp (the gauge of time).

Bias drift counts from ``t0_ns``: the first stamp the object has seen unless
given, so fusing a stream in chunks uses the recording's first stamp.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.errors import FusionError
from imu_array_ros.fusion.ml_fusion import FusionConfig, FusionStats, MLFusion
from imu_array_ros.model.trajectory import fused_timing_context
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.linear import LinearArrayModel

__all__ = ["ModelFusion", "fuse_model"]


class ModelFusion:
    """Fusion for a :class:`SensorModel`; ``fuse`` has the signature of :meth:`MLFusion.fuse`."""

    def __init__(self, model: SensorModel, config: FusionConfig | None = None, *, passes: int = 2,
                 acc_range: float | None = None, gyro_range: float | None = None, t0_ns: int | None = None) -> None:
        self.model = model
        self.linear = LinearArrayModel.from_sensor_model(model, acc_range, gyro_range)
        self.fusion = MLFusion(self.linear, config)
        self._linear_part = model.linear_part()
        self.passes = int(passes)
        self._nonlinear = bool(model.nonlinear_terms)
        self.t0_ns = t0_ns

    @property
    def config(self) -> FusionConfig:
        return self.fusion.config

    def correction(self, fused: FusedSamples, stamp_delays: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """h(x_hat) - h_linear(x_hat) for accelerometers and gyroscopes, each (N, K, 3); the timing terms
        (and ``stamp_delays`` (N, K) s of own stamps) evaluated along the fused trajectory."""
        ctx = dict(stamps=fused.stamps, omega=fused.omega, omega_dot=fused.omega_dot,
                   specific_force=fused.specific_force, rotations=self.model.rotations, t0_ns=self.t0_ns)
        if self.model.timed or stamp_delays is not None:  # along the local cubics through the estimate
            motion = np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1)
            full = self.model.predict(motion_context(**ctx, stamp_delays=stamp_delays,
                                                     **fused_timing_context(fused.stamps, motion)))
        else:
            full = self.model.predict(motion_context(**ctx, derivatives=True))
        lin = self._linear_part.predict(motion_context(**ctx))
        return full[0] - lin[0], full[1] - lin[1]

    def fuse(self, samples: ImuSamples) -> tuple[FusedSamples, FusionStats]:
        stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
        if self.t0_ns is None and len(stamps):
            self.t0_ns = int(stamps[0])
        fused, stats = self.fusion.fuse(samples)
        delays = samples.stamp_delays
        if not self.passes or not len(fused) or not (self._nonlinear or delays is not None):
            return fused, stats
        valid = samples.valid(self.model)
        for _ in range(self.passes):
            idx = np.searchsorted(stamps, fused.stamps)
            da, dg = self.correction(fused, None if delays is None else delays[idx])
            acc, gyr = accel.copy(), gyro.copy()
            # only the readings that carry information are compensated; saturated ones stay as read, so
            # the fusion still sees them as saturated and takes their sign (skog2016 Sec. III)
            acc[idx] -= np.where(valid[idx, :, :3], da, 0.0)
            gyr[idx] -= np.where(valid[idx, :, 3:], dg, 0.0)
            fused, stats = self.fusion.fuse(ImuSamples(stamps, acc, gyr, samples.names, samples.own_stamps))
        return fused, stats


def fuse_model(samples: ImuSamples, model: SensorModel, config: FusionConfig | None = None,
               **kwargs) -> tuple[FusedSamples, FusionStats]:
    """Fuse a whole :class:`ImuSamples` batch with every term of ``model`` (see module docstring)."""
    if tuple(samples.names) != tuple(model.names):
        raise FusionError(f"fusion: samples are for IMUs {list(samples.names)[:4]}..., "
                          f"model for {list(model.names)[:4]}...")
    return ModelFusion(model, config, **kwargs).fuse(samples)
