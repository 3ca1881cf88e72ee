"""Primitive meshes: closed, outward-facing, and of the analytic volume and extent."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onfly.world.primitives import (
    PrimitiveError,
    box_mesh,
    check_polygon,
    cylinder_mesh,
    extruded_polygon_mesh,
    mesh_arrays,
    plane_mesh,
    ramp_mesh,
    read_mesh_file,
    sphere_mesh,
    stairs_mesh,
    triangulate_polygon,
)

L_SHAPE = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 3], [0, 3]], dtype=float)  # area 6


def signed_volume(mesh) -> float:
    """Divergence theorem: positive iff the closed mesh's triangles face outwards."""
    V, F = mesh_arrays(mesh)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0)


@pytest.mark.parametrize(
    "mesh, volume",
    [
        (box_mesh([1, 2, 3], [2.0, 3.0, 4.0], 0.7), 24.0),
        (cylinder_mesh([0, 0, 1], 0.5, 2.0, 12), 12 / 2 * 0.25 * math.sin(2 * math.pi / 12) * 2.0),
        (extruded_polygon_mesh(L_SHAPE, -1.0, 2.0), 12.0),
        (extruded_polygon_mesh(L_SHAPE[::-1], 0.0, 1.0), 6.0),
        (stairs_mesh([1, 1, 0], 0.3, 1.5, 4, 0.2, 0.3), 1.5 * 0.3 * 0.2 * (1 + 2 + 3 + 4)),
        (ramp_mesh([0, 0, 0], -2.0, 4.0, 2.0, 1.0), 0.5 * 4.0 * 1.0 * 2.0),
    ],
)
def test_closed_primitives_are_watertight_outward_and_exact_volume(mesh, volume):
    assert mesh.is_watertight()
    assert signed_volume(mesh) == pytest.approx(volume, rel=1e-9)


def test_sphere_is_closed_outward_and_inscribed():
    m = sphere_mesh([1, -2, 3], 2.0, rings=6)
    assert m.is_watertight()
    V, F = mesh_arrays(m)
    np.testing.assert_allclose(np.linalg.norm(V - [1, -2, 3], axis=1), 2.0)
    assert len(F) == 4 * 6 * 5
    vol = signed_volume(m)
    assert 0.75 * (4 / 3) * math.pi * 8 < vol < (4 / 3) * math.pi * 8


def test_box_extent_with_yaw_and_stairs_height():
    V, _ = mesh_arrays(box_mesh([0, 0, 0], [4.0, 2.0, 1.0], math.pi / 2))
    np.testing.assert_allclose(V.max(axis=0), [1.0, 2.0, 0.5], atol=1e-12)
    V, _ = mesh_arrays(stairs_mesh([0, 0, 0.5], math.pi / 2, 2.0, 10, 0.25, 0.3))
    np.testing.assert_allclose(V.min(axis=0), [-1.0, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(V.max(axis=0), [1.0, 3.0, 3.0], atol=1e-12)


def test_plane_faces_up_and_covers_its_size():
    V, F = mesh_arrays(plane_mesh([0, 0, 2], [6.0, 4.0]))
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    assert np.all(n[:, 2] > 0)
    assert 0.5 * np.linalg.norm(n, axis=1).sum() == pytest.approx(24.0)


def test_triangulation_of_non_convex_polygon_is_exact_and_ccw():
    for P in (L_SHAPE, L_SHAPE[::-1]):
        T = triangulate_polygon(P)
        a, b, c = P[T[:, 0]], P[T[:, 1]], P[T[:, 2]]
        cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        assert len(T) == len(P) - 2
        assert np.all(cross > 0)
        assert 0.5 * cross.sum() == pytest.approx(6.0)


@pytest.mark.parametrize(
    "points, pattern",
    [
        ([[0, 0], [1, 0]], r"shape \(n >= 3, 2\)"),
        ([[0, 0], [1, 0], [1, 0], [0, 1]], "points 1 and 2 coincide"),
        ([[0, 0], [1, 1], [2, 2]], "zero area"),
        ([[0, 0], [4, 2], [4, 0], [0, 3]], "edges 0 and 2 intersect"),
    ],
)
def test_bad_polygons_are_rejected(points, pattern):
    with pytest.raises(PrimitiveError, match=pattern):
        check_polygon(points)


def test_mesh_file_is_placed_and_empty_file_rejected(tmp_path):
    p = tmp_path / "t.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    V, F = mesh_arrays(read_mesh_file(p, [10, 0, 1], math.pi / 2, 2.0))
    np.testing.assert_allclose(V, [[10, 0, 1], [10, 2, 1], [8, 0, 1]], atol=1e-12)
    empty = tmp_path / "e.ply"
    empty.write_text("")
    with pytest.raises(PrimitiveError, match="has no triangles"):
        read_mesh_file(empty, [0, 0, 0])
