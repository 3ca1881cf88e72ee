"""Weight-tuning example: sweep two planner weights over a grid, compare closed-loop flights.

Every grid cell builds a :class:`planning.planner_config.PlannerConfig` from the TOML's
``[planner]`` table with the two ``[sweep]`` fields set, and flies the same seeded obstacle
scenes (``[scenes]``) in closed loop (:func:`planning.planner.run_closed_loop`: perfect
tracking of each step's first command). Per cell it reports

* ``reached``: episodes that ended within 0.15 m of the goal, at rest;
* ``min_clearance_m``: the smallest exact distance to the obstacles along all executed paths
  (sampled 8 times per control period) and ``mean_min_clearance_m`` (per-episode minimum,
  averaged);
* ``path_length_m`` and ``time_to_goal_s``: means over the episodes that reached the goal;
* ``step_ms_median``: wall time of one planner step.

Run: ``.venv/bin/python experiments/tune_planner.py --config experiments/configs/tune_planner.toml
[--json out.json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from planning.analytic_field import SCENE_KINDS, obstacle_scene
from planning.planner import Planner, run_closed_loop
from planning.planner_config import PlannerConfig, PlannerConfigError
from planning.trajectory import VehicleState


class TuneConfigError(ValueError):
    """A tuning TOML with a missing or invalid entry (the message names file and key)."""


def load(path: Path) -> dict:
    try:
        with path.open("rb") as fh:
            data = tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise TuneConfigError(f"cannot read {path}: {exc}") from exc
    sweep = data.get("sweep")
    if not isinstance(sweep, dict):
        raise TuneConfigError(f"{path}: missing [sweep] table")
    for key in ("x", "x_values", "y", "y_values"):
        if key not in sweep:
            raise TuneConfigError(f"{path}: [sweep] needs '{key}'")
    valid = set(PlannerConfig().to_dict())
    for axis in ("x", "y"):
        if sweep[axis] not in valid:
            raise TuneConfigError(f"{path}: [sweep] {axis} = {sweep[axis]!r} is not a PlannerConfig field")
        if not isinstance(sweep[f"{axis}_values"], list) or not sweep[f"{axis}_values"]:
            raise TuneConfigError(f"{path}: [sweep] {axis}_values must be a non-empty list")
    scenes = data.get("scenes", {})
    kinds = scenes.get("kinds", list(SCENE_KINDS))
    unknown = [k for k in kinds if k not in SCENE_KINDS]
    if unknown:
        raise TuneConfigError(f"{path}: [scenes] kinds {unknown} not in {SCENE_KINDS}")
    try:
        base = PlannerConfig.from_dict(data.get("planner", {}))
    except PlannerConfigError as exc:
        raise TuneConfigError(f"{path}: [planner] {exc}") from exc
    return {
        "base": base.to_dict(),
        "x": sweep["x"],
        "x_values": sweep["x_values"],
        "y": sweep["y"],
        "y_values": sweep["y_values"],
        "kinds": kinds,
        "per_kind": int(scenes.get("per_kind", 2)),
        "seed": int(scenes.get("seed", 0)),
        "time_limit_s": float(scenes.get("time_limit_s", 40.0)),
    }


def fly_cell(cfg: PlannerConfig, spec: dict) -> dict:
    planner = Planner(cfg)
    min_clear, per_episode, lengths, times, step_ms, reached, episodes = np.inf, [], [], [], [], 0, 0
    for seed in range(spec["seed"], spec["seed"] + spec["per_kind"]):
        for kind in spec["kinds"]:
            scene = obstacle_scene(kind, seed, clearance_m=cfg.d_safe_m)
            planner.reset()
            log = run_closed_loop(
                planner,
                VehicleState(0.0, scene.start, np.zeros(3), scene.start_yaw),
                scene.goal,
                scene.field,
                max_steps=int(spec["time_limit_s"] / cfg.dt_s),
            )
            episodes += 1
            d = float(scene.field.distance(log.sampled_path(8)).min())
            min_clear = min(min_clear, d)
            per_episode.append(d)
            step_ms.extend(r.solve_time_ms for r in log.results)
            if log.reached:
                reached += 1
                lengths.append(float(np.sum(np.linalg.norm(np.diff(log.p, axis=0), axis=1))))
                times.append(float(log.t_s[-1] - log.t_s[0]))
    return {
        "reached": reached,
        "episodes": episodes,
        "min_clearance_m": min_clear,
        "mean_min_clearance_m": float(np.mean(per_episode)),
        "path_length_m": float(np.mean(lengths)) if lengths else float("nan"),
        "time_to_goal_s": float(np.mean(times)) if times else float("nan"),
        "step_ms_median": float(np.median(step_ms)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, required=True, help="tuning TOML (see experiments/configs/tune_planner.toml)")
    ap.add_argument("--json", type=Path, help="write the table here")
    args = ap.parse_args()
    try:
        spec = load(args.config)
    except TuneConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = []
    t0 = time.perf_counter()
    for xv in spec["x_values"]:
        for yv in spec["y_values"]:
            try:
                cfg = PlannerConfig.from_dict({**spec["base"], spec["x"]: xv, spec["y"]: yv})
            except PlannerConfigError as exc:
                print(f"error: {args.config}: {exc}", file=sys.stderr)
                return 2
            rows.append({spec["x"]: xv, spec["y"]: yv, **fly_cell(cfg, spec)})
    header = (
        f"{spec['x']:>10} {spec['y']:>10} {'reached':>8} {'min clr m':>9} {'mean clr m':>10} "
        f"{'path m':>7} {'time s':>7} {'step ms':>8}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        print(
            f"{r[spec['x']]:>10g} {r[spec['y']]:>10g} {r['reached']:>4}/{r['episodes']:<3} "
            f"{r['min_clearance_m']:>9.3f} {r['mean_min_clearance_m']:>10.3f} {r['path_length_m']:>7.2f} "
            f"{r['time_to_goal_s']:>7.1f} {r['step_ms_median']:>8.2f}"
        )
    print(f"({len(rows)} cells, {rows[0]['episodes']} episodes each, {time.perf_counter() - t0:.0f} s)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"spec": spec, "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
