"""Physics the sensor model cannot describe, added to simulated measurements.

The forward model (:class:`~imu_array_ros.model.sensor_model.SensorModel` and its
term library :mod:`imu_array_ros.model.terms`) assumes a *rigid* array whose
sensors see deterministic functions of the rigid-body motion plus *white*
Gaussian noise.  The effects here break that assumption on purpose, so a
mismatch-discovery tool can be checked to report them as unexplained residual
instead of forcing them into some term:

``vibration`` (:func:`add_vibration`)
    A narrowband structural mode of the board: some sensors (say the outer
    ones) see an extra oscillating acceleration that the others do not.  A
    mode is not rigid-body motion, so no geometry, calibration, time-offset or
    g-sensitivity term reproduces it.

    The mode is modelled as a lightly damped resonance driven by broadband
    noise.  In the narrowband limit that is a carrier at ``f0`` whose complex
    envelope is a complex Ornstein-Uhlenbeck process::

        x(t) = sqrt(2) Re{ z(t) exp(i 2 pi f0 t) },   dz = -gamma z dt + dW,

    i.e. a sinusoid whose amplitude and phase random-walk slowly.  The
    envelope autocorrelation ``exp(-gamma |tau|)`` gives a Lorentzian power
    spectral density centred on ``f0`` with full width at half maximum
    ``B = gamma / pi`` Hz (``bandwidth_hz``); equivalently a mode of damping
    ratio ``zeta = B / (2 f0)`` (quality factor ``f0 / B``).  ``B = 0`` is a
    pure sinusoid of random phase.  ``x`` is scaled to unit RMS *over the
    record* (not only in expectation), so ``amplitude`` is exactly the RMS of
    the added acceleration along ``direction``.

``colored_noise`` (:func:`add_colored_noise`)
    A sensor whose noise is not white: first-order Gauss-Markov noise
    (discrete AR(1), ``e[n] = phi e[n-1] + sqrt(1 - phi^2) sigma w[n]`` with
    ``phi = exp(-dt / tau)``, started in its stationary distribution, so its
    std is ``sigma`` and its lag-1 autocorrelation ``phi``).  It is random, not
    a deterministic function of the motion, so again no term explains it.

Both effects are generated on a uniform time grid at the median sample step
spanning the stamps; each stamp takes the value at its nearest grid point (the
vibration's carrier is evaluated at the exact stamp), so gaps in the stamps are
handled.  A NaN reading stays NaN, and the affected readings are clipped again at
the model's clip level (``acc_clip``/``gyro_clip``).  The input is never modified.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.samples import ImuSamples

__all__ = ["add_vibration", "add_colored_noise", "narrowband_process", "EFFECTS", "SENSOR_KINDS"]

#: ``sensor_kind`` values of :func:`add_colored_noise`.
SENSOR_KINDS = ("accelerometer", "gyroscope")


# --------------------------------------------------------------------------- helpers


def _check_model(samples: ImuSamples, model: SensorModel) -> None:
    if tuple(model.names) != tuple(samples.names):
        raise ValueError(f"the model's IMUs {tuple(model.names)} are not the samples' IMUs {samples.names}")


def _sensor_index(names: tuple[str, ...], sensor) -> int:
    """Index of an IMU given by name or index."""
    if isinstance(sensor, (int, np.integer)) and not isinstance(sensor, bool):
        k = int(sensor)
        if not -len(names) <= k < len(names):
            raise ValueError(f"IMU index {k} out of range (the array has {len(names)} IMUs)")
        return k % len(names)
    if isinstance(sensor, str):
        try:
            return names.index(sensor)
        except ValueError:
            raise ValueError(f"unknown IMU {sensor!r} (known: {', '.join(names)})") from None
    raise TypeError(f"an IMU is given by name or index, not {type(sensor).__name__}")


def _sensor_indexes(names: tuple[str, ...], sensors) -> np.ndarray:
    """Sorted unique indexes of IMUs given by a name, an index, or an iterable of either."""
    if isinstance(sensors, (str, int, np.integer)):
        sensors = [sensors]
    idx = sorted({_sensor_index(names, s) for s in sensors})
    if not idx:
        raise ValueError("no IMU given")
    return np.asarray(idx, dtype=int)


def _grid(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Time since the first stamp t (N,) s, the nearest uniform grid index (N,) and the grid step dt (s)."""
    if len(stamps) < 2:
        raise ValueError(f"{len(stamps)} samples: at least 2 are needed to define a sample rate")
    step = np.diff(stamps)
    if np.any(step <= 0):
        raise ValueError("the stamps are not strictly increasing")
    t = (stamps - stamps[0]) * 1e-9
    dt = float(np.median(step)) * 1e-9
    return t, np.rint(t / dt).astype(np.int64), dt


def _ar1(n: int, phi: float, size: int, rng: np.random.Generator) -> np.ndarray:
    """(n, size) stationary unit-variance AR(1) sequences with coefficient ``phi`` (real), along axis 0."""
    w = rng.normal(size=(n, size))
    start = rng.normal(size=size)  # the state before the first sample, drawn from the stationary law
    return lfilter([np.sqrt(1.0 - phi * phi)], [1.0, -phi], w, axis=0, zi=(phi * start)[None, :])[0]


