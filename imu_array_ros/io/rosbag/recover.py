"""Salvage a damaged recording: every complete, intact chunk and message into a valid one.

``imu-array recover REC --out OUT`` runs :func:`recover_recording`.  A recorder
killed mid-write leaves an MCAP file without footer and summary (the reader
refuses it); a damaged byte makes a chunk fail its CRC.  Recovery streams
each file front to back with the ``mcap`` library (``StreamReader``, chunks
emitted whole), keeps every chunk that is complete and passes its CRC and
every complete message outside chunks, stops at the first record that is cut
off or unreadable, and writes what it kept with
:func:`imu_array_ros.io.rosbag.mcap_writer.write_recording` (atomically; a
bare ``.mcap`` when ``out`` ends in ``.mcap``, else a rosbag2 directory).

What the writer can rewrite: channels with ``cdr`` messages of a ROS 2 Jazzy
type (the schema text is regenerated from that type) whose messages on one
topic all have the same length (true of every header-plus-floats type such as
sensor_msgs/Imu).  Intact messages of other channels are counted as
*skipped* and named in the stats, never silently dropped.  Message sequence
numbers and publish times are not kept (the writer sets publish time = log
time, as in recordings this package writes).

How many messages were lost is counted, in this order of preference, from the
rosbag2 ``metadata.yaml`` message count of the file, the summary statistics
(when the file still has its footer), the Message Index records of damaged
chunks; otherwise it is estimated from the uncompressed size of a cut-off
chunk (or the bytes of the incomplete tail) divided by the mean size of the
kept message records; :attr:`RecoverStats.lost_exact` tells which.
"""

from __future__ import annotations

import io
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import InvalidMagic, McapError
from mcap.records import Channel, Chunk, DataEnd, Message, MessageIndex, Schema, Statistics
from mcap.stream_reader import StreamReader, read_magic

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.outputs import check_output
from imu_array_ros.io.rosbag.cdr_columns import gather_bytes
from imu_array_ros.io.rosbag.mcap_format import OP_CHANNEL, OP_CHUNK, OP_MESSAGE, OP_SCHEMA
from imu_array_ros.io.rosbag.mcap_locate import locate_messages, message_batch
from imu_array_ros.io.rosbag.mcap_reader import decompress_chunk
from imu_array_ros.io.rosbag.mcap_recording import read_rosbag2_metadata
from imu_array_ros.io.rosbag.mcap_writer import ChannelData, message_definition, write_recording

__all__ = ["RecoverStats", "recover_recording"]

#: Errors the mcap library, struct and decoding raise on a cut-off or damaged record.
_READ_ERRORS = (McapError, struct.error, ValueError, IndexError, OverflowError, KeyError)

_ALL_CHANNELS = np.arange(65536, dtype=np.int32)  # lut: a batch's "topic" is the channel id


@dataclass
class RecoverStats:
    """What :func:`recover_recording` kept and lost.

    messages_kept: written to the output; messages_lost: damaged or cut off
    (an estimate when ``lost_exact`` is False; ``lost_basis`` says how it was
    counted); messages_skipped: intact but on a channel the writer can not
    rewrite (``notes`` name the topics and why); chunks_kept / chunks_lost:
    complete CRC-valid chunks / chunks cut off or failing their CRC;
    bytes_cut: bytes of the incomplete last record present in the files (after the last complete record),
    over all files; the bytes cut off after them are not in the file and cannot be counted.
    """

    messages_kept: int = 0
    messages_lost: int = 0
    lost_exact: bool = True
    lost_basis: str = "no damage found"
    messages_skipped: int = 0
    chunks_kept: int = 0
    chunks_lost: int = 0
    bytes_cut: int = 0
    files: int = 0
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """One line for the user."""
        lost = f"{self.messages_lost}" if self.lost_exact else f"~{self.messages_lost}"
        text = (
            f"kept {self.messages_kept} messages ({self.chunks_kept} chunks), lost {lost} "
            f"({self.chunks_lost} chunks; {self.lost_basis})"
        )
        if self.bytes_cut:  # what the file still holds of the record it broke in; what was cut is not in it
            text += (f"; the file ends inside a record ({self.bytes_cut} bytes of it present; how much was cut "
                     "off after them is not in the file)")
        if self.messages_skipped:
            text += f", skipped {self.messages_skipped} intact messages the writer can not rewrite"
        if self.notes:
            text += "; " + "; ".join(self.notes)
        return text


@dataclass
class _Topic:
    """Salvaged messages of one (topic, type): payload rows of one length."""

    topic: str
    type_name: str
    length: int = -1
    stamps: list[np.ndarray] = field(default_factory=list)
    payloads: list[np.ndarray] = field(default_factory=list)
    count: int = 0


