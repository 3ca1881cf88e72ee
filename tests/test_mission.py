"""The mission protocol and AUTO mission flight of the simulated vehicle, driven by real clients
(MAVSDK's Mission plugin on the PX4 personality, pymavlink the way MAVProxy's ``wp load`` /
``wp list`` work on the ArduCopter one) and by a raw MAVLink companion for the protocol's
error paths. Rules and sources: ``onfly/mavlink/mission.py`` and docs/flight.md "Missions"."""

import math
import threading
import time

import numpy as np
import pytest
from mavsdk.plugins.mission.mission import Mission, MissionItem, MissionPlan
from test_mavlink_clients import MavproxyStyle, MavsdkRig, free_udp_port, wait_until
from test_sim_vehicle import Companion

from onfly.mavlink.link import MavlinkLink, mavlink2, memory_link_pair
from onfly.mavlink.sim_vehicle import EARTH_RADIUS_M, SimMavlinkVehicle, SimVehicleConfig

M = mavlink2  # the MAVLink 2 dialect (MISSION_* with mission_type)
pytestmark = pytest.mark.timeout(120)
ORIGIN = (47.397742, 8.545594, 488.0)  # the outdoor profile's global origin


def latlon(east_m, north_m):
    """Scene ENU metres -> (lat, lon) degrees around the outdoor origin (the vehicle's projection)."""
    return (ORIGIN[0] + math.degrees(north_m / EARTH_RADIUS_M),
            ORIGIN[1] + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(ORIGIN[0])))))


def e7(east_m, north_m):
    lat, lon = latlon(east_m, north_m)
    return int(round(lat * 1e7)), int(round(lon * 1e7))


class Trace:
    """Samples the vehicle's ground-truth position at 20 Hz in the background."""

    def __init__(self, vehicle):
        self.v, self.points, self.speeds_xy, self._stop = vehicle, [], [], threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        while not self._stop.is_set():
            self.points.append((time.monotonic(), *self.v.position_enu()))
            self.speeds_xy.append(float(np.linalg.norm(self.v.velocity_enu()[:2])))
            time.sleep(0.05)

    def stop(self):
        """(N, 3) positions; :attr:`times` holds their sample times."""
        self._stop.set()
        self._t.join(1)
        arr = np.array(self.points)
        self.times = arr[:, 0]
        return arr[:, 1:]


# -- MAVSDK Mission plugin, PX4 outdoor ---------------------------------------------------------
def test_mavsdk_px4_upload_download_and_fly_a_three_waypoint_mission():
    rig = MavsdkRig(autopilot="px4", profile="outdoor")
    try:
        v, mission = rig.vehicle, Mission(rig.system)
        wps = [(0.0, 4.0, 3.0), (4.0, 4.0, 3.0), (4.0, 0.0, 4.0)]  # east, north, up (m above home)
        items = [MissionItem(latitude_deg=latlon(e, n)[0], longitude_deg=latlon(e, n)[1], relative_altitude_m=u,
                             speed_m_s=3.0, is_fly_through=False, acceptance_radius_m=0.5) for e, n, u in wps]
        mission.upload_mission(MissionPlan(items))
        assert len(v.mission.items) >= 3  # MAVSDK adds a DO_CHANGE_SPEED before each waypoint
        back = mission.download_mission().mission_items
        assert len(back) == 3
        for up, down in zip(items, back):
            assert down.latitude_deg == pytest.approx(up.latitude_deg, abs=2e-7)
            assert down.longitude_deg == pytest.approx(up.longitude_deg, abs=2e-7)
            assert down.relative_altitude_m == pytest.approx(up.relative_altitude_m, abs=1e-3)
            assert down.speed_m_s == pytest.approx(3.0) and down.acceptance_radius_m == pytest.approx(0.5)
            assert down.is_fly_through == up.is_fly_through
        wait_until(lambda: rig.telemetry.health().is_armable, 5.0, "armable")
        rig.action.arm()
        trace = Trace(v)
        mission.start_mission()  # PX4 AUTO.MISSION: armed on the ground it takes off by itself
        wait_until(lambda: v.mode_name == "auto.mission", 3.0, "AUTO.MISSION")
        wait_until(mission.is_mission_finished, 45.0, "mission finished (MAVSDK)")
        pts = trace.stop()
        progress = mission.mission_progress()
        assert progress.current == progress.total == 3
        # ground truth: every waypoint passed within its 0.5 m acceptance radius and NAV_MC_ALT_RAD
        for e, n, u in wps:
            d_xy = np.linalg.norm(pts[:, :2] - [e, n], axis=1)
            k = int(np.argmin(d_xy))
            assert d_xy[k] < 0.55 and abs(pts[k, 2] - u) < 0.85, (e, n, u, d_xy[k], pts[k])
        # the vertical take-off came first (PX4 do_need_vertical_takeoff), then the waypoints in order
        first_up = int(np.argmax(pts[:, 2] > 2.0))
        assert np.linalg.norm(pts[first_up, :2]) < 0.3
        order = [int(np.argmin(np.linalg.norm(pts[:, :2] - [e, n], axis=1))) for e, n, _ in wps]
        assert order == sorted(order)
        # the end: "Mission finished, loitering", Commander switches to Hold over the last waypoint
        wait_until(lambda: v.mode_name == "auto.loiter", 3.0, "Hold after the mission")
        assert any("Mission finished, loitering" in t for _, t in v.statustexts)
        assert np.linalg.norm(v.position_enu() - [4.0, 0.0, 4.0]) < 0.9 and v.armed
    finally:
        rig.close()


