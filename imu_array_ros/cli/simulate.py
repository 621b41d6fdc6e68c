"""``imu-array simulate``: a simulated recording of an array (:func:`imu_array_ros.workflows.simulate`)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from imu_array_ros import workflows
from imu_array_ros.cli.options import (FORCE_RECORDING_HELP, MAX_RATE_HZ, MAX_SIMULATED_SAMPLES, MAX_STAMP_NS,
                                       add_force_quiet, non_negative_float, non_negative_int, positive_float,
                                       sample_rate, start_time)
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import ImuArrayError, OutputError
from imu_array_ros.io.outputs import check_output
from imu_array_ros.io.rosbag.recording import write_imu_recording
from imu_array_ros.model.description import load_description, save_description
from imu_array_ros.workflows import icosahedron_seconds

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("simulate", help="simulate a recording of an array (rosbag2 MCAP)")
    sp.add_argument("--array", required=True, type=Path,
                    help="array description YAML (nominal; written into the recording); must be identifiable")
    sp.add_argument("--out", required=True, type=Path, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--motion", choices=list(workflows.MOTIONS), default="twist",
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
    add_force_quiet(sp, force=FORCE_RECORDING_HELP)
    sp.set_defaults(handler=run)
    return sp


def _session(motion: str, duration: float | None, rate: float | None, still_seconds: float | None,
             transition_seconds: float | None, tilt_std_deg: float | None,
             twist_seconds: float | None) -> tuple[float, float, dict]:
    """(duration, rate, icosahedron options) with the defaults filled in; the one-line errors of options
    that do not go together."""
    session = {"--still-seconds": still_seconds, "--transition-seconds": transition_seconds,
               "--tilt-std-deg": tilt_std_deg, "--twist-seconds": twist_seconds}
    if motion != "icosahedron":
        given = [k for k, v in session.items() if v is not None]
        if given:
            raise ImuArrayError(f"{given[0]} needs --motion icosahedron")
        return 5.0 if duration is None else duration, 1000.0 if rate is None else rate, {}
    if duration is not None:
        raise ImuArrayError("--duration does not apply to --motion icosahedron (its length is 20 x "
                            "--still-seconds + 19 x --transition-seconds + --twist-seconds)")
    ico = dict(still_seconds=3.0 if still_seconds is None else still_seconds,
               transition_seconds=2.0 if transition_seconds is None else transition_seconds,
               tilt_std_deg=1.0 if tilt_std_deg is None else tilt_std_deg,
               twist_seconds=0.0 if twist_seconds is None else twist_seconds)
    rate = 100.0 if rate is None else rate
    if ico["still_seconds"] * rate < 1:
        raise ImuArrayError(f"--still-seconds {ico['still_seconds']:g} at --rate {rate:g} Hz leaves a face "
                            f"without a sample at rest")
    seconds = icosahedron_seconds(ico["still_seconds"], ico["transition_seconds"], ico["twist_seconds"])
    return seconds, rate, ico


def run(*, array: Path, out: Path, motion: str = "twist", duration: float | None = None, rate: float | None = None,
        rms_rate: float = 600.0, angular_accel: float = 2000.0, still_seconds: float | None = None,
        transition_seconds: float | None = None, tilt_std_deg: float | None = None,
        twist_seconds: float | None = None, seed: int = 0, start_ns: int | None = None,
        true_array: Path | None = None, error_seed: int | None = None, position_error_std: float | None = None,
        truth_array_out: Path | None = None, force: bool = False, quiet: bool = False) -> int:
    """Simulate a recording of ``array`` (rms_rate in deg/s, angular_accel in deg/s^2).

    ``start_ns``: stamp of the first sample, ns since the epoch (default: now).
    ``duration`` (default 5 s) and ``rate`` (default 1000 Hz) for twist and random; the
    icosahedron session (nilsson2014; ``rate`` default 100 Hz) lasts 20 ``still_seconds``
    (default 3) + 19 ``transition_seconds`` (default 2) + ``twist_seconds`` (default 0), with
    each rest tilted by ``tilt_std_deg`` (default 1) per axis, and rejects ``duration``.
    """
    if motion not in workflows.MOTIONS:
        raise ImuArrayError(f"--motion must be 'twist', 'random' or 'icosahedron', not {motion!r}")
    duration, rate, ico = _session(motion, duration, rate, still_seconds, transition_seconds, tilt_std_deg,
                                   twist_seconds)
    if position_error_std is not None and error_seed is None:
        raise ImuArrayError("--position-error-std needs --error-seed (it sets the size of the seeded errors)")
    inputs = [array, true_array]
    out = check_output(out, inputs, "recording", force, other_outputs=[("--truth-array-out", truth_array_out)])
    if truth_array_out is not None:
        truth_array_out = check_output(truth_array_out, inputs, "yaml", force, option="--truth-array-out",
                                       other_outputs=[("--out", out)])
    n = int(round(duration * rate))
    length = f"the icosahedron session ({duration:g} s)" if motion == "icosahedron" else f"--duration {duration:g} s"
    if n < 1:
        raise ImuArrayError(f"{length} at --rate {rate:g} Hz gives no sample")
    if n > MAX_SIMULATED_SAMPLES:
        raise ImuArrayError(f"{length} at --rate {rate:g} Hz gives {n} samples, more than {MAX_SIMULATED_SAMPLES}")
    if start_ns is None:
        start_ns = time.time_ns()
    if start_ns + int(round((n - 1) * 1e9 / rate)) > MAX_STAMP_NS:
        raise ImuArrayError("--start-time plus --duration ends after 2038-01-19T03:14:07Z "
                            "(int32 seconds of a ROS time stamp)")

    desc = load_description(array)
    workflows.check_fusable(desc, array)
    true_desc = load_description(true_array) if true_array else None
    sim = workflows.simulate(desc, motion=motion, duration=duration, rate=rate, rms_rate=rms_rate,
                             angular_accel=angular_accel, seed=seed, start_ns=start_ns, true_desc=true_desc,
                             error_seed=error_seed, position_error_std=position_error_std, **ico)
    info(quiet, f"simulated {len(sim.samples)} samples of {len(desc.imus)} IMUs ({motion}, {duration:g} s at "
                f"{rate:g} Hz)")
    write_imu_recording(out, sim.samples, desc, truth=sim.truth)
    info(quiet, f"wrote {out}")
    if truth_array_out is not None:
        true = sim.true_description
        record = true.with_imus(true.imus, calibration={"method": "simulation ground truth", "seed": seed,
                                                        "error_seed": error_seed})
        try:
            save_description(record, truth_array_out)
        except OSError as err:
            raise OutputError(f"{truth_array_out}: cannot write --truth-array-out: {err.strerror or err}") from None
        info(quiet, f"wrote {truth_array_out}")
    return 0
