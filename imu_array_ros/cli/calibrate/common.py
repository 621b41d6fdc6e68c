"""What the ``calibrate`` methods share: their inputs, their outputs checked first, the install lines."""

from __future__ import annotations

import argparse
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from imu_array_ros.cli.options import add_recording_inputs, positive_float
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import CalibrationError
from imu_array_ros.io.outputs import check_output
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.util.extras import require
from imu_array_ros.workflows import Calibration, Installed

__all__ = ["add_calibration_inputs", "add_still_options", "still_options", "check_outputs", "about",
           "install"]


def add_calibration_inputs(sp: argparse.ArgumentParser, *, many: bool = False) -> None:
    """The recording (``many``: one or more), --array and --calibration of every ``calibrate`` method."""
    add_recording_inputs(sp, array="array description YAML (initial values)",
                         calibration="calibrated description (same schema) to start from instead of --array's values",
                         many=many)


def add_still_options(sp: argparse.ArgumentParser) -> None:
    """--gravity and the still-interval thresholds of ``calibrate static`` and ``calibrate all``."""
    sp.add_argument("--gravity", type=positive_float, metavar="M/S2",
                    help="local gravity magnitude (default 9.80665)")
    sp.add_argument("--still-gyro", type=positive_float, metavar="RAD/S",
                    help="still-interval threshold on the gyroscopes' moving std (default: from the noise)")
    sp.add_argument("--still-accel", type=positive_float, metavar="M/S2",
                    help="still-interval threshold on the accelerometers' moving std (default: from the noise)")
    sp.add_argument("--still-min-duration", type=positive_float, metavar="SECONDS",
                    help="shortest still interval kept as a pose")


def still_options(gravity: float | None, still_gyro: float | None, still_accel: float | None,
                  still_min_duration: float | None) -> dict:
    """The options of :func:`add_still_options` given, as the calibration's keywords (the method's defaults
    for the rest)."""
    still = {"gyro_threshold": still_gyro, "accel_threshold": still_accel, "min_duration_s": still_min_duration}
    out: dict = {"still_options": {k: v for k, v in still.items() if v is not None}}
    if gravity is not None:
        out["gravity"] = gravity
    return out


def check_outputs(out: Path, plot: Path | None, inputs: list, force: bool) -> tuple[Path, Path | None]:
    """--out (a YAML description) and --plot (a PNG, and matplotlib to draw it), checked before any work."""
    out = check_output(out, inputs, "yaml", force)
    if plot is not None:
        plot = check_output(plot, inputs, "png", force, option="--plot", other_outputs=[("--out", out)])
        require("matplotlib", "plots", f"--plot {plot}")
    return out, plot


@contextmanager
def about(recording: Path) -> Iterator[None]:
    """A CalibrationError inside names the recording it is about."""
    try:
        yield
    except CalibrationError as err:
        raise CalibrationError(f"{recording}: {err}") from None


def install(cal: Calibration, desc: ArrayDescription, out: Path, recording: Path, quiet: bool, *,
            summary: bool = True) -> Installed:
    """``cal.install(desc, out)`` (a refusal names the recording), then the calibration's summary line
    (``summary``), where the previous file was kept and what was written."""
    with about(recording):
        installed = cal.install(desc, out)
    if summary:
        info(quiet, cal.summary())
    if installed.backup is not None:
        info(quiet, f"previous {out} kept as {installed.backup}")
    info(quiet, f"wrote {out}")
    return installed
