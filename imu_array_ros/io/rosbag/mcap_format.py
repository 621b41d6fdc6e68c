"""MCAP container format pieces shared by our writer and the reader's message location.

Magic and record opcodes (the values of :class:`mcap.opcode.Opcode`), the
``struct`` formats of little-endian integers (:data:`U16`, :data:`U32`,
:data:`U64`) and of a record's (opcode, length) head (:data:`RECORD_HEAD`),
the fixed 31-byte head of a Message record as a numpy dtype
(:data:`MESSAGE_HEAD`, :data:`MESSAGE_HEAD_SIZE`), the chunk compression
defaults of files we write (:data:`DEFAULT_COMPRESSION`,
:data:`DEFAULT_CHUNK_SIZE`, :data:`ZSTD_LEVEL`) and the chunk compressor
lookup (:func:`compressor`).  Decompression and the parsing of the container
itself are the ``mcap`` library's (see :mod:`imu_array_ros.io.rosbag.mcap_reader`).

Reading: :mod:`imu_array_ros.io.rosbag.mcap_reader` (container) and
:mod:`imu_array_ros.io.rosbag.mcap_locate` (message location); writing:
:mod:`imu_array_ros.io.rosbag.mcap_writer`.
"""

from __future__ import annotations

import struct
from typing import Callable

import numpy as np
from mcap.opcode import Opcode

__all__ = [
    "MAGIC",
    "OP_HEADER",
    "OP_FOOTER",
    "OP_SCHEMA",
    "OP_CHANNEL",
    "OP_MESSAGE",
    "OP_CHUNK",
    "OP_MESSAGE_INDEX",
    "OP_CHUNK_INDEX",
    "OP_STATISTICS",
    "OP_METADATA",
    "OP_METADATA_INDEX",
    "OP_SUMMARY_OFFSET",
    "OP_DATA_END",
    "U16",
    "U32",
    "U64",
    "RECORD_HEAD",
    "MESSAGE_HEAD",
    "MESSAGE_HEAD_SIZE",
    "DEFAULT_COMPRESSION",
    "DEFAULT_CHUNK_SIZE",
    "ZSTD_LEVEL",
    "compressor",
]

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = int(Opcode.HEADER)
OP_FOOTER = int(Opcode.FOOTER)
OP_SCHEMA = int(Opcode.SCHEMA)
OP_CHANNEL = int(Opcode.CHANNEL)
OP_MESSAGE = int(Opcode.MESSAGE)
OP_CHUNK = int(Opcode.CHUNK)
OP_MESSAGE_INDEX = int(Opcode.MESSAGE_INDEX)
OP_CHUNK_INDEX = int(Opcode.CHUNK_INDEX)
OP_STATISTICS = int(Opcode.STATISTICS)
OP_METADATA = int(Opcode.METADATA)
OP_METADATA_INDEX = int(Opcode.METADATA_INDEX)
OP_SUMMARY_OFFSET = int(Opcode.SUMMARY_OFFSET)
OP_DATA_END = int(Opcode.DATA_END)

#: Chunk compression of files we write.  Measured (benchmarks/results/recording_io.md,
#: 1.92 M Imu messages): lz4 costs the least CPU to read among the compressed options and
#: writes fastest; zstd (level 1) is ~1.25x smaller but ~10 % more read CPU; none is ~5x larger.
#: Both rosbags and the mcap library read all three.
DEFAULT_COMPRESSION = "lz4"
DEFAULT_CHUNK_SIZE = 4 * 1024 * 1024
ZSTD_LEVEL = 1

U16 = struct.Struct("<H")
U32 = struct.Struct("<I")
U64 = struct.Struct("<Q")
#: Head of every record: opcode (uint8), length of the record body in bytes (uint64).
RECORD_HEAD = struct.Struct("<BQ")

#: Message record head: opcode, record length, channel id, sequence, log time (ns), publish time (ns).
MESSAGE_HEAD = np.dtype(
    {
        "names": ["op", "len", "channel", "sequence", "log_time", "publish_time"],
        "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
        "offsets": [0, 1, 9, 11, 15, 23],
        "itemsize": 31,
    }
)
#: The payload starts this many bytes after a Message record's opcode byte; the record
#: length counts 22 of them (channel id, sequence, log and publish time) plus the payload.
MESSAGE_HEAD_SIZE = 31


def compressor(name: str) -> Callable[[bytes], bytes]:
    """Chunk compressor ``bytes -> bytes`` for ``name`` in (``zstd``, ``lz4``, ``none``)."""
    if name == "none":
        return lambda data: data
    if name == "zstd":
        try:
            import zstandard

            cctx = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
            return cctx.compress
        except ImportError:  # pragma: no cover - rosbags brings backports.zstd
            from backports import zstd as _z  # type: ignore[import-not-found]

            return lambda data: _z.compress(data, level=ZSTD_LEVEL)
    if name == "lz4":
        import lz4.frame

        return lambda data: lz4.frame.compress(data)
    raise ValueError(f"unknown chunk compression {name!r} (zstd, lz4, none)")
