"""WorldVehicleModel: the embedded world's dynamics, collisions and camera behind the MAVLink
vehicle (setpoint -> plan, take-off, touchdown, crash, fall, camera), and the simulated PX4
disarming on a crash."""

import time
from types import SimpleNamespace

import numpy as np
import pytest

from onfly.mavlink.sim_world import BENCHMARK_CAMERA, WorldModelConfig, WorldVehicleModel, ground_below, trajectory_from_setpoint
from onfly.world.vehicle import VehicleConfig
from planning.trajectory import VehicleState

START = [0.0, -26.0, 1.5]  # urban_block's start, facing +y (the street)


def sp(p=None, v=None, a=None, yaw=None):
    arr = lambda x: None if x is None else np.asarray(x, float)
    return SimpleNamespace(p=arr(p), v=arr(v), a=arr(a), yaw=yaw)


@pytest.fixture(scope="module")
def model_factory():
    return lambda **kw: WorldVehicleModel.from_scene("urban_block", position_m=START, yaw_rad=np.pi / 2, **kw)


def fly(model, target, seconds, armed=True):
    for _ in range(int(round(seconds / 0.01))):
        model.step(0.01, target, armed)


def test_trajectory_from_setpoint_extrapolates_exactly():
    s = VehicleState(3.0, np.array([1.0, 2.0, 3.0]), np.zeros(3), 3.0)
    tr = trajectory_from_setpoint(3.0, s, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0], -3.0, horizon_s=1.0, dt_s=0.1)
    assert tr.steps == 10 and tr.t0_s == 3.0
    p, v, a, yaw, _ = tr.sample(3.5)
    np.testing.assert_allclose(p, [0.5, 0.25, 1.0])  # p + v t + a t^2 / 2
    np.testing.assert_allclose(v, [1.0, 1.0, 0.0])
    np.testing.assert_allclose(a, [0.0, 2.0, 0.0])
    assert yaw == pytest.approx(-3.0) and tr.yaw[0] == pytest.approx(3.0 + (2 * np.pi - 6.0))  # unwrapped near 3.0
    down = trajectory_from_setpoint(3.0, s, None, [0.0, 0.0, -0.5], None, None)
    np.testing.assert_allclose(down.sample(4.0)[0], [1.0, 2.0, 2.5])
    assert trajectory_from_setpoint(3.0, s, None, [0.0, 0.0, 0.0], None, None) is None  # BRAKE: brake to hover
    assert trajectory_from_setpoint(3.0, s, None, None, None, 1.0) is None


def test_starts_on_the_ground_takes_off_within_the_world_limits_and_touches_down(model_factory):
    m = model_factory()
    assert m.ground_z_m == pytest.approx(0.0, abs=1e-5) and m.on_ground and m.p[2] == pytest.approx(m.ground_z_m)
    limits = VehicleConfig()
    fly(m, sp(p=[0.0, -26.0, 0.0]), 0.5)  # armed, hold on the ground: stays
    assert m.on_ground and m.p[2] == pytest.approx(m.ground_z_m)
    speeds = []
    for _ in range(600):
        m.step(0.01, sp(p=START), True)
        speeds.append(np.linalg.norm(m.v))
    assert not m.on_ground and abs(m.p[2] - 1.5) < 0.02 and max(speeds) <= limits.v_max_mps + 1e-9
    fly(m, sp(v=[0.0, 0.0, -0.7]), 5.0)  # PX4 AUTO.LAND: a velocity setpoint held until replaced
    assert m.on_ground and m.p[2] == pytest.approx(m.ground_z_m) and not m.crashed
    kinds = [e.split(" ")[0] for _, e in m.events]
    assert kinds == ["lift-off", "touchdown"]


