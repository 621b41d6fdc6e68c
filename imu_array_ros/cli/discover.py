"""``imu-array discover``: where a recording differs from the model, which physics is missing, and the fit after.

Reads the recording (and ``--sim``, ``--validate`` recordings) with the
description, runs :func:`imu_array_ros.workflows.discover` and writes
``DIR/report.json``, ``DIR/report.md`` and the plots; ``--apply OUT.yaml``
installs the description extended with the findings
(:func:`imu_array_ros.workflows.findings_calibration`, the one install path:
atomic, the previous file kept as ``OUT.yaml.bak``, refused when the file there
fits the recording better), so fusion, the nodes and the calibrations use the
improved model.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros import workflows
from imu_array_ros.calibration.result import check_install_target
from imu_array_ros.cli.options import add_force_quiet, add_recording_inputs, as_flags, non_negative_int, parse_list, \
    positive_float, positive_int
from imu_array_ros.cli.window import add_window_options, time_window
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.discovery.blocks import LADDER_FROM, SEARCH_READINGS
from imu_array_ros.discovery.report import PLOTS, write_report
from imu_array_ros.errors import CalibrationError, OutputError
from imu_array_ros.io.outputs import check_output, check_report_directory, write_report_manifest
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.terms import candidate_names, term_names
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.util.extras import require

__all__ = ["add_parser", "run"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("discover", help="where a recording differs from the model, which physics the model "
                                                "left out (terms found, confirmed on held-out blocks), and the fit "
                                                "after")
    add_recording_inputs(sp, array="array description YAML",
                         calibration="calibrated description (same schema) to start from")
    add_window_options(sp)  # the same window as calibrate geometry's, of the recording and of --sim
    sp.add_argument("--report", required=True, type=Path,
                    help="directory for report.md, report.json and the plots: new or empty (--force: or holding "
                         "only a previous discovery report, which is replaced); never one holding other files or "
                         "an input")
    sp.add_argument("--sim", type=Path,
                    help="your own simulated recording of the same run (same stamps and IMUs): localise "
                         "recording - simulation instead of recording - model prediction")
    sp.add_argument("--apply", type=Path, metavar="OUT.yaml",
                    help="write the description extended with the found terms (not written when nothing is found)")
    sp.add_argument("--validate", type=Path, nargs="+", metavar="REC",
                    help="other recordings of the same array: log-likelihood and NIS with and without the findings")
    others = [t for t in term_names() if t not in candidate_names()]
    sp.add_argument("--terms", help=f"comma-separated candidate terms (default: the {len(candidate_names())} candidate "
                                    f"terms, every registered term but {', '.join(others[:-1])} and {others[-1]}, which the "
                                    "timing stage "
                                    "searches for instead)")
    sp.add_argument("--alpha", type=positive_float, default=0.01,
                    help="family-wise false-finding rate per recording, in (0, 1) (default 0.01)")
    sp.add_argument("--block", type=positive_float, default=0.5, metavar="SECONDS",
                    help="time block of the robust test and the held-out folds, s (default 0.5)")
    sp.add_argument("--max-findings", type=positive_int, default=8, help="cap on the findings (default 8)")
    sp.add_argument("--search-readings", type=non_negative_int, default=SEARCH_READINGS, metavar="N",
                    help=f"a recording of more than {LADDER_FROM} readings (samples x IMUs) is searched first on "
                         f"every k-th time block (k the least within N), then every (k/2)-th, ..., the whole "
                         f"recording, each only when the one before runs out of candidates; 0: always the whole "
                         f"recording (default {SEARCH_READINGS})")
    sp.add_argument("--no-plots", action="store_true", help="no PNG plots (report.md and report.json only)")
    sp.add_argument("--no-empirical", action="store_true", help="do not model the unexplained residual")
    add_force_quiet(sp, force="replace an existing report in --report and an existing --apply YAML (only files of "
                              "those kinds; the YAML kept as OUT.yaml.bak, unless it fits the recording better than "
                              "the description with the findings)")
    sp.set_defaults(handler=run)
    return sp


#: the kind of report ``--report`` holds (its manifest); a directory from before manifests holds only these files
REPORT_KIND = "imu_array_ros discovery report"
LEGACY_FILES = ("report.json", "report.md", *PLOTS)


def _read(path: Path, desc: ArrayDescription, label: str, quiet: bool) -> ImuSamples:
    samples, _ = workflows.read_imu_recording(path, desc, progress=Progress(f"reading {label}", quiet))
    if len(samples.stamps) == 0:
        raise CalibrationError(f"{path}: no array samples")
    return samples


def _nis(value: float) -> str:
    """A NIS ratio for the console; n/a where the recording has no sample of that regime (NaN)."""
    return "n/a (no such samples)" if value != value else f"{value:.4g}"


def run(recording: Path, *, array: Path, report: Path, calibration: Path | None = None, sim: Path | None = None,
        apply: Path | None = None, validate: list[Path] | None = None, terms: str | None = None,
        alpha: float = 0.01, block: float = 0.5, max_findings: int = 8, search_readings: int = SEARCH_READINGS,
        no_plots: bool = False,
        no_empirical: bool = False, force: bool = False, quiet: bool = False, start: float | None = None,
        duration: float | None = None) -> int:
    """Mismatch discovery on ``recording`` (``start``/``duration``: a window of it and of ``sim``, s) with the
    description ``array`` (``calibration``: its calibrated values)."""
    validate = list(validate or [])
    inputs = [recording, array, calibration, sim, *validate]
    options = workflows.DiscoveryOptions(terms=tuple(parse_list(terms)) if terms else None, alpha=alpha,
                                         block_s=block, max_findings=max_findings, empirical=not no_empirical,
                                         search_readings=search_readings or None)
    try:
        options.candidate_terms()
    except CalibrationError as err:
        raise CalibrationError(f"--terms: {err}") from None
    if not 0 < alpha < 1:
        raise CalibrationError(f"--alpha must be in (0, 1), got {alpha}")
    report = check_report_directory(report, inputs, force, kind=REPORT_KIND, legacy=LEGACY_FILES)
    if not no_plots:
        require("matplotlib", "plots", "the report's plots", instead="pass --no-plots")
    if apply is not None:
        apply = check_output(apply, inputs, "yaml", force, option="--apply",
                             other_outputs=[("--report", report)])  # not the report directory, nor inside it
    desc, _ = workflows.load_array(array, calibration)
    if apply is not None:
        check_install_target(apply, desc.names)  # refused before the work, not after

    samples = _read(recording, desc, str(recording), quiet)
    info(quiet, f"read {len(samples.stamps)} array samples of {len(desc.imus)} IMUs from {recording}")
    samples = time_window(samples, recording, start, duration, quiet)
    sim_samples = _read(sim, desc, f"--sim {sim}", quiet) if sim is not None else None
    if sim_samples is not None:
        sim_samples = time_window(sim_samples, sim, start, duration, True)
    windowed = start is not None or duration is not None
    source = str(recording) if not windowed else (
        f"{recording}, {start or 0:g} s" + (f" to {(start or 0) + duration:g} s" if duration else " to the end"))
    others = [(str(p), _read(p, desc, f"--validate {p}", quiet)) for p in validate]
    with as_flags({"sim": "--sim", "validate": "--validate"}):
        d = workflows.discover(samples, desc, options=options, sim=sim_samples, validate=others,
                               progress=lambda text: info(quiet, f"discover: {text}"))
    info(quiet, f"baseline: log-likelihood {d.baseline.loglik:.8g}, NIS still {_nis(d.baseline.nis_still)}, "
                f"moving {_nis(d.baseline.nis_moving)}")
    for f in d.findings:
        info(quiet, f"found {f.effect} on {f.sensor}: log-likelihood +{f.exact_delta_loglik:.4g}, "
                    f"held-out +{f.candidate.heldout:.4g}")
    for e in d.indistinguishable:
        info(quiet, f"indistinguishable: {' / '.join(e['effects'])} on {', '.join(e['sensors'])}")
    for u in d.unexplained:
        info(quiet, f"unexplained: {', '.join(u['sensors'][:4])}{' ...' if len(u['sensors']) > 4 else ''} "
                    f"{', '.join(u['axes'])}, {u['band_hz'][0]:.3g}-{u['band_hz'][1]:.3g} Hz, "
                    f"{u['share_of_residual']:.0%} of the excess")
    info(quiet, f"after: log-likelihood {d.after.loglik:.8g}, NIS still {_nis(d.after.nis_still)}, "
                f"moving {_nis(d.after.nis_moving)}")
    try:
        written = write_report(d, report, plots=not no_plots, source=source)
        written.append(write_report_manifest(report, REPORT_KIND, [p.name for p in written]))
    except OSError as err:
        raise OutputError(f"{report}: cannot write the report: {err.strerror or err}") from None
    info(quiet, f"wrote {', '.join(str(p) for p in written)}")
    if apply is not None:
        # after the report: a refused install (the file there fits the recording better) loses no work
        if not d.findings and not (d.timing is not None and d.timing.used):
            info(quiet, f"no findings: {apply} not written (the description already explains the recording)")
        else:
            info(quiet, f"--apply: checking the findings' calibration against the recording before writing "
                        f"{apply} (its log-likelihood on the whole {'window' if windowed else 'recording'})")
            try:
                from imu_array_ros.discovery.apply import install_findings

                cal = workflows.findings_calibration(d, samples, source=source, start=workflows.as_model(desc))
                installed = install_findings(cal, desc, apply)  # one BLAS thread; scored only against a file
            except CalibrationError as err:
                raise CalibrationError(f"{err} (the report is in {report})") from None
            if installed.backup is not None:
                info(quiet, f"previous {apply} kept as {installed.backup}")
            info(quiet, f"wrote {apply}")
    return 0
