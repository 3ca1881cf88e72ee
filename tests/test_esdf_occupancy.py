"""RollingOccupancy: hits, misses, log-odds schedule, window shifts."""

import numpy as np
import pytest

from planning.camera import PinholeCamera
from planning.esdf_config import EsdfConfig
from planning.esdf_occupancy import RollingOccupancy, shift_array

CAMERA = PinholeCamera.from_fov(64, 48, 90.0, 60.0)
# optical z along world +x, optical x along world -y, optical y along world -z
T_LOOK_X = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def _grid(**kw) -> RollingOccupancy:
    """The mechanics under the optimistic policy without a body sphere unless asked."""
    kw = {"unknown_policy": "free", "body_clear_radius_m": 0.0, **kw}
    occ = RollingOccupancy(EsdfConfig(size_m=(4.0, 4.0, 2.0), stride_px=1, **kw))
    occ.shift_to(occ.origin_for_center([0.0, 0.0, 0.0]))
    return occ


def _wall(depth_m: float) -> np.ndarray:
    return np.full(CAMERA.shape, depth_m, dtype=np.float32)


def _state_at(occ, p):
    i = np.floor(np.asarray(p) / occ.voxel_m).astype(int) - occ.origin_index
    return occ.logodds[tuple(i)], occ.observed[tuple(i)], occ.solid[tuple(i)]


def test_shift_array_moves_content_and_fills():
    a = np.arange(24).reshape(2, 3, 4)
    b = shift_array(a, np.array([0, 1, -1]), -1)
    assert b[0, 0, 1] == a[0, 1, 0] and b[1, 1, 3] == a[1, 2, 2]
    assert np.all(b[:, 2, :] == -1) and np.all(b[:, :, 0] == -1)
    np.testing.assert_array_equal(shift_array(a, np.zeros(3, int), 0), a)



def test_shift_array_by_more_than_the_window_is_all_fill():
    # regression: a first frame far from the map's initial origin shifted by more than the
    # window and numpy failed to broadcast (found by the benchmark oracle)
    a = np.arange(24, dtype=float).reshape(2, 3, 4)
    for shift in ([5, 0, 0], [0, -3, 0], [0, 0, 4], [-7, 9, 1]):
        np.testing.assert_array_equal(shift_array(a, np.array(shift), -1.0), np.full(a.shape, -1.0))

