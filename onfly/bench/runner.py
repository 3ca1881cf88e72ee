"""The benchmark runner: methods x tasks x runs, in parallel, resumable, reproducible.

A run is described by a TOML config (``experiments/configs/*.toml``, see :class:`BenchConfig`)
and writes into an output folder:

- ``episodes.jsonl``: one JSON line per finished episode, appended as soon as it finishes
  (config hash, method, task, kind, run index, seed, metrics, end and failure reason, VLM calls
  and their charged latency, simulated and wall seconds, the method's own summary);
- ``summary.json`` and ``summary.md``: SR / OSR / CR / FT / NE / SPL per method and per method
  and task kind, the error model and the realtime factor (simulated s / wall s of the episodes;
  ``realtime_factor_cpu`` divides by their CPU time instead, which a shared machine does not
  distort);
- ``config.json``: the resolved config and the hash of each method's part.

Episodes are keyed by ``(config hash, method, task, run index)``: an interrupted run started
again with the same config and folder skips every episode already in ``episodes.jsonl``. The
config hash of a method covers everything that can change its results (episode protocol,
world, shared planner / ESDF / verifier tables, the method's own options, VLM spec, base seed,
the task's content), never the worker count, folder or task selection.

Determinism: an episode's seed is derived from ``(base seed, task id, run index)`` only, every
episode builds a fresh world and method in whatever process runs it, and planners cached per
process are reset at every episode; results are therefore identical whatever the number of
workers, and equal on Ray (``ray_address``) and local processes.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import hashlib
import json
import logging
import multiprocessing as mp
import os
import signal
import time
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from onfly import defaults
from onfly.serialize import to_jsonable
from onfly.bench.code_version import CodeVersion, code_version
from onfly.bench.episode import EpisodeConfig, EpisodeResult, run_episode
from onfly.bench.metrics import EpisodeMetrics, TrackMetrics, as_track_episode, summarize, summarize_track, track_metrics
from onfly.bench.motion import MOTION_KEYS, motion_metrics
from onfly.bench.registry import get_factory, method_names
from onfly.bench.tasks import KINDS, Task, load_tasks, select_tasks
from onfly.world.realism import PROFILES, realism_profile
from onfly.world.render import RenderConfig
from onfly.world.scene import Scene, load_scene, resolve_scene
from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.trajectory import VehicleState

__all__ = [
    "BenchConfig",
    "BenchConfigError",
    "MixedCodeError",
    "EpisodeJob",
    "episode_seed",
    "error_model_name",
    "plan_jobs",
    "run_job",
    "run_bench",
    "read_records",
    "summarize_records",
    "format_summary",
    "BenchResult",
    "EPISODES_FILE",
    "with_overrides",
    "check_bench",
    "fly_task",
    "check_vlm_spec",
]

log = logging.getLogger(__name__)

EPISODES_FILE = "episodes.jsonl"
SHARED_TABLES = ("planner", "esdf", "verifier", "movers")
_WORLD_KEYS = ("width_px", "height_px", "hfov_deg", "vfov_deg", "render_threads", "realism")


class BenchConfigError(ValueError):
    """A benchmark config that cannot be used (the message names the file and field)."""


def _digest(data: Any) -> str:
    return hashlib.sha256(json.dumps(to_jsonable(data), sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class BenchConfig:
    """A benchmark run (the ``[bench]`` table plus the protocol, world and method tables).

    name : label of the run
    methods : registered method names
    task_ids / scenes / kinds / count : task selection (see :func:`onfly.bench.tasks.select_tasks`)
    task_files : task files (default: the committed ones)
    runs : runs per task (the paper: 3); seed : base seed
    vlm : VLM spec for every method (``sim:<preset>``, see :mod:`vlm.factory`)
    workers : local worker processes
    episode : EpisodeConfig fields; world : camera and renderer (``width_px``, ``height_px``,
        ``hfov_deg``, ``vfov_deg``, ``render_threads``) and the realism profile (``realism``:
        ``"ideal"``, the default, ``"realistic"`` or ``"realistic_calm"``; see ``docs/realism.md``)
    shared : ``planner`` / ``esdf`` / ``verifier`` override tables passed to every method
    method_options : method name -> its own option table (``[methods.<name>]``)
    source : the file it was read from
    """

    name: str = "bench"
    methods: tuple[str, ...] = ("oracle",)
    task_ids: tuple[str, ...] | None = None
    scenes: tuple[str, ...] | None = None
    kinds: tuple[str, ...] | None = None
    count: int | None = None
    task_files: tuple[str, ...] | None = None
    runs: int = 3
    seed: int = defaults.SEED
    vlm: str = defaults.VLM
    workers: int = 1
    episode: dict = field(default_factory=dict)
    world: dict = field(default_factory=dict)
    shared: dict = field(default_factory=dict)
    method_options: dict = field(default_factory=dict)
    source: str | None = None

    def __post_init__(self) -> None:
        where = f"{self.source}: " if self.source else ""
        if not self.methods:
            raise BenchConfigError(f"{where}bench.methods: list at least one method")
        for name in ("runs", "workers"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise BenchConfigError(f"{where}bench.{name} must be a positive integer, got {v!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise BenchConfigError(f"{where}bench.seed must be an integer >= 0, got {self.seed!r}")
        if not isinstance(self.vlm, str) or not self.vlm:
            raise BenchConfigError(f"{where}bench.vlm must be a VLM spec string like 'sim:nominal', got {self.vlm!r}")
        try:
            EpisodeConfig(**self.episode)
        except TypeError as exc:
            raise BenchConfigError(f"{where}[episode]: {exc}; valid fields: {[f.name for f in fields(EpisodeConfig)]}") from None
        except ValueError as exc:
            raise BenchConfigError(f"{where}[episode]: {exc}") from None
        bad = sorted(set(self.world) - set(_WORLD_KEYS))
        if bad:
            raise BenchConfigError(f"{where}[world]: unknown field(s) {bad}; valid: {list(_WORLD_KEYS)}")
        realism = self.world.get("realism", "ideal")
        if not isinstance(realism, str) or realism not in PROFILES:
            raise BenchConfigError(f"{where}[world] realism: unknown profile {realism!r}; valid: {', '.join(PROFILES)}")
        bad = sorted(set(self.shared) - set(SHARED_TABLES))
        if bad:
            raise BenchConfigError(f"{where}unknown shared table(s) {bad}; valid: {list(SHARED_TABLES)}")
        if self.kinds is not None:
            bad = sorted(set(self.kinds) - set(KINDS))
            if bad:
                raise BenchConfigError(f"{where}bench.tasks.kinds: unknown kind(s) {bad}; valid: {list(KINDS)}")

    # -- loading ---------------------------------------------------------------------------
    @classmethod
    def from_toml(cls, path: str | Path) -> "BenchConfig":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"benchmark config not found: {path}")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise BenchConfigError(f"{path}: not valid TOML: {exc}") from None
        return cls.from_dict(data, source=str(path))

    @classmethod
    def from_dict(cls, data: dict, source: str | None = None) -> "BenchConfig":
        where = f"{source}: " if source else ""
        allowed = ("bench", "episode", "world", "methods", *SHARED_TABLES)
        bad = sorted(set(data) - set(allowed))
        if bad:
            raise BenchConfigError(f"{where}unknown table(s) {bad}; valid: {list(allowed)}")
        b = dict(data.get("bench", {}))
        sel = dict(b.pop("tasks", {}) or {})
        bad_sel = sorted(set(sel) - {"ids", "scenes", "kinds", "count", "files"})
        if bad_sel:
            raise BenchConfigError(f"{where}bench.tasks: unknown field(s) {bad_sel}; valid: ids, scenes, kinds, count, files")
        valid = {"name", "methods", "runs", "seed", "vlm", "workers"}
        bad = sorted(set(b) - valid)
        if bad:
            raise BenchConfigError(f"{where}[bench]: unknown field(s) {bad}; valid: {sorted(valid | {'tasks'})}")
        methods_tbl = data.get("methods", {})
        if not isinstance(methods_tbl, dict) or not all(isinstance(v, dict) for v in methods_tbl.values()):
            raise BenchConfigError(f"{where}[methods.<name>] must be tables of options")

        def tup(v, field_name):
            if v is None:
                return None
            if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
                raise BenchConfigError(f"{where}{field_name} must be a list of strings, got {v!r}")
            return tuple(v)

        methods = b.get("methods", ["oracle"])
        return cls(
            name=str(b.get("name", Path(source).stem if source else "bench")),
            methods=tup(methods if isinstance(methods, list) else [methods], "bench.methods"),
            task_ids=tup(sel.get("ids"), "bench.tasks.ids"),
            scenes=tup(sel.get("scenes"), "bench.tasks.scenes"),
            kinds=tup(sel.get("kinds"), "bench.tasks.kinds"),
            count=sel.get("count"),
            task_files=_relative_to(tup(sel.get("files"), "bench.tasks.files"), source),
            runs=b.get("runs", 3),
            seed=b.get("seed", 0),
            vlm=b.get("vlm", "sim:nominal"),
            workers=b.get("workers", 1),
            episode=dict(data.get("episode", {})),
            world=dict(data.get("world", {})),
            shared={k: dict(data[k]) for k in SHARED_TABLES if k in data},
            method_options={k: dict(v) for k, v in methods_tbl.items()},
            source=source,
        )

    # -- identity ----------------------------------------------------------------------------
    def method_options_for(self, method: str) -> dict:
        """Options handed to the method's factory: shared tables plus its own table."""
        opts = {k: dict(v) for k, v in self.shared.items()}
        opts.update(self.method_options.get(method, {}))
        return opts

    def method_hash(self, method: str) -> str:
        """Hash of everything that can change ``method``'s results (see the module docstring).
        The ideal realism profile is left out, so hashes of runs before profiles still match."""
        world = self.world_settings()
        if world.get("realism") == "ideal":
            del world["realism"]
        return _digest(
            {
                "method": method,
                "options": self.method_options_for(method),
                "episode": asdict(EpisodeConfig(**self.episode)),
                "world": world,
                "vlm": self.vlm,
                "seed": self.seed,
            }
        )

    def world_settings(self) -> dict:
        w = dict(defaults.WORLD)
        w.setdefault("realism", "ideal")
        w.update(self.world)
        return w

    def to_dict(self) -> dict:
        return to_jsonable(asdict(self))


