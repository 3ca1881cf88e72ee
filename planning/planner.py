"""The receding-horizon planner: build once, step every control period.

``Planner(config, solver="qp")`` builds the CasADi formulation and its solver once (the fast
path's QP data compiled once per formulation and cached, :mod:`planning.mpc_codegen`);
``planner.step(state, goal_world, field, volume=None)`` returns a :class:`PlanResult` with the trajectory,
the first command and everything a log needs. One step (the fast path) is one real-time
iteration:

1. **Goal check.** A goal with clearance below ``d_safe + goal_clearance_margin`` is moved to
   the nearest point with that clearance: Newton steps along the field gradient
   (``g += (target - d) grad``), and if that fails within ``goal_search_max_m``, a line search
   back along the segment toward the vehicle. With a flight volume the goal is also clamped into
   it (shrunk by ``body_radius_m``). ``PlanResult.goal_adjusted`` says so.
2. **Attractor.** If the straight segment from the vehicle to the goal keeps ``d_safe``, the
   progress terms pull toward the goal. Otherwise the front-end (:mod:`planning.guide_path`, a
   clearance-aware grid search run when the goal changes or the path is blocked) supplies a
   path and the attractor is the point ``guide_lookahead_m`` ahead on it: a linearized-distance
   MPC alone stops at a wall it could fly around (Fast-Planner pairs its optimizer with a search
   front-end for the same reason). The search stays inside the volume, above
   ``guide_floor_m`` and below ``guide_ceiling_m``, out of unknown space, within its node
   budget (``guide_max_cells``) and, if set, its time budget. The yaw term always uses the goal.
3. **Linearization point.** The previous plan's inputs shifted by one knot, rolled out from the
   *measured* state with the exact model (so it is dynamically consistent even after a
   disturbance). On the first step (or after :meth:`Planner.reset`) the vehicle coasts
   (zero inputs) and ``cold_start_iterations`` QPs are solved in sequence instead of one.
4. **One QP.** Field distance and gradient at the linearized knots give
   ``d(pbar_k) + grad_k . (p_k - pbar_k) + s_k >= d_safe`` for knots 1..N (knot 0 is the
   measured state, pinned, never softened); the speed norm is cut by the half-space at the
   previous direction plus cutting planes kept from earlier solves, and so is the acceleration
   norm (``accel_limit_mode = "norm"``); the flight volume, shrunk by the body radius, the
   tracking margin and the drift margin (``drift_margin_m``), bounds every knot's position; the
   QP data come from one call of the compiled (or NumPy) step data; OSQP is updated in place and
   warm-started from the shifted previous primal (its last dual iterate is kept). If the true
   speed (acceleration) norm of the result exceeds the limit by more than
   ``speed_tolerance_rel`` (``accel_tolerance_rel``) a cut is added at the violating knots and the
   QP is solved again (at most ``max_speed_refinements`` times). After a failed solve the next
   one starts from zero duals and the configured rho. With ``step_time_budget_ms`` OSQP gets the
   time left, and a step out of time skips to the fallback with status ``timeout``.
5. **Check.** The inputs are clipped to their (exact) bounds (the acceleration scaled onto the
   norm ball), rolled out with the exact model, and the plan is accepted only if the solve
   converged, the speed norm is within tolerance, the knots are inside the volume, and
   the field's true clearance over the braking horizon stays above
   ``min(d_safe, d(p_0)) - safety_tolerance_m``.
6. **Fallback.** Otherwise the shifted previous plan is used if it passes the same check, and
   else a braking plan (maximum deceleration along -v, yaw held). A step always returns a
   command.

Yaw. The reference is the goal bearing ``psi_g = atan2(g_y - y, g_x - x)`` from the current
position (the paper's yaw term, not the path tangent), unwrapped near the current yaw with
:func:`planning.frames.unwrap_near`. Within ``yaw_hold_radius_m`` (horizontal) of the goal the
bearing is undefined and the reference is the current yaw: the vehicle holds its heading.

Frames. The QP is posed in a frame translated to the vehicle's position (axes of the world
ENU frame), so solver tolerances mean the same everywhere; every array in :class:`PlanResult`
is in world ENU.
"""

from __future__ import annotations

import enum
import logging
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from planning.field import DistanceField
from planning.frames import unwrap_near, wrap_angle
from planning.guide_path import carrot_on_path, guide_search, segment_clear, segment_points
from planning.mpc_model import NU, NX, MpcFormulation, simulate
from planning.planner_config import VOLUME_DRIFT_STEP_M, PlannerConfig
from planning.trajectory import Trajectory, VehicleState
from planning.volume import FlightVolume

__all__ = [
    "Planner",
    "PlanResult",
    "ControlCommand",
    "SolveStatus",
    "Fallback",
    "PlannerInputError",
    "adjust_goal",
    "ClosedLoopLog",
    "ProblemSnapshot",
    "ShiftedField",
    "InflatedField",
    "run_closed_loop",
]

logger = logging.getLogger(__name__)

SOLVERS = ("qp", "nlp")

#: Tracking errors below this give no margin: half a voxel of the ESDF (0.1 m), below what the
#: map resolves (its obstacles are placed to +-5 cm), and what the ideal world's tracker lags a
#: plan by (up to ~3 cm: plans may exceed v_max by the QP's 1 % speed tolerance, the vehicle
#: does not). A margin of a few centimetres that changes every step measured worse: it moved the
#: clearance constraint under plans that were at it, and the planner fell back to shifted plans
#: step after step (tests/test_pilot.py's two-subtask flight stalled to the time limit).
_TRACKING_NOISE_FLOOR_M = 0.05

#: Step, metres, of the raised segments :func:`adjust_goal` searches last.
_GOAL_LIFT_STEP_M = 0.25


class PlannerInputError(ValueError):
    """A state, goal or field answer the planner cannot use (wrong shape, NaN, wrong type)."""


class SolveStatus(enum.Enum):
    """Outcome of the optimization in one step (before any fallback)."""

    SOLVED = "solved"
    """Converged, within limits, clearance check passed."""
    NOT_CONVERGED = "not_converged"
    """Iteration limit or inaccurate solution."""
    INFEASIBLE = "infeasible"
    """The solver reported (primal or dual) infeasibility."""
    UNSAFE = "unsafe"
    """Converged, but the rolled-out plan failed the speed or clearance check."""
    FAILED = "failed"
    """Numerical failure (NaN) or solver error."""
    TIMEOUT = "timeout"
    """The step's time budget (``step_time_budget_ms``) ran out before or during the solve."""


class Fallback(enum.Enum):
    """Which plan the command comes from."""

    NONE = "none"
    """The fresh optimized plan."""
    SHIFTED = "shifted"
    """The previous plan shifted by one knot, re-rolled from the measured state."""
    BRAKE = "brake"
    """Maximum deceleration along -v, yaw held."""


@dataclass(frozen=True, eq=False)
class ControlCommand:
    """The first input of a plan, to hold for one control period.

    Attributes
    ----------
    a : array (3,), acceleration, m/s^2, world ENU
    yaw_rate : float, rad/s
    """

    a: np.ndarray
    yaw_rate: float


