"""Map-free straight-line plans: the "without planner" ablation and SPF-style flight.

The plan flies a straight segment to the goal under the same dynamic limits as the MPC
(speed, acceleration, yaw rate) with no knowledge of obstacles: accelerate toward the goal,
cruise, brake to stop at it (a 1D time-optimal bang-coast-bang profile along the line, re-planned
from the current state each step). Yaw turns toward the goal bearing at the limited rate. With
``yaw_first=True`` the vehicle does not translate until its heading is within
``yaw_tolerance_rad`` of the bearing (SPF's yaw-then-straight-line motion).
"""

from __future__ import annotations

import numpy as np

from planning.frames import unwrap_near
from planning.trajectory import Trajectory, VehicleState

__all__ = ["straight_line_plan"]


def straight_line_plan(
    state: VehicleState,
    goal,
    *,
    v_max_mps: float,
    a_max_mps2: float,
    yaw_rate_max_rps: float,
    dt_s: float = 0.1,
    steps: int = 40,
    yaw_first: bool = False,
    yaw_tolerance_rad: float = 0.15,
    bearing_min_dist_m: float = 0.3,
    yaw_ref: float | None = None,
    reference: Trajectory | None = None,
    reference_reset_m: float = 1.5,
    reference_max_age_s: float = 0.5,
) -> Trajectory:
    """A ``steps``-interval plan from ``state`` straight at ``goal`` (3,), world ENU metres.

    Every interval's acceleration has norm <= ``a_max_mps2``; velocities stay within
    ``v_max_mps`` when the start does; yaw rate within ``yaw_rate_max_rps``. ``yaw_ref``
    (radians) overrides the goal bearing as the heading to turn to.

    ``reference`` (optional): the plan the vehicle has been flying. When it is at most
    ``reference_max_age_s`` old and the measured position lies within ``reference_reset_m`` of
    its position at ``state.t_s``, the new plan starts from that reference position and
    velocity (yaw from the measurement), so the vehicle's position controller corrects a
    tracking error (a gust) instead of every plan restarting wherever the vehicle was pushed;
    the same rule as :class:`planning.planner.Planner` (``reference_start``).
    """
    goal = np.asarray(goal, float).reshape(3)
    if not np.all(np.isfinite(goal)):
        raise ValueError(f"goal must be finite, got {goal}")
    if reference is not None and 0.0 <= state.t_s - reference.t0_s <= reference_max_age_s:
        p_r, v_r = reference.sample(state.t_s)[0:2]
        if np.linalg.norm(p_r - state.p) <= reference_reset_m:
            state = VehicleState(state.t_s, p_r, v_r, state.yaw, state.yaw_rate, state.a)
    p = np.zeros((steps + 1, 3))
    v = np.zeros((steps + 1, 3))
    yaw = np.zeros(steps + 1)
    a = np.zeros((steps, 3))
    wr = np.zeros(steps)
    p[0], v[0], yaw[0] = state.p, state.v, state.yaw
    d0 = goal[:2] - state.p[:2]
    bearing = float(np.arctan2(d0[1], d0[0])) if np.linalg.norm(d0) > bearing_min_dist_m else state.yaw
    psi_ref = float(unwrap_near(bearing if yaw_ref is None else yaw_ref, state.yaw))
    for k in range(steps):
        # yaw: rate-limited step toward the bearing
        err = psi_ref - yaw[k]
        wr[k] = float(np.clip(err / dt_s, -yaw_rate_max_rps, yaw_rate_max_rps))
        yaw[k + 1] = yaw[k] + wr[k] * dt_s
        hold = yaw_first and abs(err) > yaw_tolerance_rad
        to_goal = goal - p[k]
        dist = float(np.linalg.norm(to_goal))
        if hold or dist < 1e-6:
            v_des = np.zeros(3)
        else:
            # fastest speed from which braking at a_max still stops at the goal
            speed = min(v_max_mps, np.sqrt(2.0 * a_max_mps2 * dist), dist / dt_s)
            v_des = to_goal / dist * speed
        dv = v_des - v[k]
        n = float(np.linalg.norm(dv))
        a[k] = dv / dt_s if n <= a_max_mps2 * dt_s else dv / n * a_max_mps2
        v[k + 1] = v[k] + a[k] * dt_s
        p[k + 1] = p[k] + v[k] * dt_s + 0.5 * a[k] * dt_s * dt_s
    return Trajectory(state.t_s, dt_s, p, v, yaw, a, wr)
