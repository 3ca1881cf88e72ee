"""Renderer: depth equals analytic depth of known primitives, ids match, shading and noise."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.world.geometry import SceneGeometry
from onfly.world.render import DepthNoise, RenderConfig, Renderer, default_camera
from onfly.world.scene import parse_scene
from planning.camera import PinholeCamera
from planning.frames import FrameError, body_transform, cam_transform_from_body, make_transform

CAM = PinholeCamera.from_fov(160, 107, 90.0, 60.0)


def scene_of(objects, light=None):
    d = {
        "format": "onfly-scene/1",
        "name": "test",
        "bounds": {"min_m": [-50, -50, -5], "max_m": [50, 50, 20]},
        "start": {"position_m": [0, 0, 1], "yaw_deg": 0},
        "objects": objects,
    }
    if light is not None:
        d["light"] = light
    return parse_scene(d)


def obj(name, iid, color, parts, label=None, **kw):
    return {"name": name, "label": label or name, "instance_id": iid, "color": color, "parts": parts, **kw}


def renderer(objects, camera=CAM, **kw):
    return Renderer(SceneGeometry(scene_of(objects)), camera, RenderConfig(**kw))


def looking_down(height_m, x=0.0, y=0.0):
    """Camera at (x, y, height) with the optical axis along world -z."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # columns: optical x, y, z in world
    return make_transform(R, [x, y, height_m])


def forward(p, yaw=0.0):
    return cam_transform_from_body(body_transform(p, yaw))


def test_default_camera_is_the_benchmark_camera():
    c = default_camera()
    assert (c.width, c.height) == (640, 427)
    assert np.degrees(c.hfov_rad) == pytest.approx(90.0) and np.degrees(c.vfov_rad) == pytest.approx(60.0)


def test_plane_seen_from_above_has_constant_z_depth():
    r = renderer([obj("floor", 1, "#808080", [{"type": "plane", "center_m": [0, 0, 0], "size_m": [100, 100]}])])
    out = r.render(looking_down(3.7))
    assert out.depth_m.dtype == np.float32 and out.depth_m.shape == (CAM.height, CAM.width)
    np.testing.assert_allclose(out.depth_m, 3.7, rtol=2e-6)
    assert np.all(out.instance_ids == 1)


def test_box_face_depth_and_ids_match_the_projection():
    # Front face of the box at x = 5 (box centre x = 6, depth 2), camera at origin looking +x.
    r = renderer([obj("box", 7, "#C03030", [{"type": "box", "center_m": [6, 0.5, 1.0], "size_m": [2, 2, 1.6]}])])
    T = forward([0, 0, 1.0])
    out = r.render(T)
    # Face x = 5, y in [-0.5, 1.5], z in [0.2, 1.8]; optical x = -y_world, optical y = 1 - z.
    (ul, vt), (ur, vb) = CAM.project(np.array([[-1.5, -0.8, 5.0], [0.5, 0.8, 5.0]]))[0]
    cols, rows = np.meshgrid(np.arange(CAM.width), np.arange(CAM.height))
    inside = (cols > ul + 1) & (cols < ur - 1) & (rows > vt + 1) & (rows < vb - 1)
    outside = (cols < ul - 1) | (cols > ur + 1) | (rows < vt - 1) | (rows > vb + 1)
    assert inside.sum() > 100
    np.testing.assert_allclose(out.depth_m[inside], 5.0, rtol=2e-6)
    assert np.all(out.instance_ids[inside] == 7)
    assert np.all(out.instance_ids[outside] == 0) and np.all(out.depth_m[outside] == 0.0)
    assert np.all(out.rgb[outside] == r.geometry.scene.sky_color)


def test_depth_is_z_depth_not_ray_length_on_an_oblique_wall():
    # Wall x = 4 seen by a camera yawed 30 deg: z-depth at pixel u is 4 / (cos(yaw) + sin(yaw) * xn)
    # where xn = (u - cx) / fx is the normalized image x (optical x = -y_world).
    r = renderer([obj("wall", 2, "#A0A0A0", [{"type": "box", "center_m": [4.5, 0, 1], "size_m": [1, 40, 20]}])])
    yaw = np.radians(30.0)
    out = r.render(forward([0, 0, 1], yaw))
    xn = (np.arange(CAM.width) - CAM.cx) / CAM.fx
    expected = 4.0 / (np.cos(yaw) + np.sin(yaw) * xn)
    row = CAM.height // 2
    np.testing.assert_allclose(out.depth_m[row], expected, rtol=5e-6)


def test_sphere_depth_at_the_centre_pixel():
    cam = PinholeCamera.from_fov(161, 109, 90.0, 60.0)  # odd size: a pixel centre on the axis
    r = renderer([obj("ball", 4, "#3060C0", [{"type": "sphere", "center_m": [6, 0, 1], "radius_m": 1.0, "rings": 16}])], camera=cam)
    out = r.render(forward([0, 0, 1]))
    assert out.depth_m[54, 80] == pytest.approx(5.0, abs=1e-5)  # an equator vertex of the UV sphere lies on the axis
    assert out.instance_ids[54, 80] == 4


