"""MCAP / rosbag2 container writing: pre-serialized payload columns to MCAP in bulk.

Knows nothing about message semantics: it writes pre-serialized payload
columns (one :class:`ChannelData` per topic); the CDR layer
(:mod:`imu_array_ros.io.rosbag.cdr_columns`) serializes them.

Chunks are assembled with numpy from per-channel ``(M, L)`` payload arrays,
so writing costs no per-message Python.  Output: MCAP with profile
``ros2``, ``ros2msg`` schemas, ``cdr`` channels carrying
``offered_qos_profiles`` / ``topic_type_hash`` metadata, message indexes,
chunk indexes, statistics and a ``rosbag2`` metadata record; for a
directory also a rosbag2 Jazzy (version 9) ``metadata.yaml``.  Files are
written atomically (:func:`imu_array_ros.util.files.atomic_path`).

Format constants and compressors: :mod:`imu_array_ros.io.rosbag.mcap_format`;
reading: :mod:`imu_array_ros.io.rosbag.mcap_reader` (one file),
:mod:`imu_array_ros.io.rosbag.mcap_recording` (a recording).
"""

from __future__ import annotations

import copy
import os
import struct
import zlib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import BinaryIO, Mapping, Sequence

import numpy as np
import yaml
from numpy.lib.stride_tricks import sliding_window_view

from imu_array_ros.util.files import atomic_path
from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_format import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_COMPRESSION,
    MAGIC,
    MESSAGE_HEAD,
    MESSAGE_HEAD_SIZE,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_METADATA,
    OP_METADATA_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    OP_SUMMARY_OFFSET,
    RECORD_HEAD,
    U16,
    U32,
    U64,
    compressor,
)

__all__ = [
    "ChannelData",
    "write_recording",
    "message_definition",
]

#: rosbag2 Jazzy serialization of an offered QoS profile (reliable, volatile, keep_last 1000).
_INFINITE = {"sec": 9223372036, "nsec": 854775807}
OFFERED_QOS: list[dict] = [
    {
        "history": "keep_last",
        "depth": 1000,
        "reliability": "reliable",
        "durability": "volatile",
        "deadline": dict(_INFINITE),
        "lifespan": dict(_INFINITE),
        "liveliness": "automatic",
        "liveliness_lease_duration": dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }
]


@lru_cache(maxsize=None)
def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@lru_cache(maxsize=None)
def message_definition(type_name: str) -> tuple[str, str]:
    """(concatenated ros2msg definition, RIHS01 type hash) of a ROS 2 Jazzy type."""
    ts = _typestore()
    text, _ = ts.generate_msgdef(type_name, ros_version=2)
    return text, ts.hash_rihs01(type_name)


@dataclass
class ChannelData:
    """Pre-serialized messages of one topic.

    log_time (M,) int64 ns (>= 0; also used as publish time); payload (M, L)
    uint8, one CDR message per row.
    """

    topic: str
    type_name: str
    log_time: np.ndarray
    payload: np.ndarray


def _pack_string(s: str) -> bytes:
    b = s.encode("utf-8")
    return U32.pack(len(b)) + b


def _pack_map(d: Mapping[str, str]) -> bytes:
    body = b"".join(_pack_string(k) + _pack_string(v) for k, v in d.items())
    return U32.pack(len(body)) + body


def _record(op: int, body: bytes) -> bytes:
    return RECORD_HEAD.pack(op, len(body)) + body


class _Out:
    """File writer tracking position and a running data-section CRC."""

    def __init__(self, fh: BinaryIO) -> None:
        self.fh = fh
        self.pos = 0
        self.crc = 0
        self.track = True

    def write(self, data) -> None:
        self.fh.write(data)
        if self.track:
            self.crc = zlib.crc32(data, self.crc)
        self.pos += len(data)


def _qos_string() -> str:
    return yaml.safe_dump(OFFERED_QOS, sort_keys=False, default_flow_style=False).strip()


