"""How the fitting engine parametrises each sample's motion: the nuisance of every calibration.

The sensor model reads the motion of sample n as x_n = [omega, omega_dot, s] (9,)
in the array frame.  A *motion model* says which x_n are allowed and by which
coordinates z_n (``dim`` of them) the engine estimates them:

* :class:`RigidMotion` (the default): any rigid-body motion, z_n = x_n (9).
  Every dynamic calibration (positions, time offsets, ...) uses it.
* :class:`StaticMotion`: the array at rest, omega = omega_dot = 0 and a
  specific force of known magnitude g (local gravity) in an unknown direction,
  z_n (2) -- nilsson2014's pose nuisance (its pitch and roll).  This is what
  makes static multi-pose calibration possible: with |s| = g known, the
  accelerometer gains and biases of every IMU are identifiable.

The engine needs ``expand`` (z -> x) and its Jacobian dx/dz (None when the
identity), both batched over samples.  For the static model the direction is
u_n = (a_n + T_n z_n) / |a_n + T_n z_n| with a fixed anchor a_n (the initial
direction) and an orthonormal tangent basis T_n of it: no singular pole (unlike
pitch/roll at +-90 deg) and z_n stays small.  The Earth's rotation (7.3e-5 rad/s)
is left out of the static model: the gyroscope biases absorb its mean.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.constants import STANDARD_GRAVITY

__all__ = ["RigidMotion", "StaticMotion"]


class RigidMotion:
    """Any rigid-body motion: z_n = [omega, omega_dot, s] (9), the identity parametrisation."""

    dim = 9
    name = "rigid"

    def initial(self, x: np.ndarray) -> np.ndarray:
        """Coordinates of the (N, 9) initial motion x."""
        return x

    def expand(self, z: np.ndarray, sel=slice(None)) -> np.ndarray:
        return z

    def jacobian(self, z: np.ndarray, sel=slice(None)) -> np.ndarray | None:
        return None


class StaticMotion:
    """At rest on local gravity: omega = omega_dot = 0, |s| = ``gravity``; z_n (2) tangent coordinates."""

    dim = 2
    name = "static"

    def __init__(self, gravity: float = STANDARD_GRAVITY) -> None:
        if not np.isfinite(gravity) or gravity <= 0:
            raise ValueError(f"gravity must be positive, got {gravity!r}")
        self.gravity = float(gravity)
        self.anchors: np.ndarray | None = None
        self.tangents: np.ndarray | None = None

    def initial(self, x: np.ndarray) -> np.ndarray:
        """Anchor every sample at the direction of the initial specific force x[:, 6:9]; z = 0."""
        s = np.asarray(x, dtype=float)[:, 6:9]
        norm = np.linalg.norm(s, axis=1, keepdims=True)
        a = np.where(norm > 0, s / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
        # tangent basis: e = the coordinate axis least aligned with a, t1 = a x e normalised, t2 = a x t1
        e = np.eye(3)[np.argmin(np.abs(a), axis=1)]
        t1 = np.cross(a, e)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(a, t1)
        self.anchors, self.tangents = a, np.stack([t1, t2], axis=2)
        return np.zeros((len(s), 2))

    def directions(self, z: np.ndarray, sel=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """(unit directions u (n, 3), |v| (n,)) of the samples ``sel``, v = a + T z."""
        v = self.anchors[sel] + np.einsum("nij,nj->ni", self.tangents[sel], z)
        norm = np.linalg.norm(v, axis=1)
        return v / norm[:, None], norm

    def expand(self, z: np.ndarray, sel=slice(None)) -> np.ndarray:
        u, _ = self.directions(z, sel)
        return np.concatenate([np.zeros((len(u), 6)), self.gravity * u], axis=1)

    def jacobian(self, z: np.ndarray, sel=slice(None)) -> np.ndarray:
        """(n, 9, 2) dx/dz: only the specific-force rows, g (I - u u^T) T / |v|."""
        u, norm = self.directions(z, sel)
        proj = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
        out = np.zeros((len(u), 9, 2))
        out[:, 6:9] = self.gravity * np.matmul(proj, self.tangents[sel]) / norm[:, None, None]
        return out
