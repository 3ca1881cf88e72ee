"""Generate the committed scenes of the embedded world (onfly/data/scenes/*.toml).

The TOML files are committed; this script is how they were made and how to remake them:

    .venv/bin/python experiments/make_scenes.py [--out onfly/data/scenes] [--seed 7]

Each scene is laid out by hand in code (coordinates in metres, world ENU, the drone starts
1.5 m above the floor) with a few seeded choices (tree and car placement). Named objects that
tasks may target sit about 8-35 m from the start (the drone flies 0.6 m/s for at most 70 s);
corridors between obstacles stay wider than 1.5 m. Look-alike distractors (two vans of
different colours, several doors, several people) make grounding fail the way it fails on
real images.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

# -- a tiny TOML writer for this format ------------------------------------------------------


def _num(x) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    v = round(float(x), 3)
    if v == 0:
        v = 0.0
    return repr(v)


def _val(v) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_val(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_val(x) for x in v) + "]"
    return _num(v)


# -- parts ------------------------------------------------------------------------------------


def box(center, size, yaw=0.0, color=None) -> dict:
    d = {"type": "box", "center_m": list(center), "size_m": list(size)}
    if yaw:
        d["yaw_deg"] = yaw
    if color is not None:
        d["color"] = color
    return d


def cyl(base, r, h, seg=12, color=None) -> dict:
    d = {"type": "cylinder", "base_m": list(base), "radius_m": r, "height_m": h, "segments": seg}
    if color is not None:
        d["color"] = color
    return d


def sph(center, r, rings=5, color=None) -> dict:
    d = {"type": "sphere", "center_m": list(center), "radius_m": r, "rings": rings}
    if color is not None:
        d["color"] = color
    return d


def plane(center, size, yaw=0.0, color=None) -> dict:
    d = {"type": "plane", "center_m": list(center), "size_m": list(size)}
    if yaw:
        d["yaw_deg"] = yaw
    if color is not None:
        d["color"] = color
    return d


def poly(points, z0, h, color=None) -> dict:
    d = {"type": "extruded_polygon", "points_m": [list(p) for p in points], "z_min_m": z0, "height_m": h}
    if color is not None:
        d["color"] = color
    return d


def stairs(start, yaw, width, n, rise, run, color=None) -> dict:
    d = {"type": "stairs", "start_m": list(start), "yaw_deg": yaw, "width_m": width, "step_count": n, "rise_m": rise, "run_m": run}
    if color is not None:
        d["color"] = color
    return d


def ramp(start, yaw, length, width, rise, color=None) -> dict:
    d = {"type": "ramp", "start_m": list(start), "yaw_deg": yaw, "length_m": length, "width_m": width, "rise_m": rise}
    if color is not None:
        d["color"] = color
    return d


def _local(x, y, yaw_deg, dx, dy):
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return (x + c * dx - s * dy, y + s * dx + c * dy)


# -- scene builder ----------------------------------------------------------------------------


class SceneBuilder:
    def __init__(self, name, description, bounds_min, bounds_max, start, yaw_deg, sky="#B4CDE6", light=(0.35, 0.25, 0.9), ambient=0.4,
                 indoor=False):
        self.name = name
        self.indoor = indoor
        self.description = description
        self.bounds = (list(bounds_min), list(bounds_max))
        self.start = list(start)
        self.yaw_deg = yaw_deg
        self.sky = sky
        self.light = list(light)
        self.ambient = ambient
        self.objects: list[dict] = []

    def add_object(self, obj: dict, comment: str | None = None) -> int:
        """Append an object table as given (its own ``instance_id``; e.g. the tracking walkers of
        issue 19, whose ids 61+ the tracking tasks rely on), optionally after a comment block."""
        if any(o["instance_id"] == obj["instance_id"] for o in self.objects):
            raise ValueError(f"{self.name}: duplicate instance id {obj['instance_id']}")
        o = dict(obj)
        if comment:
            o["_comment"] = comment
        self.objects.append(o)
        return o["instance_id"]

    def add(self, name, label, color, parts, aliases=(), target=True, texture=None, material=None, motion=None) -> int:
        iid = len(self.objects) + 1
        o = {"name": name, "label": label, "instance_id": iid, "color": color, "aliases": list(aliases), "target": target}
        if texture is not None:
            o["texture"] = texture
        if material is not None:
            o["material"] = material
        if motion is not None:
            o["motion"] = motion
        # glass panes and dark rubber / steel parts carry their material (depth sensors see
        # neither: docs/realism.md)
        parts = [dict(p, material=_PART_MATERIALS[p["color"]]) if p.get("color") in _PART_MATERIALS and "material" not in p else p
                 for p in parts]
        o["parts"] = parts
        self.objects.append(o)
        return iid

    def to_toml(self) -> str:
        out = [
            "# Generated by experiments/make_scenes.py; format documented in docs/scene_format.md.",
            'format = "onfly-scene/1"',
            f"name = {_val(self.name)}",
            f"description = {_val(self.description)}",
            f"sky_color = {_val(self.sky)}",
            *(["indoor = true"] if self.indoor else []),
            "",
            "[bounds]",
            f"min_m = {_val(self.bounds[0])}",
            f"max_m = {_val(self.bounds[1])}",
            "",
            "[start]",
            f"position_m = {_val(self.start)}",
            f"yaw_deg = {_num(float(self.yaw_deg))}",
            "",
            "[light]",
            f"direction = {_val(self.light)}",
            f"ambient = {_num(self.ambient)}",
        ]
        for o in self.objects:
            out.append("")
            if "_comment" in o:
                out += [f"# {line}".rstrip() for line in o["_comment"].splitlines()]
            out.append("[[objects]]")
            for k in ("name", "label", "instance_id", "color", "aliases", "target", "texture", "material"):
                if k in o:
                    out.append(f"{k} = {_val(o[k])}")
            out.append("parts = [")
            for p in o["parts"]:
                out.append(f"  {_val(p)},")
            out.append("]")
            if "motion" in o:
                out += ["", "[objects.motion]"]
                for k, v in o["motion"].items():
                    if k == "waypoints":
                        out.append("waypoints = [")
                        out += [f"  {_val(w)}," for w in v]
                        out.append("]")
                    else:
                        out.append(f"{k} = {_val(v)}")
        return "\n".join(out) + "\n"


# -- reusable things ------------------------------------------------------------------------

DARK = "#2A2A2E"
GLASS = "#6E8CA8"
SKIN = "#D8A47F"
_PART_MATERIALS = {GLASS: "glass", DARK: "dark"}


def van(b, name, color, x, y, yaw, aliases=()):
    parts = [box((x, y, 1.3), (4.6, 2.0, 1.9), yaw)]
    fx, fy = _local(x, y, yaw, 2.31, 0.0)
    parts.append(box((fx, fy, 1.75), (0.04, 1.7, 0.7), yaw, color=GLASS))
    for dx in (-1.5, 1.5):
        for dy in (-0.85, 0.85):
            wx, wy = _local(x, y, yaw, dx, dy)
            parts.append(box((wx, wy, 0.3), (0.7, 0.3, 0.6), yaw, color=DARK))
    return b.add(name, "van", color, parts, aliases)


def car(b, name, color, x, y, yaw, aliases=(), target=True, label="car"):
    parts = [box((x, y, 0.7), (4.2, 1.8, 0.8), yaw)]
    cx, cy = _local(x, y, yaw, -0.2, 0.0)
    parts.append(box((cx, cy, 1.4), (2.2, 1.6, 0.6), yaw))
    gx, gy = _local(x, y, yaw, 0.92, 0.0)
    parts.append(box((gx, gy, 1.4), (0.04, 1.5, 0.5), yaw, color=GLASS))
    for dx in (-1.3, 1.3):
        for dy in (-0.8, 0.8):
            wx, wy = _local(x, y, yaw, dx, dy)
            parts.append(box((wx, wy, 0.3), (0.6, 0.25, 0.6), yaw, color=DARK))
    return b.add(name, label, color, parts, aliases, target)


def tree(b, name, x, y, crown="#3C7D32", trunk="#6B4A2B", height=5.5, crown_r=1.6, aliases=(), target=True, z0=0.0):
    parts = [cyl((x, y, z0), 0.22, height - crown_r, 8, color=trunk), sph((x, y, z0 + height - crown_r * 0.6), crown_r, 5)]
    return b.add(name, "tree", crown, parts, aliases, target, {"pattern": "noise", "period_m": 0.4, "contrast": 0.25, "seed": len(b.objects)})


def bench(b, name, color, x, y, yaw, aliases=(), z0=0.0, target=True):
    parts = [box((x, y, z0 + 0.45), (1.8, 0.5, 0.08), yaw)]
    bx, by = _local(x, y, yaw, 0.0, 0.22)
    parts.append(box((bx, by, z0 + 0.75), (1.8, 0.06, 0.5), yaw))
    for dx in (-0.8, 0.8):
        lx, ly = _local(x, y, yaw, dx, 0.0)
        parts.append(box((lx, ly, z0 + 0.21), (0.08, 0.45, 0.42), yaw, color=DARK))
    return b.add(name, "bench", color, parts, aliases, target)


def person(b, name, shirt, x, y, z0=0.0, trousers="#2F3A56", aliases=(), target=True, height=1.75, motion=None, extra=()):
    """A standing person at (x, y, z0); with ``motion`` a walker whose parts are in its own frame
    (x, y, z0 are then ignored: the motion places it). ``extra`` parts (a cart) follow the body."""
    k = height / 1.75
    if motion is not None:
        x, y, z0 = 0.0, 0.0, 0.0
    parts = [
        cyl((x, y, z0), 0.2 * k, 0.85 * k, 8, color=trousers),
        cyl((x, y, z0 + 0.85 * k), 0.24 * k, 0.62 * k, 8),
        sph((x, y, z0 + 1.6 * k), 0.13 * k, 4, color=SKIN),
        *extra,
    ]
    return b.add(name, "person", shirt, parts, aliases, target, motion=motion)


# Walking speeds of the walkers (docs/scene_format.md, "Actors"): comfortable gait speed of
# healthy adults 1.27-1.46 m/s (Bohannon 1997, Age and Ageing 26:15-19, means by age and sex);
# the MUTCD 2009 (section 4E.06) times pedestrian clearance for 1.07 m/s (3.5 ft/s) and for
# 0.91 m/s (3.0 ft/s) where slower pedestrians cross. Strollers and people pushing carts walk
# at the slow end (0.8-0.9 m/s, our choice within that range).
WALK_MPS = 1.3
STROLL_MPS = 0.9
CART_MPS = 0.8


def path(points, speed, loop=True, pauses=None, start_s=0.0):
    """A ``path`` motion table: waypoints (x, y) or (x, y, z) at ``speed`` (a number or one per
    waypoint), ``pauses`` {waypoint index: seconds}."""
    speeds = speed if isinstance(speed, (list, tuple)) else [speed] * len(points)
    wps = []
    for i, p in enumerate(points):
        w = {"position_m": [p[0], p[1], p[2] if len(p) > 2 else 0.0], "speed_mps": speeds[i]}
        if pauses and i in pauses:
            w["pause_s"] = pauses[i]
        wps.append(w)
    m = {"type": "path", "loop": loop}
    if start_s:
        m["start_s"] = start_s
    m["waypoints"] = wps
    return m


def circle(center, radius, speed, phase_deg=0.0, clockwise=False):
    """A ``circle`` motion table about (x, y[, z])."""
    c = [center[0], center[1], center[2] if len(center) > 2 else 0.0]
    return {"type": "circle", "center_m": c, "radius_m": radius, "speed_mps": speed, "phase_deg": phase_deg, "clockwise": clockwise}


def cart(length=0.8, width=0.55, height=0.95, color="#9E9E9E"):
    """Parts of a hand cart pushed in front of a walker (walker frame: x forward)."""
    return (box((0.35 + length / 2, 0.0, 0.55), (length, width, 0.5), color=color),
            box((0.35 + 0.05, 0.0, height - 0.05), (0.06, width, 0.06), color=DARK))


def lamp_post(b, name, x, y, h=4.5, target=False, aliases=()):
    parts = [cyl((x, y, 0.0), 0.08, h, 8), box((x, y, h + 0.15), (0.5, 0.3, 0.3), color="#F2E6A0")]
    return b.add(name, "lamp post", "#3A3D42", parts, aliases, target)


def door(b, name, color, x, y, wall_axis, width=1.0, height=2.1, z0=0.0, aliases=(), target=True, material=None):
    """A door slab 0.12 m thick on a wall; ``wall_axis`` 'x' = wall runs along x."""
    size = (width, 0.12, height) if wall_axis == "x" else (0.12, width, height)
    return b.add(name, "door", color, [box((x, y, z0 + height / 2), size)], aliases, target, material=material)


def walls(b, name, x0, x1, y0, y1, h, color="#B9BCC2", t=0.3, ceiling=True, floor_color="#8C8C8C", floor_label="floor"):
    parts = [
        box(((x0 + x1) / 2, y0 - t / 2, h / 2), (x1 - x0 + 2 * t, t, h)),
        box(((x0 + x1) / 2, y1 + t / 2, h / 2), (x1 - x0 + 2 * t, t, h)),
        box((x0 - t / 2, (y0 + y1) / 2, h / 2), (t, y1 - y0, h)),
        box((x1 + t / 2, (y0 + y1) / 2, h / 2), (t, y1 - y0, h)),
    ]
    b.add(name, "wall", color, parts, target=False)
    b.add("floor", floor_label, floor_color, [plane(((x0 + x1) / 2, (y0 + y1) / 2, 0.0), (x1 - x0, y1 - y0))], target=False,
          texture={"pattern": "noise", "period_m": 0.5, "contrast": 0.15, "seed": 1})
    if ceiling:
        b.add("ceiling", "ceiling", "#D5D5D0", [box(((x0 + x1) / 2, (y0 + y1) / 2, h + t / 2), (x1 - x0 + 2 * t, y1 - y0 + 2 * t, t))], target=False)


def ground(b, color, size, center=(0.0, 0.0), label="ground", pattern="noise", period=0.8, contrast=0.2):
    b.add(label, label, color, [plane((center[0], center[1], 0.0), size)], target=False,
          texture={"pattern": pattern, "period_m": period, "contrast": contrast, "seed": 2})


# -- the ten scenes ----------------------------------------------------------------------------


def urban_block(rng) -> SceneBuilder:
    b = SceneBuilder("urban_block", "City street crossing with buildings on four blocks, parked vans and cars, doors, a bus stop.",
                     (-27, -36, 0), (27, 14, 14), (0.0, -26.0, 1.5), 90.0)
    ground(b, "#55565C", (120, 120), label="road")
    b.add("brick building", "building", "#9C4A36", [box((18, -23, 7), (20, 30, 14))], ["red brick building", "brick block"],
          texture={"pattern": "stripes", "period_m": 0.35, "contrast": 0.2, "axis": "z"})
    b.add("glass office tower", "building", "#7C98B4", [box((-18, -23, 12), (20, 30, 24))], ["office tower", "glass building"],
          texture={"pattern": "checker", "period_m": 1.5, "contrast": 0.3}, material="mirror")
    b.add("white apartment building", "building", "#E4E0D6", [box((18, 23, 8), (20, 30, 16))], ["apartment block", "white building"],
          texture={"pattern": "checker", "period_m": 1.2, "contrast": 0.15})
    b.add("yellow house", "building", "#D9B84A", [box((-18, 23, 5), (20, 30, 10))], ["yellow building"])
    door(b, "red door", "#B02A2A", 7.94, -20, "y", aliases=["red entrance"])
    door(b, "green door", "#2E7D4A", 7.94, -13, "y", aliases=["green entrance"])
    door(b, "blue door", "#2A4FB0", -7.94, -16, "y", aliases=["blue entrance", "door of the office tower"])
    door(b, "glass door", "#9FC3D8", -7.94, -24, "y", width=2.0, height=2.6, aliases=["office entrance"], material="glass")
    van(b, "red van", "#C0282D", 4.3, -15.0, 90, ["red delivery van", "red vehicle"])
    van(b, "blue van", "#2B4C9B", -4.3, -9.0, 270, ["blue delivery van", "blue vehicle"])
    car(b, "white car", "#E8E8E8", 4.3, -20.0, 90, ["white sedan"])
    car(b, "yellow taxi", "#F2C12E", -4.3, -17.0, 270, ["taxi", "yellow car", "cab"])
    car(b, "black car", "#1E1E22", -16.0, -4.3, 0, ["black sedan"])
    car(b, "green car", "#2F7A3A", 15.0, 4.3, 180, ["green sedan"])
    b.add("bus stop", "bus stop", "#5E7D8C",
          [box((6.9, -5.0 - 1.5, 2.5), (1.4, 0.08, 0.1)), box((6.9, -5.0, 2.55), (1.4, 3.2, 0.1)), box((7.55, -5.0, 1.25), (0.08, 3.0, 2.5), color=GLASS),
           cyl((6.3, -6.5, 0), 0.05, 2.5, 6), cyl((6.3, -3.5, 0), 0.05, 2.5, 6)],
          ["bus shelter", "bus station"])
    b.add("fire hydrant", "hydrant", "#C62828", [cyl((-6.6, -18.0, 0), 0.18, 0.7, 8), sph((-6.6, -18.0, 0.7), 0.18, 3)], ["red hydrant", "hydrant"])
    b.add("green dumpster", "dumpster", "#2F6B3A", [box((-6.9, -13.0, 0.65), (1.0, 2.0, 1.3))], ["trash container", "dumpster"])
    b.add("newspaper kiosk", "kiosk", "#8C5A9C", [box((6.8, -10.0, 1.2), (1.4, 2.2, 2.4)), box((6.8, -10.0, 2.5), (1.8, 2.6, 0.2), color="#5C3A66")],
          ["kiosk", "purple kiosk"])
    for i, (x, y) in enumerate([(6.5, -6.5), (-6.5, 6.5)]):
        nm = "south traffic light" if i == 0 else "north traffic light"
        b.add(nm, "traffic light", "#2D2F33", [cyl((x, y, 0), 0.1, 3.2, 8), box((x, y, 3.6), (0.35, 0.35, 0.9), color="#1B1B1B")],
              ["traffic light", "traffic signal"])
    for i, y in enumerate([-34.0, -12.0]):
        lamp_post(b, f"lamp post {i + 1}", 6.6, y)
        lamp_post(b, f"lamp post {i + 3}", -6.6, y + 8)
    for i, x in enumerate([-22.0, -12.0, 12.0, 22.0]):
        tree(b, f"street tree {i + 1}", x, 6.8 if x < 0 else -6.8, target=False)
    return b


def factory_hall(rng) -> SceneBuilder:
    b = SceneBuilder("factory_hall", "Factory hall with two robot arms, a conveyor belt, machines, cabinets, a gantry crane and several doors.",
                     (0.3, -14.7, 0.2), (35.7, 14.7, 8.7), (3.0, 0.0, 1.5), 0.0, light=(0.2, 0.3, 0.93), ambient=0.45, indoor=True)
    walls(b, "hall walls", 0, 36, -15, 15, 9.0, color="#AEB6BE", floor_color="#7D8084")
    for x in (10, 20, 30):
        for y in (-10, 10):
            b.add(f"steel column {x // 10}{'S' if y < 0 else 'N'}", "column", "#51637A", [box((x, y, 4.5), (0.5, 0.5, 9.0))], target=False)

    def arm(name, color, x, y, aliases):
        parts = [cyl((x, y, 0), 0.55, 0.8, 12), box((x, y, 1.55), (0.35, 0.35, 1.5)), box((x + 0.7, y, 2.45), (1.7, 0.3, 0.3)),
                 box((x + 1.5, y, 2.1), (0.15, 0.15, 0.6), color=DARK)]
        return b.add(name, "robot arm", color, parts, aliases)

    arm("yellow robot arm", "#E8B923", 16, -6, ["yellow robot", "yellow industrial robot"])
    arm("orange robot arm", "#E0701E", 16, 6, ["orange robot", "orange industrial robot"])
    b.add("conveyor belt", "conveyor", "#3B3E45", [box((22, -2.5, 0.45), (14, 1.0, 0.9))], ["conveyor", "assembly line"],
          texture={"pattern": "stripes", "period_m": 0.3, "contrast": 0.4, "axis": "x"}, material="dark")
    b.add("CNC machine", "machine", "#9AA3A8", [box((30, -11.5, 1.25), (3.0, 2.4, 2.5)), box((28.45, -11.5, 1.5), (0.1, 1.2, 0.9), color=GLASS)],
          ["milling machine", "grey machine"])
    b.add("hydraulic press", "machine", "#3D6E9E", [box((22, 11.5, 1.75), (2.4, 2.0, 3.5))], ["blue machine", "press"])
    b.add("red tool cabinet", "cabinet", "#C0392B", [box((9, -14.4, 0.9), (1.6, 0.6, 1.8))], ["red cabinet", "red toolbox"])
    b.add("blue tool cabinet", "cabinet", "#2E5FA8", [box((12, 14.4, 0.9), (1.6, 0.6, 1.8))], ["blue cabinet", "blue toolbox"])
    b.add("control panel", "control panel", "#5A6470", [box((10, 2.6, 0.75), (0.6, 1.2, 1.5)), box((9.68, 2.6, 1.2), (0.04, 0.9, 0.5), color="#2DBE6C")],
          ["control station", "operator panel"])
    b.add("gantry crane", "crane", "#E3C22B", [box((26, -12.5, 3.25), (0.6, 0.6, 6.5)), box((26, 12.5, 3.25), (0.6, 0.6, 6.5)),
                                               box((26, 0, 6.8), (0.8, 26, 0.6)), box((26, 3, 5.9), (0.6, 0.6, 1.2), color=DARK)],
          ["overhead crane", "yellow gantry"], texture={"pattern": "stripes", "period_m": 0.4, "contrast": 0.5, "axis": "y"})
    parts = [cyl((33 + dx, 11 + dy, 0), 0.3, 0.9, 10) for dx, dy in ((0, 0), (0.65, 0), (0, 0.65), (0.65, 0.65), (-0.65, 0.65))]
    b.add("stack of barrels", "barrels", "#2F6FB3", parts, ["blue barrels", "oil drums"])
    b.add("green forklift", "forklift", "#3C8D40", [box((32.5, -7, 0.9), (2.2, 1.2, 1.4)), box((31.2, -7, 1.6), (0.12, 1.0, 3.2), color=DARK),
                                                   box((30.7, -7, 0.1), (1.0, 0.8, 0.08), color=DARK)], ["forklift", "green lift truck"])
    b.add("pallet of boxes", "pallet", "#B08A5A", [box((7, 10, 0.6), (1.2, 1.2, 1.2))], ["stacked boxes", "cardboard boxes"])
    door(b, "large roller door", "#8E979E", 35.94, 0, "y", width=4.0, height=4.5, aliases=["roller door", "shutter door", "loading door"])
    door(b, "green door", "#2E7D4A", 18, 14.94, "x", aliases=["green exit"])
    door(b, "grey door", "#7F868C", 30, 14.94, "x", aliases=["grey exit"])
    door(b, "emergency exit door", "#C0392B", 22, -14.94, "x", aliases=["red door", "fire exit"])
    return b


def villa(rng) -> SceneBuilder:
    b = SceneBuilder("villa", "Villa with a pool, loungers, a patio umbrella, garden hedge, trees, a fountain and three doors.",
                     (-19, -15, 0), (19, 19, 10), (-10.0, -10.0, 1.5), 40.0)
    ground(b, "#5E9E48", (80, 80), label="lawn")
    b.add("villa", "building", "#EDE6D6", [poly([(-16, 10), (6, 10), (6, 16), (-4, 16), (-4, 22), (-16, 22)], 0.0, 6.5)],
          ["house", "white villa"])
    b.add("villa roof", "roof", "#8A4B38", [poly([(-16.3, 9.7), (6.3, 9.7), (6.3, 16.3), (-3.7, 16.3), (-3.7, 22.3), (-16.3, 22.3)], 6.5, 0.3)],
          target=False)
    door(b, "front door", "#7A4A24", -11, 9.94, "x", width=1.2, height=2.3, aliases=["wooden door", "main entrance"])
    door(b, "glass door", "#A9CFE0", -2, 9.94, "x", width=2.4, height=2.3, aliases=["patio door", "sliding door"], material="glass")
    door(b, "garage door", "#D8D8D8", 3.5, 9.94, "x", width=3.0, height=2.5, aliases=["white garage door"])
    b.add("pool", "pool", "#3FA3D6", [plane((7, -1, 0.01), (10, 6))], ["swimming pool", "pool water"],
          texture={"pattern": "noise", "period_m": 0.3, "contrast": 0.2, "seed": 4})
    b.add("pool edge", "pool edge", "#E0DCD0", [box((7, -4.2, 0.05), (10.8, 0.4, 0.1)), box((7, 2.2, 0.05), (10.8, 0.4, 0.1)),
                                                box((1.8, -1, 0.05), (0.4, 6.0, 0.1)), box((12.2, -1, 0.05), (0.4, 6.0, 0.1))],
          ["edge of the pool", "pool coping", "poolside"])
    b.add("pool ladder", "ladder", "#C8CCD0", [cyl((12.1, -0.3, 0), 0.04, 1.0, 6), cyl((12.1, 0.3, 0), 0.04, 1.0, 6),
                                               box((12.1, 0, 0.95), (0.08, 0.6, 0.05))], ["ladder", "metal ladder"])
    b.add("white sun lounger", "lounger", "#F4F4F0", [box((4, -6.5, 0.3), (0.7, 1.9, 0.3), 0), box((4, -5.7, 0.6), (0.7, 0.3, 0.5))],
          ["white deck chair", "white lounger"])
    b.add("blue sun lounger", "lounger", "#2F6DB5", [box((7, -6.5, 0.3), (0.7, 1.9, 0.3)), box((7, -5.7, 0.6), (0.7, 0.3, 0.5))],
          ["blue deck chair", "blue lounger"])
    b.add("patio umbrella", "umbrella", "#E6D8B0", [cyl((0.5, -6.5, 0), 0.04, 2.3, 6, color="#777777"), cyl((0.5, -6.5, 2.3), 1.3, 0.12, 12)],
          ["parasol", "sun umbrella"], texture={"pattern": "stripes", "period_m": 0.3, "contrast": 0.35, "axis": "x"})
    b.add("garden hedge", "hedge", "#2C6B2A", [box((-13, -2, 0.6), (8, 1.0, 1.2))], ["hedge", "bushes"],
          texture={"pattern": "noise", "period_m": 0.25, "contrast": 0.3, "seed": 5})
    b.add("fountain", "fountain", "#BFB8A8", [cyl((-6, 2, 0), 1.4, 0.5, 14), cyl((-6, 2, 0.5), 0.25, 1.0, 8), cyl((-6, 2, 1.5), 0.6, 0.15, 10)],
          ["stone fountain", "garden fountain"])
    b.add("garden shed", "shed", "#7A5234", [box((16, 11, 1.25), (3.0, 2.5, 2.5))], ["wooden shed", "tool shed"],
          texture={"pattern": "stripes", "period_m": 0.2, "contrast": 0.2, "axis": "x"})
    tree(b, "palm tree near the pool", 14.5, -4.5, crown="#4F8F2F", height=6.5, crown_r=1.5, aliases=["palm tree", "palm"])
    tree(b, "apple tree", -16, 5, crown="#3C7D32", aliases=["fruit tree"])
    tree(b, "cypress tree", 12, 8, crown="#24562B", height=6.0, crown_r=1.2, aliases=["dark tree"])
    b.add("outdoor table", "table", "#8B6A45", [cyl((-2, -9, 0), 0.08, 0.72, 6), cyl((-2, -9, 0.72), 0.6, 0.05, 12)], ["garden table", "round table"])
    return b


def duplex(rng) -> SceneBuilder:
    b = SceneBuilder("duplex", "Two-level building: an open ground floor under a second-floor platform reached by an outside staircase.",
                     (-9, -18, 0), (26, 14, 11), (8.0, -13.0, 1.5), 90.0)
    ground(b, "#6E8F5A", (80, 80), label="lawn")
    slab_z = 3.5
    b.add("second-floor platform", "platform", "#C9C3B6", [box((8, 5, slab_z - 0.15), (16, 10, 0.3))],
          ["upper platform", "second floor", "upper deck", "terrace on the second floor"])
    b.add("pillars", "pillar", "#9B9A95", [box((x, y, (slab_z - 0.3) / 2), (0.4, 0.4, slab_z - 0.3)) for x in (0.3, 8, 15.7) for y in (0.3, 9.7)],
          target=False)
    b.add("back wall", "wall", "#D7D0C2", [box((8, 9.85, 3.75), (16, 0.3, 7.5))], target=False)
    b.add("roof", "roof", "#6F6A63", [box((4, 5, 7.65), (8.6, 10.6, 0.3))], target=False)
    b.add("railing", "railing", "#4A4A4A", [box((15.9, 5, slab_z + 0.55), (0.06, 10, 0.08)), box((15.9, 5, slab_z + 1.0), (0.06, 10, 0.06))]
          + [cyl((15.9, y, slab_z), 0.03, 1.05, 4) for y in (0.2, 2.5, 5, 7.5, 9.8)],
          ["metal railing", "balustrade"])
    b.add("staircase", "stairs", "#A8A49C", [stairs((-1.2, -2.0, 0.0), 90, 1.6, 12, slab_z / 12, 0.3)],
          ["outside stairs", "stairs", "steps"])
    b.add("stair landing", "platform", "#A8A49C", [box((-1.0, 2.2, slab_z - 0.15), (2.0, 1.2, 0.3))], target=False)
    person(b, "person near the railing", "#C0392B", 14.8, 6.0, z0=slab_z, aliases=["person on the platform", "person upstairs"])
    person(b, "person by the entrance", "#2E86C1", 4.0, -1.5, aliases=["person downstairs", "person in blue"])
    b.add("potted plant", "plant", "#3E8E41", [cyl((2.0, 2.0, slab_z), 0.3, 0.5, 8, color="#8B5A2B"), sph((2.0, 2.0, slab_z + 0.9), 0.45, 4)],
          ["plant on the platform", "green plant"])
    b.add("orange lounge chair", "chair", "#E07B1F", [box((10, 3, slab_z + 0.25), (0.8, 1.6, 0.5)), box((10, 3.7, slab_z + 0.7), (0.8, 0.2, 0.5))],
          ["orange chair", "deck chair on the platform"])
    door(b, "balcony door", "#5B7FA6", 9, 9.64, "x", z0=slab_z, width=1.6, height=2.2, aliases=["upstairs door", "glass door upstairs"],
         material="glass")
    door(b, "entrance door", "#7A4A24", 5, 9.64, "x", width=1.2, height=2.2, aliases=["front door", "ground floor door"])
    door(b, "storage door", "#7F868C", 12, 9.64, "x", width=1.0, height=2.0, aliases=["grey door", "utility door"])
    b.add("blue sofa", "sofa", "#2F4F8F", [box((8, 7.5, 0.4), (2.4, 0.9, 0.8)), box((8, 7.9, 0.9), (2.4, 0.2, 0.6))], ["sofa", "couch"])
    b.add("coffee table", "table", "#7B5B3A", [box((8, 5.8, 0.22), (1.2, 0.6, 0.44))], ["low table"])
    car(b, "red car", "#B3242B", 20.5, -2.0, 90, ["red sedan"])
    car(b, "white car", "#E6E6E6", 20.5, -8.0, 90, ["white sedan"])
    b.add("wheelchair ramp", "ramp", "#B5AFA3", [ramp((13.0, -6.0, 0.0), 90, 4.0, 1.5, 0.5), box((13.0, -1.25, 0.25), (1.5, 1.5, 0.5))],
          ["ramp"])
    tree(b, "tree by the staircase", -5.5, 4.0, aliases=["tree"])
    # issue 19: walkers (appended, so the ids above stay); the standing people are goals of the
    # paper's static tasks and stay put; the walkers keep off those tasks' routes.
    person(b, "person in yellow raincoat", "#FBC02D", 0.0, 0.0, aliases=["person in yellow", "person in the raincoat"],
           motion=path([(-7.0, -16.5), (23.0, -16.5), (23.0, -17.3), (-7.0, -17.3)], 1.2))
    person(b, "person in green jacket", "#2E7D32", 0.0, 0.0, aliases=["person in green"],
           motion=path([(23.2, -15.0), (23.2, 11.0), (24.6, 11.0), (24.6, -15.0)], WALK_MPS, start_s=-8.0))
    person(b, "person on the phone", "#6A1B9A", 0.0, 0.0, aliases=["person pacing", "person in purple"],
           motion=circle((-6.0, 9.0), 1.5, STROLL_MPS, phase_deg=90.0, clockwise=True))
    for i, o in enumerate(TRACKING_WALKERS["duplex"]):
        b.add_object(o, TRACKING_COMMENT if i == 0 else None)
    return b


def corridor(rng) -> SceneBuilder:
    b = SceneBuilder("corridor", "Long office corridor with numbered doors, a vending machine, an extinguisher and other sparse landmarks.",
                     (0.4, -1.75, 0.4), (36.6, 1.75, 3.1), (2.0, 0.0, 1.5), 0.0, light=(0.3, 0.2, 0.93), ambient=0.5, indoor=True)
    walls(b, "corridor walls", 0, 37, -2, 2, 3.5, color="#D9D4C7", floor_color="#9A8F7E")
    b.add("window at the end of the corridor", "window", "#9CC8E6", [box((36.94, 0, 1.8), (0.12, 2.4, 1.6))], ["window", "end window"],
          material="glass")
    door(b, "red door", "#B0302A", 31, 1.94, "x", aliases=["red office door"])
    door(b, "blue door", "#2C56A8", 14, -1.94, "x", aliases=["blue office door"])
    for i, (x, side) in enumerate([(9, 1), (11, -1), (19, 1), (23, -1), (27, 1), (33, -1), (34.5, 1)]):
        door(b, f"door {101 + i}", "#8C8F93", x, side * 1.94, "x", aliases=["grey door", f"office {101 + i}"])
    b.add("fire extinguisher", "extinguisher", "#D32F2F", [cyl((20.5, 1.78, 0.3), 0.12, 0.55, 8)], ["red extinguisher"])
    b.add("vending machine", "vending machine", "#C62828", [box((24.5, -1.55, 0.95), (0.9, 0.9, 1.9)), box((24.5, -1.09, 1.2), (0.7, 0.02, 1.0), color=GLASS)],
          ["snack machine", "drinks machine"])
    b.add("water fountain", "water fountain", "#B8C2CC", [box((12, 1.8, 0.95), (0.5, 0.4, 0.3)), box((12, 1.9, 0.4), (0.2, 0.2, 0.8))],
          ["drinking fountain"])
    b.add("exit sign", "sign", "#2EAD4B", [box((35.5, 0, 3.3), (0.08, 0.6, 0.3))], ["green exit sign", "emergency exit sign"])
    b.add("notice board", "board", "#C9A46B", [box((16.5, -1.97, 1.5), (1.6, 0.06, 1.0))], ["bulletin board", "cork board"],
          texture={"pattern": "noise", "period_m": 0.1, "contrast": 0.3, "seed": 6})
    b.add("potted plant", "plant", "#3E8E41", [cyl((33, 1.6, 0), 0.25, 0.45, 8, color="#8B5A2B"), sph((33, 1.6, 0.9), 0.35, 4)], ["green plant"])
    b.add("trash bin", "bin", "#4A4A4A", [cyl((16.5, 1.7, 0), 0.2, 0.7, 8)], ["grey bin", "waste bin"])
    b.add("recycling bin", "bin", "#2F6DB5", [cyl((29, -1.7, 0), 0.2, 0.7, 8)], ["blue bin"])
    b.add("wall clock", "clock", "#F2F2F2", [cyl((18, -1.98, 2.2), 0.2, 0.04, 12)], ["clock"])
    return b


def park(rng) -> SceneBuilder:
    b = SceneBuilder("park", "Park with paths, trees, three benches, a fountain, a gazebo, a playground slide, a statue and a pond.",
                     (-24, -24, 0), (24, 24, 10), (0.0, -17.0, 1.5), 90.0)
    ground(b, "#5FA04A", (80, 80), label="grass")
    b.add("path", "path", "#C9B58E", [plane((0, 0, 0.01), (3, 48)), plane((0, 6, 0.011), (48, 3))], ["footpath", "gravel path"], target=False,
          texture={"pattern": "noise", "period_m": 0.2, "contrast": 0.2, "seed": 7})
    b.add("fountain", "fountain", "#B9B4A6", [cyl((0, 10, 0), 2.2, 0.6, 16), cyl((0, 10, 0.6), 0.3, 1.4, 8), cyl((0, 10, 2.0), 0.8, 0.15, 12)],
          ["stone fountain", "water fountain"])
    bench(b, "green bench", "#2E7D32", 2.8, -6, 90, ["green park bench"])
    bench(b, "brown bench", "#7B5231", -2.8, -2, 270, ["wooden bench", "brown park bench"])
    bench(b, "white bench", "#E8E8E2", 8, 8.2, 0, ["white park bench"])
    b.add("gazebo", "gazebo", "#E9E4D8", [cyl((-14 + dx, -6 + dy, 0), 0.12, 3.0, 8) for dx in (-2, 2) for dy in (-2, 2)]
          + [box((-14, -6, 3.1), (4.8, 4.8, 0.25), color="#8A4B38")], ["pavilion", "white gazebo"])
    b.add("playground slide", "slide", "#D84315", [ramp((9, 15, 0), 180, 3.0, 0.6, 1.6), box((12.4, 15, 0.8), (0.8, 0.8, 1.6), color="#1565C0")],
          ["slide", "red slide"])
    b.add("picnic table", "table", "#8B6A45", [box((14, -4, 0.75), (1.8, 0.8, 0.06)), box((14, -4.65, 0.45), (1.8, 0.3, 0.05)),
                                               box((14, -3.35, 0.45), (1.8, 0.3, 0.05)), box((14, -4, 0.36), (0.1, 0.6, 0.72), color=DARK)],
          ["wooden table"])
    b.add("statue", "statue", "#9E9E96", [box((-12, 12, 0.6), (1.2, 1.2, 1.2)), cyl((-12, 12, 1.2), 0.3, 1.4, 8), sph((-12, 12, 2.8), 0.25, 4)],
          ["stone statue", "monument"])
    b.add("pond", "pond", "#3B83B5", [plane((10, -14, 0.012), (8, 5))], ["pond water", "small lake"],
          texture={"pattern": "noise", "period_m": 0.3, "contrast": 0.2, "seed": 8})
    b.add("trash can", "bin", "#37474F", [cyl((-2.2, -6, 0), 0.25, 0.9, 8)], ["bin", "litter bin"])
    lamp_post(b, "lamp post by the fountain", 3.2, 12.5, target=True, aliases=["street lamp"])
    lamp_post(b, "lamp post 2", -3.0, -14.0)
    tree(b, "maple tree", -6, 16, crown="#B5402A", aliases=["red tree", "tree with red leaves"])
    tree(b, "oak tree", 8, -8, crown="#3C7D32", height=6.5, crown_r=2.0, aliases=["big tree", "large oak"])
    keep_out = [(0, 0, 2.5, 30), (0, 6, 30, 2.5), (0, 10, 3.5, 3.5), (-14, -6, 4, 4), (10, 15, 4, 2), (14, -4, 2.5, 2), (-12, 12, 2, 2),
                (10, -14, 5.5, 4), (-6, 16, 2.5, 2.5), (8, -8, 3, 3), (0, -17, 4, 4), (-2.2, -6, 1, 1), (8, 8.2, 2, 1.5), (2.8, -6, 1.5, 2), (-2.8, -2, 1.5, 2)]
    n = 0
    while n < 9:
        x, y = rng.uniform(-22, 22, 2)
        if any(abs(x - kx) < hx + 1.6 and abs(y - ky) < hy + 1.6 for kx, ky, hx, hy in keep_out):
            continue
        keep_out.append((x, y, 2.0, 2.0))
        n += 1
        tree(b, f"tree {n}", float(x), float(y), crown="#3F8A36", target=False)
    return b


def parking_lot(rng) -> SceneBuilder:
    b = SceneBuilder("parking_lot", "Open parking lot: two rows of parked cars around a driving lane, vans, a ticket machine and a barrier.",
                     (-24, -17, 0), (18, 17, 10), (-22.0, 0.0, 1.5), 0.0)
    ground(b, "#4E4F54", (80, 60), label="asphalt")
    lines = []
    for row in (-1, 1):
        for i in range(13):
            x = -17.6 + 2.8 * i
            lines.append(plane((x, row * 5.5, 0.01), (0.12, 5.0)))
    b.add("parking lines", "marking", "#EDEDED", lines, target=False)
    named = {
        (1, 2): ("red van", "#C0282D", "van", ["red delivery van"]),
        (1, 8): ("white van", "#EDEDED", "van", ["white delivery van"]),
        (-1, 5): ("yellow car", "#F2C12E", "car", ["yellow hatchback"]),
        (-1, 9): ("black SUV", "#1C1C20", "car", ["black car", "dark SUV"]),
        (1, 5): ("silver car", "#B8BCC2", "car", ["grey car", "silver sedan"]),
        (-1, 1): ("blue car", "#2B4C9B", "car", ["blue sedan"]),
    }
    empty = {(1, 4), (-1, 7), (1, 10)}
    palette = ["#7A7F87", "#3D4450", "#8E2F2F", "#E0E0E0", "#2D5A3A", "#5A4A3A"]
    k = 0
    for row in (-1, 1):
        for i in range(12):
            if (row, i) in empty:
                continue
            x = -16.2 + 2.8 * i
            y = row * 5.5
            yaw = 90 if row < 0 else 270
            if (row, i) in named:
                nm, col, kind, al = named[(row, i)]
                if kind == "van":
                    van(b, nm, col, x, y, yaw, al)
                else:
                    car(b, nm, col, x, y, yaw, al)
            else:
                k += 1
                car(b, f"parked car {k}", palette[int(rng.integers(len(palette)))], x, y, yaw, target=False)
    b.add("ticket machine", "ticket machine", "#1F5FA8", [box((-21, 9.5, 0.8), (0.6, 0.5, 1.6))], ["pay station", "parking meter"])
    b.add("barrier gate", "barrier", "#E53935", [box((12.5, -2.6, 0.55), (0.5, 0.5, 1.1), color="#9E9E9E"), box((12.5, -0.4, 1.0), (0.1, 4.2, 0.1))],
          ["boom barrier", "exit barrier"], texture={"pattern": "stripes", "period_m": 0.4, "contrast": 0.9, "axis": "y"})
    b.add("EV charging station", "charger", "#2EAD4B", [box((-9.8, 9.0, 0.75), (0.4, 0.3, 1.5)), box((-7.0, 9.0, 0.75), (0.4, 0.3, 1.5))],
          ["charging station", "electric car charger"])
    b.add("shopping cart corral", "cart corral", "#B0B7BE", [box((-4, 10.5, 0.5), (2.5, 0.06, 1.0)), box((-4, 11.7, 0.5), (2.5, 0.06, 1.0))],
          ["cart return"])
    b.add("motorcycle", "motorcycle", "#D84315", [box((-19.5, -10.0, 0.6), (0.4, 2.0, 0.7)), box((-19.5, -9.3, 1.1), (0.5, 0.4, 0.3), color=DARK)],
          ["motorbike", "orange motorcycle"])
    for i, x in enumerate((-12.0, 0.0, 12.0)):
        b.add(f"light pole {i + 1}", "lamp post", "#50555C", [cyl((x, 9.0 if i != 1 else -9.0, 0), 0.12, 7.0, 8)], target=False)
    b.add("trolley booth", "kiosk", "#F0E3C0", [box((0, 14.5, 1.3), (3, 2, 2.6))], ["attendant booth", "small booth"])
    return b


def warehouse(rng) -> SceneBuilder:
    b = SceneBuilder("warehouse", "Warehouse with four long shelving racks and aisles, two forklifts, pallets, crates and three dock doors.",
                     (0.3, -15.7, 0.2), (39.7, 15.7, 8.7), (3.0, 0.0, 1.5), 0.0, light=(0.25, 0.35, 0.9), ambient=0.45, indoor=True)
    walls(b, "warehouse walls", 0, 40, -16, 16, 9.0, color="#B7B2A8", floor_color="#8A8B8D")
    for nm, y, col in (("rack A", -9, "#3B6EA5"), ("rack B", -3, "#D9822B"), ("rack C", 3, "#3B6EA5"), ("rack D", 9, "#D9822B")):
        b.add(nm, "shelf", col, [box((20, y, 3.0), (24, 2.4, 6.0))], [f"shelf {nm[-1]}", f"shelving {nm[-1]}"],
              texture={"pattern": "stripes", "period_m": 1.0, "contrast": 0.45, "axis": "z"})
    b.add("orange forklift", "forklift", "#E67E22", [box((4.5, -11, 0.9), (2.2, 1.2, 1.4)), box((5.8, -11, 1.6), (0.12, 1.0, 3.2), color=DARK),
                                                    box((6.3, -11, 0.1), (1.0, 0.8, 0.08), color=DARK)], ["orange lift truck"])
    b.add("yellow forklift", "forklift", "#F1C40F", [box((36, 11, 0.9), (2.2, 1.2, 1.4)), box((34.7, 11, 1.6), (0.12, 1.0, 3.2), color=DARK),
                                                    box((34.2, 11, 0.1), (1.0, 0.8, 0.08), color=DARK)], ["yellow lift truck"])
    b.add("pallet of boxes", "pallet", "#B08A5A", [box((36.5, -6, 0.6), (1.2, 1.2, 1.2))], ["cardboard boxes", "stacked boxes"])
    b.add("stack of blue crates", "crates", "#2E5FA8", [box((5, 12.5, 0.75), (1.5, 1.5, 1.5))], ["blue crates", "blue boxes"])
    b.add("stack of red crates", "crates", "#B03A2E", [box((34.5, -12.5, 0.75), (1.5, 1.5, 1.5))], ["red crates", "red boxes"])
    b.add("safety cone", "cone", "#FF6F00", [cyl((20, -6, 0), 0.22, 0.6, 8)], ["orange cone", "traffic cone"])
    b.add("workbench", "workbench", "#8B6A45", [box((37.5, 1, 0.45), (1.2, 2.4, 0.9))], ["work table"])
    b.add("fire extinguisher", "extinguisher", "#D32F2F", [cyl((0.15, 9, 0.3), 0.12, 0.55, 8)], ["red extinguisher"])
    b.add("office cabin", "office", "#D6D2C4", [box((3, 14, 1.5), (5.6, 3.6, 3.0)), box((3, 12.17, 1.6), (2.0, 0.06, 1.0), color=GLASS)],
          ["site office", "cabin"])
    for i, x in enumerate((12, 22, 32)):
        door(b, f"dock door {i + 1}", ["#6F7B85", "#7E8A94", "#6A7680"][i], x, 15.94, "x", width=3.0, height=3.5,
             aliases=["dock door", "loading dock door", f"loading door {i + 1}"])
    b.add("yellow floor marking", "marking", "#E8C21F", [plane((4, 0, 0.01), (0.15, 30))], target=False)
    return b


# The tracking walkers of issue 19 (h19t's tracking tasks follow them: onfly/data/tasks/track/).
# Their ids (61+) and names are what those tasks use; change them together.
TRACKING_COMMENT = """-- Tracking walkers (issue 19, h19t): followed people walk slowly (0.40-0.45 m/s) because the
vehicle's speed limit is the paper's 0.6 m/s (its real pedestrian-tracking flight used the same
limit). Such gait speeds are within the range measured in adults (0.4-0.6 m/s among older adults:
S. Studenski et al., "Gait speed and survival in older adults", JAMA 305(1), 2011); a cart or a
stroller slows a walker further. Each stands for the first 6 s (start_s: the operator designates
them while they stand), then walks. Parts are in the actor's frame (x forward, z up)."""
TRACKING_WALKERS = {'plaza': [{'name': 'woman in the yellow coat',
            'label': 'person',
            'instance_id': 61,
            'color': '#F2C12E',
            'aliases': ['woman in yellow', 'person in the yellow coat', 'yellow coat'],
            'target': True,
            'parts': [{'type': 'cylinder', 'base_m': [0.0, 0.0, 0.0], 'radius_m': 0.2, 'height_m': 0.85, 'segments': 8, 'color': '#2F3A56'},
                      {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                      {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'}],
            'motion': {'type': 'circle',
                       'start_s': 6.0,
                       'center_m': [0.0, 4.0, 0.0],
                       'radius_m': 6.5,
                       'speed_mps': 0.45,
                       'phase_deg': -90.0,
                       'clockwise': False}},
           {'name': 'man in the green hoodie',
            'label': 'person',
            'instance_id': 62,
            'color': '#2E8B57',
            'aliases': ['man in green', 'person in the green hoodie', 'green hoodie'],
            'target': True,
            'parts': [{'type': 'cylinder', 'base_m': [0.0, 0.0, 0.0], 'radius_m': 0.2, 'height_m': 0.85, 'segments': 8, 'color': '#2F3A56'},
                      {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                      {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'}],
            'motion': {'type': 'path',
                       'start_s': 6.0,
                       'loop': True,
                       'waypoints': [{'position_m': [-17.0, -1.0, 0.0], 'speed_mps': 0.45},
                                     {'position_m': [-7.0, -1.0, 0.0], 'speed_mps': 0.45},
                                     {'position_m': [-7.0, 7.0, 0.0], 'speed_mps': 0.45},
                                     {'position_m': [-17.0, 7.0, 0.0], 'speed_mps': 0.45}]}},
           {'name': 'man with the cart',
            'label': 'person',
            'instance_id': 63,
            'color': '#8D6E63',
            'aliases': ['man pushing the cart', 'person with the cart'],
            'target': True,
            'parts': [{'type': 'cylinder', 'base_m': [0.0, 0.0, 0.0], 'radius_m': 0.2, 'height_m': 0.85, 'segments': 8, 'color': '#2F3A56'},
                      {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                      {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'},
                      {'type': 'box', 'center_m': [0.75, 0.0, 0.55], 'size_m': [0.7, 0.5, 0.5], 'color': '#9E9E9E'},
                      {'type': 'box', 'center_m': [0.75, 0.0, 0.15], 'size_m': [0.6, 0.4, 0.1], 'color': '#2A2A2E', 'material': 'dark'}],
            'motion': {'type': 'path',
                       'start_s': 6.0,
                       'loop': False,
                       'waypoints': [{'position_m': [-20.0, -14.0, 0.0], 'speed_mps': 0.4},
                                     {'position_m': [-6.0, -14.0, 0.0], 'speed_mps': 0.4}]}},
           {'name': 'woman with the stroller',
            'label': 'person',
            'instance_id': 64,
            'color': '#EC407A',
            'aliases': ['woman pushing the stroller', 'person with the stroller'],
            'target': True,
            'parts': [{'type': 'cylinder', 'base_m': [0.0, 0.0, 0.0], 'radius_m': 0.2, 'height_m': 0.85, 'segments': 8, 'color': '#2F3A56'},
                      {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                      {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'},
                      {'type': 'box', 'center_m': [0.7, 0.0, 0.6], 'size_m': [0.6, 0.45, 0.45], 'color': '#37474F'},
                      {'type': 'box', 'center_m': [0.7, 0.0, 0.2], 'size_m': [0.5, 0.4, 0.1], 'color': '#2A2A2E', 'material': 'dark'}],
            'motion': {'type': 'path',
                       'start_s': 6.0,
                       'loop': False,
                       'waypoints': [{'position_m': [18.0, -18.0, 0.0], 'speed_mps': 0.4},
                                     {'position_m': [18.0, -4.0, 0.0], 'speed_mps': 0.4}]}},
           {'name': 'woman in the purple dress',
            'label': 'person',
            'instance_id': 65,
            'color': '#8E24AA',
            'aliases': ['woman in purple', 'person in the purple dress', 'purple dress'],
            'target': True,
            'parts': [{'type': 'cylinder', 'base_m': [0.0, 0.0, 0.0], 'radius_m': 0.2, 'height_m': 0.85, 'segments': 8, 'color': '#2F3A56'},
                      {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                      {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'}],
            'motion': {'type': 'path',
                       'start_s': 6.0,
                       'loop': True,
                       'waypoints': [{'position_m': [-3.0, -8.0, 0.0], 'speed_mps': 0.45},
                                     {'position_m': [5.0, -8.0, 0.0], 'speed_mps': 0.45},
                                     {'position_m': [5.0, -14.0, 0.0], 'speed_mps': 0.45},
                                     {'position_m': [-3.0, -14.0, 0.0], 'speed_mps': 0.45}]}}],
 'duplex': [{'name': 'man in the orange vest',
             'label': 'person',
             'instance_id': 61,
             'color': '#FB8C00',
             'aliases': ['man in orange', 'person in the orange vest', 'orange vest'],
             'target': True,
             'parts': [{'type': 'cylinder',
                        'base_m': [0.0, 0.0, 0.0],
                        'radius_m': 0.2,
                        'height_m': 0.85,
                        'segments': 8,
                        'color': '#2F3A56'},
                       {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                       {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'}],
             'motion': {'type': 'path',
                        'start_s': 6.0,
                        'loop': True,
                        'waypoints': [{'position_m': [-4.0, -5.0, 0.0], 'speed_mps': 0.45},
                                      {'position_m': [16.0, -5.0, 0.0], 'speed_mps': 0.45},
                                      {'position_m': [16.0, -13.0, 0.0], 'speed_mps': 0.45},
                                      {'position_m': [-4.0, -13.0, 0.0], 'speed_mps': 0.45}]}},
            {'name': 'woman with the shopping bag',
             'label': 'person',
             'instance_id': 62,
             'color': '#00897B',
             'aliases': ['woman carrying a shopping bag', 'person with the shopping bag'],
             'target': True,
             'parts': [{'type': 'cylinder',
                        'base_m': [0.0, 0.0, 0.0],
                        'radius_m': 0.2,
                        'height_m': 0.85,
                        'segments': 8,
                        'color': '#2F3A56'},
                       {'type': 'cylinder', 'base_m': [0.0, 0.0, 0.85], 'radius_m': 0.24, 'height_m': 0.62, 'segments': 8},
                       {'type': 'sphere', 'center_m': [0.0, 0.0, 1.6], 'radius_m': 0.13, 'rings': 4, 'color': '#D8A47F'},
                       {'type': 'box', 'center_m': [0.0, -0.33, 0.75], 'size_m': [0.3, 0.12, 0.35], 'color': '#FFFFFF'}],
             'motion': {'type': 'path',
                        'start_s': 6.0,
                        'loop': False,
                        'waypoints': [{'position_m': [-4.0, -15.5, 0.0], 'speed_mps': 0.4},
                                      {'position_m': [10.0, -15.5, 0.0], 'speed_mps': 0.4}]}}]}


def plaza(rng) -> SceneBuilder:
    b = SceneBuilder("plaza", "Paved city plaza with a fountain, statue, flagpole, cafe tables, a kiosk, a railing and many people.",
                     (-24, -22, 0), (24, 22, 10), (0.0, -18.0, 1.5), 90.0)
    ground(b, "#B5ADA0", (80, 80), label="paving", pattern="checker", period=1.0, contrast=0.12)
    for nm, c, s in (("north building", (0, 30), (60, 10)), ("west building", (-31, 0), (10, 60)), ("east building", (31, 0), (10, 60))):
        b.add(nm, "building", "#C9B79C", [box((c[0], c[1], 6), (s[0], s[1], 12))], target=False,
              texture={"pattern": "checker", "period_m": 1.5, "contrast": 0.2})
    b.add("fountain", "fountain", "#BDB7AA", [cyl((0, 4, 0), 2.5, 0.6, 16), cyl((0, 4, 0.6), 0.35, 1.6, 8), cyl((0, 4, 2.2), 0.9, 0.15, 12)],
          ["central fountain"])
    b.add("railing", "railing", "#4A4A4A", [box((0, 16.5, 1.0), (30, 0.06, 0.08)), box((0, 16.5, 0.55), (30, 0.06, 0.06))]
          + [cyl((x, 16.5, 0), 0.03, 1.05, 4) for x in range(-15, 16, 5)], ["metal railing", "fence"])
    person(b, "person near the railing", "#7E57C2", -3.0, 15.5, aliases=["person by the railing", "person in purple"])
    person(b, "person in red shirt", "#C62828", -6.0, 10.0, aliases=["person in red", "man in red"])
    person(b, "person in blue shirt", "#1E63B5", 6.5, 12.0, aliases=["person in blue", "man in blue"])
    person(b, "person near the fountain", "#2E7D32", 3.4, 1.2, aliases=["person by the fountain", "person in green"])
    person(b, "person in white shirt", "#F0F0F0", 11.0, -4.0, aliases=["person in white"])
    person(b, "child with a yellow shirt", "#F9A825", -9.0, -3.0, height=1.2, aliases=["child", "kid"])
    # walks around the round flower bed (added below), counter-clockwise
    person(b, "person in red jacket", "#B71C1C", 0.0, 0.0, aliases=["person in red"], target=True,
           motion=circle((16.0, 11.5), 4.0, STROLL_MPS, phase_deg=180.0))
    b.add("statue", "statue", "#8D8A80", [box((-12, 2, 0.75), (1.5, 1.5, 1.5)), cyl((-12, 2, 1.5), 0.35, 1.6, 8), sph((-12, 2, 3.35), 0.3, 4)],
          ["bronze statue", "monument"])
    b.add("flagpole", "flagpole", "#D0D0D0", [cyl((12, 2, 0), 0.08, 8.0, 8), box((12.8, 2, 7.3), (1.5, 0.03, 1.0), color="#C62828")],
          ["flag", "flag pole"])
    for i, (x, y, col) in enumerate(((-10, -9, "#2E7D32"), (-6.5, -11, "#C62828"))):
        b.add(["cafe table with green umbrella", "cafe table with red umbrella"][i], "cafe table", col,
              [cyl((x, y, 0), 0.05, 2.2, 6, color="#777777"), cyl((x, y, 2.2), 1.2, 0.1, 12), cyl((x, y, 0.72), 0.45, 0.04, 10, color="#EEEEEE")],
              ["cafe table", "table with umbrella"])
    b.add("kiosk", "kiosk", "#2F5D8A", [box((14, -10, 1.3), (2.4, 2.4, 2.6)), box((14, -10, 2.7), (3.0, 3.0, 0.2), color="#C62828")],
          ["newsstand", "blue kiosk"])
    bench(b, "stone bench", "#A8A29A", -15, 10, 0, ["grey bench"])
    bench(b, "wooden bench", "#7B5231", 15, 6, 90, ["brown bench"])
    b.add("bicycle rack", "bicycle rack", "#9E9E9E", [box((-10 + 0.6 * i, 13.5, 0.4), (0.05, 0.7, 0.8)) for i in range(5)], ["bike rack"])
    for i, (x, y) in enumerate(((-8, -16), (8, -16), (-18, 16), (18, 16))):
        lamp_post(b, f"street lamp {i + 1}", x, y)
    # issue 19: walkers (appended, so the ids above stay). The standing people above are goals of
    # the paper's static tasks and stay put; the walkers keep off those tasks' routes.
    b.add("round flower bed", "flower bed", "#C2185B", [cyl((16.0, 11.5, 0), 1.6, 0.45, 16, color="#6D4C41"), cyl((16.0, 11.5, 0.45), 1.4, 0.15, 16)],
          ["flower bed", "flowers"])
    person(b, "person in grey coat", "#757575", 0.0, 0.0, aliases=["person in grey", "man in grey"],
           motion=path([(-20.0, -10.0), (-20.0, 12.0), (-21.5, 12.0), (-21.5, -10.0)], WALK_MPS))
    person(b, "woman in green", "#43A047", 0.0, 0.0, aliases=["woman in a green dress", "person in green dress"], height=1.65,
           motion=path([(19.5, -19.0), (19.5, -1.0), (21.0, -1.0), (21.0, -19.0)], 1.2, start_s=-6.0))
    for i, o in enumerate(TRACKING_WALKERS["plaza"]):
        b.add_object(o, TRACKING_COMMENT if i == 0 else None)
    return b


def terrace(rng) -> SceneBuilder:
    b = SceneBuilder("terrace", "Stepped lawn: lower lawn, middle and upper terraces joined by stone stairs and a grass ramp, with benches, flower beds, a sundial and a pergola.",
                     (-19, -14, 0), (19, 29, 9), (0.0, -7.0, 1.5), 90.0)
    ground(b, "#62A34C", (80, 80), label="lower lawn")
    mid, up = 0.8, 1.6
    b.add("middle terrace", "terrace", "#A39A88", [box((0, 13, mid / 2), (36, 10, mid)), plane((0, 13, mid + 0.01), (36, 10), color="#5E9E48")],
          ["middle lawn", "second terrace"], texture={"pattern": "stripes", "period_m": 0.3, "contrast": 0.2, "axis": "z"})
    b.add("upper terrace", "terrace", "#A39A88", [box((0, 23.5, up / 2), (36, 11, up)), plane((0, 23.5, up + 0.01), (36, 11), color="#5A9944")],
          ["top terrace", "upper lawn", "highest terrace"], texture={"pattern": "stripes", "period_m": 0.3, "contrast": 0.2, "axis": "z"})
    b.add("stone staircase", "stairs", "#BDB5A5", [stairs((0, 5.4, 0), 90, 2.0, 4, mid / 4, 0.4)], ["stone steps", "lower stairs"])
    b.add("upper staircase", "stairs", "#BDB5A5", [stairs((8, 16.4, mid), 90, 2.0, 4, (up - mid) / 4, 0.4)], ["upper steps"])
    b.add("grass ramp", "ramp", "#6AAE52", [ramp((-12, 4, 0), 90, 4.0, 3.0, mid)], ["ramp", "lawn slope"])
    bench(b, "bench on the top terrace", "#7B5231", 0, 26, 0, ["top bench", "upper bench"], z0=up)
    bench(b, "white bench", "#E8E8E2", -8, -4, 0, ["bench on the lower lawn"])
    b.add("red flower bed", "flower bed", "#C62846", [box((-6, 12, mid + 0.2), (3.0, 1.2, 0.4))], ["red flowers", "roses"],
          texture={"pattern": "noise", "period_m": 0.15, "contrast": 0.35, "seed": 9})
    b.add("yellow flower bed", "flower bed", "#F2C12E", [box((4, 12, mid + 0.2), (3.0, 1.2, 0.4))], ["yellow flowers", "sunflowers"],
          texture={"pattern": "noise", "period_m": 0.15, "contrast": 0.35, "seed": 10})
    b.add("sundial", "sundial", "#A1887F", [cyl((-6, 23, up), 0.25, 1.0, 8), cyl((-6, 23, up + 1.0), 0.45, 0.08, 12)], ["stone sundial"])
    b.add("pergola", "pergola", "#D7CCC8", [cyl((8 + dx, 24 + dy, up), 0.1, 2.6, 6) for dx in (-1.5, 1.5) for dy in (-1.5, 1.5)]
          + [box((8, 24 + dy, up + 2.65), (3.6, 0.12, 0.12)) for dy in (-1.5, -0.5, 0.5, 1.5)], ["arbor", "wooden pergola"])
    b.add("stone urn", "urn", "#9E9A90", [cyl((12, 10, mid), 0.45, 0.9, 10)], ["urn", "planter"])
    b.add("wheelbarrow", "wheelbarrow", "#2E7D32", [box((10, -3, 0.45), (1.4, 0.7, 0.4)), box((10.9, -3, 0.2), (0.3, 0.1, 0.4), color=DARK)],
          ["green wheelbarrow"])
    b.add("hedge", "hedge", "#2C6B2A", [box((0, 28.4, 1.0 + up), (36, 0.8, 2.0))], ["back hedge"], target=False,
          texture={"pattern": "noise", "period_m": 0.25, "contrast": 0.3, "seed": 11})
    for i, x in enumerate((-3.0, 3.0)):
        b.add(["left garden lantern", "right garden lantern"][i], "lantern", "#37474F",
              [cyl((x, 4.6, 0), 0.06, 1.4, 6), box((x, 4.6, 1.55), (0.25, 0.25, 0.3), color="#FFE082")], ["garden lantern", "lantern"])
    tree(b, "tree on the upper terrace", -12, 24, z0=up, aliases=["tree at the top"])
    tree(b, "tree on the lower lawn", 13, -6, crown="#4B8F3A", aliases=["tree at the bottom"])
    return b


# -- the harder scenes (issue 16): rooms joined by doorways, dead-end corners, narrow passages,
# low beams and ceilings, clutter and look-alikes -------------------------------------------
#
# Real sizes: interior walls 0.12 m, exterior walls 0.25-0.3 m, ceilings 2.6-2.8 m, door
# heights 2.1 m with a lintel above. Openings a drone passes are 1.6-2.0 m (double doors, open
# archways: a 0.25 m body with the planner's 0.45 m clearance cannot pass a 0.9 m door leaf);
# furniture at catalogue sizes (beds 1.6 x 2.0 m, sofas 2.2 x 0.9 m, desks 1.4 x 0.7 x 0.74 m,
# cars 4.2 x 1.8 m). Walls, ceilings, beams and unnamed clutter are ``target = false``.


def wall_run(axis, at, a0, a1, h, t, gaps=(), lintel=2.1):
    """Boxes of one straight wall with door openings.

    ``axis`` 'x': the wall runs along x at y = ``at`` from x = ``a0`` to ``a1`` ('y' likewise).
    ``gaps``: (g0, g1) openings along the wall; a lintel fills each from ``lintel`` up to ``h``.
    """
    spans, cur = [], a0
    for g0, g1 in sorted(gaps):
        if g0 > cur:
            spans.append((cur, g0))
        cur = g1
    if cur < a1:
        spans.append((cur, a1))

    def seg(s0, s1, z0, z1):
        mid, length = (s0 + s1) / 2, s1 - s0
        if axis == "x":
            return box((mid, at, (z0 + z1) / 2), (length, t, z1 - z0))
        return box((at, mid, (z0 + z1) / 2), (t, length, z1 - z0))

    out = [seg(s0, s1, 0.0, h) for s0, s1 in spans]
    out += [seg(g0, g1, lintel, h) for g0, g1 in gaps if lintel < h]
    return out


def room_shell(b, name, x1, y1, h, runs, wall_color="#E6E1D8", floor_color="#A07850", ceiling_color="#EEEDEA", t_ext=0.25,
               floor_texture=None):
    """Exterior walls of the rectangle 0..x1 x 0..y1 (``runs`` adds interior runs), a floor and a ceiling."""
    parts = [
        box((x1 / 2, 0.0, h / 2), (x1 + t_ext, t_ext, h)),
        box((x1 / 2, y1, h / 2), (x1 + t_ext, t_ext, h)),
        box((0.0, y1 / 2, h / 2), (t_ext, y1 + t_ext, h)),
        box((x1, y1 / 2, h / 2), (t_ext, y1 + t_ext, h)),
    ]
    for r in runs:
        parts += r
    b.add(name, "wall", wall_color, parts, target=False)
    b.add("floor", "floor", floor_color, [plane((x1 / 2, y1 / 2, 0.0), (x1 + 1, y1 + 1))], target=False,
          texture=floor_texture or {"pattern": "noise", "period_m": 0.5, "contrast": 0.15, "seed": 1})
    b.add("ceiling", "ceiling", ceiling_color, [box((x1 / 2, y1 / 2, h + 0.1), (x1 + 1, y1 + 1, 0.2))], target=False)


def table(center, size, color=None, legs=True):
    """A table: top slab 0.04 m and four 0.05 m legs; ``size`` (x, y, height)."""
    x, y = center
    sx, sy, h = size
    parts = [box((x, y, h - 0.02), (sx, sy, 0.04), color=color)]
    if legs:
        for dx in (-1, 1):
            for dy in (-1, 1):
                parts.append(box((x + dx * (sx / 2 - 0.06), y + dy * (sy / 2 - 0.06), (h - 0.04) / 2), (0.05, 0.05, h - 0.04), color=color))
    return parts


def chair(x, y, facing_deg, color=None, seat=0.46, back=0.9):
    """A chair 0.45 x 0.45 m, seat at ``seat`` m, backrest up to ``back`` m, facing ``facing_deg``."""
    bx, by = _local(x, y, facing_deg, -0.2, 0.0)
    return [box((x, y, seat / 2), (0.45, 0.45, seat), facing_deg, color=color),
            box((bx, by, (seat + back) / 2), (0.05, 0.45, back - seat), facing_deg, color=color)]


def floor_lamp(x, y, shade="#F3E5C0"):
    return [cyl((x, y, 0.0), 0.15, 0.03, 10), cyl((x, y, 0.03), 0.02, 1.45, 6), cyl((x, y, 1.45), 0.2, 0.3, 10, color=shade)]


def potted_plant(x, y, h=1.3, pot="#9C5B3B"):
    return [cyl((x, y, 0.0), 0.2, 0.4, 10, color=pot), sph((x, y, 0.4 + (h - 0.4) / 2), (h - 0.4) / 2 + 0.05, 5)]


def apartment(rng) -> SceneBuilder:
    """A 15 x 12 m flat under a 2.6 m ceiling: living/dining room, kitchen, a 2 m hallway, two
    bedrooms, a bathroom, a laundry and a study behind it, joined by 1.6-1.8 m openings."""
    h = 2.6
    b = SceneBuilder("apartment", "Flat with living room, kitchen, hallway, two bedrooms, bathroom, laundry and study joined by doorways under a 2.6 m ceiling.",
                     (0.2, 0.2, 0.1), (14.8, 11.8, 2.55), (1.4, 2.8, 1.5), 0.0, light=(0.3, 0.2, 0.93), ambient=0.5, indoor=True)
    ti = 0.12
    runs = [
        wall_run("y", 8.0, 0.0, 6.5, h, ti, [(0.9, 2.7)]),            # living | kitchen (+ closet)
        wall_run("x", 4.5, 8.0, 15.0, h, ti),                          # kitchen | closet, laundry
        wall_run("x", 6.5, 0.0, 12.0, h, ti, [(3.9, 5.7)]),            # living, closet | hallway
        wall_run("y", 12.0, 4.5, 8.5, h, ti, [(6.6, 8.4)]),            # closet, hallway | laundry
        wall_run("x", 8.5, 0.0, 15.0, h, ti, [(1.7, 3.3), (5.9, 7.5), (9.5, 11.1), (12.9, 14.7)]),  # hallway | bedrooms, bath, study
        wall_run("y", 5.0, 8.5, 12.0, h, ti),                          # bedroom | bedroom 2
        wall_run("y", 9.0, 8.5, 12.0, h, ti),                          # bedroom 2 | bathroom
        wall_run("y", 12.0, 8.5, 12.0, h, ti),                         # bathroom | study
    ]
    room_shell(b, "apartment walls", 15.0, 12.0, h, runs, floor_texture={"pattern": "stripes", "period_m": 0.18, "contrast": 0.12, "axis": "x"})
    b.add("ceiling beam", "beam", "#CFC8BB", [box((4.0, 3.25, 2.45), (0.2, 6.5, 0.3))], target=False)
    b.add("closet block", "wall", "#E6E1D8", [box((10.0, 5.5, h / 2), (3.88, 1.88, h))], target=False)
    # living and dining room (x 0..8, y 0..6.5)
    b.add("grey sofa", "sofa", "#7F8489", [box((2.6, 4.3, 0.22), (2.2, 0.8, 0.44)), box((2.6, 4.75, 0.45), (2.2, 0.2, 0.9)),
                                            box((1.55, 4.35, 0.31), (0.2, 0.9, 0.62)), box((3.65, 4.35, 0.31), (0.2, 0.9, 0.62))],
          ["sofa", "couch", "grey couch"])
    b.add("coffee table", "table", "#8B6A45", table((2.6, 2.2), (1.0, 0.5, 0.42)), ["low table"])
    b.add("TV", "tv", "#1E1E22", [box((2.6, 0.4, 0.25), (1.8, 0.45, 0.5), color="#5B4636"), box((2.6, 0.3, 0.95), (1.4, 0.06, 0.8))],
          ["television", "TV stand"])
    b.add("living room bookshelf", "shelf", "#6B4E33", [box((5.2, 2.1, 0.95), (0.4, 2.4, 1.9))], ["bookshelf", "room divider", "bookcase"],
          texture={"pattern": "stripes", "period_m": 0.38, "contrast": 0.35, "axis": "z"})
    b.add("dining table", "table", "#B08A5A", table((6.2, 4.6), (1.6, 0.9, 0.75)), ["kitchen table", "wooden table"])
    b.add("dining chairs", "chair", "#5D4037", chair(5.8, 3.7, 90) + chair(6.6, 3.7, 90) + chair(5.8, 5.5, -90) + chair(6.6, 5.5, -90),
          target=False)
    b.add("living room floor lamp", "lamp", "#3A3A3A", floor_lamp(0.5, 6.0), ["floor lamp", "standing lamp"])
    b.add("potted plant in the living room", "plant", "#3E8E41", potted_plant(7.35, 5.9), ["plant in the living room"])
    b.add("blue armchair", "armchair", "#35598F", [box((6.8, 1.0, 0.22), (0.8, 0.8, 0.44)), box((6.8, 0.65, 0.45), (0.8, 0.15, 0.9))],
          ["armchair", "blue chair"])
    b.add("living room window", "window", GLASS, [box((4.6, 0.14, 1.4), (1.6, 0.04, 1.3))], ["window"], material="glass")
    # kitchen (x 8..15, y 0..4.5)
    b.add("kitchen counter", "counter", "#D9D4CC", [box((12.0, 0.425, 0.45), (6.0, 0.6, 0.9)), box((12.0, 0.3, 1.85), (6.0, 0.35, 0.7), color="#C9C2B6")],
          ["worktop"], target=False)
    b.add("kitchen sink", "sink", "#B8C2CC", [box((11.0, 0.45, 0.92), (0.8, 0.5, 0.06))], ["sink"])
    b.add("stove", "stove", "#2A2A2E", [box((13.6, 0.45, 0.92), (0.6, 0.55, 0.05))], ["cooker", "hob"])
    b.add("microwave", "microwave", "#E0E0E0", [box((9.8, 0.45, 1.05), (0.5, 0.38, 0.3))], ["microwave oven"])
    b.add("fridge", "fridge", "#F2F2F2", [box((14.45, 3.95, 0.925), (0.75, 0.7, 1.85))], ["refrigerator", "white fridge"])
    b.add("kitchen island", "island", "#9E8B73", [box((11.5, 2.6, 0.46), (2.2, 0.9, 0.92))], ["island", "breakfast bar"])
    b.add("bar stools", "stool", "#404040", [cyl((x, 3.4, 0.0), 0.18, 0.75, 8) for x in (10.9, 11.5, 12.1)], target=False)
    b.add("trash bin", "bin", "#4A4A4A", [cyl((8.45, 4.1, 0.0), 0.18, 0.6, 8)], ["grey bin", "rubbish bin"])
    b.add("recycling bin", "bin", "#2F6DB5", [cyl((8.95, 4.1, 0.0), 0.18, 0.6, 8)], ["blue bin"])
    b.add("kitchen wall clock", "clock", "#F5F5F5", [box((8.075, 3.3, 1.9), (0.03, 0.32, 0.32))], ["wall clock", "clock"])
    # hallway (x 0..12, y 6.5..8.5)
    b.add("front door", "door", "#6D4C41", [box((0.185, 7.5, 1.05), (0.12, 1.0, 2.1))], ["entrance door", "apartment door"])
    b.add("shoe cabinet", "cabinet", "#E8E2D6", [box((1.1, 6.76, 0.5), (1.2, 0.4, 1.0))], ["shoe rack"])
    b.add("coat rack", "coat rack", "#5D4037", [cyl((0.55, 8.1, 0.0), 0.02, 1.8, 6), cyl((0.55, 8.1, 0.0), 0.2, 0.03, 8)], ["coat stand"])
    b.add("storage cabinet", "cabinet", "#D7CCC8", [box((9.9, 6.71, 1.0), (1.8, 0.3, 2.0))], ["tall cabinet", "hallway cupboard"])
    b.add("painting of sunflowers", "painting", "#E0B22E", [box((2.4, 6.575, 1.55), (0.9, 0.03, 0.6))], ["yellow painting", "sunflower painting"])
    b.add("painting of a sailboat", "painting", "#3A6EA5", [box((4.6, 8.425, 1.55), (0.9, 0.03, 0.6))], ["blue painting", "sailboat painting"])
    # bedroom (x 0..5, y 8.5..12)
    b.add("double bed", "bed", "#E8E4DA", [box((2.7, 10.875, 0.275), (1.6, 2.0, 0.55)), box((2.7, 11.82, 0.55), (1.6, 0.08, 1.1), color="#6D4C41")],
          ["bed", "big bed"])
    b.add("wardrobe", "wardrobe", "#BCAAA4", [box((0.425, 10.0, 1.05), (0.6, 2.0, 2.1))], ["closet", "wardrobe closet"])
    b.add("nightstands", "nightstand", "#6D4C41", [box((1.45, 11.6, 0.275), (0.45, 0.4, 0.55)), box((3.95, 11.6, 0.275), (0.45, 0.4, 0.55))], target=False)
    b.add("bedside lamp near the wardrobe", "lamp", "#F0D58C", [cyl((1.45, 11.6, 0.55), 0.12, 0.35, 10)], ["left bedside lamp"])
    b.add("bedside lamp near the window", "lamp", "#F0D58C", [cyl((3.95, 11.6, 0.55), 0.12, 0.35, 10)], ["right bedside lamp"])
    b.add("bedroom window", "window", GLASS, [box((4.2, 11.86, 1.5), (1.0, 0.04, 1.2))], [], material="glass")
    b.add("potted plant in the bedroom", "plant", "#2E7D32", potted_plant(4.5, 10.4, 1.1), ["plant in the bedroom"])
    # second bedroom (x 5..9, y 8.5..12)
    b.add("single bed", "bed", "#5C8FD6", [box((8.45, 10.6, 0.25), (0.9, 2.0, 0.5))], ["small bed", "blue bed", "kid's bed"])
    b.add("toy chest", "chest", "#E57373", [box((5.6, 11.55, 0.225), (0.8, 0.4, 0.45))], ["toy box", "red chest"])
    b.add("small desk", "desk", "#F5F0E6", table((5.36, 9.8), (0.6, 1.2, 0.72)), ["white desk", "kid's desk"])
    b.add("desk lamp", "lamp", "#43A047", [cyl((5.3, 10.2, 0.72), 0.08, 0.4, 8)], ["green lamp"])
    # bathroom (x 9..12, y 8.5..12)
    b.add("bathtub", "bathtub", "#FAFAFA", [box((9.91, 11.49, 0.3), (1.7, 0.75, 0.6))], ["bath", "tub"])
    b.add("toilet", "toilet", "#FFFFFF", [box((11.6, 10.2, 0.2), (0.65, 0.4, 0.4)), box((11.85, 10.2, 0.6), (0.18, 0.4, 0.4))], ["WC"])
    b.add("bathroom sink", "sink", "#ECEFF1", [box((9.29, 9.5, 0.425), (0.45, 0.6, 0.85))], ["washbasin", "vanity"])
    b.add("bathroom mirror", "mirror", "#C9D6DF", [box((9.075, 9.5, 1.6), (0.03, 0.6, 0.8))], ["mirror"])
    # laundry (x 12..15, y 4.5..8.5)
    b.add("washing machine", "washing machine", "#F4F4F4", [box((14.5, 4.86, 0.425), (0.6, 0.6, 0.85)), cyl((14.5, 4.54, 0.3), 0.18, 0.03, 12, color=GLASS)],
          ["washer"])
    b.add("tumble dryer", "dryer", "#F0F0F0", [box((13.8, 4.86, 0.425), (0.6, 0.6, 0.85))], ["dryer", "clothes dryer"])
    b.add("laundry basket", "basket", "#D7B98E", [cyl((12.55, 5.0, 0.0), 0.25, 0.5, 10)], ["basket"])
    b.add("ironing board", "ironing board", "#90A4AE", [box((14.6, 6.2, 0.9), (0.35, 1.3, 0.04)), box((14.6, 6.2, 0.45), (0.05, 0.9, 0.86), color=DARK)],
          [])
    # study (x 12..15, y 8.5..12)
    b.add("study desk", "desk", "#8D6E63", table((14.52, 10.6), (0.7, 1.6, 0.75)), ["desk", "computer desk"])
    b.add("computer monitor", "monitor", "#202124", [box((14.65, 10.6, 0.97), (0.05, 0.6, 0.38))], ["monitor", "screen"])
    b.add("office chair", "chair", "#263238", chair(13.75, 10.6, 0.0, seat=0.5, back=1.05), ["desk chair"])
    b.add("study bookshelf", "shelf", "#8D6E63", [box((12.24, 10.5, 1.0), (0.35, 2.0, 2.0))], ["bookshelf in the study", "bookcase in the study"],
          texture={"pattern": "stripes", "period_m": 0.4, "contrast": 0.35, "axis": "z"})
    b.add("floor lamp in the study", "lamp", "#3A3A3A", floor_lamp(12.7, 11.6), ["study lamp"])
    return b


def desk_cluster(cx, cy, chair_color="#37474F", top="#E8E4DC"):
    """Four desks (1.4 x 0.7 x 0.74 m) facing in pairs, a 1.25 m screen between them, monitors,
    chairs and two linear pendant lights hung at 2.0 m."""
    parts = [box((cx, cy, 0.72), (2.8, 1.4, 0.04), color=top)]
    parts += [box((cx + dx, cy, 0.35), (0.03, 1.4, 0.7), color="#9E9E9E") for dx in (-1.38, 0.0, 1.38)]
    parts.append(box((cx, cy, 0.995), (2.8, 0.04, 0.51), color="#7A8C99"))
    for dx in (-0.7, 0.7):
        for dy in (-1, 1):
            parts.append(box((cx + dx, cy + dy * 0.18, 0.92), (0.55, 0.04, 0.36), color=DARK))
            parts += chair(cx + dx, cy + dy * 1.0, -90 * dy, color=chair_color, seat=0.5, back=1.0)
    for dy in (-0.35, 0.35):
        parts.append(box((cx, cy + dy, 2.04), (2.6, 0.15, 0.08), color="#ECEFF1"))
    parts.append(box((cx, cy, 2.37), (0.03, 0.03, 0.58), color="#9E9E9E"))
    return parts


def office_floor(rng) -> SceneBuilder:
    """A 26 x 17 m office floor under a 2.7 m ceiling: open plan with six desk clusters and 1.7 m
    aisles, two meeting rooms, a 2 m corridor (dropped ceiling and a duct over part of it), a
    kitchenette, a copy room, a storage room and a server room, joined by 1.6-2.0 m doorways."""
    h = 2.7
    b = SceneBuilder("office_floor", "Office floor: open plan with desk clusters, meeting rooms, a corridor with a low duct, kitchenette, copy room, storage and server room.",
                     (0.3, 0.3, 0.1), (25.7, 16.7, 2.65), (1.5, 5.0, 1.5), 0.0, light=(0.25, 0.3, 0.92), ambient=0.5, indoor=True)
    ti = 0.12
    runs = [
        wall_run("y", 17.0, 0.0, 10.5, h, ti, [(2.0, 3.8)]),
        wall_run("x", 6.0, 17.0, 26.0, h, ti),
        wall_run("x", 10.5, 0.0, 26.0, h, ti, [(1.5, 3.5), (12.9, 14.7), (19.9, 21.7)]),
        wall_run("x", 12.5, 0.0, 26.0, h, ti, [(4.0, 5.8), (8.1, 9.7), (13.9, 15.5), (23.4, 25.1)]),
        wall_run("y", 7.0, 12.5, 17.0, h, ti),
        wall_run("y", 11.0, 12.5, 17.0, h, ti),
        wall_run("y", 17.0, 12.5, 17.0, h, ti),
    ]
    room_shell(b, "office walls", 26.0, 17.0, h, runs, wall_color="#E4E6E8", floor_color="#6E7580", ceiling_color="#F0F0EE", t_ext=0.3,
               floor_texture={"pattern": "checker", "period_m": 0.5, "contrast": 0.08})
    b.add("concrete beam", "beam", "#C8C8C4", [box((6.75, 5.25, 2.45), (0.3, 10.5, 0.5))], target=False)
    b.add("dropped ceiling", "ceiling", "#E0E0DC", [box((21.5, 11.5, 2.55), (9.0, 1.88, 0.3))], target=False)
    b.add("ventilation duct", "duct", "#B0B6BB", [box((11.0, 11.95, 2.25), (10.0, 0.45, 0.3))], ["duct", "air duct"], target=False)
    # open plan (x 0..17, y 0..10.5)
    for i, (cx, cy) in enumerate((cx, cy) for cy in (2.2, 7.2) for cx in (4.5, 9.0, 13.5)):
        b.add(f"desk cluster {i + 1}", "desk", "#E8E4DC", desk_cluster(cx, cy), target=False)
    b.add("glass entrance door", "door", GLASS, [box((0.21, 5.0, 1.05), (0.12, 2.0, 2.1))], ["entrance", "front door", "glass door"], material="glass")
    b.add("reception desk", "desk", "#5D4037", [box((1.4, 1.3, 0.55), (2.0, 0.7, 1.1))], ["front desk", "reception"])
    b.add("coat stand", "coat rack", "#4E342E", [cyl((0.7, 9.8, 0.0), 0.02, 1.8, 6), cyl((0.7, 9.8, 0.0), 0.22, 0.03, 8)], ["coat rack"])
    b.add("mobile whiteboard", "whiteboard", "#FAFAFA", [box((8.2, 5.2, 1.3), (0.05, 1.3, 1.0)), box((8.2, 5.2, 0.4), (0.5, 1.2, 0.8), color="#9E9E9E")],
          ["whiteboard on wheels", "rolling whiteboard"])
    b.add("tall potted plant", "plant", "#2E7D32", potted_plant(16.1, 9.6, 1.8), ["big plant", "tall plant"])
    b.add("grey filing cabinets", "cabinet", "#8A9299", [box((16.72, 6.0, 0.65), (0.44, 2.0, 1.3))], ["filing cabinets", "file cabinets"])
    # large meeting room (x 17..26, y 0..6)
    b.add("conference table", "table", "#6D4C41", table((21.8, 3.0), (4.0, 1.4, 0.75)), ["meeting table", "big table"])
    cparts = []
    for dx in (-1.3, 0.0, 1.3):
        cparts += chair(21.8 + dx, 1.85, 90, color="#263238") + chair(21.8 + dx, 4.15, -90, color="#263238")
    b.add("conference chairs", "chair", "#263238", cparts, target=False)
    b.add("TV screen", "tv", "#111214", [box((25.8, 3.0, 1.45), (0.06, 1.8, 1.0))], ["screen", "TV", "display"])
    b.add("whiteboard in the large meeting room", "whiteboard", "#FAFAFA", [box((20.2, 5.92, 1.5), (2.4, 0.03, 1.2))],
          ["large meeting room whiteboard"])
    b.add("potted plant in the meeting room", "plant", "#388E3C", potted_plant(25.3, 0.75, 1.2), ["meeting room plant"])
    # small meeting room (x 17..26, y 6..10.5)
    b.add("round table", "table", "#BCAAA4", [cyl((22.0, 8.2, 0.0), 0.06, 0.72, 8), cyl((22.0, 8.2, 0.72), 0.6, 0.04, 16)], ["small round table"])
    b.add("round table chairs", "chair", "#00796B", chair(21.0, 8.2, 0.0) + chair(23.0, 8.2, 180) + chair(22.0, 7.2, 90), target=False)
    b.add("whiteboard in the small meeting room", "whiteboard", "#FAFAFA", [box((25.82, 8.2, 1.5), (0.03, 2.0, 1.2))],
          ["small meeting room whiteboard"])
    # corridor (y 10.5..12.5)
    b.add("fire extinguisher", "extinguisher", "#D32F2F", [cyl((16.4, 12.3, 0.3), 0.1, 0.55, 8)], ["red extinguisher", "extinguisher"])
    b.add("notice board", "board", "#C9A46B", [box((6.45, 12.425, 1.5), (0.9, 0.03, 0.9))], ["bulletin board", "cork board"],
          texture={"pattern": "noise", "period_m": 0.1, "contrast": 0.3, "seed": 6})
    # kitchenette (x 0..7, y 12.5..17)
    b.add("kitchenette counter", "counter", "#D9D4CC", [box((2.6, 16.55, 0.45), (4.9, 0.6, 0.9)), box((2.6, 16.67, 1.85), (4.9, 0.35, 0.7), color="#C9C2B6")],
          target=False)
    b.add("coffee machine", "coffee machine", "#212121", [box((2.0, 16.55, 1.125), (0.35, 0.4, 0.45))], ["espresso machine", "coffee maker"])
    b.add("office microwave", "microwave", "#E0E0E0", [box((4.2, 16.55, 1.05), (0.5, 0.38, 0.3))], ["microwave"])
    b.add("office fridge", "fridge", "#ECEFF1", [box((6.5, 16.4, 0.925), (0.7, 0.7, 1.85))], ["fridge", "refrigerator"])
    b.add("kitchen table", "table", "#8D6E63", [cyl((3.0, 14.4, 0.0), 0.06, 0.75, 8), cyl((3.0, 14.4, 0.75), 0.5, 0.04, 14)], ["round kitchen table"])
    b.add("kitchen chairs", "chair", "#FFB300", chair(2.1, 14.4, 0.0) + chair(3.9, 14.4, 180), target=False)
    b.add("recycling bins", "bin", "#1565C0", [cyl((0.45, y, 0.0), 0.2, 0.8, 8) for y in (13.1, 13.6, 14.1)], ["bins", "recycling station"])
    # copy room (x 7..11, y 12.5..17)
    b.add("large printer", "printer", "#ECEFF1", [box((10.4, 16.35, 0.6), (0.9, 0.7, 1.2)), box((10.4, 16.35, 1.22), (0.6, 0.5, 0.04), color=DARK)],
          ["big printer", "copier", "photocopier"])
    b.add("small printer", "printer", "#ECEFF1", [box((7.6, 16.5, 0.375), (0.8, 0.5, 0.75), color="#8D6E63"), box((7.6, 16.5, 0.9), (0.45, 0.4, 0.3))],
          ["desktop printer"])
    b.add("paper shelf", "shelf", "#B0BEC5", [box((7.26, 14.2, 0.9), (0.4, 1.4, 1.8))], ["paper cabinet"])
    # storage room (x 11..17, y 12.5..17)
    b.add("metal shelving", "shelf", "#78909C", [box((14.0, 16.6, 1.1), (5.6, 0.5, 2.2))], ["metal shelves", "storage shelves"],
          texture={"pattern": "stripes", "period_m": 0.45, "contrast": 0.4, "axis": "z"})
    b.add("stack of cardboard boxes", "boxes", "#B08A5A", [box((12.3, 14.3, 0.6), (1.2, 1.0, 1.2)), box((12.2, 14.3, 1.4), (0.7, 0.6, 0.4))],
          ["cardboard boxes", "boxes"])
    b.add("step ladder", "ladder", "#FBC02D", [box((16.5, 13.4, 0.75), (0.5, 0.6, 1.5))], ["ladder", "yellow ladder"])
    b.add("vacuum cleaner", "vacuum", "#D32F2F", [box((15.2, 15.4, 0.2), (0.35, 0.3, 0.4))], ["vacuum", "hoover"])
    # server room (x 17..26, y 12.5..17)
    b.add("server racks", "server rack", "#212121", [box((20.7, 13.8, 1.0), (5.4, 1.0, 2.0)), box((20.7, 16.2, 1.0), (5.4, 1.0, 2.0))],
          ["server rack", "racks", "servers"], texture={"pattern": "stripes", "period_m": 0.6, "contrast": 0.3, "axis": "x"})
    b.add("air conditioning unit", "air conditioner", "#CFD8DC", [box((25.45, 14.75, 0.95), (0.8, 1.5, 1.9))], ["AC unit", "cooling unit"])
    b.add("UPS cabinet", "cabinet", "#455A64", [box((25.3, 16.45, 0.9), (0.9, 0.6, 1.8))], ["UPS", "battery cabinet"])
    return b


def parking_garage(rng) -> SceneBuilder:
    """An underground car park, 32 x 24 m: a slab at 2.8 m with downstand beams to 2.3 m and a
    duct to 2.0 m, a ring of 3.9 m aisles around a ramp core, nose-in bays along both long walls,
    an elevator lobby and a bike cage as dead-end rooms with 1.8 m doorways."""
    h = 2.8
    b = SceneBuilder("parking_garage", "Underground car park: low ceiling with beams and a duct, a ring aisle around a ramp core, parked cars, an elevator lobby and a bike cage.",
                     (0.3, 0.3, 0.1), (31.7, 23.7, 2.75), (3.0, 7.5, 1.5), 0.0, light=(0.2, 0.2, 0.96), ambient=0.55, indoor=True)
    t = 0.2
    runs = [
        wall_run("y", 4.5, 9.0, 15.0, h, t, [(11.1, 12.9)]),
        wall_run("x", 9.0, 0.0, 4.5, h, t),
        wall_run("x", 15.0, 0.0, 4.5, h, t),
    ]
    room_shell(b, "garage walls", 32.0, 24.0, h, runs, wall_color="#BDBDB8", floor_color="#6B6B6B", ceiling_color="#A9A9A4", t_ext=0.3,
               floor_texture={"pattern": "noise", "period_m": 0.6, "contrast": 0.2, "seed": 3})
    b.add("ramp core", "wall", "#A7A7A2", [box((16.0, 12.0, h / 2), (12.0, 5.0, h))], target=False,
          texture={"pattern": "stripes", "period_m": 0.9, "contrast": 0.15, "axis": "z"})
    cols = [(x, y) for x in (6.25, 13.75, 21.25, 28.75) for y in (5.4, 18.6)] + [(7.25, 12.0), (24.0, 12.0)]
    b.add("concrete columns", "column", "#9E9E99", [box((x, y, h / 2), (0.5, 0.5, h)) for x, y in cols], target=False)
    beams = [box((16.0, y, 2.55), (32.0, 0.4, 0.5)) for y in (5.4, 18.6)] + [box((x, 12.0, 2.55), (0.4, 24.0, 0.5)) for x in (6.25, 13.75, 21.25, 28.75)]
    b.add("ceiling beams", "beam", "#B3B3AE", beams, target=False)
    b.add("ventilation duct", "duct", "#C0C4C8", [box((16.0, 16.0, 2.2), (28.0, 0.6, 0.4))], ["duct"], target=False)
    b.add("bike cage fence", "fence", "#8E9497", wall_run("y", 26.0, 9.5, 14.5, 2.2, 0.05, [(11.0, 12.8)], lintel=2.2)
          + [box((28.95, 9.5, 1.1), (5.9, 0.05, 2.2)), box((28.95, 14.5, 1.1), (5.9, 0.05, 2.2))], target=False)
    # parked cars: nose-in along the south wall (yaw -90) and the north wall (yaw 90); 2.5 m bays
    named_s = {7.5: ("red car", "#C62828", ["red sedan"]), 12.5: ("white car in the south row", "#F2F2F2", ["white car by the charger"]),
               22.5: ("blue car", "#1E4FA0", ["blue sedan"])}
    named_n = {5.0: ("white car in the north row", "#EFEFEF", ["white car near the lobby"]), 22.5: ("yellow car", "#F2C12E", ["yellow taxi", "taxi"])}
    palette = ["#3C3F44", "#8A9097", "#5A6B7D", "#2B2B2E", "#7D2E2E", "#B7B9BC", "#44574A"]
    for row, y, yaw, named, empty in (("south", 2.7, -90, named_s, (10.0, 25.0)), ("north", 21.3, 90, named_n, (12.5, 15.0))):
        for k in range(12):
            x = 2.5 + 2.5 * k
            if x in empty:
                continue
            if x in named:
                nm, col, al = named[x]
                car(b, nm, col, x, y, yaw, al)
            else:
                car(b, f"parked car {row} {k + 1}", palette[int(rng.integers(len(palette)))], x, y, yaw, target=False)
    van(b, "white van", "#F5F5F5", 15.0, 21.3, 90, ["van", "delivery van"])
    b.add("charging station by the red car", "charger", "#2E7D32", [box((10.0, 0.27, 1.2), (0.35, 0.2, 0.7)), box((10.0, 0.25, 0.6), (0.12, 0.12, 0.5), color=DARK)],
          ["EV charger by the red car", "charger by the red car"])
    b.add("charging station by the blue car", "charger", "#2E7D32", [box((25.0, 0.27, 1.2), (0.35, 0.2, 0.7)), box((25.0, 0.25, 0.6), (0.12, 0.12, 0.5), color=DARK)],
          ["EV charger by the blue car", "charger by the blue car"])
    # elevator lobby (x 0..4.5, y 9..15)
    b.add("elevator doors", "elevator", "#9EA7AD", [box((0.21, 12.0, 1.05), (0.12, 1.2, 2.1))], ["elevator", "lift"])
    bench(b, "lobby bench", "#6D4C41", 2.3, 14.55, 0, ["bench"])
    b.add("lobby trash can", "bin", "#424242", [cyl((3.95, 9.55, 0.0), 0.2, 0.75, 8)], ["trash can", "bin"])
    # west side
    b.add("green stairwell door", "door", "#2E7D32", [box((0.21, 6.8, 1.05), (0.12, 1.0, 2.1))], ["stairwell door", "stairs door", "green door"])
    b.add("exit sign", "sign", "#2EAD4B", [box((0.2, 6.8, 2.3), (0.08, 0.5, 0.2))], ["green exit sign"])
    b.add("pay station", "ticket machine", "#1565C0", [box((4.85, 10.2, 0.8), (0.5, 0.5, 1.6))], ["ticket machine", "parking pay machine"])
    # east side
    b.add("garage exit shutter", "door", "#7B8287", [box((31.79, 16.5, 1.3), (0.12, 3.0, 2.6))], ["exit shutter", "roller shutter", "garage door"],
          texture={"pattern": "stripes", "period_m": 0.12, "contrast": 0.35, "axis": "z"})
    b.add("bicycles", "bicycle", "#D84315", [box((30.6, y, 0.55), (1.7, 0.05, 0.8)) for y in (12.0, 12.8, 13.6)], ["bikes", "bicycle"])
    b.add("red motorcycle", "motorcycle", "#B71C1C", [box((27.6, 10.25, 0.55), (2.0, 0.5, 0.9)), box((28.4, 10.25, 1.1), (0.15, 0.7, 0.1), color=DARK)],
          ["motorcycle", "motorbike"])
    b.add("fire hose cabinet", "cabinet", "#C62828", [box((16.0, 14.55, 1.3), (0.8, 0.1, 0.8))], ["fire hose", "red cabinet"])
    b.add("level sign", "sign", "#FDD835", [box((16.0, 9.47, 1.9), (1.2, 0.04, 0.5))], ["P1 sign", "yellow sign"])
    b.add("traffic cones", "cone", "#FF6F00", [cyl((x, 17.0, 0.0), 0.17, 0.5, 8) for x in (9.0, 9.6)], ["cones", "orange cones"])
    return b


def station_concourse(rng) -> SceneBuilder:
    """Issue 19: a station concourse whose crowd crosses the routes. Passengers stream between the
    street doors (south wall) and the platform gates (north wall) on two two-way lanes (x = 12 and
    x = 22.5), so every flight from the west entrance to the east half crosses them; a man pushes a
    luggage cart and stops at the information desk, a traveller paces round a column. The drone
    starts (and the tasks fly) at 2.5 m, above head height."""
    b = SceneBuilder("station_concourse", "Station concourse: columns, ticket machines, an information desk, kiosks, platform gates and a crowd crossing the hall.",
                     (0.3, 0.3, 0.2), (37.7, 27.7, 8.7), (3.0, 14.0, 2.5), 0.0, light=(0.25, 0.3, 0.92), ambient=0.5, indoor=True)
    walls(b, "concourse walls", 0, 38, 0, 28, 9.0, color="#CFC8BA", floor_color="#9C968C")
    cols = [(x, y) for x in (7.0, 17.5, 28.0) for y in (7.0, 21.0)]
    b.add("columns", "column", "#B8B2A6", [box((x, y, 4.5), (0.8, 0.8, 9.0)) for x, y in cols], target=False)
    b.add("departure board", "board", "#1B2A49", [box((19.0, 27.8, 4.6), (8.0, 0.3, 2.4))], ["departures board", "timetable board"])
    b.add("information desk", "desk", "#2E7D9A", [box((19.0, 14.0, 0.6), (4.0, 1.6, 1.2)), cyl((19.0, 14.0, 1.2), 0.08, 1.4, 6, color="#777777"),
                                                 box((19.0, 14.0, 2.8), (0.9, 0.12, 0.6), color="#F5F5F5")],
          ["info desk", "information counter"])
    b.add("red ticket machine", "ticket machine", "#C62828", [box((8.0, 0.55, 0.9), (0.9, 0.6, 1.8))], ["red machine"])
    b.add("blue ticket machine", "ticket machine", "#1565C0", [box((9.8, 0.55, 0.9), (0.9, 0.6, 1.8))], ["blue machine"])
    b.add("coffee kiosk", "kiosk", "#6D4C41", [box((31.0, 4.0, 1.3), (3.0, 2.0, 2.6)), box((31.0, 4.0, 2.7), (3.4, 2.4, 0.2), color="#EFEBE9")],
          ["coffee stand", "brown kiosk"])
    b.add("newsstand", "kiosk", "#00897B", [box((31.0, 23.5, 1.25), (2.6, 2.0, 2.5))], ["news kiosk", "green kiosk"])
    for i, x in enumerate((12.6, 23.1)):
        b.add(f"platform gate {i + 1}", "gate", ["#F9A825", "#EF6C00"][i], [box((x, 27.85, 1.3), (3.0, 0.12, 2.6))],
              [f"gate {i + 1}", f"platform entrance {i + 1}"])
    for i, x in enumerate((12.6, 23.1)):
        b.add(f"street door {i + 1}", "door", "#90A4AE", [box((x, 0.15, 1.3), (3.0, 0.12, 2.6))], [f"south door {i + 1}", f"exit {i + 1}"],
              material="glass")
    b.add("luggage lockers", "lockers", "#78909C", [box((37.6, 14.0, 1.0), (0.7, 5.0, 2.0))], ["lockers", "left-luggage lockers"])
    bench(b, "bench by the west wall", "#8D6E63", 4.0, 25.0, 0, ["west bench"])
    bench(b, "bench by the east wall", "#8D6E63", 34.0, 25.0, 0, ["east bench"])
    b.add("station clock", "clock", "#FAFAFA", [box((17.5, 20.55, 3.2), (0.9, 0.08, 0.9))], ["clock"], target=False)
    b.add("rubbish bin", "bin", "#37474F", [cyl((5.0, 9.5, 0.0), 0.25, 0.9, 8)], ["bin", "trash can"])
    b.add("plant pot", "plant", "#388E3C", [cyl((34.0, 9.0, 0.0), 0.4, 0.6, 10, color="#795548"), sph((34.0, 9.0, 1.1), 0.55, 4)],
          ["potted plant", "green plant"])
    # the crowd: two two-way lanes between the street doors and the platform gates; three
    # passengers per lane, spread evenly over the loop (start_s < 0: already walking at t = 0)
    shirts = ["#D32F2F", "#1976D2", "#388E3C", "#FBC02D", "#7B1FA2", "#F57C00"]
    names = ["passenger in red", "passenger in blue", "passenger in green", "passenger in yellow", "passenger in purple", "passenger in orange"]
    k = 0
    for lane_x, speed in ((12.0, WALK_MPS), (22.5, 1.2)):
        loop = [(lane_x, 2.0), (lane_x, 26.0), (lane_x + 1.2, 26.0), (lane_x + 1.2, 2.0)]
        cycle = (2 * 24.0 + 2 * 1.2) / speed
        for j in range(3):
            person(b, names[k], shirts[k], 0.0, 0.0, aliases=[names[k].replace("passenger", "person")],
                   motion=path(loop, speed, start_s=round(-(j + 0.5 * (lane_x > 20)) * cycle / 3, 2)))
            k += 1
    person(b, "man with a luggage cart", "#455A64", 0.0, 0.0, aliases=["man with the luggage cart", "man pushing a trolley"], extra=cart(color="#B0BEC5"),
           motion=path([(4.0, 4.5), (15.0, 4.5), (15.5, 11.0), (18.0, 11.5)], CART_MPS, loop=False, pauses={1: 4.0}))
    person(b, "traveller pacing by the clock", "#C2185B", 0.0, 0.0, aliases=["person by the clock column", "woman in pink"], height=1.65,
           motion=circle((17.5, 21.0), 2.0, STROLL_MPS, phase_deg=-90.0))
    return b


SCENES = {
    "urban_block": urban_block,
    "factory_hall": factory_hall,
    "villa": villa,
    "duplex": duplex,
    "corridor": corridor,
    "park": park,
    "parking_lot": parking_lot,
    "warehouse": warehouse,
    "plaza": plaza,
    "terrace": terrace,
    # the harder scenes of issue 16 (their tasks: onfly/data/tasks/hard/)
    "apartment": apartment,
    "office_floor": office_floor,
    "parking_garage": parking_garage,
    # issue 19: a scene whose crowd crosses the routes (its tasks: onfly/data/tasks/crowds/)
    "station_concourse": station_concourse,
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "onfly" / "data" / "scenes")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--only", nargs="*", default=None, help="scene names to write (default: all)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for i, (name, fn) in enumerate(SCENES.items()):
        if args.only and name not in args.only:
            continue
        b = fn(np.random.default_rng([args.seed, i]))
        path = args.out / f"{name}.toml"
        path.write_text(b.to_toml())
        print(f"{path}: {len(b.objects)} objects")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
