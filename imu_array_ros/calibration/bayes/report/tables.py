"""The report's tables: one row per coordinate (MCMC vs Laplace vs ML), the disagreements, the markdown."""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np

__all__ = ["diagnostics_table", "disagreements", "disagreement_line", "report_markdown", "lowest_ess_coords",
           "coord_index", "summary_values", "COORD_LABEL", "Z_LIMIT", "SD_RATIO_RANGE", "AXES", "UM", "MM"]

#: |z| (MCMC vs Laplace mean, in MCMC sds) above which :func:`disagreements` names a coordinate
Z_LIMIT = 2.0
#: Laplace / MCMC sd ratios outside this range are named by :func:`disagreements`
SD_RATIO_RANGE = (0.8, 1.25)
AXES = ("x", "y", "z")
UM = 1e6  # metres -> micrometres
MM = 1e3  # metres -> millimetres
#: ArviZ's label of a coordinate in the summary: position[imu, axis]
COORD_LABEL = re.compile(r"^position\[(?P<imu>.+), (?P<axis>[xyz])\]$")


# --------------------------------------------------------------------------- coordinates


def coord_index(post) -> dict[tuple[str, str], int]:
    """(imu, axis) -> column of post.draws."""
    return {(name, a): 3 * j + i for j, name in enumerate(post.free_names) for i, a in enumerate(AXES)}


def lowest_ess_coords(post, n: int = 6) -> list[tuple[str, str]]:
    """The ``n`` free coordinates (imu, axis) with the lowest bulk ESS (post.summary), lowest first."""
    index = coord_index(post)
    ess = summary_values(post, "ess_bulk")
    if not ess:  # no (or an unexpected) summary: the coordinates in order
        return list(index)[:n]
    # NaN (ArviZ could not compute it) counts as lowest; ties in the draws' order
    key = [(v if np.isfinite(v) else -1.0, index[c], c) for c, v in ess.items() if c in index]
    return [c for _, _, c in sorted(key)[:n]]


def summary_values(post, column: str) -> dict[tuple[str, str], float]:
    """(imu, axis) -> the value of ``column`` (e.g. "ess_bulk") in post.summary ({} without a summary)."""
    out = {}
    if post.summary is None or column not in post.summary:
        return out
    for label, value in post.summary[column].items():
        m = COORD_LABEL.match(str(label))
        if m:
            out[m["imu"], m["axis"]] = float(value)
    return out


# --------------------------------------------------------------------------- the table


def diagnostics_table(post) -> list[dict]:
    """One row per free coordinate (the order of ``post.draws``' columns).

    imu, axis; nominal_mm; mean_um, sd_um (MCMC, mean relative to nominal); hdi_low_um, hdi_high_um
    (ArviZ's highest density interval, 94 % by default: hdi_3%/hdi_97%, relative to nominal);
    mcse_mean_um, mcse_sd_um, ess_bulk, ess_tail, r_hat (ArviZ summary); laplace_mean_um,
    laplace_sd_um (the Gaussian approximation, relative to nominal); ml_um, crb_sd_um (the ML estimate
    and its Cramér-Rao std it is built from); z = (mean - laplace_mean) / sd; sd_ratio =
    laplace_sd / sd.  Values are floats (NaN where ArviZ gave none).
    """
    s = post.summary
    hdi = sorted([c for c in s.columns if str(c).startswith("hdi_")],
                 key=lambda c: float(str(c)[4:].rstrip("%"))) if s is not None else []
    lap = post.laplace
    lap_sd = np.sqrt(np.clip(np.diag(lap.covariance), 0.0, None))
    crb_sd = np.sqrt(np.clip(np.diag(lap.crb), 0.0, None))
    nominal = post.problem.theta_of(post.problem.positions)
    mean, sd = post.mean, post.flat.std(axis=0, ddof=1)
    rows = []
    for (imu, axis), j in coord_index(post).items():
        label = f"position[{imu}, {axis}]"
        stat = s.loc[label] if s is not None and label in s.index else None

        def col(name, scale=1.0, shift=0.0):
            if stat is None or name not in stat:
                return float("nan")
            return (float(stat[name]) - shift) * scale

        row = {
            "imu": imu, "axis": axis, "nominal_mm": float(nominal[j] * MM),
            "mean_um": float((mean[j] - nominal[j]) * UM), "sd_um": float(sd[j] * UM),
            "hdi_label": f"{hdi[0]}..{hdi[-1]}" if len(hdi) >= 2 else None,
            "hdi_low_um": col(hdi[0], UM, nominal[j]) if len(hdi) >= 2 else float("nan"),
            "hdi_high_um": col(hdi[-1], UM, nominal[j]) if len(hdi) >= 2 else float("nan"),
            "mcse_mean_um": col("mcse_mean", UM), "mcse_sd_um": col("mcse_sd", UM),
            "ess_bulk": col("ess_bulk"), "ess_tail": col("ess_tail"), "r_hat": col("r_hat"),
            "laplace_mean_um": float((lap.mean[j] - nominal[j]) * UM), "laplace_sd_um": float(lap_sd[j] * UM),
            "ml_um": float((lap.ml[j] - nominal[j]) * UM), "crb_sd_um": float(crb_sd[j] * UM),
        }
        row["z"] = (row["mean_um"] - row["laplace_mean_um"]) / row["sd_um"] if row["sd_um"] > 0 else float("nan")
        row["sd_ratio"] = row["laplace_sd_um"] / row["sd_um"] if row["sd_um"] > 0 else float("nan")
        rows.append(row)
    return rows


