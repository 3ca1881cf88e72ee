"""The scriptable API behind ``import onfly``: fly a task, run a benchmark, replay a recording.

Each function runs the same code as its CLI command with the same defaults
(:mod:`onfly.defaults`): :func:`fly` is ``onfly run`` (and one benchmark episode, through
:func:`onfly.bench.runner.fly_task`), :func:`benchmark` is ``onfly bench``, :func:`replay_recording` is
``onfly replay``. Examples: ``docs/api.md`` (run by ``tests/test_api.py``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, is_dataclass, replace
from pathlib import Path
from typing import Any, Sequence

from onfly import defaults

__all__ = ["Flight", "fly", "benchmark", "replay_recording", "tasks", "ApiError"]


class ApiError(ValueError):
    """A bad argument to the API (the message names it)."""


@dataclass(frozen=True, eq=False)
class Flight:
    """One flown episode.

    Attributes
    ----------
    task_id, method, vlm, seed : what flew
    metrics : :class:`onfly.bench.metrics.EpisodeMetrics` (success, oracle_success, collided,
        flight_time_s, navigation_error_m, path_length_m, spl)
    motion : :class:`onfly.bench.motion.MotionMetrics` as a dict (rms_accel_mps2,
        rms_jerk_mps3, path_length_m, time_to_goal_s, yaw_error_deg)
    min_clearance_m : smallest exact distance of the flown path to the scene, metres
    end_reason : ``stopped`` | ``collision`` | ``time_limit`` | ``out_of_bounds`` | ``method_error``
    failure : empty on success, else the benchmark's failure label
    result : the full :class:`onfly.bench.episode.EpisodeResult` (trace, VLM calls, ...)
    """

    task_id: str
    method: str
    vlm: str
    seed: int
    metrics: Any
    motion: dict
    min_clearance_m: float
    end_reason: str
    failure: str
    result: Any

    @property
    def success(self) -> bool:
        return bool(self.metrics.success)


def _table(value: Any, name: str) -> dict:
    """A config object or a dict of overrides -> a plain dict (a TOML-like table)."""
    if value is None:
        return {}
    if is_dataclass(value) and not isinstance(value, type):
        d = value.to_dict() if hasattr(value, "to_dict") else asdict(value)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}
    if isinstance(value, dict):
        return dict(value)
    raise ApiError(f"{name} must be a config object or a dict of its fields, got {type(value).__name__}")


def tasks(ids: Sequence[str] | None = None, *, scenes: Sequence[str] | None = None, kinds: Sequence[str] | None = None,
          count: int | None = None, files: Sequence[str | Path] | None = None) -> list:
    """Benchmark tasks (:class:`onfly.bench.tasks.Task`), selected as ``onfly tasks list`` does
    (``count``: an evenly spread subset over kinds and scenes)."""
    from onfly.bench.tasks import load_tasks, select_tasks

    return select_tasks(load_tasks(files), ids=ids, scenes=scenes, kinds=kinds, count=count)


def fly(
    task,
    *,
    method: str = defaults.METHOD,
    vlm: str = defaults.VLM,
    seed: int = defaults.SEED,
    pilot=None,
    planner=None,
    esdf=None,
    verifier=None,
    episode=None,
    world: dict | None = None,
    task_files: Sequence[str | Path] | None = None,
    log_dir: str | Path | None = None,
) -> Flight:
    """Fly one task exactly as one benchmark episode and return its metrics.

    Parameters
    ----------
    task : a task id (``"parking_lot-o01"``) or a :class:`onfly.bench.tasks.Task`
    method : a registered method (``onfly``, its ablations, ``oracle``, the baselines)
    vlm : VLM spec (``sim:<preset>``, ``http:<url>[#model]``, ``transformers:<dir>``)
    seed : episode seed
    pilot : PilotConfig (or a dict of its fields) for the OnFly variants
    planner, esdf, verifier : PlannerConfig / EsdfConfig / VerifierConfig or dicts of fields
        (every method that takes them; they override ``pilot``'s nested tables)
    episode : EpisodeConfig or a dict (defaults: :mod:`onfly.defaults`, as the CLI and benchmark)
    world : camera settings (``width_px``, ``height_px``, ``hfov_deg``, ``vfov_deg``, ``render_threads``)
    task_files : task files to find ``task`` in (default: the committed ones)
    log_dir : also write the flight as an OnFly log (frames + events) to this new folder
        (replay it with :func:`replay_recording`)
    """
    from onfly.bench.runner import fly_task

    if isinstance(task, str):
        found = [t for t in tasks(files=task_files) if t.task_id == task]
        if not found:
            raise ApiError(f"no task {task!r} (see onfly.tasks() or `onfly tasks list`)")
        task = found[0]
    options = _table(pilot, "pilot")
    for name, value in (("planner", planner), ("esdf", esdf), ("verifier", verifier)):
        if value is not None:
            options[name] = _table(value, name)
    ep = _table(episode, "episode")
    observer = None
    writer = None
    if log_dir is not None:
        from onfly.logs.writer import LogWriter

        writer = LogWriter(Path(log_dir), meta={"instruction": task.instruction, "task": task.task_id, "vlm": vlm, "seed": seed})
        n_events = [0]

        def observer(step) -> None:
            if step.obs is not None:
                writer.write(step.obs)
            events = getattr(getattr(step.method, "pilot", None), "events", [])
            for ev in events[n_events[0]:]:
                writer.event(ev.kind, ev.data, t_s=ev.t_s)
            n_events[0] = len(events)

    try:
        result, extras = fly_task(task, method, vlm=vlm, seed=seed, options=options, episode=ep, world=world, observer=observer)
    finally:
        if writer is not None:
            writer.close()
    return Flight(task.task_id, method, vlm, seed, result.metrics, extras["motion"], extras["min_clearance_m"],
                  result.end_reason, extras["failure"], result)


def benchmark(config, out: str | Path | None = None, *, workers: int | None = None, ray_address: str | None = None,
          progress: bool = False, allow_mixed_code: bool = False, **changes):
    """Run (or resume) a benchmark as ``onfly bench`` does and return its
    :class:`onfly.bench.runner.BenchResult` (``.summary``, ``.records``, ``.errored``).

    ``config`` is a :class:`onfly.BenchConfig` or the path of a benchmark TOML; ``changes``
    replace its fields (``methods=("oracle",)``, ``task_ids=(...)``, ``runs=1`` ...);
    ``out`` defaults to ``runs/bench/<name>``. Everything is checked before the first episode.
    A folder with episodes other code flew raises :class:`onfly.bench.runner.MixedCodeError`
    unless ``allow_mixed_code``.
    """
    from onfly.bench.runner import BenchConfig, run_bench

    cfg = BenchConfig.from_toml(config) if isinstance(config, (str, Path)) else config
    if not isinstance(cfg, BenchConfig):
        raise ApiError(f"config must be a BenchConfig or a TOML path, got {type(config).__name__}")
    if changes:
        cfg = replace(cfg, **changes)
    folder = Path(out) if out is not None else Path("runs") / "bench" / cfg.name
    return run_bench(cfg, folder, workers=workers, ray_address=ray_address, progress=progress, allow_mixed_code=allow_mixed_code)


def replay_recording(
    path: str | Path,
    *,
    config=None,
    goal: Sequence[float] | None = None,
    future_pose_s: float | None = None,
    instruction: str | None = None,
    vlm: str | None = None,
    max_frames: int | None = None,
    every_n: int | None = None,
    kind: str | None = None,
    rrd: str | Path | None = None,
    progress: bool = False,
    **source_options,
):
    """Replay a recording (OnFly log, TUM folder, ROS 1/2 bag) open loop as ``onfly replay``
    does and return its :class:`onfly.replay.ReplayReport`.

    ``goal`` (x, y, z in the log's world frame) gives the planner a fixed goal, else
    ``future_pose_s`` the logged pose that far ahead, else with ``instruction`` the agents'
    verified goals. ``source_options`` are the reader's fields (``depth_topic``,
    ``pose_topic``, ``tf_parent_frame``, ``tf_child_frame``, ``intrinsics`` ...).
    """
    from onfly.readers import open_source
    from onfly.replay import ReplayConfig
    from onfly.replay import replay as _replay

    cfg = config if config is not None else ReplayConfig()
    changes: dict[str, Any] = {}
    if goal is not None:
        changes.update(goal_mode="fixed", goal_world=tuple(float(v) for v in goal))
    elif future_pose_s is not None:
        changes.update(goal_mode="future_pose", future_pose_s=float(future_pose_s))
    elif instruction is not None:
        changes.update(goal_mode="agents")
    if instruction is not None:
        changes["instruction"] = instruction
    if vlm is not None:
        changes["vlm"] = vlm
    if max_frames is not None:
        changes["max_frames"] = max_frames
    if every_n is not None:
        changes["every_n"] = every_n
    cfg = replace(cfg, **changes)
    recorder = None
    try:
        with open_source(Path(path), kind=kind, **source_options) as source:
            if rrd is not None:
                from onfly.viz import RerunRecorder

                recorder = RerunRecorder(rrd, application_id="onfly_replay")
            return _replay(source, cfg, recorder=recorder, progress=progress)
    finally:
        if recorder is not None:
            recorder.close()