# -- pymavlink the way MAVProxy's wp module works, ArduCopter outdoor --------------------------
class WpModule(MavproxyStyle):
    """``wp load`` / ``wp list`` as MAVProxy's wp module does them: MISSION_COUNT, answer each
    MISSION_REQUEST(_INT) with the MISSION_ITEM_INT asked for, until the MISSION_ACK."""

    def wp_load(self, items, timeout_s=10.0):
        self.drain()
        self.m.mav.mission_count_send(self.m.target_system, self.m.target_component, len(items), M.MAV_MISSION_TYPE_MISSION)
        asked = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            msg = self.m.recv_match(type=["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"], blocking=True, timeout=0.5)
            if msg is None:
                continue
            if msg.get_type() == "MISSION_ACK":
                return msg.type, asked
            asked.append((msg.get_type(), msg.seq))
            self.m.mav.send(items[msg.seq])
        raise AssertionError("no MISSION_ACK for the upload")

    def wp_list(self, timeout_s=10.0):
        self.drain()
        self.m.mav.mission_request_list_send(self.m.target_system, self.m.target_component, M.MAV_MISSION_TYPE_MISSION)
        count = self.m.recv_match(type="MISSION_COUNT", blocking=True, timeout=timeout_s)
        assert count is not None, "no MISSION_COUNT"
        got = []
        for seq in range(count.count):
            self.m.mav.mission_request_int_send(self.m.target_system, self.m.target_component, seq, M.MAV_MISSION_TYPE_MISSION)
            item = self.m.recv_match(type="MISSION_ITEM_INT", blocking=True, timeout=timeout_s, condition=f"MISSION_ITEM_INT.seq=={seq}")
            assert item is not None, f"no item {seq}"
            got.append(item)
        self.m.mav.mission_ack_send(self.m.target_system, self.m.target_component, M.MAV_MISSION_ACCEPTED, M.MAV_MISSION_TYPE_MISSION)
        return got


def item_int(seq, east, north, alt, command=M.MAV_CMD_NAV_WAYPOINT, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT, p1=0.0):
    x, y = e7(east, north)
    return M.MAVLink_mission_item_int_message(1, 1, seq, frame, command, 0, 1, p1, 0.0, 0.0, 0.0, x, y, alt, M.MAV_MISSION_TYPE_MISSION)


