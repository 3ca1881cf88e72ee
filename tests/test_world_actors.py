"""Actors in the world: scene format, poses through the World, rendering against analytic
references, and collisions at the right time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onfly.world.actors import PathMotion
from onfly.world.collision import CollisionChecker
from onfly.world.geometry import SceneGeometry
from onfly.world.render import RenderConfig, Renderer
from onfly.world.scene import SceneFormatError, parse_scene
from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.frames import body_transform, cam_transform_from_body, make_transform

CAM = PinholeCamera.from_fov(160, 107, 90.0, 60.0)  # fx = fy... fx = 80 px


def scene_of(objects, start=(0.0, 0.0, 1.0)):
    return parse_scene(
        {
            "format": "onfly-scene/1",
            "name": "actors",
            "bounds": {"min_m": [-50, -50, -5], "max_m": [50, 50, 20]},
            "start": {"position_m": list(start), "yaw_deg": 0},
            "objects": objects,
        },
        "actors.toml",
    )


GROUND = {"name": "ground", "label": "ground", "instance_id": 1, "color": "#808080", "target": False,
          "parts": [{"type": "plane", "center_m": [0, 0, 0], "size_m": [100, 100]}]}


def walker(iid=5, name="walker", size=(0.5, 0.5, 1.8), motion=None):
    """A box person: ``size`` (forward, left, up) in its own frame, standing on its origin."""
    return {
        "name": name, "label": "person", "instance_id": iid, "color": "#C62828",
        "parts": [{"type": "box", "center_m": [0, 0, size[2] / 2], "size_m": list(size)}],
        "motion": motion,
    }


def north_walk(x=5.0, y0=-5.0, y1=5.0, speed=1.0, loop=False):
    return {"type": "path", "loop": loop, "waypoints": [
        {"position_m": [x, y0, 0.0], "speed_mps": speed}, {"position_m": [x, y1, 0.0], "speed_mps": speed}]}


def looking_down(height_m, x=0.0, y=0.0):
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # optical x, y, z in world
    return make_transform(R, [x, y, height_m])


# -- scene format -----------------------------------------------------------------------------


def test_scene_object_with_motion_is_an_actor():
    s = scene_of([GROUND, walker(motion=north_walk())])
    assert [o.name for o in s.actors] == ["walker"]
    assert [o.name for o in s.static_objects] == ["ground"]
    assert isinstance(s.object_by_name("walker").motion, PathMotion)
    assert s.object_by_name("walker").is_actor and not s.object_by_name("ground").is_actor


def test_bad_motion_names_file_object_and_field():
    bad = north_walk()
    bad["waypoints"][1]["speed_mps"] = 0
    with pytest.raises(SceneFormatError, match=r"actors\.toml: object 'walker': field 'motion\.waypoints\[1\]\.speed_mps': must be > 0"):
        scene_of([GROUND, walker(motion=bad)])
    with pytest.raises(SceneFormatError, match=r"field 'motion\.type'"):
        scene_of([GROUND, walker(motion={"type": "teleport"})])


def test_actor_cannot_have_a_texture():
    w = walker(motion=north_walk())
    w["texture"] = {"pattern": "checker"}
    with pytest.raises(SceneFormatError, match=r"object 'walker': field 'texture': an actor"):
        scene_of([GROUND, w])


# -- world API ----------------------------------------------------------------------------------


def test_world_actor_pose_by_id_and_name():
    w = World(scene_of([GROUND, walker(motion=north_walk())]), camera=CAM)
    assert w.actor_ids == (5,)
    p = w.actor_pose(5, 3.0)
    np.testing.assert_allclose(p.position_m, [5.0, -2.0, 0.0])
    assert p.yaw_rad == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(w.actor_pose("walker", 3.0).position_m, p.position_m)
    np.testing.assert_allclose(w.actor_pose("walker").position_m, [5.0, -5.0, 0.0])  # now = 0
    w.step(0.5)
    np.testing.assert_allclose(w.actor_pose("walker").position_m, [5.0, -4.5, 0.0], atol=1e-9)
    assert set(w.actor_poses(1.0)) == {5}
    with pytest.raises(KeyError, match="'ground' is not an actor.*actors: 'walker'"):
        w.actor_pose("ground")
    with pytest.raises(KeyError, match="not an actor"):
        w.actor_pose(99)


# -- rendering ----------------------------------------------------------------------------------


def test_rendered_actor_from_above_matches_analytic_depth_and_extent():
    # walker (2 m long along its x, 1 m wide, 2 m tall) walks north: seen from 10 m up at its
    # position, the top face is at z-depth 8 m, 1 m wide in world x (u) and 2 m long in y (v)
    w = walker(size=(2.0, 1.0, 2.0), motion=north_walk(x=3.0, y0=-10.0, y1=10.0))
    r = Renderer(SceneGeometry(scene_of([GROUND, w])), CAM)
    t = 7.0  # at (3, -3, 0)
    out = r.render(looking_down(10.0, 3.0, -3.0), t_s=t)
    cv, cu = CAM.height // 2, CAM.width // 2
    assert out.instance_ids[cv, cu] == 5
    assert out.depth_m[cv, cu] == pytest.approx(8.0, abs=1e-5)
    rows, cols = np.nonzero(out.instance_ids == 5)
    f = CAM.K[0, 0]
    # a pixel centre u is inside when |u - cx| <= f * half_width / depth
    expect_u = np.flatnonzero(np.abs(np.arange(CAM.width) - CAM.K[0, 2]) <= f * 0.5 / 8.0)
    expect_v = np.flatnonzero(np.abs(np.arange(CAM.height) - CAM.K[1, 2]) <= CAM.K[1, 1] * 1.0 / 8.0)
    assert (cols.min(), cols.max()) == (expect_u.min(), expect_u.max())
    assert (rows.min(), rows.max()) == (expect_v.min(), expect_v.max())
    np.testing.assert_allclose(out.depth_m[out.instance_ids == 5], 8.0, atol=1e-5)
    np.testing.assert_allclose(out.depth_m[out.instance_ids == 1], 10.0, atol=1e-5)
    assert np.all(out.semantic_ids[out.instance_ids == 5] == parse_scene_label_id("person"))


def parse_scene_label_id(label):
    return {"ground": 1, "person": 2}[label]


def test_moving_actor_render_equals_a_static_scene_at_its_pose():
    # the actor at its pose (with a yaw) renders exactly like the same box placed statically
    motion = {"type": "circle", "center_m": [6.0, 0.0, 0.0], "radius_m": 2.0, "speed_mps": 1.2, "phase_deg": 200.0}
    w = walker(size=(0.6, 0.4, 1.7), motion=motion)
    r_act = Renderer(SceneGeometry(scene_of([GROUND, w])), CAM)
    T_cam = cam_transform_from_body(body_transform([0.0, 0.5, 1.2], 0.1))
    for t in (0.0, 2.3, 7.9):
        geo = r_act.geometry
        pose = geo.actor(5).pose(t)
        static = walker(size=(0.6, 0.4, 1.7))
        del static["motion"]
        c = pose.T_world_actor @ [0.0, 0.0, 0.85, 1.0]
        static["parts"] = [{"type": "box", "center_m": c[:3].tolist(), "size_m": [0.6, 0.4, 1.7], "yaw_deg": math.degrees(pose.yaw_rad)}]
        r_ref = Renderer(SceneGeometry(scene_of([GROUND, static])), CAM)
        a = r_act.render(T_cam, t_s=t)
        b = r_ref.render(T_cam)
        assert np.count_nonzero(a.instance_ids == 5) > 50
        np.testing.assert_array_equal(a.instance_ids, b.instance_ids)
        np.testing.assert_allclose(a.depth_m, b.depth_m, atol=2e-5)
        # shading: same face normals at the pose
        assert np.mean(np.all(a.rgb == b.rgb, axis=2)) > 0.999


def test_actor_in_front_of_a_wall_occludes_it_and_behind_it_is_hidden():
    wall = {"name": "wall", "label": "wall", "instance_id": 2, "color": "#AAAAAA", "target": False,
            "parts": [{"type": "box", "center_m": [8.0, 0.0, 2.0], "size_m": [0.2, 20.0, 4.0]}]}
    # walks east along y = 0 from x = 2 to x = 14 at 1 m/s (passes through the wall: a test)
    motion = {"type": "path", "loop": False, "waypoints": [{"position_m": [2.0, 0.0, 0.0], "speed_mps": 1.0}, {"position_m": [14.0, 0.0, 0.0], "speed_mps": 1.0}]}
    r = Renderer(SceneGeometry(scene_of([GROUND, wall, walker(size=(1.0, 1.0, 2.0), motion=motion)])), CAM)
    T = cam_transform_from_body(body_transform([0.0, 0.0, 1.0], 0.0))
    cv, cu = CAM.height // 2, CAM.width // 2
    near = r.render(T, t_s=0.0)  # centre at x = 2: the camera is inside its bounding sphere
    assert near.instance_ids[cv, cu] == 5
    assert near.depth_m[cv, cu] == pytest.approx(1.5, abs=1e-5)
    front = r.render(T, t_s=2.0)  # actor centre at x = 4: front face at 3.5
    assert front.instance_ids[cv, cu] == 5
    assert front.depth_m[cv, cu] == pytest.approx(3.5, abs=1e-5)
    behind = r.render(T, t_s=9.0)  # at x = 13, behind the wall (front face at 7.9)
    assert behind.instance_ids[cv, cu] == 2
    assert behind.depth_m[cv, cu] == pytest.approx(7.9, abs=1e-5)
    assert not np.any(behind.instance_ids == 5)


def test_world_renders_actors_at_the_clock_time():
    motion = {"type": "path", "loop": False, "waypoints": [{"position_m": [3.0, 0.0, 0.0], "speed_mps": 1.0}, {"position_m": [9.0, 0.0, 0.0], "speed_mps": 1.0}]}
    w = World(scene_of([GROUND, walker(size=(1.0, 1.0, 2.0), motion=motion)]), camera=CAM)
    cv, cu = CAM.height // 2, CAM.width // 2
    assert w.render().depth_m[cv, cu] == pytest.approx(2.5, abs=1e-5)
    for _ in range(20):
        w.step(0.1)
    assert w.render().depth_m[cv, cu] == pytest.approx(4.5, abs=1e-4)


# -- collisions ---------------------------------------------------------------------------------


def test_collision_with_a_walker_at_the_right_time():
    # the walker's 0.5 m box front face reaches y = t - 5 + 0.25; a body of radius 0.25 m
    # hovering at (5, 0, 1) is hit once that face is closer than 0.25 m: t > 4.5 s
    g = SceneGeometry(scene_of([GROUND, walker(motion=north_walk())]))
    cc = CollisionChecker(g, 0.25)
    t = np.arange(0.0, 10.0, 0.01)
    hover = np.tile([5.0, 0.0, 1.0], (len(t), 1))
    hit = cc.first_collision(hover, t)
    assert hit is not None and hit.object_name == "walker" and hit.instance_id == 5
    assert 4.5 < hit.t_s <= 4.52
    assert hit.point_m[1] == pytest.approx(hit.t_s - 5.0 + 0.25, abs=1e-5)
    # crossing the walker's line (x = 5) while it is there collides; after it has gone does not
    x = np.linspace(0.0, 10.0, 2001)
    path = np.stack([x, np.zeros_like(x), np.full_like(x, 1.0)], axis=1)
    early = cc.first_collision(path, x)  # at (5, 0) at t = 5: walker there
    assert early is not None and early.object_name == "walker" and 4.4 < early.t_s < 5.0
    assert cc.first_collision(path, x + 7.0) is None  # at (5, 0) at t = 12: walker long gone
    assert cc.clearance(path[1000:1001], 12.0)[0] == pytest.approx(1.0, abs=1e-6)  # the ground
    assert cc.clearance(path[1000:1001], 4.6)[0] == pytest.approx(0.15, abs=1e-5)  # walker face at y = -0.15
    assert cc.clearance(path[1000:1001])[0] == pytest.approx(1.0, abs=1e-6)  # static scene only
    with pytest.raises(ValueError, match="has actors: first_collision needs times_s"):
        cc.first_collision(path)


def test_world_step_detects_a_walker_hitting_the_hovering_vehicle():
    w = World(scene_of([GROUND, walker(motion=north_walk())], start=(5.0, 0.0, 1.0)), camera=CAM)
    hit = None
    while hit is None and w.clock.now_s < 8.0:
        hit = w.step(0.1).collision
    assert hit is not None and hit.object_name == "walker"
    assert 4.5 < hit.t_s <= 4.55
