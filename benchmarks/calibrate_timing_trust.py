"""Do the timing stage's reported time-offset std match how the offsets repeat?  (calibrate all --timing)

Monte Carlo over seeds of the session of test/test_calibrate_array_timing.py (tetrahedron4, icosahedron session
at 62.5 Hz: 20 still poses of 1 s, 0.3 s transitions, 1.2 s of twisting; gyroscopes of imu_01 3 ms late and imu_03
2 ms early): per seed ``calibrate_array(..., timing=True, clock_period=None)`` and, for every fitted time offset
(the reference gyroscope's is held: the gauge of time; all others, the accelerometers' included, are relative to
it and identifiable), z = (estimate - truth) / std for

* ``written``: what ``ArrayCalibration.stds()`` writes, on the session simulated at the true sample times
  (``simulate_icosahedron(exact_timing=True)``, the default since 2026-11-28);
* ``written_cubic``: the same on the session as simulated before (``exact_timing=False``: the delayed readings
  through local cubics of the truth at the stamps, which smooth the 0.3 s transitions at 62.5 Hz);
* ``schur``: the exact session's errors over the marginal std of the offsets in a joint linearisation of the
  moving and timing terms at the written point (``fit_terms`` with ``max_iterations=0``: the inverse of the Schur
  complement of the offsets' block, sandwich) -- the held terms' uncertainty propagated;
* ``truth_held``: the timing fit on the same window with the TRUE positions and gyroscope terms held (what no
  propagation of the held terms' uncertainty can do better than);
* which held term carries the gyroscopes' delays: the timing fit with only the TRUE ``gyroscope_gain``
  (``true_gain_held``) or only the TRUE positions (``true_position_held``) put in, the other moving-stage terms
  as written;
* candidate estimators: ``gain_joint``: the time offsets fitted jointly with the gyroscope gains (the reference
  IMU's gain held, positions, misalignment and non-orthogonality as written), its own std -- and the written
  gains' z against the fitted gains' (``gain z``); ``bcd``: one more round of block coordinate descent (the
  moving terms refitted on the same window with the written time offsets in the model, then the offsets again).

Usage: python -m benchmarks.calibrate_timing_trust --seeds 100-115 [--out benchmarks/results/NAME]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from datetime import datetime, timezone

import numpy as np

from benchmarks.harness import command, commit
from imu_array_ros.calibration.array import MOVING_TERMS, calibrate_array
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.model.layouts import tetrahedron4
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.icosahedron import simulate_icosahedron
from imu_array_ros.util.files import atomic_write_text

STILL = dict(window_s=0.3, min_duration_s=0.3, settle_s=0.1)


def truth_offsets(n_imus: int) -> np.ndarray:
    to = np.zeros((n_imus, 2))
    to[1, 1], to[3, 1] = 3e-3, -2e-3
    return to


KINDS = ("written", "written_cubic", "schur", "truth_held", "true_gain_held", "true_position_held", "gain_joint", "bcd")
REFERENCE = "imu_00 gyroscope.time_offset"  # the gauge of time the timing stage holds


def calibrate(seed: int, exact: bool):
    nominal = SensorModel.from_description(tetrahedron4())
    to = truth_offsets(nominal.n_imus)
    samples, _, _ = simulate_icosahedron(nominal.with_terms(time_offset=to), np.random.default_rng(seed),
                                         rate_hz=62.5, still_s=1.0, transition_s=0.3, twist_s=1.2,
                                         exact_timing=exact)
    t0 = time.perf_counter()
    cal = calibrate_array(samples, nominal, timing=True, clock_period=None, still_options=STILL)
    return nominal, to, samples, cal, time.perf_counter() - t0


def one_seed(seed: int) -> dict:
    row = {"seed": seed}
    z = {}
    nominal, to, samples, cal, seconds = calibrate(seed, False)
    if cal.timing is None:
        return {"seed": seed, "skipped": cal.skipped}
    std = cal.stds()["time_offset"]
    fitted = np.isfinite(std) & (std > 0)
    z["written_cubic"] = (cal.model.terms["time_offset"].values - to)[fitted] / std[fitted]
    nominal, to, samples, cal, seconds = calibrate(seed, True)
    if cal.timing is None:
        return {"seed": seed, "skipped": cal.skipped}
    est, std = cal.model.terms["time_offset"].values, cal.stds()["time_offset"]
    err = (est - to)[fitted]
    z["written"] = err / std[fitted]
    t0 = int(samples.stamps[0])
    joint = fit_terms(cal.moving_window, cal.model, MOVING_TERMS + ("time_offset",), max_iterations=0, t0_ns=t0,
                      hold=[REFERENCE] + list(cal.moving.held), motion0=np.nan_to_num(cal.timing.motion))
    z["schur"] = err / joint.std_robust["time_offset"][fitted]
    true_held = cal.model.with_terms(**{t: nominal.terms[t].values for t in MOVING_TERMS},
                                     time_offset=np.zeros_like(to))
    fit = fit_terms(cal.moving_window, true_held, ("time_offset",), hold=[REFERENCE], t0_ns=t0)
    z["truth_held"] = (fit.model.terms["time_offset"].values - to)[fitted] / fit.std_robust["time_offset"][fitted]
    z.update(diagnose(cal, nominal, to, t0, fitted, row))
    row.update({"seconds": seconds, "names": [f"{cal.model.names[k]} {('accelerometer', 'gyroscope')[s]}"
                                              for k, s in zip(*np.nonzero(fitted))],
                "error_us": (err * 1e6).tolist(), "written_std_us": (std[fitted] * 1e6).tolist(),
                "truth_held_error_us": ((fit.model.terms["time_offset"].values - to)[fitted] * 1e6).tolist()})
    row.update({f"z_{k}": v.tolist() for k, v in z.items()})
    return row


def diagnose(cal, nominal, to, t0, fitted, row) -> dict:
    """The z of the time offsets for the diagnostic kinds (module docstring); the gains' z into ``row``."""
    z = {}
    zero = np.zeros_like(to)

    def offsets_z(fit):
        return (fit.model.terms["time_offset"].values - to)[fitted] / fit.std_robust["time_offset"][fitted]

    for kind, term in (("true_gain_held", "gyroscope_gain"), ("true_position_held", "position")):
        model = cal.model.with_terms(**{term: nominal.terms[term].values}, time_offset=zero)
        z[kind] = offsets_z(fit_terms(cal.moving_window, model, ("time_offset",), hold=[REFERENCE], t0_ns=t0))
    gauge = [h for h in cal.moving.held if "gyroscope" in h]  # the reference IMU's gain
    fit = fit_terms(cal.moving_window, cal.model.with_terms(time_offset=zero), ("gyroscope_gain", "time_offset"),
                    hold=[REFERENCE] + gauge, t0_ns=t0)
    z["gain_joint"] = offsets_z(fit)
    true_gain = nominal.terms["gyroscope_gain"].values
    written_std = cal.stds()["gyroscope_gain"]
    free = np.isfinite(written_std) & (written_std > 0)
    row["gain_z_written"] = ((cal.model.terms["gyroscope_gain"].values - true_gain)[free] / written_std[free]).tolist()
    row["gain_z_gain_joint"] = ((fit.model.terms["gyroscope_gain"].values - true_gain)[free]
                                / fit.std_robust["gyroscope_gain"][free]).tolist()
    moving = fit_terms(cal.moving_window, cal.model, MOVING_TERMS, hold=list(cal.moving.held), t0_ns=t0)
    z["bcd"] = offsets_z(fit_terms(cal.moving_window, moving.model.with_terms(time_offset=zero), ("time_offset",),
                                   hold=[REFERENCE], t0_ns=t0))
    return z


