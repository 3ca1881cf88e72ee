"""Real MAVLink clients against the simulated vehicle: MAVSDK-Python (the C++ MAVSDK library
behind ctypes; the wheel carries it, nothing is downloaded) for the PX4 personality, and
pymavlink scripts written the way MAVProxy drives ArduCopter (SET_MODE, arm, NAV_TAKEOFF,
``guided`` as COMMAND_INT DO_REPOSITION, parameter fetch/set, LAND).

Each test checks the vehicle's outcome (mode, armed state, position reached, landed state) on
both sides: what the client reports and the vehicle's ground truth."""

import math
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink import mavutil

from onfly.mavlink.link import MavlinkLink
from onfly.mavlink.sim_vehicle import EARTH_RADIUS_M, SimMavlinkVehicle, SimVehicleConfig


from mavsdk import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.plugins.action.action import Action, ActionError  # noqa: E402
from mavsdk.plugins.manual_control.manual_control import ManualControl  # noqa: E402
from mavsdk.plugins.offboard.offboard import Offboard, PositionGlobalYaw, PositionNedYaw, VelocityBodyYawspeed, VelocityNedYaw  # noqa: E402
from mavsdk.plugins.param.param import Param  # noqa: E402
from mavsdk.plugins.telemetry.telemetry import FlightMode, LandedState, Telemetry  # noqa: E402

M = mavutil.mavlink
pytestmark = pytest.mark.timeout(90)


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def wait_until(pred, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


class MavsdkRig:
    """A sim vehicle sending to a MAVSDK instance listening on a free loopback port."""

    def __init__(self, **cfg):
        port = free_udp_port()
        self.vehicle = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(**cfg)).start()
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        self.mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = self.mavsdk.first_autopilot(10.0)
        assert system is not None, "MAVSDK found no autopilot"
        self.system = system
        self.action, self.telemetry = Action(system), Telemetry(system)

    def close(self):
        self.vehicle.stop()
        self.mavsdk.destroy()


@pytest.fixture
def px4_outdoor():
    rig = MavsdkRig(autopilot="px4", profile="outdoor")
    yield rig
    rig.close()


@pytest.fixture
def px4_indoor():
    rig = MavsdkRig(autopilot="px4", profile="indoor", estimator_origin_m=(3.0, -2.0, 0.0), initial_position_m=(3.0, -2.0, 0.0))
    yield rig
    rig.close()


def test_mavsdk_px4_arm_takeoff_goto_land_with_telemetry_units(px4_outdoor):
    rig = px4_outdoor
    act, tel, v = rig.action, rig.telemetry, rig.vehicle
    wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
    # MAVSDK reports NaN until its first GLOBAL_POSITION_INT: a client waits for one, as here
    wait_until(lambda: math.isfinite(tel.position().latitude_deg), 5.0, "a first global position")
    pos0 = tel.position()
    assert pos0.latitude_deg == pytest.approx(47.397742, abs=1e-6) and pos0.absolute_altitude_m == pytest.approx(488.0, abs=0.01)
    batt = tel.battery()
    assert 14.0 < batt.voltage_v < 16.9 and 0 < batt.remaining_percent <= 100.0  # volts and percent, not mV / fraction
    # EXTENDED_SYS_STATE streams at its own rate: wait for the first one instead of racing it
    wait_until(lambda: tel.landed_state() == LandedState.ON_GROUND, 5.0, "landed_state ON_GROUND")
    assert not tel.in_air()
    assert Param(rig.system).get_param_float("MIS_TAKEOFF_ALT") == pytest.approx(2.5)
    act.set_takeoff_altitude(3.0)  # PARAM_SET of MIS_TAKEOFF_ALT
    assert v.params["MIS_TAKEOFF_ALT"] == pytest.approx(3.0)

    act.arm()  # MAVSDK sends NaN in the unused parameters
    assert v.armed
    wait_until(tel.armed, 2.0, "client sees armed (HEARTBEAT)")
    act.takeoff()  # NAV_TAKEOFF with param7 NaN -> MIS_TAKEOFF_ALT above home
    wait_until(lambda: v.mode_name == "auto.loiter" and tel.in_air(), 15.0, "take-off complete")
    assert v.position_enu()[2] == pytest.approx(3.0, abs=0.15)
    wait_until(lambda: tel.position().relative_altitude_m > 2.8, 3.0, "relative altitude in metres")
    home = tel.home()
    assert home.latitude_deg == pytest.approx(47.397742, abs=1e-6) and home.relative_altitude_m == pytest.approx(0.0, abs=0.05)
    wait_until(lambda: tel.flight_mode() == FlightMode.HOLD, 2.0, "client sees HOLD")

    # goto 6 m north, 4 m east (COMMAND_INT DO_REPOSITION, AMSL altitude)
    p = tel.position()
    dlat = math.degrees(6.0 / EARTH_RADIUS_M)
    dlon = math.degrees(4.0 / (EARTH_RADIUS_M * math.cos(math.radians(p.latitude_deg))))
    act.goto_location(p.latitude_deg + dlat, p.longitude_deg + dlon, p.absolute_altitude_m, 0.0)
    wait_until(lambda: np.linalg.norm(v.position_enu()[:2] - [4.0, 6.0]) < 0.2, 15.0, "goto target reached")

    act.land()
    wait_until(lambda: not v.armed, 20.0, "landed and disarmed (COM_DISARM_LAND)")
    assert v.position_enu()[2] == pytest.approx(0.0, abs=0.02)
    wait_until(lambda: tel.landed_state() == LandedState.ON_GROUND and not tel.armed(), 3.0, "client sees landed, disarmed")
    assert any("Disarmed" in text for _, text in v.statustexts)


def test_mavsdk_px4_offboard_after_one_setpoint_position_and_velocity(px4_indoor):
    rig = px4_indoor
    act, tel, v = rig.action, rig.telemetry, rig.vehicle
    wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
    # indoor: no GPS, so no global position; local position is the estimator's (origin at boot)
    assert not tel.health().is_global_position_ok
    off = Offboard(rig.system)
    act.arm()
    off.set_position_ned(PositionNedYaw(0.0, 0.0, -1.5, 0.0))  # one setpoint, then start at once
    off.start()
    wait_until(lambda: v.mode_name == "offboard", 2.0, "OFFBOARD")
    wait_until(lambda: abs(v.position_enu()[2] - 1.5) < 0.1, 10.0, "1.5 m up")
    off.set_position_ned(PositionNedYaw(2.0, 1.0, -1.5, 90.0))  # 2 m north, 1 m east of the estimator origin
    wait_until(lambda: np.linalg.norm(v.position_enu() - [3.0 + 1.0, -2.0 + 2.0, 1.5]) < 0.15, 10.0, "position setpoint")
    pv = tel.position_velocity_ned()
    assert pv.position.north_m == pytest.approx(2.0, abs=0.2) and pv.position.east_m == pytest.approx(1.0, abs=0.2)
    off.set_velocity_ned(VelocityNedYaw(0.0, -0.5, 0.0, 90.0))  # west at 0.5 m/s
    time.sleep(1.5)
    assert v.velocity_enu()[0] == pytest.approx(-0.5, abs=0.1) 
    assert tel.position_velocity_ned().velocity.east_m_s == pytest.approx(-0.5, abs=0.1)  # m/s from LOCAL_POSITION_NED
    off.stop()  # stops the stream: COM_OBL_RC_ACT of the indoor setting (Hold) after COM_OF_LOSS_T
    wait_until(lambda: v.mode_name == "auto.loiter", 3.0, "offboard-loss action Hold")
    assert v.armed


