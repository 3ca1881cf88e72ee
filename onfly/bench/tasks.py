"""Benchmark tasks as data: the format, a loader that names every fault, and selection.

One TOML file per scene (``onfly/data/tasks/<scene>.toml``)::

    format = "onfly-tasks/1"
    scene = "villa"

    [[tasks]]
    id = "villa-p03"                       # unique over all files
    kind = "precise"                       # "object" | "precise" | "long_range"
    instruction = "Stop at the pool edge right next to the ladder."
    subtasks = ["stop at the pool edge next to the ladder"]   # reference decomposition
    targets = ["pool edge", "pool ladder"] # named objects of the scene the instruction uses
    start = { position_m = [-10, -10, 1.5], yaw_deg = 40 }     # optional: the scene's start
    goal = { center_m = [11.6, 0, 0.9], half_extents_m = [0.6, 0.6, 0.6] }
    # or, for object navigation:  goal = { object = "pool ladder", margin_m = 0.2 }
    via = ["fountain"]                     # optional: objects the route passes (long-range)
    # tracking tasks (kind = "track") follow a moving actor instead of reaching a goal:
    # track = { actor = "person in red jacket", band_m = [1.5, 4.0], in_band_frac = 0.8,
    #           duration_s = 60, lost_after_s = 3.0, stop_radius_m = 3.0 }   # stop_radius_m optional

    [tasks.reference]                      # written by `onfly tasks check --write`
    path_length_m = 17.9
    goal_point_m = [11.2, 0.1, 1.2]
    visible_from_m = [9.0, -0.5, 1.4]
    min_clearance_m = 0.61
    waypoints_m = [[-10, -10, 1.5], ..., [11.2, 0.1, 1.2]]

World frame ENU, metres; yaw in degrees in the file, radians here. A goal given by ``object``
is that object's axis-aligned bounds (all its parts) grown by ``margin_m``. Every target, the
goal object and every via object must be a named object of the scene with ``target = true``.

A tracking task (``kind = "track"``, :class:`TrackSpec`; ``docs/tracking.md``) names the actor
to follow (a scene object with a motion, one of the targets), the horizontal distance band to
keep from it, the fraction of the episode to spend in the band, the episode's length, and
optionally a stop radius: "stop next to them when they stop". It has no ``goal`` table: its goal
is the actor's bounds where the actor is at the end of ``duration_s`` (grown by 0.5 m), used
only for the navigation error of the classic metrics.

The reference block is the checker's proof (:mod:`onfly.bench.checker`): a collision-free
path from the start through the via objects to ``goal_point_m`` (a free point next to the goal
region), from which ``visible_from_m`` sees the targets. Committed files hold it, so benchmark
runs never recompute it.
"""

from __future__ import annotations

import functools
import math
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from onfly.bench.method import PrivilegedGoal
from onfly.bench.metrics import GoalRegion
from onfly.world.primitives import mesh_arrays, shape_mesh
from onfly.world.scene import Scene, load_scene, resolve_scene

__all__ = [
    "TASK_FORMAT",
    "KINDS",
    "TaskFormatError",
    "StartPose",
    "GoalSpec",
    "TrackSpec",
    "Reference",
    "Task",
    "tasks_dir",
    "load_task_file",
    "load_tasks",
    "select_tasks",
    "write_task_file",
    "object_bounds",
]

TASK_FORMAT = "onfly-tasks/1"
KINDS = ("object", "precise", "long_range", "track")


class TaskFormatError(ValueError):
    """A task file that does not follow the format.

    Attributes
    ----------
    path : str, the file at fault
    task : str or None, the task id (or ``tasks[i]`` when it has none)
    field : str or None, the field at fault (dotted, e.g. ``goal.margin_m``)
    """

    def __init__(self, path, task: str | None, field: str | None, message: str) -> None:
        self.path = str(path)
        self.task = task
        self.field = field
        where = [self.path]
        if task is not None:
            where.append(f"task {task!r}")
        if field is not None:
            where.append(f"field {field!r}")
        super().__init__(": ".join(where) + f": {message}")


# -- value types ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class StartPose:
    """Where an episode starts: body position (3,) metres ENU, yaw radians (at rest)."""

    position_m: np.ndarray
    yaw_rad: float


