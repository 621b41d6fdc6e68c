"""What the subcommands share: validating argument types, the common options, and the inputs.

Every numeric option is checked by its type (positive, finite, non-negative, a
time) so a handler only ever sees sensible values; a bad one gives one line
``imu-array: error: argument --duration: ...`` and exit status 2.

* argument types: :func:`positive_float`, :func:`non_negative_float`, :func:`positive_int`,
  :func:`non_negative_int`, :func:`sample_rate`, :func:`start_time`;
* declarations: :func:`add_force_quiet` (``--force``, ``-q``), :func:`add_recording_inputs`
  (the recording, ``--array``, ``--calibration``); ``--start`` / ``--duration``: :mod:`.window`;
* inputs: :func:`read_array_recording` (the array checked fusable, the recording read for it, one
  line saying how many samples), :func:`read_and_fuse`, :func:`check_imus`, :func:`parse_list`;
* errors: :func:`as_flags` (the core's error naming a parameter, told with the user's flag).
"""

from __future__ import annotations

import argparse
import math
import re
from contextlib import contextmanager
from datetime import datetime, timedelta, timezone
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path
from typing import Iterator, Mapping, Sequence

from imu_array_ros import workflows
from imu_array_ros.cli.progress import Progress, info
from imu_array_ros.errors import ImuArrayError
from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.samples import ImuSamples

__all__ = [
    "positive_float", "non_negative_float", "non_negative_int", "positive_int", "sample_rate", "start_time",
    "MAX_RATE_HZ", "MAX_STAMP_NS", "MAX_SIMULATED_SAMPLES", "QUIET_HELP", "FORCE_RECORDING_HELP",
    "add_force_quiet", "add_recording_inputs", "read_array_recording", "read_and_fuse", "check_imus", "parse_list",
    "as_flags",
]

#: Highest sample rate accepted: stamps are integer nanoseconds and must stay distinct.
MAX_RATE_HZ = 1e6
#: Last nanosecond a ROS ``builtin_interfaces/Time`` (int32 seconds) can hold.
MAX_STAMP_NS = (2**31) * 10**9 - 1
#: Upper bound on ``--duration`` x ``--rate`` (keeps a typo from exhausting memory).
MAX_SIMULATED_SAMPLES = 10**8


# --------------------------------------------------------------------------- argument types


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0."""
    value = _number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """An integer >= 0 (seeds)."""
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (counts)."""
    value = non_negative_int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text!r}")
    return value


def sample_rate(text: str) -> float:
    """A sample rate in Hz: > 0 and at most :data:`MAX_RATE_HZ`."""
    value = positive_float(text)
    if value > MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_RATE_HZ:g} Hz (stamps are whole nanoseconds), got {text!r}")
    return value


_EPOCH = datetime(1970, 1, 1, tzinfo=timezone.utc)


def start_time(text: str) -> int:
    """A start time -> int ns since the epoch (UTC).

    Accepts seconds since the epoch (``1795255200``, ``1795255200.25``) or an
    ISO 8601 time (``2026-11-21T10:00:00Z``, ``2026-11-21T11:00:00+01:00``; a
    time without offset is UTC).  Must lie within what a ROS
    ``builtin_interfaces/Time`` (int32 seconds) can hold.
    """
    s = text.strip()
    try:
        seconds = Decimal(s)
    except InvalidOperation:
        seconds = None
    if seconds is not None:
        if not seconds.is_finite():
            raise argparse.ArgumentTypeError(f"must be a finite time, got {text!r}")
        ns = int((seconds * 10**9).to_integral_value(rounding=ROUND_HALF_EVEN))
    else:
        iso = s[:-1] + "+00:00" if s.endswith(("Z", "z")) else s
        try:
            when = datetime.fromisoformat(iso)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected an ISO 8601 time (e.g. 2026-11-21T10:00:00Z) or seconds since the epoch, got {text!r}"
            ) from None
        if when.tzinfo is None:
            when = when.replace(tzinfo=timezone.utc)
        delta: timedelta = when - _EPOCH
        ns = (delta.days * 86400 + delta.seconds) * 10**9 + delta.microseconds * 1000
    if not 0 <= ns <= MAX_STAMP_NS:
        raise argparse.ArgumentTypeError(
            f"must lie between 1970-01-01T00:00:00Z and 2038-01-19T03:14:07Z "
            f"(int32 seconds of a ROS time stamp), got {text!r}"
        )
    return ns


