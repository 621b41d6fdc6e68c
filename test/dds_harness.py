"""Node processes over real DDS for the tests: one harness instead of a copy per test file.

:class:`DdsProcesses` (the ``dds`` fixture of ``conftest.py``) gives a test

* a DDS domain of its own (``ROS_DOMAIN_ID``; ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``), set in the
  test process's environment too, so an rclpy node the test creates itself joins it.  The domain is drawn
  from ``IMU_ARRAY_TEST_DOMAINS`` (``LO-HI``, default ``100-229``; several test runs on one machine each
  give their own range);
* processes started in it (:meth:`DdsProcesses.start`), their stdout and stderr written to files (never
  pipes: a pipe nobody reads blocks a process that logs a lot), read back at any time
  (:meth:`Proc.out`, :meth:`Proc.err`), waited on for a line (:meth:`Proc.wait_line`), stopped with
  SIGINT as Ctrl-C would (:meth:`Proc.stop`);
* at the end every process still running stopped (SIGINT, then SIGKILL), and the Fast DDS shared-memory
  files (``/dev/shm/fastrtps_*``) its processes had open removed once no live process has them open (a
  killed process leaves them behind).
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

__all__ = ["BIN", "COME_UP_S", "DdsProcesses", "Proc", "dds_env", "pick_domain"]

BIN = Path(sys.executable).parent
#: seconds a process may take to come up (say its first line) on a loaded machine; a wait ends at the line
COME_UP_S = 90.0
_SHM = "/dev/shm/fastrtps_"
#: numerical libraries one thread per process: several node processes on a small machine do not starve each
#: other (a calibration's BLAS threads cannot hold a replay driver up on a 2-core machine)
ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}


_used: set[int] = set()


def _busy_domains() -> set[int]:
    """DDS domains some process on this machine has a participant in: the UDP ports bound in the range RTPS
    gives domain d (7400 + 250 d ... + 249), read from /proc/net/udp{,6} (another test run beside this one,
    or a node a killed test left running, is seen; an empty set where /proc cannot be read)."""
    busy = set()
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table) as f:
                rows = f.read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            if len(fields) > 1 and ":" in fields[1]:
                port = int(fields[1].rsplit(":", 1)[1], 16)
                if port >= 7400:
                    busy.add((port - 7400) // 250)
    return busy


def pick_domain() -> int:
    """A DDS domain from ``IMU_ARRAY_TEST_DOMAINS`` (``LO-HI``; default 100-229) that no other test and no
    other process on this machine uses: under pytest-xdist each worker draws only from its own slice of the
    range (worker ``gwN`` of ``PYTEST_XDIST_WORKER_COUNT``), a process never hands out a domain twice until its
    slice is used up, and a domain with a live participant (:func:`_busy_domains`: another test run beside
    this one) is skipped.  Two tests in one domain see each other's nodes: a fusion node then fuses the other
    test's IMUs."""
    lo, _, hi = os.environ.get("IMU_ARRAY_TEST_DOMAINS", "100-229").partition("-")
    lo, hi = int(lo), int(hi or lo)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    size = (hi - lo + 1) // max(count, 1)
    if size >= 1 and index < count:
        lo, hi = lo + index * size, lo + (index + 1) * size - 1
    free = [d for d in range(lo, hi + 1) if d not in _used]
    if not free:
        _used.clear()
        free = list(range(lo, hi + 1))
    idle = [d for d in free if d not in _busy_domains()] or free
    domain = random.Random(os.getpid() * 1_000_003 + time.monotonic_ns()).choice(idle)
    _used.add(domain)
    return domain


def dds_env(domain: int) -> dict:
    """The environment of a process in ``domain``, localhost only, unbuffered output, one-thread numerics."""
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                PYTHONUNBUFFERED="1", **ONE_THREAD)


def _shm_files(pid: int | str) -> set[str]:
    """The Fast DDS shared-memory files process ``pid`` has mapped or open (empty if it is gone)."""
    found = set()
    try:
        with open(f"/proc/{pid}/maps") as f:
            for line in f:
                i = line.find(_SHM)
                if i >= 0:
                    found.add(line[i:].strip().removesuffix(" (deleted)"))
    except OSError:
        pass
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        fds = []
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith(_SHM):
            found.add(target.removesuffix(" (deleted)"))
    return found


