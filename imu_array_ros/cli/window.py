"""``--start`` / ``--duration``: the part of a recording a command works on (calibrate geometry, discover).

:func:`add_window_options` declares them, :func:`time_window` cuts the samples (one line saying how many; a
window holding none is a one-line error naming the recording).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from imu_array_ros.cli.options import non_negative_float, positive_float
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.samples import ImuSamples

__all__ = ["add_window_options", "time_window"]


def add_window_options(sp: argparse.ArgumentParser) -> None:
    """``--start SECONDS`` and ``--duration SECONDS``: the part of the recording a command works on
    (:func:`time_window`)."""
    sp.add_argument("--start", type=non_negative_float, metavar="SECONDS",
                    help="window start, seconds after the first sample (default 0)")
    sp.add_argument("--duration", type=positive_float, metavar="SECONDS", help="window length (default: to the end)")


def time_window(samples: ImuSamples, recording: Path, start: float | None, duration: float | None,
                quiet: bool) -> ImuSamples:
    """The samples from ``start`` s after the first for ``duration`` s (None: all of them;
    :meth:`ImuSamples.window`), one line saying how many; CalibrationError naming the recording when the
    window holds none."""
    if not len(samples) or (start is None and duration is None):
        return samples
    window = samples.window(start, duration)
    lo, span = start or 0.0, (samples.stamps[-1] - samples.stamps[0]) / 1e9
    if not len(window):
        where = f"between {lo:g} s and {lo + duration:g} s" if duration is not None else f"from {lo:g} s on"
        raise CalibrationError(f"{recording}: no samples {where} (the recording spans {span:.3f} s)")
    info(quiet, f"window: {len(window)} samples from {lo:g} s")
    return window
