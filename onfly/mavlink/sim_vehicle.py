"""SimMavlinkVehicle: a MAVLink vehicle that answers a companion computer the way PX4 and
ArduCopter do, so the companion is tested against the rules it will meet in the air.

Every rule below names its source (PX4 documentation at docs.px4.io, PX4-Autopilot source
files, the ArduPilot wiki or ArduCopter source files). ``docs/flight.md`` lists them with the
two settings (GPS-less indoor, outdoor) and what is simplified.

Commands (COMMAND_LONG and COMMAND_INT alike; unused parameters may be NaN)
---------------------------------------------------------------------------
Both autopilots accept a command in either message and answer every command addressed to
them with one COMMAND_ACK (MAVLink command protocol; PX4 ``mavlink_receiver.cpp``
``handle_message_command_both``, ArduPilot ``GCS_MAVLINK::handle_command_long/int``). A NaN
in a parameter the command does not use is ignored, as MAVSDK sends it (PX4 and ArduPilot
treat NaN as "unchanged / default"). Unknown commands answer UNSUPPORTED.

A command addressed elsewhere (:meth:`SimMavlinkVehicle._command_for_me`): PX4
(``MavlinkReceiver::evaluate_target_ok``) takes only our system with our component or 0 (target
system 0 only for REQUEST_AUTOPILOT_CAPABILITIES / REQUEST_PROTOCOL_VERSION) and does not answer
the rest; ArduPilot (``MAVLink_routing::check_and_forward``) answers anything for system 0 or ours,
whatever the component, and never another system's.

- COMPONENT_ARM_DISARM: arming runs the pre-arm checks (below); disarming in the air is
  DENIED unless param2 = 21196 (PX4 Commander ``disarm`` with ``forced``; ArduCopter
  ``AP_Arming::Method::MAVLINK`` "disarm while flying" needs the magic too).
- DO_SET_MODE (and the legacy SET_MODE message, ACKed with command = 11 as ArduPilot does):
  PX4 main/sub modes in param2/param3, ArduCopter mode number in param2. A mode that needs a
  position estimate is refused without one (PX4: "Flying vehicles can't switch to this mode
  without valid local position", docs.px4.io flight_modes_mc/hold and land; ArduCopter
  ``Mode::requires_GPS``). PX4 OFFBOARD is refused unless a setpoint arrived within
  COM_OF_LOSS_T (PX4 ``Commander`` offboard-signal check: "recent setpoint", no pre-stream
  duration; the >2 Hz rule of docs.px4.io flight_modes/offboard is COM_OF_LOSS_T).
- NAV_TAKEOFF: PX4 switches to AUTO.TAKEOFF (``Commander.cpp``: a user-intended mode change,
  accepted armed or not, TEMPORARILY_REJECTED when the mode cannot run) and, armed, climbs at MPC_TKO_SPEED to param7 (AMSL,
  needs a global origin) or, when param7 is NaN, MIS_TAKEOFF_ALT above home, then holds in
  AUTO.LOITER (docs.px4.io flight_modes_mc/takeoff). ArduCopter accepts it only in GUIDED,
  armed and landed, param7 = altitude above home, climbing at WPNAV_SPEED_UP
  (``ArduCopter/GCS_Mavlink.cpp`` ``MAV_CMD_NAV_TAKEOFF`` -> ``do_user_takeoff``); a
  position target is ignored until the take-off completes (``mode_guided.cpp``
  ``takeoff_run``); while landed, targets are ignored (the guided run functions' ground
  handling when ``land_complete``).
- NAV_RETURN_TO_LAUNCH: a switch to the Return mode (below). PX4 Commander
  ``VEHICLE_CMD_NAV_RETURN_TO_LAUNCH``: "Returning to launch", or TEMPORARILY_REJECTED with
  "Switching to Return is currently not available" (``printRejectMode``) without a global
  position and home (docs.px4.io flight_modes_mc/return); ArduCopter ``GCS_Mavlink.cpp``:
  ``set_mode(RTL)`` or FAILED, armed without home "Mode change to RTL failed: init failed"
  (``ModeRTL::init`` ``home_is_set``; home is a location, so none without a global origin).
  MAVSDK's ``action.return_to_launch()`` sends PX4 a DO_SET_MODE to AUTO.RTL instead.
- NAV_LAND: PX4 AUTO.LAND, ArduCopter LAND (both: land where the vehicle is;
  docs.px4.io flight_modes_mc/land "The mode can be triggered using the MAV_CMD_NAV_LAND";
  ArduCopter ``GCS_Mavlink.cpp`` sets LAND).
- DO_REPOSITION (COMMAND_INT, x/y = lat/lon degE7, z = metres in the message's frame): needs a
  global origin (FAILED without). PX4 switches to AUTO.LOITER if param2 has
  MAV_DO_REPOSITION_FLAGS_CHANGE_MODE and flies there (PX4 ``Commander`` +
  ``navigator_main.cpp`` reposition, param4 the yaw in radians); ArduCopter flies there in GUIDED (switching to it with
  the flag, else FAILED outside GUIDED; ``GCS_Mavlink.cpp`` ``handle_command_int_do_reposition``).
- DO_CHANGE_SPEED (MAVSDK ``set_current_speed``, MAVProxy ``setspeed``): PX4 always ACCEPTED
  (``navigator_main.cpp``): param2 > 0 sets the navigator's cruising speed, else resets it; the
  next reposition made in Hold without its own speed flies at it (entering Hold resets to the
  default MPC_XY_CRUISE; every goto speed is capped at MPC_XY_VEL_MAX, ``FlightTaskAuto``).
  ArduCopter (``GCS_MAVLINK_Copter::handle_MAV_CMD_DO_CHANGE_SPEED``): param2 <= 0 or an unknown
  speed type DENIED, a mode without ``set_speed_NE_ms`` FAILED; GUIDED limits position targets
  until the guided submode changes (``ModeGuided::set_speed_NE_ms``, ``pva_control_start``), RTL
  its return leg (``ModeRTL::set_speed_NE_ms``).
- DO_SET_HOME: param1 1 (PX4: > 0.5; ArduPilot also lat = lon = 0) sets home here, else at the
  command's lat/lon/alt (PX4 ``Commander`` VEHICLE_CMD_DO_SET_HOME: AMSL, non-finite DENIED, no
  global reference TEMPORARILY_REJECTED; ArduPilot ``handle_command_do_set_home``: the command's
  frame, COMMAND_LONG absolute, bad frame DENIED, ``set_home`` refusals FAILED). That home is kept at
  arming and read by Return, the geofence and GLOBAL_POSITION_INT.
- CONDITION_YAW (MAVProxy ``setyaw``): ArduCopter ACCEPTED for a heading in [0, 360] and param4
  0/1 (else FAILED), turning in GUIDED at min(param2, ATC_SLEW_YAW) until the next target
  (``handle_MAV_CMD_CONDITION_YAW``, ``AutoYaw::set_fixed_yaw_rad``); PX4 has no handler outside
  missions: UNSUPPORTED (``Commander::handle_command`` default).
- PREFLIGHT_REBOOT_SHUTDOWN (MAVSDK ``reboot``, MAVProxy ``reboot``): armed, PX4 DENIED
  (``shutdown_if_allowed``) and ArduPilot FAILED ("refuse reboot when armed"); disarmed, param1
  = 1 ACCEPTED, then silence for ``reboot_time_s`` and a fresh boot (parameters and the mission
  kept). PX4 param1 0 ACCEPTED (nothing), others DENIED; ArduPilot param1 other than 1/3
  UNSUPPORTED (3: held in the bootloader, silent).
- REQUEST_MESSAGE / REQUEST_AUTOPILOT_CAPABILITIES / GET_HOME_POSITION: the message is sent
  once after the ACK (DENIED if it cannot be produced, e.g. HOME_POSITION before home is set).
- SET_MESSAGE_INTERVAL: any stream below; interval -1 stops it, 0 restores the default.
- MISSION_START, DO_SET_MISSION_CURRENT and the whole mission protocol (MISSION_* messages,
  PX4 AUTO.MISSION, ArduCopter AUTO): :mod:`onfly.mavlink.mission`, with its sources. PX4
  MISSION_START switches to AUTO.MISSION and arms (``Commander.cpp``), DENIED without a valid
  mission; AUTO.MISSION / AUTO need a mission (PX4: and a global origin), ArduCopter refuses
  AUTO armed on the ground unless the mission starts with a take-off.

Parameters (PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET -> PARAM_VALUE)
--------------------------------------------------------------------------------
The few parameters a companion reads or sets, with the autopilots' defaults
(:data:`PX4_PARAMS`, :data:`ARDUPILOT_PARAMS`). PX4 encodes integer parameters bytewise in
the float field, ArduPilot casts them (AUTOPILOT_VERSION's MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_*
bit says which; mavlink.io/en/services/parameter.html). The rules read them live:
COM_OF_LOSS_T, COM_OBL_RC_ACT, COM_DISARM_PRFLT, COM_DISARM_LAND, MIS_TAKEOFF_ALT,
MPC_TKO_SPEED, MPC_LAND_SPEED and the Return mode's RTL_RETURN_ALT, RTL_DESCEND_ALT,
RTL_LAND_DELAY, RTL_MIN_DIST, RTL_CONE_ANG, MPC_XY_CRUISE, MPC_XY_VEL_MAX, MPC_Z_V_AUTO_UP/DN, NAV_ACC_RAD,
NAV_MC_ALT_RAD (PX4; a multicopter's ROMFS ``rc.mc_defaults`` values: RTL_RETURN_ALT 30,
RTL_DESCEND_ALT 10, NAV_ACC_RAD 2); GUID_TIMEOUT, DISARM_DELAY, LAND_SPEED, WPNAV_SPEED_UP and
RTL_ALT, RTL_CLIMB_MIN, RTL_SPEED, RTL_LOIT_TIME, RTL_ALT_FINAL, RTL_CONE_SLOPE, WPNAV_SPEED,
WPNAV_SPEED_DN, WPNAV_RADIUS, ATC_SLEW_YAW (ArduCopter). Geofence and rally: GF_ACTION, GF_MAX_HOR_DIST,
GF_MAX_VER_DIST, GF_SOURCE (PX4 ``geofence_params.c``); FENCE_ENABLE, FENCE_TYPE, FENCE_ACTION,
FENCE_ALT_MAX, FENCE_RADIUS, FENCE_MARGIN (``AC_Fence.cpp``, Copter defaults), RALLY_LIMIT_KM,
RALLY_INCL_HOME (``AP_Rally.cpp``).

Geofence and rally points
-------------------------
Uploaded with mission_type FENCE / RALLY (:mod:`onfly.mavlink.mission`), enforced by
:class:`~onfly.mavlink.geofence.FenceMonitor` every physics step, with a global position only
(outdoors). PX4: a breach (outside the zones, or beyond GF_MAX_HOR_DIST / GF_MAX_VER_DIST from
home) refuses arming and, armed, takes GF_ACTION (default 2 Hold; 3 Return, 4 Terminate, 5 Land).
ArduCopter with FENCE_ENABLE 1: pre-arm "Vehicle breaching ..." / "Fence requires position", and a
new breach armed disarms on the ground or takes FENCE_ACTION (default 1 RTL, else Land). The Return
mode flies to the closest rally point where the autopilot's rule picks one over home.

Return mode (PX4 AUTO.RTL, ArduCopter RTL)
------------------------------------------
Flown by :mod:`onfly.mavlink.rtl` (each rule cited there), entered by DO_SET_MODE, SET_MODE,
NAV_RETURN_TO_LAUNCH or PX4's COM_OBL_RC_ACT = 3, stopped by any mode change. PX4 (``rtl.cpp``,
``rtl_direct.cpp``): climb to the return altitude (RTL_RETURN_ALT above home, lowered near home
by the RTL_CONE_ANG cone, never a descent) at MPC_Z_V_AUTO_UP, fly home at MPC_XY_CRUISE, then
land at once (RTL_LAND_DELAY 0) or descend to RTL_DESCEND_ALT, wait RTL_LAND_DELAY (-1: for
ever) and land; the land detector and COM_DISARM_LAND disarm. ArduCopter (``mode_rtl.cpp``):
climb to max(RTL_ALT, current + RTL_CLIMB_MIN) (cm; capped by the RTL_CONE_SLOPE cone) at
WPNAV_SPEED_UP, return at RTL_SPEED (0: WPNAV_SPEED), loiter RTL_LOIT_TIME, then land (disarming
at touchdown) or, RTL_ALT_FINAL > 0, descend to it and hover. Landed when entered: nothing
moves. EXTENDED_SYS_STATE says LANDING in the land phase. The climb ignores what is above: in
the embedded world a ceiling below the return altitude is a crash.

Arming and disarming
--------------------
- Pre-arm: a position estimate (the vehicle's :meth:`SimMavlinkVehicle.set_position_valid`;
  PX4 ``HealthAndArmingChecks`` estimator checks; ArduCopter "PreArm: Need Position
  Estimate") and a mode that allows arming: PX4 refuses in AUTO.LAND and AUTO.RTL ("Mode
  prevents arming", docs.px4.io flight_modes_mc/land); OFFBOARD needs a recent setpoint;
  ArduCopter refuses in LAND, RTL, BRAKE and AUTO (``Mode::allows_arming``). A refusal is
  FAILED (PX4 ``Commander::arm``) / FAILED (ArduPilot) with a STATUSTEXT saying why.
- Pre-flight auto-disarm: armed on the ground without taking off for COM_DISARM_PRFLT (10 s,
  PX4 ``Commander``) or DISARM_DELAY (10 s, ArduCopter ``motors.cpp`` ``auto_disarm_check``).
- Land detector, in every mode: on the ground and still for LNDMC_TRIG_TIME (1 s, PX4
  ``land_detector``; ArduCopter ``land_detector.cpp`` LAND_DETECTOR_TRIGGER_SEC = 1 s) means
  landed; after a flight PX4 then disarms after COM_DISARM_LAND (2 s), ArduCopter at once in
  LAND (``mode_land.cpp``) and after DISARM_DELAY in other modes.

Manual control (PX4)
--------------------
MANUAL_CONTROL from a ground station (MAVSDK ManualControl, QGroundControl's virtual joystick) is
PX4's MAVLink manual control input (``handle_message_manual_control``; COM_RC_IN_MODE 0 and 4 ignore
it). While it lasts (COM_RC_LOSS_T) Position / Altitude / Stabilized / Manual are available;
Position mode flies the sticks as velocities (MPC_VEL_MANUAL, MPC_Z_VEL_MAX_UP/DN, MPC_MAN_Y_MAX,
``expo_deadzone``) and holds at centre; its loss while armed takes NAV_RCL_ACT (``failsafe.cpp``,
COM_RCL_EXCEPT). ArduCopter takes MANUAL_CONTROL from SYSID_MYGCS as RC overrides
(``GCS_MAVLINK::handle_manual_control``, ``handle_manual_control_axes``; RC_OVERRIDE_TIME);
LOITER and ALT_HOLD fly them (THR_DZ, PILOT_SPEED_UP/DN, PILOT_Y_RATE, AC_Loiter's LOIT_SPEED drag
and braking) and GUIDED ignores them; 1 s without one is the radio failsafe (``read_radio``,
FS_THR_ENABLE, FS_OPTIONS).

Companion loss
--------------
- PX4 OFFBOARD: no setpoint for COM_OF_LOSS_T (1 s) -> the COM_OBL_RC_ACT action (0 Position,
  1 Altitude, 2 Manual, 3 Return, 4 Land, 5 Hold, 6 Terminate, 7 Disarm; PX4 parameter
  reference). Position/Altitude/Manual need manual control (``rc_connected`` or recent
  MANUAL_CONTROL), Position and
  Hold a position estimate, Return a global origin and home (and then flies the Return mode
  home); an action that cannot run
  falls back to Hold, then to Land, then to Descend (PX4 ``failsafe.cpp`` mode fallback).
- ArduCopter GUIDED: GUID_TIMEOUT (3 s) applies only to velocity and acceleration targets: a
  velocity (or acceleration) target not refreshed stops the vehicle (velocity zero), a
  position+velocity+acceleration target keeps its position with the feed-forwards zeroed,
  and a position-only target is held for ever (``mode_guided.cpp``
  ``velaccel_control_run`` / ``posvelaccel_control_run`` vs ``pos_control_run``).

Setpoints (SET_POSITION_TARGET_LOCAL_NED, SET_POSITION_TARGET_GLOBAL_INT)
------------------------------------------------------------------------
In MAV_FRAME_LOCAL_NED (the estimator's frame) PX4 reads type_mask per axis: an ignored
component is NaN and the controller uses what is finite on each axis (``mavlink_receiver.cpp``
``handle_message_set_position_target_local_ned``; e.g. x/y position with z velocity).
ArduCopter uses a whole vector or none: any set ignore bit of a vector ignores all of it
(``GCS_MAVLink_Copter.cpp`` ``handle_message_set_position_target_local_ned``: ``pos_ignore =
type_mask & POS_IGNORE``). Non-finite used fields drop the message. ArduCopter takes targets in
GUIDED only (ignored in any other mode).

The other frames of SET_POSITION_TARGET_LOCAL_NED. The body frames' vectors are in the heading
frame (x forward, y right, z down) and turned by the vehicle's heading in the estimator frame
(:meth:`SimMavlinkVehicle._local_ned_from_heading_frame`), so a body-frame target means the same
in the scene whatever the estimator frame's rotation:

- PX4 (``handle_message_set_position_target_local_ned``): LOCAL_NED and BODY_NED only. In
  BODY_NED the position is never used (NaN whatever the mask), velocity and acceleration are
  each used whole or not at all (any of their three ignore bits drops the vector), the
  velocity's x/y are rotated by the heading (``Eulerf(R)(2)``) and its z kept, the acceleration
  by the whole attitude (``R * acceleration_body_sp``); the yaw stays absolute. Any other frame
  (LOCAL_OFFSET_NED, BODY_OFFSET_NED, BODY_FRD, ...) is dropped with "SET_POSITION_TARGET_LOCAL_NED
  coordinate frame N unsupported"; a used acceleration with the force bit with "... force not
  supported"; a message with nothing used (a BODY_NED position alone) with "... invalid". A
  dropped message is no offboard signal (OFFBOARD refused, offboard lost in it).
- ArduCopter (``handle_message_set_position_target_local_ned``): LOCAL_NED, LOCAL_OFFSET_NED,
  BODY_NED, BODY_OFFSET_NED; any other frame (BODY_FRD too) stops: ``ModeGuided::init(true)``,
  a zero-velocity target (brake and hover), as a force setpoint, an insane velocity
  (``sane_vel_or_acc_vector``), position + acceleration without velocity or nothing used do. In
  the body frames the x/y of position, velocity and acceleration are rotated by the heading
  (``AP_AHRS::body_to_earth2D``); in every frame but LOCAL_NED the position is an offset from the
  current position (BODY_NED too; ``get_relative_position_NED_origin``, without a position
  estimate: stop); velocities are never offset. The yaw is relative in the body frames. Then
  pos + vel (+ acc) is a position/velocity/acceleration target, vel (+ acc) a velocity one, acc
  alone an acceleration one, pos alone a position one (``set_pos_vel_accel_NED_m``,
  ``set_vel_accel_NED_m``, ``set_accel_NED_mss``, ``set_pos_NED_m``).

The yaw rate (type_mask YAW_RATE_IGNORE clear; rad/s NED, clockwise positive; both messages):

- PX4: the offboard yawspeed. With the yaw ignored the vehicle turns at it
  (``PositionControl::update`` keeps the yaw where it is and feeds the yawspeed forward), with a
  yaw it is the feed-forward added to the heading correction (``AttitudeControl::update``);
  within the model's yaw-rate limit. POSITION_TARGET_LOCAL_NED reports it.
- ArduCopter (``ModeGuided::set_yaw_state_rad`` and ``AutoYaw``, ``autoyaw.cpp``): a rate alone is
  RATE, a turn at the rate; yaw and rate are ANGLE_RATE, a heading target starting at the yaw
  and advancing at the rate (``AutoYaw::yaw_rad``); a yaw alone is that heading; a relative yaw
  (the body frames) is FIXED, the offset added to AutoYaw's angle (``set_fixed_yaw_rad``) and
  slewed at ATC_SLEW_YAW, the rate unused. RATE's turn is capped at ATC_SLEW_YAW
  (``AC_AttitudeControl::input_thrust_vector_rate_heading_rads``); ANGLE_RATE's heading target
  advances at the rate as sent (only its feed-forward is capped there,
  ``input_thrust_vector_heading_rad``, the heading correction making up the rest). GUID_TIMEOUT without a new target turns RATE and ANGLE_RATE into HOLD for every target kind,
  a position target too (the run functions' "stop rotating").

SET_POSITION_TARGET_GLOBAL_INT (lat/lon degE7, alt m, NED velocity / acceleration, NED yaw rad
and yaw rate rad/s as above; converted with the same :meth:`SimMavlinkVehicle._scene_from_global`
as DO_REPOSITION and mission items):

- PX4 (``mavlink_receiver.cpp`` ``handle_message_set_position_target_global_int``): position
  all or nothing, velocity / acceleration per axis; a used position needs a global position
  estimate (indoors the message is dropped whole: no offboard signal, OFFBOARD refused) and one
  of the INT frames: GLOBAL_INT AMSL, GLOBAL_RELATIVE_ALT_INT (needs home; local z =
  (home.alt - alt) - ref_alt as the receiver writes it, the height above home while home is at
  the EKF origin's altitude), GLOBAL_TERRAIN_ALT_INT (needs a terrain altitude: no distance
  sensor here, dropped); other frames dropped with "SET_POSITION_TARGET_GLOBAL_INT invalid
  coordinate frame N", a force setpoint with "... force not supported". Accepted ones are
  offboard setpoints exactly as LOCAL_NED ones (COM_OF_LOSS_T, arming, entering OFFBOARD).
- ArduCopter (``GCS_MAVLink_Copter.cpp`` ``handle_message_set_position_target_global_int``,
  ``mode_guided.cpp``): GUIDED only; whole vectors; GLOBAL(_INT) AMSL, GLOBAL_RELATIVE_ALT(_INT)
  above home, GLOBAL_TERRAIN_ALT(_INT) above terrain (no terrain data here: stop). Invalid input
  (force, lat/lon out of range, unknown frame, insane velocity, pos+acc without velocity,
  nothing used, pos+vel without an EKF origin or above terrain) calls ``ModeGuided::init(true)``:
  a zero-velocity target, brake and hover. A position-only target without a vector from the EKF
  origin (indoors) is ignored and the last target kept (``set_destination`` returns first).

Frames and telemetry
--------------------
LOCAL_POSITION_NED is relative to the estimator's origin (EKF origin), which is not the
scene's origin: by default the vehicle's position at boot, rotated by ``estimator_yaw_rad``
(a vision-only estimator's heading is arbitrary), as PX4/EKF2 and ArduPilot/EKF3 set their
origin where the estimate starts. With a global origin (outdoor), GLOBAL_POSITION_INT and
HOME_POSITION carry lat/lon (PX4 ``lib/geo`` azimuthal-equidistant projection, earth radius
6371 km). Streams at the autopilot's default rates until SET_MESSAGE_INTERVAL
(:data:`DEFAULT_RATES_HZ`; PX4: ``mavlink_main.cpp`` onboard mode; ArduPilot: the ``STREAM_*_msgs``
groups at this simulation's companion-port SRn_* rates, ArduCopter's compiled defaults being 0):
HEARTBEAT, SYS_STATUS (sensor and pre-arm health, battery), EXTENDED_SYS_STATE (landed state),
LOCAL_POSITION_NED, ATTITUDE_QUATERNION and ATTITUDE (PX4) / ATTITUDE (ArduPilot),
GLOBAL_POSITION_INT, GPS_RAW_INT and HOME_POSITION (with a global origin; HOME_POSITION also
without, lat/lon 0, once home is set at arming), SYSTEM_TIME, BATTERY_STATUS, MISSION_CURRENT
(ArduPilot's EXT_STAT stream; PX4 sends it at 1 Hz from its mission manager, not as a stream);
MISSION_ITEM_REACHED and STATUSTEXT on events (a text over 50 characters in chunks of one id:
PX4 ``streams/STATUSTEXT.hpp``, ArduPilot ``GCS::send_textv``); AUTOPILOT_VERSION on request. GPS_RAW_INT (outdoor only): PX4's onboard mode forwards
every fix (``mavlink_main.cpp`` ``unlimited_rate``; the model makes 5 a second), ArduPilot sends
it in the EXT_STAT group (``STREAM_EXTENDED_STATUS_msgs``, 2 Hz); 3D fix, 12 satellites, degE7,
mm AMSL, eph/epv = HDOP/VDOP x 100 (MAVLink), h_acc/v_acc mm, vel cm/s, cog cdeg.

What a client's telemetry plugin waits for, each from the model's state (``_altitude``,
``_vfr_hud``, ``_odometry``, ``_highres_imu``, ``_raw_imu``, ``_position_target_local_ned`` cite
their sources): PX4 ALTITUDE 10 Hz, VFR_HUD 10, ODOMETRY 30 (EKF2: pose and velocity in
MAV_FRAME_LOCAL_NED, quality 0, covariances NaN), HIGHRES_IMU 50, POSITION_TARGET_LOCAL_NED 10,
and its TIMESYNC (10) and PING (1) requests; ArduCopter VFR_HUD in EXTRA2 (4 Hz), RAW_IMU in
RAW_SENS (2 Hz), POSITION_TARGET_LOCAL_NED on request in GUIDED. The accelerometer measures the
model's acceleration over the last physics step minus gravity (FRD: -9.81 on z at rest), the
gyro the yaw rate; the baro is an ISA standard day at the AMSL altitude, so only outdoors (indoors
the model knows no altitude above sea level: ALTITUDE's amsl and monotonic are NaN); no
magnetometer field. VFR_HUD's throttle is the hover throttle (MPC_THR_HOVER / MOT_THST_HOVER) times
the thrust the model needs. ESTIMATOR_STATUS and VIBRATION are not sent: the model has no
estimator innovations or vibration to report. TIMESYNC requests (tc1 = 0) are answered with
tc1 = time since boot in ns and ts1 echoed (both autopilots); PING requests only by PX4.

Dynamics: :class:`PointMassModel` (default) or the embedded world's
:class:`~onfly.mavlink.sim_world.WorldVehicleModel` (``model=``, exact collisions; a crash
disarms). State is ENU in the scene frame internally; NED/FRD and the estimator frame appear
only at the MAVLink boundary.

Fault injection for tests: :meth:`set_link_cut`, :meth:`set_odometry_frozen`,
:meth:`set_position_valid`, :meth:`pilot_takeover`.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from onfly.mavlink import frames, rtl
from onfly.mavlink.autopilot import ARDUCOPTER_MODE, PX4_AUTO_SUB, PX4_MAIN, px4_custom_mode, px4_main_mode
from onfly.mavlink.link import Link, LinkError, mavlink2
from onfly.mavlink.geofence import FenceMonitor, ardu_rally_destination, px4_rally_destination
from onfly.mavlink.mission import MissionManager
from planning.frames import wrap_angle

__all__ = [
    "SimVehicleConfig",
    "PointMassModel",
    "SimMavlinkVehicle",
    "PX4_PARAMS",
    "ARDUPILOT_PARAMS",
    "DEFAULT_RATES_HZ",
    "PROFILES",
    "EARTH_RADIUS_M",
]

_FORCE_DISARM_MAGIC = 21196
EARTH_RADIUS_M = frames.EARTH_RADIUS_M  # re-exported: clients' tests convert metres to degrees with it

log = logging.getLogger(__name__)
_M = mavlink2

#: type_mask ignore bits per setpoint row (position, velocity, acceleration; NED axes)
_AXIS_BITS = (
    (_M.POSITION_TARGET_TYPEMASK_X_IGNORE, _M.POSITION_TARGET_TYPEMASK_Y_IGNORE, _M.POSITION_TARGET_TYPEMASK_Z_IGNORE),
    (_M.POSITION_TARGET_TYPEMASK_VX_IGNORE, _M.POSITION_TARGET_TYPEMASK_VY_IGNORE, _M.POSITION_TARGET_TYPEMASK_VZ_IGNORE),
    (_M.POSITION_TARGET_TYPEMASK_AX_IGNORE, _M.POSITION_TARGET_TYPEMASK_AY_IGNORE, _M.POSITION_TARGET_TYPEMASK_AZ_IGNORE),
)
_POS_BITS = _AXIS_BITS[0][0] | _AXIS_BITS[0][1] | _AXIS_BITS[0][2]

def _finite_or_unused(*values: float | None) -> bool:
    """True when every used field (not None) is finite: a setpoint's yaw and yaw rate."""
    return all(math.isfinite(v) for v in values if v is not None)


