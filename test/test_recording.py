"""Recording I/O: our MCAP writer/reader against rosbags and the mcap library."""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import pytest
import yaml

from imu_array_ros.io.rosbag import mcap_format, mcap_locate, mcap_reader, mcap_writer
from imu_array_ros.io.rosbag.cdr_columns import encode_imu
from imu_array_ros.model.description import description_from_dict
from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_recording import McapRecording
from imu_array_ros.io.rosbag.mcap_writer import ChannelData, write_recording
from imu_array_ros.io.rosbag.recording import (
    imu_topic,
    read_fused_recording,
    read_imu_recording,
    read_truth,
    write_fused_recording,
    write_imu_recording,
)
from imu_array_ros.model.samples import FusedSamples, ImuSamples, MotionTruth

rosbags_typesys = pytest.importorskip("rosbags.typesys")
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.rosbag2 import Reader as Rosbag2Reader  # noqa: E402
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode  # noqa: E402

IMU = "sensor_msgs/msg/Imu"
ACCEL = "geometry_msgs/msg/AccelWithCovarianceStamped"
# names of different lengths -> frame_id (and payload layout) differs across topics
NAMES = ("a", "imu_01", "left_front_imu", "b2")
T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def ts():
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)


def make_desc(names=NAMES, frame_id="imu_array_link"):
    imus = [
        {"name": n, "position": [0.01 * i, 0.02 * (i % 2), 0.0 if i < 3 else 0.01], "orientation": [1, 0, 0, 0, 1, 0, 0, 0, 1]}
        for i, n in enumerate(names)
    ]
    return description_from_dict(
        {
            "imu_array": {
                "frame_id": frame_id,
                "accelerometer_noise_std": 0.013,
                "gyroscope_noise_std": 0.0017,
                "gyroscope_range": 30.0,
                "accelerometer_range": 100.0,
                "imus": imus,
            }
        }
    )


def make_samples(desc, n=150, seed=7, t0=T0, dt=1_000_000):
    rng = np.random.default_rng(seed)
    k = len(desc.names)
    stamps = t0 + np.arange(n, dtype=np.int64) * dt
    return ImuSamples(stamps, rng.normal(0, 5, size=(n, k, 3)), rng.normal(0, 2, size=(n, k, 3)), desc.names)


def make_truth(samples, seed=8, attitude=True):
    rng = np.random.default_rng(seed)
    n = len(samples)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return MotionTruth(samples.stamps.copy(), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
                       q if attitude else None)


def msgs_by_topic(path, ts):
    """topic -> list of (log time, deserialized message) via rosbags AnyReader."""
    out: dict[str, list] = {}
    with AnyReader([Path(path)], default_typestore=ts) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append((t, reader.deserialize(raw, conn.msgtype)))
    return out


def stamp_ns(msg):
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def vec(v):
    return [v.x, v.y, v.z]


def one_line(err):
    msg = str(err.value)
    assert "\n" not in msg and msg
    return msg


# --------------------------------------------------------------------------- our writer -> rosbags


@pytest.mark.parametrize("target", ["bag", "bag.mcap"])
def test_written_recording_reads_back_bit_exact_in_rosbags(tmp_path, ts, target):
    desc = make_desc()
    s = make_samples(desc)
    s.accel[[3, 4], 2] = np.nan  # IMU 'left_front_imu' missing in samples 3 and 4
    truth = make_truth(s)
    out = tmp_path / target
    write_imu_recording(out, s, desc, truth=truth)

    got = msgs_by_topic(out, ts)
    assert set(got) == {imu_topic(n) for n in NAMES} | {"/imu_array/truth/imu", "/imu_array/truth/accel"}
    gvar, avar = 0.0017**2, 0.013**2
    for k, name in enumerate(NAMES):
        rows = np.flatnonzero(s.present[:, k])
        msgs = got[imu_topic(name)]
        assert len(msgs) == len(rows) == (len(s) - 2 if k == 2 else len(s))
        for (t, m), r in zip(msgs, rows):
            assert m.header.frame_id == name
            assert stamp_ns(m) == s.stamps[r] == t
            assert vec(m.angular_velocity) == s.gyro[r, k].tolist()  # bit for bit
            assert vec(m.linear_acceleration) == s.accel[r, k].tolist()
            assert m.angular_velocity_covariance.tolist() == np.diag([gvar] * 3).ravel().tolist()
            assert m.linear_acceleration_covariance.tolist() == np.diag([avar] * 3).ravel().tolist()
            assert m.orientation_covariance.tolist() == [-1.0] + [0.0] * 8
            assert [m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w] == [0.0] * 4
    for (t, m), r in zip(got["/imu_array/truth/imu"], range(len(s))):
        assert m.header.frame_id == "imu_array_link" and stamp_ns(m) == truth.stamps[r]
        assert vec(m.angular_velocity) == truth.omega[r].tolist()
        assert vec(m.linear_acceleration) == truth.specific_force[r].tolist()
        q = truth.attitude[r]
        assert [m.orientation.w, m.orientation.x, m.orientation.y, m.orientation.z] == q.tolist()
        assert not m.orientation_covariance.any() and not m.angular_velocity_covariance.any()
    for (t, m), r in zip(got["/imu_array/truth/accel"], range(len(s))):
        assert vec(m.accel.accel.linear) == truth.specific_force[r].tolist()
        assert vec(m.accel.accel.angular) == truth.omega_dot[r].tolist()
        assert not m.accel.covariance.any()

    # and our own reader gives the same arrays back, missing IMU -> NaN
    back, stats = read_imu_recording(out, desc)
    np.testing.assert_array_equal(back.stamps, s.stamps)
    np.testing.assert_array_equal(back.accel[s.present], s.accel[s.present])
    np.testing.assert_array_equal(back.gyro, np.where(s.present[..., None], s.gyro, np.nan))
    assert back.names == desc.names
    assert (stats.messages, stats.samples, stats.bad_messages, stats.duplicate_messages, stats.incomplete_samples) == (
        4 * len(s) - 2, len(s), 0, 0, 2)


