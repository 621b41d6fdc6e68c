"""Static and whole-array calibration on the real MIMU4444BT captures, cross-validated (issue 9).

For each of the six captures in ../shared/data/openshoe_mimu4444bt/ (imported with
``import_capture`` and config/mimu4444bt_corners.yaml, reference imu_1):

* still poses (``find_still_poses``, default thresholds);
* static calibration three ways: ML with every nilsson2014 term ("full"), ML without the
  misalignment ("per-IMU", nilsson2014's reduced calibration), and the closed-form PCA;
* ``calibrate_array`` ("calibrate all": static stage, then positions and gyroscope gain and
  misalignment on the moving phase).

Held out, for every calibration capture c and every other capture d (30 pairs):
* nilsson2014's consistency figure on d's poses, in dB, of c's calibration vs the nominal
  array and vs c's per-IMU calibration;
* the NIS ratio (observed / expected, still and moving samples, as ``imu-array residuals``
  prints it) of d's whole recording under c's ``calibrate all`` description, and under nominal.

Also the repeatability of the parameters across the six captures (mean (range), nilsson2014
Table I style) and PCA vs ML time.  Writes benchmarks/results/real_data_static.md and .png.

    python -m benchmarks.real_data_static
"""

from __future__ import annotations

import time

import numpy as np

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, write_results
from imu_array_ros.calibration.array import calibrate_array
from imu_array_ros.calibration.static import calibrate_static, consistency_db
from imu_array_ros.calibration.still import find_still_poses
from imu_array_ros.errors import MissingDependencyError
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.fusion.residuals import normalized_residuals
from imu_array_ros.io.openshoe.capture import import_capture
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

OUT = RESULTS
REDUCED = ("accelerometer_gain", "accelerometer_nonorthogonality", "accelerometer_bias", "gyroscope_bias")


def nis_ratio(samples, model: SensorModel, desc) -> tuple[float, float]:
    """(still, moving) NIS ratio observed / expected of the whole recording, as ``imu-array residuals``."""
    fusion = ModelFusion(model, acc_range=desc.accelerometer_range, gyro_range=desc.gyroscope_range)
    fused, _ = fusion.fuse(samples)
    rep = normalized_residuals(samples, model, fused)
    return tuple(float(rep.observed[r].sum() / rep.expected[r].sum()) for r in ("still", "moving"))


