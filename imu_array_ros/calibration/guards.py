"""What every calibration must pass before anything is written: never write nonsense.

:func:`check_calibration` runs on every calibration result (the dispatcher
:func:`imu_array_ros.calibration.methods.calibrate`, hence the command line, the
``/calibrate_geometry`` service, the Python API; and ``discover --apply``) and raises
:class:`~imu_array_ros.errors.CalibrationError`, one line naming the reason, when

(a) **not converged**: the method's own convergence test failed (``Calibration.converged``);
    the iterations it ran are named;
(b) **implausible**: a value it changed is beyond what a real sensor has:

    * a position moved more than ``position_bound`` (default :data:`POSITION_BOUND`, 5 mm)
      from the description it started from (a chip does not move on its board; a
      description's positions come from a drawing good to a millimetre or two; a fit
      that moves them further has absorbed something else -- on the MIMU4444BT
      captures, still poses passed as rotation moved 19 mm-board positions by 35-46 mm);
    * any other field changed by the calibration beyond its term's declared bound
      (``Field.plausible``, :mod:`imu_array_ros.model.terms`): gains within 0.2 of 1,
      misalignment and non-orthogonality angles within 0.1 rad, biases within 10 % of the
      sensor's full-scale range, time offsets within 0.1 s, clock rates within 5 % (5e4 ppm);
      fields without a declared bound are not tested;
(c) **fits worse**: the calibrated model's log-likelihood on the calibration's own data
    (plus its ``allowance``, the Bayesian posterior mean's) is below the starting model's
    by more than :data:`~imu_array_ros.calibration.result.LOGLIK_TOLERANCE` -- a
    calibration that explains its data worse than where it started is refused.

A calibration made of stages (``calibrate all``: static, moving, timing) applies (a) and (b) to
each stage that builds on an earlier one before the next runs (:func:`check_stage`): a refused
stage is skipped with the reason and the earlier stages' result kept.

``checks=False`` in the dispatcher (Python API only) skips all of them, for experts who
judge the numbers themselves.  Session states (clock phases) are not
tested: they are never written as device constants.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.calibration.result import LOGLIK_TOLERANCE, Calibration
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY

__all__ = ["check_calibration", "check_converged", "check_plausible", "check_fits_better", "check_stage",
           "implausible", "POSITION_BOUND"]

#: default largest distance, m, a calibrated position may be from the position it started from
POSITION_BOUND = 5e-3
#: how a refusal ends: nothing was written, and the expert's way past it
_NOTHING = "nothing written"


def check_calibration(cal: Calibration, start: SensorModel, *, position_bound: float = POSITION_BOUND) -> None:
    """(a) converged, (b) plausible, (c) fits its data at least as well as ``start``, the model it
    started from (module docstring); CalibrationError naming the first reason otherwise."""
    check_converged(cal)
    check_plausible(cal, start, position_bound=position_bound)
    check_fits_better(cal, start)


def _iterations(cal: Calibration) -> str:
    """What the unconverged part of ``cal`` ran, for the message."""
    d = cal.details
    if hasattr(d, "iterations"):
        return f"{int(d.iterations)} iterations"
    stages = [(name, getattr(d, name, None)) for name in ("static", "moving")]
    parts = [f"{name} stage: {int(s.iterations)} iterations" for name, s in stages
             if s is not None and not s.converged and hasattr(s, "iterations")]
    return "; ".join(parts) or "its convergence test failed"


def check_converged(cal: Calibration) -> None:
    """(a): CalibrationError when the method's convergence test failed."""
    if not cal.converged:
        raise CalibrationError(f"{cal.method}: refused: not converged ({_iterations(cal)}); {_NOTHING} "
                               "(a longer window with more rotation, or a higher iteration cap)")


