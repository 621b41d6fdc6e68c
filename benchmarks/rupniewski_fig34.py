"""Monte Carlo reproduction of rupniewski Fig. 3 and Fig. 4: calibration error of four gyroscope triads by
PCA (Algorithm 2, ``imu_array_ros.calibration.pca.pca_calibrate``) vs the noise sigma and vs the number of
positions n.

Setting of the paper's Sec. IV: a_model (3 x 12, four triads), every sensitivity vector (column) perturbed
by N(0, 0.01^2 I) -- drawn anew for every repetition; n random orientations of the system on a rotary table
turning at a constant rate c, so the rate in the system's frame is c times a direction uniform on the sphere.
The paper does not give c; we take c = 1 rad/s (sigma is in rad/s, so only sigma / c matters).  Readings are
unbiased (the paper's eq. 18 bias subtraction is assumed done; its noise is part of sigma).  Calibration
error eps = ||h a - k a_hat||_F with h a and k a_hat upper triangular with positive diagonal (eq. 19,
``calibration_error``).  Fig. 3: median and interquartile range (IQR) of eps vs sigma at n = N_FIG3; Fig. 4:
vs n at sigma = SIGMA_FIG4 (and, as a check for the O(sigma^2) bias of the fit, at 10 x that sigma).  The
paper does not state its fixed n and sigma; ours are below.  Log-log slopes are least-squares fits over all
points of a curve.  All repetitions of a point are one batched call (numpy SVD / QR / eigh on stacks).

Writes benchmarks/results/rupniewski_fig34.md and .png (matplotlib, Agg).

    python -m benchmarks.rupniewski_fig34 [--reps 1000] [--seed 2023]
"""

from __future__ import annotations

from benchmarks.harness import RESULTS, machine_header, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from imu_array_ros.calibration.pca import calibration_error, pca_calibrate  # noqa: E402

OUT = RESULTS / "rupniewski_fig34"

#: rupniewski Sec. IV: sensitivity vectors of the four triads (columns)
A_MODEL = np.array([
    [1, 0, 0, 0, 1, 0, 0, -1, 0, 1, 0, 0],
    [0, 1, 0, -1, 0, 0, 1, 0, 0, 0, 0, -1],
    [0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 1, 0],
], dtype=float)
AXIS_SIGMA = 0.01          # spread of the sensitivity vectors (paper)
RATE = 1.0                 # c, rad/s (our choice)
N_FIG3 = 100               # positions for Fig. 3 (our choice)
SIGMAS = np.array([1e-4, 2e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2])   # rad/s, two decades
SIGMA_FIG4 = 1e-3          # rad/s for Fig. 4 (our choice)
NS = np.array([10, 20, 50, 100, 200, 500, 1000])
CHUNK = 2_000_000          # readings per batched call (memory)


