"""Simulated sensor clocks: when each reading of a simulated array was really taken.

Two kinds of array, two clock set-ups:

* **Host-read chips** (the OpenShoe MIMU4444BT): every chip samples on its own
  free-running ~1 kHz oscillator and keeps the latest sample; the host reads all
  chips at 62.5 Hz and stamps the read, so each reading is 0-1 ms older than its
  stamp (the ``sample_clock`` term), and each accelerometer lags its gyroscope
  (``time_offset``).  :func:`mimu_like_clocks` puts such clocks into a sensor
  model (periods and rates: device constants; phases: a session state) and
  :func:`new_session` draws the phases of a new power-up.  Simulate with
  :func:`~imu_array_ros.simulation.simulator.simulate_twist`: every reading is the
  motion at its true sample time.
* **IMUs that stamp their own messages** (one driver and clock per IMU):
  :func:`simulate_own_clocks` gives each IMU's message stream, sampled and
  stamped on its own clock, with the true clock parameters;
  :func:`pair_to_reference` pairs the streams to the reference IMU's stamps
  (nearest stamp) into :class:`~imu_array_ros.model.samples.ImuSamples` with
  ``own_stamps``, the input of the ``stamp_clock`` term.

Clock of IMU k (seconds since ``start_ns``; t the true time since ``start_ns``)::

    c_k(t) = t (1 + eps_k) + o_k

Read on the reference IMU's (IMU 0's) clock, the array's time, IMU k's sample
with own stamp c (no jitter) was taken at ``(1 + r_k) c + b_k`` with
``r_k = (1 + eps_0) / (1 + eps_k) - 1`` and ``b_k = o_0 - (1 + r_k) o_k``
(:meth:`OwnClockStreams.stamp_clock_values`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.motion import TrajectoryFunction, TwistTrajectory
from imu_array_ros.simulation.simulator import as_sensor_model, simulate_measurements

__all__ = ["mimu_like_clocks", "new_session", "OwnClockStreams", "ClockTrajectory", "simulate_own_clocks",
           "pair_to_reference"]


def mimu_like_clocks(model: SensorModel | ArrayDescription, rng: np.random.Generator, *, period: float = 1e-3,
                     rate_ppm: float = 3000.0, acc_lag: float = 1.6e-3, gyro_lag: float = 0.0) -> SensorModel:
    """``model`` with MIMU4444BT-like timing: per-chip sample clocks of ``period`` s with rates uniform in
    +-``rate_ppm`` (device constants), each accelerometer's ``time_offset`` -``acc_lag`` s and each
    gyroscope's -``gyro_lag`` s (replacing the model's time offsets), and the phases of a first session
    (:func:`new_session`).  Each reading is then 0 to ~``period`` s older than its stamp, plus the lags."""
    if not (np.isfinite(period) and period > 0):
        raise ValueError(f"mimu_like_clocks: period must be > 0 s, got {period:g}")
    if not (np.isfinite(rate_ppm) and 0 <= rate_ppm < 1e6):
        raise ValueError(f"mimu_like_clocks: rate_ppm must be in [0, 1e6), got {rate_ppm:g}")
    if not (np.isfinite(acc_lag) and np.isfinite(gyro_lag)):
        raise ValueError(f"mimu_like_clocks: acc_lag and gyro_lag must be finite, got {acc_lag:g}, {gyro_lag:g}")
    model = as_sensor_model(model)
    k = model.n_imus
    clock = np.column_stack([np.full(k, float(period)), rng.uniform(-rate_ppm, rate_ppm, k), np.zeros(k)])
    offsets = np.column_stack([np.full(k, -float(acc_lag)), np.full(k, -float(gyro_lag))])
    return new_session(model.with_terms(sample_clock=clock, time_offset=offsets), rng)


def new_session(model: SensorModel | ArrayDescription, rng: np.random.Generator) -> SensorModel:
    """``model`` with fresh sample-clock phases, uniform in [0, T) with T = period / (1 + rate 1e-6) for every
    IMU with a sample clock (a new power-up); device constants unchanged."""
    model = as_sensor_model(model)
    values = model.terms["sample_clock"].values.copy()
    on = values[:, 0] > 0
    if not on.any():
        raise ValueError("new_session: the model has no sample clock (every sample_clock period is 0)")
    big_t = values[on, 0] / (1.0 + values[on, 1] * 1e-6)
    values[on, 2] = rng.uniform(0.0, 1.0, int(on.sum())) * big_t
    return model.with_terms(sample_clock=values)


@dataclass(frozen=True)
class ClockTrajectory:
    """The true motion as a function of the reference IMU's clock (int64 ns stamps, any shape): what
    ``MotionContext.trajectory`` takes for samples stamped on that clock.  A stamp a is the true time
    t = ((a - start_ns) 1e-9 - o_0) / (1 + eps_0) s since ``start_ns``."""

    function: TrajectoryFunction
    start_ns: int
    rate: float  # eps_0
    offset: float  # o_0, s

    def __call__(self, stamps_ns: np.ndarray):
        c = (np.asarray(stamps_ns, dtype=np.int64) - np.int64(self.start_ns)) * 1e-9
        t = (c - self.offset) / (1.0 + self.rate) + (self.start_ns - self.function.origin_ns) * 1e-9
        return self.function.seconds(t)[:3]


@dataclass(frozen=True)
class OwnClockStreams:
    """Per-IMU message streams of IMUs that sample and stamp on their own clocks (:func:`simulate_own_clocks`).

    names (K,); stamps: K int64 arrays (M,), each message's own stamp, ns: ``start_ns`` + its clock's
    reading at the sample, rounded to ns, + the stamping jitter; accel, gyro: K arrays (M, 3), sensor
    frames.  sample_times: K int64 arrays (M,), the TRUE time of each sample, ns (``start_ns`` + t),
    where the readings were taken (plus the model's own timing delays, e.g. an accelerometer lag).
    truth: the motion as a function of TRUE time, origin ``start_ns``; rates (K,) eps_k and
    offsets (K,) o_k s: the clocks c_k(t) = t (1 + eps_k) + o_k, t and c_k in s since ``start_ns``
    (the reference IMU 0 has its own).  :meth:`reference_trajectory` is the motion on IMU 0's clock.
    """

    names: tuple[str, ...]
    stamps: list[np.ndarray]
    accel: list[np.ndarray]
    gyro: list[np.ndarray]
    sample_times: list[np.ndarray]
    truth: TrajectoryFunction
    rates: np.ndarray
    offsets: np.ndarray
    start_ns: int
    rate_hz: float

    def reference_trajectory(self) -> ClockTrajectory:
        """The true motion as a function of IMU 0's clock (the array's time)."""
        return ClockTrajectory(self.truth, self.start_ns, float(self.rates[0]), float(self.offsets[0]))

    def reference_times(self) -> list[np.ndarray]:
        """K int64 arrays (M,): each sample's true time read on IMU 0's clock, ns (``start_ns`` + c_0(t))."""
        out = []
        for times in self.sample_times:
            t = (times - np.int64(self.start_ns)) * 1e-9
            out.append(self.start_ns + np.round(((1.0 + self.rates[0]) * t + self.offsets[0]) * 1e9).astype(np.int64))
        return out

    def stamp_clock_values(self, first_stamp_ns: int) -> np.ndarray:
        """(K, 2) [offset s, skew ppm] of the ``stamp_clock`` term, relative to IMU 0's clock, for samples whose
        array stamps (IMU 0's stamps) start at ``first_stamp_ns``: offset = b_k + r_k A, skew = r_k 1e6 (A the
        first stamp in s since ``start_ns``; r_k, b_k: module docstring).  The term's delay
        offset + skew 1e-6 t_array then misses r_k (own stamp - array stamp) of the true delay, as the term
        counts its skew over the array stamp, not the IMU's own."""
        r = (1.0 + self.rates[0]) / (1.0 + self.rates) - 1.0
        b = self.offsets[0] - (1.0 + r) * self.offsets
        a = (int(first_stamp_ns) - self.start_ns) * 1e-9
        return np.column_stack([b + r * a, r * 1e6])