def test_mavsdk_px4_refusals_are_answered():
    rig = MavsdkRig(autopilot="px4", profile="indoor")
    try:
        act, v = rig.action, rig.vehicle
        time.sleep(0.5)
        v.set_position_valid(False)
        with pytest.raises(ActionError):
            act.arm()  # pre-arm: no position estimate -> FAILED, with a STATUSTEXT
        assert not v.armed and any("position" in t for _, t in v.statustexts)
        v.set_position_valid(True)
        with pytest.raises(ActionError):
            act.goto_location(47.0, 8.0, 500.0, 0.0)  # indoor: no global origin -> FAILED, not silence
    finally:
        rig.close()


# -- pymavlink in MAVProxy's style against the ArduPilot personality --------------------------
class MavproxyStyle:
    """What MAVProxy sends for `mode`, `arm throttle`, `takeoff`, `guided`, `param fetch/set`."""

    def __init__(self, port):
        self.m = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
        self.m.wait_heartbeat(timeout=5)

    def ack(self, command, timeout_s=5.0):  # generous: the machine runs many jobs
        msg = self.m.recv_match(type="COMMAND_ACK", blocking=True, timeout=timeout_s, condition=f"COMMAND_ACK.command=={command}")
        assert msg is not None, f"no COMMAND_ACK for {command}"
        return msg.result

    def drain(self):
        """Read what is buffered, as MAVProxy's loop always does: a client that stops reading
        lets the socket buffer fill with telemetry, and the kernel then drops the newest
        datagrams, a command's ACK among them."""
        while self.m.recv_match(blocking=False) is not None:
            pass

    def mode(self, name):
        self.drain()
        self.m.mav.set_mode_send(self.m.target_system, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, self.m.mode_mapping()[name])
        return self.ack(M.MAVLINK_MSG_ID_SET_MODE)

    def long(self, cmd, *params):
        p = list(params) + [0.0] * (7 - len(params))
        self.drain()
        self.m.mav.command_long_send(self.m.target_system, self.m.target_component, cmd, 0, *p)
        return self.ack(cmd)

    def guided_takeoff(self, v, alt_m):
        """`mode GUIDED`, `arm throttle`, `takeoff ALT`; waits on the vehicle's truth."""
        assert self.mode("GUIDED") == M.MAV_RESULT_ACCEPTED
        assert self.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert self.long(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt_m) == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: v.position_enu()[2] > alt_m - 0.1, 10.0, f"take-off to {alt_m} m")

    def guided_north(self, v, north_m, alt_m):
        """`guided LAT LON ALT` ``north_m`` north of the vehicle: COMMAND_INT DO_REPOSITION,
        relative altitude; waits until the vehicle (taken off at the scene origin) is there.
        Returns the target's latitude, degE7."""
        gp = self.m.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=3)
        lat = gp.lat + int(round(math.degrees(north_m / EARTH_RADIUS_M) * 1e7))
        self.drain()
        self.m.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_DO_REPOSITION, 0, 0,
                                    -1, M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan, lat, gp.lon, alt_m)
        assert self.ack(M.MAV_CMD_DO_REPOSITION) == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: np.linalg.norm(v.position_enu() - [0.0, north_m, alt_m]) < 0.15, 15.0, "guided target")
        return lat

    def latest(self, mtype, pred, timeout_s=3.0):
        """Read ``mtype`` messages (older buffered ones first) until one satisfies ``pred``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.m.recv_match(type=mtype, blocking=True, timeout=0.5)
            if msg is not None and pred(msg):
                return msg
        raise AssertionError(f"no {mtype} satisfying the condition within {timeout_s} s")

    def statustext(self, text, timeout_s=3.0):
        """Read STATUSTEXT (older buffered ones first) until one reads ``text``, joining the
        50-character chunks of one id as MAVProxy and MAVSDK do (id 0 is a whole text, a shorter
        chunk ends one)."""
        parts = {}
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.m.recv_match(type="STATUSTEXT", blocking=True, timeout=0.5)
            if msg is None:
                continue
            whole = parts.pop(msg.id, "") + msg.text
            if msg.id != 0 and len(msg.text) == 50:
                parts[msg.id] = whole
            elif whole == text:
                return
        raise AssertionError(f"no STATUSTEXT {text!r} within {timeout_s} s")


def test_pymavlink_mavproxy_style_ardupilot_guided_flight():
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot="ardupilot", profile="outdoor")).start()
    try:
        mp = MavproxyStyle(port)
        # param fetch: the whole table, C-cast integers
        mp.m.mav.param_request_list_send(1, 1)
        params, count = {}, None
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (count is None or len(params) < count):
            pv = mp.m.recv_match(type="PARAM_VALUE", blocking=True, timeout=1)
            if pv is not None:
                params[pv.param_id], count = pv.param_value, pv.param_count
        assert params["GUID_TIMEOUT"] == pytest.approx(3.0) and params["DISARM_DELAY"] == 10.0 and len(params) == pv.param_count
        mp.m.mav.param_set_send(1, 1, b"GUID_TIMEOUT", 2.0, M.MAV_PARAM_TYPE_REAL32)
        echo = mp.m.recv_match(type="PARAM_VALUE", blocking=True, timeout=2, condition="PARAM_VALUE.param_id=='GUID_TIMEOUT'")
        assert echo.param_value == pytest.approx(2.0) and v.params["GUID_TIMEOUT"] == pytest.approx(2.0)

        mp.guided_takeoff(v, 2.0)
        mp.guided_north(v, 5.0, 3.0)
        time.sleep(2.5)  # past GUID_TIMEOUT: a position target is held, not dropped
        assert np.linalg.norm(v.position_enu() - [0.0, 5.0, 3.0]) < 0.15 and v.mode_name == "guided"
        # `mode LAND`: ArduCopter disarms as soon as the land detector says landed
        assert mp.mode("LAND") == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: not v.armed, 15.0, "landed and disarmed")
        mp.latest("EXTENDED_SYS_STATE", lambda m: m.landed_state == M.MAV_LANDED_STATE_ON_GROUND)
        mp.latest("HEARTBEAT", lambda m: m.custom_mode == 9 and not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
        # a fresh arm in LAND is refused (mode does not allow arming)
        assert mp.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED
    finally:
        v.stop()


def test_mavsdk_px4_return_to_launch_climbs_comes_home_lands_and_gps_has_a_3d_fix(px4_outdoor):
    from mavsdk.plugins.telemetry.telemetry import FixType

    rig = px4_outdoor
    act, tel, v = rig.action, rig.telemetry, rig.vehicle
    wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
    wait_until(lambda: tel.gps_info().fix_type == FixType.FIX_3D, 5.0, "GPS_RAW_INT 3D fix")  # outdoor: GPS streams
    assert tel.gps_info().num_satellites >= 6
    raw = tel.raw_gps()
    assert raw.latitude_deg == pytest.approx(47.397742, abs=1e-6) and raw.absolute_altitude_m == pytest.approx(488.0, abs=0.01)
    assert Param(rig.system).get_param_float("RTL_RETURN_ALT") == pytest.approx(30.0)  # PX4 multicopter default
    act.set_return_to_launch_altitude(4.0)  # PARAM_SET RTL_RETURN_ALT: a short test, not a 60 m climb
    assert v.params["RTL_RETURN_ALT"] == pytest.approx(4.0)
    act.set_takeoff_altitude(2.0)

    act.arm()
    act.takeoff()
    wait_until(lambda: v.mode_name == "auto.loiter" and tel.in_air(), 15.0, "take-off complete")
    p = tel.position()
    dlat = math.degrees(6.0 / EARTH_RADIUS_M)
    dlon = math.degrees(4.0 / (EARTH_RADIUS_M * math.cos(math.radians(p.latitude_deg))))
    act.goto_location(p.latitude_deg + dlat, p.longitude_deg + dlon, p.absolute_altitude_m, 0.0)
    wait_until(lambda: np.linalg.norm(v.position_enu()[:2] - [4.0, 6.0]) < 0.2, 15.0, "goto target reached")
    assert v.position_enu()[2] == pytest.approx(2.0, abs=0.1)

    act.return_to_launch()  # MAV_CMD_NAV_RETURN_TO_LAUNCH
    assert v.mode_name == "auto.rtl"
    wait_until(lambda: tel.flight_mode() == FlightMode.RETURN_TO_LAUNCH, 3.0, "client sees RETURN_TO_LAUNCH")
    track = []  # (scene position) while returning
    deadline = time.monotonic() + 40.0
    while v.armed and time.monotonic() < deadline:
        track.append(v.position_enu())
        time.sleep(0.02)
    assert not v.armed, "still armed 40 s after RTL"
    track = np.array(track)
    # climbed to RTL_RETURN_ALT above home before coming home (7.2 m away, inside RTL_MIN_DIST:
    # the 45 degree cone allows 7.2 m, RTL_RETURN_ALT caps it), then came back and landed on home
    top = int(np.argmax(track[:, 2]))
    assert track[top, 2] == pytest.approx(4.0, abs=0.15)
    # the climb came first, straight up over the goto point, until within NAV_MC_ALT_RAD (0.8 m)
    climbed = int(np.argmax(track[:, 2] >= 4.0 - 0.9))
    assert np.linalg.norm(track[climbed, :2] - [4.0, 6.0]) < 0.3
    assert np.linalg.norm(v.position_enu()[:2]) < 0.15 and v.position_enu()[2] == pytest.approx(0.0, abs=0.02)
    texts = [text for _, text in v.statustexts]
    assert v.first_event("mode auto.rtl: commanded") is not None  # MAVSDK sends PX4 a DO_SET_MODE for it
    assert "RTL: land at destination" in texts
    assert any(t.startswith("RTL: start return at 492 m (4 m above destination)") for t in texts)
    wait_until(lambda: tel.landed_state() == LandedState.ON_GROUND and not tel.armed(), 3.0, "client sees landed, disarmed")


@pytest.mark.slow  # real time, ~10 s: opt-in (`-m slow`)
def test_pymavlink_mavproxy_style_ardupilot_mode_rtl_climbs_returns_loiters_lands_and_disarms():
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot="ardupilot", profile="outdoor")).start()
    try:
        mp = MavproxyStyle(port)
        # `param set` (C-cast integers): a low RTL_ALT, a short loiter and a quick final landing keep the test short
        for name, value, ptype in (("RTL_ALT", 600, M.MAV_PARAM_TYPE_INT32), ("RTL_LOIT_TIME", 1000, M.MAV_PARAM_TYPE_INT32),
                                   ("LAND_SPEED", 150, M.MAV_PARAM_TYPE_INT16)):
            mp.drain()
            mp.m.mav.param_set_send(1, 1, name.encode(), float(value), ptype)
            echo = mp.m.recv_match(type="PARAM_VALUE", blocking=True, timeout=3, condition=f"PARAM_VALUE.param_id=='{name}'")
            assert echo is not None and echo.param_value == value and v.params[name] == value
        mp.guided_takeoff(v, 2.0)
        lat = mp.guided_north(v, 5.0, 3.0)
        mp.drain()
        gps = mp.latest("GPS_RAW_INT", lambda m: True)  # EXT_STAT group
        assert gps.fix_type == M.GPS_FIX_TYPE_3D_FIX and gps.satellites_visible > 0 and abs(gps.lat - lat) < 20

        assert mp.mode("RTL") == M.MAV_RESULT_ACCEPTED  # `mode RTL`
        track, landing_seen = [], False
        deadline = time.monotonic() + 40.0
        while v.armed and time.monotonic() < deadline:
            track.append(v.position_enu())
            for m in iter(lambda: mp.m.recv_match(blocking=False), None):  # read as MAVProxy does
                landing_seen |= m.get_type() == "EXTENDED_SYS_STATE" and m.landed_state == M.MAV_LANDED_STATE_LANDING
            time.sleep(0.02)
        assert not v.armed, "still armed 40 s after RTL"
        track = np.array(track)
        # RTL_ALT 6 m > 3 m + RTL_CLIMB_MIN: climbed over the stopping point (to within WPNAV_RADIUS, 2 m) first
        climbed = int(np.argmax(track[:, 2] >= 6.0 - 2.05))
        assert np.linalg.norm(track[climbed, :2] - [0.0, 5.0]) < 0.3
        assert track[:, 2].max() == pytest.approx(6.0, abs=0.15)
        assert np.linalg.norm(v.position_enu()[:2]) < 0.15 and v.position_enu()[2] == pytest.approx(0.0, abs=0.02)
        events = [e for _, e in v.events]
        assert [e for e in events if e.startswith("rtl: ") and " at " not in e] == ["rtl: climb", "rtl: return", "rtl: loiter", "rtl: land"]
        assert v.first_event("disarmed: landed") - v.first_event("landed") < 0.1  # at once, as in LAND (land_run)
        loiter_s = v.first_event("rtl: land") - v.first_event("rtl: loiter")
        assert 1.0 <= loiter_s <= 1.2  # RTL_LOIT_TIME
        assert landing_seen
        mp.latest("HEARTBEAT", lambda m: m.custom_mode == 6 and not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
    finally:
        v.stop()


# -- speed, yaw and reboot: MAVSDK's set_current_speed / reboot, MAVProxy's setspeed / setyaw / reboot --
def test_mavsdk_px4_set_current_speed_slows_the_next_goto_and_reboot_is_refused_armed(px4_outdoor):
    from mavsdk.plugins.action.action import ActionResult

    rig = px4_outdoor
    act, tel, v = rig.action, rig.telemetry, rig.vehicle
    wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
    wait_until(lambda: math.isfinite(tel.position().latitude_deg), 5.0, "a first global position")
    act.set_takeoff_altitude(2.0)
    act.arm()
    with pytest.raises(ActionError) as refused:
        act.reboot()  # PREFLIGHT_REBOOT_SHUTDOWN armed: Commander's shutdown_if_allowed -> DENIED
    assert refused.value.result == ActionResult.COMMAND_DENIED
    assert v.armed and not v.rebooting
    act.takeoff()
    wait_until(lambda: v.mode_name == "auto.loiter" and tel.in_air(), 15.0, "take-off complete")
    act.set_current_speed(1.0)  # DO_CHANGE_SPEED ground speed: the navigator's cruising speed
    p = tel.position()
    dlat = math.degrees(3.0 / EARTH_RADIUS_M)
    t0 = time.monotonic()
    act.goto_location(p.latitude_deg + dlat, p.longitude_deg, p.absolute_altitude_m, float("nan"))
    speeds = []
    while np.linalg.norm(v.position_enu()[:2] - [0.0, 3.0]) > 0.2 and time.monotonic() - t0 < 15.0:
        vel = tel.position_velocity_ned().velocity  # LOCAL_POSITION_NED, m/s
        speeds.append(math.hypot(vel.north_m_s, vel.east_m_s))
        time.sleep(0.05)
    assert np.linalg.norm(v.position_enu()[:2] - [0.0, 3.0]) <= 0.2, "goto target not reached"
    # the goto flew at the commanded 1 m/s, not MPC_XY_CRUISE (5 m/s): 3 m took more than 2.5 s
    assert 0.9 < max(speeds) <= 1.05 and time.monotonic() - t0 > 2.5


def test_pymavlink_mavproxy_style_ardupilot_setspeed_setyaw_and_reboot():
    port = free_udp_port()
    cfg = SimVehicleConfig(autopilot="ardupilot", profile="outdoor", reboot_time_s=1.0)
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), cfg).start()
    try:
        mp = MavproxyStyle(port)
        # `setspeed` outside GUIDED/RTL/AUTO: the mode has no set_speed_NE_ms -> FAILED
        assert mp.long(M.MAV_CMD_DO_CHANGE_SPEED, 0, 1.0) == M.MAV_RESULT_FAILED
        mp.guided_takeoff(v, 1.5)
        assert mp.long(M.MAV_CMD_DO_CHANGE_SPEED, 0, 0.0) == M.MAV_RESULT_DENIED  # speed must be > 0
        assert mp.long(M.MAV_CMD_DO_CHANGE_SPEED, 0, 1.0) == M.MAV_RESULT_ACCEPTED  # `setspeed 1`
        # `guided` 3 m north: a position target flown at the changed speed (WPNAV_SPEED is 10 m/s)
        gp = mp.m.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=3)
        lat = gp.lat + int(round(math.degrees(3.0 / EARTH_RADIUS_M) * 1e7))
        mp.drain()
        mp.m.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_DO_REPOSITION, 0, 0,
                                  -1, 0, 0, math.nan, lat, gp.lon, 1.5)
        assert mp.ack(M.MAV_CMD_DO_REPOSITION) == M.MAV_RESULT_ACCEPTED
        speeds, reported = [], []
        t0 = time.monotonic()
        while np.linalg.norm(v.position_enu()[:2] - [0.0, 3.0]) > 0.15 and time.monotonic() - t0 < 10.0:
            speeds.append(float(np.linalg.norm(v.velocity_enu()[:2])))
            for m in iter(lambda: mp.m.recv_match(type="GLOBAL_POSITION_INT", blocking=False), None):
                reported.append(math.hypot(m.vx, m.vy) / 100.0)  # cm/s
            time.sleep(0.02)
        assert np.linalg.norm(v.position_enu()[:2] - [0.0, 3.0]) <= 0.15, "guided target not reached"
        assert 0.9 < max(speeds) <= 1.02 and reported and max(reported) <= 1.02

        # `setyaw 0 45 0`: from east (the boot heading) to north at 45 deg/s (below ATC_SLEW_YAW's 60)
        assert abs(math.degrees(v.model.yaw)) < 1.0
        assert mp.long(M.MAV_CMD_CONDITION_YAW, 0.0, 45.0, 0, 0) == M.MAV_RESULT_ACCEPTED
        assert mp.long(M.MAV_CMD_CONDITION_YAW, 400.0, 45.0, 0, 0) == M.MAV_RESULT_FAILED  # not a heading
        t0 = time.monotonic()
        rates = []
        while abs(math.degrees(v.model.yaw) - 90.0) > 0.5 and time.monotonic() - t0 < 6.0:
            rates.append(abs(v.model.yaw_rate))
            time.sleep(0.02)
        assert abs(math.degrees(v.model.yaw) - 90.0) <= 0.5  # ENU yaw 90 deg = facing north
        assert rates and 40.0 < math.degrees(max(rates)) <= 45.5 and time.monotonic() - t0 > 1.9
        mp.latest("VFR_HUD", lambda m: m.heading in (0, 359, 1))  # what a ground station shows
        assert np.linalg.norm(v.position_enu()[:2] - [0.0, 3.0]) < 0.15  # turned in place

        # `reboot` armed: FAILED; after landing and disarming it is ACCEPTED and the link goes quiet
        assert mp.long(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == M.MAV_RESULT_FAILED
        mp.m.mav.param_set_send(1, 1, b"WPNAV_SPEED", 500.0, M.MAV_PARAM_TYPE_REAL32)
        mp.m.mav.param_set_send(1, 1, b"LAND_SPEED", 150.0, M.MAV_PARAM_TYPE_INT16)  # a quick landing
        wait_until(lambda: v.params["LAND_SPEED"] == 150, 2.0, "LAND_SPEED set")
        assert mp.mode("LAND") == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: not v.armed, 10.0, "landed and disarmed")
        assert mp.long(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 2) == M.MAV_RESULT_UNSUPPORTED  # only 1 / 3
        assert mp.long(M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1, 0, 0, 0) == M.MAV_RESULT_ACCEPTED
        time.sleep(0.5)
        mp.drain()
        assert mp.m.recv_match(type="HEARTBEAT", blocking=True, timeout=0.6) is None  # silent while it boots
        hb = mp.m.recv_match(type="HEARTBEAT", blocking=True, timeout=3.0)
        assert hb is not None and hb.custom_mode == 0  # back, in its boot mode (STABILIZE)
        st = mp.latest("SYSTEM_TIME", lambda m: True)
        assert st.time_boot_ms < 1500  # a fresh boot
        mp.m.mav.param_request_read_send(1, 1, b"WPNAV_SPEED", -1)
        pv = mp.m.recv_match(type="PARAM_VALUE", blocking=True, timeout=2, condition="PARAM_VALUE.param_id=='WPNAV_SPEED'")
        assert pv is not None and pv.param_value == pytest.approx(500.0)  # parameters survive a reboot
    finally:
        v.stop()


# -- SET_POSITION_TARGET_GLOBAL_INT: MAVSDK's set_position_global, a pymavlink script's GUIDED goto --
_ORIGIN = (47.397742, 8.545594, 488.0)  # the outdoor profile's global origin (the scene origin)


def latlon(north_m, east_m):
    """Degrees of the point ``north_m`` / ``east_m`` from the outdoor origin."""
    return (_ORIGIN[0] + math.degrees(north_m / EARTH_RADIUS_M),
            _ORIGIN[1] + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(_ORIGIN[0])))))


def settled(v, p_enu, tol_m=0.1):
    """The vehicle (ground truth) is within ``tol_m`` of ``p_enu`` (scene ENU, m) and still."""
    return np.linalg.norm(v.position_enu() - p_enu) < tol_m and np.linalg.norm(v.velocity_enu()) < 0.1


def test_mavsdk_px4_offboard_set_position_global_relative_and_amsl_and_agl_is_no_setpoint():
    # stiffer gains than the default: the test is about the rules, its legs stay short in wall time
    rig = MavsdkRig(autopilot="px4", profile="outdoor", k_pos=3.0, k_vel=6.0)
    try:
        act, tel, v = rig.action, rig.telemetry, rig.vehicle
        wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
        wait_until(lambda: math.isfinite(tel.position().latitude_deg), 5.0, "a first global position")
        act.arm()  # home = the arming point: RELATIVE_ALT_INT needs it
        off = Offboard(rig.system)
        Alt = PositionGlobalYaw.AltitudeType
        # REL_HOME -> MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, type_mask: position + yaw (MAVSDK offboard_impl.cpp)
        off.set_position_global(PositionGlobalYaw(*latlon(2.0, 1.5), 1.5, 90.0, Alt.REL_HOME))
        off.start()  # one setpoint is enough: it refreshed the offboard signal
        wait_until(lambda: v.mode_name == "offboard", 2.0, "OFFBOARD")
        wait_until(lambda: settled(v, [1.5, 2.0, 1.5]), 8.0, "relative-altitude target")
        pos = tel.position()  # GLOBAL_POSITION_INT, against the target and the ground truth
        assert (pos.latitude_deg, pos.longitude_deg) == pytest.approx(latlon(2.0, 1.5), abs=2e-6)
        assert pos.relative_altitude_m == pytest.approx(1.5, abs=0.1)
        assert abs(v.model.yaw) < 0.05  # yaw 90 deg NED: facing east
        # AMSL -> MAV_FRAME_GLOBAL_INT
        off.set_position_global(PositionGlobalYaw(*latlon(0.5, 0.0), 490.5, 90.0, Alt.AMSL))
        wait_until(lambda: settled(v, [0.0, 0.5, 2.5]), 8.0, "AMSL target")
        wait_until(lambda: abs(tel.position().absolute_altitude_m - 490.5) < 0.1, 2.0, "AMSL altitude reported")
        assert tel.position().latitude_deg == pytest.approx(latlon(0.5, 0.0)[0], abs=2e-6)
        # AGL -> MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: no distance sensor, no terrain altitude: PX4 drops
        # every one, so the offboard signal is lost after COM_OF_LOSS_T -> COM_OBL_RC_ACT Position,
        # which needs RC -> Hold, where the vehicle stands
        off.set_position_global(PositionGlobalYaw(*latlon(2.0, 1.5), 1.0, 90.0, Alt.AGL))
        wait_until(lambda: v.mode_name == "auto.loiter", 3.0, "offboard lost -> Hold")
        assert np.linalg.norm(v.position_enu() - [0.0, 0.5, 2.5]) < 0.15 and v.armed
        assert v.first_event("mode auto.loiter: offboard lost") is not None
    finally:
        rig.close()


def test_pymavlink_ardupilot_guided_set_position_target_global_int_relative_alt_and_a_bad_type_mask():
    port = free_udp_port()
    cfg = SimVehicleConfig(autopilot="ardupilot", profile="outdoor", k_pos=3.0, k_vel=6.0)
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), cfg).start()
    try:
        mp = MavproxyStyle(port)
        mp.guided_takeoff(v, 1.0)
        # the usual script: RELATIVE_ALT_INT, position only (0b0000111111111000: yaw and rates ignored)
        lat, lon = latlon(3.0, 0.0)
        mp.m.mav.set_position_target_global_int_send(0, 1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0x0FF8,
                                                     int(round(lat * 1e7)), int(round(lon * 1e7)), 1.5, 0, 0, 0, 0, 0, 0, 0, 0)
        wait_until(lambda: settled(v, [0.0, 3.0, 1.5]), 8.0, "guided global target")
        mp.drain()
        gp = mp.latest("GLOBAL_POSITION_INT", lambda m: abs(m.relative_alt - 1500) < 100)  # mm above home
        assert abs(gp.lat - lat * 1e7) < 20 and abs(gp.lon - lon * 1e7) < 20  # degE7: 20 is ~2 cm
        # position + acceleration without velocity: not a combination ArduCopter flies ->
        # ModeGuided::init(true): brake and hover where it is, not 3 m further north
        lat2, _ = latlon(6.0, 0.0)
        mp.m.mav.set_position_target_global_int_send(0, 1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0x0C38,
                                                     int(round(lat2 * 1e7)), int(round(lon * 1e7)), 1.5, 0, 0, 0, 0, 0, 0, 0, 0)
        wait_until(lambda: v.first_event("guided: input not valid (unsupported type_mask combination): stop") is not None,
                   2.0, "the stop")
        time.sleep(0.5)
        assert np.linalg.norm(v.position_enu() - [0.0, 3.0, 1.5]) < 0.15 and v.mode_name == "guided"
    finally:
        v.stop()


def test_mavsdk_px4_manual_control_position_mode_flies_the_sticks_home_and_input_loss_is_rc_loss():
    """MAVSDK's ManualControl as a ground station's joystick: stick input makes Position mode
    available, the sticks fly as velocities (MPC_Z_VEL_MAX_UP, MPC_VEL_MANUAL at full stick),
    centred sticks hold; DO_SET_HOME (MAVSDK ``set_home``) moves home; stopping the input is
    PX4's RC loss after COM_RC_LOSS_T: NAV_RCL_ACT 2 Return, which flies to the new home."""
    rig = MavsdkRig(autopilot="px4", profile="outdoor", k_pos=4.0, k_vel=8.0, a_max_mps2=8.0,
                    params=(("MPC_VEL_MANUAL", 2.0), ("MPC_Z_VEL_MAX_UP", 1.5), ("RTL_RETURN_ALT", 3.0)))
    v, act, tel = rig.vehicle, rig.action, rig.telemetry
    man = ManualControl(rig.system)
    sticks = [0.0, 0.0, 0.5, 0.0]  # x forward, y right, z throttle (0.5 centre), r yaw
    stop = threading.Event()

    def joystick():
        while not stop.is_set():
            man.set_manual_control_input(*sticks)
            time.sleep(0.05)

    stick_thread = threading.Thread(target=joystick, daemon=True)
    try:
        wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
        # no stick input yet: Position mode needs manual control (the setting has no RC)
        assert v._cmd_set_mode(1.0, 3.0, 0.0) == M.MAV_RESULT_TEMPORARILY_REJECTED
        stick_thread.start()
        wait_until(lambda: v.first_event("manual control: MAVLink stick input") is not None, 2.0, "stick input")
        man.start_position_control()  # DO_SET_MODE POSCTL
        wait_until(lambda: v.mode_name == "posctl", 2.0, "Position mode")
        act.arm()
        sticks[2] = 1.0  # full throttle: climb at MPC_Z_VEL_MAX_UP
        wait_until(lambda: v.position_enu()[2] > 1.0, 4.0, "climb")
        assert v.velocity_enu()[2] == pytest.approx(1.5, abs=0.15)
        sticks[2] = 0.5
        # centred throttle reaches the vehicle through MAVSDK's queue: hold from when the climb stopped
        wait_until(lambda: abs(v.velocity_enu()[2]) < 0.05, 2.0, "the climb stopped at centred throttle")
        z_hold = v.position_enu()[2]
        sticks[0] = 1.0  # full forward: heading east (yaw 0) at MPC_VEL_MANUAL
        time.sleep(1.2)
        vel = v.velocity_enu()
        assert vel[0] == pytest.approx(2.0, abs=0.15)
        assert abs(vel[1]) < 0.15
        assert abs(v.position_enu()[2] - z_hold) < 0.1
        sticks[0] = 0.0  # centred: brake and hold
        time.sleep(1.0)
        p_hold = v.position_enu()
        time.sleep(0.5)
        assert np.linalg.norm(v.position_enu() - p_hold) < 0.05 and np.linalg.norm(v.velocity_enu()) < 0.1
        # set_home: COMMAND_INT DO_SET_HOME 4 m north of the origin, AMSL
        lat0, lon0, alt0 = 47.397742, 8.545594, 488.0
        act.set_home(False, lat0 + math.degrees(4.0 / EARTH_RADIUS_M), lon0, alt0)
        np.testing.assert_allclose(v._home, [0.0, 4.0, 0.0], atol=0.05)
        wait_until(lambda: tel.home().latitude_deg == pytest.approx(lat0 + math.degrees(4.0 / EARTH_RADIUS_M), abs=1e-7), 5.0,
                   "HOME_POSITION with the new home")
        stop.set()  # the joystick goes silent
        stick_thread.join(1.0)
        wait_until(lambda: v.mode_name == "auto.rtl", 2.0, "RC loss -> NAV_RCL_ACT Return")
        lost = v.first_event("manual control lost")
        assert lost is not None and 0.5 <= lost - v._sticks_t <= 0.5 + 0.3  # COM_RC_LOSS_T after the last input (slack: a loaded machine)
        wait_until(lambda: np.linalg.norm(v.position_enu()[:2] - [0.0, 4.0]) < 0.3, 8.0, "Return to the new home")
    finally:
        stop.set()
        rig.close()


