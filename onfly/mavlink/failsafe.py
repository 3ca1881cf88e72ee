"""Companion-side failsafes: what the bridge does when its inputs go bad.

The autopilot has its own failsafes (PX4 leaves offboard after ``COM_OF_LOSS_T`` without
setpoints; ArduPilot stops after its guided timeout). These are the companion's, evaluated by
the bridge's streamer thread every tick and fed by the pilot:

==================  ==========================================  ===========================
cause               condition                                   action
==================  ==========================================  ===========================
LINK_LOST           no message of any kind from the vehicle      STOP_STREAMING (report)
                    for ``link_timeout_s`` (default 0.3 s)
HEARTBEAT_LOST      no HEARTBEAT for ``heartbeat_timeout_s``     STOP_STREAMING (report)
                    (default 3.0 s: three missed 1 Hz beats)
ODOMETRY_STALE      newest position sample older than            HOLD
                    ``odometry_max_age_s`` (default 0.3 s)
PLANNER_FAILED      the pilot reported a failed plan             BRAKE until a plan succeeds
VLM_TIMEOUT /       the pilot reported a VLM timeout or          KEEP_GOAL (fly the last
VLM_GARBAGE         unparseable answer                           verified goal)
VLM_SILENT          no usable VLM answer for                     HOLD until one arrives
                    ``vlm_hold_after_s`` (default 10 s)
PILOT_TAKEOVER      the vehicle left offboard/guided             STOP_STREAMING, for good
==================  ==========================================  ===========================

Why ``link_timeout_s`` is not the heartbeat: HEARTBEAT comes at 1 Hz, so a cut could go
unnoticed for a full second. The bridge asks for LOCAL_POSITION_NED and ATTITUDE_QUATERNION
at >= 10 Hz (50 Hz by default), so the age of the newest message of any kind notices a cut
within ``link_timeout_s`` plus one streamer tick (0.3 + 0.05 s by default, inside the 0.5 s
bound). The slower heartbeat check stays as a second, independent guard.

The most severe active action wins: STOP_STREAMING > BRAKE > HOLD > KEEP_GOAL > CONTINUE.
Every rising edge (a cause becoming active) and every clearing is logged with its time and
kept in :attr:`FailsafeMonitor.events` for the run summary.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
from dataclasses import dataclass

__all__ = ["FailsafeConfig", "FailsafeCause", "FailsafeAction", "FailsafeEvent", "FailsafeMonitor"]

log = logging.getLogger(__name__)


class FailsafeAction(enum.IntEnum):
    """What the streamer does; larger is more severe."""

    CONTINUE = 0
    KEEP_GOAL = 1
    HOLD = 2
    BRAKE = 3
    STOP_STREAMING = 4


class FailsafeCause(str, enum.Enum):
    LINK_LOST = "link_lost"
    HEARTBEAT_LOST = "heartbeat_lost"
    ODOMETRY_STALE = "odometry_stale"
    PLANNER_FAILED = "planner_failed"
    VLM_TIMEOUT = "vlm_timeout"
    VLM_GARBAGE = "vlm_garbage"
    VLM_SILENT = "vlm_silent"
    PILOT_TAKEOVER = "pilot_takeover"


_ACTION_OF = {
    FailsafeCause.LINK_LOST: FailsafeAction.STOP_STREAMING,
    FailsafeCause.HEARTBEAT_LOST: FailsafeAction.STOP_STREAMING,
    FailsafeCause.ODOMETRY_STALE: FailsafeAction.HOLD,
    FailsafeCause.PLANNER_FAILED: FailsafeAction.BRAKE,
    FailsafeCause.VLM_TIMEOUT: FailsafeAction.KEEP_GOAL,
    FailsafeCause.VLM_GARBAGE: FailsafeAction.KEEP_GOAL,
    FailsafeCause.VLM_SILENT: FailsafeAction.HOLD,
    FailsafeCause.PILOT_TAKEOVER: FailsafeAction.STOP_STREAMING,
}


@dataclass(frozen=True)
class FailsafeConfig:
    """Thresholds of the companion failsafes (seconds on the bridge's clock)."""

    odometry_max_age_s: float = 0.3
    link_timeout_s: float = 0.3
    heartbeat_timeout_s: float = 3.0
    vlm_hold_after_s: float = 10.0

    def __post_init__(self) -> None:
        for name in ("odometry_max_age_s", "link_timeout_s", "heartbeat_timeout_s", "vlm_hold_after_s"):
            val = getattr(self, name)
            if not (isinstance(val, (int, float)) and math.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be a positive number of seconds, got {val!r}")


@dataclass(frozen=True)
class FailsafeEvent:
    """One failsafe transition.

    Attributes
    ----------
    t_s : float, time on the bridge's clock, seconds
    cause : FailsafeCause
    action : FailsafeAction taken for it (CONTINUE when ``cleared``)
    detail : str, human-readable specifics (ages, messages)
    cleared : bool, True when the cause stopped being active
    """

    t_s: float
    cause: FailsafeCause
    action: FailsafeAction
    detail: str = ""
    cleared: bool = False

    def as_dict(self) -> dict:
        return {"t_s": self.t_s, "cause": self.cause.value, "action": self.action.name.lower(), "detail": self.detail, "cleared": self.cleared}


class FailsafeMonitor:
    """Tracks which failsafe causes are active and the action they call for. Thread-safe.

    The streamer calls :meth:`evaluate` every tick with the link ages; the pilot reports VLM
    and planner outcomes with the ``report_*`` methods.
    """

    def __init__(self, config: FailsafeConfig = FailsafeConfig(), start_s: float = 0.0) -> None:
        self.config = config
        self._lock = threading.Lock()
        self._active: dict[FailsafeCause, str] = {}
        self.events: list[FailsafeEvent] = []
        self._last_vlm_ok_s = float(start_s)
        self._vlm_failed_since_ok = False

    # -- pilot reports ----------------------------------------------------------------------
    def report_vlm_ok(self, t_s: float) -> None:
        """A VLM answer parsed and its goal verified (or a valid status) at ``t_s``."""
        with self._lock:
            self._last_vlm_ok_s = float(t_s)
            self._vlm_failed_since_ok = False
            for cause in (FailsafeCause.VLM_TIMEOUT, FailsafeCause.VLM_GARBAGE, FailsafeCause.VLM_SILENT):
                self._clear(cause, t_s)

    def report_vlm_failure(self, t_s: float, cause: FailsafeCause, detail: str = "") -> None:
        """A VLM call timed out (VLM_TIMEOUT) or returned garbage (VLM_GARBAGE) at ``t_s``."""
        if cause not in (FailsafeCause.VLM_TIMEOUT, FailsafeCause.VLM_GARBAGE):
            raise ValueError(f"cause must be VLM_TIMEOUT or VLM_GARBAGE, got {cause!r}")
        with self._lock:
            self._vlm_failed_since_ok = True
            # Every failure is recorded, not only the first, so the summary counts them.
            self._active.pop(cause, None)
            self._raise(cause, t_s, detail)

    def report_planner(self, t_s: float, ok: bool, detail: str = "") -> None:
        """Outcome of a planner step at ``t_s``: a failure brakes until the next success."""
        with self._lock:
            if ok:
                self._clear(FailsafeCause.PLANNER_FAILED, t_s)
            else:
                self._raise(FailsafeCause.PLANNER_FAILED, t_s, detail)

    def report_takeover(self, t_s: float, detail: str = "") -> None:
        """The vehicle left the companion's mode (pilot takeover); permanent for this run."""
        with self._lock:
            self._raise(FailsafeCause.PILOT_TAKEOVER, t_s, detail)

    # -- streamer ---------------------------------------------------------------------------
    def evaluate(self, now_s: float, odometry_age_s: float, link_age_s: float, heartbeat_age_s: float) -> FailsafeAction:
        """Update the link-driven causes from the current ages (seconds) and return the action."""
        c = self.config
        with self._lock:
            checks = (
                (FailsafeCause.LINK_LOST, link_age_s > c.link_timeout_s, f"no vehicle message for {link_age_s:.3f} s"),
                (FailsafeCause.HEARTBEAT_LOST, heartbeat_age_s > c.heartbeat_timeout_s, f"no vehicle heartbeat for {heartbeat_age_s:.3f} s"),
                (FailsafeCause.ODOMETRY_STALE, odometry_age_s > c.odometry_max_age_s, f"odometry age {odometry_age_s:.3f} s"),
                (
                    FailsafeCause.VLM_SILENT,
                    self._vlm_failed_since_ok and now_s - self._last_vlm_ok_s > c.vlm_hold_after_s,
                    f"no usable VLM answer for {now_s - self._last_vlm_ok_s:.1f} s",
                ),
            )
            for cause, active, detail in checks:
                if active:
                    self._raise(cause, now_s, detail)
                else:
                    self._clear(cause, now_s)
            return self._action()

    def action(self) -> FailsafeAction:
        """The action the currently active causes call for."""
        with self._lock:
            return self._action()

    def active(self) -> dict[FailsafeCause, str]:
        """Active causes with the detail of their rising edge."""
        with self._lock:
            return dict(self._active)

    def first_event(self, cause: FailsafeCause) -> FailsafeEvent | None:
        """The earliest rising edge of ``cause``, or None."""
        with self._lock:
            return next((e for e in self.events if e.cause == cause and not e.cleared), None)

    # -- internals (lock held) --------------------------------------------------------------
    def _action(self) -> FailsafeAction:
        return max((_ACTION_OF[c] for c in self._active), default=FailsafeAction.CONTINUE)

    def _raise(self, cause: FailsafeCause, t_s: float, detail: str) -> None:
        if cause in self._active:
            return
        self._active[cause] = detail
        event = FailsafeEvent(float(t_s), cause, _ACTION_OF[cause], detail)
        self.events.append(event)
        log.warning("failsafe %s at t=%.3f s -> %s (%s)", cause.value, t_s, event.action.name.lower(), detail)

    def _clear(self, cause: FailsafeCause, t_s: float) -> None:
        if cause not in self._active or cause == FailsafeCause.PILOT_TAKEOVER:
            return
        del self._active[cause]
        self.events.append(FailsafeEvent(float(t_s), cause, FailsafeAction.CONTINUE, "cleared", cleared=True))
        log.info("failsafe %s cleared at t=%.3f s", cause.value, t_s)
