"""Opening one MCAP file: magic, footer, summary CRC, summary and chunk index; the schemas and channels it declares.

Container (the ``mcap`` library): the footer and summary
(``SeekingReader.get_summary``) and every record's fields.  The summary CRC
(footer) is verified; a CRC of 0 means "not computed" (MCAP spec) and is not
checked.  The chunk index entries must lie in the data section, in order and
without overlap.  A file whose summary has no chunk index (no summary,
unchunked, or chunk indexes not written) is streamed
(:mod:`imu_array_ros.io.rosbag.mcap_stream`).

A file without footer (a recorder killed mid-write) is refused with a one-line
error naming ``imu-array recover`` (:func:`recover_command`;
:func:`imu_array_ros.io.rosbag.recover.recover_recording`).

Reading the file: :mod:`imu_array_ros.io.rosbag.mcap_reader`.
"""

from __future__ import annotations

import io
import os
import shlex
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.reader import FOOTER_SIZE, SeekingReader
from mcap.records import Channel, ChunkIndex, Footer, Header, Schema
from mcap.stream_reader import MAGIC_SIZE, StreamReader, read_magic

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.rosbag.mcap_format import OP_CHANNEL, OP_HEADER, OP_SCHEMA

__all__ = [
    "ChannelInfo",
    "CorruptMcap",
    "FileLayout",
    "McapDeclarations",
    "PARSE_ERRORS",
    "read_layout",
    "record_body",
    "recover_command",
]

#: Errors the mcap library and struct raise on malformed bytes.
PARSE_ERRORS = (McapError, struct.error, ValueError, IndexError, OverflowError, KeyError)


class CorruptMcap(Exception):
    """A structural problem; the reader translates it into RecordingError with file context."""


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


def record_body(buf, pos: int, ln: int) -> ReadDataStream:
    """Library record reader over the body of the record at ``buf[pos]`` (opcode offset)."""
    return ReadDataStream(io.BytesIO(bytes(memoryview(buf)[pos + 9 : pos + 9 + ln])))


class McapDeclarations:
    """What one file declares: ``schemas`` id -> (name, encoding); ``channels`` id ->
    :class:`ChannelInfo` (those of the summary, then those met while reading); ``profile``
    (the Header record's)."""

    def __init__(self) -> None:
        self.schemas: dict[int, tuple[str, str]] = {}
        self.channels: dict[int, ChannelInfo] = {}
        self.profile = ""

    def add_channel(self, ch: Channel) -> None:
        sname, senc = self.schemas.get(ch.schema_id, ("", ""))
        self.channels[ch.id] = ChannelInfo(ch.id, ch.topic, ch.message_encoding, sname, senc, dict(ch.metadata))

    def add_schema(self, schema: Schema) -> None:
        self.schemas[schema.id] = (schema.name, schema.encoding)

    def register(self, buf, records: list[tuple[int, int, int]]) -> bool:
        """Parse the Header / Schema / Channel records among ``records``; True if a channel was added."""
        added = False
        for op, pos, ln in records:
            if op == OP_SCHEMA:
                self.add_schema(Schema.read(record_body(buf, pos, ln)))
            elif op == OP_CHANNEL:
                self.add_channel(Channel.read(record_body(buf, pos, ln)))
                added = True
            elif op == OP_HEADER:
                self.profile = Header.read(record_body(buf, pos, ln)).profile
        return added


@dataclass
class FileLayout:
    """Where things are in one MCAP file, from its footer and summary.

    size: bytes; chunks: the summary's chunk index records (``mcap.records.ChunkIndex``)
    sorted by file offset, empty when the file is streamed; has_summary: the summary
    lists the channels; indexed: read by seeking chunk by chunk (else streamed);
    data_end: the data section ends here (the summary starts; 0 without a summary).
    """

    size: int
    chunks: list[ChunkIndex] = field(default_factory=list)
    has_summary: bool = False
    indexed: bool = False
    data_end: int = 0


def _raw_capture_hint(head: bytes, path: Path) -> str:
    """'; it looks like a raw OpenShoe serial capture: ...' when ``head`` (the file's first bytes) holds an
    OpenShoe acknowledgement or several data-packet headers (``A0 28`` / ``AA``), else ''."""
    looks = head.startswith(b"\xa0") or head.count(b"\xaa") >= 8 or Path(path).suffix.lower() == ".bin"
    if not looks:
        return ""
    return (f"; if it is a raw OpenShoe serial capture, turn it into a recording first: imu-array import-openshoe "
            f"{path} --array A.yaml --out rec.mcap")


def read_layout(fh: BinaryIO, path: Path, source: Path, declared: McapDeclarations) -> FileLayout:
    """Check the magic, footer and summary CRC of the open file ``fh`` and read its summary into ``declared``.

    Raises :class:`RecordingError` (one line naming ``path``; the ``imu-array recover`` hint names
    ``source``) for a file that is not MCAP or has no footer, :class:`CorruptMcap` or one of
    :data:`PARSE_ERRORS` for a damaged footer, summary or chunk index.
    """
    size = os.fstat(fh.fileno()).st_size
    try:
        read_magic(ReadDataStream(fh))
    except (InvalidMagic, EndOfFile, struct.error):
        fh.seek(0)
        if fh.read(8) == b"SQLite f":
            raise RecordingError(
                f"{path}: sqlite3 rosbag2 storage is not supported; convert to mcap (`ros2 bag convert`)"
            ) from None
        fh.seek(0)
        raise RecordingError(f"{path}: not an MCAP file (bad magic){_raw_capture_hint(fh.read(4096), path)}") from None
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
            f"{path}: truncated MCAP file (no footer/summary: was the recorder stopped before "
            f"closing it?); salvage it with {recover_command(source)}"
        )
    fh.seek(footer_pos)
    footer = next(iter(StreamReader(fh, skip_magic=True).records), None)
    if not isinstance(footer, Footer):
        raise CorruptMcap("no footer record before the end magic")
    summary_start = footer.summary_start
    if summary_start and not MAGIC_SIZE <= summary_start <= footer_pos:
        raise CorruptMcap("summary offset outside the file")
    if footer.summary_crc:
        start = summary_start or footer_pos
        fh.seek(start)
        crc = zlib.crc32(fh.read(size - MAGIC_SIZE - 4 - start))  # through the footer's summary_offset_start
        if crc != footer.summary_crc:
            raise CorruptMcap("summary CRC mismatch (the summary / index section is damaged)")
    if not summary_start:
        return FileLayout(size)  # no summary: streamed
    fh.seek(0)
    summary = SeekingReader(fh).get_summary()
    if summary is None:
        return FileLayout(size)
    for sid, schema in summary.schemas.items():
        declared.schemas[sid] = (schema.name, schema.encoding)
    for channel in summary.channels.values():
        declared.add_channel(channel)
    has_summary = bool(declared.channels)  # the summary repeats the channels
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    prev = MAGIC_SIZE
    for c in chunks:
        if c.chunk_start_offset < prev or c.chunk_length < 9 or c.chunk_start_offset + c.chunk_length > summary_start:
            raise CorruptMcap(f"chunk index entry for byte {c.chunk_start_offset} overlaps or leaves the data section")
        prev = c.chunk_start_offset + c.chunk_length
    return FileLayout(size, chunks, has_summary, bool(chunks), summary_start)
