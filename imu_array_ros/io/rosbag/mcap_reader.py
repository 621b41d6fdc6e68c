"""One MCAP file read through the ``mcap`` library: chunks, CRCs, batches of messages.

Knows nothing about message semantics: :meth:`McapFile.iter_batches` hands
out *where* the payloads of selected channels are (one
:class:`~imu_array_ros.io.rosbag.mcap_locate.MessageBatch` per decompressed
chunk: buffer, offsets, lengths, log times).  The CDR layer
(:mod:`imu_array_ros.io.rosbag.cdr_columns`) does the rest.

Container (the ``mcap`` library): chunk records (``Chunk.read``),
decompression and chunk CRCs (``get_chunk_data_stream(validate_crc=True)``;
``zstd``, ``lz4`` or none; :func:`decompress_chunk`) and every other
record's fields.  Opening (magic, footer, summary CRC, summary, chunk index)
and the schemas and channels a file declares:
:mod:`imu_array_ros.io.rosbag.mcap_summary`.  Files whose summary has no
chunk index (no summary, unchunked, or chunk indexes not written) are
streamed once with ``StreamReader``
(:mod:`imu_array_ros.io.rosbag.mcap_stream`).  The data-section CRC
(DataEnd) is verified as well; a CRC of 0 means "not computed" (MCAP spec)
and is not checked.  Indexed chunks are read and decompressed ahead by a
worker thread.

Messages are located inside each decompressed chunk with numpy
(:mod:`imu_array_ros.io.rosbag.mcap_locate`: the chunk's Message Index, then
a walk of every byte it does not cover).  The top-level records between
indexed chunks are walked the same way, so messages or chunks the chunk
index does not list are read too, and the DataEnd record's position is
known for the data-section CRC.

A file without footer (a recorder killed mid-write) is refused with a one-line
error naming ``imu-array recover`` (:func:`~imu_array_ros.io.rosbag.mcap_summary.recover_command`;
:func:`imu_array_ros.io.rosbag.recover.recover_recording`).

A recording (rosbag2 directory or bare ``.mcap`` file, several files):
:mod:`imu_array_ros.io.rosbag.mcap_recording`.  Format constants:
:mod:`imu_array_ros.io.rosbag.mcap_format`; writing:
:mod:`imu_array_ros.io.rosbag.mcap_writer`.
"""

from __future__ import annotations

import io
import os
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.records import Chunk, ChunkIndex, DataEnd
from mcap.stream_reader import MAGIC_SIZE, CRCValidationError, get_chunk_data_stream

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
from imu_array_ros.io.rosbag.mcap_stream import streamed_batches
from imu_array_ros.io.rosbag.mcap_summary import (
    PARSE_ERRORS,
    ChannelInfo,
    CorruptMcap,
    McapDeclarations,
    read_layout,
    record_body,
    recover_command,
)

__all__ = ["ChannelInfo", "LoadedChunk", "McapFile", "decompress_chunk", "recover_command", "SUPPORTED_COMPRESSIONS"]

_PREFETCH = 2  # chunks read + decompressed ahead by a worker thread

#: Chunk compressions the reader decompresses ("" = none).
SUPPORTED_COMPRESSIONS = ("", "lz4", "zstd")


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


# --------------------------------------------------------------------------- one MCAP file


