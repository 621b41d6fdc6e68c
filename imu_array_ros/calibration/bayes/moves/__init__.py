"""The proposals of theta, one small class each (as emcee's moves).

Every proposal has the same three methods, so the chain (:func:`~imu_array_ros.calibration.bayes.chain.run_chunk`)
treats them alike:

``draw(rng, n) -> (n, d)``
    the random numbers of ``n`` proposals, drawn for a whole chunk at once (the order in which the chain
    calls ``draw`` fixes the stream of random numbers, hence every chain);
``propose(theta, row) -> theta'``
    the proposal from the current theta (d,) and one row of the batch;
``log_correction(theta, theta') -> float``
    log q(theta | theta') - log q(theta' | theta), added to the Metropolis-Hastings log ratio
    (0 for a symmetric proposal).

:class:`RandomWalk` is the Gaussian random walk of carlsson2021 eq. 27 (isotropic, sigma_q I, or shaped by
the Laplace covariance); :class:`IndependenceT` draws from a multivariate t around the Laplace
approximation, independently of theta.
"""

from imu_array_ros.calibration.bayes.moves.independence import IND_DOF, IndependenceT
from imu_array_ros.calibration.bayes.moves.random_walk import RandomWalk

__all__ = ["RandomWalk", "IndependenceT", "IND_DOF"]
