"""Reading recordings whose IMUs stamp their messages with their own clocks.

:func:`~imu_array_ros.io.rosbag.recording.read_imu_recording` groups messages by
their common ``header.stamp``.  When the IMUs' stamps mostly differ (each IMU with
its own driver and clock), it calls :func:`pair_recording` instead: each topic's
messages in file order become a stream paired onto the reference IMU's stamps by
:func:`~imu_array_ros.io.pairing.pair_streams` (grid, tolerance, errors: there).
The first message of a topic at a stamp is kept (duplicates are removed before),
messages with non-finite values are left out (counted by the reader).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.errors import RecordingError
from imu_array_ros.io.pairing import ImuStream, PairingStats, pair_streams
from imu_array_ros.model.samples import ImuSamples

__all__ = ["pair_recording"]


def pair_recording(path, names: tuple[str, ...], topic: np.ndarray, stamps: np.ndarray, accel: np.ndarray,
                   gyro: np.ndarray, *, reference: str | int | None = None, max_gap_s: float = 1.0,
                   unused_rows: bool = False) -> tuple[ImuSamples, PairingStats, str | None]:
    """Pair the IMU messages of a recording (columns in file order, duplicates and bad ones removed).

    topic (M,) index into ``names``; stamps (M,) int64 ns; accel, gyro (M, 3).  The reference is
    ``reference`` or, when None, the first IMU with two messages or more.  Returns (samples, stats,
    a note when the reference is not the first IMU); RecordingError naming ``path`` and the IMU.
    ``unused_rows``: see :func:`~imu_array_ros.io.pairing.pair_streams`.
    """
    k_count = len(names)
    order = np.argsort(topic, kind="stable")  # by IMU, file order within
    bounds = np.searchsorted(topic[order], np.arange(k_count + 1))
    streams = []
    for k in range(k_count):
        rows = order[bounds[k]:bounds[k + 1]]
        streams.append(ImuStream(stamps[rows], accel[rows], gyro[rows]))
    note = None
    if reference is None:
        counts = np.diff(bounds)
        usable = np.flatnonzero(counts >= 2)
        reference = int(usable[0]) if len(usable) else 0
        if reference != 0:
            note = (f"IMU {names[0]!r} has {int(counts[0])} message(s): the grid is the stamps of "
                    f"{names[reference]!r} instead")
    try:
        samples, stats = pair_streams(streams, names, reference=reference, max_gap_s=max_gap_s,
                                      unused_rows=unused_rows)
    except RecordingError as err:
        raise RecordingError(f"{path}: {err}") from None
    return samples, stats, note
