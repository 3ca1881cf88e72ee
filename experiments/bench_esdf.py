"""Benchmark of the ESDF update on a moving camera in a cluttered synthetic scene.

Scene: a ground plane and seeded random boxes, spheres and cylinders in a 24 x 24 m yard, rendered
to 640 x 480 z-depth with Open3D's ``RaycastingScene`` (the paper's 90 x 60 deg camera). The
camera flies a seeded smooth path at ``--speed-mps`` with ``--rate-hz`` frames, its yaw turning
along the path and sweeping left and right, so the rolling window shifts every few frames.

Measured in the same run:

- ``update_ms_*``: our :meth:`EsdfMap.integrate` per frame (everything: recentre, Open3D
  back-projection, clearing, log-odds, incremental distance update);
- ``reference_ms_median``: the full-grid recompute of the same signed, clamped field with
  ``scipy.ndimage.distance_transform_edt`` (outside and inside transforms), on every
  ``--reference-every``-th frame; ``incremental_vs_full_max_diff_m`` checks that our
  incremental field equals it;
- ``query_us_40_points``: one :meth:`EsdfMap.query` of 40 points (the planner's per-step size);
- ``max_abs_error_m``: ours against the exact mesh distance
  (``RaycastingScene.compute_distance``), both clamped to ``max_distance_m``, at points in
  seen free space (on the last frames' rays, short of the hit) whose nearest mesh point lies
  within one voxel of an observed obstacle voxel (geometry the camera never saw cannot be in
  any map) and that are at least one voxel from the surface.

Run: ``.venv/bin/python experiments/bench_esdf.py --json /tmp/bench_esdf.json``
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict

import numpy as np
import open3d as o3d
import scipy.ndimage as ndi

from planning.camera import PinholeCamera
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig
from planning.frames import body_transform, cam_transform_from_body


def build_scene(seed: int, n_obstacles: int) -> tuple[o3d.t.geometry.RaycastingScene, np.ndarray]:
    """Cluttered yard around a closed camera path; returns the scene and the path (m, 2)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    path = np.stack([7.0 * np.cos(s), 4.5 * np.sin(2.0 * s)], axis=-1)
    meshes = []
    ground = o3d.geometry.TriangleMesh.create_box(30.0, 30.0, 0.2)
    ground.translate([-15.0, -15.0, -0.2])
    meshes.append(ground)
    placed = 0
    while placed < n_obstacles:
        kind = rng.choice(["box", "box", "sphere", "cylinder"])
        c = rng.uniform(-11.0, 11.0, size=2)
        if kind == "box":
            size = rng.uniform([0.3, 0.3, 0.5], [2.0, 2.0, 3.5])
            radius = 0.5 * np.hypot(size[0], size[1])
        else:
            radius = rng.uniform(0.2, 0.8)
        if np.min(np.linalg.norm(path - c, axis=1)) < radius + 0.8:
            continue
        if kind == "box":
            m = o3d.geometry.TriangleMesh.create_box(*size)
            m.translate([c[0] - size[0] / 2, c[1] - size[1] / 2, 0.0])
            m.rotate(o3d.geometry.get_rotation_matrix_from_xyz([0.0, 0.0, rng.uniform(0, np.pi)]), center=[*c, 0.0])
        elif kind == "sphere":
            m = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=24)
            m.translate([c[0], c[1], rng.uniform(radius, 2.5)])
        else:
            h = rng.uniform(1.0, 3.5)
            m = o3d.geometry.TriangleMesh.create_cylinder(radius, h, resolution=32)
            m.translate([c[0], c[1], h / 2])
        meshes.append(m)
        placed += 1
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    return scene, path


def render_depth(scene, camera: PinholeCamera, T_world_cam: np.ndarray) -> np.ndarray:
    """z-depth (h, w) float32: rays with optical z = 1 make RaycastingScene's t_hit the z-depth.

    Misses come back as inf (no reading).
    """
    d_world = camera.rays().reshape(-1, 3) @ T_world_cam[:3, :3].T
    rays = np.hstack([np.broadcast_to(T_world_cam[:3, 3], d_world.shape), d_world]).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return t.reshape(camera.height, camera.width).astype(np.float32)