def _relative_to(paths: tuple[str, ...] | None, source: str | None) -> tuple[str, ...] | None:
    """Relative paths inside a config resolve against the config file's folder."""
    if paths is None or source is None:
        return paths
    base = Path(source).resolve().parent
    return tuple(str(p if Path(p).is_absolute() else (base / p).resolve()) for p in (Path(x).expanduser() for x in paths))


def episode_seed(base_seed: int, task_id: str, run_index: int) -> int:
    """Seed of one episode, from the base seed, the task and the run index only (< 2**31)."""
    h = hashlib.sha256(f"onfly-episode:{int(base_seed)}:{task_id}:{int(run_index)}".encode()).digest()
    return int.from_bytes(h[:4], "little") & 0x7FFFFFFF


def error_model_name(vlm_spec: str) -> str:
    """The simulated-VLM error model of a spec (``sim:nominal`` -> ``nominal``), or
    ``real:<spec>`` for a real backend."""
    if vlm_spec.startswith("sim:"):
        return vlm_spec.split(":", 1)[1] or "nominal"
    return f"real:{vlm_spec}"


def _task_digest(task: Task) -> str:
    return _digest(
        {
            "instruction": task.instruction,
            "start": [task.start.position_m, task.start.yaw_rad],
            "goal": [task.goal.center_m, task.goal.half_extents_m],
            "reference": None if task.reference is None else [task.reference.path_length_m, task.reference.waypoints_m],
        }
    )


