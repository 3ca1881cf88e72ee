"""The OnFly pilot (and its ablations) as a benchmark method."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace
from typing import Any

from onfly.bench.method import EpisodeSpec, MethodStep
from onfly.observation import Observation
from onfly.pilot import OnFlyPilot, PilotConfig
from planning.planner import Planner
from planning.trajectory import VehicleState
from vlm.factory import make_backend

__all__ = ["OnFlyMethod", "ABLATIONS", "ablation_config", "make_onfly_factory"]

#: Paper Table III ablations as config changes of the full system.
ABLATIONS: dict[str, dict[str, Any]] = {
    "onfly": {},
    "onfly_no_dual_agent": {"dual_agent": False},
    "onfly_no_verification": {"verify": False},
    "onfly_no_planner": {"use_planner": False},
    "onfly_time_sampling": {"memory": "time"},
    "onfly_sliding_window": {"memory": "sliding"},
    # ours: the paper's pilot without the search (onfly.search) and last-sighting recovery
    "onfly_no_search": {"search": False},
}


def ablation_config(name: str, base: PilotConfig | None = None) -> PilotConfig:
    """The pilot config of a named variant (see :data:`ABLATIONS`)."""
    if name not in ABLATIONS:
        raise ValueError(f"unknown OnFly variant {name!r}; valid: {sorted(ABLATIONS)}")
    cfg = base if base is not None else PilotConfig()
    changes = dict(ABLATIONS[name])
    if "memory" in changes:
        changes["memory"] = replace(cfg.memory, strategy=changes["memory"])
    if "search" in changes:
        changes["search"] = replace(cfg.search, enabled=changes["search"])
    return replace(cfg, **changes)


class OnFlyMethod:
    """Runs :class:`onfly.pilot.OnFlyPilot` in the benchmark.

    Parameters
    ----------
    vlm_spec : backend spec for :func:`vlm.factory.make_backend` (``sim:nominal`` ...)
    config : the pilot config (a variant from :func:`ablation_config`)
    name : the row name in result tables
    planner : optional prebuilt Planner shared across episodes of one process (reset per episode)
    """

    privileged = False

    def __init__(self, vlm_spec: str, config: PilotConfig | None = None, name: str = "onfly", planner: Planner | None = None) -> None:
        self.vlm_spec = vlm_spec
        self.config = config if config is not None else PilotConfig()
        self.name = name
        self._planner = planner
        self.pilot: OnFlyPilot | None = None

    def reset(self, spec: EpisodeSpec) -> None:
        backend = make_backend(self.vlm_spec, seed=spec.seed)
        if self._planner is None and self.config.use_planner:
            self._planner = Planner(self.config.planner)
        self.pilot = OnFlyPilot(self.config, backend, spec.runtime, planner=self._planner, volume=spec.flight_volume)
        self.pilot.begin(spec.instruction, spec.start_state.t_s)

    def step(self, t_s: float, state: VehicleState, obs: Observation | None) -> MethodStep:
        if self.pilot is None:
            raise RuntimeError("reset() must be called before step()")
        tick = self.pilot.tick(t_s, state, obs)
        return MethodStep(tick.trajectory, tick.finished)

    def summary(self) -> dict[str, Any]:
        if self.pilot is None:
            return {}
        p = self.pilot
        kinds = Counter(e.kind for e in p.events)
        decisions = [e.data for e in p.events if e.kind == "decision"]
        monitors = [e.data for e in p.events if e.kind == "monitor"]
        statuses = Counter(str(m.get("status")) for m in monitors)
        failed = Counter((d.get("reason") or "").split(":")[0] for d in decisions if d.get("goal_world") is None)
        moved = [d for d in decisions if d.get("verifier") and (d["verifier"].get("pixel_shift_px") or 0) > 0]
        return {
            "mode": p.mode.value,
            "subtasks": list(p.tasks.subtasks) if p.tasks else [],
            "subtask_index": p.tasks.index if p.tasks else 0,
            "events": dict(kinds),
            "decisions": len(decisions),
            "decision_failures": dict(failed),
            "verifier_moved": len(moved),
            "monitor_statuses": dict(statuses),
            "planner_fallbacks": p.planner_fallbacks,
            "search_triggers": dict(Counter(e.data.get("trigger") for e in p.events if e.kind == "search_start")),
            "goals_clamped": kinds.get("goal_clamped", 0),
            "follow": p.follow.summary() if hasattr(p, "follow") else {},
            "movers": p.movers.summary() if hasattr(p, "movers") else {},
        }


_PLANNERS: dict[Any, Planner] = {}


def _shared_planner(config) -> Planner:
    """One Planner per planner config per process (CasADi set-up is built once; the pilot
    resets it at every episode)."""
    if config not in _PLANNERS:
        _PLANNERS[config] = Planner(config)
    return _PLANNERS[config]


def make_onfly_factory(variant: str):
    """Registry factory of an OnFly variant: ``factory(vlm_spec, seed, **options)``.

    Options: the shared tables ``planner`` / ``esdf`` / ``verifier`` / ``movers`` and the variant's own
    ``[methods.<name>]`` table, all :class:`PilotConfig` fields (``memory`` as a table too).
    """
    if variant not in ABLATIONS:
        raise ValueError(f"unknown OnFly variant {variant!r}; valid: {sorted(ABLATIONS)}")

    def factory(vlm_spec: str, seed: int, **options) -> OnFlyMethod:
        data = {k: dict(v or {}) if k in ("planner", "esdf", "verifier", "memory", "movers") else v for k, v in options.items()}
        base = PilotConfig.from_dict(data)
        cfg = ablation_config(variant, base)
        planner = _shared_planner(cfg.planner) if cfg.use_planner else None
        return OnFlyMethod(vlm_spec, cfg, name=variant, planner=planner)

    factory.__name__ = f"make_{variant}"
    return factory


def _register() -> None:
    from onfly.bench.registry import register

    for name in ABLATIONS:
        register(name, make_onfly_factory(name), replace=True)


_register()