#: SET_POSITION_TARGET_LOCAL_NED frames whose vectors are in the vehicle's heading frame
#: (x forward, y right, z down)
_BODY_FRAMES = (_M.MAV_FRAME_BODY_NED, _M.MAV_FRAME_BODY_OFFSET_NED)
#: the SET_POSITION_TARGET_LOCAL_NED frames ArduCopter takes (GCS_MAVLink_Copter.cpp
#: ``handle_message_set_position_target_local_ned``); PX4 takes LOCAL_NED and BODY_NED only
_ARDU_LOCAL_FRAMES = (_M.MAV_FRAME_LOCAL_NED, _M.MAV_FRAME_LOCAL_OFFSET_NED, *_BODY_FRAMES)

#: ArduPilot ``mavlink_coordinate_frame_to_location_alt_frame`` (GCS_Common.cpp): the global
#: frames and the Location altitude frame each means; any other frame is unknown
_ARDU_ALT_FRAME = {
    _M.MAV_FRAME_GLOBAL: "absolute", _M.MAV_FRAME_GLOBAL_INT: "absolute",
    _M.MAV_FRAME_GLOBAL_RELATIVE_ALT: "above_home", _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: "above_home",
    _M.MAV_FRAME_GLOBAL_TERRAIN_ALT: "terrain", _M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: "terrain",
}


def _ardu_vectors_used(mask: int) -> tuple[bool, bool, bool]:
    """ArduCopter's reading of a SET_POSITION_TARGET type_mask: position, velocity and
    acceleration are each used whole or not at all, and any one set ignore bit of a vector
    ignores all of it (``bool pos_ignore = type_mask & MAVLINK_SET_POS_TYPE_MASK_POS_IGNORE``
    with the mask covering its three bits; ``GCS_MAVLINK_Copter``, ArduCopter ``defines.h``)."""
    return tuple(not mask & (row[0] | row[1] | row[2]) for row in _AXIS_BITS)


_R32 = _M.MAV_PARAM_TYPE_REAL32
_I32 = _M.MAV_PARAM_TYPE_INT32
_I16 = _M.MAV_PARAM_TYPE_INT16
_I8 = _M.MAV_PARAM_TYPE_INT8

#: PX4 parameters the vehicle serves: name -> (default, MAV_PARAM_TYPE). Defaults from the
#: PX4 parameter reference (docs.px4.io advanced_config/parameter_reference).
PX4_PARAMS = {
    "COM_OF_LOSS_T": (1.0, _R32),
    "COM_OBL_RC_ACT": (0, _I32),
    "COM_DISARM_PRFLT": (10.0, _R32),
    "COM_DISARM_LAND": (2.0, _R32),
    "LNDMC_TRIG_TIME": (1.0, _R32),
    "MIS_TAKEOFF_ALT": (2.5, _R32),
    "MPC_TKO_SPEED": (1.5, _R32),
    "MPC_LAND_SPEED": (0.7, _R32),
    # hover thrust (mc_pos_control multicopter_position_control_params.c): VFR_HUD's throttle
    "MPC_THR_HOVER": (0.5, _R32),
    # Return mode (navigator rtl_params.yaml) and the speeds and acceptance radii it flies with
    # (mc_pos_control multicopter_autonomous_params.c, navigator_params.c); a multicopter boots
    # with ROMFS rc.mc_defaults over them: RTL_RETURN_ALT 30 (not 60), RTL_DESCEND_ALT 10 (not
    # 30), NAV_ACC_RAD 2 (not 10)
    "RTL_RETURN_ALT": (30.0, _R32),
    "RTL_DESCEND_ALT": (10.0, _R32),
    "RTL_LAND_DELAY": (0.0, _R32),
    "RTL_MIN_DIST": (10.0, _R32),
    "RTL_CONE_ANG": (45, _I32),
    "MPC_XY_CRUISE": (5.0, _R32),
    # the cap on every horizontal speed the position controller is given (FlightTaskAuto: the
    # cruise speed of a goto is min(cruise, MPC_XY_VEL_MAX); multicopter_position_control_params.c)
    "MPC_XY_VEL_MAX": (12.0, _R32),
    "MPC_Z_V_AUTO_UP": (3.0, _R32),
    "MPC_Z_V_AUTO_DN": (1.5, _R32),
    "NAV_ACC_RAD": (2.0, _R32),
    "NAV_MC_ALT_RAD": (0.8, _R32),
    # manual control (a ground station's MANUAL_CONTROL is the stick input; Commander
    # commander_params.c, navigator_params.c, mc_pos_control multicopter_*_params.c):
    # COM_RC_IN_MODE 0 RC only, 1 MAVLink only, 2 RC or MAVLink with fallback, 3 RC or MAVLink keep
    # first, 4 disabled; COM_RC_LOSS_T s; NAV_RCL_ACT 1 Hold, 2 Return, 3 Land, 5 Terminate, 6 Disarm;
    # COM_RCL_EXCEPT bits 0 Mission, 1 Hold, 2 Offboard; Position-mode stick scaling
    "COM_RC_IN_MODE": (3, _I32),
    "COM_RC_LOSS_T": (0.5, _R32),
    "NAV_RCL_ACT": (2, _I32),
    "COM_RCL_EXCEPT": (0, _I32),
    "MPC_VEL_MANUAL": (10.0, _R32),
    "MPC_Z_VEL_MAX_UP": (3.0, _R32),
    "MPC_Z_VEL_MAX_DN": (1.5, _R32),
    "MPC_MAN_Y_MAX": (150.0, _R32),
    "MPC_HOLD_DZ": (0.1, _R32),
    # FlightTaskManualAltitude::_updateAltitudeLock: centred throttle brakes, and the altitude is
    # locked once |vz| is below this (m/s; multicopter_position_control_params.c default 0.6)
    "MPC_HOLD_MAX_Z": (0.6, _R32),
    "MPC_XY_MAN_EXPO": (0.6, _R32),
    "MPC_Z_MAN_EXPO": (0.6, _R32),
    "MPC_YAW_EXPO": (0.6, _R32),
    # geofence (navigator geofence_params.c / geofence_params.yaml): 0 None, 1 Warning, 2 Hold,
    # 3 Return, 4 Terminate, 5 Land; distances from home in m, 0 = off; source 0 GPOS, 1 GPS
    "GF_ACTION": (2, _I32),
    "GF_MAX_HOR_DIST": (0.0, _R32),
    "GF_MAX_VER_DIST": (0.0, _R32),
    "GF_SOURCE": (0, _I32),
}
#: ArduCopter parameters: name -> (default, MAV_PARAM_TYPE); units as ArduPilot's (cm/s, s).
ARDUPILOT_PARAMS = {
    "GUID_TIMEOUT": (3.0, _R32),
    "DISARM_DELAY": (10, _I16),
    "LAND_SPEED": (50, _I16),
    "WPNAV_SPEED_UP": (250.0, _R32),
    # hover throttle (AP_MotorsMulticopter.cpp): VFR_HUD's throttle
    "MOT_THST_HOVER": (0.35, _R32),
    "FS_GCS_ENABLE": (0, _I8),
    # RTL (ArduCopter Parameters.cpp, config.h) and the waypoint controller it flies with (AC_WPNav.cpp)
    "RTL_ALT": (1500, _I32),
    "RTL_CLIMB_MIN": (0, _I16),
    "RTL_SPEED": (0, _I16),
    "RTL_LOIT_TIME": (5000, _I32),
    "RTL_ALT_FINAL": (0, _I16),
    "RTL_CONE_SLOPE": (3.0, _R32),
    "WPNAV_SPEED": (1000.0, _R32),
    "WPNAV_SPEED_DN": (150.0, _R32),
    "WPNAV_RADIUS": (200.0, _R32),
    # the attitude controller's yaw slew limit (cdeg/s, AC_AttitudeControl.cpp): CONDITION_YAW's rate cap
    "ATC_SLEW_YAW": (6000.0, _R32),
    # fence (libraries/AC_Fence/AC_Fence.cpp; Copter defaults): FENCE_ENABLE 0, FENCE_TYPE 7 (bit 0
    # max altitude, 1 circle around home, 2 polygons / uploaded zones), FENCE_ACTION 1 (0 report,
    # 1 RTL or Land, 2 Land, 3 SmartRTL or RTL or Land, 4 Brake or Land, 5 SmartRTL or Land), m
    "FENCE_ENABLE": (0, _I8),
    "FENCE_TYPE": (7, _I8),
    "FENCE_ACTION": (1, _I8),
    "FENCE_ALT_MAX": (100.0, _R32),
    "FENCE_RADIUS": (300.0, _R32),
    "FENCE_MARGIN": (2.0, _R32),
    # rally points (libraries/AP_Rally/AP_Rally.cpp, ArduCopter defaults)
    "RALLY_LIMIT_KM": (0.3, _R32),
    "RALLY_INCL_HOME": (1, _I8),
    # a ground station's MANUAL_CONTROL as RC overrides (GCS_Common.cpp handle_manual_control: only
    # from SYSID_MYGCS, newer MAV_GCS_SYSID; RC_Channel.cpp: an override lapses RC_OVERRIDE_TIME s
    # after the last one) and the radio failsafe (FS_THR_ENABLE 0 off, 1 RTL, 2 RTL (continue in
    # AUTO), 3 Land, 4/5 SmartRTL (no SmartRTL here: RTL), FS_OPTIONS bit 0 continue in AUTO, 1
    # continue in GUIDED, 2 continue landing, 4 GCS failsafe continues under pilot control)
    "SYSID_MYGCS": (255, _I16),
    "RC_OVERRIDE_TIME": (3.0, _R32),
    "FS_THR_ENABLE": (1, _I8),
    "FS_THR_VALUE": (975, _I16),
    "FS_OPTIONS": (16, _I32),
    # pilot input (Parameters.cpp; cm/s, cdeg, deg/s): THR_DZ around mid throttle, climb PILOT_SPEED_UP,
    # descent PILOT_SPEED_DN (0: PILOT_SPEED_UP), yaw rate PILOT_Y_RATE with PILOT_Y_EXPO
    "THR_DZ": (100, _I16),
    "PILOT_SPEED_UP": (250, _I16),
    "PILOT_SPEED_DN": (0, _I16),
    "PILOT_Y_RATE": (202.5, _R32),
    "PILOT_Y_EXPO": (0.0, _R32),
    "ANGLE_MAX": (3000, _I16),
    # Loiter (AC_Loiter.cpp): max speed cm/s, lean angle deg (0: 2/3 of ANGLE_MAX), braking
    "LOIT_SPEED": (1250.0, _R32),
    "LOIT_ANG_MAX": (0.0, _R32),
    "LOIT_BRK_ACCEL": (250.0, _R32),
    "LOIT_BRK_DELAY": (1.0, _R32),
    "LOIT_BRK_JERK": (500.0, _R32),
}

#: ArduCopter's RC input channel defaults (RC_Channel.cpp RCn_MIN/MAX/TRIM; radio.cpp
#: ``default_dead_zones``: roll, pitch, yaw 20, throttle 30 PWM) and the radio failsafe's frame
#: timeouts (radio.cpp ``read_radio``; config.h FS_RADIO_TIMEOUT_MS, FS_RADIO_RC_OVERRIDE_TIMEOUT_MS).
ARDU_RC_MIN, ARDU_RC_MAX, ARDU_RC_TRIM = 1100, 1900, 1500
ARDU_RC_DEAD_ZONE = {"roll": 20, "pitch": 20, "throttle": 30, "yaw": 20}
ARDU_FS_RADIO_TIMEOUT_S, ARDU_FS_RADIO_RC_OVERRIDE_TIMEOUT_S = 0.5, 1.0

_ID = {
    "SYS_STATUS": _M.MAVLINK_MSG_ID_SYS_STATUS,
    "EXTENDED_SYS_STATE": _M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    "LOCAL_POSITION_NED": _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    "ATTITUDE": _M.MAVLINK_MSG_ID_ATTITUDE,
    "ATTITUDE_QUATERNION": _M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
    "GLOBAL_POSITION_INT": _M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "GPS_RAW_INT": _M.MAVLINK_MSG_ID_GPS_RAW_INT,
    "HOME_POSITION": _M.MAVLINK_MSG_ID_HOME_POSITION,
    "SYSTEM_TIME": _M.MAVLINK_MSG_ID_SYSTEM_TIME,
    "BATTERY_STATUS": _M.MAVLINK_MSG_ID_BATTERY_STATUS,
    "AUTOPILOT_VERSION": _M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
    "MISSION_CURRENT": _M.MAVLINK_MSG_ID_MISSION_CURRENT,
    "ALTITUDE": _M.MAVLINK_MSG_ID_ALTITUDE,
    "VFR_HUD": _M.MAVLINK_MSG_ID_VFR_HUD,
    "ODOMETRY": _M.MAVLINK_MSG_ID_ODOMETRY,
    "HIGHRES_IMU": _M.MAVLINK_MSG_ID_HIGHRES_IMU,
    "RAW_IMU": _M.MAVLINK_MSG_ID_RAW_IMU,
    "POSITION_TARGET_LOCAL_NED": _M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED,
    "TIMESYNC": _M.MAVLINK_MSG_ID_TIMESYNC,
    "PING": _M.MAVLINK_MSG_ID_PING,
}

#: Fixes per second of the model's GPS receiver (a model choice; PX4 forwards each fix).
GPS_FIX_RATE_HZ = 5.0

#: Default stream rates (Hz) until SET_MESSAGE_INTERVAL. PX4: ``mavlink_main.cpp``
#: ``configure_streams_to_default`` onboard mode (the companion port): TIMESYNC 10, HIGHRES_IMU
#: 50, LOCAL_POSITION_NED 30, ATTITUDE 100, ALTITUDE 10, ODOMETRY 30, ATTITUDE_QUATERNION 50,
#: EXTENDED_SYS_STATE 5, GLOBAL_POSITION_INT 50, GPS_RAW_INT every fix, HOME_POSITION 0.5, PING 1,
#: POSITION_TARGET_LOCAL_NED 10, SYS_STATUS 5, SYSTEM_TIME 1, VFR_HUD 10, BATTERY_STATUS 0.5.
#: ArduPilot: per stream group (``GCS_MAVLink`` ``STREAM_*_msgs``): RAW_SENS (RAW_IMU) 2,
#: EXT_STAT (SYS_STATUS, GPS_RAW_INT, MISSION_CURRENT) 2, POSITION (GLOBAL_POSITION_INT,
#: LOCAL_POSITION_NED) 2, EXTRA1 (ATTITUDE) 4, EXTRA2 (VFR_HUD) 4, EXTRA3 (SYSTEM_TIME,
#: BATTERY_STATUS) 2 Hz. These are the companion port's SRn_* settings of this simulation:
#: ArduCopter's compiled defaults are 0 for every group (``AP_MAV_DEFAULT_STREAM_RATE_*``), so a
#: real port streams only what was configured or requested. POSITION_TARGET_LOCAL_NED is in no
#: ArduPilot group (0: on request, and only in GUIDED). ``telemetry_rate_hz`` of the config
#: overrides the position and attitude rates. GPS_RAW_INT: PX4's onboard mode sends every new fix
#: (``unlimited_rate``; the model's receiver makes :data:`GPS_FIX_RATE_HZ` fixes a second).
DEFAULT_RATES_HZ = {
    "px4": {"SYS_STATUS": 5.0, "EXTENDED_SYS_STATE": 5.0, "LOCAL_POSITION_NED": 30.0, "ATTITUDE_QUATERNION": 50.0,
            "ATTITUDE": 100.0, "GLOBAL_POSITION_INT": 50.0, "HOME_POSITION": 0.5, "SYSTEM_TIME": 1.0,
            "BATTERY_STATUS": 0.5, "GPS_RAW_INT": GPS_FIX_RATE_HZ, "ALTITUDE": 10.0, "VFR_HUD": 10.0,
            "ODOMETRY": 30.0, "HIGHRES_IMU": 50.0, "POSITION_TARGET_LOCAL_NED": 10.0, "TIMESYNC": 10.0, "PING": 1.0},
    "ardupilot": {"SYS_STATUS": 2.0, "EXTENDED_SYS_STATE": 2.0, "LOCAL_POSITION_NED": 2.0, "ATTITUDE": 4.0,
                  "GLOBAL_POSITION_INT": 2.0, "HOME_POSITION": 0.0, "SYSTEM_TIME": 2.0, "BATTERY_STATUS": 2.0,
                  "GPS_RAW_INT": 2.0, "MISSION_CURRENT": 2.0, "VFR_HUD": 4.0, "RAW_IMU": 2.0,
                  "POSITION_TARGET_LOCAL_NED": 0.0},
}

#: ArduCopter's stream groups as far as the model sends their messages (``GCS_MAVLink``
#: ``STREAM_*_msgs``; MAV_DATA_STREAM id -> messages), for REQUEST_DATA_STREAM. RC_CHANNELS and
#: RAW_CONTROLLER hold nothing the model sends; EXTENDED_SYS_STATE and HOME_POSITION are in no
#: group.
ARDUPILOT_STREAM_GROUPS = {
    _M.MAV_DATA_STREAM_RAW_SENSORS: ("RAW_IMU",),
    _M.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "MISSION_CURRENT"),
    _M.MAV_DATA_STREAM_RC_CHANNELS: (),
    _M.MAV_DATA_STREAM_RAW_CONTROLLER: (),
    _M.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    _M.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    _M.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    _M.MAV_DATA_STREAM_EXTRA3: ("SYSTEM_TIME", "BATTERY_STATUS"),
}

