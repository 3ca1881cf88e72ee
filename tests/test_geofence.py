"""Geofence and rally points of the simulated vehicle, driven by real clients: MAVSDK's Geofence
plugin against the PX4 personality, pymavlink the way MAVProxy's ``fence`` / ``rally`` modules
upload (mission_type FENCE / RALLY) against the ArduCopter one, and a raw companion for the
protocol's error paths. Rules and sources: ``onfly/mavlink/geofence.py``, ``mission.py`` and
docs/flight.md "Geofence and rally points"."""

import math
import time

import numpy as np
import pytest
from mavsdk.plugins.geofence.geofence import FenceType, GeofenceData, Point, Polygon
from mavsdk.plugins.geofence.geofence import Geofence as MavsdkGeofence
from mavsdk.plugins.offboard.offboard import Offboard, PositionNedYaw
from mavsdk.plugins.telemetry.telemetry import FlightMode
from test_mavlink_clients import MavproxyStyle, MavsdkRig, free_udp_port, wait_until
from test_mission import e7, latlon, raw, send, upload, wait_msg

from onfly.mavlink import rtl
from onfly.mavlink.geofence import ardu_rally_destination, fence_from_items, px4_rally_destination
from onfly.mavlink.link import MavlinkLink, mavlink2, memory_link_pair
from onfly.mavlink.sim_vehicle import SimMavlinkVehicle, SimVehicleConfig

M = mavlink2
FENCE, RALLY = M.MAV_MISSION_TYPE_FENCE, M.MAV_MISSION_TYPE_RALLY
pytestmark = pytest.mark.timeout(120)
SQUARE = [(-6.0, -6.0), (6.0, -6.0), (6.0, 8.0), (-6.0, 8.0)]  # east, north (m): the inclusion polygon


def fence_item(seq, east, north, n=4, command=M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, frame=M.MAV_FRAME_GLOBAL_INT):
    return M.MAVLink_mission_item_int_message(1, 1, seq, frame, command, 0, 1, float(n), 0, 0, 0, *e7(east, north), 0.0, FENCE)


