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

The difference h - h_linear is computed as one difference, not two predictions
(:meth:`SensorModel.predict_nonlinear <imu_array_ros.model.sensor_model.SensorModel.predict_nonlinear>`:
linear terms cancel, the timing stage's shift is a polynomial in each reading's delay with per-sample
coefficients), the local cubics' weights are solved once for all passes (they depend on the stamps only,
:func:`~imu_array_ros.model.trajectory.shared_fits`), and so are the readings' delays; the readings are
compensated chunk by chunk into two arrays reused by the passes.  Same numbers as two predictions to
rounding (test/test_timed_fusion_fast.py); speed: benchmarks/results/time_aware_fusion.md.

Bias drift counts from ``t0_ns``: the first stamp the object has seen unless
given, so fusing a stream in chunks uses the recording's first stamp.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.errors import FusionError
from imu_array_ros.fusion.ml_fusion import FusionConfig, FusionStats, MLFusion
from imu_array_ros.model.trajectory import fused_timing_context, shared_fits
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
        self.passes = int(passes)
        self._nonlinear = bool(model.nonlinear_terms)
        self._timed = model.timed
        self.t0_ns = t0_ns

    @property
    def config(self) -> FusionConfig:
        return self.fusion.config

    def correction(self, fused: FusedSamples, stamp_delays: np.ndarray | None = None, *,
                   subtract_from: tuple[np.ndarray, np.ndarray] | None = None,
                   out: tuple[np.ndarray, np.ndarray] | None = None,
                   delays: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """h(x_hat) - h_linear(x_hat) for accelerometers and gyroscopes, each (N, K, 3); the timing terms
        (and ``stamp_delays`` (N, K) s of own stamps) evaluated along the fused trajectory.  Computed as one
        difference (:meth:`SensorModel.predict_nonlinear`), not as two predictions; ``subtract_from``:
        readings (N, K, 3) each, to return minus the correction instead; ``out``: arrays to write into;
        ``delays``: the model's :meth:`~SensorModel.timing_delays` at these stamps, when known."""
        ctx = dict(stamps=fused.stamps, omega=fused.omega, omega_dot=fused.omega_dot,
                   specific_force=fused.specific_force, rotations=self.model.rotations, t0_ns=self.t0_ns)
        if self._timed or stamp_delays is not None:  # along the local cubics through the estimate
            motion = np.concatenate([fused.omega, fused.omega_dot, fused.specific_force], axis=1)
            ctx = motion_context(**ctx, stamp_delays=stamp_delays, **fused_timing_context(fused.stamps, motion))
        else:
            ctx = motion_context(**ctx)  # no timing stage: nothing reads the motion's derivatives
        return self.model.predict_nonlinear(ctx, delays=delays, out=out, subtract_from=subtract_from)

    def fuse(self, samples: ImuSamples) -> tuple[FusedSamples, FusionStats]:
        stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
        if self.t0_ns is None and len(stamps):
            self.t0_ns = int(stamps[0])
        fused, stats = self.fusion.fuse(samples)
        delays = samples.stamp_delays
        if not self.passes or not len(fused) or not (self._nonlinear or delays is not None):
            return fused, stats
        # only the readings that carry information are compensated; saturated ones stay as read, so
        # the fusion still sees them as saturated and takes their sign (skog2016 Sec. III).  The linear
        # fusion applies the model's saturation rule: when it found no saturated or missing reading, every
        # reading is valid
        keep_a = keep_g = None
        if stats.saturated_accel_samples or stats.saturated_gyro_samples or stats.incomplete_samples:
            valid_a, valid_g = self.model.acc_unsaturated(accel), self.model.gyro_unsaturated(gyro)
            keep_a = None if valid_a.all() else ~valid_a
            keep_g = None if valid_g.all() else ~valid_g
        acc, gyr = np.empty_like(accel), np.empty_like(gyro)  # the compensated readings, rewritten by every pass
        held = None  # the model's timing delays at every sample (they depend on the stamps only)
        with shared_fits():  # the local cubics' weights, fitted once at these stamps
            for _ in range(self.passes):
                if len(fused) == len(stamps):  # every sample fused: compensated in place, chunk by chunk
                    if held is None and (self._timed or delays is not None):
                        held = self.model.timing_delays(motion_context(
                            stamps, fused.omega, fused.omega_dot, fused.specific_force, self.model.rotations,
                            t0_ns=self.t0_ns, stamp_delays=delays))
                    self.correction(fused, delays, subtract_from=(accel, gyro), out=(acc, gyr), delays=held)
                else:
                    idx = np.searchsorted(stamps, fused.stamps)
                    da, dg = self.correction(fused, None if delays is None else delays[idx])
                    acc[...], gyr[...] = accel, gyro
                    acc[idx] -= da
                    gyr[idx] -= dg
                if keep_a is not None:
                    np.copyto(acc, accel, where=keep_a)
                if keep_g is not None:
                    np.copyto(gyr, gyro, where=keep_g)
                fused, stats = self.fusion.fuse(ImuSamples(stamps, acc, gyr, samples.names, samples.own_stamps))
        return fused, stats


def fuse_model(samples: ImuSamples, model: SensorModel, config: FusionConfig | None = None,
               **kwargs) -> tuple[FusedSamples, FusionStats]:
    """Fuse a whole :class:`ImuSamples` batch with every term of ``model`` (see module docstring)."""
    if tuple(samples.names) != tuple(model.names):
        raise FusionError(f"fusion: samples are for IMUs {list(samples.names)[:4]}..., "
                          f"model for {list(model.names)[:4]}...")
    return ModelFusion(model, config, **kwargs).fuse(samples)
