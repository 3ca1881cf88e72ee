"""The embedded world behind :class:`~onfly.mavlink.sim_vehicle.SimMavlinkVehicle`.

:class:`WorldVehicleModel` gives the MAVLink vehicle the embedded world's dynamics
(:class:`onfly.world.vehicle.SimVehicle`: the benchmark's limits, 0.6 m/s, 0.6 m/s^2,
0.4 rad/s), its exact collision checks against the scene's meshes, and its camera
(:meth:`WorldVehicleModel.observe`, served to the companion by a
:class:`~onfly.mavlink.camera_channel.FrameServer`). It has the interface of
:class:`~onfly.mavlink.sim_vehicle.PointMassModel` (``p``, ``v``, ``a``, ``yaw``,
``yaw_rate``, ``on_ground``, ``step(dt, target, armed)``, ``R_enu_flu()``) plus ``crashed``.

Setpoints to trajectories
-------------------------
The world's vehicle tracks a :class:`~planning.trajectory.Trajectory`. Each new setpoint
(``p``, ``v``, ``a``, ``yaw``; any may be absent) becomes a short plan starting at the
vehicle's current time: with a position, ``p(tau) = p + v tau + a tau^2 / 2`` (absent terms
zero); velocity only, ``p(tau) = p_now + v tau`` (re-made from the current position every
half horizon while that setpoint stays, as a velocity command holds); a zero velocity alone
(BRAKE) clears the plan so the vehicle brakes to a hover. The plan spans ``target_horizon_s`` (1 s, PX4's
offboard loss timeout); the autopilot rules replace it long before it runs out.

Ground, takeoff, touchdown, crashes
-----------------------------------
The vehicle starts at rest on the ground (``ground_z_m``, default the first surface straight
below the start position, found by a ray cast) below the task's start pose: the companion takes off like on a real drone. The local frame
of the MAVLink telemetry *is* the scene's world frame (an EKF origin at the scene origin), so
the companion's map and the scene agree.

- On the ground it stays put until a plan pulls it up (armed, reference above the ground).
- Contacts with the ground surface itself (closest point at ``ground_z_m``) are not collisions
  (take-off and touchdown); any other contact below the body radius is: the vehicle stops
  there, :attr:`collision` records it, ``crashed`` becomes True (the MAVLink vehicle disarms).
- Descending to the ground is a touchdown: the vehicle rests there.
- Disarmed in the air (a forced disarm), it falls; reaching the ground is a crash.
- Leaving the scene bounds (after having been inside them) is recorded
  (:attr:`out_of_bounds_s`) but does not stop it.

Threads: the MAVLink vehicle steps the model from its physics thread (holding its lock); the
camera thread calls :meth:`observe`, which renders the newest state snapshot without that
lock. Open3D's ray-casting scene answers concurrent queries once built; it is built (and
queried once for rays and closest points) in the constructor, before any thread runs.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from onfly.observation import Observation
from onfly.world.collision import Collision
from onfly.world.vehicle import SimVehicle
from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.frames import wrap_angle
from planning.trajectory import Trajectory, VehicleState

__all__ = ["WorldModelConfig", "WorldVehicleModel", "trajectory_from_setpoint", "ground_below", "BENCHMARK_CAMERA"]

log = logging.getLogger(__name__)

#: The benchmark camera: 320 x 214 pixels, 90 x 60 degrees.
BENCHMARK_CAMERA = PinholeCamera.from_fov(320, 214, 90.0, 60.0)

_GRAVITY_MPS2 = 9.81


@dataclass(frozen=True)
class WorldModelConfig:
    """Options of :class:`WorldVehicleModel` (seconds, metres).

    target_horizon_s : span of the plan made from one setpoint
    target_dt_s : knot spacing of that plan
    ground_z_m : height of the ground the vehicle starts on (None: the surface below the start)
    liftoff_margin_m : on the ground, a plan must reach this far above it to lift off
    """

    target_horizon_s: float = 1.0
    target_dt_s: float = 0.1
    ground_z_m: float | None = None
    liftoff_margin_m: float = 0.02

    def __post_init__(self) -> None:
        for name in ("target_horizon_s", "target_dt_s", "liftoff_margin_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"WorldModelConfig.{name} must be positive, got {v}")
        if self.target_dt_s > self.target_horizon_s:
            raise ValueError("WorldModelConfig.target_dt_s must not exceed target_horizon_s")
        if self.ground_z_m is not None and not np.isfinite(self.ground_z_m):
            raise ValueError(f"WorldModelConfig.ground_z_m must be finite or None, got {self.ground_z_m}")


def trajectory_from_setpoint(
    t0_s: float,
    state: VehicleState,
    p: np.ndarray | None,
    v: np.ndarray | None,
    a: np.ndarray | None,
    yaw: float | None,
    horizon_s: float = 1.0,
    dt_s: float = 0.1,
) -> Trajectory | None:
    """The plan the world's vehicle tracks for one setpoint (see the module docstring).

    Parameters
    ----------
    t0_s : start of the plan on the vehicle's time, seconds
    state : the vehicle's current state (ENU)
    p, v, a : (3,) position (m), velocity (m/s), acceleration (m/s^2), ENU, or None if unused
    yaw : heading (rad, ENU) or None to keep the current one

    Returns a Trajectory of ``round(horizon_s / dt_s)`` intervals, or None to brake to a hover
    (no position and a zero or absent velocity).
    """
    n = max(1, int(round(horizon_s / dt_s)))
    tau = dt_s * np.arange(n + 1)[:, None]
    yaw_ref = float(state.yaw if yaw is None else yaw)
    yaw_knots = np.full(n + 1, state.yaw + wrap_angle(yaw_ref - state.yaw))
    if p is not None:
        v0 = np.zeros(3) if v is None else np.asarray(v, float)
        a0 = np.zeros(3) if a is None else np.asarray(a, float)
        P = np.asarray(p, float) + tau * v0 + 0.5 * tau**2 * a0
        V = v0 + tau * a0
        A = np.tile(a0, (n, 1))
    elif v is not None and np.linalg.norm(v) > 0:
        v0 = np.asarray(v, float)
        P = state.p + tau * v0
        V = np.tile(v0, (n + 1, 1))
        A = np.zeros((n, 3))
    else:
        return None
    return Trajectory(float(t0_s), float(dt_s), P, V, yaw_knots, A, np.zeros(n))


def ground_below(world: World, p_m) -> float:
    """Height (m) of the first surface straight below ``p_m`` (3,), world ENU.

    Raises ValueError when nothing is below (the vehicle would have nowhere to stand).
    """
    p = np.asarray(p_m, dtype=float).reshape(3)
    hit = world.geometry.cast(np.array([[p[0], p[1], p[2], 0.0, 0.0, -1.0]], dtype=np.float32))
    t = float(hit["t_hit"][0])
    if not np.isfinite(t):
        raise ValueError(f"no ground below ({p[0]:.2f}, {p[1]:.2f}, {p[2]:.2f}) in scene {world.scene.name!r}")
    return float(p[2] - t)


class WorldVehicleModel:
    """Dynamics, collisions and camera of the embedded world for the MAVLink vehicle.

    Parameters
    ----------
    world : a World whose vehicle is at rest on the ground (see :meth:`from_scene`)
    config : WorldModelConfig
    camera : the camera :meth:`observe` renders (default :data:`BENCHMARK_CAMERA`)

    Attributes
    ----------
    collision : the collision that ended the flight, or None
    out_of_bounds_s : vehicle time the body first left the scene bounds, or None
    events : ``(t_s, text)`` of touchdowns, lift-offs, collisions (vehicle time)
    """

    def __init__(self, world: World, config: WorldModelConfig = WorldModelConfig(), camera: PinholeCamera | None = None) -> None:
        self.world = world
        self.config = config
        self.camera = camera if camera is not None else BENCHMARK_CAMERA
        self.ground_z_m = float(world.state.p[2] if config.ground_z_m is None else config.ground_z_m)
        self.radius_m = world.vehicle.config.body_radius_m
        self._names = {o.instance_id: o.name for o in world.scene.objects}
        self._state = world.vehicle.state
        self._a = np.zeros(3)
        self._on_ground = self._state.p[2] <= self.ground_z_m + 1e-6
        self._been_inside = False
        self._last_target = None
        self._fall_v = None  # vertical speed while falling disarmed, m/s
        self._frame_index = 0
        self._frame_lock = threading.Lock()
        self.collision: Collision | None = None
        self.out_of_bounds_s: float | None = None
        self.events: list[tuple[float, str]] = []
        # Build Open3D's acceleration structures before any thread queries them.
        world.geometry.closest(self._state.p[None])
        world.renderer_for(self.camera)
        self.observe()
        self._frame_index = 0

    @classmethod
    def from_scene(
        cls,
        scene: str,
        *,
        position_m=None,
        yaw_rad: float | None = None,
        config: WorldModelConfig = WorldModelConfig(),
        camera: PinholeCamera | None = None,
    ) -> "WorldVehicleModel":
        """A model on the ground of a committed scene (or scene file) below ``position_m``
        (default: the scene's start), facing ``yaw_rad`` (default: the start's heading)."""
        probe = World.from_scene(scene, camera=camera or BENCHMARK_CAMERA)
        start = probe.scene.start
        p = np.array(start.position_m if position_m is None else position_m, dtype=float).reshape(3)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"position_m must be 3 finite numbers, got {position_m!r}")
        ground = config.ground_z_m
        if ground is None:
            ground = ground_below(probe, p)
            config = WorldModelConfig(config.target_horizon_s, config.target_dt_s, ground, config.liftoff_margin_m)
        p[2] = ground
        yaw = float(start.yaw_rad if yaw_rad is None else yaw_rad)
        probe.vehicle = SimVehicle(VehicleState(0.0, p, np.zeros(3), yaw), probe.vehicle.config)
        return cls(probe, config, camera)

    # -- the PointMassModel interface -------------------------------------------------------
    @property
    def p(self) -> np.ndarray:
        return self._state.p.copy()

    @property
    def v(self) -> np.ndarray:
        return self._state.v.copy()

    @property
    def a(self) -> np.ndarray:
        return self._a.copy()

    @property
    def yaw(self) -> float:
        return float(self._state.yaw)

    def controller_setpoint(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The velocity (m/s) and acceleration (m/s^2), ENU, of the plan the world's vehicle
        follows at this instant (what its controller tracks; the MAVLink vehicle reports them as
        PX4 reports its ``_vel_sp`` and ``_acc_sp``), or None with no plan (disarmed, landed,
        crashed)."""
        traj = self.world.vehicle.trajectory
        if self.crashed or self._on_ground or traj is None:
            return None
        _, v, a, _, _ = traj.sample(float(self._state.t_s))
        return np.asarray(v, float).copy(), np.asarray(a, float).copy()

    @property
    def yaw_rate(self) -> float:
        return float(self._state.yaw_rate)

    @property
    def on_ground(self) -> bool:
        return self._on_ground

    @property
    def crashed(self) -> bool:
        return self.collision is not None

    @property
    def state(self) -> VehicleState:
        """Newest state snapshot (vehicle time)."""
        return self._state

    def R_enu_flu(self) -> np.ndarray:
        """Body attitude (3, 3): thrust along ``a + g z``, heading ``yaw`` (as the point mass)."""
        thrust = self._a + np.array([0.0, 0.0, _GRAVITY_MPS2])
        z_b = thrust / max(np.linalg.norm(thrust), 1e-6)
        x_c = np.array([np.cos(self.yaw), np.sin(self.yaw), 0.0])
        y_b = np.cross(z_b, x_c)
        y_b /= max(np.linalg.norm(y_b), 1e-9)
        return np.column_stack([np.cross(y_b, z_b), y_b, z_b])

    def step(self, dt_s: float, target, armed: bool) -> None:
        """Advance ``dt_s`` seconds toward ``target`` (a setpoint with ``p``, ``v``, ``a``,
        ``yaw`` attributes, any None; None = hover in place)."""
        if self.crashed:
            return
        vehicle = self.world.vehicle
        s = self._state
        if not armed:
            if not self._on_ground:
                self._fall(dt_s)
            else:
                self._rest(s.t_s + dt_s, s.p, s.yaw)
            return
        refresh = (
            target is not None
            and getattr(target, "p", None) is None
            and vehicle.trajectory is not None
            and s.t_s >= vehicle.trajectory.t0_s + 0.5 * vehicle.trajectory.duration_s
        )  # a velocity-only setpoint holds until replaced: keep extending its plan
        if target is not self._last_target or refresh:
            self._last_target = target
            traj = None
            if target is not None:
                traj = trajectory_from_setpoint(
                    s.t_s, s, target.p, target.v, target.a, target.yaw, self.config.target_horizon_s, self.config.target_dt_s
                )
            elif not self._on_ground:
                traj = trajectory_from_setpoint(s.t_s, s, s.p, None, None, s.yaw, self.config.target_horizon_s, self.config.target_dt_s)
            vehicle.set_trajectory(traj)
        if self._on_ground and not self._lifting(vehicle.trajectory, s.t_s):
            self._rest(s.t_s + dt_s, s.p, s.yaw)
            return
        if self._on_ground:
            self._on_ground = False
            self._log(s.t_s, "lift-off")
        v_before = s.v.copy()
        times, pos = vehicle.step(dt_s)
        new = vehicle.state
        if self._check_contacts(times, pos):
            return
        if new.p[2] <= self.ground_z_m:
            self._log(new.t_s, f"touchdown at ({new.p[0]:.2f}, {new.p[1]:.2f})")
            self._rest(new.t_s, new.p, new.yaw)
            return
        self._a = (new.v - v_before) / dt_s
        self._state = new
        self._check_bounds(new)

    # -- camera -----------------------------------------------------------------------------
    def observe(self) -> Observation:
        """Render the newest state with the model's camera (thread-safe against :meth:`step`).

        ``t_s`` is the vehicle time of the state; ``annotation`` is the world's ground truth
        for the simulated VLM.
        """
        s = self._state
        renderer = self.world.renderer_for(self.camera)
        with self._frame_lock:
            index = self._frame_index
            self._frame_index += 1
        r = renderer.render(self.world.T_world_cam(s), noise_key=index, t_s=float(s.t_s))
        return Observation(
            t_s=float(s.t_s),
            rgb=r.rgb,
            depth_m=r.depth_m,
            T_world_cam=r.T_world_cam,
            camera=renderer.camera,
            frame_id=f"{self.world.scene.name}/{index:06d}",
            T_body_cam=self.world.T_body_cam,
            annotation=renderer.annotate(r),
        )

    # -- internals --------------------------------------------------------------------------
    def _log(self, t_s: float, text: str) -> None:
        self.events.append((float(t_s), text))
        log.info("world vehicle t=%.2f: %s", t_s, text)

    def _lifting(self, traj: Trajectory | None, t_s: float) -> bool:
        if traj is None:
            return False
        p_ref = traj.sample(t_s + self.config.target_horizon_s)[0]
        return bool(p_ref[2] > self.ground_z_m + self.config.liftoff_margin_m)

    def _rest(self, t_s: float, p, yaw: float) -> None:
        """Sit on the ground at ``p`` (z clamped to the ground), at rest."""
        p = np.array(p, dtype=float)
        p[2] = self.ground_z_m
        self._on_ground = True
        self._fall_v = None
        self._a = np.zeros(3)
        vehicle = self.world.vehicle
        traj = vehicle.trajectory
        self.world.vehicle = SimVehicle(VehicleState(t_s, p, np.zeros(3), yaw), vehicle.config)
        self.world.vehicle.set_trajectory(traj)
        self._state = self.world.vehicle.state

    def _fall(self, dt_s: float) -> None:
        s = self._state
        vz = (s.v[2] if self._fall_v is None else self._fall_v) - _GRAVITY_MPS2 * dt_s
        self._fall_v = vz
        p = s.p + np.array([s.v[0], s.v[1], vz]) * dt_s
        t = s.t_s + dt_s
        if p[2] <= self.ground_z_m:
            p[2] = self.ground_z_m
            self._crash(Collision(t, p, np.array([p[0], p[1], self.ground_z_m]), 0.0, 0, "ground (fell disarmed)"), p)
            return
        self._state = VehicleState(t, p, np.array([s.v[0], s.v[1], vz]), s.yaw)

    def _check_contacts(self, times: np.ndarray, pos: np.ndarray) -> bool:
        d, q, inst = self.world.geometry.closest(pos, t_s=times)  # actors at their poses then
        ground = q[:, 2] <= self.ground_z_m + 1e-3
        bad = np.flatnonzero((d < self.radius_m) & ~ground)
        if len(bad) == 0:
            return False
        i = int(bad[0])
        iid = int(inst[i])
        self._crash(Collision(float(times[i]), pos[i].copy(), q[i].copy(), float(d[i]), iid, self._names.get(iid, "")), pos[i])
        return True

    def _crash(self, hit: Collision, p) -> None:
        self.collision = hit
        self._a = np.zeros(3)
        self._state = VehicleState(hit.t_s, np.asarray(p, float), np.zeros(3), self._state.yaw)
        self._log(hit.t_s, f"collision with {hit.object_name!r} at ({hit.position_m[0]:.2f}, {hit.position_m[1]:.2f}, {hit.position_m[2]:.2f})")

    def _check_bounds(self, s: VehicleState) -> None:
        inside = bool(self.world.scene.bounds.contains(s.p[None])[0])
        self._been_inside = self._been_inside or inside
        if self.out_of_bounds_s is None and self._been_inside and not inside:
            self.out_of_bounds_s = float(s.t_s)
            self._log(s.t_s, "left the scene bounds")

    def summary(self) -> dict:
        """Ground truth for run summaries (JSON-able)."""
        c = self.collision
        return {
            "scene": self.world.scene.name,
            "position_m": self._state.p.tolist(),
            "collision": None
            if c is None
            else {"t_s": c.t_s, "object": c.object_name, "position_m": np.asarray(c.position_m).tolist(), "distance_m": c.distance_m},
            "out_of_bounds_s": self.out_of_bounds_s,
            "frames_rendered": self._frame_index,
            "events": [{"t_s": t, "text": e} for t, e in self.events],
        }
