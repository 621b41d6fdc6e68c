"""The Bayesian (PmMH) position calibration on the six real MIMU4444BT captures (carlsson2021 Sec. IV-B/C).

For each capture ../shared/data/openshoe_mimu4444bt/exp_N.bin, imported with the nominal description
config/mimu4444bt_corners.yaml (``import_capture(path, desc)[0]``), as ``imu-array calibrate bayes``
does per recording: T samples (default 500) spread evenly over the usable ones (``select_samples``: every
reading valid, rotation by the fused motion's test and by the gyroscopes'), ``build_problem``
(reference imu_1 held, gaussian prior N(nominal, 3 mm)), ``laplace`` (ML on the same samples + CRB +
prior), then ``sample_posterior`` as the library runs it by default -- N tuned to Var[log p_N] <= 0.1
(refused when even N = 1024 leaves it above 10x that), rho 0.9, 4 chains on 2 worker processes,
Laplace-shaped random walk mixed with independence proposals, ESS >= 400, R-hat <= 1.01 -- with the
warm-up and sampling capped (see Method), in three noise settings:

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

Writes benchmarks/results/bayes_real.md (tables: :mod:`benchmarks.bayes_real_report`), bayes_real.json,
bayes_real_ellipses_<setting>.png and bayes_real_trace_<setting>.png for every setting with posteriors (and
removes those of settings without).

    python -m benchmarks.bayes_real [--captures 1 2 ...] [--settings a b c] [--samples 500]
        [--max-warmup 10000] [--max-iterations 40000] [--report-only]
"""

from __future__ import annotations

from benchmarks.harness import DATA, REPO, RESULTS, header_of, machine_header, say, single_threaded_blas, write_results

single_threaded_blas()

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

DESC = REPO / "config" / "mimu4444bt_corners.yaml"
NAME = "bayes_real"
TITLE = "Bayesian (PmMH) position calibration on the real MIMU4444BT captures"
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


