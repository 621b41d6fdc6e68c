"""The Bayesian (PmMH) position calibration on the six real MIMU4444BT captures (carlsson2021 Sec. IV-B/C).

For each capture ../shared/data/openshoe_mimu4444bt/exp_N.bin, imported with the nominal description
config/mimu4444bt_corners.yaml (``import_capture(path, desc)[0]``), as ``imu-array calibrate bayes``
does per recording: T samples (default 500) spread evenly over the usable ones (``select_samples``: every
reading valid, rotation by the fused motion's test and by the gyroscopes'), ``build_problem``
(reference imu_1 held, gaussian prior N(nominal, 3 mm)), ``laplace`` (ML on the same samples + CRB +
prior), then ``sample_posterior`` as the library runs it by default -- N tuned to Var[log p_N] <= 0.1
(refused when even N = 1024 leaves it above 10x that), rho 0.9, 4 chains on 2 worker processes,
Laplace-shaped random walk mixed with independence proposals, ESS >= 400, R-hat <= 1.01 -- with the
warm-up and sampling capped (see Choices), in three noise settings:

(a) the description's accelerometer noise (0.045 m/s^2) and p(omega | gyroscopes) from the gyroscope
    noise model (eq. 26b, ``omega_covariance="model"``);
(b) carlsson2021's real-data setting: sigma_a = 0.79 m/s^2 (the MPU-9150 non-linearity at full scale)
    and the gyroscopes' sample covariance at each sample (eq. 30, ``omega_covariance="sample"``);
(c) an empirical-Bayes noise level: sigma_a per capture = the ML estimate of the accelerometer noise on
    the same T samples (RMS of the accelerometer residuals of the ML position fit that setting (a)'s
    Laplace approximation rests on), with the gyroscope noise model.

Where the sampler refuses (untunable N) the report gives the error, the tuning table (``choose_draws``)
and the Laplace approximation only, labelled as such.  Per capture and setting: the posterior (or
Laplace) mean and std per IMU, ESS / R-hat / time, the ML estimate on every usable sample of the capture
(``calibrate_geometry``, joint solver, the setting's noise) with its CRB, and the Laplace agreement
(``laplace_agreement``).  Then whether the captures agree with each other (pairwise differences of the
means against the combined covariances) and with the ML/CRB, and a carlsson2021 Fig. 5-style plot per
setting with posteriors, one colour per capture.

Writes benchmarks/results/bayes_real.md, bayes_real.json, bayes_real_ellipses_<setting>.png and
bayes_real_trace_<setting>.png for every setting with posteriors (and removes those of settings without).

    python benchmarks/bayes_real.py [--captures 1 2 ...] [--settings a b c] [--samples 500]
        [--max-warmup 10000] [--max-iterations 40000] [--report-only]
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
#: "ml": the per-capture ML estimate of the accelerometer noise (setting c)
ML_SIGMA = "ml"
#: the settings: label -> (accelerometer std (None: the description's; ML_SIGMA: estimated), omega
#: covariance, description)
SETTINGS = {
    "a": (None, "model", "description's sigma_a (0.045 m/s^2), omega covariance from the gyroscope noise model"),
    "b": (PAPER_SIGMA_A, "sample", "sigma_a = 0.79 m/s^2 (carlsson2021), gyroscopes' sample covariance (eq. 30)"),
    "c": (ML_SIGMA, "model", "empirical Bayes: sigma_a = the capture's ML accelerometer residual RMS, omega "
                             "covariance from the gyroscope noise model"),
}
#: a sample "is moving" (hand twisting, not a static pose) when the mean over the IMUs of |gyro| exceeds this
MOVING_RAD_S = 1.0
#: replicates of the log acceptance ratio noise (rho check)
REPLICATES = 24
#: rho values at which the log acceptance ratio noise is measured (the library default is 0.9)
RHO_CHECK = (0.0, 0.9)
#: draws of omega per sample for the fixed-random-number mode check (see mode_check)
MODE_DRAWS = 16


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


def mode_check(problem, lap, post, rng) -> dict:
    """Where the Laplace mean and the posterior mean sit relative to the mode of the sampled target.

    With fixed random numbers (MODE_DRAWS per sample) log p_N(y | theta, u) + log p(theta) is a smooth
    function of theta; its maximum is found (BFGS from the Laplace mean) once as it is and once without
    the -T/2 log|H^T Omega H| term of the marginalised linear motion (eq. 22-26).  Without that term the
    likelihood is the profile one the ML/CRB of ``laplace`` maximises.  Distances in posterior stds."""
    from scipy.optimize import minimize

    p = problem.with_(n_draws=MODE_DRAWS)
    u = rng.standard_normal((p.n_samples, MODE_DRAWS, 3))
    sd = np.sqrt(np.diag(post.covariance))

    def neg(x, det: bool) -> float:
        theta = lap.mean + x * sd
        quad = p.quadratic(theta)
        if quad is None:
            return 1e30
        ll = float(p.loglik(theta, u)) + (0.0 if det else 0.5 * p.n_samples * quad[3])
        return -(ll + p.prior.logpdf(theta))

    out = {"draws": MODE_DRAWS}
    for key, det in (("with_logdet", True), ("without_logdet", False)):
        res = minimize(neg, np.zeros(p.dim), args=(det,), method="BFGS")
        mode = lap.mean + res.x * sd
        out[key] = {"max_abs_z_vs_posterior_mean": float(np.max(np.abs(mode - post.mean) / sd)),
                    "max_abs_z_vs_laplace_mean": float(np.max(np.abs(mode - lap.mean) / sd)),
                    "iterations": int(res.nit)}
    return out


def per_imu(free: np.ndarray, vec: np.ndarray, cov: np.ndarray, k: int):
    """(K, 3) positions and (K, 3, 3) covariances (reference rows zero) from free-coordinate vectors."""
    pos = np.zeros((k, 3))
    c = np.zeros((k, 3, 3))
    for j, i in enumerate(free):
        pos[i] = vec[3 * j:3 * j + 3]
        c[i] = cov[3 * j:3 * j + 3, 3 * j:3 * j + 3]
    return pos, c


def estimate(rec: dict):
    """(mean (d,), covariance (d, d), source) of a setting's record: the posterior where the sampler ran,
    else the Laplace approximation; None without either."""
    if "mean_free" in rec:
        return np.array(rec["mean_free"]), np.array(rec["cov_free"]), "posterior"
    if "laplace_mean_free" in rec:
        return np.array(rec["laplace_mean_free"]), np.array(rec["laplace_cov_free"]), "Laplace"
    return None


def noise_estimate(st, acc, gyr, model) -> dict:
    """Setting (c)'s sigma_a: the ML estimate of the accelerometer noise on the T selected samples.

    The fit is the one setting (a)'s ``laplace`` runs (``calibrate_geometry``, joint solver, the
    description's noise, ``min_excitation=0``) on the same samples; sigma_a = the RMS over every IMU, axis
    and sample of its accelerometer residuals at the ML positions and motion (the ML estimate of a common
    white-noise std).  As a check, the positions and motion are refitted once with that sigma_a on the
    same samples (``fit_terms``: no sample selection) and the RMS recomputed."""
    from imu_array_ros.calibration.geometry import _profile, calibrate_geometry
    from imu_array_ros.estimation.fit_terms import fit_terms
    from imu_array_ros.estimation.model_fusion import ModelFusion
    from imu_array_ros.model.forward import motion_context

    k = model.n_imus
    geo = calibrate_geometry(st, acc, gyr, model, reference=0, method="joint", min_excitation=0.0)
    rms = np.asarray(geo.rms_after, dtype=float)
    sigma = float(np.sqrt(np.mean(rms ** 2)))  # every selected sample is complete: equal counts per IMU
    m = dataclasses.replace(model, acc_std=np.full((k, 3), sigma))
    fit = fit_terms(st, acc, gyr, m, ["position"], reference=0)
    refit = float(np.sqrt(np.mean(_profile(st, acc, gyr, fit.model).rms ** 2)))
    # the gyroscopes at the same fit: how far they are from one rigid-body omega (the noise model says 0.0039 rad/s)
    fused, _ = ModelFusion(geo.model).fuse(st, acc, gyr)
    rows = np.searchsorted(st, fused.stamps)
    ctx = motion_context(fused.stamps, fused.omega, fused.omega_dot, fused.specific_force, geo.model.rotations,
                         derivatives=True)
    _, gyr_pred = geo.model.predict(ctx)
    gyro_rms = float(np.sqrt(np.mean((gyr[rows] - gyr_pred) ** 2)))
    return {"sigma_a": sigma, "rms_per_imu": rms.tolist(), "fit_samples_used": int(geo.samples_used),
            "nis_after": float(geo.nis_after), "sigma_after_one_refit": refit, "gyro_residual_rms": gyro_rms,
            "gyro_std_model": float(np.mean(model.gyro_std))}


def laplace_model(problem, model):
    """The model ``bayes.laplace`` gives ``calibrate_geometry`` for ``problem`` (its noise; with eq. 30
    the gyroscope std of ``sample_gyro_std``)."""
    from imu_array_ros.calibration import bayes

    m = dataclasses.replace(model, acc_std=np.asarray(problem.accel_std, dtype=float))
    if problem.omega_covariance == "sample":
        m = dataclasses.replace(m, gyro_std=bayes.sample_gyro_std(problem))
    return m


def run_capture(i: int, desc, model, args) -> dict:
    """Everything for one capture: every setting."""
    from imu_array_ros.calibration import bayes, bayes_sampler
    from imu_array_ros.calibration.bayes_sampler import VAR_REPLICATES, _diagnostics
    from imu_array_ros.calibration.geometry import calibrate_geometry
    from imu_array_ros.errors import CalibrationError
    from imu_array_ros.io.openshoe.capture import import_capture

    samples = import_capture(DATA / f"exp_{i}.bin", desc)[0]
    stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
    t0 = time.perf_counter()
    idx, dropped, usable = bayes.select_samples(stamps, accel, gyro, model, args.samples)
    select_s = time.perf_counter() - t0
    all_idx, _, _ = bayes.select_samples(stamps, accel, gyro, model, None)
    rate = np.mean(np.linalg.norm(gyro, axis=2), axis=1)  # rotation invariant: mean over IMUs of |gyro|
    st, acc, gyr = stamps[idx], accel[idx], gyro[idx]
    # the samples the gyroscope test drops: what the fused-motion test saw in them
    from imu_array_ros.calibration import geometry

    used_geo, _, motion = geometry._select(stamps, accel, gyro, model, geometry.MIN_EXCITATION)
    still = used_geo.copy()
    still[all_idx] = False
    out = {
        "capture": f"exp_{i}", "samples_total": int(len(stamps)), "usable": int(usable),
        "dropped": {key: int(v) for key, v in dropped.items()}, "selected": int(len(idx)),
        "moving_selected": int(np.sum(rate[idx] > MOVING_RAD_S)),
        "moving_usable": int(np.sum(rate[all_idx] > MOVING_RAD_S)),
        "max_gyro_over_clip_selected": float(np.max(np.abs(gyr)) / model.gyro_clip),
        "max_acc_over_clip_selected": float(np.max(np.abs(acc)) / model.acc_clip),
        "select_seconds": select_s, "settings": {},
        "still_fused_omega_dot_median": float(np.median(np.linalg.norm(motion[still, 3:6], axis=1)))
        if still.any() else None,
        "still_gyro_rate_median": float(np.median(rate[still])) if still.any() else None,
    }
    say(f"exp_{i}: {len(idx)} of {usable} usable samples ({len(stamps)} total, dropped {dropped}); "
        f"{out['moving_selected']} of the selected have mean |gyro| > {MOVING_RAD_S} rad/s")
    if ML_SIGMA in [SETTINGS[lab][0] for lab in args.settings]:
        t0 = time.perf_counter()
        out["noise_estimate"] = noise_estimate(st, acc, gyr, model)
        out["noise_estimate"]["seconds"] = time.perf_counter() - t0
        say(f"exp_{i}: ML accelerometer noise on the {len(idx)} samples: {out['noise_estimate']['sigma_a']:.4g} m/s^2 "
            f"(one refit: {out['noise_estimate']['sigma_after_one_refit']:.4g})")
    for n_label, (label, (accel_std, omega_cov, _)) in enumerate(SETTINGS.items()):
        if label not in args.settings:
            continue
        if accel_std == ML_SIGMA:
            accel_std = out["noise_estimate"]["sigma_a"]
        seed = 10 * i + n_label
        rec = {"accel_std": accel_std if accel_std is not None else float(np.mean(model.acc_std)),
               "omega_covariance": omega_cov, "seed": seed}
        out["settings"][label] = rec
        settings = bayes_sampler.SamplerSettings(
            chains=args.chains, workers=args.workers, seed=seed, ess=args.ess,
            max_warmup=args.max_warmup, max_iterations=args.max_iterations)
        rec["sampler_settings"] = dataclasses.asdict(settings)
        try:
            t0 = time.perf_counter()
            problem = bayes.build_problem(st, acc, gyr, model, reference=0, accel_std=accel_std,
                                          omega_covariance=omega_cov)
            lap = bayes.laplace(problem, st, acc, gyr, model)
            rec["laplace_seconds"] = time.perf_counter() - t0
        except CalibrationError as err:
            rec["error"] = f"Laplace: {err}"
            say(f"exp_{i} ({label}): Laplace FAILED: {err}")
            continue
        cov_w = problem.chol @ problem.chol.transpose(0, 2, 1)
        rec["omega_std_median"] = float(np.median(np.sqrt(np.einsum("tii->t", cov_w) / 3)))  # rad/s, per axis
        lm = laplace_model(problem, model)
        # how many of the T samples the Laplace's ML fit uses (its noise-dependent excitation test may drop some)
        geo_lap = calibrate_geometry(st, acc, gyr, lm, reference=0, method="joint", min_excitation=0.0)
        rec.update({"laplace_mean_free": lap.mean.tolist(), "laplace_cov_free": lap.covariance.tolist(),
                    "laplace_fit_samples_used": int(geo_lap.samples_used)})
        try:
            post = bayes_sampler.sample_posterior(problem, lap, settings,
                                                  progress=lambda s, lab=label: say(f"exp_{i} ({lab}): {s}"))
        except CalibrationError as err:
            rec["error"] = str(err)
            rec["refused"] = "too noisy to sample" in str(err)
            say(f"exp_{i} ({label}): sampler refused: {err}")
            if rec["refused"]:  # the tuning table: the same call with the same generator as the sampler's
                _, table = bayes_sampler.choose_draws(problem, lap.mean, settings.loglik_var,
                                                      np.random.default_rng(settings.seed))
                rec["var_loglik"] = [[int(n), float(v)] for n, v in table]
        else:
            rec["refused"] = False
            say(f"exp_{i} ({label}): {post.summary_line()}")
            ess_t, ess_tail_t, rhat_t = _diagnostics(post.draws)  # theta alone (the sampler adds the log-lik)
            _, _, rhat_ll = _diagnostics(post.loglik[..., None])
            rng = np.random.default_rng(seed + 100000)
            p_n = problem.with_(n_draws=post.n_draws)
            lap_chol = np.linalg.cholesky(lap.covariance)
            t0 = time.perf_counter()
            rec.update({
                "summary": post.summary_line(), "n_draws": int(post.n_draws), "rho": float(post.problem.rho),
                "var_loglik": [[int(n), float(v)] for n, v in post.var_loglik],
                "chains": int(post.draws.shape[0]), "draws_per_chain": int(post.draws.shape[1]),
                "warmup_per_chain": int(post.warmup),
                "acceptance_random_walk": post.acceptance.tolist(),
                "acceptance_independence": post.acceptance_independence.tolist(),
                "ess_bulk_min": post.ess_bulk_min, "ess_tail_min": post.ess_tail_min, "rhat_max": post.rhat_max,
                "converged": bool(post.converged), "seconds": post.seconds, "cpu_seconds": post.cpu_seconds,
                "theta_only": {"ess_bulk_min": ess_t, "ess_tail_min": ess_tail_t, "rhat_max": rhat_t},
                "rhat_loglik_estimate": rhat_ll,
                "mean_free": post.mean.tolist(), "cov_free": post.covariance.tolist(),
                "laplace_agreement": bayes_sampler.laplace_agreement(post),
                "ratio_noise_sd": {str(r): ratio_noise(p_n, lap.mean, lap_chol, r, rng) for r in RHO_CHECK},
                "mode_check": mode_check(problem, lap, post, rng),
            })
            rec["check_seconds"] = time.perf_counter() - t0
            rec["_post"] = post  # for the trace plot; dropped before writing JSON
        # the ML estimate on every usable sample of the capture (select_samples with no cap), the Laplace's noise
        t0 = time.perf_counter()
        try:
            geo = calibrate_geometry(stamps[all_idx], accel[all_idx], gyro[all_idx], lm, reference=0,
                                     method="joint", min_excitation=0.0)
        except CalibrationError as err:
            rec["ml_error"] = str(err)
            say(f"exp_{i} ({label}): ML FAILED: {err}")
            continue
        pos = geo.positions - geo.positions[0] + model.positions[0]
        fidx = (3 * problem.free[:, None] + np.arange(3)).reshape(-1)
        crb = geo.covariance[np.ix_(fidx, fidx)]
        rec["ml"] = {"theta": problem.theta_of(pos).tolist(), "crb_free": (0.5 * (crb + crb.T)).tolist(),
                     "usable": int(len(all_idx)), "samples_used": int(geo.samples_used),
                     "iterations": int(geo.iterations), "converged": bool(geo.converged),
                     "nis_before": float(geo.nis_before), "nis_after": float(geo.nis_after),
                     "seconds": time.perf_counter() - t0}
        say(f"exp_{i} ({label}): ML on {geo.samples_used} of {len(all_idx)} usable samples, NIS "
            f"{geo.nis_before:.4g} -> {geo.nis_after:.4g}, {rec['ml']['seconds']:.1f} s")
    # which part of (b) makes it untunable: its sigma_a or eq. 30?  The settings' ingredients swapped, Var[log p_N]
    # at N = 1 and 16 at (c)'s Laplace mean (the positions hardly matter at this scale)
    c = out["settings"].get("c", {})
    if "laplace_mean_free" in c and "b" in out["settings"]:
        rng = np.random.default_rng(10 * i + 7)
        theta = np.array(c["laplace_mean_free"])
        out["swap"] = {}
        for key, (sa, oc) in {"sigma_c+model": (c["accel_std"], "model"), "sigma_c+sample": (c["accel_std"], "sample"),
                              "0.79+model": (PAPER_SIGMA_A, "model"), "0.79+sample": (PAPER_SIGMA_A, "sample")}.items():
            pr = bayes.build_problem(st, acc, gyr, model, reference=0, accel_std=sa, omega_covariance=oc)
            out["swap"][key] = {str(n): bayes.loglik_variance(pr.with_(n_draws=n), theta, VAR_REPLICATES, rng)
                                for n in (1, 16)}
        say(f"exp_{i}: Var[log p_N] at N = 1 with the ingredients swapped: "
            + ", ".join(f"{k} {v['1']:.3g}" for k, v in out["swap"].items()))
    return out


# --------------------------------------------------------------------------- comparisons


def compare(results: list[dict], label: str, names, free) -> dict:
    """Cross-capture agreement of the estimates (posterior, else Laplace) of setting ``label``, and with
    the ML/CRB."""
    caps, est = [], []
    for r in results:
        e = estimate(r["settings"].get(label, {}))
        if e is not None:
            caps.append(r)
            est.append(e)
    out = {"captures": [r["capture"] for r in caps], "sources": [e[2] for e in est], "pairs": []}
    if not caps:
        return out
    means = np.array([e[0] for e in est])
    covs = np.array([e[1] for e in est])
    out.update(agreement(means, covs, out["captures"], names, free))
    sds = np.sqrt(np.einsum("cii->ci", covs))
    out["sd_median_um"] = float(np.median(sds) * UM)
    mls = [r["settings"][label].get("ml") for r in caps]
    if all(m is not None for m in mls):
        ml = np.array([m["theta"] for m in mls])
        crbs = np.array([np.sqrt(np.diag(m["crb_free"])) for m in mls])
        zml = (means - ml) / sds
        many = len(caps) > 1
        out["ml"] = {
            "z_vs_ml": zml.tolist(),
            "max_abs_z_per_capture": np.max(np.abs(zml), axis=1).tolist(),
            "rms_z_per_capture": np.sqrt(np.mean(zml ** 2, axis=1)).tolist(),
            "crb_sd_median_um": float(np.median(crbs) * UM),
            "ml_scatter_um": (ml.std(axis=0, ddof=1) * UM).tolist() if many else None,
            "ml_scatter_over_crb_median": float(np.median(ml.std(axis=0, ddof=1) / np.sqrt(np.mean(crbs ** 2, axis=0))))
            if many else None,
            "minus_ml_rms_um": float(np.sqrt(np.mean((means - ml) ** 2)) * UM),
        }
        lap = [r["settings"][label].get("laplace_mean_free") for r in caps]
        if all(v is not None for v in lap):  # the Laplace mean (profile ML on the T samples + prior) against ML(all)
            out["ml"]["laplace_minus_ml_rms_um"] = float(np.sqrt(np.mean((np.array(lap) - ml) ** 2)) * UM)
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
    if len(caps) > 1:
        scatter = means.std(axis=0, ddof=1)
        rms_sd = np.sqrt(np.mean(sds ** 2, axis=0))
        out["scatter_um"] = (scatter * UM).tolist()
        out["sd_rms_um"] = (rms_sd * UM).tolist()
        out["scatter_over_sd"] = (scatter / rms_sd).tolist()
        # the paired differences pooled: their z should be N(0,1) if the posteriors are right
        allz = np.concatenate([np.asarray([p["imu"][n]["z"] for n in p["imu"]]).ravel() for p in out["pairs"]])
        out["pooled_z_rms"] = float(np.sqrt(np.mean(allz ** 2)))
        out["fraction_abs_z_gt_2"] = float(np.mean(np.abs(allz) > 2))
    return out


# --------------------------------------------------------------------------- report


TITLE = "Bayesian (PmMH) position calibration on the real MIMU4444BT captures"


def _rng(vals, spec=".3g") -> str:
    """'lo-hi' (or the one value) of a list of numbers."""
    vals = [int(v) if spec == "d" else float(v) for v in vals]
    if not vals:
        return "—"
    lo, hi = min(vals), max(vals)
    return format(lo, spec) if format(lo, spec) == format(hi, spec) else f"{format(lo, spec)}-{format(hi, spec)}"


def _p(p: float) -> str:
    """A p-value; 0 (below the double range) as such."""
    return "< 1e-300" if p == 0 else format(p, ".2g")


def _recs(results, label):
    return [(r["capture"], r["settings"][label]) for r in results if label in r["settings"]]


def _var_at(rec, n):
    for nn, v in rec.get("var_loglik", []):
        if nn == n:
            return v
    return None


def _intro() -> str:
    doc = __doc__.split("\n\n", 1)[1]
    return doc[:doc.index("\nWrites benchmarks/")].strip() + "\n\n"


def summary_line(label, text, results, comps, args) -> str:
    from imu_array_ros.calibration.bayes_sampler import MAX_DRAWS, UNTUNABLE

    recs = [s for _, s in _recs(results, label)]
    c = comps.get(label) or {}
    if not recs:
        return ""
    line = f"- **({label}) {text}**: "
    if label == "c":
        sig = [s["accel_std"] for s in recs]
        line += f"sigma_a = {_rng(sig)} m/s^2 over the captures. "
    refused = [s for s in recs if s.get("refused")]
    ok = [s for s in recs if "mean_free" in s]
    other = [s for s in recs if "error" in s and not s.get("refused")]
    target = recs[0]["sampler_settings"]["loglik_var"]
    if refused:
        v1 = [_var_at(s, 1) for s in refused]
        vmax = [_var_at(s, MAX_DRAWS) for s in refused]
        line += (f"**the sampler refused {len(refused)} of {len(recs)} captures** (untunable: Var[log p_N] at the "
                 f"Laplace mean {_rng(v1)} at N = 1 and still {_rng(vmax)} at N = {MAX_DRAWS}, against the target "
                 f"{target:g} and the refusal threshold {UNTUNABLE * target:g}); ")
    if other:
        line += f"{len(other)} other failure(s) ({'; '.join(s['error'] for s in other)}); "
    if ok:
        n_conv = sum(s["converged"] for s in ok)
        th = [s["theta_only"] for s in ok]
        line += (f"{'P' if line.endswith('. ') else 'p'}osteriors for {len(ok)} of {len(recs)}: N tuned to {_rng([s['n_draws'] for s in ok], 'd')} "
                 f"(Var[log p_N] {_rng([s['var_loglik'][-1][1] for s in ok], '.2g')}), sampler convergence (ESS >= "
                 f"{args.ess:g}, R-hat of positions and log-likelihood estimate <= 1.01) in {n_conv} of {len(ok)} "
                 f"within the caps; positions alone ESS bulk {_rng([t['ess_bulk_min'] for t in th], '.0f')}, "
                 f"R-hat {_rng([t['rhat_max'] for t in th], '.3f')}; "
                 f"{_rng([s['seconds'] for s in ok], '.0f')} s wall each; Laplace agrees with the chains "
                 f"(`laplace_agreement`) in {sum(s['laplace_agreement']['agrees'] for s in ok)} of {len(ok)} (largest "
                 f"mean offset per capture {_rng([s['laplace_agreement']['max_abs_mean_z'] for s in ok], '.2g')} "
                 "posterior stds, Laplace/MCMC std ratios "
                 f"{_rng([s['laplace_agreement'][q] for s in ok for q in ('sd_ratio_min', 'sd_ratio_max')], '.2f')}). ")
    src = sorted(set(c.get("sources", [])))
    what = " / ".join("posterior" if s == "posterior" else "**Laplace approximation (not a posterior)**" for s in src)
    short = " / ".join(src)
    if c.get("captures"):
        line += f"{what[0].upper() + what[1:]} std median {c['sd_median_um']:.3g} um. "
    if c.get("pairs") and "scatter_over_sd" in c:
        ps = np.array([p["p"] for p in c["pairs"]])
        ratio = np.array(c["scatter_over_sd"])
        line += (f"Between captures ({short}): the means scatter by {np.sqrt(np.mean(np.square(c['scatter_um']))):.3g} "
                 f"um RMS per coordinate, {np.median(ratio):.3g}x (median over coordinates; {ratio.min():.2g}-"
                 f"{ratio.max():.2g}x) the std; pairwise chi2 ({c['pairs'][0]['dof']} dof): {int(np.sum(ps < 0.01))} of "
                 f"{len(ps)} pairs with p < 0.01 (p from {_p(ps.min())} to {_p(ps.max())}), pooled z RMS "
                 f"{c['pooled_z_rms']:.3g} (1 if the uncertainties were right), {c['fraction_abs_z_gt_2']:.0%} of |z| > 2 "
                 "(5 % expected). ")
        line += ("**The captures agree.**" if np.sum(ps < 0.01) == 0 and c["pooled_z_rms"] < 1.5 else
                 "**The captures do not agree**: the std is too small for the scatter between captures." if
                 np.median(ratio) > 1.5 else "**Some pairs disagree.**")
        if "ml" in c:
            m = c["ml"]
            line += (f" ML on all usable samples: CRB median {m['crb_sd_median_um']:.3g} um, ML scatter between "
                     f"captures {m['ml_scatter_over_crb_median']:.3g}x the CRB (median); {short} mean - ML(all) "
                     f"{m['minus_ml_rms_um']:.3g} um RMS, |z| up to {max(m['max_abs_z_per_capture']):.3g} stds.")
    return line + "\n"


def reading(results, comps, args) -> str:
    """What the numbers say, in words (every number computed from this run's records)."""
    from imu_array_ros.calibration.bayes_sampler import MAX_DRAWS, UNTUNABLE, VAR_REPLICATES

    md = "## Reading\n\n"
    recs = {lab: [s for _, s in _recs(results, lab)] for lab in SETTINGS}
    # agreement between captures
    parts = []
    for lab in SETTINGS:
        c = comps.get(lab) or {}
        if not c.get("pairs") or "scatter_over_sd" not in c:
            continue
        ps = np.array([p["p"] for p in c["pairs"]])
        src = "posteriors" if set(c["sources"]) == {"posterior"} else (
            "Laplace approximations" if set(c["sources"]) == {"Laplace"} else "posteriors / Laplace approximations")
        n_imu = sum(sum(v["p"] < 0.01 for v in p["imu"].values()) for p in c["pairs"])
        parts.append(f"({lab}) {src}: scatter {np.median(c['scatter_over_sd']):.3g}x the std (median; up to "
                     f"{max(c['scatter_over_sd']):.2g}x), pooled z RMS {c['pooled_z_rms']:.3g}, {int(np.sum(ps < 0.01))} "
                     f"of {len(ps)} pairs reject at p < 0.01 (largest p {_p(ps.max())}), the 3-dof test per IMU rejects in "
                     f"{n_imu} of {sum(len(p['imu']) for p in c['pairs'])} IMU-pairs")
    if parts:
        agree_all = all(
            sum(p["p"] < 0.01 for p in comps[lab]["pairs"]) == 0 for lab in SETTINGS if comps.get(lab, {}).get("pairs"))
        md += ("- **Do the captures agree?** " + ("Yes. " if agree_all else "No. ") + "; ".join(parts) + ". ")
        if not agree_all:
            md += (f"{len(results)} recordings of one board must give one set of positions; a scatter of the means larger than "
                   "their stated uncertainty means the model behind that uncertainty leaves out something that "
                   "changes from capture to capture (here: the intrinsics the nominal description holds at their "
                   "identities -- biases, gains, misalignments, g-sensitivity -- whose effect on the lever-arm "
                   "fit depends on each capture's motion), so the stds are not the error of the positions.")
        md += "\n"
    # what sigma_a would make the uncertainty cover the scatter
    sig_parts = []
    for lab in SETTINGS:
        c = comps.get(lab) or {}
        if "scatter_over_sd" not in c:
            continue
        sig = float(np.mean([s["accel_std"] for s in recs[lab]]))
        r = float(np.median(c["scatter_over_sd"]))
        sig_parts.append(f"{sig:.3g} x {r:.3g} = {sig * r:.2g} m/s^2 from ({lab})")
    if sig_parts:
        md += ("- **What the scatter says about the noise level**: the std scales about with sigma_a, so the sigma_a at "
               "which the std would match the scatter between captures is about " + ", ".join(sig_parts)
               + " (mean sigma_a x median ratio). ")
        ne = [r["noise_estimate"] for r in results if "noise_estimate" in r]
        if ne:
            sg = [n["sigma_a"] for n in ne]
            rf = [abs(n["sigma_after_one_refit"] / n["sigma_a"] - 1) for n in ne]
            md += (f"The residuals themselves say {_rng(sg)} m/s^2 (setting (c)'s ML estimate on the T samples: "
                   f"{min(sg) / 0.045:.0f}-{max(sg) / 0.045:.0f}x the description's 0.045 m/s^2 white noise and "
                   f"{min(sg) / PAPER_SIGMA_A:.2g}-{max(sg) / PAPER_SIGMA_A:.2g}x the paper's {PAPER_SIGMA_A}; one refit "
                   f"with it changes it by at most {max(rf):.2%}). ")
            cc = comps.get("c") or {}
            if "scatter_over_sd" in cc and set(cc["sources"]) == {"posterior"}:
                r = float(np.median(cc["scatter_over_sd"]))
                md += (f"So the scatter between captures needs about {r:.2g}x the noise level the residuals show "
                       + ("(median coordinate): the misfit moves the positions more than white noise of its size "
                          "would -- it is correlated across the samples of a capture, so it does not average down "
                          "with T as the posterior assumes. " if r > 1.2 else "(median coordinate). "))
        md += "\n"
    # refusals
    ref = {lab: [s for s in recs[lab] if s.get("refused")] for lab in SETTINGS}
    if any(ref.values()):
        bits = []
        for lab, rs in ref.items():
            if not rs:
                continue
            v1 = np.array([_var_at(s, 1) for s in rs])
            vm = np.array([_var_at(s, MAX_DRAWS) for s in rs])
            bits.append(f"({lab}) in {len(rs)} of {len(recs[lab])} captures: Var[log p_N] {_rng(v1)} at N = 1 and "
                        f"{_rng(vm)} at N = {MAX_DRAWS}, where 1/N would give {_rng(v1 / MAX_DRAWS, '.2g')}; "
                        f"N ~ {_rng(MAX_DRAWS * vm / rs[0]['sampler_settings']['loglik_var'], '.2g')} draws per "
                        "sample would be needed")
        md += ("- **Where the sampler refuses**: `sample_posterior` (N tuned) raised \"the log-likelihood estimate is "
               "too noisy to sample\" for " + "; ".join(bits) + f" (threshold {UNTUNABLE:g} x the target 0.1 at N = "
               f"{MAX_DRAWS}). The variance falls far slower than 1/N: the estimator is heavy-tailed.\n")
        # why: the residuals against sigma_a, the omega draws' width, and the swapped ingredients
        ne = [r["noise_estimate"] for r in results if "noise_estimate" in r]
        wstd = {lab: [s["omega_std_median"] for s in recs[lab] if "omega_std_median" in s] for lab in SETTINGS}
        sw = [r["swap"] for r in results if "swap" in r]
        md += ("- **Why**: per sample, the exponent ||z - h(omega)||^2 / sigma_a^2 of the likelihood changes between "
               "the drawn omegas by about 2 x residual x dh/domega x spread(omega) / sigma_a^2, so the estimate is "
               "noisy when sigma_a is far below the residuals or the omega draws are wide. ")
        if ne and ref.get("a"):
            sg = [n["sigma_a"] for n in ne]
            md += (f"(a): the accelerometer residuals of the nominal description are {_rng(sg, '.2g')} m/s^2 RMS on "
                   f"these samples (setting (c)'s estimate), {min(sg) / 0.045:.0f}-{max(sg) / 0.045:.0f}x the "
                   "description's sigma_a = 0.045, so even the noise model's narrow omega draws (median std "
                   f"{_rng(wstd['a'], '.2g')} rad/s per axis) spread the exponent widely. ")
        if ref.get("b") and wstd.get("b"):
            md += (f"(b): eq. 30's omega draws are wide, median std {_rng(wstd['b'], '.2g')} rad/s per axis (the "
                   "noise model's: " + _rng(wstd["a"] or wstd["c"], '.2g') + " rad/s)")
            if ne:
                g = [n["gyro_residual_rms"] for n in ne]
                gr = [n["gyro_residual_rms"] / n["gyro_std_model"] for n in ne]
                md += (f", because the 8 gyroscopes disagree: at the ML fit their residual RMS is {_rng(g, '.2g')} "
                       f"rad/s, {_rng(gr, '.0f')}x the noise model's std (uncalibrated gyroscope gains and "
                       "misalignments give such errors at high rates)")
            md += ". "
            if sw:
                v = {k: [x[k]["1"] for x in sw] for k in sw[0]}
                v16 = {k: [x[k]["16"] for x in sw] for k in sw[0]}
                md += (f"Swapping the ingredients (Var[log p_N] at N = 1 / 16 at (c)'s Laplace mean, {VAR_REPLICATES} "
                       f"replicates) locates it: sigma_a = 0.79 with the noise model gives {_rng(v['0.79+model'], '.2g')} "
                       f"/ {_rng(v16['0.79+model'], '.2g')}, with eq. 30 {_rng(v['0.79+sample'], '.3g')} / "
                       f"{_rng(v16['0.79+sample'], '.3g')}; (c)'s sigma_a with the noise model "
                       f"{_rng(v['sigma_c+model'], '.2g')} / {_rng(v16['sigma_c+model'], '.2g')}, with eq. 30 "
                       f"{_rng(v['sigma_c+sample'], '.3g')} / {_rng(v16['sigma_c+sample'], '.3g')}. ")
                b_tunable = max(v["0.79+model"]) <= 0.1
                c_sample_bad = min(v16["sigma_c+sample"]) > UNTUNABLE * 0.1
                md += ("So (b) refuses because of eq. 30, not because of its sigma_a" if b_tunable and c_sample_bad
                       else "So both its sigma_a and eq. 30 contribute") + ". "
        md += ("Both are the data disagreeing with the noise model. carlsson2021 assumes \"that the sensor triads' "
               "scale factor-, misalignment-, orientation-, and offset-errors are calibrated\" (Sec. II); with those "
               "errors left in, (a) and (b) are outside the method's assumptions, and the refusal is the library "
               "working as designed. For these settings the report gives the Laplace approximation (ML + CRB + "
               "prior) only; it is not a posterior, and its std rests on the same noise level.\n")
    # the sampled settings
    for lab in SETTINGS:
        ok = [s for s in recs[lab] if "mean_free" in s]
        if not ok:
            continue
        th = [s["theta_only"] for s in ok]
        la = [s["laplace_agreement"] for s in ok]
        mc = [s["mode_check"] for s in ok]
        rn = [s["ratio_noise_sd"] for s in ok]
        used = [s["laplace_fit_samples_used"] for s in ok]
        md += (f"- **Sampler in ({lab})**: N tuned to {_rng([s['n_draws'] for s in ok], 'd')} "
               f"(Var[log p_N] {_rng([s['var_loglik'][-1][1] for s in ok], '.2g')} at the Laplace mean; the noise of "
               f"the log acceptance ratio for one typical step, sd {_rng([r['0.0'] for r in rn], '.2g')} at rho = 0 and "
               f"{_rng([r['0.9'] for r in rn], '.2g')} at rho = 0.9, so the library's rho = 0.9 was kept). "
               f"{sum(s['converged'] for s in ok)} of {len(ok)} converged (ESS >= {args.ess:g} and R-hat <= 1.01 for "
               f"positions and log-likelihood estimate) after {_rng([s['warmup_per_chain'] for s in ok], 'd')} warm-up "
               f"and {_rng([s['draws_per_chain'] for s in ok], 'd')} sampling iterations per chain; positions ESS "
               f"{_rng([t['ess_bulk_min'] for t in th], '.0f')}, R-hat {_rng([t['rhat_max'] for t in th], '.3f')}, "
               f"log-likelihood estimate R-hat {_rng([s['rhat_loglik_estimate'] for s in ok], '.3f')}. ")
        ratios = [a[q] for a in la for q in ("sd_ratio_min", "sd_ratio_max")]
        width_ok = min(ratios) >= 0.8 and max(ratios) <= 1.25
        md += (f"The Laplace approximation's std is {'about right' if width_ok else 'off'} (Laplace/MCMC std ratios "
               f"{_rng(ratios, '.2f')}); its mean is off by up to {_rng([a['max_abs_mean_z'] for a in la], '.2g')} "
               f"posterior stds (RMS {_rng([a['rms_mean_z'] for a in la], '.2g')}), so by `laplace_agreement` it agrees "
               f"in {sum(a['agrees'] for a in la)} of {len(la)}. The mode check: the mode of the sampled target (fixed "
               f"random numbers) is {_rng([m['with_logdet']['max_abs_z_vs_posterior_mean'] for m in mc], '.2g')} "
               f"posterior stds from the posterior mean and "
               f"{_rng([m['with_logdet']['max_abs_z_vs_laplace_mean'] for m in mc], '.2g')} from the Laplace mean; "
               "without the -T/2 log|H^T Omega H| term of the marginalised linear motion it is "
               f"{_rng([m['without_logdet']['max_abs_z_vs_laplace_mean'] for m in mc], '.2g')} stds from the "
               "Laplace mean. ")
        explained = (max(m["with_logdet"]["max_abs_z_vs_posterior_mean"] for m in mc) < 0.5
                     and max(m["without_logdet"]["max_abs_z_vs_laplace_mean"] for m in mc) < 0.5)
        if explained:
            md += ("So the offset is the difference between the marginal likelihood the posterior uses (eq. 22-26, "
                   "omega_dot and s integrated out) and the profile likelihood (maximised over them) whose ML and CRB "
                   "`laplace` takes, not a sampler error. ")
        md += (f"The Laplace's ML fit uses {_rng(used, 'd')} of the {args.samples} samples: `calibrate_geometry`'s "
               "noise-dependent excitation test drops the least-excited ones even with min_excitation = 0")
        if explained:
            md += (" -- without effect here, as the profile mode on all T samples (the mode check without the term) "
                   "coincides with the Laplace mean")
        md += ".\n"
    # the empirical-Bayes setting: do its posteriors cover the scatter?
    for lab in SETTINGS:
        c = comps.get(lab) or {}
        if SETTINGS[lab][0] != ML_SIGMA or set(c.get("sources", [])) != {"posterior"} or "scatter_over_sd" not in c:
            continue
        ratio = np.array(c["scatter_over_sd"])
        ps = np.array([p["p"] for p in c["pairs"]])
        coords = [f"{n} {a}" for n in c["pairs"][0]["imu"] for a in "xyz"]
        worst = np.argsort(ratio)[::-1][:3]
        n_imu = sum(sum(v["p"] < 0.01 for v in p["imu"].values()) for p in c["pairs"])
        n_all = sum(len(p["imu"]) for p in c["pairs"])
        md += (f"- **Empirical Bayes ({lab})**: with sigma_a at the level the residuals call for, the posterior means "
               f"scatter between captures by {np.sqrt(np.mean(np.square(c['scatter_um']))):.3g} um RMS, "
               f"{np.median(ratio):.3g}x the posterior std (median {c['sd_median_um']:.3g} um) in the median "
               f"coordinate; {int(np.sum(ratio > 1))} of {len(ratio)} coordinates above 1x, the largest "
               + ", ".join(f"{coords[q]} {ratio[q]:.2g}x" for q in worst) + ". ")
        if np.sum(ps < 0.01):
            md += (f"Yet the full-covariance test rejects: {int(np.sum(ps < 0.01))} of {len(ps)} pairs at p < 0.01, "
                   f"{n_imu} of {n_all} IMU-pairs, pooled z RMS {c['pooled_z_rms']:.3g}. So even at the noise level "
                   "the residuals call for, the captures disagree beyond their posteriors: the misfit of the nominal "
                   "model is not white noise independent between samples (what sigma_a models) but a systematic "
                   "error that moves some IMUs' estimates by different amounts in different captures. "
                   + (f"The posterior std gives the order of the position error of this uncalibrated array (within "
                      f"a factor {max(ratio):.2g} in every coordinate), not a calibrated uncertainty. "
                      if max(ratio) <= 3 else "")
                   + "The remedy is calibrating the intrinsics (carlsson2021 does this first, "
                   "Sec. II / IV-B), not a larger sigma_a.\n")
        else:
            md += (f"No pair rejects at p < 0.01 (pooled z RMS {c['pooled_z_rms']:.3g}): at this noise level the "
                   "posteriors cover the scatter between captures.\n")
        ne = [r["noise_estimate"] for r in results if "noise_estimate" in r]
        if ne:
            gr = [n["gyro_residual_rms"] / n["gyro_std_model"] for n in ne]
            md += (f"- **(c)'s gyroscope side** keeps the noise model: p(omega | gyroscopes) is {_rng(gr, '.0f')}x "
                   "narrower than the gyroscopes' disagreement at the fit (\"Why\" above); whatever that misses ends "
                   "in the accelerometer residuals, which sigma_a absorbs.\n")
    # (a) and (b): the same ML, different widths
    if all(comps.get(lab, {}).get("captures") for lab in ("a", "b")):
        dab, zab = [], []
        for r in results:
            ea, eb = estimate(r["settings"].get("a", {})), estimate(r["settings"].get("b", {}))
            if ea is None or eb is None:
                continue
            dab.append(float(np.sqrt(np.mean((ea[0] - eb[0]) ** 2)) * UM))
            zab.append(float(np.max(np.abs(ea[0] - eb[0]) / np.sqrt(np.diag(eb[1])))))
        if dab:
            md += (f"- **(a) vs (b)**: their {'/'.join(sorted(set(comps['a']['sources'] + comps['b']['sources'])))} "
                   f"means are {_rng(dab)} um RMS apart per capture (at most {max(zab):.2g} (b)-stds): both rest on "
                   "an ML position fit of the same samples" + (" (the noise weighting hardly moves it)" if max(zab) < 1
                                                               else "") + ", "
                   f"and the settings differ in the width: std median {comps['a']['sd_median_um']:.3g} um (a) vs "
                   f"{comps['b']['sd_median_um']:.3g} um (b).\n")
    # ML / CRB
    ml_parts = []
    for lab in SETTINGS:
        c = comps.get(lab) or {}
        m = c.get("ml")
        if not m or m.get("ml_scatter_over_crb_median") is None:
            continue
        src = "posterior" if set(c["sources"]) == {"posterior"} else "Laplace"
        ml_parts.append(f"({lab}) ML scatter {m['ml_scatter_over_crb_median']:.3g}x its CRB (CRB median "
                        f"{m['crb_sd_median_um']:.3g} um), {src} mean {m['minus_ml_rms_um']:.3g} um RMS from it (|z| up to "
                        f"{max(m['max_abs_z_per_capture']):.3g} {src} stds)"
                        + (f"; its Laplace mean (the profile ML on the T samples + prior) "
                           f"{m['laplace_minus_ml_rms_um']:.3g} um RMS" if src == "posterior" and
                           "laplace_minus_ml_rms_um" in m else ""))
    if ml_parts:
        md += "- **ML on all usable samples / CRB**: " + "; ".join(ml_parts) + ". "
        worst = [lab for lab in SETTINGS if (comps.get(lab) or {}).get("ml", {}).get("ml_scatter_over_crb_median")]
        low = min(comps[lab]["ml"]["ml_scatter_over_crb_median"] for lab in worst)
        if low > 1.5:
            md += ("The ML estimates of different captures disagree with each other by more than their CRB in every "
                   f"setting (at least {low:.3g}x): with the intrinsics uncalibrated, more samples shrink the CRB but "
                   "not the systematic error.")
        md += "\n"
    # time
    sec = [s["seconds"] for lab in SETTINGS for s in recs[lab] if "seconds" in s]
    if sec:
        md += (f"- **Time**: {_rng(sec, '.0f')} s wall per posterior ({args.chains} chains on {args.workers} worker "
               f"processes, caps {args.max_warmup} warm-up + {args.max_iterations} sampling iterations per chain, "
               "the 2 cores shared with other jobs)")
        ns = sorted({n for lab in SETTINGS for s in recs[lab] if s.get("refused") for n, _ in s.get("var_loglik", [])})
        if ns:
            md += ("; a refusal costs the tuning only (Var measurements at N = " + ", ".join(str(n) for n in ns) + ")")
        md += ".\n"
    return md + "\n"


def markdown(results, comps, names, free, args, total_s, header: str | None = None) -> str:
    from imu_array_ros.calibration.bayes_sampler import MAX_DRAWS, UNTUNABLE, VAR_REPLICATES

    axes = "xyz"
    if header is None:
        md = machine_header(TITLE)
        md += (f"- run time: {total_s:.0f} s (whole script; {len(results)} captures x {len(args.settings)} settings "
               "one after the other; machine shared with other work)\n")
        md += f"- code: {_commit()}\n\n"
    else:
        md = header
    md += _intro()

    md += "## Summary\n\n"
    for label, (_, _, text) in SETTINGS.items():
        md += summary_line(label, text, results, comps, args)
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
           "supposed to explain. carlsson2021 (Sec. II) assumes them calibrated.\n\n")

    md += "## Choices\n\n"
    md += (f"- **Samples**: `select_samples(..., {args.samples})`: every reading valid (none clipped), "
           "||[w]x^2 + [w_dot]x||_F >= 1 rad/s^2 from the fused motion (and >= 3x what its own noise gives) and "
           "the same from the gyroscopes alone (w_dot the time derivative of the fused w: drops the static poses, "
           f"counted as `still_by_gyroscopes`), then {args.samples} spread evenly in time over the usable ones. "
           "The same samples serve every setting.\n")
    md += ("- **Setting (c)'s noise level**: per capture, from that capture's T samples only: the fit behind "
           "setting (a)'s Laplace approximation (`calibrate_geometry`, joint solver, description noise, "
           "min_excitation = 0; it used every one of the T samples, see the table), and sigma_a = RMS of its "
           "accelerometer residuals over all IMUs, axes and samples -- the ML estimate of one white-noise std "
           "for every accelerometer axis. It is an empirical-Bayes choice: the data set the noise level of "
           "their own likelihood, so the posterior does not carry the uncertainty of sigma_a (small at "
           f"{8 * 3 * args.samples} residuals) and sigma_a absorbs every misfit of the nominal model, white or "
           "not. The gyroscope noise stays the description's (0.0039 rad/s), although at the same fit the gyroscopes "
           "are further from one rigid-body omega than that (gyroscope residual RMS in the table): p(omega | "
           "gyroscopes) is narrower than the gyroscopes' disagreement. No hand tuning, nothing shared across "
           "captures.\n")
    md += (f"- **N and rho**: the sampler's own: `n_draws=None` (N = the smallest power of two with "
           f"Var[log p_N] <= 0.1 at the Laplace mean over {VAR_REPLICATES} replicates; it jumps to the cap N = "
           f"{MAX_DRAWS} when 1/N scaling would need more than 4x the cap; refused when Var at the cap exceeds "
           f"{UNTUNABLE:g} x 0.1) and rho = 0.9 (the default; the log acceptance ratio noise at rho = 0 and 0.9 "
           "is in the sampler table). The tuning table of a refused setting is `choose_draws` rerun with the "
           "sampler's generator (same seed, so the same numbers as in the error message). Seed 10 x capture + "
           "setting index: different random numbers for every posterior.\n")
    md += (f"- **Caps**: {args.chains} chains on {args.workers} worker processes, the sampler's chunk (1000) and "
           f"min_warmup (2000), warm-up at most {args.max_warmup} and sampling at most {args.max_iterations} "
           "iterations per chain (library defaults: 40000 and 400000); a posterior that reaches a cap is flagged "
           "as not converged.\n")
    md += ("- **Convergence**: `sample_posterior` declares convergence when the smallest bulk ESS of the "
           f"coordinates reaches {args.ess:g} and the largest split R-hat of the coordinates *and of the "
           "log-likelihood estimate* is <= 1.01. The tables also give ESS and R-hat of the positions alone.\n")
    md += ("- **Laplace agreement / mode check**: `laplace_agreement` (|mean difference| <= 0.5 posterior std and "
           "Laplace/MCMC std ratio in [0.8, 1.25] for every coordinate). The mode check maximises the sampled "
           f"target log p_N(y | theta, u) + log p(theta) at fixed random numbers (N = {MODE_DRAWS}) by BFGS from the "
           "Laplace mean, with and without the -T/2 log|H^T Omega H| term, and gives each mode's largest "
           "distance (in posterior stds) to the posterior and the Laplace mean.\n")
    md += ("- **ML(all)**: `calibrate_geometry(method=\"joint\", min_excitation=0)` on every usable sample of the "
           "capture (`select_samples` with no cap), with the noise the setting's Laplace uses (the setting's "
           "sigma_a; in (b) the gyroscope std of `sample_gyro_std`); the CRB is its Cramér-Rao bound. Its "
           "noise-dependent excitation test drops the least-excited samples when sigma_a is large (samples-used "
           "column). A right model would put each posterior mean within a few posterior stds of it and make "
           "the ML scatter between captures match its CRB.\n")
    md += ("- **Agreement between captures**: the posterior where the sampler ran, else the Laplace approximation "
           "(labelled). For each pair, d = mean_i - mean_j over the 21 free coordinates (imu_1 held at nominal in "
           "every capture, the same gauge), z = d / sqrt(var_i + var_j) per coordinate, chi2 = d^T (C_i + C_j)^-1 d "
           "with the full covariances (21 dof) and per IMU (3 dof). Captures are independent recordings, so with "
           f"a right model z ~ N(0, 1) and chi2 ~ chi2(21); the scatter of the {len(results)} means per coordinate "
           "(sample std) should match the std.\n\n")

    md += "## Samples\n\n"
    md += ("| capture | samples | usable | dropped: clipped/missing | little rotation | not identified | "
           "still by gyroscopes | usable moving (mean \\|gyro\\| > 1 rad/s) | selected | of them moving | "
           "max \\|gyro\\| / clip | max \\|acc\\| / clip |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for r in results:
        dr = r["dropped"]
        md += (f"| {r['capture']} | {r['samples_total']} | {r['usable']} | {dr.get('missing_or_saturated', '—')} | "
               f"{dr.get('little_rotation', '—')} | {dr.get('motion_not_identified', '—')} | "
               f"{dr.get('still_by_gyroscopes', '—')} | {r['moving_usable']} | {r['selected']} | "
               f"{r['moving_selected']} | {r['max_gyro_over_clip_selected']:.3f} | "
               f"{r['max_acc_over_clip_selected']:.3f} |\n")
    if results:
        mv = [r["moving_selected"] / r["selected"] for r in results]
        st = [r["dropped"].get("still_by_gyroscopes", 0) for r in results]
        md += (f"\n{_rng([r['moving_selected'] for r in results], 'd')} of the {args.samples} selected samples per "
               f"capture ({min(mv):.0%}-{max(mv):.0%}) have mean |gyro| > {MOVING_RAD_S} rad/s; the others pass the "
               "gyroscope test by angular acceleration (starts and ends of twists). The gyroscope test dropped "
               f"{_rng(st, 'd')} samples per capture as still: mean |gyro| median "
               f"{_rng([r['still_gyro_rate_median'] for r in results if r.get('still_gyro_rate_median') is not None], '.2g')} "
               "rad/s, yet the fused motion (whose omega_dot comes from the accelerometers, biases uncalibrated) gives "
               "them |omega_dot| median "
               f"{_rng([r['still_fused_omega_dot_median'] for r in results if r.get('still_fused_omega_dot_median') is not None], '.3g')} "
               "rad/s^2, which is why they passed the fused-motion test.\n\n")

    ne = [(r["capture"], r["noise_estimate"]) for r in results if "noise_estimate" in r]
    if ne:
        md += ("## Setting (c): the ML accelerometer noise per capture\n\n"
               "| capture | fit: samples used | residual RMS per IMU (m/s^2) | sigma_a (m/s^2) | / 0.045 | / 0.79 | "
               "after one refit at sigma_a | gyroscope residual RMS (rad/s) | / the model's gyro std | NIS of the fit "
               "(description noise) |\n|---|---|---|---|---|---|---|---|---|---|\n")
        for cap, n in ne:
            md += (f"| {cap} | {n['fit_samples_used']} | {', '.join(f'{v:.3g}' for v in n['rms_per_imu'])} | "
                   f"{n['sigma_a']:.4g} | {n['sigma_a'] / 0.045:.1f} | {n['sigma_a'] / PAPER_SIGMA_A:.2f} | "
                   f"{n['sigma_after_one_refit']:.4g} | {n['gyro_residual_rms']:.3g} | "
                   f"{n['gyro_residual_rms'] / n['gyro_std_model']:.0f} | {n['nis_after']:.4g} |\n")
        md += "\n"

    for label, (_, _, text) in SETTINGS.items():
        recs = _recs(results, label)
        if not recs:
            continue
        md += f"## Setting ({label}): {text}\n\n### Sampler\n\n"
        refused = [(cap, s) for cap, s in recs if "mean_free" not in s]
        ok = [(cap, s) for cap, s in recs if "mean_free" in s]
        if refused:
            md += ("| capture | sigma_a (m/s^2) | sampler | tuning: Var[log p_N] at N (target 0.1) | Laplace std median (um) | "
                   "Laplace fit: samples used |\n|---|---|---|---|---|---|\n")
            for cap, s in refused:
                what = "**refused** (untunable)" if s.get("refused") else f"**failed**: {s.get('error', '—')}"
                tab = ", ".join(f"{v:.3g} at {n}" for n, v in s.get("var_loglik", [])) or "—"
                sd = (f"{np.median(np.sqrt(np.diag(s['laplace_cov_free']))) * UM:.3g}"
                      if "laplace_cov_free" in s else "—")
                md += (f"| {cap} | {s['accel_std']:.4g} | {what} | {tab} | {sd} | "
                       f"{s.get('laplace_fit_samples_used', '—')} |\n")
            errs = [s["error"] for _, s in refused if s.get("refused")]
            if errs:
                md += f"\nThe error, e.g. for {refused[0][0]}: \"{errs[0]}\"\n\n"
        if ok:
            md += ("| capture | sigma_a (m/s^2) | N | Var[log p_N] at N | log-ratio noise sd rho=0 / 0.9 | warm-up | "
                   "draws/chain | RW acceptance | indep. acceptance | positions: ESS bulk / tail | positions: R-hat | "
                   "log-lik estimate: R-hat | converged | wall s | CPU s | Laplace: max / RMS \\|z\\| | "
                   "Laplace/MCMC sd ratio | Laplace agrees | Laplace fit: samples used | mode: from post. / Laplace mean "
                   "(without log-det: from Laplace) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
                   "---|---|---|---|\n")
            for cap, s in ok:
                la, th, rn, mc = s["laplace_agreement"], s["theta_only"], s["ratio_noise_sd"], s["mode_check"]
                md += (f"| {cap} | {s['accel_std']:.4g} | {s['n_draws']} | "
                       f"{', '.join(f'{v:.2g} at {n}' for n, v in s['var_loglik'])} | "
                       f"{rn['0.0']:.2g} / {rn['0.9']:.2g} | {s['warmup_per_chain']} | {s['draws_per_chain']} | "
                       f"{min(s['acceptance_random_walk']):.0%}-{max(s['acceptance_random_walk']):.0%} | "
                       f"{np.nanmin(s['acceptance_independence']):.0%}-{np.nanmax(s['acceptance_independence']):.0%} | "
                       f"{th['ess_bulk_min']:.0f} / {th['ess_tail_min']:.0f} | {th['rhat_max']:.3f} | "
                       f"{s['rhat_loglik_estimate']:.3f} | {'yes' if s['converged'] else '**no**'} | "
                       f"{s['seconds']:.0f} | {s['cpu_seconds']:.0f} | {la['max_abs_mean_z']:.2f} / {la['rms_mean_z']:.2f} | "
                       f"{la['sd_ratio_min']:.2f}-{la['sd_ratio_max']:.2f} | {'yes' if la['agrees'] else 'no'} | "
                       f"{s['laplace_fit_samples_used']} | "
                       f"{mc['with_logdet']['max_abs_z_vs_posterior_mean']:.2f} / "
                       f"{mc['with_logdet']['max_abs_z_vs_laplace_mean']:.2f} "
                       f"({mc['without_logdet']['max_abs_z_vs_laplace_mean']:.2f}) |\n")
            md += "\n"
        mls = [(cap, s["ml"]) for cap, s in recs if "ml" in s]
        if mls:
            md += ("ML(all) on every usable sample:\n\n| capture | usable | samples used | NIS before -> after | s |\n"
                   "|---|---|---|---|---|\n")
            for cap, m in mls:
                md += (f"| {cap} | {m['usable']} | {m['samples_used']} | {m['nis_before']:.4g} -> "
                       f"{m['nis_after']:.4g} | {m['seconds']:.1f} |\n")
            md += "\n"
        srcs = {estimate(s)[2] for _, s in recs if estimate(s) is not None}
        what = ("posterior" if srcs == {"posterior"} else "**Laplace approximation (not a posterior)**"
                if srcs == {"Laplace"} else "posterior or **Laplace approximation** (column source)")
        md += (f"### Per IMU\n\n{what[0].upper() + what[1:]}: mean (mm) and std (um) of each "
               "free IMU; ML(all): the ML estimate on every usable sample (mm) and its CRB std (um); z = (mean - "
               "ML) / std.\n\n| IMU | capture | source | mean x, y, z (mm) | std x, y, z (um) | ML(all) x, y, z (mm) | "
               "CRB x, y, z (um) | z vs ML |\n|---|---|---|---|---|---|---|---|\n")
        for j, kk in enumerate(free):
            for cap, s in recs:
                e = estimate(s)
                if e is None:
                    continue
                sl = slice(3 * j, 3 * j + 3)
                m, sd = e[0][sl], np.sqrt(np.diag(e[1]))[sl]
                if "ml" in s:
                    ml = np.array(s["ml"]["theta"])[sl]
                    crb = np.sqrt(np.diag(s["ml"]["crb_free"]))[sl]
                    mlt = (", ".join(f"{v * MM:.3f}" for v in ml), ", ".join(f"{v * UM:.3g}" for v in crb),
                           ", ".join(f"{v:+.1f}" for v in (m - ml) / sd))
                else:
                    mlt = ("—", "—", "—")
                md += (f"| {names[kk]} | {cap} | {e[2]} | {', '.join(f'{v * MM:.3f}' for v in m)} | "
                       f"{', '.join(f'{v * UM:.3g}' for v in sd)} | {mlt[0]} | {mlt[1]} | {mlt[2]} |\n")
        c = comps.get(label) or {}
        if c.get("pairs") and "scatter_um" in c:
            md += f"\n### Between captures ({what})\n\n"
            md += ("Scatter of the means across the captures (sample std, um) against the RMS std (um), per "
                   "coordinate:\n\n| IMU | " + " | ".join(
                       f"{a}: scatter | {a}: std | {a}: ratio" for a in axes) + " |\n|---|" + "---|---|---|" * 3 + "\n")
            for j, kk in enumerate(free):
                cells = []
                for a in range(3):
                    q = 3 * j + a
                    cells.append(f"{c['scatter_um'][q]:.3g} | {c['sd_rms_um'][q]:.3g} | {c['scatter_over_sd'][q]:.3g}")
                md += f"| {names[kk]} | " + " | ".join(cells) + " |\n"
            md += ("\nPairs: chi2 of the 21 free coordinates with the combined covariance, its p-value, the largest "
                   "and median |z|, and the IMUs whose own 3-dof chi2 has p < 0.01.\n\n"
                   "| pair | chi2 (21 dof) | p | max \\|z\\| | median \\|z\\| | IMUs with p < 0.01 |\n"
                   "|---|---|---|---|---|---|\n")
            for p in c["pairs"]:
                bad = [n for n, v in p["imu"].items() if v["p"] < 0.01]
                md += (f"| {p['pair'][0]} - {p['pair'][1]} | {p['chi2']:.4g} | {_p(p['p'])} | {p['max_abs_z']:.3g} | "
                       f"{p['median_abs_z']:.3g} | {', '.join(bad) if bad else 'none'} |\n")
            if "ml" in c and c["ml"].get("ml_scatter_um") is not None:
                m = c["ml"]
                md += (f"\nML(all) vs {what}: mean - ML {m['minus_ml_rms_um']:.3g} um RMS over coordinates and "
                       "captures; |z| per capture: "
                       + ", ".join(f"{cap} max {mx:.2g} (RMS {rm:.2g})" for cap, mx, rm in
                                   zip(c["captures"], m["max_abs_z_per_capture"], m["rms_z_per_capture"]))
                       + f". CRB median {m['crb_sd_median_um']:.3g} um vs std median {c['sd_median_um']:.3g} um; the "
                       f"ML estimates scatter between captures by {np.sqrt(np.mean(np.square(m['ml_scatter_um']))):.3g} "
                       f"um RMS, {m['ml_scatter_over_crb_median']:.3g}x their CRB (median over coordinates).\n")
        md += "\n"
    return md


def plots(results, names, nominal, free, out_dir: Path, args, traces: bool = True) -> list[str]:
    """The ellipse figure per setting with posteriors (from the means and covariances) and, with ``traces``,
    the trace plot of its posterior with the lowest ESS (needs the chains)."""
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
        extent = max(float(np.max(np.abs(pos[1:, :2] - nominal[1:, :2])
                                  + ellipse_radius(0.5) * np.sqrt(np.einsum("kii->ki", cov[1:, :2, :2]))))
                     for pos, cov in est.values()) * MM
        path = out_dir / f"{NAME}_ellipses_{label}.png"
        plot_ellipses(path, names, nominal, est, prior_std=prior_std, package=PACKAGE_SIZE, reference=names[0],
                      view=max(2.2, 1.15 * extent),
                      title=f"({label}) {text}: 50 % credible ellipses (x-y) of the position posteriors, one colour "
                            f"per capture, T = {args.samples}; mm relative to nominal")
        written.append(path.name)
        if not traces or "_post" not in worst[1]:
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
    ap.add_argument("--samples", type=int, default=500, help="T, samples per capture (default 500)")
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ess", type=float, default=400.0)
    ap.add_argument("--max-warmup", type=int, default=10000, help="warm-up cap per chain (library default 40000)")
    ap.add_argument("--max-iterations", type=int, default=40000,
                    help="sampling cap per chain (library default 400000)")
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
        out_dir = args.out
        args = argparse.Namespace(**{**record["args"], "out": out_dir, "report_only": True})
        old = (out_dir / f"{NAME}.md").read_text() if (out_dir / f"{NAME}.md").exists() else ""
        # the run's header, up to its code line (without one: a new header, whose command is this one)
        header = old[:old.index("\n", old.index("- code:")) + 1] if "- code:" in old else (
            machine_header(TITLE) + f"- run time: {total:.0f} s (the run that wrote {NAME}.json)\n- code: {_commit()}\n")
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
        for stale in sorted(args.out.glob(f"{NAME}_*.png")):  # figures of an earlier run that this one has not
            if stale.name not in pngs:
                stale.unlink()
                say(f"removed {stale.name} (no posterior for it in this run)")
        total = time.perf_counter() - t_start
    comps = {label: compare(results, label, names, free) for label in SETTINGS}
    for r in results:
        for st in r["settings"].values():
            st.pop("_post", None)
    record = {"script": "benchmarks/bayes_real.py", "args": {k: (str(v) if isinstance(v, Path) else v)
                                                             for k, v in vars(args).items() if k != "report_only"},
              "settings": {k: v[2] for k, v in SETTINGS.items()}, "names": names,
              "nominal": nominal.tolist(), "free": [names[f] for f in free], "units": "m, m^2, m/s^2",
              "captures": results, "comparisons": comps, "figures": pngs, "seconds": total}
    if not getattr(args, "report_only", False):  # the numbers first: --report-only can rebuild the text
        atomic_write_text(args.out / f"{NAME}.json", json.dumps(json_safe(record), indent=1) + "\n")
    md = markdown(results, comps, names, free, args, total, header)
    md += "## Figures\n\n" + ("\n".join(f"- `{p}`" for p in pngs) if pngs else "none (no posterior)") + "\n"
    if pngs:
        md += ("\n`bayes_real_ellipses_<setting>.png`: carlsson2021 Fig. 5 style, one panel per IMU as on the board "
               "(top side left, underside right, seen from above), 50 % ellipses of each capture's posterior, the "
               "prior (cyan) and the 4 x 4 mm package outline (dashed). `bayes_real_trace_<setting>.png`: the chains "
               "of the posterior with the lowest ESS in that setting (ArviZ trace of its six worst coordinates, the "
               "log posterior, and the discarded warm-up). Settings whose sampler refused have no figures (no "
               "chains; their Laplace approximations are in the tables).\n")
    atomic_write_text(args.out / f"{NAME}.md", md)
    say(f"wrote {args.out / (NAME + '.md')}{'' if getattr(args, 'report_only', False) else ' and .json'} "
        f"in {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
