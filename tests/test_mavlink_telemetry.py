"""The telemetry a real client waits for, from real clients: MAVSDK's Telemetry plugin on the PX4
personality (outdoor and GPS-less indoor) and pymavlink against ArduCopter.

Each value is checked against the vehicle's ground truth in flight, in the client's units (m,
m/s, deg, rad/s, m/s^2 with gravity), and each stream at the autopilot's rate. A GPS-less vehicle
must not send what needs a global position. TIMESYNC and PING are answered as the autopilots do."""

import math
import threading
import time

import numpy as np
import pytest
from pymavlink import mavutil

from onfly.mavlink.link import MavlinkLink, mavlink2
from onfly.mavlink.sim_vehicle import EARTH_RADIUS_M, SimMavlinkVehicle, SimVehicleConfig
from test_mavlink_clients import MavproxyStyle, free_udp_port, px4_indoor, px4_outdoor, wait_until  # noqa: F401 (fixtures)

M = mavutil.mavlink
G = 9.81
pytestmark = pytest.mark.timeout(120)


class Received:
    """Latest value and count of each MAVSDK Telemetry subscription (callbacks run on MAVSDK's
    thread)."""

    def __init__(self, tel, names):
        self._lock = threading.Lock()
        self.latest, self.count = {}, {name: 0 for name in names}
        for name in names:
            getattr(tel, f"subscribe_{name}")(self._callback(name))

    def _callback(self, name):
        def cb(value, _user_data):
            with self._lock:
                self.latest[name] = value
                self.count[name] += 1

        return cb

    def get(self, name):
        with self._lock:
            return self.latest.get(name)

    def n(self, name):
        with self._lock:
            return self.count[name]


STREAMS = ("odometry", "altitude", "fixedwing_metrics", "imu", "attitude_euler", "heading", "velocity_ned")


def heading_deg_of(v) -> float:
    """The vehicle's heading (deg from north, clockwise) from its ENU yaw (outdoors the estimator
    frame is the scene's)."""
    return math.degrees(math.pi / 2 - v.model.yaw) % 360.0


