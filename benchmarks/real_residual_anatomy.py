"""What the model still misses on the real captures while the array moves: the anatomy of the moving residual
left after ``calibrate all`` + discovery's findings (issue 23's level target, held-out moving NIS <= 1,500).

For one ``--fit`` capture of ../shared/data/openshoe_mimu4444bt/: ``calibrate all`` of the whole capture, then
discovery (defaults) on its moving phase (as :mod:`benchmarks.real_discovery_heldout`), its findings installed
as ``discover --apply`` would.  Then, on every other capture's moving phase, the maximum-likelihood motion under
that model (:func:`~imu_array_ros.fitting.engine.fit_motion`, each recording's sample-clock phases estimated on
it) and its normalised residuals, asked six questions that each have a stated answer under the model:

1. **whiteness**: the residuals' spectrum by band (Welch, averaged over readings) and lag-1 autocorrelation --
   a slowly varying missing term would sit in the low bands;
2. **tails**: the share of the residual sum of squares carried by the worst 1 % of samples (1 % under
   Gaussian readings with equal variance is ~0.06);
3. **sample instants**: for every pair of IMUs, the mean squared difference of their residuals (array frame,
   samples with |omega_dot| > 400 rad/s^2) against the difference of their gyroscope chips' modelled reading
   ages -- flat if every reading is predicted at its true instant;
4. **the gyroscopes' and accelerometers' own rates**: the share of the residual sum of squares a free 3-vector per sample, acting on
   the gyroscopes only as (age - the sample's mean age) times it (their angular acceleration at their own
   instants, decoupled from the omega_dot the accelerometers see), removes when fitted with the 9 motion
   states; the same for the accelerometers on the same chip clock, and both together; chance (white
   residuals): the added states / (valid readings - 9) per sample; and a placebo: both with every reading's
   age drawn at random;
5. **a per-sample angular jerk**: the same for a free omega_ddot acting on both sensors at their delays (gyroscope
   delta^2/2, accelerometer delta times the lever-arm field's omega_dot column);
6. **sawtooth amplitude**: per IMU, the gyroscope residual regressed on omega_dot (b0, s) and omega_dot times
   (age - 0.5 ms) (b1, dimensionless: 0 when the modelled sawtooth has the true amplitude).

Nothing here changes the model: it says where the remaining residual lives.  Writes
benchmarks/results/real_residual_anatomy.md (+ .json).

    python -m benchmarks.real_residual_anatomy [--fit exp_6] [--score exp_1 ...]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from benchmarks.harness import DATA, RESULTS, load_average, machine_header, say, single_threaded_blas, write_results
from benchmarks.real_discovery_heldout import ARRAY, CAPTURES, moving_phase
from imu_array_ros.fitting.reading_rates import age_columns

OUT = RESULTS / "real_residual_anatomy"
BANDS = ((0, 1), (1, 3), (3, 6), (6, 10), (10, 15), (15, 20), (20, 25), (25, 32))
AGE_EDGES_MS = (0, .1, .2, .3, .4, .5, .6, .7, .8, 1.0)
FAST = 400.0  # rad/s^2: samples where a reading's instant matters


def fitted_model(fit: str, log):
    """(model description after calibrate all + discover --apply on ``fit``'s moving phase, notes)."""
    from imu_array_ros import workflows
    from imu_array_ros.discovery.apply import findings_calibration
    from imu_array_ros.workflows.arrays import as_model

    desc, _ = workflows.load_array(ARRAY)
    samples, _ = workflows.import_openshoe(DATA / f"{fit}.bin", desc, start_ns=0)
    caldesc = workflows.calibrate("all", samples, desc).apply(desc)
    part, _ = moving_phase(samples, 10.0, 2.0)
    d = workflows.discover(part, caldesc, progress=lambda text: log(f"{fit}: {text}"))
    cal = findings_calibration(d, part, start=as_model(caldesc))
    return cal.apply(caldesc), [f"{f.effect} on {f.sensor}" for f in d.findings], desc


def residual_state(samples, model):
    """Normalised residuals, validity, motion, whitened motion Jacobians and each reading's delay at the ML motion."""
    from imu_array_ros.discovery.timing import session_model
    from imu_array_ros.fitting.engine import fit_motion
    from imu_array_ros.fusion.residuals import motion_context
    from imu_array_ros.model.terms.sample_clock import clock_ticks
    from imu_array_ros.model.trajectory import timing_context

    model = session_model(samples, model)
    motion, _, z = fit_motion(samples, model)
    tc = timing_context(samples.stamps, motion)
    ctx = motion_context(samples.stamps, motion[:, :3], motion[:, 3:6], motion[:, 6:9], model.rotations,
                         t0_ns=int(samples.stamps[0]), **tc)
    jac = model.jacobians(ctx)
    valid = np.isfinite(z)
    t = (samples.stamps - samples.stamps[0]) * 1e-9
    clock = model.terms["gyroscope_sample_clock"].values if "gyroscope_sample_clock" in model.terms else None
    if clock is None:
        raise SystemExit("the fitted model has no gyroscope sample clocks: nothing to say about reading instants")
    _, age, _ = clock_ticks(t[:, None], clock[None, :, 0], clock[None, :, 1], clock[None, :, 2])
    offset = model.terms["time_offset"].values if "time_offset" in model.terms else np.zeros((model.n_imus, 2))
    delta = np.empty(z.shape)
    delta[..., :3] = -offset[None, :, 0, None]
    delta[..., 3:] = (-(offset[None, :, 1] + age))[..., None]
    jw = np.where(valid[..., None], jac.motion / model.std[None, :, :, None], 0.0)
    return dict(z=np.where(valid, z, 0.0), valid=valid, motion=motion, t=t, age=age, delta=delta, jw=jw,
                rot=model.rotations, std=model.std)


def whiteness(s) -> dict:
    from scipy.signal import welch

    out = {}
    fs = 1.0 / float(np.median(np.diff(s["t"])))
    for name, sl in (("accelerometer", slice(0, 3)), ("gyroscope", slice(3, 6))):
        x = s["z"][:, :, sl].reshape(len(s["t"]), -1)
        f, p = welch(x, fs=fs, nperseg=256, axis=0)
        p = p.mean(axis=1)
        out[name] = {"bands": {f"{a}-{b} Hz": float(p[(f >= a) & (f < b)].sum() / p.sum()) for a, b in BANDS},
                     "lag1": float(np.mean([np.corrcoef(x[:-1, j], x[1:, j])[0, 1] for j in range(x.shape[1])]))}
        ss = (x ** 2).sum(axis=1)
        out[name]["top1pct_share"] = float(np.sort(ss)[::-1][:max(1, len(ss) // 100)].sum() / ss.sum())
    return out


def instants(s) -> dict:
    """Mean squared pair difference of residuals (array frame, physical units) by |age_j - age_k|."""
    rot, std, z, valid, age = s["rot"], s["std"], s["z"], s["valid"], s["age"]
    fast = np.linalg.norm(s["motion"][:, 3:6], axis=1) > FAST
    out = {}
    for name, sl in (("accelerometer", slice(0, 3)), ("gyroscope", slice(3, 6))):
        r = np.einsum("kij,nkj->nki", rot, z[:, :, sl] * std[None, :, sl])
        ok = valid[:, :, sl].all(axis=2) & fast[:, None]
        da, dd = [], []
        for j in range(r.shape[1]):
            for k in range(j + 1, r.shape[1]):
                sel = ok[:, j] & ok[:, k]
                da.append(np.abs(age[sel, j] - age[sel, k]) * 1e3)
                dd.append(((r[sel, j] - r[sel, k]) ** 2).sum(axis=1))
        da, dd = np.concatenate(da), np.concatenate(dd)
        out[name] = [float(dd[(da >= lo) & (da < hi)].mean()) if np.any((da >= lo) & (da < hi)) else None
                     for lo, hi in zip(AGE_EDGES_MS[:-1], AGE_EDGES_MS[1:])]
    return out


def extra_states(s, *blocks: np.ndarray) -> dict:
    """Per-sample states the model lacks, each block (N, K, 6, 3) the whitened columns of one free 3-vector per
    sample: the share of the moving residual sum of squares they remove once fitted jointly with the 9 motion
    states, what chance would remove (white residuals: their count / (valid readings - 9) per sample), the
    residual per reading before and after (sum of squares / (valid readings - states)), the fitted vectors'
    median size, and the pair differences of section 3 after."""
    n, k = s["age"].shape
    a = s["jw"].reshape(n, 6 * k, 9)
    b = np.concatenate([np.where(s["valid"][..., None], c, 0.0).reshape(n, 6 * k, 3) for c in blocks], axis=2)
    r = s["z"].reshape(n, 6 * k)

    def fit(cols):
        p = cols.shape[2]
        gram = cols.transpose(0, 2, 1) @ cols + 1e-9 * np.eye(p)
        sol = np.linalg.solve(gram, cols.transpose(0, 2, 1) @ r[..., None])
        return r - (cols @ sol)[..., 0], sol[..., 0]

    r0, _ = fit(a)
    r1, sol = fit(np.concatenate([a, b], axis=2))
    moving = np.linalg.norm(s["motion"][:, :3], axis=1) >= 0.2
    m = s["valid"].reshape(n, -1).sum(axis=1)[moving]
    extra = b.shape[2]
    ss0, ss1 = (r0[moving] ** 2).sum(), (r1[moving] ** 2).sum()
    after = dict(s, z=r1.reshape(n, k, 6))
    return {"removed": float(1 - ss1 / ss0), "chance": float(np.mean(extra / np.maximum(m - 9, 1))),
            "per_reading_before": float(ss0 / np.sum(m - 9)), "per_reading_after": float(ss1 / np.sum(m - 9 - extra)),
            "median_norm": float(np.median(np.linalg.norm(sol[moving, 9:12], axis=1))),
            "instants_after": instants(after)}


def own_rate_columns(s) -> np.ndarray:
    """The gyroscopes' own rate: the engine's rho_g columns (:func:`age_columns`), normalised."""
    return age_columns(s["age"], s["rot"].transpose(0, 2, 1))[..., 0:3] / s["std"][None, :, :, None]


def accel_rate_columns(s) -> np.ndarray:
    """The accelerometers' own rate: (age of the chip's gyroscope clock - the sample's mean) times a free
    array-frame 3-vector, as if each chip sampled its accelerometer on the same clock (the engine's rho_a)."""
    return age_columns(s["age"], s["rot"].transpose(0, 2, 1))[..., 3:6] / s["std"][None, :, :, None]


def placebo(s, seed: int = 1):
    """Both own rates with every reading's age replaced by an independent uniform draw in [0, 1 ms): the same
    number and structure of states, no chip clock -- what six free states per sample remove by themselves."""
    fake = dict(s, age=np.random.default_rng(seed).uniform(0.0, 1e-3, s["age"].shape))
    return s, own_rate_columns(fake), accel_rate_columns(fake)


def jerk_columns(s) -> np.ndarray:
    half = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
    return (s["delta"] * half)[..., None] * s["jw"][..., 3:6]


def sawtooth_amplitude(s) -> list:
    rot, std, z, valid, age = s["rot"], s["std"], s["z"], s["valid"], s["age"]
    wd = s["motion"][:, 3:6]
    fast = np.linalg.norm(wd, axis=1) > FAST
    r = np.einsum("kij,nkj->nki", rot, z[:, :, 3:] * std[None, :, 3:])
    out = []
    for k in range(r.shape[1]):
        sel = fast & valid[:, k, 3:].all(axis=1)
        x = wd[sel]
        design = np.stack([x.ravel(), (x * (age[sel, k] - 0.5e-3)[:, None]).ravel()], axis=1)
        y = r[sel, k].ravel()
        beta = np.linalg.lstsq(design, y, rcond=None)[0]
        out.append({"b0_ms": float(beta[0] * 1e3), "b1": float(beta[1]),
                    "explained": float(1 - ((y - design @ beta) ** 2).sum() / (y ** 2).sum())})
    return out


def analyse(label, samples, model) -> dict:
    s = residual_state(samples, model)
    moving = np.linalg.norm(s["motion"][:, :3], axis=1) >= 0.2
    return {"capture": label, "samples": int(len(s["t"])), "mean_z2_moving": float((s["z"][moving] ** 2).sum()
                                                                                  / s["valid"][moving].sum()),
            "whiteness": whiteness(s), "instants": instants(s), "own_rate": extra_states(s, own_rate_columns(s)),
            "accel_rate": extra_states(s, accel_rate_columns(s)),
            "both_rates": extra_states(s, own_rate_columns(s), accel_rate_columns(s)),
            "placebo": extra_states(*placebo(s)),
            "jerk": extra_states(s, jerk_columns(s)), "sawtooth": sawtooth_amplitude(s)}


def render(fit, findings, rows, header) -> str:
    lines = [header, f"Fit capture: {fit}; findings installed: {'; '.join(findings) or 'none'}.", "",
             "## 1-2. Whiteness and tails (normalised residuals of the moving phase)", "",
             "| scored | mean z^2 (moving) | sensor | " + " | ".join(f"{a}-{b} Hz" for a, b in BANDS)
             + " | lag-1 autocorr | worst 1 % of samples' share |",
             "|---|---|---|" + "---|" * (len(BANDS) + 2)]
    for r in rows:
        for name, w in r["whiteness"].items():
            lines.append(f"| {r['capture']} | {r['mean_z2_moving']:.0f} | {name} | "
                         + " | ".join(f"{v:.2f}" for v in w["bands"].values())
                         + f" | {w['lag1']:.3f} | {w['top1pct_share']:.2f} |")
    edges = [f"{lo}-{hi}" for lo, hi in zip(AGE_EDGES_MS[:-1], AGE_EDGES_MS[1:])]
    lines += ["", f"## 3. Pairs of IMUs: mean squared residual difference by |age_j - age_k| (ms), |omega_dot| > "
                  f"{FAST:g} rad/s^2", "", "| scored | sensor (unit^2) | " + " | ".join(edges) + " | last / first |",
              "|---|---|" + "---|" * (len(edges) + 1)]
    for r in rows:
        for name, v in r["instants"].items():
            ratio = v[-1] / v[0] if v[0] and v[-1] else float("nan")
            lines.append(f"| {r['capture']} | {name} | " + " | ".join("—" if x is None else f"{x:.3g}" for x in v)
                         + f" | {ratio:.1f} |")
    lines += ["", "## 4-5. Per-sample states the model lacks, fitted with the 9 motion states", "",
              "Share of the moving residual sum of squares removed (what chance would remove), the residual per "
              "reading before -> after (sum of squares / (valid readings - states)), the first vector's median size "
              "(rad/s^2 for a rate of omega, m/s^3 for one of s, rad/s^3 for omega_ddot), and the pair differences "
              "of section 3 after (0.8-1.0 ms bin / 0-0.1 ms bin; accelerometer, gyroscope).", "",
              "| scored | states | removed (chance) | per reading | median size | pair growth after (acc, gyro) |",
              "|---|---|---|---|---|---|"]
    names = (("own_rate", "gyroscopes' own rate"), ("accel_rate", "accelerometers' own rate, on the chip clock"),
             ("both_rates", "both own rates (6)"),
             ("placebo", "placebo: both, random ages"), ("jerk", "per-sample omega_ddot"))
    for r in rows:
        for key, label in names:
            e = r[key]
            g = [v[-1] / v[0] if v[0] and v[-1] else float("nan") for v in e["instants_after"].values()]
            lines.append(f"| {r['capture']} | {label} | {e['removed']:.3f} ({e['chance']:.3f}) | "
                         f"{e['per_reading_before']:.0f} -> {e['per_reading_after']:.0f} | {e['median_norm']:.3g} | "
                         f"{g[0]:.1f}, {g[1]:.1f} |")
    lines += ["", "## 6. Gyroscope sawtooth amplitude error b1 per IMU (0: the modelled amplitude)", "",
              "| scored | " + " | ".join(f"imu {k + 1}" for k in range(len(rows[0]["sawtooth"]))) + " |",
              "|---|" + "---|" * len(rows[0]["sawtooth"])]
    for r in rows:
        lines.append(f"| {r['capture']} | " + " | ".join(f"{x['b1']:+.2f}" for x in r["sawtooth"]) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", default="exp_6", choices=CAPTURES, help="capture the model is fitted on")
    ap.add_argument("--score", nargs="+", choices=CAPTURES, help="captures analysed (default: every other one)")
    ap.add_argument("--description", help="analyse under this calibrated description (e.g. written by discover "
                                           "--apply) instead of fitting one on --fit")
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    single_threaded_blas()
    from imu_array_ros import workflows
    from imu_array_ros.workflows.arrays import as_model

    load0 = load_average()
    t = time.monotonic()
    if args.description:
        desc, _ = workflows.load_array(ARRAY)
        found, _ = workflows.load_array(ARRAY, args.description)
        findings = [f"the description {args.description}"]
    else:
        found, findings, desc = fitted_model(args.fit, say)
    model = as_model(found)
    rows = []
    for cap in args.score or [c for c in CAPTURES if c != args.fit]:
        samples, _ = workflows.import_openshoe(DATA / f"{cap}.bin", desc, start_ns=0)
        rows.append(analyse(cap, moving_phase(samples, 10.0, 2.0)[0], model))
        b = rows[-1]["both_rates"]
        say(f"{cap}: per reading {b['per_reading_before']:.0f}; with both own rates {b['per_reading_after']:.0f} "
            f"(removed {b['removed']:.3f}, chance {b['chance']:.3f})")
        with open(f"{args.out}.json", "w") as fh:
            json.dump({"fit": args.fit, "findings": findings, "rows": rows}, fh, indent=1)
    header = machine_header("Anatomy of the moving residual on the real captures (issue 23)",
                            extra=(f"load average at the start: {load0}; at the end: {load_average()}",
                                   f"wall time: {time.monotonic() - t:.0f} s"))
    write_results(f"{args.out}.md", render(args.fit, findings, rows, header))
    say(f"wrote {args.out}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
