"""``onfly bench --config experiments/configs/<name>.toml``: run the embedded benchmark.

Runs every selected method on every selected task ``runs`` times (in parallel, resumable;
see :mod:`onfly.bench.runner`), prints the summary table per method and task kind, and writes
``episodes.jsonl``, ``summary.json`` and ``summary.md`` to the output folder (default
``runs/bench/<config name>``); ``--json PATH`` writes the summary JSON there as well. A TERM
or Ctrl-C stops the worker processes with the command; the finished episodes stay on disk and a
rerun resumes.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

from onfly.cli import CliError, echo
from onfly.console import status

#: Task kinds (as :data:`onfly.bench.tasks.KINDS`; kept here so ``--help`` imports nothing heavy).
KINDS = ("object", "precise", "long_range", "track")

NAME = "bench"
HELP = "run the embedded benchmark (methods x tasks x runs) and print SR / OSR / CR / FT / NE / SPL"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="benchmark config TOML (experiments/configs/*.toml)")
    parser.add_argument("--methods", default=None, help="comma-separated method names (overrides the config)")
    sel = parser.add_mutually_exclusive_group()
    sel.add_argument("--tasks", default=None, help="comma-separated task ids")
    sel.add_argument("--scene", default=None, help="only the tasks of this scene")
    sel.add_argument("--kind", default=None, choices=KINDS, help="only tasks of this kind")
    sel.add_argument("--count", type=int, default=None, help="an evenly spread subset of this many tasks (over kinds and scenes)")
    parser.add_argument("--runs", type=int, default=None, help="runs per task (the paper: 3)")
    parser.add_argument("--seed", type=int, default=None, help="base seed")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes")
    parser.add_argument("--out", default=None, help="output folder (default runs/bench/<config name>); reruns resume")
    parser.add_argument("--json", default=None, help="also write the summary JSON here")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="run episodes as Ray tasks: a cluster address or 'local'")
    parser.add_argument("--vlm", default=None, help="VLM spec for every method, e.g. sim:nominal")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--allow-mixed-code", action="store_true",
                        help="resume an --out folder whose episodes other code flew (refused by default: one table, one code version)")


def build_config(args):
    from onfly.bench.runner import BenchConfig, with_overrides

    cfg = BenchConfig.from_toml(args.config)
    changes: dict = {}
    if args.methods:
        changes["methods"] = tuple(m for m in args.methods.split(",") if m)
    if args.tasks:
        changes.update(task_ids=tuple(t for t in args.tasks.split(",") if t), scenes=None, kinds=None, count=None)
    elif args.scene:
        changes.update(scenes=(args.scene,), task_ids=None, kinds=None, count=None)
    elif args.kind:
        changes.update(kinds=(args.kind,), task_ids=None, scenes=None, count=None)
    elif args.count is not None:
        changes.update(count=args.count, task_ids=None, scenes=None, kinds=None)
    if changes:
        cfg = replace(cfg, **changes)
    return with_overrides(cfg, runs=args.runs, seed=args.seed, vlm=args.vlm, workers=args.workers)


def run(args) -> int:
    if args.ray is not None and not args.ray.strip():
        raise CliError("--ray needs a cluster address or 'local'")
    for option in ("runs", "workers", "count"):
        v = getattr(args, option)
        if v is not None and v < 1:
            raise CliError(f"--{option} must be a positive integer, got {v}")
    if args.seed is not None and args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    from onfly.bench.runner import check_bench, format_summary, run_bench, sigterm_exits

    cfg = build_config(args)
    tasks = check_bench(cfg)  # before anything is written or flown
    out = Path(args.out) if args.out else Path("runs") / "bench" / cfg.name
    t0 = time.perf_counter()
    with sigterm_exits():  # a TERM stops the workers too; finished episodes stay, a rerun resumes
        res = run_bench(cfg, out, ray_address=args.ray, progress=not args.no_progress, checked_tasks=tasks,
                        allow_mixed_code=args.allow_mixed_code)  # MixedCodeError: a usage error, nothing flown
    echo(format_summary(res.summary))
    echo(
        f"\n{res.ran} episodes run, {res.skipped} already done (resumed), wall {time.perf_counter() - t0:.1f} s, "
        f"realtime factor {res.summary.get('realtime_factor') or float('nan'):.2f} "
        f"(per CPU second {res.summary.get('realtime_factor_cpu') or float('nan'):.2f}); results in {out}"
    )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res.summary, indent=1))
    if res.errored:
        status(f"\n{len(res.errored)} episode(s) ended with a method error (see {out}/episodes.jsonl):")
        for line in res.errored[:10]:
            status(f"  {line}")
        return 1
    return 0
