"""A target seen over an obstacle that every straight ray grazes: the pilot routes around it.

The verifier rejects such a target (no pixel of it has a ray clear of the car in front); with
``PilotConfig.route_blocked`` the pilot flies to the free point in front of it
(:func:`planning.approach.approach_point`) and the planner's guide goes round the car.
"""

from dataclasses import replace

import numpy as np
import pytest

from onfly.bench.metrics import GoalRegion
from onfly.pilot import PilotConfig
from onfly.search import SearchConfig
from onfly.world.scene import parse_scene
from onfly.world.world import World
from planning.analytic_field import AnalyticField, Box
from planning.planner import Planner
from test_search import CAM, PilotMethod, SeeingVlm, _box, fly


def car_scene():
    """A 1.3 m high car 2-3.5 m ahead of the start at 1.5 m, and a charger behind it (top 1.4 m):
    the charger's visible band shows only over the car's roof, closer than 0.2 m to it."""
    objects = [
        {"name": "ground", "label": "ground", "instance_id": 1, "color": "#777777", "target": False,
         "parts": [{"type": "plane", "center_m": [0, 0, 0], "size_m": [40, 40]}]},
        {"name": "grey car", "label": "car", "instance_id": 2, "color": "#8899aa", "target": False,
         "parts": [_box([2.75, 0.0, 0.65], [1.5, 2.4, 1.3])]},
        {"name": "green charger", "label": "charger", "instance_id": 3, "color": "#22aa44",
         "parts": [_box([5.0, 0.0, 0.9], [0.3, 2.0, 1.0])]},
    ]
    data = {
        "format": "onfly-scene/1", "name": "car_and_charger",
        "bounds": {"min_m": [-4, -6, 0], "max_m": [10, 6, 4]},
        "start": {"position_m": [0.0, 0.0, 1.5], "yaw_deg": 0},
        "objects": objects,
    }
    return parse_scene(data, "<car_and_charger>")


@pytest.fixture(scope="module")
def planner():
    return Planner(PilotConfig().planner)


REGION = GoalRegion([5.0, 0.0, 0.9], [0.15, 1.0, 0.5])
INSTRUCTION = "Fly to the green charger and stop next to it."


def test_a_target_behind_a_car_is_reached_round_the_car(planner):
    world = World(car_scene(), camera=CAM)
    m = PilotMethod(SeeingVlm(3, min_px=20), planner=planner)
    r, plans = fly(world, m, INSTRUCTION, REGION, limit_s=40.0)
    events = m.pilot.events
    rejected = [e for e in events if e.kind == "decision" and "no_feasible_pixel" in str(e.data.get("reason", "")).lower()]
    routed = [e for e in events if e.kind == "goal_routed"]
    assert rejected, "the case must be a blocked ray"
    assert routed
    car = Box(center=[2.75, 0.0, 0.65], half_extents=[0.75, 1.2, 0.65])
    charger = Box(center=[5.0, 0.0, 0.9], half_extents=[0.15, 1.0, 0.5])
    exact = AnalyticField(boxes=[car, charger])
    for e in routed:
        g = np.asarray(e.data["goal"], float)
        assert g[0] > 3.5, "the routed goal is past the car, in front of the charger"
        assert exact.distance(g[None])[0] >= PilotConfig().planner.d_safe_m
    assert r.end_reason == "stopped" and r.metrics.success and not r.metrics.collided
    # the car is never entered: every plan point keeps the body outside its box
    lo, hi = np.array([2.0, -1.2, 0.0]), np.array([3.5, 1.2, 1.3])
    for pts in plans:
        nearest = np.clip(pts, lo, hi)
        assert np.all(np.linalg.norm(pts - nearest, axis=1) > 0.25)


def test_the_papers_rule_hovers_with_the_target_in_view(planner):
    world = World(car_scene(), camera=CAM)
    cfg = replace(PilotConfig(), route_blocked=False, search=SearchConfig(enabled=False))
    m = PilotMethod(SeeingVlm(3, min_px=20), config=cfg, planner=planner)
    r, _ = fly(world, m, INSTRUCTION, REGION, limit_s=25.0)
    assert not r.metrics.success
    kinds = [e.kind for e in m.pilot.events]
    assert "goal_routed" not in kinds
    assert any(e.kind == "decision" and "no_feasible_pixel" in str(e.data.get("reason", "")).lower() for e in m.pilot.events)
