"""Live fusion: serialized per-IMU messages in, serialized fused messages out.

The fusion node is a thin adapter around :class:`LiveFusion`; everything it does
to data happens here, ROS-free and testable without DDS:

1. :meth:`LiveFusion.add` decodes a batch of raw ``sensor_msgs/Imu`` payloads
   column-wise (:func:`~imu_array_ros.io.messages.decode_raw_imu`), rejects and
   counts undecodable ones, wrong ``frame_id`` and non-finite values, and puts
   the rest into the stamp-keyed :class:`~imu_array_ros.io.sync.SampleAssembler`
   -- or, for IMUs that stamp their own messages (``own_stamps=True``), the
   :class:`~imu_array_ros.io.live_pairing.PairingAssembler`, which pairs them onto
   the reference IMU's stamps and hands out every message's own stamp;
2. :meth:`LiveFusion.step` takes the ready array samples and fuses them, at most
   ``max_batch`` at a time, with :class:`~imu_array_ros.fusion.model_fusion.ModelFusion`
   -- the object ``imu-array fuse`` uses, built the same way -- and returns the
   fused payloads (:func:`~imu_array_ros.io.messages.fused_payloads`, the
   writer of fused recordings), each stamped with the array (grid) stamp its
   estimate refers to;
3. the last ``window_ns`` of samples is kept for the diagnostics: the NIS ratio
   of the residuals (:func:`~imu_array_ros.fusion.residuals.normalized_residuals`,
   as ``imu-array residuals``), rates, and output latency.

Same numbers as the offline command.  Without timing (no timing term away from
its identity, common stamps) each sample is fused on its own, so batching
changes a value only by rounding (within 1e-12 relative, tested; a few
vectorised sums run in another order for another batch size).  *Time-aware*
fusion (timing terms, or own stamps) evaluates every reading along local cubics
through the fused estimates of the neighbouring samples
(:mod:`~imu_array_ros.model.trajectory`), which reach ``half`` samples to each
side per compensation pass.  So each call fuses its samples together with
``passes * half + 1`` samples of *context* on both sides -- the last ones
published before, and the next ones, which are held back until they have
arrived (the *lookahead*: about ``passes`` x 12.5 ms, at least ``passes`` x 2
samples; after the first sample one half width more) -- and publishes the
middle only.  Every published sample then saw the same neighbours as offline:
with a compensation that depends on those neighbours only, it equals the
offline fusion with the same model bit for bit (tested), except where the
stream paused for longer than the lookahead (the held samples go out with what
has arrived, as at the end of a recording).  The compensation as it stands also
takes one constant over the whole call (the gyroscopes' rate offset,
:func:`~imu_array_ros.model.trajectory.fused_timing_context`), which a live call
of a few dozen samples cannot share with the offline one: typically 0.3, at
most ~1 Cramér-Rao standard deviation apart (tested).  A time-aware call costs
~10 ms for 32 IMUs whatever its size, so it fuses at least ``timed_batch_s`` of
samples at a time.
Bias drift and the clocks count from the first stamp fused, as offline (the
recording's first stamp).

:meth:`LiveFusion.set_description` swaps the description, :meth:`LiveFusion.set_model`
the sensor model (e.g. with this session's clock states, estimated off the hot
path by :mod:`imu_array_ros.workflows.live_session`), between two steps, so
neither loses a sample.  ``sink(samples, fused)``, when given, sees every batch
published (the raw samples as fused, own stamps included, and their estimates).

Event-driven fusion: :class:`~imu_array_ros.io.live_queue.CompletionQueue` takes the serialized messages from the
subscription callbacks and tells, per message and without decoding it (its stamp's 8
bytes as a key, one bit per IMU), when it completed its array sample; the node then
drains the queue into :meth:`LiveFusion.add` and :meth:`LiveFusion.step` at once, so a
complete sample is fused without waiting for a timer (the timer only sweeps samples
whose ``sync_timeout`` has passed).  When messages back up
(:class:`~imu_array_ros.io.live_queue.BacklogGate`), completed samples wait and are fused together.  The diagnostics are split so that only a cheap
copy is taken on the fusing thread (:meth:`LiveFusion.snapshot`) and the NIS ratio
and quantiles are computed elsewhere (:func:`summarize`, e.g. in a worker thread).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, fields
from typing import Callable, Sequence

import numpy as np

from imu_array_ros.errors import ConfigError
from imu_array_ros.fusion.ml_fusion import FusionStats
from imu_array_ros.fusion.model_fusion import ModelFusion
from imu_array_ros.fusion.stream import concatenate_fused
from imu_array_ros.io.messages import fused_payloads
from imu_array_ros.io.sync import InputCounts, RawIntake
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.identifiability import check_identifiable
from imu_array_ros.model.samples import FusedSamples, ImuSamples
from imu_array_ros.model.trajectory import MIN_HALF, WINDOW_S

__all__ = ["LiveFusion", "FusedBatch", "InputCounts", "WindowSummary", "WindowSnapshot", "build_fusion",
           "concatenate_samples", "context_size", "summarize"]

#: stamps of skipped samples kept in the counts
MAX_SKIPPED_STAMPS = 10


def build_fusion(description: ArrayDescription, t0_ns: int | None = None) -> ModelFusion:
    """The fusion ``imu-array fuse`` runs for ``description`` (checked fusable first)."""
    check_identifiable(description.positions, len(description.imus), where=str(description.source))
    return ModelFusion(SensorModel.from_description(description), acc_range=description.accelerometer_range,
                       gyro_range=description.gyroscope_range, t0_ns=t0_ns)


def concatenate_samples(parts: Sequence[ImuSamples]) -> ImuSamples:
    """One :class:`ImuSamples` from consecutive parts of one array (own stamps kept when every part has them)."""
    parts = [p for p in parts if p is not None]
    if len(parts) == 1:
        return parts[0]
    own = [p.own_stamps for p in parts]
    return ImuSamples(np.concatenate([p.stamps for p in parts]), np.concatenate([p.accel for p in parts]),
                      np.concatenate([p.gyro for p in parts]), parts[0].names,
                      None if any(o is None for o in own) else np.concatenate(own))


def context_size(spacing_ns: float, passes: int, *, start: bool = False) -> int:
    """Samples of context a time-aware fusion needs on each side of a sample for its estimate to be what it
    is inside a whole recording: ``passes`` times the local cubics' half width (at the median stamp spacing
    ``spacing_ns``; rounded up, so a spacing at a rounding edge is covered), plus one.  ``start``: after the
    stream's first sample, whose windows are shifted forward (as offline), one half width more ahead."""
    half = max(MIN_HALF, math.ceil(0.5 * WINDOW_S / max(float(spacing_ns) * 1e-9, 1e-9) - 1e-9))
    return (int(passes) + bool(start)) * half + 1


