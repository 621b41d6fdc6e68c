"""Every calibration method behind one call that returns a :class:`~imu_array_ros.calibration.result.Calibration`.

:func:`calibrate` (``method`` one of :data:`METHODS`) is what the command line, the
calibration node, the Python API and the benchmarks run (through
:func:`imu_array_ros.workflows.calibrate`).  Each method runs its estimator and
says, in the same form for all, what it calibrated (model, standard deviations), how
(the ``calibration:`` record) and on which data a calibration on file is compared
with it (the scorer):

======== ================================================ ===================================
method   estimator                                        scored on
======== ================================================ ===================================
geometry positions, joint ML or BCD (carlsson2017)        the samples used, motion profiled out
static   still poses: accelerometer intrinsics, gyroscope the pose averages, poses profiled out
         biases (nilsson2014 ML or rupniewski PCA)
all      static stage, then positions and gyroscope gain  the pose averages + the moving samples
         and misalignment from the motion
fit      any terms jointly with the motion (the engine)   the recording, motion profiled out
bayes    posterior of the positions (carlsson2021 PmMH)   the samples used (posterior allowance)
======== ================================================ ===================================

``discover --apply`` is the sixth: :func:`imu_array_ros.discovery.apply.findings_calibration`.
``source`` (e.g. the recording's path) is written into the record as ``recording``.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from imu_array_ros.calibration.array import MOVING_TERMS, calibrate_array
from imu_array_ros.calibration.geometry import DEFAULT_METHOD, calibrate_geometry
from imu_array_ros.calibration.guards import POSITION_BOUND, check_calibration
from imu_array_ros.calibration.noise import noise_calibration
from imu_array_ros.calibration.result import Calibration, SumScorer, fit_statistics, provenance
from imu_array_ros.calibration.scoring import WindowScorer
from imu_array_ros.calibration.selection import MIN_EXCITATION
from imu_array_ros.calibration.sessions import combine_calibrations, session_record
from imu_array_ros.calibration.static import STATIC_TERMS, PoseScorer
from imu_array_ros.errors import CalibrationError
from imu_array_ros.fitting.engine import check_terms, fit_terms
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.reference import reference_index
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.session import estimate_session, needs_session

__all__ = ["calibrate", "METHODS", "geometry", "static", "whole_array", "fit", "bayes"]


def _with_source(record: dict, source: str | None) -> dict:
    return record if source is None else {**record, "recording": str(source)}


def geometry(samples: ImuSamples, model: SensorModel, *, reference=None, method: str = DEFAULT_METHOD,
             max_iterations: int | None = None, min_excitation: float = MIN_EXCITATION,
             progress: Callable[[int, float], None] | None = None, source: str | None = None) -> Calibration:
    """Accelerometer positions from a window of hand twisting
    (:func:`~imu_array_ros.calibration.geometry.calibrate_geometry`); ``progress(iteration, log-likelihood)``."""
    result = calibrate_geometry(samples, model, reference=reference, method=method, max_iterations=max_iterations,
                                min_excitation=min_excitation, progress=progress)
    return Calibration(method="geometry", model=result.model, std={"position": result.position_std},
                       record=_with_source(result.record(), source), scorer=WindowScorer(samples.select(result.used)),
                       score=result.loglik_after, converged=result.converged, summary_line=result.summary(),
                       details=result)


def _array(samples: ImuSamples, model: SensorModel, method: str, source: str | None, **kwargs) -> Calibration:
    result = calibrate_array(samples, model, **kwargs)
    parts = []
    if result.static is not None:
        p = result.poses
        parts.append(PoseScorer(p.accel, p.gyro, p.counts, result.static.gravity))
    if result.moving is not None:
        parts.append(WindowScorer(result.moving_window))
    converged = all(s.converged for s in (result.static, result.moving, result.timing) if s is not None)
    data = " and ".join(d for d, s in (("poses", result.static), ("moving samples", result.moving)) if s is not None)
    return Calibration(method=method, model=result.model, std=result.stds(), record=_with_source(result.record(), source),
                       scorer=SumScorer(parts), data=data, converged=converged, summary_line=result.summary(),
                       details=result)


def static(samples: ImuSamples, model: SensorModel, *, method: str = "ml", reference=None,
           terms: Sequence[str] = STATIC_TERMS, gravity: float = STANDARD_GRAVITY, still_options: dict | None = None,
           max_iterations: int = 50, progress: Callable[[str], None] | None = None,
           source: str | None = None) -> Calibration:
    """Accelerometer intrinsics and gyroscope biases from the still poses of a recording (nilsson2014 ML or
    rupniewski PCA; :func:`~imu_array_ros.calibration.array.calibrate_array` without a moving stage)."""
    return _array(samples, model, "static", source, reference=reference, static_method=method, static_terms=terms,
                  moving_terms=(), gravity=gravity, still_options=still_options, max_iterations=max_iterations,
                  progress=progress)


def whole_array(samples: ImuSamples | Sequence[ImuSamples], model: SensorModel, *, reference=None,
                static_method: str = "ml", static_terms: Sequence[str] = STATIC_TERMS,
                moving_terms: Sequence[str] = MOVING_TERMS, gravity: float = STANDARD_GRAVITY,
                still_options: dict | None = None, max_iterations: int = 50,
                progress: Callable[[str], None] | None = None, source=None, timing: bool = False,
                clock_period: float | None = 1e-3, checks: bool = True,
                position_bound: float = POSITION_BOUND) -> Calibration:
    """Still poses -> static stage, then the motion -> ``moving_terms``, then the timing stage (``timing``:
    sample clocks of ``clock_period`` s searched, time offsets fitted) (``calibrate all``).  A moving or timing
    stage that did not converge or is implausible (``position_bound``; ``checks=False``: not checked) is skipped
    with the reason and the earlier stages' result kept
    (:func:`~imu_array_ros.calibration.array.calibrate_array`).

    ``samples`` a list of recordings of the same array (``source`` then a list of their names): each calibrated
    on its own, then device constants combined and session states (biases) written with their turn-on
    repeatability (:func:`~imu_array_ros.calibration.sessions.combine_calibrations`)."""
    moving_terms = tuple(moving_terms)
    if moving_terms:
        check_terms(moving_terms)
    options = dict(reference=reference, static_method=static_method, static_terms=static_terms,
                   moving_terms=moving_terms, gravity=gravity, still_options=still_options,
                   max_iterations=max_iterations, timing=timing, clock_period=clock_period, checks=checks,
                   position_bound=position_bound)
    recordings = [samples] if isinstance(samples, ImuSamples) else list(samples)
    sources = list(source) if isinstance(source, (list, tuple)) else [source] * len(recordings)
    if len(sources) != len(recordings):
        raise CalibrationError(f"{len(recordings)} recordings but {len(sources)} sources")
    if len(recordings) == 1:
        cal = _array(recordings[0], model, "all", sources[0], progress=progress, **options)
        cal.record.update(session_record(cal))
        return cal
    # several recordings (calibrate all REC1 REC2 ...): each on its own, then combined
    if timing:
        raise CalibrationError("the timing stage runs on one recording at a time (its clocks' phases and the "
                               "searched clocks differ per recording): calibrate the timing on one recording")
    say = progress or (lambda text: None)
    cals = []
    for i, (rec, src) in enumerate(zip(recordings, sources)):
        name = '' if src is None else f' ({src})'
        where = f"recording {i + 1}{name}"
        say(f"recording {i + 1} of {len(recordings)}{name}")
        try:
            cals.append(_array(rec, model, "all", None if src is None else str(src), progress=progress, **options))
        except CalibrationError as err:
            raise CalibrationError(f"{where}: {err}") from None
    return combine_calibrations(cals, sources)


def fit(samples: ImuSamples, model: SensorModel, terms: Sequence[str], *, imus=None, reference=None,
        max_iterations: int = 50, progress: Callable[[int, float], None] | None = None,
        source: str | None = None) -> Calibration:
    """Maximum likelihood of any ``terms`` jointly with the motion (:func:`~imu_array_ros.fitting.engine.fit_terms`);
    ``progress(iteration, cost)``.  The written ``_std`` are the sandwich std (misfit-robust,
    :mod:`imu_array_ros.fitting.robust`), the record keeps the Cramér-Rao bound's median per term; parameters
    held to fix a gauge are exact in that gauge (std 0); IMUs not fitted get none."""
    free = check_terms(terms)
    if needs_session(samples, model):  # this recording's clock phases / stamp clocks first
        model = estimate_session(samples, model).model
    result = fit_terms(samples, model, free, imus=imus, reference=reference, max_iterations=max_iterations,
                       progress=progress)
    record = {
        "method": "fit_terms: joint maximum likelihood of the terms and the motion (Schur-complement "
                  "Gauss-Newton/Levenberg-Marquardt); *_std = sandwich std (misfit-robust; crb_median: the "
                  "Cramer-Rao bound of the joint problem, median per term)",
        "std_kind": result.sandwich.describe() if result.sandwich is not None else "Cramer-Rao bound",
        "crb_median": {t: float(np.nanmedian(result.std[t])) for t in result.free if np.isfinite(result.std[t]).any()},
        **provenance(),
        **({} if source is None else {"recording": str(source)}),
        "terms": list(result.free),
        "imus": list(result.imus),
        "held_for_gauge": list(result.held),
        "samples_used": int(result.samples_used),
        "samples_dropped": int(result.samples_dropped),
        **fit_statistics(result),
    }
    fitted = np.isin(np.array(model.names), np.array(result.imus))
    robust = result.std_robust or result.std
    std = {n: np.where(fitted[:, None] & ~np.isfinite(robust[n]), 0.0, robust[n]) for n in result.free}
    line = (f"fitted {len(result.theta)} parameters of {', '.join(result.free)} on {result.samples_used} samples in "
            f"{result.iterations} iterations{'' if result.converged else ' (NOT converged)'}; NIS per degree of "
            f"freedom {result.nis_before:.4g} -> {result.nis_after:.4g}")
    return Calibration(method="fit", model=result.model, std=std, record=record, scorer=WindowScorer(samples),
                       data="recording", converged=result.converged, summary_line=line, details=result)


def bayes(samples: ImuSamples, model: SensorModel, *, n_samples: int = 50, settings=None, reference=None,
          prior: str = "gaussian", prior_std: float | None = None, accel_std: float | None = None,
          omega_covariance: str = "model", min_excitation: float | None = None,
          progress: Callable[[str], None] | None = None, source: str | None = None) -> Calibration:
    """Posterior of the accelerometer positions (carlsson2021 PmMH) from ``n_samples`` samples with rotation,
    evenly spread; ``settings``: a ``SamplerSettings`` (chains, scheduler, ...).  Writes the posterior mean and
    std; a calibration on file is kept only when it fits those samples better than any position in the
    posterior's 99 % credible region would (the allowance)."""
    from imu_array_ros.calibration import bayes as posterior
    from imu_array_ros.calibration.scoring import window_loglik

    say = progress or (lambda text: None)
    settings = settings or posterior.SamplerSettings()
    settings.check()
    ref = reference_index(model.names, reference)
    idx, dropped, usable = posterior.select_samples(samples, model, n_samples, min_excitation=min_excitation)
    chosen = samples.select(idx)
    dropped_text = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in dropped.items() if v) or "none"
    say(f"samples: {len(idx)} of {usable} usable ({len(samples)} in the recording; dropped: {dropped_text}), "
        "evenly spread")
    problem = posterior.build_problem(chosen, model, reference=ref, prior_kind=prior,
                                          prior_std=posterior.PRIOR_STD if prior_std is None else prior_std,
                                          accel_std=accel_std, omega_covariance=omega_covariance)
    say("Laplace approximation: maximum likelihood of the positions on the same samples, with its CRB")
    lap = posterior.laplace(problem, chosen, model)
    post = posterior.sample_posterior(problem, lap, settings, progress=say)
    mean, std = post.positions_mean(), post.positions_std()
    new_model = model.with_terms(position=mean)
    record = {**post.record(), **({} if source is None else {"recording": str(source)}),
              "laplace_agreement": posterior.laplace_agreement(post)}
    return Calibration(method="bayes", model=new_model, std={"position": std}, record=record,
                       scorer=WindowScorer(chosen), score=window_loglik(chosen, new_model),
                       allowance=posterior.install_allowance(post), converged=post.converged,
                       summary_line=post.summary_line(), details=post)


#: method name -> the function that runs it
METHODS: dict[str, Callable[..., Calibration]] = {"geometry": geometry, "static": static, "all": whole_array,
                                                   "fit": fit, "bayes": bayes, "noise": noise_calibration}


def calibrate(method: str, samples: ImuSamples, model: SensorModel, /, *, checks: bool = True,
              position_bound: float = POSITION_BOUND, **options) -> Calibration:
    """Run calibration ``method`` (:data:`METHODS`) on ``samples`` starting from ``model``; the result must
    pass :func:`~imu_array_ros.calibration.guards.check_calibration` (converged, plausible -- positions within
    ``position_bound`` m of ``model``'s -- and fitting its data at least as well as ``model``), else
    CalibrationError names why and nothing is returned to write.  ``checks=False`` (experts only) skips them."""
    try:
        run = METHODS[method]
    except KeyError:
        raise CalibrationError(f"unknown calibration method {method!r} (known: {', '.join(METHODS)})") from None
    if run is whole_array:  # its stages are checked as they run: a refused stage is skipped, the others kept
        options.update(checks=checks, position_bound=position_bound)
    cal = run(samples, model, **options)
    if checks:
        check_calibration(cal, model, position_bound=position_bound)
    return cal
