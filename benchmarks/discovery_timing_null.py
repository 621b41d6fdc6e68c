"""The false-alarm rate of discovery's sample-clock test (issue 23, item 5), measured on simulated nulls.

Null recordings: the 8 corner IMUs of ``config/mimu4444bt_corners.yaml``, hand twisting
(:func:`~imu_array_ros.simulation.simulator.simulate_twist`) of ``--seconds`` s at 62.5, 100 and 200 Hz, no
sample clock, no time offset, fresh seeds.  For every chip's gyroscope and accelerometer the sawtooth search
of :func:`imu_array_ros.discovery.timing.timing_stage` gives the peak / median ratio of its spectrum; a clock
is found at >= ``MIN_SNR`` (8).  Reported: the ratio's null distribution (quantiles, maximum), how many chips
reached the threshold, the exact binomial 95 % upper bound on the per-chip rate, and the Rayleigh bound.

    python -m benchmarks.discovery_timing_null [--seeds 6] [--seconds 30]
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import scipy.stats

from imu_array_ros.discovery.timing import false_alarm_bound, timing_stage
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_twist
from imu_array_ros.timing.clocks import MIN_SNR


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--first-seed", type=int, default=23000)
    a = ap.parse_args()
    nominal = SensorModel.from_description(load_description("config/mimu4444bt_corners.yaml"))
    ratios = []
    for rate in (62.5, 100.0, 200.0):
        for i in range(a.seeds):
            seed = a.first_seed + i + int(rate) * 100
            s, _ = simulate_twist(nominal, a.seconds, rate, np.random.default_rng(seed), start_ns=10**9)
            out = timing_stage(s, nominal)
            for v in out.snr.values():
                ratios += [float(x) for x in v]
            print(f"{rate:g} Hz seed {seed}: max ratio {max(max(v) for v in out.snr.values()):.2f}, "
                  f"found {len(out.findings)}", flush=True)
    r = np.array(ratios)
    hits = int(np.sum(r >= MIN_SNR))
    upper = float(scipy.stats.beta.ppf(0.95, hits + 1, len(r) - hits))
    print(json.dumps({"chips": len(r), "above_threshold": hits, "max_snr": float(r.max()),
                      "quantiles": {q: float(np.quantile(r, q)) for q in (0.5, 0.9, 0.99)},
                      "binomial_95_upper_per_chip": upper, "rayleigh_bound_per_chip": false_alarm_bound()}))


if __name__ == "__main__":
    main()
