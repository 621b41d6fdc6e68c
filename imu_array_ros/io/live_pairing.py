"""Live pairing of IMUs that stamp their own messages: the streaming form of :mod:`.pairing`.

:class:`PairingAssembler` has the interface of
:class:`~imu_array_ros.io.sync.SampleAssembler` (``add`` batches of decoded
messages, ``pop`` the ready array samples, ``stats``, ``pending``), but its IMUs
need not share stamps: their messages are paired onto the reference IMU's stamps
by the rules of :func:`~imu_array_ros.io.pairing.pair_streams` (the grid, its
filled dropouts and extension, nearest grid sample within ``tolerance`` of a
period, the nearest message wins), and every sample handed out carries
``own_stamps`` (P, K), each message's own stamp (the grid stamp where missing).

To use it in a node::

    asm = PairingAssembler(len(names), timeout_ns=50_000_000, reference=0)
    asm.add(imu_index, stamps, accel, gyro, now_ns)     # per batch of messages, arrival order
    ready = asm.pop(now_ns)                             # AssembledSamples with own_stamps
    samples = ImuSamples(ready.stamps, ready.accel, ready.gyro, names, ready.own_stamps)
    asm.set_clocks(StampClocks(offset_s, skew_ppm, t0_ns))   # when the clocks are estimated

or ``RawIntake(names, own_stamps=True)`` (:mod:`.sync`).

When a grid sample is handed out:

* its pairing is final: the grid sample after it is known and every IMU has
  delivered a message past the latest time that could still pair with it
  (``min(g + tolerance P_k, midpoint to the next grid sample)``), or has been
  silent for ``timeout_ns``.  The output lags the newest message by about a
  period of the slowest IMU (plus its offset);
* the reference silent for ``timeout_ns``: the grid is extended at its period
  over the messages of the others, so the output goes on without it; when it
  comes back its stamps continue the grid;
* more than ``capacity`` grid samples pending, or messages of one IMU buffered:
  the oldest go as they are (``overflow_samples``, ``overflow_messages``).

Rejected messages, counted and never used: ``duplicate`` / ``backwards`` (an IMU's
stamp equal to / below its previous one), ``late`` (the grid samples it could pair
with are handed out already).  Jumps of more than ``max_gap_s`` are counted
(``jumps``) and not filled.

Each IMU's period is, as offline, the median of its first ``PERIOD_COUNT`` (64)
stamp differences; nothing is handed out before the reference and every IMU that
is not silent have theirs (~0.3 s at 200 Hz).  It then pairs exactly as
:func:`~imu_array_ros.io.pairing.pair_streams` does offline (tested), except for
messages rejected above or dropped by ``capacity``, an IMU silent for
``timeout_ns`` that comes back before it had 64 differences (a provisional
period), and the reference coming back after a silence (the grid was extended
at its period where offline the gap is filled in equal steps).  ``arrival_ns``
and ``now_ns`` are the node's clock, stamps the IMUs' own.  Memory is bounded
(``capacity``); every call is vectorised over messages, IMUs and grid samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.io.pairing import PERIOD_COUNT, StampClocks, assign_slots, grid_points
from imu_array_ros.io.sync import AssembledSamples

__all__ = ["PairingAssembler", "PairingAssemblerStats"]

INT_MIN = int(np.iinfo(np.int64).min)


@dataclass
class PairingAssemblerStats:
    """Running counts (messages unless said otherwise)."""

    accepted: int = 0
    duplicate: int = 0
    backwards: int = 0
    late: int = 0
    jumps: int = 0  # stamp steps over max_gap_s (any IMU)
    paired: int = 0
    unused: int = 0  # accepted, but no grid sample took them
    overflow_messages: int = 0
    overflow_samples: int = 0
    grid_filled: int = 0  # samples handed out that are not at a stamp of the reference
    complete_samples: int = 0
    incomplete_samples: int = 0
    missing_messages: int = 0  # IMU slots empty in the samples handed out

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class PairingAssembler:
    """Pairs the messages of ``n_imus`` IMUs with own stamps onto the reference's (module docstring).

    Parameters
    ----------
    n_imus : int
    timeout_ns : int
        How long an IMU may be silent before the samples it may still pair with go without it.
    reference : int
        Index of the IMU whose stamps make the grid.
    capacity : int
        Most grid samples pending, and most messages buffered per IMU (at least ``2 PERIOD_COUNT``).
    tolerance : float
        Fraction of an IMU's period within which a message pairs with a grid sample.
    periods_ns : (K,) int, optional
        Each IMU's period; default, as offline, the median of its first ``PERIOD_COUNT`` stamp
        differences (until every IMU has them or is silent, nothing is handed out: ~0.3 s at 200 Hz).
    max_gap_s : float
        Stamp steps over this are counted as jumps and not filled.
    clocks : StampClocks, optional
        Clock corrections (``set_clocks`` changes them).
    """

    def __init__(self, n_imus: int, *, timeout_ns: int, reference: int = 0, capacity: int = 4096,
                 tolerance: float = 0.5, periods_ns=None, max_gap_s: float = 1.0,
                 clocks: StampClocks | None = None) -> None:
        if n_imus < 1 or timeout_ns < 0 or capacity < 2 * PERIOD_COUNT or not 0 <= reference < n_imus or tolerance <= 0:
            raise ValueError(f"n_imus >= 1, 0 <= reference < n_imus, timeout_ns >= 0, capacity >= {2 * PERIOD_COUNT} "
                             "and tolerance > 0 are required")
        k = self.n_imus = int(n_imus)
        self.timeout_ns, self.reference, self.capacity = int(timeout_ns), int(reference), int(capacity)
        self.tolerance, self.max_gap_ns = float(tolerance), int(round(max_gap_s * 1e9))
        self.clocks = clocks
        self.stats = PairingAssemblerStats()
        self._fixed = None if periods_ns is None else np.asarray(periods_ns, dtype=np.int64).reshape(k)
        self._diffs = np.zeros((k, PERIOD_COUNT), dtype=np.int64)  # each IMU's first stamp differences
        self._n_diffs = np.zeros(k, dtype=np.int64)
        self._period = np.zeros(k, dtype=np.int64)  # the estimates, made from _period_at differences
        self._period_at = np.zeros(k, dtype=np.int64)
        # the buffered messages of every IMU, arrival order (so each IMU's in stamp order)
        self._k = np.zeros(0, np.int64)
        self._own = np.zeros(0, np.int64)
        self._acc = np.zeros((0, 3))
        self._gyr = np.zeros((0, 3))
        self._latest = np.full(k, INT_MIN)  # last accepted own stamp per IMU
        self._heard: np.ndarray | None = None  # arrival time of each IMU's last message
        self._grid = np.zeros(0, np.int64)  # pending grid samples
        self._from_ref = np.zeros(0, bool)
        self._grid_end: int | None = None  # last grid sample made
        self._decided: tuple[int, int] | None = None  # (a, b): messages with 2t <= a + b are decided

    # ------------------------------------------------------------------ state

    @property
    def pending(self) -> int:
        """Grid samples waiting."""
        return len(self._grid)

    @property
    def periods_ns(self) -> np.ndarray:
        """(K,) each IMU's period (0: not known yet): the median of its first ``PERIOD_COUNT`` stamp
        differences (:func:`~imu_array_ros.io.pairing.median_period`), provisional before it has them."""
        if self._fixed is not None:
            return self._fixed.copy()
        stale = np.flatnonzero((self._n_diffs > 0) & (self._period_at != self._n_diffs))
        for k in stale:  # an IMU's estimate changes only while it has fewer than PERIOD_COUNT differences
            self._period[k] = int(np.median(self._diffs[k, :self._n_diffs[k]]))
            self._period_at[k] = self._n_diffs[k]
        return self._period.copy()

    @property
    def _period_final(self) -> np.ndarray:
        return np.ones(self.n_imus, bool) if self._fixed is not None else self._n_diffs >= PERIOD_COUNT

    def set_clocks(self, clocks: StampClocks | None) -> None:
        """Pair from now on with these clock corrections (relative to the reference's clock)."""
        self.clocks = clocks

    def _times(self, k, own: np.ndarray) -> np.ndarray:
        return own if self.clocks is None else self.clocks.corrected(k, own)

    # ------------------------------------------------------------------ input

    def add(self, imu_index, stamps, accel, gyro, arrival_ns: int) -> np.ndarray:
        """Add M messages (arrival order); returns (M,) bool: accepted.

        imu_index (M,) int in [0, n_imus); stamps (M,) int64 ns, each IMU's own; accel, gyro (M, 3).
        """
        idx = np.asarray(imu_index, dtype=np.int64).reshape(-1)
        st = np.asarray(stamps, dtype=np.int64).reshape(-1)
        m = len(idx)
        if not m:
            return np.ones(0, dtype=bool)
        if idx.min() < 0 or idx.max() >= self.n_imus:
            raise ValueError(f"imu_index outside [0, {self.n_imus})")
        if self._heard is None:  # an IMU that never speaks is silent from the first message on
            self._heard = np.full(self.n_imus, int(arrival_ns), dtype=np.int64)
        # the previous stamp of each message's IMU: the stored latest or the batch's running max, by
        # ranks (no int64 overflow): a running max over group * m + rank runs within each group
        order = np.argsort(idx, kind="stable")
        i_sorted, s_sorted = idx[order], st[order]
        first = np.concatenate([[True], i_sorted[1:] != i_sorted[:-1]])
        group = np.cumsum(first) - 1
        by_stamp = np.argsort(s_sorted, kind="stable")
        rank = np.empty(m, dtype=np.int64)
        rank[by_stamp] = np.arange(m)
        run = np.maximum.accumulate(group * m + rank) - group * m
        prev = self._latest[i_sorted].copy()
        prev[1:] = np.where(first[1:], prev[1:], np.maximum(prev[1:], s_sorted[by_stamp[run[:-1]]]))
        good = s_sorted > prev
        st_ = self.stats
        st_.duplicate += int((s_sorted == prev).sum())
        st_.backwards += int((s_sorted < prev).sum())
        if self._decided is not None:
            a, b = self._decided
            late = good & (2 * (self._times(i_sorted, s_sorted) - a) <= b - a)
            good &= ~late
            st_.late += int(late.sum())
        ok = np.empty(m, dtype=bool)
        ok[order] = good
        st_.accepted += int(good.sum())
        self._heard[idx] = int(arrival_ns)  # rejected or not, the IMU is alive
        if not good.any():
            return ok
        # stamp differences of the accepted messages (after the IMU's previous accepted one)
        ks, ss = i_sorted[good], s_sorted[good]
        first = np.concatenate([[True], ks[1:] != ks[:-1]])
        before = np.where(first, self._latest[ks], np.concatenate([[0], ss[:-1]]))
        d = ss - before
        jump = d > self.max_gap_ns
        st_.jumps += int((jump & (before != INT_MIN)).sum())
        use = ~jump & (before != INT_MIN)
        if use.any():
            ku = ks[use]
            pos = self._n_diffs[ku] + np.arange(len(ku)) - np.searchsorted(ku, ku)  # the IMU's difference number
            first_ones = pos < PERIOD_COUNT
            self._diffs[ku[first_ones], pos[first_ones]] = d[use][first_ones]
            self._n_diffs = np.minimum(self._n_diffs + np.bincount(ku, minlength=self.n_imus), PERIOD_COUNT)
        np.maximum.at(self._latest, ks, ss)
        self._k = np.concatenate([self._k, idx[ok]])
        self._own = np.concatenate([self._own, st[ok]])
        self._acc = np.concatenate([self._acc, np.asarray(accel, dtype=float).reshape(-1, 3)[ok]])
        self._gyr = np.concatenate([self._gyr, np.asarray(gyro, dtype=float).reshape(-1, 3)[ok]])
        counts = np.bincount(self._k, minlength=self.n_imus)
        if counts.max() > self.capacity:  # the oldest messages of an IMU over capacity go
            excess = np.maximum(counts - self.capacity, 0)
            by_imu = np.argsort(self._k, kind="stable")
            pos = np.arange(len(by_imu)) - np.searchsorted(self._k[by_imu], self._k[by_imu])
            drop = np.zeros(len(self._k), dtype=bool)
            drop[by_imu] = pos < excess[self._k[by_imu]]
            st_.overflow_messages += int(drop.sum())
            self._keep(~drop)
        return ok

    def _keep(self, mask: np.ndarray) -> None:
        self._k, self._own, self._acc, self._gyr = self._k[mask], self._own[mask], self._acc[mask], self._gyr[mask]

    # ------------------------------------------------------------------ the grid

    def _append_grid(self, pts: np.ndarray, from_ref: np.ndarray) -> None:
        if len(pts):
            self._grid = np.concatenate([self._grid, pts]).astype(np.int64)
            self._from_ref = np.concatenate([self._from_ref, from_ref])
            self._grid_end = int(pts[-1])

    def _extend_grid(self, p_ref: int, silent: np.ndarray) -> None:
        """New grid samples: the reference's new stamps (dropouts filled), and the extension over the
        other IMUs' messages before its first stamp (once every IMU has spoken or is silent) or, when
        the reference is silent, after its last."""
        r = self.reference
        is_ref = self._k == r
        spoke = self._latest != INT_MIN
        if self._grid_end is None:  # wait for the reference's period (the extension's step) and every IMU
            if not is_ref.any() or not (spoke | silent).all() or not (self._period_final[r] or silent[r]):
                return
            others = ~is_ref
            lo = int(self._times(self._k[others], self._own[others]).min()) if others.any() else None
            self._append_grid(*grid_points(self._times(r, self._own[is_ref]), p_ref, lo=lo,
                                           max_fill_ns=self.max_gap_ns))
        elif spoke[r] and self._times(r, self._latest[r:r + 1])[0] > self._grid_end:
            t_ref = self._times(r, self._own[is_ref])
            new = t_ref[t_ref > self._grid_end]
            pts, from_ref = grid_points(np.concatenate([[self._grid_end], new]), p_ref, max_fill_ns=self.max_gap_ns)
            self._append_grid(pts[1:], from_ref[1:])
        if silent[r] and self._grid_end is not None:
            ks = np.flatnonzero(spoke & (np.arange(self.n_imus) != r))
            hi = int(self._times(ks, self._latest[ks]).max()) if len(ks) else None
            if hi is not None and hi > self._grid_end + p_ref / 2:
                pts, from_ref = grid_points(np.array([self._grid_end]), p_ref, hi=hi)
                self._append_grid(pts[1:], from_ref[1:])

    # ------------------------------------------------------------------ output

    def pop(self, now_ns: int, *, flush: bool = False) -> AssembledSamples:
        """Hand out the grid samples whose pairing is final (all pending ones with ``flush``), oldest first."""
        r = self.reference
        periods = self.periods_ns
        p_ref = int(periods[r])
        if self._heard is None or p_ref <= 0:
            return self._empty()
        silent = (int(now_ns) - self._heard >= self.timeout_ns) | flush
        periods = np.where(periods > 0, periods, p_ref)  # an IMU with no period yet pairs within the reference's
        self._extend_grid(p_ref, silent)
        g = self._grid
        n = len(g)
        if not n:
            return self._empty()
        if flush:
            count = n
        else:
            gb = g - g[0]
            heard = self._latest != INT_MIN
            latest = np.where(heard, self._times(np.arange(self.n_imus), np.where(heard, self._latest, g[0])) - g[0],
                              -(1 << 62))
            tol = self.tolerance * periods
            # every message that could pair with grid sample n has arrived: past n + tol, or past the midpoint to n+1
            passed = latest[None, :] >= gb[:, None] + tol[None, :]
            passed[:-1] |= 2 * latest[None, :] >= (gb[:-1] + gb[1:])[:, None]
            final = (silent[None, :] | passed).all(axis=1) & bool((silent | self._period_final).all())
            final[-1] &= bool(silent[r])  # the last one waits for the next grid sample
            blocked = np.flatnonzero(~final)
            count = int(blocked[0]) if len(blocked) else n
            over = n - self.capacity
            if over > count:
                self.stats.overflow_samples += over - count
                count = over
        if count == 0:
            return self._empty()
        return self._take(count, periods)

    def _empty(self) -> AssembledSamples:
        k = self.n_imus
        return AssembledSamples(np.zeros(0, np.int64), np.zeros((0, k, 3)), np.zeros((0, k, 3)),
                                np.zeros((0, k), np.int64))

    def _take(self, count: int, periods: np.ndarray) -> AssembledSamples:
        """Pair the first ``count`` pending grid samples, consume the messages decided, hand them out."""
        k_count = self.n_imus
        g = self._grid
        # messages with 2t <= a + b are decided now (paired or unused); the next grid sample (if any)
        # takes part in the pairing: it decides which messages are nearer to it
        if count < len(g):
            a, b = int(g[count - 1]), int(g[count])
        else:
            a, b = int(g[-1]), int(g[-1]) + int(periods[self.reference])
        t = self._times(self._k, self._own)
        done = 2 * (t - a) <= b - a
        kd = self._k[done]
        slot = assign_slots(g[:count + 1], t[done], self.tolerance * periods[kd], kd)
        used = (slot >= 0) & (slot < count)
        rows, ku = slot[used], kd[used]
        accel = np.full((count, k_count, 3), np.nan)
        gyro = np.full((count, k_count, 3), np.nan)
        own_out = np.repeat(g[:count, None], k_count, axis=1)
        have = np.zeros((count, k_count), dtype=bool)
        accel[rows, ku], gyro[rows, ku] = self._acc[done][used], self._gyr[done][used]
        own_out[rows, ku] = self._own[done][used]
        have[rows, ku] = True
        st = self.stats
        st.paired += int(used.sum())
        st.unused += int((~used).sum())
        self._keep(~done)
        from_ref = self._from_ref[:count]
        keep = from_ref | have.any(axis=1)  # filled / extended samples nothing paired with: left out
        self._decided = (a, b)
        self._grid, self._from_ref = g[count:], self._from_ref[count:]
        have = have[keep]
        complete = have.all(axis=1)
        st.grid_filled += int((~from_ref[keep]).sum())
        st.complete_samples += int(complete.sum())
        st.incomplete_samples += int((~complete).sum())
        st.missing_messages += int((~have).sum())
        return AssembledSamples(g[:count][keep], accel[keep], gyro[keep], own_out[keep])
