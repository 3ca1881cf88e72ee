"""The embedded world: scenes as data, CPU ray-cast RGB-D + semantics, vehicle, collisions, clock.

See ``docs/scene_format.md`` for the scene files, ``docs/realism.md`` for the realism profiles
(``ideal``, ``realistic``, ``realistic_calm``) and ``DESIGN.md`` ("The embedded world").
"""

from onfly.world.actors import ActorPose, CircleMotion, Motion, MotionFormatError, PathMotion, Waypoint, parse_motion, pose_at, positions_at
from onfly.world.clock import DECISION, MONITORING, LatencyModel, PendingCall, SimClock
from onfly.world.collision import Collision, CollisionChecker
from onfly.world.geometry import SceneGeometry
from onfly.world.realism import PROFILES, RealismError, RealismProfile, realism_profile
from onfly.world.render import DepthNoise, RenderConfig, Renderer, RenderResult, default_camera
from onfly.world.scene import Scene, SceneFormatError, SceneObject, list_scenes, load_scene, resolve_scene
from onfly.world.vehicle import SimVehicle, VehicleConfig
from onfly.world.world import EpisodeEndedError, World, WorldStep

__all__ = [
    "ActorPose",
    "CircleMotion",
    "Motion",
    "MotionFormatError",
    "PathMotion",
    "Waypoint",
    "parse_motion",
    "pose_at",
    "positions_at",
    "DECISION",
    "MONITORING",
    "Collision",
    "CollisionChecker",
    "DepthNoise",
    "EpisodeEndedError",
    "LatencyModel",
    "PROFILES",
    "PendingCall",
    "RealismError",
    "RealismProfile",
    "RenderConfig",
    "RenderResult",
    "Renderer",
    "Scene",
    "SceneFormatError",
    "SceneGeometry",
    "SceneObject",
    "SimClock",
    "SimVehicle",
    "VehicleConfig",
    "World",
    "WorldStep",
    "default_camera",
    "list_scenes",
    "realism_profile",
    "load_scene",
    "resolve_scene",
]
