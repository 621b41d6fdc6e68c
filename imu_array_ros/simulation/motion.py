"""Motion generators for simulation (array/body frame, SI units).

* :func:`random_motion` — independent samples with set |omega|, |omega_dot|
  and random directions (the Monte Carlo setting of carlsson2017 Sec. IV).
* :class:`TwistTrajectory` — a smooth, continuous hand-twisting motion: omega(t)
  is a sum of sinusoids (analytic derivative omega_dot), the attitude is
  integrated from omega so that gravity turns in the body frame, and the
  translational acceleration is a smooth sway.  Specific force at the array
  origin: ``s = R^T (a_world - g_world)`` with ``g_world = [0, 0, -g]`` (ENU,
  REP-103), i.e. ``s = [0, 0, +g]`` at rest and level.  :meth:`TwistTrajectory.sample`
  gives the truth at sorted stamps; :meth:`TwistTrajectory.motion_at` at any int64 ns
  times from an origin, and :class:`TrajectoryFunction` (:meth:`TwistTrajectory.function`)
  is the motion as a function of time that the timing stage reads every reading's
  true sample time from (``MotionContext.trajectory``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.model.constants import STANDARD_GRAVITY as GRAVITY
from imu_array_ros.model.samples import MotionTruth

__all__ = ["random_motion", "gaussian_motion", "TwistTrajectory", "TrajectoryFunction", "quat_multiply",
           "quat_to_matrix", "quat_exp"]


def _unit(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def random_motion(
    n: int,
    omega_norm: float,
    omega_dot_norm: float,
    rng: np.random.Generator,
    *,
    specific_force_norm: float = GRAVITY,
    omega_direction: np.ndarray | None = None,
    rate_hz: float = 1000.0,
    start_ns: int = 0,
) -> MotionTruth:
    """``n`` independent motion samples (carlsson2017 Sec. IV).

    Directions of omega, omega_dot and the specific force are uniform on the
    sphere unless ``omega_direction`` fixes omega's (skog2016 Fig. 5: rotation
    about x or z).  Stamps are spaced 1/rate_hz apart from ``start_ns`` (ns
    since the epoch; no time continuity).
    """
    if omega_direction is None:
        omega = omega_norm * _unit(rng, n)
    else:
        d = np.asarray(omega_direction, dtype=float)
        omega = np.broadcast_to(omega_norm * d / np.linalg.norm(d), (n, 3)).copy()
    stamps = int(start_ns) + (np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    return MotionTruth(
        stamps=stamps,
        omega=omega,
        omega_dot=omega_dot_norm * _unit(rng, n),
        specific_force=specific_force_norm * _unit(rng, n),
    )


def gaussian_motion(n: int, omega_std: float, omega_dot_std: float, specific_force_std: float,
                    rng: np.random.Generator, *, rate_hz: float = 1000.0, start_ns: int = 0) -> MotionTruth:
    """``n`` independent motion samples, every component of omega, omega_dot and the specific force
    zero-mean Gaussian with the given stds (carlsson2021 Sec. IV-A: 1000 deg/s, 35000 deg/s^2, 20 m/s^2)."""
    stamps = int(start_ns) + (np.arange(n) * (1e9 / rate_hz)).astype(np.int64)
    return MotionTruth(stamps=stamps, omega=omega_std * rng.normal(size=(n, 3)),
                       omega_dot=omega_dot_std * rng.normal(size=(n, 3)),
                       specific_force=specific_force_std * rng.normal(size=(n, 3)))


# --------------------------------------------------------------------------- quaternions [w, x, y, z]


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p * q of (..., 4) quaternions [w, x, y, z]."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of a rotation vector (..., 3) -> (..., 4)."""
    angle = np.linalg.norm(rotvec, axis=-1)
    half = 0.5 * angle
    k = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half)[..., None], rotvec * k[..., None]], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4), body -> world."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _cumulative_product(q: np.ndarray) -> np.ndarray:
    """Prefix products q0 * q1 * ... * qi, vectorized by doubling (Hillis-Steele scan)."""
    out = q.copy()
    step = 1
    while step < len(out):
        out[step:] = quat_multiply(out[:-step], out[step:])
        step *= 2
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _integrate(omega, t: np.ndarray, q_start: np.ndarray, substeps: int) -> np.ndarray:
    """Body -> world quaternions at times ``t`` (s, monotonic) from ``q_start`` at t[0]: ``substeps``
    midpoint-rule exponential steps of the body rate ``omega(t)`` per interval."""
    fractions = np.arange(1, substeps + 1) / substeps
    grid = np.concatenate([[t[0]], (t[:-1, None] + np.diff(t)[:, None] * fractions).ravel()])
    mid = 0.5 * (grid[:-1] + grid[1:])
    inc = quat_exp(omega(mid) * np.diff(grid)[:, None])
    q = _cumulative_product(np.vstack([q_start[None], inc]))
    return q[::substeps]


_KNOT_BLOCK = 4096  # knots integrated per block (bounds the scan's memory on long recordings)
_G_WORLD = np.array([0.0, 0.0, -GRAVITY])  # ENU (REP-103)


