"""Planner.step: inputs, goal adjustment, yaw reference, fallbacks, result consistency."""

from __future__ import annotations

import numpy as np
import pytest

from planning.analytic_field import AnalyticField, Box, HalfSpace
from planning.planner import Fallback, Planner, PlannerInputError, SolveStatus, adjust_goal, run_closed_loop
from planning.planner_config import PlannerConfig
from planning.trajectory import VehicleState

CFG = PlannerConfig()
GROUND = HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0]))


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner(CFG)


def free_field() -> AnalyticField:
    return AnalyticField(half_spaces=(GROUND,))


def box_field() -> AnalyticField:
    """A 2 m cube centred at (3, 0, 1.5) on the ground."""
    return AnalyticField(boxes=(Box(np.array([3.0, 0.0, 1.5]), np.array([1.0, 1.0, 1.5])),), half_spaces=(GROUND,))


def state_at(p, v=(0.0, 0.0, 0.0), yaw=0.0, t=0.0) -> VehicleState:
    return VehicleState(t, np.asarray(p, float), np.asarray(v, float), yaw)


class NanField:
    def query(self, points):
        n = len(points)
        return np.full(n, np.nan), np.zeros((n, 3))


class WrongShapeField:
    def query(self, points):
        return np.ones(len(points) + 1), np.zeros((len(points), 3))


class RejectingField:
    def query(self, points):
        raise ValueError("outside the map")


@pytest.mark.parametrize(
    ("state", "goal", "field", "match"),
    [
        (state_at([0, 0, 1]), np.array([1.0, np.nan, 1.0]), free_field(), "goal_world must be finite"),
        (state_at([0, 0, 1]), np.array([1.0, 2.0]), free_field(), r"goal_world must have shape \(3,\)"),
        (state_at([0, 0, 1]), np.ones((3, 1)), free_field(), r"goal_world must have shape \(3,\)"),
        (state_at([0, 0, 1]), "north", free_field(), r"goal_world must have shape \(3,\)"),
        (np.zeros(7), np.ones(3), free_field(), "state must be a VehicleState"),
        (state_at([0, 0, 1]), np.ones(3), object(), "field must implement DistanceField.query"),
        (state_at([0, 0, 1]), np.ones(3), NanField(), "NaN or inf"),
        (state_at([0, 0, 1]), np.ones(3), WrongShapeField(), r"expected \(\d+,\), \(\d+, 3\)"),
        (state_at([0, 0, 1]), np.ones(3), RejectingField(), "rejected a query: outside the map"),
    ],
)
def test_bad_inputs_raise_a_named_error(planner, state, goal, field, match):
    with pytest.raises(PlannerInputError, match=match):
        planner.step(state, goal, field)
    assert issubclass(PlannerInputError, ValueError)


def test_unknown_solver_lists_the_choices():
    with pytest.raises(ValueError, match=r"solver must be one of \('qp', 'nlp'\)"):
        Planner(CFG, solver="acados")


def test_result_is_consistent_with_its_trajectory(planner):
    planner.reset()
    field = box_field()
    state = state_at([0.0, 0.3, 1.2], v=[0.2, 0.0, 0.0], yaw=0.4, t=12.5)
    res = planner.step(state, np.array([6.0, 0.0, 1.2]), field)
    tr = res.trajectory
    assert res.ok and res.status is SolveStatus.SOLVED and res.fallback is Fallback.NONE
    assert tr.steps == CFG.horizon_steps and tr.dt_s == CFG.dt_s and tr.t0_s == 12.5
    np.testing.assert_array_equal(tr.p[0], state.p)
    np.testing.assert_array_equal(tr.v[0], state.v)
    assert tr.yaw[0] == pytest.approx(0.4)
    np.testing.assert_array_equal(res.command.a, tr.a[0])
    assert res.command.yaw_rate == tr.yaw_rate[0]
    # the trajectory is the exact rollout of its inputs
    np.testing.assert_allclose(tr.v[1:], tr.v[:-1] + CFG.dt_s * tr.a, atol=1e-12)
    np.testing.assert_allclose(tr.p[1:], tr.p[:-1] + CFG.dt_s * tr.v[:-1] + 0.5 * CFG.dt_s**2 * tr.a, atol=1e-12)
    assert res.min_predicted_clearance_m == pytest.approx(field.distance(tr.p[1:]).min())
    assert res.min_predicted_clearance_m >= CFG.d_safe_m - 0.01
    assert not res.goal_adjusted
    np.testing.assert_array_equal(res.goal_used, [6.0, 0.0, 1.2])
    assert res.solve_time_ms > 0 and res.iterations > 0 and res.qp_solves >= CFG.cold_start_iterations
    assert 0.0 <= res.slack_max_m < 0.01
    # the box blocks the straight line: the front-end pulls toward a point beside it
    assert not np.allclose(res.attractor, res.goal_used)