def spread(z: np.ndarray) -> dict:
    return {"n": int(z.size), "std": float(np.std(z)), "rms": float(np.sqrt(np.mean(z ** 2))),
            "mean": float(np.mean(z)), "frac_abs_gt_3": float(np.mean(np.abs(z) > 3)),
            "max_abs": float(np.max(np.abs(z)))}


def parse_seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="100-115")
    ap.add_argument("--out", default=None, help="write OUT.json and OUT.md")
    args = ap.parse_args(argv)
    rows = []
    for seed in parse_seeds(args.seeds):
        row = one_seed(seed)
        rows.append(row)
        if "skipped" in row:
            print(f"seed {seed}: timing skipped: {row['skipped']}", flush=True)
            continue
        print(f"seed {seed} ({row['seconds']:.1f} s): " + "; ".join(f"z {k} {np.round(row['z_' + k], 2).tolist()}"
                                                                  for k in KINDS), flush=True)
    done = [r for r in rows if "skipped" not in r]
    names = done[0]["names"]
    summary = {}
    for kind in KINDS:
        z = np.array([r[f"z_{kind}"] for r in done])
        summary[kind] = {"all": spread(z.reshape(-1)), "per_parameter": {n: spread(z[:, i]) for i, n in
                                                                         enumerate(names)}}
    summary["gain_z"] = {k: spread(np.array([r[f"gain_z_{k}"] for r in done]).reshape(-1))
                         for k in ("written", "gain_joint")}
    err = np.array([r["error_us"] for r in done])
    summary["error_rms_us"] = dict(zip(names, np.sqrt(np.mean(err ** 2, axis=0)).tolist()))
    summary["written_std_median_us"] = dict(zip(names, np.median([r["written_std_us"] for r in done],
                                                                 axis=0).tolist()))
    summary["truth_held_error_mean_us"] = dict(zip(names, np.mean([r["truth_held_error_us"] for r in done],
                                                                  axis=0).tolist()))
    meta = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": platform.node(),
            "cpu": platform.processor() or platform.machine(), "python": platform.python_version(),
            "commit": commit(), "seeds": args.seeds, "timed": len(done), "total": len(rows)}
    result = {"meta": meta, "summary": summary, "rows": rows}
    for kind in KINDS:
        s = summary[kind]["all"]
        print(f"{kind}: z std {s['std']:.2f}, rms {s['rms']:.2f}, |z|>3 {s['frac_abs_gt_3']:.1%}, "
              f"max {s['max_abs']:.1f} (n={s['n']})")
    if args.out:
        atomic_write_text(args.out + ".json", json.dumps(result, indent=1))
        atomic_write_text(args.out + ".md", report(result, command(None if argv is None else
                                                                  ["benchmarks/calibrate_timing_trust.py", *argv])))
    return result


