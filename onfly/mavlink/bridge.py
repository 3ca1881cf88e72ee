"""MavlinkBridge: the companion computer's side of the autopilot link.

Threads
-------
- **receiver**: reads every message from the :class:`~onfly.mavlink.link.Link`, feeds the
  :class:`~onfly.mavlink.state.StateReader`, delivers COMMAND_ACKs to waiting commands and calls
  status listeners on the autopilot's HEARTBEAT.
- **streamer**: at ``setpoint_rate_hz`` (default 20 Hz) evaluates the failsafes and sends one
  SET_POSITION_TARGET_LOCAL_NED; every ``heartbeat_period_s`` (1 s) it sends the companion
  HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER from component MAV_COMP_ID_ONBOARD_COMPUTER).

Neither thread ever waits for the planner or the VLM: the pilot hands over a new
:class:`~planning.trajectory.Trajectory` with :meth:`MavlinkBridge.set_trajectory` (an atomic
reference swap), or installs a setpoint callback with :meth:`MavlinkBridge.set_setpoint_source`,
and reads :meth:`MavlinkBridge.state` (a :class:`~planning.trajectory.VehicleState` in ENU).
The trajectory is sampled at ``clock()``, so the pilot must build the bridge with its own clock
(``MavlinkBridge(link, config, clock=pilot_clock)``).

How the pilot plugs in::

    with MavlinkBridge.from_url("udpin:0.0.0.0:14540", BridgeConfig(), clock=pilot_clock) as bridge:
        bridge.wait_for_vehicle(timeout_s=10.0)
        bridge.request_message_intervals()
        session = make_session("px4", bridge)        # onfly.mavlink.autopilot
        session.engage()                             # streams, arms, OFFBOARD; watches takeover
        while not bridge.released:
            state = bridge.state()                   # VehicleState, ENU, pilot clock
            result = planner.step(state, goal, esdf)
            bridge.set_trajectory(result.trajectory)
            bridge.failsafe.report_planner(state.t_s, ok=result.ok)
            # VLM outcomes: bridge.failsafe.report_vlm_ok(t) / report_vlm_failure(t, cause)
    summary = [e.as_dict() for e in bridge.failsafe.events]

Frames
------
Telemetry arrives in the autopilot's estimator frame (LOCAL_POSITION_NED, relative to the
EKF origin). :meth:`MavlinkBridge.anchor_world` anchors the pilot's world frame at the
vehicle's current pose (origin at its position, x along its heading, z up); from then on
:meth:`~MavlinkBridge.state`, :meth:`~MavlinkBridge.attitude` and every setpoint are in that
world frame and converted at the MAVLink boundary (``T_local_world``).

type_mask (POSITION_TARGET_TYPEMASK: a set bit means *ignore* that field)
-----------------------------------------------------------------------------
============  ==========================================  ================
kind          fields used                                 type_mask
============  ==========================================  ================
TRACK         x y z, vx vy vz, afx afy afz, yaw            0x0800 (2048)
HOLD          x y z, yaw                                   0x09F8 (2552)
BRAKE         vx vy vz (= 0), yaw                          0x09C7 (2503)
============  ==========================================  ================

All use MAV_FRAME_LOCAL_NED; all three are combinations PX4 offboard and ArduCopter guided
accept (all three axes of each used vector). ``yaw_rate`` is always ignored: the yaw setpoint
already follows the plan at 20 Hz.

Every setpoint passes :meth:`MavlinkBridge.send_setpoint`, which clips it to
:class:`SafetyLimits` and returns what was actually sent (LeRobot ``send_action`` style).
"""

from __future__ import annotations

import collections
import enum
import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from onfly.mavlink import frames
from onfly.mavlink.failsafe import FailsafeAction, FailsafeConfig, FailsafeMonitor
from onfly.mavlink.link import Link, LinkError, MavlinkLink, mavlink2
from onfly.mavlink.state import StateReader, StateReaderConfig, VehicleStatus
from planning.frames import wrap_angle
from planning.trajectory import Trajectory, VehicleState

__all__ = [
    "BridgeError",
    "CommandError",
    "CommandTimeoutError",
    "CommandRejectedError",
    "SetpointKind",
    "Setpoint",
    "SafetyLimits",
    "BridgeConfig",
    "MavlinkBridge",
    "TYPE_MASK",
    "result_name",
    "command_name",
]

