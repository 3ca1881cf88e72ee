"""Every weight and limit of the receding-horizon MPC, in one frozen dataclass.

Scripts change a :class:`PlannerConfig`, never the code. Units are in the field names. The
paper states the dynamic limits (0.6 m/s, 0.6 m/s^2, 0.4 rad/s); every other default is our
documented choice:

- ``d_safe_m = 0.45``: a 0.25 m body radius (a 250-350 mm class quadrotor with props) plus the
  paper's 0.2 m clearance dilation ``r``. The planner keeps the body *centre* at least this far
  from every obstacle surface.
- ``horizon_steps = 40`` at ``dt_s = 0.1``: a 4 s horizon, longer than the 1 s stopping time
  at the default limits (0.6 / 0.6), so every plan can brake inside its own horizon.
- The acceleration limit is on the **norm** ``||a|| <= a_max_mps2`` by default
  (``accel_limit_mode = "norm"``): the paper's ``a_m`` bounds the norm, and so do the simulated
  vehicle (:mod:`onfly.world.vehicle`) and the MAVLink bridge's feed-forward clip. ``"per_axis"``
  keeps Fast-Planner's convention (``|a_i| <= a_max_mps2``, which lets the norm reach
  ``sqrt(3) a_max``). The speed limit is on the **norm** ``||v|| <= v_max_mps``. Both norms are
  exact in the NLP; in the QP each is an outer polyhedral approximation, the tangent at the
  previous direction plus cutting planes added until the true norm is within
  ``speed_tolerance_rel`` / ``accel_tolerance_rel`` (see :mod:`planning.mpc_qp`), and the
  commanded acceleration is then scaled onto the ball, so the executed norm never exceeds
  ``a_max_mps2``.
- ``body_radius_m = 0.25``: the vehicle's radius with props; the operator flight volume
  (:class:`planning.volume.FlightVolume`) is shrunk by it for plans, goals and guide paths.
- Bounded step: the guide search visits at most ``guide_max_cells`` grid cells (the grid is
  coarsened to fit; deterministic), and optionally stops refining when ``guide_time_budget_ms``
  is spent (anytime: the finest completed level is the answer); a step that has used
  ``step_time_budget_ms`` before or during its solve returns the shifted previous plan with
  status ``timeout``. Both time budgets are 0 (off) by default so runs are reproducible
  whatever the machine's load; set them on a vehicle (e.g. 30 and 80 ms at 10 Hz).
- Cost weights (dimensionless ratios; only their ratios matter): the stage progress weight pulls
  every knot toward the goal, the terminal weights make the plan end at rest on the goal,
  ``w_accel`` / ``w_jerk`` keep commands small and smooth, ``w_yaw`` is the paper's
  ``lambda_psi``, and the slack weights (exact L1 penalty plus a small quadratic for
  conditioning) are large enough that the clearance constraint only gives way when it is
  infeasible (the L1 weight exceeds the clearance multipliers the progress terms create for
  goals within ~20 m).
- OSQP: eps 1e-3 (the fast path's real-time iteration; tighter tolerances cost hundreds of
  ADMM iterations on this problem), rho 1.0 with adaptive updates every 25 iterations.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path

__all__ = ["PlannerConfig", "PlannerConfigError", "ACCEL_LIMIT_MODES", "VOLUME_DRIFT_STEP_M", "check_field_reach"]

#: Values of :attr:`PlannerConfig.accel_limit_mode`.
ACCEL_LIMIT_MODES = ("norm", "per_axis")
#: The distance flown that the volume's drift margin counts grows in moves of at least this
#: much (metres): the estimate's noise while hovering (about 2 cm a step) is not a path.
VOLUME_DRIFT_STEP_M = 0.25


class PlannerConfigError(ValueError):
    """A planner configuration field with an invalid value (the message names the field)."""


@dataclass(frozen=True)
class PlannerConfig:
    """Frozen configuration of :class:`planning.planner.Planner`.

    Attributes
    ----------
    horizon_steps : int, number of control intervals N (default 40)
    dt_s : float, interval length in seconds (default 0.1; horizon 4 s)
    v_max_mps : float, speed norm limit, m/s (paper: 0.6)
    a_max_mps2 : float, acceleration limit, m/s^2 (paper: 0.6), on the norm or per axis
        (``accel_limit_mode``)
    accel_limit_mode : ``"norm"`` (default, ``||a|| <= a_max``) or ``"per_axis"``
        (``|a_i| <= a_max``, Fast-Planner's convention)
    accel_tolerance_rel : relative tolerance on the acceleration norm after the QP (cuts are
        added until it holds; the command is then scaled onto the ball exactly)
    body_radius_m : vehicle radius with props, metres; the flight volume is shrunk by it
    yaw_rate_max_rps : float, yaw rate limit, rad/s (paper: 0.4)
    d_safe_m : float, minimum clearance of the body centre to obstacles, metres (0.25 m body
        radius + 0.2 m dilation)
    w_goal : stage weight on ``||p_k - g||^2``, 1/m^2
    w_terminal_pos : terminal weight on ``||p_N - g||^2``
    w_terminal_vel : terminal weight on ``||v_N||^2``
    w_vel : stage weight on ``||v_k||^2`` (damping)
    w_accel : stage weight on ``||a_k||^2``
    w_jerk : weight on ``||a_k - a_{k-1}||^2`` (``a_{-1}`` = the last command)
    w_yaw : the paper's ``lambda_psi`` on ``wrap(psi_k - psi_g)^2``
    w_yaw_rate : weight on ``yaw_rate_k^2``
    w_slack_l1 : exact-penalty weight on the clearance slack, per metre
    w_slack_l2 : quadratic weight on the clearance slack, per m^2
    w_prox_accel : QP-only proximal weight on ``||a_k - a_bar_k||^2`` toward the linearization
        point; damps the sequential linearization, zero at a fixed point (not in the NLP)
    goal_clearance_margin_m : a goal is moved until its clearance is ``d_safe_m`` plus this
        (a goal lifted over the segment to it: plus the step's tracking margin too)
    goal_search_max_m : how far the goal may be moved by gradient ascent before the line
        search back toward the vehicle takes over, metres
    goal_lift_max_m : when no point of that line has the goal clearance, the line raised by up to
        this much (0.25 m steps) is searched for the point nearest the goal that has it, metres
        (ours; 0 = off). A target on a floor or a ledge whose height is within the clearance
        of the floor has no such point at the vehicle's height: the goal then stayed where the
        vehicle was, short of the target (under gusts the clearance grows by the tracking
        margin: `terrace-o05`, held 3 m from a sundial on a terrace)
    yaw_hold_radius_m : within this horizontal distance of the goal the bearing is undefined
        and the yaw reference is the current yaw (hold heading)
    safety_tolerance_m : a plan (or the shifted previous plan) is accepted if its predicted
        clearance over the braking horizon stays above ``min(d_safe_m, d(p_0)) -`` this
    speed_tolerance_rel : relative tolerance on the speed norm after the QP (0.01 = 1 %)
    max_speed_refinements : extra QP solves when the true speed norm of a plan exceeds the
        limit by more than ``speed_tolerance_rel`` (each adds a cut at the violating knots)
    speed_cuts_per_knot : K half-spaces ``n . v_k <= bound_k`` per knot in the QP: the tangent
        at the previous plan's direction plus K - 1 cutting planes added on violation
    cold_start_iterations : QP solves (sequential linearization) on the first step after
        construction or :meth:`Planner.reset`, when there is no previous plan to linearize about
    guide_enable : run the grid-search front-end (:mod:`planning.guide_path`) when the straight
        segment to the goal lacks clearance; the MPC is then pulled toward a point on that path
    guide_resolution_m : front-end grid spacing, metres
    guide_clearance_margin_m : grid cells need clearance ``d_safe_m`` plus this, metres
    guide_preferred_clearance_m : edges through cells with less clearance cost more, metres
    guide_lookahead_m : arc length from the vehicle's nearest path point to the attractor
    guide_replan_period_s : least time between two searches while no valid path exists
    guide_max_cells : node budget of the guide search: the grid is coarsened until it has at
        most this many cells (deterministic bound on the search's work)
    guide_time_budget_ms : time budget of the guide search, milliseconds (0 = none). With a
        budget the search runs coarse-to-fine (4x, 2x, 1x ``guide_resolution_m``) and does not
        start a level it predicts will not finish; the finest completed path is the answer
    guide_floor_m, guide_ceiling_m : the guide search never goes below / above these heights,
        metres, world ENU (None = no limit). With a flight volume its z-extent shrunk by
        ``body_radius_m`` is used (intersected with these when both are set)
    guide_unknown_blocked : cells the distance field reports as unknown (when it exposes
        ``is_unknown(points)`` or ``known(points)``, as :class:`planning.esdf.EsdfMap` does)
        are blocked for the guide search
    step_time_budget_ms : wall-time budget of one step, milliseconds (0 = none): OSQP's time
        limit is the budget left, and a step past it returns the shifted previous plan (status
        ``timeout``; a braking plan if the shifted plan fails its check)
    qp_eps_abs, qp_eps_rel : OSQP tolerances (the problem is posed in a frame centred on the
        vehicle, so absolute tolerances do not depend on where in the world it flies)
    qp_max_iter : OSQP iteration cap; hitting it counts as a non-converged solve
    qp_rho : OSQP initial ADMM step
    qp_adaptive_rho : let OSQP adapt rho during a solve (rho is reset to ``qp_rho`` before
        every solve, so an adapted value never carries over to the next problem)
    qp_adaptive_rho_interval : OSQP iterations between rho updates (0 = OSQP's automatic)
    qp_check_termination : OSQP iterations between termination checks
    qp_polish : OSQP solution polishing
    nlp_tol : ipopt tolerance of the reference NLP
    nlp_max_iter : ipopt iteration cap
    reference_start : start each plan from the previous plan's reference state (position,
        velocity, acceleration) at the current time instead of the measured state, while the
        measured position lies within ``reference_reset_m`` of it and the previous plan is at
        most ``reference_max_age_s`` old (EGO-Planner's ``planFromCurrentTraj``, Fast-Planner's
        ``start_pt_`` from the running B-spline). The vehicle's position controller then sees
        and corrects the tracking error with its own authority (PX4's cascade up to its tilt
        limit) instead of the planner re-basing every plan on wherever a gust pushed the
        vehicle, which leaves only the planner's ``a_max_mps2`` against the disturbance. Yaw
        always starts from the measured yaw. Off: every plan starts at the measured state
    reference_reset_m : a measured position farther than this from the reference restarts the
        plan from the measured state (the reference is no longer a place the vehicle can be
        pulled back to), metres
    reference_max_age_s : a previous plan older than this is not a reference (the planner was
        not stepped meanwhile), seconds
    tracking_margin_max_m : the clearance and flight-volume margin added to ``d_safe_m`` and
        ``body_radius_m`` grows with the *measured* tracking error (``|plan(t) - measured
        position|``, the error the vehicle's own estimate shows against the plan it was
        flying): the largest error of the last ``tracking_window_s`` seconds, capped at this
        value, metres (0 = no margin). Errors under 5 cm (half a voxel of the map) give no
        margin, so under perfect tracking it is 0
    tracking_window_s : how long a measured tracking error keeps the margin up, seconds
    volume_drift_fraction : the flight volume's margin for odometry drift, as a fraction of the
        distance flown since ``Planner.reset()`` (by the estimate, counted in moves of at least
        ``VOLUME_DRIFT_STEP_M`` so hover noise does not add up), added to the volume's shrink.
        The tracking margin covers what the estimate shows; drift is what it cannot show, and a
        LiDAR- or visual-inertial odometry drifts with the path (``docs/realism.md``: 1 % is a
        conservative figure). 0 trusts the estimate, e.g. under a GNSS-aided EKF whose error
        does not grow (then give the fence its own margin, as ArduPilot's ``FENCE_MARGIN`` does)
    volume_drift_max_m : cap of that margin, metres. Without it a long flight would squeeze a
        room-sized volume to its middle (after 130 m at 1 %, a 3 m tall room has no height
        left); past the cap the estimate needs an outside fix (a loop closure, GNSS), not a
        smaller volume
    """

    horizon_steps: int = 40
    dt_s: float = 0.1
    v_max_mps: float = 0.6
    a_max_mps2: float = 0.6
    yaw_rate_max_rps: float = 0.4
    d_safe_m: float = 0.45
    accel_limit_mode: str = "norm"
    accel_tolerance_rel: float = 0.01
    body_radius_m: float = 0.25
    w_goal: float = 1.0
    w_terminal_pos: float = 20.0
    w_terminal_vel: float = 20.0
    w_vel: float = 0.1
    w_accel: float = 0.5
    w_jerk: float = 2.0
    w_yaw: float = 2.0
    w_yaw_rate: float = 0.5
    w_slack_l1: float = 2000.0
    w_slack_l2: float = 10.0
    w_prox_accel: float = 1.0
    goal_clearance_margin_m: float = 0.05
    goal_search_max_m: float = 3.0
    goal_lift_max_m: float = 1.0
    yaw_hold_radius_m: float = 0.3
    safety_tolerance_m: float = 0.05
    speed_tolerance_rel: float = 0.01
    max_speed_refinements: int = 3
    speed_cuts_per_knot: int = 3
    cold_start_iterations: int = 3
    guide_enable: bool = True
    guide_resolution_m: float = 0.25
    guide_clearance_margin_m: float = 0.1
    guide_preferred_clearance_m: float = 1.0
    guide_lookahead_m: float = 3.0
    guide_replan_period_s: float = 1.0
    guide_max_cells: int = 60000
    guide_time_budget_ms: float = 0.0
    guide_floor_m: float | None = None
    guide_ceiling_m: float | None = None
    guide_unknown_blocked: bool = True
    step_time_budget_ms: float = 0.0
    qp_eps_abs: float = 1e-3
    qp_eps_rel: float = 1e-3
    qp_max_iter: int = 1000
    qp_rho: float = 1.0
    qp_adaptive_rho: bool = True
    qp_adaptive_rho_interval: int = 25
    qp_check_termination: int = 5
    qp_polish: bool = False
    nlp_tol: float = 1e-8
    nlp_max_iter: int = 1000
    reference_start: bool = True
    reference_reset_m: float = 1.5
    reference_max_age_s: float = 0.5
    tracking_margin_max_m: float = 1.0
    tracking_window_s: float = 10.0
    volume_drift_fraction: float = 0.01
    volume_drift_max_m: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("str", str):
                if not isinstance(value, str):
                    raise PlannerConfigError(f"{f.name} must be a string, got {value!r}")
                continue
            if f.type == "float | None" and value is None:
                continue
            if f.type in ("int", int):
                if isinstance(value, bool) or not isinstance(value, int):
                    raise PlannerConfigError(f"{f.name} must be an int, got {value!r}")
            elif f.type in ("bool", bool):
                if not isinstance(value, bool):
                    raise PlannerConfigError(f"{f.name} must be a bool, got {value!r}")
            else:
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise PlannerConfigError(f"{f.name} must be a number, got {value!r}")
                if not math.isfinite(value):
                    raise PlannerConfigError(f"{f.name} must be finite, got {value!r}")
                object.__setattr__(self, f.name, float(value))
        positive = (
            "dt_s", "v_max_mps", "a_max_mps2", "yaw_rate_max_rps", "d_safe_m", "w_goal",
            "w_slack_l1", "w_slack_l2", "speed_tolerance_rel", "accel_tolerance_rel", "qp_eps_abs",
            "qp_rho", "nlp_tol", "guide_resolution_m", "guide_lookahead_m", "reference_reset_m",
            "reference_max_age_s", "tracking_window_s",
        )
        for name in positive:
            if getattr(self, name) <= 0:
                raise PlannerConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        non_negative = (
            "w_terminal_pos", "w_terminal_vel", "w_vel", "w_accel", "w_jerk", "w_yaw",
            "w_yaw_rate", "w_prox_accel", "goal_clearance_margin_m", "goal_search_max_m", "goal_lift_max_m", "yaw_hold_radius_m",
            "safety_tolerance_m", "max_speed_refinements", "qp_adaptive_rho_interval", "qp_eps_rel",
            "guide_clearance_margin_m", "guide_preferred_clearance_m", "guide_replan_period_s",
            "body_radius_m", "guide_time_budget_ms", "step_time_budget_ms", "tracking_margin_max_m",
            "volume_drift_fraction", "volume_drift_max_m",
        )
        for name in non_negative:
            if getattr(self, name) < 0:
                raise PlannerConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.volume_drift_fraction >= 0.5:
            raise PlannerConfigError(
                f"volume_drift_fraction is a fraction of the distance flown (0.01 = 1 %), must be < 0.5, "
                f"got {self.volume_drift_fraction}"
            )
        if self.horizon_steps < 2:
            raise PlannerConfigError(f"horizon_steps must be >= 2, got {self.horizon_steps}")
        for name in (
            "qp_max_iter", "qp_check_termination", "nlp_max_iter", "speed_cuts_per_knot",
            "cold_start_iterations", "guide_max_cells",
        ):
            if getattr(self, name) < 1:
                raise PlannerConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("speed_tolerance_rel", "accel_tolerance_rel"):
            if getattr(self, name) > 0.1:
                raise PlannerConfigError(f"{name} must be <= 0.1, got {getattr(self, name)}")
        if self.accel_limit_mode not in ACCEL_LIMIT_MODES:
            raise PlannerConfigError(
                f"accel_limit_mode must be one of {ACCEL_LIMIT_MODES}, got {self.accel_limit_mode!r}"
            )
        if self.body_radius_m > self.d_safe_m:
            raise PlannerConfigError(
                f"body_radius_m ({self.body_radius_m}) must be <= d_safe_m ({self.d_safe_m})"
            )
        if (
            self.guide_floor_m is not None
            and self.guide_ceiling_m is not None
            and self.guide_floor_m >= self.guide_ceiling_m
        ):
            raise PlannerConfigError(
                f"guide_floor_m ({self.guide_floor_m}) must be below guide_ceiling_m ({self.guide_ceiling_m})"
            )

    @property
    def horizon_s(self) -> float:
        """Horizon length in seconds, ``horizon_steps * dt_s``."""
        return self.horizon_steps * self.dt_s

    @property
    def braking_steps(self) -> int:
        """Intervals needed to stop from ``v_max_mps`` at ``a_max_mps2`` (at most N)."""
        return min(self.horizon_steps, int(math.ceil(self.v_max_mps / self.a_max_mps2 / self.dt_s)) + 1)

    @property
    def field_reach_m(self) -> float:
        """The largest distance the planner reads from its field, metres: ``d_safe_m`` plus the
        largest tracking margin plus the larger of the goal's and the guide search's margins. A
        distance field clamped below it (``EsdfConfig.max_distance_m``) can never show the
        clearance the planner asks for once the margin is large: :func:`check_field_reach`."""
        return self.d_safe_m + self.tracking_margin_max_m + max(self.goal_clearance_margin_m, self.guide_clearance_margin_m)

    def to_dict(self) -> dict:
        """Plain dict of every field (TOML/JSON-serializable), for writing next to results."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "PlannerConfig":
        """Build from a dict; unknown keys raise :class:`PlannerConfigError` listing valid ones."""
        valid = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - valid)
        if unknown:
            raise PlannerConfigError(
                f"unknown planner config field(s) {unknown}; valid fields: {sorted(valid)}"
            )
        return cls(**data)

    @classmethod
    def from_toml(cls, path: str | Path, table: str | None = "planner") -> "PlannerConfig":
        """Load from a TOML file.

        Parameters
        ----------
        path : the TOML file
        table : name of the table holding the fields (default ``[planner]``); ``None`` reads
            the top level. A file without that table but with top-level fields is read as is.
        """
        path = Path(path)
        try:
            with path.open("rb") as fh:
                data = tomllib.load(fh)
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise PlannerConfigError(f"cannot read planner config {path}: {exc}") from exc
        if table is not None and table in data:
            data = data[table]
            if not isinstance(data, dict):
                raise PlannerConfigError(f"{path}: [{table}] must be a table")
        elif table is not None:
            data = {k: v for k, v in data.items() if not isinstance(v, dict)}
        try:
            return cls.from_dict(data)
        except PlannerConfigError as exc:
            raise PlannerConfigError(f"{path}: {exc}") from exc


def check_field_reach(config: PlannerConfig, field_max_distance_m: float) -> None:
    """Raise :class:`PlannerConfigError` when a distance field clamped at
    ``field_max_distance_m`` (metres) cannot show the clearance ``config`` asks for
    (:attr:`PlannerConfig.field_reach_m`): every plan would fall back once the tracking margin
    grows. Call it wherever a planner is paired with its map."""
    if field_max_distance_m < config.field_reach_m:
        raise PlannerConfigError(
            f"the distance field is clamped at {field_max_distance_m} m (EsdfConfig.max_distance_m), below the "
            f"{config.field_reach_m:.2f} m the planner reads (d_safe_m {config.d_safe_m} + tracking_margin_max_m "
            f"{config.tracking_margin_max_m} + goal/guide margin); raise max_distance_m or lower the margins"
        )
