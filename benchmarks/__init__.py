"""Benchmarks of imu_array_ros: speed, accuracy and reproductions of the papers' figures.

Run from the repository root: ``python -m benchmarks.<name> [args]``; results go to benchmarks/results/
(tables and figures written by the scripts, each file's ``## Interpretation`` written by a person;
see :mod:`benchmarks.harness`).
"""
