"""Gyroscope biases tracked on the still intervals of the real MIMU4444BT captures (issue 22, item 4).

For every capture exp_1..exp_6 (config/mimu4444bt_corners.yaml, 62.5 Hz, 20 rests then twisting):

1. the bias measured on every still piece (:func:`imu_array_ros.calibration.bias_tracking.track_biases`,
   the numbers ``imu-array fuse`` and the fusion node use): how much the measurements wander within a
   capture (std over the pieces, per IMU the largest over the axes) against how much the captures' means
   differ (std over the six captures), and how much of the within-capture wander the orientation explains
   (a constant plus a gain on the piece's gravity direction per axis, i.e. a g-sensitivity: R^2);
2. the random-walk intensity of the Kalman update, chosen on ``--fit`` (default exp_1: the value whose
   normalised innovations have a mean square closest to 1) and scored on the others;
3. the NIS ratios still and moving, as ``imu-array residuals`` prints them, fused with and without tracking:
   with the nominal description (biases 0) on every capture, and with ``calibrate all`` of ``--fit`` (its
   biases measured in that session) on the other captures.

    python -m benchmarks.real_bias_tracking [--fit exp_1]

Writes benchmarks/results/real_bias_tracking.md (+ .json).
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import numpy as np  # noqa: E402

from imu_array_ros.calibration.bias_tracking import RANDOM_WALK, track_biases  # noqa: E402
from imu_array_ros.calibration.methods import whole_array  # noqa: E402
from imu_array_ros.fusion.residuals import normalized_residuals  # noqa: E402
from imu_array_ros.io.openshoe.capture import import_capture  # noqa: E402
from imu_array_ros.model.description import load_description  # noqa: E402
from imu_array_ros.model.sensor_model import SensorModel  # noqa: E402
from imu_array_ros.workflows.fusion import prepare_fusion  # noqa: E402

OUT = RESULTS / "real_bias_tracking.md"
CAPTURES = [f"exp_{i}" for i in range(1, 7)]
WALKS = [0.0, 1e-10, 1e-9, 1e-8, 1e-7, np.inf]


def nis(samples, desc, tracking: bool) -> tuple:
    """(still, moving) NIS ratios as ``imu-array residuals`` prints them, the number of bias updates, and the
    gyroscopes' (still, moving) ratios."""
    p = prepare_fusion(samples, desc, bias_tracking=tracking)
    fused, _ = p.fusion.fuse(p.samples)
    s = normalized_residuals(p.samples, p.fusion.model, fused).summary()
    return (s["still"]["ratio_all"], s["moving"]["ratio_all"], 0 if p.biases is None else len(p.biases.updates),
            s["still"]["ratio_gyroscopes"], s["moving"]["ratio_gyroscopes"])


def innovations(track, walk: float) -> float:
    """Mean square of the normalised innovations of every update after the first, had the filter run with
    random walk ``walk`` on the same measurements."""
    z, r = np.array([u.measured for u in track.updates]), np.array([u.measured_std for u in track.updates]) ** 2
    t = np.array([u.piece.mean_ns for u in track.updates]) * 1e-9
    b, var, out = z[0], r[0], []
    for i in range(1, len(z)):
        pred = var + (walk * (t[i] - t[i - 1]) if np.isfinite(walk) else 1e12)
        out.append((z[i] - b) ** 2 / (pred + r[i]))
        gain = pred / (pred + r[i])
        b, var = b + gain * (z[i] - b), (1 - gain) * pred
    return float(np.nanmean(out))


