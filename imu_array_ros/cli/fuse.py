"""``imu-array fuse``: ML fusion of a recording (skog2016) with Cramér-Rao covariances
(:func:`imu_array_ros.workflows.fuse_recording`: the fusion the fusion node runs, every term of the description)."""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros.cli.options import FORCE_RECORDING_HELP, add_force_quiet, add_recording_inputs, read_and_fuse
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import FusionError
from imu_array_ros.io.outputs import check_output
from imu_array_ros.io.rosbag.recording import write_fused_recording

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("fuse", help="ML fusion of a recording (skog2016) with Cramér-Rao covariances")
    add_recording_inputs(sp, array="array description YAML",
                         calibration="calibrated description (same schema) to use instead of --array's values")
    sp.add_argument("--out", required=True, type=Path, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--no-bias-tracking", dest="bias_tracking", action="store_false",
                    help="fuse with the description's gyroscope biases throughout (default: re-measured on every "
                         "still interval of 1 s or more, the description's before the first)")
    add_force_quiet(sp, force=FORCE_RECORDING_HELP)
    sp.set_defaults(handler=run)
    return sp


def run(recording: Path, *, array: Path, out: Path, calibration: Path | None = None, bias_tracking: bool = True,
        force: bool = False, quiet: bool = False) -> int:
    """ML fusion of ``recording`` (skog2016) into ``out`` with Cramér-Rao covariances; the gyroscope biases
    tracked on the still intervals unless ``bias_tracking`` is False."""
    out = check_output(out, [recording, array, calibration], "recording", force)
    desc, f = read_and_fuse(recording, array, calibration, quiet, bias_tracking=bias_tracking)
    r, s = f.read_stats, f.stats
    info(quiet, f"read {r.samples} array samples ({r.messages} messages); bad messages {r.bad_messages}, "
                f"duplicates {r.duplicate_messages}, incomplete samples {r.incomplete_samples}")
    info(quiet, f"fused {s.fused} of {s.samples} samples; skipped (not identifiable) {s.skipped_unidentifiable}, "
                f"saturated-gyro samples {s.saturated_gyro_samples}, not converged {s.not_converged}")
    if s.skipped_stamps:
        info(quiet, "  first skipped stamps (ns): " + ", ".join(map(str, s.skipped_stamps)))
    if s.not_converged:
        # said even with -q: on a sound recording this is the description not fitting the array
        info(False, f"imu-array: warning: the estimate of {s.not_converged} samples did not converge; unless the "
                    "array spun beyond its gyroscopes' range, the description does not fit it (a position or "
                    f"orientation typo?): `imu-array residuals {recording} --array {array}` shows which IMU")
    if s.fused == 0:
        raise FusionError(f"{recording}: no sample could be fused (see counts above)")
    write_fused_recording(out, f.fused, desc.frame_id)
    info(quiet, f"wrote {out}")
    return 0
