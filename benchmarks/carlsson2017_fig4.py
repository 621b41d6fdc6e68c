"""Monte Carlo reproduction of carlsson2017 Fig. 4 (and Fig. 5): accelerometer position RMSE of the
on-the-fly geometry calibration (``imu_array_ros.calibration.geometry.calibrate_geometry``).

Setting of the paper's Sec. IV: the 32-IMU array (``grid_array32``: 6.3 mm pitch, 2 mm in z,
sigma_a = 0.04 m/s^2, sigma_g = 0.06 deg/s, gyroscopes saturating at 2000 deg/s), true positions
= nominal + N(0, (1 mm)^2) per component, independent samples with |omega| = 2000 deg/s and
|omega_dot| = 2000 deg/s^2 in uniformly random directions (``simulate_random``).  The calibration
starts from the nominal positions shifted so that the reference IMU (imu_00, held) sits at its true
position (only relative positions are observable); the RMSE is over the position components of the
31 other IMUs, pooled over the realisations, as in the paper.

Per realisation:

* ``method="joint"`` (Gauss-Newton, converged ML) and its reported ``position_std`` (the Cramér-Rao
  bound of the joint problem at the estimate): sqrt CRB = sqrt(mean over realisations and components
  of position_std^2);
* on a subset of the realisations, the BCD after k iterations (k = 0 and CHECKPOINTS), both the literal
  carlsson2017 Alg. 1 (``recenter=False``, reference held) and the repository's default BCD
  (``recenter=True``).  ``calibrate_geometry`` returns only the final positions, so the positions
  after k iterations are obtained by resuming: the result of ``max_iterations=k1`` is passed as the
  start of a call with ``max_iterations=k2-k1`` (BCD's only state is the positions, so this is the
  same iterate as one call with ``max_iterations=k2``: checked bit-for-bit; a chain that reports
  convergence stops and keeps its positions for the later checkpoints).

N = 2 is refused by ``calibrate_geometry`` (``CalibrationError``, message printed and written).

Fig. 5 (N = 10, the paper's 200 iterations): RMSE vs |omega| and |omega_dot|, joint (converged)
and literal Alg. 1 after 200 iterations on fewer realisations.  The paper's text does not give the
ranges of its axes; the grid is ours (|omega| up to the gyroscope range, |omega_dot| up to 64000
deg/s^2, where ||[omega_dot]x|| reaches ||[omega]x^2|| at 2000 deg/s).

Runs the realisations on ``--workers`` processes (BLAS single-threaded in each).  The paper used
1e4 realisations per point; the defaults below take 630 s of CPU, ~5.5 min on 2 idle cores (13 min
wall measured on the shared machine at load 5-9).  Writes
benchmarks/results/carlsson2017_fig4.md and .png (matplotlib, Agg).

    python -m benchmarks.carlsson2017_fig4 [--workers 2] [--scale 1.0] [--no-fig5]
"""

from __future__ import annotations

import os

from benchmarks.harness import RESULTS, machine_header, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import multiprocessing as mp  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from imu_array_ros.calibration.geometry import calibrate_geometry  # noqa: E402
from imu_array_ros.errors import CalibrationError  # noqa: E402
from imu_array_ros.model.sensor_model import SensorModel  # noqa: E402
from imu_array_ros.model.layouts import grid_array32  # noqa: E402
from imu_array_ros.simulation.perturb import perturb  # noqa: E402
from imu_array_ros.simulation.simulator import simulate_random  # noqa: E402

SIGMA_R = 1e-3
#: BCD iteration counts at which the positions are recorded (500 = the repository's BCD cap)
CHECKPOINTS = (1, 2, 5, 10, 20, 50, 100, 200, 500)
#: N -> (realisations with the joint solver, of which the first ones also run both BCD chains)
PLAN = {3: (1000, 60), 10: (1000, 60), 100: (300, 30), 1000: (40, 8)}
#: Fig. 5 grid (deg/s, deg/s^2), N = 10, realisations (joint, literal Alg. 1 with 200 iterations)
FIG5_N, FIG5_ITER = 10, 200
FIG5_OMEGA = (250, 500, 1000, 1500, 2000)
FIG5_OMEGA_DOT = (250, 1000, 4000, 16000, 64000)
FIG5_RUNS = (100, 10)

_NOMINAL: SensorModel | None = None


