"""Processes of one measurement: their own DDS domain, output to files, stopped with SIGINT; the commands
that start the driver, the helper roles and the simulated recordings."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.harness import REPO

ARRAY = REPO / "config" / "array32.yaml"
BIN = Path(sys.executable).parent
N_IMUS = 32
LOG_TIME = re.compile(r"\[(\d+\.\d+)\]")



_domain_counter = [0]


def next_domain() -> int:
    """A DDS domain of this run's own (30..99: the DDS tests use 100..229)."""
    _domain_counter[0] += 1
    return 30 + (os.getpid() * 7 + _domain_counter[0]) % 70


class Procs:
    """Processes of one run: their own domain, output to files, stopped with SIGINT then killed."""

    def __init__(self, work: Path, tag: str) -> None:
        self.domain = next_domain()
        self.env = dict(os.environ, ROS_DOMAIN_ID=str(self.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                        PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        self.dir = work / tag
        self.dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *cmd) -> subprocess.Popen:
        out = open(self.dir / f"{name}.out", "w")
        err = open(self.dir / f"{name}.err", "w")
        p = subprocess.Popen([str(c) for c in cmd], env=self.env, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                             cwd=REPO)
        out.close()
        err.close()
        self.procs[name] = p
        return p

    def text(self, name: str, stream: str = "err") -> str:
        try:
            return (self.dir / f"{name}.{stream}").read_text()
        except OSError:
            return ""

    def wait_line(self, name: str, text: str, timeout: float = 30.0) -> None:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if text in self.text(name, "out"):
                return
            if self.procs[name].poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"{name}: no {text!r} within {timeout} s: {self.text(name)[-2000:]}")

    def wait(self, name: str, timeout: float, unless: str | None = None) -> int | None:
        """Exit status of ``name`` within ``timeout`` (None: still running); gives up early when
        process ``unless`` has ended with an error."""
        end = time.monotonic() + timeout
        p = self.procs[name]
        while time.monotonic() < end:
            if p.poll() is not None:
                return p.returncode
            if unless is not None and self.procs[unless].poll() not in (None, 0):
                return None
            time.sleep(0.05)
        return p.poll()

    def stop(self, name: str, timeout: float = 10.0) -> int:
        p = self.procs[name]
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        return p.returncode

    def stop_all(self) -> None:
        for name in list(self.procs):
            self.stop(name)


def log_time(text: str, marker: str) -> float | None:
    """ROS log timestamp (s) of the first line holding ``marker``."""
    for line in text.splitlines():
        if marker in line:
            m = LOG_TIME.search(line)
            if m:
                return float(m.group(1))
    return None



def role_cmd(role: str, *args) -> list:
    """A helper role of :mod:`benchmarks.nodes.roles` in its own interpreter (started from the repository root)."""
    return [sys.executable, "-m", "benchmarks.nodes.roles", role, *args]


def recording(work: Path, rate: int, duration: float) -> Path:
    out = work / f"rec_{rate}hz"
    if not out.exists():
        exe = BIN / "imu-array"
        t0 = time.perf_counter()
        subprocess.run([exe, "simulate", "--array", ARRAY, "--out", out, "--duration", str(duration),
                        "--rate", str(rate), "--seed", "1", "--start-time", "0", "-q"], check=True,
                       env=dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1"))
        print(f"  simulated {rate} Hz x {duration:g} s in {time.perf_counter() - t0:.1f} s", flush=True)
    return out


def driver_cmd(bag: Path, rate: float, *, reliable: bool = True, wait: int = 1, poll: float = 0.0005) -> list:
    return [BIN / "driver_node", "--ros-args", "-p", f"array_config:={ARRAY}", "-p", "mode:=replay",
            "-p", f"bag:={bag}", "-p", f"rate:={float(rate)!r}", "-p", "restamp:=true", "-p", f"reliable:={str(reliable).lower()}",
            "-p", f"wait_for_subscribers:={wait}", "-p", "exit_at_end:=true", "-p", f"poll_period:={float(poll)!r}"]