def _bag_info(files: list[tuple[str, int, int, int]], topics: list[tuple[str, str, int]]) -> dict:
    """rosbag2 v9 ``rosbag2_bagfile_information`` for (path, start, duration, count) files."""
    start = min((f[1] for f in files), default=0)
    end = max((f[1] + f[2] for f in files), default=0)
    return {
        "version": 9,
        "storage_identifier": "mcap",
        "duration": {"nanoseconds": int(end - start)},
        "starting_time": {"nanoseconds_since_epoch": int(start)},
        "message_count": int(sum(f[3] for f in files)),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": type_name,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": copy.deepcopy(OFFERED_QOS),
                    "type_description_hash": message_definition(type_name)[1],
                },
                "message_count": int(count),
            }
            for topic, type_name, count in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "relative_file_paths": [f[0] for f in files],
        "files": [
            {
                "path": name,
                "starting_time": {"nanoseconds_since_epoch": int(s)},
                "duration": {"nanoseconds": int(d)},
                "message_count": int(n),
            }
            for name, s, d, n in files
        ],
        "custom_data": None,
        "ros_distro": "jazzy",
    }


def _dump_yaml(data) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False, width=1000)


def _assemble_chunk(
    channels: Sequence[ChannelData],
    lengths: np.ndarray,
    chan: np.ndarray,
    row: np.ndarray,
    time: np.ndarray,
    off: np.ndarray,
    size: int,
) -> tuple[np.ndarray, list[tuple[int, bytes]]]:
    """Message records of one chunk, scattered per channel with numpy.

    chan, row, time, off (M,): channel index, row in its payload array, log
    time and record offset within the chunk, in chunk order.  Returns the
    uncompressed chunk records (size,) uint8 and the Message Index records
    [(channel id, record bytes)].
    """
    buf = np.empty(size, dtype=np.uint8)
    by_chan = np.argsort(chan, kind="stable")
    present, first = np.unique(chan[by_chan], return_index=True)
    index_recs: list[tuple[int, bytes]] = []
    for c, sel in zip(present, np.split(by_chan, first[1:])):
        cid = int(c) + 1
        width = int(MESSAGE_HEAD_SIZE + lengths[c])
        rec_dt = np.dtype(
            {
                "names": ["head", "data"],
                "formats": [MESSAGE_HEAD, ("u1", (int(lengths[c]),))],
                "offsets": [0, MESSAGE_HEAD_SIZE],
                "itemsize": width,
            }
        )
        recs = np.empty(len(sel), dtype=rec_dt)
        head = recs["head"]
        head["op"] = OP_MESSAGE
        head["len"] = 22 + lengths[c]
        head["channel"] = cid
        head["sequence"] = 0
        head["log_time"] = time[sel]
        head["publish_time"] = time[sel]
        recs["data"] = channels[c].payload[row[sel]]
        sliding_window_view(buf, width, writeable=True)[off[sel]] = recs.view(np.uint8).reshape(-1, width)
        entries = np.empty((len(sel), 2), dtype="<u8")
        entries[:, 0] = time[sel]
        entries[:, 1] = off[sel]
        eb = entries.tobytes()
        index_recs.append((cid, _record(OP_MESSAGE_INDEX, U16.pack(cid) + U32.pack(len(eb)) + eb)))
    return buf, index_recs


