"""The default ESDF on a real depth camera's holes: unknown is not free.

Constructed scenes with exact depth (a wall perpendicular to a level camera, a ground plane,
sky and a patch of no readings), the knownness queries against a reference computed here from
the pinhole model, and the planner (``Planner.step`` with the map) in front of a hole in a wall.
"""

import dataclasses
import types

import numpy as np
import pytest

from planning.camera import PinholeCamera
from planning.esdf import EsdfError, EsdfMap
from planning.esdf_config import EsdfConfig, EsdfConfigError
from planning.esdf_occupancy import _hole_reach, free_reach
from planning.planner import Planner, map_frame
from planning.planner_config import PlannerConfig
from planning.trajectory import VehicleState

CAMERA = PinholeCamera.from_fov(640, 480, 90.0, 60.0)
HOLE_5M = (20 * 5.0 / CAMERA.fx, 20 * 5.0 / CAMERA.fy)  # half-sizes (y, z) m of 40 x 40 px at 5 m
ROT_LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical z = world +x
HEIGHT_M = 1.5
DEFAULT = EsdfConfig()


def pose(p) -> np.ndarray:
    """T_world_cam of a level camera at ``p`` looking along world +x."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = ROT_LOOK_X, p
    return T


def wall_depth(p, wall_x_m, hole_half_m=None, hole_center=(0.0, HEIGHT_M)):
    """z-depth (h, w) of a wall x = wall_x_m seen from a level camera at ``p``; pixels whose
    ray meets the wall inside the rectangular hole (world-fixed, half-sizes hole_half_m (y, z)
    around (y, z) = hole_center) have no reading (0)."""
    zd = np.float32(wall_x_m - p[0])
    depth = np.full(CAMERA.shape, zd, dtype=np.float32)
    if hole_half_m is not None:
        rays = CAMERA.rays()  # z = 1
        y = p[1] - rays[..., 0] * zd
        z = p[2] - rays[..., 1] * zd
        hy, hz = (hole_half_m, hole_half_m) if np.isscalar(hole_half_m) else hole_half_m
        hole = (np.abs(y - hole_center[0]) < hy) & (np.abs(z - hole_center[1]) < hz)
        depth[hole] = 0.0
    return depth


def ground_depth(p, max_reading_m=np.inf):
    """z-depth of a ground plane z = 0 from a level camera at ``p``: sky (no reading, inf) above
    the horizon; ground beyond ``max_reading_m`` is no reading too (0), as a D435 past range."""
    rays = CAMERA.rays() @ ROT_LOOK_X.T  # world direction per pixel, optical z = 1
    with np.errstate(divide="ignore"):
        t = np.where(rays[..., 2] < 0, -p[2] / rays[..., 2], np.inf)
    depth = t.astype(np.float32)
    depth[np.isfinite(depth) & (depth > max_reading_m)] = 0.0
    return depth


def hole_in_the_wall_map(cfg=DEFAULT):
    esdf = EsdfMap(cfg)
    p = np.array([0.0, 0.0, HEIGHT_M])
    depth = wall_depth(p, 5.0, hole_half_m=HOLE_5M)
    assert (depth == 0).sum() == 40 * 40  # the 40 x 40 px patch
    esdf.integrate(depth, CAMERA, pose(p))
    return esdf


# -- the hole in the wall ----------------------------------------------------------------------
def test_hole_in_a_wall_is_not_open_space():
    esdf = hole_in_the_wall_map()
    # through the hole and around it, behind the wall: never known, never free
    ys, zs = np.meshgrid(np.linspace(-1.0, 1.0, 21), np.linspace(HEIGHT_M - 1.0, HEIGHT_M + 1.0, 21))
    for x in (5.15, 5.5, 6.0, 7.0, 7.5):
        P = np.stack([np.full(ys.size, x), ys.ravel(), zs.ravel()], axis=1)
        assert not esdf.known(P).any() and not esdf.observed_free(P).any()
        assert np.all(esdf.query(P)[0] <= 0.0)
    # the wall's own layer: occupied around the hole, unknown in it, free nowhere
    P = np.stack([np.full(ys.size, 5.05), ys.ravel(), zs.ravel()], axis=1)
    assert not esdf.observed_free(P).any() and np.all(esdf.query(P)[0] <= 0.0)
    assert not esdf.known(np.array([[5.05, 0.0, HEIGHT_M]]))[0]
    # in the hole's direction the space is free only up to the no-reading bound (4.5 m)
    ahead = np.array([[x, 0.0, HEIGHT_M] for x in (1.0, 2.0, 3.0, 4.0, 4.3)])
    assert esdf.observed_free(ahead).all()
    assert not esdf.known(np.array([[4.6, 0.0, HEIGHT_M]]))[0]
    # beside the hole the wall's readings clear up to the wall
    assert esdf.observed_free(np.array([[4.8, 1.5, HEIGHT_M]]))[0]
    # the old optimistic map (the measured bug): free space behind the wall through the hole
    old = hole_in_the_wall_map(dataclasses.replace(DEFAULT, unknown_policy="free"))
    assert old.query(np.array([[7.0, 0.0, HEIGHT_M]]))[0][0] == pytest.approx(old.config.max_distance_m)


def fly_level_at_wall(wall_x_m, hole_half_m, goal_x_m, steps, cfg=DEFAULT):
    """Closed loop on the modelled clock: level flight along the hole's axis (the worst case)
    toward a goal at ``goal_x_m``; the vehicle re-senses the wall (its hole world-fixed) at
    every step and flies the first knot of each plan. Returns the plans and the final state."""
    planner = Planner(PlannerConfig())
    esdf = EsdfMap(cfg)
    goal = np.array([goal_x_m, 0.0, HEIGHT_M])
    state = VehicleState(0.0, np.array([0.0, 0.0, HEIGHT_M]), np.zeros(3), 0.0)
    plans = []
    for _ in range(steps):
        p = state.p.copy()
        p[1:] = [0.0, HEIGHT_M]
        esdf.integrate(wall_depth(p, wall_x_m, hole_half_m=hole_half_m), CAMERA, pose(p), center_world=state.p)
        plan = planner.step(state, goal, esdf)
        plans.append(plan)
        tr = plan.trajectory
        state = VehicleState(state.t_s + tr.dt_s, tr.p[1], tr.v[1], float(tr.yaw[1]))
    return plans, state


def test_planner_does_not_plan_through_the_hole():
    """Toward a goal 2 m behind the wall, through the issue's 40 x 40 px hole."""
    d_safe = PlannerConfig().d_safe_m
    plans, state = fly_level_at_wall(5.0, HOLE_5M, 7.0, 40)
    assert all(pl.trajectory.p[:, 0].max() < 5.0 - d_safe + 0.1 and pl.goal_used[0] < 5.0 for pl in plans)
    assert state.p[0] < 5.0 - d_safe + 0.1
    assert max(pl.trajectory.p[:, 0].max() for pl in plans) > 2.0  # it flew toward the wall: no freeze


