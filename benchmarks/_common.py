"""Shared by the benchmark scripts: machine facts for result files, the rosbags baseline."""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import sys
import time
from pathlib import Path


def machine_header(title: str) -> str:
    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    import numpy

    return (
        f"# {title}\n\n"
        f"- date: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}\n"
        f"- machine: {platform.uname().system} {platform.uname().release} {platform.machine()}, {cpu}, "
        f"{os.cpu_count()} cores\n"
        f"- python {platform.python_version()}, numpy {numpy.__version__}\n"
        f"- command: `{' '.join(shlex.quote(a) for a in [os.path.basename(sys.executable)] + sys.argv)}`\n\n"
    )


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
