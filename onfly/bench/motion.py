"""What planner and verifier weights change in a flight: smoothness, length, clearance, timing
and heading, computed from an episode's flown samples.

All quantities come from the vehicle states sampled once per control period (the world's
simulated vehicle, 10 Hz in the benchmark), by finite differences on a uniform grid:

- ``rms_accel_mps2``: root mean square of the acceleration magnitude, second differences of
  position over dt^2;
- ``rms_jerk_mps3``: root mean square of the jerk magnitude, third differences over dt^3;
- ``path_length_m``: length of the flown polyline;
- ``time_to_goal_s``: time from take-off until the vehicle first came within the success
  radius of the goal region (None if it never did);
- ``yaw_error_deg``: mean absolute angle between the vehicle's heading and the horizontal
  bearing to the goal centre, over samples more than ``bearing_min_m`` (horizontally) from the
  goal centre (None without such samples). A camera that looks where the vehicle goes keeps it
  small; the planner's yaw weight moves it.

The minimum clearance to the scene is the exact one the runner computes (mesh distance of the
flown samples, :meth:`onfly.world.collision.CollisionChecker.clearance`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["MotionMetrics", "motion_metrics", "MOTION_KEYS"]

#: Keys of :meth:`MotionMetrics.to_dict` that summaries average over episodes.
MOTION_KEYS = ("rms_accel_mps2", "rms_jerk_mps3", "path_length_m", "time_to_goal_s", "yaw_error_deg")


@dataclass(frozen=True)
class MotionMetrics:
    """Per-episode motion quantities (see the module docstring); None = undefined."""

    rms_accel_mps2: float | None
    rms_jerk_mps3: float | None
    path_length_m: float
    time_to_goal_s: float | None
    yaw_error_deg: float | None

    def to_dict(self) -> dict:
        return asdict(self)


def _rms_norm(d: np.ndarray) -> float | None:
    if len(d) == 0:
        return None
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def motion_metrics(
    t_s,
    positions_m,
    yaw_rad,
    goal_center_m,
    goal_distance_m,
    success_radius_m: float,
    *,
    bearing_min_m: float = 1.0,
) -> MotionMetrics:
    """Motion metrics of one flight.

    Parameters
    ----------
    t_s : (n,) sample times, seconds, uniform spacing (the control period)
    positions_m : (n, 3) positions, metres, world ENU
    yaw_rad : (n,) headings, radians (ENU, counter-clockwise from +x)
    goal_center_m : (3,) goal centre, metres
    goal_distance_m : (n,) distance of each sample to the goal region, metres
    success_radius_m : the episode's success radius, metres
    bearing_min_m : samples closer (horizontally) to the goal centre are left out of the yaw error
    """
    t = np.asarray(t_s, float).reshape(-1)
    p = np.asarray(positions_m, float).reshape(-1, 3)
    yaw = np.asarray(yaw_rad, float).reshape(-1)
    if not (len(t) == len(p) == len(yaw)):
        raise ValueError(f"t_s, positions_m and yaw_rad need one sample each, got {len(t)}, {len(p)}, {len(yaw)}")
    if len(t) == 0:
        raise ValueError("motion_metrics needs at least one sample")
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    acc = np.diff(p, n=2, axis=0) / dt**2 if dt > 0 else np.zeros((0, 3))
    jerk = np.diff(p, n=3, axis=0) / dt**3 if dt > 0 else np.zeros((0, 3))
    length = float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
    inside = np.flatnonzero(np.asarray(goal_distance_m, float).reshape(-1) <= success_radius_m)
    ttg = float(t[inside[0]] - t[0]) if len(inside) else None
    g = np.asarray(goal_center_m, float).reshape(3)
    d = g[None, :2] - p[:, :2]
    far = np.linalg.norm(d, axis=1) > bearing_min_m
    yaw_err = None
    if far.any():
        bearing = np.arctan2(d[far, 1], d[far, 0])
        err = np.abs((yaw[far] - bearing + math.pi) % (2 * math.pi) - math.pi)
        yaw_err = float(np.degrees(err.mean()))
    return MotionMetrics(_rms_norm(acc), _rms_norm(jerk), length, ttg, yaw_err)
