"""World: observations carry a consistent pose, images and ground-truth annotation."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.observation import Observation
from onfly.world import World
from planning.frames import T_BODY_CAM
from planning.trajectory import Trajectory, VehicleState


@pytest.fixture(scope="module")
def world():
    return World.from_scene("villa")


def test_observation_matches_the_vehicle_pose_and_renderer(world):
    obs = world.observe()
    assert isinstance(obs, Observation)
    s = world.state
    np.testing.assert_allclose(obs.position, s.p, atol=1e-12)
    assert obs.yaw == pytest.approx(s.yaw)
    np.testing.assert_allclose(obs.T_body_cam, T_BODY_CAM)
    assert obs.rgb.shape == (427, 640, 3) and obs.depth_m.shape == (427, 640)
    ann = obs.annotation
    np.testing.assert_array_equal(ann.depth_m, obs.depth_m)
    present = set(np.unique(ann.instance_ids)) - {0}
    assert set(ann.objects) == present
    for iid, vo in ann.objects.items():
        o = world.scene.object_by_id(iid)
        assert (vo.name, vo.label, vo.aliases) == (o.name, o.label, o.aliases)
    again = world.observe()
    assert again.frame_id != obs.frame_id and again.frame_id.startswith("villa/")
    np.testing.assert_array_equal(again.rgb, obs.rgb)


def test_leaving_the_bounds_is_reported():
    w = World.from_scene("corridor", initial_state=VehicleState(0.0, [2.0, 0.0, 2.9], [0.0, 0.0, 0.5], 0.0))
    n = 20
    p = np.tile([2.0, 0.0, 2.9], (n + 1, 1))
    p[:, 2] += 0.05 * np.arange(n + 1)
    w.set_trajectory(Trajectory(0.0, 0.1, p, np.tile([0, 0, 0.5], (n + 1, 1)), np.zeros(n + 1), np.zeros((n, 3)), np.zeros(n)))
    flags = [w.step(0.1).out_of_bounds for _ in range(5)]
    # bounds top at 3.1 m: crossed during the 5th step (z reaches 3.15)
    assert flags == [False, False, False, False, True]


def test_observe_at_another_resolution_shares_the_scene(world):
    half = world.camera.scaled(0.5)
    obs = world.observe(half)
    assert obs.camera == half and obs.depth_m.shape == (half.height, half.width)
    assert world.renderer_for(half) is world.renderer_for(half)
    assert world.renderer_for(half).geometry is world.geometry
    full = world.observe()
    # the same view: mean depth over the valid pixels agrees closely between resolutions
    a, b = obs.depth_m[obs.depth_m > 0].mean(), full.depth_m[full.depth_m > 0].mean()
    assert abs(a - b) < 0.02 * b
