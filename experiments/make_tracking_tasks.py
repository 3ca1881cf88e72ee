"""Write the tracking task files (onfly/data/tasks/track/<scene>.toml), without references.

Each task starts behind or beside its walker at t = 0 (``offset_deg`` from straight behind,
``r`` metres away horizontally, 1.5 m up), facing them. Prove them and store the references
with ``onfly tasks check --write --files onfly/data/tasks/track/*.toml``.

    PYTHONPATH=. python experiments/make_tracking_tasks.py
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from onfly.bench.tasks import GoalSpec, StartPose, Task, TrackSpec, actor_bounds_at, tasks_dir, write_task_file
from onfly.commands.tasks import HEADER
from onfly.world.actors import pose_at
from onfly.world.scene import load_scene, resolve_scene
from vlm.decompose import attach_back_references, split_instruction

#: (id suffix, actor, instruction, r, offset_deg, options)
TASKS = {
    "plaza": [
        ("t01", "woman in the yellow coat", "Follow the woman in the yellow coat.", 3.0, 0, {}),
        ("t02", "woman in the yellow coat", "Keep up with the woman in the yellow coat as she walks.", 3.5, -35, {}),
        ("t03", "woman in the yellow coat", "Track the woman in the yellow coat and keep a few metres from her.", 2.5, -30, {}),
        ("t04", "woman in the yellow coat", "Stay behind the woman in the yellow coat.", 3.0, -20, {"duration_s": 50.0}),
        ("t05", "woman in the yellow coat", "Tail the woman in the yellow coat.", 2.5, 0, {"duration_s": 50.0, "in_band_frac": 0.7}),
        ("t06", "woman with the stroller", "Follow the woman with the stroller until she stops, then stop next to her.", 3.0, 0, {"stop_radius_m": 3.0}),
        ("t07", "woman with the stroller", "Stay behind the woman with the stroller until she comes to a stop, then stop beside her.", 3.5, 25,
         {"stop_radius_m": 3.0}),
        ("t08", "woman with the stroller", "Keep up with the woman with the stroller.", 2.5, 20, {"duration_s": 50.0}),
        ("t09", "man with the wheelbarrow", "Stay behind the man with the wheelbarrow until he stops, then stop next to him.", 3.0, 0,
         {"stop_radius_m": 3.0}),
        ("t10", "man with the wheelbarrow", "Follow the man with the wheelbarrow until he stops, then stop beside him.", 3.0, 25, {"stop_radius_m": 3.0}),
        ("t11", "man with the wheelbarrow", "Follow the man with the wheelbarrow.", 2.5, -20, {"duration_s": 50.0}),
        ("t12", "woman in the purple dress", "Follow the woman in the purple dress.", 3.0, 0, {}),
        ("t13", "woman in the purple dress", "Stay close to the woman in the purple dress while she walks.", 3.0, 30, {}),
        ("t14", "woman in the purple dress", "Track the woman in the purple dress.", 2.5, 40, {"duration_s": 50.0}),
    ],
    "duplex": [
        ("t01", "man in the orange vest", "Follow the man in the orange vest.", 3.0, -60, {}),
        ("t02", "man in the orange vest", "Stay behind the man in the orange vest.", 3.0, -90, {}),
        ("t03", "man in the orange vest", "Keep pace with the man in the orange vest.", 2.5, -75, {"duration_s": 50.0}),
        ("t04", "man in the orange vest", "Track the man in the orange vest and stay a few metres away.", 3.5, -70, {"duration_s": 50.0}),
        ("t05", "woman with the shopping bag", "Follow the woman with the shopping bag until she stops, then stop next to her.", 3.0, 0,
         {"stop_radius_m": 3.0}),
        ("t06", "woman with the shopping bag", "Stay behind the woman with the shopping bag until she stops, then stop beside her.", 3.0, 30,
         {"stop_radius_m": 3.0}),
        ("t07", "woman with the shopping bag", "Follow the woman with the shopping bag.", 2.5, -25, {"duration_s": 50.0}),
    ],
}
ALTITUDE_M = 1.5


def build(scene_name: str) -> list[Task]:
    scene = load_scene(resolve_scene(scene_name))
    out = []
    for suffix, actor, instruction, r, offset_deg, opts in TASKS[scene_name]:
        motion = scene.object_by_name(actor).motion
        pose = pose_at(motion, 0.0)
        back = pose.yaw_rad + math.pi + math.radians(offset_deg)
        p = pose.position_m[:2] + r * np.array([math.cos(back), math.sin(back)])
        start = StartPose(np.array([p[0], p[1], ALTITUDE_M]), math.atan2(pose.position_m[1] - p[1], pose.position_m[0] - p[0]))
        track = TrackSpec(actor, **{"band_m": (1.5, 4.0), "in_band_frac": 0.8, "duration_s": 60.0, "lost_after_s": 3.0, **opts})
        lo, hi = actor_bounds_at(scene, actor, track.duration_s)
        goal = GoalSpec((lo + hi) / 2, (hi - lo) / 2 + 0.5)
        subtasks = attach_back_references(split_instruction(instruction))
        out.append(Task(f"{scene_name}-{suffix}", scene_name, "track", instruction, tuple(subtasks), (actor,), goal, start, track=track))
    return out


def main() -> None:
    folder = tasks_dir() / "track"
    folder.mkdir(exist_ok=True)
    header = HEADER + "\nTracking tasks (issue 19): experiments/make_tracking_tasks.py writes them; docs/tracking.md."
    for name in TASKS:
        path = Path(folder) / f"{name}.toml"
        write_task_file(path, name, build(name), header)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
