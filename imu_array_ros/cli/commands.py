"""``imu-array``: the offline command line (same core functions as the ROS nodes).

Subcommands::

    imu-array simulate  --array A.yaml --out REC [--motion twist|random] ...
    imu-array fuse      REC --array A.yaml [--calibration C.yaml] --out OUT
    imu-array import-openshoe CAPTURE --array A.yaml --out REC
    imu-array residuals REC --array A.yaml [--calibration C.yaml] [--compare-simulated]

User mistakes (bad files, missing topics, ...) print one line
``imu-array: error: ...`` and exit with status 2; nothing is half-written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from imu_array_ros import __version__
from imu_array_ros.model.description import ArrayDescription, load_description, save_description
from imu_array_ros.errors import ConfigError, ImuArrayError

__all__ = ["main", "build_parser"]

EXIT_USER_ERROR = 2


class Progress:
    """Progress lines on stderr: a live line on a terminal, a few lines otherwise."""

    def __init__(self, label: str, quiet: bool = False) -> None:
        self.label = label
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.last = -1
        self.t0 = time.perf_counter()

    def __call__(self, done, total=None) -> None:
        if self.quiet:
            return
        frac = float(done) / float(total) if total else float(done)
        pct = int(100 * min(max(frac, 0.0), 1.0))
        bucket = pct // (1 if self.tty else 25)
        if bucket == self.last:
            return
        self.last = bucket
        end = "\r" if self.tty and pct < 100 else "\n"
        print(f"{self.label}: {pct:3d}%  ({time.perf_counter() - self.t0:.1f} s)", end=end, file=sys.stderr, flush=True)


def _info(args, text: str) -> None:
    if not args.quiet:
        print(text, file=sys.stderr)


def _load_array(args) -> ArrayDescription:
    desc = load_description(args.array)
    cal_path = getattr(args, "calibration", None)
    if cal_path:
        cal = load_description(cal_path)
        if set(cal.names) != set(desc.names):
            extra = sorted(set(cal.names) ^ set(desc.names))
            raise ConfigError(f"{cal_path}: IMU names differ from {args.array} (e.g. {extra[0]!r})")
        # a calibrated file is a full description: use it, in the array file's IMU order
        by_name = {imu.name: imu for imu in cal.imus}
        desc = cal.with_imus([by_name[n] for n in desc.names])
    return desc


def _check_out(args, inputs) -> Path:
    out = Path(args.out)
    for inp in inputs:
        if inp is not None and out.resolve() == Path(inp).resolve():
            raise ImuArrayError(f"{out}: output would overwrite the input; choose another --out")
    if out.exists() and not args.force:
        raise ImuArrayError(f"{out}: already exists (use --force to replace it)")
    return out


# --------------------------------------------------------------------------- simulate


def cmd_simulate(args) -> int:
    from imu_array_ros.io.rosbag.recording import write_imu_recording
    from imu_array_ros.model.sensor_model import DEFAULT_ERROR_SCALES, apply_terms, random_error_terms
    from imu_array_ros.simulation.simulator import simulate_random, simulate_twist

    desc = load_description(args.array)
    out = _check_out(args, [])
    rng = np.random.default_rng(args.seed)
    true_desc = load_description(args.true_array) if args.true_array else desc
    if args.true_array and true_desc.names != desc.names:
        raise ConfigError(f"{args.true_array}: IMU names differ from {args.array}")
    if args.error_seed is not None:
        scales = dict(DEFAULT_ERROR_SCALES)
        if args.position_error_std is not None:
            scales["position_offset"] = args.position_error_std
        terms = random_error_terms(len(desc.imus), np.random.default_rng(args.error_seed), scales)
        true_desc = apply_terms(true_desc, terms)
    if args.motion == "twist":
        samples, truth = simulate_twist(true_desc, args.duration, args.rate, rng, rms_rate=np.deg2rad(args.rms_rate))
    else:
        n = int(round(args.duration * args.rate))
        samples, truth = simulate_random(true_desc, n, np.deg2rad(args.rms_rate), np.deg2rad(args.angular_accel),
                                         rng, rate_hz=args.rate)
    if args.truth_array_out:
        save_description(
            true_desc.with_imus(true_desc.imus, calibration={"method": "simulation ground truth", "seed": args.seed,
                                                             "error_seed": args.error_seed}),
            args.truth_array_out,
        )
    _info(args, f"simulated {len(samples)} samples of {len(desc.imus)} IMUs ({args.motion}, {args.duration} s at {args.rate} Hz)")
    write_imu_recording(out, samples, desc, truth=truth)
    _info(args, f"wrote {out}")
    return 0


# --------------------------------------------------------------------------- fuse


def cmd_fuse(args) -> int:
    from imu_array_ros.estimation.ml_fusion import MLFusion
    from imu_array_ros.estimation.stream import fuse_chunked
    from imu_array_ros.io.rosbag.recording import read_imu_recording, write_fused_recording
    from imu_array_ros.model.sensor_model import LinearArrayModel

    desc = _load_array(args)
    out = _check_out(args, [args.recording])
    fusion = MLFusion(LinearArrayModel.from_description(desc))
    samples, rstats = read_imu_recording(args.recording, desc, progress=Progress("reading", args.quiet))
    _info(args, f"read {rstats.samples} array samples ({rstats.messages} messages); bad messages {rstats.bad_messages}, "
                f"duplicates {rstats.duplicate_messages}, incomplete samples {rstats.incomplete_samples}")
    fused, stats = fuse_chunked(fusion, samples, Progress("fusing", args.quiet))
    _info(args, f"fused {stats.fused} of {stats.samples} samples; skipped (not identifiable) {stats.skipped_unidentifiable}, "
                f"saturated-gyro samples {stats.saturated_gyro_samples}, not converged {stats.not_converged}")
    if stats.skipped_stamps:
        _info(args, "  first skipped stamps (ns): " + ", ".join(map(str, stats.skipped_stamps)))
    if stats.fused == 0:
        raise ImuArrayError(f"{args.recording}: no sample could be fused (see counts above)")
    write_fused_recording(out, fused, desc.frame_id)
    _info(args, f"wrote {out}")
    return 0


# --------------------------------------------------------------------------- import-openshoe


def cmd_import_openshoe(args) -> int:
    from imu_array_ros.io.openshoe.capture import import_capture
    from imu_array_ros.io.rosbag.recording import write_imu_recording

    desc = load_description(args.array)
    out = _check_out(args, [args.capture])
    samples, stats = import_capture(args.capture, desc, progress=Progress("parsing", args.quiet))
    _info(args, stats.summary())
    write_imu_recording(out, samples, desc)
    _info(args, f"wrote {out}")
    return 0


# --------------------------------------------------------------------------- residuals


def cmd_residuals(args) -> int:
    from imu_array_ros.estimation.ml_fusion import MLFusion
    from imu_array_ros.estimation.stream import fuse_chunked
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.discovery.residuals import normalized_residuals, simulate_same_motion
    from imu_array_ros.model.sensor_model import LinearArrayModel

    desc = _load_array(args)
    model = LinearArrayModel.from_description(desc)
    samples, _ = read_imu_recording(args.recording, desc, progress=Progress("reading", args.quiet))
    fusion = MLFusion(model)
    fused, stats = fuse_chunked(fusion, samples, Progress("fusing", args.quiet))
    if stats.fused == 0:
        raise ImuArrayError(f"{args.recording}: no sample could be fused")
    reports = {"recording": normalized_residuals(samples, model, fused, still_threshold=args.still_threshold)}
    if args.compare_simulated:
        sim = simulate_same_motion(fused, model, np.random.default_rng(args.seed), like=samples)
        sim_fused, _ = fuse_chunked(fusion, sim, Progress("fusing simulated", args.quiet))
        reports["simulated_same_motion"] = normalized_residuals(sim, model, sim_fused, still_threshold=args.still_threshold)
    result = {name: rep.summary() for name, rep in reports.items()}
    if args.json:
        text = json.dumps(result, indent=2)
        if args.json == "-":
            print(text)
        else:
            from imu_array_ros.io.atomic import atomic_write_text

            atomic_write_text(args.json, text + "\n")
    if not args.json or args.json != "-":
        for name, rep in reports.items():
            for regime in ("still", "moving"):
                s = result[name][regime]
                print(f"## {name}, {regime}: {s['samples']} samples, NIS ratio {s['ratio_all']:.3g} "
                      f"(accelerometers {s['ratio_accelerometers']:.3g}, gyroscopes {s['ratio_gyroscopes']:.3g})")
                if args.tables and s["samples"]:
                    print(rep.table(regime))
    return 0


# --------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="imu-array", description="Inertial sensor array tools (imu_array_ros).")
    p.add_argument("--version", action="version", version=f"imu-array {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def common(sp):
        sp.add_argument("-q", "--quiet", action="store_true", help="no progress or summary lines")

    sp = sub.add_parser("simulate", help="simulate a recording of an array (rosbag2 MCAP)")
    sp.add_argument("--array", required=True, help="array description YAML (nominal; written into the recording)")
    sp.add_argument("--out", required=True, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--motion", choices=["twist", "random"], default="twist",
                    help="twist: smooth hand twisting; random: independent samples (carlsson2017 Monte Carlo)")
    sp.add_argument("--duration", type=float, default=5.0, help="seconds (default 5)")
    sp.add_argument("--rate", type=float, default=1000.0, help="sample rate in Hz (default 1000)")
    sp.add_argument("--rms-rate", type=float, default=600.0,
                    help="twist: RMS angular speed; random: |omega|; deg/s (default 600)")
    sp.add_argument("--angular-accel", type=float, default=2000.0, help="random: |omega_dot| in deg/s^2 (default 2000)")
    sp.add_argument("--seed", type=int, default=0, help="seed of motion and noise (default 0)")
    sp.add_argument("--true-array", help="description holding the true sensor parameters (default: --array)")
    sp.add_argument("--error-seed", type=int, help="add seeded sensor errors (positions, gains, biases, angles)")
    sp.add_argument("--position-error-std", type=float, help="with --error-seed: position error sigma in m (default 1e-4)")
    sp.add_argument("--truth-array-out", help="write the true sensor parameters as a description YAML")
    sp.add_argument("--force", action="store_true", help="replace an existing output")
    common(sp)
    sp.set_defaults(func=cmd_simulate)

    sp = sub.add_parser("fuse", help="ML fusion of a recording (skog2016) with Cramér-Rao covariances")
    sp.add_argument("recording", help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, help="array description YAML")
    sp.add_argument("--calibration", help="calibrated description (same schema) to use instead of --array's values")
    sp.add_argument("--out", required=True, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--force", action="store_true", help="replace an existing output")
    common(sp)
    sp.set_defaults(func=cmd_fuse)

    sp = sub.add_parser("import-openshoe", help="convert an OpenShoe raw serial capture to a recording")
    sp.add_argument("capture", help="raw capture file (e.g. exp_1.bin)")
    sp.add_argument("--array", required=True, help="array description YAML (IMU order = capture order)")
    sp.add_argument("--out", required=True, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--force", action="store_true", help="replace an existing output")
    common(sp)
    sp.set_defaults(func=cmd_import_openshoe)

    sp = sub.add_parser("residuals", help="how well the model explains a recording (normalised residuals)")
    sp.add_argument("recording", help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, help="array description YAML")
    sp.add_argument("--calibration", help="calibrated description (same schema)")
    sp.add_argument("--compare-simulated", action="store_true",
                    help="also analyse a simulated recording of the same (fused) motion")
    sp.add_argument("--still-threshold", type=float, default=0.2, help="|omega| below this (rad/s) is 'still'")
    sp.add_argument("--seed", type=int, default=0, help="seed of the simulated comparison")
    sp.add_argument("--json", help="write the summary as JSON to this file ('-' for stdout)")
    sp.add_argument("--tables", action="store_true", help="print the ratio table by IMU and axis")
    common(sp)
    sp.set_defaults(func=cmd_residuals)
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ImuArrayError as err:
        print(f"imu-array: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("imu-array: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