def test_rosbag2_directory_metadata_and_container(tmp_path, ts):
    desc = make_desc()
    s = make_samples(desc, n=40)
    out = tmp_path / "rec"
    write_imu_recording(out, s, desc)
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "rec_0.mcap"]
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["rec_0.mcap"]
    assert info["message_count"] == 160
    assert info["starting_time"]["nanoseconds_since_epoch"] == s.stamps[0]
    assert info["duration"]["nanoseconds"] == s.stamps[-1] - s.stamps[0]
    assert info["files"] == [{"path": "rec_0.mcap", "starting_time": {"nanoseconds_since_epoch": int(s.stamps[0])},
                              "duration": {"nanoseconds": int(s.stamps[-1] - s.stamps[0])}, "message_count": 160}]
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert set(topics) == {imu_topic(n) for n in NAMES}
    for t in topics.values():
        md = t["topic_metadata"]
        assert t["message_count"] == 40 and md["type"] == IMU and md["serialization_format"] == "cdr"
        assert md["type_description_hash"] == ts.hash_rihs01(IMU)
        assert md["offered_qos_profiles"][0]["reliability"] == "reliable"

    # rosbags' rosbag2 Reader: metadata, QoS and counts
    with Rosbag2Reader(out) as reader:
        assert reader.message_count == 160
        assert {c.topic: c.msgcount for c in reader.connections} == {imu_topic(n): 40 for n in NAMES}
        assert all(c.ext.offered_qos_profiles for c in reader.connections)

    # the mcap library: profile, schemas, encodings, CRCs, summary
    from mcap.reader import make_reader

    with open(out / "rec_0.mcap", "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary.statistics.message_count == 160
        assert {sc.name for sc in summary.schemas.values()} == {IMU}
        schema = next(iter(summary.schemas.values()))
        text, _ = mcap_writer.message_definition(IMU)
        assert schema.encoding == "ros2msg" and schema.data.decode() == text and "MSG: std_msgs/Header" in text
        assert all(ch.message_encoding == "cdr" and "offered_qos_profiles" in ch.metadata for ch in summary.channels.values())
        assert {ci.compression for ci in summary.chunk_indexes} == {mcap_format.DEFAULT_COMPRESSION}
        assert sum(1 for _ in reader.iter_messages()) == 160
        assert [m.name for m in reader.iter_metadata()] == ["rosbag2"]
    data = (out / "rec_0.mcap").read_bytes()
    for ci in summary.chunk_indexes:  # chunk index -> chunk record and its message index records
        op, ln = struct.unpack_from("<BQ", data, ci.chunk_start_offset)
        assert op == 0x06 and 9 + ln == ci.chunk_length
        total = 0
        for cid, off in ci.message_index_offsets.items():
            op, ln, ch = struct.unpack_from("<BQH", data, off)
            assert op == 0x07 and ch == cid
            total += 9 + ln
        assert total == ci.message_index_length
    from mcap.stream_reader import StreamReader

    with open(out / "rec_0.mcap", "rb") as fh:  # streams every record incl. data-section and summary CRCs
        assert sum(1 for _ in StreamReader(fh, validate_crcs=True).records) > 160


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_multi_chunk_compressions(tmp_path, ts, compression):
    """Small chunks: messages of one sample straddle chunk boundaries; every compression reads back."""
    desc = make_desc()
    s = make_samples(desc, n=120)
    chans = []
    for k, name in enumerate(NAMES):
        p = encode_imu(s.stamps, name, angular_velocity=s.gyro[:, k], linear_acceleration=s.accel[:, k])
        chans.append(ChannelData(imu_topic(name), IMU, s.stamps, p))
    out = tmp_path / f"c_{compression}.mcap"
    write_recording(out, chans, compression=compression, chunk_size=5000)
    with McapRecording(out).open_files().__next__() as mf:
        assert len(mf.chunks) > 20 and {c.compression for c in mf.chunks} == {"" if compression == "none" else compression}
    back, stats = read_imu_recording(out, desc)
    np.testing.assert_array_equal(back.accel, s.accel)
    np.testing.assert_array_equal(back.gyro, s.gyro)
    assert stats.incomplete_samples == 0
    assert sum(len(v) for v in msgs_by_topic(out, ts).values()) == 4 * 120


# --------------------------------------------------------------------------- foreign writers -> our reader


def _ros_imu(ts, stamp, frame_id, gyro, acc):
    t = ts.types
    sec, nsec = divmod(int(stamp), 1_000_000_000)
    v3 = t["geometry_msgs/msg/Vector3"]
    return t[IMU](
        header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0),
        orientation_covariance=np.array([-1.0] + [0.0] * 8),
        angular_velocity=v3(x=gyro[0], y=gyro[1], z=gyro[2]),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(x=acc[0], y=acc[1], z=acc[2]),
        linear_acceleration_covariance=np.zeros(9),
    )