@dataclass
class _FileResult:
    kept: int = 0  # complete messages salvaged (kept + skipped)
    lost_counted: int = 0  # messages of damaged chunks, from their Message Index
    lost_unknown_bytes: int = 0  # uncompressed bytes of damaged / cut chunks with no message count
    cut_bytes: int = 0  # bytes after the last complete record
    cut_uncounted: int = 0  # compressed bytes of a cut record whose kind is unknown
    cut_message: bool = False  # the cut record was a message outside chunks
    complete: bool = False  # the data section ended with DataEnd
    total: int | None = None  # message count from the summary statistics
    chunk_bytes: int = 0  # uncompressed bytes of kept chunks
    chunk_msgs: int = 0
    comp_bytes: int = 0  # compressed bytes of kept chunks


class _Salvage:
    """Messages kept so far, by topic; channels and schemas of the file being read."""

    def __init__(self) -> None:
        self.topics: dict[str, _Topic] = {}
        self.skipped: dict[str, tuple[int, str]] = {}  # topic -> (count, why)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}

    def new_file(self) -> None:
        self.schemas, self.channels = {}, {}

    def register(self, record) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record

    def _skip(self, topic: str, n: int, why: str) -> None:
        count, first_why = self.skipped.get(topic, (0, why))
        self.skipped[topic] = (count + n, first_why)

    def _writable(self, ch: Channel) -> tuple[str | None, str]:
        """(type name, "") if our writer can rewrite the channel, else (None, why not)."""
        schema = self.schemas.get(ch.schema_id)
        if schema is None:
            return None, "no schema"
        if ch.message_encoding != "cdr" or schema.encoding != "ros2msg":
            return None, f"{ch.message_encoding}/{schema.encoding or 'no'} encoding, not cdr/ros2msg"
        try:
            message_definition(schema.name)
        except Exception:  # rosbags raises several kinds for an unknown type
            return None, f"type {schema.name} unknown to the ROS 2 Jazzy type store"
        return schema.name, ""

    def add(self, cid: int, stamps: np.ndarray, payloads: np.ndarray | None) -> None:
        """Messages of channel ``cid``: stamps (M,) int64 ns; payloads (M, L) uint8 when all M
        have the same length L, else None (the topic can not be rewritten)."""
        ch = self.channels.get(cid)
        if ch is None:
            self._skip(f"<channel id {cid}>", len(stamps), "no channel record")
            return
        type_name, why = self._writable(ch)
        if type_name is None:
            self._skip(ch.topic, len(stamps), why)
            return
        t = self.topics.get(ch.topic)
        if t is None:
            t = self.topics[ch.topic] = _Topic(ch.topic, type_name)
        if t.type_name != type_name:
            self._skip(ch.topic, len(stamps), f"a second type {type_name} on the topic")
            return
        if payloads is None or (t.length >= 0 and payloads.shape[1] != t.length):
            self._skip(ch.topic, len(stamps) + t.count, "messages of different lengths")
            del self.topics[ch.topic]
            return
        t.length = payloads.shape[1]
        t.stamps.append(stamps)
        t.payloads.append(payloads)
        t.count += len(stamps)

    def add_batch(self, arr: np.ndarray, batch) -> None:
        """Messages of a :class:`MessageBatch` whose ``topic`` is the channel id."""
        if not len(batch):
            return
        order = np.argsort(batch.topic, kind="stable")
        cids, first = np.unique(batch.topic[order], return_index=True)
        for cid, sel in zip(cids, np.split(order, first[1:])):
            lengths = batch.length[sel]
            rows = None
            if (lengths == lengths[0]).all():
                rows = gather_bytes(arr, batch.offset[sel], int(lengths[0]))
            self.add(int(cid), batch.log_time[sel], rows)

    @property
    def kept(self) -> int:
        return sum(t.count for t in self.topics.values())

    @property
    def skipped_count(self) -> int:
        return sum(n for n, _ in self.skipped.values())


class _Progress:
    """``progress(fraction)`` of all input bytes, called when it moved by 1 % or more."""

    def __init__(self, progress: Callable[[float], None], base: int, total: float) -> None:
        self.progress, self.base, self.total, self.last = progress, base, total, -1.0

    def __call__(self, pos: int) -> None:
        frac = min((self.base + pos) / self.total, 1.0)
        if frac - self.last >= 0.01:
            self.progress(frac)
            self.last = frac