def _write_mcap(
    fh: BinaryIO,
    channels: Sequence[ChannelData],
    *,
    compression: str,
    chunk_size: int,
    file_name: str,
    library: str,
) -> tuple[int, int, int]:
    """Write one MCAP file; returns (start time, duration, message count)."""
    compress = compressor(compression)
    comp_name = "" if compression == "none" else compression
    out = _Out(fh)
    out.write(MAGIC)
    out.write(_record(OP_HEADER, _pack_string("ros2") + _pack_string(library)))

    # schemas and channels (ids from 1), top level, before the first chunk
    schema_ids: dict[str, int] = {}
    schema_recs: list[bytes] = []
    chan_recs: list[bytes] = []
    qos = _qos_string()
    for ch in channels:
        if ch.type_name not in schema_ids:
            schema_ids[ch.type_name] = len(schema_ids) + 1
            text, _ = message_definition(ch.type_name)
            body = U16.pack(schema_ids[ch.type_name]) + _pack_string(ch.type_name) + _pack_string("ros2msg")
            data = text.encode("utf-8")
            schema_recs.append(_record(OP_SCHEMA, body + U32.pack(len(data)) + data))
    for i, ch in enumerate(channels):
        meta = {"offered_qos_profiles": qos, "topic_type_hash": message_definition(ch.type_name)[1]}
        body = (
            struct.pack("<HH", i + 1, schema_ids[ch.type_name])
            + _pack_string(ch.topic)
            + _pack_string("cdr")
            + _pack_map(meta)
        )
        chan_recs.append(_record(OP_CHANNEL, body))
    for rec in schema_recs + chan_recs:
        out.write(rec)

    # merge all messages into log-time order (ties: channel order, then row order)
    lengths = np.array([ch.payload.shape[1] for ch in channels], dtype=np.int64)
    counts = np.array([len(ch.log_time) for ch in channels], dtype=np.int64)
    times = np.concatenate([ch.log_time for ch in channels] + [np.zeros(0, np.int64)])
    chan = np.repeat(np.arange(len(channels), dtype=np.int64), counts)
    row = np.concatenate([np.arange(n, dtype=np.int64) for n in counts] + [np.zeros(0, np.int64)])
    order = np.argsort(times, kind="stable")
    times, chan, row = times[order], chan[order], row[order]
    rec_len = MESSAGE_HEAD_SIZE + lengths[chan]
    start = np.cumsum(rec_len) - rec_len
    chunk_of = start // chunk_size
    bounds = np.concatenate(([0], np.flatnonzero(np.diff(chunk_of)) + 1, [len(times)]))

    chunk_indexes: list[bytes] = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        if a == b:
            continue
        c_time = times[a:b]
        c_off = start[a:b] - start[a]
        size = int(c_off[-1] + rec_len[b - 1])
        buf, index_recs = _assemble_chunk(channels, lengths, chan[a:b], row[a:b], c_time, c_off, size)
        crc = zlib.crc32(buf)
        comp = compress(buf)
        t0, t1 = int(c_time.min()), int(c_time.max())
        body_head = struct.pack("<QQQI", t0, t1, size, crc) + _pack_string(comp_name) + U64.pack(len(comp))
        chunk_start = out.pos
        out.write(RECORD_HEAD.pack(OP_CHUNK, len(body_head) + len(comp)))
        out.write(body_head)
        out.write(comp)
        chunk_len = out.pos - chunk_start
        idx_offsets = []
        idx_start = out.pos
        for cid, rec in index_recs:
            idx_offsets.append((cid, out.pos))
            out.write(rec)
        offs_map = b"".join(struct.pack("<HQ", cid, p) for cid, p in idx_offsets)
        chunk_indexes.append(
            _record(
                OP_CHUNK_INDEX,
                struct.pack("<QQQQ", t0, t1, chunk_start, chunk_len)
                + U32.pack(len(offs_map))
                + offs_map
                + U64.pack(out.pos - idx_start)
                + _pack_string(comp_name)
                + struct.pack("<QQ", len(comp), size),
            )
        )

    n_msgs = int(len(times))
    t_start = int(times[0]) if n_msgs else 0
    t_end = int(times[-1]) if n_msgs else 0
    info = _bag_info(
        [(file_name, t_start, t_end - t_start, n_msgs)],
        [(ch.topic, ch.type_name, int(n)) for ch, n in zip(channels, counts)],
    )
    meta_start = out.pos
    meta_body = _pack_string("rosbag2") + _pack_map({"serialized_metadata": _dump_yaml(info), "ros_distro": "jazzy"})
    out.write(_record(OP_METADATA, meta_body))
    meta_len = out.pos - meta_start
    out.write(_record(OP_DATA_END, U32.pack(out.crc)))

    # summary
    out.track = False
    summary_start = out.pos
    groups: list[tuple[int, int, int]] = []
    summary_crc = 0

    def group(op: int, recs: list[bytes]) -> None:
        nonlocal summary_crc
        g0 = out.pos
        for r in recs:
            out.write(r)
            summary_crc = zlib.crc32(r, summary_crc)
        groups.append((op, g0, out.pos - g0))

    stats_map = b"".join(struct.pack("<HQ", i + 1, int(n)) for i, n in enumerate(counts))
    stats = (
        struct.pack("<QHIIII", n_msgs, len(schema_recs), len(chan_recs), 0, 1, len(chunk_indexes))
        + struct.pack("<QQ", t_start, t_end)
        + U32.pack(len(stats_map))
        + stats_map
    )
    group(OP_SCHEMA, schema_recs)
    group(OP_CHANNEL, chan_recs)
    group(OP_STATISTICS, [_record(OP_STATISTICS, stats)])
    group(OP_CHUNK_INDEX, chunk_indexes)
    meta_index = struct.pack("<QQ", meta_start, meta_len) + _pack_string("rosbag2")
    group(OP_METADATA_INDEX, [_record(OP_METADATA_INDEX, meta_index)])
    offset_start = out.pos
    for op, g0, glen in groups:
        rec = _record(OP_SUMMARY_OFFSET, struct.pack("<BQQ", op, g0, glen))
        out.write(rec)
        summary_crc = zlib.crc32(rec, summary_crc)
    footer_head = RECORD_HEAD.pack(OP_FOOTER, 20) + struct.pack("<QQ", summary_start, offset_start)
    summary_crc = zlib.crc32(footer_head, summary_crc)
    out.write(footer_head + U32.pack(summary_crc))
    out.write(MAGIC)
    return t_start, t_end - t_start, n_msgs