# -- unknown space and the body sphere -----------------------------------------------------------
def test_unknown_space_behind_the_camera_is_not_free():
    esdf = EsdfMap(DEFAULT)
    p = np.array([0.0, 0.0, HEIGHT_M])
    esdf.integrate(wall_depth(p, 4.0), CAMERA, pose(p))
    behind = np.array([[-x, y, HEIGHT_M] for x in (1.5, 2.0, 3.0, 5.0) for y in (-1.0, 0.0, 1.0)])
    assert not esdf.known(behind).any()
    assert not esdf.is_free(behind).any()
    assert np.all(esdf.query(behind)[0] <= 0.0)
    # outside the window: not known, an obstacle
    far = np.array([[-20.0, 0.0, HEIGHT_M]])
    assert not esdf.known(far)[0] and esdf.query(far)[0][0] < -10.0


def test_body_sphere_is_free_and_never_overrides_an_observation():
    cfg = DEFAULT
    esdf = EsdfMap(cfg)
    p = np.array([0.0, 0.0, HEIGHT_M])
    esdf.integrate(wall_depth(p, 4.0), CAMERA, pose(p))
    r = cfg.body_clear_radius_m
    dirs = np.array([[-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, -1], [-0.6, 0.8, 0]], dtype=float)
    inside = p + (r - 0.1) * dirs
    outside = p + (r + 0.15) * dirs[[0, 3]]  # behind, below: out of view
    assert esdf.observed_free(inside).all()
    assert not esdf.known(outside).any()
    # above the vehicle only up to body_clear_above_m: the camera never saw the ceiling there
    up = cfg.body_clear_above_m
    assert esdf.observed_free(p + [[0.0, 0.0, up - 0.05], [-0.5, 0.3, up - 0.05]]).all()
    assert not esdf.known(p + [[0.0, 0.0, up + 0.1], [-0.5, 0.3, up + 0.1], [-0.9, 0.0, up + 0.1]]).any()
    # the vehicle's own position has room for the planner's safety distance
    assert esdf.query(p[None])[0][0] >= PlannerConfig().d_safe_m + 0.1
    # an obstacle seen inside the sphere stays an obstacle
    near = EsdfMap(cfg)
    near.integrate(wall_depth(p, 0.9), CAMERA, pose(p))
    assert near.occupied_grid.any()
    wall_pt = np.array([[0.95, 0.0, HEIGHT_M]])
    assert near.known(wall_pt)[0] and not near.observed_free(wall_pt)[0]
    assert near.query(wall_pt)[0][0] <= 0.0
    # mark_free_sphere: unknown only, and bad input named
    assert near.mark_free_sphere([0.95, 0.0, HEIGHT_M], 0.3) >= 0
    assert not near.observed_free(wall_pt)[0]
    with pytest.raises(EsdfError, match="radius_m"):
        near.mark_free_sphere(p, -1.0)
    with pytest.raises(EsdfError, match="center_world"):
        near.mark_free_sphere([0.0, np.nan, 0.0], 1.0)
    with pytest.raises(EsdfError, match="body_world"):
        near.integrate(wall_depth(p, 2.0), CAMERA, pose(p), body_world=[0.0, 0.0])


