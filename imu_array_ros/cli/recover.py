"""``imu-array recover``: salvage a truncated or damaged recording
(:func:`imu_array_ros.io.rosbag.recover.recover_recording`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros.cli.options import FORCE_RECORDING_HELP, add_force_quiet
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.io.rosbag.recover import recover_recording

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("recover",
                               help="salvage a truncated or damaged recording (e.g. a recorder killed mid-write)")
    sp.add_argument("recording", type=Path, help="the damaged recording: .mcap file or rosbag2 directory (only read)")
    sp.add_argument("--out", required=True, type=Path,
                    help="the salvaged recording: directory (rosbag2) or file ending in .mcap")
    add_force_quiet(sp, force=FORCE_RECORDING_HELP)
    sp.set_defaults(handler=run)
    return sp


def run(recording: Path, *, out: Path, force: bool = False, quiet: bool = False) -> int:
    """Salvage every complete chunk and message of a truncated or damaged recording into ``out``.

    The input is only read; ``out`` is a new, valid recording (checked like every
    output by the recovery itself).  One summary line says how many messages were kept and lost.
    """
    stats = recover_recording(recording, out, Progress("recovering", quiet), force=force)
    info(quiet, stats.summary())
    info(quiet, f"wrote {out}")
    return 0
