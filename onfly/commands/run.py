"""``onfly run``: fly one episode in the embedded world and record it."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

NAME = "run"
HELP = "fly one task in the embedded world (metrics, JSON summary, rerun recording, log)"
DESCRIPTION = """Fly one episode of a benchmark task (or your own instruction) with the OnFly pilot
in the embedded world, print its metrics, and write a rerun recording with the camera, the map,
the plans, raw and verified goals, and the agents' text on the timeline.

examples:
  onfly run --task urban_block-o01
  onfly run --scene urban_block --task o01 --vlm sim:noisy --seed 2 --json out.json
  onfly run --task villa-p03 --method oracle --rrd runs/oracle.rrd
  onfly run --scene villa --instruction "fly to the pool edge next to the ladder" --goal-object "pool edge"
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("--scene", help="scene name (or a scene file path with --instruction)")
    p.add_argument("--task", help="task id (with or without the 'scene/' prefix); see `onfly tasks list`")
    p.add_argument("--instruction", help="your own instruction instead of a task's")
    p.add_argument("--goal-object", help="with --instruction: the scene object whose box is the goal (for metrics)")
    p.add_argument(
        "--method",
        default="onfly",
        help="a registered method (default: onfly; ablations such as onfly_no_planner; 'oracle' checks world and planner)",
    )
    p.add_argument("--vlm", default="sim:nominal", help="sim:<preset> | http:<url>[#model] | transformers:<dir> (default: sim:nominal)")
    p.add_argument("--seed", type=int, default=0, help="episode seed (default 0)")
    p.add_argument("--time-limit-s", type=float, default=70.0, help="episode limit (paper: 70 s)")
    p.add_argument("--width", type=int, default=320, help="camera width in pixels, 90 x 60 deg FOV (default 320, as the benchmark)")
    p.add_argument("--height", type=int, default=214, help="camera height in pixels (default 214)")
    p.add_argument("--frame-period-s", type=float, default=0.5, help="seconds between camera frames (default 0.5, as the benchmark)")
    p.add_argument("--config", type=Path, help="TOML with a [pilot] table of PilotConfig overrides")
    p.add_argument("--json", type=Path, help="write the episode summary as JSON here")
    p.add_argument("--rrd", type=Path, help="rerun recording path (default runs/<task>-s<seed>.rrd)")
    p.add_argument("--no-rrd", action="store_true", help="do not write a rerun recording")
    p.add_argument("--log", type=Path, help="also write the flight as an OnFly log (frames + agent events) to this folder")


def _resolve_task(args):
    from onfly.bench.tasks import load_tasks

    tasks = load_tasks()
    wanted = {args.task}
    if args.scene:
        wanted.add(f"{args.scene}-{args.task}")
    matches = [t for t in tasks if t.task_id in wanted and (not args.scene or t.scene == args.scene)]
    if not matches:
        near = sorted(t.task_id for t in tasks if (not args.scene or t.scene == args.scene))[:12]
        raise ValueError(f"no task {args.task!r}; some valid ids: {', '.join(near)} (all: `onfly tasks list`)")
    return matches[0]


