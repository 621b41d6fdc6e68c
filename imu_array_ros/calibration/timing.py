"""The timing stage of ``calibrate all``: when each IMU really samples, as device constants.

Run on the recording's moving samples after the moving stage (positions and gyroscope gains fitted
without timing):

1. **Sample clocks.**  A description that has them (a ``sample_clock`` period) gets this recording's
   phases (:func:`~imu_array_ros.timing.session.estimate_session`).  One that has none is searched for
   free-running chip clocks of period ``clock_period`` (:func:`~imu_array_ros.timing.clocks.find_sample_clocks`):
   a chip whose reading delays show a sawtooth clearly above their noise gets a clock (rate, this
   session's phase); the others are named.  ``clock_period=None`` skips the search.
2. ``time_offset`` (each sensor's constant delay) is then fitted with the gyroscope gains, the moving stage's
   positions, gyroscope misalignment and non-orthogonality held (``calibration.array._timing_stage``).
   The clocks' rates stay those of the search (the spectral peak places them to a fraction of a ppm;
   the engine's Gauss-Newton cannot refine them, as a rate moves the sawtooth's wraps, which its
   first-order Jacobian does not see, and it stalls); the phase is a session state, never written.
   A common delay of every sensor is not observable: the reference IMU's gyroscope offset is held
   (the gauge of time).

What the recording cannot identify (too little motion) is skipped with the reason, as every stage.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.clocks import find_sample_clocks
from imu_array_ros.timing.session import active_clocks, estimate_session

__all__ = ["TimingSetup", "prepare_timing", "CLOCK_PERIOD"]

#: the internal sample period searched by default (the ~1 kHz of most MEMS IMUs)
CLOCK_PERIOD = 1e-3


@dataclass
class TimingSetup:
    """model: the input with sample clocks (found, or the description's with this recording's phases);
    terms: the timing terms the moving stage fits (``time_offset``); notes: what was found and why."""

    model: SensorModel
    terms: tuple[str, ...]
    notes: list[str] = field(default_factory=list)
    clocks_found: int = 0


def prepare_timing(samples: ImuSamples, model: SensorModel, *, clock_period: float | None = CLOCK_PERIOD,
                   t0_ns: int | None = None) -> TimingSetup:
    """The sample clocks of ``samples`` under ``model`` and the timing terms to fit (module docstring).
    Raises :class:`CalibrationError` when there is too little motion for any timing term."""
    clocks = active_clocks(model)
    if clocks:
        session = estimate_session(samples, model, t0_ns=t0_ns)
        if not session.estimated:
            raise CalibrationError("; ".join(session.notes))
        return TimingSetup(session.model, ("time_offset",),
                           [f"sample clocks of the description: phases of this recording found; {session.notes[-1]}"],
                           sum(int(np.sum(model.terms[t].values[:, 0] > 0)) for t in clocks))
    if clock_period is None:
        return TimingSetup(model, ("time_offset",), ["no sample-clock search (clock period not given)"])
    try:
        search = find_sample_clocks(samples, model, period=clock_period, t0_ns=t0_ns)
    except ValueError as err:
        raise CalibrationError(f"timing not identifiable: {err}") from None
    return TimingSetup(search.model, ("time_offset",), search.notes, search.count)