@dataclass(frozen=True, eq=False)
class GoalSpec:
    """The goal region: an axis-aligned box (metres, world ENU).

    center_m : (3,); half_extents_m : (3,) >= 0
    object : the scene object the box was derived from (None when given explicitly)
    margin_m : growth applied to that object's bounds (0 for explicit boxes)
    """

    center_m: np.ndarray
    half_extents_m: np.ndarray
    object: str | None = None
    margin_m: float = 0.0

    @property
    def region(self) -> GoalRegion:
        return GoalRegion(self.center_m, self.half_extents_m)


@dataclass(frozen=True)
class TrackSpec:
    """What a tracking task asks (``kind = "track"``; definitions in :mod:`onfly.bench.metrics`).

    actor : name of the scene object to follow (it has a motion)
    band_m : (lo, hi), the horizontal distance band to keep from the actor's centre, metres
    in_band_frac : fraction of the episode the vehicle must spend in the band, (0, 1]
    duration_s : the episode's length (the time limit of a tracking episode), seconds
    lost_after_s : out of the band for longer than this counts as having lost the actor
    stop_radius_m : None, or "stop next to them when they stop": the method must declare its
        stop after the actor has stopped, within this horizontal distance of it
    """

    actor: str
    band_m: tuple[float, float] = (1.5, 4.0)
    in_band_frac: float = 0.8
    duration_s: float = 60.0
    lost_after_s: float = 3.0
    stop_radius_m: float | None = None

    def __post_init__(self) -> None:
        lo, hi = (float(x) for x in self.band_m)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise ValueError(f"TrackSpec.band_m must be 0 < lo < hi, got {self.band_m!r}")
        object.__setattr__(self, "band_m", (lo, hi))
        if not (0 < self.in_band_frac <= 1):
            raise ValueError(f"TrackSpec.in_band_frac must be in (0, 1], got {self.in_band_frac!r}")
        for name in ("duration_s", "lost_after_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"TrackSpec.{name} must be positive, got {v!r}")
        if self.stop_radius_m is not None and not (math.isfinite(self.stop_radius_m) and self.stop_radius_m > 0):
            raise ValueError(f"TrackSpec.stop_radius_m must be positive or absent, got {self.stop_radius_m!r}")

    @property
    def standoff_m(self) -> float:
        """The middle of the band, metres (where a follower aims)."""
        return 0.5 * (self.band_m[0] + self.band_m[1])


@dataclass(frozen=True, eq=False)
class Reference:
    """The checker's result for one task (see the module docstring).

    path_length_m : length of the reference path (for SPL), metres
    waypoints_m : (k, 3), polyline from the start to ``goal_point_m``, world ENU
    goal_point_m : (3,), the free point next to the goal region the path ends at
    visible_from_m : (3,), first path point from which every target is in view
    min_clearance_m : smallest exact distance from the polyline to the scene's triangles
    """

    path_length_m: float
    waypoints_m: np.ndarray
    goal_point_m: np.ndarray
    visible_from_m: np.ndarray
    min_clearance_m: float


@dataclass(frozen=True, eq=False)
class Task:
    """One benchmark task.

    task_id : unique id; scene : committed scene name; kind : one of :data:`KINDS`
    instruction : the natural-language instruction a method receives
    subtasks : the reference decomposition (never shown to methods)
    targets : named scene objects the instruction refers to, in order of mention
    goal : GoalSpec; start : StartPose; via : objects the route passes (long-range)
    reference : the checker's Reference, or None if the task was never checked
    track : TrackSpec of a tracking task (``kind == "track"``), else None
    source : the file the task came from (None if built in code)
    scene_file : the scene file when the task file names one by path (an external scene; a
        relative path resolves against the task file's folder), None for a committed scene
    """

    task_id: str
    scene: str
    kind: str
    instruction: str
    subtasks: tuple[str, ...]
    targets: tuple[str, ...]
    goal: GoalSpec
    start: StartPose
    via: tuple[str, ...] = ()
    reference: Reference | None = None
    source: Path | None = None
    scene_file: Path | None = None
    track: TrackSpec | None = None

    @property
    def goal_region(self) -> GoalRegion:
        return self.goal.region

    @property
    def scene_ref(self) -> str:
        """What the world loads this task's scene from: the scene file's path for an external
        scene, else the committed scene's name (:func:`onfly.world.scene.resolve_scene` takes
        either)."""
        return str(self.scene_file) if self.scene_file is not None else self.scene

    def privileged_goal(self) -> PrivilegedGoal:
        """Ground truth for privileged methods (the oracle): goal box and reference waypoints."""
        wp = self.reference.waypoints_m if self.reference is not None else np.zeros((0, 3))
        motion = None
        if self.track is not None:
            motion = actor_motion(_scene(self.scene_ref), self.track.actor)
        return PrivilegedGoal(self.goal.center_m.copy(), self.goal.half_extents_m.copy(), wp.copy(), self.track, motion)

    def with_reference(self, reference: Reference | None) -> "Task":
        return replace(self, reference=reference)


# -- parsing -------------------------------------------------------------------------------


class _Ctx:
    def __init__(self, path, task: str | None = None, prefix: str = "") -> None:
        self.path, self.task, self.prefix = path, task, prefix

    def sub(self, prefix: str) -> "_Ctx":
        return _Ctx(self.path, self.task, f"{self.prefix}{prefix}.")

    def err(self, field: str | None, message: str) -> TaskFormatError:
        return TaskFormatError(self.path, self.task, None if field is None else f"{self.prefix}{field}", message)


def _get(ctx: _Ctx, t: dict, key: str, default: Any = ...) -> Any:
    if key not in t:
        if default is ...:
            raise ctx.err(key, "missing required field")
        return default
    return t[key]


def _check_keys(ctx: _Ctx, t: dict, allowed: tuple[str, ...]) -> None:
    for k in t:
        if k not in allowed:
            raise ctx.err(k, f"unknown field (allowed: {', '.join(allowed)})")


def _number(ctx: _Ctx, t: dict, key: str, default: Any = ..., *, lo: float | None = None) -> float:
    v = _get(ctx, t, key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ctx.err(key, f"expected a finite number, got {v!r}")
    if lo is not None and v < lo:
        raise ctx.err(key, f"must be >= {lo}, got {v}")
    return float(v)


def _vector(ctx: _Ctx, t: dict, key: str, n: int = 3, *, nonneg: bool = False) -> np.ndarray:
    v = _get(ctx, t, key)
    ok = isinstance(v, list) and len(v) == n
    ok = ok and all(not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in v)
    if not ok:
        raise ctx.err(key, f"expected a list of {n} finite numbers, got {v!r}")
    a = np.asarray(v, dtype=float)
    if nonneg and np.any(a < 0):
        raise ctx.err(key, f"entries must be >= 0, got {v!r}")
    return a


def _points(ctx: _Ctx, t: dict, key: str) -> np.ndarray:
    v = _get(ctx, t, key)
    if not isinstance(v, list) or len(v) < 2:
        raise ctx.err(key, f"expected a list of at least 2 [x, y, z] points, got {v!r}")
    return np.array([_vector(ctx, {f"{key}[{i}]": p}, f"{key}[{i}]") for i, p in enumerate(v)])


def _string(ctx: _Ctx, t: dict, key: str, default: Any = ...) -> str:
    v = _get(ctx, t, key, default)
    if not isinstance(v, str) or not v.strip():
        raise ctx.err(key, f"expected a non-empty string, got {v!r}")
    return v


def _strings(ctx: _Ctx, t: dict, key: str, default: Any = ..., *, min_len: int = 0) -> tuple[str, ...]:
    v = _get(ctx, t, key, default)
    if not isinstance(v, list) or not all(isinstance(s, str) and s.strip() for s in v):
        raise ctx.err(key, f"expected a list of non-empty strings, got {v!r}")
    if len(v) < min_len:
        raise ctx.err(key, f"expected at least {min_len} entries, got {len(v)}")
    return tuple(v)


def object_bounds(scene: Scene, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min (3,), max (3,)) metres of a named object's parts."""
    obj = scene.object_by_name(name)
    V = np.vstack([mesh_arrays(shape_mesh(p.shape))[0] for p in obj.parts])
    return V.min(axis=0).astype(float), V.max(axis=0).astype(float)


def _target_object(ctx: _Ctx, scene: Scene, field: str, name: str) -> None:
    try:
        obj = scene.object_by_name(name)
    except KeyError:
        names = ", ".join(repr(o.name) for o in scene.targets)
        raise ctx.err(field, f"scene {scene.name!r} has no object named {name!r} (targets: {names})") from None
    if not obj.target:
        raise ctx.err(field, f"object {name!r} of scene {scene.name!r} is not a target (target = false)")


_TASK_KEYS = ("id", "kind", "instruction", "subtasks", "targets", "goal", "start", "via", "reference", "track")
_TRACK_KEYS = ("actor", "band_m", "in_band_frac", "duration_s", "lost_after_s", "stop_radius_m")
_REF_KEYS = ("path_length_m", "waypoints_m", "goal_point_m", "visible_from_m", "min_clearance_m")


def _parse_goal(ctx: _Ctx, t: Any, scene: Scene) -> GoalSpec:
    if not isinstance(t, dict):
        raise ctx.err(None, f"expected a table, got {t!r}")
    if "object" in t:
        _check_keys(ctx, t, ("object", "margin_m"))
        name = _string(ctx, t, "object")
        _target_object(ctx, scene, "object", name)
        margin = _number(ctx, t, "margin_m", 0.0, lo=0.0)
        lo, hi = object_bounds(scene, name)
        return GoalSpec((lo + hi) / 2, (hi - lo) / 2 + margin, name, margin)
    _check_keys(ctx, t, ("center_m", "half_extents_m"))
    center = _vector(ctx, t, "center_m")
    if not scene.bounds.contains(center)[0]:
        raise ctx.err("center_m", f"goal centre {center.tolist()} lies outside the scene bounds")
    return GoalSpec(center, _vector(ctx, t, "half_extents_m", nonneg=True))


def _parse_reference(ctx: _Ctx, t: Any) -> Reference:
    if not isinstance(t, dict):
        raise ctx.err(None, f"expected a table, got {t!r}")
    _check_keys(ctx, t, _REF_KEYS)
    return Reference(
        _number(ctx, t, "path_length_m", lo=0.0),
        _points(ctx, t, "waypoints_m"),
        _vector(ctx, t, "goal_point_m"),
        _vector(ctx, t, "visible_from_m"),
        _number(ctx, t, "min_clearance_m", lo=0.0),
    )


def _parse_track(ctx: _Ctx, t: Any, scene: Scene, targets: tuple[str, ...]) -> TrackSpec:
    if not isinstance(t, dict):
        raise ctx.err(None, f"expected a table, got {t!r}")
    _check_keys(ctx, t, _TRACK_KEYS)
    actor = _string(ctx, t, "actor")
    _target_object(ctx, scene, "actor", actor)
    if actor not in targets:
        raise ctx.err("actor", f"the followed actor {actor!r} must be one of the targets {list(targets)}")
    if actor_motion(scene, actor) is None:
        raise ctx.err("actor", f"object {actor!r} of scene {scene.name!r} does not move (it has no motion): nothing to follow")
    band = _get(ctx, t, "band_m", [1.5, 4.0])
    ok = isinstance(band, list) and len(band) == 2 and all(
        not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x) for x in band)
    if not ok or not (0 < band[0] < band[1]):
        raise ctx.err("band_m", f"expected [lo, hi] metres with 0 < lo < hi, got {band!r}")
    frac = _number(ctx, t, "in_band_frac", 0.8, lo=0.0)
    if not (0 < frac <= 1):
        raise ctx.err("in_band_frac", f"must be in (0, 1], got {frac}")
    duration = _number(ctx, t, "duration_s", 60.0, lo=0.0)
    lost = _number(ctx, t, "lost_after_s", 3.0, lo=0.0)
    for key, v in (("duration_s", duration), ("lost_after_s", lost)):
        if v <= 0:
            raise ctx.err(key, f"must be positive, got {v}")
    stop = None
    if "stop_radius_m" in t:
        stop = _number(ctx, t, "stop_radius_m", lo=0.0)
        if stop <= 0:
            raise ctx.err("stop_radius_m", f"must be positive, got {stop}")
    return TrackSpec(actor, (float(band[0]), float(band[1])), frac, duration, lost, stop)


def actor_motion(scene: Scene, name: str):
    """The motion of a named scene object (an actor), or None for a static object."""
    return getattr(scene.object_by_name(name), "motion", None)


def actor_bounds_at(scene: Scene, name: str, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min (3,), max (3,)) metres, world ENU, of an actor at time ``t_s``
    (its parts are given in its own frame, placed at its pose then)."""
    from onfly.world.actors import pose_at

    lo, hi = object_bounds(scene, name)
    pose = pose_at(actor_motion(scene, name), float(t_s))
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    W = corners @ R.T + np.asarray(pose.position_m, float)
    return W.min(axis=0), W.max(axis=0)


def _parse_task(ctx: _Ctx, t: dict, scene: Scene, path: Path) -> Task:
    _check_keys(ctx, t, _TASK_KEYS)
    task_id = _string(ctx, t, "id")
    ctx = _Ctx(ctx.path, task_id)
    kind = _string(ctx, t, "kind")
    if kind not in KINDS:
        raise ctx.err("kind", f"unknown kind {kind!r} (known: {', '.join(KINDS)})")
    instruction = " ".join(_string(ctx, t, "instruction").split())
    subtasks = _strings(ctx, t, "subtasks", min_len=2 if kind == "long_range" else 1)
    targets = _strings(ctx, t, "targets", min_len=1)
    for i, name in enumerate(targets):
        _target_object(ctx, scene, f"targets[{i}]", name)
    via = _strings(ctx, t, "via", [])
    for i, name in enumerate(via):
        _target_object(ctx, scene, f"via[{i}]", name)
    track = None
    if kind == "track":
        track = _parse_track(ctx.sub("track"), _get(ctx, t, "track"), scene, targets)
    elif "track" in t:
        raise ctx.err("track", f"only tasks of kind 'track' have a track table (this one is {kind!r})")
    if track is not None and "goal" in t:
        raise ctx.err("goal", "a tracking task has no goal table: its goal is derived from the followed actor")
    if track is not None:
        lo, hi = actor_bounds_at(scene, track.actor, track.duration_s)
        goal = GoalSpec((lo + hi) / 2, (hi - lo) / 2 + 0.5, None, 0.0)
    else:
        goal = _parse_goal(ctx.sub("goal"), _get(ctx, t, "goal"), scene)
    if goal.object is not None and goal.object not in targets:
        raise ctx.err("goal.object", f"goal object {goal.object!r} must be one of the targets {list(targets)}")
    if "start" in t:
        st = _get(ctx, t, "start")
        sctx = ctx.sub("start")
        if not isinstance(st, dict):
            raise ctx.err("start", f"expected a table, got {st!r}")
        _check_keys(sctx, st, ("position_m", "yaw_deg"))
        p = _vector(sctx, st, "position_m")
        if not scene.bounds.contains(p)[0]:
            raise sctx.err("position_m", f"start {p.tolist()} lies outside the bounds of scene {scene.name!r}")
        start = StartPose(p, math.radians(_number(sctx, st, "yaw_deg", 0.0)))
    else:
        start = StartPose(scene.start.position_m.copy(), float(scene.start.yaw_rad))
    ref = None
    if "reference" in t:
        ref = _parse_reference(ctx.sub("reference"), t["reference"])
    return Task(task_id, scene.name, kind, instruction, subtasks, targets, goal, start, via, ref, path, track=track)


@functools.lru_cache(maxsize=32)
def _scene(name: str) -> Scene:
    return load_scene(resolve_scene(name))


def tasks_dir() -> Path:
    """Folder of the committed task files (``onfly/data/tasks``)."""
    return Path(__file__).resolve().parent.parent / "data" / "tasks"


def load_task_file(path: str | Path) -> list[Task]:
    """Read and validate one task file.

    Raises
    ------
    FileNotFoundError if the file is missing; TaskFormatError naming file, task and field.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"task file not found: {path}")
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise TaskFormatError(path, None, None, f"not valid TOML: {exc}") from None
    ctx = _Ctx(path)
    _check_keys(ctx, data, ("format", "scene", "tasks"))
    fmt = _get(ctx, data, "format")
    if fmt != TASK_FORMAT:
        raise ctx.err("format", f"unsupported format {fmt!r} (this reader knows {TASK_FORMAT!r})")
    scene_name = _string(ctx, data, "scene")
    scene_file = None
    if scene_name.endswith(".toml") or "/" in scene_name:  # a scene file: relative to this task file
        scene_file = Path(scene_name).expanduser()
        if not scene_file.is_absolute():
            scene_file = (path.resolve().parent / scene_file).resolve()
    try:
        scene = _scene(str(scene_file) if scene_file is not None else scene_name)
    except FileNotFoundError as exc:
        raise ctx.err("scene", str(exc)) from None
    raw = _get(ctx, data, "tasks")
    if not isinstance(raw, list) or not raw:
        raise ctx.err("tasks", "expected a non-empty list of task tables ([[tasks]])")
    out: list[Task] = []
    seen: dict[str, int] = {}
    for i, t in enumerate(raw):
        tctx = _Ctx(path, t.get("id") if isinstance(t, dict) and isinstance(t.get("id"), str) else f"tasks[{i}]")
        if not isinstance(t, dict):
            raise tctx.err(None, f"expected a table, got {type(t).__name__}")
        task = _parse_task(tctx, t, scene, path)
        if scene_file is not None:
            task = replace(task, scene_file=scene_file)
        if task.task_id in seen:
            raise TaskFormatError(path, task.task_id, "id", f"duplicate id (also tasks[{seen[task.task_id]}])")
        seen[task.task_id] = i
        out.append(task)
    return out


