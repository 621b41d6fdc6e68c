"""CPU time of processes and of the whole machine (/proc), sampled in a thread while a measurement runs."""

from __future__ import annotations

import os
import threading
import time

CLK_TCK = os.sysconf("SC_CLK_TCK")



def proc_cpu_s(pid: int) -> float | None:
    """utime + stime of a process in seconds (None once it is gone)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK_TCK
    except (OSError, IndexError):
        return None


def machine_cpu() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine since boot (/proc/stat)."""
    with open("/proc/stat") as fh:
        v = [int(x) for x in fh.readline().split()[1:]]
    total = sum(v[:8])
    idle = v[3] + v[4]
    return (total - idle) / CLK_TCK, total / CLK_TCK


class CpuSampler:
    """Samples the CPU time of some processes and of the machine every ``period`` s (wall clock ns)."""

    def __init__(self, pids: dict[str, int], period: float = 0.05) -> None:
        self.pids = dict(pids)
        self.samples: dict[str, list[tuple[int, float]]] = {k: [] for k in list(pids) + ["_machine"]}
        self._stop = threading.Event()
        self._period = period
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def add(self, name: str, pid: int) -> None:
        self.samples.setdefault(name, [])
        self.pids[name] = pid

    def _run(self) -> None:
        while not self._stop.is_set():
            now = time.time_ns()
            for name, pid in list(self.pids.items()):
                c = proc_cpu_s(pid)
                if c is not None:
                    self.samples[name].append((now, c))
            self.samples["_machine"].append((now, machine_cpu()[0]))
            self._stop.wait(self._period)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def used(self, name: str, t0_ns: int, t1_ns: int) -> float:
        """CPU seconds used between two wall times (linear interpolation between samples)."""
        import numpy as np

        s = self.samples.get(name) or []
        if len(s) < 2 or t1_ns <= t0_ns:
            return float("nan")
        t = np.array([a for a, _ in s], dtype=float)
        c = np.array([b for _, b in s])
        return float(np.interp(t1_ns, t, c) - np.interp(t0_ns, t, c))

    def share(self, name: str, t0_ns: int, t1_ns: int) -> float:
        """CPU use over the window, as a fraction of one core."""
        return self.used(name, t0_ns, t1_ns) / max((t1_ns - t0_ns) / 1e9, 1e-9)


def window_others(cpu: CpuSampler, names, t0: int, t1: int) -> float:
    """Busy CPU of everything else (cores); /proc/stat and per-process ticks are counted apart, so the
    difference can come out slightly negative: clamped at 0."""
    ours = sum(cpu.used(n, t0, t1) for n in names)
    return max(0.0, (cpu.used("_machine", t0, t1) - ours) / max((t1 - t0) / 1e9, 1e-9))
