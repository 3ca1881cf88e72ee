"""Handing the vehicle to the companion and noticing when a pilot takes it back.

PX4 offboard (:class:`Px4Offboard`)
-----------------------------------
1. wait for the vehicle's state; start streaming HOLD setpoints at the current position;
2. keep streaming for ``prestream_s`` (default 0.5 s). Current PX4 only needs a setpoint
   newer than COM_OF_LOSS_T when OFFBOARD is requested (the simulated vehicle holds us to
   exactly that); the short pre-stream makes sure the first one has arrived;
3. arm (MAV_CMD_COMPONENT_ARM_DISARM, param1 = 1);
4. switch with MAV_CMD_DO_SET_MODE(param1 = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 = 6
   (PX4 main mode OFFBOARD), param3 = 0); PX4's HEARTBEAT reports it as
   ``custom_mode = main << 16 | sub << 24``;
5. wait until the HEARTBEAT shows OFFBOARD and armed.

Every COMMAND_ACK is checked: anything but MAV_RESULT_ACCEPTED raises
:class:`~onfly.mavlink.bridge.CommandRejectedError` naming the command and the result; no ACK
raises :class:`~onfly.mavlink.bridge.CommandTimeoutError`. On failure the session stops
streaming so a half-engaged vehicle is never left with a live stream.

ArduPilot guided (:class:`ArduPilotGuided`)
-------------------------------------------
1. MAV_CMD_DO_SET_MODE(param1 = 1, param2 = 4 (GUIDED)); wait for the HEARTBEAT to show it;
2. arm; 3. MAV_CMD_NAV_TAKEOFF (param7 = altitude, metres above home); wait until the
vehicle is within ``takeoff_tolerance_m`` of it; 4. stream setpoints on all axes
(position, velocity, acceleration, yaw) at the bridge rate, far inside ArduCopter's 3 s guided
timeout (checked at construction).

Hand-over and takeover
----------------------
Before the companion changes the mode itself (Hold at the end, the landing) it calls
:meth:`AutopilotSession.expect` with the HEARTBEAT it expects: that one is a hand-over
(:attr:`AutopilotSession.handover_status`), not a takeover.

After engaging, every autopilot HEARTBEAT is checked (in the bridge's receiver thread): if
the mode is no longer OFFBOARD / GUIDED, or the vehicle disarmed, the session releases the bridge
(no more motion commands, ever) and records a PILOT_TAKEOVER failsafe event. HEARTBEAT is 1 Hz,
so a takeover is noticed within one heartbeat period plus transport delay.
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
from dataclasses import dataclass

from onfly.mavlink.bridge import BridgeError, MavlinkBridge
from onfly.mavlink.link import mavlink2
from onfly.mavlink.state import VehicleStatus

__all__ = [
    "AutopilotError",
    "ModeChangeError",
    "TakeoffError",
    "OffboardConfig",
    "AutopilotSession",
    "Px4Offboard",
    "ArduPilotGuided",
    "make_session",
    "PX4_MAIN",
    "PX4_AUTO_SUB",
    "ARDUCOPTER_MODE",
    "px4_custom_mode",
    "px4_main_mode",
]

log = logging.getLogger(__name__)
_M = mavlink2

#: PX4 main modes (HEARTBEAT custom_mode bits 16..23); sub modes in bits 24..31.
PX4_MAIN = {"manual": 1, "altctl": 2, "posctl": 3, "auto": 4, "acro": 5, "offboard": 6, "stabilized": 7}
#: PX4 AUTO sub modes.
PX4_AUTO_SUB = {"ready": 1, "takeoff": 2, "loiter": 3, "mission": 4, "rtl": 5, "land": 6}
#: ArduCopter flight modes (HEARTBEAT custom_mode).
ARDUCOPTER_MODE = {"stabilize": 0, "acro": 1, "alt_hold": 2, "auto": 3, "guided": 4, "loiter": 5, "rtl": 6, "land": 9, "brake": 17}

def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 HEARTBEAT ``custom_mode`` for a main/sub mode pair."""
    return (int(main) & 0xFF) << 16 | (int(sub) & 0xFF) << 24


