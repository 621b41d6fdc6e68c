"""Time-aware calibration on the real MIMU4444BT captures, cross-validated (issue 21).

For each capture a of ``--fit`` (default exp_1, exp_3, exp_5): ``calibrate all`` (the workflow
``imu-array calibrate all`` runs) from config/mimu4444bt_corners.yaml, once without the timing stage
(``timing=False``: today's calibration) and once with it (sample clocks searched at 1 ms, time offsets and
clock rates refitted with the moving terms).  Then every other capture b is scored with each: fused (the
time-aware one with its own session states, estimated by the fusion workflow) and its NIS ratio still and
moving computed against the description's white-noise figures, as ``imu-array residuals`` prints it.
Also: the chip clock rates found on each fitted capture, relative to the reference IMU (they should
repeat to a few ppm), and a plot of the estimated reading ages of one capture against time.

    python -m benchmarks.time_aware_real [--fit exp_1,exp_3,exp_5]

Writes benchmarks/results/time_aware_real.md (+ .json, _ages.png).
"""

from __future__ import annotations

import argparse
import json
import time

from benchmarks.harness import DATA, REPO, RESULTS, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import numpy as np  # noqa: E402

from imu_array_ros.calibration.methods import whole_array  # noqa: E402
from imu_array_ros.fusion.residuals import normalized_residuals  # noqa: E402
from imu_array_ros.io.openshoe.capture import import_capture  # noqa: E402
from imu_array_ros.model.description import load_description  # noqa: E402
from imu_array_ros.model.sensor_model import SensorModel  # noqa: E402
from imu_array_ros.timing.delays import reading_delays  # noqa: E402
from imu_array_ros.timing.sawtooth import sawtooth_delay  # noqa: E402
from imu_array_ros.workflows.fusion import session_fusion  # noqa: E402

OUT = RESULTS / "time_aware_real.md"


def nis(samples, model) -> tuple[float, float, dict | None]:
    """(still, moving) NIS ratios of ``samples`` fused with ``model`` (session states estimated first), and
    the session states' summary."""
    fusion, session = session_fusion(samples, model)
    fused, _ = fusion.fuse(samples)
    s = normalized_residuals(samples, fusion.model, fused).summary()
    return s["still"]["ratio_all"], s["moving"]["ratio_all"], None if session is None else session.summary()


