"""The paper's episode metrics (SR, OSR, CR, FT) plus NE and SPL.

Definitions (paper, "Metrics"; success radius 5 m):

- **SR**: the method *declared the end* (its own stop) within ``success_radius_m`` of the goal
  region and never collided. An episode that ends by the time limit is not a success even if
  the vehicle is near the goal: stopping by itself is part of the task.
- **OSR**: the vehicle was within ``success_radius_m`` of the goal region at least once before
  the episode ended (collision-free up to that moment).
- **CR**: the vehicle collided (the episode ends at the first collision).
- **FT**: seconds from take-off (the first sample) to the end of the episode.
- **NE**: distance from the final position to the goal region, metres.
- **SPL**: ``SR * L_ref / max(L, L_ref)`` with ``L`` the flown path length and ``L_ref`` the
  task's reference (shortest collision-free) path length.

Distances to the goal region are to the region's surface (0 inside), so a large object is
reached when the vehicle is near any part of it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable, Sequence

import numpy as np

__all__ = ["GoalRegion", "EpisodeTrace", "EpisodeMetrics", "episode_metrics", "summarize", "MetricsError"]


class MetricsError(ValueError):
    """Malformed trace or goal region."""


@dataclass(frozen=True, eq=False)
class GoalRegion:
    """An axis-aligned box in the world frame (a point when ``half_extents_m`` is zero).

    Attributes
    ----------
    center : array (3,), metres, world ENU
    half_extents_m : array (3,), metres, >= 0
    """

    center: np.ndarray
    half_extents_m: np.ndarray

    def __post_init__(self) -> None:
        c = np.asarray(self.center, float).reshape(-1)
        h = np.asarray(self.half_extents_m, float).reshape(-1)
        if c.shape != (3,) or h.shape != (3,) or not np.all(np.isfinite(c)) or not np.all(np.isfinite(h)):
            raise MetricsError(f"goal region needs finite center (3,) and half_extents_m (3,), got {c} {h}")
        if np.any(h < 0):
            raise MetricsError(f"half_extents_m must be >= 0, got {h}")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "half_extents_m", h)

    def distance(self, points) -> np.ndarray:
        """Euclidean distance from points (n, 3) or (3,) to the box (0 inside), metres."""
        p = np.asarray(points, float)
        excess = np.maximum(np.abs(p - self.center) - self.half_extents_m, 0.0)
        return np.linalg.norm(excess, axis=-1)


@dataclass(frozen=True, eq=False)
class EpisodeTrace:
    """What happened in one episode.

    Attributes
    ----------
    t_s : array (n,), sample times, seconds, increasing; ``t_s[0]`` is take-off
    positions : array (n, 3), metres, world ENU
    stopped_by_method : bool, the method declared the end (its final STOP)
    collided : bool, the episode ended at a collision (the last sample is the contact)
    """

    t_s: np.ndarray
    positions: np.ndarray
    stopped_by_method: bool
    collided: bool

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float)
        p = np.asarray(self.positions, float)
        if t.ndim != 1 or t.size < 1 or p.shape != (t.size, 3):
            raise MetricsError(f"t_s (n,) and positions (n, 3) required, got {t.shape} and {p.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p))):
            raise MetricsError("trace contains non-finite values")
        if np.any(np.diff(t) < 0):
            raise MetricsError("t_s must be non-decreasing")
        if self.stopped_by_method and self.collided:
            raise MetricsError("an episode ends either by the method's stop or by a collision, not both")
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "positions", p)


@dataclass(frozen=True)
class EpisodeMetrics:
    success: bool
    oracle_success: bool
    collided: bool
    flight_time_s: float
    navigation_error_m: float
    path_length_m: float
    spl: float


def episode_metrics(
    trace: EpisodeTrace, goal: GoalRegion, reference_path_m: float, success_radius_m: float = 5.0
) -> EpisodeMetrics:
    """Metrics of one episode (see the module docstring for the definitions)."""
    if not (reference_path_m >= 0 and np.isfinite(reference_path_m)):
        raise MetricsError(f"reference_path_m must be finite and >= 0, got {reference_path_m}")
    d = goal.distance(trace.positions)
    ne = float(d[-1])
    within = d <= success_radius_m
    # the contact sample of a collision does not count as having reached the goal
    reach = within[:-1] if trace.collided else within
    osr = bool(np.any(reach))
    success = bool(trace.stopped_by_method and not trace.collided and within[-1])
    length = float(np.sum(np.linalg.norm(np.diff(trace.positions, axis=0), axis=1)))
    spl = 0.0
    if success:
        spl = 1.0 if max(length, reference_path_m) == 0 else reference_path_m / max(length, reference_path_m)
    return EpisodeMetrics(
        success=success,
        oracle_success=osr,
        collided=bool(trace.collided),
        flight_time_s=float(trace.t_s[-1] - trace.t_s[0]),
        navigation_error_m=ne,
        path_length_m=length,
        spl=float(spl),
    )


def summarize(metrics: Iterable[EpisodeMetrics]) -> dict[str, float]:
    """Mean metrics over episodes: SR, OSR, CR as fractions in [0, 1]; FT, NE in s and m.

    ``FT`` is the mean over all episodes (as the paper reports), ``FT_success`` over
    successful ones only (NaN when none succeeded).
    """
    ms: Sequence[EpisodeMetrics] = list(metrics)
    if not ms:
        raise MetricsError("no episodes to summarize")
    succ = [m for m in ms if m.success]
    return {
        "episodes": len(ms),
        "SR": float(np.mean([m.success for m in ms])),
        "OSR": float(np.mean([m.oracle_success for m in ms])),
        "CR": float(np.mean([m.collided for m in ms])),
        "FT": float(np.mean([m.flight_time_s for m in ms])),
        "FT_success": float(np.mean([m.flight_time_s for m in succ])) if succ else float("nan"),
        "NE": float(np.mean([m.navigation_error_m for m in ms])),
        "SPL": float(np.mean([m.spl for m in ms])),
    }


def metrics_dict(m: EpisodeMetrics) -> dict:
    return asdict(m)
