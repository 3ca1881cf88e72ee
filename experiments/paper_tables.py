"""The paper's three result tables, reproduced in the embedded world beside the published numbers.

Tables (paper, Sec. IV):

- **Table II**, zero-shot AVLN benchmark: TypeFly, PIVOT, SPF, OnFly;
- **planner control study**: SPF with our ESDF + MPC against OnFly;
- **Table III**, ablations: architecture (OnFly without the dual agent, the verification, the
  planner), memory (time sampling, sliding window, hybrid = OnFly) and VLM backbone (OnFly under
  the simulated-VLM presets ``weak`` / ``nominal`` / ``strong``, labelled as *stand-ins* for
  Qwen3-VL-2B / 4B / 30B-A3B: not fits of those models).

Every number is SR / OSR / CR in % and FT in s over ``tasks x runs`` episodes, under the
simulated-VLM error model the config names. A section per method lists how its episodes ended
(end reasons, failure classes) and the per-episode means of its own summary counters.

The config is a benchmark config (:class:`onfly.bench.runner.BenchConfig`: ``[bench]``,
``[episode]``, ``[world]``, shared tables, ``[methods.<name>]``) plus a ``[paper_tables]``
table::

    [paper_tables]
    # backbone rows: VLM spec -> the model it stands in for (one must be bench.vlm)
    backbones = [["sim:weak", "Qwen3-VL-2B"], ["sim:nominal", "Qwen3-VL-4B"], ["sim:strong", "Qwen3-VL-30B-A3B"]]
    # optional: run in chunks of this many tasks (every method and backbone per chunk)
    chunk_tasks = 10

``bench.methods`` is ignored: the methods are the tables' rows. Episodes run through the
benchmark runner into ``OUT/<error model>/`` (one folder per VLM spec; resumable: a run
started again skips finished episodes). With ``chunk_tasks`` the selected tasks are cut into
chunks that mix scenes and kinds (:func:`task_chunks`) and every method and backbone runs on
one chunk before the next starts: a long run stopped early holds comparable rows. Episode keys do not depend on the selection, so chunked and unchunked runs
of one config share their finished episodes. ``--from-runs DIR`` only reads finished episodes
of such a folder tree and runs nothing; rows without episodes show ``n/a``. ``--methods a,b``
runs only those rows (the backbone rows belong to ``onfly``) and reads the others from the
folder as they are: rows whose code did not change need not run again, and row groups can run
side by side into one folder (each episode is one appended line).

Run::

    .venv/bin/python experiments/paper_tables.py --config experiments/configs/paper_tables_quick.toml \\
        [--out runs/paper_quick] [--workers 2] [--json PATH] [--from-runs DIR] [--methods a,b]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Sequence

from onfly.bench.episode import END_REASONS
from onfly.bench.runner import (
    EPISODES_FILE,
    BenchConfig,
    error_model_name,
    plan_jobs,
    read_records,
    run_bench,
    summarize_records,
)
from onfly.bench.tasks import load_tasks, select_tasks

__all__ = [
    "PaperTablesConfig",
    "PaperTablesError",
    "PAPER",
    "TABLE2",
    "PLANNER_STUDY",
    "ARCHITECTURE",
    "MEMORY",
    "BACKBONE_METHOD",
    "load_config",
    "run_all",
    "check_methods",
    "task_chunks",
    "read_runs",
    "build_tables",
    "format_markdown",
    "main",
]

#: Rows of each table: (method name, row label). OnFly is every table's reference row.
TABLE2 = (("typefly", "TypeFly"), ("pivot", "PIVOT"), ("spf", "SPF"), ("onfly", "OnFly (ours)"))
PLANNER_STUDY = (("spf_planner", "SPF w/ planner"), ("onfly", "OnFly (ours)"))
ARCHITECTURE = (
    ("onfly", "OnFly (ours)"),
    ("onfly_no_dual_agent", "w/o Dual Agent"),
    ("onfly_no_verification", "w/o Verification"),
    ("onfly_no_planner", "w/o Planner"),
)
MEMORY = (("onfly_time_sampling", "Time Sampling"), ("onfly_sliding_window", "Sliding Windows"), ("onfly", "Hybrid Memory"))
BACKBONE_METHOD = "onfly"

#: The paper's published numbers: row label -> (SR %, OSR %, CR %, FT s).
PAPER: dict[str, tuple[float, float, float, float]] = {
    "TypeFly": (5.7, 17.5, 66.5, 35.4),
    "PIVOT": (10.3, 44.2, 64.1, 32.9),
    "SPF": (26.4, 61.5, 42.7, 39.2),
    "OnFly (ours)": (67.8, 78.1, 2.7, 27.1),
    "SPF w/ planner": (43.2, 80.3, 4.7, 50.2),
    "w/o Dual Agent": (48.6, 77.9, 2.9, 44.1),
    "w/o Verification": (63.7, 72.6, 3.2, 28.3),
    "w/o Planner": (35.8, 69.4, 37.5, 32.2),
    "Time Sampling": (64.2, 78.4, 2.9, 27.4),
    "Sliding Windows": (60.4, 79.5, 2.8, 28.3),
    "Hybrid Memory": (67.8, 78.1, 2.7, 27.1),
    "Qwen3-VL-2B": (43.4, 53.6, 2.6, 23.7),
    "Qwen3-VL-4B": (67.8, 78.1, 2.7, 27.1),
    "Qwen3-VL-30B-A3B": (71.8, 84.0, 2.5, 29.2),
}


class PaperTablesError(ValueError):
    """A paper-tables config that cannot be used (names the file and field)."""


@dataclass(frozen=True)
class PaperTablesConfig:
    """The benchmark config of the main VLM and the backbone rows.

    bench : BenchConfig (its ``vlm`` is the main error model of every table)
    backbones : ((VLM spec, stand-in label), ...), one of them ``bench.vlm``
    chunk_tasks : None (one run per VLM spec) or tasks per interleaved chunk
    source : the file it was read from
    """

    bench: BenchConfig
    backbones: tuple[tuple[str, str], ...]
    chunk_tasks: int | None = None
    source: str | None = None

    def __post_init__(self) -> None:
        c = self.chunk_tasks
        if c is not None and (isinstance(c, bool) or not isinstance(c, int) or c < 1):
            raise PaperTablesError(f"{self.source}: paper_tables.chunk_tasks must be a positive integer, got {c!r}")
        specs = [s for s, _ in self.backbones]
        if len(set(specs)) != len(specs):
            raise PaperTablesError(f"{self.source}: paper_tables.backbones lists a VLM spec twice: {specs}")
        if self.bench.vlm not in specs:
            raise PaperTablesError(f"{self.source}: paper_tables.backbones must include bench.vlm ({self.bench.vlm!r}), got {specs}")

    @property
    def main_methods(self) -> tuple[str, ...]:
        """Every method of the tables, run under the main VLM. The runner runs them in this
        order (method-major), so a long run that is cut short has the reference row and the
        Table II baselines first."""
        out: list[str] = [BACKBONE_METHOD, "spf", "typefly", "pivot"]
        for rows in (TABLE2, PLANNER_STUDY, ARCHITECTURE, MEMORY):
            for m, _ in rows:
                if m not in out:
                    out.append(m)
        return tuple(out)

    def bench_for(self, vlm: str, only: Sequence[str] | None = None) -> BenchConfig | None:
        """The benchmark config of one VLM spec: all methods under the main one, the backbone
        method under the others; ``only`` keeps just those methods (the order stays), None
        when that leaves none."""
        methods = self.main_methods if vlm == self.bench.vlm else (BACKBONE_METHOD,)
        if only is not None:
            methods = tuple(m for m in methods if m in only)
            if not methods:
                return None
        return replace(self.bench, vlm=vlm, methods=methods, name=f"{self.bench.name}-{error_model_name(vlm)}")


def load_config(path: str | Path) -> PaperTablesConfig:
    """Read a paper-tables TOML (module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"paper-tables config not found: {path}")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise PaperTablesError(f"{path}: not valid TOML: {exc}") from None
    own = dict(data.pop("paper_tables", {}) or {})
    bad = sorted(set(own) - {"backbones", "chunk_tasks"})
    if bad:
        raise PaperTablesError(f"{path}: [paper_tables]: unknown field(s) {bad}; valid: ['backbones', 'chunk_tasks']")
    bench = BenchConfig.from_dict(data, source=str(path))
    raw = own.get("backbones", [[bench.vlm, "main backbone"]])
    if not isinstance(raw, list) or not all(
        isinstance(b, list) and len(b) == 2 and all(isinstance(x, str) and x for x in b) for b in raw
    ):
        raise PaperTablesError(f"{path}: paper_tables.backbones must be a list of [vlm spec, label] pairs, got {raw!r}")
    return PaperTablesConfig(bench, tuple((s, lab) for s, lab in raw), own.get("chunk_tasks"), str(path))


