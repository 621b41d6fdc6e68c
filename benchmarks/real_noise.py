"""Noise characterisation (``calibrate noise``) on the six real MIMU4444BT captures (issue 22, item 5).

For each capture in ../shared/data/openshoe_mimu4444bt/ (``import_capture``, config/mimu4444bt_corners.yaml):
the still intervals (``find_still_poses``, >= 5 s), the Allan deviation per IMU and axis and the figures read
from it (:func:`imu_array_ros.calibration.noise.characterise_noise`).  Tables: per IMU and axis the mean over
the captures of noise_std (and of the per-sample std), its spread across the captures (min-max and the
coefficient of variation), how often the random walk and the bias instability were seen and their values.
Writes benchmarks/results/real_noise.md and real_noise.png (the Allan deviation of exp_1).

    python -m benchmarks.real_noise
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, write_results
from imu_array_ros.calibration.noise import SENSORS, characterise_noise
from imu_array_ros.calibration.noise_plots import plot_noise
from imu_array_ros.io.openshoe.capture import import_capture
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

ARRAY = REPO / "config" / "mimu4444bt_corners.yaml"


def main() -> None:
    desc = load_description(ARRAY)
    model = SensorModel.from_description(desc)
    caps = sorted(DATA.glob("exp_*.bin"))
    results, seconds = {}, {}
    for path in caps:
        samples = import_capture(path, desc)[0]
        t0 = time.perf_counter()
        results[path.stem] = characterise_noise(samples, model)
        seconds[path.stem] = time.perf_counter() - t0
        print(path.stem, results[path.stem].summary(), flush=True)
    names = desc.names
    first = results[caps[0].stem]
    plot_noise(first, RESULTS / "real_noise.png")
    text = machine_header("Noise characterisation on the real MIMU4444BT captures (calibrate noise)", extra=[
        f"captures: {', '.join(results)}; array {ARRAY.relative_to(REPO)}; still intervals >= 5 s",
        "time per capture (Allan deviations and fits, 8 IMUs x 6 axes): "
        + ", ".join(f"{c} {s:.1f} s" for c, s in seconds.items())])
    text += "| capture | still intervals | still s | rate Hz | accelerometer tau range s | gyroscope tau range s |\n"
    text += "|---|---|---|---|---|---|\n"
    for c, r in results.items():
        rng = lambda sensor: f"{min(s.tau_range[0] for s in r.sensors[sensor]):.3g}-{max(s.tau_range[1] for s in r.sensors[sensor]):.3g}"  # noqa: E731
        text += f"| {c} | {len(r.intervals)} | {r.still_seconds:.0f} | {r.rate:.4g} | {rng('accelerometer')} | {rng('gyroscope')} |\n"
    for sensor, unit in SENSORS.items():
        ns = np.array([[r.sensors[sensor][k].noise_std for k in range(len(names))] for r in results.values()])
        ps = np.array([[r.sensors[sensor][k].per_sample_std for k in range(len(names))] for r in results.values()])
        sd = np.array([[r.sensors[sensor][k].noise_std_std for k in range(len(names))] for r in results.values()])
        rw = np.array([[r.sensors[sensor][k].random_walk for k in range(len(names))] for r in results.values()])
        bi = np.array([[r.sensors[sensor][k].instability for k in range(len(names))] for r in results.values()])
        bound = np.array([[r.sensors[sensor][k].instability_bound for k in range(len(names))] for r in results.values()])
        text += (f"\n## {sensor}: noise_std = N sqrt(rate), {unit} per sample, across the {len(results)} captures\n\n"
                 "mean (min-max) over the captures; CV: std / mean across the captures; stated: the median stated "
                 "std of one capture's estimate / its value; per-sample: the std of the still readings, mean removed\n\n"
                 "| IMU | axis | noise_std mean (min-max) | CV | stated | per-sample std mean | random walk seen (values) "
                 "| bias instability seen (values) | bound min sigma/0.664 mean |\n|---|---|---|---|---|---|---|---|---|\n")
        for k, name in enumerate(names):
            for a, axis in enumerate("xyz"):
                v = ns[:, k, a]
                seen_rw, seen_bi = np.isfinite(rw[:, k, a]), np.isfinite(bi[:, k, a])
                vals = lambda x, m: ", ".join(f"{y:.2g}" for y in x[m]) or "-"  # noqa: E731
                text += (f"| {name} | {axis} | {v.mean():.4g} ({v.min():.4g}-{v.max():.4g}) | {v.std(ddof=1) / v.mean():.1%} "
                         f"| {np.median(sd[:, k, a] / v):.2%} | {ps[:, k, a].mean():.4g} | {seen_rw.sum()}/{len(v)} "
                         f"({vals(rw[:, k, a], seen_rw)}) | {seen_bi.sum()}/{len(v)} ({vals(bi[:, k, a], seen_bi)}) "
                         f"| {bound[:, k, a].mean():.3g} |\n")
        per_imu = ns.mean(axis=(0, 2))
        order = np.argsort(per_imu)[::-1]
        text += (f"\nPer IMU, mean over the captures and axes: "
                 + ", ".join(f"{names[k]} {per_imu[k]:.4g}" for k in order)
                 + f" {unit} (range {per_imu.min():.4g}-{per_imu.max():.4g}; RMS over axes: "
                 + ", ".join(f"{names[k]} {np.sqrt((ns[:, k] ** 2).mean()):.4g}" for k in order) + ").\n")
    text += "\n![Allan deviation, exp_1](real_noise.png)\n"
    write_results(RESULTS / "real_noise.md", text)


if __name__ == "__main__":
    main()
