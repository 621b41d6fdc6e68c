"""Calibrations of the array (geometry, static multi-pose, PCA, Bayesian); filled by
the calibration issues."""
