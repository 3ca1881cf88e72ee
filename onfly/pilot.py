"""The OnFly pilot: dual agents, hybrid memory, task manager, verifier, ESDF and MPC in one loop.

One :meth:`OnFlyPilot.tick` per control period (0.1 s by default):

1. a new camera frame (when there is one) updates the ESDF and the monitoring memory;
2. agent calls that have landed are applied: a decision sets the navigation goal (or is
   logged and ignored when it failed); a monitoring status feeds the task manager
   (stable STOP advances or finishes; LOST starts the stop-and-reorient recovery);
3. idle agents are started when due: the decision agent as soon as its last call landed and a
   new frame exists (high rate), the monitoring agent every ``monitor_period_s``; before the
   one-time decomposition has landed only the decision agent runs, on the whole instruction
   (``early_start``), so the vehicle does not hover through that call;
4. the planner runs on the latest verified goal, whatever the agents are doing.

Safety rules the loop keeps: no goal yet, a goal older than ``goal_timeout_s`` without a fresh
decision, or recovery in progress -> hold position; the planner's own fallbacks (shifted plan,
braking) cover solver failures. A VLM that times out or emits garbage never blocks the loop.
Every goal, search point and hold point stays inside the operator's flight volume (``volume``),
and so does every plan.

Ours, beyond the paper: when the current subtask's target is not being found ("not visible"
answers, unparseable or rejected decisions, a LOST with nothing to turn back to, a dead end)
the pilot searches (mode ``SEARCHING``, :mod:`onfly.search`): a scan in place, then legs to the
map's frontiers, until a decision points at the target again; LOST turns toward the last
sighting when there is one.

Ablations (paper, Table III) are switches of :class:`PilotConfig`: ``dual_agent=False`` runs
decision and monitoring as one stream (one call pays both latencies), ``verify=False`` lifts
raw pixels, ``use_planner=False`` flies goals in straight lines, and the memory strategy is
``memory.strategy``.
"""

from __future__ import annotations

import logging
import tomllib
from dataclasses import asdict, dataclass, field, replace
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from onfly.agents import DecisionAgent, DecisionOutcome, MonitoringAgent, MonitorOutcome
from onfly.follow import FollowConfig, Follower
from onfly.memory import MemoryConfig, make_memory
from onfly.observation import Observation
from onfly.runtime import AgentRuntime, Landed
from onfly.search import (
    Search,
    SearchConfig,
    SearchPhase,
    SearchTrigger,
    at_dead_end,
    best_look_target,
    leg_end_held,
    explore_target,
    frontier_target,
    look_target,
    open_heading,
    open_ray_target,
    side_opening,
    side_to_look,
    unknown_fraction,
)
from onfly.serialize import config_from_tables, to_jsonable
from onfly.task_manager import Status, TaskEvent, TaskManager, same_subtask
from planning.approach import approach_point
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig
from planning.frames import wrap_angle
from planning.movers import MoverConfig, MoverTracker
from planning.planner import Planner, PlanResult, map_frame
from planning.planner_config import PlannerConfig, PlannerConfigError, check_field_reach
from planning.straight_line import straight_line_plan
from planning.trajectory import Trajectory, VehicleState
from planning.verifier import Verifier, VerifierConfig
from planning.volume import FlightVolume
from vlm.compass import compass_heading
from vlm.decompose import DecompositionError, count_steps, decompose_detailed
from vlm.following import follow_intent
from vlm.feature_cache import FeatureCache
from vlm.parsing import CoordFormat
from vlm.turns import opening_turn
from vlm.types import VlmBackend

__all__ = ["PilotConfig", "PilotConfigError", "PilotMode", "PilotEvent", "PilotTick", "OnFlyPilot"]

log = logging.getLogger(__name__)

#: A goal nearer than this (horizontal, metres) is flown to without turning first: a step back
#: or aside while a STOP is confirmed is not worth a half turn.
_TURN_FIRST_MIN_M = 1.0
# a routed goal keeps this much more than the planner's safety distance from every obstacle and
# from the target: the guide search needs a cell of slack around the goal to end on
_ROUTE_MARGIN_M = 0.15
#: a vehicle slower than this is at rest, m/s (a leg the planner cannot plan on ends; a goal
#: whose target is gone is reached)
_AT_REST_MPS = 0.1

#: half-width of the sector a compass heading names, radians (a quarter of the horizon)
_ROUTE_SECTOR_RAD = np.pi / 4
#: how often a leg's sides are checked for an opening to glance into, seconds (a frame's period)
_GLANCE_CHECK_PERIOD_S = 0.5

#: An odometry reset: consecutive frames whose camera moved farther than this many metres per
#: second of their time apart (and at least ``_ODOMETRY_RESET_MIN_M``). No multicopter flown
#: here does 10 m/s (the planner's limit is 0.6 m/s; the gust runaway of docs/robustness.md
#: peaked at 3.9 m/s); a VIO/LIO estimator re-initialising or an EKF's position reset
#: (PX4's ``xy_reset_counter``) does, in one step.
_ODOMETRY_RESET_SPEED_MPS = 10.0
_ODOMETRY_RESET_MIN_M = 1.0

DECISION = "decision"
MONITORING = "monitoring"
SINGLE = "single"
DECOMPOSE = "decompose"


#: Below the raised height by more than this, metres, a raised goal is drawn in to climb first.
_CLIMB_TOLERANCE_M = 0.1
#: ... but not nearer than this horizontally, metres: a goal straight above is a hover.
_CLIMB_MIN_REACH_M = 1.0


class PilotConfigError(ValueError):
    """Invalid pilot configuration (names the field)."""


