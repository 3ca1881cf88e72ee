"""The planner as a real-time component: the vehicle's own limits, the flight volume, budgets."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from planning.analytic_field import AnalyticField, Box, HalfSpace, obstacle_scene
from planning.guide_path import guide_search
from planning.planner import Fallback, Planner, SolveStatus, run_closed_loop
from planning.planner_config import PlannerConfig, PlannerConfigError
from planning.trajectory import VehicleState
from planning.volume import FlightVolume

CFG = PlannerConfig()
GROUND = HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0]))


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner(CFG)


def fly(planner: Planner, scene, seconds: float | None = None, **kw):
    planner.reset()
    if seconds is None:
        seconds = 2.0 * np.linalg.norm(scene.goal - scene.start) / planner.config.v_max_mps + 15.0
    return run_closed_loop(
        planner,
        VehicleState(0.0, scene.start, np.zeros(3), scene.start_yaw),
        scene.goal,
        scene.field,
        max_steps=int(seconds / planner.config.dt_s),
        **kw,
    )


# ---------------------------------------------------------------- acceleration norm
def test_norm_mode_commands_never_exceed_the_norm_and_per_axis_mode_does():
    """The overhang scene needs a climb and a swerve at once: per axis the norm reaches
    sqrt(2..3) a_max; with the norm limit (default) no command exceeds a_max."""
    scene = obstacle_scene("overhang", 0, clearance_m=CFG.d_safe_m)
    norm_log = fly(Planner(CFG), scene)
    axis_log = fly(Planner(dataclasses.replace(CFG, accel_limit_mode="per_axis")), scene)
    assert norm_log.reached and axis_log.reached
    assert np.linalg.norm(norm_log.a, axis=1).max() <= CFG.a_max_mps2 * (1 + 1e-9)
    assert np.abs(axis_log.a).max() <= CFG.a_max_mps2 * (1 + 1e-9)
    assert np.linalg.norm(axis_log.a, axis=1).max() > CFG.a_max_mps2 * 1.2
    # every plan (not only its first command) is within the norm
    for res in norm_log.results:
        assert np.linalg.norm(res.trajectory.a, axis=1).max() <= CFG.a_max_mps2 * (1 + 1e-9)


def test_reference_nlp_bounds_the_acceleration_norm():
    pl = Planner(CFG, solver="nlp")
    field = AnalyticField(half_spaces=(GROUND,))
    # a goal up and to the side: the unconstrained optimum pushes on two axes at once
    res = pl.step(VehicleState(0.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0), np.array([5.0, 5.0, 4.0]), field)
    assert res.ok
    norms = np.linalg.norm(res.trajectory.a, axis=1)
    assert norms.max() <= CFG.a_max_mps2 * (1 + 1e-6)
    assert norms.max() >= CFG.a_max_mps2 * 0.95  # the limit is active, not avoided


def test_config_rejects_bad_new_fields():
    with pytest.raises(PlannerConfigError, match="accel_limit_mode"):
        PlannerConfig(accel_limit_mode="box")
    with pytest.raises(PlannerConfigError, match="body_radius_m"):
        PlannerConfig(body_radius_m=0.5)
    with pytest.raises(PlannerConfigError, match="guide_floor_m"):
        PlannerConfig(guide_floor_m=2.0, guide_ceiling_m=1.0)
    with pytest.raises(PlannerConfigError, match="guide_max_cells"):
        PlannerConfig(guide_max_cells=0)
    with pytest.raises(PlannerConfigError, match="step_time_budget_ms"):
        PlannerConfig(step_time_budget_ms=-1.0)
    assert PlannerConfig.from_dict(PlannerConfig(guide_floor_m=0.3).to_dict()).guide_floor_m == 0.3


# ---------------------------------------------------------------- flight volume
def test_no_plan_point_leaves_the_volume_flying_toward_a_goal_outside_it(planner):
    volume = FlightVolume(np.array([-1.0, -2.0, 0.0]), np.array([5.0, 2.0, 2.0]))
    field = AnalyticField(boxes=(Box(np.array([2.5, 0.0, 1.0]), np.array([0.3, 0.6, 1.0])),), half_spaces=(GROUND,))
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([9.0, 3.0, 2.8])  # outside on x, y and z
    planner.reset()
    p, v, yaw = start.copy(), np.zeros(3), 0.0
    inner = volume.shrunk(CFG.body_radius_m)
    dt = CFG.dt_s
    for k in range(300):
        res = planner.step(VehicleState(k * dt, p, v, yaw), goal, field, volume=volume)
        assert np.all(volume.contains(res.trajectory.p)), k
        assert np.all(inner.contains(res.trajectory.p[1:], margin_m=-0.02)), k
        assert res.goal_adjusted and np.all(inner.contains(res.goal_used, margin_m=-1e-9))
        a = res.command.a
        p, v, yaw = p + v * dt + 0.5 * a * dt * dt, v + a * dt, yaw + res.command.yaw_rate * dt
    np.testing.assert_allclose(p, inner.max_m, atol=0.1)  # at the corner nearest the goal
    assert np.linalg.norm(v) < 0.05
    assert field.distance(p[None])[0] >= CFG.d_safe_m - 0.05


def test_start_outside_the_volume_is_braked_back_not_failed(planner):
    volume = FlightVolume(np.array([-5.0, -5.0, 0.0]), np.array([5.0, 5.0, 3.0]))
    field = AnalyticField(half_spaces=(GROUND,))
    planner.reset()
    # 0.1 m beyond the shrunk box and still moving out at 0.5 m/s
    res = planner.step(VehicleState(0.0, np.array([4.85, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), 0.0),
                       np.array([0.0, 0.0, 1.0]), field, volume=volume)
    assert res.status is SolveStatus.SOLVED and res.ok
    assert res.command.a[0] < -0.5 * CFG.a_max_mps2
    assert res.trajectory.p[-1, 0] <= 4.75 + 0.02


def test_nlp_keeps_the_volume_too():
    pl = Planner(CFG, solver="nlp")
    volume = FlightVolume(np.array([-5.0, -5.0, 0.0]), np.array([2.0, 5.0, 3.0]))
    res = pl.step(VehicleState(0.0, np.array([0.0, 0.0, 1.0]), np.array([0.5, 0.0, 0.0]), 0.0),
                  np.array([8.0, 0.0, 1.0]), AnalyticField(half_spaces=(GROUND,)), volume=volume)
    assert res.ok
    assert res.trajectory.p[:, 0].max() <= 2.0 - CFG.body_radius_m + 1e-6


# ---------------------------------------------------------------- guide search limits
class UnknownLeft:
    """Free space above the ground, with everything at y > 0.3 reported as unknown."""

    def __init__(self, field: AnalyticField) -> None:
        self._field = field

    def query(self, points):
        return self._field.query(points)

    def is_unknown(self, points):
        return np.asarray(points)[:, 1] > 0.3


class KnownRight:
    """The ESDF's form of the same thing: ``known(points)`` true only at y <= 0.3."""

    def __init__(self, field: AnalyticField) -> None:
        self._field = field

    def query(self, points):
        return self._field.query(points)

    def known(self, points):
        return np.asarray(points)[:, 1] <= 0.3


