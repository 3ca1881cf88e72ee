"""The walker test scenes' shared parts: a person and a 10 m wide street (experiments/avoid_walker.py
flies the same street)."""

from __future__ import annotations

from onfly.world.scene import parse_scene


def person(motion: dict | None) -> dict:
    """A 1.73 m person (legs, torso, head) as scene object ``walker``, id 9, with ``motion``."""
    obj = {
        "name": "walker", "label": "person", "instance_id": 9, "color": "#C62828",
        "parts": [
            {"type": "cylinder", "base_m": [0, 0, 0], "radius_m": 0.2, "height_m": 0.85, "segments": 8},
            {"type": "cylinder", "base_m": [0, 0, 0.85], "radius_m": 0.24, "height_m": 0.62, "segments": 8},
            {"type": "sphere", "center_m": [0, 0, 1.6], "radius_m": 0.13, "rings": 4},
        ],
    }  # fmt: skip
    if motion is not None:
        obj["motion"] = motion
    return obj


def street(motion: dict | None = None, extra: tuple[dict, ...] = ()):
    """A 10 m wide street (floor, two long walls, an end wall at x = 21.2) from x = -2, start
    (0, 0, 1.5) facing +x; the walker with ``motion`` when given, and ``extra`` objects."""
    objects = [
        {"name": "floor", "label": "floor", "instance_id": 1, "color": "#808080", "target": False,
         "parts": [{"type": "plane", "center_m": [9, 0, 0], "size_m": [40, 20]}]},
        {"name": "walls", "label": "wall", "instance_id": 2, "color": "#A0A0A0", "target": False,
         "parts": [{"type": "box", "center_m": [9, 5.2, 2], "size_m": [26, 0.2, 4]},
                   {"type": "box", "center_m": [9, -5.2, 2], "size_m": [26, 0.2, 4]},
                   {"type": "box", "center_m": [21.2, 0, 2], "size_m": [0.2, 10.6, 4]}]},
        *extra,
    ]  # fmt: skip
    if motion is not None:
        objects.append(person(motion))
    return parse_scene({
        "format": "onfly-scene/1", "name": "street", "bounds": {"min_m": [-2, -5, 0], "max_m": [20, 5, 4]},
        "start": {"position_m": [0.0, 0.0, 1.5], "yaw_deg": 0}, "objects": objects,
    })  # fmt: skip