def _write_with_mcap_library(path, ts, s, *, library="test", order=None, channel_metadata=None, **writer_kwargs):
    """Write the IMU samples ``s`` with the ``mcap`` library's own Writer (an independent writer);
    ``order``: message order as indexes into the (sample, IMU) pairs, default sample by sample."""
    from mcap.writer import Writer as McapWriter

    text, _ = mcap_writer.message_definition(IMU)
    items = [(i, k) for i in range(len(s)) for k in range(len(NAMES))]
    with open(path, "wb") as fh:
        w = McapWriter(fh, **writer_kwargs)
        w.start(profile="ros2", library=library)
        sid = w.register_schema(IMU, "ros2msg", text.encode())
        cids = [w.register_channel(imu_topic(n), "cdr", sid, *([channel_metadata] if channel_metadata else []))
                for n in NAMES]
        for j in (range(len(items)) if order is None else order):
            i, k = items[j]
            raw = bytes(ts.serialize_cdr(_ros_imu(ts, s.stamps[i], NAMES[k], s.gyro[i, k], s.accel[i, k]), IMU))
            w.add_message(cids[k], int(s.stamps[i]), raw, int(s.stamps[i]))
        w.finish()


def write_with_rosbags(path, ts, samples, *, extra=(), compress=False, prefix="/imu_array"):
    """rosbags.rosbag2.Writer (mcap storage, v9); ``extra``: (k, stamp, gyro, acc) appended messages."""
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    if compress:
        w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with w:
        conns = [w.add_connection(imu_topic(n, prefix), IMU, typestore=ts) for n in samples.names]
        w.add_connection("/other/chatter", "std_msgs/msg/String", typestore=ts)
        for i, st in enumerate(samples.stamps):
            for k, name in enumerate(samples.names):
                if samples.present[i, k]:
                    raw = ts.serialize_cdr(_ros_imu(ts, st, name, samples.gyro[i, k], samples.accel[i, k]), IMU)
                    w.write(conns[k], int(st), raw)
        for k, st, gyro, acc in extra:
            raw = ts.serialize_cdr(_ros_imu(ts, st, samples.names[k], gyro, acc), IMU)
            w.write(conns[k], int(st), raw)


@pytest.mark.parametrize("compress", [False, True])
def test_rosbags_written_bag_reads_bit_exact(tmp_path, ts, compress):
    desc = make_desc()
    s = make_samples(desc, n=100, seed=11)
    s.gyro[10, 1] = np.nan  # imu_01 absent in sample 10 (not written)
    s.accel[20:25, 3] = np.nan
    write_with_rosbags(tmp_path / "bag", ts, s, compress=compress)
    back, stats = read_imu_recording(tmp_path / "bag", desc)
    np.testing.assert_array_equal(back.stamps, s.stamps)
    want_g = np.where(s.present[..., None], s.gyro, np.nan)
    want_a = np.where(s.present[..., None], s.accel, np.nan)
    assert back.gyro.view(np.uint64)[s.present].tolist() == want_g.view(np.uint64)[s.present].tolist()
    np.testing.assert_array_equal(back.accel, want_a)
    np.testing.assert_array_equal(back.gyro, want_g)
    assert stats.incomplete_samples == 6 and stats.bad_messages == 0 and stats.messages == 400 - 6


def test_mcap_library_unindexed_unchunked_and_shuffled(tmp_path, ts):
    """mcap Writer without message indexes (record walk), messages out of time order, lz4; and an unchunked file."""
    from mcap.writer import CompressionType, IndexType

    desc = make_desc()
    s = make_samples(desc, n=60, seed=12)
    rng = np.random.default_rng(13)
    order = rng.permutation(len(s) * len(NAMES))
    for variant, kwargs in {
        "noindex": dict(compression=CompressionType.LZ4, index_types=IndexType.NONE, chunk_size=3000),
        "unchunked": dict(compression=CompressionType.NONE, use_chunking=False),
        "nosummary": dict(compression=CompressionType.ZSTD, index_types=IndexType.NONE, repeat_channels=False,
                          repeat_schemas=False, use_statistics=False, use_summary_offsets=False, chunk_size=3000),
    }.items():
        path = tmp_path / f"{variant}.mcap"
        _write_with_mcap_library(path, ts, s, order=order, channel_metadata={"offered_qos_profiles": ""}, **kwargs)
        with mcap_reader.McapFile(path) as mf:
            assert mf.has_summary == (variant != "nosummary")
        back, stats = read_imu_recording(path, desc)
        np.testing.assert_array_equal(back.stamps, s.stamps)
        np.testing.assert_array_equal(back.accel, s.accel)
        np.testing.assert_array_equal(back.gyro, s.gyro)
        assert stats.messages == 4 * len(s)


