"""Exact analytic distance field: closed-form references, rotations, gradients, scenes."""

from __future__ import annotations

import numpy as np
import pytest

from planning.analytic_field import (
    SCENE_KINDS,
    AnalyticField,
    AnalyticFieldError,
    Box,
    HalfSpace,
    Sphere,
    VerticalCylinder,
    obstacle_scene,
)
from planning.field import DistanceField


def unit_box() -> AnalyticField:
    return AnalyticField(boxes=(Box(np.zeros(3), np.array([1.0, 2.0, 3.0])),))


def test_is_a_distance_field():
    assert isinstance(unit_box(), DistanceField)


def test_box_exact_distances_face_edge_corner_inside():
    f = unit_box()
    pts = np.array(
        [
            [3.0, 0.0, 0.0],  # face: 2 m from x = 1
            [2.0, 3.0, 0.0],  # edge: (1, 1) beyond the (x, y) corner
            [2.0, 4.0, 5.0],  # corner: (1, 2, 2)
            [0.5, 0.0, 0.0],  # inside: 0.5 m from the x faces
            [0.0, 0.0, -2.9],  # inside near the bottom face
        ]
    )
    d, g = f.query(pts)
    np.testing.assert_allclose(d, [2.0, np.sqrt(2.0), 3.0, -0.5, -0.1], atol=1e-12)
    np.testing.assert_allclose(g[0], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(g[1], [np.sqrt(0.5), np.sqrt(0.5), 0.0])
    np.testing.assert_allclose(g[2], [1 / 3, 2 / 3, 2 / 3])
    np.testing.assert_allclose(g[3], [1.0, 0.0, 0.0])
    np.testing.assert_allclose(g[4], [0.0, 0.0, -1.0])


def test_yawed_box_equals_axis_aligned_box_in_rotated_coordinates():
    rng = np.random.default_rng(0)
    yaw = 0.7
    c = np.array([1.0, -2.0, 0.5])
    h = np.array([0.4, 1.2, 0.8])
    f_rot = AnalyticField(boxes=(Box(c, h, yaw),))
    f_ref = AnalyticField(boxes=(Box(np.zeros(3), h),))
    Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    local = rng.uniform(-3, 3, size=(200, 3))
    world = local @ Rz.T + c
    d_rot, g_rot = f_rot.query(world)
    d_ref, g_ref = f_ref.query(local)
    np.testing.assert_allclose(d_rot, d_ref, atol=1e-12)
    np.testing.assert_allclose(g_rot, g_ref @ Rz.T, atol=1e-12)


def test_sphere_cylinder_and_half_space_closed_forms():
    f = AnalyticField(spheres=(Sphere(np.array([0.0, 0.0, 5.0]), 1.0),))
    d, g = f.query(np.array([[0.0, 3.0, 5.0], [0.0, 0.0, 5.5]]))
    np.testing.assert_allclose(d, [2.0, -0.5])
    np.testing.assert_allclose(g, [[0, 1, 0], [0, 0, 1]], atol=1e-12)

    cyl = AnalyticField(cylinders=(VerticalCylinder(np.array([1.0, 1.0]), 0.5, 0.0, 2.0),))
    pts = np.array([[3.0, 1.0, 1.0], [1.0, 1.0, 3.0], [2.5, 1.0, 3.0], [1.2, 1.0, 1.0]])
    d, g = cyl.query(pts)
    np.testing.assert_allclose(d, [1.5, 1.0, np.hypot(1.0, 1.0), -0.3], atol=1e-12)
    np.testing.assert_allclose(g[0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(g[1], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(g[2], [np.sqrt(0.5), 0, np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(g[3], [1, 0, 0], atol=1e-12)

    ground = AnalyticField(half_spaces=(HalfSpace(np.zeros(3), np.array([0.0, 0.0, 2.0])),))
    d, g = ground.query(np.array([[5.0, -3.0, 1.25], [0.0, 0.0, -0.5]]))
    np.testing.assert_allclose(d, [1.25, -0.5])
    np.testing.assert_allclose(g, [[0, 0, 1], [0, 0, 1]])


def test_union_is_the_minimum_and_gradient_comes_from_the_nearest_primitive():
    rng = np.random.default_rng(1)
    parts = (
        AnalyticField(boxes=(Box(np.array([2.0, 0, 1]), np.array([0.5, 0.5, 1.0]), 0.3),)),
        AnalyticField(spheres=(Sphere(np.array([-2.0, 1.0, 1.0]), 0.7),)),
        AnalyticField(cylinders=(VerticalCylinder(np.array([0.0, -2.0]), 0.4, 0.0, 3.0),)),
        AnalyticField(half_spaces=(HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0])),)),
    )
    union = AnalyticField(
        boxes=parts[0].boxes, spheres=parts[1].spheres, cylinders=parts[2].cylinders, half_spaces=parts[3].half_spaces
    )
    P = rng.uniform([-4, -4, 0.1], [4, 4, 3], size=(300, 3))
    D = np.stack([p.query(P)[0] for p in parts])
    G = np.stack([p.query(P)[1] for p in parts])
    d, g = union.query(P)
    np.testing.assert_allclose(d, D.min(axis=0), atol=1e-12)
    np.testing.assert_allclose(g, G[np.argmin(D, axis=0), np.arange(len(P))], atol=1e-12)


def test_gradient_matches_finite_differences_and_is_unit():
    rng = np.random.default_rng(2)
    f = obstacle_scene("pillars", 3).field
    P = rng.uniform(-25, 25, size=(400, 3))
    P[:, 2] = rng.uniform(0.2, 3.0, size=400)
    d, g = f.query(P)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)
    h = 1e-6
    fd = np.stack([(f.query(P + h * e)[0] - f.query(P - h * e)[0]) / (2 * h) for e in np.eye(3)], axis=1)
    # away from medial sets (where the nearest primitive switches) the gradient is exact
    ok = np.all(np.isfinite(fd), axis=1) & (np.abs(np.linalg.norm(fd, axis=1) - 1.0) < 1e-4)
    assert ok.mean() > 0.95
    np.testing.assert_allclose(g[ok], fd[ok], atol=1e-5)


def test_single_point_is_accepted_and_bad_points_raise():
    f = unit_box()
    d, g = f.query(np.array([3.0, 0.0, 0.0]))
    assert d.shape == (1,) and g.shape == (1, 3)
    with pytest.raises(AnalyticFieldError, match=r"shape \(n, 3\)"):
        f.query(np.zeros((4, 2)))
    with pytest.raises(AnalyticFieldError, match="NaN or inf"):
        f.query(np.array([[0.0, np.nan, 0.0]]))


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: Box(np.zeros(3), np.array([1.0, 0.0, 1.0])), "half_extents must be > 0"),
        (lambda: Box(np.zeros(2), np.ones(3)), r"Box.center must be a finite \(3,\)"),
        (lambda: Sphere(np.zeros(3), -1.0), "radius_m must be > 0"),
        (lambda: VerticalCylinder(np.zeros(2), 0.5, 2.0, 1.0), "z_min_m < z_max_m"),
        (lambda: HalfSpace(np.zeros(3), np.zeros(3)), "normal must be nonzero"),
        (lambda: AnalyticField(), "at least one primitive"),
        (lambda: AnalyticField(boxes=(Sphere(np.zeros(3), 1.0),)), "boxes must hold Box items"),
    ],
)
def test_invalid_primitives_raise(make, match):
    with pytest.raises(AnalyticFieldError, match=match):
        make()


def test_scenes_are_seeded_and_start_and_goal_have_clearance():
    for kind in SCENE_KINDS:
        a, b = obstacle_scene(kind, 7), obstacle_scene(kind, 7)
        np.testing.assert_array_equal(a.start, b.start)
        np.testing.assert_array_equal(a.goal, b.goal)
        P = np.array([a.start, a.goal])
        np.testing.assert_array_equal(a.field.query(P)[0], b.field.query(P)[0])
        assert np.all(a.field.distance(P) >= 0.45 + 0.15), kind
        assert not np.array_equal(obstacle_scene(kind, 8).start, a.start)


def test_scene_obstacles_block_the_straight_line():
    """Walls, gaps and overhangs are designed so the straight segment lacks clearance."""
    for kind in ("wall", "overhang"):
        for seed in range(5):
            s = obstacle_scene(kind, seed)
            t = np.linspace(0, 1, 200)[:, None]
            seg = s.start + t * (s.goal - s.start)
            assert s.field.distance(seg).min() < 0.45, (kind, seed)


def test_unknown_scene_kind_lists_the_valid_ones():
    with pytest.raises(AnalyticFieldError, match="scene kind must be one of"):
        obstacle_scene("maze", 0)