def nominal() -> SensorModel:
    global _NOMINAL
    if _NOMINAL is None:
        _NOMINAL = SensorModel.from_description(grid_array32())
    return _NOMINAL


def realisation(seed: int, n: int, i: int, omega_deg: float = 2000.0, omega_dot_deg: float = 2000.0):
    """(true model, samples, start model) of realisation i: seeded by (seed, n, i, |omega|, |omega_dot|)."""
    nom = nominal()
    rng = np.random.default_rng([seed, n, i, int(omega_deg), int(omega_dot_deg)])
    true = perturb(nom, rng, {"position": SIGMA_R})
    samples, _ = simulate_random(true, n, np.deg2rad(omega_deg), np.deg2rad(omega_dot_deg), rng)
    start = nom.with_terms(position=nom.positions + (true.positions[0] - nom.positions[0]))
    return true, samples, start


def sse(model: SensorModel, true: SensorModel) -> float:
    """Sum of squared position errors over the non-reference IMUs' components (m^2)."""
    return float(np.sum((model.positions[1:] - true.positions[1:]) ** 2))


def bcd_chain(samples, start: SensorModel, true: SensorModel, recenter: bool, checkpoints) -> tuple[list, int | None]:
    """SSE after k = 0 and each checkpoint of BCD iterations (resumed calls), and the iteration of convergence."""
    out, model, done, converged_at = [sse(start, true)], start, 0, None
    for k in checkpoints:
        if converged_at is None:
            r = calibrate_geometry(samples, model, method="bcd", max_iterations=k - done, recenter=recenter)
            model = r.model
            if r.converged:
                converged_at = done + r.iterations
            done = k
        out.append(sse(model, true))
    return out, converged_at


def run_task(task):
    """One realisation; returns a small dict of sums (picklable)."""
    kind, seed, n, i, w, wd, chains, bcd_iter = task
    t0, c0 = time.perf_counter(), time.process_time()
    true, samples, start = realisation(seed, n, i, w, wd)
    res = dict(kind=kind, n=n, i=i, w=w, wd=wd, count=3 * (true.n_imus - 1))
    try:
        j = calibrate_geometry(samples, start, method="joint")
        res.update(sse_joint=sse(j.model, true), ssd=float(np.sum(j.position_std[1:] ** 2)),
                   joint_iterations=j.iterations, joint_converged=j.converged, joint_seconds=j.seconds)
        if chains:
            for label, rec in (("literal", False), ("recentred", True)):
                s, conv = bcd_chain(samples, start, true, rec, CHECKPOINTS)
                res[f"sse_{label}"], res[f"conv_{label}"] = s, conv
        if bcd_iter:
            b = calibrate_geometry(samples, start, method="bcd", max_iterations=bcd_iter, recenter=False)
            res["sse_bcd_fixed"] = sse(b.model, true)
    except CalibrationError as exc:
        res["refused"] = str(exc)
    res["seconds"], res["cpu"] = time.perf_counter() - t0, time.process_time() - c0
    return res


# --------------------------------------------------------------------------- statistics


def rmse(values, counts) -> float:
    return float(np.sqrt(np.sum(values) / np.sum(counts)))


def ratio_ci(num, den, rng, n_boot: int = 4000) -> tuple[float, float, float]:
    """sqrt(sum num / sum den) and its 95 % bootstrap interval (realisations resampled)."""
    num, den = np.asarray(num, float), np.asarray(den, float)
    idx = rng.integers(0, len(num), size=(n_boot, len(num)))
    boot = np.sqrt(num[idx].sum(axis=1) / den[idx].sum(axis=1))
    return float(np.sqrt(num.sum() / den.sum())), float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def um(x: float) -> str:
    return f"{x * 1e6:.3g}"


# --------------------------------------------------------------------------- main