def rally_item(seq, east, north, alt, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
    return M.MAVLink_mission_item_int_message(1, 1, seq, frame, M.MAV_CMD_NAV_RALLY_POINT, 0, 1, 0, 0, 0, 0, *e7(east, north), alt, RALLY)


def download(c, mission_type, timeout_s=3.0):
    """MISSION_REQUEST_LIST -> COUNT -> MISSION_REQUEST_INT per seq, all with ``mission_type``."""
    mav = c.link.mav
    n = len(c.of_type("MISSION_COUNT"))
    send(c, mav.mission_request_list_encode(1, 1, mission_type))
    count = wait_msg(c, "MISSION_COUNT", n, timeout_s=timeout_s)
    assert count.mission_type == mission_type
    out = []
    for seq in range(count.count):
        k = len(c.of_type("MISSION_ITEM_INT"))
        send(c, mav.mission_request_int_encode(1, 1, seq, mission_type))
        out.append(wait_msg(c, "MISSION_ITEM_INT", k, lambda m, s=seq: m.seq == s, timeout_s))
    send(c, mav.mission_ack_encode(1, 1, M.MAV_MISSION_ACCEPTED, mission_type))
    return out


# -- MAVSDK Geofence plugin, PX4 outdoor -----------------------------------------------------------
def test_mavsdk_px4_geofence_upload_breach_holds_and_clear():
    rig = MavsdkRig(autopilot="px4", profile="outdoor")
    try:
        v, geofence, offboard = rig.vehicle, MavsdkGeofence(rig.system), Offboard(rig.system)
        pts = [Point(*latlon(e, n)) for e, n in SQUARE]
        geofence.upload_geofence(GeofenceData(polygons=[Polygon(pts, FenceType.INCLUSION)], circles=[]))
        assert [it.command for it in v.mission.fence] == [M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION] * 4
        assert [it.params[0] for it in v.mission.fence] == [4.0] * 4 and len(v.mission.fence_zones.zones) == 1
        back = geofence.download_geofence()
        assert len(back.polygons) == 1 and back.polygons[0].fence_type == FenceType.INCLUSION
        for up, down in zip(pts, back.polygons[0].points):
            assert down.latitude_deg == pytest.approx(up.latitude_deg, abs=2e-7)
            assert down.longitude_deg == pytest.approx(up.longitude_deg, abs=2e-7)
        # offboard up to 2.5 m, then a setpoint 15 m north: the fence is at 8 m north
        wait_until(lambda: rig.telemetry.health().is_armable, 5.0, "armable")
        rig.action.arm()
        offboard.set_position_ned(PositionNedYaw(0.0, 0.0, -2.5, 0.0))
        offboard.start()
        wait_until(lambda: v.position_enu()[2] > 2.0, 6.0, "offboard climb")
        assert not v.fence.breached
        offboard.set_position_ned(PositionNedYaw(15.0, 0.0, -2.5, 0.0))
        # GF_ACTION 2 (default): Hold at the breach; the client sees the mode change
        wait_until(lambda: rig.telemetry.flight_mode() == FlightMode.HOLD, 8.0, "client sees HOLD after the breach")
        assert v.mode_name == "auto.loiter" and v.armed
        assert any("Geofence: approaching or outside geofence" in t for _, t in v.statustexts)
        # the hold point is where the breach was seen: within one 200 ms check at <= 5 m/s of the
        # line; the vehicle brakes to it (a_max 5 m/s^2: 2.5 m from 5 m/s) and stays, short of 15 m
        with v._lock:
            hold_north = float(v._target.p[1])
        assert 8.0 <= hold_north < 9.2, hold_north
        wait_until(lambda: np.linalg.norm(v.velocity_enu()) < 0.2, 5.0, "stopped")
        assert 8.0 <= v.position_enu()[1] < 12.5, v.position_enu()
        # clear_geofence: MISSION_CLEAR_ALL with mission_type FENCE; nothing is checked any more
        geofence.clear_geofence()
        assert v.mission.fence == [] and v.mission.fence_zones.zones == ()
        wait_until(lambda: not v.fence.breached, 1.0, "no breach without a fence")
    finally:
        rig.close()


# -- pymavlink the way MAVProxy's fence / rally modules work, ArduCopter outdoor ----------------------
class FenceModule(MavproxyStyle):
    """MAVProxy's ``fence load`` / ``rally load`` and ``fence list``: the mission item protocol
    with the module's mission_type (MAVProxy's MissionItemProtocol modules)."""

    def load(self, items, mission_type, timeout_s=10.0):
        self.drain()
        self.m.mav.mission_count_send(1, 1, len(items), mission_type)
        asked = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.m.recv_match(type=["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"], blocking=True, timeout=0.5)
            if msg is None:
                continue
            if msg.get_type() == "MISSION_ACK":
                return msg, asked
            asked.append((msg.seq, msg.mission_type))
            self.m.mav.send(items[msg.seq])
        raise AssertionError("no MISSION_ACK")

    def list(self, mission_type, timeout_s=5.0):
        self.drain()
        self.m.mav.mission_request_list_send(1, 1, mission_type)
        count = self.m.recv_match(type="MISSION_COUNT", blocking=True, timeout=timeout_s)
        assert count is not None and count.mission_type == mission_type
        got = []
        for seq in range(count.count):
            self.m.mav.mission_request_int_send(1, 1, seq, mission_type)
            item = self.m.recv_match(type="MISSION_ITEM_INT", blocking=True, timeout=timeout_s, condition=f"MISSION_ITEM_INT.seq=={seq}")
            assert item is not None and item.mission_type == mission_type
            got.append(item)
        self.m.mav.mission_ack_send(1, 1, M.MAV_MISSION_ACCEPTED, mission_type)
        return got


def test_pymavlink_mavproxy_fence_on_ardupilot_breach_takes_fence_action():
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1),
                          SimVehicleConfig(autopilot="ardupilot", profile="outdoor", k_pos=4.0, k_vel=8.0, a_max_mps2=8.0)).start()
    try:
        mp = FenceModule(port)
        items = [fence_item(i, e, n) for i, (e, n) in enumerate(SQUARE)]
        ack, asked = mp.load(items, FENCE)
        assert ack.type == M.MAV_MISSION_ACCEPTED and ack.mission_type == FENCE
        assert asked == [(i, FENCE) for i in range(4)]  # every request carries mission_type FENCE
        got = mp.list(FENCE)
        assert [(g.command, g.param1, g.x, g.y) for g in got] == [(it.command, 4.0, it.x, it.y) for it in items]
        # FENCE_ENABLE is 0 on Copter: `param set FENCE_ENABLE 1`
        mp.m.mav.param_set_send(1, 1, b"FENCE_ENABLE", 1.0, M.MAV_PARAM_TYPE_INT8)
        wait_until(lambda: v.params["FENCE_ENABLE"] == 1, 3.0, "FENCE_ENABLE set")
        mp.guided_takeoff(v, 2.0)
        # `guided` 20 m north: out through the fence at 8 m -> FENCE_ACTION 1 (RTL)
        gp = mp.m.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=3)
        mp.drain()
        mp.m.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_DO_REPOSITION, 0, 0, -1,
                                  M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan, *e7(0.0, 20.0), 2.0)
        assert mp.ack(M.MAV_CMD_DO_REPOSITION) == M.MAV_RESULT_ACCEPTED and gp is not None
        hb = mp.latest("HEARTBEAT", lambda m: m.custom_mode == 6, timeout_s=8.0)  # the client sees RTL
        assert hb is not None and v.mode_name == "rtl"
        assert any(t == "Polygon fence breached" for _, t in v.statustexts)
        assert 8.0 <= v.position_enu()[1] < 11.0
    finally:
        v.stop()