def angle_diff_deg(a, b) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def test_mavsdk_px4_outdoor_telemetry_matches_ground_truth_in_flight(px4_outdoor):
    rig = px4_outdoor
    act, tel, v = rig.action, rig.telemetry, rig.vehicle
    rx = Received(tel, STREAMS)
    wait_until(lambda: all(rx.n(s) > 0 for s in STREAMS), 10.0, "every subscribed stream")
    wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")

    # on the ground: an accelerometer reads -g on the body z axis (FRD: down is +z, the reaction is up)
    imu = rx.get("imu")
    assert imu.acceleration_frd.down_m_s2 == pytest.approx(-G, abs=0.05)
    assert abs(imu.acceleration_frd.forward_m_s2) < 0.05 and abs(imu.acceleration_frd.right_m_s2) < 0.05
    assert rx.get("fixedwing_metrics").throttle_percentage == 0.0  # disarmed

    act.set_takeoff_altitude(3.0)
    act.arm()
    act.takeoff()
    wait_until(lambda: v.mode_name == "auto.loiter" and v.position_enu()[2] > 2.9, 15.0, "take-off complete")
    time.sleep(1.0)  # settle in the hover

    # hover: altitudes, throttle at MPC_THR_HOVER, specific force -g
    p = v.position_enu()
    alt = rx.get("altitude")
    assert alt.altitude_amsl_m == pytest.approx(488.0 + p[2], abs=0.05)
    assert alt.altitude_relative_m == pytest.approx(p[2], abs=0.05)  # home is the arming point at z = 0
    assert alt.altitude_local_m == pytest.approx(p[2], abs=0.05)
    assert alt.altitude_monotonic_m == pytest.approx(488.0 + p[2], abs=0.05)  # ISA baro altitude
    assert math.isnan(alt.bottom_clearance_m)  # no distance sensor
    fw = rx.get("fixedwing_metrics")
    assert fw.absolute_altitude_m == pytest.approx(488.0 + p[2], abs=0.05)
    # VFR_HUD.throttle is 50 (percent, MPC_THR_HOVER 0.5); MAVSDK divides it by 100 into "throttle_percentage"
    assert fw.throttle_percentage == pytest.approx(0.50, abs=0.02)
    assert fw.airspeed_m_s == 0.0  # a multicopter has no airspeed sensor
    assert rx.get("imu").acceleration_frd.down_m_s2 == pytest.approx(-G, abs=0.1)
    odo = rx.get("odometry")
    assert odo.position_body.z_m == pytest.approx(-p[2], abs=0.05)  # NED: up is negative

    # fly 8 m north-east with a turn to heading 45 deg: sample client and truth together
    pos = tel.position()
    dlat = math.degrees(8.0 / EARTH_RADIUS_M)
    dlon = math.degrees(8.0 / (EARTH_RADIUS_M * math.cos(math.radians(pos.latitude_deg))))
    act.goto_location(pos.latitude_deg + dlat, pos.longitude_deg + dlon, pos.absolute_altitude_m, 45.0)
    pairs = []
    deadline = time.monotonic() + 12.0
    while time.monotonic() < deadline and np.linalg.norm(v.position_enu()[:2] - [8.0, 8.0]) > 0.2:
        vel, yaw_rate, hdg = v.velocity_enu(), v.model.yaw_rate, heading_deg_of(v)
        pairs.append((vel, yaw_rate, hdg, rx.get("velocity_ned"), rx.get("odometry"), rx.get("imu"),
                      rx.get("fixedwing_metrics"), rx.get("heading"), rx.get("attitude_euler")))
        time.sleep(0.05)
    assert np.linalg.norm(v.position_enu()[:2] - [8.0, 8.0]) < 0.3, "goto target not reached"
    assert len(pairs) > 20
    fast = [q for q in pairs if np.hypot(*q[0][:2]) > 1.5]
    assert len(fast) > 5, "never flew faster than 1.5 m/s"
    # velocity_ned (GLOBAL_POSITION_INT, cm/s -> m/s) and odometry (LOCAL_NED velocity): north = ENU y
    err_v = [abs(q[3].north_m_s - q[0][1]) + abs(q[3].east_m_s - q[0][0]) for q in fast]
    err_o = [abs(q[4].velocity_body.x_m_s - q[0][1]) + abs(q[4].velocity_body.y_m_s - q[0][0]) for q in fast]
    err_g = [abs(q[6].groundspeed_m_s - np.hypot(*q[0][:2])) for q in fast]
    assert np.median(err_v) < 0.3 and np.median(err_o) < 0.3 and np.median(err_g) < 0.3
    assert all(q[3].north_m_s > 0.5 and q[3].east_m_s > 0.5 for q in fast[len(fast) // 2:])  # flying north-east
    # the turn: body rate about FRD z is -(ENU yaw rate); heading from the north, clockwise
    turning = [q for q in pairs if abs(q[1]) > 0.5]
    assert turning, "the vehicle never turned"
    err_w = [abs(q[5].angular_velocity_frd.down_rad_s - (-q[1])) for q in turning]
    assert np.median(err_w) < 0.3
    assert all(q[5].angular_velocity_frd.down_rad_s > 0.0 for q in turning if q[1] < -0.5)  # clockwise seen from above
    err_h = [angle_diff_deg(q[7].heading_deg, q[2]) for q in pairs]
    err_e = [angle_diff_deg(q[8].yaw_deg, q[2]) for q in pairs]
    err_f = [angle_diff_deg(q[6].heading_deg, q[2]) for q in pairs]
    assert np.median(err_h) < 5.0 and np.median(err_e) < 5.0 and np.median(err_f) < 5.0
    # accelerating forward tilts the nose down (negative pitch) and the accelerometer sees it
    assert min(q[8].pitch_deg for q in pairs) < -3.0
    time.sleep(1.5)
    assert rx.get("heading").heading_deg == pytest.approx(45.0, abs=2.0)
    assert rx.get("attitude_euler").yaw_deg == pytest.approx(45.0, abs=2.0)
    assert rx.get("fixedwing_metrics").heading_deg == pytest.approx(45.0, abs=2.0)
    p = v.position_enu()
    odo = rx.get("odometry")
    assert odo.position_body.x_m == pytest.approx(p[1], abs=0.1) and odo.position_body.y_m == pytest.approx(p[0], abs=0.1)


@pytest.mark.slow  # real time, ~8 s: opt-in (`-m slow`)
def test_mavsdk_px4_indoor_sends_what_a_gps_less_vehicle_sends_and_set_rate_works(px4_indoor):
    rig = px4_indoor
    act, tel, v = rig.action, rig.telemetry, rig.vehicle
    rx = Received(tel, STREAMS + ("raw_gps",))
    wait_until(lambda: all(rx.n(s) > 0 for s in ("odometry", "altitude", "fixedwing_metrics", "imu", "attitude_euler")),
               10.0, "the estimator's and the IMU's streams")
    time.sleep(1.0)
    # heading and velocity_ned come from GLOBAL_POSITION_INT, raw_gps from GPS_RAW_INT: none indoors
    assert rx.n("heading") == 0 and rx.n("velocity_ned") == 0 and rx.n("raw_gps") == 0
    alt = rx.get("altitude")
    assert math.isnan(alt.altitude_amsl_m) and math.isnan(alt.altitude_monotonic_m)  # no AMSL reference indoors
    assert alt.altitude_local_m == pytest.approx(0.0, abs=0.02)
    assert rx.get("imu").acceleration_frd.down_m_s2 == pytest.approx(-G, abs=0.05)

    act.set_takeoff_altitude(1.5)
    act.arm()
    act.takeoff()  # indoors: MIS_TAKEOFF_ALT above home, no global origin needed
    wait_until(lambda: v.mode_name == "auto.loiter" and v.position_enu()[2] > 1.4, 15.0, "take-off complete")
    time.sleep(1.0)
    p = v.position_enu()
    alt = rx.get("altitude")
    assert alt.altitude_local_m == pytest.approx(p[2], abs=0.05) and alt.altitude_relative_m == pytest.approx(p[2], abs=0.05)
    odo = rx.get("odometry")  # the estimator frame: origin at (3, -2, 0) in the scene
    assert odo.position_body.x_m == pytest.approx(p[1] + 2.0, abs=0.05)
    assert odo.position_body.y_m == pytest.approx(p[0] - 3.0, abs=0.05)
    assert odo.position_body.z_m == pytest.approx(-p[2], abs=0.05)
    assert rx.get("fixedwing_metrics").throttle_percentage == pytest.approx(0.50, abs=0.02)  # VFR_HUD 50 % / 100
    assert rx.n("heading") == 0 and rx.n("velocity_ned") == 0

    # SET_MESSAGE_INTERVAL through MAVSDK: ODOMETRY from 30 Hz down to 5 Hz
    tel.set_rate_odometry(5.0)
    n0, t0 = rx.n("odometry"), time.monotonic()
    time.sleep(3.0)
    rate = (rx.n("odometry") - n0) / (time.monotonic() - t0)
    assert 3.5 < rate < 6.5, f"ODOMETRY at {rate:.1f} Hz after set_rate_odometry(5)"


def count_over(mp, types, seconds):
    """Messages of each type read over ``seconds`` (reading everything, as MAVProxy does)."""
    counts = {t: 0 for t in types}
    last = {}
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = mp.m.recv_match(blocking=True, timeout=0.2)
        if msg is not None and msg.get_type() in counts:
            counts[msg.get_type()] += 1
            last[msg.get_type()] = msg
    return counts, last


@pytest.mark.slow  # real time, ~10 s: opt-in (`-m slow`)
def test_pymavlink_ardupilot_stream_groups_rates_values_and_message_interval():
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot="ardupilot", profile="outdoor")).start()
    try:
        mp = MavproxyStyle(port)
        mp.drain()
        # EXTRA2 (VFR_HUD) at 4 Hz, RAW_SENS (RAW_IMU) at 2 Hz: 4 s windows, +-40 %
        counts, last = count_over(mp, ("VFR_HUD", "RAW_IMU"), 4.0)
        assert 10 <= counts["VFR_HUD"] <= 22, counts
        assert 5 <= counts["RAW_IMU"] <= 11, counts
        raw = last["RAW_IMU"]
        assert raw.zacc == pytest.approx(-1000, abs=3) and abs(raw.xacc) <= 2 and abs(raw.yacc) <= 2  # milli-g, FRD
        hud = last["VFR_HUD"]
        assert hud.alt == pytest.approx(488.0, abs=0.05) and hud.throttle == 0 and hud.heading == 90  # yaw 0 = east

        # SET_MESSAGE_INTERVAL: VFR_HUD at 10 Hz, then stopped (-1), then the group's default (0)
        assert mp.long(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_VFR_HUD, 100000) == M.MAV_RESULT_ACCEPTED
        counts, _ = count_over(mp, ("VFR_HUD",), 3.0)
        assert 21 <= counts["VFR_HUD"] <= 39, counts
        assert mp.long(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_VFR_HUD, -1) == M.MAV_RESULT_ACCEPTED
        mp.drain()
        counts, _ = count_over(mp, ("VFR_HUD",), 1.5)
        assert counts["VFR_HUD"] == 0
        assert mp.long(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_VFR_HUD, 0) == M.MAV_RESULT_ACCEPTED
        # ArduPilot has no ODOMETRY / HIGHRES_IMU stream
        assert mp.long(M.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink2.MAVLINK_MSG_ID_ODOMETRY, 100000) == M.MAV_RESULT_DENIED

        # fly: GUIDED take-off to 2 m; VFR_HUD climbs with the vehicle
        assert mp.mode("GUIDED") == M.MAV_RESULT_ACCEPTED
        assert mp.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert mp.long(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == M.MAV_RESULT_ACCEPTED
        climbing = mp.latest("VFR_HUD", lambda m: m.climb > 0.5, timeout_s=5.0)
        assert climbing.groundspeed < 0.1 and climbing.throttle > 0
        wait_until(lambda: v.position_enu()[2] > 1.95, 10.0, "take-off to 2 m")
        time.sleep(1.0)
        hud = mp.latest("VFR_HUD", lambda m: abs(m.climb) < 0.05, timeout_s=3.0)
        assert hud.alt == pytest.approx(488.0 + v.position_enu()[2], abs=0.05)
        assert hud.throttle == pytest.approx(35, abs=2)  # MOT_THST_HOVER 0.35 in percent
        # POSITION_TARGET_LOCAL_NED is in no stream group: on request, in GUIDED
        assert mp.long(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED) == M.MAV_RESULT_ACCEPTED
        tgt = mp.m.recv_match(type="POSITION_TARGET_LOCAL_NED", blocking=True, timeout=3)
        assert tgt is not None and tgt.coordinate_frame == M.MAV_FRAME_LOCAL_NED
        assert not tgt.type_mask & M.POSITION_TARGET_TYPEMASK_Z_IGNORE and tgt.type_mask & M.POSITION_TARGET_TYPEMASK_VX_IGNORE
        assert tgt.z == pytest.approx(-2.0, abs=0.01)  # NED, metres above the EKF origin (the boot position)
    finally:
        v.stop()


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_timesync_answered_with_ts1_echoed_and_ping_as_each_autopilot(autopilot):
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot=autopilot, profile="indoor")).start()
    try:
        m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
        assert m.wait_heartbeat(timeout=5) is not None
        ts1 = 987654321012345
        m.mav.timesync_send(0, ts1)
        answer = m.recv_match(type="TIMESYNC", blocking=True, timeout=3, condition=f"TIMESYNC.ts1=={ts1}")
        assert answer is not None, "TIMESYNC request not answered"
        boot_ns = v.time_boot_us() * 1000
        assert 0 < answer.tc1 <= boot_ns and boot_ns - answer.tc1 < 2e9  # our time since boot, in ns
        # an answer (tc1 != 0) is not answered again
        m.mav.timesync_send(5, 1111)
        assert m.recv_match(type="TIMESYNC", blocking=True, timeout=1.5, condition="TIMESYNC.ts1==1111") is None
        # PING: PX4 returns a request (target 0/0) to its sender; ArduPilot does not handle PING
        m.mav.ping_send(424242, 17, 0, 0)
        pong = m.recv_match(type="PING", blocking=True, timeout=2, condition="PING.seq==17 and PING.target_system==255")
        if autopilot == "px4":
            assert pong is not None and pong.time_usec == 424242 and pong.target_component == 190
            # and PX4's own TIMESYNC and PING streams are requests (tc1 = 0, target 0/0)
            req = m.recv_match(type="TIMESYNC", blocking=True, timeout=2, condition="TIMESYNC.tc1==0")
            assert req is not None and req.ts1 > 0
        else:
            assert pong is None
    finally:
        v.stop()


