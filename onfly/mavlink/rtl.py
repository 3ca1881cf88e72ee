"""Return mode (RTL) of the simulated autopilot, flown as PX4 and ArduCopter fly it.

:class:`SimMavlinkVehicle <onfly.mavlink.sim_vehicle.SimMavlinkVehicle>` starts one of these
state machines when it enters PX4 AUTO.RTL or ArduCopter RTL and drops it when it leaves the
mode; every physics step it asks the machine for the target to track. Positions are scene ENU
metres (z up), home is the arming position, parameters are read live from the vehicle's table.

PX4 (``src/modules/navigator/rtl.cpp`` and ``rtl_direct.cpp``, RTL_TYPE 0: straight home)
------------------------------------------------------------------------------------------
Multicopter defaults (ROMFS ``rc.mc_defaults`` over ``rtl_params.yaml``): RTL_RETURN_ALT 30 m,
RTL_DESCEND_ALT 10 m, NAV_ACC_RAD 2 m; RTL_LAND_DELAY 0 s, RTL_MIN_DIST 10 m, RTL_CONE_ANG 45.

- Return altitude (``RTL::computeReturnAltitude``, multicopter with RTL_CONE_ANG > 0): start
  from ``home + RTL_RETURN_ALT``; within NAV_ACC_RAD of home ``home + 2 d``; else within
  RTL_MIN_DIST the cone ``home + d / tan(RTL_CONE_ANG)`` if lower, and never below
  ``home + 2 NAV_ACC_RAD``; the result is capped at ``home + RTL_RETURN_ALT`` and raised to the
  current altitude (the vehicle never descends to return). RTL_CONE_ANG = 0: ``max(current,
  home + RTL_RETURN_ALT)``. STATUSTEXT ``RTL: start return at N m (M m above destination)``.
- Activation (``RtlDirect::getActivationState``): landed -> idle ("for safety reasons don't go
  into RTL if landed"); below the return altitude -> CLIMB; else -> RETURN.
- CLIMB straight up to the return altitude at MPC_Z_V_AUTO_UP; RETURN to home at the return
  altitude at MPC_XY_CRUISE. An item is reached within NAV_ACC_RAD horizontally and
  NAV_MC_ALT_RAD vertically (``MissionBlock::is_mission_item_reached_or_completed``); the
  position target stays on the item, so the vehicle keeps converging on it.
- After RETURN (``RtlDirect::_updateRtlState``): RTL_LAND_DELAY = 0 (the default) -> LAND at
  once; otherwise DESCEND to ``min(home + RTL_DESCEND_ALT, return altitude)`` at
  MPC_Z_V_AUTO_DN, HOLD there RTL_LAND_DELAY seconds (< 0: for ever, STATUSTEXT ``RTL:
  completed, loitering``), then LAND.
- LAND on home (``RTL: land at destination``): down at MPC_LAND_SPEED while holding home
  horizontally; the land detector and COM_DISARM_LAND disarm as in any mode.

ArduCopter (``ArduCopter/mode_rtl.cpp``)
----------------------------------------
- Entry needs home (``ModeRTL::init``: ``home_is_set``, checked when armed: ``Copter::set_mode``
  ignores the checks disarmed); home needs a location, so a vehicle without a global origin
  has none.
- Return altitude (``ModeRTL::compute_return_target``, alt above home, cm): ``max(RTL_ALT,
  max(RTL_ALT_MIN = 30, current + max(0, RTL_CLIMB_MIN)))``; with RTL_CONE_SLOPE >= 0.5 capped
  at ``max(distance * RTL_CONE_SLOPE, that minimum)``; never below the current altitude.
- INITIAL_CLIMB above the stopping point at WPNAV_SPEED_UP, RETURN_HOME at RTL_SPEED (0:
  WPNAV_SPEED); a leg is reached within WPNAV_RADIUS (``AC_WPNav``).
- LOITER_AT_HOME for RTL_LOIT_TIME ms, then RTL_ALT_FINAL > 0 -> FINAL_DESCENT to it at
  WPNAV_SPEED_DN and hover there; RTL_ALT_FINAL = 0 -> LAND at LAND_SPEED, disarming as soon as
  the land detector says landed (``ModeRTL::land_run``).
- Landed (``is_disarmed_or_landed``): ground handling, nothing moves.

Both report the land phase as MAV_LANDED_STATE_LANDING (PX4 EXTENDED_SYS_STATE from a LAND
setpoint; ArduCopter ``ModeRTL::is_landing``).

Rally points: the vehicle picks the destination (:func:`onfly.mavlink.geofence.px4_rally_destination`,
PX4 ``RTL::findRtlDestination`` with RTL_TYPE 0; :func:`~onfly.mavlink.geofence.ardu_rally_destination`,
``AP_Rally::calc_best_rally_or_home_location``). PX4 then flies this machine with the safe point in
place of home: the return altitude is above it and it lands there (``RTL: start return at ... above
destination``). ArduCopter returns to the rally point, with the target altitude at least the rally
altitude above home (``compute_return_target``: negative rally altitudes count as 0, the cone is
measured to the rally point), loiters and lands there.

Simplified: the landing descends at MPC_LAND_SPEED / LAND_SPEED all the way down, as the
vehicle's LAND mode does (PX4 descends faster above MPC_LAND_ALT1, ArduCopter above
LAND_ALT_LOW); yaw is held (PX4 turns toward the waypoint, MPC_YAW_MODE 0); PX4's RTL_TYPE is
fixed at its default 0 (no mission-landing or rally-only return types, no VTOL land approaches);
no terrain following; the return path is straight, not routed around a fence
(PX4's geofence avoidance planner, ArduPilot's fence avoidance are not modelled).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["ReturnSetpoint", "Px4Return", "ArduCopterReturn", "px4_return_altitude", "ardu_return_altitude_cm"]

RTL_ALT_MIN_CM = 30.0  # ArduCopter config.h RTL_ALT_MIN
RTL_MIN_CONE_SLOPE = 0.5  # ArduCopter config.h RTL_MIN_CONE_SLOPE


@dataclass(frozen=True)
class ReturnSetpoint:
    """What the vehicle tracks this step (scene ENU; None fields are unused).

    p : (3,) position target, m
    v : (3,) velocity feed-forward, m/s
    v_limit_mps : speed limit on the way to ``p``
    """

    p: np.ndarray | None = None
    v: np.ndarray | None = None
    v_limit_mps: float | None = None


def px4_return_altitude(p_m, home_m, params: dict) -> float:
    """PX4 ``RTL::computeReturnAltitude`` for a multicopter: scene z (m) to return at.

    p_m, home_m : (3,) current and home position, scene ENU, m
    params : the vehicle's PX4 parameters (RTL_RETURN_ALT, RTL_CONE_ANG, RTL_MIN_DIST, NAV_ACC_RAD)
    """
    p, home = np.asarray(p_m, float), np.asarray(home_m, float)
    max_return = home[2] + float(params["RTL_RETURN_ALT"])
    cone_deg = float(params["RTL_CONE_ANG"])
    if cone_deg <= 0:
        return max(p[2], max_return)
    dist = float(np.linalg.norm(p[:2] - home[:2]))
    acc_rad = float(params["NAV_ACC_RAD"])
    alt = max_return
    if dist <= acc_rad:
        alt = home[2] + 2.0 * dist
    else:
        if dist <= float(params["RTL_MIN_DIST"]):
            half = math.radians(min(max(cone_deg, 1.0), 89.0))
            alt = min(home[2] + dist / math.tan(half), alt)
        alt = max(alt, home[2] + 2.0 * acc_rad)
    return max(p[2], min(alt, max_return))  # math::constrain(alt, current, max_return)


def ardu_return_altitude_cm(p_m, home_m, params: dict, dest_m=None) -> float:
    """ArduCopter ``ModeRTL::compute_return_target`` (alt above home): return altitude, cm.

    p_m, home_m : (3,) current and home position, scene ENU, m
    params : the vehicle's ArduCopter parameters (RTL_ALT, RTL_CLIMB_MIN, RTL_CONE_SLOPE; cm)
    dest_m : (3,) the return target when it is a rally point (its z = home z + the rally
        altitude), or None for home. The target starts from the rally altitude (negative -> 0) and
        the cone is measured to the target.
    """
    p, home = np.asarray(p_m, float), np.asarray(home_m, float)
    dest = home if dest_m is None else np.asarray(dest_m, float)
    curr_cm = (p[2] - home[2]) * 100.0
    min_rtl_cm = max(RTL_ALT_MIN_CM, curr_cm + max(0.0, float(params["RTL_CLIMB_MIN"])))
    target_cm = max(max((dest[2] - home[2]) * 100.0, 0.0), float(params["RTL_ALT"]), min_rtl_cm)
    slope = float(params["RTL_CONE_SLOPE"])
    if slope >= RTL_MIN_CONE_SLOPE:
        dist_cm = float(np.linalg.norm(p[:2] - dest[:2])) * 100.0
        target_cm = min(target_cm, max(dist_cm * slope, min_rtl_cm))
    return max(target_cm, curr_cm)


class _Return:
    """Common state: phase, home, the phase's target and the event/STATUSTEXT callbacks."""

    def __init__(self, home_m, params: dict, event: Callable[[str, float], None], statustext: Callable[[str], None]) -> None:
        self.home = np.array(home_m, dtype=float)
        self.params = params
        self._event = event
        self._statustext = statustext
        self.phase = "idle"
        self._since_s = 0.0
        self._sp: ReturnSetpoint | None = None

    @property
    def landing(self) -> bool:
        """In the land phase (EXTENDED_SYS_STATE says LANDING while descending)."""
        return self.phase == "land"

    def _enter(self, phase: str, t_s: float, sp: ReturnSetpoint | None) -> None:
        self.phase, self._since_s, self._sp = phase, t_s, sp
        self._event(f"rtl: {phase}", t_s)  # on the physics clock the phases run on

    def _land_setpoint(self, p, speed_mps: float, v_xy_limit_mps: float, over=None) -> ReturnSetpoint:
        """Down at ``speed_mps`` over ``over`` (default home): a position target at the current
        height plus a descent feed-forward, re-made every step so only the horizontal part pulls."""
        over = self.home if over is None else over
        target = np.array([over[0], over[1], p[2]])
        return ReturnSetpoint(p=target, v=np.array([0.0, 0.0, -speed_mps]), v_limit_mps=max(v_xy_limit_mps, speed_mps))

    @staticmethod
    def _reached(p, target, horizontal_m: float, vertical_m: float) -> bool:
        p, target = np.asarray(p, float), np.asarray(target, float)
        return float(np.linalg.norm(p[:2] - target[:2])) <= horizontal_m and abs(p[2] - target[2]) <= vertical_m


