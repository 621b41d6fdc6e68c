"""Property tests (hypothesis) of the OpenShoe frame parser: any bytes, any chunking.

The checks live in :mod:`benchmarks.framing_checks` (plain functions, no hypothesis), so that
``python -m benchmarks.fuzz_framer`` runs exactly the same checks on 10**6 inputs.

What "correct" means here (the rule stated in ``imu_array_ros/io/openshoe/framing.py``):

* a frame at ``p`` is *acceptable* when ``data[p] == AA``, its size byte matches
  ``L``, its 16-bit checksum is valid and, with ``require_next_header``, the byte
  after it is ``AA``/``A0`` or the stream ends right after it;
* the emitted packets are the greedy chain of acceptable frames: the earliest
  acceptable frame, then the earliest one starting at or after its end, ...
  (:func:`reference`, a plain-Python model of that rule);
* an acknowledgement is ``A0 cmd cs`` (cs = 0xA0 + cmd, 16 bit) lying wholly outside
  the packets; when acknowledgements overlap each other the earliest wins, like packets;
* ``trailing_bytes`` is the incomplete frame at the end: from the first ``AA`` that
  starts after the last packet, the last acknowledgement and ``n - L``; the rest
  is garbage, so ``bytes_in == packets * L + 4 * acks + garbage_bytes + trailing_bytes``;
* ``bad_checksums`` counts rejected ``AA`` frames (complete, outside packets) at a
  multiple of ``L`` after the last packet/acknowledgement end before them (or the
  stream start);
* feeding the stream in any chunks gives the same packets and the same stats.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from imu_array_ros.io.openshoe.framing import (
    ACK_HEADER,
    PACKET_HEADER,
    encode_packets,
    packet_length,
    payload_length,
)

# --------------------------------------------------------------------------- the checks (shared with the benchmark)

from benchmarks.framing_checks import (  # noqa: E402
    ack,
    check_bit_flips,
    check_recovery,
    check_stream,
    corrupt,
)



# --------------------------------------------------------------------------- strategies

#: CI runs are reproducible: a fixed example sequence, no example database.
FUZZ = settings(
    derandomize=True,
    database=None,
    deadline=None,
    max_examples=250,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

#: small arrays, and K >= 21 where the size byte wraps (K = 21: size byte 0)
n_imus = st.one_of(st.integers(1, 4), st.sampled_from([21, 22]))

#: interesting command bytes: 0x00 and 0xA0 end / continue an ack with A0, 0x0A and 0xAA with AA
ack_cmds = st.one_of(st.sampled_from([0x00, 0x0A, 0x28, 0xA0, 0xAA]), st.integers(0, 255))


def valid_frame(k: int, counter: int, payload: bytes) -> bytes:
    ticks = int.from_bytes(payload[:4], "big")
    raw = np.frombuffer(payload[4:], ">i2").astype(np.int16).reshape(1, k, 6)
    return encode_packets([counter], [ticks], raw)


@st.composite
def packets(draw, k: int) -> bytes:
    payload = draw(st.binary(min_size=payload_length(k), max_size=payload_length(k)))
    return valid_frame(k, draw(st.integers(0, 65535)), payload)


@st.composite
def damaged_packets(draw, k: int) -> bytes:
    frame = bytearray(draw(packets(k)))
    how = draw(st.sampled_from(["flip", "prefix", "suffix", "slice"]))
    i, j = sorted(draw(st.lists(st.integers(0, len(frame)), min_size=2, max_size=2)))
    if how == "flip":
        frame[min(i, len(frame) - 1)] ^= 1 << draw(st.integers(0, 7))
        return bytes(frame)
    return bytes({"prefix": frame[:j], "suffix": frame[i:], "slice": frame[i:j]}[how])


@st.composite
def forged_frames(draw, k: int) -> bytes:
    """A frame with a valid checksum but any size byte, or a valid packet for another K."""
    if draw(st.booleans()):
        return draw(packets(draw(st.sampled_from(sorted({max(k - 1, 1), k + 1})))))
    frame = bytearray(draw(packets(k)))
    frame[3] = draw(st.one_of(st.just(payload_length(k) % 256), st.integers(0, 255)))
    frame[-2:] = (sum(frame[:-2]) & 0xFFFF).to_bytes(2, "big")
    return bytes(frame)


def fragments(k: int):
    header_like = st.sampled_from([PACKET_HEADER, ACK_HEADER, 0x00, 0x01, payload_length(k) % 256])
    headerish = st.lists(header_like, min_size=1, max_size=6)
    return st.one_of(
        packets(k),
        damaged_packets(k),
        forged_frames(k),
        packets(k).map(lambda f: ack(0x0A)[:3] + f),  # A0 0A 00 AA...: an ack overlapping a packet
        ack_cmds.map(ack),
        st.tuples(ack_cmds, st.integers(1, 3)).map(lambda t: ack(t[0])[: t[1]]),
        headerish.map(bytes),
        st.binary(min_size=1, max_size=40),
    )


@st.composite
def fragment_streams(draw) -> tuple[bytes, int]:
    k = draw(n_imus)
    return b"".join(draw(st.lists(fragments(k), max_size=8))), k


@st.composite
def cut_points(draw, n: int) -> list[int]:
    """Chunk boundaries: none, a few anywhere (repeats are empty chunks), or every byte."""
    if n and draw(st.integers(0, 9)) == 0:
        return list(range(1, n))
    return draw(st.lists(st.integers(0, n), max_size=8))


# --------------------------------------------------------------------------- any bytes


@FUZZ
@given(st.binary(max_size=700), n_imus, st.booleans(), st.data())
def test_any_bytes_any_chunking(data, k, require_next_header, draw):
    check_stream(data, k, require_next_header, draw.draw(cut_points(len(data)), label="cuts"))


@FUZZ
@given(fragment_streams(), st.booleans(), st.data())
def test_fragment_streams_any_chunking(stream, require_next_header, draw):
    """Valid and damaged packets, acknowledgements, runs of AA/A0/size bytes, random bytes."""
    data, k = stream
    check_stream(data, k, require_next_header, draw.draw(cut_points(len(data)), label="cuts"))


# Found by these tests (framing.py as of 5d79859): acknowledgements that end in / contain
# an A0 or AA byte, at the end of the stream or of a chunk, and overlapping ones.
ACK_EDGE_CASES = {
    "ack A0 00 00 A0 at the end": "a00000a0",
    "ack A0 A0 01 40 at the end": "a0a00140",
    "ack A0 0A 00 AA at the end": "a00a00aa",
    "ack A0 AA 01 4A, then a partial frame": "a0aa014a" + "55" * 30,
    "ack A0 0A 00 AA, then bytes": "a00a00aa" + "55" * 30,
    "ack ending in A0, then an ack": "a00000a0a06a010a",
    "acks sharing a byte": "a00000a04700e7",
}


@pytest.mark.parametrize("require_next_header", [False, True])
@pytest.mark.parametrize("hexdata", list(ACK_EDGE_CASES.values()), ids=list(ACK_EDGE_CASES))
def test_acknowledgement_edge_cases(hexdata, require_next_header):
    data = bytes.fromhex(hexdata)
    for cuts in [[]] + [[c] for c in range(1, len(data))] + [list(range(1, len(data)))]:
        check_stream(data, 1, require_next_header, cuts)


# --------------------------------------------------------------------------- corrupted packet streams


CORRUPTIONS = ("flip", "drop byte", "drop packet", "insert between", "insert inside")


@st.composite
def corrupted_streams(draw):
    """m consecutive packets (optionally after an ack), then bit flips, dropped bytes,
    dropped packets and garbage inserted between or inside packets."""
    k = draw(n_imus)
    m = draw(st.integers(1, 25 if k < 21 else 8))
    L = packet_length(k)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="payload seed"))
    counter = (draw(st.integers(0, 65535)) + np.arange(m)) % 65536
    ticks = rng.integers(0, 1 << 32, m)
    raw = rng.integers(-32768, 32768, (m, k, 6)).astype(np.int16)
    frames = [encode_packets(counter[i : i + 1], ticks[i : i + 1], raw[i : i + 1]) for i in range(m)]
    headers = st.lists(st.sampled_from([PACKET_HEADER, ACK_HEADER]), min_size=1, max_size=4).map(bytes)
    junk = st.one_of(st.binary(min_size=1, max_size=30), headers)
    op = st.tuples(st.sampled_from(CORRUPTIONS), st.integers(0, m - 1), st.integers(0, L - 1), st.integers(0, 7), junk)
    lead = ack(0x28) if draw(st.booleans()) else b""
    data, where = corrupt(frames, draw(st.lists(op, max_size=6)), lead)
    return data, k, (counter, ticks, raw), where


@FUZZ
@given(corrupted_streams(), st.booleans(), st.data())
def test_corrupted_streams_recover_intact_packets(stream, require_next_header, draw):
    """Recovered = emitted at its own offset with its own counter, ticks and counts.

    An intact packet (bytes unchanged) that satisfies the acceptance rule where it
    lies (with require_next_header: followed by AA/A0 or the end) is recovered,
    unless an earlier emitted frame overlaps it: earliest candidate wins, and that
    frame is then a checksum-passing frame of damaged bytes or garbage (each AA
    passes size byte and checksum with probability 2**-24), never another packet.
    Damaged packets come out only as such frames (``check_stream``: every emitted
    packet is an acceptable frame of the input, byte for byte).  Without such a
    frame the counter gaps are exactly the packets lost between the first and the
    last one recovered, and no backsteps.
    """
    data, k, originals, where = stream
    check_recovery(data, k, require_next_header, draw.draw(cut_points(len(data)), label="cuts"), originals, where)


@st.composite
def flipped_streams(draw):
    """m consecutive packets (optionally after an ack) with bit flips only: every packet keeps its place."""
    k = draw(n_imus)
    m = draw(st.integers(1, 25 if k < 21 else 8))
    L = packet_length(k)
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="payload seed"))
    counter = (draw(st.integers(0, 65535)) + np.arange(m)) % 65536
    clean = encode_packets(counter, rng.integers(0, 1 << 32, m), rng.integers(-32768, 32768, (m, k, 6)))
    data = bytearray(clean)
    for at in draw(st.lists(st.integers(0, m * L * 8 - 1), max_size=8)):
        data[at // 8] ^= 1 << (at % 8)
    lead = ack(0x28) if draw(st.booleans()) else b""
    return lead + bytes(data), k, clean, len(lead)


@FUZZ
@given(flipped_streams(), st.booleans(), st.data())
def test_bit_flips_are_counted_as_bad_checksums(stream, require_next_header, draw):
    """Packets at fixed places: each one not emitted that still starts with AA is a bad
    checksum, and the counter gaps are the packets not emitted inside the run.  A single
    flip never passes the checksum; two flips of one bit position in opposite directions
    do (in ``check_bit_flips`` such a frame is spurious and the counts are not checked)."""
    data, k, clean, lead = stream
    check_bit_flips(data, k, require_next_header, draw.draw(cut_points(len(data)), label="cuts"), clean, lead)


# --------------------------------------------------------------------------- counters


@FUZZ
@given(
    st.integers(1, 3),
    st.integers(0, 65535),
    st.lists(st.one_of(st.sampled_from([0, 1, 2, 32767, 32768, 32769, 65535]), st.integers(0, 65535)), max_size=30),
    st.booleans(),
    st.data(),
)
def test_counter_gaps_and_backsteps(k, c0, steps, require_next_header, draw):
    """Counter steps d (mod 65536) between packets: d in 1..32768 is d - 1 missing, 0 or > 32768 a backstep."""
    counter = (c0 + np.concatenate([[0], np.cumsum(steps, dtype=np.int64)])) % 65536
    m = len(counter)
    data = encode_packets(counter, np.arange(m), np.zeros((m, k, 6), np.int16))
    _, stats = check_stream(data, k, require_next_header, draw.draw(cut_points(len(data)), label="cuts"))
    assert stats.packets == m
    assert stats.counter_gaps == sum(d - 1 for d in steps if 1 <= d <= 32768)
    assert stats.counter_backsteps == sum(1 for d in steps if d == 0 or d > 32768)
