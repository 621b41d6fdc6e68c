"""Writing the report of a Bayesian position calibration into a directory.

:func:`write_report` writes into one directory:

``diagnostics.json``
    Strict JSON: the sampler settings, the run (chains, draws, warm-up, N and
    the Var[log-likelihood] table it was tuned on, acceptances, ESS, R-hat,
    wall and CPU time, convergence), and the rows of
    :func:`~imu_array_ros.calibration.bayes.report.tables.diagnostics_table`, one per free coordinate.
``diagnostics.md``
    The same for a human: a summary, the N-tuning table, the table of rows,
    and one line naming where the MCMC posterior and its Laplace (Gaussian /
    Cramér-Rao) approximation disagree: |z| > ``Z_LIMIT`` with z = (MCMC mean -
    Laplace mean) / MCMC sd, or a Laplace / MCMC sd ratio outside
    ``SD_RATIO_RANGE``.
``ellipses.png`` (:func:`~imu_array_ros.calibration.bayes.report.ellipses.plot_ellipses`, after carlsson2021 Fig. 5)
    One panel per IMU, placed as the IMUs sit on the board when their nominal
    positions form a grid (one block per z level, side by side), in mm
    relative to the IMU's nominal position: the x-y 50 % credible ellipses
    and means of the MCMC posterior and of the Laplace approximation, the
    prior's ellipse (cyan), the package outline (dashed) and, when known,
    the true position (black x).  Every panel has the same scale.
``trace.png`` (:func:`~imu_array_ros.calibration.bayes.report.chains.plot_trace`)
    ArviZ trace plot (density per chain and the chains' draws) of the
    coordinates with the lowest bulk ESS, in um relative to nominal, and the
    log posterior; below, the log posterior during the discarded warm-up.
``autocorr.png`` (:func:`~imu_array_ros.calibration.bayes.report.chains.plot_autocorr`)
    Autocorrelation per chain of the same coordinates (slow decay = low ESS).
``posterior.nc``
    The chains as ArviZ InferenceData (netCDF), metres, for later analysis.

Everything is written atomically (a temporary sibling renamed over the target).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Mapping

import numpy as np

from imu_array_ros.calibration.bayes.posterior import imu_covariances
from imu_array_ros.calibration.bayes.problem import PACKAGE_SIZE
from imu_array_ros.calibration.bayes.report.chains import plot_autocorr, plot_trace
from imu_array_ros.calibration.bayes.report.ellipses import plot_ellipses
from imu_array_ros.calibration.bayes.report.tables import SD_RATIO_RANGE, UM, Z_LIMIT, diagnostics_table, \
    disagreements, report_markdown
from imu_array_ros.util.files import atomic_path, atomic_write_text
from imu_array_ros.util.jsontools import json_safe

__all__ = ["write_report", "BAYES_REPORT_TEXT", "BAYES_REPORT_PNGS", "BAYES_REPORT_NETCDF"]

#: the report's text files (always written)
BAYES_REPORT_TEXT = ("diagnostics.json", "diagnostics.md")
#: the report's figures (``plots=True``)
BAYES_REPORT_PNGS = ("ellipses.png", "trace.png", "autocorr.png")
#: the chains (written when a netCDF engine is installed)
BAYES_REPORT_NETCDF = "posterior.nc"


def write_report(post, out_dir: str | Path, *, plots: bool = True, truth=None,
                 extra: Mapping | None = None) -> list[Path]:
    """Write the report of ``post`` into ``out_dir`` (module docstring); returns the paths written.

    truth : (K, 3) true positions (simulations): added to the rows (truth_um, z_truth = (mean - truth) /
    sd) and to the ellipse plot.  extra : merged into diagnostics.json at the top level.  With
    ``plots=False`` no PNG is written.  A posterior.nc that cannot be written (no netCDF engine) is
    skipped and noted in diagnostics.md and diagnostics.json (``netcdf_error``).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = post.problem
    rows = diagnostics_table(post)
    truth_rows = None
    if truth is not None:
        truth = np.asarray(truth, dtype=float)
        if truth.shape != p.positions.shape:
            raise ValueError(f"truth of shape {truth.shape}, expected {p.positions.shape}")
        t = p.theta_of(truth) - p.theta_of(p.positions)
        for r, tj in zip(rows, t):
            r["truth_um"] = float(tj * UM)
            r["z_truth"] = (r["mean_um"] - r["truth_um"]) / r["sd_um"] if r["sd_um"] > 0 else float("nan")
        truth_rows = rows
    dis = disagreements(rows)
    written: list[Path] = []

    nc_note = None
    nc = out / BAYES_REPORT_NETCDF
    try:
        idata = post.inference_data()
        with atomic_path(nc) as tmp:
            idata.to_netcdf(str(tmp))
        written.append(nc)
    except Exception as err:  # no netCDF engine, or one that refuses: the report goes on without it
        nc_note = f"{type(err).__name__}: {err}".splitlines()[0]

    c, m, _ = post.draws.shape
    doc = {
        "summary": post.summary_line(),
        "settings": dataclasses.asdict(post.settings),
        "run": {
            "chains": c, "draws_per_chain": m, "warmup_per_chain": post.warmup, "n_draws": post.n_draws,
            "var_loglik": [{"n_draws": int(n), "variance": float(v)} for n, v in post.var_loglik],
            "acceptance_random_walk": post.acceptance, "acceptance_independence": post.acceptance_independence,
            "ess_bulk_min": post.ess_bulk_min, "ess_tail_min": post.ess_tail_min, "rhat_max": post.rhat_max,
            "converged": bool(post.converged), "seconds": post.seconds, "cpu_seconds": post.cpu_seconds,
            "runner": post.runner,
        },
        "problem": {
            "names": list(p.names), "reference": p.names[p.reference], "free": post.free_names,
            "samples": p.n_samples, "prior": p.prior.kind, "rho": p.rho, "omega_covariance": p.omega_covariance,
        },
        "units": "rows: um relative to the nominal position (nominal_mm: mm)",
        "criteria": {"z_limit": Z_LIMIT, "sd_ratio_range": list(SD_RATIO_RANGE)},
        "disagreements": dis,
        "rows": rows,
    }
    if nc_note:
        doc["netcdf_error"] = nc_note
    doc.update(dict(extra or {}))
    json_path, md_path = (out / name for name in BAYES_REPORT_TEXT)
    path = json_path
    atomic_write_text(path, json.dumps(json_safe(doc), indent=1, allow_nan=False) + "\n")
    written.append(path)
    path = md_path
    atomic_write_text(path, report_markdown(post, rows, dis, nc_note, truth_rows))
    written.append(path)

    if plots:
        pr = p.prior
        k = len(p.names)
        if pr.kind == "gaussian":
            prior_std = np.zeros((k, 3))
            prior_std[p.free] = pr.std.reshape(-1, 3)
            prior_mean = p.positions.copy()
            prior_mean[p.free] = pr.mean.reshape(-1, 3)
            package = PACKAGE_SIZE
            title = ("50 % credible ellipses (x-y): MCMC posterior vs Laplace approximation vs prior, "
                     "mm relative to nominal")
        else:  # the uniform prior is a box: drawn as the package outline
            prior_std = prior_mean = None
            package = tuple(2.0 * pr.std[:3])
            title = ("50 % credible ellipses (x-y): MCMC posterior vs Laplace approximation; the uniform prior "
                     "is the dashed box; mm relative to nominal")
        lap = post.laplace
        estimates = {"posterior (MCMC)": (post.positions_mean(), post.imu_covariances()),
                     "Laplace": (p.full_positions(lap.mean), imu_covariances(p, lap.covariance))}
        ellipses_png, trace_png, autocorr_png = (out / name for name in BAYES_REPORT_PNGS)
        path = ellipses_png
        plot_ellipses(path, p.names, p.positions, estimates, prior_std=prior_std, prior_mean=prior_mean,
                      package=package, truth=truth, reference=p.names[p.reference], title=title)
        written.append(path)
        path = trace_png
        plot_trace(path, post)
        written.append(path)
        path = autocorr_png
        plot_autocorr(path, post)
        written.append(path)
    return written
