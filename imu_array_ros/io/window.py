"""A sliding window of array samples from raw per-IMU messages (the calibration node's buffer).

:class:`SampleWindow` is the ROS-free part of ``calibration_node``:

1. :meth:`SampleWindow.add` decodes a batch of raw ``sensor_msgs/Imu`` payloads
   column-wise (:func:`~imu_array_ros.io.messages.decode_raw_imu`), counts and
   drops undecodable ones, wrong ``frame_id`` and non-finite values, and puts
   the rest into the stamp-keyed :class:`~imu_array_ros.io.sync.SampleAssembler`
   (:class:`~imu_array_ros.io.sync.RawIntake`, the input of :class:`~imu_array_ros.fusion.live.LiveFusion` too);
2. :meth:`SampleWindow.step` moves the ready array samples into a ring buffer
   that keeps the latest ``window_samples`` samples, or (``window_samples`` 0)
   the samples of the last ``window_s`` seconds of stamps (the buffer grows by
   doubling as the sample rate requires);
3. :meth:`SampleWindow.snapshot` returns a copy of the window, oldest first,
   taken under a lock: the calibration runs on it in another thread while
   ``add``/``step`` go on in the node's executor thread.

An array sample with IMUs missing (lost messages, ``sync_timeout``) keeps NaN
rows for them, as the fusion's input does; the calibration drops such samples.
Everything is vectorised over a batch; there is no per-message Python here.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from imu_array_ros.io.sync import RawIntake
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples

__all__ = ["SampleWindow", "WindowCounts"]


@dataclass
class WindowCounts:
    """What the window holds and has seen (one consistent reading, for /diagnostics).

    buffered: samples in the window; span_s: last - first stamp in it (s);
    fill: buffered / window_samples, or span / window_s (0..1); received: array
    samples that ever entered the window; messages and the rejected kinds:
    raw messages (the assembler's duplicate/backwards/late/incomplete counts too).
    """

    buffered: int
    span_s: float
    fill: float
    received: int
    counts: dict


class SampleWindow:
    """The latest array samples of one array's raw topics (see module docstring).

    Parameters
    ----------
    description : ArrayDescription
        IMU names (their order is the IMU index of :meth:`add`).
    frame_prefix : str
        Raw messages must carry ``frame_id = frame_prefix + name``.
    sync_timeout_s : float
        How long a sample waits for missing IMUs (:class:`SampleAssembler`).
    window_s : float
        Span of stamps kept when ``window_samples`` is 0.
    window_samples : int
        Number of samples kept (0: by ``window_s``).
    """

    def __init__(self, description: ArrayDescription, frame_prefix: str = "", sync_timeout_s: float = 0.05,
                 window_s: float = 10.0, window_samples: int = 0, *, capacity: int = 4096) -> None:
        if window_samples < 0 or (window_samples == 0 and not window_s > 0):
            raise ValueError("window_samples >= 1, or window_samples 0 and window_s > 0, is required")
        self.names = tuple(description.names)
        k = len(self.names)
        self.intake = RawIntake(self.names, frame_prefix, sync_timeout_s, capacity)
        self.assembler = self.intake.assembler
        self.window_samples = int(window_samples)
        self.window_ns = int(round(window_s * 1e9))
        self._lock = threading.Lock()
        size = self.window_samples or 256
        self._stamps = np.zeros(size, dtype=np.int64)
        self._acc = np.full((size, k, 3), np.nan)
        self._gyr = np.full((size, k, 3), np.nan)
        self._start = 0  # ring index of the oldest sample
        self._count = 0  # samples in the window
        self._received = 0

    # ------------------------------------------------------------------ input (executor thread)

    def add(self, payloads: Sequence[bytes], imu_index: Sequence[int] | np.ndarray, now_ns: int) -> None:
        """Decode and queue raw Imu payloads; ``imu_index[i]`` is the IMU whose topic payload i came on."""
        self.intake.add(payloads, imu_index, now_ns)

    def step(self, now_ns: int, *, flush: bool = False) -> int:
        """Move the ready samples (all pending ones with ``flush``) into the window; returns how many."""
        ready = self.assembler.pop(now_ns, flush=flush)
        if len(ready):
            self._append(ready.stamps, ready.accel, ready.gyro)
        return len(ready)

    def _append(self, stamps: np.ndarray, accel: np.ndarray, gyro: np.ndarray) -> None:
        with self._lock:
            self._received += len(stamps)
            if self.window_samples:
                keep = min(len(stamps), self.window_samples)
                stamps, accel, gyro = stamps[-keep:], accel[-keep:], gyro[-keep:]
                drop = max(0, self._count + keep - self.window_samples)
            else:
                newest = int(stamps[-1])
                horizon = newest - self.window_ns  # keep stamps >= horizon: a span of at most window_s
                first_new = int(np.searchsorted(stamps, horizon))
                stamps, accel, gyro = stamps[first_new:], accel[first_new:], gyro[first_new:]
                keep = len(stamps)
                drop = int(np.searchsorted(self._ordered_stamps(), horizon))
                if self._count - drop + keep > len(self._stamps):
                    self._grow(self._count - drop + keep)
            self._start = (self._start + drop) % len(self._stamps)
            self._count -= drop
            rows = (self._start + self._count + np.arange(keep)) % len(self._stamps)
            self._stamps[rows], self._acc[rows], self._gyr[rows] = stamps, accel, gyro
            self._count += keep

    def _ordered_stamps(self) -> np.ndarray:
        return self._stamps[(self._start + np.arange(self._count)) % len(self._stamps)]

    def _grow(self, needed: int) -> None:
        """Reallocate (under the lock) with room for ``needed`` samples, oldest first at index 0."""
        size = len(self._stamps)
        while size < needed:
            size *= 2
        rows = (self._start + np.arange(self._count)) % len(self._stamps)
        k = len(self.names)
        stamps, acc, gyr = np.zeros(size, dtype=np.int64), np.full((size, k, 3), np.nan), np.full((size, k, 3), np.nan)
        stamps[: self._count], acc[: self._count], gyr[: self._count] = self._stamps[rows], self._acc[rows], self._gyr[rows]
        self._stamps, self._acc, self._gyr, self._start = stamps, acc, gyr, 0

    # ------------------------------------------------------------------ output (any thread)

    def snapshot(self) -> ImuSamples:
        """A copy of the window, oldest first: stamps (N,) int64 ns strictly increasing, accel and
        gyro (N, K, 3) raw sensor-frame readings, NaN for IMUs missing from a sample."""
        with self._lock:
            rows = (self._start + np.arange(self._count)) % len(self._stamps)
            return ImuSamples(self._stamps[rows], self._acc[rows], self._gyr[rows], self.names)  # copies

    def __len__(self) -> int:
        return self._count

    def counts(self) -> WindowCounts:
        """Samples in the window, its span and fill, samples received, message counts."""
        with self._lock:
            n = self._count
            if n:
                first = int(self._stamps[self._start])
                last = int(self._stamps[(self._start + n - 1) % len(self._stamps)])
                span = (last - first) / 1e9
            else:
                span = 0.0
            received = self._received
        fill = n / self.window_samples if self.window_samples else min(1.0, span / (self.window_ns / 1e9))
        counts = dict(self.intake.counts.__dict__)
        counts.update(self.assembler.stats.as_dict())
        return WindowCounts(buffered=n, span_s=span, fill=fill, received=received, counts=counts)
