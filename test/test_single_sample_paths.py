"""The live node's per-sample paths (issue 24, latency) give what the batched code gives.

The fusion node fuses a sample as soon as its last message arrives, so it decodes 32 messages, assembles one
sample, fuses it and encodes two messages at a time.  Each step has a path for that case (back-to-back
payloads of one length; one message per IMU; one sample in Python floats; a cached message template); these
tests hold each to the general code on the same input, including the inputs the paths must reject.
"""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.fusion.gauss_newton import gauss_newton, gauss_newton_one
from imu_array_ros.io.messages import decode_raw_imu
from imu_array_ros.io.rosbag.cdr_columns import decode_imu, encode_imu
from imu_array_ros.io.sync import SampleAssembler


def _payloads(n, frame_id="imu_00", seed=0):
    rng = np.random.default_rng(seed)
    stamps = 10**9 + np.arange(n, dtype=np.int64) * 5_000_000
    out = encode_imu(stamps, frame_id, angular_velocity=rng.normal(size=(n, 3)),
                     linear_acceleration=rng.normal(size=(n, 3)), angular_velocity_covariance=rng.normal(size=9))
    return [bytes(r) for r in out]


def _spoil(good, frame_id):
    """Payloads of the good ones' length that the decoder must reject, one way each."""
    bad = []
    nul = 16 + len(frame_id.encode())
    for i, (at, value) in enumerate([(0, 1), (1, 7), (12, 0), (12, 200), (8, None), (nul, ord("x"))]):
        b = bytearray(good[i])
        if value is None:
            b[8:12] = (1_000_000_000).to_bytes(4, "little")  # nanosec out of range
        else:
            b[at] = value  # encapsulation; XCDR2; frame_id length (none / past the end); the NUL
        bad.append(bytes(b))
    return bad


@pytest.mark.parametrize("frame_id", ["", "a", "imu_00", "abcdefgh"])
def test_back_to_back_payloads_decode_as_with_gaps(frame_id):
    good = _payloads(8, frame_id, seed=len(frame_id))
    payloads = good[:2] + _spoil(good, frame_id) + good[2:]
    joined = np.frombuffer(b"".join(payloads), dtype=np.uint8)
    length = len(payloads[0])
    fast = decode_imu(joined, np.arange(len(payloads)) * length, [length] * len(payloads))
    gap = np.concatenate([np.concatenate([np.full(3, 0xAB, np.uint8), np.frombuffer(p, np.uint8)]) for p in payloads])
    slow = decode_imu(gap, 3 + np.arange(len(payloads)) * (length + 3), [length] * len(payloads))
    assert slow.valid.tolist() == [True] * 2 + [False] * 6 + [True] * 6
    for a, b in ((fast.valid, slow.valid), (fast.encapsulation_ok, slow.encapsulation_ok), (fast.stamps, slow.stamps)):
        np.testing.assert_array_equal(a, b)
    for name in slow.fields:
        np.testing.assert_array_equal(fast[name], slow[name])


def test_frame_check_compares_length_bytes_and_terminator():
    """A frame_id that begins with the expected one (same padded length) is not the expected one."""
    names = ["imu_1", "imu_2"]
    ok = _payloads(1, "imu_1")[0]
    longer = _payloads(1, "imu_1a")[0]  # n 7 instead of 6: the same payload length
    other = _payloads(1, "imu_2")[0]
    assert len(ok) == len(longer)
    for payloads in ([ok, longer, other], [ok, longer, other, ok[:40]]):  # one length (back to back); mixed
        batch = decode_raw_imu(payloads, np.zeros(len(payloads), dtype=int), names)
        assert batch.frame_ok[:3].tolist() == [True, False, False]
    batch = decode_raw_imu([other, ok], [1, 1], names)
    assert batch.frame_ok.tolist() == [True, False]
    empty = decode_raw_imu([_payloads(1, "")[0], ok], [0, 0], [""])
    assert empty.frame_ok.tolist() == [True, False]


def test_one_message_per_imu_is_checked_as_a_batch():
    """The assembler's one-message-per-IMU path flags duplicates, backwards and late stamps as the general one."""
    rng = np.random.default_rng(3)
    fast, slow = SampleAssembler(4, timeout_ns=10**9), SampleAssembler(4, timeout_ns=10**9)
    for t in range(60):
        idx = rng.permutation(4)[: rng.integers(1, 5)]
        st = 1000 + 10 * (t + rng.integers(-3, 2, len(idx)))
        a = rng.normal(size=(len(idx), 3))
        got = fast.add(idx, st, a, a, t)
        # the same messages through the general path: one extra message of an IMU (a duplicate of its last)
        extra = np.r_[idx, idx[:1]], np.r_[st, st[:1]]
        want = slow.add(*extra, np.r_[a, a[:1]], np.r_[a, a[:1]], t)
        np.testing.assert_array_equal(got, want[:-1])
        assert not want[-1]
        if t % 7 == 0:
            f, s = fast.pop(t + 10**9, flush=True), slow.pop(t + 10**9, flush=True)
            np.testing.assert_array_equal(f.stamps, s.stamps)
            np.testing.assert_array_equal(f.accel, s.accel)
    assert fast.stats.backwards + fast.stats.late > 0 and fast.stats.duplicate > 0


@pytest.mark.parametrize("seed", range(6))
def test_one_sample_gauss_newton_equals_the_batch(seed):
    """Random concentrated costs (positive definite and not, far starts needing step halving, iteration caps):
    the Python-float iteration of one sample gives the batched one's estimate, iterations, convergence."""
    rng = np.random.default_rng(seed)
    for trial in range(40):
        a = rng.normal(size=(6, 6))
        ft = a @ a.T * (10 ** rng.uniform(-2, 2))
        t = rng.normal(size=(6, 9)) * 0.1
        tf = np.concatenate([t, ft], axis=1)
        b = rng.normal(size=(3, 3))
        wg = b @ b.T if trial % 9 else np.zeros((3, 3))  # an indefinite/singular start now and then
        omega0 = rng.normal(size=(1, 3)) * 10 ** rng.uniform(-1, 1)
        beta_t, g = rng.normal(size=(1, 6)) * 5, rng.normal(size=(1, 3))
        kw = dict(max_iterations=int(rng.choice([1, 3, 30])), tolerance=1e-10)
        w1, i1, c1, h1 = gauss_newton_one(omega0, tf, beta_t, wg, g, **kw)
        w2, i2, c2, h2 = gauss_newton(omega0, tf, beta_t, wg, g, **kw)
        assert (i1.tolist(), c1.tolist()) == (i2.tolist(), c2.tolist())
        np.testing.assert_allclose(w1, w2, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(h1, h2, rtol=1e-9, atol=1e-9 * np.abs(h2).max())
