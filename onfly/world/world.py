"""The embedded world: one scene, its renderer and collision checker, a vehicle and a clock.

:class:`World` only wires the parts together and keeps them in step; each part lives in its
own module. One :meth:`World.step` advances the vehicle and the clock by the same ``dt_s``,
checks the swept path for collisions and returns the VLM calls that completed. The episode
ends at the first collision: the vehicle stops there and further steps raise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from onfly.observation import Observation
from onfly.world.clock import LatencyModel, PendingCall, SimClock
from onfly.world.collision import Collision, CollisionChecker
from onfly.world.geometry import SceneGeometry
from onfly.world.render import RenderConfig, Renderer, RenderResult
from onfly.world.scene import Scene, load_scene, resolve_scene
from onfly.world.vehicle import SimVehicle, VehicleConfig
from planning.camera import PinholeCamera
from planning.frames import T_BODY_CAM, body_transform, cam_transform_from_body
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
    ) -> None:
        self.scene = scene
        self.geometry = SceneGeometry(scene)
        self.renderer = Renderer(self.geometry, camera, render_config)
        vehicle_config = vehicle_config if vehicle_config is not None else VehicleConfig()
        self.collision = CollisionChecker(self.geometry, vehicle_config.body_radius_m)
        if initial_state is None:
            initial_state = VehicleState(0.0, scene.start.position_m, np.zeros(3), scene.start.yaw_rad)
        self.vehicle = SimVehicle(initial_state, vehicle_config)
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
        return self.vehicle.state

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
        times, pos = self.vehicle.step(dt_s)
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
        """Render the current view (advances the frame counter that keys depth noise)."""
        result = self.renderer_for(camera).render(self.T_world_cam(), noise_key=self._frame_index)
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
        return Observation(
            t_s=self.clock.now_s,
            rgb=r.rgb,
            depth_m=r.depth_m,
            T_world_cam=r.T_world_cam,
            camera=renderer.camera,
            frame_id=f"{self.scene.name}/{index:06d}",
            T_body_cam=self.T_body_cam,
            annotation=renderer.annotate(r),
        )
