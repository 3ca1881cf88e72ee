"""planning: the ESDF map, the MPC planner and the semantic-geometric verifier.

The few names a script needs, imported on first use (``import planning`` stays light)::

    from planning import Planner, PlannerConfig, EsdfMap, EsdfConfig, Verifier, VerifierConfig
    from planning import VehicleState, Trajectory, PinholeCamera, FlightVolume

``planning`` never imports ``vlm`` or ``onfly``.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "Planner",
    "PlannerConfig",
    "EsdfMap",
    "EsdfConfig",
    "Verifier",
    "VerifierConfig",
    "VehicleState",
    "Trajectory",
    "PinholeCamera",
    "FlightVolume",
]

_LAZY = {
    "Planner": "planning.planner",
    "PlannerConfig": "planning.planner_config",
    "EsdfMap": "planning.esdf",
    "EsdfConfig": "planning.esdf_config",
    "Verifier": "planning.verifier",
    "VerifierConfig": "planning.verifier_config",
    "VehicleState": "planning.trajectory",
    "Trajectory": "planning.trajectory",
    "PinholeCamera": "planning.camera",
    "FlightVolume": "planning.volume",
}


def __getattr__(name: str) -> Any:
    try:
        module = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'planning' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
