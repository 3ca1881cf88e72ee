"""The pilot's search (onfly.search): scan, exploration choice, dead ends, hand-back, volume.

Unit tests pin the bookkeeping and the exploration choice on exact geometry; closed-loop tests
fly the pilot in the embedded world with a scripted model that answers only when the target is
in the frame, as a real model that can say "not visible" would.
"""

import json
import math

import numpy as np
import pytest

from onfly.bench.episode import EpisodeConfig, run_episode
from onfly.bench.metrics import GoalRegion
from onfly.bench.onfly_method import OnFlyMethod, ablation_config
from onfly.pilot import OnFlyPilot, PilotConfig, PilotMode
from onfly.runtime import ClockRuntime
from onfly.search import (
    Search,
    SearchConfig,
    SearchConfigError,
    SearchPhase,
    SearchTrigger,
    best_look_target,
    explore_target,
    leg_end_held,
    look_target,
    open_heading,
    open_ray_target,
    opening_gain,
    seen_obstacle_in_column,
    side_opening,
    side_to_look,
)
from onfly.world.scene import parse_scene
from onfly.world.world import World
from planning.analytic_field import AnalyticField, Box, HalfSpace
from planning.camera import PinholeCamera
from planning.frames import wrap_angle
from planning.planner import Planner
from planning.trajectory import VehicleState
from planning.volume import FlightVolume
from vlm.prompts import DecisionPrompt, DecomposePrompt, parse_prompt
from vlm_fakes import ScriptedVlm, text

CAM = PinholeCamera.from_fov(160, 107, 90.0, 60.0)
NOT_VISIBLE = "I cannot see it in this image."  # unparseable today; "not visible" once parsed


# -- bookkeeping ------------------------------------------------------------------------------
def test_config_rejects_bad_values():
    with pytest.raises(SearchConfigError, match="fail_streak"):
        SearchConfig(fail_streak=0)
    with pytest.raises(SearchConfigError, match="explore_ranges_m"):
        SearchConfig(explore_ranges_m=(2.0, -1.0))
    with pytest.raises(SearchConfigError, match="scan_step_rad"):
        SearchConfig(scan_step_rad=float("nan"))


def test_scan_turns_the_rest_of_the_circle_in_steps_with_a_dwell_then_reports_done():
    cfg = SearchConfig(scan_dwell_s=1.0)
    s = Search(cfg)
    p = np.array([1.0, 2.0, 1.5])
    s.start(0.0, p, 0.3, SearchTrigger.NOT_VISIBLE)
    assert s.phase is SearchPhase.SCAN
    yaw, t, seen = 0.3, 0.0, []
    for _ in range(400):
        point, yaw_ref, ev = s.control(t, p, yaw)
        np.testing.assert_allclose(point, p)  # turning in place
        if ev == "scan_done":
            break
        seen.append(yaw_ref)
        yaw = yaw_ref  # an ideal turn: the heading is reached at once
        t += 0.1
    else:
        pytest.fail("scan never finished")
    headings = sorted({round(float(wrap_angle(y - 0.3)), 6) for y in seen})
    # three quarter turns: the start heading was the view that failed
    np.testing.assert_allclose(sorted(abs(h) for h in headings), [math.pi / 2, math.pi / 2, math.pi], atol=1e-6)
    # each heading held for the dwell before moving on
    assert t >= 3 * cfg.scan_dwell_s


def test_scan_goes_first_toward_the_last_sighting_and_alternates_without_one():
    s = Search(SearchConfig())
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.LOST, toward_yaw=-2.0)
    _, first, _ = s.control(0.0, np.zeros(3), 0.0)
    assert first == pytest.approx(-2.0)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NO_GOAL)
    _, a, _ = s.control(0.0, np.zeros(3), 0.0)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NO_GOAL)
    _, b, _ = s.control(0.0, np.zeros(3), 0.0)
    assert np.sign(a) == -np.sign(b)


def test_stall_needs_the_whole_window_and_little_travel():
    s = Search(SearchConfig(stall_window_s=5.0, stall_distance_m=0.5))
    for k in range(40):  # 4 s hovering
        s.remember(k * 0.1, np.array([0.0, 0.01 * (k % 2), 1.0]))
    assert not s.stalled(3.9)  # the window is not covered yet
    for k in range(40, 80):
        s.remember(k * 0.1, np.array([0.0, 0.0, 1.0]))
    assert s.stalled(7.9)
    s.reset_stall()
    assert not s.stalled(7.9)
    moving = Search(SearchConfig(stall_window_s=5.0, stall_distance_m=0.5))
    for k in range(80):
        moving.remember(k * 0.1, np.array([0.1 * k, 0.0, 1.0]))
    assert not moving.stalled(7.9)


def test_exploration_arrival_and_timeout_end_the_leg():
    s = Search(SearchConfig(explore_arrive_m=0.5, explore_timeout_s=3.0, weave_rad=0.0))
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.STALL)
    s.explore_from(0.0, np.array([4.0, 0.0, 1.0]), np.zeros(3), 0.0)
    point, yaw_ref, ev = s.control(1.0, np.array([1.0, 0.0, 1.0]), 0.0)
    assert ev is None and yaw_ref is None and point.tolist() == [4.0, 0.0, 1.0]
    assert s.control(1.5, np.array([3.7, 0.1, 1.0]), 0.0)[2] == "explore_done"
    assert s.control(3.5, np.array([1.0, 0.0, 1.0]), 0.0)[2] == "explore_done"


def test_a_reaim_lengthens_or_bends_a_leg_but_never_turns_it_round():
    """A fresher look point moves the leg's end within twice the look cone of the leg's first
    bearing (from where the leg began); one further round is refused and the leg keeps its end.
    Chained re-aims cannot walk the bearing round either: the bound is on the first bearing."""
    cfg = SearchConfig(look_cone_rad=math.radians(20.0), explore_timeout_s=10.0)
    s = Search(cfg)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE)
    s.explore_from(0.0, np.array([4.0, 0.0, 1.5]), np.zeros(3), 0.0, kind="look")  # bearing 0
    here = np.array([1.0, 0.0, 1.5])
    ahead = np.array([8.0, 0.0, 1.5])
    assert s.reaim(5.0, ahead)  # further the same way: taken, and its timeout counts from now
    assert s.control(14.0, here, 0.0)[0].tolist() == ahead.tolist()
    bent = np.array([6.0 * math.cos(0.6), 6.0 * math.sin(0.6), 1.5])  # 34 deg off: inside 40 deg
    assert s.reaim(6.0, bent)
    for deg in (45.0, 90.0, 180.0):  # past twice the cone, measured from the first bearing
        a = math.radians(deg)
        assert not s.reaim(7.0, np.array([6.0 * math.cos(a), 6.0 * math.sin(a), 1.5]))
    assert s.control(7.5, here, 0.0)[0].tolist() == bent.tolist()
    # the refused re-aims did not restart the leg's timeout (still counted from t = 6)
    assert s.control(16.5, here, 0.0)[2] == "explore_done"


def test_the_weave_swings_the_camera_about_the_leg_bearing_within_the_yaw_rate():
    cfg = SearchConfig(weave_rad=0.6, weave_period_s=8.0, explore_timeout_s=100.0)
    s = Search(cfg)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.STALL)
    s.explore_from(0.0, np.array([0.0, 10.0, 1.0]), np.zeros(3), 0.0)  # bearing +90 deg
    here = np.array([0.0, 0.0, 1.0])
    yaws = np.array([s.control(t, here, 0.0)[1] for t in np.arange(0.0, 8.0, 0.1)])
    off = yaws - np.pi / 2
    # a triangle wave: 0 at the start, +A at a quarter period, -A at three quarters
    assert off[0] == pytest.approx(0.0, abs=1e-9)
    assert off[20] == pytest.approx(0.6) and off[60] == pytest.approx(-0.6)
    assert np.max(np.abs(off)) <= 0.6 + 1e-9
    # constant turn rate 4 A / T = 0.3 rad/s, inside the paper's 0.4 rad/s
    assert np.max(np.abs(np.diff(off))) / 0.1 == pytest.approx(0.3, abs=1e-6)
    # the last 1.5 m of a leg face the way of travel (what the vehicle arrives at)
    assert s.control(3.0, np.array([0.0, 9.0, 1.0]), 0.0)[1] is None


def test_a_scan_skips_headings_the_camera_has_already_seen():
    s = Search(SearchConfig())
    # the sector at +90 deg is already known: not worth turning to
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE, worth_scanning=lambda y: abs(wrap_angle(y - np.pi / 2)) > 0.1)
    # three quarter turns from yaw 0 would be +90, 180, -90 deg
    assert [abs(round(float(np.rad2deg(y)))) for y in s._scan_yaws] == [180, 90]
    assert s._scan_yaws[1] < 0
    # the heading toward the last sighting is always turned to, however well known
    t = Search(SearchConfig())
    t.start(0.0, np.zeros(3), 0.0, SearchTrigger.LOST, toward_yaw=1.0, worth_scanning=lambda y: False)
    assert t._scan_yaws == [1.0]
    # nothing worth turning to: the scan is over at once
    u = Search(SearchConfig())
    u.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE, worth_scanning=lambda y: False)
    assert u.control(0.0, np.zeros(3), 0.0)[2] == "scan_done"


