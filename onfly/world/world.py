"""The embedded world: one scene, its renderer and collision checker, a vehicle and a clock.

:class:`World` only wires the parts together and keeps them in step; each part lives in its
own module. One :meth:`World.step` advances the vehicle and the clock by the same ``dt_s``,
checks the swept path for collisions and returns the VLM calls that completed. The episode
ends at the first collision: the vehicle stops there and further steps raise.

A realism profile (:mod:`onfly.world.realism`, ``realism=`` and the episode ``seed``) adds a
depth sensor model, odometry drift and noise, PX4-like tracking with gusts, and frame drops
and latency. Truth and estimate are kept apart: :attr:`World.state`, the collision check, the
out-of-bounds check and the rendered view use the true pose; what a pilot reads
(:attr:`World.estimate`, the ``T_world_cam`` of each :class:`Observation`) is the odometry's
estimate. Under ``ideal`` the estimate *is* the truth and every frame arrives at once, so the
world behaves exactly as before profiles existed.

Actors (objects with a motion, :mod:`onfly.world.actors`) move on the world clock: the view is
rendered and the swept path is checked with every actor at its pose at that instant
(:meth:`World.actor_pose`). The pilot never reads actor poses; they are ground truth for the
world, the metrics and privileged oracles.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from onfly.observation import Observation
from onfly.world.actors import ActorPose
from onfly.world.clock import LatencyModel, PendingCall, SimClock
from onfly.world.collision import Collision, CollisionChecker
from onfly.world.geometry import SceneGeometry
from onfly.world.realism import GustProcess, OdometryDrift, RealismProfile, realism_profile
from onfly.world.render import RenderConfig, Renderer, RenderResult
from onfly.world.scene import Scene, load_scene, resolve_scene
from onfly.world.vehicle import SimVehicle, VehicleConfig
from planning.camera import PinholeCamera
from planning.frames import T_BODY_CAM, body_transform, cam_transform_from_body, wrap_angle
from planning.trajectory import Trajectory, VehicleState

__all__ = ["World", "WorldStep", "EpisodeEndedError"]


class EpisodeEndedError(RuntimeError):
    """The world was stepped after the episode ended in a collision."""


@dataclass(frozen=True, eq=False)
class WorldStep:
    """Outcome of one :meth:`World.step`.

    state : vehicle state at the end of the step
    collision : the first collision on the swept path, or None
    out_of_bounds : True if the body centre left the scene bounds during the step
    completed : VLM calls whose results were delivered in this step
    """

    state: VehicleState
    collision: Collision | None
    out_of_bounds: bool
    completed: tuple[PendingCall, ...]


class World:
    """A flyable scene.

    Parameters
    ----------
    scene : Scene (see :meth:`from_scene` to load one by name or path)
    camera : PinholeCamera, default 640 x 427, 90 x 60 deg
    render_config, vehicle_config, latency : configs of the parts
    initial_state : default: the scene's start pose at rest at t = 0
    T_body_cam : camera mount, default forward and level
    realism : RealismProfile or its name (default ``"ideal"``)
    seed : int, seeds every draw of the realism models (the episode seed)
    """

    def __init__(
        self,
        scene: Scene,
        *,
        camera: PinholeCamera | None = None,
        render_config: RenderConfig | None = None,
        vehicle_config: VehicleConfig | None = None,
        latency: LatencyModel | None = None,
        initial_state: VehicleState | None = None,
        T_body_cam: np.ndarray = T_BODY_CAM,
        realism: RealismProfile | str | None = None,
        seed: int = 0,
    ) -> None:
        self.scene = scene
        self.realism = realism_profile(realism)
        self.seed = int(seed)
        self.geometry = SceneGeometry(scene)
        if self.realism.depth is not None:
            render_config = replace(render_config if render_config is not None else RenderConfig(),
                                    sensor=self.realism.depth, sensor_seed=self.seed)
        self.renderer = Renderer(self.geometry, camera, render_config)
        vehicle_config = vehicle_config if vehicle_config is not None else VehicleConfig()
        self.collision = CollisionChecker(self.geometry, vehicle_config.body_radius_m)
        if initial_state is None:
            initial_state = VehicleState(0.0, scene.start.position_m, np.zeros(3), scene.start.yaw_rad)
        gusts = None
        if self.realism.wind is not None and not scene.indoor:
            gusts = GustProcess(self.realism.wind, self.seed)
        self.vehicle = SimVehicle(initial_state, vehicle_config, controller=self.realism.controller, gusts=gusts)
        self.odometry = None if self.realism.odometry is None else OdometryDrift(self.realism.odometry, self.seed, initial_state.p)
        self._step_index = 0
        self._frames: list[tuple[float, Observation]] = []
        self.frames_dropped = 0
        self.clock = SimClock(initial_state.t_s, latency)
        self.T_body_cam = np.asarray(T_body_cam, dtype=float)
        self._renderers: dict[PinholeCamera, Renderer] = {}
        self._frame_index = 0
        self._collision: Collision | None = None

    @classmethod
    def from_scene(cls, name_or_path: str | Path, **kwargs) -> "World":
        """World of a committed scene (by name) or a scene file (by path)."""
        return cls(load_scene(resolve_scene(name_or_path)), **kwargs)

    @property
    def camera(self) -> PinholeCamera:
        return self.renderer.camera

    @property
    def state(self) -> VehicleState:
        """The true vehicle state (collisions, metrics, bounds)."""
        return self.vehicle.state

    @property
    def estimate(self) -> VehicleState:
        """The vehicle state a pilot reads: the truth plus the odometry's drift and noise (the
        noise is drawn once per control step, so repeated reads agree). Ideal: the truth."""
        s = self.vehicle.state
        if self.odometry is None:
            return s
        dp, dyaw = self.odometry.noise(self._step_index)
        return VehicleState(s.t_s, s.p + self.odometry.offset_m + dp, s.v, wrap_angle(s.yaw + dyaw), s.yaw_rate, s.a)

    @property
    def actor_ids(self) -> tuple[int, ...]:
        """Instance ids of the actors (objects with a motion), in scene order."""
        return tuple(a.instance_id for a in self.geometry.actors)

    def actor_pose(self, actor: int | str, t_s: float | None = None) -> ActorPose:
        """The true pose of an actor at ``t_s`` (default: now on the world clock).

        ``actor`` is its instance id or its name. Raises KeyError naming the actors when it is
        not one (a static object or no object)."""
        iid = actor
        if isinstance(actor, str):
            try:
                iid = self.scene.object_by_name(actor).instance_id
            except KeyError:
                iid = None
        if iid is None or int(iid) not in self.actor_ids:
            names = ", ".join(repr(a.obj.name) for a in self.geometry.actors) or "(none)"
            raise KeyError(f"{actor!r} is not an actor of scene {self.scene.name!r}; actors: {names}")
        return self.geometry.actor(int(iid)).pose(self.clock.now_s if t_s is None else float(t_s))

    def actor_poses(self, t_s: float | None = None) -> dict[int, ActorPose]:
        """Every actor's true pose at ``t_s`` (default: now): instance id -> ActorPose."""
        t = self.clock.now_s if t_s is None else float(t_s)
        return {a.instance_id: a.pose(t) for a in self.geometry.actors}

    @property
    def collided(self) -> Collision | None:
        """The collision that ended the episode, or None."""
        return self._collision

    def set_trajectory(self, trajectory: Trajectory | None) -> None:
        """Hand the vehicle a new plan (None: brake to hover)."""
        self.vehicle.set_trajectory(trajectory)

    def step(self, dt_s: float) -> WorldStep:
        """Advance vehicle and clock by ``dt_s`` seconds; check the swept path."""
        if self._collision is not None:
            raise EpisodeEndedError(f"episode ended by a collision with {self._collision.object_name!r} at t = {self._collision.t_s:.2f} s")
        if self.odometry is not None:
            self.vehicle.estimate_offset_m = self.odometry.offset_m
        times, pos = self.vehicle.step(dt_s)
        if self.odometry is not None:
            self.odometry.advance(pos)
        self._step_index += 1
        completed = tuple(self.clock.advance(dt_s))
        hit = self.collision.first_collision(pos, times)
        if hit is not None:
            self._collision = hit
        out = not bool(np.all(self.scene.bounds.contains(pos)))
        return WorldStep(self.vehicle.state, hit, out, completed)

    def T_world_cam(self, state: VehicleState | None = None) -> np.ndarray:
        """Camera pose (4, 4) of the vehicle (level body: yaw only)."""
        s = self.vehicle.state if state is None else state
        return cam_transform_from_body(body_transform(s.p, s.yaw), self.T_body_cam)

    def renderer_for(self, camera: PinholeCamera | None = None) -> Renderer:
        """The renderer of ``camera`` (default: the world's camera). Renderers of other cameras
        (e.g. ``world.camera.scaled(0.5)`` for cheap depth frames) share the scene geometry and
        are built once each."""
        if camera is None or camera == self.renderer.camera:
            return self.renderer
        r = self._renderers.get(camera)
        if r is None:
            r = self._renderers[camera] = Renderer(self.geometry, camera, self.renderer.config)
        return r

    def render(self, camera: PinholeCamera | None = None) -> RenderResult:
        """Render the current view, actors at their poses now (advances the frame counter that
        keys depth noise)."""
        result = self.renderer_for(camera).render(self.T_world_cam(), noise_key=self._frame_index, t_s=self.clock.now_s)
        self._frame_index += 1
        return result

    def observe(self, camera: PinholeCamera | None = None) -> Observation:
        """Render the current view as an Observation with its ground-truth annotation.

        ``camera`` (optional) renders at other intrinsics, e.g. a lower resolution; render cost
        is proportional to the pixel count.
        """
        index = self._frame_index
        renderer = self.renderer_for(camera)
        r = self.render(renderer.camera)
        T_world_cam = r.T_world_cam if self.odometry is None else self.T_world_cam(self.estimate)
        return Observation(
            t_s=self.clock.now_s,
            rgb=r.rgb,
            depth_m=r.depth_m,
            T_world_cam=T_world_cam,
            camera=renderer.camera,
            frame_id=f"{self.scene.name}/{index:06d}",
            T_body_cam=self.T_body_cam,
            annotation=self._annotate_motion(renderer.annotate(r)),
        )

    def _annotate_motion(self, ann):
        """Mark the visible actors that are moving now (``VisibleObject.moving``: what the
        simulated VLM sees of a walking person; ``vlm.sim.error_model``, Following)."""
        moving = {iid for iid in self.actor_ids if iid in ann.objects and self.actor_pose(iid).moving}
        if not moving:
            return ann
        objects = {i: (replace(o, moving=True) if i in moving else o) for i, o in ann.objects.items()}
        return replace(ann, objects=objects)

    # -- frame delivery (drops and latency of a realism profile) ---------------------------------

    def capture(self, camera: PinholeCamera | None = None) -> None:
        """Capture a camera frame now; it reaches :meth:`receive` after the profile's latency,
        or never if dropped (ideal: at once, always). The frame keeps its capture time and the
        estimated camera pose at capture."""
        frames = self.realism.frames
        if frames is None:
            self._frames.append((self.clock.now_s, self.observe(camera)))
            return
        dropped, latency_s = frames.draw(self.seed, self._frame_index)
        if dropped:
            self._frame_index += 1  # the frame's key is spent: later frames keep their draws
            self.frames_dropped += 1
            return
        self._frames.append((self.clock.now_s + latency_s, self.observe(camera)))

    def receive(self) -> Observation | None:
        """The newest captured frame delivered by now (older ready ones are superseded), or None."""
        now = self.clock.now_s + 1e-9
        ready = [f for f in self._frames if f[0] <= now]
        if not ready:
            return None
        self._frames = [f for f in self._frames if f[0] > now]
        return ready[-1][1]
