"""OpenShoe / MIMU host commands: encoding (host side) and incremental parsing (device side).

Our best knowledge of the OpenShoe/MIMU command framing, from the OpenShoe
host software and the captures in ``shared/data/openshoe_mimu4444bt`` (whose
first bytes are the acknowledgement ``A0 28 00 C8``).  **To be verified
against hardware**: only the acknowledgement bytes have been seen in a real
stream; the command payloads below are not yet confirmed on a board.

Host -> device command (all integers big-endian)::

    command byte · payload · uint16 checksum (= 16-bit sum of the command byte and the payload bytes)

    0x28  start raw IMU output   payload: uint32 IMU mask · uint8 rate divider d   (8 bytes in all)
          bit k of the mask set = IMU k streamed; packets carry the selected IMUs in
          ascending k.  Output rate = 1000 Hz / 2**(d - 1), d = 1..7
          (1000, 500, 250, 125, 62.5, 31.25, 15.625 Hz; d = 5 gives 62.5 Hz, the
          rate of the real captures).
    0x22  stop all outputs       no payload:  22 00 22

Device -> host: acknowledgement ``A0 · cmd · uint16 checksum (= 0xA0 + cmd)``,
e.g. ``A0 28 00 C8``, then (after ``0x28``) data packets in the format of
:mod:`imu_array_ros.io.openshoe.framing`.

:class:`CommandParser` is the device side (used by the simulated device of
:mod:`~imu_array_ros.io.openshoe.fake_device`): it finds commands in an
arbitrary byte stream, drops commands with a bad checksum (counted) and skips
bytes that start no known command (counted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from imu_array_ros.io.openshoe.framing import ACK_HEADER

__all__ = [
    "START_RAW_IMU",
    "STOP_OUTPUT",
    "BASE_RATE_HZ",
    "RATE_DIVIDERS",
    "COMMAND_PAYLOAD_LENGTH",
    "STOP_COMMAND",
    "START_ACK",
    "checksum",
    "encode_command",
    "start_command",
    "ack_for",
    "output_rate_hz",
    "rate_divider_for",
    "default_imu_mask",
    "mask_bits",
    "Command",
    "CommandParserStats",
    "CommandParser",
]

START_RAW_IMU = 0x28
STOP_OUTPUT = 0x22
BASE_RATE_HZ = 1000.0
RATE_DIVIDERS = range(1, 8)
#: Payload bytes of each known command (the device side needs them to find frame ends).
COMMAND_PAYLOAD_LENGTH = {START_RAW_IMU: 5, STOP_OUTPUT: 0}


def checksum(data: bytes) -> int:
    """16-bit sum of ``data`` (int in 0..65535)."""
    return sum(data) & 0xFFFF


def encode_command(code: int, payload: bytes = b"") -> bytes:
    """``code · payload · checksum`` (big-endian uint16 sum of code and payload)."""
    if not 0 <= int(code) <= 0xFF:
        raise ValueError(f"command code must be one byte (0..255), got {code}")
    body = bytes([int(code)]) + bytes(payload)
    return body + checksum(body).to_bytes(2, "big")


def _check_mask(imu_mask: int) -> int:
    if isinstance(imu_mask, bool) or int(imu_mask) != imu_mask or not 0 < int(imu_mask) < (1 << 32):
        raise ValueError(f"imu_mask must be a nonzero 32-bit integer (1..0xFFFFFFFF), got {imu_mask!r}")
    return int(imu_mask)


def _check_divider(rate_divider: int) -> int:
    if isinstance(rate_divider, bool) or int(rate_divider) != rate_divider or int(rate_divider) not in RATE_DIVIDERS:
        raise ValueError(f"rate_divider must be an integer 1..7 (rate = 1000 Hz / 2**(d-1)), got {rate_divider!r}")
    return int(rate_divider)


def start_command(imu_mask: int, rate_divider: int) -> bytes:
    """The 8-byte "start raw IMU output" command ``28 · mask (4) · d · checksum (2)``.

    imu_mask: bit k set = IMU k streamed (nonzero, < 2**32); rate_divider d in 1..7.
    """
    mask = _check_mask(imu_mask)
    d = _check_divider(rate_divider)
    return encode_command(START_RAW_IMU, mask.to_bytes(4, "big") + bytes([d]))


STOP_COMMAND = encode_command(STOP_OUTPUT)
"""``22 00 22``: stop all outputs."""


def ack_for(cmd: int) -> bytes:
    """The device's acknowledgement of command ``cmd``: ``A0 · cmd · uint16 (0xA0 + cmd)``."""
    if not 0 <= int(cmd) <= 0xFF:
        raise ValueError(f"cmd must be one byte (0..255), got {cmd}")
    return bytes([ACK_HEADER, int(cmd)]) + (ACK_HEADER + int(cmd)).to_bytes(2, "big")


