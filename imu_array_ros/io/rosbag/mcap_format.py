"""MCAP container format pieces shared by the reader and the writer.

Magic, record opcodes, the ``struct`` formats of little-endian integers and of
a record's (opcode, length) head, the fixed 31-byte head of a Message record
as a numpy dtype, the chunk compression defaults of files we write
(:data:`DEFAULT_COMPRESSION`, :data:`DEFAULT_CHUNK_SIZE`, :data:`ZSTD_LEVEL`)
and the chunk compressor / decompressor lookups (``zstd``, ``lz4`` or none).

Reading: :mod:`imu_array_ros.io.rosbag.mcap_reader`; writing:
:mod:`imu_array_ros.io.rosbag.mcap_writer`.
"""

from __future__ import annotations

import struct
from functools import lru_cache
from typing import Callable

import numpy as np

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
    "DEFAULT_COMPRESSION",
    "DEFAULT_CHUNK_SIZE",
    "ZSTD_LEVEL",
]

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_STATISTICS = 0x0B
OP_METADATA = 0x0C
OP_METADATA_INDEX = 0x0D
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F

#: Chunk compression of files we write.  Measured (benchmarks/results/recording_io.md,
#: 1.92 M Imu messages): lz4 costs the least CPU to read among the compressed options and
#: writes fastest; zstd (level 1) is ~1.25x smaller but ~10 % more read CPU; none is ~5x larger.
#: Both rosbags and the mcap library read all three.
DEFAULT_COMPRESSION = "lz4"
DEFAULT_CHUNK_SIZE = 4 * 1024 * 1024
ZSTD_LEVEL = 1

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_REC = struct.Struct("<BQ")

#: Message record: opcode, record length, channel id, sequence, log time, publish time.
_MSG_HEAD = np.dtype(
    {
        "names": ["op", "len", "channel", "sequence", "log_time", "publish_time"],
        "formats": ["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
        "offsets": [0, 1, 9, 11, 15, 23],
        "itemsize": 31,
    }
)
_MSG_HEAD_SIZE = 31  # payload starts 31 bytes after the record's opcode byte


# --------------------------------------------------------------------------- compression


def _zstd_decompress() -> Callable[[bytes, int], bytes]:
    try:  # Python >= 3.14
        from compression import zstd as _z  # type: ignore[import-not-found]
    except ImportError:
        try:
            from backports import zstd as _z  # type: ignore[import-not-found,no-redef]
        except ImportError:
            _z = None
    if _z is not None:
        return lambda data, size: _z.decompress(data)
    import io

    import zstandard  # a decompression context per call: contexts are not thread-safe

    def decompress(data: bytes, size: int) -> bytes:  # stream API: handles multi-frame chunks
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True) as r:
            return r.read(size + 1)

    return decompress


def _lz4_decompress() -> Callable[[bytes, int], bytes]:
    import lz4.frame

    return lambda data, size: lz4.frame.decompress(data)


@lru_cache(maxsize=None)
def _decompressor(name: str) -> Callable[[bytes, int], bytes] | None:
    if name == "":
        return lambda data, size: bytes(data)
    if name == "zstd":
        return _zstd_decompress()
    if name == "lz4":
        return _lz4_decompress()
    return None


def _compressor(name: str) -> Callable[[bytes], bytes]:
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
