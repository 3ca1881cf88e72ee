"""The map under motion (issue 19): does the ESDF + MPC path avoid a person who walks into it?

The oracle (``onfly.bench.oracle``: ESDF from rendered depth, MPC, a carrot on a straight
reference to (16, 0, 1.5)) flies down a 10 m wide street at the paper's 0.6 m/s while a person
(1.75 m, 0.24 m torso radius) either steps from the kerb into the middle of the path ``at_m``
metres ahead and stands there (``step_in``), crosses the street once there and stands on the
far kerb (``cross_once``), or paces back and forth across the path there (``cross``, turning
0.6 m further on) at ``speed_mps``, starting at ``start_s``. Frames at 2 Hz, 320 x 214 (the
benchmark's). Per scenario: success, collision, the closest the vehicle came to the person's
surface (exact, at its pose at each instant), and the flight time against the same flight with
nobody in the street.

Run: ``.venv/bin/python experiments/avoid_walker.py --json /tmp/avoid.json``
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from onfly.bench.episode import EpisodeConfig, run_episode
from onfly.bench.method import PrivilegedGoal
from onfly.bench.metrics import GoalRegion
from onfly.bench.oracle import make_oracle
from onfly.world.scene import parse_scene
from onfly.world.world import World
from planning.camera import PinholeCamera

CAM = PinholeCamera.from_fov(320, 214, 90.0, 60.0)
PERSON = [
    {"type": "cylinder", "base_m": [0, 0, 0], "radius_m": 0.2, "height_m": 0.85, "segments": 8},
    {"type": "cylinder", "base_m": [0, 0, 0.85], "radius_m": 0.24, "height_m": 0.62, "segments": 8},
    {"type": "sphere", "center_m": [0, 0, 1.6], "radius_m": 0.13, "rings": 4},
]


def street(motion: dict | None):
    objects = [
        {"name": "floor", "label": "floor", "instance_id": 1, "color": "#808080", "target": False,
         "parts": [{"type": "plane", "center_m": [9, 0, 0], "size_m": [40, 20]}]},
        {"name": "walls", "label": "wall", "instance_id": 2, "color": "#A0A0A0", "target": False,
         "parts": [{"type": "box", "center_m": [9, 5.2, 2], "size_m": [26, 0.2, 4]},
                   {"type": "box", "center_m": [9, -5.2, 2], "size_m": [26, 0.2, 4]},
                   {"type": "box", "center_m": [21.2, 0, 2], "size_m": [0.2, 10.6, 4]}]},
    ]
    if motion is not None:
        objects.append({"name": "walker", "label": "person", "instance_id": 9, "color": "#C62828", "parts": PERSON, "motion": motion})
    return parse_scene({"format": "onfly-scene/1", "name": "street", "bounds": {"min_m": [-2, -5, 0], "max_m": [20, 5, 4]},
                        "start": {"position_m": [0.0, 0.0, 1.5], "yaw_deg": 0}, "objects": objects})


def motion_of(kind: str, at_m: float, speed_mps: float, start_s: float) -> dict:
    if kind == "step_in":
        wps = [[at_m, -4.0, 0.0], [at_m, 0.0, 0.0]]
        return {"type": "path", "loop": False, "start_s": start_s, "waypoints": [{"position_m": p, "speed_mps": speed_mps} for p in wps]}
    if kind == "cross_once":  # from one kerb to the other, then stands there
        wps = [[at_m, -4.5, 0.0], [at_m, 4.5, 0.0]]
        return {"type": "path", "loop": False, "start_s": start_s, "waypoints": [{"position_m": p, "speed_mps": speed_mps} for p in wps]}
    wps = [[at_m, -4.0, 0.0], [at_m, 4.0, 0.0], [at_m + 0.6, 4.0, 0.0], [at_m + 0.6, -4.0, 0.0]]
    return {"type": "path", "loop": True, "start_s": start_s, "waypoints": [{"position_m": p, "speed_mps": speed_mps} for p in wps]}


def fly(motion: dict | None, movers: bool = True) -> dict:
    world = World(street(motion), camera=CAM)
    goal = np.array([16.0, 0.0, 1.5])
    oracle = make_oracle("sim:nominal", 0, movers={"enabled": movers})
    res = run_episode(world, oracle, instruction="fly to the end of the street", goal=GoalRegion(goal, np.full(3, 0.5)),
                      reference_path_m=16.0, seed=0, error_model="none",
                      privileged=PrivilegedGoal(goal, np.full(3, 0.5), np.array([[0.0, 0.0, 1.5], goal])),
                      config=EpisodeConfig(frame_period_s=0.5))
    tr = res.trace
    out = {"end": res.end_reason, "success": bool(res.metrics.success), "collided": bool(res.metrics.collided),
           "flight_time_s": float(res.metrics.flight_time_s), "movers": oracle.movers.summary()}
    if motion is not None:
        out["min_to_person_m"] = float(distance_to_actor(world, tr.positions, tr.t_s).min())
    return out


def distance_to_actor(world: World, points: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """Exact distance (n,) from points (n, 3) to the walker's surface at its pose at each time."""
    import open3d as o3d

    a = world.geometry.actor(9)
    out = np.empty(len(points))
    for i, (p, t) in enumerate(zip(points, times_s)):
        T = a.pose(float(t)).T_world_actor
        local = (T[:3, :3].T @ (p - T[:3, 3])).astype(np.float32)[None]
        q = a.raycasting.compute_closest_points(o3d.core.Tensor(local))["points"].numpy()[0]
        out[i] = float(np.linalg.norm(q - local[0]))
    return out


