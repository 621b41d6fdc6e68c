"""One MCAP file read through the ``mcap`` library: summary, chunks, CRCs, batches of messages.

Knows nothing about message semantics: :meth:`McapFile.iter_batches` hands
out *where* the payloads of selected channels are (one
:class:`~imu_array_ros.io.rosbag.mcap_locate.MessageBatch` per decompressed
chunk: buffer, offsets, lengths, log times).  The CDR layer
(:mod:`imu_array_ros.io.rosbag.cdr_columns`) does the rest.

Container (the ``mcap`` library): the footer and summary
(``SeekingReader.get_summary``), chunk records (``Chunk.read``),
decompression and chunk CRCs (``get_chunk_data_stream(validate_crc=True)``;
``zstd``, ``lz4`` or none; :func:`decompress_chunk`) and every other
record's fields.  Files whose summary has no chunk index (no summary,
unchunked, or chunk indexes not written) are streamed once with
``StreamReader``.  The summary CRC (footer) and the data-section CRC
(DataEnd) are verified as well; a CRC of 0 means "not computed" (MCAP spec)
and is not checked.  Indexed chunks are read and decompressed ahead by a
worker thread.

Messages are located inside each decompressed chunk with numpy
(:mod:`imu_array_ros.io.rosbag.mcap_locate`: the chunk's Message Index, then
a walk of every byte it does not cover).  The top-level records between
indexed chunks are walked the same way, so messages or chunks the chunk
index does not list are read too, and the DataEnd record's position is
known for the data-section CRC.

A file without footer (a recorder killed mid-write) is refused with a one-line
error naming ``imu-array recover`` (:func:`recover_command`;
:func:`imu_array_ros.io.rosbag.recover.recover_recording`).

A recording (rosbag2 directory or bare ``.mcap`` file, several files):
:mod:`imu_array_ros.io.rosbag.mcap_recording`.  Format constants:
:mod:`imu_array_ros.io.rosbag.mcap_format`; writing:
:mod:`imu_array_ros.io.rosbag.mcap_writer`.
"""

from __future__ import annotations

import io
import os
import shlex
import struct
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.reader import FOOTER_SIZE, SeekingReader
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, MessageIndex, Schema
from mcap.stream_reader import MAGIC_SIZE, CRCValidationError, StreamReader, get_chunk_data_stream, read_magic

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_format import (
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    RECORD_HEAD,
)
from imu_array_ros.io.rosbag.mcap_locate import (
    MessageBatch,
    locate_messages,
    message_batch,
    message_index_offsets,
    ordered_records,
)

__all__ = [
    "ChannelInfo",
    "LoadedChunk",
    "McapFile",
    "decompress_chunk",
    "recover_command",
    "SUPPORTED_COMPRESSIONS",
]

_PREFETCH = 2  # chunks read + decompressed ahead by a worker thread
_LOOSE_BATCH = 1 << 16  # messages outside chunks handed out per batch when streaming

#: Chunk compressions the reader decompresses ("" = none).
SUPPORTED_COMPRESSIONS = ("", "lz4", "zstd")

#: Errors the mcap library and struct raise on malformed bytes.
_PARSE_ERRORS = (McapError, struct.error, ValueError, IndexError, OverflowError, KeyError)


class _Corrupt(Exception):
    """Internal: a structural problem; translated into RecordingError with file context."""


def recover_command(source: str | os.PathLike) -> str:
    """The command that salvages a damaged recording (for error messages)."""
    return f"`imu-array recover {shlex.quote(str(source))} --out OUT`"


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
class LoadedChunk:
    """One indexed chunk as read by the worker thread, with the top-level records after it.

    data: the decompressed chunk records; index (K,) int64 message record
    offsets in ``data`` from the Message Index records that follow the chunk
    (None: no index); raw: the file bytes from the chunk record (file offset
    ``offset``) up to the next indexed chunk (or the end of the data section);
    records: (opcode, position in ``raw``, body length) of the top-level
    records after the chunk's Message Index records, in file order;
    data_crc: CRC-32 of the data section up to the DataEnd record when
    ``raw`` holds it, else None.
    """

    offset: int
    raw: bytes
    data: bytes
    index: np.ndarray | None
    records: list[tuple[int, int, int]]
    data_crc: int | None = None


# --------------------------------------------------------------------------- chunks (mcap library)


