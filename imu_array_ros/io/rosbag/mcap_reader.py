"""MCAP / rosbag2 container reading: find and walk MCAP files in bulk.

Knows nothing about message semantics: it hands out *where* the payloads of
selected topics are (one :class:`MessageBatch` per decompressed chunk:
buffer, offsets, lengths, log times).  The CDR layer
(:mod:`imu_array_ros.io.rosbag.cdr_columns`) does the rest.

A recording is a rosbag2 directory (``metadata.yaml``; its
``relative_file_paths`` are read in order) or a bare ``.mcap`` file.
Top-level records are walked with a small loop (a few per chunk); inside a
chunk the message records are located from the chunk's Message Index
records (vectorized, then every byte of the chunk not covered by an indexed
message is walked, so a partial index can not hide messages), falling back
to a record walk when the index is absent or inconsistent.
Chunk compression ``zstd``, ``lz4`` or none; chunk CRCs are verified.

Format constants and decompressors: :mod:`imu_array_ros.io.rosbag.mcap_format`;
writing: :mod:`imu_array_ros.io.rosbag.mcap_writer`.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Iterator, Mapping

import numpy as np
import yaml
from numpy.lib.stride_tricks import sliding_window_view

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_format import (
    _MSG_HEAD,
    _MSG_HEAD_SIZE,
    _REC,
    _U16,
    _U32,
    _U64,
    MAGIC,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    _decompressor,
)

__all__ = [
    "ChannelInfo",
    "MessageBatch",
    "McapFile",
    "McapRecording",
]

_PREFETCH = 2  # chunks decompressed ahead by a worker thread


class _Corrupt(Exception):
    """Internal: a structural problem; translated into RecordingError with file context."""


@dataclass(frozen=True)
class ChannelInfo:
    """One MCAP channel (a topic with one type/encoding/QoS within one file)."""

    id: int
    topic: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    metadata: dict[str, str] = field(default_factory=dict)


@dataclass
class MessageBatch:
    """Messages of the selected topics found in one chunk, in file order.

    buffer (S,) uint8: the decompressed chunk; topic (M,) int32: index into the
    selection given to ``iter_batches``; log_time (M,) int64 ns; offset,
    length (M,) int64: payload location within ``buffer``.
    """

    buffer: np.ndarray
    topic: np.ndarray
    log_time: np.ndarray
    offset: np.ndarray
    length: np.ndarray

    def __len__(self) -> int:
        return len(self.topic)


@dataclass
class _ChunkRef:
    start: int  # file offset of the chunk record's opcode
    data_offset: int  # file offset of the compressed records
    compressed_size: int
    uncompressed_size: int
    crc: int
    compression: str
    indexes: list[tuple[int, int]] = field(default_factory=list)  # (file offset of entries, count)


def _string(data, pos: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(data, pos)
    end = pos + 4 + n
    if end > len(data):
        raise _Corrupt("string runs past its record")
    return bytes(data[pos + 4 : end]).decode("utf-8", errors="replace"), end


def _string_map(data, pos: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(data, pos)
    pos += 4
    end = pos + n
    if end > len(data):
        raise _Corrupt("map runs past its record")
    out: dict[str, str] = {}
    while pos < end:
        key, pos = _string(data, pos)
        value, pos = _string(data, pos)
        out[key] = value
    return out, end


def _walk(buf, start: int, end: int) -> tuple[list[int], list[tuple[int, int, int]]]:
    """Walk records in ``buf[start:end]``: (message record offsets, other (op, pos, len))."""
    messages: list[int] = []
    others: list[tuple[int, int, int]] = []
    unpack = _REC.unpack_from
    pos = start
    while pos < end:
        if pos + 9 > end:
            raise _Corrupt(f"record header at byte {pos} runs past the end")
        op, ln = unpack(buf, pos)
        nxt = pos + 9 + ln
        if nxt > end:
            raise _Corrupt(f"record (opcode 0x{op:02x}) at byte {pos} runs past the end")
        if op == OP_MESSAGE:
            messages.append(pos)
        else:
            others.append((op, pos, ln))
        pos = nxt
    return messages, others


def _gather(arr: np.ndarray, start: np.ndarray, nbytes: int) -> np.ndarray:
    if len(start) == 0:
        return np.empty((0, nbytes), dtype=np.uint8)
    return sliding_window_view(arr, nbytes)[start]


def _locate(buf: bytes, arr: np.ndarray, indexed: np.ndarray | None) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Message record offsets (sorted, file order) and other records of one chunk."""
    size = len(buf)
    if indexed is not None and len(indexed) and size >= 9:
        off = np.sort(indexed)
        if off[0] >= 0 and off[-1] <= size - 9 and (len(off) < 2 or (np.diff(off) > 0).all()):
            head = _gather(arr, off, 9)
            ln = np.ascontiguousarray(head[:, 1:9]).view("<u8").reshape(-1)
            if (head[:, 0] == OP_MESSAGE).all() and (ln <= size).all():
                end = off + 9 + ln.astype(np.int64)
                if end[-1] <= size and (ln >= 22).all() and (end[:-1] <= off[1:]).all():
                    gap_start = np.concatenate(([0], end))
                    gap_end = np.concatenate((off, [size]))
                    gaps = np.flatnonzero(gap_end > gap_start)
                    try:
                        extra: list[int] = []
                        others: list[tuple[int, int, int]] = []
                        for g in gaps:
                            m, o = _walk(buf, int(gap_start[g]), int(gap_end[g]))
                            extra += m
                            others += o
                    except _Corrupt:
                        pass  # inconsistent index: fall back to a full walk
                    else:
                        if extra:
                            off = np.sort(np.concatenate((off, np.asarray(extra, dtype=np.int64))))
                        return off, others
    messages, others = _walk(buf, 0, size)
    return np.asarray(messages, dtype=np.int64), others


