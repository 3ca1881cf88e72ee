"""``onfly replay PATH``: a recording replayed open loop through ESDF, planner, agents and verifier."""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import replace
from pathlib import Path

from onfly.cli import CliError, echo

NAME = "replay"
HELP = "replay a recording (OnFly log, TUM RGB-D folder, ROS 1/2 bag) open loop and report latency, clearance and verifier changes"
DESCRIPTION = """Replay a recording open loop: every frame goes through the ESDF and the planner (state
from the logged pose, velocity by finite differences), and with --instruction through the
memory, the decision and monitoring agents and the verifier. Prints a table of per-stage
latency (median, p95), the ESDF clearance along the logged camera path (> 0: the camera was
never inside an obstacle of the map built from the log's own depth), the planner's predicted
clearance, how often it needed slack or a fallback, and what the verifier changed.

Planner goal: --goal x,y,z (fixed, log's world frame), else --future-pose-s S (the logged
pose S seconds ahead, default 3 s), else with --instruction the agents' verified goals.

VLM (--vlm, with --instruction): sim:<preset> needs the frame annotations only OnFly logs of
the embedded world carry (`onfly run --task ... --log DIR`); for TUM folders, bags and real
flight logs use http:URL[#model] or transformers:DIR, or `tiny` (a tiny random-weight Qwen
model built offline: garbage answers, exercises the pipeline).

examples:
  onfly replay ../shared/realdata/7scenes-kitchen-tum --json out.json --rrd out.rrd
  onfly replay runs/urban-log --instruction "fly to the red delivery van" --vlm sim:perfect
  onfly replay flight.bag --depth-topic /camera/depth/image_raw --pose-topic /odom --goal 2,0,1.5
  onfly replay flight.bag --pose-topic /tf --tf-parent odom --tf-child camera_link --goal -2,0,1.5

--config TOML: one [replay] table of ReplayConfig fields (nested [replay.planner] ...); any
other table or unknown key is an error naming the file and key.
"""


