"""``imu-array`` commands as typed functions (the parser in :mod:`.parser` calls them).

Each function takes the values the command line gives, already validated by
the parser's types, returns the exit status (0), and raises an
:class:`~imu_array_ros.errors.ImuArrayError` subclass for a user mistake.
Every output is checked by :func:`imu_array_ros.io.outputs.check_output` before
any work starts, and written atomically.

stdout carries only what was asked for (``residuals --tables``, ``--json -``);
progress and summary lines go to stderr and ``quiet`` silences them.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.errors import ConfigError, FusionError, ImuArrayError, OutputError
from imu_array_ros.io.outputs import check_output
from imu_array_ros.util.jsontools import json_safe
from imu_array_ros.model.description import ArrayDescription, load_description, save_description
from imu_array_ros.model.identifiability import check_identifiable

__all__ = ["simulate", "fuse", "import_openshoe", "residuals", "recover", "MAX_STAMP_NS", "MAX_SIMULATED_SAMPLES"]

#: Last nanosecond a ROS ``builtin_interfaces/Time`` (int32 seconds) can hold.
MAX_STAMP_NS = (2**31) * 10**9 - 1
#: Upper bound on ``--duration`` x ``--rate`` (keeps a typo from exhausting memory).
MAX_SIMULATED_SAMPLES = 10**8


def load_array(array: Path, calibration: Path | None) -> tuple[ArrayDescription, Path]:
    """The description to fuse with, and the file its values (and geometry) came from."""
    desc = load_description(array)
    if calibration is None:
        return desc, Path(array)
    cal = load_description(calibration)
    if set(cal.names) != set(desc.names):
        extra = sorted(set(cal.names) ^ set(desc.names))
        raise ConfigError(f"{calibration}: IMU names differ from {array} (e.g. {extra[0]!r})")
    # a calibrated file is a full description: use it, in the array file's IMU order
    by_name = {imu.name: imu for imu in cal.imus}
    return cal.with_imus([by_name[n] for n in desc.names]), Path(calibration)


def check_fusable(desc: ArrayDescription, source: Path) -> None:
    """skog2016 Sec. II-D, with the error naming the description file."""
    check_identifiable(desc.positions, len(desc.imus), where=str(source))


def _read_and_fuse(recording: Path, array: Path, calibration: Path | None, quiet: bool):
    """Load the description (checked fusable), read ``recording`` and fuse it in chunks.

    Returns (description, ModelFusion, ImuSamples, ReadStats, FusedSamples, FusionStats);
    the fusion carries every term of the description (``fusion.model``).
    """
    from imu_array_ros.fusion.live import build_fusion
    from imu_array_ros.fusion.stream import fuse_chunked
    from imu_array_ros.io.rosbag.recording import read_imu_recording

    desc, _ = load_array(array, calibration)
    fusion = build_fusion(desc)  # checks it is fusable (naming the file); the fusion node builds the same
    samples, rstats = read_imu_recording(recording, desc, progress=Progress("reading", quiet))
    fused, stats = fuse_chunked(fusion, samples, Progress("fusing", quiet))
    return desc, fusion, samples, rstats, fused, stats


def _write_text(path: Path, text: str, option: str) -> None:
    from imu_array_ros.util.files import atomic_write_text

    try:
        atomic_write_text(path, text)
    except OSError as err:
        raise OutputError(f"{path}: cannot write {option}: {err.strerror or err}") from None


_json_safe = json_safe


def _g(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3g}"


# --------------------------------------------------------------------------- simulate


def simulate(
    array: Path,
    out: Path,
    *,
    motion: str = "twist",
    duration: float | None = None,
    rate: float | None = None,
    rms_rate: float = 600.0,
    angular_accel: float = 2000.0,
    still_seconds: float | None = None,
    transition_seconds: float | None = None,
    tilt_std_deg: float | None = None,
    twist_seconds: float | None = None,
    seed: int = 0,
    start_ns: int | None = None,
    true_array: Path | None = None,
    error_seed: int | None = None,
    position_error_std: float | None = None,
    truth_array_out: Path | None = None,
    force: bool = False,
    quiet: bool = False,
) -> int:
    """Simulate a recording of ``array`` (rms_rate in deg/s, angular_accel in deg/s^2).

    ``start_ns``: stamp of the first sample, ns since the epoch (default: now).
    ``duration`` (default 5 s) and ``rate`` (default 1000 Hz) for twist and random; the
    icosahedron session (nilsson2014; ``rate`` default 100 Hz) lasts 20 ``still_seconds``
    (default 3) + 19 ``transition_seconds`` (default 2) + ``twist_seconds`` (default 0), with
    each rest tilted by ``tilt_std_deg`` (default 1) per axis, and rejects ``duration``.
    """
    from imu_array_ros.io.rosbag.recording import write_imu_recording
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.simulation.icosahedron import FACES, simulate_icosahedron
    from imu_array_ros.simulation.perturb import DEFAULT_ERROR_SCALES, perturb
    from imu_array_ros.simulation.simulator import simulate_random, simulate_twist

    if motion not in ("twist", "random", "icosahedron"):
        raise ImuArrayError(f"--motion must be 'twist', 'random' or 'icosahedron', not {motion!r}")
    session = {"--still-seconds": still_seconds, "--transition-seconds": transition_seconds,
               "--tilt-std-deg": tilt_std_deg, "--twist-seconds": twist_seconds}
    if motion == "icosahedron":
        if duration is not None:
            raise ImuArrayError("--duration does not apply to --motion icosahedron (its length is 20 x "
                                "--still-seconds + 19 x --transition-seconds + --twist-seconds)")
        still_seconds = 3.0 if still_seconds is None else still_seconds
        transition_seconds = 2.0 if transition_seconds is None else transition_seconds
        tilt_std_deg = 1.0 if tilt_std_deg is None else tilt_std_deg
        twist_seconds = 0.0 if twist_seconds is None else twist_seconds
        rate = 100.0 if rate is None else rate
        if still_seconds * rate < 1:
            raise ImuArrayError(f"--still-seconds {still_seconds:g} at --rate {rate:g} Hz leaves a face without "
                                f"a sample at rest")
        duration = FACES * still_seconds + (FACES - 1) * transition_seconds + twist_seconds
    else:
        given = [k for k, v in session.items() if v is not None]
        if given:
            raise ImuArrayError(f"{given[0]} needs --motion icosahedron")
        duration = 5.0 if duration is None else duration
        rate = 1000.0 if rate is None else rate
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
    last_ns = start_ns + int(round((n - 1) * 1e9 / rate))
    if last_ns > MAX_STAMP_NS:
        raise ImuArrayError("--start-time plus --duration ends after 2038-01-19T03:14:07Z "
                            "(int32 seconds of a ROS time stamp)")

    desc = load_description(array)
    check_fusable(desc, Path(array))
    rng = np.random.default_rng(seed)
    true_desc = load_description(true_array) if true_array else desc
    if true_array and true_desc.names != desc.names:
        raise ConfigError(f"{true_array}: IMU names differ from {array}")
    true_model = SensorModel.from_description(true_desc)  # every term of the true description
    if error_seed is not None:
        scales = dict(DEFAULT_ERROR_SCALES)
        if position_error_std is not None:
            scales["position"] = position_error_std
        true_model = perturb(true_model, np.random.default_rng(error_seed), scales)
        true_desc = true_model.to_description(true_desc, names=[n for n in scales if scales[n]])
    if motion == "twist":
        samples, truth = simulate_twist(true_model, duration, rate, rng, rms_rate=np.deg2rad(rms_rate),
                                        start_ns=start_ns)
    elif motion == "icosahedron":
        samples, truth, _ = simulate_icosahedron(true_model, rng, rate_hz=rate, still_s=still_seconds,
                                                 transition_s=transition_seconds,
                                                 tilt_std=float(np.deg2rad(tilt_std_deg)), twist_s=twist_seconds,
                                                 rms_rate=float(np.deg2rad(rms_rate)), start_ns=start_ns)
    else:
        samples, truth = simulate_random(true_model, n, np.deg2rad(rms_rate), np.deg2rad(angular_accel), rng,
                                         rate_hz=rate, start_ns=start_ns)
    info(quiet, f"simulated {len(samples)} samples of {len(desc.imus)} IMUs ({motion}, {duration:g} s at {rate:g} Hz)")
    write_imu_recording(out, samples, desc, truth=truth)
    info(quiet, f"wrote {out}")
    if truth_array_out is not None:
        record = true_desc.with_imus(true_desc.imus, calibration={"method": "simulation ground truth", "seed": seed,
                                                                  "error_seed": error_seed})
        try:
            save_description(record, truth_array_out)
        except OSError as err:
            raise OutputError(f"{truth_array_out}: cannot write --truth-array-out: {err.strerror or err}") from None
        info(quiet, f"wrote {truth_array_out}")
    return 0


# --------------------------------------------------------------------------- fuse


def fuse(
    recording: Path,
    array: Path,
    out: Path,
    *,
    calibration: Path | None = None,
    force: bool = False,
    quiet: bool = False,
) -> int:
    """ML fusion of ``recording`` (skog2016) into ``out`` with Cramér-Rao covariances."""
    from imu_array_ros.io.rosbag.recording import write_fused_recording

    out = check_output(out, [recording, array, calibration], "recording", force)
    desc, _, _, rstats, fused, stats = _read_and_fuse(recording, array, calibration, quiet)
    info(quiet, f"read {rstats.samples} array samples ({rstats.messages} messages); bad messages {rstats.bad_messages}, "
                f"duplicates {rstats.duplicate_messages}, incomplete samples {rstats.incomplete_samples}")
    info(quiet, f"fused {stats.fused} of {stats.samples} samples; skipped (not identifiable) {stats.skipped_unidentifiable}, "
                f"saturated-gyro samples {stats.saturated_gyro_samples}, not converged {stats.not_converged}")
    if stats.skipped_stamps:
        info(quiet, "  first skipped stamps (ns): " + ", ".join(map(str, stats.skipped_stamps)))
    if stats.fused == 0:
        raise FusionError(f"{recording}: no sample could be fused (see counts above)")
    write_fused_recording(out, fused, desc.frame_id)
    info(quiet, f"wrote {out}")
    return 0


# --------------------------------------------------------------------------- import-openshoe


def import_openshoe(
    capture: Path,
    array: Path,
    out: Path,
    *,
    start_ns: int | None = None,
    force: bool = False,
    quiet: bool = False,
) -> int:
    """Convert an OpenShoe raw serial capture into a recording.

    ``start_ns``: stamp of the first packet, ns since the epoch.  Default: the
    last packet is stamped with the capture file's modification time (the
    capture ended when the file was last written).
    """
    from imu_array_ros.io.openshoe.capture import import_capture
    from imu_array_ros.io.rosbag.recording import write_imu_recording

    out = check_output(out, [capture, array], "recording", force)
    desc = load_description(array)
    samples, stats = import_capture(capture, desc, progress=Progress("parsing", quiet),
                                    start_ns=0 if start_ns is None else start_ns)
    if start_ns is None and len(samples):
        end_ns = os.stat(capture).st_mtime_ns
        samples.stamps = samples.stamps + max(end_ns - int(samples.stamps[-1]), 0)
    info(quiet, stats.summary())
    write_imu_recording(out, samples, desc)
    info(quiet, f"wrote {out}")
    return 0


# --------------------------------------------------------------------------- residuals


def residuals(
    recording: Path,
    array: Path,
    *,
    calibration: Path | None = None,
    compare_simulated: bool = False,
    still_threshold: float = 0.2,
    seed: int = 0,
    json_out: str | os.PathLike | None = None,
    tables: bool = False,
    force: bool = False,
    quiet: bool = False,
) -> int:
    """How well the model explains ``recording``: normalised residuals by IMU, axis and regime.

    Summary lines (``## ...``) go to stderr; ``tables`` prints the ratio tables
    on stdout; ``json_out`` writes the summary as strict JSON (``"-"``: stdout),
    a ratio over no samples being ``null``.
    """
    from imu_array_ros.fusion.residuals import normalized_residuals
    from imu_array_ros.simulation.simulator import simulate_same_motion
    from imu_array_ros.fusion.stream import fuse_chunked

    to_stdout = json_out is not None and str(json_out) == "-"
    if json_out is not None and not to_stdout:
        json_out = check_output(json_out, [recording, array, calibration], "json", force, option="--json")
    _, fusion, samples, _, fused, stats = _read_and_fuse(recording, array, calibration, quiet)
    model = fusion.model
    if stats.fused == 0:
        raise FusionError(f"{recording}: no sample could be fused")
    reports = {"recording": normalized_residuals(samples, model, fused, still_threshold=still_threshold)}
    if compare_simulated:
        sim = simulate_same_motion(fused, model, np.random.default_rng(seed), like=samples)
        sim_fused, _ = fuse_chunked(fusion, sim, Progress("fusing simulated", quiet))
        reports["simulated_same_motion"] = normalized_residuals(sim, model, sim_fused, still_threshold=still_threshold)
    result = _json_safe({name: rep.summary() for name, rep in reports.items()})

    for name in reports:
        for regime in ("still", "moving"):
            s = result[name][regime]
            if s["samples"]:
                info(quiet, f"## {name}, {regime}: {s['samples']} samples, NIS ratio {_g(s['ratio_all'])} "
                            f"(accelerometers {_g(s['ratio_accelerometers'])}, gyroscopes {_g(s['ratio_gyroscopes'])})")
            else:
                info(quiet, f"## {name}, {regime}: 0 samples")
    if tables:
        for name, rep in reports.items():
            for regime in ("still", "moving"):
                if result[name][regime]["samples"]:
                    print(f"## {name}, {regime}: NIS ratio by IMU and axis\n\n{rep.table(regime)}")
    if json_out is not None:
        text = json.dumps(result, indent=2, allow_nan=False)
        if to_stdout:
            print(text)
        else:
            _write_text(Path(json_out), text + "\n", "--json")
            info(quiet, f"wrote {json_out}")
    sys.stdout.flush()
    return 0


def recover(recording: Path, out: Path, *, force: bool = False, quiet: bool = False) -> int:
    """Salvage every complete chunk and message of a truncated or damaged recording into ``out``.

    The input is only read; ``out`` is a new, valid recording (checked like every
    output).  One summary line says how many messages were kept and lost.
    """
    from imu_array_ros.io.rosbag.recover import recover_recording

    stats = recover_recording(recording, out, Progress("recovering", quiet), force=force)
    info(quiet, stats.summary())
    info(quiet, f"wrote {out}")
    return 0
