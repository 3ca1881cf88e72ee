"""Onboard flight: the OnFly pilot flying a real (or simulated) autopilot through MAVLink.

:class:`OnboardFlight` wires four parts that already exist, each on its own thread where it
must never wait for the others:

- the :class:`~onfly.mavlink.bridge.MavlinkBridge` (receiver + 20 Hz setpoint streamer),
  engaged by an :class:`~onfly.mavlink.autopilot.AutopilotSession` (PX4 offboard or
  ArduPilot guided) that also watches for a pilot takeover;
- a :class:`~onfly.sources.camera.CameraFeed` (newest frame, never blocks);
- the :class:`~onfly.pilot.OnFlyPilot` over a :class:`~onfly.runtime.ThreadRuntime`, so VLM
  calls run on worker threads and land when done (or, for a simulated VLM, after its modelled
  latency: ``honour_modelled_latency``);
- this loop, driven by a :class:`~onfly.readers.realtime.PlaybackClock` (monotonic by
  default, injectable): one pilot tick every ``control_period_s`` (10 Hz); between ticks it
  only waits for the next deadline.

Phases
------
1. **connect**: wait for the autopilot's HEARTBEAT and telemetry; ask for telemetry rates;
   anchor the pilot's world frame at the vehicle's estimated pose (origin at its position, x
   along its heading, z up: heights relative to the start). Camera frames arrive posed in the
   estimator's local frame and are re-posed into the world frame (:meth:`OnboardFlight.to_world`).
2. **engage**: the autopilot session (PX4: stream, arm, OFFBOARD; ArduPilot: GUIDED, arm,
   NAV_TAKEOFF to ``takeoff_alt_m``).
3. **takeoff** (PX4): climb straight up by ``takeoff_alt_m`` on a rate-limited straight-line
   plan (the planner's speed, acceleration and yaw-rate limits) until within
   ``takeoff_tolerance_m`` and nearly at rest.
4. **mission**: ``pilot.begin(instruction, t)``, then ``pilot.tick(t, state, frame)`` each
   period with the bridge's ENU state and the newest camera frame; each new plan goes to
   :meth:`MavlinkBridge.set_trajectory`. Ends when the pilot finishes (its stable STOP), at
   ``time_limit_s``, on a takeover, or when the link stays lost for ``link_lost_abort_s``.
5. **finish**: hold (the pilot's hold plans keep streaming) for ``hold_after_finish_s``, then
   ``on_finish``: ``"hold"`` (default): a position-only HOLD setpoint, then PX4 is switched to
   Hold (AUTO.LOITER) and ArduPilot keeps that position target in GUIDED (GUID_TIMEOUT never
   drops a position target); the vehicle is never left to a loss failsafe. ``"land"``: a site
   whose column is clear in the pilot's map (:meth:`OnboardFlight.landing_site`), the vehicle
   turns to face it and checks it again in the fresh map, the planner flies over it and down
   to ``land_handover_height_m``, then MAV_CMD_NAV_LAND hands the touchdown to the autopilot
   (an expected hand-over, not a takeover) and the flight waits for the disarm. A disarm
   above ``land_crash_height_m`` is a crash (``crashed`` in the summary).

Failsafes (every one lands in the summary with its time and cause)
------------------------------------------------------------------
================================  ==========================================================
condition                         reaction
================================  ==========================================================
stale odometry (bridge)           the streamer holds position; the pilot is not ticked with a
                                  state it cannot trust (its VLM calls keep running)
link lost (bridge)                the streamer stops commanding motion (the autopilot's own
                                  loss failsafe holds); the pilot pauses; the flight ends after
                                  ``link_lost_abort_s``
VLM timeout / garbage / raising   reported to the bridge (keep the last verified goal); the
                                  pilot drops a goal not refreshed for ``goal_timeout_s`` and
                                  holds; the bridge holds after ``vlm_hold_after_s`` of silence
planner failure (braking plan)    reported: the bridge brakes until a plan succeeds
pilot tick raising (a bug)        treated as a planner failure: brake, log, keep ticking
pilot takeover (mode change)      the session releases the bridge: no motion command, ever;
                                  the pilot keeps running (logging) for
                                  ``observe_after_takeover_s``
================================  ==========================================================

A mode change the companion commands itself (Hold, the landing) is announced to the session
(:meth:`AutopilotSession.expect`) and is not a takeover; any other mode change still is. A
disarm during the mission or above the ground is reported as a crash. Every event and failsafe
of the summary is on the loop's clock, relative to the mission start.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from onfly.mavlink.autopilot import ARDUCOPTER_MODE, PX4_AUTO_SUB, PX4_MAIN, AutopilotSession, Px4Offboard, px4_custom_mode
from onfly.mavlink.bridge import BridgeError, MavlinkBridge
from onfly.mavlink.failsafe import FailsafeCause
from onfly.mavlink.link import mavlink2
from onfly.pilot import OnFlyPilot, PilotMode
from onfly.readers.realtime import MonotonicClock, PlaybackClock
from onfly.sources.camera import CameraFeed
from planning.frames import make_transform, wrap_angle
from planning.planner import Fallback, map_frame
from planning.straight_line import straight_line_plan
from planning.trajectory import Trajectory, VehicleState

__all__ = ["OnboardConfig", "OnboardConfigError", "OnboardFlight", "FlightSummary", "GroundTruth", "pose_source"]

log = logging.getLogger(__name__)
_M = mavlink2

def px4_custom_mode_of(main: str, sub: str | None = None) -> int:
    return px4_custom_mode(PX4_MAIN[main], PX4_AUTO_SUB[sub] if sub else 0)


#: failsafe causes after which the bridge's state cannot be trusted for planning
_UNTRUSTED = (FailsafeCause.LINK_LOST, FailsafeCause.HEARTBEAT_LOST, FailsafeCause.ODOMETRY_STALE)
END_REASONS = ("finished", "time_limit", "takeover", "link_lost", "interrupted", "bridge_stopped")


class OnboardConfigError(ValueError):
    """Invalid onboard configuration (names the field)."""


@dataclass(frozen=True)
class OnboardConfig:
    """Timing and behaviour of an onboard flight (seconds, metres, on the loop's clock).

    Attributes
    ----------
    control_period_s : pilot tick period (10 Hz)
    connect_timeout_s : wait for the autopilot's heartbeat and telemetry
    takeoff_alt_m : climb this far above the engage position before the mission (PX4: in
        offboard; ArduPilot: NAV_TAKEOFF altitude above home); 0 skips the PX4 climb
    takeoff_tolerance_m : the climb is done within this of the target height ...
    takeoff_speed_tolerance_mps : ... and below this speed
    takeoff_timeout_s : give up the climb (and hold) after this long
    time_limit_s : the mission ends (and the vehicle holds) this long after ``begin``
    hold_after_finish_s : hold after the pilot's STOP before ``on_finish``
    on_finish : ``"hold"`` (default: stop streaming; the autopilot's own hover takes over) or
        ``"land"`` (hand over to the autopilot's landing, straight down where the vehicle
        stopped: only where the ground below is clear; the goal is often next to an object)
    land_timeout_s : wait this long for the disarm after commanding the landing
    land_search_radius_m, land_search_step_m : the landing site is searched on a grid of this
        step within this radius of where the vehicle stopped (then the take-off point)
    land_clear_radius_m : a site's column, from ``land_crash_height_m`` above the ground up
        to the flight height, must be this far from every mapped (or unknown) obstacle
    land_handover_height_m : the planner descends to this height above the take-off ground
        over the site; the autopilot's landing (NAV_LAND) does the last part straight down
    land_approach_timeout_s : give up moving over the site after this long (then hold)
    land_goal_held_s : a site whose approach goal the planner's goal check has held more than
        the approach tolerance off it for this long is blocked (the next site is chosen): the
        planner keeps a goal ``d_safe_m`` plus a margin from every obstacle in its map, so the
        vehicle would settle beside the site until the approach times out
    land_crash_height_m : a disarm higher than this above the ground is a crash, not a landing
    observe_after_takeover_s : after a takeover, keep the pilot running (no commands) this long
    link_lost_abort_s : a link lost for this long ends the flight
    """

    control_period_s: float = 0.1
    connect_timeout_s: float = 15.0
    takeoff_alt_m: float = 1.5
    takeoff_tolerance_m: float = 0.15
    takeoff_speed_tolerance_mps: float = 0.15
    takeoff_timeout_s: float = 30.0
    time_limit_s: float = 70.0
    hold_after_finish_s: float = 2.0
    on_finish: str = "hold"
    land_timeout_s: float = 30.0
    observe_after_takeover_s: float = 5.0
    link_lost_abort_s: float = 10.0
    land_search_radius_m: float = 8.0
    land_search_step_m: float = 0.5
    land_clear_radius_m: float = 0.6
    land_handover_height_m: float = 0.7
    land_approach_timeout_s: float = 40.0
    land_goal_held_s: float = 2.0
    land_crash_height_m: float = 0.3

    def __post_init__(self) -> None:
        positive = ("control_period_s", "connect_timeout_s", "takeoff_tolerance_m", "takeoff_speed_tolerance_mps",
                    "takeoff_timeout_s", "time_limit_s", "land_timeout_s", "link_lost_abort_s", "land_search_radius_m",
                    "land_search_step_m", "land_clear_radius_m", "land_handover_height_m", "land_approach_timeout_s",
                    "land_goal_held_s", "land_crash_height_m")
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise OnboardConfigError(f"OnboardConfig.{name} must be positive, got {v!r}")
        for name in ("takeoff_alt_m", "hold_after_finish_s", "observe_after_takeover_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise OnboardConfigError(f"OnboardConfig.{name} must be >= 0, got {v!r}")
        if self.on_finish not in ("land", "hold"):
            raise OnboardConfigError(f"OnboardConfig.on_finish must be 'land' or 'hold', got {self.on_finish!r}")


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What a benchmark task knows about success (for the summary only; never shown to the
    pilot): the goal region (scene frame), the reference path length, the success radius, and
    ``T_scene_world`` (4, 4): where the pilot's world frame (anchored at the start pose) sits in
    the scene, so the flown trace is scored in the scene's frame (identity if None)."""

    goal: Any  # onfly.bench.metrics.GoalRegion
    reference_path_m: float
    success_radius_m: float = 5.0
    task_id: str = ""
    T_scene_world: Any = None


@dataclass(frozen=True, eq=False)
class FlightSummary:
    """Everything one onboard flight did (JSON-able through :meth:`to_dict`).

    Times are seconds on the loop's clock relative to the mission start (``begin``); negative
    times happened before it (connect, engage, take-off).
    """

    instruction: str
    autopilot: str
    end_reason: str
    finished: bool
    flight_time_s: float
    takeoff_s: float
    final_position_m: list
    failsafes: list
    events: list
    pilot: dict
    camera: dict
    loop: dict
    metrics: dict | None
    crashed: bool = False
    landed: bool = False
    t_begin_abs_s: float | None = None
    frames: dict = field(default_factory=dict)
    trace_t_x_y_z: list = field(repr=False, default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def pose_source(bridge: MavlinkBridge):
    """``() -> T_local_body (4, 4)``: the body pose in the estimator's local frame (the
    autopilot's LOCAL_POSITION_NED as ENU) from the bridge's newest telemetry, or None (for
    cameras without a pose of their own, e.g. a RealSense). Frames reach
    :class:`OnboardFlight` posed in that local frame, as a camera stamped by the vehicle's
    estimator is; the flight maps them into the pilot's world frame."""

    def pose() -> np.ndarray | None:
        state, R = bridge.reader.state(), bridge.reader.attitude()
        if state is None or R is None:
            return None
        return make_transform(R, state.p)

    return pose


class OnboardFlight:
    """One onboard flight (see the module docstring).

    Parameters
    ----------
    bridge : a started :class:`MavlinkBridge` built with ``clock=clock.now_s``
    session : the autopilot session over ``bridge`` (``make_session``)
    pilot : the :class:`OnFlyPilot` (its runtime on the same clock)
    camera : a started :class:`CameraFeed`, or None (the pilot then flies blind: it holds)
    instruction : the task instruction
    config : OnboardConfig
    clock : :class:`PlaybackClock` driving the loop (monotonic by default)
    ground_truth : optional :class:`GroundTruth` for benchmark metrics in the summary
    writer : optional :class:`onfly.logs.writer.LogWriter`: every frame the pilot gets (posed in
        the pilot's world frame), the pilot's events, this flight's events and the failsafes,
        all stamped on the loop's clock (the camera feed restamps frames on it)
    recorder : optional :class:`onfly.viz.RerunRecorder` (frames, map, state, plans, events)
    """

    def __init__(
        self,
        bridge: MavlinkBridge,
        session: AutopilotSession,
        pilot: OnFlyPilot,
        camera: CameraFeed | None,
        instruction: str,
        config: OnboardConfig = OnboardConfig(),
        clock: PlaybackClock | None = None,
        ground_truth: GroundTruth | None = None,
        writer=None,
        recorder=None,
    ) -> None:
        if not isinstance(instruction, str) or not instruction.strip():
            raise OnboardConfigError("instruction must be a non-empty string")
        pilot_cfg = getattr(pilot, "config", None)
        planner_cfg = getattr(pilot_cfg, "planner", None)
        if config.on_finish == "land" and getattr(pilot_cfg, "use_planner", False) and planner_cfg is not None:
            # the planner keeps its goals d_safe_m + goal_clearance_margin_m from the ground too
            floor = planner_cfg.d_safe_m + planner_cfg.goal_clearance_margin_m
            if config.land_handover_height_m <= floor:
                raise OnboardConfigError(
                    f"OnboardConfig.land_handover_height_m ({config.land_handover_height_m} m) must exceed the planner's goal "
                    f"clearance above the ground, d_safe_m + goal_clearance_margin_m = {floor:.2f} m: the planner would hold "
                    "the descent above it and no landing site could be reached")
        self.bridge = bridge
        self.session = session
        self.pilot = pilot
        self.camera = camera
        self.instruction = instruction
        self.config = config
        self.clock = clock if clock is not None else MonotonicClock()
        self.ground_truth = ground_truth
        self.writer = writer
        self.recorder = recorder
        # PX4 climbs in offboard (phase 3); ArduPilot took off inside engage()
        self.autopilot = "px4" if session.MODE_NAME == Px4Offboard.MODE_NAME else "ardupilot"
        self.events: list[dict] = []
        self.t_begin_s: float | None = None
        self.t_finished_s: float | None = None
        self.t_handover_s: float | None = None
        self.t_takeover_s: float | None = None
        self.crash_suspected = False
        self.landed = False
        self._frames_reposed = 0
        self._t_start = self.clock.now_s()
        self._next_s = self._t_start
        self._trace: list[tuple[float, np.ndarray]] = []
        self._n_events = 0
        self._pending_obs = None
        self._ticks = 0
        self._paused_ticks = 0
        self._overruns = 0
        self._tick_ms: list[float] = []
        self._link_lost_since: float | None = None
        self.pilot_ticks_after_takeover = 0

    # -- public -----------------------------------------------------------------------------
    def run(self) -> FlightSummary:
        """Fly the whole flight; returns its summary. Engagement errors propagate (the session
        has already stopped the stream); every later problem ends the flight safely."""
        cfg = self.config
        self._event("connect", {})
        self.bridge.wait_for_vehicle(cfg.connect_timeout_s)
        self.bridge.wait_for_state(cfg.connect_timeout_s)
        self.bridge.request_message_intervals()
        if hasattr(self.bridge, "anchor_world"):
            T_local_world = np.asarray(self.bridge.anchor_world(), dtype=float)
            # the estimator's local frame is north-aligned (MAV_FRAME_LOCAL_NED: x north, y
            # east), so east is its ENU x axis; the world frame is turned to the take-off heading
            east = T_local_world[:3, :3].T @ np.array([1.0, 0.0, 0.0])
            east_yaw = float(np.arctan2(east[1], east[0]))
            if hasattr(self.pilot, "set_east_yaw"):
                self.pilot.set_east_yaw(east_yaw)
            self._event("world_anchored", {"T_local_world": T_local_world.round(6).tolist(), "east_yaw_rad": round(east_yaw, 6)})
        self._event("engage", {"autopilot": self.autopilot})
        t_engage = self.clock.now_s()
        self.session.engage()  # ArduPilot: includes its NAV_TAKEOFF
        self._event("engaged", {"position_m": self.bridge.state().p.tolist(), "duration_s": self.clock.now_s() - t_engage})
        end = "finished"
        try:
            if self.autopilot == "px4" and cfg.takeoff_alt_m > 0:
                end = self._takeoff()
            if end == "finished":
                end = self._mission()
            self._finish(end)
        except KeyboardInterrupt:
            end = "interrupted"
            self._event("interrupted", {})
            if not self.bridge.released:
                self.bridge.set_trajectory(None)  # hold where we are; the caller stops the bridge
        return self._summary(end)

    def to_world(self, obs):
        """A camera frame posed in the estimator's local frame, re-posed in the pilot's world
        frame (the bridge's anchor; identity for a bridge without one)."""
        T_local_world = getattr(self.bridge, "T_local_world", None)
        if T_local_world is None:
            return obs
        T = np.asarray(T_local_world, dtype=float)
        if np.array_equal(T, np.eye(4)):
            return obs
        self._frames_reposed += 1
        return dataclasses.replace(obs, T_world_cam=np.linalg.inv(T) @ obs.T_world_cam)

    # -- phases -----------------------------------------------------------------------------
    def _wait_next(self) -> float:
        """Wait for the next tick deadline; returns its time. A late tick re-anchors the grid."""
        period = self.config.control_period_s
        self._next_s += period
        now = self.clock.now_s()
        if now > self._next_s:
            self._overruns += 1
            self._next_s = now
        else:
            self.clock.sleep_until_s(self._next_s)
        return self.clock.now_s()

    def _trusted_state(self, t_s: float) -> VehicleState | None:
        state = self.bridge.state()
        active = self.bridge.failsafe.active()
        if FailsafeCause.LINK_LOST in active or FailsafeCause.HEARTBEAT_LOST in active:
            if self._link_lost_since is None:
                self._link_lost_since = t_s
        else:
            self._link_lost_since = None
        if state is None or any(c in active for c in _UNTRUSTED):
            return None
        return state

    def _takeoff(self) -> str:
        cfg = self.config
        p0 = self.bridge.state().p.copy()
        target = p0 + np.array([0.0, 0.0, cfg.takeoff_alt_m])
        t0 = self.clock.now_s()
        self._event("takeoff", {"target_m": target.tolist()})
        pc = self.pilot.config.planner
        while True:
            t = self._wait_next()
            if self.bridge.released:
                self._on_takeover(t)
                return "takeover"
            state = self._trusted_state(t)
            if state is None:
                if self._link_lost_since is not None and t - self._link_lost_since > cfg.link_lost_abort_s:
                    return "link_lost"
                continue
            if abs(state.p[2] - target[2]) <= cfg.takeoff_tolerance_m and np.linalg.norm(state.v) <= cfg.takeoff_speed_tolerance_mps:
                self._event("takeoff_done", {"position_m": state.p.tolist(), "duration_s": t - t0})
                return "finished"
            if t - t0 > cfg.takeoff_timeout_s:
                self._event("takeoff_timeout", {"position_m": state.p.tolist()})
                self.bridge.set_trajectory(None)
                return "time_limit"
            self.bridge.set_trajectory(
                straight_line_plan(
                    state, target, v_max_mps=pc.v_max_mps, a_max_mps2=pc.a_max_mps2, yaw_rate_max_rps=pc.yaw_rate_max_rps,
                    dt_s=pc.dt_s, steps=pc.horizon_steps, yaw_ref=state.yaw,
                )
            )

    def _mission(self) -> str:
        cfg = self.config
        t = self.clock.now_s()
        self.t_begin_s = t
        self.pilot.begin(self.instruction, t)
        self._event("begin", {"instruction": self.instruction})
        takeover_at = None
        while True:
            t = self._wait_next()
            if not self.bridge.running:
                return "bridge_stopped"
            if self.bridge.released and takeover_at is None:
                takeover_at = t
                self._on_takeover(t)
            if takeover_at is not None and t - takeover_at >= cfg.observe_after_takeover_s:
                return "takeover"
            if t - self.t_begin_s >= cfg.time_limit_s:
                self._event("time_limit", {"limit_s": cfg.time_limit_s})
                return "takeover" if takeover_at is not None else "time_limit"
            finished = self._tick(t, commanding=takeover_at is None)
            if finished:
                self.t_finished_s = t
                self._event("mission_end", {"position_m": self._trace[-1][1].tolist() if self._trace else None})
                return "takeover" if takeover_at is not None else "finished"
            if self._link_lost_since is not None and t - self._link_lost_since > cfg.link_lost_abort_s:
                self._event("link_lost_abort", {"lost_for_s": t - self._link_lost_since})
                return "link_lost"

    def _tick(self, t: float, commanding: bool) -> bool:
        """One pilot period; True when the pilot has finished."""
        obs = self.camera.latest() if self.camera is not None else None
        if obs is not None:
            self._pending_obs = obs
        state = self._trusted_state(t)
        if state is None:
            self._paused_ticks += 1
            return False
        obs, self._pending_obs = self._pending_obs, None
        if obs is not None:
            obs = self.to_world(obs)
        w0 = time.perf_counter()
        try:
            tick = self.pilot.tick(t, state, obs)
        except Exception as exc:  # a pilot bug must not leave the vehicle flying the last plan
            log.exception("pilot tick failed; braking")
            self._event("pilot_error", {"error": repr(exc)}, t)
            self.bridge.failsafe.report_planner(t, ok=False, detail=f"pilot tick raised {exc!r}")
            return False
        self._tick_ms.append((time.perf_counter() - w0) * 1e3)
        self._record(t, state, obs, tick)
        self._ticks += 1
        if not commanding:
            self.pilot_ticks_after_takeover += 1
        self._trace.append((t, state.p.copy()))
        self._report_pilot_events(t)
        if tick.plan is not None:
            braking = tick.plan.fallback is Fallback.BRAKE
            self.bridge.failsafe.report_planner(t, ok=not braking, detail="planner fell back to braking" if braking else "")
        if commanding and tick.trajectory is not None:
            self.bridge.set_trajectory(tick.trajectory)
        return bool(tick.finished)

    def _record(self, t: float, state: VehicleState, obs, tick) -> None:
        """Frames, state, plan and the pilot's new events to the log and the recording; a
        recording problem is logged, never allowed to stop the flight."""
        try:
            if self.writer is not None:
                if obs is not None:
                    self.writer.write(obs)
                for ev in self.pilot.events[self._n_events :]:
                    self.writer.event(ev.kind, ev.data, t_s=ev.t_s)
            if self.recorder is not None:
                if obs is not None:
                    self.recorder.log_frame(obs)
                    esdf = getattr(self.pilot, "esdf", None)
                    if esdf is not None:
                        self.recorder.log_map(t, esdf.occupied_points())
                self.recorder.log_state(state)
                if tick.trajectory is not None:
                    self.recorder.log_plan(t, tick.trajectory)
                self.recorder.log_pilot_events(self.pilot.events)
        except Exception as exc:  # noqa: BLE001 - a full disk must not crash the vehicle
            log.warning("recording failed at t=%.2f: %s", t, exc)

    def _report_pilot_events(self, t: float) -> None:
        """Feed the pilot's new events to the bridge's failsafe monitor (VLM health), each at
        its own time (the pilot stamps events on the flight's clock when the answer landed)."""
        fs = self.bridge.failsafe
        events = self.pilot.events
        for ev in events[self._n_events :]:
            d = ev.data
            if ev.kind == "decision":
                if d.get("goal_world") is not None:
                    fs.report_vlm_ok(ev.t_s)
                elif d.get("status") == "timeout":
                    fs.report_vlm_failure(ev.t_s, FailsafeCause.VLM_TIMEOUT, f"decision: {d.get('reason', '')}")
                elif d.get("status") == "error" or str(d.get("reason", "")).startswith("parse"):
                    fs.report_vlm_failure(ev.t_s, FailsafeCause.VLM_GARBAGE, f"decision: {d.get('reason', '')}")
            elif ev.kind == "monitor":
                if d.get("status") is not None:
                    fs.report_vlm_ok(ev.t_s)
                elif d.get("reason") == "memory too short":
                    continue  # no call was made
                elif str(d.get("reason", "")).startswith("call timeout"):
                    fs.report_vlm_failure(ev.t_s, FailsafeCause.VLM_TIMEOUT, f"monitor: {d.get('reason', '')}")
                else:
                    fs.report_vlm_failure(ev.t_s, FailsafeCause.VLM_GARBAGE, f"monitor: {d.get('reason', '')}")
            elif ev.kind == "agent_error":
                fs.report_vlm_failure(ev.t_s, FailsafeCause.VLM_GARBAGE, f"{d.get('kind')} call raised: {d.get('error')}")
                self._event("agent_error", d, t)
            elif ev.kind in ("goal_timeout", "lost", "resumed", "advanced", "finished", "decomposition"):
                self._event(f"pilot_{ev.kind}", d, ev.t_s)
        self._n_events = len(events)

    def _on_takeover(self, t: float) -> None:
        self.t_takeover_s = t
        status = self.bridge.status()
        disarmed = status is not None and not status.armed
        # The autopilot disarmed during the mission, or anywhere above the ground: from the
        # companion's view a crash (or a kill switch), never a success.
        state = self.bridge.state()
        high = state is not None and float(state.p[2]) > self.config.land_crash_height_m
        mid_mission = self.t_begin_s is not None and self.t_finished_s is None and self.t_handover_s is None
        self.crash_suspected = self.crash_suspected or (disarmed and (mid_mission or high))
        self._event("takeover", {"reason": self.bridge.release_reason, "armed": None if status is None else status.armed})

    def _finish(self, end: str) -> None:
        cfg = self.config
        if self.bridge.released or end in ("link_lost", "bridge_stopped"):
            return
        self._event("hold", {"s": cfg.hold_after_finish_s})
        t_hold = self.clock.now_s()
        while self.clock.now_s() - t_hold < cfg.hold_after_finish_s:
            t = self._wait_next()
            if self.bridge.released:
                self._on_takeover(t)
                return
            if self.t_begin_s is not None:
                self._tick(t, commanding=True)  # a finished pilot plans to its hold point
        if cfg.on_finish == "hold":
            self._hand_over_hold()
        else:
            self._land()

    # -- the end of the flight: our own hold, or a landing over clear ground ----------------------
    def _land_mode(self, status) -> bool:
        if self.autopilot == "px4":
            return status.custom_mode == px4_custom_mode_of("auto", "land")
        return status.custom_mode == ARDUCOPTER_MODE["land"]

    def _hand_over_hold(self) -> None:
        """Leave the vehicle holding by its own rule, never by a loss failsafe: PX4 is switched to
        Hold (AUTO.LOITER, which needs the position estimate it has); ArduCopter stays in GUIDED
        with a position-only target, which GUID_TIMEOUT never drops."""
        self.t_handover_s = self.clock.now_s()
        self.bridge.set_trajectory(None)  # the bridge holds the current point (position-only HOLD)
        self._wait_next()
        self._wait_next()
        if self.autopilot == "px4":
            loiter = px4_custom_mode_of("auto", "loiter")
            self.session.expect(lambda st: st.custom_mode == loiter and st.armed, "hold hand-over")
            try:
                self.bridge.command(_M.MAV_CMD_DO_SET_MODE, (_M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_MAIN["auto"], PX4_AUTO_SUB["loiter"]))
            except BridgeError as exc:
                self._event("hold_refused", {"error": str(exc), "then": "land"})
                self._land()
                return
        self.bridge.stop_streaming()
        self._event("handover_hold", {"mode": "AUTO.LOITER" if self.autopilot == "px4" else "GUIDED position target"})

    def _planner_step(self, state: VehicleState, goal: np.ndarray, face_goal: bool = False):
        """One plan toward ``goal`` in the pilot's map (MPC over the ESDF), or a straight line
        when the pilot has no planner. ``face_goal``: turn toward the goal (the camera sees the
        way), else keep the heading. Returns ``(trajectory, goal_used)``: the goal the plan aims
        for, (3,) metres, world ENU (the planner's goal check may move it to clear space)."""
        pilot = self.pilot
        pc = pilot.config.planner
        d = goal[:2] - state.p[:2]
        yaw_ref = float(np.arctan2(d[1], d[0])) if face_goal and np.linalg.norm(d) > 0.5 else state.yaw
        if getattr(pilot.config, "use_planner", False) and getattr(pilot, "planner", None) is not None:
            field = pilot.planning_field(state.t_s) if hasattr(pilot, "planning_field") else pilot.esdf
            res = pilot.planner.step(state, goal, field, yaw_ref=yaw_ref, volume=pilot.volume)
            return res.trajectory, np.asarray(res.goal_used, dtype=float)
        return straight_line_plan(state, goal, v_max_mps=pc.v_max_mps, a_max_mps2=pc.a_max_mps2, yaw_rate_max_rps=pc.yaw_rate_max_rps,
                                  dt_s=pc.dt_s, steps=pc.horizon_steps, yaw_ref=yaw_ref), np.asarray(goal, dtype=float)

    def _column_clear(self, xy: np.ndarray, top_m: float) -> np.ndarray:
        """(k,) True where the column above each ``xy`` (k, 2), from ``land_crash_height_m`` to
        ``top_m``, is known (where the map tells knownness) with no seen obstacle within
        ``land_clear_radius_m`` of it (every voxel of that cylinder,
        :func:`onfly.search.seen_obstacle_in_column`: the planner keeps its goals ``d_safe_m``
        plus ``goal_clearance_margin_m`` from any obstacle, so a site it would hold off cannot
        be reached). Unknown space beside the column is not an obstacle here (the
        map's default counts it as one): a level camera never sees the space beside a column
        it looks down, and a site is only taken after the vehicle turned to look at it."""
        from onfly.search import known_mask, seen_obstacle_in_column

        cfg = self.config
        esdf = self.pilot.esdf
        top = max(top_m, cfg.land_handover_height_m + 0.1)
        zs = np.arange(cfg.land_crash_height_m, top + 1e-9, 0.25)
        k, nz = len(xy), len(zs)
        pts = np.column_stack([np.repeat(xy, nz, axis=0), np.tile(zs, k)])
        known = known_mask(esdf, pts).reshape(k, nz).all(axis=1)
        return known & ~seen_obstacle_in_column(esdf, xy, cfg.land_crash_height_m, top, cfg.land_clear_radius_m)

    def landing_site(self, p_now: np.ndarray, yaw: float | None = None, exclude=()) -> tuple[np.ndarray, str]:
        """Where to land (world, on the take-off ground z = 0) and how it was chosen.

        Candidates on a grid within ``land_search_radius_m``: those in front of the camera
        (within 40 deg of ``yaw``: seen, not guessed) first, each group nearest first. A site
        needs a clear column (:meth:`_column_clear`) and a clear straight way to it at the
        current height; sites within a step of one in ``exclude`` are skipped (seen blocked
        after turning toward them). ``"map"``; ``"takeoff_point"`` when nothing qualifies (back over the
        take-off point, a column the vehicle flew up through); ``"no_map"`` for a pilot without a
        map (straight down).
        """
        cfg = self.config
        esdf = getattr(self.pilot, "esdf", None)
        if esdf is None:
            return np.array([p_now[0], p_now[1], 0.0]), "no_map"
        r, step = cfg.land_search_radius_m, cfg.land_search_step_m
        g = np.arange(-r, r + 1e-9, step)
        dx, dy = np.meshgrid(g, g, indexing="ij")
        offsets = np.stack([dx.ravel(), dy.ravel()], axis=1)
        dist = np.linalg.norm(offsets, axis=1)
        keep = dist <= r
        offsets, dist = offsets[keep], dist[keep]
        behind = np.zeros(len(offsets), dtype=bool)
        if yaw is not None:
            bearing = np.arctan2(offsets[:, 1], offsets[:, 0])
            off_axis = np.abs(wrap_angle(bearing - yaw))
            behind = (off_axis > np.deg2rad(40.0)) & (dist > step)
        order = np.lexsort((dist, behind))
        xy = p_now[:2] + offsets[order]
        for ex in exclude:
            far = np.linalg.norm(xy - np.asarray(ex)[:2], axis=1) > step * 1.01
            xy, order = xy[far], order[far]
        free = self._column_clear(xy, float(p_now[2]))
        for i in np.flatnonzero(free):
            if self._way_clear(p_now, xy[i]):
                return np.array([xy[i, 0], xy[i, 1], 0.0]), "map"
        return np.zeros(3), "takeoff_point"

    def _way_clear(self, p_now: np.ndarray, xy: np.ndarray) -> bool:
        """The straight way at the current height to above ``xy``: as clear as where the vehicle
        is now, up to the column's clearance (it may have stopped closer than that to its goal
        object)."""
        esdf = self.pilot.esdf
        p_now = np.asarray(p_now, dtype=float)
        d_now = float(esdf.query(p_now[None])[0][0])
        margin = min(self.config.land_clear_radius_m, max(0.3, d_now - 0.05))
        end = np.array([xy[0], xy[1], p_now[2]])
        seg = np.linspace(p_now, end, max(2, int(np.ceil(np.linalg.norm(end - p_now) / 0.25)) + 1))
        return bool(np.all(esdf.is_free(seg, margin_m=margin)))

    def site_still_clear(self, site: np.ndarray, p_now: np.ndarray) -> bool:
        """The chosen site's column and the way to it, checked again in the current map."""
        return bool(self._column_clear(np.asarray(site)[None, :2], float(p_now[2]))[0]) and self._way_clear(p_now, site[:2])

    def _turn_toward(self, target_xy: np.ndarray, t_end: float) -> bool:
        """Hold position and turn to face ``target_xy`` (the camera then sees the way and the
        site); True once within 0.15 rad, False on timeout / takeover."""
        pc = self.pilot.config.planner
        hold = None
        while True:
            step = self._landing_period(t_end)
            if step is None:
                return False
            t, state = step
            if state is None:
                continue
            hold = state.p.copy() if hold is None else hold
            d = np.asarray(target_xy) - hold[:2]
            turn = float(wrap_angle(float(np.arctan2(d[1], d[0])) - state.yaw))
            if abs(turn) < 0.15 and abs(state.yaw_rate) < 0.1:
                return True
            # a hold at ``hold`` with the final heading: the autopilot turns at its own yaw-rate limit
            n = pc.horizon_steps
            yaw_to = state.yaw + turn
            self.bridge.set_trajectory(Trajectory(t, pc.dt_s, np.tile(hold, (n + 1, 1)), np.zeros((n + 1, 3)), np.full(n + 1, yaw_to),
                                                  np.zeros((n, 3)), np.zeros(n)))

    def _landing_period(self, t_end: float) -> tuple[float, VehicleState | None] | None:
        """One control period of a landing manoeuvre: wait for it, feed the map the newest frame,
        then the checks every manoeuvre shares. Returns ``(t, state)`` (state None: no trusted
        state this period, wait) or None to stop: taken over (reported), out of time, or the
        link lost for longer than ``link_lost_abort_s``."""
        t = self._wait_next()
        self._map_frame(t)
        if self.bridge.released:
            self._on_takeover(t)
            return None
        if t > t_end:
            return None
        state = self._trusted_state(t)
        if state is None and self._link_lost_since is not None and t - self._link_lost_since > self.config.link_lost_abort_s:
            return None
        return t, state

    def _map_frame(self, t: float) -> None:
        """During the landing the pilot no longer ticks: keep its map fed with the newest frame
        (and the log / recording)."""
        obs = self.camera.latest() if self.camera is not None else None
        esdf = getattr(self.pilot, "esdf", None)
        if obs is None:
            return
        obs = self.to_world(obs)
        if esdf is not None:
            map_frame(esdf, getattr(self.pilot, "planner", None), obs.depth_m, obs.camera, obs.T_world_cam, obs.position)
        try:
            if self.writer is not None:
                self.writer.write(obs)
            if self.recorder is not None:
                self.recorder.log_frame(obs)
        except Exception as exc:  # noqa: BLE001
            log.warning("recording failed at t=%.2f: %s", t, exc)

    def _fly_to(self, goal: np.ndarray, tol_xy_m: float, tol_z_m: float, t_end: float, face_goal: bool = False) -> bool | None:
        """Plan toward ``goal`` every tick until within tolerance and slow; False on timeout or
        when the vehicle is taken over / loses its link; None when the site's column (``goal``'s
        x, y) no longer looks clear in the map the new frames build, or when the planner has
        held its goal out of tolerance of ``goal`` for ``land_goal_held_s``."""
        esdf = getattr(self.pilot, "esdf", None)
        held_since = None
        while True:
            step = self._landing_period(t_end)
            if step is None:
                return False
            t, state = step
            if esdf is not None and not bool(self._column_clear(goal[None, :2], float(goal[2]))[0]):
                return None
            if state is None:
                continue
            self._trace.append((t, state.p.copy()))
            d = state.p - goal
            if np.linalg.norm(d[:2]) <= tol_xy_m and abs(d[2]) <= tol_z_m and np.linalg.norm(state.v) < 0.2:
                return True
            traj, used = self._planner_step(state, goal, face_goal)
            off = used - goal
            if np.linalg.norm(off[:2]) > tol_xy_m or abs(off[2]) > tol_z_m:
                held_since = t if held_since is None else held_since
                if t - held_since >= self.config.land_goal_held_s:
                    self._event("land_goal_held", {"site_m": goal.tolist(), "goal_used_m": used.tolist(), "held_s": t - held_since})
                    return None
            else:
                held_since = None
            self.bridge.set_trajectory(traj)

    def _land(self) -> None:
        cfg = self.config
        state = self.bridge.state()
        if state is None:
            self._event("land_failed", {"error": "no vehicle state"})
            return
        t_end = self.clock.now_s() + cfg.land_approach_timeout_s
        rejected: list = []
        for attempt in range(8):
            site, how = self.landing_site(state.p, state.yaw, exclude=rejected)
            if how == "map" and np.linalg.norm(site[:2] - state.p[:2]) > 0.5:
                # look before moving: face the site, let the new frames update the map, check again
                if not self._turn_toward(site[:2], t_end):
                    reached = False
                    break
                state = self.bridge.state() or state
                if not self.site_still_clear(site, state.p):
                    self._event("land_site_blocked", {"site_m": site.tolist(), "seen_from_m": state.p.tolist()})
                    rejected.append(site.copy())
                    continue
            self._event("land_site", {"site_m": site.tolist(), "found_by": how, "from_m": state.p.tolist(), "attempt": attempt})
            over = np.array([site[0], site[1], max(float(state.p[2]), cfg.land_handover_height_m)])
            low = np.array([site[0], site[1], cfg.land_handover_height_m])
            reached = self._fly_to(over, 0.3, 0.3, t_end, face_goal=True)
            if reached:
                reached = self._fly_to(low, 0.3, 0.15, t_end)
            if reached is not None:
                break
            self._event("land_site_blocked", {"site_m": site.tolist()})  # the new frames show something there: choose again
            rejected.append(site.copy())
            state = self.bridge.state() or state
        if not reached:
            if self.bridge.released:
                return
            self._event("land_approach_failed", {"site_m": site.tolist(), "then": "hold"})
            self._hand_over_hold()
            return
        self.t_handover_s = self.clock.now_s()
        self.session.expect(self._land_mode, "commanded landing")
        try:
            self.bridge.command(_M.MAV_CMD_NAV_LAND, (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, math.nan))
        except BridgeError as exc:
            self._event("land_failed", {"error": str(exc), "then": "hold"})
            self._hand_over_hold()
            return
        self.bridge.stop_streaming()
        self._event("land", {"height_m": float(self.bridge.state().p[2])})
        t_land = self.clock.now_s()
        while True:
            t = self._wait_next()
            if self.bridge.released:  # someone else changed the mode during the landing
                self._on_takeover(t)
                return
            status, state = self.bridge.status(), self.bridge.state()
            if state is not None:
                self._trace.append((t, state.p.copy()))
            if status is not None and not status.armed:
                height = None if state is None else float(state.p[2])
                if height is not None and height > cfg.land_crash_height_m:
                    self.crash_suspected = True
                    self._event("disarmed_in_the_air", {"height_m": height, "position_m": state.p.tolist()})
                else:
                    self.landed = True
                    self._event("landed", {"duration_s": t - t_land, "position_m": None if state is None else state.p.tolist()})
                return
            if t - t_land > cfg.land_timeout_s:
                self._event("land_timeout", {"timeout_s": cfg.land_timeout_s})
                return
            if FailsafeCause.HEARTBEAT_LOST in self.bridge.failsafe.active():
                self._event("land_unconfirmed", {"why": "vehicle heartbeat lost during the landing"})
                return

    # -- records ----------------------------------------------------------------------------
    def _rel(self, t: float) -> float:
        base = self.t_begin_s if self.t_begin_s is not None else self._t_start
        return round(float(t - base), 4)

    def _event(self, kind: str, data: dict, t_s: float | None = None) -> None:
        t = self.clock.now_s() if t_s is None else t_s
        self.events.append({"t_abs_s": float(t), "kind": kind, "data": data})
        log.info("onboard %s: %s", kind, data)
        if self.writer is not None:
            try:
                self.writer.event(f"onboard.{kind}", data, t_s=t)
            except Exception as exc:  # noqa: BLE001
                log.warning("log event failed: %s", exc)

    def _summary(self, end: str) -> FlightSummary:
        p = self.pilot
        for e in self.events:
            e["t_s"] = self._rel(e.pop("t_abs_s"))
        failsafes = []
        for e in self.bridge.failsafe.events:
            if self.writer is not None:
                try:
                    self.writer.event("failsafe", e.as_dict(), t_s=e.t_s)
                except Exception as exc:  # noqa: BLE001
                    log.warning("log event failed: %s", exc)
            d = e.as_dict()
            d["t_s"] = self._rel(d["t_s"])
            d["after_handover"] = self.t_handover_s is not None and e.t_s >= self.t_handover_s
            failsafes.append(d)
        t_end = self.t_finished_s
        trace = [(t, x) for t, x in self._trace if t_end is None or t <= t_end]
        metrics = None
        if self.ground_truth is not None and trace and self.t_begin_s is not None:
            from onfly.bench.metrics import EpisodeTrace, episode_metrics

            times = np.array([self.t_begin_s] + [t for t, _ in trace]) - self.t_begin_s
            pos = np.vstack([trace[0][1]] + [x for _, x in trace])
            if self.ground_truth.T_scene_world is not None:
                T = np.asarray(self.ground_truth.T_scene_world, dtype=float)
                pos = pos @ T[:3, :3].T + T[:3, 3]
            finished = self.t_finished_s is not None and end == "finished"
            m = episode_metrics(
                EpisodeTrace(times, pos, stopped_by_method=finished and not self.crash_suspected, collided=self.crash_suspected),
                self.ground_truth.goal,
                self.ground_truth.reference_path_m,
                self.ground_truth.success_radius_m,
            )
            metrics = {"task": self.ground_truth.task_id, **asdict(m)}
        kinds: dict[str, int] = {}
        for e in p.events:
            kinds[e.kind] = kinds.get(e.kind, 0) + 1
        ticks = np.array(self._tick_ms) if self._tick_ms else np.zeros(1)
        state = self.bridge.state()
        return FlightSummary(
            instruction=self.instruction,
            autopilot=self.autopilot,
            end_reason=end,
            finished=p.mode is PilotMode.FINISHED,
            flight_time_s=float((self.t_finished_s or (trace[-1][0] if trace else self._t_start)) - (self.t_begin_s or self._t_start)),
            takeoff_s=float(next((e["data"]["duration_s"] for e in self.events if e["kind"] == "takeoff_done"), 0.0)),
            final_position_m=[] if state is None else state.p.tolist(),
            failsafes=failsafes,
            events=self.events,
            pilot={
                "mode": p.mode.value,
                "subtasks": list(p.tasks.subtasks) if p.tasks else [],
                "subtask_index": p.tasks.index if p.tasks else 0,
                "event_counts": kinds,
                "planner_fallbacks": dict(p.planner_fallbacks),
                "ticks_after_takeover": self.pilot_ticks_after_takeover,
            },
            camera={} if self.camera is None else self.camera.stats(),
            loop={
                "ticks": self._ticks,
                "paused_ticks": self._paused_ticks,
                "overruns": self._overruns,
                "tick_ms_mean": float(ticks.mean()),
                "tick_ms_p95": float(np.percentile(ticks, 95)),
                "tick_ms_max": float(ticks.max()),
                "setpoints_sent": len(self.bridge.sent),
                "bridge_errors": list(self.bridge.errors[-10:]),
            },
            metrics=metrics,
            crashed=bool(self.crash_suspected),
            landed=bool(self.landed),
            t_begin_abs_s=None if self.t_begin_s is None else float(self.t_begin_s),
            frames={"world": "anchored at the estimator pose when the flight started (x along the heading, z up, "
                             "heights relative to the start)",
                    "T_local_world": np.asarray(getattr(self.bridge, "T_local_world", np.eye(4))).round(6).tolist(),
                    "camera_frames_reposed": self._frames_reposed},
            trace_t_x_y_z=[[self._rel(t), *map(float, x)] for t, x in self._trace],
        )
