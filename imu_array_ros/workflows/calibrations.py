"""Calibrating an array: every method through one call, one result type and one install path."""

from __future__ import annotations

from imu_array_ros.calibration.methods import METHODS
from imu_array_ros.calibration.methods import calibrate as run_method
from imu_array_ros.calibration.result import Calibration, Installed
from imu_array_ros.discovery.apply import findings_calibration
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.workflows.arrays import as_model

__all__ = ["calibrate", "install", "findings_calibration", "METHODS"]


def calibrate(method: str, samples: ImuSamples, desc: ArrayDescription, /, **options) -> Calibration:
    """Run calibration ``method`` -- "geometry", "static", "all", "fit" or "bayes"
    (:mod:`imu_array_ros.calibration.methods`, where each method's options are) -- on ``samples``,
    starting from every value of ``desc``.  Returns the :class:`~imu_array_ros.calibration.result.Calibration`:
    ``.apply(desc)`` gives the calibrated description, ``.install(desc, path)`` writes it (atomic, the
    previous file kept as ``.bak``, refused when the file on disk fits the calibration's data better),
    ``.record`` is its ``calibration:`` block, ``.details`` the method's own result.
    CalibrationError (one line) when the data cannot determine what the method calibrates."""
    return run_method(method, samples, as_model(desc), **options)


def install(calibration: Calibration, desc: ArrayDescription, out) -> Installed:
    """``calibration.install(desc, out)``: the one install path."""
    return calibration.install(desc, out)