@dataclass(frozen=True)
class EpisodeJob:
    """One episode to run (picklable; a worker rebuilds world and method from it)."""

    method: str
    task_id: str
    run_index: int
    seed: int
    config_hash: str
    vlm: str
    options: dict
    episode: dict
    world: dict
    task_files: tuple[str, ...] | None

    @property
    def key(self) -> str:
        return f"{self.config_hash}/{self.method}/{self.task_id}/{self.run_index}"


def plan_jobs(config: BenchConfig, tasks: Sequence[Task]) -> list[EpisodeJob]:
    """All episodes of a run, method-major then task then run index."""
    jobs = []
    for m in config.methods:
        base = config.method_hash(m)
        for t in tasks:
            h = _digest([base, _task_digest(t)])
            for r in range(config.runs):
                jobs.append(
                    EpisodeJob(m, t.task_id, r, episode_seed(config.seed, t.task_id, r), h, config.vlm,
                               config.method_options_for(m), dict(config.episode), config.world_settings(), config.task_files)
                )
    return jobs


# -- running one episode (in any process) ---------------------------------------------------


@functools.lru_cache(maxsize=4)
def _tasks_by_id(files: tuple[str, ...] | None) -> dict[str, Task]:
    return {t.task_id: t for t in load_tasks(files)}


@functools.lru_cache(maxsize=16)
def _scene(name_or_path: str) -> Scene:
    return load_scene(resolve_scene(name_or_path))


def _task_scene(task: Task) -> Scene:
    """The scene a task flies in: the file its task file named (external scenes), else the
    committed scene of that name."""
    return _scene(task.scene_ref)


def _failure(end_reason: str, m: EpisodeMetrics) -> str:
    if m.success:
        return ""
    if end_reason == "stopped":
        return "stopped_outside_radius"
    return end_reason


def world_camera(world: dict | None = None) -> PinholeCamera:
    """The benchmark's camera for ``world`` settings (``width_px``, ``height_px``, ``hfov_deg``,
    ``vfov_deg``; missing ones from :data:`onfly.defaults.WORLD`)."""
    w = dict(defaults.WORLD)
    w.update(world or {})
    return PinholeCamera.from_fov(int(w["width_px"]), int(w["height_px"]), float(w["hfov_deg"]), float(w["vfov_deg"]))


