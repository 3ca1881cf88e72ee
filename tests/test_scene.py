"""Scene format: a valid file loads to the right values; every malformed file names its fault."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from onfly.world.scene import (
    Box,
    MeshFile,
    SceneFormatError,
    Stairs,
    load_scene,
    resolve_scene,
)

VALID = """
format = "onfly-scene/1"
name = "tiny"
description = "two objects"

[bounds]
min_m = [-10, -10, 0]
max_m = [10, 10, 5]

[start]
position_m = [0, 0, 1.5]
yaw_deg = 90

[[objects]]
name = "red van"
label = "van"
instance_id = 3
color = "#C0282D"
aliases = ["red vehicle"]
texture = { pattern = "stripes", period_m = 0.4, contrast = 0.5, axis = "x", seed = 2 }
parts = [
  { type = "box", center_m = [5, 0, 1], size_m = [4, 2, 2], yaw_deg = 90 },
  { type = "cylinder", base_m = [5, 2, 0], radius_m = 0.3, height_m = 0.6, color = [10, 20, 30] },
]

[[objects]]
name = "ground"
label = "ground"
instance_id = 1
color = [90, 90, 90]
target = false
parts = [ { type = "plane", center_m = [0, 0, 0], size_m = [20, 20] } ]
"""


def write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_valid_scene_loads_with_units_converted(tmp_path):
    s = load_scene(write(tmp_path, VALID))
    assert s.name == "tiny"
    assert s.start.yaw_rad == pytest.approx(math.pi / 2)
    np.testing.assert_array_equal(s.start.position_m, [0, 0, 1.5])
    van = s.object_by_name("red van")
    assert van.instance_id == 3 and van.label == "van" and van.aliases == ("red vehicle",)
    np.testing.assert_array_equal(van.color, [0xC0, 0x28, 0x2D])
    assert isinstance(van.parts[0].shape, Box)
    assert van.parts[0].shape.yaw_rad == pytest.approx(math.pi / 2)
    np.testing.assert_array_equal(van.parts[1].color, [10, 20, 30])
    assert van.texture.pattern == "stripes" and van.texture.seed == 2
    np.testing.assert_array_equal(van.texture.axis, [1, 0, 0])
    assert s.object_by_id(1).name == "ground" and not s.object_by_id(1).target
    assert [o.name for o in s.targets] == ["red van"]
    assert s.label_ids == {"ground": 1, "van": 2}
    assert s.bounds.contains([[0, 0, 1], [0, 0, 6]]).tolist() == [True, False]


@pytest.mark.parametrize(
    "old, new, pattern",
    [
        ('label = "van"\n', "", r"scene\.toml: object 'red van': field 'label': missing required field"),
        ("instance_id = 3", 'instance_id = "3"', r"object 'red van': field 'instance_id': expected an integer, got str"),
        ('type = "box"', 'type = "cube"', r"object 'red van': field 'parts\[0\]\.type': unknown primitive 'cube'"),
        ('color = "#C0282D"', 'color = "#C0282Z"', r"object 'red van': field 'color': bad colour '#C0282Z'"),
        ("color = [10, 20, 30]", "color = [10, 20, 300]", r"object 'red van': field 'parts\[1\]\.color': bad colour"),
        ("size_m = [4, 2, 2]", "size_m = [4, -2, 2]", r"field 'parts\[0\]\.size_m': all entries must be positive"),
        ("size_m = [4, 2, 2]", "size_m = [4, 2]", r"field 'parts\[0\]\.size_m': expected a list of 3 numbers"),
        ("radius_m = 0.3", "radius_m = true", r"field 'parts\[1\]\.radius_m': expected a number, got bool"),
        ('pattern = "stripes"', 'pattern = "zigzag"', r"field 'texture\.pattern': unknown texture pattern 'zigzag'"),
        ("instance_id = 1", "instance_id = 3", r"object 'ground': field 'instance_id': duplicate instance id 3"),
        ('name = "ground"', 'name = "red van"', r"object 'red van': field 'name': duplicate name"),
        ("aliases = [", "colour = 1\naliases = [", r"object 'red van': field 'colour': unknown field"),
        ("position_m = [0, 0, 1.5]", "position_m = [0, 0, 9]", r"field 'start\.position_m': .* outside the bounds"),
        ("max_m = [10, 10, 5]", "max_m = [10, -10, 5]", r"field 'bounds\.max_m': must exceed min_m"),
        ('format = "onfly-scene/1"', 'format = "onfly-scene/9"', r"field 'format': unsupported format"),
        ("instance_id = 1", "instance_id = 0", r"object 'ground': field 'instance_id': must be >= 1"),
    ],
)
def test_malformed_scene_names_file_object_and_field(tmp_path, old, new, pattern):
    assert old in VALID
    path = write(tmp_path, VALID.replace(old, new, 1))
    with pytest.raises(SceneFormatError, match=pattern) as info:
        load_scene(path)
    assert info.value.path == str(path)


def test_object_without_name_is_named_by_index(tmp_path):
    text = VALID.replace('name = "ground"\n', "", 1)
    with pytest.raises(SceneFormatError, match=r"object 'objects\[1\]': field 'name': missing required field"):
        load_scene(write(tmp_path, text))


def test_bad_toml_and_missing_file(tmp_path):
    with pytest.raises(SceneFormatError, match=r"bad\.toml: not valid TOML"):
        load_scene(write(tmp_path, VALID + "\n[[objects]\n", "bad.toml"))
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")


def test_self_intersecting_polygon_is_rejected_with_its_field(tmp_path):
    bowtie = '{ type = "extruded_polygon", points_m = [[0, 0], [4, 2], [4, 0], [0, 3]], z_min_m = 0, height_m = 1 }'
    text = VALID.replace('{ type = "plane", center_m = [0, 0, 0], size_m = [20, 20] }', bowtie)
    with pytest.raises(SceneFormatError, match=r"object 'ground': field 'parts\[0\]\.points_m': polygon edges 0 and 2 intersect"):
        load_scene(write(tmp_path, text))


def test_stairs_and_mesh_file_parts(tmp_path):
    obj = tmp_path / "tri.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    parts = (
        '{ type = "stairs", start_m = [0, 0, 0], yaw_deg = 180, width_m = 1, step_count = 5, rise_m = 0.2, run_m = 0.3 },'
        ' { type = "mesh", path = "tri.obj", position_m = [1, 2, 3], scale = 2.0 }'
    )
    text = VALID.replace('{ type = "plane", center_m = [0, 0, 0], size_m = [20, 20] }', parts)
    s = load_scene(write(tmp_path, text))
    st, mesh = (p.shape for p in s.object_by_name("ground").parts)
    assert isinstance(st, Stairs) and st.step_count == 5 and st.yaw_rad == pytest.approx(math.pi)
    assert isinstance(mesh, MeshFile) and mesh.path == obj.resolve() and mesh.scale == 2.0
    missing = VALID.replace('{ type = "plane", center_m = [0, 0, 0], size_m = [20, 20] }', '{ type = "mesh", path = "gone.ply", position_m = [0, 0, 0] }')
    with pytest.raises(SceneFormatError, match=r"field 'parts\[0\]\.path': mesh file not found"):
        load_scene(write(tmp_path, missing, "m.toml"))


def test_resolve_scene_by_name_and_unknown_name_lists_choices():
    assert resolve_scene("villa").name == "villa.toml"
    with pytest.raises(FileNotFoundError, match=r"no scene named 'atlantis'; committed scenes: .*villa"):
        resolve_scene("atlantis")


def test_the_documented_example_loads(tmp_path):
    doc = (Path(__file__).resolve().parent.parent / "docs" / "scene_format.md").read_text()
    example = doc.split("```toml\n", 1)[1].split("```", 1)[0]
    s = load_scene(write(tmp_path, example, "driveway.toml"))
    assert s.name == "driveway" and [o.name for o in s.targets] == ["red van", "blue van", "garage"]
    assert s.label_ids["van"] == 3


def test_materials_on_objects_and_parts_and_the_indoor_flag(tmp_path):
    text = VALID.replace('aliases = ["red vehicle"]', 'aliases = ["red vehicle"]\nmaterial = "dark"').replace(
        "color = [10, 20, 30] }", 'color = [10, 20, 30], material = "glass" }').replace('description = "two objects"', 'description = "two objects"\nindoor = true')
    scene = load_scene(write(tmp_path, text))
    van, ground = scene.object_by_name("red van"), scene.object_by_name("ground")
    assert scene.indoor and load_scene(write(tmp_path, VALID, "plain.toml")).indoor is False
    assert van.material == "dark" and ground.material == "opaque"
    assert [van.part_material(p) for p in van.parts] == ["dark", "glass"]


@pytest.mark.parametrize(
    "old, new, pattern",
    [
        ('aliases = ["red vehicle"]', 'aliases = ["red vehicle"]\nmaterial = "velvet"', r"object 'red van': field 'material': unknown material 'velvet' \(known: opaque, glass, mirror, dark\)"),
        ("color = [10, 20, 30] }", "color = [10, 20, 30], material = 3 }", r"object 'red van': field 'parts\[1\]\.material': unknown material 3"),
        ('description = "two objects"', 'description = "two objects"\nindoor = "yes"', r"field 'indoor': expected true or false"),
    ],
)
def test_bad_materials_name_the_field(tmp_path, old, new, pattern):
    assert old in VALID
    with pytest.raises(SceneFormatError, match=pattern):
        load_scene(write(tmp_path, VALID.replace(old, new, 1)))