def _approach_dark_patch(cfg: EsdfConfig, stops_m) -> tuple[EsdfMap, np.ndarray]:
    """A level camera flown at a wall x = 3 m whose middle square metre gives no reading (a
    dark machine's face, a glass pane), stopping at the given distances from it. Returns the
    map and points (k, 3) on the wall's plane inside the patch."""
    esdf = EsdfMap(cfg)
    for d in stops_m:
        p = np.array([3.0 - d, 0.0, HEIGHT_M])
        esdf.integrate(wall_depth(p, 3.0, hole_half_m=0.5), CAMERA, pose(p), center_world=p)
    ys, zs = np.meshgrid(np.linspace(-0.3, 0.3, 7), np.linspace(HEIGHT_M - 0.3, HEIGHT_M + 0.3, 7))
    patch = np.stack([np.full(ys.size, 3.05), ys.ravel(), zs.ravel()], axis=1)
    return esdf, patch


def test_body_sphere_never_clears_what_the_camera_looks_at():
    """Closing in on a surface without readings: the patch's row and column bound its clearing
    to the wall's depth minus the margin, and the body sphere (1.2 m) must not erase it when the
    vehicle comes within reach. The old sphere, which cleared in view, does: that is the hazard."""
    stops = (3.0, 2.0, 1.4, 1.0, 0.8, 0.6)
    esdf, patch = _approach_dark_patch(DEFAULT, stops)
    assert not esdf.observed_free(patch).any()
    assert np.all(esdf.query(patch)[0] <= 0.0)
    # the vehicle, 0.6 m out, reads the wall as at most the patch's distance away, never more
    p = np.array([[3.0 - stops[-1], 0.0, HEIGHT_M]])
    assert esdf.query(p)[0][0] <= stops[-1] + 0.05
    old, patch = _approach_dark_patch(dataclasses.replace(DEFAULT, body_clear_in_view=True), stops)
    assert old.observed_free(patch).all()
    # out of view the sphere still clears: below a level camera, 1 m down at 0.4 m ahead
    below = np.array([[3.0 - stops[-1] + 0.4, 0.0, HEIGHT_M - 1.0]])
    assert esdf.observed_free(below)[0]


def test_body_sphere_remembers_what_earlier_frames_looked_at():
    """The dark patch approached to 0.6 m, then the vehicle turns 90 deg left (a turn toward a
    goal, a gust): the patch is beside the view and inside the 1.2 m sphere. The frames that
    looked at it from within the no-reading reach keep it unknown; with no memory of them
    (body_clear_recent_views=0) the sphere erases it, as it did to factory_hall-l02's belt."""
    stops = (3.0, 2.0, 1.4, 1.0, 0.8, 0.6)
    look_y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # optical z = world +y
    p = np.array([3.0 - stops[-1], 0.0, HEIGHT_M])
    turned = np.eye(4)
    turned[:3, :3], turned[:3, 3] = look_y, p
    beyond = np.full(CAMERA.shape, 6.0, dtype=np.float32)  # a wall 6 m to the left

    def approach_and_turn(cfg):
        esdf, patch = _approach_dark_patch(cfg, stops)
        esdf.integrate(beyond, CAMERA, turned, center_world=p)
        return esdf, patch

    esdf, patch = approach_and_turn(DEFAULT)
    assert not esdf.observed_free(patch).any() and np.all(esdf.query(patch)[0] <= 0.0)
    forgetful, patch = approach_and_turn(dataclasses.replace(DEFAULT, body_clear_recent_views=0))
    assert forgetful.observed_free(patch).all()
    # what no frame looked at is still filled in: at the start, below a level camera that has
    # hovered for a few frames, 1 m down and 0.4 m ahead
    start = np.array([0.0, 0.0, HEIGHT_M])
    hover = EsdfMap(DEFAULT)
    for _ in range(4):
        hover.integrate(wall_depth(start, 4.0), CAMERA, pose(start), center_world=start)
    assert hover.observed_free(np.array([[0.4, 0.0, HEIGHT_M - 1.0]]))[0]
    for bad in (-1, 2.5, True):
        with pytest.raises(EsdfConfigError, match="body_clear_recent_views"):
            dataclasses.replace(DEFAULT, body_clear_recent_views=bad)