def _select_fused(fused: FusedSamples, mask: np.ndarray) -> FusedSamples:
    return FusedSamples(**{f.name: None if getattr(fused, f.name) is None else getattr(fused, f.name)[mask]
                           for f in fields(FusedSamples)})


@dataclass
class FusedBatch:
    """One fused batch: the estimates and their payloads, ready to publish in order."""

    fused: FusedSamples
    imu_payloads: np.ndarray  # (N, L1) uint8
    accel_payloads: np.ndarray  # (N, L2) uint8


@dataclass
class WindowSummary:
    """Diagnostics over the last window: rates (per second), NIS ratio, latency quantiles (s)."""

    input_rate: float
    fused_rate: float
    nis_ratio: float
    nis_samples: int
    latency_p50: float
    latency_p99: float
    counts: dict = field(default_factory=dict)


@dataclass
class WindowSnapshot:
    """What :func:`summarize` needs, copied on the fusing thread (cheap): the last window's batches."""

    window_s: float
    recent: list
    arrivals: list
    counts: dict
    model: SensorModel
    timed: bool


class LiveFusion:
    """Streaming ML fusion of one array's raw messages (see module docstring).

    Parameters
    ----------
    description : ArrayDescription
    frame_prefix : str
        Raw messages must carry ``frame_id = frame_prefix + name``.
    sync_timeout_s : float
        How long a sample waits for missing IMUs (:class:`SampleAssembler`).
    max_batch : int
        Most samples per fusion call.
    window_s : float
        Span of the diagnostics window.
    own_stamps : bool
        The IMUs stamp their own messages: paired onto the stamps of IMU ``reference`` (an index).
    timed_batch_s : float
        Time-aware fusion: the least span of samples fused per call (not at a pause or a flush).
    sink : callable(samples, fused), optional
        Called with every batch published.
    """

    def __init__(self, description: ArrayDescription, *, frame_prefix: str = "", sync_timeout_s: float = 0.05,
                 max_batch: int = 1000, window_s: float = 1.0, capacity: int = 4096, own_stamps: bool = False,
                 reference: int = 0, timed_batch_s: float = 0.05,
                 sink: Callable[[ImuSamples, FusedSamples], None] | None = None) -> None:
        self.description = description
        self.names = tuple(description.names)
        self.own_stamps = bool(own_stamps)
        self._use(build_fusion(description))
        self.reference = int(reference)
        self.intake = RawIntake(self.names, frame_prefix, sync_timeout_s, capacity, own_stamps=self.own_stamps,
                                reference=self.reference)
        self.assembler = self.intake.assembler
        self.max_batch = int(max_batch)
        self.window_ns = int(round(window_s * 1e9))
        self.timeout_ns = int(round(sync_timeout_s * 1e9))
        self.timed_batch_ns = int(round(timed_batch_s * 1e9))
        self.sink = sink
        self.inputs: InputCounts = self.intake.counts
        self.fusion_stats = FusionStats()
        self._recent: deque = deque()  # (time_ns, samples, fused, ages) of recent batches
        self._arrivals: deque = deque()  # (time_ns, messages)
        self._before: ImuSamples | None = None  # time-aware: the last samples published (the next call's context)
        self._held: ImuSamples | None = None  # time-aware: ready samples waiting for their lookahead
        self._held_since = 0  # when the newest held sample became ready (node clock, ns)

    @property
    def timed(self) -> bool:
        """True when the fusion is time-aware: a timing term away from its identity, or own stamps."""
        return self._timed

    def _use(self, fusion: ModelFusion) -> None:
        self.fusion = fusion
        self._timed = self.own_stamps or fusion.model.timed  # once per model: not on the hot path

    @property
    def held(self) -> int:
        """Ready samples held back for their lookahead (time-aware fusion)."""
        return 0 if self._held is None else len(self._held)

    # ------------------------------------------------------------------ input

    def add(self, payloads: Sequence[bytes], imu_index: Sequence[int] | np.ndarray, now_ns: int) -> None:
        """Decode and buffer raw Imu payloads; ``imu_index[i]`` is the IMU whose topic payload i came on."""
        if not len(payloads):
            return
        self.intake.add(payloads, imu_index, now_ns)
        self._arrivals.append((int(now_ns), len(payloads)))

    def set_description(self, description: ArrayDescription) -> None:
        """Fuse from now on with ``description`` (same IMU names and order); raises ConfigError."""
        self._check_names(description.names, description.source)
        fusion = build_fusion(description, t0_ns=self.fusion.t0_ns)
        self.description = description
        self._use(fusion)

    def set_model(self, model: SensorModel) -> None:
        """Fuse from now on with ``model`` (same IMU names and order; e.g. the description's model with this
        session's clock states), keeping the time origin, the ranges and the settings; raises ConfigError."""
        self._check_names(model.names, "the model")
        f = self.fusion
        self._use(ModelFusion(model, f.config, passes=f.passes, acc_range=f.linear.acc_range,
                              gyro_range=f.linear.gyro_range, t0_ns=f.t0_ns))

    def _check_names(self, names, source) -> None:
        if tuple(names) != self.names:
            raise ConfigError(f"{source}: IMU names {list(names)[:4]}... differ from the "
                              f"running array's {list(self.names)[:4]}...")

    # ------------------------------------------------------------------ fusion

    def step(self, now_ns: int, *, flush: bool = False) -> list[FusedBatch]:
        """Fuse every ready sample (all buffered ones with ``flush``); batches in stamp order."""
        ready = self.assembler.pop(now_ns, flush=flush)
        if self._timed or self._held is not None:
            out = self._step_timed(ready, int(now_ns), flush)
        else:
            out = []
            for lo in range(0, len(ready), self.max_batch):
                hi = min(lo + self.max_batch, len(ready))
                samples = ImuSamples(ready.stamps[lo:hi], ready.accel[lo:hi], ready.gyro[lo:hi], self.names)
                fused, stats = self.fusion.fuse(samples)
                out.append(self._emit(now_ns, samples, fused, stats))
        self._trim(now_ns)
        return out

    def _emit(self, now_ns: int, samples: ImuSamples, fused: FusedSamples, stats: FusionStats) -> FusedBatch:
        self.fusion_stats.merge(stats)
        imu, acc = fused_payloads(fused, self.description.frame_id)
        self._recent.append((int(now_ns), samples, fused, None))
        if self.sink is not None:
            self.sink(samples, fused)
        return FusedBatch(fused, imu, acc)

    def _step_timed(self, ready, now_ns: int, flush: bool) -> list[FusedBatch]:
        """Time-aware: fuse the held and ready samples whose lookahead has arrived, with context on both sides."""
        pending = self._held
        if len(ready):
            new = ImuSamples(ready.stamps, ready.accel, ready.gyro, self.names, ready.own_stamps)
            pending = new if pending is None else concatenate_samples([pending, new])
            self._held_since = now_ns
        if pending is None or not len(pending):
            self._held = None
            return []
        known = pending.stamps if self._before is None else np.concatenate([self._before.stamps, pending.stamps])
        if len(known) < 2:  # no spacing yet: wait for the next sample
            c, spacing = 1, 0.0
        else:
            spacing = float(np.median(np.diff(known[-64:])))
            c = context_size(spacing, self.fusion.passes, start=self._before is None)
        # the stream paused: no lookahead is coming, the held samples go with what has arrived
        paused = now_ns - self._held_since >= self.timeout_ns + (c + 1) * spacing + self.timed_batch_ns
        if flush or paused or not self.timed:
            count = len(pending)
        elif spacing <= 0:
            count = 0
        else:
            count = len(pending) - c
            if count * spacing < self.timed_batch_ns:
                count = 0
        out = []
        before = self._before
        for lo in range(0, count, self.max_batch):
            hi = min(lo + self.max_batch, count)
            core = pending.select(slice(lo, hi))
            if not self.timed:  # no longer time-aware (a new model): samples on their own
                fused, stats = self.fusion.fuse(core)
            else:
                batch = concatenate_samples([before, core, pending.select(slice(hi, hi + c))])
                fused, stats = self.fusion.fuse(batch)
                keep = (fused.stamps >= core.stamps[0]) & (fused.stamps <= core.stamps[-1])
                fused, stats = _select_fused(fused, keep), self._core_stats(core, fused, keep, stats)
            out.append(self._emit(now_ns, core, fused, stats))
            tail = concatenate_samples([before, core])
            before = tail.select(slice(max(0, len(tail) - c), len(tail)))  # (at the start: more than needed)
        self._before = before
        self._held = pending.select(slice(count, len(pending))) if count < len(pending) else None
        return out

    def _core_stats(self, core: ImuSamples, fused: FusedSamples, keep: np.ndarray, stats: FusionStats) -> FusionStats:
        """The counts of the published samples ``core`` of a call that fused context around them too."""
        n, done = len(core), int(keep.sum())
        finite = np.isfinite(core.readings)
        saturated = finite & ~core.valid(self.fusion.model)
        out = FusionStats(samples=n, fused=done, skipped_unidentifiable=n - done, patterns=stats.patterns,
                          incomplete_samples=int((~finite).any(axis=(1, 2)).sum()),
                          saturated_gyro_samples=int(saturated[..., 3:].any(axis=(1, 2)).sum()),
                          saturated_accel_samples=int(saturated[..., :3].any(axis=(1, 2)).sum()))
        if fused.converged is not None:
            out.not_converged = int((~fused.converged[keep]).sum())
        if done < n:
            out.skipped_stamps = core.stamps[~np.isin(core.stamps, fused.stamps[keep])][:MAX_SKIPPED_STAMPS].tolist()
        return out

    def record_latency(self, now_ns: int, stamps: np.ndarray) -> None:
        """Note that fused samples with these stamps were published at ``now_ns`` (same clock as stamps)."""
        if len(stamps):
            self._recent.append((int(now_ns), None, None, (int(now_ns) - np.asarray(stamps, np.int64)) / 1e9))

    def _trim(self, now_ns: int) -> None:
        horizon = int(now_ns) - self.window_ns
        while self._recent and self._recent[0][0] < horizon:
            self._recent.popleft()
        while self._arrivals and self._arrivals[0][0] < horizon:
            self._arrivals.popleft()

    # ------------------------------------------------------------------ diagnostics

    def snapshot(self, now_ns: int) -> WindowSnapshot:
        """The diagnostics' inputs over the last window, copied (cheap: for the fusing thread)."""
        self._trim(now_ns)
        counts = dict(self.inputs.__dict__)
        counts.update(self.assembler.stats.as_dict())
        fs = self.fusion_stats
        counts.update(fused=fs.fused, skipped_unidentifiable=fs.skipped_unidentifiable,
                      saturated_gyro_samples=fs.saturated_gyro_samples, not_converged=fs.not_converged)
        if self.timed:
            counts.update(held_samples=self.held)
        return WindowSnapshot(self.window_ns / 1e9, list(self._recent), list(self._arrivals), counts,
                              self.fusion.model, self.timed)

    def summary(self, now_ns: int) -> WindowSummary:
        """Rates, NIS ratio and latency over the last window (:func:`summarize` of :meth:`snapshot`)."""
        return summarize(self.snapshot(now_ns))