def _out_dir(root: Path, vlm: str) -> Path:
    return root / error_model_name(vlm).replace(":", "_").replace("/", "_")


def _selected_ids(bench: BenchConfig) -> list[str]:
    tasks = select_tasks(load_tasks(bench.task_files), ids=bench.task_ids, scenes=bench.scenes, kinds=bench.kinds, count=bench.count)
    return [t.task_id for t in tasks]


def task_chunks(ids: Sequence[str], chunk_tasks: int | None) -> list[list[str]]:
    """Chunks of about ``chunk_tasks`` tasks that mix scenes and kinds: the tasks in a fixed
    pseudo-random order (by the SHA-256 of their ids; task files list a scene's tasks grouped
    by kind), then every ``n``-th of them from the ``i``-th for chunk ``i``. One chunk of
    everything when ``chunk_tasks`` is None."""
    ids = list(ids)
    if chunk_tasks is None or chunk_tasks >= len(ids):
        return [ids]
    order = sorted(ids, key=lambda t: hashlib.sha256(t.encode("utf-8")).hexdigest())
    n = math.ceil(len(ids) / chunk_tasks)
    return [order[i::n] for i in range(n)]


def check_methods(cfg: PaperTablesConfig, methods: Sequence[str]) -> tuple[str, ...]:
    """``methods`` if every one is a row of the tables, else :class:`PaperTablesError`."""
    bad = sorted(set(methods) - set(cfg.main_methods))
    if bad or not methods:
        raise PaperTablesError(f"unknown method(s) {bad or list(methods)}; the tables' methods are {list(cfg.main_methods)}")
    return tuple(methods)


