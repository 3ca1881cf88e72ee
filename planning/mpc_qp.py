"""Fast path: the MPC of :mod:`planning.mpc_model` as a sparse QP solved by a persistent OSQP.

Everything the QP needs is generated **once**, from the CasADi functions of the formulation:

- ``P``: the Hessian of the cost (constant; the cost is quadratic in ``z``).
- ``q(theta) = q0 + Mq theta``: the cost gradient at ``z = 0``, affine in ``theta``.
- ``A(theta)``: the Jacobian of the stacked constraints; its sparsity is fixed and its nonzeros
  are affine in ``theta`` (only the clearance rows (gradient) and the speed rows (direction)
  move), ``Ax = A0 + MA theta``.
- ``l(theta), u(theta)``: the constraint bounds minus the constraint value at ``z = 0``, affine.

The maps ``Mq, MA, Ml, Mu`` are the (constant) Jacobians of those CasADi expressions with
respect to ``theta``, evaluated once into ``scipy.sparse`` matrices. The hot path is four
sparse mat-vecs in NumPy, one in-place OSQP ``update(q, l, u, Ax)`` (same sparsity), a warm
start and ``solve()``: no CasADi call.

Scaling. OSQP's own Ruiz equilibration re-runs on every matrix update and costs more than the
KKT refactorization, so the problem is equilibrated **once** here (modified Ruiz on the KKT
matrix at a representative ``theta``), the diagonal scalings are folded into the affine maps,
and OSQP runs with ``scaling=0``. The rows that change hold unit vectors (gradients, speed
directions), so one scaling fits every step. :meth:`MpcQp.solve` returns the unscaled ``z, y``.

Constraint rows (in this order): dynamics (7 (N+1), equalities, knot 0 pinned to ``x0``),
linearized clearance (N), speed cuts (N K, knot-major), then one identity row for every entry
of ``z`` with a finite bound (inputs, velocities, slacks).

Speed. Each knot has K half-spaces ``n_kj . v_k <= bound_k`` with unit ``n_kj``: each is
implied by ``||v_k|| <= bound_k``, so together they are an outer polyhedral approximation that
the caller tightens where needed: slot 0 is the tangent at the previous plan's velocity
direction, the other slots are cutting planes added at the directions of violating solutions
(:class:`planning.planner.Planner` re-solves until the true norm is within 1 % of the bound).
Cuts never cycle (the set only shrinks toward the ball), unlike re-linearizing a single tangent,
which we measured to alternate between two solutions. The per-axis box ``|v_i| <= bound`` keeps
every direction bounded.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp

from planning.mpc_model import NX, MpcFormulation

__all__ = ["MpcQp", "QpSolution", "QpBuildError"]

logger = logging.getLogger(__name__)

_INF = 1e30


class QpBuildError(RuntimeError):
    """The formulation is not a QP with constant Hessian and affine data (a modelling bug)."""


@dataclass(frozen=True, eq=False)
class QpSolution:
    """One OSQP solve.

    Attributes
    ----------
    z : array (n_z,), primal solution (layout of :class:`planning.mpc_model.MpcLayout`)
    y : array (m,), dual solution
    status : str, OSQP status text (``"solved"``, ``"maximum iterations reached"``, ...)
    converged : bool, status is ``solved`` (``solved inaccurate`` counts as not converged)
    iterations : int, ADMM iterations
    solve_time_s : float, OSQP's own setup-free solve time, seconds
    """

    z: np.ndarray
    y: np.ndarray
    status: str
    converged: bool
    iterations: int
    solve_time_s: float


def _sparse_const(expr: ca.SX, wrt: ca.SX, name: str) -> sp.csr_matrix:
    """Jacobian of ``expr`` with respect to ``wrt`` as a constant scipy matrix (checked)."""
    jac = ca.jacobian(expr, wrt)
    if ca.depends_on(jac, wrt):
        raise QpBuildError(f"{name} is not affine in its parameters")
    f = ca.Function(f"jac_{name}", [wrt], [jac])
    dm = f(np.zeros(wrt.numel()))
    return sp.csr_matrix(dm.sparse()) if hasattr(dm, "sparse") else sp.csr_matrix(np.array(dm))


def _ruiz_equilibrate(
    P: sp.spmatrix, A: sp.spmatrix, iterations: int = 25
) -> tuple[np.ndarray, np.ndarray, float]:
    """Modified Ruiz equilibration of the KKT matrix ``[[P, A'], [A, 0]]`` (as OSQP does).

    Returns ``D (n,)``, ``E (m,)`` and the cost scale ``c`` such that the scaled problem
    ``min c (1/2 zt'(DPD)zt + (Dq)'zt)  s.t.  E l <= E A D zt <= E u`` with ``z = D zt`` is
    the original one. Factors are clipped to [1e-4, 1e4].
    """
    P = sp.csc_matrix(abs(P))
    A = sp.csc_matrix(abs(A))
    n, m = P.shape[0], A.shape[0]
    D, E = np.ones(n), np.ones(m)
    for _ in range(iterations):
        Ps = sp.diags(D) @ P @ sp.diags(D)
        As = sp.diags(E) @ A @ sp.diags(D)
        col = np.maximum(Ps.max(axis=0).toarray().ravel(), As.max(axis=0).toarray().ravel())
        row = As.max(axis=1).toarray().ravel()
        D = np.clip(D / np.sqrt(np.clip(col, 1e-4, 1e4)), 1e-4, 1e4)
        E = np.clip(E / np.sqrt(np.clip(row, 1e-4, 1e4)), 1e-4, 1e4)
    Ps = sp.diags(D) @ P @ sp.diags(D)
    c = 1.0 / float(np.clip(np.mean(Ps.max(axis=0).toarray()), 1e-4, 1e4))
    return D, E, c


class MpcQp:
    """The MPC as a persistent, warm-started OSQP problem.

    Build once from a :class:`MpcFormulation` (generates every matrix, sets OSQP up once);
    then :meth:`solve` per control step with a new ``theta``.

    Attributes
    ----------
    n : int, number of variables (``layout.n_z``)
    m : int, number of constraint rows
    P : scipy.sparse.csc_matrix (n, n), upper triangle of the cost Hessian (constant)
    """

    def __init__(self, formulation: MpcFormulation) -> None:
        self.formulation = formulation
        self.config = formulation.config
        L = self.layout = formulation.layout
        z, th = formulation.symbols
        zero_th = np.zeros(L.n_theta)

        # --- cost: J = 1/2 z'Pz + q(theta)'z + c(theta)
        J = formulation.cost(z, th) + formulation.proximal(z, th)
        H = ca.hessian(J, z)[0]
        if ca.depends_on(H, ca.vertcat(z, th)):
            raise QpBuildError("the cost Hessian is not constant")
        H_dm = ca.Function("H", [th], [H])(zero_th)
        P_full = sp.csc_matrix(H_dm.sparse())
        self._P_full = P_full
        self.P = sp.triu(P_full, format="csc")
        grad0 = ca.substitute(ca.gradient(J, z), z, ca.SX.zeros(L.n_z))
        self._Mq = _sparse_const(grad0, th, "q")
        self._q0 = np.array(ca.Function("q0", [th], [grad0])(zero_th)).ravel()

        # --- constraints G(z, theta) with bounds lower(theta) <= G <= upper(theta)
        lbz, ubz = formulation.z_bounds(th)
        lbz0, ubz0 = (np.array(b).ravel() for b in formulation.z_bounds(self._generic_theta()))
        bounded = np.flatnonzero(np.isfinite(lbz0) | np.isfinite(ubz0))
        #: indices of ``z`` with a finite bound, one identity row each (the last rows of A)
        self.bounded_z = bounded
        G = ca.vertcat(
            formulation.dynamics(z, th),
            formulation.clearance_linear(z, th),
            formulation.speed_linear(z, th),
            z[bounded.tolist()],
        )
        n_dyn, N = NX * (L.N + 1), L.N
        K = L.speed_cuts
        inf_col = ca.SX(np.full((N, 1), np.inf))
        lower = ca.vertcat(ca.SX.zeros(n_dyn), ca.SX.zeros(N), -ca.repmat(inf_col, K, 1), lbz[bounded.tolist()])
        upper = ca.vertcat(ca.SX.zeros(n_dyn), inf_col, ca.SX.zeros(N * K), ubz[bounded.tolist()])
        self.m = G.numel()
        self.n = L.n_z

        A_sym = ca.jacobian(G, z)
        A_sp = A_sym.sparsity()
        A_nz = A_sym.nz[:]  # nonzeros in CCS (column-major) order
        colind, row = A_sp.get_ccs()
        self._A_indptr = np.asarray(colind, dtype=np.int64)
        self._A_indices = np.asarray(row, dtype=np.int64)
        self._MA = _sparse_const(A_nz, th, "A")
        self._A0 = np.array(ca.Function("A0", [th], [A_nz])(zero_th)).ravel()

        G0 = ca.substitute(G, z, ca.SX.zeros(L.n_z))
        l_expr = self._finite(lower) - G0
        u_expr = self._finite(upper) - G0
        self._Ml = _sparse_const(l_expr, th, "l")
        self._Mu = _sparse_const(u_expr, th, "u")
        f_lu = ca.Function("lu", [th], [lower - G0, upper - G0])
        l0, u0 = (np.array(v).ravel() for v in f_lu(zero_th))
        self._l_inf = ~np.isfinite(l0)
        self._u_inf = ~np.isfinite(u0)
        l0[self._l_inf] = -_INF
        u0[self._u_inf] = _INF
        self._l0, self._u0 = l0, u0

        # --- fixed equilibration, computed once (OSQP's own scaling would re-run on every
        # matrix update and cost more than the factorization; the rows that change hold unit
        # vectors whose magnitude does not change, so one scaling fits every step)
        theta = self._generic_theta()
        A = self.constraint_matrix(theta)
        D, E, c_cost = _ruiz_equilibrate(P_full, A)
        self._D, self._E, self._c = D, E, c_cost
        cols = np.repeat(np.arange(self.n), np.diff(self._A_indptr))
        s_nz = E[self._A_indices] * D[cols]
        self._sA0 = s_nz * self._A0
        self._sMA = (sp.diags(s_nz) @ self._MA).tocsr()
        self._sq0 = c_cost * D * self._q0
        self._sMq = (sp.diags(c_cost * D) @ self._Mq).tocsr()
        self._sl0 = E * self._l0
        self._su0 = E * self._u0
        self._sMl = (sp.diags(E) @ self._Ml).tocsr()
        self._sMu = (sp.diags(E) @ self._Mu).tocsr()
        self._sP = sp.triu(sp.diags(c_cost * D) @ P_full @ sp.diags(D), format="csc")

        cfg = self.config
        self._settings = dict(
            eps_abs=cfg.qp_eps_abs,
            eps_rel=cfg.qp_eps_rel,
            max_iter=cfg.qp_max_iter,
            rho=cfg.qp_rho,
            adaptive_rho=int(cfg.qp_adaptive_rho),
            adaptive_rho_interval=cfg.qp_adaptive_rho_interval,
            check_termination=cfg.qp_check_termination,
            polishing=cfg.qp_polish,
            warm_starting=True,
            verbose=False,
            scaling=0,
        )
        q, l, u = self._scaled_vectors(theta)
        sA = sp.csc_matrix((self._scaled_Ax(theta), self._A_indices, self._A_indptr), shape=(self.m, self.n))
        self._solver = osqp.OSQP()
        self._solver.setup(self._sP, q, sA, l, u, **self._settings)
        logger.debug("MpcQp built: n=%d m=%d nnz(P)=%d nnz(A)=%d", self.n, self.m, self.P.nnz, A.nnz)

    # ------------------------------------------------------------------ build helpers
    @staticmethod
    def _finite(expr: ca.SX) -> ca.SX:
        """``expr`` with infinite constant entries replaced by 0 (their slope is 0 anyway)."""
        out = ca.SX(expr)
        for i in range(out.numel()):
            e = out[i]
            if e.is_constant() and not np.isfinite(float(ca.DM(e))):
                out[i] = 0
        return out

    def _generic_theta(self) -> np.ndarray:
        """A theta with every structural entry nonzero, used for setup (no pruned zeros)."""
        L = self.layout
        g = np.tile([0.6, 0.64, 0.48], (L.N, 1))  # a unit vector with no zero component
        return L.pack_theta(
            x0=np.zeros(NX),
            goal=np.zeros(3),
            psi_ref=0.0,
            a_prev=np.zeros(3),
            lin_grad=g,
            lin_offset=np.ones(L.N),
            speed_dir=g,
            speed_bound=np.full(L.N, self.config.v_max_mps),
        )

    # ------------------------------------------------------------------ hot path
    def constraint_matrix(self, theta: np.ndarray) -> sp.csc_matrix:
        """``A(theta)`` as a CSC matrix (m, n), the sparsity OSQP was set up with."""
        Ax = self._A0 + self._MA @ theta
        return sp.csc_matrix((Ax, self._A_indices, self._A_indptr), shape=(self.m, self.n))

    def vectors(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(q (n,), l (m,), u (m,))`` for ``theta``; infinite bounds as +-1e30."""
        q = self._q0 + self._Mq @ theta
        l = self._l0 + self._Ml @ theta
        u = self._u0 + self._Mu @ theta
        l[self._l_inf] = -_INF
        u[self._u_inf] = _INF
        return q, l, u

    def _scaled_vectors(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = self._sq0 + self._sMq @ theta
        l = self._sl0 + self._sMl @ theta
        u = self._su0 + self._sMu @ theta
        l[self._l_inf] = -_INF
        u[self._u_inf] = _INF
        return q, l, u

    def _scaled_Ax(self, theta: np.ndarray) -> np.ndarray:
        return self._sA0 + self._sMA @ theta

    def solve(
        self, theta: np.ndarray, z_warm: np.ndarray | None = None, y_warm: np.ndarray | None = None
    ) -> QpSolution:
        """Update the persistent OSQP problem in place for ``theta`` and solve it.

        Parameters
        ----------
        theta : array (n_theta,), see :class:`planning.mpc_model.MpcLayout`
        z_warm, y_warm : optional primal (n,) / dual (m,) warm start (e.g. the shifted
            previous solution); without them OSQP starts from its last iterate.

        Returns
        -------
        QpSolution with ``z`` and ``y`` of the unscaled problem.
        """
        q, l, u = self._scaled_vectors(theta)
        solver = self._solver
        solver.update(q=q, l=l, u=u, Ax=self._scaled_Ax(theta))
        if z_warm is not None or y_warm is not None:
            solver.warm_start(
                x=None if z_warm is None else z_warm / self._D,
                y=None if y_warm is None else y_warm * (self._c / self._E),
            )
        res = solver.solve(raise_error=False)
        info = res.info
        status = str(info.status)
        return QpSolution(
            z=res.x * self._D,
            y=res.y * (self._E / self._c),
            status=status,
            converged=status == "solved",
            iterations=int(info.iter),
            solve_time_s=float(info.solve_time),
        )

    def reset_rho(self) -> None:
        """Set OSQP's step size back to the configured ``qp_rho`` (after a failed solve)."""
        self._solver.update_settings(rho=self.config.qp_rho)

    def objective(self, z: np.ndarray, theta: np.ndarray) -> float:
        """``1/2 z'Pz + q(theta)'z`` (the QP objective without the theta-only constant)."""
        q = self._q0 + self._Mq @ theta
        return float(0.5 * z @ (self._P_full @ z) + q @ z)
