"""``onfly scenes``: list the committed embedded-world scenes."""

from __future__ import annotations

import argparse
import json

from onfly.cli import echo


NAME = "scenes"
HELP = "list the committed scenes with their object counts and bounds"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--objects", action="store_true", help="also list each scene's target objects")


def run(args: argparse.Namespace) -> int:
    from onfly.world.geometry import SceneGeometry
    from onfly.world.scene import list_scenes, load_scene, resolve_scene

    rows = []
    for name in list_scenes():
        path = resolve_scene(name)
        scene = load_scene(path)
        geometry = SceneGeometry(scene)
        rows.append(
            {
                "name": scene.name,
                "objects": len(scene.objects),
                "targets": len(scene.targets),
                "actors": len(scene.actors),
                "triangles": geometry.total_triangle_count,
                "bounds_min_m": scene.bounds.min_m.tolist(),
                "bounds_max_m": scene.bounds.max_m.tolist(),
                "start_m": scene.start.position_m.tolist(),
                "target_names": [o.name for o in scene.targets],
                "path": str(path),
            }
        )
    if args.json:
        echo(json.dumps(rows, indent=2))
        return 0
    echo(f"{'scene':<18} {'objects':>7} {'targets':>7} {'actors':>6} {'triangles':>9}  bounds (min .. max, m)")
    for r in rows:
        lo = ", ".join(f"{v:g}" for v in r["bounds_min_m"])
        hi = ", ".join(f"{v:g}" for v in r["bounds_max_m"])
        echo(f"{r['name']:<18} {r['objects']:>7} {r['targets']:>7} {r['actors']:>6} {r['triangles']:>9}  ({lo}) .. ({hi})")
        if args.objects:
            echo("    " + "; ".join(r["target_names"]))
    return 0
