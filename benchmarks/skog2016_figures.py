"""Monte Carlo reproduction of skog2016 Fig. 5 and Fig. 6 as tables.

Fig. 5: planar 4-triad array (config/planar4.yaml geometry, 2 cm square),
sigma_s = 0.01 m/s^2, sigma_w = 1 deg/s, gyros saturating at 2000 deg/s,
rotation about x (a) and about z (b), 0-3000 deg/s.  Fig. 6: non-planar
4-triad array (tetrahedron), rotation about [1,1,1], ML vs the tensor method.
Each point: 20,000 realizations (the paper used 1e5).  Writes
benchmarks/results/skog2016_figures.md.

    python -m benchmarks.skog2016_figures
"""

from __future__ import annotations

import numpy as np

from benchmarks.harness import RESULTS, machine_header, write_results
from imu_array_ros.fusion.crb import crb
from imu_array_ros.fusion.ml_fusion import MLFusion
from imu_array_ros.fusion.tensor_method import tensor_method
from imu_array_ros.model.layouts import planar_square4, tetrahedron4
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.simulation.motion import random_motion
from imu_array_ros.simulation.simulator import simulate_measurements

NOISE = dict(accelerometer_noise_std=0.01, gyroscope_noise_std=float(np.deg2rad(1.0)))
N = 20000


def curve(desc, direction, speeds, rng, tensor=False):
    model = LinearArrayModel.from_description(desc)
    fusion = MLFusion(model)
    rows = []
    for speed in speeds:
        truth = random_motion(N, np.deg2rad(speed), np.deg2rad(1000.0), rng, omega_direction=direction)
        s = simulate_measurements(desc, truth, rng)
        f, _ = fusion.fuse(s)
        rmse = np.rad2deg(np.sqrt(np.mean((f.omega - truth.omega) ** 2, axis=0)))
        bound = np.rad2deg(np.sqrt(np.diag(crb(truth.omega[:1], model, gyro_valid=model.gyro_unsaturated(s.gyro[:1]))[0])[:3]))
        row = [speed, *rmse, *bound]
        if tensor:
            wt, _, _ = tensor_method(s, model)
            row += list(np.rad2deg(np.sqrt(np.mean((wt - truth.omega) ** 2, axis=0))))
        rows.append(row)
        print(" ".join(f"{v:.4g}" for v in row), flush=True)
    return rows


def main() -> None:
    rng = np.random.default_rng(2016)
    text = machine_header("skog2016 Fig. 5 and Fig. 6, Monte Carlo")
    text += f"{N} realizations per speed; RMSE and sqrt(CRB) per axis in deg/s. Plain averaging of the 4 gyroscopes: {1.0 / 2:.3f} deg/s per axis.\n"
    speeds = list(range(0, 3001, 250))
    for label, direction in (("Fig. 5(a): planar array, rotation about x", [1, 0, 0]),
                             ("Fig. 5(b): planar array, rotation about z", [0, 0, 1])):
        rows = curve(planar_square4(**NOISE), direction, speeds, rng)
        text += f"\n## {label}\n\n| deg/s | RMSE x | RMSE y | RMSE z | sqrt CRB x | sqrt CRB y | sqrt CRB z | max RMSE/sqrtCRB - 1 |\n|---|---|---|---|---|---|---|---|\n"
        for r in rows:
            dev = max(abs(r[i] / r[i + 3] - 1) for i in (1, 2, 3))
            text += f"| {r[0]} | " + " | ".join(f"{v:.4f}" for v in r[1:7]) + f" | {100 * dev:.1f} % |\n"
    speeds6 = list(range(0, 5001, 500))
    rows = curve(tetrahedron4(**NOISE), [1, 1, 1], speeds6, rng, tensor=True)
    text += ("\n## Fig. 6: non-planar array, rotation about [1,1,1]/sqrt(3) (all gyro axes saturate above 3464 deg/s)\n\n"
             "| deg/s | RMSE ML (x) | sqrt CRB (x) | RMSE tensor (x) | tensor / ML (mean of axes) |\n|---|---|---|---|---|\n")
    for r in rows:
        ratio = np.mean([r[7 + i] / r[1 + i] for i in range(3)])
        text += f"| {r[0]} | {r[1]:.4f} | {r[4]:.4f} | {r[7]:.4f} | {ratio:.3f} |\n"
    print(f"wrote {write_results(RESULTS / 'skog2016_figures.md', text)}")


if __name__ == "__main__":
    main()
