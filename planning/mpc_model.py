"""The CasADi formulation of the receding-horizon MPC, shared by both solvers.

One formulation, two solvers: :mod:`planning.mpc_nlp` hands it to ipopt with the exact speed
norm and the exact distance field; :mod:`planning.mpc_qp` differentiates the same functions
once into the matrices of a sparse QP (clearance and speed linearized about the previous plan).

Model (world ENU, metres, seconds, radians)
-------------------------------------------
State ``x = [p(3), v(3), yaw]`` (7), input ``u = [a(3), yaw_rate]`` (4), exact zero-order-hold
discretization of the double integrator and the yaw integrator over ``dt``::

    p+ = p + v dt + a dt^2 / 2,   v+ = v + a dt,   yaw+ = yaw + yaw_rate dt

Decision vector ``z = [x_0 .. x_N, u_0 .. u_{N-1}, s_1 .. s_N]`` (``s_k >= 0`` the clearance
slack of knot k). Knot 0 is pinned to the measured state by an equality (never softened) and
carries no clearance row: it is where the vehicle already is.

Parameter vector ``theta`` (see :class:`MpcLayout` for offsets)::

    x0 (7)            measured state
    goal (3)          verified goal, world ENU
    psi_ref (1)       goal bearing unwrapped near the current yaw (cost never sees a 2 pi jump)
    a_prev (3)        last commanded acceleration (jerk term of interval 0)
    lin_grad (N, 3)   field gradient at the linearization point of knots 1..N
    lin_offset (N)    d(pbar_k) - grad_k . pbar_k  (so d_lin(p) = grad_k . p + lin_offset_k)
    speed_dir (N,K,3) unit directions of the K speed-limit half-spaces ("cuts") of knots 1..N
    speed_bound (N)   speed limit of knots 1..N, m/s (>= v_max; larger only while an initial
                      overspeed is being braked away)
    a_bar (N, 3)      accelerations of the linearization point (QP proximal term only)
    accel_dir (N,Ka,3) unit directions of the Ka acceleration half-spaces of inputs 0..N-1
                      (``Ka = speed_cuts`` with the norm limit, 0 with the per-axis limit)
    pos_lo, pos_hi (3) position box of knots 1..N in the vehicle-centred frame, metres (the
                      flight volume shrunk by the body radius; +-inf when there is none)
    pos_active (1)    1 with a flight volume, 0 without: the QP's position rows are
                      ``pos_active * p_k`` (see :mod:`planning.mpc_qp`)

Cost::

    J = sum_{k=1..N}  w_goal ||p_k - g||^2 + w_vel ||v_k||^2 + w_yaw (yaw_k - psi_ref)^2
      + w_terminal_pos ||p_N - g||^2 + w_terminal_vel ||v_N||^2
      + sum_{k=0..N-1} w_accel ||a_k||^2 + w_jerk ||a_k - a_{k-1}||^2 + w_yaw_rate r_k^2
      + sum_{k=1..N} w_slack_l1 s_k + w_slack_l2 s_k^2

``(yaw_k - psi_ref)^2`` equals the paper's ``wrap(yaw_k - psi_g)^2`` because ``psi_ref`` is
unwrapped to within pi of the current yaw and the optimal yaw moves monotonically toward it.

The QP adds a proximal term ``w_prox_accel * sum_k ||a_k - a_bar_k||^2`` toward the
linearization point (:attr:`MpcFormulation.proximal`). It damps the sequential linearization
(clearance and speed are re-linearized about the last plan) and vanishes at a fixed point
``a = a_bar``, so a converged QP and the NLP share their optimum.

Constraints::

    x_0 = x0,  x_{k+1} = F(x_k, u_k)                       (hard)
    |a_i| <= a_max,  |r| <= yaw_rate_max                   (per axis, hard)
    ||a_k|| <= a_max    (accel_limit_mode "norm"; NLP: exact; QP: accel_dir_kj . a_k <= a_max)
    |v_{k,i}| <= speed_bound_k,  s_k >= 0                  (hard)
    ||v_k|| <= speed_bound_k          (NLP: exact; QP: speed_dir_kj . v_k <= bound_k, j < K)
    pos_lo <= p_k <= pos_hi, k = 1..N                      (hard; the flight volume)

The per-axis box on ``a`` is kept in both modes: with the norm limit it is implied by the norm
(an outer bound that keeps the QP bounded in every direction); with ``"per_axis"`` it is the
limit itself (Fast-Planner's convention). The position rows are present whether or not a
volume is given (+-inf bounds then), so the QP's sparsity never depends on the volume.
    d(p_k) + s_k >= d_safe                                 (NLP: exact; QP: linearized)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from planning.planner_config import PlannerConfig

__all__ = [
    "NX",
    "NU",
    "MpcLayout",
    "MpcFormulation",
    "discrete_dynamics",
    "dynamics_matrices",
    "simulate",
]

#: State dimension ``[p(3), v(3), yaw]``.
NX = 7
#: Input dimension ``[a(3), yaw_rate]``.
NU = 4


def discrete_dynamics(dt_s: float) -> ca.Function:
    """Exact discretization ``F(x (7,), u (4,)) -> x_next (7,)`` over ``dt_s`` seconds."""
    x = ca.SX.sym("x", NX)
    u = ca.SX.sym("u", NU)
    p, v, yaw = x[0:3], x[3:6], x[6]
    a, r = u[0:3], u[3]
    x_next = ca.vertcat(p + v * dt_s + 0.5 * dt_s**2 * a, v + dt_s * a, yaw + dt_s * r)
    return ca.Function("F", [x, u], [x_next], ["x", "u"], ["x_next"])


def dynamics_matrices(dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(A (7, 7), B (7, 4))`` with ``F(x, u) = A x + B u``, differentiated from CasADi."""
    F = discrete_dynamics(dt_s)
    x = ca.SX.sym("x", NX)
    u = ca.SX.sym("u", NU)
    xn = F(x, u)
    jac = ca.Function("jac_F", [x, u], [ca.jacobian(xn, x), ca.jacobian(xn, u)])
    A, B = jac(np.zeros(NX), np.zeros(NU))
    return np.array(A), np.array(B)


