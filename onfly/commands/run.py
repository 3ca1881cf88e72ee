"""``onfly run``: fly one episode in the embedded world and record it."""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path

from onfly import defaults
from onfly.cli import CliError, echo
from onfly.console import live_line, status

NAME = "run"
HELP = "fly one task in the embedded world (live status, metrics, JSON summary, rerun recording, log)"
DESCRIPTION = f"""Fly one episode of a benchmark task (or your own instruction) in the embedded world,
exactly as the benchmark flies it (same defaults: {defaults.WIDTH_PX} x {defaults.HEIGHT_PX} px,
a frame every {defaults.FRAME_PERIOD_S} s, {defaults.TIME_LIMIT_S:g} s limit), show a live line while it
flies, print its metrics and, on failure, why in one line; write a rerun recording with the
scene mesh, the camera, the map, the plans, raw and verified goals, the agents' text and metric
plots on the timeline.

Everything is checked before the episode starts: task, scene, method, VLM spec (an http:
server is reached once), config file and recording path; a mistake exits with status 2 and one
line naming it.

Recordings are named runs/<task>-<method>-<backend>-s<seed>.rrd; an existing recording is
never overwritten: the default name gets a -2, -3 ... suffix, an explicit --rrd needs
--overwrite.

--config TOML tables (unknown tables and keys are errors naming the file and key):
  [pilot]                 PilotConfig fields of the OnFly variants (nested [pilot.planner] ...)
  [planner] [esdf] [verifier]  shortcuts for [pilot.planner] ... (every method that takes them)
  [episode]               EpisodeConfig fields (time_limit_s, frame_period_s, ...)
  [world]                 width_px, height_px, hfov_deg, vfov_deg, render_threads
A benchmark config (experiments/configs/*.toml) is read too: its [bench] and [methods] tables
are accepted ([methods.<this method>] applies).

examples:
  onfly run --task urban_block-o01
  onfly run --scene urban_block --task o01 --vlm sim:noisy --seed 2 --json out.json
  onfly run --task villa-p03 --method oracle --rrd runs/oracle.rrd
  onfly run --files my_tasks.toml --task my-o01          (a task file naming its own scene file)
  onfly run --scene villa --instruction "fly to the pool edge next to the ladder" --goal-object "pool edge"
"""

RUN_TABLES = ("pilot", "planner", "esdf", "verifier", "episode", "world", "bench", "methods")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--scene", help="scene name or scene file (with --instruction), or a filter for --task")
    p.add_argument("--task", help="task id (with or without the '<scene>-' prefix); see `onfly tasks list`")
    p.add_argument("--files", nargs="+", default=None, help="task files to find --task in (default: the committed ones)")
    p.add_argument("--instruction", help="your own instruction instead of a task's")
    p.add_argument("--goal-object", help="with --instruction: the scene object whose box is the goal (for metrics)")
    p.add_argument(
        "--method",
        default=defaults.METHOD,
        help="a registered method (default: onfly; ablations such as onfly_no_planner; 'oracle' checks world and planner)",
    )
    p.add_argument("--vlm", default=defaults.VLM, help=f"sim:<preset> | http:<url>[#model] | transformers:<dir> (default: {defaults.VLM})")
    p.add_argument("--seed", type=int, default=defaults.SEED, help="episode seed (default 0)")
    p.add_argument("--time-limit-s", type=float, default=None, help=f"episode limit (default {defaults.TIME_LIMIT_S:g}, the paper's)")
    p.add_argument("--width", type=int, default=None, help=f"camera width in pixels, 90 x 60 deg FOV (default {defaults.WIDTH_PX}, as the benchmark)")
    p.add_argument("--height", type=int, default=None, help=f"camera height in pixels (default {defaults.HEIGHT_PX})")
    p.add_argument("--frame-period-s", type=float, default=None, help=f"seconds between camera frames (default {defaults.FRAME_PERIOD_S}, as the benchmark)")
    p.add_argument("--config", type=Path, help="TOML of pilot / planner / episode / world overrides (see above)")
    p.add_argument("--json", type=Path, help="write the episode summary as JSON here")
    p.add_argument("--rrd", type=Path, help="rerun recording path (default runs/<task>-<method>-<backend>-s<seed>.rrd)")
    p.add_argument("--overwrite", action="store_true", help="let an explicit --rrd / --json replace an existing file")
    p.add_argument("--no-rrd", action="store_true", help="do not write a rerun recording")
    p.add_argument("--log", type=Path, help="also write the flight as an OnFly log (frames + agent events) to this folder")
    p.add_argument("--quiet", action="store_true", help="no live status line")