class McapFile:
    """One MCAP file; its footer, summary and chunk index are read on open (``mcap`` library).

    Use as a context manager.  Raises :class:`RecordingError` (one line naming
    the file) for anything that is not a complete MCAP file; ``source`` (the
    recording the user named, default the file) is what the ``imu-array
    recover`` hint names.

    Attributes: ``schemas`` id -> (name, encoding); ``channels`` id ->
    :class:`ChannelInfo` (those of the summary, then those met while reading);
    both held by ``declared`` (:class:`~imu_array_ros.io.rosbag.mcap_summary.McapDeclarations`);
    ``chunks``: the summary's chunk index records (``mcap.records.ChunkIndex``)
    sorted by file offset, empty when the file is streamed; ``has_summary``:
    the summary lists the channels; ``indexed``: read by seeking chunk by chunk
    (else streamed with ``StreamReader``); ``size`` bytes.
    """

    def __init__(self, path: str | os.PathLike, *, source: str | os.PathLike | None = None) -> None:
        self.path = Path(path)
        self.source = Path(source) if source is not None else self.path
        self.declared = McapDeclarations()
        self.chunks: list[ChunkIndex] = []
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
            layout = read_layout(self._fh, self.path, self.source, self.declared)
        except CorruptMcap as err:
            self.close()
            raise self._corrupt(err) from None
        except PARSE_ERRORS as err:
            self.close()
            raise self._corrupt(err) from None
        except BaseException:
            self.close()
            raise
        self.size, self.chunks, self.has_summary = layout.size, layout.chunks, layout.has_summary
        self.indexed, self._data_end = layout.indexed, layout.data_end

    @property
    def schemas(self) -> dict[int, tuple[str, str]]:
        return self.declared.schemas

    @property
    def channels(self) -> dict[int, ChannelInfo]:
        return self.declared.channels

    @property
    def profile(self) -> str:
        return self.declared.profile

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
                raise CorruptMcap("the chunk index points at no chunk record")
            stream = io.BytesIO(raw)
            stream.seek(9)
            chunk = Chunk.read(ReadDataStream(stream))
            data = self._decompress(chunk, c.chunk_start_offset)
            records = ordered_records(raw, c.chunk_length, len(raw))
            k = 0
            while k < len(records) and records[k][0] == OP_MESSAGE_INDEX:
                k += 1
            index = message_index_offsets(raw, records[:k])
        except (CorruptMcap, *PARSE_ERRORS) as err:
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
            yield from streamed_batches(self._fh, self.size, self.declared, lut, refresh, decompress=self._decompress,
                                        chunk_batch=self._chunk_batch, corrupt=self._corrupt)

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
                    yield (len(got.raw) + (len(head) if i == 0 else 0),
                           self._chunk_batch(got.offset, got.data, got.index, lut, refresh))
                    yield from self._top_level(got.raw, got.offset, got.records, lut, refresh, got.data_crc)
                    if i + 1 == n and not any(op == OP_DATA_END for op, _, _ in got.records):
                        raise self._corrupt(CorruptMcap("no DataEnd record at the end of the data section"))
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
                    if self.declared.register(buf, [(op, pos, ln)]):
                        refresh()
                elif op == OP_CHUNK:  # not in the chunk index
                    chunk = Chunk.read(record_body(buf, pos, ln))
                    data = self._decompress(chunk, base + pos)
                    j = k
                    while j < len(records) and records[j][0] == OP_MESSAGE_INDEX:
                        j += 1
                    index = message_index_offsets(buf, records[k:j])
                    k = j
                    yield 0, self._chunk_batch(base + pos, data, index, lut, refresh)
                elif op == OP_DATA_END:
                    expected = DataEnd.read(record_body(buf, pos, ln)).data_section_crc
                    if expected and data_crc is not None and expected != data_crc:
                        raise self._corrupt(CorruptMcap("data section CRC mismatch (DataEnd)"))
        except (CorruptMcap, *PARSE_ERRORS) as err:
            raise self._corrupt(err, f" (record at byte {base + pos})") from None
        if loose:
            yield 0, self._batch(buf, np.asarray(loose, dtype=np.int64), lut)

    def _chunk_batch(self, offset: int, data: bytes, index: np.ndarray | None, lut: np.ndarray,
                     refresh: Callable[[], None]) -> MessageBatch:
        """Batch of the selected messages of a decompressed chunk (``index``: its Message Index offsets)."""
        arr = np.frombuffer(data, dtype=np.uint8)
        try:
            off, others = locate_messages(data, arr, index)
            if others and self.declared.register(data, others):
                refresh()
        except (CorruptMcap, *PARSE_ERRORS) as err:
            raise self._chunk_error(offset, str(err)) from None
        return self._batch(data, off, lut, arr)

    def _batch(self, data: bytes, off: np.ndarray, lut: np.ndarray, arr: np.ndarray | None = None) -> MessageBatch:
        """Batch of the selected message records at offsets ``off`` of ``data``."""
        try:
            return message_batch(data, off, lut, arr)
        except ValueError as err:
            raise RecordingError(f"{self.path}: {err}") from None