class Px4Return(_Return):
    """PX4 Return mode (RTL_TYPE 0): climb, return, [descend, hold], land. See the module docstring.

    home_m : (3,) home, scene ENU, m; p_m : (3,) position at activation; landed : land detector
    amsl_offset_m : AMSL altitude of scene z = 0 (for the STATUSTEXT), or None
    """

    def __init__(self, home_m, p_m, landed: bool, t_s: float, params: dict, event, statustext, amsl_offset_m: float | None = None) -> None:
        super().__init__(home_m, params, event, statustext)
        p = np.asarray(p_m, float)
        self.return_z_m = px4_return_altitude(p, self.home, params)
        if landed:
            self._enter("idle", t_s, None)
            return
        off = 0.0 if amsl_offset_m is None else amsl_offset_m
        statustext(f"RTL: start return at {math.ceil(self.return_z_m + off)} m "
                   f"({math.ceil(self.return_z_m - self.home[2])} m above destination)")
        if p[2] < self.return_z_m:
            self._enter("climb", t_s, ReturnSetpoint(p=np.array([p[0], p[1], self.return_z_m]),
                                                     v_limit_mps=float(params["MPC_Z_V_AUTO_UP"])))
        else:
            self._enter_return(t_s)

    def _enter_return(self, t_s: float) -> None:
        self._enter("return", t_s, ReturnSetpoint(p=np.array([self.home[0], self.home[1], self.return_z_m]),
                                                  v_limit_mps=float(self.params["MPC_XY_CRUISE"])))

    @property
    def loiter_z_m(self) -> float:
        return min(self.home[2] + float(self.params["RTL_DESCEND_ALT"]), self.return_z_m)

    def step(self, t_s: float, p_m) -> ReturnSetpoint | None:
        """The target for this step (None: nothing to fly, e.g. idle on the ground)."""
        P = self.params
        p = np.asarray(p_m, float)
        acc_xy, acc_z = float(P["NAV_ACC_RAD"]), float(P["NAV_MC_ALT_RAD"])
        if self.phase == "climb" and self._reached(p, self._sp.p, math.inf, acc_z):
            self._enter_return(t_s)
        elif self.phase == "return" and self._reached(p, self._sp.p, acc_xy, acc_z):
            delay = float(P["RTL_LAND_DELAY"])
            if abs(delay) > 1e-6:
                target = np.array([self.home[0], self.home[1], self.loiter_z_m])
                self._enter("descend", t_s, ReturnSetpoint(p=target, v_limit_mps=float(P["MPC_Z_V_AUTO_DN"])))
            else:
                self._enter_land(t_s)
        elif self.phase == "descend" and self._reached(p, self._sp.p, acc_xy, acc_z):
            self._enter("hold", t_s, self._sp)
            if float(P["RTL_LAND_DELAY"]) < 0:
                self._statustext("RTL: completed, loitering")
        elif self.phase == "hold":
            delay = float(P["RTL_LAND_DELAY"])
            if delay >= 0 and t_s - self._since_s >= delay:
                self._enter_land(t_s)
        if self.phase == "land":
            return self._land_setpoint(p, float(P["MPC_LAND_SPEED"]), float(P["MPC_XY_CRUISE"]))
        return self._sp

    def _enter_land(self, t_s: float) -> None:
        self._enter("land", t_s, None)
        self._statustext("RTL: land at destination")

    def landed(self, t_s: float) -> None:
        """The land detector says landed: the mode is complete (``RTLState::IDLE``)."""
        if self.phase == "land":
            self._enter("idle", t_s, None)