def _inputs(src: Path) -> tuple[Path, list[Path], dict | None]:
    """(recording path, MCAP files, rosbag2 info or None) of ``src``."""
    if src.name == "metadata.yaml" and src.is_file():
        src = src.parent
    if not src.exists():
        raise RecordingError(f"{src}: recording not found")
    if src.is_file():
        return src, [src], None
    if not src.is_dir():
        raise RecordingError(f"{src}: not a file or directory")
    if (src / "metadata.yaml").is_file():
        files, info = read_rosbag2_metadata(src)
        return src, files, info
    # a recorder killed before writing metadata.yaml: every .mcap file, in natural order
    files = sorted(src.glob("*.mcap"), key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])
    if not files:
        raise RecordingError(f"{src}: no metadata.yaml and no .mcap file: nothing to recover")
    return src, files, None


def _file_count(info: dict | None, path: Path, n_files: int) -> int | None:
    """Message count of one file from rosbag2 metadata, if it says."""
    if info is None:
        return None
    for entry in info.get("files") or []:
        if isinstance(entry, dict) and entry.get("path") == path.name and isinstance(entry.get("message_count"), int):
            return entry["message_count"]
    if n_files == 1 and isinstance(info.get("message_count"), int):
        return info["message_count"]
    return None


def _cut_record(fh, start: int, size: int, res: _FileResult) -> bool:
    """Classify the incomplete record at file byte ``start`` (the stream broke there).

    True if it is a chunk (then counted as lost).
    """
    res.cut_bytes = size - start
    if res.cut_bytes <= 0 or res.complete:
        return False  # nothing cut, or only the summary section: no message lost
    fh.seek(start)
    head = fh.read(9 + 24)
    if len(head) < 9:
        res.cut_uncounted += len(head)  # record of unknown kind
        return False
    op = head[0]
    if op == OP_MESSAGE:
        res.cut_message = True
    elif op == OP_CHUNK:
        if len(head) >= 9 + 24:
            stream = ReadDataStream(io.BytesIO(head[9:]))
            stream.read8()  # message start time
            stream.read8()  # message end time
            res.lost_unknown_bytes += stream.read8()  # uncompressed size
        else:
            res.cut_uncounted += res.cut_bytes
        return True
    # schema, channel, message index, metadata, attachment, DataEnd: no message lost
    return False


def _salvage_file(path: Path, salvage: _Salvage, stats: RecoverStats, progress) -> _FileResult:
    res = _FileResult()
    salvage.new_file()
    try:
        fh = open(path, "rb")
    except OSError as err:
        raise RecordingError(f"{path}: cannot open: {err.strerror or err}") from None
    with fh:
        size = os.fstat(fh.fileno()).st_size
        try:
            read_magic(ReadDataStream(fh))
        except (InvalidMagic, McapError, struct.error):
            raise RecordingError(f"{path}: not an MCAP file (bad magic); nothing to recover") from None
        fh.seek(0)
        records = iter(StreamReader(fh, emit_chunks=True, validate_crcs=False).records)
        good = 8  # end of the last complete record
        lost_chunk: int | None = None  # damaged chunk whose Message Index entries are being counted
        while True:
            try:
                record = next(records)
            except StopIteration:  # footer and end magic read: the file is whole
                good = fh.tell()
                break
            except _READ_ERRORS:
                break  # a cut-off or unreadable record: stop here
            good = fh.tell()
            if isinstance(record, MessageIndex):
                if lost_chunk is not None:
                    res.lost_counted += len(record.records)
                    lost_chunk = -1  # counted
                continue
            if lost_chunk is not None and lost_chunk >= 0:
                res.lost_unknown_bytes += lost_chunk  # no index followed the damaged chunk
            lost_chunk = None
            if isinstance(record, (Schema, Channel)):
                salvage.register(record)
            elif isinstance(record, Message):
                if not 0 <= record.log_time < 2 ** 63:  # damaged bytes read as a message: no int64 ns stamp
                    res.lost_counted += 1
                    continue
                stamps = np.array([record.log_time], dtype=np.int64)
                data = np.frombuffer(record.data, dtype=np.uint8)
                salvage.add(record.channel_id, stamps, data.reshape(1, -1).copy())
                res.kept += 1
            elif isinstance(record, Chunk):
                try:
                    data = decompress_chunk(record)
                    arr = np.frombuffer(data, dtype=np.uint8)
                    off, others = locate_messages(data, arr, None)
                    for op, pos, ln in others:
                        if op in (OP_SCHEMA, OP_CHANNEL):
                            body = ReadDataStream(io.BytesIO(data[pos + 9 : pos + 9 + ln]))
                            salvage.register(Schema.read(body) if op == OP_SCHEMA else Channel.read(body))
                    batch = message_batch(data, off, _ALL_CHANNELS, arr)
                except _READ_ERRORS:
                    stats.chunks_lost += 1
                    lost_chunk = record.uncompressed_size
                    continue
                salvage.add_batch(arr, batch)
                stats.chunks_kept += 1
                res.kept += len(batch)
                res.chunk_msgs += len(batch)
                res.chunk_bytes += len(data)
                res.comp_bytes += len(record.data)
            elif isinstance(record, DataEnd):
                res.complete = True
            elif isinstance(record, Statistics):
                res.total = record.message_count
            if progress is not None:
                progress(good)
        if lost_chunk is not None and lost_chunk >= 0:
            res.lost_unknown_bytes += lost_chunk
        if _cut_record(fh, good, size, res):
            stats.chunks_lost += 1
    return res


