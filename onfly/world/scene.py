"""The scene format: frozen dataclasses and a TOML loader that names every fault.

A scene is one TOML file (``docs/scene_format.md`` documents it field by field): bounds, a
start pose, lighting, and a list of *objects*. An object is one semantic instance (a van, a
staircase, the walls of a hall) with a name tasks can refer to, a label, an instance id, a
colour, aliases, an optional texture pattern, and one or more *parts*, each a primitive shape
(box, cylinder, sphere, plane, extruded polygon, stairs, ramp) or a mesh file (OBJ / PLY).

World frame ENU, metres. Angles are written in degrees in the file (``yaw_deg``) and held in
radians here (``yaw_rad``). Colours are ``"#RRGGBB"`` strings or ``[r, g, b]`` in 0..255.

Every error is a :class:`SceneFormatError` naming the file, the object and the field.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Union

import numpy as np

from onfly.world.actors import Motion, MotionFormatError, parse_motion

__all__ = [
    "SceneFormatError",
    "Bounds",
    "StartPose",
    "Light",
    "Texture",
    "Box",
    "Cylinder",
    "Sphere",
    "Plane",
    "ExtrudedPolygon",
    "Stairs",
    "Ramp",
    "MeshFile",
    "Shape",
    "Part",
    "SceneObject",
    "Scene",
    "load_scene",
    "parse_scene",
    "scenes_dir",
    "list_scenes",
    "resolve_scene",
    "FORMAT_VERSION",
    "TEXTURE_PATTERNS",
    "SHAPE_TYPES",
    "MATERIALS",
    "DEFAULT_MATERIAL",
]

#: Version written as ``format = "onfly-scene/1"`` at the top of each file.
FORMAT_VERSION = "onfly-scene/1"
TEXTURE_PATTERNS = ("stripes", "checker", "noise")
#: Surface materials a depth sensor cares about (effects per realism profile in docs/realism.md):
#: ``opaque`` (the default: a normal matte surface), ``glass`` (transparent: doors, windows),
#: ``mirror`` (specular: mirror-like facades, polished metal), ``dark`` (low infrared albedo:
#: black machines, tyres, rubber). Geometry and collisions never depend on the material.
MATERIALS = ("opaque", "glass", "mirror", "dark")
DEFAULT_MATERIAL = "opaque"
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
#: Largest instance id (ids are written to 16-bit images).
MAX_INSTANCE_ID = 65535


class SceneFormatError(ValueError):
    """A scene file that does not follow the format.

    Attributes
    ----------
    path : str, the file at fault
    obj : str or None, the object (its name, or ``objects[i]`` when it has none)
    field : str or None, the field at fault (dotted, e.g. ``parts[1].size_m``)
    """

    def __init__(self, path, obj: str | None, field: str | None, message: str) -> None:
        self.path = str(path)
        self.obj = obj
        self.field = field
        where = [self.path]
        if obj is not None:
            where.append(f"object {obj!r}")
        if field is not None:
            where.append(f"field {field!r}")
        super().__init__(": ".join(where) + f": {message}")


# -- value types ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Bounds:
    """Axis-aligned flight volume, world ENU, metres: ``min_m`` (3,), ``max_m`` (3,)."""

    min_m: np.ndarray
    max_m: np.ndarray

    def contains(self, points) -> np.ndarray:
        """True where points (n, 3) lie inside (inclusive); returns bool (n,)."""
        P = np.atleast_2d(np.asarray(points, dtype=float))
        return np.all((P >= self.min_m) & (P <= self.max_m), axis=1)

    @property
    def size_m(self) -> np.ndarray:
        return self.max_m - self.min_m


@dataclass(frozen=True, eq=False)
class StartPose:
    """Where an episode begins: body position (3,) metres ENU and yaw in radians."""

    position_m: np.ndarray
    yaw_rad: float


@dataclass(frozen=True, eq=False)
class Light:
    """Directional light for Lambert shading.

    direction : array (3,), unit vector *towards* the light, world ENU
    ambient : float in [0, 1], the share of brightness a face gets with no direct light
    """

    direction: np.ndarray
    ambient: float = 0.35


@dataclass(frozen=True, eq=False)
class Texture:
    """A procedural pattern modulating an object's colour, fixed to world coordinates.

    pattern : "stripes" (bands across ``axis``), "checker" (3D checkerboard) or "noise"
        (random brightness per cubic cell, seeded)
    period_m : float > 0, stripe / checker / noise cell size in metres
    contrast : float in [0, 1], darkest factor is ``1 - contrast``
    axis : array (3,), unit stripe normal (stripes only)
    seed : int, noise seed
    """

    pattern: str
    period_m: float = 0.5
    contrast: float = 0.3
    axis: np.ndarray = None  # type: ignore[assignment]
    seed: int = 0


@dataclass(frozen=True, eq=False)
class Box:
    """Cuboid: centre (3,) m, full size (3,) m along its own axes, yaw about z in radians."""

    center_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: float = 0.0


@dataclass(frozen=True, eq=False)
class Cylinder:
    """Upright cylinder: ``base_m`` (3,) is the centre of its bottom disc."""

    base_m: np.ndarray
    radius_m: float
    height_m: float
    segments: int = 12


@dataclass(frozen=True, eq=False)
class Sphere:
    """UV sphere: centre (3,) m, radius m, ``rings`` latitude bands (longitudes = 2 * rings)."""

    center_m: np.ndarray
    radius_m: float
    rings: int = 6


@dataclass(frozen=True, eq=False)
class Plane:
    """Horizontal rectangle facing up (ground, floors, water): centre (3,), size (2,), yaw."""

    center_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: float = 0.0


@dataclass(frozen=True, eq=False)
class ExtrudedPolygon:
    """Simple polygon ``points_m`` (n, 2) in the xy-plane extruded from ``z_min_m`` up by
    ``height_m``. Either winding; must not self-intersect."""

    points_m: np.ndarray
    z_min_m: float
    height_m: float


@dataclass(frozen=True, eq=False)
class Stairs:
    """Solid straight staircase.

    ``start_m`` (3,) is the middle of the first step's front edge on the floor; the stairs
    climb along ``yaw_rad``; ``step_count`` steps of ``rise_m`` up and ``run_m`` deep, each
    ``width_m`` wide. Top surface at ``start_m[2] + step_count * rise_m``.
    """

    start_m: np.ndarray
    yaw_rad: float
    width_m: float
    step_count: int
    rise_m: float
    run_m: float


@dataclass(frozen=True, eq=False)
class Ramp:
    """Solid wedge: from ``start_m`` (3,) (middle of the low edge, on the floor) it climbs
    along ``yaw_rad`` by ``rise_m`` over ``length_m`` horizontally, ``width_m`` wide."""

    start_m: np.ndarray
    yaw_rad: float
    length_m: float
    width_m: float
    rise_m: float


@dataclass(frozen=True, eq=False)
class MeshFile:
    """A triangle mesh file (OBJ / PLY, read with Open3D), scaled, rotated by yaw, then moved
    to ``position_m`` (3,). ``path`` is absolute (resolved against the scene file)."""

    path: Path
    position_m: np.ndarray
    yaw_rad: float = 0.0
    scale: float = 1.0


Shape = Union[Box, Cylinder, Sphere, Plane, ExtrudedPolygon, Stairs, Ramp, MeshFile]


@dataclass(frozen=True, eq=False)
class Part:
    """One shape of an object; ``color`` (3,) uint8 overrides the object's colour if set, and
    ``material`` (one of :data:`MATERIALS`) the object's material."""

    shape: Shape
    color: np.ndarray | None = None
    material: str | None = None


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One semantic instance.

    name : unique in the scene, what tasks call it ("red van")
    label : semantic class ("van"); several objects share a label
    instance_id : int in 1..65535, unique in the scene (0 is background)
    color : uint8 array (3,), RGB
    aliases : other names a person might use
    target : True if tasks may name it as a goal (ground, walls, roofs are not targets)
    texture : optional Texture
    parts : one or more Part
    material : one of :data:`MATERIALS` (default ``"opaque"``); a part may override it
    motion : a :class:`onfly.world.actors.PathMotion` or ``CircleMotion``, or None. An object
        with a motion is an *actor*: its parts are written in its own frame (origin on the
        ground between the feet, x forward, z up) and placed at the motion's pose at each
        instant (``onfly.world.actors``); without one, parts are in the world frame.
    """

    name: str
    label: str
    instance_id: int
    color: np.ndarray
    parts: tuple[Part, ...]
    aliases: tuple[str, ...] = ()
    target: bool = True
    texture: Texture | None = None
    material: str = DEFAULT_MATERIAL
    motion: Motion | None = None

    @property
    def is_actor(self) -> bool:
        """True for an object that moves (it has a motion)."""
        return self.motion is not None

    def part_material(self, part: Part) -> str:
        """The material of one of this object's parts (its own, else the object's)."""
        return self.material if part.material is None else part.material


@dataclass(frozen=True, eq=False)
class Scene:
    """A loaded scene. ``path`` is the file it came from (None if built in code); ``indoor``
    is True for scenes under a roof (no wind gusts in the realistic profile)."""

    name: str
    description: str
    bounds: Bounds
    start: StartPose
    objects: tuple[SceneObject, ...]
    light: Light
    sky_color: np.ndarray
    path: Path | None = None
    indoor: bool = False

    @property
    def label_ids(self) -> dict[str, int]:
        """Semantic label -> id (1..K, labels sorted alphabetically; 0 is background)."""
        return {lab: i + 1 for i, lab in enumerate(sorted({o.label for o in self.objects}))}

    @property
    def actors(self) -> tuple[SceneObject, ...]:
        """Objects that move (with a motion), in file order."""
        return tuple(o for o in self.objects if o.motion is not None)

    @property
    def static_objects(self) -> tuple[SceneObject, ...]:
        """Objects that never move, in file order."""
        return tuple(o for o in self.objects if o.motion is None)

    @property
    def targets(self) -> tuple[SceneObject, ...]:
        """Objects tasks may name as goals."""
        return tuple(o for o in self.objects if o.target)

    def object_by_name(self, name: str) -> SceneObject:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(f"scene {self.name!r} has no object named {name!r}")

    def object_by_id(self, instance_id: int) -> SceneObject:
        for o in self.objects:
            if o.instance_id == instance_id:
                return o
        raise KeyError(f"scene {self.name!r} has no object with instance id {instance_id}")


# -- parsing -------------------------------------------------------------------------------

SHAPE_TYPES = ("box", "cylinder", "sphere", "plane", "extruded_polygon", "stairs", "ramp", "mesh")


class _Ctx:
    """Where we are in the file, so every error names file, object and field."""

    def __init__(self, path, obj: str | None = None, prefix: str = "") -> None:
        self.path = path
        self.obj = obj
        self.prefix = prefix

    def sub(self, prefix: str) -> "_Ctx":
        return _Ctx(self.path, self.obj, f"{self.prefix}{prefix}.")

    def err(self, field: str | None, message: str) -> SceneFormatError:
        f = None if field is None else f"{self.prefix}{field}"
        return SceneFormatError(self.path, self.obj, f, message)


def _type_name(v: Any) -> str:
    return type(v).__name__


def _get(ctx: _Ctx, table: dict, key: str, default: Any = ...) -> Any:
    if key not in table:
        if default is ...:
            raise ctx.err(key, "missing required field")
        return default
    return table[key]


def _float(ctx: _Ctx, table: dict, key: str, default: Any = ..., *, positive: bool = False, lo=None, hi=None) -> float:
    v = _get(ctx, table, key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ctx.err(key, f"expected a number, got {_type_name(v)} {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ctx.err(key, f"must be finite, got {v}")
    if positive and v <= 0:
        raise ctx.err(key, f"must be positive, got {v}")
    if lo is not None and v < lo:
        raise ctx.err(key, f"must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        raise ctx.err(key, f"must be <= {hi}, got {v}")
    return v


def _int(ctx: _Ctx, table: dict, key: str, default: Any = ..., *, lo=None, hi=None) -> int:
    v = _get(ctx, table, key, default)
    if isinstance(v, bool) or not isinstance(v, int):
        raise ctx.err(key, f"expected an integer, got {_type_name(v)} {v!r}")
    if lo is not None and v < lo:
        raise ctx.err(key, f"must be >= {lo}, got {v}")
    if hi is not None and v > hi:
        raise ctx.err(key, f"must be <= {hi}, got {v}")
    return int(v)


def _str(ctx: _Ctx, table: dict, key: str, default: Any = ...) -> str:
    v = _get(ctx, table, key, default)
    if not isinstance(v, str):
        raise ctx.err(key, f"expected a string, got {_type_name(v)} {v!r}")
    return v


def _bool(ctx: _Ctx, table: dict, key: str, default: Any = ...) -> bool:
    v = _get(ctx, table, key, default)
    if not isinstance(v, bool):
        raise ctx.err(key, f"expected true or false, got {_type_name(v)} {v!r}")
    return v


def _vector(ctx: _Ctx, table: dict, key: str, n: int, default: Any = ..., *, positive: bool = False) -> np.ndarray:
    v = _get(ctx, table, key, default)
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise ctx.err(key, f"expected a list of {n} numbers, got {v!r}")
    for x in v:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise ctx.err(key, f"expected a list of {n} finite numbers, got {v!r}")
    a = np.asarray(v, dtype=float)
    if positive and np.any(a <= 0):
        raise ctx.err(key, f"all entries must be positive, got {v!r}")
    return a


def _table(ctx: _Ctx, table: dict, key: str, default: Any = ...) -> dict:
    v = _get(ctx, table, key, default)
    if not isinstance(v, dict):
        raise ctx.err(key, f"expected a table, got {_type_name(v)} {v!r}")
    return v


def _check_keys(ctx: _Ctx, table: dict, allowed: tuple[str, ...], where: str | None = None) -> None:
    for k in table:
        if k not in allowed:
            field = k if where is None else f"{where}.{k}"
            raise ctx.err(field, f"unknown field (allowed: {', '.join(allowed)})")


def _color(ctx: _Ctx, table: dict, key: str, default: Any = ...) -> np.ndarray | None:
    v = _get(ctx, table, key, default)
    if v is None:
        return None
    if isinstance(v, str):
        s = v.strip()
        if len(s) == 7 and s[0] == "#":
            try:
                return np.array([int(s[i : i + 2], 16) for i in (1, 3, 5)], dtype=np.uint8)
            except ValueError:
                pass
        raise ctx.err(key, f'bad colour {v!r}: expected "#RRGGBB" or [r, g, b] in 0..255')
    if isinstance(v, (list, tuple)) and len(v) == 3:
        if all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255 for c in v):
            return np.array(v, dtype=np.uint8)
    raise ctx.err(key, f'bad colour {v!r}: expected "#RRGGBB" or [r, g, b] in 0..255')


def _yaw(ctx: _Ctx, table: dict) -> float:
    return math.radians(_float(ctx, table, "yaw_deg", 0.0))


_SHAPE_KEYS = {
    "box": ("type", "color", "material", "center_m", "size_m", "yaw_deg"),
    "cylinder": ("type", "color", "material", "base_m", "radius_m", "height_m", "segments"),
    "sphere": ("type", "color", "material", "center_m", "radius_m", "rings"),
    "plane": ("type", "color", "material", "center_m", "size_m", "yaw_deg"),
    "extruded_polygon": ("type", "color", "material", "points_m", "z_min_m", "height_m"),
    "stairs": ("type", "color", "material", "start_m", "yaw_deg", "width_m", "step_count", "rise_m", "run_m"),
    "ramp": ("type", "color", "material", "start_m", "yaw_deg", "length_m", "width_m", "rise_m"),
    "mesh": ("type", "color", "material", "path", "position_m", "yaw_deg", "scale"),
}


def _parse_shape(ctx: _Ctx, t: dict, base_dir: Path) -> Shape:
    kind = _str(ctx, t, "type")
    if kind not in _SHAPE_TYPES_SET:
        raise ctx.err("type", f"unknown primitive {kind!r} (known: {', '.join(SHAPE_TYPES)})")
    _check_keys(ctx, t, _SHAPE_KEYS[kind])
    if kind == "box":
        return Box(_vector(ctx, t, "center_m", 3), _vector(ctx, t, "size_m", 3, positive=True), _yaw(ctx, t))
    if kind == "cylinder":
        return Cylinder(
            _vector(ctx, t, "base_m", 3),
            _float(ctx, t, "radius_m", positive=True),
            _float(ctx, t, "height_m", positive=True),
            _int(ctx, t, "segments", 12, lo=3, hi=128),
        )
    if kind == "sphere":
        return Sphere(_vector(ctx, t, "center_m", 3), _float(ctx, t, "radius_m", positive=True), _int(ctx, t, "rings", 6, lo=2, hi=64))
    if kind == "plane":
        return Plane(_vector(ctx, t, "center_m", 3), _vector(ctx, t, "size_m", 2, positive=True), _yaw(ctx, t))
    if kind == "extruded_polygon":
        raw = _get(ctx, t, "points_m")
        if not isinstance(raw, list) or len(raw) < 3:
            raise ctx.err("points_m", f"expected a list of at least 3 [x, y] points, got {raw!r}")
        pts = []
        for i, p in enumerate(raw):
            pts.append(_vector(ctx, {f"points_m[{i}]": p}, f"points_m[{i}]", 2))
        pts = np.array(pts)
        # Local import: primitives depends on this module's dataclasses.
        from onfly.world.primitives import PrimitiveError, check_polygon

        try:
            check_polygon(pts)
        except PrimitiveError as exc:
            raise ctx.err("points_m", str(exc)) from None
        return ExtrudedPolygon(pts, _float(ctx, t, "z_min_m"), _float(ctx, t, "height_m", positive=True))
    if kind == "stairs":
        return Stairs(
            _vector(ctx, t, "start_m", 3),
            _yaw(ctx, t),
            _float(ctx, t, "width_m", positive=True),
            _int(ctx, t, "step_count", lo=1, hi=200),
            _float(ctx, t, "rise_m", positive=True),
            _float(ctx, t, "run_m", positive=True),
        )
    if kind == "ramp":
        return Ramp(
            _vector(ctx, t, "start_m", 3),
            _yaw(ctx, t),
            _float(ctx, t, "length_m", positive=True),
            _float(ctx, t, "width_m", positive=True),
            _float(ctx, t, "rise_m", positive=True),
        )
    # mesh
    rel = _str(ctx, t, "path")
    path = (base_dir / rel).resolve()
    if path.suffix.lower() not in (".obj", ".ply"):
        raise ctx.err("path", f"mesh files must be .obj or .ply, got {rel!r}")
    if not path.is_file():
        raise ctx.err("path", f"mesh file not found: {path}")
    return MeshFile(path, _vector(ctx, t, "position_m", 3), _yaw(ctx, t), _float(ctx, t, "scale", 1.0, positive=True))


_SHAPE_TYPES_SET = frozenset(SHAPE_TYPES)
_OBJECT_KEYS = ("name", "label", "instance_id", "color", "aliases", "target", "texture", "material", "motion", "parts")
_TEXTURE_KEYS = ("pattern", "period_m", "contrast", "axis", "seed")


def _parse_texture(ctx: _Ctx, t: dict) -> Texture:
    _check_keys(ctx, t, _TEXTURE_KEYS)
    pattern = _str(ctx, t, "pattern")
    if pattern not in TEXTURE_PATTERNS:
        raise ctx.err("pattern", f"unknown texture pattern {pattern!r} (known: {', '.join(TEXTURE_PATTERNS)})")
    axis_name = _str(ctx, t, "axis", "z")
    if axis_name not in _AXES:
        raise ctx.err("axis", f"axis must be one of x, y, z, got {axis_name!r}")
    return Texture(
        pattern,
        _float(ctx, t, "period_m", 0.5, positive=True),
        _float(ctx, t, "contrast", 0.3, lo=0.0, hi=1.0),
        np.array(_AXES[axis_name]),
        _int(ctx, t, "seed", 0, lo=0, hi=2**31 - 1),
    )


def _material(ctx: _Ctx, table: dict, default: Any) -> str | None:
    v = _get(ctx, table, "material", default)
    if v is None:
        return None
    if not isinstance(v, str) or v not in MATERIALS:
        raise ctx.err("material", f"unknown material {v!r} (known: {', '.join(MATERIALS)})")
    return v


def _parse_object(ctx: _Ctx, t: dict, base_dir: Path) -> SceneObject:
    _check_keys(ctx, t, _OBJECT_KEYS)
    name = _str(ctx, t, "name")
    if not name.strip():
        raise ctx.err("name", "must not be empty")
    ctx = _Ctx(ctx.path, name)
    label = _str(ctx, t, "label")
    if not label.strip():
        raise ctx.err("label", "must not be empty")
    iid = _int(ctx, t, "instance_id", lo=1, hi=MAX_INSTANCE_ID)
    color = _color(ctx, t, "color")
    aliases = _get(ctx, t, "aliases", [])
    if not isinstance(aliases, list) or not all(isinstance(a, str) for a in aliases):
        raise ctx.err("aliases", f"expected a list of strings, got {aliases!r}")
    target = _bool(ctx, t, "target", True)
    material = _material(ctx, t, DEFAULT_MATERIAL)
    texture = None
    if "texture" in t:
        texture = _parse_texture(ctx.sub("texture"), _table(ctx, t, "texture"))
    raw_parts = _get(ctx, t, "parts")
    if not isinstance(raw_parts, list) or not raw_parts:
        raise ctx.err("parts", "expected a non-empty list of part tables ([[objects.parts]])")
    parts = []
    for i, p in enumerate(raw_parts):
        pctx = ctx.sub(f"parts[{i}]")
        if not isinstance(p, dict):
            raise ctx.err(f"parts[{i}]", f"expected a table, got {_type_name(p)}")
        shape = _parse_shape(pctx, p, base_dir)
        parts.append(Part(shape, _color(pctx, p, "color", None), _material(pctx, p, None)))
    motion = None
    if "motion" in t:
        try:
            motion = parse_motion(t["motion"])
        except MotionFormatError as exc:
            raise ctx.err("motion" if exc.field is None else f"motion.{exc.field}", exc.detail) from None
        if texture is not None:
            raise ctx.err("texture", "an actor (an object with a motion) cannot have a texture: patterns are fixed to world coordinates")
    return SceneObject(name, label, iid, color, tuple(parts), tuple(aliases), target, texture, material, motion)


_TOP_KEYS = ("format", "name", "description", "indoor", "bounds", "start", "light", "sky_color", "objects")


def parse_scene(data: dict, path: str | Path = "<memory>", base_dir: Path | None = None) -> Scene:
    """Build a :class:`Scene` from a parsed TOML table.

    Parameters
    ----------
    data : dict, the TOML document
    path : used in error messages and stored on the scene
    base_dir : folder that relative mesh paths resolve against (default: the file's folder)

    Raises
    ------
    SceneFormatError naming the file, object and field at fault.
    """
    path = Path(path) if not isinstance(path, Path) else path
    base_dir = base_dir if base_dir is not None else path.parent
    ctx = _Ctx(path)
    _check_keys(ctx, data, _TOP_KEYS)
    fmt = _str(ctx, data, "format")
    if fmt != FORMAT_VERSION:
        raise ctx.err("format", f"unsupported format {fmt!r} (this reader knows {FORMAT_VERSION!r})")
    name = _str(ctx, data, "name")
    description = _str(ctx, data, "description", "")
    indoor = _bool(ctx, data, "indoor", False)

    bt = _table(ctx, data, "bounds")
    _check_keys(ctx, bt, ("min_m", "max_m"), "bounds")
    bctx = ctx.sub("bounds")
    bmin, bmax = _vector(bctx, bt, "min_m", 3), _vector(bctx, bt, "max_m", 3)
    if np.any(bmax <= bmin):
        raise bctx.err("max_m", f"must exceed min_m on every axis, got min {bmin.tolist()} max {bmax.tolist()}")
    bounds = Bounds(bmin, bmax)

    st = _table(ctx, data, "start")
    _check_keys(ctx, st, ("position_m", "yaw_deg"), "start")
    sctx = ctx.sub("start")
    start = StartPose(_vector(sctx, st, "position_m", 3), math.radians(_float(sctx, st, "yaw_deg", 0.0)))
    if not bounds.contains(start.position_m)[0]:
        raise sctx.err("position_m", f"start {start.position_m.tolist()} lies outside the bounds")

    lt = _table(ctx, data, "light", {})
    _check_keys(ctx, lt, ("direction", "ambient"), "light")
    lctx = ctx.sub("light")
    ld = _vector(lctx, lt, "direction", 3, [0.35, 0.25, 0.9])
    if np.linalg.norm(ld) < 1e-9:
        raise lctx.err("direction", "must not be the zero vector")
    light = Light(ld / np.linalg.norm(ld), _float(lctx, lt, "ambient", 0.35, lo=0.0, hi=1.0))
    sky = _color(ctx, data, "sky_color", "#B4CDE6")

    raw_objects = _get(ctx, data, "objects")
    if not isinstance(raw_objects, list) or not raw_objects:
        raise ctx.err("objects", "expected a non-empty list of object tables ([[objects]])")
    objects: list[SceneObject] = []
    names: dict[str, int] = {}
    ids: dict[int, str] = {}
    for i, t in enumerate(raw_objects):
        octx = _Ctx(path, f"objects[{i}]")
        if not isinstance(t, dict):
            raise octx.err(None, f"expected a table, got {_type_name(t)}")
        if isinstance(t.get("name"), str) and t["name"].strip():
            octx = _Ctx(path, t["name"])
        obj = _parse_object(octx, t, base_dir)
        if obj.name in names:
            raise SceneFormatError(path, obj.name, "name", f"duplicate name (also objects[{names[obj.name]}])")
        if obj.instance_id in ids:
            raise SceneFormatError(path, obj.name, "instance_id", f"duplicate instance id {obj.instance_id} (also {ids[obj.instance_id]!r})")
        names[obj.name] = i
        ids[obj.instance_id] = obj.name
        objects.append(obj)
    return Scene(name, description, bounds, start, tuple(objects), light, sky, path, indoor)


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene file (TOML).

    Raises
    ------
    FileNotFoundError if the file does not exist; SceneFormatError for bad TOML or content.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise SceneFormatError(path, None, None, f"not valid TOML: {exc}") from None
    return parse_scene(data, path)


def scenes_dir() -> Path:
    """Folder of the committed scenes (``onfly/data/scenes``)."""
    return Path(__file__).resolve().parent.parent / "data" / "scenes"


def list_scenes() -> list[str]:
    """Names of the committed scenes (file stems), sorted."""
    return sorted(p.stem for p in scenes_dir().glob("*.toml"))


def resolve_scene(name_or_path: str | Path) -> Path:
    """A committed scene's name (``"villa"``) or a path to a scene file -> the file's path.

    Raises FileNotFoundError listing the committed scenes when neither exists.
    """
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.is_file():
        if not p.is_file():
            raise FileNotFoundError(f"scene file not found: {p}")
        return p
    cand = scenes_dir() / f"{name_or_path}.toml"
    if cand.is_file():
        return cand
    raise FileNotFoundError(f"no scene named {str(name_or_path)!r}; committed scenes: {', '.join(list_scenes()) or '(none)'}")