SCENARIOS = [
    ("step_in", 6.0, 1.2, 1.0), ("step_in", 9.0, 1.2, 2.0), ("step_in", 12.0, 1.2, 4.0),
    ("cross_once", 8.0, 1.3, 4.0), ("cross_once", 8.0, 1.3, 7.0), ("cross_once", 8.0, 1.3, 10.0),
    ("cross_once", 8.0, 0.45, 2.0), ("cross_once", 8.0, 0.45, 8.0),
    ("cross", 6.0, 0.45, 0.0), ("cross", 8.0, 0.9, 0.0), ("cross", 8.0, 1.3, 0.0), ("cross", 11.0, 1.3, 3.0),
]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None, help="write the rows to this JSON file")
    ap.add_argument("--scenarios", default=None, help="comma-separated row indices of SCENARIOS (default: all)")
    args = ap.parse_args(argv)
    picked = SCENARIOS if args.scenarios is None else [SCENARIOS[int(i)] for i in args.scenarios.split(",")]
    base = fly(None)
    rows = []
    print(f"nobody in the street: {base['end']}, flight time {base['flight_time_s']:.1f} s")
    print(f"{'scenario':<10} {'at m':>5} {'m/s':>5} {'start s':>7} | {'prediction: end':<16} {'min m':>6} {'extra s':>7} | "
          f"{'map alone: end':<16} {'min m':>6} {'extra s':>7}")
    for kind, at_m, v, s0 in picked:
        row = {"scenario": kind, "at_m": at_m, "speed_mps": v, "start_s": s0}
        cells = []
        for label, movers in (("prediction", True), ("map_alone", False)):
            r = fly(motion_of(kind, at_m, v, s0), movers)
            r["extra_time_s"] = r["flight_time_s"] - base["flight_time_s"]
            row[label] = r
            end = "collision" if r["collided"] else ("success" if r["success"] else r["end"])
            extra = "-" if r["collided"] else f"{r['extra_time_s']:.1f}"
            cells.append(f"{end:<16} {r['min_to_person_m']:>6.2f} {extra:>7}")
        rows.append(row)
        print(f"{kind:<10} {at_m:>5.1f} {v:>5.2f} {s0:>7.1f} | {cells[0]} | {cells[1]}", flush=True)
    for label in ("prediction", "map_alone"):
        n = sum(r[label]["collided"] for r in rows)
        print(f"{label}: {n} collision(s) in {len(rows)}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"baseline": base, "rows": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
