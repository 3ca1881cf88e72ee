import numpy as np
import pytest

from planning.frames import (
    R_BODY_CAM,
    FrameError,
    body_transform,
    cam_transform_from_body,
    check_rotation,
    check_transform,
    euler_zyx_from_matrix,
    invert_transform,
    make_transform,
    matrix_from_euler_zyx,
    matrix_from_quat,
    quat_from_matrix,
    quat_wxyz_from_xyzw,
    rot_z,
    transform_points,
    unwrap_near,
    wrap_angle,
    yaw_from_matrix,
)


def random_rotation(rng):
    q = rng.normal(size=4)
    return matrix_from_quat(q / np.linalg.norm(q))


def test_wrap_angle_interval_is_half_open():
    assert wrap_angle(np.pi) == pytest.approx(np.pi)
    assert wrap_angle(-np.pi) == pytest.approx(np.pi)
    assert wrap_angle(3 * np.pi) == pytest.approx(np.pi)
    assert wrap_angle(-3 * np.pi / 2) == pytest.approx(np.pi / 2)
    assert wrap_angle(0.0) == 0.0


def test_wrap_angle_vectorized_range_and_equivalence():
    rng = np.random.default_rng(0)
    a = rng.uniform(-50, 50, size=10_000)
    w = wrap_angle(a)
    assert w.shape == a.shape
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    # same angle modulo 2 pi
    assert np.allclose(np.cos(w), np.cos(a)) and np.allclose(np.sin(w), np.sin(a))


def test_unwrap_near_never_jumps():
    ref = 3.0
    target = -3.0  # 0.28 rad away across the seam
    u = unwrap_near(target, ref)
    assert abs(u - ref) < np.pi
    assert u == pytest.approx(2 * np.pi - 3.0)


def test_quaternion_round_trip_and_sign():
    rng = np.random.default_rng(1)
    for _ in range(500):
        R = random_rotation(rng)
        q = quat_from_matrix(R)
        assert q[0] >= 0
        assert np.linalg.norm(q) == pytest.approx(1.0)
        assert np.allclose(matrix_from_quat(q), R, atol=1e-10)


def test_quaternion_known_value_scalar_first():
    # 90 deg about z: (w, x, y, z) = (cos 45, 0, 0, sin 45)
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    assert np.allclose(matrix_from_quat(q), rot_z(np.pi / 2))
    assert np.allclose(matrix_from_quat(q) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(quat_wxyz_from_xyzw([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)]), q)


def test_euler_round_trip():
    rng = np.random.default_rng(2)
    for _ in range(500):
        yaw, pitch, roll = rng.uniform(-np.pi, np.pi), rng.uniform(-1.5, 1.5), rng.uniform(-np.pi, np.pi)
        R = matrix_from_euler_zyx(yaw, pitch, roll)
        y2, p2, r2 = euler_zyx_from_matrix(R)
        assert np.allclose(matrix_from_euler_zyx(y2, p2, r2), R, atol=1e-9)
        assert wrap_angle(y2 - yaw) == pytest.approx(0, abs=1e-9)
        assert yaw_from_matrix(R) == pytest.approx(y2, abs=1e-9)


def test_transform_inverse_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(200):
        T = make_transform(random_rotation(rng), rng.normal(size=3) * 10)
        P = rng.normal(size=(20, 3))
        assert np.allclose(transform_points(invert_transform(T), transform_points(T, P)), P)
        assert np.allclose(invert_transform(T) @ T, np.eye(4))


def test_camera_mount_axes():
    # optical z (forward) is body x, optical x (right) is body -y, optical y (down) is body -z
    assert np.allclose(R_BODY_CAM @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R_BODY_CAM @ [1, 0, 0], [0, -1, 0])
    assert np.allclose(R_BODY_CAM @ [0, 1, 0], [0, 0, -1])
    check_rotation(R_BODY_CAM)
    # a drone at (1, 2, 3) facing north (yaw = pi/2): a point 5 m ahead of the camera is north
    T_wc = cam_transform_from_body(body_transform([1, 2, 3], np.pi / 2))
    assert np.allclose(transform_points(T_wc, [0, 0, 5]), [1, 7, 3])
    # a point right of the image centre is east of it
    assert np.allclose(transform_points(T_wc, [1, 0, 5]), [2, 7, 3])


@pytest.mark.parametrize(
    "T, match",
    [
        (np.full((4, 4), np.nan), "non-finite"),
        (np.eye(3), "shape"),
        (np.diag([1.0, 2.0, 1.0, 1.0]), "orthonormal"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "reflection"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], float), "last row"),
    ],
)
def test_check_transform_rejects_bad_poses(T, match):
    with pytest.raises(FrameError, match=match):
        check_transform(T)


def test_bad_quaternions_rejected():
    with pytest.raises(FrameError, match="zero norm"):
        matrix_from_quat([0, 0, 0, 0])
    with pytest.raises(FrameError, match="not finite"):
        matrix_from_quat([np.nan, 0, 0, 1])
    with pytest.raises(FrameError, match="shape"):
        matrix_from_quat([1, 0, 0])