def test_nan_values_duplicates_and_extra_topics(tmp_path, ts):
    desc = make_desc()
    s = make_samples(desc, n=50, seed=14)
    # non-finite values in each of the six components of imu_01 at samples 0..5 (written as is),
    # and a duplicate of 'b2' at sample 7 with other values
    extra = []
    for i in range(6):
        gyro, acc = s.gyro[i, 1].copy(), s.accel[i, 1].copy()
        (gyro if i < 3 else acc)[i % 3] = [np.nan, np.inf, -np.inf][i % 3]
        extra.append((1, s.stamps[i], gyro, acc))
    extra.append((3, s.stamps[7], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]))
    s_written = ImuSamples(s.stamps, s.accel.copy(), s.gyro.copy(), s.names)
    s_written.accel[:6, 1] = np.nan  # not written by the helper; the bad messages come via extra
    write_with_rosbags(tmp_path / "bag", ts, s_written, extra=extra)
    back, stats = read_imu_recording(tmp_path / "bag", desc)
    assert stats.bad_messages == 6 and stats.duplicate_messages == 1 and stats.messages == 4 * 50 + 1
    assert np.isnan(back.gyro[:6, 1]).all() and np.isnan(back.accel[:6, 1]).all()  # whole row, never fused
    np.testing.assert_array_equal(back.gyro[:6, [0, 2, 3]], s.gyro[:6, [0, 2, 3]])
    np.testing.assert_array_equal(back.gyro[6:], s.gyro[6:])
    np.testing.assert_array_equal(back.gyro[7, 3], s.gyro[7, 3])  # first message kept
    assert not back.present[:6, 1].any() and stats.incomplete_samples == 6
    assert any("non-finite" in n and "imu_01" in n for n in stats.notes)


def test_custom_prefix_and_subset_of_imus(tmp_path, ts):
    desc = make_desc()
    s = make_samples(desc, n=30, seed=15)
    write_imu_recording(tmp_path / "r.mcap", s, desc, topic_prefix="/left_array/")
    assert set(msgs_by_topic(tmp_path / "r.mcap", ts)) == {f"/left_array/{n}/data_raw" for n in NAMES}
    sub = make_desc(names=("b2", "a"))
    back, _ = read_imu_recording(tmp_path / "r.mcap", sub, topic_prefix="/left_array")
    np.testing.assert_array_equal(back.accel, s.accel[:, [3, 0]])
    with pytest.raises(RecordingError) as err:
        read_imu_recording(tmp_path / "r.mcap", sub)
    assert "no topic /imu_array/b2/data_raw for IMU 'b2'" in one_line(err) and "/left_array/a/data_raw" in str(err.value)


def test_multi_file_directory_in_listed_order(tmp_path):
    desc = make_desc()
    s = make_samples(desc, n=80, seed=16)
    first, second = s.select(slice(0, 50)), s.select(slice(50, 80))
    bag = tmp_path / "bag"
    bag.mkdir()
    write_imu_recording(bag / "part_1.mcap", second, desc)
    write_imu_recording(bag / "part_0.mcap", first, desc)
    write_imu_recording(tmp_path / "tmpl", first, desc)
    info = yaml.safe_load((tmp_path / "tmpl" / "metadata.yaml").read_text())
    info["rosbag2_bagfile_information"]["relative_file_paths"] = ["part_0.mcap", "part_1.mcap"]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(info))
    fractions = []
    back, stats = read_imu_recording(bag, desc, progress=fractions.append)
    np.testing.assert_array_equal(back.stamps, s.stamps)
    np.testing.assert_array_equal(back.gyro, s.gyro)
    assert fractions and fractions[-1] == 1.0 and fractions == sorted(fractions)
    back2, _ = read_imu_recording(bag / "metadata.yaml", desc)  # the metadata file names its directory
    np.testing.assert_array_equal(back2.accel, s.accel)