def test_pymavlink_ardupilot_manual_control_is_an_rc_override_loiter_flies_it_and_its_loss_is_radio_failsafe():
    """A ground station's joystick against ArduCopter: MANUAL_CONTROL at 20 Hz from SYSID_MYGCS
    (255) becomes RC overrides; `mode LOITER`, arm (refused while the throttle is above the
    deadband), full throttle climbs at PILOT_SPEED_UP, centred throttle holds, full forward stick
    settles at LOIT_SPEED, the yaw stick turns at PILOT_Y_RATE; another sender's sticks are
    ignored; stopping the stream is the radio failsafe 1 s later (FS_THR_ENABLE 1: RTL)."""
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(
        autopilot="ardupilot", profile="outdoor", k_pos=4.0, k_vel=8.0, a_max_mps2=8.0,
        params=(("LOIT_SPEED", 300.0), ("PILOT_SPEED_UP", 150), ("PILOT_Y_RATE", 45.0)))).start()
    mp = MavproxyStyle(port)
    sticks = {"x": 0, "y": 0, "z": 500, "r": 0}
    stop = threading.Event()

    def joystick():
        while not stop.is_set():
            mp.m.mav.manual_control_send(1, sticks["x"], sticks["y"], sticks["z"], sticks["r"], 0)
            time.sleep(0.05)

    stick_thread = threading.Thread(target=joystick, daemon=True)
    try:
        # a sender that is not SYSID_MYGCS: no override at all
        for _ in range(5):
            mp.m.mav.srcSystem = 254
            mp.m.mav.manual_control_send(1, 1000, 0, 1000, 0, 0)
        mp.m.mav.srcSystem = 255
        time.sleep(0.3)
        assert v.first_event("manual control: RC overrides") is None and not v._rc_override
        sticks["z"] = 1000
        stick_thread.start()
        assert mp.mode("LOITER") == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: v.first_event("manual control: RC overrides") is not None, 2.0, "overrides")
        assert mp.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED  # "Arm: Throttle too high"
        sticks["z"] = 500
        time.sleep(0.2)
        assert mp.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        time.sleep(0.5)
        assert v.position_enu()[2] < 0.05  # centred throttle on the ground: no takeoff
        sticks["z"] = 1000  # full throttle: PILOT_SPEED_UP
        wait_until(lambda: v.position_enu()[2] > 1.5, 4.0, "climb")
        assert v.velocity_enu()[2] == pytest.approx(1.5, abs=0.15)
        sticks["z"] = 550  # inside THR_DZ around mid throttle: hold
        time.sleep(1.0)
        z_hold = v.position_enu()[2]
        time.sleep(0.5)
        assert abs(v.position_enu()[2] - z_hold) < 0.1 and abs(v.velocity_enu()[2]) < 0.1
        sticks["x"] = 1000  # full forward (heading east, yaw 0): settles at LOIT_SPEED
        time.sleep(2.5)
        assert v.velocity_enu()[0] == pytest.approx(3.0, abs=0.2) and abs(v.velocity_enu()[1]) < 0.1
        sticks["x"] = 0
        sticks["r"] = 1000  # full right yaw: clockwise at PILOT_Y_RATE
        time.sleep(0.5)
        assert math.degrees(v.model.yaw_rate) == pytest.approx(-45.0, abs=5.0)
        sticks["r"] = 0
        assert v.mode_name == "loiter" and v.armed
        stop.set()  # the joystick goes silent
        stick_thread.join(1.0)
        t_last = v._rc_override_t
        wait_until(lambda: v.mode_name == "rtl", 3.0, "radio failsafe -> RTL")
        fs = v.first_event("radio failsafe")
        assert fs is not None and 1.0 <= fs - t_last <= 1.0 + 0.3  # FS_RADIO_RC_OVERRIDE_TIMEOUT_MS
        wait_until(lambda: not v._ardu_overrides_active(), 3.0, "overrides lapse after RC_OVERRIDE_TIME")
        assert v.clock() - t_last >= 3.0 - 0.1
    finally:
        stop.set()
        v.stop()