def simulate(x0: np.ndarray, U: np.ndarray, dt_s: float) -> np.ndarray:
    """Roll the exact discrete model out in NumPy (the same map as :func:`discrete_dynamics`).

    Parameters
    ----------
    x0 : array (7,), ``[p (m), v (m/s), yaw (rad)]``
    U : array (N, 4), ``[a (m/s^2), yaw_rate (rad/s)]`` held over each interval
    dt_s : interval, seconds

    Returns
    -------
    X : array (N + 1, 7), knot states, ``X[0] = x0``
    """
    U = np.asarray(U, dtype=float)
    a, r = U[:, 0:3], U[:, 3]
    X = np.empty((U.shape[0] + 1, NX))
    X[0] = x0
    v = np.empty((U.shape[0] + 1, 3))
    v[0] = x0[3:6]
    np.cumsum(a * dt_s, axis=0, out=v[1:])
    v[1:] += x0[3:6]
    X[:, 3:6] = v
    X[0, 0:3] = x0[0:3]
    np.cumsum(v[:-1] * dt_s + (0.5 * dt_s * dt_s) * a, axis=0, out=X[1:, 0:3])
    X[1:, 0:3] += x0[0:3]
    X[0, 6] = x0[6]
    np.cumsum(r * dt_s, out=X[1:, 6])
    X[1:, 6] += x0[6]
    return X


