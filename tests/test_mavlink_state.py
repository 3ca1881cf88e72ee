"""StateReader: ENU state from MAVLink telemetry, id filtering, vehicle-clock sync, and a replay
of a real ArduCopter telemetry log."""


import numpy as np
import pytest
from pymavlink import mavutil

from onfly.mavlink.link import mavlink2
from onfly.mavlink.state import StateReader, StateReaderConfig, VehicleClockSync
from planning.frames import wrap_angle
from realdata_paths import REALDATA

REALDATA = REALDATA / "mavlink"


class Wire:
    """Encodes messages as system/component ``(sys, comp)`` and parses them back from bytes."""

    def __init__(self, sys_id=1, comp_id=1):
        self.enc = mavlink2.MAVLink(None, srcSystem=sys_id, srcComponent=comp_id)
        self.dec = mavlink2.MAVLink(None, srcSystem=0, srcComponent=0)

    def __call__(self, msg):
        out = self.dec.parse_char(msg.pack(self.enc))
        assert out is not None
        return out


def make_reader():
    now = [100.0]
    reader = StateReader(StateReaderConfig(), clock=lambda: now[0])
    return reader, now


def test_local_position_and_attitude_become_enu_state():
    reader, now = make_reader()
    w = Wire()
    assert reader.state() is None
    assert reader.handle(w(w.enc.local_position_ned_encode(1000, 1.0, 2.0, -3.0, 0.1, 0.2, -0.3)))
    assert reader.state() is None  # no attitude yet
    assert reader.handle(w(w.enc.attitude_encode(1000, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5)))
    st = reader.state()
    np.testing.assert_allclose(st.p, [2.0, 1.0, 3.0])
    np.testing.assert_allclose(st.v, [0.2, 0.1, 0.3], atol=1e-7)
    assert st.yaw == pytest.approx(np.pi / 2)  # nose north
    assert st.yaw_rate == pytest.approx(-0.5)  # clockwise seen from above
    assert st.t_s == pytest.approx(100.0)


def test_attitude_quaternion_and_odometry():
    reader, now = make_reader()
    w = Wire()
    yaw_ned = 0.3  # quaternion of a pure NED yaw
    q = [np.cos(yaw_ned / 2), 0.0, 0.0, np.sin(yaw_ned / 2)]
    reader.handle(w(w.enc.local_position_ned_encode(10, 0, 0, 0, 0, 0, 0)))
    assert reader.handle(w(w.enc.attitude_quaternion_encode(10, *q, 0.0, 0.0, 0.0)))
    assert reader.state().yaw == pytest.approx(np.pi / 2 - yaw_ned, abs=1e-6)
    # ODOMETRY with body-FRD velocity (PX4's convention): 1 m/s forward while heading east
    q_east = [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]
    now[0] = 101.0
    msg = w.enc.odometry_encode(
        2_000_000, mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD,
        5.0, 6.0, -7.0, q_east, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, [np.nan] * 21, [np.nan] * 21,
    )
    assert reader.handle(w(msg))
    st = reader.state()
    np.testing.assert_allclose(st.p, [6.0, 5.0, 7.0])
    np.testing.assert_allclose(st.v, [1.0, 0.0, 0.0], atol=1e-6)
    assert st.yaw == pytest.approx(0.0, abs=1e-6)
    # An ODOMETRY in a frame we do not understand is rejected, not misread
    bad = w.enc.odometry_encode(3_000_000, mavlink2.MAV_FRAME_BODY_FRD, mavlink2.MAV_FRAME_BODY_FRD,
                                0, 0, 0, q_east, 0, 0, 0, 0, 0, 0, [0.0] * 21, [0.0] * 21)
    assert not reader.handle(w(bad))
    np.testing.assert_allclose(reader.state().p, [6.0, 5.0, 7.0])


def test_foreign_ids_unknown_messages_and_nan_are_ignored():
    reader, _ = make_reader()
    good, foreign_sys, foreign_comp = Wire(1, 1), Wire(42, 1), Wire(1, 154)
    reader.handle(good(good.enc.local_position_ned_encode(1, 1, 1, 1, 0, 0, 0)))
    reader.handle(good(good.enc.attitude_encode(1, 0, 0, 0, 0, 0, 0)))
    before = reader.state()
    assert not reader.handle(foreign_sys(foreign_sys.enc.local_position_ned_encode(2, 99, 99, 99, 0, 0, 0)))
    assert not reader.handle(foreign_comp(foreign_comp.enc.local_position_ned_encode(2, 99, 99, 99, 0, 0, 0)))
    assert not reader.handle(good(good.enc.vfr_hud_encode(1, 2, 3, 4, 5, 6)))
    assert not reader.handle(good(good.enc.local_position_ned_encode(3, np.nan, 0, 0, 0, 0, 0)))
    assert not reader.handle(good(good.enc.attitude_quaternion_encode(3, 0, 0, 0, 0, 0, 0, 0)))  # zero quaternion
    np.testing.assert_array_equal(reader.state().p, before.p)
    assert reader.counts == {"accepted": 2, "foreign": 2, "ignored": 1, "rejected": 2}