def run_all(
    cfg: PaperTablesConfig,
    out: str | Path,
    *,
    workers: int | None = None,
    progress: bool = True,
    methods: Sequence[str] | None = None,
) -> tuple[dict[str, list[dict]], dict[str, float]]:
    """Run (or resume) every episode the tables need, chunk by chunk (``chunk_tasks``); returns
    the records and the wall seconds spent per VLM spec. ``methods`` runs only those rows (the
    backbone rows belong to :data:`BACKBONE_METHOD`); the others are read from ``out`` as
    they are, so a table can be filled row group by row group."""
    root = Path(out)
    walls: dict[str, float] = {vlm: 0.0 for vlm, _ in cfg.backbones}
    chunks = task_chunks(_selected_ids(cfg.bench), cfg.chunk_tasks)
    specs = [(vlm, cfg.bench_for(vlm, methods)) for vlm, _ in _ordered_backbones(cfg)]
    specs = [(vlm, b) for vlm, b in specs if b is not None]
    if len(chunks) > 1:
        for chunk in chunks:
            for vlm, b in specs:
                bench = replace(b, task_ids=tuple(chunk), scenes=None, kinds=None, count=None)
                walls[vlm] += run_bench(bench, _out_dir(root, vlm), workers=workers, progress=progress).wall_s
    for vlm, b in specs:  # the whole selection: summaries over every episode
        walls[vlm] += run_bench(b, _out_dir(root, vlm), workers=workers, progress=progress).wall_s
    return read_runs(cfg, root), walls


def _ordered_backbones(cfg: PaperTablesConfig) -> list[tuple[str, str]]:
    """The main VLM first (its run holds most methods), then the other backbones."""
    return sorted(cfg.backbones, key=lambda b: b[0] != cfg.bench.vlm)


def read_runs(cfg: PaperTablesConfig, runs_dir: str | Path) -> dict[str, list[dict]]:
    """Finished episodes under ``runs_dir`` (the tree :func:`run_all` writes) that belong to
    this config (same config hash, task selection and runs); runs nothing."""
    root = Path(runs_dir)
    out: dict[str, list[dict]] = {}
    for vlm, _ in cfg.backbones:
        bench = cfg.bench_for(vlm)
        ids = set(_selected_ids(bench))
        tasks = [t for t in load_tasks(bench.task_files) if t.task_id in ids]
        keys = {j.key: i for i, j in enumerate(plan_jobs(bench, tasks))}
        latest = {r["key"]: r for r in read_records(_out_dir(root, vlm) / EPISODES_FILE) if r.get("key") in keys}
        out[vlm] = sorted(latest.values(), key=lambda r: keys[r["key"]])
    return out