def fly_task(
    task: Task,
    method: str,
    *,
    vlm: str = defaults.VLM,
    seed: int = defaults.SEED,
    options: dict | None = None,
    episode: dict | None = None,
    world: dict | None = None,
    observer: Callable | None = None,
    on_world: Callable[[World], None] | None = None,
) -> tuple[EpisodeResult, dict]:
    """Fly one task with a registered method exactly as the benchmark does.

    Parameters
    ----------
    task : the task (its scene, start, goal and reference)
    method : registered method name (:func:`onfly.bench.registry.method_names`)
    vlm : VLM spec; seed : episode seed
    options : the method's options (shared ``planner`` / ``esdf`` / ``verifier`` tables and its
        own fields, as in a benchmark config)
    episode : EpisodeConfig fields (defaults: :mod:`onfly.defaults`)
    world : camera and renderer settings (``width_px`` ...; defaults: :data:`onfly.defaults.WORLD`)
    observer : called with every :class:`onfly.bench.episode.EpisodeStep` (must not change the world)
    on_world : called once with the fresh World before the episode (recordings: the scene mesh)

    Returns
    -------
    (EpisodeResult, extras) : extras holds ``min_clearance_m`` (exact, to the scene mesh),
    ``failure`` (empty on success), ``motion`` (:class:`onfly.bench.motion.MotionMetrics` as a
    dict) and ``cpu_s``; a tracking task's extras add ``track``
    (:class:`onfly.bench.metrics.TrackMetrics` as a dict), and its episode lasts the task's
    ``duration_s`` and its SR / OSR / SPL are the tracking ones (:func:`as_track_episode`).
    """
    if task.reference is None:
        raise ValueError(f"task {task.task_id!r} has no reference path: run `onfly tasks check --write`")
    w = dict(defaults.WORLD)
    w.update(world or {})
    ep = EpisodeConfig(**(episode or {}))
    if task.track is not None:  # a tracking episode lasts the task's duration
        ep = replace(ep, time_limit_s=float(task.track.duration_s))
    camera = world_camera(w)
    start = VehicleState(0.0, task.start.position_m.copy(), np.zeros(3), float(task.start.yaw_rad))
    realism = realism_profile(w.get("realism", "ideal"))
    the_world = World(_task_scene(task), camera=camera, render_config=RenderConfig(threads=int(w["render_threads"])), initial_state=start,
                      realism=realism, seed=seed)
    if on_world is not None:
        on_world(the_world)
    cpu0 = time.process_time()
    factory = get_factory(method)
    the_method = factory(vlm, seed, **{k: (dict(v) if isinstance(v, dict) else v) for k, v in (options or {}).items()})
    yaws = {0.0: float(start.yaw)}

    def watch(step) -> None:
        yaws[round(float(step.t_s), 6)] = float(step.state.yaw)
        if observer is not None:
            observer(step)

    result = run_episode(
        the_world,
        the_method,
        instruction=task.instruction,
        goal=task.goal_region,
        reference_path_m=task.reference.path_length_m,
        seed=seed,
        error_model=error_model_name(vlm),
        config=ep,
        privileged=task.privileged_goal(),
        observer=watch,
    )
    cpu_s = time.process_time() - cpu0
    tr = result.trace
    yaw = np.array([yaws.get(round(float(t), 6), np.nan) for t in tr.t_s])
    yaw[-1] = float(the_world.state.yaw)
    good = np.isfinite(yaw)  # the last control period's heading is the world's final state
    if not good.all():
        idx = np.arange(len(yaw))
        yaw[~good] = np.interp(idx[~good], idx[good], yaw[good])
    goal = task.goal_region
    motion = motion_metrics(tr.t_s, tr.positions, yaw, goal.center, goal.distance(tr.positions), ep.success_radius_m)
    clearance = the_world.collision.clearance(tr.positions, tr.t_s)  # people at their pose then
    track = None
    if task.track is not None:
        track = _track_metrics(task, the_world, tr)
        result = replace(result, metrics=as_track_episode(result.metrics, track))
    extras = {
        "min_clearance_m": float(clearance.min()),
        "failure": _failure(result.end_reason, result.metrics),
        "motion": motion.to_dict(),
        "cpu_s": cpu_s,
    }
    if track is not None:
        extras["track"] = asdict(track)
    return result, extras


def _track_metrics(task: Task, world: World, trace) -> TrackMetrics:
    """Tracking metrics of a flown trace against the followed actor's true poses."""
    from onfly.world.actors import poses_at

    motion = world.scene.object_by_name(task.track.actor).motion
    P, _, _, moving = poses_at(motion, np.asarray(trace.t_s, float))
    tr = task.track
    return track_metrics(trace, P, moving, band_m=tr.band_m, in_band_frac=tr.in_band_frac, duration_s=tr.duration_s,
                         lost_after_s=tr.lost_after_s, stop_radius_m=tr.stop_radius_m)


