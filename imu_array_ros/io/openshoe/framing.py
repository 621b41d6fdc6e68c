"""OpenShoe raw-IMU serial framing: streaming parser, timestamp unwrapper, SI scaling.

Byte format (all integers big-endian), as streamed by OpenShoe / MIMU boards
after command ``0x28`` ("raw IMU output")::

    acknowledgement  A0 · cmd · uint16 checksum (= 0xA0 + cmd)     4 bytes, e.g. A0 28 00 C8
    data packet      AA · uint16 counter · size byte · payload · uint16 checksum
    payload          uint32 timestamp (64 MHz counter, wraps every 2**32 / 64e6 ≈ 67.1 s)
                     then for each IMU k = 1..K in ascending order six int16:
                     acc x, y, z, gyro x, y, z (counts, the IMU's own sensor axes)

* payload length = 4 + 12·K bytes; packet length ``L = 10 + 12·K`` (106 for K = 8).
* size byte = payload length mod 256 (it wraps for K >= 21, so K cannot be read from
  the stream: it is given by the array description and checked through the checksum).
* checksum = 16-bit sum of every byte from ``AA`` through the last payload byte.
* scale: accelerometer 2048 LSB/g (±16 g), gyroscope 16.4 LSB per °/s (±2000 °/s).

A candidate packet is accepted when it starts with ``AA``, its size byte matches
``L``, its checksum is valid and (optionally, ``require_next_header``) the byte
after it is again ``AA`` (or ``A0``, an acknowledgement); among overlapping
candidates the earliest wins.  A random frame passes the size byte and the
checksum with probability 2**-24, so a false resync inside garbage is rare but
possible; ``require_next_header`` makes it rarer still.  Candidates are searched
with numpy on the whole buffer, so a 4 MB capture parses in about 15 ms, and the
same :class:`OpenShoeFramer` serves a live serial port read in arbitrary chunks:
the result never depends on where the chunk boundaries fall.

Saturation: the MPU-9150 clips at the int16 limits; use :func:`saturation_mask`
on raw counts.  In SI units the largest magnitudes are ``32768/2048 g = 16 g``
(= ``accelerometer_range`` exactly) and ``32768/16.4 °/s ≈ 1998.05 °/s``,
slightly *below* a 2000 °/s ``gyroscope_range``: compare SI values against
:func:`si_saturation_level`, not against the description's range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imu_array_ros.model.constants import STANDARD_GRAVITY

__all__ = [
    "ACK_HEADER",
    "PACKET_HEADER",
    "TICK_HZ",
    "STANDARD_GRAVITY",
    "ACC_LSB_PER_G",
    "GYRO_LSB_PER_DPS",
    "ACC_SCALE",
    "GYRO_SCALE",
    "payload_length",
    "packet_length",
    "ParsedPackets",
    "FramerStats",
    "OpenShoeFramer",
    "parse_buffer",
    "encode_packets",
    "TickUnwrapper",
    "ticks_to_ns",
    "counts_to_si",
    "saturation_mask",
    "si_saturation_level",
]

PACKET_HEADER = 0xAA
ACK_HEADER = 0xA0
TICK_HZ = 64_000_000
ACC_LSB_PER_G = 2048.0
GYRO_LSB_PER_DPS = 16.4
ACC_SCALE = STANDARD_GRAVITY / ACC_LSB_PER_G
"""m/s^2 per accelerometer count."""
GYRO_SCALE = math.radians(1.0) / GYRO_LSB_PER_DPS
"""rad/s per gyroscope count."""

_HEAD = 4  # AA, counter (2), size byte
_TS = 4  # uint32 timestamp at the start of the payload
_U16 = 1 << 16


def payload_length(n_imus: int) -> int:
    """Payload bytes for ``n_imus`` IMUs: 4 (timestamp) + 12 per IMU."""
    return _TS + 12 * int(n_imus)


def packet_length(n_imus: int) -> int:
    """Whole packet bytes ``L``: header (4) + payload + checksum (2)."""
    return _HEAD + payload_length(n_imus) + 2


# --------------------------------------------------------------------------- containers


@dataclass
class ParsedPackets:
    """Complete, checksum-valid packets, in stream order.

    counter : (M,) uint16 packet counter.
    ticks : (M,) uint32 raw 64 MHz timestamp.
    raw : (M, K, 6) int16 counts ``[acc x, y, z, gyro x, y, z]`` per IMU, sensor axes.
    offsets : (M,) int64 absolute byte offset of each packet's ``AA`` in the stream.
    """

    counter: np.ndarray
    ticks: np.ndarray
    raw: np.ndarray
    offsets: np.ndarray

    @classmethod
    def empty(cls, n_imus: int) -> "ParsedPackets":
        return cls(
            np.zeros(0, np.uint16), np.zeros(0, np.uint32), np.zeros((0, n_imus, 6), np.int16), np.zeros(0, np.int64)
        )

    @classmethod
    def concatenate(cls, parts: "list[ParsedPackets]", n_imus: int) -> "ParsedPackets":
        """Join parts in order (an empty list gives an empty result)."""
        if not parts:
            return cls.empty(n_imus)
        return cls(
            np.concatenate([p.counter for p in parts]),
            np.concatenate([p.ticks for p in parts]),
            np.concatenate([p.raw for p in parts]),
            np.concatenate([p.offsets for p in parts]),
        )

    def __len__(self) -> int:
        return len(self.counter)


@dataclass
class FramerStats:
    """Running counters of an :class:`OpenShoeFramer` (all byte counts are stream bytes).

    bytes_in: bytes fed so far.  packets: packets accepted.  acks: command
    acknowledgements (``A0 cmd cs cs``) found outside packets.  garbage_bytes:
    bytes skipped that are neither packets, acknowledgements nor the trailing
    partial packet (includes the bytes of frames dropped for a bad checksum).
    bad_checksums: frames dropped at a position where a packet was expected
    (right after the previous packet/ack, or a multiple of ``L`` after it) that
    start with ``AA`` but fail the size-byte/checksum(/next-header) test.
    counter_gaps: packets missing according to the uint16 counter (wraps at 65536;
    a step of d in 2..32768 means d-1 missing).  counter_backsteps: counter repeated
    or went backwards (step 0 or > 32768: duplicate or device restart), not counted
    as missing.  trailing_bytes: incomplete packet at the end (set by ``finish``).
    """

    bytes_in: int = 0
    packets: int = 0
    acks: int = 0
    garbage_bytes: int = 0
    bad_checksums: int = 0
    counter_gaps: int = 0
    counter_backsteps: int = 0
    trailing_bytes: int = 0
    finished: bool = False

    @property
    def ack_seen(self) -> bool:
        return self.acks > 0


# --------------------------------------------------------------------------- framer


class OpenShoeFramer:
    """Incremental OpenShoe raw-IMU packet parser for ``n_imus`` IMUs.

    ``feed(data)`` returns the packets completed by ``data`` and keeps the
    undecided tail (at most one packet length plus 3 bytes) for the next call;
    ``finish()`` decides the tail at end of stream.  Any split of a byte stream
    into chunks gives the same packets and the same :attr:`stats` as one
    :func:`parse_buffer` call.

    Parameters
    ----------
    n_imus : int
        K, number of IMUs per packet (from the array description).
    require_next_header : bool
        Also require the byte after a packet to start a packet or an
        acknowledgement (``AA`` or ``A0``), or the stream to end there.
        Stronger against false resyncs in garbage, but delays each packet
        until the first byte of the next one arrives.
    """

    def __init__(self, n_imus: int, *, require_next_header: bool = False) -> None:
        if int(n_imus) < 1:
            raise ValueError(f"n_imus must be >= 1, got {n_imus}")
        self.n_imus = int(n_imus)
        self.length = packet_length(self.n_imus)
        self.size_byte = payload_length(self.n_imus) % 256
        self.require_next_header = bool(require_next_header)
        self.stats = FramerStats()
        self._buf = b""
        self._base = 0  # absolute stream offset of self._buf[0]
        self._anchor = 0  # absolute offset where the next packet is expected
        self._last_counter: int | None = None

    @property
    def pending(self) -> int:
        """Bytes held back, waiting for more data."""
        return len(self._buf)

    def feed(self, data: bytes) -> ParsedPackets:
        """Add stream bytes; return the packets completed so far (possibly none)."""
        if self.stats.finished:
            raise RuntimeError("OpenShoeFramer.feed() after finish()")
        self.stats.bytes_in += len(data)
        self._buf = self._buf + bytes(data) if self._buf else bytes(data)
        return self._process(final=False)

    def finish(self) -> ParsedPackets:
        """End of stream: decide the held-back tail; sets ``stats.trailing_bytes``."""
        if self.stats.finished:
            return ParsedPackets.empty(self.n_imus)
        out = self._process(final=True)
        self.stats.finished = True
        return out

    # ------------------------------------------------------------------ internals

    def _process(self, final: bool) -> ParsedPackets:
        L = self.length
        buf = np.frombuffer(self._buf, dtype=np.uint8)
        n = len(buf)
        if n == 0:
            return ParsedPackets.empty(self.n_imus)
        # Last start position whose verdict is known now.
        last = n - L if (final or not self.require_next_header) else n - L - 1
        is_aa = buf == PACKET_HEADER
        cand = np.flatnonzero(is_aa[: max(last + 1, 0)])
        valid = self._valid(buf, cand, final)
        starts = _greedy_chain(cand[valid], L)
        ends = starts + L
        end_last = int(ends[-1]) if len(starts) else 0

        # Every complete acknowledgement outside the packets (its verdict may still wait, below).
        acks = self._find_acks(buf, starts, n)
        # How far we may consume.
        consumed = n
        if not final:
            undecided_aa = np.flatnonzero(is_aa[max(last + 1, end_last) :])
            if len(undecided_aa):
                consumed = min(consumed, max(last + 1, end_last) + int(undecided_aa[0]))
            # an A0 in the last 3 bytes may begin an acknowledgement still incomplete,
            # unless it lies inside a complete one
            tail0 = max(n - 3, end_last)
            tail_a0 = tail0 + np.flatnonzero(buf[tail0:] == ACK_HEADER)
            if len(tail_a0) and len(acks):
                k = np.searchsorted(acks, tail_a0, side="right") - 1
                tail_a0 = tail_a0[~((k >= 0) & (tail_a0 < acks[np.maximum(k, 0)] + 4))]
            if len(tail_a0):
                consumed = min(consumed, int(tail_a0[0]))
            # never cut through an acknowledgement: keep it whole for the next call
            straddle = acks[(acks < consumed) & (acks + 4 > consumed)]
            if len(straddle):
                consumed = int(straddle[0])
        acks = acks[acks + 4 <= consumed]

        # The anchors for bad-frame alignment.
        anchors = np.sort(np.concatenate([ends, acks + 4]))
        self._count_bad_frames(cand[~valid], starts, anchors)

        trailing = 0
        if final:
            # An incomplete frame at the very end is a partial packet, not garbage.
            tail_from = max(last + 1, end_last, int(acks[-1]) + 4 if len(acks) else 0)
            tail_aa = np.flatnonzero(is_aa[tail_from:])
            if len(tail_aa):
                trailing = n - (tail_from + int(tail_aa[0]))
            self.stats.trailing_bytes = trailing
        self.stats.garbage_bytes += consumed - len(starts) * L - 4 * len(acks) - trailing
        self.stats.acks += len(acks)
        if len(anchors):
            self._anchor = self._base + int(anchors[-1])

        packets = self._extract(buf, starts)
        self._count_counter(packets.counter)
        self.stats.packets += len(starts)
        self._buf = self._buf[consumed:]
        self._base += consumed
        return packets

    def _valid(self, buf: np.ndarray, cand: np.ndarray, final: bool) -> np.ndarray:
        """(C,) bool: size byte, checksum (and next header) of candidates ``cand`` hold."""
        L = self.length
        if len(cand) == 0:
            return np.zeros(0, bool)
        ok = buf[cand + 3] == self.size_byte
        # 16-bit sums from cumulative uint32 sums: wrap-around mod 2**32 is exact mod 2**16.
        csum = np.concatenate([[0], np.cumsum(buf[: int(cand[-1]) + L - 2], dtype=np.uint32)])
        total = (csum[cand + L - 2] - csum[cand]) & 0xFFFF
        stored = (buf[cand + L - 2].astype(np.uint32) << 8) | buf[cand + L - 1]
        ok &= total == stored
        if self.require_next_header:
            nxt = cand + L
            inside = nxt < len(buf)
            after = buf[np.minimum(nxt, len(buf) - 1)]
            ok &= np.where(inside, (after == PACKET_HEADER) | (after == ACK_HEADER), final)
        return ok

    def _find_acks(self, buf: np.ndarray, starts: np.ndarray, consumed: int) -> np.ndarray:
        """Positions of ``A0 cmd cs cs`` (cs = 0xA0 + cmd) lying wholly outside packets and
        wholly before ``consumed``, not overlapping each other (the earliest wins)."""
        q = np.flatnonzero(buf[: max(consumed - 3, 0)] == ACK_HEADER)
        if len(q) == 0:
            return q
        cmd = buf[q + 1].astype(np.int64)
        cs = (buf[q + 2].astype(np.int64) << 8) | buf[q + 3]
        q = q[cs == ACK_HEADER + cmd]
        if len(q) and len(starts):
            k = np.searchsorted(starts, q, side="right") - 1
            prev_end = np.where(k >= 0, starts[np.maximum(k, 0)] + self.length, -1)
            nxt = np.searchsorted(starts, q, side="right")
            next_start = np.where(nxt < len(starts), starts[np.minimum(nxt, len(starts) - 1)], np.iinfo(np.int64).max)
            q = q[(q >= prev_end) & (q + 4 <= next_start)]
        return _greedy_chain(q, 4)  # overlapping acknowledgements: the earliest wins

    def _count_bad_frames(self, rejected: np.ndarray, starts: np.ndarray, anchors: np.ndarray) -> None:
        """Count rejected ``AA`` candidates outside packets that sit where a packet was due."""
        L = self.length
        if len(rejected) == 0:
            return
        if len(starts):
            k = np.searchsorted(starts, rejected, side="right") - 1
            inside = (k >= 0) & (rejected < starts[np.maximum(k, 0)] + L)
            rejected = rejected[~inside]
        a = np.searchsorted(anchors, rejected, side="right") - 1
        anchor_abs = np.where(a >= 0, self._base + anchors[np.maximum(a, 0)] if len(anchors) else 0, self._anchor)
        self.stats.bad_checksums += int(np.count_nonzero((self._base + rejected - anchor_abs) % L == 0))

    def _extract(self, buf: np.ndarray, starts: np.ndarray) -> ParsedPackets:
        K, L = self.n_imus, self.length
        if len(starts) == 0:
            return ParsedPackets.empty(K)
        frames = buf[starts[:, None] + np.arange(L)]  # (M, L) uint8
        counter = frames[:, 1:3].copy().view(">u2").ravel().astype(np.uint16)
        ticks = frames[:, 4:8].copy().view(">u4").ravel().astype(np.uint32)
        raw = frames[:, 8 : 8 + 12 * K].copy().view(">i2").astype(np.int16).reshape(-1, K, 6)
        return ParsedPackets(counter, ticks, raw, (self._base + starts).astype(np.int64))

    def _count_counter(self, counter: np.ndarray) -> None:
        if len(counter) == 0:
            return
        c = counter.astype(np.int64)
        if self._last_counter is not None:
            c = np.concatenate([[self._last_counter], c])
        step = np.diff(c) % _U16
        forward = (step >= 1) & (step <= _U16 // 2)
        self.stats.counter_gaps += int((step[forward] - 1).sum())
        self.stats.counter_backsteps += int(np.count_nonzero(~forward))
        self._last_counter = int(c[-1])


def _greedy_chain(valid: np.ndarray, L: int) -> np.ndarray:
    """Greedy non-overlapping packet starts: first valid start, then the first valid >= end, ...

    Vectorised over runs of back-to-back packets; the Python loop only runs once
    per discontinuity (garbage, dropped packet), never per packet.
    """
    n = len(valid)
    if n == 0:
        return valid
    nxt = np.searchsorted(valid, valid + L)  # index of first valid start after each packet
    breaks = np.flatnonzero(nxt != np.arange(1, n + 1))
    runs = []
    j = 0
    while j < n:
        b = np.searchsorted(breaks, j)
        r = int(breaks[b]) if b < len(breaks) else n - 1
        runs.append(valid[j : r + 1])
        j = int(nxt[r])
    return np.concatenate(runs)


def parse_buffer(data: bytes, n_imus: int, *, require_next_header: bool = False) -> tuple[ParsedPackets, FramerStats]:
    """Parse a whole byte stream at once (pure function): packets and final stats."""
    framer = OpenShoeFramer(n_imus, require_next_header=require_next_header)
    first = framer.feed(data)
    rest = framer.finish()
    return ParsedPackets.concatenate([first, rest], n_imus), framer.stats


def encode_packets(counter: np.ndarray, ticks: np.ndarray, raw: np.ndarray) -> bytes:
    """Build valid packets (test and replay use); inverse of the parser.

    counter (M,) uint16-compatible; ticks (M,) uint32-compatible; raw (M, K, 6) int16 counts.
    """
    raw = np.asarray(raw)
    M, K = raw.shape[0], raw.shape[1]
    L = packet_length(K)
    frames = np.zeros((M, L), dtype=np.uint8)
    frames[:, 0] = PACKET_HEADER
    frames[:, 1:3] = np.asarray(counter, dtype=np.int64).astype(">u2").view(np.uint8).reshape(M, 2)
    frames[:, 3] = payload_length(K) % 256
    frames[:, 4:8] = np.asarray(ticks, dtype=np.int64).astype(">u4").view(np.uint8).reshape(M, 4)
    frames[:, 8 : L - 2] = raw.astype(">i2").view(np.uint8).reshape(M, 12 * K)
    cs = frames[:, : L - 2].sum(axis=1, dtype=np.int64) & 0xFFFF
    frames[:, L - 2] = cs >> 8
    frames[:, L - 1] = cs & 0xFF
    return frames.tobytes()


# --------------------------------------------------------------------------- time


def ticks_to_ns(ticks: np.ndarray) -> np.ndarray:
    """64 MHz ticks (int64, already unwrapped) -> int64 ns, rounded (1 tick = 15.625 ns)."""
    t = np.asarray(ticks, dtype=np.int64)
    return (t * 125 + 4) // 8


class TickUnwrapper:
    """Unwrap the uint32 64 MHz timestamp into a continuous int64 tick count.

    Each step is taken modulo 2**32, so the result keeps increasing across
    counter wraps (every ≈ 67.1 s) as long as consecutive packets are less
    than 67 s apart.  Incremental: successive calls continue where the last
    one stopped.  The first tick seen is kept as is (not shifted to zero).
    """

    PERIOD = 1 << 32

    def __init__(self) -> None:
        self._last: int | None = None  # last unwrapped tick

    def unwrap(self, ticks: np.ndarray) -> np.ndarray:
        """(M,) uint32 ticks -> (M,) int64 continuous ticks."""
        t = np.asarray(ticks, dtype=np.int64)
        if len(t) == 0:
            return t
        if self._last is None:
            start = int(t[0])
            steps = np.diff(t) % self.PERIOD
        else:
            steps = np.diff(np.concatenate([[self._last % self.PERIOD], t])) % self.PERIOD
            start = self._last + int(steps[0])
            steps = steps[1:]
        out = start + np.concatenate([[0], np.cumsum(steps)])
        self._last = int(out[-1])
        return out

    def to_ns(self, ticks: np.ndarray) -> np.ndarray:
        """(M,) uint32 ticks -> (M,) int64 ns of the unwrapped device clock."""
        return ticks_to_ns(self.unwrap(ticks))


# --------------------------------------------------------------------------- scaling


def counts_to_si(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, K, 6) int16 counts -> accel (M, K, 3) m/s^2, gyro (M, K, 3) rad/s, sensor axes."""
    raw = np.asarray(raw)
    return raw[..., :3] * ACC_SCALE, raw[..., 3:] * GYRO_SCALE


def saturation_mask(raw: np.ndarray) -> np.ndarray:
    """(..., 6) bool: the count sits at an int16 limit (-32768 or 32767), i.e. clipped."""
    raw = np.asarray(raw)
    return (raw >= 32767) | (raw <= -32768)


def si_saturation_level() -> tuple[float, float]:
    """(accel m/s^2, gyro rad/s) magnitude of the smallest clipped count, 32767 counts.

    An SI value with ``abs(v) >= level * (1 - 1e-9)`` came from a clipped count.
    Accel: 32767/2048 g ≈ 15.9995 g ≈ ``accelerometer_range`` (16 g).  Gyro:
    32767/16.4 °/s ≈ 1997.99 °/s, 0.1 % below a 2000 °/s ``gyroscope_range``.
    """
    return 32767 * ACC_SCALE, 32767 * GYRO_SCALE