def _resolve_task(args):
    from onfly.bench.tasks import committed_task_files, load_tasks

    try:
        tasks = load_tasks(committed_task_files() if args.files is None else args.files)
    except FileNotFoundError as exc:
        raise CliError(f"--files: {exc}") from None
    wanted = {args.task}
    if args.scene:
        wanted.add(f"{args.scene}-{args.task}")
    matches = [t for t in tasks if t.task_id in wanted and (not args.scene or t.scene == args.scene)]
    if not matches:
        near = sorted(t.task_id for t in tasks if (not args.scene or t.scene == args.scene))[:12]
        raise CliError(f"--task: no task {args.task!r}; some valid ids: {', '.join(near)} (all: `onfly tasks list`)")
    return matches[0]


def backend_slug(vlm: str) -> str:
    """A file-name-safe form of a VLM spec: ``sim:nominal`` -> ``sim-nominal``."""
    s = re.sub(r"^https?://", "", vlm.split("#")[-1] if vlm.startswith(("http", "https")) and "#" in vlm else vlm)
    s = re.sub(r"[^A-Za-z0-9_.+]+", "-", s).strip("-.")
    return s[:48] or "vlm"


def recording_path(label: str, method: str, vlm: str, seed: int, folder: Path = Path("runs")) -> Path:
    """``runs/<task>-<method>-<backend>-s<seed>.rrd``; when it exists, the first free ``-2``,
    ``-3`` ... variant (an existing recording is never overwritten)."""
    stem = f"{re.sub(r'[^A-Za-z0-9_.+-]+', '-', label)}-{method}-{backend_slug(vlm)}-s{seed}"
    path = folder / f"{stem}.rrd"
    n = 2
    while path.exists():
        path = folder / f"{stem}-{n}.rrd"
        n += 1
    return path


def read_run_config(path: Path, method: str) -> tuple[dict, dict, dict]:
    """(method options, episode fields, world fields) of a ``--config`` file; unknown tables and
    keys are errors naming the file and key."""
    from onfly.serialize import ConfigFileError, read_toml

    data = read_toml(path, allowed=RUN_TABLES, what="run config")
    options: dict = {}
    pilot = dict(data.get("pilot", {}))
    for table in ("planner", "esdf", "verifier"):
        if table in data:
            if table in pilot:
                raise ConfigFileError(f"{path}: [{table}] and [pilot.{table}] both given; use one")
            pilot[table] = dict(data[table])
    methods = data.get("methods", {})
    if not isinstance(methods, dict) or not all(isinstance(v, dict) for v in methods.values()):
        raise ConfigFileError(f"{path}: [methods.<name>] must be tables of options")
    options.update(pilot)
    options.update(methods.get(method, {}))
    if "pilot" in data and not method.startswith("onfly"):
        raise ConfigFileError(f"{path}: [pilot] holds PilotConfig fields; method {method!r} is not an OnFly variant")
    if "bench" in data:
        from onfly.bench.runner import BenchConfig

        BenchConfig.from_dict({k: v for k, v in data.items() if k != "pilot"}, source=str(path))  # validates its tables
    episode, world = dict(data.get("episode", {})), dict(data.get("world", {}))
    from onfly.bench.runner import _WORLD_KEYS  # the benchmark's [world] keys, one list for both

    bad = sorted(set(world) - set(_WORLD_KEYS))
    if bad:
        raise ConfigFileError(f"{path}: [world]: unknown key(s) {bad}; valid: {sorted(_WORLD_KEYS)}")
    return options, episode, world


