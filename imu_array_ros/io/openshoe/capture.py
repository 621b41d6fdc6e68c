"""Import a raw OpenShoe serial capture (``*.bin``) into :class:`ImuSamples`.

The byte format is described in :mod:`imu_array_ros.io.openshoe.framing`.  The
number of IMUs per packet cannot be read from the stream (the size byte wraps),
so it is taken from the array description and confirmed by the checksums.

Mapping: capture IMU ``k`` (1-based, ascending in the packet) becomes
``description.names[k-1]``; values stay in each IMU's own sensor frame (the
description's ``orientation`` maps them to the array frame later).

Time: ``stamps`` come from the board's 64 MHz timestamp, unwrapped across its
≈ 67 s wrap, as ``start_ns + (t - t_first)`` — i.e. the first packet is at
``start_ns`` (0 by default: a fixed epoch, not wall-clock time).  Packets lost
in transmission (counter gaps) are simply absent: no NaN rows are inserted.
Saturated samples are kept as clipped values; see
:func:`~imu_array_ros.io.openshoe.framing.saturation_mask` /
:func:`~imu_array_ros.io.openshoe.framing.si_saturation_level`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.errors import CaptureError
from imu_array_ros.io.openshoe.framing import (
    OpenShoeFramer,
    ParsedPackets,
    TickUnwrapper,
    counts_to_si,
    packet_length,
    parse_buffer,
    saturation_mask,
)
from imu_array_ros.model.samples import ImuSamples

__all__ = ["CaptureStats", "import_capture", "guess_imu_count"]

_CHUNK = 1 << 20  # bytes per framer feed (progress granularity)
_MIN_PACKET_FRACTION = 0.5  # below this share of bytes in valid packets, K is judged wrong


@dataclass
class CaptureStats:
    """What :func:`import_capture` found in a capture file.

    packets: valid packets imported; bytes: file size; acks: command
    acknowledgements (``A0 cmd cs cs``) skipped; garbage_bytes: other bytes
    skipped while resynchronising (incl. frames with a bad checksum);
    bad_checksums: frames dropped for a bad size byte/checksum where a packet
    was due; counter_gaps: packets missing per the uint16 counter;
    counter_backsteps: counter repeats/backward jumps; trailing_bytes:
    incomplete packet at the end of the file; duration_s: last minus first
    stamp; interval_ms_min/median/max: spacing of consecutive stamps (NaN with
    fewer than 2 packets); accel_saturated / gyro_saturated: (K,) number of
    samples in which that IMU's triad had at least one clipped axis.
    """

    path: str
    n_imus: int
    packets: int
    bytes: int
    acks: int
    garbage_bytes: int
    bad_checksums: int
    counter_gaps: int
    counter_backsteps: int
    trailing_bytes: int
    duration_s: float
    interval_ms_min: float
    interval_ms_median: float
    interval_ms_max: float
    accel_saturated: np.ndarray
    gyro_saturated: np.ndarray

    def summary(self) -> str:
        """A few human-readable lines for the CLI."""
        return "\n".join(
            [
                f"{self.path}: {self.packets} packets of {self.n_imus} IMUs, {self.bytes} bytes, "
                f"{self.duration_s:.1f} s",
                f"  interval ms min/median/max: {self.interval_ms_min:.3f} / {self.interval_ms_median:.3f} / "
                f"{self.interval_ms_max:.3f}",
                f"  acks {self.acks}, garbage bytes {self.garbage_bytes}, bad checksums {self.bad_checksums}, "
                f"counter gaps {self.counter_gaps}, counter backsteps {self.counter_backsteps}, "
                f"trailing partial bytes {self.trailing_bytes}",
                f"  saturated samples per IMU: accel {self.accel_saturated.tolist()}, "
                f"gyro {self.gyro_saturated.tolist()}",
            ]
        )


def guess_imu_count(data: bytes, max_imus: int = 64) -> list[int]:
    """IMU counts K (1..max_imus) at which ``data`` holds valid packets, best first.

    Ranked by the share of bytes covered by valid packets; only counts covering
    at least half of ``data`` are returned.  Meant for error hints: pass a
    prefix of the capture (e.g. the first 64 KiB).
    """
    scores = []
    for k in range(1, max_imus + 1):
        packets, _ = parse_buffer(data, k)
        share = len(packets) * packet_length(k) / max(len(data), 1)
        if share >= _MIN_PACKET_FRACTION:
            scores.append((share, k))
    return [k for _, k in sorted(scores, reverse=True)]


def _read(path: Path) -> bytes:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CaptureError(f"{path}: capture file not found") from None
    except IsADirectoryError:
        raise CaptureError(f"{path}: is a directory, expected a raw capture file") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot read capture: {err.strerror or err}") from None
    if not data:
        raise CaptureError(f"{path}: empty capture file (0 bytes)")
    return data


def _wrong_k_message(path: Path, data: bytes, k: int, found: int) -> str:
    hint = guess_imu_count(data[: 1 << 16])
    if hint:
        also = f" (the capture frames as {hint[0]}-IMU packets)"
    else:
        also = " (no IMU count frames it: not an OpenShoe raw-IMU capture?)"
    if found == 0:
        return (
            f"{path}: no valid packet for {k} IMUs ({packet_length(k)}-byte packets) in {len(data)} bytes; "
            f"wrong array description?{also}"
        )
    return (
        f"{path}: only {found} valid {k}-IMU packets cover less than half of {len(data)} bytes; "
        f"wrong array description?{also}"
    )


def import_capture(
    path: str | Path,
    description: ArrayDescription,
    *,
    progress: Callable[[int, int], None] | None = None,
    start_ns: int = 0,
) -> tuple[ImuSamples, CaptureStats]:
    """Read an OpenShoe raw-IMU capture into samples of the described array.

    Parameters
    ----------
    path : str or Path
        Capture file: optional acknowledgement(s), then packets back to back.
    description : ArrayDescription
        K = ``len(description.imus)`` IMUs per packet, in capture order.
    progress : callable(bytes_done, bytes_total), optional
        Called after each parsed chunk (1 MiB) and once at the end.
    start_ns : int
        Stamp given to the first packet, ns (default 0).

    Returns
    -------
    samples : ImuSamples
        stamps (N,) int64 ns; accel (N, K, 3) m/s^2; gyro (N, K, 3) rad/s, sensor frames.
    stats : CaptureStats

    Raises
    ------
    CaptureError
        Missing/unreadable/empty file, or no (or too few) valid packets for K IMUs.
    """
    path = Path(path)
    data = _read(path)
    k = len(description.imus)
    framer = OpenShoeFramer(k)
    parts: list[ParsedPackets] = []
    for offset in range(0, len(data), _CHUNK):
        parts.append(framer.feed(data[offset : offset + _CHUNK]))
        if progress is not None:
            progress(min(offset + _CHUNK, len(data)), len(data))
    parts.append(framer.finish())
    packets = ParsedPackets.concatenate(parts, k)
    st = framer.stats
    if len(packets) * framer.length < _MIN_PACKET_FRACTION * len(data):
        raise CaptureError(_wrong_k_message(path, data, k, len(packets)))

    ns = TickUnwrapper().to_ns(packets.ticks)
    stamps = int(start_ns) + (ns - ns[0])
    accel, gyro = counts_to_si(packets.raw)
    samples = ImuSamples(stamps, accel, gyro, description.names)

    sat = saturation_mask(packets.raw)
    dt_ms = np.diff(stamps) / 1e6
    nan = float("nan")
    stats = CaptureStats(
        path=str(path),
        n_imus=k,
        packets=len(packets),
        bytes=len(data),
        acks=st.acks,
        garbage_bytes=st.garbage_bytes,
        bad_checksums=st.bad_checksums,
        counter_gaps=st.counter_gaps,
        counter_backsteps=st.counter_backsteps,
        trailing_bytes=st.trailing_bytes,
        duration_s=float(stamps[-1] - stamps[0]) / 1e9,
        interval_ms_min=float(dt_ms.min()) if len(dt_ms) else nan,
        interval_ms_median=float(np.median(dt_ms)) if len(dt_ms) else nan,
        interval_ms_max=float(dt_ms.max()) if len(dt_ms) else nan,
        accel_saturated=sat[..., :3].any(axis=2).sum(axis=0),
        gyro_saturated=sat[..., 3:].any(axis=2).sum(axis=0),
    )
    return samples, stats