def refuse_two(seed: int) -> str:
    true, samples, start = realisation(seed, 2, 0)
    lines = []
    for method in ("joint", "bcd"):
        try:
            calibrate_geometry(samples, start, method=method)
            lines.append(f"{method}: NOT refused")
        except CalibrationError as exc:
            lines.append(f"{method}: CalibrationError: {exc}")
    for line in lines:
        print(f"N = 2, {line}", flush=True)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every realisation count (min 2)")
    ap.add_argument("--no-fig5", action="store_true")
    ap.add_argument("--seed", type=int, default=2017)
    ap.add_argument("--out", default=str(RESULTS / "carlsson2017_fig4.md"))
    args = ap.parse_args()
    t_start, load0 = time.perf_counter(), os.getloadavg()
    sc = lambda m: max(2, int(round(m * args.scale)))  # noqa: E731
    plan = {n: (sc(m), min(sc(m), sc(c))) for n, (m, c) in PLAN.items()}
    fig5 = None if args.no_fig5 else (sc(FIG5_RUNS[0]), min(sc(FIG5_RUNS[0]), sc(FIG5_RUNS[1])))

    refusal = refuse_two(args.seed)
    tasks = []
    for n, (m, c) in plan.items():
        tasks += [("fig4", args.seed, n, i, 2000, 2000, i < c, 0) for i in range(m)]
    if fig5:
        for w in FIG5_OMEGA:
            for wd in FIG5_OMEGA_DOT:
                tasks += [("fig5", args.seed, FIG5_N, i, w, wd, False, FIG5_ITER if i < fig5[1] else 0)
                          for i in range(fig5[0])]
    # expensive first (load balance): chains at large N, then fixed-iteration BCD, then joint only
    cost = lambda t: (t[6] * (t[2] + 300) * 10 + (t[7] > 0) * 100 + t[2])  # noqa: E731
    tasks.sort(key=cost, reverse=True)
    print(f"{len(tasks)} realisations on {args.workers} workers", flush=True)
    results, t0 = [], time.perf_counter()
    with mp.get_context("fork").Pool(args.workers) as pool:
        for k, r in enumerate(pool.imap_unordered(run_task, tasks, chunksize=1)):
            results.append(r)
            if (k + 1) % 200 == 0 or k + 1 == len(tasks):
                print(f"  {k + 1}/{len(tasks)} done, {time.perf_counter() - t0:.0f} s", flush=True)
    wall_mc = time.perf_counter() - t0
    load = (load0, os.getloadavg())
    text = report(results, plan, fig5, refusal, args, wall_mc, load)
    text = text.replace("@TOTAL@", f"{time.perf_counter() - t_start:.0f}")
    write_results(args.out, text)
    print(text)
    print(f"wrote {args.out}")


