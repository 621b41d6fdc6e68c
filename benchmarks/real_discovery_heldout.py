"""Discovery's findings on the real captures, scored on captures they were not found on (issue 23's real target:
after ``calibrate all`` + ``discover --apply``, held-out moving NIS >= 10 % below calibration alone and <= 1,500).

For each ``--fit`` capture F of ../shared/data/openshoe_mimu4444bt/ (imported as ``imu-array import-openshoe``):

1. ``calibrate all`` of the whole of F from config/mimu4444bt_corners.yaml (the workflow function the CLI calls);
2. discovery (:func:`imu_array_ros.workflows.discover`, defaults) on F's moving phase -- from ``--lead`` s before
   the first sample where some gyroscope reads more than ``--moving`` rad/s to the end -- or with ``--whole``
   on all of F (slow: ~35 min on this machine);
3. whether ``discover --apply`` would install the findings (:func:`~imu_array_ros.discovery.apply.
   findings_calibration` with the calibration's checks) or refuses them, and why;
4. the other captures' moving phases (same rule) as discovery's validation recordings: log-likelihood and NIS
   under the calibration alone (``before``) and with the findings (``after``; sample-clock phases of each
   recording estimated on it, as ``discover --validate`` does).

Nothing is tuned here: the findings are discovery's own, the moving phase is found by one threshold applied
alike to every capture.  Writes benchmarks/results/real_discovery_heldout.md (+ .json).

    python -m benchmarks.real_discovery_heldout --fit exp_3 [--fit exp_1 ...] [--whole]
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks.harness import DATA, REPO, RESULTS, load_average, machine_header, say, single_threaded_blas, \
    write_results

ARRAY = REPO / "config" / "mimu4444bt_corners.yaml"
OUT = RESULTS / "real_discovery_heldout"
CAPTURES = tuple(f"exp_{i}" for i in range(1, 7))


def moving_phase(samples, moving: float, lead: float, duration: float | None = None):
    """The samples from ``lead`` s before the first |gyro| > ``moving`` rad/s (any IMU, any axis) to the end
    (or ``duration`` s)."""
    import numpy as np

    wmax = np.nanmax(np.abs(samples.gyro), axis=(1, 2))
    first = int(np.argmax(wmax > moving))
    if not wmax[first] > moving:
        raise SystemExit(f"no gyroscope reads more than {moving} rad/s")
    t0 = (samples.stamps[first] - samples.stamps[0]) * 1e-9 - lead
    return samples.window(max(t0, 0.0), duration), max(t0, 0.0)


def run_one(fit: str, others, args, log) -> dict:
    from imu_array_ros import workflows
    from imu_array_ros.discovery.apply import findings_calibration
    from imu_array_ros.errors import CalibrationError
    from imu_array_ros.workflows.arrays import as_model

    desc, _ = workflows.load_array(ARRAY)
    samples, _ = workflows.import_openshoe(DATA / f"{fit}.bin", desc, start_ns=0)
    t = time.monotonic()
    cal = workflows.calibrate("all", samples, desc)
    t_cal = time.monotonic() - t
    caldesc = cal.apply(desc)
    log(f"{fit}: calibrate all {t_cal:.1f} s")
    part, t0 = (samples, 0.0) if args.whole else moving_phase(samples, args.moving, args.lead, args.duration)
    validate = []
    for o in others:
        s, _ = workflows.import_openshoe(DATA / f"{o}.bin", desc, start_ns=0)
        validate.append((o, moving_phase(s, args.moving, args.lead, args.duration)[0]))
    t = time.monotonic()
    d = workflows.discover(part, caldesc, validate=validate, progress=lambda text: log(f"{fit}: {text}"))
    t_disc = time.monotonic() - t
    try:
        findings_calibration(d, part, start=as_model(caldesc))
        applied = "installed"
    except CalibrationError as err:
        applied = f"refused: {err}"
    return {"fit": fit, "window_start_s": round(t0, 2), "samples": len(part), "calibrate_s": round(t_cal, 1),
            "discover_s": round(t_disc, 1), "apply": applied,
            "findings": [f"{f.effect} on {f.sensor}" for f in d.findings],
            "finding_values": [f.to_dict()["parameters"] for f in d.findings],
            "rejected": [{k: r[k] for k in ("effect", "scope", "step", "reason") if k in r} for r in d.rejected],
            "notes": list(d.notes),
            "fit_before": d.baseline.to_dict(), "fit_after": d.after.to_dict(),
            "validation": d.validation}


def nis_moving(summary: dict) -> float:
    return summary["nis_moving"]


def render(runs: list[dict], header: str) -> str:
    lines = [header, "## Per fit capture", "",
             "| fit on | window (s from start) | samples | calibrate all (s) | discover (s) | NIS moving before -> after "
             "(own) | --apply | findings |", "|---|---|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['fit']} | {r['window_start_s']:g}- | {r['samples']} | {r['calibrate_s']} | "
                     f"{r['discover_s']} | {nis_moving(r['fit_before']):.4g} -> {nis_moving(r['fit_after']):.4g} | "
                     f"{r['apply']} | {'; '.join(r['findings']) or 'none'} |")
    stops = [f"- {r['fit']}: {n}" for r in runs for n in r.get("notes", []) if "stopped" in n]
    if stops:
        lines += ["", "Where discovery stopped:", "", *stops]
    lines += ["", "## Held out (the other captures' moving phases)", "",
              "| fit on | scored on | NIS moving, calibration alone | with the findings | ratio | Δ log-lik |",
              "|---|---|---|---|---|---|"]
    ratios = []
    for r in runs:
        for v in r["validation"]:
            b, a = nis_moving(v["before"]), nis_moving(v["after"])
            ratios.append(a / b)
            lines.append(f"| {r['fit']} | {v['recording']} | {b:.4g} | {a:.4g} | {a / b:.3f} | {v['delta_loglik']:.4g} |")
    if ratios:
        import numpy as np

        lines += ["", f"Held-out ratio after / before: median {np.median(ratios):.3f}, range {min(ratios):.3f}-"
                      f"{max(ratios):.3f} over {len(ratios)} (fit, scored) pairs.  Target: <= 0.90 and after <= 1,500."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", action="append", choices=CAPTURES, help="capture discovery runs on (repeatable)")
    ap.add_argument("--validate", nargs="+", choices=CAPTURES, help="scored captures (default: every other one)")
    ap.add_argument("--whole", action="store_true", help="discover on the whole fit capture, not its moving phase")
    ap.add_argument("--moving", type=float, default=10.0, help="|gyro| (rad/s) that starts the moving phase")
    ap.add_argument("--lead", type=float, default=2.0, help="seconds kept before it")
    ap.add_argument("--duration", type=float, help="seconds of each moving phase (default: to the end)")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    single_threaded_blas()
    fits = args.fit or ["exp_3"]
    load0 = load_average()
    runs = []
    for fit in fits:
        others = [c for c in (args.validate or CAPTURES) if c != fit]
        runs.append(run_one(fit, others, args, say))
        with open(f"{args.out}.json", "w") as fh:
            json.dump(runs, fh, indent=1, default=float)
    header = machine_header("Discovery's findings on real captures, scored on held-out captures (issue 23)",
                            extra=(f"load average at the start: {load0}; at the end: {load_average()}",))
    write_results(f"{args.out}.md", render(runs, header))
    say(f"wrote {args.out}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
