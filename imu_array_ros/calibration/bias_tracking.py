"""Gyroscope biases as session states: re-estimated whenever the array is still.

A MEMS gyroscope's turn-on bias changes at every power-up (on the MIMU4444BT captures the gyroscope
biases ``calibrate all`` finds on three captures differ by 13-14x their standard deviations, every other
field repeats within 1-2x), so the bias a description holds is stale in the next session.  This module
re-measures it on every still interval, with the same numbers offline (a whole recording) and live
(chunks as they come):

1. **Still detection** (:class:`StillDetector`, streaming; the batch use is the same object fed the whole
   recording).  For every sample, the *trailing* window of ``window_s`` (default 1 s) of stamps ending at
   it: every IMU's total standard deviation of each triad, sqrt(sum over the axes of the variance), over its
   valid (finite, unsaturated) readings; the median over the IMUs; the window is still when both medians
   are below the thresholds of :mod:`~imu_array_ros.calibration.still` (``NOISE_FACTOR`` x the model's
   total white-noise std, floored at ``GYRO_FLOOR`` / ``ACCEL_FLOOR``).  A window is only judged once the
   data reach a whole window back.  A *run* is a stretch of consecutive still windows; its samples span
   from the first window's first sample to the last window's last.  The run is trimmed by ``settle_s`` at
   both ends and cut into *pieces* of ``max_piece_s`` (default 10 s; live, a long rest is not waited out),
   the last piece being the rest of the run if it spans ``min_still_s`` (default 1 s).  A piece whose
   specific force is not gravity (the mean over the IMUs of R_k mean(accel_k), > ``gravity_tolerance`` off
   g) is rejected: the array was accelerating.
2. **Measurement** (:func:`piece_biases`).  The model predicts gyro reading = f(omega, s, t) + bias; at
   rest omega = 0, so bias = mean reading - (f(0, s, t) with the model's bias removed), with ``f`` the whole
   calibrated chain (gain, misalignment, g-sensitivity at the piece's specific force, a bias drift at the
   piece's mean time).  The Earth's rotation (7.29e-5 rad/s, ``EARTH_RATE``) is neglected: it goes into
   every IMU's bias as the same vector in the array frame, so the fused angular velocity becomes the
   rotation relative to the ground, off by at most 7.3e-5 rad/s (0.0042 deg/s) from the inertial one.  That
   is below a 1 s piece's noise (0.0039 / sqrt(62) = 5e-4 rad/s on the MIMU4444BT at 62.5 Hz) and ~2/3 of a
   20 s rest's; with 1 kHz and quieter sensors it may not be.  The measurement's std per axis is the larger
   of the white-noise one (sample std / sqrt(n)) and the batch-means one (the spread of the means of 8
   consecutive blocks / sqrt(8)), which accounts for correlated noise (a slowly wandering bias).
3. **Update** (:class:`BiasTracker`): per IMU and axis, a random-walk Kalman filter.  Before the first
   piece the description's bias holds; the first piece's measurement replaces it (a turn-on bias is not
   known before the session: no prior); every later one is combined with the current estimate, whose
   variance grows by ``random_walk`` (rad/s)^2/s times the seconds since the last update.

Offline (:func:`track_biases`, :meth:`BiasTrack.correct`), the estimate after piece i applies from the start
of piece i to the start of piece i + 1, and the first one also back to the recording's start: the turn-on
bias is there from power-up, and the first rest measures it better than the description.  Live, an estimate
applies from the moment it is made.  Applying a bias is subtracting its change from the unsaturated gyro
readings (the bias is the last stage of the gyroscope's chain but a linear drift, so this is the model with
that bias), which is what the fusion, the residuals and the session-state estimates then see.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from imu_array_ros.calibration.still import ACCEL_FLOOR, GYRO_FLOOR, NOISE_FACTOR
from imu_array_ros.model.constants import STANDARD_GRAVITY
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel, motion_context

__all__ = ["StillDetector", "StillPiece", "BiasTracker", "BiasUpdate", "BiasTrack", "track_biases", "piece_biases",
           "equivalent_sigma", "EARTH_RATE", "RANDOM_WALK", "JUMP_SIGMA", "BLOCKS"]

#: the Earth's rotation rate, rad/s (neglected at rest; see the module docstring)
EARTH_RATE = 7.292115e-5
#: default random-walk intensity of a gyroscope bias, (rad/s)^2/s (benchmarks/real_bias_tracking.py)
RANDOM_WALK = 1e-9
#: an update whose innovation exceeds this many standard deviations is reported
JUMP_SIGMA = 3.0
#: updates over JUMP_SIGMA listed one per console line; the rest share one line
MAX_JUMP_LINES = 3
#: batch means: blocks per piece
BLOCKS = 8


@dataclass
class StillPiece:
    """A still piece: stamps [start_ns, stop_ns] (first and last sample), mean_ns its mean stamp; per IMU
    (K,) ``count`` valid gyro readings, ``gyro`` (K, 3) their mean (NaN: none), ``gyro_std`` (K, 3) the std of
    that mean (see the module docstring); ``specific_force`` (3,) array frame, from the accelerometers."""

    start_ns: int
    stop_ns: int
    mean_ns: int
    count: np.ndarray
    gyro: np.ndarray
    gyro_std: np.ndarray
    specific_force: np.ndarray

    @property
    def seconds(self) -> float:
        return (self.stop_ns - self.start_ns) * 1e-9


def _piece(stamps, accel, gyro, ok_a, ok_g, rotations) -> StillPiece:
    """Statistics of one piece's samples (L,), (L, K, 3), valid masks (L, K)."""
    n = ok_g.sum(axis=0)  # (K,)
    g = np.where(ok_g[..., None], gyro, 0.0)
    nn = np.maximum(n, 1)[:, None]
    mean = g.sum(axis=0) / nn
    dev = np.where(ok_g[..., None], gyro - mean, 0.0)
    var = (dev * dev).sum(axis=0) / np.maximum(n - 1, 1)[:, None]
    white = var / nn
    blocks = np.array_split(np.arange(len(stamps)), BLOCKS)
    bn = np.stack([ok_g[b].sum(axis=0) for b in blocks])  # (B, K)
    bm = np.stack([g[b].sum(axis=0) for b in blocks]) / np.maximum(bn, 1)[..., None]  # (B, K, 3)
    full = (bn >= 2).all(axis=0)  # every block has readings
    batch = np.var(bm, axis=0, ddof=1) / BLOCKS
    std = np.sqrt(np.where(full[:, None], np.maximum(white, batch), white))
    bad = n < 2
    mean[bad], std[bad] = np.nan, np.nan
    na = ok_a.sum(axis=0)
    a = np.where(ok_a[..., None], accel, 0.0).sum(axis=0) / np.maximum(na, 1)[:, None]
    f = np.einsum("kij,kj->ki", rotations, a)[na > 0]
    force = f.mean(axis=0) if len(f) else np.full(3, np.nan)
    return StillPiece(int(stamps[0]), int(stamps[-1]), int(stamps[0] + np.mean(stamps - stamps[0])), n.astype(np.int64),
                      mean, std, force)