def _custom_task(args, world_scene):
    """A Task for ``--instruction`` (goal: the named object's box; reference: straight line)."""
    import numpy as np

    from onfly.bench.tasks import GoalSpec, Reference, StartPose, Task, object_bounds

    try:
        lo, hi = object_bounds(world_scene, args.goal_object)
    except (KeyError, ValueError) as exc:
        names = ", ".join(repr(o.name) for o in world_scene.targets)
        raise CliError(f"--goal-object: scene {world_scene.name!r} has no object {args.goal_object!r} (targets: {names}) [{exc}]") from None
    goal = GoalSpec((lo + hi) / 2, (hi - lo) / 2, args.goal_object)
    start = StartPose(world_scene.start.position_m.copy(), float(world_scene.start.yaw_rad))
    straight = float(goal.region.distance(start.position_m[None, :])[0])
    ref = Reference(straight, np.stack([start.position_m, goal.center_m]), goal.center_m.copy(), start.position_m.copy(), float("nan"))
    return Task(f"{world_scene.name}-custom", world_scene.name, "object", args.instruction, (args.instruction,),
                (args.goal_object,), goal, start, (), ref, None, None)


def failure_line(result, extras: dict, goal_radius_m: float, last_mode: str | None) -> str:
    """Why an episode failed, in one line (empty on success)."""
    m = result.metrics
    if m.success:
        return ""
    ne = m.navigation_error_m
    if result.end_reason == "collision" and result.collision:
        c = result.collision
        return f"collision with {c['object']!r} at t={c['t_s']:.1f} s, {ne:.1f} m from the goal"
    if result.end_reason == "method_error":
        return f"the method raised: {result.error}"
    if result.end_reason == "out_of_bounds":
        return f"left the scene bounds at t={m.flight_time_s:.1f} s, {ne:.1f} m from the goal"
    mode = f"; pilot mode {last_mode}" if last_mode else ""
    if result.end_reason == "stopped":
        return f"stopped {ne:.1f} m from the goal region (success needs <= {goal_radius_m:g} m){mode}"
    return f"time limit reached at {m.flight_time_s:.1f} s, {ne:.1f} m from the goal region{mode}"


def _check_output(path: Path | None, option: str, overwrite: bool) -> None:
    if path is None:
        return
    if path.exists() and not overwrite:
        raise CliError(f"{option} {path} exists; pass --overwrite to replace it or choose another path")
    if path.exists() and path.is_dir():
        raise CliError(f"{option} {path} is a directory")


