"""Is the matched mode test's family-wise p calibrated?  Its realised false-alarm rate on white residuals.

:func:`imu_array_ros.discovery.matched.matched_scan` turns its statistic into a family-wise p with a law fitted to
``matched.NULL_DRAWS`` white recordings: the joint law over widths (since helper-68), or (``bonferroni=True``, the
law before it) per template width a Gumbel law of the scan maxima, Bonferroni over the widths; both are measured
in the same run, on the same recordings.  This benchmark draws ``--draws`` further white-noise recordings (unit
normalised accelerometer
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

    python -m benchmarks.matched_null_calibration [--seed S] [--draws 1000] [--rate 100] [--seconds 45]
        [--discovery-nulls 0] [--out PATH]
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
#: the laws compared: key in the json -> matched_scan's bonferroni flag
LAWS = {"p": False, "p_bonferroni": True}
LAW_NAMES = {"p": "joint law over widths", "p_bonferroni": "Bonferroni over widths (before)"}


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


def run(seed: int, draws: int, rate: float, seconds: float, discovery_nulls: int = 0) -> dict:
    from imu_array_ros.discovery.coherent import field_basis
    from imu_array_ros.discovery.modes import SMOOTH_SCALE
    from imu_array_ros.simulation.suites import ARRAYS, array_description

    n = int(round(rate * seconds))
    rows = []
    for i, array in enumerate(ARRAYS):
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
    return {"seed": seed, "draws": draws, "rate_hz": rate, "seconds": seconds, "samples": n, "rows": rows,
            "discovery_nulls": nulls}


def render(res: dict, header: str) -> str:
    from benchmarks.discovery_generalisation import clopper_pearson

    def cells(ps) -> str:
        ps, out = np.asarray(ps), []
        for a in LEVELS:
            k = int(np.sum(ps < a))
            lo, hi = clopper_pearson(k, len(ps))
            out.append(f"{k / len(ps):.4f} ({lo:.4f}–{hi:.4f})")
        return " | ".join(out)

    lines = [header, "## Realised rate of p < nominal on white recordings\n",
             "| array | IMUs | field channels | law | " + " | ".join(f"nominal {a:g}" for a in LEVELS) + " |",
             "|---|---|---|---|" + "---|" * len(LEVELS)]
    for r in res["rows"]:
        for key in LAWS:
            if key in r:
                lines.append(f"| {r['array']} | {r['imus']} | {r['field_channels']} | {LAW_NAMES[key]} | "
                             + cells(r[key]) + " |")
    lines.append(f"\n{res['draws']} white recordings per array, {res['samples']} samples at {res['rate_hz']:g} Hz "
                 f"({res['seconds']:g} s), seed {res['seed']}.")
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
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seconds", type=float, default=45.0)
    ap.add_argument("--discovery-nulls", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    load = load_average()
    res = run(args.seed, args.draws, args.rate, args.seconds, args.discovery_nulls)
    header = machine_header(TITLE, extra=[f"seed: {args.seed}", f"load average at the start: {load}"])
    out = args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    from imu_array_ros.util.files import atomic_write_text

    atomic_write_text(out.with_suffix(".json"), json.dumps(res))
    write_results(out.with_suffix(".md"), render(res, header))
    say(f"wrote {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