def disagreements(rows: Sequence[dict], z_limit: float = Z_LIMIT, sd_range=SD_RATIO_RANGE) -> list[dict]:
    """The rows (of :func:`diagnostics_table`) where MCMC and Laplace disagree: |z| > z_limit or the sd
    ratio outside sd_range (a NaN counts as a disagreement); each {imu, axis, z, sd_ratio, why}."""
    out = []
    for r in rows:
        why = []
        if not np.isfinite(r["z"]) or abs(r["z"]) > z_limit:
            why.append(f"z = {r['z']:+.2f}")
        if not np.isfinite(r["sd_ratio"]) or not sd_range[0] <= r["sd_ratio"] <= sd_range[1]:
            why.append(f"sd ratio {r['sd_ratio']:.2f}")
        if why:
            out.append({"imu": r["imu"], "axis": r["axis"], "z": r["z"], "sd_ratio": r["sd_ratio"],
                        "why": ", ".join(why)})
    return out


def disagreement_line(dis: list[dict]) -> str:
    """The markdown line naming the disagreements (:func:`disagreements`), or saying there are none."""
    crit = (f"|z| > {Z_LIMIT:g} or Laplace/MCMC sd ratio outside "
            f"[{SD_RATIO_RANGE[0]:g}, {SD_RATIO_RANGE[1]:g}]")
    if not dis:
        return f"**MCMC vs Laplace:** agree everywhere (no coordinate with {crit})."
    return (f"**MCMC vs Laplace:** disagree at {len(dis)} coordinate(s) ({crit}): "
            + "; ".join(f"{d['imu']} {d['axis']} ({d['why']})" for d in dis) + ".")


def _fmt(v, spec: str) -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, spec)


def report_markdown(post, rows, dis, nc_note: str | None, truth_rows: list | None) -> str:
    """diagnostics.md: the run, the N-tuning table and one table row per coordinate (``rows`` of
    :func:`diagnostics_table`, with truth_um and z_truth when ``truth_rows``); ``dis``: the
    :func:`disagreements`; ``nc_note``: why posterior.nc was not written (None: it was)."""
    p = post.problem
    c, m, _ = post.draws.shape
    lines = ["# Bayesian position calibration: diagnostics", "",
             f"{post.summary_line()}", "",
             f"* IMUs: {len(p.names)}, reference {p.names[p.reference]} (held); {p.n_samples} samples; "
             f"prior {p.prior.kind}; rho {p.rho:g}; omega covariance {p.omega_covariance}; proposal "
             f"{post.settings.proposal}; runner {post.runner}",
             f"* chains {c}, draws per chain {m}, warm-up per chain {post.warmup}, N = {post.n_draws}",
             f"* random-walk acceptance per chain: {', '.join(_fmt(a, '.1%') for a in post.acceptance)}; "
             f"independence: {', '.join(_fmt(a, '.1%') for a in post.acceptance_independence)}",
             f"* ESS bulk >= {post.ess_bulk_min:.0f}, ESS tail >= {post.ess_tail_min:.0f}, "
             f"R-hat <= {post.rhat_max:.4f} (targets: ESS {post.settings.ess:g}, R-hat {post.settings.rhat:g}) "
             f"-> {'converged' if post.converged else '**NOT converged**'}",
             f"* {post.seconds:.1f} s wall, {post.cpu_seconds:.1f} CPU s", "",
             disagreement_line(dis), ""]
    if nc_note:
        lines += [f"**posterior.nc not written:** {nc_note}", ""]
    lines += ["## Draws per time sample (N)", ""]
    if post.var_loglik:
        lines += ["| N | Var[log-likelihood estimate] |", "|---:|---:|"]
        lines += [f"| {n} | {v:.4g} |" for n, v in post.var_loglik]
        lines += ["", f"Target variance {post.settings.loglik_var:g}; chosen N = {post.n_draws}.", ""]
    else:
        lines += [f"N = {post.n_draws} was given (not tuned).", ""]
    hdi = rows[0]["hdi_label"] if rows and rows[0]["hdi_label"] else "hdi"
    lines += ["## Per coordinate", "",
              "Micrometres relative to the nominal position; z = (MCMC mean - Laplace mean) / MCMC sd; "
              "sd ratio = Laplace sd / MCMC sd.", "",
              f"| IMU | axis | mean | sd | {hdi} | MCSE mean | ESS bulk | ESS tail | R-hat | Laplace mean | "
              "Laplace sd | z | sd ratio |" + (" truth | (mean-truth)/sd |" if truth_rows else ""),
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|" + ("---:|---:|" if truth_rows else "")]
    for i, r in enumerate(rows):
        line = (f"| {r['imu']} | {r['axis']} | {_fmt(r['mean_um'], '.2f')} | {_fmt(r['sd_um'], '.2f')} | "
                f"{_fmt(r['hdi_low_um'], '.1f')} .. {_fmt(r['hdi_high_um'], '.1f')} | "
                f"{_fmt(r['mcse_mean_um'], '.2f')} | "
                f"{_fmt(r['ess_bulk'], '.0f')} | {_fmt(r['ess_tail'], '.0f')} | {_fmt(r['r_hat'], '.4f')} | "
                f"{_fmt(r['laplace_mean_um'], '.2f')} | {_fmt(r['laplace_sd_um'], '.2f')} | {_fmt(r['z'], '+.2f')} | "
                f"{_fmt(r['sd_ratio'], '.2f')} |")
        if truth_rows:
            line += f" {_fmt(r['truth_um'], '.2f')} | {_fmt(r['z_truth'], '+.2f')} |"
        lines.append(line)
    lines += ["", "Files: diagnostics.json (the same, machine-readable), ellipses.png (posterior vs Laplace vs "
              "prior, x-y), trace.png, autocorr.png, posterior.nc (the chains, ArviZ netCDF).", ""]
    return "\n".join(lines)
