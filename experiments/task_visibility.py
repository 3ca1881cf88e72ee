"""Which tasks start with their goal in view, and how every method of a run does on each side.

A task *starts in view* when its goal object (:func:`onfly.bench.checker.goal_target`: the
goal object, else the last named target) has at least one pixel in the first rendered frame at
the start pose, at the benchmark's camera (``[world]`` of the config). Where it does not, a
method has to search: the simulated VLM then points by its documented exploration rule
(``vlm/sim/error_model.py``), TypeFly has its ``find`` skill (turn in place), and OnFly has
its pilot's search (``onfly/search.py``, our addition; the paper's pilot, ablation
``onfly_no_search``, has none).

With ``--runs DIR`` (a benchmark or paper-tables run folder: every ``episodes.jsonl`` below it)
it prints, per method and error model, SR / CR over all episodes and SR on each side, with the
failure classes of the out-of-view episodes. Records are counted as they are in the files
(the latest record of each episode key).

With ``--reference DIR`` as well (a run of the oracle, which flies the reference path with the
goal known) it splits each side again by how long the oracle flew the task (``--edges``,
seconds): the two sides of a task set need not be equally long, and a search costs time that
a long route does not have. A task the reference did not fly, or failed, is left out of that
table.

The tasks are the config's selection (``[bench.tasks]``: files, ids, scenes, kinds, count), so
``experiments/configs/hard.toml`` gives the harder set of ``onfly/data/tasks/hard/``. Run::

    .venv/bin/python experiments/task_visibility.py --config experiments/configs/paper_tables.toml \\
        [--runs runs/paper_final] [--json PATH]
    .venv/bin/python experiments/task_visibility.py --config experiments/configs/hard.toml --runs runs/hard \\
        [--reference runs/hard_oracle --edges 30,36]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from onfly.bench.checker import goal_target
from onfly.bench.runner import EPISODES_FILE, BenchConfig, read_records, world_camera
from onfly.bench.tasks import Task, load_tasks, select_tasks
from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.trajectory import VehicleState

__all__ = ["starts_in_view", "split_by_view", "split_by_length", "reference_times", "config_tasks", "main"]


def starts_in_view(tasks: Iterable[Task], camera: PinholeCamera) -> dict[str, bool]:
    """``{task id: goal object has a pixel in the first frame at the start pose}``.

    The first frame is the one an episode's world renders first (frame key 0, the world's
    default render settings); the world of each scene is built once."""
    out: dict[str, bool] = {}
    worlds: dict[str, World] = {}
    for t in tasks:
        world = worlds.get(t.scene_ref)
        if world is None:  # an external scene by its file, a committed one by name
            world = worlds[t.scene_ref] = World.from_scene(t.scene_ref, camera=camera)
        start = VehicleState(0.0, t.start.position_m.copy(), np.zeros(3), float(t.start.yaw_rad))
        r = world.renderer.render(world.T_world_cam(start), noise_key=0)
        ann = world.renderer.annotate(r)
        present = set(np.unique(ann.instance_ids).tolist())
        name = goal_target(t)
        out[t.task_id] = any(o.name == name and iid in present for iid, o in ann.objects.items())
    return out


def config_tasks(bench: BenchConfig) -> list[Task]:
    """The tasks a benchmark config selects, as the runner selects them."""
    return select_tasks(load_tasks(bench.task_files), ids=bench.task_ids, scenes=bench.scenes, kinds=bench.kinds, count=bench.count)


def _latest(records: Iterable[dict]) -> list[dict]:
    latest: dict[str, dict] = {}
    for r in records:
        if "metrics" in r and "key" in r:
            latest[r["key"]] = r
    return list(latest.values())


def split_by_view(records: Iterable[dict], in_view: dict[str, bool]) -> list[dict]:
    """One row per (method, error model): episodes, SR %, CR % over all episodes, SR % and
    episodes on each side, and the failure classes of the out-of-view episodes. Records of
    tasks missing from ``in_view`` are skipped."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in _latest(records):
        if r.get("task") in in_view:
            groups.setdefault((r["method"], r.get("error_model", "?")), []).append(r)

    def sr(xs: list[dict]) -> float | None:
        return 100.0 * sum(bool(x["metrics"]["success"]) for x in xs) / len(xs) if xs else None

    rows = []
    for (method, em), rs in sorted(groups.items()):
        seen = [r for r in rs if in_view[r["task"]]]
        hidden = [r for r in rs if not in_view[r["task"]]]
        rows.append(
            {
                "method": method,
                "error_model": em,
                "episodes": len(rs),
                "sr_pct": sr(rs),
                "cr_pct": 100.0 * sum(bool(r["metrics"]["collided"]) for r in rs) / len(rs),
                "in_view_episodes": len(seen),
                "sr_in_view_pct": sr(seen),
                "out_of_view_episodes": len(hidden),
                "sr_out_of_view_pct": sr(hidden),
                "out_of_view_failures": dict(Counter(r["failure"] for r in hidden if r.get("failure"))),
            }
        )
    return rows


def reference_times(records: Iterable[dict]) -> dict[str, float]:
    """``{task id: flight time, seconds}`` of the reference's successful episodes (the latest
    record of each key; the mean over runs). Raises ValueError when the records hold more
    than one method: a reference is one method's run."""
    rs = _latest(records)
    methods = {r["method"] for r in rs}
    if len(methods) > 1:
        raise ValueError(f"a reference run holds one method, this one holds {sorted(methods)}")
    times: dict[str, list[float]] = {}
    for r in rs:
        if r["metrics"]["success"]:
            times.setdefault(r["task"], []).append(float(r["metrics"]["flight_time_s"]))
    return {t: float(np.mean(v)) for t, v in times.items()}


