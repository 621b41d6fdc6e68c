"""Noise characterisation: the Allan deviation of every IMU and axis on the still intervals of a recording.

IEEE Std 952-1997 Annex C / IEEE Std 1293-1998 (El-Sheimy, Hou and Niu 2008, "Analysis and modeling of
inertial sensors using Allan variance").  Steps (:func:`characterise_noise`):

1. Still intervals: :func:`~imu_array_ros.calibration.still.find_still_poses` (gyroscope- and
   accelerometer-based stillness, drifting and accelerating rests rejected), keeping those of
   ``min_interval_s`` (default :data:`MIN_INTERVAL_S`, 5 s) or more after trimming.  Each IMU's readings on
   them are cut where a reading is missing or saturated or the stamps jump, into *segments*.
2. Overlapping Allan variance (``allantools.oadev``, frequency data at the recording's rate) of each
   segment and axis at octave-spaced averaging times tau = m / rate, m = 1, 2, 4, ...; pooled per tau over
   the segments as the mean of the Allan *variances* weighted by their number of terms.  Equivalent
   degrees of freedom: the sum over the segments of Greenhall's edf (``allantools.edf_greenhall``).
3. The tau range: from the first tau where the deviation falls with slope -1/2 (local slope <= -0.4,
   mean over the three axes: below it the chip's low-pass filter shows) up to the longest tau with at
   least :data:`MIN_EDF` degrees of freedom.
4. Weighted non-negative least squares of AVAR(tau) = N^2 / tau + F + K^2 tau / 3 over that range
   (weights: edf / (2 AVAR^2), AVAR^2 the model's, edf for the noise that dominates the model at that
   tau; three passes; the standard deviations are scaled by sqrt(chi^2 per degree of freedom) when the model
   fits worse than the noise; they treat the octave-spaced taus as independent, which they are not quite:
   on simulated white noise + random walk the errors are 1.2-1.6 times the stated std, RMS, test_noise.py).
   Reported per axis:

   * white noise: N (unit/sqrt(Hz), slope -1/2), written as ``noise_std`` = N sqrt(rate), the std per
     sample of the white noise at the recording's rate, with its standard deviation;
   * bias random walk: K (unit/sqrt(s), sigma(tau) = K sqrt(tau/3), slope +1/2) only where the +1/2 slope
     is seen: the K^2 tau/3 part is the largest of the three at the longest tau and K^2 is at least
     :data:`RW_SIGNIFICANCE` standard deviations above 0; otherwise not written (NaN: too short to see);
   * bias instability: B = min sigma / 0.664 (the pooled deviation's minimum over the range) where the
     minimum is seen: the fitted curve has its minimum inside the range (sqrt(3 N^2 / K^2) <= longest tau)
     or is flat at its end (F >= N^2 / tau_max); otherwise only the bound min sigma / 0.664 is recorded.

What the still intervals of a calibration capture show: 20 rests of ~22 s at 62.5 Hz reach tau ~ 8 s,
enough for N; the random walk needs rests of minutes (docs/noise.md).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from scipy.optimize import nnls

from imu_array_ros.calibration.result import Calibration, provenance
from imu_array_ros.calibration.still import find_still_poses
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.util.extras import require

__all__ = ["characterise_noise", "noise_calibration", "NoiseResult", "SensorNoise", "NoiseCalibration",
           "pooled_allan", "fit_allan", "MIN_INTERVAL_S", "MIN_EDF", "RW_SIGNIFICANCE", "B_FACTOR", "SENSORS"]

#: default shortest still interval used, s (after trimming): 5 s at 62.5 Hz reach tau ~ 1.6 s
MIN_INTERVAL_S = 5.0
#: a tau is used when the pooled equivalent degrees of freedom reach this (sigma known to ~1/sqrt(2 edf))
MIN_EDF = 4.0
#: the random walk is written when K^2 is this many standard deviations above 0
RW_SIGNIFICANCE = 2.0
#: sigma(tau) at the flicker floor = B sqrt(2 ln 2 / pi) = 0.664 B (IEEE Std 952)
B_FACTOR = 0.664
#: slope of log sigma below which the white noise is reached (the tau range starts there)
WHITE_SLOPE = -0.4
#: the sensors and their units
SENSORS = {"accelerometer": "m/s^2", "gyroscope": "rad/s"}
_MIN_SEGMENT = 8  # samples: shorter pieces between gaps are left out
_ALPHAS = (0, -1, -2)  # frequency-noise exponents of the white, flicker and random-walk terms


@dataclass
class SensorNoise:
    """One sensor (triad) of one IMU: the pooled Allan deviation and what was read from it.

    taus (T,) s; adev (T, 3) pooled Allan deviation per axis; terms (T,) Allan terms summed over the
    segments; edf (3, T) equivalent degrees of freedom for white, flicker, random-walk noise; used (T,)
    the tau range fitted; coef (3, 3) per axis [N^2, F, K^2/3] and coef_std; noise_density (3,) N
    unit/sqrt(Hz) and its std; noise_std (3,) N sqrt(rate) and its std; random_walk (3,) K unit/sqrt(s)
    (NaN: no +1/2 slope seen) and its std; instability (3,) B (NaN: no minimum seen); instability_bound
    (3,) min sigma / 0.664 always; per_sample_std (3,) the segments' std (mean removed); seconds of data.
    """

    taus: np.ndarray
    adev: np.ndarray
    terms: np.ndarray
    edf: np.ndarray
    used: np.ndarray
    coef: np.ndarray
    coef_std: np.ndarray
    rate: float
    per_sample_std: np.ndarray
    seconds: float
    segments: int

    @property
    def tau_range(self) -> tuple[float, float]:
        t = self.taus[self.used]
        return (float(t[0]), float(t[-1])) if len(t) else (float("nan"), float("nan"))

    @property
    def noise_density(self) -> np.ndarray:
        return np.sqrt(self.coef[:, 0])

    @property
    def noise_density_std(self) -> np.ndarray:
        return self.coef_std[:, 0] / (2 * np.maximum(self.noise_density, 1e-300))

    @property
    def noise_std(self) -> np.ndarray:
        return self.noise_density * np.sqrt(self.rate)

    @property
    def noise_std_std(self) -> np.ndarray:
        return self.noise_density_std * np.sqrt(self.rate)

    @property
    def random_walk_seen(self) -> np.ndarray:
        """(3,) the +1/2 slope is seen: K^2 tau/3 the largest part at the longest tau, and significant."""
        a, f, c = self.coef.T
        t = self.tau_range[1]
        return (c > 0) & (c * t >= a / t + f) & (c >= RW_SIGNIFICANCE * self.coef_std[:, 2])

    @property
    def random_walk(self) -> np.ndarray:
        return np.where(self.random_walk_seen, np.sqrt(3 * self.coef[:, 2]), np.nan)

    @property
    def random_walk_std(self) -> np.ndarray:
        k = np.sqrt(3 * self.coef[:, 2])
        return np.where(self.random_walk_seen, 1.5 * self.coef_std[:, 2] / np.maximum(k, 1e-300), np.nan)

    @property
    def instability_bound(self) -> np.ndarray:
        return np.nanmin(np.where(self.used[:, None], self.adev, np.nan), axis=0) / B_FACTOR

    @property
    def instability_seen(self) -> np.ndarray:
        """(3,) the minimum of the deviation is inside the range, or the curve is flat at its end."""
        a, f, c = self.coef.T
        t = self.tau_range[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            inside = (c > 0) & (np.sqrt(3 * a / np.where(c > 0, c, 1.0)) <= t)
        return inside | ((f > 0) & (f >= a / t))

    @property
    def instability(self) -> np.ndarray:
        return np.where(self.instability_seen, self.instability_bound, np.nan)


@functools.lru_cache(maxsize=4096)
def _edf(alpha: int, m: int, n: int) -> float:
    """Greenhall's edf of the overlapping Allan variance at averaging factor m of n frequency samples."""
    import allantools

    return float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n + 1, overlapping=True))


