"""The ``onfly`` command line.

Each subcommand lives in its own module under :mod:`onfly.commands` and exposes
``NAME`` (the subcommand), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Modules are found at start-up, so adding a command never edits this file.
Commands write their reports and status lines with :func:`echo`; errors leave as
:class:`CliError` and become one line on stderr here.

Start-up stays fast: the command list and its one-line helps are read from the modules'
source (``NAME`` / ``HELP`` constants, no import), and only the module of the command asked
for is imported. Command modules import the heavy stack (open3d, torch, casadi, scipy,
rosbags, the planner) inside ``run``, so ``onfly --help``, ``onfly <command> --help`` and
argument errors never load it (``tests/test_cli_startup.py`` holds every command to that).

Values that start with a minus sign (``--pose -3,0,6,0``, ``--goal -1.5,2,1``) are read as
values, not as options: argparse alone refuses them.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import logging
import pkgutil
import re
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["main", "build_parser", "CliError", "task_by_id", "command_specs", "echo"]

_COMMANDS_PACKAGE = "onfly.commands"
_COMMANDS_DIR = Path(__file__).resolve().parent / "commands"

#: A value made of numbers separated by commas (or one negative number): ``-3,0,6,0``, ``-2.5``.
_NUMBERS = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(,\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)*$")


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2, no traceback."""


def echo(line: str = "") -> None:
    """Write one line of a command's output to stdout, flushed: the one writer of the commands'
    reports and status lines. A command that is also called as a library function (``onfly
    sim-vehicle``'s ``run``) takes its writer as an argument, with this one as the default."""
    print(line, flush=True)


def task_by_id(task_id: str, files=None):
    """The benchmark task ``task_id`` (:class:`onfly.bench.tasks.Task`) from the committed task
    files, the paper's set and the groups in its subfolders (the hard set), or from ``files``;
    a CliError naming some valid ids."""
    from onfly.bench.tasks import committed_task_files, load_tasks

    tasks = load_tasks(committed_task_files() if files is None else files)
    for t in tasks:
        if t.task_id == task_id:
            return t
    near = sorted(t.task_id for t in tasks)[:10]
    raise CliError(f"no task {task_id!r}; some valid ids: {', '.join(near)} (all: `onfly tasks list`)")


@dataclass(frozen=True)
class CommandSpec:
    """A subcommand found in :mod:`onfly.commands` without importing it."""

    name: str
    help: str
    module: str


def _constant(tree: ast.Module, name: str) -> str | None:
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                return None
            return value if isinstance(value, str) else None
    return None


def command_specs() -> list[CommandSpec]:
    """Every subcommand (name, one-line help, module), sorted by module name, read from the
    modules' source so nothing is imported."""
    out = []
    for info in sorted(pkgutil.iter_modules([str(_COMMANDS_DIR)]), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        path = _COMMANDS_DIR / f"{info.name}.py"
        module = f"{_COMMANDS_PACKAGE}.{info.name}"
        try:
            tree = ast.parse(path.read_text(), str(path))
            name, help_ = _constant(tree, "NAME"), _constant(tree, "HELP")
        except (OSError, SyntaxError):
            name = help_ = None
        if name is None:  # not a literal: fall back to importing the module
            mod = importlib.import_module(module)
            name, help_ = mod.NAME, mod.HELP
        out.append(CommandSpec(name, help_ or "", module))
    return out


def _chosen(argv: list[str], names: set[str]) -> str | None:
    """The subcommand named in ``argv`` (the first token that is not a top-level option)."""
    for tok in argv:
        if tok == "--":
            return None
        if tok.startswith("-"):
            continue
        return tok if tok in names else None
    return None


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser. With ``argv``, only the command ``argv`` names gets its full arguments (its
    module is imported); without it, every command's module is imported."""
    parser = argparse.ArgumentParser(
        prog="onfly",
        description="Onboard zero-shot aerial vision-language navigation toolkit.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug and tracebacks)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    specs = command_specs()
    wanted = None if argv is None else _chosen(argv, {s.name for s in specs})
    for spec in specs:
        if argv is not None and spec.name != wanted:
            sub.add_parser(spec.name, help=spec.help, add_help=False)
            continue
        mod = importlib.import_module(spec.module)
        p = sub.add_parser(spec.name, help=spec.help, description=getattr(mod, "DESCRIPTION", spec.help))
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def attach_negative_values(argv: list[str]) -> list[str]:
    """``["--pose", "-3,0,6,0"]`` -> ``["--pose=-3,0,6,0"]``: an option followed by a number
    list that starts with a minus sign takes it as its value."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else None
        if tok.startswith("--") and "=" not in tok and nxt is not None and _NUMBERS.match(nxt):
            out.append(f"{tok}={nxt}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    argv = attach_negative_values(list(sys.argv[1:] if argv is None else argv))
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print("onfly: interrupted", file=sys.stderr)
        return 130
    except (CliError, FileNotFoundError, ValueError) as exc:
        # Named errors of the toolkit subclass ValueError/RuntimeError with messages that
        # name the file and field at fault; users get that line, not a traceback.
        if args.verbose >= 2:
            raise
        msg = " ".join(str(exc).split())
        print(f"onfly {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    # run through the imported module so commands and this entry share one CliError class
    from onfly.cli import main as _main

    sys.exit(_main())