def report(results, plan, fig5, refusal, args, wall_mc, load) -> str:
    rng = np.random.default_rng(1)
    fig4 = [r for r in results if r["kind"] == "fig4"]
    busy, cpu = sum(r["seconds"] for r in results), sum(r["cpu"] for r in results)
    rows, curves, summary = [], {}, {}
    ks = (0,) + CHECKPOINTS
    show_k = (1, 10, 50, 200, 500)
    for n, (m, c) in plan.items():
        rs = sorted((r for r in fig4 if r["n"] == n), key=lambda r: r["i"])
        ok = [r for r in rs if "refused" not in r]
        refused = len(rs) - len(ok)
        cnt = np.array([r["count"] for r in ok], float)
        sj, sd = np.array([r["sse_joint"] for r in ok]), np.array([r["ssd"] for r in ok])
        ratio = ratio_ci(sj, sd, rng)
        ch = [r for r in ok if "sse_literal" in r]
        cc = np.array([r["count"] for r in ch], float)
        cur = {lab: [rmse([r[f"sse_{lab}"][q] for r in ch], cc) for q in range(len(ks))]
               for lab in ("literal", "recentred")}
        conv = {lab: [r[f"conv_{lab}"] for r in ch] for lab in ("literal", "recentred")}
        # the CRB of the chain subset (for the ratio of the BCD after 500 iterations)
        sd_ch = np.array([r["ssd"] for r in ch])
        lit_ratio = ratio_ci([r["sse_literal"][-1] for r in ch], sd_ch, rng)
        curves[n] = dict(cur=cur, crb=rmse(sd, cnt), joint=rmse(sj, cnt), crb_sub=rmse(sd_ch, cc))
        summary[n] = dict(joint=rmse(sj, cnt), crb=rmse(sd, cnt), ratio=ratio, lit_ratio=lit_ratio, m=len(ok), c=len(ch))
        conv_txt = {lab: (f"{sum(x is not None for x in v)}/{len(v)}, median "
                          f"{np.median([x for x in v if x is not None]):.0f}" if any(x is not None for x in v)
                          else f"0/{len(v)}") for lab, v in conv.items()}
        jit = np.array([r["joint_iterations"] for r in ok])
        rows.append(
            f"| {n} | {len(ok)} ({refused} refused) / {len(ch)} | {um(cur['literal'][0])} | "
            + " | ".join(um(cur["literal"][ks.index(k)]) for k in show_k) + f" | {conv_txt['literal']} | "
            + " | ".join(um(cur["recentred"][ks.index(k)]) for k in (1, 10, 50)) + f" | {conv_txt['recentred']} | "
            f"**{um(rmse(sj, cnt))}** ({np.median(jit):.0f} it) | {um(rmse(sd, cnt))} | "
            f"**{ratio[0]:.3f}** [{ratio[1]:.3f}, {ratio[2]:.3f}] | {lit_ratio[0]:.3f} [{lit_ratio[1]:.3f}, {lit_ratio[2]:.3f}] |")
    ns = np.array(sorted(summary))
    fit_all = np.polyfit(np.log(ns), np.log([summary[n]["joint"] for n in ns]), 1)
    big = ns[ns >= 10]
    fit_big = np.polyfit(np.log(big), np.log([summary[n]["joint"] for n in big]), 1)
    fit_crb = np.polyfit(np.log(ns), np.log([summary[n]["crb"] for n in ns]), 1)
    within = {n: s["ratio"][0] <= 1.2 for n, s in summary.items()}
    within_ci = {n: s["ratio"][2] <= 1.2 for n, s in summary.items()}
    n1000 = summary.get(1000)

    f5_rows, f5 = [], None
    if fig5:
        f5 = {}
        for w in FIG5_OMEGA:
            cells = []
            for wd in FIG5_OMEGA_DOT:
                rs = [r for r in results if r["kind"] == "fig5" and r["w"] == w and r["wd"] == wd]
                ok = [r for r in rs if "refused" not in r]
                cnt = np.array([r["count"] for r in ok], float)
                b = [r for r in ok if "sse_bcd_fixed" in r]
                val = dict(joint=rmse([r["sse_joint"] for r in ok], cnt) if ok else np.nan,
                           crb=rmse([r["ssd"] for r in ok], cnt) if ok else np.nan,
                           bcd=rmse([r["sse_bcd_fixed"] for r in b], [r["count"] for r in b]) if b else np.nan,
                           refused=len(rs) - len(ok))
                f5[(w, wd)] = val
                cells.append(f"{um(val['joint'])} / {um(val['crb'])} / {um(val['bcd'])}"
                             + (f" ({val['refused']} refused)" if val["refused"] else ""))
            f5_rows.append(f"| {w} | " + " | ".join(cells) + " |")

    png = Path(args.out).with_suffix(".png")
    plotted = plot(curves, summary, f5, fit_all, png)

    t = machine_header("carlsson2017 Fig. 4 (and Fig. 5): geometry calibration RMSE, Monte Carlo")
    t += (f"Run time: @TOTAL@ s wall in all ({wall_mc:.0f} s for the Monte Carlo on {args.workers} worker processes, "
          f"{busy:.0f} s of realisation wall time and {cpu:.0f} s of CPU time summed over the workers, i.e. "
          f"~{cpu / 2:.0f} s on 2 idle cores; BLAS single-threaded per process; "
          f"load average (1/5/15 min) at the start {'/'.join(f'{x:.1f}' for x in load[0])}, at the end "
          f"{'/'.join(f'{x:.1f}' for x in load[1])}: the machine is shared, so the times are upper bounds).  "
          f"Seed {args.seed}; every realisation is seeded by (seed, N, index, |omega|, |omega_dot|), so the "
          "numbers do not depend on the number of workers.\n\n")
    t += ("## Setting\n\ncarlsson2017 Sec. IV: the 32-IMU array (`grid_array32`: 6.3 mm pitch, 2 mm in z, "
          "sigma_a = 0.04 m/s^2, sigma_g = 0.06 deg/s, gyroscope range 2000 deg/s); true positions = nominal + "
          "N(0, (1 mm)^2) per component; N independent samples (`simulate_random`) with |omega| = 2000 deg/s, "
          "|omega_dot| = 2000 deg/s^2, directions uniform on the sphere; start: the nominal positions shifted so "
          "that the reference imu_00 (held) is at its true position.  RMSE = sqrt(mean of the squared error over "
          "the 93 position components of the 31 other IMUs and over the realisations), as the paper.  "
          "sqrt CRB = sqrt(mean of the reported `position_std`^2 (the Cramér-Rao bound of the joint problem, at "
          "the joint estimate) over the same components and realisations).\n\n"
          "Realisations: the paper used 10^4 per point; here "
          + ", ".join(f"N = {n}: {m} (joint), {c} (BCD chains)" for n, (m, c) in plan.items()) +
          " -- chosen so the whole script runs in about 10 min on 2 cores (a BCD chain to 500 literal iterations "
          "costs ~15 s at N = 1000).  The BCD positions after k iterations are from resumed calls of "
          "`calibrate_geometry(..., method=\"bcd\", max_iterations=k2-k1)` (exact: BCD's only state is the "
          "positions; a chain that converges keeps its positions).  *literal* = carlsson2017 Alg. 1 "
          "(`recenter=False`, the reference held); *recentred* = the repository's default BCD (`recenter=True`).\n\n")
    t += f"## N = 2 is refused\n\n```\n{refusal}\n```\n\n"
    t += ("## Fig. 4: RMSE (um) vs BCD iterations and N\n\n"
          "Columns: BCD at k = 0 (the start) and after k iterations; 'conv.' = chains that met the BCD's "
          "own stopping rule (every step below 1e-3 of its std) within 500 iterations, and the median "
          "iteration at which they did; joint = the converged Gauss-Newton ML (median iterations); ratio = "
          "joint RMSE / sqrt CRB over all realisations, with the 95 % bootstrap interval (realisations "
          "resampled); last column the same ratio for literal Alg. 1 after 500 iterations (the chain subset).\n\n"
          "| N | realisations (joint / chains) | start | Alg. 1 k=1 | k=10 | k=50 | k=200 | k=500 | Alg. 1 conv. "
          "| recentred k=1 | k=10 | k=50 | recentred conv. | joint | sqrt CRB | RMSE/sqrt CRB (joint) "
          "| RMSE/sqrt CRB (Alg. 1, 500) |\n|" + "---|" * 17 + "\n" + "\n".join(rows) + "\n\n")
    t += ("Full curves (RMSE um, literal Alg. 1 / recentred) at k = " + ", ".join(map(str, ks)) + ":\n\n")
    for n, cv in curves.items():
        t += (f"- N = {n}: " + ", ".join(f"{um(a)}/{um(b)}" for a, b in zip(cv["cur"]["literal"], cv["cur"]["recentred"]))
              + f" (sqrt CRB of this subset {um(cv['crb_sub'])})\n")
    t += (f"\nN^-1/2 law: log-log least-squares slope of the joint RMSE vs N: {fit_all[0]:.3f} over N = "
          f"{', '.join(map(str, ns))}; {fit_big[0]:.3f} over N >= 10; slope of sqrt CRB {fit_crb[0]:.3f} "
          "(the paper: -1/2).\n\n")
    t += "## Verdicts\n\n"
    t += ("- *Within 20 % of the CRB* (joint RMSE / sqrt CRB <= 1.2): "
          + "; ".join(f"N = {n}: {'yes' if within[n] else 'NO'} ({summary[n]['ratio'][0]:.2f}, 95 % CI upper "
                      f"{summary[n]['ratio'][2]:.2f}{'' if within_ci[n] else ' > 1.2'})" for n in summary) + ".\n")
    if n1000:
        t += (f"- *Order 1 um at N = 1000*: RMSE {um(n1000['joint'])} um (joint), sqrt CRB {um(n1000['crb'])} um: "
              + ("yes, of order 1 um" if n1000["joint"] < 5e-6 else "NO") + ".\n")
    t += ("- *RMSE does not fall with iterations at N = 2* (the paper): not measurable here, N = 2 is refused "
          "before any iteration (above).\n"
          "- *With N > 2 the RMSE falls with iterations and with N*: see the table and the figure.\n\n")
    if fig5:
        t += (f"## Fig. 5: RMSE vs |omega| and |omega_dot| at N = {FIG5_N}\n\n"
              f"{fig5[0]} realisations per cell with the joint solver, the first {fig5[1]} of them also with "
              f"literal Alg. 1 stopped after {FIG5_ITER} iterations (the paper's setting).  The paper's text does "
              "not give the ranges of its axes; this grid is ours (|omega_dot| up to 64000 deg/s^2 = 1117 rad/s^2, "
              "where ||[omega_dot]x|| reaches ||[omega]x^2|| = 1218 rad^2/s^2 at 2000 deg/s).  Cells: "
              "joint RMSE / sqrt CRB / Alg. 1 (200 iterations) RMSE, um.\n\n"
              "| |omega| deg/s \\ |omega_dot| deg/s^2 | " + " | ".join(map(str, FIG5_OMEGA_DOT)) + " |\n|"
              + "---|" * (len(FIG5_OMEGA_DOT) + 1) + "\n" + "\n".join(f5_rows) + "\n\n")
    else:
        t += "## Fig. 5\n\nNot run (`--no-fig5`).\n\n"
    t += (f"Figure: `{png.name}`" + ("" if plotted else " NOT written (matplotlib missing: the `plots` extra)")
          + " -- (a) RMSE vs iterations (solid literal Alg. 1, dashed recentred BCD, dotted sqrt CRB, "
          "x = joint), (b) RMSE vs N, (c) Fig. 5.\n")
    return t


