"""The results file of :mod:`benchmarks.bayes_real`: tables and figures from its records (also from a saved
bayes_real.json: ``--report-only``).  What they mean is the file's hand-written ``## Interpretation``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.bayes_real import (
    MM,
    MODE_DRAWS,
    MOVING_RAD_S,
    NAME,
    PAPER_SIGMA_A,
    SETTINGS,
    UM,
    estimate,
    per_imu,
)
from benchmarks.harness import say


def _rng(vals, spec=".3g") -> str:
    """'lo-hi' (or the one value) of a list of numbers; '—' for none."""
    vals = [int(v) if spec == "d" else float(v) for v in vals if v is not None]
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
    from benchmarks import bayes_real

    doc = bayes_real.__doc__.split("\n\n", 1)[1]
    return doc[:doc.index("\nWrites benchmarks/")].strip() + "\n\n"


def summary(results, comps, args) -> str:
    """One table, a column per setting: the sampler, the Laplace approximation, agreement between captures and
    with the ML on all usable samples."""
    from imu_array_ros.calibration.bayes import MAX_DRAWS

    labels = [lab for lab in SETTINGS if _recs(results, lab)]
    if not labels:
        return ""
    rows: dict[str, list[str]] = {}

    def row(name: str, fn) -> None:
        rows[name] = [fn(lab) for lab in labels]

    recs = {lab: [s for _, s in _recs(results, lab)] for lab in labels}
    ok = {lab: [s for s in recs[lab] if "mean_free" in s] for lab in labels}
    ref = {lab: [s for s in recs[lab] if s.get("refused")] for lab in labels}
    c = {lab: comps.get(lab) or {} for lab in labels}
    ml = {lab: c[lab].get("ml") or {} for lab in labels}
    row("sigma_a (m/s^2)", lambda lab: _rng([s["accel_std"] for s in recs[lab]]))
    row("median std of the omega draws (rad/s per axis)",
        lambda lab: _rng([s.get("omega_std_median") for s in recs[lab]], ".2g"))
    row("captures: posterior / sampler refused (untunable) / other failure",
        lambda lab: f"{len(ok[lab])} / {len(ref[lab])} / {len(recs[lab]) - len(ok[lab]) - len(ref[lab])}")
    row(f"refused: Var[log p_N] at the Laplace mean, N = 1 / N = {MAX_DRAWS}",
        lambda lab: (f"{_rng([_var_at(s, 1) for s in ref[lab]])} / {_rng([_var_at(s, MAX_DRAWS) for s in ref[lab]])}"
                     if ref[lab] else "—"))
    row("posteriors: N tuned (Var[log p_N] at N)",
        lambda lab: (f"{_rng([s['n_draws'] for s in ok[lab]], 'd')} "
                     f"({_rng([s['var_loglik'][-1][1] for s in ok[lab]], '.2g')})" if ok[lab] else "—"))
    row("converged (ESS >= {:g}, R-hat <= 1.01)".format(args.ess),
        lambda lab: f"{sum(s['converged'] for s in ok[lab])} of {len(ok[lab])}" if ok[lab] else "—")
    row("warm-up + draws per chain",
        lambda lab: (f"{_rng([s['warmup_per_chain'] for s in ok[lab]], 'd')} + "
                     f"{_rng([s['draws_per_chain'] for s in ok[lab]], 'd')}" if ok[lab] else "—"))
    row("positions: ESS bulk / R-hat; log-lik estimate R-hat",
        lambda lab: (f"{_rng([s['theta_only']['ess_bulk_min'] for s in ok[lab]], '.0f')} / "
                     f"{_rng([s['theta_only']['rhat_max'] for s in ok[lab]], '.3f')}; "
                     f"{_rng([s['rhat_loglik_estimate'] for s in ok[lab]], '.3f')}" if ok[lab] else "—"))
    row("wall s per posterior", lambda lab: _rng([s["seconds"] for s in ok[lab]], ".0f"))
    row("log acceptance ratio noise sd, rho = 0 / 0.9",
        lambda lab: (f"{_rng([s['ratio_noise_sd']['0.0'] for s in ok[lab]], '.2g')} / "
                     f"{_rng([s['ratio_noise_sd']['0.9'] for s in ok[lab]], '.2g')}" if ok[lab] else "—"))
    row("Laplace agrees with the chains (`laplace_agreement`)",
        lambda lab: f"{sum(s['laplace_agreement']['agrees'] for s in ok[lab])} of {len(ok[lab])}" if ok[lab] else "—")
    row("Laplace: max / RMS \\|mean z\\| (posterior stds)",
        lambda lab: (f"{_rng([s['laplace_agreement']['max_abs_mean_z'] for s in ok[lab]], '.2g')} / "
                     f"{_rng([s['laplace_agreement']['rms_mean_z'] for s in ok[lab]], '.2g')}" if ok[lab] else "—"))
    row("Laplace / MCMC std ratio", lambda lab: _rng([s["laplace_agreement"][q] for s in ok[lab]
                                                      for q in ("sd_ratio_min", "sd_ratio_max")], ".2f"))
    def mode(lab: str, which: str, to: str) -> str:
        return _rng([s["mode_check"][which][f"max_abs_z_vs_{to}_mean"] for s in ok[lab]], ".2g")

    row("mode of the sampled target: from the posterior mean / the Laplace mean; without the log-det term: "
        "from the Laplace mean (posterior stds)",
        lambda lab: (f"{mode(lab, 'with_logdet', 'posterior')} / {mode(lab, 'with_logdet', 'laplace')}; "
                     f"{mode(lab, 'without_logdet', 'laplace')}" if ok[lab] else "—"))
    row("Laplace fit: samples used (of T)",
        lambda lab: _rng([s.get("laplace_fit_samples_used") for s in recs[lab]], "d"))
    row("estimate compared between captures", lambda lab: " / ".join(sorted(set(c[lab].get("sources", [])))) or "—")
    row("its std, median (um)", lambda lab: f"{c[lab]['sd_median_um']:.3g}" if "sd_median_um" in c[lab] else "—")
    row("scatter of the means between captures, RMS per coordinate (um)",
        lambda lab: (f"{np.sqrt(np.mean(np.square(c[lab]['scatter_um']))):.3g}" if "scatter_um" in c[lab] else "—"))
    row("scatter / std: median (range) over coordinates",
        lambda lab: (f"{np.median(c[lab]['scatter_over_sd']):.3g} ({min(c[lab]['scatter_over_sd']):.2g}-"
                     f"{max(c[lab]['scatter_over_sd']):.2g})" if "scatter_over_sd" in c[lab] else "—"))
    row("coordinates with scatter / std > 1",
        lambda lab: (f"{int(np.sum(np.array(c[lab]['scatter_over_sd']) > 1))} of {len(c[lab]['scatter_over_sd'])}"
                     if "scatter_over_sd" in c[lab] else "—"))
    row("mean sigma_a x median scatter / std (m/s^2)",
        lambda lab: (f"{np.mean([s['accel_std'] for s in recs[lab]]) * np.median(c[lab]['scatter_over_sd']):.2g}"
                     if "scatter_over_sd" in c[lab] else "—"))
    row("pairs with chi2 p < 0.01 (21 dof); p range",
        lambda lab: (f"{sum(p['p'] < 0.01 for p in c[lab]['pairs'])} of {len(c[lab]['pairs'])}; "
                     f"{_p(min(p['p'] for p in c[lab]['pairs']))} to {_p(max(p['p'] for p in c[lab]['pairs']))}"
                     if c[lab].get("pairs") else "—"))
    row("IMU-pairs with 3-dof chi2 p < 0.01",
        lambda lab: (f"{sum(sum(v['p'] < 0.01 for v in p['imu'].values()) for p in c[lab]['pairs'])} of "
                     f"{sum(len(p['imu']) for p in c[lab]['pairs'])}" if c[lab].get("pairs") else "—"))
    row("pooled z RMS (1 expected); share of \\|z\\| > 2 (5 % expected)",
        lambda lab: (f"{c[lab]['pooled_z_rms']:.3g}; {c[lab]['fraction_abs_z_gt_2']:.0%}"
                     if "pooled_z_rms" in c[lab] else "—"))
    row("ML(all): CRB median (um)", lambda lab: f"{ml[lab]['crb_sd_median_um']:.3g}" if ml[lab] else "—")
    row("ML(all): scatter between captures / CRB, median",
        lambda lab: (f"{ml[lab]['ml_scatter_over_crb_median']:.3g}"
                     if ml[lab].get("ml_scatter_over_crb_median") is not None else "—"))
    row("estimate - ML(all): RMS (um); max \\|z\\| (its stds)",
        lambda lab: (f"{ml[lab]['minus_ml_rms_um']:.3g}; {max(ml[lab]['max_abs_z_per_capture']):.3g}"
                     if ml[lab] else "—"))
    row("Laplace mean - ML(all): RMS (um)",
        lambda lab: f"{ml[lab]['laplace_minus_ml_rms_um']:.3g}" if "laplace_minus_ml_rms_um" in ml[lab] else "—")
    md = ("## Summary\n\nPer setting, over the captures (ranges: lowest-highest capture; *estimate*: the posterior "
          "where the sampler ran, else the Laplace approximation, which is not a posterior).\n\n| | "
          + " | ".join(f"({lab})" for lab in labels) + " |\n|---|" + "---|" * len(labels) + "\n")
    md += "".join(f"| {name} | " + " | ".join(cells) + " |\n" for name, cells in rows.items())
    md += "\n" + "".join(f"- ({lab}) {SETTINGS[lab][2]}\n" for lab in labels) + "\n"
    return md


def swap_table(results) -> str:
    """Var[log p_N] with the settings' ingredients swapped (sigma_a and omega covariance), per capture."""
    from imu_array_ros.calibration.bayes import VAR_REPLICATES

    sw = [(r["capture"], r["swap"]) for r in results if "swap" in r]
    if not sw:
        return ""
    keys = list(sw[0][1])
    md = ("## Which ingredient makes the log-likelihood estimate noisy\n\nVar[log p_N] at N = 1 / N = 16 at setting "
          f"(c)'s Laplace mean ({VAR_REPLICATES} replicates) with setting (c)'s sigma_a (`sigma_c`) or "
          f"{PAPER_SIGMA_A} m/s^2, and the omega covariance of the gyroscope noise model (`model`) or eq. 30 "
          "(`sample`).\n\n| capture | " + " | ".join(f"{k}: N = 1 / 16" for k in keys) + " |\n|---|"
          + "---|" * len(keys) + "\n")
    for cap, s in sw:
        md += f"| {cap} | " + " | ".join(f"{s[k]['1']:.3g} / {s[k]['16']:.3g}" for k in keys) + " |\n"
    return md + "\n"


