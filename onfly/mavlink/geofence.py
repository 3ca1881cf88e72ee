"""Geofence and rally points of :class:`~onfly.mavlink.sim_vehicle.SimMavlinkVehicle`: the
geometry of an uploaded fence, each autopilot's validation of it, its enforcement, and the
choice of a rally point by the Return mode.

The items arrive through the mission protocol (:mod:`onfly.mavlink.mission`, mission_type
FENCE and RALLY); this module reads them as stored there (:class:`~onfly.mavlink.mission.MissionItem`:
``x``/``y`` lat/lon in degE7, ``params[0]`` the vertex count of a polygon or the radius of a
circle in metres). Fences are in lat/lon: they apply only where the vehicle has a global position
(the outdoor profile). Each rule names its source.

Geometry (both autopilots)
--------------------------
A polygon starts at an item whose param1 is its vertex count n and takes that item and the n - 1
after it (PX4 ``Geofence::_updateFence``; ArduPilot ``AC_PolyFence_loader`` stores each polygon
with its count). The vehicle is inside the fence when it is inside every inclusion polygon and
circle and outside every exclusion one: PX4 ``Geofence::isInsidePolygonOrCircle`` ANDs every
zone; ArduPilot ``AC_PolyFence_loader::breached`` is breached outside any inclusion zone or inside
any exclusion zone (FENCE_OPTIONS bit 1, the union of inclusion zones, is Plane-only). The polygon
test is the even-odd ray test on lat/lon (PX4 ``Geofence::insidePolygon``, PNPOLY); a circle is a
local-projection distance against its radius (PX4 ``insideCircle``: inside when closer than the
radius). NAV_FENCE_RETURN_POINT is stored and downloaded but not flown (Plane's fence return).

PX4 (``src/modules/navigator/geofence.cpp``, ``navigator_main.cpp``, Commander)
--------------------------------------------------------------------------------
- When an upload completes the navigator re-reads the fence (``_updateFence``) and drops a zone
  that does not contain home ("Geofence invalid, doesn't contain Home position") and, flying with
  GF_ACTION != 0, one that does not contain the vehicle ("Geofence invalid, doesn't contain current
  vehicle position"); the upload itself was ACCEPTED. A polygon with 0 vertices is skipped.
- ``Navigator::geofence_breach_check`` every 200 ms (GEOFENCE_CHECK_INTERVAL_US), armed or not,
  only with a global position: without one "we can't check for geofence violations" and nothing
  happens (indoors a lat/lon fence is never checked; GF_MAX_HOR_DIST / GF_MAX_VER_DIST neither,
  they need the global position and home). Breached = beyond GF_MAX_HOR_DIST from home (0:
  off), GF_MAX_VER_DIST above home (0: off), or outside the uploaded zones. GF_SOURCE 0 (global
  position) and 1 (GPS) are the same position in this model. GF_PREDICT (default 0) is not
  modelled: the test point is the current position.
- A breach with GF_ACTION != 0 is a failsafe (``HealthAndArmingChecks/checks/geofenceCheck.cpp``:
  STATUSTEXT "Geofence: approaching or outside geofence", an arming-check failure, so arming is
  refused while breached) and Commander takes the action (``failsafe.cpp`` ``fromGfActParam``):
  1 Warning (the text only), 2 Hold (AUTO.LOITER where the vehicle is; the navigator's breach
  reposition with GF_PREDICT 0 is the current position), 3 Return, 4 Terminate (motors off: a
  disarm in the air), 5 Land. The action runs once per breach (clear condition "on mode change or
  disarm": the user may fly on) and again after the vehicle was back inside.

ArduCopter (``libraries/AC_Fence/AC_Fence.cpp``, ``ArduCopter/fence.cpp``)
-------------------------------------------------------------------------
- FENCE_ENABLE (Copter default 0) switches the fence on; FENCE_TYPE (default 7: max altitude 1,
  circle 2, polygons 4) selects the fences: FENCE_ALT_MAX (100 m above home), FENCE_RADIUS (300 m
  around home) and the uploaded inclusion / exclusion zones. Checked at 25 Hz
  (``Copter::fence_checks_async``), armed or not; a zone check needs a location (indoors the
  polygons are never breached).
- Pre-arm (``AC_Fence::pre_arm_check``, enabled only): "Fence requires position" when a circle or
  polygon fence is selected and there is no position relative to home (indoors: no home location),
  "Vehicle breaching <fences>" while breached.
- A new breach armed (``Copter::fence_check``): STATUSTEXT "<Polygon fence> breached"
  (``AC_Fence::print_fence_message``); landed -> disarm; else FENCE_ACTION: 0 report only,
  1 RTL (Land if RTL fails), 2 Land, 3 SmartRTL or RTL or Land, 4 Brake or Land, 5 SmartRTL or Land
  (no SmartRTL in this model: its fallback), and more than 100 m outside (AC_FENCE_GIVE_UP_DISTANCE;
  altitude and circle distances) always Land. "Fence breach cleared" when back inside.
- FENCE_MARGIN (2 m) is served for clients and checked against FENCE_RADIUS pre-arm; the margin
  avoidance of the position controllers is not modelled.

Rally points and the Return mode
--------------------------------
- PX4 ``RTL::findRtlDestination`` (RTL_TYPE 0, the default: home or the closest safe point): a
  rally point counts only if it is more than 10 m from home (MAX_DIST_FROM_HOME_FOR_LAND_APPROACHES)
  and is chosen if it is closer than the best so far by more than 2 m (MIN_DIST_THRESHOLD), starting
  from home's distance; its altitude is relative to home in a RELATIVE frame, else AMSL.
- ArduCopter ``AP_Rally::calc_best_rally_or_home_location``: the nearest rally point, unless
  RALLY_LIMIT_KM (0.3) > 0 and it is farther than that (then home); with RALLY_INCL_HOME (1) it must
  also be closer than home. Rally altitudes are metres above home (int16).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
import numpy as np

from onfly.mavlink.frames import ne_offset_m
from onfly.mavlink.link import mavlink2

__all__ = ["FenceZone", "Fence", "fence_from_items", "ardupilot_fence_error", "px4_rally_destination",
           "ardu_rally_destination", "PX4_FENCE_MAX_ITEMS", "PX4_RALLY_MAX_ITEMS", "ARDUPILOT_FENCE_MAX_ITEMS",
           "ARDUPILOT_RALLY_MAX_ITEMS", "FenceMonitor"]

_M = mavlink2
PX4_FENCE_MAX_ITEMS = 64  # PX4 dataman.h DM_KEY_FENCE_POINTS_MAX
PX4_RALLY_MAX_ITEMS = 32  # PX4 dataman.h DM_KEY_SAFE_POINTS_MAX
ARDUPILOT_FENCE_MAX_ITEMS = 84  # AC_PolyFence_loader::max_items on a 16 kB board (StorageManager layout)
ARDUPILOT_RALLY_MAX_ITEMS = 50  # AP_Rally::get_rally_max on a 16 kB board (StorageManager layout)
PX4_CHECK_INTERVAL_S = 0.2  # navigator_main.cpp GEOFENCE_CHECK_INTERVAL_US
AP_CHECK_INTERVAL_S = 0.04  # Copter::fence_checks_async, 25 Hz
AP_GIVE_UP_DISTANCE_M = 100.0  # AC_Fence.h AC_FENCE_GIVE_UP_DISTANCE
PX4_SAFE_POINT_MIN_FROM_HOME_M = 10.0  # rtl.cpp MAX_DIST_FROM_HOME_FOR_LAND_APPROACHES
PX4_SAFE_POINT_THRESHOLD_M = 2.0  # rtl.cpp MIN_DIST_THRESHOLD

POLYGON_COMMANDS = (_M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, _M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION)
CIRCLE_COMMANDS = (_M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, _M.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION)
FENCE_COMMANDS = POLYGON_COMMANDS + CIRCLE_COMMANDS + (_M.MAV_CMD_NAV_FENCE_RETURN_POINT,)
_INCLUSION = (_M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, _M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION)


@dataclass(frozen=True)
class FenceZone:
    """One zone of a fence.

    command : the MAV_CMD of its (first) item (polygon / circle, inclusion / exclusion)
    vertices : ((lat_deg, lon_deg), ...) of a polygon; empty for a circle
    center : (lat_deg, lon_deg) of a circle
    radius_m : circle radius, m
    first_seq : seq of its first item in the fence upload
    """

    command: int
    vertices: tuple = ()
    center: tuple = (0.0, 0.0)
    radius_m: float = 0.0
    first_seq: int = 0

    @property
    def inclusion(self) -> bool:
        return self.command in _INCLUSION

    @property
    def is_circle(self) -> bool:
        return self.command in CIRCLE_COMMANDS

    def inside(self, lat: float, lon: float) -> bool:
        """Is (lat, lon) (degrees) inside the zone's area (not: is it allowed there)."""
        if self.is_circle:
            return _distance_m(lat, lon, *self.center) < self.radius_m
        c = False  # PNPOLY on lat/lon, lon as the abscissa (PX4 Geofence::insidePolygon)
        n = len(self.vertices)
        for i in range(n):
            lat_i, lon_i = self.vertices[i]
            lat_j, lon_j = self.vertices[i - 1]
            if (lon_i >= lon) != (lon_j >= lon) and lat <= (lat_j - lat_i) * (lon - lon_i) / (lon_j - lon_i) + lat_i:
                c = not c
        return c

    def allows(self, lat: float, lon: float) -> bool:
        return self.inside(lat, lon) == self.inclusion


