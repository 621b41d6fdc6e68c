"""Each chip's readings at its own sample instant: the signals' rates of change within the chips' clock spread as
per-sample motion coordinates (the fitting engine's option, on inside :func:`reading_rates`).

When every chip samples its sensors on its own free-running clock (``sample_clock``, ``gyroscope_sample_clock``:
a ~1 kHz sawtooth of reading ages), the readings of one array sample are up to a clock period apart.  The model
predicts each reading at its own instant along the estimated motion (:mod:`imu_array_ros.model.terms.timing`):
first order from the sample's omega_dot (gyroscopes) or the local polynomials' ds/dt (accelerometers).  At a low read
rate (62.5 Hz on the MIMU4444BT captures) the signals change within that millisecond by more than those rates
say -- the motion has content the read rate cannot follow -- and the readings of chips with different ages
disagree by it.  On the real captures the moving residual of two IMUs grows ~5-10x from equal ages to ages
1 ms apart, and a free rate per sample, acting on each chip as (its age - the sample's mean age), removes about
half of the moving residual where random ages remove what chance does
(``benchmarks/results/real_residual_anatomy.md``).

So, with :func:`reading_rates` on and a model with sample clocks, every sample's motion coordinates are
[omega, omega_dot, s, rho_g, rho_a] (15): rho_g (rad/s^2) and rho_a (m/s^3) in the array frame add
R_k^T (age_k - mean age) rho to IMU k's gyroscope and accelerometer readings.  They are estimated per sample with
the motion (the Schur complement eliminates them with it), so they cost no parameter and are never written
anywhere; the readings' information on the terms is what is left once they are profiled out.  The common part
of a shift stays on the motion (the ages are centred per sample), so time offsets and the accelerometer-gyroscope
lag keep their meaning.  The sample clocks themselves must be known first (found by search,
:mod:`imu_array_ros.timing`): their rates of change within the spread are what the coordinates absorb.
"""

from __future__ import annotations

import contextlib
import contextvars

import numpy as np

from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["reading_rates", "rates_on", "rates_scope", "keep_rates", "chip_clock", "rate_columns", "age_columns",
           "RATES"]

#: motion coordinates added per sample: rho_g (3), rho_a (3)
RATES = 6
_ON = contextvars.ContextVar("reading_rates", default=False)
_SCOPE = contextvars.ContextVar("reading_rates_scope", default=False)
#: the terms whose sawtooth gives each chip's reading age, in order of preference
CLOCK_TERMS = ("sample_clock", "gyroscope_sample_clock")


@contextlib.contextmanager
def reading_rates(on: bool = True):
    """Inside (also as a decorator): fitting problems made for a model with sample clocks carry each sample's
    reading rates as motion coordinates (see the module docstring); off by default."""
    token = _ON.set(bool(on))
    try:
        yield
    finally:
        _ON.reset(token)


def rates_on() -> bool:
    return _ON.get()


@contextlib.contextmanager
def rates_scope():
    """A block in which :func:`keep_rates` may switch the reading rates on for the rest of the block (off at its
    start; the state before it restored at its end): what a workflow wraps an analysis in, so that a decision
    taken inside (discovery's timing stage) holds for that analysis only."""
    token, scope = _ON.set(False), _SCOPE.set(True)
    try:
        yield
    finally:
        _SCOPE.reset(scope)
        _ON.reset(token)


def keep_rates(on: bool) -> bool:
    """Inside :func:`rates_scope`: reading rates on (or off) for the rest of it; True when switched.  Outside a
    scope nothing changes (False): a decision never leaks into the caller's later fits."""
    if not _SCOPE.get():
        return False
    _ON.set(bool(on))
    return True


def chip_clock(model: SensorModel) -> str | None:
    """The term that clocks the chips of ``model`` (a sample clock with some period > 0), else None."""
    for name in CLOCK_TERMS:
        if name in model.terms and np.any(model.terms[name].values[:, 0] > 0):
            return name
    return None


def rate_columns(model: SensorModel, ctx, clock: str) -> np.ndarray:
    """(n, K, 6, 6) d reading / d [rho_g, rho_a] of the samples of ``ctx``: R_k^T (age_k - the mean age of the
    clocked chips) in the gyroscope rows (columns 0-2) and the accelerometer rows (columns 3-5); zero on chips
    without a clock."""
    term = model.terms[clock]
    return age_columns(-term.delay(ctx, "gyroscope"), ctx.rot_t, term.values[:, 0] > 0)


def age_columns(age: np.ndarray, rot_t: np.ndarray, on: np.ndarray | None = None) -> np.ndarray:
    """:func:`rate_columns` from the readings' ages (n, K) s and R_k^T (K, 3, 3); ``on`` (K,) the clocked
    chips (default all): the others' columns are zero and their ages are left out of the mean."""
    on = np.ones(age.shape[1], dtype=bool) if on is None else np.asarray(on, dtype=bool)
    centred = np.where(on[None], age - age[:, on].mean(axis=1, keepdims=True), 0.0)
    block = centred[:, :, None, None] * rot_t[None]  # (n, K, 3, 3)
    out = np.zeros(age.shape + (6, RATES))
    out[:, :, 3:, 0:3] = block
    out[:, :, 0:3, 3:6] = block
    return out
