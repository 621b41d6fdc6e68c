"""Calibration a user can trust, on the real MIMU4444BT captures (issue 22's real-data targets).

``calibrate all`` (defaults: static stage, moving stage with positions and the gyroscopes' full 3x3; written
``_std`` the misfit-robust sandwich std of the moving stage) on each of the six captures separately, then:

1. **Repeatability**: per field, the spread across the six captures (std over the captures) divided by the
   median reported std; device constants (target: median 0.5-2, none above 4) and session states (biases:
   their spread is the turn-on repeatability, reported separately) apart.  Also ``calibrate all`` on three
   captures together (device constants combined, biases written with their turn-on repeatability), and whether
   that written bias std covers the biases of the three captures it did not see.
2. **Held-out NIS**: the description calibrated on capture i, scored on every other capture j (``imu-array
   residuals``: the NIS against the description's white-noise figures, gyroscope biases tracked on the still
   intervals as ``fuse`` does); median over the 30 pairs, still and moving (targets: still <= 1.3, moving <=
   2,000 without timing terms).

    python -m benchmarks.real_calibration_trust [--workers 2]
    python -m benchmarks.real_calibration_trust --timing [--workers 2]

Writes benchmarks/results/real_calibration_trust.md and .json.  ``--timing``: ``calibrate all --timing`` on each
capture (sample clocks, time offsets refitted with the moving terms) and item 1's repeatability only (the
held-out NIS of such calibrations: benchmarks/real_timing_heldout.py), to real_calibration_trust_timing.md/.json.
"""

from __future__ import annotations

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

TITLE = "Calibration a user can trust: the real captures (issue 22)"
CORNERS = REPO / "config" / "mimu4444bt_corners.yaml"
OUT = RESULTS / "real_calibration_trust"
SESSION = ("accelerometer_bias", "gyroscope_bias")


def load(path):
    from imu_array_ros.model.description import load_description
    from imu_array_ros.workflows import import_openshoe

    desc = load_description(CORNERS)
    samples, _ = import_openshoe(path, desc)
    return desc, samples


def calibrate_job(path: str, timing: bool = False) -> dict:
    from imu_array_ros.workflows import calibrate

    desc, samples = load(path)
    t0 = time.perf_counter()
    cal = calibrate("all", samples, desc, source=path, timing=timing)
    seconds = time.perf_counter() - t0
    d = cal.details
    crb = {t: d.moving.std[t].tolist() for t in d.moving.free} if d.moving is not None else {}
    return {"path": path, "seconds": seconds, "summary": cal.summary(),
            "values": {t: cal.model.terms[t].values.tolist() for t in cal.std},
            "std": {t: np.asarray(s).tolist() for t, s in cal.std.items()}, "crb": crb,
            "description": cal.apply(desc)}


def residual_job(args) -> dict:
    from imu_array_ros.workflows import residuals

    i, j, cal_desc = args
    _, samples = load(str(sorted(DATA.glob("exp_*.bin"))[j]))
    out = {}
    for label, d in (("calibrated", cal_desc),) if cal_desc is not None else (("nominal", None),):
        if d is None:
            from imu_array_ros.model.description import load_description
            d = load_description(CORNERS)
        s = residuals(samples, d)["recording"].summary()
        out[label] = {"still": s["still"]["ratio_all"], "moving": s["moving"]["ratio_all"],
                      "still_gyro": s["still"]["ratio_gyroscopes"], "still_acc": s["still"]["ratio_accelerometers"],
                      "moving_gyro": s["moving"]["ratio_gyroscopes"], "moving_acc": s["moving"]["ratio_accelerometers"]}
    return {"fit": i, "score": j, **out}


def combined_job(paths: list[str]) -> dict:
    from imu_array_ros.workflows import calibrate

    loaded = [load(p) for p in paths]
    cal = calibrate("all", [s for _, s in loaded], loaded[0][0], source=paths)
    return {"paths": paths, "summary": cal.summary(), "terms": cal.record["terms"],
            "values": {t: cal.model.terms[t].values.tolist() for t in cal.std},
            "std": {t: np.asarray(s).tolist() for t, s in cal.std.items()}}