# --------------------------------------------------------------------------- hand twisting


@dataclass(frozen=True)
class TwistTrajectory:
    """Smooth hand-twisting motion (see module docstring).

    omega(t) = sum_j a_j sin(2 pi f_j t + p_j) per axis, j = 1..3 components
    with frequencies in [0.3, 2.5] Hz, scaled so that the RMS angular speed is
    ``rms_rate`` rad/s; sway acceleration of ``sway`` m/s^2 RMS per axis.
    """

    amplitudes: np.ndarray  # (3 axes, J) rad/s
    frequencies: np.ndarray  # (3, J) Hz
    phases: np.ndarray  # (3, J) rad
    sway_amplitudes: np.ndarray  # (3, J) m/s^2
    sway_frequencies: np.ndarray
    sway_phases: np.ndarray
    initial_attitude: np.ndarray  # (4,) body -> world

    @classmethod
    def random(cls, rng: np.random.Generator, *, rms_rate: float = np.deg2rad(600.0), sway: float = 2.0,
               components: int = 3) -> "TwistTrajectory":
        f = rng.uniform(0.3, 2.5, (3, components))
        a = rng.normal(size=(3, components))
        a *= rms_rate / np.sqrt(0.5 * np.sum(a**2))  # E|omega|^2 = sum a^2 / 2
        sf = rng.uniform(0.2, 1.5, (3, components))
        sa = rng.normal(size=(3, components))
        sa *= sway * np.sqrt(3) / np.sqrt(0.5 * np.sum(sa**2))
        q0 = rng.normal(size=4)
        return cls(a, f, rng.uniform(0, 2 * np.pi, (3, components)), sa, sf,
                   rng.uniform(0, 2 * np.pi, (3, components)), q0 / np.linalg.norm(q0))

    def omega(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.frequencies[None] * t[:, None, None] + self.phases[None]
        return np.sum(self.amplitudes[None] * np.sin(arg), axis=2)

    def omega_dot(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.frequencies[None] * t[:, None, None] + self.phases[None]
        return np.sum(self.amplitudes[None] * 2 * np.pi * self.frequencies[None] * np.cos(arg), axis=2)

    def acceleration_world(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * self.sway_frequencies[None] * t[:, None, None] + self.sway_phases[None]
        return np.sum(self.sway_amplitudes[None] * np.sin(arg), axis=2)

    def attitude(self, t: np.ndarray, substeps: int = 8) -> np.ndarray:
        """Body -> world quaternions at sorted times ``t`` (s), integrating omega from
        ``initial_attitude`` at ``t[0]``.

        Each interval is split into ``substeps`` midpoint-rule exponential steps
        of the body rate (q_dot = q * [0, omega/2]); times may also decrease (a
        backward integration).  The error grows with the interval: at 62.5 Hz
        (16 ms intervals) the specific force drifts by ~2e-3 m/s^2 in 20 s from a
        much finer integration, at 1 kHz by ~1e-5 m/s^2 (see :meth:`motion` for a
        grid that does not depend on the times asked for).
        """
        return _integrate(self.omega, np.asarray(t, dtype=float), self.initial_attitude, substeps)

    def motion(self, t: np.ndarray, *, step: float | None = None, substeps: int = 8):
        """(omega, omega_dot, specific_force, attitude) at times ``t`` (s since the origin, where the
        attitude is ``initial_attitude``; any shape, unsorted, negative allowed), each t.shape + (3,)
        (attitude + (4,)).

        ``step`` None: the attitude is integrated over the sorted unique times (and the origin), forward
        from the origin and backward to the times before it, like :meth:`sample`: at sorted times
        starting at the origin the result equals :meth:`sample`'s bit for bit, and it depends on the
        other times asked for (their intervals are the integration's).  ``step`` (s): the attitude is
        integrated on the knots j * step (from the origin outwards, ``substeps`` steps per knot
        interval) and from the knot between the origin and each time, nearest to it, to the time
        itself in ``substeps`` steps: a function of each time alone, whatever else is asked for.
        With step 1e-3 and 8 substeps the specific force stays within ~1e-5 m/s^2 of an integration
        with 10 times shorter steps over 20 s of 600 deg/s twisting.
        """
        t = np.asarray(t, dtype=float)
        flat = t.ravel()
        if substeps < 1 or (step is not None and not step > 0):
            raise ValueError(f"attitude integration: step must be > 0 s and substeps >= 1, got {step}, {substeps}")
        q = self._attitude_sorted(flat, substeps) if step is None else self._attitude_knots(flat, float(step), substeps)
        rot = quat_to_matrix(q)
        s = np.einsum("nji,nj->ni", rot, self.acceleration_world(flat) - _G_WORLD)
        shape = t.shape
        return (self.omega(flat).reshape(shape + (3,)), self.omega_dot(flat).reshape(shape + (3,)),
                s.reshape(shape + (3,)), q.reshape(shape + (4,)))

    def motion_at(self, stamps_ns: np.ndarray, origin_ns: int, *, step: float | None = None, substeps: int = 8):
        """:meth:`motion` at int64 ns stamps of any shape, times counted from ``origin_ns``."""
        t = (np.asarray(stamps_ns, dtype=np.int64) - np.int64(origin_ns)) * 1e-9
        return self.motion(t, step=step, substeps=substeps)

    def function(self, origin_ns: int, *, step: float = 1e-3, substeps: int = 8) -> "TrajectoryFunction":
        """The motion as a function of int64 ns time from ``origin_ns`` (knots every ``step`` s, see
        :meth:`motion`): what :attr:`MotionContext.trajectory <imu_array_ros.model.terms.base.MotionContext>`
        takes."""
        if substeps < 1 or not step > 0:
            raise ValueError(f"trajectory function: step must be > 0 s and substeps >= 1, got {step}, {substeps}")
        return TrajectoryFunction(self, int(origin_ns), float(step), int(substeps))

    def _attitude_sorted(self, t: np.ndarray, substeps: int) -> np.ndarray:
        u, inv = np.unique(t, return_inverse=True)
        q = np.empty((len(u), 4))
        fwd, back = u >= 0, u < 0
        if fwd.any():
            tf = u[fwd]
            q[fwd] = self.attitude(tf, substeps) if tf[0] == 0 else self.attitude(np.r_[0.0, tf], substeps)[1:]
        if back.any():
            q[back] = self.attitude(np.r_[0.0, u[back][::-1]], substeps)[1:][::-1]
        return q[inv.ravel()]

    def _attitude_knots(self, t: np.ndarray, step: float, substeps: int) -> np.ndarray:
        j = np.trunc(t / step).astype(np.int64)  # the knot between the origin and t, nearest to t
        q_fwd = self._knots(max(int(j.max(initial=0)), 0), step, substeps)
        q_back = self._knots(min(int(j.min(initial=0)), 0), step, substeps)
        q = np.where((j >= 0)[:, None], q_fwd[np.maximum(j, 0)], q_back[np.maximum(-j, 0)])
        tk = j * step
        h = (t - tk) / substeps
        for m in range(substeps):
            q = quat_multiply(q, quat_exp(self.omega(tk + (m + 0.5) * h) * h[:, None]))
        return q / np.linalg.norm(q, axis=-1, keepdims=True)

    def _knots(self, last: int, step: float, substeps: int) -> np.ndarray:
        """Attitudes at the knots sign(last) * j * step, j = 0 .. |last|, integrated from the origin in
        blocks of knots (the same blocks whatever ``last`` is, so a knot's value depends on its index only)."""
        n, sign = abs(last), (1.0 if last >= 0 else -1.0)
        out = np.empty((n + 1, 4))
        out[0] = self.initial_attitude
        for a in range(0, n, _KNOT_BLOCK):
            b = min(a + _KNOT_BLOCK, n)
            out[a + 1:b + 1] = _integrate(self.omega, sign * np.arange(a, b + 1) * step, out[a], substeps)[1:]
        return out

    def sample(self, stamps_ns: np.ndarray) -> MotionTruth:
        """Ground truth at ``stamps_ns`` (int64 ns, sorted), the attitude integrated over the stamps
        from ``initial_attitude`` at the first stamp (:meth:`attitude`)."""
        t = (np.asarray(stamps_ns, dtype=np.int64) - stamps_ns[0]) * 1e-9
        q = self.attitude(t)
        rot = quat_to_matrix(q)
        s = np.einsum("nji,nj->ni", rot, self.acceleration_world(t) - _G_WORLD)
        return MotionTruth(stamps=np.asarray(stamps_ns, dtype=np.int64), omega=self.omega(t),
                           omega_dot=self.omega_dot(t), specific_force=s, attitude=q)


@dataclass(frozen=True)
class TrajectoryFunction:
    """A :class:`TwistTrajectory` as a function of int64 ns time (:meth:`TwistTrajectory.function`).

    Called with stamps of any shape it returns (omega, omega_dot, specific_force), each
    stamps.shape + (3,), array frame: the ``MotionContext.trajectory`` of the timing stage.  Every
    time's value depends on that time alone (the knots of :meth:`TwistTrajectory.motion`), so the
    truth at the stamps (:meth:`truth`) and the readings at their true sample times come from one
    and the same motion.
    """

    trajectory: TwistTrajectory
    origin_ns: int
    step: float = 1e-3
    substeps: int = 8

    def seconds(self, t: np.ndarray):
        """(omega, omega_dot, specific_force, attitude) at float times ``t`` (s since ``origin_ns``)."""
        return self.trajectory.motion(t, step=self.step, substeps=self.substeps)

    def __call__(self, stamps_ns: np.ndarray):
        return self.trajectory.motion_at(stamps_ns, self.origin_ns, step=self.step, substeps=self.substeps)[:3]

    def truth(self, stamps_ns: np.ndarray) -> MotionTruth:
        """Ground truth at ``stamps_ns`` (N,) from this function."""
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        omega, omega_dot, s, q = self.trajectory.motion_at(stamps, self.origin_ns, step=self.step,
                                                           substeps=self.substeps)
        return MotionTruth(stamps=stamps, omega=omega, omega_dot=omega_dot, specific_force=s, attitude=q)