@dataclass(frozen=True)
class MpcLayout:
    """Index bookkeeping of ``z`` and ``theta`` for a horizon of ``N`` intervals and ``K``
    speed cuts per knot (``speed_cuts``). Properties are computed once and cached.

    All index arrays are into the flat vectors; e.g. ``z[layout.idx_p]`` has shape (N+1, 3).
    """

    N: int
    speed_cuts: int = 1
    accel_cuts: int = 0

    @cached_property
    def n_x(self) -> int:
        return NX * (self.N + 1)

    @cached_property
    def n_u(self) -> int:
        return NU * self.N

    @cached_property
    def n_z(self) -> int:
        return self.n_x + self.n_u + self.N

    @cached_property
    def idx_x(self) -> np.ndarray:
        """(N+1, 7) indices of the states."""
        return np.arange(self.n_x).reshape(self.N + 1, NX)

    @cached_property
    def idx_u(self) -> np.ndarray:
        """(N, 4) indices of the inputs."""
        return self.n_x + np.arange(self.n_u).reshape(self.N, NU)

    @cached_property
    def idx_s(self) -> np.ndarray:
        """(N,) indices of the slacks of knots 1..N."""
        return self.n_x + self.n_u + np.arange(self.N)

    @cached_property
    def idx_p(self) -> np.ndarray:
        return self.idx_x[:, 0:3]

    @cached_property
    def idx_v(self) -> np.ndarray:
        return self.idx_x[:, 3:6]

    @cached_property
    def idx_yaw(self) -> np.ndarray:
        return self.idx_x[:, 6]

    @cached_property
    def idx_a(self) -> np.ndarray:
        return self.idx_u[:, 0:3]

    @cached_property
    def idx_yaw_rate(self) -> np.ndarray:
        return self.idx_u[:, 3]

    # ------------------------------------------------------------------ theta layout
    @cached_property
    def _theta_blocks(self) -> dict[str, tuple[int, int]]:
        """Name -> (offset, size) of every block of ``theta``, in order."""
        N, K = self.N, self.speed_cuts
        sizes = [
            ("x0", NX), ("goal", 3), ("psi_ref", 1), ("a_prev", 3), ("lin_grad", 3 * N),
            ("lin_offset", N), ("speed_dir", 3 * N * K), ("speed_bound", N), ("a_bar", 3 * N),
            ("accel_dir", 3 * N * self.accel_cuts), ("pos_lo", 3), ("pos_hi", 3),
            ("pos_active", 1),
        ]
        out, off = {}, 0
        for name, size in sizes:
            out[name] = (off, size)
            off += size
        return out

    def _th(self, name: str) -> slice:
        off, size = self._theta_blocks[name]
        return slice(off, off + size)

    @cached_property
    def th_x0(self) -> slice:
        return self._th("x0")

    @cached_property
    def th_goal(self) -> slice:
        return self._th("goal")

    @cached_property
    def th_psi_ref(self) -> int:
        return self._theta_blocks["psi_ref"][0]

    @cached_property
    def th_a_prev(self) -> slice:
        return self._th("a_prev")

    @cached_property
    def th_lin_grad(self) -> slice:
        return self._th("lin_grad")

    @cached_property
    def th_lin_offset(self) -> slice:
        return self._th("lin_offset")

    @cached_property
    def th_speed_dir(self) -> slice:
        """(N, K, 3) knot-major: the K cut directions of knot 1, then knot 2, ..."""
        return self._th("speed_dir")

    @cached_property
    def th_speed_bound(self) -> slice:
        return self._th("speed_bound")

    @cached_property
    def th_a_bar(self) -> slice:
        return self._th("a_bar")

    @cached_property
    def th_accel_dir(self) -> slice:
        """(N, Ka, 3) knot-major, like :attr:`th_speed_dir` (empty with the per-axis limit)."""
        return self._th("accel_dir")

    @cached_property
    def th_pos_lo(self) -> slice:
        return self._th("pos_lo")

    @cached_property
    def th_pos_hi(self) -> slice:
        return self._th("pos_hi")

    @cached_property
    def th_pos_active(self) -> int:
        return self._theta_blocks["pos_active"][0]

    @cached_property
    def n_theta(self) -> int:
        off, size = self._theta_blocks["pos_active"]
        return off + size

    def pack_theta(
        self,
        x0: np.ndarray,
        goal: np.ndarray,
        psi_ref: float,
        a_prev: np.ndarray,
        lin_grad: np.ndarray,
        lin_offset: np.ndarray,
        speed_dir: np.ndarray,
        speed_bound: np.ndarray,
        a_bar: np.ndarray | None = None,
        accel_dir: np.ndarray | None = None,
        pos_lo: np.ndarray | None = None,
        pos_hi: np.ndarray | None = None,
        pos_active: float | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Assemble ``theta`` (n_theta,) from its parts (shapes as in the module docstring).

        ``speed_dir`` may be (N, 3) (one direction per knot, copied into all K cut slots) or
        (N, K, 3); ``accel_dir`` likewise (N, 3) or (N, Ka, 3), default: the speed
        directions' first slot. ``pos_lo`` / ``pos_hi`` default to -inf / +inf (no volume);
        ``pos_active`` defaults to 1 when any of their entries is finite, else 0.
        """
        th = np.empty(self.n_theta) if out is None else out
        th[self.th_x0] = x0
        th[self.th_goal] = goal
        th[self.th_psi_ref] = psi_ref
        th[self.th_a_prev] = a_prev
        th[self.th_lin_grad] = np.ravel(lin_grad)
        th[self.th_lin_offset] = lin_offset
        sd = np.asarray(speed_dir, dtype=float)
        if sd.shape == (self.N, 3):
            sd = np.repeat(sd[:, None, :], self.speed_cuts, axis=1)
        th[self.th_speed_dir] = sd.ravel()
        th[self.th_speed_bound] = speed_bound
        th[self.th_a_bar] = 0.0 if a_bar is None else np.ravel(a_bar)
        if self.accel_cuts:
            ad = sd[:, 0, :] if accel_dir is None else np.asarray(accel_dir, dtype=float)
            if ad.shape == (self.N, 3):
                ad = np.repeat(ad[:, None, :], self.accel_cuts, axis=1)
            th[self.th_accel_dir] = ad.ravel()
        th[self.th_pos_lo] = -np.inf if pos_lo is None else pos_lo
        th[self.th_pos_hi] = np.inf if pos_hi is None else pos_hi
        if pos_active is None:
            pos_active = float(np.isfinite(th[self.th_pos_lo]).any() or np.isfinite(th[self.th_pos_hi]).any())
        th[self.th_pos_active] = pos_active
        return th


class MpcFormulation:
    """Symbolic MPC problem for one :class:`PlannerConfig`, as CasADi functions of ``(z, theta)``.

    Attributes (all ``ca.Function`` over SX, callable with MX too)
    ----------
    cost : (z, theta) -> J, scalar (the true cost, shared by both solvers)
    proximal : (z, theta) -> J_prox, the QP's damping term (zero at a fixed point)
    dynamics : (z, theta) -> residual (7 (N+1),), equal to 0 when feasible
    clearance_linear : (z, theta) -> (N,), ``grad_k . p_k + lin_offset_k + s_k - d_safe`` (>= 0)
    speed_linear : (z, theta) -> (N K,), ``speed_dir_kj . v_k - speed_bound_k`` (<= 0),
        knot-major
    speed_squared : (z, theta) -> (N,), ``||v_k||^2 - speed_bound_k^2`` (<= 0)
    accel_linear : (z, theta) -> (N Ka,), ``accel_dir_kj . a_k - a_max`` (<= 0), knot-major
        (an empty function with the per-axis limit)
    accel_squared : (z) -> (N,) ``||a_k||^2 - a_max^2`` (<= 0) (empty with the per-axis limit)
    positions : (z) -> (N, 3)-flattened positions of knots 1..N, row-major (3N,)
    slack : (z) -> (N,)
    z_bounds : (theta) -> (lbz, ubz), each (n_z,), +-inf where unbounded
    """

    def __init__(self, config: PlannerConfig) -> None:
        self.config = config
        norm_accel = config.accel_limit_mode == "norm"
        self.layout = MpcLayout(
            config.horizon_steps, config.speed_cuts_per_knot, config.speed_cuts_per_knot if norm_accel else 0
        )
        L = self.layout
        N, c = L.N, config
        z = ca.SX.sym("z", L.n_z)
        th = ca.SX.sym("theta", L.n_theta)
        F = discrete_dynamics(c.dt_s)

        X = [z[L.idx_x[k].tolist()] for k in range(N + 1)]
        U = [z[L.idx_u[k].tolist()] for k in range(N)]
        S = z[L.idx_s.tolist()]
        x0 = th[L.th_x0]
        goal = th[L.th_goal]
        psi_ref = th[L.th_psi_ref]
        a_prev = th[L.th_a_prev]
        grad = ca.reshape(th[L.th_lin_grad], 3, N)  # column k-1 = knot k
        offset = th[L.th_lin_offset]
        K = L.speed_cuts
        sdir = ca.reshape(th[L.th_speed_dir], 3, N * K)  # column (k-1) K + j = cut j of knot k
        sbound = th[L.th_speed_bound]
        a_bar = ca.reshape(th[L.th_a_bar], 3, N)
        Ka = L.accel_cuts
        adir = ca.reshape(th[L.th_accel_dir], 3, N * Ka) if Ka else None
        pos_lo, pos_hi = th[L.th_pos_lo], th[L.th_pos_hi]

        J = 0
        for k in range(1, N + 1):
            p, v, yaw = X[k][0:3], X[k][3:6], X[k][6]
            J += c.w_goal * ca.sumsqr(p - goal) + c.w_vel * ca.sumsqr(v)
            J += c.w_yaw * (yaw - psi_ref) ** 2
        J += c.w_terminal_pos * ca.sumsqr(X[N][0:3] - goal) + c.w_terminal_vel * ca.sumsqr(X[N][3:6])
        a_before = a_prev
        for k in range(N):
            a, r = U[k][0:3], U[k][3]
            J += c.w_accel * ca.sumsqr(a) + c.w_yaw_rate * r**2 + c.w_jerk * ca.sumsqr(a - a_before)
            a_before = a
        J += c.w_slack_l1 * ca.sum1(S) + c.w_slack_l2 * ca.sumsqr(S)

        prox = 0
        for k in range(N):
            prox += c.w_prox_accel * ca.sumsqr(U[k][0:3] - a_bar[:, k])

        dyn = [X[0] - x0] + [X[k + 1] - F(X[k], U[k]) for k in range(N)]
        clear_lin = ca.vertcat(
            *[ca.dot(grad[:, k - 1], X[k][0:3]) + offset[k - 1] + S[k - 1] - c.d_safe_m for k in range(1, N + 1)]
        )
        speed_lin = ca.vertcat(
            *[
                ca.dot(sdir[:, (k - 1) * K + j], X[k][3:6]) - sbound[k - 1]
                for k in range(1, N + 1)
                for j in range(K)
            ]
        )
        speed_sq = ca.vertcat(*[ca.sumsqr(X[k][3:6]) - sbound[k - 1] ** 2 for k in range(1, N + 1)])
        if Ka:
            accel_lin = ca.vertcat(
                *[ca.dot(adir[:, k * Ka + j], U[k][0:3]) - c.a_max_mps2 for k in range(N) for j in range(Ka)]
            )
            accel_sq = ca.vertcat(*[ca.sumsqr(U[k][0:3]) - c.a_max_mps2**2 for k in range(N)])
        else:
            accel_lin = ca.SX(0, 1)
            accel_sq = ca.SX(0, 1)
        positions = ca.vertcat(*[X[k][0:3] for k in range(1, N + 1)])

        lbz = ca.SX(-np.inf * np.ones(L.n_z))
        ubz = ca.SX(np.inf * np.ones(L.n_z))
        amax = np.array([c.a_max_mps2] * 3 + [c.yaw_rate_max_rps])
        for k in range(N):
            for i in range(NU):
                lbz[int(L.idx_u[k, i])] = -amax[i]
                ubz[int(L.idx_u[k, i])] = amax[i]
            for i in range(3):
                lbz[int(L.idx_v[k + 1, i])] = -sbound[k]
                ubz[int(L.idx_v[k + 1, i])] = sbound[k]
            lbz[int(L.idx_s[k])] = 0.0
            for i in range(3):
                lbz[int(L.idx_p[k + 1, i])] = pos_lo[i]
                ubz[int(L.idx_p[k + 1, i])] = pos_hi[i]

        self.cost = ca.Function("cost", [z, th], [J], ["z", "theta"], ["J"])
        self.proximal = ca.Function("proximal", [z, th], [prox], ["z", "theta"], ["J_prox"])
        self.dynamics = ca.Function("dynamics", [z, th], [ca.vertcat(*dyn)], ["z", "theta"], ["residual"])
        self.clearance_linear = ca.Function("clearance_linear", [z, th], [clear_lin], ["z", "theta"], ["g"])
        self.speed_linear = ca.Function("speed_linear", [z, th], [speed_lin], ["z", "theta"], ["g"])
        self.speed_squared = ca.Function("speed_squared", [z, th], [speed_sq], ["z", "theta"], ["g"])
        self.accel_linear = ca.Function("accel_linear", [z, th], [accel_lin], ["z", "theta"], ["g"])
        self.accel_squared = ca.Function("accel_squared", [z], [accel_sq], ["z"], ["g"])
        self.positions = ca.Function("positions", [z], [positions], ["z"], ["p"])
        self.slack = ca.Function("slack", [z], [S], ["z"], ["s"])
        self.z_bounds = ca.Function("z_bounds", [th], [lbz, ubz], ["theta"], ["lbz", "ubz"])
        self._z_sym = z
        self._theta_sym = th

    @property
    def symbols(self) -> tuple[ca.SX, ca.SX]:
        """The SX symbols ``(z, theta)`` the functions were built from."""
        return self._z_sym, self._theta_sym

    def evaluate_cost(self, z: np.ndarray, theta: np.ndarray) -> float:
        """The true cost ``J(z, theta)`` (constant terms included), for comparing solvers."""
        return float(self.cost(z, theta))