def test_ardupilot_fence_prearm_outside_indoors_and_protocol_errors():
    # outside the fence on the ground: "Vehicle breaching Polygon fence", arming refused
    ap, va = raw("ardupilot", initial_position_m=(0.0, 12.0, 0.0))
    ai, vi = raw("ardupilot", profile="indoor")
    try:
        good = [fence_item(i, e, n) for i, (e, n) in enumerate(SQUARE)]
        assert upload(ap, good, FENCE) == M.MAV_MISSION_ACCEPTED
        assert ap.command(M.MAV_CMD_DO_SET_MODE, 1, 4) == M.MAV_RESULT_ACCEPTED
        assert ap.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED  # FENCE_ENABLE 0: no fence
        assert ap.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0) == M.MAV_RESULT_ACCEPTED
        send(ap, ap.link.mav.param_set_encode(1, 1, b"FENCE_ENABLE", 1.0, M.MAV_PARAM_TYPE_INT8))
        wait_until(lambda: va.params["FENCE_ENABLE"] == 1, 2.0, "FENCE_ENABLE")
        time.sleep(0.1)  # the 25 Hz check
        assert ap.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED and not va.armed
        assert any(t == "Vehicle breaching Polygon fence" for _, t in va.statustexts)
        # indoors (no home location) an enabled circle / polygon fence needs a position
        send(ai, ai.link.mav.param_set_encode(1, 1, b"FENCE_ENABLE", 1.0, M.MAV_PARAM_TYPE_INT8))
        wait_until(lambda: vi.params["FENCE_ENABLE"] == 1, 2.0, "FENCE_ENABLE indoors")
        assert ai.command(M.MAV_CMD_DO_SET_MODE, 1, 4) == M.MAV_RESULT_ACCEPTED
        assert ai.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED
        assert any(t == "Fence requires position" for _, t in vi.statustexts)
        # a bad polygon: the vertex counts disagree -> validate_fence, ACK ERROR, the old fence kept
        bad = good[:2] + [fence_item(2, 6.0, 8.0, n=5), fence_item(3, -6.0, 8.0)]
        n = len(ap.of_type("MISSION_ACK"))
        assert upload(ap, bad, FENCE) == M.MAV_MISSION_ERROR
        assert wait_msg(ap, "MISSION_ACK", n).mission_type == FENCE
        assert any(t == "Unexpected vertex count want=4 got=5" for _, t in va.statustexts)
        assert any(t == "Fence validation failed" for _, t in va.statustexts) and len(va.mission.fence) == 4
        assert upload(ap, [fence_item(i, e, n, n=2) for i, (e, n) in enumerate(SQUARE[:2])], FENCE) == M.MAV_MISSION_ERROR
        assert any(t == "Invalid vertex count (2)" for _, t in va.statustexts)
        # the wrong seq: INVALID_SEQUENCE with mission_type FENCE, the transfer goes on
        send(ap, ap.link.mav.mission_count_encode(1, 1, 4, FENCE))
        req = wait_msg(ap, "MISSION_REQUEST", pred=lambda m: m.mission_type == FENCE and m.seq == 0)
        n = len(ap.of_type("MISSION_ACK"))
        send(ap, good[1])
        ack = wait_msg(ap, "MISSION_ACK", n)
        assert (ack.type, ack.mission_type, req.seq) == (M.MAV_MISSION_INVALID_SEQUENCE, FENCE, 0)
        assert upload(ap, good, FENCE) == M.MAV_MISSION_ACCEPTED
        # rally: only NAV_RALLY_POINT in a relative frame
        assert upload(ap, [rally_item(0, 0.0, 20.0, 5.0, frame=M.MAV_FRAME_GLOBAL_INT)], RALLY) == M.MAV_MISSION_UNSUPPORTED_FRAME
        assert upload(ap, [fence_item(0, 0.0, 0.0)], RALLY) == M.MAV_MISSION_UNSUPPORTED
        # MISSION_CLEAR_ALL with mission_type FENCE clears the fence only
        n = len(ap.of_type("MISSION_ACK"))
        send(ap, ap.link.mav.mission_clear_all_encode(1, 1, FENCE))
        assert wait_msg(ap, "MISSION_ACK", n).mission_type == FENCE and va.mission.fence == []
        assert ap.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED  # inside the 300 m circle now
    finally:
        for c, v in ((ap, va), (ai, vi)):
            c.stop()
            v.stop()


