"""``imu-array calibrate static``: accelerometer intrinsics and gyroscope biases from the still poses.

nilsson2014 maximum likelihood or rupniewski's closed-form PCA
(``workflows.calibrate("static", ...)``); :func:`calibrate_stages` is shared with
``calibrate all`` (:mod:`.whole_array`), which adds the moving stage.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from imu_array_ros import workflows
from imu_array_ros.calibration.result import check_install_target
from imu_array_ros.calibration.plots import plot_static
from imu_array_ros.calibration.report import check_report_dir, write_calibration_report
from imu_array_ros.cli.calibrate.common import about, add_calibration_inputs, add_still_options, check_outputs, \
    install, still_options
from imu_array_ros.cli.options import add_force_quiet, parse_list, read_array_recording
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import OutputError
from imu_array_ros.util.extras import require

__all__ = ["add_parser", "run", "calibrate_stages", "print_static_table"]


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("static", help="accelerometer gain, bias, non-orthogonality and misalignment, and "
                                              "gyroscope biases, from the still poses of a recording (nilsson2014 "
                                              "ML / rupniewski PCA)")
    add_calibration_inputs(sp)
    sp.add_argument("--method", choices=("ml", "pca"), default="ml",
                    help="'ml': maximum likelihood, robust (default); 'pca': closed form (rupniewski)")
    sp.add_argument("--reference", help="IMU whose accelerometer axes define the array frame (default: the first)")
    sp.add_argument("--terms", help="comma-separated subset of accelerometer_gain, accelerometer_nonorthogonality, "
                                    "accelerometer_misalignment, accelerometer_bias, gyroscope_bias (default: all)")
    add_still_options(sp)
    sp.add_argument("--out", required=True, type=Path,
                    help="calibrated description YAML to write (with --force an existing one is replaced only if "
                         "the new calibration fits the poses better; the old one is kept as OUT.bak)")
    sp.add_argument("--plot", type=Path, metavar="PNG",
                    help="also write a plot: poses on the sphere, parameters with 3-sigma bars, residuals")
    add_force_quiet(sp, force="replace an existing --out (a YAML mapping), keeping it as OUT.bak, unless it fits the "
                              "poses better than the new calibration; and an existing --plot PNG")
    sp.set_defaults(handler=run)
    return sp


def print_static_table(result, quiet: bool) -> None:
    """Per IMU of an ArrayCalibration's static stage: gain, bias, non-orthogonality, misalignment with their
    std, residual RMS (nothing without a static stage)."""
    st = result.static
    if st is None:
        return
    m, std = st.model.terms, st.written_std()
    nan3 = np.full(3, np.nan)

    def cell(term, k, scale, fmt):
        if term not in st.terms:
            return "held".rjust(10)
        v = m[term].values[k] * scale
        s = std[term][k] * scale if term in std else nan3
        return " ".join(f"{a:{fmt}}" for a in v) + " +-" + f"{np.nanmax(s) if np.isfinite(s).any() else 0:.1g}"

    info(quiet, "  IMU      gain [-]                    bias [m/s^2]              non-orth [deg]         "
                "misalignment [deg]     residual RMS")
    for k, name in enumerate(st.names):
        if name in st.skipped:
            info(quiet, f"  {name}: skipped (no data)")
            continue
        info(quiet, f"  {name}  {cell('accelerometer_gain', k, 1.0, '.4f')}  {cell('accelerometer_bias', k, 1.0, '+.3f')}"
                    f"  {cell('accelerometer_nonorthogonality', k, 180 / np.pi, '+.2f')}"
                    f"  {cell('accelerometer_misalignment', k, 180 / np.pi, '+.2f')}  {st.residual_rms[k]:.3g} m/s^2"
                    f"{'  (reference)' if name == st.reference else ''}")


def calibrate_stages(kind: str, recording: Path, *, array: Path, out: Path, calibration: Path | None,
                     plot: Path | None, force: bool, quiet: bool, reference: str | None,
                     report: Path | None = None, **options) -> int:
    """``calibrate static`` (``kind`` "static") and ``calibrate all`` ("all"): outputs checked, the
    recording read, the stages run (progress lines), the static table, the install, the static plot, the
    report (``report``: a directory, :mod:`imu_array_ros.calibration.report`)."""
    recordings = list(recording) if isinstance(recording, (list, tuple)) else [recording]
    out, plot = check_outputs(out, plot, [*recordings, array, calibration], force)
    if report is not None:
        report = check_report_dir(report, [*recordings, array, calibration], force,
                                  other_outputs=[("--out", out), ("--plot", plot)])
        require("matplotlib", "plots", f"--report {report}")
    read = [read_array_recording(r, array, calibration, quiet, imus=[reference]) for r in recordings]
    desc, samples = read[0][0], [s for _, s in read]
    check_install_target(out, desc.names)  # refused before the work, not after
    name = recordings[0] if len(recordings) == 1 else Path(", ".join(map(str, recordings)))
    with about(name):
        cal = workflows.calibrate(kind, samples[0] if len(samples) == 1 else samples, desc, reference=reference,
                                  progress=lambda text: info(quiet, text),
                                  source=str(recordings[0]) if len(recordings) == 1 else [str(r) for r in recordings],
                                  **options)
    per_recording = cal.details.recordings if len(recordings) > 1 else [cal]
    for r, c in zip(recordings, per_recording):
        if len(recordings) > 1:
            info(quiet, f"{r}: {c.summary()}")
        print_static_table(c.details, quiet)
    install(cal, desc, out, name, quiet)
    first = per_recording[0].details
    if plot is not None and first.static is not None:
        plot_static(first, plot)  # with several recordings: the first one's static stage
        info(quiet, f"wrote {plot}")
    if report is not None:
        try:  # with several recordings: the first in full, all of them in the repeatability section
            write_calibration_report(report, per_recording, start=desc, sources=[str(r) for r in recordings])
        except OSError as err:
            raise OutputError(f"{report}: cannot write the report: {err.strerror or err}") from None
        info(quiet, f"wrote the report {report / 'index.md'}")
    return 0


def run(recording: Path, *, array: Path, out: Path, calibration: Path | None = None, method: str = "ml",
        reference: str | None = None, terms: str | None = None, gravity: float | None = None,
        still_gyro: float | None = None, still_accel: float | None = None, still_min_duration: float | None = None,
        plot: Path | None = None, force: bool = False, quiet: bool = False) -> int:
    """Static multi-pose calibration (nilsson2014 ML or rupniewski PCA) from the still poses of ``recording``."""
    options = still_options(gravity, still_gyro, still_accel, still_min_duration)
    if parse_list(terms):
        options["terms"] = parse_list(terms)
    return calibrate_stages("static", recording, array=array, out=out, calibration=calibration, plot=plot,
                            force=force, quiet=quiet, reference=reference, method=method, **options)
