"""Closed loop: the exact double integrator flown with each step's first command.

Safety is checked against the exact geometry (the analytic field's distance at points sampled
along the executed constant-acceleration path), never against the planner's own prediction.
By default 6 seeded scenes per kind run (24); ``-m slow`` runs 50 per kind (200).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from planning.analytic_field import SCENE_KINDS, AnalyticField, Box, HalfSpace, VerticalCylinder, obstacle_scene
from planning.frames import wrap_angle
from planning.planner import ClosedLoopLog, Fallback, Planner, run_closed_loop
from planning.planner_config import PlannerConfig
from planning.trajectory import VehicleState

CFG = PlannerConfig()
GROUND = HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0]))
GOLDEN = Path(__file__).parent / "golden" / "planner_closed_loop.json"
SAFETY_ALLOWANCE_M = 0.05


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner(CFG)


def fly(planner: Planner, start, goal, field, yaw=0.0, seconds=None) -> ClosedLoopLog:
    planner.reset()
    if seconds is None:
        seconds = 2.0 * np.linalg.norm(np.asarray(goal) - start) / CFG.v_max_mps + 15.0
    return run_closed_loop(
        planner, VehicleState(0.0, start, np.zeros(3), yaw), goal, field, max_steps=int(seconds / CFG.dt_s)
    )


def assert_limits(log: ClosedLoopLog) -> None:
    """Every executed step within 1 % of the speed and yaw-rate limits, and within the
    acceleration *norm* (the commands are scaled onto the ball, so exactly)."""
    assert np.linalg.norm(log.v, axis=1).max() <= CFG.v_max_mps * 1.01
    assert np.linalg.norm(log.a, axis=1).max() <= CFG.a_max_mps2 * (1 + 1e-9)
    assert np.abs(log.yaw_rate).max() <= CFG.yaw_rate_max_rps * 1.01


def run_scene(planner: Planner, kind: str, seed: int) -> None:
    scene = obstacle_scene(kind, seed, clearance_m=CFG.d_safe_m)
    log = fly(planner, scene.start, scene.goal, scene.field, yaw=scene.start_yaw)
    clearance = scene.field.distance(log.sampled_path(8)).min()
    assert clearance >= CFG.d_safe_m - SAFETY_ALLOWANCE_M, (kind, seed, clearance)
    assert log.reached, (kind, seed, log.p[-1], scene.goal)
    np.testing.assert_allclose(log.p[-1], scene.goal, atol=0.15)
    assert_limits(log)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("kind", SCENE_KINDS)
def test_seeded_scenes_reach_the_goal_safely_within_limits(planner, kind, seed):
    run_scene(planner, kind, seed)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(50))
@pytest.mark.parametrize("kind", SCENE_KINDS)
def test_two_hundred_seeded_scenes(planner, kind, seed):
    run_scene(planner, kind, seed)


def test_yaw_follows_the_goal_bearing_not_the_path_tangent(planner):
    field = AnalyticField(cylinders=(VerticalCylinder(np.array([4.0, 0.2]), 0.5, 0.0, 4.0),), half_spaces=(GROUND,))
    start, goal = np.array([0.0, 0.0, 1.2]), np.array([8.0, 0.0, 1.2])
    log = fly(planner, start, goal, field, yaw=1.2)
    assert log.reached
    bearing = np.arctan2(goal[1] - log.p[:-1, 1], goal[0] - log.p[:-1, 0])
    tangent = np.arctan2(log.v[1:, 1], log.v[1:, 0])
    moving = np.linalg.norm(log.v[1:], axis=1) > 0.3
    curving = moving & (np.abs(wrap_angle(tangent - bearing)) > 0.3)
    assert curving.sum() >= 10  # the path really curves around the pillar
    yaw_err = np.abs(wrap_angle(log.yaw[1:] - bearing))
    after_turn = np.arange(len(yaw_err)) * CFG.dt_s > 3.5  # 1.2 rad at 0.4 rad/s, plus settling
    assert yaw_err[curving & after_turn].max() < 0.1
    assert np.abs(wrap_angle(log.yaw[1:] - tangent))[curving & after_turn].max() > 0.25


def test_unreachable_goal_ends_at_the_closest_safe_point_without_oscillation(planner):
    wall = Box(np.array([5.0, 0.0, 4.0]), np.array([0.1, 30.0, 6.0]))
    field = AnalyticField(boxes=(wall,), half_spaces=(GROUND,))
    goal = np.array([7.0, 1.0, 1.2])
    log = fly(planner, np.array([0.0, 0.0, 1.2]), goal, field, seconds=30.0)
    assert not log.reached
    closest = np.array([4.9 - CFG.d_safe_m, 1.0, 1.2])
    np.testing.assert_allclose(log.p[-1], closest, atol=0.03)
    tail = slice(-30, None)  # the last 3 s
    assert np.linalg.norm(log.v[tail], axis=1).max() < 0.01
    assert np.ptp(log.p[tail], axis=0).max() < 0.005
    assert np.abs(log.yaw_rate[-30:]).max() < 0.01
    assert field.distance(log.sampled_path()).min() >= CFG.d_safe_m - SAFETY_ALLOWANCE_M
    # pressed against the wall the QP is hard for ADMM; a non-converged step may reuse the
    # shifted previous plan, but never needs to brake
    fallbacks = [r.fallback for r in log.results]
    assert Fallback.BRAKE not in fallbacks
    assert fallbacks.count(Fallback.SHIFTED) <= 0.1 * len(fallbacks)


def test_start_inside_the_margin_leaves_it(planner):
    wall = AnalyticField(boxes=(Box(np.array([0.0, 1.0, 2.0]), np.array([10.0, 0.1, 2.0])),), half_spaces=(GROUND,))
    start = np.array([0.0, 0.6, 1.2])  # 0.3 m from the wall, 0.15 m inside the margin
    log = fly(planner, start, np.array([4.0, 0.4, 1.2]), wall)
    d = wall.distance(log.sampled_path())
    assert d.min() >= 0.3 - 1e-6  # never closer than where it started
    t_out = np.argmax(wall.distance(log.p) >= CFG.d_safe_m - 0.01) * CFG.dt_s
    assert 0 < t_out <= 1.5
    assert log.reached


def golden_run(planner: Planner) -> dict:
    scene = obstacle_scene("pillars", 0)
    log = fly(planner, scene.start, scene.goal, scene.field, yaw=scene.start_yaw, seconds=6.0)
    every = slice(None, None, 5)
    return {
        "scene": {"kind": "pillars", "seed": 0},
        "config": CFG.to_dict(),
        "steps": len(log.results),
        "p": np.round(log.p[every], 9).tolist(),
        "a": np.round(log.a[every], 9).tolist(),
        "yaw": np.round(log.yaw[every], 9).tolist(),
        "status": [r.status.value for r in log.results],
    }


def test_closed_loop_golden(planner):
    """Regenerate with ONFLY_REGEN_GOLDEN=1 after an intended behaviour change."""
    run = golden_run(planner)
    if os.environ.get("ONFLY_REGEN_GOLDEN") == "1":
        GOLDEN.parent.mkdir(parents=True, exist_ok=True)
        GOLDEN.write_text(json.dumps(run, indent=1) + "\n")
    stored = json.loads(GOLDEN.read_text())
    assert stored["config"] == run["config"], "planner defaults changed: regenerate the golden file"
    assert stored["steps"] == run["steps"]
    assert stored["status"] == run["status"]
    np.testing.assert_allclose(run["p"], stored["p"], atol=1e-4)
    np.testing.assert_allclose(run["a"], stored["a"], atol=1e-3)
    np.testing.assert_allclose(run["yaw"], stored["yaw"], atol=1e-4)
