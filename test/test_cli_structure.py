"""The command line's structure: every subcommand's parser agrees with its typed handler.

``main`` calls ``handler(**vars(args))``; a renamed option (or parameter) would
otherwise break only when a user runs that subcommand.  ``handler_problems``
compares the parser's option dests with the handler's parameter names both
ways, requires a type annotation on every parameter and the return value, and
the same defaults in both places.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

from imu_array_ros.cli import build_parser
from imu_array_ros.cli.parser import handler_options, handler_problems, subcommands

CLI = Path(__file__).resolve().parents[1] / "imu_array_ros" / "cli"

LEAVES = [prog for prog, _ in subcommands(build_parser())]


def test_every_subcommand_is_found():
    assert LEAVES == ["imu-array simulate", "imu-array fuse", "imu-array import-openshoe", "imu-array fake-device",
                      "imu-array residuals", "imu-array calibrate fit", "imu-array calibrate geometry",
                      "imu-array calibrate bayes", "imu-array calibrate static", "imu-array calibrate all",
                      "imu-array calibrate noise", "imu-array discover", "imu-array recover",
                      "imu-array export kalibr", "imu-array import kalibr"]


@pytest.mark.parametrize("prog", LEAVES)
def test_parser_and_handler_agree(prog):
    parser = dict(subcommands(build_parser()))[prog]
    handler = parser.get_default("handler")
    assert handler is not None and handler.__module__.startswith("imu_array_ros.cli."), handler
    assert handler_problems(parser) == []
    assert set(handler_options(parser)) and "handler" not in handler_options(parser)


# --------------------------------------------------------------------------- the check catches a mismatch


def _tiny(handler, *, rename: str | None = None) -> argparse.ArgumentParser:
    """``tool cmd REC --out OUT [--seed N] [-q]`` with ``--out`` declared as ``rename`` if given."""
    p = argparse.ArgumentParser(prog="tool")
    sp = p.add_subparsers(dest="command").add_parser("cmd", prog="tool cmd")
    sp.add_argument("recording", type=Path)
    sp.add_argument(rename or "--out", required=True, type=Path)
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("-q", "--quiet", action="store_true")
    sp.set_defaults(handler=handler)
    return sp


def good(recording: Path, *, out: Path, seed: int = 0, quiet: bool = False) -> int:
    return 0


def test_a_matching_pair_passes():
    assert handler_problems(_tiny(good)) == []


def test_a_renamed_option_is_reported_both_ways():
    problems = handler_problems(_tiny(good, rename="--output"))
    assert any("--output (dest 'output') is not a parameter of good" in p for p in problems), problems
    assert any("parameter 'out' of good is not an option" in p for p in problems), problems
    assert all(p.startswith("tool cmd: ") for p in problems) and len(problems) == 2, problems


def test_a_renamed_parameter_is_reported():
    def renamed(recording: Path, *, out_path: Path, seed: int = 0, quiet: bool = False) -> int:
        return 0

    problems = handler_problems(_tiny(renamed))
    assert any("--out (dest 'out') is not a parameter" in p for p in problems), problems
    assert any("parameter 'out_path'" in p and "not an option" in p for p in problems), problems


def test_missing_annotations_kwargs_and_defaults_are_reported():
    def untyped(recording, *, out: Path, seed=0, quiet: bool = False):
        return 0

    problems = handler_problems(_tiny(untyped))
    assert any("'recording'" in p and "no type annotation" in p for p in problems), problems
    assert any("'seed'" in p and "no type annotation" in p for p in problems), problems
    assert any("no return annotation" in p for p in problems), problems

    def kwargs(recording: Path, **options) -> int:
        return 0

    assert any("**kwargs" in p for p in handler_problems(_tiny(kwargs)))

    def other_default(recording: Path, *, out: Path, seed: int = 1, quiet: bool = False) -> int:
        return 0

    assert any("--seed" in p and "defaults to 0" in p for p in handler_problems(_tiny(other_default)))

    def misspelt(recording: "Pathh", *, out: Path, seed: int = 0, quiet: bool = False) -> int:  # noqa: F821
        return 0

    assert any("do not resolve" in p for p in handler_problems(_tiny(misspelt)))


def test_the_real_parser_against_another_handler_fails():
    """A real subcommand's parser with the wrong handler (as after a rename): reported, not run."""
    subs = dict(subcommands(build_parser()))
    problems = handler_problems(subs["imu-array fuse"], subs["imu-array recover"].get_default("handler"))
    assert any("--array (dest 'array') is not a parameter" in p for p in problems), problems


# --------------------------------------------------------------------------- module layout


def test_every_subcommand_module_has_its_parser_beside_its_handler():
    """Each handler lives in the module that declares its options; no module of the CLI is large."""
    for prog, parser in subcommands(build_parser()):
        handler = parser.get_default("handler")
        module = __import__(handler.__module__, fromlist=["add_parser"])
        assert callable(getattr(module, "add_parser", None)), (prog, handler.__module__)
    for path in CLI.rglob("*.py"):
        lines = path.read_text(encoding="utf-8").count("\n")
        assert lines < 250, (path, lines)
        ast.parse(path.read_text(encoding="utf-8"))
