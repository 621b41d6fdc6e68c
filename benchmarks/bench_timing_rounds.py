"""The trajectory rounds of fits with timing terms (fitting/rounds.py): the old loop (3 plain rounds) against the
loop to a stated criterion, and both against a many-round reference, same run.

Fits as discovery's confirming refits make them (``only``: each term on every IMU, max_iterations 30,
cost_tolerance 0.1, no sandwich),
under the model the discover timing stage leaves (the capture's sample clocks, reading rates when it keeps them):

* real: capture exp_3 (``--capture``), ``calibrate all`` of it, the timing stage on the whole capture, then the
  fits on every ``--every``-th 0.5-s block (discovery's subsample ladder's blocks);
* sim: the simulated twisting recordings of test/test_reading_rates.py (8 corner IMUs, sample clocks, 250
  samples at 62.5 Hz, reading rates), time offsets fitted from the truth, seeds 11-13.

Variants: ``old`` = the loop before (first optimisation uncapped, then at most 3 re-freezes, stopping when the
parameters moved < 0.01 std or a round gained < cost_tolerance; monkeypatched in here); ``new`` = the engine
as it is; ``anderson`` = the same with the held trajectory extrapolated from the last 3 near rounds (depth 3);
``reference`` = plain re-freezing (no extrapolation) until a Gauss-Newton step at the motion's own
trajectory moves no parameter by 0.005 std and gains < 0.001, at most 200 rounds, no step budget.  Distances are to the
reference: largest |theta - theta_ref| / std_ref over the parameters; loglik = what the fit reports; profile = the
log-likelihood of the fit's parameters with the motion re-fitted from the fit's (``fit_motion``, whose own
two trajectory rounds are not iterated to a fixed point: comparable only where it lands near the fit's value).

    python -m benchmarks.bench_timing_rounds [--capture exp_3] [--every 32] [--work DIR] [--skip-real]
"""

from __future__ import annotations

from benchmarks.harness import single_threaded_blas

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import pickle  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import imu_array_ros.fitting.engine as engine  # noqa: E402
import imu_array_ros.fitting.rounds as rounds  # noqa: E402
from benchmarks.harness import DATA, REPO, RESULTS, load_average, machine_header, say, write_results  # noqa: E402
from imu_array_ros.fitting.engine import fit_motion, fit_terms, keep_schur  # noqa: E402
from imu_array_ros.fitting.optimiser import inverse, levenberg_marquardt  # noqa: E402
from imu_array_ros.fitting.reading_rates import rates_scope, reading_rates  # noqa: E402

OUT = RESULTS / "timing_rounds.md"
JSON = RESULTS / "timing_rounds.json"
ARRAY = REPO / "config" / "mimu4444bt_corners.yaml"
CLI = "import sys; from imu_array_ros.cli import main; sys.exit(main())"
VARIANTS = ("old", "new", "anderson", "reference")
FITS = (("time_offset",), ("time_offset", "axis_offsets", "gyroscope_gain"))


def old_rounds(prob, model, motion, lin, gauge, max_iterations, tolerance, progress, cost_tolerance):
    """The loop of fit_terms before this change (TIMING_ROUNDS = 3), verbatim."""
    iterations, converged = 0, True
    for _ in range(3):
        theta = prob.values(model).reshape(-1)
        prob.freeze(motion)
        lin = None
        lin = prob.linearize(model, motion)
        start = lin.cost
        model, motion, lin, more, converged = levenberg_marquardt(prob, model, motion, lin, gauge, max_iterations,
                                                                  tolerance, progress, cost_tolerance)
        iterations += more
        if cost_tolerance is not None and start - lin.cost < cost_tolerance:
            break
        s_z, _ = gauge.reduce(lin.S, lin.g)
        std = np.sqrt(np.clip(np.diag(gauge.expand_covariance(inverse(s_z))), 0.0, None))
        moved = np.abs(prob.values(model).reshape(-1) - theta)
        if np.all(moved[std > 0] < tolerance * 10 * std[std > 0]):
            break
    return model, motion, lin, iterations, converged


class Variant:
    """Patch the engine's rounds for one fit (``old``, ``new``, ``reference``); ``log`` collects the new loop's
    per-round record."""

    def __init__(self, name: str):
        self.name, self.log, self.saved = name, rounds.RoundLog(), None

    def __enter__(self):
        self.saved = (engine.timing_rounds, engine.FAR_ITERATIONS, rounds.ROUND_STD, rounds.ROUND_GAIN, rounds.BUDGET)
        real, log = rounds.timing_rounds, self.log
        if self.name == "old":
            engine.timing_rounds, engine.FAR_ITERATIONS = old_rounds, 10 ** 9
        elif self.name == "anderson":
            engine.timing_rounds = lambda *a, **k: real(*a, **k, depth=3, log=log)
        elif self.name == "reference":
            rounds.ROUND_STD, rounds.ROUND_GAIN, rounds.BUDGET = 0.005, 0.001, 10 ** 6
            engine.timing_rounds = lambda *a, **k: real(*a, **k, depth=0, rounds=200, log=log)
        else:
            engine.timing_rounds = lambda *a, **k: real(*a, **k, log=log)
        return self

    def __exit__(self, *exc):
        (engine.timing_rounds, engine.FAR_ITERATIONS, rounds.ROUND_STD, rounds.ROUND_GAIN,
         rounds.BUDGET) = self.saved