def _bin_label(edges: Sequence[float], k: int) -> str:
    lo = "0" if k == 0 else f"{edges[k - 1]:g}"
    return f"> {lo}" if k == len(edges) else f"{lo}-{edges[k]:g}"


def split_by_length(records: Iterable[dict], in_view: dict[str, bool], ref_s: dict[str, float], edges: Sequence[float]) -> list[dict]:
    """One row per (method, error model, reference-time bin): SR % and episodes on each side,
    for the tasks whose reference flight time (``ref_s``, seconds) falls in the bin; bins are
    ``(0, e0], (e0, e1], ..., (e_last, inf)``. Tasks missing from ``in_view`` or ``ref_s`` are
    skipped."""
    edges = [float(e) for e in edges]
    if any(not np.isfinite(e) or e <= 0 for e in edges) or edges != sorted(set(edges)):
        raise ValueError(f"edges must be increasing positive seconds, got {edges}")
    groups: dict[tuple[str, str, int, bool], list[bool]] = {}
    for r in _latest(records):
        t = r.get("task")
        if t not in in_view or t not in ref_s:
            continue
        k = int(np.searchsorted(edges, ref_s[t], side="left"))
        groups.setdefault((r["method"], r.get("error_model", "?"), k, in_view[t]), []).append(bool(r["metrics"]["success"]))
    rows = []
    for method, em, k in sorted({g[:3] for g in groups}):
        row = {"method": method, "error_model": em, "reference_s": _bin_label(edges, k)}
        for side, name in ((True, "in_view"), (False, "out_of_view")):
            xs = groups.get((method, em, k, side), [])
            row[f"{name}_episodes"] = len(xs)
            row[f"sr_{name}_pct"] = 100.0 * sum(xs) / len(xs) if xs else None
        rows.append(row)
    return rows


def format_length_rows(rows: Sequence[dict]) -> str:
    lines = [
        "| method | error model | reference flight s | SR % in view (n) | SR % out of view (n) |",
        "| --- | --- | --- | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['error_model']} | {r['reference_s']} | {_f(r['sr_in_view_pct'])} ({r['in_view_episodes']}) | "
            f"{_f(r['sr_out_of_view_pct'])} ({r['out_of_view_episodes']}) |"
        )
    return "\n".join(lines)


def _f(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1f}"


def format_rows(rows: Sequence[dict]) -> str:
    lines = [
        "| method | error model | episodes | SR % | CR % | SR % in view (n) | SR % out of view (n) | out-of-view failures |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in rows:
        fails = ", ".join(f"{k} {v}" for k, v in sorted(r["out_of_view_failures"].items())) or "-"
        lines.append(
            f"| {r['method']} | {r['error_model']} | {r['episodes']} | {_f(r['sr_pct'])} | {_f(r['cr_pct'])} | "
            f"{_f(r['sr_in_view_pct'])} ({r['in_view_episodes']}) | {_f(r['sr_out_of_view_pct'])} ({r['out_of_view_episodes']}) | {fails} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", required=True, help="benchmark or paper-tables TOML (its [world] sets the camera)")
    ap.add_argument("--runs", default=None, metavar="DIR", help="split the episodes of this run folder by start visibility")
    ap.add_argument("--reference", default=None, metavar="DIR", help="an oracle run of the same tasks: split each side by its flight time")
    ap.add_argument("--edges", default="30,36", help="reference flight-time bin edges, seconds, comma-separated (default 30,36)")
    ap.add_argument("--json", default=None, help="also write the flags (and rows) as JSON here")
    args = ap.parse_args(argv)
    if args.reference and not args.runs:
        ap.error("--reference needs --runs")
    try:
        edges = [float(x) for x in args.edges.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--edges: comma-separated seconds expected, got {args.edges!r}")
    try:
        import tomllib

        data = tomllib.loads(Path(args.config).read_text())
        data.pop("paper_tables", None)
        bench = BenchConfig.from_dict(data, source=args.config)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    camera = world_camera(bench.world_settings())
    flags = starts_in_view(config_tasks(bench), camera)
    n_in = sum(flags.values())
    print(f"{n_in} of {len(flags)} tasks start with their goal in view ({camera.width} x {camera.height} px)")
    print("out of view: " + ", ".join(sorted(t for t, v in flags.items() if not v)))
    out: dict = {"camera_px": [camera.width, camera.height], "in_view": flags}
    if args.runs:
        records = [r for p in sorted(Path(args.runs).rglob(EPISODES_FILE)) for r in read_records(p)]
        rows = split_by_view(records, flags)
        print()
        print(format_rows(rows))
        out["rows"] = rows
        if args.reference:
            try:
                ref = reference_times(r for p in sorted(Path(args.reference).rglob(EPISODES_FILE)) for r in read_records(p))
                if not ref:
                    raise ValueError(f"no successful episode under {args.reference}")
                length_rows = split_by_length(records, flags, ref, edges)
            except ValueError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            print()
            print(f"by the reference's flight time ({len(ref)} tasks it flew to success)")
            print(format_length_rows(length_rows))
            out["reference_s"] = ref
            out["length_rows"] = length_rows
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