def run(args: argparse.Namespace) -> int:
    # -- everything checked before the episode starts (plain values first: no import) ----------
    for option, value in (("--width", args.width), ("--height", args.height)):
        if value is not None and value <= 0:
            raise CliError(f"{option} must be a positive number of pixels, got {value}")
    for option, value in (("--time-limit-s", args.time_limit_s), ("--frame-period-s", args.frame_period_s)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise CliError(f"{option} must be a positive number of seconds, got {value}")
    if args.task and args.instruction:
        raise CliError("give --task or --instruction, not both")
    if not args.task and not args.instruction:
        raise CliError("give --task ID, or --scene S --instruction TEXT --goal-object NAME")
    from onfly.bench.registry import method_names

    if args.method not in method_names():
        raise CliError(f"--method must be one of {', '.join(method_names())}; got {args.method!r}")
    options, episode, world = ({}, {}, {})
    if args.config is not None:
        options, episode, world = read_run_config(args.config, args.method)
    if args.time_limit_s is not None:
        episode["time_limit_s"] = args.time_limit_s
    if args.frame_period_s is not None:
        episode["frame_period_s"] = args.frame_period_s
    if args.width is not None:
        world["width_px"] = args.width
    if args.height is not None:
        world["height_px"] = args.height
    from onfly.bench.episode import EpisodeConfig

    try:
        EpisodeConfig(**episode)
    except (TypeError, ValueError) as exc:
        raise CliError(f"episode settings: {exc}") from None
    from onfly.bench.registry import get_factory
    from onfly.bench.runner import check_vlm_spec

    try:
        check_vlm_spec(args.vlm)
    except ValueError as exc:
        raise CliError(f"--vlm: {exc}") from None
    try:
        get_factory(args.method)(args.vlm, args.seed, **{k: (dict(v) if isinstance(v, dict) else v) for k, v in options.items()})
    except (TypeError, ValueError) as exc:
        where = f"{args.config}: " if args.config else ""
        raise CliError(f"{where}options of method {args.method!r}: {exc}") from None
    if args.task:
        task = _resolve_task(args)
    elif args.instruction:
        if not args.scene or not args.goal_object:
            raise CliError("--instruction needs --scene and --goal-object (the object whose box scores the episode)")
        from onfly.world.scene import SceneFormatError, load_scene, resolve_scene

        try:
            scene = load_scene(resolve_scene(args.scene))
        except (FileNotFoundError, SceneFormatError) as exc:
            raise CliError(f"--scene: {exc}") from None
        task = _custom_task(args, scene)
    else:
        raise CliError("give --task ID, or --scene S --instruction TEXT --goal-object NAME")
    if task.reference is None:
        raise CliError(f"task {task.task_id!r} has no reference path: run `onfly tasks check --write --files {task.source}`")
    if args.task is None:
        method = get_factory(args.method)(args.vlm, args.seed, **options)
        if getattr(method, "privileged", False):
            raise CliError(f"method {args.method!r} needs a task's ground truth: use --task")
    label = task.task_id
    if args.no_rrd:
        rrd_path = None
    elif args.rrd is not None:
        _check_output(args.rrd, "--rrd", args.overwrite)
        rrd_path = args.rrd
    else:
        rrd_path = recording_path(label, args.method, args.vlm, args.seed)
    _check_output(args.json, "--json", args.overwrite)
    if args.log is not None and args.log.exists() and any(args.log.iterdir()):
        raise CliError(f"--log {args.log} exists and is not empty; choose a new folder")

    return _fly(args, task, options, episode, world, rrd_path)


def _fly(args, task, options, episode, world, rrd_path) -> int:
    import numpy as np

    from onfly.bench.runner import fly_task
    from onfly.viz import RerunRecorder

    recorder = RerunRecorder(rrd_path) if rrd_path else None
    writer = None
    if args.log:
        from onfly.logs.writer import LogWriter

        writer = LogWriter(args.log, meta={"instruction": task.instruction, "task": task.task_id, "vlm": args.vlm, "seed": args.seed})
    goal = task.goal_region
    n_events = 0
    state = {"world": None, "mode": None, "last_print": -1e9, "subtask": ""}
    live = not args.quiet
    tty = sys.stderr.isatty()

    def on_world(world) -> None:
        state["world"] = world
        if recorder:
            log_scene_mesh(recorder, world.geometry)
            recorder.log_goal(0.0, "task_region", goal.center, color=(255, 0, 255))

    def observe(step):
        nonlocal n_events
        pilot = getattr(step.method, "pilot", None)
        esdf = pilot.esdf if pilot is not None else getattr(step.method, "esdf", None)
        events = pilot.events if pilot is not None else []
        dist = float(goal.distance(step.state.p[None, :])[0])
        mode = getattr(getattr(pilot, "mode", None), "value", None) if pilot is not None else "flying"
        state["mode"] = mode
        tasks = getattr(pilot, "tasks", None) if pilot is not None else None
        if tasks is not None and tasks.subtasks:
            i = min(tasks.index, len(tasks.subtasks) - 1)
            state["subtask"] = f"{tasks.index + 1}/{len(tasks.subtasks)} {tasks.subtasks[i]!r}"
        if step.obs is not None:
            if recorder:
                recorder.log_frame(step.obs)
                if esdf is not None:
                    recorder.log_map(step.t_s, esdf.occupied_points())
            if writer:
                writer.write(step.obs)
        if recorder:
            recorder.log_state(step.state)
            if step.output.trajectory is not None:
                recorder.log_plan(step.t_s, step.output.trajectory)
            recorder.log_pilot_events(events)
            recorder.log_scalars(step.t_s, {
                "distance_to_goal_m": dist,
                "speed_mps": float(np.linalg.norm(step.state.v)),
                "altitude_m": float(step.state.p[2]),
            })
        if writer:
            for ev in events[n_events:]:
                writer.event(ev.kind, ev.data, t_s=ev.t_s)
            n_events = len(events)
        if live and (tty or step.t_s - state["last_print"] >= 5.0):
            state["last_print"] = step.t_s
            live_line(f"t {step.t_s:5.1f} s  goal {dist:5.1f} m  {mode or '':<10}  {state['subtask']}", width=110)

    t0 = time.perf_counter()
    try:
        result, extras = fly_task(
            task, args.method, vlm=args.vlm, seed=args.seed, options=options, episode=episode, world=world,
            observer=observe, on_world=on_world,
        )
    finally:
        if live and tty:
            status()  # end the line redrawn in place
        if recorder:
            recorder.close()
        if writer:
            writer.close()
    from onfly.bench.episode import EpisodeConfig

    radius = EpisodeConfig(**episode).success_radius_m
    m = result.metrics
    mo = extras["motion"]

    def f(x, fmt):
        return "n/a" if x is None else format(x, fmt)

    echo(f"task       {task.task_id}")
    echo(f"instruction {task.instruction}")
    echo(f"vlm        {args.vlm}   method {args.method}   seed {args.seed}")
    echo(f"end        {result.end_reason}")
    echo(f"success    {m.success}   oracle success {m.oracle_success}   collided {m.collided}")
    why = failure_line(result, extras, radius, state["mode"])
    if why:
        echo(f"failed     {why}")
    echo(f"flight     {m.flight_time_s:.1f} s   NE {m.navigation_error_m:.2f} m   path {m.path_length_m:.1f} m   SPL {m.spl:.2f}")
    echo(f"motion     rms accel {f(mo['rms_accel_mps2'], '.2f')} m/s^2   rms jerk {f(mo['rms_jerk_mps3'], '.2f')} m/s^3   "
         f"min clearance {extras['min_clearance_m']:.2f} m   time to goal {f(mo['time_to_goal_s'], '.1f')} s   "
         f"yaw error {f(mo['yaw_error_deg'], '.0f')} deg")
    echo(f"vlm calls  {result.vlm_calls}   wall {time.perf_counter() - t0:.1f} s   realtime x{result.realtime_factor:.1f}")
    if rrd_path:
        echo(f"recording  {rrd_path}   (open with: rerun {rrd_path})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        summary = {"task": task.task_id, "instruction": task.instruction, "vlm": args.vlm, "method": args.method,
                   "seed": args.seed, "failure_reason": why, **extras, **result.to_dict()}
        from onfly.serialize import to_jsonable

        args.json.write_text(json.dumps(to_jsonable(summary), indent=2, default=str))
    return 0 if result.end_reason != "method_error" else 1


def log_scene_mesh(recorder, geometry) -> None:
    """The scene's triangles (per-object colours) as a static ``world/scene`` mesh."""
    import numpy as np
    import rerun as rr

    tri = geometry.triangles.astype(np.int64)
    verts = geometry.vertices[tri.reshape(-1)]
    colors = np.repeat((geometry.tri_color * 255).astype(np.uint8), 3, axis=0)
    recorder.rec.log(
        "world/scene",
        rr.Mesh3D(vertex_positions=verts, triangle_indices=np.arange(len(verts)).reshape(-1, 3), vertex_colors=colors),
        static=True,
    )


if __name__ == "__main__":  # pragma: no cover
    from onfly.cli import main

    sys.exit(main(["run", *sys.argv[1:]]))