def test_px4_fence_protocol_rules_and_indoor_fence_is_never_checked():
    px, vp = raw("px4")
    pi, vi = raw("px4", profile="indoor")
    try:
        good = [fence_item(i, e, n) for i, (e, n) in enumerate(SQUARE)]
        # a polygon of 2 vertices: "Fence: too few vertices" -> MISSION_ACK ERROR (mission_type FENCE)
        n = len(px.of_type("MISSION_ACK"))
        assert upload(px, [fence_item(i, e, n_, n=2) for i, (e, n_) in enumerate(SQUARE[:2])], FENCE) == M.MAV_MISSION_ERROR
        assert wait_msg(px, "MISSION_ACK", n).mission_type == FENCE and vp.mission.fence == []
        # fence commands in a mission upload are refused (ERROR); rally / fence counts past storage -> NO_SPACE
        assert upload(px, [M.MAVLink_mission_item_int_message(1, 1, 0, M.MAV_FRAME_GLOBAL_INT, M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                                                              0, 1, 4, 0, 0, 0, *e7(0, 0), 0, 0)]) == M.MAV_MISSION_ERROR
        for mt, cap in ((FENCE, 64), (RALLY, 32)):
            n = len(px.of_type("MISSION_ACK"))
            send(px, px.link.mav.mission_count_encode(1, 1, cap + 1, mt))
            ack = wait_msg(px, "MISSION_ACK", n)
            assert (ack.type, ack.mission_type) == (M.MAV_MISSION_NO_SPACE, mt)
        # the wrong seq is ignored and the request repeated, with mission_type FENCE
        k = len(px.of_type("MISSION_REQUEST_INT"))  # int mode since the last MISSION_ITEM_INT
        send(px, px.link.mav.mission_count_encode(1, 1, 4, FENCE))
        wait_msg(px, "MISSION_REQUEST_INT", k, pred=lambda m: m.seq == 0 and m.mission_type == FENCE)
        send(px, good[2])
        time.sleep(0.4)
        again = [m for _, m in px.of_type("MISSION_REQUEST_INT")[k:]]
        assert len(again) >= 2 and all(m.seq == 0 and m.mission_type == FENCE for m in again)
        for it in good:
            send(px, it)
        wait_until(lambda: len(vp.mission.fence) == 4, 2.0, "fence stored")
        back = download(px, FENCE)
        assert [(b.command, b.param1, b.x, b.y, b.frame) for b in back] == \
            [(g.command, 4.0, g.x, g.y, M.MAV_FRAME_GLOBAL_INT) for g in good]
        # outside the fence on the ground: arming refused by the geofence check (GF_ACTION 2)
        assert not vp.fence.breached
        # indoors: the upload is stored but there is no global position to check it against
        assert upload(pi, good, FENCE) == M.MAV_MISSION_ACCEPTED and len(vi.mission.fence) == 4
        assert vi.fence.px4_breached(np.array([0.0, 50.0, 3.0])) is None
        assert pi.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    finally:
        for c, v in ((px, vp), (pi, vi)):
            c.stop()
            v.stop()


