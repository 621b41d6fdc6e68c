"""The checks of the OpenShoe frame parser's property tests, as plain functions (no hypothesis).

``test/test_framing_fuzz.py`` (the CI property tests, hypothesis) and :mod:`benchmarks.fuzz_framer` (10**6
generated inputs) run the same checks; each raises ``AssertionError("<property>: <details>")``.  What
"correct" means is stated in test/test_framing_fuzz.py's docstring and in
``imu_array_ros/io/openshoe/framing.py``.
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.io.openshoe.framing import (
    ACK_HEADER,
    PACKET_HEADER,
    OpenShoeFramer,
    ParsedPackets,
    encode_packets,
    packet_length,
    parse_buffer,
    payload_length,
)

__all__ = ["acceptable", "reference", "stream_chunks", "counter_steps", "check_stream", "ack", "CORRUPTIONS",
           "corrupt", "check_recovery", "check_bit_flips"]


def acceptable(data: bytes, p: int, k: int, require_next_header: bool) -> bool:
    """The acceptance rule at offset ``p`` of the whole stream ``data``."""
    L, n = packet_length(k), len(data)
    if p < 0 or p + L > n or data[p] != PACKET_HEADER or data[p + 3] != payload_length(k) % 256:
        return False
    if sum(data[p : p + L - 2]) & 0xFFFF != int.from_bytes(data[p + L - 2 : p + L], "big"):
        return False
    return not require_next_header or p + L == n or data[p + L] in (PACKET_HEADER, ACK_HEADER)


def reference(data: bytes, k: int, require_next_header: bool) -> tuple[list[int], dict]:
    """Plain-Python model of the framing rule: packet offsets and the stats it implies."""
    L, n = packet_length(k), len(data)
    valid, rejected = [], []
    p = data.find(PACKET_HEADER)
    while 0 <= p <= n - L:
        (valid if acceptable(data, p, k, require_next_header) else rejected).append(p)
        p = data.find(PACKET_HEADER, p + 1)
    packets: list[int] = []
    for p in valid:  # earliest candidate wins
        if not packets or p >= packets[-1] + L:
            packets.append(p)
    covered = bytearray(n)
    for p in packets:
        covered[p : p + L] = b"\x01" * L
    acks: list[int] = []
    q = data.find(ACK_HEADER)
    while 0 <= q <= n - 4:
        if (
            (not acks or q >= acks[-1] + 4)
            and int.from_bytes(data[q + 2 : q + 4], "big") == ACK_HEADER + data[q + 1]
            and not any(covered[q : q + 4])
        ):
            acks.append(q)
        q = data.find(ACK_HEADER, q + 1)
    tail_from = max(n - L + 1, packets[-1] + L if packets else 0, acks[-1] + 4 if acks else 0)
    t = data.find(PACKET_HEADER, tail_from)
    trailing = n - t if t >= 0 else 0
    anchors = sorted([p + L for p in packets] + [q + 4 for q in acks])
    bad = 0
    for p in rejected:
        if covered[p]:
            continue
        i = np.searchsorted(anchors, p, side="right") - 1
        bad += (p - (anchors[i] if i >= 0 else 0)) % L == 0
    stats = dict(
        packets=len(packets),
        acks=len(acks),
        garbage_bytes=n - len(packets) * L - 4 * len(acks) - trailing,
        bad_checksums=bad,
        trailing_bytes=trailing,
    )
    return packets, stats


def stream_chunks(data: bytes, k: int, require_next_header: bool, cuts) -> tuple[ParsedPackets, object]:
    """Feed ``data`` split at the offsets ``cuts`` (any order, repeats = empty chunks), then finish."""
    framer = OpenShoeFramer(k, require_next_header=require_next_header)
    parts, prev = [], 0
    for c in sorted(int(c) for c in cuts) + [len(data)]:
        parts.append(framer.feed(data[prev:c]))
        prev = c
        assert framer.pending <= framer.length + 3, f"pending: {framer.pending} > L + 3 after a feed"
    parts.append(framer.finish())
    return ParsedPackets.concatenate(parts, k), framer.stats


def counter_steps(counter: np.ndarray) -> tuple[int, int]:
    """(gaps, backsteps) as documented: a step d in 1..32768 means d - 1 missing, else a backstep."""
    step = np.diff(np.asarray(counter, np.int64)) % 65536
    forward = (step >= 1) & (step <= 32768)
    return int((step[forward] - 1).sum()), int(np.count_nonzero(~forward))


def check_stream(data: bytes, k: int, require_next_header: bool, cuts=()) -> tuple[ParsedPackets, object]:
    """Every property of one input; raises ``AssertionError("<property>: <details>")``.

    Returns the whole-buffer packets and stats.
    """
    L, n = packet_length(k), len(data)
    whole, ws = parse_buffer(data, k, require_next_header=require_next_header)

    # chunked == whole: packets (values, offsets, dtypes) and every stats field
    streamed, ss = stream_chunks(data, k, require_next_header, cuts)
    for f in ("counter", "ticks", "raw", "offsets"):
        a, b = getattr(whole, f), getattr(streamed, f)
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), f"chunking packets: {f} differ"
    assert ss == ws, f"chunking stats: {ss} != whole {ws}"  # every field

    # no corrupt sample out: each packet is, byte for byte, an acceptable frame of the input
    assert whole.raw.shape == (len(whole), k, 6) and whole.raw.dtype == np.int16, "packets: raw shape/dtype"
    off = [int(o) for o in whole.offsets]
    again = encode_packets(whole.counter, whole.ticks, whole.raw)
    for i, p in enumerate(off):
        assert data[p : p + L] == again[i * L : (i + 1) * L], f"packets: packet {i} at {p} is not the input's bytes"
        assert acceptable(data, p, k, require_next_header), f"packets: frame at {p} fails the acceptance rule"
    assert all(b >= a + L for a, b in zip(off, off[1:])), "packets: overlapping or unordered offsets"

    # exactly the frames the rule selects (earliest candidate wins), no more, no fewer
    ref_packets, ref_stats = reference(data, k, require_next_header)
    assert off == ref_packets, f"reference packets: at {off}, the rule selects {ref_packets}"

    # stats: what FramerStats promises
    assert ws.finished and ws.bytes_in == n and ws.packets == len(whole), f"stats: counts {ws}"
    parts = (ws.acks, ws.garbage_bytes, ws.trailing_bytes, ws.bad_checksums)
    assert min(parts) >= 0, f"stats: negative count {ws}"
    assert ws.packets * L + 4 * ws.acks + ws.garbage_bytes + ws.trailing_bytes == n, f"accounting: {ws}, n={n}"
    assert ws.trailing_bytes < L and (ws.trailing_bytes == 0 or data[n - ws.trailing_bytes] == PACKET_HEADER), (
        f"stats: trailing_bytes={ws.trailing_bytes} is not an incomplete frame"
    )
    assert (ws.counter_gaps, ws.counter_backsteps) == counter_steps(whole.counter), f"stats: counter steps {ws}"
    got = {f: getattr(ws, f) for f in ref_stats}
    assert got == ref_stats, f"reference stats: {got}, the rule gives {ref_stats}"
    return whole, ws


# --------------------------------------------------------------------------- strategies


def ack(cmd: int) -> bytes:
    return bytes([ACK_HEADER, cmd]) + (ACK_HEADER + cmd).to_bytes(2, "big")



CORRUPTIONS = ("flip", "drop byte", "drop packet", "insert between", "insert inside")


def corrupt(frames: list[bytes], ops, lead: bytes = b"") -> tuple[bytes, dict]:
    """Apply ``ops`` = [(kind, packet i, byte j, bit, junk bytes)] to the packets ``frames``.

    kind: one of :data:`CORRUPTIONS`; "insert inside" puts the junk strictly inside
    the packet.  Returns the stream (``lead`` first) and {i: offset} of the packets
    whose bytes arrive unchanged and contiguous (intact).
    """
    work = [bytearray(f) for f in frames]
    after = [b""] * len(frames)  # junk after packet i
    dropped = [False] * len(frames)
    for kind, i, j, bit, junk in ops:
        f = work[i]
        if kind == "flip" and f:
            f[j % len(f)] ^= 1 << bit
        elif kind == "drop byte" and f:
            del f[j % len(f)]
        elif kind == "drop packet":
            dropped[i] = True
        elif kind == "insert between":
            after[i] += junk
        elif kind == "insert inside" and len(f) > 1:
            at = 1 + j % (len(f) - 1)
            f[at:at] = junk
    data, where = bytearray(lead), {}
    for i, f in enumerate(work):
        if not dropped[i]:
            if f == frames[i]:
                where[i] = len(data)
            data += f
        data += after[i]
    return bytes(data), where


def check_recovery(data: bytes, k: int, require_next_header: bool, cuts, originals, where):
    """:func:`check_stream`, then: intact packets are recovered (test/test_framing_fuzz.py,
    ``test_corrupted_streams_recover_intact_packets``).  Returns the packets, the stats and the number
    of emitted frames that are not intact packets (damaged bytes passing the checksum).

    ``originals`` = (counter, ticks, raw) of the packets sent, ``where`` = {packet index:
    offset in ``data``} of those whose bytes arrived unchanged and contiguous.
    """
    counter, ticks, raw = originals
    L = packet_length(k)
    whole, stats = check_stream(data, k, require_next_header, cuts)
    emitted = {int(p): j for j, p in enumerate(whole.offsets)}
    intact_at = {p: i for i, p in where.items()}
    spurious = [p for p in emitted if p not in intact_at]
    for i, p in where.items():
        if p in emitted:
            j = emitted[p]
            same = (whole.counter[j], whole.ticks[j]) == (counter[i], ticks[i]) and np.array_equal(whole.raw[j], raw[i])
            assert same, f"recovery: packet {i} at {p} decoded wrongly"
        elif acceptable(data, p, k, require_next_header):
            over = [e for e in spurious if e < p < e + L]
            assert over, f"recovery: intact, acceptable packet {i} at {p} not recovered and not overlapped"
    if not spurious:
        got = sorted(intact_at[p] for p in emitted)
        lost = got[-1] - got[0] + 1 - len(got) if got else 0
        steps = (stats.counter_gaps, stats.counter_backsteps)
        assert steps == (lost, 0), f"recovery: counter gaps/backsteps {steps}, {lost} packets lost"
    return whole, stats, len(spurious)


def check_bit_flips(data: bytes, k: int, require_next_header: bool, cuts, clean: bytes, lead: int):
    """:func:`check_stream` on packets ``clean`` with bits flipped, placed after ``lead`` bytes; then see
    test/test_framing_fuzz.py, ``test_bit_flips_are_counted_as_bad_checksums``.  Returns the packets, the
    stats and the number of emitted frames that are not one of the clean packets."""
    L = packet_length(k)
    whole, stats = check_stream(data, k, require_next_header, cuts)
    places = range(lead, lead + len(clean), L)
    emitted = [int(p) for p in whole.offsets]
    spurious = [p for p in emitted if p not in places or data[p : p + L] != clean[p - lead : p - lead + L]]
    if not spurious and stats.acks == (1 if lead else 0):  # (an ack made of flipped bits would move the anchor)
        missing = [p for p in places if p not in emitted]
        bad = sum(data[p] == PACKET_HEADER for p in missing)
        assert stats.bad_checksums == bad, f"flips: bad_checksums {stats.bad_checksums}, {bad} packets rejected"
        idx = [places.index(p) for p in emitted]
        lost = idx[-1] - idx[0] + 1 - len(idx) if idx else 0
        steps = (stats.counter_gaps, stats.counter_backsteps)
        assert steps == (lost, 0), f"flips: counter gaps/backsteps {steps}, {lost} packets lost"
    return whole, stats, len(spurious)