def repeatability(cals: list[dict]) -> dict:
    """term -> median over parameters of spread across captures / median reported std (and CRB)."""
    out = {}
    for t in cals[0]["std"]:
        v = np.array([c["values"][t] for c in cals], dtype=float)
        s = np.array([c["std"][t] for c in cals], dtype=float)
        spread = np.std(v, axis=0, ddof=1)
        med = np.array([np.nanmedian(c) if np.isfinite(c).any() else np.nan for c in np.where(s > 0, s, np.nan).reshape(len(s), -1).T]).reshape(s.shape[1:])
        ok = np.isfinite(med) & (med > 0)
        ratio = spread[ok] / med[ok]
        row = {"kind": "session state" if t in SESSION else "device constant", "parameters": int(ok.sum()),
               "median_ratio": float(np.median(ratio)) if ok.any() else None,
               "max_ratio": float(np.max(ratio)) if ok.any() else None,
               "p90_ratio": float(np.percentile(ratio, 90)) if ok.any() else None,
               "median_spread": float(np.median(spread[ok])) if ok.any() else None,
               "median_std": float(np.median(med[ok])) if ok.any() else None}
        if t in cals[0]["crb"]:
            c = np.array([x["crb"][t] for x in cals], dtype=float)
            cm = np.nanmedian(np.where(c > 0, c, np.nan), axis=0)
            okc = np.isfinite(cm) & (cm > 0)
            row["median_ratio_crb"] = float(np.median(spread[okc] / cm[okc])) if okc.any() else None
        out[t] = row
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--timing", action="store_true", help="calibrate all --timing; repeatability only")
    args = ap.parse_args(argv)
    paths = [str(p) for p in sorted(DATA.glob("exp_*.bin"))]
    header = machine_header(TITLE)
    t0 = time.perf_counter()
    ctx = multiprocessing.get_context("fork")
    if args.timing:
        return timing_main(paths, header, t0, ctx, args.workers)
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=ctx) as pool:
        cals = list(pool.map(calibrate_job, paths))
        say("calibrated: " + ", ".join(f"{c['seconds']:.0f} s" for c in cals))
        jobs = [(i, j, cals[i]["description"]) for i in range(len(paths)) for j in range(len(paths)) if i != j]
        jobs += [(j, j, None) for j in range(len(paths))]  # the nominal description on each capture
        held = list(pool.map(residual_job, jobs))
        combined = pool.submit(combined_job, paths[:3]).result()
    say(f"done in {time.perf_counter() - t0:.0f} s")
    rep = repeatability(cals)
    # the combined calibration's written bias std (turn-on repeatability of exp_1-3) against exp_4-6's biases
    cover = {}
    for t in SESSION:
        if t not in combined["std"]:
            continue
        mean, std = np.array(combined["values"][t]), np.array(combined["std"][t])
        z = np.array([(np.array(c["values"][t]) - mean) / std for c in cals[3:]])
        cover[t] = {"rms_z": float(np.sqrt(np.mean(z ** 2))), "max_abs_z": float(np.max(np.abs(z))),
                    "within_2": float(np.mean(np.abs(z) < 2))}
    res = {"cals": [{k: v for k, v in c.items() if k != "description"} for c in cals], "held_out": held,
           "repeatability": rep, "combined": combined, "bias_cover": cover,
           "seconds": time.perf_counter() - t0}
    OUT.with_suffix(".json").write_text(json.dumps(res, indent=1, default=str) + "\n")
    write_results(OUT.with_suffix(".md"), header + markdown(res))
    return 0


def timing_main(paths, header, t0, ctx, workers) -> int:
    """``--timing``: the six captures' ``calibrate all --timing`` and their repeatability."""
    from functools import partial

    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        cals = list(pool.map(partial(calibrate_job, timing=True), paths))
    say("calibrated: " + ", ".join(f"{c['seconds']:.0f} s" for c in cals))
    res = {"cals": [{k: v for k, v in c.items() if k != "description"} for c in cals],
           "repeatability": repeatability(cals), "seconds": time.perf_counter() - t0}
    out = OUT.with_name(OUT.name + "_timing")
    out.with_suffix(".json").write_text(json.dumps(res, indent=1, default=str) + "\n")
    lines = ["", "## Interpretation", "", "(interpretation not yet written)", "",
             "## Repeatability of `calibrate all --timing` on each capture separately", "",
             "Spread across the six captures (std) / median reported `_std` (`/ CRB`: the same spread over the "
             "Cramer-Rao bound).", "", "| term | kind | parameters | median spread/std | 90th pct | max | "
             "median spread/CRB |", "|---|---|---|---|---|---|---|"]
    for t, r in res["repeatability"].items():
        f = lambda x: "-" if x is None else f"{x:.3g}"  # noqa: E731
        lines.append(f"| {t} | {r['kind']} | {r['parameters']} | {f(r['median_ratio'])} | {f(r['p90_ratio'])} | "
                     f"{f(r['max_ratio'])} | {f(r.get('median_ratio_crb'))} |")
    lines += ["", "Per capture: " + "; ".join(f"{Path(c['path']).name} {c['seconds']:.0f} s" for c in cals), ""]
    lines += [f"- {Path(c['path']).name}: {c['summary']}" for c in cals]
    write_results(out.with_suffix(".md"), header + "\n".join(lines) + "\n")
    return 0