def run_job(job: EpisodeJob) -> dict:
    """Run one episode and return its JSON-able record (the line written to episodes.jsonl)."""
    task = _tasks_by_id(job.task_files)[job.task_id]
    result, extras = fly_task(
        task, job.method, vlm=job.vlm, seed=job.seed, options=job.options, episode=job.episode, world=job.world
    )
    rec = result.to_dict()
    return to_jsonable(
        {
            "key": job.key,
            "config_hash": job.config_hash,
            "method": job.method,
            "task": task.task_id,
            "scene": task.scene,
            "kind": task.kind,
            "run": job.run_index,
            "seed": job.seed,
            "vlm": job.vlm,
            "error_model": error_model_name(job.vlm),
            "realism": realism_profile(job.world.get("realism", "ideal")).name,
            "metrics": rec.pop("metrics"),
            "end_reason": rec.pop("end_reason"),
            **extras,
            **rec,
        }
    )


# -- checks before the first episode ------------------------------------------------------------


def check_vlm_spec(spec: str, *, reach: bool = True, timeout_s: float = 3.0) -> None:
    """Raise a ValueError naming what is wrong with a VLM spec, before any episode flies.

    ``sim:`` specs are built once (an unknown preset fails here); ``http:`` servers are
    reached once (``GET /v1/models``) when ``reach``; ``transformers:`` needs its checkpoint
    directory (or a hub id) and is not loaded here.
    """
    from vlm.factory import VALID_SPECS, make_backend

    if not isinstance(spec, str) or ":" not in spec:
        raise ValueError(f"bad VLM backend spec {spec!r}: expected <kind>:<argument>; valid forms: {VALID_SPECS}")
    kind = spec.split(":", 1)[0].strip().lower()
    if kind == "sim":
        make_backend(spec, seed=0)
        return
    if kind in ("http", "https"):
        from vlm.types import VlmError

        url, _, model = spec.split(":", 1)[1].partition("#")
        try:
            backend = make_backend(spec if model.strip() else spec + "#probe", timeout_s=timeout_s)
            models = backend.list_models(timeout_s=timeout_s) if reach else None
        except VlmError as exc:
            raise ValueError(f"VLM backend {spec!r} cannot be reached: {exc}") from None
        except OSError as exc:
            raise ValueError(f"VLM backend {spec!r} cannot be reached: {exc}") from None
        if reach and not models:
            raise ValueError(f"VLM backend {spec!r} serves no models")
        if reach and model.strip() and model.strip() not in models:
            raise ValueError(f"VLM backend {spec!r}: the server has no model {model.strip()!r} (it serves {', '.join(models)})")
        return
    if kind == "transformers":
        path = spec.split(":", 1)[1].strip()
        from vlm.factory import _HUB_ID  # the same rule make_backend applies

        if not path or not (Path(path).expanduser().is_dir() or _HUB_ID.match(path)):
            raise ValueError(f"bad VLM backend spec {spec!r}: no checkpoint directory at {path!r}")
        return
    make_backend(spec)  # raises the factory's own message for an unknown kind


def check_bench(config: BenchConfig, *, reach_vlm: bool = True) -> list[Task]:
    """Everything a benchmark run needs, checked before the first episode; returns its tasks.

    Checks: method names, the task files and selection, the tasks' reference paths, the VLM
    spec (an ``http:`` server is reached once) and every method's options (each factory is
    built once, so an unknown planner field fails here, naming the config file).
    Raises BenchConfigError (a ValueError) with one line naming what is wrong.
    """
    where = f"{config.source}: " if config.source else ""
    unknown = [m for m in config.methods if m not in method_names()]
    if unknown:
        raise BenchConfigError(f"{where}unknown method(s) {unknown}; registered methods: {', '.join(method_names())}")
    unknown = sorted(m for m in config.method_options if m not in method_names())
    if unknown:
        raise BenchConfigError(f"{where}[methods.{unknown[0]}]: no registered method {unknown[0]!r}; registered: {', '.join(method_names())}")
    try:
        all_tasks = load_tasks(config.task_files)
        tasks = select_tasks(all_tasks, ids=config.task_ids, scenes=config.scenes, kinds=config.kinds, count=config.count)
    except (ValueError, FileNotFoundError) as exc:
        raise BenchConfigError(f"{where}task selection: {exc}") from None
    if not tasks:
        raise BenchConfigError(f"{where}the task selection is empty")
    unchecked = [t.task_id for t in tasks if t.reference is None]
    if unchecked:
        raise BenchConfigError(f"{where}task(s) without a reference path {unchecked[:5]}: run `onfly tasks check --write`")
    try:
        check_vlm_spec(config.vlm, reach=reach_vlm)
    except ValueError as exc:
        raise BenchConfigError(f"{where}bench.vlm: {' '.join(str(exc).split())}") from None
    for m in config.methods:
        opts = config.method_options_for(m)
        try:
            get_factory(m)(config.vlm, 0, **{k: (dict(v) if isinstance(v, dict) else v) for k, v in opts.items()})
        except (ValueError, TypeError) as exc:
            tables = sorted(set(opts))
            raise BenchConfigError(f"{where}options of method {m!r} (tables/keys {tables}): {' '.join(str(exc).split())}") from None
    return tasks


