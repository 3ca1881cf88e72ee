"""NED/FRD <-> ENU/FLU: the only module of OnFly where NED and FRD exist.

MAVLink autopilots (PX4, ArduPilot) express local positions and velocities in NED
(x north, y east, z down) and body quantities in FRD (x forward, y right, z down). OnFly uses
ENU (x east, y north, z up) and FLU (x forward, y left, z up) everywhere else
(:mod:`planning.frames`). Every conversion goes through the functions below; nothing else in
the project may swap axes by hand.

Relations (all exact, all involutions except the yaw map which is its own inverse too):

- vectors: ``enu = (ned_y, ned_x, -ned_z)``, i.e. ``enu = R_ENU_NED @ ned``;
- body vectors: ``flu = (frd_x, -frd_y, -frd_z)``, i.e. ``flu = R_FLU_FRD @ frd``;
- attitude: ``R_enu_flu = R_ENU_NED @ R_ned_frd @ R_FRD_FLU``;
- heading: ``yaw_enu = pi/2 - yaw_ned`` (wrapped to (-pi, pi]);
- yaw rate: ``yaw_rate_enu = -yaw_rate_ned``.

Quaternions are scalar first ``(w, x, y, z)`` as in :mod:`planning.frames` and in MAVLink's
ATTITUDE_QUATERNION (``q1..q4``) and ODOMETRY (``q[0..3]``). All functions are vectorized over
leading dimensions.
"""

from __future__ import annotations

import math

import numpy as np

from planning.frames import FrameError, quat_from_matrix, wrap_angle

__all__ = [
    "EARTH_RADIUS_M",
    "ne_offset_m",
    "R_ENU_NED",
    "R_FLU_FRD",
    "enu_from_ned",
    "ned_from_enu",
    "flu_from_frd",
    "frd_from_flu",
    "yaw_enu_from_ned",
    "yaw_ned_from_enu",
    "yaw_rate_enu_from_ned",
    "yaw_rate_ned_from_enu",
    "matrices_from_quats",
    "matrix_ned_frd_from_euler",
    "matrix_enu_flu_from_quat_ned_frd",
    "matrix_enu_flu_from_euler_ned_frd",
    "yaw_enu_from_quat_ned_frd",
    "euler_rates_from_body_rates",
    "quat_ned_frd_from_matrix_enu_flu",
]

