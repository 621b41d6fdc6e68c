"""The one rule that decides what an output may replace (every command that writes calls it first).

:func:`check_output`: whether an output path may be written at all.  An
output is never an input, never contains one and never lies inside one; an
existing output is replaced only with ``force`` and only when it is itself a
file of the kind being written (an MCAP file, a rosbag2 directory holding
nothing but its own files, a YAML or JSON file, a PNG).  The write itself is
atomic (:mod:`imu_array_ros.util.files`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

from imu_array_ros.errors import OutputError
from imu_array_ros.io.rosbag.mcap_format import MAGIC as MCAP_MAGIC
from imu_array_ros.util.files import atomic_write_text, parse_yaml, unnamed

__all__ = ["check_output", "OUTPUT_KINDS", "check_report_directory", "report_manifest", "write_report_manifest",
           "MANIFEST"]

#: What :func:`check_output` knows how to recognise (and therefore may replace).
OUTPUT_KINDS = ("recording", "yaml", "json", "png")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

_MAX_TEXT_BYTES = 64 << 20  # a YAML/JSON output larger than this is not one of ours


# --------------------------------------------------------------------------- what may be replaced


def _real(path: Path) -> Path:
    return Path(os.path.realpath(path))


def _same(a: Path, b: Path) -> bool:
    if _real(a) == _real(b):
        return True
    try:
        return os.path.samefile(a, b)  # hard links, bind mounts
    except OSError:
        return False


def _cwd_relation(real: Path) -> str | None:
    """"is" / "contains" when the resolved output path ``real`` is / contains the current directory."""
    cwd = _real(Path.cwd())
    return "is" if real == cwd else "contains" if real in cwd.parents else None


def _input_relation(out: Path, real: Path, inp: Path) -> str | None:
    """How output ``out`` (resolved: ``real``) meets input ``inp``: "same", "contains", "inside" or None
    (symbolic and hard links followed)."""
    inp_real = _real(inp)
    if _same(out, inp):
        return "same"
    if real in inp_real.parents:
        return "contains"
    if inp_real in real.parents:
        return "inside"
    return None


def _overlap(real: Path, other_outputs) -> tuple | None:
    """The first (option, path) of ``other_outputs`` that is, contains or lies inside ``real``."""
    for name, other in other_outputs:
        if other is None:
            continue
        other_real = _real(Path(other))
        if other_real == real or other_real in real.parents or real in other_real.parents:
            return name, other
    return None


def _read_head(path: Path, n: int) -> bytes | None:
    try:
        with open(path, "rb") as fh:
            return fh.read(n)
    except OSError:
        return None


def _rosbag_problem(directory: Path) -> str | None:
    """None if ``directory`` is a rosbag2 recording holding only its own files, else why not."""
    meta = directory / "metadata.yaml"
    if meta.is_symlink() or not meta.is_file():
        return "is a directory but not a rosbag2 recording (no metadata.yaml)"
    try:
        if meta.stat().st_size > _MAX_TEXT_BYTES:
            raise ValueError
        info = parse_yaml(meta.read_text(encoding="utf-8"))["rosbag2_bagfile_information"]
        files = info["relative_file_paths"]
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            raise ValueError
    except Exception:  # any way of not being rosbag2 metadata: unreadable, not YAML, missing keys
        return "is a directory whose metadata.yaml is not rosbag2 metadata (no relative_file_paths)"
    own = {"metadata.yaml", *files}
    try:
        entries = sorted(os.listdir(directory))
    except OSError as err:
        return f"is a directory that cannot be listed ({err.strerror or err})"
    others = [e for e in entries if e not in own]
    if others:
        return (f"is a directory holding files that are not part of its recording "
                f"(e.g. {others[0]!r}, {len(others)} in all)")
    for entry in entries:
        p = directory / entry
        if p.is_symlink() or not p.is_file():
            return f"is a directory holding {entry!r}, which is not a regular file"
    return None


def _kind_problem(out: Path, kind: str) -> str | None:
    """None if the existing ``out`` is itself an output of ``kind``, else why it is not."""
    if kind == "recording" and out.suffix != ".mcap":
        if not out.is_dir():
            return "exists and is not a directory, so not a rosbag2 recording"
        return _rosbag_problem(out)
    if out.is_dir():
        return "is a directory"
    if not out.is_file():
        return "exists and is not a regular file"
    if kind == "recording":
        if _read_head(out, len(MCAP_MAGIC)) != MCAP_MAGIC:
            return "exists and is not an MCAP file (no MCAP magic)"
        return None
    if kind == "png":
        return None if _read_head(out, len(PNG_MAGIC)) == PNG_MAGIC else "exists and is not a PNG file"
    if out.stat().st_size > _MAX_TEXT_BYTES:
        return f"exists and is too large to be a {kind.upper()} output of this tool"
    raw = _read_head(out, _MAX_TEXT_BYTES)
    try:
        text = (raw or b"").decode("utf-8")
        if kind == "yaml":
            if not isinstance(parse_yaml(text), dict):
                raise ValueError
        else:
            json.loads(text)
    except Exception:  # not UTF-8, not YAML/JSON, or not a YAML mapping
        return f"exists and is not a {kind.upper()} file"
    return None


def check_output(
    out: str | os.PathLike,
    inputs: Iterable[str | os.PathLike | None] = (),
    kind: str = "recording",
    force: bool = False,
    *,
    option: str = "--out",
    other_outputs: Iterable[tuple[str, str | os.PathLike | None]] = (),
) -> Path:
    """Refuse an unsafe output; return it as a :class:`~pathlib.Path` if it may be written.

    Parameters
    ----------
    out : path
        The output about to be written.
    inputs : paths
        Every file the command reads (``None`` entries are ignored).  ``out``
        must not be one of them, contain one, or lie inside one (symbolic
        links and hard links are followed).
    kind : ``"recording"``, ``"yaml"``, ``"json"`` or ``"png"``
        What is written: a recording (a bare MCAP file when ``out`` ends in
        ``.mcap``, else a rosbag2 directory), or a YAML / JSON file.
    force : bool
        Replace an existing ``out`` -- only if it is itself of ``kind``: a file
        starting with the MCAP magic; a directory with a rosbag2
        ``metadata.yaml`` holding nothing but that file and the files its
        ``relative_file_paths`` lists; a YAML file holding a mapping; a JSON file;
        a PNG file (PNG signature).
    option : str
        The command line option that named ``out`` (for messages).
    other_outputs : (option, path) pairs
        Other outputs of the same command; ``out`` must not overlap them.

    Raises
    ------
    OutputError
        One line naming ``out`` and the reason; nothing has been touched.
    """
    if kind not in OUTPUT_KINDS:
        raise ValueError(f"unknown output kind {kind!r} (known: {', '.join(OUTPUT_KINDS)})")
    out = Path(out)
    if unnamed(out):
        raise OutputError(f"{out}: {option} must name a file or directory, not {str(out)!r}")
    real = _real(out)
    what = _cwd_relation(real)
    if what:
        raise OutputError(f"{out}: {option} {what} the current directory; choose another {option}")
    for inp in inputs:
        if inp is None:
            continue
        relation = _input_relation(out, real, Path(inp))
        if relation:
            verb = {"same": "would overwrite", "contains": "contains", "inside": "lies inside"}[relation]
            raise OutputError(f"{out}: output {verb} the input {inp}; choose another {option}")
    overlap = _overlap(real, other_outputs)
    if overlap:
        raise OutputError(f"{out}: {option} overlaps {overlap[0]} {overlap[1]}; give them separate paths")
    if out.is_symlink():
        raise OutputError(f"{out}: is a symbolic link (to {os.readlink(out)}); give the real path as {option}")
    for parent in out.parents:
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                raise OutputError(f"{out}: {parent} is not a directory")
            break
    if not out.exists():
        return out
    problem = _kind_problem(out, kind)
    if problem is not None:
        raise OutputError(f"{out}: {problem}; not replaced, even with --force")
    if not force:
        raise OutputError(f"{out}: already exists (use --force to replace it)")
    return out


# --------------------------------------------------------------------------- report directories

#: the file that marks a directory as one of our reports (its ``kind``) and lists the report's files
MANIFEST = "manifest.json"


def report_manifest(d: Path, kind: str) -> set[str] | None:
    """The files the manifest of report directory ``d`` lists (with the manifest itself), or None when ``d`` has
    no manifest of a report of ``kind``."""
    m = d / MANIFEST
    if m.is_symlink() or not m.is_file() or m.stat().st_size > 1 << 20:
        return None
    try:
        doc = json.loads(m.read_text(encoding="utf-8"))
        files = doc["files"]
        if doc.get("kind") != kind or not all(isinstance(f, str) and "/" not in f for f in files):
            return None
    except (ValueError, KeyError, TypeError, OSError):
        return None
    return set(files) | {MANIFEST}


def write_report_manifest(d: Path, kind: str, names: Iterable[str]) -> Path:
    """Write the manifest of report directory ``d`` (atomic): its ``kind`` and the file names of the report."""
    path = Path(d) / MANIFEST
    atomic_write_text(path, json.dumps({"kind": kind, "files": sorted(set(names) - {MANIFEST})}, indent=1) + "\n")
    return path


def check_report_directory(directory, inputs, force: bool, *, kind: str, option: str = "--report",
                           other_outputs=(), legacy: Iterable[str] = ()) -> Path:
    """Refuse a report directory that may not be written; return it as a Path.

    Allowed: a directory that does not exist yet, an empty one, or (with ``force``) one holding nothing but a
    previous report of ``kind`` (the files its :data:`MANIFEST` lists; or, without a manifest, only files named
    in ``legacy``: reports written before manifests existed).  Refused (:class:`OutputError`, one line, nothing
    touched): a file or symbolic link; any other non-empty directory, even with ``force``; a directory that is,
    holds or lies inside an input; the current directory or one containing it; one that overlaps another
    output of the command (``other_outputs``: (option, path) pairs)."""
    d = Path(directory)
    label = kind.removeprefix("imu_array_ros ")  # e.g. "calibration report"
    if unnamed(d):
        raise OutputError(f"{d}: {option} must name a new or empty directory of its own, not {str(d)!r} (a "
                          f"current, parent or root directory)")
    if d.is_symlink():
        raise OutputError(f"{d}: {option} is a symbolic link; give the real path")
    if d.exists() and not d.is_dir():
        raise OutputError(f"{d}: {option} must be a directory (it is a file)")
    real = _real(d)
    what = _cwd_relation(real)
    if what:
        raise OutputError(f"{d}: {option} {what} the current directory; choose another {option}")
    for inp in inputs:
        if inp is None:
            continue
        relation = _input_relation(d, real, Path(inp))
        if relation:
            verb = "lies inside" if relation == "inside" else "holds"
            raise OutputError(f"{d}: {option} {verb} the input {inp}; choose another {option}")
    overlap = _overlap(real, other_outputs)
    if overlap:
        raise OutputError(f"{d}: {option} overlaps {overlap[0]} {overlap[1]}; give them separate paths")
    for parent in d.parents:
        if parent.exists():
            if not parent.is_dir():
                raise OutputError(f"{d}: {parent} is not a directory")
            break
    if not d.exists():
        return d
    entries = sorted(os.listdir(d))
    if not entries:
        return d
    ours = report_manifest(d, kind)
    if ours is None and MANIFEST not in entries and set(entries) <= set(legacy):
        ours = set(legacy)
    if ours is None:
        raise OutputError(f"{d}: {option} is a directory holding other files (e.g. {entries[0]!r}) and no "
                          f"{label} of ours; choose an empty or new directory")
    others = [e for e in entries if e not in ours or not (d / e).is_file() or (d / e).is_symlink()]
    if others:
        raise OutputError(f"{d}: {option} holds {others[0]!r}, which is not part of its {label}; "
                          f"not replaced, even with --force")
    if not force:
        raise OutputError(f"{d}: holds a {label} already (use --force to replace it)")
    return d
