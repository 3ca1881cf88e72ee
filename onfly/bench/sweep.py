"""Config sweeps: run the benchmark over a grid of planner / verifier weights and tabulate.

A sweep file (``experiments/configs/sweep_*.toml``)::

    [sweep]
    name = "planner"
    base = "quick.toml"            # the benchmark config the grid modifies (relative to this file)
    methods = ["oracle"]           # optional: overrides the base config's methods
    runs = 1                       # optional
    [sweep.tasks]                  # optional: overrides the base config's task selection
    count = 10

    [grid]                         # dotted keys -> lists of values; the grid is their product
    planner.w_yaw = [0.5, 1.0, 2.0]
    planner.w_jerk = [1.0, 2.0]

A grid key is ``<table>.<field>`` with table ``planner``, ``esdf`` or ``verifier`` (shared by
every method), ``episode`` or ``world``, or ``methods.<name>.<field>`` for one method's options.
Each combination is an ordinary benchmark run in its own folder (``<out>/<combination>``), so
an interrupted sweep resumes, and ``ray_address`` runs every episode as a Ray task. The table
has one row per combination and method: SR, CR, FT, SPL and the smallest exact clearance to the
scene flown by any episode.
"""

from __future__ import annotations

import itertools
import json
import logging
import re
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from onfly.bench.runner import SHARED_TABLES, BenchConfig, BenchConfigError, run_bench

__all__ = ["SweepConfig", "SweepError", "apply_setting", "combinations", "run_sweep", "format_sweep"]

log = logging.getLogger(__name__)


class SweepError(ValueError):
    """A sweep file that cannot be used (the message names the file and key)."""


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


@dataclass(frozen=True)
class SweepConfig:
    """A parsed sweep: the base benchmark config and the grid (dotted key -> values)."""

    name: str
    base: BenchConfig
    grid: tuple[tuple[str, tuple], ...]
    source: str | None = None

    @classmethod
    def from_toml(cls, path: str | Path) -> "SweepConfig":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"sweep config not found: {path}")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise SweepError(f"{path}: not valid TOML: {exc}") from None
        bad = sorted(set(data) - {"sweep", "grid"})
        if bad:
            raise SweepError(f"{path}: unknown table(s) {bad}; valid: ['sweep', 'grid']")
        sw = dict(data.get("sweep", {}))
        allowed = {"name", "base", "methods", "runs", "seed", "tasks", "workers", "vlm"}
        bad = sorted(set(sw) - allowed)
        if bad:
            raise SweepError(f"{path}: [sweep]: unknown field(s) {bad}; valid: {sorted(allowed)}")
        if "base" not in sw:
            raise SweepError(f"{path}: [sweep]: field 'base' (the benchmark config to modify) is missing")
        base = BenchConfig.from_toml((path.parent / sw["base"]).resolve())
        changes: dict[str, Any] = {}
        if "methods" in sw:
            changes["methods"] = tuple(sw["methods"])
        for k in ("runs", "seed", "workers", "vlm"):
            if k in sw:
                changes[k] = sw[k]
        if "tasks" in sw:
            t = sw["tasks"]
            changes.update(
                task_ids=tuple(t["ids"]) if "ids" in t else None,
                scenes=tuple(t["scenes"]) if "scenes" in t else None,
                kinds=tuple(t["kinds"]) if "kinds" in t else None,
                count=t.get("count"),
            )
        try:
            base = replace(base, name=str(sw.get("name", path.stem)), **changes)
        except (TypeError, BenchConfigError) as exc:
            raise SweepError(f"{path}: [sweep]: {exc}") from None
        grid = _flatten(dict(data.get("grid", {})))
        if not grid:
            raise SweepError(f"{path}: [grid] lists no values (e.g. planner.w_yaw = [0.5, 1.0, 2.0])")
        items = []
        for key, values in grid.items():
            if not isinstance(values, list) or not values:
                raise SweepError(f"{path}: grid key {key!r}: expected a non-empty list of values, got {values!r}")
            apply_setting(base, key, values[0], where=str(path))  # validates the key
            items.append((key, tuple(values)))
        return cls(base.name, base, tuple(items), str(path))


