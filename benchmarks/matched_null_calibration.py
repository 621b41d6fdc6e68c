"""Is the matched mode test's family-wise p calibrated?  Its realised false-alarm rate on white residuals.

:func:`imu_array_ros.discovery.matched.matched_scan` turns its statistic into a family-wise p with a law fitted to
``matched.NULL_DRAWS`` white recordings: the joint law over widths (``bonferroni=False``, helper-68), or (the one
discover uses, ``matched.JOINT_LAW``) per template width a Gumbel law of the scan maxima, Bonferroni over the
widths; both measured in the same run, on the same recordings.  This benchmark draws ``--draws`` further
white-noise recordings (unit normalised accelerometer
residuals: exactly the null the law is fitted to) per suite array (:data:`imu_array_ros.simulation.suites.ARRAYS`),
at ``--rate`` Hz for ``--seconds`` s, with the field basis discover's mode search uses
(:func:`imu_array_ros.discovery.coherent.field_basis`, ``min_scale`` = ``modes.SMOOTH_SCALE``), and counts the
recordings whose smallest p over widths and centres (``matched_scan(..., alpha=1)``) is below each nominal level
(Clopper-Pearson 95 % intervals).  Calibrated: realised = nominal; below it the test spends less than its share
of alpha (conservative: power lost at the same false-alarm rate).  In discover the test gets alpha / 4 = 0.0025.

``--discovery-nulls N``: also N null recordings of :mod:`benchmarks.discovery_modes` (kinds white, broadband,
library in turn: :func:`benchmarks.discovery_modes.null_recording`; the motion fitted by the engine, so the
residuals carry its leverage, Gauss-Markov noise and random-walk bias on 1-3 IMUs, or a library term's misfit),
their accelerometer residuals through the matched scan as ``detect_modes`` calls it (field basis with the model's
accelerometer stds).  Any p below a level there is a false alarm at that level too.

``--vibrations N``: the other side, power: the suite's first N vibration scenarios (``--vibration-seed``,
oracle evidence ``--evidence``; :func:`imu_array_ros.simulation.suites.draw_scenario` and ``build``, the nominal
model's motion fit), each law's smallest p over the templates overlapping the mode's band (centre +- max(width,
0.25 Hz)) and elsewhere, on the same residuals; found by the matched test when below its share in discover,
``modes.MODE_ALPHA`` / 4.  (discover runs the Welch coherent test and the line tests beside it: this is the
matched test's own power, not discovery's.)

    python -m benchmarks.matched_null_calibration [--seed S] [--draws 1000] [--rate 100] [--seconds 45]
        [--discovery-nulls 0] [--vibrations 0] [--vibration-seed S] [--evidence 100 1000] [--out PATH]
"""

from __future__ import annotations

from benchmarks.harness import RESULTS, load_average, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

TITLE = "Matched mode test: realised family-wise false-alarm rate on white residuals against its nominal p"
OUT = RESULTS / "matched_null_calibration"
#: drawn with secrets.randbelow(10**6) when the benchmark was written; no code was tuned on it
SEED = 748673
LEVELS = (0.001, 0.0025, 0.01, 0.05, 0.1, 0.2)
#: the laws compared: key in the json -> matched_scan's bonferroni flag (discover: matched.JOINT_LAW)
LAWS = {"p": False, "p_bonferroni": True}
LAW_NAMES = {"p": "joint law over widths", "p_bonferroni": "Bonferroni over widths (discover's)"}


def smallest_p(acc: np.ndarray, basis: np.ndarray, fs: float, bonferroni: bool = False) -> float:
    """The matched test's smallest family-wise p over widths and centres on accelerometer residuals (N, 3K)."""
    from imu_array_ros.discovery.matched import matched_scan

    out = matched_scan(acc, basis, fs, 1.0, bonferroni=bonferroni)
    return min((float(np.min(w["p"])) for w in out["widths"].values()), default=1.0) if out else 1.0


def discovery_null(seed: int, kind: str) -> dict:
    """A null of benchmarks.discovery_modes (module docstring): its accelerometer residuals' smallest p per law."""
    from benchmarks.discovery_modes import null_recording
    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.modes import SMOOTH_SCALE
    from imu_array_ros.fitting.engine import fit_motion

    kind, array, rate, _, model, samples = null_recording(seed, kind)
    _, _, r = fit_motion(samples, model)
    n, k = r.shape[:2]
    fs = 1e9 / float(np.median(np.diff(samples.stamps)))
    basis = field_basis(model.positions, model.rotations, np.asarray(model.std, dtype=float)[:, :3],
                        min_scale=SMOOTH_SCALE)
    acc = np.where(np.isfinite(r), r, np.nan)[:, :, :3].reshape(n, 3 * k)
    row = {"seed": seed, "kind": kind, "array": array, "rate_hz": rate, "samples": n}
    row.update({key: smallest_p(acc, basis, fs, b) if basis.shape[1] >= 2 else 1.0 for key, b in LAWS.items()})
    return row