def one_fit(samples, model, motion, terms, variant: str, rates: bool) -> dict:
    with Variant(variant) as v, reading_rates(rates):
        t0, c0 = time.perf_counter(), time.process_time()
        every = list(range(model.n_imus))  # as discovery's confirm refits a finding on every IMU
        fit = fit_terms(samples, model, list(terms), imus=every, only={t: every for t in terms}, motion0=motion,
                        max_iterations=30, sandwich=False, cost_tolerance=0.1)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        profile = fit_motion(samples, fit.model, np.where(np.isfinite(fit.motion), fit.motion, motion))[1]
    log = {k: [float(x) for x in val] for k, val in v.log.__dict__.items()}
    return {"variant": variant, "wall_s": wall, "cpu_s": cpu, "iterations": fit.iterations,
            "converged": bool(fit.converged), "rounds": len(log["cost"]) if variant != "old" else None,
            "loglik": fit.loglik_after, "profile_loglik": profile, "theta": fit.theta.tolist(),
            "std": np.sqrt(np.clip(np.diag(fit.covariance), 0, None)).tolist(), "log": log}


def compare(runs: list[dict]) -> None:
    """Distances of every run to its reference, in place."""
    ref = next(r for r in runs if r["variant"] == "reference")
    sd, th = np.array(ref["std"]), np.array(ref["theta"])
    ok = sd > 0
    for r in runs:
        r["dist_std"] = float(np.max(np.abs(np.array(r["theta"])[ok] - th[ok]) / sd[ok]))
        r["dloglik"] = r["loglik"] - ref["loglik"]
        r["dprofile"] = r["profile_loglik"] - ref["profile_loglik"]


def real_setup(capture: str, work: Path):
    """(subsample-able samples, model after the timing stage, its motion, reading rates kept), cached in work."""
    cache = work / f"{capture}_timing.pkl"
    from imu_array_ros import workflows
    from imu_array_ros.discovery.timing import timing_stage
    from imu_array_ros.fitting.reading_rates import rates_on
    from imu_array_ros.workflows.arrays import as_model

    mcap, cal = work / f"{capture}.mcap", work / f"{capture}_cal.yaml"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    if not mcap.exists():
        say(f"import-openshoe {capture}")
        subprocess.run([sys.executable, "-c", CLI, "import-openshoe", str(DATA / f"{capture}.bin"), "--array",
                        str(ARRAY), "--out", str(mcap)], check=True, cwd=REPO, env=env)
    if not cal.exists():
        say("calibrate all")
        subprocess.run([sys.executable, "-c", CLI, "calibrate", "all", str(mcap), "--array", str(ARRAY), "--out",
                        str(cal), "-q"], check=True, cwd=REPO, env=env)
    desc, _ = workflows.load_array(ARRAY, cal)
    samples, _ = workflows.read_imu_recording(mcap, desc)
    if cache.exists():
        model, motion, rates, seconds = pickle.loads(cache.read_bytes())
        return samples, model, motion, rates, seconds
    say("timing stage (sample clocks, reading rates) on the whole capture")
    t0 = time.perf_counter()
    with rates_scope():
        model = as_model(desc)
        motion, ll, r = fit_motion(samples, model)
        out = timing_stage(samples, model, motion=motion, loglik=ll, residuals=r, say=say)
        motion = out.motion if out.motion is not None else fit_motion(samples, out.model, motion)[0]
        rates = rates_on()
    seconds = time.perf_counter() - t0
    cache.write_bytes(pickle.dumps((out.model, motion, rates, seconds)))
    return samples, out.model, motion, rates, seconds


@keep_schur()
def run_real(args, work: Path) -> list[dict]:
    from imu_array_ros.discovery.blocks import time_blocks

    samples, model, motion, rates, seconds = real_setup(args.capture, work)
    sel = np.flatnonzero(time_blocks(samples.stamps, 0.5) % args.every == 0)
    sub = samples.select(sel)
    with reading_rates(rates):
        msub = fit_motion(sub, model, motion[sel])[0]
    out = []
    for terms in FITS:
        runs = []
        for variant in VARIANTS:
            say(f"real {args.capture} x{args.every}: {'+'.join(terms)} {variant}")
            runs.append(one_fit(sub, model, msub, terms, variant, rates))
            say(f"  {runs[-1]['wall_s']:.1f} s, {runs[-1]['iterations']} iterations, converged {runs[-1]['converged']}")
        compare(runs)
        out.append({"case": f"real {args.capture}, every {args.every}th 0.5-s block ({len(sub)} samples)",
                    "terms": list(terms), "rates": bool(rates), "timing_stage_s": seconds, "runs": runs})
    return out