def run(args: argparse.Namespace) -> int:
    from onfly.bench.episode import EpisodeConfig, run_episode
    from onfly.bench.metrics import GoalRegion
    from onfly.bench.onfly_method import ABLATIONS, OnFlyMethod, ablation_config
    from onfly.bench.registry import make_method, method_names
    from onfly.bench.tasks import object_bounds
    from onfly.pilot import PilotConfig
    from onfly.viz import RerunRecorder
    from onfly.world.world import World
    from planning.camera import PinholeCamera
    from planning.trajectory import VehicleState

    if args.method not in method_names():
        raise ValueError(f"--method must be one of {method_names()}, got {args.method!r}")
    camera = PinholeCamera.from_fov(args.width, args.height, 90.0, 60.0)
    if args.task:
        task = _resolve_task(args)
        world = World.from_scene(
            task.scene, camera=camera, initial_state=VehicleState(0.0, task.start.position_m, [0, 0, 0], task.start.yaw_rad)
        )
        instruction, goal, ref_m, label = task.instruction, task.goal_region, (task.reference.path_length_m if task.reference else 0.0), task.task_id
        privileged = task.privileged_goal()
    elif args.instruction:
        if not args.scene or not args.goal_object:
            raise ValueError("--instruction needs --scene and --goal-object (the object whose box scores the episode)")
        world = World.from_scene(args.scene, camera=camera)
        lo, hi = object_bounds(world.scene, args.goal_object)
        goal = GoalRegion((lo + hi) / 2, (hi - lo) / 2)
        instruction, label = args.instruction, f"{world.scene.name}-custom"
        ref_m = float(goal.distance(world.state.p))
        privileged = None
    else:
        raise ValueError("give --task ID, or --scene S --instruction TEXT --goal-object NAME")

    if args.method in ABLATIONS:
        base = PilotConfig.from_toml(args.config) if args.config else PilotConfig()
        method = OnFlyMethod(args.vlm, ablation_config(args.method, base), name=args.method)
    else:
        if args.config:
            raise ValueError("--config holds PilotConfig overrides; it applies to the OnFly variants only")
        method = make_method(args.method, args.vlm, args.seed)
        if getattr(method, "privileged", False) and privileged is None:
            raise ValueError(f"method {args.method!r} needs a task's ground truth: use --task")
    rrd_path = None if args.no_rrd else (args.rrd or Path("runs") / f"{label.replace('/', '-')}-s{args.seed}.rrd")
    recorder = RerunRecorder(rrd_path) if rrd_path else None
    writer = None
    if args.log:
        from onfly.logs.writer import LogWriter

        writer = LogWriter(args.log, meta={"instruction": instruction, "task": label, "vlm": args.vlm, "seed": args.seed})
    n_events = 0

    def observe(step):
        nonlocal n_events
        pilot = getattr(step.method, "pilot", None)
        esdf = pilot.esdf if pilot is not None else getattr(step.method, "esdf", None)
        events = pilot.events if pilot is not None else []
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
            if privileged is not None and step.t_s == 0.0:
                recorder.log_goal(0.0, "task_region", goal.center, color=(255, 0, 255))
            recorder.log_pilot_events(events)
        if writer:
            for ev in events[n_events:]:
                writer.event(ev.kind, ev.data, t_s=ev.t_s)
            n_events = len(events)

    try:
        result = run_episode(
            world,
            method,
            instruction=instruction,
            goal=goal,
            reference_path_m=ref_m,
            seed=args.seed,
            error_model=args.vlm,
            config=EpisodeConfig(time_limit_s=args.time_limit_s, frame_period_s=args.frame_period_s),
            observer=observe,
            privileged=privileged,
        )
    finally:
        if recorder:
            recorder.close()
        if writer:
            writer.close()
    m = result.metrics
    print(f"task       {label}")
    print(f"instruction {instruction}")
    print(f"vlm        {args.vlm}   method {args.method}   seed {args.seed}")
    print(f"end        {result.end_reason}" + (f" ({result.error})" if result.error else ""))
    print(f"success    {m.success}   oracle success {m.oracle_success}   collided {m.collided}")
    print(f"flight     {m.flight_time_s:.1f} s   NE {m.navigation_error_m:.2f} m   path {m.path_length_m:.1f} m   SPL {m.spl:.2f}")
    print(f"vlm calls  {result.vlm_calls}   wall {result.wall_s:.1f} s   realtime x{result.realtime_factor:.1f}")
    if rrd_path:
        print(f"recording  {rrd_path}   (open with: rerun {rrd_path})")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        summary = {"task": label, "instruction": instruction, "vlm": args.vlm, "error_model": args.vlm, "method": args.method, "seed": args.seed, **result.to_dict()}
        args.json.write_text(json.dumps(summary, indent=2, default=str))
    return 0 if result.end_reason != "method_error" else 1


if __name__ == "__main__":  # pragma: no cover
    from onfly.cli import main

    sys.exit(main(["run", *sys.argv[1:]]))