def summarize(snap: WindowSnapshot) -> WindowSummary:
    """Rates, NIS ratio and latency quantiles of a :class:`WindowSnapshot` (the costly part of the
    diagnostics: the residuals of every sample of the window; safe in another thread)."""
    from imu_array_ros.fusion.residuals import normalized_residuals

    span = snap.window_s
    batches = [(s, f) for _, s, f, _ in snap.recent if s is not None and len(f)]
    ages = [a for *_, a in snap.recent if a is not None]
    nis = nis_exp = 0.0
    n_nis = 0
    if batches:
        samples = concatenate_samples([s for s, _ in batches])
        fused = concatenate_fused([f for _, f in batches])
        order = np.argsort(samples.stamps, kind="stable")
        samples = samples.select(order)
        rep = normalized_residuals(samples, snap.model, fused)
        nis, nis_exp, n_nis = float(rep.nis.sum()), float(rep.nis_expected.sum()), len(fused)
    lat = np.concatenate(ages) if ages else np.zeros(0)
    return WindowSummary(
        input_rate=sum(n for _, n in snap.arrivals) / span,
        fused_rate=sum(len(f) for _, f in batches) / span,
        nis_ratio=nis / nis_exp if nis_exp > 0 else float("nan"),
        nis_samples=n_nis,
        latency_p50=float(np.percentile(lat, 50)) if len(lat) else float("nan"),
        latency_p99=float(np.percentile(lat, 99)) if len(lat) else float("nan"),
        counts=snap.counts,
    )
