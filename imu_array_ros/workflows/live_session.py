"""Session states tracked live: the fusion node's clock phases, common clock rate and own-stamp clocks.

A description with sample clocks (a period > 0 in a sample-clock term), or IMUs that stamp their own
messages, has *session states* that no description holds (:mod:`imu_array_ros.timing`).  Offline,
``imu-array fuse`` estimates them from the whole recording first
(:func:`~imu_array_ros.workflows.fusion.session_fusion`).  Live there is no whole recording, so
:class:`SessionTracker`:

* keeps the samples the fusion published during the last ``window_s`` seconds (by stamp), through
  :meth:`SessionTracker.add`, the sink of :class:`~imu_array_ros.fusion.live.LiveFusion`, and counts
  the moving ones cheaply (the fused angular rate changing faster than
  :data:`~imu_array_ros.timing.delays.MOVING_RATE`; only a trigger: the estimate decides itself);
* once that window holds :data:`~imu_array_ros.timing.session.MIN_MOVING_S` s of motion, estimates
  the states (:func:`~imu_array_ros.timing.session.estimate_session` on the window, under the
  description's model, with the time origin ``t0_ns`` the fusion counts from, so phases stay
  consistent between estimates) in a worker thread, off the hot path; :meth:`SessionTracker.poll`,
  called between two fusion steps, starts it and hands back a finished estimate for
  :meth:`LiveFusion.set_model <imu_array_ros.fusion.live.LiveFusion.set_model>`;
* re-estimates every ``interval_s`` seconds of stamps while the array moves (after a too-still
  attempt, sooner: every ``min(interval_s, RETRY_S)``).  An estimate from too little motion
  (``estimated`` False), a failed one, or one that is not :func:`usable` (a state not finite; own-stamp
  clocks none of which could be told from their skews in a short window) never replaces the states in
  use.

Until the first estimate the fusion uses :func:`fallback_model`: what ``estimate_session`` gives a
recording with too little motion (each sample clock replaced by its mean age, half a period; own
stamps taken as the sample times).

The gyroscopes' biases are tracked by :class:`BiasSessionTracker`: on every still interval, in a worker
thread, with the numbers ``imu-array fuse`` finds offline.
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

from imu_array_ros.fusion.live import concatenate_samples
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.timing.delays import MOVING_RATE
from imu_array_ros.timing.session import CLOCK_TERMS, MIN_MOVING_S, SessionStates, active_clocks, estimate_session

__all__ = ["SessionTracker", "BiasSessionTracker", "fallback_model", "with_states", "usable", "has_sample_clocks", "RETRY_S", "MIN_MOVING_S"]

#: seconds (of stamps) between attempts while no estimate has succeeded yet (at most ``interval_s``)
RETRY_S = 5.0


def has_sample_clocks(model: SensorModel) -> bool:
    """True when some IMU of ``model`` has a sample clock (a period > 0 in one of the clock terms)."""
    return bool(active_clocks(model))


def fallback_model(model: SensorModel) -> SensorModel:
    """The model a session is fused with before its states are estimated: as
    :func:`~imu_array_ros.timing.session.estimate_session` with too little motion, every sample clock
    replaced by its mean age (a constant delay of half a period: the ``time_offset`` of the sensors it
    drives minus T/2) and own stamps taken as the sample times (``stamp_clock`` as the model has it)."""
    clocks = active_clocks(model)
    if not clocks:
        return model
    offsets = model.terms["time_offset"].values.copy()  # columns [accelerometer, gyroscope]
    reset = {}
    for term in clocks:
        clock = model.terms[term].values.copy()
        has = clock[:, 0] > 0
        half = np.where(has, 0.5 * clock[:, 0] / (1.0 + clock[:, 1] * 1e-6), 0.0)
        sensor = CLOCK_TERMS[term]
        for c in ([0, 1] if sensor is None else [("accelerometer", "gyroscope").index(sensor)]):
            offsets[:, c] -= half
        clock[:, 0] = 0.0
        reset[term] = clock
    return model.with_terms(time_offset=offsets, **reset)


def usable(states: SessionStates) -> bool:
    """False when a state is not finite, or own-stamp clocks were to be estimated but none was (every IMU's
    offset std NaN: the window's span too short to tell offsets from skews), though the estimate says
    ``estimated``."""
    if not all(np.isfinite(states.model.terms[n].values).all() for n in ("stamp_clock", *CLOCK_TERMS)):
        return False
    std = states.stamp_offset_std
    return std is None or len(std) < 2 or bool(np.isfinite(std).any())


def with_states(model: SensorModel, states: SessionStates) -> SensorModel:
    """``model`` (e.g. a reloaded calibration's) with the session states ``states`` estimated under another:
    the common clock-rate shift, each chip's own rate shift and the phases on its sample clocks, the stamp clocks'
    offsets and skews."""
    values = {}
    for term, phases in states.phases.items():
        clock = model.terms[term].values.copy()
        has = clock[:, 0] > 0
        if has.any():
            clock[has, 1] += float(states.common_rate_ppm.get(term) or 0.0)
            chip = states.chip_rate_ppm.get(term)
            if chip is not None and len(chip) == len(has):
                clock[has, 1] += np.asarray(chip, dtype=float)[has]
            clock[:, 2] = np.where(has & np.isfinite(phases), phases, 0.0)
            values[term] = clock
    if states.stamp_offset is not None:
        values["stamp_clock"] = np.column_stack([states.stamp_offset, states.stamp_skew])
    return model.with_terms(**values) if values else model


class SessionTracker:
    """Live estimation of the session states of one array (see module docstring).

    Parameters
    ----------
    model : SensorModel
        The description's model (device constants; no session states).
    own_stamps : bool
        The IMUs stamp their own messages (stamp clocks to estimate).
    window_s, interval_s : float
        Seconds of samples an estimate uses; seconds of stamps between estimates.
    """

    def __init__(self, model: SensorModel, *, own_stamps: bool, window_s: float = 20.0,
                 interval_s: float = 30.0) -> None:
        self.base = model
        self.own_stamps = bool(own_stamps)
        self.window_ns = int(round(window_s * 1e9))
        self.interval_ns = int(round(interval_s * 1e9))
        self.retry_ns = min(self.interval_ns, int(round(RETRY_S * 1e9)))
        self.states: SessionStates | None = None  # the last estimate in use
        self.states_base: SensorModel | None = None  # the model it was estimated under
        self.last_note = ""  # what the last attempt said
        self.attempts = self.estimates = self.failures = 0
        self.estimated_at_ns: int | None = None  # node clock
        self.error: str | None = None  # the last failure, one line
        self._chunks: deque = deque()  # (samples, moving seconds) published in the window
        self._moving = 0.0  # their moving seconds, summed
        self._last_attempt: int | None = None  # stamp of the newest sample of the last attempt
        self._worker: threading.Thread | None = None
        self._result: tuple | None = None
        self._seconds = 0.0  # CPU seconds of the last estimate (its thread's)

    @property
    def enabled(self) -> bool:
        """True when the model or the stamps have session states to estimate."""
        return self.own_stamps or has_sample_clocks(self.base)

    @property
    def busy(self) -> bool:
        return self._worker is not None

    @property
    def model(self) -> SensorModel:
        """The model to fuse with now: the base with the states in use, or the fallback before any."""
        if self.states is None:
            return fallback_model(self.base)
        return self.states.model if self.states_base is self.base else with_states(self.base, self.states)

    def rebase(self, model: SensorModel) -> SensorModel:
        """A new description's model (a calibration reload): the states in use carried over; returns the model
        to fuse with.  The next estimate is made under it (soon: the window is kept)."""
        self.base = model
        self._last_attempt = None
        return self.model

    # ------------------------------------------------------------------ samples (the hot path)

    def add(self, samples: ImuSamples, fused: FusedSamples) -> None:
        """The fusion's sink: keep the samples published, count the moving ones, trim the window."""
        if not self.enabled or not len(samples):
            return
        moving = 0.0
        if len(fused) > 1:
            dt = np.diff(fused.stamps) * 1e-9
            rate = np.linalg.norm(np.diff(fused.omega, axis=0), axis=1) / dt
            moving = float(np.count_nonzero(rate > MOVING_RATE) * np.median(dt))
        self._chunks.append((samples, moving))
        self._moving += moving
        newest = int(samples.stamps[-1])
        while self._chunks and int(self._chunks[0][0].stamps[-1]) < newest - self.window_ns:
            self._moving -= self._chunks.popleft()[1]

    def window(self) -> ImuSamples | None:
        """The samples kept (None: none yet)."""
        return concatenate_samples([s for s, _ in self._chunks]) if self._chunks else None

    @property
    def moving_seconds(self) -> float:
        """Seconds of motion in the window (the cheap count that triggers an estimate)."""
        return max(self._moving, 0.0)

    def due(self) -> bool:
        """An estimate should start now: none running, enough motion, and the interval passed."""
        if not self.enabled or self.busy or not self._chunks or self.moving_seconds < MIN_MOVING_S:
            return False
        if self._last_attempt is None:
            return True
        wait = self.interval_ns if self.states is not None else self.retry_ns
        return int(self._chunks[-1][0].stamps[-1]) - self._last_attempt >= wait

    # ------------------------------------------------------------------ estimates (off the hot path)

    def poll(self, now_ns: int, t0_ns: int | None) -> SessionStates | None:
        """Between two fusion steps: hand back a finished attempt (a :class:`SessionStates`, ``estimated``
        False when there was too little motion; ``model`` is then the one to keep fusing with), and start the
        next one when :meth:`due`.  A failed attempt returns None and sets ``error``."""
        out = None
        if self._worker is not None and not self._worker.is_alive():
            self._worker = None
            kind, value, base = self._result
            self._result = None
            if kind == "error":
                self.failures += 1
                self.error = value
            else:
                self.last_note = "; ".join(value.notes)
                if value.estimated and not usable(value):
                    value.estimated = False
                    self.last_note = ("not used: a state is not finite, or the stamp clocks are not identifiable "
                                      "from this window (too short a span for the skews)")
                if value.estimated:
                    self.states, self.states_base = value, base
                    self.estimates += 1
                    self.estimated_at_ns = int(now_ns)
                    self.error = None
                out = value
        if t0_ns is not None and self.due():
            self._start(int(t0_ns))
        return out

    def _start(self, t0_ns: int) -> None:
        chunks = [s for s, _ in self._chunks]
        self._last_attempt = int(chunks[-1].stamps[-1])
        self.attempts += 1
        base = self.base
        self._worker = threading.Thread(target=self._run, args=(chunks, base, t0_ns), daemon=True,
                                        name="session-states")
        self._worker.start()

    def _run(self, chunks: list, base: SensorModel, t0_ns: int) -> None:
        start = time.thread_time()
        try:
            samples = concatenate_samples(chunks)
            states = estimate_session(samples, base, t0_ns=t0_ns)
            self._result = ("ok", states, base)
        except Exception as err:  # noqa: BLE001 - reported as one line, the fusion goes on
            self._result = ("error", f"{type(err).__name__}: {err}".splitlines()[0], base)
        self._seconds = time.thread_time() - start

    def wait(self, timeout: float | None = None) -> None:
        """Wait for a running estimate (tests, shutdown)."""
        worker = self._worker
        if worker is not None:
            worker.join(timeout)

    # ------------------------------------------------------------------ reporting

    def line(self) -> str:
        """One console line on the states in use."""
        s = self.states
        if s is None:
            return "session states: not estimated yet (" + (self.last_note or "no attempt yet") + ")"
        parts = [f"session states estimated from {s.moving_seconds:.0f} s of motion"]
        for term, phases in s.phases.items():
            rate = s.common_rate_ppm.get(term)
            parts.append(f"{int(np.isfinite(phases).sum())} {term} phases"
                         + ("" if rate is None else f", common rate {rate:+.1f} ppm"))
        if s.stamp_offset is not None:
            parts.append(f"stamp clocks: offsets up to {1e3 * float(np.nanmax(np.abs(s.stamp_offset))):.3g} ms, "
                         f"skews up to {float(np.nanmax(np.abs(s.stamp_skew))):.3g} ppm")
        parts.append(f"in {self._seconds:.2g} s CPU")
        return ", ".join(parts)

    def values(self, now_ns: int) -> dict:
        """The /diagnostics values: state of the tracking, and the states in use per IMU."""
        s = self.states
        out = {"session_states": "estimated" if s is not None else "fallback",
               "session_window_moving_s": round(self.moving_seconds, 2),
               "session_estimates": self.estimates, "session_attempts": self.attempts,
               "session_failures": self.failures, "session_busy": self.busy}
        if self.error:
            out["session_error"] = self.error
        if s is None:
            out["session_note"] = self.last_note or "waiting for motion"
            return out
        out["session_moving_s"] = round(s.moving_seconds, 2)
        out["session_age_s"] = (int(now_ns) - self.estimated_at_ns) / 1e9
        names = self.base.names
        for term, phases in s.phases.items():
            if s.common_rate_ppm.get(term) is not None:
                out[f"{term}_common_rate_ppm"] = float(s.common_rate_ppm[term])
            for name, p in zip(names, phases):
                if np.isfinite(p):
                    out[f"{term}_phase_s/{name}"] = float(p)
        if s.stamp_offset is not None:
            for name, o, k in zip(names, s.stamp_offset, s.stamp_skew):
                out[f"stamp_clock_offset_s/{name}"] = float(o)
                out[f"stamp_clock_skew_ppm/{name}"] = float(k)
        return out


class BiasSessionTracker:
    """Live tracking of the gyroscope biases (:mod:`imu_array_ros.calibration.bias_tracking`), the same
    :class:`~imu_array_ros.calibration.bias_tracking.BiasTracker` ``imu-array fuse`` feeds the whole recording.

    :meth:`add` (a sink of :class:`~imu_array_ros.fusion.live.LiveFusion`: the raw samples as fused) only
    queues the samples; :meth:`poll`, between two fusion steps, hands back the updates a worker thread made
    and gives the worker the queued samples once they span ``batch_s`` (the still detection and the estimates
    are vectorised over them, off the hot path).  An update applies from the moment it is handed back
    (:meth:`apply`: the model with the tracked biases); a still interval counts once it ends or every
    ``max_piece_s`` while it lasts.  The updates equal the offline ones on the same samples, but for the
    last still interval of a recording (offline ends it at the end).
    """

    def __init__(self, model: SensorModel, *, batch_s: float = 0.5, **settings) -> None:
        from imu_array_ros.calibration.bias_tracking import BiasTracker

        self.tracker = BiasTracker(model, **settings)
        self.batch_ns = int(round(batch_s * 1e9))
        self.updates: list = []  # handed back so far
        self.error: str | None = None
        self._pending: list[ImuSamples] = []
        self._worker: threading.Thread | None = None
        self._result: tuple | None = None

    @property
    def names(self) -> tuple:
        return tuple(self.tracker.model.names)

    @property
    def busy(self) -> bool:
        return self._worker is not None

    def add(self, samples: ImuSamples, fused: FusedSamples | None = None) -> None:
        """The fusion's sink: queue the samples (nothing else on the hot path)."""
        if len(samples):
            self._pending.append(samples)

    def poll(self, t0_ns: int | None = None) -> list:
        """Updates (:class:`~imu_array_ros.calibration.bias_tracking.BiasUpdate`) made since the last call; starts
        the worker on the queued samples when they span ``batch_s``.  ``t0_ns``: the fusion's time origin (drifts
        count from it), taken once."""
        out = []
        if self._worker is not None and not self._worker.is_alive():
            self._worker = None
            kind, value = self._result
            self._result = None
            if kind == "error":
                self.error = value
            else:
                out = value
                self.updates += value
        if self.tracker.t0_ns is None and t0_ns is not None:
            self.tracker.t0_ns = int(t0_ns)
        if (self._worker is None and self._pending and self.tracker.t0_ns is not None
                and int(self._pending[-1].stamps[-1]) - int(self._pending[0].stamps[0]) >= self.batch_ns):
            chunks, self._pending = self._pending, []
            self._worker = threading.Thread(target=self._run, args=(chunks,), daemon=True, name="gyro-biases")
            self._worker.start()
        return out

    def _run(self, chunks: list) -> None:
        try:
            self._result = ("ok", self.tracker.add(concatenate_samples(chunks)))
        except Exception as err:  # noqa: BLE001 - reported as one line, the fusion goes on
            self._result = ("error", f"{type(err).__name__}: {err}".splitlines()[0])

    def wait(self, timeout: float | None = None) -> None:
        """Wait for a running worker (tests, shutdown)."""
        worker = self._worker
        if worker is not None:
            worker.join(timeout)

    @property
    def bias(self) -> np.ndarray:
        """(K, 3) rad/s, the biases in use (the description's before the first update)."""
        return self.updates[-1].bias if self.updates else self.tracker.initial

    def apply(self, model: SensorModel) -> SensorModel:
        """``model`` with the biases in use (unchanged before the first update)."""
        return model.with_terms(gyroscope_bias=self.bias) if self.updates else model

    def rebase(self, model: SensorModel) -> None:
        """A new description (a calibration reload): its intrinsics map the next measurements; the biases in use
        are kept (they are this session's)."""
        self.tracker.model = self.tracker.detector.model = model
        self.tracker.initial = model.terms["gyroscope_bias"].values.copy()

    def line(self, update) -> str:
        """One console line on an update."""
        change = np.abs(update.bias - update.before).max(axis=1)
        k = int(np.argmax(change))
        text = (f"gyroscope biases updated from {update.piece.seconds:.1f} s still (update {len(self.updates)}): "
                f"largest change {change[k]:.3g} rad/s ({self.names[k]})")
        jumps = update.jumps(self.names)
        return text + ("; moved by more than 3 sigma: " + ", ".join(jumps) if jumps else "")

    def values(self) -> dict:
        """The /diagnostics values: the biases in use per IMU and axis (rad/s) and their stds."""
        out = {"gyro_bias_updates": len(self.updates), "gyro_bias_busy": self.busy,
               "gyro_bias_source": "still intervals" if self.updates else "description"}
        if self.error:
            out["gyro_bias_error"] = self.error
        std = self.updates[-1].bias_std if self.updates else np.full_like(self.bias, np.nan)
        for name, b, s in zip(self.names, self.bias, std):
            for axis, v, sv in zip("xyz", b, s):
                out[f"gyro_bias_{axis}_rad_s/{name}"] = float(v)
                if np.isfinite(sv):
                    out[f"gyro_bias_{axis}_std_rad_s/{name}"] = float(sv)
        if self.updates:
            u = self.updates[-1]
            out["gyro_bias_last_still_s"] = round(u.piece.seconds, 2)
            out["gyro_bias_last_stamp_ns"] = u.piece.stop_ns
        return out