def test_heartbeat_status_and_ages():
    reader, now = make_reader()
    w = Wire()
    gcs = Wire(1, 1)
    assert reader.heartbeat_age_s() == np.inf and reader.link_age_s() == np.inf
    hb = w.enc.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4,
                                mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | 1, 6 << 16, mavlink2.MAV_STATE_ACTIVE)
    assert reader.handle(w(hb))
    st = reader.status()
    assert st.armed and st.custom_mode == 6 << 16 and st.autopilot == mavlink2.MAV_AUTOPILOT_PX4
    # A GCS-type heartbeat from the same ids does not overwrite the autopilot status
    assert not reader.handle(gcs(gcs.enc.heartbeat_encode(mavlink2.MAV_TYPE_GCS, 8, 0, 0, 0)))
    assert reader.status().armed
    now[0] += 0.7
    assert reader.heartbeat_age_s() == pytest.approx(0.7)
    reader.handle(w(w.enc.vfr_hud_encode(1, 2, 3, 4, 5, 6)))  # any message keeps the link alive
    assert reader.link_age_s() == pytest.approx(0.0) and reader.heartbeat_age_s() == pytest.approx(0.7)


def test_frozen_timestamps_do_not_refresh_odometry_age():
    reader, now = make_reader()
    w = Wire()
    msg = w.enc.local_position_ned_encode(5000, 1, 2, 3, 0, 0, 0)
    assert reader.handle(w(msg))
    for _ in range(5):
        now[0] += 0.1
        assert not reader.handle(w(w.enc.local_position_ned_encode(5000, 1, 2, 3, 0, 0, 0)))
    assert reader.odometry_age_s() == pytest.approx(0.5)


def test_clock_sync_offset_wrap_reset_and_out_of_order():
    sync = VehicleClockSync(reset_threshold_s=2.0, drift_ppm=0.0)
    # Latency varies 10..50 ms; the smallest seen defines the offset.
    assert sync.from_boot_ms(1_001_000, 51.050) == pytest.approx(51.050)
    assert sync.from_boot_ms(1_001_100, 51.110) == pytest.approx(51.110)  # offset now -949.990
    assert sync.from_boot_ms(1_001_200, 51.250) == pytest.approx(51.210)
    assert sync.from_boot_ms(1_001_150, 51.260) is None  # out of order: dropped
    assert sync.dropped == 1
    # uint32 wrap
    sync2 = VehicleClockSync(drift_ppm=0.0)
    t_a = sync2.from_boot_ms(2**32 - 100, 10.0)
    t_b = sync2.from_boot_ms(50, 10.150)
    assert t_b - t_a == pytest.approx(0.150)
    # reboot: vehicle time jumps back by ~1000 s -> re-sync, time stays monotonic
    t_c = sync.from_boot_ms(500, 60.0)
    assert sync.resets == 1 and t_c == pytest.approx(60.0)
    rng = np.random.default_rng(0)
    out, rx = [], 60.0
    tb = 500
    for _ in range(200):
        tb += int(rng.integers(5, 40))
        rx += rng.uniform(0.005, 0.04)
        t = sync.from_boot_ms(tb, rx)
        if t is not None:
            out.append((t, rx))
    ts = np.array(out)
    assert np.all(np.diff(ts[:, 0]) >= 0) and np.all(ts[:, 0] <= ts[:, 1] + 1e-12)


def test_replay_arducopter_tlog_gives_continuous_monotonic_state():
    conn = mavutil.mavlink_connection(str(REALDATA / "arducopter-flight.tlog"))
    reader = StateReader(StateReaderConfig(target_system=1, target_component=1), clock=lambda: 0.0)
    states, last_t = [], None
    n_bad = 0
    while True:
        m = conn.recv_msg()
        if m is None:
            break
        if m.get_type() == "BAD_DATA":
            n_bad += 1
        reader.handle(m, t_rx_s=m._timestamp)
        if m.get_type() == "LOCAL_POSITION_NED" and m.get_srcSystem() == 1:
            st = reader.state()
            if st is not None and st.t_s != last_t:
                states.append((st.t_s, m._timestamp, *st.p, *st.v, st.yaw))
                last_t = st.t_s
    S = np.array(states)
    assert n_bad > 1000 and reader.counts["foreign"] > 1000  # real radio noise and a GCS on the link
    assert len(S) > 1100
    t, rx, P, V, yaw = S[:, 0], S[:, 1], S[:, 2:5], S[:, 5:8], S[:, 8]
    assert np.all(np.diff(t) > 0), "state time must increase strictly between new samples"
    assert np.all(t <= rx + 1e-9), "a sample is never newer than its arrival"
    # Positions move continuously: no jump larger than what the measured speed explains.
    dt = np.diff(t)
    dp = np.linalg.norm(np.diff(P, axis=0), axis=1)
    vmax = np.maximum(np.linalg.norm(V[1:], axis=1), np.linalg.norm(V[:-1], axis=1))
    assert np.all(dp <= vmax * dt * 1.5 + 0.5)
    assert np.all(np.isfinite(yaw)) and np.all(np.abs(yaw) <= np.pi)
    dyaw = np.abs(wrap_angle(np.diff(yaw)))
    assert np.median(dyaw) < 0.15 and np.percentile(dyaw, 99) < 1.5
    # The log contains a real autopilot reboot (ATTITUDE time_boot_ms 279402 -> 18951): handled
    # as a re-sync, not as 260 s of stale attitude.
    assert reader.clock_resets() == {"position": 0, "attitude": 1, "odometry": 0}