# -- the exploration choice on exact geometry -------------------------------------------------
class KnownField:
    """An analytic field that knows only a box of space (what a camera has seen)."""

    def __init__(self, field, lo, hi):
        self.field, self.lo, self.hi = field, np.asarray(lo, float), np.asarray(hi, float)

    def query(self, points):
        return self.field.query(points)

    def known(self, points):
        P = np.atleast_2d(points)
        return np.all((P >= self.lo) & (P <= self.hi), axis=1)


def pocket_field():
    """A dead-end pocket open toward -x: walls at y = +-1.2 (x in [0, 4]) and x = 4."""
    boxes = [
        Box(center=[2.0, 1.3, 1.5], half_extents=[2.0, 0.1, 1.5]),
        Box(center=[2.0, -1.3, 1.5], half_extents=[2.0, 0.1, 1.5]),
        Box(center=[4.1, 0.0, 1.5], half_extents=[0.1, 1.4, 1.5]),
    ]
    return AnalyticField(boxes=boxes, half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])


def corridor_field():
    """A corridor along +x: walls at y = +-1.0, from x = -1 to 20, over a floor."""
    boxes = [
        Box(center=[9.5, 1.1, 1.5], half_extents=[10.5, 0.1, 1.5]),
        Box(center=[9.5, -1.1, 1.5], half_extents=[10.5, 0.1, 1.5]),
    ]
    return AnalyticField(boxes=boxes, half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])


def test_from_a_dead_end_the_only_reachable_way_out_is_chosen():
    f = KnownField(pocket_field(), [-1.0, -1.2, 0.0], [4.0, 1.2, 3.0])  # seen: the pocket
    target = explore_target(
        np.array([3.0, 0.0, 1.5]), 0.0, f, config=SearchConfig(), volume=None, volume_margin_m=0.45,
        visited=np.zeros((0, 3)), z_m=1.5,
    )
    assert target is not None
    assert target[0] < 2.0  # back out through the open side
    # the straight segment to it keeps the clearance
    seg = np.linspace([3.0, 0.0, 1.5], target, 50)
    assert f.field.distance(seg).min() >= SearchConfig().explore_clearance_m


