"""What the baselines share: flight limits, map-free motion, option handling, call outcomes.

Every baseline flies under the same dynamic limits as OnFly (the ``planner`` table of the
benchmark config: ``v_max_mps``, ``a_max_mps2``, ``yaw_rate_max_rps``, ``dt_s``,
``horizon_steps``); map-free motion is :func:`planning.straight_line.straight_line_plan`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from onfly.observation import Observation
from planning.frames import wrap_angle
from planning.planner import Planner
from planning.planner_config import PlannerConfig
from planning.straight_line import straight_line_plan
from planning.trajectory import Trajectory, VehicleState
from vlm.types import VlmImage, VlmResponse

__all__ = [
    "BaselineOptionError",
    "FlightLimits",
    "split_options",
    "shared_planner",
    "straight_plan",
    "arrived",
    "Arrival",
    "yaw_settled",
    "ray_world",
    "vlm_image",
    "CallOutcome",
]

#: arrival tolerances of map-free moves (position, speed)
ARRIVE_TOL_M = 0.15
ARRIVE_SPEED_MPS = 0.1
#: a move is also over once its setpoint has stood at the goal this long with the vehicle within
#: ARRIVE_SETTLE_RADIUS_M of it (:class:`Arrival`): under turbulence the vehicle holds a setpoint
#: to tenths of a metre and is never still (docs/realism.md: 0.36 m mean, 0.69 m p95 from a
#: flown plan outdoors), and PX4 itself accepts a waypoint by radius alone, with no stillness
#: check (NAV_ACC_RAD; NAV_MC_ALT_RAD = 0.8 m vertically for multicopters)
ARRIVE_SETTLE_RADIUS_M = 0.5
ARRIVE_SETTLE_S = 1.0


class BaselineOptionError(ValueError):
    """A baseline option that does not exist or is out of range (names it)."""


@dataclass(frozen=True)
class FlightLimits:
    """The dynamic limits every method flies under (from the shared planner config).

    v_max_mps, a_max_mps2, yaw_rate_max_rps : speed, per-interval acceleration and yaw-rate limits
    dt_s, steps : interval length and count of a map-free plan
    """

    v_max_mps: float
    a_max_mps2: float
    yaw_rate_max_rps: float
    dt_s: float
    steps: int

    @classmethod
    def from_planner(cls, config: PlannerConfig) -> "FlightLimits":
        return cls(config.v_max_mps, config.a_max_mps2, config.yaw_rate_max_rps, config.dt_s, config.horizon_steps)


def split_options(options: dict[str, Any], config_cls, method: str) -> tuple[PlannerConfig, dict, Any]:
    """Split factory options into ``(planner config, esdf overrides, method config)``.

    ``verifier`` and ``movers`` are accepted (shared tables of the benchmark config); a baseline
    that flies our planner reads ``movers`` from the options itself, the others ignore them.
    Unknown keys raise :class:`BaselineOptionError` listing the valid ones.
    """
    opts = dict(options)
    planner = PlannerConfig.from_dict(dict(opts.pop("planner", {}) or {}))
    esdf = dict(opts.pop("esdf", {}) or {})
    opts.pop("verifier", None)
    opts.pop("movers", None)
    valid = {f.name for f in fields(config_cls)}
    bad = sorted(set(opts) - valid)
    if bad:
        raise BaselineOptionError(f"unknown {method} option(s) {bad}; valid: {sorted(valid | {'planner', 'esdf', 'verifier', 'movers'})}")
    return planner, esdf, config_cls(**opts)


_PLANNERS: dict[PlannerConfig, Planner] = {}


def shared_planner(config: PlannerConfig) -> Planner:
    """One Planner per config per process (CasADi set-up is built once), reset for the episode."""
    if config not in _PLANNERS:
        _PLANNERS[config] = Planner(config)
    planner = _PLANNERS[config]
    planner.reset()
    return planner


class PlanMemory:
    """The last straight-line plan a method handed the vehicle: the next plan starts from its
    reference state while the vehicle tracks it (``straight_line_plan(reference=...)``, the
    planner's ``reference_start`` rule), so a gust is corrected by the position controller
    instead of moving every later plan. One per method instance, cleared at ``reset``."""

    def __init__(self) -> None:
        self.last: Trajectory | None = None


def straight_plan(
    state: VehicleState,
    goal,
    limits: FlightLimits,
    *,
    yaw_first: bool = False,
    yaw_ref: float | None = None,
    memory: PlanMemory | None = None,
) -> Trajectory:
    """Map-free straight-line plan to ``goal`` (3,), world ENU metres, under ``limits``; with
    ``memory`` it starts from the last plan's reference and is remembered."""
    traj = straight_line_plan(
        state,
        np.asarray(goal, float),
        v_max_mps=limits.v_max_mps,
        a_max_mps2=limits.a_max_mps2,
        yaw_rate_max_rps=limits.yaw_rate_max_rps,
        dt_s=limits.dt_s,
        steps=limits.steps,
        yaw_first=yaw_first,
        yaw_ref=yaw_ref,
        reference=None if memory is None else memory.last,
    )
    if memory is not None:
        memory.last = traj
    return traj


def arrived(state: VehicleState, goal) -> bool:
    """At ``goal`` (within :data:`ARRIVE_TOL_M`) and nearly still."""
    return bool(
        np.linalg.norm(state.p - np.asarray(goal, float)) <= ARRIVE_TOL_M and np.linalg.norm(state.v) <= ARRIVE_SPEED_MPS
    )


class Arrival:
    """When a map-free move to a goal is over, as a companion computer on PX4 would judge it.

    The move is over when the vehicle is at the goal and nearly still (:func:`arrived`), or when
    the plan's reference (the setpoint the position controller tracks) has stood at the goal for
    :data:`ARRIVE_SETTLE_S` and the vehicle is within :data:`ARRIVE_SETTLE_RADIUS_M` of it. With
    exact tracking (the ideal world) the vehicle is at the goal when its reference is, so the
    first rule decides exactly as before; under gusts and controller lag the second ends the move
    instead of a wait for a stillness that never comes (until the method's step timeout). One
    per move: :meth:`reset` when a new goal is set.
    """

    def __init__(self) -> None:
        self._ref_since_s: float | None = None

    def reset(self) -> None:
        self._ref_since_s = None

    def __call__(self, t_s: float, state: VehicleState, goal, plan: Trajectory | None) -> bool:
        """``plan``: the straight-line plan being flown (``PlanMemory.last``), None if none."""
        goal = np.asarray(goal, float)
        if arrived(state, goal):
            return True
        ref_at_goal = plan is not None and 0.0 <= t_s - plan.t0_s <= 0.5 and np.linalg.norm(plan.sample(t_s)[0] - goal) <= ARRIVE_TOL_M
        if not ref_at_goal:
            self._ref_since_s = None
            return False
        if self._ref_since_s is None:
            self._ref_since_s = t_s
        return bool(t_s - self._ref_since_s >= ARRIVE_SETTLE_S and np.linalg.norm(state.p - goal) <= ARRIVE_SETTLE_RADIUS_M)


def yaw_settled(state: VehicleState, yaw_rad: float, tol_rad: float = 0.05) -> bool:
    """Heading within ``tol_rad`` of ``yaw_rad`` and the yaw rate nearly zero."""
    return bool(abs(wrap_angle(state.yaw - yaw_rad)) <= tol_rad and abs(state.yaw_rate) <= 0.05)


def ray_world(obs: Observation, uv) -> np.ndarray:
    """Unit viewing ray through pixel ``uv`` of ``obs``, shape (3,), world frame."""
    ray_cam = obs.camera.K_inv @ np.array([float(uv[0]), float(uv[1]), 1.0])
    r = obs.T_world_cam[:3, :3] @ ray_cam
    return r / np.linalg.norm(r)


def vlm_image(obs: Observation, rgb: np.ndarray | None = None) -> VlmImage:
    """The VLM's view of ``obs`` (``rgb`` replaces the pixels, e.g. with drawn overlays; the
    annotation rides along for the simulated VLM)."""
    return VlmImage(rgb=obs.rgb if rgb is None else rgb, frame_id=obs.frame_id, annotation=obs.annotation)


@dataclass(frozen=True, eq=False)
class CallOutcome:
    """One VLM call of a baseline: what was asked about and the response (lands after its latency).

    kind : str, the baseline's call kind; frame_id : the frame asked about; payload : the
    method's own context for the call (e.g. the candidates drawn)
    """

    kind: str
    frame_id: str
    response: VlmResponse
    payload: Any = None

    @property
    def latency_s(self) -> float:
        return self.response.latency_s

