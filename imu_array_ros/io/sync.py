"""Group per-IMU messages into array samples by stamp (the fusion node's input buffer).

Every IMU of one array sample carries the same ``header.stamp`` (recording
contract).  :class:`SampleAssembler` collects decoded messages of all IMUs in a
bounded buffer keyed by stamp and hands out array samples in stamp order:

* a sample is **ready** when every IMU missing from it is known not to deliver
  it: the IMU has already delivered a *later* stamp (messages of one topic
  arrive in order, so the missing one is lost, not late), or it has been silent
  -- no message at all -- for ``timeout_ns`` since the sample's first message
  arrived (so after a pause in the stream the first sample still waits).  An IMU that is merely behind
  (a burst queued in the executor) is waited for, however long its messages
  take, as long as they keep coming;
* samples leave strictly in stamp order: a sample that is not ready holds back
  the later ones (head of line), so the output stream never goes backwards;
* a sample handed out with IMUs missing has NaN rows for them (the fusion uses
  those present) and is counted as incomplete;
* when more than ``capacity`` samples are pending, the oldest are handed out
  as they are and counted as ``overflow``.

IMUs that stamp their own messages (own drivers and clocks) are paired onto the
reference IMU's stamps instead: :class:`~imu_array_ros.io.live_pairing.PairingAssembler`
(the same interface; ``RawIntake(..., own_stamps=True)``).

Rejected messages, each counted by kind and never used: ``duplicate`` (an IMU's
stamp equal to its previous one), ``backwards`` (an IMU's stamp below its
previous one), ``late`` (a stamp at or before the last sample handed out).
Everything is vectorised over a batch of messages; per-message Python is left
to the subscription callbacks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.io.messages import decode_raw_imu

__all__ = ["SampleAssembler", "AssemblerStats", "AssembledSamples", "RawIntake", "InputCounts"]


@dataclass
class AssemblerStats:
    """Running counts (messages unless said otherwise)."""

    accepted: int = 0
    duplicate: int = 0
    backwards: int = 0
    late: int = 0
    complete_samples: int = 0
    incomplete_samples: int = 0
    overflow_samples: int = 0
    missing_messages: int = 0  # IMU slots empty in the samples handed out

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class AssembledSamples:
    """Array samples handed out: stamps (P,), accel/gyro (P, K, 3) NaN where missing; own_stamps
    (P, K) each message's own stamp (the grid stamp where missing) from a
    :class:`~imu_array_ros.io.live_pairing.PairingAssembler`, None from a :class:`SampleAssembler`."""

    stamps: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray
    own_stamps: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.stamps)


class SampleAssembler:
    """Bounded stamp-keyed buffer of ``n_imus`` streams (see module docstring).

    Parameters
    ----------
    n_imus : int
    timeout_ns : int
        How long an IMU may be silent before the samples it is missing from go without it.
    capacity : int
        Most samples pending at once.
    """

    def __init__(self, n_imus: int, *, timeout_ns: int, capacity: int = 4096) -> None:
        if n_imus < 1 or timeout_ns < 0 or capacity < 1:
            raise ValueError("n_imus >= 1, timeout_ns >= 0 and capacity >= 1 are required")
        self.n_imus = int(n_imus)
        self.timeout_ns = int(timeout_ns)
        self.capacity = int(capacity)
        self.stats = AssemblerStats()
        k = self.n_imus
        self._stamps = np.zeros(0, dtype=np.int64)
        self._acc = np.zeros((0, k, 3))
        self._gyr = np.zeros((0, k, 3))
        self._have = np.zeros((0, k), dtype=bool)
        self._first = np.zeros(0, dtype=np.int64)
        self._latest = np.full(k, np.iinfo(np.int64).min)  # last accepted stamp per IMU
        self._heard: np.ndarray | None = None  # when each IMU's last message arrived (ns)
        self._last_out = np.iinfo(np.int64).min  # stamp of the last sample handed out

    @property
    def pending(self) -> int:
        """Samples waiting in the buffer."""
        return len(self._stamps)

    def add(self, imu_index: np.ndarray, stamps: np.ndarray, accel: np.ndarray, gyro: np.ndarray,
            arrival_ns: int) -> np.ndarray:
        """Add M messages (in arrival order); returns (M,) bool: accepted.

        imu_index (M,) int in [0, n_imus); stamps (M,) int64 ns; accel, gyro (M, 3).
        """
        idx = np.asarray(imu_index, dtype=np.int64).reshape(-1)
        st = np.asarray(stamps, dtype=np.int64).reshape(-1)
        m = len(idx)
        ok = np.ones(m, dtype=bool)
        if m == 0:
            return ok
        if self._heard is None:  # an IMU that never speaks is silent from the first message on
            self._heard = np.full(self.n_imus, int(arrival_ns), dtype=np.int64)
        if idx.min() < 0 or idx.max() >= self.n_imus:
            raise ValueError(f"imu_index outside [0, {self.n_imus})")
        once = bool((np.bincount(idx, minlength=self.n_imus) <= 1).all())  # one message per IMU (a live sample)
        if once:
            prev = self._latest[idx]
        else:
            prev = self._previous(idx, st)
        dup = st == prev
        back = st < prev
        late = ~dup & ~back & (st <= self._last_out)
        ok = ~(dup | back | late)
        self.stats.duplicate += int(dup.sum())
        self.stats.backwards += int(back.sum())
        self.stats.late += int(late.sum())
        self.stats.accepted += int(ok.sum())
        self._heard[idx] = int(arrival_ns)  # rejected or not, the IMU is alive
        if not ok.any():
            return ok
        if once:
            self._latest[idx[ok]] = st[ok]  # above the previous stamp: neither a duplicate nor backwards
        else:
            np.maximum.at(self._latest, idx[ok], st[ok])
        self._insert(idx[ok], st[ok], np.asarray(accel, float).reshape(-1, 3)[ok],
                     np.asarray(gyro, float).reshape(-1, 3)[ok], int(arrival_ns))
        return ok

    def _previous(self, idx: np.ndarray, st: np.ndarray) -> np.ndarray:
        """Previous stamp of the same IMU for each message, in arrival order: the stored latest or the batch's
        running max."""
        m = len(idx)
        order = np.lexsort((np.arange(m), idx))
        prev = np.empty(m, dtype=np.int64)
        s_sorted, i_sorted = st[order], idx[order]
        starts = np.flatnonzero(np.r_[True, i_sorted[1:] != i_sorted[:-1]])
        group = np.repeat(starts, np.diff(np.r_[starts, m]))
        running = s_sorted.copy()
        for a, b in zip(starts, np.r_[starts[1:], m]):  # at most n_imus groups
            running[a:b] = np.maximum.accumulate(s_sorted[a:b])
        shifted = np.empty(m, dtype=np.int64)
        shifted[1:] = running[:-1]
        first_of_group = np.arange(m) == group
        shifted[first_of_group] = self._latest[i_sorted[first_of_group]]
        shifted[~first_of_group] = np.maximum(shifted[~first_of_group], self._latest[i_sorted[~first_of_group]])
        prev[order] = shifted
        return prev

    def _insert(self, idx, st, acc, gyr, arrival_ns) -> None:
        new = np.setdiff1d(np.unique(st), self._stamps, assume_unique=True)
        if len(new):
            k = self.n_imus
            stamps = np.concatenate([self._stamps, new])
            # new stamps after every buffered one (np.unique sorts them): appended in order
            order = slice(None) if not len(self._stamps) or new[0] > self._stamps[-1] else np.argsort(stamps, kind="stable")
            n_new = len(new)
            self._stamps = stamps[order]
            self._acc = np.concatenate([self._acc, np.full((n_new, k, 3), np.nan)])[order]
            self._gyr = np.concatenate([self._gyr, np.full((n_new, k, 3), np.nan)])[order]
            self._have = np.concatenate([self._have, np.zeros((n_new, k), dtype=bool)])[order]
            self._first = np.concatenate([self._first, np.full(n_new, arrival_ns, dtype=np.int64)])[order]
        row = np.searchsorted(self._stamps, st)
        self._acc[row, idx] = acc
        self._gyr[row, idx] = gyr
        self._have[row, idx] = True

    def pop(self, now_ns: int, *, flush: bool = False) -> AssembledSamples:
        """Hand out the ready samples (all pending ones with ``flush``), oldest first."""
        n = len(self._stamps)
        if n == 0:
            return self._take(0)
        if flush:
            count = n
        else:
            lost = self._latest[None, :] > self._stamps[:, None]
            # silent: nothing from the IMU for timeout_ns, counted from when the sample appeared at the earliest
            since = np.maximum(self._heard[None, :], self._first[:, None])
            silent = int(now_ns) - since >= self.timeout_ns
            ready = (self._have | lost | silent).all(axis=1)
            blocked = np.flatnonzero(~ready)
            count = int(blocked[0]) if len(blocked) else n
            over = n - self.capacity
            if over > count:
                self.stats.overflow_samples += over - count
                count = over
        return self._take(count)

    def _take(self, count: int) -> AssembledSamples:
        out = AssembledSamples(self._stamps[:count], self._acc[:count], self._gyr[:count])
        have = self._have[:count]
        complete = have.all(axis=1)
        self.stats.complete_samples += int(complete.sum())
        self.stats.incomplete_samples += int((~complete).sum())
        self.stats.missing_messages += int((~have).sum())
        if count:
            self._last_out = int(self._stamps[count - 1])
        self._stamps, self._acc, self._gyr = self._stamps[count:], self._acc[count:], self._gyr[count:]
        self._have, self._first = self._have[count:], self._first[count:]
        return out


@dataclass
class InputCounts:
    """Raw messages seen and rejected, by kind (the assembler adds duplicate/backwards/late)."""

    messages: int = 0
    undecodable: int = 0
    wrong_frame_id: int = 0
    non_finite: int = 0


class RawIntake:
    """The live nodes' input: batches of raw ``sensor_msgs/Imu`` payloads decoded column-wise
    (:func:`~imu_array_ros.io.messages.decode_raw_imu`), undecodable ones, a wrong ``frame_id``
    (``frame_prefix + name`` expected) and non-finite values counted and dropped, the rest grouped
    by stamp in a :class:`SampleAssembler`.  Used by the fusion (``LiveFusion``) and the
    calibration node's window (``SampleWindow``).

    ``own_stamps=True``: IMUs that stamp their own messages; the messages are paired onto the
    stamps of IMU ``reference`` (an index) by a
    :class:`~imu_array_ros.io.live_pairing.PairingAssembler` instead, whose ``pop`` hands out
    ``own_stamps`` too (same interface otherwise)."""

    def __init__(self, names, frame_prefix: str = "", sync_timeout_s: float = 0.05, capacity: int = 4096, *,
                 own_stamps: bool = False, reference: int = 0) -> None:
        self.frame_ids = [frame_prefix + n for n in names]
        timeout_ns = int(round(sync_timeout_s * 1e9))
        if own_stamps:
            from imu_array_ros.io.live_pairing import PairingAssembler

            self.assembler = PairingAssembler(len(self.frame_ids), timeout_ns=timeout_ns, reference=reference,
                                              capacity=capacity)
        else:
            self.assembler = SampleAssembler(len(self.frame_ids), timeout_ns=timeout_ns, capacity=capacity)
        self.counts = InputCounts()

    def add(self, payloads, imu_index, now_ns: int) -> None:
        """Decode, check and buffer payloads; ``imu_index[i]`` is the IMU whose topic payload i came on."""
        if not len(payloads):
            return
        idx = np.asarray(imu_index, dtype=np.int64)
        batch = decode_raw_imu(payloads, idx, self.frame_ids)
        c = self.counts
        c.messages += len(payloads)
        c.undecodable += int((~batch.decodable).sum())
        c.wrong_frame_id += int((batch.decodable & ~batch.frame_ok).sum())
        c.non_finite += int((batch.decodable & batch.frame_ok & ~batch.finite).sum())
        use = batch.usable
        self.assembler.add(idx[use], batch.stamps[use], batch.accel[use], batch.gyro[use], now_ns)
