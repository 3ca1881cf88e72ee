"""Why an episode ended as it did: re-fly benchmark episodes with an observer and print, per
episode, the end reason beside the figures that explain a collision or a bound crossing.

For each control period the observer records (world ENU, metres):

- ``clearance``: the true body centre's distance to the scene mesh (exact, Open3D);
- ``est_err``: ``|estimate - truth|`` (the odometry's drift and noise);
- ``track_est``: ``|plan(t) - estimate|``, the tracking error the pilot can measure (the plan
  the vehicle flew over the last period, sampled at ``t``, against the estimated position);
- ``track_true``: ``|plan(t) - truth|``, what the vehicle really missed the plan by;
- ``pred_clear``: the planner's predicted clearance of the plan in its own map (when the
  method exposes a pilot with a last plan), and the plan's fallback.

Episodes are flown exactly as the benchmark flies them (``onfly.bench.runner.fly_task`` with
the config's seed, method options, episode and world settings), so the end reasons match a
benchmark run of the same config and code.

Run (a handful of tasks; each episode costs what a benchmark episode costs)::

    PYTHONPATH=$PWD python experiments/diagnose_episodes.py \
        --config experiments/configs/quick_realistic.toml --method onfly \
        --tasks park-l03,plaza-o06 --json /tmp/diag.json

``--tasks`` defaults to every task of the config (its ``[bench.tasks]`` selection).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from onfly.bench.runner import BenchConfig, check_bench, episode_seed, fly_task


def _fly(task, method: str, config: BenchConfig) -> dict:
    rows: list[dict] = []
    holder: dict = {}
    last_traj = {"traj": None}

    def on_world(world) -> None:
        holder["world"] = world

    def observe(step) -> None:
        world = holder["world"]
        truth = step.state.p
        est = step.estimate.p if step.estimate is not None else truth
        traj = last_traj["traj"]
        if traj is not None:
            p_ref = traj.sample(step.t_s)[0]
            track_est = float(np.linalg.norm(p_ref - est))
            track_true = float(np.linalg.norm(p_ref - truth))
        else:
            track_est = track_true = float("nan")
        pilot = getattr(step.method, "pilot", None)
        plan = getattr(pilot, "_last_plan", None) if pilot is not None else None
        rows.append(
            {
                "t": float(step.t_s),
                "truth": truth.tolist(),
                "clearance": float(world.collision.clearance(truth[None])[0]),
                "est_err": float(np.linalg.norm(est - truth)),
                "track_est": track_est,
                "track_true": track_true,
                "speed": float(np.linalg.norm(step.state.v)),
                "pred_clear": None if plan is None else float(plan.min_predicted_clearance_m),
                "fallback": None if plan is None else plan.fallback.value,
                "mode": None if pilot is None else pilot.mode.value,
            }
        )
        if step.output is not None and step.output.trajectory is not None:
            last_traj["traj"] = step.output.trajectory

    seed = episode_seed(config.seed, task.task_id, 0)
    t0 = time.perf_counter()
    result, extras = fly_task(
        task, method, vlm=config.vlm, seed=seed, options=config.method_options_for(method), episode=dict(config.episode),
        world=config.world_settings(), observer=observe, on_world=on_world,
    )
    world = holder["world"]
    end = {
        "task": task.task_id,
        "end_reason": result.end_reason,
        "success": bool(result.metrics.success),
        "min_clearance_m": extras["min_clearance_m"],
        "collision": result.collision,
        "final_truth": world.state.p.tolist(),
        "bounds": [world.scene.bounds.min_m.tolist(), world.scene.bounds.max_m.tolist()],
        "wall_s": time.perf_counter() - t0,
        "planner_fallbacks": result.method_summary.get("planner_fallbacks"),
    }
    track = np.array([r["track_true"] for r in rows], float)
    track_e = np.array([r["track_est"] for r in rows], float)
    est = np.array([r["est_err"] for r in rows], float)
    end["track_true_mean_m"] = float(np.nanmean(track)) if len(track) else float("nan")
    end["track_true_max_m"] = float(np.nanmax(track)) if len(track) else float("nan")
    end["track_est_max_m"] = float(np.nanmax(track_e)) if len(track_e) else float("nan")
    end["est_err_final_m"] = float(est[-1]) if len(est) else float("nan")
    end["last_rows"] = rows[-15:]
    return end


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", required=True)
    ap.add_argument("--method", default="onfly")
    ap.add_argument("--tasks", default="", help="comma-separated task ids (default: the config's selection)")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    config = BenchConfig.from_toml(args.config)
    tasks = check_bench(config, reach_vlm=False)
    if args.tasks:
        want = [t.strip() for t in args.tasks.split(",") if t.strip()]
        by_id = {t.task_id: t for t in tasks}
        missing = [t for t in want if t not in by_id]
        if missing:
            print(f"--tasks: not in the config's selection: {missing}", file=sys.stderr)
            return 2
        tasks = [by_id[t] for t in want]
    out = []
    print(f"{'task':22s} {'end':14s} {'minclr':>6s} {'trk mean':>8s} {'trk max':>7s} {'trkE max':>8s} {'est err':>7s}  last: clr trk mode fallback")
    for task in tasks:
        rec = _fly(task, args.method, config)
        out.append(rec)
        last = rec["last_rows"][-1] if rec["last_rows"] else {}
        print(
            f"{rec['task']:22s} {rec['end_reason']:14s} {rec['min_clearance_m']:6.2f} {rec['track_true_mean_m']:8.2f} "
            f"{rec['track_true_max_m']:7.2f} {rec['track_est_max_m']:8.2f} {rec['est_err_final_m']:7.2f}  "
            f"{last.get('clearance', float('nan')):.2f} {last.get('track_true', float('nan')):.2f} {last.get('mode')} {last.get('fallback')}"
            + (f"  hit {rec['collision']['object']}" if rec["collision"] else "")
            + (f"  at {np.round(rec['final_truth'], 2).tolist()} bounds {rec['bounds']}" if rec["end_reason"] == "out_of_bounds" else ""),
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