class ArduCopterReturn(_Return):
    """ArduCopter RTL: climb, return, loiter at home, final descent or land. See the module docstring."""

    def __init__(self, home_m, p_m, landed: bool, t_s: float, params: dict, event, statustext, dest_m=None) -> None:
        super().__init__(home_m, params, event, statustext)
        p = np.asarray(p_m, float)
        # AP_Rally::calc_best_rally_or_home_location: a rally point replaces home as the target
        # (return, loiter, land); altitudes stay above home
        self.dest = self.home.copy() if dest_m is None else np.asarray(dest_m, float).copy()
        self.return_z_m = self.home[2] + ardu_return_altitude_cm(p, self.home, params, dest_m) / 100.0
        if landed:
            self._enter("idle", t_s, None)  # is_disarmed_or_landed: ground handling
            return
        self._enter("climb", t_s, ReturnSetpoint(p=np.array([p[0], p[1], self.return_z_m]),
                                                 v_limit_mps=float(params["WPNAV_SPEED_UP"]) / 100.0))

    def step(self, t_s: float, p_m) -> ReturnSetpoint | None:
        """The target for this step (None: nothing to fly)."""
        P = self.params
        p = np.asarray(p_m, float)
        radius = float(P["WPNAV_RADIUS"]) / 100.0

        def near(target) -> bool:
            return float(np.linalg.norm(p - target)) <= radius

        if self.phase == "climb" and near(self._sp.p):
            speed = float(P["RTL_SPEED"]) if float(P["RTL_SPEED"]) > 0 else float(P["WPNAV_SPEED"])
            self._enter("return", t_s, ReturnSetpoint(p=np.array([self.dest[0], self.dest[1], self.return_z_m]),
                                                      v_limit_mps=speed / 100.0))
        elif self.phase == "return" and near(self._sp.p):
            self._enter("loiter", t_s, self._sp)
        elif self.phase == "loiter" and (t_s - self._since_s) * 1000.0 >= float(P["RTL_LOIT_TIME"]):
            final_cm = float(P["RTL_ALT_FINAL"])
            if final_cm <= 0:
                self._enter("land", t_s, None)
            else:
                target = np.array([p[0], p[1], self.home[2] + final_cm / 100.0])  # holds its stopping point
                self._enter("final_descent", t_s, ReturnSetpoint(p=target, v_limit_mps=float(P["WPNAV_SPEED_DN"]) / 100.0))
        if self.phase == "land":
            return self._land_setpoint(p, float(P["LAND_SPEED"]) / 100.0, float(P["WPNAV_SPEED"]) / 100.0, self.dest)
        return self._sp

    def landed(self, t_s: float) -> None:
        """Landed in the land phase: stays in it (the vehicle disarms at once, ``land_run``)."""