class Proc(subprocess.Popen):
    """A started process: ``Popen`` plus its output files."""

    out_path: Path
    err_path: Path
    name: str
    shm: set

    def out(self) -> str:
        return _read(self.out_path)

    def err(self) -> str:
        return _read(self.err_path)

    def text(self) -> str:
        """stdout then stderr."""
        return self.out() + self.err()

    def note_shm(self) -> None:
        """Remember the shared-memory files the process has now (to remove them once it is gone)."""
        if self.poll() is None:
            self.shm |= _shm_files(self.pid)

    def wait_line(self, text: str, timeout: float = COME_UP_S, stream: str = "out") -> str:
        """Wait until ``text`` appears on ``stream`` ('out', 'err' or 'any'); that line.  Fails at once when
        the process ends without it."""
        end = time.monotonic() + timeout
        while True:
            alive = self.poll() is None
            body = self.text() if stream == "any" else (self.out() if stream == "out" else self.err())
            for line in body.splitlines():
                if text in line:
                    self.note_shm()
                    return line
            if not alive or time.monotonic() > end:
                break
            time.sleep(0.02)
        state = f"exited with {self.returncode}" if self.poll() is not None else f"still running after {timeout:g} s"
        raise AssertionError(f"no {text!r} from {self.name} ({state}): {self.text()[-3000:]}")

    def finish(self, timeout: float) -> tuple[int, str, str]:
        """Wait for the process to end (``subprocess.TimeoutExpired`` after ``timeout``); (status, out, err)."""
        self.note_shm()
        self.wait(timeout)
        return self.returncode, self.out(), self.err()

    def stop(self, timeout: float = 15.0) -> tuple[int, str, str]:
        """Ctrl-C (SIGINT) and wait for the end; (status, out, err)."""
        self.note_shm()
        if self.poll() is None:
            self.send_signal(signal.SIGINT)
        return self.finish(timeout)


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


class DdsProcesses:
    """Processes of one test in a DDS domain of their own (see module docstring)."""

    def __init__(self, directory: Path, domain: int | None = None) -> None:
        self.domain = pick_domain() if domain is None else domain
        self.env = dds_env(self.domain)
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.procs: list[Proc] = []

    def start(self, name: str, *cmd, env: dict | None = None, **kw) -> Proc:
        """Start ``cmd`` (str()'d) as ``name``: output to ``<dir>/<name>.out`` / ``.err``."""
        n = sum(p.name == name or p.name.startswith(f"{name}.") for p in self.procs)
        name = name if n == 0 else f"{name}.{n}"
        out_path, err_path = self.dir / f"{name}.out", self.dir / f"{name}.err"
        with open(out_path, "w") as out, open(err_path, "w") as err:
            p = Proc([str(c) for c in cmd], env={**self.env, **(env or {})}, stdout=out, stderr=err,
                     stdin=subprocess.DEVNULL, text=True, **kw)
        p.out_path, p.err_path, p.name, p.shm = out_path, err_path, name, set()
        self.procs.append(p)
        return p

    def close(self, timeout: float = 10.0) -> None:
        """Stop what still runs (SIGINT, then SIGKILL after ``timeout``); remove the shared-memory files left."""
        running = [p for p in self.procs if p.poll() is None]
        for p in running:
            p.note_shm()
            p.send_signal(signal.SIGINT)
        end = time.monotonic() + timeout
        for p in running:
            try:
                p.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.remove_shm()

    def remove_shm(self) -> list[str]:
        """Remove the Fast DDS shared-memory files this harness's processes had, once none of them runs and
        no live process has the file open; the paths removed."""
        ours = set().union(*(p.shm for p in self.procs)) if self.procs else set()
        ours = {f for f in ours if os.path.exists(f)}
        if not ours or any(p.poll() is None for p in self.procs):
            return []
        in_use = set()
        for pid in os.listdir("/proc"):
            if pid.isdigit():
                in_use |= _shm_files(pid)
        ours |= {f + "_el" for f in ours if not f.endswith("_el") and os.path.exists(f + "_el")}
        removed = []
        for path in sorted(ours - in_use):
            try:
                os.unlink(path)
                removed.append(path)
            except OSError:
                pass
        return removed