def main() -> None:
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    nominal = SensorModel.from_description(desc)
    caps = sorted(DATA.glob("exp_*.bin"))
    if not caps:
        raise SystemExit(f"no captures in {DATA}")
    lines = []
    log = lambda text: (print(text, flush=True), lines.append(text))  # noqa: E731
    samples, poses, fits, times = {}, {}, {}, {}
    for path in caps:
        c = path.stem
        samples[c] = import_capture(path, desc)[0]
        s = samples[c]
        poses[c] = p = find_still_poses(s, nominal)
        fits[c], times[c] = {}, {}
        for label, kw in (("full", {}), ("per-IMU", {"terms": REDUCED}), ("pca", {"method": "pca"})):
            t0 = time.process_time()
            fits[c][label] = calibrate_static(p.accel, p.gyro, p.counts, nominal, **kw)
            times[c][label] = time.process_time() - t0
        t0 = time.process_time()
        fits[c]["all"] = calibrate_array(s, nominal)
        times[c]["all"] = time.process_time() - t0
        log(f"{c}: {len(p)} poses ({p.spread()['min_eigenvalue']:.3f} min eigenvalue), "
            f"{len(p.rejected)} rejected; full: {fits[c]['full'].summary()}; all: {fits[c]['all'].summary()}")
    names = list(caps and [p.stem for p in caps])
    # held-out consistency and NIS
    rows, nis_rows = [], []
    base_nis = {d: nis_ratio(samples[d], nominal, desc) for d in names}
    for c in names:
        for d in names:
            if d == c:
                continue
            a = poses[d].accel
            rows.append((c, d, consistency_db(a, fits[c]["full"].model, nominal),
                         consistency_db(a, fits[c]["full"].model, fits[c]["per-IMU"].model),
                         consistency_db(a, fits[c]["pca"].model, nominal),
                         consistency_db(a, fits[c]["all"].model, nominal)))
            nis_rows.append((c, d, *nis_ratio(samples[d], fits[c]["all"].model, desc), *base_nis[d]))
        log(f"held out from {c}: done")
    vs_nom = np.array([r[2] for r in rows])
    vs_red = np.array([r[3] for r in rows])
    vs_pca = np.array([r[4] for r in rows])
    vs_all = np.array([r[5] for r in rows])
    worst = rows[int(np.argmin(vs_nom))]

    md = [machine_header("Static and whole-array calibration on the real MIMU4444BT captures (issue 9)")]
    md.append("Six captures of the real 8-IMU array (`../shared/data/openshoe_mimu4444bt/`), description "
              "`config/mimu4444bt_corners.yaml`, reference imu_1, gravity 9.80665 m/s^2, default still-pose "
              "thresholds. Every calibration uses one capture; every score is on another (held out).\n\n")
    md.append("## Poses found and fits per capture\n\n| capture | poses | rejected | min eigenvalue | coverage (deg) | "
              "ML iterations | NIS after (ML) | down-weighted | ML CPU s | PCA CPU s | all CPU s | moving samples used |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for c in names:
        p, f, a = poses[c], fits[c]["full"], fits[c]["all"]
        sp = p.spread()
        md.append(f"| {c} | {len(p)} | {len(p.rejected)} | {sp['min_eigenvalue']:.3f} | {sp['coverage_deg']:.1f} | "
                  f"{f.iterations} | {f.nis_after:.3g} | {len(f.downweighted())} | {times[c]['full']:.2f} | "
                  f"{times[c]['pca']:.2f} | {times[c]['all']:.1f} | {a.moving_samples[0]} of {a.moving_samples[1]} |\n")
    md.append("\n## Held-out consistency (nilsson2014's figure, dB; positive = more consistent)\n\n"
              "30 pairs (calibrate on c, score the poses of d != c).\n\n"
              "| calibration | vs | median | worst | best |\n|---|---|---|---|---|\n")
    for label, v, vs in (("ML, every term", vs_nom, "nominal"), ("ML, every term", vs_red, "ML per-IMU (no misalignment)"),
                         ("PCA", vs_pca, "nominal"), ("calibrate all", vs_all, "nominal")):
        md.append(f"| {label} | {vs} | {np.median(v):.1f} | {v.min():.1f} | {v.max():.1f} |\n")
    md.append(f"\nTarget (issue 9): median >= 20 dB held out vs nominal: **{'met' if np.median(vs_nom) >= 20 else 'NOT met'}** "
              f"({np.median(vs_nom):.1f} dB); worst pair {worst[0]} -> {worst[1]}: {worst[2]:.1f} dB. "
              f"nilsson2014 reports -23 dB for its full vs per-IMU calibration on its own array; here "
              f"{np.median(vs_red):.1f} dB (median).\n")
    md.append("\n## Held-out NIS ratio after `calibrate all` (observed / expected, as `imu-array residuals`)\n\n"
              "| calibrated on | scored on | still | moving | still, nominal | moving, nominal |\n|---|---|---|---|---|---|\n")
    for c, d, s1, m1, s0, m0 in nis_rows:
        md.append(f"| {c} | {d} | {s1:.3g} | {m1:.4g} | {s0:.3g} | {m0:.4g} |\n")
    st = np.array([r[2] for r in nis_rows])
    mv = np.array([r[3] for r in nis_rows])
    st0 = np.array([r[4] for r in nis_rows])
    mv0 = np.array([r[5] for r in nis_rows])
    md.append(f"\nMedian over the 30 pairs: still {np.median(st):.3g} (nominal {np.median(st0):.3g}), moving "
              f"{np.median(mv):.4g} (nominal {np.median(mv0):.4g}).\n")
    # repeatability, Table I style
    md.append("\n## Repeatability across the six captures (ML, every term): mean (range)\n\n"
              "| IMU | k_x | k_y | k_z | b_x (m/s^2) | b_y | b_z | l_yz (deg) | l_zy | l_zx | xi_x (deg) | xi_y | xi_z |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    terms = (("accelerometer_gain", 1.0, "{:.4f} ({:.1e})"), ("accelerometer_bias", 1.0, "{:.3f} ({:.1e})"),
             ("accelerometer_nonorthogonality", 180 / np.pi, "{:.2f} ({:.1e})"),
             ("accelerometer_misalignment", 180 / np.pi, "{:.2f} ({:.1e})"))
    for k, name in enumerate(nominal.names):
        cells = []
        for t, scale, fmt in terms:
            v = np.array([fits[c]["full"].model.terms[t].values[k] for c in names]) * scale
            cells += [fmt.format(v[:, j].mean(), np.ptp(v[:, j])) for j in range(3)]
        md.append(f"| {name} | " + " | ".join(cells) + " |\n")
    md.append("\n## Log\n\n```\n" + "\n".join(lines) + "\n```\n")
    write_results(OUT / "real_data_static.md", "".join(md))
    try:
        from imu_array_ros.util.plotting import pyplot, save_png

        plt = pyplot(OUT / "real_data_static.png")
        fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
        a1.boxplot([vs_nom, vs_red, vs_pca, vs_all])
        a1.set_xticks([1, 2, 3, 4], ["ML vs nominal", "ML vs per-IMU", "PCA vs nominal", "all vs nominal"],
                      fontsize=8)
        a1.axhline(20, color="C3", ls="--", lw=0.8)
        a1.set_ylabel("held-out consistency gain (dB)")
        a2.scatter(mv0, mv, s=12, label="moving")
        a2.scatter(st0, st, s=12, label="still")
        lim = [min(st.min(), mv.min(), st0.min()) / 2, max(mv0.max(), mv.max()) * 2]
        a2.plot(lim, lim, color="0.6", lw=0.8)
        a2.set_xscale("log"), a2.set_yscale("log")
        a2.set_xlabel("NIS ratio, nominal"), a2.set_ylabel("NIS ratio, calibrate all (held out)")
        a2.legend()
        fig.tight_layout()
        save_png(fig, OUT / "real_data_static.png")
    except MissingDependencyError:  # matplotlib is an extra: the tables are written anyway
        pass
    print(f"wrote {OUT / 'real_data_static.md'}")


if __name__ == "__main__":
    main()
