"""What the command line says while it works: progress and summary lines on stderr.

stdout carries only what the user asked for (tables, ``--json -``); ``-q``
silences everything here, never that.
"""

from __future__ import annotations

import sys
import time

__all__ = ["Progress", "info"]


class Progress:
    """Progress lines on stderr: a live line on a terminal, a few lines otherwise.

    Call with ``(done, total)``; prints at every percent on a terminal; otherwise at 25/50/75 % when
    at least ``MIN_INTERVAL_S`` have passed since the last line (a job of a second says it once), and
    always at 100 %.  ``quiet=True`` prints nothing.
    """

    #: off a terminal, the shortest time between two intermediate lines
    MIN_INTERVAL_S = 1.0

    def __init__(self, label: str, quiet: bool = False) -> None:
        self.label = label
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.last = -1
        self.t0 = self.printed = time.perf_counter()

    def __call__(self, done, total=None) -> None:
        if self.quiet:
            return
        frac = float(done) / float(total) if total else float(done)
        pct = int(100 * min(max(frac, 0.0), 1.0))
        bucket = pct // (1 if self.tty else 25)
        if bucket == self.last:
            return
        self.last = bucket
        now = time.perf_counter()
        if not self.tty and pct < 100 and now - self.printed < self.MIN_INTERVAL_S:
            return
        self.printed = now
        end = "\r" if self.tty and pct < 100 else "\n"
        print(f"{self.label}: {pct:3d}%  ({now - self.t0:.1f} s)", end=end, file=sys.stderr, flush=True)


def info(quiet: bool, text: str) -> None:
    """A summary line (or lines) on stderr, unless ``quiet``."""
    if not quiet:
        print(text, file=sys.stderr, flush=True)