def test_body_sphere_grows_by_the_planners_tracking_margin():
    """Out of view (below a level camera) the sphere reaches body_clear_radius_m plus the margin
    the caller passes, and no further; a bad margin is named."""
    p = np.array([0.0, 0.0, HEIGHT_M])
    r = DEFAULT.body_clear_radius_m
    below = np.array([[0.0, 0.0, HEIGHT_M - (r + 0.3)]])
    plain, grown = EsdfMap(DEFAULT), EsdfMap(DEFAULT)
    plain.integrate(wall_depth(p, 4.0), CAMERA, pose(p))
    grown.integrate(wall_depth(p, 4.0), CAMERA, pose(p), body_margin_m=0.4)
    assert not plain.known(below)[0] and grown.observed_free(below)[0]
    beyond = np.array([[0.0, 0.0, HEIGHT_M - (r + 0.5)]])
    assert not grown.known(beyond)[0]
    # what the camera looks at is left to it whatever the margin: the wall's unknown shell
    shell = np.array([[3.95, 0.0, HEIGHT_M]])
    near = EsdfMap(DEFAULT)
    q = np.array([3.0, 0.0, HEIGHT_M])
    near.integrate(wall_depth(q, 4.0), CAMERA, pose(q), body_margin_m=1.0)
    assert not near.observed_free(shell)[0]
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(EsdfError, match="body_margin_m"):
            grown.integrate(wall_depth(p, 4.0), CAMERA, pose(p), body_margin_m=bad)


def test_map_frame_grows_the_sphere_by_the_planners_margin_and_not_without_a_planner():
    """planning.planner.map_frame is the one pairing of a map and its planner per frame: the
    planner's tracking margin reaches the sphere; a method without a planner gets the bare one."""
    p = np.array([0.0, 0.0, HEIGHT_M])
    below = np.array([[0.0, 0.0, HEIGHT_M - (DEFAULT.body_clear_radius_m + 0.3)]])
    shaken = types.SimpleNamespace(tracking_margin_m=0.4)  # what a planner reports after gusts
    with_planner, without = EsdfMap(DEFAULT), EsdfMap(DEFAULT)
    map_frame(with_planner, shaken, wall_depth(p, 4.0), CAMERA, pose(p), p)
    map_frame(without, None, wall_depth(p, 4.0), CAMERA, pose(p), p)
    assert with_planner.observed_free(below)[0]
    assert not without.known(below)[0]


def test_planner_does_not_close_in_on_a_surface_without_readings():
    """Toward a goal 1 m behind a wall whose middle square metre has no reading: the plans stop
    d_safe short of the wall's plane (the old sphere, clearing in view, let them through)."""
    d_safe = PlannerConfig().d_safe_m
    plans, _ = fly_level_at_wall(3.0, 0.5, 4.0, 60)
    assert all(pl.trajectory.p[:, 0].max() < 3.0 - d_safe + 0.1 for pl in plans)
    assert max(pl.trajectory.p[:, 0].max() for pl in plans) > 1.5  # it flew toward the wall: no freeze
    old, _ = fly_level_at_wall(3.0, 0.5, 4.0, 60, cfg=dataclasses.replace(DEFAULT, body_clear_in_view=True))
    assert max(pl.trajectory.p[:, 0].max() for pl in old) > 3.0 - d_safe + 0.1


def test_no_reading_never_clears_an_observed_obstacle_and_a_blind_frame_clears_nothing():
    esdf = EsdfMap(DEFAULT)
    p = np.array([0.0, 0.0, HEIGHT_M])
    for _ in range(3):
        esdf.integrate(wall_depth(p, 6.5, hole_half_m=None), CAMERA, pose(p))
    box = np.array([[2.05, 0.0, HEIGHT_M]])
    depth = wall_depth(p, 6.5)
    rays = CAMERA.rays()
    near = (np.abs(rays[..., 0] * 2.0) < 0.2) & (np.abs(rays[..., 1] * 2.0) < 0.2)
    depth[near] = 2.0  # a 0.4 m box at 2 m
    esdf.integrate(depth, CAMERA, pose(p))
    assert not esdf.observed_free(box)[0] and esdf.known(box)[0]
    depth[near] = 0.0  # the box turns dark: no readings where it is, the wall around it
    for _ in range(8):
        esdf.integrate(depth, CAMERA, pose(p))
    assert not esdf.observed_free(box)[0], "a no-reading pixel cleared an observed obstacle"
    # a frame without any reading clears nothing new
    blind = EsdfMap(DEFAULT)
    blind.integrate(np.zeros(CAMERA.shape, np.float32), CAMERA, pose(p))
    ahead = np.array([[x, 0.0, HEIGHT_M] for x in (1.5, 2.0, 3.0)])
    assert not blind.known(ahead).any()


@pytest.mark.parametrize("ground_range_m", [np.inf, 7.0])
def test_open_ground_under_the_sky_leaves_room_to_fly(ground_range_m):
    """Outdoors a level camera at 1.5 m sees the ground from ~2.6 m and sky above the horizon
    (no reading; with a D435-like range, the far ground too): the space the vehicle flies
    through must still be seen free, or it could never move."""
    esdf = EsdfMap(DEFAULT)
    p = np.array([0.0, 0.0, HEIGHT_M])
    depth = ground_depth(p, ground_range_m)
    assert (~np.isfinite(depth) | (depth == 0)).mean() >= 0.5
    esdf.integrate(depth, CAMERA, pose(p))
    d_safe = PlannerConfig().d_safe_m
    path = np.array([[x, 0.0, HEIGHT_M] for x in np.arange(0.0, 3.61, 0.2)])
    assert esdf.observed_free(path).all()
    assert esdf.query(path)[0].min() > d_safe, esdf.query(path)[0]
    # the ground stays an obstacle
    assert esdf.query(np.array([[3.0, 0.0, 0.05]]))[0][0] <= 0.0