def apply_setting(config: BenchConfig, key: str, value: Any, where: str = "") -> BenchConfig:
    """``config`` with one dotted key set (see the module docstring for valid keys)."""
    parts = key.split(".")
    pre = f"{where}: " if where else ""
    if len(parts) == 2 and parts[0] in SHARED_TABLES:
        shared = {k: dict(v) for k, v in config.shared.items()}
        shared.setdefault(parts[0], {})[parts[1]] = value
        return replace(config, shared=shared)
    if len(parts) == 2 and parts[0] in ("episode", "world"):
        table = dict(getattr(config, parts[0]))
        table[parts[1]] = value
        try:
            return replace(config, **{parts[0]: table})
        except BenchConfigError as exc:
            raise SweepError(f"{pre}grid key {key!r}: {exc}") from None
    if len(parts) == 3 and parts[0] == "methods":
        opts = {k: dict(v) for k, v in config.method_options.items()}
        opts.setdefault(parts[1], {})[parts[2]] = value
        return replace(config, method_options=opts)
    raise SweepError(
        f"{pre}grid key {key!r}: expected <table>.<field> with table in {list(SHARED_TABLES) + ['episode', 'world']}, "
        "or methods.<name>.<field>"
    )


def combinations(sweep: SweepConfig) -> list[dict[str, Any]]:
    """Every combination of the grid, as {dotted key: value}, in row-major order."""
    keys = [k for k, _ in sweep.grid]
    return [dict(zip(keys, vals)) for vals in itertools.product(*(v for _, v in sweep.grid))]


def _slug(combo: dict[str, Any]) -> str:
    s = "_".join(f"{k.split('.')[-1]}={v}" for k, v in combo.items())
    return re.sub(r"[^A-Za-z0-9_.=+-]", "-", s)


def run_sweep(
    sweep: SweepConfig,
    out_dir: str | Path,
    *,
    workers: int | None = None,
    ray_address: str | None = None,
    progress: bool = False,
) -> list[dict]:
    """Run every combination (resumable) and return the table rows (one per combination x method).

    A method whose factory rejects a combination's option (e.g. a planner field it does not
    know) fails loudly: the grid keys are validated by the methods themselves.
    """
    out = Path(out_dir)
    rows = []
    for combo in combinations(sweep):
        cfg = sweep.base
        for k, v in combo.items():
            cfg = apply_setting(cfg, k, v)
        res = run_bench(cfg, out / _slug(combo), workers=workers, ray_address=ray_address, progress=progress)
        for method, block in res.summary["methods"].items():
            rows.append(
                {
                    **combo,
                    "method": method,
                    "episodes": block["episodes"],
                    "SR": block["SR"],
                    "OSR": block["OSR"],
                    "CR": block["CR"],
                    "FT": block["FT"],
                    "SPL": block["SPL"],
                    "min_clearance_m": block.get("min_clearance_m"),
                    "realtime_factor": block.get("realtime_factor"),
                }
            )
    (out / "sweep.json").write_text(json.dumps({"name": sweep.name, "grid": [list(g) for g in sweep.grid], "rows": rows}, indent=1))
    (out / "sweep.md").write_text(format_sweep(rows, [k for k, _ in sweep.grid]) + "\n")
    return rows


def format_sweep(rows: list[dict], keys: list[str]) -> str:
    """Markdown table, one row per combination and method."""

    def f(x, fmt, scale=1.0):
        return "n/a" if x is None else fmt.format(scale * x)

    head = "| " + " | ".join(keys) + " | method | episodes | SR % | CR % | FT s | SPL | min clearance m |"
    sep = "| " + " | ".join("---:" for _ in keys) + " | --- | ---: | ---: | ---: | ---: | ---: | ---: |"
    lines = [head, sep]
    for r in rows:
        cells = [str(r[k]) for k in keys] + [
            r["method"], str(r["episodes"]), f(r["SR"], "{:.1f}", 100.0), f(r["CR"], "{:.1f}", 100.0),
            f(r["FT"], "{:.1f}"), f(r["SPL"], "{:.2f}"), f(r["min_clearance_m"], "{:.2f}"),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
