import numpy as np
import pytest

from planning.frames import wrap_angle
from planning.straight_line import straight_line_plan
from planning.trajectory import VehicleState

LIMITS = dict(v_max_mps=0.6, a_max_mps2=0.6, yaw_rate_max_rps=0.4)


def closed_loop(state, goal, n=600, **kw):
    states = [state]
    for _ in range(n):
        tr = straight_line_plan(state, goal, **LIMITS, **kw)
        p, v, a, yaw, wr = tr.sample(state.t_s + 0.1)
        state = VehicleState(state.t_s + 0.1, p, v, yaw, wr, a)
        states.append(state)
    return states


def test_limits_hold_and_it_stops_at_the_goal():
    rng = np.random.default_rng(0)
    for _ in range(5):
        s = VehicleState(0.0, rng.uniform(-5, 5, 3), [0, 0, 0], rng.uniform(-np.pi, np.pi))
        goal = rng.uniform(-10, 10, 3)
        states = closed_loop(s, goal, n=500)
        for a, b in zip(states, states[1:]):
            assert np.linalg.norm(b.v) <= 0.6 * 1.01
            assert np.linalg.norm(b.a) <= 0.6 * 1.01
            assert abs(b.yaw_rate) <= 0.4 * 1.01
        assert np.linalg.norm(states[-1].p - goal) < 0.05
        assert np.linalg.norm(states[-1].v) < 0.05


def test_yaw_first_turns_before_translating():
    s = VehicleState(0.0, [0, 0, 1], [0, 0, 0], 0.0)
    states = closed_loop(s, [0, 10, 1], n=60, yaw_first=True)
    # pi/2 at 0.4 rad/s takes ~3.9 s: no translation until the heading is within 0.15 rad
    for st in states:
        if abs(wrap_angle(st.yaw - np.pi / 2)) > 0.15 + 0.04 + 1e-9:
            assert np.linalg.norm(st.p - [0, 0, 1]) < 1e-9
    assert states[-1].p[1] > 0.5  # and then it flies


def test_plan_ignores_obstacles_by_design_and_rejects_nan():
    s = VehicleState(0.0, [0, 0, 1], [0, 0, 0], 0.0)
    tr = straight_line_plan(s, [5, 0, 1], **LIMITS)
    assert np.allclose(tr.p[:, 1:], [0, 1])  # a straight line, whatever is in the way
    with pytest.raises(ValueError, match="finite"):
        straight_line_plan(s, [np.nan, 0, 0], **LIMITS)
