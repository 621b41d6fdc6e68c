"""Columnar CDR encode/decode of ``sensor_msgs/msg/Imu`` and
``geometry_msgs/msg/AccelWithCovarianceStamped`` (pure numpy).

Both messages are a ``std_msgs/Header`` followed only by ``float64`` fields, so
for a given ``header.frame_id`` length every message of a topic has the same
byte layout.  Decoding therefore gathers the few fixed-offset byte ranges a
caller needs from many messages at once (one fancy-indexing operation per
field over a whole MCAP chunk) instead of deserializing message by message;
encoding fills a numpy structured array whose dtype *is* the CDR layout.

Only little-endian plain CDR (XCDR1, encapsulation ``00 01``, what ROS 2 Jazzy
rmw implementations publish) is decoded.  Anything else -- another
encapsulation, a payload whose length does not match the layout implied by its
frame_id length, a frame_id without NUL terminator, ``nanosec >= 1e9`` -- is
reported as invalid per message, never decoded into numbers.

Byte layout (offsets in bytes).  CDR aligns primitives to their size relative
to the end of the 4-byte encapsulation header, so below offsets are given
relative to ``payload[4:]``; ``n = len(frame_id.encode()) + 1`` (the string
length field counts the NUL) and ``b = align8(12 + n)``::

    payload[0:4]  encapsulation header 00 01 00 00 (CDR, little endian)
    -- relative to payload[4:] --
    0      int32       header.stamp.sec
    4      uint32      header.stamp.nanosec
    8      uint32      n
    12     n bytes     frame_id, NUL, then zero padding up to b

    sensor_msgs/msg/Imu                      total length 4 + b + 296
    b+0    float64[4]  orientation x y z w
    b+32   float64[9]  orientation_covariance (row-major 3x3)
    b+104  float64[3]  angular_velocity x y z          rad/s
    b+128  float64[9]  angular_velocity_covariance
    b+200  float64[3]  linear_acceleration x y z       m/s^2
    b+224  float64[9]  linear_acceleration_covariance

    geometry_msgs/msg/AccelWithCovarianceStamped   total length 4 + b + 336
    b+0    float64[3]  accel.accel.linear x y z        m/s^2
    b+24   float64[3]  accel.accel.angular x y z       rad/s^2
    b+48   float64[36] accel.covariance (6x6 row-major, [linear, angular])

Stamps are carried as int64 nanoseconds ``sec * 1e9 + nanosec``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

__all__ = [
    "IMU_FIELDS",
    "ACCEL_FIELDS",
    "CDR_LE",
    "MessageLayout",
    "IMU_LAYOUT",
    "ACCEL_LAYOUT",
    "DecodedColumns",
    "encode_columns",
    "decode_columns",
    "encode_imu",
    "decode_imu",
    "encode_accel_with_covariance_stamped",
    "decode_accel_with_covariance_stamped",
    "split_stamps",
    "join_stamps",
    "gather_bytes",
    "back_to_back",
]

#: Encapsulation header of little-endian plain CDR (XCDR1).
CDR_LE = bytes((0x00, 0x01, 0x00, 0x00))

_NS = 1_000_000_000
_INT32_MIN, _INT32_MAX = int(np.iinfo(np.int32).min), int(np.iinfo(np.int32).max)

#: Imu float64 fields: name -> (offset from ``b``, number of float64).
IMU_FIELDS: dict[str, tuple[int, int]] = {
    "orientation": (0, 4),
    "orientation_covariance": (32, 9),
    "angular_velocity": (104, 3),
    "angular_velocity_covariance": (128, 9),
    "linear_acceleration": (200, 3),
    "linear_acceleration_covariance": (224, 9),
}

#: AccelWithCovarianceStamped float64 fields: name -> (offset from ``b``, count).
ACCEL_FIELDS: dict[str, tuple[int, int]] = {
    "linear": (0, 3),
    "angular": (24, 3),
    "covariance": (48, 36),
}


@dataclass(frozen=True)
class MessageLayout:
    """A header-plus-float64 message: field table and body size after ``b``."""

    type_name: str
    fields: Mapping[str, tuple[int, int]]
    body_size: int

    def base(self, frame_len: np.ndarray | int) -> np.ndarray | int:
        """``b = align8(12 + n)`` for string length field(s) ``n`` (incl. NUL)."""
        return (12 + frame_len + 7) // 8 * 8

    def payload_length(self, frame_len: np.ndarray | int) -> np.ndarray | int:
        """Total serialized length (encapsulation header included)."""
        return 4 + self.base(frame_len) + self.body_size

    def dtype(self, frame_id: bytes) -> np.dtype:
        """Structured dtype spelling out the whole payload for this frame_id."""
        n = len(frame_id) + 1
        b = int(self.base(n))
        names = ["encapsulation", "sec", "nanosec", "frame_len"]
        formats: list = [("u1", (4,)), "<i4", "<u4", "<u4"]
        offsets = [0, 4, 8, 12]
        if frame_id:
            names.append("frame_id")
            formats.append(("u1", (len(frame_id),)))
            offsets.append(16)
        for name, (off, count) in self.fields.items():
            names.append(name)
            formats.append(("<f8", (count,)))
            offsets.append(4 + b + off)
        return np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": int(self.payload_length(n))}
        )


IMU_LAYOUT = MessageLayout("sensor_msgs/msg/Imu", IMU_FIELDS, 296)
ACCEL_LAYOUT = MessageLayout("geometry_msgs/msg/AccelWithCovarianceStamped", ACCEL_FIELDS, 336)


# --------------------------------------------------------------------------- stamps


def split_stamps(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) int64 ns -> (sec int32, nanosec uint32) as builtin_interfaces/Time.

    Raises ValueError if a stamp does not fit an int32 second count.
    """
    stamps = np.asarray(stamps, dtype=np.int64)
    sec, nsec = np.divmod(stamps, _NS)
    if sec.size and (sec.min() < _INT32_MIN or sec.max() > _INT32_MAX):
        raise ValueError("stamp outside the int32-seconds range of builtin_interfaces/Time")
    return sec.astype(np.int32), nsec.astype(np.uint32)