def gravity_fit(track) -> float:
    """Fraction of the within-capture variance of the measurements (all IMUs and axes) a constant plus a
    linear function of the piece's gravity direction explains (a g-sensitivity)."""
    z = np.array([u.measured for u in track.updates])  # (P, K, 3)
    g = np.array([u.piece.specific_force for u in track.updates])
    a = np.column_stack([np.ones(len(g)), g / np.linalg.norm(g, axis=1, keepdims=True)])
    y = z.reshape(len(z), -1)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    res = y - a @ coef
    return float(1.0 - np.sum(res ** 2) / np.sum((y - y.mean(axis=0)) ** 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", default="exp_1", help="capture the random walk is chosen on and calibrate all fits")
    args = ap.parse_args()
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    model = SensorModel.from_description(desc)
    samples = {}
    for name in CAPTURES:
        samples[name], _ = import_capture(DATA / f"{name}.bin", desc, start_ns=0)
    res: dict = {"fit": args.fit, "captures": {}}

    say("bias measurements per still piece")
    tracks = {n: track_biases(s, model) for n, s in samples.items()}
    means = {}
    for n, tr in tracks.items():
        z = np.array([u.measured for u in tr.updates])
        means[n] = z.mean(axis=0)
        res["captures"][n] = {
            "pieces": len(tr.updates), "still_s": sum(u.piece.seconds for u in tr.updates),
            "piece_std_median": float(np.median([u.measured_std for u in tr.updates])),
            "within_std": np.nanstd(z, axis=0, ddof=1).max(axis=1).tolist(),
            "within_range": np.ptp(z, axis=0).max(axis=1).tolist(),
            "gravity_r2": gravity_fit(tr),
            "mean_bias": means[n].tolist(),
            "innovation_ms": {repr(w): innovations(tr, w) for w in WALKS}}
    across = np.std(np.array(list(means.values())), axis=0, ddof=1).max(axis=1)
    res["across_std"] = across.tolist()
    fit_ms = res["captures"][args.fit]["innovation_ms"]
    chosen = min(WALKS, key=lambda w: abs(np.log(fit_ms[repr(w)])))
    res["walk_chosen"], res["walk_default"] = chosen, RANDOM_WALK

    say("NIS with the nominal description")
    res["nominal"] = {}
    for n, s in samples.items():
        t = time.time()
        off, on = nis(s, desc, False), nis(s, desc, True)
        res["nominal"][n] = {"off": off, "on": on}
        say(f"  {n}: still {off[0]:.3g} -> {on[0]:.3g}, moving {off[1]:.4g} -> {on[1]:.4g}; gyroscopes still "
            f"{off[3]:.3g} -> {on[3]:.3g}, moving {off[4]:.4g} -> {on[4]:.4g} ({time.time() - t:.0f} s)")

    say(f"calibrate all on {args.fit}")
    cal = whole_array(samples[args.fit], model, source=args.fit).apply(desc)
    res["calibrated"] = {}
    for n, s in samples.items():
        if n == args.fit:
            continue
        off, on = nis(s, cal, False), nis(s, cal, True)
        res["calibrated"][n] = {"off": off, "on": on}
        say(f"  {n}: still {off[0]:.3g} -> {on[0]:.3g}, moving {off[1]:.4g} -> {on[1]:.4g}; gyroscopes still "
            f"{off[3]:.3g} -> {on[3]:.3g}, moving {off[4]:.4g} -> {on[4]:.4g}")
    (RESULTS / "real_bias_tracking.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    write_results(OUT, report(res, desc.names))


def report(res: dict, names) -> str:
    caps = res["captures"]
    lines = [machine_header("Gyroscope biases tracked on the still intervals: real MIMU4444BT captures"),
             "Per capture: still pieces found (rests cut into pieces of at most 10 s), the median std of one piece's "
             "measurement, and per IMU (largest over the axes, rad/s) the std of the measurements over the pieces "
             "of the capture; the last rows: the std over the six captures of each capture's mean, and the "
             "fraction of the within-capture variance a g-sensitivity (constant + gain on the gravity "
             "direction) explains.\n",
             "| capture | pieces | still s | piece std | " + " | ".join(names) + " | g-fit R^2 |",
             "|---|---|---|---|" + "---|" * len(names) + "---|"]
    for n, c in caps.items():
        lines.append(f"| {n} | {c['pieces']} | {c['still_s']:.0f} | {c['piece_std_median']:.2g} | "
                     + " | ".join(f"{v:.2g}" for v in c["within_std"]) + f" | {c['gravity_r2']:.2f} |")
    lines.append("| across captures (std of the means) | | | | " + " | ".join(f"{v:.2g}" for v in res["across_std"])
                 + " | |")
    lines += ["", f"Random walk of the Kalman update: mean square of the normalised innovations (1 = the filter's "
              f"variances right) per intensity ((rad/s)^2/s); chosen on {res['fit']}: {res['walk_chosen']:g} "
              f"(the default RANDOM_WALK is {res['walk_default']:g}).\n",
              "| capture | " + " | ".join(f"{w:g}" for w in WALKS) + " |", "|---|" + "---|" * len(WALKS)]
    for n, c in caps.items():
        lines.append(f"| {n} | " + " | ".join(f"{c['innovation_ms'][repr(w)]:.3g}" for w in WALKS) + " |")
    for key, title in (("nominal", "the nominal description (biases 0)"),
                       ("calibrated", f"calibrate all of {res['fit']} (its session's biases)")):
        lines += ["", f"NIS ratio (`imu-array residuals`), fused with {title}, without -> with tracking:\n",
                  "| capture | still off | still on | moving off | moving on | gyro still off | gyro still on | "
                  "gyro moving off | gyro moving on | updates |", "|---|---|---|---|---|---|---|---|---|---|"]
        for n, v in res[key].items():
            lines.append(f"| {n} | {v['off'][0]:.3g} | {v['on'][0]:.3g} | {v['off'][1]:.4g} | {v['on'][1]:.4g} | "
                         f"{v['off'][3]:.3g} | {v['on'][3]:.3g} | {v['off'][4]:.4g} | {v['on'][4]:.4g} | {v['on'][2]} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