class StillDetector:
    """Streaming still detection (see the module docstring): :meth:`add` chunks of samples in stamp order,
    get the still pieces that ended; :meth:`flush` at the end of the data ends the open run.  Fed a whole
    recording at once or in any chunks it finds the same pieces (to rounding of the window sums)."""

    def __init__(self, model: SensorModel, *, window_s: float = 1.0, min_still_s: float = 1.0, settle_s: float = 0.25,
                 max_piece_s: float = 10.0, gyro_threshold: float | None = None, accel_threshold: float | None = None,
                 gravity_tolerance: float = 0.05, gravity: float = STANDARD_GRAVITY) -> None:
        if window_s <= 0 or min_still_s <= 0 or settle_s < 0 or max_piece_s < min_still_s:
            raise ValueError("window_s and min_still_s must be > 0, settle_s >= 0, max_piece_s >= min_still_s")
        self.model = model
        k = model.n_imus
        total = lambda std: float(np.median(np.linalg.norm(np.asarray(std, float).reshape(k, -1), axis=1)))  # noqa: E731
        self.gyro_threshold = max(NOISE_FACTOR * total(model.gyro_std), GYRO_FLOOR) if gyro_threshold is None \
            else float(gyro_threshold)
        self.accel_threshold = max(NOISE_FACTOR * total(model.acc_std), ACCEL_FLOOR) if accel_threshold is None \
            else float(accel_threshold)
        self.window_ns, self.settle_ns = int(round(window_s * 1e9)), int(round(settle_s * 1e9))
        self.min_ns, self.max_ns = int(round(min_still_s * 1e9)), int(round(max_piece_s * 1e9))
        self.gravity, self.gravity_tolerance = float(gravity), float(gravity_tolerance)
        self.rejected: list[tuple[int, int, str]] = []  # (start_ns, stop_ns, why) of pieces not kept
        self._buf = None  # (stamps, accel, gyro, ok_a, ok_g) kept: the last window and the open run's next piece
        self._ref = None  # (K, 3) x2 centring of the window sums
        self._run_start: int | None = None  # stamp where the open run's next piece starts (before trimming)
        self._run_end: int | None = None  # last stamp of the open run's last still window
        self._trimmed = False  # the open run's start already trimmed (a piece was emitted)
        self._last_end = -(2 ** 62)  # end of the last run (runs do not overlap)

    @property
    def settings(self) -> dict:
        return {"window_s": self.window_ns * 1e-9, "min_still_s": self.min_ns * 1e-9, "settle_s": self.settle_ns * 1e-9,
                "max_piece_s": self.max_ns * 1e-9, "gyro_threshold": self.gyro_threshold,
                "accel_threshold": self.accel_threshold, "gravity_tolerance": self.gravity_tolerance}

    def add(self, samples: ImuSamples) -> list[StillPiece]:
        """The pieces that ended with these samples (stamps increasing, after the previous chunk's)."""
        if not len(samples):
            return []
        ok = self.model.valid(samples.accel, samples.gyro)
        new = (samples.stamps, samples.accel, samples.gyro, ok[..., :3].all(axis=2), ok[..., 3:].all(axis=2))
        first = 0 if self._buf is None else len(self._buf[0])
        buf = new if self._buf is None else tuple(np.concatenate([a, b]) for a, b in zip(self._buf, new))
        self._buf = buf
        still, starts = self._windows(buf, first)
        out = []
        stamps = buf[0]
        cuts = np.flatnonzero(np.diff(still.astype(np.int8))) + 1
        for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(still)]])):  # segments of one flag
            if still[a]:
                if self._run_end is None:
                    self._run_start = max(int(stamps[starts[a]]), self._last_end + 1)
                    self._trimmed = False
                self._run_end = int(stamps[first + b - 1])
                out += self._emit(final=False)
            elif self._run_end is not None:
                out += self._emit(final=True)
        self._trim()
        return out

    def flush(self) -> list[StillPiece]:
        """End of the data: the open run ends at its last still window."""
        return self._emit(final=True) if self._run_end is not None else []

    def _windows(self, buf, first: int) -> tuple[np.ndarray, np.ndarray]:
        """Still flag and window start index of the trailing window of every sample from ``first`` on."""
        stamps, accel, gyro, ok_a, ok_g = buf
        ends = np.arange(first, len(stamps))
        starts = np.searchsorted(stamps, stamps[ends] - self.window_ns, side="right")
        covered = starts > 0  # a sample at or before the window's start: the data reach a whole window back
        if self._ref is None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an IMU without a valid reading yet: 0
                self._ref = tuple(np.nan_to_num(np.nanmedian(np.where(o[..., None], x, np.nan), axis=0))
                                  for x, o in ((accel, ok_a), (gyro, ok_g)))
        medians = []
        for x, ok, ref in ((gyro, ok_g, self._ref[1]), (accel, ok_a, self._ref[0])):
            x0 = np.where(ok[..., None], x - ref, 0.0)
            rows = np.concatenate([x0, x0 * x0, ok[..., None].astype(float)], axis=2)  # (N, K, 7)
            c = np.concatenate([np.zeros((1,) + rows.shape[1:]), np.cumsum(rows, axis=0)])
            d = c[ends + 1] - c[starts]
            cnt = d[..., 6]
            nn = np.maximum(cnt, 1.0)[..., None]
            m1, m2 = d[..., :3] / nn, d[..., 3:6] / nn
            var = np.maximum(m2 - m1 * m1, 0.0).sum(axis=-1) * (cnt / np.maximum(cnt - 1.0, 1.0))
            size = (ends + 1 - starts)[:, None]
            stat = np.where(cnt >= np.maximum(size / 2.0, 2.0), np.sqrt(var), np.inf)
            medians.append(np.median(stat, axis=1))
        still = covered & (medians[0] < self.gyro_threshold) & (medians[1] < self.accel_threshold)
        return still, starts

    def _emit(self, final: bool) -> list[StillPiece]:
        """Pieces of the open run: full ones that are confirmed, and with ``final`` the rest (the run ends)."""
        out = []
        end = self._run_end - self.settle_ns  # trimmed end
        while True:
            a = self._run_start + (0 if self._trimmed else self.settle_ns)
            if a + self.max_ns <= end:
                out += self._make(a, a + self.max_ns)
                self._run_start, self._trimmed = a + self.max_ns, True
                continue
            if final:
                if end - a >= self.min_ns:
                    out += self._make(a, end + 1)
                self._last_end, self._run_start, self._run_end = self._run_end, None, None
            return out

    def _make(self, a: int, b: int) -> list[StillPiece]:
        stamps, accel, gyro, ok_a, ok_g = self._buf
        lo, hi = np.searchsorted(stamps, [a, b], side="left")
        if hi - lo < 2 or stamps[hi - 1] - stamps[lo] < min(self.min_ns, b - a - 1):
            return []
        p = _piece(stamps[lo:hi], accel[lo:hi], gyro[lo:hi], ok_a[lo:hi], ok_g[lo:hi], self.model.rotations)
        mag = float(np.linalg.norm(p.specific_force))
        if not abs(mag / self.gravity - 1.0) <= self.gravity_tolerance:
            self.rejected.append((p.start_ns, p.stop_ns, f"not gravity: |specific force| {mag:.3g} m/s^2"))
            return []
        return [p]

    def _trim(self) -> None:
        stamps = self._buf[0]
        keep = int(np.searchsorted(stamps, stamps[-1] - self.window_ns, side="right")) - 1
        if self._run_start is not None:
            keep = min(keep, int(np.searchsorted(stamps, self._run_start, side="left")))
        if keep > 0:
            self._buf = tuple(x[keep:] for x in self._buf)