# -- SET_POSITION_TARGET_LOCAL_NED in the body and offset frames, and the yaw rate -------------
def heading_unit(yaw_enu):
    """Scene ENU unit vector (2,) of a heading (rad, ENU)."""
    return np.array([math.cos(yaw_enu), math.sin(yaw_enu)])


def angle_between(a, b):
    """a - b wrapped to [-pi, pi) (radians)."""
    return (a - b + math.pi) % (2 * math.pi) - math.pi


def test_mavsdk_px4_set_velocity_body_starts_offboard_flies_body_forward_and_turns_at_the_yawspeed():
    """MAVSDK's canonical offboard example: ``set_velocity_body`` (MAV_FRAME_BODY_NED, velocity
    and yaw rate; MAVSDK ``offboard_impl.cpp`` ``send_velocity_body``) then ``offboard.start()``.
    PX4 rotates the velocity by the heading and flies the yawspeed. The estimator frame is
    rotated against the scene and the vehicle faces neither axis, so body-forward is neither
    the scene's nor the estimator's x."""
    yaw0, est_yaw = 0.5, -0.9  # ENU heading in the scene, the estimator frame's rotation
    rig = MavsdkRig(autopilot="px4", profile="indoor", initial_yaw_rad=yaw0, estimator_yaw_rad=est_yaw,
                    k_pos=4.0, k_vel=8.0, a_max_mps2=8.0)
    try:
        act, tel, v = rig.action, rig.telemetry, rig.vehicle
        wait_until(lambda: tel.health().is_armable, 5.0, "health.is_armable")
        off = Offboard(rig.system)
        act.arm()
        off.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, -1.0, 0.0))  # climb at 1 m/s
        off.start()  # DO_SET_MODE OFFBOARD: accepted only if the body-frame setpoint counted
        wait_until(lambda: v.mode_name == "offboard", 2.0, "OFFBOARD")
        wait_until(lambda: v.position_enu()[2] > 1.0, 5.0, "climbing")
        # forward at 1.5 m/s: along the heading, which is neither a scene nor an estimator axis
        off.set_velocity_body(VelocityBodyYawspeed(1.5, 0.0, 0.0, 0.0))
        time.sleep(1.0)
        vel = v.velocity_enu()
        np.testing.assert_allclose(vel[:2], 1.5 * heading_unit(yaw0), atol=0.1)  # ground truth: body forward
        assert abs(vel[2]) < 0.1
        pv, att = tel.position_velocity_ned().velocity, tel.attitude_euler()  # the client's view (estimator frame)
        assert math.hypot(pv.north_m_s, pv.east_m_s) == pytest.approx(1.5, abs=0.1)
        course = math.degrees(math.atan2(pv.east_m_s, pv.north_m_s))
        assert abs(math.degrees(angle_between(math.radians(course), math.radians(att.yaw_deg)))) < 5.0  # where the nose points
        assert abs(angle_between(math.radians(att.yaw_deg), math.pi / 2 - (yaw0 - est_yaw))) < 0.02  # NED, estimator frame
        # turn clockwise at 30 deg/s (yawspeed, NED), no translation
        off.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 30.0))
        time.sleep(0.6)
        yaw_a, t_a = tel.attitude_euler().yaw_deg, time.monotonic()
        time.sleep(1.0)
        yaw_b, t_b = tel.attitude_euler().yaw_deg, time.monotonic()
        turned = math.degrees(angle_between(math.radians(yaw_b), math.radians(yaw_a)))
        assert turned / (t_b - t_a) == pytest.approx(30.0, abs=4.0)  # deg/s, clockwise seen from above
        assert math.degrees(v.model.yaw_rate) == pytest.approx(-30.0, abs=0.5)  # ENU: counter-clockwise positive
        assert tel.attitude_angular_velocity_body().yaw_rad_s == pytest.approx(math.radians(30.0), abs=0.01)
        assert np.linalg.norm(v.velocity_enu()) < 0.1
    finally:
        rig.close()


