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

Four maps run on the same frames and are printed side by side: ``before`` (the old defaults:
unknown space free, no body sphere, no clearing by pixels without a reading, a 10 x 10 x 4 m
window), ``window only`` (the same in the new window), ``after, no cull`` (the new defaults
with ``reach_cull=False``: the clearing path before its shortcuts) and ``after``
(``EsdfConfig()``: unknown is an obstacle, bounded no-reading clearing, a body sphere, a
16 x 16 x 5 m window covering D_max, the clearing shortcuts). ``update CPU ms`` is this
process's CPU time per frame (robust to other processes on shared cores); the last row checks
that ``after`` and ``after, no cull`` build the same map after every frame. Also reported: the largest *optimistic*
error (the field above the truth, the unsafe direction), the share of seen-free sample points
the map reads free, and the share of the last camera's view cone (0.5-7 m) the map knows.

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


#: The configurations compared in one run: the map before issue 17 (main's old defaults), the
#: old map in the new window (the cost of item 3 alone), the new defaults without the clearing
#: shortcuts (``reach_cull=False``: every candidate voxel of the frustum projected, the reach
#: scanned over the whole image) and the new defaults.
CONFIGS = {
    "before": EsdfConfig(unknown_policy="free", no_reading_clear_m=0.0, body_clear_radius_m=0.0, size_m=(10.0, 10.0, 4.0)),
    "window only": EsdfConfig(unknown_policy="free", no_reading_clear_m=0.0, body_clear_radius_m=0.0),
    "after, no cull": EsdfConfig(reach_cull=False),
    "after": EsdfConfig(),
}


