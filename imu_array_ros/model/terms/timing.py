"""Sample time: every reading is the signal at its sensor's true sample time, not at its stamp.

A *timing term* says how far the true sample time of a reading lies from the
array sample's stamp: its ``delay`` (N, K) in seconds (negative: the reading is
older than its stamp) for each sensor.  The model adds up the delays of every
timing term of a chain (and, for IMUs that stamp their own messages, each
message's own stamp minus the array stamp, ``MotionContext.stamp_delays``) into
one delay per reading, Delta, and evaluates the signal at ``stamp + Delta``, in
one stage at the timing terms' place in the chain (:class:`TimingStage`):

* to first order, x + Delta dx/dt, with dx/dt = R^T omega_dot for a gyroscope and
  R^T (ds/dt + dC/dt p) for an accelerometer (the sample's own omega and omega_dot,
  omega_ddot and ds/dt from the motion context).  The sample's own motion in the
  first-order term is what ties the estimate to its stamp: a common shift of every
  delay is then exactly absorbed by the motion, the gauge of time;
* plus, with a ``MotionContext.trajectory`` (the simulator's dense truth, or the
  local cubics through an estimated motion,
  :class:`~imu_array_ros.model.trajectory.MotionTrajectory`), the *remainder* the
  first order leaves out: the exact shift along the trajectory minus the
  trajectory's own first-order shift (second and higher order in the delay;
  held fixed, it depends on no sample's motion).  With the simulator's truth the
  reading is then exactly the motion at its true time (its omega_dot is the
  derivative of its omega); with an estimate it removes the truncation error.

The Jacobians: d y / d theta_j = (dx/dt + the change of the trajectory's rate
between the stamp and the reading's time) * d Delta_j / d theta_j.

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
        rate = ctx.omega_dot if ctx.omega_rate is None else ctx.omega_rate
        v = np.broadcast_to(rate[:, None, :], (ctx.n, ctx.k, 3))
    else:
        sd = ctx.specific_force_dot if ctx.specific_force_dot is not None else np.zeros_like(ctx.specific_force)
        v = sd[:, None, :] + np.einsum("nij,kj->nki", ctx.lever_dot, ctx.positions)
    return np.einsum("kji,nkj->nki", ctx.rotations, v)


def exact_shift(ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
    """(N, K, 3) x(stamp + delta) - x(stamp) of the ideal signal, both read from ``ctx.trajectory``
    (delta (N, K) s): the motion at every reading's own time minus the motion at its stamp."""
    traj = ctx.trajectory
    if hasattr(traj, "shift"):  # a trajectory that evaluates differences directly (the fusion's local cubics)
        if sensor == "gyroscope":
            return _to_sensor(ctx, traj.shift(delta, "omega"))
        ds, omega, omega_dot = traj.shift(delta, "specific_force"), *traj.at_delays(delta)
        omega0, omega_dot0, _ = traj.at_stamps()
        w0, wd0 = omega0[:, None], omega_dot0[:, None]
    else:
        when = ctx.stamps[:, None] + np.round(delta * 1e9).astype(np.int64)
        omega, omega_dot, s = traj(when)  # each (N, K, 3)
        omega0, omega_dot0, s0 = (a[:, 0] for a in traj(ctx.stamps[:, None]))
        if sensor == "gyroscope":
            return _to_sensor(ctx, omega - omega0[:, None])
        ds, w0, wd0 = s - s0[:, None], omega0[:, None], omega_dot0[:, None]
    p = ctx.positions[None]
    lever = _cross(omega, _cross(omega, p)) + _cross(omega_dot, p)
    lever0 = _cross(w0, _cross(w0, p)) + _cross(wd0, p)
    return _to_sensor(ctx, ds + lever - lever0)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcast), written out (faster than np.cross on small trailing axes)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _to_sensor(ctx: MotionContext, v: np.ndarray) -> np.ndarray:
    """(N, K, 3) R_k^T v_nk (v_nk^T R_k: one product per IMU)."""
    return np.matmul(v.transpose(1, 0, 2), ctx.rotations).transpose(1, 0, 2)


def _rate_along(ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
    """(N, K, 3) d/d delta of :func:`exact_shift`: the ideal signal's rate of change at stamp + delta."""
    when = ctx.stamps[:, None] + np.round(delta * 1e9).astype(np.int64)
    d_omega, d_omega_dot, d_s = ctx.trajectory.slope_at(when)
    if sensor == "gyroscope":
        v = d_omega
    else:
        omega, _, _ = ctx.trajectory(when)
        w, dw = skew(omega), skew(d_omega)
        lever_dot = np.einsum("nkij,nkjl->nkil", dw, w) + np.einsum("nkij,nkjl->nkil", w, dw) + skew(d_omega_dot)
        v = d_s + np.einsum("nkij,kj->nki", lever_dot, ctx.positions)
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
        first = delta[..., None] * signal_rate(ctx, sensor)
        if ctx.trajectory is None:
            return x + first
        return x + first + self.remainder(ctx, sensor, delta)

    @staticmethod
    def remainder(ctx: MotionContext, sensor: str, delta: np.ndarray) -> np.ndarray:
        """(N, K, 3) what the trajectory says the first-order shift leaves out: the exact shift along it minus
        its own first-order shift (second and higher order in the delay; independent of the sample's motion)."""
        if hasattr(ctx.trajectory, "slope_at"):
            rate0 = _rate_along(ctx, sensor, np.zeros_like(delta))
        else:  # a trajectory without slopes (the simulator's truth): the context's own rates
            rate0 = signal_rate(ctx, sensor)
        return exact_shift(ctx, sensor, delta) - delta[..., None] * rate0

    def d_input(self, x, ctx, sensor):
        return None

    def d_params_of(self, term: TimingTerm, x, ctx, sensor):
        """(N, K, 3, P) d apply / d theta_k of one member term: the first-order rate, plus, along a trajectory
        that gives slopes, the change of its rate between the stamp and the reading's own time."""
        rate = signal_rate(ctx, sensor)
        if ctx.trajectory is not None and hasattr(ctx.trajectory, "slope_at"):
            delta = self.delay(ctx, sensor)
            rate = rate + _rate_along(ctx, sensor, delta) - _rate_along(ctx, sensor, np.zeros_like(delta))
        return rate[..., None] * term.d_delay(ctx, sensor)[:, :, None, :]

    def d_motion(self, x, ctx, sensor):
        out = np.zeros(x.shape + (9,))  # the remainder along a trajectory is held: only the first order moves
        d = self.delay(ctx, sensor)  # (N, K)
        rt = ctx.rot_t
        if sensor == "gyroscope":
            if ctx.omega_rate is None:  # the rate is the sample's own omega_dot
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
