"""Columnar CDR codec vs rosbags' reference (de)serializer, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from imu_array_ros.io.rosbag.cdr_columns import (
    ACCEL_LAYOUT,
    IMU_LAYOUT,
    decode_accel_with_covariance_stamped,
    decode_imu,
    encode_accel_with_covariance_stamped,
    encode_imu,
    join_stamps,
    split_stamps,
)

rosbags_typesys = pytest.importorskip("rosbags.typesys")

IMU = "sensor_msgs/msg/Imu"
ACCEL = "geometry_msgs/msg/AccelWithCovarianceStamped"
# frame_id lengths 0..9 and 13 exercise every padding case of align8(12 + n); one non-ASCII
FRAME_IDS = ["", "a", "ab", "abc", "imu_0", "imu_00", "imu_007", "abcdefgh", "abcdefghi", "x" * 13, "bär"]


@pytest.fixture(scope="module")
def ts():
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)


def _imu_msg(ts, stamp, frame_id, rng):
    t = ts.types
    sec, nsec = divmod(int(stamp), 1_000_000_000)
    vec = lambda v: t["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2])  # noqa: E731
    q = rng.normal(size=4)
    return t[IMU](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id),
        orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        orientation_covariance=rng.normal(size=9),
        angular_velocity=vec(rng.normal(size=3)),
        angular_velocity_covariance=rng.normal(size=9),
        linear_acceleration=vec(rng.normal(size=3)),
        linear_acceleration_covariance=rng.normal(size=9),
    )


def _imu_fields(m):
    q, w, a = m.orientation, m.angular_velocity, m.linear_acceleration
    return {
        "orientation": [q.x, q.y, q.z, q.w],
        "orientation_covariance": list(m.orientation_covariance),
        "angular_velocity": [w.x, w.y, w.z],
        "angular_velocity_covariance": list(m.angular_velocity_covariance),
        "linear_acceleration": [a.x, a.y, a.z],
        "linear_acceleration_covariance": list(m.linear_acceleration_covariance),
    }


def _concat(payloads, rng, gap_max=9):
    """Payloads in one buffer with random gaps (as in an MCAP chunk); (buffer, offsets, lengths)."""
    parts, offs, lens, pos = [], [], [], 0
    for p in payloads:
        gap = int(rng.integers(0, gap_max))
        parts.append(rng.integers(0, 256, size=gap, dtype=np.uint8))
        pos += gap
        offs.append(pos)
        lens.append(len(p))
        parts.append(np.frombuffer(bytes(p), dtype=np.uint8))
        pos += len(p)
    return np.concatenate(parts), np.array(offs), np.array(lens)


@pytest.mark.parametrize("frame_id", FRAME_IDS)
def test_imu_encode_is_byte_identical_to_rosbags(ts, frame_id):
    rng = np.random.default_rng(1)
    stamps = np.array([0, 1, 1_700_000_000_123_456_789, 2**31 * 1_000_000_000 - 1], dtype=np.int64)
    msgs = [_imu_msg(ts, s, frame_id, rng) for s in stamps]
    cols = {k: np.array([_imu_fields(m)[k] for m in msgs]) for k in IMU_LAYOUT.fields}
    ours = encode_imu(stamps, frame_id, **cols)
    assert ours.shape == (len(stamps), IMU_LAYOUT.payload_length(len(frame_id.encode()) + 1))
    for row, m in zip(ours, msgs):
        assert row.tobytes() == bytes(ts.serialize_cdr(m, IMU))


@pytest.mark.parametrize("frame_id", FRAME_IDS)
def test_accel_encode_is_byte_identical_to_rosbags(ts, frame_id):
    rng = np.random.default_rng(2)
    t = ts.types
    stamps = np.array([5, 3_000_000_001], dtype=np.int64)
    lin, ang, cov = rng.normal(size=(2, 3)), rng.normal(size=(2, 3)), rng.normal(size=(2, 36))
    ours = encode_accel_with_covariance_stamped(stamps, frame_id, linear=lin, angular=ang, covariance=cov)
    for i, s in enumerate(stamps):
        sec, nsec = divmod(int(s), 1_000_000_000)
        m = t[ACCEL](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id),
            accel=t["geometry_msgs/msg/AccelWithCovariance"](
                accel=t["geometry_msgs/msg/Accel"](
                    linear=t["geometry_msgs/msg/Vector3"](x=lin[i, 0], y=lin[i, 1], z=lin[i, 2]),
                    angular=t["geometry_msgs/msg/Vector3"](x=ang[i, 0], y=ang[i, 1], z=ang[i, 2]),
                ),
                covariance=cov[i],
            ),
        )
        assert ours[i].tobytes() == bytes(ts.serialize_cdr(m, ACCEL))
        back = decode_accel_with_covariance_stamped(ours[i], [0], [ours.shape[1]])
        assert back.valid.all() and back.stamps[0] == s
        np.testing.assert_array_equal(back["linear"][0], lin[i])
        np.testing.assert_array_equal(back["angular"][0], ang[i])
        np.testing.assert_array_equal(back["covariance"][0], cov[i])


def test_imu_decode_mixed_frame_ids_bit_exact(ts):
    """Messages of different topics (frame_id lengths) interleaved in one buffer decode in one call."""
    rng = np.random.default_rng(3)
    msgs, stamps = [], []
    for i in range(60):
        stamp = int(rng.integers(0, 2**31 * 1_000_000_000))
        stamps.append(stamp)
        msgs.append(_imu_msg(ts, stamp, FRAME_IDS[i % len(FRAME_IDS)], rng))
    # special values travel unchanged
    msgs[7].angular_velocity.y = np.nan
    msgs[8].linear_acceleration.z = -np.inf
    msgs[9].orientation_covariance[0] = -1.0
    buf, off, ln = _concat([ts.serialize_cdr(m, IMU) for m in msgs], rng)
    dec = decode_imu(buf, off, ln)
    assert dec.valid.all() and dec.encapsulation_ok.all()
    np.testing.assert_array_equal(dec.stamps, stamps)
    for name in IMU_LAYOUT.fields:
        want = np.array([_imu_fields(m)[name] for m in msgs])
        assert np.array_equal(dec[name], want, equal_nan=True), name
        assert dec[name].view(np.uint64).tolist() == want.view(np.uint64).tolist(), name  # bits, not just values
    only = decode_imu(buf, off, ln, fields=("angular_velocity",))
    assert list(only.fields) == ["angular_velocity"]


def test_imu_decode_rejects_what_it_cannot_read(ts):
    rng = np.random.default_rng(4)
    good = [bytes(ts.serialize_cdr(_imu_msg(ts, 10**9 * (i + 1), "imu_00", rng), IMU)) for i in range(8)]
    bad = list(good)
    bad[1] = bytes(ts.serialize_cdr(ts.deserialize_cdr(good[1], IMU), IMU, little_endian=False))  # big endian
    bad[2] = good[2][:-8]  # truncated
    bad[3] = good[3] + b"\0" * 8  # too long
    b = bytearray(good[4])
    b[12] = 6  # frame_id length field says 6 instead of 7: layout shifts, NUL check fails
    bad[4] = bytes(b)
    b = bytearray(good[5])
    b[8:12] = (1_000_000_000).to_bytes(4, "little")  # nanosec out of range
    bad[5] = bytes(b)
    b = bytearray(good[6])
    b[1] = 0x07  # XCDR2 little endian: different alignment rules
    bad[6] = bytes(b)
    buf, off, ln = _concat(bad, rng)
    dec = decode_imu(buf, off, ln)
    assert dec.valid.tolist() == [True, False, False, False, False, False, False, True]
    assert dec.encapsulation_ok.tolist() == [True, False, True, True, True, True, False, True]
    assert np.isnan(dec["angular_velocity"][~dec.valid]).all()
    for i in (0, 7):
        m = ts.deserialize_cdr(good[i], IMU)
        np.testing.assert_array_equal(dec["linear_acceleration"][i], _imu_fields(m)["linear_acceleration"])
    # a buffer too short for any message, and an empty selection
    tiny = decode_imu(np.zeros(10, np.uint8), [0], [10])
    assert not tiny.valid.any()
    empty = decode_imu(buf, [], [])
    assert empty.stamps.shape == (0,) and empty["orientation"].shape == (0, 4)
    with pytest.raises(ValueError):
        decode_imu(buf, [len(buf) - 4], [324])


def test_encode_broadcasting_and_errors():
    st = np.array([1, 2, 3], dtype=np.int64)
    a = encode_imu(st, "f", angular_velocity=[1.0, 2.0, 3.0], linear_acceleration=np.zeros((3, 3)),
                   angular_velocity_covariance=np.eye(3), linear_acceleration_covariance=np.tile(np.eye(3), (3, 1, 1)))
    dec = decode_imu(a.reshape(-1), np.arange(3) * a.shape[1], [a.shape[1]] * 3)
    np.testing.assert_array_equal(dec["angular_velocity"], [[1, 2, 3]] * 3)
    np.testing.assert_array_equal(dec["angular_velocity_covariance"], [np.eye(3).ravel()] * 3)
    np.testing.assert_array_equal(dec["linear_acceleration_covariance"], [np.eye(3).ravel()] * 3)
    np.testing.assert_array_equal(dec["orientation"], np.zeros((3, 4)))
    with pytest.raises(ValueError):
        encode_imu(st, "f", angular_velocity=np.zeros((2, 3)), linear_acceleration=np.zeros(3))
    with pytest.raises(ValueError):
        encode_imu(st, "a\0b", angular_velocity=np.zeros(3), linear_acceleration=np.zeros(3))
    with pytest.raises(ValueError):
        encode_imu([2**31 * 10**9], "f", angular_velocity=np.zeros(3), linear_acceleration=np.zeros(3))
    assert ACCEL_LAYOUT.payload_length(7) == 4 + 24 + 336


def test_stamps_split_join_roundtrip():
    st = np.array([-1, 0, 999_999_999, 1_000_000_000, -(2**31) * 10**9, 2**31 * 10**9 - 1], dtype=np.int64)
    sec, nsec = split_stamps(st)
    assert (nsec < 1_000_000_000).all()
    np.testing.assert_array_equal(join_stamps(sec, nsec), st)
