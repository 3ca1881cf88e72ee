"""Realism profiles: each figure seeded and reproducible; the pilot's estimate apart from the
truth that collisions use; glass in a committed scene gives no depth readings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onfly.world import World
from onfly.world.realism import (
    PROFILES,
    ControllerModel,
    DepthModel,
    FrameModel,
    GustProcess,
    OdometryDrift,
    OdometryModel,
    RealismError,
    RealismProfile,
    WindModel,
    realism_profile,
)
from onfly.world.render import default_camera
from onfly.world.scene import MATERIALS
from planning.trajectory import Trajectory, VehicleState

REALISTIC = PROFILES["realistic"]


# -- profiles -----------------------------------------------------------------------------------


def test_profiles_by_name_and_unknown_names_list_the_valid_ones():
    assert realism_profile(None) is PROFILES["ideal"] and PROFILES["ideal"].is_ideal
    assert realism_profile("realistic") is REALISTIC and not REALISTIC.is_ideal
    calm = realism_profile("realistic_calm")
    assert calm.wind is None and (calm.depth, calm.odometry, calm.controller, calm.frames) == (
        REALISTIC.depth, REALISTIC.odometry, REALISTIC.controller, REALISTIC.frames)
    with pytest.raises(RealismError, match=r"unknown realism profile 'foggy'; valid: ideal, realistic, realistic_calm"):
        realism_profile("foggy")
    with pytest.raises(RealismError, match="no_reading_materials: unknown material"):
        DepthModel(no_reading_materials=("velvet",))
    with pytest.raises(RealismError, match="drop_prob must be < 1"):
        FrameModel(drop_prob=1.0)


def test_realistic_figures_are_the_cited_ones():
    d = REALISTIC.depth
    # Intel's stereo RMS formula with the D435 at 848 px (focal 424 px, 50 mm, subpixel 0.08)
    assert d.sigma_m(2.0) == pytest.approx(4.0 * 0.08 / (424.0 * 0.05))
    assert d.sigma_m(2.0) / 2.0 < 0.02  # inside the datasheet's "< 2 % at 2 m"
    assert d.sigma_m(4.0) == pytest.approx(4.0 * d.sigma_m(2.0))  # quadratic growth
    assert d.min_range_m == pytest.approx(424.0 * 0.05 / 126, abs=0.005) and d.max_range_m == 10.0
    c = REALISTIC.controller
    assert (c.k_pos_xy_per_s, c.k_vel_xy_per_s, c.k_pos_z_per_s, c.k_vel_z_per_s) == (0.95, 1.8, 1.0, 4.0)
    assert c.tau_s == pytest.approx(1 / 6.5)
    w = REALISTIC.wind  # MIL-F-8785C low-altitude light turbulence at 1.5 m
    assert w.sigma_z_mps == pytest.approx(0.77)
    assert w.sigma_xy_mps == pytest.approx(0.77 / (0.177 + 0.000823 * 1.5 / 0.3048) ** 0.4)
    assert 1.0 < w.tau_xy_s < 4.0 and w.tau_z_s < w.tau_xy_s


# -- depth --------------------------------------------------------------------------------------


def test_depth_noise_is_quadratic_seeded_and_reproducible():
    d = DepthModel(edge_jump_ratio=0.0)
    for z in (2.0, 5.0):
        img = np.full((200, 300), z, np.float32)
        a = d.apply(img, None, np.random.default_rng([1, 2]))
        b = d.apply(img, None, np.random.default_rng([1, 2]))
        c = d.apply(img, None, np.random.default_rng([1, 3]))
        np.testing.assert_array_equal(a, b)
        assert not np.array_equal(a, c)
        assert np.std(a - z) == pytest.approx(d.sigma_m(z), rel=0.03)
        assert abs(np.mean(a - z)) < 0.01 * d.sigma_m(z) * 10


def test_depth_range_limits_and_no_reading_materials():
    d = DepthModel(subpixel=0.0, edge_jump_ratio=0.0)
    img = np.array([[0.1, 0.5, 9.0, 12.0]], np.float32)
    out = d.apply(img, None, np.random.default_rng(0))
    np.testing.assert_array_equal(out, [[0.0, 0.5, 9.0, 0.0]])
    img = np.full((1, len(MATERIALS)), 3.0, np.float32)
    mat = np.arange(len(MATERIALS), dtype=np.uint8)[None]
    out = d.apply(img, mat, np.random.default_rng(0))
    for code, name in enumerate(MATERIALS):
        assert (out[0, code] == 0.0) == (name in ("glass", "mirror", "dark")), name


def test_flying_pixels_lie_between_the_surfaces_on_the_far_side_of_an_edge():
    d = DepthModel(subpixel=0.0)
    img = np.full((20, 40), 6.0, np.float32)
    img[:, :20] = 2.0  # a near surface on the left half
    out = d.apply(img, None, np.random.default_rng(4))
    changed = out != img
    assert changed[:, 20].all() and changed.sum() == 20  # exactly the far-side column of the edge
    assert np.all((out[:, 20] > 2.0) & (out[:, 20] < 6.0))
    again = d.apply(img, None, np.random.default_rng(4))
    np.testing.assert_array_equal(out, again)


def _glass_door_view(realism):
    # in front of the glass door of the office tower (urban_block), looking west at it
    start = VehicleState(0.0, [-4.0, -24.0, 1.4], np.zeros(3), math.pi)
    return World.from_scene("urban_block", realism=realism, seed=5, initial_state=start)


def test_glass_doors_and_mirror_facades_rendered_from_a_scene_give_no_readings():
    real, ideal = _glass_door_view("realistic"), _glass_door_view("ideal")
    door = real.scene.object_by_name("glass door").instance_id
    tower = real.scene.object_by_name("glass office tower").instance_id
    obs_r, obs_i = real.observe(), ideal.observe()
    on_door = obs_r.annotation.instance_ids == door
    on_tower = obs_r.annotation.instance_ids == tower
    assert on_door.sum() > 1000 and on_tower.sum() > 1000
    assert np.all(obs_r.depth_m[on_door] == 0.0) and np.all(obs_r.depth_m[on_tower] == 0.0)
    assert np.all(obs_i.depth_m[on_door] > 0.0)  # the ideal camera sees the door
    # the VLM still sees the door (the annotation keeps the exact depth) and it is solid
    assert np.all(obs_r.annotation.depth_m[on_door] > 0.0)
    wall_ahead = np.array([[-7.8, -24.0, 1.4]])
    assert real.collision.clearance(wall_ahead)[0] < real.vehicle.config.body_radius_m
    # opaque surfaces in range in the same frame keep their readings
    exact = obs_r.annotation.depth_m
    mat = real.geometry.tri_material  # per triangle; opaque objects here: everything but door, tower, tyres
    others = ~on_door & ~on_tower & (exact > 0.5) & (exact < 9.0)
    assert others.sum() > 1000 and (obs_r.depth_m[others] > 0).mean() > 0.9
    assert mat.max() < len(MATERIALS)


# -- odometry, vehicle, wind --------------------------------------------------------------------


def _line(p0, length_m, t0=0.0, v=0.6, dt=0.1, direction=(1.0, 0.0, 0.0)):
    """A straight plan from rest: accelerate at 0.6 m/s^2, cruise at ``v``, hold at the end."""
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    n = int(math.ceil((length_m / v + 2.0) / dt))
    p, vel, a = np.zeros((n + 1, 3)), np.zeros((n + 1, 3)), np.zeros((n, 3))
    s, sp = 0.0, 0.0
    for k in range(n):
        acc = min(0.6, (v - sp) / dt) if s < length_m - 0.3 else max(-0.6, -sp / dt)
        s, sp = s + sp * dt + 0.5 * acc * dt * dt, sp + acc * dt
        a[k], p[k + 1], vel[k + 1] = acc * u, s * u, sp * u
    return Trajectory(t0, dt, np.asarray(p0, float) + p, vel, np.zeros(n + 1), a, np.zeros(n))


def _fly(world, plan, seconds):
    world.set_trajectory(plan)
    truth, est, ref = [], [], []
    for _ in range(int(round(seconds / 0.1))):
        ws = world.step(0.1)
        truth.append(ws.state.p.copy())
        est.append(world.estimate.p.copy())
        ref.append(plan.sample(ws.state.t_s)[0])
        if ws.collision is not None:
            break
    return np.array(truth), np.array(est), np.array(ref)


def test_odometry_drift_grows_with_the_distance_flown_and_is_reproducible():
    model = OdometryModel(drift_fraction=0.01, noise_m=0.0, yaw_noise_rad=0.0)
    profile = RealismProfile("drift only", odometry=model)
    start = VehicleState(0.0, [2.0, 0.0, 1.5], np.zeros(3), 0.0)
    paths = []
    for seed in (3, 3, 4):
        w = World.from_scene("corridor", realism=profile, seed=seed, initial_state=start)
        truth, est, _ = _fly(w, _line(start.p, 20.0), 40.0)
        flown = np.linalg.norm(np.diff(np.vstack([start.p, truth]), axis=0), axis=1).sum()
        assert w.odometry.distance_m == pytest.approx(flown, rel=1e-3)  # it sums the 0.01 s substeps
        assert np.linalg.norm(est[-1] - truth[-1]) == pytest.approx(0.01 * w.odometry.distance_m)
        paths.append(truth)
    np.testing.assert_array_equal(paths[0], paths[1])
    assert not np.allclose(paths[0], paths[2])
    # white noise on every read, fixed within a control step
    d = OdometryDrift(OdometryModel(), 9, np.zeros(3))
    assert d.noise(5)[0].tolist() == d.noise(5)[0].tolist() and d.noise(5)[0].tolist() != d.noise(6)[0].tolist()


def _seed_with_drift_towards(direction_y_min: float) -> int:
    model = OdometryModel()
    for seed in range(200):
        if OdometryDrift(model, seed, np.zeros(3)).direction[1] > direction_y_min:
            return seed
    raise AssertionError("no seed found")


@pytest.mark.parametrize("plan_y, collides", [(-1.1, True), (1.95, False)])
def test_drift_moves_the_executed_path_and_collisions_use_the_truth(plan_y, collides):
    """The controller tracks the plan with the drifting estimate, so the true path is the plan
    minus the drift. A plan the estimate keeps clear hits the wall in truth (collision), and a
    plan the estimate puts inside the wall's margin stays clear in truth (no collision)."""
    seed = _seed_with_drift_towards(0.7)
    profile = RealismProfile("drift only", odometry=OdometryModel(drift_fraction=0.06, noise_m=0.0, yaw_noise_rad=0.0),
                             controller=ControllerModel())
    start = VehicleState(0.0, [2.0, 0.0, 1.5], np.zeros(3), 0.0)
    w = World.from_scene("corridor", realism=profile, seed=seed, initial_state=start)
    radius = w.vehicle.config.body_radius_m
    _fly(w, _line(start.p, 14.0), 30.0)  # builds up ~0.8 m of drift towards +y
    assert w.odometry.offset_m[1] > 0.45
    est0 = w.estimate.p
    truth, est, _ = _fly(w, _line(est0, 10.0, t0=w.state.t_s, direction=(1.0, plan_y / 10.0, 0.0)), 25.0)
    clear_est = w.collision.clearance(est) > radius
    if collides:
        assert w.collided is not None
        assert clear_est[-1]  # the pilot's estimate was clear where the truth hit
        assert w.collided.t_s <= w.state.t_s
    else:
        assert w.collided is None
        assert not clear_est.all()  # the estimate crossed the wall's margin, the truth never did
        assert np.all(w.collision.clearance(truth) > radius)