START_ACK = ack_for(START_RAW_IMU)
"""``A0 28 00 C8``: acknowledgement of the start command."""


def output_rate_hz(rate_divider: int) -> float:
    """Output rate in Hz of divider d: ``1000 / 2**(d - 1)`` (d = 1..7)."""
    return BASE_RATE_HZ / 2 ** (_check_divider(rate_divider) - 1)


def rate_divider_for(rate_hz: float) -> int:
    """The divider d giving exactly ``rate_hz`` (one of 1000, 500, ..., 15.625 Hz); ValueError otherwise."""
    for d in RATE_DIVIDERS:
        if math.isclose(float(rate_hz), output_rate_hz(d), rel_tol=1e-9):
            return d
    rates = ", ".join(f"{output_rate_hz(d):g}" for d in RATE_DIVIDERS)
    raise ValueError(f"rate must be one of {rates} Hz (OpenShoe rate dividers 1..7), got {rate_hz!r}")


def default_imu_mask(n_imus: int) -> int:
    """Mask of the lowest ``n_imus`` IMUs (bits 0..n_imus-1), n_imus in 1..32."""
    if isinstance(n_imus, bool) or int(n_imus) != n_imus or not 1 <= int(n_imus) <= 32:
        raise ValueError(f"n_imus must be an integer 1..32 for a 32-bit IMU mask, got {n_imus!r}")
    return (1 << int(n_imus)) - 1


def mask_bits(imu_mask: int) -> list[int]:
    """IMU indices k whose bit is set, ascending (= their order in a packet)."""
    mask = _check_mask(imu_mask)
    return [k for k in range(32) if mask >> k & 1]


@dataclass(frozen=True)
class Command:
    """One host command as the device received it (checksum already verified)."""

    code: int
    payload: bytes = b""

    @property
    def imu_mask(self) -> int:
        """Start command: the uint32 IMU mask (may be invalid, e.g. 0: check with :func:`mask_bits`)."""
        self._need_start()
        return int.from_bytes(self.payload[:4], "big")

    @property
    def rate_divider(self) -> int:
        """Start command: the rate divider byte (may be invalid: check with :func:`output_rate_hz`)."""
        self._need_start()
        return self.payload[4]

    def encode(self) -> bytes:
        """The command's bytes, checksum included."""
        return encode_command(self.code, self.payload)

    def _need_start(self) -> None:
        if self.code != START_RAW_IMU:
            raise ValueError(f"command 0x{self.code:02X} is not a start command (0x{START_RAW_IMU:02X})")


@dataclass
class CommandParserStats:
    """commands: accepted; bad_checksums: known command byte whose frame failed the checksum
    (dropped; parsing resumes one byte later); unknown_bytes: bytes that start no known command."""

    commands: int = 0
    bad_checksums: int = 0
    unknown_bytes: int = 0


class CommandParser:
    """Incremental device-side parser of host commands.

    ``feed(data)`` returns the commands completed by ``data`` and keeps an
    incomplete frame (at most 7 bytes) for the next call; the result does not
    depend on how the stream is split into chunks.  A frame is recognised by its
    command byte (one of ``payload_lengths``, default
    :data:`COMMAND_PAYLOAD_LENGTH`) and its checksum.  A frame failing the
    checksum is dropped and counted, and the search resumes at the next byte,
    so a stray command byte cannot swallow a real command that follows it.
    """

    def __init__(self, payload_lengths: dict[int, int] | None = None) -> None:
        self.payload_lengths = dict(COMMAND_PAYLOAD_LENGTH if payload_lengths is None else payload_lengths)
        self.stats = CommandParserStats()
        self._buf = b""

    def feed(self, data: bytes) -> list[Command]:
        """Add received bytes; return the complete, checksum-valid commands in order."""
        buf = self._buf + bytes(data)
        out: list[Command] = []
        i = 0
        while i < len(buf):  # commands are a few bytes: a per-byte loop is fine here
            n = self.payload_lengths.get(buf[i])
            if n is None:
                self.stats.unknown_bytes += 1
                i += 1
                continue
            end = i + n + 3
            if end > len(buf):
                break
            if checksum(buf[i : end - 2]) == int.from_bytes(buf[end - 2 : end], "big"):
                out.append(Command(buf[i], bytes(buf[i + 1 : end - 2])))
                self.stats.commands += 1
                i = end
            else:
                self.stats.bad_checksums += 1
                i += 1
        self._buf = buf[i:]
        return out
