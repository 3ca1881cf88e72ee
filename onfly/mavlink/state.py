"""Vehicle state from MAVLink telemetry, in ENU, on the companion's monotonic clock.

:class:`StateReader` consumes the autopilot's messages (LOCAL_POSITION_NED, ATTITUDE,
ATTITUDE_QUATERNION, ODOMETRY, HEARTBEAT), ignores everything else and everything from other
systems or components, and assembles a :class:`planning.trajectory.VehicleState` in ENU through
:mod:`onfly.mavlink.frames`.

Time
----
Autopilots stamp telemetry with their boot time (``time_boot_ms``, uint32 milliseconds, or
``time_usec``). :class:`VehicleClockSync` maps it onto the companion clock with the smallest
observed one-way offset ``offset = min(t_rx - t_vehicle)`` (the sample can never be newer than
its arrival), letting the offset creep up by ``drift_ppm`` so a slow vehicle crystal cannot
freeze it. A 2^32 ms wrap is unwrapped; a jump backwards larger than ``reset_threshold_s``
(a reboot) re-synchronizes; a smaller step backwards is an out-of-order or repeated sample and
is dropped. Output times are monotonic (never decrease) and never later than their arrival.

A sample whose vehicle time does not advance (a frozen estimator re-sending the same message)
does not refresh the odometry age, so a frozen stream reads as stale.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from onfly.mavlink import frames
from onfly.mavlink.link import mavlink2
from planning.frames import wrap_angle
from planning.trajectory import VehicleState

__all__ = ["StateReaderConfig", "VehicleClockSync", "VehicleStatus", "StateReader"]

log = logging.getLogger(__name__)

_WRAP_MS = 2**32


@dataclass(frozen=True)
class StateReaderConfig:
    """Which vehicle to listen to and how to treat its clock.

    Attributes
    ----------
    target_system : int, the autopilot's MAVLink system id (1..255)
    target_component : int, the autopilot's component id (MAV_COMP_ID_AUTOPILOT1 = 1)
    reset_threshold_s : float, a backwards step of vehicle time larger than this is a reboot
    drift_ppm : float, how fast the clock offset may creep up (parts per million of elapsed time)
    """

    target_system: int = 1
    target_component: int = mavlink2.MAV_COMP_ID_AUTOPILOT1
    reset_threshold_s: float = 2.0
    drift_ppm: float = 200.0

    def __post_init__(self) -> None:
        if not 1 <= int(self.target_system) <= 255:
            raise ValueError(f"target_system must be in [1, 255], got {self.target_system}")
        if not 0 <= int(self.target_component) <= 255:
            raise ValueError(f"target_component must be in [0, 255], got {self.target_component}")
        if not (self.reset_threshold_s > 0 and np.isfinite(self.reset_threshold_s)):
            raise ValueError(f"reset_threshold_s must be positive, got {self.reset_threshold_s}")
        if not (0 <= self.drift_ppm < 1e5):
            raise ValueError(f"drift_ppm must be in [0, 1e5), got {self.drift_ppm}")


class VehicleClockSync:
    """Maps one stream of vehicle timestamps onto the companion clock (see module docstring)."""

    def __init__(self, reset_threshold_s: float = 2.0, drift_ppm: float = 200.0, name: str = "stream") -> None:
        self.reset_threshold_s = float(reset_threshold_s)
        self.drift = float(drift_ppm) * 1e-6
        self.name = name
        self._wraps = 0
        self._last_raw_ms: int | None = None
        self._last_vehicle_s: float | None = None
        self._offset_s: float | None = None
        self._last_rx_s: float | None = None
        self._last_out_s = -np.inf
        self.resets = 0
        self.dropped = 0

    def from_boot_ms(self, time_boot_ms: int, t_rx_s: float) -> float | None:
        """Companion time (s) of a sample stamped ``time_boot_ms``, or None if not newer."""
        raw = int(time_boot_ms) % _WRAP_MS
        if self._last_raw_ms is not None and raw < self._last_raw_ms:
            if self._last_raw_ms - raw > _WRAP_MS // 2:
                self._wraps += 1  # uint32 rollover after 49.7 days
        self._last_raw_ms = raw
        return self.from_vehicle_s((raw + self._wraps * _WRAP_MS) * 1e-3, t_rx_s)

    def from_usec(self, time_usec: int, t_rx_s: float) -> float | None:
        """Companion time (s) of a sample stamped ``time_usec`` (uint64), or None if not newer."""
        return self.from_vehicle_s(int(time_usec) * 1e-6, t_rx_s)

    def from_vehicle_s(self, t_vehicle_s: float, t_rx_s: float) -> float | None:
        if self._last_vehicle_s is not None:
            step = t_vehicle_s - self._last_vehicle_s
            if step < -self.reset_threshold_s:
                log.warning("%s: vehicle clock jumped back %.3f s (reboot?); re-synchronizing", self.name, -step)
                self.resets += 1
                self._offset_s = None
            elif step <= 0.0:
                self.dropped += 1
                return None
        self._last_vehicle_s = t_vehicle_s
        candidate = t_rx_s - t_vehicle_s
        if self._offset_s is None:
            self._offset_s = candidate
        else:
            creep = self.drift * max(0.0, t_rx_s - self._last_rx_s)
            self._offset_s = min(self._offset_s + creep, candidate)
        self._last_rx_s = t_rx_s
        t_out = min(t_vehicle_s + self._offset_s, t_rx_s)
        t_out = max(t_out, self._last_out_s)
        self._last_out_s = t_out
        return t_out


@dataclass(frozen=True)
class VehicleStatus:
    """What the autopilot's HEARTBEAT says.

    Attributes
    ----------
    t_s : float, companion time the heartbeat arrived, seconds
    autopilot : int, MAV_AUTOPILOT (12 = PX4, 3 = ArduPilot)
    vehicle_type : int, MAV_TYPE
    base_mode : int, MAV_MODE_FLAG bits
    custom_mode : int, autopilot-specific mode (see :mod:`onfly.mavlink.autopilot`)
    system_status : int, MAV_STATE
    """

    t_s: float
    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    system_status: int

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED)


class StateReader:
    """Assembles the latest :class:`VehicleState` (ENU) from the autopilot's telemetry.

    Feed it every received message with :meth:`handle`; it is thread-safe (one writer, many
    readers). ``clock`` is the companion's monotonic clock in seconds (defaults to
    ``time.monotonic``); replays pass each message's receive time to :meth:`handle` instead.

    Position and velocity come from LOCAL_POSITION_NED or ODOMETRY, heading and heading rate
    from ATTITUDE, ATTITUDE_QUATERNION or ODOMETRY, whichever arrived last.
    """

    def __init__(self, config: StateReaderConfig = StateReaderConfig(), clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.clock = clock
        self._lock = threading.Lock()
        self._sync = {
            name: VehicleClockSync(config.reset_threshold_s, config.drift_ppm, name)
            for name in ("position", "attitude", "odometry")
        }
        self._p = self._v = None
        self._t_pos: float | None = None
        self._yaw: float | None = None
        self._yaw_rate = 0.0
        self._R_enu_flu: np.ndarray | None = None
        self._t_att: float | None = None
        self._status: VehicleStatus | None = None
        self._t_any: float | None = None
        self.counts = {"accepted": 0, "foreign": 0, "ignored": 0, "rejected": 0}
        self._handlers = {
            "LOCAL_POSITION_NED": self._on_local_position,
            "ATTITUDE": self._on_attitude,
            "ATTITUDE_QUATERNION": self._on_attitude_quaternion,
            "ODOMETRY": self._on_odometry,
            "HEARTBEAT": self._on_heartbeat,
        }

    # -- input ------------------------------------------------------------------------------
    def handle(self, msg, t_rx_s: float | None = None) -> bool:
        """Consume one message; True if it came from the target and updated the state.

        Messages from other systems/components are counted as ``foreign``; message types this
        reader does not use as ``ignored``; non-finite or out-of-frame values as ``rejected``.
        Never raises on message content.
        """
        t_rx = self.clock() if t_rx_s is None else float(t_rx_s)
        try:
            src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        except AttributeError:
            self.counts["rejected"] += 1
            return False
        if src_sys != self.config.target_system or src_comp != self.config.target_component:
            self.counts["foreign"] += 1
            return False
        with self._lock:
            self._t_any = t_rx
            handler = self._handlers.get(msg.get_type())
            if handler is None:
                self.counts["ignored"] += 1
                return False
            try:
                ok = handler(msg, t_rx)
            except (ValueError, TypeError, ArithmeticError) as exc:  # malformed content is data, not a crash
                log.debug("rejected %s: %s", msg.get_type(), exc)
                ok = False
            self.counts["accepted" if ok else "rejected"] += 1
            return ok

    def _on_local_position(self, msg, t_rx: float) -> bool:
        ned = np.array([[msg.x, msg.y, msg.z], [msg.vx, msg.vy, msg.vz]], dtype=float)
        if not np.all(np.isfinite(ned)):
            return False
        t = self._sync["position"].from_boot_ms(msg.time_boot_ms, t_rx)
        if t is None:
            return False
        enu = frames.enu_from_ned(ned)
        self._p, self._v, self._t_pos = enu[0], enu[1], t
        return True

    def _set_attitude(self, R_ned_frd: np.ndarray, body_rates_frd, t: float) -> None:
        R_enu_flu = frames.R_ENU_NED @ R_ned_frd @ frames.R_FLU_FRD
        roll = np.arctan2(R_ned_frd[2, 1], R_ned_frd[2, 2])
        pitch = np.arcsin(np.clip(-R_ned_frd[2, 0], -1.0, 1.0))
        yaw_rate_ned = frames.euler_rates_from_body_rates(roll, pitch, body_rates_frd)[2]
        self._R_enu_flu = R_enu_flu
        self._yaw = wrap_angle(float(np.arctan2(R_enu_flu[1, 0], R_enu_flu[0, 0])))
        self._yaw_rate = float(frames.yaw_rate_enu_from_ned(yaw_rate_ned))
        self._t_att = t

    def _on_attitude(self, msg, t_rx: float) -> bool:
        vals = np.array([msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if not np.all(np.isfinite(vals)):
            return False
        t = self._sync["attitude"].from_boot_ms(msg.time_boot_ms, t_rx)
        if t is None:
            return False
        R = frames.matrix_ned_frd_from_euler(vals[0], vals[1], vals[2])
        self._set_attitude(R, vals[3:], t)
        return True

    def _on_attitude_quaternion(self, msg, t_rx: float) -> bool:
        q = np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=float)
        rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(rates))) or abs(np.linalg.norm(q) - 1.0) > 0.05:
            return False
        t = self._sync["attitude"].from_boot_ms(msg.time_boot_ms, t_rx)
        if t is None:
            return False
        self._set_attitude(frames.matrices_from_quats(q), rates, t)
        return True

    def _on_odometry(self, msg, t_rx: float) -> bool:
        if msg.frame_id not in (mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_LOCAL_FRD):
            return False
        q = np.array(msg.q, dtype=float)
        pos = np.array([msg.x, msg.y, msg.z], dtype=float)
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if not all(np.all(np.isfinite(a)) for a in (q, pos, vel, rates)) or abs(np.linalg.norm(q) - 1.0) > 0.05:
            return False
        R_ned_frd = frames.matrices_from_quats(q)
        if msg.child_frame_id == mavlink2.MAV_FRAME_BODY_FRD:
            vel_ned = R_ned_frd @ vel  # PX4 sends velocity in the body frame
        elif msg.child_frame_id in (mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_LOCAL_FRD):
            vel_ned = vel
        else:
            return False
        t = self._sync["odometry"].from_usec(msg.time_usec, t_rx)
        if t is None:
            return False
        enu = frames.enu_from_ned(np.stack([pos, vel_ned]))
        self._p, self._v, self._t_pos = enu[0], enu[1], t
        self._set_attitude(R_ned_frd, rates, t)
        return True

    def _on_heartbeat(self, msg, t_rx: float) -> bool:
        if msg.type in (mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER):
            return False
        self._status = VehicleStatus(t_rx, int(msg.autopilot), int(msg.type), int(msg.base_mode), int(msg.custom_mode), int(msg.system_status))
        return True

    # -- output -----------------------------------------------------------------------------
    def state(self) -> VehicleState | None:
        """Latest state (ENU, ``t_s`` = time of the position sample), or None before both a
        position and an attitude have arrived."""
        with self._lock:
            if self._p is None or self._yaw is None:
                return None
            return VehicleState(t_s=self._t_pos, p=self._p.copy(), v=self._v.copy(), yaw=self._yaw, yaw_rate=self._yaw_rate)

    def attitude(self) -> np.ndarray | None:
        """Latest body attitude ``R_enu_flu``, shape (3, 3), or None."""
        with self._lock:
            return None if self._R_enu_flu is None else self._R_enu_flu.copy()

    def status(self) -> VehicleStatus | None:
        """Latest autopilot HEARTBEAT, or None."""
        with self._lock:
            return self._status

    def clock_resets(self) -> dict[str, int]:
        """How many vehicle-clock resets (reboots) each stream has seen."""
        with self._lock:
            return {name: sync.resets for name, sync in self._sync.items()}

    def odometry_age_s(self, now_s: float | None = None) -> float:
        """Seconds since the newest position sample was taken (inf before the first)."""
        now = self.clock() if now_s is None else now_s
        with self._lock:
            return np.inf if self._t_pos is None else max(0.0, now - self._t_pos)

    def heartbeat_age_s(self, now_s: float | None = None) -> float:
        """Seconds since the last autopilot HEARTBEAT arrived (inf before the first)."""
        now = self.clock() if now_s is None else now_s
        with self._lock:
            return np.inf if self._status is None else max(0.0, now - self._status.t_s)

    def link_age_s(self, now_s: float | None = None) -> float:
        """Seconds since ANY message from the autopilot arrived (inf before the first).

        Telemetry streams at >= 10 Hz, so this notices a dead link within a few tens of
        milliseconds of the timeout, where the 1 Hz HEARTBEAT alone would need seconds.
        """
        now = self.clock() if now_s is None else now_s
        with self._lock:
            return np.inf if self._t_any is None else max(0.0, now - self._t_any)