def write_recording(
    path: str | os.PathLike,
    channels: Sequence[ChannelData],
    *,
    compression: str = DEFAULT_COMPRESSION,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    library: str = "imu_array_ros",
) -> None:
    """Write channels atomically: ``*.mcap`` -> bare MCAP file, else a rosbag2 directory.

    The directory form is ``<path>/metadata.yaml`` + ``<path>/<name>_0.mcap``.
    An existing target is replaced only when the new one is complete.
    """
    path = Path(path)
    checked = []
    for ch in channels:
        log_time = np.asarray(ch.log_time, dtype=np.int64).reshape(-1)
        payload = np.ascontiguousarray(ch.payload, dtype=np.uint8)
        if payload.ndim != 2 or payload.shape[0] != len(log_time):
            raise ValueError(f"{ch.topic}: payload must be (M, L) uint8 with M = len(log_time)")
        if len(log_time) and log_time.min() < 0:
            raise RecordingError(f"{path}: {ch.topic}: negative time stamps can not be written to MCAP")
        checked.append(ChannelData(ch.topic, ch.type_name, log_time, payload))
    channels = checked
    topics = [ch.topic for ch in channels]
    if len(set(topics)) != len(topics):
        raise ValueError("duplicate topic in channels")
    compressor(compression)  # validate early

    def write_file(target: Path, name: str) -> tuple[int, int, int]:
        with open(target, "wb", buffering=1 << 20) as fh:
            res = _write_mcap(fh, channels, compression=compression, chunk_size=chunk_size, file_name=name, library=library)
            fh.flush()
            os.fsync(fh.fileno())
        return res

    try:
        if path.suffix == ".mcap":
            with atomic_path(path) as tmp:
                write_file(tmp, path.name)
        else:
            name = f"{path.name}_0.mcap"
            with atomic_path(path, directory=True) as tmp:
                t0, dur, n = write_file(tmp / name, name)
                info = _bag_info(
                    [(name, t0, dur, n)],
                    [(ch.topic, ch.type_name, len(ch.log_time)) for ch in channels],
                )
                text = _dump_yaml({"rosbag2_bagfile_information": info})
                with open(tmp / "metadata.yaml", "w", encoding="utf-8") as fh:
                    fh.write(text)
                    fh.flush()
                    os.fsync(fh.fileno())
                os.chmod(tmp, 0o755)
    except OSError as err:
        raise RecordingError(f"{path}: cannot write recording: {err.strerror or err}") from None
