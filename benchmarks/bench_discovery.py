"""Speed of mismatch discovery (issue 10 targets: 32 IMUs x 60 s x 200 Hz in < 2 min, an 8-IMU real capture
in < 1 min, one core).

* simulated: the 32-IMU array (config/array32.yaml), 20 still poses then hand twisting, 200 Hz, 60 s in all,
  a position error on one IMU (0.3 noise std RMS), analysed by ``discover`` with every default (all 14 terms
  x 32 IMUs candidates, held-out refits, empirical models);
* real: capture exp_1 of ../shared/data/openshoe_mimu4444bt/ from its standard-term fit
  (benchmarks/results/real_data_terms/exp_1.yaml), defaults (at most 8 findings).

Baseline in the same run: one ML motion fit (``fit_motion``) of the same recording, so the ratio says how
many motion fits discovery costs.  Single-threaded BLAS.

    python -m benchmarks.bench_discovery [--skip-real]
"""

from __future__ import annotations

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from imu_array_ros.discovery.discover import DiscoveryOptions, discover  # noqa: E402
from imu_array_ros.fitting.engine import fit_motion  # noqa: E402
from imu_array_ros.simulation.concealed import Scenario, build  # noqa: E402

OUT = RESULTS / "discovery.md"


def _time(samples, model):
    t0 = time.perf_counter()
    fit_motion(samples, model)
    base = time.perf_counter() - t0
    t0 = time.perf_counter()
    d = discover(samples, model, options=DiscoveryOptions(),
                 progress=lambda s: say(f"  {s}"))
    return base, time.perf_counter() - t0, d


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-real", action="store_true")
    args = ap.parse_args()
    text = machine_header("Mismatch discovery speed") + __doc__.split("\n\n", 1)[1].rsplit("\n\n", 1)[0] + "\n\n"
    text += "| recording | samples x IMUs | fit_motion (baseline) | discover | ratio | findings | target |\n"
    text += "|---|---|---|---|---|---|---|\n"
    sc = Scenario("bench", str(REPO / "config" / "array32.yaml"), [("position", 9)], seed=7, rate_hz=200.0,
                  still_s=1.0, transition_s=0.5, twist_s=30.5)
    built = build(sc)
    base, total, d = _time(built.samples, built.nominal)
    n = len(built.samples.stamps)
    text += (f"| simulated, 32 IMUs, {n / sc.rate_hz:.0f} s at 200 Hz | {n} x 32 | {base:.2f} s | {total:.1f} s | "
             f"{total / base:.0f} | {', '.join(f'{f.effect}@{f.sensor}' for f in d.findings) or '—'} | < 120 s |\n")
    print(text.splitlines()[-1])
    if not args.skip_real:
        from imu_array_ros.io.openshoe.capture import import_capture
        from imu_array_ros.model.description import load_description
        from imu_array_ros.model.sensor_model import SensorModel

        data = DATA / "exp_1.bin"
        desc = load_description(RESULTS / "real_data_terms" / "exp_1.yaml")
        samples = import_capture(data, load_description(REPO / "config" / "mimu4444bt_corners.yaml"))[0]
        base, total, d = _time(samples, SensorModel.from_description(desc))
        n = len(samples.stamps)
        dur = (samples.stamps[-1] - samples.stamps[0]) * 1e-9
        text += (f"| real exp_1, 8 IMUs, {dur / 60:.1f} min | {n} x 8 | {base:.2f} s | {total:.1f} s | "
                 f"{total / base:.0f} | {len(d.findings)} | < 60 s (for 10 min) |\n")
        text += "\nTime per stage of the real capture: " + ", ".join(f"{k} {v:.1f} s" for k, v in d.timings.items())
        text += "\n"
        print(text.splitlines()[-3])
    write_results(OUT, text)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