def calibration_errors(rng: np.random.Generator, reps: int, n: int, sigma: float, a_model: np.ndarray = A_MODEL,
                       rate: float = RATE, axis_sigma: float = AXIS_SIGMA) -> np.ndarray:
    """eps (reps,) of ``reps`` independent simulated calibrations (new a, orientations and noise each)."""
    d, m = a_model.shape
    out = np.empty(reps)
    step = max(1, CHUNK // (n * m))
    for lo in range(0, reps, step):
        b = min(step, reps - lo)
        a = a_model + rng.normal(0.0, axis_sigma, (b, d, m))
        u = rng.normal(size=(b, n, d))
        v = rate * u / np.linalg.norm(u, axis=-1, keepdims=True)
        readings = v @ a + rng.normal(0.0, sigma, (b, n, m))
        out[lo:lo + b] = calibration_error(a, pca_calibrate(readings, rate, dim=d).a)
    return out


def loglog_slope(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def stats(eps: np.ndarray) -> tuple[float, float]:
    q1, med, q3 = np.percentile(eps, [25, 50, 75])
    return float(med), float(q3 - q1)


def run(reps: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    res = {"fig3": [], "fig4": [], "fig4_hi": []}
    for sigma in SIGMAS:
        res["fig3"].append(stats(calibration_errors(rng, reps, N_FIG3, sigma)))
    for n in NS:
        res["fig4"].append(stats(calibration_errors(rng, reps, int(n), SIGMA_FIG4)))
    for n in NS:
        res["fig4_hi"].append(stats(calibration_errors(rng, reps, int(n), 10 * SIGMA_FIG4)))
    return {k: np.array(v) for k, v in res.items()}


def plot(res: dict, path: Path) -> None:
    from imu_array_ros.util.plotting import pyplot, save_png

    plt = pyplot(path)
    fig, (ax3, ax4) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax3.loglog(SIGMAS, res["fig3"][:, 0], "o-", label="median")
    ax3.loglog(SIGMAS, res["fig3"][:, 1], "s--", label="IQR")
    ax3.loglog(SIGMAS, res["fig3"][0, 0] * SIGMAS / SIGMAS[0], ":", color="gray", label=r"$\propto\sigma$")
    ax3.set(xlabel=r"noise $\sigma$ [rad/s] (c = 1 rad/s)", ylabel=r"calibration error $\epsilon$ (eq. 19)",
            title=f"Fig. 3: n = {N_FIG3} positions")
    ax4.loglog(NS, res["fig4"][:, 0], "o-", label=rf"median, $\sigma$ = {SIGMA_FIG4:g}")
    ax4.loglog(NS, res["fig4"][:, 1], "s--", label=rf"IQR, $\sigma$ = {SIGMA_FIG4:g}")
    ax4.loglog(NS, res["fig4_hi"][:, 0], "^-", label=rf"median, $\sigma$ = {10 * SIGMA_FIG4:g}")
    ax4.loglog(NS, res["fig4"][3, 0] * (NS / NS[3]) ** -0.5, ":", color="gray", label=r"$\propto n^{-1/2}$")
    ax4.set(xlabel="positions n", title=rf"Fig. 4: $\sigma$ = {SIGMA_FIG4:g} rad/s")
    for ax in (ax3, ax4):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, path)


def report(res: dict, reps: int, seed: int, seconds: float) -> str:
    s3 = [loglog_slope(SIGMAS, res["fig3"][:, j]) for j in (0, 1)]
    s4 = [loglog_slope(NS, res["fig4"][:, j]) for j in (0, 1)]
    s4h = [loglog_slope(NS, res["fig4_hi"][:, j]) for j in (0, 1)]
    tail = NS >= 50
    s4t = [loglog_slope(NS[tail], res["fig4"][tail, j]) for j in (0, 1)]
    lines = [machine_header("rupniewski Fig. 3-4: PCA calibration error of four gyroscope triads"),
             f"Setting: `a_model` of Sec. IV + N(0, {AXIS_SIGMA}^2 I) per sensitivity vector (new each repetition), "
             f"rotary-table rate c = {RATE:g} rad/s (our choice; the paper gives none) in uniformly random directions, "
             f"unbiased readings + N(0, sigma^2), Algorithm 2 (`pca_calibrate`), eps of eq. 19 (`calibration_error`). "
             f"{reps} repetitions per point, seed {seed}; total {seconds:.1f} s wall.\n",
             f"## Fig. 3: eps vs sigma (n = {N_FIG3})\n", "| sigma [rad/s] | median eps | IQR eps |", "|---|---|---|"]
    lines += [f"| {sg:g} | {md:.4g} | {iq:.4g} |" for sg, (md, iq) in zip(SIGMAS, res["fig3"])]
    lines += ["", f"log-log slope: median **{s3[0]:.3f}**, IQR **{s3[1]:.3f}** (paper: ~1)\n",
              f"## Fig. 4: eps vs n (sigma = {SIGMA_FIG4:g} rad/s; last two columns: sigma = {10 * SIGMA_FIG4:g})\n",
              "| n | median eps | IQR eps | median eps (10 sigma) | IQR eps (10 sigma) |", "|---|---|---|---|---|"]
    lines += [f"| {n} | {a:.4g} | {b:.4g} | {c:.4g} | {d:.4g} |"
              for n, (a, b), (c, d) in zip(NS, res["fig4"], res["fig4_hi"])]
    lines += ["", f"log-log slope: median **{s4[0]:.3f}**, IQR **{s4[1]:.3f}** (paper: ~-0.5); "
              f"at 10 sigma: median {s4h[0]:.3f}, IQR {s4h[1]:.3f}; over n >= 50 only: median {s4t[0]:.3f}, "
              f"IQR {s4t[1]:.3f} (near the minimum of 6 positions eps is larger than the n^-0.5 law)\n"]
    ratio = res["fig4_hi"][:, 0] / res["fig4"][:, 0]
    lines += [f"Median eps at 10 sigma / median eps at sigma, over n: {ratio.min():.2f}-{ratio.max():.2f} "
              "(10 if eps were proportional to sigma).\n",
              f"![Fig. 3-4]({OUT.name}.png)", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=1000, help="repetitions per point (paper: 1000)")
    ap.add_argument("--seed", type=int, default=2023)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    res = run(args.reps, args.seed)
    seconds = time.perf_counter() - t0
    plot(res, OUT.with_suffix(".png"))
    text = report(res, args.reps, args.seed, seconds)
    print(text)
    print(f"wrote {write_results(OUT.with_suffix('.md'), text)}")


if __name__ == "__main__":
    main()
