"""``imu-array calibrate ...``: calibrations that write a calibrated description.

``calibrate geometry`` is the on-the-fly calibration of the accelerometer
positions (carlsson2017; :mod:`imu_array_ros.calibration.geometry`), the same
function the calibration node's ``/calibrate_geometry`` service runs.

``calibrate fit`` is the general one: maximum likelihood of any set of sensor-model
terms jointly with the motion (:func:`imu_array_ros.fitting.engine.fit_terms`),
written as the description schema with every fitted field, its ``_std`` (the
Cramér-Rao bound of the joint problem) and a ``calibration:`` block.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imu_array_ros.calibration.output import fit_statistics, provenance
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.errors import CalibrationError, OutputError
from imu_array_ros.io.outputs import check_output

__all__ = ["calibrate_bayes", "calibrate_fit", "calibrate_geometry", "calibrate_static", "calibrate_all", "parse_list", "write_calibrated"]


def parse_list(text: str | None) -> list[str] | None:
    """``a,b, c`` -> ['a', 'b', 'c']; None stays None."""
    if text is None:
        return None
    items = [t.strip() for t in text.split(",") if t.strip()]
    return items


def write_calibrated(model, desc, terms, stds: dict, record: dict, out: Path, option: str) -> None:
    """Write ``desc`` with the values of ``terms`` and of every other term of ``model`` not at its identity,
    the ``stds`` (term -> (K, P); NaN entries left out) and the ``calibration:`` ``record``, atomically."""
    from imu_array_ros.model.description import save_description

    names = sorted(set(terms) | {n for n, t in model.terms.items() if not t.is_identity})
    result = model.to_description(desc, names=names, stds=stds)
    try:
        save_description(result.with_imus(result.imus, calibration=record), out)
    except OSError as err:
        raise OutputError(f"{out}: cannot write {option}: {err.strerror or err}") from None


def calibrate_fit(recording: Path, array: Path, terms: str, out: Path, *, calibration: Path | None = None,
                  imus: str | None = None, reference: str | None = None, max_iterations: int = 50,
                  force: bool = False, quiet: bool = False) -> int:
    """Fit the sensor-model ``terms`` (comma-separated registry names) to ``recording``; write ``out``."""
    from imu_array_ros.cli.commands import check_fusable, load_array
    from imu_array_ros.fitting.engine import check_terms, fit_terms
    from imu_array_ros.io.rosbag.recording import read_imu_recording
    from imu_array_ros.model.sensor_model import SensorModel
    from imu_array_ros.model.terms import REGISTRY

    try:  # before reading anything
        free = check_terms(parse_list(terms))
    except CalibrationError as err:
        raise CalibrationError(f"--terms: {err}") from None
    out = check_output(out, [recording, array, calibration], "yaml", force)
    desc, source = load_array(array, calibration)
    check_fusable(desc, source)
    imu_list = parse_list(imus)
    for name in (imu_list or []) + ([reference] if reference else []):
        desc.index(name)  # a one-line error naming the unknown IMU
    samples, rstats = read_imu_recording(recording, desc, progress=Progress("reading", quiet))
    info(quiet, f"read {rstats.samples} array samples of {len(desc.imus)} IMUs")
    model = SensorModel.from_description(desc)

    def progress(iteration: int, cost: float) -> None:
        info(quiet, f"fitting: iteration {iteration}, cost {cost:.6g}")

    fit = fit_terms(samples, model, free, imus=imu_list, reference=reference,
                    max_iterations=max_iterations, progress=progress)
    for line in fit.gauge:
        info(quiet, f"gauge: {line}")
    info(quiet, f"fitted {len(fit.theta)} parameters on {fit.samples_used} samples"
                f" ({fit.samples_dropped} without motion information dropped) in {fit.iterations} iterations"
                f"{'' if fit.converged else ' (NOT converged: raise --max-iterations or check the data)'}")
    info(quiet, f"log-likelihood {fit.loglik_before:.6g} -> {fit.loglik_after:.6g}; "
                f"NIS per degree of freedom {fit.nis_before:.4g} -> {fit.nis_after:.4g}")
    for name in fit.free:
        change = fit.model.terms[name].values - model.terms[name].values
        std = fit.std[name]
        info(quiet, f"  {name}: RMS change {np.sqrt(np.mean(change ** 2)):.3g}, "
                    f"median std {np.nanmedian(std) if np.isfinite(std).any() else float('nan'):.3g} "
                    f"({REGISTRY[name].fields[0].unit})")
    record = {
        "method": "fit_terms: joint maximum likelihood of the terms and the motion (Schur-complement "
                  "Gauss-Newton/Levenberg-Marquardt); *_std = Cramer-Rao bound of the joint problem",
        **provenance(),
        "recording": str(recording),
        "terms": list(fit.free),
        "imus": list(fit.imus),
        "held_for_gauge": list(fit.held),
        "samples_used": int(fit.samples_used),
        "samples_dropped": int(fit.samples_dropped),
        **fit_statistics(fit),
    }
    # held parameters are exact in the chosen gauge: std 0 (the record lists them); IMUs not fitted get no _std
    fitted = np.isin(np.array(desc.names), np.array(fit.imus))
    stds = {n: np.where(fitted[:, None] & ~np.isfinite(fit.std[n]), 0.0, fit.std[n]) for n in fit.free}
    write_calibrated(fit.model, desc, fit.free, stds, record, out, "--out")
    info(quiet, f"wrote {out}")
    return 0


def calibrate_geometry(recording: Path, array: Path, out: Path, *, calibration: Path | None = None,
                       reference: str | None = None, method: str | None = None, max_iterations: int | None = None,
                       min_excitation: float | None = None, start: float | None = None,
                       duration: float | None = None, plot: Path | None = None, force: bool = False,
                       quiet: bool = False) -> int:
    """Calibrate the accelerometer positions on (a window of) ``recording``; install at ``out``."""
    from imu_array_ros.calibration import geometry
    from imu_array_ros.cli.commands import check_fusable, load_array
    from imu_array_ros.io.rosbag.recording import read_imu_recording

    out = check_output(out, [recording, array, calibration], "yaml", force)
    if plot is not None:
        plot = check_output(plot, [recording, array, calibration], "png", force, option="--plot",
                            other_outputs=[("--out", out)])
    desc, source = load_array(array, calibration)
    check_fusable(desc, source)
    if reference:
        desc.index(reference)  # a one-line error naming the unknown IMU
    samples, rstats = read_imu_recording(recording, desc, progress=Progress("reading", quiet))
    info(quiet, f"read {rstats.samples} array samples of {len(desc.imus)} IMUs")
    if len(samples) and (start is not None or duration is not None):
        window = samples.window(start, duration)
        lo, span = start or 0.0, (samples.stamps[-1] - samples.stamps[0]) / 1e9
        if not len(window):
            raise CalibrationError(f"{recording}: no samples between {lo:g} s and "
                                   f"{lo + duration if duration is not None else span:g} s "
                                   f"(the recording spans {span:.3f} s)")
        samples = window
        info(quiet, f"window: {len(samples)} samples from {lo:g} s")

    def progress(iteration: int, loglik: float) -> None:
        info(quiet, f"calibrating: iteration {iteration}, log-likelihood {loglik:.10g}")

    kwargs = dict(reference=reference, method=method or geometry.DEFAULT_METHOD, max_iterations=max_iterations,
                  min_excitation=geometry.MIN_EXCITATION if min_excitation is None else min_excitation,
                  progress=progress)
    try:
        result, installed = geometry.calibrate_and_write(desc, samples, out,
                                                         **kwargs)
    except CalibrationError as err:
        raise CalibrationError(f"{recording}: {err}") from None
    dropped = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in result.dropped.items() if v) or "none"
    info(quiet, f"samples: {result.samples_used} of {result.samples_total} used (dropped: {dropped})")
    info(quiet, f"log-likelihood {result.loglik_before:.10g} -> {result.loglik_after:.10g}; "
                f"NIS per degree of freedom {result.nis_before:.4g} -> {result.nis_after:.4g}")
    change, std = result.position_change(), np.linalg.norm(result.position_std, axis=1)
    for k, name in enumerate(result.names):
        info(quiet, f"  {name}: moved {change[k] * 1e3:8.4f} mm, std {std[k] * 1e6:8.2f} um, "
                    f"residual RMS {result.rms_before[k]:.4g} -> {result.rms_after[k]:.4g} m/s^2"
                    f"{'  (reference)' if name == result.reference else ''}")
    info(quiet, result.summary())
    if installed.backup is not None:
        info(quiet, f"previous {out} kept as {installed.backup}")
    info(quiet, f"wrote {out}")
    if plot is not None:
        from imu_array_ros.calibration.plots import plot_geometry

        plot_geometry(result, plot)
        info(quiet, f"wrote {plot}")
    return 0


def _read_recording(recording: Path, array: Path, calibration: Path | None, quiet: bool):
    from imu_array_ros.cli.commands import check_fusable, load_array
    from imu_array_ros.io.rosbag.recording import read_imu_recording

    desc, source = load_array(array, calibration)
    check_fusable(desc, source)
    samples, rstats = read_imu_recording(recording, desc, progress=Progress("reading", quiet))
    info(quiet, f"read {rstats.samples} array samples of {len(desc.imus)} IMUs")
    return desc, samples


def _still_options(still_gyro: float | None, still_accel: float | None, still_min_duration: float | None) -> dict:
    opts = {"gyro_threshold": still_gyro, "accel_threshold": still_accel, "min_duration_s": still_min_duration}
    return {k: v for k, v in opts.items() if v is not None}


def _static_table(result, quiet: bool) -> None:
    """Per IMU: gain, bias, non-orthogonality, misalignment with their std, residual RMS."""
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


def _calibrate_and_install(recording: Path, array: Path, out: Path, calibration: Path | None, plot: Path | None,
                           force: bool, quiet: bool, **kwargs) -> int:
    from imu_array_ros.calibration.array import array_description, calibrate_array
    from imu_array_ros.calibration.output import install_calibration
    from imu_array_ros.calibration.static import static_loglik
    from imu_array_ros.model.sensor_model import SensorModel

    inputs = [recording, array, calibration]
    out = check_output(out, inputs, "yaml", force)
    if plot is not None:
        plot = check_output(plot, inputs, "png", force, option="--plot", other_outputs=[("--out", out)])
    desc, samples = _read_recording(recording, array, calibration, quiet)
    if kwargs.get("reference"):
        desc.index(kwargs["reference"])  # a one-line error naming the unknown IMU
    model = SensorModel.from_description(desc)
    try:
        result = calibrate_array(samples, model,
                                 progress=lambda text: info(quiet, text), **kwargs)
    except CalibrationError as err:
        raise CalibrationError(f"{recording}: {err}") from None
    _static_table(result, quiet)
    new = array_description(desc, result)
    score = new_score = None
    if result.static is not None and result.moving is None:
        # a static calibration on file is replaced only by one that fits these poses at least as well
        p = result.poses
        score = lambda previous: static_loglik(  # noqa: E731
            p.accel, p.gyro, p.counts, SensorModel.from_description(previous), result.static.gravity)
        new_score = result.static.loglik_after
    try:
        installed = install_calibration(new, out, score=score, new_score=new_score)
    except CalibrationError as err:
        raise CalibrationError(f"{recording}: {err}") from None
    info(quiet, result.summary())
    if installed.backup is not None:
        info(quiet, f"previous {out} kept as {installed.backup}")
    info(quiet, f"wrote {out}")
    if plot is not None and result.static is not None:
        from imu_array_ros.calibration.plots import plot_static

        plot_static(result, plot)
        info(quiet, f"wrote {plot}")
    return 0


def calibrate_static(recording: Path, array: Path, out: Path, *, calibration: Path | None = None,
                     method: str = "ml", reference: str | None = None, terms: str | None = None,
                     gravity: float | None = None, still_gyro: float | None = None, still_accel: float | None = None,
                     still_min_duration: float | None = None, plot: Path | None = None, force: bool = False,
                     quiet: bool = False) -> int:
    """Static multi-pose calibration (nilsson2014 ML or rupniewski PCA) from the still poses of ``recording``."""
    from imu_array_ros.calibration.static import STATIC_TERMS
    from imu_array_ros.model.constants import STANDARD_GRAVITY

    return _calibrate_and_install(
        recording, array, out, calibration, plot, force, quiet, reference=reference, static_method=method,
        static_terms=parse_list(terms) or STATIC_TERMS, moving_terms=(), gravity=gravity or STANDARD_GRAVITY,
        still_options=_still_options(still_gyro, still_accel, still_min_duration))


def calibrate_all(recording: Path, array: Path, out: Path, *, calibration: Path | None = None,
                  reference: str | None = None, static_method: str = "ml", moving_terms: str | None = None,
                  gravity: float | None = None, still_gyro: float | None = None, still_accel: float | None = None,
                  still_min_duration: float | None = None, plot: Path | None = None, force: bool = False,
                  quiet: bool = False) -> int:
    """Whole-array calibration: still poses -> static stage -> moving stage, one description."""
    from imu_array_ros.calibration.array import MOVING_TERMS
    from imu_array_ros.model.constants import STANDARD_GRAVITY

    terms = MOVING_TERMS if moving_terms is None else tuple(parse_list(moving_terms) or ())
    if terms:
        from imu_array_ros.fitting.engine import check_terms

        check_terms(terms)
    return _calibrate_and_install(
        recording, array, out, calibration, plot, force, quiet, reference=reference, static_method=static_method,
        moving_terms=terms, gravity=gravity or STANDARD_GRAVITY,
        still_options=_still_options(still_gyro, still_accel, still_min_duration))


#: what ``calibrate bayes --report DIR`` writes (calibration/bayes_report.py)
BAYES_REPORT_PNGS = ("ellipses.png", "trace.png", "autocorr.png")
BAYES_REPORT_NETCDF = "posterior.nc"


def _bayes_report_outputs(report: Path, inputs, force: bool, out: Path) -> None:
    """Check every file ``--report`` writes (a directory, created if missing), before any work."""
    if report.exists() and not report.is_dir():
        raise OutputError(f"{report}: --report must be a directory (it is a file)")
    if not report.exists():
        check_output(report, inputs, "json", False, option="--report", other_outputs=[("--out", out)])
    check_output(report / "diagnostics.json", inputs, "json", force, option="--report")
    for name in ("diagnostics.md", BAYES_REPORT_NETCDF):
        f = report / name
        if f.exists() and not force:
            raise OutputError(f"{f}: exists; pass --force to replace the report in {report}")
        if f.exists() and not (report / "diagnostics.json").exists():
            raise OutputError(f"{f}: exists without a diagnostics.json beside it; it is not one of our reports, "
                              "choose another --report")
    for name in BAYES_REPORT_PNGS:
        check_output(report / name, inputs, "png", force, option="--report")


def calibrate_bayes(recording: Path, array: Path, out: Path, *, calibration: Path | None = None,
                    samples: int = 50, chains: int = 4, scheduler: str | None = None, workers: int | None = None,
                    report: Path | None = None, reference: str | None = None, prior: str = "gaussian",
                    prior_std: float | None = None, accel_std: float | None = None,
                    omega_covariance: str = "model", draws: int | None = None, rho: float = 0.9,
                    proposal: str = "laplace", ess: float = 400.0, max_iterations: int = 400000,
                    min_excitation: float | None = None, seed: int = 0, force: bool = False,
                    quiet: bool = False) -> int:
    """Posterior of the accelerometer positions (carlsson2021 PmMH) from ``samples`` samples of ``recording``."""
    from imu_array_ros.calibration import bayes, bayes_sampler
    from imu_array_ros.calibration.output import install_calibration, positions_description
    from imu_array_ros.model.sensor_model import SensorModel

    inputs = [recording, array, calibration]
    out = check_output(out, inputs, "yaml", force)
    if report is not None:
        _bayes_report_outputs(Path(report), inputs, force, out)
    settings = bayes_sampler.SamplerSettings(chains=chains, scheduler=scheduler, workers=workers, n_draws=draws,
                                             rho=rho, proposal=proposal, ess=ess, max_iterations=max_iterations,
                                             seed=seed)
    settings.check()
    desc, data = _read_recording(recording, array, calibration, quiet)
    ref = desc.index(reference) if reference else 0  # a one-line error naming an unknown IMU
    model = SensorModel.from_description(desc)
    try:
        idx, dropped, usable = bayes.select_samples(data, model, samples, min_excitation=min_excitation)
        chosen = data.select(idx)
        dropped_text = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in dropped.items() if v) or "none"
        info(quiet, f"samples: {len(idx)} of {usable} usable ({len(data.stamps)} in the recording; dropped: "
                    f"{dropped_text}), evenly spread")
        problem = bayes.build_problem(chosen, model, reference=ref, prior_kind=prior,
                                      prior_std=bayes.PRIOR_STD if prior_std is None else prior_std,
                                      accel_std=accel_std, omega_covariance=omega_covariance)
        info(quiet, "Laplace approximation: maximum likelihood of the positions on the same samples, with its CRB")
        lap = bayes.laplace(problem, chosen, model)
        post = bayes_sampler.sample_posterior(problem, lap, settings, progress=lambda text: info(quiet, text))
    except CalibrationError as err:
        raise CalibrationError(f"{recording}: {err}") from None
    info(quiet, post.summary_line())
    if not post.converged:
        info(quiet, f"warning: the chains did not reach ESS {ess:g} with R-hat <= {settings.rhat} within "
                    f"{max_iterations} iterations; raise --max-iterations or check the report")
    mean, std = post.positions_mean(), post.positions_std()
    new_model = model.with_terms(position=mean)
    record = {**post.record(), "recording": str(recording),
              "laplace_agreement": bayes_sampler.laplace_agreement(post)}
    new = positions_description(desc, new_model, std, record)
    for k, name in enumerate(desc.names):
        change = np.linalg.norm(mean[k] - model.positions[k]) * 1e3
        info(quiet, f"  {name}: moved {change:8.4f} mm, posterior std {np.linalg.norm(std[k]) * 1e6:8.2f} um"
                    f"{'  (reference)' if k == ref else ''}")
    # a calibration on file is kept when it fits these samples better than the posterior's own spread explains
    score, new_score = bayes_sampler.install_scores(post, chosen, model)
    try:
        installed = install_calibration(new, out, score=score, new_score=new_score)
    except CalibrationError as err:
        raise CalibrationError(f"{recording}: {err}") from None
    if installed.backup is not None:
        info(quiet, f"previous {out} kept as {installed.backup}")
    info(quiet, f"wrote {out}")
    if report is not None:
        from imu_array_ros.calibration.bayes_report import write_report

        paths = write_report(post, report, extra={"recording": str(recording), "out": str(out)})
        info(quiet, f"wrote {len(paths)} report files in {report}")
    return 0