class McapFile:
    """One MCAP file, memory-mapped; top-level records are indexed on open.

    Use as a context manager.  Raises :class:`RecordingError` (one line naming
    the file) for anything that is not a complete MCAP file.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.schemas: dict[int, tuple[str, str]] = {}  # id -> (name, encoding)
        self.channels: dict[int, ChannelInfo] = {}
        self.chunks: list[_ChunkRef] = []
        self.loose_messages: list[int] = []  # message records outside chunks (file offsets)
        self.profile = ""
        self.has_summary = False  # True: the summary section lists every channel
        self._mm: mmap.mmap | None = None
        self._fh: BinaryIO | None = None
        try:
            self._fh = open(self.path, "rb")
        except FileNotFoundError:
            raise RecordingError(f"{self.path}: recording file not found") from None
        except OSError as err:
            raise RecordingError(f"{self.path}: cannot open: {err.strerror}") from None
        try:
            self._open()
        except _Corrupt as err:
            self.close()
            raise RecordingError(f"{self.path}: corrupt MCAP file: {err}") from None
        except (struct.error, ValueError, IndexError, OverflowError) as err:
            self.close()
            raise RecordingError(f"{self.path}: corrupt MCAP file: {err}") from None
        except BaseException:
            self.close()
            raise

    # -- lifecycle
    def close(self) -> None:
        if self._mm is not None:
            self._mm.close()
            self._mm = None
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "McapFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- parsing
    def _open(self) -> None:
        assert self._fh is not None
        size = os.fstat(self._fh.fileno()).st_size
        head = self._fh.read(16)[:8]
        if head != MAGIC:
            if head == b"SQLite f":
                raise RecordingError(
                    f"{self.path}: sqlite3 rosbag2 storage is not supported; convert to mcap (`ros2 bag convert`)"
                )
            raise RecordingError(f"{self.path}: not an MCAP file (bad magic)")
        min_size = 8 + 9 + 8 + 9 + 20 + 8  # magic, empty header, data end... footer, magic
        if size < min_size:
            raise RecordingError(f"{self.path}: truncated MCAP file ({size} bytes)")
        self._mm = mm = mmap.mmap(self._fh.fileno(), 0, access=mmap.ACCESS_READ)
        if mm[size - 8 :] != MAGIC:
            raise RecordingError(
                f"{self.path}: truncated MCAP file (no end magic; was the recording closed cleanly? "
                "`ros2 bag reindex` may repair it)"
            )
        footer = size - 8 - 29
        op, ln = _REC.unpack_from(mm, footer)
        if op != OP_FOOTER or ln != 20:
            raise _Corrupt("no footer record before the end magic")
        summary_start, _summary_offset_start, _crc = struct.unpack_from("<QQI", mm, footer + 9)
        if summary_start:
            if not 8 <= summary_start <= footer:
                raise _Corrupt("summary offset outside the file")
            self._scan_summary(summary_start, footer)
            self.has_summary = bool(self.channels)  # the summary repeats the channels
        self._scan_data(footer)

    def _record_schema(self, data, pos: int) -> None:
        (sid,) = _U16.unpack_from(data, pos)
        name, p = _string(data, pos + 2)
        enc, p = _string(data, p)
        self.schemas[sid] = (name, enc)

    def _record_channel(self, data, pos: int) -> None:
        cid, sid = struct.unpack_from("<HH", data, pos)
        topic, p = _string(data, pos + 4)
        msg_enc, p = _string(data, p)
        meta, p = _string_map(data, p)
        sname, senc = self.schemas.get(sid, ("", ""))
        self.channels[cid] = ChannelInfo(cid, topic, msg_enc, sname, senc, meta)

    def _other_record(self, data, op: int, pos: int) -> None:
        """Schema / channel records found in a chunk or at top level (pos = opcode offset)."""
        if op == OP_SCHEMA:
            self._record_schema(data, pos + 9)
        elif op == OP_CHANNEL:
            self._record_channel(data, pos + 9)

    def _scan_summary(self, start: int, end: int) -> None:
        mm = self._mm
        _, others = _walk(mm, start, end)
        for op, pos, _ in others:
            self._other_record(mm, op, pos)

    def _scan_data(self, footer: int) -> None:
        mm = self._mm
        assert mm is not None
        pos = 8
        chunk: _ChunkRef | None = None
        unpack = _REC.unpack_from
        while True:
            if pos + 9 > footer:
                raise _Corrupt("no DataEnd record (file truncated?)")
            op, ln = unpack(mm, pos)
            body = pos + 9
            nxt = body + ln
            if nxt > footer and op != OP_FOOTER:
                raise _Corrupt(f"record (opcode 0x{op:02x}) at byte {pos} runs past the end")
            if op == OP_CHUNK:
                t0, t1, usize, crc = struct.unpack_from("<QQQI", mm, body)
                comp, p = _string(mm, body + 28)
                (csize,) = _U64.unpack_from(mm, p)
                if p + 8 + csize > nxt:
                    raise _Corrupt(f"chunk at byte {pos} is longer than its record")
                chunk = _ChunkRef(pos, p + 8, csize, usize, crc, comp)
                self.chunks.append(chunk)
            elif op == OP_MESSAGE_INDEX:
                (n,) = _U32.unpack_from(mm, body + 2)
                if n % 16 or body + 6 + n > nxt:
                    raise _Corrupt(f"malformed message index at byte {pos}")
                if chunk is not None:
                    chunk.indexes.append((body + 6, n // 16))
            elif op == OP_MESSAGE:
                self.loose_messages.append(pos)
            elif op == OP_HEADER:
                self.profile, _ = _string(mm, body)
            elif op in (OP_SCHEMA, OP_CHANNEL):
                self._other_record(mm, op, pos)
            elif op == OP_DATA_END or op == OP_FOOTER:
                break
            else:
                chunk = None  # message indexes directly follow their chunk
            pos = nxt

    # -- chunk access
    @property
    def chunk_bytes(self) -> int:
        """Total compressed chunk bytes (for progress reporting)."""
        return sum(c.compressed_size for c in self.chunks)

    def _chunk_data(self, c: _ChunkRef) -> bytes:
        dec = _decompressor(c.compression)
        if dec is None:
            raise RecordingError(f"{self.path}: unsupported chunk compression {c.compression!r} (zstd, lz4, none)")
        mm = self._mm
        assert mm is not None
        try:
            data = dec(mm[c.data_offset : c.data_offset + c.compressed_size], c.uncompressed_size)
        except Exception as err:  # third-party decompressor errors vary
            raise RecordingError(f"{self.path}: corrupt chunk at byte {c.start}: {c.compression}: {err}") from None
        if len(data) != c.uncompressed_size:
            raise RecordingError(
                f"{self.path}: corrupt chunk at byte {c.start}: {len(data)} bytes after decompression, "
                f"expected {c.uncompressed_size}"
            )
        if c.crc and zlib.crc32(data) != c.crc:
            raise RecordingError(f"{self.path}: corrupt chunk at byte {c.start}: CRC mismatch")
        return data

    def _index_offsets(self, c: _ChunkRef) -> np.ndarray | None:
        if not c.indexes:
            return None
        mm = self._mm
        parts = [
            np.frombuffer(mm[p : p + 16 * n], dtype="<u8").reshape(n, 2)[:, 1] for p, n in c.indexes if n
        ]
        if not parts:
            return None
        off = np.concatenate(parts)
        if off.max() > np.iinfo(np.int64).max:
            return None
        return off.astype(np.int64)

    def iter_batches(self, select: Callable[[ChannelInfo], int]) -> Iterator[tuple[int, MessageBatch]]:
        """Yield (compressed bytes consumed, batch) per chunk.

        ``select(channel)`` returns the selection index of a channel, or -1 to
        skip its messages.  Channels are resolved as their records are met.
        """
        lut = np.full(65536, -1, dtype=np.int32)
        known: set[int] = set()

        def refresh() -> None:
            for cid, ch in self.channels.items():
                if cid not in known:
                    known.add(cid)
                    lut[cid] = select(ch)

        refresh()
        if self.loose_messages:
            data = bytes(self._mm[:])  # unchunked file: the file itself is the buffer
            yield 0, self._batch(data, np.asarray(self.loose_messages, dtype=np.int64), lut)
        # decompress + CRC (GIL released) of the next chunk overlaps decoding of this one
        with ThreadPoolExecutor(max_workers=1) as pool:
            ahead = [pool.submit(self._chunk_data, c) for c in self.chunks[:_PREFETCH]]
            for i, c in enumerate(self.chunks):
                data = ahead[i].result()
                ahead[i] = None
                if i + _PREFETCH < len(self.chunks):
                    ahead.append(pool.submit(self._chunk_data, self.chunks[i + _PREFETCH]))
                yield c.compressed_size, self._chunk_batch(c, data, lut, refresh)

    def _chunk_batch(self, c: _ChunkRef, data: bytes, lut: np.ndarray, refresh: Callable[[], None]) -> MessageBatch:
        arr = np.frombuffer(data, dtype=np.uint8)
        try:
            off, others = _locate(data, arr, self._index_offsets(c))
            for op, pos, _ in others:
                self._other_record(data, op, pos)
        except (_Corrupt, struct.error) as err:
            raise RecordingError(f"{self.path}: corrupt chunk at byte {c.start}: {err}") from None
        if others:
            refresh()
        return self._batch(data, off, lut, arr)

    def _batch(self, data: bytes, off: np.ndarray, lut: np.ndarray, arr: np.ndarray | None = None) -> MessageBatch:
        if arr is None:
            arr = np.frombuffer(data, dtype=np.uint8)
        if len(off) and off[-1] + _MSG_HEAD_SIZE > len(arr):
            raise RecordingError(f"{self.path}: corrupt message record at byte {int(off[-1])}")
        head = np.ascontiguousarray(_gather(arr, off, _MSG_HEAD_SIZE)).view(_MSG_HEAD).reshape(-1)
        if len(head) and (head["len"] < 22).any():
            raise RecordingError(f"{self.path}: corrupt message record (shorter than its header)")
        topic = lut[head["channel"]]
        keep = topic >= 0
        return MessageBatch(
            buffer=arr,
            topic=topic[keep],
            log_time=head["log_time"][keep].astype(np.int64),
            offset=off[keep] + _MSG_HEAD_SIZE,
            length=head["len"][keep].astype(np.int64) - 22,
        )


def _read_metadata_yaml(directory: Path) -> tuple[list[Path], dict]:
    meta_path = directory / "metadata.yaml"
    if not meta_path.is_file():
        mcaps = sorted(p.name for p in directory.glob("*.mcap"))
        hint = f" (it has {', '.join(mcaps[:3])}: pass the .mcap file, or run `ros2 bag reindex`)" if mcaps else ""
        raise RecordingError(f"{directory}: not a rosbag2 directory: no metadata.yaml{hint}")
    try:
        doc = yaml.safe_load(meta_path.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise RecordingError(f"{meta_path}: {where}malformed YAML: {problem}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RecordingError(f"{meta_path}: cannot read: {err}") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise RecordingError(f"{meta_path}: malformed metadata: no rosbag2_bagfile_information mapping")
    storage = info.get("storage_identifier")
    if storage != "mcap":
        raise RecordingError(
            f"{meta_path}: storage_identifier is {storage!r}; only 'mcap' is supported "
            "(convert with `ros2 bag convert` to mcap)"
        )
    mode = str(info.get("compression_mode") or "").strip().lower()
    if mode not in ("", "none"):
        raise RecordingError(
            f"{meta_path}: rosbag2 compression_mode {mode!r} is not supported "
            "(use MCAP chunk compression: `ros2 bag convert` / `ros2 bag record --storage-preset-profile`)"
        )
    rel = info.get("relative_file_paths")
    if not isinstance(rel, list) or not rel or not all(isinstance(x, str) and x for x in rel):
        raise RecordingError(f"{meta_path}: malformed metadata: relative_file_paths must be a non-empty list of file names")
    files = []
    for name in rel:
        p = directory / name
        if not p.is_file():
            raise RecordingError(f"{meta_path}: relative_file_paths lists {name!r}, which does not exist")
        files.append(p)
    return files, info


class McapRecording:
    """A recording: rosbag2 MCAP directory or bare ``.mcap`` file.

    ``files`` are the MCAP files in reading order; ``metadata`` the
    ``rosbag2_bagfile_information`` mapping (None for a bare file).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        p = Path(path)
        if p.name == "metadata.yaml" and p.is_file():
            p = p.parent
        self.path = p
        if not p.exists():
            raise RecordingError(f"{p}: recording not found")
        self.metadata: dict | None
        if p.is_dir():
            self.files, self.metadata = _read_metadata_yaml(p)
        elif p.is_file():
            self.files, self.metadata = [p], None
        else:
            raise RecordingError(f"{p}: not a file or directory")

    def open_files(self) -> Iterator[McapFile]:
        for f in self.files:
            with McapFile(f) as mf:
                yield mf

    def topics(self) -> dict[str, list[ChannelInfo]]:
        """topic -> channels over all files (from the summaries; files without one are scanned)."""
        out: dict[str, list[ChannelInfo]] = {}
        for mf in self.open_files():
            if not mf.has_summary and mf.chunks:  # channel records may hide in chunks
                for _ in mf.iter_batches(lambda ch: -1):
                    pass
            for ch in mf.channels.values():
                out.setdefault(ch.topic, []).append(ch)
        return out

    def iter_batches(
        self,
        select: Mapping[str, str],
        *,
        encoding: str = "cdr",
        progress: Callable[[float], None] | None = None,
    ) -> Iterator[MessageBatch]:
        """Batches of the messages on topics ``select`` (topic -> schema name).

        A channel is selected when its topic is a key of ``select``, its schema
        name equals the value and its message encoding is ``encoding``;
        ``MessageBatch.topic`` indexes ``list(select)``.  ``progress(f)`` gets
        the fraction of chunk bytes done, now and then.
        """
        index = {t: i for i, t in enumerate(select)}

        def choose(ch: ChannelInfo) -> int:
            i = index.get(ch.topic, -1)
            if i >= 0 and ch.schema_name == select[ch.topic] and ch.message_encoding == encoding:
                return i
            return -1

        total = sum(max(f.stat().st_size, 1) for f in self.files)
        done_files = 0
        last = -1.0
        for mf in self.open_files():
            fsize = max(mf.path.stat().st_size, 1)
            cbytes = max(mf.chunk_bytes, 1)
            done = 0
            with contextlib.closing(mf.iter_batches(choose)) as batches:
                for used, batch in batches:
                    done += used
                    if progress is not None:
                        frac = (done_files + fsize * min(done / cbytes, 1.0)) / total
                        if frac - last >= 0.01:
                            progress(frac)
                            last = frac
                    if len(batch):
                        yield batch
            done_files += fsize
        if progress is not None and last < 1.0:
            progress(1.0)
