"""``onfly sweep --config experiments/configs/sweep_*.toml``: the tuning tool. Run the benchmark
over a grid of planner / verifier weights or over trials sampled by Optuna, print the table of
what the weights change, and draw it (see :mod:`onfly.bench.sweep`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from onfly.cli import CliError, echo
from onfly.console import status

NAME = "sweep"
HELP = "tune weights: grid or sampled (Optuna) search; SR / CR / FT beside jerk, clearance, path, yaw error; HTML plots"
DESCRIPTION = """Run the benchmark over planner / verifier weights: a [grid] (every combination) or a
[search] (trials sampled by Optuna, resumable in SQLite). Every row reports SR / CR / FT / SPL
beside what weights change: RMS acceleration and jerk, path length, minimum clearance, time to
goal and yaw error to the goal bearing. A live line names the combination being flown.

Writes into the output folder (default runs/sweep/<name>; a rerun resumes): one benchmark
folder per combination, sweep.md (the table), sweep.json, sweep.html (table + one scatter plot
per metric and key, opens offline) and, for a search, study.db and study.html (Optuna's plots).

examples:
  onfly sweep --config experiments/configs/sweep_planner.toml --workers 2
  onfly sweep --config experiments/configs/tune_planner.toml --trials 12
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--config", required=True, type=Path, help="sweep TOML (experiments/configs/sweep_*.toml, tune_*.toml)")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes per combination")
    parser.add_argument("--trials", type=int, default=None, help="search: run this many more trials (default: up to [search] trials)")
    parser.add_argument("--sampler-seed", type=int, default=None,
                        help="search: the sampler's seed instead of [search] seed (give each of several processes sharing one study its own)")
    parser.add_argument("--out", default=None, help="output folder (default runs/sweep/<name>); reruns resume")
    parser.add_argument("--json", default=None, help="also write the table rows as JSON here")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="run episodes as Ray tasks: a cluster address or 'local'")
    parser.add_argument("--no-progress", action="store_true", help="no live progress line")


def run(args) -> int:
    for option in ("workers", "trials"):
        v = getattr(args, option)
        if v is not None and v < 1:
            raise CliError(f"--{option} must be a positive integer, got {v}")
    if args.ray is not None and not args.ray.strip():
        raise CliError("--ray needs a cluster address or 'local'")
    from onfly.bench.sweep import SweepConfig, combinations, format_sweep, run_sweep

    sweep = SweepConfig.from_toml(args.config)
    if sweep.search is None and (args.trials is not None or args.sampler_seed is not None):
        raise CliError(f"--trials and --sampler-seed apply to a [search] config; {args.config} has a [grid]")
    if args.sampler_seed is not None:
        if args.sampler_seed < 0:
            raise CliError(f"--sampler-seed must be >= 0, got {args.sampler_seed}")
        from dataclasses import replace

        sweep = replace(sweep, search=replace(sweep.search, seed=args.sampler_seed))
    out = Path(args.out) if args.out else Path("runs") / "sweep" / sweep.name
    if sweep.search is None:
        echo(f"sweep {sweep.name}: {len(combinations(sweep))} combinations of {', '.join(sweep.keys)}")
    else:
        s = sweep.search
        echo(f"search {sweep.name}: {s.sampler} sampler (seed {s.seed}) over {', '.join(sweep.keys)}; "
             f"objectives {', '.join(f'{k}:{d}' for k, d in s.objectives)} of {s.method}")
    rows = run_sweep(sweep, out, workers=args.workers, ray_address=args.ray, progress=not args.no_progress, trials=args.trials)
    echo(format_sweep(rows, sweep.keys))
    pics = "sweep.html" + (", study.html" if (out / "study.html").exists() else "")
    echo(f"results in {out} (table sweep.md, pictures {pics})")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=1))
    errors = [r for r in rows if r.get("method_errors")]
    if errors:
        status(f"{len(errors)} row(s) hold episodes that ended with a method error; see the folders' episodes.jsonl")
        return 1
    return 0