def test_wind_and_lag_move_the_executed_path_off_the_plan_reproducibly():
    start = VehicleState(0.0, [0.0, -20.0, 1.5], np.zeros(3), math.pi / 2)
    profile = RealismProfile("wind", controller=ControllerModel(), wind=REALISTIC.wind)
    runs = []
    for seed in (1, 1, 2):
        w = World.from_scene("park", realism=profile, seed=seed, initial_state=start)
        assert w.vehicle.gusts is not None
        truth, est, ref = _fly(w, _line(start.p, 8.0, direction=(0, 1, 0)), 20.0)
        np.testing.assert_array_equal(truth, est)  # no odometry model: the pilot reads the truth
        assert np.max(np.linalg.norm(truth - ref, axis=1)) > 0.1
        runs.append(truth)
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.allclose(runs[0], runs[2])
    ideal = World.from_scene("park", initial_state=start)
    truth, _, ref = _fly(ideal, _line(start.p, 8.0, direction=(0, 1, 0)), 20.0)
    assert np.max(np.linalg.norm(truth - ref, axis=1)) < 1e-6  # ideal tracking stays exact
    indoor = World.from_scene("corridor", realism=profile, seed=1)
    assert indoor.scene.indoor and indoor.vehicle.gusts is None  # no wind under a roof


