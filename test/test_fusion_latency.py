"""Issue 24 item 4: the fusion is event-driven -- a complete array sample is fused as soon as its last
message arrives, not on the next timer tick (benchmarks/bench_fusion_latency.py measures the latency)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from conftest import REPO
from imu_array_ros.fusion.live import LiveFusion
from imu_array_ros.io.live_queue import CompletionQueue
from imu_array_ros.io.messages import decode_fused, raw_imu_payloads
from imu_array_ros.model.description import load_description
from imu_array_ros.simulation.simulator import simulate_twist

PLANAR4 = REPO / "config" / "planar4.yaml"


def _payloads(desc, n, rng):
    """Raw payloads [sample][imu] of ``n`` simulated samples of ``desc`` (stamps 5 ms apart, random start)."""
    samples, _ = simulate_twist(desc, n / 200.0, 200.0, rng, start_ns=int(rng.integers(10**18, 2 * 10**18)))
    per_imu = raw_imu_payloads(samples, desc)
    out = [[None] * len(per_imu) for _ in range(len(samples))]
    for k, (rows, pl) in enumerate(per_imu):
        for r, p in zip(rows, pl):
            out[r][k] = bytes(p)
    return samples, out


def test_completion_is_the_message_that_completes_its_sample():
    rng = np.random.default_rng()
    for _ in range(20):
        k = int(rng.integers(1, 70))
        calls = []
        q = CompletionQueue(k, lambda key: calls.append(len(q)))
        stamps = np.sort(rng.choice(10**12, size=4, replace=False)) + 10**18
        msgs = [(s, i) for s in stamps for i in range(k)]
        rng.shuffle(msgs)  # stamps interleaved, IMUs in any order
        dups = [msgs[int(j)] for j in rng.integers(len(msgs), size=3)]
        msgs = msgs[:len(msgs) // 2] + dups + msgs[len(msgs) // 2:]
        for s, i in msgs:
            q.receiver(i)(b"\x00\x01\x00\x00" + int(s).to_bytes(8, "little") + b"rest")
        # the queue length when each stamp got its last new IMU (a duplicate after that completes nothing)
        first = {}
        for n, m in enumerate(msgs, 1):
            first.setdefault(m, n)
        expected = sorted(max(n for m, n in first.items() if m[0] == s) for s in stamps)
        assert calls == expected, (k, calls, expected)
        assert q.completed == 4 and len(q) == len(msgs)
        assert len(q.drain()[0]) == len(msgs) and len(q) == 0


def test_own_stamps_complete_on_every_reference_message():
    calls = []
    q = CompletionQueue(3, lambda key: calls.append(1), own_stamps=True, reference=1)
    for i in (0, 2, 0, 1, 2, 1):
        q.receiver(i)(b"\x00\x01\x00\x00" + bytes(8))
    assert len(calls) == 2


def test_a_completed_sample_fuses_at_once_without_time_passing():
    """ROS-free: the completing message's callback, then drain + add + step at the same clock reading (no sync
    timeout elapsed) hands out exactly the completed samples, fused; one missing message holds its sample."""
    rng = np.random.default_rng()
    desc = load_description(PLANAR4)
    samples, pl = _payloads(desc, 6, rng)
    live = LiveFusion(desc, sync_timeout_s=10.0)
    now = int(rng.integers(10**18, 2 * 10**18))
    done = []
    q = CompletionQueue(len(desc.names), lambda key: done.append(True))
    skip = (3, int(rng.integers(len(desc.names))))  # sample 3 misses one IMU's message
    for r in range(len(pl)):
        for k in rng.permutation(len(desc.names)):
            if (r, k) != skip:
                q.receiver(int(k))(pl[r][k])
        if done:
            done.clear()
            payloads, index = q.drain()
            live.add(payloads, index, now)
            out = live.step(now)
            got = np.concatenate([b.fused.stamps for b in out]) if out else np.zeros(0, np.int64)
            # sample r fused now; sample 3 (incomplete) goes out with sample 4, as its IMU already sent a later one
            want = samples.stamps[[3, 4]] if r == 4 else samples.stamps[[r]]
            np.testing.assert_array_equal(got, want)
            fused = decode_fused([p.tobytes() for b in out for p in b.imu_payloads],
                                 [p.tobytes() for b in out for p in b.accel_payloads])
            np.testing.assert_array_equal(fused.stamps, want)
            assert np.isfinite(fused.omega).all()
        else:
            assert r == 3, r  # only the incomplete sample completes nothing


@pytest.fixture
def fusion_node(dds):
    import rclpy
    from rclpy.experimental import EventsExecutor

    from imu_array_ros.nodes.fusion_node import FusionNode

    # a 1 s timer and a 10 s sync timeout: within the test's spin, only an event can fuse
    rclpy.init(args=["--ros-args", "-p", f"array_config:={PLANAR4}", "-p", "period:=1.0",
                     "-p", "sync_timeout:=10.0", "-p", "bias_tracking:=false"])
    try:
        node = FusionNode()
    except BaseException:
        rclpy.try_shutdown()
        raise
    executor = EventsExecutor()
    executor.add_node(node)
    try:
        yield node, executor
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def test_node_fuses_a_complete_sample_before_any_timer(fusion_node):
    node, executor = fusion_node
    published = []
    node.pub_imu.publish = lambda data: published.append((time.monotonic(), bytes(data)))
    node.pub_accel.publish = lambda data: None
    rng = np.random.default_rng()
    desc = load_description(PLANAR4)
    _, pl = _payloads(desc, 3, rng)
    receivers = [node.raw.receiver(k) for k in range(len(desc.names))]
    executor.spin_once(timeout_sec=0.01)
    for r in range(len(pl)):
        # stamped as they are fed (as a restamping driver does; the pace of this test is not the recording's)
        t = time.time_ns()
        stamp = (t // 10**9).to_bytes(4, "little") + (t % 10**9).to_bytes(4, "little")
        pl[r] = [p[:4] + stamp + p[12:] for p in pl[r]]
        order = rng.permutation(len(desc.names))
        for k in order[:-1]:
            receivers[k](pl[r][k])
        executor.spin_once(timeout_sec=0.01)
        assert len(published) == r, "fused before the sample was complete"
        t0 = time.monotonic()
        receivers[order[-1]](pl[r][order[-1]])
        while len(published) <= r and time.monotonic() - t0 < 0.3:
            executor.spin_once(timeout_sec=0.01)
        assert len(published) == r + 1, "a complete sample was not fused within 0.3 s (the timer's period is 1 s)"
        assert published[-1][1][4:12] == stamp


def test_backlog_gate_batches_only_samples_already_queued():
    from imu_array_ros.io.live_queue import BacklogGate

    rng = np.random.default_rng()
    gate = BacklogGate(max_wait=8)
    offset = int(rng.integers(-10**18, 10**18))  # any clock offset (recorded stamps): only the changes count
    period = 5_000_000
    transport = int(rng.integers(500_000, 3_000_000))

    def complete(i, late):
        return gate.complete(offset + period * i + transport + int(rng.integers(0, 1_000_000)) + late, period * i)

    assert all(complete(i, 0) for i in range(50))  # on time, with jitter below one spacing: every sample at once
    # a 4-sample backlog: samples 50..54 stamped on time, the node gets to them 20 ms late, then back to back
    got = [complete(50 + j, 20_000_000 - j * 4_500_000) for j in range(5)]
    assert got.count(False) >= 2 and got[-1], got  # waits only for samples already stamped, then fuses them
    assert all(complete(60 + i, 0) for i in range(10))  # caught up: at once again
    # far behind (a long stall): batches, never above 8
    got = [complete(100 + j, 200_000_000 - j * 4_800_000) for j in range(40)]
    runs = np.diff(np.flatnonzero([True] + got))
    assert runs.max() <= 8 and runs.mean() > 3, got
    # on time, but a fusion call takes most of a spacing: left to the timer's batches (at most 8 wait)
    gate.fused()  # (a sweep fused those still waiting)
    got = [gate.complete(offset + period * i + transport, period * i, cost_ns=0.8 * period) for i in range(200, 216)]
    assert got == ([False] * 7 + [True]) * 2, got
    assert gate.complete(offset + period * 216 + transport, period * 216, cost_ns=0.2 * period)
