"""Pairing per-IMU message streams that carry their own stamps onto one grid of array samples.

IMUs with their own drivers stamp their messages with their own clocks: slightly
different rates (a few hundred ppm), constant offsets of a few ms, jitter.  Their
messages are paired onto one **grid** of array samples, by default the
reference IMU's stamps (the description's first IMU unless named):

* **grid**: the reference's stamps; where it dropped messages (two stamps more
  than 1.5 of its median period P apart) the gap is cut into
  ``floor(gap / P + 1/2)`` equal steps, and where other IMUs deliver before its
  first or after its last stamp the grid is extended at P.  A filled or extended grid
  sample that no message pairs with is left out, so every grid sample has data
  and the grid has no gaps where any IMU delivers.
* **pairing**: every message goes to the grid sample nearest to its (optionally
  clock-corrected) time, if one lies within ``tolerance`` (default 1/2) of its
  IMU's period (:func:`median_period`: the median of its first 64 stamp
  differences); a grid sample several messages of one IMU go to keeps the
  nearest (ties: the earlier message), the others are **unused**.  A grid sample
  no message of an IMU pairs with is **missing** for that IMU: NaN readings, and
  its own stamp set to the grid stamp (a stamp delay of 0; ``ImuSamples.present``
  tells missing slots apart).  Ties between two grid samples go to the earlier.
* **clock correction** (:class:`StampClocks`, relative to the grid's clock):
  ``corrected = own + offset + skew 1e-6 (own - t0)``, the ``stamp_clock`` term's
  convention; a caller that has estimated the clocks re-pairs with
  :func:`pair_again`.  ``own_stamps`` always holds the uncorrected stamps.

Bad input raises :class:`~imu_array_ros.errors.RecordingError`, one line naming
the IMU: a stamp that goes backwards, repeats or jumps by more than
``max_gap_s``; an IMU whose stamps (almost) never come within a few periods of
the reference's (another clock base).  An IMU that stops or starts late is not
an error: its slots are missing and counted (:class:`PairingStats`).

Everything is vectorised over messages (``np.searchsorted``); the loops run over
IMUs.  The live counterpart, pairing as messages arrive:
:class:`~imu_array_ros.io.live_pairing.PairingAssembler`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from imu_array_ros.errors import RecordingError
from imu_array_ros.model.reference import reference_index
from imu_array_ros.model.samples import ImuSamples

__all__ = ["ImuStream", "StampClocks", "PairingStats", "pair_streams", "pair_again", "split_streams",
           "check_stream", "median_period", "grid_points", "assign_slots", "FILL_GAP", "FAR_PERIODS",
           "PERIOD_COUNT"]

#: a gap in the reference's stamps over this many periods is filled
FILL_GAP = 1.5
#: an IMU's period is the median of its first this many stamp differences
PERIOD_COUNT = 64
#: an IMU whose messages (almost) never come within this many periods of the reference's stamps is refused
FAR_PERIODS = 3.0
#: ... "almost never": fewer than this fraction of its messages
FAR_FRACTION = 0.01


@dataclass(frozen=True)
class ImuStream:
    """One IMU's messages in arrival order: stamps (M,) int64 ns (its own clock), accel, gyro (M, 3)."""

    stamps: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray


@dataclass(frozen=True)
class StampClocks:
    """Per-IMU clock corrections relative to the grid's clock (``stamp_clock`` convention).

    offset_s (K,) s and skew_ppm (K,) ppm; ``corrected = own + offset + skew 1e-6 (own - t0_ns)``,
    t0_ns the recording's first grid stamp (what the fusion counts ``stamp_clock`` time from).
    """

    offset_s: np.ndarray
    skew_ppm: np.ndarray
    t0_ns: int

    def corrected(self, k, own: np.ndarray) -> np.ndarray:
        """IMU k's stamps ``own`` (int64 ns) on the grid's clock (int64 ns); k an index, or an index
        array broadcasting with ``own``."""
        own = np.asarray(own, dtype=np.int64)
        off, skew = np.asarray(self.offset_s, dtype=float)[k], np.asarray(self.skew_ppm, dtype=float)[k]
        if not (np.any(off) or np.any(skew)):
            return own
        shift = off * 1e9 + skew * 1e-6 * (own - int(self.t0_ns)).astype(float)
        return own + np.rint(shift).astype(np.int64)


