"""Every IMU's reading delay per sample, relative to the other IMUs, from the fusion's residuals.

With the motion fused at the array stamp and every reading predicted at the sample time the model
gives it (:class:`~imu_array_ros.model.trajectory.MotionTrajectory`), the residual r (N, K, 6) of
IMU k at sample n is, to first order, J d, with J = d y / d delay (the six readings' rates of change,
both sensors of a chip sharing its clock) and d the error of the model's delay.  So

    d_nk = (J^T W r) / (J^T W J),   info_nk = J^T W J   (W: inverse noise variances, 0 where saturated)

is the delay error of IMU k at sample n, with standard deviation 1 / sqrt(info).  The fusion
absorbs whatever the IMUs share, so only the differences between IMUs mean something:
:meth:`ReadingDelays.relative` removes the weighted mean per sample.

Only moving samples carry timing information: ``moving`` is decided on the gyroscopes (the slope of
the fused angular rate, which the accelerometers' noise does not fake), as everywhere else.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.model.trajectory import fused_timing_context
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context
from imu_array_ros.model.terms.time_offset import TimeOffset

__all__ = ["ReadingDelays", "reading_delays", "MOVING_RATE"]

#: |d omega / dt| (rad/s^2, from the fused angular rate) above which a sample is moving
MOVING_RATE = 5.0


@dataclass
class ReadingDelays:
    """Per sample n and IMU k: stamps (N,) int64; t (N,) s since ``t0_ns``; delay (N, K) s: the
    gyroscope's sample time minus the stamp, as the model gave it plus the residual's correction;
    info (N, K) s^-2 (0: no information); moving (N,) bool; model_delay (N, K) s: the delay the model
    gave (``delay`` minus the correction)."""

    stamps: np.ndarray
    t: np.ndarray
    delay: np.ndarray
    info: np.ndarray
    moving: np.ndarray
    t0_ns: int
    model_delay: np.ndarray

    @property
    def correction(self) -> np.ndarray:
        """(N, K) s: what the readings say the model's delay misses."""
        return self.delay - self.model_delay

    @property
    def weights(self) -> np.ndarray:
        """(N, K) information of the moving samples, 0 elsewhere."""
        return np.where(self.moving[:, None], self.info, 0.0)

    def relative(self) -> np.ndarray:
        """(N, K) delays minus their information-weighted mean over the IMUs of each sample."""
        w = self.weights
        total = w.sum(axis=1)
        common = np.sum(w * self.delay, axis=1) / np.where(total > 0, total, 1.0)
        return self.delay - common[:, None]

    @property
    def moving_seconds(self) -> float:
        if len(self.stamps) < 2:
            return 0.0
        dt = np.median(np.diff(self.stamps)) * 1e-9
        return float(self.moving.sum() * dt)


def reading_delays(samples: ImuSamples, model: SensorModel, fused: FusedSamples | None = None, *,
                   t0_ns: int | None = None, moving_rate: float = MOVING_RATE,
                   sensor: str | None = None) -> ReadingDelays:
    """The delays of every IMU's readings in ``samples`` under ``model`` (see module docstring);
    ``fused``: the fusion of ``samples`` with ``model`` (fused here when not given); t0_ns: the time
    origin of the clocks (default the first stamp); ``sensor``: "gyroscope" or "accelerometer" for the
    delays of that sensor's readings alone (None: one delay shared by both, a chip's clock)."""
    t0 = int(samples.stamps[0]) if t0_ns is None else int(t0_ns)
    if fused is None:
        fused, _ = ModelFusion(model, t0_ns=t0).fuse(samples)
    k = model.n_imus
    if len(fused) < 5:
        z = np.zeros((len(fused), k))
        return ReadingDelays(fused.stamps, (fused.stamps - t0) * 1e-9, z, z.copy(), np.zeros(len(fused), bool), t0,
                             z.copy())
    idx = np.searchsorted(samples.stamps, fused.stamps)
    sel = samples.select(idx)
    tc = fused_timing_context(fused.stamps, np.concatenate([fused.omega, fused.omega_dot, fused.specific_force],
                                                           axis=1))
    ctx = motion_context(fused.stamps, fused.omega, fused.omega_dot, fused.specific_force, model.rotations,
                         t0_ns=t0, stamp_delays=sel.stamp_delays, **tc)
    jac = model.jacobians(ctx, free=["time_offset"], motion=False)
    w = np.where(sel.valid(model), 1.0 / model.std[None], 0.0)
    r = np.where(w > 0, sel.readings - jac.predicted, 0.0) * w
    col = {None: slice(None), "accelerometer": slice(0, 1), "gyroscope": slice(1, 2)}[sensor]
    j = jac.params["time_offset"][..., col].sum(axis=3) * w
    info = np.sum(j * j, axis=2)
    correction = np.sum(j * r, axis=2) / np.where(info > 0, info, 1.0)
    current = model.sample_delays(ctx)[..., TimeOffset.column(sensor)]
    moving = np.linalg.norm(tc["trajectory"].derivative()[:, 0:3], axis=1) > moving_rate  # the gyroscopes' rate
    return ReadingDelays(fused.stamps, ctx.t, current + correction, info, moving, t0, current)