def committed_task_files(groups: bool = True) -> list[Path]:
    """The committed task files: the paper's set (``tasks/*.toml``), and with ``groups`` the
    groups kept beside it in subfolders (``tasks/hard/*.toml``), which the default set of the
    benchmark configs does not read."""
    files = sorted(tasks_dir().glob("*.toml"))
    return files + sorted(tasks_dir().glob("*/*.toml")) if groups else files


def load_tasks(paths: Iterable[str | Path] | None = None) -> list[Task]:
    """All tasks of the given files (default: every committed file), in file then file order.

    Raises TaskFormatError on a duplicate id across files.
    """
    files = sorted(tasks_dir().glob("*.toml")) if paths is None else [Path(p) for p in paths]
    out: list[Task] = []
    where: dict[str, Path] = {}
    for f in files:
        for task in load_task_file(f):
            if task.task_id in where:
                raise TaskFormatError(f, task.task_id, "id", f"duplicate id (also in {where[task.task_id]})")
            where[task.task_id] = f
            out.append(task)
    return out


def select_tasks(
    tasks: Sequence[Task],
    *,
    ids: Sequence[str] | None = None,
    scenes: Sequence[str] | None = None,
    kinds: Sequence[str] | None = None,
    count: int | None = None,
) -> list[Task]:
    """Tasks matching every given filter, in their original order.

    ``ids`` must all exist (a ValueError lists the unknown ones); ``count`` then keeps that
    many tasks, each kind in proportion and spread evenly over the scenes (deterministic).
    """
    out = list(tasks)
    if ids is not None:
        known = {t.task_id for t in out}
        missing = [i for i in ids if i not in known]
        if missing:
            raise ValueError(f"unknown task id(s) {missing}")
        wanted = set(ids)
        out = [t for t in out if t.task_id in wanted]
    if scenes is not None:
        known_scenes = {t.scene for t in tasks}
        bad = [s for s in scenes if s not in known_scenes]
        if bad:
            raise ValueError(f"no tasks for scene(s) {bad}; scenes with tasks: {sorted(known_scenes)}")
        out = [t for t in out if t.scene in set(scenes)]
    if kinds is not None:
        bad = [k for k in kinds if k not in KINDS]
        if bad:
            raise ValueError(f"unknown task kind(s) {bad}; valid: {list(KINDS)}")
        out = [t for t in out if t.kind in set(kinds)]
    if count is not None:
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            raise ValueError(f"count must be a positive integer, got {count!r}")
        if count < len(out):
            out = _spread(out, count)
    return out


