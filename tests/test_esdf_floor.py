"""The floor apart from the rest of the map (planning/esdf_floor.py, ``EsdfMap.floor_split``) and
the planner's margin that gives the floor only the vertical tracking error.

- The floor's top layer is the layer most columns end on, plus the noise layers just above it;
  never a ceiling over the vehicle; none without enough floor.
- The rest field is the exact distance to every obstacle voxel that is not floor (brute force).
- Inflated with a floor, the field answers no more than the exact clearance with the floor
  inflated by the vertical margin and the rest by the full one, and never less than the plain
  inflation; over open floor it gives the vehicle its height back.
- The planner keeps a goal 0.9 m over the ground when its error is sideways, and holds it off
  a pole by the full margin.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi

from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig
from planning.esdf_floor import FloorSplit, floor_top_index
from planning.planner import InflatedField, Planner
from planning.planner_config import PlannerConfig
from planning.trajectory import VehicleState
from tests.test_esdf import CAMERA, box_mesh, integrate_all, look_at, make_scene


def _columns(nx, ny, nz, layer_counts):
    """An occupied grid whose columns end (lowest occupied voxel) on the given layers:
    ``{layer: number of columns}``; columns are filled row by row."""
    occ = np.zeros((nx, ny, nz), dtype=bool)
    cols = iter(np.ndindex(nx, ny))
    for layer, n in layer_counts.items():
        for _ in range(n):
            i, j = next(cols)
            occ[i, j, layer:] = False
            occ[i, j, layer] = True
    return occ


def test_floor_top_is_the_modal_layer_and_its_noise_layers():
    occ = _columns(40, 40, 20, {3: 1000, 4: 100, 5: 5, 9: 40})
    assert floor_top_index(occ, below_k=15) == 4  # 10 % joins, 0.5 % does not, a box top at 9 is no floor
    occ = _columns(40, 40, 20, {3: 1000, 5: 300})
    assert floor_top_index(occ, below_k=15) == 3  # the layer right above is empty: the floor ends


def test_floor_top_never_comes_from_over_the_vehicle_and_needs_enough_columns():
    occ = _columns(40, 40, 20, {2: 200, 16: 1000})  # a big ceiling at 16, a floor at 2
    assert floor_top_index(occ, below_k=12) == 2
    assert floor_top_index(occ, below_k=20) == 16  # the caller's height decides
    assert floor_top_index(_columns(40, 40, 20, {2: 30}), below_k=12) is None
    assert floor_top_index(occ, below_k=0) is None
    with pytest.raises(ValueError, match="3-D"):
        floor_top_index(np.zeros((4, 4), bool), 2)


# A floor slab with a pole and a low box on it, seen from four sides at flight height.
CFG = EsdfConfig(size_m=(6.0, 6.0, 3.0), stride_px=1, body_clear_radius_m=0.0)
CENTER = np.array([0.05, 0.05, 1.05])


@pytest.fixture(scope="module")
def floor_map() -> EsdfMap:
    scene = make_scene([
        box_mesh((12.0, 12.0, 0.2), (0.0, 0.0, -0.13)),  # floor, top at z = -0.03 (inside the voxel layer under 0)
        box_mesh((0.12, 0.12, 2.0), (1.0, 0.0, 1.0)),  # pole
        box_mesh((0.6, 0.6, 0.4), (-1.0, -1.0, 0.2)),  # low box
    ])
    esdf = EsdfMap(CFG)
    headings = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    views = [look_at(CENTER + [2.2 * np.cos(a), 2.2 * np.sin(a), 0.4], CENTER - [0, 0, 0.8]) for a in headings]
    # and from the middle, outward and down
    views += [look_at(CENTER + [0.0, 0.0, 0.5], CENTER + [2.0 * np.cos(a), 2.0 * np.sin(a), -1.0]) for a in headings]
    integrate_all(esdf, scene, views, CENTER)
    return esdf


def test_rest_field_is_the_exact_distance_to_every_obstacle_but_the_floor(floor_map):
    split = floor_map.floor_split(1.5)
    assert split is not None
    assert split.top_m == pytest.approx(-0.05, abs=1e-9)  # the voxel layer holding the floor's top
    o, v = floor_map.origin_index, floor_map.voxel_m
    top_k = int(round(split.top_m / v - 0.5)) - o[2]
    solid = floor_map._occ.solid.copy()
    solid[:, :, : top_k + 1] = False
    padded = np.pad(solid, 1, constant_values=True)
    padded[:, :, : top_k + 2] = False
    ref = np.minimum(ndi.distance_transform_edt(~padded)[1:-1, 1:-1, 1:-1] * v, CFG.max_distance_m)
    np.testing.assert_allclose(split.rest[:, :, top_k:], ref[:, :, top_k:], atol=1e-6)
    # the pole and the box are in it; right over the floor, far from both, the rest is far
    d, _, inside = split.query(np.array([[0.95, 0.0, 1.0], [-1.0, -1.0, 0.55], [0.0, 1.5, 0.3]]))
    assert inside.all()
    assert d[0] < 0.1 and d[1] < 0.2
    full, _ = floor_map.query(np.array([[0.0, 1.5, 0.3]]))
    assert full[0] < 0.4 and d[2] > full[0] + 0.5


def test_floor_split_is_cached_until_the_map_changes(floor_map):
    a = floor_map.floor_split(1.5)
    assert floor_map.floor_split(1.5) is a
    assert floor_map.floor_split(-2.0) is None  # nothing under the window's bottom layers


@pytest.mark.parametrize("margins", [(0.9, 0.1), (0.5, 0.0), (0.3, 0.25)])
def test_inflation_with_a_floor_is_sound_and_no_worse_than_plain(floor_map, margins):
    m, m_z = margins
    split = floor_map.floor_split(1.5)
    inflated = InflatedField(floor_map, m, split, m_z)
    plain = InflatedField(floor_map, m)
    # every free voxel centre in the middle of the window (the distances there are exact)
    centres = floor_map.voxel_centers().reshape(-1, 3)
    keep = (np.abs(centres[:, 0]) < 1.6) & (np.abs(centres[:, 1]) < 1.6) & (centres[:, 2] > 0.0) & (centres[:, 2] < 2.0)
    P = centres[keep]
    d_full, _ = floor_map.query(P)
    P = P[d_full > 0]
    P = P[np.random.default_rng(0).choice(len(P), 600, replace=False)]
    got, _ = inflated.query(P)
    base, _ = plain.query(P)
    assert np.all(got >= base - 1e-9)
    # exact: floor voxels (all obstacle voxels at or under the top) by m_z, the rest by m
    cells = floor_map.voxel_centers()
    solid = floor_map._occ.solid
    is_floor = cells[..., 2] <= split.top_m + 1e-9
    floor_pts = cells[solid & is_floor & (np.abs(cells[..., 0]) < 3.5) & (np.abs(cells[..., 1]) < 3.5) & (cells[..., 2] > -0.4)]
    rest_pts = cells[solid & ~is_floor]
    near_floor = np.array([np.min(np.linalg.norm(floor_pts - p, axis=1)) for p in P])
    near_rest = np.array([np.min(np.linalg.norm(rest_pts - p, axis=1)) for p in P])
    exact = np.minimum(np.minimum(near_floor, CFG.max_distance_m) - m_z, np.minimum(near_rest, CFG.max_distance_m) - m)
    assert np.all(got <= exact + 1e-6)
    # and tight where the floor binds: over the open floor it is the exact clearance
    floor_binds = np.minimum(near_rest, CFG.max_distance_m) - m > near_floor - m_z + 0.05
    assert floor_binds.sum() >= 15
    np.testing.assert_allclose(got[floor_binds], exact[floor_binds], atol=1e-6)
    assert np.all(got[floor_binds] >= base[floor_binds] + (m - m_z) - 1e-6)


def test_floor_split_rejects_a_bad_height_and_inflation_a_bad_margin(floor_map):
    with pytest.raises(Exception, match="finite"):
        floor_map.floor_split(float("nan"))
    with pytest.raises(Exception, match="floor_margin_m"):
        InflatedField(floor_map, 0.5, floor_map.floor_split(1.5), None)


class _PoleOverFloor:
    """An exact field: the ground plane z = 0 and a vertical pole of radius 0.1 m at (2, 1),
    with the floor kept apart (``floor_split``) on a 0.1 m grid."""

    voxel = 0.1

    def __init__(self) -> None:
        n = (80, 60, 40)
        self.origin = np.array([-20, -30, -5])
        idx = np.stack(np.meshgrid(*(np.arange(k) for k in n), indexing="ij"), axis=-1)
        c = (idx + self.origin + 0.5) * self.voxel
        rest = np.hypot(c[..., 0] - 2.0, c[..., 1] - 1.0) - 0.1
        self.rest = np.clip(rest, 0.0, 1.6).astype(np.float32)

    def query(self, points):
        P = np.asarray(points, float)
        pole = np.hypot(P[:, 0] - 2.0, P[:, 1] - 1.0)
        d_pole = pole - 0.1
        g_pole = np.zeros_like(P)
        g_pole[:, 0] = (P[:, 0] - 2.0) / np.maximum(pole, 1e-9)
        g_pole[:, 1] = (P[:, 1] - 1.0) / np.maximum(pole, 1e-9)
        d = np.minimum(d_pole, P[:, 2])
        g = np.where((P[:, 2] < d_pole)[:, None], np.array([0.0, 0.0, 1.0]), g_pole)
        return np.minimum(d, 1.6), g

    def floor_split(self, below_z_m):
        return FloorSplit(top_m=0.0, rest=self.rest, origin_index=self.origin, voxel_m=self.voxel)


def _pushed_planner(floor_vertical: bool) -> tuple[Planner, float]:
    """A planner whose last plans were flown 0.7 m off sideways (a gust), level in height."""
    pl = Planner(PlannerConfig(floor_vertical_margin=floor_vertical))
    field = _PoleOverFloor()
    p = np.array([0.0, 0.0, 1.4])
    r = pl.step(VehicleState(0.0, p, np.zeros(3), 0.0), p, field)
    t = 0.0
    for _ in range(5):
        t += 0.1
        p_ref = r.trajectory.sample(t)[0]
        r = pl.step(VehicleState(t, p_ref + [0.0, 0.7, 0.0], np.zeros(3), 0.0), p, field)
    return pl, t


@pytest.mark.parametrize("floor_vertical", [True, False])
def test_a_sideways_error_keeps_a_low_goal_over_the_floor_but_not_beside_a_pole(floor_vertical):
    pl, t = _pushed_planner(floor_vertical)
    field = _PoleOverFloor()
    assert pl.tracking_margin_m == pytest.approx(0.7, abs=1e-6)
    assert pl.floor_margin_m == pytest.approx(0.0 if floor_vertical else 0.7, abs=1e-6)
    p = np.array([0.0, 0.7, 1.4])
    low = np.array([1.0, -1.0, 0.8])  # 0.8 m over the floor, 2.2 m from the pole
    r = pl.step(VehicleState(t + 0.1, p, np.zeros(3), 0.0), low, field)
    # d_safe 0.45 + 0.7 = 1.15 m is more than 0.8 m: only a floor with its own margin keeps it
    assert r.goal_adjusted is not floor_vertical
    if floor_vertical:
        np.testing.assert_allclose(r.goal_used, low)
        assert r.floor_margin_m == 0.0 and r.tracking_margin_m == pytest.approx(0.7, abs=1e-6)
    beside = np.array([2.0, 0.2, 1.4])  # 0.7 m from the pole's surface: held off by the full margin
    r = pl.step(VehicleState(t + 0.2, p, np.zeros(3), 0.0), beside, field)
    assert r.goal_adjusted
    d_pole = np.hypot(r.goal_used[0] - 2.0, r.goal_used[1] - 1.0) - 0.1
    assert d_pole >= 0.45 + 0.7 - 0.02