def piece_biases(pieces: list[StillPiece], model: SensorModel, t0_ns: int) -> np.ndarray:
    """(P, K, 3) the gyroscope bias each piece measures: mean reading minus the model's prediction at rest
    (omega = 0, the piece's specific force, its mean time from ``t0_ns``) with the model's bias taken out."""
    if not pieces:
        return np.zeros((0, model.n_imus, 3))
    p = len(pieces)
    zeros = np.zeros((p, 3))
    force = np.array([np.nan_to_num(x.specific_force) for x in pieces])
    ctx = motion_context(np.array([x.mean_ns for x in pieces], dtype=np.int64), zeros, zeros, force, model.rotations,
                         t0_ns=t0_ns, omega_ddot=zeros, specific_force_dot=zeros)
    _, pred = model.predict(ctx)
    bias = model.terms["gyroscope_bias"].values[None]
    return np.array([x.gyro for x in pieces]) - pred + bias


def equivalent_sigma(chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """The one-dimensional number of sigmas with the same two-sided tail probability as ``chi2`` with ``dof``
    degrees of freedom (an IMU's three axes judged together; 0 where dof is 0)."""
    from scipy.special import chdtrc, ndtri

    dof = np.asarray(dof)
    p = chdtrc(np.maximum(dof, 1), np.asarray(chi2, dtype=float))
    return np.where(dof > 0, -ndtri(np.clip(p, 1e-300, 1.0) / 2.0), 0.0)


@dataclass
class BiasUpdate:
    """One update: the piece, the bias it measured (K, 3) and that measurement's std, the bias before and after
    (K, 3) with the std after, and ``jump_sigma`` (K,): per IMU how far the measurement is from the bias before,
    the three axes' normalised innovations judged together (chi-square, 3 dof) and stated as the one-dimensional
    sigma of the same tail probability (the first update: against the description's bias, with the
    measurement's std); above :data:`JUMP_SIGMA` (3) by chance in 0.27 % of updates per IMU."""

    piece: StillPiece
    measured: np.ndarray
    measured_std: np.ndarray
    before: np.ndarray
    bias: np.ndarray
    bias_std: np.ndarray
    jump_sigma: np.ndarray

    def jumps(self, names, sigma: float = JUMP_SIGMA) -> list[str]:
        """'name (x.x sigma)' of the IMUs whose bias moved by more than ``sigma``."""
        return [f"{n} ({z:.1f} sigma)" for n, z in zip(names, self.jump_sigma) if z > sigma]


class BiasTracker:
    """The gyroscope biases of one session, kept current (see the module docstring): :meth:`add` samples in
    stamp order (any chunks), :meth:`flush` at the end; ``bias`` (K, 3) and ``bias_std`` (K, 3) are the
    current estimate (the description's, std NaN, before the first still piece); ``updates`` every update."""

    def __init__(self, model: SensorModel, *, t0_ns: int | None = None, random_walk: float = RANDOM_WALK,
                 **detector) -> None:
        self.model = model
        self.t0_ns = t0_ns
        self.random_walk = float(random_walk)
        self.detector = StillDetector(model, **detector)
        self.initial = model.terms["gyroscope_bias"].values.copy()
        self.bias = self.initial.copy()
        self.var = np.full_like(self.bias, np.inf)
        self.updates: list[BiasUpdate] = []
        self._last_ns: int | None = None

    @property
    def bias_std(self) -> np.ndarray:
        return np.where(np.isfinite(self.var), np.sqrt(self.var), np.nan)

    def add(self, samples: ImuSamples) -> list[BiasUpdate]:
        if self.t0_ns is None and len(samples):
            self.t0_ns = int(samples.stamps[0])
        return self._update(self.detector.add(samples))

    def flush(self) -> list[BiasUpdate]:
        return self._update(self.detector.flush())

    def _update(self, pieces: list[StillPiece]) -> list[BiasUpdate]:
        out = []
        for piece, z in zip(pieces, piece_biases(pieces, self.model, self.t0_ns or 0)):
            r = piece.gyro_std ** 2
            var = self.var.copy()
            if self._last_ns is not None:
                var += self.random_walk * max(piece.mean_ns - self._last_ns, 0) * 1e-9
            ok = np.isfinite(z) & np.isfinite(r) & (r > 0)
            first = ~np.isfinite(var)
            finite_var = np.where(first, 0.0, var)
            gain = np.where(first, 1.0, finite_var / np.where(ok, finite_var + r, 1.0))
            before = self.bias.copy()
            innov = np.where(ok, z - before, 0.0)
            sd = np.sqrt(np.where(ok, np.where(first, r, finite_var + r), 1.0))
            jump = equivalent_sigma(np.sum((innov / sd) ** 2, axis=1), ok.sum(axis=1))
            self.bias = np.where(ok, before + gain * innov, before)
            self.var = np.where(ok, np.where(first, r, (1.0 - gain) * finite_var), var)
            self._last_ns = piece.mean_ns
            out.append(BiasUpdate(piece, z, piece.gyro_std, before, self.bias.copy(), self.bias_std, jump))
        self.updates += out
        return out


@dataclass
class BiasTrack:
    """The gyroscope biases of a whole recording: ``updates`` in order, ``initial`` (K, 3) the description's,
    ``names``; :meth:`correct` applies them (see the module docstring)."""

    names: tuple
    initial: np.ndarray
    updates: list[BiasUpdate] = field(default_factory=list)
    rejected: list = field(default_factory=list)
    settings: dict = field(default_factory=dict)

    def starts(self) -> np.ndarray:
        """(U,) int64 the stamp from which each update's bias applies offline (the first: from the start)."""
        s = np.array([u.piece.start_ns for u in self.updates], dtype=np.int64)
        if len(s):
            s[0] = np.iinfo(np.int64).min
        return s

    def biases_at(self, stamps: np.ndarray) -> np.ndarray:
        """(N, K, 3) the bias in use at each stamp, offline."""
        if not self.updates:
            return np.broadcast_to(self.initial, (len(stamps),) + self.initial.shape)
        table = np.array([u.bias for u in self.updates])
        return table[np.searchsorted(self.starts(), np.asarray(stamps, dtype=np.int64), side="right") - 1]

    def correct(self, samples: ImuSamples, model: SensorModel) -> ImuSamples:
        """``samples`` with each unsaturated gyro reading minus (bias in use - the description's bias): the
        readings the description's model sees as those of the tracked biases."""
        if not self.updates:
            return samples
        delta = self.biases_at(samples.stamps) - self.initial[None]
        gyro = np.where(model.gyro_unsaturated(samples.gyro), samples.gyro - delta, samples.gyro)
        return ImuSamples(samples.stamps, samples.accel, gyro, samples.names, samples.own_stamps)

    @property
    def bias(self) -> np.ndarray:
        """(K, 3) the last estimate (the description's without updates)."""
        return self.updates[-1].bias if self.updates else self.initial

    def notes(self) -> list[str]:
        """What was done, for the console."""
        if not self.updates:
            return ["gyroscope biases: no still interval of "
                    f"{self.settings.get('min_still_s', 1.0):g} s or more: the description's biases kept"]
        seconds = sum(u.piece.seconds for u in self.updates)
        change = np.abs(self.bias - self.initial).max(axis=1)
        k = int(np.argmax(change))
        wander = self.wander()
        lines = [f"gyroscope biases: {len(self.updates)} still pieces ({seconds:.0f} s still); largest change from the "
                 f"description {change[k]:.3g} rad/s ({self.names[k]}); within the recording the estimates moved by up "
                 f"to {np.nanmax(wander):.3g} rad/s"]
        jumped = [(i, u) for i, u in enumerate(self.updates[1:], 1) if u.jumps(self.names)]
        at = lambda u: (u.piece.start_ns - self.updates[0].piece.start_ns) * 1e-9  # noqa: E731
        for i, u in jumped[:MAX_JUMP_LINES]:
            lines.append(f"gyroscope biases: update {i} at {at(u):.1f} s "
                         f"moved by more than {JUMP_SIGMA:g} sigma: " + ", ".join(u.jumps(self.names)))
        if len(jumped) > MAX_JUMP_LINES:  # one line for the rest (a real capture has dozens)
            rest = jumped[MAX_JUMP_LINES:]
            lines.append(f"gyroscope biases: {len(rest)} more updates moved by more than {JUMP_SIGMA:g} sigma, at "
                         + ", ".join(f"{at(u):.0f}" for _, u in rest) + " s")
        return lines

    def wander(self) -> np.ndarray:
        """(K,) per IMU the largest range over the axes of the estimates after each update."""
        b = np.array([u.bias for u in self.updates])
        return np.ptp(b, axis=0).max(axis=1) if len(b) else np.zeros(len(self.names))

    def summary(self) -> dict:
        """JSON-ready: the estimates per update and the final biases per IMU."""
        return {"updates": [{"start_s": u.piece.start_ns * 1e-9, "stop_s": u.piece.stop_ns * 1e-9,
                             "measured_rad_s": dict(zip(self.names, u.measured.tolist())),
                             "measured_std_rad_s": dict(zip(self.names, u.measured_std.tolist())),
                             "jump_sigma": dict(zip(self.names, u.jump_sigma.tolist()))} for u in self.updates],
                "bias_rad_s": dict(zip(self.names, np.asarray(self.bias).tolist())),
                "bias_std_rad_s": (dict(zip(self.names, self.updates[-1].bias_std.tolist())) if self.updates else None),
                "description_bias_rad_s": dict(zip(self.names, self.initial.tolist())),
                "notes": self.notes(), "settings": dict(self.settings)}


def track_biases(samples: ImuSamples, model: SensorModel, *, t0_ns: int | None = None, chunk: int = 0,
                 **settings) -> BiasTrack:
    """The gyroscope biases of ``samples`` under ``model`` (offline): a :class:`BiasTracker` fed the samples
    (in chunks of ``chunk`` samples when > 0, as live) and flushed.  ``settings``: those of
    :class:`BiasTracker` and :class:`StillDetector`."""
    tracker = BiasTracker(model, t0_ns=int(samples.stamps[0]) if t0_ns is None and len(samples) else t0_ns,
                          **settings)
    n = len(samples)
    step = chunk if chunk > 0 else max(n, 1)
    for lo in range(0, n, step):
        hi = min(lo + step, n)
        tracker.add(ImuSamples(samples.stamps[lo:hi], samples.accel[lo:hi], samples.gyro[lo:hi], samples.names))
    tracker.flush()
    return BiasTrack(tuple(model.names), tracker.initial, tracker.updates, tracker.detector.rejected,
                     {**tracker.detector.settings, "random_walk": tracker.random_walk})