def simulate_own_clocks(model: SensorModel | ArrayDescription, rng: np.random.Generator, duration: float,
                        rate_hz: float = 200.0, *, skew_ppm: float = 200.0, offset_s: float = 2e-3,
                        jitter_s: float = 50e-6, rms_rate: float = np.deg2rad(600.0), start_ns: int = 0,
                        reference_ideal: bool = False, noise: bool = True,
                        saturate: bool = True) -> OwnClockStreams:
    """Hand twisting measured by IMUs that each sample and stamp on their own clock (see
    :class:`OwnClockStreams`).

    IMU k's clock c_k(t) = t (1 + eps_k) + o_k with eps_k uniform in +-``skew_ppm`` 1e-6 and o_k uniform in
    +-``offset_s`` (``reference_ideal``: IMU 0's clock is true time, eps_0 = o_0 = 0).  It samples at the
    ticks c = j / ``rate_hz`` (ns-rounded), round(``duration`` ``rate_hz``) samples from its first tick at
    true time >= 0, each at the true time t = (c - o_k) / (1 + eps_k) rounded to ns, and stamps the message
    with c + N(0, ``jitter_s``) (ns).  The readings come from ``model`` (whose ``stamp_clock`` must be at its
    identity: the clocks are drawn here) along the true motion at each sample's true time, exactly
    (``MotionContext.trajectory``); the model's other timing terms (e.g. ``time_offset``) act on top, and
    drifts count from IMU 0's first sample.
    """
    if not (np.isfinite(duration) and duration > 0 and np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"simulate_own_clocks: duration and rate_hz must be > 0, got {duration:g} s, {rate_hz:g} Hz")
    if not all(np.isfinite(v) and v >= 0 for v in (skew_ppm, offset_s, jitter_s)) or skew_ppm >= 1e6:
        raise ValueError(f"simulate_own_clocks: skew_ppm (< 1e6), offset_s and jitter_s must be >= 0, got "
                         f"{skew_ppm:g}, {offset_s:g}, {jitter_s:g}")
    model = as_sensor_model(model)
    if not model.terms["stamp_clock"].is_identity:
        raise ValueError("simulate_own_clocks: the model has a stamp_clock; the clocks are drawn here")
    k, m = model.n_imus, int(round(duration * rate_hz))
    if m < 1:
        raise ValueError(f"simulate_own_clocks: {duration:g} s at {rate_hz:g} Hz gives no sample")
    trajectory = TwistTrajectory.random(rng, rms_rate=rms_rate).function(int(start_ns))
    eps = rng.uniform(-skew_ppm, skew_ppm, k) * 1e-6
    off = rng.uniform(-offset_s, offset_s, k)
    if reference_ideal:
        eps[0] = off[0] = 0.0
    ticks = np.ceil(off * rate_hz).astype(np.int64)[None, :] + np.arange(m)[:, None]  # (M, K)
    clock_ns = np.round(ticks * (1e9 / rate_hz)).astype(np.int64)
    true_ns = int(start_ns) + np.round((clock_ns * 1e-9 - off) / (1.0 + eps) * 1e9).astype(np.int64)
    jitter = np.round(rng.normal(0.0, 1.0, (m, k)) * jitter_s * 1e9).astype(np.int64)
    own = int(start_ns) + clock_ns + jitter
    rows = trajectory.truth(true_ns[:, 0])  # the readings at true_ns: own_stamps of the model's timing stage
    samples = simulate_measurements(model, rows, rng, noise=noise, saturate=saturate, trajectory=trajectory,
                                    own_stamps=true_ns)
    return OwnClockStreams(names=model.names, stamps=[own[:, i] for i in range(k)],
                           accel=[samples.accel[:, i] for i in range(k)], gyro=[samples.gyro[:, i] for i in range(k)],
                           sample_times=[true_ns[:, i] for i in range(k)], truth=trajectory, rates=eps, offsets=off,
                           start_ns=int(start_ns), rate_hz=float(rate_hz))