@dataclass(frozen=True, eq=False)
class ProblemSnapshot:
    """The optimization problem a step posed, for re-solving it with another solver.

    Attributes
    ----------
    theta : array (n_theta,), parameters in the vehicle-centred frame (see
        :class:`planning.mpc_model.MpcLayout`)
    origin : array (3,), world ENU position of that frame's origin (the vehicle), metres
    z_init : array (n_z,), the linearization point the step started from (decision layout)
    z_plan : array (n_z,), the returned plan in decision layout (slack = the exact field's
        clearance shortfall, so ``cost(z_plan, theta)`` is the plan's cost in the exact problem)
    """

    theta: np.ndarray
    origin: np.ndarray
    z_init: np.ndarray
    z_plan: np.ndarray


@dataclass(frozen=True, eq=False)
class PlanResult:
    """Everything one planner step produced (world ENU, SI units).

    Attributes
    ----------
    trajectory : Trajectory, the plan (knot 0 = the measured state)
    command : ControlCommand, ``trajectory.a[0]`` and ``trajectory.yaw_rate[0]``
    status : SolveStatus, outcome of the optimization this step
    fallback : Fallback, NONE when the command comes from the fresh plan
    iterations : int, solver iterations summed over the QPs (or ipopt iterations) of this step
    qp_solves : int, number of solver calls this step
    solve_time_ms : float, wall time of the whole step (data, solve, checks), milliseconds
    slack_max_m : float, largest clearance slack of the accepted optimized plan, metres
        (0 for fallback plans)
    min_predicted_clearance_m : float, the field's distance minimized over knots 1..N of the
        returned trajectory, metres
    goal_used : array (3,), the goal the plan aims for (after adjustment), world ENU
    goal_adjusted : bool, the requested goal was moved to a point with clearance
    attractor : array (3,), the point the progress terms pulled toward this step: the goal
        used, or a point on the front-end's guide path when the straight segment to the goal
        lacks clearance (world ENU)
    cpu_time_ms : float, CPU time of this thread over the step, milliseconds (beside the wall
        time ``solve_time_ms``: a large gap means the process waited for a core)
    guide_search_ms : float, wall time of the guide search run this step, milliseconds (0 when
        none ran)
    guide_status : str, ``""`` (no search this step) or the search's status (``"found"``,
        ``"budget"``, ``"unreachable"``, see :class:`planning.guide_path.GuideResult`)
    tracking_error_m : float, ``|previous plan(t) - measured position|`` this step, metres
        (NaN when no previous plan covers ``t``)
    tracking_margin_m : float, the margin added to ``d_safe_m`` and ``body_radius_m`` this step
        (the largest recent tracking error, capped), metres
    from_reference : bool, the plan started from the previous plan's reference state (else
        from the measured state)
    """

    trajectory: Trajectory
    command: ControlCommand
    status: SolveStatus
    fallback: Fallback
    iterations: int
    qp_solves: int
    solve_time_ms: float
    slack_max_m: float
    min_predicted_clearance_m: float
    goal_used: np.ndarray
    goal_adjusted: bool
    attractor: np.ndarray
    cpu_time_ms: float = 0.0
    guide_search_ms: float = 0.0
    guide_status: str = ""
    tracking_error_m: float = float("nan")
    tracking_margin_m: float = 0.0
    from_reference: bool = False

    @property
    def ok(self) -> bool:
        """True when the command comes from a fresh, converged, checked plan."""
        return self.fallback is Fallback.NONE


