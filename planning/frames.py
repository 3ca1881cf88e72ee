"""Frame conventions, in one place.

Every other module calls these functions instead of re-deriving a convention.

Conventions
-----------
- World frame: ENU (x east, y north, z up), metres.
- Body frame: FLU (x forward, y left, z up).
- Camera optical frame: x right, y down, z forward (OpenCV / pinhole convention).
- Angles in radians; :func:`wrap_angle` maps to the half-open interval (-pi, pi].
- Quaternions are **scalar first**: ``q = (w, x, y, z)``, unit norm, Hamilton product,
  active rotation (``R @ v`` rotates a vector ``v``). TUM files store ``qx qy qz qw``;
  use :func:`quat_wxyz_from_xyzw` when reading them.
- Transforms are 4x4 homogeneous matrices named ``T_<to>_<from>``: ``T_world_cam`` maps
  points expressed in the camera frame into the world frame, ``p_world = T_world_cam @ p_cam``.
- Euler angles, where used, are ZYX (yaw about z, then pitch about the new y, then roll about
  the new x): ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
- NED/FRD exist only inside the MAVLink bridge (``onfly.mavlink.frames``).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "R_BODY_CAM",
    "T_BODY_CAM",
    "FrameError",
    "wrap_angle",
    "unwrap_near",
    "rot_x",
    "rot_y",
    "rot_z",
    "matrix_from_euler_zyx",
    "euler_zyx_from_matrix",
    "yaw_from_matrix",
    "matrix_from_quat",
    "quat_from_matrix",
    "quat_wxyz_from_xyzw",
    "check_rotation",
    "check_transform",
    "make_transform",
    "invert_transform",
    "transform_points",
    "body_transform",
    "cam_transform_from_body",
]


class FrameError(ValueError):
    """A rotation, quaternion or transform that is not what it claims to be."""


#: Rotation taking camera-optical vectors into the body FLU frame for a forward-looking,
#: level camera: optical z (forward) -> body x, optical x (right) -> body -y,
#: optical y (down) -> body -z. Columns are the optical axes expressed in the body frame.
R_BODY_CAM = np.array(
    [
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
    ]
)
#: Default camera mount: at the body origin, looking forward, level.
T_BODY_CAM = np.eye(4)
T_BODY_CAM[:3, :3] = R_BODY_CAM

_ORTHO_TOL = 1e-5


def wrap_angle(angle):
    """Wrap angles to (-pi, pi].

    Parameters
    ----------
    angle : float or array, radians

    Returns
    -------
    float or array of the same shape, radians in (-pi, pi]. ``-pi`` maps to ``+pi``.
    """
    a = np.asarray(angle, dtype=float)
    w = np.pi - np.mod(np.pi - a, 2.0 * np.pi)
    if np.ndim(w) == 0:
        return float(w)
    return w


def unwrap_near(angle, reference):
    """The representative of ``angle`` (mod 2 pi) closest to ``reference``.

    Used to express a yaw target relative to the current yaw so a cost never sees a 2 pi jump:
    ``reference + wrap_angle(angle - reference)``.
    """
    return np.asarray(reference, dtype=float) + wrap_angle(np.asarray(angle) - reference)


def rot_x(angle: float) -> np.ndarray:
    """Active rotation about x by ``angle`` radians, shape (3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    """Active rotation about y by ``angle`` radians, shape (3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> np.ndarray:
    """Active rotation about z by ``angle`` radians, shape (3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def matrix_from_euler_zyx(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``, shape (3, 3)."""
    return rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def euler_zyx_from_matrix(R) -> tuple[float, float, float]:
    """Inverse of :func:`matrix_from_euler_zyx`: ``(yaw, pitch, roll)`` in radians.

    At gimbal lock (|pitch| = pi/2) roll is set to 0 and the whole rotation about z goes to yaw.
    """
    R = check_rotation(R)
    pitch = float(np.arcsin(np.clip(-R[2, 0], -1.0, 1.0)))
    if abs(R[2, 0]) < 1.0 - 1e-9:
        yaw = float(np.arctan2(R[1, 0], R[0, 0]))
        roll = float(np.arctan2(R[2, 1], R[2, 2]))
    else:
        yaw = float(np.arctan2(-R[0, 1], R[1, 1]))
        roll = 0.0
    return wrap_angle(yaw), pitch, wrap_angle(roll)


def yaw_from_matrix(R) -> float:
    """Heading of the body x axis projected on the world xy-plane, radians in (-pi, pi]."""
    R = np.asarray(R, dtype=float)
    return wrap_angle(float(np.arctan2(R[1, 0], R[0, 0])))


def matrix_from_quat(q) -> np.ndarray:
    """Rotation matrix from a quaternion ``(w, x, y, z)``; normalized first.

    Raises
    ------
    FrameError
        If ``q`` is not shape (4,), is not finite, or has (near) zero norm.
    """
    q = np.asarray(q, dtype=float)
    if q.shape != (4,):
        raise FrameError(f"quaternion must have shape (4,), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise FrameError(f"quaternion is not finite: {q}")
    n = np.linalg.norm(q)
    if n < 1e-9:
        raise FrameError("quaternion has zero norm")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_from_matrix(R) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` with ``w >= 0`` from a rotation matrix (Shepperd's method)."""
    R = check_rotation(R)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def quat_wxyz_from_xyzw(q_xyzw) -> np.ndarray:
    """Reorder a scalar-last quaternion (TUM, ROS, scipy) to our scalar-first order."""
    q = np.asarray(q_xyzw, dtype=float)
    if q.shape[-1] != 4:
        raise FrameError(f"quaternion must have last dimension 4, got shape {q.shape}")
    return q[..., [3, 0, 1, 2]]


def check_rotation(R, name: str = "rotation") -> np.ndarray:
    """Coerce to a (3, 3) float array and check it is a proper rotation.

    Raises
    ------
    FrameError
        Wrong shape, non-finite entries, ``R^T R != I`` beyond 1e-5, or ``det(R) != +1``.
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise FrameError(f"{name} must have shape (3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise FrameError(f"{name} has non-finite entries")
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > _ORTHO_TOL:
        raise FrameError(f"{name} is not orthonormal (max |R^T R - I| = {err:.2e})")
    if np.linalg.det(R) < 0:
        raise FrameError(f"{name} is a reflection (det = -1), not a rotation")
    return R


def check_transform(T, name: str = "transform") -> np.ndarray:
    """Coerce to a (4, 4) float array and check it is a rigid transform.

    Raises
    ------
    FrameError
        Wrong shape, NaN/inf, a rotation block that is not a rotation, or a last row
        other than ``[0, 0, 0, 1]``.
    """
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise FrameError(f"{name} must have shape (4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise FrameError(f"{name} has non-finite entries")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise FrameError(f"{name} last row must be [0, 0, 0, 1], got {T[3]}")
    check_rotation(T[:3, :3], name=f"{name} rotation block")
    return T


def make_transform(R, p) -> np.ndarray:
    """4x4 transform from a rotation (3, 3) and a translation (3,) in metres."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(p, dtype=float).reshape(3)
    return T


def invert_transform(T) -> np.ndarray:
    """Inverse of a rigid transform without a general matrix inverse: ``T_b_a`` from ``T_a_b``."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T, P) -> np.ndarray:
    """Apply ``T`` (4, 4) to points ``P`` of shape (n, 3) or (3,); returns the same shape."""
    T = np.asarray(T, dtype=float)
    P = np.asarray(P, dtype=float)
    if P.shape[-1] != 3:
        raise FrameError(f"points must have last dimension 3, got shape {P.shape}")
    return P @ T[:3, :3].T + T[:3, 3]


def body_transform(p_world, yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """``T_world_body`` from an ENU position (3,) in metres and ZYX Euler angles in radians."""
    return make_transform(matrix_from_euler_zyx(yaw, pitch, roll), p_world)


def cam_transform_from_body(T_world_body, T_body_cam=T_BODY_CAM) -> np.ndarray:
    """``T_world_cam = T_world_body @ T_body_cam`` (camera mount defaults to :data:`T_BODY_CAM`)."""
    return np.asarray(T_world_body, dtype=float) @ np.asarray(T_body_cam, dtype=float)