def test_goal_inside_an_obstacle_moves_to_the_nearest_point_with_clearance(planner):
    planner.reset()
    field = box_field()
    target = CFG.d_safe_m + CFG.goal_clearance_margin_m
    res = planner.step(state_at([8.0, 0.0, 1.0]), np.array([3.8, 0.0, 1.0]), field)
    assert res.goal_adjusted
    np.testing.assert_allclose(res.goal_used, [4.0 + target, 0.0, 1.0], atol=2e-3)
    assert field.distance(res.goal_used[None])[0] >= target
    # next to the obstacle (inside d_safe) also counts
    res = planner.step(state_at([8.0, 0.0, 1.0]), np.array([4.2, 0.0, 1.0]), field)
    assert res.goal_adjusted
    np.testing.assert_allclose(res.goal_used, [4.0 + target, 0.0, 1.0], atol=2e-3)


def test_a_goal_on_a_ledge_is_found_above_the_line_toward_it():
    """A target on a ledge 1.6 m up, the vehicle 1.0 m above the ledge and 3 m away, the clearance
    1.1 m: no point of the line between them has it (the ledge is under all of it); the line
    raised finds the point nearest the target that has it, above the vehicle's height. The
    gradient ascent is held to 0.3 m so that the line search decides (under a sundial's plate
    the ascent is trapped, as in the realistic world's terrace-o05)."""
    ledge = HalfSpace(point=np.array([0.0, 0.0, 1.6]), normal=np.array([0.0, 0.0, 1.0]))
    post = Box(np.array([-0.25, -0.25, 1.6]), np.array([0.25, 0.25, 2.6]))
    field = AnalyticField(boxes=(post,), half_spaces=(ledge,))
    goal, vehicle = np.array([-0.3, 0.0, 2.1]), np.array([-3.0, 0.0, 2.6])
    clearance = 1.1
    line = goal + np.linspace(0.0, 1.0, 200)[:, None] * (vehicle - goal)
    assert field.distance(line).max() < clearance
    flat, moved = adjust_goal(goal, vehicle, field, clearance, 0.3)
    assert moved and np.allclose(flat, vehicle, atol=0.05)  # without the lift: where the vehicle is
    lifted, moved = adjust_goal(goal, vehicle, field, clearance, 0.3, lift_max_m=1.0)
    assert moved and field.distance(lifted[None])[0] >= clearance
    assert np.linalg.norm(lifted - goal) < np.linalg.norm(vehicle - goal) - 1.0  # over a metre closer
    assert lifted[2] <= vehicle[2] + 1.0 + 1e-9
    # nothing above the line either (a ceiling 0.5 m over the vehicle): the old answer stands
    ceiling = HalfSpace(point=np.array([0.0, 0.0, 3.1]), normal=np.array([0.0, 0.0, -1.0]))
    low = AnalyticField(boxes=(post,), half_spaces=(ledge, ceiling))
    kept, moved = adjust_goal(goal, vehicle, low, clearance, 0.3, lift_max_m=1.0)
    assert moved and np.allclose(kept, adjust_goal(goal, vehicle, low, clearance, 0.3)[0])


