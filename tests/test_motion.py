"""Motion metrics against closed-form flights."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onfly.bench.motion import motion_metrics


def _line(a_mps2: float, n: int = 51, dt: float = 0.1):
    t = np.arange(n) * dt
    p = np.zeros((n, 3))
    p[:, 0] = 0.5 * a_mps2 * t**2
    return t, p


def test_constant_acceleration_has_that_rms_and_no_jerk():
    t, p = _line(0.8)
    goal = np.array([100.0, 0.0, 0.0])
    m = motion_metrics(t, p, np.zeros(len(t)), goal, np.linalg.norm(p - goal, axis=1), 5.0)
    assert m.rms_accel_mps2 == pytest.approx(0.8, rel=1e-9)
    assert m.rms_jerk_mps3 == pytest.approx(0.0, abs=1e-9)
    assert m.path_length_m == pytest.approx(0.5 * 0.8 * 5.0**2)
    assert m.time_to_goal_s is None  # never within 5 m of x = 100
    assert m.yaw_error_deg == pytest.approx(0.0)  # heading +x, goal straight ahead


def test_time_to_goal_is_the_first_sample_inside_the_radius():
    t, p = _line(2.0)  # x(t) = t^2
    goal = np.array([20.0, 0.0, 0.0])
    d = np.abs(p[:, 0] - 20.0)
    m = motion_metrics(t, p, np.zeros(len(t)), goal, d, 5.0)
    first = t[np.flatnonzero(d <= 5.0)[0]]
    assert m.time_to_goal_s == pytest.approx(first) and first == pytest.approx(3.9)  # sqrt(15) = 3.87 -> the 3.9 s sample


def test_yaw_error_is_the_angle_to_the_goal_bearing():
    t = np.arange(5) * 0.1
    p = np.zeros((5, 3))
    goal = np.array([0.0, 10.0, 0.0])  # bearing +90 deg
    m = motion_metrics(t, p, np.zeros(5), goal, np.full(5, 10.0), 5.0)
    assert m.yaw_error_deg == pytest.approx(90.0)
    m = motion_metrics(t, p, np.full(5, -math.pi / 2), goal, np.full(5, 10.0), 5.0)
    assert m.yaw_error_deg == pytest.approx(180.0)
    # wrap-around: heading 179 deg vs bearing -179 deg is 2 deg off
    g2 = np.array([-10.0, -10.0 * math.tan(math.radians(1.0)), 0.0])
    m = motion_metrics(t, p, np.full(5, math.radians(179.0)), g2, np.full(5, 10.0), 5.0)
    assert m.yaw_error_deg == pytest.approx(2.0, abs=1e-6)
    # samples within bearing_min_m of the goal centre do not count
    m = motion_metrics(t, p, np.zeros(5), np.array([0.5, 0.0, 0.0]), np.zeros(5), 5.0)
    assert m.yaw_error_deg is None


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="one sample each"):
        motion_metrics([0.0, 0.1], np.zeros((3, 3)), [0.0, 0.0], np.zeros(3), [1.0, 1.0], 5.0)
    with pytest.raises(ValueError, match="at least one sample"):
        motion_metrics([], np.zeros((0, 3)), [], np.zeros(3), [], 5.0)
