"""Benchmark of the embedded world: render cost now, closed-loop cost once the oracle exists.

Measured in the same run, per committed scene (or ``--scenes``), at the benchmark resolution
(640 x 427, 90 x 60 deg) on ``--threads`` Embree threads (1 = the one-core budget):

- ``render_ms_median``: :meth:`Renderer.render` + :meth:`Renderer.annotate` (RGB, z-depth,
  instance and semantic ids, the VLM annotation) from seeded collision-free poses, with the
  scene's ray-casting structure and camera rays built once (the fast path);
- ``render_cpu_ms_median``: the same frames in CPU time of this process (less sensitive to
  other processes sharing the cores than wall time);
- ``cast_ms_median``: Open3D ``cast_rays`` alone on the same rays, the floor our shading adds to;
- ``half_res_ms_median``: the same frames at half resolution (320 x 214, ``camera.scaled(0.5)``),
  the cheaper option for frames that only feed the ESDF;
- ``realistic_ms_median`` / ``realistic_cpu_ms_median``: the same frames under the ``realistic``
  realism profile (the D435 depth model: material holes, flying pixels, quadratic noise,
  range gate; ``docs/realism.md``), against the ideal ``render_ms_median`` of the same run;
- ``naive_ms_median`` (reference): the same frame when nothing is kept between frames (meshes,
  ``RaycastingScene`` and camera rays rebuilt each frame), measured on ``--naive-frames`` frames.

Actors (``actors``, issue 19): for each scene with walkers, the same seeded poses rendered
(:meth:`Renderer.render` + :meth:`Renderer.annotate`) at the same instants (0.5 s apart) by two
renderers built in this run: the scene as committed (walkers cast in their own frames and
composited, ``with_actors_ms_median``) and the same scene without its actor objects
(``static_ms_median``); ``ratio`` is with / without (the target: at most 1.2), and
``actor_px_mean`` how many pixels per frame show a walker. Poses alternate between the seeded
free poses and poses looking at a walker from 4-8 m, so walkers are in view in half the frames.

Tracking (``tracking``): how far the executed (true) path lies from a straight 0.6 m/s plan
over 25 s, and how far the pilot's estimate lies from the truth, under each profile, five seeds,
in an outdoor scene (``park``, gusts) and an indoor one (``corridor``, lag and drift only).

Closed loop (``step_ms_median``: one 0.1 s control step of the oracle pilot: render when due,
ESDF update, MPC, vehicle; ``realtime_factor``: simulated seconds per wall second over whole
episodes) flies the registry's ``oracle`` method (:mod:`onfly.bench.registry`) through
:func:`onfly.bench.episode.run_episode` on the first checked task of up to ``--episodes``
scenes; ``realtime_factor_cpu`` is the same with this process's CPU time (robust to other
processes on shared cores, but it counts every thread). If the oracle, the episode loop or
checked tasks are missing, those two keys are
**left out of the JSON** and the reason is printed and written as ``closed_loop_not_measured``.
Nothing is estimated.

Run: ``.venv/bin/python experiments/bench_world.py --json /tmp/bench_world.json``
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from onfly.world import World, list_scenes
from onfly.world.geometry import SceneGeometry
from onfly.world.render import RenderConfig, Renderer, default_camera
from onfly.world.scene import load_scene, resolve_scene
from planning.frames import body_transform, cam_transform_from_body


def free_poses(world: World, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``n`` camera poses at collision-free points (clearance >= 0.5 m) inside the bounds,
    starting with the start pose; random yaw, level camera."""
    b = world.scene.bounds
    s = world.scene.start
    poses = [cam_transform_from_body(body_transform(s.position_m, s.yaw_rad))]
    while len(poses) < n:
        P = rng.uniform(b.min_m, b.max_m, size=(64, 3))
        P[:, 2] = rng.uniform(b.min_m[2] + 0.5, min(b.max_m[2], b.min_m[2] + 4.0), size=64)
        ok = P[world.collision.clearance(P) >= 0.5]
        for p in ok[: n - len(poses)]:
            poses.append(cam_transform_from_body(body_transform(p, rng.uniform(-np.pi, np.pi))))
    return poses