def test_deeply_buried_goal_falls_back_to_the_line_toward_the_vehicle():
    big = AnalyticField(boxes=(Box(np.array([0.0, 0.0, 1.0]), np.array([4.0, 4.0, 4.0])),))
    goal, moved = adjust_goal(np.array([0.0, 0.0, 1.0]), np.array([10.0, 0.0, 1.0]), big, 0.5, 3.0)
    assert moved
    np.testing.assert_allclose(goal, [4.5, 0.0, 1.0], atol=0.03)
    assert big.distance(goal[None])[0] >= 0.5
    same, moved = adjust_goal(np.array([9.0, 0.0, 1.0]), np.array([10.0, 0.0, 1.0]), big, 0.5, 3.0)
    assert not moved and np.array_equal(same, [9.0, 0.0, 1.0])


def test_yaw_reference_is_unwrapped_near_the_current_yaw(planner):
    """Current yaw 3.0 rad, goal bearing -3.0 rad: turn the short way (+0.28 rad), not -6."""
    planner.reset()
    p = np.array([0.0, 0.0, 1.5])
    goal = p + 5.0 * np.array([np.cos(-3.0), np.sin(-3.0), 0.0])
    bearing = np.arctan2(goal[1] - p[1], goal[0] - p[0])
    assert bearing == pytest.approx(-3.0)
    res = planner.step(state_at(p, yaw=3.0), goal, free_field())
    yaw = res.trajectory.yaw
    assert res.command.yaw_rate > 0.0
    assert np.all(np.diff(yaw) >= -1e-6)
    ref = 3.0 + (bearing + 2 * np.pi - 3.0)
    assert yaw.max() <= ref + 0.01 and yaw[-1] == pytest.approx(ref, abs=0.02)


def test_explicit_yaw_reference_replaces_the_bearing_and_is_unwrapped(planner):
    planner.reset()
    p = np.array([0.0, 0.0, 1.5])
    goal = p + np.array([0.1, 0.0, 0.0])  # inside the hold radius: the bearing would be ignored
    res = planner.step(state_at(p, yaw=3.0), goal, free_field(), yaw_ref=-3.0)
    assert res.command.yaw_rate > 0.0  # the short way, +0.28 rad
    assert res.trajectory.yaw[-1] == pytest.approx(3.0 + (2 * np.pi - 6.0), abs=0.02)
    with pytest.raises(PlannerInputError, match="yaw_ref must be finite"):
        planner.step(state_at(p, yaw=3.0), goal, free_field(), yaw_ref=float("nan"))


def test_yaw_is_held_near_the_goal(planner):
    planner.reset()
    p = np.array([1.0, 1.0, 1.0])
    goal = p + np.array([0.1, -0.15, 0.3])  # within yaw_hold_radius_m horizontally
    res = planner.step(state_at(p, yaw=-2.0), goal, free_field())
    np.testing.assert_allclose(res.trajectory.yaw_rate, 0.0, atol=1e-3)
    assert res.ok


def test_start_inside_the_margin_commands_a_way_out(planner):
    planner.reset()
    wall = AnalyticField(boxes=(Box(np.array([0.0, 1.0, 2.0]), np.array([10.0, 0.1, 2.0])),), half_spaces=(GROUND,))
    p = np.array([0.0, 0.6, 1.2])  # 0.3 m from the wall face at y = 0.9
    d0 = wall.distance(p[None])[0]
    assert d0 == pytest.approx(0.3)
    res = planner.step(state_at(p), np.array([5.0, 0.6, 1.2]), wall)
    assert res.fallback is Fallback.NONE
    assert res.command.a[1] < -0.3  # away from the wall (-y)
    d = wall.distance(res.trajectory.p)
    assert np.all(np.diff(d[:6]) > 0)  # clearance grows from the first knot on
    assert d[-1] >= CFG.d_safe_m - 0.01
    assert res.slack_max_m > 0  # the margin is infeasible at first: the slack, not the start, gives


def test_initial_overspeed_is_braked_within_the_relaxed_bound(planner):
    planner.reset()
    res = planner.step(state_at([0, 0, 1.5], v=[1.0, 0.0, 0.0]), np.array([20.0, 0.0, 1.5]), free_field())
    assert res.ok
    speed = np.linalg.norm(res.trajectory.v[1:], axis=1)
    bound = np.maximum(CFG.v_max_mps, 1.0 - CFG.a_max_mps2 * CFG.dt_s * np.arange(1, CFG.horizon_steps + 1))
    assert np.all(speed <= bound * 1.01)
    assert res.command.a[0] == pytest.approx(-CFG.a_max_mps2, abs=1e-3)


