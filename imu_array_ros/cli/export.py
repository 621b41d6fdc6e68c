"""``imu-array export FORMAT``: an array description in another tool's format.

* ``export kalibr``: Kalibr's IMU set (``imu0``, ``imu1``, ...; :mod:`imu_array_ros.io.kalibr`, docs/kalibr.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros.cli.options import add_force_quiet, positive_float, sample_rate
from imu_array_ros.cli.progress import info
from imu_array_ros.io.kalibr import MODELS, dump_kalibr, kalibr_from_description
from imu_array_ros.io.outputs import check_output
from imu_array_ros.model.description import load_description
from imu_array_ros.util.files import atomic_write_text

__all__ = ["add_parser", "run_kalibr"]

FORCE_YAML_HELP = "replace an existing --out, only if it is itself a YAML file holding a mapping (never an input)"


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("export", help="write an array description in another tool's format")
    formats = sp.add_subparsers(dest="format_command", required=True, metavar="FORMAT")
    k = formats.add_parser("kalibr", help="Kalibr's multi-IMU YAML (imu0, imu1, ...: T_i_b, noise, rostopic)")
    k.add_argument("description", type=Path, help="array description (or calibrated description) YAML")
    k.add_argument("--out", required=True, type=Path, help="the Kalibr IMU-set YAML to write")
    k.add_argument("--rate", required=True, type=sample_rate, metavar="HZ",
                   help="the rate the IMUs publish at (Kalibr's update_rate; a description holds none): "
                        "the noise densities are noise_std / sqrt(rate)")
    k.add_argument("--topic-prefix", default="/imu_array",
                   help="rostopic = <prefix>/<name>/data_raw, the driver's topics (default: %(default)s)")
    k.add_argument("--model", choices=MODELS, default=None,
                   help="Kalibr's IMU model (default: scale-misalignment if the description gives gains, "
                        "nonorthogonalities, misalignments or g-sensitivities, else calibrated)")
    k.add_argument("--random-walk-accel", type=positive_float, default=None, metavar="K",
                   help="accelerometer bias random walk, (m/s^2)/sqrt(s), for IMUs whose description has none")
    k.add_argument("--random-walk-gyro", type=positive_float, default=None, metavar="K",
                   help="gyroscope bias random walk, (rad/s)/sqrt(s), for IMUs whose description has none")
    add_force_quiet(k, force=FORCE_YAML_HELP)
    k.set_defaults(handler=run_kalibr)
    return sp


def run_kalibr(description: Path, *, out: Path, rate: float, topic_prefix: str = "/imu_array",
               model: str | None = None, random_walk_accel: float | None = None,
               random_walk_gyro: float | None = None, force: bool = False, quiet: bool = False) -> int:
    """Write ``description`` as Kalibr's IMU set; notes on what does not carry over go to stderr."""
    out = check_output(out, [description], "yaml", force)
    desc = load_description(description)
    imus, notes = kalibr_from_description(desc, rate=rate, topic_prefix=topic_prefix, model=model,
                                          random_walk_accel=random_walk_accel, random_walk_gyro=random_walk_gyro)
    atomic_write_text(out, dump_kalibr(imus))
    for note in notes:
        info(quiet, f"note: {note}")
    info(quiet, f"wrote {out}: {len(imus)} IMUs, model {imus[0].model}")
    return 0