# --------------------------------------------------------------------------- shared declarations


QUIET_HELP = "no progress or summary lines on stderr (errors still appear)"
FORCE_RECORDING_HELP = ("replace an existing output, only if it is itself a recording (an MCAP file, or a rosbag2 "
                        "directory holding only its own files); an input, a directory holding other files, or any "
                        "other file is never replaced")


def add_force_quiet(sp: argparse.ArgumentParser, *, force: str, quiet: str = QUIET_HELP) -> None:
    """``--force`` (what it may replace: ``force``) and ``-q/--quiet``."""
    sp.add_argument("--force", action="store_true", help=force)
    sp.add_argument("-q", "--quiet", action="store_true", help=quiet)


def add_recording_inputs(sp: argparse.ArgumentParser, *, array: str, calibration: str, many: bool = False) -> None:
    """The recording (positional; ``many``: one or more), ``--array`` (required) and ``--calibration``, with
    their help texts."""
    if many:
        sp.add_argument("recording", type=Path, nargs="+",
                        help="rosbag2 MCAP directories or .mcap files: one or more recordings of the same array")
    else:
        sp.add_argument("recording", type=Path, help="rosbag2 MCAP directory or .mcap file")
    sp.add_argument("--array", required=True, type=Path, help=array)
    sp.add_argument("--calibration", type=Path, help=calibration)


def parse_list(text: str | None) -> list[str] | None:
    """``a,b, c`` -> ['a', 'b', 'c']; None stays None."""
    if text is None:
        return None
    return [t.strip() for t in text.split(",") if t.strip()]


@contextmanager
def as_flags(flags: Mapping[str, str]) -> Iterator[None]:
    """An error of the core inside names the parameters it was given (``chains 1: ...``, ``sim: ...``,
    ``... (n_draws) ...``); re-raised (same type) with the user's flags instead (``flags``: parameter ->
    flag): a parameter name that starts the message, and any parameter name with an underscore."""
    try:
        yield
    except ImuArrayError as err:
        text = str(err)
        for name, flag in flags.items():
            if re.match(rf"{re.escape(name)}[ :]", text):
                text = flag + text[len(name):]
            if "_" in name:
                text = re.sub(rf"(?<![\w-]){re.escape(name)}(?!\w)", flag, text)
        if text == str(err):
            raise
        raise type(err)(text) from None


# --------------------------------------------------------------------------- inputs


def check_imus(desc: ArrayDescription, *names: str | None) -> None:
    """A one-line error naming the first of ``names`` (None: skipped) that is not an IMU of ``desc``."""
    for name in names:
        if name:
            desc.index(name)


def read_array_recording(recording: Path, array: Path, calibration: Path | None, quiet: bool,
                         *, imus: Sequence[str | None] = ()) -> tuple[ArrayDescription, ImuSamples]:
    """The description (``--calibration``'s values if given; checked fusable, naming the file it came from;
    ``imus``, e.g. a --reference, checked to be its IMUs before reading) and ``recording`` read for it,
    saying how many samples."""
    desc, source = workflows.load_array(array, calibration)
    workflows.check_fusable(desc, source)
    check_imus(desc, *imus)
    samples, stats = workflows.read_imu_recording(recording, desc, progress=Progress("reading", quiet))
    info(quiet, f"read {stats.samples} array samples of {len(desc.imus)} IMUs")
    return desc, samples


def read_and_fuse(recording: Path, array: Path, calibration: Path | None, quiet: bool, *,
                  bias_tracking: bool = True) -> tuple[ArrayDescription, workflows.FusedRecording]:
    """The description (``calibration``'s values if given) and ``recording`` read for it and fused in chunks
    with every term (checked fusable first, naming the file), the gyroscope biases tracked unless
    ``bias_tracking`` is False, with progress lines and the session states' notes."""
    desc, _ = workflows.load_array(array, calibration)
    fused = workflows.fuse_recording(recording, desc, read_progress=Progress("reading", quiet),
                                     fuse_progress=Progress("fusing", quiet), bias_tracking=bias_tracking)
    for note in fused.read_stats.notes:
        info(quiet, note)
    for note in fused.notes():
        info(quiet, note)
    return desc, fused
