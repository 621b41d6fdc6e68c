"""fit_motion with timing terms on a real window: does it return the motion it claims, before and after the change
(two trajectory rounds and a ridge on samples with an uninformed coordinate -> rounds to the fixed point, those
coordinates held)?

Setup (cached in ``--work``, shared with benchmarks/bench_timing_rounds.py): capture exp_3, ``calibrate all`` of it,
the discover timing stage on the whole capture (sample clocks, reading rates kept).  On the window ``--start`` s
+ ``--duration`` s, in each source tree given by ``--tree label=path`` (its own subprocess, imu_array_ros
imported from that path):

1. fit_motion from the timing stage's motion, then again from the motion it returned, three calls: a fixed point
   gives the same log-likelihood each time;
2. a discovery-style time_offset refit (every IMU, max_iterations 30, cost_tolerance 0.1) from the first motion;
3. fit_motion under the refit's model from the refit's motion ("profile"), its log-likelihood over every sample
   and over the samples the refit used (the refit drops the samples that do not identify their whole motion), and
   the cost on the dropped samples.

    python -m benchmarks.fit_motion_rounds --work /tmp/h42 --tree before=/tmp/h42/old --tree after=. \
        [--start 500 --duration 60]

Writes benchmarks/results/fit_motion_rounds.md (+ .json).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from benchmarks.harness import REPO, RESULTS, load_average, machine_header, say, write_results

OUT = RESULTS / "fit_motion_rounds"


def measure(work: Path, start: float, duration: float) -> dict:
    """In this process (the tree on sys.path): the measurements of the module docstring."""
    import time

    import numpy as np

    from benchmarks.bench_timing_rounds import real_setup
    from imu_array_ros.fitting.engine import fit_motion, fit_terms, keep_schur
    from imu_array_ros.fitting.reading_rates import reading_rates

    samples, model, motion, rates, _ = real_setup("exp_3", work)
    t = (samples.stamps - samples.stamps[0]) * 1e-9
    sel = np.flatnonzero((t >= start) & (t < start + duration))
    sub = samples.select(sel)
    out = {"samples": len(sub), "rates": bool(rates), "calls": []}
    with reading_rates(rates), keep_schur():
        m, first = motion[sel], None
        for i in range(3):
            t0 = time.perf_counter()
            res = fit_motion(sub, model, m)
            out["calls"].append({"loglik": res[1], "seconds": time.perf_counter() - t0,
                                 "converged": getattr(res, "converged", None), "rounds": getattr(res, "rounds", None)})
            first = res[0] if i == 0 else first
            m = res[0]
        t0 = time.perf_counter()
        every = list(range(model.n_imus))
        fit = fit_terms(sub, model, ["time_offset"], imus=every, only={"time_offset": every}, motion0=first,
                        max_iterations=30, sandwich=False, cost_tolerance=0.1)
        out["refit"] = {"loglik": fit.loglik_after, "converged": bool(fit.converged), "iterations": fit.iterations,
                        "dropped": fit.samples_dropped, "seconds": time.perf_counter() - t0}
        t0 = time.perf_counter()
        prof = fit_motion(sub, fit.model, np.where(np.isfinite(fit.motion), fit.motion, first))
        used = np.isfinite(fit.motion[:, 0])
        r = np.nan_to_num(prof[2])
        valid = sub.valid(fit.model) & used[:, None, None]
        sig = np.broadcast_to(fit.model.std[None], valid.shape)[valid]
        ll_used = -0.5 * float(np.sum(r[used] ** 2)) - float(np.sum(np.log(sig))) - 0.5 * len(sig) * np.log(2 * np.pi)
        out["profile"] = {"loglik": prof[1], "loglik_used": ll_used,
                          "cost_dropped": 0.5 * float(np.sum(r[~used] ** 2)),
                          "converged": getattr(prof, "converged", None), "rounds": getattr(prof, "rounds", None),
                          "seconds": time.perf_counter() - t0}
    return out


def render(runs: dict, args) -> str:
    lines = [f"Window {args.start:g}-{args.start + args.duration:g} s of exp_3.", "",
             "| tree | call 1 log-lik | call 2 - call 1 | call 3 - call 2 | converged, rounds (call 1) | s (call 1) | "
             "refit log-lik (converged, dropped) | profile log-lik | profile over the refit's samples - refit | "
             "cost on dropped samples | profile converged, rounds | s (profile) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, r in runs.items():
        c, f, p = r["calls"], r["refit"], r["profile"]
        lines.append(f"| {label} | {c[0]['loglik']:.7g} | {c[1]['loglik'] - c[0]['loglik']:+.4g} | "
                     f"{c[2]['loglik'] - c[1]['loglik']:+.4g} | {c[0]['converged']}, {c[0]['rounds']} | "
                     f"{c[0]['seconds']:.1f} | {f['loglik']:.7g} ({f['converged']}, {f['dropped']}) | "
                     f"{p['loglik']:.7g} | {p['loglik_used'] - f['loglik']:+.4g} | {p['cost_dropped']:.4g} | "
                     f"{p['converged']}, {p['rounds']} | {p['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--tree", action="append", required=True, help="label=path of a source tree")
    ap.add_argument("--start", type=float, default=500.0)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:  # the child (run by the parent with the tree first on PYTHONPATH): json out
        print(json.dumps(measure(Path(args.work), args.start, args.duration), default=float))
        return 0
    runs = {}
    for spec in args.tree:
        label, path = spec.split("=", 1)
        path = str(Path(path).resolve())
        # the child: this script run by its path, in the tree, with the tree first on PYTHONPATH: the tree's
        # imu_array_ros (and its benchmarks.harness, which every tree measured here has); no sys.path edit
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([path, str(REPO)]))
        say(f"{label}: {path}")
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--work", args.work,
                               "--tree", spec, "--start", str(args.start), "--duration", str(args.duration),
                               "--one", path],
                              env=env, cwd=path, check=True, capture_output=True, text=True)
        runs[label] = json.loads(done.stdout.strip().splitlines()[-1])
    Path(f"{OUT}.json").write_text(json.dumps(runs, indent=1) + "\n")
    header = machine_header("fit_motion with timing terms on a real window, before and after its rounds",
                            extra=(f"load average at the end: {load_average()}",))
    write_results(Path(f"{OUT}.md"), header + render(runs, args))
    print(render(runs, args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
