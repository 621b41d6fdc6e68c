"""Statistical validation of the PmMH posterior sampler (carlsson2021 Sec. IV-A setting).

Setting: the 32-IMU grid array (d = 93 free position coordinates, IMU 0 held), sigma_a 0.04 m/s^2,
sigma_g 0.06 deg/s, no clipping; omega, omega_dot, s ~ N(0, 1000 deg/s, 35000 deg/s^2, 20 m/s^2) per sample
(:func:`imu_array_ros.simulation.simulator.simulate_gaussian`); the true positions are drawn FROM THE PRIOR
(nominal + N(0, 3 mm) per coordinate), so the posterior computed from the data is the exact conditional of
the truth and every check below has a known answer.

1. Coverage / simulation-based calibration (Talts et al. 2018) over independent datasets, one Dask task
   per dataset on a ``LocalCluster`` of single-threaded worker processes, each sampling with the default
   :class:`~imu_array_ros.calibration.bayes.SamplerSettings` (serial chains inside the task).
2. Agreement of the default sampler with a long plain PmMH random-walk reference chain on one dataset.
3. Correlated pseudo-marginal (rho 0.9) against independent random numbers (rho 0), N = 1 for both.

Writes benchmarks/results/bayes_validation.md, .json and bayes_validation_ranks.png.

    python -m benchmarks.bayes_validation [--runs 50] [--samples 50] [--quick] [--render]

(--samples is T, the time samples per dataset; --quick is a smoke test: 6 runs and short, unconverged
chains in sections 2-3; --render re-writes the .md/.png from the saved .json.)
"""

from __future__ import annotations

import os

from benchmarks.harness import RESULTS, machine_header, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

OUT = RESULTS / "bayes_validation"
LEVELS = (0.5, 0.9, 0.95)
SBC_BINS = 10
#: seeds of the coverage datasets are COVERAGE_SEED0 + i; the fixed dataset of sections 2-3
COVERAGE_SEED0 = 1000
FIXED_SEED = 7
#: seeds of the Laplace-only datasets (section 1b)
LAPLACE_SEED0 = 50000
ALPHA_KS = 0.01
TITLE = "Bayesian sampler validation: coverage, SBC, reference chain, correlated pseudo-marginal"


# --------------------------------------------------------------------------- the setting (paper Sec. IV-A)


def dataset(seed: int, n_samples: int):
    """(problem, laplace, theta_true) of one simulated dataset, truth drawn from the prior."""
    from imu_array_ros.calibration import bayes
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.model.layouts import grid_array32
    from imu_array_ros.simulation.simulator import simulate_gaussian

    nominal = dataclasses.replace(SensorModel.from_description(grid_array32()), acc_clip=np.inf, gyro_clip=np.inf)
    rng = np.random.default_rng(seed)
    pos = nominal.positions.copy()
    pos[1:] += rng.normal(size=pos[1:].shape) * bayes.PRIOR_STD
    true = nominal.with_terms(position=pos)
    s, _ = simulate_gaussian(true, n_samples, rng)
    p = bayes.build_problem(s, nominal)
    lap = bayes.laplace(p, s, nominal)
    return p, lap, p.theta_of(pos)


def _ess_per_coordinate(draws: np.ndarray) -> np.ndarray:
    from imu_array_ros.calibration import bayes

    az = bayes.arviz()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.asarray(az.ess(az.convert_to_dataset({"theta": draws}), method="bulk")["theta"].values)


def _thin(draws: np.ndarray, ess: float) -> np.ndarray:
    """Draws (C, M, ...) thinned within each chain by ~ C*M / ess, flattened (roughly independent draws)."""
    c, m = draws.shape[:2]
    step = max(1, int(round(c * m / max(ess, 1.0))))
    return draws[:, ::step].reshape((-1,) + draws.shape[2:])


# --------------------------------------------------------------------------- 1. one coverage run (a Dask task)


def coverage_run(seed: int, n_samples: int, rank_draws: int) -> dict:
    """One dataset: sample its posterior with the default settings; small arrays only."""
    from scipy import stats

    from imu_array_ros.calibration import bayes

    t_cpu, t_wall = time.process_time(), time.perf_counter()
    p, lap, theta = dataset(seed, n_samples)
    post = bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="serial", seed=seed))
    c, m, d = post.draws.shape
    flat = post.flat
    # SBC rank of the truth among rank_draws roughly independent draws, spread evenly over the pooled chains
    # (spacing C*M / rank_draws iterations >= 4 x the integrated autocorrelation time at ESS >= 400)
    idx = np.round(np.linspace(0, c * m - 1, rank_draws)).astype(int)
    ranks = np.sum(flat[idx] < theta, axis=0)
    cover = []
    for lev in LEVELS:
        lo, hi = np.quantile(flat, [(1 - lev) / 2, (1 + lev) / 2], axis=0)
        cover.append((lo <= theta) & (theta <= hi))
    mean, cov = post.mean, post.covariance
    sd = np.sqrt(np.diag(cov))
    r = theta - mean
    chi2_mcmc = float(r @ np.linalg.solve(cov, r))
    chi2_lapcov = float(r @ np.linalg.solve(lap.covariance, r))
    rl = theta - lap.mean
    chi2_laplace = float(rl @ np.linalg.solve(lap.covariance, rl))
    # Hotelling T^2 with the covariance of n roughly independent (ESS-thinned) draws: exact F reference
    thin = _thin(post.draws, post.ess_bulk_min)
    n = len(thin)
    rt = theta - thin.mean(axis=0)
    t2 = float(rt @ np.linalg.solve(np.cov(thin, rowvar=False), rt)) / (1.0 + 1.0 / n)
    hotelling_p = float(stats.f.sf(t2 * (n - d) / (d * (n - 1)), d, n - d)) if n > d + 1 else float("nan")
    lap_sd = np.sqrt(np.diag(lap.covariance))
    lap_cover = [np.abs(rl) <= stats.norm.ppf((1 + lev) / 2) * lap_sd for lev in LEVELS]
    # the same SBC ranks in whitened coordinates w = L^-1 (theta - laplace mean), L the Laplace Cholesky
    # factor (a function of the data only, so any such test quantity keeps SBC exact): the posterior errors
    # of the raw coordinates share a common mode (every position is relative to the held reference), the
    # whitened ones are nearly independent, so pooling them over coordinates is a fair test
    low = np.linalg.cholesky(lap.covariance)
    w_draws = np.linalg.solve(low, (flat[idx] - lap.mean).T).T
    w_true = np.linalg.solve(low, theta - lap.mean)
    ranks_white = np.sum(w_draws < w_true, axis=0)
    # inflation of the quadratic form by the estimated covariance: tr(S^-1 Sigma_laplace) / d
    inflation = float(np.trace(np.linalg.solve(cov, lap.covariance))) / d
    return {
        "seed": int(seed), "ranks": ranks.astype(int).tolist(), "cover": np.array(cover).astype(int).tolist(),
        "laplace_cover": np.array(lap_cover).astype(int).tolist(),
        "z": ((mean - theta) / sd).tolist(), "z_laplace": ((lap.mean - theta) / lap_sd).tolist(),
        "sd_ratio_laplace": (lap_sd / sd).tolist(), "mean_minus_laplace": ((mean - lap.mean) / sd).tolist(),
        "ranks_white": ranks_white.astype(int).tolist(), "inflation": inflation,
        "chi2_mcmc": chi2_mcmc, "chi2_laplace_cov": chi2_lapcov, "chi2_laplace": chi2_laplace,
        "hotelling_t2": t2, "hotelling_n": int(n), "hotelling_p": hotelling_p,
        "ess_bulk_min": float(post.ess_bulk_min), "ess_tail_min": float(post.ess_tail_min),
        "rhat_max": float(post.rhat_max), "converged": bool(post.converged), "n_draws": int(post.n_draws),
        "warmup": int(post.warmup), "iterations": int(m), "chains": int(c),
        "acceptance_rw": float(np.nanmean(post.acceptance)),
        "acceptance_independence": float(np.nanmean(post.acceptance_independence)),
        "sampler_cpu_seconds": float(post.cpu_seconds),
        "cpu_seconds": time.process_time() - t_cpu, "wall_seconds": time.perf_counter() - t_wall,
        "pid": os.getpid(),
    }


