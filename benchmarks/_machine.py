"""Machine facts for benchmark result files."""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import sys


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