# -- the reach of a pixel and the knownness queries against a reference --------------------------
def test_free_reach_bounds_holes_by_their_row_and_column():
    cfg = DEFAULT
    depth = np.full((5, 7), 6.0, np.float32)
    depth[0, :] = np.inf  # sky row
    depth[2, 3] = 0.0  # a one-pixel hole
    depth[2, 4] = 1.0  # a near reading next to the hole on its row
    depth[2, 6] = 0.5  # nearer, but behind that one: the scan stops at the first reading
    depth[4, 0] = 9.0  # beyond max range: a reading clipped to 7 m
    reach, valid = free_reach(depth, cfg)
    m = cfg.clear_margin_m
    assert not valid[0].any() and not valid[2, 3] and valid[4, 0]
    assert reach[4, 0] == pytest.approx(cfg.max_range_m - m)
    assert reach[2, 3] == pytest.approx(1.0 - m)  # the nearest reading on its row
    assert reach[0, 1] == pytest.approx(cfg.no_reading_clear_m - m)  # sky: bounded by 4.5 m
    assert reach[1, 1] == pytest.approx(6.0 - m)
    off = free_reach(depth, dataclasses.replace(cfg, no_reading_clear_m=0.0))[0]
    assert np.all(off[~valid] == -np.inf) and np.array_equal(off[valid], reach[valid])


def test_a_hole_that_reaches_the_bottom_edge_clears_nothing():
    """A dark object the vehicle flies beside runs out of the image's bottom edge; the floor
    *behind* it is read on its columns, above it in the image. Those readings bound nothing: its
    pixels clear nothing (the pixel reach of free_reach and of the per-pixel search agree), while
    a hole with a reading below it (a dark patch in a wall) keeps its row-and-column bound."""
    depth = np.full((6, 8), 5.0, np.float32)  # the floor behind, 5 m
    depth[3:, 2:5] = 0.0  # the dark object, from row 3 to the bottom edge
    depth[1, 6] = 0.0  # a patch with readings all round
    reach, valid = free_reach(depth, DEFAULT)
    m = DEFAULT.clear_margin_m
    assert np.all(reach[3:, 2:5] == -np.inf)
    assert reach[1, 6] == pytest.approx(DEFAULT.no_reading_clear_m - m)
    old = free_reach(depth, dataclasses.replace(DEFAULT, no_reading_needs_below=False))[0]
    assert np.all(old[3:, 2:5] == pytest.approx(DEFAULT.no_reading_clear_m - m))  # the old rule cleared it
    rows, cols = np.nonzero(~valid)
    clipped = np.where(valid, np.minimum(depth, DEFAULT.max_range_m), np.inf).astype(np.float32)
    for cfg in (DEFAULT, dataclasses.replace(DEFAULT, no_reading_needs_below=False)):
        np.testing.assert_array_equal(_hole_reach(clipped, valid, rows, cols, cfg), free_reach(depth, cfg)[0][rows, cols])
    with pytest.raises(EsdfConfigError, match="no_reading_needs_below"):
        dataclasses.replace(DEFAULT, no_reading_needs_below=1)


def test_flying_level_beside_a_dark_box_keeps_it_an_obstacle():
    """A level camera 0.9 m up passes 1 m from a dark box 0.9 m tall (no readings; the floor
    behind it is read): the box's voxels never become free (the old rule cleared them)."""
    floor_far = np.float32(6.0)

    def frame(p):
        depth = np.full(CAMERA.shape, floor_far, np.float32)
        rays = CAMERA.rays()  # optical frame, z = 1; the camera looks along world +x
        # the box: x in [p0 + 1.0, p0 + 2.0], |y| < 0.5, z < 0.9; mark the pixels whose ray meets its face
        t = 1.0  # z-depth of the face
        y = p[1] - rays[..., 0] * t
        z = p[2] - rays[..., 1] * t
        depth[(np.abs(y) < 0.5) & (z < 0.9)] = 0.0
        return depth

    box = np.array([[1.3, 0.0, 0.5], [1.5, 0.2, 0.3], [1.2, -0.3, 0.7]])
    for cfg, cleared in ((DEFAULT, False), (dataclasses.replace(DEFAULT, no_reading_needs_below=False), True)):
        esdf = EsdfMap(cfg)
        p = np.array([0.0, 0.0, 0.9])
        esdf.integrate(frame(p), CAMERA, pose(p), center_world=p)
        assert bool(esdf.observed_free(box).any()) is cleared


