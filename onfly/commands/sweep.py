"""``onfly sweep --config experiments/configs/sweep_*.toml``: run a grid of planner / verifier
weights over a task subset and print the table researchers tune from (see
:mod:`onfly.bench.sweep`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from onfly.bench.sweep import SweepConfig, combinations, format_sweep, run_sweep

NAME = "sweep"
HELP = "run the benchmark over a grid of config values and print SR / CR / FT / clearance per combination"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, help="sweep TOML (experiments/configs/sweep_*.toml)")
    parser.add_argument("--workers", type=int, default=None, help="local worker processes per combination")
    parser.add_argument("--out", default=None, help="output folder (default runs/sweep/<name>); reruns resume")
    parser.add_argument("--json", default=None, help="also write the table rows as JSON here")
    parser.add_argument("--ray", default=None, metavar="ADDRESS", help="run episodes as Ray tasks: a cluster address or 'local'")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args) -> int:
    sweep = SweepConfig.from_toml(args.config)
    out = Path(args.out) if args.out else Path("runs") / "sweep" / sweep.name
    print(f"sweep {sweep.name}: {len(combinations(sweep))} combinations of {', '.join(k for k, _ in sweep.grid)}")
    rows = run_sweep(sweep, out, workers=args.workers, ray_address=args.ray, progress=not args.no_progress)
    print(format_sweep(rows, [k for k, _ in sweep.grid]))
    print(f"results in {out}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0