def _spread(tasks: list[Task], count: int) -> list[Task]:
    """``count`` tasks, each kind in proportion (largest remainder), each kind's share spread
    evenly over its tasks (so over the scenes); original order kept."""
    n = len(tasks)
    groups = [[i for i, t in enumerate(tasks) if t.kind == k] for k in KINDS]
    exact = [count * len(g) / n for g in groups]
    quota = [int(math.floor(e)) for e in exact]
    for j in sorted(range(len(groups)), key=lambda j: (quota[j] - exact[j], j))[: count - sum(quota)]:
        quota[j] += 1
    # Each kind's share is evenly strided over its tasks; the stride's phase is chosen, kind by
    # kind, to land on the scenes used least so far (ties: the smallest phase), so a small
    # count spreads over scenes instead of taking the first task of every kind from one scene.
    used: dict[str, int] = {}
    keep: list[int] = []
    for g, q in zip(groups, quota):
        if q == 0:
            continue
        best = None
        for phase in range(max(1, len(g) // q)):
            picks = [g[min(len(g) - 1, (i * len(g)) // q + phase)] for i in range(q)]
            cost = sum(used.get(tasks[i].scene, 0) for i in picks)
            if best is None or cost < best[0]:
                best = (cost, picks)
        for i in best[1]:
            used[tasks[i].scene] = used.get(tasks[i].scene, 0) + 1
        keep.extend(best[1])
    return [tasks[i] for i in sorted(keep)]


# -- writing -------------------------------------------------------------------------------


def _toml_str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _toml_num(x: float) -> str:
    v = round(float(x), 3)
    return repr(0.0 if v == 0 else v)


def _toml_vec(v) -> str:
    return "[" + ", ".join(_toml_num(x) for x in np.asarray(v, float).reshape(-1)) + "]"


def write_task_file(path: str | Path, scene: str, tasks: Sequence[Task], header: str = "", scene_ref: str | None = None) -> None:
    """Write tasks (with their references, if any) in the format :func:`load_task_file` reads.

    Numbers are rounded to millimetres; ``header`` lines are written as comments on top.
    ``scene_ref`` is written as the file's ``scene`` instead of the name (an external scene's
    path as the file had it).
    """
    lines = [f"# {h}" if h else "#" for h in header.splitlines()]
    lines += [f'format = "{TASK_FORMAT}"', f"scene = {_toml_str(scene_ref or scene)}", ""]
    for t in tasks:
        if t.scene != scene:
            raise ValueError(f"task {t.task_id!r} belongs to scene {t.scene!r}, not {scene!r}")
        lines.append("[[tasks]]")
        lines.append(f"id = {_toml_str(t.task_id)}")
        lines.append(f"kind = {_toml_str(t.kind)}")
        lines.append(f"instruction = {_toml_str(t.instruction)}")
        lines.append("subtasks = [" + ", ".join(_toml_str(s) for s in t.subtasks) + "]")
        lines.append("targets = [" + ", ".join(_toml_str(s) for s in t.targets) + "]")
        if t.via:
            lines.append("via = [" + ", ".join(_toml_str(s) for s in t.via) + "]")
        yaw_deg = round(math.degrees(t.start.yaw_rad), 3)
        lines.append(f"start = {{ position_m = {_toml_vec(t.start.position_m)}, yaw_deg = {_toml_num(yaw_deg)} }}")
        g = t.goal
        if t.track is not None:
            tr = t.track
            items = [f"actor = {_toml_str(tr.actor)}", f"band_m = {_toml_vec(tr.band_m)}", f"in_band_frac = {_toml_num(tr.in_band_frac)}",
                     f"duration_s = {_toml_num(tr.duration_s)}", f"lost_after_s = {_toml_num(tr.lost_after_s)}"]
            if tr.stop_radius_m is not None:
                items.append(f"stop_radius_m = {_toml_num(tr.stop_radius_m)}")
            lines.append("track = { " + ", ".join(items) + " }")
        elif g.object is not None:
            lines.append(f"goal = {{ object = {_toml_str(g.object)}, margin_m = {_toml_num(g.margin_m)} }}")
        else:
            lines.append(f"goal = {{ center_m = {_toml_vec(g.center_m)}, half_extents_m = {_toml_vec(g.half_extents_m)} }}")
        r = t.reference
        if r is not None:
            lines.append("")
            lines.append("[tasks.reference]")
            lines.append(f"path_length_m = {_toml_num(r.path_length_m)}")
            lines.append(f"goal_point_m = {_toml_vec(r.goal_point_m)}")
            lines.append(f"visible_from_m = {_toml_vec(r.visible_from_m)}")
            lines.append(f"min_clearance_m = {_toml_num(r.min_clearance_m)}")
            lines.append("waypoints_m = [" + ", ".join(_toml_vec(p) for p in r.waypoints_m) + "]")
        lines.append("")
    Path(path).write_text("\n".join(lines))