def test_ids_match_the_object_hit_and_labels_map_to_semantic_ids():
    objs = [
        obj("left van", 11, "#C03030", [{"type": "box", "center_m": [6, 2, 1], "size_m": [1, 2, 2]}], label="van"),
        obj("right van", 12, "#3030C0", [{"type": "box", "center_m": [6, -2, 1], "size_m": [1, 2, 2]}], label="van"),
        obj("floor", 3, "#707070", [{"type": "plane", "center_m": [0, 0, 0], "size_m": [100, 100]}], label="ground"),
    ]
    r = renderer(objs)
    out = r.render(forward([0, 0, 1]))
    row = CAM.height // 2
    # y = +2 is on the image's left (optical x = -y_world); u = cx - fx * 2 / 5.5 ~ column 50.
    left_u = int(round(CAM.cx - CAM.fx * 2 / 5.5))
    right_u = int(round(CAM.cx + CAM.fx * 2 / 5.5))
    assert out.instance_ids[row, left_u] == 11 and out.instance_ids[row, right_u] == 12
    assert out.instance_ids[row, int(CAM.cx)] == 0  # the gap between them shows sky
    assert out.instance_ids[-1, int(CAM.cx)] == 3  # floor at the bottom of the image
    labels = r.geometry.scene.label_ids
    assert out.semantic_ids[row, left_u] == out.semantic_ids[row, right_u] == labels["van"]
    assert out.semantic_ids[-1, 0] == labels["ground"]
    ann = r.annotate(out)
    assert set(ann.objects) == {3, 11, 12}
    assert ann.objects[11].name == "left van" and ann.objects[11].label == "van"
    np.testing.assert_array_equal(ann.instance_ids, out.instance_ids)


def test_annotation_lists_only_instances_present_in_the_image():
    objs = [
        obj("front", 1, "#C03030", [{"type": "box", "center_m": [5, 0, 1], "size_m": [1, 30, 30]}]),
        obj("hidden", 2, "#3030C0", [{"type": "box", "center_m": [9, 0, 1], "size_m": [1, 2, 2]}]),
        obj("behind camera", 3, "#30C030", [{"type": "box", "center_m": [-5, 0, 1], "size_m": [1, 2, 2]}]),
    ]
    r = renderer(objs)
    ann = r.annotate(r.render(forward([0, 0, 1])))
    assert set(ann.objects) == {1}


def test_rgb_differs_between_labels_and_faces_are_shaded():
    objs = [
        obj("red thing", 1, "#C03030", [{"type": "box", "center_m": [6, 2, 1], "size_m": [1, 2, 2]}], label="a"),
        obj("blue thing", 2, "#3030C0", [{"type": "box", "center_m": [6, -2, 1], "size_m": [1, 2, 2]}], label="b"),
    ]
    r = renderer(objs)
    out = r.render(forward([0, 0, 1]))
    m1 = out.rgb[out.instance_ids == 1].astype(float).mean(axis=0)
    m2 = out.rgb[out.instance_ids == 2].astype(float).mean(axis=0)
    assert m1[0] > 3 * m1[2] and m2[2] > 3 * m2[0]
    # Seen from above at an angle, the top face (lit, normal +z) is brighter than a side face.
    top = r.render(cam_transform_from_body(body_transform([0, 2, 4], 0.0, pitch=np.radians(30))))
    ids = top.instance_ids == 1
    vals = top.rgb[ids][:, 0]
    assert len(np.unique(vals)) >= 2 and vals.max() - vals.min() > 30


