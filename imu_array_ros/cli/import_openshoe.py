"""``imu-array import-openshoe``: an OpenShoe raw serial capture as a recording
(:func:`imu_array_ros.workflows.import_openshoe`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros import workflows
from imu_array_ros.cli.options import FORCE_RECORDING_HELP, add_force_quiet, start_time
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.io.outputs import check_output
from imu_array_ros.io.rosbag.recording import write_imu_recording

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("import-openshoe", help="convert an OpenShoe raw serial capture to a recording")
    sp.add_argument("capture", type=Path, help="raw capture file (e.g. exp_1.bin)")
    sp.add_argument("--array", required=True, type=Path, help="array description YAML (IMU order = capture order)")
    sp.add_argument("--out", required=True, type=Path, help="output: directory (rosbag2) or file ending in .mcap")
    sp.add_argument("--start-time", dest="start_ns", type=start_time, metavar="TIME",
                    help="stamp of the first packet: ISO 8601 (2026-11-21T10:00:00Z; UTC without an offset) or "
                         "seconds since the epoch (default: the capture ends at the file's modification time)")
    add_force_quiet(sp, force=FORCE_RECORDING_HELP)
    sp.set_defaults(handler=run)
    return sp


def run(capture: Path, *, array: Path, out: Path, start_ns: int | None = None, force: bool = False,
        quiet: bool = False) -> int:
    """Convert an OpenShoe raw serial capture into a recording.

    ``start_ns``: stamp of the first packet, ns since the epoch.  Default: the
    last packet is stamped with the capture file's modification time (the
    capture ended when the file was last written).
    """
    out = check_output(out, [capture, array], "recording", force)
    desc, _ = workflows.load_array(array)
    samples, stats = workflows.import_openshoe(capture, desc, start_ns=start_ns, progress=Progress("parsing", quiet))
    info(quiet, stats.summary())
    write_imu_recording(out, samples, desc)
    info(quiet, f"wrote {out}")
    return 0