def camera_poses(path: np.ndarray, n_frames: int, speed_mps: float, rate_hz: float, height_m: float) -> list[np.ndarray]:
    """T_world_cam along the closed path at constant speed, yaw = tangent + a +-35 deg sweep."""
    seg = np.linalg.norm(np.diff(np.vstack([path, path[:1]]), axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    closed = np.vstack([path, path[:1]])
    poses = []
    for k in range(n_frames):
        s = (k * speed_mps / rate_hz) % arc[-1]
        x = np.interp(s, arc, closed[:, 0])
        y = np.interp(s, arc, closed[:, 1])
        x2 = np.interp((s + 0.2) % arc[-1], arc, closed[:, 0])
        y2 = np.interp((s + 0.2) % arc[-1], arc, closed[:, 1])
        yaw = np.arctan2(y2 - y, x2 - x) + np.deg2rad(35.0) * np.sin(2.0 * np.pi * k / (4.0 * rate_hz))
        poses.append(cam_transform_from_body(body_transform([x, y, height_m], yaw)))
    return poses


def reference_field(solid: np.ndarray, config: EsdfConfig) -> np.ndarray:
    """The same clamped signed field as EsdfMap, recomputed on the whole grid with scipy.

    Space outside the grid takes the unknown policy (one padded layer), as in EsdfMap.
    """
    v = config.voxel_m
    outside_solid = config.unknown_policy == "occupied"
    padded = np.pad(solid, 1, mode="constant", constant_values=outside_solid)
    d_out = ndi.distance_transform_edt(~padded)[1:-1, 1:-1, 1:-1] * v
    d_in = ndi.distance_transform_edt(padded)[1:-1, 1:-1, 1:-1] * v
    inside = -np.minimum(d_in - v, config.max_inside_distance_m)
    return np.where(solid, inside, np.minimum(d_out, config.max_distance_m)).astype(np.float32)


def error_points(scene, esdf: EsdfMap, camera: PinholeCamera, frames, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points in seen free space whose nearest mesh point was observed; returns (points, truth)."""
    pts = []
    for depth, T in frames:
        rows = rng.integers(0, camera.height, 4000)
        cols = rng.integers(0, camera.width, 4000)
        d = depth[rows, cols]
        ok = np.isfinite(d) & (d < esdf.config.max_range_m)
        frac = rng.uniform(0.05, 0.95, ok.sum())
        P_cam = camera.back_project(np.stack([cols[ok], rows[ok]], -1).astype(float), d[ok] * frac)
        pts.append(P_cam @ T[:3, :3].T + T[:3, 3])
    P = np.vstack(pts)
    lo, hi = esdf.bounds_world
    P = P[np.all((P > lo + esdf.voxel_m) & (P < hi - esdf.voxel_m), axis=1)]
    t = o3d.core.Tensor(P.astype(np.float32))
    truth = scene.compute_distance(t).numpy().astype(float)
    nearest = scene.compute_closest_points(t)["points"].numpy().astype(float)
    occ = esdf.occupied_points()
    grid = np.zeros(esdf.shape, dtype=bool)
    idx = np.floor(occ / esdf.voxel_m).astype(np.int64) - esdf.origin_index
    grid[tuple(idx.T)] = True
    grid = ndi.binary_dilation(grid, iterations=1, structure=np.ones((3, 3, 3), bool))
    ni = np.floor(nearest / esdf.voxel_m).astype(np.int64) - esdf.origin_index
    inside = np.all((ni >= 0) & (ni < np.asarray(esdf.shape)), axis=1)
    seen = np.zeros(len(P), dtype=bool)
    seen[inside] = grid[tuple(ni[inside].T)]
    keep = seen & (truth > esdf.voxel_m)
    return P[keep], truth[keep]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--obstacles", type=int, default=60)
    ap.add_argument("--speed-mps", type=float, default=0.6)
    ap.add_argument("--rate-hz", type=float, default=15.0)
    ap.add_argument("--reference-every", type=int, default=10)
    ap.add_argument("--unknown-policy", choices=["free", "occupied"], default="free")
    ap.add_argument("--json", type=str, default=None, help="write the results here")
    args = ap.parse_args(argv)

    config = EsdfConfig(unknown_policy=args.unknown_policy)
    camera = PinholeCamera.from_fov(640, 480, 90.0, 60.0)
    scene, path = build_scene(args.seed, args.obstacles)
    poses = camera_poses(path, args.frames, args.speed_mps, args.rate_hz, height_m=1.5)
    depths = [render_depth(scene, camera, T) for T in poses]  # rendered first: not timed

    esdf = EsdfMap(config)
    esdf.integrate(depths[0], camera, poses[0])  # first frame fills an empty map: not counted
    update_ms, ref_ms, diffs, stage = [], [], [], []
    for k in range(1, len(poses)):
        u = esdf.integrate(depths[k], camera, poses[k])
        update_ms.append(u.total_ms)
        stage.append([u.shift_ms, u.backproject_ms, u.occupancy_ms, u.esdf_ms, u.esdf_voxels, u.n_changed_voxels])
        if k % args.reference_every == 0:
            solid = esdf._occ.solid.copy()
            t0 = time.perf_counter()
            ref = reference_field(solid, config)
            ref_ms.append((time.perf_counter() - t0) * 1e3)
            diffs.append(float(np.abs(ref - esdf.distance_grid).max()))

    rng = np.random.default_rng(args.seed + 1)
    tail = list(zip(depths[-10:], poses[-10:]))
    P, truth = error_points(scene, esdf, camera, tail, rng)
    ours, _ = esdf.query(P)
    clamp = config.max_distance_m
    err = np.abs(np.minimum(ours, clamp) - np.minimum(truth, clamp))

    # query latency at the planner's size (about 40 points per control step)
    q = P[:40] if len(P) >= 40 else np.resize(P, (40, 3))
    n_calls = 2000
    t0 = time.perf_counter()
    for _ in range(n_calls):
        esdf.query(q)
    query_us_40 = (time.perf_counter() - t0) / n_calls * 1e6

    stage = np.asarray(stage)
    update_ms = np.asarray(update_ms)
    result = {
        "update_ms_median": float(np.median(update_ms)),
        "update_ms_p95": float(np.percentile(update_ms, 95)),
        "update_ms_max": float(update_ms.max()),
        "reference_ms_median": float(np.median(ref_ms)),
        "speedup": float(np.median(ref_ms) / np.median(update_ms)),
        "max_abs_error_m": float(err.max()),
        "mean_abs_error_m": float(err.mean()),
        "error_points": int(len(P)),
        "incremental_vs_full_max_diff_m": float(max(diffs)),
        "query_us_40_points": float(query_us_40),
        "voxel_m": config.voxel_m,
        "grid_shape": list(esdf.shape),
        "frames": int(len(update_ms)),
        "image": [camera.width, camera.height],
        "stage_ms_median": {
            "shift": float(np.median(stage[:, 0])),
            "backproject": float(np.median(stage[:, 1])),
            "occupancy": float(np.median(stage[:, 2])),
            "esdf": float(np.median(stage[:, 3])),
        },
        "esdf_voxels_median": float(np.median(stage[:, 4])),
        "changed_voxels_median": float(np.median(stage[:, 5])),
        "config": asdict(config),
        "args": vars(args),
    }
    rows = [
        ("update ms (median / p95 / max)", f"{result['update_ms_median']:.2f} / {result['update_ms_p95']:.2f} / {result['update_ms_max']:.2f}"),
        ("  shift / backproject / occupancy / esdf ms", " / ".join(f"{v:.2f}" for v in result["stage_ms_median"].values())),
        ("  voxels rewritten per frame (median)", f"{result['esdf_voxels_median']:.0f} of {int(np.prod(esdf.shape))}"),
        ("reference full recompute ms (median)", f"{result['reference_ms_median']:.2f}"),
        ("speedup (reference / ours)", f"{result['speedup']:.1f}x"),
        ("incremental vs full max diff m", f"{result['incremental_vs_full_max_diff_m']:.2e}"),
        ("max / mean abs error vs mesh m", f"{result['max_abs_error_m']:.3f} / {result['mean_abs_error_m']:.3f} ({len(P)} pts)"),
        ("query of 40 points us", f"{query_us_40:.1f}"),
        ("voxel m / grid", f"{config.voxel_m} / {tuple(esdf.shape)}"),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"ESDF benchmark: {result['frames']} frames 640x480, unknown={config.unknown_policy}, seed {args.seed}")
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