def test_the_open_ray_leg_goes_down_the_longest_line_of_sight_and_stops_short_of_its_end():
    # the vehicle at the corridor's mouth; the camera has seen it to x = 9 and a little beyond
    corridor = corridor_field()
    f = KnownField(corridor, [-1.0, -1.0, 0.0], [9.0, 1.0, 3.0])
    cfg = SearchConfig(open_ray_max_m=6.0)
    p = np.array([0.0, 0.0, 1.5])
    # heading kept: the reverse (-x): a short run (1 m of seen space behind): still down the corridor
    target = open_ray_target(p, math.pi, f, config=cfg, volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    assert target is not None
    assert target[0] == pytest.approx(6.0) and abs(target[1]) < 1e-9  # capped at open_ray_max_m, on the axis
    # a shorter cap: still along the corridor; a seen end at x = 4: 0.5 m short of the run's end
    f_short = KnownField(corridor, [-1.0, -1.0, 0.0], [4.0, 1.0, 3.0])
    t2 = open_ray_target(p, 0.0, f_short, config=cfg, volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    assert t2 is not None and 3.0 <= t2[0] <= 3.75 + 1e-9 and abs(t2[1]) < 1e-9
    # the straight segment keeps the clearance, and the volume is respected
    seg = np.linspace(p, target, 60)
    assert corridor.distance(seg).min() >= cfg.explore_clearance_m
    vol = FlightVolume(np.array([-5.0, -5.0, 0.0]), np.array([3.0, 5.0, 5.0]))
    t3 = open_ray_target(p, 0.0, f, config=cfg, volume=vol, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    assert t3 is None or bool(vol.contains(t3, margin_m=0.45)[0])
    # nothing runs min_leg_m: no leg
    f_tiny = KnownField(corridor, [-0.5, -1.0, 0.0], [1.0, 1.0, 3.0])
    assert open_ray_target(p, 0.0, f_tiny, config=cfg, volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5) is None


def test_the_look_leg_is_the_longest_free_run_near_the_heading_the_model_looked():
    corridor = corridor_field()  # seen to x = 9
    f = KnownField(corridor, [-1.0, -1.0, 0.0], [9.0, 1.0, 3.0])
    cfg = SearchConfig(open_ray_max_m=6.0)
    p = np.array([0.0, 0.0, 1.5])
    none = np.zeros((0, 3))
    common = dict(config=cfg, volume=None, volume_margin_m=0.45, z_m=1.5)
    # the model looked 15 deg off the corridor's axis (a noisy point): the leg goes down the
    # corridor (the longest free run in the cone, capped at open_ray_max_m), not at the wall
    # 15 deg off, where the run ends after 2 m
    t = look_target(p, math.radians(15.0), f, visited=none, **common)
    assert t is not None and np.linalg.norm(t - p) == pytest.approx(6.0) and abs(t[1]) <= 0.55
    assert corridor.distance(np.linspace(p, t, 60)).min() >= cfg.look_clearance_m
    # the model looked at a wall: no run in the cone reaches look_min_leg_m, no leg
    assert look_target(p, math.radians(90.0), f, visited=none, **common) is None
    # outside the cone the axis is not considered: 60 deg off with a 20 deg cone finds nothing
    assert look_target(p, math.radians(60.0), f, visited=none, **common) is None
    # the leg's end is where the vehicle has been: the model looks back the way it came, no leg
    been = np.array([[5.5, 0.0, 1.5], [6.0, 0.0, 1.5], [6.5, 0.0, 1.5]])
    assert look_target(p, 0.0, f, visited=been, **common) is None
    # the volume shortens the leg (its face keeps the margin) and it stays inside
    vol = FlightVolume(np.array([-5.0, -5.0, 0.0]), np.array([4.0, 5.0, 5.0]))
    t_vol = look_target(p, 0.0, f, visited=none, **{**common, "volume": vol})
    assert t_vol is not None and bool(vol.contains(t_vol, margin_m=0.45)[0]) and 2.5 <= t_vol[0] <= 3.55


def test_after_a_scan_the_leg_is_the_longest_look_weighted_by_the_way_kept():
    """Walls 1.6 m ahead (+x), 2.6 m to the left (+y) and 4.6 m to the right (-y); open 6 m
    behind. The model looked one way from each heading of a scan: with no way to keep the leg is
    the longest (behind); keeping +x, the right (4 m at 0.6 of its length) beats behind (6 m at a
    fifth); a look into a wall gives no leg, and no looks give none."""
    boxes = [Box(center=[2.1, 0.0, 1.5], half_extents=[0.1, 9.0, 1.5]), Box(center=[0.0, 3.1, 1.5], half_extents=[9.0, 0.1, 1.5]),
             Box(center=[0.0, -5.1, 1.5], half_extents=[9.0, 0.1, 1.5])]
    field = AnalyticField(boxes=boxes, half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])
    cfg = SearchConfig(open_ray_max_m=6.0, look_cone_rad=0.0)
    p = np.array([0.0, 0.0, 1.5])
    common = dict(config=cfg, volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    looks = [0.0, math.pi / 2, math.pi, -math.pi / 2]
    free = {y: look_target(p, y, field, **common) for y in looks}
    assert free[0.0] is None  # 1.6 m to the wall: no run reaches look_min_leg_m past the clearance
    run = {y: float(np.linalg.norm(t[:2])) for y, t in free.items() if t is not None}
    assert run[math.pi] == pytest.approx(6.0) and run[-math.pi / 2] > run[math.pi / 2]
    best = best_look_target(p, looks, field, keep_yaw=None, **common)
    assert best is not None and best[0] == pytest.approx(-6.0) and abs(best[1]) < 1e-9
    kept = best_look_target(p, looks, field, keep_yaw=0.0, **common)
    assert kept is not None and kept[1] == pytest.approx(-run[-math.pi / 2]) and abs(kept[0]) < 1e-9
    assert best_look_target(p, [0.0], field, keep_yaw=0.0, **common) is None
    assert best_look_target(p, [], field, keep_yaw=None, **common) is None


def test_exploration_prefers_unknown_space_and_never_leaves_the_volume():
    free = AnalyticField(half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])
    # everything around is known except the +y side; the volume ends at x = 1
    f = KnownField(free, [-50, -50, -1], [50, 1.0, 10])
    vol = FlightVolume(np.array([-20.0, -20.0, 0.0]), np.array([1.0, 20.0, 5.0]))
    target = explore_target(
        np.zeros(3) + [0, 0, 1.5], 0.0, f, config=SearchConfig(), volume=vol, volume_margin_m=0.45,
        visited=np.zeros((0, 3)), z_m=1.5,
    )
    assert target is not None and bool(vol.contains(target, margin_m=0.45)[0])
    assert target[1] > 0.5  # toward the unknown side (the last known cells before it)


def test_with_no_heading_to_keep_every_direction_is_judged_by_its_unknown_space_alone():
    free = AnalyticField(half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])
    f = KnownField(free, [-4.0, -50, -1], [50, 50, 10])  # unknown only behind (x < -4)
    p = np.array([0.0, 0.0, 1.5])
    common = dict(config=SearchConfig(forward_weight=1.0), volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    def bearing_deg(t):
        return abs(float(np.rad2deg(np.arctan2(t[1], t[0]))))

    # keeping heading 0 (+x) with full forward weight: straight behind is worth nothing
    assert bearing_deg(explore_target(p, 0.0, f, **common)) < 150.0
    # no heading to keep (a search from a hover): straight into the unknown side
    assert bearing_deg(explore_target(p, None, f, **common)) > 170.0


def test_visited_places_are_avoided():
    free = AnalyticField(half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])
    f = KnownField(free, [-50, -50, -1], [50, 50, 10])  # nothing unknown: only memory decides
    p = np.array([0.0, 0.0, 1.5])
    visited = np.array(
        [[r * np.cos(a), r * np.sin(a), 1.5] for a in np.linspace(-2.5, 2.5, 40) for r in np.arange(1.0, 6.5, 0.5)]
    )
    target = explore_target(p, 0.0, f, config=SearchConfig(), volume=None, volume_margin_m=0.45, visited=visited, z_m=1.5)
    assert target is not None
    assert abs(wrap_angle(np.arctan2(target[1], target[0]))) > 2.5  # the unvisited sector behind


def test_a_dead_end_reverses_the_heading_to_keep_and_an_open_way_keeps_it():
    f = pocket_field()
    # inside the pocket facing its end wall: back out
    assert open_heading(np.array([3.0, 0.0, 1.5]), 0.0, f, clearance_m=0.45) == pytest.approx(math.pi)
    # at the pocket's mouth facing out: keep going
    assert open_heading(np.array([0.5, 0.0, 1.5]), math.pi, f, clearance_m=0.45) == pytest.approx(math.pi)
    # a narrow obstacle right ahead with free space 45 deg to the side: the route goes on past it
    post = AnalyticField(boxes=[Box(center=[1.2, 0.0, 1.5], half_extents=[0.2, 0.3, 2.0])])
    assert open_heading(np.zeros(3) + [0, 0, 1.5], 0.0, post, clearance_m=0.45) == pytest.approx(0.0)


class ShellMap:
    """A 0.1 m voxel map of an analytic field as a camera leaves it: the voxel holding a surface
    seen occupied, the space outside seen free, the inside of an obstacle never seen."""

    voxel_m = 0.1

    def __init__(self, field):
        self.field = field

    def query(self, points):
        return self.field.query(points)

    def _centre_distance(self, points):
        return self.field.query((np.floor(np.atleast_2d(points) / self.voxel_m) + 0.5) * self.voxel_m)[0]

    def known(self, points):
        return self._centre_distance(points) > -0.5 * self.voxel_m

    def observed_free(self, points):
        return self._centre_distance(points) > 0.5 * self.voxel_m


def test_a_landing_column_finds_a_seen_wall_anywhere_in_its_cylinder_but_not_the_ground_below():
    # a parked car seen as its surface only (its inside unknown), its side at y = -0.12 m
    car = Box(center=[0.25, -1.02, 0.745], half_extents=[2.25, 0.9, 0.725])
    ground = HalfSpace(point=[0.0, 0.0, 0.02], normal=[0.0, 0.0, 1.0])
    roof = Box(center=[0.0, 3.0, 2.1], half_extents=[1.0, 1.0, 0.05])  # an overhang 0.25 m above the column's top
    seen = ShellMap(AnalyticField(boxes=[car, roof], half_spaces=[ground]))
    xy = np.array([[0.0, 0.0], [1.5, 0.3], [0.0, 0.72], [0.0, 3.0]])
    # 0.12 m and 0.42 m beside the car, or under the overhang: blocked; 0.72 m off the car: clear
    np.testing.assert_array_equal(seen_obstacle_in_column(seen, xy, 0.3, 1.8, 0.6), [True, True, False, True])
    assert not seen_obstacle_in_column(seen, xy[3:], 0.3, 1.3, 0.6)[0]  # 0.75 m under it
    # the ground 0.3 m below the column's foot is where the vehicle lands, not an obstacle beside it
    assert not seen_obstacle_in_column(seen, np.array([[0.0, 6.0]]), 0.3, 1.8, 0.6)[0]
    # a field without knownness: its distance along the axis
    exact = AnalyticField(boxes=[car])
    np.testing.assert_array_equal(seen_obstacle_in_column(exact, xy[:3], 0.3, 1.8, 0.6), [True, True, False])


class SliceMap:
    """An analytic field with the map's distance slice (what the pilot's ESDF gives the search)."""

    def __init__(self, field, lo=(-2.0, -2.0), hi=(14.0, 12.0)):
        self.field, self.lo, self.hi = field, lo, hi

    def query(self, points):
        return self.field.query(points)

    def distance_slice(self, z_m):
        from planning.esdf import DistanceSlice

        x = np.arange(self.lo[0], self.hi[0], 0.1) + 0.05
        y = np.arange(self.lo[1], self.hi[1], 0.1) + 0.05
        X, Y = np.meshgrid(x, y, indexing="ij")
        d = self.field.distance(np.stack([X.ravel(), Y.ravel(), np.full(X.size, z_m)], axis=-1)).reshape(X.shape)
        return DistanceSlice(z_m, x, y, d)


def test_a_doorway_reached_off_the_heading_is_the_way_on():
    """The hard set's ``apartment-l01``: the vehicle came up to the living room's 1.8 m doorway 30
    deg off its heading (the jamb straight ahead), and the next subtask's target was behind the
    wall. No straight ray through the doorway keeps the 0.55 m clearance, so a search that read
    rays turned back into the room it had just crossed; the guide search's reach goes through."""
    floor = HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])
    wall = [Box(center=[1.95, 6.5, 1.3], half_extents=[1.95, 0.06, 1.3]), Box(center=[8.85, 6.5, 1.3], half_extents=[3.15, 0.06, 1.3])]
    p, heading = np.array([3.3, 5.46, 1.47]), 1.07
    doorway = AnalyticField(boxes=wall, half_spaces=[floor])
    assert open_heading(p, heading, doorway, clearance_m=0.55) == pytest.approx(wrap_angle(heading + math.pi))  # rays: closed
    assert open_heading(p, heading, SliceMap(doorway), clearance_m=0.55) == pytest.approx(heading)
    # the doorway shut: the way ahead is a wall, back out
    shut = AnalyticField(boxes=[Box(center=[6.0, 6.5, 1.3], half_extents=[6.0, 0.06, 1.3])], half_spaces=[floor])
    assert open_heading(p, heading, SliceMap(shut), clearance_m=0.55) == pytest.approx(wrap_angle(heading + math.pi))
    # a way round that is far longer than the straight line is no way on (the room's far end)
    assert open_heading(np.array([3.3, 5.9, 1.47]), math.pi / 2, SliceMap(shut), clearance_m=0.55) == pytest.approx(-math.pi / 2)


def test_after_a_leg_the_side_that_opens_on_unseen_space_is_looked_at():
    free = AnalyticField(half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])
    cfg = SearchConfig()
    # known everywhere but y > 1: the left side (yaw 0 -> +90 deg)
    f = KnownField(free, [-50, -50, -1], [50, 1.0, 10])
    assert side_to_look(np.array([0, 0, 1.5]), 0.0, f, config=cfg, volume=None) == pytest.approx(math.pi / 2)
    # nothing unknown: no look
    f_all = KnownField(free, [-50, -50, -1], [50, 50, 10])
    assert side_to_look(np.array([0, 0, 1.5]), 0.0, f_all, config=cfg, volume=None) is None
    # the unknown side lies outside the flight volume: nothing to find there
    vol = FlightVolume(np.array([-20.0, -20.0, 0.0]), np.array([20.0, 0.5, 5.0]))
    assert side_to_look(np.array([0, 0, 1.5]), 0.0, f, config=cfg, volume=vol) is None
    # beside walls seen on the way in there is nothing to look at, however unseen the space
    # behind them; abreast of a doorway the side it opens on is looked at
    corridor = doorway_corridor()
    assert side_to_look(np.array([10.0, 0.0, 1.5]), 0.0, corridor, config=cfg, volume=None) is None
    assert side_to_look(np.array([4.5, 0.0, 1.5]), 0.0, corridor, config=cfg, volume=None) == pytest.approx(math.pi / 2)


class SeenField:
    """An analytic field whose camera has seen only the given boxes of space (lo, hi): known
    there, free where the field is clear of every obstacle."""

    def __init__(self, field, seen):
        self.field, self.seen = field, [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in seen]

    def query(self, points):
        return self.field.query(points)

    def known(self, points):
        P = np.atleast_2d(points)
        return np.any([np.all((P >= lo) & (P <= hi), axis=1) for lo, hi in self.seen], axis=0)

    def observed_free(self, points):
        return self.known(points) & (self.field.query(np.atleast_2d(points))[0] > 0.0)