# -- tables ----------------------------------------------------------------------------------------


def _numeric_leaves(d: Any, prefix: str = "", depth: int = 0) -> dict[str, float]:
    """Numeric (and boolean) leaves of nested dicts, keyed ``"a.b.c"`` (at most 3 levels)."""
    if isinstance(d, dict):
        out: dict[str, float] = {}
        if depth < 3:
            for k, v in d.items():
                out.update(_numeric_leaves(v, f"{prefix}{k}.", depth + 1))
        return out
    if isinstance(d, (bool, int, float)) and math.isfinite(float(d)):
        return {prefix[:-1]: float(d)}
    return {}


def _row(records: list[dict], label: str, method: str, error_model: str) -> dict:
    """One table row: our numbers (None when there are no episodes) and the paper's."""
    paper = PAPER.get(label)
    row: dict[str, Any] = {"label": label, "method": method, "error_model": error_model, "episodes": len(records)}
    if records:
        s = summarize_records(records, error_model=error_model)["methods"][method]
        row.update(SR=100 * s["SR"], OSR=100 * s["OSR"], CR=100 * s["CR"], FT=s["FT"])
    else:
        row.update(SR=None, OSR=None, CR=None, FT=None)
    row["paper"] = None if paper is None else dict(zip(("SR", "OSR", "CR", "FT"), paper))
    return row


def _failures(records: list[dict]) -> dict:
    """How a method's episodes ended and the per-episode means of its summary counters."""
    ends = {r: 0 for r in END_REASONS}
    classes: dict[str, int] = {}
    sums: dict[str, float] = {}
    for r in records:
        ends[r["end_reason"]] = ends.get(r["end_reason"], 0) + 1
        key = r["failure"] or "success"
        classes[key] = classes.get(key, 0) + 1
        for k, v in _numeric_leaves(r.get("method_summary") or {}).items():
            sums[k] = sums.get(k, 0.0) + v
    n = max(len(records), 1)
    return {
        "episodes": len(records),
        "end_reasons": {k: v for k, v in ends.items() if v},
        "outcomes": dict(sorted(classes.items())),
        "summary_means": {k: v / n for k, v in sorted(sums.items()) if v},
    }


def build_tables(cfg: PaperTablesConfig, records: dict[str, list[dict]]) -> dict:
    """The three tables (plus failure sections) from records per VLM spec."""
    main = cfg.bench.vlm
    em = error_model_name(main)
    by_method: dict[str, list[dict]] = {}
    for r in records.get(main, []):
        by_method.setdefault(r["method"], []).append(r)

    def rows(spec):
        return [_row(by_method.get(m, []), label, m, em) for m, label in spec]

    backbone_rows = []
    for vlm, label in cfg.backbones:
        recs = [r for r in records.get(vlm, []) if r["method"] == BACKBONE_METHOD]
        row = _row(recs, label, BACKBONE_METHOD, error_model_name(vlm))
        row["label"] = f"{label} (stand-in: sim {error_model_name(vlm)})" if vlm.startswith("sim:") else label
        backbone_rows.append(row)
    failures = {m: _failures(by_method.get(m, [])) for m in cfg.main_methods}
    for vlm, _ in cfg.backbones:
        if vlm != main:
            failures[f"{BACKBONE_METHOD}@{error_model_name(vlm)}"] = _failures(
                [r for r in records.get(vlm, []) if r["method"] == BACKBONE_METHOD]
            )
    tasks = sorted({r["task"] for rs in records.values() for r in rs})
    return {
        "error_model": em,
        "config": cfg.source,
        "tasks": len(tasks),
        "runs": cfg.bench.runs,
        "table2": rows(TABLE2),
        "planner_study": rows(PLANNER_STUDY),
        "ablation": {"architecture": rows(ARCHITECTURE), "memory": rows(MEMORY), "backbone": backbone_rows},
        "failures": failures,
    }


