"""OnFly: onboard zero-shot aerial vision-language navigation.

The public API (``import onfly``; see ``docs/api.md``)::

    onfly.fly(task, ...)      fly one task in the embedded world -> onfly.Flight (metrics, motion)
    onfly.benchmark(config, ...)  run a benchmark (BenchConfig or a TOML path) -> BenchResult
    onfly.replay_recording(path, ...)  replay a recording open loop -> ReplayReport
    onfly.tasks(...)          the benchmark's tasks (filtered as ``onfly tasks list``)

and the configs they take: ``PilotConfig``, ``PlannerConfig``, ``VerifierConfig``,
``EsdfConfig``, ``EpisodeConfig``, ``BenchConfig``, ``ReplayConfig``; ``onfly.defaults`` holds
the one set of defaults the API, the CLI and the benchmark share.

Names are imported on first use, so ``import onfly`` (and the ``onfly`` CLI's start-up) loads
none of the heavy stack (open3d, casadi, scipy, torch).
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "fly",
    "benchmark",
    "replay_recording",
    "tasks",
    "Flight",
    "PilotConfig",
    "PlannerConfig",
    "VerifierConfig",
    "EsdfConfig",
    "EpisodeConfig",
    "BenchConfig",
    "ReplayConfig",
    "defaults",
]

_LAZY = {
    "fly": ("onfly.api", "fly"),
    "benchmark": ("onfly.api", "benchmark"),
    "replay_recording": ("onfly.api", "replay_recording"),
    "tasks": ("onfly.api", "tasks"),
    "Flight": ("onfly.api", "Flight"),
    "PilotConfig": ("onfly.pilot", "PilotConfig"),
    "PlannerConfig": ("planning.planner_config", "PlannerConfig"),
    "VerifierConfig": ("planning.verifier_config", "VerifierConfig"),
    "EsdfConfig": ("planning.esdf_config", "EsdfConfig"),
    "EpisodeConfig": ("onfly.bench.episode", "EpisodeConfig"),
    "BenchConfig": ("onfly.bench.runner", "BenchConfig"),
    "ReplayConfig": ("onfly.replay", "ReplayConfig"),
    "defaults": ("onfly.defaults", None),
}


def __getattr__(name: str) -> Any:
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'onfly' has no attribute {name!r}") from None
    mod = importlib.import_module(module)
    value = mod if attr is None else getattr(mod, attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