def recover_recording(
    src: str | os.PathLike,
    out: str | os.PathLike,
    progress: Callable[[float], None] | None = None,
    *,
    force: bool = False,
) -> RecoverStats:
    """Salvage every complete, intact chunk and message of ``src`` into a valid recording ``out``.

    Parameters
    ----------
    src : a bare ``.mcap`` file or a rosbag2 directory (with ``metadata.yaml``,
        or without one: then every ``*.mcap`` file in it), damaged or cut off.
    out : the recording to write: a bare MCAP file when it ends in ``.mcap``,
        else a rosbag2 directory; never ``src``, inside it or containing it.
    progress : called with the fraction (0..1) of input bytes read, now and then.
    force : replace an existing ``out`` (only if it is itself a recording).

    Returns
    -------
    RecoverStats; ``stats.summary()`` is one line for the user.

    Raises
    ------
    RecordingError
        ``src`` is missing or not MCAP, or nothing can be salvaged.
    OutputError
        ``out`` is unsafe to write (see :func:`imu_array_ros.io.outputs.check_output`).
    """
    src_path, files, info = _inputs(Path(src))
    out = check_output(out, [src_path, *files], "recording", force)
    stats = RecoverStats(files=len(files))
    salvage = _Salvage()
    sizes = [max(f.stat().st_size, 1) for f in files]
    total_bytes = float(sum(sizes))
    results: list[tuple[Path, _FileResult]] = []
    done = 0
    for f, fsize in zip(files, sizes):
        report = None if progress is None else _Progress(progress, done, total_bytes)
        results.append((f, _salvage_file(f, salvage, stats, report)))
        done += fsize
    if progress is not None:
        progress(1.0)

    kept_records = sum(r.chunk_msgs for _, r in results)
    kept_bytes = sum(r.chunk_bytes for _, r in results)
    comp_bytes = sum(r.comp_bytes for _, r in results)
    mean_record = kept_bytes / kept_records if kept_records else 0.0
    ratio = kept_bytes / comp_bytes if comp_bytes else 1.0
    lost, exact, bases = 0, True, set()
    for f, r in results:
        stats.bytes_cut += r.cut_bytes
        count = _file_count(info, f, len(files))
        for known, basis in ((count, "rosbag2 metadata message count"), (r.total, "summary statistics")):
            if known is not None and known >= r.kept:
                lost += known - r.kept
                bases.add(f"counted from the {basis}")
                break
        else:
            lost += r.lost_counted + int(r.cut_message)
            if r.lost_counted:
                bases.add("counted from the message indexes of damaged chunks")
            unknown = r.lost_unknown_bytes + r.cut_uncounted * ratio
            if unknown:
                exact = False
                if mean_record:
                    lost += int(round(unknown / mean_record))
                    bases.add("estimated from the size of cut-off / damaged chunks over the mean kept record size")
                else:
                    bases.add("not estimable: no complete chunk to measure")
            if not r.complete:
                bases.add("what was never written after the cut is not counted")
    stats.messages_lost = lost
    stats.lost_exact = exact
    if bases:
        stats.lost_basis = "; ".join(sorted(bases))
    stats.messages_kept = salvage.kept
    stats.messages_skipped = salvage.skipped_count
    for topic, (n, why) in sorted(salvage.skipped.items()):
        stats.notes.append(f"skipped {n} on {topic} ({why})")
    if not salvage.topics:
        what = "no complete, intact message" if not stats.messages_skipped else (
            f"no message the writer can rewrite ({'; '.join(stats.notes)})")
        raise RecordingError(
            f"{src_path}: nothing to recover: {what}; {stats.chunks_lost} damaged or cut-off chunks, "
            f"{stats.bytes_cut} bytes cut off"
        )
    channels = []
    for t in salvage.topics.values():
        stamps = np.concatenate(t.stamps)
        payload = np.concatenate(t.payloads) if len(t.payloads) > 1 else t.payloads[0]
        channels.append(ChannelData(t.topic, t.type_name, stamps, payload))
    write_recording(out, channels, library="imu_array_ros recover")
    return stats
