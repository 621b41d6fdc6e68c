"""``imu-array discover``: where a recording differs from the model, which physics is missing, and the fit after.

Reads the recording (and ``--sim``, ``--validate`` recordings) with the
description, runs :func:`imu_array_ros.discovery.discover.discover` and writes
``DIR/report.json``, ``DIR/report.md`` and the plots; ``--apply OUT.yaml``
writes the description extended with the findings (atomically), so fusion,
the nodes and the calibrations use the improved model.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imu_array_ros.calibration.output import provenance
from imu_array_ros.cli.calibrate import parse_list, write_calibrated
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.errors import CalibrationError, OutputError
from imu_array_ros.io.outputs import check_output

__all__ = ["discover_command"]


def _report_outputs(report: Path, inputs, force: bool, plots: bool) -> Path:
    """Check every file the report writes into ``report`` (a directory, created if missing)."""
    from imu_array_ros.discovery.report import PLOTS

    if report.exists() and not report.is_dir():
        raise OutputError(f"{report}: --report must be a directory (it is a file)")
    if not report.exists():
        check_output(report, inputs, "json", False, option="--report")  # not an input, not inside one
    check_output(report / "report.json", inputs, "json", force, option="--report")
    md = report / "report.md"
    if md.exists() and not force:
        raise OutputError(f"{md}: exists; pass --force to replace the report in {report}")
    if md.exists() and not (report / "report.json").exists():
        raise OutputError(f"{md}: exists without a report.json beside it; it is not one of our reports, "
                          f"choose another --report")
    if plots:
        for name in PLOTS:
            check_output(report / name, inputs, "png", force, option="--report")
    return report


def discover_command(recording: Path, array: Path, report: Path, *, calibration: Path | None = None,
                     sim: Path | None = None, apply: Path | None = None, validate: list[Path] | None = None,
                     terms: str | None = None, alpha: float = 0.01, block: float = 0.5, max_findings: int = 8,
                     no_plots: bool = False, no_empirical: bool = False, force: bool = False,
                     quiet: bool = False) -> int:
    """Mismatch discovery on ``recording`` with the description ``array`` (``calibration``: its calibrated values)."""
    from imu_array_ros.cli.commands import load_array
    from imu_array_ros.discovery.discover import DiscoveryOptions, discover
    from imu_array_ros.discovery.report import write_report
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.sensor_model import SensorModel

    validate = list(validate or [])
    inputs = [recording, array, calibration, sim, *validate]
    options = DiscoveryOptions(terms=tuple(parse_list(terms)) if terms else None, alpha=alpha, block_s=block,
                               max_findings=max_findings, empirical=not no_empirical)
    try:
        options.candidate_terms()
    except CalibrationError as err:
        raise CalibrationError(f"--terms: {err}") from None
    if not 0 < alpha < 1:
        raise CalibrationError(f"--alpha must be in (0, 1), got {alpha}")
    _report_outputs(Path(report), inputs, force, not no_plots)
    if apply is not None:
        apply = check_output(apply, inputs, "yaml", force, option="--apply",
                             other_outputs=[("--report", Path(report) / "report.json")])
    desc, source = load_array(array, calibration)
    model = SensorModel.from_description(desc)

    def read(path: Path, label: str):
        samples, stats = read_imu_recording(path, desc, progress=Progress(f"reading {label}", quiet))
        if len(samples.stamps) == 0:
            raise CalibrationError(f"{path}: no array samples")
        return samples

    samples = read(recording, str(recording))
    info(quiet, f"read {len(samples.stamps)} array samples of {len(desc.imus)} IMUs from {recording}")
    sim_samples = read(sim, f"--sim {sim}") if sim is not None else None
    others = [(str(p), read(p, f"--validate {p}")) for p in validate]
    d = discover(samples, model, options=options, sim=sim_samples, validate=others,
                 progress=lambda text: info(quiet, f"discover: {text}"))
    info(quiet, f"baseline: log-likelihood {d.baseline.loglik:.8g}, NIS still {d.baseline.nis_still:.4g}, "
                f"moving {d.baseline.nis_moving:.4g}")
    for f in d.findings:
        info(quiet, f"found {f.effect} on {f.sensor}: log-likelihood +{f.exact_delta_loglik:.4g}, "
                    f"held-out +{f.candidate.heldout:.4g}")
    for e in d.indistinguishable:
        info(quiet, f"indistinguishable: {' / '.join(e['effects'])} on {', '.join(e['sensors'])}")
    for u in d.unexplained:
        info(quiet, f"unexplained: {', '.join(u['sensors'][:4])}{' ...' if len(u['sensors']) > 4 else ''} "
                    f"{', '.join(u['axes'])}, {u['band_hz'][0]:.3g}-{u['band_hz'][1]:.3g} Hz, "
                    f"{u['share_of_residual']:.0%} of the excess")
    info(quiet, f"after: log-likelihood {d.after.loglik:.8g}, NIS still {d.after.nis_still:.4g}, "
                f"moving {d.after.nis_moving:.4g}")
    try:
        written = write_report(d, Path(report), plots=not no_plots, source=str(recording))
    except OSError as err:
        raise OutputError(f"{report}: cannot write the report: {err.strerror or err}") from None
    info(quiet, f"wrote {', '.join(str(p) for p in written)}")
    if apply is not None:
        if not d.findings:
            info(quiet, f"no findings: {apply} not written (the description already explains the recording)")
        else:
            _apply(d, desc, apply, recording)
            info(quiet, f"wrote {apply}")
    return 0


def _apply(d, desc, out: Path, recording: Path) -> None:
    names = sorted({f.effect for f in d.findings})
    stds = {}
    for n in names:
        sd = np.full(d.model.terms[n].values.shape, np.nan)
        for f in d.findings:
            if f.effect == n:
                sd[f.k] = f.std
        stds[n] = sd
    record = {
        "method": "imu-array discover: terms found by mismatch discovery, fitted by the engine (fit_terms); "
                  "*_std = Cramer-Rao bound",
        **provenance(),
        "recording": str(recording),
        "findings": [f"{f.effect} on {f.sensor}" for f in d.findings],
        "log_likelihood_before": float(d.baseline.loglik),
        "log_likelihood_after": float(d.after.loglik),
    }
    write_calibrated(d.model, desc, names, stds, record, out, "--apply")
