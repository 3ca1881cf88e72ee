import numpy as np
import pytest

from planning.trajectory import Trajectory, TrajectoryError, VehicleState


def make_traj(n=10, dt=0.1):
    rng = np.random.default_rng(0)
    a = rng.uniform(-0.5, 0.5, size=(n, 3))
    wr = rng.uniform(-0.3, 0.3, size=n)
    p = np.zeros((n + 1, 3))
    v = np.zeros((n + 1, 3))
    yaw = np.zeros(n + 1)
    v[0] = [0.2, 0, 0]
    for k in range(n):
        p[k + 1] = p[k] + v[k] * dt + 0.5 * a[k] * dt * dt
        v[k + 1] = v[k] + a[k] * dt
        yaw[k + 1] = yaw[k] + wr[k] * dt
    return Trajectory(5.0, dt, p, v, yaw, a, wr)


def test_sample_hits_knots_and_is_exact_between():
    tr = make_traj()
    for k in range(tr.steps + 1):
        p, v, _, _, _ = tr.sample(tr.t0_s + k * tr.dt_s)
        assert np.allclose(p, tr.p[k]) and np.allclose(v, tr.v[k])
    p, v, a, _, _ = tr.sample(tr.t0_s + 0.25)
    h = 0.05
    assert np.allclose(p, tr.p[2] + tr.v[2] * h + 0.5 * tr.a[2] * h * h)
    assert np.allclose(a, tr.a[2])
    p, v, a, _, wr = tr.sample(100.0)
    assert np.allclose(p, tr.p[-1]) and np.allclose(a, 0) and wr == 0


def test_shape_and_value_errors():
    with pytest.raises(TrajectoryError, match="p must have shape"):
        Trajectory(0, 0.1, np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1), np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(TrajectoryError, match="yaw must have shape"):
        Trajectory(0, 0.1, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(2), np.zeros((2, 3)), np.zeros(2))
    with pytest.raises(TrajectoryError, match="p is not finite"):
        VehicleState(0.0, [np.nan, 0, 0], [0, 0, 0], 0.0)
    s = VehicleState(0.0, [1, 2, 3], [0, 0, 0], 4.0)
    assert -np.pi < s.yaw <= np.pi and s.x.shape == (7,)
