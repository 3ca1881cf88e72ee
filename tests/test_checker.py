"""The task checker on constructed scenes (detour through a gap, enclosed goal, hidden target,
bad starts) and a re-check of the committed references."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.bench.checker import CheckerConfig, TaskChecker, densify, path_clearance, polyline_length
from onfly.bench.tasks import GoalSpec, StartPose, Task, load_tasks, object_bounds
from onfly.world.geometry import SceneGeometry
from onfly.world.scene import load_scene, parse_scene, resolve_scene


def _obj(name, iid, parts, target=True):
    return {"name": name, "label": name.split()[-1], "instance_id": iid, "color": "#808080", "target": target, "parts": parts}


def _box(center, size):
    return {"type": "box", "center_m": list(center), "size_m": list(size)}


def _scene(extra_objects=()):
    """20 x 20 m yard; a wall along x = 0 as high as the bounds with a 2 m gap at y in [4, 6]; a red crate."""
    objects = [
        _obj("ground", 1, [{"type": "plane", "center_m": [0, 0, 0], "size_m": [40, 40]}], target=False),
        _obj("wall", 2, [_box([0, -4.5, 2.5], [0.4, 17, 5]), _box([0, 8.5, 2.5], [0.4, 5, 5])], target=False),
        _obj("red crate", 3, [_box([6, -3, 0.5], [1, 1, 1])]),
        *extra_objects,
    ]
    data = {
        "format": "onfly-scene/1",
        "name": "yard",
        "bounds": {"min_m": [-10, -10, 0], "max_m": [10, 11, 5]},
        "start": {"position_m": [-6, -3, 1.5], "yaw_deg": 0},
        "objects": objects,
    }
    return parse_scene(data, "<yard>")


def _task(scene, goal: GoalSpec, targets, start=(-6.0, -3.0, 1.5), task_id="yard-1", via=()):
    return Task(task_id, scene.name, "object", "fly to the red crate", ("fly to the red crate",), tuple(targets), goal,
                StartPose(np.array(start, float), 0.0), tuple(via))


def _object_goal(scene, name, margin=0.0):
    lo, hi = object_bounds(scene, name)
    return GoalSpec((lo + hi) / 2, (hi - lo) / 2 + margin, name, margin)


@pytest.fixture(scope="module")
def yard():
    scene = _scene()
    return scene, TaskChecker(scene, CheckerConfig())


def test_detour_through_the_gap_is_found_and_proven_clear(yard):
    scene, checker = yard
    r = checker.check(_task(scene, _object_goal(scene, "red crate"), ["red crate"]))
    assert r.ok, r.problems
    ref = r.reference
    # the straight line crosses the wall; the way round goes through the gap (y in [4, 6])
    straight = np.linalg.norm(np.array([5.5, -3.0]) - np.array([-6.0, -3.0]))
    assert ref.path_length_m > straight + 6.0
    dense = densify(ref.waypoints_m, 0.05)
    at_wall = dense[np.abs(dense[:, 0]) < 0.2]
    assert len(at_wall) and np.all((at_wall[:, 1] > 4.0) & (at_wall[:, 1] < 6.0))
    # exact proof: the body (0.25 m) plus margin never touches a triangle
    assert ref.min_clearance_m >= 0.35
    assert path_clearance(checker.geometry, ref.waypoints_m) == pytest.approx(ref.min_clearance_m, abs=1e-6)
    assert ref.path_length_m == pytest.approx(polyline_length(ref.waypoints_m))
    assert r.stats["goal_gap_m"] <= 1.5
    # the shortest way round is two straight legs through the gap: the reference is near it
    gap = np.array([0.0, 5.0])
    shortest = np.linalg.norm(gap - [-6, -3]) + np.linalg.norm([5.5, -3] - gap)
    assert ref.path_length_m < shortest + 2.5
    # and the crate is seen from the path
    assert ref.visible_from_m is not None


def _cage():
    """A closed 3 x 3 x 3 m box of 0.2 m walls and a roof round (6, 7.5), its floor the ground."""
    walls = [_box([6, 6, 1.5], [3, 0.2, 3]), _box([6, 9, 1.5], [3, 0.2, 3]), _box([4.5, 7.5, 1.5], [0.2, 3, 3]),
             _box([7.5, 7.5, 1.5], [0.2, 3, 3]), _box([6, 7.5, 3.1], [3.2, 3.2, 0.2])]
    return _obj("cage", 4, walls, target=False)


def test_enclosed_goal_is_unreachable():
    cage = _cage()
    gem = _obj("green gem", 5, [_box([6, 7.5, 0.3], [0.4, 0.4, 0.4])])
    scene = _scene([cage, gem])
    r = TaskChecker(scene).check(_task(scene, _object_goal(scene, "green gem"), ["green gem"]))
    assert not r.ok and r.reference is None
    assert any("goal region: the closest reachable free point is" in p for p in r.problems)


def test_a_goal_point_behind_the_wall_its_object_stands_against_is_refused():
    # the gem stands inside a closed cage, against its 0.2 m south wall: the reachable voxels
    # nearest it are outside, within the goal gap, but the wall is between them and it
    cage = _cage()
    gem = _obj("green gem", 5, [_box([6, 6.35, 1.5], [0.4, 0.3, 0.4])])
    scene = _scene([cage, gem])
    checker = TaskChecker(scene)
    r = checker.check(_task(scene, _object_goal(scene, "green gem"), ["green gem"]))
    assert not r.ok and r.reference is None
    assert r.problems == (f"goal region: no reachable free point within {CheckerConfig().max_goal_gap_m} m of it has a line of sight to it",)
    # the same cage with a doorway in the north wall: the goal point is the nearest voxel that
    # sees the gem through it, inside, not the nearer one outside the south wall
    walls = [p for p in cage["parts"]]
    walls[1] = _box([4.8, 9, 1.5], [0.6, 0.2, 3])
    walls.append(_box([7.2, 9, 1.5], [0.6, 0.2, 3]))  # a 1.8 m doorway at x in [5.1, 6.9]
    scene = _scene([{**cage, "parts": walls}, gem])
    checker = TaskChecker(scene)
    r = checker.check(_task(scene, _object_goal(scene, "green gem"), ["green gem"]))
    assert r.ok, r.problems
    goal = r.reference.goal_point_m
    assert checker.visible_mask(goal[None], "green gem", level_camera=False)[0]
    assert 6.0 < goal[1] < 9.0  # inside the cage


def test_target_behind_a_tall_wall_is_not_visible():
    # a 6 m wall (above the 5 m bounds) hides a post; the goal box is reachable in front of the wall
    screen = _obj("screen", 4, [_box([5.5, 7.5, 3], [9, 0.2, 6])], target=False)
    post = _obj("blue post", 5, [_box([6, 9.5, 0.5], [0.3, 0.3, 1])])
    scene = _scene([screen, post])
    goal = GoalSpec(np.array([6.0, 6.3, 1.5]), np.array([0.5, 0.3, 0.5]))
    r = TaskChecker(scene).check(_task(scene, goal, ["blue post"]))
    assert not r.ok
    assert r.problems == ("target 'blue post' is not visible from any point of the reference path",)


def test_bad_starts_are_reported(yard):
    scene, checker = yard
    goal = _object_goal(scene, "red crate")
    r = checker.check(_task(scene, goal, ["red crate"], start=(0.0, -3.0, 1.5)))  # inside the wall
    assert not r.ok and "start has clearance" in r.problems[-1]
    r = checker.check(_task(scene, goal, ["red crate"], start=(2.0, -3.0, 1.5)))  # 3.5 m from the crate
    assert not r.ok and "only 3.5 m from the start" in r.problems[0]


def test_via_objects_are_passed(yard):
    scene, checker = yard
    lamp = _obj("lamp", 4, [{"type": "cylinder", "base_m": [-6, 6, 0], "radius_m": 0.1, "height_m": 3}])
    scene2 = _scene([lamp])
    checker2 = TaskChecker(scene2)
    direct = checker2.check(_task(scene2, _object_goal(scene2, "red crate"), ["red crate"]))
    via = checker2.check(_task(scene2, _object_goal(scene2, "red crate"), ["lamp", "red crate"], via=["lamp"]))
    assert direct.ok and via.ok
    lo, hi = object_bounds(scene2, "lamp")
    d = np.linalg.norm(np.maximum(np.abs(densify(via.reference.waypoints_m, 0.05) - (lo + hi) / 2) - (hi - lo) / 2, 0), axis=1)
    assert d.min() <= 2.5
    assert via.reference.path_length_m > direct.reference.path_length_m


def test_a_via_object_is_passed_where_it_is_in_sight_not_through_the_wall_it_hangs_on():
    # a red banner hangs on the east face of a 0.12 m partition south of the wall's gap; the
    # reachable voxels nearest it (within the approach slack) include the partition's west side,
    # cheaper from the gap, which a route would pass with the partition between it and the banner
    part = _obj("partition", 4, [_box([3, -4, 2.5], [0.12, 12, 5])], target=False)
    banner = _obj("red banner", 5, [_box([3.16, -3, 2.5], [0.2, 2, 1])])
    scene = _scene([part, banner])
    checker = TaskChecker(scene)
    r = checker.check(_task(scene, _object_goal(scene, "red crate"), ["red banner", "red crate"], via=["red banner"]))
    assert r.ok, r.problems
    wp = densify(r.reference.waypoints_m, 0.05)
    lo, hi = object_bounds(scene, "red banner")
    d = np.linalg.norm(np.maximum(np.abs(wp - (lo + hi) / 2) - (hi - lo) / 2, 0), axis=1)
    passed = wp[np.argmin(d)]
    assert d.min() <= CheckerConfig().via_radius_m
    assert checker.visible_mask(passed[None], "red banner", level_camera=False)[0]
    assert not np.any((wp[:, 0] > 0.2) & (wp[:, 0] < 3.0) & (wp[:, 1] < 1.0))  # never down the partition's west side


def test_checker_config_is_validated():
    with pytest.raises(ValueError, match="CheckerConfig.voxel_m must be positive"):
        CheckerConfig(voxel_m=0.0)
    with pytest.raises(ValueError, match="proof_margin_m must not exceed clearance_margin_m"):
        CheckerConfig(proof_margin_m=0.3, clearance_margin_m=0.2)


def test_committed_references_are_collision_free_and_in_bounds():
    """Every committed reference polyline keeps body radius + 10 cm from every triangle (exact)."""
    by_scene: dict[str, list[Task]] = {}
    for t in load_tasks():
        by_scene.setdefault(t.scene, []).append(t)
    for name, tasks in by_scene.items():
        scene = load_scene(resolve_scene(name))
        geo = SceneGeometry(scene)
        for t in tasks:
            dense = densify(t.reference.waypoints_m, 0.05)
            assert geo.closest(dense)[0].min() >= 0.35 - 2e-3, t.task_id  # waypoints stored to the mm
            assert np.all(scene.bounds.contains(dense)), t.task_id


def test_recheck_of_a_committed_sample_reproduces_the_reference():
    tasks = [t for t in load_tasks() if t.task_id in ("corridor-o01", "corridor-p05", "corridor-l01")]
    checker = TaskChecker(load_scene(resolve_scene("corridor")))
    for t in tasks:
        r = checker.check(t)
        assert r.ok, (t.task_id, r.problems)
        assert r.reference.path_length_m == pytest.approx(t.reference.path_length_m, abs=0.01)
        np.testing.assert_allclose(r.reference.goal_point_m, t.reference.goal_point_m, atol=1e-3)
