"""Does ``calibrate all --timing`` hold up on captures it did not see?  The calibration with the timing stage
(sample clocks found, time offsets refitted with the moving terms) and the one without, both of the whole of
``--fit``, scored on the moving phases of the other captures; and a third: the calibration without timing with
the --timing one's sample clocks and only the time offsets refitted (positions and gyroscope terms held), which
separates what the timing terms bring from what the moving terms' refit with them does.  With ``--baseline TREE``
(a git worktree of older code): a fourth, ``calibrate all --timing`` of that tree's code (run there in a
subprocess), scored here by the same code, so old and new timing stages are compared in one run.

For each scored capture (its moving phase: from ``--lead`` s before the first |gyro| > ``--moving`` rad/s, as
benchmarks/real_discovery_heldout.py, ``--duration`` s of it): the sample clocks' phases of that recording
estimated under the timing calibration (a session state, as ``fuse`` does; the clock rates and time offsets are
the calibration's), then every sample's motion at its ML estimate under each calibration
(:func:`~imu_array_ros.fitting.engine.fit_motion`, whose trajectory rounds now reach their fixed point; reading rates
off, as the calibration fits) and: log-likelihood per sample, NIS on the moving samples (sum of squared normalised
residuals / (valid axes - 9 x samples)).  Nothing is tuned here.

    python -m benchmarks.real_timing_heldout --fit exp_3 [exp_5 ...] [--baseline TREE] [--jobs 2] [--duration 60]
        [--work DIR]

Several ``--fit`` captures each get their own calibrations and table (``--jobs``: that many fits at once, one
process each).  Writes benchmarks/results/real_timing_heldout.md (+ .json).
"""

from __future__ import annotations

from benchmarks.harness import DATA, REPO, RESULTS, load_average, machine_header, say, single_threaded_blas, \
    write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import pickle  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
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
                     "skipped": dict(cal.details.skipped), "timed": bool(cal.details.timed),
                     "gain_std": cal.std.get("gyroscope_gain")}
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


#: run in the baseline tree (its own imu_array_ros): calibrate all --timing of argv[2] with argv[1]'s description,
#: pickled to argv[3]
_BASELINE_CODE = """
import os, pickle, sys, time
from imu_array_ros import workflows
desc, _ = workflows.load_array(sys.argv[1])
samples, _ = workflows.import_openshoe(sys.argv[2], desc, start_ns=0)
t0 = time.monotonic()
cal = workflows.calibrate("all", samples, desc, timing=True)
out = {"model": cal.model, "seconds": time.monotonic() - t0, "summary": cal.summary(),
       "skipped": dict(cal.details.skipped), "timed": bool(cal.details.timed),
       "gain_std": cal.std.get("gyroscope_gain")}
tmp = sys.argv[3] + ".tmp"
with open(tmp, "wb") as fh:
    fh.write(pickle.dumps(out))
os.replace(tmp, sys.argv[3])
"""


def baseline_label(tree: Path) -> str:
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=tree, capture_output=True, text=True,
                          check=True).stdout.strip()
    return f"--timing at {head}"


def baseline_calibration(fit: str, tree: Path, work: Path | None) -> dict:
    """calibrate all --timing of the whole capture by the code of ``tree`` (a subprocess with that tree first on
    the path; its model is unpickled here: the model's classes must not have changed in between)."""
    label = baseline_label(tree)
    cache = (work or Path(os.environ.get("TMPDIR", "/tmp"))) / f"{fit}_baseline_{label.split()[-1]}.pkl"
    if not cache.exists():
        env = dict(os.environ, PYTHONPATH=str(tree))
        subprocess.run([sys.executable, "-c", _BASELINE_CODE, str(ARRAY), str(DATA / f"{fit}.bin"), str(cache)],
                       cwd=tree, env=env, check=True)
    out = pickle.loads(cache.read_bytes())
    say(f"{fit}: calibrate all {label}: {out['seconds']:.0f} s; timed {out['timed']}")
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


def gains(model, untimed, std) -> str:
    """The reference IMU's gyroscope gains, the other IMUs' mean per axis, and the change from calibrate all's
    (``untimed``) in its written std ``std`` (K, 3; NaN: held): mean per axis over the IMUs and the largest."""
    gg = model.terms["gyroscope_gain"].values
    text = (f"{model.names[0]} gyroscope gain {', '.join(f'{v:.4f}' for v in gg[0])}; the others' mean "
            f"{', '.join(f'{v:.4f}' for v in gg[1:].mean(axis=0))}")
    if std is None or model is untimed:
        return text
    z = (gg - untimed.terms["gyroscope_gain"].values) / np.asarray(std, dtype=float)
    return (text + f"; change from without timing in its written std: mean over the IMUs "
            f"{', '.join(f'{v:+.1f}' for v in np.nanmean(z, axis=0))} (x, y, z), largest {np.nanmax(np.abs(z)):.1f}")


