"""``imu-array calibrate noise``: each IMU's white noise, bias random walk and bias instability per axis from the
Allan deviation of the recording's still intervals (``workflows.calibrate("noise", ...)``; docs/noise.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros import workflows
from imu_array_ros.calibration.result import check_install_target
from imu_array_ros.cli.calibrate.common import about, add_calibration_inputs, add_still_options, check_outputs, \
    install, still_options
from imu_array_ros.cli.options import add_force_quiet, read_array_recording
from imu_array_ros.cli.progress import info
from imu_array_ros.util.extras import require

__all__ = ["add_parser", "run", "print_noise_table"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("noise", help="each IMU's white noise (noise_std), bias random walk and bias "
                                             "instability per axis, from the Allan deviation of the still intervals")
    add_calibration_inputs(sp)
    add_still_options(sp)
    sp.add_argument("--out", required=True, type=Path,
                    help="description YAML to write with each IMU's noise figures (with --force an existing one is "
                         "replaced, kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG",
                    help="also write a plot: the Allan deviation of every IMU with the fitted slopes and floors")
    add_force_quiet(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, and an existing "
                              "--plot PNG")
    sp.set_defaults(handler=run)
    return sp


def print_noise_table(result, quiet: bool) -> None:
    """Per IMU and sensor: noise_std, random walk and bias instability per axis (``-``: not seen)."""
    fmt = lambda v: " ".join("      -  " if v[i] != v[i] else f"{v[i]:9.3g}" for i in range(3))  # noqa: E731
    info(quiet, "  IMU     sensor         noise_std (x y z)              random walk /sqrt(s)           "
                "bias instability")
    for k, name in enumerate(result.names):
        for sensor, per_imu in result.sensors.items():
            s = per_imu[k]
            if s is None:
                info(quiet, f"  {name:7s} {sensor:13s}  no still data")
                continue
            info(quiet, f"  {name:7s} {sensor:13s}  {fmt(s.noise_std)}  {fmt(s.random_walk)}  {fmt(s.instability)}")


def run(recording: Path, *, array: Path, out: Path, calibration: Path | None = None, gravity: float | None = None,
        still_gyro: float | None = None, still_accel: float | None = None, still_min_duration: float | None = None,
        plot: Path | None = None, force: bool = False, quiet: bool = False) -> int:
    """Noise figures of every IMU from the still intervals of ``recording`` (at least one of --still-min-duration,
    default 5 s)."""
    out, plot = check_outputs(out, plot, [recording, array, calibration], force)
    require("allantools", "noise", "imu-array calibrate noise")
    options = still_options(gravity, still_gyro, still_accel, still_min_duration)
    desc, samples = read_array_recording(recording, array, calibration, quiet)
    check_install_target(out, desc.names)  # refused before the work, not after
    with about(recording):
        cal = workflows.calibrate("noise", samples, desc, progress=lambda text: info(quiet, text),
                                  source=str(recording), **options)
    print_noise_table(cal.details, quiet)
    install(cal, desc, out, recording, quiet)
    if plot is not None:
        from imu_array_ros.calibration.noise_plots import plot_noise

        plot_noise(cal.details, plot)
        info(quiet, f"wrote {plot}")
    return 0
