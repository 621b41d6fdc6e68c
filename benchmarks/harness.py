"""What every benchmark script shares: the results header, timing, progress lines, writing a results file.

* :func:`machine_header`: ``# title`` and the run's facts (date, machine, python/numpy, command, commit);
* :func:`timed` / :func:`best_of`: wall and CPU seconds of repeated calls (best = min, median);
* :func:`say`: a progress line on stderr;
* :func:`write_results`: writes a results file atomically and keeps its hand-written ``## Interpretation``
  section: scripts write tables and figures, a person writes what they mean, and re-running a script never
  destroys that text (a file without one gets "(interpretation not yet written)").

Scripts run from the repository root: ``python -m benchmarks.<name> [args]``.  Numpy is imported lazily
here, so that :func:`single_threaded_blas` can run before it.
"""

from __future__ import annotations

import datetime
import os
import platform
import shlex
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

__all__ = ["REPO", "RESULTS", "DATA", "INTERPRETATION", "NOT_WRITTEN", "single_threaded_blas", "command",
           "commit", "load_average", "cpu_affinity", "machine_header", "say", "Timings", "timed", "best_of",
           "write_results", "interpretation_of", "header_of"]

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results"
#: the real MIMU4444BT captures (exp_1..6.bin), outside the repository
DATA = REPO.parent / "shared" / "data" / "openshoe_mimu4444bt"
INTERPRETATION = "## Interpretation"
NOT_WRITTEN = "(interpretation not yet written)"


def single_threaded_blas() -> None:
    """One BLAS/OpenMP thread (per-core figures), unless the environment says otherwise; call it before
    numpy is imported."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def command(argv: list[str] | None = None) -> str:
    """The command line of this run, as it is typed from the repository root: ``python -m benchmarks.<name> ...``."""
    argv = list(sys.argv if argv is None else argv)
    script = Path(argv[0]).resolve() if argv and argv[0] not in ("", "-c") else None
    if script is not None and script.suffix == ".py" and script.is_relative_to(REPO):
        module = ".".join(script.relative_to(REPO).with_suffix("").parts)
        head = ["python", "-m", module.removesuffix(".__main__")]
    else:
        head = ["python"] + argv[:1]
    return " ".join(head + [shlex.quote(a) for a in argv[1:]])


def commit() -> str:
    """Short HEAD of the repository, and whether the package has uncommitted changes."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "imu_array_ros"], cwd=REPO,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head + (" + uncommitted changes in imu_array_ros/" if dirty else "")


def load_average() -> str:
    """The 1, 5 and 15 min load averages, e.g. ``1.07 1.08 1.26``."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


def cpu_affinity() -> str:
    """The CPUs this process may run on, e.g. ``[0, 1]``."""
    return str(sorted(os.sched_getaffinity(0))) if hasattr(os, "sched_getaffinity") else "unknown"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def machine_header(title: str, *, date: str | None = None, cmd: str | None = None, code: str | None = None,
                   extra: tuple[str, ...] | list[str] = ()) -> str:
    """``# title`` then one ``- key: value`` line each for the date, machine, python/numpy, command and commit
    (``date``/``cmd``/``code``: those of an earlier run, when a report is rebuilt from saved numbers), then the
    ``extra`` lines, then a blank line."""
    import numpy

    u = platform.uname()
    lines = [
        f"date: {date or datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}",
        f"machine: {u.system} {u.release} {platform.machine()}, {_cpu_model()}, {os.cpu_count()} cores",
        f"python {platform.python_version()}, numpy {numpy.__version__}",
        f"command: `{cmd or command()}`",
        f"commit: {code or commit()}",
        *extra,
    ]
    return f"# {title}\n\n" + "".join(f"- {line}\n" for line in lines) + "\n"


def header_of(path: Path) -> str | None:
    """The header of an existing results file (``# title``, a blank line, its ``- key: value`` lines, blank
    lines between them dropped; no blank line at the end), to rebuild a report from that run's saved numbers;
    None without one."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines(keepends=True)
    except OSError:
        return None
    if not lines or not lines[0].startswith("# "):
        return None
    facts, i = [], 1
    while i < len(lines):
        if lines[i].startswith("- "):
            facts.append(lines[i])
        elif lines[i].strip() or not (i + 1 < len(lines) and lines[i + 1].startswith("- ")) and facts:
            break
        i += 1
    return lines[0] + "\n" + "".join(facts) if facts else None


def say(text: str) -> None:
    """A progress line on stderr."""
    print(text, file=sys.stderr, flush=True)


@dataclass
class Timings:
    """Seconds of repeated calls: ``wall`` (perf_counter) and ``cpu`` (this process's CPU time) per call, and
    the last call's result."""

    wall: list[float] = field(default_factory=list)
    cpu: list[float] = field(default_factory=list)
    result: Any = None

    @property
    def best(self) -> float:
        return min(self.wall)

    @property
    def median(self) -> float:
        return statistics.median(self.wall)

    @property
    def best_cpu(self) -> float:
        return min(self.cpu)

    @property
    def median_cpu(self) -> float:
        return statistics.median(self.cpu)


def timed(fn: Callable[[], Any], repeat: int = 1) -> Timings:
    """Call ``fn`` ``repeat`` times; wall and CPU seconds of each call."""
    out = Timings()
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        out.result = fn()
        out.wall.append(time.perf_counter() - t0)
        out.cpu.append(time.process_time() - c0)
    return out


def best_of(fn: Callable[[], Any], repeat: int) -> float:
    """The smallest wall time of ``repeat`` calls of ``fn`` (s)."""
    return timed(fn, repeat).best


def _section(text: str, heading: str) -> tuple[int, int] | None:
    """[start, end) of the level-2 section ``heading`` in ``text`` (to the next level-2 heading or the end)."""
    if text.startswith(heading + "\n"):
        start = 0
    else:
        at = text.find("\n" + heading + "\n")
        if at < 0:
            return None
        start = at + 1
    nxt = text.find("\n## ", start + len(heading))
    return start, (len(text) if nxt < 0 else nxt + 1)


def interpretation_of(path: Path) -> str | None:
    """The ``## Interpretation`` section of an existing results file (heading included), None without one."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError:
        return None
    span = _section(text, INTERPRETATION)
    return None if span is None else text[span[0]:span[1]].rstrip("\n") + "\n"


def write_results(path: Path, text: str) -> Path:
    """Write the results file ``path`` atomically: ``text`` (header, tables, figures) with the file's existing
    ``## Interpretation`` section kept (or a placeholder), placed before the first level-2 heading of ``text``
    (at the end when it has none).  A ``## Interpretation`` section in ``text`` itself is replaced."""
    from imu_array_ros.util.files import atomic_write_text

    path = Path(path)
    keep = interpretation_of(path) or f"{INTERPRETATION}\n\n{NOT_WRITTEN}\n"
    own = _section(text, INTERPRETATION)
    if own is not None:
        text = text[:own[0]] + text[own[1]:]
    first = text.find("\n## ")
    if first < 0:
        text = text.rstrip("\n") + "\n\n" + keep
    else:
        text = text[:first + 1] + keep + "\n" + text[first + 1:]
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    return path
