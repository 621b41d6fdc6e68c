"""Whole-array calibration from one recording: still poses, then the moving phase.

``calibrate_array`` (what ``imu-array calibrate all`` runs):

1. **Still poses** (:func:`~imu_array_ros.calibration.still.find_still_poses`):
   the still intervals of the recording, averaged per IMU.
2. **Static stage** (:func:`~imu_array_ros.calibration.static.calibrate_static`,
   nilsson2014 ML): accelerometer gain, non-orthogonality, bias and
   misalignment, and the gyroscope biases.  Skipped, with the reason, when the
   recording has too few or too clustered poses.
3. **Moving stage**: with the static result applied, the accelerometer
   positions and the gyroscopes' full 3x3 (gain, misalignment, non-orthogonality), jointly with every
   sample's motion, by the fitting engine
   (:func:`~imu_array_ros.fitting.engine.fit_terms`) on the samples
   outside the still intervals that rotate enough (the geometry calibration's
   sample selection).  A common scale of the gyroscopes and of the positions
   is not observable from motion alone (engine docstring: omega (1 + e),
   positions / (1 + e)^2 read the same); the engine holds the reference IMU's
   gyroscope gain for it.  Skipped, with the reason, when there is no such
   motion, and refused (skipped, the static stage's model kept) when its fit did
   not converge or moved a value beyond what a real sensor has
   (:func:`~imu_array_ros.calibration.guards.check_stage`: a position more than
   5 mm, a gain more than 0.2, ...).
4. **Timing stage** (``timing``): :func:`_timing_stage`.  Skipped, with the
   reason, when the moving stage did not run or the data cannot identify the
   timing terms; refused by the same check; the moving stage's model then kept.

One description comes out with every calibrated field, its ``_std`` and a
``calibration:`` block listing each stage, the data it used and its residuals.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from imu_array_ros.calibration.guards import POSITION_BOUND, check_stage
from imu_array_ros.calibration.result import provenance
from imu_array_ros.errors import CalibrationError, FusionError, IdentifiabilityError
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["MOVING_TERMS", "ArrayCalibration", "calibrate_array"]

#: what the moving stage fits by default
#: (the gyroscopes' full 3x3 relative to the reference: gain, misalignment and non-orthogonality; on the real
#: MIMU4444BT captures leaving the non-orthogonality out left held-out moving NIS at 3.1e3 instead of 2.2e3)
MOVING_TERMS = ("position", "gyroscope_gain", "gyroscope_misalignment", "gyroscope_nonorthogonality")
#: what a stage raises when the recording cannot determine what it fits (a property of the data, not of the call):
#: the stage is skipped with the reason and the earlier stages' result kept
DATA_ERRORS = (CalibrationError, IdentifiabilityError, FusionError)


@dataclass
class ArrayCalibration:
    """The stages of :func:`calibrate_array`: model (every stage applied), poses (StillPoses),
    static (StaticCalibration or None), moving (FitResult or None), skipped: stage -> reason,
    moving_samples: (used, total) of the moving stage, moving_window: the samples the moving stage
    fitted (None: no moving stage), seconds, timing: the timing stage's refit of the timing terms and the gyroscope
    gains (FitResult; the moving stage's positions, gyroscope misalignment and non-orthogonality are kept; None: it
    did not run or was skipped)."""

    model: SensorModel
    poses: object
    static: object | None
    moving: object | None
    skipped: dict[str, str] = field(default_factory=dict)
    moving_samples: tuple[int, int] = (0, 0)
    moving_terms: tuple[str, ...] = ()
    moving_window: ImuSamples | None = field(default=None, repr=False)
    seconds: float = 0.0
    timing_notes: list[str] = field(default_factory=list)
    timing: object | None = None

    @property
    def timed(self) -> bool:
        """The timing stage ran and its result was kept."""
        return self.timing is not None

    def stds(self) -> dict[str, np.ndarray]:
        """term -> (K, P) standard deviations of every calibrated field: the static stage's
        (``written_std``), the moving stage's sandwich std (:mod:`imu_array_ros.fitting.robust`: holds when the
        model does not fit to the noise level; its Cramer-Rao bound where the sandwich was not computed)."""
        out = {}
        if self.static is not None:
            out.update(self.static.written_std())
        if self.moving is not None:
            for t in self.moving.free:
                out[t] = self.moving.std_robust.get(t, self.moving.std[t])
        if self.timing is not None:  # a term the moving stage fitted keeps its std (the timing fit's is conditional
            for t in self.timing.free:  # on the held positions and gyroscope axes' terms, too small)
                if self.moving is None or t not in self.moving.free:
                    out[t] = self.timing.std_robust.get(t, self.timing.std[t])
        return out

    def summary(self) -> str:
        parts = []
        if self.static is not None:
            parts.append(f"static: {self.static.summary()}")
        if self.moving is not None:
            m = self.moving
            parts.append(f"moving: {self.moving_samples[0]} of {self.moving_samples[1]} samples, "
                         f"{', '.join(m.free)}; NIS {m.nis_before:.4g} -> {m.nis_after:.4g}, {m.iterations} iterations"
                         f"{'' if m.converged else ' (NOT converged)'}")
        if self.timing is not None:
            m = self.timing
            parts.append(f"timing: {', '.join(m.free)} on {self.moving_samples[0]} samples; NIS {m.nis_before:.4g} -> "
                         f"{m.nis_after:.4g}, {m.iterations} iterations")
        parts += [f"timing: {note}" for note in self.timing_notes]
        parts += [f"{stage} skipped: {why}" for stage, why in self.skipped.items()]
        return "; ".join(parts)

    def record(self) -> dict:
        f = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        stages = []
        spread = self.poses.spread() if self.poses is not None else {}
        stages.append({"stage": "still poses", "poses": int(len(self.poses.accel)) if self.poses is not None else 0,
                       "spread": {k: (f(v) if isinstance(v, float) else v) for k, v in spread.items()},
                       "rejected": [{"start": int(a), "stop": int(b), "reason": r}
                                    for a, b, r in (self.poses.rejected if self.poses is not None else [])]})
        if self.static is not None:
            stages.append(self.static.record())
        if self.moving is not None:
            m = self.moving
            stages.append({"stage": "moving", "method": "maximum likelihood of the terms jointly with every sample's "
                           "motion (Schur-complement Gauss-Newton); _std = sandwich std (misfit-robust; "
                           "crb_median: the Cramer-Rao bound's median per term)",
                           "std_kind": m.sandwich.describe() if m.sandwich is not None else "Cramer-Rao bound",
                           "crb_median": {t: f(np.nanmedian(m.std[t])) for t in m.free if np.isfinite(m.std[t]).any()},
                           "terms": list(m.free), "samples_used": int(self.moving_samples[0]),
                           "samples_total": int(self.moving_samples[1]), "iterations": int(m.iterations),
                           "converged": bool(m.converged), "held": list(m.held),
                           "log_likelihood_before": f(m.loglik_before), "log_likelihood_after": f(m.loglik_after),
                           "nis_before": f(m.nis_before), "nis_after": f(m.nis_after)})
        if self.timing_notes or self.timing is not None:
            stage = {"stage": "timing", "notes": list(self.timing_notes)}
            if self.timing is not None:
                m = self.timing
                stage.update({"terms": list(m.free), "held": list(m.held), "samples_used": int(self.moving_samples[0]),
                              "iterations": int(m.iterations), "converged": bool(m.converged),
                              "log_likelihood_before": f(m.loglik_before), "log_likelihood_after": f(m.loglik_after),
                              "nis_before": f(m.nis_before), "nis_after": f(m.nis_after)})
            stages.append(stage)
        return {"method": self.method(), **provenance(), "stages": stages, "skipped": dict(self.skipped)}

    def method(self) -> str:
        """The stages this calibration ran through: ``calibrate static`` (no moving terms asked for) or
        ``calibrate all``; the timing stage named only when it ran (a skipped stage is in ``skipped``)."""
        stages = ["still poses", "static (accelerometer intrinsics, gyroscope biases)"]
        if not self.moving_terms:
            return "calibrate static: " + " -> ".join(stages)
        stages.append("moving (positions, gyroscope gain, misalignment and non-orthogonality)")
        if self.timed:
            stages.append("timing (sample clocks, time offsets with the gyroscope gains; the moving stage's positions, "
                          "gyroscope misalignment and non-orthogonality kept)")
        return "calibrate all: " + " -> ".join(stages)


def calibrate_array(samples: ImuSamples, model: SensorModel, *, reference=None, static_method: str = "ml",
                    static_terms: Sequence[str] | None = None, moving_terms: Sequence[str] = MOVING_TERMS,
                    gravity: float = STANDARD_GRAVITY, still_options: dict | None = None,
                    max_iterations: int = 50, progress: Callable[[str], None] | None = None,
                    timing: bool = False, clock_period: float | None = 1e-3, checks: bool = True,
                    position_bound: float = POSITION_BOUND) -> ArrayCalibration:
    """Calibrate what the recording can: static stage from its still poses, moving stage from the rest,
    then (``timing``) the timing stage (:mod:`~imu_array_ros.calibration.timing`: sample clocks of period
    ``clock_period`` searched, then the time offsets fitted with the gyroscope gains, the moving stage's other
    terms held).  The moving and
    timing stages' results are kept only when they pass :func:`~imu_array_ros.calibration.guards.check_stage`
    (converged; positions within ``position_bound`` m; every other value within its term's bound);
    ``checks=False`` (experts) keeps them as they come.

    Raises :class:`CalibrationError` only when neither the static nor the moving stage gives a result (the
    reasons of both)."""
    from imu_array_ros.calibration.selection import MIN_EXCITATION, require_rotation, select_rotating
    from imu_array_ros.calibration.static import MIN_POSES, STATIC_TERMS, calibrate_static
    from imu_array_ros.calibration.still import check_poses, find_still_poses
    from imu_array_ros.fitting.engine import fit_terms

    say = progress or (lambda text: None)
    t0 = time.perf_counter()
    static_terms = tuple(STATIC_TERMS if static_terms is None else static_terms)
    skipped: dict[str, str] = {}
    poses = find_still_poses(samples, model, **(still_options or {}))
    say(f"still poses: {poses.summary()}")
    current, static = model, None
    try:
        check_poses(poses, MIN_POSES["accelerometer_misalignment" in static_terms])
        say(f"static stage: {static_method} on {len(poses.accel)} poses")
        static = calibrate_static(poses.accel, poses.gyro, poses.counts, current, method=static_method,
                                  terms=static_terms, reference=reference, gravity=gravity,
                                  max_iterations=max_iterations)
        current = static.model
        say(f"static stage: {static.summary()}")
    except CalibrationError as err:
        skipped["static"] = str(err)
        say(f"static stage skipped: {err}")
    moving, used_total, window = None, (0, 0), None
    moving_terms = tuple(moving_terms)
    if moving_terms:  # calibrate static: no moving stage to run or to report as skipped
        try:
            idx = np.flatnonzero(poses.moving)
            if len(idx) < 3:
                raise CalibrationError(f"no moving phase: {len(idx)} samples outside the still intervals")
            moving_samples = samples.select(idx)
            selection = select_rotating(moving_samples, current, MIN_EXCITATION, gyroscopes=True)
            require_rotation(selection)
            used = selection.used
            used_total = (selection.n_used, len(samples))
            say(f"moving stage: {', '.join(moving_terms)} on {used_total[0]} of {len(idx)} moving samples")
            window = moving_samples.select(used)
            from imu_array_ros.timing.session import active_clocks, estimate_session
            start = estimate_session(samples, current).model if active_clocks(current) else current  # clock phases
            fit = fit_terms(window, start, moving_terms, reference=reference, t0_ns=int(samples.stamps[0]),
                            motion0=selection.motion[used], max_iterations=max_iterations,
                            progress=lambda it, cost: say(f"moving stage: iteration {it}, cost {cost:.10g}"))
            say(f"moving stage: NIS {fit.nis_before:.4g} -> {fit.nis_after:.4g}")
            if checks:  # a refused result is neither written nor built on by the timing stage
                check_stage(fit, start, position_bound=position_bound)
            moving, current = fit, fit.model
        except DATA_ERRORS as err:
            skipped["moving"] = str(err)
            used_total, window = (0, 0), None
            say(f"moving stage skipped: {err}")
    timing_notes: list[str] = []
    timing_fit = None
    if timing and moving is not None:
        timing_fit, current, timed_window, timing_notes = _timing_stage(
            samples, poses, current, moving, skipped, reference, clock_period, max_iterations, say,
            position_bound if checks else None)
        if timed_window is not None:
            window, used_total = timed_window, (len(timed_window), len(samples))
    elif timing and moving_terms:
        skipped["timing"] = "no moving stage result to build on (the moving stage was skipped)"
    if static is None and not moving_terms:
        raise CalibrationError(skipped["static"])
    if static is None and moving is None:
        raise CalibrationError(f"nothing to calibrate: static stage: {skipped['static']}; "
                               f"moving stage: {skipped['moving']}")
    return ArrayCalibration(model=current, poses=poses, static=static, moving=moving, skipped=skipped,
                            moving_samples=used_total, moving_terms=tuple(moving.free) if moving else moving_terms,
                            timing_notes=timing_notes, timing=timing_fit,
                            moving_window=window if moving is not None else None,
                            seconds=time.perf_counter() - t0)


def _timing_stage(samples, poses, current, moving, skipped, reference, clock_period, max_iterations, say, position_bound):
    """The timing stage (:mod:`~imu_array_ros.calibration.timing`): on the contiguous moving samples (the timing
    terms read the motion's time derivatives, so no sample is picked out), the timing terms fitted with the
    gyroscope gains (:func:`_timing_terms`), the moving stage's positions, gyroscope misalignment and
    non-orthogonality held.  Not refitted with the positions: the time offsets open a weak direction (a common
    gyroscope scale with the positions growing as its square) along which each capture lands elsewhere -- on the
    six real captures such a joint refit wrote gyroscope gains spreading 4.2x their std and arrays 6-18 % larger
    than the board, for 1-9 % of its held-out gain (benchmarks/results/real_calibration_trust_timing_joint.md,
    real_timing_heldout.md); with the positions and the reference IMU's gain held that direction is closed.  The
    gains are written with the moving stage's std (:meth:`ArrayCalibration.stds`).  The fit is refused unless it passes
    :func:`~imu_array_ros.calibration.guards.check_stage` against the moving stage's model (``position_bound``
    None: not checked).  Returns (timing fit, model, window, notes); when the data cannot identify the timing terms
    (:data:`DATA_ERRORS`) or the fit is refused, (None, the moving stage's model, None, []) and a skip reason."""
    from imu_array_ros.calibration.timing import prepare_timing
    from imu_array_ros.fitting.engine import fit_terms

    idx = np.flatnonzero(poses.moving)
    try:
        setup = prepare_timing(samples.select(idx), current, clock_period=clock_period, t0_ns=int(samples.stamps[0]))
        for note in setup.notes:
            say(f"timing stage: {note}")
        window = samples.select(idx)
        terms, hold = _timing_terms(current, reference, setup.terms, moving)
        say(f"timing stage: {', '.join(terms)} on the {len(idx)} moving samples (the moving stage's other terms "
            f"held); held: {', '.join(hold) or 'nothing'}")
        fit = fit_terms(window, setup.model, terms, reference=reference, max_iterations=max_iterations,
                        t0_ns=int(samples.stamps[0]), hold=hold,
                        progress=lambda it, cost: say(f"timing stage: iteration {it}, cost {cost:.10g}"))
        say(f"timing stage: NIS {fit.nis_before:.4g} -> {fit.nis_after:.4g}")
        if position_bound is not None:  # a refused refit is not written over the moving stage's result
            check_stage(fit, current, position_bound=position_bound)
        return fit, fit.model, window, setup.notes
    except DATA_ERRORS as err:
        skipped["timing"] = f"{err}; the moving stage's result is kept"
        say(f"timing stage skipped: {err}")
        return None, current, None, []


def _timing_terms(model: SensorModel, reference, terms, moving) -> tuple[tuple[str, ...], list[str]]:
    """What the timing fit frees and holds.  With ``time_offset``: the gyroscope gains too, when the moving stage
    fitted them (fitted there without the delays, they absorb part of the gyroscopes' delays: on the simulated
    session the moved gyroscopes' offsets came out 1.3-1.6 of their std short, unbiased with the true gains put in,
    unchanged with the true positions; benchmarks/results/calibrate_timing_trust.md); held: the gauge of time, the
    reference IMU's gyroscope delay (the fused motion then refers to the instant the reference gyroscope samples; a
    common delay of every reading is absorbed by the motion), and the gains the moving stage held (its gauge)."""
    from imu_array_ros.model.reference import reference_index

    if "time_offset" not in terms:
        return tuple(terms), []
    hold = [f"{model.names[reference_index(model.names, reference)]} gyroscope.time_offset"]
    if "gyroscope_gain" in moving.free:
        terms = tuple(terms) + ("gyroscope_gain",)
        hold += [h for h in moving.held if " gyroscope.gain[" in h]
    return terms, hold
