"""Salvaging damaged recordings: recover_recording keeps every complete, intact chunk and message."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import yaml
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from imu_array_ros.errors import OutputError, RecordingError
from imu_array_ros.io.rosbag.cdr_columns import encode_imu
from imu_array_ros.io.rosbag.mcap_writer import ChannelData, message_definition, write_recording
from imu_array_ros.io.rosbag.recording import imu_topic, read_imu_recording, read_truth, write_imu_recording
from imu_array_ros.io.rosbag.recover import RecoverStats, recover_recording
from imu_array_ros.simulation.simulator import simulate_twist

IMU = "sensor_msgs/msg/Imu"


def one_line(err) -> str:
    msg = str(err.value)
    assert msg and "\n" not in msg
    return msg


@pytest.fixture
def twist(tetra4):
    """4 IMUs, 1.5 s at 1 kHz, with ground truth (stamps from 2023)."""
    samples, truth = simulate_twist(tetra4, 1.5, 1000.0, np.random.default_rng(5), start_ns=1_700_000_000_000_000_000)
    return tetra4, samples, truth


def write_chunked(path, samples, chunk_size=40_000, compression="lz4"):
    """The IMU topics of ``samples`` in many small chunks (our writer)."""
    chans = []
    for k, name in enumerate(samples.names):
        rows = samples.present[:, k]
        payload = encode_imu(samples.stamps[rows], name, angular_velocity=samples.gyro[rows, k],
                             linear_acceleration=samples.accel[rows, k])
        chans.append(ChannelData(imu_topic(name), IMU, samples.stamps[rows], payload))
    write_recording(path, chans, chunk_size=chunk_size, compression=compression)


def chunk_table(path):
    """[(record start, record end, messages)] of every chunk, from the mcap library (summary + breakup)."""
    out = []
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for ci in sorted(reader.get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset):
            fh.seek(ci.chunk_start_offset + 9)
            chunk = Chunk.read(ReadDataStream(fh))
            n = sum(isinstance(r, Message) for r in breakup_chunk(chunk, validate_crc=True))
            out.append((ci.chunk_start_offset, ci.chunk_start_offset + ci.chunk_length, n))
    return out


def footer_fields(data: bytes) -> tuple[int, int, int]:
    """(summary start, summary offset start, summary CRC) of a complete MCAP file's footer."""
    op, ln, start, offsets, crc = struct.unpack_from("<BQQQI", data, len(data) - 8 - 29)
    assert op == 0x02 and ln == 20
    return start, offsets, crc


def assert_subset_of_original(out, desc, samples):
    """Every IMU message read back from ``out`` equals the original one of that IMU and stamp."""
    back, stats = read_imu_recording(out, desc)
    rows = np.searchsorted(samples.stamps, back.stamps)
    assert (samples.stamps[rows] == back.stamps).all()
    present = back.present
    np.testing.assert_array_equal(back.accel[present], samples.accel[rows][present])
    np.testing.assert_array_equal(back.gyro[present], samples.gyro[rows][present])
    assert stats.bad_messages == 0 and stats.duplicate_messages == 0
    return back, stats


# --------------------------------------------------------------------------- truncated bare files


CUTS = ["halfway", "inside_last_chunk", "after_a_chunk", "inside_message_index", "before_footer", "before_summary"]


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
@pytest.mark.parametrize("where", CUTS)
def test_truncated_file_keeps_every_complete_chunk(tmp_path, twist, where, compression):
    desc, samples, _ = twist
    good = tmp_path / "good.mcap"
    write_chunked(good, samples, compression=compression)
    data = good.read_bytes()
    table = chunk_table(good)
    assert len(table) >= 8
    total = sum(n for _, _, n in table)
    summary_start, _, _ = footer_fields(data)
    cut = {
        "halfway": len(data) // 2,
        "inside_last_chunk": (table[-1][0] + table[-1][1]) // 2,
        "after_a_chunk": table[3][1],  # the chunk record is complete, its message index is not written yet
        "inside_message_index": table[3][1] + 20,
        "before_footer": len(data) - 8 - 29,
        "before_summary": summary_start,
    }[where]
    bad = tmp_path / "cut.mcap"
    bad.write_bytes(data[:cut])

    with pytest.raises(RecordingError) as err:
        read_imu_recording(bad, desc)
    msg = one_line(err)
    assert str(bad) in msg and "truncated MCAP file" in msg and f"`imu-array recover {bad} --out OUT`" in msg

    out = tmp_path / "fixed.mcap"
    stats = recover_recording(bad, out)
    complete = [(s, e, n) for s, e, n in table if e <= cut]
    want_kept = sum(n for _, _, n in complete)
    assert stats.messages_kept == want_kept > 0
    assert stats.chunks_kept == len(complete)
    # bytes after the last complete record: none when cut at a record boundary
    assert stats.bytes_cut == {"after_a_chunk": 0, "inside_message_index": 20, "before_footer": 0,
                               "before_summary": 0}.get(where, stats.bytes_cut)
    assert 0 <= stats.bytes_cut < cut
    cut_chunk = [n for s, e, n in table if s < cut < e]
    if cut_chunk:  # the chunk cut in two is lost; its size gives an estimate of its messages
        assert stats.chunks_lost == 1 and not stats.lost_exact
        assert abs(stats.messages_lost - cut_chunk[0]) <= max(2, 0.05 * cut_chunk[0]), stats.summary()
    else:
        assert stats.chunks_lost == 0 and stats.messages_lost == 0 and stats.lost_exact
    if where in ("before_footer", "before_summary"):  # the data section is complete: nothing lost
        assert stats.messages_kept == total and stats.lost_exact
    text = stats.summary()
    assert "\n" not in text and f"kept {want_kept} messages" in text
    # the bytes present of the broken record are not what was cut off (issue 24: "584 bytes cut off" for 1.9 MB)
    assert "bytes cut off" not in text
    assert ("ends inside a record" in text) == (stats.bytes_cut > 0)

    back, rstats = assert_subset_of_original(out, desc, samples)
    assert rstats.messages == want_kept
    # the kept messages are the first ones in file (= time) order: a prefix of the original
    np.testing.assert_array_equal(back.stamps, samples.stamps[: len(back.stamps)])
    # the output is a valid, complete MCAP file for the mcap library as well (CRCs checked)
    with open(out, "rb") as fh:
        assert sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages()) == want_kept