def laplace_batch(seeds: list[int], n_samples: int) -> dict:
    """The Laplace approximation alone on many datasets (~0.1 core-s each): the calibration of the Gaussian
    posterior the sampler's draws are checked against (section 1b)."""
    from scipy import stats

    t_cpu = time.process_time()
    z, chi, cover = [], [], []
    for seed in seeds:
        _, lap, theta = dataset(seed, n_samples)
        sd = np.sqrt(np.diag(lap.covariance))
        r = lap.mean - theta
        z.append(r / sd)
        chi.append(float(r @ np.linalg.solve(lap.covariance, r)))
        cover.append([np.mean(np.abs(r / sd) <= stats.norm.ppf((1 + lev) / 2)) for lev in LEVELS])
    z = np.array(z)
    return {"seeds": [int(s) for s in seeds], "run_mean_z": z.mean(axis=1).tolist(),
            "run_mean_z_axis": z.reshape(len(seeds), -1, 3).mean(axis=1).tolist(), "chi2": chi, "cover": cover,
            "sum_z2": float(np.sum(z ** 2)), "count": int(z.size), "cpu_seconds": time.process_time() - t_cpu}


# --------------------------------------------------------------------------- 2-3. one posterior, thinned (a Dask task)


def chain_run(label: str, seed: int, n_samples: int, settings: dict, sampler_seed: int) -> dict:
    """One sampler configuration on the fixed dataset ``seed``: per-coordinate ESS-thinned draws and the costs.

    Every configuration gets its own ``sampler_seed``: with one seed two configurations would start from the
    same points and, where their kernels draw random numbers alike (rho 0 and rho 0.9 here), run on common
    random numbers, which couples the chains and makes a two-sample test blind."""
    from imu_array_ros.calibration import bayes

    t_cpu = time.process_time()
    p, lap, theta = dataset(seed, n_samples)
    st = bayes.SamplerSettings(scheduler="serial", seed=sampler_seed, **settings)
    post = bayes.sample_posterior(p, lap, st)
    ess = _ess_per_coordinate(post.draws)
    thinned = [_thin(post.draws[:, :, j], ess[j]).tolist() for j in range(p.dim)]
    thinned2 = [_thin(post.draws[:, :, j], ess[j] / 2).tolist() for j in range(p.dim)]
    # noise of the log-likelihood ratio at the posterior mean: ll(theta, u') - ll(theta, u) with u' the
    # chain's proposal of the random numbers (rho u + sqrt(1 - rho^2) eps), over 256 replicates
    pn = p.with_(n_draws=post.n_draws)
    rng = np.random.default_rng(12345)
    diffs = []
    for _ in range(8):
        u = rng.standard_normal((32, pn.n_samples, pn.n_draws, 3))
        un = st.rho * u + np.sqrt(1 - st.rho ** 2) * rng.standard_normal(u.shape)
        diffs.append(pn.loglik_batch(post.mean, un) - pn.loglik_batch(post.mean, u))
    diffs = np.concatenate(diffs)
    return {
        "label": label, "settings": settings, "sampler_seed": int(sampler_seed), "thinned": thinned,
        "thinned2": thinned2, "ess": ess.tolist(),
        "mean": post.mean.tolist(), "sd": np.sqrt(np.diag(post.covariance)).tolist(),
        "theta_true": theta.tolist(),
        "ess_bulk_min": float(post.ess_bulk_min), "ess_tail_min": float(post.ess_tail_min),
        "rhat_max": float(post.rhat_max), "converged": bool(post.converged), "n_draws": int(post.n_draws),
        "rho": float(st.rho), "warmup": int(post.warmup), "iterations": int(post.draws.shape[1]),
        "chains": int(post.draws.shape[0]), "acceptance_rw": float(np.nanmean(post.acceptance)),
        "acceptance_independence": float(np.nanmean(post.acceptance_independence))
        if np.isfinite(post.acceptance_independence).any() else None,
        "var_loglik_table": [[int(a), float(b)] for a, b in post.var_loglik],
        "llr_noise_sd": float(np.std(diffs, ddof=1)), "llr_noise_mean_abs": float(np.mean(np.abs(diffs))),
        "sampler_cpu_seconds": float(post.cpu_seconds), "cpu_seconds": time.process_time() - t_cpu,
        "wall_seconds": float(post.seconds),
    }


def compare(a: dict, b: dict, key: str = "thinned") -> dict:
    """Per-coordinate two-sample KS of ESS-thinned draws of runs a and b (key "thinned2": twice as thin)."""
    from scipy import stats

    pv, dv = [], []
    for xa, xb in zip(a[key], b[key]):
        res = stats.ks_2samp(xa, xb)
        pv.append(float(res.pvalue))
        dv.append(float(res.statistic))
    pv = np.array(pv)
    d = len(pv)
    counts = np.histogram(pv, bins=SBC_BINS, range=(0, 1))[0]
    za = (np.array(a["mean"]) - np.array(b["mean"])) / np.sqrt(np.array(b["sd"]) ** 2)
    return {
        "a": a["label"], "b": b["label"], "pvalues": pv.tolist(), "statistics": dv,
        "rejections_1pct": int(np.sum(pv < ALPHA_KS)), "expected_rejections": ALPHA_KS * d,
        "binomial_p_rejections": float(stats.binomtest(int(np.sum(pv < ALPHA_KS)), d, ALPHA_KS,
                                                       alternative="greater").pvalue),
        "min_p": float(pv.min()), "bonferroni_min_p": float(min(1.0, d * pv.min())),
        "pvalue_hist": counts.tolist(), "pvalue_hist_chi2_p": float(stats.chisquare(counts).pvalue),
        "pvalue_ks_uniform_p": float(stats.kstest(pv, "uniform").pvalue),
        "max_abs_mean_diff_in_sd": float(np.max(np.abs(za))),
        "sd_ratio_range": [float(np.min(np.array(a["sd"]) / np.array(b["sd"]))),
                           float(np.max(np.array(a["sd"]) / np.array(b["sd"])))],
        "thinned_sizes_a": [int(np.min([len(x) for x in a[key]])), int(np.max([len(x) for x in a[key]]))],
        "thinned_sizes_b": [int(np.min([len(x) for x in b[key]])), int(np.max([len(x) for x in b[key]]))],
    }


# --------------------------------------------------------------------------- analysis of the coverage study


def _wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    if n == 0:
        return float("nan"), float("nan")
    ph = k / n
    den = 1 + z * z / n
    c = (ph + z * z / (2 * n)) / den
    h = z * np.sqrt(ph * (1 - ph) / n + z * z / (4 * n * n)) / den
    return float(c - h), float(c + h)