def test_px4_arming_refused_outside_the_fence():
    c, v = raw("px4", initial_position_m=(0.0, 12.0, 0.0))
    try:
        assert upload(c, [fence_item(i, e, n) for i, (e, n) in enumerate(SQUARE)], FENCE) == M.MAV_MISSION_ACCEPTED
        wait_until(lambda: v.fence.breached, 1.0, "breach seen on the ground")
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED and not v.armed
        assert any(t == "Geofence: approaching or outside geofence" for _, t in v.statustexts)
        send(c, c.link.mav.param_set_encode(1, 1, b"GF_ACTION", _px4_int(0), M.MAV_PARAM_TYPE_INT32))
        wait_until(lambda: v.params["GF_ACTION"] == 0, 2.0, "GF_ACTION 0")
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED  # None: no check
    finally:
        c.stop()
        v.stop()


def _px4_int(i):
    import struct
    return struct.unpack("<f", struct.pack("<i", int(i)))[0]


# -- rally points ---------------------------------------------------------------------------------
def test_rally_round_trip_on_both_and_the_return_destination_rules():
    px, vp = raw("px4")
    ap, va = raw("ardupilot")
    try:
        pts = [rally_item(0, 0.0, 30.0, 5.0), rally_item(1, 40.0, 0.0, 8.0)]
        for c, v in ((px, vp), (ap, va)):
            assert upload(c, pts, RALLY) == M.MAV_MISSION_ACCEPTED and len(v.mission.rally) == 2
            back = download(c, RALLY)
            assert [(b.command, b.x, b.y, b.z) for b in back] == [(M.MAV_CMD_NAV_RALLY_POINT, p.x, p.y, p.z) for p in pts]
            assert back[0].frame == (M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT if c is px else M.MAV_FRAME_GLOBAL_RELATIVE_ALT)
        assert any(t == "Rally points received" for _, t in va.statustexts)
        home = np.zeros(3)
        # PX4 RTL_TYPE 0: the closest of home and the safe points (> 10 m from home, 2 m better)
        near = px4_rally_destination(vp, np.array([0.0, 25.0, 3.0]), home, vp.mission.rally)
        assert near == pytest.approx([0.0, 30.0, 5.0], abs=0.02)
        assert px4_rally_destination(vp, np.array([0.0, 5.0, 3.0]), home, vp.mission.rally) is None  # home is closer
        # ArduCopter: the nearest rally point if closer than home (RALLY_INCL_HOME 1), within RALLY_LIMIT_KM
        assert ardu_rally_destination(va, np.array([30.0, 2.0, 3.0]), home, va.mission.rally, va.params) == \
            pytest.approx([40.0, 0.0, 8.0], abs=0.02)
        assert ardu_rally_destination(va, np.array([0.0, 10.0, 3.0]), home, va.mission.rally, va.params) is None
        far = dict(va.params, RALLY_LIMIT_KM=0.01)  # 10 m: the rally points are all beyond it
        assert ardu_rally_destination(va, np.array([30.0, 2.0, 3.0]), home, va.mission.rally, far) is None
        # the Return state machines fly to the destination and land there
        noop = lambda *a: None  # noqa: E731
        r = rtl.ArduCopterReturn(home, [30.0, 2.0, 3.0], False, 0.0, va.params, noop, noop, dest_m=[40.0, 0.0, 8.0])
        assert r.return_z_m == pytest.approx(15.0)  # RTL_ALT 1500 cm over the rally point's 8 m
        r.step(0.0, [30.0, 2.0, 15.0])
        assert r.step(0.1, [30.0, 2.0, 15.0]).p[:2] == pytest.approx([40.0, 0.0])
        # clear with mission_type RALLY
        n = len(px.of_type("MISSION_ACK"))
        send(px, px.link.mav.mission_clear_all_encode(1, 1, RALLY))
        assert wait_msg(px, "MISSION_ACK", n).mission_type == RALLY and vp.mission.rally == []
    finally:
        for c, v in ((px, vp), (ap, va)):
            c.stop()
            v.stop()