def report(result: dict, command: str) -> str:
    """The z table of every kind (all offsets, and per parameter: mean and std of z) as Markdown."""
    meta, summary = result["meta"], result["summary"]
    lines = [f"# calibrate all --timing: do the written time-offset std match how the offsets repeat?", "",
             f"{meta['date']}, {meta['machine']} ({meta['cpu']}, Python {meta['python']}), commit {meta['commit']}; "
             f"seeds {meta['seeds']} ({meta['timed']} of {meta['total']} timed); `{command}`", "",
             "z = (estimate - truth) / std over the 7 fitted offsets per seed (the reference gyroscope's is held: "
             "the gauge of time).  Expected for honest std: rms 1, |z| > 3 in 0.3 %.", "",
             "| kind | n | rms z | mean z | std z | abs(z) > 3 | max abs(z) |", "|---|---|---|---|---|---|---|"]
    for kind in KINDS:
        a = summary[kind]["all"]
        lines.append(f"| {kind} | {a['n']} | {a['rms']:.2f} | {a['mean']:.2f} | {a['std']:.2f} | "
                     f"{a['frac_abs_gt_3']:.1%} | {a['max_abs']:.1f} |")
    names = list(summary["written"]["per_parameter"])
    lines += ["", "Per parameter, mean z / std z:", "",
              "| parameter | " + " | ".join(KINDS) + " | written std median, us | truth-held error mean, us |",
              "|---" * (len(KINDS) + 3) + "|"]
    for n in names:
        cells = [f"{summary[k]['per_parameter'][n]['mean']:.2f} / {summary[k]['per_parameter'][n]['std']:.2f}"
                 for k in KINDS]
        lines.append(f"| {n} | " + " | ".join(cells) + f" | {summary['written_std_median_us'][n]:.1f} | "
                     f"{summary['truth_held_error_mean_us'][n]:.1f} |")
    lines += ["", "The gyroscope gains' z (true gain 1; the reference IMU's held), written (the moving stage's) and "
              "fitted jointly with the time offsets (`gain_joint`):", "",
              "| gains | n | rms z | mean z | abs(z) > 3 | max abs(z) |", "|---|---|---|---|---|---|"]
    for kind, a in summary["gain_z"].items():
        lines.append(f"| {kind} | {a['n']} | {a['rms']:.2f} | {a['mean']:.2f} | {a['frac_abs_gt_3']:.1%} | "
                     f"{a['max_abs']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