def test_gusts_are_coloured_noise_with_the_dryden_variance():
    model = WindModel(sigma_xy_mps=1.5, sigma_z_mps=0.8, tau_xy_s=2.0, tau_z_s=0.3)
    g, g2 = GustProcess(model, 7), GustProcess(model, 7)
    W = np.array([g.step(0.01).copy() for _ in range(200_000)])
    W2 = np.array([g2.step(0.01).copy() for _ in range(10)])
    np.testing.assert_array_equal(W[:10], W2)
    assert np.std(W[:, 0]) == pytest.approx(1.5, rel=0.15) and np.std(W[:, 2]) == pytest.approx(0.8, rel=0.1)
    lag = int(2.0 / 0.01)  # correlation e^-1 after one time constant
    r = np.corrcoef(W[:-lag, 0], W[lag:, 0])[0, 1]
    assert r == pytest.approx(math.exp(-1), abs=0.1)


def test_controller_lag_is_first_order_with_the_attitude_time_constant():
    profile = RealismProfile("lag", controller=ControllerModel())
    w = World.from_scene("corridor", realism=profile, initial_state=VehicleState(0.0, [2.0, 0.0, 1.5], np.zeros(3), 0.0))
    w.set_trajectory(_line([2.0, 0.0, 1.5], 5.0))
    w.step(0.01)
    # first step: a_sp = a_ref (0.6) at zero error, reached through the lag
    assert w.state.a[0] == pytest.approx(0.6 * (1 - math.exp(-0.01 * 6.5)), rel=1e-6)