def wall_with_gaps() -> AnalyticField:
    """A wall across x = 3 (y in [-2, 2], z up to 1.6) with open space around its ends and
    above it: the shortest way is over the top."""
    wall = Box(np.array([3.0, 0.0, 0.8]), np.array([0.1, 2.0, 0.8]))
    return AnalyticField(boxes=(wall,), half_spaces=(GROUND,))


def test_guide_search_respects_the_ceiling_floor_and_box():
    field = wall_with_gaps()
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([6.0, 0.0, 1.0])
    over = guide_search(field, start, goal, 0.55, 1.0)
    assert over.path is not None and over.path[:, 2].max() > 1.6 + 0.55  # over the top
    capped = guide_search(field, start, goal, 0.55, 1.0, z_min_m=0.6, z_max_m=1.8)
    assert capped.path is not None
    inner = capped.path[1:-1]
    assert inner[:, 2].max() <= 1.8 + 1e-9 and inner[:, 2].min() >= 0.6 - 1e-9
    assert np.abs(inner[:, 1]).max() > 2.0 + 0.55 - 1e-9  # around an end instead
    boxed = guide_search(field, start, goal, 0.55, 1.0, z_max_m=1.8,
                         bounds=(np.array([-1.0, -1.0, 0.0]), np.array([7.0, 6.0, 3.0])))
    assert boxed.path is not None
    assert boxed.path[1:-1, 1].min() >= -1.0 - 1e-9 and boxed.path[1:-1, 1].max() > 2.5  # the +y end


def test_guide_search_treats_unknown_space_as_blocked():
    field = wall_with_gaps()
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([6.0, 0.0, 1.0])
    for wrapped in (UnknownLeft(field), KnownRight(field)):
        path = guide_search(wrapped, start, goal, 0.55, 1.0, z_max_m=1.8).path
        assert path is not None and path[1:-1, 1].max() <= 0.3 and path[1:-1, 1].min() < -2.5
    assert guide_search(UnknownLeft(field), start, goal, 0.55, 1.0, z_max_m=1.8, unknown_blocked=False).path is not None