def pooled_allan(segments: list[np.ndarray], rate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Overlapping Allan variance of ``segments`` (each (L_i, 3), one axis a column, at ``rate`` Hz) pooled per
    octave tau.  Returns taus (T,) s, avar (T, 3), terms (T,) and edf (3, T) (white, flicker, random walk)."""
    import allantools

    longest = max(len(s) for s in segments)
    ms = 2 ** np.arange(int(np.floor(np.log2(max((longest - 1) // 2, 1)))) + 1)
    t = len(ms)
    num, terms, edf = np.zeros((t, 3)), np.zeros(t), np.zeros((len(_ALPHAS), t))
    for seg in segments:
        for axis in range(3):
            taus, dev, _, ns = allantools.oadev(seg[:, axis], rate=rate, data_type="freq", taus=ms / rate)
            idx = np.searchsorted(ms, np.rint(np.asarray(taus) * rate).astype(int))
            num[idx, axis] += np.asarray(ns) * np.asarray(dev) ** 2
            if axis == 0:
                terms[idx] += ns
                for j, alpha in enumerate(_ALPHAS):
                    edf[j, idx] += [_edf(alpha, int(m), len(seg)) for m in ms[idx]]
    keep = terms > 0
    return ms[keep] / rate, num[keep] / terms[keep, None], terms[keep], edf[:, keep]


def fit_allan(taus: np.ndarray, avar: np.ndarray, edf: np.ndarray, passes: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Weighted NNLS of avar (T,) = N^2/tau + F + K^2 tau/3 (module docstring); edf (3, T).  Returns
    [N^2, F, K^2/3] and their standard deviations (0 for a coefficient at its bound; scaled by
    sqrt(max(1, chi^2 / dof)))."""
    a = np.column_stack([1 / taus, np.ones_like(taus), taus])
    model = np.asarray(avar, dtype=float)
    coef = np.zeros(3)
    for _ in range(passes):
        dominant = np.argmax(a * np.maximum(coef, 0), axis=1) if coef.any() else np.zeros(len(taus), int)
        dof = edf[dominant, np.arange(len(taus))]
        w = np.sqrt(dof / 2) / np.maximum(model, 1e-300)
        coef, _ = nnls(a * w[:, None], avar * w)
        model = a @ coef
    free = coef > 0
    std = np.zeros(3)
    if free.any():
        aw = a[:, free] * w[:, None]
        dof = len(taus) - int(free.sum())
        chi2 = float(np.sum(((avar - model) * w) ** 2)) / dof if dof > 0 else 1.0
        std[free] = np.sqrt(np.diag(np.linalg.pinv(aw.T @ aw)) * max(1.0, chi2))
    return coef, std


def _tau_range(taus: np.ndarray, adev: np.ndarray, edf: np.ndarray) -> np.ndarray:
    """(T,) taus fitted: from the first where the mean local slope over the axes is <= WHITE_SLOPE up to the
    last with at least MIN_EDF (white-noise) degrees of freedom."""
    ok = edf[0] >= MIN_EDF
    used = np.zeros(len(taus), bool)
    if not ok.any():
        return used
    hi = int(np.flatnonzero(ok)[-1])
    slope = np.mean(np.diff(np.log(adev), axis=0), axis=1) / np.diff(np.log(taus)) if len(taus) > 1 else np.zeros(0)
    white = np.flatnonzero(slope[:hi] <= WHITE_SLOPE)
    lo = int(white[0]) if len(white) else 0
    used[lo:hi + 1] = True
    return used


def _segments(valid: np.ndarray, values: np.ndarray, intervals: np.ndarray, breaks: np.ndarray) -> list[np.ndarray]:
    """Runs of ``valid`` (N,) inside ``intervals`` (P, 2), cut where ``breaks`` (N,) (a stamp jump before the
    sample), of at least _MIN_SEGMENT samples: the (L, 3) rows of ``values``."""
    inside = np.zeros(len(valid) + 1, dtype=np.int8)
    np.add.at(inside, intervals[:, 0], 1)
    np.add.at(inside, intervals[:, 1], -1)
    mask = (np.cumsum(inside[:-1]) > 0) & valid
    start = mask & (~np.concatenate([[False], mask[:-1]]) | breaks)
    stop = mask & (~np.concatenate([mask[1:], [False]]) | np.concatenate([breaks[1:], [False]]))
    return [values[a:b + 1] for a, b in zip(np.flatnonzero(start), np.flatnonzero(stop)) if b + 1 - a >= _MIN_SEGMENT]


@dataclass
class NoiseResult:
    """The noise of every IMU: names (K,); sensors: sensor -> K :class:`SensorNoise` (None: no data);
    rate Hz; still intervals used (P, 2) and their seconds; settings of the still detection."""

    names: tuple[str, ...]
    sensors: dict[str, list[SensorNoise | None]]
    rate: float
    intervals: np.ndarray
    still_seconds: float
    settings: dict = field(default_factory=dict)

    def figures(self, name: str) -> dict[str, np.ndarray]:
        """The description's noise figures of IMU ``name`` (``"<sensor>.<figure>"`` -> (3,))."""
        k = self.names.index(name)
        out = {}
        for sensor, per_imu in self.sensors.items():
            s = per_imu[k]
            if s is not None:
                out.update({f"{sensor}.noise_std": s.noise_std, f"{sensor}.bias_random_walk": s.random_walk,
                            f"{sensor}.bias_instability": s.instability})
        return out

    def record(self) -> dict:
        """The ``calibration:`` record: method, tau ranges, still seconds per IMU, per IMU/axis results."""
        lst = lambda v: [float(x) if np.isfinite(x) else None for x in v]  # noqa: E731
        imus = {}
        for k, name in enumerate(self.names):
            entry: dict = {}
            for sensor, per_imu in self.sensors.items():
                s = per_imu[k]
                if s is None:
                    entry[sensor] = "no still data"
                    continue
                entry.setdefault("still_seconds", round(s.seconds, 3))
                entry[sensor] = {
                    "tau_range_s": lst(s.tau_range), "segments": s.segments,
                    "noise_density": lst(s.noise_density), "noise_std": lst(s.noise_std),
                    "noise_std_std": lst(s.noise_std_std), "per_sample_std": lst(s.per_sample_std),
                    "bias_random_walk": lst(s.random_walk), "bias_random_walk_std": lst(s.random_walk_std),
                    "bias_instability": lst(s.instability), "bias_instability_bound": lst(s.instability_bound),
                }
            imus[name] = entry
        return {
            "method": "noise: overlapping Allan deviation (allantools) of the still intervals, Allan variances "
                      "pooled per octave tau weighted by their number of terms; weighted NNLS of "
                      "AVAR = N^2/tau + F + K^2 tau/3 over tau_range_s; noise_std = N sqrt(rate); bias_random_walk "
                      "= K where the +1/2 slope is seen (null: not seen within tau_range_s); bias_instability = "
                      "min sigma / 0.664 where the minimum is seen (bias_instability_bound: that value always)",
            **provenance(),
            "rate_hz": float(self.rate),
            "still_intervals": int(len(self.intervals)),
            "still_seconds": round(float(self.still_seconds), 3),
            "min_interval_s": float(self.settings.get("min_duration_s", MIN_INTERVAL_S)),
            "units": {"noise_std": "m/s^2, rad/s", "noise_density": "unit/sqrt(Hz)",
                      "bias_random_walk": "unit/sqrt(s)", "bias_instability": "unit"},
            "imus": imus,
        }

    def summary(self) -> str:
        parts = []
        for sensor, unit in SENSORS.items():
            fits = [s for s in self.sensors[sensor] if s is not None]
            if not fits:
                continue
            ns = np.concatenate([s.noise_std for s in fits])
            rw = sum(int(np.isfinite(s.random_walk).sum()) for s in fits)
            bi = sum(int(np.isfinite(s.instability).sum()) for s in fits)
            lo = min(s.tau_range[0] for s in fits)
            hi = max(s.tau_range[1] for s in fits)
            parts.append(f"{sensor} noise_std {ns.min():.3g}-{ns.max():.3g} {unit} (tau {lo:.3g}-{hi:.3g} s), random "
                         f"walk seen on {rw} of {3 * len(fits)} axes, bias instability on {bi}")
        return (f"noise of {len(self.names)} IMUs from {len(self.intervals)} still intervals "
                f"({self.still_seconds:.0f} s at {self.rate:.4g} Hz): " + "; ".join(parts))


def characterise_noise(samples: ImuSamples, model: SensorModel, *, min_interval_s: float = MIN_INTERVAL_S,
                       still_options: dict | None = None, gravity: float = STANDARD_GRAVITY,
                       progress: Callable[[str], None] | None = None) -> NoiseResult:
    """The Allan deviation of every IMU and axis on the still intervals of ``samples`` (raw readings, sensor
    frames) and the figures read from it (module docstring).  ``still_options``: keywords of
    :func:`find_still_poses` (``min_duration_s`` there overrides ``min_interval_s``).  CalibrationError
    (one line) when no still interval is long enough."""
    require("allantools", "noise", "the noise calibration")
    say = progress or (lambda text: None)
    options = {"min_duration_s": min_interval_s, **(still_options or {})}
    poses = find_still_poses(samples, model, gravity=gravity, **options)
    st = poses.settings
    if not len(poses):
        need = st["min_duration_s"] + 2 * (st["settle_s"] + 0.5 * st["window_s"])
        why = sorted({r[2].split(":")[0] for r in poses.rejected})
        raise CalibrationError(
            f"no still interval of {st['min_duration_s']:g} s or more (after trimming) found "
            f"({len(poses.rejected)} rejected{': ' + ', '.join(why) if why else ''}): the noise calibration needs "
            f"the array held still for "
            f"{np.ceil(need * 10) / 10:g} s or more at least once (minutes to see the bias random walk)")
    stamps = samples.stamps
    dt = np.diff(stamps) * 1e-9
    step = float(np.median(dt))
    rate = 1.0 / step
    breaks = np.concatenate([[False], dt > 1.5 * step])
    valid = model.valid(samples.accel, samples.gyro)  # (N, K, 6)
    still_s = float(np.sum(poses.intervals[:, 1] - poses.intervals[:, 0]) * step)
    say(f"still intervals: {len(poses)} of {st['min_duration_s']:g} s or more ({still_s:.0f} s at {rate:.4g} Hz)")
    sensors: dict[str, list[SensorNoise | None]] = {s: [] for s in SENSORS}
    for k, name in enumerate(model.names):
        for j, (sensor, data) in enumerate((("accelerometer", samples.accel), ("gyroscope", samples.gyro))):
            segs = _segments(valid[:, k, 3 * j:3 * j + 3].all(axis=1), data[:, k], poses.intervals, breaks)
            sensors[sensor].append(_sensor_noise(segs, rate) if segs else None)
        say(f"{name}: Allan deviation of {sum(len(s) for s in segs) * step:.0f} s of still data")
    return NoiseResult(names=tuple(model.names), sensors=sensors, rate=rate, intervals=poses.intervals,
                       still_seconds=still_s, settings=dict(st))


def _sensor_noise(segs: list[np.ndarray], rate: float) -> SensorNoise | None:
    taus, avar, terms, edf = pooled_allan(segs, rate)
    adev = np.sqrt(avar)
    used = _tau_range(taus, adev, edf)
    if used.sum() < 2:
        return None
    fits = [fit_allan(taus[used], avar[used, axis], edf[:, used]) for axis in range(3)]
    n = sum(len(s) for s in segs)
    dev = np.concatenate([s - s.mean(axis=0) for s in segs])
    per_sample = np.sqrt((dev ** 2).sum(axis=0) / max(n - len(segs), 1))
    return SensorNoise(taus=taus, adev=adev, terms=terms, edf=edf, used=used,
                       coef=np.array([f[0] for f in fits]), coef_std=np.array([f[1] for f in fits]), rate=rate,
                       per_sample_std=per_sample, seconds=n / rate, segments=len(segs))


@dataclass
class NoiseCalibration(Calibration):
    """A :class:`Calibration` whose :meth:`apply` also writes each IMU's noise figures (``noise``: IMU name ->
    ``"<sensor>.<figure>"`` -> (3,); an IMU's previous figures are replaced).  A figure measured and not seen
    on any axis (a bias random walk the still intervals were too short to show) is written too, all ``null``:
    the file then says the noise calibration looked for it (``export kalibr`` tells that apart from a
    description never noise-calibrated)."""

    noise: dict = field(default_factory=dict)

    def apply(self, desc: ArrayDescription) -> ArrayDescription:
        out = super().apply(desc)
        imus = []
        for imu in out.imus:
            new = self.noise.get(imu.name)
            if new is None:
                imus.append(imu)
                continue
            kept = {k: v for k, v in imu.noise.items() if k.split(".")[0] not in {n.split(".")[0] for n in new}}
            figures = {k: np.asarray(v, dtype=float) for k, v in new.items()}
            imus.append(replace(imu, noise={**kept, **figures}))
        return out.with_imus(imus)


def noise_calibration(samples: ImuSamples, model: SensorModel, *, min_interval_s: float = MIN_INTERVAL_S,
                      still_options: dict | None = None, gravity: float = STANDARD_GRAVITY,
                      progress: Callable[[str], None] | None = None, source: str | None = None) -> Calibration:
    """``calibrate noise``: :func:`characterise_noise`, as a :class:`Calibration` whose model has each IMU's
    ``noise_std`` (IMUs without still data keep theirs) and which writes every figure into the description.
    Not scored: a description on file is always replaced (kept as ``.bak``)."""
    result = characterise_noise(samples, model, min_interval_s=min_interval_s, still_options=still_options,
                                gravity=gravity, progress=progress)
    acc, gyro = model.acc_std.copy(), model.gyro_std.copy()
    for std, sensor in ((acc, "accelerometer"), (gyro, "gyroscope")):
        for k, s in enumerate(result.sensors[sensor]):
            if s is not None:
                std[k] = s.noise_std
    record = result.record()
    if source is not None:
        record["recording"] = str(source)
    noise = {name: result.figures(name) for name in result.names}
    return NoiseCalibration(method="noise", model=replace(model, acc_std=acc, gyro_std=gyro), std={}, record=record,
                            data="still intervals", summary_line=result.summary(), details=result, noise=noise)