def test_rosbag2_directory_with_truncated_data_file(tmp_path, tetra4):
    """metadata.yaml still has the message count: kept + lost is exact; truth is recovered too."""
    desc = tetra4
    samples, truth = simulate_twist(desc, 4.0, 1000.0, np.random.default_rng(6))  # > one 4 MiB chunk
    rec = tmp_path / "rec"
    write_imu_recording(rec, samples, desc, truth=truth)
    info = yaml.safe_load((rec / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    total = info["message_count"]
    mcap_file = rec / "rec_0.mcap"
    data = mcap_file.read_bytes()
    table = chunk_table(mcap_file)
    assert len(table) >= 2
    cut = (table[1][0] + table[1][1]) // 2  # inside the second chunk
    mcap_file.write_bytes(data[:cut])

    with pytest.raises(RecordingError) as err:
        read_imu_recording(rec, desc)
    assert f"`imu-array recover {rec} --out OUT`" in one_line(err)

    out = tmp_path / "fixed"
    fractions = []
    stats = recover_recording(rec, out, progress=fractions.append)
    assert fractions and fractions == sorted(fractions) and fractions[-1] == 1.0
    assert stats.messages_kept == table[0][2]
    assert stats.lost_exact and stats.messages_kept + stats.messages_lost == total
    assert "rosbag2 metadata" in stats.lost_basis
    assert sorted(p.name for p in out.iterdir()) == ["fixed_0.mcap", "metadata.yaml"]
    assert_subset_of_original(out, desc, samples)
    got = read_truth(out)
    rows = np.searchsorted(truth.stamps, got.stamps)
    assert len(got.stamps) > 0 and (truth.stamps[rows] == got.stamps).all()
    np.testing.assert_array_equal(got.omega, truth.omega[rows])
    np.testing.assert_array_equal(got.specific_force, truth.specific_force[rows])
    # a killed recorder writes no metadata.yaml: the directory's .mcap files are used
    (rec / "metadata.yaml").unlink()
    stats2 = recover_recording(rec, tmp_path / "fixed2.mcap")
    assert stats2.messages_kept == stats.messages_kept and not stats2.lost_exact


def test_corrupt_chunk_in_a_complete_file(tmp_path, twist):
    """A chunk failing its CRC is lost, the others kept; the summary statistics give the exact loss."""
    desc, samples, _ = twist
    good = tmp_path / "good.mcap"
    write_chunked(good, samples, compression="none")
    table = chunk_table(good)
    data = bytearray(good.read_bytes())
    s, e, n = table[2]
    data[(s + e) // 2] ^= 0xFF  # one flipped byte inside an uncompressed chunk: its CRC fails
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError) as err:
        read_imu_recording(bad, desc)
    msg = one_line(err)
    assert f"corrupt chunk at byte {s}: CRC mismatch" in msg and "imu-array recover" in msg
    stats = recover_recording(bad, tmp_path / "fixed.mcap")
    total = sum(m for _, _, m in table)
    assert (stats.chunks_kept, stats.chunks_lost) == (len(table) - 1, 1)
    assert stats.messages_lost == n and stats.lost_exact and stats.messages_kept == total - n
    back, _ = assert_subset_of_original(tmp_path / "fixed.mcap", desc, samples)
    assert len(back) < len(samples)


def test_foreign_writer_variable_length_topic_is_reported_not_dropped_silently(tmp_path, twist):
    """mcap library writer, no summary index; a std_msgs/String topic can not be rewritten by our writer."""
    from mcap.writer import CompressionType, IndexType
    from mcap.writer import Writer as McapWriter

    desc, samples, _ = twist
    path = tmp_path / "foreign.mcap"
    n = 300
    with open(path, "wb") as fh:
        w = McapWriter(fh, chunk_size=20_000, compression=CompressionType.ZSTD, index_types=IndexType.NONE)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(IMU, "ros2msg", message_definition(IMU)[0].encode())
        sid_str = w.register_schema("std_msgs/msg/String", "ros2msg", message_definition("std_msgs/msg/String")[0].encode())
        cids = [w.register_channel(imu_topic(name), "cdr", sid) for name in samples.names]
        chat = w.register_channel("/chatter", "cdr", sid_str)
        payloads = [encode_imu(samples.stamps[:n], name, angular_velocity=samples.gyro[:n, k],
                               linear_acceleration=samples.accel[:n, k]) for k, name in enumerate(samples.names)]
        for i in range(n):
            t = int(samples.stamps[i])
            for k in range(len(samples.names)):
                w.add_message(cids[k], t, payloads[k][i].tobytes(), t)
            text = ("x" * (i % 7)).encode() + b"\0"
            w.add_message(chat, t, struct.pack("<4sI", b"\0\1\0\0", len(text)) + text, t)
        w.finish()
    data = path.read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) * 2 // 3])
    stats = recover_recording(tmp_path / "cut.mcap", tmp_path / "fixed")
    assert stats.messages_skipped > 0 and any("/chatter" in note and "different lengths" in note for note in stats.notes)
    assert "/chatter" in stats.summary()
    back, rstats = assert_subset_of_original(tmp_path / "fixed", desc, samples)
    assert rstats.messages == stats.messages_kept > 0
    assert stats.messages_kept + stats.messages_skipped <= 5 * n


# --------------------------------------------------------------------------- refusals


def test_refuses_unsafe_outputs_and_hopeless_inputs(tmp_path, twist):
    desc, samples, truth = twist
    rec = tmp_path / "rec"
    write_imu_recording(rec, samples, desc, truth=truth)
    data_file = rec / "rec_0.mcap"
    for out in (rec, rec / "inside", data_file, tmp_path):
        with pytest.raises(OutputError) as err:
            recover_recording(rec, out)
        assert str(out) in one_line(err)
    with pytest.raises(OutputError):  # the bare data file as input: its directory contains it
        recover_recording(data_file, rec)
    before = sorted(p.name for p in rec.iterdir())
    assert before == ["metadata.yaml", "rec_0.mcap"]

    existing = tmp_path / "done.mcap"
    recover_recording(rec, existing)
    with pytest.raises(OutputError, match="already exists"):
        recover_recording(rec, existing)
    assert isinstance(recover_recording(rec, existing, force=True), RecoverStats)

    not_mcap = tmp_path / "notes.mcap"
    not_mcap.write_bytes(b"hello, world" * 10)
    with pytest.raises(RecordingError) as err:
        recover_recording(not_mcap, tmp_path / "x.mcap")
    assert "not an MCAP file" in one_line(err)

    tiny = tmp_path / "tiny.mcap"
    tiny.write_bytes(data_file.read_bytes()[:300])  # magic, header, part of a schema
    with pytest.raises(RecordingError) as err:
        recover_recording(tiny, tmp_path / "y.mcap")
    assert "nothing to recover" in one_line(err)
    with pytest.raises(RecordingError, match="recording not found"):
        recover_recording(tmp_path / "missing.mcap", tmp_path / "z.mcap")
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "y.mcap").exists()