def test_planner_guide_stays_under_the_volume_ceiling():
    field = wall_with_gaps()
    volume = FlightVolume(np.array([-2.0, -8.0, 0.0]), np.array([9.0, 8.0, 2.0]))
    pl = Planner(CFG)
    scene = type("S", (), {"start": np.array([0.0, 0.0, 1.0]), "goal": np.array([6.0, 0.0, 1.0]), "field": field, "start_yaw": 0.0})
    pl.reset()
    p, v = scene.start.copy(), np.zeros(3)
    guided = 0
    for k in range(400):
        res = pl.step(VehicleState(k * 0.1, p, v, 0.0), scene.goal, field, volume=volume)
        if pl._guide is not None:
            guided += 1
            assert pl._guide[1:, 2].max() <= 2.0 - CFG.body_radius_m + 1e-9
        assert res.trajectory.p[:, 2].max() <= 2.0 - CFG.body_radius_m + 0.02
        a = res.command.a
        p, v = p + v * 0.1 + 0.005 * a, v + a * 0.1
        if np.linalg.norm(p - scene.goal) < 0.15 and np.linalg.norm(v) < 0.05:
            break
    assert guided > 0
    assert np.linalg.norm(p - scene.goal) < 0.15


# ---------------------------------------------------------------- budgets
def test_guide_search_cut_by_its_time_budget_answers_coarse():
    field = wall_with_gaps()
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([6.0, 0.0, 1.0])
    full = guide_search(field, start, goal, 0.55, 1.0, resolution_m=0.25)
    cut = guide_search(field, start, goal, 0.55, 1.0, resolution_m=0.25, time_budget_s=1e-9)
    assert full.status == "found" and full.resolution_m == pytest.approx(0.25)
    assert cut.status == "budget" and cut.levels_run == 1 and cut.resolution_m == pytest.approx(1.0)
    assert cut.cells < full.cells / 20
    roomy = guide_search(field, start, goal, 0.55, 1.0, resolution_m=0.25, time_budget_s=60.0)
    assert roomy.status == "found" and roomy.levels_run == 3
    np.testing.assert_allclose(roomy.path, full.path)


def test_guide_search_node_budget_bounds_the_grid():
    field = AnalyticField(half_spaces=(GROUND,))
    res = guide_search(field, np.array([0.0, 0.0, 1.0]), np.array([60.0, 40.0, 1.0]), 0.5, 1.0, max_cells=5000)
    assert res.cells <= 5000 and res.path is not None


@pytest.mark.parametrize("seed", range(3))
def test_a_guide_search_cut_by_its_budget_still_yields_safe_commands(seed):
    cfg = dataclasses.replace(CFG, guide_time_budget_ms=1e-6)  # every search stops after its coarsest level
    scene = obstacle_scene("wall", seed, clearance_m=cfg.d_safe_m)
    log = fly(Planner(cfg), scene)
    statuses = {r.guide_status for r in log.results} - {""}
    assert statuses == {"budget"}
    assert scene.field.distance(log.sampled_path(8)).min() >= cfg.d_safe_m - 0.05
    assert np.linalg.norm(log.a, axis=1).max() <= cfg.a_max_mps2 * (1 + 1e-9)


def test_a_step_out_of_time_returns_the_shifted_previous_plan(planner):
    field = AnalyticField(half_spaces=(GROUND,))
    planner.reset()
    goal = np.array([6.0, 0.0, 1.0])
    res = planner.step(VehicleState(0.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0), goal, field)
    assert res.ok
    prev = res.trajectory
    timed = Planner.__new__(Planner)
    timed.__dict__.update(planner.__dict__)
    timed.config = dataclasses.replace(CFG, step_time_budget_ms=1e-9)
    state = VehicleState(0.1, prev.p[1], prev.v[1], float(prev.yaw[1]), 0.0, prev.a[0])
    out = timed.step(state, goal, field)
    assert out.status is SolveStatus.TIMEOUT and out.fallback is Fallback.SHIFTED
    np.testing.assert_allclose(out.command.a, prev.a[1], atol=1e-12)
    np.testing.assert_allclose(out.trajectory.p[:-1], prev.p[1:], atol=1e-9)
    assert out.qp_solves == 0
    assert out.cpu_time_ms > 0 and out.solve_time_ms > 0