def still(v):
    """The vehicle (ground truth) has stopped: speed below 5 cm/s."""
    return np.linalg.norm(v.velocity_enu()) < 0.05


def test_pymavlink_ardupilot_guided_body_offset_local_offset_and_body_velocity_targets():
    """A companion script's GUIDED targets in the frames ArduCopter takes besides LOCAL_NED
    (``GCS_MAVLINK_Copter::handle_message_set_position_target_local_ned``): BODY_OFFSET_NED 2 m
    forward reaches the point 2 m ahead along the heading, LOCAL_OFFSET_NED reaches the current
    position plus the offset in the estimator's axes, BODY_NED velocity flies along the heading.
    The estimator frame is rotated against the scene and the vehicle faces neither axis."""
    yaw0, est_yaw = 2.2, 0.7
    port = free_udp_port()
    cfg = SimVehicleConfig(autopilot="ardupilot", profile="indoor", initial_yaw_rad=yaw0, estimator_yaw_rad=est_yaw,
                           k_pos=4.0, k_vel=8.0, a_max_mps2=8.0)  # stiff: the legs stay short in wall time
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), cfg).start()
    pos_only, vel_only = 0x0DF8, 0x0DC7  # type_mask: yaw and yaw rate ignored too

    def target(frame, mask, p=(0.0, 0.0, 0.0), vel=(0.0, 0.0, 0.0)):
        mp.m.mav.set_position_target_local_ned_send(0, 1, 1, frame, mask, *p, *vel, 0, 0, 0, 0, 0)

    def local_position():
        mp.drain()
        m = mp.latest("LOCAL_POSITION_NED", lambda m: True)
        return np.array([m.x, m.y, m.z])

    try:
        mp = MavproxyStyle(port)
        for msg_id in (M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, M.MAVLINK_MSG_ID_ATTITUDE):  # 10 Hz, not the 2-4 Hz SRn_ rates
            assert mp.long(M.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 100000) == M.MAV_RESULT_ACCEPTED
        mp.guided_takeoff(v, 1.0)
        wait_until(lambda: still(v), 5.0, "hovering")
        p0, lp0 = v.position_enu(), local_position()
        att = mp.latest("ATTITUDE", lambda m: True)
        assert abs(angle_between(att.yaw, math.pi / 2 - (yaw0 - est_yaw))) < 0.01  # NED heading in the estimator frame
        # BODY_OFFSET_NED: 2 m forward of where it is, at its altitude
        target(M.MAV_FRAME_BODY_OFFSET_NED, pos_only, p=(2.0, 0.0, 0.0))
        ahead = p0 + [*(2.0 * heading_unit(yaw0)), 0.0]
        wait_until(lambda: settled(v, ahead, 0.05), 6.0, "2 m ahead along the heading")
        assert v.model.yaw == pytest.approx(yaw0, abs=0.01)  # yaw ignored: no turn
        moved = local_position() - lp0  # the client's view: 2 m along ATTITUDE's heading
        assert np.hypot(*moved[:2]) == pytest.approx(2.0, abs=0.1) and abs(moved[2]) < 0.05
        assert abs(angle_between(math.atan2(moved[1], moved[0]), att.yaw)) < 0.05
        # LOCAL_OFFSET_NED: 1 m north, 1 m west and 0.5 m up of here, in the estimator's axes
        p1, lp1 = v.position_enu(), local_position()
        target(M.MAV_FRAME_LOCAL_OFFSET_NED, pos_only, p=(1.0, -1.0, -0.5))
        c, s = math.cos(est_yaw), math.sin(est_yaw)
        offset_scene = np.array([c * -1.0 - s * 1.0, s * -1.0 + c * 1.0, 0.5])  # ENU (-1, 1, 0.5) rotated by est_yaw
        wait_until(lambda: settled(v, p1 + offset_scene, 0.05), 6.0, "current position plus the offset")
        np.testing.assert_allclose(local_position() - lp1, [1.0, -1.0, -0.5], atol=0.1)
        # BODY_NED velocity: 1 m/s forward, streamed at 10 Hz
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            target(M.MAV_FRAME_BODY_NED, vel_only, vel=(1.0, 0.0, 0.0))
            time.sleep(0.1)
        np.testing.assert_allclose(v.velocity_enu(), [*heading_unit(yaw0), 0.0], atol=0.08)
        gp = mp.latest("LOCAL_POSITION_NED", lambda m: math.hypot(m.vx, m.vy) > 0.9)
        assert abs(angle_between(math.atan2(gp.vy, gp.vx), att.yaw)) < 0.08  # along the heading, in the client's frame
    finally:
        v.stop()


