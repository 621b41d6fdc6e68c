"""Still intervals / static poses of a multi-pose calibration session (nilsson2014 Sec. III).

:func:`find_still_poses` finds where the array rests (e.g. on each face of an
icosahedron), averages every IMU's raw readings over each rest and reports the
poses and what it rejected; :func:`check_poses` says whether the poses can
calibrate the accelerometer model (nilsson2014: at least 12 non-coplanar
orientations for gain, bias, non-orthogonality and misalignment, 9 without
misalignment).

Detection (vectorised, cumulative sums; 600 s at 62.5 Hz x 8 IMUs in ~0.2 s on 2 shared cores):

1. For every window of ``window_s`` (default 1 s) and every IMU, the *total*
   sample standard deviation of each triad, sqrt(sum over the axes of the
   variance); rotation-invariant, so top and underside IMUs compare alike, and
   blind to the (constant) gyroscope biases of up to a few deg/s.  A window of an
   IMU with fewer than half its samples finite is ignored.
2. The median over the IMUs (a missing or faulty IMU cannot hide or fake motion).
3. A sample is still when both medians of the window centred on it are below
   their thresholds; runs of still samples are the *still candidates* (a candidate
   ends half a window before the motion is seen, and an abrupt change splits two
   rests by a window).  Everything else is the moving phase.  With the defaults a
   rest loses 0.75 s at each end (half the 1 s window, then ``settle_s`` 0.25 s):
   the simulator's default 3 s rests keep ~1.6 s, more than ``min_duration_s`` (1 s).
4. Each candidate is trimmed by ``settle_s`` at both ends (settling after the
   hand lets go / before it grabs), then averaged per IMU, and rejected when it
   is too short, holds a saturated reading, has no usable IMU, its specific force
   is not gravity (> ``gravity_tolerance`` off: the array was accelerating), or
   it drifts (see below).

Default thresholds (``gyro_threshold`` / ``accel_threshold`` None):
``NOISE_FACTOR`` (2) x the median over the IMUs of the model's total white-noise
std sqrt(sum sigma_axis^2), floored at ``GYRO_FLOOR`` = 0.005 rad/s (0.29 deg/s)
and ``ACCEL_FLOOR`` = 0.03 m/s^2 (noise-free simulations, quantised readings).
The statistic under pure noise is about the total std (its spread over a 1 s
window is ~5 %, less after the median), so a factor of 2 leaves a wide margin
while a rest-to-motion change shows at once: MPU-9150 (array32.yaml: 0.04 m/s^2,
0.06 deg/s per axis) -> 0.139 m/s^2, 0.005 rad/s (floor); MIMU4444BT captures
(mimu4444bt_corners.yaml: 0.045 m/s^2, 0.0039 rad/s) -> 0.156 m/s^2, 0.0135 rad/s,
where the measured rest statistics are 0.068 m/s^2 and 0.0058 rad/s (99.9th percentile
0.085, 0.0068) and every handling motion peaks above 2.9 m/s^2 and 0.6 rad/s.

Drift: each axis's mean over the first and second half of the interval,
z = |m1 - m2| / (s sqrt(1/n1 + 1/n2)) with s the larger of the within-interval
std and the model's noise std; per IMU the largest z over its six axes; the pose
drifts when the median over the IMUs exceeds ``drift_sigma`` (default 6) for
differences above a floor that matters for a calibration (``DRIFT_FLOOR_ACCEL``
0.02 m/s^2 ~ 0.1 deg of tilt, ``DRIFT_FLOOR_GYRO`` 0.002 rad/s).  On the real
captures' 20 s rests this median z is 1.4 (median) to 4.6 (largest) before the
floors (bias wander, colored noise), 0 after them; a 3 deg creep over a 3 s rest
gives z ~ 40.  Gravity: |mean over the IMUs of R_k mean(accel_k)| (nominal R_k;
the uncalibrated biases largely cancel) is within -1.0 % .. +1.5 % of g on every
real rest, against the 5 % tolerance.

Real data (``../shared/data/openshoe_mimu4444bt``, config/mimu4444bt_corners.yaml, defaults,
~0.2 s per capture).  The README says "about 20" poses then hand twisting: every capture has
exactly 20 rests before the twisting, spread like the faces of an icosahedron (ideal: smallest
eigenvalue 1/3, coverage 37.4 deg, closest pair 41.8 deg); some recordings end with the array
set down again after the twisting (extra poses, same direction as an earlier one)::

    capture  poses  before twist  after twist      rejected (short)  rest s     min eig  coverage  closest
    exp_1    21     20            1 (1.2 s)        0                 20.9-27.0  0.331    37.7 deg  40.4 deg
    exp_2    22     20            2 (3.7, 6.5 s)   1                 21.6-32.1  0.332    37.8 deg  40.3 deg
    exp_3    21     20            1 (2.6 s)        0                 21.1-31.1  0.332    38.0 deg  40.3 deg
    exp_4    20     20            0                2                 21.8-28.8  0.330    37.8 deg  40.4 deg
    exp_5    20     20            0                1                 21.1-29.8  0.332    37.6 deg  40.4 deg
    exp_6    20     20            0                1                 21.4-26.5  0.332    37.6 deg  40.4 deg

(rest durations, eigenvalue, coverage and closest pair over the 20 rests before the twisting;
the rejected candidates are pauses shorter than a second, around the twisting.)
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel

__all__ = ["StillPoses", "find_still_poses", "check_poses", "NOISE_FACTOR", "GYRO_FLOOR", "ACCEL_FLOOR",
           "MIN_EIGENVALUE", "POSES_FULL_MODEL", "POSES_WITHOUT_MISALIGNMENT"]

#: Default thresholds are this many times the model's total white-noise std (median over IMUs).
NOISE_FACTOR = 2.0
#: Lowest default gyroscope threshold, rad/s (total std over a window).
GYRO_FLOOR = 0.005
#: Lowest default accelerometer threshold, m/s^2 (total std over a window).
ACCEL_FLOOR = 0.03
#: Drift floors: a first-half / second-half difference below these never rejects a pose.
DRIFT_FLOOR_ACCEL = 0.02
DRIFT_FLOOR_GYRO = 0.002
#: An IMU with fewer valid samples than this fraction of the trimmed interval is missing in that pose.
MIN_VALID_FRACTION = 0.5
#: check_poses: smallest eigenvalue of mean(d d^T) below this -> clustered / coplanar (1/3 when even).
MIN_EIGENVALUE = 0.05
#: nilsson2014 Sec. II: orientations needed for the full accelerometer model / without misalignment.
POSES_FULL_MODEL = 12
POSES_WITHOUT_MISALIGNMENT = 9


@dataclass
class StillPoses:
    """Static poses found in a recording (P poses, K IMUs, N samples); see the module docstring.

    intervals (P, 2) sample index [start, stop) after trimming; stamps (P, 2) int64 ns of the
    first and last sample; accel, gyro (P, K, 3) mean raw readings (sensor frames; NaN: the IMU
    is missing in that pose); accel_std, gyro_std (P, K, 3) within-interval sample std per axis;
    counts (P, K) samples averaged; directions (P, 3) unit specific-force direction in the array
    frame (nominal rotations, mean over the IMUs); rejected: (start, stop, reason) of the still
    candidates not kept; still (N,) samples inside accepted intervals; moving (N,) samples in no
    still candidate; names (K,); settings: the thresholds used.
    """

    intervals: np.ndarray
    stamps: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    accel_std: np.ndarray
    gyro_std: np.ndarray
    counts: np.ndarray
    directions: np.ndarray
    rejected: list[tuple[int, int, str]]
    still: np.ndarray
    moving: np.ndarray
    names: tuple[str, ...] = ()
    settings: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.intervals)

    @property
    def durations(self) -> np.ndarray:
        """(P,) seconds from the first to the last sample of each pose."""
        return (self.stamps[:, 1] - self.stamps[:, 0]) * 1e-9

    def spread(self) -> dict[str, float]:
        """How well the poses cover the sphere of gravity directions.

        poses; min_eigenvalue: smallest eigenvalue of mean(d d^T) over the directions d
        (1/3 when evenly spread, 0 when coplanar); coverage_deg: largest angle from any unit
        direction to its nearest pose (37.4 for the 20 faces of an icosahedron, 180 without
        poses); min_separation_deg: smallest angle between two poses (NaN for fewer than two).
        """
        d = self.directions
        p = len(d)
        if p == 0:
            return {"poses": 0, "min_eigenvalue": 0.0, "coverage_deg": 180.0, "min_separation_deg": float("nan")}
        eig = float(np.linalg.eigvalsh(d.T @ d / p)[0])
        probes = _fibonacci_sphere(20000)
        if p >= 4:
            try:  # the exact farthest points: vertices of the spherical Voronoi diagram
                from scipy.spatial import SphericalVoronoi

                probes = np.vstack([probes, SphericalVoronoi(d).vertices])
            except Exception:  # degenerate (duplicate, coplanar) directions: the grid alone (~1 deg)
                pass
        coverage = np.degrees(np.arccos(np.clip(np.max(probes @ d.T, axis=1), -1.0, 1.0)).max())
        if p > 1:
            cos = d @ d.T
            np.fill_diagonal(cos, -1.0)
            sep = float(np.degrees(np.arccos(np.clip(cos.max(), -1.0, 1.0))))
        else:
            sep = float("nan")
        return {"poses": p, "min_eigenvalue": max(eig, 0.0), "coverage_deg": float(coverage),
                "min_separation_deg": sep}

    def summary(self) -> str:
        """One paragraph: poses found, durations, spread, rejections, missing IMUs."""
        s = self.spread()
        n = len(self)
        text = f"{n} static pose{'s' if n != 1 else ''}"
        if n:
            dur = self.durations
            text += (f" ({dur.min():.1f}-{dur.max():.1f} s each, {int(self.still.sum())} samples); directions: "
                     f"smallest eigenvalue {s['min_eigenvalue']:.3f} (1/3 when evenly spread), every direction "
                     f"within {s['coverage_deg']:.0f} deg of a pose")
            if n > 1:
                text += f", closest pair {s['min_separation_deg']:.1f} deg apart"
        text += f"; {len(self.rejected)} still interval{'s' if len(self.rejected) != 1 else ''} rejected"
        if self.rejected:
            reasons: dict[str, int] = {}
            for _, _, why in self.rejected:
                key = why.split(" (")[0].split(":")[0]
                reasons[key] = reasons.get(key, 0) + 1
            text += " (" + ", ".join(f"{k}: {v}" for k, v in reasons.items()) + ")"
        missing = np.isnan(self.accel).any(axis=2).sum(axis=0) if n else np.zeros(0, int)
        gone = [f"{self.names[k] if k < len(self.names) else k} in {m}" for k, m in enumerate(missing) if m]
        if gone:
            text += "; IMUs missing: " + ", ".join(gone)
        return text + "."


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _window_total_std(x: np.ndarray, ok: np.ndarray, w: int) -> np.ndarray:
    """(N, K, 3) readings, (N, K) usable -> (N - w + 1, K) total std per window (NaN: < w/2 usable)."""
    n, k, _ = x.shape
    ok3 = np.repeat(ok, 3, axis=1)  # (N, 3K)
    x0 = np.where(ok3, x.reshape(n, 3 * k), 0.0)
    x0 -= x0.sum(axis=0) / np.maximum(ok3.sum(axis=0), 1)  # centred: no cancellation in the sums
    x0[~ok3] = 0.0
    rows = np.concatenate([x0, x0 * x0, ok], axis=1).T  # (7K, N): one contiguous cumulative sum
    c = np.zeros((7 * k, n + 1))
    np.cumsum(rows, axis=1, out=c[:, 1:])
    d = c[:, w:] - c[:, :-w]
    cnt = d[6 * k:].T  # (M, K)
    nn = np.maximum(cnt, 1.0)
    m1 = d[:3 * k].T.reshape(-1, k, 3) / nn[..., None]
    m2 = d[3 * k:6 * k].T.reshape(-1, k, 3) / nn[..., None]
    var = np.maximum(m2 - m1 * m1, 0.0).sum(axis=-1) * (cnt / np.maximum(cnt - 1.0, 1.0))
    return np.where(cnt >= max(w / 2.0, 2.0), np.sqrt(var), np.nan)


def _median_over_imus(stat: np.ndarray) -> np.ndarray:
    """(M, K) -> (M,) median over the non-NaN entries of each row (inf when none); faster than nanmedian."""
    srt = np.sort(np.where(np.isnan(stat), np.inf, stat), axis=1)
    m = (~np.isnan(stat)).sum(axis=1)
    lo = np.take_along_axis(srt, np.maximum((m - 1) // 2, 0)[:, None], axis=1)[:, 0]
    hi = np.take_along_axis(srt, np.minimum(m // 2, stat.shape[1] - 1)[:, None], axis=1)[:, 0]
    return np.where(m > 0, 0.5 * (lo + hi), np.inf)


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def find_still_poses(
    samples: ImuSamples,
    model: SensorModel,
    *,
    window_s: float = 1.0,
    gyro_threshold: float | None = None,
    accel_threshold: float | None = None,
    min_duration_s: float = 1.0,
    settle_s: float = 0.25,
    gravity_tolerance: float = 0.05,
    drift_sigma: float = 6.0,
    gravity: float = STANDARD_GRAVITY,
) -> StillPoses:
    """Static poses in raw readings (see the module docstring for the method and defaults).

    samples: stamps increasing; raw readings in each IMU's sensor frame (m/s^2, rad/s; NaN = missing); ``model`` a :class:`SensorModel` (or a description):
    nominal rotations, noise stds and clip levels.  gyro_threshold (rad/s) / accel_threshold
    (m/s^2): largest median-over-IMUs total std of a still window (None: from the noise);
    min_duration_s: shortest pose kept, after ``settle_s`` is trimmed from both ends;
    gravity_tolerance: largest relative deviation of |mean specific force| from ``gravity`` (m/s^2).
    """
    if not isinstance(model, SensorModel):
        model = SensorModel.from_description(model)
    stamps, accel, gyro = samples.stamps, samples.accel, samples.gyro
    n, k = len(stamps), model.n_imus
    if accel.shape != (n, k, 3) or gyro.shape != (n, k, 3):
        raise ValueError(f"accel {accel.shape} and gyro {gyro.shape} must be {(n, k, 3)} (stamps, model IMUs)")
    if window_s <= 0 or min_duration_s < 0 or settle_s < 0:
        raise ValueError("window_s must be > 0, min_duration_s and settle_s >= 0")
    dt = float(np.median(np.diff(stamps))) * 1e-9 if n > 1 else 1.0
    if not dt > 0:
        raise ValueError("stamps must increase")
    w = max(int(round(window_s / dt)), 2)

    def total(std) -> float:  # median over the IMUs of the total (3-axis) noise std
        return float(np.median(np.linalg.norm(np.asarray(std, dtype=float).reshape(k, -1), axis=1)))

    gthr = max(NOISE_FACTOR * total(model.gyro_std), GYRO_FLOOR) if gyro_threshold is None else float(gyro_threshold)
    athr = max(NOISE_FACTOR * total(model.acc_std), ACCEL_FLOOR) if accel_threshold is None else float(accel_threshold)
    settings = {"window_s": w * dt, "gyro_threshold": gthr, "accel_threshold": athr, "min_duration_s": min_duration_s,
                "settle_s": settle_s, "gravity_tolerance": gravity_tolerance, "drift_sigma": drift_sigma,
                "gravity": gravity}

    finite_a = np.isfinite(accel).all(axis=2)
    finite_g = np.isfinite(gyro).all(axis=2)
    candidate = np.zeros(n, dtype=bool)
    if n >= w:  # the window centred on each sample (the first / last window for the samples near the ends)
        still_win = ((_median_over_imus(_window_total_std(gyro, finite_g, w)) < gthr)
                     & (_median_over_imus(_window_total_std(accel, finite_a, w)) < athr))
        candidate = still_win[np.clip(np.arange(n) - w // 2, 0, len(still_win) - 1)]

    valid6 = model.valid(accel, gyro)  # (N, K, 6) finite and not saturated
    usable = valid6.all(axis=2)  # (N, K) the IMU's whole reading is usable
    saturated = (np.isfinite(accel) & ~valid6[..., :3]).any(axis=2) | (np.isfinite(gyro) & ~valid6[..., 3:]).any(axis=2)
    std6 = np.concatenate([model.acc_std, model.gyro_std], axis=1).reshape(k, 6)
    floor6 = np.array([DRIFT_FLOOR_ACCEL] * 3 + [DRIFT_FLOOR_GYRO] * 3)
    settle = int(round(settle_s / dt))
    need = int(np.ceil(min_duration_s / dt)) + 1  # samples spanning min_duration_s

    keep, rejected, rows = [], [], []
    for a, b in zip(*_runs(candidate)):
        s0, s1 = a + settle, b - settle
        if s1 - s0 < max(need, 2):
            rejected.append((int(a), int(b), f"too short: {max(s1 - s0 - 1, 0) * dt:.2f} s after trimming "
                                             f"{settle_s:g} s at each end (< {min_duration_s:g} s)"))
            continue
        sat = int(saturated[s0:s1].sum())
        if sat:
            rejected.append((int(a), int(b), f"saturated: {sat} saturated IMU readings"))
            continue
        y = np.concatenate([accel[s0:s1], gyro[s0:s1]], axis=2)  # (L, K, 6)
        ok = usable[s0:s1]
        cnt = ok.sum(axis=0)
        present = cnt >= max(MIN_VALID_FRACTION * (s1 - s0), 2)
        if not present.any():
            rejected.append((int(a), int(b), "no IMU: no IMU has enough valid samples"))
            continue
        y = np.where(ok[..., None], y, np.nan)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(y, axis=0)
            sd = np.nanstd(y, axis=0, ddof=1)
            half = (s1 - s0) // 2
            m1, m2 = np.nanmean(y[:half], axis=0), np.nanmean(y[half:], axis=0)
        n1, n2 = ok[:half].sum(axis=0), ok[half:].sum(axis=0)
        mean[~present] = np.nan
        sd[~present] = np.nan
        f = np.einsum("kij,kj->ki", model.rotations, mean[:, :3])  # array frame
        f_mean = np.nanmean(f[present], axis=0)
        mag = float(np.linalg.norm(f_mean))
        if abs(mag / gravity - 1.0) > gravity_tolerance:
            rejected.append((int(a), int(b), f"not gravity: |specific force| {mag:.3g} m/s^2, "
                                             f"{100 * abs(mag / gravity - 1):.1f} % off g (accelerating)"))
            continue
        both = present & (n1 > 1) & (n2 > 1)
        if both.any():
            se = np.maximum(sd, std6) * np.sqrt(1.0 / np.maximum(n1, 1) + 1.0 / np.maximum(n2, 1))[:, None]
            diff = np.abs(m1 - m2)
            z = np.where(diff > floor6, diff / se, 0.0)[both].max(axis=1)
            zmed = float(np.median(z))
            if zmed > drift_sigma:
                rejected.append((int(a), int(b), f"drifting: first and second half differ by {zmed:.1f} sigma "
                                                 f"(median over IMUs; > {drift_sigma:g})"))
                continue
        keep.append((s0, s1))
        rows.append((mean, sd, cnt, f_mean / mag))

    p = len(keep)
    intervals = np.array(keep, dtype=np.int64).reshape(p, 2)
    still = np.zeros(n, dtype=bool)
    for s0, s1 in keep:
        still[s0:s1] = True
    pick = lambda i, c: np.array([r[i][:, c] for r in rows]).reshape(p, k, 3)  # noqa: E731
    return StillPoses(
        intervals=intervals,
        stamps=(np.column_stack([stamps[intervals[:, 0]], stamps[intervals[:, 1] - 1]]) if p
                else np.zeros((0, 2), np.int64)),
        accel=pick(0, slice(0, 3)), gyro=pick(0, slice(3, 6)),
        accel_std=pick(1, slice(0, 3)), gyro_std=pick(1, slice(3, 6)),
        counts=np.array([r[2] for r in rows], dtype=np.int64).reshape(p, k),
        directions=np.array([r[3] for r in rows], dtype=float).reshape(p, 3),
        rejected=rejected, still=still, moving=~candidate, names=tuple(model.names), settings=settings,
    )


def _rest_needed(settings: dict) -> float:
    """Seconds a rest must last to give a pose: min_duration_s plus half a window and settle_s at each end."""
    return (settings.get("min_duration_s", 1.0)
            + 2 * (settings.get("settle_s", 0.25) + 0.5 * settings.get("window_s", 1.0)))


def check_poses(poses: StillPoses, needed: int = POSES_FULL_MODEL, *, what: str = "the full model") -> None:
    """Raise :class:`CalibrationError` (one line) unless ``poses`` can calibrate ``what``.

    Needs at least ``needed`` poses (nilsson2014: 12 for gain, bias, non-orthogonality and
    misalignment, 9 without misalignment) whose directions are not clustered or coplanar:
    smallest eigenvalue of mean(d d^T) at least :data:`MIN_EIGENVALUE` (0.05; 1/3 when evenly
    spread, 0 when all directions lie in one plane through the origin).
    """
    s = poses.spread()
    p = s["poses"]
    if p < needed:
        extra = f" ({len(poses.rejected)} still intervals rejected)" if poses.rejected else ""
        raise CalibrationError(
            f"only {p} static pose{'s' if p != 1 else ''} found{extra}, {what} needs at least {needed}: set the "
            f"array down on more faces (e.g. all 20 of an icosahedron), holding each still for "
            f"{_rest_needed(poses.settings):.3g} s or more")
    if s["min_eigenvalue"] < MIN_EIGENVALUE:
        raise CalibrationError(
            f"the {p} static poses are clustered or coplanar (smallest eigenvalue of the mean direction outer "
            f"product {s['min_eigenvalue']:.3f} < {MIN_EIGENVALUE:g}; 1/3 when evenly spread), {what} needs "
            f"directions all round: set the array down on faces pointing in more different directions "
            f"(e.g. all 20 faces of an icosahedron)")
