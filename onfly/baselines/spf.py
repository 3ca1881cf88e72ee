"""See-Point-Fly-style baseline (and the same goals through OnFly's ESDF + MPC).

After SPF (Hu et al. 2025): per frame the VLM points at where to fly next and says how far
(whole metres); the pixel is lifted along its viewing ray to that z-depth and the vehicle flies
there, closed loop (a new question as soon as the last answer has landed, on the newest
frame). Motion is yaw-then-straight-line (:func:`planning.straight_line.straight_line_plan`
with ``yaw_first=True``): no map, no monitor, no verifier. Depth 0 means "reached" and ends
the episode (the stop interface the OnFly paper added). An answer that does not parse is
logged and the last goal is kept.

``use_planner=True`` is the paper's "SPF w/ planner" control study: the same goals, flown
through :class:`planning.esdf.EsdfMap` (updated from every depth frame) and
:class:`planning.planner.Planner`. Without it the method holds no map object at all.

The travel distance is the model's number capped at ``max_travel_m`` (our choice: the paper's
``D_max = 7 m``); SPF's own adaptive scaling of the travel distance is not reproduced (with a
closed loop re-asking every 0.81 s the cap matters only when answers stop coming).
"""

from __future__ import annotations

import logging
import math
import re
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from onfly.baselines.common import (
    BaselineOptionError,
    CallOutcome,
    FlightLimits,
    PlanMemory,
    shared_planner,
    split_options,
    straight_plan,
    vlm_image,
)
from onfly.bench.method import EpisodeSpec, MethodStep
from onfly.observation import Observation
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig
from planning.movers import MoverConfig, MoverTracker
from planning.frames import transform_points
from planning.planner import Planner, map_frame
from planning.planner_config import check_field_reach
from planning.trajectory import VehicleState
from vlm.factory import make_backend
from vlm.parsing import parse_point_depth
from vlm.prompts import build_spf_prompt, spf_schema
from vlm.types import CallStatus, VlmBackend

__all__ = ["SpfConfig", "SpfMethod", "SpfAnswer", "parse_spf_answer", "make_spf", "make_spf_planner"]

log = logging.getLogger(__name__)

SPF = "spf"
_ZERO_DEPTH_RE = re.compile(r'"(?:depth|depth_m|distance|distance_m)"\s*:\s*"?0+(?:\.0*)?"?\s*[,}]')


@dataclass(frozen=True)
class SpfConfig:
    """SPF parameters.

    max_travel_m : cap on the travel distance the model asks for, metres
    structured_output : ask the backend for schema-constrained JSON
    """

    max_travel_m: float = 7.0
    structured_output: bool = False

    def __post_init__(self) -> None:
        v = self.max_travel_m
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
            raise BaselineOptionError(f"SpfConfig.max_travel_m must be a finite number > 0, got {v!r}")


@dataclass(frozen=True)
class SpfAnswer:
    """A parsed SPF answer: ``stop`` (depth 0), or a pixel ``uv`` and ``depth_m``, or a failure."""

    ok: bool
    stop: bool = False
    uv: tuple[float, float] | None = None
    depth_m: float | None = None
    reason: str = ""


def parse_spf_answer(text: str, image_size: tuple[int, int]) -> SpfAnswer:
    """``{"point_2d": [x, y], "depth": d}`` in any syntax :func:`vlm.parsing.parse_point_depth`
    reads; a JSON depth of exactly 0 is the stop answer (the point is then not needed)."""
    if isinstance(text, str) and _ZERO_DEPTH_RE.search(text):
        return SpfAnswer(True, stop=True)
    p = parse_point_depth(text, image_size)
    if not p.ok:
        return SpfAnswer(False, reason=p.reason)
    return SpfAnswer(True, uv=p.uv, depth_m=p.depth_m)