def test_pymavlink_offset_and_frd_frames_px4_drops_with_statustext_ardupilot_stops():
    """The per-autopilot refusals a script meets: PX4's receiver takes LOCAL_NED and BODY_NED only
    and drops LOCAL_OFFSET_NED with a STATUSTEXT (so it is no offboard signal: OFFBOARD refused)
    and a BODY_NED position (never used) as "invalid"; ArduCopter flies the offset frames (the
    test above) but answers a frame it does not take (BODY_FRD) with ``ModeGuided::init(true)``:
    it brakes and hovers, well before GUID_TIMEOUT would have stopped it."""
    px4_offboard = (M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6)
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot="px4", profile="indoor")).start()
    try:
        mp = MavproxyStyle(port)
        assert mp.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        mp.m.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_LOCAL_OFFSET_NED, 0x0DF8, 0, 0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0)
        mp.statustext("SET_POSITION_TARGET_LOCAL_NED coordinate frame 7 unsupported")  # 61 characters: two chunks
        assert mp.long(*px4_offboard) == M.MAV_RESULT_TEMPORARILY_REJECTED  # no recent setpoint
        mp.m.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_BODY_NED, 0x0DF8, 0, 0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0)
        mp.statustext("SET_POSITION_TARGET_LOCAL_NED invalid")
        assert mp.long(*px4_offboard) == M.MAV_RESULT_TEMPORARILY_REJECTED and v.setpoints_received == 0
        mp.m.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_BODY_NED, 0x0DC7, 0, 0, 0, 0, 0, -0.5, 0, 0, 0, 0, 0)
        assert mp.long(*px4_offboard) == M.MAV_RESULT_ACCEPTED and v.setpoints_received == 1  # a body-frame velocity counts
    finally:
        v.stop()

    port = free_udp_port()
    cfg = SimVehicleConfig(autopilot="ardupilot", profile="indoor", initial_yaw_rad=0.8, k_pos=4.0, k_vel=8.0, a_max_mps2=8.0)
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), cfg).start()
    try:
        mp = MavproxyStyle(port)
        mp.guided_takeoff(v, 1.0)
        for _ in range(8):  # BODY_NED: 1 m/s forward
            mp.m.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_BODY_NED, 0x0DC7, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0)
            time.sleep(0.1)
        assert v.velocity_enu()[:2] @ heading_unit(0.8) > 0.9
        mp.m.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_BODY_FRD, 0x0DC7, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0)
        wait_until(lambda: still(v), 1.5, "stopped by the unsupported frame, not by GUID_TIMEOUT (3 s)")
        assert v.first_event("guided: input not valid (unsupported coordinate frame 12): stop") is not None
        assert v.first_event("guided timeout") is None and v.mode_name == "guided" and v.position_enu()[2] > 0.9
        assert v.statustexts == [] or all("coordinate frame" not in t for _, t in v.statustexts)  # ArduCopter says nothing
    finally:
        v.stop()