#: The two settings: a GPS-less indoor vehicle (vision position, no global origin, offboard
#: loss -> Hold, since Position mode needs an RC link it does not have) and an outdoor one
#: (GPS: a global origin, offboard loss -> PX4's default Position, falling back to Hold
#: without RC).
PROFILES = {
    "indoor": {"global_origin": None, "rc_connected": False, "px4_params": (("COM_OBL_RC_ACT", 5),)},
    "outdoor": {"global_origin": (47.397742, 8.545594, 488.0), "rc_connected": False, "px4_params": ()},
}


def _flight_sw_version(major: int, minor: int, patch: int) -> int:
    return (major << 24) | (minor << 16) | (patch << 8) | 0xFF  # FIRMWARE_VERSION_TYPE_OFFICIAL


@dataclass(frozen=True)
class SimVehicleConfig:
    """Rules, rates and limits of the simulated vehicle (seconds, metres, radians, ENU).

    Attributes
    ----------
    autopilot : ``"px4"`` or ``"ardupilot"``
    profile : ``"indoor"`` (no global origin) or ``"outdoor"`` (:data:`PROFILES`)
    telemetry_rate_hz : LOCAL_POSITION_NED and attitude rate, or None for the autopilot default
    offboard_loss_timeout_s : initial COM_OF_LOSS_T (PX4)
    guided_timeout_s : initial GUID_TIMEOUT (ArduCopter)
    params : ``((name, value), ...)`` overrides of the autopilot's parameters
    estimator_origin_m : scene ENU position of the estimator's origin, or None for the boot
        position (where the estimate started)
    estimator_yaw_rad : ENU yaw (rad) of the estimator frame's east axis in the scene
        (0: aligned with the scene; a vision-only estimator starts with an arbitrary heading)
    global_origin : ``(lat_deg, lon_deg, alt_amsl_m)`` of the scene origin, or None (GPS-less);
        default from the profile
    rc_connected : an RC link is present (PX4 manual-control modes as loss actions)
    reboot_time_s : how long an accepted reboot keeps the autopilot silent (a model choice: a
        flight controller takes a few seconds to boot)
    """

    autopilot: str = "px4"
    profile: str = "indoor"
    system_id: int = 1
    component_id: int = _M.MAV_COMP_ID_AUTOPILOT1
    physics_rate_hz: float = 100.0
    telemetry_rate_hz: float | None = 50.0
    heartbeat_period_s: float = 1.0
    offboard_loss_timeout_s: float = 1.0
    guided_timeout_s: float = 3.0
    v_max_mps: float = 5.0
    a_max_mps2: float = 5.0
    yaw_rate_max_radps: float = 1.5
    k_pos: float = 1.5
    k_vel: float = 4.0
    k_yaw: float = 2.0
    initial_position_m: tuple = (0.0, 0.0, 0.0)
    initial_yaw_rad: float = 0.0
    boot_time_ms: int = 0
    params: tuple = ()
    estimator_origin_m: tuple | None = None
    estimator_yaw_rad: float = 0.0
    global_origin: tuple | None | str = "profile"
    rc_connected: bool | None = None
    battery_capacity_s: float = 1200.0
    reboot_time_s: float = 3.0

    def __post_init__(self) -> None:
        if self.autopilot not in ("px4", "ardupilot"):
            raise ValueError(f"autopilot must be 'px4' or 'ardupilot', got {self.autopilot!r}")
        if self.profile not in PROFILES:
            raise ValueError(f"profile must be one of {sorted(PROFILES)}, got {self.profile!r}")
        if not 1 <= int(self.system_id) <= 255:
            raise ValueError(f"system_id must be in [1, 255], got {self.system_id}")
        positive = (
            "physics_rate_hz", "heartbeat_period_s", "offboard_loss_timeout_s", "guided_timeout_s",
            "v_max_mps", "a_max_mps2", "yaw_rate_max_radps", "k_pos", "k_vel", "k_yaw", "battery_capacity_s",
            "reboot_time_s",
        )
        for name in positive:
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive, got {val!r}")
        if self.telemetry_rate_hz is not None and not (math.isfinite(self.telemetry_rate_hz) and self.telemetry_rate_hz > 0):
            raise ValueError(f"telemetry_rate_hz must be positive or None, got {self.telemetry_rate_hz!r}")
        p = tuple(float(x) for x in self.initial_position_m)
        if len(p) != 3 or not all(math.isfinite(x) for x in p) or p[2] < 0:
            raise ValueError(f"initial_position_m must be 3 finite numbers with z >= 0, got {self.initial_position_m!r}")
        object.__setattr__(self, "initial_position_m", p)
        if not 0 <= int(self.boot_time_ms) < 2**32:
            raise ValueError(f"boot_time_ms must be a uint32, got {self.boot_time_ms}")
        if self.estimator_origin_m is not None:
            o = tuple(float(x) for x in self.estimator_origin_m)
            if len(o) != 3 or not all(math.isfinite(x) for x in o):
                raise ValueError(f"estimator_origin_m must be 3 finite numbers or None, got {self.estimator_origin_m!r}")
            object.__setattr__(self, "estimator_origin_m", o)
        if not math.isfinite(self.estimator_yaw_rad):
            raise ValueError(f"estimator_yaw_rad must be finite, got {self.estimator_yaw_rad}")
        prof = PROFILES[self.profile]
        if isinstance(self.global_origin, str):
            if self.global_origin != "profile":
                raise ValueError(f"global_origin must be (lat, lon, alt), None or 'profile', got {self.global_origin!r}")
            object.__setattr__(self, "global_origin", prof["global_origin"])
        if self.global_origin is not None:
            g = tuple(float(x) for x in self.global_origin)
            if len(g) != 3 or not (-90 < g[0] < 90 and -180 <= g[1] <= 180 and math.isfinite(g[2])):
                raise ValueError(f"global_origin must be (lat_deg, lon_deg, alt_amsl_m), got {self.global_origin!r}")
            object.__setattr__(self, "global_origin", g)
        if self.rc_connected is None:
            object.__setattr__(self, "rc_connected", bool(prof["rc_connected"]))
        table = PX4_PARAMS if self.autopilot == "px4" else ARDUPILOT_PARAMS
        overrides = dict(prof["px4_params"]) if self.autopilot == "px4" else {}
        for item in self.params:
            if not (isinstance(item, (tuple, list)) and len(item) == 2):
                raise ValueError(f"params must be (name, value) pairs, got {item!r}")
            name, val = item
            if name not in table:
                raise ValueError(f"unknown {self.autopilot} parameter {name!r}; known: {', '.join(table)}")
            if not (isinstance(val, (int, float)) and math.isfinite(val)):
                raise ValueError(f"parameter {name} must be a finite number, got {val!r}")
            overrides[name] = val
        object.__setattr__(self, "params", tuple(sorted(overrides.items())))

    def initial_params(self) -> dict:
        """The parameter table with this config's values (name -> value)."""
        if self.autopilot == "px4":
            values = {k: v for k, (v, _) in PX4_PARAMS.items()}
            values["COM_OF_LOSS_T"] = float(self.offboard_loss_timeout_s)
        else:
            values = {k: v for k, (v, _) in ARDUPILOT_PARAMS.items()}
            values["GUID_TIMEOUT"] = float(self.guided_timeout_s)
        values.update(dict(self.params))
        return values


@dataclass
class _Target:
    """What the controller tracks (scene ENU); None fields are ignored.

    ``yaw_rate`` (rad/s, ENU: counter-clockwise positive) is a commanded turn rate: without a
    ``yaw`` the vehicle turns at it (PX4 offboard yawspeed with the yaw NaN, ArduCopter AutoYaw
    RATE); with one it is the feed-forward added to the heading correction (PX4
    ``AttitudeControl::update``, ArduCopter ``input_thrust_vector_heading_rad``). ``yaw_t_s`` set
    means the yaw target itself advances at ``yaw_rate`` from that clock time on (ArduCopter
    AutoYaw ANGLE_RATE); :meth:`at` gives the target at a given time.
    """

    p: np.ndarray | None = None
    v: np.ndarray | None = None
    a: np.ndarray | None = None
    yaw: float | None = None
    v_limit_mps: float | None = None
    kind: str = "position"  # position | velocity | acceleration | full (for GUID_TIMEOUT)
    yaw_rate_limit_radps: float | None = None  # a slower turn than the model's limit (CONDITION_YAW)
    yaw_rate: float | None = None
    yaw_t_s: float | None = None

    def at(self, t_s: float) -> "_Target":
        """This target at clock time ``t_s`` (s): a yaw that advances at ``yaw_rate`` moved on to it."""
        if self.yaw_t_s is None or self.yaw is None or self.yaw_rate is None:
            return self
        return replace(self, yaw=wrap_angle(self.yaw + self.yaw_rate * (t_s - self.yaw_t_s)), yaw_t_s=t_s)

    def turning(self) -> bool:
        """A commanded turn rate is part of the target (a rate or an advancing yaw)."""
        return self.yaw_rate is not None


