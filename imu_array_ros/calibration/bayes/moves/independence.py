"""The independence proposal: a multivariate t around the Laplace approximation."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["IndependenceT", "IND_DOF"]

#: degrees of freedom of the independence proposal's multivariate t (heavier tails than the posterior)
IND_DOF = 10.0


@dataclass(frozen=True)
class IndependenceT:
    """theta' ~ t_nu(mean, L L^T), independent of theta.

    mean (d,), chol: L (d, d) (the Laplace approximation, moved toward the warm-up's draws); dof: nu.
    Not symmetric: the Metropolis-Hastings ratio carries q(theta) / q(theta') (:meth:`log_correction`).
    Where the posterior is close to its Laplace approximation most proposals are accepted and each one
    jumps across the whole posterior; the heavier tails keep q(theta) / q(theta') bounded.
    """

    mean: np.ndarray
    chol: np.ndarray
    dof: float = IND_DOF
    chol_inv: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "chol_inv", np.linalg.inv(self.chol))

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """(n, d) proposals: mean + L z sqrt(nu / chi2_nu), the n chi-square draws first, then the
        (n, d) standard normals."""
        w = np.sqrt(self.dof / rng.chisquare(self.dof, n))
        return self.mean + (rng.standard_normal((n, len(self.mean))) @ self.chol.T) * w[:, None]

    def propose(self, theta: np.ndarray, draw: np.ndarray) -> np.ndarray:
        return draw

    def log_density(self, theta: np.ndarray) -> float:
        """log q(theta) up to a constant: -(nu + d)/2 log(1 + |L^-1 (theta - mean)|^2 / nu)."""
        z = self.chol_inv @ (theta - self.mean)
        return -0.5 * (self.dof + len(theta)) * np.log1p(float(z @ z) / self.dof)

    def log_correction(self, theta: np.ndarray, proposal: np.ndarray) -> float:
        """log q(theta) - log q(theta')."""
        return self.log_density(theta) - self.log_density(proposal)
