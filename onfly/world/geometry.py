"""A scene compiled once into Open3D ``RaycastingScene`` structures with per-triangle tables.

The renderer and the collision checker share one :class:`SceneGeometry`. All parts of all
*static* objects are merged into a single triangle mesh in the world frame, and every triangle
carries its object's instance id, semantic label id, colour and texture. Each *actor* (an
object with a motion, :mod:`onfly.world.actors`) gets its own small mesh and ray-casting
structure in its own frame, built once: rendering and collision queries transform rays and
points into the actor frame at the actor's pose instead of rebuilding anything. Ray hits and
closest-point queries return triangle indices, which index these tables directly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from onfly.world.actors import ActorPose, pose_at, poses_at
from onfly.world.primitives import mesh_arrays, shape_mesh
from onfly.world.scene import MATERIALS, TEXTURE_PATTERNS, Scene, SceneObject

__all__ = ["SceneGeometry", "ActorGeometry", "TEXTURE_NONE"]

log = logging.getLogger(__name__)

#: Texture code of untextured triangles; patterns are 1 + their index in TEXTURE_PATTERNS.
TEXTURE_NONE = 0


def _compile(objects, label_ids: dict[str, int]) -> dict[str, np.ndarray]:
    """Triangle soup and per-triangle tables of ``objects`` (their parts as written)."""
    V_all, F_all = [], []
    inst, lab, col, tex, tex_p, mat = [], [], [], [], [], []
    offset = 0
    for obj in objects:
        code = TEXTURE_NONE
        params = np.zeros(6, dtype=np.float32)
        if obj.texture is not None:
            code = 1 + TEXTURE_PATTERNS.index(obj.texture.pattern)
            params = np.array([obj.texture.period_m, obj.texture.contrast, *obj.texture.axis, obj.texture.seed], dtype=np.float32)
        for part in obj.parts:
            V, F = mesh_arrays(shape_mesh(part.shape))
            m = len(F)
            V_all.append(V)
            F_all.append(F + offset)
            offset += len(V)
            color = obj.color if part.color is None else part.color
            inst.append(np.full(m, obj.instance_id, np.int32))
            lab.append(np.full(m, label_ids[obj.label], np.int32))
            col.append(np.tile(np.asarray(color, np.float32) / 255.0, (m, 1)))
            tex.append(np.full(m, code, np.int8))
            tex_p.append(np.tile(params, (m, 1)))
            mat.append(np.full(m, MATERIALS.index(obj.part_material(part)), np.uint8))
    if not V_all:
        z3 = np.zeros((0, 3))
        return {
            "vertices": z3.astype(np.float32), "triangles": np.zeros((0, 3), np.uint32),
            "tri_instance": np.zeros(0, np.int32), "tri_label": np.zeros(0, np.int32),
            "tri_color": z3.astype(np.float32), "tri_texture": np.zeros(0, np.int8),
            "tri_tex_params": np.zeros((0, 6), np.float32), "tri_material": np.zeros(0, np.uint8),
            "tri_normal": z3.astype(np.float32), "tri_v0": z3.astype(np.float32),
        }
    out = {
        "vertices": np.vstack(V_all).astype(np.float32),
        "triangles": np.vstack(F_all).astype(np.uint32),
        "tri_instance": np.concatenate(inst),
        "tri_label": np.concatenate(lab),
        "tri_color": np.vstack(col).astype(np.float32),
        "tri_texture": np.concatenate(tex),
        "tri_tex_params": np.vstack(tex_p).astype(np.float32),
        "tri_material": np.concatenate(mat),
    }
    Vf, Ff = out["vertices"], out["triangles"]
    v0, v1, v2 = (Vf[Ff[:, k]] for k in range(3))
    n = np.cross(v1 - v0, v2 - v0)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    out["tri_normal"] = np.where(norm > 0, n / np.where(norm > 0, norm, 1.0), 0.0).astype(np.float32)
    out["tri_v0"] = v0.astype(np.float32)
    return out


def _raycasting(vertices: np.ndarray, triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    rc = o3d.t.geometry.RaycastingScene()
    if len(triangles):
        rc.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
    return rc


@dataclass(frozen=True, eq=False)
class ActorGeometry:
    """One actor's mesh in its own frame and its ray-casting structure (built once).

    obj : the SceneObject (``obj.motion`` is not None)
    vertices : float32 (n, 3), metres, actor frame (x forward, z up, origin on the ground)
    triangles : uint32 (m, 3)
    tri_offset : index of this actor's first triangle in the renderer's combined tables
        (static triangles first, then the actors in scene order)
    center_local_m : (3,) centre of the mesh's bounding box in the actor frame
    radius_m : distance from ``center_local_m`` to the farthest vertex (a bounding sphere)
    raycasting : open3d.t.geometry.RaycastingScene over ``vertices``, ``triangles``
    tables : per-triangle tables as :class:`SceneGeometry` has them (``tri_normal``, ``tri_v0``
        in the actor frame)
    """

    obj: SceneObject
    vertices: np.ndarray
    triangles: np.ndarray
    tri_offset: int
    center_local_m: np.ndarray
    radius_m: float
    raycasting: o3d.t.geometry.RaycastingScene
    tables: dict

    @property
    def instance_id(self) -> int:
        return self.obj.instance_id

    def pose(self, t_s: float) -> ActorPose:
        """The actor's pose at ``t_s`` (world clock), see :func:`onfly.world.actors.pose_at`."""
        return pose_at(self.obj.motion, t_s)

    def bounding_sphere(self, t_s: float) -> tuple[np.ndarray, float]:
        """World centre (3,) and radius (m) of a sphere holding the actor at ``t_s``."""
        T = self.pose(t_s).T_world_actor
        return T[:3, :3] @ self.center_local_m + T[:3, 3], self.radius_m

    def local_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (min (3,), max (3,)) of the mesh in the actor frame, metres."""
        return self.vertices.min(axis=0).astype(float), self.vertices.max(axis=0).astype(float)

    def world_vertices(self, t_s: float) -> np.ndarray:
        """Vertices (n, 3) float64, world ENU, at the actor's pose at ``t_s``."""
        T = self.pose(t_s).T_world_actor
        return self.vertices.astype(float) @ T[:3, :3].T + T[:3, 3]


