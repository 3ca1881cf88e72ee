"""Simulated vehicle: never exceeds its limits, integrates exactly, tracks feasible plans."""

from __future__ import annotations

import numpy as np
import pytest

from onfly.world.vehicle import SimVehicle, VehicleConfig, VehicleError
from planning.trajectory import Trajectory, VehicleState

CFG = VehicleConfig()


def start(p=(0.0, 0.0, 1.5), v=(0.0, 0.0, 0.0), yaw=0.0, t=0.0):
    return VehicleState(t, np.array(p), np.array(v), yaw)


def random_trajectory(rng, t0, p0, wild: bool) -> Trajectory:
    """Random plan; ``wild`` plans jump in position, velocity and yaw and ask for huge
    accelerations (infeasible for the vehicle)."""
    n, dt = int(rng.integers(5, 30)), 0.1
    scale = 20.0 if wild else 0.3
    a = rng.normal(0, scale, (n, 3))
    yaw_rate = rng.normal(0, 5.0 if wild else 0.2, n)
    p = np.zeros((n + 1, 3))
    v = np.zeros((n + 1, 3))
    yaw = np.zeros(n + 1)
    p[0] = p0 + (rng.normal(0, 10.0, 3) if wild else 0.0)
    v[0] = rng.normal(0, 3.0, 3) if wild else 0.0
    yaw[0] = rng.uniform(-np.pi, np.pi)
    for k in range(n):
        p[k + 1] = p[k] + v[k] * dt + 0.5 * a[k] * dt * dt
        v[k + 1] = v[k] + a[k] * dt
        yaw[k + 1] = yaw[k] + yaw_rate[k] * dt
    return Trajectory(t0, dt, p, v, yaw, a, yaw_rate)


@pytest.mark.parametrize("seed", range(6))
def test_limits_hold_at_every_step_under_random_and_infeasible_plans(seed):
    rng = np.random.default_rng(seed)
    veh = SimVehicle(start(), CFG)
    h = CFG.step_s
    for _ in range(12):
        veh.set_trajectory(random_trajectory(rng, veh.state.t_s, veh.state.p, wild=bool(rng.random() < 0.6)))
        for _ in range(int(rng.integers(20, 120))):
            s0 = veh.state
            veh.step(h)
            s1 = veh.state
            assert np.linalg.norm(s1.v) <= CFG.v_max_mps + 1e-9
            assert np.linalg.norm(s1.a) <= CFG.a_max_mps2 + 1e-9
            assert abs(s1.yaw_rate) <= CFG.yaw_rate_max_radps + 1e-12
            # exact integration of the held acceleration
            np.testing.assert_allclose(s1.v, s0.v + s1.a * h, atol=1e-12)
            np.testing.assert_allclose(s1.p, s0.p + s0.v * h + 0.5 * s1.a * h * h, atol=1e-12)
            assert s1.t_s == pytest.approx(s0.t_s + h, abs=1e-12)


def test_tracks_a_feasible_plan_closely():
    # A plan the vehicle can fly: accelerate at 0.3 m/s^2 for 1.5 s (to 0.45 m/s), cruise, brake.
    dt = 0.1
    a = np.zeros((60, 3))
    a[:15, 0] = 0.3
    a[45:, 0] = -0.3
    p, v = np.zeros((61, 3)), np.zeros((61, 3))
    p[0] = [0.0, 0.0, 1.5]
    for k in range(60):
        p[k + 1] = p[k] + v[k] * dt + 0.5 * a[k] * dt * dt
        v[k + 1] = v[k] + a[k] * dt
    yaw = np.linspace(0, 0.5, 61)
    traj = Trajectory(0.0, dt, p, v, yaw, a, np.full(60, 0.5 / 6.0))
    veh = SimVehicle(start(), CFG)
    veh.set_trajectory(traj)
    worst = 0.0
    for _ in range(60):
        veh.step(0.1)
        pr, _, _, yr, _ = traj.sample(veh.state.t_s)
        worst = max(worst, float(np.linalg.norm(veh.state.p - pr)))
        assert abs(veh.state.yaw - yr) < 1e-6
    assert worst < 1e-6  # the feed-forward alone flies a feasible plan exactly
    np.testing.assert_allclose(veh.state.p, p[-1], atol=1e-6)


def test_recovers_from_an_offset_then_holds_the_final_knot():
    p = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 1.5]])
    traj = Trajectory(0.0, 0.1, p, np.zeros((2, 3)), np.zeros(2), np.zeros((1, 3)), np.zeros(1))
    veh = SimVehicle(start(p=(1.0, -0.5, 2.0)), CFG)
    veh.set_trajectory(traj)
    veh.step(15.0)
    np.testing.assert_allclose(veh.state.p, [0.0, 0.0, 1.5], atol=1e-3)
    assert np.linalg.norm(veh.state.v) < 1e-3


def test_without_a_plan_the_vehicle_brakes_to_hover():
    veh = SimVehicle(start(v=(0.5, 0.0, 0.0)), CFG)
    times, pos = veh.step(3.0)
    assert len(times) == 300 and times[-1] == pytest.approx(3.0)
    assert np.linalg.norm(veh.state.v) < 1e-3
    # Braking from 0.5 m/s at most 0.6 m/s^2 needs at least 0.5^2 / (2 * 0.6) m.
    assert pos[-1, 0] >= 0.5**2 / (2 * 0.6) - 1e-9


def test_yaw_turns_the_short_way_at_the_rate_limit():
    p = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 1.5]])
    traj = Trajectory(0.0, 0.1, p, np.zeros((2, 3)), np.full(2, -3.0), np.zeros((1, 3)), np.zeros(1))
    veh = SimVehicle(start(yaw=3.0), CFG)
    veh.set_trajectory(traj)
    veh.step(0.2)
    # From +3.0 to -3.0 the short way is +0.283 rad through pi; the error stays above
    # 0.2 rad (gain 2/s asks > 0.4 rad/s), so 0.2 s at the 0.4 rad/s limit turns 0.08 rad.
    assert veh.state.yaw == pytest.approx(3.08, abs=1e-9)
    assert veh.state.yaw_rate == pytest.approx(0.4)
    veh.step(0.3)
    assert veh.state.yaw < 0  # wrapped through pi


def test_step_of_a_non_multiple_duration_is_exact_in_time():
    veh = SimVehicle(start(), CFG)
    times, pos = veh.step(0.105)
    assert times[-1] == pytest.approx(0.105, abs=1e-12) and len(times) == 11


def test_bad_inputs_are_rejected():
    with pytest.raises(VehicleError, match="initial speed"):
        SimVehicle(start(v=(1.0, 0.0, 0.0)), CFG)
    veh = SimVehicle(start(), CFG)
    with pytest.raises(VehicleError, match="dt_s must be positive"):
        veh.step(0.0)
    with pytest.raises(VehicleError, match="Trajectory"):
        veh.set_trajectory("not a plan")
    with pytest.raises(ValueError, match="v_max_mps"):
        VehicleConfig(v_max_mps=-1.0)
