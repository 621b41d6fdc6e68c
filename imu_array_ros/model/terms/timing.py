"""Sample time: every reading is the signal at its sensor's true sample time, not at its stamp.

A *timing term* says how far the true sample time of a reading lies from the
array sample's stamp: its ``delay`` (N, K) in seconds (negative: the reading is
older than its stamp) for each sensor.  The model adds up the delays of every
timing term of a chain (and, for IMUs that stamp their own messages, each
message's own stamp minus the array stamp, ``MotionContext.stamp_delays``) into
one delay per reading, Delta, and evaluates the signal at ``stamp + Delta``, in
one stage at the timing terms' place in the chain (:class:`TimingStage`):

* with a ``MotionContext.trajectory`` (the simulator's dense truth, or the
  fusion's interpolant of its own estimate): exactly, the motion evaluated at
  the true time;
* otherwise to first order, x + Delta dx/dt, with dx/dt = R^T omega_dot for a
  gyroscope and R^T (ds/dt + dC/dt p) for an accelerometer (omega_ddot and
  ds/dt from the motion context).  This is what the fitting engine linearises:
  d y / d theta_j = dx/dt * d Delta_j / d theta_j.

Time is relative: a delay common to every sensor of every IMU moves no reading
relative to another and is absorbed by the motion (per sample).  The gauge:
the fused motion refers to the instant the model calls Delta = 0, the array
stamp (for the sample clock, see :mod:`.sample_clock`).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.terms.base import MotionContext, Term

__all__ = ["TimingTerm", "TimingStage", "signal_rate", "exact_shift"]


class TimingTerm(Term):
    """A term that moves the sample time of readings (see module docstring).  Subclasses define
    :meth:`delay` and :meth:`d_delay`; the model applies the sum of the chain's delays once."""

    sensors = ("accelerometer", "gyroscope")
    order = 2
    candidate = False  # the dedicated estimators of :mod:`imu_array_ros.timing` set them up
    linear = False  # the accelerometer's shift needs ds/dt, which is not in the motion

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        """(N, K) s: true sample time minus stamp of ``sensor``'s readings."""
        raise NotImplementedError

    def d_delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        """(N, K, P) d delay / d theta_k."""
        raise NotImplementedError

    # alone (outside a TimingStage) a timing term acts as a first-order shift by its own delay
    def apply(self, x, ctx, sensor):
        return TimingStage([self]).apply(x, ctx, sensor)

    def d_params(self, x, ctx, sensor):
        return TimingStage([self]).d_params_of(self, x, ctx, sensor)

    def d_motion(self, x, ctx, sensor):
        return TimingStage([self]).d_motion(x, ctx, sensor)

    def d_positions(self, x, ctx, sensor):
        return TimingStage([self]).d_positions(x, ctx, sensor)


def signal_rate(ctx: MotionContext, sensor: str) -> np.ndarray:
    """(N, K, 3) dx/dt of the sensor's ideal signal in its (nominal) frame."""
    if sensor == "gyroscope":
        v = np.broadcast_to(ctx.omega_dot[:, None, :], (ctx.n, ctx.k, 3))
    else:
        sd = ctx.specific_force_dot if ctx.specific_force_dot is not None else np.zeros_like(ctx.specific_force)
        v = sd[:, None, :] + np.einsum("nij,kj->nki", ctx.lever_dot, ctx.positions)
    return np.einsum("kji,nkj->nki", ctx.rotations, v)


def exact_shift(ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
    """(N, K, 3) x(stamp + delta) - x(stamp) of the ideal signal, the motion read from ``ctx.trajectory``
    at every reading's own time (delta (N, K) s) and from the context at the stamps."""
    when = ctx.stamps[:, None] + np.round(delta * 1e9).astype(np.int64)
    omega, omega_dot, s = ctx.trajectory(when)  # each (N, K, 3)
    if sensor == "gyroscope":
        v = omega - ctx.omega[:, None, :]
    else:
        p = ctx.positions
        w, wd = skew(omega), skew(omega_dot)  # (N, K, 3, 3)
        lever = np.einsum("nkij,nkjl->nkil", w, w) + wd
        v = s + np.einsum("nkij,kj->nki", lever, p) - ctx.force_at(p)
    return np.einsum("kji,nkj->nki", ctx.rotations, v)


class TimingStage:
    """The timing terms of one chain applied as one stage: the signal at stamp + the sum of their delays
    (+ the context's stamp delays).  Quacks like a :class:`Term` in the model's chain."""

    name = "timing"
    order = TimingTerm.order

    def __init__(self, terms: list[TimingTerm]) -> None:
        self.terms = list(terms)

    def delay(self, ctx: MotionContext, sensor: str) -> np.ndarray:
        out = np.zeros((ctx.n, ctx.k)) if ctx.stamp_delays is None else np.array(ctx.stamp_delays, dtype=float)
        for t in self.terms:
            out = out + t.delay(ctx, sensor)
        return out

    def apply(self, x, ctx, sensor):
        delta = self.delay(ctx, sensor)
        if ctx.trajectory is not None:
            return x + exact_shift(ctx, sensor, delta)
        return x + delta[..., None] * signal_rate(ctx, sensor)

    def d_input(self, x, ctx, sensor):
        return None

    def d_params_of(self, term: TimingTerm, x, ctx, sensor):
        """(N, K, 3, P) d apply / d theta_k of one member term (first order)."""
        return signal_rate(ctx, sensor)[..., None] * term.d_delay(ctx, sensor)[:, :, None, :]

    def d_motion(self, x, ctx, sensor):
        d = self.delay(ctx, sensor)  # (N, K)
        out = np.zeros(x.shape + (9,))
        rt = ctx.rot_t
        if sensor == "gyroscope":
            out[..., 3:6] = d[..., None, None] * rt[None]
            return out
        p = ctx.positions
        sw, swd, sp = skew(ctx.omega)[:, None], skew(ctx.omega_dot)[:, None], skew(p)[None]
        # d(C_dot p)/d omega = -[w_dot]x[p]x - [w_dot x p]x ; d/d omega_dot = -[w x p]x - [w]x[p]x
        d_w = -swd @ sp - skew(np.cross(ctx.omega_dot[:, None], p[None]))
        d_wd = -skew(np.cross(ctx.omega[:, None], p[None])) - sw @ sp
        out[..., 0:3] = d[..., None, None] * (rt[None] @ d_w)
        out[..., 3:6] = d[..., None, None] * (rt[None] @ d_wd)
        return out

    def d_positions(self, x, ctx, sensor):
        if sensor == "gyroscope":
            return None
        d = self.delay(ctx, sensor)
        return d[..., None, None] * np.einsum("kji,njl->nkil", ctx.rotations, ctx.lever_dot)  # d R^T C_dot p / d p
