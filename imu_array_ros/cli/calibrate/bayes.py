"""``imu-array calibrate bayes``: the posterior of the accelerometer positions (carlsson2021 PmMH).

``workflows.calibrate("bayes", ...)`` with the sampler's settings; writes the
posterior mean and std (and the covariance per IMU in the record), and with
``--report DIR`` the report of :func:`imu_array_ros.calibration.bayes.write_report`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from imu_array_ros import workflows
from imu_array_ros.calibration import bayes
from imu_array_ros.calibration.result import check_install_target
from imu_array_ros.cli.calibrate.common import about, add_calibration_inputs, install
from imu_array_ros.cli.options import add_force_quiet, as_flags, non_negative_float, non_negative_int, positive_float, \
    positive_int, read_array_recording
from imu_array_ros.cli.progress import info
from imu_array_ros.io.outputs import check_output, check_report_directory, write_report_manifest
from imu_array_ros.model.reference import reference_index
from imu_array_ros.util.extras import require

__all__ = ["add_parser", "run", "FLAGS"]

#: the sampler's and the problem's parameter names, as this command's flags (for their errors)
FLAGS = {"chains": "--chains", "scheduler": "--scheduler", "workers": "--workers", "n_draws": "--draws",
         "rho": "--rho", "proposal": "--proposal", "ess": "--ess", "max_iterations": "--max-iterations",
         "accel_std": "--accel-std", "prior_std": "--prior-std", "min_excitation": "--min-excitation"}


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("bayes", help="posterior of the accelerometer positions (carlsson2021 "
                                             "pseudo-marginal MCMC): mean, std and covariance per IMU, with "
                                             "convergence diagnostics")
    add_calibration_inputs(sp)
    sp.add_argument("--out", required=True, type=Path,
                    help="calibrated description YAML to write: position = posterior mean, position_std, and the "
                         "covariance per IMU in the calibration: block (with --force an existing one is replaced, "
                         "kept as OUT.bak, unless it fits the samples better than the posterior allows)")
    sp.add_argument("--samples", type=positive_int, default=50, metavar="T",
                    help="time samples used, spread evenly over the samples with rotation (default 50; the paper "
                         "uses 5, 50 and 500)")
    sp.add_argument("--chains", type=positive_int, default=4, help="Markov chains, >= 2 (default 4)")
    sp.add_argument("--scheduler", metavar="ADDR",
                    help="run the chains on Dask: 'local' for a new LocalCluster, or a scheduler address "
                         "(tcp://host:8786); default: worker processes on this machine ('serial': this process)")
    sp.add_argument("--workers", type=positive_int, help="worker processes (default: one per core, at most --chains)")
    sp.add_argument("--report", type=Path, metavar="DIR",
                    help="write credible-ellipse, trace and autocorrelation plots, the diagnostics table "
                         "(diagnostics.md/.json) and the draws (posterior.nc) into DIR")
    sp.add_argument("--reference", help="IMU whose position is held (default: the first)")
    sp.add_argument("--prior", choices=("gaussian", "uniform"), default="gaussian",
                    help="prior on each position around --array's: gaussian with --prior-std (default) or "
                         "uniform over the 4 x 4 x 1 mm package")
    sp.add_argument("--prior-std", type=positive_float, metavar="M", help="gaussian prior std, m (default 0.003)")
    sp.add_argument("--accel-std", type=positive_float, metavar="M/S2",
                    help="accelerometer noise std to assume instead of the description's (carlsson2021 uses "
                         "0.79 m/s^2 on real data to cover non-linearity)")
    sp.add_argument("--omega-covariance", choices=("model", "sample"), default="model",
                    help="p(omega | gyroscopes): 'model' noise (eq. 26b, default) or the gyroscopes' sample "
                         "covariance at each sample (eq. 30)")
    sp.add_argument("--draws", type=positive_int, metavar="N",
                    help="omega draws per time sample (default: tuned so Var[log-likelihood estimate] <= 0.1; an error "
                         "when 1024 cannot bring it below 1, which means the readings disagree with the noise "
                         "model; give N to sample anyway)")
    sp.add_argument("--rho", type=non_negative_float, default=0.9,
                    help="correlation of the random numbers between iterations, in [0, 1) (0: plain PmMH; "
                         "default 0.9)")
    sp.add_argument("--proposal", choices=("laplace", "isotropic"), default="laplace",
                    help="'laplace': random walk shaped by the Laplace covariance mixed with independence "
                         "proposals (default); 'isotropic': the paper's sigma_q I random walk (eq. 27)")
    sp.add_argument("--ess", type=positive_float, default=400.0,
                    help="sample until the smallest bulk effective sample size reaches this (default 400)")
    sp.add_argument("--max-iterations", type=positive_int, default=400000,
                    help="cap on the sampling iterations per chain (default 400000)")
    sp.add_argument("--min-excitation", type=non_negative_float,
                    help="samples with ||[w]x^2 + [w_dot]x|| below this (rad/s^2) are not used (default 1)")
    sp.add_argument("--seed", type=non_negative_int, default=0, help="seed of the chains (default 0)")
    add_force_quiet(sp, force="replace an existing --out (a YAML mapping; kept as OUT.bak) and an existing report")
    sp.set_defaults(handler=run)
    return sp


#: the kind of report --report writes (its manifest.json), and the files of a report from before manifests
REPORT_KIND = "imu_array_ros bayes report"
LEGACY_FILES = (*bayes.BAYES_REPORT_TEXT, bayes.BAYES_REPORT_NETCDF, *bayes.BAYES_REPORT_PNGS)


def run(recording: Path, *, array: Path, out: Path, calibration: Path | None = None, samples: int = 50,
        chains: int = 4, scheduler: str | None = None, workers: int | None = None, report: Path | None = None,
        reference: str | None = None, prior: str = "gaussian", prior_std: float | None = None,
        accel_std: float | None = None, omega_covariance: str = "model", draws: int | None = None,
        rho: float = 0.9, proposal: str = "laplace", ess: float = 400.0, max_iterations: int = 400000,
        min_excitation: float | None = None, seed: int = 0, force: bool = False, quiet: bool = False) -> int:
    """Posterior of the accelerometer positions (carlsson2021 PmMH) from ``samples`` samples of ``recording``."""
    inputs = [recording, array, calibration]
    out = check_output(out, inputs, "yaml", force)
    if report is not None:  # the rule of every report directory (docs/cli.md): before any work
        report = check_report_directory(report, inputs, force, kind=REPORT_KIND, other_outputs=[("--out", out)],
                                        legacy=LEGACY_FILES)
    # the [bayes] extra (and [plots] for the report) before any work, not after minutes of sampling
    if scheduler not in (None, "serial"):
        require("distributed", "bayes", f"--scheduler {scheduler}")
    require("arviz", "bayes", "calibrate bayes")
    if report is not None:
        require("matplotlib", "plots", f"--report {report}")
    settings = bayes.SamplerSettings(chains=chains, scheduler=scheduler, workers=workers, n_draws=draws, rho=rho,
                                     proposal=proposal, ess=ess, max_iterations=max_iterations, seed=seed)
    with as_flags(FLAGS):
        settings.check()
    desc, data = read_array_recording(recording, array, calibration, quiet, imus=[reference])
    check_install_target(out, desc.names)  # refused before the work, not after
    with about(recording), as_flags(FLAGS):
        cal = workflows.calibrate("bayes", data, desc, n_samples=samples, settings=settings, reference=reference,
                                  prior=prior, prior_std=prior_std, accel_std=accel_std,
                                  omega_covariance=omega_covariance, min_excitation=min_excitation,
                                  progress=lambda text: info(quiet, text), source=str(recording))
    post = cal.details
    info(quiet, post.summary_line())
    if not post.converged:
        info(quiet, f"warning: the chains did not reach ESS {ess:g} with R-hat <= {settings.rhat} within "
                    f"{max_iterations} iterations; raise --max-iterations or check the report")
    mean, std = post.positions_mean(), post.positions_std()
    initial = workflows.as_model(desc).positions
    ref = reference_index(desc.names, reference)
    for k, name in enumerate(desc.names):
        change = np.linalg.norm(mean[k] - initial[k]) * 1e3
        info(quiet, f"  {name}: moved {change:8.4f} mm, posterior std {np.linalg.norm(std[k]) * 1e6:8.2f} um"
                    f"{'  (reference)' if k == ref else ''}")
    install(cal, desc, out, recording, quiet, summary=False)
    if report is not None:
        paths = bayes.write_report(post, report, extra={"recording": str(recording), "out": str(out)})
        paths.append(write_report_manifest(report, REPORT_KIND, [p.name for p in paths]))
        info(quiet, f"wrote {len(paths)} report files in {report}")
    return 0
