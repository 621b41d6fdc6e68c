"""Motion generators for simulation (array/body frame, SI units).

* :func:`random_motion` — independent samples with set |omega|, |omega_dot|
  and random directions (the Monte Carlo setting of carlsson2017 Sec. IV).
* :class:`TwistTrajectory` — a smooth, continuous hand-twisting motion: omega(t)
  is a sum of sinusoids (analytic derivative omega_dot), the attitude is
  integrated from omega so that gravity turns in the body frame, and the
  translational acceleration is a smooth sway.  Specific force at the array
  origin: ``s = R^T (a_world - g_world)`` with ``g_world = [0, 0, -g]`` (ENU,
  REP-103), i.e. ``s = [0, 0, +g]`` at rest and level.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.model.constants import STANDARD_GRAVITY as GRAVITY
from imu_array_ros.model.samples import MotionTruth

__all__ = ["random_motion", "gaussian_motion", "TwistTrajectory", "quat_multiply", "quat_to_matrix", "quat_exp"]



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
        """Body -> world quaternions at sorted times ``t`` (s), integrating omega.

        Each interval is split into ``substeps`` midpoint-rule exponential steps
        of the body rate (q_dot = q * [0, omega/2]).
        """
        t = np.asarray(t, dtype=float)
        grid = np.concatenate([[t[0]], (t[:-1, None] + np.diff(t)[:, None] * (np.arange(1, substeps + 1) / substeps)).ravel()])
        mid = 0.5 * (grid[:-1] + grid[1:])
        inc = quat_exp(self.omega(mid) * np.diff(grid)[:, None])
        q = _cumulative_product(np.vstack([self.initial_attitude[None], inc]))
        return q[::substeps]

    def sample(self, stamps_ns: np.ndarray) -> MotionTruth:
        """Ground truth at ``stamps_ns`` (int64 ns, sorted)."""
        t = (np.asarray(stamps_ns, dtype=np.int64) - stamps_ns[0]) * 1e-9
        q = self.attitude(t)
        rot = quat_to_matrix(q)
        g_world = np.array([0.0, 0.0, -GRAVITY])
        s = np.einsum("nji,nj->ni", rot, self.acceleration_world(t) - g_world)
        return MotionTruth(stamps=np.asarray(stamps_ns, dtype=np.int64), omega=self.omega(t),
                           omega_dot=self.omega_dot(t), specific_force=s, attitude=q)
