"""The MAVLink mission protocol and AUTO mission flight of :class:`~onfly.mavlink.sim_vehicle.SimMavlinkVehicle`.

Each rule names its source: the MAVLink mission service (mavlink.io/en/services/mission.html),
PX4 ``src/modules/mavlink/mavlink_mission.cpp`` / ``.h`` (the mission manager),
``src/modules/navigator/mission*.cpp`` / ``mission_block.cpp`` / ``navigator_main.cpp`` and
``src/modules/commander/Commander.cpp``; ArduPilot ``libraries/GCS_MAVLink/MissionItemProtocol.cpp``,
``MissionItemProtocol_Waypoints.cpp``, ``GCS_Common.cpp``, ``libraries/AP_Mission/AP_Mission.cpp``
and ``ArduCopter/mode_auto.cpp``. ``docs/flight.md`` ("Missions") lists them with what is
simplified. ``mission_type`` FENCE and RALLY go through the same transfer state machine into
their own storage (:attr:`MissionManager.fence`, :attr:`MissionManager.rally`); every
MISSION_COUNT, MISSION_REQUEST(_INT), MISSION_ITEM(_INT) and MISSION_ACK of a transfer carries
its mission_type. What the vehicle does with them is :mod:`onfly.mavlink.geofence`.

Fence and rally, PX4 (``mavlink_mission.cpp``, dataman)
------------------------------------------------------
- Capacity DM_KEY_FENCE_POINTS_MAX 64 and DM_KEY_SAFE_POINTS_MAX 32 (``dataman.h``); over it
  NO_SPACE. Like the mission, an upload is written to the inactive storage and made active on
  the last item (``update_geofence_count`` / ``update_safepoint_count``); COUNT 0 and
  MISSION_CLEAR_ALL with that type (or ALL) clear it.
- Items are parsed by ``parse_mavlink_mission_item``: fence commands (polygon vertex, param1 the
  vertex count rounded; circle, param1 the radius; return point) and NAV_RALLY_POINT in the
  global frames only. In a FENCE upload a polygon vertex with a count below 3 ("Fence: too few
  vertices"), and in a MISSION upload any fence or rally command, end the transfer with
  MISSION_ACK ERROR. A download formats them like positions (frame from the altitude mode and the
  int mode, param1 back).

Fence and rally, ArduPilot (``MissionItemProtocol_Fence.cpp``, ``MissionItemProtocol_Rally.cpp``)
-------------------------------------------------------------------------------------------------
- Fence: up to 84 items (``AC_PolyFence_loader::max_items``, 16 kB storage); global frames
  (terrain too) else UNSUPPORTED_FRAME, fence commands else UNSUPPORTED. The items are buffered
  and written at the end (``complete`` -> ``write_fence``): ``validate_fence`` failing (a vertex
  count below 3 "Invalid vertex count (n)", counts or types that disagree within a polygon, a
  non-positive radius, two return points, a polygon cut short "Incorrect item count") answers
  ERROR after "Fence validation failed" and keeps the old fence. Downloaded with frame 0
  (GLOBAL), param1 the count / radius, z 0. Timeout "Fence upload timeout".
- Rally: up to 50 (``AP_Rally::get_rally_max``); NAV_RALLY_POINT only (UNSUPPORTED), in
  GLOBAL_RELATIVE_ALT(_INT) only (UNSUPPORTED_FRAME), the altitude an int16 of metres
  (INVALID_PARAM7). Truncated at COUNT and written live like the mission; "Rally points
  received"; downloaded in GLOBAL_RELATIVE_ALT. Timeout "Rally upload timeout".
- MISSION_CLEAR_ALL with FENCE or RALLY clears that storage (``write_fence(nullptr, 0)``,
  ``truncate(0)``).

Protocol, PX4 (``MavlinkMissionManager``)
-----------------------------------------
- One transfer at a time (IDLE / SENDLIST / GETLIST) with one partner (sysid, compid).
  MISSION_COUNT: more than 500 items (CONFIG_NUM_MISSION_ITMES_SUPPORTED) -> NO_SPACE;
  0 -> the mission is cleared, ACCEPTED; else items are requested from seq 0. A COUNT while
  receiving from another partner, or past seq 0, or while sending -> ERROR.
- PX4 starts a link in float mode (``_int_mode{false}``): the first request is MISSION_REQUEST;
  a MISSION_ACK UNSUPPORTED from the client flips the mode and repeats the request as
  MISSION_REQUEST_INT (MAVSDK answers that way); any MISSION_*_INT it receives switches to
  int mode.
- An item whose seq is not the one requested is ignored (no ACK; the request is repeated
  every 250 ms, MAVLINK_MISSION_RETRY_TIMEOUT_DEFAULT); an item that cannot be parsed
  ends the transfer with its MAV_MISSION_RESULT (UNSUPPORTED_FRAME, UNSUPPORTED, ...).
  The upload is written to the inactive storage and made active only when complete: a
  transfer that times out (5 s without a message, MAVLINK_MISSION_PROTOCOL_TIMEOUT_DEFAULT;
  STATUSTEXT "Operation timeout") leaves the old mission in place. Uploading while a
  mission flies is allowed (the navigator continues with the new mission).
- Download: MISSION_REQUEST_LIST -> MISSION_COUNT; each MISSION_REQUEST(_INT) for the
  expected seq (or the previous one again) -> MISSION_ITEM(_INT); any other seq -> ERROR.
  Items come back as PX4 stored them (a waypoint keeps param1/2/4, yaw in [0, 360)).
- MISSION_CLEAR_ALL -> ACCEPTED when idle; MISSION_SET_CURRENT with seq < count sets the
  current item. MISSION_CURRENT is sent at 1 Hz and on change (``_slow_rate_limiter``, not
  a stream), MISSION_ITEM_REACHED on change and then repeated up to 10 times at 1 Hz.

Protocol, ArduPilot (``MissionItemProtocol``)
---------------------------------------------
- Item 0 is home: a download always returns the current home at seq 0 and the flown items
  start at seq 1 (``AP_Mission::read_cmd_from_storage``; ``AP_MISSION_FIRST_REAL_COMMAND``).
- MISSION_COUNT: another partner while receiving -> DENIED; over 724 items -> NO_SPACE (the
  storage of a 16 kB board, ``num_commands_max``). The mission is truncated to the new count
  at once and each item replaces the stored one as it arrives (no inactive copy: a transfer
  that stops half-way leaves a mixed mission). Requests are MISSION_REQUEST (the legacy
  message, ``queued_request_send``), repeated after 1 s; 8 s without an item
  (``upload_timeout_ms``) -> MISSION_ACK OPERATION_CANCELLED, "Mission upload timeout".
- An item with the wrong seq -> MISSION_ACK INVALID_SEQUENCE (the transfer goes on); from
  another partner -> DENIED; NaN where not allowed -> INVALID_PARAMn; a bad frame ->
  UNSUPPORTED_FRAME; an unknown command -> UNSUPPORTED (``mavlink_int_to_mission_cmd``).
  MISSION_ITEM (float) is converted and answered with one STATUSTEXT warning per transfer.
- Download while receiving -> DENIED; a seq beyond the mission -> MISSION_COUNT then
  INVALID_SEQUENCE. MISSION_REQUEST (legacy) is answered with MISSION_ITEM and a warning.
- MISSION_CLEAR_ALL while the mission runs -> ERROR (``AP_Mission::clear``).
- MISSION_CURRENT streams in the EXT_STAT group (2 Hz), ``total`` without home;
  MISSION_ITEM_REACHED for every completed command (DO commands too).

Flight
------
PX4 AUTO.MISSION needs a valid mission (items and a global origin) and global position;
armed and landed it takes off first (``Mission::do_need_vertical_takeoff``: to the item's
altitude, at least MIS_TAKEOFF_ALT above the ground), so arming in mission mode or
MAV_CMD_MISSION_START (which arms) makes it fly. A waypoint is reached within its param2
(else NAV_ACC_RAD, 2 m on multicopters) horizontally and NAV_MC_ALT_RAD (0.8 m) vertically,
then held param1 seconds (``MissionBlock::is_mission_item_reached``). At the end it loiters
and Commander switches to AUTO.LOITER; a final NAV_LAND lands and disarms.

ArduCopter AUTO needs a mission with at least one item after home and refuses to start
armed on the ground unless the first item is a take-off ("Auto: Missing Takeoff Cmd");
it cannot be armed in AUTO (the vehicle's arming rule). Without an EKF origin (indoors) the
mission waits (``ModeAuto::run`` ``waiting_to_start``). A waypoint is reached within
WPNAV_RADIUS (2 m), then delayed param1 whole seconds; a lat/lon of 0 means "here" and an
altitude of 0 "this altitude" (``loc_from_cmd``). At the end it loiters in AUTO, or disarms
when landed (``exit_mission``). DO commands after a NAV command run when it starts.
NAV_RETURN_TO_LAUNCH switches to the vehicle's Return mode (PX4 AUTO.RTL; ArduCopter runs
RTL inside AUTO, simplified here to the RTL mode). DO_CHANGE_SPEED sets the horizontal
speed of the following legs.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, replace

import numpy as np

from onfly.mavlink.autopilot import ARDUCOPTER_MODE, PX4_AUTO_SUB, PX4_MAIN, px4_custom_mode
from onfly.mavlink.geofence import (ARDUPILOT_FENCE_MAX_ITEMS, ARDUPILOT_RALLY_MAX_ITEMS, CIRCLE_COMMANDS, FENCE_COMMANDS,
                                    POLYGON_COMMANDS, PX4_FENCE_MAX_ITEMS, PX4_RALLY_MAX_ITEMS, Fence, ardupilot_fence_error,
                                    fence_from_items)
from onfly.mavlink.link import mavlink2

__all__ = ["MissionItem", "MissionManager", "PX4_MAX_ITEMS", "ARDUPILOT_MAX_ITEMS", "MISSION_PARAM_SI"]

_M = mavlink2

PX4_MAX_ITEMS = 500  # PX4 dataman CONFIG_NUM_MISSION_ITMES_SUPPORTED (NuttX boards)
ARDUPILOT_MAX_ITEMS = 724  # AP_Mission::num_commands_max on a 16 kB storage board; board-dependent
PX4_RETRY_S = 0.25  # MAVLINK_MISSION_RETRY_TIMEOUT_DEFAULT
PX4_TIMEOUT_S = 5.0  # MAVLINK_MISSION_PROTOCOL_TIMEOUT_DEFAULT
AP_RESEND_S = 1.0  # MissionItemProtocol::update wp_recv_timeout_ms (no stream slowdown)
AP_TIMEOUT_S = 8.0  # MissionItemProtocol upload_timeout_ms
LOCATION_ALT_MAX_M = 83000.0  # ArduPilot Location 24-bit cm altitude

#: The mission's navigation parameters, read live from the vehicle's parameter table
#: (``sim_vehicle.PX4_PARAMS`` / ``ARDUPILOT_PARAMS``, with the autopilots' defaults), and the
#: factor that turns each into SI units: ArduCopter's are centimetres (per second).
MISSION_PARAM_SI = {
    "NAV_ACC_RAD": 1.0,  # PX4, m (multicopter default 2 m, rc.mc_defaults)
    "NAV_MC_ALT_RAD": 1.0,  # PX4, m
    "MPC_XY_CRUISE": 1.0,  # PX4, m/s
    "WPNAV_RADIUS": 0.01,  # ArduCopter, cm
    "WPNAV_SPEED": 0.01,  # ArduCopter, cm/s
}

_GLOBAL_FRAMES = {_M.MAV_FRAME_GLOBAL: False, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT: True,
                  _M.MAV_FRAME_GLOBAL_INT: False, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: True}
_INT_FRAMES = (_M.MAV_FRAME_GLOBAL_INT, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
_NAV_POSITION = (_M.MAV_CMD_NAV_WAYPOINT, _M.MAV_CMD_NAV_TAKEOFF, _M.MAV_CMD_NAV_LAND)
_NAV = _NAV_POSITION + (_M.MAV_CMD_NAV_RETURN_TO_LAUNCH,)
_SUPPORTED = _NAV + (_M.MAV_CMD_DO_CHANGE_SPEED,)
_FENCE_RALLY = FENCE_COMMANDS + (_M.MAV_CMD_NAV_RALLY_POINT,)
_POSITION_LIKE = _NAV_POSITION + _FENCE_RALLY  # items whose x/y are lat/lon (degE7 when stored)
_MT_MISSION, _MT_FENCE, _MT_RALLY = _M.MAV_MISSION_TYPE_MISSION, _M.MAV_MISSION_TYPE_FENCE, _M.MAV_MISSION_TYPE_RALLY
_IDLE, _SENDLIST, _GETLIST = "idle", "sendlist", "getlist"


def _f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", float(x)))[0]


@dataclass(frozen=True)
class MissionItem:
    """One stored item. For position items ``x``/``y`` are lat/lon in degE7 and ``relative``
    says whether ``z`` is above home; other items keep ``x``/``y``/``z`` as sent."""

    command: int
    frame: int
    params: tuple = (0.0, 0.0, 0.0, 0.0)
    x: float = 0
    y: float = 0
    z: float = 0.0
    relative: bool = True
    autocontinue: int = 1
    current: int = 0

    @property
    def is_position(self) -> bool:
        """x/y are lat/lon in degE7 (a position item, a fence vertex / circle, a rally point)."""
        return self.command in _POSITION_LIKE


class MissionManager:
    """The mission of one vehicle: the protocol server and the AUTO executor. All methods run
    with the vehicle's lock held; :meth:`step` is called once per physics step."""

    def __init__(self, vehicle) -> None:
        self.v = vehicle
        self.px4 = vehicle.px4
        self.items: list[MissionItem] = []
        self.fence: list[MissionItem] = []  # mission_type FENCE, as stored
        self.rally: list[MissionItem] = []  # mission_type RALLY, as stored
        self.fence_zones = Fence()  # the zones the vehicle checks (onfly/mavlink/geofence.py)
        self.reached_log: list[int] = []  # every MISSION_ITEM_REACHED seq sent (tests)
        # protocol
        self._state = _IDLE
        self._partner: tuple[int, int] | None = None
        self._int_mode = False
        self._xfer_type = _M.MAV_MISSION_TYPE_MISSION
        self._xfer_seq = 0
        self._xfer_count = 0
        self._xfer_items: list[MissionItem] = []
        self._xfer_current = 0
        self._t_recv = 0.0
        self._t_sent = 0.0
        self._item_warning = self._request_warning = False
        # execution
        self.current = 0  # PX4 current seq / ArduPilot current nav index
        self.finished = False  # PX4 mission_result.finished
        self.ap_state = "stopped"  # ArduPilot AP_Mission state: stopped | running | complete
        self._ap_started = False
        self._active = False
        self._phase: str | None = None
        self._phase_t = 0.0
        self._target: np.ndarray | None = None  # the current NAV item's point (scene ENU)
        self._takeoff_point = np.zeros(3)  # PX4: the climb of a take-off
        self._land_alt = 0.0  # PX4: the altitude a NAV_LAND moves over its point at
        self._speed: float | None = None  # DO_CHANGE_SPEED horizontal speed
        self._last_reached = -1
        self._reached_resends = 0
        self._next_current_s = 0.0
        self._last_sent_current: int | None = None

    # -- helpers ------------------------------------------------------------------------------
    def _now(self) -> float:
        return self.v.clock()

    def _send(self, msg) -> None:
        self.v._send(msg)

    def _text(self, severity: int, text: str) -> None:
        self.v._statustext(severity, text)

    def _ack(self, to: tuple[int, int], result: int, mission_type: int | None = None) -> None:
        mt = self._xfer_type if mission_type is None else mission_type
        self._send(self.v.link.mav.mission_ack_encode(to[0], to[1], result, mt))

    def _for_me(self, msg) -> bool:
        comp = msg.target_component
        ok_comp = comp in (0, self.v.c.component_id) or (self.px4 and comp == _M.MAV_COMP_ID_MISSIONPLANNER)
        return msg.target_system == self.v.c.system_id and ok_comp

    @staticmethod
    def _src(msg) -> tuple[int, int]:
        return msg.get_srcSystem(), msg.get_srcComponent()

    def _max_items(self, mission_type: int) -> int | None:
        if mission_type == _M.MAV_MISSION_TYPE_MISSION:
            return PX4_MAX_ITEMS if self.px4 else ARDUPILOT_MAX_ITEMS
        if mission_type == _MT_FENCE:
            return PX4_FENCE_MAX_ITEMS if self.px4 else ARDUPILOT_FENCE_MAX_ITEMS
        if mission_type == _MT_RALLY:
            return PX4_RALLY_MAX_ITEMS if self.px4 else ARDUPILOT_RALLY_MAX_ITEMS
        return 0 if self.px4 else None  # PX4: current_max_item_count() of an unknown type is 0

    @property
    def home_scene(self) -> np.ndarray:
        return self.v._home if self.v._home is not None else self.v.model.p.copy()

    def valid(self) -> bool:
        """PX4 ``mission_result.valid`` (simplified feasibility: items and a global origin)."""
        return bool(self.items) and self.v.c.global_origin is not None

    def present(self) -> bool:
        """ArduPilot ``AP_Mission::present``: more than home."""
        return len(self.items) > 1

    # -- message entry ------------------------------------------------------------------------
    def handle(self, msg) -> bool:
        """Handle a MISSION_* message; True when it was one."""
        mtype = msg.get_type()
        handler = {
            "MISSION_COUNT": self._on_count, "MISSION_ITEM": self._on_item, "MISSION_ITEM_INT": self._on_item,
            "MISSION_REQUEST_LIST": self._on_request_list, "MISSION_REQUEST": self._on_request,
            "MISSION_REQUEST_INT": self._on_request, "MISSION_ACK": self._on_ack,
            "MISSION_CLEAR_ALL": self._on_clear_all, "MISSION_SET_CURRENT": self._on_set_current,
        }.get(mtype)
        if handler is None:
            return False
        with self.v._lock:
            if self.px4 or mtype != "MISSION_ACK":
                handler(msg)
        return True

    # -- upload -------------------------------------------------------------------------------
    def _on_count(self, msg) -> None:
        if not self._for_me(msg):
            return
        src, now, mt = self._src(msg), self._now(), int(msg.mission_type)
        cap = self._max_items(mt)
        if self.px4:
            if self._state == _GETLIST:
                self._t_recv = now
                if src != self._partner:
                    self._ack(src, _M.MAV_MISSION_ERROR, mt)
                elif self._xfer_seq == 0:
                    self._send_request()  # our first request was lost: ask again
                else:
                    self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: REJ. CMD: Busy")
                    self._ack(src, _M.MAV_MISSION_ERROR)
                return
            if self._state == _SENDLIST:
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: IGN MISSION_COUNT: Busy")
                self._ack(src, _M.MAV_MISSION_ERROR, mt)
                return
            self._t_recv = now
            self._partner, self._xfer_type = src, mt
            self._last_reached = -1
            if msg.count > cap:
                self._ack(src, _M.MAV_MISSION_NO_SPACE)
                return
            if msg.count == 0:  # clears that type (update_geofence_count / update_safepoint_count with 0)
                self._commit_type(mt, [], 0)
                self._ack(src, _M.MAV_MISSION_ACCEPTED)
                return
            self._begin_receive(src, mt, msg.count)
            return
        # ArduPilot
        if cap is None:
            self._ack(src, _M.MAV_MISSION_UNSUPPORTED, mt)
            return
        if self._state == _GETLIST and src != self._partner:
            self._ack(src, _M.MAV_MISSION_DENIED, mt)
            return
        self._xfer_type = mt
        if msg.count > cap:
            self._ack(src, _M.MAV_MISSION_NO_SPACE, mt)
            self._text(_M.MAV_SEVERITY_WARNING, f"Only {cap} items are supported")
            self._state = _IDLE
            return
        if mt == _MT_MISSION:
            del self.items[msg.count:]  # AP_Mission::truncate: the live mission, at once
        elif mt == _MT_RALLY:
            del self.rally[msg.count:]  # MissionItemProtocol_Rally::truncate: AP_Rally::truncate, live
        # fence: MissionItemProtocol_Fence::truncate does nothing; the items are written at the end
        if msg.count == 0:
            self._state = _IDLE
            self._ap_complete_upload(src, mt, [])
            return
        self._begin_receive(src, mt, msg.count)

    def _begin_receive(self, src, mt: int, count: int) -> None:
        self._state, self._partner, self._xfer_type = _GETLIST, src, mt
        self._xfer_seq, self._xfer_count, self._xfer_items, self._xfer_current = 0, int(count), [], 0
        self._t_recv = self._now()
        self._item_warning = self._request_warning = False
        self._send_request()

    def _send_request(self) -> None:
        self._t_sent = self._now()
        mav, (sysid, compid) = self.v.link.mav, self._partner
        if self.px4 and self._int_mode:
            self._send(mav.mission_request_int_encode(sysid, compid, self._xfer_seq, self._xfer_type))
        else:  # PX4 in float mode; ArduPilot always asks with the legacy MISSION_REQUEST
            self._send(mav.mission_request_encode(sysid, compid, self._xfer_seq, self._xfer_type))

    def _on_item(self, msg) -> None:
        if not self._for_me(msg):
            return
        is_int = msg.get_type() == "MISSION_ITEM_INT"
        src, mt = self._src(msg), int(msg.mission_type)
        if self.px4:
            self._int_mode = is_int
            if src != self._partner:
                self._text(_M.MAV_SEVERITY_CRITICAL, "REJ. MIS ITEM: partner id mismatch")
                return
            if mt != self._xfer_type:
                self._ack(src, _M.MAV_MISSION_ERROR)
                return
            if self._state == _IDLE:
                if self._xfer_seq == msg.seq + 1:  # a repeat of the last item: our ACK was lost
                    self._ack(src, _M.MAV_MISSION_ACCEPTED)
                else:
                    self._text(_M.MAV_SEVERITY_CRITICAL, "IGN MISSION_ITEM: No transfer")
                    self._ack(src, _M.MAV_MISSION_ERROR)
                return
            if self._state == _SENDLIST:
                self._text(_M.MAV_SEVERITY_CRITICAL, "IGN MISSION_ITEM: Busy")
                self._ack(src, _M.MAV_MISSION_ERROR)
                return
            self._t_recv = self._now()
            if msg.seq != self._xfer_seq:
                return  # mavlink_mission.cpp: "Item sequence not expected, ignore item"
            result, item = self._parse_px4(msg, is_int)
            if result != _M.MAV_MISSION_ACCEPTED:
                self._text(_M.MAV_SEVERITY_CRITICAL, "IGN MISSION_ITEM: Invalid item")
                self._ack(src, result)
                self._state = _IDLE
                return
            # handle_mission_item_both: a fence / rally command in a mission, or a polygon of fewer
            # than 3 vertices in a fence ("Fence: too few vertices"), fail the transfer with ERROR
            bad_mission = mt == _MT_MISSION and item.command in _FENCE_RALLY
            bad_polygon = mt == _MT_FENCE and item.command in POLYGON_COMMANDS and item.params[0] < 3
            if bad_mission or bad_polygon:
                self._ack(src, _M.MAV_MISSION_ERROR)
                self._state = _IDLE
                return
            self._xfer_items.append(item)
            if msg.current:
                self._xfer_current = msg.seq
            self._xfer_seq = msg.seq + 1
            if self._xfer_seq == self._xfer_count:
                self._state = _IDLE
                self._commit_type(self._xfer_type, self._xfer_items, self._xfer_current)
                self._ack(src, _M.MAV_MISSION_ACCEPTED)
            else:
                self._send_request()
            return
        # ArduPilot: current = 2 / 3 (guided and alt-change requests) are not modelled
        if self._state != _GETLIST:
            self._ack(src, _M.MAV_MISSION_ERROR, mt)
            return
        if not is_int and not self._item_warning:
            self._item_warning = True
            self._text(_M.MAV_SEVERITY_WARNING, "got MISSION_ITEM; GCS should send MISSION_ITEM_INT")
        if msg.seq != self._xfer_seq:
            self._ack(src, _M.MAV_MISSION_INVALID_SEQUENCE, mt)
            return
        if src != self._partner:
            self._ack(src, _M.MAV_MISSION_DENIED, mt)
            return
        parse = {_MT_FENCE: self._parse_ap_fence, _MT_RALLY: self._parse_ap_rally}.get(self._xfer_type, self._parse_ardupilot)
        result, item = parse(msg, is_int)
        live = self.rally if self._xfer_type == _MT_RALLY else (None if self._xfer_type == _MT_FENCE else self.items)
        if result == _M.MAV_MISSION_ACCEPTED and live is not None and msg.seq > len(live):
            result = _M.MAV_MISSION_ERROR
        if result != _M.MAV_MISSION_ACCEPTED:
            self._ack(src, result, mt)
            self._state = _IDLE
            return
        if live is None:
            self._xfer_items.append(item)  # MissionItemProtocol_Fence: buffered until complete()
        elif msg.seq < len(live):
            live[msg.seq] = item  # replace_cmd / set_rally_point_with_index: live
        else:
            live.append(item)  # add_cmd / AP_Rally::append
        self._t_recv = self._now()
        self._xfer_seq += 1
        if self._xfer_seq >= self._xfer_count:
            self._state = _IDLE
            self._ap_complete_upload(src, self._xfer_type, self._xfer_items)
        else:
            self._send_request()

    def _ap_complete_upload(self, src, mt: int, items: list) -> None:
        """ArduPilot ``MissionItemProtocol::transfer_is_complete`` -> each type's ``complete()``."""
        if mt == _MT_FENCE:  # MissionItemProtocol_Fence::complete -> AC_PolyFence_loader::write_fence
            why = ardupilot_fence_error(items)
            if why is not None:
                self._text(_M.MAV_SEVERITY_WARNING, why)
                self._text(_M.MAV_SEVERITY_WARNING, "Fence validation failed")
                self._ack(src, _M.MAV_MISSION_ERROR, mt)
                return
            self._commit_type(mt, items, 0)
        elif mt == _MT_RALLY:
            self._text(_M.MAV_SEVERITY_INFO, "Rally points received")
        else:
            self._text(_M.MAV_SEVERITY_INFO, "Flight plan received")
            self._mission_changed()
        self._ack(src, _M.MAV_MISSION_ACCEPTED, mt)

    def _parse_px4(self, msg, is_int: bool) -> tuple[int, MissionItem | None]:
        """``MavlinkMissionManager::parse_mavlink_mission_item``, limited to the commands the
        simulated vehicle flies (others: UNSUPPORTED, where PX4 accepts more)."""
        frame, cmd = int(msg.frame), int(msg.command)
        p = tuple(_f32(x) for x in (msg.param1, msg.param2, msg.param3, msg.param4))
        if frame in (_M.MAV_FRAME_GLOBAL, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT) or (is_int and frame in _INT_FRAMES):
            if cmd not in _NAV_POSITION + _FENCE_RALLY:
                return _M.MAV_MISSION_UNSUPPORTED, None
            x, y = (int(msg.x), int(msg.y)) if is_int else (int(round(msg.x * 1e7)), int(round(msg.y * 1e7)))
            if cmd in _FENCE_RALLY:  # vertex_count = (uint16)(param1 + 0.5), circle_radius = param1, else nothing
                p1 = float(int(p[0] + 0.5)) if cmd in POLYGON_COMMANDS else (p[0] if cmd in CIRCLE_COMMANDS else 0.0)
                return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, frame, (p1, 0.0, 0.0, 0.0), x, y, _f32(msg.z),
                                                            _GLOBAL_FRAMES[frame], int(msg.autocontinue))
            yaw = math.degrees(math.radians(p[3]) % (2 * math.pi)) if math.isfinite(p[3]) else p[3]
            params = {_M.MAV_CMD_NAV_WAYPOINT: (p[0], p[1], 0.0, yaw), _M.MAV_CMD_NAV_TAKEOFF: (0.0, 0.0, 0.0, yaw),
                      _M.MAV_CMD_NAV_LAND: (0.0, p[1], 0.0, yaw)}[cmd]
            return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, frame, params, x, y, _f32(msg.z), _GLOBAL_FRAMES[frame],
                                                        int(msg.autocontinue))
        if frame == _M.MAV_FRAME_MISSION:
            if cmd not in (_M.MAV_CMD_DO_CHANGE_SPEED, _M.MAV_CMD_NAV_RETURN_TO_LAUNCH):
                return _M.MAV_MISSION_UNSUPPORTED, None
            return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, frame, p, msg.x, msg.y, _f32(msg.z), False, int(msg.autocontinue))
        return _M.MAV_MISSION_UNSUPPORTED_FRAME, None

    def _parse_ardupilot(self, msg, is_int: bool) -> tuple[int, MissionItem | None]:
        """``AP_Mission::mavlink_int_to_mission_cmd`` (and the MISSION_ITEM conversion), limited to
        the commands the simulated vehicle flies (others: UNSUPPORTED, where ArduPilot accepts
        more). Terrain frames are refused (no terrain database here)."""
        cmd = int(msg.command)
        p = tuple(_f32(x) for x in (msg.param1, msg.param2, msg.param3, msg.param4))
        if is_int:
            x, y = int(msg.x), int(msg.y)
        else:
            if not -90.0 <= msg.x <= 90.0:
                return _M.MAV_MISSION_INVALID_PARAM5_X, None
            if not -180.0 <= msg.y <= 180.0:
                return _M.MAV_MISSION_INVALID_PARAM6_Y, None
            x, y = int(msg.x * 1e7), int(msg.y * 1e7)
        nan_ok = 3 if cmd in _NAV_POSITION else None  # param4 may be NaN for WAYPOINT / LAND / TAKEOFF
        for i, val in enumerate(p):
            if math.isinf(val) or (math.isnan(val) and i != nan_ok):
                return _M.MAV_MISSION_INVALID_PARAM1 + i, None
        if cmd not in _SUPPORTED:
            return _M.MAV_MISSION_UNSUPPORTED, None
        if cmd == _M.MAV_CMD_DO_CHANGE_SPEED:
            return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, _M.MAV_FRAME_GLOBAL, (float(int(p[0]) & 0xFF), p[1], float(int(p[2])), 0.0))
        if cmd == _M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, _M.MAV_FRAME_GLOBAL)
        if abs(x) > 900000000:
            return _M.MAV_MISSION_INVALID_PARAM5_X, None
        if abs(y) > 1800000000:
            return _M.MAV_MISSION_INVALID_PARAM6_Y, None
        if math.isnan(msg.z) or abs(msg.z) >= LOCATION_ALT_MAX_M:
            return _M.MAV_MISSION_INVALID_PARAM7, None
        frame = int(msg.frame)
        if frame in (_M.MAV_FRAME_MISSION, _M.MAV_FRAME_GLOBAL, _M.MAV_FRAME_GLOBAL_INT):
            relative = False
        elif frame in (_M.MAV_FRAME_GLOBAL_RELATIVE_ALT, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
            relative = True
        else:
            return _M.MAV_MISSION_UNSUPPORTED_FRAME, None
        p1 = float(int(p[0]) & 0xFFFF)  # stored as uint16 (delay s / abort alt / min pitch)
        params = (p1, 0.0, 0.0, 0.0)
        if cmd == _M.MAV_CMD_NAV_LAND:
            params = (p1, 0.0, 0.0, -1.0 if p[3] < 0 else 1.0)  # loiter_ccw flag on the way back
        alt_cm = int(float(msg.z) * 100.0)
        return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT if relative else _M.MAV_FRAME_GLOBAL,
                                                    params, x, y, alt_cm / 100.0, relative)

    def _ap_xy(self, msg, is_int: bool) -> tuple[int, int]:
        return (int(msg.x), int(msg.y)) if is_int else (int(msg.x * 1e7), int(msg.y * 1e7))

    def _parse_ap_fence(self, msg, is_int: bool) -> tuple[int, MissionItem | None]:
        """``convert_MISSION_ITEM_INT_to_AC_PolyFenceItem`` (MissionItemProtocol_Fence.cpp): global
        frames (terrain ones too), fence commands; stored as lat/lon and param1 only."""
        frames = (_M.MAV_FRAME_GLOBAL, _M.MAV_FRAME_GLOBAL_INT, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                  _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, _M.MAV_FRAME_GLOBAL_TERRAIN_ALT, _M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
        if int(msg.frame) not in frames:
            return _M.MAV_MISSION_UNSUPPORTED_FRAME, None
        cmd = int(msg.command)
        if cmd not in FENCE_COMMANDS:
            return _M.MAV_MISSION_UNSUPPORTED, None
        p1 = _f32(msg.param1)
        if cmd in POLYGON_COMMANDS:
            p1 = float(int(p1) & 0xFF) if math.isfinite(p1) and p1 >= 0 else 0.0  # uint8 vertex_count
        elif cmd not in CIRCLE_COMMANDS:
            p1 = 0.0
        x, y = self._ap_xy(msg, is_int)  # get_item_as_mission_item: frame 0 (GLOBAL), z = 0 on the way back
        return _M.MAV_MISSION_ACCEPTED, MissionItem(cmd, _M.MAV_FRAME_GLOBAL, (p1, 0.0, 0.0, 0.0), x, y, 0.0, False)

    def _parse_ap_rally(self, msg, is_int: bool) -> tuple[int, MissionItem | None]:
        """``MissionItemProtocol_Rally::convert_MISSION_ITEM_INT_to_RallyLocation``: NAV_RALLY_POINT in
        a GLOBAL_RELATIVE_ALT frame, altitude an int16 of metres above home."""
        if int(msg.command) != _M.MAV_CMD_NAV_RALLY_POINT:
            return _M.MAV_MISSION_UNSUPPORTED, None
        if int(msg.frame) not in (_M.MAV_FRAME_GLOBAL_RELATIVE_ALT, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
            return _M.MAV_MISSION_UNSUPPORTED_FRAME, None
        x, y = self._ap_xy(msg, is_int)
        if abs(x) > 900000000:
            return _M.MAV_MISSION_INVALID_PARAM5_X, None
        if abs(y) > 1800000000:
            return _M.MAV_MISSION_INVALID_PARAM6_Y, None
        if not (math.isfinite(msg.z) and -32768 <= msg.z <= 32767):
            return _M.MAV_MISSION_INVALID_PARAM7, None
        return _M.MAV_MISSION_ACCEPTED, MissionItem(_M.MAV_CMD_NAV_RALLY_POINT, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                                                    (0.0, 0.0, 0.0, 0.0), x, y, float(int(msg.z)), True)

    def _stored(self, mt: int) -> list[MissionItem]:
        return {_MT_FENCE: self.fence, _MT_RALLY: self.rally}.get(mt, self.items)

    def _commit_type(self, mt: int, items: list[MissionItem], current: int) -> None:
        """A completed upload (or a clear) of one mission type becomes the stored one."""
        if mt == _MT_MISSION:
            self._commit(items, current)
        elif mt == _MT_FENCE:
            self.fence = list(items)
            self.update_fence()
        elif mt == _MT_RALLY:
            self.rally = list(items)
            self.v._event(f"rally points: {len(items)}")

    def update_fence(self) -> None:
        """The zones the vehicle checks: PX4 drops the zones ``Geofence::_updateFence`` refuses
        (home or, flying, the vehicle outside); ArduPilot checked the fence at upload."""
        zones = fence_from_items(self.fence).zones
        if self.px4:
            zones = tuple(z for z in zones if self.v.fence.px4_zone_accepted(z))
        self.fence_zones = Fence(zones)
        self.v._event(f"geofence: {len(self.fence)} items, {len(zones)} zones")

    def _commit(self, items: list[MissionItem], current: int) -> None:
        """PX4: the received mission becomes active (``update_active_mission``)."""
        self.items = list(items)
        self.current = current if 0 <= current < len(items) else 0
        self.finished = False
        self._mission_changed()

    def _mission_changed(self) -> None:
        if self._active:  # the navigator re-plans from the current item of the new mission
            self._phase = None
            if not self.px4:
                if self.current >= len(self.items):
                    self._ap_complete()

    # -- download -----------------------------------------------------------------------------
    def _count_for(self, mt: int) -> int:
        return len(self._stored(mt)) if mt in (_MT_MISSION, _MT_FENCE, _MT_RALLY) else 0

    def _on_request_list(self, msg) -> None:
        if not self._for_me(msg):
            return
        src, mt = self._src(msg), int(msg.mission_type)
        if self.px4:
            if self._state == _SENDLIST and self._xfer_seq == self._xfer_count:
                self._state = _IDLE  # all sent but the ACK never came
            if self._state == _IDLE or (self._state == _SENDLIST and mt == self._xfer_type and src == self._partner):
                self._t_recv = self._now()
                self._state, self._xfer_type, self._partner = _SENDLIST, mt, src
                self._xfer_seq, self._xfer_count = 0, self._count_for(mt)
                self._t_sent = self._now()
                self._send(self.v.link.mav.mission_count_encode(src[0], src[1], self._xfer_count, mt))
            else:
                self._text(_M.MAV_SEVERITY_INFO, "Mission download request ignored, already active")
            return
        if self._max_items(mt) is None:
            self._ack(src, _M.MAV_MISSION_UNSUPPORTED, mt)
        elif self._state == _GETLIST:
            self._ack(src, _M.MAV_MISSION_DENIED, mt)
        else:
            self._send(self.v.link.mav.mission_count_encode(src[0], src[1], self._count_for(mt), mt))

    def _on_request(self, msg) -> None:
        if not self._for_me(msg):
            return
        is_int, src, mt, seq = msg.get_type() == "MISSION_REQUEST_INT", self._src(msg), int(msg.mission_type), int(msg.seq)
        if self.px4:
            self._int_mode = is_int
            if src != self._partner:
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: REJ. CMD: partner id mismatch")
                return
            if self._state == _IDLE:
                return  # silently ignored (PX4: "some OSDs have buggy mission protocol implementations")
            if self._state == _GETLIST:
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: REJ. CMD: Busy")
                return
            if mt != self._xfer_type:
                return
            self._t_recv = self._now()
            if seq == self._xfer_seq and seq < self._xfer_count:
                self._xfer_seq += 1
            elif seq != self._xfer_seq - 1:
                self._state = _IDLE
                self._ack(src, _M.MAV_MISSION_ERROR)
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: REJ. CMD: Req. WP was unexpected")
                return
            if seq >= self._count_for(mt):
                self._state = _IDLE
                self._ack(src, _M.MAV_MISSION_ERROR)
                return
            self._t_sent = self._now()
            self._send_item(src, seq, self._stored(mt)[seq], is_int, mt)
            return
        if self._max_items(mt) is None:
            return
        if is_int and self._state == _GETLIST:
            self._ack(src, _M.MAV_MISSION_DENIED, mt)
            return
        count = self._count_for(mt)
        if (mt == _MT_MISSION and seq != 0 and seq >= count) or (mt != _MT_MISSION and seq >= count):
            if is_int:  # educate the GCS about the mission size
                self._send(self.v.link.mav.mission_count_encode(src[0], src[1], count, mt))
            self._ack(src, _M.MAV_MISSION_INVALID_SEQUENCE, mt)
            return
        item = self._home_item() if (seq == 0 and mt == _MT_MISSION) else self._stored(mt)[seq]
        if item is None:
            self._ack(src, _M.MAV_MISSION_ERROR, mt)
            return
        if not is_int and not self._request_warning:
            self._request_warning = True
            self._text(_M.MAV_SEVERITY_WARNING, "got MISSION_REQUEST; use MISSION_REQUEST_INT!")
        self._send_item(src, seq, item, is_int, mt)

    def _home_item(self) -> MissionItem | None:
        """ArduPilot's item 0: the current home (absolute altitude)."""
        if self.v.c.global_origin is None:
            return MissionItem(_M.MAV_CMD_NAV_WAYPOINT, _M.MAV_FRAME_GLOBAL, relative=False)
        lat, lon, alt = self.v._global_from_scene(self.home_scene)
        return MissionItem(_M.MAV_CMD_NAV_WAYPOINT, _M.MAV_FRAME_GLOBAL, (0.0, 0.0, 0.0, 0.0),
                           int(round(lat * 1e7)), int(round(lon * 1e7)), int(alt * 100) / 100.0, False)

    def _send_item(self, to, seq: int, item: MissionItem, as_int: bool, mt: int) -> None:
        mav = self.v.link.mav
        frame = item.frame
        if self.px4 and item.is_position:  # format_mavlink_mission_item: frame from the altitude mode and int mode
            frame = ((_M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT if as_int else _M.MAV_FRAME_GLOBAL_RELATIVE_ALT) if item.relative
                     else (_M.MAV_FRAME_GLOBAL_INT if as_int else _M.MAV_FRAME_GLOBAL))
        current = int(seq == self.current) if (self.px4 or (seq > 0 and mt == _MT_MISSION)) else 0
        autocontinue = item.autocontinue if self.px4 else 1
        if as_int:
            x, y = (int(item.x), int(item.y)) if (item.is_position or not self.px4) else (int(round(item.x)), int(round(item.y)))
            self._send(mav.mission_item_int_encode(to[0], to[1], seq, frame, item.command, current, autocontinue,
                                                   *item.params, x, y, item.z, mt))
        else:
            x, y = (item.x * 1e-7, item.y * 1e-7) if (item.is_position or not self.px4) else (float(item.x), float(item.y))
            self._send(mav.mission_item_encode(to[0], to[1], seq, frame, item.command, current, autocontinue,
                                               *item.params, x, y, item.z, mt))

    def _on_ack(self, msg) -> None:  # PX4 only: ArduPilot ignores a GCS's MISSION_ACK
        if not self._for_me(msg) or self._src(msg) != self._partner:
            return
        if self._state == _SENDLIST and int(msg.mission_type) == self._xfer_type:
            self._t_recv = self._now()
            self._state = _IDLE
        elif self._state == _GETLIST:
            if msg.type == _M.MAV_MISSION_UNSUPPORTED:  # the client wants the other item message
                self._int_mode = not self._int_mode
                self._send_request()
            elif msg.type == _M.MAV_MISSION_OPERATION_CANCELLED:
                self._state = _IDLE

    # -- clear, set current -------------------------------------------------------------------
    def _on_clear_all(self, msg) -> None:
        if not self._for_me(msg):
            return
        src, mt = self._src(msg), int(msg.mission_type)
        if self.px4:
            if self._state != _IDLE:
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: IGN CLEAR CMD: Busy")
                return
            self._xfer_type = mt
            for t in (_MT_MISSION, _MT_FENCE, _MT_RALLY):
                if mt in (t, _M.MAV_MISSION_TYPE_ALL):
                    self._commit_type(t, [], 0)
            self._ack(src, _M.MAV_MISSION_ACCEPTED, mt)
            return
        if self._max_items(mt) is None:
            self._ack(src, _M.MAV_MISSION_UNSUPPORTED, mt)
            return
        if self._state == _GETLIST:
            if src != self._partner:
                self._ack(src, _M.MAV_MISSION_DENIED, mt)
                self._ack(src, _M.MAV_MISSION_ERROR, mt)
                return
            self._state = _IDLE
        if mt == _M.MAV_MISSION_TYPE_MISSION:
            if self.ap_state == "running":  # AP_Mission::clear refuses while the mission runs
                self._ack(src, _M.MAV_MISSION_ERROR, mt)
                return
            self.items = []
            self.current = 0
            self._text(_M.MAV_SEVERITY_INFO, "Flight plan received")
        else:  # MissionItemProtocol_Fence / _Rally::clear_all_items: write_fence(nullptr, 0), truncate(0)
            self._commit_type(mt, [], 0)
        self._ack(src, _M.MAV_MISSION_ACCEPTED, mt)

    def _on_set_current(self, msg) -> None:
        if msg.target_system != self.v.c.system_id:
            return
        seq = int(msg.seq)
        if self.px4:
            if self._state != _IDLE:
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: IGN WP CURR CMD: Busy")
            elif seq < len(self.items):
                self._px4_set_current(seq)
            else:
                self._text(_M.MAV_SEVERITY_CRITICAL, "WPM: WP CURR CMD: Not in list")
            return
        if self._ap_set_current(seq):  # the same seq back, the GCSs' acknowledgement
            self._send(self._mission_current_msg(seq))

    def _px4_set_current(self, seq: int) -> None:
        self.current, self.finished, self._phase = seq, False, None
        self._send(self._mission_current_msg())

    def _ap_set_current(self, seq: int) -> bool:
        """``AP_Mission::set_current_cmd``."""
        n = len(self.items)
        if seq >= n or n == 1:
            return False
        seq = max(seq, 1)
        if self.ap_state == "running":
            self._ap_start_nav(seq)
        else:
            self.current, self.ap_state, self._ap_started = seq, "stopped", True
        return True

    # -- commands -----------------------------------------------------------------------------
    def on_command(self, cmd: int, p: list) -> int | None:
        """MAV_CMD_MISSION_START and MAV_CMD_DO_SET_MISSION_CURRENT; None for other commands."""
        if cmd == _M.MAV_CMD_MISSION_START:
            return self._cmd_mission_start(p)
        if cmd == _M.MAV_CMD_DO_SET_MISSION_CURRENT:
            if self.px4:  # navigator_main.cpp
                if not (math.isfinite(p[0]) and p[0] >= -1 and math.isfinite(p[1]) and p[1] in (0.0, 1.0)):
                    return _M.MAV_RESULT_DENIED
                seq = int(p[0])
                if not self.valid() or seq >= len(self.items):
                    return _M.MAV_RESULT_FAILED
                if seq >= 0:
                    self._px4_set_current(seq)
                return _M.MAV_RESULT_ACCEPTED
            if not math.isfinite(p[0]) or not self._ap_set_current(int(p[0])):
                return _M.MAV_RESULT_FAILED
            self.v._pending.append(self._mission_current_msg(int(p[0])))
            return _M.MAV_RESULT_ACCEPTED
        return None

    def _cmd_mission_start(self, p: list) -> int:
        v = self.v
        if self.px4:  # Commander.cpp VEHICLE_CMD_MISSION_START: switch to AUTO_MISSION and arm
            if not self.valid():
                self._text(_M.MAV_SEVERITY_CRITICAL, "Mission start denied! No valid mission")
                return _M.MAV_RESULT_DENIED
            if not (math.isfinite(p[0]) and -1 <= p[0] < len(self.items)):
                return _M.MAV_RESULT_DENIED
            mode = px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["mission"])
            if self.refuse_mode(mode) is not None or not v._position_valid:
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            if p[0] >= 0:
                self._px4_set_current(int(p[0]))
            v._set_mode(mode, "MISSION_START")
            if v._cmd_arm(True, False) != _M.MAV_RESULT_ACCEPTED:
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            return _M.MAV_RESULT_ACCEPTED
        # ArduCopter GCS_Mavlink.cpp: set AUTO, then start or resume the mission
        if self.refuse_mode(ARDUCOPTER_MODE["auto"]) is not None or not v._position_valid:
            return _M.MAV_RESULT_FAILED
        v._set_mode(ARDUCOPTER_MODE["auto"], "MISSION_START")
        return _M.MAV_RESULT_ACCEPTED

    def refuse_mode(self, custom_mode: int) -> int | None:
        """The MAV_RESULT refusing a switch to the mission mode, or None."""
        v = self.v
        if self.px4:
            if custom_mode != px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["mission"]):
                return None
            if not self.valid():  # failsafe flag auto_mission_missing / global position needed
                self._text(_M.MAV_SEVERITY_CRITICAL, "Switching to Mission is currently not available")
                self._text(_M.MAV_SEVERITY_CRITICAL, "No valid mission available")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            return None
        if custom_mode != ARDUCOPTER_MODE["auto"] or v.custom_mode == custom_mode:
            return None
        if not self.present():
            self._text(_M.MAV_SEVERITY_CRITICAL, "Flight mode change failed")
            return _M.MAV_RESULT_FAILED
        if v.armed and v.landed_state == _M.MAV_LANDED_STATE_ON_GROUND and not self._ap_starts_with_takeoff():
            self._text(_M.MAV_SEVERITY_CRITICAL, "Auto: Missing Takeoff Cmd")
            return _M.MAV_RESULT_FAILED
        return None

    def _ap_starts_with_takeoff(self) -> bool:
        """``AP_Mission::starts_with_takeoff_cmd`` (MIS_RESTART 0: from the resume point)."""
        start = self.current if (self._ap_started and self.ap_state != "complete" and self.current >= 1) else 1
        nav = next((it for it in self.items[start:] if it.command in _NAV), None)
        return nav is not None and nav.command == _M.MAV_CMD_NAV_TAKEOFF

    # -- telemetry ----------------------------------------------------------------------------
    def in_mission_mode(self) -> bool:
        mode = px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["mission"]) if self.px4 else ARDUCOPTER_MODE["auto"]
        return self.v.custom_mode == mode

    def _mission_current_msg(self, seq: int | None = None):
        n = len(self.items)
        in_mode = self.in_mission_mode()
        if self.px4:  # MavlinkMissionManager::send_mission_current
            total = n if n > 0 else 0xFFFF
            if n == 0:
                state = _M.MISSION_STATE_NO_MISSION
            elif self.finished:
                state = _M.MISSION_STATE_COMPLETE
            elif in_mode and self.v.armed:
                state = _M.MISSION_STATE_ACTIVE
            elif self.current > 0 or self._last_reached >= 0:
                state = _M.MISSION_STATE_PAUSED
            else:
                state = _M.MISSION_STATE_NOT_STARTED
            return self.v.link.mav.mission_current_encode(self.current if seq is None else seq, total, state, int(in_mode))
        # GCS_MAVLINK::send_mission_current: total excludes home
        state = {"stopped": _M.MISSION_STATE_NOT_STARTED, "running": _M.MISSION_STATE_ACTIVE,
                 "complete": _M.MISSION_STATE_COMPLETE}[self.ap_state] if self.present() else _M.MISSION_STATE_NO_MISSION
        return self.v.link.mav.mission_current_encode(self.current if seq is None else seq, max(n - 1, 0), state, int(in_mode))

    def mission_current_stream(self):
        """ArduPilot's streamed MISSION_CURRENT (EXT_STAT group); None on PX4."""
        return None if self.px4 else self._mission_current_msg()

    def _reached(self, seq: int) -> None:
        self.reached_log.append(seq)
        self.v._event(f"mission item {seq} reached")
        self._send(self.v.link.mav.mission_item_reached_encode(seq))
        if self.px4:
            self._last_reached, self._reached_resends = seq, 0

    # -- the periodic part --------------------------------------------------------------------
    def step(self, t: float) -> None:
        """Transfer timers, PX4's MISSION_CURRENT, and the mission flight (vehicle lock held)."""
        self._protocol_timers(t)
        if self.px4 and t >= self._next_current_s:
            self._next_current_s = t + 1.0  # _slow_rate_limiter: 1 Hz
            self._send(self._mission_current_msg())
            if self.items and self._last_reached >= 0 and self._reached_resends < 10:
                self._reached_resends += 1
                self._send(self.v.link.mav.mission_item_reached_encode(self._last_reached))
        if self.px4 and self._last_sent_current != self.current:
            self._last_sent_current = self.current
            self._send(self._mission_current_msg())
        in_mode = self.in_mission_mode()
        if in_mode and not self._active:
            self._active = True
            self._activate()
        elif not in_mode and self._active:
            self._active = False
            self._phase = None
            if not self.px4 and self.ap_state == "running":
                self.ap_state = "stopped"  # ModeAuto::exit: mission.stop()
        if self._active and self.v.armed:
            (self._px4_run if self.px4 else self._ap_run)(t)

    def _protocol_timers(self, t: float) -> None:
        if self._state == _IDLE:
            return
        if self.px4:
            if self._state == _GETLIST and t - self._t_sent > PX4_RETRY_S:
                self._send_request()
            elif t - self._t_recv > PX4_TIMEOUT_S:
                self._text(_M.MAV_SEVERITY_CRITICAL, "Operation timeout")
                self.v._event("mission transfer timed out")
                self._state = _IDLE  # the received items were never made active
            return
        if self._state != _GETLIST:
            return
        if t - self._t_recv > AP_TIMEOUT_S:
            self._state = _IDLE
            self._text(_M.MAV_SEVERITY_WARNING, {_MT_FENCE: "Fence upload timeout", _MT_RALLY: "Rally upload timeout"}.get(
                self._xfer_type, "Mission upload timeout"))
            self.v._event("mission transfer timed out")
            self._ack(self._partner, _M.MAV_MISSION_OPERATION_CANCELLED)
        elif t - self._t_sent > AP_RESEND_S:
            self._send_request()

    # -- flight: shared -----------------------------------------------------------------------
    def _param(self, name: str) -> float:
        """A navigation parameter of :data:`MISSION_PARAM_SI` in SI units (m, m/s)."""
        return float(self.v.params[name]) * MISSION_PARAM_SI[name]

    def _item_scene(self, item: MissionItem) -> np.ndarray:
        lat, lon = item.x * 1e-7, item.y * 1e-7
        alt = item.z + (self.v._global_from_scene(self.home_scene)[2] if item.relative else 0.0)
        return self.v._scene_from_global(lat, lon, alt)

    def _landed(self) -> bool:
        return self.v.landed_state == _M.MAV_LANDED_STATE_ON_GROUND or self.v.model.on_ground

    def _go(self, p: np.ndarray, speed: float | None) -> None:
        from onfly.mavlink.sim_vehicle import _Target

        self.v._target = _Target(p=np.asarray(p, float).copy(), yaw=None, v_limit_mps=speed)

    def _descend(self, xy: np.ndarray, speed: float) -> None:
        from onfly.mavlink.sim_vehicle import _Target

        m = self.v.model
        v = np.zeros(3)
        v[:2] = self.v.c.k_pos * (np.asarray(xy[:2]) - m.p[:2])
        v[2] = -speed
        self.v._target = _Target(v=v, yaw=m.yaw, kind="velocity")

    def _apply_speed(self, item: MissionItem) -> None:
        speed_type, speed = int(item.params[0]), item.params[1]
        if speed > 0 and speed_type in (_M.SPEED_TYPE_AIRSPEED, _M.SPEED_TYPE_GROUNDSPEED):
            self._speed = float(speed)
            self.v._event(f"mission speed {speed:.2f} m/s")

    def _return(self) -> None:
        mode = px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["rtl"]) if self.px4 else ARDUCOPTER_MODE["rtl"]
        self.v._set_mode(mode, "mission RETURN_TO_LAUNCH")

    # -- flight: PX4 --------------------------------------------------------------------------
    def _activate(self) -> None:
        self._phase = None
        if self.px4:
            if self.finished:  # a finished mission starts again from its first item
                self.current, self.finished = 0, False
            return
        # ArduCopter: start_or_resume (MIS_RESTART 0) once there is an EKF origin
        self._speed = None
        if self.v.c.global_origin is None:
            self.v._event("mission waiting for an EKF origin")
            return
        if self.ap_state == "complete" or not self._ap_started or self.current < 1:
            self._ap_start()
        else:
            self.ap_state = "running"
            self._ap_start_nav(self.current)

    def _px4_run(self, t: float) -> None:
        if self.finished or not self.items:
            return
        if self.current >= len(self.items):
            self._px4_finish()
            return
        item = self.items[self.current]
        if self._phase is None:
            self._phase, self._phase_t = "start", t
            if item.command == _M.MAV_CMD_DO_CHANGE_SPEED:
                self._apply_speed(item)
                self._reached(self.current)  # a DO item completes at once
                self._px4_advance()
                return
            if item.command == _M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                self._reached(self.current)
                self._px4_advance(finish_mode=False)
                self._return()
                return
            self._target = self._item_scene(item)
            m = self.v.model
            if self._landed() and item.command in (_M.MAV_CMD_NAV_TAKEOFF, _M.MAV_CMD_NAV_WAYPOINT):
                alt = max(self._target[2], m.p[2] + float(self.v.params["MIS_TAKEOFF_ALT"]))
                self._takeoff_point = np.array([m.p[0], m.p[1], alt])
                self._phase = "takeoff" if item.command == _M.MAV_CMD_NAV_TAKEOFF else "takeoff_first"
                self._text(_M.MAV_SEVERITY_INFO, f"Takeoff to {alt - self.home_scene[2]:.1f} meters above home")
            elif item.command == _M.MAV_CMD_NAV_TAKEOFF:
                self._takeoff_point = np.array([m.p[0], m.p[1], max(self._target[2], m.p[2])])
                self._phase = "takeoff"
            elif item.command == _M.MAV_CMD_NAV_LAND:
                far = np.linalg.norm(self._target[:2] - m.p[:2]) > self._param("NAV_ACC_RAD")
                self._phase = "move_to_land" if far else "land"
                self._land_alt = m.p[2]
            else:
                self._phase = "goto"
        m = self.v.model
        alt_rad = self._param("NAV_MC_ALT_RAD")
        if self._phase in ("takeoff", "takeoff_first"):
            self._go(self._takeoff_point, float(self.v.params["MPC_TKO_SPEED"]))
            if m.p[2] >= self._takeoff_point[2] - alt_rad:
                if self._phase == "takeoff":
                    self._reached(self.current)
                    self._px4_advance()
                else:
                    self._phase = "goto"
            return
        if self._phase == "goto":
            self._go(self._target, self._speed or self._param("MPC_XY_CRUISE"))
            acc = item.params[1] if (math.isfinite(item.params[1]) and item.params[1] >= 0.001) else self._param("NAV_ACC_RAD")
            if np.linalg.norm(self._target[:2] - m.p[:2]) <= acc and abs(self._target[2] - m.p[2]) <= alt_rad:
                self._phase, self._phase_t = "hold", t
            return
        if self._phase == "hold":
            self._go(self._target, self._speed or self._param("MPC_XY_CRUISE"))
            hold = item.params[0] if math.isfinite(item.params[0]) and item.params[0] > 0 else 0.0
            if t - self._phase_t >= hold:
                self._reached(self.current)
                self._px4_advance()
            return
        if self._phase == "move_to_land":
            p = np.array([self._target[0], self._target[1], self._land_alt])
            self._go(p, self._speed or self._param("MPC_XY_CRUISE"))
            if np.linalg.norm(p[:2] - m.p[:2]) <= self._param("NAV_ACC_RAD"):
                self._phase = "land"
            return
        if self._phase == "land":
            self._descend(self._target, float(self.v.params["MPC_LAND_SPEED"]))
            if self.v.landed_state == _M.MAV_LANDED_STATE_ON_GROUND:
                self._reached(self.current)
                self._px4_advance()

    def _px4_advance(self, finish_mode: bool = True) -> None:
        self._phase = None
        if self.current + 1 < len(self.items):
            self.current += 1
            return
        self._px4_finish(finish_mode)

    def _px4_finish(self, switch_to_hold: bool = True) -> None:
        """End of mission: "Mission finished, landed" or loiter; in the air Commander then
        switches to AUTO.LOITER (Commander.cpp: mission finished in AUTO_MISSION)."""
        self.finished = True
        self.current = max(len(self.items) - 1, 0)
        if self._landed():
            self._text(_M.MAV_SEVERITY_INFO, "Mission finished, landed")
            return
        self._text(_M.MAV_SEVERITY_INFO, "Mission finished, loitering")
        if switch_to_hold:
            self.v._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]), "mission finished")

    # -- flight: ArduCopter --------------------------------------------------------------------
    def _ap_start(self) -> None:
        """``AP_Mission::start``: from the first real command (1)."""
        self.ap_state, self._ap_started, self._speed = "running", True, None
        first_nav = next((i for i in range(1, len(self.items)) if self.items[i].command in _NAV), None)
        for i in range(1, first_nav if first_nav is not None else len(self.items)):
            self._ap_do(i)  # DO commands before the first NAV command
        if first_nav is None:
            self._ap_complete()
        else:
            self._ap_start_nav(first_nav)

    def _ap_do(self, i: int) -> None:
        item = self.items[i]
        if item.command == _M.MAV_CMD_DO_CHANGE_SPEED:
            self._apply_speed(item)
        self._reached(i)  # do commands verify at once

    def _ap_start_nav(self, i: int) -> None:
        """Start NAV command ``i`` (or the next NAV at or after it) and the DO commands after it."""
        while i < len(self.items) and self.items[i].command not in _NAV:
            self._ap_do(i)
            i += 1
        if i >= len(self.items):
            self._ap_complete()
            return
        self.current, self._phase = i, None
        j = i + 1
        while j < len(self.items) and self.items[j].command not in _NAV:
            self._ap_do(j)
            j += 1

    def _ap_complete(self) -> None:
        """``ModeAuto::exit_mission``: loiter in AUTO, or disarm when landed."""
        self.ap_state, self._phase = "complete", "done"
        m = self.v.model
        if self._landed():
            self.v._disarm("mission complete (landed)")
        else:  # loiter_start: at the stopping point
            self._go(m.p + m.v * np.linalg.norm(m.v) / (2.0 * self.v.c.a_max_mps2), None)

    def _ap_run(self, t: float) -> None:
        if self.ap_state != "running" or self._phase == "done":
            return
        if self.current >= len(self.items):
            self._ap_complete()
            return
        item, m = self.items[self.current], self.v.model
        if self._phase is None:
            self._phase, self._phase_t = "start", t
            if item.command == _M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                self._return()  # simplified: ArduCopter runs RTL as a sub-mode of AUTO
                return
            target = self._ap_location(item)
            if item.command == _M.MAV_CMD_NAV_TAKEOFF:
                floor = m.p[2] + (1.0 if self._landed() else 0.0)  # takeoff_start: at least 1 m when landed
                self._target, self._phase = np.array([m.p[0], m.p[1], max(target[2], floor)]), "takeoff"
            elif item.command == _M.MAV_CMD_NAV_LAND:
                if item.x != 0 or item.y != 0:
                    self._target, self._phase = np.array([target[0], target[1], m.p[2]]), "move_to_land"
                else:
                    self._target, self._phase = m.p.copy(), "land"
            else:
                self._target, self._phase = target, "goto"
        if self._phase == "takeoff":
            self._go(self._target, float(self.v.params["WPNAV_SPEED_UP"]) / 100.0)
            if m.p[2] >= self._target[2] - 0.1:
                self._reached(self.current)
                self._ap_start_nav(self.current + 1)
            return
        if self._landed() and self._phase in ("goto", "hold"):
            self.v._target = None  # wp_run: disarmed or landed -> ground handling
            return
        if self._phase in ("goto", "hold", "move_to_land"):
            self._go(self._target, self._speed or self._param("WPNAV_SPEED"))
            reached = np.linalg.norm(self._target - m.p) <= self._param("WPNAV_RADIUS")
            if self._phase == "move_to_land":
                if reached:
                    self._phase = "land"
                return
            if self._phase == "goto" and reached:
                self._phase, self._phase_t = "hold", t
            if self._phase == "hold" and int(t - self._phase_t) >= item.params[0]:
                self._text(_M.MAV_SEVERITY_INFO, f"Reached command #{self.current}")
                self._reached(self.current)
                self._ap_start_nav(self.current + 1)
            return
        if self._phase == "land":
            self._descend(self._target, float(self.v.params["LAND_SPEED"]) / 100.0)
            if self.v.landed_state == _M.MAV_LANDED_STATE_ON_GROUND and self.v._flying_since_arm:
                self.v._disarm("landed")  # verify_land: disarm, the mission stays on its NAV_LAND

    def _ap_location(self, item: MissionItem) -> np.ndarray:
        """``ModeAuto::loc_from_cmd``: lat/lon 0 -> here, altitude 0 -> this altitude."""
        m = self.v.model
        if item.x == 0 and item.y == 0:
            lat, lon, _ = self.v._global_from_scene(m.p)
            item = replace(item, x=int(round(lat * 1e7)), y=int(round(lon * 1e7)))
        p = self._item_scene(item)
        if item.z == 0:
            p[2] = m.p[2]
        return p