def px4_main_mode(custom_mode: int) -> int:
    """PX4 main mode from a HEARTBEAT ``custom_mode``."""
    return (int(custom_mode) >> 16) & 0xFF


class AutopilotError(BridgeError):
    """The vehicle did not enter or stay in the companion's mode."""


class ModeChangeError(AutopilotError):
    """A mode change was acknowledged but the HEARTBEAT never showed it (or showed disarmed)."""


class TakeoffError(AutopilotError):
    """ArduPilot did not reach the takeoff altitude in time."""


@dataclass(frozen=True)
class OffboardConfig:
    """Timing of the engagement sequences (seconds, metres).

    Attributes
    ----------
    prestream_s : PX4: how long setpoints stream before OFFBOARD is requested
    state_timeout_s : wait for the first position + attitude
    confirm_timeout_s : wait for the HEARTBEAT to confirm a mode / armed state
    takeoff_alt_m : ArduPilot takeoff altitude above home
    takeoff_tolerance_m : ArduPilot: takeoff is complete within this of the altitude
    takeoff_timeout_s : ArduPilot: give up on the takeoff after this long
    guided_timeout_s : ArduPilot's guided timeout the setpoint period must stay well inside
    """

    prestream_s: float = 0.5
    state_timeout_s: float = 5.0
    confirm_timeout_s: float = 3.0
    takeoff_alt_m: float = 2.0
    takeoff_tolerance_m: float = 0.25
    takeoff_timeout_s: float = 20.0
    guided_timeout_s: float = 3.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive, got {val!r}")


class AutopilotSession(abc.ABC):
    """Engages one autopilot through a started :class:`MavlinkBridge` and watches for takeover."""

    #: Human name of the companion's mode, for messages.
    MODE_NAME = ""

    def __init__(self, bridge: MavlinkBridge, config: OffboardConfig = OffboardConfig()) -> None:
        self.bridge = bridge
        self.config = config
        self.engaged = False
        self.takeover_s: float | None = None
        self._watching = False
        self._expected = None  # (predicate, why): a mode change the companion commands itself
        self.handover_status: VehicleStatus | None = None
        self._lock = threading.Lock()
        bridge.add_status_listener(self._on_status)

    @abc.abstractmethod
    def in_companion_mode(self, status: VehicleStatus) -> bool:
        """True if ``status`` shows the mode the companion flies in."""

    @abc.abstractmethod
    def _engage(self) -> None:
        """The autopilot-specific sequence; raises on any failure."""

    def engage(self) -> None:
        """Run the sequence; on success the bridge is streaming and the takeover watch is on."""
        if self.bridge.released:
            raise AutopilotError(f"bridge released ({self.bridge.release_reason}); cannot engage again")
        try:
            self._engage()
        except Exception:
            self.bridge.stop_streaming()
            raise
        with self._lock:
            self.engaged = True
            self._watching = True
        log.info("%s engaged", self.MODE_NAME)

    def _wait_status(self, predicate, what: str) -> VehicleStatus:
        deadline = time.monotonic() + self.config.confirm_timeout_s
        while True:
            st = self.bridge.status()
            if st is not None and predicate(st):
                return st
            if time.monotonic() >= deadline:
                raise ModeChangeError(f"vehicle did not report {what} within {self.config.confirm_timeout_s} s (last: {st})")
            if self.bridge.wait(0.01):
                raise AutopilotError("bridge stopped while waiting for the vehicle")

    def _arm(self) -> None:
        self.bridge.command(_M.MAV_CMD_COMPONENT_ARM_DISARM, (1,))

    def expect(self, predicate, why: str) -> None:
        """The companion is about to hand the vehicle over itself (a commanded landing or hold):
        a HEARTBEAT for which ``predicate(status)`` is true is that hand-over, not a takeover.
        Anything else that leaves the companion's mode still is one."""
        with self._lock:
            self._expected = (predicate, why)

    def _on_status(self, status: VehicleStatus) -> None:
        with self._lock:
            if not self._watching:
                return
            if self.in_companion_mode(status) and status.armed:
                return
            if self._expected is not None and self._expected[0](status):
                if self.handover_status is None:
                    log.info("hand-over seen (%s): custom_mode %#x armed=%s", self._expected[1], status.custom_mode, status.armed)
                self.handover_status = status
                return
            self._watching = False
            self.takeover_s = self.bridge.clock()
        why = f"vehicle left {self.MODE_NAME} (custom_mode {status.custom_mode:#x}, armed={status.armed})"
        self.bridge.release(why)
        self.bridge.failsafe.report_takeover(self.takeover_s, why)