def markdown(res: dict) -> str:
    f = lambda x, p="{:.3g}": "-" if x is None else p.format(x)  # noqa: E731
    text = "\n## 1. Repeatability of `calibrate all` on each capture separately\n\n"
    text += ("Spread across the six captures (std) / median reported `_std` (moving stage: the sandwich std; "
             "`/ CRB`: the same spread over the Cramer-Rao bound).\n\n"
             "| term | kind | parameters | median spread/std | 90th pct | max | median spread/CRB |\n|---|---|---|---|---|---|---|\n")
    for t, r in res["repeatability"].items():
        text += (f"| {t} | {r['kind']} | {r['parameters']} | {f(r['median_ratio'])} | {f(r['p90_ratio'])} | "
                 f"{f(r['max_ratio'])} | {f(r.get('median_ratio_crb'))} |\n")
    text += "\nPer capture: " + "; ".join(f"{c['path'].rsplit('/', 1)[-1]} {c['seconds']:.0f} s" for c in res["cals"])
    text += "\n\n## 2. Session states: three captures together\n\n"
    text += f"`calibrate all exp_1 exp_2 exp_3`: {res['combined']['summary']}\n\n"
    text += "| term | kind | median within-recording std | median spread over recordings | spread / within |\n|---|---|---|---|---|\n"
    for t, r in res["combined"]["terms"].items():
        text += (f"| {t} | {r['kind']} | {f(r['median_within_std'])} | {f(r['median_spread_over_recordings'])} | "
                 f"{f(r['median_spread_over_within_std'])} |\n")
    text += "\nThe written bias std (turn-on repeatability of exp_1-3) against the biases exp_4-6 gave: "
    text += "; ".join(f"{t}: RMS z {v['rms_z']:.2f}, max |z| {v['max_abs_z']:.2f}, {100 * v['within_2']:.0f} % "
                      "within 2" for t, v in res["bias_cover"].items()) + "\n"
    text += "\n## 3. Held-out NIS (fit on capture i, scored on capture j != i; gyroscope biases tracked)\n\n"
    held = [h for h in res["held_out"] if "calibrated" in h]
    nominal = {h["score"]: h["nominal"] for h in res["held_out"] if "nominal" in h}
    text += "| scored on | nominal still | nominal moving | calibrated still: median (range) | moving: median (range) |\n|---|---|---|---|---|\n"
    for j in sorted({h["score"] for h in held}):
        rows = [h["calibrated"] for h in held if h["score"] == j]
        st, mv = [r["still"] for r in rows], [r["moving"] for r in rows]
        text += (f"| exp_{j + 1} | {f(nominal[j]['still'])} | {f(nominal[j]['moving'])} | {f(np.median(st))} "
                 f"({f(min(st))}-{f(max(st))}) | {f(np.median(mv))} ({f(min(mv))}-{f(max(mv))}) |\n")
    st = [h["calibrated"]["still"] for h in held]
    mv = [h["calibrated"]["moving"] for h in held]
    text += (f"\nOver all {len(held)} pairs: still median {np.median(st):.3g}, moving median {np.median(mv):.4g} "
             f"(gyroscopes {np.median([h['calibrated']['moving_gyro'] for h in held]):.4g}, accelerometers "
             f"{np.median([h['calibrated']['moving_acc'] for h in held]):.4g}).\n")
    text += f"\nTotal {res['seconds']:.0f} s.\n"
    return text


if __name__ == "__main__":
    raise SystemExit(main())
