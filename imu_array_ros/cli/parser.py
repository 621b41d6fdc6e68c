"""``imu-array`` argument parsing: argparse with validating types, dispatch to :mod:`.commands`.

Every option is checked here (positive, finite, non-negative, a time) so a
command function only ever sees sensible values; a bad one gives one line
``imu-array: error: argument --duration: ...`` and exit status 2.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from datetime import datetime, timedelta, timezone
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path
from typing import Callable

from imu_array_ros.version import __version__
from imu_array_ros.cli import calibrate, commands, discover, fake_device
from imu_array_ros.errors import ImuArrayError

__all__ = [
    "main",
    "build_parser",
    "EXIT_USER_ERROR",
    "positive_float",
    "non_negative_float",
    "non_negative_int",
    "positive_int",
    "sample_rate",
    "start_time",
]

EXIT_USER_ERROR = 2

#: Highest sample rate accepted: stamps are integer nanoseconds and must stay distinct.
MAX_RATE_HZ = 1e6


# --------------------------------------------------------------------------- argument types


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An integer >= 0 (seeds)."""
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (counts)."""
    value = non_negative_int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


def sample_rate(text: str) -> float:
    """A sample rate in Hz: > 0 and at most :data:`MAX_RATE_HZ`."""
    value = positive_float(text)
    if value > MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_RATE_HZ:g} Hz (stamps are whole nanoseconds), got {text!r}")
    return value


_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


def start_time(text: str) -> int:
    """A start time -> int ns since the epoch (UTC).

    Accepts seconds since the epoch (``1795255200``, ``1795255200.25``) or an
    ISO 8601 time (``2026-11-21T10:00:00Z``, ``2026-11-21T11:00:00+01:00``; a
    time without offset is UTC).  Must lie within what a ROS
    ``builtin_interfaces/Time`` (int32 seconds) can hold.
    """
    s = text.strip()
    try:
        seconds = Decimal(s)
    except InvalidOperation:
        seconds = None
    if seconds is not None:
        if not seconds.is_finite():
            raise argparse.ArgumentTypeError(f"must be a finite time, got {text!r}")
        ns = int((seconds * 10**9).to_integral_value(rounding=ROUND_HALF_EVEN))
    else:
        iso = s[:-1] + "+00:00" if s.endswith(("Z", "z")) else s
        try:
            when = datetime.fromisoformat(iso)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected an ISO 8601 time (e.g. 2026-11-21T10:00:00Z) or seconds since the epoch, got {text!r}"
            ) from None
        if when.tzinfo is None:
            when = when.replace(tzinfo=timezone.utc)
        delta: timedelta = when - _EPOCH
        ns = (delta.days * 86400 + delta.seconds) * 10**9 + delta.microseconds * 1000
    if not 0 <= ns <= commands.MAX_STAMP_NS:
        raise argparse.ArgumentTypeError(
            f"must lie between 1970-01-01T00:00:00Z and 2038-01-19T03:14:07Z "
            f"(int32 seconds of a ROS time stamp), got {text!r}"
        )
    return ns


# --------------------------------------------------------------------------- parser


class _UsageError(Exception):
    """A command line argparse rejects; printed as one line by :func:`main`."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage mistake as one line instead of usage + exit."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise _UsageError(f"{message} (see '{self.prog} --help')")


QUIET_HELP = "no progress or summary lines on stderr (errors still appear)"


def _common(sp: argparse.ArgumentParser, *, force: str, quiet: str = QUIET_HELP) -> None:
    sp.add_argument("--force", action="store_true", help=force)
    sp.add_argument("-q", "--quiet", action="store_true", help=quiet)


_FORCE_RECORDING = ("replace an existing output, only if it is itself a recording (an MCAP file, or a rosbag2 "
                    "directory holding only its own files); an input, a directory holding other files, or any "
                    "other file is never replaced")


def _calibration_inputs(sp: argparse.ArgumentParser) -> None:
    """The recording, --array and --calibration of every ``calibrate`` method."""
    sp.add_argument("recording", type=Path, help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, type=Path, help="array description YAML (initial values)")
    sp.add_argument("--calibration", type=Path,
                    help="calibrated description (same schema) to start from instead of --array's values")