class SceneGeometry:
    """Triangle soup of a scene and the ray-casting structures built over it (once).

    The attributes below describe the *static* objects only (world frame); the actors are in
    :attr:`actors`, each in its own frame.

    Attributes
    ----------
    scene : the Scene
    vertices : float32 (n, 3), metres, world ENU
    triangles : uint32 (m, 3)
    tri_instance : int32 (m,), instance id of each triangle
    tri_label : int32 (m,), semantic label id (``scene.label_ids``)
    tri_color : float32 (m, 3), RGB in [0, 1]
    tri_texture : int8 (m,), 0 none, else 1 + index in TEXTURE_PATTERNS
    tri_tex_params : float32 (m, 6): period_m, contrast, axis (3), seed
    tri_material : uint8 (m,), index in ``onfly.world.scene.MATERIALS`` (0 = opaque)
    tri_normal : float32 (m, 3), unit face normals (right-hand rule on the vertex order)
    tri_v0 : float32 (m, 3), first vertex of each triangle, metres
    raycasting : open3d.t.geometry.RaycastingScene of the static triangles
    actors : tuple of :class:`ActorGeometry`, in scene order
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        label_ids = scene.label_ids
        static = _compile(scene.static_objects, label_ids)
        for k, v in static.items():
            setattr(self, k, v)
        self.raycasting = _raycasting(self.vertices, self.triangles)
        actors = []
        offset = len(self.triangles)
        for obj in scene.actors:
            t = _compile([obj], label_ids)
            V = t["vertices"].astype(float)
            centre = (V.min(axis=0) + V.max(axis=0)) / 2
            radius = float(np.linalg.norm(V - centre, axis=1).max()) + 1e-3
            actors.append(ActorGeometry(obj, t["vertices"], t["triangles"], offset, centre, radius, _raycasting(t["vertices"], t["triangles"]), t))
            offset += len(t["triangles"])
        self.actors: tuple[ActorGeometry, ...] = tuple(actors)
        self._actor_by_id = {a.instance_id: a for a in self.actors}
        log.debug("scene %s: %d objects (%d actors), %d triangles", scene.name, len(scene.objects), len(self.actors), offset)

    @property
    def triangle_count(self) -> int:
        """Triangles of the static objects."""
        return int(len(self.triangles))

    @property
    def total_triangle_count(self) -> int:
        """Triangles of the static objects and of every actor."""
        return self.triangle_count + sum(len(a.triangles) for a in self.actors)

    def actor(self, instance_id: int) -> ActorGeometry:
        """The :class:`ActorGeometry` of an actor; KeyError if the id is not an actor."""
        try:
            return self._actor_by_id[int(instance_id)]
        except KeyError:
            raise KeyError(f"instance id {instance_id} is not an actor of scene {self.scene.name!r}") from None

    def combined_table(self, name: str) -> np.ndarray:
        """A per-triangle table (``"tri_instance"``, ``"tri_color"``, ...) over the static
        triangles followed by each actor's (rows ``a.tri_offset ...``); normals and first
        vertices of actors are in their own frames."""
        return np.concatenate([getattr(self, name)] + [a.tables[name] for a in self.actors], axis=0)

    def object_bounds(self, instance_id: int, t_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (min (3,), max (3,)) of one object's vertices, metres, world ENU.

        An actor's bounds are at its pose at ``t_s`` (required for actors)."""
        if int(instance_id) in self._actor_by_id:
            if t_s is None:
                raise ValueError(f"instance id {instance_id} is an actor: its bounds need a time t_s")
            V = self._actor_by_id[int(instance_id)].world_vertices(t_s)
            return V.min(axis=0), V.max(axis=0)
        tri = self.triangles[self.tri_instance == instance_id]
        if len(tri) == 0:
            raise KeyError(f"no triangles with instance id {instance_id}")
        V = self.vertices[np.unique(tri)]
        return V.min(axis=0).astype(float), V.max(axis=0).astype(float)

    def cast(self, rays: np.ndarray, threads: int = 1) -> dict[str, np.ndarray]:
        """First hits of rays (n, 6) float32 ``[origin, direction]`` on the static scene:
        ``t_hit`` (n,) in units of the direction's length (inf on a miss), ``primitive_ids`` (n,)
        uint32 (2^32 - 1 on a miss), ``primitive_normals`` (n, 3). The rays are passed to Open3D
        without a copy. Actors: :meth:`cast_actors`."""
        rays = np.ascontiguousarray(rays, dtype=np.float32)
        out = self.raycasting.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=threads)
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_normals")}

    def cast_actors(self, rays: np.ndarray, t_hit: np.ndarray, tri: np.ndarray, t_s: float, threads: int = 1,
                    candidates=None) -> None:
        """Let the actors at their poses at ``t_s`` occlude the hits of ``rays`` (n, 6) float32,
        world ENU: where an actor is nearer, ``t_hit`` (n,) float32 and ``tri`` (n,) (indices in
        the combined tables, :meth:`combined_table`) are overwritten in place.

        Each actor's rays are moved into its frame (``T_actor_world``, a rigid transform, so
        the ray parameter ``t`` is unchanged) and cast against its own structure; only rays
        that pass within the actor's bounding sphere, ahead of their current hit, are cast.

        ``candidates`` (optional): ``f(centre_m (3,), radius_m) -> int array or None``, a
        superset of the ray indices that can meet that sphere (a camera's pixel rectangle), or
        None for "all rays"; the renderer passes one so the sphere test runs on a few pixels.
        """
        if not self.actors:
            return
        origin = rays[0, :3].astype(float)
        same_origin = candidates is not None or bool(np.all(rays[:, :3] == rays[0, :3]))
        for a in self.actors:
            pose = a.pose(t_s)
            c = pose.position_m
            R = pose.T_world_actor[:3, :3]
            centre = R @ a.center_local_m + c
            sub = None if candidates is None else candidates(centre, a.radius_m)
            if sub is not None and len(sub) == 0:
                continue
            if same_origin:
                # rays from one point (a camera): the sphere's angular cone, then the nearer check
                if sub is None:
                    idx = _cone_rays(rays[:, 3:6], centre - origin, a.radius_m, t_hit)
                else:
                    idx = sub[_cone_rays(rays[sub, 3:6], centre - origin, a.radius_m, t_hit[sub])]
            else:
                idx = _sphere_rays(rays, centre, a.radius_m, t_hit)
            if len(idx) == 0:
                continue
            sub = np.empty((len(idx), 6), dtype=np.float32)
            if same_origin:  # one origin: move it once; directions rotate in float32
                sub[:, :3] = (origin - c) @ R
                np.matmul(rays[idx, 3:6], R.astype(np.float32), out=sub[:, 3:6])
            else:
                sub[:, :3] = (rays[idx, :3].astype(float) - c) @ R
                sub[:, 3:6] = rays[idx, 3:6].astype(float) @ R
            out = a.raycasting.cast_rays(o3d.core.Tensor.from_numpy(sub), nthreads=threads)
            th = out["t_hit"].numpy()
            nearer = th < t_hit[idx]
            if np.any(nearer):
                j = idx[nearer]
                t_hit[j] = th[nearer]
                tri[j] = a.tri_offset + out["primitive_ids"].numpy()[nearer].astype(tri.dtype)

    def closest(self, points: np.ndarray, threads: int = 1, t_s=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points to ``points`` (n, 3), metres, world ENU.

        ``t_s``: None queries the static objects only; a time (scalar, or (n,) one per point,
        world clock) also queries every actor at its pose at that time (exact: the point is
        moved into the actor frame and queried against the actor's mesh).

        Returns
        -------
        distance (n,) metres (unsigned), closest point (n, 3), instance id (n,) of its object
        """
        P = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float32)
        if self.triangle_count:
            out = self.raycasting.compute_closest_points(o3d.core.Tensor(P), nthreads=threads)
            q = out["points"].numpy().astype(float)
            tri = out["primitive_ids"].numpy().astype(np.int64)
            d = np.linalg.norm(q - P.astype(float), axis=1)
            inst = self.tri_instance[tri]
        else:
            q = np.full((len(P), 3), np.inf)
            d = np.full(len(P), np.inf)
            inst = np.zeros(len(P), np.int32)
        if t_s is None or not self.actors:
            return d, q, inst
        t = np.broadcast_to(np.asarray(t_s, dtype=float), (len(P),))
        Pd = P.astype(float)
        inst = inst.copy()
        for a in self.actors:
            pos, yaw, _, _ = poses_at(a.obj.motion, t)
            rel = Pd - pos
            # only points whose bounding-sphere distance could beat the current nearest surface
            cl = a.center_local_m
            cw = np.stack([np.cos(yaw) * cl[0] - np.sin(yaw) * cl[1], np.sin(yaw) * cl[0] + np.cos(yaw) * cl[1], np.full(len(yaw), cl[2])], axis=1)
            near = np.flatnonzero(np.linalg.norm(rel - cw, axis=1) - a.radius_m < d)
            if len(near) == 0:
                continue
            c, s = np.cos(yaw[near]), np.sin(yaw[near])
            r = rel[near]
            local = np.stack([c * r[:, 0] + s * r[:, 1], -s * r[:, 0] + c * r[:, 1], r[:, 2]], axis=1)
            out = a.raycasting.compute_closest_points(o3d.core.Tensor(local.astype(np.float32)), nthreads=threads)
            ql = out["points"].numpy().astype(float)
            da = np.linalg.norm(ql - local, axis=1)
            better = da < d[near]
            if np.any(better):
                j = near[better]
                qb, cb, sb = ql[better], c[better], s[better]
                d[j] = da[better]
                q[j] = np.stack([cb * qb[:, 0] - sb * qb[:, 1], sb * qb[:, 0] + cb * qb[:, 1], qb[:, 2]], axis=1) + pos[j]
                inst[j] = a.instance_id
        return d, q, inst


def _cone_rays(directions: np.ndarray, centre_rel: np.ndarray, radius_m: float, t_hit: np.ndarray) -> np.ndarray:
    """Indices of rays from one origin (directions (n, 3)) that pass within ``radius_m`` of a
    sphere centred at ``centre_rel`` (3,) relative to the origin, and whose current hit is not
    nearer than the sphere's near side."""
    dist = float(np.linalg.norm(centre_rel))
    if dist <= radius_m:  # the origin is inside the bound: every ray may hit
        return np.arange(len(directions))
    D = directions.astype(np.float32)
    dot = D @ centre_rel.astype(np.float32)  # t of the closest approach times |d|^2
    dd = np.einsum("ij,ij->i", D, D)
    # squared closest-approach distance of the ray line: dist^2 - dot^2 / |d|^2
    close = (dot > 0) & (dist * dist - dot * dot / dd <= radius_m * radius_m)
    idx = np.flatnonzero(close)
    if len(idx):
        # z-depth parameter of the sphere's nearest point along each ray (lower bound)
        t_near = (dot[idx] - np.sqrt(np.maximum(dot[idx] ** 2 - dd[idx] * (dist * dist - radius_m * radius_m), 0.0))) / dd[idx]
        idx = idx[t_near < t_hit[idx]]
    return idx


def _sphere_rays(rays: np.ndarray, centre: np.ndarray, radius_m: float, t_hit: np.ndarray) -> np.ndarray:
    """Indices of rays (n, 6) of any origins whose line passes within ``radius_m`` of ``centre``
    ahead of the origin and not behind the current hit."""
    O = rays[:, :3].astype(float) - centre
    D = rays[:, 3:6].astype(float)
    dd = np.einsum("ij,ij->i", D, D)
    b = np.einsum("ij,ij->i", O, D)
    c = np.einsum("ij,ij->i", O, O) - radius_m * radius_m
    disc = b * b - dd * c
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    t0 = (-b - sq) / dd
    t1 = (-b + sq) / dd
    return np.flatnonzero(ok & (t1 >= 0) & (t0 < t_hit))
