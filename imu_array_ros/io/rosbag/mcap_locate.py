"""Locating MCAP message records inside a block of records, with numpy.

Knows nothing about the container or message semantics: given the bytes of
a decompressed chunk (or of the top-level records between chunks) it finds
*where* the Message records are and hands their payloads out as one
:class:`MessageBatch` (buffer, offsets, lengths, log times).

Inside a chunk the message records are located from the chunk's Message
Index records (:func:`message_index_offsets`, vectorized), then every byte
of the chunk not covered by an indexed message is walked
(:func:`walk_records`), so a partial index can not hide messages; an absent
or inconsistent index falls back to a walk of the whole chunk
(:func:`locate_messages`).  Top-level records are walked the same way
(:func:`ordered_records`).  Malformed bytes raise ValueError.

The container (footer, summary, chunks, decompression, CRCs) is
:mod:`imu_array_ros.io.rosbag.mcap_reader`; the CDR payloads are decoded by
:mod:`imu_array_ros.io.rosbag.cdr_columns`; format constants:
:mod:`imu_array_ros.io.rosbag.mcap_format`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imu_array_ros.io.rosbag.cdr_columns import gather_bytes
from imu_array_ros.io.rosbag.mcap_format import MESSAGE_HEAD, MESSAGE_HEAD_SIZE, OP_MESSAGE, RECORD_HEAD, U32

__all__ = [
    "MessageBatch",
    "walk_records",
    "ordered_records",
    "message_index_offsets",
    "locate_messages",
    "message_batch",
]


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


def walk_records(buf, start: int, end: int) -> tuple[list[int], list[tuple[int, int, int]]]:
    """Walk the records in ``buf[start:end]``.

    Returns (offsets of Message records, [(opcode, offset, body length)] of the
    other records), offsets into ``buf``.  Raises ValueError when a record runs
    past ``end``.
    """
    messages: list[int] = []
    others: list[tuple[int, int, int]] = []
    unpack = RECORD_HEAD.unpack_from
    pos = start
    while pos < end:
        if pos + 9 > end:
            raise ValueError(f"record header at byte {pos} runs past the end")
        op, ln = unpack(buf, pos)
        nxt = pos + 9 + ln
        if nxt > end:
            raise ValueError(f"record (opcode 0x{op:02x}) at byte {pos} runs past the end")
        if op == OP_MESSAGE:
            messages.append(pos)
        else:
            others.append((op, pos, ln))
        pos = nxt
    return messages, others


def ordered_records(buf, start: int, end: int) -> list[tuple[int, int, int]]:
    """(opcode, offset, body length) of every record in ``buf[start:end]``, in file order."""
    messages, others = walk_records(buf, start, end)
    if not messages:
        return others
    return sorted(others + [(OP_MESSAGE, p, int(RECORD_HEAD.unpack_from(buf, p)[1])) for p in messages], key=lambda r: r[1])


def message_index_offsets(buf, records: list[tuple[int, int, int]]) -> np.ndarray | None:
    """Record offsets (int64) listed by the Message Index records ``records`` of ``buf``."""
    parts = []
    for _, pos, ln in records:
        (n,) = U32.unpack_from(buf, pos + 11)  # body: channel id (u16), entries length (u32), entries
        if n % 16 or 6 + n > ln:
            raise ValueError(f"malformed message index at byte {pos}")
        if n:
            parts.append(np.frombuffer(buf, dtype="<u8", count=n // 8, offset=pos + 15).reshape(-1, 2)[:, 1])
    if not parts:
        return None
    off = np.concatenate(parts)
    if off.max() > np.iinfo(np.int64).max:
        return None
    return off.astype(np.int64)


def locate_messages(
    buf: bytes, arr: np.ndarray, indexed: np.ndarray | None
) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Message record offsets (sorted, file order) and the other records of one decompressed chunk.

    buf, arr: the chunk records as bytes and as (S,) uint8 view; indexed (K,)
    int64: record offsets from the chunk's Message Index (any order, may be
    partial), or None.  Indexed offsets are checked in one vectorized pass;
    the bytes they do not cover are walked.  An inconsistent index falls back
    to walking the whole chunk.  Raises ValueError for a malformed chunk.
    """
    size = len(buf)
    if indexed is not None and len(indexed) and size >= 9:
        off = np.sort(indexed)
        if off[0] >= 0 and off[-1] <= size - 9 and (len(off) < 2 or (np.diff(off) > 0).all()):
            head = gather_bytes(arr, off, 9)
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
                            m, o = walk_records(buf, int(gap_start[g]), int(gap_end[g]))
                            extra += m
                            others += o
                    except ValueError:
                        pass  # inconsistent index: fall back to a full walk
                    else:
                        if extra:
                            off = np.sort(np.concatenate((off, np.asarray(extra, dtype=np.int64))))
                        return off, others
    messages, others = walk_records(buf, 0, size)
    return np.asarray(messages, dtype=np.int64), others


def message_batch(data: bytes, off: np.ndarray, lut: np.ndarray, arr: np.ndarray | None = None) -> MessageBatch:
    """Batch of the selected message records at offsets ``off`` (K,) int64 of ``data``.

    lut (65536,) int32: channel id -> selection index, -1 skips the channel.
    arr: ``data`` as (S,) uint8 if already at hand.  Raises ValueError for a
    record running past ``data`` or shorter than its header.
    """
    if arr is None:
        arr = np.frombuffer(data, dtype=np.uint8)
    if len(off) and off[-1] + MESSAGE_HEAD_SIZE > len(arr):
        raise ValueError(f"corrupt message record at byte {int(off[-1])}")
    head = np.ascontiguousarray(gather_bytes(arr, off, MESSAGE_HEAD_SIZE)).view(MESSAGE_HEAD).reshape(-1)
    if len(head) and ((head["len"] < 22).any() or (off + 9 + head["len"].astype(np.int64) > len(arr)).any()):
        raise ValueError("corrupt message record (shorter than its header or running past its chunk)")
    topic = lut[head["channel"]]
    keep = topic >= 0
    return MessageBatch(
        buffer=arr,
        topic=topic[keep],
        log_time=head["log_time"][keep].astype(np.int64),
        offset=off[keep] + MESSAGE_HEAD_SIZE,
        length=head["len"][keep].astype(np.int64) - 22,
    )