def _floats(text: str | None, n: int, option: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    parts = text.replace(",", " ").split()
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise CliError(f"{option} must be {n} comma-separated finite numbers, got {text!r}")
    return vals


def _positive(value, option: str, integer: bool = False):
    if value is None:
        return None
    try:
        v = int(value) if integer else float(value)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise CliError(f"{option} must be a positive {'integer' if integer else 'number'}, got {value!r}")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("path", type=Path, help="OnFly log directory, TUM RGB-D folder, ROS 1 .bag or ROS 2 bag directory")
    p.add_argument("--kind", choices=("onfly-log", "tum", "ros1-bag", "ros2-bag"), help="source kind (default: detected)")
    p.add_argument("--instruction", help="run memory, agents and verifier on this instruction")
    p.add_argument("--vlm", help="sim:<preset> | http:<url>[#model] | transformers:<dir> | tiny[:family] (default sim:nominal)")
    p.add_argument("--goal", metavar="X,Y,Z", help="fixed planner goal in the log's world frame, metres")
    p.add_argument("--future-pose-s", metavar="S", help="planner goal: the logged pose S seconds ahead (default 3)")
    p.add_argument("--every", default="1", metavar="N", help="process every N-th frame (default 1)")
    p.add_argument("--max-frames", metavar="N", help="stop after N processed frames")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated VLM (default 0)")
    p.add_argument("--config", type=Path, help="TOML with a [replay] table of ReplayConfig overrides (nested [replay.planner] ...)")
    p.add_argument("--json", type=Path, metavar="PATH", help="write the report (with per-frame results) as JSON")
    p.add_argument("--rrd", type=Path, metavar="PATH", help="write a rerun recording")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    src = p.add_argument_group("source options")
    src.add_argument("--intrinsics", metavar="FX,FY,CX,CY", help="camera intrinsics in pixels (TUM folders and bags)")
    src.add_argument("--depth-topic", help="bag: depth image topic")
    src.add_argument("--rgb-topic", help="bag: colour image topic")
    src.add_argument("--camera-info-topic", help="bag: CameraInfo topic")
    src.add_argument("--pose-topic", help="bag: Odometry / PoseStamped / TF topic")
    src.add_argument("--tf-parent", metavar="FRAME", help="bag: with a TF pose topic (/tf), the parent frame of the camera pose, e.g. odom")
    src.add_argument("--tf-child", metavar="FRAME", help="bag: with a TF pose topic (/tf), the child frame, e.g. camera_link")


#: Reader config fields -> the flags that set them (reader errors are reworded to name flags).
FIELD_FLAGS = {
    "tf_parent_frame": "--tf-parent",
    "tf_child_frame": "--tf-child",
    "depth_topic": "--depth-topic",
    "rgb_topic": "--rgb-topic",
    "camera_info_topic": "--camera-info-topic",
    "pose_topic": "--pose-topic",
    "intrinsics": "--intrinsics",
}


def flag_names(message: str) -> str:
    """A reader's message with its config field names replaced by the CLI flags."""
    for name, flag in FIELD_FLAGS.items():
        message = re.sub(rf"\b(BagConfig\.|TumConfig\.)?{name}\b", flag, message)
    return message


def _config(args: argparse.Namespace):
    from onfly.replay import ReplayConfig

    goal = _floats(args.goal, 3, "--goal")
    future_s = _positive(args.future_pose_s, "--future-pose-s")
    every = _positive(args.every, "--every", integer=True)
    max_frames = _positive(args.max_frames, "--max-frames", integer=True)
    if goal is not None and future_s is not None:
        raise CliError("give either --goal or --future-pose-s, not both")
    base = ReplayConfig()
    if args.config is not None:
        from onfly.serialize import read_toml

        data = read_toml(args.config, allowed=("replay",), what="replay config")
        try:
            base = ReplayConfig.from_dict(data.get("replay", {}))
        except ValueError as exc:
            raise CliError(f"{args.config}: [replay]: {exc}") from None
    if goal is not None:
        mode, goal_world = "fixed", goal
    elif future_s is not None:
        mode, goal_world = "future_pose", None
    elif args.instruction is not None and args.config is None:
        mode, goal_world = "agents", None
    else:
        mode, goal_world = base.goal_mode, base.goal_world
    changes = dict(goal_mode=mode, goal_world=goal_world, every_n=every, seed=args.seed)
    if future_s is not None:
        changes["future_pose_s"] = future_s
    if args.instruction is not None:
        changes["instruction"] = args.instruction
    if args.vlm is not None:
        changes["vlm"] = args.vlm
    if max_frames is not None:
        changes["max_frames"] = max_frames
    return replace(base, **changes)


def _ms(lat) -> str:
    return f"{lat.median_ms:9.1f} {lat.p95_ms:9.1f} {lat.n:6d}"


def _num(x, fmt: str = ".3f") -> str:
    return "-" if x is None else format(x, fmt)


def format_report(r) -> str:
    """The table ``onfly replay`` prints."""
    lines = [
        f"source        {r.source} ({r.kind})",
        f"frames        {r.frames} processed of {r.frames_read} read, {r.duration_s:.2f} s of log, wall {r.wall_s:.1f} s",
        f"goal          {r.goal_mode}" + (f"   instruction {r.instruction!r}   vlm {r.vlm} (latency {r.vlm_latency})" if r.instruction else ""),
        "",
        f"{'stage':<16}{'median ms':>9} {'p95 ms':>9} {'n':>6}",
    ]
    for name, lat in r.latency_ms.items():
        lines.append(f"{name:<16}{_ms(lat)}")
    fb = ", ".join(f"{k} {v}" for k, v in sorted(r.planner_fallbacks.items())) or "none"
    lines += [
        "",
        f"path clearance    min {r.path_clearance_min_m:.3f} m (frame {r.path_clearance_min_index})   median {r.path_clearance_median_m:.3f} m",
        f"planned clearance min {r.planner_clearance_min_m:.3f} m   median {r.planner_clearance_median_m:.3f} m",
        f"planner           slack needed {r.planner_slack_steps}/{r.frames}   fallbacks {fb}   logged speed max {r.logged_speed_max_mps:.2f} m/s",
    ]
    if r.verifier is not None:
        v = r.verifier
        rej = ", ".join(f"{k} {n}" for k, n in sorted(v.rejected.items())) or "none"
        fails = ", ".join(f"{k} {n}" for k, n in sorted(r.decision_failures.items())) or "none"
        mons = ", ".join(f"{k} {n}" for k, n in sorted(r.monitor_statuses.items())) or "none"
        lines += [
            f"subtasks          {list(r.subtasks)} ({r.decomposition_source})",
            f"decisions         {r.decisions}   goals {r.goals_accepted}   no goal: {fails}",
            f"monitoring        {r.monitor_calls} calls: {mons}" + (f"   task finished at frame {r.task_finished_frame}" if r.task_finished_frame is not None else ""),
            f"verifier          {v.candidates} candidates, {v.accepted} accepted, {v.moved} moved "
            f"(shift median {_num(v.pixel_shift_median_px, '.1f')} px, max {_num(v.pixel_shift_max_px, '.1f')} px), "
            f"{v.range_gated} range-gated (median gating {_num(v.gating_factor_median, '.2f')}), rejected: {rej}",
        ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from onfly.readers import open_source
    from onfly.replay import replay
    from onfly.viz import RerunRecorder
    from vlm.types import VlmError

    if not args.path.exists():
        raise CliError(f"{args.path}: no such file or directory")
    if (args.tf_parent is None) != (args.tf_child is None):
        raise CliError("--tf-parent and --tf-child go together (the transform parent -> child of the camera pose on /tf)")
    config = _config(args)
    if config.instruction is not None and config.vlm.split(":", 1)[0].strip().lower() in ("sim", "http", "https", "transformers"):
        from onfly.bench.runner import check_vlm_spec

        try:
            check_vlm_spec(config.vlm)
        except ValueError as exc:
            raise CliError(f"--vlm: {exc}") from None
    options = dict(
        intrinsics=_floats(args.intrinsics, 4, "--intrinsics (fx,fy,cx,cy)"),
        depth_topic=args.depth_topic,
        rgb_topic=args.rgb_topic,
        camera_info_topic=args.camera_info_topic,
        pose_topic=args.pose_topic,
        tf_parent_frame=args.tf_parent,
        tf_child_frame=args.tf_child,
    )
    recorder = None
    try:
        with open_source(args.path, kind=args.kind, **options) as source:
            recorder = RerunRecorder(args.rrd, application_id="onfly_replay") if args.rrd else None
            report = replay(source, config, recorder=recorder, progress=not args.no_progress)
    except VlmError as exc:
        raise CliError(f"VLM backend {config.vlm!r}: {exc}") from None
    except ValueError as exc:
        raise CliError(flag_names(" ".join(str(exc).split()))) from None
    finally:
        if recorder is not None:
            recorder.close()
    echo(format_report(report))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report.to_dict(), indent=2))
        echo(f"json          {args.json}")
    if args.rrd:
        echo(f"recording     {args.rrd}   (open with: rerun {args.rrd})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    from onfly.cli import main

    sys.exit(main(["replay", *sys.argv[1:]]))