@dataclass(frozen=True)
class Fence:
    """The zones of a stored fence (empty: no fence)."""

    zones: tuple = ()

    def allows(self, lat: float, lon: float) -> bool:
        """Inside every inclusion zone and outside every exclusion zone (both autopilots)."""
        return all(z.allows(lat, lon) for z in self.zones)


def _distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Horizontal distance (m) on a local tangent plane (PX4 map projection / ArduPilot Location)."""
    return math.hypot(*ne_offset_m(lat1, lon1, lat2, lon2))


def fence_from_items(items) -> Fence:
    """Zones of stored fence items (PX4 ``Geofence::_updateFence`` walk: a polygon takes its first
    item's vertex count of items; a polygon with 0 vertices or an unknown command is skipped)."""
    zones, seq = [], 0
    while seq < len(items):
        it = items[seq]
        if it.command in CIRCLE_COMMANDS:
            zones.append(FenceZone(it.command, center=(it.x * 1e-7, it.y * 1e-7), radius_m=float(it.params[0]), first_seq=seq))
            seq += 1
        elif it.command in POLYGON_COMMANDS:
            n = int(round(it.params[0]))
            if n <= 0:
                seq += 1
                continue
            verts = tuple((v.x * 1e-7, v.y * 1e-7) for v in items[seq:seq + n])
            if len(verts) >= 3:
                zones.append(FenceZone(it.command, vertices=verts, first_seq=seq))
            seq += n
        else:
            seq += 1  # NAV_FENCE_RETURN_POINT (not flown) or an unhandled command
    return Fence(tuple(zones))


def ardupilot_fence_error(items) -> str | None:
    """``AC_PolyFence_loader::validate_fence``: the STATUSTEXT of the first problem, or None."""
    expected, orig, kind, seen_return = 0, 0, None, False
    for it in items:
        if it.command in POLYGON_COMMANDS:
            count = int(it.params[0])
            if count < 3:
                return f"Invalid vertex count ({count})"
            if expected == 0:
                expected = orig = count
                kind = it.command
            elif it.command != kind:
                return f"Received incorrect vertex type (want={kind} got={it.command})"
            elif count != orig:
                return f"Unexpected vertex count want={orig} got={count}"
            expected -= 1
        elif it.command in CIRCLE_COMMANDS or it.command == _M.MAV_CMD_NAV_FENCE_RETURN_POINT:
            if expected:
                return f"Received incorrect type (want={kind} got={it.command})"
            if it.command in CIRCLE_COMMANDS and not it.params[0] > 0:
                return "Non-positive circle radius"
            if it.command == _M.MAV_CMD_NAV_FENCE_RETURN_POINT:
                if seen_return:
                    return "Multiple return points"
                seen_return = True
        if abs(it.x) > 900000000 or abs(it.y) > 1800000000:
            return "Bad lat or lon"
    if expected:
        return "Incorrect item count"
    return None


def px4_rally_destination(v, p_m: np.ndarray, home_m: np.ndarray, rally) -> np.ndarray | None:
    """PX4 ``RTL::findRtlDestination`` (RTL_TYPE 0): the scene point of the chosen safe point, or
    None for home. ``rally`` are stored MissionItems; positions scene ENU, m."""
    best, min_dist = None, float(np.linalg.norm(p_m[:2] - home_m[:2]))
    home_amsl = v._global_from_scene(home_m)[2]
    for it in rally:
        alt = it.z + (home_amsl if it.relative else 0.0)
        q = v._scene_from_global(it.x * 1e-7, it.y * 1e-7, alt)
        if np.linalg.norm(q[:2] - home_m[:2]) <= PX4_SAFE_POINT_MIN_FROM_HOME_M:
            continue
        d = float(np.linalg.norm(q[:2] - p_m[:2]))
        if d + PX4_SAFE_POINT_THRESHOLD_M < min_dist:
            best, min_dist = q, d
    return best


def ardu_rally_destination(v, p_m: np.ndarray, home_m: np.ndarray, rally, params: dict) -> np.ndarray | None:
    """ArduCopter ``AP_Rally::calc_best_rally_or_home_location``: the scene point of the rally point
    to return to (z = its altitude above home), or None for home."""
    best, min_dist = None, -1.0
    for it in rally:
        if it.x == 0 and it.y == 0:
            continue  # get_rally_point_with_index sanity check
        q = v._scene_from_global(it.x * 1e-7, it.y * 1e-7, v._global_from_scene(home_m)[2] + it.z)
        d = float(np.linalg.norm(q[:2] - p_m[:2]))
        if min_dist < 0 or d < min_dist:
            best, min_dist = q, d
    if best is None:
        return None
    limit_km = float(params["RALLY_LIMIT_KM"])
    if limit_km > 0 and min_dist > limit_km * 1000.0:
        return None  # all rally points beyond the limit: home
    if int(params["RALLY_INCL_HOME"]) and not min_dist < float(np.linalg.norm(home_m[:2] - p_m[:2])):
        return None
    return best


class FenceMonitor:
    """The breach check and its action, run every physics step with the vehicle's lock held.

    ``v`` is the vehicle; the fence is read from ``v.mission.fence_zones``. Observers for tests:
    :attr:`breached` (the current breach state), :attr:`breach_log` (``(t_s, what)``).
    """

    def __init__(self, vehicle) -> None:
        self.v = vehicle
        self.px4 = vehicle.px4
        self.breached = False
        self.breach_names = ""  # ArduPilot: the breached fences' names
        self.breach_log: list[tuple[float, str]] = []
        self._next_check_s = 0.0
        self._acted = False  # PX4: the action already ran for this breach

    # -- what the vehicle knows --------------------------------------------------------------
    def _global(self, p_m) -> tuple[float, float, float] | None:
        v = self.v
        if v.c.global_origin is None or not v._position_valid:
            return None
        return v._global_from_scene(p_m)

    def _home(self) -> np.ndarray | None:
        return None if self.v._home is None else self.v._home

    # -- PX4 -------------------------------------------------------------------------------
    def px4_breached(self, p_m) -> bool | None:
        """PX4 breach of the current position, or None when it cannot be checked (no global position)."""
        g = self._global(p_m)
        if g is None:
            return None
        P, home = self.v.params, self._home()
        if home is not None:
            if float(P["GF_MAX_HOR_DIST"]) > 1e-6 and np.linalg.norm(np.asarray(p_m)[:2] - home[:2]) >= float(P["GF_MAX_HOR_DIST"]):
                return True
            if float(P["GF_MAX_VER_DIST"]) > 1e-6 and p_m[2] - home[2] >= float(P["GF_MAX_VER_DIST"]):
                return True
        return not self.v.mission.fence_zones.allows(g[0], g[1])

    def px4_zone_accepted(self, zone: FenceZone) -> bool:
        """``Geofence::checkHomeRequirementsForGeofence`` and ``checkCurrentPositionRequirementsForGeofence``."""
        v = self.v
        home = self._home()
        if home is not None and v.c.global_origin is not None and not zone.allows(*v._global_from_scene(home)[:2]):
            v._statustext(_M.MAV_SEVERITY_CRITICAL, "Geofence invalid, doesn't contain Home position")
            return False
        g = self._global(v.model.p)
        landed = v.landed_state == _M.MAV_LANDED_STATE_ON_GROUND
        if int(v.params["GF_ACTION"]) != 0 and not landed and g is not None and not zone.allows(g[0], g[1]):
            v._statustext(_M.MAV_SEVERITY_CRITICAL, "Geofence invalid, doesn't contain current vehicle position")
            return False
        return True

    # -- ArduCopter -------------------------------------------------------------------------
    def _ap_types(self) -> int:
        return int(self.v.params["FENCE_TYPE"]) if int(self.v.params["FENCE_ENABLE"]) else 0

    def ap_breaches(self, p_m) -> list[str]:
        """Names of the fences breached at ``p_m`` (``AC_Fence::check``), in FENCE_NAMES order."""
        types, P, out = self._ap_types(), self.v.params, []
        home = self._home() if self._home() is not None else self.v.model.p
        if types & 1 and p_m[2] - home[2] >= float(P["FENCE_ALT_MAX"]):
            out.append("Max Alt")
        g = self._global(p_m)
        if types & 2 and g is not None and np.linalg.norm(np.asarray(p_m)[:2] - home[:2]) >= float(P["FENCE_RADIUS"]):
            out.append("Circle")
        if types & 4 and g is not None and not self.v.mission.fence_zones.allows(g[0], g[1]):
            out.append("Polygon")
        return out

    def ap_breach_distance(self, p_m, names: list[str]) -> float:
        """``AC_Fence::get_breach_distance`` over altitude and circle (m)."""
        P, d = self.v.params, 0.0
        home = self._home() if self._home() is not None else self.v.model.p
        if "Max Alt" in names:
            d = max(d, p_m[2] - home[2] - float(P["FENCE_ALT_MAX"]))
        if "Circle" in names:
            d = max(d, float(np.linalg.norm(np.asarray(p_m)[:2] - home[:2])) - float(P["FENCE_RADIUS"]))
        return d

    @staticmethod
    def _names(names: list[str]) -> str:
        """``AC_Fence::get_fence_names``: "Polygon fence", "Max Alt and Polygon fences"."""
        if not names:
            return ""
        text = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]
        return text + (" fences" if len(names) > 1 else " fence")

    # -- pre-arm -----------------------------------------------------------------------------
    def prearm_failure(self) -> str | None:
        """Why the fence refuses arming now, or None."""
        v = self.v
        if self.px4:
            if int(v.params["GF_ACTION"]) != 0 and self.px4_breached(v.model.p):
                return "Geofence: approaching or outside geofence"
            return None
        if not int(v.params["FENCE_ENABLE"]):
            return None
        types = int(v.params["FENCE_TYPE"])
        if types & 6 and v.c.global_origin is None:
            return "Fence requires position"  # get_relative_position_NE_home: no home location indoors
        if types & 2 and float(v.params["FENCE_RADIUS"]) < float(v.params["FENCE_MARGIN"]):
            return "Circle FENCE_MARGIN is greater than FENCE_RADIUS"
        names = self.ap_breaches(v.model.p)
        if names:
            return f"Vehicle breaching {self._names(names)}"
        return None

    # -- the periodic check --------------------------------------------------------------------
    def step(self, t: float) -> None:
        if t < self._next_check_s:
            return
        if self.px4:
            self._next_check_s = t + PX4_CHECK_INTERVAL_S
            self._px4_step(t)
        else:
            self._next_check_s = t + AP_CHECK_INTERVAL_S
            self._ap_step(t)

    def _px4_step(self, t: float) -> None:
        v = self.v
        action = int(v.params["GF_ACTION"])
        breached = self.px4_breached(v.model.p)
        if breached is None:
            return  # no global position: the navigator cannot check
        was, self.breached = self.breached, bool(breached) and action != 0
        if not self.breached:
            self._acted = False
            return
        if was and self._acted:
            return
        self._acted = True
        self.breach_log.append((t, "breach"))
        v._event(f"geofence breached (GF_ACTION {action})", t)
        v._statustext(_M.MAV_SEVERITY_CRITICAL, "Geofence: approaching or outside geofence")
        if not v.armed or action == 1:
            return
        v._px4_failsafe_action({2: "loiter", 3: "rtl", 4: "terminate", 5: "land"}.get(action, "loiter"), "geofence breached")

    def _ap_step(self, t: float) -> None:
        v = self.v
        names = self.ap_breaches(v.model.p)
        new = [n for n in names if n not in self.breach_names.split("|")] if self.breached else names
        was = self.breached
        self.breached, self.breach_names = bool(names), "|".join(names)
        if was and not names:
            self.breach_log.append((t, "cleared"))
            if not v._mission_landed():
                v._statustext(_M.MAV_SEVERITY_NOTICE, "Fence breach cleared")
            return
        if not new or not v.armed:
            return
        self.breach_log.append((t, "breach " + ",".join(new)))
        landed = v._mission_landed()
        if not landed:
            v._statustext(_M.MAV_SEVERITY_NOTICE, f"{self._names(new)} breached")
        action = int(v.params["FENCE_ACTION"])
        v._event(f"fence breached: {','.join(new)} (FENCE_ACTION {action})", t)
        if action == 0:
            return
        if landed:
            v._disarm("fence breach on the ground")
            return
        if self.ap_breach_distance(v.model.p, new) > AP_GIVE_UP_DISTANCE_M:
            chain = ("land",)
        else:
            chain = {2: ("land",), 3: ("rtl", "land"), 4: ("brake", "land"), 5: ("land",)}.get(action, ("rtl", "land"))
        for mode in chain:
            if v._ardu_fence_mode(mode):
                break