def test_a_collision_stops_the_vehicle_and_names_the_object(model_factory):
    m = model_factory()
    fly(m, sp(p=START), 5.0)
    fly(m, sp(p=[12.0, -26.0, 1.5], yaw=0.0), 25.0)  # into the brick building (x >= 8)
    c = m.collision
    assert m.crashed and c.object_name == "brick building"
    assert c.distance_m < VehicleConfig().body_radius_m and c.position_m[0] == pytest.approx(8.0 - 0.25, abs=0.01)
    p = m.p
    fly(m, sp(p=[0.0, -26.0, 1.5]), 1.0)
    np.testing.assert_array_equal(m.p, p)  # a crashed vehicle does not move


def test_disarmed_in_the_air_it_falls_and_crashes(model_factory):
    m = model_factory()
    fly(m, sp(p=START), 5.0)
    fly(m, None, 1.0, armed=False)
    assert m.crashed and m.collision.object_name.startswith("ground") and m.p[2] == pytest.approx(m.ground_z_m)
    t_fall = m.collision.t_s - 5.0
    assert t_fall == pytest.approx(np.sqrt(2 * 1.5 / 9.81), abs=0.03)


def test_camera_renders_the_benchmark_view_from_the_current_pose(model_factory):
    m = model_factory()
    fly(m, sp(p=START), 5.0)
    obs = m.observe()
    assert obs.camera == BENCHMARK_CAMERA and obs.rgb.shape == (214, 320, 3)
    np.testing.assert_allclose(obs.position, m.p, atol=1e-9)
    assert obs.yaw == pytest.approx(np.pi / 2, abs=1e-3)
    names = {o.name for o in obs.annotation.objects.values()}
    assert "red van" in names  # o01's target is in view from the start
    assert m.observe().frame_id != obs.frame_id


def test_ground_below_and_bad_starts(model_factory):
    m = model_factory()
    assert ground_below(m.world, [0.0, -26.0, 5.0]) == pytest.approx(0.0, abs=1e-5)
    with pytest.raises(ValueError, match="no ground below"):
        ground_below(m.world, [0.0, -26.0, -5.0])
    with pytest.raises(ValueError, match="position_m must be 3 finite numbers"):
        WorldVehicleModel.from_scene("urban_block", position_m=[np.nan, 0.0, 1.0])
    with pytest.raises(ValueError, match="target_dt_s must not exceed"):
        WorldModelConfig(target_horizon_s=0.1, target_dt_s=0.5)


def test_the_simulated_px4_disarms_when_its_world_vehicle_crashes(model_factory):
    from onfly.mavlink.link import memory_link_pair
    from onfly.mavlink.sim_vehicle import SimMavlinkVehicle, SimVehicleConfig

    m = model_factory()
    fly(m, sp(p=START), 5.0)
    _, link = memory_link_pair(1, 191, 1, 1)
    vehicle = SimMavlinkVehicle(link, SimVehicleConfig(), model=m)
    vehicle.armed = True
    m.collision = SimpleNamespace(object_name="lamp post")  # the model reports a crash
    with vehicle:
        deadline = time.monotonic() + 2.0
        while vehicle.armed and time.monotonic() < deadline:
            time.sleep(0.01)
    assert not vehicle.armed and vehicle.first_event("disarmed: crashed into 'lamp post'") is not None


def test_the_controller_setpoint_is_the_followed_plan_and_none_on_the_ground(model_factory):
    """What the MAVLink vehicle reports as PX4's velocity and acceleration setpoints
    (POSITION_TARGET_LOCAL_NED): the plan the world's vehicle follows at this instant; nothing
    while it rests on the ground."""
    m = model_factory()
    assert m.controller_setpoint() is None
    fly(m, sp(p=START), 3.0)  # take off to the start height
    fly(m, sp(v=[1.0, 0.0, 0.0]), 0.5)  # a velocity setpoint: its plan holds 1 m/s east
    v, a = m.controller_setpoint()
    traj = m.world.vehicle.trajectory
    _, v_ref, a_ref, _, _ = traj.sample(float(m.world.vehicle.state.t_s))
    np.testing.assert_allclose(v, v_ref, atol=1e-12)
    np.testing.assert_allclose(a, a_ref, atol=1e-12)
    assert v[0] > 0.5 and abs(v[1]) < 0.05  # east, as commanded (within the world's limits)
