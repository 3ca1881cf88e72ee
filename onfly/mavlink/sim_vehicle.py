"""SimMavlinkVehicle: a MAVLink vehicle on a link that follows PX4's offboard rules or
ArduCopter's guided rules closely enough to test the companion against them.

PX4 rules modelled (``autopilot="px4"``)
----------------------------------------
- Starts disarmed in AUTO.LOITER (hold). Arming (MAV_CMD_COMPONENT_ARM_DISARM) is accepted;
  disarming in the air is DENIED unless forced (param2 = 21196).
- MAV_CMD_DO_SET_MODE to OFFBOARD (custom main mode 6) is TEMPORARILY_REJECTED unless
  SET_POSITION_TARGET_LOCAL_NED has been streaming for ``offboard_prestream_s`` (default 1 s)
  with no gap longer than ``1 / offboard_min_rate_hz`` (PX4 needs > 2 Hz).
- In OFFBOARD, if no setpoint arrives for ``offboard_loss_timeout_s`` (COM_OF_LOSS_T,
  default 1 s) the vehicle switches to AUTO.LOITER and holds where it is; the change shows in
  its HEARTBEAT ``custom_mode``.
- MAV_CMD_NAV_TAKEOFF is answered UNSUPPORTED (PX4 companions take off through offboard).

ArduCopter rules modelled (``autopilot="ardupilot"``)
-----------------------------------------------------
- Starts disarmed in STABILIZE (0). GUIDED is custom mode 4, LOITER 5, LAND 9.
- MAV_CMD_NAV_TAKEOFF (param7 = altitude above home, metres) is accepted only in GUIDED and
  armed (else FAILED); the vehicle climbs at ``takeoff_speed_mps`` and ignores position targets
  until the altitude is reached.
- After takeoff, position targets are followed; if none arrives for ``guided_timeout_s``
  (3 s, ArduCopter's guided position/velocity timeout) the vehicle stops and holds.

Both: HEARTBEAT at 1 Hz, LOCAL_POSITION_NED and the attitude message (ATTITUDE_QUATERNION for
PX4, ATTITUDE for ArduPilot) at ``telemetry_rate_hz`` (50 Hz), adjustable with
MAV_CMD_SET_MESSAGE_INTERVAL; time_boot_ms from the vehicle's own boot clock; every
COMMAND_LONG addressed to it gets a COMMAND_ACK; unknown commands are UNSUPPORTED.
``pilot_takeover()`` models the RC pilot switching to POSCTL (PX4) or LOITER (ArduPilot).

Dynamics
--------
Two models behind one interface (``p``, ``v``, ``a``, ``yaw``, ``yaw_rate``, ``on_ground``,
``step(dt, target, armed)``, ``R_enu_flu()``; optionally ``crashed``):

- :class:`PointMassModel` (default, no scene): a point mass under a cascaded P (position) /
  P (velocity) controller with velocity and acceleration feed-forward, speed, acceleration and
  yaw-rate limits, a ground plane at z = 0, and a tilt derived from the commanded acceleration
  (for a realistic attitude quaternion).
- :class:`onfly.mavlink.sim_world.WorldVehicleModel` (``model=``): the embedded world's
  vehicle, exact collisions against a scene and its camera. A model that reports ``crashed``
  makes the vehicle disarm (``crashed: ...`` event).

State is ENU internally; NED/FRD appear only at the MAVLink boundary through
:mod:`onfly.mavlink.frames`.

Fault injection for tests: :meth:`SimMavlinkVehicle.set_link_cut` (drop all traffic both ways)
and :meth:`SimMavlinkVehicle.set_odometry_frozen` (keep re-sending the last position sample with
its old timestamp, as a stuck estimator would).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from onfly.mavlink import frames
from onfly.mavlink.autopilot import ARDUCOPTER_MODE, PX4_AUTO_SUB, PX4_MAIN, px4_custom_mode, px4_main_mode
from onfly.mavlink.link import Link, LinkError, mavlink2
from planning.frames import wrap_angle

__all__ = [
    "SimVehicleConfig",
    "PointMassModel",
    "SimMavlinkVehicle",
]

_FORCE_DISARM_MAGIC = 21196

log = logging.getLogger(__name__)
_M = mavlink2

@dataclass(frozen=True)
class SimVehicleConfig:
    """Rules, rates and limits of the simulated vehicle (seconds, metres, radians, ENU)."""

    autopilot: str = "px4"
    system_id: int = 1
    component_id: int = _M.MAV_COMP_ID_AUTOPILOT1
    physics_rate_hz: float = 100.0
    telemetry_rate_hz: float = 50.0
    heartbeat_period_s: float = 1.0
    offboard_prestream_s: float = 1.0
    offboard_min_rate_hz: float = 2.0
    offboard_loss_timeout_s: float = 1.0
    guided_timeout_s: float = 3.0
    takeoff_speed_mps: float = 1.5
    land_speed_mps: float = 0.7
    v_max_mps: float = 5.0
    a_max_mps2: float = 5.0
    yaw_rate_max_radps: float = 1.5
    k_pos: float = 1.5
    k_vel: float = 4.0
    k_yaw: float = 2.0
    initial_position_m: tuple = (0.0, 0.0, 0.0)
    initial_yaw_rad: float = 0.0
    boot_time_ms: int = 0

    def __post_init__(self) -> None:
        if self.autopilot not in ("px4", "ardupilot"):
            raise ValueError(f"autopilot must be 'px4' or 'ardupilot', got {self.autopilot!r}")
        if not 1 <= int(self.system_id) <= 255:
            raise ValueError(f"system_id must be in [1, 255], got {self.system_id}")
        positive = (
            "physics_rate_hz", "telemetry_rate_hz", "heartbeat_period_s", "offboard_prestream_s",
            "offboard_min_rate_hz", "offboard_loss_timeout_s", "guided_timeout_s", "takeoff_speed_mps",
            "land_speed_mps", "v_max_mps", "a_max_mps2", "yaw_rate_max_radps", "k_pos", "k_vel", "k_yaw",
        )
        for name in positive:
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive, got {val!r}")
        p = tuple(float(x) for x in self.initial_position_m)
        if len(p) != 3 or not all(math.isfinite(x) for x in p) or p[2] < 0:
            raise ValueError(f"initial_position_m must be 3 finite numbers with z >= 0, got {self.initial_position_m!r}")
        object.__setattr__(self, "initial_position_m", p)
        if not 0 <= int(self.boot_time_ms) < 2**32:
            raise ValueError(f"boot_time_ms must be a uint32, got {self.boot_time_ms}")


@dataclass
class _Target:
    """What the controller tracks (ENU); None fields are ignored."""

    p: np.ndarray | None = None
    v: np.ndarray | None = None
    a: np.ndarray | None = None
    yaw: float | None = None
    v_limit_mps: float | None = None


class PointMassModel:
    """Point mass with a cascaded P/P controller (see the module docstring). ENU, SI units.

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

    @property
    def on_ground(self) -> bool:
        return self.p[2] <= 1e-3 and self.v[2] <= 1e-3

    def step(self, dt_s: float, target: _Target | None, armed: bool) -> None:
        c = self.c
        if not armed or target is None:
            if self.on_ground or not armed:
                # Disarmed (or no target on the ground): motors off, sitting on the ground.
                self.a = np.zeros(3) if self.on_ground else np.array([0.0, 0.0, -self.GRAVITY_MPS2])
                self._integrate(dt_s)
                self.yaw_rate = 0.0
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
        self._integrate(dt_s)
        if target.yaw is not None:
            rate = float(np.clip(c.k_yaw * wrap_angle(target.yaw - self.yaw), -c.yaw_rate_max_radps, c.yaw_rate_max_radps))
        else:
            rate = 0.0
        self.yaw_rate = rate
        self.yaw = wrap_angle(self.yaw + rate * dt_s)

    def _integrate(self, dt_s: float) -> None:
        self.v = self.v + self.a * dt_s
        n = np.linalg.norm(self.v)
        if n > self.c.v_max_mps:
            self.v *= self.c.v_max_mps / n
        self.p = self.p + self.v * dt_s
        if self.p[2] < 0.0:
            self.p[2] = 0.0
            self.v[2] = max(self.v[2], 0.0)

    def R_enu_flu(self) -> np.ndarray:
        """Body attitude (3, 3): thrust axis along ``a + g z``, heading ``yaw``."""
        thrust = self.a + np.array([0.0, 0.0, self.GRAVITY_MPS2])
        z_b = thrust / max(np.linalg.norm(thrust), 1e-6)
        x_c = np.array([np.cos(self.yaw), np.sin(self.yaw), 0.0])
        y_b = np.cross(z_b, x_c)
        y_b /= max(np.linalg.norm(y_b), 1e-9)
        x_b = np.cross(y_b, z_b)
        return np.column_stack([x_b, y_b, z_b])


