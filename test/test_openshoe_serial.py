"""OpenShoe serial side of the driver: command protocol, device clock, serial link <-> fake device on a real pty.

Link tests run against :class:`FakeArrayDevice` (or a pseudo-terminal the test
drives itself) in real time; all randomness comes from fixed seeds.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
import serial

from imu_array_ros.errors import OutputError
from imu_array_ros.io.openshoe.clock import DeviceClock
from imu_array_ros.io.openshoe.framing import encode_packets, ticks_to_ns
from imu_array_ros.io.openshoe.protocol import (
    START_ACK,
    STOP_COMMAND,
    Command,
    CommandParser,
    ack_for,
    default_imu_mask,
    mask_bits,
    output_rate_hz,
    rate_divider_for,
    start_command,
)

from conftest import SHARED_DATA

needs_pty = pytest.mark.skipif(not hasattr(os, "openpty"), reason="os.openpty is not available")
CAPTURE = SHARED_DATA / "exp_1.bin"
needs_capture = pytest.mark.skipif(not CAPTURE.is_file(), reason=f"{CAPTURE} not found")
K = 8


# --------------------------------------------------------------------------- protocol


def test_command_bytes():
    assert start_command(0xFF, 5) == bytes.fromhex("28 000000FF 05 012C")
    assert start_command(0x80000001, 1) == bytes.fromhex("28 80000001 01 00AA")
    assert STOP_COMMAND == bytes.fromhex("22 00 22")
    assert ack_for(0x28) == START_ACK == bytes.fromhex("A0 28 00 C8")
    assert ack_for(0x22) == bytes.fromhex("A0 22 00 C2")
    assert [output_rate_hz(d) for d in range(1, 8)] == [1000, 500, 250, 125, 62.5, 31.25, 15.625]
    assert all(rate_divider_for(output_rate_hz(d)) == d for d in range(1, 8))
    assert default_imu_mask(8) == 0xFF and default_imu_mask(32) == 0xFFFFFFFF
    assert mask_bits(0b1010_0001) == [0, 5, 7]


@pytest.mark.parametrize("call, name", [
    (lambda: start_command(0, 5), "imu_mask"),
    (lambda: start_command(1 << 32, 5), "imu_mask"),
    (lambda: start_command(-1, 5), "imu_mask"),
    (lambda: start_command(0xFF, 0), "rate_divider"),
    (lambda: start_command(0xFF, 8), "rate_divider"),
    (lambda: output_rate_hz(2.5), "rate_divider"),
    (lambda: rate_divider_for(100.0), "rate must be one of 1000, 500"),
    (lambda: default_imu_mask(33), "n_imus"),
])
def test_command_validation(call, name):
    with pytest.raises(ValueError, match=name):
        call()


def test_command_parser_any_split_and_bad_checksums():
    start = start_command(0x0F, 5)
    bad_stop = bytes.fromhex("22 00 23")
    stream = b"\x01\x28" + start + bad_stop + b"\x99" + STOP_COMMAND + start_command(0xFF, 7)
    whole = CommandParser()
    cmds = whole.feed(stream)
    # a stray 0x28 in front of the real command does not swallow it; the bad stop is dropped and counted
    assert cmds == [Command(0x28, bytes.fromhex("0000000F05")), Command(0x22),
                    Command(0x28, bytes.fromhex("000000FF07"))]
    assert cmds[0].imu_mask == 0x0F and cmds[0].rate_divider == 5 and cmds[2].rate_divider == 7
    assert whole.stats.bad_checksums == 2 and whole.stats.commands == 3  # stray 28 and the bad stop
    assert whole.stats.unknown_bytes >= 2
    for cut in range(len(stream) + 1):
        p = CommandParser()
        assert p.feed(stream[:cut]) + p.feed(stream[cut:]) == cmds
        assert p.stats == whole.stats
    one = CommandParser()
    assert sum((one.feed(bytes([b])) for b in stream), []) == cmds
    with pytest.raises(ValueError, match="not a start command"):
        Command(0x22).imu_mask


# --------------------------------------------------------------------------- clock


def _arrivals(seed: int, seconds: float, *, skew=50e-6, min_latency=2e6, jitter=20e6, poll=5e6, stall=None):
    """Device times at 62.5 Hz, true generation host times, and poll batches (host ns, slice)."""
    rng = np.random.default_rng(seed)
    n = int(seconds * 62.5)
    d = 7_000_000_000 + np.arange(n, dtype=np.int64) * 16_000_000
    gen = 1_795_255_200 * 10**9 + np.round((d - d[0]) * (1 + skew)).astype(np.int64)
    lat = (min_latency + rng.uniform(0, jitter, n)).astype(np.int64)
    if stall is not None:  # a radio stall: everything in [t0, t1) s arrives 300 ms late
        lat[((d - d[0]) >= stall[0] * 1e9) & ((d - d[0]) < stall[1] * 1e9)] += 300_000_000
    received = np.maximum.accumulate(gen + lat)  # a serial link keeps the order
    polls = np.arange(received[0], received[-1] + poll, poll).astype(np.int64)
    ends = np.searchsorted(received, polls, side="right")
    starts = np.concatenate([[0], ends[:-1]])
    keep = ends > starts
    return d, gen, list(zip(polls[keep], starts[keep], ends[keep]))


def _map_all(clock, d, batches):
    return np.concatenate([clock.map(d[a:b], int(h)) for h, a, b in batches])


def test_clock_follows_drift_without_latency_jitter():
    """50 ppm drift, 2 ms + U(0, 20 ms) latency, 5 ms polling, a 300 ms radio stall at 60-63 s."""
    d, gen, batches = _arrivals(11, 120.0, stall=(60, 63))
    clock = DeviceClock()
    stamps = _map_all(clock, d, batches)
    err_ms = (stamps - (gen + 2_000_000)) / 1e6  # against truth + minimum latency
    settled = (d - d[0]) > 30e9
    assert np.abs(err_ms[settled]).max() < 1.5, np.abs(err_ms[settled]).max()
    assert np.median(np.abs(err_ms[settled])) < 0.5
    assert abs(clock.skew - 50e-6) < 10e-6
    assert clock.reanchors == 0
    # strictly increasing; every interval is the device interval within the slew bound, and after
    # settling nearly always the device interval times (1 + skew)
    ratio = np.diff(stamps) / np.diff(d)
    assert (np.diff(stamps) > 0).all()
    assert np.abs(ratio - 1).max() <= clock.max_slew + 1e-6
    assert np.median(np.abs(ratio[settled[1:]] - (1 + 50e-6))) < 1e-5


def test_clock_same_device_time_same_stamp_and_reset():
    d, _, batches = _arrivals(3, 5.0)
    clock = DeviceClock()
    _map_all(clock, d, batches[:-1])
    h, a, b = batches[-1]
    twice = clock.map(np.concatenate([d[a:b], d[b - 1 : b]]), int(h))
    assert twice[-1] == twice[-2]
    assert clock.map(d[b - 1 : b], int(h) + 5_000_000)[0] == twice[-1]  # again in a later batch
    clock.map(d[:1], int(h))  # device time went backwards: the clock re-anchors itself
    assert clock.reanchors == 1
    clock.reset()
    assert clock.offset_ns is None and clock.skew == 0.0
    assert clock.map(np.zeros(0, np.int64), 0).shape == (0,)


def test_samples_to_counts_inverts_scaling_with_clipping():
    from imu_array_ros.io.openshoe.fake_device import samples_to_counts, stamps_to_ticks
    from imu_array_ros.io.openshoe.framing import ACC_SCALE, GYRO_SCALE, counts_to_si

    raw = np.random.default_rng(5).integers(-32768, 32768, size=(40, 3, 6)).astype(np.int16)
    np.testing.assert_array_equal(samples_to_counts(*counts_to_si(raw)), raw)
    acc = np.array([[[1e6, -1e6, 0.4 * ACC_SCALE]]])
    gyr = np.array([[[np.nan, 40.0, -0.6 * GYRO_SCALE]]])
    np.testing.assert_array_equal(samples_to_counts(acc, gyr), [[[32767, -32768, 0, 0, 32767, -1]]])
    stamps = 1_795_255_200 * 10**9 + np.array([0, 15_625, 1_000_000_000, 70 * 10**9])
    np.testing.assert_array_equal(stamps_to_ticks(stamps), [0, 1000, 64_000_000, (70 * 64_000_000) % (1 << 32)])


# --------------------------------------------------------------------------- link helpers


def _collect(link, dev=None, *, until=None, timeout=15.0):
    """Poll ``link`` every 2 ms until ``until()`` (default: ``dev`` finished and drained); the batches."""
    parts = []
    end = time.monotonic() + timeout
    done = until or (lambda: dev.wait_finished(0))
    while time.monotonic() < end:
        b = link.poll()
        if len(b):
            parts.append(b)
        elif done():
            break
        else:
            time.sleep(0.002)
    else:
        pytest.fail(f"timed out; link {link.stats}")
    b = link.poll()
    return parts + ([b] if len(b) else [])


def _cat(parts, name):
    return np.concatenate([getattr(p, name) for p in parts])


def _packets(m, k=K, *, seed=0, c0=0, t0=0, dt=1_024_000):
    rng = np.random.default_rng(seed)
    counter = (c0 + np.arange(m)) % 65536
    ticks = (t0 + np.arange(m, dtype=np.int64) * dt) % (1 << 32)
    raw = rng.integers(-32768, 32768, size=(m, k, 6)).astype(np.int16)
    return counter, ticks, raw


# --------------------------------------------------------------------------- link <-> fake device


@needs_pty
@needs_capture
def test_capture_replayed_byte_for_byte_decodes_like_import():
    from imu_array_ros.io.openshoe.capture import import_capture
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink
    from imu_array_ros.model.layouts import make_description

    samples, cstats = import_capture(CAPTURE, make_description(np.zeros((K, 3))))
    with FakeArrayDevice.from_capture(CAPTURE, K, speed=0) as dev:
        link = SerialArrayLink(dev.port, K)
        parts = _collect(link, dev)
        link.close()
        rec = dev.record
    st = link.stats
    assert st.packets == cstats.packets == len(samples) == rec.packets_sent
    assert st.bytes_in == CAPTURE.stat().st_size  # the device's ack replaces the file's: same bytes
    assert (st.bad_checksums, st.garbage_bytes, st.counter_gaps, st.acks, st.connects) == (0, 0, 0, 1, 1)
    np.testing.assert_array_equal(_cat(parts, "accel"), samples.accel)
    np.testing.assert_array_equal(_cat(parts, "gyro"), samples.gyro)
    dev_ns = _cat(parts, "device_ns")
    np.testing.assert_array_equal(dev_ns - dev_ns[0], samples.stamps - samples.stamps[0])
    assert _cat(parts, "raw").dtype == np.int16 and _cat(parts, "stamps_ns").dtype == np.int64


@needs_pty
def test_faults_never_deliver_a_corrupt_sample_and_link_reconnects():
    """Garbage, bit errors, dropped bytes and one unplug/replug at 1000 Hz, real time."""
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink
    from imu_array_ros.model.layouts import grid_array32
    from imu_array_ros.simulation.simulator import simulate_twist

    desc = grid_array32()
    samples, _ = simulate_twist(desc.with_imus(desc.imus[:K]), 3.0, 1000.0, np.random.default_rng(7))
    with FakeArrayDevice.from_imu_samples(samples, garbage_every=97, bit_error_rate=1e-5, drop_byte_rate=5e-5,
                                          unplug_at=1.0, unplug_duration=0.3, seed=3) as dev:
        link = SerialArrayLink(dev.port, K, rate_divider=1, ack_timeout=0.5, backoff=(0.05, 0.2))
        parts = _collect(link, dev)
        link.close()
    rec, st = dev.record, link.stats
    assert rec.unplugs == 1 and len(rec.streams) == 2
    assert (st.connects, st.reconnects, st.start_retries) == (2, 1, 0)
    assert rec.corrupted_packets >= 20 and rec.garbage_bytes > 0  # the faults did happen

    counter, device_ns, raw = _cat(parts, "counter").astype(np.int64), _cat(parts, "device_ns"), _cat(parts, "raw")
    stream = (counter >= int(rec.streams[1].counter[0])).astype(int)  # counters continue after the replug
    assert (np.diff(stream) >= 0).all() and stream[-1] == 1  # data resumed after the replug
    expected_gaps = 0
    for j in range(2):
        p = rec.sent_packets(j, intact=True)
        where = {int(c): i for i, c in enumerate(p.counter)}
        sel = np.flatnonzero(stream == j)
        assert [c for c in counter[sel] if int(c) not in where] == []  # only packets sent intact come out
        idx = np.array([where[int(c)] for c in counter[sel]])
        np.testing.assert_array_equal(raw[sel], p.raw[idx])  # ... with their exact counts and times
        np.testing.assert_array_equal(device_ns[sel], ticks_to_ns(p.ticks[idx]))
        expected_gaps += int(counter[sel][-1] - counter[sel][0] + 1 - len(sel))
    # nothing intact is lost except what was in flight at the unplug (at most 0.1 s here); every loss within
    # a connection shows as a counter gap
    assert len(counter) >= sum(len(rec.sent_packets(j)) for j in range(2)) - 100
    assert st.counter_gaps == expected_gaps >= rec.corrupted_packets - 100
    assert 0 < st.bad_checksums <= rec.corrupted_packets + rec.garbage_bytes
    assert st.garbage_bytes >= rec.garbage_bytes


@needs_pty
def test_start_resent_without_ack_and_stop_on_close():
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    counter, ticks, raw = _packets(300, dt=64_000)  # 1000 Hz
    with FakeArrayDevice.from_samples(raw, ticks, counter, speed=2, ignore_commands=1) as dev:
        link = SerialArrayLink(dev.port, K, rate_divider=1, ack_timeout=0.2)
        parts = _collect(link, dev)
        link.close()
        deadline = time.monotonic() + 2
        while len(dev.record.commands) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        # a command with a bad checksum is ignored (no ack) and counted
        with serial.serial_for_url(dev.port, timeout=0) as port:
            port.write(start_command(0xFF, 5)[:-1] + b"\x00")
            while dev.record.bad_commands == 0 and time.monotonic() < deadline + 1:
                time.sleep(0.01)
        rec = dev.record
    start = Command(0x28, bytes.fromhex("000000FF01"))
    assert rec.commands == [start, start, Command(0x22)]  # ignored start, re-sent start, stop on close
    assert (rec.ignored_commands, rec.acks_sent, rec.bad_commands) == (1, 2, 1)
    st = link.stats
    assert (st.start_retries, st.acks, st.connects, st.state) == (1, 1, 1, "disconnected")
    np.testing.assert_array_equal(_cat(parts, "raw"), raw)


@needs_pty
def test_device_streams_selected_imus_at_requested_rate():
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    counter, ticks, raw = _packets(320, k=4, dt=64_000)  # 1000 Hz source, IMUs on mask bits 3, 5, 9, 12
    with FakeArrayDevice.from_samples(raw, ticks, counter, imu_bits=[3, 5, 9, 12], speed=0) as dev:
        link = SerialArrayLink(dev.port, 2, imu_mask=(1 << 12) | (1 << 5), rate_divider=5)  # 62.5 Hz
        parts = _collect(link, dev)
        link.close()
    np.testing.assert_array_equal(_cat(parts, "raw"), raw[::16][:, [1, 3]])
    np.testing.assert_array_equal(_cat(parts, "counter"), np.arange(20))  # renumbered consecutively
    np.testing.assert_array_equal(np.diff(_cat(parts, "device_ns")), 16_000_000)
    assert link.stats.counter_gaps == 0


@needs_pty
def test_loop_continues_counters_and_ticks():
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    counter, ticks, raw = _packets(50, t0=(1 << 32) - 20 * 1_024_000)  # 62.5 Hz, ticks wrap within the source
    with FakeArrayDevice.from_samples(raw, ticks, counter, speed=0, loop=True) as dev:
        link = SerialArrayLink(dev.port, K)
        got = []
        deadline = time.monotonic() + 10
        while sum(map(len, got)) < 160 and time.monotonic() < deadline:
            got.append(link.poll())
            time.sleep(0.002)
        link.close()
    c, d, r = _cat(got, "counter")[:160], _cat(got, "device_ns")[:160], _cat(got, "raw")[:160]
    np.testing.assert_array_equal(c, np.arange(160))
    np.testing.assert_array_equal(np.diff(d), 16_000_000)
    np.testing.assert_array_equal(r, np.concatenate([raw] * 4)[:160])
    assert not dev.finished and len(dev.record.streams) >= 4


# --------------------------------------------------------------------------- link against a hand-driven pty


class _Pty:
    """A pseudo-terminal the test drives as the device."""

    def __init__(self):
        import tty

        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)

    def read(self, timeout=2.0) -> bytes:
        import select

        r, _, _ = select.select([self.master], [], [], timeout)
        return os.read(self.master, 4096) if r else b""

    def close(self):
        os.close(self.master)
        os.close(self.slave)


@needs_pty
def test_link_discards_data_before_the_ack_and_restarts_on_device_restart():
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    pty = _Pty()
    try:
        host = [10**18]
        link = SerialArrayLink(pty.path, 3, ack_timeout=0.15, now=lambda: host[0])
        assert len(link.poll()) == 0 and link.state == "waiting_ack"
        assert pty.read() == start_command(0b111, 5)
        old = encode_packets(*_packets(5, 3, seed=1, c0=40))
        new_c, new_t, new_raw = _packets(12, 3, seed=2, c0=100, t0=(1 << 32) - 3 * 1_024_000)
        new = encode_packets(new_c, new_t, new_raw)
        os.write(pty.master, old + START_ACK[:2])  # stale packets, then an ack split over two reads
        time.sleep(0.05)
        assert len(link.poll()) == 0 and link.state == "waiting_ack"
        os.write(pty.master, START_ACK[2:] + new[: 6 * 22])
        time.sleep(0.05)
        host[0] += 10**8
        a = link.poll()
        assert link.state == "streaming" and link.stats.packets_before_ack == 5
        # after a restart the counter steps back: the tick unwrapper and the clock start again
        restart_c, restart_t, restart_raw = _packets(4, 3, seed=3, c0=0, t0=500)
        os.write(pty.master, new[6 * 22 :] + encode_packets(restart_c, restart_t, restart_raw))
        time.sleep(0.05)
        host[0] += 10**8
        b = link.poll()
        np.testing.assert_array_equal(np.concatenate([a.raw, b.raw]), np.concatenate([new_raw, restart_raw]))
        dev_ns = np.concatenate([a.device_ns, b.device_ns])
        assert (np.diff(dev_ns[:12]) == 16_000_000).all() and dev_ns[11] > ticks_to_ns(1 << 32)  # tick wrap unwrapped
        assert dev_ns[12] < 10_000 and link.stats.device_restarts == 1
        assert (np.diff(a.stamps_ns) > 0).all() and b.stamps_ns[-1] <= host[0]
        st = link.stats
        assert (st.acks, st.packets, st.start_retries, st.counter_backsteps) == (1, 21, 0, 1)
        link.close()
        assert pty.read() == STOP_COMMAND
    finally:
        pty.close()


def test_link_without_port_retries_with_backoff(tmp_path):
    from imu_array_ros.io.openshoe.serial_link import SerialArrayLink

    with pytest.raises(ValueError, match="selects 3 IMUs, but n_imus is 8"):
        SerialArrayLink("loop://", 8, imu_mask=0b111)
    with pytest.raises(ValueError, match="rate_divider"):
        SerialArrayLink("loop://", 8, rate_divider=9)
    link = SerialArrayLink(str(tmp_path / "nothing"), K, backoff=(0.05, 0.1))
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.4:
        assert len(link.poll()) == 0
        time.sleep(0.005)
    st = link.stats
    assert (st.state, st.connects) == ("disconnected", 0) and "nothing" in st.last_error
    link.close()


@needs_pty
def test_fake_device_link_path_rules(tmp_path):
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice

    counter, ticks, raw = _packets(3)
    user_file = tmp_path / "port"
    user_file.write_text("mine")
    with pytest.raises(OutputError, match="exists and is not a symlink"):
        FakeArrayDevice.from_samples(raw, ticks, link=user_file)
    assert user_file.read_text() == "mine"
    other = tmp_path / "other"
    other.symlink_to(user_file)
    with pytest.raises(OutputError, match="not to a pseudo-terminal"):
        FakeArrayDevice.from_samples(raw, ticks, link=other)
    stale = tmp_path / "stale"
    stale.symlink_to("/dev/pts/999")  # left behind by a killed run: replaced
    with FakeArrayDevice.from_samples(raw, ticks, link=stale) as dev:
        assert os.readlink(stale) == dev.tty
    assert not os.path.lexists(stale) and user_file.read_text() == "mine"
