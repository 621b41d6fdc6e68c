"""Sample time: finding, from a recording's own readings, when each IMU really sampled.

The timing terms of the sensor model (:mod:`imu_array_ros.model.terms.timing`) hold two kinds of
value.  *Device constants* (a sensor's ``time_offset``, a chip's ``sample_clock`` period and rate)
live in the description and are fitted by the calibrations.  *Session states* change at every
power-up or start: the phase of each chip's free-running sample clock, the clock rate the whole
board drifts to, the offset and skew of IMUs that stamp their own messages.  This package
estimates the session states from each recording, before it is fused, analysed or calibrated:

* :mod:`.delays` -- every IMU's reading delay per sample, relative to the others (the residual of
  the fusion along d y / d delay), with its information and the samples that carry it (moving);
* :mod:`.sawtooth` -- a free-running sample clock read by the host makes the delay a sawtooth:
  its rate found by a spectrum of the delays (on the true stamps), its phase by the fundamental's
  phase refined on the sawtooth itself;
* :mod:`.session` -- :func:`estimate_session`: the session states of a model for one recording.

Time is relative: a delay common to every reading moves no reading relative to another, so only
relative delays are observed, sample by sample; the sawtooth's shape (its wraps) still fixes each
chip's own phase.  The fused motion refers to the array stamp (delay 0), the gauge the model states.
"""

from imu_array_ros.timing.delays import ReadingDelays, reading_delays
from imu_array_ros.timing.sawtooth import fit_phases, search_rates
from imu_array_ros.timing.session import MIN_MOVING_S, SessionStates, estimate_session

__all__ = ["ReadingDelays", "reading_delays", "fit_phases", "search_rates", "SessionStates", "estimate_session",
           "MIN_MOVING_S"]
