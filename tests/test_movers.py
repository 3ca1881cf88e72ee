"""Moving obstacles from depth (planning.movers): detection, tracks, the capsule field, and
the planner keeping clear of a walker in closed loop."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.esdf import EsdfMap
from planning.frames import body_transform, cam_transform_from_body
from planning.movers import MoverConfig, MoverConfigError, MoverField, MoverTrack, MoverTracker
from street_scene import street

CAM = PinholeCamera.from_fov(320, 214, 90.0, 60.0)
CLUTTER = {
    "name": "crates", "label": "crate", "instance_id": 3, "color": "#8D6E63", "target": False,
    "parts": [{"type": "box", "center_m": [7, 2.5, 0.5], "size_m": [1, 1, 1]},
              {"type": "box", "center_m": [10, -2, 0.75], "size_m": [0.6, 2, 1.5]},
              {"type": "cylinder", "base_m": [12, 1, 0], "radius_m": 0.3, "height_m": 3.0, "segments": 12}],
}  # fmt: skip


def crossing(x_m: float, speed_mps: float, start_s: float = 0.0, loop: bool = False) -> dict:
    wps = [[x_m, -4.0, 0.0], [x_m, 4.0, 0.0]]
    if loop:
        wps += [[x_m + 0.6, 4.0, 0.0], [x_m + 0.6, -4.0, 0.0]]
    return {"type": "path", "loop": loop, "start_s": start_s, "waypoints": [{"position_m": p, "speed_mps": speed_mps} for p in wps]}


def feed(world: World, positions, times, tracker: MoverTracker, esdf: EsdfMap):
    """Render at each (position, time) looking down +x and feed tracker then map; the active
    tracks after each frame."""
    out = []
    for k, (p, t) in enumerate(zip(positions, times)):
        T = cam_transform_from_body(body_transform(np.asarray(p, float), 0.0))
        depth = world.renderer.render(T, noise_key=k, t_s=t).depth_m
        out.append(tracker.observe(t, depth, CAM, T, esdf))
        esdf.integrate(depth, CAM, T, center_world=np.asarray(p, float))
    return out


def test_a_walker_crossing_is_tracked_with_its_velocity():
    world = World(street(crossing(8.0, 0.9)), camera=CAM)
    tracker, esdf = MoverTracker(), EsdfMap()
    times = 0.5 * np.arange(1, 13)
    active = feed(world, [[3.0, 0.0, 1.5]] * len(times), times, tracker, esdf)
    assert active[-1], "no track after 6 s of a person crossing 5 m ahead"
    assert len(active[-1]) == 1
    tr = active[-1][0]
    truth = world.actor_pose(9, float(times[-1]))
    assert np.allclose(tr.velocity_mps, truth.velocity_mps[:2], atol=0.1)
    # the readings are the walker's near side: the centre sits within its radius of the truth
    assert np.hypot(*(tr.position_m - truth.position_m[:2])) <= 0.3
    assert tr.z_range_m[0] < 0.3 and tr.z_range_m[1] > 1.4
    # confirmed on the second sighting: active from the third frame on at the latest
    assert all(a for a in active[2:])


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_static_clutter_seen_from_a_moving_camera_makes_no_mover(realism):
    world = World(street(None, extra=(CLUTTER,)), camera=CAM, realism=realism, seed=3)
    tracker, esdf = MoverTracker(), EsdfMap()
    times = 0.5 * np.arange(40)
    xs = np.linspace(0.0, 12.0, len(times))  # 0.6 m/s down the street, past the clutter
    positions = [[x, 0.3 * np.sin(x), 1.5] for x in xs]
    active = feed(world, positions, times, tracker, esdf)
    assert not any(active)


@pytest.mark.parametrize("realism", ["ideal", "realistic"])
def test_a_wall_swept_by_a_camera_turning_beside_it_makes_no_mover(realism):
    """A vehicle 1 m from a wall turning in place at the paper's 0.4 rad/s (a search's scan in
    a corridor): each frame shows 0.4 m more of the wall, in voxels that rays grazing along it
    carved free, so the young rule takes every new stretch for something that moved there. Its
    first place is still there: the track is static, never predicted."""
    world = World(street(None), camera=CAM, realism=realism, seed=5)
    tracker, esdf = MoverTracker(), EsdfMap()
    p = np.array([5.0, 4.1, 1.5])  # the wall's face is at y = 5.1
    out = []
    for k in range(32):  # 0.2 rad per 0.5 s frame: a full turn and a half
        t, yaw = 0.5 * k, np.pi + 0.2 * k
        T = cam_transform_from_body(body_transform(p, yaw))
        depth = world.renderer.render(T, noise_key=k, t_s=t).depth_m
        out.append(tracker.observe(t, depth, CAM, T, esdf))
        esdf.integrate(depth, CAM, T, center_world=p)
    assert not any(out), [(k, a) for k, a in enumerate(out) if a]
    assert tracker.summary()["tracks"] > 0  # the sweep did make tracks: the rule is what kept them static


def test_a_walker_who_stops_is_left_to_the_map():
    # walks 8 m across from t = 0 at 1 m/s, then stands at y = 4
    world = World(street(crossing(8.0, 1.0)), camera=CAM)
    tracker, esdf = MoverTracker(), EsdfMap()
    times = 0.5 * np.arange(1, 31)
    active = feed(world, [[3.0, 0.0, 1.5]] * len(times), times, tracker, esdf)
    assert any(active[:16])
    assert not any(active[-4:])


def _capsule_reference(P, a, b, r, z0, z1, n=4001):
    """Brute force: distance to the core (the segment a-b times [z0, z1]) by dense sampling."""
    s = np.linspace(0.0, 1.0, n)
    core = a[None] + s[:, None] * (b - a)[None]
    dh = np.min(np.hypot(P[:, None, 0] - core[None, :, 0], P[:, None, 1] - core[None, :, 1]), axis=1)
    dz = np.maximum(np.maximum(z0 - P[:, 2], P[:, 2] - z1), 0.0)
    return np.hypot(dh, dz) - r


class _Far:
    def query(self, points):
        P = np.asarray(points, float)
        return np.full(len(P), 10.0), np.zeros((len(P), 3))


def test_capsule_distance_and_gradient_match_references():
    tr = MoverTrack(0, np.array([2.0, 1.0]), np.array([1.0, -0.5]), 0.3, (0.0, 1.8), t_s=1.0, hits=3)
    f = MoverField(_Far(), [tr], t_s=2.0, horizon_s=1.5)
    a = tr.predicted(2.0)
    assert np.allclose(a, [3.0, 0.5])
    b = a + 1.5 * tr.velocity_mps
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(0, 7, 400), rng.uniform(-3, 3, 400), rng.uniform(-1, 3.5, 400)])
    d, g = f.capsule_distance(P)
    ref = _capsule_reference(P, a, b, 0.3, 0.0, 1.8)
    assert np.max(np.abs(d - ref)) < 2e-3
    # gradient: central differences where the field is smooth (off the core)
    h = 1e-5
    off = d > -0.25
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        num = (f.capsule_distance(P + e)[0] - f.capsule_distance(P - e)[0]) / (2 * h)
        assert np.allclose(g[off, k], num[off], atol=1e-4)
    # the combined field takes the nearer obstacle, value and gradient
    dq, gq = f.query(P)
    near = d < 10.0
    assert np.allclose(dq[near], d[near]) and np.allclose(gq[near], g[near])
    assert np.allclose(dq[~near], 10.0)


def test_a_track_the_camera_sees_through_is_dropped():
    world = World(street(crossing(8.0, 0.9)), camera=CAM)
    tracker, esdf = MoverTracker(), EsdfMap()
    feed(world, [[3.0, 0.0, 1.5]] * 6, 0.5 * np.arange(1, 7), tracker, esdf)
    assert tracker.active(3.0)
    # the same street without the walker: the predicted position is seen empty
    empty = World(street(None), camera=CAM)
    T = cam_transform_from_body(body_transform(np.array([3.0, 0.0, 1.5]), 0.0))
    tracker.observe(3.5, empty.renderer.render(T, t_s=3.5).depth_m, CAM, T, esdf)
    assert tracker.tracks == []


def test_tracks_expire_after_keep_s_and_disabled_tracks_nothing():
    world = World(street(crossing(8.0, 0.9)), camera=CAM)
    tracker, esdf = MoverTracker(MoverConfig(keep_s=1.0)), EsdfMap()
    feed(world, [[3.0, 0.0, 1.5]] * 6, 0.5 * np.arange(1, 7), tracker, esdf)
    assert tracker.active(3.0) and not tracker.active(4.1)
    assert tracker.field(esdf, 4.1) is esdf
    off = MoverTracker(MoverConfig(enabled=False))
    assert not any(feed(world, [[3.0, 0.0, 1.5]] * 6, 0.5 * np.arange(1, 7), off, EsdfMap()))
    assert off.field(esdf, 3.0) is esdf


@pytest.mark.parametrize(
    "kw",
    [{"cell_m": 0.0}, {"keep_s": -1.0}, {"min_points": 0}, {"free_logodds_max": 0.1}, {"alpha": 1.5},
     {"radius_min_m": 0.5, "radius_max_m": 0.4}, {"stride_px": 0}, {"horizon_s": float("nan")}],
)  # fmt: skip
def test_bad_mover_config_is_refused(kw):
    with pytest.raises(MoverConfigError):
        MoverConfig(**kw)


def _fly_street(motion: dict, movers: dict):
    from onfly.bench.episode import EpisodeConfig, run_episode
    from onfly.bench.method import PrivilegedGoal
    from onfly.bench.metrics import GoalRegion
    from onfly.bench.oracle import make_oracle

    world = World(street(motion), camera=CAM)
    goal = np.array([16.0, 0.0, 1.5])
    return run_episode(
        world, make_oracle("sim:nominal", 0, movers=movers), instruction="fly to the end of the street",
        goal=GoalRegion(goal, np.full(3, 0.5)), reference_path_m=16.0, seed=0, error_model="none",
        privileged=PrivilegedGoal(goal, np.full(3, 0.5), np.array([[0.0, 0.0, 1.5], goal])),
        config=EpisodeConfig(frame_period_s=0.5),
    )  # fmt: skip


def test_a_person_pacing_across_the_path_is_avoided_only_with_the_prediction():
    # paces back and forth across the street 8 m ahead at 0.9 m/s: the map alone (its trail
    # cleared, the lane entered, the person back) is walked into; the tracked prediction keeps
    # the vehicle out of the lane until the person has passed
    pacing = crossing(8.0, 0.9, loop=True)
    with_prediction = _fly_street(pacing, {})
    assert not with_prediction.metrics.collided and with_prediction.metrics.success
    assert with_prediction.method_summary["movers"]["active_frames"] > 0
    map_alone = _fly_street(pacing, {"enabled": False})
    assert map_alone.metrics.collided


def _pilot_in_street(config):
    """OnFly's pilot with a scripted VLM pointing straight ahead, a walker pacing across the
    street 7 m ahead at head height; (method, result, heights)."""
    from onfly.bench.episode import EpisodeConfig, run_episode
    from onfly.bench.metrics import GoalRegion
    from onfly.bench.onfly_method import OnFlyMethod
    from onfly.pilot import OnFlyPilot
    from planning.planner import Planner
    from vlm_fakes import ScriptedVlm, text

    class Scripted(OnFlyMethod):
        def reset(self, spec):
            backend = ScriptedVlm(
                "perfect", decision=lambda i, r: text('{"point_2d": [160, 107]}', 0.81), monitor=lambda i, r: text("CONTINUE", 1.15)
            )
            self.pilot = OnFlyPilot(self.config, backend, spec.runtime, planner=Planner(self.config.planner))
            self.pilot.begin(spec.instruction, spec.start_state.t_s)

    method = Scripted("sim:perfect", config)
    world = World(street(crossing(7.0, 0.9, loop=True)), camera=CAM)
    heights = []
    result = run_episode(
        world, method, instruction="Fly down the street.", goal=GoalRegion([19.0, 0.0, 1.5], [1.0, 4.0, 1.5]),
        reference_path_m=19.0, seed=0, error_model="test", config=EpisodeConfig(time_limit_s=25.0, frame_period_s=0.5),
        observer=lambda s: heights.append((s.t_s, float(s.state.p[2]))),
    )  # fmt: skip
    return method, result, heights


def test_the_pilot_climbs_above_people_it_has_tracked():
    from onfly.pilot import PilotConfig

    # the scripted goal stays ~7 m ahead; the release near a target is tested on its own below
    method, result, heights = _pilot_in_street(PilotConfig(above_movers_release_m=0.0))
    events = [e for e in method.pilot.events if e.kind == "over_movers"]
    assert events, "the walker was never tracked"
    z_min = events[0].data["z_min_m"]
    # over the walker's head (1.73 m; the readings of a 2-px stride reach within 0.15 m of it)
    # by the planner's safety distance and the margin
    assert z_min >= 1.73 - 0.15 + 0.45 + 0.3
    assert not result.metrics.collided
    # it climbs on the way (the straight line to goals ~7 m ahead): over the walker's head by
    # more than its body radius by the end, and never back down
    after = [z for t, z in heights if t >= events[0].t_s + 8.0]
    assert min(after[-30:]) >= 1.73 + 0.25 + 0.15
    assert min(after) >= max(z for t, z in heights if t <= events[0].t_s) + 0.2
    # off: the vehicle stays at the height of its goals, level with the walker's head
    _, off, level = _pilot_in_street(PilotConfig(above_movers_s=None))
    assert max(z for _, z in level) < 1.8


def test_goals_are_raised_over_recent_movers_but_not_near_the_target():
    from onfly.pilot import OnFlyPilot, PilotConfig, PilotConfigError
    from onfly.runtime import ClockRuntime
    from planning.trajectory import VehicleState
    from vlm_fakes import ScriptedVlm

    cfg = PilotConfig()
    pilot = OnFlyPilot(cfg, ScriptedVlm("perfect"), ClockRuntime())
    state = VehicleState(10.0, np.array([0.0, 0.0, 1.5]), np.zeros(3), 0.0)
    goal = np.array([8.0, 0.0, 1.2])
    assert pilot._above_movers(10.0, goal, state) is goal  # no mover tracked yet
    pilot._movers_seen_s, pilot._movers_top_m = 5.0, 1.7
    raised = pilot._above_movers(10.0, goal, state)
    z = 1.7 + cfg.planner.d_safe_m + cfg.above_movers_margin_m
    assert raised[2] == pytest.approx(z) and goal[2] == 1.2  # a new array
    # 0.95 m under that height the goal is drawn in along its bearing: climb first
    reach = (z - 1.5) / np.tan(np.radians(cfg.above_movers_climb_deg))
    np.testing.assert_allclose(raised[:2], [reach, 0.0], atol=1e-9)
    assert [e.kind for e in pilot.events] == ["over_movers"]
    # at that height (within 0.1 m) it is not drawn in
    level = VehicleState(10.0, np.array([0.0, 0.0, z - 0.05]), np.zeros(3), 0.0)
    assert np.array_equal(pilot._above_movers(10.0, goal, level)[:2], goal[:2])
    # nor nearer than 1 m: a goal straight above is a hover
    close = VehicleState(10.0, np.array([0.0, 0.0, z - 0.2]), np.zeros(3), 0.0)
    np.testing.assert_allclose(pilot._above_movers(10.0, goal, close)[:2], [1.0, 0.0], atol=1e-9)
    # the last metres to the target the vehicle was sent to keep its height
    pilot.goal_world = np.array([3.0, 1.0, 1.0])
    assert pilot._above_movers(10.0, goal, state) is goal
    pilot.goal_world = np.array([6.0, 0.0, 1.0])
    assert pilot._above_movers(10.0, goal, state)[2] > 2.0
    # above_movers_s after the last mover the rule ends
    assert pilot._above_movers(5.0 + cfg.above_movers_s + 0.1, goal, state) is goal
    assert pilot.events[-1].kind == "over_movers_end"
    for bad in (
        {"above_movers_s": -1.0}, {"above_movers_margin_m": float("nan")}, {"above_movers_release_m": -0.5},
        {"above_movers_climb_deg": 0.0}, {"above_movers_climb_deg": 90.0}, {"above_movers_climb_deg": float("nan")},
    ):  # fmt: skip
        with pytest.raises(PilotConfigError):
            PilotConfig(**bad)


@pytest.mark.parametrize("speed_mps", [0.45, 0.6])
def test_a_slow_walker_near_the_camera_is_tracked_though_the_map_holds_where_it_just_was(speed_mps):
    """At 2 Hz a walker at 0.45 m/s moves 0.23 m between frames: less than ``clear_m`` from
    the occupancy the map gave its last position. Within ``young_max_range_m`` those readings
    are taken for what they are (the tables of record's duplex-l02, run 1: a man at 0.45 m/s,
    seen once, walked into)."""
    world = World(street(crossing(5.5, speed_mps)), camera=CAM)
    tracker, esdf = MoverTracker(), EsdfMap()
    times = 0.5 * np.arange(1, 17)
    active = feed(world, [[3.0, 0.0, 1.5]] * len(times), times, tracker, esdf)
    first = next(k for k, a in enumerate(active) if a)
    assert all(active[first:]), [len(a) for a in active]
    truth_first = world.actor_pose(9, float(times[first])).position_m
    assert abs(truth_first[1]) <= 2.5  # tracked as soon as it is well inside the view
    tr = active[-1][0]
    truth = world.actor_pose(9, float(times[-1]))
    assert np.allclose(tr.velocity_mps, truth.velocity_mps[:2], atol=0.1)
    assert np.hypot(*(tr.position_m - truth.position_m[:2])) <= 0.3
    # before: the map's trace of the walker hid every reading after the first
    old = MoverTracker(MoverConfig(young_max_range_m=0.0))
    assert not any(feed(World(street(crossing(5.5, speed_mps)), camera=CAM), [[3.0, 0.0, 1.5]] * len(times), times, old, EsdfMap()))
