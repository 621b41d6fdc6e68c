"""What the command line, the ROS nodes, the Python API and the benchmarks all call.

One function per job, so that offline and live results are the same numbers:

* arrays: :func:`load_array` (a description, optionally its calibrated values), :func:`check_fusable`;
* recordings: :func:`read_imu_recording`, :func:`import_openshoe`, :func:`simulate`;
* fusion: :func:`build_fusion`, :func:`fuse` (samples), :func:`fuse_recording` (a file);
* calibration: :func:`calibrate` (every method, one :class:`~imu_array_ros.calibration.result.Calibration`
  result, one install path), :func:`findings_calibration` (``discover --apply``);
* analysis: :func:`residuals`, :func:`discover`.

The names are imported when first used (:pep:`562`): a node that needs :func:`load_array` does not
pay for importing the calibrations and discovery (and scipy.stats) at start.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what a type checker (and test_architecture's layer check) sees
    from imu_array_ros.calibration.result import Calibration, Installed
    from imu_array_ros.workflows.analysis import DiscoveryOptions, discover, residuals
    from imu_array_ros.workflows.arrays import as_model, check_fusable, load_array
    from imu_array_ros.workflows.calibrations import METHODS, calibrate, findings_calibration, install
    from imu_array_ros.workflows.fusion import FusedRecording, build_fusion, fuse, fuse_recording
    from imu_array_ros.workflows.recordings import (MOTIONS, Simulated, icosahedron_seconds, import_openshoe,
                                                    read_imu_recording, simulate)

#: public name -> the module that defines it
EXPORTS = {
    **dict.fromkeys(("load_array", "check_fusable", "as_model"), "imu_array_ros.workflows.arrays"),
    **dict.fromkeys(("read_imu_recording", "import_openshoe", "simulate", "Simulated", "MOTIONS", "icosahedron_seconds"),
                    "imu_array_ros.workflows.recordings"),
    **dict.fromkeys(("build_fusion", "fuse", "fuse_recording", "FusedRecording"), "imu_array_ros.workflows.fusion"),
    **dict.fromkeys(("calibrate", "install", "findings_calibration", "METHODS"),
                    "imu_array_ros.workflows.calibrations"),
    **dict.fromkeys(("Calibration", "Installed"), "imu_array_ros.calibration.result"),
    **dict.fromkeys(("residuals", "discover", "DiscoveryOptions"), "imu_array_ros.workflows.analysis"),
}
__all__ = list(EXPORTS)


def __getattr__(name: str):
    try:
        module = EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(EXPORTS))
