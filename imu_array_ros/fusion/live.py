"""Live fusion: serialized per-IMU messages in, serialized fused messages out.

The fusion node is a thin adapter around :class:`LiveFusion`; everything it does
to data happens here, ROS-free and testable without DDS:

1. :meth:`LiveFusion.add` decodes a batch of raw ``sensor_msgs/Imu`` payloads
   column-wise (:func:`~imu_array_ros.io.messages.decode_raw_imu`), rejects and
   counts undecodable ones, wrong ``frame_id`` and non-finite values, and puts
   the rest into the stamp-keyed :class:`~imu_array_ros.io.sync.SampleAssembler`;
2. :meth:`LiveFusion.step` takes the ready array samples and fuses them, at most
   ``max_batch`` at a time, with :class:`~imu_array_ros.fusion.model_fusion.ModelFusion`
   -- the object ``imu-array fuse`` uses, built the same way -- and returns the
   fused payloads (:func:`~imu_array_ros.io.messages.fused_payloads`, the
   writer of fused recordings);
3. the last ``window_ns`` of samples is kept for the diagnostics: the NIS ratio
   of the residuals (:func:`~imu_array_ros.fusion.residuals.normalized_residuals`,
   as ``imu-array residuals``), rates, and output latency.

Same numbers as the offline command: each sample is fused on its own, so
batching changes a value only by rounding (within 1e-12 relative, tested; a few vectorised
sums run in another order for another batch size), with one exception stated in
:mod:`~imu_array_ros.fusion.model_fusion`: a time-offset term compensates with
time derivatives of the estimate taken across neighbouring samples, which at a
batch edge are one-sided.  Bias drift counts from the first stamp fused, as
offline (the recording's first stamp).

:meth:`LiveFusion.set_description` swaps the description between two steps, so
a calibration reload loses no sample.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Sequence

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

__all__ = ["LiveFusion", "FusedBatch", "InputCounts", "WindowSummary", "build_fusion"]


def build_fusion(description: ArrayDescription, t0_ns: int | None = None) -> ModelFusion:
    """The fusion ``imu-array fuse`` runs for ``description`` (checked fusable first)."""
    check_identifiable(description.positions, len(description.imus), where=str(description.source))
    return ModelFusion(SensorModel.from_description(description), acc_range=description.accelerometer_range,
                       gyro_range=description.gyroscope_range, t0_ns=t0_ns)


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
    """

    def __init__(self, description: ArrayDescription, *, frame_prefix: str = "", sync_timeout_s: float = 0.05,
                 max_batch: int = 1000, window_s: float = 1.0, capacity: int = 4096) -> None:
        self.description = description
        self.names = tuple(description.names)
        self.fusion = build_fusion(description)
        self.intake = RawIntake(self.names, frame_prefix, sync_timeout_s, capacity)
        self.assembler = self.intake.assembler
        self.max_batch = int(max_batch)
        self.window_ns = int(round(window_s * 1e9))
        self.inputs: InputCounts = self.intake.counts
        self.fusion_stats = FusionStats()
        self._recent: deque = deque()  # (time_ns, samples, fused, ages) of recent batches
        self._arrivals: deque = deque()  # (time_ns, messages)

    # ------------------------------------------------------------------ input

    def add(self, payloads: Sequence[bytes], imu_index: Sequence[int] | np.ndarray, now_ns: int) -> None:
        """Decode and buffer raw Imu payloads; ``imu_index[i]`` is the IMU whose topic payload i came on."""
        if not len(payloads):
            return
        self.intake.add(payloads, imu_index, now_ns)
        self._arrivals.append((int(now_ns), len(payloads)))

    def set_description(self, description: ArrayDescription) -> None:
        """Fuse from now on with ``description`` (same IMU names and order); raises ConfigError."""
        if tuple(description.names) != self.names:
            raise ConfigError(f"{description.source}: IMU names {list(description.names)[:4]}... differ from the "
                              f"running array's {list(self.names)[:4]}...")
        fusion = build_fusion(description, t0_ns=self.fusion.t0_ns)
        self.description, self.fusion = description, fusion

    # ------------------------------------------------------------------ fusion

    def step(self, now_ns: int, *, flush: bool = False) -> list[FusedBatch]:
        """Fuse every ready sample (all buffered ones with ``flush``); batches in stamp order."""
        ready = self.assembler.pop(now_ns, flush=flush)
        out = []
        for lo in range(0, len(ready), self.max_batch):
            hi = min(lo + self.max_batch, len(ready))
            samples = ImuSamples(ready.stamps[lo:hi], ready.accel[lo:hi], ready.gyro[lo:hi], self.names)
            fused, stats = self.fusion.fuse(samples)
            self.fusion_stats.merge(stats)
            imu, acc = fused_payloads(fused, self.description.frame_id)
            self._recent.append((int(now_ns), samples, fused, None))
            out.append(FusedBatch(fused, imu, acc))
        self._trim(now_ns)
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

    def summary(self, now_ns: int) -> WindowSummary:
        """Rates, NIS ratio and latency over the last window (the node's /diagnostics)."""
        from imu_array_ros.fusion.residuals import normalized_residuals

        self._trim(now_ns)
        span = self.window_ns / 1e9
        batches = [(s, f) for _, s, f, _ in self._recent if s is not None and len(f)]
        ages = [a for *_, a in self._recent if a is not None]
        nis = nis_exp = 0.0
        n_nis = 0
        if batches:
            samples = ImuSamples(np.concatenate([s.stamps for s, _ in batches]),
                                 np.concatenate([s.accel for s, _ in batches]),
                                 np.concatenate([s.gyro for s, _ in batches]), self.names)
            fused = concatenate_fused([f for _, f in batches])
            order = np.argsort(samples.stamps, kind="stable")
            samples = samples.select(order)
            rep = normalized_residuals(samples, self.fusion.model, fused)
            nis, nis_exp, n_nis = float(rep.nis.sum()), float(rep.nis_expected.sum()), len(fused)
        lat = np.concatenate(ages) if ages else np.zeros(0)
        counts = dict(self.inputs.__dict__)
        counts.update(self.assembler.stats.as_dict())
        fs = self.fusion_stats
        counts.update(fused=fs.fused, skipped_unidentifiable=fs.skipped_unidentifiable,
                      saturated_gyro_samples=fs.saturated_gyro_samples, not_converged=fs.not_converged)
        return WindowSummary(
            input_rate=sum(n for _, n in self._arrivals) / span,
            fused_rate=sum(len(f) for _, f in batches) / span,
            nis_ratio=nis / nis_exp if nis_exp > 0 else float("nan"),
            nis_samples=n_nis,
            latency_p50=float(np.percentile(lat, 50)) if len(lat) else float("nan"),
            latency_p99=float(np.percentile(lat, 99)) if len(lat) else float("nan"),
            counts=counts,
        )
