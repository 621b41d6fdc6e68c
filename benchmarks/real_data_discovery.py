"""Mismatch discovery on the real MIMU4444BT captures: what is left after the standard-term fit, per capture.

For each capture in ../shared/data/openshoe_mimu4444bt/: start from the standard-term fit of that capture
(benchmarks/results/real_data_terms/exp_N.yaml, written by benchmarks/real_data_terms.py: positions,
accelerometer and gyroscope gain / misalignment / bias, time offsets), run
:func:`imu_array_ros.discovery.discover.discover` (the engine behind ``imu-array discover``; defaults:
alpha 0.01, every registered term a candidate, 0.5 s blocks, at most ``--max-findings`` findings), and
validate on the five other captures (``--validate``): their log-likelihood and NIS with the starting
description and with the findings added.  The full report of each capture is written to
benchmarks/results/real_data_discovery/exp_N/ (report.md, report.json, plots).

Writes benchmarks/results/real_data_discovery.md.

    python -m benchmarks.real_data_discovery [--captures 1 2 ...] [--max-findings 8]
"""

from __future__ import annotations

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from imu_array_ros.discovery.discover import DiscoveryOptions, discover  # noqa: E402
from imu_array_ros.discovery.report import write_report  # noqa: E402
from imu_array_ros.io.openshoe.capture import import_capture  # noqa: E402
from imu_array_ros.model.description import load_description  # noqa: E402
from imu_array_ros.model.sensor_model import SensorModel  # noqa: E402

OUT = RESULTS


def _g(x, fmt=".4g"):
    return "—" if x is None else format(x, fmt)


def _nis(before: dict, after: dict) -> str:
    """'still before → after | moving before → after' table cells."""
    return " | ".join(f"{_g(before[k])} → {_g(after[k])}" for k in ("nis_still", "nis_moving"))


def _tables() -> str:
    """The tables, from every capture's report.json under real_data_discovery/ (runs may be split)."""
    import json

    reports = {}
    for i in range(1, 7):
        path = OUT / "real_data_discovery" / f"exp_{i}" / "report.json"
        if path.exists():
            reports[i] = json.loads(path.read_text())
    text = "## Per capture (fitting data)\n\n"
    text += ("| capture | samples | NIS still before → after | NIS moving before → after | Δ log-lik | "
             "held-out Δ log-lik (even/odd blocks) | findings | unexplained entries | s |\n"
             "|---|---|---|---|---|---|---|---|---|\n")
    for i, r in reports.items():
        b, a = r["baseline"], r["after"]
        text += (f"| exp_{i} | {r['settings']['samples']} | {_nis(b, a)} | {a['loglik'] - b['loglik']:.4g} | "
                 f"{_g(r['heldout'].get('delta_loglik'))} | {len(r['findings'])} | {len(r['unexplained'])} | "
                 f"{r['timings_s']['total']:.0f} |\n")
    text += ("\n## Findings (in the order found)\n\n| capture | step | effect | sensor | Δ log-lik | "
             "held-out Δ (CV) |\n|---|---|---|---|---|---|\n")
    for i, r in reports.items():
        for f in r["findings"]:
            e = f["evidence"]
            text += (f"| exp_{i} | {f['step']} | {f['effect']} | {f['sensors'][0]} | {e['delta_loglik']:.4g} | "
                     f"{e['heldout_delta_loglik']:.4g} |\n")
        for e in r["indistinguishable"]:
            text += f"| exp_{i} | | indistinguishable: {' / '.join(e['effects'])} | {', '.join(e['sensors'])} | | |\n"
    text += "\n## Validation on the other captures (fit on one, score on the others)\n\n"
    text += ("| fitted on | validated on | Δ log-lik | NIS still before → after | NIS moving before → after |\n"
             "|---|---|---|---|---|\n")
    better = total = 0
    for i, r in reports.items():
        for v in r["validation"]:
            total += 1
            better += v["delta_loglik"] > 0
            text += f"| exp_{i} | {v['recording']} | {v['delta_loglik']:.4g} | {_nis(v['before'], v['after'])} |\n"
    text += f"\nThe findings raise the held-out log-likelihood in {better} of {total} capture pairs.\n"
    text += ("\n## Unexplained after the findings\n\n| capture | sensors | axes | regime | band (Hz) | share | "
             "empirical model |\n|---|---|---|---|---|---|---|\n")
    for i, r in reports.items():
        for u in r["unexplained"]:
            em = u["empirical_model"]
            text += (f"| exp_{i} | {', '.join(u['sensors'][:4])}{' ...' if len(u['sensors']) > 4 else ''} | "
                     f"{', '.join(u['axes'])} | {u['regime']} | {u['band_hz'][0]:.3g}–{u['band_hz'][1]:.3g} | "
                     f"{u['share_of_residual']:.0%} | "
                     f"{'improves held-out by ' + format(em['heldout_delta_loglik'], '.3g') if em['improves_heldout'] else 'no'} |\n")
    return text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, nargs="*", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--max-findings", type=int, default=8)
    ap.add_argument("--tables-only", action="store_true", help="only rebuild the tables from the reports")
    args = ap.parse_args()
    nominal = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    samples = {} if args.tables_only else {i: import_capture(DATA / f"exp_{i}.bin", nominal)[0] for i in range(1, 7)}
    for i in ([] if args.tables_only else args.captures):
        desc = load_description(OUT / "real_data_terms" / f"exp_{i}.yaml")
        model = SensorModel.from_description(desc)
        t0 = time.perf_counter()
        others = [(f"exp_{j}", samples[j]) for j in range(1, 7) if j != i]
        d = discover(samples[i], model, options=DiscoveryOptions(max_findings=args.max_findings), validate=others,
                     progress=lambda s, i=i: say(f"exp_{i}: {s}"))
        seconds = time.perf_counter() - t0
        write_report(d, OUT / "real_data_discovery" / f"exp_{i}", source=f"exp_{i}.bin")
        print(f"exp_{i}: {len(d.findings)} findings in {seconds:.0f} s", flush=True)
    text = machine_header("Mismatch discovery on the real MIMU4444BT captures")
    text += __doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0] + "\n\n"
    done = sorted(int(p.parent.name.split("_")[1]) for p in (OUT / "real_data_discovery").glob("exp_*/report.json"))
    text += f"Captures analysed: {', '.join(f'exp_{i}' for i in done)}.\n\n"
    text += _tables()
    write_results(OUT / "real_data_discovery.md", text)
    print(f"wrote {OUT / 'real_data_discovery.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
