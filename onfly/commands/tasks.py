"""``onfly tasks list|check``: the benchmark's task files.

``onfly tasks list [--scene S] [--kind K]`` prints one line per task. ``onfly tasks check``
proves each selected task solvable and its goal visible (:mod:`onfly.bench.checker`) and
compares the result with the reference committed in the file; ``--write`` stores the new
references in the files (the committed files hold them, so benchmark runs never recompute).
Exit status 1 when a task fails the check or its committed reference is missing or stale.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

from onfly.cli import CliError, echo

#: Task kinds (as :data:`onfly.bench.tasks.KINDS`; kept here so ``--help`` imports nothing heavy).
KINDS = ("object", "precise", "long_range", "track")

NAME = "tasks"
HELP = "list the benchmark tasks or check that each is solvable (and write the reference paths)"

#: A committed reference is stale when its length differs from a fresh check by more than this.
STALE_LENGTH_M = 0.05

HEADER = (
    "Benchmark tasks (format: onfly/bench/tasks.py). The [tasks.reference] tables are written by\n"
    "`onfly tasks check --write` (onfly/bench/checker.py); edit the rest by hand."
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, help_ in (("list", "one line per task"), ("check", "prove the tasks solvable and compare the references")):
        p = sub.add_parser(name, help=help_)
        p.add_argument("--files", nargs="+", default=None, help="task files (default: the committed ones)")
        p.add_argument("--tasks", default=None, help="comma-separated task ids")
        p.add_argument("--scene", action="append", default=None, help="only this scene (repeatable)")
        p.add_argument("--kind", action="append", choices=KINDS, default=None, help="only this kind (repeatable)")
        p.add_argument("--count", type=int, default=None, help="an evenly spread subset of this many tasks (over kinds and scenes)")
        if name == "check":
            p.add_argument("--write", action="store_true", help="store the new references in the task files")
            p.add_argument("--json", default=None, help="write the per-task results to this JSON file")
            p.add_argument("--no-progress", action="store_true", help="no progress bar (as `onfly bench`)")


def _scene_ref(path: Path) -> str | None:
    """The ``scene`` string a task file holds (a name or an external scene's path)."""
    import tomllib

    with open(path, "rb") as fh:
        value = tomllib.load(fh).get("scene")
    return value if isinstance(value, str) else None


def _header(path: Path) -> str:
    """The comment block a task file opens with (without the ``#``), kept when references are
    written; :data:`HEADER` for a file that has none."""
    lines = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        lines.append(line[1:].removeprefix(" "))
    return "\n".join(lines) if lines else HEADER


def _selected(args) -> list:
    if args.count is not None and args.count < 1:
        raise CliError(f"--count must be a positive integer, got {args.count}")
    from onfly.bench.tasks import load_tasks, select_tasks

    tasks = load_tasks(args.files)
    ids = [s for s in args.tasks.split(",") if s] if args.tasks else None
    try:
        return select_tasks(tasks, ids=ids, scenes=args.scene, kinds=args.kind, count=args.count)
    except ValueError as exc:
        raise CliError(f"task selection: {exc}") from None


def run(args) -> int:
    tasks = _selected(args)
    if args.action == "list":
        for t in tasks:
            ref = f"{t.reference.path_length_m:5.1f} m" if t.reference else "unchecked"
            echo(f"{t.task_id:22s} {t.kind:10s} {ref:>9s}  {t.instruction}")
        echo(f"{len(tasks)} tasks")
        return 0
    import numpy as np
    from tqdm import tqdm

    from onfly.bench.checker import CheckerConfig, check_tasks
    from onfly.bench.tasks import load_task_file, write_task_file

    with tqdm(total=len(tasks), desc="checking", unit="task", disable=args.no_progress) as bar:
        results = check_tasks(tasks, CheckerConfig(), progress=bar)
    failed = stale = 0
    rows = []
    for t, r in zip(tasks, results):
        status = "ok"
        if not r.ok:
            status, failed = "FAIL", failed + 1
        elif t.reference is None or abs(t.reference.path_length_m - r.reference.path_length_m) > STALE_LENGTH_M:
            status, stale = "written" if args.write else ("unchecked" if t.reference is None else "stale"), stale + 1
        length = r.reference.path_length_m if r.reference else float("nan")
        echo(f"{t.task_id:22s} {status:9s} path {length:5.1f} m  straight to region {r.straight_distance_m:5.1f} m  {'; '.join(r.problems)}")
        rows.append({"task": t.task_id, "status": status, "problems": list(r.problems), "path_length_m": None if np.isnan(length) else length})
    if args.write:
        by_file: dict[Path, dict] = defaultdict(dict)
        for t, r in zip(tasks, results):
            if r.ok:
                by_file[t.source][t.task_id] = r.reference
        for path, refs in by_file.items():
            every = load_task_file(path)
            write_task_file(path, every[0].scene, [t.with_reference(refs.get(t.task_id, t.reference)) for t in every],
                            _header(path), scene_ref=_scene_ref(path))
        echo(f"wrote references of {sum(len(v) for v in by_file.values())} tasks to {len(by_file)} files")
    if args.json:
        Path(args.json).write_text(json.dumps({"tasks": rows, "failed": failed, "stale": stale}, indent=1))
    fresh = f"{stale} written (were stale or unchecked)" if args.write else f"{stale} stale or unchecked"
    echo(f"{len(tasks)} tasks: {len(tasks) - failed - stale} ok, {fresh}, {failed} failed")
    return 1 if failed or (stale and not args.write) else 0