class SpfMethod:
    """The SPF-style baseline; ``planner`` set: SPF with OnFly's ESDF + MPC (module docstring).

    Parameters
    ----------
    vlm_spec : backend spec
    config : SpfConfig
    limits : FlightLimits (straight-line motion)
    planner : None (no map at all) or a Planner, with ``esdf_config`` for its map and
        ``mover_config`` for the moving obstacles it avoids besides the map (as OnFly's pilot)
    backend : a VLM backend to use instead of building one from ``vlm_spec`` per episode
    """

    privileged = False

    def __init__(
        self,
        vlm_spec: str,
        config: SpfConfig,
        limits: FlightLimits,
        planner: Planner | None = None,
        esdf_config: EsdfConfig | None = None,
        backend: VlmBackend | None = None,
        mover_config: MoverConfig | None = None,
    ) -> None:
        self.vlm_spec = vlm_spec
        self._backend = backend
        self.config = config
        self.limits = limits
        self.planner = planner
        self.esdf_config = esdf_config if esdf_config is not None else EsdfConfig()
        if planner is not None:
            check_field_reach(planner.config, self.esdf_config.max_distance_m)
        self.mover_config = mover_config if mover_config is not None else MoverConfig()
        self.name = "spf_planner" if planner is not None else "spf"
        self.esdf: EsdfMap | None = None

    def reset(self, spec: EpisodeSpec) -> None:
        self.plans = PlanMemory()  # straight-line plans start from the last one's reference
        self.spec = spec
        self.backend = self._backend if self._backend is not None else make_backend(self.vlm_spec, seed=spec.seed)
        self.runtime = spec.runtime
        self.latest: Observation | None = None
        self._asked_frame: str | None = None
        self.goal: np.ndarray | None = None
        self.hold_p = spec.start_state.p.copy()
        self.stats: Counter = Counter()
        self.fallbacks: Counter = Counter()
        if self.planner is not None:
            self.planner.reset()
            self.esdf = EsdfMap(self.esdf_config)
            self.movers = MoverTracker(self.mover_config)

    def step(self, t_s: float, state: VehicleState, obs: Observation | None) -> MethodStep:
        if obs is not None:
            self.latest = obs
            if self.esdf is not None:
                self.movers.observe(obs.t_s, obs.depth_m, obs.camera, obs.T_world_cam, self.esdf)
                map_frame(self.esdf, self.planner, obs.depth_m, obs.camera, obs.T_world_cam, obs.position)
        for landed in self.runtime.poll():
            if self._on_answer(landed.outcome):
                return MethodStep(None, True, {"stop": True})
        if not self.runtime.busy(SPF) and self.latest is not None and self.latest.frame_id != self._asked_frame:
            self._ask(self.latest)
        goal = self.goal if self.goal is not None else self.hold_p
        if self.planner is not None:
            volume = self.spec.flight_volume
            margin = self.planner.volume_goal_margin_m
            if volume is not None and not bool(volume.contains(goal, margin_m=margin)[0]):
                # the operator's flight volume: every method that flies our planner honours it
                goal = volume.clamp(goal, margin_m=margin)
                self.stats["goals_clamped"] += 1
            plan = self.planner.step(state, goal, self.movers.field(self.esdf, t_s), volume=volume)
            if not plan.ok:
                self.fallbacks[plan.fallback.value] += 1
            return MethodStep(plan.trajectory, False)
        return MethodStep(straight_plan(state, goal, self.limits, yaw_first=True, memory=self.plans), False)

    def _ask(self, obs: Observation) -> None:
        self._asked_frame = obs.frame_id
        messages, images = build_spf_prompt(self.spec.instruction, vlm_image(obs))
        backend, schema = self.backend, spf_schema() if self.config.structured_output else None
        self.stats["calls"] += 1

        def call() -> CallOutcome:
            return CallOutcome(SPF, obs.frame_id, backend.complete(messages, images, json_schema=schema, max_new_tokens=32), obs)

        self.runtime.submit(SPF, call)

    def _on_answer(self, out) -> bool:
        """Apply one landed answer; True when it is the stop answer."""
        if not isinstance(out, CallOutcome):
            log.error("SPF call raised: %r", out)
            self.stats["call_errors"] += 1
            return False
        if out.response.status is not CallStatus.OK:
            self.stats["call_failures"] += 1
            return False
        obs: Observation = out.payload
        h, w = obs.depth_m.shape
        ans = parse_spf_answer(out.response.text, (w, h))
        if ans.stop:
            self.stats["stop"] += 1
            return True
        if not ans.ok:
            log.info("SPF answer unreadable (%s): %r", ans.reason, out.response.text[:120])
            self.stats["unreadable"] += 1
            return False
        travel = min(float(ans.depth_m), self.config.max_travel_m)
        p_cam = obs.camera.back_project(np.asarray(ans.uv, float), travel)
        self.goal = transform_points(obs.T_world_cam, p_cam)
        self.stats["goals"] += 1
        return False

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: int(v) for k, v in self.stats.items()}
        out["uses_map"] = self.esdf is not None
        if self.esdf is not None:
            out["movers"] = self.movers.summary()
        if self.planner is not None:
            out["planner_fallbacks"] = dict(self.fallbacks)
        return out


def make_spf(vlm_spec: str, seed: int, **options) -> SpfMethod:
    """Registry factory of SPF. Options: the shared ``planner`` table (limits), ``esdf`` /
    ``verifier`` (accepted, unused: no map) and :class:`SpfConfig` fields."""
    planner, _, cfg = split_options(options, SpfConfig, "spf")
    return SpfMethod(vlm_spec, cfg, FlightLimits.from_planner(planner))


def make_spf_planner(vlm_spec: str, seed: int, **options) -> SpfMethod:
    """Registry factory of SPF with OnFly's ESDF + MPC. Options: the shared ``planner``,
    ``esdf`` and ``movers`` tables, ``verifier`` (unused) and :class:`SpfConfig` fields."""
    movers = MoverConfig(**dict(options.get("movers", {}) or {}))
    planner_cfg, esdf, cfg = split_options(options, SpfConfig, "spf_planner")
    return SpfMethod(
        vlm_spec, cfg, FlightLimits.from_planner(planner_cfg), shared_planner(planner_cfg), EsdfConfig(**esdf), mover_config=movers
    )