#: Change of basis NED -> ENU (a proper rotation: pi about (1, 1, 0)/sqrt(2)). Symmetric.
R_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Change of basis FRD -> FLU (pi about body x). Symmetric.
R_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def _vectors(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape[-1:] != (3,):
        raise FrameError(f"{name} must have last dimension 3, got shape {a.shape}")
    return a


def enu_from_ned(p_ned) -> np.ndarray:
    """World vectors (positions, velocities, accelerations) from NED to ENU.

    Parameters
    ----------
    p_ned : array (..., 3), NED components (north, east, down)

    Returns
    -------
    array (..., 3), ENU components (east, north, up)
    """
    a = _vectors(p_ned, "p_ned")
    return np.stack([a[..., 1], a[..., 0], -a[..., 2]], axis=-1)


def ned_from_enu(p_enu) -> np.ndarray:
    """World vectors from ENU (..., 3) to NED (..., 3); the inverse of :func:`enu_from_ned`."""
    a = _vectors(p_enu, "p_enu")
    return np.stack([a[..., 1], a[..., 0], -a[..., 2]], axis=-1)


def flu_from_frd(v_frd) -> np.ndarray:
    """Body vectors (rates, velocities) from FRD (..., 3) to FLU (..., 3): ``(x, -y, -z)``."""
    a = _vectors(v_frd, "v_frd")
    return a * np.array([1.0, -1.0, -1.0])


def frd_from_flu(v_flu) -> np.ndarray:
    """Body vectors from FLU (..., 3) to FRD (..., 3); the inverse of :func:`flu_from_frd`."""
    a = _vectors(v_flu, "v_flu")
    return a * np.array([1.0, -1.0, -1.0])


def yaw_enu_from_ned(yaw_ned):
    """Heading from NED (clockwise from north) to ENU (counter-clockwise from east).

    Parameters
    ----------
    yaw_ned : float or array, radians

    Returns
    -------
    float or array, radians wrapped to (-pi, pi]: ``pi/2 - yaw_ned``
    """
    return wrap_angle(np.pi / 2.0 - np.asarray(yaw_ned, dtype=float))


def yaw_ned_from_enu(yaw_enu):
    """Heading from ENU to NED, radians wrapped to (-pi, pi]: ``pi/2 - yaw_enu``."""
    return wrap_angle(np.pi / 2.0 - np.asarray(yaw_enu, dtype=float))


def yaw_rate_enu_from_ned(yaw_rate_ned):
    """Heading rate from NED to ENU (rad/s): the sign flips because the z axes are opposite."""
    r = -np.asarray(yaw_rate_ned, dtype=float)
    return float(r) if r.ndim == 0 else r


def yaw_rate_ned_from_enu(yaw_rate_enu):
    """Heading rate from ENU to NED (rad/s): the same sign flip."""
    return yaw_rate_enu_from_ned(yaw_rate_enu)


def matrices_from_quats(q) -> np.ndarray:
    """Rotation matrices from unit quaternions ``(w, x, y, z)``, normalized first.

    Parameters
    ----------
    q : array (..., 4)

    Returns
    -------
    array (..., 3, 3)

    Raises
    ------
    FrameError
        Wrong last dimension, non-finite entries, or a (near) zero norm.
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1:] != (4,):
        raise FrameError(f"quaternions must have last dimension 4, got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise FrameError("quaternion is not finite")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-9):
        raise FrameError("quaternion has zero norm")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_ned_frd_from_euler(roll, pitch, yaw) -> np.ndarray:
    """``R_ned_frd = Rz(yaw) Ry(pitch) Rx(roll)`` from MAVLink ATTITUDE angles (radians).

    Parameters
    ----------
    roll, pitch, yaw : float or arrays broadcastable to shape (...)

    Returns
    -------
    array (..., 3, 3)
    """
    r, p, y = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (roll, pitch, yaw)))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty(r.shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def matrix_enu_flu_from_quat_ned_frd(q_ned_frd) -> np.ndarray:
    """Body attitude in OnFly frames from a MAVLink attitude quaternion.

    Parameters
    ----------
    q_ned_frd : array (..., 4), ``(w, x, y, z)``, rotates FRD body vectors into NED

    Returns
    -------
    R_enu_flu : array (..., 3, 3), rotates FLU body vectors into ENU
    """
    return R_ENU_NED @ matrices_from_quats(q_ned_frd) @ R_FLU_FRD


def matrix_enu_flu_from_euler_ned_frd(roll, pitch, yaw) -> np.ndarray:
    """Body attitude ``R_enu_flu`` (..., 3, 3) from MAVLink ATTITUDE roll, pitch, yaw (NED/FRD)."""
    return R_ENU_NED @ matrix_ned_frd_from_euler(roll, pitch, yaw) @ R_FLU_FRD


def yaw_enu_from_quat_ned_frd(q_ned_frd):
    """ENU heading of body x (radians, (-pi, pi]) from NED-FRD quaternions (..., 4)."""
    R = matrix_enu_flu_from_quat_ned_frd(q_ned_frd)
    return wrap_angle(np.arctan2(R[..., 1, 0], R[..., 0, 0]))


def euler_rates_from_body_rates(roll, pitch, body_rates):
    """ZYX Euler angle rates from body angular rates (same body convention on both sides).

    ``yaw_dot = (q sin(roll) + r cos(roll)) / cos(pitch)``, and likewise for roll and pitch.
    Near ``|pitch| = pi/2`` the cosine is clamped to 1e-6 so the result stays finite.

    Parameters
    ----------
    roll, pitch : float or array (...), radians
    body_rates : array (..., 3), ``(p, q, r)`` in rad/s about body x, y, z

    Returns
    -------
    array (..., 3): ``(roll_dot, pitch_dot, yaw_dot)`` in rad/s
    """
    w = _vectors(body_rates, "body_rates")
    p, q, r = w[..., 0], w[..., 1], w[..., 2]
    roll = np.asarray(roll, dtype=float)
    pitch = np.asarray(pitch, dtype=float)
    cp = np.cos(pitch)
    cp = np.where(np.abs(cp) < 1e-6, np.copysign(1e-6, cp), cp)
    sr, cr = np.sin(roll), np.cos(roll)
    roll_dot = p + (q * sr + r * cr) * np.tan(pitch)
    pitch_dot = q * cr - r * sr
    yaw_dot = (q * sr + r * cr) / cp
    return np.stack(np.broadcast_arrays(roll_dot, pitch_dot, yaw_dot), axis=-1)


def quat_ned_frd_from_matrix_enu_flu(R_enu_flu) -> np.ndarray:
    """MAVLink attitude quaternion ``(w, x, y, z)`` (FRD -> NED, ``w >= 0``) from ``R_enu_flu`` (3, 3).

    The inverse of :func:`matrix_enu_flu_from_quat_ned_frd` (both basis changes are symmetric
    involutions, so ``R_ned_frd = R_ENU_NED @ R_enu_flu @ R_FLU_FRD``).
    """
    R = np.asarray(R_enu_flu, dtype=float)
    if R.shape != (3, 3):
        raise FrameError(f"R_enu_flu must have shape (3, 3), got {R.shape}")
    return quat_from_matrix(R_ENU_NED @ R @ R_FLU_FRD)


#: PX4 ``lib/geo`` CONSTANTS_RADIUS_OF_EARTH (m): the sphere of the flat-earth projection below.
EARTH_RADIUS_M = 6371000.0


def ne_offset_m(lat_deg: float, lon_deg: float, lat0_deg: float, lon0_deg: float) -> tuple[float, float]:
    """North and east offset (m) of ``(lat, lon)`` from the reference ``(lat0, lon0)`` (degrees)
    on the plane tangent at the reference, the flat-earth projection of PX4's map projection and
    ArduPilot's ``Location`` offsets over the few hundred metres a scene spans. The one
    lat/lon -> metres rule of the simulated autopilot (positions, fences, rally points)."""
    n = math.radians(lat_deg - lat0_deg) * EARTH_RADIUS_M
    e = math.radians(lon_deg - lon0_deg) * EARTH_RADIUS_M * math.cos(math.radians(lat0_deg))
    return n, e
