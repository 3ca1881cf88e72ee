"""Exact collision checks of a spherical body against the scene's triangles.

The body collides when the distance from its centre to the nearest triangle is below its
radius (``distance < radius``; touching at exactly the radius is not a collision). The
distance is exact for the meshes (Open3D closest-point query on the triangles, float32
geometry). A body centre can only get inside a closed object by first passing within the
radius of its surface, so checking every integration step of the vehicle (it moves at most
``v_max * step_s`` = 6 mm per step at the defaults, far below the radius) never misses an
entry.

Actors (people walking, :mod:`onfly.world.actors`) are checked exactly at their pose at the
instant of each point: the point is moved into the actor's frame at that time and the distance
to the actor's own mesh is taken. An actor walks at most ~1.4 m/s, so between two vehicle
integration steps the relative motion stays a few millimetres, and the same argument holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onfly.world.geometry import SceneGeometry

__all__ = ["Collision", "CollisionChecker"]


@dataclass(frozen=True, eq=False)
class Collision:
    """Where and with what the body collided.

    t_s : time of the first colliding position, seconds
    position_m : (3,), body centre, world ENU
    point_m : (3,), closest point on the obstacle surface
    distance_m : centre-to-surface distance (< body radius)
    instance_id : the object hit; object_name : its name
    """

    t_s: float
    position_m: np.ndarray
    point_m: np.ndarray
    distance_m: float
    instance_id: int
    object_name: str


class CollisionChecker:
    """Distance queries and collision tests for a body of radius ``body_radius_m``."""

    def __init__(self, geometry: SceneGeometry, body_radius_m: float = 0.25) -> None:
        if not (np.isfinite(body_radius_m) and body_radius_m > 0):
            raise ValueError(f"body_radius_m must be positive, got {body_radius_m}")
        self.geometry = geometry
        self.body_radius_m = float(body_radius_m)
        self._names = {o.instance_id: o.name for o in geometry.scene.objects}

    def clearance(self, points, times_s=None) -> np.ndarray:
        """Distance (n,) in metres from each point (n, 3) to the nearest triangle; with
        ``times_s`` (scalar or (n,), world clock) the actors count at their poses then, without
        it only the static scene counts."""
        return self.geometry.closest(points, t_s=times_s)[0]

    def first_collision(self, points, times_s=None) -> Collision | None:
        """The first of ``points`` (n, 3) (a swept path, in time order) that collides, or None.

        ``times_s`` (n,) are the world-clock times of the points: each actor is checked at its
        pose at each point's time. Without ``times_s`` the points are labelled ``0..n-1`` and
        only the static scene is checked; a scene with actors then raises ValueError.
        """
        P = np.atleast_2d(np.asarray(points, dtype=float))
        t = np.arange(len(P), dtype=float) if times_s is None else np.asarray(times_s, dtype=float).reshape(-1)
        if t.shape[0] != P.shape[0]:
            raise ValueError(f"times_s has {t.shape[0]} entries for {P.shape[0]} points")
        if times_s is None and self.geometry.actors:
            raise ValueError(f"scene {self.geometry.scene.name!r} has actors: first_collision needs times_s")
        d, q, inst = self.geometry.closest(P, t_s=None if times_s is None else t)
        bad = np.flatnonzero(d < self.body_radius_m)
        if len(bad) == 0:
            return None
        i = int(bad[0])
        iid = int(inst[i])
        return Collision(float(t[i]), P[i].copy(), q[i].copy(), float(d[i]), iid, self._names.get(iid, ""))
