"""``imu-array calibrate geometry``: the accelerometer positions from hand twisting (carlsson2017).

The on-the-fly calibration of the positions (:mod:`imu_array_ros.calibration.geometry`, through
``workflows.calibrate("geometry", ...)``), the same one the calibration node's ``/calibrate_geometry``
service runs, on the whole recording or a window of it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from imu_array_ros import workflows
from imu_array_ros.calibration.result import check_install_target
from imu_array_ros.calibration.plots import plot_geometry
from imu_array_ros.cli.calibrate.common import about, add_calibration_inputs, check_outputs, install
from imu_array_ros.cli.options import add_force_quiet, non_negative_float, positive_int, read_array_recording
from imu_array_ros.cli.window import add_window_options, time_window
from imu_array_ros.cli.progress import info

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("geometry", help="accelerometer positions from hand-twisting (carlsson2017), with "
                                                "their Cramer-Rao std; what the /calibrate_geometry service runs")
    add_calibration_inputs(sp)
    sp.add_argument("--reference", help="IMU whose position is held (default: the first)")
    sp.add_argument("--method", choices=("joint", "bcd"),
                    help="'joint': Schur-complement Gauss-Newton (default); 'bcd': block coordinate descent "
                         "(carlsson2017 Alg. 1)")
    sp.add_argument("--max-iterations", type=positive_int,
                    help="iteration cap, >= 1 (default 50 joint, 500 bcd)")
    sp.add_argument("--min-excitation", type=non_negative_float,
                    help="samples with ||[w]x^2 + [w_dot]x|| below this (rad/s^2, >= 0) carry too little rotation "
                         "and are dropped (default 1)")
    add_window_options(sp)
    sp.add_argument("--out", required=True, type=Path,
                    help="calibrated description YAML to write (with --force an existing one is replaced only if "
                         "the new calibration fits the window better; the old one is kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG",
                    help="also write a plot: position change per IMU with 3-sigma bars, residual RMS before/after")
    add_force_quiet(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, unless it fits the "
                              "window better than the new calibration; and an existing --plot PNG")
    sp.set_defaults(handler=run)
    return sp


def run(recording: Path, *, array: Path, out: Path, calibration: Path | None = None, reference: str | None = None,
        method: str | None = None, max_iterations: int | None = None, min_excitation: float | None = None,
        start: float | None = None, duration: float | None = None, plot: Path | None = None, force: bool = False,
        quiet: bool = False) -> int:
    """Calibrate the accelerometer positions on (a window of) ``recording``; install at ``out``."""
    out, plot = check_outputs(out, plot, [recording, array, calibration], force)
    desc, samples = read_array_recording(recording, array, calibration, quiet, imus=[reference])
    check_install_target(out, desc.names)  # refused before the work, not after
    samples = time_window(samples, recording, start, duration, quiet)

    def progress(iteration: int, loglik: float) -> None:
        info(quiet, f"calibrating: iteration {iteration}, log-likelihood {loglik:.10g}")

    given = {k: v for k, v in (("method", method), ("min_excitation", min_excitation)) if v is not None}
    with about(recording):
        cal = workflows.calibrate("geometry", samples, desc, reference=reference, max_iterations=max_iterations,
                                  progress=progress, source=str(recording), **given)
    result = cal.details
    dropped = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in result.dropped.items() if v) or "none"
    info(quiet, f"samples: {result.samples_used} of {result.samples_total} used (dropped: {dropped})")
    info(quiet, f"log-likelihood {result.loglik_before:.10g} -> {result.loglik_after:.10g}; "
                f"NIS per degree of freedom {result.nis_before:.4g} -> {result.nis_after:.4g}")
    change, std = result.position_change(), np.linalg.norm(result.position_std, axis=1)
    for k, name in enumerate(result.names):
        info(quiet, f"  {name}: moved {change[k] * 1e3:8.4f} mm, std {std[k] * 1e6:8.2f} um, "
                    f"residual RMS {result.rms_before[k]:.4g} -> {result.rms_after[k]:.4g} m/s^2"
                    f"{'  (reference)' if name == result.reference else ''}")
    install(cal, desc, out, recording, quiet)
    if plot is not None:
        plot_geometry(result, plot)
        info(quiet, f"wrote {plot}")
    return 0