@pytest.mark.slow  # real time, ~20 s: opt-in (`-m slow`)
def test_px4_return_mode_lands_on_the_closest_rally_point():
    c, v = raw("px4", params=(("RTL_RETURN_ALT", 4.0),))
    try:
        assert upload(c, [rally_item(0, 0.0, 14.0, 3.0)], RALLY) == M.MAV_MISSION_ACCEPTED
        assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, math.nan) == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: v.mode_name == "auto.loiter" and v.position_enu()[2] > 2.3, 8.0, "take-off")
        c.link.send(M.MAVLink_command_int_message(1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_DO_REPOSITION, 0, 0, -1,
                                                  1, 0, math.nan, *e7(0.0, 12.0), 2.5))
        wait_until(lambda: v.position_enu()[1] > 11.5, 8.0, "north of the rally point's side")
        assert c.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH) == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: not v.armed, 25.0, "landed on the rally point")
        assert np.linalg.norm(v.position_enu()[:2] - [0.0, 14.0]) < 0.5
    finally:
        c.stop()
        v.stop()


def test_fence_geometry_inclusion_exclusion_and_circles():
    a, b = memory_link_pair(1, 191, 1, 1)
    v = SimMavlinkVehicle(b, SimVehicleConfig(profile="outdoor"))
    from onfly.mavlink.mission import MissionItem

    def it(cmd, e, n, p1):
        return MissionItem(cmd, M.MAV_FRAME_GLOBAL, (p1, 0, 0, 0), *e7(e, n), 0.0, False)

    items = [it(M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, e, n, 4) for e, n in SQUARE]
    items += [it(M.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION, 0.0, 5.0, 2.0)]
    items += [it(M.MAV_CMD_NAV_FENCE_RETURN_POINT, 0.0, 0.0, 0)]
    fence = fence_from_items(items)
    assert len(fence.zones) == 2

    def ok(e, n):
        return fence.allows(*v._global_from_scene([e, n, 0.0])[:2])

    assert ok(0.0, 0.0) and ok(5.9, 7.9) and not ok(0.0, 8.1) and not ok(-6.1, 0.0)
    assert not ok(0.0, 5.5) and ok(0.0, 7.5)  # inside the 2 m exclusion circle at (0, 5) is a breach
