"""A scene compiled once into one Open3D ``RaycastingScene`` with per-triangle lookup tables.

The renderer and the collision checker share one :class:`SceneGeometry`: all parts of all
objects are merged into a single triangle mesh, and every triangle carries its object's
instance id, semantic label id, colour and texture. Ray hits and closest-point queries return
triangle indices, which index these tables directly.
"""

from __future__ import annotations

import logging

import numpy as np
import open3d as o3d

from onfly.world.primitives import mesh_arrays, shape_mesh
from onfly.world.scene import MATERIALS, TEXTURE_PATTERNS, Scene

__all__ = ["SceneGeometry", "TEXTURE_NONE"]

log = logging.getLogger(__name__)

#: Texture code of untextured triangles; patterns are 1 + their index in TEXTURE_PATTERNS.
TEXTURE_NONE = 0


class SceneGeometry:
    """Triangle soup of a scene and the ray-casting structure built over it (once).

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
    raycasting : open3d.t.geometry.RaycastingScene
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        label_ids = scene.label_ids
        V_all, F_all = [], []
        inst, lab, col, tex, tex_p, mat = [], [], [], [], [], []
        offset = 0
        for obj in scene.objects:
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
        self.vertices = np.vstack(V_all).astype(np.float32)
        self.triangles = np.vstack(F_all).astype(np.uint32)
        self.tri_instance = np.concatenate(inst)
        self.tri_label = np.concatenate(lab)
        self.tri_color = np.vstack(col).astype(np.float32)
        self.tri_texture = np.concatenate(tex)
        self.tri_tex_params = np.vstack(tex_p).astype(np.float32)
        self.tri_material = np.concatenate(mat)
        v0, v1, v2 = (self.vertices[self.triangles[:, k]] for k in range(3))
        n = np.cross(v1 - v0, v2 - v0)
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        self.tri_normal = np.where(norm > 0, n / np.where(norm > 0, norm, 1.0), 0.0).astype(np.float32)
        self.tri_v0 = v0.astype(np.float32)
        self.raycasting = o3d.t.geometry.RaycastingScene()
        self.raycasting.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
        log.debug("scene %s: %d objects, %d triangles", scene.name, len(scene.objects), len(self.triangles))

    @property
    def triangle_count(self) -> int:
        return int(len(self.triangles))

    def object_bounds(self, instance_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds (min (3,), max (3,)) of one object's vertices, metres."""
        tri = self.triangles[self.tri_instance == instance_id]
        if len(tri) == 0:
            raise KeyError(f"no triangles with instance id {instance_id}")
        V = self.vertices[np.unique(tri)]
        return V.min(axis=0).astype(float), V.max(axis=0).astype(float)

    def cast(self, rays: np.ndarray, threads: int = 1) -> dict[str, np.ndarray]:
        """First hits of rays (n, 6) float32 ``[origin, direction]``: ``t_hit`` (n,) in units of
        the direction's length (inf on a miss), ``primitive_ids`` (n,) uint32 (2^32 - 1 on a
        miss), ``primitive_normals`` (n, 3). The rays are passed to Open3D without a copy."""
        rays = np.ascontiguousarray(rays, dtype=np.float32)
        out = self.raycasting.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=threads)
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_normals")}

    def closest(self, points: np.ndarray, threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points to ``points`` (n, 3), metres, world ENU.

        Returns
        -------
        distance (n,) metres (unsigned), closest point (n, 3), instance id (n,) of its object
        """
        P = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float32)
        out = self.raycasting.compute_closest_points(o3d.core.Tensor(P), nthreads=threads)
        q = out["points"].numpy().astype(float)
        tri = out["primitive_ids"].numpy().astype(np.int64)
        d = np.linalg.norm(q - P.astype(float), axis=1)
        return d, q, self.tri_instance[tri]
