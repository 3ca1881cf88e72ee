"""The ``onfly`` command line.

Each subcommand lives in its own module under :mod:`onfly.commands` and exposes
``NAME`` (the subcommand), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Modules are found at start-up, so adding a command never edits this file.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

import onfly.commands

__all__ = ["main", "build_parser", "CliError", "task_by_id"]


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2, no traceback."""


def task_by_id(task_id: str):
    """The benchmark task ``task_id`` (:class:`onfly.bench.tasks.Task`), or a CliError naming
    some valid ids."""
    from onfly.bench.tasks import load_tasks

    tasks = load_tasks()
    for t in tasks:
        if t.task_id == task_id:
            return t
    near = sorted(t.task_id for t in tasks)[:10]
    raise CliError(f"no task {task_id!r}; some valid ids: {', '.join(near)} (all: `onfly tasks list`)")


def _command_modules():
    for info in sorted(pkgutil.iter_modules(onfly.commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        yield importlib.import_module(f"onfly.commands.{info.name}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="onfly",
        description="Onboard zero-shot aerial vision-language navigation toolkit.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
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
        print(f"onfly {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    # run through the imported module so commands and this entry share one CliError class
    from onfly.cli import main as _main

    sys.exit(_main())