def _sbc(ranks: np.ndarray, rank_draws: int) -> dict:
    """Uniformity of SBC ranks (R runs, d coordinates; values 0..rank_draws): pooled and cluster-robust."""
    from scipy import stats

    n_runs, d = ranks.shape
    nvals = rank_draws + 1
    bins = np.minimum((ranks * SBC_BINS) // nvals, SBC_BINS - 1)
    counts = np.bincount(bins.ravel(), minlength=SBC_BINS)
    # expected share of each bin (exact when nvals is not a multiple of the bin count)
    share = np.bincount((np.arange(nvals) * SBC_BINS) // nvals, minlength=SBC_BINS) / nvals
    chi = stats.chisquare(counts, counts.sum() * share)
    # cluster-robust: Hotelling test of the per-run bin fractions (9 free) against the expected shares
    frac = np.stack([np.bincount(b, minlength=SBC_BINS) / d for b in bins])[:, :-1] - share[:-1]
    hot_p = float("nan")
    if n_runs > SBC_BINS:
        mu, s = frac.mean(axis=0), np.cov(frac, rowvar=False)
        q = SBC_BINS - 1
        t2 = n_runs * float(mu @ np.linalg.solve(s, mu))
        hot_p = float(stats.f.sf(t2 * (n_runs - q) / (q * (n_runs - 1)), q, n_runs - q))
    u = (ranks + 0.5) / nvals
    run_u = u.mean(axis=1)
    # one coordinate per run (run i: coordinate i mod d): independent ranks, a valid but weak pooled test
    one = bins[np.arange(n_runs), np.arange(n_runs) % d]
    one_counts = np.bincount(one, minlength=SBC_BINS)
    return {
        "rank_draws": rank_draws, "bins": SBC_BINS, "counts": counts.tolist(),
        "expected": (counts.sum() * share).tolist(), "chi2": float(chi.statistic), "chi2_p": float(chi.pvalue),
        "cluster_hotelling_p": hot_p,
        "mean_rank_fraction": float(u.mean()), "ks_uniform_p": float(stats.kstest(u.ravel(), "uniform").pvalue),
        "run_mean_rank_sd": float(run_u.std(ddof=1)) if n_runs > 1 else None,
        "run_mean_rank_sd_independent": float(np.sqrt((nvals ** 2 - 1) / 12.0) / nvals / np.sqrt(d)),
        "run_mean_rank_t_p": float(stats.ttest_1samp(run_u, 0.5).pvalue) if n_runs > 1 else None,
        "one_per_run_counts": one_counts.tolist(),
        "one_per_run_chi2_p": float(stats.chisquare(one_counts, n_runs * share).pvalue),
        "edge_share": float(np.mean((ranks == 0) | (ranks == rank_draws))),
        "edge_expected": 2.0 / nvals,
    }


def analyse_null(reps: list[dict], ref: dict) -> dict:
    """The two-sample test between independent default-sampler runs (same target: the test's null) and each
    run against the reference; the replicates' average against the reference."""
    out = {"replicates": len(reps), "sampler_seeds": [r["sampler_seed"] for r in reps],
           "cpu_seconds": float(sum(r["cpu_seconds"] for r in reps))}
    d = len(ref["mean"])
    for key in ("thinned", "thinned2"):
        null = [compare(reps[2 * i], reps[2 * i + 1], key) for i in range(len(reps) // 2)]
        vref = [compare(ref, r, key) for r in reps]
        pn = np.concatenate([c["pvalues"] for c in null]) if null else np.array([])
        pr = np.concatenate([c["pvalues"] for c in vref])
        out[key] = {
            "null_rejections": [c["rejections_1pct"] for c in null], "null_tests": int(len(pn)),
            "null_rate_1pct": float(np.mean(pn < ALPHA_KS)) if len(pn) else None,
            "null_rate_5pct": float(np.mean(pn < 0.05)) if len(pn) else None,
            "vs_reference_rejections": [c["rejections_1pct"] for c in vref], "vs_reference_tests": int(len(pr)),
            "vs_reference_rate_1pct": float(np.mean(pr < ALPHA_KS)),
            "vs_reference_rate_5pct": float(np.mean(pr < 0.05)),
        }
    # each run's mean against the reference in units of the combined Monte Carlo standard error from the
    # runs' own per-coordinate ESS: mean z^2 ~ 1 when the ESS estimates are honest
    rm, rs, rn = (np.array(ref[k]) for k in ("mean", "sd", "ess"))
    z2 = []
    for r in reps:
        m, s, e = (np.array(r[k]) for k in ("mean", "sd", "ess"))
        z2.append(float(np.mean((m - rm) ** 2 / (rs ** 2 / rn + s ** 2 / e))))
    out["mcse_z2_per_run"] = z2
    out["mcse_z2_mean"] = float(np.mean(z2))
    m = np.mean([r["mean"] for r in reps], axis=0)
    sd = np.array(ref["sd"])
    dz = (m - np.array(ref["mean"])) / sd
    sr = np.mean([r["sd"] for r in reps], axis=0) / sd
    out["average_vs_reference"] = {
        "mean_diff_rms_sd": float(np.sqrt(np.mean(dz ** 2))), "mean_diff_max_sd": float(np.max(np.abs(dz))),
        "mc_error_reference_sd": float(1 / np.sqrt(np.median(ref["ess"]))),
        "mc_error_average_sd": float(1 / np.sqrt(np.sum([np.median(r["ess"]) for r in reps]))),
        "sd_ratio_mean": float(sr.mean()), "sd_ratio_range": [float(sr.min()), float(sr.max())], "dim": d}
    return out


def analyse_laplace(batches: list[dict], wall: float) -> dict:
    """Section 1b: calibration of the Laplace approximation over many datasets."""
    from scipy import stats

    run_mean = np.concatenate([b["run_mean_z"] for b in batches])
    axis = np.concatenate([b["run_mean_z_axis"] for b in batches])
    chi = np.concatenate([b["chi2"] for b in batches])
    cover = np.concatenate([b["cover"] for b in batches])  # (R, levels): per-run fractions
    n = len(run_mean)
    d = int(round(sum(b["count"] for b in batches) / n))
    tq = float(stats.t.ppf(0.975, n - 1))
    cov = []
    for i, lev in enumerate(LEVELS):
        m, se = float(cover[:, i].mean()), float(cover[:, i].std(ddof=1) / np.sqrt(n))
        cov.append({"level": lev, "coverage": m, "cluster_t95": [m - tq * se, m + tq * se]})
    return {
        "datasets": int(n), "coverage": cov, "mean_z": float(run_mean.mean()),
        "mean_z_t_p": float(stats.ttest_1samp(run_mean, 0.0).pvalue), "run_mean_sd": float(run_mean.std(ddof=1)),
        "axis_mean_z": axis.mean(axis=0).tolist(),
        "axis_t_p": [float(stats.ttest_1samp(axis[:, a], 0.0).pvalue) for a in range(3)],
        "rms_z": float(np.sqrt(sum(b["sum_z2"] for b in batches) / sum(b["count"] for b in batches))),
        "chi2_mean": float(chi.mean()), "chi2_ks_p": float(stats.kstest(chi, stats.chi2(d).cdf).pvalue),
        "cpu_seconds": float(sum(b["cpu_seconds"] for b in batches)), "wall_seconds": float(wall),
    }


def analyse_coverage(runs: list[dict], rank_draws: int) -> dict:
    from scipy import stats

    n_runs = len(runs)
    cover = np.array([r["cover"] for r in runs])  # (R, levels, d)
    lap_cover = np.array([r["laplace_cover"] for r in runs])
    d = cover.shape[-1]
    out = {"runs": n_runs, "dim": d, "levels": list(LEVELS), "coverage": []}
    for i, lev in enumerate(LEVELS):
        k, n = int(cover[:, i].sum()), int(cover[:, i].size)
        per_run = cover[:, i].mean(axis=1)
        se = float(per_run.std(ddof=1) / np.sqrt(n_runs)) if n_runs > 1 else float("nan")
        tq = float(stats.t.ppf(0.975, n_runs - 1)) if n_runs > 1 else float("nan")
        # design effect: how much the within-run correlation inflates the binomial variance
        binom_var_run = lev * (1 - lev) / d
        out["coverage"].append({
            "level": lev, "covered": k, "total": n, "pooled": k / n, "wilson95": _wilson(k, n),
            "per_run_mean": float(per_run.mean()), "per_run_sd": float(per_run.std(ddof=1)) if n_runs > 1 else None,
            "per_run_min": float(per_run.min()), "per_run_max": float(per_run.max()),
            "cluster_t95": [float(per_run.mean() - tq * se), float(per_run.mean() + tq * se)],
            "design_effect": float(per_run.var(ddof=1) / binom_var_run) if n_runs > 1 else None,
            "laplace_pooled": float(lap_cover[:, i].mean()),
        })
    out["sbc"] = _sbc(np.array([r["ranks"] for r in runs]), rank_draws)
    if all("ranks_white" in r for r in runs):
        out["sbc_white"] = _sbc(np.array([r["ranks_white"] for r in runs]), rank_draws)
    z = np.array([r["z"] for r in runs])
    zl = np.array([r["z_laplace"] for r in runs])
    run_mean = z.mean(axis=1)
    out["z"] = {"mcmc_mean": float(z.mean()), "mcmc_rms": float(np.sqrt(np.mean(z ** 2))),
                "run_mean_sd": float(run_mean.std(ddof=1)) if n_runs > 1 else None,
                "run_mean_sd_independent": float(1 / np.sqrt(d)),
                "run_mean_t_p": float(stats.ttest_1samp(run_mean, 0.0).pvalue) if n_runs > 1 else None,
                "axis_mean": z.reshape(n_runs, -1, 3).mean(axis=(0, 1)).tolist(),
                "laplace_mean": float(zl.mean()), "laplace_rms": float(np.sqrt(np.mean(zl ** 2))),
                "sd_ratio_laplace_median": float(np.median([r["sd_ratio_laplace"] for r in runs])),
                "sd_ratio_laplace_range": [float(np.min([r["sd_ratio_laplace"] for r in runs])),
                                           float(np.max([r["sd_ratio_laplace"] for r in runs]))]}
    if all("mean_minus_laplace" in r for r in runs):
        dm = np.array([r["mean_minus_laplace"] for r in runs])
        out["z"]["mcmc_minus_laplace_rms"] = float(np.sqrt(np.mean(dm ** 2)))
        out["z"]["mcmc_minus_laplace_max"] = float(np.max(np.abs(dm)))
        out["z"]["mc_error_expected"] = float(np.median([1 / np.sqrt(r["ess_bulk_min"]) for r in runs]))
    chis = {}
    for key in ("chi2_mcmc", "chi2_laplace_cov", "chi2_laplace"):
        v = np.array([r[key] for r in runs])
        chis[key] = {"values": v.tolist(), "mean": float(v.mean()), "expected_mean": float(d),
                     "ks_p": float(stats.kstest(v, stats.chi2(d).cdf).pvalue) if n_runs > 1 else None}
    hp = np.array([r["hotelling_p"] for r in runs])
    if all("inflation" in r for r in runs):
        chis["inflation_mean"] = float(np.mean([r["inflation"] for r in runs]))
    chis["hotelling"] = {"pvalues": hp.tolist(), "ks_uniform_p": float(stats.kstest(hp, "uniform").pvalue)
                         if n_runs > 1 else None, "n_min": int(min(r["hotelling_n"] for r in runs))}
    out["chi2"] = chis
    out["diagnostics"] = {
        "ess_bulk_min": [float(min(r["ess_bulk_min"] for r in runs)), float(np.median([r["ess_bulk_min"] for r in runs]))],
        "rhat_max": float(max(r["rhat_max"] for r in runs)),
        "not_converged": [r["seed"] for r in runs if not r["converged"]],
        "n_draws": sorted({r["n_draws"] for r in runs}),
        "warmup": [int(min(r["warmup"] for r in runs)), int(max(r["warmup"] for r in runs))],
        "iterations": [int(min(r["iterations"] for r in runs)), int(max(r["iterations"] for r in runs))],
        "acceptance_rw": float(np.mean([r["acceptance_rw"] for r in runs])),
        "acceptance_independence": float(np.mean([r["acceptance_independence"] for r in runs])),
        "cpu_seconds_per_run": [float(min(r["cpu_seconds"] for r in runs)),
                                float(np.median([r["cpu_seconds"] for r in runs])),
                                float(max(r["cpu_seconds"] for r in runs))],
    }
    return out


# --------------------------------------------------------------------------- plot


def plot(path: Path, cov: dict) -> None:
    from scipy import stats

    from imu_array_ros.util.plotting import pyplot, save_png

    plt = pyplot(path)

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    sbc = cov["sbc"]
    counts, expected = np.array(sbc["counts"]), np.array(sbc["expected"])
    ax = axes[0]
    ax.bar(np.arange(SBC_BINS) + 0.5, counts, width=0.9, color="#4c72b0")
    n = counts.sum()
    lo, hi = stats.binom.ppf([0.005, 0.995], n, expected.mean() / n)
    ax.fill_between([0, SBC_BINS], [lo] * 2, [hi] * 2, color="0.8", zorder=0,
                    label="99 % band (independent ranks)")
    ax.axhline(expected.mean(), color="k", lw=1)
    if cov.get("sbc_white"):
        sw = cov["sbc_white"]
        ax.step(np.arange(SBC_BINS + 1), np.r_[sw["counts"], sw["counts"][-1]], where="post", color="#c44e52",
                lw=1.5, label=f"whitened coordinates (p = {sw['chi2_p']:.2g})")
    ax.set_xlim(0, SBC_BINS)
    ax.set_xlabel(f"rank of truth among {sbc['rank_draws']} draws (decile)")
    ax.set_ylabel("count (runs x coordinates)")
    ax.set_title(f"SBC ranks (bars: raw coordinates, p = {sbc['chi2_p']:.2g})", fontsize=9)
    ax.legend(fontsize=7, loc="lower center")
    ax = axes[1]
    levs = [c["level"] for c in cov["coverage"]]
    obs = [c["pooled"] for c in cov["coverage"]]
    err = np.array([[c["pooled"] - c["cluster_t95"][0], c["cluster_t95"][1] - c["pooled"]] for c in cov["coverage"]]).T
    x = np.arange(len(levs))
    ax.bar(x - 0.2, levs, width=0.4, color="0.7", label="nominal")
    ax.bar(x + 0.2, obs, width=0.4, color="#dd8452", yerr=err, capsize=3, label="observed (cluster 95 % CI)")
    ax.set_xticks(x, [f"{int(100 * v)} %" for v in levs])
    ax.set_ylim(0, 1.05)
    ax.set_title(f"central-interval coverage, {cov['runs']} runs x {cov['dim']}", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    ax = axes[2]
    d = cov["dim"]
    for key, lab in (("chi2_mcmc", "MCMC mean/cov"), ("chi2_laplace_cov", "MCMC mean, Laplace cov")):
        v = np.sort(cov["chi2"][key]["values"])
        ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post",
                label=f"{lab} (KS p {cov['chi2'][key]['ks_p']:.2g})")
    xs = np.linspace(stats.chi2(d).ppf(0.001), stats.chi2(d).ppf(0.999), 200)
    ax.plot(xs, stats.chi2(d).cdf(xs), "k--", lw=1, label=f"chi2({d})")
    ax.set_xlabel("Mahalanobis chi2 of the truth")
    ax.set_title("chi2 ECDF", fontsize=10)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    save_png(fig, path, dpi=90)


# --------------------------------------------------------------------------- report


def _verdict(ok: bool) -> str:
    return "**pass**" if ok else "**FAIL**"


def summary(res: dict) -> str:
    """The key numbers, one table."""
    cov, cl = res["coverage"], res["cluster"]
    s, sw, ch = cov["sbc"], cov.get("sbc_white"), cov["chi2"]
    c2, c3 = res["compare"]["reference_vs_default"], res["compare"]["rho0.9_vs_rho0"]
    nl = res.get("null")
    text = "## Summary\n\n| check | result |\n|---|---|\n"
    text += ("| coverage 50 / 90 / 95 % (pooled, cluster 95 % CI) | " + "; ".join(
        f"{c['pooled']:.3f} ({c['cluster_t95'][0]:.3f}-{c['cluster_t95'][1]:.3f})" for c in cov["coverage"]) + " |\n")
    lo = res.get("laplace_only")
    if lo:
        text += (f"| same, Laplace approximation over {lo['datasets']} datasets | "
                 + "; ".join(f"{c['coverage']:.4f}" for c in lo["coverage"]) + " |\n")
    text += (f"| SBC rank uniformity, chi-square p: pooled raw coordinates / cluster-robust / whitened pooled | "
             f"{s['chi2_p']:.3g} / {s['cluster_hotelling_p']:.3g} / {sw['chi2_p']:.3g} |\n" if sw else
             f"| SBC rank uniformity, chi-square p: pooled / cluster-robust | {s['chi2_p']:.3g} / "
             f"{s['cluster_hotelling_p']:.3g} |\n")
    text += (f"| chi2({cov['dim']}) KS p: MCMC mean+cov / MCMC mean + Laplace cov / Hotelling | "
             f"{ch['chi2_mcmc']['ks_p']:.3g} / {ch['chi2_laplace_cov']['ks_p']:.3g} / {ch['hotelling']['ks_uniform_p']:.3g} |\n")
    text += (f"| reference vs default, KS rejections at 1 % (of 93): thinned draws/ESS / 2x | "
             f"{c2['rejections_1pct']} / {res['compare'].get('reference_vs_default_thin2', {}).get('rejections_1pct', '—')}"
             + (f" (the test's own null rate at draws/ESS: {nl['thinned']['null_rate_1pct']:.3f}, i.e. "
                f"{93 * nl['thinned']['null_rate_1pct']:.1f} of 93)" if nl else "") + " |\n")
    text += (f"| rho 0.9 vs rho 0 (N = 1), KS rejections at 1 %: draws/ESS / 2x | {c3['rejections_1pct']} / "
             f"{res['compare'].get('rho0.9_vs_rho0_thin2', {}).get('rejections_1pct', '—')} |\n")
    text += (f"| coverage study on Dask ({cov['runs']} runs, {cl['workers']} workers) | {cl['wall_seconds']:.0f} s wall, "
             f"{cl['core_seconds']:.0f} core-s |\n")
    text += f"| whole script | {res['total_wall_seconds']:.0f} s wall |\n\n"
    return text


def _sbc_table(s: dict) -> str:
    return ("| bin | " + " | ".join(str(i + 1) for i in range(s["bins"])) + " |\n|" + "---|" * (s["bins"] + 1)
            + "\n| count | " + " | ".join(str(v) for v in s["counts"])
            + " |\n| expected | " + " | ".join(f"{v:.1f}" for v in s["expected"]) + " |\n\n")


def _sbc_lines(s: dict) -> str:
    return (f"- pooled chi-square uniformity (9 dof; treats every rank as independent): chi2 = {s['chi2']:.1f}, "
            f"**p = {s['chi2_p']:.3g}**; KS of the pooled rank fractions against U(0,1): p = {s['ks_uniform_p']:.3g}\n"
            f"- mean rank fraction {s['mean_rank_fraction']:.3f} (0.5); spread of the per-run mean "
            f"{s['run_mean_rank_sd']:.3f} (independent coordinates: {s['run_mean_rank_sd_independent']:.3f}); "
            f"t-test of the per-run means (runs independent): p = {s['run_mean_rank_t_p']:.3g}\n"
            f"- cluster-robust histogram test (Hotelling T^2 of the per-run bin fractions): p = "
            f"{s['cluster_hotelling_p']:.3g}\n"
            f"- one coordinate per run (run i: coordinate i mod d; independent, weak): counts "
            f"{s['one_per_run_counts']}, chi-square p = {s['one_per_run_chi2_p']:.3g}\n"
            f"- extreme ranks (0 or {s['rank_draws']}): {s['edge_share']:.3f} (expected {s['edge_expected']:.3f}; "
            f"an excess would mean too narrow posteriors or autocorrelated draws)\n")


def markdown(res: dict) -> str:
    a = res["args"]
    text = res.get("header") or machine_header(TITLE)
    text += __doc__.split("\n\nWrites", 1)[0].split("\n\n", 1)[1] + "\n\n"
    text += (f"Runs: {a['runs']} datasets (seeds {COVERAGE_SEED0}..{COVERAGE_SEED0 + a['runs'] - 1}), T = "
             f"{a['samples']} samples each; fixed dataset of sections 2-3: seed {FIXED_SEED}. Wall times are on a "
             f"machine shared with other jobs (see the cores-busy figure).{' **--quick**: a shortened smoke test, not the validation.' if a['quick'] else ''}\n\n")
    text += summary(res)
    cov = res["coverage"]
    cl = res["cluster"]
    d = cov["dim"]
    text += "## 1. Coverage and simulation-based calibration (Dask)\n\n"
    text += (f"{cov['runs']} tasks on a `LocalCluster(n_workers={cl['workers']}, threads_per_worker=1, processes=True)`: "
             f"**{cl['wall_seconds']:.0f} s wall, {cl['core_seconds']:.0f} core-s** (sum of the tasks' CPU time; "
             f"{cl['core_seconds'] / max(cl['wall_seconds'], 1e-9):.2f} cores busy on average; cluster start-up "
             f"{cl['startup_seconds']:.1f} s not counted). Per run: "
             f"{cov['diagnostics']['cpu_seconds_per_run'][0]:.1f} / {cov['diagnostics']['cpu_seconds_per_run'][1]:.1f} / "
             f"{cov['diagnostics']['cpu_seconds_per_run'][2]:.1f} core-s (min / median / max).\n\n")
    dg = cov["diagnostics"]
    text += (f"Sampler diagnostics over the runs: N = {dg['n_draws']}, warm-up {dg['warmup'][0]}-{dg['warmup'][1]}, "
             f"sampling iterations per chain {dg['iterations'][0]}-{dg['iterations'][1]}, min bulk ESS "
             f"{dg['ess_bulk_min'][0]:.0f} (median over runs {dg['ess_bulk_min'][1]:.0f}), max R-hat "
             f"{dg['rhat_max']:.4f}, not converged: {dg['not_converged'] or 'none'}; acceptance random walk "
             f"{dg['acceptance_rw']:.0%}, independence {dg['acceptance_independence']:.0%}.\n\n")
    text += ("### Coverage of the central credible intervals (from all draws)\n\nPooled over runs x coordinates. "
             "The coordinates of one run share the data and are strongly correlated (below), so the naive binomial "
             "(Wilson) interval is too narrow by sqrt(design effect); the cluster interval (t interval of the "
             "per-run coverage fractions, runs independent) is the one to read.\n\n")
    text += ("| level | covered / total | pooled | Wilson 95 % (naive) | per-run mean +- sd (min-max) | "
             "cluster 95 % CI | design effect | Laplace approx., same runs | verdict |\n|---|---|---|---|---|---|---|---|---|\n")
    for c in cov["coverage"]:
        ok = c["cluster_t95"][0] <= c["level"] <= c["cluster_t95"][1]
        text += (f"| {c['level']:.0%} | {c['covered']} / {c['total']} | {c['pooled']:.3f} | "
                 f"{c['wilson95'][0]:.3f}-{c['wilson95'][1]:.3f} | {c['per_run_mean']:.3f} +- "
                 f"{(c['per_run_sd'] or 0):.3f} ({c['per_run_min']:.2f}-{c['per_run_max']:.2f}) | "
                 f"{c['cluster_t95'][0]:.3f}-{c['cluster_t95'][1]:.3f} | {(c['design_effect'] or 0):.1f} | "
                 f"{c['laplace_pooled']:.3f} | {_verdict(ok)} |\n")
    z = cov["z"]
    text += (f"\nStandardised errors (posterior mean - truth) / posterior sd: mean {z['mcmc_mean']:+.3f}, RMS "
             f"{z['mcmc_rms']:.3f} (ideal 0, 1); per axis x/y/z mean "
             + "/".join(f"{v:+.3f}" for v in z["axis_mean"]) +
             f". The per-run mean of the {d} errors spreads by {z['run_mean_sd']:.3f} across runs where independent "
             f"coordinates would give {z['run_mean_sd_independent']:.3f}. t-test of the per-run means "
             f"against 0: p = {z['run_mean_t_p']:.3g}.\n\n")
    if "mcmc_minus_laplace_rms" in z:
        text += (f"MCMC against the Laplace approximation on the same runs: (MCMC mean - Laplace mean) / MCMC sd RMS "
                 f"{z['mcmc_minus_laplace_rms']:.3f}, max {z['mcmc_minus_laplace_max']:.3f} (Monte Carlo error at the "
                 f"runs' min ESS ~{z['mc_error_expected']:.3f}); Laplace sd / MCMC sd median "
                 f"{z['sd_ratio_laplace_median']:.3f} (range {z['sd_ratio_laplace_range'][0]:.2f}-"
                 f"{z['sd_ratio_laplace_range'][1]:.2f}); Laplace errors mean {z['laplace_mean']:+.3f}, RMS "
                 f"{z['laplace_rms']:.3f}.\n\n")
    lo = res.get("laplace_only")
    if lo:
        text += (f"### 1b. The Laplace approximation alone on {lo['datasets']} more datasets\n\n"
                 f"(seeds {LAPLACE_SEED0}.., same setting, {lo['cpu_seconds']:.0f} core-s, {lo['wall_seconds']:.0f} s "
                 f"wall on the cluster) -- the Gaussian posterior the chains reproduce, with {lo['datasets']} "
                 f"independent runs instead of {cov['runs']}:\n\n| level | coverage | cluster 95 % CI |\n|---|---|---|\n")
        for c in lo["coverage"]:
            text += f"| {c['level']:.0%} | {c['coverage']:.4f} | {c['cluster_t95'][0]:.4f}-{c['cluster_t95'][1]:.4f} |\n"
        text += (f"\nMean standardised error {lo['mean_z']:+.4f} (t-test of the per-run means p = {lo['mean_z_t_p']:.3g}; "
                 f"per-run mean spread {lo['run_mean_sd']:.3f}); per axis " + "/".join(f"{v:+.3f}" for v in lo["axis_mean_z"])
                 + " (p " + "/".join(f"{v:.2g}" for v in lo["axis_t_p"]) + f"); RMS {lo['rms_z']:.4f}; chi2({d}) mean "
                 f"{lo['chi2_mean']:.2f}, KS p = {lo['chi2_ks_p']:.3g}.\n\n")
    s = cov["sbc"]
    text += ("### SBC rank histogram\n\n"
             f"Rank of the truth among {s['rank_draws']} draws spread evenly over the pooled chains (ranks "
             f"0..{s['rank_draws']}; spacing >= 4 integrated autocorrelation times at ESS >= 400), {s['bins']} bins. "
             f"Raw coordinates, pooled over runs x coordinates:\n\n" + _sbc_table(s) + _sbc_lines(s) + "\n")
    sw = cov.get("sbc_white")
    if sw:
        text += ("Whitened coordinates w = L^-1 (theta - Laplace mean) (L the Laplace Cholesky factor, a function of the "
                 "data only, so SBC stays exact; the whitened errors are nearly independent within a run, so this pooled "
                 "test is fair):\n\n" + _sbc_table(sw) + _sbc_lines(sw) + "\n")
    valid = [p for p in (s["run_mean_rank_t_p"], s["cluster_hotelling_p"], s["one_per_run_chi2_p"])
             + ((sw["chi2_p"], sw["run_mean_rank_t_p"]) if sw else ()) if p is not None and np.isfinite(p)]
    text += (f"Verdict: naive pooled test on the raw coordinates {_verdict(s['chi2_p'] > 0.01)} (p = {s['chi2_p']:.3g}); "
             f"the tests that respect the within-run correlation (per-run t-test, cluster Hotelling, one coordinate "
             f"per run{', whitened pooled' if sw else ''}) {_verdict(min(valid) > 0.01)} (smallest p = {min(valid):.3g}).\n\n")
    ch = cov["chi2"]
    text += ("### Mahalanobis chi2 of the truth\n\n"
             f"(theta_true - mean)^T Cov^-1 (theta_true - mean) should be chi2({d}) across runs.\n\n"
             f"| mean / covariance | mean of the values (expected {d}) | KS p against chi2({d}) | verdict |\n|---|---|---|---|\n")
    for key, lab in (("chi2_mcmc", "MCMC mean, MCMC covariance (all draws)"),
                     ("chi2_laplace_cov", "MCMC mean, Laplace covariance"),
                     ("chi2_laplace", "Laplace mean and covariance")):
        text += f"| {lab} | {ch[key]['mean']:.1f} | {ch[key]['ks_p']:.3g} | {_verdict(ch[key]['ks_p'] > 0.01)} |\n"
    text += (f"| Hotelling T^2 on ESS-thinned draws (n >= {ch['hotelling']['n_min']}), p-values against U(0,1) | — | "
             f"{ch['hotelling']['ks_uniform_p']:.3g} | {_verdict(ch['hotelling']['ks_uniform_p'] > 0.01)} |\n\n")
    infl = ch.get("inflation_mean")
    if infl:
        text += (f"Inflation of the first row's quadratic form by the estimated covariance, tr(S^-1 Sigma_Laplace) / "
                 f"d, mean over the runs: {infl:.3f} (expected mean of the first row: {d * infl:.1f}).\n\n")
    text += "![SBC ranks and coverage](bayes_validation_ranks.png)\n\n"
    # ---- section 2
    runs = res["chains"]
    text += "## 2. Default sampler against a long plain-PmMH reference chain\n\n"
    text += _chain_table([runs["reference"], runs["default"]])
    text += _compare_text(res["compare"]["reference_vs_default"], "reference", "default")
    if "reference_vs_default_thin2" in res["compare"]:
        c = res["compare"]["reference_vs_default_thin2"]
        text += (f"Robustness, draws thinned twice as much (2 x draws / ESS, less residual autocorrelation): "
                 f"{c['rejections_1pct']} / {len(c['pvalues'])} rejections at 1 %, Bonferroni min p "
                 f"{c['bonferroni_min_p']:.3g}, p-value histogram {c['pvalue_hist']} (chi-square p "
                 f"{c['pvalue_hist_chi2_p']:.3g}).\n\n")
    nl = res.get("null")
    if nl:
        t1, t2 = nl["thinned"], nl["thinned2"]
        av = nl["average_vs_reference"]
        c = res["compare"]["reference_vs_default"]
        from scipy import stats

        p_emp = float(stats.binom.sf(c["rejections_1pct"] - 1, len(c["pvalues"]), t1["null_rate_1pct"])) \
            if t1["null_rate_1pct"] else float("nan")
        text += (f"The KS test's own null: {nl['replicates']} more default-sampler runs on the same dataset with their "
                 f"own seeds ({nl['cpu_seconds']:.0f} core-s): the same test between pairs of them (same target, so "
                 "every rejection is a false one) and each of them against the reference.\n\n"
                 "| thinning | default vs default (null): rejections at 1 % per pair | null rate at 1 % / 5 % | "
                 "reference vs each default: rejections | rate at 1 % / 5 % |\n|---|---|---|---|---|\n"
                 f"| draws / ESS | {t1['null_rejections']} | {t1['null_rate_1pct']:.3f} / {t1['null_rate_5pct']:.3f} | "
                 f"{t1['vs_reference_rejections']} | {t1['vs_reference_rate_1pct']:.3f} / {t1['vs_reference_rate_5pct']:.3f} |\n"
                 f"| 2 x draws / ESS | {t2['null_rejections']} | {t2['null_rate_1pct']:.3f} / {t2['null_rate_5pct']:.3f} | "
                 f"{t2['vs_reference_rejections']} | {t2['vs_reference_rate_1pct']:.3f} / {t2['vs_reference_rate_5pct']:.3f} |\n\n"
                 "| measure | value |\n|---|---|\n"
                 f"| each replicate's mean against the reference, in combined Monte Carlo standard errors (both runs' "
                 f"per-coordinate ESS): mean z^2 over the replicates (1 expected) | {nl['mcse_z2_mean']:.2f} (per run "
                 + ", ".join(f"{v:.2f}" for v in nl["mcse_z2_per_run"]) + ") |\n"
                 f"| reference vs default ({c['rejections_1pct']} rejections above): binomial P(>= observed) at the "
                 f"empirical null rate | {p_emp:.3g} |\n"
                 f"| the replicates' average against the reference: mean difference RMS / max (sd) | "
                 f"{av['mean_diff_rms_sd']:.4f} / {av['mean_diff_max_sd']:.4f} |\n"
                 f"| Monte Carlo error of that difference from the reference / from the average (sd) | "
                 f"{av['mc_error_reference_sd']:.4f} / {av['mc_error_average_sd']:.4f} |\n"
                 f"| sd ratio, mean (range) | {av['sd_ratio_mean']:.4f} ({av['sd_ratio_range'][0]:.3f}-"
                 f"{av['sd_ratio_range'][1]:.3f}) |\n"
                 "| verdict against the test's own null (P >= 0.01 and reference-vs-default rate <= 2 x null rate "
                 f"+ 0.01) | {_verdict(p_emp > 0.01 and t1['vs_reference_rate_1pct'] <= 2 * t1['null_rate_1pct'] + 0.01)} "
                 "|\n\n")
    # ---- section 3
    text += "## 3. Correlated pseudo-marginal keeps the target (N = 1, random walk only)\n\n"
    text += ("Both at ESS 1000 instead of the default 400 (a pure random walk in 93 dimensions reaches ESS 400 well "
             "before the max split R-hat over 94 series falls below 1.01). Sampler seeds differ per "
             "configuration.\n\n")
    text += _chain_table([runs["rho0.9"], runs["rho0"]])
    text += _compare_text(res["compare"]["rho0.9_vs_rho0"], "rho 0.9", "rho 0")
    if "rho0.9_vs_rho0_thin2" in res["compare"]:
        c = res["compare"]["rho0.9_vs_rho0_thin2"]
        text += (f"Thinned twice as much: {c['rejections_1pct']} / {len(c['pvalues'])} rejections at 1 %, Bonferroni "
                 f"min p {c['bonferroni_min_p']:.3g}.\n\n")
    null_rate = nl["thinned"]["null_rate_1pct"] if nl else None
    for key in ("rho0.9_vs_rho0", "rho0.9_vs_reference", "rho0_vs_reference"):
        c = res["compare"][key]
        emp = ""
        if null_rate:
            from scipy import stats

            emp = (f", binomial P(>= observed) at the empirical null rate {null_rate:.3f}: "
                   f"{float(stats.binom.sf(c['rejections_1pct'] - 1, len(c['pvalues']), null_rate)):.3g}")
        text += (f"- {c['a']} against {c['b']}: {c['rejections_1pct']} / {len(c['pvalues'])} rejections at "
                 f"1 %{emp}; Bonferroni min p {c['bonferroni_min_p']:.3g}; p-value histogram chi-square p "
                 f"{c['pvalue_hist_chi2_p']:.3g}\n")
    r9, r0 = runs["rho0.9"], runs["rho0"]
    text += (f"\nLog-likelihood-ratio noise at the posterior mean (sd of ll(theta, u') - ll(theta, u), u' the chain's "
             f"proposal of the random numbers, 256 replicates): rho 0.9: {r9['llr_noise_sd']:.3f}, rho 0: "
             f"{r0['llr_noise_sd']:.3f} (ratio {r9['llr_noise_sd'] / r0['llr_noise_sd']:.2f}; sqrt(1 - 0.9) = 0.32 "
             f"for a log-likelihood linear in u). ESS per core-second (min bulk ESS / sampler CPU incl. its "
             f"diagnostics): rho 0.9: {r9['ess_bulk_min'] / r9['sampler_cpu_seconds']:.2f}, rho 0: "
             f"{r0['ess_bulk_min'] / r0['sampler_cpu_seconds']:.2f}.\n\n")
    text += (f"Sections 2-3 ran as {4 + (nl['replicates'] if nl else 0)} Dask tasks on the same cluster: "
             f"{res['chains_wall_seconds']:.0f} s wall. "
             f"Whole script: {res['total_wall_seconds']:.0f} s wall.\n")
    return text


def _chain_table(rows: list[dict]) -> str:
    text = ("| run | settings | N | warm-up | iterations/chain | acceptance RW / ind. | min bulk ESS | max R-hat | "
            "sampler core-s | ESS / core-s |\n|---|---|---|---|---|---|---|---|---|---|\n")
    for r in rows:
        ai = "—" if r["acceptance_independence"] is None else f"{r['acceptance_independence']:.0%}"
        sett = ", ".join(f"{k}={v}" for k, v in r["settings"].items()) or "defaults"
        text += (f"| {r['label']} | {sett} | {r['n_draws']} | {r['warmup']} | {r['iterations']} | "
                 f"{r['acceptance_rw']:.0%} / {ai} | {r['ess_bulk_min']:.0f} | {r['rhat_max']:.4f} | "
                 f"{r['sampler_cpu_seconds']:.0f} | {r['ess_bulk_min'] / r['sampler_cpu_seconds']:.2f} |\n")
    return text + "\n"


def _compare_text(c: dict, la: str, lb: str) -> str:
    d = len(c["pvalues"])
    ok = c["bonferroni_min_p"] > 0.01 and c["binomial_p_rejections"] > 0.01
    return (f"Per-coordinate two-sample KS test of draws thinned within each chain by ~ draws / ESS of the "
            f"coordinate ({la}: {c['thinned_sizes_a'][0]}-{c['thinned_sizes_a'][1]}, {lb}: "
            f"{c['thinned_sizes_b'][0]}-{c['thinned_sizes_b'][1]} draws per coordinate):\n\n"
            f"- rejections at 1 %: **{c['rejections_1pct']} / {d}** (expected {c['expected_rejections']:.2f}; "
            f"binomial P(>= observed) = {c['binomial_p_rejections']:.3g})\n"
            f"- smallest p {c['min_p']:.3g}, Bonferroni-corrected **{c['bonferroni_min_p']:.3g}**\n"
            f"- p-value histogram (10 bins): {c['pvalue_hist']}, chi-square uniformity p = "
            f"{c['pvalue_hist_chi2_p']:.3g}; KS against U(0,1) p = {c['pvalue_ks_uniform_p']:.3g}\n"
            f"- largest |mean difference| {c['max_abs_mean_diff_in_sd']:.3f} sd of {lb}; sd ratio "
            f"{c['sd_ratio_range'][0]:.3f}-{c['sd_ratio_range'][1]:.3f}\n"
            f"- verdict, taking the nominal 1 % at face value: {_verdict(ok)}\n\n")


# --------------------------------------------------------------------------- main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=50, help="datasets in the coverage study (default 50)")
    ap.add_argument("--samples", type=int, default=50, help="time samples T per dataset (default 50)")
    ap.add_argument("--rank-draws", type=int, default=99, help="posterior draws per SBC rank (default 99)")
    ap.add_argument("--laplace-runs", type=int, default=2000,
                    help="datasets of the Laplace-only check (section 1b, ~0.1 core-s each; default 2000)")
    ap.add_argument("--replicates", type=int, default=10,
                    help="extra default-sampler runs on the fixed dataset: the KS test's own null (default 10)")
    ap.add_argument("--workers", type=int, default=2, help="Dask worker processes (default 2)")
    ap.add_argument("--quick", action="store_true", help="smoke test: 6 runs, short reference chain")
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--raw", type=Path, default=None,
                    help="re-analyse the raw task results saved by a previous run (printed path) instead of running")
    ap.add_argument("--render", action="store_true", help="only re-write the .md and .png from the saved .json")
    args = ap.parse_args()
    if args.render:
        render(json.loads(args.out.with_suffix(".json").read_text()), args.out)
        return 0
    if args.quick and args.runs == 50:
        args.runs = 6
    if args.quick and args.laplace_runs == 2000:
        args.laplace_runs = 100
    if args.quick and args.replicates == 10:
        args.replicates = 2
    ref_ess = 4000.0
    res = {"args": {"runs": args.runs, "samples": args.samples, "rank_draws": args.rank_draws,
                    "laplace_runs": args.laplace_runs,
                    "workers": args.workers, "quick": args.quick, "reference_ess": ref_ess}}
    # section 3 asks for ESS 1000 (not the default 400): a random walk in 93 dimensions reaches ESS 400 long
    # before the max split R-hat over 94 series drops below 1.01, and the sampler then extends by one chunk per
    # round, re-diagnosing every draw each time; a larger ESS target gets there geometrically
    rho_ess = 1000.0
    chain_specs = {
        "reference": {"rho": 0.0, "independence": 0.0, "ess": ref_ess},
        "default": {},
        "rho0.9": {"n_draws": 1, "rho": 0.9, "independence": 0.0, "ess": rho_ess},
        "rho0": {"n_draws": 1, "rho": 0.0, "independence": 0.0, "ess": rho_ess},
    }
    if args.quick:  # bounded smoke test: short chains, not converged
        chain_specs["reference"].update(ess=600.0, max_warmup=10000, max_iterations=40000)
        for k in ("rho0.9", "rho0"):
            chain_specs[k].update(ess=200.0, max_warmup=10000, max_iterations=20000)
    if args.raw is not None and args.raw.exists():  # re-analyse saved raw results
        import pickle

        raw = pickle.loads(args.raw.read_bytes())
    else:
        import pickle
        import tempfile

        raw = run_all(args, chain_specs)
        # kept outside the repository so a failure of the analysis below loses no simulation (--raw PATH)
        saved = Path(tempfile.gettempdir()) / f"{args.out.name}.raw.pkl"
        saved.write_bytes(pickle.dumps(raw))
        print(f"raw results saved to {saved}", flush=True)
    runs, chains = raw["runs"], raw["chains"]
    res["cluster"] = raw["cluster"]
    res["chains_wall_seconds"] = raw["chains_wall_seconds"]
    res["total_wall_seconds"] = raw["total_wall_seconds"]
    res["coverage"] = analyse_coverage(runs, args.rank_draws)
    if raw.get("laplace_batches"):
        res["laplace_only"] = analyse_laplace(raw["laplace_batches"], raw["laplace_wall_seconds"])
    res["coverage_runs"] = runs
    res["compare"] = {
        "reference_vs_default": compare(chains["reference"], chains["default"]),
        "rho0.9_vs_rho0": compare(chains["rho0.9"], chains["rho0"]),
        "rho0.9_vs_reference": compare(chains["rho0.9"], chains["reference"]),
        "rho0_vs_reference": compare(chains["rho0"], chains["reference"]),
    }
    if all("thinned2" in c for c in chains.values()):
        res["compare"]["reference_vs_default_thin2"] = compare(chains["reference"], chains["default"], "thinned2")
        res["compare"]["rho0.9_vs_rho0_thin2"] = compare(chains["rho0.9"], chains["rho0"], "thinned2")
    if raw.get("replicates"):
        res["null"] = analyse_null(raw["replicates"], chains["reference"])
    res["chains"] = {k: {kk: vv for kk, vv in v.items() if kk not in ("thinned", "thinned2")} for k, v in chains.items()}
    res["header"] = raw["header"]
    res["machine"] = {line.split(":", 1)[0].lstrip("- "): line.split(":", 1)[1].strip()
                      for line in res["header"].split("\n") if line.startswith("- ") and ":" in line}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(res, indent=1) + "\n")
    render(res, args.out)
    return 0


def run_all(args, chain_specs: dict) -> dict:
    """The Dask part: the coverage tasks, then the four sampler runs on the fixed dataset."""
    from distributed import as_completed

    from imu_array_ros.calibration import bayes

    header = machine_header(TITLE)
    t_start = time.perf_counter()
    with bayes.dask_client("local", args.workers) as client:
        startup = time.perf_counter() - t_start
        print(f"cluster up in {startup:.1f} s: {client}", flush=True)
        # ---- 1. coverage: one task per dataset
        t0 = time.perf_counter()
        futs = [client.submit(coverage_run, COVERAGE_SEED0 + i, args.samples, args.rank_draws, pure=False)
                for i in range(args.runs)]
        runs = []
        for fut in as_completed(futs):
            r = fut.result()
            runs.append(r)
            print(f"[{len(runs)}/{args.runs}] seed {r['seed']}: cpu {r['cpu_seconds']:.1f} s, ESS {r['ess_bulk_min']:.0f}, "
                  f"R-hat {r['rhat_max']:.4f}, chi2 {r['chi2_mcmc']:.1f}, coverage "
                  f"{np.mean(r['cover'], axis=1).round(2).tolist()}", flush=True)
        wall = time.perf_counter() - t0
        runs.sort(key=lambda r: r["seed"])
        cluster = {"workers": args.workers, "wall_seconds": wall, "startup_seconds": startup,
                   "core_seconds": float(sum(r["cpu_seconds"] for r in runs)),
                   "task_wall_seconds": float(sum(r["wall_seconds"] for r in runs)),
                   "worker_pids": sorted({r["pid"] for r in runs})}
        print(f"coverage study: {wall:.0f} s wall, {cluster['core_seconds']:.0f} core-s", flush=True)
        # ---- 1b. the Laplace approximation alone on many more datasets
        t0 = time.perf_counter()
        seeds = LAPLACE_SEED0 + np.arange(args.laplace_runs)
        futs = [client.submit(laplace_batch, chunk.tolist(), args.samples, pure=False)
                for chunk in np.array_split(seeds, max(1, args.laplace_runs // 50))]
        lap_batches = client.gather(futs)
        lap_wall = time.perf_counter() - t0
        print(f"laplace-only: {args.laplace_runs} datasets, {lap_wall:.0f} s wall", flush=True)
        # ---- 2-3. the fixed dataset (the reference is the longest task: submitted first)
        t0 = time.perf_counter()
        futs = [client.submit(chain_run, k, FIXED_SEED, args.samples, v, FIXED_SEED * 1000 + i, pure=False)
                for i, (k, v) in enumerate(chain_specs.items())]
        # replicates of the default sampler (own seeds): the null distribution of the two-sample test itself
        futs += [client.submit(chain_run, f"default#{i}", FIXED_SEED, args.samples, {}, FIXED_SEED * 1000 + 100 + i,
                               pure=False) for i in range(args.replicates)]
        chains, replicates = {}, []
        for fut in as_completed(futs):
            r = fut.result()
            if "#" in r["label"]:
                replicates.append(r)
                continue
            chains[r["label"]] = r
            print(f"chain run {r['label']}: {r['iterations']} iterations/chain after {r['warmup']} warm-up, ESS "
                  f"{r['ess_bulk_min']:.0f}, R-hat {r['rhat_max']:.4f}, {r['sampler_cpu_seconds']:.0f} core-s", flush=True)
        chains_wall = time.perf_counter() - t0
    replicates.sort(key=lambda r: r["sampler_seed"])
    return {"runs": runs, "chains": chains, "replicates": replicates, "cluster": cluster,
            "chains_wall_seconds": chains_wall,
            "laplace_batches": lap_batches, "laplace_wall_seconds": lap_wall,
            "total_wall_seconds": time.perf_counter() - t_start, "header": header}


def render(res: dict, out: Path) -> None:
    """The markdown and the PNG of a result (also from a saved .json: ``--render``)."""
    png = out.parent / (out.name + "_ranks.png")
    plot(png, res["coverage"])
    write_results(out.with_suffix(".md"), markdown(res))
    print(f"wrote {out.with_suffix('.md')}, .json, {png.name}; total {res['total_wall_seconds']:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