def check_stage(fit, start: SensorModel, *, position_bound: float = POSITION_BOUND) -> None:
    """(a) and (b) for one stage of a calibration: ``fit`` (``converged``, ``iterations``, ``model``) the stage's
    result, ``start`` the model the stage started from (the earlier stages' result); CalibrationError, one line
    naming the reason, when the stage did not converge or changed a value beyond its bound."""
    if not fit.converged:
        raise CalibrationError(f"refused: not converged ({int(fit.iterations)} iterations)")
    problem = implausible(fit.model, start, position_bound=position_bound)
    if problem is not None:
        raise CalibrationError(f"refused: {problem}")


def _bound(field, model: SensorModel) -> float | None:
    """``field``'s plausible |value - default| for ``model`` (None: no bound)."""
    if field.plausible is None:
        return None
    if not field.plausible_of_range:
        return float(field.plausible)
    full_scale = model.acc_clip if field.path[0] == "accelerometer" else model.gyro_clip
    return float(field.plausible) * float(full_scale)  # inf when the description gives no range


def check_plausible(cal: Calibration, start: SensorModel, *, position_bound: float = POSITION_BOUND) -> None:
    """(b): CalibrationError naming the worst value beyond its bound (module docstring)."""
    problem = implausible(cal.model, start, position_bound=position_bound)
    if problem is not None:
        raise CalibrationError(f"{cal.method}: refused: {problem}; {_NOTHING}")


def implausible(model: SensorModel, start: SensorModel, *, position_bound: float = POSITION_BOUND) -> str | None:
    """Why ``model`` is physically implausible as a change from ``start`` (check (b) of the module docstring):
    the worst value beyond its bound, in one phrase; None when every changed value is within its bound.
    Mismatch discovery asks this of every exact refit before it reports a finding."""
    if not position_bound > 0:
        raise CalibrationError(f"the position bound must be > 0 m, got {position_bound!r}")
    names = model.names
    change = np.linalg.norm(model.positions - start.positions, axis=1)
    if not np.all(np.isfinite(change)) or np.max(change) > position_bound:
        k = int(np.argmax(np.where(np.isfinite(change), change, np.inf)))
        return (f"{names[k]} position moved {change[k] * 1e3:.2f} mm from the description it started from "
                f"(more than {position_bound * 1e3:g} mm: physically implausible)")
    for term_name, term in model.terms.items():
        before = start.terms.get(term_name)
        if before is not None and np.array_equal(before.values, term.values):
            continue  # not changed by this calibration
        for f, values in zip(REGISTRY[term_name].fields, term.split().values()):
            bound = _bound(f, model)
            if bound is None or f.session:
                continue
            excess = np.abs(np.asarray(values, dtype=float) - f.default)
            bad = ~(excess <= bound)  # NaN is beyond every bound
            if bad.any():
                idx = np.unravel_index(int(np.argmax(np.where(bad, np.nan_to_num(excess, nan=np.inf), -1.0))),
                                       bad.shape)
                element = f"[{','.join(str(int(i)) for i in idx[1:])}]" if len(idx) > 1 else ""
                unit = "" if f.unit == "1" else f" {f.unit}"
                return (f"{names[idx[0]]} {f.key}{element} = {float(np.reshape(values, bad.shape)[idx]):.4g}{unit}, "
                        f"more than {bound:.4g} from {f.default:g} (physically implausible)")
    return None


def check_fits_better(cal: Calibration, start: SensorModel) -> None:
    """(c): CalibrationError when ``cal`` scores its own data worse than ``start`` does (no scorer: not tested)."""
    if cal.scorer is None:
        return
    new = (cal.score_of(cal.model) if cal.score is None else float(cal.score)) + cal.allowance
    old = cal.score_of(start)
    if not np.isfinite(new) or (np.isfinite(old) and new < old - LOGLIK_TOLERANCE):
        raise CalibrationError(
            f"{cal.method}: refused: the calibrated model fits its own {cal.data} worse than the one it started "
            f"from (log-likelihood {new:.10g} < {old:.10g}); {_NOTHING}")
