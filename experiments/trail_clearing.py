"""The map under motion (issue 19): how long a walker's trail stays in the default ESDF.

A walker (a 1.75 m person, 0.24 m torso radius) crosses 4 m in front of a hovering camera at
flight height (y from -3 to +3, then out of view) in front of a wall 6.5 m away; every frame the
embedded world renders depth (320 x 214, the benchmark's frames) and the map (``EsdfConfig()``)
integrates it. Per frame rate and walking speed this prints:

- ``phantom_max``: the most occupied voxels of the trail at once (voxels of the slab the walker
  crosses that are more than 0.45 m from it: space it has left);
- ``trail_max_m``: the longest stretch along its path, behind it, that the map still holds as
  obstacle (metres);
- ``free_obs_max``: the most free observations any trail voxel got while still an obstacle (the
  map clears a voxel on its 6th: float32 log-odds, ``tests/test_esdf_walker.py``);
- ``clear_s``: seconds from the walker leaving the slab until no trail voxel is left.

Run: ``.venv/bin/python experiments/trail_clearing.py --json /tmp/trail.json``
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from onfly.world.scene import parse_scene
from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig

CAM = PinholeCamera.from_fov(320, 214, 90.0, 60.0)


def scene(speed_mps: float):
    person = [
        {"type": "cylinder", "base_m": [0, 0, 0], "radius_m": 0.2, "height_m": 0.85, "segments": 8},
        {"type": "cylinder", "base_m": [0, 0, 0.85], "radius_m": 0.24, "height_m": 0.62, "segments": 8},
        {"type": "sphere", "center_m": [0, 0, 1.6], "radius_m": 0.13, "rings": 4},
    ]
    motion = {"type": "path", "loop": False, "waypoints": [
        {"position_m": [4.0, -3.0, 0.0], "speed_mps": speed_mps}, {"position_m": [4.0, 8.0, 0.0], "speed_mps": speed_mps}]}
    return parse_scene({
        "format": "onfly-scene/1", "name": "trail",
        "bounds": {"min_m": [-10, -10, 0], "max_m": [10, 10, 5]},
        "start": {"position_m": [0.0, 0.0, 1.5], "yaw_deg": 0},
        "objects": [
            {"name": "floor", "label": "floor", "instance_id": 1, "color": "#808080", "target": False,
             "parts": [{"type": "plane", "center_m": [0, 0, 0], "size_m": [40, 40]}]},
            {"name": "back wall", "label": "wall", "instance_id": 2, "color": "#A0A0A0", "target": False,
             "parts": [{"type": "box", "center_m": [6.6, 0, 2.5], "size_m": [0.2, 30, 5]}]},
            {"name": "walker", "label": "person", "instance_id": 9, "color": "#C62828", "parts": person, "motion": motion},
        ],
    })


def run(frame_period_s: float, speed_mps: float) -> dict:
    cfg = EsdfConfig()
    world = World(scene(speed_mps), camera=CAM)
    esdf = EsdfMap(cfg)
    centers = slab = None
    runs = None
    phantom, trail_len, worst = [], [], 0
    t_leave = 6.0 / speed_mps
    times = []
    while world.clock.now_s <= t_leave + 8.0:
        obs = world.observe()
        esdf.integrate(obs.depth_m, obs.camera, obs.T_world_cam, body_world=world.state.p)
        if centers is None:
            centers = esdf.voxel_centers().reshape(-1, 3)
            slab = np.flatnonzero((np.abs(centers[:, 0] - 4.0) < 0.6) & (np.abs(centers[:, 1]) < 3.0) & (centers[:, 2] > 0.25) & (centers[:, 2] < 1.8))
            runs = np.zeros(len(slab), dtype=int)
        occ = esdf.occupied_grid.reshape(-1)[slab]
        T_cam_world = np.linalg.inv(obs.T_world_cam)
        pc = centers[slab] @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        uv = np.round(pc[:, :2] / pc[:, 2:3] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]).astype(int)
        inside = (pc[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < CAM.width) & (uv[:, 1] >= 0) & (uv[:, 1] < CAM.height)
        d = np.zeros(len(pc))
        d[inside] = obs.depth_m[uv[inside, 1], uv[inside, 0]]
        seen_free = inside & (d > pc[:, 2] + cfg.clear_margin_m + cfg.voxel_m)
        walker = world.actor_pose("walker").position_m
        away = np.linalg.norm(centers[slab, :2] - walker[:2], axis=1) > 0.45
        runs = np.where(away, runs + seen_free, 0)
        trail = occ & away
        phantom.append(int(trail.sum()))
        behind = centers[slab[trail], 1]
        trail_len.append(float(walker[1] - behind.min()) if trail.any() and behind.min() < walker[1] else 0.0)
        if trail.any():
            worst = max(worst, int(runs[trail].max()))
        times.append(world.clock.now_s)
        for _ in range(int(round(frame_period_s / 0.1))):
            world.step(0.1)
    last = max((t for t, p in zip(times, phantom) if p > 0), default=0.0)
    return {"frame_period_s": frame_period_s, "speed_mps": speed_mps, "frames": len(times), "phantom_max": max(phantom),
            "trail_max_m": max(trail_len), "free_obs_max": worst, "clear_s": max(0.0, last + frame_period_s - t_leave)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows = [run(fp, v) for fp in (0.1, 0.5) for v in (0.45, 0.9, 1.3)]
    print(f"{'frame s':>7} {'speed m/s':>9} {'frames':>6} {'phantom max':>11} {'trail max m':>11} {'free obs max':>12} {'clear s':>7}")
    for r in rows:
        print(f"{r['frame_period_s']:>7.1f} {r['speed_mps']:>9.2f} {r['frames']:>6} {r['phantom_max']:>11} {r['trail_max_m']:>11.2f} "
              f"{r['free_obs_max']:>12} {r['clear_s']:>7.1f}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"esdf": "EsdfConfig() defaults", "camera": [CAM.width, CAM.height], "rows": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
