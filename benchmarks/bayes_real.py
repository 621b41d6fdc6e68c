"""The Bayesian (PmMH) position calibration on the six real MIMU4444BT captures (carlsson2021 Sec. IV-B/C).

For each capture ../shared/data/openshoe_mimu4444bt/exp_N.bin, imported with the nominal description
config/mimu4444bt_corners.yaml (``import_capture(path, desc)[0]``), as ``imu-array calibrate bayes``
does per recording: T = 500 samples spread evenly over the usable ones (``select_samples``),
``build_problem`` (reference imu_1 held, gaussian prior N(nominal, 3 mm)), ``laplace`` (ML on the same
samples + CRB + prior), ``sample_posterior`` (4 chains on 2 worker processes, Laplace-shaped random walk
mixed with independence proposals, ESS >= 400, R-hat <= 1.01 -- capped, see below), in two noise settings:

(a) the description's accelerometer noise (0.045 m/s^2) and p(omega | gyroscopes) from the gyroscope
    noise model (eq. 26b, ``omega_covariance="model"``);
(b) carlsson2021's real-data setting: sigma_a = 0.79 m/s^2 (the MPU-9150 non-linearity at full scale)
    and the gyroscopes' sample covariance at each sample (eq. 30, ``omega_covariance="sample"``).

Per capture and setting: the posterior mean and std per IMU, ESS / R-hat / time, the ML estimate on
every usable sample of the capture (``calibrate_geometry``, joint solver, same accelerometer noise) with
its CRB, and the Laplace agreement (``laplace_agreement``).  Then whether the captures' posteriors agree
with each other (pairwise differences of the means against the combined posterior covariance) and with
the ML/CRB, and a carlsson2021 Fig. 5-style plot per setting, one colour per capture.

Writes benchmarks/results/bayes_real.md, bayes_real.json, bayes_real_ellipses_a.png,
bayes_real_ellipses_b.png, bayes_real_trace_a.png, bayes_real_trace_b.png.

    python benchmarks/bayes_real.py [--captures 1 2 ...] [--samples 500] [--draws 16] [--report-only]
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_header  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"
DESC = REPO / "config" / "mimu4444bt_corners.yaml"
RESULTS = REPO / "benchmarks" / "results"
NAME = "bayes_real"
UM, MM = 1e6, 1e3
#: carlsson2021 Sec. IV-B: sigma_a covering the MPU-9150's non-linearity (0.5 % of 157 m/s^2)
PAPER_SIGMA_A = 0.79
#: the two settings: label -> (accelerometer std (None: the description's), omega covariance, description)
SETTINGS = {
    "a": (None, "model", "description's sigma_a (0.045 m/s^2), omega covariance from the gyroscope noise model"),
    "b": (PAPER_SIGMA_A, "sample", "sigma_a = 0.79 m/s^2 (carlsson2021), gyroscopes' sample covariance (eq. 30)"),
}
#: correlation of the random numbers per setting (see "Choices" in the report; measured, not guessed)
RHO = {"a": 0.99, "b": 0.99}
#: a sample "is moving" (hand twisting, not a static pose) when the mean over the IMUs of |gyro| exceeds this
MOVING_RAD_S = 1.0
#: replicates of the log-likelihood for the variance table and of the log acceptance ratio noise
REPLICATES = 24
VAR_NS = (16, 64, 1024)


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                             timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "imu_array_ros"], cwd=REPO,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return out.stdout.strip() + (" + uncommitted changes in imu_array_ros/" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def ratio_noise(problem, theta, step_chol, rho: float, rng, replicates: int = REPLICATES) -> float:
    """sd of the estimated log acceptance ratio log p_N(theta', u') - log p_N(theta, u) over the random
    numbers, theta' one typical random-walk step (2.38/sqrt(d) Laplace) from theta, u' = rho u + ..."""
    d = problem.dim
    theta2 = theta + 2.38 / np.sqrt(d) * step_chol @ rng.standard_normal(d)
    shape = (problem.n_samples, problem.n_draws, 3)
    diffs = []
    for _ in range(replicates):
        u = rng.standard_normal(shape)
        u2 = rho * u + np.sqrt(1 - rho ** 2) * rng.standard_normal(shape)
        diffs.append(problem.loglik(theta2, u2) - problem.loglik(theta, u))
    return float(np.std(diffs, ddof=1))


def per_imu(free: np.ndarray, vec: np.ndarray, cov: np.ndarray, k: int):
    """(K, 3) positions and (K, 3, 3) covariances (reference rows zero) from free-coordinate vectors."""
    pos = np.zeros((k, 3))
    c = np.zeros((k, 3, 3))
    for j, i in enumerate(free):
        pos[i] = vec[3 * j:3 * j + 3]
        c[i] = cov[3 * j:3 * j + 3, 3 * j:3 * j + 3]
    return pos, c


def run_capture(i: int, desc, model, args) -> dict:
    """Everything for one capture: both settings."""
    from imu_array_ros.calibration import bayes, bayes_sampler
    from imu_array_ros.calibration.bayes_sampler import _diagnostics
    from imu_array_ros.calibration.geometry import calibrate_geometry
    from imu_array_ros.errors import CalibrationError
    from imu_array_ros.io.openshoe.capture import import_capture

    samples = import_capture(DATA / f"exp_{i}.bin", desc)[0]
    stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
    t0 = time.perf_counter()
    idx, dropped, usable = bayes.select_samples(stamps, accel, gyro, model, args.samples)
    select_s = time.perf_counter() - t0
    rate = np.mean(np.linalg.norm(gyro, axis=2), axis=1)  # rotation invariant: mean over IMUs of |gyro|
    valid_all = model.valid(accel, gyro).all(axis=(1, 2))
    st, acc, gyr = stamps[idx], accel[idx], gyro[idx]
    out = {
        "capture": f"exp_{i}", "samples_total": int(len(stamps)), "usable": int(usable),
        "dropped": {k: int(v) for k, v in dropped.items()}, "selected": int(len(idx)),
        "moving_in_capture": int(np.sum(valid_all & (rate > MOVING_RAD_S))),
        "moving_selected": int(np.sum(rate[idx] > MOVING_RAD_S)),
        "max_gyro_over_clip_selected": float(np.max(np.abs(gyr)) / model.gyro_clip),
        "max_acc_over_clip_selected": float(np.max(np.abs(acc)) / model.acc_clip),
        "select_seconds": select_s, "settings": {},
    }
    say(f"exp_{i}: {len(idx)} of {usable} usable samples ({len(stamps)} total, dropped {dropped}); "
        f"{out['moving_selected']} of the selected have mean |gyro| > {MOVING_RAD_S} rad/s")
    k = model.n_imus
    # the diagnostic: the same number of samples spread over the usable samples that are moving (Laplace only)
    all_idx, _, _ = bayes.select_samples(stamps, accel, gyro, model, None)
    mov = all_idx[rate[all_idx] > MOVING_RAD_S]
    mov = mov[np.round(np.linspace(0, len(mov) - 1, min(args.samples, len(mov)))).astype(int)]
    out["moving_only"] = {"usable_moving": int(np.sum(rate[all_idx] > MOVING_RAD_S)), "selected": int(len(mov)),
                          "settings": {}}
    for label, (accel_std, omega_cov, _) in SETTINGS.items():
        if label not in args.settings:
            continue
        try:
            pm = bayes.build_problem(stamps[mov], accel[mov], gyro[mov], model, reference=0, accel_std=accel_std,
                                     omega_covariance=omega_cov)
            lm = bayes.laplace(pm, stamps[mov], accel[mov], gyro[mov], model)
            out["moving_only"]["settings"][label] = {"mean_free": lm.mean.tolist(), "cov_free": lm.covariance.tolist()}
        except CalibrationError as err:
            out["moving_only"]["settings"][label] = {"error": str(err)}
    for label, (accel_std, omega_cov, _) in SETTINGS.items():
        if label not in args.settings:
            continue
        rec = {"accel_std": accel_std if accel_std is not None else float(np.mean(model.acc_std)),
               "omega_covariance": omega_cov, "rho": RHO[label], "n_draws": args.draws}
        out["settings"][label] = rec
        rng = np.random.default_rng(1000 * i + ord(label))
        try:
            t0 = time.perf_counter()
            problem = bayes.build_problem(st, acc, gyr, model, reference=0, accel_std=accel_std,
                                          omega_covariance=omega_cov)
            lap = bayes.laplace(problem, st, acc, gyr, model)
            rec["laplace_seconds"] = time.perf_counter() - t0
            lap_chol = np.linalg.cholesky(lap.covariance)
            t0 = time.perf_counter()
            rec["var_loglik"] = {int(n): bayes.loglik_variance(problem.with_(n_draws=n), lap.mean, REPLICATES, rng)
                                 for n in VAR_NS}
            p_n = problem.with_(n_draws=args.draws)
            rec["ratio_noise_sd"] = {str(r): ratio_noise(p_n, lap.mean, lap_chol, r, rng)
                                     for r in sorted({0.0, 0.9, RHO[label], 0.999})}
            rec["noise_seconds"] = time.perf_counter() - t0
            settings = bayes_sampler.SamplerSettings(
                chains=args.chains, workers=args.workers, n_draws=args.draws, rho=RHO[label], seed=i,
                max_warmup=args.max_warmup, max_iterations=args.max_iterations)
            rec["sampler_settings"] = dataclasses.asdict(settings)
            post = bayes_sampler.sample_posterior(problem, lap, settings,
                                                  progress=lambda s, lab=label: say(f"exp_{i} ({lab}): {s}"))
        except CalibrationError as err:
            rec["error"] = str(err)
            say(f"exp_{i} ({label}): FAILED: {err}")
            continue
        say(f"exp_{i} ({label}): {post.summary_line()}")
        mean, cov = post.mean, post.covariance
        ess_t, ess_tail_t, rhat_t = _diagnostics(post.draws)  # theta alone (the sampler adds the log-lik)
        _, _, rhat_ll = _diagnostics(post.loglik[..., None])
        rec.update({
            "summary": post.summary_line(),
            "chains": int(post.draws.shape[0]), "draws_per_chain": int(post.draws.shape[1]),
            "warmup_per_chain": int(post.warmup),
            "acceptance_random_walk": post.acceptance.tolist(),
            "acceptance_independence": post.acceptance_independence.tolist(),
            "ess_bulk_min": post.ess_bulk_min, "ess_tail_min": post.ess_tail_min, "rhat_max": post.rhat_max,
            "converged": bool(post.converged), "seconds": post.seconds, "cpu_seconds": post.cpu_seconds,
            "theta_only": {"ess_bulk_min": ess_t, "ess_tail_min": ess_tail_t, "rhat_max": rhat_t},
            "rhat_loglik_estimate": rhat_ll,
            "loglik_chain_means": post.loglik.mean(axis=1).tolist(),
            "loglik_chain_sds": post.loglik.std(axis=1).tolist(),
            "mean_free": mean.tolist(), "cov_free": cov.tolist(),
            "laplace_mean_free": lap.mean.tolist(), "laplace_cov_free": lap.covariance.tolist(),
            "laplace_agreement": bayes_sampler.laplace_agreement(post),
        })
        rec["_post"] = post  # for the trace plot; dropped before writing JSON
        # the ML estimate on every usable sample of the capture, same accelerometer noise
        m = model if accel_std is None else dataclasses.replace(model, acc_std=np.full((k, 3), float(accel_std)))
        t0 = time.perf_counter()
        try:
            geo = calibrate_geometry(stamps, accel, gyro, m, reference=0)
        except CalibrationError as err:
            rec["ml_error"] = str(err)
            say(f"exp_{i} ({label}): ML FAILED: {err}")
            continue
        pos = geo.positions - geo.positions[0] + model.positions[0]
        fidx = (3 * problem.free[:, None] + np.arange(3)).reshape(-1)
        crb = geo.covariance[np.ix_(fidx, fidx)]
        rec["ml"] = {"positions": pos.tolist(), "theta": problem.theta_of(pos).tolist(),
                     "crb_free": (0.5 * (crb + crb.T)).tolist(), "samples_used": int(geo.samples_used),
                     "iterations": int(geo.iterations), "converged": bool(geo.converged),
                     "nis_before": float(geo.nis_before), "nis_after": float(geo.nis_after),
                     "seconds": time.perf_counter() - t0}
        say(f"exp_{i} ({label}): ML on {geo.samples_used} samples, NIS {geo.nis_before:.4g} -> {geo.nis_after:.4g}, "
            f"{rec['ml']['seconds']:.1f} s")
    return out


# --------------------------------------------------------------------------- comparisons


def compare(results: list[dict], label: str, names, free) -> dict:
    """Cross-capture agreement of the posteriors of setting ``label``, and with the ML/CRB."""
    caps = [r for r in results if label in r["settings"] and "mean_free" in r["settings"][label]]
    out = {"captures": [r["capture"] for r in caps], "pairs": []}
    if not caps:
        return out
    means = np.array([r["settings"][label]["mean_free"] for r in caps])
    covs = np.array([r["settings"][label]["cov_free"] for r in caps])
    out.update(agreement(means, covs, [r["capture"] for r in caps], names, free))
    sds = np.sqrt(np.einsum("cii->ci", covs))
    # the diagnostic: Laplace on moving samples only
    mo = [r["moving_only"]["settings"].get(label, {}) for r in results]
    if all("mean_free" in m for m in mo) and len(mo) > 1:
        out["moving_only"] = agreement(np.array([m["mean_free"] for m in mo]), np.array([m["cov_free"] for m in mo]),
                                       [r["capture"] for r in results], names, free)
        out["moving_only"]["sd_median_um"] = float(np.median(np.sqrt(np.einsum(
            "cii->ci", np.array([m["cov_free"] for m in mo])))) * UM)
    # ML on all usable samples, and its CRB
    mls = [np.array(r["settings"][label]["ml"]["theta"]) if "ml" in r["settings"][label] else None for r in caps]
    if all(m is not None for m in mls):
        mls = np.array(mls)
        crbs = np.array([np.sqrt(np.diag(r["settings"][label]["ml"]["crb_free"])) for r in caps])
        zml = (means - mls) / sds
        out["ml"] = {
            "z_post_vs_ml": zml.tolist(),
            "max_abs_z_per_capture": np.max(np.abs(zml), axis=1).tolist(),
            "rms_z_per_capture": np.sqrt(np.mean(zml ** 2, axis=1)).tolist(),
            "crb_sd_median_um": float(np.median(crbs) * UM),
            "post_sd_median_um": float(np.median(sds) * UM),
            "ml_scatter_um": (mls.std(axis=0, ddof=1) * UM).tolist() if len(caps) > 1 else None,
            "ml_scatter_over_crb_median": float(np.median(mls.std(axis=0, ddof=1) / np.sqrt(np.mean(crbs ** 2, axis=0))))
            if len(caps) > 1 else None,
            "post_minus_ml_rms_um": float(np.sqrt(np.mean((means - mls) ** 2)) * UM),
        }
    return out


def agreement(means: np.ndarray, covs: np.ndarray, caps: list[str], names, free) -> dict:
    """Pairwise z / chi2 of the means (C, d) with the combined covariances (C, d, d), and the scatter."""
    from scipy.stats import chi2

    out = {"pairs": []}
    d = means.shape[1]
    sds = np.sqrt(np.einsum("cii->ci", covs))
    for a in range(len(caps)):
        for b in range(a + 1, len(caps)):
            diff = means[a] - means[b]
            c = covs[a] + covs[b]
            z = diff / np.sqrt(np.diag(c))
            x2 = float(diff @ np.linalg.solve(c, diff))
            imu = {}
            for j, name in enumerate(names[f] for f in free):
                s = slice(3 * j, 3 * j + 3)
                xk = float(diff[s] @ np.linalg.solve(c[s, s], diff[s]))
                imu[name] = {"z": z[s].tolist(), "chi2": xk, "p": float(chi2.sf(xk, 3))}
            out["pairs"].append({"pair": [caps[a], caps[b]], "chi2": x2, "dof": d,
                                 "p": float(chi2.sf(x2, d)), "max_abs_z": float(np.max(np.abs(z))),
                                 "median_abs_z": float(np.median(np.abs(z))), "imu": imu})
    # scatter of the posterior means across captures vs the posterior std
    if len(caps) > 1:
        scatter = means.std(axis=0, ddof=1)
        rms_sd = np.sqrt(np.mean(sds ** 2, axis=0))
        out["scatter_um"] = (scatter * UM).tolist()
        out["posterior_sd_rms_um"] = (rms_sd * UM).tolist()
        out["scatter_over_sd"] = (scatter / rms_sd).tolist()
        # the paired differences pooled: their z should be N(0,1) if the posteriors are right
        allz = np.concatenate([np.asarray([p["imu"][n]["z"] for n in p["imu"]]).ravel() for p in out["pairs"]])
        out["pooled_z_rms"] = float(np.sqrt(np.mean(allz ** 2)))
        out["fraction_abs_z_gt_2"] = float(np.mean(np.abs(allz) > 2))
    return out


# --------------------------------------------------------------------------- report


def _f(x, spec=".3g"):
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


TITLE = "Bayesian (PmMH) position calibration on the real MIMU4444BT captures"


def markdown(results, comps, names, nominal, free, args, total_s, header: str | None = None) -> str:
    axes = "xyz"
    if header is None:
        md = machine_header(TITLE)
        md += f"- run time: {total_s:.0f} s (whole script, 12 posteriors one after the other; machine shared with other work)\n"
        md += f"- code: {_commit()}\n\n"
    else:
        md = header
    md += __doc__.split("\n\n", 1)[1].rsplit("\n\n", 2)[0] + "\n\n"

    # ---- summary (numbers only; the reading of them follows each section)
    md += "## Summary\n\n"
    for label, (_, _, text) in SETTINGS.items():
        c = comps.get(label) or {}
        recs = [r["settings"][label] for r in results if label in r["settings"]]
        ok = [s for s in recs if "mean_free" in s]
        if not ok:
            md += f"- **({label}) {text}**: no posterior.\n"
            continue
        sd_med = float(np.median([np.sqrt(np.diag(s["cov_free"])) for s in ok]) * UM)
        n_conv = sum(s["converged"] for s in ok)
        th = [s["theta_only"] for s in ok]
        n_th = sum(t["ess_bulk_min"] >= args.ess and t["rhat_max"] <= 1.01 for t in th)
        line = (f"- **({label}) {text}**: posterior std median {sd_med:.3g} um; sampler convergence "
                f"(ESS >= {args.ess:g}, R-hat of positions and log-likelihood estimate <= 1.01) reached by {n_conv} "
                f"of {len(ok)} within the caps; the positions alone: ESS bulk "
                f"{min(t['ess_bulk_min'] for t in th):.0f}-{max(t['ess_bulk_min'] for t in th):.0f}, R-hat "
                f"{min(t['rhat_max'] for t in th):.3f}-{max(t['rhat_max'] for t in th):.3f} ({n_th} of {len(ok)} "
                f"meet both targets); R-hat of the log-likelihood estimate "
                f"{min(s['rhat_loglik_estimate'] for s in ok):.3f}-{max(s['rhat_loglik_estimate'] for s in ok):.3f}; "
                f"Laplace agrees with the chains in {sum(s['laplace_agreement']['agrees'] for s in ok)} of {len(ok)}; "
                f"{min(s['seconds'] for s in ok):.0f}-{max(s['seconds'] for s in ok):.0f} s wall each.")
        if c.get("pairs"):
            ps = np.array([p["p"] for p in c["pairs"]])
            ratio = np.array(c["scatter_over_sd"])
            line += (f" Between captures: the posterior means scatter by {np.sqrt(np.mean(np.square(c['scatter_um']))):.3g} "
                     f"um RMS per coordinate, {np.median(ratio):.3g}x (median over coordinates; "
                     f"{ratio.min():.2g}-{ratio.max():.2g}x) the posterior std; pairwise chi2 "
                     f"({c['pairs'][0]['dof']} dof): {int(np.sum(ps < 0.01))} of {len(ps)} pairs with p < 0.01 "
                     f"(p from {ps.min():.2g} to {ps.max():.2g}), pooled z RMS {c['pooled_z_rms']:.3g} "
                     f"(1 if the posteriors were right), {c['fraction_abs_z_gt_2']:.0%} of |z| > 2 (5 % expected). ")
            line += ("**The captures agree.**" if np.sum(ps < 0.01) == 0 and c["pooled_z_rms"] < 1.5 else
                     "**The captures do not agree: the posterior std is too small for the scatter between "
                     "captures, so the model leaves out something that changes the estimate by more than its "
                     "std.**" if np.median(ratio) > 1.5 else
                     "**Some pairs disagree.**")
            if "ml" in c:
                mlc = c["ml"]
                line += (f" ML on all usable samples: CRB median {mlc['crb_sd_median_um']:.3g} um against an ML "
                         f"scatter between captures {mlc['ml_scatter_over_crb_median']:.3g}x the CRB (median); "
                         f"posterior mean - ML(all) {mlc['post_minus_ml_rms_um']:.3g} um RMS, |z| (in posterior "
                         f"stds) up to {max(mlc['max_abs_z_per_capture']):.3g}.")
        md += line + "\n"
    md += "\n"

    md += reading(results, comps, args)
    md += ("## What the description calibrates, and what not\n\n"
           "`config/mimu4444bt_corners.yaml` is nominal: it gives each IMU's nominal position (the README's "
           "corner coordinates, +-9.45 mm, +-1 mm; here the prior's centre and the panels' origin), its "
           "orientation (sensor -> array; verified on the captures), white-noise stds (0.045 m/s^2, 0.0039 "
           "rad/s, pooled from the static segments) and the clip levels (samples with a clipped reading are "
           "dropped). Everything else is held at its identity: accelerometer and gyroscope gains, biases "
           "(up to 0.6 m/s^2 on these accelerometers, per the description's notes), misalignment / "
           "non-orthogonality, g-sensitivity, time offsets and sampling jitter, and the sensors' non-linearity. "
           "The posterior is of the positions *given* those identities: any of these errors that projects onto "
           "the lever-arm terms moves the positions, and all of them enter the residual the noise model is "
           "supposed to explain.\n\n")

    md += "## Choices\n\n"
    md += (f"- **Samples**: `select_samples(..., {args.samples})`, which keeps samples with every reading valid "
           "(none clipped) and ||[w]x^2 + [w_dot]x||_F >= 1 rad/s^2 from the fused motion, then spreads the "
           f"{args.samples} evenly in time over the whole capture. The same samples serve both settings.\n")
    md += (f"- **N and rho**: N = {args.draws} draws of omega per sample, fixed, and rho = {RHO['a']} (a) / "
           f"{RHO['b']} (b) -- not the CLI defaults (N tuned to Var[log p_N] <= 0.1, rho = 0.9). The tuning "
           f"cannot reach its target on these captures: Var[log p_N] at the Laplace mean is still "
           f"{_var_range(results, 'a', 1024)} (a) and {_var_range(results, 'b', 1024)} (b) at the cap "
           "N = 1024 (table below), where one likelihood costs ~0.07-0.09 s at T = 500 (hours per "
           "posterior). The variance falls slowly with N -- a few fast-turning samples dominate it, the "
           "estimator is heavy-tailed -- while the noise of the log acceptance ratio is set mostly by rho: "
           "on exp_1 (a), its sd for one typical random-walk step was 18 / 7.1 / 2.6 / 0.8 at rho = 0 / 0.9 / "
           "0.99 / 0.999 with N = 16 and 11 / 5.6 / 2.7 / 0.7 with N = 128 (measured before the run). So N is kept small (cheap "
           "iterations) and rho raised to 0.99 (measured for every capture in the sampler table). rho = 0.999 "
           "was tried on exp_1 (a) (N = 64): more theta moves were accepted, but the warm-up R-hat (positions and "
           "log-likelihood estimate) stayed at 1.8-1.9 after 4000 iterations: the random numbers hardly move, "
           "and they are part of the target (at rho = 0.99 the same run reached R-hat 1.02 for the positions, "
           "1.52 for the log-likelihood estimate). The pseudo-marginal chain targets the exact posterior for any N and "
           "rho; N and rho only change how fast it mixes.\n")
    md += ("- **Convergence**: `sample_posterior` declares convergence when the smallest bulk ESS of the "
           "coordinates reaches the target and the largest split R-hat of the coordinates *and of the "
           "log-likelihood estimate* is <= 1.01. The log-likelihood estimate depends on the random numbers "
           "u (part of the pseudo-marginal target), so its R-hat measures how well u mixes; the tables give "
           "it separately, with ESS and R-hat of the positions alone (what the posterior summaries rest on).\n")
    md += (f"- **Caps**: {args.chains} chains on {args.workers} worker processes, warm-up at most "
           f"{args.max_warmup} and sampling at most {args.max_iterations} iterations per chain (CLI: 40000 "
           "and 400000), so a posterior that mixes slowly ends unconverged instead of running for hours; "
           "it is then flagged in the tables.\n")
    md += ("- **ML(all)**: `calibrate_geometry(method=\"joint\")` on every sample of the capture that passes "
           "its selection (the same test as `select_samples`), with the setting's accelerometer std "
           "(the gyroscope noise model in both: the sample covariance has no counterpart there); the CRB is "
           "its Cramér-Rao bound. The selection depends on the noise: its rotation test asks for ||C_n|| >= 3x "
           "what the fused motion's own noise gives, and with sigma_a = 0.79 the fused omega_dot of a still "
           "array is that noisy, so in (b) the static poses drop out and ML(all) uses about the moving samples "
           "only (see the samples-used column). It uses far more samples than the posterior, so its CRB is smaller; a "
           "posterior mean should lie within a few posterior stds of it.\n")
    md += ("- **Agreement between captures**: for each pair, d = mean_i - mean_j over the 21 free coordinates "
           "(imu_1 held at nominal in every capture, the same gauge), z = d / sqrt(var_i + var_j) per "
           "coordinate, chi2 = d^T (C_i + C_j)^-1 d with the full posterior covariances (21 dof) and per IMU "
           "(3 dof). Captures are independent recordings, so with a right model z ~ N(0, 1) and chi2 ~ "
           "chi2(21); the scatter of the six posterior means per coordinate (sample std) should match the "
           "posterior std.\n\n")

    md += "## Samples\n\n"
    md += ("| capture | samples | usable | dropped: clipped/missing | little rotation | not identified | "
           "moving in capture (valid, mean \\|gyro\\| > 1 rad/s) | of them usable | selected | of them moving | "
           "max \\|gyro\\| / clip | max \\|acc\\| / clip |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for r in results:
        dr = r["dropped"]
        md += (f"| {r['capture']} | {r['samples_total']} | {r['usable']} | {dr['missing_or_saturated']} | "
               f"{dr['little_rotation']} | {dr['motion_not_identified']} | {r['moving_in_capture']} | "
               f"{r['moving_only']['usable_moving']} | "
               f"{r['selected']} | {r['moving_selected']} | {r['max_gyro_over_clip_selected']:.3f} | "
               f"{r['max_acc_over_clip_selected']:.3f} |\n")
    mv = [r["moving_selected"] for r in results]
    md += (f"\nOnly {min(mv)}-{max(mv)} of the {args.samples} selected samples per capture are from the hand "
           "twisting; the others are from the static poses. They pass the rotation test because the fused "
           "omega_dot of the still array is not ~0: on exp_1 (checked separately) its median is 14 rad/s^2 at "
           "rest (||C|| median 20 rad/s^2 against the threshold 1), as accelerometer bias differences of a few "
           "tenths of m/s^2 over the ~2 cm between IMUs would make it. At rest [w]x^2 ~ 0 and omega_dot is "
           "marginalised, so these samples carry little information about the positions")
    ca, mo_a = comps.get("a") or {}, (comps.get("a") or {}).get("moving_only")
    if mo_a and "a" in (results[0]["settings"] if results else {}):
        sd_sel = float(np.median([np.sqrt(np.diag(r["settings"]["a"]["cov_free"])) for r in results
                                  if "cov_free" in r["settings"].get("a", {})]) * UM)
        md += (f": in (a) the posterior std on the CLI's selection ({sd_sel:.3g} um median) is about what "
               f"~{np.mean(mv):.0f} moving samples give -- on {args.samples} moving samples the std is "
               f"{mo_a['sd_median_um']:.3g} um, {sd_sel / mo_a['sd_median_um']:.2g}x smaller (sqrt({args.samples}/"
               f"{np.mean(mv):.0f}) = {np.sqrt(args.samples / np.mean(mv)):.2g})")
    md += ". The selection is what the CLI does; the report keeps it and adds the moving-only diagnostic.\n\n"

    for label, (_, _, text) in SETTINGS.items():
        recs = [(r["capture"], r["settings"][label]) for r in results if label in r["settings"]]
        if not recs:
            continue
        md += f"## Setting ({label}): {text}\n\n### Sampler\n\n"
        md += ("| capture | Var[log p_N] N=16 / 64 / 1024 | log-ratio noise sd rho=0 / 0.9 / 0.99 / 0.999 | warm-up | "
               "draws/chain | RW acceptance | indep. acceptance | positions: ESS bulk / tail min | positions: R-hat max | "
               "log-lik estimate: R-hat | sampler: converged | wall s | CPU s | Laplace: max \\|z\\| | "
               "Laplace/MCMC sd ratio | Laplace agrees | ML(all): samples used, NIS before -> after, s |\n"
               "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
        for cap, s in recs:
            if "error" in s:
                md += f"| {cap} | **failed**: {s['error']} |" + " |" * 14 + "\n"
                continue
            vl = s["var_loglik"]
            rn = s["ratio_noise_sd"]
            la = s["laplace_agreement"]
            th = s["theta_only"]
            md += (f"| {cap} | {' / '.join(format(vl[n], '.3g') for n in VAR_NS)} | "
                   f"{' / '.join(format(rn[k], '.2g') for k in sorted(rn, key=float))} | {s['warmup_per_chain']} | "
                   f"{s['draws_per_chain']} | {min(s['acceptance_random_walk']):.0%}-{max(s['acceptance_random_walk']):.0%} | "
                   f"{np.nanmin(s['acceptance_independence']):.0%}-{np.nanmax(s['acceptance_independence']):.0%} | "
                   f"{th['ess_bulk_min']:.0f} / {th['ess_tail_min']:.0f} | {th['rhat_max']:.3f} | "
                   f"{s['rhat_loglik_estimate']:.3f} | "
                   f"{'yes' if s['converged'] else '**no**'} | {s['seconds']:.0f} | {s['cpu_seconds']:.0f} | "
                   f"{la['max_abs_mean_z']:.2f} | {la['sd_ratio_min']:.2f}-{la['sd_ratio_max']:.2f} | "
                   f"{'yes' if la['agrees'] else 'no'} | "
                   + (f"{s['ml']['samples_used']}, {s['ml']['nis_before']:.4g} -> {s['ml']['nis_after']:.4g}, "
                      f"{s['ml']['seconds']:.0f} |\n" if "ml" in s else f"{s.get('ml_error', '—')} |\n"))
        md += ("\nLaplace agreement: `laplace_agreement` (|mean difference| <= 0.5 posterior std and Laplace/MCMC "
               "std ratio in [0.8, 1.25] for every coordinate); the Laplace approximation is the ML on the same "
               f"{args.samples} samples with its CRB, combined with the prior.\n\n")
        md += ("### Per IMU\n\nPosterior mean (mm) and std (um) of each free IMU; ML(all): the ML estimate on every "
               "usable sample (mm) and its CRB std (um); z = (posterior mean - ML) / posterior std.\n\n"
               "| IMU | capture | mean x, y, z (mm) | std x, y, z (um) | ML(all) x, y, z (mm) | CRB x, y, z (um) | "
               "z vs ML |\n|---|---|---|---|---|---|---|\n")
        for j, kk in enumerate(free):
            for cap, s in recs:
                if "mean_free" not in s:
                    continue
                sl = slice(3 * j, 3 * j + 3)
                m = np.array(s["mean_free"])[sl]
                sd = np.sqrt(np.diag(s["cov_free"]))[sl]
                if "ml" in s:
                    ml = np.array(s["ml"]["theta"])[sl]
                    crb = np.sqrt(np.diag(s["ml"]["crb_free"]))[sl]
                    mlt = (", ".join(f"{v * MM:.3f}" for v in ml), ", ".join(f"{v * UM:.3g}" for v in crb),
                           ", ".join(f"{v:+.1f}" for v in (m - ml) / sd))
                else:
                    mlt = ("—", "—", "—")
                md += (f"| {names[kk]} | {cap} | {', '.join(f'{v * MM:.3f}' for v in m)} | "
                       f"{', '.join(f'{v * UM:.3g}' for v in sd)} | {mlt[0]} | {mlt[1]} | {mlt[2]} |\n")
        c = comps.get(label) or {}
        if c.get("pairs"):
            md += "\n### Between captures\n\n"
            md += ("Scatter of the posterior means across the captures (sample std, um) against the RMS posterior "
                   "std (um), per coordinate:\n\n| IMU | " + " | ".join(
                       f"{a}: scatter | {a}: post. std | {a}: ratio" for a in axes) + " |\n|---|"
                   + "---|---|---|" * 3 + "\n")
            for j, kk in enumerate(free):
                cells = []
                for a in range(3):
                    q = 3 * j + a
                    cells.append(f"{c['scatter_um'][q]:.3g} | {c['posterior_sd_rms_um'][q]:.3g} | "
                                 f"{c['scatter_over_sd'][q]:.3g}")
                md += f"| {names[kk]} | " + " | ".join(cells) + " |\n"
            md += ("\nPairs: chi2 of the 21 free coordinates with the combined posterior covariance, its p-value, "
                   "the largest and median |z|, and the IMUs whose own 3-dof chi2 has p < 0.01.\n\n"
                   "| pair | chi2 (21 dof) | p | max \\|z\\| | median \\|z\\| | IMUs with p < 0.01 |\n"
                   "|---|---|---|---|---|---|\n")
            for p in c["pairs"]:
                bad = [n for n, v in p["imu"].items() if v["p"] < 0.01]
                md += (f"| {p['pair'][0]} - {p['pair'][1]} | {p['chi2']:.4g} | {p['p']:.2g} | {p['max_abs_z']:.3g} | "
                       f"{p['median_abs_z']:.3g} | {', '.join(bad) if bad else 'none'} |\n")
            if "ml" in c:
                mlc = c["ml"]
                md += (f"\nML(all) vs posterior: posterior mean - ML {mlc['post_minus_ml_rms_um']:.3g} um RMS over "
                       f"coordinates and captures; |z| in posterior stds per capture: "
                       + ", ".join(f"{cap} max {mx:.2g} (RMS {rm:.2g})" for cap, mx, rm in
                                   zip(c["captures"], mlc["max_abs_z_per_capture"], mlc["rms_z_per_capture"]))
                       + f". CRB median {mlc['crb_sd_median_um']:.3g} um vs posterior std median "
                       f"{mlc['post_sd_median_um']:.3g} um; the ML estimates themselves scatter between captures "
                       f"by {np.sqrt(np.mean(np.square(mlc['ml_scatter_um']))):.3g} um RMS, "
                       f"{mlc['ml_scatter_over_crb_median']:.3g}x their CRB (median over coordinates).\n")
        mo = c.get("moving_only")
        if mo:
            ps = np.array([p["p"] for p in mo["pairs"]])
            shift = [np.sqrt(np.mean((np.array(r["moving_only"]["settings"][label]["mean_free"])
                                      - np.array(r["settings"][label]["mean_free"])) ** 2)) * UM
                     for r in results if "mean_free" in r["settings"].get(label, {})]
            md += ("\n### Diagnostic: the same on moving samples only (Laplace, no chains)\n\n"
                   f"{args.samples} samples spread evenly over each capture's usable samples with mean |gyro| > "
                   f"{MOVING_RAD_S} rad/s instead of over all usable ones (the static poses left out), and the "
                   "Laplace approximation (ML + CRB + prior) instead of the chains, which agree with it where "
                   f"the Laplace agreement above says so. Std median {mo['sd_median_um']:.3g} um; between captures "
                   f"the means scatter by {np.sqrt(np.mean(np.square(mo['scatter_um']))):.3g} um RMS per coordinate, "
                   f"{np.median(mo['scatter_over_sd']):.3g}x the std (median; {min(mo['scatter_over_sd']):.2g}-"
                   f"{max(mo['scatter_over_sd']):.2g}x); {int(np.sum(ps < 0.01))} of {len(ps)} pairs with p < 0.01 "
                   f"(p {ps.min():.2g}-{ps.max():.2g}); pooled z RMS {mo['pooled_z_rms']:.3g}. Moving-only Laplace mean "
                   f"minus the posterior on the CLI's selection: {min(shift):.3g}-{max(shift):.3g} um RMS per "
                   "capture.\n\n| pair | chi2 (21 dof) | p | max \\|z\\| | median \\|z\\| |\n|---|---|---|---|---|\n")
            for p in mo["pairs"]:
                md += (f"| {p['pair'][0]} - {p['pair'][1]} | {p['chi2']:.4g} | {p['p']:.2g} | {p['max_abs_z']:.3g} | "
                       f"{p['median_abs_z']:.3g} |\n")
        md += "\n"
    return md


def reading(results, comps, args) -> str:
    """What the numbers say, in words (every number computed from this run's records)."""
    ok = {lab: [r["settings"][lab] for r in results if "mean_free" in r["settings"].get(lab, {})] for lab in SETTINGS}
    if not all(ok.values()) or not all(comps.get(lab, {}).get("pairs") for lab in SETTINGS):
        return ""
    sig = {lab: ok[lab][0]["accel_std"] for lab in SETTINGS}
    ratio = {lab: float(np.median(comps[lab]["scatter_over_sd"])) for lab in SETTINGS}
    mo_ratio = {lab: float(np.median(comps[lab]["moving_only"]["scatter_over_sd"])) if comps[lab].get("moving_only")
                else float("nan") for lab in SETTINGS}
    ab = [r for r in results if all("mean_free" in r["settings"].get(lab, {}) for lab in SETTINGS)]
    d_ab = [np.sqrt(np.mean((np.array(r["settings"]["a"]["mean_free"]) - np.array(r["settings"]["b"]["mean_free"])) ** 2))
            * UM for r in ab]
    z_ab = [np.max(np.abs(np.array(r["settings"]["a"]["mean_free"]) - np.array(r["settings"]["b"]["mean_free"]))
                   / np.sqrt(np.diag(r["settings"]["b"]["cov_free"]))) for r in ab]
    ind_b = max(np.nanmax(s["acceptance_independence"]) for s in ok["b"])
    lap_b = [s["laplace_agreement"]["max_abs_mean_z"] for s in ok["b"]]
    th = {lab: [s["theta_only"] for s in ok[lab]] for lab in SETTINGS}
    rl = {lab: [s["rhat_loglik_estimate"] for s in ok[lab]] for lab in SETTINGS}
    var1024 = {lab: [s["var_loglik"][1024] for s in ok[lab]] for lab in SETTINGS}
    mcse = [1 / np.sqrt(t["ess_bulk_min"]) for t in th["b"]]
    pb = np.array([p["p"] for p in comps["b"]["pairs"]])
    pool = {lab: comps[lab]["pooled_z_rms"] for lab in SETTINGS}
    md = "## Reading\n\n"
    md += (f"- **Do the captures agree?** No, in neither setting. (a): the six posteriors are {ratio['a']:.3g}x "
           f"(median) too narrow for their scatter, pooled pairwise z RMS {pool['a']:.3g}. (b), the paper's "
           f"inflated sigma_a: much closer but still not consistent -- scatter {ratio['b']:.3g}x the posterior std "
           f"(median; up to {max(comps['b']['scatter_over_sd']):.2g}x), pooled z RMS {pool['b']:.3g}, and every one of "
           f"the {len(pb)} pairs rejects at p < 0.01 (largest p {pb.max():.2g}); the 3-dof test per IMU rejects in "
           f"{sum(sum(v['p'] < 0.01 for v in p['imu'].values()) for p in comps['b']['pairs'])} of "
           f"{sum(len(p['imu']) for p in comps['b']['pairs'])} IMU-pairs.\n")
    md += (f"- **What the scatter says about the noise model**: the posterior std scales about with sigma_a, so the "
           f"sigma_a at which the posterior std would match the scatter is about {sig['a']:.3g} x {ratio['a']:.3g} = "
           f"{sig['a'] * ratio['a']:.2g} m/s^2 from (a) and {sig['b']:.3g} x {ratio['b']:.3g} = "
           f"{sig['b'] * ratio['b']:.2g} m/s^2 from (b) on the CLI's sample selection, and "
           f"{sig['a'] * mo_ratio['a']:.2g} / {sig['b'] * mo_ratio['b']:.2g} m/s^2 on moving samples only (the "
           "diagnostic sections). That is the size of the accelerometer misfit of the nominal model while the array "
           "is twisted (benchmarks/results/real_data_geometry.md: accelerometer residual RMS 1.3-1.6 m/s^2 on the "
           "motion phase after the ML position fit), far above the white noise (0.045) and above the paper's "
           "0.79. carlsson2021 calibrated offsets, scale factors and misalignments of both triads before "
           "(Sec. IV-B); the description here has none of them, so 0.79 m/s^2 does not cover this board's misfit. "
           "The misfit is also not white: the estimate moves with which samples are used (posterior on the CLI "
           "selection vs ML(all) vs the moving-only Laplace: hundreds of um apart, sections below) and with the "
           f"noise model (posterior mean (a) vs (b): {min(d_ab):.3g}-{max(d_ab):.3g} um RMS per capture, up to "
           f"{max(z_ab):.2g} (b)-stds), so a larger sigma_a widens the posterior without making it right.\n")
    md += (f"- **ML / CRB**: the ML on every usable sample scatters between captures by "
           f"{comps['a']['ml']['ml_scatter_over_crb_median']:.3g}x its CRB in (a) "
           f"(CRB {comps['a']['ml']['crb_sd_median_um']:.2g} um; as in real_data_geometry.md) and "
           f"{comps['b']['ml']['ml_scatter_over_crb_median']:.3g}x in (b); the posterior means are "
           f"{comps['a']['ml']['post_minus_ml_rms_um']:.3g} um (a) / {comps['b']['ml']['post_minus_ml_rms_um']:.3g} um "
           f"(b) RMS from it, |z| up to {max(comps['a']['ml']['max_abs_z_per_capture']):.3g} (a) / "
           f"{max(comps['b']['ml']['max_abs_z_per_capture']):.2g} (b) posterior stds. Neither agrees with the "
           "posteriors.\n")
    md += ("- **Sample selection**: the CLI's selection (`select_samples`) takes 500 samples evenly over the "
           "usable ones, and with uncalibrated accelerometer biases the static poses pass its rotation test, so "
           "only ~15 % of them are from the twisting (Samples section). It does not change the verdict: on 500 "
           f"moving samples the captures disagree too ({mo_ratio['a']:.3g}x / {mo_ratio['b']:.3g}x in (a) / (b)).\n")
    md += ("- **Sampler on real data**: no failure (no CalibrationError, no singular matrix: eq. 30's sample "
           "covariance was positive definite at every selected sample; no selected sample has a clipped reading, "
           "though the selected gyroscope readings reach 0.95-1.00 of the clip level). But: "
           f"(1) N cannot be tuned: Var[log p_N] at N = 1024 is {min(var1024['a']):.3g}-{max(var1024['a']):.3g} (a), "
           f"{min(var1024['b']):.3g}-{max(var1024['b']):.3g} (b), against the target 0.1 -- the CLI would run at N = "
           "1024 with a very sticky chain; N = 16 and rho = 0.99 were used instead (Choices). "
           f"(2) The random numbers mix slowly: R-hat of the log-likelihood estimate {min(rl['a']):.2f}-{max(rl['a']):.2f} "
           f"(a), {min(rl['b']):.2f}-{max(rl['b']):.2f} (b), so `sample_posterior` declares no posterior converged; in "
           f"{NAME}_trace_a.png the log posterior of every chain keeps rising through the warm-up and the sampling "
           "(the random numbers still drifting toward the likelihood-overestimating region the pseudo-marginal "
           "target puts them in, which with Var[log p_N] ~ 100 is far from where they start). The positions "
           f"themselves look stationary in (a) (R-hat {min(t['rhat_max'] for t in th['a']):.3f}-"
           f"{max(t['rhat_max'] for t in th['a']):.3f}, ESS {min(t['ess_bulk_min'] for t in th['a']):.0f}-"
           f"{max(t['ess_bulk_min'] for t in th['a']):.0f}) and agree with the Laplace approximation. "
           + (f"(3) In (b) the independence proposal is never accepted (0 % in every chain) and the Laplace "
              if ind_b == 0 else f"(3) In (b) the independence proposal is hardly accepted (at most {ind_b:.0%}) and the Laplace ")
           + f"approximation is {min(lap_b):.2g}-{max(lap_b):.2g} posterior stds off: `laplace` computes the ML and "
           "CRB with the gyroscope *noise model*, while the posterior uses eq. 30's sample covariance of the "
           "gyroscopes, a different model. The sampler starts from it and shrinks its proposals toward it, so "
           f"(b) mixes by the random walk alone: ESS {min(t['ess_bulk_min'] for t in th['b']):.0f}-"
           f"{max(t['ess_bulk_min'] for t in th['b']):.0f} of {ok['b'][0]['chains'] * ok['b'][0]['draws_per_chain']} "
           f"draws, R-hat {min(t['rhat_max'] for t in th['b']):.3f}-{max(t['rhat_max'] for t in th['b']):.3f} for the "
           f"positions. Their Monte Carlo error in the means is {min(mcse):.2f}-{max(mcse):.2f} posterior stds, and "
           "the std estimates are uncertain by about as much: enough to blur the per-pair p-values, not the "
           "verdict (pairwise |z| up to "
           f"{max(p['max_abs_z'] for p in comps['b']['pairs']):.2g}). "
           f"(4) Time: {min(s['seconds'] for lab in SETTINGS for s in ok[lab]):.0f}-"
           f"{max(s['seconds'] for lab in SETTINGS for s in ok[lab]):.0f} s wall per posterior "
           f"({args.max_warmup} + {args.max_iterations} iterations per chain, {args.chains} chains on "
           f"{args.workers} worker processes, the 2 cores shared with other jobs), even with these caps; the CLI "
           "defaults (N tuned to the cap 1024, up to 40000 + 400000 iterations) would take hours per posterior.\n\n")
    return md


def _var_range(results, label, n) -> str:
    v = [r["settings"][label]["var_loglik"][n] for r in results
         if label in r["settings"] and "var_loglik" in r["settings"][label]]
    return f"{min(v):.3g}-{max(v):.3g}" if v else "—"


def plots(results, names, nominal, free, out_dir: Path, args, traces: bool = True) -> list[str]:
    """The ellipse figure per setting (from the means and covariances) and, with ``traces``, the trace plot of
    the posterior with the lowest ESS (needs the chains)."""
    from imu_array_ros.calibration.bayes import PACKAGE_SIZE, PRIOR_STD
    from imu_array_ros.calibration.bayes_report import ellipse_radius, plot_ellipses, plot_trace

    written = []
    k = len(names)
    prior_std = np.full((k, 3), PRIOR_STD)
    prior_std[0] = 0.0
    for label, (_, _, text) in SETTINGS.items():
        est = {}
        worst = None
        for r in results:
            s = r["settings"].get(label)
            if not s or "mean_free" not in s:
                continue
            pos, cov = per_imu(free, np.array(s["mean_free"]), np.array(s["cov_free"]), k)
            pos[0] = nominal[0]
            est[r["capture"]] = (pos, cov)
            if worst is None or s["ess_bulk_min"] < worst[1]["ess_bulk_min"]:
                worst = (r["capture"], s)
        if not est:
            continue
        # the view: the package outline and every ellipse (the 3 mm prior, drawn, reaches beyond it)
        extent = max(float(np.max(np.abs(pos[1:, :2] - nominal[1:, :2])
                                  + ellipse_radius(0.5) * np.sqrt(np.einsum("kii->ki", cov[1:, :2, :2]))))
                     for pos, cov in est.values()) * MM
        path = out_dir / f"{NAME}_ellipses_{label}.png"
        plot_ellipses(path, names, nominal, est, prior_std=prior_std, package=PACKAGE_SIZE, reference=names[0],
                      view=max(2.2, 1.15 * extent),
                      title=f"({label}) {text}: 50 % credible ellipses (x-y) of the position posteriors, one colour "
                            f"per capture, T = {args.samples}; mm relative to nominal")
        written.append(path.name)
        if not traces:
            continue
        path = out_dir / f"{NAME}_trace_{label}.png"
        plot_trace(path, worst[1]["_post"])
        written.append(path.name)
        say(f"wrote {path.name} ({worst[0]}: the lowest ESS of setting {label})")
    return written


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, nargs="*", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=list(SETTINGS))
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--draws", type=int, default=16)
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ess", type=float, default=400.0)
    ap.add_argument("--max-warmup", type=int, default=3000)
    ap.add_argument("--max-iterations", type=int, default=6000)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--report-only", action="store_true",
                    help="rebuild bayes_real.md from bayes_real.json (no sampling; the PNGs are left as they are)")
    args = ap.parse_args()
    from imu_array_ros.io.atomic import atomic_write_text, json_safe
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.forward import SensorModel

    t_start = time.perf_counter()
    desc = load_description(DESC)
    model = SensorModel.from_description(desc)
    names = list(model.names)
    nominal = np.asarray(model.positions, dtype=float)
    free = np.arange(1, len(names))
    if args.report_only:
        record = json.loads((args.out / f"{NAME}.json").read_text())
        results, pngs, total = record["captures"], record["figures"], record["seconds"]
        for r in results:
            for st in r["settings"].values():
                if "var_loglik" in st:
                    st["var_loglik"] = {int(n): v for n, v in st["var_loglik"].items()}
        out_dir = args.out
        args = argparse.Namespace(**{**record["args"], "out": out_dir, "report_only": True})
        old = (out_dir / f"{NAME}.md").read_text()
        header = old[:old.index("\n", old.index("- code:")) + 1]  # the run's header, up to its code line
        header += (f"- report text and ellipse figures rebuilt from {NAME}.json by `--report-only` on "
                   f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} (same numbers, no new sampling)\n\n")
        plots(results, names, nominal, free, out_dir, args, traces=False)
    else:
        header = None
        results = []
        for i in args.captures:
            results.append(run_capture(i, desc, model, args))
        args.out.mkdir(parents=True, exist_ok=True)
        pngs = plots(results, names, nominal, free, args.out, args)
        total = time.perf_counter() - t_start
    comps = {label: compare(results, label, names, free) for label in SETTINGS}
    md = markdown(results, comps, names, nominal, free, args, total, header)
    md += "## Figures\n\n" + "\n".join(f"- `{p}`" for p in pngs) + "\n"
    md += ("\n`bayes_real_ellipses_{a,b}.png`: carlsson2021 Fig. 5 style, one panel per IMU as on the board "
           "(top side left, underside right, seen from above), 50 % ellipses of each capture's posterior, the "
           "prior (cyan) and the 4 x 4 mm package outline (dashed). `bayes_real_trace_{a,b}.png`: the chains of "
           "the posterior with the lowest ESS in that setting (ArviZ trace of its six worst coordinates, the log "
           "posterior, and the discarded warm-up).\n")
    for r in results:
        for st in r["settings"].values():
            st.pop("_post", None)
    record = {"script": "benchmarks/bayes_real.py", "args": {k: (str(v) if isinstance(v, Path) else v)
                                                             for k, v in vars(args).items() if k != "report_only"},
              "rho": RHO, "settings": {k: v[2] for k, v in SETTINGS.items()}, "names": names,
              "nominal": nominal.tolist(), "free": [names[f] for f in free], "units": "m, m^2",
              "captures": results, "comparisons": comps, "figures": pngs, "seconds": total}
    if not getattr(args, "report_only", False):
        atomic_write_text(args.out / f"{NAME}.json", json.dumps(json_safe(record), indent=1) + "\n")
    atomic_write_text(args.out / f"{NAME}.md", md)
    say(f"wrote {args.out / (NAME + '.md')}{'' if getattr(args, 'report_only', False) else ' and .json'} "
        f"in {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