@pytest.mark.slow  # real time, ~8 s: opt-in (`-m slow`)
def test_pymavlink_mavproxy_wp_load_and_auto_on_ardupilot():
    port = free_udp_port()
    v = SimMavlinkVehicle(MavlinkLink(f"udpout:127.0.0.1:{port}", 1, 1), SimVehicleConfig(autopilot="ardupilot", profile="outdoor")).start()
    try:
        mp = WpModule(port)
        wps = [(0.0, 6.0, 3.0), (6.0, 6.0, 3.0), (6.0, 0.0, 4.0)]
        # a waypoint file: item 0 is home (ArduPilot overwrites it with its own home)
        items = [item_int(0, 0.0, 0.0, 0.0, frame=M.MAV_FRAME_GLOBAL)] + [item_int(i + 1, *w) for i, w in enumerate(wps)]
        result, asked = mp.wp_load(items)
        assert result == M.MAV_MISSION_ACCEPTED
        assert [s for _, s in asked] == [0, 1, 2, 3] and {t for t, _ in asked} == {"MISSION_REQUEST"}  # ArduPilot asks with the legacy message
        # arm and take off in GUIDED (ArduCopter cannot arm in AUTO), then AUTO
        assert mp.mode("GUIDED") == M.MAV_RESULT_ACCEPTED
        assert mp.long(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert mp.long(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == M.MAV_RESULT_ACCEPTED
        wait_until(lambda: v.position_enu()[2] > 1.9, 10.0, "take-off to 2 m")
        # `param set WPNAV_SPEED 300`: the mission flies at 3 m/s (cm/s on the wire, read live),
        # not the 10 m/s default, so the 20 Hz trace below samples the passes finely
        mp.m.mav.param_set_send(1, 1, b"WPNAV_SPEED", 300.0, M.MAV_PARAM_TYPE_REAL32)
        wait_until(lambda: v.params["WPNAV_SPEED"] == 300.0, 3.0, "WPNAV_SPEED set")
        trace = Trace(v)
        assert mp.mode("AUTO") == M.MAV_RESULT_ACCEPTED
        reached = []
        deadline = time.monotonic() + 45.0
        while time.monotonic() < deadline and 3 not in reached:
            msg = mp.m.recv_match(type=["MISSION_ITEM_REACHED", "MISSION_CURRENT"], blocking=True, timeout=0.5)
            if msg is not None and msg.get_type() == "MISSION_ITEM_REACHED":
                reached.append(msg.seq)
            if msg is not None and msg.get_type() == "MISSION_CURRENT" and len(reached) == 1 and 1 in reached:
                # the mission runs: AP_Mission::clear refuses, the mission is kept
                mp.m.mav.mission_clear_all_send(1, 1, M.MAV_MISSION_TYPE_MISSION)
                ack = mp.m.recv_match(type="MISSION_ACK", blocking=True, timeout=3)
                assert ack is not None and ack.type == M.MAV_MISSION_ERROR and len(v.mission.items) == 4
                assert msg.total == 3 and msg.mission_state == M.MISSION_STATE_ACTIVE  # total excludes home
        pts = trace.stop()
        assert reached == [1, 2, 3]
        assert 2.5 < max(trace.speeds_xy) < 3.2  # WPNAV_SPEED in cm/s, flown in m/s
        for e, n, u in wps:  # within WPNAV_RADIUS (2 m, 3-D) of each waypoint, in order; the 20 Hz
            d = np.linalg.norm(pts - [e, n, u], axis=1)  # trace at 3 m/s samples every 0.15 m
            assert d.min() < 2.0 + 0.2, (e, n, u, d.min())
        order = [int(np.argmin(np.linalg.norm(pts - list(w), axis=1))) for w in wps]
        assert order == sorted(order)
        # exit_mission in the air: it loiters in AUTO
        wait_until(lambda: np.abs(v.velocity_enu()).max() < 0.2, 5.0, "loitering after the mission")
        assert v.mode_name == "auto" and v.armed and v.mission.ap_state == "complete"
        # `wp list`: item 0 is home, then the items as stored (frame GLOBAL_RELATIVE_ALT)
        got = mp.wp_list()
        assert len(got) == 4
        home_x, home_y = e7(*v.mission.home_scene[:2])
        assert (got[0].x, got[0].y, got[0].frame) == (home_x, home_y, M.MAV_FRAME_GLOBAL)
        assert got[0].z == pytest.approx(ORIGIN[2], abs=0.02)
        for item, up in zip(got[1:], items[1:]):
            assert (item.command, item.frame, item.x, item.y) == (M.MAV_CMD_NAV_WAYPOINT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT, up.x, up.y)
            assert item.z == pytest.approx(up.z, abs=0.01)
    finally:
        v.stop()


# -- the protocol's error paths, against a raw companion ----------------------------------------
def raw(autopilot, profile="outdoor", **kw):
    a, b = memory_link_pair(1, 191, 1, 1)
    cfg = dict(heartbeat_period_s=0.2, k_pos=4.0, k_vel=8.0, a_max_mps2=8.0, autopilot=autopilot, profile=profile)
    cfg.update(kw)
    vehicle = SimMavlinkVehicle(b, SimVehicleConfig(**cfg)).start()
    return Companion(a), vehicle


def wait_msg(c, mtype, n0=0, pred=lambda m: True, timeout_s=3.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for _, m in c.of_type(mtype)[n0:]:
            if pred(m):
                return m
        time.sleep(0.01)
    raise AssertionError(f"no {mtype}")


def send(c, msg):
    c.link.send(msg)


def upload(c, items, mission_type=M.MAV_MISSION_TYPE_MISSION, timeout_s=5.0):
    """A well-behaved client: answers each request (either message) with the item, returns the ACK."""
    mav = c.link.mav
    n_ack, n_req = len(c.of_type("MISSION_ACK")), {t: len(c.of_type(t)) for t in ("MISSION_REQUEST", "MISSION_REQUEST_INT")}
    send(c, mav.mission_count_encode(1, 1, len(items), mission_type))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        acks = c.of_type("MISSION_ACK")[n_ack:]
        if acks:
            return acks[0][1].type
        for t in n_req:
            reqs = c.of_type(t)[n_req[t]:]
            n_req[t] += len(reqs)
            for _, r in reqs:
                send(c, items[r.seq])
        time.sleep(0.005)
    raise AssertionError("no MISSION_ACK")


def download(c, timeout_s=3.0):
    mav = c.link.mav
    n = len(c.of_type("MISSION_COUNT"))
    send(c, mav.mission_request_list_encode(1, 1, M.MAV_MISSION_TYPE_MISSION))
    count = wait_msg(c, "MISSION_COUNT", n, timeout_s=timeout_s).count
    out = []
    for seq in range(count):
        k = len(c.of_type("MISSION_ITEM_INT"))
        send(c, mav.mission_request_int_encode(1, 1, seq, M.MAV_MISSION_TYPE_MISSION))
        out.append(wait_msg(c, "MISSION_ITEM_INT", k, lambda m, s=seq: m.seq == s, timeout_s))
    send(c, mav.mission_ack_encode(1, 1, M.MAV_MISSION_ACCEPTED, M.MAV_MISSION_TYPE_MISSION))
    return out


def test_protocol_sequence_frame_space_and_legacy_request_rules():
    px, vp = raw("px4")
    ap, va = raw("ardupilot")
    try:
        wp = [item_int(i, 0.0, 3.0 * i, 3.0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) for i in range(3)]
        # ArduPilot: an item out of sequence -> MISSION_ACK INVALID_SEQUENCE, and the transfer goes on
        send(ap, ap.link.mav.mission_count_encode(1, 1, 2, 0))
        wait_msg(ap, "MISSION_REQUEST", pred=lambda m: m.seq == 0)
        n = len(ap.of_type("MISSION_ACK"))
        send(ap, wp[1])
        assert wait_msg(ap, "MISSION_ACK", n).type == M.MAV_MISSION_INVALID_SEQUENCE
        send(ap, wp[0])
        wait_msg(ap, "MISSION_REQUEST", pred=lambda m: m.seq == 1)
        n = len(ap.of_type("MISSION_ACK"))
        send(ap, wp[1])
        assert wait_msg(ap, "MISSION_ACK", n).type == M.MAV_MISSION_ACCEPTED and len(va.mission.items) == 2
        # PX4: the same item is ignored, not ACKed, and the expected one is asked for again (250 ms)
        send(px, px.link.mav.mission_count_encode(1, 1, 2, 0))
        wait_msg(px, "MISSION_REQUEST", pred=lambda m: m.seq == 0)  # PX4 starts in float mode
        n_ack, n_req = len(px.of_type("MISSION_ACK")), len(px.of_type("MISSION_REQUEST_INT")) + len(px.of_type("MISSION_REQUEST"))
        send(px, wp[1])
        time.sleep(0.6)
        assert len(px.of_type("MISSION_ACK")) == n_ack
        repeats = [m for _, m in (px.of_type("MISSION_REQUEST") + px.of_type("MISSION_REQUEST_INT"))]
        assert len(repeats) - n_req >= 1 and all(m.seq == 0 for m in repeats)
        send(px, wp[0])
        wait_msg(px, "MISSION_REQUEST_INT", pred=lambda m: m.seq == 1)  # a MISSION_ITEM_INT switched it to int mode
        send(px, wp[1])
        assert wait_msg(px, "MISSION_ACK", n_ack).type == M.MAV_MISSION_ACCEPTED and len(vp.mission.items) == 2
        # frames: PX4 takes only global frames (and MISSION for DO items); a local frame ends the transfer
        def local(seq):
            return M.MAVLink_mission_item_int_message(1, 1, seq, M.MAV_FRAME_LOCAL_NED, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, 10, 10, -3, 0)
        assert upload(px, [local(0)]) == M.MAV_MISSION_UNSUPPORTED_FRAME
        assert upload(ap, [wp[0], local(1)]) == M.MAV_MISSION_UNSUPPORTED_FRAME
        assert len(vp.mission.items) == 2  # PX4 keeps the old mission on a failed upload
        # PX4 takes DO_CHANGE_SPEED only in MAV_FRAME_MISSION
        speed_rel = M.MAVLink_mission_item_int_message(1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_DO_CHANGE_SPEED, 0, 1, 1, 2, -1, 0, 0, 0, 0, 0)
        assert upload(px, [speed_rel]) == M.MAV_MISSION_UNSUPPORTED
        # capacity: over the mission storage -> NO_SPACE; over the fence storage too (PX4 dataman
        # DM_KEY_FENCE_POINTS_MAX 64, ArduPilot AC_PolyFence_loader::max_items 84; tests/test_geofence.py)
        for c, cap, fence_cap in ((px, 500, 64), (ap, 724, 84)):
            n = len(c.of_type("MISSION_ACK"))
            send(c, c.link.mav.mission_count_encode(1, 1, cap + 1, 0))
            assert wait_msg(c, "MISSION_ACK", n).type == M.MAV_MISSION_NO_SPACE
            n = len(c.of_type("MISSION_ACK"))
            send(c, c.link.mav.mission_count_encode(1, 1, fence_cap + 1, M.MAV_MISSION_TYPE_FENCE))
            assert wait_msg(c, "MISSION_ACK", n).type == M.MAV_MISSION_NO_SPACE
        # legacy MISSION_REQUEST: both answer with MISSION_ITEM (float lat/lon); ArduPilot warns once
        for c in (px, ap):
            send(c, c.link.mav.mission_request_list_encode(1, 1, 0))
            for seq in (0, 1):  # PX4 serves a download in order
                n = len(c.of_type("MISSION_ITEM"))
                send(c, c.link.mav.mission_request_encode(1, 1, seq, 0))
                item = wait_msg(c, "MISSION_ITEM", n)
            assert item.seq == 1 and item.x == pytest.approx(latlon(0.0, 3.0)[0], abs=1e-5)
            send(c, c.link.mav.mission_ack_encode(1, 1, 0, 0))
        assert any("use MISSION_REQUEST_INT" in t for _, t in va.statustexts)
        # ArduPilot: a seq past the end -> MISSION_COUNT (the real size) then INVALID_SEQUENCE
        n, k = len(ap.of_type("MISSION_ACK")), len(ap.of_type("MISSION_COUNT"))
        send(ap, ap.link.mav.mission_request_int_encode(1, 1, 7, 0))
        assert wait_msg(ap, "MISSION_ACK", n).type == M.MAV_MISSION_INVALID_SEQUENCE
        assert wait_msg(ap, "MISSION_COUNT", k).count == 2
    finally:
        for c, v in ((px, vp), (ap, va)):
            c.stop()
            v.stop()


@pytest.mark.slow  # real time, ~10 s: opt-in (`-m slow`)
def test_a_client_that_stops_mid_upload_times_out():
    px, vp = raw("px4")
    ap, va = raw("ardupilot")
    try:
        old = [item_int(i, 0.0, 2.0 * i, 3.0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) for i in range(3)]
        new = [item_int(i, 5.0, 2.0 * i, 6.0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) for i in range(4)]
        for c in (px, ap):
            assert upload(c, old) == M.MAV_MISSION_ACCEPTED
            # a new upload: two items, then the client goes silent (PX4 stays in int mode from the
            # last upload; ArduPilot asks with MISSION_REQUEST)
            req_type = "MISSION_REQUEST_INT" if c is px else "MISSION_REQUEST"
            n = len(c.of_type(req_type))
            send(c, c.link.mav.mission_count_encode(1, 1, 4, 0))
            for seq in (0, 1):
                wait_msg(c, req_type, n, pred=lambda m, s=seq: m.seq == s)
                send(c, new[seq])
        t0 = time.monotonic()
        n_px, n_ap = len(px.of_type("MISSION_ACK")), len(ap.of_type("MISSION_ACK"))
        # PX4: requests repeated every 250 ms, then after 5 s "Operation timeout", no ACK, the old mission kept
        wait_until(lambda: any("Operation timeout" in t for _, t in vp.statustexts), 7.0, "PX4 timeout")
        assert 4.0 < time.monotonic() - t0 < 6.5 and len(px.of_type("MISSION_ACK")) == n_px
        assert len([m for _, m in px.of_type("MISSION_REQUEST_INT") if m.seq == 2]) >= 10
        assert [it.z for it in vp.mission.items] == [3.0, 3.0, 3.0]
        assert [round(m.z) for m in download(px)] == [3, 3, 3]
        # ArduPilot: after 8 s MISSION_ACK OPERATION_CANCELLED; its live mission was rewritten in
        # place (truncated to 4, items 0-1 replaced): what it holds is what arrived
        assert wait_msg(ap, "MISSION_ACK", n_ap, timeout_s=6.0).type == M.MAV_MISSION_OPERATION_CANCELLED
        assert 7.5 < time.monotonic() - t0 < 10.0
        assert any("Mission upload timeout" in t for _, t in va.statustexts)
        assert [it.z for it in va.mission.items] == [6.0, 6.0, 3.0]
        # the server is free again: a new upload goes through
        assert upload(px, new) == M.MAV_MISSION_ACCEPTED and upload(ap, new) == M.MAV_MISSION_ACCEPTED
    finally:
        for c, v in ((px, vp), (ap, va)):
            c.stop()
            v.stop()


def test_mission_start_is_refused_without_a_mission_or_a_global_origin():
    pi, vi = raw("px4", profile="indoor")
    po, vo = raw("px4")
    ao, va = raw("ardupilot")
    try:
        # PX4 outdoor, no mission: MISSION_START DENIED ("No valid mission"), mode switch refused
        assert po.command(M.MAV_CMD_MISSION_START, 0, 0) == M.MAV_RESULT_DENIED
        assert any("No valid mission" in t for _, t in vo.statustexts) and not vo.armed
        assert po.command(M.MAV_CMD_DO_SET_MODE, 1, 4, 4) == M.MAV_RESULT_TEMPORARILY_REJECTED
        # PX4 indoor: the upload is accepted (the mission manager stores it), but without a global
        # position the mission is not valid: no start, no AUTO.MISSION
        wp = [item_int(i, 0.0, 2.0 * i, 3.0, frame=M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) for i in range(2)]
        assert upload(pi, wp) == M.MAV_MISSION_ACCEPTED and len(vi.mission.items) == 2
        assert pi.command(M.MAV_CMD_MISSION_START, 0, 0) == M.MAV_RESULT_DENIED
        assert pi.command(M.MAV_CMD_DO_SET_MODE, 1, 4, 4) == M.MAV_RESULT_TEMPORARILY_REJECTED
        assert not vi.armed and vi.mode_name == "auto.loiter"
        # ArduCopter: AUTO without a mission fails; armed on the ground without a take-off first too
        assert ao.command(M.MAV_CMD_DO_SET_MODE, 1, 3) == M.MAV_RESULT_FAILED
        assert upload(ao, [item_int(0, 0, 0, 0)] + [item_int(1, 0.0, 3.0, 3.0)]) == M.MAV_MISSION_ACCEPTED
        assert ao.command(M.MAV_CMD_DO_SET_MODE, 1, 4) == M.MAV_RESULT_ACCEPTED
        assert ao.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert ao.command(M.MAV_CMD_DO_SET_MODE, 1, 3) == M.MAV_RESULT_FAILED
        assert any("Missing Takeoff Cmd" in t for _, t in va.statustexts) and va.mode_name == "guided"
    finally:
        for c, v in ((pi, vi), (po, vo), (ao, va)):
            c.stop()
            v.stop()


@pytest.mark.slow  # real time, ~10 s: opt-in (`-m slow`)
def test_px4_mission_start_arms_takes_off_keeps_speed_and_lands_on_a_final_land_item():
    c, v = raw("px4")
    try:
        mav = c.link.mav
        x, y = e7(0.0, 4.0)
        items = [
            M.MAVLink_mission_item_int_message(1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_TAKEOFF, 1, 1, 0, 0, 0, math.nan, *e7(0, 0), 2.5, 0),
            M.MAVLink_mission_item_int_message(1, 1, 1, M.MAV_FRAME_MISSION, M.MAV_CMD_DO_CHANGE_SPEED, 0, 1, 1, 1.5, -1, 0, 0, 0, 0, 0),
            M.MAVLink_mission_item_int_message(1, 1, 2, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0.3, 0, math.nan, x, y, 2.5, 0),
            M.MAVLink_mission_item_int_message(1, 1, 3, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_LAND, 0, 1, 0, 0, 0, math.nan, x, y, 0.0, 0),
        ]
        assert upload(c, items) == M.MAV_MISSION_ACCEPTED
        trace = Trace(v)
        assert c.command(M.MAV_CMD_MISSION_START, 0, 0) == M.MAV_RESULT_ACCEPTED  # switches to AUTO.MISSION and arms
        assert v.armed and v.mode_name == "auto.mission"
        wait_until(lambda: not v.armed, 30.0, "landed and disarmed (COM_DISARM_LAND)")
        pts = trace.stop()
        assert v.mission.reached_log == [0, 1, 2, 3]
        assert np.linalg.norm(v.position_enu() - [0.0, 4.0, 0.0]) < 0.3
        assert pts[:, 2].max() == pytest.approx(2.5, abs=0.15)
        assert 1.2 < max(trace.speeds_xy) < 1.5 * 1.05  # DO_CHANGE_SPEED 1.5 m/s (the model's default cruise is 5)
        assert v.mode_name == "auto.mission" and any("Mission finished, landed" in t for _, t in v.statustexts)
        reached = [m.seq for _, m in c.of_type("MISSION_ITEM_REACHED")]
        # each once when reached, then repeated at 1 Hz (up to 10 times) until the next one
        assert [s for i, s in enumerate(reached) if i == 0 or s != reached[i - 1]] == [0, 1, 2, 3]
        cur = c.of_type("MISSION_CURRENT")[-1][1]
        assert (cur.seq, cur.total, cur.mission_state) == (3, 4, M.MISSION_STATE_COMPLETE)
        # MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT: in range -> current item; past the end -> FAILED
        assert c.command(M.MAV_CMD_DO_SET_MISSION_CURRENT, 2, 0) == M.MAV_RESULT_ACCEPTED and v.mission.current == 2
        assert c.command(M.MAV_CMD_DO_SET_MISSION_CURRENT, 9, 0) == M.MAV_RESULT_FAILED
        send(c, mav.mission_clear_all_encode(1, 1, 0))
        wait_until(lambda: not v.mission.items, 2.0, "mission cleared")
    finally:
        c.stop()
        v.stop()


def test_return_to_launch_item_switches_to_the_return_mode():
    for autopilot, rtl_mode in (("px4", "auto.rtl"), ("ardupilot", "rtl")):
        c, v = raw(autopilot)
        try:
            home = [item_int(0, 0, 0, 0)] if autopilot == "ardupilot" else []
            items = home + [
                M.MAVLink_mission_item_int_message(1, 1, len(home), M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_TAKEOFF, 0, 1, 0, 0, 0, 0, *e7(0, 0), 2.5, 0),
                M.MAVLink_mission_item_int_message(1, 1, len(home) + 1, M.MAV_FRAME_MISSION, M.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0),
            ]
            assert upload(c, items) == M.MAV_MISSION_ACCEPTED
            if autopilot == "px4":
                assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 4, 4) == M.MAV_RESULT_ACCEPTED
                assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED  # armed in mission mode: it flies
            else:
                assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 3) == M.MAV_RESULT_ACCEPTED
                assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_FAILED  # no arming in AUTO
                assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 4) == M.MAV_RESULT_ACCEPTED
                assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
                assert c.command(M.MAV_CMD_DO_SET_MODE, 1, 3) == M.MAV_RESULT_ACCEPTED  # the mission starts with a take-off
            wait_until(lambda: v.mode_name == rtl_mode, 15.0, f"{autopilot} Return mode from the mission")
            assert v.position_enu()[2] > 1.6 and v.mission.reached_log[0] == len(home)
        finally:
            c.stop()
            v.stop()