def doorway_corridor(room_seen=False):
    """The corridor of :func:`corridor_field` with a 1 m doorway in its left wall (x in [4, 5]);
    seen: the corridor and its walls, the doorway's frame, and the room beyond when
    ``room_seen``."""
    boxes = [
        Box(center=[1.5, 1.1, 1.5], half_extents=[2.5, 0.1, 1.5]),
        Box(center=[12.5, 1.1, 1.5], half_extents=[7.5, 0.1, 1.5]),
        Box(center=[9.5, -1.1, 1.5], half_extents=[10.5, 0.1, 1.5]),
    ]
    f = AnalyticField(boxes=boxes, half_spaces=[HalfSpace(point=[0, 0, 0], normal=[0, 0, 1])])
    seen = [([-1.0, -1.2, 0.0], [20.0, 1.2, 3.0])]
    if room_seen:
        seen.append(([-1.0, 1.2, 0.0], [20.0, 8.0, 3.0]))
    return SeenField(f, seen)


def test_passing_a_doorway_opens_a_side_to_glance_but_the_unseen_side_of_a_wall_does_not():
    cfg = SearchConfig()
    f = doorway_corridor()
    # abreast of the doorway: the unseen room beyond it is to the left of a +x leg
    assert side_opening(np.array([4.5, 0.0, 1.5]), 0.0, f, config=cfg, volume=None) == pytest.approx(math.pi / 2)
    assert opening_gain(np.array([4.5, 0.0, 1.5]), math.pi / 2, f, config=cfg, volume=None) > 0.5
    # beside a seen wall: the space behind it is as unseen as the room, but it is no opening
    # (the rays meet the wall's seen surface first; 5 cm steps never step over it)
    assert side_opening(np.array([10.0, 0.0, 1.5]), 0.0, f, config=cfg, volume=None) is None
    for yaw in (math.pi / 2, -math.pi / 2):
        assert opening_gain(np.array([10.0, 0.0, 1.5]), yaw, f, config=cfg, volume=None) == 0.0
    # a room already seen through the doorway: nothing left to glance at
    assert side_opening(np.array([4.5, 0.0, 1.5]), 0.0, doorway_corridor(room_seen=True), config=cfg, volume=None) is None
    # the room lies outside the flight volume: nothing to find there
    vol = FlightVolume(np.array([-20.0, -20.0, 0.0]), np.array([30.0, 1.3, 5.0]))
    assert side_opening(np.array([4.5, 0.0, 1.5]), 0.0, f, config=cfg, volume=vol) is None


def test_a_glance_holds_faces_the_opening_for_the_dwell_then_resumes_the_same_leg():
    cfg = SearchConfig(glance_dwell_s=1.0, explore_timeout_s=15.0, weave_rad=0.0)
    s = Search(cfg)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE)
    end = np.array([10.0, 0.0, 1.5])
    s.explore_from(0.0, end, np.array([0.0, 0.0, 1.5]), 0.0, kind="frontier")
    p = np.array([4.5, 0.0, 1.5])
    assert s.may_glance(p)
    # not near where the leg began: its sides were not yet in view
    assert not s.may_glance(np.array([cfg.glance_open_within_m - 0.1, 0.0, 1.5]))
    s.glance(8.0, p, math.pi / 2)
    assert s.glancing and not s.may_glance(p)
    t, yaw = 8.0, 0.0
    while True:
        point, yaw_ref, ev = s.control(t, p, yaw)
        assert ev is None  # a glance is no scan: it never asks the pilot for a new leg
        if not s.glancing:
            break
        np.testing.assert_allclose(point, p)  # held where it began
        assert yaw_ref == pytest.approx(math.pi / 2)
        yaw = yaw_ref  # an ideal turn
        t += 0.1
        assert t < 20.0, "the glance never ended"
    assert t == pytest.approx(9.1, abs=0.15)  # facing it from 8.1 s, then the 1 s dwell
    # back on the same leg, its kind kept, its timeout paused for the glance
    assert s.phase is SearchPhase.EXPLORE and s.leg_kind == "frontier"
    np.testing.assert_allclose(point, end)
    assert s.control(15.5, p, 0.0)[2] is None  # 15.5 s after the leg began, 14.5 s of it flown
    # one glance per opening: not again within the spacing, again past it
    assert not s.may_glance(p + [cfg.glance_spacing_m - 0.1, 0.0, 0.0])
    assert s.may_glance(p + [cfg.glance_spacing_m + 0.1, 0.0, 0.0])
    # near the leg's end the look after the leg takes over
    assert not s.may_glance(end - [cfg.explore_arrive_m + 0.5, 0.0, 0.0])


def test_frames_from_a_glance_until_the_camera_faces_the_leg_again_are_marked():
    s = Search(SearchConfig(glance_dwell_s=0.5))
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE)
    s.explore_from(0.0, np.array([10.0, 0.0, 1.5]), np.array([0.0, 0.0, 1.5]), 0.0)
    p = np.array([4.5, 0.0, 1.5])
    assert not s.during_glance(3.0)
    s.glance(4.0, p, math.pi / 2)
    t = 4.0
    while s.glancing:
        s.control(t, p, math.pi / 2)
        t += 0.1
    # back on the leg but still facing the side: the window stays open
    s.control(t, p, math.pi / 2)
    assert s.during_glance(4.0) and s.during_glance(t + 5.0)
    # the camera swings back within 45 deg of the leg's bearing: the window closes there
    s.control(t + 2.0, p, math.radians(40.0))
    assert s.during_glance(t + 2.0) and not s.during_glance(t + 2.1) and not s.during_glance(3.9)
    # a leg that ends before the camera faces it again closes the window at its last tick
    s.glance(20.0, p + [3.0, 0.0, 0.0], math.pi / 2)
    t = 20.0
    while s.glancing:
        s.control(t, p, math.pi / 2)
        t += 0.1
    s.control(t, p, math.pi / 2)
    s.explore_from(t + 0.5, np.array([0.0, 10.0, 1.5]), p, math.pi / 2)
    assert s.during_glance(t) and not s.during_glance(t + 0.1) and not s.during_glance(60.0)


def test_a_leg_whose_end_the_planner_holds_back_ends_after_the_grace_time():
    cfg = SearchConfig(leg_blocked_s=2.0, explore_timeout_s=30.0)
    s = Search(cfg)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE)
    s.explore_from(0.0, np.array([10.0, 0.0, 1.5]), np.zeros(3), 0.0)
    p = np.array([3.0, 0.0, 1.5])
    assert not s.leg_blocked(1.0, True)
    assert not s.leg_blocked(2.0, False)  # a free tick restarts the count
    assert not s.leg_blocked(2.5, True) and not s.leg_blocked(4.4, True)
    assert s.control(4.4, p, 0.0)[2] is None
    assert s.leg_blocked(4.5, True)  # 2 s held back: over, reported once
    assert not s.leg_blocked(4.6, True)
    assert s.control(4.6, p, 0.0)[2] == "explore_done"
    # a new leg starts afresh
    s.explore_from(5.0, np.array([0.0, 10.0, 1.5]), p, 0.0)
    assert s.control(5.1, p, 0.0)[2] is None and not s.leg_blocked(5.1, True)


def test_glances_are_off_with_the_switch():
    s = Search(SearchConfig(glance=False))
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE)
    s.explore_from(0.0, np.array([10.0, 0.0, 1.5]), np.zeros(3), 0.0)
    assert not s.may_glance(np.array([4.0, 0.0, 1.5]))


def test_travel_heading_is_the_recent_displacement():
    s = Search(SearchConfig())
    for k in range(30):
        s.remember(k * 0.2, np.array([0.0, -0.1 * k, 1.0]))  # flying toward -y
    assert s.travel_heading(5.8) == pytest.approx(-math.pi / 2)
    still = Search(SearchConfig())
    for k in range(30):
        still.remember(k * 0.2, np.array([0.0, 0.0, 1.0]))
    assert still.travel_heading(5.8) is None


def test_a_leg_end_held_back_at_the_vehicle_is_held_at_any_distance_beyond_arrival():
    p = np.array([-13.21, -6.77, 1.49])
    at_vehicle = p + [0.05, 0.0, 0.0]
    # the held-out yard: an end 1.1 m off round a container's corner, the plan held at the
    # vehicle; before, an end nearer than arrival + 0.5 m was never held, and the vehicle
    # hovered until the stall window ended
    assert leg_end_held(at_vehicle, [-14.15, -7.35, 1.5], p, 0.8)
    assert leg_end_held(at_vehicle, p + [6.0, 0.0, 0.0], p, 0.8)
    assert not leg_end_held(at_vehicle, p + [0.7, 0.0, 0.0], p, 0.8)  # arrived: the leg ends by arrival
    assert not leg_end_held(p + [1.5, 0.0, 0.0], p + [3.0, 0.0, 0.0], p, 0.8)  # the plan still leads on
    assert leg_end_held(at_vehicle, p + [0.0, 0.0, 3.0] + [0.9, 0.0, 0.0], p, 0.8)  # horizontal distances