log = logging.getLogger(__name__)

_M = mavlink2
_IGNORE_POS = _M.POSITION_TARGET_TYPEMASK_X_IGNORE | _M.POSITION_TARGET_TYPEMASK_Y_IGNORE | _M.POSITION_TARGET_TYPEMASK_Z_IGNORE
_IGNORE_VEL = _M.POSITION_TARGET_TYPEMASK_VX_IGNORE | _M.POSITION_TARGET_TYPEMASK_VY_IGNORE | _M.POSITION_TARGET_TYPEMASK_VZ_IGNORE
_IGNORE_ACC = _M.POSITION_TARGET_TYPEMASK_AX_IGNORE | _M.POSITION_TARGET_TYPEMASK_AY_IGNORE | _M.POSITION_TARGET_TYPEMASK_AZ_IGNORE
_IGNORE_YAW_RATE = _M.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE


class BridgeError(RuntimeError):
    """The bridge cannot do what was asked (not started, no vehicle, bad input)."""


class CommandError(BridgeError):
    """A COMMAND_LONG that did not succeed."""

    def __init__(self, message: str, command: int, result: int | None = None) -> None:
        super().__init__(message)
        self.command = command
        self.result = result


class CommandTimeoutError(CommandError):
    """No COMMAND_ACK arrived within the timeout (after the allowed retries)."""


class CommandRejectedError(CommandError):
    """The autopilot answered with a result other than MAV_RESULT_ACCEPTED."""


def command_name(command: int) -> str:
    entry = _M.enums["MAV_CMD"].get(int(command))
    return entry.name if entry is not None else f"MAV_CMD_{command}"


def result_name(result: int) -> str:
    entry = _M.enums["MAV_RESULT"].get(int(result))
    return entry.name if entry is not None else f"MAV_RESULT_{result}"


class SetpointKind(str, enum.Enum):
    TRACK = "track"
    HOLD = "hold"
    BRAKE = "brake"


#: type_mask per setpoint kind (see the module docstring).
TYPE_MASK = {
    SetpointKind.TRACK: _IGNORE_YAW_RATE,
    SetpointKind.HOLD: _IGNORE_VEL | _IGNORE_ACC | _IGNORE_YAW_RATE,
    SetpointKind.BRAKE: _IGNORE_POS | _IGNORE_ACC | _IGNORE_YAW_RATE,
}