def test_partial_or_wrong_message_index_can_not_hide_messages(tmp_path):
    """Chunk records not covered by the Message Index are walked; a bad index falls back to a walk."""
    desc = make_desc()
    s = make_samples(desc, n=30, seed=23)
    write_imu_recording(tmp_path / "r.mcap", s, desc)
    with mcap_reader.McapFile(tmp_path / "r.mcap") as mf:
        assert len(mf.chunks) == 1
        got = mf.read_chunk(0)
        data, full = got.data, got.index
        arr = np.frombuffer(data, dtype=np.uint8)
    assert len(full) == 120
    want, _ = mcap_locate.walk_records(data, 0, len(data))
    rng = np.random.default_rng(24)
    for index in (
        full,
        full[rng.permutation(120)[:77]],  # a partial index (e.g. one channel's index missing)
        full[:1],
        full + 1,  # pointing into records: inconsistent
        np.concatenate([full, full[:3]]),  # duplicate entries
        np.array([len(data) + 5]),
        None,
    ):
        off, others = mcap_locate.locate_messages(data, arr, index)
        assert off.tolist() == want and not others


# --------------------------------------------------------------------------- stamps


def test_jittered_stamps_become_incomplete_samples(tmp_path):
    """A few stamps off on one IMU (the others' stamps coinciding) are not an error: they become incomplete
    samples.  (An IMU whose stamps all differ is paired as stamping its own messages: test_pairing.py.)"""
    desc = make_desc()
    s = make_samples(desc, n=60, seed=17)
    chans = []
    for k, name in enumerate(NAMES):
        p = encode_imu(s.stamps, name, angular_velocity=s.gyro[:, k], linear_acceleration=s.accel[:, k])
        chans.append(ChannelData(imu_topic(name), IMU, s.stamps, p))
    # a few jittered stamps are not an error: they become incomplete samples
    jit = s.stamps.copy()
    jit[:5] += 1000
    p = encode_imu(jit, "b2", angular_velocity=s.gyro[:, 3], linear_acceleration=s.accel[:, 3])
    p2 = encode_imu(s.stamps, "left_front_imu", angular_velocity=s.gyro[:, 2], linear_acceleration=s.accel[:, 2])
    chans[2] = ChannelData(imu_topic("left_front_imu"), IMU, s.stamps, p2)
    chans[3] = ChannelData(imu_topic("b2"), IMU, jit, p)
    write_recording(tmp_path / "jit.mcap", chans)
    back, stats = read_imu_recording(tmp_path / "jit.mcap", desc)
    assert len(back) == 65 and stats.incomplete_samples == 10


# --------------------------------------------------------------------------- errors