# -- closed loop ------------------------------------------------------------------------------
def test_a_blocked_or_stalled_leg_is_a_dead_end_that_no_later_leg_chooses():
    cfg = SearchConfig(leg_blocked_s=1.0, explore_timeout_s=30.0)
    s = Search(cfg)
    s.start(0.0, np.zeros(3), 0.0, SearchTrigger.NOT_VISIBLE)
    end = np.array([-3.5, 0.0, 1.5])
    s.explore_from(0.0, end, np.zeros(3), 0.0)
    assert s.dead_ends.shape == (0, 3)
    assert not s.leg_blocked(0.5, True) and s.leg_blocked(1.6, True)
    np.testing.assert_allclose(s.dead_ends, [end])
    s.leg_failed()  # outside a leg (the blocked one is over): nothing more to remember
    assert s.control(1.7, np.zeros(3), 0.0)[2] == "explore_done"
    # from the pocket the only way out is -x; with every end that way dead, there is none
    f = KnownField(pocket_field(), [-1.0, -1.2, 0.0], [4.0, 1.2, 3.0])
    kw = dict(config=SearchConfig(), volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    p0 = np.array([3.0, 0.0, 1.5])
    first = explore_target(p0, 0.0, f, **kw)
    assert first is not None
    dead = np.array([first])
    radius = SearchConfig().dead_end_radius_m

    def clear_of(point, dead_end):
        return point is None or float(np.linalg.norm(point[:2] - dead_end[:2])) > radius

    assert clear_of(explore_target(p0, 0.0, f, dead_ends=dead, **kw), first)
    ray = open_ray_target(p0, 0.0, f, **kw)
    assert ray is not None and clear_of(open_ray_target(p0, 0.0, f, dead_ends=np.array([ray]), **kw), ray)
    look = look_target(p0, math.pi, f, **kw)
    assert look is not None and look_target(p0, math.pi, f, dead_ends=np.array([look]), **kw) is None


class SeeingVlm(ScriptedVlm):
    """The simulated model's answers, except that a decision with the target out of the frame
    says it cannot see it (a model that never invents a point)."""

    def __init__(self, target_id: int, min_px: int = 30, **kw):
        super().__init__("perfect", **kw)
        self.target_id, self.min_px = target_id, min_px
        self.hidden = 0

    def complete(self, messages, images=(), **kw):
        prompt = parse_prompt(messages)
        if isinstance(prompt, DecisionPrompt) and images:
            ann = images[-1].annotation
            if int(np.count_nonzero(ann.instance_ids == self.target_id)) < self.min_px:
                self.hidden += 1
                self.counts["decision"] += 1
                return text(self.hidden_answer(prompt, images[-1]), 0.81)
        return super().complete(messages, images, **kw)

    def hidden_answer(self, prompt: DecisionPrompt, image) -> str:
        """The decision answer with the target out of the frame."""
        return NOT_VISIBLE


class LookingVlm(SeeingVlm):
    """As :class:`SeeingVlm`, but "not visible" carries where the model would look
    (``decision/v3``): the centre of the image, straight ahead."""

    def hidden_answer(self, prompt, image):
        w, h = image.size
        return json.dumps({"target_visible": False, "point_2d": [w // 2, h // 2]})


class PilotMethod(OnFlyMethod):
    def __init__(self, backend, config=None, planner=None):
        super().__init__("sim:perfect", config, planner=planner)
        self._backend = backend

    def reset(self, spec):
        self.pilot = OnFlyPilot(self.config, self._backend, spec.runtime, planner=self._planner, volume=spec.flight_volume)
        self.pilot.begin(spec.instruction, spec.start_state.t_s)


@pytest.fixture(scope="module")
def planner():
    return Planner(PilotConfig().planner)


def fly(world, method, instruction, goal, limit_s=70.0):
    plans = []

    def observer(step):
        if step.output.trajectory is not None:
            plans.append(np.asarray(step.output.trajectory.p))

    r = run_episode(
        world, method, instruction=instruction, goal=goal, reference_path_m=10.0, seed=0, error_model="test",
        config=EpisodeConfig(time_limit_s=limit_s, frame_period_s=0.5), observer=observer,
    )
    return r, plans


def assert_plans_inside(world, plans):
    vol = FlightVolume(world.scene.bounds.min_m, world.scene.bounds.max_m)
    for pts in plans:
        assert bool(np.all(vol.contains(pts))), "a plan point left the flight volume"


def test_target_behind_at_the_start_is_found_by_the_scan_and_the_task_succeeds(planner):
    world0 = World.from_scene("urban_block", camera=CAM)
    van = next(o for o in world0.scene.objects if o.name == "red van")
    s = world0.scene.start
    start = VehicleState(0.0, s.position_m, np.zeros(3), float(wrap_angle(s.yaw_rad + math.pi)))
    world = World(world0.scene, camera=CAM, initial_state=start)
    backend = SeeingVlm(van.instance_id)
    m = PilotMethod(backend, planner=planner)
    region = GoalRegion([4.3, -15.0, 1.3], [1.0, 2.3, 0.95])
    r, plans = fly(world, m, "Fly over to the red van and stop right next to it.", region)
    kinds = [e.kind for e in m.pilot.events]
    assert "search_start" in kinds and "search_end" in kinds
    end = next(e for e in m.pilot.events if e.kind == "search_end")
    assert end.data["reason"] == "target_pointed"
    assert r.end_reason == "stopped" and r.metrics.success and not r.metrics.collided
    assert_plans_inside(world, plans)


def test_the_paper_pilot_without_search_hovers_with_the_target_behind(planner):
    world0 = World.from_scene("urban_block", camera=CAM)
    van = next(o for o in world0.scene.objects if o.name == "red van")
    s = world0.scene.start
    start = VehicleState(0.0, s.position_m, np.zeros(3), float(wrap_angle(s.yaw_rad + math.pi)))
    world = World(world0.scene, camera=CAM, initial_state=start)
    m = PilotMethod(SeeingVlm(van.instance_id), config=ablation_config("onfly_no_search"), planner=planner)
    region = GoalRegion([4.3, -15.0, 1.3], [1.0, 2.3, 0.95])
    r, _ = fly(world, m, "Fly over to the red van and stop right next to it.", region, limit_s=30.0)
    assert r.end_reason == "time_limit" and not r.metrics.success
    assert "search_start" not in [e.kind for e in m.pilot.events]


def _box(c, size):
    return {"type": "box", "center_m": list(c), "size_m": list(size)}


def _crate_scene(name, walls, crate, bounds, start_m, extra=()):
    """A scene of ``walls`` (box parts) over a ground plane, with one red crate (a box part)
    and the ``extra`` objects (scene-format dicts)."""
    objects = [
        {"name": "ground", "label": "ground", "instance_id": 1, "color": "#777777", "target": False,
         "parts": [{"type": "plane", "center_m": [0, 0, 0], "size_m": [40, 40]}]},
        {"name": "walls", "label": "wall", "instance_id": 2, "color": "#bbbbaa", "target": False, "parts": walls},
        {"name": "red crate", "label": "crate", "instance_id": 3, "color": "#cc2222", "parts": [crate]},
        *extra,
    ]
    data = {
        "format": "onfly-scene/1", "name": name,
        "bounds": {"min_m": list(bounds[0]), "max_m": list(bounds[1])},
        "start": {"position_m": list(start_m), "yaw_deg": 0},
        "objects": objects,
    }  # fmt: skip
    return parse_scene(data, f"<{name}>")


def pocket_scene(extra=()):
    """A 2.4 m wide dead-end pocket open toward -x; a red crate around the corner outside it,
    hidden from anywhere inside the pocket by its left wall."""
    walls = [_box([2.0, 1.3, 1.5], [4.0, 0.2, 3.0]), _box([2.0, -1.3, 1.5], [4.0, 0.2, 3.0]), _box([4.1, 0.0, 1.5], [0.2, 2.8, 3.0])]
    crate = _box([-2.0, 5.0, 0.6], [1.2, 1.2, 1.2])
    return _crate_scene("pocket", walls, crate, ([-8, -8, 0], [6, 10, 5]), [3.0, 0.0, 1.5], extra)


def test_a_vehicle_in_a_dead_end_corner_gets_out_and_finds_the_target(planner):
    scene = pocket_scene()
    world = World(scene, camera=CAM)
    m = PilotMethod(SeeingVlm(3), planner=planner)
    region = GoalRegion([-2.0, 5.0, 0.6], [0.6, 0.6, 0.6])
    r, plans = fly(world, m, "Find the red crate and stop next to it.", region)
    events = m.pilot.events
    kinds = [e.kind for e in events]
    assert "search_start" in kinds and "search_explore" in kinds
    assert not r.metrics.collided
    # out of the pocket (x < 0) and at the crate
    assert r.end_reason == "stopped" and r.metrics.success, (r.end_reason, kinds[-12:])
    assert_plans_inside(world, plans)


class RepeatingVlm(SeeingVlm):
    """As :class:`SeeingVlm`, but with the target out of the frame the model answers that it
    sees it: at the history point when the prompt shows one, else straight ahead (the image
    centre). So the simulated model answers a leg that names nothing to find; once the
    vehicle is at a goal in front of a wall, every frame hands it the same goal again."""

    def hidden_answer(self, prompt, image):
        w, h = image.size
        uv = [int(round(x)) for x in prompt.history_uv] if prompt.history_uv is not None else [w // 2, h // 2]
        return json.dumps({"target_visible": True, "point_2d": uv})


def test_a_model_that_keeps_pointing_at_the_wall_of_a_dead_end_does_not_hold_the_vehicle_there(planner):
    # the vehicle flies to the pocket's end wall and the model keeps handing it a goal there:
    # the stall starts a search, goals at the stall spot are no goals, and the vehicle gets out
    scene = pocket_scene()
    start = VehicleState(0.0, np.array([1.0, 0.0, 1.5]), np.zeros(3), 0.0)
    world = World(scene, camera=CAM, initial_state=start)
    m = PilotMethod(RepeatingVlm(3), planner=planner)
    region = GoalRegion([-2.0, 5.0, 0.6], [0.6, 0.6, 0.6])
    r, plans = fly(world, m, "Find the red crate and stop next to it.", region, limit_s=100.0)
    events = m.pilot.events
    kinds = [e.kind for e in events]
    stall = next(e for e in events if e.kind == "stalled")
    assert stall.data["position"][0] > 2.0  # it did fly into the pocket's end first
    assert "goal_dead_spot" in kinds
    assert not r.metrics.collided
    assert r.end_reason == "stopped" and r.metrics.success, (r.end_reason, kinds[-12:])
    assert_plans_inside(world, plans)


def doorway_scene():
    """A corridor along +x (walls at y = +-1.3, x in [-1, 14], closed at both ends) with a
    1.2 m doorway in its left wall at x in [5.0, 6.2] into a room (y up to 6.5); a red crate in
    the room, hidden by the corridor's wall from everywhere in the corridor but abreast of the
    doorway."""
    walls = [
        _box([2.0, 1.3, 1.5], [6.0, 0.2, 3.0]), _box([10.1, 1.3, 1.5], [7.8, 0.2, 3.0]),  # left, doorway between
        _box([6.5, -1.3, 1.5], [15.0, 0.2, 3.0]),  # right
        _box([-1.1, 0.0, 1.5], [0.2, 2.8, 3.0]), _box([14.1, 0.0, 1.5], [0.2, 2.8, 3.0]),  # ends
        _box([1.9, 3.9, 1.5], [0.2, 5.0, 3.0]), _box([9.1, 3.9, 1.5], [0.2, 5.0, 3.0]),  # the room's sides
        _box([5.5, 6.5, 1.5], [7.4, 0.2, 3.0]),  # its back
    ]
    crate = _box([5.6, 5.0, 0.9], [1.0, 1.0, 1.0])
    return _crate_scene("doorway", walls, crate, ([-1.0, -1.3, 0.0], [14.0, 6.5, 3.0]), [0.0, 0.0, 1.5])


def test_a_doorway_passed_on_a_leg_is_glanced_into_and_the_target_behind_it_found(planner):
    """The model looks down the corridor (the deepest way on), so the leg passes the doorway
    with the camera facing ahead; the glance turns it to the doorway and the crate is pointed
    at, which ends the search with a goal in the room. With glances off the vehicle flies past
    the doorway without a sight of the crate."""
    scene = doorway_scene()
    start = VehicleState(0.0, np.array([0.0, 0.0, 1.5]), np.zeros(3), 0.0)
    region = GoalRegion([5.6, 5.0, 0.9], [0.5, 0.5, 0.5])
    instruction = "Find the red crate and stop next to it."
    m = PilotMethod(LookingVlm(3), config=PilotConfig(search=SearchConfig(scan_first_search=False)), planner=planner)
    world = World(scene, camera=CAM, initial_state=start)
    r, plans = fly(world, m, instruction, region, limit_s=24.0)
    ev = m.pilot.events
    glances = [e for e in ev if e.kind == "search_glance"]
    end = next(e for e in ev if e.kind == "search_end")
    assert glances and end.data["reason"] == "target_pointed"
    doorway = next(e for e in glances if e.t_s <= end.t_s)
    assert 4.0 <= doorway.data["position"][0] <= 7.0 and doorway.data["yaw"] == pytest.approx(math.pi / 2, abs=0.2)
    goals = [e.data["goal_world"] for e in ev if e.kind == "decision" and e.t_s >= end.t_s and e.data["goal_world"] is not None]
    assert max(g[1] for g in goals) > 1.3  # through the doorway, into the room
    assert not r.metrics.collided
    assert_plans_inside(world, plans)

    m2 = PilotMethod(LookingVlm(3), config=PilotConfig(search=SearchConfig(scan_first_search=False, glance=False)), planner=planner)
    track = []
    world2 = World(scene, camera=CAM, initial_state=start)
    run_episode(
        world2, m2, instruction=instruction, goal=region, reference_path_m=10.0, seed=0, error_model="test",
        config=EpisodeConfig(time_limit_s=end.t_s + 2.0, frame_period_s=0.5),
        observer=lambda st: track.append(st.state.p[0]),
    )  # fmt: skip
    assert max(track) > 7.0  # past the doorway
    assert not any(e.kind == "search_end" for e in m2.pilot.events)


class FrontierMap:
    """Exact geometry (a wall at x = 2 with a 2 m doorway at y in [0.5, 2.5]) with a frontier
    beyond the doorway and one behind the solid wall, as a map would report them."""

    def __init__(self):
        self.field = AnalyticField(boxes=[
            Box(center=[2.0, -4.75, 1.5], half_extents=[0.1, 5.25, 2.0]),
            Box(center=[2.0, 7.75, 1.5], half_extents=[0.1, 5.25, 2.0]),
        ])
        gy = np.arange(0.5, 2.51, 0.1)
        gz = np.arange(1.0, 2.01, 0.1)
        door = np.array([[3.0, y, z] for y in gy for z in gz])
        behind = np.array([[3.0, y, z] for y in np.arange(-4.0, -2.0, 0.1) for z in gz])
        self.frontier = np.vstack([door, behind])

    def query(self, points):
        return self.field.query(points)

    def known(self, points):
        return np.asarray(points)[:, 0] < 2.0

    def frontier_points(self, axes=(0, 1, 2)):
        return self.frontier

    def distance_slice(self, z_m):
        from planning.esdf import DistanceSlice

        x = np.arange(-6.0, 6.0, 0.1) + 0.05
        y = np.arange(-6.0, 6.0, 0.1) + 0.05
        X, Y = np.meshgrid(x, y, indexing="ij")
        d = self.field.distance(np.stack([X.ravel(), Y.ravel(), np.full(X.size, z_m)], axis=-1)).reshape(X.shape)
        return DistanceSlice(z_m, x, y, d)


def test_the_frontier_target_is_the_reachable_doorway_not_the_frontier_behind_a_wall():
    from onfly.search import frontier_target

    m = FrontierMap()
    target = frontier_target(np.array([-2.0, -3.0, 1.5]), 0.0, m, config=SearchConfig(), volume=None, volume_margin_m=0.45,
                             visited=np.zeros((0, 3)), z_m=1.5)
    assert target is not None
    # next to the doorway's frontier (reached through the doorway), not behind the solid wall
    assert 0.0 <= target[1] <= 3.0 and target[0] > 1.0
    assert float(m.field.distance(target[None])[0]) >= SearchConfig().explore_clearance_m
    # the door shut: the frontier behind the wall cannot be reached, so there is no target
    m.field = AnalyticField(boxes=[*m.field.boxes, Box(center=[2.0, 1.5, 1.5], half_extents=[0.1, 1.1, 2.0])])
    assert frontier_target(np.array([-2.0, -3.0, 1.5]), 0.0, m, config=SearchConfig(), volume=None, volume_margin_m=0.45,
                           visited=np.zeros((0, 3)), z_m=1.5) is None


def test_a_frontier_leg_never_ends_where_the_planners_guide_search_cannot_go():
    """A 1.1 m doorway (0.55 m clearance on its middle line only) is narrower than the planner's
    guide search passes (``d_safe_m`` + ``guide_clearance_margin_m`` = 0.55 m on its grid's
    cells): a leg through it would
    hover until the stall window ends. With the default clearance there is no frontier leg; with
    the safety distance alone (0.45 m) there was one, which the guide search cannot reach."""
    from onfly.search import frontier_target
    from planning.guide_path import guide_search
    from planning.planner_config import PlannerConfig

    m = FrontierMap()
    m.field = AnalyticField(boxes=[
        Box(center=[2.0, -4.5, 1.5], half_extents=[0.1, 5.5, 2.0]),  # the wall up to y = 1.0
        Box(center=[2.0, 7.05, 1.5], half_extents=[0.1, 4.95, 2.0]),  # and from y = 2.1
    ])  # fmt: skip
    start = np.array([-2.0, -3.0, 1.5])
    pc = PlannerConfig()
    guide_clear = pc.d_safe_m + pc.guide_clearance_margin_m
    assert SearchConfig().explore_clearance_m >= guide_clear
    kw = dict(volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    assert frontier_target(start, 0.0, m, config=SearchConfig(), **kw) is None
    narrow = frontier_target(start, 0.0, m, config=SearchConfig(explore_clearance_m=pc.d_safe_m), **kw)
    assert narrow is not None and narrow[0] > 2.0  # through the doorway
    assert guide_search(m, start, narrow, clearance_m=guide_clear, preferred_clearance_m=1.0).status == "unreachable"


def test_a_look_through_a_doorway_is_a_leg_through_it_on_the_maps_free_layer():
    """With a map that has a distance layer the look leg is a place reached through the free
    layer: the model looked through the doorway at an angle, the leg ends beyond the wall; with
    the door shut it ends in front of the wall, never behind it."""
    m = FrontierMap()
    p = np.array([-1.0, -2.0, 1.5])
    cfg = SearchConfig()
    look = math.atan2(1.5 - p[1], 4.0 - p[0])  # toward a point 2 m beyond the doorway's middle
    common = dict(config=cfg, volume=None, volume_margin_m=0.45, visited=np.zeros((0, 3)), z_m=1.5)
    t = look_target(p, look, m, **common)
    assert t is not None and t[0] > 2.1 + cfg.look_clearance_m  # beyond the wall, so through the door
    assert float(m.field.distance(t[None])[0]) >= cfg.look_clearance_m
    bearing = math.atan2(t[1] - p[1], t[0] - p[0])
    assert abs(wrap_angle(bearing - look)) <= cfg.look_cone_rad + 1e-9
    m.field = AnalyticField(boxes=[*m.field.boxes, Box(center=[2.0, 1.5, 1.5], half_extents=[0.1, 1.1, 2.0])])
    shut = look_target(p, look, m, **common)
    assert shut is not None and shut[0] < 2.0 - cfg.look_clearance_m


def test_a_withdrawn_stop_resumes_the_search_and_a_lost_without_a_sighting_does_not_end_it(planner):
    # the target is behind: every decision says "not visible" until the scan shows it. The
    # monitor (scripted) answers STOP once, then CONTINUE (the STOP is withdrawn), then LOST
    # (nothing was ever pointed at: no sighting to turn back to), then the simulated answers.
    # The decisions stay blind until the script has played out, so the first scan may well end
    # before they see anything: the search has explored on by then, hence the 100 s limit.
    script = {2: "STOP", 3: "CONTINUE", 4: "LOST"}  # calls 0, 1 (before the search): CONTINUE

    def monitor(i, resp):
        return text(script.get(i, "CONTINUE"), 1.15) if i <= 4 else None

    class BlindUntilScripted(SeeingVlm):
        """Decisions say "not visible" until the monitor's script has played out."""

        def complete(self, messages, images=(), **kw):
            if isinstance(parse_prompt(messages), DecisionPrompt) and self.counts["monitor"] <= 4:
                self.counts["decision"] += 1
                return text(NOT_VISIBLE, 0.81)
            return super().complete(messages, images, **kw)

    world0 = World.from_scene("urban_block", camera=CAM)
    van = next(o for o in world0.scene.objects if o.name == "red van")
    s = world0.scene.start
    start = VehicleState(0.0, s.position_m, np.zeros(3), float(wrap_angle(s.yaw_rad + math.pi)))
    world = World(world0.scene, camera=CAM, initial_state=start)
    backend = BlindUntilScripted(van.instance_id, monitor=monitor)
    m = PilotMethod(backend, planner=planner)
    region = GoalRegion([4.3, -15.0, 1.3], [1.0, 2.3, 0.95])
    modes = []
    r = run_episode(
        world, m, instruction="Fly over to the red van and stop right next to it.", goal=region, reference_path_m=10.0,
        seed=0, error_model="test", config=EpisodeConfig(time_limit_s=100.0, frame_period_s=0.5),
        observer=lambda st: modes.append((st.t_s, st.method.pilot.mode)),
    )
    ev = m.pilot.events
    kinds = [e.kind for e in ev]
    heard = next(e.t_s for e in ev if e.kind == "stop_heard")
    withdrawn = next(e.t_s for e in ev if e.kind == "stop_withdrawn")
    started = [e.t_s for e in ev if e.kind == "search_start"]
    assert started and started[0] < heard < withdrawn
    # the STOP paused the search: hover while confirming, then the same search goes on (no new
    # start, no end until the target is pointed at)
    assert all(mode is PilotMode.CONFIRMING for t, mode in modes if heard + 0.15 < t < withdrawn - 1e-9)
    assert [mode for t, mode in modes if t > withdrawn + 0.15][0] is PilotMode.SEARCHING
    lost = next(e for e in ev if e.kind == "lost")
    assert lost.data["recovery"] == "searching"
    assert "recovering" not in [mo.value for _, mo in modes]
    ends = [e for e in ev if e.kind == "search_end"]
    assert ends[0].data["reason"] == "target_pointed" and ends[0].t_s > lost.t_s
    assert len([t for t in started if t < ends[0].t_s]) == 1
    assert r.end_reason == "stopped" and r.metrics.success and not r.metrics.collided


def test_a_look_point_starts_the_search_on_a_leg_that_way_without_a_scan(planner):
    """A "not visible" answer that says where to look starts a search straight on a leg that way
    (no scan: the model has just looked at this view); the vehicle then gets out of the pocket
    and finds the crate. The episode's first search scans first by default
    (``scan_first_search``), so here it is off: the rule is that of every later search. Without
    look hints the same answers start a scan."""
    scene = pocket_scene()
    start = VehicleState(0.0, np.array([3.0, 0.0, 1.5]), np.zeros(3), math.pi)  # facing out of the pocket
    world = World(scene, camera=CAM, initial_state=start)
    m = PilotMethod(LookingVlm(3), config=PilotConfig(search=SearchConfig(scan_first_search=False)), planner=planner)
    track = []
    region = GoalRegion([-2.0, 5.0, 0.6], [0.6, 0.6, 0.6])
    r = run_episode(
        world, m, instruction="Find the red crate and stop next to it.", goal=region, reference_path_m=10.0, seed=0,
        error_model="test", config=EpisodeConfig(time_limit_s=70.0, frame_period_s=0.5),
        observer=lambda st: track.append((st.t_s, st.state.p.copy(), st.state.yaw)),
    )
    ev = m.pilot.events
    # the instruction has one step (its closing clause points back): the first answer, on the
    # whole instruction before the decomposition lands, starts the search
    first = next(e for e in ev if e.kind == "decision")
    assert first.data["subtask"] == "Find the red crate and stop next to it."
    assert first.t_s < next(e.t_s for e in ev if e.kind == "decomposition")
    first_decision = first.t_s
    start_ev = next(e for e in ev if e.kind == "search_start")
    assert start_ev.t_s == pytest.approx(first_decision) and start_ev.data["trigger"] == "not_visible"
    after = [e for e in ev if e.t_s >= start_ev.t_s and e.kind.startswith("search_")]
    assert after[1].kind == "search_explore" and after[1].data["how"] == "look"
    leg = np.asarray(after[1].data["target"])
    assert leg[0] <= 3.0 - SearchConfig().look_min_leg_m and abs(leg[1]) < 1.0  # straight ahead, out of the pocket
    # flying at once, facing the way it flies: no turn in place before the first leg
    early = [(t, p, y) for t, p, y in track if t <= start_ev.t_s + 2.0]
    assert max(abs(wrap_angle(y - math.pi)) for _, _, y in early) < 0.3
    assert early[-1][1][0] < 2.5 and abs(early[-1][1][1]) < 0.3
    assert r.end_reason == "stopped" and r.metrics.success and not r.metrics.collided

    # look hints off: the same answers start a scan in place first
    cfg = PilotConfig(search=SearchConfig(look_hints=False, scan_first_search=False))
    m2 = PilotMethod(LookingVlm(3), config=cfg, planner=planner)
    world2 = World(scene, camera=CAM, initial_state=start)
    fly(world2, m2, "Find the red crate and stop next to it.", region, limit_s=12.0)
    assert "look" not in [e.data.get("how") for e in m2.pilot.events if e.kind == "search_explore"]
    assert any(e.kind == "search_start" for e in m2.pilot.events)


def test_a_one_step_instruction_starts_its_scan_on_the_first_answer_before_the_decomposition(planner):
    """An instruction of one step names the first subtask's target, so the first "not visible"
    answer about it starts the scan at once; it is not dropped as stale when the decomposition
    returns the step reworded. One step is what the deterministic reading leaves
    (:func:`vlm.decompose.count_steps`): a closing clause that only points back ("and stop next
    to it", "Go to it.") adds none. An instruction of two steps waits for an answer about its
    first subtask (the whole instruction's target is the last)."""
    scene = pocket_scene()
    start = VehicleState(0.0, np.array([3.0, 0.0, 1.5]), np.zeros(3), math.pi)
    region = GoalRegion([-2.0, 5.0, 0.6], [0.6, 0.6, 0.6])
    one_step = ("Find the red crate.", "Find the red crate and stop next to it.", "Somewhere outside there is a red crate. Go to it.")
    two_steps = "Fly to the blue barrel, then find the red crate."
    firsts = {}
    for instruction in (*one_step, two_steps):
        m = PilotMethod(LookingVlm(3), planner=planner)
        fly(World(scene, camera=CAM, initial_state=start), m, instruction, region, limit_s=8.0)
        ev = m.pilot.events
        t_dec = next(e.t_s for e in ev if e.kind == "decomposition")
        first_answer = next(e.t_s for e in ev if e.kind == "decision")
        firsts[instruction] = (next(e.t_s for e in ev if e.kind == "search_start"), t_dec, first_answer)
    for instruction in one_step:
        t_search, t_dec, first_answer = firsts[instruction]
        assert t_search == pytest.approx(first_answer) and t_search < 1.5 < t_dec, instruction
    t_search, t_dec, _ = firsts[two_steps]
    assert t_search > t_dec


class MergingVlm(LookingVlm):
    """As :class:`LookingVlm`, but the decomposition merges every instruction into one reworded
    subtask (a model may: the error model's merge rate)."""

    def complete(self, messages, images=(), **kw):
        if isinstance(parse_prompt(messages), DecomposePrompt):
            self.counts["decompose"] += 1
            return text(json.dumps(["find the red crate past the blue barrel"]), 3.0)
        return super().complete(messages, images, **kw)


def test_an_answer_about_the_instruction_counts_when_it_decomposed_into_one_subtask(planner):
    """A decision call submitted on the whole instruction before the decomposition landed, and
    landing after it, answers the one subtask the decomposition returned: its "not visible"
    starts the search then, not one decision later."""
    scene = pocket_scene()
    start = VehicleState(0.0, np.array([3.0, 0.0, 1.5]), np.zeros(3), math.pi)
    instruction = "Fly to the blue barrel, then find the red crate."
    m = PilotMethod(MergingVlm(3), planner=planner)
    fly(World(scene, camera=CAM, initial_state=start), m, instruction, GoalRegion([-2.0, 5.0, 0.6], [0.6, 0.6, 0.6]), limit_s=8.0)
    ev = m.pilot.events
    dec = next(e for e in ev if e.kind == "decomposition")
    assert dec.data["subtasks"] == ["find the red crate past the blue barrel"]
    late = next(e for e in ev if e.kind == "decision" and e.t_s > dec.t_s)
    assert late.data["subtask"] == instruction and late.data["not_visible"]
    assert next(e for e in ev if e.kind == "search_start").t_s == pytest.approx(late.t_s)


def test_scan_first_search_turns_all_round_then_takes_the_best_look_of_the_scan(planner):
    """With ``scan_first_search`` the first "not visible" answer on a subtask starts a scan even
    though it carries a look point: the vehicle holds its place and turns before any leg; the
    leg after the scan is the look from the one heading that gave a leg (out of the pocket),
    not the last heading's look (into a wall)."""
    scene = pocket_scene()
    start = VehicleState(0.0, np.array([3.0, 0.0, 1.5]), np.zeros(3), math.pi)  # facing out of the pocket
    world = World(scene, camera=CAM, initial_state=start)
    m = PilotMethod(LookingVlm(3), planner=planner)  # scan_first_search is the default
    track = []
    r = run_episode(
        world, m, instruction="Find the red crate and stop next to it.", goal=GoalRegion([-2.0, 5.0, 0.6], [0.6, 0.6, 0.6]),
        reference_path_m=10.0, seed=0, error_model="test", config=EpisodeConfig(time_limit_s=40.0, frame_period_s=0.5),
        observer=lambda st: track.append((st.t_s, st.state.p.copy(), st.state.yaw)),
    )
    ev = m.pilot.events
    start_ev = next(e for e in ev if e.kind == "search_start")
    assert start_ev.data["trigger"] == "not_visible"
    leg = next(e for e in ev if e.kind == "search_explore")
    assert leg.data["how"] == "look" and leg.t_s > start_ev.t_s + 5.0
    scan = [(p, y) for t, p, y in track if start_ev.t_s <= t <= leg.t_s]
    assert max(np.linalg.norm(p[:2] - start_ev.data["position"][:2]) for p, _ in scan) < 0.3  # turned in place
    assert max(abs(wrap_angle(y - math.pi)) for _, y in scan) > 0.75 * math.pi  # three quarters round
    end = np.asarray(leg.data["target"])
    assert end[0] <= 3.0 - SearchConfig().look_min_leg_m and abs(end[1]) < 1.0  # out of the pocket
    assert not r.metrics.collided


def two_way_corridor_scene():
    """A corridor 2.4 m wide along x from -9 to 9, closed at both ends, with an alcove off its
    north side near each end; the red crate stands in the west alcove, hidden by the north
    wall from anywhere in the corridor's middle. East and west are alike to the map."""
    walls = [
        _box([-7.75 - 0.75 - 0.5, 1.3, 1.5], [1.0, 0.2, 3.0]),  # north wall, west of the west alcove
        _box([0.0, 1.3, 1.5], [13.0, 0.2, 3.0]),  # north wall between the alcoves
        _box([7.75 + 0.75 + 0.5, 1.3, 1.5], [1.0, 0.2, 3.0]),
        _box([0.0, -1.3, 1.5], [18.4, 0.2, 3.0]),  # south wall
        _box([-9.1, 0.0, 1.5], [0.2, 2.8, 3.0]), _box([9.1, 0.0, 1.5], [0.2, 2.8, 3.0]),  # ends
        _box([-7.25, 3.6, 1.5], [2.3, 0.2, 3.0]), _box([7.25, 3.6, 1.5], [2.3, 0.2, 3.0]),  # alcove backs
        _box([-8.5, 2.45, 1.5], [0.2, 2.1, 3.0]), _box([-6.0, 2.45, 1.5], [0.2, 2.1, 3.0]),  # alcove sides
        _box([8.5, 2.45, 1.5], [0.2, 2.1, 3.0]), _box([6.0, 2.45, 1.5], [0.2, 2.1, 3.0]),
    ]  # fmt: skip
    crate = _box([-7.25, 2.8, 0.6], [0.8, 0.8, 1.2])
    return _crate_scene("two_way_corridor", walls, crate, ([-9.5, -2, 0], [9.5, 4, 4]), [0.0, 0.0, 1.5])


@pytest.mark.parametrize("heading", ["west", "east"])
def test_a_compass_heading_in_the_subtask_is_the_way_the_search_goes(planner, heading):
    """The corridor is alike both ways; the words say which way the route runs. The search's
    legs (its look legs included, which the model would point either way) keep the heading the
    subtask names: west, the vehicle finds the crate in the west alcove; east, it flies east."""
    scene = two_way_corridor_scene()
    start = VehicleState(0.0, np.array([0.0, 0.0, 1.5]), np.zeros(3), math.pi / 2)  # facing the north wall
    world = World(scene, camera=CAM, initial_state=start)
    m = PilotMethod(LookingVlm(3), planner=planner)
    region = GoalRegion([-7.25, 2.8, 0.6], [0.4, 0.4, 0.6])
    instruction = f"Fly {heading} along the corridor and stop next to the red crate."
    r, plans = fly(world, m, instruction, region, limit_s=60.0 if heading == "west" else 30.0)
    legs = [np.asarray(e.data["target"]) for e in m.pilot.events if e.kind == "search_explore" and e.data["target"] is not None]
    assert legs, "the search flew no leg"
    sign = -1.0 if heading == "west" else 1.0
    assert all(sign * leg[0] > 1.0 for leg in legs), legs
    starts = [e for e in m.pilot.events if e.kind == "search_start"]
    assert starts and starts[0].data["heading"] == pytest.approx(math.pi if heading == "west" else 0.0)
    if heading == "west":
        assert r.end_reason == "stopped" and r.metrics.success and not r.metrics.collided
    assert_plans_inside(world, plans)


def test_the_pilot_reads_a_compass_heading_as_a_yaw_of_its_world_frame(planner):
    """East is yaw 0 of an ENU world frame (the default); an onboard flight anchored at its
    take-off heading says where east lies instead (``set_east_yaw``); with east unknown, or
    the switch off, no heading is read."""
    def route(instruction, east=0.0, **search):
        pilot = OnFlyPilot(PilotConfig(search=SearchConfig(**search)), LookingVlm(3), ClockRuntime(), planner=planner)
        pilot.begin(instruction, 0.0)
        pilot.set_east_yaw(east)
        return pilot._route_yaw()

    assert route("Fly north along the road.") == pytest.approx(math.pi / 2)
    assert route("Fly east along the road.", east=math.radians(-75.0)) == pytest.approx(math.radians(-75.0))
    assert route("Fly west along the road.", east=math.radians(-75.0)) == pytest.approx(math.radians(105.0))
    assert route("Fly east along the road.", east=None) is None
    assert route("Fly east along the road.", compass=False) is None
    assert route("Fly along the north aisle.") is None
    # before the decomposition a two-step instruction's heading is not the first step's
    assert route("Fly to the gate, then head west along the road.") is None