@keep_schur()
def run_sim() -> list[dict]:
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.simulation.clocks import mimu_like_clocks
    from imu_array_ros.simulation.motion import TwistTrajectory
    from imu_array_ros.simulation.simulator import simulate_trajectory

    corners = SensorModel.from_description(load_description(ARRAY))
    stamps = (np.arange(250) * 16_000_000).astype(np.int64)
    a = np.array([[8.0, 1.4], [6.0, 1.2], [7.0, 1.3]])  # test/test_reading_rates.py's twist(rng, fast=1)
    f = np.array([[1.1, 34.0], [1.7, 38.0], [0.9, 41.0]])
    sa = np.array([[2.0, 8.0], [2.0, 7.0], [2.0, 9.0]])
    sf = np.array([[0.7, 36.0], [1.2, 43.0], [0.5, 39.0]])
    out = []
    for seed in (11, 12, 13):
        rng = np.random.default_rng(seed)
        clocked = mimu_like_clocks(corners, rng, acc_lag=0.8e-3, gyro_lag=2.9e-3)
        twist = TwistTrajectory(a, f, rng.uniform(0, 2 * np.pi, (3, 2)), sa, sf, rng.uniform(0, 2 * np.pi, (3, 2)),
                                np.array([1.0, 0.0, 0.0, 0.0]))
        samples = simulate_trajectory(clocked, twist, stamps, rng)[0]
        with reading_rates(True):
            motion = fit_motion(samples, clocked)[0]
        runs = [one_fit(samples, clocked, motion, ("time_offset",), v, True) for v in VARIANTS]
        compare(runs)
        out.append({"case": f"sim seed {seed} (250 samples)", "terms": ["time_offset"], "rates": True, "runs": runs})
        say(f"sim seed {seed} done")
    return out


def table(cases: list[dict]) -> str:
    text = ("| case | terms | variant | wall | iterations | rounds | converged | reported loglik - ref | "
            "profile loglik - ref | max abs(theta - ref) / std |\n|---|---|---|---|---|---|---|---|---|---|\n")
    for c in cases:
        for r in c["runs"]:
            text += (f"| {c['case']} | {'+'.join(c['terms'])} | {r['variant']} | {r['wall_s']:.1f} s | "
                     f"{r['iterations']} | {'-' if r['rounds'] is None else r['rounds']} | {r['converged']} | "
                     f"{r['dloglik']:+.2f} | {r['dprofile']:+.2f} | {r['dist_std']:.3f} |\n")
    return text


def rounds_table(cases: list[dict]) -> str:
    text = ""
    for c in cases:
        for r in c["runs"]:
            if r["variant"] == "old":
                continue
            lg = r["log"]
            text += (f"\n**{c['case']}, {'+'.join(c['terms'])}, {r['variant']}** (per round: cost rise on re-freeze, "
                     "then the self-consistent Gauss-Newton step: largest parameter step / std, predicted gain; "
                     "iterations of the round's optimisation; x: extrapolated)\n\n")
            text += "| round | rise | step / std | gain | iterations |\n|---|---|---|---|---|\n"
            for i, (rise, st, g) in enumerate(zip(lg["rise"], lg["step_std"], lg["gain"])):
                it = f"{lg['iterations'][i]:.0f}{' x' if lg['extrapolated'][i] else ''}" if i < len(lg["iterations"]) \
                    else "(stop)"
                text += f"| {i} | {rise:.4g} | {st:.3g} | {g:.3g} | {it} |\n"
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default="exp_3")
    ap.add_argument("--every", type=int, default=32, help="fit every k-th 0.5-s block of the capture")
    ap.add_argument("--work", help="work directory (kept: the imported capture, calibration, timing stage)")
    ap.add_argument("--skip-real", action="store_true")
    args = ap.parse_args()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="bench_timing_rounds_"))
    work.mkdir(parents=True, exist_ok=True)
    cases = run_sim()
    if not args.skip_real:
        cases += run_real(args, work)
    JSON.write_text(json.dumps({"cases": cases, "load_average": load_average()}, indent=1) + "\n")
    text = machine_header("Trajectory rounds of fits with timing terms: old loop, new loop, many-round reference",
                          extra=[f"load average at the end: {load_average()}"])
    text += __doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0] + "\n\n"
    setup = [c.get("timing_stage_s") for c in cases if c.get("timing_stage_s")]
    if setup:
        text += f"Timing stage on the whole capture (setup, once): {setup[0]:.0f} s.\n\n"
    text += "## Results\n\n" + table(cases) + "\n## Rounds\n" + rounds_table(cases)
    write_results(OUT, text)
    print(table(cases))
    return 0


if __name__ == "__main__":
    sys.exit(main())
