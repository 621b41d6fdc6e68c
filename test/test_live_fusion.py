"""The ROS-free core of the live nodes: message conversion, the stamp assembler and
LiveFusion -- checked against rclpy's own serializer and the offline command."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ARRAY32, REPO
from imu_array_ros.fusion.live import LiveFusion, build_fusion
from imu_array_ros.fusion.stream import fuse_chunked
from imu_array_ros.io.messages import decode_fused, decode_raw_imu, fused_payloads, raw_imu_payloads
from imu_array_ros.io.rosbag.recording import read_imu_recording
from imu_array_ros.io.sync import SampleAssembler
from imu_array_ros.model.description import load_description
from imu_array_ros.errors import ConfigError

BAG = REPO / "bags" / "twist32_sample"


@pytest.fixture(scope="module")
def recording():
    desc = load_description(ARRAY32)
    samples, _ = read_imu_recording(BAG, desc)
    return desc, samples


def _interleaved(samples, desc, frame_prefix=""):
    """Every raw payload in the order a subscriber would see them: by stamp, IMUs shuffled."""
    per_imu = raw_imu_payloads(samples, desc, frame_prefix)
    rows = np.concatenate([r for r, _ in per_imu])
    imu = np.concatenate([np.full(len(r), k) for k, (r, _) in enumerate(per_imu)])
    payloads = [bytes(p) for _, pl in per_imu for p in pl]
    order = np.lexsort((np.random.default_rng(3).random(len(rows)), rows))
    return [payloads[i] for i in order], imu[order], rows[order]


# --------------------------------------------------------------------------- messages


def _unpadded(cdr: bytes) -> bytes:
    """rmw leaves the alignment bytes after header.frame_id uninitialised; ours are zero."""
    n = int.from_bytes(cdr[12:16], "little")
    end = 4 + (12 + n + 7) // 8 * 8
    return cdr[: 16 + n] + bytes(end - 16 - n) + cdr[end:]


def test_payloads_are_what_rclpy_serializes(recording):
    from rclpy.serialization import deserialize_message, serialize_message
    from geometry_msgs.msg import AccelWithCovarianceStamped
    from sensor_msgs.msg import Imu

    desc, samples = recording
    sub = samples.select(slice(0, 5))
    rows, payloads = raw_imu_payloads(sub, desc, "arr/")[7]
    msg = deserialize_message(bytes(payloads[2]), Imu)
    assert msg.header.frame_id == "arr/" + desc.names[7]
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == sub.stamps[rows[2]]
    assert [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z] == list(sub.gyro[rows[2], 7])
    assert msg.linear_acceleration.z == sub.accel[rows[2], 7, 2]
    assert msg.orientation_covariance[0] == -1.0
    assert msg.linear_acceleration_covariance[4] == desc.accelerometer_noise_std ** 2
    assert _unpadded(serialize_message(msg)) == bytes(payloads[2])  # byte for byte what rmw publishes

    fusion = build_fusion(desc)
    fused, _ = fusion.fuse(sub)
    imu, acc = fused_payloads(fused, desc.frame_id)
    a = deserialize_message(bytes(acc[1]), AccelWithCovarianceStamped)
    assert _unpadded(serialize_message(a)) == bytes(acc[1])
    assert a.accel.accel.angular.y == fused.omega_dot[1, 1]
    back = decode_fused([bytes(p) for p in imu], [bytes(p) for p in acc])
    np.testing.assert_array_equal(back.omega, fused.omega)
    np.testing.assert_array_equal(back.omega_dot, fused.omega_dot)
    np.testing.assert_array_equal(back.specific_force, fused.specific_force)
    carried = np.isfinite(back.covariance)
    np.testing.assert_array_equal(back.covariance[carried], fused.covariance[carried])
    assert carried[:, 3:, 3:].all() and carried[:, :3, :3].all()


def test_decode_flags_each_kind_of_bad_message(recording):
    desc, samples = recording
    sub = samples.select(slice(0, 2))
    good = [bytes(p) for p in raw_imu_payloads(sub, desc)[0][1]]
    nan = sub.accel.copy()
    nan[:, 0, 1] = np.nan
    payloads = [
        good[0],                                             # fine
        bytes(raw_imu_payloads(sub, desc, "x")[0][1][0]),    # wrong frame_id (length differs)
        good[0][:16] + b"J" + good[0][17:],                  # wrong frame_id (same length)
        good[0][:40],                                        # truncated
        b"\x00\x00" + good[0][2:],                          # big-endian/unknown encapsulation
        bytes(encode_nan(sub, desc)),                       # NaN reading
    ]
    batch = decode_raw_imu(payloads, np.zeros(len(payloads), dtype=int), desc.names)
    assert list(batch.usable) == [True, False, False, False, False, False]
    assert list(batch.decodable) == [True, True, True, False, False, True]
    assert list(batch.frame_ok[:3]) == [True, False, False] and batch.frame_ok[5]
    assert not batch.finite[5]


def test_decode_checks_every_message_against_its_own_imus_frame(recording):
    """One batch, many IMUs whose names differ in length (imu_1 .. imu_32): a message is frame_ok exactly when
    the frame_id it carries is the one of the IMU whose topic it came from."""
    desc, samples = recording
    sub = samples.select(slice(0, 1))
    per_imu = [bytes(p[1][0]) for p in raw_imu_payloads(sub, desc)]
    rng = np.random.default_rng(5)
    carried = rng.integers(0, len(per_imu), 200)     # the IMU whose message it is
    topic = np.where(rng.random(200) < 0.5, carried, rng.integers(0, len(per_imu), 200))  # the topic it came on
    batch = decode_raw_imu([per_imu[j] for j in carried], topic, desc.names)
    expected = np.array([desc.names[j] == desc.names[k] for j, k in zip(carried, topic)])
    assert 0 < expected.sum() < len(expected)
    np.testing.assert_array_equal(batch.frame_ok, expected)
    assert batch.decodable.all()


def encode_nan(sub, desc):
    from imu_array_ros.io.rosbag.cdr_columns import encode_imu

    return encode_imu(sub.stamps[:1], desc.names[0], angular_velocity=[0, np.nan, 0], linear_acceleration=[0, 0, 9.8])[0]


# --------------------------------------------------------------------------- assembler


def _add(asm, k, stamps, now=0):
    stamps = np.atleast_1d(stamps)
    k = np.broadcast_to(k, stamps.shape)
    vals = np.c_[stamps, stamps, stamps].astype(float)
    return asm.add(k, stamps, vals, -vals, now)


def test_assembler_orders_waits_and_times_out():
    asm = SampleAssembler(3, timeout_ns=100, capacity=10)
    _add(asm, 0, [10, 20, 30])
    _add(asm, 1, [10, 20])
    assert len(asm.pop(0)) == 0  # IMU 2 has delivered nothing: wait
    _add(asm, 2, [10], now=5)
    out = asm.pop(5)
    assert list(out.stamps) == [10]
    np.testing.assert_array_equal(out.gyro[0, :, 0], [-10, -10, -10])
    _add(asm, 2, [30], now=6)  # IMU 2 skipped 20: it is lost, not late -> 20 goes out incomplete
    out = asm.pop(6)
    assert list(out.stamps) == [20]
    assert np.isnan(out.accel[0, 2]).all() and np.isfinite(out.accel[0, :2]).all()
    _add(asm, 0, [40], now=7)  # 30 still waits for IMU 1, silent since t=0
    assert len(asm.pop(99)) == 0
    assert list(asm.pop(100).stamps) == [30]  # IMU 1 silent for the timeout
    assert len(asm.pop(106)) == 0
    assert list(asm.pop(107).stamps) == [40]  # IMU 1 and 2 silent for the timeout since 40 appeared (t=7)
    _add(asm, 0, [50], now=1000)  # after a pause every IMU has been silent long: 50 still waits its timeout
    assert len(asm.pop(1001)) == 0 and list(asm.pop(1100).stamps) == [50]
    s = asm.stats
    assert (s.complete_samples, s.incomplete_samples, s.missing_messages) == (1, 4, 1 + 1 + 2 + 2)


def test_assembler_rejects_duplicates_backwards_and_late():
    asm = SampleAssembler(2, timeout_ns=10**9, capacity=10)
    ok = _add(asm, np.array([0, 0, 0, 0, 1]), np.array([10, 10, 5, 20, 10]))
    assert list(ok) == [True, False, False, True, True]
    assert (asm.stats.duplicate, asm.stats.backwards) == (1, 1)
    assert list(asm.pop(0).stamps) == [10]
    ok = _add(asm, 1, [10, 20])  # 10 again: duplicate of IMU 1's last stamp; 20 fine
    assert list(ok) == [False, True]
    out = asm.pop(0)
    assert list(out.stamps) == [20]
    asm2 = SampleAssembler(2, timeout_ns=0, capacity=10)
    _add(asm2, 0, [10, 20])
    asm2.pop(0)  # both out incomplete (timeout 0)
    assert list(_add(asm2, 1, [15, 25])) == [False, True]  # 15 <= last handed out: late
    assert asm2.stats.late == 1


def test_assembler_capacity_bounds_the_buffer():
    asm = SampleAssembler(2, timeout_ns=10**12, capacity=4)
    _add(asm, 0, np.arange(1, 11))
    out = asm.pop(0)
    assert list(out.stamps) == list(range(1, 7)) and asm.pending == 4
    assert asm.stats.overflow_samples == 6


# --------------------------------------------------------------------------- LiveFusion


def test_live_fusion_equals_the_offline_command(recording):
    desc, samples = recording
    offline, _ = fuse_chunked(build_fusion(desc), samples)
    payloads, imu, rows = _interleaved(samples, desc)
    live = LiveFusion(desc, sync_timeout_s=0.01, max_batch=7)
    rng = np.random.default_rng(5)
    cuts = np.sort(rng.choice(len(payloads), 60, replace=False))
    out = []
    for part in np.split(np.arange(len(payloads)), cuts):  # batches of arbitrary size, arrival order
        live.add([payloads[i] for i in part], imu[part], now_ns=0)
        out += live.step(0)
    out += live.step(0, flush=True)
    imu_p = [bytes(p) for b in out for p in b.imu_payloads]
    acc_p = [bytes(p) for b in out for p in b.accel_payloads]
    back = decode_fused(imu_p, acc_p)
    np.testing.assert_array_equal(back.stamps, offline.stamps)
    # the same numbers up to rounding: batch size changes the order of a few vectorised sums
    for name in ("omega", "omega_dot", "specific_force"):
        np.testing.assert_allclose(getattr(back, name), getattr(offline, name), rtol=1e-12, atol=1e-12)
    carried = np.isfinite(back.covariance)
    np.testing.assert_allclose(back.covariance[carried], offline.covariance[carried], rtol=1e-9, atol=1e-18)
    assert live.assembler.stats.incomplete_samples == 0
    summary = live.summary(0)
    assert 0.5 < summary.nis_ratio < 2.0  # simulated with this very description
    assert summary.counts["fused"] == len(samples)


def test_live_fusion_survives_malformed_input_and_keeps_fusing(recording):
    desc, samples = recording
    sub = samples.select(slice(0, 40))
    offline, _ = build_fusion(desc).fuse(sub)
    payloads, imu, rows = _interleaved(sub, desc)
    live = LiveFusion(desc, sync_timeout_s=0.0)
    bad = [b"garbage", bytes(encode_nan(sub, desc)), bytes(raw_imu_payloads(sub, desc, "wrong/")[0][1][3])]
    live.add(payloads[:300] + bad, np.r_[imu[:300], 0, 0, 0], 0)
    live.add(payloads[:5], imu[:5], 0)  # duplicates
    live.add(payloads[300:], imu[300:], 0)
    fused = [b.fused for b in live.step(1, flush=True)]
    c = live.summary(1).counts
    assert (c["undecodable"], c["non_finite"], c["wrong_frame_id"]) == (1, 1, 1)
    assert c["duplicate"] + c["backwards"] + c["late"] == 5
    got = np.concatenate([f.omega for f in fused])
    np.testing.assert_allclose(got, offline.omega, rtol=1e-12, atol=1e-12)  # no good message lost, no bad one used


def test_reload_swaps_the_description_between_steps(recording, tmp_path):
    from imu_array_ros.model.description import save_description

    desc, samples = recording
    sub = samples.select(slice(0, 10))
    moved = desc.with_imus([imu if k else imu.__class__(**{**imu.__dict__, "position": imu.position + 0.001})
                            for k, imu in enumerate(desc.imus)])
    save_description(moved, tmp_path / "cal.yaml")
    moved = load_description(tmp_path / "cal.yaml")
    live = LiveFusion(desc)
    payloads, imu, rows = _interleaved(sub, desc)
    half = int(np.flatnonzero(rows == 5)[0])
    live.add(payloads[:half], imu[:half], 0)
    first = live.step(0, flush=True)
    live.set_description(moved)
    live.add(payloads[half:], imu[half:], 0)
    second = live.step(0, flush=True)
    want_old, _ = build_fusion(desc).fuse(sub.select(slice(None, 5)))
    want_new, _ = build_fusion(moved).fuse(sub.select(slice(5, None)))
    np.testing.assert_allclose(np.concatenate([b.fused.specific_force for b in first]), want_old.specific_force,
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([b.fused.specific_force for b in second]), want_new.specific_force,
                               rtol=1e-12, atol=1e-12)
    assert not np.array_equal(want_old.specific_force[:1], build_fusion(moved).fuse(
        sub.select(slice(None, 1)))[0].specific_force)
    with pytest.raises(ConfigError, match="differ"):
        live.set_description(desc.with_imus(desc.imus[:4]))
