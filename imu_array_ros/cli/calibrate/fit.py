"""``imu-array calibrate fit``: maximum likelihood of any sensor-model terms jointly with the motion.

The fitting engine (:func:`imu_array_ros.fitting.fit_terms`, through
``workflows.calibrate("fit", ...)``), written as the description schema with
every fitted field, its ``_std`` (the Cramér-Rao bound of the joint problem)
and a ``calibration:`` block.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from imu_array_ros import workflows
from imu_array_ros.calibration.result import check_install_target
from imu_array_ros.cli.calibrate.common import add_calibration_inputs, check_outputs, install
from imu_array_ros.cli.options import add_force_quiet, parse_list, positive_int, read_array_recording
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting import check_terms
from imu_array_ros.model.terms import REGISTRY

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("fit", help="maximum likelihood of any sensor-model terms jointly with the motion")
    add_calibration_inputs(sp)
    sp.add_argument("--terms", required=True,
                    help="comma-separated registry names of the terms to fit, e.g. position,gyroscope_gain,time_offset")
    sp.add_argument("--imus", help="comma-separated IMU names whose parameters are fitted (default: all)")
    sp.add_argument("--reference",
                    help="IMU whose parameters fix the gauge freedoms (default: the first fitted IMU)")
    sp.add_argument("--max-iterations", type=positive_int, default=50, help="iteration cap, >= 1 (default 50)")
    sp.add_argument("--out", required=True, type=Path, help="calibrated description YAML to write")
    add_force_quiet(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, unless it fits "
                              "the recording better than the new calibration")
    sp.set_defaults(handler=run)
    return sp


def _print_fit(fit, initial, quiet: bool) -> None:
    """The engine's result: gauge, samples and iterations, likelihood, and per term its change and std."""
    for line in fit.gauge:
        info(quiet, f"gauge: {line}")
    info(quiet, f"fitted {len(fit.theta)} parameters on {fit.samples_used} samples"
                f" ({fit.samples_dropped} without motion information dropped) in {fit.iterations} iterations"
                f"{'' if fit.converged else ' (NOT converged: raise --max-iterations or check the data)'}")
    info(quiet, f"log-likelihood {fit.loglik_before:.6g} -> {fit.loglik_after:.6g}; "
                f"NIS per degree of freedom {fit.nis_before:.4g} -> {fit.nis_after:.4g}")
    for name in fit.free:
        change = fit.model.terms[name].values - initial.terms[name].values
        std = fit.std[name]
        info(quiet, f"  {name}: RMS change {np.sqrt(np.mean(change ** 2)):.3g}, "
                    f"median std {np.nanmedian(std) if np.isfinite(std).any() else float('nan'):.3g} "
                    f"({REGISTRY[name].fields[0].unit})")


def run(recording: Path, *, array: Path, terms: str, out: Path, calibration: Path | None = None,
        imus: str | None = None, reference: str | None = None, max_iterations: int = 50, force: bool = False,
        quiet: bool = False) -> int:
    """Fit the sensor-model ``terms`` (comma-separated registry names) to ``recording``; install at ``out``."""
    try:  # before reading anything
        free = check_terms(parse_list(terms))
    except CalibrationError as err:
        raise CalibrationError(f"--terms: {err}") from None
    out, _ = check_outputs(out, None, [recording, array, calibration], force)
    imu_list = parse_list(imus)
    desc, samples = read_array_recording(recording, array, calibration, quiet,
                                         imus=[*(imu_list or []), reference])
    check_install_target(out, desc.names)  # refused before the work, not after

    def progress(iteration: int, cost: float) -> None:
        info(quiet, f"fitting: iteration {iteration}, cost {cost:.6g}")

    cal = workflows.calibrate("fit", samples, desc, terms=free, imus=imu_list, reference=reference,
                              max_iterations=max_iterations, progress=progress, source=str(recording))
    _print_fit(cal.details, workflows.as_model(desc), quiet)
    install(cal, desc, out, recording, quiet, summary=False)
    return 0
