"""Vehicle state and planned trajectories: the values the planner hands to a vehicle.

World frame ENU, metres, seconds, radians. These frozen dataclasses cross package boundaries
(planner -> simulated vehicle, MAVLink bridge, logs), so they hold numpy arrays only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planning.frames import wrap_angle

__all__ = ["VehicleState", "Trajectory", "TrajectoryError"]


class TrajectoryError(ValueError):
    """A state or trajectory with wrong shapes or non-finite values."""


def _vec(x, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float).reshape(-1)
    if a.shape != (n,):
        raise TrajectoryError(f"{name} must have shape ({n},), got {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise TrajectoryError(f"{name} is not finite: {a}")
    return a


@dataclass(frozen=True, eq=False)
class VehicleState:
    """Kinematic state of the vehicle.

    Attributes
    ----------
    t_s : float, seconds on the pilot's clock
    p : array (3,), position in metres, world ENU
    v : array (3,), velocity in m/s, world ENU
    yaw : float, heading of body x in radians, wrapped to (-pi, pi]
    yaw_rate : float, rad/s
    a : array (3,), acceleration in m/s^2 (last commanded), world ENU
    """

    t_s: float
    p: np.ndarray
    v: np.ndarray
    yaw: float
    yaw_rate: float = 0.0
    a: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if not np.isfinite(self.t_s):
            raise TrajectoryError(f"t_s must be finite, got {self.t_s}")
        object.__setattr__(self, "p", _vec(self.p, 3, "p"))
        object.__setattr__(self, "v", _vec(self.v, 3, "v"))
        object.__setattr__(self, "a", np.zeros(3) if self.a is None else _vec(self.a, 3, "a"))
        for name in ("yaw", "yaw_rate"):
            val = float(getattr(self, name))
            if not np.isfinite(val):
                raise TrajectoryError(f"{name} must be finite, got {val}")
        object.__setattr__(self, "yaw", wrap_angle(float(self.yaw)))
        object.__setattr__(self, "yaw_rate", float(self.yaw_rate))

    @property
    def x(self) -> np.ndarray:
        """Planner state vector ``[p(3), v(3), yaw]``, shape (7,)."""
        return np.concatenate([self.p, self.v, [self.yaw]])


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A time-parametrized plan: knots ``k = 0..N`` at ``t0_s + k * dt_s``.

    Attributes
    ----------
    t0_s : float, time of knot 0 on the pilot's clock, seconds
    dt_s : float, knot spacing, seconds
    p : array (N + 1, 3), positions, metres, world ENU
    v : array (N + 1, 3), velocities, m/s
    yaw : array (N + 1,), radians, *unwrapped* (continuous along the plan)
    a : array (N, 3), accelerations held over each interval, m/s^2
    yaw_rate : array (N,), rad/s held over each interval
    """

    t0_s: float
    dt_s: float
    p: np.ndarray
    v: np.ndarray
    yaw: np.ndarray
    a: np.ndarray
    yaw_rate: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.p, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2:
            raise TrajectoryError(f"p must have shape (N + 1, 3) with N >= 1, got {p.shape}")
        n = p.shape[0] - 1
        shapes = {"v": (n + 1, 3), "yaw": (n + 1,), "a": (n, 3), "yaw_rate": (n,)}
        for name, shape in shapes.items():
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != shape:
                raise TrajectoryError(f"{name} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise TrajectoryError(f"{name} is not finite")
            object.__setattr__(self, name, arr)
        if not np.all(np.isfinite(p)):
            raise TrajectoryError("p is not finite")
        object.__setattr__(self, "p", p)
        if not (self.dt_s > 0 and np.isfinite(self.dt_s)):
            raise TrajectoryError(f"dt_s must be positive, got {self.dt_s}")

    @property
    def steps(self) -> int:
        """Number of intervals N."""
        return self.p.shape[0] - 1

    @property
    def duration_s(self) -> float:
        return self.steps * self.dt_s

    @property
    def times_s(self) -> np.ndarray:
        """Knot times, shape (N + 1,), seconds."""
        return self.t0_s + self.dt_s * np.arange(self.steps + 1)

    def sample(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Exact state of the piecewise-constant-acceleration plan at time ``t_s``.

        Before ``t0_s`` the first knot is returned. After the end, the last knot's position
        and velocity are returned with zero acceleration; callers that outlive a plan decide
        whether to brake.

        Returns
        -------
        p (3,), v (3,), a (3,), yaw (wrapped), yaw_rate
        """
        tau = (t_s - self.t0_s) / self.dt_s
        if tau <= 0:
            return self.p[0].copy(), self.v[0].copy(), self.a[0].copy(), wrap_angle(self.yaw[0]), float(self.yaw_rate[0])
        k = int(np.floor(tau))
        if k >= self.steps:
            return self.p[-1].copy(), self.v[-1].copy(), np.zeros(3), wrap_angle(self.yaw[-1]), 0.0
        h = (tau - k) * self.dt_s
        a = self.a[k]
        p = self.p[k] + self.v[k] * h + 0.5 * a * h * h
        v = self.v[k] + a * h
        yaw = self.yaw[k] + self.yaw_rate[k] * h
        return p, v, a.copy(), wrap_angle(yaw), float(self.yaw_rate[k])
