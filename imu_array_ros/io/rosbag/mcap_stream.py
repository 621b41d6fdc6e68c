"""Reading an MCAP file without a chunk index: every record streamed once with the ``mcap`` library.

Files whose summary has no chunk index (no summary, unchunked, or chunk
indexes not written) are read front to back with ``StreamReader``
(``validate_crcs=True``: chunk CRCs and the data-section CRC of the DataEnd
record; a CRC of 0 is not checked).  Chunks are handed to the reader's batch
builder with the Message Index records that follow them; messages outside
chunks are batched here (:func:`library_message_batch`).

Files with a chunk index are read by seeking:
:class:`imu_array_ros.io.rosbag.mcap_reader.McapFile`.
"""

from __future__ import annotations

from typing import BinaryIO, Callable, Iterator

import numpy as np
from mcap.records import Channel, Chunk, DataEnd, Header, Message, MessageIndex, Schema
from mcap.stream_reader import CRCValidationError, StreamReader

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_locate import MessageBatch
from imu_array_ros.io.rosbag.mcap_summary import PARSE_ERRORS, CorruptMcap, McapDeclarations

__all__ = ["library_message_batch", "streamed_batches"]

_LOOSE_BATCH = 1 << 16  # messages outside chunks handed out per batch when streaming


def streamed_batches(
    fh: BinaryIO,
    size: int,
    declared: McapDeclarations,
    lut: np.ndarray,
    refresh: Callable[[], None],
    *,
    decompress: Callable[[Chunk, int], bytes],
    chunk_batch: Callable[[int, bytes, np.ndarray | None, np.ndarray, Callable[[], None]], MessageBatch],
    corrupt: Callable[..., RecordingError],
) -> Iterator[tuple[int, MessageBatch]]:
    """No chunk index: stream every record once (``StreamReader``, data-section CRC checked).

    Yields (file bytes consumed, batch) in file order, like
    :meth:`~imu_array_ros.io.rosbag.mcap_reader.McapFile.iter_batches`.  ``fh``: the open file
    of ``size`` bytes; schemas, channels and the profile met go to ``declared`` (``refresh()``
    after a channel); ``lut``: channel id -> selection index (-1: skip).  The reader supplies
    ``decompress(chunk, offset)`` (checked records of a chunk), ``chunk_batch(offset, data,
    index, lut, refresh)`` (the batch of a decompressed chunk) and ``corrupt(err, where)`` (the
    RecordingError naming the file).
    """
    fh.seek(0)
    reader = StreamReader(fh, emit_chunks=True, validate_crcs=True)
    done = 0
    pending: tuple[int, bytes, list] | None = None  # (offset, data, index parts) of the last chunk
    loose: list[Message] = []

    def flush_chunk() -> MessageBatch:
        offset, data, parts = pending
        index = np.concatenate(parts).astype(np.int64) if parts else None
        return chunk_batch(offset, data, index, lut, refresh)

    def flush_loose() -> MessageBatch:
        batch = library_message_batch(loose, lut)
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
                pending = (pos, decompress(record, pos), [])
            elif isinstance(record, Schema):
                declared.add_schema(record)
            elif isinstance(record, Channel):
                declared.add_channel(record)
                refresh()
            elif isinstance(record, Header):
                declared.profile = record.profile
            pos = fh.tell()
    except CRCValidationError as err:
        if isinstance(err.record, DataEnd):
            raise corrupt(CorruptMcap("data section CRC mismatch (DataEnd)")) from None
        raise corrupt(err, f" (record at byte {pos})") from None
    except (CorruptMcap, *PARSE_ERRORS) as err:
        raise corrupt(err, f" (record at byte {pos})") from None
    if pending is not None:
        yield fh.tell() - done, flush_chunk()
    if loose:
        yield 0, flush_loose()
    yield max(size - fh.tell(), 0), library_message_batch([], lut)


def library_message_batch(messages: list[Message], lut: np.ndarray) -> MessageBatch:
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