def a_vs_b_table(results) -> str:
    """The estimates of settings (a) and (b) of each capture against each other."""
    rows = []
    for r in results:
        ea, eb = estimate(r["settings"].get("a", {})), estimate(r["settings"].get("b", {}))
        if ea is None or eb is None:
            continue
        rows.append(f"| {r['capture']} | {ea[2]} / {eb[2]} | {np.sqrt(np.mean((ea[0] - eb[0]) ** 2)) * UM:.3g} | "
                    f"{np.max(np.abs(ea[0] - eb[0]) / np.sqrt(np.diag(eb[1]))):.2g} |")
    if not rows:
        return ""
    return ("## Settings (a) and (b) against each other\n\n| capture | estimates (a) / (b) | RMS difference (um) | "
            "max \\|difference\\| in (b) stds |\n|---|---|---|---|\n" + "\n".join(rows) + "\n\n")


def samples_table(results) -> str:
    md = "## Samples\n\n"
    md += ("| capture | samples | usable | dropped: clipped/missing | little rotation | not identified | "
           "still by gyroscopes | usable moving (mean \\|gyro\\| > 1 rad/s) | selected | of them moving | "
           "max \\|gyro\\| / clip | max \\|acc\\| / clip | still by gyroscopes: median mean \\|gyro\\| (rad/s) | "
           "their fused \\|omega_dot\\| median (rad/s^2) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    for r in results:
        dr = r["dropped"]
        g, w = r.get("still_gyro_rate_median"), r.get("still_fused_omega_dot_median")
        md += (f"| {r['capture']} | {r['samples_total']} | {r['usable']} | {dr.get('missing_or_saturated', '—')} | "
               f"{dr.get('little_rotation', '—')} | {dr.get('motion_not_identified', '—')} | "
               f"{dr.get('still_by_gyroscopes', '—')} | {r['moving_usable']} | {r['selected']} | "
               f"{r['moving_selected']} | {r['max_gyro_over_clip_selected']:.3f} | "
               f"{r['max_acc_over_clip_selected']:.3f} | {'—' if g is None else f'{g:.2g}'} | "
               f"{'—' if w is None else f'{w:.3g}'} |\n")
    return md + (f"\n*moving*: mean over the IMUs of \\|gyro\\| > {MOVING_RAD_S} rad/s.\n\n")


def markdown(results, comps, names, free, args, header: str) -> str:
    """The whole results file but the interpretation: ``header`` (the run's), the setting, the tables."""
    from imu_array_ros.calibration.bayes import MAX_DRAWS, UNTUNABLE, VAR_REPLICATES

    axes = "xyz"
    md = header + _intro()
    md += summary(results, comps, args)
    md += "## Method\n\n"
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

    md += samples_table(results)
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
    md += swap_table(results) + a_vs_b_table(results)
    return md


def plots(results, names, nominal, free, out_dir: Path, args, traces: bool = True) -> list[str]:
    """The ellipse figure per setting with posteriors (from the means and covariances) and, with ``traces``,
    the trace plot of its posterior with the lowest ESS (needs the chains)."""
    from imu_array_ros.calibration.bayes import PACKAGE_SIZE, PRIOR_STD, ellipse_radius, plot_ellipses, plot_trace

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
