"""Same-run baselines shared by the recording benchmarks."""

from __future__ import annotations

import time
from pathlib import Path

__all__ = ["rosbags_plain_read"]


def rosbags_plain_read(path: Path) -> tuple[float, int]:
    """Seconds and message count for rosbags AnyReader + deserialize of every IMU (``/data_raw``) message.

    The same-run baseline of the recording benchmarks: plain reading, nothing else.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    typestore = get_typestore(Stores.ROS2_JAZZY)
    t0 = time.perf_counter()
    count = 0
    with AnyReader([path], default_typestore=typestore) as reader:
        conns = [c for c in reader.connections if c.topic.endswith("/data_raw")]
        for conn, _, raw in reader.messages(connections=conns):
            reader.deserialize(raw, conn.msgtype)
            count += 1
    return time.perf_counter() - t0, count
