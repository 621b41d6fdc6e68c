"""Sample-clock search (``timing.clocks.find_sample_clocks``, the discovery's timing stage) on library misfits.

Recordings as ``benchmarks.discovery_modes``' library nulls draw them (an array: 4 planar, the 8 MIMU4444BT corners,
32; a rate 62.5-1000 Hz; 10-30 s of twisting, at most 120 000 readings; one IMU carries a gain, misalignment,
position or g-sensitivity error 1-5x its test size the model analysed with lacks), simulated with exact stamps:

* ``null``: no sample clock; any chip given a clock is a false finding;
* ``clocked``: the same, and every IMU's gyroscope samples on its own 1 ms clock (rate uniform +-3000 ppm, random
  phase; the time offset -1.6 ms as on the MIMU4444BT); a chip counts as found when its clock is found within
  10 ppm of its rate (chips whose beat 1 kHz x |rate| is slower than 2 / duration are not counted).

    python -m benchmarks.timing_misfit_clocks --seed S [--recordings 12] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from benchmarks.discovery_modes import ARRAYS, CAP, MISFIT_TERMS, RATES
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.perturb import TERM_TEST_SIZES
from imu_array_ros.simulation.simulator import simulate_twist
from imu_array_ros.timing.clocks import find_sample_clocks

TERMS = MISFIT_TERMS  # the library terms a clock-free recording lacks, as discovery_modes draws them


def case(seed: int, clocked: bool) -> dict:
    rng = np.random.default_rng([seed, 7])
    array = str(rng.choice(list(ARRAYS)))
    model = SensorModel.from_description(ARRAYS[array]())
    k = model.n_imus
    term = str(rng.choice(TERMS))
    v = model.terms[term].values.copy()
    kk = int(rng.integers(k))
    v[kk] += rng.normal(size=v[kk].shape) * TERM_TEST_SIZES[term] * rng.uniform(1.0, 5.0)
    sim = model.with_terms(**{term: v})
    rate = float(rng.choice([r for r in RATES if 10.0 * r * k <= CAP]))
    dur = float(min(rng.uniform(10.0, 30.0), CAP / (rate * k)))
    clock = np.zeros((k, 3))
    if clocked:
        clock = np.column_stack([np.full(k, 1e-3), rng.uniform(-3000, 3000, k), np.zeros(k)])
        clock[:, 2] = rng.uniform(0, 1, k) * clock[:, 0] / (1 + clock[:, 1] * 1e-6)
        sim = sim.with_terms(gyroscope_sample_clock=clock,
                             time_offset=np.column_stack([np.full(k, -1.6e-3), np.zeros(k)]))
    samples, _ = simulate_twist(sim, dur, rate, rng, start_ns=10**9)
    t0 = time.time()
    try:
        s = find_sample_clocks(samples, model)
    except ValueError as err:
        return {"seed": seed, "clocked": clocked, "error": str(err)}
    out = {"seed": seed, "clocked": clocked, "array": array, "rate_hz": rate, "seconds_recorded": dur, "term": term,
           "imu": kk, "seconds": time.time() - t0,
           "found": {sen: int(f.sum()) for sen, f in s.found.items()}, "notes": s.notes}
    if clocked:
        beats = np.abs(clock[:, 1]) * 1e-3 >= 2.0 / dur
        g = s.found.get("gyroscope", np.zeros(k, bool))
        right = g & (np.abs(np.nan_to_num(s.rates.get("gyroscope", np.full(k, np.nan)), nan=1e9) - clock[:, 1]) <= 10.0)
        out.update(chips=int(beats.sum()), right=int((right & beats).sum()),
                   accelerometer_false=int(s.found.get("accelerometer", np.zeros(k, bool)).sum()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--recordings", type=int, default=12)
    ap.add_argument("--json")
    a = ap.parse_args()
    rows = []
    for i in range(a.recordings):
        for clocked in (False, True):
            rows.append(case(a.seed * 1000 + i, clocked))
            print(json.dumps(rows[-1], default=float), flush=True)
    nulls = [r for r in rows if not r["clocked"] and "error" not in r]
    clk = [r for r in rows if r["clocked"] and "error" not in r]
    summary = {"null_recordings": len(nulls), "null_with_a_clock": sum(sum(r["found"].values()) > 0 for r in nulls),
               "null_chips_with_a_clock": sum(sum(r["found"].values()) for r in nulls),
               "clocked_recordings": len(clk), "clocked_chips": sum(r["chips"] for r in clk),
               "clocked_right": sum(r["right"] for r in clk),
               "clocked_accelerometer_false": sum(r["accelerometer_false"] for r in clk)}
    print(json.dumps(summary))
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"summary": summary, "rows": rows}, f, default=float, indent=1)


if __name__ == "__main__":
    main()