# -- results ------------------------------------------------------------------------------------


def read_records(path: str | Path) -> list[dict]:
    """Records of an episodes.jsonl (a torn last line from an interrupted write is skipped)."""
    path = Path(path)
    if not path.is_file():
        return []
    out = []
    with path.open() as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                log.warning("%s:%d: skipping an unreadable line (interrupted write?)", path, n)
    return out


def _metrics(rec: dict) -> EpisodeMetrics:
    m = rec["metrics"]
    return EpisodeMetrics(**{f.name: m[f.name] for f in fields(EpisodeMetrics)})


def _block(recs: list[dict]) -> dict:
    s = summarize(_metrics(r) for r in recs)
    sim = sum(r["sim_s"] for r in recs)
    wall = sum(r["wall_s"] for r in recs)
    cpu = sum(r.get("cpu_s", 0.0) for r in recs)
    s["realtime_factor"] = sim / wall if wall > 0 else None
    s["realtime_factor_cpu"] = sim / cpu if cpu > 0 else None
    s["sim_s"] = sim
    s["wall_s"] = wall
    s["cpu_s"] = cpu
    clear = [r["min_clearance_m"] for r in recs if r.get("min_clearance_m") is not None]
    s["min_clearance_m"] = min(clear) if clear else None
    for key in MOTION_KEYS:
        vals = [r["motion"][key] for r in recs if r.get("motion") and r["motion"].get(key) is not None]
        s[key] = float(np.mean(vals)) if vals else None
    tracked = [TrackMetrics(**r["track"]) for r in recs if r.get("track")]
    s["track"] = summarize_track(tracked) if tracked else None
    s["failures"] = {}
    for r in recs:
        if r["failure"]:
            s["failures"][r["failure"]] = s["failures"].get(r["failure"], 0) + 1
    calls: dict[str, float] = {}
    charged: dict[str, float] = {}
    for r in recs:
        for k, v in (r.get("vlm_calls") or {}).items():
            calls[k] = calls.get(k, 0) + v
        for k, v in (r.get("vlm_charged_s") or {}).items():
            charged[k] = charged.get(k, 0.0) + v
    s["vlm_calls_per_episode"] = {k: v / len(recs) for k, v in calls.items()}
    s["vlm_charged_s_per_episode"] = {k: v / len(recs) for k, v in charged.items()}
    return to_jsonable(s)


def summarize_records(records: Iterable[dict], *, error_model: str, name: str = "bench") -> dict:
    """The summary JSON: per method (and per method and kind) metrics, error model, realtime factor."""
    recs = list(records)
    by_method: dict[str, list[dict]] = {}
    for r in recs:
        by_method.setdefault(r["method"], []).append(r)
    methods = {}
    for m, rs in by_method.items():
        block = _block(rs)
        block["error_model"] = error_model
        block["by_kind"] = {k: _block([r for r in rs if r["kind"] == k]) for k in KINDS if any(r["kind"] == k for r in rs)}
        methods[m] = block
    sim = sum(r["sim_s"] for r in recs)
    wall = sum(r["wall_s"] for r in recs)
    cpu = sum(r.get("cpu_s", 0.0) for r in recs)
    return to_jsonable(
        {
            "name": name,
            "error_model": error_model,
            "episodes": len(recs),
            "realtime_factor": sim / wall if wall > 0 else None,
            "realtime_factor_cpu": sim / cpu if cpu > 0 else None,
            "methods": methods,
        }
    )


def _pct(x) -> str:
    return "  n/a" if x is None else f"{100 * x:5.1f}"


def _num(x, fmt="{:5.1f}") -> str:
    return "  n/a" if x is None else fmt.format(x)