def decompress_chunk(chunk: Chunk) -> bytes:
    """The records of a library ``Chunk`` record, decompressed (``mcap`` library) and checked.

    Raises ValueError naming the problem: unsupported compression, a
    decompressor error, a size other than the chunk's ``uncompressed_size``,
    or a CRC mismatch (a CRC of 0 is not checked).
    """
    if chunk.compression not in SUPPORTED_COMPRESSIONS:
        raise ValueError(f"unsupported chunk compression {chunk.compression!r} (zstd, lz4, none)")
    try:
        stream, size = get_chunk_data_stream(chunk, validate_crc=True)
        data = stream.read(size)
    except CRCValidationError:
        raise ValueError("CRC mismatch") from None
    except Exception as err:  # decompressor errors vary by library
        raise ValueError(f"{chunk.compression}: {str(err).splitlines()[0] if str(err) else type(err).__name__}") from None
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"{len(data)} bytes after decompression, expected {chunk.uncompressed_size}")
    return data


def _body_stream(buf, pos: int, ln: int) -> ReadDataStream:
    """Library record reader over the body of the record at ``buf[pos]`` (opcode offset)."""
    return ReadDataStream(io.BytesIO(bytes(memoryview(buf)[pos + 9 : pos + 9 + ln])))


# --------------------------------------------------------------------------- one MCAP file