def _reference_known(esdf: EsdfMap, depth: np.ndarray, p: np.ndarray, reach_of_pixel) -> tuple[np.ndarray, np.ndarray]:
    """(known, hit) bool grids of one frame from the pinhole model, computed independently:
    hit = voxels holding a back-projected point (stride 2); cleared = voxel centres projecting
    into the image with min_range < z < reach; plus the body sphere up to body_clear_above_m."""
    cfg = esdf.config
    C = esdf.voxel_centers().reshape(-1, 3)
    P_cam = (C - p) @ ROT_LOOK_X  # R^T (c - t) as rows
    z = P_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.floor(CAMERA.fx * P_cam[:, 0] / z + CAMERA.cx + 0.5)
        v = np.floor(CAMERA.fy * P_cam[:, 1] / z + CAMERA.cy + 0.5)
    inside = (z > cfg.min_range_m) & (u >= 0) & (u < CAMERA.width) & (v >= 0) & (v < CAMERA.height)
    reach = np.full(len(C), -np.inf)
    reach[inside] = reach_of_pixel(v[inside].astype(int), u[inside].astype(int))
    cleared = inside & (z < reach)
    s = cfg.stride_px
    d = depth[::s, ::s]
    ok = (d >= cfg.min_range_m) & (d < cfg.max_range_m)
    rays = CAMERA.rays()[::s, ::s]
    pts = (rays * d[..., None])[ok] @ ROT_LOOK_X.T + p
    idx = np.floor(pts / cfg.voxel_m).astype(np.int64) - esdf.origin_index
    hit = np.zeros(esdf.shape, bool)
    keep = np.all((idx >= 0) & (idx < np.array(esdf.shape)), axis=1)
    hit[tuple(idx[keep].T)] = True
    body = (np.linalg.norm(C - p, axis=1) <= cfg.body_clear_radius_m) & ~inside  # what the camera cannot see
    if cfg.body_clear_above_m is not None:
        body &= C[:, 2] - p[2] <= cfg.body_clear_above_m
    known = hit | (cleared | body).reshape(esdf.shape)
    return known, hit


def test_knownness_matches_a_pinhole_reference_on_a_wall_with_sky_and_a_hole():
    cfg = DEFAULT
    esdf = EsdfMap(cfg)
    p = np.array([0.03, -0.02, HEIGHT_M])
    # wall at 6.02 m: no voxel centre sits on a clearing bound (float32 ties)
    depth = wall_depth(p, 6.02, hole_half_m=0.4, hole_center=(0.5, HEIGHT_M - 0.2))
    depth[:120] = np.inf  # the top quarter: sky over the wall
    esdf.integrate(depth, CAMERA, pose(p), center_world=p)
    m = cfg.clear_margin_m
    sky_or_hole = ~np.isfinite(depth) | (depth == 0)

    def reach_of_pixel(v, u):
        # every no-reading pixel here has the wall (5.99 m) on its column or row: min(4.5, 5.99)
        return np.where(sky_or_hole[v, u], cfg.no_reading_clear_m - m, depth[v, u].astype(float) - m)

    known_ref, hit_ref = _reference_known(esdf, depth, p, reach_of_pixel)
    known = esdf.known_grid
    assert known_ref.sum() > 100_000
    np.testing.assert_array_equal(known, known_ref)
    np.testing.assert_array_equal(esdf.occupied_grid, hit_ref)
    C = esdf.voxel_centers().reshape(-1, 3)
    sample = np.random.default_rng(0).choice(len(C), 20000, replace=False)
    np.testing.assert_array_equal(esdf.known(C[sample]), known_ref.reshape(-1)[sample])
    np.testing.assert_array_equal(esdf.observed_free(C[sample]), (known_ref & ~hit_ref).reshape(-1)[sample])
    # the hole's voxels behind the clearing bound are unknown; beside it the wall clears more
    assert not esdf.known(np.array([[5.0, 0.5, HEIGHT_M - 0.2]]))[0]
    assert esdf.known(np.array([[5.5, -1.5, HEIGHT_M - 0.2]]))[0]
    # frontier: observed free voxels with an unknown face neighbour, e.g. at the hole's bound
    F = esdf.frontier_points()
    assert len(F) > 0 and esdf.observed_free(F).all()
    assert np.any(np.all(np.abs(F - [4.35, 0.5, HEIGHT_M - 0.2]) < 0.1, axis=1))
    # bad input named
    with pytest.raises(EsdfError, match=r"shape \(n, 3\)"):
        esdf.known(np.zeros((2, 2)))
    with pytest.raises(EsdfError, match="NaN"):
        esdf.observed_free(np.array([[np.nan, 0.0, 0.0]]))


# -- the window covers the verifier's range ---------------------------------------------------------
def test_window_covers_the_verifier_range():
    """A goal check 6.4 m ahead reads the wall 0.4 m further, not a value clamped at the
    window's face (the old 10 m window ended at 5 m)."""
    esdf = EsdfMap(DEFAULT)
    p = np.array([0.0, 0.0, HEIGHT_M])
    esdf.integrate(wall_depth(p, 6.85), CAMERA, pose(p))
    lo, hi = esdf.bounds_world
    assert np.all(hi[:2] - p[:2] >= 7.5) and np.all(p[:2] - lo[:2] >= 7.5)
    d = esdf.query(np.array([[6.4, 0.0, HEIGHT_M], [6.4, 1.0, HEIGHT_M]]))[0]
    np.testing.assert_allclose(d, 0.4, atol=0.1)
    old = EsdfMap(dataclasses.replace(DEFAULT, size_m=(10.0, 10.0, 4.0)))
    old.integrate(wall_depth(p, 6.85), CAMERA, pose(p))
    assert old.query(np.array([[6.4, 0.0, HEIGHT_M]]))[0][0] < 0.0  # outside: read as an obstacle