def pair_to_reference(streams: OwnClockStreams) -> ImuSamples:
    """The streams as array samples on IMU 0's stamps: each IMU's message with the stamp nearest to each of
    IMU 0's (a simple pairing for tests: where two clocks slip by a sample, a message may pair twice or not
    at all).  Array samples where some IMU has no message within half a sample period are left out;
    ``own_stamps`` holds each paired message's stamp."""
    ref = streams.stamps[0]
    half = 0.5e9 / streams.rate_hz
    index, keep = [], np.ones(len(ref), dtype=bool)
    for stamps in streams.stamps:
        order = np.argsort(stamps, kind="stable")
        s = stamps[order]
        i = np.clip(np.searchsorted(s, ref), 1, len(s) - 1)
        nearer = np.where(np.abs(s[i - 1] - ref) <= np.abs(s[i] - ref), i - 1, i)
        keep &= np.abs(s[nearer] - ref) < half
        index.append(order[nearer])
    cols = range(len(streams.stamps))
    own = np.column_stack([streams.stamps[c][index[c]] for c in cols])[keep]
    accel = np.stack([streams.accel[c][index[c]] for c in cols], axis=1)[keep]
    gyro = np.stack([streams.gyro[c][index[c]] for c in cols], axis=1)[keep]
    return ImuSamples(ref[keep], accel, gyro, streams.names, own)
