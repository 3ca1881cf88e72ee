"""Fast path: the QP data reproduce the CasADi formulation exactly; OSQP solves it in place."""

from __future__ import annotations

import numpy as np
import osqp
import pytest

from planning.mpc_model import NU, NX, MpcFormulation, discrete_dynamics, dynamics_matrices, simulate
from planning.mpc_qp import MpcQp
from planning.planner_config import PlannerConfig

SMALL = PlannerConfig(horizon_steps=12)


@pytest.fixture(scope="module")
def qp() -> MpcQp:
    return MpcQp(MpcFormulation(SMALL))


def random_theta(layout, rng, volume: bool = True) -> np.ndarray:
    N = layout.N
    g = rng.normal(size=(N, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    sd = rng.normal(size=(N, layout.speed_cuts, 3))
    sd /= np.linalg.norm(sd, axis=2, keepdims=True)
    ad = rng.normal(size=(N, layout.accel_cuts, 3))
    ad /= np.linalg.norm(ad, axis=2, keepdims=True)
    lo = -rng.uniform(1.0, 5.0, size=3) if volume else None
    hi = rng.uniform(1.0, 5.0, size=3) if volume else None
    return layout.pack_theta(
        x0=rng.normal(size=NX),
        goal=rng.normal(size=3) * 3,
        psi_ref=rng.uniform(-3, 3),
        a_prev=rng.normal(size=3) * 0.3,
        lin_grad=g,
        lin_offset=rng.normal(size=N),
        speed_dir=sd,
        speed_bound=rng.uniform(0.6, 1.0, size=N),
        a_bar=rng.normal(size=(N, 3)) * 0.2,
        accel_dir=ad,
        pos_lo=lo,
        pos_hi=hi,
    )


def test_exact_discretization_matches_closed_form():
    dt = 0.1
    A, B = dynamics_matrices(dt)
    A_ref = np.eye(7)
    A_ref[0:3, 3:6] = dt * np.eye(3)
    B_ref = np.zeros((7, 4))
    B_ref[0:3, 0:3] = 0.5 * dt * dt * np.eye(3)
    B_ref[3:6, 0:3] = dt * np.eye(3)
    B_ref[6, 3] = dt
    np.testing.assert_allclose(A, A_ref, atol=1e-15)
    np.testing.assert_allclose(B, B_ref, atol=1e-15)


def test_numpy_rollout_equals_casadi_dynamics():
    rng = np.random.default_rng(0)
    F = discrete_dynamics(0.1)
    x0 = rng.normal(size=NX)
    U = rng.normal(size=(25, NU))
    X = simulate(x0, U, 0.1)
    x = x0
    for k in range(25):
        x = np.array(F(x, U[k])).ravel()
        np.testing.assert_allclose(X[k + 1], x, atol=1e-12)


def test_cost_data_reproduce_the_casadi_cost(qp):
    rng = np.random.default_rng(1)
    form = qp.formulation
    L = form.layout
    for _ in range(5):
        th = random_theta(L, rng)
        z = rng.normal(size=L.n_z)
        J = float(form.cost(z, th)) + float(form.proximal(z, th))
        J0 = float(form.cost(np.zeros(L.n_z), th)) + float(form.proximal(np.zeros(L.n_z), th))
        assert qp.objective(z, th) + J0 == pytest.approx(J, rel=1e-10)


def test_constraint_data_reproduce_the_casadi_constraints(qp):
    rng = np.random.default_rng(2)
    form = qp.formulation
    L = form.layout
    for i in range(6):
        th = random_theta(L, rng, volume=i % 2 == 0)
        z = rng.normal(size=L.n_z)
        A = qp.constraint_matrix(th)
        _, l, u = qp.vectors(th)
        lbz, ubz = (np.array(b).ravel() for b in form.z_bounds(th))
        # the flight-volume rows come last and are scaled by pos_active (0 without a volume)
        row_scale = np.ones(qp.bounded_z.size)
        row_scale[-3 * L.N :] = th[L.th_pos_active]
        G = np.concatenate(
            [
                np.array(form.dynamics(z, th)).ravel(),
                np.array(form.clearance_linear(z, th)).ravel(),
                np.array(form.speed_linear(z, th)).ravel(),
                np.array(form.accel_linear(z, th)).ravel(),
                row_scale * z[qp.bounded_z],
            ]
        )
        n_dyn, N, K, Ka = NX * (L.N + 1), L.N, L.speed_cuts, L.accel_cuts
        lower = np.concatenate(
            [np.zeros(n_dyn), np.zeros(N), np.full(N * (K + Ka), -np.inf), lbz[qp.bounded_z]]
        )
        upper = np.concatenate([np.zeros(n_dyn), np.full(N, np.inf), np.zeros(N * (K + Ka)), ubz[qp.bounded_z]])
        Az = A @ z
        fin_l, fin_u = np.isfinite(lower), np.isfinite(upper)
        np.testing.assert_allclose((Az - l)[fin_l], (G - lower)[fin_l], atol=1e-10)
        np.testing.assert_allclose((u - Az)[fin_u], (upper - G)[fin_u], atol=1e-10)
        assert np.all(l[~fin_l] <= -1e29) and np.all(u[~fin_u] >= 1e29)


def test_hessian_is_constant_and_positive_definite(qp):
    P = qp.P.toarray()
    P = P + np.triu(P, 1).T
    assert np.linalg.eigvalsh(P[: qp.n, : qp.n]).min() > -1e-9
    # on the inputs and slacks (where the cost is strictly convex) it is definite
    L = qp.layout
    idx = np.concatenate([L.idx_u.ravel(), L.idx_s])
    assert np.linalg.eigvalsh(P[np.ix_(idx, idx)]).min() > 0


def test_equilibrated_solve_equals_a_direct_solve_of_the_unscaled_qp():
    cfg = PlannerConfig(horizon_steps=12, qp_eps_abs=1e-8, qp_eps_rel=1e-8, qp_max_iter=200000, qp_polish=True)
    qp = MpcQp(MpcFormulation(cfg))
    L = qp.layout
    th = L.pack_theta(
        x0=np.array([0, 0, 0, 0.2, 0.1, 0, 0.3]),
        goal=np.array([3.0, 1.0, 0.5]),
        psi_ref=1.0,
        a_prev=np.zeros(3),
        lin_grad=np.tile([-1.0, 0.0, 0.0], (L.N, 1)),
        lin_offset=np.full(L.N, 2.0),  # wall at x = 2 - d: clearance 2 - x >= 0.45
        speed_dir=np.tile([1.0, 0.0, 0.0], (L.N, 1)),
        speed_bound=np.full(L.N, 0.6),
    )
    sol = qp.solve(th)
    assert sol.converged
    ref = osqp.OSQP()
    q, l, u = qp.vectors(th)
    ref.setup(qp.P, q, qp.constraint_matrix(th), l, u, eps_abs=1e-9, eps_rel=1e-9, max_iter=400000, polishing=True, verbose=False)
    res = ref.solve(raise_error=False)
    np.testing.assert_allclose(sol.z, res.x, atol=2e-5)
    # the linearized wall holds: x_k <= 2 - 0.45 at every knot 1..N
    assert np.all(sol.z[L.idx_p[1:, 0]] <= 1.55 + 1e-5)


def test_solution_respects_bounds_and_dynamics(qp):
    L = qp.layout
    c = SMALL
    th = L.pack_theta(
        x0=np.array([0, 0, 0, 0.5, 0.0, 0.0, 0.0]),
        goal=np.array([-4.0, 2.0, 0.0]),
        psi_ref=2.0,
        a_prev=np.zeros(3),
        lin_grad=np.tile([0.0, 0.0, 1.0], (L.N, 1)),
        lin_offset=np.full(L.N, 5.0),
        speed_dir=np.tile([1.0, 0.0, 0.0], (L.N, 1)),
        speed_bound=np.full(L.N, c.v_max_mps),
    )
    sol = qp.solve(th)
    assert sol.converged and sol.iterations > 0
    z = sol.z
    U = z[L.idx_u]
    tol = 1e-3
    assert np.all(np.abs(U[:, :3]) <= c.a_max_mps2 + tol)
    assert np.all(np.abs(U[:, 3]) <= c.yaw_rate_max_rps + tol)
    X = simulate(th[L.th_x0], U, c.dt_s)
    np.testing.assert_allclose(z[L.idx_x], X, atol=5e-3)
    # reversing toward the goal: the first command decelerates along +x
    assert U[0, 0] < -0.3


def test_warm_start_from_the_shifted_solution_saves_iterations(qp):
    L = qp.layout
    th = L.pack_theta(
        x0=np.zeros(NX),
        goal=np.array([5.0, 0.0, 0.0]),
        psi_ref=0.0,
        a_prev=np.zeros(3),
        lin_grad=np.tile([0.0, 0.0, 1.0], (L.N, 1)),
        lin_offset=np.full(L.N, 5.0),
        speed_dir=np.tile([1.0, 0.0, 0.0], (L.N, 1)),
        speed_bound=np.full(L.N, 0.6),
    )
    cold = qp.solve(th, np.zeros(qp.n), np.zeros(qp.m))
    warm = qp.solve(th, cold.z, cold.y)
    assert warm.converged and warm.iterations < cold.iterations
    np.testing.assert_allclose(warm.z, cold.z, atol=5e-3)


def test_sparsity_is_fixed_by_construction(qp):
    rng = np.random.default_rng(4)
    L = qp.layout
    A1 = qp.constraint_matrix(random_theta(L, rng))
    A2 = qp.constraint_matrix(random_theta(L, rng))
    np.testing.assert_array_equal(A1.indptr, A2.indptr)
    np.testing.assert_array_equal(A1.indices, A2.indices)
    assert not np.allclose(A1.data, A2.data)
    # only clearance gradients and speed and acceleration directions move: 3 N (1 + K + Ka)
    assert np.count_nonzero(A1.data != A2.data) <= 3 * L.N * (1 + L.speed_cuts + L.accel_cuts)
