"""EsdfMap against exact geometry, plus clearing, rolling, bad input and queries.

Depth is rendered with Open3D's RaycastingScene from unit rays (``t_hit`` is the ray length,
converted to z-depth by the ray's optical z component), and the field is compared with the
scene's exact ``compute_distance`` / ``compute_signed_distance`` on the same meshes.
"""

import dataclasses

import numpy as np
import open3d as o3d
import pytest
import scipy.ndimage as ndi

from planning.camera import CameraError, PinholeCamera
from planning.esdf import DistanceSlice, EsdfError, EsdfMap, EsdfUpdate
from planning.esdf_config import EsdfConfig
from planning.field import DistanceField
from planning.frames import FrameError

CAMERA = PinholeCamera.from_fov(160, 120, 90.0, 60.0)


# -- helpers ---------------------------------------------------------------------------------
def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_cam of an optical camera at ``eye`` looking at ``target`` (z-up world)."""
    eye = np.asarray(eye, dtype=float)
    f = np.asarray(target, dtype=float) - eye
    f /= np.linalg.norm(f)
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(f, x), f, eye
    return T


def render_depth(scene, camera: PinholeCamera, T_world_cam: np.ndarray) -> np.ndarray:
    """z-depth (h, w) float32; misses are inf (no reading)."""
    rays_cam = camera.rays(normalize=True)
    d_world = rays_cam.reshape(-1, 3) @ T_world_cam[:3, :3].T
    rays = np.hstack([np.broadcast_to(T_world_cam[:3, 3], d_world.shape), d_world]).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(camera.height, camera.width)
    return (t_hit * rays_cam[..., 2]).astype(np.float32)


def make_scene(meshes) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    return scene


def box_mesh(size, center, yaw=0.0):
    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(np.asarray(center, dtype=float) - np.asarray(size, dtype=float) / 2)
    m.rotate(o3d.geometry.get_rotation_matrix_from_xyz([0.0, 0.0, yaw]), center=np.asarray(center, dtype=float))
    return m


def ring_views(center, radius, heights, n=8):
    c = np.asarray(center, dtype=float)
    return [
        look_at(c + [radius * np.cos(a), radius * np.sin(a), h], c)
        for h in heights
        for a in np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    ]


def integrate_all(esdf, scene, views, center, camera=CAMERA):
    for T in views:
        esdf.integrate(render_depth(scene, camera, T), camera, T, center_world=center)


def exact(scene, P):
    t = o3d.core.Tensor(P.astype(np.float32))
    sd = scene.compute_signed_distance(t).numpy().astype(float)
    nearest = scene.compute_closest_points(t)["points"].numpy().astype(float)
    return sd, nearest


# The mapping mechanics (exact distances, clearing, rolling) under the optimistic policy, with
# no body sphere (the window centres below are not a vehicle); the default (unknown is an
# obstacle, a body sphere) has its own tests in test_esdf_unknown.py.
SMALL = EsdfConfig(size_m=(4.0, 4.0, 3.0), stride_px=1, unknown_policy="free", body_clear_radius_m=0.0)

BOXES = [
    ((0.6, 0.6, 1.2), (-0.9, -0.8, 0.0), 0.3),
    ((0.5, 0.9, 0.5), (0.9, -0.7, 0.3), 0.0),
    ((0.8, 0.4, 0.8), (0.7, 0.9, -0.2), 1.0),
    ((0.4, 0.4, 0.4), (-0.8, 0.9, 0.5), 0.0),
]


def _geometry_case(name):
    """(meshes, views, window centre, predicate selecting the observed side)."""
    if name == "plane":
        meshes = [box_mesh((20.0, 20.0, 0.2), (0.0, 0.0, -0.1))]
        views = [look_at([2.5 * np.cos(a), 2.5 * np.sin(a), 1.5], [0, 0, 0]) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
        return meshes, views, [0.0, 0.0, 0.5], lambda P: P[:, 2] > 0.0
    if name == "box":
        return [box_mesh((1.0, 1.0, 1.0), (0, 0, 0), 0.5)], ring_views([0, 0, 0], 2.5, [-1.2, 0.0, 1.2]), [0, 0, 0], None
    if name == "sphere":
        return [o3d.geometry.TriangleMesh.create_sphere(0.6, resolution=40)], ring_views([0, 0, 0], 2.5, [-1.2, 0.0, 1.2]), [0, 0, 0], None
    if name == "boxes":
        return [box_mesh(*b) for b in BOXES], ring_views([0, 0, 0], 3.0, [-1.5, 0.0, 1.5], n=12), [0, 0, 0], None
    raise ValueError(name)


# -- exact geometry --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["plane", "box", "sphere", "boxes"])
def test_field_matches_exact_mesh_distance(name):
    meshes, views, center, observed_side = _geometry_case(name)
    scene = make_scene(meshes)
    esdf = EsdfMap(SMALL)
    integrate_all(esdf, scene, views, center)
    rng = np.random.default_rng(7)
    lo, hi = esdf.bounds_world
    P = rng.uniform(lo + 0.05, hi - 0.05, size=(20000, 3))
    if observed_side is not None:
        P = P[observed_side(P)]
    sd, nearest = exact(scene, P)
    dist, grad = esdf.query(P)
    v, clamp = SMALL.voxel_m, SMALL.max_distance_m

    # distance within one voxel away from the surface (both clamped)
    away = sd >= v
    assert away.sum() > 5000
    err = np.abs(np.minimum(dist[away], clamp) - np.minimum(sd[away], clamp))
    assert err.max() <= v, f"{name}: max error {err.max():.3f} m"
    # beyond the clamp the field reads exactly the clamp
    far = sd > clamp + 2 * v  # voxel centres may sit up to half a diagonal closer
    if far.any():
        assert np.median(dist[far]) == np.float32(clamp) and dist[far].min() > clamp - 0.01

    # gradient points away from the nearest obstacle (unit length there)
    sel = (sd > 2 * v) & (sd < clamp - 2 * v)
    if name == "boxes":  # skip points near the medial axis between two boxes
        each = np.stack([make_scene([m]).compute_distance(o3d.core.Tensor(P.astype(np.float32))).numpy() for m in meshes], 1)
        srt = np.sort(each, axis=1)
        sel &= srt[:, 1] - srt[:, 0] > 2 * v
    away_dir = P[sel] - nearest[sel]
    away_dir /= np.linalg.norm(away_dir, axis=1, keepdims=True)
    g = grad[sel]
    gnorm = np.linalg.norm(g, axis=1)
    cos = np.einsum("ij,ij->i", g, away_dir) / gnorm
    assert sel.sum() > 2000
    assert cos.min() > 0.7, f"{name}: worst gradient angle {np.degrees(np.arccos(cos.min())):.0f} deg"
    assert np.median(cos) > 0.98
    assert np.median(gnorm) == pytest.approx(1.0, abs=0.05)


def test_inside_is_negative_with_unknown_as_occupied():
    meshes, views, center, _ = _geometry_case("box")
    scene = make_scene(meshes)
    cfg = EsdfConfig(size_m=(4.0, 4.0, 3.0), stride_px=1, unknown_policy="occupied", body_clear_radius_m=0.0)
    esdf = EsdfMap(cfg)
    integrate_all(esdf, scene, views, center)
    rng = np.random.default_rng(3)
    P = rng.uniform(-0.7, 0.7, size=(20000, 3))
    sd, _ = exact(scene, P)
    inside = sd <= -1.5 * cfg.voxel_m
    assert inside.sum() > 1000
    dist, grad = esdf.query(P[inside])
    assert np.all(dist < 0)
    expected = np.maximum(sd[inside], -cfg.max_inside_distance_m)
    assert np.abs(dist - expected).max() <= cfg.voxel_m
    # outside, unknown-as-occupied is never optimistic: at most one voxel above the truth
    outside = rng.uniform(-1.9, 1.9, size=(20000, 3))
    sd_o, _ = exact(scene, outside)
    d_o, _ = esdf.query(outside[sd_o > 0])
    assert np.all(d_o <= np.minimum(sd_o[sd_o > 0], cfg.max_distance_m) + cfg.voxel_m)


def test_surface_band_makes_thin_shells_negative_with_unknown_as_free():
    scene = make_scene([box_mesh((1.0, 1.0, 1.0), (0, 0, 0))])
    T = look_at([-2.5, 0.0, 0.0], [0, 0, 0])
    plain = EsdfMap(SMALL)
    band = EsdfMap(dataclasses.replace(SMALL, surface_thickness_m=0.3))
    depth = render_depth(scene, CAMERA, T)
    for esdf in (plain, band):
        esdf.integrate(depth, CAMERA, T, center_world=[0, 0, 0])
    # points 0.15-0.25 m behind the seen face (x = -0.5)
    rng = np.random.default_rng(5)
    P = np.column_stack([rng.uniform(-0.35, -0.25, 500), rng.uniform(-0.3, 0.3, 500), rng.uniform(-0.3, 0.3, 500)])
    assert np.all(band.query(P)[0] < 0)
    assert np.all(plain.query(P)[0] > 0)  # unseen interior is free under the free policy


# -- incremental update equals full recompute -------------------------------------------------
def _full_reference(esdf: EsdfMap) -> np.ndarray:
    cfg = esdf.config
    solid = esdf._occ.solid
    outside_solid = cfg.unknown_policy == "occupied"
    padded = np.pad(solid, 1, mode="constant", constant_values=outside_solid)
    d_out = ndi.distance_transform_edt(~padded)[1:-1, 1:-1, 1:-1] * cfg.voxel_m
    d_in = ndi.distance_transform_edt(padded)[1:-1, 1:-1, 1:-1] * cfg.voxel_m
    return np.where(solid, -np.minimum(d_in - cfg.voxel_m, cfg.max_inside_distance_m), np.minimum(d_out, cfg.max_distance_m))


@pytest.mark.parametrize("policy", ["free", "occupied"])
def test_incremental_update_equals_full_recompute_while_moving(policy):
    scene = make_scene([box_mesh(*b) for b in BOXES] + [box_mesh((12.0, 12.0, 0.2), (0.0, 0.0, -1.0))])
    cfg = EsdfConfig(size_m=(3.0, 3.0, 2.0), stride_px=2, unknown_policy=policy)
    esdf = EsdfMap(cfg)
    for k, a in enumerate(np.linspace(0.0, 1.5 * np.pi, 16)):
        eye = [2.2 * np.cos(a), 2.2 * np.sin(a), 0.2 * np.sin(3 * a)]
        T = look_at(eye, [0.0, 0.0, -0.2])
        u = esdf.integrate(render_depth(scene, CAMERA, T), CAMERA, T)
        assert isinstance(u, EsdfUpdate)
        if k % 3 == 2:
            np.testing.assert_allclose(esdf.distance_grid, _full_reference(esdf), atol=1e-5)
    assert u.shift_voxels != (0, 0, 0)


def test_update_reports_changed_box_and_untouched_region():
    scene = make_scene([box_mesh((0.4, 0.4, 0.4), (1.0, 0.0, 0.0))])
    esdf = EsdfMap(SMALL)
    T = look_at([-0.5, 0.0, 0.0], [1.0, 0.0, 0.0])
    u = esdf.integrate(render_depth(scene, CAMERA, T), CAMERA, T, center_world=[0, 0, 0])
    assert u.n_changed_voxels > 0
    lo, hi = np.array(u.changed_box_min_m), np.array(u.changed_box_max_m)
    assert np.all(lo >= [0.7, -0.3, -0.3]) and np.all(hi <= [1.3, 0.3, 0.3])
    assert lo[0] == pytest.approx(0.7, abs=0.11)  # the seen face at x = 0.8
    assert 0 < u.esdf_voxels < np.prod(esdf.shape)
    assert u.total_ms >= u.esdf_ms >= 0.0
    # the same frame again changes nothing
    u2 = esdf.integrate(render_depth(scene, CAMERA, T), CAMERA, T, center_world=[0, 0, 0])
    assert u2.n_changed_voxels == 0 and u2.changed_box_min_m is None and u2.esdf_voxels == 0


# -- free-space clearing ----------------------------------------------------------------------
def test_obstacle_that_moved_away_disappears():
    wall = box_mesh((0.2, 6.0, 4.0), (3.0, 0.0, 0.0))
    obstacle = box_mesh((0.4, 0.4, 0.4), (1.0, 0.0, 0.0))
    cfg = SMALL
    esdf = EsdfMap(cfg)
    T = look_at([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    before = render_depth(make_scene([wall, obstacle]), CAMERA, T)
    after = render_depth(make_scene([wall]), CAMERA, T)
    probe = np.array([[0.82, 0.0, 0.0], [0.82, 0.1, -0.1]])  # on the seen face (x = 0.8)
    for _ in range(5):  # confident obstacle: log-odds at the clamp
        esdf.integrate(before, CAMERA, T, center_world=[0, 0, 0])
    assert np.all(esdf.query(probe)[0] < 0.05)
    n_needed = int(np.ceil((cfg.max_logodds - cfg.occupied_logodds) / -cfg.miss_logodds)) + 1  # float32 rounding
    for k in range(n_needed):
        u = esdf.integrate(after, CAMERA, T, center_world=[0, 0, 0])
        if k < n_needed - 2:
            assert np.all(esdf.query(probe)[0] < 0.05), "cleared faster than the log-odds allow"
    assert u.n_changed_voxels > 0
    d, _ = esdf.query(probe)
    assert np.all(d > 0.6)  # only the wall (1.8+ m away, clamped to 1 m) is left
    occ = esdf.occupied_points()
    assert np.all(occ[:, 0] > 2.8)


def test_readings_beyond_max_range_clear_but_do_not_hit():
    cfg = dataclasses.replace(SMALL, max_range_m=3.0)
    esdf = EsdfMap(cfg)
    near_box = box_mesh((0.4, 0.4, 0.4), (1.0, 0.0, 0.0))
    T = look_at([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    for _ in range(6):
        esdf.integrate(render_depth(make_scene([near_box]), CAMERA, T), CAMERA, T, center_world=[0, 0, 0])
    far_wall = box_mesh((0.2, 40.0, 40.0), (8.0, 0.0, 0.0))  # 9 m away: beyond max range
    depth = render_depth(make_scene([far_wall]), CAMERA, T)
    assert np.isfinite(depth).all() and depth.min() > 3.0
    for _ in range(7):
        u = esdf.integrate(depth, CAMERA, T, center_world=[0, 0, 0])
        assert u.n_points == 0
    assert esdf.occupied_points().shape == (0, 3)
    # inf means no reading: it neither hits nor clears
    esdf2 = EsdfMap(cfg)
    esdf2.integrate(render_depth(make_scene([near_box]), CAMERA, T), CAMERA, T, center_world=[0, 0, 0])
    n_occ = len(esdf2.occupied_points())
    for _ in range(7):
        esdf2.integrate(np.full(CAMERA.shape, np.inf, np.float32), CAMERA, T, center_world=[0, 0, 0])
    assert len(esdf2.occupied_points()) == n_occ > 0


# -- rolling window ---------------------------------------------------------------------------
def test_rolling_window_keeps_obstacles_on_the_lattice_without_smearing():
    scene = make_scene([box_mesh((0.5, 0.5, 0.5), (0.3, 0.2, 0.0), 0.4)])
    cfg = SMALL
    esdf = EsdfMap(cfg)
    integrate_all(esdf, scene, ring_views([0.3, 0.2, 0.0], 1.6, [-0.8, 0.0, 0.8]), [0.0, 0.0, 0.0])
    occ0 = {tuple(p) for p in np.round(esdf.occupied_points() / cfg.voxel_m, 6)}
    rng = np.random.default_rng(11)
    probe = rng.uniform([-0.5, -0.5, -0.5], [1.1, 0.9, 0.5], size=(2000, 3))
    d0, g0 = esdf.query(probe)
    # wander by non-integer offsets that keep the obstacle and the probes >= K voxels inside
    for c in ([0.37, -0.21, 0.13], [0.61, 0.44, -0.09], [-0.26, 0.33, 0.18], [0.05, 0.02, 0.0]):
        shift = esdf.recenter(c)
        assert any(shift)
        occ = {tuple(p) for p in np.round(esdf.occupied_points() / cfg.voxel_m, 6)}
        assert occ == occ0
        d, g = esdf.query(probe)
        np.testing.assert_allclose(d, d0, atol=1e-12)  # same voxels, same values
        np.testing.assert_allclose(g, g0, atol=1e-9)
    # voxel centres stay on the global lattice (index + 0.5) * voxel
    frac = np.array(sorted(occ0)) % 1.0
    np.testing.assert_allclose(frac, 0.5, atol=1e-6)


def test_rolling_window_forgets_what_left_and_recomputes_edges():
    scene = make_scene([box_mesh((0.4, 0.4, 0.4), (1.2, 0.0, 0.0))])
    esdf = EsdfMap(SMALL)
    T = look_at([-0.5, 0.0, 0.0], [1.2, 0.0, 0.0])
    esdf.integrate(render_depth(scene, CAMERA, T), CAMERA, T, center_world=[0, 0, 0])
    assert len(esdf.occupied_points()) > 0
    esdf.recenter([-1.5, 0.0, 0.0])  # window now spans x in [-3.5, 0.5): the box left
    assert len(esdf.occupied_points()) == 0
    np.testing.assert_allclose(esdf.distance_grid, SMALL.max_distance_m)
    esdf.recenter([0.0, 0.0, 0.0])  # back: what left is unknown now
    assert len(esdf.occupied_points()) == 0
    # a jump larger than the window resets
    esdf.integrate(render_depth(scene, CAMERA, T), CAMERA, T, center_world=[0, 0, 0])
    assert esdf.recenter([50.0, 0.0, 0.0]) == (500, 0, 0)
    assert len(esdf.occupied_points()) == 0


def test_window_follows_the_camera_by_default():
    esdf = EsdfMap(SMALL)
    T = look_at([5.03, -2.0, 1.0], [6.0, -2.0, 1.0])
    esdf.integrate(np.zeros(CAMERA.shape, np.float32), CAMERA, T)
    lo, hi = esdf.bounds_world
    np.testing.assert_allclose((lo + hi) / 2, [5.0, -2.0, 1.0], atol=0.051)
    np.testing.assert_allclose(hi - lo, [4.0, 4.0, 3.0])


# -- bad input --------------------------------------------------------------------------------
def test_bad_depth_values_are_ignored():
    scene = make_scene([box_mesh((0.6, 0.6, 0.6), (1.0, 0.2, 0.0), 0.3)])
    T = look_at([-0.8, 0.0, 0.1], [1.0, 0.0, 0.0])
    clean = render_depth(scene, CAMERA, T)
    rng = np.random.default_rng(2)
    bad = rng.random(CAMERA.shape) < 0.3
    noisy = clean.copy()
    noisy[bad] = rng.choice(np.array([0.0, np.nan, np.inf, -np.inf, -1.0, 0.01], np.float32), size=bad.sum())
    dropped = clean.copy()
    dropped[bad] = 0.0
    a, b = EsdfMap(SMALL), EsdfMap(SMALL)
    ua = a.integrate(noisy, CAMERA, T, center_world=[0, 0, 0])
    ub = b.integrate(dropped, CAMERA, T, center_world=[0, 0, 0])
    assert ua.n_points == ub.n_points > 0
    np.testing.assert_array_equal(a.distance_grid, b.distance_grid)
    np.testing.assert_array_equal(a.occupied_points(), b.occupied_points())
    # a frame of nothing but bad values changes nothing
    junk = np.full(CAMERA.shape, np.nan, np.float32)
    junk[::2] = -3.0
    u = a.integrate(junk, CAMERA, T, center_world=[0, 0, 0])
    assert (u.n_points, u.n_changed_voxels) == (0, 0)
    np.testing.assert_array_equal(a.distance_grid, b.distance_grid)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda T: T.__setitem__((0, 3), np.nan), "non-finite"),
        (lambda T: T.__setitem__((1, 1), np.inf), "non-finite"),
        (lambda T: T[:3, :3].__imul__(1.1), "not orthonormal"),
        (lambda T: T.__setitem__((0, 1), 0.3), "not orthonormal"),
        (lambda T: T[:3, 0].__imul__(-1.0), "reflection"),
        (lambda T: T.__setitem__((3, 0), 1.0), "last row"),
    ],
)
def test_bad_poses_are_rejected(mutate, message):
    esdf = EsdfMap(SMALL)
    T = look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    mutate(T)
    with pytest.raises(FrameError, match=message):
        esdf.integrate(np.ones(CAMERA.shape, np.float32), CAMERA, T)
    assert esdf.occupied_points().shape == (0, 3)


def test_bad_shapes_and_types_raise():
    esdf = EsdfMap(SMALL)
    T = np.eye(4)
    with pytest.raises(FrameError, match=r"shape \(4, 4\)"):
        esdf.integrate(np.ones(CAMERA.shape, np.float32), CAMERA, np.eye(3))
    with pytest.raises(CameraError, match="depth_m must have shape"):
        esdf.integrate(np.ones((60, 80), np.float32), CAMERA, T)
    with pytest.raises(EsdfError, match="2-D"):
        esdf.integrate(np.ones((*CAMERA.shape, 3), np.float32), CAMERA, T)
    with pytest.raises(EsdfError, match="PinholeCamera"):
        esdf.integrate(np.ones(CAMERA.shape, np.float32), "cam", T)
    with pytest.raises(EsdfError, match="float z-depth image in metres"):
        esdf.integrate(np.full(CAMERA.shape, "x"), CAMERA, T)
    with pytest.raises(EsdfError, match="center_world"):
        esdf.integrate(np.ones(CAMERA.shape, np.float32), CAMERA, T, center_world=[0.0, np.nan, 0.0])
    with pytest.raises(EsdfError, match=r"shape \(n, 3\)"):
        esdf.query(np.zeros((4, 2)))
    with pytest.raises(EsdfError, match=r"shape \(n, 3\)"):
        esdf.query(np.zeros(3))
    with pytest.raises(EsdfError, match="NaN or inf"):
        esdf.query(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(EsdfError, match="EsdfConfig"):
        EsdfMap({"voxel_m": 0.1})


def test_integer_depth_is_accepted_as_metres():
    scene = make_scene([box_mesh((0.6, 0.6, 0.6), (1.5, 0.0, 0.0))])
    T = look_at([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    depth = render_depth(scene, CAMERA, T).astype(np.float64)
    a, b = EsdfMap(SMALL), EsdfMap(SMALL)
    a.integrate(depth, CAMERA, T)
    b.integrate(depth.astype(np.float32), CAMERA, T)
    np.testing.assert_array_equal(a.distance_grid, b.distance_grid)


# -- queries ----------------------------------------------------------------------------------
def _one_box_map(policy="free"):
    cfg = EsdfConfig(size_m=(4.0, 4.0, 3.0), stride_px=1, unknown_policy=policy)
    esdf = EsdfMap(cfg)
    scene = make_scene([box_mesh((0.6, 0.6, 0.6), (0.5, 0.0, 0.0))])
    integrate_all(esdf, scene, ring_views([0.5, 0.0, 0.0], 1.4, [-0.6, 0.0, 0.6]), [0.0, 0.0, 0.0])
    return esdf


def test_is_a_distance_field_and_gradient_matches_finite_differences():
    esdf = _one_box_map()
    assert isinstance(esdf, DistanceField)
    rng = np.random.default_rng(4)
    P = rng.uniform(-1.5, 1.5, size=(500, 3))
    d, g = esdf.query(P)
    assert d.shape == (500,) and g.shape == (500, 3)
    h = 1e-5
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        fd = (esdf.query(P + e)[0] - esdf.query(P - e)[0]) / (2 * h)
        # piecewise trilinear: equal except at the rare points next to a cell face
        assert np.mean(np.abs(fd - g[:, axis]) < 1e-4) > 0.98
    # trilinear interpolation reproduces the voxel-centre values exactly at the centres
    centres = esdf.voxel_centers()[5:35:7, 5:35:7, 5:25:6].reshape(-1, 3)
    idx = np.floor(centres / esdf.voxel_m).astype(int) - esdf.origin_index
    np.testing.assert_allclose(esdf.query(centres)[0], esdf.distance_grid[tuple(idx.T)], atol=1e-6)
    # small and single-point queries work the same
    d1, g1 = esdf.query(P[:1])
    assert d1.shape == (1,) and d1[0] == d[0] and np.array_equal(g1[0], g[0])


def test_outside_the_grid_free_policy_extends_constantly():
    esdf = _one_box_map("free")
    lo, hi = esdf.bounds_world
    inner = np.array([[hi[0] - 0.05, 0.3, 0.2], [0.2, lo[1] + 0.05, -0.1]])
    outer = inner + np.array([[3.0, 0.0, 0.0], [0.0, -2.0, 0.0]])
    d_in, g_in = esdf.query(inner)
    d_out, g_out = esdf.query(outer)
    np.testing.assert_allclose(d_out, d_in)
    assert g_out[0, 0] == 0.0 and g_out[1, 1] == 0.0
    np.testing.assert_allclose(g_out[0, 1:], g_in[0, 1:])


def test_outside_the_grid_occupied_policy_decreases_outward():
    esdf = _one_box_map("occupied")
    lo, hi = esdf.bounds_world
    edge = np.array([[hi[0] - 0.05, 0.3, 0.2]])
    d_edge, _ = esdf.query(edge)
    for k in (0.5, 1.0, 2.0):
        d, g = esdf.query(edge + [k, 0.0, 0.0])
        assert d[0] == pytest.approx(d_edge[0] - k)
        assert g[0, 0] == pytest.approx(-1.0)
    # the window's faces border obstacles: the edge voxels are within one voxel of them
    assert np.all(esdf.distance_grid[-1] <= esdf.voxel_m + 1e-6)


def test_is_free_occupied_points_slice_and_reset():
    esdf = _one_box_map()
    # on the top face, 0.25 m above it, 1.2 m away
    pts = np.array([[0.5, 0.0, 0.3], [0.5, 0.0, 0.55], [-1.2, 0.0, 0.0]])
    np.testing.assert_array_equal(esdf.is_free(pts), [False, True, True])
    np.testing.assert_array_equal(esdf.is_free(pts, margin_m=0.4), [False, False, True])
    occ = esdf.occupied_points()
    assert occ.shape[1] == 3 and len(occ) > 100
    assert np.all(np.abs(occ - [0.5, 0.0, 0.0]).max(axis=1) <= 0.3 + esdf.voxel_m)
    s = esdf.distance_slice(0.02)
    assert isinstance(s, DistanceSlice)
    assert s.z_m == pytest.approx(0.05)
    assert s.distance_m.shape == (40, 40) and s.x_m.shape == (40,) and s.y_m.shape == (40,)
    i, j = np.argmin(np.abs(s.x_m - 0.25)), np.argmin(np.abs(s.y_m - 0.05))  # face x = 0.2
    assert s.distance_m[i, j] < 0 or s.distance_m[i, j] == pytest.approx(0.0)
    assert s.distance_m.max() == pytest.approx(esdf.config.max_distance_m)
    lo, hi = esdf.bounds_world
    np.testing.assert_allclose(hi - lo, [4.0, 4.0, 3.0])
    esdf.reset()
    assert esdf.occupied_points().shape == (0, 3)
    np.testing.assert_allclose(esdf.distance_grid, esdf.config.max_distance_m)
    np.testing.assert_allclose(esdf.bounds_world[0], lo)
    with pytest.raises(EsdfError, match="finite"):
        esdf.distance_slice(np.nan)


def test_distance_grid_is_read_only():
    esdf = EsdfMap(SMALL)
    with pytest.raises(ValueError, match="read-only"):
        esdf.distance_grid[0, 0, 0] = 1.0
