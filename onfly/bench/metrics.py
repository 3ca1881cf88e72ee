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

Tracking tasks (``kind = "track"``, :func:`track_metrics`) follow a moving actor. With ``d(t)``
the *horizontal* distance from the vehicle to the actor's centre and the task's band
``[lo, hi]``:

- **time in band**: the fraction of the horizon ``H`` during which ``lo <= d <= hi``. Samples
  are held until the next one (sample ``i`` stands for ``[t_i, t_{i+1})``). ``H`` is the task's
  ``duration_s`` (an episode that ends early - collision, out of bounds, a stop that is not
  asked for - counts the rest as out of band), or the episode's length when the task asks for
  a stop and the method declared it;
- **band error**: the time-weighted mean of ``max(lo - d, 0, d - hi)`` over the flown samples
  (0 inside the band), metres;
- **lost / re-found**: a maximal stretch out of the band that lasts longer than
  ``lost_after_s`` (from its first sample to the first sample back in band, or to the end)
  counts as *lost*; it is *re-found* when the vehicle gets back into the band. A stretch
  before the vehicle first enters the band is the acquisition, not a loss;
- **stop** (tasks with ``stop_radius_m``): the method declared its stop, the actor was not
  moving at that moment but had moved before (it *has stopped*; a person who has not set off
  yet has not), and ``d <= stop_radius_m`` then;
- **success**: time in band ``>= in_band_frac``, no collision, and the stop where asked.
  The classic SR of a tracking episode is this success; OSR is the time-in-band condition
  alone (collision-free up to then), SPL is SR (no reference path applies).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Iterable, Sequence

import numpy as np

__all__ = [
    "GoalRegion",
    "EpisodeTrace",
    "EpisodeMetrics",
    "episode_metrics",
    "summarize",
    "MetricsError",
    "TrackMetrics",
    "track_metrics",
    "summarize_track",
    "as_track_episode",
]


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


@dataclass(frozen=True)
class TrackMetrics:
    """Metrics of one tracking episode (definitions in the module docstring).

    in_band_frac : time in band / horizon, [0, 1]
    band_error_m : time-weighted mean distance outside the band, metres
    times_lost, times_refound : counts of out-of-band stretches longer than ``lost_after_s``,
        and of those that ended back in the band
    stop_ok : the stop condition held (None when the task asks for no stop)
    success : in band long enough, no collision, stop where asked
    band_ok : in band long enough (the time-in-band condition alone)
    horizon_s : the horizon the fraction is taken over, seconds
    min_distance_m, final_distance_m : horizontal vehicle-actor distances, metres
    """

    in_band_frac: float
    band_error_m: float
    times_lost: int
    times_refound: int
    stop_ok: bool | None
    success: bool
    band_ok: bool
    horizon_s: float
    min_distance_m: float
    final_distance_m: float


def track_metrics(
    trace: EpisodeTrace,
    actor_positions,
    actor_moving,
    *,
    band_m: tuple[float, float],
    in_band_frac: float,
    duration_s: float,
    lost_after_s: float,
    stop_radius_m: float | None = None,
) -> TrackMetrics:
    """Tracking metrics of one episode.

    Parameters
    ----------
    trace : the episode's trace (vehicle positions (n, 3) at ``t_s`` (n,), world ENU)
    actor_positions : array (n, 3), the followed actor's centre at the same times, metres
    actor_moving : bool array (n,), whether the actor was moving at each time
    band_m, in_band_frac, duration_s, lost_after_s, stop_radius_m : the task's
        :class:`onfly.bench.tasks.TrackSpec`
    """
    t = trace.t_s
    n = t.size
    A = np.asarray(actor_positions, float)
    moving = np.asarray(actor_moving, bool).reshape(-1)
    if A.shape != (n, 3) or moving.shape != (n,) or not np.all(np.isfinite(A)):
        raise MetricsError(f"actor positions (n, 3) and moving flags (n,) for n = {n} samples required, got {A.shape} and {moving.shape}")
    lo, hi = float(band_m[0]), float(band_m[1])
    if not (0 < lo < hi) or not (0 < in_band_frac <= 1) or not (duration_s > 0) or not (lost_after_s > 0):
        raise MetricsError(f"bad tracking spec: band {band_m}, fraction {in_band_frac}, duration {duration_s}, lost after {lost_after_s}")
    d = np.linalg.norm(trace.positions[:, :2] - A[:, :2], axis=1)
    inside = (d >= lo) & (d <= hi)
    err = np.maximum(np.maximum(lo - d, d - hi), 0.0)
    flown = float(t[-1] - t[0])
    # sample i stands for [t_i, t_{i+1}); the last sample for nothing (0 s), unless it is the only one
    w = np.diff(t) if n > 1 else np.zeros(0)
    if stop_radius_m is not None and trace.stopped_by_method:
        horizon = flown
    else:
        horizon = max(float(duration_s), flown)
    if horizon <= 0:
        frac = float(inside[0])
        band_err = float(err[0])
    else:
        frac = float(np.sum(w * inside[:-1]) / horizon)
        band_err = float(np.sum(w * err[:-1]) / flown) if flown > 0 else float(err[0])
    lost = refound = 0
    entered = bool(inside[0])
    i = 0
    while i < n:
        if inside[i]:
            entered = True
            i += 1
            continue
        j = i
        while j < n and not inside[j]:
            j += 1
        end_t = t[j] if j < n else t[-1]
        if entered and end_t - t[i] > lost_after_s:
            lost += 1
            refound += int(j < n)
        i = j
    stop_ok = None
    if stop_radius_m is not None:
        stop_ok = bool(trace.stopped_by_method and not moving[-1] and bool(moving[:-1].any()) and d[-1] <= stop_radius_m)
    band_ok = bool(frac >= in_band_frac - 1e-12)
    ok = band_ok and not trace.collided and (stop_ok is None or stop_ok)
    return TrackMetrics(
        in_band_frac=frac,
        band_error_m=band_err,
        times_lost=lost,
        times_refound=refound,
        stop_ok=stop_ok,
        success=bool(ok),
        band_ok=band_ok,
        horizon_s=float(horizon),
        min_distance_m=float(d.min()),
        final_distance_m=float(d[-1]),
    )


def as_track_episode(m: EpisodeMetrics, tm: TrackMetrics) -> EpisodeMetrics:
    """The classic metrics of a tracking episode: SR is the tracking success, OSR the time in
    band alone, SPL is SR (see the module docstring)."""
    from dataclasses import replace

    return replace(m, success=tm.success, oracle_success=tm.band_ok, spl=float(tm.success))


def summarize_track(metrics: Iterable[TrackMetrics]) -> dict[str, float]:
    """Means over tracking episodes: time in band, band error, lost and re-found counts, and the
    share of stop episodes whose stop held (None when none asked for one)."""
    ms = list(metrics)
    if not ms:
        raise MetricsError("no tracking episodes to summarize")
    stops = [m.stop_ok for m in ms if m.stop_ok is not None]
    return {
        "episodes": len(ms),
        "in_band": float(np.mean([m.in_band_frac for m in ms])),
        "band_error_m": float(np.mean([m.band_error_m for m in ms])),
        "lost": float(np.mean([m.times_lost for m in ms])),
        "refound": float(np.mean([m.times_refound for m in ms])),
        "stop_ok": float(np.mean(stops)) if stops else None,
    }
