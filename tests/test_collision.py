"""Collisions: exact at a known contact distance, first hit recorded, episode ends there."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.world.collision import CollisionChecker
from onfly.world.geometry import SceneGeometry
from onfly.world.scene import parse_scene
from onfly.world.world import EpisodeEndedError, World
from planning.trajectory import Trajectory, VehicleState

R = 0.25


def scene():
    return parse_scene(
        {
            "format": "onfly-scene/1",
            "name": "wall",
            "bounds": {"min_m": [-10, -10, 0], "max_m": [10, 10, 5]},
            "start": {"position_m": [0, 0, 1.5], "yaw_deg": 0},
            "objects": [
                {"name": "grey wall", "label": "wall", "instance_id": 5, "color": "#808080",
                 "parts": [{"type": "box", "center_m": [3.5, 0, 2], "size_m": [1, 4, 4]}]},
                {"name": "post", "label": "post", "instance_id": 9, "color": "#404040",
                 "parts": [{"type": "cylinder", "base_m": [-3, 0, 0], "radius_m": 0.3, "height_m": 3, "segments": 8}]},
            ],
        }
    )


@pytest.fixture(scope="module")
def checker():
    return CollisionChecker(SceneGeometry(scene()), R)


@pytest.mark.parametrize(
    "centre_on_surface, normal",
    [
        ([3.0, 0.3, 1.7], [-1.0, 0.0, 0.0]),  # wall face x = 3
        ([3.2, 2.0, 1.1], [0.0, 1.0, 0.0]),  # side face y = 2
        ([3.0, -2.0, 4.0], np.array([-1.0, -1.0, 1.0]) / np.sqrt(3)),  # corner (3, -2, 4)
    ],
)
def test_contact_is_exact_at_radius_plus_minus_one_centimetre(checker, centre_on_surface, normal):
    q = np.asarray(centre_on_surface)
    n = np.asarray(normal)
    clear = q + n * (R + 0.01)
    hit = q + n * (R - 0.01)
    assert checker.clearance(clear[None])[0] == pytest.approx(R + 0.01, abs=1e-5)
    assert checker.first_collision(clear[None]) is None
    c = checker.first_collision(hit[None], [7.5])
    assert c is not None
    assert c.t_s == 7.5 and c.instance_id == 5 and c.object_name == "grey wall"
    assert c.distance_m == pytest.approx(R - 0.01, abs=1e-5)
    np.testing.assert_allclose(c.point_m, q, atol=1e-5)
    np.testing.assert_allclose(c.position_m, hit)


def test_first_collision_in_time_order_and_the_object_hit(checker):
    path = np.array([[0.0, 0.0, 1.5], [-2.4, 0.0, 1.5], [-2.6, 0.0, 1.5], [2.9, 0.0, 1.5]])
    c = checker.first_collision(path, [0.0, 1.0, 2.0, 3.0])
    # The octagonal post has a vertex at (-2.7, 0): 0.3 m from (-2.4, 0), 0.1 m from (-2.6, 0).
    assert c.t_s == 2.0 and c.object_name == "post"
    assert c.distance_m == pytest.approx(0.1, abs=1e-5)
    with pytest.raises(ValueError, match="times_s has 2 entries for 4 points"):
        checker.first_collision(path, [0.0, 1.0])


def test_world_episode_ends_at_the_first_contact_with_the_wall():
    world = World(scene(), initial_state=VehicleState(0.0, [0, 0, 1.5], [0.5, 0, 0], 0.0))
    # A plan that flies straight into the wall at 0.5 m/s.
    n, dt = 200, 0.1
    p = np.zeros((n + 1, 3))
    p[:, 0] = 0.5 * dt * np.arange(n + 1)
    p[:, 2] = 1.5
    v = np.tile([0.5, 0.0, 0.0], (n + 1, 1))
    world.set_trajectory(Trajectory(0.0, dt, p, v, np.zeros(n + 1), np.zeros((n, 3)), np.zeros(n)))
    hit = None
    for _ in range(200):
        step = world.step(0.1)
        if step.collision is not None:
            hit = step.collision
            break
    assert hit is not None and hit.object_name == "grey wall"
    # Contact at x = 3 - R; detected at the first 10 ms integration step past it.
    assert 3.0 - R < hit.position_m[0] <= 3.0 - R + 0.5 * 0.01 + 1e-6
    assert hit.t_s == pytest.approx((3.0 - R) / 0.5, abs=0.011)
    assert world.collided is hit
    with pytest.raises(EpisodeEndedError, match="grey wall"):
        world.step(0.1)