# -- a glass door rendered from a committed scene (the realistic world profile) ---------------------
def test_glass_door_rendered_from_a_scene_is_not_a_passage():
    """urban_block's glass door and glass tower give no depth readings under the realistic
    profile; the VLM could point through the door into the lobby behind it (free in the truth).
    The default map keeps the door and the lobby unknown, and the planner stops in front."""
    import math

    from onfly.world import World

    start = VehicleState(0.0, np.array([-4.0, -24.0, 1.4]), np.zeros(3), math.pi)  # facing west
    world = World.from_scene("urban_block", realism="realistic", seed=5, initial_state=start)
    obs = world.observe()
    door = obs.annotation.instance_ids == world.scene.object_by_name("glass door").instance_id
    assert door.sum() > 1000 and np.all(obs.depth_m[door] == 0.0)
    door_x = -4.0 - float(np.median(obs.annotation.depth_m[door]))  # about -7.9 m
    lobby = np.array([[x, -24.0, 1.4] for x in (-9.5, -10.5)])
    assert np.all(world.collision.clearance(lobby) > 1.0)  # free space behind the door
    goal = lobby[1]
    planner = Planner(PlannerConfig())
    d_safe = planner.config.d_safe_m
    new = EsdfMap(DEFAULT)
    new.integrate(obs.depth_m, obs.camera, obs.T_world_cam, center_world=obs.position)
    behind = np.array([[x, y, 1.4] for x in (door_x - 0.3, -9.5, -10.5) for y in (-24.5, -24.0, -23.5)])
    assert not new.known(behind).any() and np.all(new.query(behind)[0] <= 0.0)
    plan = planner.step(start, goal, new)
    assert plan.trajectory.p[:, 0].min() > door_x + d_safe - 0.1 and plan.goal_used[0] > door_x
    # the old optimistic map: the door is open space and the plan heads through it
    old = EsdfMap(EsdfConfig(  # the map before the unknown-space policy, with its 1 m clamp
        unknown_policy="free", no_reading_clear_m=0.0, body_clear_radius_m=0.0, size_m=(10.0, 10.0, 4.0), max_distance_m=1.0
    ))
    old.integrate(obs.depth_m, obs.camera, obs.T_world_cam, center_world=obs.position)
    assert np.all(old.query(behind)[0] == old.config.max_distance_m)
    assert Planner(PlannerConfig()).step(start, goal, old).goal_used[0] < door_x


# -- the sphere's cap: a ceiling the camera never saw ---------------------------------------------
class _MapAndBoxes:
    """The map with analytic boxes added (their union): distance and gradient of the nearer."""

    def __init__(self, esdf: EsdfMap, boxes):
        from planning.analytic_field import AnalyticField

        self.esdf, self.boxes = esdf, AnalyticField(boxes=tuple(boxes))

    def query(self, points):
        d1, g1 = self.esdf.query(points)
        d2, g2 = self.boxes.query(points)
        nearer = d2 < d1
        return np.where(nearer, d2, d1), np.where(nearer[:, None], g2, g1)


def _lifted_goal(cfg: EsdfConfig, margin_m: float = 0.0) -> np.ndarray:
    """The goal the goal check gives a vehicle at 1.4 m whose goal is round a corner
    (everything from 0.9 m ahead is a wall here) with a cabinet beside it (top at 1.6 m, side
    0.45 m away): the whole line toward the goal lacks the goal clearance, so it is lifted.
    ``margin_m``: the planner's tracking margin (the sphere and the lift's clearance grow by it)."""
    from planning.analytic_field import Box
    from planning.planner import adjust_goal

    planner_cfg = PlannerConfig()
    clearance = planner_cfg.d_safe_m + planner_cfg.goal_clearance_margin_m
    wall = Box(np.array([3.9, 0.0, 2.5]), np.array([3.0, 5.0, 2.5]))
    cabinet = Box(np.array([0.0, 0.95, 0.8]), np.array([1.5, 0.5, 0.8]))
    esdf = EsdfMap(cfg)
    p = np.array([0.0, 0.0, 1.4])
    esdf.integrate(wall_depth(p, 0.95), CAMERA, pose(p), center_world=p, body_margin_m=margin_m)
    field = _MapAndBoxes(esdf, (wall, cabinet))
    used, _ = adjust_goal(
        np.array([3.0, 0.0, 1.2]), p, field, clearance, planner_cfg.goal_search_max_m, lift_max_m=planner_cfg.goal_lift_max_m,
        lift_margin_m=margin_m,
    )
    return used


