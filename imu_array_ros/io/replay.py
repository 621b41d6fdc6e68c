"""Replay of a recording in real time (the driver node's ``replay`` mode).

:class:`Replay` reads the IMU topics of a recording with the columnar reader
(:func:`~imu_array_ros.io.rosbag.recording.read_imu_recording`) and hands out the
array samples that are due ``elapsed`` nanoseconds after the start: sample i
is due at ``(stamp_i - stamp_0) / rate``.  ``rate = 0`` hands out up to
``burst`` samples per call regardless of time (the node then waits for its
subscribers to acknowledge before asking again).  With ``loop``, the recording
starts again after its last sample, one median sample interval later, with
stamps shifted by the recording's span so that they keep increasing.
With ``restamp_ns`` (the wall time of the start), samples are stamped with the
wall time they fall due instead of the recorded time (``rate = 0``: the time
of the call, 1 ns apart).

IMUs with their own stamps (a recording read with ``own_stamps``, see
:mod:`imu_array_ros.io.pairing`): the samples handed out keep every message's
own recorded stamp in ``own_stamps`` (shifted with the loop), and the messages
the pairing left unused come as rows of their own, so every message is
replayed; timing follows the grid (the reference IMU's stamps).  Restamped, each own stamp moves with its
array sample's stamp, so the IMUs keep their recorded offsets from each other.
Publish with :func:`~imu_array_ros.io.rosbag.recording.imu_payloads`, which
stamps every message with its own stamp.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples, ReadStats

__all__ = ["Replay"]


class Replay:
    """Hands out the samples of a recording as they fall due (see module docstring)."""

    def __init__(self, path, description: ArrayDescription, *, rate: float = 1.0, loop: bool = False,
                 topic_prefix: str = "/imu_array", burst: int = 200) -> None:
        from imu_array_ros.io.rosbag.recording import read_imu_recording

        if rate < 0:
            raise ValueError("rate must be >= 0")
        samples, stats = read_imu_recording(path, description, topic_prefix=topic_prefix, unused_rows=True)
        self.samples: ImuSamples = samples
        self.read_stats: ReadStats = stats
        self.rate = float(rate)
        self.loop = bool(loop)
        self.burst = int(burst)
        st = samples.stamps
        step = int(np.median(np.diff(st))) if len(st) > 1 else 1
        self.period_ns = int(st[-1] - st[0]) + max(step, 1) if len(st) else 0
        self._offset = (st - st[0]) if len(st) else st  # ns from the first sample
        self._next = 0  # next sample index in the current pass
        self._pass = 0

    @property
    def done(self) -> bool:
        """Every sample handed out (never, with loop)."""
        return not self.loop and self._next >= len(self.samples)

    def due(self, elapsed_ns: int, restamp_ns: int | None = None) -> ImuSamples:
        """The samples due by ``elapsed_ns`` after the start that were not handed out yet."""
        n = len(self.samples)
        parts, taken = [], 0
        while n and not self.done and not (self.rate == 0 and taken >= self.burst):
            if self.rate == 0:
                hi = min(self._next + self.burst - taken, n)
            else:
                local = elapsed_ns * self.rate - self._pass * self.period_ns
                hi = int(np.searchsorted(self._offset, local, side="right"))
            if hi <= self._next:
                break
            parts.append((np.arange(self._next, hi), self._pass))
            taken += hi - self._next
            self._next = hi
            if self._next >= n and self.loop:
                self._next, self._pass = 0, self._pass + 1
        if not parts:
            return self.samples.select(slice(0, 0))
        idx = np.concatenate([p[0] for p in parts])
        shift = np.concatenate([np.full(len(p[0]), p[1] * self.period_ns, dtype=np.int64) for p in parts])
        out = self.samples.select(idx)
        stamps = out.stamps + shift
        if restamp_ns is not None:
            if self.rate:
                due = ((self._offset[idx] + shift) / self.rate).astype(np.int64)
            else:  # as fast as possible: stamped now, 1 ns apart
                due = int(elapsed_ns) + np.arange(len(idx), dtype=np.int64)
            stamps = int(restamp_ns) + due
        if out.own_stamps is not None:  # each message's own stamp moves with its array sample's
            out.own_stamps = out.own_stamps + (stamps - out.stamps)[:, None]
        out.stamps = stamps
        return out
