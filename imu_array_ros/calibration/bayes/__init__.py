"""Bayesian calibration of the accelerometer positions: the PmMH posterior of carlsson2021.

The posterior p(theta | y_1:T) of the positions theta of every IMU but the reference, sampled by
(correlated) pseudo-marginal Metropolis-Hastings on the Rao-Blackwellised likelihood (eq. 26), with
its Laplace approximation as the start, the proposals' shape and the check.  By concept:

``model``
    :func:`affine_model`: the sensor model as the paper's (affine in the motion); the compensated readings.
``problem``
    :class:`Prior`, :class:`BayesProblem` (the likelihood, its coefficients; the paper erratum on the
    determinant's exponent), :func:`select_samples`, :func:`build_problem`, :func:`loglik_variance`.
``laplace_approx``
    :class:`Laplace`, :func:`laplace`, :func:`sample_gyro_std`, the log-determinant correction (eq. 23).
``moves``
    the proposals, one small class each: :class:`RandomWalk` (eq. 27) and :class:`IndependenceT`.
``chain``
    :class:`ChainState`, :func:`initial_state`, :func:`run_chunk`: the PmMH loop with correlated random numbers.
``runners``
    :class:`ChainRunner` (processes, Dask, serial), :func:`dask_client`.
``sampler``
    :class:`SamplerSettings`, :func:`choose_draws`, :func:`sample_posterior` (tuning N, warm-up, R-hat,
    ESS), :func:`laplace_agreement`, :func:`install_allowance`.
``posterior``
    :class:`BayesPosterior`, :func:`chain_diagnostics`, :func:`arviz`.
``report``
    plots (ellipses, trace, autocorrelation), tables (diagnostics, disagreements, markdown) and
    :func:`write_report` (the files).

Importing this package imports numpy and the core only: ArviZ and Dask (the ``[bayes]`` extra) and
matplotlib (``[plots]``) are imported when a function needs them, with a one-line error naming the
extra when missing.
"""

from imu_array_ros.calibration.bayes.chain import ChainState, ChunkResult, initial_state, run_chunk
from imu_array_ros.calibration.bayes.laplace_approx import Laplace, laplace, logdet_correction, sample_gyro_std
from imu_array_ros.calibration.bayes.model import AFFINE_RTOL, Compensated, affine_model, compensate
from imu_array_ros.calibration.bayes.moves import IND_DOF, IndependenceT, RandomWalk
from imu_array_ros.calibration.bayes.posterior import BayesPosterior, arviz, chain_diagnostics, imu_covariances
from imu_array_ros.calibration.bayes.problem import OMEGA_COVARIANCES, PACKAGE_SIZE, PRIOR_STD, BayesProblem, \
    Prior, build_problem, likelihood_coefficients, loglik_variance, select_samples
from imu_array_ros.calibration.bayes.report import BAYES_REPORT_NETCDF, BAYES_REPORT_PNGS, BAYES_REPORT_TEXT, \
    ESTIMATE_COLORS, PRIOR_COLOR, SD_RATIO_RANGE, Z_LIMIT, diagnostics_table, disagreements, ellipse_points, \
    ellipse_radius, lowest_ess_coords, panel_layout, plot_autocorr, plot_ellipses, plot_trace, write_report
from imu_array_ros.calibration.bayes.runners import ChainRunner, dask_client
from imu_array_ros.calibration.bayes.sampler import AGREE_MEAN_Z, AGREE_SD_RATIO, MAX_DRAWS, PROPOSALS, \
    UNTUNABLE, VAR_REPLICATES, WARMUP_KEEP, WARMUP_RHAT, SamplerSettings, choose_draws, install_allowance, \
    laplace_agreement, sample_posterior

__all__ = [
    # the model and the problem
    "affine_model", "compensate", "Compensated", "AFFINE_RTOL",
    "Prior", "BayesProblem", "build_problem", "select_samples", "loglik_variance", "likelihood_coefficients",
    "PRIOR_STD", "PACKAGE_SIZE", "OMEGA_COVARIANCES",
    # the Laplace approximation
    "Laplace", "laplace", "sample_gyro_std", "logdet_correction",
    # the proposals and the chain
    "RandomWalk", "IndependenceT", "IND_DOF", "ChainState", "ChunkResult", "initial_state", "run_chunk",
    # running and diagnosing the chains
    "ChainRunner", "dask_client", "SamplerSettings", "sample_posterior", "choose_draws", "laplace_agreement",
    "install_allowance", "PROPOSALS", "VAR_REPLICATES", "MAX_DRAWS", "UNTUNABLE", "WARMUP_RHAT", "WARMUP_KEEP",
    "AGREE_MEAN_Z", "AGREE_SD_RATIO", "BayesPosterior", "chain_diagnostics", "arviz", "imu_covariances",
    # the report
    "write_report", "diagnostics_table", "disagreements", "lowest_ess_coords", "plot_ellipses", "plot_trace",
    "plot_autocorr", "ellipse_points", "ellipse_radius", "panel_layout", "Z_LIMIT", "SD_RATIO_RANGE",
    "PRIOR_COLOR", "ESTIMATE_COLORS", "BAYES_REPORT_TEXT", "BAYES_REPORT_PNGS", "BAYES_REPORT_NETCDF",
]
