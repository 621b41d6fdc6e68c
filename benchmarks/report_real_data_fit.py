"""How well the nominal model explains the real MIMU4444BT captures (issue 2, section 6).

For every ../shared/data/openshoe_mimu4444bt/exp_*.bin: import, fuse with the
nominal description config/mimu4444bt_corners.yaml, and compute the normalised
residual ratio (observed / expected NIS, see imu_array_ros.residuals) by IMU
and axis, still vs moving; next to it the same figure for a simulated
recording of the same (fused) motion measured by the nominal model.
Writes benchmarks/results/real_data_fit.md.

    python benchmarks/report_real_data_fit.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_header  # noqa: E402

from imu_array_ros.description import load_description  # noqa: E402
from imu_array_ros.fusion import MLFusion  # noqa: E402
from imu_array_ros.openshoe_import import import_capture  # noqa: E402
from imu_array_ros.residuals import normalized_residuals, simulate_same_motion  # noqa: E402
from imu_array_ros.sensor_model import LinearArrayModel  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"


def main() -> None:
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    model = LinearArrayModel.from_description(desc)
    fusion = MLFusion(model)
    rows, tables = [], ""
    for i, path in enumerate(sorted(DATA.glob("exp_*.bin"))):
        samples, _ = import_capture(path, desc)
        fused, stats = fusion.fuse(samples.stamps, samples.accel, samples.gyro)
        real = normalized_residuals(samples, model, fused)
        sim_samples = simulate_same_motion(fused, model, np.random.default_rng(i), like=samples)
        sim_fused, _ = fusion.fuse(sim_samples.stamps, sim_samples.accel, sim_samples.gyro)
        sim = normalized_residuals(sim_samples, model, sim_fused)
        r, s = real.summary(), sim.summary()
        rows.append(
            f"| {path.name} | {stats.fused}/{stats.samples} | {stats.saturated_gyro_samples} "
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
        "| capture | fused | saturated-gyro samples | still samples | still acc ratio | still gyro ratio "
        "| still, simulated | moving samples | moving acc ratio | moving gyro ratio | moving, simulated |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    text += "".join(rows) + tables
    out = REPO / "benchmarks" / "results" / "real_data_fit.md"
    out.write_text(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