def format_summary(summary: dict) -> str:
    """Markdown table: one row per method and one per method and task kind."""
    lines = [
        f"### {summary['name']} (simulated VLM error model: {summary['error_model']}; {summary['episodes']} episodes)",
        "",
        "| method | kind | episodes | SR % | OSR % | CR % | FT s | NE m | SPL | realtime x |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for m, b in summary["methods"].items():
        rows = [("all", b)] + list(b["by_kind"].items())
        for kind, s in rows:
            lines.append(
                f"| {m} | {kind} | {s['episodes']} | {_pct(s['SR'])} | {_pct(s['OSR'])} | {_pct(s['CR'])} | "
                f"{_num(s['FT'])} | {_num(s['NE'], '{:5.2f}')} | {_num(s['SPL'], '{:4.2f}')} | {_num(s['realtime_factor'], '{:5.2f}')} |"
            )
    tracking = [(m, b["by_kind"]["track"]) for m, b in summary["methods"].items() if (b.get("by_kind") or {}).get("track", {}).get("track")]
    if tracking:
        lines += [
            "",
            "| method | tracking episodes | SR % | CR % | time in band % | band error m | lost | re-found | stop held % |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        for m, s in tracking:
            t = s["track"]
            stop = t.get("stop_ok")
            stop_txt = _pct(stop)
            lines.append(
                f"| {m} | {s['episodes']} | {_pct(s['SR'])} | {_pct(s['CR'])} | {_pct(t['in_band'])} | {_num(t['band_error_m'], '{:5.2f}')} | "
                f"{_num(t['lost'], '{:4.2f}')} | {_num(t['refound'], '{:4.2f}')} | {stop_txt} |"
            )
    return "\n".join(lines)


# -- executing ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class BenchResult:
    """What :func:`run_bench` did: the summary, the records it covers, and counts."""

    summary: dict
    records: list
    ran: int
    skipped: int
    out_dir: Path
    wall_s: float
    errored: tuple = ()


#: Compute threads per local worker process (BLAS/OpenMP, Open3D, torch), set deliberately so
#: two workers on two cores do not spin extra pools (issue 22); ``ONFLY_WORKER_THREADS``
#: overrides it.
WORKER_THREADS = 1


def worker_threads() -> int:
    """Threads per worker: ``$ONFLY_WORKER_THREADS`` (an int >= 1) or :data:`WORKER_THREADS`."""
    raw = os.environ.get("ONFLY_WORKER_THREADS")
    if raw is None:
        return WORKER_THREADS
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise BenchConfigError(f"ONFLY_WORKER_THREADS must be an integer >= 1, got {raw!r}")
    return n


def _worker_init(level: int, threads: int = WORKER_THREADS) -> None:
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    from planning.threads import limit_threads

    limit_threads(threads)


def _run_local(jobs: list[EpisodeJob], workers: int, on_record: Callable[[dict], None]) -> None:
    if workers <= 1:
        for job in jobs:
            on_record(run_job(job))
        return
    ctx = mp.get_context("spawn")
    pool = cf.ProcessPoolExecutor(
        max_workers=workers, mp_context=ctx, initializer=_worker_init,
        initargs=(logging.getLogger().level, worker_threads()),
    )
    try:
        futures = [pool.submit(run_job, j) for j in jobs]
        for fut in cf.as_completed(futures):
            on_record(fut.result())
    except BaseException:
        _stop_pool(pool)
        raise
    pool.shutdown(wait=True)


def _stop_pool(pool: cf.ProcessPoolExecutor) -> None:
    """Cancel the episodes not started and end the workers now (Ctrl-C, a TERM, an error).

    ``shutdown(wait=False, cancel_futures=True)`` alone lets every worker finish its episode and
    the ones already queued to it, as orphans once this process has exited (two benchmark workers
    ran on for 20 minutes). The episodes finished are on disk already; the ones cut short are
    flown again by a rerun, which resumes."""
    # no public handle on the workers before Python 3.14's terminate_workers()
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=5.0)


@contextlib.contextmanager
def sigterm_exits():
    """Within the block a TERM (a session's end, a scheduler's stop, ``kill``) unwinds like
    Ctrl-C, as ``SystemExit(143)``: ``finally`` blocks run and the workers are stopped. Restores
    the previous handler after. Main thread only (Python's rule for signal handlers)."""

    def _exit(signum: int, frame: Any) -> None:
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, _exit)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def init_ray(address: str, workers: int) -> bool:
    """Start Ray (``address == "local"``: on this machine with ``workers`` CPUs) or join the
    cluster at ``address``, unless Ray is already initialized; True when this call started it
    (the caller then shuts it down)."""
    import ray  # optional at import time: only --ray needs it

    if ray.is_initialized():
        return False
    if address == "local":
        ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address=address, log_to_driver=False)
    return True