def _query(field: DistanceField, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Query a field and validate its answer."""
    try:
        d, g = field.query(points)
    except PlannerInputError:
        raise
    except (ValueError, TypeError) as exc:
        raise PlannerInputError(f"the distance field rejected a query: {exc}") from exc
    d = np.asarray(d, dtype=float)
    g = np.asarray(g, dtype=float)
    n = points.shape[0]
    if d.shape != (n,) or g.shape != (n, 3):
        raise PlannerInputError(
            f"field.query returned shapes {d.shape}, {g.shape}; expected ({n},), ({n}, 3)"
        )
    if not (np.isfinite(d).all() and np.isfinite(g).all()):
        raise PlannerInputError("field.query returned NaN or inf distance/gradient")
    return d, g


def adjust_goal(
    goal: np.ndarray,
    vehicle_p: np.ndarray,
    field: DistanceField,
    clearance_m: float,
    search_max_m: float,
    iterations: int = 30,
    goal_query: tuple[float, np.ndarray] | None = None,
    lift_max_m: float = 0.0,
    lift_margin_m: float = 0.0,
) -> tuple[np.ndarray, bool]:
    """Move ``goal`` to the nearest point with clearance at least ``clearance_m``.

    Newton steps on the distance field, ``g <- g + (clearance_m - d(g) + 1 mm) grad / |grad|``,
    while the total displacement stays within ``search_max_m``; if that does not reach the
    clearance (a medial ridge, a thick obstacle), the segment from the goal back toward the
    vehicle is searched in 2.5 cm steps for the first point with the clearance. If no point on
    it has the clearance, the same segment raised in 0.25 m steps up to ``lift_max_m`` is
    searched, and the point with the clearance (plus ``lift_margin_m``) nearest the goal is
    returned (a target on a floor or a ledge lower than the clearance allows: the whole line
    toward it is too close to the floor, a point above it is not). If none has it either, the
    point of largest clearance on the segment is returned.

    Parameters
    ----------
    goal, vehicle_p : arrays (3,), metres, world ENU
    field : DistanceField
    clearance_m : required clearance, metres
    search_max_m : largest displacement of the gradient ascent, metres
    goal_query : optional ``(d, grad (3,))`` already known at ``goal`` (saves a query)
    lift_max_m : highest raise of the segment searched last, metres (0: none)
    lift_margin_m : metres a raised point needs beyond ``clearance_m`` (the planner's tracking
        margin, by which the body sphere's top grows: no lift then lands in that top)

    Returns
    -------
    goal_used (3,), adjusted (bool)
    """
    if goal_query is None:
        d, g = _query(field, goal[None, :])
        goal_query = (float(d[0]), g[0])
    di, gi = goal_query
    if di >= clearance_m:
        return goal.copy(), False
    p = goal.copy()
    for _ in range(iterations):
        n = np.linalg.norm(gi)
        if n < 1e-9:
            break
        p = p + (clearance_m - di + 1e-3) * gi / n
        if np.linalg.norm(p - goal) > search_max_m:
            break
        dd, gg = _query(field, p[None, :])
        di, gi = dd[0], gg[0]
        if di >= clearance_m:
            return p, True
    seg = vehicle_p - goal
    length = float(np.linalg.norm(seg))
    steps = max(2, int(np.ceil(length / 0.025)) + 1)
    t = np.linspace(0.0, 1.0, steps)[:, None]
    pts = goal[None, :] + t * seg[None, :]
    dd, _ = _query(field, pts)
    ok = np.flatnonzero(dd >= clearance_m)
    if ok.size:
        return pts[ok[0]].copy(), True
    n_lifts = int(np.floor(lift_max_m / _GOAL_LIFT_STEP_M + 1e-9))
    if n_lifts > 0:
        lifts = _GOAL_LIFT_STEP_M * np.arange(1, n_lifts + 1)
        raised = (pts[None, :, :] + lifts[:, None, None] * np.array([0.0, 0.0, 1.0])).reshape(-1, 3)
        dr, _ = _query(field, raised)
        ok = np.flatnonzero(dr >= clearance_m + lift_margin_m)
        if ok.size:
            best = ok[int(np.argmin(np.linalg.norm(raised[ok] - goal, axis=1)))]
            return raised[best].copy(), True
    return pts[int(np.argmax(dd))].copy(), True


def _row_norms(M: np.ndarray) -> np.ndarray:
    """Euclidean norm of each row of ``M`` (n, 3) (cheaper than ``np.linalg.norm`` on small arrays)."""
    return np.sqrt(np.einsum("ij,ij->i", M, M))


class ShiftedField:
    """A :class:`DistanceField` seen from a frame translated to ``origin`` (3,), world ENU:
    ``query(points)`` answers for ``points + origin``. The planner poses its problems in the
    vehicle-centred frame; this hands the reference NLP the same view of the map."""

    def __init__(self, field: DistanceField, origin: np.ndarray) -> None:
        self._field, self._origin = field, origin

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _query(self._field, np.asarray(points, dtype=float) + self._origin)


class InflatedField:
    """A :class:`DistanceField` whose obstacles are inflated by ``margin_m``: ``query`` answers
    ``d - margin_m`` with the same gradient, so every clearance the planner keeps (``d_safe_m``
    in the QP, the goal check, the guide search, the plan check) grows by the margin. Every
    other attribute (``known``, ``is_unknown`` ...) is the wrapped field's."""

    def __init__(self, field: DistanceField, margin_m: float) -> None:
        if not (np.isfinite(margin_m) and margin_m >= 0):
            raise PlannerInputError(f"margin_m must be finite and >= 0, got {margin_m}")
        self._field, self.margin_m = field, float(margin_m)

    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, g = _query(self._field, points)
        return d - self.margin_m, g

    def __getattr__(self, name: str):
        return getattr(self._field, name)


class Planner:
    """Receding-horizon MPC planner (see the module docstring for one step).

    Parameters
    ----------
    config : PlannerConfig
    solver : ``"qp"`` (fast path: persistent OSQP, one QP per step) or ``"nlp"`` (reference:
        ipopt with exact speed and acceleration norms and exact field constraints, every step
        from the shifted previous plan)
    qp_backend : how the fast path builds its QP data (:data:`planning.mpc_qp.QP_BACKENDS`):
        ``"auto"`` (the compiled C function of :mod:`planning.mpc_codegen`, built once and
        cached, or NumPy when no compiler is available), ``"compiled"`` or ``"python"``
    """

    #: Keep a :class:`ProblemSnapshot` of every step in :attr:`last_problem` (benchmarks,
    #: solver comparisons); off by default, it copies a few arrays per step.
    record_problems: bool = False
    last_problem: ProblemSnapshot | None = None

    def __init__(self, config: PlannerConfig | None = None, solver: str = "qp", qp_backend: str = "auto") -> None:
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        self.config = config if config is not None else PlannerConfig()
        if not isinstance(self.config, PlannerConfig):
            raise PlannerInputError(f"config must be a PlannerConfig, got {type(self.config).__name__}")
        self.solver_name = solver
        self.formulation = MpcFormulation(self.config)
        self.layout = self.formulation.layout
        from planning.mpc_qp import DataLayout

        if solver == "qp":
            from planning.mpc_qp import MpcQp

            self._qp = MpcQp(self.formulation, backend=qp_backend)
            self._nlp = None
            self._dl = self._qp.data_layout
        else:
            from planning.mpc_nlp import MpcNlp

            self._qp = None
            self._nlp = MpcNlp(self.formulation)
            self._dl = DataLayout(self.layout, 0, 0, 0)
        c, L = self.config, self.layout
        N, K = L.N, L.speed_cuts
        self._norm_accel = L.accel_cuts > 0
        self._k_dt = np.arange(1, N + 1) * c.dt_s
        self._u_max = np.array([c.a_max_mps2] * 3 + [c.yaw_rate_max_rps])
        self._idx_u = L.idx_u
        self._idx_a = L.idx_a
        self._idx_v1 = L.idx_v[1:]
        self._idx_s = L.idx_s
        self._w = np.zeros(self._dl.n_w)
        W = self._dl.w
        self._w_u = self._w[W["u_bar"]].reshape(N, NU)
        self._w_d = self._w[W["lin_d"]]
        self._w_g = self._w[W["lin_grad"]].reshape(N, 3)
        self._check_steps = c.braking_steps
        self._pos_lo = np.full(3, -np.inf)
        self._pos_hi = np.full(3, np.inf)
        self.reset()
        logger.debug("Planner built: solver=%s N=%d K=%d backend=%s", solver, N, K, self.qp_backend)

    @property
    def qp_backend(self) -> str:
        """``"compiled"`` or ``"python"`` (how the QP data are built), ``"nlp"`` for ipopt."""
        return "nlp" if self._qp is None else self._qp.backend

    def reset(self) -> None:
        """Forget the previous plan (the next step cold-starts)."""
        L = self.layout
        self._prev_u: np.ndarray | None = None
        # the last solution the check refused on clearance: the next step linearizes around
        # it, not around the fallback flown meanwhile (real-time iteration: the linearization
        # point is the last QP iterate, applied or not)
        self._lin_u: np.ndarray | None = None
        self._prev_s = np.zeros(L.N)
        self._cuts: np.ndarray | None = None  # (N, K, 3)
        self._acuts: np.ndarray | None = None  # (N, Ka, 3)
        self._qp_healthy = False
        self._guide: np.ndarray | None = None  # (n, 3) world ENU
        self._guide_goal: np.ndarray | None = None
        self._guide_attempt_t: float | None = None
        self._guide_ms = 0.0
        self._guide_status = ""
        self._prev_traj: Trajectory | None = None
        self._track: deque[tuple[float, float]] = deque()  # (t_s, measured tracking error m)
        self._flown_m = 0.0  # distance flown since reset (estimate, counted in VOLUME_DRIFT_STEP_M moves)
        self._flown_anchor: np.ndarray | None = None  # where the last counted move ended

    # ------------------------------------------------------------------ tracking
    def _reference(self, state: VehicleState) -> tuple[VehicleState, float, bool]:
        """The state this step plans from, the measured tracking error and whether the plan
        starts from the reference (see ``reference_start`` in :class:`PlannerConfig`).

        The error ``|prev_plan(t) - p|`` is recorded for the tracking margin whenever the
        previous plan covers ``t`` (at most ``reference_max_age_s`` old)."""
        c = self.config
        prev = self._prev_traj
        if prev is None or not (-1e-9 <= state.t_s - prev.t0_s <= c.reference_max_age_s):
            return state, float("nan"), False
        p_r, v_r, _, _, _ = prev.sample(state.t_s)
        # the acceleration the reference held over the period just flown (the jerk term's
        # "last command"; the measured one carries the gusts)
        a_r = prev.sample(state.t_s - 0.5 * prev.dt_s)[2]
        err = float(np.linalg.norm(p_r - state.p))
        self._track.append((float(state.t_s), err))
        if not c.reference_start or err > c.reference_reset_m:
            return state, err, False
        return VehicleState(state.t_s, p_r, v_r, state.yaw, state.yaw_rate, a_r), err, True

    @property
    def tracking_margin_m(self) -> float:
        """The clearance and volume margin of the next step: the largest measured tracking
        error of the last ``tracking_window_s``, capped at ``tracking_margin_max_m`` (metres)."""
        c = self.config
        if c.tracking_margin_max_m <= 0 or not self._track:
            return 0.0
        peak = max(e for _, e in self._track)
        if peak < _TRACKING_NOISE_FLOOR_M:
            return 0.0
        return min(c.tracking_margin_max_m, peak)

    @property
    def drift_margin_m(self) -> float:
        """The flight volume's margin for odometry drift (metres): ``volume_drift_fraction``
        times the distance flown since :meth:`reset`, at most ``volume_drift_max_m``. Goals
        chosen against the volume (the pilot's, the baselines') add it to their own margin, so
        that they stay reachable."""
        c = self.config
        return min(c.volume_drift_fraction * self._flown_m, c.volume_drift_max_m)

    @property
    def volume_goal_margin_m(self) -> float:
        """How far a goal chosen against the flight volume keeps from its faces, metres:
        ``d_safe_m`` plus :attr:`drift_margin_m`. The pilot, the baselines that fly this planner
        and the replay clamp their goals with it, so that the planner's own box (shrunk by the
        body radius, the tracking margin and the drift margin) does not move them again."""
        return float(self.config.d_safe_m) + self.drift_margin_m

    def _count_flown(self, p: np.ndarray) -> None:
        if self._flown_anchor is None:
            self._flown_anchor = p.copy()
            return
        move = float(np.linalg.norm(p - self._flown_anchor))
        if move >= VOLUME_DRIFT_STEP_M:
            self._flown_m += move
            self._flown_anchor = p.copy()

    def _forget_old_errors(self, t_s: float) -> None:
        window = self.config.tracking_window_s
        while self._track and self._track[0][0] < t_s - window - 1e-9:
            self._track.popleft()

    # ------------------------------------------------------------------ validation
    def _validate(self, state, goal_world, field, volume) -> np.ndarray:
        if not isinstance(state, VehicleState):
            raise PlannerInputError(f"state must be a VehicleState, got {type(state).__name__}")
        goal = np.asarray(goal_world, dtype=float) if not isinstance(goal_world, str) else None
        if goal is None or goal.shape != (3,):
            raise PlannerInputError(f"goal_world must have shape (3,), got {np.shape(goal_world)}")
        if not np.all(np.isfinite(goal)):
            raise PlannerInputError(f"goal_world must be finite, got {goal}")
        if not callable(getattr(field, "query", None)):
            raise PlannerInputError(
                f"field must implement DistanceField.query(points), got {type(field).__name__}"
            )
        if volume is not None and not isinstance(volume, FlightVolume):
            raise PlannerInputError(f"volume must be a FlightVolume or None, got {type(volume).__name__}")
        return goal

    def _guide_z_limits(self, box: FlightVolume | None) -> tuple[float | None, float | None]:
        """Floor and ceiling of the guide search: the configured ones intersected with the
        volume's z-extent (already shrunk by the body radius)."""
        c = self.config
        lo, hi = c.guide_floor_m, c.guide_ceiling_m
        if box is not None:
            lo = float(box.min_m[2]) if lo is None else max(lo, float(box.min_m[2]))
            hi = float(box.max_m[2]) if hi is None else min(hi, float(box.max_m[2]))
        return lo, hi

    def _position_box(self, box: FlightVolume | None, state: VehicleState) -> tuple[np.ndarray, np.ndarray]:
        """Position bounds of knots 1..N in the vehicle-centred frame: the shrunk volume, widened
        on an axis only as far as a vehicle already outside it (or unable to stop inside it)
        needs to brake at ``a_max`` along ``-v`` (so the QP stays feasible); +-inf without one."""
        if box is None:
            return self._pos_lo, self._pos_hi
        c = self.config
        p, v = state.p, state.v
        speed = float(np.linalg.norm(v))
        excursion = np.abs(v) * speed / (2.0 * c.a_max_mps2) + 1e-3
        lo = np.minimum(box.min_m, p - np.where(v < 0, excursion, 1e-3)) if np.any(
            p - np.where(v < 0, excursion, 0.0) < box.min_m
        ) else box.min_m.copy()
        hi = np.maximum(box.max_m, p + np.where(v > 0, excursion, 1e-3)) if np.any(
            p + np.where(v > 0, excursion, 0.0) > box.max_m
        ) else box.max_m.copy()
        return lo - p, hi - p

    # ------------------------------------------------------------------ step
    def step(
        self,
        state: VehicleState,
        goal_world: np.ndarray,
        field: DistanceField,
        yaw_ref: float | None = None,
        volume: FlightVolume | None = None,
    ) -> PlanResult:
        """Plan from ``state`` toward ``goal_world`` in ``field``; always returns a command.

        Parameters
        ----------
        state : VehicleState, measured state (world ENU)
        goal_world : array (3,), metres, world ENU
        field : DistanceField, signed distance and gradient (world ENU)
        yaw_ref : optional heading in radians that replaces the goal bearing as the yaw
            reference (e.g. turning in place toward a target or a recovery heading); it is
            unwrapped relative to the current yaw like the bearing
        volume : optional operator flight volume (:class:`planning.volume.FlightVolume`, world
            ENU). Every plan knot 1..N stays inside it shrunk by ``body_radius_m`` (hard
            position bounds in the QP and the NLP), the goal is clamped into that box
            (``goal_adjusted`` then), and the guide search never leaves it. A vehicle already
            outside (or too fast to stop inside) gets the least widening that lets it brake.

        Raises
        ------
        PlannerInputError
            Wrong types, shapes, or non-finite values in the inputs or in the field's answer.
        """
        t_start = time.perf_counter()
        cpu_start = time.thread_time()
        goal = self._validate(state, goal_world, field, volume)
        c, L = self.config, self.layout
        N, dt = L.N, c.dt_s
        budget_s = c.step_time_budget_ms * 1e-3
        measured = state
        state, track_err, from_ref = self._reference(measured)
        self._forget_old_errors(measured.t_s)
        self._count_flown(measured.p)
        margin = self.tracking_margin_m
        if margin > 0:
            field = InflatedField(field, margin)
        box = volume.shrunk(c.body_radius_m + margin + self.drift_margin_m) if volume is not None else None
        clamped = False
        if box is not None:
            inside = box.clamp(goal)
            clamped = bool(np.any(inside != goal))
            goal = inside
        origin = state.p.copy()
        x0 = np.empty(NX)
        x0[0:3] = 0.0
        x0[3:6] = state.v
        x0[6] = state.yaw
        self._guide_ms, self._guide_status = 0.0, ""

        # linearization point first: one field query serves it, the goal check and the attractor
        cold = self._prev_u is None
        last = self._prev_u if self._lin_u is None else self._lin_u
        self._lin_u = None
        if cold:
            u_bar = np.zeros((N, NU))
        else:
            u_bar = np.empty((N, NU))
            u_bar[:-1] = last[1:]
            u_bar[-1] = last[-1]
        X_bar = simulate(x0, u_bar, dt)
        extra = self._attractor_points(origin, goal)
        pts = np.concatenate([goal[None, :], origin[None, :], X_bar[1:, 0:3] + origin, extra])
        d_all, g_all = _query(field, pts)
        d0 = float(d_all[1])

        # goal check, attractor, yaw reference
        goal_clear = c.d_safe_m + c.goal_clearance_margin_m
        # a lift needs the tracking margin too: the body sphere's top grows by it
        # (EsdfConfig.body_clear_above_m), and a lift (0.25 m) must never land in that top
        goal_used, adjusted = adjust_goal(
            goal, origin, field, goal_clear, c.goal_search_max_m, goal_query=(float(d_all[0]), g_all[0]),
            lift_max_m=c.goal_lift_max_m, lift_margin_m=margin,
        )
        if box is not None and adjusted:
            goal_used = box.clamp(goal_used)
        adjusted = adjusted or clamped
        pre = None if adjusted else (extra, d_all[N + 2 :])
        attractor = self._attractor(state.t_s, origin, d0, goal_used, field, pre, box)
        goal_local = attractor - origin
        to_goal = goal_used - origin
        horiz = float(np.hypot(to_goal[0], to_goal[1]))
        if yaw_ref is not None:
            if not np.isfinite(yaw_ref):
                raise PlannerInputError(f"yaw_ref must be finite, got {yaw_ref}")
            psi_ref = float(unwrap_near(float(yaw_ref), state.yaw))
        elif horiz > c.yaw_hold_radius_m:
            psi_ref = float(unwrap_near(np.arctan2(to_goal[1], to_goal[0]), state.yaw))
        else:
            psi_ref = float(state.yaw)

        # speed bound per knot (above v_max only while braking an initial overspeed)
        speed0 = float(np.linalg.norm(state.v))
        bound = np.maximum(c.v_max_mps, speed0 - c.a_max_mps2 * self._k_dt)
        pos_lo, pos_hi = self._position_box(box, state)

        w, W = self._w, self._dl.w
        w[W["x0"]] = x0
        w[W["goal"]] = goal_local
        w[W["psi_ref"]] = psi_ref
        w[W["a_prev"]] = state.a
        w[W["speed_bound"]] = bound
        w[W["pos_lo"]] = pos_lo
        w[W["pos_hi"]] = pos_hi
        w[W["pos_active"]] = 0.0 if box is None else 1.0

        iterations = 0
        solves = 0
        status = SolveStatus.FAILED
        plan = None
        slack_max = 0.0
        n_outer = max(1, c.cold_start_iterations) if cold and self._qp is not None else 1
        # Duals: OSQP keeps its last dual iterate, which we reuse unshifted. Shifting them one
        # knot (like the primal) measured worse: at rest against an obstacle it moves the
        # terminal multiplier onto knot N - 1 and costs hundreds of iterations.
        y_warm = None
        if self._qp is not None and not self._qp_healthy:
            # the last solve failed: its dual iterate and adapted rho are not a warm start
            y_warm = np.zeros(self._qp.m)
            self._qp.reset_rho()
        s_warm = np.zeros(N) if cold else np.concatenate([self._prev_s[1:], self._prev_s[-1:]])
        knots_query = (d_all[2 : N + 2], g_all[2 : N + 2])
        theta = None
        z_init = None
        deadline = t_start + budget_s if budget_s > 0 else None
        for outer in range(n_outer):
            if deadline is not None and time.perf_counter() >= deadline:
                status = SolveStatus.TIMEOUT
                break
            if outer > 0:
                X_bar = simulate(x0, u_bar, dt)
                knots_query = None
            cuts_mode = ("fresh" if outer == 0 else "keep") if cold else "shift"
            self._linearize(X_bar, u_bar, s_warm, origin, goal_local, field, cuts_mode, knots_query)
            sol = self._solve(field, origin, deadline, y_warm=y_warm, record=z_init is None)
            if z_init is None:
                theta, z_init = sol[5], sol[6]
            iterations += sol[2]
            solves += sol[3]
            status, z, y = sol[0], sol[1], sol[4]
            self._qp_healthy = status in (SolveStatus.SOLVED, SolveStatus.UNSAFE)
            # a cold start's early iterations may end with the speed norm not yet cut tight
            # enough (its cuts start at one guessed direction): re-linearize and go on
            more = status is SolveStatus.UNSAFE and z is not None and outer < n_outer - 1
            if (status is not SolveStatus.SOLVED or z is None) and not more:
                break
            u_bar = self._clip_inputs(z[self._idx_u])
            s_warm = z[self._idx_s]
            y_warm = y
        if status is SolveStatus.SOLVED:
            U = u_bar
            X = simulate(x0, U, dt)
            ok, dmin, d_knots = self._check(X, U, origin, field, d0, bound, pos_lo, pos_hi)
            if ok:
                plan = (X, U, d_knots)
                slack_max = float(np.max(z[self._idx_s], initial=0.0))
                self._prev_s = np.maximum(z[self._idx_s], 0.0)
            else:
                # a plan that swings into an obstacle the linearization's cuts do not hold:
                # linearized around the fallback again (at rest: the hold) the next step would
                # pose the same problem and be refused the same way, and the vehicle would hold
                # for good (park-l02: 17 s at a picnic table); around this plan, the cuts sit
                # where it went wrong
                status = SolveStatus.UNSAFE
                if not self._clearance_ok(d_knots, d0):
                    self._lin_u = U
        fallback = Fallback.NONE
        if plan is None and not cold:
            U = np.empty((N, NU))
            U[:-1] = self._prev_u[1:]
            U[-1] = 0.0
            X = simulate(x0, U, dt)
            ok, _, d_knots = self._check(X, U, origin, field, d0, bound, pos_lo, pos_hi)
            if ok:
                plan, fallback = (X, U, d_knots), Fallback.SHIFTED
        if plan is None:
            U = self._braking_inputs(state.v)
            X = simulate(x0, U, dt)
            d_knots, _ = _query(field, X[1:, 0:3] + origin)
            plan, fallback = (X, U, d_knots), Fallback.BRAKE
        if fallback is not Fallback.NONE:
            self._prev_s = np.zeros(N)
            logger.info("planner fallback %s (status %s)", fallback.value, status.value)
        X, U, d_knots = plan
        self._prev_u = U
        if self.record_problems:
            if theta is None:  # no solve ran (out of time): the problem as posed
                self._linearize(X_bar, u_bar, s_warm, origin, goal_local, field, "keep", knots_query)
                theta, z_init = self._theta_and_warm()
            self.last_problem = ProblemSnapshot(
                theta=theta,
                origin=origin,
                z_init=z_init,
                z_plan=self._assemble_z(X, U, np.maximum(c.d_safe_m - d_knots, 0.0)),
            )

        P = X[:, 0:3] + origin
        traj = Trajectory(
            t0_s=state.t_s, dt_s=dt, p=P, v=X[:, 3:6], yaw=X[:, 6], a=U[:, 0:3], yaw_rate=U[:, 3]
        )
        self._prev_traj = traj
        command = ControlCommand(a=U[0, 0:3].copy(), yaw_rate=float(U[0, 3]))
        return PlanResult(
            trajectory=traj,
            command=command,
            status=status,
            fallback=fallback,
            iterations=iterations,
            qp_solves=solves,
            solve_time_ms=(time.perf_counter() - t_start) * 1e3,
            slack_max_m=slack_max,
            min_predicted_clearance_m=float(np.min(d_knots)),
            goal_used=goal_used,
            goal_adjusted=adjusted,
            attractor=attractor,
            cpu_time_ms=(time.thread_time() - cpu_start) * 1e3,
            guide_search_ms=self._guide_ms,
            guide_status=self._guide_status,
            tracking_error_m=track_err,
            tracking_margin_m=margin,
            from_reference=from_ref,
        )

    def converge(
        self, problem: ProblemSnapshot, field: DistanceField, max_iterations: int = 20, tol: float = 1e-4
    ) -> tuple[np.ndarray, int]:
        """Iterate the fast path's QP on one problem to its fixed point (sequential QP).

        The step solves *one* QP about the shifted previous plan (real-time iteration); this
        re-linearizes clearance, speed and acceleration about each new solution, with the goal,
        state and bounds of ``problem`` fixed, until the inputs change by less than ``tol``
        (m/s^2, rad/s). At the fixed point the proximal term vanishes and the QP's optimum is a
        KKT point of the exact problem, which is what :mod:`planning.mpc_nlp` solves. The
        planner's own state (previous plan, cuts) is left untouched.

        Returns
        -------
        z : array (n_z,), inputs clipped to their bounds, states rolled out exactly, slack
            equal to the exact field's shortfall
        iterations : QP solves used
        """
        if self._qp is None:
            raise ValueError("converge() needs the QP solver (Planner(solver='qp'))")
        c, L = self.config, self.layout
        saved = (
            self._w.copy(),
            None if self._cuts is None else self._cuts.copy(),
            None if self._acuts is None else self._acuts.copy(),
        )
        try:
            th = problem.theta
            w, W = self._w, self._dl.w
            x0 = th[L.th_x0].copy()
            goal_local = th[L.th_goal].copy()
            w[W["x0"]] = x0
            w[W["goal"]] = goal_local
            w[W["psi_ref"]] = th[L.th_psi_ref]
            w[W["a_prev"]] = th[L.th_a_prev]
            w[W["speed_bound"]] = th[L.th_speed_bound]
            w[W["pos_lo"]] = th[L.th_pos_lo]
            w[W["pos_hi"]] = th[L.th_pos_hi]
            w[W["pos_active"]] = th[L.th_pos_active]
            U = self._clip_inputs(problem.z_plan[self._idx_u])
            s = problem.z_plan[self._idx_s].copy()
            y_warm = None
            self._cuts = th[L.th_speed_dir].reshape(L.N, L.speed_cuts, 3).copy()
            self._acuts = th[L.th_accel_dir].reshape(L.N, L.accel_cuts, 3).copy() if L.accel_cuts else None
            it = 0
            for it in range(1, max_iterations + 1):
                X = simulate(x0, U, c.dt_s)
                self._linearize(X, U, s, problem.origin, goal_local, field, "keep")
                status, z, _, _, y, _, _ = self._solve(field, problem.origin, None, y_warm=y_warm)
                if z is None:
                    break
                U_new = self._clip_inputs(z[self._idx_u])
                change = float(np.max(np.abs(U_new - U)))
                U, s, y_warm = U_new, z[self._idx_s], y
                if change < tol:
                    break
            X = simulate(x0, U, c.dt_s)
            d, _ = _query(field, X[1:, 0:3] + problem.origin)
            return self._assemble_z(X, U, np.maximum(c.d_safe_m - d, 0.0)), it
        finally:
            self._w[:] = saved[0]
            self._cuts, self._acuts = saved[1], saved[2]

    # ------------------------------------------------------------------ pieces
    def _attractor_points(self, origin: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Points whose clearance :meth:`_attractor` needs: the segment to the goal, then the
        current guide path (empty when the front-end is off)."""
        if not self.config.guide_enable:
            return np.empty((0, 3))
        seg = segment_points(origin, goal, 0.1)
        return seg if self._guide is None else np.concatenate([seg, self._guide])

    def _attractor(self, t_s, origin, d0, goal, field, pre=None, box: FlightVolume | None = None) -> np.ndarray:
        """The point the progress terms pull toward: the goal when the straight segment to it
        keeps ``d_safe``, else a point ``guide_lookahead_m`` ahead on the guide path.

        ``pre``: ``(points, distances)`` of :meth:`_attractor_points` already queried.
        ``box``: the flight volume shrunk by the body radius (the guide search stays inside).
        """
        c = self.config
        if not c.guide_enable:
            return goal
        if pre is None:
            pts = self._attractor_points(origin, goal)
            d, _ = _query(field, pts)
        else:
            pts, d = pre
        path = self._guide
        n_seg = pts.shape[0] - (0 if path is None else path.shape[0])
        skip = 0.3 + max(0.0, c.d_safe_m - d0)
        far = _row_norms(pts[:n_seg] - origin) > skip
        if segment_clear(d[:n_seg][far], c.d_safe_m):
            self._guide = None
            return goal
        if path is not None:
            nearest = int(np.argmin(np.sum((path - origin) ** 2, axis=1)))
            still_valid = np.linalg.norm(self._guide_goal - goal) < 0.25 and np.all(
                d[n_seg + nearest + 1 :] >= c.d_safe_m
            )
            if still_valid and box is not None:
                still_valid = bool(np.all(box.contains(path[nearest + 1 :], margin_m=-1e-9)))
            if not still_valid:
                path = self._guide = None
        if path is None:
            due = self._guide_attempt_t is None or t_s - self._guide_attempt_t >= c.guide_replan_period_s
            goal_moved = self._guide_goal is None or np.linalg.norm(self._guide_goal - goal) >= 0.25
            if due or goal_moved:
                self._guide_attempt_t = t_s
                self._guide_goal = goal.copy()
                z_min, z_max = self._guide_z_limits(box)
                res = guide_search(
                    field,
                    origin,
                    goal,
                    clearance_m=c.d_safe_m + c.guide_clearance_margin_m,
                    preferred_clearance_m=c.guide_preferred_clearance_m,
                    resolution_m=c.guide_resolution_m,
                    max_cells=c.guide_max_cells,
                    z_min_m=z_min,
                    z_max_m=z_max,
                    bounds=None if box is None else (box.min_m, box.max_m),
                    time_budget_s=c.guide_time_budget_ms * 1e-3 if c.guide_time_budget_ms > 0 else None,
                    unknown_blocked=c.guide_unknown_blocked,
                )
                path = self._guide = res.path
                self._guide_ms, self._guide_status = res.elapsed_ms, res.status
        if path is None:
            return goal
        carrot, _ = carrot_on_path(path, origin, c.guide_lookahead_m)
        return carrot

    # ------------------------------------------------------------------ pieces (solver)
    def _clip_inputs(self, U: np.ndarray) -> np.ndarray:
        """Inputs (N, 4) onto their exact bounds: yaw rate (and, per axis, the acceleration)
        clipped; with the norm limit the acceleration scaled onto the ball ``||a|| <= a_max``."""
        U = np.clip(U, -self._u_max, self._u_max)
        if self._norm_accel:
            a_max = self.config.a_max_mps2
            n = _row_norms(U[:, 0:3])
            over = n > a_max
            if over.any():
                U[over, 0:3] *= (a_max / n[over])[:, None]
        return U

    @staticmethod
    def _directions(vectors: np.ndarray, floor: float, default: np.ndarray) -> np.ndarray:
        """Unit directions of ``vectors`` (n, 3); ``default`` where the norm is below ``floor``."""
        norm = _row_norms(vectors)
        moving = norm > floor
        return np.where(moving[:, None], vectors / np.where(moving, norm, 1.0)[:, None], default)

    @staticmethod
    def _update_cuts(old: np.ndarray | None, dirs: np.ndarray, K: int, mode: str) -> np.ndarray:
        if mode == "fresh" or old is None:
            return np.repeat(dirs[:, None, :], K, axis=1)
        if mode == "shift":
            cuts = np.empty_like(old)
            cuts[:-1] = old[1:]
            cuts[-1] = old[-1]
        else:
            cuts = old
        cuts[:, 0, :] = dirs
        return cuts

    def _linearize(self, X_bar, u_bar, s_warm, origin, goal_local, field, cuts_mode: str, knots_query=None) -> None:
        """Fill the linearization parts of the step inputs ``w`` about ``(X_bar, u_bar)``: the
        field's distance and gradient at knots 1..N, the inputs, the speed and acceleration
        cut directions, the slack warm start.

        ``cuts_mode``: ``"fresh"`` (all K cuts of a knot at its direction), ``"shift"`` (cuts
        of the previous step moved one knot on), ``"keep"`` (same step, cuts kept); slot 0 is
        always the tangent at the linearization point's direction.
        """
        L, c = self.layout, self.config
        w, W = self._w, self._dl.w
        d, g = _query(field, X_bar[1:, 0:3] + origin) if knots_query is None else knots_query
        self._w_d[:] = d
        self._w_g[:] = g
        self._w_u[:] = u_bar
        w[W["s_warm"]] = s_warm
        default = goal_local.copy()
        nd = np.linalg.norm(default)
        default = default / nd if nd > 1e-6 else np.array([1.0, 0.0, 0.0])
        dirs = self._directions(X_bar[1:, 3:6], 0.05 * c.v_max_mps, default)
        self._cuts = self._update_cuts(self._cuts, dirs, L.speed_cuts, cuts_mode)
        w[W["speed_dir"]] = self._cuts.ravel()
        if self._norm_accel:
            # Acceleration cuts: slot 0 is the tangent at the linearization point's direction
            # (on a cold start only where its norm is near the limit; a zero row, always
            # satisfied, where the direction is undefined); other slots
            # hold cuts added where a solution exceeded the norm. Zero rows rather than
            # tangents at small or arbitrary directions: a cold start with every knot's tangent
            # at the goal direction measured 4x the ADMM iterations.
            a_bar = u_bar[:, 0:3]
            norm = _row_norms(a_bar)
            near = norm > (0.5 if cuts_mode == "fresh" or self._acuts is None else 0.05) * c.a_max_mps2
            adirs = np.where(near[:, None], a_bar / np.where(near, norm, 1.0)[:, None], 0.0)
            if cuts_mode == "fresh" or self._acuts is None:
                self._acuts = np.zeros((L.N, L.accel_cuts, 3))
            elif cuts_mode == "shift":
                shifted = np.empty_like(self._acuts)
                shifted[:-1] = self._acuts[1:]
                shifted[-1] = self._acuts[-1]
                self._acuts = shifted
            self._acuts[:, 0, :] = adirs
            w[W["accel_dir"]] = self._acuts.ravel()

    def _theta_and_warm(self) -> tuple[np.ndarray, np.ndarray]:
        """``theta`` and the unscaled warm-start ``z`` of the current step inputs (NumPy)."""
        from planning.mpc_qp import theta_and_warm_start

        return theta_and_warm_start(self.layout, self._dl, self._w, self.config.dt_s)

    def _assemble_z(self, X, U, s) -> np.ndarray:
        L = self.layout
        z = np.empty(L.n_z)
        z[: L.n_x] = X.ravel()
        z[L.n_x : L.n_x + L.n_u] = U.ravel()
        z[L.n_x + L.n_u :] = s
        return z

    def _solve(self, field, origin, deadline, y_warm=None, record: bool = False):
        """Solve the problem in ``self._w`` with speed and acceleration refinement.

        Returns ``(status, z, iterations, solves, y, theta, z_init)``; ``theta`` and the
        unscaled warm start ``z_init`` only with ``record`` (else None). ``z`` is None when the
        solver failed or ran out of time; with ``UNSAFE`` (speed still above tolerance after
        ``max_speed_refinements``) it is the last solution, which :meth:`converge` keeps
        iterating from and :meth:`step` rejects. An acceleration norm still above tolerance
        after the refinements is not rejected: the command is scaled onto the ball.
        """
        c, L = self.config, self.layout
        K = L.speed_cuts
        iterations, solves = 0, 0
        theta = z_init = None
        if self._nlp is not None:
            theta, z_init = self._theta_and_warm()
            sol = self._nlp.solve(theta, ShiftedField(field, origin), z_init)
            ok = sol.converged and np.all(np.isfinite(sol.z))
            return (SolveStatus.SOLVED if ok else SolveStatus.NOT_CONVERGED), sol.z, sol.iterations, 1, None, theta, z_init
        qp = self._qp
        O = self._dl.out
        out = qp.data(self._w)
        if record or self.record_problems:
            theta = out[O["theta"]].copy()
            z_init = out[O["z_warm"]] * qp._D
        bound = self._w[self._dl.w["speed_bound"]]
        limit = bound * (1.0 + c.speed_tolerance_rel)
        a_limit = c.a_max_mps2 * (1.0 + c.accel_tolerance_rel)
        z_warm_scaled = out[O["z_warm"]]
        update_vectors = True
        sol = None
        for r in range(c.max_speed_refinements + 1):
            if deadline is not None:
                left = deadline - time.perf_counter()
                if left <= 0:
                    return SolveStatus.TIMEOUT, None, iterations, solves, None, theta, z_init
                qp.set_time_limit(left)
            elif qp._time_limit_s < 1e9:
                qp.set_time_limit(0.0)
            sol = qp.solve_data(out, z_warm_scaled, y_warm, update_vectors)
            iterations += sol.iterations
            solves += 1
            if not np.isfinite(sol.z).all():
                return SolveStatus.FAILED, None, iterations, solves, None, theta, z_init
            if "infeasible" in sol.status:
                return SolveStatus.INFEASIBLE, None, iterations, solves, None, theta, z_init
            if "time limit" in sol.status:
                return SolveStatus.TIMEOUT, None, iterations, solves, None, theta, z_init
            if not sol.converged:
                return SolveStatus.NOT_CONVERGED, None, iterations, solves, None, theta, z_init
            V = sol.z[self._idx_v1]
            speed = _row_norms(V)
            bad = np.flatnonzero(speed > limit)
            bad_a = np.empty(0, dtype=int)
            if self._norm_accel:
                A = sol.z[self._idx_a]
                a_norm = _row_norms(A)
                bad_a = np.flatnonzero(a_norm > a_limit)
            if bad.size == 0 and bad_a.size == 0:
                return SolveStatus.SOLVED, sol.z, iterations, solves, sol.y, theta, z_init
            if r == c.max_speed_refinements:
                break
            # cutting planes at the violating directions (slot 0 stays the linearization)
            slot = 1 + r % (K - 1) if K > 1 else 0
            w, W = self._w, self._dl.w
            if bad.size:
                self._cuts[bad, slot, :] = V[bad] / speed[bad, None]
                w[W["speed_dir"]] = self._cuts.ravel()
            if bad_a.size:
                Ka = L.accel_cuts
                aslot = 1 + r % (Ka - 1) if Ka > 1 else 0
                self._acuts[bad_a, aslot, :] = A[bad_a] / a_norm[bad_a, None]
                w[W["accel_dir"]] = self._acuts.ravel()
            out = qp.data(self._w)
            update_vectors = False  # only A changed
            z_warm_scaled, y_warm = sol.z / qp._D, sol.y
        speed_ok = bool((_row_norms(sol.z[self._idx_v1]) <= limit).all())
        status = SolveStatus.SOLVED if speed_ok else SolveStatus.UNSAFE
        return status, sol.z, iterations, solves, sol.y, theta, z_init

    def _check(self, X, U, origin, field, d0, bound, pos_lo=None, pos_hi=None):
        """Speed within tolerance everywhere; clearance over the braking horizon; knots inside
        the position box (vehicle-centred frame) within ``safety_tolerance_m``."""
        c = self.config
        speed = _row_norms(X[1:, 3:6])
        d_knots, _ = _query(field, X[1:, 0:3] + origin)
        if (speed > bound * (1.0 + c.speed_tolerance_rel)).any():
            return False, float(d_knots.min()), d_knots
        if pos_lo is not None and pos_lo is not self._pos_lo:
            P = X[1:, 0:3]
            tol = c.safety_tolerance_m
            if (P < pos_lo - tol).any() or (P > pos_hi + tol).any():
                return False, float(d_knots.min()), d_knots
        return self._clearance_ok(d_knots, d0), float(d_knots.min()), d_knots

    def _clearance_ok(self, d_knots: np.ndarray, d0: float) -> bool:
        """The check's clearance rule: over the braking horizon, every knot keeps ``d_safe``
        (or the start's clearance ``d0`` when that is less) within ``safety_tolerance_m``."""
        c = self.config
        floor = min(c.d_safe_m, d0) - c.safety_tolerance_m
        return bool((d_knots[: self._check_steps] >= floor).all())

    def _braking_inputs(self, v0: np.ndarray) -> np.ndarray:
        """Inputs (N, 4): decelerate at a_max along -v until at rest, zero yaw rate."""
        c, L = self.config, self.layout
        U = np.zeros((L.N, NU))
        v = v0.copy()
        for k in range(L.N):
            s = float(np.linalg.norm(v))
            if s < 1e-9:
                break
            dec = min(c.a_max_mps2, s / c.dt_s)
            a = -dec * v / s
            U[k, 0:3] = a
            v = v + a * c.dt_s
        return U


@dataclass(frozen=True, eq=False)
class ClosedLoopLog:
    """An idealized closed loop: the exact double integrator driven by each step's command.

    Attributes
    ----------
    t_s : array (T+1,), times, seconds
    p : array (T+1, 3), positions, metres, world ENU
    v : array (T+1, 3), velocities, m/s
    yaw : array (T+1,), radians, wrapped
    a : array (T, 3), executed accelerations, m/s^2
    yaw_rate : array (T,), executed yaw rates, rad/s
    results : tuple of PlanResult, one per step
    reached : bool, the vehicle came within the tolerance of the goal used and slowed down
    """

    t_s: np.ndarray
    p: np.ndarray
    v: np.ndarray
    yaw: np.ndarray
    a: np.ndarray
    yaw_rate: np.ndarray
    results: tuple
    reached: bool

    def sampled_path(self, samples_per_step: int = 4) -> np.ndarray:
        """Exact positions between knots (constant acceleration), shape (T s + 1, 3), metres."""
        T = self.a.shape[0]
        dt = float(self.t_s[1] - self.t_s[0]) if T else 0.0
        h = np.arange(samples_per_step) / samples_per_step * dt
        seg = (
            self.p[:-1, None, :]
            + self.v[:-1, None, :] * h[None, :, None]
            + 0.5 * self.a[:, None, :] * (h * h)[None, :, None]
        )
        return np.concatenate([seg.reshape(-1, 3), self.p[-1:]], axis=0)


def map_frame(esdf, planner: Planner | None, depth_m, camera, T_world_cam, center_world=None):
    """Integrate one depth frame into the map a planner flies on: the one place where a map and
    its planner meet per frame.

    The body sphere (the voxels marked free around the vehicle, ``EsdfConfig.body_clear_radius_m``)
    grows by the planner's current tracking margin, because the planner keeps that margin from
    unknown space too; with no planner (a method that flies without one) it does not grow.

    Parameters
    ----------
    esdf : :class:`planning.esdf.EsdfMap`.
    planner : the :class:`Planner` that reads ``esdf``, or None.
    depth_m, camera, T_world_cam, center_world : as :meth:`planning.esdf.EsdfMap.integrate`
        (metres, (H, W); the camera-to-world transform (4, 4); the window centre, world, metres).

    Returns the map's update record (:meth:`planning.esdf.EsdfMap.integrate`).
    """
    margin = planner.tracking_margin_m if planner is not None else 0.0
    return esdf.integrate(depth_m, camera, T_world_cam, center_world=center_world, body_margin_m=margin)


def run_closed_loop(
    planner: Planner,
    start: VehicleState,
    goal_world: np.ndarray,
    field: DistanceField,
    max_steps: int,
    goal_tolerance_m: float = 0.15,
    stop_speed_mps: float = 0.05,
    stop_when_reached: bool = True,
) -> ClosedLoopLog:
    """Fly ``planner`` in ``field`` with perfect tracking: each period the first command is
    integrated exactly (``p += v dt + a dt^2 / 2``, ``v += a dt``, ``yaw += yaw_rate dt``).

    ``reached`` becomes true once the vehicle is within ``goal_tolerance_m`` of the goal the
    planner used and slower than ``stop_speed_mps``; the loop then ends if
    ``stop_when_reached``.
    """
    dt = planner.config.dt_s
    p, v, yaw, a = start.p.copy(), start.v.copy(), float(start.yaw), start.a.copy()
    t = float(start.t_s)
    ps, vs, yaws, ts, acc, rates, results = [p], [v], [yaw], [t], [], [], []
    reached = False
    for _ in range(max_steps):
        res = planner.step(VehicleState(t, p, v, yaw, 0.0, a), goal_world, field)
        a = res.command.a
        r = res.command.yaw_rate
        p = p + v * dt + 0.5 * a * dt * dt
        v = v + a * dt
        yaw = float(wrap_angle(yaw + r * dt))
        t += dt
        ps.append(p)
        vs.append(v)
        yaws.append(yaw)
        ts.append(t)
        acc.append(a)
        rates.append(r)
        results.append(res)
        if np.linalg.norm(p - res.goal_used) < goal_tolerance_m and np.linalg.norm(v) < stop_speed_mps:
            reached = True
            if stop_when_reached:
                break
    return ClosedLoopLog(
        t_s=np.array(ts),
        p=np.array(ps),
        v=np.array(vs),
        yaw=np.array(yaws),
        a=np.array(acc).reshape(-1, 3),
        yaw_rate=np.array(rates),
        results=tuple(results),
        reached=reached,
    )
