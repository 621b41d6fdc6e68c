"""How well the nominal model explains the real MIMU4444BT captures (issue 2, section 6).

For every ../shared/data/openshoe_mimu4444bt/exp_*.bin: import, fuse with the
nominal description config/mimu4444bt_corners.yaml, and compute the normalised
residual ratio (observed / expected NIS, see imu_array_ros.fusion.residuals) by IMU
and axis, still vs moving; next to it the same figure for a simulated
recording of the same (fused) motion measured by the nominal model.
Writes benchmarks/results/real_data_fit.md.

    python -m benchmarks.report_real_data_fit
"""

from __future__ import annotations

import numpy as np

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, write_results
from imu_array_ros.fusion.ml_fusion import MLFusion
from imu_array_ros.fusion.residuals import normalized_residuals
from imu_array_ros.io.openshoe.capture import import_capture
from imu_array_ros.io.openshoe.framing import si_saturation_level
from imu_array_ros.model.description import load_description
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_same_motion


def range_extension(samples, fused, model) -> str:
    """One table row on fusion beyond the gyro range (skog2016 Fig. 3), as test_real_data_fusion checks it."""
    gyro = samples.gyro[np.searchsorted(samples.stamps, fused.stamps)]
    clipped = np.abs(gyro) >= si_saturation_level()[1] * (1 - 1e-9)  # from the raw full-scale counts
    sat_sample = clipped.any(axis=(1, 2))
    axes = clipped[:, 0, :]  # imu_1, identity-mounted: its axes are array axes
    cells = []
    for sign in (1, -1):
        c = np.abs(fused.omega[axes & (np.sign(gyro[:, 0, :]) == sign)]) / model.gyro_range
        cells.append(f"{np.median(c):.3f} / {np.mean(c > 1.01):.2f}")
    step = np.linalg.norm(np.diff(fused.omega, axis=0), axis=1)
    edges = np.flatnonzero(np.diff(sat_sample.astype(int)) != 0)
    fast = (np.linalg.norm(fused.omega[1:], axis=1) > 20) & ~sat_sample[1:] & ~sat_sample[:-1]
    sign_ok = np.mean(np.sign(fused.omega[axes]) == np.sign(gyro[:, 0, :][axes]))
    return (f"| {int(sat_sample.sum())} | {np.linalg.norm(fused.omega[sat_sample], axis=1).max():.1f} | {cells[0]} | {cells[1]} "
            f"| {sign_ok:.4f} | {np.median(step[edges]):.1f} | {np.median(step[fast]):.1f} |")


def main() -> None:
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    sensor_model = SensorModel.from_description(desc)
    model = LinearArrayModel.from_sensor_model(sensor_model, desc.accelerometer_range, desc.gyroscope_range)
    fusion = MLFusion(model)
    rows, ext_rows, tables = [], [], ""
    for i, path in enumerate(sorted(DATA.glob("exp_*.bin"))):
        samples, _ = import_capture(path, desc)
        fused, stats = fusion.fuse(samples)
        real = normalized_residuals(samples, sensor_model, fused)
        sim_samples = simulate_same_motion(fused, sensor_model, np.random.default_rng(i), like=samples)
        sim_fused, _ = fusion.fuse(sim_samples)
        sim = normalized_residuals(sim_samples, sensor_model, sim_fused)
        r, s = real.summary(), sim.summary()
        ext_rows.append(f"| {path.name} " + range_extension(samples, fused, model) + "\n")
        rows.append(
            f"| {path.name} | {stats.fused}/{stats.samples} | {stats.saturated_accel_samples} | {stats.saturated_gyro_samples} "
            f"| {r['still']['samples']} | {r['still']['ratio_accelerometers']:.3g} | {r['still']['ratio_gyroscopes']:.3g} "
            f"| {s['still']['ratio_all']:.3f} "
            f"| {r['moving']['samples']} | {r['moving']['ratio_accelerometers']:.3g} | {r['moving']['ratio_gyroscopes']:.3g} "
            f"| {s['moving']['ratio_all']:.3f} |\n"
        )
        print(rows[-1], end="", flush=True)
        if i == 0:
            for regime in ("still", "moving"):
                tables += f"\n### {path.name}, {regime}: real recording, ratio by IMU and axis\n\n" + real.table(regime)
                tables += f"\n### {path.name}, {regime}: simulated same motion\n\n" + sim.table(regime)
    text = machine_header("Real MIMU4444BT captures vs the nominal model")
    text += (
        "Ratio = sum of squared normalised residuals / its expected value under the model "
        "(1 = the model explains the data to the noise level). Still: |omega_hat| < 0.2 rad/s. "
        "Saturated gyro axes are excluded from the likelihood and from the residuals.\n\n"
        "| capture | fused | saturated-accel samples | saturated-gyro samples | still samples | still acc ratio "
        "| still gyro ratio | still, simulated | moving samples | moving acc ratio | moving gyro ratio | moving, simulated |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    text += "".join(rows)
    text += (
        "\n## Beyond the gyro range (skog2016 Fig. 3)\n\n"
        "Clipped = raw count at full scale. Columns: samples with a clipped gyro; max fused |omega| (rad/s) among them; "
        "on imu_1's clipped axes (identity-mounted, so array axes), median |fused component| / gyroscope_range and the "
        "share above 1.01, for +32767 and -32768 clipping; share with the clipped gyro's sign; median |step| of the fused "
        "omega (rad/s per sample) where saturation starts/ends vs between unsaturated samples with |omega| > 20 rad/s.\n\n"
        "| capture | clipped samples | max |omega| | + clip: median / >1.01 | - clip: median / >1.01 | sign agrees "
        "| step at edges | step, fast unsaturated |\n|---|---|---|---|---|---|---|---|\n"
    )
    text += "".join(ext_rows) + tables
    print(f"wrote {write_results(RESULTS / 'real_data_fit.md', text)}")


if __name__ == "__main__":
    main()