def vibration(seed: int, index: int, evidence: tuple[float, float]) -> dict:
    """A suite vibration scenario (module docstring): each law's smallest p at the mode's band and elsewhere."""
    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.matched import matched_scan
    from imu_array_ros.discovery.modes import SMOOTH_SCALE
    from benchmarks.discovery_vibration_bound import built_vibration
    from imu_array_ros.fitting.engine import fit_motion

    sc, b, fs, unsizable = built_vibration(seed, index, evidence)
    if unsizable:
        return unsizable
    s, m, vib = b.samples, b.nominal, b.scenario.vibration
    _, _, r = fit_motion(s, m)
    n, k = r.shape[:2]
    basis = field_basis(m.positions, m.rotations, np.asarray(m.std, dtype=float)[:, :3], min_scale=SMOOTH_SCALE)
    half = max(vib.bandwidth_hz, 0.25)
    row = {"scenario": sc.name.replace(" | ", ", "), "array": sc.array, "rate_hz": fs, "samples": n,
           "frequency_hz": vib.frequency_hz, "bandwidth_hz": vib.bandwidth_hz, "evidence": float(b.oracle[-1])}
    for key, bonf in LAWS.items():
        out = matched_scan(np.where(np.isfinite(r), r, np.nan)[:, :, :3].reshape(n, 3 * k), basis, fs, 1.0,
                           bonferroni=bonf) if basis.shape[1] >= 2 else None
        at, off = 1.0, 1.0
        for w, d in (out or {}).get("widths", {}).items():
            f = d["centres"] * fs / n
            near = (f + w >= vib.frequency_hz - half) & (f - w <= vib.frequency_hz + half)
            at = min(at, float(np.min(d["p"][near], initial=1.0)))
            off = min(off, float(np.min(d["p"][~near], initial=1.0)))
        row[key], row[key + "_elsewhere"] = at, off
    return row


def run(seed: int, draws: int, rate: float, seconds: float, discovery_nulls: int = 0, vibrations: int = 0,
        vibration_seed: int = 0, evidence: tuple[float, float] = (100.0, 1000.0)) -> dict:
    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.modes import SMOOTH_SCALE
    from imu_array_ros.simulation.suites import ARRAYS, array_description

    n = int(round(rate * seconds))
    rows = []
    for i, array in enumerate(ARRAYS if draws else ()):
        desc = array_description(array)
        basis = field_basis(desc.positions, desc.orientations, None, min_scale=SMOOTH_SCALE)
        rng = np.random.default_rng([seed, i])
        t0 = time.perf_counter()
        ps = {key: [] for key in LAWS}
        for _ in range(draws):
            acc = rng.normal(size=(n, basis.shape[0]))
            for key, b in LAWS.items():
                ps[key].append(smallest_p(acc, basis, rate, b))
        rows.append({"array": array, "imus": basis.shape[0] // 3, "field_channels": int(basis.shape[1]),
                     **ps, "seconds": time.perf_counter() - t0})
        say(f"{array}: {draws} draws in {rows[-1]['seconds']:.0f} s; " + "; ".join(
            f"{key} " + ", ".join(f"{a:g}: {np.mean(np.array(ps[key]) < a):.4f}" for a in LEVELS) for key in LAWS))
    nulls = []
    for i in range(discovery_nulls):
        t0 = time.perf_counter()
        nulls.append(discovery_null(seed * 1000 + i, ("white", "broadband", "library")[i % 3]))
        nulls[-1]["seconds"] = time.perf_counter() - t0
        say(f"null {i} {nulls[-1]['kind']} {nulls[-1]['array']} {nulls[-1]['samples']} samples: "
            + ", ".join(f"{key} {nulls[-1][key]:.3g}" for key in LAWS) + f" ({nulls[-1]['seconds']:.0f} s)")
    vibs = []
    for i in range(vibrations):
        t0 = time.perf_counter()
        vibs.append(vibration(vibration_seed, i, evidence))
        vibs[-1]["seconds"] = time.perf_counter() - t0
        say(f"vibration {i}: " + ", ".join(f"{key} {vibs[-1].get(key, float('nan')):.3g}" for key in LAWS)
            + f" ({vibs[-1]['seconds']:.0f} s)")
    return {"seed": seed, "draws": draws, "rate_hz": rate, "seconds": seconds, "samples": n, "rows": rows,
            "discovery_nulls": nulls, "vibration_seed": vibration_seed, "evidence": list(evidence),
            "vibrations": vibs}


