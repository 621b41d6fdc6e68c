"""``imu-array``: the parser assembled from the subcommand modules, and :func:`main`.

Each subcommand module (:mod:`.simulate`, :mod:`.fuse`, ..., :mod:`.calibrate`) has
``add_parser(subparsers)``, which declares its options and sets ``handler``: a
function whose keyword parameters are exactly the options' ``dest`` names, with
type annotations.  :func:`main` calls ``handler(**options)``;
:func:`handler_problems` says where a parser and its handler disagree (a renamed
option, a missing annotation, a different default), so the test suite, not a
user, finds it (``test/test_cli_structure.py``).
"""

from __future__ import annotations

import argparse
import inspect
import os
import sys
import typing
from typing import Callable, Iterator

from imu_array_ros.cli import (calibrate, discover, export, fake_device, fuse, import_kalibr, import_openshoe,
                               recover, residuals, simulate)
from imu_array_ros.errors import ImuArrayError
from imu_array_ros.version import __version__

__all__ = ["main", "build_parser", "EXIT_USER_ERROR", "UsageError", "subcommands", "handler_options",
           "handler_problems"]

EXIT_USER_ERROR = 2
#: what the parser itself sets: the subcommand names and the handler, not passed to the handler
NOT_OPTIONS = frozenset({"handler", "command", "calibration_command", "format_command"})


class UsageError(Exception):
    """A command line argparse rejects; printed as one line by :func:`main`."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage mistake as one line instead of usage + exit."""

    def error(self, message: str):  # noqa: D401 - argparse API
        raise UsageError(f"{message} (see '{self.prog} --help')")


def build_parser() -> argparse.ArgumentParser:
    """The ``imu-array`` parser; each subcommand's ``handler`` is the typed function to call."""
    p = _Parser(prog="imu-array", description="Inertial sensor array tools (imu_array_ros).")
    p.add_argument("--version", action="version", version=f"imu-array {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (simulate, fuse, import_openshoe, fake_device, residuals, calibrate, discover, recover, export,
                   import_kalibr):
        module.add_parser(sub)
    return p


# --------------------------------------------------------------------------- parser <-> handler


def subcommands(parser: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """(prog, parser) of every leaf subcommand of ``parser`` (``imu-array calibrate fit``, ...)."""
    groups = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not groups:
        yield parser.prog, parser
    for group in groups:
        for sp in dict.fromkeys(group.choices.values()):  # aliases map to the same parser
            yield from subcommands(sp)


def handler_options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action | None]:
    """dest -> action of everything :func:`main` passes to the parser's handler (a ``set_defaults``
    value other than the handler: None)."""
    out: dict[str, argparse.Action | None] = {}
    for a in parser._actions:
        # --help and --version never reach the namespace (their default is SUPPRESS)
        if argparse.SUPPRESS not in (a.dest, a.default) and not isinstance(a, argparse._SubParsersAction):
            out[a.dest] = a
    for key in parser._defaults:
        out.setdefault(key, None)
    return {k: v for k, v in out.items() if k not in NOT_OPTIONS}


def _flag(action: argparse.Action | None, dest: str) -> str:
    if action is None or not action.option_strings:
        return dest
    return f"{action.option_strings[-1]} (dest {dest!r})"


def handler_problems(parser: argparse.ArgumentParser, handler: Callable | None = None) -> list[str]:
    """Where ``parser``'s options and ``handler`` (default: the one the parser sets) disagree: an option
    that is not a parameter, a parameter that is no option, a parameter or return value without a type
    annotation (or one that does not resolve), an optional option whose default differs from the
    parameter's, a required one whose parameter has a default.  Empty: they agree."""
    prog = parser.prog
    handler = handler if handler is not None else parser.get_default("handler")
    if handler is None:
        return [f"{prog}: no handler (add_parser must call set_defaults(handler=...))"]
    name = getattr(handler, "__qualname__", repr(handler))
    options = handler_options(parser)
    sig = inspect.signature(handler)
    params = {n: p for n, p in sig.parameters.items() if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
    problems = []
    if len(params) != len(sig.parameters):
        problems.append(f"{prog}: {name} takes *args or **kwargs: its parameters must name every option")
    for dest, action in options.items():
        if dest not in params:
            problems.append(f"{prog}: option {_flag(action, dest)} is not a parameter of {name}")
    for pname, param in params.items():
        if pname not in options:
            problems.append(f"{prog}: parameter {pname!r} of {name} is not an option")
        if param.annotation is inspect.Parameter.empty:
            problems.append(f"{prog}: parameter {pname!r} of {name} has no type annotation")
    if sig.return_annotation is inspect.Signature.empty:
        problems.append(f"{prog}: {name} has no return annotation")
    try:
        typing.get_type_hints(handler)
    except Exception as err:  # a misspelt annotation: NameError, TypeError, ...
        problems.append(f"{prog}: the annotations of {name} do not resolve: {err}")
    for dest, action in options.items():
        param = params.get(dest)
        if param is None or action is None:
            continue
        required = action.required or not action.option_strings
        if required and param.default is not inspect.Parameter.empty:
            problems.append(f"{prog}: {_flag(action, dest)} is required but {name} gives it a default")
        elif not required and param.default is inspect.Parameter.empty:
            problems.append(f"{prog}: {_flag(action, dest)} is optional but {name} has no default for it")
        elif not required and param.default != action.default:
            problems.append(f"{prog}: {_flag(action, dest)} defaults to {action.default!r} in the parser "
                            f"but to {param.default!r} in {name}")
    return problems


# --------------------------------------------------------------------------- running it


def main(argv: list[str] | None = None) -> int:
    """Run ``imu-array`` with ``argv`` (default ``sys.argv[1:]``); return the exit status.

    0 on success; 2 with one line ``imu-array: error: ...`` on stderr for a user
    mistake (bad option, bad file, unsafe output); 130 on Ctrl-C.
    """
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as err:
        print(f"imu-array: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else 0
    options = {k: v for k, v in vars(args).items() if k not in NOT_OPTIONS}
    try:
        return int(args.handler(**options) or 0)
    except ImuArrayError as err:
        print(f"imu-array: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("imu-array: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
