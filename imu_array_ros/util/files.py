"""Files written safely and YAML read with one-line errors (the lowest layer: no other package module).

* :func:`atomic_path` / :func:`atomic_write_bytes` / :func:`atomic_write_text`:
  write to a temporary sibling, then rename over the target.  A reader never
  sees a half-written file or directory, a failed write leaves the previous
  content untouched, and no temporary (``.*.tmp``) or backup (``.*.old``) path
  is left behind, whether the write succeeds or fails.  Whether an output may
  be written at all is :func:`imu_array_ros.io.outputs.check_output`'s business.
* :func:`load_yaml_file`: the one place YAML read errors are worded (the array
  description and the rosbag2 ``metadata.yaml`` reader use it).
* :func:`parse_yaml`: YAML with YAML 1.2's numbers.  PyYAML implements YAML 1.1, where a float needs a
  decimal point and a signed exponent: ``1e-3`` and ``-0.00945e3`` would be read as *strings*, a trap for
  a user typing a noise figure or a position.  :class:`YamlLoader` adds the YAML 1.2 core schema's float
  pattern (``1e-3``, ``5E2``, ``-0.00945e3``); everything else is ``yaml.safe_load``'s.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import yaml

from imu_array_ros.errors import OutputError

__all__ = ["unnamed", "atomic_path", "atomic_write_bytes", "atomic_write_text", "load_yaml_file", "yaml_error_text",
           "YamlLoader", "parse_yaml"]


class YamlLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that also reads YAML 1.2 floats without a decimal point or exponent sign."""


#: YAML 1.2 core schema floats that YAML 1.1's pattern misses (its own still match first)
_FLOAT_12 = re.compile(r"^[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)$")
YamlLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789."))


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load(text)`` with YAML 1.2's floats (:class:`YamlLoader`)."""
    return yaml.load(text, Loader=YamlLoader)  # noqa: S506 -- a SafeLoader subclass


def unnamed(target: Path) -> bool:
    """True for a path that names no file or directory (``.``, ``..``, a root)."""
    return Path(target).name in ("", ".", "..")


def _fsync_dir(path: Path) -> None:
    """Make a rename in ``path`` durable (best effort: not every platform allows it)."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _remove(path: Path) -> None:
    """Remove a temporary path of ours, file or directory; never raises."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


def _replace_directory(tmp: Path, target: Path, parent: Path) -> None:
    """Put the complete directory ``tmp`` in place of the existing directory ``target``.

    The old directory is moved aside into a fresh holder directory, the new one
    renamed in, then the old one deleted.  If the second rename fails the old
    directory is moved back, so ``target`` is never lost and nothing is left over.
    """
    holder = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=parent))
    aside = holder / "previous"
    try:
        os.rename(target, aside)
    except BaseException:
        with contextlib.suppress(OSError):
            holder.rmdir()
        raise
    try:
        os.rename(tmp, target)
    except BaseException:
        os.rename(aside, target)  # put the previous content back
        with contextlib.suppress(OSError):
            holder.rmdir()
        raise
    shutil.rmtree(holder, ignore_errors=True)


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, *, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success rename it onto ``target``.

    With ``directory=True`` the temporary path is an (empty) directory and an
    existing target directory is replaced as a whole, only once the new one is
    complete.  On any exception the temporary path is removed and the target is
    left as it was; no ``.tmp``/``.old`` path stays behind.  ``target`` must
    have a name (not ``.``, ``..`` or a root); whether it may be replaced at all
    is :func:`check_output`'s business, not this function's.
    """
    target = Path(target)
    if unnamed(target):
        raise OutputError(f"{target}: not a name an output can be written to; give a file or directory name")
    parent = target.parent if str(target.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    if directory:
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent))
    else:
        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent)
        os.close(fd)
        tmp = Path(name)
    try:
        yield tmp
        if directory:
            os.chmod(tmp, 0o755)
            if target.is_dir() and not target.is_symlink():
                _replace_directory(tmp, target, parent)
            else:
                os.rename(tmp, target)
        else:
            os.chmod(tmp, 0o644)
            os.replace(tmp, target)
        _fsync_dir(parent)
    except BaseException:
        _remove(tmp)
        raise


def atomic_write_bytes(target: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``target`` atomically (fsync before rename)."""
    with atomic_path(target) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())


def atomic_write_text(target: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``target`` atomically."""
    atomic_write_bytes(target, text.encode("utf-8"))


# --------------------------------------------------------------------------- reading YAML


def yaml_error_text(err: yaml.YAMLError) -> str:
    """``line N: malformed YAML: <problem>`` (``malformed YAML: <problem>`` without a position)."""
    mark = getattr(err, "problem_mark", None)
    where = f"line {mark.line + 1}: " if mark is not None else ""
    problem = getattr(err, "problem", None) or (str(err).splitlines() or ["unreadable"])[0]
    return f"{where}malformed YAML: {problem}"


def load_yaml_file(path: str | os.PathLike, error_cls: type[Exception], what: str) -> Any:
    """Parse the YAML file ``path`` (:func:`parse_yaml`); the parsed document.

    Every failure raises ``error_cls`` with one line naming the file:
    ``<path>: <what> not found``, ``<path>: cannot read <what>: <reason>`` or
    ``<path>: line N: malformed YAML: <problem>``.  ``what`` names the file's
    role for the user, e.g. ``"array description"``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error_cls(f"{path}: {what} not found") from None
    except IsADirectoryError:
        raise error_cls(f"{path}: cannot read {what}: is a directory") from None
    except (OSError, UnicodeDecodeError) as err:
        reason = getattr(err, "strerror", None) or str(err)
        raise error_cls(f"{path}: cannot read {what}: {reason}") from None
    try:
        return parse_yaml(text)
    except yaml.YAMLError as err:
        raise error_cls(f"{path}: {yaml_error_text(err)}") from None