def render(res: dict, header: str) -> str:
    from benchmarks.discovery_generalisation import clopper_pearson

    def cells(ps) -> str:
        ps, out = np.asarray(ps), []
        for a in LEVELS:
            k = int(np.sum(ps < a))
            lo, hi = clopper_pearson(k, len(ps))
            out.append(f"{k / len(ps):.4f} ({lo:.4f}–{hi:.4f})")
        return " | ".join(out)

    lines = [header]
    if res["rows"]:
        lines.append("## Realised rate of p < nominal on white recordings\n")
    lines += [
             "| array | IMUs | field channels | law | " + " | ".join(f"nominal {a:g}" for a in LEVELS) + " |",
             "|---|---|---|---|" + "---|" * len(LEVELS)] if res["rows"] else []
    for r in res["rows"]:
        for key in LAWS:
            if key in r:
                lines.append(f"| {r['array']} | {r['imus']} | {r['field_channels']} | {LAW_NAMES[key]} | "
                             + cells(r[key]) + " |")
    if res["rows"]:
        lines.append(f"\n{res['draws']} white recordings per array, {res['samples']} samples at {res['rate_hz']:g} "
                     f"Hz ({res['seconds']:g} s), seed {res['seed']}.")
    nulls = res.get("discovery_nulls") or []
    if nulls:
        lines += ["\n## Realised rate on the nulls of benchmarks.discovery_modes (motion fitted; residuals)\n",
                  "| nulls | count | law | " + " | ".join(f"nominal {a:g}" for a in LEVELS) + " |",
                  "|---|---|---|" + "---|" * len(LEVELS)]
        groups = {"all": nulls}
        for kind in ("white", "broadband", "library"):
            groups[kind] = [r for r in nulls if r["kind"].startswith(kind)]
        for name, rows in groups.items():
            for key in LAWS:
                if rows:
                    lines.append(f"| {name} | {len(rows)} | {LAW_NAMES[key]} | " + cells([r[key] for r in rows]) + " |")
        lines.append("\nSmallest p per null (joint / Bonferroni), sorted by the joint law's: " + ", ".join(
            f"{r['p']:.2g} / {r['p_bonferroni']:.2g} ({r['kind']}, {r['array']}, {r['samples']})"
            for r in sorted(nulls, key=lambda r: r["p"])[:10]) + ".")
    vibs = [v for v in res.get("vibrations") or [] if "error" not in v]
    if vibs:
        from imu_array_ros.discovery.modes import MODE_ALPHA

        share = MODE_ALPHA / 4
        lines += [f"\n## The suite's vibrations (seed {res['vibration_seed']}, evidence {res['evidence'][0]:g}-"
                  f"{res['evidence'][1]:g}): the matched test's smallest p at the mode's band and elsewhere\n",
                  f"Found: p at the band < {share:g} (its share in discover).  "
                  + "; ".join(f"{LAW_NAMES[key]}: {sum(v[key] < share for v in vibs)}/{len(vibs)} found, "
                              f"{sum(v[key + '_elsewhere'] < share for v in vibs)} with p < {share:g} elsewhere"
                              for key in LAWS) + ".\n",
                  "| scenario | Hz | width Hz | samples | evidence | " + " | ".join(
                      f"{LAW_NAMES[key]}: at band / elsewhere" for key in LAWS) + " |",
                  "|---|---|---|---|---|" + "---|" * len(LAWS)]
        for v in vibs:
            lines.append(f"| {v['scenario']} | {v['frequency_hz']:.2f} | {v['bandwidth_hz']:.2f} | {v['samples']} | "
                         f"{v['evidence']:.0f} | " + " | ".join(f"{v[key]:.2g} / {v[key + '_elsewhere']:.2g}"
                                                                 for key in LAWS) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seconds", type=float, default=45.0)
    ap.add_argument("--discovery-nulls", type=int, default=0)
    ap.add_argument("--vibrations", type=int, default=0)
    ap.add_argument("--vibration-seed", type=int, default=SEED)
    ap.add_argument("--evidence", type=float, nargs=2, default=(100.0, 1000.0), metavar=("LO", "HI"))
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    load = load_average()
    res = run(args.seed, args.draws, args.rate, args.seconds, args.discovery_nulls, args.vibrations,
              args.vibration_seed, tuple(args.evidence))
    header = machine_header(TITLE, extra=[f"seed: {args.seed}", f"load average at the start: {load}"])
    out = args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    from imu_array_ros.util.files import atomic_write_text

    atomic_write_text(out.with_suffix(".json"), json.dumps(res))
    write_results(out.with_suffix(".md"), render(res, header))
    say(f"wrote {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
