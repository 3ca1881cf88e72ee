"""The simulated vehicle: a point mass with yaw tracking a planned trajectory within limits.

Translation is a double integrator driven by a PD tracking law with acceleration
feed-forward,

``a_cmd = a_ref + kp * (p_ref - p) + kd * (v_ref - v)``,

clipped so that ``|a| <= a_max`` (Euclidean norm) and the velocity reached at the end of the
step satisfies ``|v| <= v_max``. The clipped acceleration is held constant over a fixed step
``h`` and integrated exactly (``p += v h + a h^2 / 2``, ``v += a h``). Because ``|v|`` is
convex and the velocity is affine in time within a step, ``|v| <= v_max`` at both ends of a
step implies it throughout.

Yaw is a first-order system: ``yaw_rate = clip(yaw_rate_ref + k_yaw * wrap(yaw_ref - yaw),
+-yaw_rate_max)``, integrated exactly over the step.

Speed projection never raises the acceleration norm: projecting ``v + a h`` onto the ball
``|v| <= v_max`` that already holds ``v`` is non-expansive, so the projected acceleration is
no longer than the clipped one. A state that starts above ``v_max`` (not reachable from a
valid initial state) is braked at ``a_max``.

Realistic tracking (optional, from a realism profile; the law above is untouched without it):
with a :class:`onfly.world.realism.ControllerModel` the vehicle runs PX4's cascaded position
controller on the *estimated* position (``p + estimate_offset_m``, the odometry's drift),
``v_sp = v_ref + K_pos (p_ref - p_est)``, ``a_sp = a_ref + K_vel e + K_int integral(e)`` with
``e = v_sp - v``, clipped to the tilt limit, and its acceleration follows ``a_sp`` through a first-order lag; a
:class:`onfly.world.realism.GustProcess` adds the gust acceleration. Neither the speed limit
nor ``a_max`` bounds the result (they are the planner's limits, not physics). Without a plan
the controller holds the estimated position where the plan ended.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onfly.world.realism import ControllerModel, GustProcess
from planning.frames import wrap_angle
from planning.trajectory import Trajectory, VehicleState

__all__ = ["VehicleConfig", "SimVehicle", "VehicleError"]


class VehicleError(ValueError):
    """An invalid initial state or step request."""


@dataclass(frozen=True)
class VehicleConfig:
    """Limits and tracking gains of the simulated vehicle (paper defaults for the limits).

    v_max_mps : speed limit (norm of the 3D velocity), m/s
    a_max_mps2 : acceleration limit (norm), m/s^2
    yaw_rate_max_radps : |yaw rate| limit, rad/s
    body_radius_m : collision sphere radius, metres
    kp_per_s2, kd_per_s : PD gains on position and velocity error (critically damped at
        kd^2 = 4 kp)
    k_yaw_per_s : proportional gain on yaw error
    step_s : fixed integration step, seconds
    """

    v_max_mps: float = 0.6
    a_max_mps2: float = 0.6
    yaw_rate_max_radps: float = 0.4
    body_radius_m: float = 0.25
    kp_per_s2: float = 4.0
    kd_per_s: float = 4.0
    k_yaw_per_s: float = 2.0
    step_s: float = 0.01

    def __post_init__(self) -> None:
        for name in ("v_max_mps", "a_max_mps2", "yaw_rate_max_radps", "body_radius_m", "step_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"VehicleConfig.{name} must be positive and finite, got {v}")
        for name in ("kp_per_s2", "kd_per_s", "k_yaw_per_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"VehicleConfig.{name} must be >= 0 and finite, got {v}")


def _clip_norm(x: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(x))
    return x if n <= limit else x * (limit / n)


class SimVehicle:
    """Point-mass vehicle with yaw that tracks a :class:`Trajectory` within its limits.

    Without a trajectory (or once the last one has ended, where it holds its final knot)
    the vehicle brakes to a hover. Call :meth:`set_trajectory` with each new plan and
    :meth:`step` to advance time.
    """

    def __init__(
        self,
        initial: VehicleState,
        config: VehicleConfig | None = None,
        *,
        controller: ControllerModel | None = None,
        gusts: GustProcess | None = None,
    ) -> None:
        self.config = config if config is not None else VehicleConfig()
        self.controller = controller
        self.gusts = gusts
        #: estimate - truth of the position the controller reads (3,), metres; set by the world
        self.estimate_offset_m = np.zeros(3)
        self._hold: np.ndarray | None = None
        speed = float(np.linalg.norm(initial.v))
        if speed > self.config.v_max_mps + 1e-9:
            raise VehicleError(f"initial speed {speed:.3f} m/s exceeds v_max_mps {self.config.v_max_mps}")
        self._t = float(initial.t_s)
        self._p = initial.p.astype(float).copy()
        self._v = initial.v.astype(float).copy()
        self._yaw = float(initial.yaw)
        self._yaw_rate = 0.0
        self._a = np.zeros(3)
        self._a_thrust = np.zeros(3)
        self._vel_integral = np.zeros(3)
        self._traj: Trajectory | None = None

    @property
    def trajectory(self) -> Trajectory | None:
        return self._traj

    @property
    def state(self) -> VehicleState:
        """Current state; ``a`` and ``yaw_rate`` are those applied over the last step."""
        return VehicleState(self._t, self._p.copy(), self._v.copy(), self._yaw, self._yaw_rate, self._a.copy())

    def set_trajectory(self, trajectory: Trajectory | None) -> None:
        """Track ``trajectory`` from now on (None: brake to hover)."""
        if trajectory is not None and not isinstance(trajectory, Trajectory):
            raise VehicleError(f"expected a planning.trajectory.Trajectory, got {type(trajectory).__name__}")
        self._traj = trajectory
        self._hold = None

    def _reference(self, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Reference position, velocity and yaw at the start of the step; feed-forward
        acceleration and yaw rate at its midpoint (so a step that starts a rounding error
        before a knot still gets the next interval's held input)."""
        if self._traj is None:
            return self._p.copy(), np.zeros(3), np.zeros(3), self._yaw, 0.0
        p_r, v_r, _, yaw_r, _ = self._traj.sample(self._t)
        _, _, a_r, _, yaw_rate_r = self._traj.sample(self._t + 0.5 * h)
        return p_r, v_r, a_r, yaw_r, yaw_rate_r

    def _advance(self, a: np.ndarray, yaw_r: float, yaw_rate_r: float, h: float) -> None:
        """Integrate ``h`` seconds under the body acceleration ``a`` (3,) m/s^2 (held), and the
        yaw loop toward ``yaw_r`` with feed-forward ``yaw_rate_r`` (rate-limited)."""
        c = self.config
        self._p = self._p + self._v * h + 0.5 * a * h * h
        self._v = self._v + a * h
        self._a = a
        rate = yaw_rate_r + c.k_yaw_per_s * wrap_angle(yaw_r - self._yaw)
        rate = float(np.clip(rate, -c.yaw_rate_max_radps, c.yaw_rate_max_radps))
        self._yaw = wrap_angle(self._yaw + rate * h)
        self._yaw_rate = rate
        self._t += h

    def _substep_realistic(self, h: float) -> None:
        ctl = self.controller
        p_est = self._p + self.estimate_offset_m
        if self._traj is None:
            if self._hold is None:
                self._hold = p_est.copy()
            p_r, v_r, a_r, yaw_r, yaw_rate_r = self._hold, np.zeros(3), np.zeros(3), self._yaw, 0.0
        else:
            p_r, v_r, a_r, yaw_r, yaw_rate_r = self._reference(h)
        v_sp = v_r + ctl.k_pos * (p_r - p_est)
        e_v = v_sp - self._v
        self._vel_integral = self._vel_integral + e_v * h
        a_sp = _clip_norm(a_r + ctl.k_vel * e_v + ctl.k_int * self._vel_integral, ctl.accel_limit_mps2)
        lag = 1.0 - math.exp(-h / ctl.tau_s) if ctl.tau_s > 0 else 1.0
        self._a_thrust = self._a_thrust + lag * (a_sp - self._a_thrust)
        a = self._a_thrust
        if self.gusts is not None:
            self.gusts.step(h)
            a = a + self.gusts.acceleration()
        self._advance(a, yaw_r, yaw_rate_r, h)

    def _substep(self, h: float) -> None:
        if self.controller is not None:
            self._substep_realistic(h)
            return
        c = self.config
        p_r, v_r, a_r, yaw_r, yaw_rate_r = self._reference(h)
        if self._traj is None:
            a = -c.kd_per_s * self._v
        else:
            # the position the autopilot reads: truth + the odometry's drift (0 when ideal)
            a = a_r + c.kp_per_s2 * (p_r - (self._p + self.estimate_offset_m)) + c.kd_per_s * (v_r - self._v)
        a = _clip_norm(a, c.a_max_mps2)
        v_next = self._v + a * h
        if np.linalg.norm(v_next) > c.v_max_mps:
            if np.linalg.norm(self._v) > c.v_max_mps:
                a = -self._v / np.linalg.norm(self._v) * c.a_max_mps2
            else:
                a = _clip_norm((_clip_norm(v_next, c.v_max_mps) - self._v) / h, c.a_max_mps2)
        self._advance(a, yaw_r, yaw_rate_r, h)

    def step(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance by ``dt_s`` seconds in fixed steps of ``config.step_s`` (a shorter last step
        if ``dt_s`` is not a multiple; still exact under the held acceleration).

        Returns
        -------
        times_s (k,), positions (k, 3) metres ENU at the end of each internal step, so a
        collision checker can test the whole swept path.
        """
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise VehicleError(f"dt_s must be positive and finite, got {dt_s}")
        h = self.config.step_s
        n_full = int(math.floor(dt_s / h + 1e-9))
        rest = dt_s - n_full * h
        steps = [h] * n_full + ([rest] if rest > 1e-9 else [])
        times = np.empty(len(steps))
        pos = np.empty((len(steps), 3))
        for i, hh in enumerate(steps):
            self._substep(hh)
            times[i] = self._t
            pos[i] = self._p
        return times, pos
