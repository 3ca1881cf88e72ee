"""NED/FRD <-> ENU/FLU conversions: exact references, round trips, and real PX4 / ArduPilot
telemetry checked against an independent route (scipy rotations built from axis-angle, never
our own functions)."""


import numpy as np
import pytest
from pymavlink import mavutil
from pyulog import ULog
from scipy.spatial.transform import Rotation

from onfly.mavlink import frames
from planning.frames import FrameError, wrap_angle
from realdata_paths import REALDATA

REALDATA = REALDATA / "mavlink"

# Independent route: NED -> ENU is a rotation by pi about (1, 1, 0)/sqrt(2); FRD -> FLU by pi about x.
ROT_ENU_NED = Rotation.from_rotvec(np.pi * np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0))
ROT_FLU_FRD = Rotation.from_rotvec([np.pi, 0.0, 0.0])


def independent_yaw_enu_from_heading_ned(heading_ned):
    """Rotate the NED heading vector into ENU with scipy and read its angle from east."""
    h = np.asarray(heading_ned, dtype=float)
    d_ned = np.stack([np.cos(h), np.sin(h), np.zeros_like(h)], axis=-1)
    d_enu = ROT_ENU_NED.apply(d_ned)
    return np.arctan2(d_enu[:, 1], d_enu[:, 0])


def independent_R_enu_flu(q_wxyz):
    """scipy: R_enu_flu = R_enu_ned * R_ned_frd * R_frd_flu from scalar-first quaternions."""
    q = np.asarray(q_wxyz, dtype=float)
    R_ned_frd = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    return (ROT_ENU_NED * R_ned_frd * ROT_FLU_FRD.inv()).as_matrix()


def angle_diff(a, b):
    return np.abs(wrap_angle(np.asarray(a) - np.asarray(b)))