@dataclass
class PairingStats:
    """What the pairing did, per IMU in ``names`` order (arrays (K,))."""

    names: tuple[str, ...]
    reference: str
    grid: int  # grid samples handed out
    grid_filled: int  # of which not at a stamp of the reference (its dropouts filled, the grid extended)
    messages: np.ndarray
    paired: np.ndarray
    unused: np.ndarray  # messages no grid sample took (beyond the tolerance, or a nearer message won)
    missing: np.ndarray  # grid samples without a message of the IMU
    missing_head: np.ndarray  # of which before its first paired message (it started late)
    missing_tail: np.ndarray  # of which after its last paired message (it stopped)
    median_abs_delay_s: np.ndarray  # median |own stamp - grid stamp| over the paired messages (NaN: none)
    period_s: np.ndarray  # median period of each IMU's stamps

    def summary(self) -> str:
        """One line for ``ReadStats.notes`` and logs."""
        text = (f"paired onto the stamps of reference IMU {self.reference!r} ({self.grid} samples, "
                f"{self.grid_filled} filled): {int(self.paired.sum())} of {int(self.messages.sum())} messages "
                f"paired, {int(self.unused.sum())} unused, {int(self.missing.sum())} missing slots")
        if self.missing.any():
            k = int(np.argmax(self.missing))
            text += (f" (most on {self.names[k]!r}: {int(self.missing[k])}, {int(self.missing_head[k])} before it "
                     f"started, {int(self.missing_tail[k])} after it stopped)")
        delay = self.median_abs_delay_s
        if np.isfinite(delay).any():
            k = int(np.nanargmax(delay))
            text += (f"; median |own stamp - grid| {1e3 * float(np.nanmedian(delay)):.3g} ms "
                     f"(largest {self.names[k]!r}: {1e3 * float(delay[k]):.3g} ms)")
        return text


def median_period(stamps: np.ndarray) -> int:
    """An IMU's period, ns: the median of its first ``PERIOD_COUNT`` stamp differences (0 for fewer
    than two stamps).  The first ones only, so that the live pairing, which knows them early, uses
    the same value."""
    stamps = np.asarray(stamps, dtype=np.int64)[:PERIOD_COUNT + 1]
    return int(np.median(np.diff(stamps))) if len(stamps) > 1 else 0


def check_stream(name: str, stamps: np.ndarray, max_gap_ns: int) -> None:
    """RecordingError (one line naming IMU ``name`` and where) if ``stamps`` (arrival order) go
    backwards, repeat, or jump forward by more than ``max_gap_ns``."""
    stamps = np.asarray(stamps, dtype=np.int64)
    if len(stamps) < 2:
        return
    d = np.diff(stamps)
    bad = np.flatnonzero((d <= 0) | (d > max_gap_ns))
    if not len(bad):
        return
    i = int(bad[0])
    at = f"at message {i + 1} of {len(stamps)}, {(stamps[i] - stamps[0]) / 1e9:.3f} s after its first stamp"
    if d[i] == 0:
        what = "repeats a stamp"
    elif d[i] < 0:
        what = f"goes backwards by {-d[i] / 1e9:.6g} s"
    else:
        what = f"jumps by {d[i] / 1e9:.6g} s (more than {max_gap_ns / 1e9:g} s)"
    raise RecordingError(f"IMU {name!r}: its stamp {what} {at}: a clock reset or another clock base")