class SimMavlinkVehicle:
    """The simulated autopilot serving one :class:`~onfly.mavlink.link.Link` from its own thread.

    ``clock`` is the real monotonic clock by default (the vehicle runs in wall time like real
    hardware). ``model`` replaces the internal :class:`PointMassModel` (e.g. a
    :class:`~onfly.mavlink.sim_world.WorldVehicleModel`; ``config.initial_position_m`` and the
    config's limits and gains then do not apply: the model has its own). Read-only observers for
    tests: :attr:`model`, :attr:`armed`, :attr:`custom_mode`, :attr:`events` (``(t_s, text)``),
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
        self.events: list[tuple[float, str]] = []
        self.setpoints_received = 0
        self.setpoint_times: list[float] = []
        self.foreign_setpoints = 0
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cut = threading.Event()
        self._frozen_pos = None
        self._t_boot = clock()
        self._target: _Target | None = None
        self._setpoint: _Target | None = None
        self._last_sp_s: float | None = None
        self._stream_since_s: float | None = None
        self._takeoff_alt_m: float | None = None
        self._took_off = False
        self._guided_timed_out = False
        att_id = _M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION if self.px4 else _M.MAVLINK_MSG_ID_ATTITUDE
        self._rates_hz = {_M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: config.telemetry_rate_hz, att_id: config.telemetry_rate_hz}
        self._next_send: dict[int, float] = {}

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

    # -- observers and faults ---------------------------------------------------------------
    @property
    def mode_name(self) -> str:
        with self._lock:
            if self.px4:
                main = px4_main_mode(self.custom_mode)
                sub = (self.custom_mode >> 24) & 0xFF
                name = next((k for k, v in PX4_MAIN.items() if v == main), str(main))
                if main == PX4_MAIN["auto"]:
                    name += "." + next((k for k, v in PX4_AUTO_SUB.items() if v == sub), str(sub))
                return name
            return next((k for k, v in ARDUCOPTER_MODE.items() if v == self.custom_mode), str(self.custom_mode))

    def position_enu(self) -> np.ndarray:
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
        """Keep re-sending the last position sample unchanged, old timestamp included."""
        with self._lock:
            self._frozen_pos = self._position_message() if frozen else None
        self._event(f"odometry {'frozen' if frozen else 'live'}")

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
        return int(self.c.boot_time_ms + (self.clock() - self._t_boot) * 1000.0) % 2**32

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
            if msg is not None and not self._cut.is_set():
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
                    self._send_telemetry(msg_id)
                    self._next_send[msg_id] = max(due + 1.0 / rate, now)

    def _send(self, msg) -> None:
        if self._cut.is_set():
            return
        try:
            self.link.send(msg)
        except LinkError as exc:
            log.debug("vehicle send failed: %s", exc)

    def _event(self, text: str) -> None:
        t = self.clock()
        with self._lock:
            self.events.append((t, text))
        log.info("sim vehicle t=%.3f: %s", t, text)

    # -- physics and rules ------------------------------------------------------------------
    def _physics(self, dt: float, t: float) -> None:
        with self._lock:
            self._apply_rules(t)
            self.model.step(dt, self._target, self.armed)
            if self.armed and getattr(self.model, "crashed", False):
                self.armed = False
                hit = getattr(self.model, "collision", None)
                self._event(f"crashed{'' if hit is None else f' into {hit.object_name!r}'}: disarmed")
            if self._landing() and self.model.on_ground and self.armed:
                self.armed = False
                self._event("landed and disarmed")

    def _landing(self) -> bool:
        if self.px4:
            return self.custom_mode == px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["land"])
        return self.custom_mode == ARDUCOPTER_MODE["land"]

    def _apply_rules(self, t: float) -> None:
        since_sp = math.inf if self._last_sp_s is None else t - self._last_sp_s
        if self.px4:
            if px4_main_mode(self.custom_mode) == PX4_MAIN["offboard"]:
                if since_sp > self.c.offboard_loss_timeout_s:
                    self._set_mode(px4_custom_mode(PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]), f"offboard lost ({since_sp:.2f} s without setpoints)")
                else:
                    self._target = self._setpoint
            return
        if self.custom_mode == ARDUCOPTER_MODE["guided"] and self.armed:
            if self._takeoff_alt_m is not None and not self._took_off:
                if self.model.p[2] >= self._takeoff_alt_m - 0.1:
                    self._took_off = True
                    self._target = _Target(p=self.model.p.copy(), yaw=self.model.yaw)
                    self._event("takeoff complete")
            elif self._took_off and self._setpoint is not None:
                if since_sp > self.c.guided_timeout_s:
                    if not self._guided_timed_out:
                        self._guided_timed_out = True
                        self._target = _Target(p=self.model.p.copy(), yaw=self.model.yaw)
                        self._event(f"guided timeout ({since_sp:.2f} s without setpoints): holding")
                else:
                    self._guided_timed_out = False
                    self._target = self._setpoint

    def _set_mode(self, custom_mode: int, why: str) -> None:
        with self._lock:
            self.custom_mode = int(custom_mode)
            hold = _Target(p=self.model.p.copy(), yaw=self.model.yaw)
            if self._landing():
                hold = _Target(v=np.array([0.0, 0.0, -self.c.land_speed_mps]), yaw=self.model.yaw)
            if self.px4 and px4_main_mode(custom_mode) == PX4_MAIN["offboard"]:
                self._target = self._setpoint if self._setpoint is not None else hold
            else:
                self._target = hold
            self._event(f"mode {self.mode_name}: {why}")

    def _stream_ok(self, t: float) -> bool:
        gap = 1.0 / self.c.offboard_min_rate_hz
        if self._last_sp_s is None or t - self._last_sp_s > gap or self._stream_since_s is None:
            return False
        return t - self._stream_since_s >= self.c.offboard_prestream_s

    # -- message handling -------------------------------------------------------------------
    def _for_me(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.c.system_id) and target_component in (0, self.c.component_id)

    def _handle(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "SET_POSITION_TARGET_LOCAL_NED":
            self._on_setpoint(msg)
        elif mtype == "COMMAND_LONG":
            if self._for_me(msg.target_system, msg.target_component):
                result = self._on_command(msg)
                self._send(self.link.mav.command_ack_encode(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_setpoint(self, msg) -> None:
        if not self._for_me(msg.target_system, msg.target_component):
            self.foreign_setpoints += 1
            return
        if msg.coordinate_frame != _M.MAV_FRAME_LOCAL_NED:
            return
        mask = int(msg.type_mask)
        vals = np.array([msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz, msg.afx, msg.afy, msg.afz, msg.yaw], dtype=float)
        ned = vals[:9].reshape(3, 3)
        use = [
            not mask & (_M.POSITION_TARGET_TYPEMASK_X_IGNORE | _M.POSITION_TARGET_TYPEMASK_Y_IGNORE | _M.POSITION_TARGET_TYPEMASK_Z_IGNORE),
            not mask & (_M.POSITION_TARGET_TYPEMASK_VX_IGNORE | _M.POSITION_TARGET_TYPEMASK_VY_IGNORE | _M.POSITION_TARGET_TYPEMASK_VZ_IGNORE),
            not mask & (_M.POSITION_TARGET_TYPEMASK_AX_IGNORE | _M.POSITION_TARGET_TYPEMASK_AY_IGNORE | _M.POSITION_TARGET_TYPEMASK_AZ_IGNORE),
        ]
        use_yaw = not mask & _M.POSITION_TARGET_TYPEMASK_YAW_IGNORE
        if not any(use) or any(u and not np.all(np.isfinite(row)) for u, row in zip(use, ned)) or (use_yaw and not np.isfinite(vals[9])):
            return  # PX4 and ArduPilot drop setpoints they cannot use
        enu = frames.enu_from_ned(np.nan_to_num(ned))
        target = _Target(
            p=enu[0] if use[0] else None,
            v=enu[1] if use[1] else None,
            a=enu[2] if use[2] else None,
            yaw=float(frames.yaw_enu_from_ned(vals[9])) if use_yaw else None,
        )
        t = self.clock()
        with self._lock:
            gap = 1.0 / self.c.offboard_min_rate_hz
            if self._last_sp_s is None or t - self._last_sp_s > gap:
                self._stream_since_s = t
            self._last_sp_s = t
            self.setpoints_received += 1
            self.setpoint_times.append(t)
            if self.px4 or self._took_off:
                self._setpoint = target

    def _on_command(self, msg) -> int:
        cmd = int(msg.command)
        with self._lock:
            if cmd == _M.MAV_CMD_COMPONENT_ARM_DISARM:
                return self._cmd_arm(msg.param1 >= 0.5, int(round(msg.param2)) == _FORCE_DISARM_MAGIC)
            if cmd == _M.MAV_CMD_DO_SET_MODE:
                return self._cmd_set_mode(msg)
            if cmd == _M.MAV_CMD_NAV_TAKEOFF:
                return self._cmd_takeoff(msg.param7)
            if cmd == _M.MAV_CMD_SET_MESSAGE_INTERVAL:
                return self._cmd_interval(msg.param1, msg.param2)
        return _M.MAV_RESULT_UNSUPPORTED

    def _cmd_arm(self, arm: bool, force: bool) -> int:
        if arm:
            if not self.armed:
                self.armed = True
                self._event("armed")
            return _M.MAV_RESULT_ACCEPTED
        if self.armed and not self.model.on_ground and not force:
            return _M.MAV_RESULT_DENIED
        if self.armed:
            self.armed = False
            self._event("disarmed")
        return _M.MAV_RESULT_ACCEPTED

    def _cmd_set_mode(self, msg) -> int:
        if not int(msg.param1) & _M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED or not all(np.isfinite([msg.param2, msg.param3])):
            return _M.MAV_RESULT_DENIED
        if self.px4:
            main, sub = int(msg.param2), int(msg.param3)
            if main not in PX4_MAIN.values():
                return _M.MAV_RESULT_DENIED
            if main == PX4_MAIN["offboard"] and not self._stream_ok(self.clock()):
                self._event("offboard refused: no setpoint stream")
                return _M.MAV_RESULT_TEMPORARILY_REJECTED
            if main == PX4_MAIN["auto"] and sub not in PX4_AUTO_SUB.values():
                return _M.MAV_RESULT_DENIED
            self._set_mode(px4_custom_mode(main, sub if main == PX4_MAIN["auto"] else 0), "commanded")
            return _M.MAV_RESULT_ACCEPTED
        mode = int(msg.param2)
        if mode not in ARDUCOPTER_MODE.values():
            return _M.MAV_RESULT_DENIED
        self._set_mode(mode, "commanded")
        return _M.MAV_RESULT_ACCEPTED

    def _cmd_takeoff(self, alt_m: float) -> int:
        if self.px4:
            return _M.MAV_RESULT_UNSUPPORTED
        if not (np.isfinite(alt_m) and 0.2 <= alt_m <= 100.0):
            return _M.MAV_RESULT_DENIED
        if self.custom_mode != ARDUCOPTER_MODE["guided"] or not self.armed or not self.model.on_ground:
            return _M.MAV_RESULT_FAILED
        self._takeoff_alt_m = float(alt_m)
        self._took_off = False
        p = self.model.p.copy()
        p[2] = float(alt_m)
        self._target = _Target(p=p, yaw=self.model.yaw, v_limit_mps=self.c.takeoff_speed_mps)
        self._event(f"takeoff to {alt_m:.2f} m")
        return _M.MAV_RESULT_ACCEPTED

    def _cmd_interval(self, msg_id: float, interval_us: float) -> int:
        if not np.isfinite(msg_id) or int(msg_id) not in (
            _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, _M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, _M.MAVLINK_MSG_ID_ATTITUDE
        ):
            return _M.MAV_RESULT_DENIED
        if not np.isfinite(interval_us):
            return _M.MAV_RESULT_DENIED
        if interval_us < 0:
            rate = 0.0
        elif interval_us == 0:
            rate = self.c.telemetry_rate_hz
        else:
            rate = min(1e6 / interval_us, self.c.physics_rate_hz)
        self._rates_hz[int(msg_id)] = rate
        self._next_send.pop(int(msg_id), None)
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
            p_ned, v_ned = frames.ned_from_enu(np.stack([self.model.p, self.model.v]))
        return self.link.mav.local_position_ned_encode(self.time_boot_ms(), *p_ned, *v_ned)

    def _send_telemetry(self, msg_id: int) -> None:
        if msg_id == _M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            with self._lock:
                frozen = self._frozen_pos
            self._send(frozen if frozen is not None else self._position_message())
            return
        with self._lock:
            R = self.model.R_enu_flu()
            rates_frd = frames.frd_from_flu(np.array([0.0, 0.0, self.model.yaw_rate]))
        if msg_id == _M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION:
            q = frames.quat_ned_frd_from_matrix_enu_flu(R)
            self._send(self.link.mav.attitude_quaternion_encode(self.time_boot_ms(), *q, *rates_frd))
        elif msg_id == _M.MAVLINK_MSG_ID_ATTITUDE:
            R_ned_frd = frames.R_ENU_NED @ R @ frames.R_FLU_FRD
            roll = math.atan2(R_ned_frd[2, 1], R_ned_frd[2, 2])
            pitch = math.asin(float(np.clip(-R_ned_frd[2, 0], -1.0, 1.0)))
            yaw = math.atan2(R_ned_frd[1, 0], R_ned_frd[0, 0])
            self._send(self.link.mav.attitude_encode(self.time_boot_ms(), roll, pitch, yaw, *rates_frd))
