"""The workflows layer's lazy exports stay the functions whatever was imported before them.

A submodule named like a function it exports (workflows/calibrate.py and workflows.calibrate, until stop 32)
was replaced by the module as soon as anything imported the submodule -- also workflows.install's own lazy
import -- and `workflows.calibrate(...)` then raised "'module' object is not callable"."""

from __future__ import annotations

import subprocess
import sys

import pytest

from imu_array_ros import workflows


@pytest.mark.parametrize("first", [*sorted(set(workflows.EXPORTS.values())), "install", "findings_calibration"])
def test_every_export_is_itself_after_any_first_import(first):
    code = (f"import importlib; from imu_array_ros import workflows\n"
            f"importlib.import_module({first!r}) if '.' in {first!r} else getattr(workflows, {first!r})\n"
            f"bad = [n for n, m in workflows.EXPORTS.items() if getattr(workflows, n) is not "
            f"getattr(importlib.import_module(m), n)]\n"
            f"assert not bad, bad\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_no_workflows_module_is_named_like_an_export():
    names = {m.rsplit(".", 1)[1] for m in workflows.EXPORTS.values() if m.startswith("imu_array_ros.workflows.")}
    assert not names & set(workflows.EXPORTS), names & set(workflows.EXPORTS)