def build_parser() -> argparse.ArgumentParser:
    """The ``imu-array`` parser; each subcommand's ``func`` is the typed command to call."""
    p = _Parser(prog="imu-array", description="Inertial sensor array tools (imu_array_ros).")
    p.add_argument("--version", action="version", version=f"imu-array {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sp = sub.add_parser("simulate", help="simulate a recording of an array (rosbag2 MCAP)")
    sp.add_argument("--array", required=True, type=Path,
                    help="array description YAML (nominal; written into the recording); must be identifiable")
    sp.add_argument("--out", required=True, type=Path, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--motion", choices=["twist", "random", "icosahedron"], default="twist",
                    help="twist: smooth hand twisting; random: independent samples (carlsson2017 Monte Carlo); "
                         "icosahedron: static calibration session, the array set down on the 20 faces of an "
                         "icosahedron in turn (nilsson2014), optionally followed by hand twisting")
    sp.add_argument("--duration", type=positive_float,
                    help="seconds, > 0 (default 5); not with --motion icosahedron, whose length is "
                         "20 x --still-seconds + 19 x --transition-seconds + --twist-seconds")
    sp.add_argument("--rate", type=sample_rate,
                    help=f"sample rate in Hz, 0 < HZ <= {MAX_RATE_HZ:g} (default 1000; 100 for icosahedron)")
    sp.add_argument("--rms-rate", type=positive_float, default=600.0,
                    help="twist (also icosahedron's twisting): RMS angular speed; random: |omega|; deg/s, > 0 "
                         "(default 600)")
    sp.add_argument("--still-seconds", type=positive_float,
                    help="icosahedron: seconds at rest on each face, > 0 (default 3)")
    sp.add_argument("--transition-seconds", type=positive_float,
                    help="icosahedron: seconds of handling between faces, > 0 (default 2)")
    sp.add_argument("--tilt-std-deg", type=non_negative_float,
                    help="icosahedron: std of the unknown tilt of each rest per horizontal axis, degrees, >= 0 "
                         "(default 1)")
    sp.add_argument("--twist-seconds", type=non_negative_float,
                    help="icosahedron: seconds of hand twisting after the last face, >= 0 (default 0)")
    sp.add_argument("--angular-accel", type=non_negative_float, default=2000.0,
                    help="random: |omega_dot| in deg/s^2, >= 0 (default 2000)")
    sp.add_argument("--seed", type=non_negative_int, default=0, help="seed of motion and noise, >= 0 (default 0)")
    sp.add_argument("--start-time", dest="start_ns", type=start_time, metavar="TIME",
                    help="stamp of the first sample: ISO 8601 (2026-11-21T10:00:00Z; UTC without an offset) "
                         "or seconds since the epoch (default: now; give a fixed time for a reproducible recording)")
    sp.add_argument("--true-array", type=Path, help="description holding the true sensor parameters (default: --array)")
    sp.add_argument("--error-seed", type=non_negative_int,
                    help="add seeded sensor errors (positions, gains, biases, angles), >= 0")
    sp.add_argument("--position-error-std", type=non_negative_float,
                    help="with --error-seed: position error sigma in m, >= 0 (default 1e-4)")
    sp.add_argument("--truth-array-out", type=Path,
                    help="write the true sensor parameters as a description YAML (with --force, replaces only "
                         "a YAML file)")
    _common(sp, force=_FORCE_RECORDING)
    sp.set_defaults(func=commands.simulate)

    sp = sub.add_parser("fuse", help="ML fusion of a recording (skog2016) with Cramér-Rao covariances")
    sp.add_argument("recording", type=Path, help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, type=Path, help="array description YAML")
    sp.add_argument("--calibration", type=Path,
                    help="calibrated description (same schema) to use instead of --array's values")
    sp.add_argument("--out", required=True, type=Path, help="output: directory (rosbag2) or file ending in .mcap")
    _common(sp, force=_FORCE_RECORDING)
    sp.set_defaults(func=commands.fuse)

    sp = sub.add_parser("import-openshoe", help="convert an OpenShoe raw serial capture to a recording")
    sp.add_argument("capture", type=Path, help="raw capture file (e.g. exp_1.bin)")
    sp.add_argument("--array", required=True, type=Path, help="array description YAML (IMU order = capture order)")
    sp.add_argument("--out", required=True, type=Path, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--start-time", dest="start_ns", type=start_time, metavar="TIME",
                    help="stamp of the first packet: ISO 8601 (2026-11-21T10:00:00Z; UTC without an offset) or "
                         "seconds since the epoch (default: the capture ends at the file's modification time)")
    _common(sp, force=_FORCE_RECORDING)
    sp.set_defaults(func=commands.import_openshoe)

    sp = sub.add_parser("fake-device", help="simulated OpenShoe array on a pseudo-terminal (no hardware needed)")
    sp.add_argument("--array", required=True, type=Path,
                    help="array description YAML: the number of IMUs per packet (and the sensor model when simulating)")
    sp.add_argument("--capture", type=Path,
                    help="raw capture to replay byte for byte (e.g. exp_1.bin; IMU order = capture order); "
                         "default: simulated hand twisting")
    sp.add_argument("--duration", type=positive_float, help="simulated seconds, > 0 (default 60)")
    sp.add_argument("--rate", type=fake_device.openshoe_rate, metavar="HZ",
                    help="simulated sample rate: 1000, 500, 250, 125, 62.5, 31.25 or 15.625 Hz (default 1000; "
                         "the host's rate divider decimates it)")
    sp.add_argument("--seed", type=non_negative_int, help="seed of the simulated motion and noise and of the "
                                                          "faults, >= 0 (default 0)")
    sp.add_argument("--link", type=Path, metavar="PATH",
                    help="symlink to create for the port (default: in a new temporary directory); an existing PATH "
                         "is replaced only if it is a symlink to a pseudo-terminal")
    sp.add_argument("--speed", type=non_negative_float, default=1.0,
                    help="playback speed, x real time, >= 0; 0 = as fast as the port is read (default 1)")
    sp.add_argument("--loop", action="store_true", help="replay the data forever (default: stop at its end)")
    sp.add_argument("--garbage-every", type=non_negative_int, default=0, metavar="N",
                    help="insert random bytes after every N-th packet (default 0: never)")
    sp.add_argument("--bit-error-rate", type=fake_device.probability, default=0.0, metavar="P",
                    help="probability of flipping each bit, 0 <= P < 1 (default 0)")
    sp.add_argument("--drop-byte-rate", type=fake_device.probability, default=0.0, metavar="P",
                    help="probability of losing each byte, 0 <= P < 1 (default 0)")
    sp.add_argument("--unplug-at", type=positive_float, metavar="SECONDS",
                    help="simulate unplugging this many seconds after the port appears (the host must reconnect "
                         "and send the start command again)")
    sp.add_argument("--unplug-duration", type=non_negative_float, default=1.0, metavar="SECONDS",
                    help="seconds the device stays unplugged, >= 0 (default 1)")
    sp.add_argument("-q", "--quiet", action="store_true", help="only the port path on stdout (errors still appear)")
    sp.set_defaults(func=fake_device.fake_device)

    sp = sub.add_parser("residuals", help="how well the model explains a recording (normalised residuals)")
    sp.add_argument("recording", type=Path, help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, type=Path, help="array description YAML")
    sp.add_argument("--calibration", type=Path, help="calibrated description (same schema)")
    sp.add_argument("--compare-simulated", action="store_true",
                    help="also analyse a simulated recording of the same (fused) motion")
    sp.add_argument("--still-threshold", type=non_negative_float, default=0.2,
                    help="|omega| below this (rad/s, >= 0) is 'still' (default 0.2)")
    sp.add_argument("--seed", type=non_negative_int, default=0, help="seed of the simulated comparison, >= 0")
    sp.add_argument("--json", dest="json_out", metavar="FILE",
                    help="write the summary as JSON to FILE ('-' for stdout); a ratio without samples is null")
    sp.add_argument("--tables", action="store_true", help="print the ratio table by IMU and axis on stdout")
    _common(sp, force="replace an existing --json FILE, only if it is itself a JSON file",
            quiet="no progress or summary lines on stderr (errors still appear); the result asked for on "
                  "stdout (--tables, --json -) is still printed")
    sp.set_defaults(func=commands.residuals)

    sp = sub.add_parser("calibrate", help="calibrate the array's sensor model from a recording")
    cal = sp.add_subparsers(dest="calibration_command", required=True, metavar="METHOD")
    sp = cal.add_parser("fit", help="maximum likelihood of any sensor-model terms jointly with the motion")
    _calibration_inputs(sp)
    sp.add_argument("--terms", required=True,
                    help="comma-separated registry names of the terms to fit, e.g. position,gyroscope_gain,time_offset")
    sp.add_argument("--imus", help="comma-separated IMU names whose parameters are fitted (default: all)")
    sp.add_argument("--reference",
                    help="IMU whose parameters fix the gauge freedoms (default: the first fitted IMU)")
    sp.add_argument("--max-iterations", type=positive_int, default=50, help="iteration cap, >= 1 (default 50)")
    sp.add_argument("--out", required=True, type=Path, help="calibrated description YAML to write")
    _common(sp, force="replace an existing --out, only if it is itself a YAML mapping")
    sp.set_defaults(func=calibrate.calibrate_fit)

    sp = cal.add_parser("geometry", help="accelerometer positions from hand-twisting (carlsson2017), with their "
                                         "Cramer-Rao std; what the /calibrate_geometry service runs")
    _calibration_inputs(sp)
    sp.add_argument("--reference", help="IMU whose position is held (default: the first)")
    sp.add_argument("--method", choices=("joint", "bcd"),
                    help="'joint': Schur-complement Gauss-Newton (default); 'bcd': block coordinate descent "
                         "(carlsson2017 Alg. 1)")
    sp.add_argument("--max-iterations", type=positive_int,
                    help="iteration cap, >= 1 (default 50 joint, 500 bcd)")
    sp.add_argument("--min-excitation", type=non_negative_float,
                    help="samples with ||[w]x^2 + [w_dot]x|| below this (rad/s^2, >= 0) carry too little rotation "
                         "and are dropped (default 1)")
    sp.add_argument("--start", type=non_negative_float, metavar="SECONDS",
                    help="window start, seconds after the first sample (default 0)")
    sp.add_argument("--duration", type=positive_float, metavar="SECONDS", help="window length (default: to the end)")
    sp.add_argument("--out", required=True, type=Path,
                    help="calibrated description YAML to write (with --force an existing one is replaced only if "
                         "the new calibration fits the window better; the old one is kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG",
                    help="also write a plot: position change per IMU with 3-sigma bars, residual RMS before/after")
    _common(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, unless it fits the "
                      "window better than the new calibration; and an existing --plot PNG")
    sp.set_defaults(func=calibrate.calibrate_geometry)

    sp = cal.add_parser("bayes", help="posterior of the accelerometer positions (carlsson2021 pseudo-marginal MCMC): "
                                      "mean, std and covariance per IMU, with convergence diagnostics")
    _calibration_inputs(sp)
    sp.add_argument("--out", required=True, type=Path,
                    help="calibrated description YAML to write: position = posterior mean, position_std, and the "
                         "covariance per IMU in the calibration: block (with --force an existing one is replaced, "
                         "kept as OUT.bak, unless it fits the samples better than the posterior allows)")
    sp.add_argument("--samples", type=positive_int, default=50, metavar="T",
                    help="time samples used, spread evenly over the samples with rotation (default 50; the paper "
                         "uses 5, 50 and 500)")
    sp.add_argument("--chains", type=positive_int, default=4, help="Markov chains, >= 2 (default 4)")
    sp.add_argument("--scheduler", metavar="ADDR",
                    help="run the chains on Dask: 'local' for a new LocalCluster, or a scheduler address "
                         "(tcp://host:8786); default: worker processes on this machine ('serial': this process)")
    sp.add_argument("--workers", type=positive_int, help="worker processes (default: one per core, at most --chains)")
    sp.add_argument("--report", type=Path, metavar="DIR",
                    help="write credible-ellipse, trace and autocorrelation plots, the diagnostics table "
                         "(diagnostics.md/.json) and the draws (posterior.nc) into DIR")
    sp.add_argument("--reference", help="IMU whose position is held (default: the first)")
    sp.add_argument("--prior", choices=("gaussian", "uniform"), default="gaussian",
                    help="prior on each position around --array's: gaussian with --prior-std (default) or "
                         "uniform over the 4 x 4 x 1 mm package")
    sp.add_argument("--prior-std", type=positive_float, metavar="M", help="gaussian prior std, m (default 0.003)")
    sp.add_argument("--accel-std", type=positive_float, metavar="M/S2",
                    help="accelerometer noise std to assume instead of the description's (carlsson2021 uses "
                         "0.79 m/s^2 on real data to cover non-linearity)")
    sp.add_argument("--omega-covariance", choices=("model", "sample"), default="model",
                    help="p(omega | gyroscopes): 'model' noise (eq. 26b, default) or the gyroscopes' sample "
                         "covariance at each sample (eq. 30)")
    sp.add_argument("--draws", type=positive_int, metavar="N",
                    help="omega draws per time sample (default: tuned so Var[log-likelihood estimate] <= 0.1; an error "
                         "when 1024 cannot bring it below 1, which means the readings disagree with the noise "
                         "model; give N to sample anyway)")
    sp.add_argument("--rho", type=non_negative_float, default=0.9,
                    help="correlation of the random numbers between iterations, in [0, 1) (0: plain PmMH; "
                         "default 0.9)")
    sp.add_argument("--proposal", choices=("laplace", "isotropic"), default="laplace",
                    help="'laplace': random walk shaped by the Laplace covariance mixed with independence "
                         "proposals (default); 'isotropic': the paper's sigma_q I random walk (eq. 27)")
    sp.add_argument("--ess", type=positive_float, default=400.0,
                    help="sample until the smallest bulk effective sample size reaches this (default 400)")
    sp.add_argument("--max-iterations", type=positive_int, default=400000,
                    help="cap on the sampling iterations per chain (default 400000)")
    sp.add_argument("--min-excitation", type=non_negative_float,
                    help="samples with ||[w]x^2 + [w_dot]x|| below this (rad/s^2) are not used (default 1)")
    sp.add_argument("--seed", type=non_negative_int, default=0, help="seed of the chains (default 0)")
    _common(sp, force="replace an existing --out (a YAML mapping; kept as OUT.bak) and an existing report")
    sp.set_defaults(func=calibrate.calibrate_bayes)

    def still_options(sp) -> None:
        sp.add_argument("--gravity", type=positive_float, metavar="M/S2",
                        help="local gravity magnitude (default 9.80665)")
        sp.add_argument("--still-gyro", type=positive_float, metavar="RAD/S",
                        help="still-interval threshold on the gyroscopes' moving std (default: from the noise)")
        sp.add_argument("--still-accel", type=positive_float, metavar="M/S2",
                        help="still-interval threshold on the accelerometers' moving std (default: from the noise)")
        sp.add_argument("--still-min-duration", type=positive_float, metavar="SECONDS",
                        help="shortest still interval kept as a pose")

    sp = cal.add_parser("static", help="accelerometer gain, bias, non-orthogonality and misalignment, and gyroscope "
                                       "biases, from the still poses of a recording (nilsson2014 ML / rupniewski PCA)")
    _calibration_inputs(sp)
    sp.add_argument("--method", choices=("ml", "pca"), default="ml",
                    help="'ml': maximum likelihood, robust (default); 'pca': closed form (rupniewski)")
    sp.add_argument("--reference", help="IMU whose accelerometer axes define the array frame (default: the first)")
    sp.add_argument("--terms", help="comma-separated subset of accelerometer_gain, accelerometer_nonorthogonality, "
                                    "accelerometer_misalignment, accelerometer_bias, gyroscope_bias (default: all)")
    still_options(sp)
    sp.add_argument("--out", required=True, type=Path,
                    help="calibrated description YAML to write (with --force an existing one is replaced only if "
                         "the new calibration fits the poses better; the old one is kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG",
                    help="also write a plot: poses on the sphere, parameters with 3-sigma bars, residuals")
    _common(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, unless it fits the "
                      "poses better than the new calibration; and an existing --plot PNG")
    sp.set_defaults(func=calibrate.calibrate_static)

    sp = cal.add_parser("all", help="the whole array from one recording: still poses -> accelerometer intrinsics "
                                    "and gyroscope biases; moving phase -> positions, gyroscope gain and misalignment")
    _calibration_inputs(sp)
    sp.add_argument("--reference", help="IMU that defines the array frame and holds the gauge (default: the first)")
    sp.add_argument("--static-method", choices=("ml", "pca"), default="ml", help="static stage method (default ml)")
    sp.add_argument("--moving-terms",
                    help="comma-separated terms of the moving stage (default position,gyroscope_gain,"
                         "gyroscope_misalignment; empty: no moving stage)")
    still_options(sp)
    sp.add_argument("--out", required=True, type=Path, help="calibrated description YAML to write (old kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG", help="also write the static stage's plot")
    _common(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak; and an existing --plot")
    sp.set_defaults(func=calibrate.calibrate_all)

    sp = sub.add_parser("discover", help="where a recording differs from the model, which physics the model "
                                         "left out (terms found, confirmed on held-out blocks), and the fit after")
    sp.add_argument("recording", type=Path, help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, type=Path, help="array description YAML")
    sp.add_argument("--calibration", type=Path, help="calibrated description (same schema) to start from")
    sp.add_argument("--report", required=True, type=Path,
                    help="directory for report.md, report.json and the plots (created if missing)")
    sp.add_argument("--sim", type=Path,
                    help="your own simulated recording of the same run (same stamps and IMUs): localise "
                         "recording - simulation instead of recording - model prediction")
    sp.add_argument("--apply", type=Path, metavar="OUT.yaml",
                    help="write the description extended with the found terms (not written when nothing is found)")
    sp.add_argument("--validate", type=Path, nargs="+", metavar="REC",
                    help="other recordings of the same array: log-likelihood and NIS with and without the findings")
    sp.add_argument("--terms", help="comma-separated candidate terms (default: every registered term)")
    sp.add_argument("--alpha", type=positive_float, default=0.01,
                    help="family-wise false-finding rate per recording, in (0, 1) (default 0.01)")
    sp.add_argument("--block", type=positive_float, default=0.5, metavar="SECONDS",
                    help="time block of the robust test and the held-out folds, s (default 0.5)")
    sp.add_argument("--max-findings", type=positive_int, default=8, help="cap on the findings (default 8)")
    sp.add_argument("--no-plots", action="store_true", help="no PNG plots (report.md and report.json only)")
    sp.add_argument("--no-empirical", action="store_true", help="do not model the unexplained residual")
    _common(sp, force="replace an existing report in --report and an existing --apply YAML (only files of "
                      "those kinds)")
    sp.set_defaults(func=discover.discover_command)

    sp = sub.add_parser("recover", help="salvage a truncated or damaged recording (e.g. a recorder killed mid-write)")
    sp.add_argument("recording", type=Path, help="the damaged recording: .mcap file or rosbag2 directory (only read)")
    sp.add_argument("--out", required=True, type=Path,
                    help="the salvaged recording: directory (rosbag2) or file ending in .mcap")
    _common(sp, force=_FORCE_RECORDING)
    sp.set_defaults(func=commands.recover)
    return p


def _call(func: Callable[..., int], args: argparse.Namespace) -> int:
    kwargs = {k: v for k, v in vars(args).items() if k not in ("func", "command", "calibration_command")}
    return int(func(**kwargs) or 0)


def main(argv: list[str] | None = None) -> int:
    """Run ``imu-array`` with ``argv`` (default ``sys.argv[1:]``); return the exit status.

    0 on success; 2 with one line ``imu-array: error: ...`` on stderr for a user
    mistake (bad option, bad file, unsafe output); 130 on Ctrl-C.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as err:
        print(f"imu-array: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else 0
    try:
        return _call(args.func, args)
    except ImuArrayError as err:
        print(f"imu-array: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("imu-array: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