@pytest.mark.parametrize("autopilot", ["ardupilot", pytest.param("px4", marks=pytest.mark.slow)])
def test_request_data_stream_sets_arducopter_groups_and_px4_ignores_it(autopilot):
    """MAVProxy's ``--streamrate`` on connect: REQUEST_DATA_STREAM for every stream at 10 Hz,
    then the POSITION group stopped. ArduCopter sets its groups (``handle_request_data_stream``);
    PX4 has no handler, so its streams keep their onboard-mode rates."""
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot=autopilot, profile="outdoor")).start()
    try:
        mp = MavproxyStyle(port)
        mp.m.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_ALL, 10, 1)
        time.sleep(0.3)
        mp.drain()
        counts, _ = count_over(mp, ("ATTITUDE", "VFR_HUD", "GLOBAL_POSITION_INT"), 2.0)
        if autopilot == "ardupilot":  # 4, 4 and 2 Hz before: now 10 Hz each (20 in 2 s, +-30 %)
            assert all(14 <= counts[t] <= 26 for t in ("ATTITUDE", "VFR_HUD", "GLOBAL_POSITION_INT")), counts
        else:  # PX4 onboard rates, unchanged: ATTITUDE and GLOBAL_POSITION_INT 50 Hz (the config's
            # telemetry rate), not 10
            assert counts["ATTITUDE"] > 60 and counts["GLOBAL_POSITION_INT"] > 60, counts
        mp.m.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_POSITION, 0, 0)
        time.sleep(0.3)
        mp.drain()
        counts, _ = count_over(mp, ("ATTITUDE", "GLOBAL_POSITION_INT"), 1.5)
        if autopilot == "ardupilot":
            assert counts["GLOBAL_POSITION_INT"] == 0 and counts["ATTITUDE"] >= 10, counts
        else:
            assert counts["GLOBAL_POSITION_INT"] > 40, counts
    finally:
        v.stop()
