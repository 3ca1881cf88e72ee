import numpy as np
import pytest

from planning.camera import CameraError, PinholeCamera


def test_paper_camera_fov():
    cam = PinholeCamera.from_fov(640, 427, 90.0, 60.0)
    assert np.rad2deg(cam.hfov_rad) == pytest.approx(90.0)
    assert np.rad2deg(cam.vfov_rad) == pytest.approx(60.0)
    assert cam.fx == pytest.approx(320.0)
    assert cam.shape == (427, 640)


def test_known_projection():
    cam = PinholeCamera(640, 480, 585.0, 585.0, 320.0, 240.0)
    uv, ok = cam.project([0.0, 0.0, 2.0])
    assert ok and np.allclose(uv, [320, 240])
    uv, ok = cam.project([1.0, -0.5, 2.0])
    assert np.allclose(uv, [320 + 585 * 0.5, 240 - 585 * 0.25])


def test_project_back_project_round_trip():
    rng = np.random.default_rng(0)
    cam = PinholeCamera.from_fov(320, 240, 90, 60)
    P = np.column_stack([rng.uniform(-3, 3, 1000), rng.uniform(-2, 2, 1000), rng.uniform(0.1, 20, 1000)])
    uv, ok = cam.project(P)
    assert ok.all()
    assert np.allclose(cam.back_project(uv, P[:, 2]), P)
    uv2 = np.column_stack([rng.uniform(0, 319, 100), rng.uniform(0, 239, 100)])
    d = rng.uniform(0.5, 9, 100)
    uv3, _ = cam.project(cam.back_project(uv2, d))
    assert np.allclose(uv3, uv2)


def test_points_behind_camera_are_flagged():
    cam = PinholeCamera.from_fov(64, 48)
    uv, ok = cam.project(np.array([[0, 0, -1.0], [0, 0, 0.0], [0, 0, 1.0]]))
    assert list(ok) == [False, False, True]
    assert np.isnan(uv[:2]).all()
    assert not cam.in_image(uv[:2]).any()


def test_rays_and_depth_to_points_ignore_bad_readings():
    cam = PinholeCamera(4, 3, 2.0, 2.0, 1.5, 1.0)
    rays = cam.rays()
    assert rays.shape == (3, 4, 3)
    assert np.allclose(rays[..., 2], 1.0)
    assert np.allclose(np.linalg.norm(cam.rays(normalize=True), axis=-1), 1.0)
    depth = np.full((3, 4), 2.0, np.float32)
    depth[0, 0] = np.nan
    depth[0, 1] = 0.0
    depth[0, 2] = np.inf
    depth[0, 3] = -1.0
    P, valid = cam.depth_to_points(depth)
    assert P.shape == (8, 3) and valid.sum() == 8
    assert np.allclose(P[:, 2], 2.0)
    with pytest.raises(CameraError, match=r"depth must have shape \(3, 4"):
        cam.depth_to_points(np.zeros((4, 3)))


def test_in_image_edges():
    cam = PinholeCamera.from_fov(10, 10)
    uv = np.array([[-0.5, 0], [-0.51, 0], [9.49, 9.49], [9.5, 0]])
    assert list(cam.in_image(uv)) == [True, False, True, False]


def test_invalid_intrinsics():
    with pytest.raises(CameraError, match="positive"):
        PinholeCamera(0, 10, 1, 1, 0, 0)
    with pytest.raises(CameraError, match="focal"):
        PinholeCamera(10, 10, -1, 1, 0, 0)
    with pytest.raises(CameraError, match="finite"):
        PinholeCamera(10, 10, np.nan, 1, 0, 0)


def test_scaled_keeps_fov():
    cam = PinholeCamera.from_fov(640, 480, 90, 60)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    assert half.hfov_rad == pytest.approx(cam.hfov_rad)
    # the same 3D point lands at half the (pixel-centre corrected) coordinates
    uv, _ = cam.project([0.3, 0.2, 2.0])
    uvh, _ = half.project([0.3, 0.2, 2.0])
    assert np.allclose((uvh + 0.5), (uv + 0.5) / 2)