class McapFile:
    """One MCAP file; its footer, summary and chunk index are read on open (``mcap`` library).

    Use as a context manager.  Raises :class:`RecordingError` (one line naming
    the file) for anything that is not a complete MCAP file; ``source`` (the
    recording the user named, default the file) is what the ``imu-array
    recover`` hint names.

    Attributes: ``schemas`` id -> (name, encoding); ``channels`` id ->
    :class:`ChannelInfo` (those of the summary, then those met while reading);
    ``chunks``: the summary's chunk index records (``mcap.records.ChunkIndex``)
    sorted by file offset, empty when the file is streamed; ``has_summary``:
    the summary lists the channels; ``indexed``: read by seeking chunk by chunk
    (else streamed with ``StreamReader``); ``size`` bytes.
    """

    def __init__(self, path: str | os.PathLike, *, source: str | os.PathLike | None = None) -> None:
        self.path = Path(path)
        self.source = Path(source) if source is not None else self.path
        self.schemas: dict[int, tuple[str, str]] = {}
        self.channels: dict[int, ChannelInfo] = {}
        self.chunks: list[ChunkIndex] = []
        self.profile = ""
        self.has_summary = False
        self.indexed = False
        self.size = 0
        self._data_end = 0  # indexed: the data section ends here (the summary starts)
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
            raise self._corrupt(err) from None
        except _PARSE_ERRORS as err:
            self.close()
            raise self._corrupt(err) from None
        except BaseException:
            self.close()
            raise

    # -- lifecycle
    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "McapFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- errors
    def _corrupt(self, err: Exception, where: str = "") -> RecordingError:
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        return RecordingError(
            f"{self.path}: corrupt MCAP file{where}: {text}; {recover_command(self.source)} keeps what is intact"
        )

    def _chunk_error(self, offset: int, text: str) -> RecordingError:
        return RecordingError(
            f"{self.path}: corrupt chunk at byte {offset}: {text}; "
            f"{recover_command(self.source)} keeps the intact chunks"
        )

    # -- opening
    def _open(self) -> None:
        fh = self._fh
        assert fh is not None
        self.size = size = os.fstat(fh.fileno()).st_size
        try:
            read_magic(ReadDataStream(fh))
        except (InvalidMagic, EndOfFile, struct.error):
            fh.seek(0)
            if fh.read(8) == b"SQLite f":
                raise RecordingError(
                    f"{self.path}: sqlite3 rosbag2 storage is not supported; convert to mcap (`ros2 bag convert`)"
                ) from None
            raise RecordingError(f"{self.path}: not an MCAP file (bad magic)") from None
        footer_pos = size - MAGIC_SIZE - FOOTER_SIZE
        truncated = footer_pos < MAGIC_SIZE
        if not truncated:
            fh.seek(size - MAGIC_SIZE)
            try:
                read_magic(ReadDataStream(fh))
            except InvalidMagic:
                truncated = True
        if truncated:
            raise RecordingError(
                f"{self.path}: truncated MCAP file (no footer/summary: was the recorder stopped before "
                f"closing it?); salvage it with {recover_command(self.source)}"
            )
        fh.seek(footer_pos)
        footer = next(iter(StreamReader(fh, skip_magic=True).records), None)
        if not isinstance(footer, Footer):
            raise _Corrupt("no footer record before the end magic")
        summary_start = footer.summary_start
        if summary_start and not MAGIC_SIZE <= summary_start <= footer_pos:
            raise _Corrupt("summary offset outside the file")
        if footer.summary_crc:
            start = summary_start or footer_pos
            fh.seek(start)
            crc = zlib.crc32(fh.read(size - MAGIC_SIZE - 4 - start))  # through the footer's summary_offset_start
            if crc != footer.summary_crc:
                raise _Corrupt("summary CRC mismatch (the summary / index section is damaged)")
        if not summary_start:
            return  # no summary: streamed
        fh.seek(0)
        summary = SeekingReader(fh).get_summary()
        if summary is None:
            return
        for sid, schema in summary.schemas.items():
            self.schemas[sid] = (schema.name, schema.encoding)
        for channel in summary.channels.values():
            self._add_channel(channel)
        self.has_summary = bool(self.channels)  # the summary repeats the channels
        chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        prev = MAGIC_SIZE
        for c in chunks:
            if c.chunk_start_offset < prev or c.chunk_length < 9 or c.chunk_start_offset + c.chunk_length > summary_start:
                raise _Corrupt(f"chunk index entry for byte {c.chunk_start_offset} overlaps or leaves the data section")
            prev = c.chunk_start_offset + c.chunk_length
        self.chunks = chunks
        self.indexed = bool(chunks)
        self._data_end = summary_start

    def _add_channel(self, ch: Channel) -> None:
        sname, senc = self.schemas.get(ch.schema_id, ("", ""))
        self.channels[ch.id] = ChannelInfo(ch.id, ch.topic, ch.message_encoding, sname, senc, dict(ch.metadata))

    def _add_schema(self, schema: Schema) -> None:
        self.schemas[schema.id] = (schema.name, schema.encoding)

    def _register(self, buf, records: list[tuple[int, int, int]]) -> bool:
        """Parse the Header / Schema / Channel records among ``records``; True if a channel was added."""
        added = False
        for op, pos, ln in records:
            if op == OP_SCHEMA:
                self._add_schema(Schema.read(_body_stream(buf, pos, ln)))
            elif op == OP_CHANNEL:
                self._add_channel(Channel.read(_body_stream(buf, pos, ln)))
                added = True
            elif op == OP_HEADER:
                self.profile = Header.read(_body_stream(buf, pos, ln)).profile
        return added

    # -- chunks
    def _decompress(self, chunk: Chunk, offset: int) -> bytes:
        """Decompressed records of ``chunk`` (record at file byte ``offset``); size and CRC checked."""
        if chunk.compression not in SUPPORTED_COMPRESSIONS:
            raise RecordingError(
                f"{self.path}: unsupported chunk compression {chunk.compression!r} at byte {offset} (zstd, lz4, none)"
            )
        try:
            return decompress_chunk(chunk)
        except ValueError as err:
            raise self._chunk_error(offset, str(err)) from None

    def read_chunk(self, i: int) -> LoadedChunk:
        """Read, check (record head, CRC, size) and decompress indexed chunk ``i``.

        Also reads the top-level records up to the next indexed chunk (or the
        end of the data section) and the chunk's Message Index from them.
        """
        fh = self._fh
        assert fh is not None and self.indexed
        c = self.chunks[i]
        end = self.chunks[i + 1].chunk_start_offset if i + 1 < len(self.chunks) else self._data_end
        fh.seek(c.chunk_start_offset)
        raw = fh.read(end - c.chunk_start_offset)
        if len(raw) != end - c.chunk_start_offset:
            raise self._chunk_error(c.chunk_start_offset, "file ends inside the chunk")
        try:
            op, ln = RECORD_HEAD.unpack_from(raw, 0)
            if op != OP_CHUNK or 9 + ln != c.chunk_length:
                raise _Corrupt("the chunk index points at no chunk record")
            stream = io.BytesIO(raw)
            stream.seek(9)
            chunk = Chunk.read(ReadDataStream(stream))
            data = self._decompress(chunk, c.chunk_start_offset)
            records = ordered_records(raw, c.chunk_length, len(raw))
            k = 0
            while k < len(records) and records[k][0] == OP_MESSAGE_INDEX:
                k += 1
            index = message_index_offsets(raw, records[:k])
        except (_Corrupt, *_PARSE_ERRORS) as err:
            raise self._chunk_error(c.chunk_start_offset, str(err)) from None
        return LoadedChunk(c.chunk_start_offset, raw, data, index, records[k:])

    # -- reading
    def iter_batches(self, select: Callable[[ChannelInfo], int]) -> Iterator[tuple[int, MessageBatch]]:
        """Yield (file bytes consumed, batch) for every chunk, in file order.

        ``select(channel)`` returns the selection index of a channel, or -1 to
        skip its messages.  Channels are resolved as their records are met.
        The whole data section is read; its CRC is checked at the end.
        """
        lut = np.full(65536, -1, dtype=np.int32)
        known: set[int] = set()

        def refresh() -> None:
            for cid, ch in self.channels.items():
                if cid not in known:
                    known.add(cid)
                    lut[cid] = select(ch)

        refresh()
        if self.indexed:
            yield from self._indexed_batches(lut, refresh)
        else:
            yield from self._streamed_batches(lut, refresh)

    def _indexed_batches(self, lut: np.ndarray, refresh: Callable[[], None]) -> Iterator[tuple[int, MessageBatch]]:
        fh = self._fh
        assert fh is not None
        first = self.chunks[0].chunk_start_offset
        fh.seek(0)
        head = fh.read(first)
        try:
            records = ordered_records(head, MAGIC_SIZE, len(head))
        except ValueError as err:
            raise self._corrupt(err) from None
        yield from self._top_level(head, 0, records, lut, refresh, None)

        state = {"crc": zlib.crc32(head)}  # running CRC of the data section, advanced by the worker
        n = len(self.chunks)

        def load(i: int) -> LoadedChunk:  # worker thread: read, CRC, decompress, find the index
            got = self.read_chunk(i)
            if i + 1 < n:
                state["crc"] = zlib.crc32(got.raw, state["crc"])
            else:
                ends = [pos for op, pos, _ in got.records if op == OP_DATA_END]
                if ends:
                    got.data_crc = zlib.crc32(memoryview(got.raw)[: ends[-1]], state["crc"])
            return got

        # read + decompress + CRC (GIL released) of the next chunks overlaps decoding of this one
        with ThreadPoolExecutor(max_workers=1) as pool:
            ahead = [pool.submit(load, i) for i in range(min(_PREFETCH, n))]
            try:
                for i in range(n):
                    got = ahead[i].result()
                    ahead[i] = None
                    if i + _PREFETCH < n:
                        ahead.append(pool.submit(load, i + _PREFETCH))
                    yield len(got.raw) + (len(head) if i == 0 else 0), self._chunk_batch(got, lut, refresh)
                    yield from self._top_level(got.raw, got.offset, got.records, lut, refresh, got.data_crc)
                    if i + 1 == n and not any(op == OP_DATA_END for op, _, _ in got.records):
                        raise self._corrupt(_Corrupt("no DataEnd record at the end of the data section"))
            finally:
                for f in ahead:
                    if f is not None:
                        f.cancel()

    def _top_level(
        self,
        buf: bytes,
        base: int,
        records: list[tuple[int, int, int]],
        lut: np.ndarray,
        refresh: Callable[[], None],
        data_crc: int | None,
    ) -> Iterator[tuple[int, MessageBatch]]:
        """Top-level records found between indexed chunks (``buf`` starts at file byte ``base``).

        Schemas and channels are registered, messages outside chunks batched,
        a chunk the chunk index does not list is read with the Message Index
        records after it, and DataEnd's CRC is compared with ``data_crc``.
        """
        loose: list[int] = []
        k = 0
        try:
            while k < len(records):
                op, pos, ln = records[k]
                k += 1
                if op == OP_MESSAGE:
                    loose.append(pos)
                    continue
                if loose:
                    yield 0, self._batch(buf, np.asarray(loose, dtype=np.int64), lut)
                    loose = []
                if op in (OP_SCHEMA, OP_CHANNEL, OP_HEADER):
                    if self._register(buf, [(op, pos, ln)]):
                        refresh()
                elif op == OP_CHUNK:  # not in the chunk index
                    chunk = Chunk.read(_body_stream(buf, pos, ln))
                    data = self._decompress(chunk, base + pos)
                    j = k
                    while j < len(records) and records[j][0] == OP_MESSAGE_INDEX:
                        j += 1
                    index = message_index_offsets(buf, records[k:j])
                    k = j
                    got = LoadedChunk(base + pos, b"", data, index, [])
                    yield 0, self._chunk_batch(got, lut, refresh)
                elif op == OP_DATA_END:
                    expected = DataEnd.read(_body_stream(buf, pos, ln)).data_section_crc
                    if expected and data_crc is not None and expected != data_crc:
                        raise self._corrupt(_Corrupt("data section CRC mismatch (DataEnd)"))
        except (_Corrupt, *_PARSE_ERRORS) as err:
            raise self._corrupt(err, f" (record at byte {base + pos})") from None
        if loose:
            yield 0, self._batch(buf, np.asarray(loose, dtype=np.int64), lut)

    def _streamed_batches(self, lut: np.ndarray, refresh: Callable[[], None]) -> Iterator[tuple[int, MessageBatch]]:
        """No chunk index: stream every record once (``StreamReader``, data-section CRC checked)."""
        fh = self._fh
        assert fh is not None
        fh.seek(0)
        reader = StreamReader(fh, emit_chunks=True, validate_crcs=True)
        done = 0
        pending: tuple[int, bytes, list] | None = None  # (offset, data, index parts) of the last chunk
        loose: list[Message] = []

        def flush_chunk() -> MessageBatch:
            offset, data, parts = pending
            index = np.concatenate(parts).astype(np.int64) if parts else None
            return self._chunk_batch(LoadedChunk(offset, b"", data, index, []), lut, refresh)

        def flush_loose() -> MessageBatch:
            batch = self._message_batch(loose, lut)
            loose.clear()
            return batch

        pos = 0
        try:
            for record in reader.records:
                if isinstance(record, MessageIndex) and pending is not None:
                    if record.records:
                        entries = np.asarray(record.records, dtype=np.uint64)[:, 1]
                        if entries.max() <= np.iinfo(np.int64).max:
                            pending[2].append(entries)
                    pos = fh.tell()
                    continue
                if pending is not None:
                    now = fh.tell()
                    yield now - done, flush_chunk()
                    done, pending = now, None
                if isinstance(record, Message):
                    loose.append(record)
                    if len(loose) >= _LOOSE_BATCH:
                        now = fh.tell()
                        yield now - done, flush_loose()
                        done = now
                    pos = fh.tell()
                    continue
                if loose:
                    yield 0, flush_loose()
                if isinstance(record, Chunk):
                    pending = (pos, self._decompress(record, pos), [])
                elif isinstance(record, Schema):
                    self._add_schema(record)
                elif isinstance(record, Channel):
                    self._add_channel(record)
                    refresh()
                elif isinstance(record, Header):
                    self.profile = record.profile
                pos = fh.tell()
        except CRCValidationError as err:
            if isinstance(err.record, DataEnd):
                raise self._corrupt(_Corrupt("data section CRC mismatch (DataEnd)")) from None
            raise self._corrupt(err, f" (record at byte {pos})") from None
        except (_Corrupt, *_PARSE_ERRORS) as err:
            raise self._corrupt(err, f" (record at byte {pos})") from None
        if pending is not None:
            yield fh.tell() - done, flush_chunk()
        if loose:
            yield 0, flush_loose()
        yield max(self.size - fh.tell(), 0), self._message_batch([], lut)

    def _chunk_batch(self, got: LoadedChunk, lut: np.ndarray, refresh: Callable[[], None]) -> MessageBatch:
        data = got.data
        arr = np.frombuffer(data, dtype=np.uint8)
        try:
            off, others = locate_messages(data, arr, got.index)
            if others and self._register(data, others):
                refresh()
        except (_Corrupt, *_PARSE_ERRORS) as err:
            raise self._chunk_error(got.offset, str(err)) from None
        return self._batch(data, off, lut, arr)

    def _batch(self, data: bytes, off: np.ndarray, lut: np.ndarray, arr: np.ndarray | None = None) -> MessageBatch:
        """Batch of the selected message records at offsets ``off`` of ``data``."""
        try:
            return message_batch(data, off, lut, arr)
        except ValueError as err:
            raise RecordingError(f"{self.path}: {err}") from None

    @staticmethod
    def _message_batch(messages: list[Message], lut: np.ndarray) -> MessageBatch:
        """Batch of the selected ones among library Message records (streamed, outside chunks)."""
        channel = np.fromiter((m.channel_id for m in messages), dtype=np.int64, count=len(messages))
        topic = lut[channel] if len(messages) else np.zeros(0, np.int32)
        keep = np.flatnonzero(topic >= 0)
        datas = [messages[i].data for i in keep]
        length = np.fromiter((len(d) for d in datas), dtype=np.int64, count=len(datas))
        offset = np.cumsum(length) - length
        return MessageBatch(
            buffer=np.frombuffer(b"".join(datas), dtype=np.uint8),
            topic=topic[keep],
            log_time=np.fromiter((messages[i].log_time for i in keep), dtype=np.int64, count=len(keep)),
            offset=offset,
            length=length,
        )