class Px4Offboard(AutopilotSession):
    MODE_NAME = "OFFBOARD"

    def in_companion_mode(self, status: VehicleStatus) -> bool:
        return px4_main_mode(status.custom_mode) == PX4_MAIN["offboard"]

    def _engage(self) -> None:
        c = self.config
        self.bridge.wait_for_state(c.state_timeout_s)
        self.bridge.start_streaming()
        self.bridge.wait_streamed(c.prestream_s, timeout_s=c.prestream_s + c.state_timeout_s)
        self._arm()
        self.bridge.command(_M.MAV_CMD_DO_SET_MODE, (_M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_MAIN["offboard"], 0))
        self._wait_status(lambda s: self.in_companion_mode(s) and s.armed, "OFFBOARD and armed")


class ArduPilotGuided(AutopilotSession):
    MODE_NAME = "GUIDED"

    def __init__(self, bridge: MavlinkBridge, config: OffboardConfig = OffboardConfig()) -> None:
        if bridge.config.setpoint_period_s > config.guided_timeout_s / 4.0:
            raise ValueError(
                f"setpoint period {bridge.config.setpoint_period_s:.3f} s is too slow for ArduPilot's "
                f"{config.guided_timeout_s} s guided timeout (needs < {config.guided_timeout_s / 4.0:.3f} s)"
            )
        super().__init__(bridge, config)

    def in_companion_mode(self, status: VehicleStatus) -> bool:
        return status.custom_mode == ARDUCOPTER_MODE["guided"]

    def _engage(self) -> None:
        c = self.config
        self.bridge.wait_for_state(c.state_timeout_s)
        self.bridge.command(_M.MAV_CMD_DO_SET_MODE, (_M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ARDUCOPTER_MODE["guided"]))
        self._wait_status(self.in_companion_mode, "GUIDED")
        self._arm()
        self._wait_status(lambda s: s.armed, "armed")
        self.bridge.command(_M.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, 0, 0, c.takeoff_alt_m))
        deadline = time.monotonic() + c.takeoff_timeout_s
        while True:
            st = self.bridge.state()
            if st is not None and st.p[2] >= c.takeoff_alt_m - c.takeoff_tolerance_m:
                break
            status = self.bridge.status()
            if status is not None and not (self.in_companion_mode(status) and status.armed):
                raise ModeChangeError(f"vehicle left GUIDED or disarmed during takeoff ({status})")
            if time.monotonic() >= deadline:
                alt = "unknown" if st is None else f"{st.p[2]:.2f} m"
                raise TakeoffError(f"takeoff to {c.takeoff_alt_m} m not reached within {c.takeoff_timeout_s} s (altitude {alt})")
            if self.bridge.wait(0.02):
                raise AutopilotError("bridge stopped during takeoff")
        self.bridge.start_streaming()


def make_session(autopilot: str, bridge: MavlinkBridge, config: OffboardConfig = OffboardConfig()) -> AutopilotSession:
    """Factory: ``"px4"`` -> :class:`Px4Offboard`, ``"ardupilot"`` -> :class:`ArduPilotGuided`."""
    sessions = {"px4": Px4Offboard, "ardupilot": ArduPilotGuided}
    if autopilot not in sessions:
        raise ValueError(f"unknown autopilot {autopilot!r}; choose one of {sorted(sessions)}")
    return sessions[autopilot](bridge, config)