def bench_scene(name: str, frames: int, naive_frames: int, threads: int, seed: int) -> dict:
    """Median render / cast / naive times (ms) of one scene from seeded free poses."""
    cfg = RenderConfig(threads=threads)
    world = World.from_scene(name, render_config=cfg)
    poses = free_poses(world, frames, np.random.default_rng(seed))
    r = world.renderer
    r.render(poses[0])  # first call builds Embree's BVH lazily; keep it out of the timings
    fast, cast, fast_cpu = [], [], []
    for T in poses:
        t0, c0 = time.perf_counter(), time.process_time()
        out = r.render(T)
        r.annotate(out)
        fast.append(time.perf_counter() - t0)
        fast_cpu.append(time.process_time() - c0)
        t0 = time.perf_counter()
        world.geometry.cast(r.world_rays(T), threads=threads)
        cast.append(time.perf_counter() - t0)
    real_r = World.from_scene(name, render_config=cfg, realism="realistic", seed=seed).renderer
    real_r.render(poses[0])
    real, real_cpu = [], []
    for k, T in enumerate(poses):
        t0, c0 = time.perf_counter(), time.process_time()
        real_r.annotate(real_r.render(T, noise_key=k))
        real.append(time.perf_counter() - t0)
        real_cpu.append(time.process_time() - c0)
    half_r = world.renderer_for(world.camera.scaled(0.5))
    half_r.render(poses[0])
    half = []
    for T in poses:
        t0 = time.perf_counter()
        half_r.annotate(half_r.render(T))
        half.append(time.perf_counter() - t0)
    naive = []
    path = resolve_scene(name)
    for T in poses[:naive_frames]:
        t0 = time.perf_counter()
        rn = Renderer(SceneGeometry(load_scene(path)), default_camera(), cfg)
        rn.annotate(rn.render(T))
        naive.append(time.perf_counter() - t0)
    return {
        "scene": name,
        "triangles": world.geometry.triangle_count,
        "frames": len(fast),
        "render_ms_median": 1e3 * float(np.median(fast)),
        "render_ms_p90": 1e3 * float(np.percentile(fast, 90)),
        "render_cpu_ms_median": 1e3 * float(np.median(fast_cpu)),
        "cast_ms_median": 1e3 * float(np.median(cast)),
        "half_res_ms_median": 1e3 * float(np.median(half)),
        "realistic_ms_median": 1e3 * float(np.median(real)),
        "realistic_cpu_ms_median": 1e3 * float(np.median(real_cpu)),
        "naive_ms_median": 1e3 * float(np.median(naive)),
    }


