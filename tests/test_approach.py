"""The goal in front of a target no straight ray reaches (planning.approach), on exact geometry."""

import math

import numpy as np
import pytest

from planning.analytic_field import AnalyticField, Box
from planning.approach import approach_point
from planning.volume import FlightVolume

# a wall whose face is the plane x = 5 (the target's surface), 10 m wide and 3 m high
WALL = Box(center=[5.1, 0.0, 1.5], half_extents=[0.1, 5.0, 1.5])
TARGET = np.array([5.0, 0.0, 1.3])
START = np.array([0.0, 0.0, 1.5])
KW = dict(clearance_m=0.55, standoff_m=0.6)  # candidates every 0.25 m from 0.6 m


class SeenField:
    """An exact field whose map has seen only the points ``seen(points)`` says (EsdfMap's
    ``observed_free``)."""

    def __init__(self, field, seen):
        self.field, self.seen = field, seen

    def query(self, points):
        return self.field.query(points)

    def observed_free(self, points):
        return self.seen(np.asarray(points))


def test_in_open_space_the_goal_is_the_standoff_on_the_straight_way_back():
    goal = approach_point(TARGET, START, AnalyticField(boxes=[WALL]), **KW)
    np.testing.assert_allclose(goal, [4.4, 0.0, 1.3], atol=1e-12)


def test_a_car_in_front_of_the_target_turns_the_approach_to_its_side():
    # a car 2 m long and wide between the vehicle and the target, 0.2 m off the wall
    car = Box(center=[3.8, 0.0, 0.75], half_extents=[1.0, 1.0, 0.75])
    field = AnalyticField(boxes=[WALL, car])
    goal = approach_point(TARGET, START, field, **KW)
    assert goal is not None
    d, _ = field.query(goal[None])
    assert d[0] >= 0.55
    assert abs(goal[1]) > 0.5, "the straight way back is blocked by the car"
    r = float(np.hypot(*(goal - TARGET)[:2]))
    assert 0.6 - 1e-9 <= r <= 2.6 + 1e-9
    assert r <= float(np.hypot(*(START - TARGET)[:2])) - 0.5
    # the straight way back has no point that keeps the clearance
    way = TARGET + np.outer(0.6 + np.arange(0.0, 2.01, 0.25), [-1.0, 0.0, 0.0])
    assert np.all(field.query(way)[0] < 0.55)
    # and the goal is the nearest passing point on its own way: every one before it fails
    a = math.atan2(goal[1] - TARGET[1], goal[0] - TARGET[0])
    before = np.arange(0.6, r - 1e-6, 0.25)
    pts = TARGET + np.column_stack([before * math.cos(a), before * math.sin(a), np.zeros(before.size)])
    assert np.all(field.query(pts)[0] < 0.55) if before.size else r == pytest.approx(0.6)


def test_unknown_space_is_never_a_goal():
    field = AnalyticField(boxes=[WALL])
    seen_up_to_4 = SeenField(field, lambda p: p[:, 0] <= 4.0)
    goal = approach_point(TARGET, START, seen_up_to_4, **KW)
    np.testing.assert_allclose(goal, [3.9, 0.0, 1.3], atol=1e-12)  # 4.4 and 4.15 are unseen
    assert approach_point(TARGET, START, SeenField(field, lambda p: np.zeros(len(p), bool)), **KW) is None


def test_no_goal_when_the_vehicle_is_already_as_near_as_a_goal_would_be():
    near = np.array([4.0, 0.3, 1.5])  # 1.04 m from the target: standoff 0.6 + 0.5 of progress
    assert approach_point(TARGET, near, AnalyticField(boxes=[WALL]), **KW) is None


def test_the_goal_stays_in_the_flight_volume_and_above_the_floor():
    field = AnalyticField(boxes=[WALL])
    low = np.array([5.0, 0.0, 0.3])
    vol = FlightVolume(np.array([-5.0, 0.5, 0.0]), np.array([10.0, 5.0, 3.0]))
    goal = approach_point(low, START, field, z_min_m=0.7, volume=vol, volume_margin_m=0.2, **KW)
    assert goal is not None
    assert goal[2] == pytest.approx(0.7)
    assert bool(vol.contains(goal[None], margin_m=0.2)[0])
    assert field.query(goal[None])[0][0] >= 0.55


def test_bad_parameters_raise_and_non_finite_points_give_none():
    field = AnalyticField(boxes=[WALL])
    with pytest.raises(ValueError):
        approach_point(TARGET, START, field, clearance_m=0.6, standoff_m=0.6, step_m=0.0)
    assert approach_point([np.nan, 0, 1], START, field, **KW) is None
