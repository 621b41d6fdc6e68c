"""Reading selected topics of a recording as decoded columns, with the topic checks.

:func:`read_topics` decodes every message of the requested topics (each
with its fixed CDR :class:`~imu_array_ros.io.rosbag.cdr_columns.MessageLayout`)
into :class:`TopicColumns`, one per message type, in file order, and runs a
caller's check of the recording's topics before the messages are read when
the summaries list every channel (else after, so each chunk is decompressed
once).  :func:`check_topic` and :func:`list_topics` are the pieces such
checks are made of.  Whole chunks are decoded column-wise
(:meth:`McapRecording.iter_batches`,
:func:`~imu_array_ros.io.rosbag.cdr_columns.decode_columns`); there is no
per-message Python.

What the topics mean (IMU data, ground truth, fused output):
:mod:`imu_array_ros.io.rosbag.recording`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping, Sequence, TypeVar

import numpy as np

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.cdr_columns import MessageLayout, decode_columns
from imu_array_ros.io.rosbag.mcap_recording import McapRecording
from imu_array_ros.io.rosbag.mcap_summary import ChannelInfo

__all__ = ["TopicColumns", "list_topics", "check_topic", "read_topics"]

T = TypeVar("T")


@dataclass
class TopicColumns:
    """Decoded messages of the topics sharing one message type, file order.

    topic (M,) int32 index into the requested topics; stamps (M,) int64 ns;
    valid (M,) bool (layout decodable); encap_ok (M,) bool; fields name -> (M, n).
    """

    topic: np.ndarray
    stamps: np.ndarray
    valid: np.ndarray
    encap_ok: np.ndarray
    fields: dict[str, np.ndarray]


def list_topics(available: Mapping[str, list[ChannelInfo]], limit: int = 12) -> str:
    """The topic names of ``available``, sorted, at most ``limit`` of them (for error messages)."""
    names = sorted(available)
    if not names:
        return "no topics"
    more = f", ... ({len(names) - limit} more)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def check_topic(rec: McapRecording, available, topic: str, type_name: str, what: str) -> bool:
    """True if ``topic`` exists with ``type_name`` (cdr); raise on a wrong type; False if absent."""
    chans = available.get(topic)
    if not chans:
        return False
    if not any(c.schema_name == type_name and c.message_encoding == "cdr" for c in chans):
        got = ", ".join(sorted({f"{c.schema_name or '<no schema>'} ({c.message_encoding})" for c in chans}))
        raise RecordingError(f"{rec.path}: topic {topic} {what} has type {got}, expected {type_name} (cdr)")
    return True


def _collect(
    rec: McapRecording,
    topics: Sequence[tuple[str, MessageLayout]],
    fields: Mapping[str, Sequence[str]],
    progress: Callable[[float], None] | None = None,
) -> dict[str, TopicColumns]:
    """Decode every message of ``topics`` ((topic, layout) pairs), grouped by type name."""
    select = {t: layout.type_name for t, layout in topics}
    layouts = {layout.type_name: layout for _, layout in topics}
    members = {
        name: np.array([i for i, (_, lay) in enumerate(topics) if lay.type_name == name], dtype=np.int32)
        for name in layouts
    }
    parts: dict[str, list] = {name: [] for name in layouts}
    for batch in rec.iter_batches(select, progress=progress):
        for name, layout in layouts.items():
            if len(layouts) == 1:
                sub = slice(None)
                topic = batch.topic
            else:
                sub = np.isin(batch.topic, members[name])
                if not sub.any():
                    continue
                topic = batch.topic[sub]
            dec = decode_columns(layout, batch.buffer, batch.offset[sub], batch.length[sub], fields[name])
            parts[name].append((topic, dec))
    out: dict[str, TopicColumns] = {}
    for name, layout in layouts.items():
        got = parts[name]
        names = list(fields[name])
        if not got:
            out[name] = TopicColumns(
                np.zeros(0, np.int32),
                np.zeros(0, np.int64),
                np.zeros(0, bool),
                np.zeros(0, bool),
                {f: np.zeros((0, layout.fields[f][1])) for f in names},
            )
            continue
        out[name] = TopicColumns(
            topic=np.concatenate([t for t, _ in got]),
            stamps=np.concatenate([d.stamps for _, d in got]),
            valid=np.concatenate([d.valid for _, d in got]),
            encap_ok=np.concatenate([d.encapsulation_ok for _, d in got]),
            fields={f: np.concatenate([d.fields[f] for _, d in got]) for f in names},
        )
    return out


def read_topics(
    rec: McapRecording,
    topics: Sequence[tuple[str, MessageLayout]],
    fields: Mapping[str, Sequence[str]],
    check: Callable[[Mapping[str, list[ChannelInfo]]], T],
    progress: Callable[[float], None] | None = None,
) -> tuple[T, dict[str, TopicColumns]]:
    """Check the recording's topics with ``check(available)`` and decode ``topics`` (see :func:`_collect`).

    When the summaries list every channel the check runs first (a wrong or
    missing topic fails before any message is read); otherwise the messages
    are read first and the check uses the channels met on the way, so each
    chunk is decompressed once.  Returns (what ``check`` returned, columns).
    """
    if rec.topics_known:
        checked = check(rec.topics())
        return checked, _collect(rec, topics, fields, progress)
    cols = _collect(rec, topics, fields, progress)
    return check(rec.topics()), cols