def _run_ray(jobs: list[EpisodeJob], address: str, workers: int, on_record: Callable[[dict], None]) -> None:
    import ray  # optional at import time: only --ray needs it

    started = init_ray(address, workers)
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(run_job)
        pending = [remote.remote(j) for j in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            on_record(ray.get(done[0]))
    finally:
        if started:
            ray.shutdown()


def run_bench(
    config: BenchConfig,
    out_dir: str | Path,
    *,
    workers: int | None = None,
    ray_address: str | None = None,
    max_episodes: int | None = None,
    progress: bool | Callable[[dict, int, int], None] = False,
    checked_tasks: Sequence[Task] | None = None,
    allow_mixed_code: bool = False,
) -> BenchResult:
    """Run (or resume) a benchmark and write episodes.jsonl, summary.json, summary.md, config.json.

    Parameters
    ----------
    config : BenchConfig
    out_dir : output folder (created); episodes already recorded there are not run again
    workers : local worker processes (default ``config.workers``); with ``ray_address`` the
        number of CPUs of a local Ray instance
    ray_address : None (local processes), ``"local"`` (start a local Ray instance) or a Ray
        cluster address
    max_episodes : stop after this many new episodes (for tests of resumption)
    allow_mixed_code : resume a folder whose episodes other code flew (each record carries
        its :class:`onfly.bench.code_version.CodeVersion`); without it that is a
        :class:`MixedCodeError` before any episode, since one table would hold two versions
    progress : True shows a tqdm bar with an ETA; a callable gets ``(record, done, total)``
        after every episode (a caller's own progress line)
    checked_tasks : the tasks :func:`check_bench` returned for this config (skips the checks
        when the caller already ran them); otherwise everything is checked before the first
        episode and nothing is written on a bad config

    The result's ``errored`` lists the episodes that ended with ``method_error``.
    """
    wall0 = time.perf_counter()
    out = Path(out_dir)
    tasks = check_bench(config) if checked_tasks is None else list(checked_tasks)
    jobs = plan_jobs(config, tasks)
    code = code_version()
    path = out / EPISODES_FILE
    if not allow_mixed_code:
        _check_one_code(path, {j.key for j in jobs}, code)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(
        json.dumps({"config": config.to_dict(), "method_hashes": {m: config.method_hash(m) for m in config.methods}}, indent=1)
    )
    done = {r["key"] for r in read_records(path)}
    todo = [j for j in jobs if j.key not in done]
    skipped = len(jobs) - len(todo)
    if max_episodes is not None:
        todo = todo[:max_episodes]
    n_workers = config.workers if workers is None else int(workers)
    bar = None
    callback = progress if callable(progress) else None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="ep", desc=config.name, dynamic_ncols=True)
    ran = 0
    with path.open("a") as f:

        def on_record(rec: dict) -> None:
            nonlocal ran
            rec["code"] = code.as_dict()
            f.write(json.dumps(rec, sort_keys=True) + "\n")
            f.flush()
            ran += 1
            if bar is not None:
                bar.set_postfix_str(f"{rec['method']} {rec['task']} {'ok' if rec['metrics']['success'] else rec['failure']}")
                bar.update(1)
            if callback is not None:
                callback(rec, ran, len(todo))

        try:
            if not todo:
                pass
            elif ray_address:
                _run_ray(todo, ray_address, n_workers, on_record)
            else:
                _run_local(todo, n_workers, on_record)
        finally:
            if bar is not None:
                bar.close()
    keys = {j.key for j in jobs}
    latest: dict[str, dict] = {}
    for r in read_records(path):
        if r["key"] in keys:
            latest[r["key"]] = r
    order = {j.key: i for i, j in enumerate(jobs)}
    records = sorted(latest.values(), key=lambda r: order[r["key"]])
    summary = summarize_records(records, error_model=error_model_name(config.vlm), name=config.name) if records else {
        "name": config.name, "error_model": error_model_name(config.vlm), "episodes": 0, "realtime_factor": None, "methods": {}}
    summary["run_wall_s"] = time.perf_counter() - wall0
    summary["complete"] = len(records) == len(jobs)
    versions = sorted({(r["code"]["digest"], r["code"]["commit"]) for r in records if "code" in r})
    summary["code"] = [{"digest": d, "commit": c} for d, c in versions]
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    if records:
        (out / "summary.md").write_text(format_summary(summary) + "\n")
    errored = tuple(f"{r['method']}/{r['task']}/run{r['run']}: {r.get('error') or 'method_error'}" for r in records if r["end_reason"] == "method_error")
    return BenchResult(summary, records, ran, skipped, out, time.perf_counter() - wall0, errored)


class MixedCodeError(ValueError):
    """A benchmark folder holds episodes that other code flew (a ValueError: the command line
    reports it as a usage error, before any episode flies)."""


def _check_one_code(path: Path, keys: set[str], code: CodeVersion) -> None:
    """Raise :class:`MixedCodeError` when a record of ``keys`` in ``path`` names another code
    digest than ``code``'s (records written before the runner recorded the code name none and
    pass)."""
    other: dict[str, str] = {}
    for r in read_records(path):
        c = r.get("code")
        if r.get("key") in keys and isinstance(c, dict) and c.get("digest") != code.digest:
            other.setdefault(str(c.get("digest")), str(c.get("commit")))
    if other:
        versions = ", ".join(f"digest {d} (commit {c})" for d, c in sorted(other.items()))
        raise MixedCodeError(
            f"{path} holds episodes flown by other code: {versions}; this code is digest {code.digest} (commit "
            f"{code.commit}). Resuming would put two code versions in one table: choose a new --out, remove the "
            f"folder, or pass --allow-mixed-code to resume anyway"
        )


def with_overrides(config: BenchConfig, **changes) -> BenchConfig:
    """A copy of ``config`` with fields replaced (None values are ignored)."""
    return replace(config, **{k: v for k, v in changes.items() if v is not None})
