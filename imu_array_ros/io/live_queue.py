"""The live nodes' intake of raw messages, before any decoding.

:class:`CompletionQueue`: the serialized payloads the raw subscription callbacks queue (drained in one batch)
and, for the fusion node, which message completed an array sample -- by its stamp's bytes, no decoding; with
own stamps, every message of the reference IMU.  Without ``on_complete`` it is a plain queue (the
calibration node's window).  :class:`BacklogGate`: fuse a completed sample at once, or batch it when messages
back up.  Plain Python on purpose: one dict look-up per message is all a callback does.
"""

from __future__ import annotations

from typing import Callable

__all__ = ["CompletionQueue", "BacklogGate", "stamp_ns"]


def stamp_ns(key: bytes) -> int:
    """The ``header.stamp`` (ns) of a stamp key of :class:`CompletionQueue` (CDR bytes 4-12)."""
    return int.from_bytes(key[:4], "little", signed=True) * 1_000_000_000 + int.from_bytes(key[4:8], "little")


class BacklogGate:
    """Fuse a completed sample now, or with the next ones when they are already queued behind it.

    The lag of a sample (``now - stamp`` on any steady clock; only its changes matter, so recorded
    stamps and clock offsets cancel) above its baseline (the least lag seen, rising by ``rise`` s per s
    to follow a slow change of the stamps' clock), divided by the stamp spacing (a running mean), is
    how many later samples were stamped before this one completed: when messages back up, they are
    waiting in the executor, and the sample waits for them (up to ``max_wait`` in all) to be fused in
    one call -- the per-call cost is mostly fixed, so this is how a backlog is caught up.  A sample on
    time (less than one spacing above the baseline) is fused at once -- if a fusion call takes less than
    ``headroom`` of the stamp spacing (``cost_ns``, the caller's running measure): a node whose calls take
    most of a spacing cannot keep up one sample per call, and its samples are all left to the timer's
    batches.  Samples waiting are fused by the node's next timer sweep."""

    def __init__(self, max_wait: int = 8, rise: float = 1e-3, headroom: float = 0.5) -> None:
        self.max_wait, self.rise, self.headroom = int(max_wait), float(rise), float(headroom)
        self._base: int | None = None
        self._last = 0
        self._stamp: int | None = None
        self.spacing = 0.0  # running mean of the completed samples' stamp spacing (ns)
        self.waiting = 0  # completed samples not yet fused
        self.batched = 0  # samples that waited for a batch so far

    def complete(self, now_ns: int, stamp: int, cost_ns: float = 0.0) -> bool:
        """A sample completed at ``now_ns``; ``cost_ns``: what a fusion call takes now.  True to fuse now
        (it and those waiting)."""
        lag = now_ns - stamp
        base = lag if self._base is None else min(self._base + int(self.rise * (now_ns - self._last)), lag)
        self._base, self._last = base, now_ns
        if self._stamp is not None and stamp > self._stamp:
            step = stamp - self._stamp
            self.spacing = step if self.spacing <= 0 else 0.95 * self.spacing + 0.05 * min(step, 4 * self.spacing)
        self._stamp = stamp
        queued = int((lag - base) // self.spacing) if self.spacing > 0 else 0
        if cost_ns > self.headroom * self.spacing > 0:
            queued = self.max_wait  # too slow for one call per sample: the timer batches
        if self.waiting < min(queued, self.max_wait - 1):
            self.waiting += 1
            self.batched += 1
            return False
        self.waiting = 0
        return True

    def fused(self) -> None:
        """The waiting samples were fused (by a sweep)."""
        self.waiting = 0


class CompletionQueue:
    """Serialized raw messages queued by the subscription callbacks (``receiver(k)`` is IMU k's callback),
    drained in one batch by :meth:`drain`; ``on_complete(stamp)`` is called from the callback of the message that
    completed an array sample: every IMU has a message of its stamp (``header.stamp``: bytes 4-12 of the
    CDR payload, taken as they are, no decoding).  A duplicate message sets its IMU's bit again and completes
    nothing (completed stamps are remembered too).  ``own_stamps``: the IMUs stamp their own messages, no stamp is shared; every message of the
    ``reference`` IMU calls ``on_complete`` instead (a new grid point).  Stamps that never complete (a lost
    message) are forgotten oldest first, keeping the newest ``keep`` stamps.  Without ``on_complete``: a plain
    queue, nothing tracked."""

    def __init__(self, n_imus: int, on_complete: Callable[[bytes], None] | None = None, *, own_stamps: bool = False,
                 reference: int = 0, keep: int = 256) -> None:
        self.n_imus = int(n_imus)
        self.on_complete = on_complete
        self.own_stamps, self.reference, self.keep = bool(own_stamps), int(reference), int(keep)
        self.payloads: list = []
        self.index: list = []
        self.completed = 0  # samples completed so far
        self._masks: dict = {}  # stamp bytes -> bits of the IMUs that sent it

    def receiver(self, k: int) -> Callable[[bytes], None]:
        """The callback of IMU k's topic."""
        payloads, index, masks = self.payloads, self.index, self._masks
        if self.on_complete is None:  # a plain queue: nothing to track

            def queue(payload: bytes) -> None:
                payloads.append(payload)
                index.append(k)

            return queue
        if self.own_stamps:
            ref = k == self.reference

            def receive_own(payload: bytes) -> None:
                payloads.append(payload)
                index.append(k)
                if ref:
                    self.on_complete(payload[4:12])

            return receive_own
        bit, full = 1 << int(k), (1 << self.n_imus) - 1

        def receive(payload: bytes) -> None:
            payloads.append(payload)
            index.append(k)
            key = payload[4:12]
            bits = masks.get(key, 0)
            if bits == full:  # complete already: a duplicate
                return
            bits |= bit
            masks[key] = bits
            if bits != full:
                if len(masks) > 2 * self.keep:
                    self._forget()
                return
            self.completed += 1
            self.on_complete(key)

        return receive

    def _forget(self) -> None:
        """Keep the newest ``keep`` stamps (amortised: once every ``keep`` new stamps)."""
        newest = list(self._masks.items())[-self.keep:]
        self._masks.clear()
        self._masks.update(newest)

    def __len__(self) -> int:
        return len(self.payloads)

    def drain(self) -> tuple[list, list]:
        """(payloads, imu indexes) queued since the last call, in arrival order."""
        payloads, index = self.payloads[:], self.index[:]
        del self.payloads[:], self.index[:]
        return payloads, index