def join_stamps(sec: np.ndarray, nanosec: np.ndarray) -> np.ndarray:
    """(sec, nanosec) -> (M,) int64 ns."""
    return sec.astype(np.int64) * _NS + nanosec.astype(np.int64)


# --------------------------------------------------------------------------- encode


def _column(value, m: int, count: int, name: str) -> np.ndarray:
    """A per-message (M, count) or constant (count,) field as an array a (M,) field assignment broadcasts."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape == (count,) or arr.shape == (m, count):
        return arr  # the field assignment broadcasts (count,)
    if arr.ndim >= 2 and arr.shape[0] == m and int(np.prod(arr.shape[1:])) == count:
        return arr.reshape(m, count)
    if arr.size == count:
        return arr.reshape(count)
    raise ValueError(f"{name}: shape {arr.shape} does not fit ({m}, {count}) or ({count},)")


def encode_columns(layout: MessageLayout, stamps: np.ndarray, frame_id: str, values: Mapping[str, object]) -> np.ndarray:
    """Serialize M messages of one topic.

    Parameters
    ----------
    layout : IMU_LAYOUT or ACCEL_LAYOUT
    stamps : (M,) int64 ns
    frame_id : header.frame_id (same for all M)
    values : field name -> (M, count) or (count,) float64; missing fields are zero.

    Returns
    -------
    (M, L) uint8, one CDR payload per row (L = ``layout.payload_length``).
    """
    unknown = set(values) - set(layout.fields)
    if unknown:
        raise ValueError(f"{layout.type_name} has no field(s) {sorted(unknown)}")
    fid = frame_id.encode("utf-8")
    if b"\x00" in fid:
        raise ValueError("frame_id must not contain NUL")
    stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
    m = len(stamps)
    template = _template(layout, fid)
    dt = template.dtype
    raw = np.empty((m, dt.itemsize), dtype=np.uint8)
    raw[:] = template.view(np.uint8)  # every byte: header and frame_id filled, fields and padding zero
    out = raw.view(dt).reshape(m)
    out["sec"], out["nanosec"] = split_stamps(stamps)
    for name, value in values.items():
        if value is not None:
            out[name] = _column(value, m, layout.fields[name][1], name)
    return raw


_TEMPLATES: dict[tuple[str, bytes], np.ndarray] = {}


def _template(layout: MessageLayout, frame_id: bytes) -> np.ndarray:
    """One message of ``layout`` with ``frame_id`` (1,) of its structured dtype: encapsulation header, frame_id
    length and bytes filled, everything else zero (built once per frame_id: the live node encodes a sample
    at a time, where building the dtype again costs more than the copy)."""
    key = (layout.type_name, frame_id)
    out = _TEMPLATES.get(key)
    if out is not None:
        return out
    out = np.zeros(1, dtype=layout.dtype(frame_id))
    out["encapsulation"] = np.frombuffer(CDR_LE, dtype=np.uint8)
    out["frame_len"] = len(frame_id) + 1
    if frame_id:
        out["frame_id"] = np.frombuffer(frame_id, dtype=np.uint8)
    out.flags.writeable = False
    if len(_TEMPLATES) < 256:
        _TEMPLATES[key] = out
    return out


def encode_imu(
    stamps: np.ndarray,
    frame_id: str,
    *,
    angular_velocity,
    linear_acceleration,
    angular_velocity_covariance=None,
    linear_acceleration_covariance=None,
    orientation=None,
    orientation_covariance=None,
) -> np.ndarray:
    """sensor_msgs/msg/Imu payloads, (M, L) uint8.

    Vectors (M, 3) or (3,); covariances (M, 9), (M, 3, 3) or (9,); orientation
    (M, 4) [x, y, z, w].  Omitted fields are zero.
    """
    return encode_columns(
        IMU_LAYOUT,
        stamps,
        frame_id,
        {
            "orientation": orientation,
            "orientation_covariance": orientation_covariance,
            "angular_velocity": angular_velocity,
            "angular_velocity_covariance": angular_velocity_covariance,
            "linear_acceleration": linear_acceleration,
            "linear_acceleration_covariance": linear_acceleration_covariance,
        },
    )


def encode_accel_with_covariance_stamped(stamps: np.ndarray, frame_id: str, *, linear, angular, covariance=None) -> np.ndarray:
    """geometry_msgs/msg/AccelWithCovarianceStamped payloads, (M, L) uint8.

    linear, angular (M, 3) or (3,); covariance (M, 36), (M, 6, 6) or (36,),
    row-major in ROS order [linear x y z, angular x y z].
    """
    return encode_columns(
        ACCEL_LAYOUT, stamps, frame_id, {"linear": linear, "angular": angular, "covariance": covariance}
    )


# --------------------------------------------------------------------------- decode


@dataclass
class DecodedColumns:
    """Columns decoded from M payloads of one message type.

    stamps (M,) int64 ns; valid (M,) bool -- False where the payload is not
    little-endian CDR of the expected layout (then every other column of that
    row is meaningless: stamps 0, floats NaN); encapsulation_ok (M,) bool --
    False where the encapsulation header was not ``00 01``; fields: name ->
    (M, count) float64 for the requested fields.
    """

    stamps: np.ndarray
    valid: np.ndarray
    encapsulation_ok: np.ndarray
    fields: dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        return self.fields[name]


def gather_bytes(buf: np.ndarray, start: np.ndarray, nbytes: int) -> np.ndarray:
    """(M, nbytes) uint8 rows ``buf[start[i] : start[i] + nbytes]`` for all i, in one indexing operation.

    buf (S,) uint8; start (M,) int, every ``start[i] + nbytes <= S`` (not checked).
    Also locates MCAP record heads in :mod:`imu_array_ros.io.rosbag.mcap_locate`.
    """
    if len(start) == 0:
        return np.empty((0, nbytes), dtype=np.uint8)
    return sliding_window_view(buf, nbytes)[start]


def decode_columns(
    layout: MessageLayout,
    buffer: np.ndarray,
    offset: np.ndarray,
    length: np.ndarray,
    fields: Sequence[str] | None = None,
) -> DecodedColumns:
    """Decode M payloads located at ``buffer[offset[i] : offset[i] + length[i]]``.

    Parameters
    ----------
    buffer : (S,) uint8, e.g. one decompressed MCAP chunk
    offset, length : (M,) int, payload start and size within ``buffer``
    fields : which float64 fields to return (default: all of the layout)
    """
    buf = np.asarray(buffer, dtype=np.uint8).reshape(-1)
    offset = np.asarray(offset, dtype=np.int64).reshape(-1)
    length = np.asarray(length, dtype=np.int64).reshape(-1)
    names = list(layout.fields) if fields is None else list(fields)
    for name in names:
        if name not in layout.fields:
            raise ValueError(f"{layout.type_name} has no field {name!r}")
    m = len(offset)
    if len(length) != m:
        raise ValueError("offset and length must have the same length")
    if m and (offset.min() < 0 or (offset + length).max() > len(buf)):
        raise ValueError("payload range outside buffer")

    rows = back_to_back(buf, offset, length)
    if rows is not None and rows.shape[1] >= 4 + 12 + 1 + layout.body_size:
        return _decode_uniform(layout, rows, names)
    valid = length >= 4 + 12 + 1 + layout.body_size
    safe = np.where(valid, offset, 0)
    if len(buf) < 4 + 12 + 1 + layout.body_size:  # nothing can be valid; keep gathers in range
        valid[:] = False
        buf = np.zeros(4 + 12 + 1 + layout.body_size, dtype=np.uint8)
        safe = np.zeros(m, dtype=np.int64)
    head = gather_bytes(buf, safe, 16)
    encap_ok = (head[:, 0] == 0x00) & (head[:, 1] == 0x01)
    hdr = np.ascontiguousarray(head[:, 4:16]).view(np.dtype([("sec", "<i4"), ("nanosec", "<u4"), ("n", "<u4")]))
    hdr = hdr.reshape(m)
    n = hdr["n"].astype(np.int64)
    base = layout.base(n)
    valid &= encap_ok & (n >= 1) & (length == 4 + base + layout.body_size) & (hdr["nanosec"] < _NS)
    safe = np.where(valid, offset, 0)
    base = np.where(valid, base, 0)
    # the frame_id string must be NUL-terminated (catches a shifted layout)
    nul = buf[np.where(valid, safe + 4 + 12 + n - 1, 0)]
    valid &= nul == 0
    safe = np.where(valid, offset, 0)
    base = np.where(valid, base, 0)

    stamps = np.where(valid, join_stamps(hdr["sec"], hdr["nanosec"]), 0)
    out: dict[str, np.ndarray] = {}
    field_start = safe + 4 + base
    for name in names:
        off, count = layout.fields[name]
        if m and not valid.any():
            out[name] = np.full((m, count), np.nan)
            continue
        raw = gather_bytes(buf, np.where(valid, field_start + off, 0), 8 * count)
        vals = np.ascontiguousarray(raw).view("<f8").reshape(m, count).astype(np.float64, copy=False)
        if not valid.all():
            vals = np.where(valid[:, None], vals, np.nan)
        out[name] = vals
    return DecodedColumns(stamps=stamps, valid=valid, encapsulation_ok=encap_ok, fields=out)


def back_to_back(buf: np.ndarray, offset: np.ndarray, length: np.ndarray) -> np.ndarray | None:
    """``buf`` as (M, L) rows when it holds exactly the M payloads, back to back, all of length L (what
    :func:`~imu_array_ros.io.messages.concat_payloads` makes of one sample's messages); else None."""
    m = len(offset)
    if not m or len(buf) != m * int(length[0]) or not (length == length[0]).all():
        return None
    if not (offset == np.arange(0, len(buf), int(length[0]))).all():
        return None
    return buf.reshape(m, int(length[0]))


_HEAD = np.dtype([("sec", "<i4"), ("nanosec", "<u4"), ("n", "<u4")])


def _decode_uniform(layout: MessageLayout, rows: np.ndarray, names: Sequence[str]) -> DecodedColumns:
    """:func:`decode_columns` of M back-to-back payloads of one length L, ``rows`` (M, L) uint8: the same
    checks and results in a few whole-array operations (the length fixes every field's offset; the live
    nodes decode a sample's messages at a time, where the general gathers cost more than the data)."""
    m, length = rows.shape
    hdr = np.ascontiguousarray(rows[:, 4:16]).view(_HEAD).reshape(m)
    n = hdr["n"].astype(np.int64)
    b = length - 4 - layout.body_size  # the base every valid payload of this length has
    valid = (rows[:, 0] == 0x00) & (rows[:, 1] == 0x01)
    encap_ok = valid.copy()
    valid &= (n >= 1) & (layout.base(n) == b) & (hdr["nanosec"] < _NS)
    # the frame_id string must be NUL-terminated (catches a shifted layout)
    valid &= rows[np.arange(m), np.where(valid, 15 + n, 0)] == 0
    stamps = join_stamps(hdr["sec"], hdr["nanosec"])
    every = bool(valid.all())
    if not every:
        stamps = np.where(valid, stamps, 0)
    out: dict[str, np.ndarray] = {}
    for name in names:
        off, count = layout.fields[name]
        start = 4 + b + off
        vals = np.ascontiguousarray(rows[:, start:start + 8 * count]).view("<f8").astype(np.float64, copy=False)
        out[name] = vals if every else np.where(valid[:, None], vals, np.nan)
    return DecodedColumns(stamps=stamps, valid=valid, encapsulation_ok=encap_ok, fields=out)


def decode_imu(buffer, offset, length, fields: Sequence[str] | None = None) -> DecodedColumns:
    """Decode sensor_msgs/msg/Imu payloads; see :func:`decode_columns`."""
    return decode_columns(IMU_LAYOUT, buffer, offset, length, fields)


def decode_accel_with_covariance_stamped(buffer, offset, length, fields: Sequence[str] | None = None) -> DecodedColumns:
    """Decode geometry_msgs/msg/AccelWithCovarianceStamped payloads; see :func:`decode_columns`."""
    return decode_columns(ACCEL_LAYOUT, buffer, offset, length, fields)