def _f(x, fmt="{:.1f}") -> str:
    return "n/a" if x is None else fmt.format(x)


def _table(rows: list[dict]) -> list[str]:
    lines = [
        "| Method | episodes | SR % | OSR % | CR % | FT s | paper SR % | paper OSR % | paper CR % | paper FT s |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        p = r["paper"] or {}
        lines.append(
            f"| {r['label']} | {r['episodes']} | {_f(r['SR'])} | {_f(r['OSR'])} | {_f(r['CR'])} | {_f(r['FT'])} | "
            f"{_f(p.get('SR'))} | {_f(p.get('OSR'))} | {_f(p.get('CR'))} | {_f(p.get('FT'))} |"
        )
    return lines


def format_markdown(tables: dict, *, wall_s: dict[str, float] | None = None, command: str = "") -> str:
    """The tables as markdown (ours beside the paper's), then the failure sections."""
    em = tables["error_model"]
    head = f"simulated VLM error model `{em}`; {tables['tasks']} tasks x {tables['runs']} runs; SR/OSR/CR in %, FT in s"
    out = [f"## Paper tables reproduced in the embedded world ({head})", ""]
    if command:
        out += [f"Command: `{command}`", ""]
    if wall_s:
        parts = ", ".join(f"{k}: {v:.0f} s" for k, v in wall_s.items())
        out += [f"Wall time: {sum(wall_s.values()):.0f} s ({parts})", ""]
    out += ["### Table II: zero-shot AVLN benchmark", "", *_table(tables["table2"]), ""]
    out += ["### Obstacle-avoidance planner control study", "", *_table(tables["planner_study"]), ""]
    ab = tables["ablation"]
    out += ["### Table III: ablations", "", "Architecture", "", *_table(ab["architecture"]), ""]
    out += ["Memory", "", *_table(ab["memory"]), ""]
    out += [
        "VLM backbone (simulated-VLM presets as stand-ins for the paper's backbones; not fits of those models)",
        "",
        *_table(ab["backbone"]),
        "",
    ]
    out += ["### How the episodes ended", "", "| method | episodes | end reasons | outcomes |", "| --- | ---: | --- | --- |"]
    for m, f in tables["failures"].items():
        ends = ", ".join(f"{k} {v}" for k, v in f["end_reasons"].items()) or "-"
        outs = ", ".join(f"{k} {v}" for k, v in f["outcomes"].items()) or "-"
        out.append(f"| {m} | {f['episodes']} | {ends} | {outs} |")
    out += ["", "Per-episode means of each method's own summary counters:", ""]
    for m, f in tables["failures"].items():
        if f["summary_means"]:
            items = ", ".join(f"{k} {v:.2f}" for k, v in f["summary_means"].items())
            out.append(f"- **{m}**: {items}")
    return "\n".join(out) + "\n"


# -- command line ----------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", required=True, help="paper-tables TOML (experiments/configs/paper_tables*.toml)")
    ap.add_argument("--out", default=None, help="run folder (default runs/paper_tables/<bench name>); reruns resume")
    ap.add_argument("--from-runs", default=None, metavar="DIR", help="only read finished episodes of this run folder")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: the config's)")
    ap.add_argument("--json", default=None, help="also write the tables as JSON here")
    ap.add_argument("--methods", default=None, help="comma-separated: run only these rows (the others are read from --out)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        cfg = load_config(args.config)
        methods = check_methods(cfg, [m.strip() for m in args.methods.split(",") if m.strip()]) if args.methods else None
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    if args.from_runs:
        records = read_runs(cfg, args.from_runs)
        walls = None
        out = Path(args.from_runs)
    else:
        out = Path(args.out) if args.out else Path("runs") / "paper_tables" / cfg.bench.name
        records, walls = run_all(cfg, out, workers=args.workers, progress=not args.no_progress, methods=methods)
    tables = build_tables(cfg, records)
    command = " ".join(["experiments/paper_tables.py", *(argv if argv is not None else sys.argv[1:])])
    text = format_markdown(tables, wall_s=walls, command=command)
    print(text)
    out.mkdir(parents=True, exist_ok=True)
    (out / "paper_tables.md").write_text(text)
    tables["wall_s"] = walls
    tables["elapsed_s"] = time.perf_counter() - t0
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(tables, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