def plot(curves, summary, f5, fit, png: Path) -> bool:
    from imu_array_ros.errors import MissingDependencyError
    from imu_array_ros.util.plotting import pyplot, save_png

    try:
        plt = pyplot(png)
    except MissingDependencyError:
        return False

    ks = np.array(CHECKPOINTS)
    fig, axes = plt.subplots(1, 3 if f5 else 2, figsize=(17 if f5 else 11.5, 5.2))
    ax = axes[0]
    for (n, cv), col in zip(curves.items(), plt.rcParams["axes.prop_cycle"].by_key()["color"]):
        ax.loglog(ks, np.array(cv["cur"]["literal"][1:]) * 1e6, "-o", ms=3, color=col, label=f"N = {n}")
        ax.loglog(ks, np.array(cv["cur"]["recentred"][1:]) * 1e6, "--", color=col, lw=1)
        ax.axhline(cv["crb"] * 1e6, color=col, ls=":", lw=1)
        ax.plot([800], [cv["joint"] * 1e6], "x", color=col, ms=8)
    ax.set_xlabel("BCD iterations")
    ax.set_ylabel("position RMSE (um)")
    ax.set_title("Fig. 4: solid Alg. 1, dashed recentred, dotted sqrt CRB, x joint", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax = axes[1]
    ns = np.array(sorted(summary))
    ax.loglog(ns, [summary[n]["joint"] * 1e6 for n in ns], "o-", label="joint RMSE")
    ax.loglog(ns, [summary[n]["crb"] * 1e6 for n in ns], "s:", label="sqrt CRB")
    nn = np.geomspace(ns[0], ns[-1], 50)
    ax.loglog(nn, np.exp(np.polyval(fit, np.log(nn))) * 1e6, "k--", lw=0.8, label=f"fit slope {fit[0]:.2f}")
    ax.set_xlabel("N (samples)")
    ax.set_ylabel("position RMSE (um)")
    ax.set_title("RMSE vs N (|w| = 2000 deg/s, |dw| = 2000 deg/s^2)", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    if f5:
        ax = axes[2]
        for wd, col in zip(FIG5_OMEGA_DOT, plt.rcParams["axes.prop_cycle"].by_key()["color"]):
            ax.semilogy(FIG5_OMEGA, [f5[(w, wd)]["joint"] * 1e6 for w in FIG5_OMEGA], "o-", color=col,
                        label=f"|dw| = {wd} deg/s^2")
            ax.semilogy(FIG5_OMEGA, [f5[(w, wd)]["bcd"] * 1e6 for w in FIG5_OMEGA], "x", color=col, ms=7)
            ax.semilogy(FIG5_OMEGA, [f5[(w, wd)]["crb"] * 1e6 for w in FIG5_OMEGA], ":", color=col, lw=1)
        ax.set_xlabel("|omega| (deg/s)")
        ax.set_ylabel("position RMSE (um)")
        ax.set_title(f"Fig. 5 (N = {FIG5_N}): o- joint, x Alg. 1 ({FIG5_ITER} it), dotted sqrt CRB", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    save_png(fig, png)
    return True


if __name__ == "__main__":
    main()
