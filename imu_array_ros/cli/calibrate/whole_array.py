"""``imu-array calibrate all``: the whole array from one recording, or from several of the same array.

Still poses -> accelerometer intrinsics and gyroscope biases; the moving phase ->
positions, gyroscope gain, misalignment and non-orthogonality; then, with ``--timing``, the timing stage (sample
clocks, time offsets) (``workflows.calibrate("all", ...)``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros.cli.calibrate.common import add_calibration_inputs, add_still_options, still_options
from imu_array_ros.cli.calibrate.static import calibrate_stages
from imu_array_ros.cli.options import add_force_quiet, parse_list
from imu_array_ros.errors import CalibrationError, ConfigError
from imu_array_ros.fitting import check_terms

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("all", help="the whole array from one or more recordings: still poses -> "
                                           "accelerometer intrinsics and gyroscope biases; moving phase -> positions, "
                                           "gyroscope gain, misalignment and non-orthogonality; several recordings: "
                                           "device constants combined, biases with their turn-on repeatability")
    add_calibration_inputs(sp, many=True)
    sp.add_argument("--reference", help="IMU that defines the array frame and holds the gauge (default: the first)")
    sp.add_argument("--static-method", choices=("ml", "pca"), default="ml", help="static stage method (default ml)")
    sp.add_argument("--moving-terms",
                    help="comma-separated terms of the moving stage (default position,gyroscope_gain,"
                         "gyroscope_misalignment,gyroscope_nonorthogonality; empty: no moving stage)")
    add_still_options(sp)
    sp.add_argument("--timing", action="store_true",
                    help="add the timing stage (sample clocks searched, then the time offsets fitted with the moving "
                         "stage's positions and gyroscope terms held); experimental, off by default (docs/timing.md)")
    sp.add_argument("--clock-period", type=float, default=1e-3, metavar="S",
                    help="internal sample period (s) of the chips' free-running clocks to search for when the "
                         "description has none (default 0.001, ~1 kHz; 0: no search)")
    sp.add_argument("--out", required=True, type=Path, help="calibrated description YAML to write (old kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG", help="also write the static stage's plot")
    sp.add_argument("--report", type=Path, metavar="DIR",
                    help="also write a calibration report into DIR (index.md, calibration.json, PNG plots): values "
                         "± std, the stages, residuals before/after per IMU and axis; DIR must be new or empty "
                         "(--force: or hold a previous report of ours, which is replaced)")
    add_force_quiet(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, unless it fits the "
                              "poses and the moving samples better than the new calibration; an existing --plot; and a "
                              "previous report of ours in --report")
    sp.set_defaults(handler=run)
    return sp


def run(recording: list[Path], *, array: Path, out: Path, calibration: Path | None = None, reference: str | None = None,
        static_method: str = "ml", moving_terms: str | None = None, gravity: float | None = None,
        still_gyro: float | None = None, still_accel: float | None = None, still_min_duration: float | None = None,
        plot: Path | None = None, force: bool = False, quiet: bool = False, timing: bool = False,
        clock_period: float = 1e-3, report: Path | None = None) -> int:
    """Whole-array calibration: still poses -> static stage -> moving stage -> timing stage, one description;
    several recordings: each calibrated, device constants combined, biases with their turn-on repeatability."""
    recording = list(recording) if isinstance(recording, (list, tuple)) else [recording]
    if len(set(map(str, recording))) != len(recording):
        raise ConfigError("the same recording is given twice")
    if timing and len(recording) > 1:
        raise ConfigError("--timing runs on one recording at a time (each power-up has its own clock phases)")
    if not (clock_period >= 0 and clock_period < 1.0):
        raise ConfigError(f"--clock-period must be in [0, 1) s, got {clock_period:g}")
    options = still_options(gravity, still_gyro, still_accel, still_min_duration)
    options["timing"] = timing
    options["clock_period"] = clock_period or None
    if moving_terms is not None:  # "" : no moving stage
        options["moving_terms"] = tuple(parse_list(moving_terms) or ())
        if options["moving_terms"]:
            try:
                check_terms(options["moving_terms"])  # before reading anything
            except CalibrationError as err:
                raise CalibrationError(f"--moving-terms: {err}") from None
    return calibrate_stages("all", recording, array=array, out=out, calibration=calibration, plot=plot,
                            force=force, quiet=quiet, reference=reference, static_method=static_method,
                            report=report, **options)
