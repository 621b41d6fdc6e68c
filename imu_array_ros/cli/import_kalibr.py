"""``imu-array import FORMAT``: another tool's calibration into an array description.

* ``import kalibr``: Kalibr's IMU set (``imu0``, ``imu1``, ...; :mod:`imu_array_ros.io.kalibr`, docs/kalibr.md).

(The module is not named ``import``: that is a Python keyword.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros.cli.options import add_force_quiet
from imu_array_ros.cli.progress import info
from imu_array_ros.io.kalibr import description_from_kalibr, load_kalibr
from imu_array_ros.io.outputs import check_output
from imu_array_ros.model.description import load_description, save_description

__all__ = ["add_parser", "run_kalibr"]

FORCE_YAML_HELP = "replace an existing --out, only if it is itself a YAML file holding a mapping (never an input)"


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("import", help="read another tool's calibration into an array description")
    formats = sp.add_subparsers(dest="format_command", required=True, metavar="FORMAT")
    k = formats.add_parser("kalibr", help="Kalibr's multi-IMU YAML (imu0, imu1, ...), matched to the array by order")
    k.add_argument("kalibr_file", type=Path, metavar="KALIBR.yaml", help="Kalibr IMU-set YAML (imu0, imu1, ...)")
    k.add_argument("--array", required=True, type=Path,
                   help="array description: IMU names and order (imu0 = its first IMU) and every value Kalibr "
                        "does not give")
    k.add_argument("--out", required=True, type=Path, help="the description to write")
    add_force_quiet(k, force=FORCE_YAML_HELP)
    k.set_defaults(handler=run_kalibr)
    return sp


def run_kalibr(kalibr_file: Path, *, array: Path, out: Path, force: bool = False, quiet: bool = False) -> int:
    """Write ``array`` with the positions, orientations, noise, time offsets and intrinsics of ``kalibr_file``."""
    out = check_output(out, [kalibr_file, array], "yaml", force)
    desc = load_description(array)
    imus = load_kalibr(kalibr_file)
    result, notes = description_from_kalibr(imus, desc, source=str(kalibr_file))
    save_description(result, out)
    for note in notes:
        info(quiet, f"note: {note}")
    info(quiet, f"wrote {out}: {len(imus)} IMUs from Kalibr ({', '.join(sorted({k.model for k in imus}))})")
    return 0