class PointMassModel:
    """Point mass with a cascaded P/P controller. ENU, SI units.

    Attributes
    ----------
    p, v : arrays (3,), position (m) and velocity (m/s), ENU
    a : array (3,), last applied acceleration, m/s^2
    yaw, yaw_rate : radians, rad/s (ENU heading of body x)
    """

    GRAVITY_MPS2 = 9.81

    def __init__(self, config: SimVehicleConfig) -> None:
        self.c = config
        self.p = np.array(config.initial_position_m, dtype=float)
        self.v = np.zeros(3)
        self.a = np.zeros(3)
        self.yaw = float(config.initial_yaw_rad)
        self.yaw_rate = 0.0
        self.ground_z_m = float(config.initial_position_m[2])
        self._flown: tuple[np.ndarray, np.ndarray] | None = None  # (v_sp, a_sp) of the last step

    @property
    def on_ground(self) -> bool:
        return self.p[2] <= self.ground_z_m + 1e-3 and self.v[2] <= 1e-3

    def step(self, dt_s: float, target: _Target | None, armed: bool) -> None:
        c = self.c
        if not armed or target is None:
            if self.on_ground or not armed:
                self.a = np.zeros(3) if self.on_ground else np.array([0.0, 0.0, -self.GRAVITY_MPS2])
                self._integrate(dt_s)
                self.yaw_rate = 0.0
                self._flown = None
                return
            target = _Target(p=self.p.copy())
        v_limit = c.v_max_mps if target.v_limit_mps is None else min(c.v_max_mps, target.v_limit_mps)
        v_des = np.zeros(3) if target.v is None else target.v.copy()
        if target.p is not None:
            v_des = v_des + c.k_pos * (target.p - self.p)
        n = np.linalg.norm(v_des)
        if n > v_limit:
            v_des *= v_limit / n
        a = c.k_vel * (v_des - self.v)
        if target.a is not None:
            a = a + target.a
        n = np.linalg.norm(a)
        if n > c.a_max_mps2:
            a *= c.a_max_mps2 / n
        self.a = a
        self._flown = (v_des, a.copy())
        self._integrate(dt_s)
        self.yaw_rate = self._yaw_rate(target)
        self.yaw = wrap_angle(self.yaw + self.yaw_rate * dt_s)

    def controller_setpoint(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The velocity (m/s) and acceleration (m/s^2) setpoints, ENU, the last step's controller
        flew (the position loop's output plus the feed-forward, limited; PX4 PositionControl's
        ``_vel_sp`` and ``_acc_sp``), or None when it tracked nothing."""
        return None if self._flown is None else (self._flown[0].copy(), self._flown[1].copy())

    def _yaw_rate(self, target: _Target) -> float:
        """The turn rate (rad/s, ENU) toward ``target``: a P correction toward its yaw plus its
        commanded rate, or the commanded rate alone, within the model's limit
        (``yaw_rate_max_radps``) and the target's own (``yaw_rate_limit_radps``)."""
        c = self.c
        if target.yaw is None and target.yaw_rate is None:
            return 0.0
        ff = 0.0 if target.yaw_rate is None else float(target.yaw_rate)
        rate = ff if target.yaw is None else c.k_yaw * wrap_angle(target.yaw - self.yaw) + ff
        r_max = c.yaw_rate_max_radps if target.yaw_rate_limit_radps is None else min(c.yaw_rate_max_radps, target.yaw_rate_limit_radps)
        return float(np.clip(rate, -r_max, r_max))

    def _integrate(self, dt_s: float) -> None:
        self.v = self.v + self.a * dt_s
        n = np.linalg.norm(self.v)
        if n > self.c.v_max_mps:
            self.v *= self.c.v_max_mps / n
        self.p = self.p + self.v * dt_s
        if self.p[2] < self.ground_z_m:
            self.p[2] = self.ground_z_m
            self.v[2] = max(self.v[2], 0.0)
            if self.v[2] == 0.0:
                self.v[:2] = 0.0  # friction: a copter resting on its legs does not slide

    def R_enu_flu(self) -> np.ndarray:
        """Body attitude (3, 3): thrust axis along ``a + g z``, heading ``yaw``."""
        thrust = self.a + np.array([0.0, 0.0, self.GRAVITY_MPS2])
        z_b = thrust / max(np.linalg.norm(thrust), 1e-6)
        x_c = np.array([np.cos(self.yaw), np.sin(self.yaw), 0.0])
        y_b = np.cross(z_b, x_c)
        y_b /= max(np.linalg.norm(y_b), 1e-9)
        x_b = np.cross(y_b, z_b)
        return np.column_stack([x_b, y_b, z_b])


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class SimMavlinkVehicle:
    """The simulated autopilot serving one :class:`~onfly.mavlink.link.Link` from its own thread.

    ``clock`` is the real monotonic clock by default (the vehicle runs in wall time like real
    hardware). ``model`` replaces the internal :class:`PointMassModel`. Read-only observers for
    tests: :attr:`model`, :attr:`armed`, :attr:`custom_mode`, :attr:`mode_name`,
    :attr:`landed_state`, :attr:`params`, :attr:`events` (``(t_s, text)``), :attr:`statustexts`,
    :attr:`setpoints_received`.
    """

    def __init__(
        self, link: Link, config: SimVehicleConfig = SimVehicleConfig(), clock: Callable[[], float] = time.monotonic, model=None
    ) -> None:
        self.link = link
        self.c = config
        self.clock = clock
        self.model = model if model is not None else PointMassModel(config)
        self.px4 = config.autopilot == "px4"
        self.armed = False
        self.custom_mode = px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]) if self.px4 else ARDUCOPTER_MODE["stabilize"]
        self.params = config.initial_params()
        self._param_types = {k: t for k, (_, t) in (PX4_PARAMS if self.px4 else ARDUPILOT_PARAMS).items()}
        self.events: list[tuple[float, str]] = []
        self.statustexts: list[tuple[float, str]] = []
        self.setpoints_received = 0
        self.setpoint_times: list[float] = []
        self.foreign_setpoints = 0
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cut = threading.Event()
        self._frozen_pos = None
        self._frozen_odom = None
        self._position_valid = True
        self._accel_enu = np.zeros(3)  # the model's acceleration over the last physics step (scene ENU)
        self._ping_seq = 0
        self._statustext_id = 0  # the id of the last chunked STATUSTEXT (PX4: of the next text)
        self._t_boot = clock()
        self._target: _Target | None = None
        self._setpoint: _Target | None = None
        self._last_sp_s: float | None = None
        self._takeoff_alt_m: float | None = None  # scene z the current take-off climbs to
        self._guided_timed_out = False
        self._rtl: rtl.Px4Return | rtl.ArduCopterReturn | None = None  # the Return mode's state machine while in it
        self._px4_cruise_mps: float | None = None  # PX4 navigator's DO_CHANGE_SPEED cruising speed (None: default)
        self._ardu_speed_ne_mps: float | None = None  # ArduCopter DO_CHANGE_SPEED horizontal speed (GUIDED Pos / RTL)
        self._reboot_at: float | None = None  # clock time the accepted reboot starts (the link goes silent)
        self._back_at: float | None = None  # clock time the rebooted autopilot speaks again (inf: stays down)
        self._boot_offset_ms = float(config.boot_time_ms)
        # estimator frame: origin and heading in the scene
        origin = config.estimator_origin_m if config.estimator_origin_m is not None else tuple(self.model.p)
        self._origin = np.array(origin, dtype=float)
        self._R_scene_est = _rot_z(config.estimator_yaw_rad)
        self._home: np.ndarray | None = None  # scene ENU, set at arming
        self._home_manual = False  # home set by DO_SET_HOME (kept at arming)
        self._sticks: tuple | None = None  # PX4 manual_control_setpoint from MANUAL_CONTROL: pitch, roll, throttle, yaw in [-1, 1]
        self._sticks_t: float | None = None  # clock time of the last accepted MANUAL_CONTROL
        self._sticks_lost = False  # the manual-control-loss failsafe has been taken for this loss
        self._stick_hold: dict = {}  # Position mode's hold points (xy, z, yaw) while the sticks are centred
        # ArduCopter RC: override PWM per channel (0 = none) and when it came; radio frames
        self._rc_override: dict[str, int] = {}
        self._rc_override_t: float | None = None  # clock time of the last accepted MANUAL_CONTROL
        self._rc_receiver_present = False  # ap.rc_receiver_present: a radio frame (here: an override) was read
        self._radio_failsafe = False  # failsafe.radio
        self._loiter: dict = {}  # AC_Loiter state: desired velocity, brake acceleration and timer, target position
        self._flying_since_arm = False
        self._armed_at: float | None = None
        self._still_since: float | None = None
        self.landed_state = _M.MAV_LANDED_STATE_ON_GROUND
        self._landed_at: float | None = None
        self._pending: list = []  # messages to send after the current ACK
        self._rates_hz: dict[int, float] = {}
        self._default_rates: dict[int, float] = {}
        for name, rate in DEFAULT_RATES_HZ[config.autopilot].items():
            if name in ("LOCAL_POSITION_NED", "ATTITUDE", "ATTITUDE_QUATERNION") and config.telemetry_rate_hz is not None:
                rate = config.telemetry_rate_hz
            self._default_rates[_ID[name]] = rate
        self._rates_hz = dict(self._default_rates)
        self._next_send: dict[int, float] = {}
        self._builders = {
            _M.MAVLINK_MSG_ID_ALTITUDE: self._altitude,
            _M.MAVLINK_MSG_ID_VFR_HUD: self._vfr_hud,
            _M.MAVLINK_MSG_ID_ODOMETRY: lambda: self._frozen_odom if self._frozen_odom is not None else self._odometry(),
            _M.MAVLINK_MSG_ID_HIGHRES_IMU: self._highres_imu,
            _M.MAVLINK_MSG_ID_RAW_IMU: self._raw_imu,
            _M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: self._position_target_local_ned,
            _M.MAVLINK_MSG_ID_TIMESYNC: self._timesync_request,
            _M.MAVLINK_MSG_ID_PING: self._ping_request,
        }
        self.fence = FenceMonitor(self)  # geofence breach check and action (onfly/mavlink/geofence.py)
        self.mission = MissionManager(self)  # mission protocol and AUTO flight (onfly/mavlink/mission.py)

    # -- lifecycle --------------------------------------------------------------------------
    def start(self) -> "SimMavlinkVehicle":
        if self._thread is not None:
            raise RuntimeError("vehicle already started")
        if not self.link.is_connected:
            self.link.connect()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="sim-vehicle", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self.link.close()

    def __enter__(self) -> "SimMavlinkVehicle":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- frames -----------------------------------------------------------------------------
    def local_from_scene(self, p_enu) -> np.ndarray:
        """Scene ENU point(s) (..., 3) -> the estimator's local ENU frame."""
        return (np.asarray(p_enu, dtype=float) - self._origin) @ self._R_scene_est

    def scene_from_local(self, p_local) -> np.ndarray:
        """The estimator's local ENU point(s) (..., 3) -> scene ENU."""
        return np.asarray(p_local, dtype=float) @ self._R_scene_est.T + self._origin

    @property
    def T_local_scene(self) -> np.ndarray:
        """(4, 4) transform taking scene ENU coordinates to the estimator's local ENU frame."""
        T = np.eye(4)
        T[:3, :3] = self._R_scene_est.T
        T[:3, 3] = -self._R_scene_est.T @ self._origin
        return T

    def _global_from_scene(self, p_enu) -> tuple[float, float, float]:
        lat0, lon0, alt0 = self.c.global_origin
        e, n, u = (float(x) for x in p_enu)
        lat = lat0 + math.degrees(n / EARTH_RADIUS_M)
        lon = lon0 + math.degrees(e / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return lat, lon, alt0 + u

    def _scene_from_global(self, lat: float, lon: float, alt_amsl: float) -> np.ndarray:
        lat0, lon0, alt0 = self.c.global_origin
        n, e = frames.ne_offset_m(lat, lon, lat0, lon0)
        return np.array([e, n, alt_amsl - alt0])

    # -- observers and faults ---------------------------------------------------------------
    @property
    def mode_name(self) -> str:
        with self._lock:
            return self._mode_name(self.custom_mode)

    def _mode_name(self, custom_mode: int) -> str:
        if self.px4:
            main = px4_main_mode(custom_mode)
            sub = (custom_mode >> 24) & 0xFF
            name = next((k for k, v in PX4_MAIN.items() if v == main), str(main))
            if main == PX4_MAIN["auto"]:
                name += "." + next((k for k, v in PX4_AUTO_SUB.items() if v == sub), str(sub))
            return name
        return next((k for k, v in ARDUCOPTER_MODE.items() if v == custom_mode), str(custom_mode))

    def position_enu(self) -> np.ndarray:
        """Scene ENU position (ground truth)."""
        with self._lock:
            return self.model.p.copy()

    def velocity_enu(self) -> np.ndarray:
        with self._lock:
            return self.model.v.copy()

    def set_link_cut(self, cut: bool) -> None:
        """Drop every message in both directions (True) or restore the link (False)."""
        (self._cut.set if cut else self._cut.clear)()
        self._event(f"link {'cut' if cut else 'restored'}")

    def set_odometry_frozen(self, frozen: bool) -> None:
        """Keep re-sending the last position sample (LOCAL_POSITION_NED, and PX4's ODOMETRY)
        unchanged, old timestamp included."""
        with self._lock:
            self._frozen_pos = self._position_message() if frozen else None
            self._frozen_odom = self._odometry() if (frozen and self.px4) else None
        self._event(f"odometry {'frozen' if frozen else 'live'}")

    def set_position_valid(self, valid: bool) -> None:
        """The estimator has (True) or has lost (False) its position estimate (e.g. vision
        dropped): LOCAL_POSITION_NED and ODOMETRY stop, arming and position modes are refused."""
        with self._lock:
            self._position_valid = bool(valid)
        self._event(f"position estimate {'valid' if valid else 'lost'}")

    def pilot_takeover(self) -> None:
        """The RC pilot flips the mode switch: POSCTL (PX4) or LOITER (ArduPilot), holding here."""
        with self._lock:
            mode = px4_custom_mode(PX4_MAIN["posctl"]) if self.px4 else ARDUCOPTER_MODE["loiter"]
            self._set_mode(mode, "pilot takeover")

    def first_event(self, text: str) -> float | None:
        """Time of the first event whose text starts with ``text``, or None."""
        with self._lock:
            return next((t for t, e in self.events if e.startswith(text)), None)

    def time_boot_ms(self) -> int:
        return int(self._boot_offset_ms + (self.clock() - self._t_boot) * 1000.0) % 2**32

    def time_boot_us(self) -> int:
        """Microseconds since boot (uint64: PX4 ``hrt_absolute_time``, ArduPilot ``micros64``)."""
        return int(round((self._boot_offset_ms + (self.clock() - self._t_boot) * 1000.0) * 1000.0))

    # -- main loop --------------------------------------------------------------------------
    def _run(self) -> None:
        dt = 1.0 / self.c.physics_rate_hz
        now = self.clock()
        next_phys = now
        next_hb = now
        while not self._stop.is_set():
            now = self.clock()
            wait = max(0.0, min(next_phys, next_hb, *self._next_send.values(), now + 0.02) - now)
            try:
                msg = self.link.recv(wait)
            except LinkError as exc:
                if self._stop.is_set():
                    return
                log.error("vehicle link receive failed: %s", exc)
                self._stop.wait(0.05)
                continue
            self._reboot_tick()
            if msg is not None and not self._cut.is_set() and not self.rebooting:
                try:
                    self._handle(msg)
                except Exception:  # a malformed message must never stop the vehicle
                    log.exception("vehicle failed to handle %s", msg.get_type())
            now = self.clock()
            steps = 0
            while now >= next_phys and steps < 20:
                self._physics(dt, next_phys)
                next_phys += dt
                steps += 1
            if now >= next_phys:  # fell far behind (loaded machine): re-anchor, keep stepping in real time
                next_phys = now + dt
            if now >= next_hb:
                self._send(self._heartbeat())
                next_hb = max(next_hb + self.c.heartbeat_period_s, now)
            for msg_id, rate in list(self._rates_hz.items()):
                if rate <= 0:
                    continue
                due = self._next_send.setdefault(msg_id, now)
                if now >= due:
                    msg = self._telemetry(msg_id, streaming=True)
                    if msg is not None:
                        self._send(msg)
                    self._next_send[msg_id] = max(due + 1.0 / rate, now)

    def _send(self, msg) -> None:
        if self._cut.is_set() or msg is None or self.rebooting:
            return
        try:
            self.link.send(msg)
        except LinkError as exc:
            log.debug("vehicle send failed: %s", exc)

    def _event(self, text: str, t_s: float | None = None) -> None:
        """Record an event at ``t_s`` (a physics step's time, for rules that run on it) or now."""
        t = self.clock() if t_s is None else float(t_s)
        with self._lock:
            self.events.append((t, text))
        log.info("sim vehicle t=%.3f: %s", t, text)

    def _statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT: a text longer than the 50-byte field goes out in 50-byte chunks sharing one
        id, chunk_seq counting up (clients such as MAVSDK and MAVProxy join them). PX4
        (``streams/STATUSTEXT.hpp``): every text takes the next id (from 0), the last chunk is the
        rest. ArduPilot (``GCS::send_textv``): id 0 for a text that fits, else the next id (never
        0), and a text of a multiple of 50 bytes ends with an empty chunk."""
        with self._lock:
            self.statustexts.append((self.clock(), text))
            data = text.encode()
            if self.px4:
                text_id, self._statustext_id = self._statustext_id, (self._statustext_id + 1) % 2**16
                chunks = [data[i:i + 50] for i in range(0, max(len(data), 1), 50)]
            elif len(data) <= 50:
                text_id, chunks = 0, [data]
            else:
                self._statustext_id = self._statustext_id % 0xFFFF + 1
                text_id, chunks = self._statustext_id, [data[i:i + 50] for i in range(0, len(data) + 1, 50)]
        for seq, chunk in enumerate(chunks):
            self._send(self.link.mav.statustext_encode(severity, chunk, text_id, seq))

    # -- physics and rules ------------------------------------------------------------------
    def _physics(self, dt: float, t: float) -> None:
        with self._lock:
            self._apply_rules(t)
            self.mission.step(t)
            self.fence.step(t)
            v0 = np.array(self.model.v, dtype=float)
            self.model.step(dt, None if self._target is None else self._target.at(t), self.armed)
            self._accel_enu = (np.array(self.model.v, dtype=float) - v0) / dt
            if self.armed and getattr(self.model, "crashed", False):
                hit = getattr(self.model, "collision", None)
                self._disarm(f"crashed{'' if hit is None else f' into {hit.object_name!r}'}")
            self._land_detector(t)

    def _disarm(self, why: str) -> None:
        self.armed = False
        self._armed_at = None
        self._event(f"disarmed: {why}")
        self._statustext(_M.MAV_SEVERITY_INFO, f"Disarmed: {why}"[:50])

    def _land_detector(self, t: float) -> None:
        """Landed state and auto-disarm (see the module docstring)."""
        m = self.model
        if not self.armed:
            self.landed_state = _M.MAV_LANDED_STATE_ON_GROUND if m.on_ground else _M.MAV_LANDED_STATE_IN_AIR
            self._still_since = None
            return
        still = m.on_ground and float(np.linalg.norm(m.v)) < 0.1
        if not m.on_ground:
            self._flying_since_arm = True
            self._still_since = None
            self._landed_at = None
            if self._landing_mode() and m.v[2] < -0.05:
                self.landed_state = _M.MAV_LANDED_STATE_LANDING
            elif self._takeoff_alt_m is not None and m.v[2] > 0.05:
                self.landed_state = _M.MAV_LANDED_STATE_TAKEOFF
            else:
                self.landed_state = _M.MAV_LANDED_STATE_IN_AIR
        elif still:
            if self._still_since is None:
                self._still_since = t
            trig = float(self.params.get("LNDMC_TRIG_TIME", 1.0))
            if t - self._still_since >= trig and self.landed_state != _M.MAV_LANDED_STATE_ON_GROUND:
                self.landed_state = _M.MAV_LANDED_STATE_ON_GROUND
                self._landed_at = t
                if self._flying_since_arm:
                    self._event("landed")
                if self._rtl is not None:
                    self._rtl.landed(t)
        if self.landed_state != _M.MAV_LANDED_STATE_ON_GROUND:
            return
        if not self._flying_since_arm:
            limit = float(self.params["COM_DISARM_PRFLT"]) if self.px4 else float(self.params["DISARM_DELAY"])
            since = self._armed_at if self._armed_at is not None else t
            if limit > 0 and t - since >= limit:
                self._disarm(f"no take-off within {limit:g} s of arming")
            return
        if self.px4:
            limit = float(self.params["COM_DISARM_LAND"])
        else:
            in_land = self.custom_mode == ARDUCOPTER_MODE["land"] or (self._rtl is not None and self._rtl.landing)
            limit = 0.0 if in_land else float(self.params["DISARM_DELAY"])  # mode_land.cpp, mode_rtl.cpp land_run
        landed_at = self._landed_at if self._landed_at is not None else t
        if limit >= 0 and t - landed_at >= limit:
            self._disarm("landed")

    def _landing_mode(self) -> bool:
        if self._rtl is not None and self._rtl.landing:
            return True
        if self.px4:
            return self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["land"])
        return self.custom_mode == ARDUCOPTER_MODE["land"]

    def _hold_here(self) -> _Target:
        return _Target(p=self.model.p.copy(), yaw=self.model.yaw)

    def _apply_rules(self, t: float) -> None:
        if self._rtl is not None:  # Return mode flies its own state machine (onfly/mavlink/rtl.py)
            if self.armed:
                phase = self._rtl.phase
                sp = self._rtl.step(t, self.model.p)
                if not self.px4 and self._rtl.phase != phase and self._rtl.phase == "return":
                    self._ardu_speed_ne_mps = None  # return_start: wp_and_spline_init at RTL_SPEED
                limit = None if sp is None else sp.v_limit_mps
                if not self.px4 and self._rtl.phase == "return" and self._ardu_speed_ne_mps is not None:
                    limit = self._ardu_speed_ne_mps  # ModeRTL::set_speed_NE_ms: wp_nav's leg speed
                self._target = None if sp is None else _Target(p=sp.p, v=sp.v, v_limit_mps=limit)
            return
        since_sp = math.inf if self._last_sp_s is None else t - self._last_sp_s
        if self.px4:
            if self._manual_control_loss(t):
                return
            main = px4_main_mode(self.custom_mode)
            if main in (PX4_MAIN["posctl"], PX4_MAIN["altctl"]) and self.armed:
                self._fly_sticks(t, hold_xy=main == PX4_MAIN["posctl"])
            elif main == PX4_MAIN["offboard"]:
                loss_t = float(self.params["COM_OF_LOSS_T"])
                if since_sp > loss_t:
                    self._offboard_lost(since_sp)
                else:
                    self._target = self._setpoint
            elif self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["takeoff"]):
                if self._takeoff_alt_m is not None and self.model.p[2] >= self._takeoff_alt_m - 0.1:
                    alt, self._takeoff_alt_m = self._takeoff_alt_m, None
                    self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]), "takeoff complete")
                    self._target = _Target(p=np.array([*self.model.p[:2], alt]), yaw=self.model.yaw)
            return
        if self._ardu_radio_check(t):
            return
        if self.armed and self.custom_mode in (ARDUCOPTER_MODE["loiter"], ARDUCOPTER_MODE["alt_hold"]):
            self._ardu_fly_sticks(t, hold_xy=self.custom_mode == ARDUCOPTER_MODE["loiter"])
            return
        if self.custom_mode != ARDUCOPTER_MODE["guided"] or not self.armed:
            return
        if self._takeoff_alt_m is not None:
            if self.model.p[2] >= self._takeoff_alt_m - 0.1:
                alt, self._takeoff_alt_m = self._takeoff_alt_m, None
                self._target = _Target(p=np.array([*self.model.p[:2], alt]), yaw=self.model.yaw)
                self._event("takeoff complete")
            return
        sp = self._setpoint
        if sp is None:
            return
        if self.landed_state == _M.MAV_LANDED_STATE_ON_GROUND:
            self._target = None  # landed: ground handling until NAV_TAKEOFF (mode_guided.cpp run functions)
            return
        timeout = float(self.params["GUID_TIMEOUT"])
        if (sp.kind != "position" or sp.turning()) and since_sp > timeout:
            if not self._guided_timed_out:
                self._guided_timed_out = True
                # every run function: AutoYaw RATE / ANGLE_RATE -> HOLD ("stop rotating")
                held = replace(sp, yaw=self.model.yaw, yaw_rate=None, yaw_t_s=None) if sp.turning() else sp
                if sp.kind == "position":  # pos_control_run: the position target is kept
                    self._target = self._ardu_limit(held)
                elif sp.kind == "full":  # keep the position, drop the feed-forwards
                    self._target = _Target(p=held.p, yaw=held.yaw)
                else:  # velocity / acceleration: stop
                    self._target = _Target(v=np.zeros(3), yaw=self.model.yaw, kind="velocity")
                self._event(f"guided timeout ({since_sp:.2f} s without a {sp.kind} target)")
        else:
            self._guided_timed_out = False
            self._target = self._ardu_limit(sp)

    # -- manual control (a ground station's joystick) ----------------------------------------------
    def _on_manual_control(self, msg) -> None:
        """MANUAL_CONTROL from a ground station (MAVSDK ManualControl, QGroundControl's virtual
        joystick). PX4 ``MavlinkReceiver::handle_message_manual_control``: published as a manual
        control input from MAVLink (x pitch and y roll / 1000, throttle z from [0, 1000] to [-1, 1],
        r yaw / 1000); the manual control selector takes it unless COM_RC_IN_MODE is 0 (RC only)
        or 4 (disabled). ArduCopter: :meth:`_ardu_manual_control`."""
        if not self.px4:
            self._ardu_manual_control(msg)
            return
        if int(msg.target) not in (0, self.c.system_id):
            return
        if int(self.params["COM_RC_IN_MODE"]) in (0, 4):
            return
        sticks = (msg.x / 1000.0, msg.y / 1000.0, msg.z / 1000.0 * 2.0 - 1.0, msg.r / 1000.0)
        with self._lock:
            self._sticks = tuple(float(np.clip(v, -1.0, 1.0)) for v in sticks)
            first = self._sticks_t is None or self._sticks_lost
            self._sticks_t = self.clock()
            if first:
                self._sticks_lost = False
                self._event("manual control: MAVLink stick input")

    def _manual_control_present(self) -> bool:
        """An RC link (``rc_connected``) or a MANUAL_CONTROL within COM_RC_LOSS_T (PX4
        ``ManualControl``: ``manual_control_signal_lost`` after COM_RC_LOSS_T without input)."""
        if self.c.rc_connected:
            return True
        return self._sticks_t is not None and self.clock() - self._sticks_t <= float(self.params["COM_RC_LOSS_T"])

    def _manual_control_loss(self, t: float) -> bool:
        """PX4 manual-control loss (``failsafe.cpp`` ``checkStateAndMode``): stick input that was
        present and stopped for COM_RC_LOSS_T while armed takes NAV_RCL_ACT, unless the mode is
        excepted by COM_RCL_EXCEPT (bit 0 Mission, 1 Hold and Takeoff, 2 Offboard) or is Return /
        Land; once per loss. True when it switched modes."""
        if self._sticks_t is None or self._sticks_lost or not self.armed:
            return False
        if t - self._sticks_t <= float(self.params["COM_RC_LOSS_T"]):
            return False
        self._sticks_lost = True
        cm, ex = self.custom_mode, int(self.params["COM_RCL_EXCEPT"])
        auto = lambda sub: px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB[sub])  # noqa: E731
        ignored = (cm == auto("mission") and ex & 1) or (cm in (auto("loiter"), auto("takeoff")) and ex & 2) or (
            px4_main_mode(cm) == PX4_MAIN["offboard"] and ex & 4) or cm in (auto("rtl"), auto("land"))
        self._event(f"manual control lost ({t - self._sticks_t:.2f} s without input)", t)
        if ignored:
            return False
        self._statustext(_M.MAV_SEVERITY_WARNING, "Failsafe: manual control lost")
        action = int(self.params["NAV_RCL_ACT"])
        why = f"manual control lost: NAV_RCL_ACT {action}"
        if action == 6:
            self._disarm(why)
            return True
        wanted = {1: "loiter", 2: "rtl", 3: "land", 5: "terminate"}.get(action)
        if wanted is None:
            return False
        self._px4_failsafe_action(wanted, why)
        return True

    @staticmethod
    def _expo_deadzone(value: float, expo: float, deadzone: float) -> float:
        """PX4 ``math::expo_deadzone``: the deadzone removed and rescaled, then
        ``(1 - e) x + e x^3``."""
        dz = min(max(deadzone, 0.0), 0.99)
        x = 0.0 if abs(value) <= dz else (value - math.copysign(dz, value)) / (1.0 - dz)
        e = min(max(expo, 0.0), 1.0)
        return (1.0 - e) * x + e * x ** 3

    def _fly_sticks(self, t: float, hold_xy: bool) -> None:
        """PX4 Position mode (``FlightTaskManualPosition`` / ``StickAccelerationXY``, ``StickYaw``,
        ``FlightTaskManualAltitude``): the pitch / roll sticks are a horizontal velocity in the
        heading frame up to MPC_VEL_MANUAL, throttle a climb rate up to MPC_Z_VEL_MAX_UP / DN, yaw
        a rate up to MPC_MAN_Y_MAX deg/s, each through ``expo_deadzone`` (MPC_*_EXPO,
        MPC_HOLD_DZ); centred sticks hold the position, altitude and heading where the vehicle
        stopped. Altitude mode (``hold_xy`` False) flies the same sticks without the horizontal
        position hold (see docs/flight.md for what is simplified). Without input since the mode
        was entered the sticks count as centred."""
        P, m = self.params, self.model
        x, y, thr, r = self._sticks if self._sticks is not None else (0.0, 0.0, 0.0, 0.0)
        dz = float(P["MPC_HOLD_DZ"])
        fwd = self._expo_deadzone(x, float(P["MPC_XY_MAN_EXPO"]), dz) * float(P["MPC_VEL_MANUAL"])
        right = self._expo_deadzone(y, float(P["MPC_XY_MAN_EXPO"]), dz) * float(P["MPC_VEL_MANUAL"])
        up = self._expo_deadzone(thr, float(P["MPC_Z_MAN_EXPO"]), dz)
        up *= float(P["MPC_Z_VEL_MAX_UP"]) if up > 0 else float(P["MPC_Z_VEL_MAX_DN"])
        rate = -self._expo_deadzone(r, float(P["MPC_YAW_EXPO"]), dz) * math.radians(float(P["MPC_MAN_Y_MAX"]))  # r > 0: clockwise
        c, s_ = math.cos(m.yaw), math.sin(m.yaw)
        v = np.array([fwd * c + right * s_, fwd * s_ - right * c, up])
        hold = self._stick_hold
        if fwd == 0.0 and right == 0.0:
            if hold_xy:
                if "xy" not in hold and float(np.linalg.norm(m.v[:2])) < 0.3:
                    hold["xy"] = m.p[:2].copy()  # brake first, then hold where it stopped
                if "xy" in hold:
                    v[:2] = self.c.k_pos * (hold["xy"] - m.p[:2])
        else:
            hold.pop("xy", None)
        if up == 0.0:
            if "z" not in hold and abs(float(m.v[2])) < float(P["MPC_HOLD_MAX_Z"]):
                hold["z"] = float(m.p[2])  # brake first, lock once slower than MPC_HOLD_MAX_Z
            if "z" in hold:
                v[2] = self.c.k_pos * (hold["z"] - m.p[2])
        else:
            hold.pop("z", None)
        if rate == 0.0:
            yaw = hold.setdefault("yaw", float(m.yaw))
        else:
            hold.pop("yaw", None)
            yaw = wrap_angle(m.yaw + rate / self.c.k_yaw)
        self._target = _Target(v=v, yaw=yaw, kind="velocity", yaw_rate_limit_radps=abs(rate) if rate else None)

    # -- ArduCopter: MANUAL_CONTROL as RC overrides ------------------------------------------------
    def _ardu_manual_control(self, msg) -> None:
        """``GCS_MAVLINK::handle_manual_control``: only from SYSID_MYGCS and only with target equal
        to our system id (0 is not accepted); ``GCS_MAVLINK_Copter::handle_manual_control_axes``
        drops a message with z < 0 and overrides roll from y, pitch from -x, throttle from z in
        [0, 1000] and yaw from r (``manual_override``: RCn_MIN + (MAX - MIN) (v + offset) / scaler;
        INT16_MAX releases that channel). Each message is a new radio frame (``read_radio``)."""
        if msg.get_srcSystem() != int(self.params["SYSID_MYGCS"]) or int(msg.target) != self.c.system_id:
            return
        if int(msg.z) < 0:
            return

        def override(value: int, offset: int, scaler: float, reversed_: bool = False) -> int:
            if value == 32767:
                return 0
            value = -value if reversed_ else value
            return int(ARDU_RC_MIN + (ARDU_RC_MAX - ARDU_RC_MIN) * (value + offset) / scaler)

        pwm = {"roll": override(int(msg.y), 1000, 2000.0), "pitch": override(int(msg.x), 1000, 2000.0, True),
               "throttle": override(int(msg.z), 0, 1000.0), "yaw": override(int(msg.r), 1000, 2000.0)}
        with self._lock:
            first = not self._rc_receiver_present
            self._rc_override = pwm
            self._rc_override_t = self.clock()
            self._rc_receiver_present = True
            if first:
                self._event("manual control: RC overrides from the GCS")
            if self._radio_failsafe and pwm["throttle"] >= int(self.params["FS_THR_VALUE"]):
                # set_throttle_and_failsafe: a good throttle frame clears the radio failsafe
                # (failsafe_radio_off_event: the mode is not changed back)
                self._radio_failsafe = False
                self._event("radio failsafe cleared")
                self._statustext(_M.MAV_SEVERITY_WARNING, "Radio Failsafe Cleared")

    def _ardu_overrides_active(self) -> bool:
        """``RC_Channel::has_override``: within RC_OVERRIDE_TIME of the last override (< 0: for ever)."""
        if self._rc_override_t is None or not any(self._rc_override.values()):
            return False
        timeout = float(self.params["RC_OVERRIDE_TIME"])
        return timeout < 0 or self.clock() - self._rc_override_t < timeout

    def _ardu_rc_input(self, channel: str) -> float:
        """The channel's control input normalised to [-1, 1] (roll, pitch, yaw: ``pwm_to_angle_dz``
        around RCn_TRIM) or [0, 1] (throttle: ``pwm_to_range_dz`` above RCn_MIN), each with its
        dead zone. Without an override the last radio input stays (RC_Channel::update runs only on
        a new frame); before any, centred sticks and zero throttle."""
        pwm = self._rc_override.get(channel, 0)
        dz = ARDU_RC_DEAD_ZONE[channel]
        if channel == "throttle":
            if not pwm:
                return 0.0
            r = min(max(pwm, ARDU_RC_MIN), ARDU_RC_MAX)
            low = ARDU_RC_MIN + dz
            return 0.0 if r <= low else (r - low) / (ARDU_RC_MAX - low)
        if not pwm:
            return 0.0
        r = min(max(pwm, ARDU_RC_MIN), ARDU_RC_MAX)
        if r > ARDU_RC_TRIM + dz:
            return (r - ARDU_RC_TRIM - dz) / (ARDU_RC_MAX - ARDU_RC_TRIM - dz)
        if r < ARDU_RC_TRIM - dz:
            return (r - ARDU_RC_TRIM + dz) / (ARDU_RC_TRIM - dz - ARDU_RC_MIN)
        return 0.0

    def _ardu_pilot_climb_rate(self) -> float:
        """``Mode::get_pilot_desired_climb_rate`` (m/s): zero in radio failsafe or without RC; else
        THR_DZ around mid throttle, PILOT_SPEED_UP above and PILOT_SPEED_DN (0: PILOT_SPEED_UP)
        below, linear in the throttle control input (0..1000)."""
        if self._radio_failsafe or not self._rc_receiver_present:
            return 0.0
        P = self.params
        thr = 1000.0 * self._ardu_rc_input("throttle")
        mid = 1000.0 * (ARDU_RC_TRIM - ARDU_RC_MIN - ARDU_RC_DEAD_ZONE["throttle"]) / (ARDU_RC_MAX - ARDU_RC_MIN - ARDU_RC_DEAD_ZONE["throttle"])
        dz = min(max(int(P["THR_DZ"]), 0), 400)
        up = float(P["PILOT_SPEED_UP"])
        dn = float(P["PILOT_SPEED_DN"]) or up
        if thr < mid - dz:
            return dn * (thr - (mid - dz)) / (mid - dz) / 100.0
        if thr > mid + dz:
            return up * (thr - (mid + dz)) / (1000.0 - (mid + dz)) / 100.0
        return 0.0

    @staticmethod
    def _ardu_input_expo(value: float, expo: float) -> float:
        """ArduPilot ``input_expo``: ``(1 - e) x / (1 - e |x|)`` for |x| <= 1 (expo capped at 0.95)."""
        x = min(max(value, -1.0), 1.0)
        e = min(expo, 0.95)
        return (1.0 - e) * x / (1.0 - e * abs(x)) if e > 0 else x

    def _ardu_fly_sticks(self, t: float, hold_xy: bool) -> None:
        """ArduCopter LOITER (``mode_loiter.cpp`` with ``AC_Loiter``) and ALT_HOLD
        (``mode_althold.cpp``) flown from the RC (override) sticks. The sticks are lean angles up
        to LOIT_ANG_MAX (0: 2/3 of ANGLE_MAX); LOITER turns them into a desired acceleration
        g tan(angle) in the heading frame, integrates it into a desired velocity with a drag
        g tan(angle_max) v / LOIT_SPEED (so full stick settles at LOIT_SPEED) and, sticks centred
        for LOIT_BRK_DELAY, a braking deceleration ramping at LOIT_BRK_JERK up to LOIT_BRK_ACCEL;
        the target position follows the desired velocity and is held when it is zero. ALT_HOLD
        has no horizontal hold: the lean accelerates the point mass (no drag here), level sticks
        keep its velocity. Both take the climb rate from the throttle
        (:meth:`_ardu_pilot_climb_rate`, the altitude target integrated from it) and the yaw rate
        PILOT_Y_RATE ``input_expo`` PILOT_Y_EXPO from the yaw stick. In radio failsafe the pilot
        input is zero (``clear_pilot_desired_acceleration``)."""
        P, m, L = self.params, self.model, self._loiter
        dt = max(t - L.get("t", t), 0.0)
        L["t"] = t
        fs = self._radio_failsafe or not self._rc_receiver_present
        roll = 0.0 if fs else self._ardu_rc_input("roll")
        pitch = 0.0 if fs else self._ardu_rc_input("pitch")
        yaw_in = 0.0 if fs else self._ardu_rc_input("yaw")
        angle_max = float(P["LOIT_ANG_MAX"]) if hold_xy and float(P["LOIT_ANG_MAX"]) > 0 else float(P["ANGLE_MAX"]) / 100.0 * (2.0 / 3.0 if hold_xy else 1.0)
        th_max = math.radians(angle_max)
        g = PointMassModel.GRAVITY_MPS2
        fwd = g * math.tan(-pitch * th_max)  # pitch stick forward: nose down, accelerate forward
        right = g * math.tan(roll * th_max)
        c, s_ = math.cos(m.yaw), math.sin(m.yaw)
        accel = np.array([fwd * c + right * s_, fwd * s_ - right * c])
        vel = L.setdefault("v", np.array(m.v[:2], dtype=float))
        if hold_xy:
            a_max = g * math.tan(th_max)
            v_lim = max(float(P["LOIT_SPEED"]), 20.0) / 100.0
            vel = vel + accel * dt
            speed = float(np.linalg.norm(vel))
            brake_target = 0.0
            jerk = float(P["LOIT_BRK_JERK"]) / 100.0
            if not accel.any():
                if t - L.setdefault("brake_timer", t) > float(P["LOIT_BRK_DELAY"]):
                    brake_target = min(self._sqrt_controller(speed, 1.0, jerk, dt), float(P["LOIT_BRK_ACCEL"]) / 100.0)
            else:
                L["brake_timer"] = t
            brake = L.get("brake", 0.0)
            brake += float(np.clip(brake_target - brake, -jerk * dt, jerk * dt))
            L["brake"] = brake
            if speed > 0:
                new = max(speed - (a_max * speed / v_lim + brake) * dt, 0.0)
                vel = vel / speed * min(new, v_lim)
            L["v"] = vel
            p_xy = L.setdefault("p", m.p[:2].copy()) + vel * dt
            L["p"] = p_xy
            v_xy = vel + self.c.k_pos * (p_xy - m.p[:2])
        else:
            vel = vel + accel * dt
            L["v"] = vel
            v_xy = vel
        climb = self._ardu_pilot_climb_rate()
        if self.model.on_ground and climb <= 0.0:
            L.pop("z", None)
            self._target = None  # on the ground until the throttle asks for a climb (takeoff)
            return
        z = L.setdefault("z", float(m.p[2])) + climb * dt
        L["z"] = z
        v_z = climb + self.c.k_pos * (z - m.p[2])
        rate = math.radians(float(P["PILOT_Y_RATE"])) * self._ardu_input_expo(yaw_in, float(P["PILOT_Y_EXPO"]))
        if rate == 0.0:
            yaw = L.setdefault("yaw", float(m.yaw))
        else:
            L.pop("yaw", None)
            yaw = wrap_angle(m.yaw - rate / self.c.k_yaw)  # yaw stick right: clockwise
        self._target = _Target(v=np.array([*v_xy, v_z]), yaw=yaw, kind="velocity", yaw_rate_limit_radps=abs(rate) if rate else None)

    @staticmethod
    def _sqrt_controller(error: float, p: float, second_ord_lim: float, dt: float) -> float:
        """AP_Math ``sqrt_controller``: linear p·error near zero, sqrt(2 a (|e| - a / 2p²)) beyond
        a / p², and no more than error / dt."""
        if second_ord_lim <= 0 or p <= 0:
            out = p * error
        else:
            linear = second_ord_lim / (p * p)
            out = math.sqrt(2.0 * second_ord_lim * (error - linear / 2.0)) if error > linear else p * error
        return min(out, error / dt) if dt > 0 else out

    def _ardu_radio_check(self, t: float) -> bool:
        """``Copter::read_radio``: no new radio frame for FS_RADIO_RC_OVERRIDE_TIMEOUT_MS (1 s)
        while overrides are active, else FS_RADIO_TIMEOUT_MS (0.5 s), with FS_THR_ENABLE set
        and (armed or RC ever seen) is the radio failsafe. Here the only radio is the GCS's
        overrides, so it needs RC to have been seen (see docs/flight.md). True when it switched
        modes."""
        if self._radio_failsafe or not self._rc_receiver_present or self._rc_override_t is None:
            return False
        timeout = ARDU_FS_RADIO_RC_OVERRIDE_TIMEOUT_S if self._ardu_overrides_active() else ARDU_FS_RADIO_TIMEOUT_S
        elapsed = t - self._rc_override_t
        if elapsed < timeout or int(self.params["FS_THR_ENABLE"]) == 0:
            return False
        self._radio_failsafe = True
        self._event(f"radio failsafe ({elapsed:.2f} s without a radio frame)", t)
        return self._ardu_radio_failsafe_action()

    def _ardu_radio_failsafe_action(self) -> bool:
        """``Copter::failsafe_radio_on_event``: FS_THR_ENABLE 1/2 RTL (or LAND when RTL cannot
        run), 3 LAND, 4/5 SmartRTL (not modelled: RTL); disarmed or landed: disarm, nothing else;
        AUTO with FS_OPTIONS bit 0, landing with bit 2, GUIDED with bit 1 continue."""
        if not self.armed or self.landed_state == _M.MAV_LANDED_STATE_ON_GROUND:
            if self.armed:
                self._disarm("radio failsafe on the ground")
            return False
        opts, cm = int(self.params["FS_OPTIONS"]), self.custom_mode
        landing = cm == ARDUCOPTER_MODE["land"] or (cm == ARDUCOPTER_MODE["rtl"] and self._rtl is not None and self._rtl.phase == "land")
        if (cm == ARDUCOPTER_MODE["auto"] and opts & 1) or (landing and opts & 4) or (cm == ARDUCOPTER_MODE["guided"] and opts & 2):
            self._statustext(_M.MAV_SEVERITY_WARNING, "Radio Failsafe - Continuing")
            return False
        self._statustext(_M.MAV_SEVERITY_WARNING, "Radio Failsafe")
        action = int(self.params["FS_THR_ENABLE"])
        if action in (1, 2, 4, 5) and self._ardu_fence_mode("rtl", "radio failsafe"):
            return True
        self._ardu_fence_mode("land", "radio failsafe")
        return True

    def _offboard_lost(self, since_sp: float) -> None:
        action = int(self.params["COM_OBL_RC_ACT"])
        names = {0: "Position", 1: "Altitude", 2: "Manual", 3: "Return", 4: "Land", 5: "Hold", 6: "Terminate", 7: "Disarm"}
        why = f"offboard lost ({since_sp:.2f} s without setpoints): {names.get(action, action)}"
        self._statustext(_M.MAV_SEVERITY_WARNING, "Failsafe: no offboard")
        if action == 7 or action == 6:
            if self.model.on_ground:
                self._disarm(why)
            else:
                self._disarm(why + " in the air")
            self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]), why)
            return
        wanted = {0: "posctl", 1: "altctl", 2: "stabilized", 3: "rtl", 4: "land", 5: "loiter"}.get(action, "loiter")
        for mode in (wanted, "loiter", "land", "descend"):
            if self._px4_mode_available(mode):
                break
        cm = {
            "posctl": px4_custom_mode(PX4_MAIN["posctl"]),
            "altctl": px4_custom_mode(PX4_MAIN["altctl"]),
            "stabilized": px4_custom_mode(PX4_MAIN["stabilized"]),
            "rtl": px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["rtl"]),
            "land": px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["land"]),
            "loiter": px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]),
            "descend": px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["land"]),  # descend shows as land here
        }[mode]
        self._set_mode(cm, why + ("" if mode == wanted else f" -> fallback {mode}"))

    def _mission_landed(self) -> bool:
        return self.landed_state == _M.MAV_LANDED_STATE_ON_GROUND

    def _px4_failsafe_action(self, wanted: str, why: str) -> None:
        """A PX4 failsafe action (``failsafe.cpp``): terminate, or a mode with the fallback chain
        Hold, Land (as for offboard loss)."""
        if wanted == "terminate":
            self._disarm(f"{why}: flight termination")
            return
        for mode in (wanted, "loiter", "land"):
            if self._px4_mode_available(mode):
                break
        cm = px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB[mode])
        self._set_mode(cm, why + ("" if mode == wanted else f" -> fallback {mode}"))
        if mode == "loiter":  # the navigator's breach reposition: hold here (also when already in Hold)
            self._target = self._hold_here()

    def _ardu_fence_mode(self, mode: str, why: str = "fence breached") -> bool:
        """``Copter::set_mode(..., reason)``: False when the mode refuses (RTL without home,
        a position mode without a position estimate)."""
        number = ARDUCOPTER_MODE[mode]
        if mode in ("rtl", "brake") and not self._position_valid:
            return False
        if mode == "rtl" and not self._ardu_home_set():
            return False
        self._set_mode(number, why)
        return True

    def _px4_mode_available(self, mode: str) -> bool:
        if mode in ("posctl", "altctl", "stabilized") and not self._manual_control_present():
            return False
        if mode in ("posctl", "loiter", "land") and not self._position_valid:
            return False
        if mode == "rtl" and (self.c.global_origin is None or self._home is None or not self._position_valid):
            return False
        return True

    def _set_mode(self, custom_mode: int, why: str) -> None:
        with self._lock:
            old = self.custom_mode
            self.custom_mode = int(custom_mode)
            if old != self.custom_mode:
                self._rtl = None  # leaving (or re-entering) Return stops its state machine
                self._stick_hold = {}
                self._loiter = {}
            hold = self._hold_here()
            if self._landing_mode():
                speed = float(self.params["MPC_LAND_SPEED"]) if self.px4 else float(self.params["LAND_SPEED"]) / 100.0
                hold = _Target(v=np.array([0.0, 0.0, -speed]), yaw=self.model.yaw, kind="velocity")
            elif self.px4 and px4_main_mode(custom_mode) == PX4_MAIN["offboard"]:
                hold = self._setpoint if self._setpoint is not None else hold
            elif self.px4 and self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["takeoff"]) and self._takeoff_alt_m is not None:
                p = self.model.p.copy()
                p[2] = self._takeoff_alt_m
                hold = _Target(p=p, yaw=self.model.yaw, v_limit_mps=float(self.params["MPC_TKO_SPEED"]))
            if not self.px4 and custom_mode != ARDUCOPTER_MODE["guided"]:
                self._setpoint = None
                self._takeoff_alt_m = None
            if not self.px4 and old != self.custom_mode:
                self._ardu_speed_ne_mps = None  # the new mode's init sets its default speeds
            self._target = hold
            if old != self.custom_mode:
                self._event(f"mode {self.mode_name}: {why}")
                self._statustext(_M.MAV_SEVERITY_INFO, f"Mode {self.mode_name}")
                if self._is_rtl_mode():
                    self._start_rtl()

    def _is_rtl_mode(self) -> bool:
        if self.px4:
            return self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["rtl"])
        return self.custom_mode == ARDUCOPTER_MODE["rtl"]

    def _start_rtl(self) -> None:
        """Activate the Return mode's state machine (only armed: disarmed it starts at arming,
        which both autopilots refuse in this mode)."""
        if not self.armed:
            return
        home = self._home if self._home is not None else self.model.p
        landed = self.landed_state == _M.MAV_LANDED_STATE_ON_GROUND
        t = self.clock()

        def say(text: str) -> None:
            self._statustext(_M.MAV_SEVERITY_INFO, text)

        dest = None  # the closest rally point, when the autopilot's rule picks one over home
        if self.c.global_origin is not None and self.mission.rally:
            if self.px4:
                dest = px4_rally_destination(self, self.model.p, home, self.mission.rally)
            else:
                dest = ardu_rally_destination(self, self.model.p, home, self.mission.rally, self.params)
            if dest is not None:
                self._event(f"rtl: to the rally point at {np.round(dest, 2).tolist()}")
        if self.px4:
            amsl = None if self.c.global_origin is None else self.c.global_origin[2]
            # RTL::findRtlDestination: the destination replaces home (altitude, return, landing)
            self._rtl = rtl.Px4Return(home if dest is None else dest, self.model.p, landed, t, self.params, self._event, say, amsl)
        else:
            self._rtl = rtl.ArduCopterReturn(home, self.model.p, landed, t, self.params, self._event, say, dest_m=dest)
        self._event(f"rtl: return at {self._rtl.return_z_m:.2f} m (scene z)")

    # -- message handling -------------------------------------------------------------------
    def _for_me(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.c.system_id) and target_component in (0, self.c.component_id)

    def _command_for_me(self, command: int, target_system: int, target_component: int) -> bool:
        """Whether a COMMAND_LONG / COMMAND_INT is this autopilot's to answer.

        PX4 ``MavlinkReceiver::evaluate_target_ok``: REQUEST_AUTOPILOT_CAPABILITIES and
        REQUEST_PROTOCOL_VERSION are taken for target system 0 or ours, any component; every other
        command only for our system and our component or MAV_COMP_ID_ALL (0), so a broadcast
        target system 0 is not ours. Another target is not answered
        (``handle_message_command_both``: ``PX4_INFO("Ignore command ...")`` and return; it is
        forwarded when forwarding is on and the component was seen on another link; PX4 up to
        v1.13 answered it FAILED instead). ArduPilot ``MAVLink_routing::check_and_forward``:
        target system 0 or ours is processed locally whatever the component unless a route to
        that component is known on another channel (``!forwarded && match_system``: one link here,
        and nothing is forwarded back on the channel it came in on), so a command for
        another component of this system is answered as the autopilot's own; another system's is
        forwarded or dropped, never answered."""
        if not self.px4:
            return target_system in (0, self.c.system_id)
        if command in (_M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, _M.MAV_CMD_REQUEST_PROTOCOL_VERSION):
            return target_system in (0, self.c.system_id)
        return target_system == self.c.system_id and target_component in (0, self.c.component_id)

    def _handle(self, msg) -> None:
        mtype = msg.get_type()
        if mtype.startswith("MISSION_") and self.mission.handle(msg):
            return
        if mtype == "REQUEST_DATA_STREAM":
            if not self.px4 and self._for_me(msg.target_system, msg.target_component):
                with self._lock:
                    self._request_data_stream(int(msg.req_stream_id), int(msg.req_message_rate), int(msg.start_stop))
            return  # PX4's receiver has no handler for it (SET_MESSAGE_INTERVAL only); no ACK either way
        if mtype == "TIMESYNC":
            # a request (tc1 = 0) is answered with our time since boot in ns and ts1 echoed (PX4
            # ``mavlink_timesync.cpp`` / ``Timesync::handle_message``: hrt_absolute_time * 1000;
            # ArduPilot ``GCS_MAVLINK::handle_timesync``: receive time in us * 1000); tc1 != 0 is
            # an answer to a request of ours: neither autopilot replies to it
            if int(msg.tc1) == 0:
                self._send(self.link.mav.timesync_encode(self.time_boot_us() * 1000, int(msg.ts1)))
            return
        if mtype == "PING":
            # PX4 ``MavlinkReceiver::handle_message_ping``: a request (target 0/0) goes back to the
            # sender with its seq and time_usec; ArduPilot's GCS_MAVLINK has no PING handler
            if self.px4 and msg.target_system == 0 and msg.target_component == 0:
                self._send(self.link.mav.ping_encode(int(msg.time_usec), int(msg.seq), msg.get_srcSystem(), msg.get_srcComponent()))
            return
        if mtype == "MANUAL_CONTROL":
            self._on_manual_control(msg)
            return
        if mtype == "SET_POSITION_TARGET_LOCAL_NED":
            self._on_setpoint(msg)
        elif mtype == "SET_POSITION_TARGET_GLOBAL_INT":
            self._on_global_setpoint(msg)
        elif mtype in ("COMMAND_LONG", "COMMAND_INT"):
            if not self._command_for_me(int(msg.command), int(msg.target_system), int(msg.target_component)):
                self._event(f"command {int(msg.command)} for {msg.target_system}/{msg.target_component} ignored")
                return
            with self._lock:
                self._pending = []
                result = self.mission.on_command(int(msg.command), [msg.param1, msg.param2, msg.param3, msg.param4])
                if result is None:
                    result = self._on_command(msg, mtype == "COMMAND_INT")
                pending, self._pending = self._pending, []
            self._send(self.link.mav.command_ack_encode(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
            for m in pending:
                self._send(m)
        elif mtype == "SET_MODE":
            if msg.target_system in (0, self.c.system_id):
                with self._lock:
                    result = self._cmd_set_mode(float(msg.base_mode), float(msg.custom_mode), 0.0, legacy=True)
                self._send(self.link.mav.command_ack_encode(_M.MAVLINK_MSG_ID_SET_MODE, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        elif mtype == "PARAM_REQUEST_LIST":
            if self._for_me(msg.target_system, msg.target_component):
                for i, name in enumerate(self._param_types):
                    self._send(self._param_value(name, i))
        elif mtype == "PARAM_REQUEST_READ":
            if self._for_me(msg.target_system, msg.target_component):
                names = list(self._param_types)
                name = msg.param_id if msg.param_index < 0 else (names[msg.param_index] if msg.param_index < len(names) else None)
                if name in self._param_types:
                    self._send(self._param_value(name))
        elif mtype == "PARAM_SET":
            if self._for_me(msg.target_system, msg.target_component) and msg.param_id in self._param_types:
                value = self._decode_param(msg.param_value, self._param_types[msg.param_id])
                if value is not None:
                    with self._lock:
                        self.params[msg.param_id] = value
                    self._event(f"param {msg.param_id} = {value}")
                self._send(self._param_value(msg.param_id))

    # parameters: PX4 bytewise, ArduPilot C cast
    def _param_value(self, name: str, index: int | None = None):
        names = list(self._param_types)
        ptype = self._param_types[name]
        value = self.params[name]
        if ptype == _R32:
            wire = float(value)
        elif self.px4:
            wire = struct.unpack("<f", struct.pack("<i", int(value)))[0]
        else:
            wire = float(int(value))
        idx = names.index(name) if index is None else index
        return self.link.mav.param_value_encode(name.encode(), wire, ptype, len(names), idx)

    def _decode_param(self, wire: float, ptype: int):
        if ptype == _R32:
            return float(wire) if math.isfinite(wire) else None
        if self.px4:
            return struct.unpack("<i", struct.pack("<f", wire))[0]
        return int(round(wire)) if math.isfinite(wire) else None

    # -- SET_POSITION_TARGET_LOCAL_NED -------------------------------------------------------
    def _on_setpoint(self, msg) -> None:
        """SET_POSITION_TARGET_LOCAL_NED: x/y/z m, vx/vy/vz m/s, afx/afy/afz m/s^2, yaw rad and
        yaw_rate rad/s in the message's coordinate_frame (the module docstring, "Setpoints")."""
        if not self._for_me(msg.target_system, msg.target_component):
            self.foreign_setpoints += 1
            return
        if self.px4:
            self._px4_local_setpoint(msg)
        else:
            self._ardu_local_setpoint(msg)

    @staticmethod
    def _local_setpoint_ned(msg) -> np.ndarray:
        """The three vectors of a SET_POSITION_TARGET_LOCAL_NED as sent: rows position (m),
        velocity (m/s), acceleration (m/s^2), columns x/y/z of the message's frame."""
        return np.array([[msg.x, msg.y, msg.z], [msg.vx, msg.vy, msg.vz], [msg.afx, msg.afy, msg.afz]], dtype=float)

    @staticmethod
    def _yaw_fields_used(msg) -> tuple[float | None, float | None]:
        """The message's yaw (rad) and yaw rate (rad/s), NED, each None when its type_mask bit
        (YAW_IGNORE, YAW_RATE_IGNORE) is set."""
        mask = int(msg.type_mask)
        yaw = None if mask & _M.POSITION_TARGET_TYPEMASK_YAW_IGNORE else float(msg.yaw)
        rate = None if mask & _M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE else float(msg.yaw_rate)
        return yaw, rate

    def _px4_local_setpoint(self, msg) -> None:
        """PX4 ``mavlink_receiver.cpp`` ``handle_message_set_position_target_local_ned``.

        MAV_FRAME_LOCAL_NED: every component on its own (an ignored one is NaN). MAV_FRAME_BODY_NED:
        the position is never used (NaN whatever the mask); velocity and acceleration are each
        used only when none of their three ignore bits is set; the velocity's x/y are rotated by
        the vehicle's heading (``Eulerf(R)(2)``) and its z kept (down), the acceleration is
        rotated by the whole attitude (``R * acceleration_body_sp``). The yaw is absolute in
        both frames and the yaw rate is the offboard yawspeed. Any other frame is dropped with
        "SET_POSITION_TARGET_LOCAL_NED coordinate frame N unsupported", an acceleration marked as
        force with "... force not supported", a message with nothing used with "... invalid"
        (none of them refreshes the offboard signal)."""
        mask = int(msg.type_mask)
        frame = int(msg.coordinate_frame)
        ned = self._local_setpoint_ned(msg)
        if frame == _M.MAV_FRAME_LOCAL_NED:
            used = np.array([[not mask & b for b in row] for row in _AXIS_BITS])
        elif frame == _M.MAV_FRAME_BODY_NED:
            vel_used = not mask & (_AXIS_BITS[1][0] | _AXIS_BITS[1][1] | _AXIS_BITS[1][2])
            acc_used = not mask & (_AXIS_BITS[2][0] | _AXIS_BITS[2][1] | _AXIS_BITS[2][2])
            used = np.array([[False] * 3, [vel_used] * 3, [acc_used] * 3])
            ned[1] = self._local_ned_from_heading_frame(ned[1])
            ned[2] = self._attitude_ned_frd() @ ned[2]
        else:
            self._statustext(_M.MAV_SEVERITY_CRITICAL, f"SET_POSITION_TARGET_LOCAL_NED coordinate frame {frame} unsupported")
            return
        if used[2].any() and mask & _M.POSITION_TARGET_TYPEMASK_FORCE_SET:
            self._statustext(_M.MAV_SEVERITY_CRITICAL, "SET_POSITION_TARGET_LOCAL_NED force not supported")
            return
        if not used.any():
            self._statustext(_M.MAV_SEVERITY_CRITICAL, "SET_POSITION_TARGET_LOCAL_NED invalid")
            return
        yaw, rate = self._yaw_fields_used(msg)
        if not np.all(np.isfinite(ned[used])) or not _finite_or_unused(yaw, rate):
            return  # non-finite values the model cannot fly: dropped
        rows, used_enu = self._setpoint_rows(ned, used)
        rows[0] = None if rows[0] is None else self.scene_from_local(rows[0])
        self._accept_setpoint(rows, used_enu, **self._px4_yaw_fields(yaw, rate))

    def _px4_yaw_fields(self, yaw_ned: float | None, rate_ned: float | None) -> dict:
        """The :class:`_Target` yaw fields of a PX4 offboard setpoint: the yaw (absolute, NED in
        the estimator frame) and the yawspeed, which ``PositionControl::update`` turns into a
        yaw held where it is (yaw NaN) and a feed-forward rate the attitude controller adds to
        its heading correction (``AttitudeControl::update``)."""
        return {"yaw": None if yaw_ned is None else self._setpoint_yaw(yaw_ned),
                "yaw_rate": None if rate_ned is None else frames.yaw_rate_enu_from_ned(rate_ned)}

    def _ardu_local_setpoint(self, msg) -> None:
        """ArduCopter ``GCS_MAVLINK_Copter::handle_message_set_position_target_local_ned``.

        Ignored outside GUIDED. Frames LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED and BODY_OFFSET_NED;
        any other (BODY_FRD too) stops (``ModeGuided::init(true)``). Whole vectors (any set bit
        ignores a vector). In BODY_NED and BODY_OFFSET_NED the x/y of position, velocity and
        acceleration are rotated by the heading (``ahrs.body_to_earth2D``); in every frame but
        LOCAL_NED the position is offset by the current position from the EKF origin (without a
        position estimate: stop), so BODY_NED positions are offsets too; velocities are never
        offset. The yaw is relative in the two body frames. Then as the global message: pos+vel
        (+acc) a pos/vel/accel target, vel (+acc), acc only, pos only; anything else, a force
        setpoint or an insane velocity (``sane_vel_or_acc_vector``) stops."""
        if self.custom_mode != ARDUCOPTER_MODE["guided"]:
            return  # in_guided_mode(): GUIDED (AUTO's NAV_GUIDED items are not modelled)
        frame = int(msg.coordinate_frame)
        if frame not in _ARDU_LOCAL_FRAMES:
            return self._ardu_stop(f"unsupported coordinate frame {frame}")
        mask = int(msg.type_mask)
        pos_used, vel_used, acc_used = _ardu_vectors_used(mask)
        if mask & _M.POSITION_TARGET_TYPEMASK_FORCE_SET and acc_used:
            return self._ardu_stop("force setpoint")
        ned = self._local_setpoint_ned(msg)
        body = frame in _BODY_FRAMES
        if body:
            ned = self._local_ned_from_heading_frame(ned)
        if pos_used and frame != _M.MAV_FRAME_LOCAL_NED:
            if not self._position_valid:
                return self._ardu_stop("no position estimate for an offset target")
            ned[0] = ned[0] + self._local_ned()[0]
        if vel_used and not (np.all(np.isfinite(ned[1])) and np.all(np.abs(ned[1]) <= 1000.0)):
            return self._ardu_stop("velocity not sane")
        yaw, rate = self._yaw_fields_used(msg)
        used_rows = np.array([pos_used, vel_used, acc_used])
        if not np.all(np.isfinite(ned[used_rows])) or not _finite_or_unused(yaw, rate):
            return  # non-finite values the model cannot fly: dropped
        if not (vel_used or pos_used != acc_used):
            return self._ardu_stop("unsupported type_mask combination")  # pos+acc without vel, or nothing
        used = np.repeat(used_rows[:, None], 3, axis=1)
        rows, used_enu = self._setpoint_rows(ned, used)
        rows[0] = None if rows[0] is None else self.scene_from_local(rows[0])
        self._accept_setpoint(rows, used_enu, **self._ardu_yaw_fields(yaw, rate, relative=body))

    def _local_ned_from_heading_frame(self, vectors) -> np.ndarray:
        """Vectors (..., 3) in the vehicle's heading frame (x forward, y right, z down: the
        BODY_NED / BODY_OFFSET_NED axes of both autopilots) as NED vectors of the estimator's
        frame: x/y rotated by the current heading, z unchanged (PX4 ``Eulerf(R)(2)``, ArduPilot
        ``AP_AHRS::body_to_earth2D``)."""
        heading_local_enu = wrap_angle(self.model.yaw - self.c.estimator_yaw_rad)
        return frames.ned_from_enu(frames.flu_from_frd(vectors) @ _rot_z(heading_local_enu).T)

    def _attitude_ned_frd(self) -> np.ndarray:
        """Body attitude (3, 3) rotating FRD vectors into the estimator's NED frame (what
        ATTITUDE / ATTITUDE_QUATERNION report)."""
        return frames.R_ENU_NED @ self._R_scene_est.T @ self.model.R_enu_flu() @ frames.R_FLU_FRD

    def _ardu_yaw_fields(self, yaw_ned: float | None, rate_ned: float | None, relative: bool = False) -> dict:
        """The :class:`_Target` yaw fields of an ArduCopter GUIDED target (``ModeGuided::set_yaw_state_rad``
        and the ``AutoYaw`` mode it sets; yaw rad and rate rad/s, NED): a relative yaw (the body
        frames) is a fixed yaw ``set_fixed_yaw_rad`` adds to AutoYaw's current angle and slews to
        at ATC_SLEW_YAW, the rate unused; an absolute yaw with a rate is ANGLE_RATE, a yaw target
        that advances at the rate from now on; a yaw alone is that heading (ANGLE_RATE at rate
        0); a rate alone is RATE, a turn at the rate capped at ATC_SLEW_YAW
        (``AC_AttitudeControl::input_thrust_vector_rate_heading_rads``); neither is the default
        yaw mode (here: the heading held). ANGLE_RATE's target advances at the rate as sent: the
        source caps only its feed-forward (``input_thrust_vector_heading_rad``), and the heading
        correction makes up the rest."""
        slew = math.radians(float(self.params["ATC_SLEW_YAW"]) / 100.0)
        if yaw_ned is not None and relative:
            return {"yaw": wrap_angle(self._ardu_auto_yaw_angle() - yaw_ned), "yaw_rate_limit_radps": slew}  # NED + is clockwise
        rate = None if rate_ned is None else float(frames.yaw_rate_enu_from_ned(rate_ned))
        if yaw_ned is None:
            return {} if rate is None else {"yaw_rate": float(np.clip(rate, -slew, slew))}
        if rate is None:
            return {"yaw": self._setpoint_yaw(yaw_ned)}
        return {"yaw": self._setpoint_yaw(yaw_ned), "yaw_rate": rate, "yaw_t_s": self.clock()}

    def _ardu_auto_yaw_angle(self) -> float:
        """AutoYaw's yaw angle (rad, scene ENU), which a relative yaw is added to
        (``AutoYaw::set_fixed_yaw_rad``): the absolute heading target being flown (moved on to
        now), else the current heading (HOLD, RATE and the default modes follow the heading; a
        fixed yaw still slewing is where the heading has got to)."""
        t = self._target
        if t is not None and t.yaw is not None and t.yaw_rate_limit_radps is None:
            return float(t.at(self.clock()).yaw)
        return float(self.model.yaw)

    def _setpoint_rows(self, ned: np.ndarray, used: np.ndarray):
        """The used rows of a setpoint (rows p, v, a; NED columns) as ENU vectors, and which ENU
        axes are used. Velocity and acceleration rows come out in scene axes (they are in the
        estimator's NED frame in both SET_POSITION_TARGET messages); the position row stays in
        the estimator's local ENU frame (the caller places it). A partial x/y selection under a
        rotated estimator frame keeps both horizontal axes."""
        used_enu = used[:, [1, 0, 2]]  # NED column order (N, E, D) -> ENU (E, N, U)
        vals = frames.enu_from_ned(np.where(used, ned, 0.0))
        rows = []
        for k in range(3):
            if not used_enu[k].any():
                rows.append(None)
            else:
                rows.append(vals[k] if k == 0 else vals[k] @ self._R_scene_est.T)
        return rows, used_enu

    def _setpoint_yaw(self, yaw_ned: float) -> float:
        """A setpoint's yaw (radians, NED heading in the estimator frame) as the scene's ENU yaw."""
        return wrap_angle(float(frames.yaw_enu_from_ned(yaw_ned)) + self.c.estimator_yaw_rad)

    def _accept_setpoint(self, rows, used_enu, yaw=None, **yaw_fields) -> None:
        """A setpoint the autopilot takes (``yaw`` and ``yaw_fields``: the :class:`_Target` yaw
        fields). PX4: an offboard setpoint (it refreshes the COM_OF_LOSS_T signal, allows arming
        and entering OFFBOARD, and is flown in OFFBOARD). ArduCopter: the GUIDED target when
        armed and not taking off."""
        t = self.clock()
        with self._lock:
            target = self._resolve(rows, used_enu, yaw, **yaw_fields)
            self._last_sp_s = t
            self.setpoints_received += 1
            self.setpoint_times.append(t)
            if self.px4:
                self._setpoint = target
            elif self.custom_mode == ARDUCOPTER_MODE["guided"] and self.armed and self._takeoff_alt_m is None:
                if target.kind != "position":
                    self._ardu_speed_ne_mps = None  # a new submode: pva_control_start restores WPNAV_SPEED
                self._setpoint = target
                self._guided_timed_out = False

    # -- SET_POSITION_TARGET_GLOBAL_INT ------------------------------------------------------
    def _on_global_setpoint(self, msg) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT: lat/lon in degE7, alt in metres in the message's
        frame, velocity / acceleration in NED (m/s, m/s^2), yaw in radians (NED)."""
        if not self._for_me(msg.target_system, msg.target_component):
            self.foreign_setpoints += 1
            return
        if self.px4:
            self._px4_global_setpoint(msg)
        else:
            self._ardu_global_setpoint(msg)

    def _px4_global_setpoint(self, msg) -> None:
        """PX4 ``mavlink_receiver.cpp`` ``handle_message_set_position_target_global_int``.

        Position is all or nothing (any of the x/y/z ignore bits drops it); velocity and
        acceleration are per axis (NaN when ignored), as for LOCAL_NED. A used position needs a
        global position estimate (``local_pos.xy_global && z_global``), else the message is
        dropped whole, so it is no offboard signal either. Frames: GLOBAL_INT = AMSL;
        GLOBAL_RELATIVE_ALT_INT needs a home altitude and computes the local down coordinate as
        ``(home.alt - alt) - ref_alt`` (written so in the source: the altitude above home when
        home is at the estimator origin's altitude, as here unless they differ);
        GLOBAL_TERRAIN_ALT_INT needs ``terrain_alt_valid`` (a distance sensor: none here ->
        dropped); any other frame (the non-INT GLOBAL frames too) is dropped with "invalid
        coordinate frame". A force setpoint is dropped with "force not supported"."""
        mask = int(msg.type_mask)
        p_scene = None
        if not mask & _POS_BITS:
            if self.c.global_origin is None or not self._position_valid:
                return  # no global reference: the setpoint cannot be converted
            frame = int(msg.coordinate_frame)
            alt = float(msg.alt)
            ref_amsl = self._global_from_scene(self._origin)[2]  # local_pos.ref_alt: the estimator origin
            if frame == _M.MAV_FRAME_GLOBAL_INT:
                amsl = alt
            elif frame == _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
                if self._home is None:
                    return  # home altitude required
                home_amsl = self._global_from_scene(self._home)[2]
                amsl = ref_amsl - ((home_amsl - alt) - ref_amsl)  # up = -z, z = (home - alt) - ref
            elif frame == _M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT:
                return  # valid terrain altitude required: no distance sensor in this model
            else:
                self._statustext(_M.MAV_SEVERITY_CRITICAL, f"SET_POSITION_TARGET_GLOBAL_INT invalid coordinate frame {frame}")
                return
            if not math.isfinite(amsl):
                return
            p_scene = self._scene_from_global(msg.lat_int * 1e-7, msg.lon_int * 1e-7, amsl)
        ned = np.array([[0.0, 0.0, 0.0], [msg.vx, msg.vy, msg.vz], [msg.afx, msg.afy, msg.afz]], dtype=float)
        used = np.array([[not mask & b for b in row] for row in _AXIS_BITS])
        used[0, :] = p_scene is not None
        yaw, rate = self._yaw_fields_used(msg)
        if used[2].any() and mask & _M.POSITION_TARGET_TYPEMASK_FORCE_SET:
            self._statustext(_M.MAV_SEVERITY_CRITICAL, "SET_POSITION_TARGET_GLOBAL_INT force not supported")
            return
        if not used.any() or not np.all(np.isfinite(ned[1:][used[1:]])) or not _finite_or_unused(yaw, rate):
            return
        rows, used_enu = self._setpoint_rows(ned, used)
        rows[0] = p_scene
        self._accept_setpoint(rows, used_enu, **self._px4_yaw_fields(yaw, rate))

    def _ardu_global_setpoint(self, msg) -> None:
        """ArduCopter ``GCS_MAVLINK_Copter::handle_message_set_position_target_global_int``.

        Ignored outside GUIDED. Whole vectors (any set bit ignores the vector). Refusals that
        "stop" call ``ModeGuided::init(true)``: velocity control with a zero target (the vehicle
        brakes and hovers): a force setpoint, lat/lon out of range (``check_latlng``), a frame
        ``mavlink_coordinate_frame_to_location_alt_frame`` does not know (GLOBAL / GLOBAL_INT
        AMSL, GLOBAL_RELATIVE_ALT(_INT) above home, GLOBAL_TERRAIN_ALT(_INT) above terrain), an
        insane velocity (``sane_vel_or_acc_vector``: non-finite or > 1000 m/s), position +
        velocity above terrain or without an EKF origin, position + acceleration without
        velocity, nothing used. Position + velocity: a pos/vel target (the acceleration is not
        passed on). Position only: ``ModeGuided::set_destination(Location)``, which returns
        before changing anything when the location has no vector from the EKF origin (no origin,
        or above home without home): the message is ignored and the last target kept; above
        terrain it enters the position submode and, without terrain data (no rangefinder or
        terrain database here), stops."""
        if self.custom_mode != ARDUCOPTER_MODE["guided"]:
            return  # in_guided_mode(): GUIDED (AUTO's NAV_GUIDED items are not modelled)
        mask = int(msg.type_mask)
        pos_used, vel_used, acc_used = _ardu_vectors_used(mask)
        if mask & _M.POSITION_TARGET_TYPEMASK_FORCE_SET and acc_used:
            return self._ardu_stop("force setpoint")
        frame = int(msg.coordinate_frame)
        alt_frame = _ARDU_ALT_FRAME.get(frame)
        if pos_used:
            if not (abs(int(msg.lat_int)) <= 900000000 and abs(int(msg.lon_int)) <= 1800000000):
                return self._ardu_stop("lat/lon out of range")
            if alt_frame is None:
                return self._ardu_stop(f"unknown coordinate frame {frame}")
        v_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if vel_used and not (np.all(np.isfinite(v_ned)) and np.all(np.abs(v_ned) <= 1000.0)):
            return self._ardu_stop("velocity not sane")
        a_ned = np.array([msg.afx, msg.afy, msg.afz], dtype=float)
        yaw_ned, rate_ned = self._yaw_fields_used(msg)
        if (acc_used and not np.all(np.isfinite(a_ned))) or not _finite_or_unused(yaw_ned, rate_ned):
            return  # non-finite values the model cannot fly: dropped (as for LOCAL_NED)
        yaw_fields = self._ardu_yaw_fields(yaw_ned, rate_ned)
        v = frames.enu_from_ned(v_ned) @ self._R_scene_est.T
        a = frames.enu_from_ned(a_ned) @ self._R_scene_est.T
        every = np.ones(3, dtype=bool)
        none = np.zeros(3, dtype=bool)
        if pos_used and vel_used:
            if alt_frame == "terrain":
                return self._ardu_stop("pos/vel target above terrain")
            p = self._ardu_location_scene(msg.lat_int, msg.lon_int, msg.alt, alt_frame)
            if p is None:
                return self._ardu_stop("no vector from the EKF origin")
            self._accept_setpoint([p, v, None], np.array([every, every, none]), **yaw_fields)
        elif vel_used:
            self._accept_setpoint([None, v, a if acc_used else None], np.array([none, every, every if acc_used else none]), **yaw_fields)
        elif acc_used and not pos_used:
            self._accept_setpoint([None, None, a], np.array([none, none, every]), **yaw_fields)
        elif pos_used and not acc_used:
            if alt_frame == "terrain":
                if self._ardu_location_scene(msg.lat_int, msg.lon_int, 0.0, "absolute") is None:
                    return  # get_vector_NEU_cm: no EKF origin -> set_destination returns, nothing changes
                return self._ardu_stop("no terrain data for an above-terrain target")
            p = self._ardu_location_scene(msg.lat_int, msg.lon_int, msg.alt, alt_frame)
            if p is None:
                self._event("guided: global target ignored (no vector from the EKF origin)")
                return
            self._accept_setpoint([p, None, None], np.array([every, none, none]), **yaw_fields)
        else:
            self._ardu_stop("unsupported type_mask combination")

    def _ardu_location_scene(self, lat_int: int, lon_int: int, alt_m: float, alt_frame: str) -> np.ndarray | None:
        """An ArduPilot ``Location`` (degE7, altitude in cm after ``int32_t(alt*100)``) as a scene
        point, or None when it has no vector from the EKF origin (no global origin or no position
        estimate; above home without home: ``Location::get_alt_cm``)."""
        if self.c.global_origin is None or not self._position_valid or not math.isfinite(alt_m):
            return None
        alt = int(alt_m * 100) / 100.0  # C cast: truncation toward zero, whole cm
        if alt_frame == "above_home":
            if not self._ardu_home_set():
                return None
            alt += self._global_from_scene(self._home)[2]
        return self._scene_from_global(int(lat_int) * 1e-7, int(lon_int) * 1e-7, alt)

    def _ardu_stop(self, why: str) -> None:
        """``ModeGuided::init(true)``: velocity control with a zero target (brake and hover), the
        speeds back at their defaults (``pva_control_start``). Applied where the model flies
        GUIDED targets (armed, take-off complete)."""
        self._event(f"guided: input not valid ({why}): stop")
        with self._lock:
            if self.armed and self._takeoff_alt_m is None:
                stop = _Target(v=np.zeros(3), yaw=self.model.yaw, kind="velocity")
                self._setpoint = self._target = stop
                self._ardu_speed_ne_mps = None
                self._guided_timed_out = True  # already stopped: no separate GUID_TIMEOUT event

    def _resolve(self, rows, used_enu, yaw=None, **yaw_fields) -> _Target:
        """A setpoint's used rows as a controller target; mixed per-axis PX4 setpoints become
        one velocity command (position axes through the position gain)."""
        p, v, a = rows
        whole = [r is None or used_enu[k].all() for k, r in enumerate(rows)]
        if all(whole):
            kind = "position" if (p is not None and v is None and a is None) else (
                "full" if p is not None else ("velocity" if v is not None else "acceleration"))
            return _Target(p=p, v=v, a=a, yaw=yaw, kind=kind, **yaw_fields)
        pos = self.model.p
        v_cmd = np.zeros(3)
        for i in range(3):
            if p is not None and used_enu[0, i]:
                v_cmd[i] = self.c.k_pos * (p[i] - pos[i]) + (v[i] if v is not None and used_enu[1, i] else 0.0)
            elif v is not None and used_enu[1, i]:
                v_cmd[i] = v[i]
        return _Target(v=v_cmd, yaw=yaw, kind="velocity", **yaw_fields)

    def _on_command(self, msg, is_int: bool) -> int:
        cmd = int(msg.command)
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        if is_int:
            x, y, z = int(msg.x), int(msg.y), float(msg.z)
            frame = int(msg.frame)
        else:
            x, y, z = msg.param5, msg.param6, msg.param7
            frame = _M.MAV_FRAME_GLOBAL
        if cmd == _M.MAV_CMD_COMPONENT_ARM_DISARM:
            force = math.isfinite(p[1]) and int(round(p[1])) == _FORCE_DISARM_MAGIC
            if not math.isfinite(p[0]):
                return _M.MAV_RESULT_DENIED
            return self._cmd_arm(p[0] >= 0.5, force)
        if cmd == _M.MAV_CMD_DO_SET_MODE:
            return self._cmd_set_mode(p[0], p[1], p[2])
        if cmd == _M.MAV_CMD_NAV_TAKEOFF:
            return self._cmd_takeoff(float(z))
        if cmd == _M.MAV_CMD_NAV_LAND:
            return self._cmd_land()
        if cmd == _M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._cmd_return_to_launch()
        if cmd == _M.MAV_CMD_DO_REPOSITION:
            if not is_int:
                return _M.MAV_RESULT_DENIED  # lat/lon need COMMAND_INT's integer fields
            return self._cmd_reposition(p, x, y, z, frame)
        if cmd == _M.MAV_CMD_DO_CHANGE_SPEED:
            return self._cmd_change_speed(p)
        if cmd == _M.MAV_CMD_DO_SET_HOME:
            return self._cmd_set_home(p, msg, is_int)
        if cmd == _M.MAV_CMD_CONDITION_YAW and not self.px4:  # PX4: no handler outside missions (Commander: UNSUPPORTED)
            return self._cmd_condition_yaw(p)
        if cmd == _M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            return self._cmd_reboot(p)
        if cmd == _M.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._cmd_interval(p[0], p[1])
        if cmd == _M.MAV_CMD_REQUEST_MESSAGE:
            return self._cmd_request(p[0])
        if cmd == _M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._cmd_request(_M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        if cmd == _M.MAV_CMD_GET_HOME_POSITION:
            return self._cmd_request(_M.MAVLINK_MSG_ID_HOME_POSITION)
        return _M.MAV_RESULT_UNSUPPORTED

    def _prearm_failure(self) -> str | None:
        """Why arming is refused now, or None."""
        if not self._position_valid:
            return "Need Position Estimate" if not self.px4 else "Preflight Fail: No valid position"
        if self.px4:
            main = px4_main_mode(self.custom_mode)
            if self.custom_mode in (px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["land"]), px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["rtl"])):
                return f"Arming denied: {self.mode_name} mode prevents arming"
            if main == PX4_MAIN["offboard"] and not self._recent_setpoint():
                return "Arming denied: no offboard signal"
            return self.fence.prearm_failure()  # geofenceCheck.cpp: a breach is an arming-check failure
        if self.custom_mode in (ARDUCOPTER_MODE["land"], ARDUCOPTER_MODE["rtl"], ARDUCOPTER_MODE["brake"], ARDUCOPTER_MODE["auto"]):
            return f"Arm: Mode not armable ({self.mode_name.upper()})"
        if self.custom_mode in (ARDUCOPTER_MODE["loiter"], ARDUCOPTER_MODE["alt_hold"]) and self._ardu_pilot_climb_rate() > 0:
            return "Arm: Throttle too high"  # AP_Arming_Copter::arm_checks: above the deadband is too high
        return self.fence.prearm_failure()  # AP_Arming::fence_checks -> AC_Fence::pre_arm_check

    def _cmd_arm(self, arm: bool, force: bool) -> int:
        if arm:
            if self.armed:
                return _M.MAV_RESULT_ACCEPTED
            why = None if force else self._prearm_failure()
            if why is not None:
                self._event(f"arming refused: {why}")
                self._statustext(_M.MAV_SEVERITY_CRITICAL, why)
                return _M.MAV_RESULT_FAILED
            self.armed = True
            self._armed_at = self.clock()
            self._flying_since_arm = not self.model.on_ground
            if not self._home_manual:  # a DO_SET_HOME home is kept (PX4 manual_home, ArduPilot locked)
                self._home = self.model.p.copy()
            self._event("armed")
            self._statustext(_M.MAV_SEVERITY_INFO, "Armed")
            takeoff = self.px4 and self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["takeoff"])
            if takeoff and self._takeoff_alt_m is not None:
                self._target = _Target(p=np.array([*self.model.p[:2], self._takeoff_alt_m]), yaw=self.model.yaw,
                                       v_limit_mps=float(self.params["MPC_TKO_SPEED"]))
            elif not (self.px4 and px4_main_mode(self.custom_mode) == PX4_MAIN["offboard"]):
                self._target = self._hold_here()
            return _M.MAV_RESULT_ACCEPTED
        if self.armed and not self.model.on_ground and not force:
            return _M.MAV_RESULT_DENIED
        if self.armed:
            self._disarm("commanded")
        return _M.MAV_RESULT_ACCEPTED

    def _recent_setpoint(self) -> bool:
        loss_t = float(self.params["COM_OF_LOSS_T"]) if self.px4 else float(self.params["GUID_TIMEOUT"])
        return self._last_sp_s is not None and self.clock() - self._last_sp_s <= loss_t

    def _cmd_set_mode(self, base_mode: float, mode: float, sub: float, legacy: bool = False) -> int:
        if not (math.isfinite(base_mode) and math.isfinite(mode)) or not int(base_mode) & _M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return _M.MAV_RESULT_DENIED
        if self.px4:
            if legacy:  # SET_MODE carries the whole custom_mode
                main, sub_i = px4_main_mode(int(mode)), (int(mode) >> 24) & 0xFF
            else:
                main, sub_i = int(mode), int(sub) if math.isfinite(sub) else 0
            if main not in PX4_MAIN.values() or (main == PX4_MAIN["auto"] and sub_i not in PX4_AUTO_SUB.values()):
                return _M.MAV_RESULT_DENIED
            if main == PX4_MAIN["offboard"] and not self._recent_setpoint():
                self._event("offboard refused: no recent setpoint")
                self._statustext(_M.MAV_SEVERITY_CRITICAL, "Switching to Offboard is currently not available")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            needs_position = main in (PX4_MAIN["posctl"], PX4_MAIN["offboard"]) or (
                main == PX4_MAIN["auto"] and sub_i in (PX4_AUTO_SUB["loiter"], PX4_AUTO_SUB["land"], PX4_AUTO_SUB["takeoff"], PX4_AUTO_SUB["mission"]))
            if needs_position and not self._position_valid:
                self._statustext(_M.MAV_SEVERITY_CRITICAL, "Mode not available: no position estimate")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            if main == PX4_MAIN["auto"] and sub_i == PX4_AUTO_SUB["rtl"] and not self._px4_mode_available("rtl"):
                self._statustext(_M.MAV_SEVERITY_CRITICAL, "Switching to Return is currently not available")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            if main in (PX4_MAIN["manual"], PX4_MAIN["altctl"], PX4_MAIN["stabilized"], PX4_MAIN["acro"], PX4_MAIN["posctl"]) and not self._manual_control_present():
                self._statustext(_M.MAV_SEVERITY_CRITICAL, "Mode not available: no manual control")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            refused = self.mission.refuse_mode(px4_custom_mode(main, sub_i if main == PX4_MAIN["auto"] else 0))
            if refused is not None:
                return refused
            self._set_mode(px4_custom_mode(main, sub_i if main == PX4_MAIN["auto"] else 0), "commanded")
            return _M.MAV_RESULT_ACCEPTED
        number = int(mode)
        if number not in ARDUCOPTER_MODE.values():
            return _M.MAV_RESULT_DENIED
        if number in (ARDUCOPTER_MODE["guided"], ARDUCOPTER_MODE["loiter"], ARDUCOPTER_MODE["rtl"], ARDUCOPTER_MODE["auto"], ARDUCOPTER_MODE["brake"]) and not self._position_valid:
            self._statustext(_M.MAV_SEVERITY_CRITICAL, "Flight mode change failed: requires position")
            return _M.MAV_RESULT_FAILED
        if number == ARDUCOPTER_MODE["rtl"] and self.armed and not self._ardu_home_set():
            # ModeRTL::init: home_is_set (checked armed; Copter::set_mode ignores checks disarmed)
            self._statustext(_M.MAV_SEVERITY_WARNING, "Mode change to RTL failed: init failed")
            return _M.MAV_RESULT_FAILED
        refused = self.mission.refuse_mode(number)
        if refused is not None:
            return refused
        self._set_mode(number, "commanded")
        return _M.MAV_RESULT_ACCEPTED

    def _ardu_home_set(self) -> bool:
        """ArduPilot's home is a location: set at arming only with a global position."""
        return self._home is not None and self.c.global_origin is not None

    def _cmd_return_to_launch(self) -> int:
        """MAV_CMD_NAV_RETURN_TO_LAUNCH: a switch to the Return mode (PX4 Commander
        ``VEHICLE_CMD_NAV_RETURN_TO_LAUNCH``: "Returning to launch" or TEMPORARILY_REJECTED with
        ``printRejectMode``; ArduCopter ``GCS_Mavlink.cpp``: ``set_mode(RTL)`` or FAILED)."""
        if self.px4:
            if not self._px4_mode_available("rtl"):
                self._statustext(_M.MAV_SEVERITY_CRITICAL, "Switching to Return is currently not available")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            self._statustext(_M.MAV_SEVERITY_INFO, "Returning to launch")
            self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["rtl"]), "NAV_RETURN_TO_LAUNCH")
            return _M.MAV_RESULT_ACCEPTED
        return self._cmd_set_mode(float(_M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(ARDUCOPTER_MODE["rtl"]), math.nan)

    def _cmd_takeoff(self, alt: float) -> int:
        m = self.model
        if self.px4:
            # Commander: a user-intended switch to AUTO.TAKEOFF, accepted whenever the mode can
            # run (armed or not; a disarmed vehicle climbs once armed), else TEMPORARILY_REJECTED
            if not self._position_valid:
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            home_z = (self._home if self._home is not None else m.p)[2]
            if math.isfinite(alt):
                if self.c.global_origin is None:
                    return _M.MAV_RESULT_DENIED  # an AMSL altitude needs a global origin
                target_z = alt - self.c.global_origin[2]
            else:
                target_z = home_z + float(self.params["MIS_TAKEOFF_ALT"])
            if target_z <= m.p[2] + 0.1:
                return _M.MAV_RESULT_DENIED
            self._takeoff_alt_m = float(target_z)
            self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["takeoff"]), f"takeoff to {target_z:.2f} m")
            return _M.MAV_RESULT_ACCEPTED
        if not (math.isfinite(alt) and 0.2 <= alt <= 100.0):
            return _M.MAV_RESULT_DENIED
        if self.custom_mode != ARDUCOPTER_MODE["guided"] or not self.armed or not m.on_ground:
            return _M.MAV_RESULT_FAILED
        home_z = (self._home if self._home is not None else m.p)[2]
        self._takeoff_alt_m = float(home_z + alt)
        self._setpoint = None
        self._ardu_speed_ne_mps = None  # the TakeOff submode
        p = m.p.copy()
        p[2] = self._takeoff_alt_m
        self._target = _Target(p=p, yaw=m.yaw, v_limit_mps=float(self.params["WPNAV_SPEED_UP"]) / 100.0)
        self._event(f"takeoff to {alt:.2f} m above home")
        return _M.MAV_RESULT_ACCEPTED

    def _cmd_land(self) -> int:
        if not self.armed:
            return _M.MAV_RESULT_TEMPORARILY_REJECTED if self.px4 else _M.MAV_RESULT_FAILED
        if self.px4:
            if not self._position_valid:
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["land"]), "NAV_LAND")
        else:
            self._set_mode(ARDUCOPTER_MODE["land"], "NAV_LAND")
        return _M.MAV_RESULT_ACCEPTED

    def _cmd_reposition(self, p, x: int, y: int, z: float, frame: int) -> int:
        if self.c.global_origin is None or not self._position_valid:
            return _M.MAV_RESULT_FAILED
        if not self.armed:
            return _M.MAV_RESULT_TEMPORARILY_REJECTED if self.px4 else _M.MAV_RESULT_FAILED
        home_amsl = self._global_from_scene(self._home if self._home is not None else self.model.p)[2]
        if frame in (_M.MAV_FRAME_GLOBAL, _M.MAV_FRAME_GLOBAL_INT):
            alt = z
        elif frame in (_M.MAV_FRAME_GLOBAL_RELATIVE_ALT, _M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT):
            alt = home_amsl + z
        else:
            return _M.MAV_RESULT_DENIED
        cur = self.model.p
        if x == 0 and y == 0:  # lat/lon 0 means "keep" (MAVLink DO_REPOSITION)
            target = cur.copy()
        else:
            target = self._scene_from_global(x * 1e-7, y * 1e-7, alt if math.isfinite(alt) else 0.0)
        if not math.isfinite(alt):
            target[2] = cur[2]
        # param4 is the yaw: PX4's navigator copies it into the position setpoint's yaw, which is in
        # radians (navigator_main.cpp DO_REPOSITION: rep->current.yaw = cmd.param4; MAVSDK's
        # goto_location sends radians for it); for ArduCopter it stays in degrees (the MAVLink spec;
        # not checked against ArduCopter's handler)
        yaw_ned = (float(p[3]) if self.px4 else math.radians(p[3])) if math.isfinite(p[3]) else None
        yaw = None if yaw_ned is None else wrap_angle(math.pi / 2 - yaw_ned)
        speed = float(p[0]) if math.isfinite(p[0]) and p[0] > 0 else None
        change_mode = math.isfinite(p[1]) and int(p[1]) & _M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
        if self.px4:
            speed = self._px4_goto_speed(speed, self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]))
            if change_mode:
                self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]), "reposition")
            elif self.custom_mode != px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]):
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
        else:
            if self.custom_mode != ARDUCOPTER_MODE["guided"]:
                if not change_mode:
                    return _M.MAV_RESULT_FAILED
                self._set_mode(ARDUCOPTER_MODE["guided"], "reposition")
            self._setpoint = _Target(p=target, yaw=yaw, v_limit_mps=speed)
        self._target = _Target(p=target, yaw=yaw, v_limit_mps=speed)
        self._event(f"reposition to scene ({target[0]:.2f}, {target[1]:.2f}, {target[2]:.2f})")
        return _M.MAV_RESULT_ACCEPTED

    # -- home ---------------------------------------------------------------------------------
    def _cmd_set_home(self, p, msg, is_int: bool) -> int:
        """MAV_CMD_DO_SET_HOME (param1 1: here; else lat/lon/alt in param5-7 or COMMAND_INT x/y/z).

        PX4 (``Commander::handle_command`` VEHICLE_CMD_DO_SET_HOME, COM_HOME_EN 1): param1 > 0.5
        sets home here (``HomePosition::setHomePosition(true)``: needs a position estimate, else
        TEMPORARILY_REJECTED); otherwise lat, lon and alt must be finite (else DENIED; the receiver
        turns COMMAND_INT x/y = INT32_MAX into NaN and divides by 1e7; the altitude is AMSL, the
        frame is not read) and ``setManually`` needs a global position reference (``xy_global``
        and ``z_global``; indoors TEMPORARILY_REJECTED). ArduPilot
        (``GCS_MAVLINK::handle_command_do_set_home``): param1 1 or lat and lon both 0 sets home
        here (``set_home_to_current_location``: needs a location, else FAILED); otherwise
        ``location_from_command_t`` (a COMMAND_LONG is converted with MAV_FRAME_GLOBAL, AMSL,
        by ``try_command_long_as_command_int``; an unknown frame or NaN altitude DENIED) and
        ``set_home`` (no EKF origin, an above-home altitude without home, an above-terrain one
        without terrain data, lat/lon out of range or more than 50 km from the EKF origin
        (``far_from_EKF_origin``): FAILED), then HOME_POSITION is sent (MSG_HOME). A home set so
        is kept at arming (PX4 ``manual_home``; ArduPilot sets it locked) and is what Return,
        the geofence and GLOBAL_POSITION_INT's relative altitude read."""
        use_current_req = math.isfinite(p[0]) and p[0] > 0.5 if self.px4 else (math.isfinite(p[0]) and p[0] == 1.0)
        if is_int:
            xi, yi, alt = int(msg.x), int(msg.y), float(msg.z)
            frame = int(msg.frame)
            lat = lon = math.nan if (xi == 2**31 - 1 and yi == 2**31 - 1) else None
            if lat is None:
                lat, lon = xi * 1e-7, yi * 1e-7
        else:
            lat, lon, alt = float(msg.param5), float(msg.param6), float(msg.param7)
            frame = _M.MAV_FRAME_GLOBAL  # try_command_long_as_command_int: DO_SET_HOME is absolute
            xi = int(lat * 1e7) if math.isfinite(lat) else 0
            yi = int(lon * 1e7) if math.isfinite(lon) else 0
        if self.px4:
            if use_current_req:
                if not self._position_valid:
                    return _M.MAV_RESULT_TEMPORARILY_REJECTED
                home = self.model.p.copy()
            else:
                if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
                    return _M.MAV_RESULT_DENIED
                if self.c.global_origin is None or not self._position_valid:
                    return _M.MAV_RESULT_TEMPORARILY_REJECTED
                home = self._scene_from_global(lat, lon, alt)
        else:
            if use_current_req or (xi == 0 and yi == 0):
                if self.c.global_origin is None or not self._position_valid:
                    return _M.MAV_RESULT_FAILED  # ahrs.get_location: no location
                home = self.model.p.copy()
            else:
                alt_frame = _ARDU_ALT_FRAME.get(frame)
                if alt_frame is None or not math.isfinite(alt):
                    return _M.MAV_RESULT_DENIED
                if alt_frame == "terrain" or not (abs(xi) <= 900000000 and abs(yi) <= 1800000000):
                    return _M.MAV_RESULT_FAILED
                home = self._ardu_location_scene(xi, yi, alt, alt_frame)
                if home is None:
                    return _M.MAV_RESULT_FAILED
                if float(np.linalg.norm(home[:2] - self._origin[:2])) > 50000.0:
                    return _M.MAV_RESULT_FAILED  # far_from_EKF_origin (EKF_ORIGIN_MAX_DIST_M)
        self._home = np.array(home, dtype=float)
        self._home_manual = True
        self._event(f"home set to scene ({home[0]:.2f}, {home[1]:.2f}, {home[2]:.2f})")
        if not self.px4:
            msg_home = self._telemetry(_M.MAVLINK_MSG_ID_HOME_POSITION, streaming=False)
            if msg_home is not None:
                self._pending.append(msg_home)
        return _M.MAV_RESULT_ACCEPTED

    # -- speed, yaw and reboot commands (what MAVSDK's Action plugin and MAVProxy send) --------
    def _px4_goto_speed(self, commanded: float | None, in_loiter: bool) -> float:
        """Horizontal speed (m/s) of a PX4 reposition: its param1 if > 0; else, when the
        navigator is already in Loiter, the DO_CHANGE_SPEED cruising speed; else (entering
        Loiter resets it) MPC_XY_CRUISE; always capped at MPC_XY_VEL_MAX (``navigator_main.cpp``
        DO_REPOSITION ``cruising_speed``; ``FlightTaskAuto`` cruise speed)."""
        if commanded is not None:
            speed = commanded
        elif in_loiter and self._px4_cruise_mps is not None:
            speed = self._px4_cruise_mps
        else:
            speed = float(self.params["MPC_XY_CRUISE"])
        return min(speed, float(self.params["MPC_XY_VEL_MAX"]))

    def _cmd_change_speed(self, p) -> int:
        """MAV_CMD_DO_CHANGE_SPEED outside a mission (param1 speed type, param2 m/s).

        PX4 (``navigator_main.cpp``): always ACCEPTED; param2 > 0 sets the navigator's cruising
        speed, anything else resets it to the default; the next reposition made in Hold uses it
        (a goto under way keeps its speed). ArduCopter (``GCS_MAVLINK_Copter::
        handle_MAV_CMD_DO_CHANGE_SPEED``): param2 <= 0 or an unknown type DENIED; air/ground speed
        goes to the mode's ``set_speed_NE_ms``: GUIDED (the position controller's horizontal limit
        until the next submode change) and RTL (the waypoint leg) ACCEPTED, modes without it
        FAILED; climb / descent speed types are answered the same way."""
        kind, speed = p[0], p[1]
        if self.px4:
            self._px4_cruise_mps = float(speed) if math.isfinite(speed) and speed > 1e-6 else None
            self._event(f"cruising speed {'default' if self._px4_cruise_mps is None else f'{speed:.2f} m/s'}")
            return _M.MAV_RESULT_ACCEPTED
        if not (math.isfinite(speed) and speed > 0):
            return _M.MAV_RESULT_DENIED
        if not (math.isfinite(kind) and 0 <= int(kind) <= _M.SPEED_TYPE_DESCENT_SPEED):
            return _M.MAV_RESULT_DENIED
        if self.custom_mode not in (ARDUCOPTER_MODE["guided"], ARDUCOPTER_MODE["rtl"], ARDUCOPTER_MODE["auto"]):
            return _M.MAV_RESULT_FAILED  # Mode::set_speed_NE_ms / set_speed_up_ms / set_speed_down_ms: false
        if int(kind) in (_M.SPEED_TYPE_AIRSPEED, _M.SPEED_TYPE_GROUNDSPEED) and self.custom_mode != ARDUCOPTER_MODE["auto"]:
            self._ardu_speed_ne_mps = float(speed)
            self._event(f"horizontal speed {speed:.2f} m/s")
        return _M.MAV_RESULT_ACCEPTED

    def _ardu_limit(self, target: _Target) -> _Target:
        """A GUIDED position target under the DO_CHANGE_SPEED horizontal speed, if one is set."""
        if self._ardu_speed_ne_mps is None or target.kind != "position" or target.p is None:
            return target
        limit = self._ardu_speed_ne_mps if target.v_limit_mps is None else min(target.v_limit_mps, self._ardu_speed_ne_mps)
        return replace(target, v_limit_mps=limit)

    def _cmd_condition_yaw(self, p) -> int:
        """ArduCopter MAV_CMD_CONDITION_YAW (MAVProxy ``setyaw``): param1 heading 0..360 deg
        (compass, clockwise from north, in the estimator's heading frame), param2 deg/s (<= 0:
        ATC_SLEW_YAW), param3 direction (-1 ccw, +1 cw; 0 = cw for a relative angle), param4 0
        absolute / 1 relative, else FAILED (``GCS_MAVLINK_Copter::handle_MAV_CMD_CONDITION_YAW``
        -> ``AutoYaw::set_fixed_yaw_rad``). ACCEPTED in every mode; GUIDED turns to it and holds
        it until the next position/velocity target resets the yaw mode (``set_yaw_state_rad``).
        An absolute heading is turned the short way (the turn direction is not modelled)."""
        angle, rate, direction, relative = p[0], p[1], p[2], p[3]
        if not (math.isfinite(angle) and 0.0 <= angle <= 360.0 and math.isfinite(relative) and relative in (0.0, 1.0)):
            return _M.MAV_RESULT_FAILED
        slew = math.radians(float(self.params["ATC_SLEW_YAW"]) / 100.0)
        rate_rad = min(slew, math.radians(rate)) if math.isfinite(rate) and rate > 0 else slew
        if relative == 1.0:
            sign = -1.0 if math.isfinite(direction) and int(direction) < 0 else 1.0
            yaw = wrap_angle(self._ardu_auto_yaw_angle() - sign * math.radians(angle))  # clockwise (NED) is negative ENU
        else:
            yaw = wrap_angle(float(frames.yaw_enu_from_ned(math.radians(angle))) + self.c.estimator_yaw_rad)
        self._event(f"condition yaw to {math.degrees(yaw):.1f} deg ENU at {math.degrees(rate_rad):.1f} deg/s")
        if self.custom_mode != ARDUCOPTER_MODE["guided"] or not self.armed:
            return _M.MAV_RESULT_ACCEPTED  # auto_yaw is set; only GUIDED flies it in this model
        base = self._setpoint if self._setpoint is not None else self._target
        if base is None:
            base = self._hold_here()
        turned = _Target(p=base.p, v=base.v, a=base.a, yaw=yaw, v_limit_mps=base.v_limit_mps, kind=base.kind,
                         yaw_rate_limit_radps=rate_rad)
        if self._setpoint is not None:
            self._setpoint = turned
        else:
            self._target = turned
        return _M.MAV_RESULT_ACCEPTED

    @property
    def rebooting(self) -> bool:
        """The autopilot is rebooting after an accepted MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: it
        neither sends nor hears anything."""
        return self._reboot_at is not None and self.clock() >= self._reboot_at

    def _cmd_reboot(self, p) -> int:
        """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN for the autopilot (param1).

        PX4 (``Commander.cpp``): 0 ACCEPTED (nothing); 1 reboots after the ACK (400 ms) unless
        ``shutdown_if_allowed`` refuses it armed: DENIED; anything else DENIED (2 and 3 need a
        board with power control / a bootloader hold: not modelled). ArduPilot
        (``GCS_MAVLINK::handle_preflight_reboot``): armed FAILED ("refuse reboot when armed");
        param1 other than 1 or 3 UNSUPPORTED; 1 ACCEPTED, reboot 200 ms later (3 holds in the
        bootloader: the vehicle stays silent). The reboot: :attr:`SimVehicleConfig.reboot_time_s`
        of silence, then a fresh boot (see :meth:`_reboot_tick`)."""
        cmd = int(round(p[0])) if math.isfinite(p[0]) else -1
        if self.px4:
            if cmd == 0:
                return _M.MAV_RESULT_ACCEPTED
            if cmd != 1 or self.armed:
                return _M.MAV_RESULT_DENIED
            delay = 0.4
        else:
            if self.armed:
                return _M.MAV_RESULT_FAILED
            if cmd not in (1, 3):
                return _M.MAV_RESULT_UNSUPPORTED
            delay = 0.2
        now = self.clock()
        self._reboot_at = now + delay
        self._back_at = math.inf if cmd == 3 else self._reboot_at + float(self.c.reboot_time_s)
        self._event("reboot commanded")
        return _M.MAV_RESULT_ACCEPTED

    def _reboot_tick(self) -> None:
        """Finish a reboot: a new boot with parameters and the stored mission kept (both
        autopilots keep them in storage); time since boot from 0, the boot mode, disarmed, no
        home, setpoints and speed changes forgotten, default stream rates, and the estimator's
        origin where the vehicle now stands (the estimate restarts there)."""
        if self._back_at is None or self.clock() < self._back_at:
            return
        with self._lock:
            self._reboot_at = self._back_at = None
            self._t_boot = self.clock()
            self._boot_offset_ms = 0.0
            self.armed = False
            self._armed_at = None
            self.custom_mode = px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]) if self.px4 else ARDUCOPTER_MODE["stabilize"]
            self._rtl = None
            self._home = None
            self._home_manual = False
            self._target = self._setpoint = None
            self._last_sp_s = None
            self._takeoff_alt_m = None
            self._px4_cruise_mps = self._ardu_speed_ne_mps = None
            self._flying_since_arm = False
            self._rates_hz = dict(self._default_rates)
            self._next_send = {}
            self._origin = np.array(self.model.p, dtype=float)
        self._event("rebooted")

    def _request_data_stream(self, stream_id: int, rate_hz: int, start_stop: int) -> None:
        """ArduPilot's REQUEST_DATA_STREAM (``GCS_MAVLINK::handle_request_data_stream``): every
        message of the stream group at ``rate_hz`` (start_stop 1) or stopped (0; any other value
        is ignored); MAV_DATA_STREAM_ALL sets every group. MAVProxy and Mission Planner ask for
        their streams this way (MAVProxy's ``--streamrate``, 4 Hz, on connect)."""
        if start_stop not in (0, 1):
            return
        rate = float(rate_hz) if start_stop == 1 else 0.0
        groups = ARDUPILOT_STREAM_GROUPS.values() if stream_id == _M.MAV_DATA_STREAM_ALL else [ARDUPILOT_STREAM_GROUPS.get(stream_id, ())]
        for names in groups:
            for name in names:
                mid = _ID[name]
                self._rates_hz[mid] = min(rate, self.c.physics_rate_hz)
                self._next_send.pop(mid, None)
        self._event(f"data stream {stream_id} at {rate:g} Hz")

    def _cmd_interval(self, msg_id: float, interval_us: float) -> int:
        if not (math.isfinite(msg_id) and math.isfinite(interval_us)) or int(msg_id) not in self._default_rates:
            return _M.MAV_RESULT_DENIED
        mid = int(msg_id)
        if interval_us < 0:
            rate = 0.0
        elif interval_us == 0:
            rate = self._default_rates[mid]
        else:
            rate = min(1e6 / interval_us, self.c.physics_rate_hz)
        self._rates_hz[mid] = rate
        self._next_send.pop(mid, None)
        return _M.MAV_RESULT_ACCEPTED

    def _cmd_request(self, msg_id: float) -> int:
        if not math.isfinite(msg_id):
            return _M.MAV_RESULT_DENIED
        msg = self._telemetry(int(msg_id), streaming=False)
        if msg is None:
            return _M.MAV_RESULT_DENIED
        self._pending.append(msg)
        return _M.MAV_RESULT_ACCEPTED

    # -- telemetry --------------------------------------------------------------------------
    def _heartbeat(self):
        with self._lock:
            base = _M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (_M.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
            status = _M.MAV_STATE_ACTIVE if self.armed else _M.MAV_STATE_STANDBY
            autopilot = _M.MAV_AUTOPILOT_PX4 if self.px4 else _M.MAV_AUTOPILOT_ARDUPILOTMEGA
            return self.link.mav.heartbeat_encode(_M.MAV_TYPE_QUADROTOR, autopilot, base, self.custom_mode, status)

    def _position_message(self):
        with self._lock:
            p_ned, v_ned = self._local_ned()
        return self.link.mav.local_position_ned_encode(self.time_boot_ms(), *p_ned, *v_ned)

    def _telemetry(self, msg_id: int, streaming: bool):
        """One telemetry message, or None when it cannot be produced now."""
        with self._lock:
            m = self.model
            mav = self.link.mav
            if msg_id == _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                if self._frozen_pos is not None:
                    return self._frozen_pos
                return self._position_message() if self._position_valid else None
            if msg_id in (_M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, _M.MAVLINK_MSG_ID_ATTITUDE):
                R = self._R_scene_est.T @ m.R_enu_flu()
                rates_frd = frames.frd_from_flu(np.array([0.0, 0.0, m.yaw_rate]))
                if msg_id == _M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
                    q = frames.quat_ned_frd_from_matrix_enu_flu(R)
                    return mav.attitude_quaternion_encode(self.time_boot_ms(), *q, *rates_frd)
                R_ned_frd = self._attitude_ned_frd()
                roll = math.atan2(R_ned_frd[2, 1], R_ned_frd[2, 2])
                pitch = math.asin(float(np.clip(-R_ned_frd[2, 0], -1.0, 1.0)))
                yaw = math.atan2(R_ned_frd[1, 0], R_ned_frd[0, 0])
                return mav.attitude_encode(self.time_boot_ms(), roll, pitch, yaw, *rates_frd)
            if msg_id == _M.MAVLINK_MSG_ID_SYS_STATUS:
                S = _M
                sensors = S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL | S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
                sensors |= S.MAV_SYS_STATUS_SENSOR_GPS if self.c.global_origin is not None else S.MAV_SYS_STATUS_SENSOR_VISION_POSITION
                sensors |= S.MAV_SYS_STATUS_SENSOR_3D_MAG if self.c.global_origin is not None else 0
                present = sensors | S.MAV_SYS_STATUS_PREARM_CHECK
                health = sensors if self._position_valid else sensors & ~(S.MAV_SYS_STATUS_SENSOR_GPS | S.MAV_SYS_STATUS_SENSOR_VISION_POSITION)
                if self._prearm_failure() is None:
                    health |= S.MAV_SYS_STATUS_PREARM_CHECK
                frac = self._battery_fraction()
                return mav.sys_status_encode(present, present, health, 250, int(self._battery_voltage_v(frac) * 1000),
                                             1500 if self.armed else 50, int(round(frac * 100)), 0, 0, 0, 0, 0, 0)
            if msg_id == _M.MAVLINK_MSG_ID_BATTERY_STATUS:
                frac = self._battery_fraction()
                cell_mv = int(self._battery_voltage_v(frac) / 4 * 1000)
                return mav.battery_status_encode(0, _M.MAV_BATTERY_FUNCTION_ALL, _M.MAV_BATTERY_TYPE_LIPO, 2500,
                                                 [cell_mv] * 4 + [65535] * 6, 1500 if self.armed else 50, -1, -1, int(round(frac * 100)))
            if msg_id == _M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
                return mav.extended_sys_state_encode(_M.MAV_VTOL_STATE_UNDEFINED, self.landed_state)
            if msg_id == _M.MAVLINK_MSG_ID_SYSTEM_TIME:
                return mav.system_time_encode(int(time.time() * 1e6), self.time_boot_ms())
            if msg_id == _M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
                if self.c.global_origin is None or not self._position_valid:
                    return None
                lat, lon, alt = self._global_from_scene(m.p)
                home = self._home if self._home is not None else self._origin
                v_ned = frames.ned_from_enu(m.v)
                hdg = int(round(math.degrees(frames.yaw_ned_from_enu(m.yaw)) * 100)) % 36000
                return mav.global_position_int_encode(self.time_boot_ms(), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
                                                      int(round((m.p[2] - home[2]) * 1000)), *(int(round(x * 100)) for x in v_ned), hdg)
            if msg_id == _M.MAVLINK_MSG_ID_GPS_RAW_INT:
                return self._gps_raw_int()
            if msg_id == _M.MAVLINK_MSG_ID_HOME_POSITION:
                if self._home is None:
                    return None
                lat = lon = alt = 0.0
                if self.c.global_origin is not None:
                    lat, lon, alt = self._global_from_scene(self._home)
                h_ned = frames.ned_from_enu(self.local_from_scene(self._home))
                return mav.home_position_encode(int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), *h_ned,
                                                [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, int(time.time() * 1e6))
            if msg_id == _M.MAVLINK_MSG_ID_MISSION_CURRENT:
                return self.mission.mission_current_stream()
            if msg_id in self._builders:
                # messages of one autopilot only: the other neither streams nor sends them on request
                return self._builders[msg_id]() if msg_id in self._default_rates else None
            if msg_id == _M.MAVLINK_MSG_ID_AUTOPILOT_VERSION and not streaming:
                C = _M
                caps = (C.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | C.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                        | C.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | C.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT)
                caps |= C.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE if self.px4 else C.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
                caps |= C.MAV_PROTOCOL_CAPABILITY_MISSION_INT | (C.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT if self.px4 else 0)
                version = _flight_sw_version(1, 15, 0) if self.px4 else _flight_sw_version(4, 5, 0)
                return mav.autopilot_version_encode(caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x5EED0000 + self.c.system_id)
            return None

    # -- state as the vehicle's sensors and estimator report it -------------------------------
    #: ISA sea-level pressure (hPa) and temperature (deg C); PX4 SENS_BARO_QNH 1013.25
    _ISA_P0_HPA = 1013.25
    _ISA_T0_C = 15.0
    #: ArduPilot's GRAVITY_MSS (RAW_IMU milli-g)
    _AP_GRAVITY_MSS = 9.80665

    def _baro(self):
        """(pressure hPa, pressure altitude m, temperature deg C) of an ISA standard day at the
        vehicle's AMSL altitude, or None indoors: without a global origin the model does not know
        the altitude above sea level, so it has no pressure to report."""
        if self.c.global_origin is None:
            return None
        h = self.c.global_origin[2] + float(self.model.p[2])
        p = self._ISA_P0_HPA * (1.0 - 2.25577e-5 * h) ** 5.25588
        return p, h, self._ISA_T0_C - 0.0065 * h

    def _specific_force_frd(self) -> np.ndarray:
        """What an accelerometer measures (m/s^2, body FRD): the model's acceleration over the
        last physics step minus gravity, so at rest z = -9.81 and in free fall 0."""
        f_enu = self._accel_enu + np.array([0.0, 0.0, PointMassModel.GRAVITY_MPS2])
        f_flu = self.model.R_enu_flu().T @ f_enu
        return frames.frd_from_flu(f_flu)

    def _body_rates_frd(self) -> np.ndarray:
        """Gyro (rad/s, body FRD): the model turns about its yaw axis only (as ATTITUDE says)."""
        return frames.frd_from_flu(np.array([0.0, 0.0, float(self.model.yaw_rate)]))

    def _heading_ned_rad(self) -> float:
        """Heading (rad, NED, from north clockwise) in the estimator's frame."""
        return float(frames.yaw_ned_from_enu(wrap_angle(self.model.yaw - self.c.estimator_yaw_rad)))

    def _throttle_fraction(self) -> float:
        """Collective thrust in [0, 1]: the hover throttle (MPC_THR_HOVER / MOT_THST_HOVER) scaled by
        the thrust the model needs (|a + g| / g); 0 disarmed or resting on the ground (idle)."""
        if not self.armed or self.model.on_ground:
            return 0.0
        hover = float(self.params["MPC_THR_HOVER"] if self.px4 else self.params["MOT_THST_HOVER"])
        need = np.linalg.norm(self._accel_enu + np.array([0.0, 0.0, PointMassModel.GRAVITY_MPS2])) / PointMassModel.GRAVITY_MPS2
        return float(np.clip(hover * need, 0.0, 1.0))

    def _local_ned(self):
        """Position and velocity (NED, the estimator's frame) of the model."""
        p_loc = self.local_from_scene(self.model.p)
        v_loc = self.model.v @ self._R_scene_est
        return frames.ned_from_enu(np.stack([p_loc, v_loc]))

    def _altitude(self):
        """PX4 ALTITUDE (``streams/ALTITUDE.hpp``): monotonic = baro altitude; amsl = -z + the
        origin's AMSL altitude with a global origin, else the baro altitude; local = -z; relative
        = height above home (-z without home); terrain and bottom clearance NaN (no distance
        sensor). Without a position estimate only the baro altitude."""
        nan = math.nan
        baro = self._baro()
        mono = nan if baro is None else baro[1]
        amsl = local = rel = nan
        if self._position_valid:
            p_ned, _ = self._local_ned()
            local = -float(p_ned[2])
            if self.c.global_origin is not None:
                amsl = self.c.global_origin[2] + float(self.model.p[2])
            else:
                amsl = mono
            rel = float(self.model.p[2] - self._home[2]) if self._home is not None else local
        return self.link.mav.altitude_encode(self.time_boot_us(), mono, amsl, local, rel, nan, nan)

    def _vfr_hud(self):
        """VFR_HUD. PX4 (``streams/VFR_HUD.hpp``): airspeed from an airspeed sensor (none on a
        multicopter: 0), groundspeed and heading (deg) of the local position, throttle = 100 x the
        thrust setpoint armed, alt AMSL of the global estimate (else the baro altitude, 0 without
        air data), climb = -vz. ArduCopter (``GCS_Common.cpp`` ``send_vfr_hud``): airspeed = GPS
        ground speed without an airspeed sensor, heading ``yaw_sensor / 100``, throttle =
        ``motors->get_throttle() * 100``, alt = the current location's AMSL altitude (0 without
        an EKF origin), climb = -vD."""
        m = self.model
        _, v_ned = self._local_ned()
        ground = float(np.hypot(v_ned[0], v_ned[1]))
        heading = int(math.degrees(self._heading_ned_rad() % (2 * math.pi))) % 360
        throttle = int(round(100.0 * self._throttle_fraction()))
        has_global = self.c.global_origin is not None and self._position_valid
        if self.px4:
            airspeed = 0.0
            if has_global:
                alt = self.c.global_origin[2] + float(m.p[2])
            else:
                baro = self._baro()
                alt = 0.0 if baro is None else baro[1]
        else:
            airspeed = ground if has_global else 0.0
            alt = self.c.global_origin[2] + float(m.p[2]) if has_global else 0.0
        climb = -float(v_ned[2]) if self._position_valid else 0.0
        if not self._position_valid:
            ground = 0.0
        return self.link.mav.vfr_hud_encode(airspeed, ground, heading, throttle, alt, climb)

    def _odometry(self):
        """PX4 ODOMETRY (``streams/ODOMETRY.hpp`` of EKF2's ``PublishOdometry``): position and
        velocity in the estimator's local NED frame (frame_id and child_frame_id
        MAV_FRAME_LOCAL_NED), attitude quaternion NED->FRD, body rates FRD, estimator_type
        AUTOPILOT, quality 0 (EKF2 sets none). Covariances NaN: the model has no estimator
        variances. None without a position estimate (as LOCAL_POSITION_NED)."""
        if not self._position_valid:
            return None
        p_ned, v_ned = self._local_ned()
        q = frames.quat_ned_frd_from_matrix_enu_flu(self._R_scene_est.T @ self.model.R_enu_flu())
        rates = self._body_rates_frd()
        cov = [math.nan] * 21
        return self.link.mav.odometry_encode(self.time_boot_us(), _M.MAV_FRAME_LOCAL_NED, _M.MAV_FRAME_LOCAL_NED,
                                             *(float(x) for x in p_ned), [float(x) for x in q], *(float(x) for x in v_ned),
                                             *(float(x) for x in rates), cov, cov, 0, _M.MAV_ESTIMATOR_TYPE_AUTOPILOT, 0)

    def _highres_imu(self):
        """PX4 HIGHRES_IMU (``streams/HIGHRES_IMU.hpp``): accel (m/s^2, FRD, gravity included) and
        gyro (rad/s) with fields_updated bits 0-5; outdoors also the baro (abs_pressure hPa,
        pressure_alt m, temperature deg C; bits 9, 11, 12). No magnetometer field is modelled:
        mag 0 and its bits clear."""
        f = self._specific_force_frd()
        g = self._body_rates_frd()
        fields = 0x3F
        press = alt = temp = 0.0
        baro = self._baro()
        if baro is not None:
            press, alt, temp = baro
            fields |= (1 << 9) | (1 << 11) | (1 << 12)
        return self.link.mav.highres_imu_encode(self.time_boot_us(), *(float(x) for x in f), *(float(x) for x in g),
                                                0.0, 0.0, 0.0, press, 0.0, alt, temp, fields)

    def _raw_imu(self):
        """ArduPilot RAW_IMU (RAW_SENS group; ``GCS_Common.cpp`` ``send_raw_imu``): the first
        IMU's scaled accel in milli-g (x 1000 / GRAVITY_MSS) and gyro in mrad/s, FRD; mag 0 (not
        modelled); temperature 0 (no IMU temperature modelled)."""
        f = self._specific_force_frd() * 1000.0 / self._AP_GRAVITY_MSS
        g = self._body_rates_frd() * 1000.0
        ints = [int(np.clip(round(float(x)), -32768, 32767)) for x in (*f, *g)]
        return self.link.mav.raw_imu_encode(self.time_boot_us(), *ints, 0, 0, 0, 0, 0)

    def _position_target_local_ned(self):
        """What the position controller tracks, MAV_FRAME_LOCAL_NED in the estimator's frame.
        Targets sent in another frame are reported as flown: rotated and offset into it.

        PX4 (``streams/POSITION_TARGET_LOCAL_NED.hpp`` sends ``vehicle_local_position_setpoint``,
        which ``PositionControl::getLocalPositionSetpoint`` fills after ``update``): the position
        as commanded (NaN with its ignore bits when not); the velocity and acceleration
        setpoints the controller flew (the position loop's output plus the feed-forward, so
        finite for a position-only target too; :meth:`controller_setpoint` of the model); a yaw
        that was not commanded is the current yaw and a yaw rate that was not is 0
        (``update``: "_yaw_sp = PX4_ISFINITE(_yaw_sp) ? _yaw_sp : _yaw", the yawspeed likewise
        to 0), neither with its ignore bit. None while nothing is tracked (disarmed).
        ArduCopter (``GCS_MAVLINK_Copter::send_position_target_local_ned``): only in GUIDED, the
        tracked position and/or velocity, the rest (yaw and yaw rate too) ignored (0)."""
        if self._target is None or not self.armed:
            return None
        if not self.px4 and self.custom_mode != ARDUCOPTER_MODE["guided"]:
            return None
        t = self._target.at(self.clock())
        nan = math.nan
        v, a = t.v, t.a  # ArduCopter: the commanded vectors
        flown = self.model.controller_setpoint() if self.px4 else None
        if flown is not None:  # PX4: the controller's, velocity only where a position or velocity is flown
            v = flown[0] if (t.p is not None or t.v is not None) else None
            a = flown[1]
        rows = [
            None if t.p is None else frames.ned_from_enu(self.local_from_scene(t.p)),
            None if v is None else frames.ned_from_enu(v @ self._R_scene_est),
            None if a is None else frames.ned_from_enu(a @ self._R_scene_est),
        ]
        T = _M
        ignore = [(T.POSITION_TARGET_TYPEMASK_X_IGNORE | T.POSITION_TARGET_TYPEMASK_Y_IGNORE | T.POSITION_TARGET_TYPEMASK_Z_IGNORE),
                  (T.POSITION_TARGET_TYPEMASK_VX_IGNORE | T.POSITION_TARGET_TYPEMASK_VY_IGNORE | T.POSITION_TARGET_TYPEMASK_VZ_IGNORE),
                  (T.POSITION_TARGET_TYPEMASK_AX_IGNORE | T.POSITION_TARGET_TYPEMASK_AY_IGNORE | T.POSITION_TARGET_TYPEMASK_AZ_IGNORE)]
        absent = nan if self.px4 else 0.0
        mask = 0
        vals = []
        for k in range(3):
            if rows[k] is None:
                mask |= ignore[k]
                vals += [absent] * 3
            else:
                vals += [float(x) for x in rows[k]]
        if self.px4:
            held = self.model.yaw if t.yaw is None else t.yaw
            yaw = float(frames.yaw_ned_from_enu(wrap_angle(held - self.c.estimator_yaw_rad)))
            yaw_rate = 0.0 if t.yaw_rate is None else float(frames.yaw_rate_ned_from_enu(t.yaw_rate))
        else:
            yaw = yaw_rate = absent
            mask |= T.POSITION_TARGET_TYPEMASK_YAW_IGNORE | T.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
        return self.link.mav.position_target_local_ned_encode(self.time_boot_ms(), _M.MAV_FRAME_LOCAL_NED, mask, *vals,
                                                              yaw, yaw_rate)

    def _timesync_request(self):
        """PX4's TIMESYNC stream (``MavlinkStreamTimesync``): a request, tc1 = 0, ts1 = our time
        since boot in ns; the companion's answer is not used here."""
        return self.link.mav.timesync_encode(0, self.time_boot_us() * 1000)

    def _ping_request(self):
        """PX4's PING stream (``streams/PING.hpp``): a request to all (target 0/0), seq counting up,
        time_usec = our time since boot (from seq 0); answers are not used here."""
        seq, self._ping_seq = self._ping_seq, (self._ping_seq + 1) % 2**32
        return self.link.mav.ping_encode(self.time_boot_us(), seq, 0, 0)

    def _gps_raw_int(self):
        """GPS_RAW_INT of the model's receiver (outdoor only): a 3D fix with 12 satellites, lat/lon
        degE7, alt mm AMSL, eph/epv the DOPs x 100 (MAVLink: HDOP 0.8, VDOP 1.2), h_acc/v_acc/vel_acc
        in mm and mm/s, vel cm/s and cog cdeg over ground (cog unknown, UINT16_MAX, below 0.1 m/s).
        Without a position estimate: no fix. alt_ellipsoid is not modelled (0)."""
        if self.c.global_origin is None:
            return None
        m = self.model
        t_us = self.time_boot_ms() * 1000
        if not self._position_valid:
            return self.link.mav.gps_raw_int_encode(t_us, _M.GPS_FIX_TYPE_NO_FIX, 0, 0, 0, 65535, 65535, 65535, 65535, 0)
        lat, lon, alt = self._global_from_scene(m.p)
        speed = float(np.hypot(m.v[0], m.v[1]))
        cog = 65535 if speed < 0.1 else int(round(math.degrees(math.atan2(m.v[0], m.v[1])) * 100)) % 36000  # from north, clockwise
        return self.link.mav.gps_raw_int_encode(t_us, _M.GPS_FIX_TYPE_3D_FIX, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                int(round(alt * 1000)), 80, 120, int(round(speed * 100)), cog, 12,
                                                0, 1200, 1800, 250, 0)

    def _battery_fraction(self) -> float:
        """Remaining charge: a linear drain over ``battery_capacity_s`` of wall time (a model,
        not a battery: it only gives the battery streams honest units)."""
        used = (self.clock() - self._t_boot) / self.c.battery_capacity_s
        return float(np.clip(1.0 - used, 0.0, 1.0))

    @staticmethod
    def _battery_voltage_v(frac: float) -> float:
        return 4 * (3.5 + 0.7 * frac)  # 4S LiPo, 3.5-4.2 V per cell

    def observation_in_local(self, obs):
        """``obs`` (posed in the scene) re-posed in the estimator's local frame, as the frames of a
        camera stamped by the vehicle's estimator are (what a companion receives)."""
        import dataclasses

        return dataclasses.replace(obs, T_world_cam=self.T_local_scene @ obs.T_world_cam)