def bench_actors(name: str, frames: int, threads: int, seed: int) -> dict | None:
    """Render cost with and without the scene's actors (same poses, same times, same run)."""
    from dataclasses import replace

    scene = load_scene(resolve_scene(name))
    if not scene.actors:
        return None
    cfg = RenderConfig(threads=threads)
    world = World(scene, render_config=cfg)
    rng = np.random.default_rng(seed)
    poses = free_poses(world, frames, rng)
    times = 0.5 * np.arange(frames)
    # every other frame looks at a walker from 4-8 m at flight height
    g = world.geometry
    for k in range(1, frames, 2):
        a = g.actors[(k // 2) % len(g.actors)]
        c = a.pose(times[k]).position_m
        for _ in range(50):
            ang, dist = rng.uniform(-np.pi, np.pi), rng.uniform(4.0, 8.0)
            p = c + np.array([dist * np.cos(ang), dist * np.sin(ang), 1.5])
            if world.scene.bounds.contains(p[None])[0] and world.collision.clearance(p[None], times[k])[0] >= 0.5:
                poses[k] = cam_transform_from_body(body_transform(p, ang + np.pi))
                break
    static = Renderer(SceneGeometry(replace(scene, objects=scene.static_objects)), world.camera, cfg)
    moving = world.renderer
    for r in (static, moving):
        r.render(poses[0], t_s=0.0)  # build Embree's BVHs outside the timings
    t_static, t_moving, c_static, c_moving, px = [], [], [], [], []
    for T, t in zip(poses, times):
        for r, wall, cpu in ((static, t_static, c_static), (moving, t_moving, c_moving)):
            t0, c0 = time.perf_counter(), time.process_time()
            out = r.render(T, t_s=float(t))
            r.annotate(out)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            if r is moving:
                px.append(int(np.isin(out.instance_ids, [a.instance_id for a in g.actors]).sum()))
    return {
        "scene": name,
        "actors": len(g.actors),
        "actor_triangles": g.total_triangle_count - g.triangle_count,
        "frames": frames,
        "static_ms_median": 1e3 * float(np.median(t_static)),
        "with_actors_ms_median": 1e3 * float(np.median(t_moving)),
        "ratio": float(np.median(t_moving) / np.median(t_static)),
        "static_cpu_ms_median": 1e3 * float(np.median(c_static)),
        "with_actors_cpu_ms_median": 1e3 * float(np.median(c_moving)),
        "ratio_cpu": float(np.median(c_moving) / np.median(c_static)),
        "actor_px_mean": float(np.mean(px)),
    }


def _line_plan(p0: np.ndarray, seconds: float = 30.0, speed_mps: float = 0.6, dt_s: float = 0.1):
    """A straight plan along +x from rest: 0.6 m/s^2 up to ``speed_mps``, then cruise."""
    from planning.trajectory import Trajectory

    n = int(seconds / dt_s)
    p, v, a = np.zeros((n + 1, 3)), np.zeros((n + 1, 3)), np.zeros((n, 3))
    s = sp = 0.0
    for k in range(n):
        acc = min(0.6, (speed_mps - sp) / dt_s)
        s, sp = s + sp * dt_s + 0.5 * acc * dt_s**2, sp + acc * dt_s
        a[k, 0], p[k + 1, 0], v[k + 1, 0] = acc, s, sp
    return Trajectory(0.0, dt_s, p + p0, v, np.zeros(n + 1), a, np.zeros(n))


def tracking(seeds: int = 5, seconds: float = 25.0) -> list[dict]:
    """Truth - plan and estimate - truth distances (m) per profile and scene (no rendering)."""
    rows = []
    for scene in ("park", "corridor"):
        for profile in ("ideal", "realistic"):
            err, est = [], []
            for seed in range(seeds):
                w = World.from_scene(scene, realism=profile, seed=seed)
                plan = _line_plan(w.state.p.copy())
                w.set_trajectory(plan)
                for _ in range(int(seconds / 0.1)):
                    ws = w.step(0.1)
                    err.append(float(np.linalg.norm(ws.state.p - plan.sample(ws.state.t_s)[0])))
                    est.append(float(np.linalg.norm(w.estimate.p - ws.state.p)))
            rows.append({"scene": scene, "realism": profile, "track_err_m_mean": float(np.mean(err)),
                         "track_err_m_p95": float(np.percentile(err, 95)), "track_err_m_max": float(np.max(err)),
                         "estimate_err_m_mean": float(np.mean(est)), "estimate_err_m_final": est[-1]})
    return rows


def closed_loop(scenes: list[str], episodes: int) -> tuple[dict | None, str]:
    """Time oracle episodes on the first committed tasks of the selected scenes.

    Returns (results, "") or (None, why nothing was measured). ``step_ms_median`` is the wall
    time between consecutive control periods (render when due, method step with ESDF update and
    MPC, vehicle and collision step); ``realtime_factor`` is total simulated over total wall time.
    """
    if episodes <= 0:
        return None, "--episodes 0"
    try:
        from onfly.bench.episode import EpisodeStep, run_episode
        from onfly.bench.registry import make_method
        from onfly.bench.tasks import load_tasks
    except ImportError as exc:
        return None, f"oracle pilot / benchmark modules not available ({exc})"
    try:
        tasks = [t for t in load_tasks() if t.scene in scenes and t.reference is not None]
    except (FileNotFoundError, ValueError) as exc:
        return None, f"tasks could not be loaded ({exc})"
    if not tasks:
        return None, "no checked tasks for the selected scenes"
    by_scene: dict[str, list] = {}
    for t in tasks:
        by_scene.setdefault(t.scene, []).append(t)
    chosen = [ts[0] for ts in by_scene.values()][:episodes]
    steps: list[float] = []
    sim_s = wall_s = cpu_s = 0.0
    rows = []
    for task in chosen:
        world = World.from_scene(task.scene)
        last = [time.perf_counter()]
        first = len(steps)

        def observer(_: EpisodeStep) -> None:
            now = time.perf_counter()
            steps.append(now - last[0])
            last[0] = now

        c0 = time.process_time()
        res = run_episode(world, make_method("oracle", "sim:nominal", 0), instruction=task.instruction, goal=task.goal_region,
                          reference_path_m=task.reference.path_length_m, seed=0, error_model="none",
                          privileged=task.privileged_goal(), observer=observer)
        cpu_s += time.process_time() - c0
        del steps[first]  # the first interval includes method reset
        sim_s += res.sim_s
        wall_s += res.wall_s
        rows.append({"task": task.task_id, "end_reason": res.end_reason, "sim_s": res.sim_s, "wall_s": res.wall_s})
    return {"step_ms_median": 1e3 * float(np.median(steps)), "realtime_factor": sim_s / wall_s, "realtime_factor_cpu": sim_s / cpu_s, "episodes": rows}, ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Embedded-world render benchmark (and closed loop once the oracle exists).")
    ap.add_argument("--scenes", nargs="*", default=None, help="scene names (default: all committed)")
    ap.add_argument("--frames", type=int, default=30, help="frames per scene for the fast path")
    ap.add_argument("--naive-frames", type=int, default=5, help="frames per scene for the rebuild-every-frame reference")
    ap.add_argument("--threads", type=int, default=1, help="Embree threads (1 = one core)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=3, help="oracle episodes for the closed-loop columns (one task per scene)")
    ap.add_argument("--json", type=str, default=None, help="write the results here")
    ap.add_argument("--only-actors", action="store_true", help="only the actors section (render with and without walkers)")
    args = ap.parse_args(argv)
    scenes = args.scenes or list_scenes()
    cam = default_camera()
    actor_rows = [r for r in (bench_actors(s, args.frames, args.threads, args.seed) for s in scenes) if r is not None]
    print(f"actors: camera {cam.width} x {cam.height}, threads {args.threads}, {args.frames} frames per scene (half of them looking at a walker)")
    print(f"{'scene':<18} {'actors':>6} {'tris':>5} {'static ms':>10} {'actors ms':>10} {'ratio':>6} {'cpu ratio':>9} {'actor px':>9}")
    for r in actor_rows:
        print(f"{r['scene']:<18} {r['actors']:>6} {r['actor_triangles']:>5} {r['static_ms_median']:>10.1f} {r['with_actors_ms_median']:>10.1f} "
              f"{r['ratio']:>6.3f} {r['ratio_cpu']:>9.3f} {r['actor_px_mean']:>9.0f}")
    if args.only_actors:
        if args.json:
            with open(args.json, "w") as fh:
                json.dump({"camera": [cam.width, cam.height], "threads": args.threads, "actors": actor_rows,
                           "machine": platform.processor() or platform.machine()}, fh, indent=2)
        return 0
    rows = [bench_scene(s, args.frames, args.naive_frames, args.threads, args.seed) for s in scenes]
    print(f"camera {cam.width} x {cam.height}, threads {args.threads}, {args.frames} frames per scene")
    print(f"{'scene':<14} {'tris':>5} {'render ms':>10} {'p90 ms':>8} {'cpu ms':>7} {'cast ms':>8} {'half ms':>8} {'real ms':>8} {'real cpu':>8} "
          f"{'naive ms':>9} {'naive/fast':>10}")
    for r in rows:
        print(f"{r['scene']:<14} {r['triangles']:>5} {r['render_ms_median']:>10.1f} {r['render_ms_p90']:>8.1f} {r['render_cpu_ms_median']:>7.1f} "
              f"{r['cast_ms_median']:>8.1f} {r['half_res_ms_median']:>8.1f} {r['realistic_ms_median']:>8.1f} {r['realistic_cpu_ms_median']:>8.1f} "
              f"{r['naive_ms_median']:>9.1f} {r['naive_ms_median'] / r['render_ms_median']:>10.2f}")
    result = {
        "camera": [cam.width, cam.height],
        "threads": args.threads,
        "render_ms_median": float(np.median([r["render_ms_median"] for r in rows])),
        "render_cpu_ms_median": float(np.median([r["render_cpu_ms_median"] for r in rows])),
        "cast_ms_median": float(np.median([r["cast_ms_median"] for r in rows])),
        "half_res_ms_median": float(np.median([r["half_res_ms_median"] for r in rows])),
        "realistic_ms_median": float(np.median([r["realistic_ms_median"] for r in rows])),
        "realistic_cpu_ms_median": float(np.median([r["realistic_cpu_ms_median"] for r in rows])),
        "naive_ms_median": float(np.median([r["naive_ms_median"] for r in rows])),
        "per_scene": rows,
        "actors": actor_rows,
        "machine": platform.processor() or platform.machine(),
    }
    print(f"all scenes: render_ms_median {result['render_ms_median']:.1f} (cpu {result['render_cpu_ms_median']:.1f}, cast alone {result['cast_ms_median']:.1f}, "
          f"naive reference {result['naive_ms_median']:.1f})")
    print(f"realistic profile: render_ms_median {result['realistic_ms_median']:.1f} (cpu {result['realistic_cpu_ms_median']:.1f}), "
          f"{result['realistic_cpu_ms_median'] / result['render_cpu_ms_median']:.2f}x the ideal cpu time")
    result["tracking"] = tracking()
    print(f"{'scene':<10} {'realism':<10} {'truth-plan mean m':>18} {'p95 m':>7} {'max m':>7} {'estimate-truth mean m':>22}")
    for r in result["tracking"]:
        print(f"{r['scene']:<10} {r['realism']:<10} {r['track_err_m_mean']:>18.3f} {r['track_err_m_p95']:>7.3f} {r['track_err_m_max']:>7.3f} "
              f"{r['estimate_err_m_mean']:>22.3f}")
    loop, why = closed_loop(scenes, args.episodes)
    if loop is None:
        result["closed_loop_not_measured"] = why
        print(f"closed loop: not measured: {why}")
    else:
        result.update(loop)
        print(f"closed loop: step_ms_median {loop['step_ms_median']:.1f}, realtime_factor {loop['realtime_factor']:.1f} (cpu time: {loop['realtime_factor_cpu']:.1f}) over {len(loop['episodes'])} episodes")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