def test_origin_puts_centre_in_middle_voxel():
    occ = RollingOccupancy(EsdfConfig(size_m=(4.0, 4.0, 2.0)))
    o = occ.origin_for_center([1.234, -0.55, 0.05])
    np.testing.assert_array_equal(o + np.array(occ.shape) // 2, [12, -6, 0])


def test_one_frame_of_hits_occupies_the_wall_once_per_voxel():
    occ = _grid()
    delta = occ.integrate(_wall(1.53), CAMERA, T_LOOK_X)
    assert delta.n_points == CAMERA.width * CAMERA.height
    lo, obs, solid = _state_at(occ, [1.55, 0.0, 0.0])
    # many pixels fall in this voxel, but a frame adds one hit
    assert lo == pytest.approx(occ.config.hit_logodds) and obs and solid
    # nothing in front of the wall is occupied, nothing behind it observed
    assert not _state_at(occ, [1.0, 0.0, 0.0])[2]
    assert not _state_at(occ, [1.75, 0.0, 0.0])[1]
    assert len(delta.flipped) == delta.n_hit_voxels > 0


def test_miss_schedule_and_hit_wins():
    cfg = EsdfConfig(size_m=(4.0, 4.0, 2.0), stride_px=1)
    occ = _grid()
    for _ in range(4):
        occ.integrate(_wall(1.05), CAMERA, T_LOOK_X)
    p = [1.05, 0.0, 0.0]
    assert _state_at(occ, p)[0] == pytest.approx(cfg.max_logodds)
    frames = 0
    while _state_at(occ, p)[2]:
        occ.integrate(_wall(1.8), CAMERA, T_LOOK_X)
        frames += 1
        assert frames < 10
    assert frames == 6  # documented in EsdfConfig: 2.0 - 5 * 0.4 is still > 0 in float32
    assert _state_at(occ, [1.85, 0.0, 0.0])[2]


def test_dead_zone_and_far_readings():
    occ = _grid(min_range_m=0.5, max_range_m=1.5)
    d = occ.integrate(_wall(0.3), CAMERA, T_LOOK_X)
    assert d.n_points == 0 and d.n_hit_voxels == 0
    d = occ.integrate(_wall(1.6), CAMERA, T_LOOK_X)
    assert d.n_points == 0 and d.n_hit_voxels == 0


def test_unknown_as_occupied_marks_seen_free_space():
    occ = _grid(unknown_policy="occupied")
    assert occ.solid.all()
    d = occ.integrate(_wall(1.55), CAMERA, T_LOOK_X)
    # in front of the wall (beyond the clear margin): observed free
    lo, obs, solid = _state_at(occ, [1.0, 0.0, 0.0])
    assert obs and not solid and lo == pytest.approx(occ.config.miss_logodds)
    # the wall itself occupied, behind it still unknown (solid)
    assert _state_at(occ, [1.55, 0.0, 0.0])[2]
    lo, obs, solid = _state_at(occ, [1.85, 0.0, 0.0])
    assert not obs and solid
    # behind the camera: never in view
    assert not _state_at(occ, [-0.5, 0.0, 0.0])[1]
    assert d.n_miss_voxels > 1000


def test_shift_reports_slabs_and_resets_on_large_jumps():
    occ = _grid()
    occ.integrate(_wall(1.55), CAMERA, T_LOOK_X)
    before = occ.solid.copy()
    shift, boxes = occ.shift_to(occ.origin_index + [2, 0, -1])
    np.testing.assert_array_equal(shift, [2, 0, -1])
    np.testing.assert_array_equal(occ.solid[:-2, :, 1:], before[2:, :, :-1])
    assert not occ.solid[-2:].any() and not occ.observed[-2:].any()
    nx, ny, nz = occ.shape
    assert ((nx - 2, 0, 0), (nx, ny, nz)) in boxes  # entering along x
    assert ((0, 0, 0), (1, ny, nz)) in boxes  # leaving face along x
    assert ((0, 0, 0), (nx, ny, 1)) in boxes  # entering along -z
    assert ((0, 0, nz - 1), (nx, ny, nz)) in boxes  # leaving face along -z
    shift, boxes = occ.shift_to(occ.origin_index + [nx, 0, 0])
    assert boxes == [((0, 0, 0), (nx, ny, nz))] and not occ.observed.any()
    assert occ.shift_to(occ.origin_index)[1] == []


def test_hit_wins_over_miss_in_the_same_frame():
    occ = _grid()
    occ.integrate(_wall(1.05), CAMERA, T_LOOK_X)  # solid now, so a candidate for clearing
    depth = _wall(1.8)
    depth[:, :33] = 1.05  # image columns 0..32 see a near wall (world y > -0.02)
    occ.integrate(depth, CAMERA, T_LOOK_X)
    # voxel x in [1.0, 1.1), y in [-0.1, 0): column 32 lands in it, but its centre projects to
    # column 33, which sees 1.8 m -> it is both hit and seen through: one hit, no miss
    p = [1.05, -0.05, 0.05]
    uv, _ = CAMERA.project(np.array([0.05, -0.05, 1.05]))
    assert int(np.floor(uv[0] + 0.5)) == 33
    lo, obs, solid = _state_at(occ, p)
    assert lo == pytest.approx(2 * occ.config.hit_logodds) and solid
    # its neighbour at y in [-0.2, -0.1) is only seen through
    assert _state_at(occ, [1.05, -0.15, 0.05])[0] == pytest.approx(occ.config.hit_logodds + occ.config.miss_logodds)


def test_frustum_block_cull_never_drops_a_voxel_that_would_be_cleared(monkeypatch):
    """Clearing with the block cull equals clearing without it, for tilted and rolled cameras."""
    from planning.frames import body_transform, cam_transform_from_body

    cam = PinholeCamera.from_fov(96, 64, 90.0, 60.0)
    cfg = EsdfConfig(size_m=(8.0, 8.0, 4.0), stride_px=2)  # the default policy: unknown is solid
    rng = np.random.default_rng(5)
    for _ in range(6):
        T = cam_transform_from_body(body_transform(rng.uniform(-0.5, 0.5, 3), rng.uniform(-np.pi, np.pi)))
        tilt = np.eye(4)  # pitch and roll the camera by up to 0.5 rad
        a, b = rng.uniform(-0.5, 0.5, 2)
        tilt[:3, :3] = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]) @ np.array(
            [[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]]
        )
        T = T @ tilt
        depth = rng.uniform(0.5, 9.0, cam.shape).astype(np.float32)
        depth[rng.random(cam.shape) < 0.3] = 0.0
        occ = RollingOccupancy(cfg)
        occ.shift_to(occ.origin_for_center(T[:3, 3]))
        culled = np.sort(occ._miss_voxels(depth, cam, T, occ._scratch))
        with monkeypatch.context() as m:
            m.setattr(RollingOccupancy, "_frustum_blocks", lambda self, c, t, box, reach=None: np.ones(tuple(np.subtract(box[1], box[0])), bool))
            full = np.sort(occ._miss_voxels(depth, cam, T, occ._scratch))
        assert culled.size > 100
        np.testing.assert_array_equal(culled, full)