def _add(samples: ImuSamples, model: SensorModel, kind: str, k: np.ndarray, added: np.ndarray) -> ImuSamples:
    """New samples with ``added`` (N, len(k), 3) on the ``kind`` readings of IMUs ``k``, clipped again."""
    accel, gyro = samples.accel.copy(), samples.gyro.copy()
    target, clip = (accel, model.acc_clip) if kind == "accelerometer" else (gyro, model.gyro_clip)
    target[:, k] = np.clip(target[:, k] + added, -clip, clip)  # NaN + x = NaN, and clip keeps NaN
    return ImuSamples(samples.stamps.copy(), accel, gyro, samples.names)


# --------------------------------------------------------------------------- effects


def narrowband_process(stamps: np.ndarray, frequency_hz: float, bandwidth_hz: float,
                       rng: np.random.Generator) -> np.ndarray:
    """(N,) the unit-RMS narrowband process x(t) of :func:`add_vibration` at ``stamps`` (N,) int64 ns."""
    t, idx, dt = _grid(np.asarray(stamps, dtype=np.int64))
    if not 0.0 < frequency_hz < 0.5 / dt:
        raise ValueError(f"frequency_hz={frequency_hz:g} must lie in (0, {0.5 / dt:g}) Hz "
                         f"(the Nyquist frequency of the samples)")
    if not bandwidth_hz >= 0.0:
        raise ValueError(f"bandwidth_hz={bandwidth_hz:g} must be >= 0")
    phi = np.exp(-np.pi * bandwidth_hz * dt)           # envelope AR(1) coefficient, gamma = pi B
    env = _ar1(int(idx[-1]) + 1, phi, 2, rng)[idx]      # (N, 2): real and imaginary part of z
    z = (env[:, 0] + 1j * env[:, 1]) / np.sqrt(2.0)     # E|z|^2 = 1
    x = np.sqrt(2.0) * np.real(z * np.exp(2j * np.pi * frequency_hz * t))
    return x / np.sqrt(np.mean(x * x))


def add_vibration(samples: ImuSamples, model: SensorModel, *, sensors, frequency_hz: float, amplitude: float,
                  direction=(0.0, 0.0, 1.0), rng: np.random.Generator, bandwidth_hz: float = 0.5) -> ImuSamples:
    """Samples with a narrowband board vibration mode added to some accelerometers (a new object).

    The IMUs ``sensors`` (names or indexes) all see the array-frame acceleration
    ``amplitude * x(t) * direction`` (m/s^2; ``direction`` (3,) is normalised),
    mapped to each sensor frame with ``model.rotations[k].T``; the other IMUs and
    every gyroscope are untouched.  x(t) (:func:`narrowband_process`) is unit RMS
    over the record with a Lorentzian spectrum centred on ``frequency_hz`` of full
    width ``bandwidth_hz`` (Hz).  NaN readings stay NaN; the result is clipped at
    ``model.acc_clip``.
    """
    _check_model(samples, model)
    k = _sensor_indexes(samples.names, sensors)
    d = np.asarray(direction, dtype=float).reshape(3)
    norm = np.linalg.norm(d)
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f"direction {tuple(d)} is not a finite non-zero vector")
    if not (np.isfinite(amplitude) and amplitude >= 0):
        raise ValueError(f"amplitude={amplitude} must be finite and >= 0 (m/s^2)")
    x = narrowband_process(samples.stamps, frequency_hz, bandwidth_hz, rng)
    in_sensor = np.einsum("kij,i->kj", np.asarray(model.rotations, dtype=float)[k], d / norm)  # R_k^T d, (len(k), 3)
    added = amplitude * x[:, None, None] * in_sensor[None, :, :]
    return _add(samples, model, "accelerometer", k, added)


def add_colored_noise(samples: ImuSamples, model: SensorModel, *, sensor, correlation_time_s: float,
                      std_ratio: float = 1.0, sensor_kind: str = "accelerometer",
                      rng: np.random.Generator) -> ImuSamples:
    """Samples with first-order Gauss-Markov noise added to one IMU's accelerometer or gyroscope (a new object).

    Every axis a of the triad of ``sensor`` (name or index) gets an independent
    AR(1) sequence with coefficient ``exp(-dt / correlation_time_s)`` (dt the median
    sample step, s) and stationary std ``std_ratio * model.acc_std[k, a]`` (m/s^2) or
    ``model.gyro_std[k, a]`` (rad/s), per ``sensor_kind`` ("accelerometer" or
    "gyroscope").  NaN readings stay NaN; the result is clipped at the model's clip level.
    """
    _check_model(samples, model)
    if sensor_kind not in SENSOR_KINDS:
        raise ValueError(f"sensor_kind={sensor_kind!r} must be one of {SENSOR_KINDS}")
    if not (np.isfinite(correlation_time_s) and correlation_time_s > 0):
        raise ValueError(f"correlation_time_s={correlation_time_s} must be finite and > 0 (s)")
    if not (np.isfinite(std_ratio) and std_ratio >= 0):
        raise ValueError(f"std_ratio={std_ratio} must be finite and >= 0")
    k = _sensor_index(samples.names, sensor)
    _, idx, dt = _grid(samples.stamps)
    std = (model.acc_std if sensor_kind == "accelerometer" else model.gyro_std)[k]
    e = _ar1(int(idx[-1]) + 1, float(np.exp(-dt / correlation_time_s)), 3, rng)[idx]  # (N, 3), unit variance
    added = (e * (std_ratio * np.asarray(std, dtype=float)))[:, None, :]
    return _add(samples, model, sensor_kind, np.array([k]), added)


#: name -> function, for tools that select effects by name.
EFFECTS = {"vibration": add_vibration, "colored_noise": add_colored_noise}
