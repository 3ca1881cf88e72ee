"""The tables of record: every result table of the project, regenerated from one code version.

A manifest (``experiments/configs/tables_of_record.toml``) lists the tables. Each table has one
or more *sets* (``parts``): a benchmark config (:class:`onfly.bench.runner.BenchConfig`) with
optional overrides (``methods``, ``runs``, ``vlm``, ``realism``); a row is a method on a set.
The command flies every episode the tables need through the benchmark runner, resumable, on
local processes or Ray, then writes into ``--out DIR``:

- ``records.jsonl.gz``: a header line (tables, sets, labels, the paper's numbers, code digest
  and commit, wall time per table) and one compact line per episode
  (:data:`print_tables.RECORD_FIELDS`: the tables it belongs to, method, task, scene, kind,
  run, seed, VLM spec, error model, realism, metrics, end reason, failure, track metrics,
  start-in-view flag where a table splits by it); per-episode bulk (trace summaries, VLM call
  counts, the method's own counters) stays in the run folders;
- ``tables.md`` and ``tables.json``: every table, made from ``records.jsonl.gz`` by
  ``experiments/print_tables.py``'s functions, which print any table again from that file;
- ``pools/<error model>-<realism>-<hash>/episodes.jsonl``: the runner's folders, one per
  *underlying config* (everything that enters an episode's key except the method's own
  options and the task: protocol, world, VLM spec, seed, shared tables). Tables whose sets
  plan the same episode key share the episode: it flies once (e.g. the robustness table's
  ideal OnFly episodes are Table II's run-0 episodes). Keys that differ never share;
- ``run_state.json``: the code digest (SHA-256 over the tracked files under
  :data:`CODE_PATHS`, as on disk) and commit of the folder, and per table the wall time spent
  running it (written every :data:`CHECKPOINT_S` while the table runs, and when a TERM or
  Ctrl-C stops the command) and the code versions that ran it.

Resuming onto a folder made by another code digest stops with an error naming both (one code
version per table set) unless ``--allow-mixed``; the code is checked again before every table,
so an edit during a run stops it too. ``--from-runs`` runs nothing and rewrites the artifacts
from the pools. ``--tables a,b`` runs only those tables, and ``--methods a,b`` only those rows'
episodes (a chunk that brings some rows first; a later run without it flies the rest); the
artifacts always cover the manifest's every table (rows without episodes say how many are missing). ``--count N`` /
``--runs N`` make a subset check (an evenly spread N tasks per set, at most N runs), named as
such in every artifact; the full command later on the same folder completes it.

Run::

    .venv/bin/python experiments/tables_of_record.py --manifest experiments/configs/tables_of_record.toml \\
        --out runs/record [--workers 2] [--ray ADDRESS] [--tables a,b] [--from-runs] [--json PATH]
    .venv/bin/python experiments/print_tables.py runs/record/records.jsonl.gz --table table2
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import json
import os
import re
import sys
import time
import tomllib
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence

from onfly.bench.code_version import CODE_PATHS, CodeVersion, code_digest, code_version
from onfly.bench.episode import EpisodeConfig
from onfly.bench.runner import (
    EPISODES_FILE,
    BenchConfig,
    BenchConfigError,
    EpisodeJob,
    check_bench,
    error_model_name,
    init_ray,
    plan_jobs,
    read_records,
    run_bench,
    sigterm_exits,
    world_camera,
)
from onfly.bench.tasks import Task
from onfly.world.realism import PROFILES

try:  # imported as experiments.tables_of_record (tests, python -m) or run as a script from experiments/
    from experiments.print_tables import FORMAT, build_tables, format_document, read_records_file, tables_json
    from experiments.task_visibility import starts_in_view
except ModuleNotFoundError:
    from print_tables import FORMAT, build_tables, format_document, read_records_file, tables_json
    from task_visibility import starts_in_view

__all__ = [
    "CODE_PATHS",
    "RECORDS_FILE",
    "STATE_FILE",
    "ManifestError",
    "CodeVersionError",
    "PartSpec",
    "TableSpec",
    "Manifest",
    "Subset",
    "CodeVersion",
    "PlannedPart",
    "load_manifest",
    "code_digest",
    "code_version",
    "pool_name",
    "plan_tables",
    "run_tables",
    "collect_records",
    "write_artifacts",
    "main",
]

REPO = Path(__file__).resolve().parents[1]
RECORDS_FILE = "records.jsonl.gz"
STATE_FILE = "run_state.json"
POOLS_DIR = "pools"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
_TOP_KEYS = ("record", "labels", "paper", "tables")
_RECORD_KEYS = ("name", "workers")
_TABLE_KEYS = ("title", "note", "config", "methods", "runs", "vlm", "realism", "labels", "paper", "split_view", "track", "parts")
_PART_KEYS = ("label", "config", "methods", "runs", "vlm", "realism", "paper_row")


class ManifestError(ValueError):
    """A manifest that cannot be used (the message names the file, table and field)."""


class CodeVersionError(RuntimeError):
    """The code differs from the one that made the output folder (names both digests)."""


# -- the manifest ----------------------------------------------------------------------------------


def _is_pos_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


@dataclass(frozen=True)
class PartSpec:
    """One set of a table: a benchmark config and its overrides.

    label : the set's name in the table ("" for a table of one set)
    config : the benchmark config file (absolute)
    methods : rows, in order (None: the config's ``bench.methods``)
    runs : runs per task (None: the config's); vlm : VLM spec override (None: the config's)
    realism : realism profile override (None: the config's ``[world] realism``)
    paper_row : the paper's row this set is compared with (None: the method's label)
    """

    label: str
    config: Path
    methods: tuple[str, ...] | None = None
    runs: int | None = None
    vlm: str | None = None
    realism: str | None = None
    paper_row: str | None = None

    def __post_init__(self) -> None:
        if self.methods is not None and (not self.methods or not all(isinstance(m, str) and m for m in self.methods)):
            raise ManifestError(f"methods must be a non-empty list of method names, got {self.methods!r}")
        if self.methods is not None and len(set(self.methods)) != len(self.methods):
            raise ManifestError(f"methods lists a method twice: {list(self.methods)}")
        if self.runs is not None and not _is_pos_int(self.runs):
            raise ManifestError(f"runs must be a positive integer, got {self.runs!r}")
        if self.vlm is not None and (not isinstance(self.vlm, str) or ":" not in self.vlm):
            raise ManifestError(f"vlm must be a VLM spec like 'sim:nominal', got {self.vlm!r}")
        if self.realism is not None and self.realism not in PROFILES:
            raise ManifestError(f"realism: unknown profile {self.realism!r}; valid: {', '.join(PROFILES)}")


@dataclass(frozen=True)
class TableSpec:
    """One table: its sets, row labels and columns.

    name : identifier (``--tables``, ``print_tables.py --table``); title : heading
    note : a sentence under the heading ("" for none)
    parts : the sets, in column order of the rows
    labels : method -> row label (the manifest's ``[labels]`` merged with the table's)
    paper : show the paper's numbers beside ours; split_view : SR by the goal in view or out of
        view at the start; track : the tracking metrics
    """

    name: str
    title: str
    parts: tuple[PartSpec, ...]
    labels: dict = field(default_factory=dict)
    note: str = ""
    paper: bool = False
    split_view: bool = False
    track: bool = False

    def __post_init__(self) -> None:
        if not _NAME.match(self.name):
            raise ManifestError(f"table name {self.name!r}: use letters, digits, '_', '-', '.'")
        if not self.parts:
            raise ManifestError(f"table {self.name!r} has no sets")
        labels = [p.label for p in self.parts]
        if len(set(labels)) != len(labels):
            raise ManifestError(f"table {self.name!r}: two sets share a label: {labels}")


@dataclass(frozen=True)
class Manifest:
    """The tables of record: name, tables in order, paper numbers (row label -> (SR %, OSR %,
    CR %, FT s)), default local workers, and the file it was read from."""

    name: str
    tables: tuple[TableSpec, ...]
    paper_numbers: dict = field(default_factory=dict)
    workers: int = 1
    source: str | None = None

    def __post_init__(self) -> None:
        if not self.tables:
            raise ManifestError(f"{self.source}: the manifest lists no [tables.<name>]")
        if not _is_pos_int(self.workers):
            raise ManifestError(f"{self.source}: record.workers must be a positive integer, got {self.workers!r}")

    def table(self, name: str) -> TableSpec:
        for t in self.tables:
            if t.name == name:
                return t
        raise ManifestError(f"no table {name!r} in {self.source}; its tables: {', '.join(t.name for t in self.tables)}")

    def select(self, names: Sequence[str] | None) -> tuple[TableSpec, ...]:
        """The named tables in manifest order (all when ``names`` is None); ManifestError
        lists the valid names for an unknown one."""
        if names is None:
            return self.tables
        known = [t.name for t in self.tables]
        bad = [n for n in names if n not in known]
        if bad or not names:
            raise ManifestError(f"unknown table(s) {bad or list(names)}; the manifest's tables: {', '.join(known)}")
        return tuple(t for t in self.tables if t.name in set(names))


def _check_keys(where: str, data: Any, valid: Sequence[str]) -> dict:
    if not isinstance(data, dict):
        raise ManifestError(f"{where}: must be a table, got {data!r}")
    bad = sorted(set(data) - set(valid))
    if bad:
        raise ManifestError(f"{where}: unknown field(s) {bad}; valid: {list(valid)}")
    return data


def _str_list(where: str, v: Any) -> tuple[str, ...] | None:
    if v is None:
        return None
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise ManifestError(f"{where}: must be a list of strings, got {v!r}")
    return tuple(v)


def _labels(where: str, v: Any) -> dict:
    if v is None:
        return {}
    if not isinstance(v, dict) or not all(isinstance(x, str) for x in v.values()):
        raise ManifestError(f"{where}: must map method names to row labels (strings), got {v!r}")
    return dict(v)


def _flag(where: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ManifestError(f"{where}: must be true or false, got {v!r}")
    return v


def _config_path(where: str, v: Any, base: Path) -> Path:
    if not isinstance(v, str) or not v:
        raise ManifestError(f"{where}: must name a benchmark config file, got {v!r}")
    p = Path(v).expanduser()
    p = p if p.is_absolute() else (base / p).resolve()
    if not p.is_file():
        raise ManifestError(f"{where}: benchmark config not found: {p}")
    return p


def _part(where: str, raw: dict, defaults: dict, base: Path, n_parts: int) -> PartSpec:
    raw = _check_keys(where, raw, _PART_KEYS)
    merged = {**defaults, **raw}
    if "config" not in merged:
        raise ManifestError(f"{where}: no config (give it on the table or on each set)")
    config = _config_path(f"{where}.config", merged["config"], base)
    label = merged.get("label", config.stem if n_parts > 1 else "")
    if not isinstance(label, str):
        raise ManifestError(f"{where}.label: must be a string, got {label!r}")
    paper_row = raw.get("paper_row")
    if paper_row is not None and not isinstance(paper_row, str):
        raise ManifestError(f"{where}.paper_row: must be a string, got {paper_row!r}")
    try:
        return PartSpec(label, config, _str_list(f"{where}.methods", merged.get("methods")), merged.get("runs"),
                        merged.get("vlm"), merged.get("realism"), paper_row)  # fmt: skip
    except ManifestError as exc:
        raise ManifestError(f"{where}: {exc}") from None


def _table(source: str, name: str, raw: Any, labels: dict, base: Path) -> TableSpec:
    where = f"{source}: tables.{name}"
    raw = _check_keys(where, raw, _TABLE_KEYS)
    defaults = {k: raw[k] for k in ("config", "methods", "runs", "vlm", "realism") if k in raw}
    parts_raw = raw.get("parts")
    if parts_raw is None:
        parts = (_part(where, {}, defaults, base, 1),)
    else:
        if not isinstance(parts_raw, list) or not parts_raw:
            raise ManifestError(f"{where}.parts: must be a non-empty array of tables ([[tables.{name}.parts]])")
        parts = tuple(_part(f"{where}.parts[{i}]", p, defaults, base, len(parts_raw)) for i, p in enumerate(parts_raw))
    title = raw.get("title", name)
    note = raw.get("note", "")
    if not isinstance(title, str) or not isinstance(note, str):
        raise ManifestError(f"{where}: title and note must be strings")
    table_labels = {**labels, **_labels(f"{where}.labels", raw.get("labels"))}
    flags = [_flag(f"{where}.{k}", raw.get(k, False)) for k in ("paper", "split_view", "track")]
    try:
        return TableSpec(name, title, parts, table_labels, note, *flags)
    except ManifestError as exc:
        raise ManifestError(f"{source}: {exc}") from None


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a tables-of-record manifest (format: ``experiments/configs/tables_of_record.toml``).

    Checks the manifest's own fields, that every benchmark config exists and every realism
    profile is known; the configs' contents, methods and VLM specs are checked by
    :func:`plan_tables`. Raises ManifestError (FileNotFoundError for a missing file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    source = str(path)
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ManifestError(f"{source}: not valid TOML: {exc}") from None
    _check_keys(source, data, _TOP_KEYS)
    record = _check_keys(f"{source}: [record]", data.get("record", {}), _RECORD_KEYS)
    labels = _labels(f"{source}: [labels]", data.get("labels"))
    paper = data.get("paper", {})
    if not isinstance(paper, dict) or not all(
        isinstance(v, list) and len(v) == 4 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        for v in paper.values()
    ):
        raise ManifestError(f"{source}: [paper]: each row label maps to [SR %, OSR %, CR %, FT s], got {paper!r}")
    tables = data.get("tables", {})
    if not isinstance(tables, dict):
        raise ManifestError(f"{source}: tables must be [tables.<name>] tables")
    base = path.resolve().parent
    name = record.get("name", path.stem)
    if not isinstance(name, str):
        raise ManifestError(f"{source}: record.name must be a string, got {name!r}")
    specs = [_table(source, tname, raw, labels, base) for tname, raw in tables.items()]
    return Manifest(name, tuple(specs), {k: tuple(float(x) for x in v) for k, v in paper.items()}, record.get("workers", 1), source)


@dataclass(frozen=True)
class Subset:
    """A subset check: ``count`` tasks per set (evenly spread, as ``onfly bench --count``) and
    at most ``runs`` runs; None leaves the manifest's value."""

    count: int | None = None
    runs: int | None = None

    def __post_init__(self) -> None:
        for name in ("count", "runs"):
            v = getattr(self, name)
            if v is not None and not _is_pos_int(v):
                raise ManifestError(f"--{name} must be a positive integer, got {v!r}")

    def as_dict(self) -> dict | None:
        d = {k: v for k, v in (("count", self.count), ("runs", self.runs)) if v is not None}
        return d or None


# -- planning --------------------------------------------------------------------------------------


def pool_name(bench: BenchConfig) -> str:
    """The run folder of a config's underlying settings: ``<error model>-<realism>-<hash>``.

    The hash covers what enters every method's episode key except the method's own options
    and the task (protocol, world, VLM spec, seed, shared tables), so configs whose episodes
    can coincide share a folder, and the runner's keys decide which episodes do."""
    world = bench.world_settings()
    realism = world.get("realism", "ideal")
    if realism == "ideal":  # as BenchConfig.method_hash
        del world["realism"]
    blob = json.dumps({"episode": asdict(EpisodeConfig(**bench.episode)), "world": world, "vlm": bench.vlm, "seed": bench.seed,
                       "shared": bench.shared}, sort_keys=True, default=str)  # fmt: skip
    em = error_model_name(bench.vlm).replace(":", "_").replace("/", "_")
    return f"{em}-{realism}-{hashlib.sha256(blob.encode()).hexdigest()[:8]}"


@dataclass(frozen=True)
class PlannedPart:
    """A set of a table, resolved: its benchmark config, tasks, episodes and run folder."""

    table: str
    index: int
    spec: PartSpec
    bench: BenchConfig
    tasks: tuple[Task, ...]
    jobs: tuple[EpisodeJob, ...]
    pool: str

    @property
    def keys(self) -> list[str]:
        return [j.key for j in self.jobs]


def _display(p: Path) -> str:
    try:
        return p.resolve().relative_to(REPO).as_posix()
    except ValueError:
        return str(p)


def _part_bench(table: TableSpec, spec: PartSpec, subset: Subset) -> BenchConfig:
    where = f"tables.{table.name}" + (f" set {spec.label!r}" if spec.label else "")
    try:
        bench = BenchConfig.from_toml(spec.config)
        world = dict(bench.world)
        if spec.realism is not None:
            world["realism"] = spec.realism
        runs = spec.runs if spec.runs is not None else bench.runs
        if subset.runs is not None:
            runs = min(runs, subset.runs)
        return replace(
            bench, name=f"{table.name}.{spec.label or 'all'}", methods=spec.methods or bench.methods, runs=runs,
            vlm=spec.vlm or bench.vlm, world=world, count=subset.count if subset.count is not None else bench.count,
        )  # fmt: skip
    except (BenchConfigError, OSError) as exc:
        raise ManifestError(f"{where}: {exc}") from None


def plan_tables(manifest: Manifest, subset: Subset = Subset()) -> list[PlannedPart]:
    """Every set of every table, checked before any episode flies (methods, task selection,
    VLM spec, options: :func:`onfly.bench.runner.check_bench`, once per underlying config with
    the union of its methods). Raises ManifestError naming the table and set at fault."""
    benches = [(t, i, s, _part_bench(t, s, subset)) for t in manifest.tables for i, s in enumerate(t.parts)]
    groups: dict[str, list[tuple[TableSpec, int, PartSpec, BenchConfig]]] = {}
    for item in benches:
        d = item[3].to_dict()
        for k in ("name", "methods", "runs", "workers", "source"):
            d.pop(k, None)
        groups.setdefault(json.dumps(d, sort_keys=True, default=str), []).append(item)
    checked: dict[int, tuple[Task, ...]] = {}
    for items in groups.values():
        union = tuple(dict.fromkeys(m for *_, b in items for m in b.methods))
        t0, _, s0, b0 = items[0]
        try:
            tasks = tuple(check_bench(replace(b0, methods=union), reach_vlm=True))
        except BenchConfigError as exc:
            names = ", ".join(sorted({f"tables.{t.name}" for t, *_ in items}))
            raise ManifestError(f"{names}: {exc}") from None
        for t, i, s, b in items:
            checked[id(b)] = tasks
    out = []
    for t, i, s, b in benches:
        tasks = checked[id(b)]
        out.append(PlannedPart(t.name, i, s, b, tasks, tuple(plan_jobs(b, tasks)), pool_name(b)))
    return out


# -- run state -------------------------------------------------------------------------------------


def read_state(out: Path) -> dict | None:
    """``run_state.json`` of an output folder (None when there is none)."""
    p = out / STATE_FILE
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise CodeVersionError(f"{p}: unreadable ({exc}); it records the folder's code digest, restore or remove it") from None


def _write_state(out: Path, state: dict) -> None:
    tmp = out / (STATE_FILE + ".tmp")
    tmp.write_text(json.dumps(state, indent=1) + "\n")
    os.replace(tmp, out / STATE_FILE)


def _has_episodes(out: Path) -> bool:
    return any(p.stat().st_size > 0 for p in (out / POOLS_DIR).glob(f"*/{EPISODES_FILE}"))


def check_code(out: Path, code: CodeVersion, *, allow_mixed: bool = False) -> dict:
    """The folder's state, made or checked against ``code`` before any episode flies.

    Raises CodeVersionError naming both digests when the folder was made by other code (or
    holds episodes without a recorded digest), unless ``allow_mixed``."""
    state = read_state(out)
    if state is None:
        if _has_episodes(out) and not allow_mixed:
            raise CodeVersionError(f"{out} holds episodes but no {STATE_FILE} (no recorded code digest; this code is "
                                   f"{code.digest}): use a new --out, or --allow-mixed")  # fmt: skip
        state = {"code_digest": code.digest, "commit": code.commit, "code_versions": [], "tables": {}}
    elif state["code_digest"] != code.digest and not allow_mixed:
        raise CodeVersionError(
            f"{out} was made by code digest {state['code_digest']} (commit {state['commit']}); this code is digest "
            f"{code.digest} (commit {code.commit}). One code version per table set: use a new --out, or --allow-mixed "
            f"to add episodes of this code to it"
        )
    if code.as_dict() not in state["code_versions"]:
        state["code_versions"].append(code.as_dict())
    out.mkdir(parents=True, exist_ok=True)
    _write_state(out, state)
    return state


# -- running ---------------------------------------------------------------------------------------


#: how often a running table's wall time is written to ``run_state.json``, seconds (a run killed
#: between checkpoints loses at most this much of its account)
CHECKPOINT_S = 60.0


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def estimate_left_s(pending: dict[str, int], mean_wall_s: dict[str, float], workers: int) -> float | None:
    """Wall time left for the ``pending`` episodes (method -> count), seconds: each method's mean
    episode wall time so far, divided among ``workers``; a method with no finished episode yet
    counts at the slowest mean seen (methods differ several-fold: a baseline that collides in
    5 s against a searching OnFly at 70 s). None before any episode has finished."""
    if not mean_wall_s:
        return None
    slowest = max(mean_wall_s.values())
    return sum(n * mean_wall_s.get(m, slowest) for m, n in pending.items()) / max(1, workers)


def _part_name(p: PlannedPart) -> str:
    return f'{p.table} set "{p.spec.label}"' if p.spec.label else p.table


def _episode_reporter(
    table: str,
    have: set,
    report: Callable[[str], None] | None,
    pending: dict[str, int],
    workers: int,
    checkpoint: Callable[[], None] = lambda: None,
    prior_means: dict[str, float] | None = None,
) -> Callable[[dict, int, int], None]:
    """The runner's progress callback: adds each finished key to ``have``, counts it off
    ``pending`` (method -> episodes still to fly), calls ``checkpoint`` at most every
    :data:`CHECKPOINT_S` and reports a line per episode with the time left
    (:func:`estimate_left_s` over this set's means so far, ``prior_means`` for a method it has
    not flown yet; ``report`` None: no line)."""
    walls: dict[str, list[float]] = {}
    last = [time.perf_counter()]

    def on_episode(rec: dict, done: int, total: int) -> None:
        have.add(rec["key"])
        m = rec["method"]
        pending[m] = max(0, pending.get(m, 0) - 1)
        if rec.get("wall_s") is not None:
            walls.setdefault(m, []).append(float(rec["wall_s"]))
        if time.perf_counter() - last[0] >= CHECKPOINT_S:
            last[0] = time.perf_counter()
            checkpoint()
        if report is not None:
            ok = "success" if rec["metrics"]["success"] else rec["failure"] or rec["end_reason"]
            means = {**(prior_means or {}), **{k: sum(v) / len(v) for k, v in walls.items()}}
            left = estimate_left_s(pending, means, workers) if walls else None
            eta = "?" if left is None else _duration(left)
            report(f"[{table}] {done}/{total} {m} {rec['task']} run {rec['run']}: {rec['end_reason']}, {ok} (left {eta})")

    return on_episode


def recorded_means(out: Path) -> dict[str, float]:
    """method -> mean episode wall time, seconds, over every record in the folder's pools: the
    time-left estimate's prior for a method this set has not flown yet (the same method in
    another set of the run is a better guess than the slowest method seen so far)."""
    walls: dict[str, list[float]] = {}
    for f in sorted((out / POOLS_DIR).glob(f"*/{EPISODES_FILE}")):
        for r in read_records(f):
            if r.get("wall_s") is not None and "method" in r:
                walls.setdefault(r["method"], []).append(float(r["wall_s"]))
    return {m: sum(v) / len(v) for m, v in walls.items()}


def _pool_keys(out: Path, pool: str, cache: dict[str, set]) -> set:
    if pool not in cache:
        cache[pool] = {r["key"] for r in read_records(out / POOLS_DIR / pool / EPISODES_FILE) if "key" in r}
    return cache[pool]


def run_tables(
    planned: Sequence[PlannedPart],
    out: str | Path,
    names: Sequence[str],
    *,
    code: CodeVersion,
    check: Callable[[], CodeVersion],
    allow_mixed: bool = False,
    workers: int = 1,
    ray_address: str | None = None,
    report: Callable[[str], None] = lambda line: None,
    episode_lines: bool = True,
    methods: Sequence[str] | None = None,
) -> dict:
    """Fly (or resume) every episode of the tables ``names``, table by table (only the rows of
    ``methods`` when given); returns the folder's state. ``check`` gives the code version before each table: a digest other than
    ``code.digest`` stops the run (CodeVersionError) unless ``allow_mixed``. ``report`` gets
    one progress line per table and set (and per episode with ``episode_lines``)."""
    out = Path(out)
    state = check_code(out, code, allow_mixed=allow_mixed)
    keys_cache: dict[str, set] = {}
    for n, name in enumerate(names, 1):
        now = check()
        if now.digest != code.digest and not allow_mixed:
            raise CodeVersionError(f"the code changed during the run: digest {code.digest} at the start, {now.digest} now "
                                   f"(before table {name!r}); the tables run so far hold episodes of {code.digest}")  # fmt: skip
        parts = [p if methods is None else _only_methods(p, methods) for p in planned if p.table == name]
        parts = [p for p in parts if p.jobs]
        entry = state["tables"].setdefault(name, {"wall_s": 0.0, "code": []})
        for versions in (entry["code"], state["code_versions"]):
            if now.as_dict() not in versions:
                versions.append(now.as_dict())
        t0, base_s = time.perf_counter(), float(entry["wall_s"])

        def checkpoint() -> None:
            entry["wall_s"] = base_s + time.perf_counter() - t0
            _write_state(out, state)

        try:
            for p in parts:
                have = _pool_keys(out, p.pool, keys_cache)
                pending: dict[str, int] = {}
                for j in p.jobs:
                    if j.key not in have:
                        pending[j.method] = pending.get(j.method, 0) + 1
                todo = sum(pending.values())
                report(f"[{n}/{len(names)} {_part_name(p)}] {len(p.jobs)} episodes planned, {len(p.jobs) - todo} recorded, {todo} to fly "
                       f"({_display(p.spec.config)}, {p.bench.vlm}, {p.bench.world_settings()['realism']}, pool {p.pool})")  # fmt: skip
                prior = recorded_means(out) if episode_lines else {}
                progress = _episode_reporter(name, have, report if episode_lines else None, pending, workers, checkpoint, prior)
                res = run_bench(p.bench, out / POOLS_DIR / p.pool, workers=workers, ray_address=ray_address, progress=progress,
                                checked_tasks=p.tasks, allow_mixed_code=True)  # fmt: skip  (its own code check: STATE_FILE)
                for e in res.errored:
                    report(f"[{name}] method error: {e}")
        finally:
            checkpoint()
        report(f"[{n}/{len(names)} {name}] done in {time.perf_counter() - t0:.0f} s")
    return state


def _only_methods(part: PlannedPart, methods: Sequence[str]) -> PlannedPart:
    """``part`` with only the rows (methods) in ``methods``: the same episode keys, fewer of them."""
    keep = tuple(m for m in part.bench.methods if m in methods)
    return replace(part, bench=replace(part.bench, methods=keep), jobs=tuple(j for j in part.jobs if j.method in keep))


def check_methods(planned: Sequence[PlannedPart], names: Sequence[str], methods: Sequence[str]) -> None:
    """Raises ManifestError when a method of ``methods`` is a row of none of the tables ``names``."""
    rows = dict.fromkeys(m for p in planned if p.table in names for m in p.bench.methods)
    unknown = [m for m in methods if m not in rows]
    if unknown:
        raise ManifestError(f"--methods: {unknown} not a row of the tables run ({', '.join(names)}); their rows: {', '.join(rows)}")


# -- the records artifact --------------------------------------------------------------------------


def _rounded(x: Any, nd: int = 4) -> Any:
    """Floats rounded to ``nd`` decimals (0.1 mm, 0.1 ms), recursively."""
    if isinstance(x, float):
        return round(x, nd)
    if isinstance(x, dict):
        return {k: _rounded(v, nd) for k, v in x.items()}
    if isinstance(x, list):
        return [_rounded(v, nd) for v in x]
    return x


def compact_record(rec: dict, tables: dict[str, list[int]], realism: str, start_in_view: bool | None = None) -> dict:
    """One line of ``records.jsonl.gz`` from a runner record (``episodes.jsonl``): the fields
    the tables use, floats to 4 decimals, without the per-episode bulk (collision, VLM calls,
    motion, the method's own summary). ``tables`` maps table name -> indices of its sets the
    episode belongs to; ``realism`` is used when the record predates realism profiles."""
    out = {
        "key": rec["key"],
        "tables": tables,
        **{k: rec.get(k) for k in ("method", "task", "scene", "kind", "run", "seed", "vlm", "error_model")},
        "realism": rec.get("realism", realism),
        "metrics": _rounded(rec["metrics"]),
        "end_reason": rec["end_reason"],
        "failure": rec.get("failure", ""),
        **{k: _rounded(rec.get(k)) for k in ("sim_s", "wall_s", "cpu_s", "min_clearance_m")},
    }
    if rec.get("track"):
        out["track"] = _rounded(rec["track"])
    if start_in_view is not None:
        out["start_in_view"] = bool(start_in_view)
    if rec.get("error"):
        out["error"] = str(rec["error"])[:200]
    return out


def _view_flags(manifest: Manifest, planned: Sequence[PlannedPart]) -> dict[tuple[str, int], dict[str, bool]]:
    """Start-in-view flags (task id -> bool) of every set of a table that splits by them, from
    the first frame at the set's camera (``experiments/task_visibility.py``)."""
    split = {t.name for t in manifest.tables if t.split_view}
    cache: dict[tuple, dict[str, bool]] = {}
    out = {}
    for p in planned:
        if p.table not in split:
            continue
        w = p.bench.world_settings()
        cam = world_camera(w)
        flags = cache.setdefault((cam.width, cam.height, float(w["hfov_deg"]), float(w["vfov_deg"])), {})
        missing = [t for t in p.tasks if t.task_id not in flags]
        if missing:
            flags.update(starts_in_view(missing, cam))
        out[(p.table, p.index)] = {t.task_id: flags[t.task_id] for t in p.tasks}
    return out


def collect_records(manifest: Manifest, planned: Sequence[PlannedPart], out: str | Path) -> list[dict]:
    """The compact records of every finished episode the tables plan, one per episode key (the
    latest line of the key in its run folder), in manifest order (table, set, method, task, run)."""
    out = Path(out)
    pools: dict[str, dict[str, dict]] = {}
    flags = _view_flags(manifest, planned)
    member: dict[str, dict[str, list[int]]] = {}
    first: dict[str, tuple[PlannedPart, str]] = {}
    view: dict[str, bool] = {}
    for p in planned:
        if p.pool not in pools:
            pools[p.pool] = {r["key"]: r for r in read_records(out / POOLS_DIR / p.pool / EPISODES_FILE) if "key" in r}
        f = flags.get((p.table, p.index))
        for j in p.jobs:
            if j.key not in pools[p.pool]:
                continue
            parts = member.setdefault(j.key, {}).setdefault(p.table, [])
            if p.index not in parts:
                parts.append(p.index)
            first.setdefault(j.key, (p, p.bench.world_settings()["realism"]))
            if f is not None:
                view[j.key] = f[j.task_id]
    return [compact_record(pools[p.pool][k], member[k], realism, view.get(k)) for k, (p, realism) in first.items()]


def make_header(manifest: Manifest, planned: Sequence[PlannedPart], state: dict | None, *, subset: Subset, command: str) -> dict:
    """The first line of ``records.jsonl.gz``: what :mod:`print_tables` needs besides the episodes."""
    state = state or {}
    tables = []
    for t in manifest.tables:
        parts = [p for p in planned if p.table == t.name]
        labels = {m: t.labels[m] for p in parts for m in p.bench.methods if m in t.labels}
        wanted = {labels.get(m, m) for p in parts for m in p.bench.methods} | {p.spec.paper_row for p in parts if p.spec.paper_row}
        entry = (state.get("tables") or {}).get(t.name) or {}
        code = entry.get("code") or state.get("code_versions") or []
        tables.append(
            {
                "name": t.name,
                "title": t.title,
                "note": t.note,
                "paper": t.paper,
                "split_view": t.split_view,
                "track": t.track,
                "labels": labels,
                "paper_numbers": {k: list(v) for k, v in manifest.paper_numbers.items() if t.paper and k in wanted},
                "wall_s": entry.get("wall_s"),
                "code": code,
                "parts": [
                    {
                        "label": p.spec.label,
                        "config": _display(p.spec.config),
                        "pool": p.pool,
                        "methods": list(p.bench.methods),
                        "vlm": p.bench.vlm,
                        "error_model": error_model_name(p.bench.vlm),
                        "realism": p.bench.world_settings()["realism"],
                        "runs": p.bench.runs,
                        "tasks": len(p.tasks),
                        "paper_row": p.spec.paper_row,
                    }
                    for p in parts
                ],
            }
        )
    versions = state.get("code_versions") or []
    return {
        "format": FORMAT,
        "name": manifest.name,
        "manifest": _display(Path(manifest.source)) if manifest.source else None,
        "code": {"digest": state.get("code_digest", "unknown"), "commit": state.get("commit", "unknown")},
        "mixed": len({v["digest"] for v in versions}) > 1,
        "subset": subset.as_dict(),
        "command": command,
        "tables": tables,
    }


def write_artifacts(out: str | Path, header: dict, records: Sequence[dict], json_path: str | Path | None = None) -> dict:
    """Write ``records.jsonl.gz`` (reproducible bytes: no gzip timestamp), then ``tables.md``
    and ``tables.json`` made from the file just written; returns the tables."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / (RECORDS_FILE + ".tmp")
    with open(tmp, "wb") as raw, gzip.GzipFile(filename="", fileobj=raw, mode="wb", mtime=0) as gz:
        for line in (header, *records):
            gz.write((json.dumps(line, separators=(",", ":")) + "\n").encode("utf-8"))
    os.replace(tmp, out / RECORDS_FILE)
    head, recs = read_records_file(out / RECORDS_FILE)
    tables = build_tables(head, recs)
    (out / "tables.md").write_text(format_document(tables))
    (out / "tables.json").write_text(tables_json(tables))
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(tables_json(tables))
    return tables


# -- command line ----------------------------------------------------------------------------------


def _csv(s: str | None) -> list[str] | None:
    return None if s is None else [x.strip() for x in s.split(",") if x.strip()]


def _start_ray(address: str, workers: int) -> Callable[[], None]:
    """Start (or join) Ray once for every table (the runner leaves an initialized Ray running);
    returns the shutdown."""
    import ray  # optional: only --ray needs it

    return ray.shutdown if init_ray(address, workers) else (lambda: None)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--manifest", required=True, help="tables-of-record manifest (experiments/configs/tables_of_record.toml)")
    ap.add_argument("--out", required=True, metavar="DIR", help="output folder; a rerun resumes")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes (default: the manifest's record.workers)")
    ap.add_argument("--ray", default=None, metavar="ADDRESS", help="run episodes as Ray tasks: a cluster address or 'local'")
    ap.add_argument("--tables", default=None, metavar="A,B", help="run only these tables (the artifacts cover every table)")
    ap.add_argument("--from-runs", action="store_true", help="run nothing: rewrite the artifacts from DIR's finished episodes")
    ap.add_argument("--json", default=None, metavar="PATH", help="also write the tables JSON here (DIR/tables.json is always written)")
    ap.add_argument("--allow-mixed", action="store_true", help="add episodes to a DIR made by another code digest")
    ap.add_argument("--count", type=int, default=None, metavar="N", help="subset check: N evenly spread tasks per set")
    ap.add_argument("--runs", type=int, default=None, metavar="N", help="subset check: at most N runs per task")
    ap.add_argument("--methods", default=None, metavar="A,B",
                    help="fly only these rows' episodes now (a chunk; a later run without it flies the rest)")
    ap.add_argument("--no-progress", action="store_true", help="no line per episode (tables and sets still report)")
    args = ap.parse_args(argv)
    if args.workers is not None and args.workers < 1:
        ap.error(f"--workers must be >= 1, got {args.workers}")
    out = Path(args.out)

    def report(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    try:
        manifest = load_manifest(args.manifest)
        subset = Subset(args.count, args.runs)
        names = [t.name for t in manifest.select(_csv(args.tables))]
        if args.from_runs and not out.is_dir():
            raise ManifestError(f"--from-runs: no output folder {out}")
        report(f"checking {len(manifest.tables)} tables of {args.manifest}")
        planned = plan_tables(manifest, subset)
        only = _csv(args.methods)
        if only is not None:
            check_methods(planned, names, only)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    command = " ".join(["experiments/tables_of_record.py", *(argv if argv is not None else sys.argv[1:])])
    try:
        if args.from_runs:
            state = read_state(out)
        else:
            workers = args.workers or manifest.workers
            # a TERM (a session's end, a scheduler's stop) unwinds like Ctrl-C: the running
            # table's wall time is written and the finished episodes are already on disk
            with sigterm_exits():
                stop_ray = _start_ray(args.ray, workers) if args.ray else None
                try:
                    state = run_tables(planned, out, names, code=code_version(), check=lambda: code_version(), allow_mixed=args.allow_mixed,
                                       workers=workers, ray_address=args.ray, report=report, episode_lines=not args.no_progress,
                                       methods=only)  # fmt: skip
                finally:
                    if stop_ray is not None:
                        stop_ray()
    except CodeVersionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    records = collect_records(manifest, planned, out)
    header = make_header(manifest, planned, state, subset=subset, command=command)
    tables = write_artifacts(out, header, records, args.json)
    sys.stdout.write(format_document(tables))
    size = (out / RECORDS_FILE).stat().st_size
    report(f"wrote {out / RECORDS_FILE} ({len(records)} episodes, {size / 1024:.0f} KiB), {out / 'tables.md'}, {out / 'tables.json'}")
    for t in tables["tables"]:
        if t["episodes"] < t["planned"]:
            report(f"incomplete: {t['name']} has {t['episodes']} of {t['planned']} episodes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