# -- frames -------------------------------------------------------------------------------------


def test_frames_arrive_late_keep_their_capture_pose_and_some_are_dropped():
    frames = FrameModel(drop_prob=0.2, latency_min_s=0.06, latency_max_s=0.133)
    profile = RealismProfile("frames", frames=frames)
    w = World.from_scene("corridor", realism=profile, seed=11, camera=default_camera().scaled(0.1))
    got, dropped, late = 0, 0, 0
    for k in range(100):
        t_cap = w.clock.now_s
        w.capture()
        assert w.receive() is None  # never at once
        w.step(0.1)
        obs = w.receive()
        if obs is None:
            obs2 = (w.step(0.1), w.receive())[1]
            if obs2 is not None:
                late += 1
                assert obs2.t_s == pytest.approx(t_cap)
            else:
                dropped += 1
        else:
            got += 1
            assert obs.t_s == pytest.approx(t_cap)
    assert dropped == w.frames_dropped and 10 <= dropped <= 32
    assert got > 0 and late > 0  # latency in [60, 133] ms straddles the 0.1 s step
    expected = [frames.draw(11, k) for k in range(100)]
    assert sum(d for d, _ in expected) == dropped


def test_ideal_frames_arrive_at_once_with_the_true_pose():
    w = World.from_scene("corridor")
    w.capture()
    obs = w.receive()
    assert obs is not None and obs.t_s == w.clock.now_s
    np.testing.assert_array_equal(obs.T_world_cam, w.T_world_cam())
    assert w.receive() is None
    assert w.estimate.p.tolist() == w.state.p.tolist()


# -- benchmark config ---------------------------------------------------------------------------


def _bench(world: dict):
    from onfly.bench.runner import BenchConfig

    return BenchConfig.from_dict({
        "bench": {"name": "t", "methods": ["oracle"], "runs": 1, "tasks": {"ids": ["corridor-p05"]}},
        "episode": {"time_limit_s": 1.0},
        "world": {"width_px": 64, "height_px": 43, **world},
    })