def test_missing_and_wrong_topics(tmp_path, ts):
    desc = make_desc()
    s = make_samples(desc, n=10)
    write_imu_recording(tmp_path / "r.mcap", s, desc)
    more = make_desc(names=NAMES + ("imu_07",))
    with pytest.raises(RecordingError) as err:
        read_imu_recording(tmp_path / "r.mcap", more)
    msg = one_line(err)
    assert msg.startswith(str(tmp_path / "r.mcap"))
    assert "no topic /imu_array/imu_07/data_raw for IMU 'imu_07' (recording has: /imu_array/a/data_raw" in msg

    with Writer(tmp_path / "wrong", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        w.add_connection(imu_topic("a"), "std_msgs/msg/String", typestore=ts)
    with pytest.raises(RecordingError) as err:
        read_imu_recording(tmp_path / "wrong", make_desc(names=("a",)))
    assert "topic /imu_array/a/data_raw" in one_line(err) and "std_msgs/msg/String" in str(err.value)


def test_garbage_truncated_and_missing(tmp_path):
    desc = make_desc()
    s = make_samples(desc, n=200, seed=18)
    good = tmp_path / "good.mcap"
    write_imu_recording(good, s, desc)
    data = good.read_bytes()
    rng = np.random.default_rng(19)

    cases = {
        "missing.mcap": None,
        "empty.mcap": b"",
        "garbage.mcap": rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(),
        "bag_0.db3": b"SQLite format 3\0" + bytes(2000),
        "truncated.mcap": data[: len(data) // 2],
        "magic_only.mcap": data[:8],
        "chopped_tail.mcap": data[:-1],
    }
    corrupt = bytearray(data)
    with mcap_reader.McapFile(good) as mf:
        c = mf.chunks[0]
        # chunk record: opcode, length, 3 times/sizes, CRC, compression string, data length, data
        data_offset = c.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(c.compression) + 8
        corrupt[data_offset + 100 : data_offset + 140] = bytes(40)  # zeroed compressed bytes
    cases["corrupt_chunk.mcap"] = bytes(corrupt)
    for name, content in cases.items():
        if content is not None:
            (tmp_path / name).write_bytes(content)
        with pytest.raises(RecordingError) as err:
            read_imu_recording(tmp_path / name, desc)
        assert str(tmp_path / name) in one_line(err), name
        if name in ("truncated.mcap", "magic_only.mcap", "chopped_tail.mcap"):
            assert "truncated MCAP file" in str(err.value) and f"imu-array recover {tmp_path / name} --out" in str(err.value)
        if name == "corrupt_chunk.mcap":
            assert "corrupt chunk at byte" in str(err.value) and "imu-array recover" in str(err.value)

    # rosbag2 directory problems
    d = tmp_path / "dir"
    d.mkdir()
    with pytest.raises(RecordingError, match="no metadata.yaml"):
        read_imu_recording(d, desc)
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    with pytest.raises(RecordingError, match="malformed YAML") as err:
        read_imu_recording(d, desc)
    one_line(err)
    def meta(**info):
        (d / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))

    meta(storage_identifier="sqlite3", relative_file_paths=["x.db3"])
    with pytest.raises(RecordingError, match="only 'mcap'"):
        read_imu_recording(d, desc)
    meta(storage_identifier="mcap", relative_file_paths=["gone.mcap"])
    with pytest.raises(RecordingError, match="gone.mcap"):
        read_imu_recording(d, desc)
    meta(storage_identifier="mcap")
    with pytest.raises(RecordingError, match="relative_file_paths"):
        read_imu_recording(d, desc)


# --------------------------------------------------------------------------- atomic writes


class _Boom(RuntimeError):
    pass


@pytest.mark.parametrize("target", ["out", "out.mcap"])
def test_failed_write_keeps_previous_output(tmp_path, monkeypatch, target):
    desc = make_desc()
    s = make_samples(desc, n=3000, seed=20)
    out = tmp_path / target
    write_imu_recording(out, s.select(slice(0, 10)), desc)
    before = {p.relative_to(tmp_path): p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file()}

    real = mcap_writer.compressor

    def failing(name):
        compress = real(name)
        calls = []

        def f(data):
            calls.append(1)
            if len(calls) == 2:  # after the first chunk is on disk
                raise _Boom("disk on fire")
            return compress(data)

        return f

    monkeypatch.setattr(mcap_writer, "compressor", failing)
    with pytest.raises(_Boom):
        payload = encode_imu(s.stamps, "a", angular_velocity=s.gyro[:, 0], linear_acceleration=s.accel[:, 0])
        write_recording(out, [ChannelData(imu_topic("a"), IMU, s.stamps, payload)], chunk_size=100_000)
    after = {p.relative_to(tmp_path): p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file()}
    assert after == before  # no temp leftovers, previous recording intact
    assert sorted(os.listdir(tmp_path)) == [target]
    back, _ = read_imu_recording(out, desc)
    assert len(back) == 10


def test_write_replaces_existing_directory(tmp_path):
    desc = make_desc()
    out = tmp_path / "rec"
    write_imu_recording(out, make_samples(desc, n=20), desc)
    (out / "stale.txt").write_text("old")
    write_imu_recording(out, make_samples(desc, n=7, seed=3), desc)
    assert sorted(p.name for p in out.iterdir()) == ["metadata.yaml", "rec_0.mcap"]
    assert len(read_imu_recording(out, desc)[0]) == 7
    assert sorted(os.listdir(tmp_path)) == ["rec"]


# --------------------------------------------------------------------------- truth and fused


@pytest.mark.parametrize("attitude", [True, False])
def test_truth_roundtrip(tmp_path, attitude):
    desc = make_desc()
    s = make_samples(desc, n=40, seed=21)
    truth = make_truth(s, attitude=attitude)
    write_imu_recording(tmp_path / "t", s, desc, truth=truth)
    back = read_truth(tmp_path / "t")
    np.testing.assert_array_equal(back.stamps, truth.stamps)
    np.testing.assert_array_equal(back.omega, truth.omega)
    np.testing.assert_array_equal(back.omega_dot, truth.omega_dot)
    np.testing.assert_array_equal(back.specific_force, truth.specific_force)
    if attitude:
        np.testing.assert_array_equal(back.attitude, truth.attitude)
    else:
        assert back.attitude is None
    write_imu_recording(tmp_path / "nt.mcap", s, desc)
    with pytest.raises(RecordingError, match="no ground truth") as err:
        read_truth(tmp_path / "nt.mcap")
    one_line(err)


def test_fused_roundtrip_and_ros_layout(tmp_path, ts):
    rng = np.random.default_rng(22)
    n = 30
    a = rng.normal(size=(n, 9, 9))
    cov = a @ a.transpose(0, 2, 1)
    fused = FusedSamples(T0 + np.arange(n, dtype=np.int64) * 1000, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
                         rng.normal(size=(n, 3)), cov)
    for target in ("f", "f.mcap"):
        write_fused_recording(tmp_path / target, fused, "array_link")
        back = read_fused_recording(tmp_path / target)
        np.testing.assert_array_equal(back.stamps, fused.stamps)
        np.testing.assert_array_equal(back.omega, fused.omega)
        np.testing.assert_array_equal(back.omega_dot, fused.omega_dot)
        np.testing.assert_array_equal(back.specific_force, fused.specific_force)
        carried = np.zeros((9, 9), bool)
        for i, j in [(0, 0), (1, 1), (2, 2), (2, 1), (1, 2)]:
            carried[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] = True
        np.testing.assert_array_equal(back.covariance[:, carried], cov[:, carried])
        assert np.isnan(back.covariance[:, ~carried]).all()

    got = msgs_by_topic(tmp_path / "f", ts)
    assert set(got) == {"/imu_array/fused/imu", "/imu_array/fused/accel"}
    for r, ((_, mi), (_, ma)) in enumerate(zip(got["/imu_array/fused/imu"], got["/imu_array/fused/accel"])):
        assert mi.header.frame_id == ma.header.frame_id == "array_link"
        assert stamp_ns(mi) == stamp_ns(ma) == fused.stamps[r]
        assert vec(mi.angular_velocity) == fused.omega[r].tolist()
        assert mi.angular_velocity_covariance.tolist() == cov[r, :3, :3].ravel().tolist()
        assert mi.linear_acceleration_covariance.tolist() == cov[r, 6:, 6:].ravel().tolist()
        assert mi.orientation_covariance[0] == -1.0
        assert vec(ma.accel.accel.linear) == fused.specific_force[r].tolist()
        assert vec(ma.accel.accel.angular) == fused.omega_dot[r].tolist()
        c6 = ma.accel.covariance.reshape(6, 6)  # ROS order [linear, angular] = [specific force, omega_dot]
        np.testing.assert_array_equal(c6[:3, :3], cov[r, 6:, 6:])
        np.testing.assert_array_equal(c6[3:, 3:], cov[r, 3:6, 3:6])
        np.testing.assert_array_equal(c6[:3, 3:], cov[r, 6:, 3:6])
        np.testing.assert_array_equal(c6[3:, :3], cov[r, 3:6, 6:])


# --------------------------------------------------------------------------- container checks (mcap library)


def _footer(data: bytes) -> tuple[int, int, int]:
    op, ln, start, offsets, crc = struct.unpack_from("<BQQQI", data, len(data) - 8 - 29)
    assert op == 0x02 and ln == 20
    return start, offsets, crc


def _flip(data: bytes, pos: int) -> bytes:
    out = bytearray(data)
    out[pos] ^= 0x20  # a letter changes case: the record still parses
    return bytes(out)


def test_summary_and_data_section_crcs_are_verified(tmp_path):
    desc = make_desc()
    s = make_samples(desc, n=300, seed=31)
    good = tmp_path / "good.mcap"
    write_imu_recording(good, s, desc)
    data = good.read_bytes()
    summary_start, _, summary_crc = _footer(data)
    assert summary_crc != 0
    # the schema text is in the data section (before the chunks) and repeated in the summary
    first = data.index(b"MSG: std_msgs/Header")
    last = data.rindex(b"MSG: std_msgs/Header")
    assert first < summary_start <= last
    cases = {
        "summary.mcap": (_flip(data, last + 5), "summary CRC mismatch"),
        "data.mcap": (_flip(data, first + 5), "data section CRC mismatch"),
        # the rosbag2 metadata record, between the last chunk and DataEnd
        "metadata.mcap": (_flip(data, data.rindex(b"ros_distro", 0, summary_start) + 1), "data section CRC mismatch"),
    }
    for name, (content, expect) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(RecordingError) as err:
            read_imu_recording(tmp_path / name, desc)
        msg = one_line(err)
        assert str(tmp_path / name) in msg and expect in msg and "imu-array recover" in msg, msg
    back, _ = read_imu_recording(good, desc)  # the undamaged file reads
    np.testing.assert_array_equal(back.gyro, s.gyro)


@pytest.mark.parametrize("data_crcs", [True, False])
@pytest.mark.parametrize("variant", ["indexed", "streamed"])
def test_data_section_crc_of_zero_is_not_checked(tmp_path, ts, data_crcs, variant):
    """mcap library writer: with enable_data_crcs the flip is caught (seeking and streaming path);
    without, DataEnd holds 0 = "not computed" (MCAP spec) and the file reads."""
    from mcap.writer import CompressionType, IndexType

    desc = make_desc()
    s = make_samples(desc, n=80, seed=32)
    path = tmp_path / f"{variant}.mcap"
    index = IndexType.ALL if variant == "indexed" else IndexType.NONE
    _write_with_mcap_library(path, ts, s, library="crc-test-library", chunk_size=4000, compression=CompressionType.LZ4,
                             index_types=index, enable_data_crcs=data_crcs)
    data = path.read_bytes()
    with mcap_reader.McapFile(path) as mf:
        assert mf.indexed == (variant == "indexed")
    path.write_bytes(_flip(data, data.index(b"crc-test-library")))  # the Header record (the schema is in a chunk)
    if data_crcs:
        with pytest.raises(RecordingError, match="data section CRC mismatch") as err:
            read_imu_recording(path, desc)
        one_line(err)
    else:
        back, _ = read_imu_recording(path, desc)
        np.testing.assert_array_equal(back.accel, s.accel)


def _count_decompressions(monkeypatch) -> list[int]:
    calls: list[int] = []
    real = mcap_reader.get_chunk_data_stream

    def counting(chunk, validate_crc=False):
        calls.append(chunk.uncompressed_size)
        return real(chunk, validate_crc=validate_crc)

    monkeypatch.setattr(mcap_reader, "get_chunk_data_stream", counting)
    return calls


def _n_chunks(path) -> int:
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        return sum(isinstance(r, Chunk) for r in StreamReader(fh, emit_chunks=True).records)


@pytest.mark.parametrize("variant", ["ours", "summary_stripped", "mcap_nosummary"])
def test_every_chunk_is_decompressed_once(tmp_path, ts, monkeypatch, variant):
    """With a chunk index (seeking) and without (StreamReader fallback): one decompression per chunk,
    also when the topics must be found in the chunks themselves."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import Footer
    from mcap.writer import CompressionType, IndexType

    desc = make_desc()
    s = make_samples(desc, n=200, seed=33)
    truth = make_truth(s)
    path = tmp_path / "r.mcap"
    if variant == "mcap_nosummary":  # channels only inside chunks, no summary, no indexes
        _write_with_mcap_library(path, ts, s, chunk_size=6000, compression=CompressionType.ZSTD,
                                 index_types=IndexType.NONE, repeat_channels=False, repeat_schemas=False,
                                 use_statistics=False, use_summary_offsets=False)
        has_truth = False
    else:
        chans = []
        for k, name in enumerate(NAMES):
            p = encode_imu(s.stamps, name, angular_velocity=s.gyro[:, k], linear_acceleration=s.accel[:, k])
            chans.append(ChannelData(imu_topic(name), IMU, s.stamps, p))
        write_recording(path, chans, chunk_size=20_000)
        write_imu_recording(tmp_path / "t.mcap", s, desc, truth=truth)
        has_truth = True
        if variant == "summary_stripped":  # data section + a footer without summary
            for f in (path, tmp_path / "t.mcap"):
                data = f.read_bytes()
                start, _, _ = _footer(data)
                rb = RecordBuilder()
                Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
                f.write_bytes(data[:start] + rb.end() + data[:8])
    with mcap_reader.McapFile(path) as mf:
        assert mf.indexed == (variant == "ours")
        assert mf.has_summary == (variant == "ours")
    chunks = _n_chunks(path)
    assert chunks > 5
    calls = _count_decompressions(monkeypatch)
    back, stats = read_imu_recording(path, desc)
    assert len(calls) == chunks  # once each, not once for the topics and once for the messages
    np.testing.assert_array_equal(back.accel, s.accel)
    np.testing.assert_array_equal(back.gyro, s.gyro)
    assert stats.messages == 4 * len(s)
    if has_truth:
        calls.clear()
        got = read_truth(tmp_path / "t.mcap")
        assert len(calls) == _n_chunks(tmp_path / "t.mcap")
        np.testing.assert_array_equal(got.omega, truth.omega)
    # a missing topic is still a one-line error, after the single pass when the channels are not summarized
    calls.clear()
    with pytest.raises(RecordingError, match="no topic /imu_array/zz/data_raw") as err:
        read_imu_recording(path, make_desc(names=NAMES + ("zz",)))
    one_line(err)
    assert len(calls) == (0 if variant == "ours" else chunks)


def test_chunks_missing_from_the_chunk_index_are_read(tmp_path):
    """A summary listing only some chunks (seeking path): the others are found between them."""
    from mcap.data_stream import RecordBuilder
    from mcap.reader import make_reader
    from mcap.records import Footer

    desc = make_desc()
    s = make_samples(desc, n=200, seed=34)
    chans = []
    for k, name in enumerate(NAMES):
        p = encode_imu(s.stamps, name, angular_velocity=s.gyro[:, k], linear_acceleration=s.accel[:, k])
        chans.append(ChannelData(imu_topic(name), IMU, s.stamps, p))
    path = tmp_path / "r.mcap"
    write_recording(path, chans, chunk_size=20_000)
    data = path.read_bytes()
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    start, _, _ = _footer(data)
    rb = RecordBuilder()
    for rec in list(summary.schemas.values()) + list(summary.channels.values()):
        rec.write(rb)
    listed = summary.chunk_indexes[::3]  # two of three chunks unlisted
    for ci in listed:
        ci.write(rb)
    Footer(summary_start=start, summary_offset_start=0, summary_crc=0).write(rb)
    path.write_bytes(data[:start] + rb.end() + data[:8])
    with mcap_reader.McapFile(path) as mf:
        assert mf.indexed and len(mf.chunks) == len(listed) < len(summary.chunk_indexes)
    back, stats = read_imu_recording(path, desc)
    assert stats.messages == 4 * len(s)
    np.testing.assert_array_equal(back.gyro, s.gyro)
    np.testing.assert_array_equal(back.stamps, s.stamps)


def test_metadata_yaml_errors_are_one_line(tmp_path):
    d = tmp_path / "bag"
    d.mkdir()
    (d / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n  files: [unclosed\n")
    with pytest.raises(RecordingError) as err:
        McapRecording(d)
    assert f"{d / 'metadata.yaml'}: line " in one_line(err) and "malformed YAML" in str(err.value)
    (d / "metadata.yaml").write_bytes(b"\xff\xfe not utf-8")
    with pytest.raises(RecordingError) as err:
        McapRecording(d)
    assert "cannot read rosbag2 metadata" in one_line(err)