def run_config(config: EsdfConfig, scene, camera, depths, poses, args) -> dict:
    """Integrate every frame with ``config``; timings, exactness and error against the mesh."""
    esdf = EsdfMap(config)
    esdf.integrate(depths[0], camera, poses[0])  # first frame fills an empty map: not counted
    update_ms, ref_ms, diffs, stage = [], [], [], []
    cpu_ms = []
    for k in range(1, len(poses)):
        c0 = time.process_time()
        u = esdf.integrate(depths[k], camera, poses[k])
        cpu_ms.append((time.process_time() - c0) * 1e3)
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
    signed = np.minimum(ours, clamp) - np.minimum(truth, clamp)
    err = np.abs(signed)

    # query latency at the planner's size (about 40 points per control step)
    q = P[:40] if len(P) >= 40 else np.resize(P, (40, 3))
    n_calls = 2000
    t0 = time.perf_counter()
    for _ in range(n_calls):
        esdf.query(q)
    query_us_40 = (time.perf_counter() - t0) / n_calls * 1e6

    # what the last camera knows: its share of the window and of the view cone up to 7 m
    T = poses[-1]
    C = esdf.voxel_centers().reshape(-1, 3)
    P_cam = (C - T[:3, 3]) @ T[:3, :3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.fx * P_cam[:, 0] / P_cam[:, 2] + camera.cx
        v = camera.fy * P_cam[:, 1] / P_cam[:, 2] + camera.cy
    cone = (P_cam[:, 2] > 0.5) & (P_cam[:, 2] < config.max_range_m) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    known = esdf.known_grid.reshape(-1)

    stage = np.asarray(stage)
    update_ms = np.asarray(update_ms)
    return {
        "update_ms_median": float(np.median(update_ms)),
        "update_cpu_ms_median": float(np.median(cpu_ms)),
        "update_cpu_ms_mean": float(np.mean(cpu_ms)),
        "update_ms_p95": float(np.percentile(update_ms, 95)),
        "update_ms_max": float(update_ms.max()),
        "reference_ms_median": float(np.median(ref_ms)),
        "speedup": float(np.median(ref_ms) / np.median(update_ms)),
        "max_abs_error_m": float(err.max()),
        "mean_abs_error_m": float(err.mean()),
        "max_optimistic_error_m": float(max(signed.max(), 0.0)),
        "seen_free_points_read_free": float(np.mean(ours > 0.0)),
        "error_points": int(len(P)),
        "incremental_vs_full_max_diff_m": float(max(diffs)),
        "query_us_40_points": float(query_us_40),
        "known_fraction_of_view_cone": float(known[cone].mean()) if cone.any() else 0.0,
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
    }


def same_map(a: EsdfConfig, b: EsdfConfig, camera, depths, poses) -> bool:
    """Both configs integrate the frames into identical maps (log-odds, observed, obstacle mask
    and distance compared after every frame)."""
    ma, mb = EsdfMap(a), EsdfMap(b)
    for depth, T in zip(depths, poses):
        ma.integrate(depth, camera, T)
        mb.integrate(depth, camera, T)
        oa, ob = ma._occ, mb._occ
        if not (
            np.array_equal(oa.logodds, ob.logodds)
            and np.array_equal(oa.observed, ob.observed)
            and np.array_equal(oa.solid, ob.solid)
            and np.array_equal(ma.distance_grid, mb.distance_grid)
        ):
            return False
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--obstacles", type=int, default=60)
    ap.add_argument("--speed-mps", type=float, default=0.6)
    ap.add_argument("--rate-hz", type=float, default=15.0)
    ap.add_argument("--reference-every", type=int, default=10)
    ap.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=list(CONFIGS), help="which maps to run")
    ap.add_argument("--json", type=str, default=None, help="write the results here")
    args = ap.parse_args(argv)

    camera = PinholeCamera.from_fov(640, 480, 90.0, 60.0)
    scene, path = build_scene(args.seed, args.obstacles)
    poses = camera_poses(path, args.frames, args.speed_mps, args.rate_hz, height_m=1.5)
    depths = [render_depth(scene, camera, T) for T in poses]  # rendered first: not timed
    no_reading = float(np.mean([np.mean(~np.isfinite(d)) for d in depths]))

    results = {name: run_config(CONFIGS[name], scene, camera, depths, poses, args) for name in args.configs}
    if "after" in args.configs and "after, no cull" in args.configs:
        results["after"]["same_map_as_no_cull"] = same_map(CONFIGS["after, no cull"], CONFIGS["after"], camera, depths, poses)
    rows = [
        ("unknown policy / no-reading clear m / body m", lambda r: f"{r['config']['unknown_policy']} / {r['config']['no_reading_clear_m']} / {r['config']['body_clear_radius_m']}"),
        ("window m / grid", lambda r: f"{tuple(r['config']['size_m'])} / {tuple(r['grid_shape'])}"),
        ("update ms (median / p95 / max)", lambda r: f"{r['update_ms_median']:.1f} / {r['update_ms_p95']:.1f} / {r['update_ms_max']:.1f}"),
        ("update CPU ms (median / mean)", lambda r: f"{r['update_cpu_ms_median']:.1f} / {r['update_cpu_ms_mean']:.1f}"),
        ("  shift / backproject / occupancy / esdf ms", lambda r: " / ".join(f"{v:.1f}" for v in r["stage_ms_median"].values())),
        ("  voxels rewritten per frame (median)", lambda r: f"{r['esdf_voxels_median']:.0f}"),
        ("reference full recompute ms (median)", lambda r: f"{r['reference_ms_median']:.1f}"),
        ("speedup (reference / ours)", lambda r: f"{r['speedup']:.1f}x"),
        ("incremental vs full max diff m", lambda r: f"{r['incremental_vs_full_max_diff_m']:.1e}"),
        ("max / mean abs error vs mesh m", lambda r: f"{r['max_abs_error_m']:.3f} / {r['mean_abs_error_m']:.3f}"),
        ("max optimistic error m (ours above truth)", lambda r: f"{r['max_optimistic_error_m']:.3f}"),
        ("seen-free points read free", lambda r: f"{100 * r['seen_free_points_read_free']:.1f} % of {r['error_points']}"),
        ("known share of the last view cone (0.5-7 m)", lambda r: f"{100 * r['known_fraction_of_view_cone']:.1f} %"),
        ("query of 40 points us", lambda r: f"{r['query_us_40_points']:.1f}"),
    ]
    if "same_map_as_no_cull" in results.get("after", {}):
        rows.append(("same map as 'after, no cull' (every frame)", lambda r: str(r.get("same_map_as_no_cull", "-"))))
    width = max(len(r[0]) for r in rows)
    names = list(results)
    print(f"ESDF benchmark: {args.frames - 1} frames 640x480 ({100 * no_reading:.1f} % pixels without a reading), seed {args.seed}")
    print(f"  {'':<{width}}  " + "  ".join(f"{n:<28}" for n in names))
    for label, fmt in rows:
        print(f"  {label:<{width}}  " + "  ".join(f"{fmt(results[n]):<28}" for n in names))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"no_reading_pixel_share": no_reading, "results": results, "args": vars(args)}, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