def ages_plot(samples, model, path) -> None:
    """Estimated reading ages (relative reading delays of the time-unaware fit) and the fitted sawtooths."""
    from imu_array_ros.util.plotting import pyplot, save_png

    plt = pyplot(path)
    fusion, _ = session_fusion(samples, model)
    d = reading_delays(samples, model.with_terms(gyroscope_sample_clock=np.zeros((model.n_imus, 3))),
                       t0_ns=int(samples.stamps[0]), sensor="gyroscope")
    clock = fusion.model.terms["gyroscope_sample_clock"].values
    saw = sawtooth_delay(d.t, clock[:, 0], clock[:, 1], clock[:, 2])
    rel = d.relative()
    w = d.weights
    moving = np.flatnonzero(w.sum(axis=1) > 0)
    mid = d.t[moving[len(moving) // 2]] if len(moving) else 0.0
    sel = (d.t > mid) & (d.t < mid + 4.0) & (w.sum(axis=1) > 0)
    fig, axes = plt.subplots(4, 1, figsize=(11, 9), sharex=True)
    for ax, k in zip(axes, (0, 2, 4, 6)):
        s = saw[sel, k] - np.mean(saw[sel, k]) + np.mean(rel[sel, k])
        ax.plot(d.t[sel], rel[sel, k] * 1e6, ".", ms=3, label="reading delay from the residuals (no clock model)")
        ax.set_ylim(-1500, 1500)
        ax.plot(d.t[sel], s * 1e6, "-", lw=1, label=f"sample clock fitted: {clock[k, 1]:+.1f} ppm")
        ax.set_ylabel(f"{model.names[k]}\nµs")
        ax.legend(loc="upper right", fontsize=7)
    axes[-1].set_xlabel("s since the capture's first stamp")
    fig.suptitle("Gyroscope reading delay relative to the other IMUs while twisting (free-running ~1 kHz chip clocks)")
    save_png(fig, path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", default="exp_1,exp_3,exp_5", help="captures to calibrate on (comma-separated)")
    args = ap.parse_args()
    desc = load_description(REPO / "config" / "mimu4444bt_corners.yaml")
    nominal = SensorModel.from_description(desc)
    paths = sorted(DATA.glob("exp_*.bin"))
    say(f"reading {len(paths)} captures")
    captures = {p.stem: import_capture(p, desc)[0] for p in paths}
    fits = [f for f in args.fit.split(",") if f]
    cal, seconds = {}, {}
    for a in fits:
        for timing in (False, True):
            t0 = time.perf_counter()
            say(f"{a}: calibrate all, timing {timing}")
            c = whole_array(captures[a], nominal, timing=timing, progress=lambda text: None)
            seconds[a, timing] = time.perf_counter() - t0
            cal[a, timing] = c
            say(f"  {seconds[a, timing]:.0f} s: {c.summary_line[:300]}")
    rows, table = [], []
    for a in fits:
        for b in captures:
            if b == a:
                continue
            off = nis(captures[b], cal[a, False].model)
            on = nis(captures[b], cal[a, True].model)
            rows.append({"fit": a, "score": b, "unaware_still": off[0], "unaware_moving": off[1],
                         "aware_still": on[0], "aware_moving": on[1], "session": on[2]})
            say(f"  {a} -> {b}: moving {off[1]:.4g} -> {on[1]:.4g}, still {off[0]:.3g} -> {on[0]:.3g}")
            table.append(f"| {a} | {b} | {off[0]:.3g} | {on[0]:.3g} | {off[1]:.4g} | {on[1]:.4g} |")
    rates = {a: cal[a, True].model.terms["gyroscope_sample_clock"].values[:, 1] for a in fits}
    rel = {a: r - r[0] for a, r in rates.items()}
    spread = np.std(np.stack(list(rel.values())), axis=0, ddof=1) if len(fits) > 1 else np.full(8, np.nan)
    ages_plot(captures[fits[0]], cal[fits[0], True].model, RESULTS / "time_aware_real_ages.png")

    med = lambda key: float(np.median([r[key] for r in rows]))  # noqa: E731
    text = machine_header("Time-aware calibration on the real captures, cross-validated")
    text += ("Calibrated with `calibrate all` from `config/mimu4444bt_corners.yaml` on each capture of the first "
             "column, without and with the timing stage; scored on every other capture (fused with the calibration, "
             "the time-aware one with the capture's own session states estimated first). NIS ratio against the "
             "description's white-noise figures (1: explained to the noise), as `imu-array residuals` prints it.\n\n"
             "## Held-out NIS\n\n| fit on | scored on | still, without timing | still, with | moving, without timing "
             "| moving, with |\n|---|---|---|---|---|---|\n" + "\n".join(table) + "\n\n"
             f"Medians: still {med('unaware_still'):.3g} -> {med('aware_still'):.3g}; moving "
             f"{med('unaware_moving'):.4g} -> {med('aware_moving'):.4g}.\n\n")
    text += "## Calibrations\n\n| capture | timing | seconds | summary |\n|---|---|---|---|\n"
    for (a, timing), c in cal.items():
        text += f"| {a} | {timing} | {seconds[a, timing]:.0f} | {c.summary_line} |\n"
    text += ("\n## Chip clock rates\n\nRates found (ppm, relative to the stamps' clock) and relative to the reference "
             "IMU (imu_1), per fitted capture (gyroscope sample clocks; the accelerometers showed none); last row: the "
             "spread (std) of the relative rates across captures.\n\n"
             "| capture | " + " | ".join(nominal.names) + " |\n|---|" + "---|" * len(nominal.names) + "\n")
    for a in fits:
        text += f"| {a} | " + " | ".join(f"{v:.1f} ({w:+.1f})" for v, w in zip(rates[a], rel[a])) + " |\n"
    text += "| spread of relative | " + " | ".join(f"{v:.2f}" for v in spread) + " |\n\n"
    text += ("## Reading ages\n\n![reading ages](time_aware_real_ages.png)\n\nThe reading delay of four IMUs relative "
             "to the others, estimated from the residuals of the time-unaware model while twisting, and the sample "
             f"clocks the timing stage fitted ({fits[0]}).\n")
    write_results(OUT, text)
    (RESULTS / "time_aware_real.json").write_text(json.dumps({"rows": rows, "rates": {a: r.tolist() for a, r in rates.items()},
                                                              "seconds": {f"{a}/{t}": s for (a, t), s in seconds.items()}},
                                                             indent=1, default=float))
    say(f"wrote {OUT}")


if __name__ == "__main__":
    main()