def run_fit(fit: str, args) -> dict:
    """Calibrations of ``fit`` (cached in ``--work``) scored on the other captures (each score cached there too)."""
    from imu_array_ros import workflows

    work = Path(args.work) if args.work else None
    base = baseline_calibration(fit, Path(args.baseline), work) if args.baseline else None
    cals = dict(calibrations(fit, work))
    if base is not None:
        cals[baseline_label(Path(args.baseline))] = base
    desc, _ = workflows.load_array(ARRAY)
    rows = []
    for cap in args.score or [c for c in CAPTURES if c != fit]:
        if cap == fit:
            continue
        part = None
        row = {"capture": cap}
        for name, c in cals.items():
            cache = None if work is None else work / f"{fit}_{cap}_{name.replace(' ', '_')}.json"
            if cache is not None and cache.exists():
                row[name] = json.loads(cache.read_text())
                continue
            if part is None:
                samples, _ = workflows.import_openshoe(DATA / f"{cap}.bin", desc, start_ns=0)
                part = moving_phase(samples, args.moving, args.lead, args.duration)[0]
            row[name] = score(part, c["model"])
            say(f"{fit} -> {cap} {name}: {row[name]}")
            if cache is not None:
                cache.write_text(json.dumps(row[name], default=float))
        rows.append(row)
    untimed, std = cals["without timing"]["model"], cals["without timing"].get("gain_std")
    return {"fit": fit, "calibrations": {k: {**{kk: vv for kk, vv in v.items() if kk not in ("model", "gain_std")},
                                             "gains": gains(v["model"], untimed, std)} for k, v in cals.items()},
            "rows": rows}


def render(result: dict, args) -> str:
    fit, cals, rows = result["fit"], result["calibrations"], result["rows"]
    names = list(cals)
    timed = [n for n in names if n != "without timing"]
    others = [n for n in timed if n != "--timing"]
    lines = ["## Calibrations of the whole of " + fit, ""]
    for name, c in cals.items():
        lines.append(f"- {name}: {c['seconds']:.0f} s, timing terms: {c['timed']}; skipped: "
                     f"{c['skipped'] or 'nothing'}; {c['gains']}; {c['summary']}")
    lines += ["", f"## {fit}'s calibrations scored on the other captures' moving phases ("
                  f"{f'{args.duration:g} s' if args.duration else 'to the end'}, from {args.lead:g} s before "
                  f"|gyro| > {args.moving:g} rad/s)", "",
              "| scored on | samples | " + " | ".join(f"log-lik / sample, {n}" for n in names) + " | "
              + " | ".join(f"NIS moving, {n}" for n in names) + " | "
              + " | ".join(f"ratio {n} / without timing" for n in timed) + " | "
              + " | ".join(f"ratio --timing / {n}" for n in others)
              + " | fit_motion converged, rounds (--timing) |",
              "|---|---|" + "---|" * (2 * len(names) + len(timed) + len(others) + 1)]
    for r in rows:
        a = r["without timing"]
        lines.append(f"| {r['capture']} | {a['samples']} | "
                     + " | ".join(f"{r[n]['loglik_per_sample']:.1f}" for n in names) + " | "
                     + " | ".join(f"{r[n]['nis']:.4g}" for n in names) + " | "
                     + " | ".join(f"{r[n]['nis'] / a['nis']:.3f}" for n in timed) + " | "
                     + " | ".join(f"{r['--timing']['nis'] / r[n]['nis']:.3f}" for n in others) + " | "
                     + ", ".join(str(r[n]["converged"]) for n in names) + f", {r['--timing']['rounds']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", nargs="+", default=["exp_3"], choices=CAPTURES, help="calibrated captures")
    ap.add_argument("--score", nargs="+", choices=CAPTURES, help="scored captures (default: every other one)")
    ap.add_argument("--baseline", help="a git worktree of older code: its calibrate all --timing added")
    ap.add_argument("--jobs", type=int, default=1, help="fits at once, one process each")
    ap.add_argument("--moving", type=float, default=10.0, help="|gyro| (rad/s) that starts the moving phase")
    ap.add_argument("--lead", type=float, default=2.0, help="seconds kept before it")
    ap.add_argument("--duration", type=float, help="seconds of each moving phase (default: to the end)")
    ap.add_argument("--work", help="cache directory for the calibrations and scores")
    args = ap.parse_args(argv)
    if args.work:
        Path(args.work).mkdir(parents=True, exist_ok=True)
    if args.baseline:
        args.baseline = str(Path(args.baseline).resolve())
    load0 = load_average()
    if args.jobs > 1 and len(args.fit) > 1:
        with ProcessPoolExecutor(min(args.jobs, len(args.fit))) as pool:
            results = list(pool.map(run_fit, args.fit, [args] * len(args.fit)))
    else:
        results = [run_fit(fit, args) for fit in args.fit]
    with open(f"{OUT}.json", "w") as fh:
        json.dump(results, fh, indent=1, default=float)
    extra = [f"load average at the start: {load0}; at the end: {load_average()}"]
    if args.baseline:
        extra.append(f"baseline: {baseline_label(Path(args.baseline)).split()[-1]} (worktree, its calibrate all "
                     f"--timing run in a subprocess; scored with this commit's code)")
    header = machine_header("calibrate all --timing against calibrate all, scored on held-out captures",
                            extra=tuple(extra))
    write_results(Path(f"{OUT}.md"), header + "".join(render(r, args) + "\n" for r in results).rstrip("\n")
                  + "\n")
    say(f"wrote {OUT}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
