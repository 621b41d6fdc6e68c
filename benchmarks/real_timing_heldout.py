"""Does ``calibrate all --timing`` hold up on captures it did not see?  The calibration with the timing stage
(sample clocks found, time offsets refitted with the moving terms) and the one without, both of the whole of
``--fit``, scored on the moving phases of the other captures; and a third: the calibration without timing with
the --timing one's sample clocks and only the time offsets refitted (positions and gyroscope terms held), which
separates what the timing terms bring from what the moving terms' refit with them does.

For each scored capture (its moving phase: from ``--lead`` s before the first |gyro| > ``--moving`` rad/s, as
benchmarks/real_discovery_heldout.py, ``--duration`` s of it): the sample clocks' phases of that recording
estimated under the timing calibration (a session state, as ``fuse`` does; the clock rates and time offsets are
the calibration's), then every sample's motion at its ML estimate under each calibration
(:func:`~imu_array_ros.fitting.engine.fit_motion`, whose trajectory rounds now reach their fixed point; reading rates
off, as the calibration fits) and: log-likelihood per sample, NIS on the moving samples (sum of squared normalised
residuals / (valid axes - 9 x samples)).  Nothing is tuned here.

    python -m benchmarks.real_timing_heldout --fit exp_3 [--duration 60] [--work DIR]

Writes benchmarks/results/real_timing_heldout.md (+ .json).
"""

from __future__ import annotations

from benchmarks.harness import DATA, REPO, RESULTS, load_average, machine_header, say, single_threaded_blas, \
    write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks.real_discovery_heldout import moving_phase  # noqa: E402

ARRAY = REPO / "config" / "mimu4444bt_corners.yaml"
OUT = RESULTS / "real_timing_heldout"
CAPTURES = tuple(f"exp_{i}" for i in range(1, 7))


def calibrations(fit: str, work: Path | None) -> dict:
    """calibrate all of the whole capture, without and with --timing (cached in ``work``)."""
    from imu_array_ros import workflows

    cache = None if work is None else work / f"{fit}_calibrations.pkl"
    out = pickle.loads(cache.read_bytes()) if cache is not None and cache.exists() else {}
    if len(out) == 3:
        return out
    desc, _ = workflows.load_array(ARRAY)
    samples, _ = workflows.import_openshoe(DATA / f"{fit}.bin", desc, start_ns=0)
    for name, timing in (("without timing", False), ("--timing", True)):
        if name in out:
            continue
        t0 = time.monotonic()
        cal = workflows.calibrate("all", samples, desc, timing=timing)
        out[name] = {"model": cal.model, "seconds": time.monotonic() - t0, "summary": cal.summary(),
                     "skipped": dict(cal.details.skipped), "timed": bool(cal.details.timed)}
        say(f"{fit}: calibrate all {name}: {out[name]['seconds']:.0f} s; timed {out[name]['timed']}")
        if cache is not None:
            cache.write_bytes(pickle.dumps(out))
    from imu_array_ros.workflows.arrays import as_model

    out["time offsets alone"] = offsets_alone(samples, as_model(desc), out["without timing"]["model"],
                                              out["--timing"]["model"])
    say(f"{fit}: time offsets alone: {out['time offsets alone']['seconds']:.0f} s")
    if cache is not None:
        cache.write_bytes(pickle.dumps(out))
    return out


def offsets_alone(samples, start, untimed, timed) -> dict:
    """The timing stage's refit with only the timing terms free: calibrate all's model ``untimed`` (its positions and
    gyroscope terms held) with the --timing calibration's sample clocks (this capture's phases), time offsets fitted
    on the same moving samples as the timing stage, the reference gyroscope's held (the gauge of time)."""
    from imu_array_ros.calibration.still import find_still_poses
    from imu_array_ros.fitting.engine import fit_terms

    t0 = time.monotonic()
    clocks = {t: timed.terms[t].values for t in ("gyroscope_sample_clock", "accelerometer_sample_clock",
                                                 "sample_clock") if t in timed.terms}
    model = untimed.with_terms(**clocks)
    window = samples.select(np.flatnonzero(find_still_poses(samples, start).moving))  # as calibrate_array finds them
    fit = fit_terms(window, model, ["time_offset"], t0_ns=int(samples.stamps[0]), max_iterations=50,
                    hold=[f"{model.names[0]} gyroscope.time_offset"], sandwich=False)
    return {"model": fit.model, "seconds": time.monotonic() - t0, "summary": f"NIS {fit.nis_before:.4g} -> "
            f"{fit.nis_after:.4g}, {fit.iterations} iterations, converged {fit.converged}", "skipped": {},
            "timed": True}


