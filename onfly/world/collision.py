"""Exact collision checks of a spherical body against the scene's triangles.

The body collides when the distance from its centre to the nearest triangle is below its
radius (``distance < radius``; touching at exactly the radius is not a collision). The
distance is exact for the meshes (Open3D closest-point query on the triangles, float32
geometry). A body centre can only get inside a closed object by first passing within the
radius of its surface, so checking every integration step of the vehicle (it moves at most
``v_max * step_s`` = 6 mm per step at the defaults, far below the radius) never misses an
entry.
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

    def clearance(self, points) -> np.ndarray:
        """Distance (n,) in metres from each point (n, 3) to the nearest triangle."""
        return self.geometry.closest(points)[0]

    def first_collision(self, points, times_s=None) -> Collision | None:
        """The first of ``points`` (n, 3) (a swept path, in time order) that collides, or None.

        ``times_s`` (n,) labels them; default ``0..n-1``.
        """
        P = np.atleast_2d(np.asarray(points, dtype=float))
        t = np.arange(len(P), dtype=float) if times_s is None else np.asarray(times_s, dtype=float).reshape(-1)
        if t.shape[0] != P.shape[0]:
            raise ValueError(f"times_s has {t.shape[0]} entries for {P.shape[0]} points")
        d, q, inst = self.geometry.closest(P)
        bad = np.flatnonzero(d < self.body_radius_m)
        if len(bad) == 0:
            return None
        i = int(bad[0])
        iid = int(inst[i])
        return Collision(float(t[i]), P[i].copy(), q[i].copy(), float(d[i]), iid, self._names.get(iid, ""))
