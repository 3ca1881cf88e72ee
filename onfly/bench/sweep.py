"""The one tuning tool: run the benchmark over planner / verifier weights (a grid, or trials
sampled by Optuna) and show what the weights change.

A sweep file (``experiments/configs/sweep_*.toml``, ``tune_*.toml``)::

    [sweep]
    name = "planner"
    base = "quick.toml"            # the benchmark config it modifies (see "Paths" below)
    methods = ["oracle"]           # optional: overrides the base config's methods
    runs = 1                       # optional; also seed, workers, vlm
    [sweep.tasks]                  # optional: overrides the base config's task selection
    count = 10                     # ids, scenes, kinds, count (one or more)

    [grid]                         # grid search: dotted keys -> lists; the grid is their product
    planner.w_yaw = [0.5, 1.0, 2.0]
    planner.w_jerk = [1.0, 2.0]

or, instead of ``[grid]``, a sampled search (Optuna: https://optuna.readthedocs.io)::

    [search]
    trials = 20                    # trials this invocation runs at most (a rerun adds none
                                   # once the study holds this many finished trials)
    sampler = "tpe"                # "tpe" | "random" | "qmc"
    seed = 0                       # the sampler's seed (determinism)
    objectives = ["SR:max", "rms_jerk_mps3:min"]   # one or more <summary key>:<max|min>
    method = "onfly"               # whose summary row the objectives read (default: the first)
    storage = "study.db"           # SQLite file (in the output folder unless absolute) or an
                                   # SQLAlchemy URL (postgresql://...) shared by several machines
    [search.space]
    planner.w_accel = { low = 0.05, high = 2.0, log = true }
    planner.horizon_steps = { low = 10, high = 30, int = true }
    verifier.some_mode = { choices = ["a", "b"] }

A key is ``<table>.<field>`` with table ``planner``, ``esdf`` or ``verifier`` (shared by every
method), ``episode`` or ``world``, or ``methods.<name>.<field>`` for one method's options.
Every combination (grid cell or trial) is an ordinary benchmark run in its own folder
(``<out>/<combination>``): interrupted sweeps resume, and an Optuna study in SQLite resumes
where it stopped (its trials are read back, finished combinations are not flown again).

Parallelism: the episodes of one combination run on ``workers`` local processes or as Ray
tasks (``ray_address``); several ``onfly sweep`` processes (on one machine or several) pointed
at the same ``storage`` run trials in parallel (Optuna's own model of distributed search).

What the weights change: next to SR / CR / FT / SPL every row has the episodes' mean RMS
acceleration and jerk, path length, time to goal and yaw error to the goal bearing
(:mod:`onfly.bench.motion`) and the smallest exact clearance to the scene. Outputs in the
folder: ``sweep.json``, ``sweep.md`` (the table) and ``sweep.html`` (the table and one scatter
plot per metric and key, self-made SVG, no network); with a study also ``study.html``
(Optuna's own plotly plots, plotly.js embedded).

Paths: ``base`` is resolved against the folder of the sweep file; when no file is there, a
bare name (``"quick.toml"``) names a committed config in ``experiments/configs/``.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import re
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

from onfly.bench.motion import MOTION_KEYS
from onfly.bench.runner import SHARED_TABLES, BenchConfig, BenchConfigError, check_bench, run_bench
from onfly.console import live_line
from onfly.serialize import ConfigFileError, read_toml

__all__ = [
    "SweepConfig",
    "SearchSpec",
    "SweepError",
    "apply_setting",
    "combinations",
    "run_sweep",
    "format_sweep",
    "COMMITTED_CONFIGS",
    "ROW_METRICS",
]

log = logging.getLogger(__name__)

#: Where bare ``base`` names are looked up (the committed benchmark configs).
COMMITTED_CONFIGS = Path(__file__).resolve().parents[2] / "experiments" / "configs"

#: Row metrics, in table order: (key, header, format, scale).
ROW_METRICS = (
    ("SR", "SR %", "{:.1f}", 100.0),
    ("CR", "CR %", "{:.1f}", 100.0),
    ("FT", "FT s", "{:.1f}", 1.0),
    ("SPL", "SPL", "{:.2f}", 1.0),
    ("rms_accel_mps2", "RMS acc m/s²", "{:.3f}", 1.0),
    ("rms_jerk_mps3", "RMS jerk m/s³", "{:.3f}", 1.0),
    ("path_length_m", "path m", "{:.2f}", 1.0),
    ("min_clearance_m", "min clearance m", "{:.2f}", 1.0),
    ("time_to_goal_s", "time to goal s", "{:.1f}", 1.0),
    ("yaw_error_deg", "yaw error °", "{:.1f}", 1.0),
)

_SWEEP_KEYS = {"name", "base", "methods", "runs", "seed", "tasks", "workers", "vlm"}
_TASK_KEYS = {"ids", "scenes", "kinds", "count"}
_SEARCH_KEYS = {"trials", "sampler", "seed", "objectives", "method", "storage", "space"}
_SAMPLERS = ("tpe", "random", "qmc")


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


def _space_items(d: dict, prefix: str = "") -> dict[str, dict]:
    """``[search.space]`` flattened to dotted key -> its distribution table."""
    out: dict[str, dict] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and ({"low", "high", "choices"} & set(v)):
            out[key] = v
        elif isinstance(v, dict):
            out.update(_space_items(v, key + "."))
        else:
            out[key] = {"_bad": v}
    return out


@dataclass(frozen=True)
class SearchSpec:
    """A sampled search: trials, sampler, objectives and the space (dotted key -> distribution)."""

    trials: int
    sampler: str
    seed: int
    objectives: tuple[tuple[str, str], ...]
    method: str
    storage: str
    space: tuple[tuple[str, dict], ...]


@dataclass(frozen=True)
class SweepConfig:
    """A parsed sweep: the base benchmark config and a grid (dotted key -> values) or a search."""

    name: str
    base: BenchConfig
    grid: tuple[tuple[str, tuple], ...]
    source: str | None = None
    search: SearchSpec | None = None

    @property
    def keys(self) -> list[str]:
        return [k for k, _ in (self.grid if self.search is None else self.search.space)]

    @classmethod
    def from_toml(cls, path: str | Path) -> "SweepConfig":
        path = Path(path)
        try:
            data = read_toml(path, allowed=("sweep", "grid", "search"), what="sweep config")
        except ConfigFileError as exc:
            if not path.exists():
                raise FileNotFoundError(f"sweep config not found: {path}") from None
            raise SweepError(str(exc)) from None
        sw = dict(data.get("sweep", {}))
        bad = sorted(set(sw) - _SWEEP_KEYS)
        if bad:
            raise SweepError(f"{path}: [sweep]: unknown key(s) {bad}; valid: {sorted(_SWEEP_KEYS)}")
        if "base" not in sw:
            raise SweepError(f"{path}: [sweep]: key 'base' (the benchmark config to modify) is missing")
        base_path = resolve_base(sw["base"], path)
        try:
            base = BenchConfig.from_toml(base_path)
        except BenchConfigError as exc:
            raise SweepError(f"{path}: [sweep] base: {exc}") from None
        changes: dict[str, Any] = {}
        if "methods" in sw:
            if not isinstance(sw["methods"], list) or not all(isinstance(m, str) for m in sw["methods"]):
                raise SweepError(f"{path}: [sweep] methods must be a list of method names, got {sw['methods']!r}")
            changes["methods"] = tuple(sw["methods"])
        for k in ("runs", "seed", "workers", "vlm"):
            if k in sw:
                changes[k] = sw[k]
        if "tasks" in sw:
            t = sw["tasks"]
            if not isinstance(t, dict):
                raise SweepError(f"{path}: [sweep.tasks] must be a table")
            bad = sorted(set(t) - _TASK_KEYS)
            if bad:
                raise SweepError(f"{path}: [sweep.tasks]: unknown key(s) {bad}; valid: {sorted(_TASK_KEYS)}")
            changes.update(
                task_ids=tuple(t["ids"]) if "ids" in t else None,
                scenes=tuple(t["scenes"]) if "scenes" in t else None,
                kinds=tuple(t["kinds"]) if "kinds" in t else None,
                count=t.get("count"),
            )
        try:
            base = replace(base, name=str(sw.get("name", path.stem)), source=str(path), **changes)
        except (TypeError, BenchConfigError) as exc:
            raise SweepError(f"{path}: [sweep]: {exc}") from None
        if ("grid" in data) == ("search" in data):
            raise SweepError(f"{path}: give exactly one of [grid] (grid search) or [search] (sampled search)")
        if "search" in data:
            search = _parse_search(path, base, dict(data["search"]))
            return cls(base.name, base, (), str(path), search)
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


def resolve_base(value: Any, sweep_file: Path) -> Path:
    """The ``base`` benchmark config of a sweep file (see "Paths" in the module docstring)."""
    if not isinstance(value, str) or not value:
        raise SweepError(f"{sweep_file}: [sweep] base must be a path to a benchmark config, got {value!r}")
    p = Path(value).expanduser()
    if p.is_absolute():
        cands = [p]
    else:
        cands = [(sweep_file.resolve().parent / p).resolve()]
        if len(p.parts) == 1:
            cands.append(COMMITTED_CONFIGS / (value if value.endswith(".toml") else value + ".toml"))
    for c in cands:
        if c.is_file():
            return c
    raise SweepError(f"{sweep_file}: [sweep] base {value!r} not found (looked at {', '.join(str(c) for c in cands)})")


def _parse_search(path: Path, base: BenchConfig, s: dict) -> SearchSpec:
    bad = sorted(set(s) - _SEARCH_KEYS)
    if bad:
        raise SweepError(f"{path}: [search]: unknown key(s) {bad}; valid: {sorted(_SEARCH_KEYS)}")
    trials = s.get("trials", 20)
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise SweepError(f"{path}: [search] trials must be a positive integer, got {trials!r}")
    sampler = s.get("sampler", "tpe")
    if sampler not in _SAMPLERS:
        raise SweepError(f"{path}: [search] sampler must be one of {list(_SAMPLERS)}, got {sampler!r}")
    seed = s.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SweepError(f"{path}: [search] seed must be an integer >= 0, got {seed!r}")
    method = s.get("method", base.methods[0])
    if method not in base.methods:
        raise SweepError(f"{path}: [search] method {method!r} is not among the sweep's methods {list(base.methods)}")
    valid_metrics = [k for k, *_ in ROW_METRICS] + ["OSR", "NE"]
    objectives = []
    raw = s.get("objectives", ["SR:max"])
    if not isinstance(raw, list) or not raw:
        raise SweepError(f"{path}: [search] objectives must be a non-empty list like ['SR:max', 'rms_jerk_mps3:min']")
    for o in raw:
        key, _, direction = str(o).partition(":")
        if key not in valid_metrics or direction not in ("max", "min"):
            raise SweepError(f"{path}: [search] objective {o!r}: expected <metric>:<max|min> with metric in {valid_metrics}")
        objectives.append((key, direction))
    storage = s.get("storage", "study.db")
    if not isinstance(storage, str) or not storage:
        raise SweepError(f"{path}: [search] storage must be a SQLite file name or an SQLAlchemy URL, got {storage!r}")
    space = _space_items(dict(s.get("space", {})))
    if not space:
        raise SweepError(f"{path}: [search.space] lists no keys (e.g. planner.w_accel = {{ low = 0.1, high = 2.0, log = true }})")
    items = []
    for key, d in space.items():
        where = f"{path}: [search.space] {key}"
        if "_bad" in d:
            raise SweepError(f"{where}: expected a table {{ low, high[, log, int, step] }} or {{ choices = [...] }}, got {d['_bad']!r}")
        extra = sorted(set(d) - {"low", "high", "log", "int", "step", "choices"})
        if extra:
            raise SweepError(f"{where}: unknown key(s) {extra}; valid: low, high, log, int, step, choices")
        if "choices" in d:
            if not isinstance(d["choices"], list) or not d["choices"] or set(d) != {"choices"}:
                raise SweepError(f"{where}: choices must be a non-empty list (and alone)")
            first = d["choices"][0]
        else:
            lo, hi = d.get("low"), d.get("high")
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (lo, hi)) or not lo < hi:
                raise SweepError(f"{where}: needs finite numbers low < high, got low={lo!r} high={hi!r}")
            if d.get("log") and lo <= 0:
                raise SweepError(f"{where}: log = true needs low > 0, got {lo!r}")
            first = int(lo) if d.get("int") else float(lo)
        apply_setting(base, key, first, where=str(path))  # validates the key
        items.append((key, dict(d)))
    return SearchSpec(trials, sampler, seed, tuple(objectives), method, storage, tuple(items))


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


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return repr(v) if len(repr(v)) <= 8 else f"{v:.4g}"
    return str(v)


def _slug(combo: dict[str, Any]) -> str:
    s = "_".join(f"{k.split('.')[-1]}={v}" for k, v in combo.items())
    return re.sub(r"[^A-Za-z0-9_.=+-]", "-", s)


def _config_for(sweep: SweepConfig, combo: dict[str, Any]) -> BenchConfig:
    cfg = sweep.base
    for k, v in combo.items():
        cfg = apply_setting(cfg, k, v)
    return cfg


def _rows_of(combo: dict, summary: dict) -> list[dict]:
    rows = []
    for method, block in summary["methods"].items():
        row = {**combo, "method": method, "episodes": block["episodes"]}
        for key in ("SR", "OSR", "CR", "FT", "SPL", "NE", "min_clearance_m", "realtime_factor", *MOTION_KEYS):
            row[key] = block.get(key)
        errors = sum(v for k, v in (block.get("failures") or {}).items() if k == "method_error")
        row["method_errors"] = errors
        rows.append(row)
    return rows


class _Progress:
    """The live line: which combination, how many of its episodes, what the last one did."""

    def __init__(self, total: int | None, enabled: bool, stream=None) -> None:
        self.total = total
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()
        self.index = 0
        self.label = ""

    def start(self, index: int, combo: dict) -> None:
        self.index, self.label = index, " ".join(f"{k}={_fmt_value(v)}" for k, v in combo.items())
        self._emit(f"[{index}/{self.total or '?'}] {self.label}: starting")

    def episode(self, rec: dict, done: int, todo: int) -> None:
        what = "ok" if rec["metrics"]["success"] else rec["failure"]
        self._emit(f"[{self.index}/{self.total or '?'}] {self.label}: episode {done}/{todo} {rec['method']} {rec['task']} {what}"
                   f"  ({time.perf_counter() - self.t0:.0f} s)")

    def finish(self, rows: list[dict]) -> None:
        parts = [f"{r['method']} SR {100 * (r['SR'] or 0):.0f}% jerk {_fmt_value(r.get('rms_jerk_mps3'))}" for r in rows]
        self._emit(f"[{self.index}/{self.total or '?'}] {self.label}: done, {'; '.join(parts)}", final=True)

    def _emit(self, line: str, final: bool = False) -> None:
        if self.enabled:
            live_line(line, width=150, final=final, stream=self.stream)


def run_sweep(
    sweep: SweepConfig,
    out_dir: str | Path,
    *,
    workers: int | None = None,
    ray_address: str | None = None,
    progress: bool = False,
    trials: int | None = None,
) -> list[dict]:
    """Run every combination (resumable) and return the table rows (one per combination x method).

    Everything is checked before the first episode (the base config, every grid cell's options
    through the methods' own factories, the VLM spec). A grid runs in row-major order; a search
    asks Optuna for ``trials`` (default ``[search] trials``) combinations. Writes ``sweep.json``,
    ``sweep.md`` and ``sweep.html`` (and ``study.html`` for a search) into ``out_dir``.
    """
    out = Path(out_dir)
    tasks = check_bench(sweep.base)
    if sweep.search is None:
        combos = combinations(sweep)
        for combo in combos:
            check_bench(_config_for(sweep, combo), reach_vlm=False)
        bar = _Progress(len(combos), progress)
        rows = []
        for i, combo in enumerate(combos, 1):
            bar.start(i, combo)
            res = run_bench(_config_for(sweep, combo), out / _slug(combo), workers=workers, ray_address=ray_address,
                            progress=bar.episode if progress else False, checked_tasks=tasks)
            new = _rows_of(combo, res.summary)
            bar.finish(new)
            rows.extend(new)
    else:
        rows = _run_search(sweep, out, tasks, workers=workers, ray_address=ray_address, progress=progress, trials=trials)
    write_report(sweep, rows, out)
    return rows


def _run_search(sweep: SweepConfig, out: Path, tasks, *, workers, ray_address, progress, trials) -> list[dict]:
    import optuna  # the sampled search only

    spec = sweep.search
    assert spec is not None
    out.mkdir(parents=True, exist_ok=True)
    storage = spec.storage if "://" in spec.storage else f"sqlite:///{(out / spec.storage).resolve() if not Path(spec.storage).is_absolute() else spec.storage}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        previous = len(optuna.load_study(study_name=sweep.name, storage=storage).trials)
    except KeyError:
        previous = 0
    # A resumed study's sampler is seeded with the seed plus the trials already asked, so the
    # new trials continue the sequence deterministically instead of repeating its start.
    seed = spec.seed + previous
    samplers = {
        "tpe": lambda: optuna.samplers.TPESampler(seed=seed),
        "random": lambda: optuna.samplers.RandomSampler(seed=seed),
        "qmc": lambda: optuna.samplers.QMCSampler(seed=spec.seed, scramble=True),  # QMC continues by itself
    }
    study = optuna.create_study(
        study_name=sweep.name,
        storage=storage,
        sampler=samplers[spec.sampler](),
        directions=["maximize" if d == "max" else "minimize" for _, d in spec.objectives],
        load_if_exists=True,
    )
    finished = [t for t in study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    done_params = [t.params for t in finished]
    for t in study.trials:  # an interrupted trial is asked again: its folder resumes its episodes
        if t.state in (optuna.trial.TrialState.RUNNING, optuna.trial.TrialState.FAIL) and t.params and t.params not in done_params:
            study.enqueue_trial(t.params, skip_if_exists=True)
            done_params.append(t.params)
    n_new = max(0, (trials if trials is not None else spec.trials) - (len(finished) if trials is None else 0))
    bar = _Progress(len(finished) + n_new, progress)
    rows_by_trial: dict[int, list[dict]] = {}

    def suggest(trial) -> dict:
        combo = {}
        for key, d in spec.space:
            name = key
            if "choices" in d:
                combo[key] = trial.suggest_categorical(name, d["choices"])
            elif d.get("int"):
                combo[key] = trial.suggest_int(name, int(d["low"]), int(d["high"]), step=int(d.get("step", 1)), log=bool(d.get("log")))
            else:
                step = d.get("step")
                combo[key] = trial.suggest_float(name, float(d["low"]), float(d["high"]), log=bool(d.get("log")),
                                                 step=None if step is None else float(step))
        return combo

    def objective(trial):
        combo = suggest(trial)
        cfg = _config_for(sweep, combo)
        check_bench(cfg, reach_vlm=False)
        bar.start(len(finished) + trial.number + 1 - _first_number, combo)
        res = run_bench(cfg, out / _slug(combo), workers=workers, ray_address=ray_address,
                        progress=bar.episode if progress else False, checked_tasks=tasks)
        rows = _rows_of(combo, res.summary)
        bar.finish(rows)
        mine = next(r for r in rows if r["method"] == spec.method)
        for r in rows:
            r["trial"] = trial.number
        trial.set_user_attr("rows", rows)
        values = []
        for key, direction in spec.objectives:
            v = mine.get(key)
            values.append(float(v) if v is not None else (-math.inf if direction == "max" else math.inf))
        return values[0] if len(values) == 1 else values

    _first_number = len(study.trials)
    if n_new:
        study.optimize(objective, n_trials=n_new, catch=())
    rows = []
    for t in study.trials:
        if t.state == optuna.trial.TrialState.COMPLETE:
            rows.extend(t.user_attrs.get("rows", []))
    _study_plots(study, spec, out)
    return rows


def _study_plots(study, spec: SearchSpec, out: Path) -> None:
    """Optuna's own plots (plotly) in one offline HTML file; skipped without plotly."""
    try:
        from optuna import visualization as vis

        if not vis.is_available():
            return
        names = [k for k, _ in spec.objectives]
        figs = []
        for i, name in enumerate(names):
            target = (lambda t, i=i: t.values[i]) if len(names) > 1 else None
            figs.append(vis.plot_parallel_coordinate(study, target=target, target_name=name))
            figs.append(vis.plot_slice(study, target=target, target_name=name))
        if len(names) > 1:
            figs.append(vis.plot_pareto_front(study, target_names=names))
        parts = [f.to_html(full_html=False, include_plotlyjs=(j == 0)) for j, f in enumerate(figs)]
        (out / "study.html").write_text(f"<html><head><meta charset='utf-8'><title>{study.study_name}</title></head><body>"
                                        + "".join(parts) + "</body></html>")
    except Exception as exc:  # plots are a by-product: never lose the results for them
        log.warning("could not draw the study plots: %r", exc)


# -- reports -----------------------------------------------------------------------------------


def write_report(sweep: SweepConfig, rows: list[dict], out: Path) -> None:
    """``sweep.json``, ``sweep.md`` and ``sweep.html`` of a finished sweep."""
    out.mkdir(parents=True, exist_ok=True)
    keys = sweep.keys
    meta = {"name": sweep.name, "keys": keys}
    if sweep.search is None:
        meta["grid"] = [list(g) for g in sweep.grid]
    else:
        meta["search"] = {"trials": sweep.search.trials, "sampler": sweep.search.sampler, "seed": sweep.search.seed,
                          "objectives": [f"{k}:{d}" for k, d in sweep.search.objectives]}
    (out / "sweep.json").write_text(json.dumps({**meta, "rows": rows}, indent=1))
    (out / "sweep.md").write_text(format_sweep(rows, keys) + "\n")
    from onfly.bench.sweep_report import sweep_html

    (out / "sweep.html").write_text(sweep_html(sweep.name, rows, keys, ROW_METRICS))


def format_sweep(rows: list[dict], keys: list[str]) -> str:
    """Markdown table, one row per combination and method."""

    def f(x, fmt, scale=1.0):
        return "n/a" if x is None else fmt.format(scale * x)

    head = "| " + " | ".join(keys) + " | method | episodes | " + " | ".join(h for _, h, _, _ in ROW_METRICS) + " |"
    sep = "| " + " | ".join("---:" for _ in keys) + " | --- | ---: | " + " | ".join("---:" for _ in ROW_METRICS) + " |"
    lines = [head, sep]
    for r in rows:
        cells = [_fmt_value(r[k]) for k in keys] + [r["method"], str(r["episodes"])]
        cells += [f(r.get(k), fmt, scale) for k, _, fmt, scale in ROW_METRICS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
