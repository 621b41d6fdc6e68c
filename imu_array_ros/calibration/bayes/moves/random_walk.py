"""The Gaussian random-walk proposal (carlsson2021 eq. 27)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

__all__ = ["RandomWalk"]


@dataclass(frozen=True)
class RandomWalk:
    """theta' = theta + scale L z, z ~ N(0, I_d): symmetric, so no correction.

    chol: L (d, d), the shape (the identity: the paper's isotropic sigma_q I, eq. 27, with sigma_q =
    ``scale``; a Cholesky factor of the Laplace covariance: a walk shaped like the posterior); scale: the
    step length, tuned during the warm-up toward a target acceptance.
    """

    chol: np.ndarray
    scale: float

    @classmethod
    def isotropic(cls, d: int, sigma_q: float) -> "RandomWalk":
        """carlsson2021 eq. 27: N(theta, sigma_q^2 I_d)."""
        return cls(np.eye(d), float(sigma_q))

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """(n, d) steps: n standard normal vectors (one ``standard_normal((n, d))`` call) times scale L."""
        return rng.standard_normal((n, len(self.chol))) @ self.chol.T * self.scale

    def propose(self, theta: np.ndarray, step: np.ndarray) -> np.ndarray:
        return theta + step

    def log_correction(self, theta: np.ndarray, proposal: np.ndarray) -> float:
        return 0.0

    def rescaled(self, factor: float) -> "RandomWalk":
        """The same shape with the step length times ``factor``."""
        return replace(self, scale=self.scale * factor)

    def reshaped(self, chol: np.ndarray) -> "RandomWalk":
        """A new shape (d, d), the step length kept (it is relative to the shape)."""
        return replace(self, chol=np.asarray(chol, dtype=float))
