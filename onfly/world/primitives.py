"""Triangle meshes of the scene primitives, as Open3D legacy ``TriangleMesh`` objects.

Every builder returns a closed mesh (except :func:`plane_mesh`, a single-sided rectangle)
with outward-facing counter-clockwise triangles, in world ENU metres. Meshes are kept small
(a cylinder has ``4 * segments`` triangles, a sphere ``4 * rings * (rings - 1)``...) because
the whole scene is ray-cast on one CPU core.
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d

from onfly.world.scene import (
    Box,
    Cylinder,
    ExtrudedPolygon,
    MeshFile,
    Plane,
    Ramp,
    Shape,
    Sphere,
    Stairs,
)

__all__ = [
    "PrimitiveError",
    "check_polygon",
    "triangulate_polygon",
    "box_mesh",
    "cylinder_mesh",
    "sphere_mesh",
    "plane_mesh",
    "extruded_polygon_mesh",
    "stairs_mesh",
    "ramp_mesh",
    "read_mesh_file",
    "shape_mesh",
    "mesh_arrays",
]


class PrimitiveError(ValueError):
    """A shape that cannot be meshed (degenerate polygon, unreadable mesh file)."""


def _to_o3d(V: np.ndarray, F: np.ndarray) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh()
    m.vertices = o3d.utility.Vector3dVector(np.asarray(V, dtype=float))
    m.triangles = o3d.utility.Vector3iVector(np.asarray(F, dtype=np.int32))
    return m


def mesh_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 metres and triangles (m, 3) int64 of a legacy mesh."""
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.triangles, dtype=np.int64)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# -- polygons ------------------------------------------------------------------------------