def test_the_sphere_never_claims_the_unseen_space_over_the_vehicle():
    """The whole sphere marked free the space up to 1.2 m over the vehicle, which a level
    camera never sees (a 2.6 m ceiling is 1.1 m over a vehicle at 1.5 m), and the goal check
    lifted goals into it; the sphere rose with the vehicle, the next lift started from there,
    and the oracle climbed at 0.3 m/s into the apartment's ceiling (``apartment-o09``; the
    closed loop is ``tests/test_oracle.py``). Capped at ``body_clear_above_m`` the lift finds
    no room over the vehicle in space the camera never saw."""
    planner_cfg = PlannerConfig()
    up = DEFAULT.body_clear_above_m
    # room for the planner's clearance and the guide's margin, none for the smallest lift
    assert up is not None and planner_cfg.d_safe_m + 0.1 <= up < 0.25 + planner_cfg.d_safe_m + planner_cfg.goal_clearance_margin_m
    whole = _lifted_goal(dataclasses.replace(DEFAULT, body_clear_above_m=None))
    assert whole[2] >= 1.4 + 0.25
    # ... into space above the camera's 30 deg upper field edge: never seen
    assert np.degrees(np.arctan2(whole[2] - 1.4, max(whole[0], 1e-9))) > 30.0
    for margin in (0.0, 0.15, 0.3, 0.6):  # the sphere and the lift's clearance grow alike
        assert _lifted_goal(DEFAULT, margin)[2] <= 1.4 + 1e-9
    grown = EsdfMap(DEFAULT)
    p = np.array([0.0, 0.0, HEIGHT_M])
    grown.integrate(wall_depth(p, 3.0), CAMERA, pose(p), center_world=p, body_margin_m=0.3)
    assert grown.known(p + [[0.0, 0.0, up + 0.25]]).all() and not grown.known(p + [[0.0, 0.0, up + 0.4]]).any()
    # the vehicle's own position keeps the planner's clearance and the guide search's margin
    esdf = EsdfMap(DEFAULT)
    p = np.array([0.0, 0.0, HEIGHT_M])
    esdf.integrate(wall_depth(p, 3.0), CAMERA, pose(p), center_world=p)
    assert esdf.query(p[None])[0][0] >= planner_cfg.d_safe_m + 0.1
    assert not esdf.known(np.array([[0.0, 0.0, 2.55], [-0.5, 0.0, 2.3]])).any()
    for bad in (-0.1, float("nan"), float("inf"), True):
        with pytest.raises(EsdfConfigError, match="body_clear_above_m"):
            dataclasses.replace(DEFAULT, body_clear_above_m=bad)


@pytest.mark.parametrize("start", [(0.0, 0.0, HEIGHT_M), (1.4, 2.8, HEIGHT_M)])
def test_the_frustum_edge_leaves_no_unknown_voxel_beside_the_vehicle(start):
    """From a voxel-aligned start, voxel centres lie exactly on the 45 deg edges of a 90 deg
    camera. The sphere's in-view test (float64) put some of them in the image and the clearing
    (float32) put them out of it, so neither marked them: an obstacle 0.21 m from the vehicle
    at the hard set's ``apartment-o02`` start (1.4, 2.8, 1.5), and the oracle never moved. The
    in-view test now takes a centre as looked at only half a pixel inside the image's border."""
    cam = PinholeCamera.from_fov(320, 214, 90.0, 60.0)
    p = np.array(start)
    esdf = EsdfMap(DEFAULT)
    esdf.integrate(np.full((cam.height, cam.width), 3.0, np.float32), cam, pose(p), center_world=p)
    C = esdf.voxel_centers().reshape(-1, 3)
    near = (np.linalg.norm(C - p, axis=1) <= DEFAULT.body_clear_radius_m - 0.1) & (C[:, 2] - p[2] <= DEFAULT.body_clear_above_m - 0.05)
    assert near.sum() > 4000 and esdf.known(C[near]).all()
    assert esdf.query(p[None])[0][0] >= PlannerConfig().d_safe_m + 0.1


def test_the_capped_sphere_is_no_frontier_to_fly_to():
    """The sphere's top (``body_clear_above_m`` over the vehicle) borders unknown space the
    camera never sees; as a frontier it drew the search back along its own trail (the pocket
    test of ``tests/test_search.py`` timed out). The ways on at a height are the horizontal
    faces (``axes=(0, 1)``); all three stay the default."""
    p = np.array([0.0, 0.0, HEIGHT_M])
    esdf = EsdfMap(DEFAULT)
    esdf.integrate(wall_depth(p, 3.0), CAMERA, pose(p), center_world=p)
    top = p[2] + DEFAULT.body_clear_above_m - 0.05
    over = lambda F: F[(np.abs(F[:, 2] - top) < 0.01) & (np.hypot(F[:, 0] - p[0], F[:, 1] - p[1]) < 0.5)]  # noqa: E731
    assert len(over(esdf.frontier_points())) > 10
    assert len(over(esdf.frontier_points(axes=(0, 1)))) == 0
    assert esdf.frontier_points(axes=(0, 1)).shape[0] > 0  # the sphere's rim behind the camera
    with pytest.raises(EsdfError, match="axes"):
        esdf.frontier_points(axes=(3,))
