"""One benchmark episode: a method flies a task in the embedded world under the paper's protocol.

Protocol (paper, "Simulation Experimental Setup"): the episode ends when the method declares
its stop, at the first collision, when the vehicle leaves the scene bounds, or at the time
limit (70 s). The control period is 0.1 s; camera frames reach the method every
``frame_period_s``. VLM latency is charged on the world's virtual clock: calls land after their
modelled latency while the vehicle keeps flying the last plan.

Under a realism profile the method reads estimates (``world.estimate``, each frame's pose) and
frames arrive late or never (``world.capture`` / ``world.receive``); the trace, the collision
and the out-of-bounds check use the truth (``world.state``).
"""

from __future__ import annotations

import logging
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from onfly import defaults
from onfly.bench.method import EpisodeSpec, Method, PrivilegedGoal
from onfly.bench.metrics import EpisodeMetrics, EpisodeTrace, GoalRegion, episode_metrics
from onfly.runtime import ClockRuntime
from onfly.world.world import World
from planning.volume import FlightVolume

__all__ = ["EpisodeConfig", "EpisodeResult", "EpisodeStep", "run_episode", "END_REASONS"]

log = logging.getLogger(__name__)

END_REASONS = ("stopped", "collision", "time_limit", "out_of_bounds", "method_error")


@dataclass(frozen=True)
class EpisodeConfig:
    """Protocol constants: the paper's limit, control period and success radius; a camera
    frame every 0.5 s as the CLI and the benchmark fly (one set of defaults:
    :mod:`onfly.defaults`)."""

    time_limit_s: float = defaults.TIME_LIMIT_S
    control_period_s: float = defaults.CONTROL_PERIOD_S
    frame_period_s: float = defaults.FRAME_PERIOD_S
    success_radius_m: float = defaults.SUCCESS_RADIUS_M

    def __post_init__(self) -> None:
        for name in ("time_limit_s", "control_period_s", "frame_period_s", "success_radius_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"EpisodeConfig.{name} must be positive, got {v}")
        if self.frame_period_s < self.control_period_s - 1e-9:
            raise ValueError("EpisodeConfig.frame_period_s must be >= control_period_s")


@dataclass(frozen=True, eq=False)
class EpisodeStep:
    """What an observer sees each control period (before the world steps): ``state`` is the
    true state, ``estimate`` the one the method read (the same object under ``ideal``)."""

    t_s: float
    state: Any
    obs: Any
    output: Any
    method: Any
    estimate: Any = None


@dataclass(frozen=True, eq=False)
class EpisodeResult:
    """Everything the runner records about an episode (JSON-able through :meth:`to_dict`)."""

    metrics: EpisodeMetrics
    end_reason: str
    trace: EpisodeTrace
    collision: dict | None
    vlm_calls: dict
    vlm_charged_s: dict
    method_summary: dict
    sim_s: float
    wall_s: float
    error: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def realtime_factor(self) -> float:
        return self.sim_s / self.wall_s if self.wall_s > 0 else float("inf")

    def to_dict(self) -> dict:
        from dataclasses import asdict

        return {
            "metrics": asdict(self.metrics),
            "end_reason": self.end_reason,
            "collision": self.collision,
            "vlm_calls": self.vlm_calls,
            "vlm_charged_s": self.vlm_charged_s,
            "method_summary": self.method_summary,
            "sim_s": self.sim_s,
            "wall_s": self.wall_s,
            "error": self.error,
            **self.extra,
        }


def run_episode(
    world: World,
    method: Method,
    *,
    instruction: str,
    goal: GoalRegion,
    reference_path_m: float,
    seed: int,
    error_model: str,
    config: EpisodeConfig | None = None,
    privileged: PrivilegedGoal | None = None,
    observer: Callable[[EpisodeStep], None] | None = None,
) -> EpisodeResult:
    """Fly one episode and compute its metrics. ``world`` must be fresh (at the start pose).

    ``observer`` (optional) is called after every control period with an :class:`EpisodeStep`
    (recordings, live views); it must not change the world.
    """
    cfg = config if config is not None else EpisodeConfig()
    wall0 = time.perf_counter()
    runtime = ClockRuntime(world.clock)
    t0 = world.clock.now_s
    spec = EpisodeSpec(
        instruction=instruction,
        camera=world.camera,
        start_state=world.estimate,
        seed=seed,
        runtime=runtime,
        error_model=error_model,
        privileged=privileged if getattr(method, "privileged", False) else None,
        flight_volume=FlightVolume(world.scene.bounds.min_m, world.scene.bounds.max_m),
    )
    times = [t0]
    positions = [world.state.p.copy()]
    end_reason = "time_limit"
    error = ""
    collision = None
    try:
        method.reset(spec)
        next_frame_s = t0
        t = t0
        n_steps = int(round(cfg.time_limit_s / cfg.control_period_s))
        for _ in range(n_steps):
            if t >= next_frame_s - 1e-9:
                world.capture()
                next_frame_s += cfg.frame_period_s
            obs = world.receive()
            estimate = world.estimate
            out = method.step(t, estimate, obs)
            if out.done:
                end_reason = "stopped"
                break
            if out.trajectory is not None:
                world.set_trajectory(out.trajectory)
            if observer is not None:
                observer(EpisodeStep(t, world.state, obs, out, method, estimate))
            ws = world.step(cfg.control_period_s)
            runtime.deliver(ws.completed)
            t = world.clock.now_s
            times.append(t)
            positions.append(ws.state.p.copy())
            if ws.collision is not None:
                end_reason = "collision"
                c = ws.collision
                collision = {
                    "t_s": float(c.t_s),
                    "position": np.asarray(c.position_m).tolist(),
                    "point": np.asarray(c.point_m).tolist(),
                    "object": c.object_name,
                }
                break
            if ws.out_of_bounds:
                end_reason = "out_of_bounds"
                break
    except Exception as exc:  # a method bug ends this episode, recorded, never the whole run
        end_reason = "method_error"
        error = "".join(traceback.format_exception_only(type(exc), exc)).strip()
        log.error("episode ended by a method error: %s\n%s", error, traceback.format_exc())
    trace = EpisodeTrace(
        np.asarray(times), np.asarray(positions), stopped_by_method=end_reason == "stopped", collided=end_reason == "collision"
    )
    metrics = episode_metrics(trace, goal, reference_path_m, cfg.success_radius_m)
    try:
        summary = method.summary()
    except Exception as exc:  # pragma: no cover - summary must not lose the episode
        summary = {"summary_error": repr(exc)}
    return EpisodeResult(
        metrics=metrics,
        end_reason=end_reason,
        trace=trace,
        collision=collision,
        vlm_calls=world.clock.call_counts,
        vlm_charged_s=world.clock.charged_s,
        method_summary=summary,
        sim_s=float(times[-1] - t0),
        wall_s=time.perf_counter() - wall0,
        error=error,
    )