def score(samples, model) -> dict:
    """Log-likelihood per sample and moving NIS of ``samples`` under ``model`` (this recording's clock phases
    first), every sample's motion at its ML estimate."""
    from imu_array_ros.fitting.engine import fit_motion
    from imu_array_ros.timing.session import active_clocks, estimate_session

    t0 = time.monotonic()
    if active_clocks(model):
        model = estimate_session(samples, model).model
    fit = fit_motion(samples, model)
    r = np.nan_to_num(fit.residuals)
    valid = samples.valid(model)
    n = len(samples)
    dof = int(valid.sum()) - 9 * n
    return {"loglik_per_sample": fit.loglik / n, "nis": float(np.sum(r * r)) / dof, "samples": n,
            "converged": fit.converged, "rounds": fit.rounds, "seconds": time.monotonic() - t0}


def render(fit: str, cals: dict, rows: list[dict], args) -> str:
    lines = ["## Calibrations of the whole of " + fit, ""]
    for name, c in cals.items():
        gg = c["model"].terms["gyroscope_gain"].values
        lines.append(f"- {name}: {c['seconds']:.0f} s, timing terms: {c['timed']}; skipped: "
                     f"{c['skipped'] or 'nothing'}; imu_1 gyroscope gain {', '.join(f'{v:.4f}' for v in gg[0])}; "
                     f"{c['summary']}")
    lines += ["", f"## Scored on the other captures' moving phases ("
                  f"{f'{args.duration:g} s' if args.duration else 'to the end'}, from {args.lead:g} s before |gyro| > {args.moving:g} rad/s)", "",
              "| scored on | samples | log-lik / sample, without timing | with --timing | time offsets alone | "
              "NIS moving, without | with --timing | time offsets alone | ratio --timing / without | "
              "ratio --timing / time offsets alone | fit_motion converged (3), rounds (--timing) |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        a, b, c = r["without timing"], r["--timing"], r["time offsets alone"]
        lines.append(f"| {r['capture']} | {a['samples']} | {a['loglik_per_sample']:.1f} | "
                     f"{b['loglik_per_sample']:.1f} | {c['loglik_per_sample']:.1f} | {a['nis']:.4g} | {b['nis']:.4g} | "
                     f"{c['nis']:.4g} | {b['nis'] / a['nis']:.3f} | {b['nis'] / c['nis']:.3f} | "
                     f"{a['converged']}, {b['converged']}, {c['converged']}, {b['rounds']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", default="exp_3", choices=CAPTURES)
    ap.add_argument("--score", nargs="+", choices=CAPTURES, help="scored captures (default: every other one)")
    ap.add_argument("--moving", type=float, default=10.0, help="|gyro| (rad/s) that starts the moving phase")
    ap.add_argument("--lead", type=float, default=2.0, help="seconds kept before it")
    ap.add_argument("--duration", type=float, help="seconds of each moving phase (default: to the end)")
    ap.add_argument("--work", help="cache directory for the calibrations")
    args = ap.parse_args(argv)
    from imu_array_ros import workflows

    work = Path(args.work) if args.work else None
    if work is not None:
        work.mkdir(parents=True, exist_ok=True)
    load0 = load_average()
    cals = calibrations(args.fit, work)
    desc, _ = workflows.load_array(ARRAY)
    rows = []
    for cap in args.score or [c for c in CAPTURES if c != args.fit]:
        samples, _ = workflows.import_openshoe(DATA / f"{cap}.bin", desc, start_ns=0)
        part = moving_phase(samples, args.moving, args.lead, args.duration)[0]
        row = {"capture": cap}
        for name, c in cals.items():
            row[name] = score(part, c["model"])
            say(f"{cap} {name}: {row[name]}")
        rows.append(row)
        with open(f"{OUT}.json", "w") as fh:
            json.dump({"fit": args.fit, "calibrations": {k: {kk: vv for kk, vv in v.items() if kk != "model"}
                                                         for k, v in cals.items()}, "rows": rows}, fh, indent=1,
                      default=float)
    header = machine_header("calibrate all --timing against calibrate all, scored on held-out captures",
                            extra=(f"load average at the start: {load0}; at the end: {load_average()}",))
    write_results(Path(f"{OUT}.md"), header + render(args.fit, cals, rows, args))
    say(f"wrote {OUT}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
