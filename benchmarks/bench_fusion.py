"""Array samples fused per second (32-IMU array), batch vs one sample at a time, and memory.

Target (issue 2): >= 200,000 array samples/s in batch on one core, memory linear
in the number of samples.  Runs single-threaded BLAS (OMP/OPENBLAS threads = 1)
so the figure is per core.  Writes benchmarks/results/fusion.md.

    python benchmarks/bench_fusion.py [--samples 200000]
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_header  # noqa: E402

from imu_array_ros.model.layouts import grid_array32  # noqa: E402
from imu_array_ros.estimation.ml_fusion import MLFusion  # noqa: E402
from imu_array_ros.model.sensor_model import LinearArrayModel  # noqa: E402
from imu_array_ros.simulation.simulator import simulate_random, simulate_twist  # noqa: E402
from imu_array_ros.estimation.tensor_method import tensor_method  # noqa: E402


def best_of(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "fusion.md"))
    args = ap.parse_args()
    rng = np.random.default_rng(7)
    desc = grid_array32()
    model = LinearArrayModel.from_description(desc)
    fusion = MLFusion(model)
    n = args.samples

    cases = {
        "twisting, 600 deg/s RMS (no saturation)": simulate_twist(desc, n / 1000.0, 1000.0, rng)[0],
        "random, |w| = 1000 deg/s": simulate_random(desc, n, np.deg2rad(1000), np.deg2rad(2000), rng)[0],
        "random, |w| = 3000 deg/s (most gyros saturated)": simulate_random(desc, n, np.deg2rad(3000), np.deg2rad(2000), rng)[0],
    }
    rows = []
    for label, s in cases.items():
        fusion.fuse(s.stamps[:100], s.accel[:100], s.gyro[:100])  # warm the geometry cache
        t_batch = best_of(lambda: fusion.fuse(s.stamps, s.accel, s.gyro))
        t_tensor = best_of(lambda: tensor_method(s, model))  # same-run baseline: closed-form least squares
        m = 2000
        t_one = best_of(lambda: [fusion.fuse(s.stamps[i:i + 1], s.accel[i:i + 1], s.gyro[i:i + 1]) for i in range(m)], 1)
        rows.append((label, n / t_batch, n / t_tensor, t_batch / t_tensor, m / t_one))
        print(f"{label}: batch {n / t_batch:,.0f} samples/s (tensor method {n / t_tensor:,.0f}/s, ML/tensor time "
              f"{t_batch / t_tensor:.2f}), one-at-a-time {m / t_one:,.0f} samples/s", flush=True)

    mem_rows = []
    s = cases["twisting, 600 deg/s RMS (no saturation)"]
    for k in (n // 4, n // 2, n):
        tracemalloc.start()
        fusion.fuse(s.stamps[:k], s.accel[:k], s.gyro[:k])
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        inputs = s.accel[:k].nbytes + s.gyro[:k].nbytes
        mem_rows.append((k, peak, inputs))
        print(f"N={k}: peak {peak / 1e6:.1f} MB ({peak / k:.0f} B/sample; inputs {inputs / k:.0f} B/sample)", flush=True)

    text = machine_header("Fusion throughput, 32-IMU array")
    text += "Single core (BLAS threads = 1), best of 3 for batch; one-at-a-time = 2,000 calls of `MLFusion.fuse` with one sample.\n\n"
    text += ("Same-run baseline: the tensor method (skog2016 appendix, one closed-form least-squares solve per "
             "batch) on the same samples; the ratio is the machine-independent figure.\n\n")
    text += ("| case | ML batch (array samples/s) | tensor method (samples/s) | ML time / tensor time "
             "| ML, one sample per call (samples/s) |\n|---|---|---|---|---|\n")
    text += "".join(f"| {a} | {b:,.0f} | {c:,.0f} | {d:.2f} | {e:,.0f} |\n" for a, b, c, d, e in rows)
    text += "\nTarget: >= 200,000 array samples/s in batch.\n\n"
    text += "Peak memory allocated by one `fuse` call (tracemalloc; the (N, 32, 3) inputs are not counted):\n\n"
    text += "| N | peak MB | bytes per sample |\n|---|---|---|\n"
    text += "".join(f"| {k} | {p / 1e6:.1f} | {p / k:.0f} |\n" for k, p, _ in mem_rows)
    per = [p / k for k, p, _ in mem_rows]
    text += f"\nBytes per sample vary by {100 * (max(per) / min(per) - 1):.1f} % across N: memory is linear in N.\n"
    Path(args.out).write_text(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