@dataclass(frozen=True, eq=False)
class Setpoint:
    """One motion setpoint in ENU.

    Attributes
    ----------
    t_s : float, bridge clock time it refers to, seconds
    kind : SetpointKind, which fields the vehicle uses (see :data:`TYPE_MASK`)
    p : array (3,), position, metres, ENU (used by TRACK and HOLD)
    v : array (3,), velocity feed-forward, m/s, ENU (used by TRACK; BRAKE sends zeros)
    a : array (3,), acceleration feed-forward, m/s^2, ENU (used by TRACK)
    yaw : float, heading of body x, radians, ENU, wrapped to (-pi, pi]
    clipped : bool, True if :meth:`MavlinkBridge.send_setpoint` changed it
    """

    t_s: float
    kind: SetpointKind
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: float
    clipped: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", SetpointKind(self.kind))
        for name in ("p", "v", "a"):
            arr = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if arr.shape != (3,):
                raise ValueError(f"Setpoint.{name} must have shape (3,), got {np.shape(getattr(self, name))}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"Setpoint.{name} is not finite: {arr}")
            object.__setattr__(self, name, arr)
        if not (math.isfinite(self.t_s) and math.isfinite(self.yaw)):
            raise ValueError(f"Setpoint t_s and yaw must be finite, got t_s={self.t_s} yaw={self.yaw}")
        object.__setattr__(self, "yaw", wrap_angle(float(self.yaw)))

    @property
    def type_mask(self) -> int:
        return TYPE_MASK[self.kind]

    @classmethod
    def hold(cls, t_s: float, p, yaw: float) -> "Setpoint":
        return cls(t_s, SetpointKind.HOLD, p, np.zeros(3), np.zeros(3), yaw)

    @classmethod
    def brake(cls, t_s: float, p, yaw: float) -> "Setpoint":
        return cls(t_s, SetpointKind.BRAKE, p, np.zeros(3), np.zeros(3), yaw)

    @classmethod
    def from_trajectory(cls, traj: Trajectory, t_s: float) -> "Setpoint":
        """Sample ``traj`` at ``t_s``; past its end, HOLD at its last knot."""
        if t_s > traj.t0_s + traj.duration_s:
            return cls.hold(t_s, traj.p[-1], wrap_angle(traj.yaw[-1]))
        p, v, a, yaw, _ = traj.sample(t_s)
        return cls(t_s, SetpointKind.TRACK, p, v, a, yaw)


def _triple(x, name: str) -> tuple[float, float, float]:
    t = tuple(float(v) for v in x)
    if len(t) != 3 or not all(math.isfinite(v) for v in t):
        raise ValueError(f"{name} must be three finite numbers, got {x!r}")
    return t


@dataclass(frozen=True)
class SafetyLimits:
    """Clipping applied to every setpoint before it leaves the companion.

    Attributes
    ----------
    v_max_mps : float, norm limit of the velocity feed-forward
    a_max_mps2 : float, norm limit of the acceleration feed-forward
    leash_m : float, a position setpoint is pulled to within this distance of the vehicle
    fence_min_m, fence_max_m : (3,) ENU box, metres, position setpoints are clipped into it
    """

    v_max_mps: float = 3.0
    a_max_mps2: float = 3.0
    leash_m: float = 3.0
    fence_min_m: tuple = (-100.0, -100.0, 0.0)
    fence_max_m: tuple = (100.0, 100.0, 30.0)

    def __post_init__(self) -> None:
        for name in ("v_max_mps", "a_max_mps2", "leash_m"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive, got {val}")
        lo, hi = _triple(self.fence_min_m, "fence_min_m"), _triple(self.fence_max_m, "fence_max_m")
        if any(a >= b for a, b in zip(lo, hi)):
            raise ValueError(f"fence_min_m must be below fence_max_m on every axis, got {lo} and {hi}")
        object.__setattr__(self, "fence_min_m", lo)
        object.__setattr__(self, "fence_max_m", hi)

    @classmethod
    def for_vehicle(cls, v_max_mps: float, a_max_mps2: float, volume=None, tolerance_rel: float = 0.01, **kw) -> "SafetyLimits":
        """The limits the planner plans with (speed and acceleration norms, plus
        ``tolerance_rel`` for the planner's own cutting-plane tolerance) and the operator's
        flight volume (:class:`planning.volume.FlightVolume`, the pilot's world frame) as the
        fence, so the companion never sends what the planner would not plan."""
        if volume is not None:
            kw.setdefault("fence_min_m", tuple(float(x) for x in volume.min_m))
            kw.setdefault("fence_max_m", tuple(float(x) for x in volume.max_m))
        return cls(v_max_mps=v_max_mps * (1.0 + tolerance_rel), a_max_mps2=a_max_mps2 * (1.0 + tolerance_rel), **kw)


@dataclass(frozen=True)
class BridgeConfig:
    """Everything the bridge needs to talk to one autopilot.

    Attributes
    ----------
    target_system, target_component : the autopilot's ids
    source_system, source_component : our ids; a companion shares the vehicle's system id and
        signs as MAV_COMP_ID_ONBOARD_COMPUTER (191), as MAVROS does. The link must use them.
    setpoint_rate_hz : streamer rate
    heartbeat_period_s : companion heartbeat period
    telemetry_rate_hz : rate requested with SET_MESSAGE_INTERVAL for ``telemetry_messages``
    telemetry_messages : message ids to request (LOCAL_POSITION_NED, ATTITUDE_QUATERNION)
    command_timeout_s : wait for a COMMAND_ACK per attempt
    command_retries : re-sends (with ``confirmation`` incremented) after a timeout
    setpoint_log_len : how many sent setpoints :attr:`MavlinkBridge.sent` keeps
    """

    target_system: int = 1
    target_component: int = _M.MAV_COMP_ID_AUTOPILOT1
    source_system: int = 1
    source_component: int = _M.MAV_COMP_ID_ONBOARD_COMPUTER
    setpoint_rate_hz: float = 20.0
    heartbeat_period_s: float = 1.0
    telemetry_rate_hz: float = 50.0
    telemetry_messages: tuple = (_M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, _M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)
    command_timeout_s: float = 1.0
    command_retries: int = 2
    setpoint_log_len: int = 20000
    limits: SafetyLimits = field(default_factory=SafetyLimits)
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig)

    def __post_init__(self) -> None:
        for name in ("target_system", "source_system"):
            if not 1 <= int(getattr(self, name)) <= 255:
                raise ValueError(f"{name} must be in [1, 255], got {getattr(self, name)}")
        for name in ("target_component", "source_component"):
            if not 0 <= int(getattr(self, name)) <= 255:
                raise ValueError(f"{name} must be in [0, 255], got {getattr(self, name)}")
        for name in ("setpoint_rate_hz", "telemetry_rate_hz"):
            val = getattr(self, name)
            if not (math.isfinite(val) and 2.0 < val <= 500.0):
                raise ValueError(f"{name} must be in (2, 500] Hz (PX4 needs > 2 Hz), got {val}")
        for name in ("heartbeat_period_s", "command_timeout_s"):
            val = getattr(self, name)
            if not (math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive, got {val}")
        if not 0 <= int(self.command_retries) <= 10:
            raise ValueError(f"command_retries must be in [0, 10], got {self.command_retries}")
        if int(self.setpoint_log_len) < 1:
            raise ValueError(f"setpoint_log_len must be >= 1, got {self.setpoint_log_len}")

    @property
    def setpoint_period_s(self) -> float:
        return 1.0 / self.setpoint_rate_hz


class _StreamMode(enum.Enum):
    IDLE = "idle"  # heartbeats only
    ACTIVE = "active"  # setpoints every tick
    RELEASED = "released"  # the vehicle was taken over: never command motion again


class MavlinkBridge:
    """Companion side of one autopilot link (see the module docstring).

    Use as a context manager or call :meth:`start` / :meth:`stop`. Setpoints only flow after
    :meth:`start_streaming` (the autopilot session does that); before, only heartbeats go out.
    """

    def __init__(self, link: Link, config: BridgeConfig = BridgeConfig(), clock: Callable[[], float] = time.monotonic) -> None:
        if (link.source_system, link.source_component) != (config.source_system, config.source_component):
            raise ValueError(
                f"link signs as {link.source_system}/{link.source_component} but the bridge config says "
                f"{config.source_system}/{config.source_component}; build the link with the config's ids (or use MavlinkBridge.from_url)"
            )
        self.link = link
        self.config = config
        self.clock = clock
        self.reader = StateReader(StateReaderConfig(config.target_system, config.target_component), clock=clock)
        self.failsafe = FailsafeMonitor(config.failsafe, start_s=clock())
        self._t_start = clock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._mode = _StreamMode.IDLE
        self._mode_lock = threading.Lock()
        self._trajectory: Trajectory | None = None
        self._source: Callable[[float], Setpoint | None] | None = None
        self._hold: Setpoint | None = None
        self._hold_cause: FailsafeAction | None = None
        self._stream_start_s: float | None = None
        self._ack_cond = threading.Condition()
        self._acks: dict[int, tuple[int, float]] = {}
        self._listeners: list[Callable[[VehicleStatus], None]] = []
        self._vehicle_seen = threading.Event()
        self._anchor: tuple[np.ndarray, np.ndarray, float] | None = None  # (R_local_world, p0_local, yaw0)
        self.sent: collections.deque[Setpoint] = collections.deque(maxlen=config.setpoint_log_len)
        self.release_reason: str | None = None
        self.errors: list[str] = []

    @classmethod
    def from_url(cls, url: str, config: BridgeConfig = BridgeConfig(), clock: Callable[[], float] = time.monotonic, baud: int = 921600) -> "MavlinkBridge":
        """A bridge over a :class:`~onfly.mavlink.link.MavlinkLink` on ``url`` signed with the config's ids."""
        return cls(MavlinkLink(url, config.source_system, config.source_component, baud=baud), config, clock)

    # -- lifecycle --------------------------------------------------------------------------
    def start(self) -> "MavlinkBridge":
        if self._threads:
            raise BridgeError("bridge already started")
        if not self.link.is_connected:
            self.link.connect()
        self._stop.clear()
        self._threads = [
            threading.Thread(target=self._receive_loop, name="mavlink-rx", daemon=True),
            threading.Thread(target=self._stream_loop, name="mavlink-tx", daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        """Stop both threads (motion commands end first) and close the link."""
        self.stop_streaming()
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        self.link.close()

    def __enter__(self) -> "MavlinkBridge":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def wait(self, timeout_s: float) -> bool:
        """Wait ``timeout_s`` seconds of real time, returning early (True) if the bridge stops."""
        return self._stop.wait(timeout_s)

    @property
    def running(self) -> bool:
        return bool(self._threads) and not self._stop.is_set()

    def wait_for_vehicle(self, timeout_s: float) -> VehicleStatus:
        """Block until the autopilot's HEARTBEAT has been seen; raises BridgeError on timeout."""
        if not self._vehicle_seen.wait(timeout_s):
            raise BridgeError(
                f"no HEARTBEAT from system {self.config.target_system} component {self.config.target_component} within {timeout_s} s"
            )
        return self.reader.status()

    def wait_for_state(self, timeout_s: float) -> VehicleState:
        """Block until position and attitude have arrived; raises BridgeError on timeout."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.state()
            if st is not None:
                return st
            if time.monotonic() >= deadline or self._stop.wait(0.01):
                raise BridgeError(f"no LOCAL_POSITION_NED/ATTITUDE from the vehicle within {timeout_s} s")

    # -- pilot interface --------------------------------------------------------------------
    def state(self) -> VehicleState | None:
        """Latest vehicle state in the pilot's world frame (ENU; the estimator's local frame
        until :meth:`anchor_world`) on the bridge clock, or None before telemetry."""
        st = self.reader.state()
        anchor = self._anchor
        if st is None or anchor is None:
            return st
        R = anchor[0].T
        return VehicleState(t_s=st.t_s, p=R @ (st.p - anchor[1]), v=R @ st.v, yaw=wrap_angle(st.yaw - anchor[2]), yaw_rate=st.yaw_rate)

    def attitude(self) -> np.ndarray | None:
        """Latest body attitude ``R_world_flu`` (3, 3) in the pilot's world frame, or None."""
        R = self.reader.attitude()
        anchor = self._anchor
        if R is None or anchor is None:
            return R
        return anchor[0].T @ R

    def anchor_world(self) -> np.ndarray:
        """Anchor the pilot's world frame at the vehicle's current estimated pose: origin at its
        position, x axis along its heading, z up (so heights are relative to where the flight
        starts). Returns ``T_local_world`` (4, 4): world coordinates -> the estimator's local ENU
        frame (LOCAL_POSITION_NED as ENU). Call it once, before streaming starts; setpoints are
        converted back to the local frame as they are sent."""
        st = self.reader.state()
        if st is None:
            raise BridgeError("cannot anchor the world frame before the vehicle's position and attitude arrived")
        c, s_ = np.cos(st.yaw), np.sin(st.yaw)
        R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        self._anchor = (R, st.p.copy(), float(st.yaw))
        return self.T_local_world

    @property
    def T_local_world(self) -> np.ndarray:
        """(4, 4) world -> estimator-local ENU transform (identity before :meth:`anchor_world`)."""
        T = np.eye(4)
        if self._anchor is not None:
            T[:3, :3] = self._anchor[0]
            T[:3, 3] = self._anchor[1]
        return T

    def status(self) -> VehicleStatus | None:
        return self.reader.status()

    def set_trajectory(self, traj: Trajectory | None) -> None:
        """Fly ``traj`` from the next streamer tick on (atomic swap; never blocks)."""
        if traj is not None and not isinstance(traj, Trajectory):
            raise TypeError(f"set_trajectory needs a planning.trajectory.Trajectory, got {type(traj).__name__}")
        self._trajectory = traj

    def set_setpoint_source(self, source: Callable[[float], Setpoint | None] | None) -> None:
        """Alternative to a trajectory: ``source(t_s)`` is called every tick; it must be fast and
        never block. Returning None (or raising) holds position."""
        self._source = source

    def add_status_listener(self, fn: Callable[[VehicleStatus], None]) -> None:
        """``fn(status)`` runs in the receiver thread on every autopilot HEARTBEAT."""
        self._listeners.append(fn)

    # -- streaming control ------------------------------------------------------------------
    def start_streaming(self) -> None:
        """Begin sending setpoints every tick (from the trajectory, else hold where we are)."""
        with self._mode_lock:
            if self._mode is _StreamMode.RELEASED:
                raise BridgeError(f"bridge was released ({self.release_reason}); it will not command motion again")
            if self._mode is _StreamMode.IDLE:
                self._mode = _StreamMode.ACTIVE
                self._stream_start_s = None
                self._hold = None

    def stop_streaming(self) -> None:
        """Back to heartbeats only (the autopilot's own offboard-loss failsafe takes over)."""
        with self._mode_lock:
            if self._mode is _StreamMode.ACTIVE:
                self._mode = _StreamMode.IDLE
                self._stream_start_s = None

    def release(self, reason: str) -> None:
        """Stop commanding motion for good (a pilot took over). Idempotent."""
        with self._mode_lock:
            if self._mode is not _StreamMode.RELEASED:
                self._mode = _StreamMode.RELEASED
                self.release_reason = reason
                log.warning("bridge released: %s; no more motion commands", reason)

    @property
    def streaming(self) -> bool:
        return self._mode is _StreamMode.ACTIVE

    @property
    def released(self) -> bool:
        return self._mode is _StreamMode.RELEASED

    def streamed_for_s(self, now_s: float | None = None) -> float:
        """Seconds since the first setpoint of the current uninterrupted stream (0 if none)."""
        start = self._stream_start_s
        if start is None or not self.streaming:
            return 0.0
        return (self.clock() if now_s is None else now_s) - start

    def wait_streamed(self, duration_s: float, timeout_s: float) -> None:
        """Block until setpoints have streamed for ``duration_s``; BridgeError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while self.streamed_for_s() < duration_s:
            if time.monotonic() >= deadline:
                raise BridgeError(f"setpoints did not stream for {duration_s} s within {timeout_s} s")
            if self._stop.wait(0.01):
                raise BridgeError("bridge stopped while waiting for the setpoint stream")

    # -- setpoints --------------------------------------------------------------------------
    def clip_setpoint(self, sp: Setpoint, state: VehicleState | None) -> Setpoint:
        """``sp`` limited by :class:`SafetyLimits` (fence, leash around ``state``, v and a norms)."""
        lim = self.config.limits
        p = np.clip(sp.p, lim.fence_min_m, lim.fence_max_m)
        if state is not None and sp.kind is not SetpointKind.BRAKE:
            d = p - state.p
            dist = float(np.linalg.norm(d))
            if dist > lim.leash_m:
                p = np.clip(state.p + d * (lim.leash_m / dist), lim.fence_min_m, lim.fence_max_m)
        v, a = sp.v, sp.a
        nv, na = float(np.linalg.norm(v)), float(np.linalg.norm(a))
        if nv > lim.v_max_mps:
            v = v * (lim.v_max_mps / nv)
        if na > lim.a_max_mps2:
            a = a * (lim.a_max_mps2 / na)
        clipped = not (np.array_equal(p, sp.p) and np.array_equal(v, sp.v) and np.array_equal(a, sp.a))
        if not clipped:
            return sp
        return replace(sp, p=p, v=v, a=a, clipped=True)

    def send_setpoint(self, sp: Setpoint) -> Setpoint:
        """Clip ``sp`` and send it as SET_POSITION_TARGET_LOCAL_NED; returns what was sent.

        Raises BridgeError after :meth:`release` (a taken-over vehicle gets no motion commands).
        """
        if self.released:
            raise BridgeError(f"bridge was released ({self.release_reason}); refusing to send a setpoint")
        sent = self.clip_setpoint(sp, self.state())
        p, v, a, yaw = sent.p, sent.v, sent.a, sent.yaw
        if self._anchor is not None:  # world -> the estimator's local frame
            R, p0, yaw0 = self._anchor
            p, v, a, yaw = R @ p + p0, R @ v, R @ a, wrap_angle(yaw + yaw0)
        p_ned, v_ned, a_ned = frames.ned_from_enu(np.stack([p, v, a]))
        yaw_ned = frames.yaw_ned_from_enu(yaw)
        msg = self.link.mav.set_position_target_local_ned_encode(
            self._time_boot_ms(),
            self.config.target_system,
            self.config.target_component,
            _M.MAV_FRAME_LOCAL_NED,
            sent.type_mask,
            *p_ned, *v_ned, *a_ned,
            yaw_ned,
            0.0,
        )
        self.link.send(msg)
        self.sent.append(sent)
        return sent

    # -- commands ---------------------------------------------------------------------------
    def command_long(self, command: int, params=(), timeout_s: float | None = None, retries: int | None = None) -> int:
        """Send COMMAND_LONG and wait for its COMMAND_ACK; returns the MAV_RESULT.

        MAV_RESULT_IN_PROGRESS keeps waiting. Retries re-send with ``confirmation`` + 1.

        Raises
        ------
        CommandTimeoutError : no final ACK after ``1 + retries`` attempts
        """
        if not self.running:
            raise BridgeError("command_long needs a started bridge (its receiver delivers the ACK)")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        if len(p) != 7:
            raise ValueError(f"COMMAND_LONG takes at most 7 params, got {len(params)}")
        timeout = self.config.command_timeout_s if timeout_s is None else float(timeout_s)
        attempts = 1 + (self.config.command_retries if retries is None else int(retries))
        for confirmation in range(attempts):
            t_sent = self.clock()
            with self._ack_cond:
                self._acks.pop(command, None)
            self.link.send(
                self.link.mav.command_long_encode(self.config.target_system, self.config.target_component, command, confirmation, *p)
            )
            deadline = time.monotonic() + timeout
            with self._ack_cond:
                while True:
                    ack = self._acks.get(command)
                    if ack is not None and ack[1] >= t_sent and ack[0] != _M.MAV_RESULT_IN_PROGRESS:
                        log.debug("%s -> %s", command_name(command), result_name(ack[0]))
                        return ack[0]
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    self._ack_cond.wait(remaining)
            log.warning("no COMMAND_ACK for %s (attempt %d/%d)", command_name(command), confirmation + 1, attempts)
        raise CommandTimeoutError(f"no COMMAND_ACK for {command_name(command)} after {attempts} attempt(s) of {timeout} s", command)

    def command(self, command: int, params=(), timeout_s: float | None = None) -> None:
        """:meth:`command_long` that raises CommandRejectedError unless the result is ACCEPTED."""
        result = self.command_long(command, params, timeout_s)
        if result != _M.MAV_RESULT_ACCEPTED:
            raise CommandRejectedError(f"{command_name(command)} rejected by the vehicle: {result_name(result)}", command, result)

    def request_message_intervals(self) -> dict[int, int]:
        """Ask for ``telemetry_messages`` at ``telemetry_rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL).

        Returns {message id: MAV_RESULT}; a refusal is logged, not raised (the stream may already
        run at the vehicle's default rate; the failsafes watch the real rate anyway).
        """
        interval_us = 1e6 / self.config.telemetry_rate_hz
        results = {}
        for msg_id in self.config.telemetry_messages:
            try:
                results[msg_id] = self.command_long(_M.MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, interval_us))
            except CommandTimeoutError as exc:
                log.warning("message interval for id %d not confirmed: %s", msg_id, exc)
                results[msg_id] = -1
                continue
            if results[msg_id] != _M.MAV_RESULT_ACCEPTED:
                log.warning("vehicle refused interval for message id %d: %s", msg_id, result_name(results[msg_id]))
        return results

    # -- threads ----------------------------------------------------------------------------
    def _time_boot_ms(self) -> int:
        return int((self.clock() - self._t_start) * 1000.0) % 2**32

    def _receive_loop(self) -> None:
        target = (self.config.target_system, self.config.target_component)
        while not self._stop.is_set():
            try:
                msg = self.link.recv(0.05)
            except LinkError as exc:
                if self._stop.is_set():
                    return
                self.errors.append(str(exc))
                log.error("link receive failed: %s", exc)
                self._stop.wait(0.05)
                continue
            if msg is None:
                continue
            try:
                self._dispatch(msg, target)
            except Exception:  # a listener bug must not kill the receiver
                log.exception("error while handling %s", msg.get_type())

    def _dispatch(self, msg, target) -> None:
        accepted = self.reader.handle(msg)
        if (msg.get_srcSystem(), msg.get_srcComponent()) != target:
            return
        mtype = msg.get_type()
        if mtype == "COMMAND_ACK":
            if msg.target_system in (0, self.link.source_system):
                with self._ack_cond:
                    self._acks[int(msg.command)] = (int(msg.result), self.clock())
                    self._ack_cond.notify_all()
        elif mtype == "HEARTBEAT" and accepted:
            self._vehicle_seen.set()
            status = self.reader.status()
            for fn in list(self._listeners):
                fn(status)

    def _send_heartbeat(self) -> None:
        self.link.send(
            self.link.mav.heartbeat_encode(
                _M.MAV_TYPE_ONBOARD_CONTROLLER, _M.MAV_AUTOPILOT_INVALID, 0, 0, _M.MAV_STATE_ACTIVE
            )
        )

    def _stream_loop(self) -> None:
        period = self.config.setpoint_period_s
        now = self.clock()
        next_sp, next_hb = now, now
        while not self._stop.is_set():
            now = self.clock()
            try:
                if now >= next_hb:
                    self._send_heartbeat()
                    next_hb = max(next_hb + self.config.heartbeat_period_s, now)
                if now >= next_sp:
                    self._tick(now)
                    # Keep the grid; if we fell behind by more than a period, re-anchor.
                    next_sp = next_sp + period if now - next_sp < period else now + period
            except (LinkError, BridgeError) as exc:
                self.errors.append(str(exc))
                log.error("streamer: %s", exc)
            self._stop.wait(max(0.0, min(next_sp, next_hb) - self.clock()))

    def _tick(self, now: float) -> None:
        if not self._vehicle_seen.is_set() or (not self.streaming and self.reader.state() is None):
            return  # no contact (or no telemetry while idle) yet: nothing to command, nothing failed
        r = self.reader
        action = self.failsafe.evaluate(now, r.odometry_age_s(now), r.link_age_s(now), r.heartbeat_age_s(now))
        if self._mode is not _StreamMode.ACTIVE or action is FailsafeAction.STOP_STREAMING:
            if action is FailsafeAction.STOP_STREAMING:
                self._stream_start_s = None  # the vehicle must see a fresh stream before re-engaging
            return
        sp = self._choose_setpoint(now, action)
        if sp is None:
            return
        if self._mode is not _StreamMode.ACTIVE:  # released while choosing
            return
        self.send_setpoint(sp)
        if self._stream_start_s is None:
            self._stream_start_s = now

    def _choose_setpoint(self, now: float, action: FailsafeAction) -> Setpoint | None:
        if action in (FailsafeAction.HOLD, FailsafeAction.BRAKE):
            return self._held(now, action)
        sp = None
        source, traj = self._source, self._trajectory
        if source is not None:
            try:
                sp = source(now)
            except Exception:
                log.exception("setpoint source failed; holding")
                sp = None
        elif traj is not None:
            sp = Setpoint.from_trajectory(traj, now)
        if sp is not None:
            self._hold, self._hold_cause = None, None
            return sp
        # Nothing to fly yet: hold where we were when the plan ran out (keeps PX4's stream alive).
        return self._held(now, FailsafeAction.CONTINUE)

    def _held(self, now: float, cause: FailsafeAction) -> Setpoint | None:
        """A HOLD (or BRAKE) setpoint at the point captured when ``cause`` began."""
        if self._hold is None or self._hold_cause is not cause:
            state = self.state()
            if state is not None:
                p, yaw = state.p, state.yaw
            elif self.sent:
                p, yaw = self.sent[-1].p, self.sent[-1].yaw
            else:
                return None
            make = Setpoint.brake if cause is FailsafeAction.BRAKE else Setpoint.hold
            self._hold, self._hold_cause = make(now, p, yaw), cause
        return replace(self._hold, t_s=now)