def test_the_config_key_selects_the_profile_and_unknown_names_name_the_key():
    from onfly.bench.runner import BenchConfigError

    with pytest.raises(BenchConfigError, match=r"\[world\] realism: unknown profile 'foggy'; valid: ideal, realistic, realistic_calm"):
        _bench({"realism": "foggy"})
    plain, ideal, real = _bench({}), _bench({"realism": "ideal"}), _bench({"realism": "realistic"})
    assert plain.world_settings()["realism"] == "ideal"
    # runs from before profiles keep their hash; the realistic profile is a different run
    assert plain.method_hash("oracle") == ideal.method_hash("oracle") != real.method_hash("oracle")


def test_each_episode_records_its_profile_and_flies_under_it(tmp_path):
    from onfly.bench.runner import run_bench

    recs = {}
    for name in ("ideal", "realistic"):
        res = run_bench(_bench({"realism": name}), tmp_path / name, workers=1)
        (rec,) = res.records
        assert rec["realism"] == name
        recs[name] = rec
    assert recs["ideal"]["metrics"] != recs["realistic"]["metrics"]  # lag, drift: another path


def test_the_invalid_depth_band_is_the_datasheets_width_down_the_left_edge():
    # Intel D400 datasheet, "Invalid Depth Band": B * F / Z pixels, on the left of the image
    d = DepthModel(subpixel=0.0, edge_jump_ratio=0.0)
    for width, fx in ((848, 424.0), (320, 160.0)):
        for z in (0.5, 1.0, 3.0):
            out = d.apply(np.full((4, width), z, np.float32), None, np.random.default_rng(0), fx_px=fx)
            band = fx * 0.05 / z
            read = out[0] > 0
            assert not read[: int(band)].any() and read[int(band) + 1:].all(), (width, z)
            assert (out[:, int(band) + 1:] == np.float32(z)).all()
    # without the image's focal length (or with the rule off) there is no band
    img = np.full((4, 320), 1.0, np.float32)
    assert (d.apply(img, None, np.random.default_rng(0)) > 0).all()
    off = DepthModel(subpixel=0.0, edge_jump_ratio=0.0, stereo_shadows=False)
    assert (off.apply(img, None, np.random.default_rng(0), fx_px=160.0) > 0).all()


def test_a_nearer_object_shadows_the_background_on_its_left_side_only():
    d = DepthModel(subpixel=0.0, edge_jump_ratio=0.0)
    fx, near, far = 160.0, 1.0, 4.0
    img = np.full((3, 320), far, np.float32)
    img[:, 150:170] = near  # a post 1 m away in front of a wall 4 m away
    out = d.apply(img, None, np.random.default_rng(0), fx_px=fx)
    assert (out[:, 150:170] == near).all()  # the post itself reads
    shadow = fx * 0.05 * (1 / near - 1 / far)  # 6 px of wall hidden from the right imager
    assert not (out[:, 150 - int(shadow):150] > 0).any()
    assert (out[:, 150 - int(shadow) - 2] == far).all()
    assert (out[:, 170:] == far).all()  # nothing is hidden on its right side
    band = fx * 0.05 / far
    assert (out[:, int(band) + 1:150 - int(shadow) - 1] == far).all()
    # sky (nothing hit) is at infinity: it hides nothing and reads nothing
    img[:, 200:] = 0.0
    out = d.apply(img, None, np.random.default_rng(0), fx_px=fx)
    assert (out[:, 170:200] == far).all() and not (out[:, 200:] > 0).any()


def test_a_rendered_realistic_frame_has_no_reading_down_its_left_edge():
    start = VehicleState(0.0, [-4.0, -24.0, 1.4], np.zeros(3), math.pi)
    real = World.from_scene("urban_block", realism="realistic", seed=5, initial_state=start)
    obs = real.observe()
    fx = float(real.camera.K[0, 0])
    exact = obs.annotation.depth_m
    rows = np.nonzero((exact[:, :4] > 0.3).all(axis=1) & (exact[:, :4] < 9.0).all(axis=1))[0]
    assert len(rows) > 10
    for r in rows[::5]:
        band = fx * 0.05 / float(exact[r, 0])
        assert not (obs.depth_m[r, : int(band)] > 0).any()
