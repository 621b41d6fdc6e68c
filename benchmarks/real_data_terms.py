"""Fitting the standard sensor-model terms to the real MIMU4444BT captures, cross-validated (issue 6).

For each of the six captures in ../shared/data/openshoe_mimu4444bt/: fit positions,
accelerometer and gyroscope gain / misalignment / bias and time offsets
(``fit_terms``, the engine behind ``imu-array calibrate fit``) on the whole capture,
starting from config/mimu4444bt_corners.yaml.  Then

* per IMU and parameter: the estimates across the six captures (mean, spread =
  standard deviation across captures, median reported std = CRB), and their ratio
  spread / reported std (about 1 if the term is repeatable and the CRB honest);
* held out: the NIS ratio (still and moving, as ``imu-array residuals`` prints it)
  of every *other* capture fused with the fitted description, against the nominal.

Writes benchmarks/results/real_data_terms.md (and the fitted descriptions to
benchmarks/results/real_data_terms/exp_N.yaml, for inspection).

    python -m benchmarks.real_data_terms
    python -m benchmarks.real_data_terms --without time_offset   # -> real_data_terms_without_time_offset.md
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, write_results
from imu_array_ros.fitting.engine import fit_terms
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.fusion.residuals import normalized_residuals
from imu_array_ros.io.openshoe.capture import import_capture
from imu_array_ros.model.description import load_description, save_description
from imu_array_ros.model.sensor_model import SensorModel

OUT = RESULTS
STANDARD = ("position", "accelerometer_gain", "accelerometer_misalignment", "accelerometer_bias",
            "gyroscope_gain", "gyroscope_misalignment", "gyroscope_bias", "time_offset")


def nis(samples, model: SensorModel, desc) -> tuple[float, float]:
    """(still, moving) NIS ratios of ``samples`` fused and analysed with ``model``."""
    fusion = ModelFusion(model, acc_range=desc.accelerometer_range, gyro_range=desc.gyroscope_range)
    fused, _ = fusion.fuse(samples)
    s = normalized_residuals(samples, model, fused).summary()
    return s["still"]["ratio_all"], s["moving"]["ratio_all"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--without", default="", help="comma-separated standard terms to leave out")
    args = ap.parse_args()
    without = [t for t in args.without.split(",") if t]
    terms = tuple(t for t in STANDARD if t not in without)
    tag = "real_data_terms" + "".join(f"_without_{t}" for t in without)
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    nominal = SensorModel.from_description(desc)
    paths = sorted(DATA.glob("exp_*.bin"))
    captures = {p.stem: import_capture(p, desc)[0] for p in paths}
    fits, lines = {}, []
    (OUT / tag).mkdir(exist_ok=True)
    for name, samples in captures.items():
        t0 = time.perf_counter()
        fit = fit_terms(samples, nominal, terms)
        dt = time.perf_counter() - t0
        fits[name] = fit
        save_description(fit.model.to_description(desc, names=terms, stds=fit.std), OUT / tag / f"{name}.yaml")
        line = (f"| {name} | {len(samples)} | {fit.samples_used} | {fit.iterations} | {fit.converged} | "
                f"{fit.nis_before:.3g} | {fit.nis_after:.3g} | {dt:.1f} |")
        lines.append(line)
        print(line, flush=True)

    # held-out NIS: fitted on capture a, scored on capture b != a
    names = list(captures)
    base = {b: nis(captures[b], nominal, desc) for b in names}
    cross = {(a, b): nis(captures[b], fits[a].model, desc) for a in names for b in names if a != b}
    own = {a: nis(captures[a], fits[a].model, desc) for a in names}

    text = machine_header("Standard sensor-model terms fitted to the real MIMU4444BT captures")
    text += ("Terms fitted jointly with the motion on each whole capture (static poses and twisting): "
             + ", ".join(f"`{t}`" for t in terms) + ". Start: `config/mimu4444bt_corners.yaml`. "
             "Gauge: the engine's default (reference imu_1; see `held`).\n\n"
             "## Fits\n\nNIS per degree of freedom of the joint fit, before (nominal terms, motion fitted) and after.\n\n"
             "| capture | samples | used | iterations | converged | NIS/dof before | after | seconds |\n"
             "|---|---|---|---|---|---|---|---|\n" + "\n".join(lines) + "\n\n")
    text += "Held: " + ", ".join(fits[names[0]].held) + "\n\n"
    text += ("## Held-out fit\n\nNIS ratio of capture b (rows) fused and analysed with the nominal description, with "
             "the description fitted on b itself, and with those fitted on each other capture a != b "
             "(median and range over the five), as `imu-array residuals` prints it.\n\n"
             "| capture b | nominal still | nominal moving | own fit still | own fit moving "
             "| other fits still: median (min-max) | other fits moving: median (min-max) |\n"
             "|---|---|---|---|---|---|---|\n")
    for b in names:
        st = [cross[a, b][0] for a in names if a != b]
        mv = [cross[a, b][1] for a in names if a != b]
        text += (f"| {b} | {base[b][0]:.3g} | {base[b][1]:.3g} | {own[b][0]:.3g} | {own[b][1]:.3g} | "
                 f"{np.median(st):.3g} ({min(st):.3g}-{max(st):.3g}) | {np.median(mv):.3g} ({min(mv):.3g}-{max(mv):.3g}) |\n")

    text += ("\n## Repeatability across the six captures\n\nPer term, over IMUs and parameters (held ones left out): "
             "RMS of the estimate's change from nominal, RMS spread across captures (std over the six fits), "
             "median reported std (CRB), and the median over parameters of spread / reported std "
             "(~1: repeatable to the CRB; >> 1: the estimate moves from capture to capture more than its CRB says).\n\n"
             "| term | unit | RMS change from nominal | RMS spread across captures | median reported std "
             "| median spread / std |\n|---|---|---|---|---|---|\n")
    per_imu = ""
    for term in terms:
        vals = np.stack([fits[n].model.terms[term].values for n in names])  # (6, K, P)
        stds = np.stack([fits[n].std[term] for n in names])
        change = vals - nominal.terms[term].values
        spread = vals.std(axis=0, ddof=1)
        held = ~np.isfinite(stds).any(axis=0)
        med_std = np.nanmedian(np.where(held, 1.0, stds), axis=0)
        ok = ~held & (med_std > 0)
        unit = type(nominal.terms[term]).fields[0].unit
        text += (f"| {term} | {unit} | {np.sqrt(np.mean(change[:, ok] ** 2)):.3g} | {np.sqrt(np.mean(spread[ok] ** 2)):.3g} "
                 f"| {np.median(med_std[ok]):.3g} | {np.median(spread[ok] / med_std[ok]):.3g} |\n")
        rows = []
        pnames = type(nominal.terms[term]).parameter_names()
        for k, imu in enumerate(nominal.names):
            cells = [f"{vals[:, k, p].mean():.4g} ± {spread[k, p]:.2g} (σ {med_std[k, p]:.2g})" if ok[k, p] else "held"
                     for p in range(vals.shape[2])]
            rows.append(f"| {imu} | " + " | ".join(cells) + " |")
        per_imu += (f"\n### {term}\n\nmean over captures ± spread (σ: median reported std)\n\n| IMU | "
                    + " | ".join(pnames) + " |\n|---|" + "---|" * len(pnames) + "\n" + "\n".join(rows) + "\n")
    text += "\n## Per IMU\n" + per_imu
    write_results(OUT / f"{tag}.md", text)
    print(f"wrote {OUT / f'{tag}.md'}")


if __name__ == "__main__":
    main()