def grid_points(ref: np.ndarray, period_ns: int, lo: int | None = None, hi: int | None = None,
                max_fill_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The grid from the reference's stamps ``ref`` (sorted): dropouts filled, extended over [lo, hi].

    Returns (grid (G,) int64, from_reference (G,) bool).  A gap of ``gap > FILL_GAP P`` (and not
    over ``max_fill_ns``) is cut into ``m = floor(gap / P + 1/2)`` equal steps: the points
    ``prev + floor(j gap / m)``, ``0 < j < m`` (the period's estimate only decides m); the grid is
    extended at P backwards while ``lo`` lies more than P/2 before its first point, forwards
    likewise for ``hi``.
    """
    ref = np.asarray(ref, dtype=np.int64)
    p = int(period_ns)
    if p <= 0 or not len(ref):
        return ref, np.ones(len(ref), dtype=bool)
    d = np.diff(ref)
    gap = (d > FILL_GAP * p) & (True if max_fill_ns is None else d <= max_fill_ns)
    m = np.where(gap, np.floor(d / p + 0.5).astype(np.int64), 1)
    counts = m - 1
    total = int(counts.sum())
    head = tail = 0
    if lo is not None and lo < ref[0] - p / 2:
        head = int(np.ceil((ref[0] - p / 2 - lo) / p))
    if hi is not None and hi > ref[-1] + p / 2:
        tail = int(np.ceil((hi - ref[-1] - p / 2) / p))
    if not (total or head or tail):
        return ref, np.ones(len(ref), dtype=bool)
    starts = np.cumsum(counts) - counts
    j = np.arange(total) - np.repeat(starts, counts) + 1
    gap, parts = np.repeat(d, counts), np.repeat(m, counts)
    fill = np.repeat(ref[:-1], counts) + (gap // parts) * j + ((gap % parts) * j) // parts  # floor(gap j / m)
    before = ref[0] - p * np.arange(head, 0, -1, dtype=np.int64)
    after = ref[-1] + p * np.arange(1, tail + 1, dtype=np.int64)
    grid = np.concatenate([before, ref, fill, after])
    from_ref = np.concatenate([np.zeros(head, bool), np.ones(len(ref), bool), np.zeros(total + tail, bool)])
    order = np.argsort(grid, kind="stable")
    return grid[order], from_ref[order]


def assign_slots(grid: np.ndarray, t: np.ndarray, tol_ns, group: np.ndarray | None = None) -> np.ndarray:
    """(M,) int64: the grid sample each message (times ``t``) pairs with, -1 for unused.

    Nearest grid sample (ties: the earlier) within ``tol_ns`` (scalar or (M,)); a grid sample
    claimed by several messages of one ``group`` (IMU; (M,) int, None: one) keeps the nearest
    (ties: the earlier message in the order given).
    """
    grid = np.asarray(grid, dtype=np.int64)
    t = np.asarray(t, dtype=np.int64)
    m, n = len(t), len(grid)
    if not m or not n:
        return np.full(m, -1, dtype=np.int64)
    j = np.searchsorted(grid, t, side="left")
    lo, hi = np.clip(j - 1, 0, n - 1), np.clip(j, 0, n - 1)
    d_lo, d_hi = np.abs(t - grid[lo]), np.abs(grid[hi] - t)
    slot = np.where(d_hi < d_lo, hi, lo)
    dist = np.minimum(d_lo, d_hi)
    slot = np.where(dist <= tol_ns, slot, -1)
    cand = np.flatnonzero(slot >= 0)
    if len(cand) > 1:
        key = slot[cand] if group is None else np.asarray(group, dtype=np.int64)[cand] * n + slot[cand]
        order = np.lexsort((cand, dist[cand], key))
        s = key[order]
        loser = np.concatenate([[False], s[1:] == s[:-1]])
        slot[cand[order[loser]]] = -1
    return slot


def _far_check(name: str, ref_name: str, t: np.ndarray, ref: np.ndarray, period: float) -> None:
    near = np.zeros(len(t), dtype=bool)
    j = np.clip(np.searchsorted(ref, t), 1, len(ref) - 1) if len(ref) > 1 else np.zeros(len(t), np.int64)
    for side in (j - 1, j):
        near |= np.abs(t - ref[side]) <= FAR_PERIODS * period
    if near.mean() < FAR_FRACTION:
        raise RecordingError(
            f"IMU {name!r}: its stamps ({t[0] / 1e9:.3f} s to {t[-1] / 1e9:.3f} s) do not come within "
            f"{FAR_PERIODS:g} periods of the reference IMU {ref_name!r}'s ({ref[0] / 1e9:.3f} s to "
            f"{ref[-1] / 1e9:.3f} s) for {100 * near.mean():.2g}% of its messages: too far apart to pair "
            "(another clock base? give its clock offset, or name another reference)")


def pair_streams(streams: Sequence[ImuStream], names: Sequence[str], *, reference: str | int | None = None,
                 grid: np.ndarray | None = None, clocks: StampClocks | None = None,
                 periods_ns: Sequence[int] | None = None, tolerance: float = 0.5,
                 max_gap_s: float = 1.0, unused_rows: bool = False) -> tuple[ImuSamples, PairingStats]:
    """Pair per-IMU streams (own stamps, arrival order) onto a grid (see module docstring).

    streams : K :class:`ImuStream` (any objects with ``stamps``, ``accel``, ``gyro``), ``names`` order.
    reference : the IMU whose stamps make the grid (name or index; None: the first).
    grid : (G,) int64 sorted, instead of the reference's stamps (kept whole: no fill, extension or
        removal).  clocks : corrections applied before pairing.  periods_ns : each IMU's period
        (default :func:`median_period`; an IMU with fewer than two messages takes the reference's,
        or the grid's).  tolerance : fraction of the period within which a message pairs.
    max_gap_s : a larger jump of an IMU's stamps is an error.
    unused_rows : also every unused message, as a row of its own (stamp: its corrected stamp, the
        other IMUs missing) sorted in: every message of the streams, for a replay (not for fusion).

    Returns (ImuSamples(stamps=grid, accel, gyro, names, own_stamps), PairingStats).
    """
    names = tuple(names)
    k_count = len(names)
    if len(streams) != k_count:
        raise ValueError(f"{len(streams)} streams for {k_count} IMU names")
    ref_k = reference_index(names, reference)
    own = [np.asarray(s.stamps, dtype=np.int64).reshape(-1) for s in streams]
    max_gap_ns = int(round(max_gap_s * 1e9))
    for name, st in zip(names, own):
        check_stream(name, st, max_gap_ns)
    times = [own[k] if clocks is None else clocks.corrected(k, own[k]) for k in range(k_count)]
    period = np.array([median_period(st) for st in own] if periods_ns is None else periods_ns, dtype=float)
    if grid is None:
        ref = times[ref_k]
        if len(ref) < 2:
            raise RecordingError(f"reference IMU {names[ref_k]!r} has {len(ref)} message(s): too few to make the "
                                 "grid of array samples (name another reference)")
        period = np.where(period > 0, period, period[ref_k])
        others = [t for k, t in enumerate(times) if k != ref_k and len(t)]
        for k, t in enumerate(times):
            if k != ref_k and len(t):
                _far_check(names[k], names[ref_k], t, ref, period[k])
        lo = min(int(t[0]) for t in others) if others else None
        hi = max(int(t[-1]) for t in others) if others else None
        grid, from_ref = grid_points(ref, int(period[ref_k]), lo, hi)
    else:
        grid = np.asarray(grid, dtype=np.int64).reshape(-1)
        if len(grid) > 1 and (np.diff(grid) <= 0).any():
            raise ValueError("grid stamps must be strictly increasing")
        from_ref = np.ones(len(grid), dtype=bool)
        step = median_period(grid)
        period = np.where(period > 0, period, step)
    slots = [assign_slots(grid, times[k], tolerance * period[k]) for k in range(k_count)]
    keep = from_ref.copy()
    for s in slots:
        keep[s[s >= 0]] = True
    if not keep.all():  # filled / extended grid samples that nothing pairs with
        new_index = np.cumsum(keep) - 1
        grid = grid[keep]
        slots = [np.where(s >= 0, new_index[np.maximum(s, 0)], -1) for s in slots]
    n = len(grid)
    accel = np.full((n, k_count, 3), np.nan)
    gyro = np.full((n, k_count, 3), np.nan)
    own_stamps = np.repeat(grid[:, None], k_count, axis=1)
    stats = PairingStats(names, names[ref_k], n, int(n - from_ref[keep].sum()),
                         *(np.zeros(k_count, dtype=np.int64) for _ in range(6)),
                         np.full(k_count, np.nan), period * 1e-9)
    for k, (s, stream) in enumerate(zip(slots, streams)):
        used = np.flatnonzero(s >= 0)
        rows = s[used]
        accel[rows, k] = np.asarray(stream.accel, dtype=float).reshape(-1, 3)[used]
        gyro[rows, k] = np.asarray(stream.gyro, dtype=float).reshape(-1, 3)[used]
        own_stamps[rows, k] = own[k][used]
        stats.messages[k], stats.paired[k] = len(s), len(used)
        stats.unused[k] = len(s) - len(used)
        stats.missing[k] = n - len(used)
        if len(used):
            stats.missing_head[k], stats.missing_tail[k] = rows[0], n - 1 - rows[-1]
            stats.median_abs_delay_s[k] = float(np.median(np.abs(own[k][used] - grid[rows]))) * 1e-9
        else:
            stats.missing_head[k] = n
    samples = ImuSamples(grid, accel, gyro, names, own_stamps)
    if unused_rows and stats.unused.any():
        samples = _with_unused(samples, streams, slots, times)
    return samples, stats


def _with_unused(samples: ImuSamples, streams, slots, times) -> ImuSamples:
    """``samples`` and a row for every unused message (see :func:`pair_streams`), in stamp order."""
    k_count = len(samples.names)
    left = [np.flatnonzero(s < 0) for s in slots]
    m = sum(len(i) for i in left)
    which = np.concatenate([np.full(len(i), k) for k, i in enumerate(left)])
    at = np.concatenate([times[k][i] for k, i in enumerate(left)])
    own = np.concatenate([np.asarray(streams[k].stamps, dtype=np.int64)[i] for k, i in enumerate(left)])
    rows = np.arange(m)
    accel, gyro = np.full((m, k_count, 3), np.nan), np.full((m, k_count, 3), np.nan)
    for field, out in (("accel", accel), ("gyro", gyro)):
        out[rows, which] = np.concatenate([np.asarray(getattr(streams[k], field), float).reshape(-1, 3)[i]
                                           for k, i in enumerate(left)])
    own_stamps = np.repeat(at[:, None], k_count, axis=1)
    own_stamps[rows, which] = own
    stamps = np.concatenate([samples.stamps, at])
    order = np.argsort(stamps, kind="stable")
    return ImuSamples(stamps[order], np.concatenate([samples.accel, accel])[order],
                      np.concatenate([samples.gyro, gyro])[order], samples.names,
                      np.concatenate([samples.own_stamps, own_stamps])[order])


def split_streams(samples: ImuSamples) -> list[ImuStream]:
    """The per-IMU streams of ``samples``: each IMU's present messages with their own stamps
    (``samples.stamps`` without own stamps).  The inverse of :func:`pair_streams`."""
    present = samples.present
    out = []
    for k in range(len(samples.names)):
        rows = np.flatnonzero(present[:, k])
        st = samples.stamps[rows] if samples.own_stamps is None else samples.own_stamps[rows, k]
        out.append(ImuStream(st, samples.accel[rows, k], samples.gyro[rows, k]))
    return out


def pair_again(samples: ImuSamples, clocks: StampClocks, *, tolerance: float = 0.5,
               max_gap_s: float = 1.0) -> tuple[ImuSamples, PairingStats]:
    """Re-pair ``samples`` (with own stamps) with estimated clocks, on the same grid (the fused
    output keeps its stamps).  Each IMU's period is the median of its own stamps' differences."""
    return pair_streams(split_streams(samples), samples.names, grid=samples.stamps, clocks=clocks,
                        tolerance=tolerance, max_gap_s=max_gap_s)
