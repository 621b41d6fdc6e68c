"""OpenShoe framing: synthetic streams from fixed seeds, chunking, resync, real captures."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from imu_array_ros.io.openshoe.framing import (
    ACC_SCALE,
    GYRO_SCALE,
    FramerStats,
    OpenShoeFramer,
    ParsedPackets,
    TickUnwrapper,
    counts_to_si,
    encode_packets,
    packet_length,
    parse_buffer,
    payload_length,
    saturation_mask,
    si_saturation_level,
    ticks_to_ns,
)

ACK = b"\xa0\x28\x00\xc8"
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "openshoe_mimu4444bt"
CAPTURES = sorted(DATA.glob("exp_*.bin")) if DATA.is_dir() else []
needs_data = pytest.mark.skipif(not CAPTURES, reason=f"real captures not found in {DATA}")


def _packets(rng: np.random.Generator, m: int, k: int, *, c0: int = 0, t0: int = 0, dt: int = 1_024_000):
    counter = (c0 + np.arange(m)) % 65536
    ticks = (t0 + np.arange(m, dtype=np.int64) * dt) % (1 << 32)
    raw = rng.integers(-32768, 32768, size=(m, k, 6)).astype(np.int16)
    return counter, ticks, raw


def _garbage(rng: np.random.Generator, n: int, *, avoid_headers: bool = True) -> bytes:
    g = rng.integers(0, 256, n, dtype=np.uint8)
    if avoid_headers:
        g[(g == 0xAA) | (g == 0xA0)] = 0x55
    return g.tobytes()


def _split(data: bytes, sizes) -> list[bytes]:
    out, i = [], 0
    for s in sizes:
        if i >= len(data):
            break
        out.append(data[i : i + s])
        i += s
    if i < len(data):
        out.append(data[i:])
    return out


def _stream(chunks, k: int, **kw) -> tuple[ParsedPackets, FramerStats]:
    framer = OpenShoeFramer(k, **kw)
    parts = []
    for c in chunks:
        parts.append(framer.feed(c))
        assert framer.pending <= framer.length + 3
    parts.append(framer.finish())
    return ParsedPackets.concatenate(parts, k), framer.stats


def _assert_same(a: ParsedPackets, b: ParsedPackets) -> None:
    for f in ("counter", "ticks", "raw", "offsets"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
        assert getattr(a, f).dtype == getattr(b, f).dtype, f


def _messy_stream(seed: int, k: int = 3, m: int = 60) -> tuple[bytes, dict]:
    """Ack, packets, garbage (with AA bytes), a bad checksum, a gap, a mid-stream ack, a partial tail."""
    rng = np.random.default_rng(seed)
    counter, ticks, raw = _packets(rng, m, k, c0=65520)
    pk = [encode_packets(counter[i : i + 1], ticks[i : i + 1], raw[i : i + 1]) for i in range(m)]
    bad = bytearray(pk[10])
    bad[-1] ^= 0x01
    pk[10] = bytes(bad)
    pk[20] = b""  # dropped in transmission: one counter gap
    pk[30] = pk[30] + _garbage(rng, 37, avoid_headers=False) + b"\xaa\xaa"
    pk[40] = pk[40] + b"\xa0\x22\x00\xc2"  # ack of another command between packets
    data = ACK + b"".join(pk) + pk[0][:17]
    return data, {"m": m, "k": k}


# --------------------------------------------------------------------------- basics


def test_lengths():
    assert packet_length(8) == 106 and payload_length(8) == 100
    assert packet_length(32) == 394 and payload_length(32) % 256 == 132  # size byte wraps


def test_round_trip():
    rng = np.random.default_rng(0)
    counter, ticks, raw = _packets(rng, 200, 8, c0=100, t0=123)
    data = encode_packets(counter, ticks, raw)
    assert len(data) == 200 * 106
    packets, stats = parse_buffer(ACK + data, 8)
    np.testing.assert_array_equal(packets.counter, counter)
    np.testing.assert_array_equal(packets.ticks, ticks)
    np.testing.assert_array_equal(packets.raw, raw)
    np.testing.assert_array_equal(packets.offsets, 4 + 106 * np.arange(200))
    assert packets.counter.dtype == np.uint16 and packets.ticks.dtype == np.uint32 and packets.raw.dtype == np.int16
    assert stats == FramerStats(bytes_in=len(data) + 4, packets=200, acks=1, finished=True)
    assert stats.ack_seen


def test_big_endian_layout():
    raw = np.zeros((1, 2, 6), np.int16)
    raw[0, 1] = [1, -2, 3, 32767, -32768, 256]
    data = encode_packets([0x1234], [0x89ABCDEF], raw)
    assert data[:8] == bytes([0xAA, 0x12, 0x34, 28, 0x89, 0xAB, 0xCD, 0xEF])
    assert data[8 + 12 : 8 + 24] == bytes.fromhex("0001fffe00037fff80000100")
    assert int.from_bytes(data[-2:], "big") == sum(data[:-2]) & 0xFFFF


def test_size_byte_wraps_for_many_imus():
    rng = np.random.default_rng(5)
    counter, ticks, raw = _packets(rng, 20, 32)
    packets, stats = parse_buffer(encode_packets(counter, ticks, raw), 32)
    np.testing.assert_array_equal(packets.raw, raw)
    assert stats.garbage_bytes == 0


def test_empty_and_tiny_inputs():
    packets, stats = parse_buffer(b"", 8)
    assert len(packets) == 0 and packets.raw.shape == (0, 8, 6) and stats.trailing_bytes == 0
    packets, stats = parse_buffer(ACK, 8)
    assert len(packets) == 0 and stats.acks == 1 and stats.garbage_bytes == 0
    packets, stats = parse_buffer(b"\xaa\x00", 8)
    assert stats.trailing_bytes == 2 and stats.garbage_bytes == 0
    with pytest.raises(ValueError):
        OpenShoeFramer(0)


# --------------------------------------------------------------------------- chunking


def test_one_byte_chunks_equal_whole_parse():
    data, info = _messy_stream(seed=1)
    whole, whole_stats = parse_buffer(data, info["k"])
    streamed, stats = _stream([data[i : i + 1] for i in range(len(data))], info["k"])
    _assert_same(whole, streamed)
    assert dataclasses.asdict(stats) == dataclasses.asdict(whole_stats)


def test_messy_stream_counts():
    data, info = _messy_stream(seed=1)
    k, L = info["k"], packet_length(info["k"])
    packets, stats = parse_buffer(data, k)
    assert len(packets) == info["m"] - 2  # one bad checksum, one lost
    assert stats.acks == 2
    assert stats.bad_checksums == 1
    assert stats.counter_gaps == 2 and stats.counter_backsteps == 0  # the dropped and the lost packet
    assert stats.garbage_bytes == L + 37 + 2  # the corrupted packet, the garbage, two stray AA
    assert stats.trailing_bytes == 17
    assert stats.bytes_in == len(data)
    # Counters wrap 65535 -> 0 inside the stream: not a gap.
    assert 65535 in packets.counter and 0 in packets.counter


@pytest.mark.parametrize("seed", [2, 3])
def test_random_chunks_equal_whole_parse(seed):
    rng = np.random.default_rng(seed)
    k = 8
    counter, ticks, raw = _packets(rng, 3000, k, c0=60000, t0=(1 << 32) - 5_000_000)
    pieces = []
    for i in range(0, 3000, 100):
        pieces.append(_garbage(rng, int(rng.integers(0, 300)), avoid_headers=False))
        pieces.append(encode_packets(counter[i : i + 100], ticks[i : i + 100], raw[i : i + 100]))
    data = ACK + b"".join(pieces) + b"\xaa\x01"
    whole, whole_stats = parse_buffer(data, k)
    np.testing.assert_array_equal(whole.raw, raw)  # everything recovered through the garbage
    sizes = rng.integers(1, 2000, size=len(data))
    streamed, stats = _stream(_split(data, sizes), k)
    _assert_same(whole, streamed)
    assert dataclasses.asdict(stats) == dataclasses.asdict(whole_stats)
    garbage = sum(len(p) for p in pieces[0::2])
    assert stats.garbage_bytes == garbage and stats.trailing_bytes == 2
    assert stats.counter_gaps == 0


def test_require_next_header_mode():
    data, info = _messy_stream(seed=4)
    k = info["k"]
    loose, loose_stats = parse_buffer(data, k)
    strict, strict_stats = parse_buffer(data, k, require_next_header=True)
    # Packet 30 is followed by garbage, so the strict mode drops it.
    assert len(strict) == len(loose) - 1
    assert strict_stats.garbage_bytes == loose_stats.garbage_bytes + packet_length(k)
    streamed, stats = _stream([data[i : i + 7] for i in range(0, len(data), 7)], k, require_next_header=True)
    _assert_same(strict, streamed)
    assert dataclasses.asdict(stats) == dataclasses.asdict(strict_stats)
    # A packet is held back until the first byte of the next one arrives.
    one = encode_packets([1, 2], [10, 20], np.zeros((2, k, 6), np.int16))
    framer = OpenShoeFramer(k, require_next_header=True)
    L = packet_length(k)
    assert len(framer.feed(one[:L])) == 0
    assert len(framer.feed(one[L : L + 1])) == 1
    assert len(framer.feed(one[L + 1 :])) == 0
    assert len(framer.finish()) == 1


@pytest.mark.parametrize("require_next_header", [False, True])
def test_fuzz_chunking_and_byte_accounting(require_next_header):
    """Random corruption (bit flips, truncation, garbage, acks, stray AA): any chunking
    gives the whole-buffer result, and every byte is a packet, ack, garbage or tail."""
    for seed in range(40):
        rng = np.random.default_rng(1000 + seed)
        k, m = int(rng.integers(1, 6)), int(rng.integers(0, 40))
        counter, ticks, raw = _packets(rng, m, k, c0=int(rng.integers(0, 65536)))
        parts = [ACK] if rng.random() < 0.5 else []
        for i in range(m):
            pk = bytearray(encode_packets(counter[i : i + 1], ticks[i : i + 1], raw[i : i + 1]))
            r = rng.random()
            if r < 0.1:
                pk[rng.integers(len(pk))] ^= 1 << int(rng.integers(8))
            elif r < 0.15:
                pk = pk[: rng.integers(len(pk))]
            parts.append(bytes(pk))
            if rng.random() < 0.15:
                parts.append(_garbage(rng, int(rng.integers(1, 50)), avoid_headers=False))
            if rng.random() < 0.05:
                parts.append(b"\xaa" * int(rng.integers(1, 5)) + ACK)
        data = b"".join(parts)
        whole, ws = parse_buffer(data, k, require_next_header=require_next_header)
        L = packet_length(k)
        assert ws.packets * L + 4 * ws.acks + ws.garbage_bytes + ws.trailing_bytes == len(data), seed
        for max_chunk in (1, 5, 300):
            sizes = rng.integers(1, max_chunk + 1, len(data) + 1)
            streamed, ss = _stream(_split(data, sizes), k, require_next_header=require_next_header)
            _assert_same(whole, streamed)
            assert dataclasses.asdict(ss) == dataclasses.asdict(ws), (seed, max_chunk)


# --------------------------------------------------------------------------- resync and counters


def test_garbage_between_packets_resyncs():
    rng = np.random.default_rng(6)
    counter, ticks, raw = _packets(rng, 10, 4)
    pk = [encode_packets(counter[i : i + 1], ticks[i : i + 1], raw[i : i + 1]) for i in range(10)]
    data = _garbage(rng, 13) + pk[0] + pk[1] + _garbage(rng, 50) + b"".join(pk[2:])
    packets, stats = parse_buffer(data, 4)
    np.testing.assert_array_equal(packets.raw, raw)
    assert stats.garbage_bytes == 63 and stats.bad_checksums == 0 and stats.acks == 0 and stats.counter_gaps == 0


def test_garbage_inside_packet_drops_it():
    rng = np.random.default_rng(7)
    counter, ticks, raw = _packets(rng, 10, 4)
    L = packet_length(4)
    data = encode_packets(counter, ticks, raw)
    cut = 5 * L + 30
    data = data[:cut] + _garbage(rng, 21) + data[cut:]
    packets, stats = parse_buffer(data, 4)
    np.testing.assert_array_equal(packets.counter, np.delete(counter, 5))
    assert stats.bad_checksums == 1 and stats.garbage_bytes == L + 21 and stats.counter_gaps == 1


def test_corrupted_checksums_dropped_and_counted():
    rng = np.random.default_rng(8)
    counter, ticks, raw = _packets(rng, 20, 8)
    L = packet_length(8)
    buf = bytearray(encode_packets(counter, ticks, raw))
    for i, at in ((3, 50), (4, 80), (11, L - 1)):  # payload byte, payload byte, checksum byte
        buf[i * L + at] ^= 0x10
    packets, stats = parse_buffer(bytes(buf), 8)
    np.testing.assert_array_equal(packets.counter, np.delete(counter, [3, 4, 11]))
    assert stats.bad_checksums == 3 and stats.garbage_bytes == 3 * L
    assert stats.counter_gaps == 3  # the framer only sees the counter jump


def test_counter_gaps_with_wrap_and_backsteps():
    k = 2
    counter = np.array([65533, 65534, 65535, 2, 3, 10, 10, 5, 6], dtype=np.int64)
    raw = np.zeros((len(counter), k, 6), np.int16)
    data = encode_packets(counter, np.arange(len(counter)), raw)
    packets, stats = parse_buffer(data, k)
    assert len(packets) == len(counter)
    assert stats.counter_gaps == 2 + 6  # 0, 1 lost over the wrap; 4..9 lost
    assert stats.counter_backsteps == 2  # 10 repeated, then back to 5
    # Same across feeds (the last counter is carried over).
    L = packet_length(k)
    streamed, st = _stream([data[i : i + L] for i in range(0, len(data), L)], k)
    assert (st.counter_gaps, st.counter_backsteps) == (8, 2)


def test_acks_split_across_feeds_and_no_false_ack_inside_packets():
    rng = np.random.default_rng(9)
    counter, ticks, raw = _packets(rng, 5, 1)
    raw[2, 0, :2] = np.array([0xA028, 0x00C8], np.uint16).view(np.int16)  # A0 28 00 C8 inside a payload
    data = ACK + encode_packets(counter, ticks, raw) + ACK
    for chunks in ([data], [data[i : i + 1] for i in range(len(data))], [data[:2], data[2:-3], data[-3:]]):
        packets, stats = _stream(chunks, 1)
        assert len(packets) == 5 and stats.acks == 2 and stats.garbage_bytes == 0


# --------------------------------------------------------------------------- time and scaling


def test_tick_unwrapper_across_wrap_and_feeds():
    rng = np.random.default_rng(10)
    steps = rng.integers(990_000, 1_050_000, 20_000)  # ~16 ms at 64 MHz; 5 wraps
    true = 4_200_000_000 + np.concatenate([[0], np.cumsum(steps)])
    wrapped = (true % (1 << 32)).astype(np.uint32)
    whole = TickUnwrapper().unwrap(wrapped)
    np.testing.assert_array_equal(whole, true)
    unwrapper = TickUnwrapper()
    parts = [unwrapper.unwrap(c) for c in np.array_split(wrapped, [1, 2, 500, 500, 7000, 19_999])]
    np.testing.assert_array_equal(np.concatenate(parts), true)
    ns = TickUnwrapper().to_ns(wrapped)
    assert np.all(np.diff(ns) > 0)
    assert ticks_to_ns(np.array([64_000_000, 1, 8])).tolist() == [1_000_000_000, 16, 125]


def test_scaling_and_saturation():
    raw = np.array([[[2048, -2048, 32767, 164, -164, -32768]]], np.int16)
    acc, gyr = counts_to_si(raw)
    np.testing.assert_allclose(acc[0, 0, :2], [9.80665, -9.80665])
    np.testing.assert_allclose(np.degrees(gyr[0, 0, :2]), [10.0, -10.0])
    assert ACC_SCALE == 9.80665 / 2048 and GYRO_SCALE == pytest.approx(np.radians(1 / 16.4))
    assert saturation_mask(raw).tolist() == [[[False, False, True, False, False, True]]]
    acc_level, gyro_level = si_saturation_level()
    assert abs(acc[0, 0, 2]) >= acc_level * (1 - 1e-9) and abs(gyr[0, 0, 2]) >= gyro_level * (1 - 1e-9)
    assert acc_level == pytest.approx(16 * 9.80665, rel=1e-4)
    assert np.degrees(gyro_level) == pytest.approx(1997.99, abs=0.01)


# --------------------------------------------------------------------------- real captures


@needs_data
def test_real_captures_frame_cleanly():
    L = packet_length(8)
    for path in CAPTURES:
        data = path.read_bytes()
        assert data[:4] == ACK
        packets, stats = parse_buffer(data, 8)
        assert stats.acks == 1
        assert stats.bad_checksums == 0 and stats.garbage_bytes == 0, path.name
        assert stats.counter_gaps == 0 and stats.counter_backsteps == 0, path.name
        assert len(packets) == (len(data) - 4) // L
        assert stats.trailing_bytes == (len(data) - 4) % L
        dt_ms = np.diff(TickUnwrapper().to_ns(packets.ticks)) / 1e6
        assert 15.6 < dt_ms.min() and dt_ms.max() < 16.05, path.name
    # exp_1 is the one capture that ends with a partial packet (83 of 106 bytes).
    _, stats = parse_buffer(CAPTURES[0].read_bytes(), 8)
    assert CAPTURES[0].name == "exp_1.bin" and stats.trailing_bytes == 83


@needs_data
def test_real_capture_random_chunks_equal_whole():
    data = CAPTURES[0].read_bytes()
    whole, whole_stats = parse_buffer(data, 8)
    sizes = np.random.default_rng(11).integers(1, 4096, size=len(data) // 1000)
    streamed, stats = _stream(_split(data, sizes), 8)
    _assert_same(whole, streamed)
    assert dataclasses.asdict(stats) == dataclasses.asdict(whole_stats)


@needs_data
def test_parse_speed_whole_capture():
    data = max(CAPTURES, key=lambda p: p.stat().st_size).read_bytes()
    parse_buffer(data[:10_000], 8)  # warm up
    t0 = time.perf_counter()
    packets, _ = parse_buffer(data, 8)
    counts_to_si(packets.raw)
    TickUnwrapper().to_ns(packets.ticks)
    elapsed = time.perf_counter() - t0
    assert elapsed < 0.5, f"{len(data)} bytes took {elapsed:.3f} s"