def _signed_area(P: np.ndarray) -> float:
    x, y = P[:, 0], P[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _segments_cross(p1, p2, q1, q2) -> bool:
    """True if closed segments p1p2 and q1q2 intersect (including touching)."""

    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    def on_seg(a, b, c):
        return min(a[0], b[0]) - 1e-12 <= c[0] <= max(a[0], b[0]) + 1e-12 and min(a[1], b[1]) - 1e-12 <= c[1] <= max(a[1], b[1]) + 1e-12

    d1, d2, d3, d4 = orient(q1, q2, p1), orient(q1, q2, p2), orient(p1, p2, q1), orient(p1, p2, q2)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 != 0 and d2 != 0 and d3 != 0 and d4 != 0:
        return True
    eps = 1e-12
    return (
        (abs(d1) < eps and on_seg(q1, q2, p1))
        or (abs(d2) < eps and on_seg(q1, q2, p2))
        or (abs(d3) < eps and on_seg(p1, p2, q1))
        or (abs(d4) < eps and on_seg(p1, p2, q2))
    )


def check_polygon(points) -> np.ndarray:
    """Validate a simple polygon; returns it as float (n, 2).

    Raises
    ------
    PrimitiveError for fewer than 3 points, non-finite values, repeated neighbours, zero area
    or self-intersection (the message names the offending edges).
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 2 or P.shape[0] < 3:
        raise PrimitiveError(f"polygon must have shape (n >= 3, 2), got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise PrimitiveError("polygon has non-finite points")
    n = len(P)
    for i in range(n):
        if np.linalg.norm(P[i] - P[(i + 1) % n]) < 1e-9:
            raise PrimitiveError(f"polygon points {i} and {(i + 1) % n} coincide")
    if abs(_signed_area(P)) < 1e-9:
        raise PrimitiveError("polygon has zero area")
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbouring edges share a vertex
            if _segments_cross(P[i], P[(i + 1) % n], P[j], P[(j + 1) % n]):
                raise PrimitiveError(f"polygon edges {i} and {j} intersect (the polygon is not simple)")
    return P


def triangulate_polygon(points) -> np.ndarray:
    """Ear-clipping triangulation of a simple polygon.

    Parameters
    ----------
    points : array (n, 2), either winding

    Returns
    -------
    int array (n - 2, 3) of vertex indices, each triangle counter-clockwise.
    """
    P = check_polygon(points)
    idx = list(range(len(P)))
    if _signed_area(P) < 0:
        idx.reverse()
    tris: list[tuple[int, int, int]] = []

    def cross(o, a, b):
        return (P[a][0] - P[o][0]) * (P[b][1] - P[o][1]) - (P[a][1] - P[o][1]) * (P[b][0] - P[o][0])

    def inside(p, a, b, c):
        return cross(a, b, p) >= -1e-12 and cross(b, c, p) >= -1e-12 and cross(c, a, p) >= -1e-12

    guard = 0
    while len(idx) > 3:
        m = len(idx)
        for k in range(m):
            a, b, c = idx[(k - 1) % m], idx[k], idx[(k + 1) % m]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or collinear corner
            if any(inside(j, a, b, c) for j in idx if j not in (a, b, c)):
                continue
            tris.append((a, b, c))
            idx.pop(k)
            break
        else:
            raise PrimitiveError("polygon could not be triangulated (degenerate corners)")
        guard += 1
        if guard > 10 * len(P):
            raise PrimitiveError("polygon triangulation did not terminate")
    tris.append((idx[0], idx[1], idx[2]))
    return np.array(tris, dtype=np.int64)


def _extrude(profile: np.ndarray, c0: float, c1: float) -> tuple[np.ndarray, np.ndarray]:
    """Prism over a polygon in local (a, b) extruded along local c from c0 to c1.

    Returns vertices (2n, 3) in local (a, b, c) and outward CCW triangles.
    """
    P = check_polygon(profile)
    if _signed_area(P) < 0:
        P = P[::-1]
    n = len(P)
    caps = triangulate_polygon(P)
    V = np.vstack([np.column_stack([P, np.full(n, c0)]), np.column_stack([P, np.full(n, c1)])])
    F = [caps[:, ::-1], caps + n]  # bottom faces -c, top faces +c
    for i in range(n):
        j = (i + 1) % n
        F.append(np.array([[i, j, j + n], [i, j + n, i + n]]))
    return V, np.vstack(F)


def _placed(V_local: np.ndarray, F: np.ndarray, M: np.ndarray, t: np.ndarray) -> o3d.geometry.TriangleMesh:
    """Map local vertices through ``V @ M.T + t``; flip winding if ``M`` mirrors."""
    V = V_local @ M.T + t
    if np.linalg.det(M) < 0:
        F = F[:, ::-1]
    return _to_o3d(V, F)


# -- builders ------------------------------------------------------------------------------


def box_mesh(center_m, size_m, yaw_rad: float = 0.0) -> o3d.geometry.TriangleMesh:
    """Cuboid, 8 vertices / 12 triangles. ``size_m`` (3,) is the full extent along its axes."""
    h = 0.5 * np.asarray(size_m, dtype=float)
    rect = np.array([[-h[0], -h[1]], [h[0], -h[1]], [h[0], h[1]], [-h[0], h[1]]])
    V, F = _extrude(rect, -h[2], h[2])
    return _placed(V, F, _rot_z(yaw_rad), np.asarray(center_m, dtype=float))


def cylinder_mesh(base_m, radius_m: float, height_m: float, segments: int = 12) -> o3d.geometry.TriangleMesh:
    """Upright cylinder (polygonal prism with ``segments`` sides), ``4 * segments`` triangles.

    The polygon's vertices lie on the circle, so the surface is within
    ``radius_m * (1 - cos(pi / segments))`` of the true cylinder.
    """
    ang = 2.0 * np.pi * np.arange(segments) / segments
    ring = radius_m * np.column_stack([np.cos(ang), np.sin(ang)])
    V, F = _extrude(ring, 0.0, height_m)
    return _placed(V, F, np.eye(3), np.asarray(base_m, dtype=float))


def sphere_mesh(center_m, radius_m: float, rings: int = 6) -> o3d.geometry.TriangleMesh:
    """UV sphere with ``rings`` latitude bands and ``2 * rings`` longitudes; vertices on the sphere."""
    n_lon = 2 * rings
    V = [[0.0, 0.0, radius_m]]
    for i in range(1, rings):
        th = np.pi * i / rings
        for j in range(n_lon):
            ph = 2.0 * np.pi * j / n_lon
            V.append([radius_m * np.sin(th) * np.cos(ph), radius_m * np.sin(th) * np.sin(ph), radius_m * np.cos(th)])
    V.append([0.0, 0.0, -radius_m])
    south = len(V) - 1
    F = []

    def ring_idx(i, j):
        return 1 + (i - 1) * n_lon + (j % n_lon)

    for j in range(n_lon):
        F.append([0, ring_idx(1, j), ring_idx(1, j + 1)])
        F.append([south, ring_idx(rings - 1, j + 1), ring_idx(rings - 1, j)])
    for i in range(1, rings - 1):
        for j in range(n_lon):
            a, b = ring_idx(i, j), ring_idx(i, j + 1)
            c, d = ring_idx(i + 1, j), ring_idx(i + 1, j + 1)
            F.append([a, c, d])
            F.append([a, d, b])
    return _to_o3d(np.asarray(V) + np.asarray(center_m, dtype=float), np.asarray(F))


def plane_mesh(center_m, size_m, yaw_rad: float = 0.0) -> o3d.geometry.TriangleMesh:
    """Horizontal rectangle facing +z, 2 triangles; ``size_m`` (2,) full extents."""
    hx, hy = 0.5 * float(size_m[0]), 0.5 * float(size_m[1])
    V = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    return _placed(V, F, _rot_z(yaw_rad), np.asarray(center_m, dtype=float))


def extruded_polygon_mesh(points_m, z_min_m: float, height_m: float) -> o3d.geometry.TriangleMesh:
    """Prism over a simple xy polygon (n, 2), from ``z_min_m`` to ``z_min_m + height_m``."""
    V, F = _extrude(np.asarray(points_m, dtype=float), z_min_m, z_min_m + height_m)
    return _to_o3d(V, F)


def _profile_frame(start_m, yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Map local (s along yaw, z up, w left) to world: columns are the three world axes."""
    d = np.array([math.cos(yaw_rad), math.sin(yaw_rad), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    left = np.cross(up, d)
    return np.column_stack([d, up, left]), np.asarray(start_m, dtype=float)


def stairs_mesh(start_m, yaw_rad: float, width_m: float, step_count: int, rise_m: float, run_m: float) -> o3d.geometry.TriangleMesh:
    """Solid staircase: the stepped side profile extruded across ``width_m``."""
    prof = [[0.0, 0.0]]
    for k in range(step_count):
        prof.append([k * run_m, (k + 1) * rise_m])
        prof.append([(k + 1) * run_m, (k + 1) * rise_m])
    prof.append([step_count * run_m, 0.0])
    M, t = _profile_frame(start_m, yaw_rad)
    V, F = _extrude(np.array(prof), -0.5 * width_m, 0.5 * width_m)
    return _placed(V, F, M, t)


def ramp_mesh(start_m, yaw_rad: float, length_m: float, width_m: float, rise_m: float) -> o3d.geometry.TriangleMesh:
    """Solid wedge climbing ``rise_m`` over ``length_m`` along ``yaw_rad``, 8 triangles."""
    prof = np.array([[0.0, 0.0], [length_m, 0.0], [length_m, rise_m]])
    M, t = _profile_frame(start_m, yaw_rad)
    V, F = _extrude(prof, -0.5 * width_m, 0.5 * width_m)
    return _placed(V, F, M, t)


def read_mesh_file(path, position_m, yaw_rad: float = 0.0, scale: float = 1.0) -> o3d.geometry.TriangleMesh:
    """Read an OBJ / PLY with Open3D, scale about its origin, rotate by yaw, move to position.

    Raises PrimitiveError if the file holds no triangles (Open3D returns an empty mesh for
    unreadable files rather than raising).
    """
    mesh = o3d.io.read_triangle_mesh(str(path))
    V, F = mesh_arrays(mesh)
    if len(F) == 0 or len(V) == 0:
        raise PrimitiveError(f"mesh file {path} has no triangles (unreadable or empty)")
    if not np.all(np.isfinite(V)):
        raise PrimitiveError(f"mesh file {path} has non-finite vertices")
    V = (scale * V) @ _rot_z(yaw_rad).T + np.asarray(position_m, dtype=float)
    return _to_o3d(V, F)


def shape_mesh(shape: Shape) -> o3d.geometry.TriangleMesh:
    """Mesh of any scene shape (dispatch on its dataclass)."""
    if isinstance(shape, Box):
        return box_mesh(shape.center_m, shape.size_m, shape.yaw_rad)
    if isinstance(shape, Cylinder):
        return cylinder_mesh(shape.base_m, shape.radius_m, shape.height_m, shape.segments)
    if isinstance(shape, Sphere):
        return sphere_mesh(shape.center_m, shape.radius_m, shape.rings)
    if isinstance(shape, Plane):
        return plane_mesh(shape.center_m, shape.size_m, shape.yaw_rad)
    if isinstance(shape, ExtrudedPolygon):
        return extruded_polygon_mesh(shape.points_m, shape.z_min_m, shape.height_m)
    if isinstance(shape, Stairs):
        return stairs_mesh(shape.start_m, shape.yaw_rad, shape.width_m, shape.step_count, shape.rise_m, shape.run_m)
    if isinstance(shape, Ramp):
        return ramp_mesh(shape.start_m, shape.yaw_rad, shape.length_m, shape.width_m, shape.rise_m)
    if isinstance(shape, MeshFile):
        return read_mesh_file(shape.path, shape.position_m, shape.yaw_rad, shape.scale)
    raise PrimitiveError(f"unknown shape type {type(shape).__name__}")
