"""Planner.step's optional yaw reference: turning in place toward a given heading."""

import numpy as np
import pytest

from planning.analytic_field import AnalyticField, HalfSpace

GROUND = HalfSpace(point=(0, 0, 0), normal=(0, 0, 1))
from planning.frames import wrap_angle
from planning.planner import Planner, PlannerInputError
from planning.planner_config import PlannerConfig
from planning.trajectory import VehicleState


def test_yaw_ref_turns_in_place_across_the_seam():
    cfg = PlannerConfig()
    planner = Planner(cfg)
    field = AnalyticField(half_spaces=(GROUND,))
    s = VehicleState(0.0, [0, 0, 1.5], [0, 0, 0], 3.0)
    target = -3.0  # 0.28 rad away across +-pi: must turn the short way
    for _ in range(30):
        r = planner.step(s, s.p, field, yaw_ref=target)
        assert abs(r.command.yaw_rate) <= cfg.yaw_rate_max_rps * 1.01
        p, v, a, yaw, wr = r.trajectory.sample(s.t_s + cfg.dt_s)
        s = VehicleState(s.t_s + cfg.dt_s, p, v, yaw, wr, a)
    assert abs(wrap_angle(s.yaw - target)) < 0.05
    assert np.linalg.norm(s.p - [0, 0, 1.5]) < 0.05  # it turned without flying off


def test_yaw_ref_must_be_finite():
    planner = Planner(PlannerConfig())
    s = VehicleState(0.0, [0, 0, 1.5], [0, 0, 0], 0.0)
    with pytest.raises(PlannerInputError, match="yaw_ref"):
        planner.step(s, s.p, AnalyticField(half_spaces=(GROUND,)), yaw_ref=float("nan"))
