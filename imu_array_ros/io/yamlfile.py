"""Reading a YAML file with one-line errors: the one place YAML read errors are worded.

Used by the array description (:func:`imu_array_ros.model.description.load_description`)
and the rosbag2 ``metadata.yaml`` reader (:mod:`imu_array_ros.io.rosbag.mcap_recording`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import yaml

__all__ = ["load_yaml_file", "yaml_error_text"]


def yaml_error_text(err: yaml.YAMLError) -> str:
    """``line N: malformed YAML: <problem>`` (``malformed YAML: <problem>`` without a position)."""
    mark = getattr(err, "problem_mark", None)
    where = f"line {mark.line + 1}: " if mark is not None else ""
    problem = getattr(err, "problem", None) or (str(err).splitlines() or ["unreadable"])[0]
    return f"{where}malformed YAML: {problem}"


def load_yaml_file(path: str | os.PathLike, error_cls: type[Exception], what: str) -> Any:
    """Parse the YAML file ``path`` (``yaml.safe_load``); the parsed document.

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
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise error_cls(f"{path}: {yaml_error_text(err)}") from None
