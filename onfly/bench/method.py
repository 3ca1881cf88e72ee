"""The method interface: what the benchmark runner evaluates.

Every method (the OnFly pilot and its ablations, the oracle pilot, the baselines) is driven by
the same episode loop (:mod:`onfly.bench.episode`) under the same world, clock and simulated-VLM
error model. Per control period the loop calls :meth:`Method.step` with the vehicle state and,
when a camera frame is due, the new observation; the method returns the plan to fly and
whether it declares the task done (its own stop).

A method sees the instruction, the camera, its seed, the agent runtime and the operator's
flight volume (the scene's bounds: an operator feature every method that flies our planner
honours, like a geofence on a real vehicle). Only a method that
sets ``privileged = True`` (the oracle, a check of the world and planner, never a method in the
tables) also receives the task's goal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

from onfly.observation import Observation
from onfly.runtime import ClockRuntime
from planning.camera import PinholeCamera
from planning.trajectory import Trajectory, VehicleState
from planning.volume import FlightVolume

__all__ = ["EpisodeSpec", "MethodStep", "Method", "MethodFactory", "PrivilegedGoal"]


@dataclass(frozen=True, eq=False)
class PrivilegedGoal:
    """Ground truth for privileged methods only: the goal region and reference waypoints.

    center / half_extents_m : the goal box (metres, world ENU)
    waypoints : array (k, 3), a collision-free reference path ending near the goal (may be empty)
    track : a tracking task's :class:`onfly.bench.tasks.TrackSpec`, else None
    actor_motion : the followed actor's motion (``onfly.world.actors``), else None: its true
        pose at any time is ``onfly.world.actors.pose_at(actor_motion, t_s)``
    """

    center: np.ndarray
    half_extents_m: np.ndarray
    waypoints: np.ndarray
    track: Any = None
    actor_motion: Any = None


@dataclass(frozen=True, eq=False)
class EpisodeSpec:
    """What a method is told when an episode starts.

    flight_volume : the operator's flight volume (world ENU, metres), or None
    """

    instruction: str
    camera: PinholeCamera
    start_state: VehicleState
    seed: int
    runtime: ClockRuntime
    error_model: str
    privileged: PrivilegedGoal | None = None
    flight_volume: FlightVolume | None = None


@dataclass(frozen=True, eq=False)
class MethodStep:
    """A method's answer for one control period.

    trajectory : the plan to fly from now on (None: keep flying the last one)
    done : the method declares the task finished (its stop); the episode ends
    """

    trajectory: Trajectory | None
    done: bool = False
    info: dict = field(default_factory=dict)


class Method(Protocol):
    name: str
    privileged: bool

    def reset(self, spec: EpisodeSpec) -> None:
        """Start an episode (e.g. decompose the instruction)."""
        ...

    def step(self, t_s: float, state: VehicleState, obs: Observation | None) -> MethodStep: ...

    def summary(self) -> dict[str, Any]:
        """JSON-able facts about the episode (VLM calls, events counts, failure hints)."""
        ...


#: A factory builds a fresh method for one episode: ``factory(vlm_spec, seed) -> Method``.
MethodFactory = Callable[[str, int], Method]