def noise_estimate(sel, model) -> dict:
    """Setting (c)'s sigma_a: the ML estimate of the accelerometer noise on the T selected samples.

    The fit is the one setting (a)'s ``laplace`` runs (``calibrate_geometry``, joint solver, the
    description's noise, ``min_excitation=0``) on the same samples; sigma_a = the RMS over every IMU, axis
    and sample of its accelerometer residuals at the ML positions and motion (the ML estimate of a common
    white-noise std).  As a check, the positions and motion are refitted once with that sigma_a on the
    same samples (``fit_terms``: no sample selection) and the RMS recomputed."""
    from imu_array_ros.calibration.geometry import calibrate_geometry
    from imu_array_ros.calibration.scoring import profile_window
    from imu_array_ros.fitting.engine import fit_terms
    from imu_array_ros.fusion.model_fusion import ModelFusion
    from imu_array_ros.model.sensor_model import motion_context

    k = model.n_imus
    geo = calibrate_geometry(sel, model, reference=0, method="joint", min_excitation=0.0)
    rms = np.asarray(geo.rms_after, dtype=float)
    sigma = float(np.sqrt(np.mean(rms ** 2)))  # every selected sample is complete: equal counts per IMU
    m = dataclasses.replace(model, acc_std=np.full((k, 3), sigma))
    fit = fit_terms(sel, m, ["position"], reference=0)
    refit = float(np.sqrt(np.mean(profile_window(sel, fit.model).rms ** 2)))
    # the gyroscopes at the same fit: how far they are from one rigid-body omega (the noise model says 0.0039 rad/s)
    fused, _ = ModelFusion(geo.model).fuse(sel)
    rows = np.searchsorted(sel.stamps, fused.stamps)
    ctx = motion_context(fused.stamps, fused.omega, fused.omega_dot, fused.specific_force, geo.model.rotations,
                         derivatives=True)
    _, gyr_pred = geo.model.predict(ctx)
    gyro_rms = float(np.sqrt(np.mean((sel.gyro[rows] - gyr_pred) ** 2)))
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
    from imu_array_ros.calibration import bayes
    from imu_array_ros.calibration.geometry import calibrate_geometry
    from imu_array_ros.calibration.selection import MIN_EXCITATION, select_rotating
    from imu_array_ros.errors import CalibrationError
    from imu_array_ros.io.openshoe.capture import import_capture

    samples = import_capture(DATA / f"exp_{i}.bin", desc)[0]
    t0 = time.perf_counter()
    idx, dropped, usable = bayes.select_samples(samples, model, args.samples)
    select_s = time.perf_counter() - t0
    all_idx, _, _ = bayes.select_samples(samples, model, None)
    rate = np.mean(np.linalg.norm(samples.gyro, axis=2), axis=1)  # rotation invariant: mean over IMUs of |gyro|
    sel = samples.select(idx)
    # the samples the gyroscope test drops: what the fused-motion test saw in them
    by_motion = select_rotating(samples, model, MIN_EXCITATION)
    motion = by_motion.motion
    still = by_motion.used.copy()
    still[all_idx] = False
    out = {
        "capture": f"exp_{i}", "samples_total": int(len(samples)), "usable": int(usable),
        "dropped": {key: int(v) for key, v in dropped.items()}, "selected": int(len(idx)),
        "moving_selected": int(np.sum(rate[idx] > MOVING_RAD_S)),
        "moving_usable": int(np.sum(rate[all_idx] > MOVING_RAD_S)),
        "max_gyro_over_clip_selected": float(np.max(np.abs(sel.gyro)) / model.gyro_clip),
        "max_acc_over_clip_selected": float(np.max(np.abs(sel.accel)) / model.acc_clip),
        "select_seconds": select_s, "settings": {},
        "still_fused_omega_dot_median": float(np.median(np.linalg.norm(motion[still, 3:6], axis=1)))
        if still.any() else None,
        "still_gyro_rate_median": float(np.median(rate[still])) if still.any() else None,
    }
    say(f"exp_{i}: {len(idx)} of {usable} usable samples ({len(samples)} total, dropped {dropped}); "
        f"{out['moving_selected']} of the selected have mean |gyro| > {MOVING_RAD_S} rad/s")
    if ML_SIGMA in [SETTINGS[lab][0] for lab in args.settings]:
        t0 = time.perf_counter()
        out["noise_estimate"] = noise_estimate(sel, model)
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
        settings = bayes.SamplerSettings(
            chains=args.chains, workers=args.workers, seed=seed, ess=args.ess,
            max_warmup=args.max_warmup, max_iterations=args.max_iterations)
        rec["sampler_settings"] = dataclasses.asdict(settings)
        try:
            t0 = time.perf_counter()
            problem = bayes.build_problem(sel, model, reference=0, accel_std=accel_std, omega_covariance=omega_cov)
            lap = bayes.laplace(problem, sel, model)
            rec["laplace_seconds"] = time.perf_counter() - t0
        except CalibrationError as err:
            rec["error"] = f"Laplace: {err}"
            say(f"exp_{i} ({label}): Laplace FAILED: {err}")
            continue
        cov_w = problem.chol @ problem.chol.transpose(0, 2, 1)
        rec["omega_std_median"] = float(np.median(np.sqrt(np.einsum("tii->t", cov_w) / 3)))  # rad/s, per axis
        lm = laplace_model(problem, model)
        # how many of the T samples the Laplace's ML fit uses (its noise-dependent excitation test may drop some)
        geo_lap = calibrate_geometry(sel, lm, reference=0, method="joint", min_excitation=0.0)
        rec.update({"laplace_mean_free": lap.mean.tolist(), "laplace_cov_free": lap.covariance.tolist(),
                    "laplace_fit_samples_used": int(geo_lap.samples_used)})
        try:
            post = bayes.sample_posterior(problem, lap, settings,
                                          progress=lambda s, lab=label: say(f"exp_{i} ({lab}): {s}"))
        except CalibrationError as err:
            rec["error"] = str(err)
            rec["refused"] = "too noisy to sample" in str(err)
            say(f"exp_{i} ({label}): sampler refused: {err}")
            if rec["refused"]:  # the tuning table: the same call with the same generator as the sampler's
                _, table = bayes.choose_draws(problem, lap.mean, settings.loglik_var,
                                              np.random.default_rng(settings.seed))
                rec["var_loglik"] = [[int(n), float(v)] for n, v in table]
        else:
            rec["refused"] = False
            say(f"exp_{i} ({label}): {post.summary_line()}")
            ess_t, ess_tail_t, rhat_t = bayes.chain_diagnostics(post.draws)  # theta alone (the sampler adds the log-lik)
            _, _, rhat_ll = bayes.chain_diagnostics(post.loglik[..., None])
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
                "laplace_agreement": bayes.laplace_agreement(post),
                "ratio_noise_sd": {str(r): ratio_noise(p_n, lap.mean, lap_chol, r, rng) for r in RHO_CHECK},
                "mode_check": mode_check(problem, lap, post, rng),
            })
            rec["check_seconds"] = time.perf_counter() - t0
            rec["_post"] = post  # for the trace plot; dropped before writing JSON
        # the ML estimate on every usable sample of the capture (select_samples with no cap), the Laplace's noise
        t0 = time.perf_counter()
        try:
            geo = calibrate_geometry(samples.select(all_idx), lm, reference=0, method="joint", min_excitation=0.0)
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
            pr = bayes.build_problem(sel, model, reference=0, accel_std=sa, omega_covariance=oc)
            out["swap"][key] = {str(n): bayes.loglik_variance(pr.with_(n_draws=n), theta, bayes.VAR_REPLICATES, rng)
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
    from benchmarks.bayes_real_report import markdown, plots
    from imu_array_ros.util.files import atomic_write_text
    from imu_array_ros.util.jsontools import json_safe
    from imu_array_ros.model.description import load_description
    from imu_array_ros.model.sensor_model import SensorModel

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
        # the header of the run that wrote the numbers (without one: a new header, whose command is this one)
        header = (record.get("header") or header_of(out_dir / f"{NAME}.md")
                  or machine_header(TITLE, extra=[f"run time: {total:.0f} s (the run that wrote {NAME}.json)"]))
        header = "\n".join(ln for ln in header.splitlines()  # without an earlier rebuild's line
                            if not ln.startswith("- report text and ellipse figures rebuilt")).rstrip("\n") + (
            f"\n- report text and ellipse figures rebuilt from {NAME}.json by `--report-only` on "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} (same numbers, no new sampling)\n\n")
        plots(results, names, nominal, free, out_dir, args, traces=False)
    else:
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
        header = machine_header(TITLE, extra=[f"run time: {total:.0f} s (whole script; {len(results)} captures x "
                                              f"{len(args.settings)} settings one after the other; machine shared "
                                              "with other work)"])
    comps = {label: compare(results, label, names, free) for label in SETTINGS}
    for r in results:
        for st in r["settings"].values():
            st.pop("_post", None)
    record = {"script": "benchmarks/bayes_real.py", "args": {k: (str(v) if isinstance(v, Path) else v)
                                                             for k, v in vars(args).items() if k != "report_only"},
              "settings": {k: v[2] for k, v in SETTINGS.items()}, "names": names,
              "nominal": nominal.tolist(), "free": [names[f] for f in free], "units": "m, m^2, m/s^2",
              "captures": results, "comparisons": comps, "figures": pngs, "seconds": total, "header": header}
    if not getattr(args, "report_only", False):  # the numbers first: --report-only can rebuild the text
        atomic_write_text(args.out / f"{NAME}.json", json.dumps(json_safe(record), indent=1) + "\n")
    md = markdown(results, comps, names, free, args, header)
    md += "## Figures\n\n" + ("\n".join(f"- `{p}`" for p in pngs) if pngs else "none (no posterior)") + "\n"
    if pngs:
        md += ("\n`bayes_real_ellipses_<setting>.png`: carlsson2021 Fig. 5 style, one panel per IMU as on the board "
               "(top side left, underside right, seen from above), 50 % ellipses of each capture's posterior, the "
               "prior (cyan) and the 4 x 4 mm package outline (dashed). `bayes_real_trace_<setting>.png`: the chains "
               "of the posterior with the lowest ESS in that setting (ArviZ trace of its six worst coordinates, the "
               "log posterior, and the discarded warm-up). Settings whose sampler refused have no figures (no "
               "chains; their Laplace approximations are in the tables).\n")
    write_results(args.out / f"{NAME}.md", md)
    say(f"wrote {args.out / (NAME + '.md')}{'' if getattr(args, 'report_only', False) else ' and .json'} "
        f"in {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
