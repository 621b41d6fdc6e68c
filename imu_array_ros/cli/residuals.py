"""``imu-array residuals``: how well the model explains a recording (:func:`imu_array_ros.workflows.residuals`).

Summary lines (``## ...``) go to stderr; ``--tables`` prints the ratio tables on
stdout; ``--json`` writes the summary as strict JSON (``-``: stdout), a ratio
over no samples being ``null``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from imu_array_ros import workflows
from imu_array_ros.cli.options import add_force_quiet, add_recording_inputs, non_negative_float, non_negative_int, \
    read_and_fuse
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.errors import FusionError, OutputError
from imu_array_ros.io.outputs import check_output
from imu_array_ros.util.files import atomic_write_text
from imu_array_ros.util.jsontools import json_safe

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("residuals", help="how well the model explains a recording (normalised residuals)")
    add_recording_inputs(sp, array="array description YAML", calibration="calibrated description (same schema)")
    sp.add_argument("--compare-simulated", action="store_true",
                    help="also analyse a simulated recording of the same (fused) motion")
    sp.add_argument("--still-threshold", type=non_negative_float, default=0.2,
                    help="|omega| below this (rad/s, >= 0) is 'still' (default 0.2)")
    sp.add_argument("--seed", type=non_negative_int, default=0, help="seed of the simulated comparison, >= 0")
    sp.add_argument("--json", dest="json_out", metavar="FILE",
                    help="write the summary as JSON to FILE ('-' for stdout); a ratio without samples is null")
    sp.add_argument("--tables", action="store_true", help="print the ratio table by IMU and axis on stdout")
    sp.add_argument("--no-bias-tracking", dest="bias_tracking", action="store_false",
                    help="the description's gyroscope biases throughout (default: re-measured on every still interval, "
                         "as imu-array fuse)")
    add_force_quiet(sp, force="replace an existing --json FILE, only if it is itself a JSON file",
                    quiet="no progress or summary lines on stderr (errors still appear); the result asked for on "
                          "stdout (--tables, --json -) is still printed")
    sp.set_defaults(handler=run)
    return sp


def _g(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def run(recording: Path, *, array: Path, calibration: Path | None = None, compare_simulated: bool = False,
        still_threshold: float = 0.2, seed: int = 0, json_out: str | None = None, tables: bool = False,
        bias_tracking: bool = True, force: bool = False, quiet: bool = False) -> int:
    """How well the model explains ``recording``: normalised residuals by IMU, axis and regime."""
    to_stdout = json_out is not None and str(json_out) == "-"
    json_path = None
    if json_out is not None and not to_stdout:
        json_path = check_output(Path(json_out), [recording, array, calibration], "json", force, option="--json")
    desc, f = read_and_fuse(recording, array, calibration, quiet, bias_tracking=bias_tracking)
    if f.stats.fused == 0:
        raise FusionError(f"{recording}: no sample could be fused")
    reports = workflows.residuals(f.samples, desc, fused=f.fused, fusion=f.fusion, compare_simulated=compare_simulated,
                                  seed=seed,
                                  still_threshold=still_threshold, progress=Progress("fusing simulated", quiet))
    result = json_safe({name: rep.summary() for name, rep in reports.items()})
    if f.session is not None:
        result["session_states"] = json_safe(f.session.summary())
    if f.biases is not None:
        result["gyroscope_biases"] = json_safe(f.biases.summary())

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
        if json_path is None:
            print(text)
        else:
            try:
                atomic_write_text(json_path, text + "\n")
            except OSError as err:
                raise OutputError(f"{json_path}: cannot write --json: {err.strerror or err}") from None
            info(quiet, f"wrote {json_path}")
    sys.stdout.flush()
    return 0