def test_failed_solves_fall_back_to_braking_then_to_the_shifted_plan():
    starved = Planner(PlannerConfig(qp_max_iter=1))
    field = free_field()
    s0 = state_at([0, 0, 1.5], v=[0.5, 0.3, 0.0], yaw=0.3)
    r0 = starved.step(s0, np.array([10.0, 0.0, 1.5]), field)
    assert r0.status is SolveStatus.NOT_CONVERGED and r0.fallback is Fallback.BRAKE and not r0.ok
    v_dir = s0.v / np.linalg.norm(s0.v)
    np.testing.assert_allclose(r0.command.a, -CFG.a_max_mps2 * v_dir, atol=1e-12)
    assert r0.command.yaw_rate == 0.0
    assert np.linalg.norm(r0.trajectory.v[-1]) == pytest.approx(0.0, abs=1e-12)
    # one period later the previous (braking) plan, shifted, is still safe: it is reused
    dt = CFG.dt_s
    s1 = VehicleState(dt, s0.p + dt * s0.v + 0.5 * dt * dt * r0.command.a, s0.v + dt * r0.command.a, 0.3, 0.0, r0.command.a)
    r1 = starved.step(s1, np.array([10.0, 0.0, 1.5]), field)
    assert r1.fallback is Fallback.SHIFTED
    np.testing.assert_allclose(r1.command.a, r0.trajectory.a[1], atol=1e-12)


def test_reset_cold_starts_again(planner):
    field = free_field()
    planner.reset()
    r0 = planner.step(state_at([0, 0, 1]), np.array([3.0, 0.0, 1.0]), field)
    r1 = planner.step(state_at([0, 0, 1], t=0.1), np.array([3.0, 0.0, 1.0]), field)
    assert r0.qp_solves >= CFG.cold_start_iterations and r1.qp_solves == 1
    planner.reset()
    r2 = planner.step(state_at([0, 0, 1]), np.array([3.0, 0.0, 1.0]), field)
    assert r2.qp_solves >= CFG.cold_start_iterations
    np.testing.assert_allclose(r2.command.a, r0.command.a, atol=1e-9)


def test_a_refused_plan_is_the_next_linearization_point_so_the_vehicle_does_not_hold_for_good():
    """At rest, every knot of the linearization point is the start, so the clearance cuts are
    all the tangent plane of the nearest obstacle (here the wall on the right). A post ahead on
    the left is in none of them: the plan toward the goal swings through it between knots,
    the check refuses it, and linearized around the hold again the next step posed the same
    problem. The vehicle held for good (the 150's ``park-l02``: 17 s beside a picnic table).
    Linearized around the refused plan, the cuts sit at the post, and after a step or two it
    flies, never inside the margin."""
    wall = Box(np.array([0.0, -0.7, 1.5]), np.array([5.0, 0.1, 1.5]))  # face at y = -0.6
    post = Box(np.array([0.6, 0.55, 1.5]), np.array([0.12, 0.12, 1.5]))
    field = AnalyticField(boxes=(wall, post), half_spaces=(GROUND,))
    start = state_at([0.0, 0.0, 1.5])
    assert field.distance(start.p[None])[0] == pytest.approx(0.6)  # the wall is the nearest
    goal = np.array([4.0, 1.2, 1.5])
    log = run_closed_loop(Planner(CFG), start, goal, field, max_steps=40, stop_when_reached=False)
    fallbacks = [r.fallback for r in log.results]
    # the case needs the first plan refused (it is sensitive to the geometry: a planner change
    # that plans it outright makes this premise, not the behaviour, fail)
    assert fallbacks[0] is not Fallback.NONE
    assert sum(f is not Fallback.NONE for f in fallbacks) <= 4
    assert np.linalg.norm(log.p[-1] - start.p) > 0.8 and np.linalg.norm(log.p[-1] - goal) < np.linalg.norm(start.p - goal) - 0.8
    assert field.distance(log.p).min() >= CFG.d_safe_m - CFG.safety_tolerance_m