@dataclass(frozen=True)
class PilotConfig:
    """Every parameter of the pilot; nested configs hold the planner, verifier, ESDF, memory.

    Attributes
    ----------
    control_period_s : planner period (10 Hz)
    monitor_period_s : monitoring-agent period (paper: 2 s)
    stop_confirmations : consecutive STOPs that make a STOP stable. After a STOP that is not
        yet stable (mode ``CONFIRMING``) the monitor is asked again as soon as a new frame
        arrives, so confirming costs one call, not a flight of ``monitor_period_s`` past a
        target beside the path; meanwhile the vehicle hovers where it heard the STOP, or keeps
        approaching its goal when that is within ``confirm_approach_m``
    confirm_approach_m : while confirming, a goal this close (metres) is still flown to (ours):
        the STOP was heard at the edge of the monitor's "close enough", where the next answer
        is a coin toss; a step closer makes a true STOP stable and costs nothing if it was false.
        0 = always hover
    intermediate_stop_confirmations : consecutive STOPs that advance past a subtask that is not
        the last (None = ``stop_confirmations``; ours: a false STOP there only starts the next
        subtask early, while confirming costs a monitoring call at every subtask)
    goal_timeout_s : a goal not refreshed by a successful decision for this long is dropped
        and the vehicle holds (VLM timeouts or garbage)
    recovery_yaw_tolerance_rad : LOST recovery is over once the heading is this close
    recovery_timeout_s : give up turning after this long and resume anyway
    dual_agent : False = one stream that decides and monitors in the same call
    verify : False = raw pixels lifted at their depth (ablation)
    use_planner : False = goals flown in straight lines without the map (ablation)
    coord_format : how the backend writes points (``vlm.parsing.CoordFormat`` value)
    vlm_deadline_s : per-call deadline handed to the backend (None = backend default)
    early_start : while the one-time decomposition call is in flight, run the decision agent
        on the whole instruction and fly its verified goals (ours; the paper does not say what
        the vehicle does meanwhile). The first subtask's own decisions replace them as soon as
        the subtask queue exists; the monitor waits for the queue, so nothing can stop or
        advance the task before it. False = hover until the decomposition lands
    goal_min_z_m : altitude floor for navigation goals, metres above the odometry origin (the
        ground at take-off). A level camera never sees the ground right below and ahead of the
        vehicle, and unobserved space counts as free in the ESDF, so a goal lifted from a pixel
        at an object's base would otherwise pull the vehicle onto unseen ground. Default 0.7 m =
        body radius 0.25 m + the planner's 0.45 m safety distance. None disables it.
    route_blocked : a decision the verifier rejects because no pixel of the target has a
        clear straight ray (something stands in between) flies to the free point in front of
        the target instead (:func:`planning.approach.approach_point`; the planner's guide
        search routes around what is in between). Ours, not the paper's: its verifier rejects
        and the vehicle hovers with the target in view. False = the paper's rule
    subtask_lookahead : both agents are asked about the current subtask with this many of the
        next ones as its later steps ("X, then Y"): the decision points at the last step's
        target when it is in view, and the monitor judges the subtask done when that target is
        reached, as every baseline reads its whole instruction (ours; the paper asks about the
        current subtask alone, which flies an intermediate leg such as "along the aisle" past a
        final target in plain view). 0 = the paper's prompts
    search : the pilot's own search when the target is not being found (``onfly.search``;
        ours, not the paper's). ``SearchConfig(enabled=False)`` is the paper's pilot.
    follow : the follow mode for a subtask that follows a moving person (``onfly.follow``)
    movers : moving obstacles tracked from depth and the space they will sweep, which the
        planner avoids besides the map (:mod:`planning.movers`; ours).
        ``MoverConfig(enabled=False)`` plans against the map alone
    above_movers_s : for this long after a moving obstacle was last tracked, every goal (a
        decision's, a search leg's, the hold point, the follow standoff) keeps the vehicle
        above the tallest tracked mover's top by ``planner.d_safe_m + above_movers_margin_m``
        (``over_movers`` events; ours). People walk in from outside the camera's 90 deg field
        of view, on a constant bearing that the camera never sees, into a vehicle at head
        height; above their heads no one walks into it. The flight volume, and the planner's
        goal check against the ceiling, still bound the goal. Within
        ``above_movers_release_m`` (horizontal) of the target the vehicle was sent to, the
        goal keeps the target's height: a level camera 90 deg wide and 60 deg tall loses a
        person or a low object under it from about 2 m away, and the monitor must see the
        target to say STOP (``plaza-l02`` lost "the man in blue" from 2.4 m above him).
        None = off
    above_movers_margin_m : metres above the planner's safety distance over the movers' top
        (people taller than those seen, tracking error)
    above_movers_release_m : horizontal distance to the target, metres, inside which goals are
        not raised
    above_movers_climb_deg : while the vehicle is under the raised height, a raised goal is
        drawn in along its bearing until the line to it climbs at least this steeply, degrees
        in (0, 90): the vehicle gets over the people first and flies on after. A goal 7 m
        ahead raised 0.9 m is a 7 deg line, 11 s of flight at 0.6 m/s before the vehicle is
        at height, and a walker who crossed in from outside the view 7 m on met it 0.2 m
        above his head (``tests/test_movers.py``). Under the camera's 30 deg upper field edge,
        so the drawn-in goal lies where the camera looks
    turn_first : a decision's goal whose bearing is more than half the camera's horizontal
        field of view off the heading is turned to in place before the
        vehicle flies to it, until it is within a quarter of the field of view (``turn_first``
        events; ours). The MPC would translate while it turns at 0.4 rad/s, for seconds sideways
        or backwards into space the camera has not seen; the map's body sphere calls unknown
        space within 1.2 m free, so the unseen back of a column beside the vehicle is no
        obstacle there (``station-p01``: a decision from a frame of the start's scan put the
        goal 150 deg behind the flight, and the vehicle backed into a column). Not while
        following a person (the follow mode faces them) nor when the pilot looks elsewhere on
        purpose (a glance), nor for a goal within 1 m. Search legs are not turned to: they run
        through the map's free space, and turning before each cost the hard set 6 tasks of 69 in
        time (142 turns). False = fly at once
    keep_in_view_margin_rad : a decision's goal is kept where its target stays inside the
        camera's vertical field of view, this far (radians) inside the image's lower edge
        (``goal_in_view`` events; ours). The planner keeps ``d_safe_m`` plus its tracking margin
        from the floor, 1.2 m or more in gusts, so a goal on a low object (a coffee table, a
        kerb) puts the vehicle above it, where a level camera no longer sees it: the monitor
        cannot say STOP on what it does not see, and the task ends at the time limit on top of
        its target (``duplex-p05``, realistic world: a STOP heard 0.8 m from the table, then the
        confirming approach flew over it and the monitor answered CONTINUE, then LOST). The goal
        is moved back toward the vehicle, level, to the horizontal distance at which the target
        is seen at that depression from the vehicle's altitude. Only targets below the vehicle:
        one above is flown up to (the goal keeps its height). Not while following (the follow
        mode keeps its own standoff), nor while goals are raised over recently tracked movers
        (``above_movers_s``: that rule owns the altitude near people and releases it by the
        target; in the street test a goal held back under a crossing walker's path was walked
        into). The pointed pixel is one point of an object that extends
        below it: 0.1 rad (6 deg) is about half the height a chair-sized object (0.5 m) spans
        from 2.5 m, kept inside the image with the point (at 0.05 rad a sofa 2 m away fell out
        of view in gusts and the monitor answered LOST, ``duplex-o05``). None = off
    keep_in_view_max_m : the farthest (horizontal metres from the target) a goal is moved back:
        a target far below (the ground) is not watched from far away; the goal then stops here
    turn_in_words : an instruction that opens with a turn made where the vehicle is ("turn
        around and head down to the elevator lobby", "turn left into the kitchen";
        :func:`vlm.turns.opening_turn`) is begun by turning in place by that angle from the
        start heading (mode ``TURNING``, ``turn_in_words`` and ``turned`` events; ours). The
        decision agent answers with a pixel of the frame, and the way the words start on lies
        behind or beside the camera: the paper's pilot flies whatever the model points at
        ahead (a held-out hotel's "turn around ...": 12 s down the corridor the wrong way, then
        a dead end). No decision is asked for or flown during the turn, a STOP is still heard,
        and the turn ends within ``recovery_yaw_tolerance_rad`` (or, should the vehicle not get
        there, after twice the time the planner's yaw-rate limit needs plus 2 s). Only the
        opening words: a later subtask's turn ("..., then turn right into the small meeting
        room") is relative to a way the vehicle may already have taken, since the decision
        agent is asked about the next subtask's target too (``subtask_lookahead``) and flies to
        it once it is in view; turning again there turned the hard set's ``office_floor-l06``
        away from its table. False = the paper's pilot
    """

    control_period_s: float = 0.1
    monitor_period_s: float = 2.0
    stop_confirmations: int = 2
    intermediate_stop_confirmations: int | None = 1
    confirm_approach_m: float = 3.0
    goal_timeout_s: float = 8.0
    recovery_yaw_tolerance_rad: float = 0.1
    recovery_timeout_s: float = 10.0
    dual_agent: bool = True
    verify: bool = True
    use_planner: bool = True
    coord_format: str = CoordFormat.PIXEL.value
    vlm_deadline_s: float | None = None
    early_start: bool = True
    goal_min_z_m: float | None = 0.7
    route_blocked: bool = True
    subtask_lookahead: int = 1
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    verifier: VerifierConfig = field(default_factory=VerifierConfig)
    esdf: EsdfConfig = field(default_factory=EsdfConfig)
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    search: SearchConfig = field(default_factory=SearchConfig)
    follow: FollowConfig = field(default_factory=FollowConfig)
    movers: MoverConfig = field(default_factory=MoverConfig)
    above_movers_s: float | None = 20.0
    above_movers_margin_m: float = 0.3
    above_movers_release_m: float = 4.0
    above_movers_climb_deg: float = 20.0
    turn_first: bool = True
    keep_in_view_margin_rad: float | None = 0.1
    keep_in_view_max_m: float = 2.5
    turn_in_words: bool = True

    def __post_init__(self) -> None:
        for name in ("control_period_s", "monitor_period_s", "goal_timeout_s", "recovery_timeout_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise PilotConfigError(f"PilotConfig.{name} must be positive, got {v}")
        if not (np.isfinite(self.confirm_approach_m) and self.confirm_approach_m >= 0):
            raise PilotConfigError(f"PilotConfig.confirm_approach_m must be >= 0, got {self.confirm_approach_m}")
        if self.above_movers_s is not None and not (np.isfinite(self.above_movers_s) and self.above_movers_s >= 0):
            raise PilotConfigError(f"PilotConfig.above_movers_s must be >= 0 or None, got {self.above_movers_s}")
        for name in ("above_movers_margin_m", "above_movers_release_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise PilotConfigError(f"PilotConfig.{name} must be >= 0, got {v}")
        if not (np.isfinite(self.above_movers_climb_deg) and 0.0 < self.above_movers_climb_deg < 90.0):
            raise PilotConfigError(f"PilotConfig.above_movers_climb_deg must be in (0, 90), got {self.above_movers_climb_deg}")
        if self.keep_in_view_margin_rad is not None and not (
            np.isfinite(self.keep_in_view_margin_rad) and 0.0 <= self.keep_in_view_margin_rad < np.pi / 4
        ):
            raise PilotConfigError(
                f"PilotConfig.keep_in_view_margin_rad must be in [0, pi/4) or None, got {self.keep_in_view_margin_rad}"
            )
        if not (np.isfinite(self.keep_in_view_max_m) and self.keep_in_view_max_m >= 0):
            raise PilotConfigError(f"PilotConfig.keep_in_view_max_m must be >= 0, got {self.keep_in_view_max_m}")
        if self.goal_min_z_m is not None and not np.isfinite(self.goal_min_z_m):
            raise PilotConfigError(f"PilotConfig.goal_min_z_m must be finite or None, got {self.goal_min_z_m}")
        if self.stop_confirmations < 1:
            raise PilotConfigError(f"PilotConfig.stop_confirmations must be >= 1, got {self.stop_confirmations}")
        if not (isinstance(self.subtask_lookahead, int) and self.subtask_lookahead >= 0):
            raise PilotConfigError(f"PilotConfig.subtask_lookahead must be an integer >= 0, got {self.subtask_lookahead!r}")
        if self.intermediate_stop_confirmations is not None and self.intermediate_stop_confirmations < 1:
            raise PilotConfigError(
                f"PilotConfig.intermediate_stop_confirmations must be >= 1 or None, got {self.intermediate_stop_confirmations}"
            )
        try:
            check_field_reach(self.planner, self.esdf.max_distance_m)
        except PlannerConfigError as e:
            raise PilotConfigError(f"PilotConfig: {e}") from None
        try:
            CoordFormat(self.coord_format)
        except ValueError:
            raise PilotConfigError(
                f"PilotConfig.coord_format must be one of {[c.value for c in CoordFormat]}, got {self.coord_format!r}"
            ) from None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PilotConfig":
        """Build from a plain dict (e.g. a TOML table); nested tables fill nested configs."""
        nested = {
            "planner": PlannerConfig,
            "verifier": VerifierConfig,
            "esdf": EsdfConfig,
            "memory": MemoryConfig,
            "search": SearchConfig,
            "follow": FollowConfig,
            "movers": MoverConfig,
        }
        return config_from_tables(cls, data, nested, PilotConfigError, "pilot")

    @classmethod
    def from_toml(cls, path: str | Path, table: str = "pilot") -> "PilotConfig":
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
        return cls.from_dict(data.get(table, {}))


class PilotMode(str, Enum):
    STARTING = "starting"  # waiting for the first goal (and the decomposition)
    NAVIGATING = "navigating"
    HOLDING = "holding"  # no valid goal: hover in place
    RECOVERING = "recovering"  # LOST: stopped, turning to the last normal heading
    CONFIRMING = "confirming"  # a STOP heard, not yet stable: ask again on the next frame
    SEARCHING = "searching"  # the target is not being found: scan in place, then explore
    TURNING = "turning"  # the words open with a turn: turning in place before asking the way
    FINISHED = "finished"


@dataclass(frozen=True)
class PilotEvent:
    """Something the pilot did or heard, for logs and recordings."""

    t_s: float
    kind: str
    data: dict


@dataclass(frozen=True, eq=False)
class PilotTick:
    """Result of one tick: the plan to fly (None = keep the last) and whether the task ended."""

    trajectory: Trajectory | None
    finished: bool
    mode: PilotMode
    goal_world: np.ndarray | None
    plan: PlanResult | None




class OnFlyPilot:
    """The full OnFly system over one VLM backend.

    Parameters
    ----------
    config : PilotConfig
    backend : VlmBackend shared by both agents (each keeps its own ``cache_key`` stream)
    runtime : where agent calls run (``ClockRuntime`` in simulation, ``ThreadRuntime`` onboard)
    planner : optional prebuilt Planner (building one costs CasADi set-up; benchmarks reuse it)
    volume : the operator flight volume (world ENU), or None. Every navigation goal, search
        point and hold point is clamped into it, shrunk by the planner's safety distance and its
        drift margin (``goal_clamped`` events), so no goal leads the vehicle out of it.
    """

    def __init__(
        self,
        config: PilotConfig,
        backend: VlmBackend,
        runtime: AgentRuntime,
        planner: Planner | None = None,
        volume: FlightVolume | None = None,
    ) -> None:
        self.config = config
        self.backend = backend
        self.runtime = runtime
        self.features = FeatureCache(backend, capacity=64)
        self.esdf = EsdfMap(config.esdf)
        self.movers = MoverTracker(config.movers)
        self._movers_seen_s = -np.inf  # when a moving obstacle was last tracked
        self._movers_top_m = -np.inf  # the highest top of those tracked since (world z, metres)
        self._over_movers = False  # goals are being raised above the movers
        self._turn_p: np.ndarray | None = None  # where the vehicle holds while it turns to its goal
        self.planner = planner if planner is not None else Planner(config.planner)
        self.planner.reset()
        self.decision = DecisionAgent(
            backend,
            self.features,
            Verifier(config.verifier) if config.verify else None,
            coord_format=config.coord_format,
            d_max_m=config.verifier.d_max_m,
            deadline_s=config.vlm_deadline_s,
        )
        self.monitor = MonitoringAgent(backend, make_memory(config.memory), self.features, deadline_s=config.vlm_deadline_s)
        self.instruction: str | None = None
        self.tasks: TaskManager | None = None
        self.mode = PilotMode.STARTING
        self.goal_world: np.ndarray | None = None
        self.goal_t_s = -np.inf
        self.latest: Observation | None = None
        self._decision_frame: str | None = None
        self._speculative = False  # the goal came from a decision on the whole instruction
        self._last_monitor_s = -np.inf
        self._confirm_frame: str | None = None
        self._recovery_yaw: float | None = None
        self._face_yaw: float | None = None
        self._recovery_start_s = 0.0
        self._hold_p: np.ndarray | None = None
        self._last_plan: PlanResult | None = None
        self._straight_ref: Trajectory | None = None  # the last straight-line plan (use_planner=False)
        self.planner_fallbacks: dict[str, int] = {}
        self.frames_stale = 0  # frames not newer than the last one taken (skipped, _on_frame)
        self.odometry_resets = 0  # pose jumps no flight makes (map forgotten, _on_frame)
        self.events: list[PilotEvent] = []
        self.volume = volume
        self.search = Search(config.search)
        self.follow = Follower(config.follow)  # follow mode (onfly.follow)
        self._no_goal_streak = 0  # decisions in a row without a goal (current subtask)
        self._not_visible_streak = 0  # "target not visible" answers in a row
        self._look: tuple[float, float] | None = None  # (t_s, heading) where the model would look
        self._glance_check_s = -np.inf  # when the leg's sides were last checked for an opening
        self._scan_looks: list[float] = []  # headings where the model would look, during a scan
        self._rejected_streak = 0  # of the decisions without a goal, those the verifier rejected
        self._answered_s = -np.inf  # when the decision agent last gave a parseable answer
        self._last_seen: np.ndarray | None = None  # where the current subtask's target was last pointed at
        # the frame the monitor's latest LOST said last showed the target: (frame id, its
        # heading, radians); the frames a search has turned back to (one look each)
        self._seen_place: tuple[str, float] | None = None
        self._seen_looked: set[str] = set()
        self._dead_spots: list[np.ndarray] = []  # where the vehicle stalled on the current subtask
        self._goal_target: np.ndarray | None = None  # the object the current goal was set for
        self._in_view_logged_t: float | None = None  # goal_t_s of the goal last moved back (one event each)
        self._start_z: float | None = None  # altitude at the first tick (the search's cruise default)
        self._pending_decomposition = None  # the decomposition call, until it is submitted
        self._one_step = False  # the instruction has one step: an answer about it is about the first subtask
        self.east_yaw_rad: float | None = 0.0  # where east lies in the world frame (set_east_yaw)
        self._turn_due: float | None = None  # the turn the instruction opens with, not yet begun (radians, CCW)
        self._turn_yaw: float | None = None  # the heading the turn in the words ends at (world)
        self._turn_until_s = 0.0  # when the turn in the words gives up (seconds)

    # -- lifecycle ------------------------------------------------------------------------------
    def set_east_yaw(self, yaw_rad: float | None) -> None:
        """Where east lies in the pilot's world frame: its yaw, radians (0, the default, for an
        ENU world frame such as the embedded world's), or None when the frame's heading is not
        known (then no compass heading in a subtask is used). An onboard flight whose world
        frame is anchored at the take-off heading sets it from the anchor
        (:class:`onfly.onboard.OnboardFlight`)."""
        self.east_yaw_rad = None if yaw_rad is None else float(wrap_angle(float(yaw_rad)))

    def begin(self, instruction: str, t_s: float) -> None:
        """Start the task: one decomposition call (deterministic fallback on failure).

        The call goes through the runtime like any other, so its latency passes before the
        subtask agents start. With ``early_start`` it is submitted on the first tick, right
        after the first decision on the whole instruction: on one inference engine calls run
        in submission order, and a decomposition first would hold the vehicle for its whole
        latency (about 3 s) before any goal.
        """
        self.instruction = instruction
        self._turn_due = opening_turn(instruction) if self.config.turn_in_words else None
        try:
            self._one_step = count_steps(instruction) == 1
        except DecompositionError:
            self._one_step = False  # the decomposition call reports it

        def call():
            dec = decompose_detailed(instruction, self.backend, deadline_s=self.config.vlm_deadline_s)
            return _Decomposed(dec, dec.response.latency_s if dec.response is not None else 0.0)

        self._pending_decomposition = call
        if not self.config.early_start:
            self._submit_decomposition()

    def _submit_decomposition(self) -> None:
        call, self._pending_decomposition = self._pending_decomposition, None
        if call is not None:
            self.runtime.submit(DECOMPOSE, call)

    @property
    def finished(self) -> bool:
        return self.mode is PilotMode.FINISHED

    def _event(self, t_s: float, kind: str, data: dict) -> None:
        self.events.append(PilotEvent(float(t_s), kind, to_jsonable(data)))

    # -- the loop -------------------------------------------------------------------------------
    def tick(self, t_s: float, state: VehicleState, obs: Observation | None = None) -> PilotTick:
        """One control period. ``obs`` is a new camera frame, or None when none arrived."""
        if self.instruction is None:
            raise RuntimeError("call begin(instruction) before tick()")
        if self._start_z is None:
            self._start_z = float(state.p[2])
        if obs is not None:
            self._on_frame(obs)
        for landed in self.runtime.poll():
            self._apply(landed, state)
        self._begin_turn(t_s, state)
        if self.mode is not PilotMode.FINISHED:
            self._start_agents(t_s)
        self._submit_decomposition()  # after the first decision (``begin``)
        return self._control(t_s, state)

    def _on_frame(self, obs: Observation) -> None:
        """Take one camera frame into the map, the mover tracker and the monitor's memory.

        Two bad inputs of a real camera and odometry are refused here (docs/robustness.md,
        "Constructed sensor cases"):

        - a frame not newer than the last one taken (timestamps duplicated or going back: a
          driver's reordering, a recording's clock) is stale: skipped, counted in
          ``frames_stale`` and logged (``stale_frame`` event); the map, the memory and the
          latest frame stay as they were;
        - a camera position that jumped farther than ``_ODOMETRY_RESET_SPEED_MPS`` times the
          frames' time apart (at least ``_ODOMETRY_RESET_MIN_M``) since the last frame is an
          odometry reset: what the map holds is in the old frame, so the map, the planner's
          reference and the mover tracks are forgotten (unknown is an obstacle, so the vehicle
          holds where its body sphere lets it), the goal is dropped (``HOLDING`` until the next
          decision), counted in ``odometry_resets`` (``odometry_reset`` event); the frame is
          then taken into the fresh map.
        """
        prev = self.latest
        if prev is not None and not obs.t_s > prev.t_s:
            self.frames_stale += 1
            self._event(obs.t_s, "stale_frame", {"t_s": obs.t_s, "latest_t_s": prev.t_s, "frame_id": obs.frame_id})
            return
        if prev is not None:
            jump = float(np.linalg.norm(obs.T_world_cam[:3, 3] - prev.T_world_cam[:3, 3]))
            if jump > max(_ODOMETRY_RESET_MIN_M, _ODOMETRY_RESET_SPEED_MPS * (obs.t_s - prev.t_s)):
                self.odometry_resets += 1
                self._event(obs.t_s, "odometry_reset", {"jump_m": jump, "dt_s": obs.t_s - prev.t_s, "frame_id": obs.frame_id})
                self.esdf.reset()
                self.planner.reset()
                self.movers = MoverTracker(self.config.movers)
                self._last_plan = None
                self._hold_p = None
                self._turn_p = None
                self.goal_world = None
                if self.mode is PilotMode.NAVIGATING:
                    self.mode = PilotMode.HOLDING
        moving = self.movers.observe(obs.t_s, obs.depth_m, obs.camera, obs.T_world_cam, self.esdf)  # before the map has the frame
        if moving:
            if obs.t_s - self._movers_seen_s > (self.config.above_movers_s or 0.0):
                self._movers_top_m = -np.inf  # a new crowd: its own heights
            self._movers_seen_s = obs.t_s
            self._movers_top_m = max(self._movers_top_m, max(t.z_range_m[1] for t in moving))
        map_frame(self.esdf, self.planner, obs.depth_m, obs.camera, obs.T_world_cam, obs.position)
        self.monitor.observe(obs)
        self.latest = obs

    def planning_field(self, t_s: float):
        """The field the planner avoids at ``t_s``: the map, with the space tracked movers will
        sweep (:meth:`planning.movers.MoverTracker.field`)."""
        return self.movers.field(self.esdf, t_s)

    def _asked_subtask(self) -> str:
        """What both agents are asked about: the current subtask with the next
        ``subtask_lookahead`` ones as its later steps (:meth:`TaskManager.with_next`). A
        subtask that follows a person, or is followed by one that does, is asked alone."""
        n = self.config.subtask_lookahead
        steps = self.tasks.subtasks[self.tasks.index : self.tasks.index + 1 + n]
        if any(follow_intent(t) is not None for t in steps):
            return self.tasks.current
        return self.tasks.with_next(n)

    def _start_agents(self, t_s: float) -> None:
        obs = self.latest
        if obs is None:
            return
        turning = self.mode in (PilotMode.RECOVERING, PilotMode.TURNING)  # no decision on a turning view
        if self.tasks is None:
            if not turning:
                self._start_early_decision(obs)
            return
        subtask = self._asked_subtask()
        if not self.config.dual_agent:
            if not self.runtime.busy(SINGLE) and obs.frame_id != self._decision_frame and not turning:
                self._decision_frame = obs.frame_id
                goal = self.goal_world
                snap = self.monitor.snapshot()  # taken here, on the control thread
                self.runtime.submit(SINGLE, lambda: _SingleStream(self.decision.decide(obs, subtask, goal), self.monitor.assess(subtask, snap)))
            return
        if not turning and not self.runtime.busy(DECISION) and obs.frame_id != self._decision_frame:
            self._decision_frame = obs.frame_id
            goal = self.goal_world
            self.runtime.submit(DECISION, lambda: self.decision.decide(obs, subtask, goal))
        confirm_now = self.mode is PilotMode.CONFIRMING and obs.frame_id != self._confirm_frame
        period = self.config.search.monitor_period_s if self.mode is PilotMode.SEARCHING else self.config.monitor_period_s
        if not self.runtime.busy(MONITORING) and (confirm_now or t_s - self._last_monitor_s >= period):
            self._last_monitor_s = t_s
            self._confirm_frame = obs.frame_id
            snap = self.monitor.snapshot()  # taken here, on the control thread
            self.runtime.submit(MONITORING, lambda: self.monitor.assess(subtask, snap))

    def _about_asked(self, subtask: str) -> bool:
        """Whether an answer about ``subtask`` answers what the agents are asked now: the
        same text (:func:`same_subtask`), or the whole instruction when it decomposed into one
        subtask (a call submitted before the decomposition landed, which may reword it)."""
        if same_subtask(subtask, self._asked_subtask()):
            return True
        return self._one_step and self.tasks is not None and same_subtask(subtask, self.instruction)

    def _start_early_decision(self, obs: Observation) -> None:
        """Before the subtask queue exists: decide on the whole instruction (``early_start``),
        on the decision stream (the single stream in the single-stream ablation)."""
        key = DECISION if self.config.dual_agent else SINGLE
        if not self.config.early_start or self.runtime.busy(key) or obs.frame_id == self._decision_frame:
            return
        self._decision_frame = obs.frame_id
        instruction, goal = self.instruction, self.goal_world
        self.runtime.submit(key, lambda: self.decision.decide(obs, instruction, goal))

    def _apply(self, landed: Landed, state: VehicleState) -> None:
        out = landed.outcome
        if isinstance(out, _Decomposed):
            dec = out.decomposition
            self.tasks = TaskManager(list(dec.subtasks), self.config.stop_confirmations, self.config.intermediate_stop_confirmations)
            # one subtask is the whole instruction reworded: answers about either are about it
            self._one_step = len(dec.subtasks) == 1
            if not self._one_step:
                self._last_seen = self._seen_place = None  # sightings on the whole instruction belong to no subtask
                self._look = None
            self._no_goal_streak = self._not_visible_streak = self._rejected_streak = 0
            self._event(
                landed.landed_s,
                "decomposition",
                {"instruction": self.instruction, "subtasks": list(dec.subtasks), "source": dec.source, "reason": dec.reason},
            )
        elif isinstance(out, _SingleStream):
            self._apply_decision(landed.landed_s, out.decision, state)
            self._apply_monitor(landed.landed_s, out.monitor, state)
        elif isinstance(out, DecisionOutcome):
            self._apply_decision(landed.landed_s, out, state)
        elif isinstance(out, MonitorOutcome):
            self._apply_monitor(landed.landed_s, out, state)
        elif isinstance(out, BaseException):
            # an agent call raised (a backend bug): log it, keep flying the last goal
            self._event(landed.landed_s, "agent_error", {"kind": landed.kind, "error": repr(out)})
            log.error("%s call raised: %r", landed.kind, out)

    def _apply_decision(self, t_s: float, out: DecisionOutcome, state: VehicleState) -> None:
        rec = out.verified.record if out.verified is not None else None
        self._event(
            t_s,
            "decision",
            {
                "frame_id": out.frame_id,
                "subtask": out.subtask,
                "status": out.response.status,
                "raw": out.response.text[:500],
                "history_uv": out.history_uv,
                "pixel": out.parse.uv if out.parse is not None else None,
                "goal_world": out.goal_world,
                "reason": out.reason,
                "not_visible": out.not_visible,
                "look_uv": getattr(out.parse, "look_uv", None),
                "verifier": rec,
                "latency_s": out.latency_s,
            },
        )
        if self.mode in (PilotMode.FINISHED, PilotMode.RECOVERING, PilotMode.TURNING):
            return  # a decision on a frame that faced elsewhere
        speculative = same_subtask(out.subtask, self.instruction) and (self.tasks is None or self._speculative)
        if self.tasks is None and not speculative:
            return
        if not speculative and not self._about_asked(out.subtask):
            return  # answered about a subtask that has since advanced
        out = self.follow.on_decision(t_s, out)  # following: the goal is the person, predicted to now
        if out.goal_world is None and out.blocked_target_world is not None and self.config.route_blocked:
            out = self._route_blocked(t_s, out, state)
        target = next((p for p in (out.target_world, out.blocked_target_world, out.goal_world) if p is not None), None)
        if out.goal_world is not None and self.config.goal_min_z_m is not None and out.goal_world[2] < self.config.goal_min_z_m:
            raised = np.array(out.goal_world, float)
            raised[2] = self.config.goal_min_z_m
            self._event(t_s, "goal_raised", {"from_z_m": float(out.goal_world[2]), "to_z_m": float(raised[2])})
            out = replace(out, goal_world=raised)
        if out.goal_world is not None:
            out = replace(out, goal_world=self._clamp_to_volume(t_s, out.goal_world, "decision"))
        if out.goal_world is not None and self._at_dead_spot(out.goal_world):
            # the vehicle stalled there on this subtask: flying back is no way on
            self._event(t_s, "goal_dead_spot", {"goal": out.goal_world})
            out = replace(out, goal_world=None, reason="dead_spot")
        self._count_decision(t_s, out, state)
        if self.mode is PilotMode.CONFIRMING:
            if out.goal_world is not None:  # kept for when the STOP is withdrawn
                self.goal_world = np.asarray(out.goal_world, float)
                self._goal_target = np.asarray(target, float)
                self.goal_t_s = t_s
            return
        if out.goal_world is None:
            # hold the last goal (it times out by itself); with no goal, at least face the
            # target the VLM pointed at, so a rejected edge-of-image target comes into view
            if self.mode is not PilotMode.SEARCHING:
                self._face_yaw = out.pixel_yaw
            return
        if self.mode is PilotMode.SEARCHING and not self.search.may_hand_back(state.p):
            return  # backing out of a dead end first: the model's goals led into it
        self._end_search(t_s, "target_pointed")
        self._face_yaw = None
        self._speculative = speculative
        self.goal_world = np.asarray(out.goal_world, float)
        self._goal_target = np.asarray(target, float)
        self.goal_t_s = t_s
        self.mode = PilotMode.NAVIGATING

    def _apply_monitor(self, t_s: float, out: MonitorOutcome, state: VehicleState) -> None:
        self._event(
            t_s,
            "monitor",
            {
                "subtask": out.subtask,
                "status": out.status,
                "raw": out.response.text[:200],
                "memory": list(out.memory_frame_ids),
                "reason": out.reason,
                "latency_s": out.latency_s,
                "cached_tokens": out.response.usage.cached_tokens,
            },
        )
        if out.status is None or self.tasks is None or self.mode is PilotMode.FINISHED:
            return
        if not same_subtask(out.subtask, self._asked_subtask()):
            return
        if self.mode in (PilotMode.RECOVERING, PilotMode.TURNING) and out.status.value != Status.STOP.value:
            return
        if out.status.value == Status.STOP.value and self.follow.ignores_stop(out.subtask):
            self._event(t_s, "stop_ignored", {"reason": "following without an end", "position": state.p})
            return
        status = Status(out.status.value)
        if status is Status.LOST and out.seen_position is not None and self.config.search.enabled and self.config.search.seen_place:
            self._seen_place = (str(out.seen_frame_id), float(out.seen_yaw))
        joined = not same_subtask(out.subtask, self.tasks.current)  # asked with the next subtask as its later step
        if out.judged_position is not None:
            # the normal point is where the judged frame was taken, not where the answer landed
            event = self.tasks.on_status(status, out.judged_t_s, out.judged_position, out.judged_yaw, joined=joined)
        else:
            event = self.tasks.on_status(status, t_s, state.p, state.yaw, joined=joined)
        if event is TaskEvent.NONE and status is Status.STOP:
            if self.mode is not PilotMode.CONFIRMING:
                # a search is paused, not ended (nothing starts or ends one while confirming but
                # a task event): a STOP that is withdrawn resumes it where it was
                self.mode = PilotMode.CONFIRMING
                self._hold_p = state.p.copy()
                self._face_yaw = None
                self._event(t_s, "stop_heard", {"position": state.p, "stops": self.tasks.pending_stops})
        elif event is TaskEvent.NONE:
            if status is Status.LOST:  # already recovered toward this normal point: fly on
                self._event(t_s, "lost_repeated", {"position": state.p})
                if self.mode is PilotMode.SEARCHING and self._last_seen is None and self._look_at_seen_place(t_s, state):
                    self._event(t_s, "lost", {"recovery": "seen_place", "frame": self._seen_place[0], "position": state.p})
            if self.mode is PilotMode.CONFIRMING:
                # CONTINUE (or a repeated LOST) after an unconfirmed STOP: carry on toward the
                # freshest goal, or with the search the STOP interrupted
                if self.search.active and self.goal_world is None:
                    self.mode = PilotMode.SEARCHING
                else:
                    self._end_search(t_s, "stop_withdrawn")
                    self.mode = PilotMode.NAVIGATING if self.goal_world is not None else PilotMode.HOLDING
                self._event(t_s, "stop_withdrawn", {"position": state.p})
        if event is TaskEvent.LOST and self.search.active and self._last_seen is None:
            # the search is already the recovery, and there is no sighting to turn back to: a
            # look back along the frame the monitor says last showed the target, if it named one
            if self._look_at_seen_place(t_s, state):
                self._event(t_s, "lost", {"recovery": "seen_place", "frame": self._seen_place[0], "position": state.p})
            else:
                self._event(t_s, "lost", {"recovery": "searching", "position": state.p})
            return
        if event is not TaskEvent.NONE:
            self._end_search(t_s, event.value)
        if event is TaskEvent.FINISHED:
            self.mode = PilotMode.FINISHED
            self._hold_p = state.p.copy()
            self._event(t_s, "finished", {"position": state.p})
        elif event is TaskEvent.ADVANCED:
            self.goal_world = None
            self._face_yaw = None
            self._last_seen = self._look = self._seen_place = None
            self._seen_looked = set()
            self._dead_spots = []
            self._no_goal_streak = self._not_visible_streak = self._rejected_streak = 0
            self.mode = PilotMode.HOLDING
            self._event(t_s, "advanced", {"subtask": self.tasks.current, "index": self.tasks.index})
            if self.tasks.pending_stops:
                # the STOP judged the joined text: the last subtask's target is reached, and that
                # STOP is the first of its confirmations; confirm on the next frame
                self.mode = PilotMode.CONFIRMING
                self._hold_p = state.p.copy()
                self._event(t_s, "stop_heard", {"position": state.p, "stops": self.tasks.pending_stops})
        elif event is TaskEvent.LOST:
            self.goal_world = None
            self._face_yaw = None
            self._hold_p = state.p.copy()
            seen = self.follow.where_now(t_s, self._last_seen)  # following: where the person is now
            if self.config.search.enabled and seen is not None and np.linalg.norm(seen[:2] - state.p[:2]) > 0.5:
                # turn toward where the target was last seen (ours; the paper turns to the
                # last normal point's heading, which after a detour can face away from it)
                self._recovery_yaw = float(np.arctan2(seen[1] - state.p[1], seen[0] - state.p[0]))
                source = "last_seen"
            elif self._seen_place is not None:
                self._recovery_yaw = self._seen_place[1]
                source = "seen_place"
            elif self.tasks.last_normal is not None or not self.config.search.enabled:
                self._recovery_yaw = self.tasks.recovery_yaw(state.yaw)
                source = "normal_point"
            else:
                self._event(t_s, "lost", {"recovery": "search", "position": state.p})
                self._start_search(t_s, state, SearchTrigger.LOST)
                return
            self.mode = PilotMode.RECOVERING
            self._recovery_start_s = t_s
            self._event(t_s, "lost", {"recovery_yaw": self._recovery_yaw, "recovery": source, "position": state.p})

    def _control(self, t_s: float, state: VehicleState) -> PilotTick:
        cfg = self.config
        yaw_ref = None
        search_goal = None
        follow = None
        if cfg.search.enabled and self.mode is not PilotMode.FINISHED:
            self.search.remember(t_s, state.p)
            # STARTING counts once the decomposition is in: a start whose every decision is
            # rejected (the model names its target, the verifier finds no feasible goal) is a
            # dead end like any hover, not a wait for the tenth rejection (``reject_streak``,
            # about 26 s with the monitor's calls between the decisions)
            started = self.mode is PilotMode.STARTING and (self.tasks is not None or self._one_step)
            stall_watch = started or self.mode in (PilotMode.NAVIGATING, PilotMode.HOLDING) or (
                self.mode is PilotMode.SEARCHING and self.search.phase is SearchPhase.EXPLORE
            )
            # a stall counts only while the model answers: with a dead model the vehicle holds
            model_alive = t_s - self._answered_s <= cfg.search.stall_window_s
            if stall_watch and model_alive and self.search.stalled(t_s):
                # a dead end: no progress while the task is not done; back out and search
                self._event(t_s, "stalled", {"position": state.p, "window_s": cfg.search.stall_window_s})
                self._dead_spots.append(state.p.copy())
                self.search.leg_failed()
                self._start_search(t_s, state, SearchTrigger.STALL, explore_first=True)
            if self.mode is PilotMode.SEARCHING:
                search_goal, yaw_ref = self._search_control(t_s, state)
        if self.mode is PilotMode.TURNING:
            err = abs(wrap_angle(state.yaw - self._turn_yaw))
            if err <= cfg.recovery_yaw_tolerance_rad or t_s > self._turn_until_s:
                self.mode = PilotMode.HOLDING
                self.search.reset_stall()  # the hold was on purpose
                self._event(t_s, "turned", {"yaw": state.yaw, "yaw_error": err})
            else:
                yaw_ref = self._turn_yaw
        if self.mode is PilotMode.RECOVERING:
            err = abs(wrap_angle(state.yaw - (self._recovery_yaw or state.yaw)))
            if err <= cfg.recovery_yaw_tolerance_rad or t_s - self._recovery_start_s > cfg.recovery_timeout_s:
                self.mode = PilotMode.HOLDING
                self._event(t_s, "resumed", {"yaw": state.yaw, "yaw_error": err})
            else:
                yaw_ref = self._recovery_yaw
        if self.mode is PilotMode.NAVIGATING and t_s - self.goal_t_s > cfg.goal_timeout_s:
            self.goal_world = None
            self.mode = PilotMode.HOLDING
            self._event(t_s, "goal_timeout", {"age_s": t_s - self.goal_t_s})
        to_goal = False  # flying to the decision's goal (not a search leg, a hold or a follow)
        if self.mode is PilotMode.SEARCHING and search_goal is not None:
            goal = search_goal
            self._hold_p = None
        elif self.goal_world is not None and (
            self.mode is PilotMode.NAVIGATING
            # a step closer while a STOP is confirmed
            or (self.mode is PilotMode.CONFIRMING and float(np.linalg.norm(self.goal_world - state.p)) <= cfg.confirm_approach_m)
        ):
            goal = self.goal_world
            self._hold_p = None
            follow = self.follow.control(t_s, state.p, cfg.goal_min_z_m or 0.0)
            if follow is not None:  # following: the standoff point, facing the person
                goal, yaw_ref = follow
            else:
                to_goal = True
        else:
            if self._hold_p is None:
                self._hold_p = state.p.copy()
            goal = self._hold_p
            if yaw_ref is None and self.mode is not PilotMode.FINISHED:
                yaw_ref = self._face_yaw
        if to_goal:
            goal, face = self._keep_in_view(t_s, state, goal)
            if yaw_ref is None:
                yaw_ref = face
            goal, yaw_ref = self._turn_first(t_s, state, goal, yaw_ref)
        else:
            self._turn_p = None
        goal = self._above_movers(t_s, goal, state)
        if self.volume is not None:
            goal = self.volume.clamp(goal, margin_m=self._volume_margin_m)
        if cfg.use_planner:
            plan = self.planner.step(state, goal, self.planning_field(t_s), yaw_ref=yaw_ref, volume=self.volume)
            traj = plan.trajectory
        else:
            plan = None
            traj = straight_line_plan(
                state,
                goal,
                v_max_mps=cfg.planner.v_max_mps,
                a_max_mps2=cfg.planner.a_max_mps2,
                yaw_rate_max_rps=cfg.planner.yaw_rate_max_rps,
                dt_s=cfg.planner.dt_s,
                steps=cfg.planner.horizon_steps,
                yaw_ref=yaw_ref,
                reference=self._straight_ref,  # start from the plan being flown (planner's rule)
            )
            self._straight_ref = traj
        self._last_plan = plan
        if plan is not None and search_goal is not None and self.mode is PilotMode.SEARCHING:
            # a leg whose end the goal check holds back where the vehicle already is (behind a
            # wall, inside an obstacle's clearance) is over: the next leg, not a hover to a stall
            held = plan.goal_adjusted and leg_end_held(plan.goal_used, search_goal, state.p, cfg.search.explore_arrive_m)
            # no safe plan toward the leg's end, the vehicle at rest on the last one flown
            unplanned = not plan.ok and _at_rest(state)
            if self.search.leg_blocked(t_s, held or unplanned):
                self._event(t_s, "search_leg_blocked", {"target": search_goal, "position": state.p, "held_at": plan.goal_used})
        if plan is not None and not plan.ok:
            key = plan.fallback.value
            self.planner_fallbacks[key] = self.planner_fallbacks.get(key, 0) + 1
        return PilotTick(traj, self.finished, self.mode, None if self.goal_world is None else self.goal_world.copy(), plan)

    def _begin_turn(self, t_s: float, state: VehicleState) -> None:
        """Begin the turn the instruction opens with (``turn_in_words``), on the first tick."""
        if self._turn_due is None:
            return
        angle, self._turn_due = self._turn_due, None
        self._turn_yaw = float(wrap_angle(state.yaw + angle))
        self._turn_until_s = t_s + 2.0 * abs(angle) / self.config.planner.yaw_rate_max_rps + 2.0
        self._hold_p = state.p.copy()
        self.mode = PilotMode.TURNING
        self._event(t_s, "turn_in_words", {"angle": angle, "from_yaw": state.yaw, "yaw": self._turn_yaw, "position": state.p})

    # -- search and the flight volume -----------------------------------------------------------
    @property
    def _volume_margin_m(self) -> float:
        """Goals keep the planner's :attr:`Planner.volume_goal_margin_m` from the volume's faces."""
        return self.planner.volume_goal_margin_m

    def _turn_first(self, t_s: float, state: VehicleState, goal: np.ndarray, yaw_ref: float | None):
        """(goal, yaw_ref) for this period: a goal whose bearing is more than half the camera's
        horizontal field of view off the heading is turned to in place first (see
        :class:`PilotConfig` ``turn_first``); otherwise the arguments unchanged."""
        cfg = self.config
        away = goal[:2] - state.p[:2]
        if not cfg.turn_first or not cfg.use_planner or float(np.hypot(*away)) <= _TURN_FIRST_MIN_M:
            self._turn_p = None
            return goal, yaw_ref
        bearing = float(np.arctan2(away[1], away[0]))
        look = bearing if yaw_ref is None else yaw_ref
        if abs(wrap_angle(look - bearing)) > 0.5 * self._half_hfov:
            self._turn_p = None  # the pilot looks elsewhere on purpose (a glance): not ours to turn
            return goal, yaw_ref
        err = abs(wrap_angle(bearing - state.yaw))
        if self._turn_p is None and err > self._half_hfov:
            self._turn_p = state.p.copy()
            self._event(t_s, "turn_first", {"bearing": bearing, "yaw": state.yaw, "goal": goal})
            if float(np.hypot(*away)) > cfg.search.stall_distance_m:
                # holding position on purpose to face a goal whose reach is progress: no dead
                # end (a goal nearer than that, turned to again and again, is one)
                self.search.reset_stall()
        elif self._turn_p is not None and err <= 0.5 * self._half_hfov:
            self._turn_p = None
        if self._turn_p is None:
            return goal, yaw_ref
        return self._turn_p, bearing

    def _keep_in_view(self, t_s: float, state: VehicleState, goal: np.ndarray) -> tuple[np.ndarray, float | None]:
        """(goal, yaw_ref): the goal moved back toward the vehicle, level, so that its target
        below the vehicle stays ``keep_in_view_margin_rad`` inside the latest camera's lower
        image edge when seen from the vehicle's altitude (see :class:`PilotConfig`), and, when
        that backs the vehicle off (it is already nearer the target than the moved goal), the
        heading toward the target (radians, world): backing off it keeps facing what it watches
        instead of turning to the goal behind it. Otherwise ``(goal, None)`` unchanged."""
        cfg = self.config
        target = self._goal_target
        if cfg.keep_in_view_margin_rad is None or target is None or self.latest is None:
            return goal, None
        if cfg.above_movers_s is not None and t_s - self._movers_seen_s <= cfg.above_movers_s:
            # near people the altitude is the above-movers rule's, with its own release by the
            # target; a goal held back under a crossing walker's path was walked into
            return goal, None
        drop = float(state.p[2] - target[2])  # metres the target lies below the vehicle
        if drop <= 0.0:
            return goal, None
        cam, R = self.latest.camera, np.asarray(self.latest.T_world_cam, float)[:3, :3]
        axis_elevation = float(np.arcsin(np.clip(R[2, 2], -1.0, 1.0)))  # the optical axis (camera +z) in the world
        lowest = axis_elevation - float(np.arctan((cam.height - cam.cy) / cam.fy)) + cfg.keep_in_view_margin_rad
        if lowest >= 0.0:  # a camera pitched this far up never sees below the horizon: nothing to keep
            return goal, None
        need = min(cfg.keep_in_view_max_m, drop / float(np.tan(-lowest)))
        off = goal[:2] - target[:2]
        if float(np.hypot(*off)) >= need:
            return goal, None
        back = state.p[:2] - target[:2]
        n = float(np.hypot(*back))
        if n < 1e-6:  # right above the target: back off the way the goal lies, if any
            back, n = off, float(np.hypot(*off))
            if n < 1e-6:
                return goal, None
        moved = np.array([target[0] + need * back[0] / n, target[1] + need * back[1] / n, goal[2]])
        if self._in_view_logged_t != self.goal_t_s:
            self._in_view_logged_t = self.goal_t_s
            self._event(t_s, "goal_in_view", {"target": target, "from": goal, "to": moved, "drop_m": drop})
        face = float(np.arctan2(-back[1], -back[0])) if n < need else None
        return moved, face

    @property
    def _half_hfov(self) -> float:
        """Half the horizontal field of view of the latest frame's camera, radians (45 deg for
        the paper's 90 deg camera, also before the first frame)."""
        return 0.5 * self.latest.camera.hfov_rad if self.latest is not None else np.pi / 4

    def _above_movers(self, t_s: float, goal: np.ndarray, state: VehicleState) -> np.ndarray:
        """``goal`` raised above the movers tracked within ``above_movers_s`` (a new array), or
        ``goal`` itself (see :class:`PilotConfig`)."""
        cfg = self.config
        target = self.goal_world
        if target is not None and float(np.hypot(*(target[:2] - state.p[:2]))) <= cfg.above_movers_release_m:
            return goal  # the last metres to the target at its height, where the camera sees it
        recent = cfg.above_movers_s is not None and t_s - self._movers_seen_s <= cfg.above_movers_s
        if not recent:
            if self._over_movers:
                self._over_movers = False
                self._event(t_s, "over_movers_end", {"last_mover_s": self._movers_seen_s})
            return goal
        z = self._movers_top_m + cfg.planner.d_safe_m + cfg.above_movers_margin_m
        if not self._over_movers:
            self._over_movers = True
            self._event(t_s, "over_movers", {"z_min_m": z, "movers_top_m": self._movers_top_m})
        if goal[2] >= z:
            return goal
        raised = np.array(goal, dtype=float)
        raised[2] = z
        below = z - float(state.p[2])
        if below > _CLIMB_TOLERANCE_M:  # climb first, fly on at height
            to = raised[:2] - state.p[:2]
            h = float(np.hypot(to[0], to[1]))
            h_climb = max(_CLIMB_MIN_REACH_M, below / np.tan(np.radians(cfg.above_movers_climb_deg)))
            if h > h_climb:
                raised[:2] = state.p[:2] + to * (h_climb / h)
        return raised

    def _route_blocked(self, t_s: float, out: DecisionOutcome, state: VehicleState) -> DecisionOutcome:
        """A decision rejected for a blocked ray, with the free point in front of its target as
        the goal (:func:`planning.approach.approach_point`), or unchanged when there is none."""
        if self.follow.intent(out.subtask) is not None:
            return out  # a person is followed at the follower's standoff, never routed to
        cfg = self.config
        goal = approach_point(
            out.blocked_target_world, state.p, self.esdf,
            clearance_m=cfg.planner.d_safe_m + _ROUTE_MARGIN_M, standoff_m=cfg.planner.d_safe_m + _ROUTE_MARGIN_M,
            z_min_m=cfg.goal_min_z_m, volume=self.volume, volume_margin_m=self._volume_margin_m,
        )  # fmt: skip
        if goal is None:
            return out
        self._event(t_s, "goal_routed", {"target": out.blocked_target_world, "goal": goal, "position": state.p})
        return replace(out, goal_world=goal, reason="")

    def _clamp_to_volume(self, t_s: float, goal, source: str) -> np.ndarray:
        g = np.asarray(goal, dtype=float)
        if self.volume is None or bool(self.volume.contains(g, margin_m=self._volume_margin_m)[0]):
            return g
        clamped = self.volume.clamp(g, margin_m=self._volume_margin_m)
        self._event(t_s, "goal_clamped", {"source": source, "from": g, "to": clamped})
        return clamped

    def _end_search(self, t_s: float, reason: str) -> None:
        if self.search.active:
            self._event(t_s, "search_end", {"reason": reason, "duration_s": t_s - self.search.started_s})
            self.search.stop()

    def _cruise_z(self, state: VehicleState) -> float:
        """Altitude of the search's legs, metres: the configured one, else the task's start
        altitude (else the vehicle's), never below the goal floor."""
        z = self.config.search.cruise_z_m if self.config.search.cruise_z_m is not None else self._start_z
        z = float(state.p[2]) if z is None else float(z)
        return z if self.config.goal_min_z_m is None else max(z, self.config.goal_min_z_m)

    def _count_decision(self, t_s: float, out: DecisionOutcome, state: VehicleState) -> None:
        """Streaks of decisions without a goal; start a search when one is long enough."""
        if out.parse is not None:
            self._answered_s = t_s  # the model answers (a goal or not): a stall is a dead end
        if out.goal_world is not None:
            self._no_goal_streak = self._not_visible_streak = self._rejected_streak = 0
            # the pointed object itself, not the goal: a goal shortened by the bearing gating or
            # the verifier can lie a few decimetres from the vehicle, in any direction
            seen = next(p for p in (out.target_world, out.blocked_target_world, out.goal_world) if p is not None)
            self._last_seen = np.asarray(seen, float).copy()
            return
        if out.parse is None:
            return  # the call itself failed: a search cannot hand back without a working model
        self._no_goal_streak += 1
        if out.verified is not None and not out.verified.accepted:
            self._rejected_streak += 1
        self._not_visible_streak = self._not_visible_streak + 1 if out.not_visible else 0
        scfg = self.config.search
        if (
            out.not_visible and out.look_yaw is not None and scfg.enabled and scfg.look_hints
            and not self.search.during_glance(out.frame_t_s)
        ):  # fmt: skip
            self._look = (t_s, float(out.look_yaw))
            if self.search.phase is SearchPhase.SCAN and not self.search.glancing:
                self._scan_looks.append(float(out.look_yaw))
        if self.search.active and self.search.phase is SearchPhase.EXPLORE and self.search.leg_kind == "look":
            target = self._look_leg(t_s, state)  # a fresher look point re-aims the leg
            if target is not None:
                self.search.reaim(t_s, target)
        if not scfg.enabled or self.search.active or self.mode in (PilotMode.CONFIRMING, PilotMode.FINISHED):
            return
        if self.mode is PilotMode.NAVIGATING and self.goal_world is not None:
            # a target seen moments ago and missed now (far, small, occluded for a frame): keep
            # flying its goal; when that goal times out the streak starts the search. At the
            # goal there is nothing left to fly: the streak starts the search at once, a turn
            # round from where the target was last seen (it was here moments ago), instead of
            # a hover to the timeout
            if self._not_visible_streak >= scfg.not_visible_streak and self._at_goal(state):
                self._start_search(t_s, state, SearchTrigger.NOT_VISIBLE)
            return
        # an answer about the whole instruction before the decomposition is about its last
        # target, which is the first subtask's only when the instruction has one step
        about_current = self.tasks is not None or self._one_step
        if out.not_visible and about_current and self.search.searches == 0 and scfg.scan_first_search:
            # the episode's first search turns all round before any leg (the start view is a
            # quarter of the horizon)
            self._start_search(t_s, state, SearchTrigger.NOT_VISIBLE)
        elif out.not_visible and about_current and self._look_leg(t_s, state) is not None:
            # the model says where it would look: go there now, no scan (it has just seen this view)
            self._start_search(t_s, state, SearchTrigger.NOT_VISIBLE, explore_first=True)
        elif self._not_visible_streak >= scfg.not_visible_streak:
            self._start_search(t_s, state, SearchTrigger.NOT_VISIBLE)
        elif self._no_goal_streak - self._rejected_streak >= scfg.fail_streak or self._no_goal_streak >= scfg.reject_streak:
            # a target the verifier keeps rejecting is usually in view and near (no feasible
            # goal in front of it): the monitor's STOP gets longer to arrive before we turn away
            self._start_search(t_s, state, SearchTrigger.NO_GOAL)

    def _at_goal(self, state: VehicleState) -> bool:
        """True when the vehicle is at rest (:func:`_at_rest`) within ``explore_arrive_m`` of
        the goal the last plan flew to (the decision's goal after the pilot's and the planner's
        adjustments: the end of the flight, not the pointed pixel; without the planner, the
        decision's goal)."""
        end = self.goal_world if self._last_plan is None else self._last_plan.goal_used
        return (
            end is not None
            and _at_rest(state)
            and float(np.linalg.norm(end - state.p)) <= self.config.search.explore_arrive_m
        )

    def _at_dead_spot(self, goal: np.ndarray) -> bool:
        """True when ``goal`` lies within ``dead_end_radius_m`` (horizontally) of a place where
        the vehicle stalled on the current subtask (:class:`SearchConfig`)."""
        return self.config.search.enabled and at_dead_end(self._dead_spots, goal, self.config.search.dead_end_radius_m)

    def _look_leg(self, t_s: float, state: VehicleState) -> np.ndarray | None:
        """The leg toward the freshest look point (:func:`onfly.search.look_target`), or None
        (no look point younger than ``look_max_age_s``, or no leg that way)."""
        scfg = self.config.search
        if self._look is None or not scfg.look_hints or t_s - self._look[0] > scfg.look_max_age_s:
            return None
        if not self._along_route(self._look[1], self._route_yaw()):
            return None
        return look_target(
            state.p, self._look[1], self.esdf, config=scfg, volume=self.volume, volume_margin_m=self._volume_margin_m,
            visited=self.search.visited, z_m=self._cruise_z(state), dead_ends=self.search.dead_ends,
        )  # fmt: skip

    def _route_yaw(self) -> float | None:
        """The compass heading the current subtask names (:func:`vlm.compass.compass_heading`)
        as a yaw in the world frame (radians, east at :attr:`east_yaw_rad`), or None (none
        named, ``compass`` off, east unknown, or no subtask yet: before the decomposition only
        a one-step instruction is its first subtask)."""
        if not self.config.search.compass or self.east_yaw_rad is None:
            return None
        if self.tasks is not None:
            heading = compass_heading(self.tasks.current)
        else:
            heading = compass_heading(self.instruction) if self._one_step else None
        return None if heading is None else float(wrap_angle(heading + self.east_yaw_rad))

    @staticmethod
    def _along_route(yaw: float, route: float | None) -> bool:
        """False for a heading outside the compass sector of ``route`` (:meth:`_route_yaw`;
        within ``_ROUTE_SECTOR_RAD`` of it: "west" is the quarter of the horizon about west)."""
        return route is None or abs(wrap_angle(yaw - route)) <= _ROUTE_SECTOR_RAD

    def _last_seen_yaw(self, state: VehicleState) -> float | None:
        """Heading from the vehicle to where the target was last seen: the decision agent's
        sighting, else the heading of the frame the monitor's LOST named; None without either."""
        seen = self._last_seen
        if seen is None:
            return None if self._seen_place is None else self._seen_place[1]
        if np.linalg.norm(seen[:2] - state.p[:2]) <= 0.5:
            return None
        return float(np.arctan2(seen[1] - state.p[1], seen[0] - state.p[0]))

    def _look_at_seen_place(self, t_s: float, state: VehicleState) -> bool:
        """While searching: turn the camera back to the heading of the frame the monitor's LOST
        named (a short look, then the search goes on), once per named frame, so the decision
        agent gets a fresh view of what that frame showed. False when there is no new place or
        the camera already faces it (within a quarter of the field of view)."""
        if self._seen_place is None or self._seen_place[0] in self._seen_looked:
            return False
        self._seen_looked.add(self._seen_place[0])
        yaw = self._seen_place[1]
        if abs(wrap_angle(yaw - state.yaw)) <= np.pi / 8:
            return False
        self.search.look(t_s, state.p, [yaw])
        return True

    def _start_search(self, t_s: float, state: VehicleState, trigger: SearchTrigger, explore_first: bool = False) -> None:
        toward = self._last_seen_yaw(state)
        fresh = not self.search.active
        travel = self.search.travel_heading(t_s)
        scfg = self.config.search

        def worth_scanning(yaw: float) -> bool:
            return unknown_fraction(state.p, yaw, self.esdf, self.volume, scfg.gain_lookahead_m) >= scfg.scan_gain_min

        self.search.start(t_s, state.p, state.yaw, trigger, toward_yaw=toward, worth_scanning=worth_scanning)
        self._scan_looks = []
        if fresh:
            # keep going the way the vehicle was going, unless that way is closed (a dead end:
            # its heading when it stalled); a vehicle that was not under way (the start, a
            # hover) has no way to keep: a heading chosen at take-off says nothing of the route
            ahead = travel if travel is not None else (state.yaw if trigger is SearchTrigger.STALL else None)
            route = self._route_yaw()
            if route is not None:  # the words say which way the route runs (search.py 3e)
                self.search.heading0 = route
            else:
                self.search.heading0 = (
                    None if ahead is None else open_heading(state.p, ahead, self.esdf, clearance_m=self.config.search.explore_clearance_m)
                )
        self.search.reset_stall()
        self._no_goal_streak = self._not_visible_streak = self._rejected_streak = 0
        self.goal_world = None
        self._face_yaw = None
        self._hold_p = state.p.copy()
        self.mode = PilotMode.SEARCHING
        self._event(
            t_s,
            "search_start",
            {"trigger": trigger.value, "position": state.p, "toward_yaw": toward, "heading": self.search.heading0, "travel": travel},
        )
        if explore_first:
            self._explore(t_s, state)

    def _best_scan_look(self, state: VehicleState) -> np.ndarray | None:
        """After a scan: the best leg toward where the model would look from each heading
        (:func:`onfly.search.best_look_target`), or None; the scan's look points are used once."""
        route = self._route_yaw()
        looks, self._scan_looks = [y for y in self._scan_looks if self._along_route(y, route)], []
        if not looks:
            return None
        keep = self.search.heading0 if self.search.heading0 is not None else self.search.yaw0
        return best_look_target(
            state.p, looks, self.esdf, config=self.config.search, volume=self.volume, volume_margin_m=self._volume_margin_m,
            visited=self.search.visited, z_m=self._cruise_z(state), dead_ends=self.search.dead_ends, keep_yaw=keep,
        )  # fmt: skip

    def _explore(self, t_s: float, state: VehicleState) -> None:
        """Pick the next exploration point and fly toward it (or scan again if none)."""
        z = self._cruise_z(state)
        common = dict(
            config=self.config.search, volume=self.volume, volume_margin_m=self._volume_margin_m, visited=self.search.visited, z_m=z,
            dead_ends=self.search.dead_ends,
        )
        # where the model would look first; then the most promising frontier of the map; the
        # ring of straight legs where the map has no reachable frontier at this height
        target, how = (self._best_scan_look(state) if self._scan_looks else None), "look"
        if target is None:
            target = self._look_leg(t_s, state)
        if target is None and self.config.search.explore_policy == "open_ray":
            target, how = open_ray_target(state.p, self.search.heading0, self.esdf, **common), "open_ray"
        if target is None:
            target, how = frontier_target(state.p, self.search.heading0, self.esdf, **common), "frontier"
        if target is None:
            target = explore_target(state.p, self.search.heading0, self.esdf, prefer_yaw=self._last_seen_yaw(state), **common)
            how = "ring"
        if target is not None and self._route_yaw() is None and (self.search.heading0 is None or how == "look"):
            # the first leg of a search with no way to keep sets it: later legs go on from there
            # rather than zig-zag between frontiers on either side; the model's look sets it too
            self.search.heading0 = float(np.arctan2(target[1] - state.p[1], target[0] - state.p[0]))
        self.search.explore_from(t_s, target, state.p, state.yaw, kind=how)
        self._event(t_s, "search_explore", {"target": target, "position": state.p, "how": how})

    def _search_control(self, t_s: float, state: VehicleState) -> tuple[np.ndarray, float | None]:
        if self.search.may_glance(state.p) and t_s - self._glance_check_s >= _GLANCE_CHECK_PERIOD_S:
            # an opening beside the leg (a doorway passed): look in, then go on with the leg
            self._glance_check_s = t_s
            to = self.search.leg_end[:2] - state.p[:2]
            side = side_opening(state.p, float(np.arctan2(to[1], to[0])), self.esdf, config=self.config.search, volume=self.volume)
            if side is not None:
                self.search.glance(t_s, state.p, side)
                self._event(t_s, "search_glance", {"yaw": side, "position": state.p})
        point, yaw_ref, ev = self.search.control(t_s, state.p, state.yaw)
        if ev == "scan_done":
            self._explore(t_s, state)
            point, yaw_ref, _ = self.search.control(t_s, state.p, state.yaw)
        elif ev == "explore_done":
            # without a weave the camera faced forward all the leg: look to the side with the
            # most unknown space, then the next leg (the turn onto it sweeps more sectors)
            leg = self.search.leg_length_m(state.p)
            side = None
            if leg >= self.config.search.min_leg_m and self.config.search.weave_rad <= 0.0:
                side = side_to_look(state.p, state.yaw, self.esdf, config=self.config.search, volume=self.volume)
            if side is None:
                self._explore(t_s, state)
            else:
                self.search.look(t_s, state.p, [side])
                self._event(t_s, "search_look", {"yaw": side, "position": state.p})
            point, yaw_ref, _ = self.search.control(t_s, state.p, state.yaw)
        return point, yaw_ref


@dataclass(frozen=True, eq=False)
class _Decomposed:
    decomposition: Any
    latency_s: float


@dataclass(frozen=True, eq=False)
class _SingleStream:
    """Outcome of the single-stream ablation: both answers of one call, both latencies paid."""

    decision: DecisionOutcome
    monitor: MonitorOutcome

    @property
    def latency_s(self) -> float:
        return self.decision.latency_s + self.monitor.latency_s


def _at_rest(state: VehicleState) -> bool:
    """True when the vehicle's speed is under ``_AT_REST_MPS`` (0.1 m/s)."""
    return float(np.linalg.norm(state.v)) < _AT_REST_MPS