def test_intact_file_comes_back_message_for_message(tmp_path, twist):
    """An undamaged recording written by us comes back message for message (no loss, nothing skipped)."""
    desc, samples, truth = twist
    write_imu_recording(tmp_path / "a.mcap", samples, desc, truth=truth)
    stats = recover_recording(tmp_path / "a.mcap", tmp_path / "b.mcap")
    assert (stats.messages_lost, stats.messages_skipped, stats.chunks_lost, stats.bytes_cut) == (0, 0, 0, 0)
    assert stats.lost_exact
    with open(tmp_path / "a.mcap", "rb") as fa, open(tmp_path / "b.mcap", "rb") as fb:
        ma = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(fa).iter_messages()]
        mb = [(c.topic, m.log_time, m.data) for _, c, m in make_reader(fb).iter_messages()]
    assert len(ma) == stats.messages_kept and sorted(ma) == sorted(mb)


def test_a_chunk_whose_opcode_reads_as_a_message_is_lost_not_a_crash(tmp_path, twist):
    """A damaged opcode byte turns a chunk into a 'message' whose stamp no int64 holds: that chunk is lost,
    the others kept, and no traceback (found by an identity check of the reader split)."""
    desc, samples, _ = twist
    good = tmp_path / "good.mcap"
    write_chunked(good, samples, compression="none")
    table = chunk_table(good)
    data = bytearray(good.read_bytes())
    s, _, n = table[1]
    assert data[s] == 0x06  # a Chunk record
    data[s] = 0x05  # ... read as a Message record
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    stats = recover_recording(bad, tmp_path / "fixed.mcap")
    assert stats.messages_kept <= sum(m for _, _, m in table) - n
    back, _ = assert_subset_of_original(tmp_path / "fixed.mcap", desc, samples)
    assert 0 < len(back) < len(samples)
