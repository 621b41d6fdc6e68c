"""``imu-array calibrate METHOD``: calibrations that install a calibrated description.

One module per method, each with its parser beside its handler; every handler
reads the recording for the array, runs :func:`imu_array_ros.workflows.calibrate`
(one :class:`~imu_array_ros.calibration.result.Calibration` result) and installs
it with ``Calibration.install`` (atomic, the previous file kept as ``OUT.bak``,
refused when the file there fits the calibration's data better):

* :mod:`.fit` -- any sensor-model terms jointly with the motion (the fitting engine);
* :mod:`.geometry` -- the accelerometer positions from hand twisting (carlsson2017);
* :mod:`.bayes` -- the posterior of the positions (carlsson2021 PmMH);
* :mod:`.static` -- accelerometer intrinsics and gyroscope biases from still poses;
* :mod:`.whole_array` -- ``calibrate all``: still poses, then the moving phase;
* :mod:`.noise` -- each IMU's noise figures from the Allan deviation of the still intervals.
"""

from __future__ import annotations

import argparse

from imu_array_ros.cli.calibrate import bayes, fit, geometry, noise, static, whole_array

__all__ = ["add_parser"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("calibrate", help="calibrate the array's sensor model from a recording")
    methods = sp.add_subparsers(dest="calibration_command", required=True, metavar="METHOD")
    for module in (fit, geometry, bayes, static, whole_array, noise):
        module.add_parser(methods)
    return sp
