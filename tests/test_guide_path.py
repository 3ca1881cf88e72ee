"""Guide-path front-end: clearance-aware grid search and the carrot on the path."""

from __future__ import annotations

import numpy as np
import pytest

from planning.analytic_field import AnalyticField, Box, HalfSpace
from planning.guide_path import carrot_on_path, search_guide_path, segment_clear, segment_points

GROUND = HalfSpace(np.zeros(3), np.array([0.0, 0.0, 1.0]))


def test_segment_points_spacing_and_ends():
    a, b = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0])
    pts = segment_points(a, b, 0.3)
    np.testing.assert_array_equal(pts[0], a)
    np.testing.assert_array_equal(pts[-1], b)
    assert np.max(np.linalg.norm(np.diff(pts, axis=0), axis=1)) <= 0.3 + 1e-12
    assert segment_clear(np.array([0.5, 0.6]), 0.5) and not segment_clear(np.array([0.5, 0.49]), 0.5)


def test_path_goes_around_the_end_of_a_wall_with_clearance():
    wall = Box(np.array([3.0, -1.0, 2.0]), np.array([0.1, 2.0, 2.0]))  # y from -3 to 1
    field = AnalyticField(boxes=(wall,), half_spaces=(GROUND,))
    start, goal = np.array([0.0, 0.0, 1.2]), np.array([6.0, 0.0, 1.2])
    path = search_guide_path(field, start, goal, clearance_m=0.55, preferred_clearance_m=1.0)
    assert path is not None
    np.testing.assert_array_equal(path[0], start)
    np.testing.assert_array_equal(path[-1], goal)
    d = field.distance(path[1:-1])
    assert d.min() >= 0.55
    assert path[:, 1].max() > 1.0 + 0.55  # it passes the wall's end at y = 1
    length = np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1))
    assert 6.0 < length < 10.0


def test_no_path_when_the_wall_closes_the_grid():
    wall = Box(np.array([3.0, 0.0, 4.0]), np.array([0.1, 30.0, 6.0]))
    field = AnalyticField(boxes=(wall,), half_spaces=(GROUND,))
    path = search_guide_path(field, np.array([0.0, 0.0, 1.2]), np.array([6.0, 0.0, 1.2]), 0.55, 1.0)
    assert path is None


def test_carrot_is_the_point_a_fixed_arc_length_ahead():
    path = np.array([[0.0, 0, 0], [1.0, 0, 0], [1.0, 1.0, 0], [1.0, 3.0, 0]])
    carrot, i = carrot_on_path(path, np.array([0.9, -0.1, 0.0]), 1.5)
    assert i == 1
    np.testing.assert_allclose(carrot, [1.0, 1.5, 0.0])
    carrot, _ = carrot_on_path(path, np.array([0.0, 0.0, 0.0]), 10.0)
    np.testing.assert_array_equal(carrot, path[-1])
    carrot, i = carrot_on_path(path, np.array([1.0, 3.2, 0.0]), 1.0)
    assert i == 3
    np.testing.assert_array_equal(carrot, path[-1])


@pytest.mark.parametrize("res", [0.2, 0.4])
def test_grid_resolution_is_respected_and_capped(res):
    field = AnalyticField(half_spaces=(GROUND,))
    start, goal = np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0])
    path = search_guide_path(field, start, goal, 0.5, 1.0, resolution_m=res)
    steps = np.linalg.norm(np.diff(path[1:-1], axis=0), axis=1)
    assert steps.max() <= res * np.sqrt(3) + 1e-9
    # a huge extent is coarsened instead of exploding the cell count
    far = search_guide_path(field, start, np.array([200.0, 50.0, 1.0]), 0.5, 1.0, resolution_m=res, max_cells=20000)
    assert far is not None and len(far) < 2000


def test_a_passage_thinner_than_the_grid_spacing_is_found_at_the_height_the_vehicle_flies():
    """A slot between a slab below (top at z = 0.9) and one above (bottom at z = 2.12), 4 m long
    and closing the grid from floor to ceiling: a 0.55 m clearance holds only for z in
    [1.45, 1.57], thinner than the 0.25 m spacing. The floor (z_min_m = 0.35, a flight volume's)
    puts the grid's layers at 1.35 and 1.60 m, both in the slabs' clearance; the lattice runs
    through the start instead, so the layer at 1.5 m is there and the slot is found."""
    below = Box(np.array([4.0, 0.0, 0.45]), np.array([2.0, 30.0, 0.45]))
    above = Box(np.array([4.0, 0.0, 3.56]), np.array([2.0, 30.0, 1.44]))
    field = AnalyticField(boxes=(below, above), half_spaces=(GROUND,))
    start, goal = np.array([0.0, 0.0, 1.5]), np.array([8.0, 0.0, 1.5])
    path = search_guide_path(field, start, goal, 0.55, 1.0, resolution_m=0.25, z_min_m=0.35, z_max_m=2.4)
    assert path is not None
    inside = path[(path[:, 0] > 2.0) & (path[:, 0] < 6.0)]
    assert len(inside) and np.allclose(inside[:, 2], 1.5)
    assert field.distance(path[1:-1]).min() >= 0.55
    # the slot closed (a slab 0.1 m lower above): no path, the lattice invents none
    above2 = Box(np.array([4.0, 0.0, 3.46]), np.array([2.0, 30.0, 1.44]))
    shut = AnalyticField(boxes=(below, above2), half_spaces=(GROUND,))
    assert search_guide_path(shut, start, goal, 0.55, 1.0, resolution_m=0.25, z_min_m=0.35, z_max_m=2.4) is None