# -- exact references ------------------------------------------------------------------------
def test_enu_from_ned_exact_and_vectorized():
    assert np.array_equal(frames.enu_from_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    assert np.array_equal(frames.ned_from_enu([2.0, 1.0, -3.0]), [1.0, 2.0, 3.0])
    rng = np.random.default_rng(0)
    P = rng.normal(size=(4, 5, 3))
    assert frames.enu_from_ned(P).shape == (4, 5, 3)
    np.testing.assert_array_equal(frames.ned_from_enu(frames.enu_from_ned(P)), P)
    np.testing.assert_allclose(frames.enu_from_ned(P.reshape(-1, 3)), ROT_ENU_NED.apply(P.reshape(-1, 3)), atol=1e-12)
    np.testing.assert_allclose(frames.R_ENU_NED, ROT_ENU_NED.as_matrix(), atol=1e-12)
    assert np.linalg.det(frames.R_ENU_NED) == pytest.approx(1.0)


def test_flu_from_frd_exact_and_round_trip():
    assert np.array_equal(frames.flu_from_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    rng = np.random.default_rng(1)
    W = rng.normal(size=(10, 3))
    np.testing.assert_array_equal(frames.frd_from_flu(frames.flu_from_frd(W)), W)
    np.testing.assert_allclose(frames.flu_from_frd(W), ROT_FLU_FRD.apply(W), atol=1e-12)


@pytest.mark.parametrize(
    "yaw_ned, yaw_enu",
    [(0.0, np.pi / 2), (np.pi / 2, 0.0), (np.pi, -np.pi / 2), (-np.pi / 2, np.pi), (np.pi / 4, np.pi / 4)],
)
def test_yaw_enu_from_ned_references(yaw_ned, yaw_enu):
    assert frames.yaw_enu_from_ned(yaw_ned) == pytest.approx(yaw_enu)
    assert angle_diff(frames.yaw_ned_from_enu(yaw_enu), yaw_ned) < 1e-12


def test_yaw_maps_are_wrapped_and_vectorized():
    rng = np.random.default_rng(2)
    y = rng.uniform(-10, 10, size=100)
    out = frames.yaw_enu_from_ned(y)
    assert out.shape == (100,) and np.all(out > -np.pi) and np.all(out <= np.pi)
    assert np.max(angle_diff(frames.yaw_ned_from_enu(out), y)) < 1e-9
    assert frames.yaw_rate_enu_from_ned(0.3) == -0.3
    assert frames.yaw_rate_ned_from_enu(frames.yaw_rate_enu_from_ned(0.3)) == 0.3  # a round trip


def test_identity_attitude_is_nose_north_level():
    R = frames.matrix_enu_flu_from_quat_ned_frd([1.0, 0.0, 0.0, 0.0])
    # body forward -> north (ENU y), body left -> west (-x), body up -> up
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert frames.yaw_enu_from_quat_ned_frd([1.0, 0.0, 0.0, 0.0]) == pytest.approx(np.pi / 2)


def test_quaternion_and_euler_routes_agree_with_scipy():
    rng = np.random.default_rng(3)
    n = 200
    roll, pitch, yaw = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n), rng.uniform(-np.pi, np.pi, n)
    q_xyzw = Rotation.from_euler("ZYX", np.column_stack([yaw, pitch, roll])).as_quat()
    q = q_xyzw[:, [3, 0, 1, 2]]
    R_q = frames.matrix_enu_flu_from_quat_ned_frd(q)
    R_e = frames.matrix_enu_flu_from_euler_ned_frd(roll, pitch, yaw)
    np.testing.assert_allclose(R_q, independent_R_enu_flu(q), atol=1e-12)
    np.testing.assert_allclose(R_e, R_q, atol=1e-12)
    assert np.max(angle_diff(frames.yaw_enu_from_quat_ned_frd(q), frames.yaw_enu_from_ned(yaw))) < 1e-9
    for R in R_q[:5]:
        q_back = frames.quat_ned_frd_from_matrix_enu_flu(R)
        np.testing.assert_allclose(frames.matrix_enu_flu_from_quat_ned_frd(q_back), R, atol=1e-12)


def test_euler_rates_match_finite_differences():
    rng = np.random.default_rng(4)
    roll, pitch, yaw = 0.3, -0.2, 1.0
    w = rng.normal(size=3) * 0.5
    R0 = Rotation.from_euler("ZYX", [yaw, pitch, roll])
    h = 1e-6
    R1 = R0 * Rotation.from_rotvec(w * h)  # body rates: right-multiplied
    y1, p1, r1 = R1.as_euler("ZYX")
    numeric = np.array([r1 - roll, p1 - pitch, y1 - yaw]) / h
    np.testing.assert_allclose(frames.euler_rates_from_body_rates(roll, pitch, w), numeric, rtol=1e-4, atol=1e-6)


def test_bad_inputs_raise_frame_error():
    with pytest.raises(FrameError, match="last dimension 3"):
        frames.enu_from_ned([1.0, 2.0])
    with pytest.raises(FrameError, match="zero norm"):
        frames.matrices_from_quats([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(FrameError, match="not finite"):
        frames.matrices_from_quats([np.nan, 0.0, 0.0, 1.0])
    with pytest.raises(FrameError, match="last dimension 4"):
        frames.matrix_enu_flu_from_quat_ned_frd(np.ones((2, 3)))


# -- real telemetry --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ulog():
    log = ULog(str(REALDATA / "sample.ulg"), ["vehicle_local_position", "vehicle_attitude"])
    return {d.name: d.data for d in log.data_list}


def test_px4_ulog_positions_velocities_headings_to_enu(ulog):
    lp = ulog["vehicle_local_position"]
    assert len(lp["timestamp"]) == 678
    P_ned = np.column_stack([lp["x"], lp["y"], lp["z"]]).astype(float)
    V_ned = np.column_stack([lp["vx"], lp["vy"], lp["vz"]]).astype(float)
    heading = np.asarray(lp["heading"] if "heading" in lp else lp["yaw"], dtype=float)
    ok = np.all(np.isfinite(P_ned), axis=1) & np.all(np.isfinite(V_ned), axis=1) & np.isfinite(heading)
    assert ok.sum() > 600
    P_ned, V_ned, heading = P_ned[ok], V_ned[ok], heading[ok]
    np.testing.assert_allclose(frames.enu_from_ned(P_ned), ROT_ENU_NED.apply(P_ned), atol=1e-9)
    np.testing.assert_allclose(frames.enu_from_ned(V_ned), ROT_ENU_NED.apply(V_ned), atol=1e-9)
    assert np.max(angle_diff(frames.yaw_enu_from_ned(heading), independent_yaw_enu_from_heading_ned(heading))) < 1e-9
    # This log is a bench session (x = y = 0, z_ned ~ +0.1 m, heading swept by hand): the ENU
    # altitude is the negated down coordinate and the heading moved through ~0.5 rad.
    np.testing.assert_array_equal(frames.enu_from_ned(P_ned)[:, 2], -P_ned[:, 2])
    assert np.ptp(frames.yaw_enu_from_ned(heading)) > 0.4


def test_px4_ulog_attitude_heading_matches_estimator_heading(ulog):
    att, lp = ulog["vehicle_attitude"], ulog["vehicle_local_position"]
    q = np.column_stack([att[f"q[{i}]"] for i in range(4)]).astype(float)
    assert q.shape[0] == 6461
    R_ours = frames.matrix_enu_flu_from_quat_ned_frd(q)
    np.testing.assert_allclose(R_ours, independent_R_enu_flu(q), atol=1e-6)
    yaw_att = frames.yaw_enu_from_quat_ned_frd(q)
    # Cross-source: the attitude quaternion's heading vs the local-position heading (same EKF,
    # different topic), matched by nearest timestamp.
    heading = np.asarray(lp["heading"] if "heading" in lp else lp["yaw"], dtype=float)
    idx = np.clip(np.searchsorted(att["timestamp"], lp["timestamp"]), 0, len(att["timestamp"]) - 1)
    d = angle_diff(yaw_att[idx], frames.yaw_enu_from_ned(heading))
    d = d[np.isfinite(d)]
    assert np.median(d) < 0.02 and np.percentile(d, 95) < 0.1


@pytest.fixture(scope="module")
def tlog():
    conn = mavutil.mavlink_connection(str(REALDATA / "arducopter-flight.tlog"))
    out = {"LOCAL_POSITION_NED": [], "ATTITUDE": []}
    while True:
        m = conn.recv_match(type=list(out))
        if m is None:
            break
        if m.get_srcSystem() == 1:
            out[m.get_type()].append(m)
    return out


def test_arducopter_tlog_positions_velocities_headings_to_enu(tlog):
    lp, att = tlog["LOCAL_POSITION_NED"], tlog["ATTITUDE"]
    assert len(lp) == 1161 and len(att) == 2829
    P_ned = np.array([[m.x, m.y, m.z] for m in lp])
    V_ned = np.array([[m.vx, m.vy, m.vz] for m in lp])
    yaw_ned = np.array([m.yaw for m in att])
    rpy = np.array([[m.roll, m.pitch, m.yaw] for m in att])
    np.testing.assert_allclose(frames.enu_from_ned(P_ned), ROT_ENU_NED.apply(P_ned), atol=1e-9)
    np.testing.assert_allclose(frames.enu_from_ned(V_ned), ROT_ENU_NED.apply(V_ned), atol=1e-9)
    assert np.max(angle_diff(frames.yaw_enu_from_ned(yaw_ned), independent_yaw_enu_from_heading_ned(yaw_ned))) < 1e-9
    R_ours = frames.matrix_enu_flu_from_euler_ned_frd(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    R_ned_frd = Rotation.from_euler("ZYX", rpy[:, ::-1])
    np.testing.assert_allclose(R_ours, (ROT_ENU_NED * R_ned_frd * ROT_FLU_FRD.inv()).as_matrix(), atol=1e-9)


def test_arducopter_tlog_velocity_is_derivative_of_position_in_enu(tlog):
    """The converted velocity agrees with the finite difference of the converted position, axis by
    axis: a swapped or sign-flipped axis in either conversion would break the correlation."""
    lp = tlog["LOCAL_POSITION_NED"]
    t = np.array([m.time_boot_ms for m in lp]) * 1e-3
    P = frames.enu_from_ned(np.array([[m.x, m.y, m.z] for m in lp]))
    V = frames.enu_from_ned(np.array([[m.vx, m.vy, m.vz] for m in lp]))
    dt = np.diff(t)
    keep = (dt > 0.05) & (dt < 1.5)
    dP = np.diff(P, axis=0)[keep] / dt[keep, None]
    Vm = 0.5 * (V[1:] + V[:-1])[keep]
    for axis in range(3):
        if np.std(Vm[:, axis]) > 0.2:
            assert np.corrcoef(dP[:, axis], Vm[:, axis])[0, 1] > 0.9, f"axis {axis}"
