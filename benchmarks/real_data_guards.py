"""Never write nonsense: geometry calibration on real windows that mix still poses and motion, before and after
the calibration guards (:mod:`imu_array_ros.calibration.guards`) and the gyroscope stillness test.

For each window (a capture in ../shared/data/openshoe_mimu4444bt/, imported with
config/mimu4444bt_corners.yaml; ``--start`` s after its first sample, ``--duration`` s long,
as ``imu-array calibrate geometry REC --start S --duration D``):

* **before**: what the code before the guards wrote -- ``calibrate_geometry`` with the
  selection it had (``select_rotating(..., gyroscopes=False)``: still samples pass as rotation
  when the fused omega_dot, from uncalibrated accelerometers, is noise), no check; every run
  was written, exit 0.  Reported: converged?, iterations, samples used, largest position change.
* **after**: ``workflows.calibrate("geometry", ...)`` as the command line and the
  ``/calibrate_geometry`` service run it now: refused (the one-line reason) or written (largest
  position change, converged).

The target (issue 22): every window either refused, or converged with every position within the guard's
bound (5 mm) of the description's.  Writes benchmarks/results/real_data_guards.md.

    python -m benchmarks.real_data_guards [--captures exp_1] [--starts 0,60,120,180,240] [--duration 60]
"""

from __future__ import annotations

import argparse
import time
from unittest import mock

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import numpy as np  # noqa: E402

from imu_array_ros import workflows  # noqa: E402
from imu_array_ros.calibration import geometry as geometry_module  # noqa: E402
from imu_array_ros.calibration.guards import POSITION_BOUND  # noqa: E402
from imu_array_ros.calibration.selection import select_rotating  # noqa: E402
from imu_array_ros.errors import CalibrationError  # noqa: E402
from imu_array_ros.io.openshoe.capture import import_capture  # noqa: E402
from imu_array_ros.model.description import load_description  # noqa: E402
from imu_array_ros.model.sensor_model import SensorModel  # noqa: E402

OUT = RESULTS / "real_data_guards.md"
ARRAY = REPO / "config" / "mimu4444bt_corners.yaml"


def before(window, model: SensorModel) -> dict:
    """The geometry calibration as it was written before the guards: old selection, no check."""
    def old(*args, **kwargs):  # the selection without the gyroscope stillness test, whatever the caller asks
        return select_rotating(*args, **{**kwargs, "gyroscopes": False})

    t0 = time.perf_counter()
    try:
        with mock.patch.object(geometry_module, "select_rotating", old):
            r = geometry_module.calibrate_geometry(window, model)
    except CalibrationError as err:  # refused by the data checks that existed before (not written either)
        return {"error": str(err), "seconds": time.perf_counter() - t0}
    return {"converged": r.converged, "iterations": r.iterations, "used": r.samples_used,
            "change_mm": float(r.position_change().max() * 1e3), "seconds": time.perf_counter() - t0}


def after(window, desc) -> dict:
    """``workflows.calibrate("geometry", ...)`` now: refused (reason) or written (largest change)."""
    t0 = time.perf_counter()
    try:
        cal = workflows.calibrate("geometry", window, desc)
    except CalibrationError as err:
        return {"error": str(err), "seconds": time.perf_counter() - t0}
    r = cal.details
    return {"converged": r.converged, "iterations": r.iterations, "used": r.samples_used,
            "dropped_still": int(r.dropped.get("still_by_gyroscopes", 0)),
            "change_mm": float(r.position_change().max() * 1e3), "seconds": time.perf_counter() - t0}


def _before_text(b: dict) -> str:
    if "error" in b:
        return f"refused: {b['error']}"
    wrong = b["change_mm"] > POSITION_BOUND * 1e3
    return (f"written, exit 0; {'converged' if b['converged'] else '**NOT converged**'} "
            f"({b['iterations']} iterations), {b['used']} samples; largest change "
            f"{'**' if wrong else ''}{b['change_mm']:.2f} mm{'**' if wrong else ''}")


def _after_text(a: dict) -> str:
    if "error" in a:
        return f"refused, exit 2: {a['error']}"
    ok = a["converged"] and a["change_mm"] <= POSITION_BOUND * 1e3
    return (f"written; {'converged' if a['converged'] else 'NOT converged'} ({a['iterations']} iterations), "
            f"{a['used']} samples ({a['dropped_still']} still dropped); largest change {a['change_mm']:.2f} mm"
            f"{'' if ok else ' **(target missed)**'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", default="exp_1")
    ap.add_argument("--starts", default="0,60,120,180,240")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--out", type=str, default=str(OUT))
    args = ap.parse_args(argv)
    desc = load_description(ARRAY)
    model = SensorModel.from_description(desc)
    rows = []
    for cap in args.captures.split(","):
        samples, _ = import_capture(DATA / f"{cap}.bin", desc)
        for start in (float(s) for s in args.starts.split(",")):
            window = samples.window(start, args.duration)
            say(f"{cap} {start:g} s: before ...")
            b = before(window, model)
            say(f"  {_before_text(b)} ({b['seconds']:.0f} s); after ...")
            a = after(window, desc)
            say(f"  {_after_text(a)} ({a['seconds']:.0f} s)")
            rows.append((cap, start, b, a))
    met = sum(("error" in a) or (a["converged"] and a["change_mm"] <= POSITION_BOUND * 1e3) for *_, a in rows)
    wrong_before = sum(("error" not in b) and (not b["converged"] or b["change_mm"] > POSITION_BOUND * 1e3)
                       for _, _, b, _ in rows)
    text = machine_header("Calibration guards on real windows that mix still poses and motion",
                          extra=[f"description: config/mimu4444bt_corners.yaml (a 18.9 mm x 18.9 mm board); "
                                 f"windows of {args.duration:g} s; position bound {POSITION_BOUND * 1e3:g} mm"])
    text += ("| window | before: what was written | after: refused (reason) or written |\n| --- | --- | --- |\n")
    for cap, start, b, a in rows:
        text += f"| {cap} {start:g}-{start + args.duration:g} s | {_before_text(b)} | {_after_text(a)} |\n"
    text += (f"\nBefore: {wrong_before} of {len(rows)} windows written unconverged or with a position moved beyond "
             f"{POSITION_BOUND * 1e3:g} mm.  After: {met} of {len(rows)} windows refused or written converged "
             f"within {POSITION_BOUND * 1e3:g} mm (the target: all).\n")
    write_results(args.out, text)
    say(f"wrote {args.out}")
    return 0 if met == len(rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
