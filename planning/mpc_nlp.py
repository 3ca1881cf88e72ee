"""Reference solver: the MPC of :mod:`planning.mpc_model` as a nonlinear program for ipopt.

The same cost, dynamics and bounds as the fast path, but with the **exact** constraints:

- speed: ``||v_k||^2 <= speed_bound_k^2`` (the exact norm, smooth in squared form);
- acceleration (``accel_limit_mode = "norm"``): ``||a_k||^2 <= a_max^2`` (the per-axis box
  stays as variable bounds in both modes, like the QP);
- flight volume: the position bounds of knots 1..N are variable bounds (+-inf without one);
- clearance: ``d(p_k) + s_k >= d_safe`` where ``d`` is the distance field itself, queried
  through a ``casadi.Callback`` (:class:`FieldCallback`). The callback returns the field's
  distance at all N knots at once; its Jacobian is a second callback built from the field's own
  gradient (block-diagonal, 3 nonzeros per row). No interpolant is fitted: ipopt sees exactly
  what the field answers.

The field has no second derivatives, so ipopt runs with a limited-memory (L-BFGS) Hessian
approximation. This is a correctness reference, built once and solved from scratch per
problem; it is slow by design (tens to hundreds of milliseconds).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from planning.field import DistanceField
from planning.mpc_model import MpcFormulation

__all__ = ["MpcNlp", "NlpSolution", "FieldCallback"]

logger = logging.getLogger(__name__)


class _FieldHolder:
    """The distance field the callbacks query (swapped per solve) and a one-entry cache."""

    def __init__(self) -> None:
        self.field: DistanceField | None = None
        self._key: bytes | None = None
        self._value: tuple[np.ndarray, np.ndarray] | None = None
        self.queries = 0

    def query(self, flat_positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = flat_positions.tobytes()
        if key != self._key:
            if self.field is None:
                raise RuntimeError("no distance field set on the NLP callback")
            d, g = self.field.query(flat_positions.reshape(-1, 3))
            self._key, self._value = key, (np.asarray(d, float), np.asarray(g, float))
            self.queries += 1
        return self._value  # type: ignore[return-value]


class _FieldJacobian(ca.Callback):
    """Jacobian of :class:`FieldCallback`: inputs (positions (3N,), nominal distances (N,))."""

    def __init__(self, name: str, holder: _FieldHolder, n_points: int, opts: dict | None = None) -> None:
        ca.Callback.__init__(self)
        self._holder = holder
        self._n = n_points
        rows = np.repeat(np.arange(n_points), 3)
        cols = np.arange(3 * n_points)
        self._sp = ca.Sparsity.triplet(n_points, 3 * n_points, rows.tolist(), cols.tolist())
        self.construct(name, opts or {})

    def get_n_in(self) -> int:
        return 2

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(3 * self._n, 1) if i == 0 else ca.Sparsity.dense(self._n, 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return self._sp

    def eval(self, arg):
        _, g = self._holder.query(np.array(arg[0]).ravel())
        # nonzeros of the triplet sparsity are column-major: column j = 3 k + i -> g[k, i]
        return [ca.DM(self._sp, g.ravel().tolist())]


class FieldCallback(ca.Callback):
    """CasADi view of a :class:`DistanceField`: positions (3N,) (knot-major) -> distances (N,)."""

    def __init__(self, name: str, holder: _FieldHolder, n_points: int, opts: dict | None = None) -> None:
        ca.Callback.__init__(self)
        self._holder = holder
        self._n = n_points
        self._jac: _FieldJacobian | None = None
        self.construct(name, opts or {})

    def get_n_in(self) -> int:
        return 1

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(3 * self._n, 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self._n, 1)

    def eval(self, arg):
        d, _ = self._holder.query(np.array(arg[0]).ravel())
        return [ca.DM(d)]

    def has_jacobian(self) -> bool:
        return True

    def get_jacobian(self, name, inames, onames, opts):
        self._jac = _FieldJacobian(name, self._holder, self._n, opts)
        return self._jac


@dataclass(frozen=True, eq=False)
class NlpSolution:
    """One ipopt solve.

    Attributes
    ----------
    z : array (n_z,), primal solution
    status : str, ipopt return status (``"Solve_Succeeded"``, ...)
    converged : bool, ipopt reports success
    iterations : int
    solve_time_s : float, wall time of the solve, seconds
    cost : float, ``J(z, theta)``
    """

    z: np.ndarray
    status: str
    converged: bool
    iterations: int
    solve_time_s: float
    cost: float


class MpcNlp:
    """The reference NLP, built once; :meth:`solve` per problem with a field and ``theta``.

    Only the ``x0``, ``goal``, ``psi_ref``, ``a_prev`` and ``speed_bound`` parts of ``theta``
    are used; the linearization parameters are ignored (the constraints here are exact).
    """

    def __init__(self, formulation: MpcFormulation) -> None:
        self.formulation = formulation
        self.config = c = formulation.config
        L = self.layout = formulation.layout
        self._holder = _FieldHolder()
        self._field_fn = FieldCallback("field", self._holder, L.N)
        z = ca.MX.sym("z", L.n_z)
        th = ca.MX.sym("theta", L.n_theta)
        positions = formulation.positions(z)
        accel_sq = formulation.accel_squared(z)
        g = ca.vertcat(
            formulation.dynamics(z, th),
            formulation.speed_squared(z, th),
            accel_sq,
            self._field_fn(positions) + formulation.slack(z) - c.d_safe_m,
        )
        n_dyn, N = formulation.dynamics.size1_out(0), L.N
        n_acc = accel_sq.numel()
        self._lbg = np.concatenate([np.zeros(n_dyn), np.full(N + n_acc, -np.inf), np.zeros(N)])
        self._ubg = np.concatenate([np.zeros(n_dyn), np.zeros(N + n_acc), np.full(N, np.inf)])
        opts = {
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
            "ipopt.tol": c.nlp_tol,
            "ipopt.acceptable_tol": max(c.nlp_tol * 100, 1e-6),
            "ipopt.max_iter": c.nlp_max_iter,
            "ipopt.hessian_approximation": "limited-memory",
            "ipopt.limited_memory_max_history": 30,
            "ipopt.mu_strategy": "adaptive",
        }
        self._solver = ca.nlpsol("mpc_nlp", "ipopt", {"x": z, "p": th, "f": formulation.cost(z, th), "g": g}, opts)

    def solve(self, theta: np.ndarray, field: DistanceField, z_init: np.ndarray) -> NlpSolution:
        """Solve the exact NLP for ``theta`` against ``field`` from the initial guess ``z_init``.

        Parameters
        ----------
        theta : array (n_theta,)
        field : DistanceField, queried through the callback
        z_init : array (n_z,), initial guess (e.g. the fast path's linearization trajectory)
        """
        lbz, ubz = (np.array(b).ravel() for b in self.formulation.z_bounds(theta))
        z0 = np.clip(np.asarray(z_init, dtype=float), lbz, ubz)
        self._holder.field = field
        t0 = time.perf_counter()
        try:
            res = self._solver(x0=z0, p=theta, lbx=lbz, ubx=ubz, lbg=self._lbg, ubg=self._ubg)
        finally:
            self._holder.field = None
        elapsed = time.perf_counter() - t0
        stats = self._solver.stats()
        z = np.array(res["x"]).ravel()
        return NlpSolution(
            z=z,
            status=str(stats.get("return_status", "unknown")),
            converged=bool(stats.get("success", False)),
            iterations=int(stats.get("iter_count", -1)),
            solve_time_s=elapsed,
            cost=float(res["f"]),
        )