def test_texture_varies_within_an_object_and_is_deterministic():
    tex = {"pattern": "stripes", "period_m": 0.25, "contrast": 0.5, "axis": "z"}
    r = renderer([obj("wall", 1, "#C0C0C0", [{"type": "box", "center_m": [5, 0, 1], "size_m": [1, 30, 30]}], texture=tex)])
    T = forward([0, 0, 1])
    a, b = r.render(T), r.render(T)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    col = a.rgb[:, CAM.width // 2, 0].astype(int)
    assert len(np.unique(col)) == 2  # one flat face: two stripe brightnesses
    # Bands of 0.25 m at 4.5 m depth: adjacent rows alternate every ~fy * 0.25 / 4.5 pixels.
    changes = np.count_nonzero(np.diff(col))
    expected = CAM.height / (CAM.fy * 0.25 / 4.5)
    assert abs(changes - expected) <= 2


@pytest.mark.parametrize("pattern", ["checker", "noise"])
def test_other_patterns_modulate_within_contrast(pattern):
    tex = {"pattern": pattern, "period_m": 0.3, "contrast": 0.4, "seed": 3}
    r = renderer([obj("floor", 1, "#C8C8C8", [{"type": "plane", "center_m": [0, 0, 0], "size_m": [100, 100]}], texture=tex)])
    out = r.render(looking_down(3.0))
    v = out.rgb[..., 0].astype(float)
    base = 0xC8 * (0.35 + 0.65 * r.geometry.scene.light.direction[2])
    assert v.max() <= base + 1 and v.min() >= (1 - 0.4) * base - 1
    assert v.std() > 5


def test_depth_noise_is_off_by_default_seeded_and_follows_its_model():
    objs = [obj("wall", 1, "#A0A0A0", [{"type": "box", "center_m": [4.5, 0, 1], "size_m": [1, 40, 40]}])]
    T = forward([0, 0, 1])
    exact = renderer(objs).render(T).depth_m
    np.testing.assert_allclose(exact, 4.0, rtol=2e-6)
    noise = DepthNoise(enabled=True, seed=5, sigma_base_m=0.01, sigma_quadratic_per_m=0.005, dropout_prob=0.05)
    r = renderer(objs, depth_noise=noise)
    a, b, c = r.render(T, noise_key=1), r.render(T, noise_key=1), r.render(T, noise_key=2)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert not np.array_equal(a.depth_m, c.depth_m)
    valid = a.depth_m > 0
    assert abs((~valid).mean() - 0.05) < 0.01
    sigma = 0.01 + 0.005 * 16.0
    assert a.depth_m[valid].std() == pytest.approx(sigma, rel=0.05)
    assert abs(a.depth_m[valid].mean() - 4.0) < 0.005
    far = DepthNoise(enabled=True, max_range_m=3.0)
    assert np.all(renderer(objs, depth_noise=far).render(T).depth_m == 0.0)


def test_bad_pose_and_configs_are_rejected():
    r = renderer([obj("floor", 1, "#808080", [{"type": "plane", "center_m": [0, 0, 0], "size_m": [10, 10]}])])
    with pytest.raises(FrameError, match="T_world_cam"):
        r.render(np.eye(3))
    with pytest.raises(ValueError, match="dropout_prob"):
        DepthNoise(dropout_prob=1.5)
    with pytest.raises(ValueError, match="threads"):
        RenderConfig(threads=-1)


def test_mesh_file_objects_render_with_their_id(tmp_path):
    ply = tmp_path / "quad.obj"
    ply.write_text("v 0 -1 0\nv 0 1 0\nv 0 1 2\nv 0 -1 2\nf 1 2 3\nf 1 3 4\n")
    r = renderer([obj("sign", 21, "#20A040", [{"type": "mesh", "path": str(ply), "position_m": [4, 0, 0]}])])
    out = r.render(forward([0, 0, 1]))
    row, col = CAM.height // 2, CAM.width // 2
    assert out.instance_ids[row, col] == 21
    assert out.depth_m[row, col] == pytest.approx(4.0, rel=2e-6)


def test_textures_can_be_switched_off_for_speed():
    tex = {"pattern": "checker", "period_m": 0.3, "contrast": 0.4}
    objs = [obj("floor", 1, "#C8C8C8", [{"type": "plane", "center_m": [0, 0, 0], "size_m": [100, 100]}], texture=tex)]
    on, off = renderer(objs).render(looking_down(3.0)), renderer(objs, textures=False).render(looking_down(3.0))
    assert len(np.unique(off.rgb[..., 0])) == 1 and len(np.unique(on.rgb[..., 0])) == 2
    np.testing.assert_array_equal(on.depth_m, off.depth_m)
    np.testing.assert_array_equal(on.instance_ids, off.instance_ids)


def test_objects_with_different_patterns_in_one_frame_keep_their_own_pattern():
    objs = [
        obj("striped", 1, "#C8C8C8", [{"type": "box", "center_m": [5, 3, 1], "size_m": [1, 4, 6]}],
            texture={"pattern": "stripes", "period_m": 0.25, "contrast": 0.5, "axis": "z"}),
        obj("noisy", 2, "#C8C8C8", [{"type": "box", "center_m": [5, -3, 1], "size_m": [1, 4, 6]}],
            texture={"pattern": "noise", "period_m": 0.1, "contrast": 0.5, "seed": 4}),
        obj("plain", 3, "#C8C8C8", [{"type": "box", "center_m": [5, 0, 1], "size_m": [1, 2, 6]}]),
    ]
    out = renderer(objs).render(forward([0, 0, 1]))
    red = out.rgb[..., 0]
    assert len(np.unique(red[out.instance_ids == 1])) == 2  # two stripe brightnesses
    assert len(np.unique(red[out.instance_ids == 2])) > 8  # many noise levels
    assert len(np.unique(red[out.instance_ids == 3])) == 1  # untextured
