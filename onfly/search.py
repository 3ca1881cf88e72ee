"""Search: what the pilot does while the current subtask's target is not being found.

Ours, not the paper's: the paper's pilot only flies toward points the decision agent gives and,
on LOST, turns back to the last normal heading. With the target out of view at the start, in a
dead-end corner, or after a LOST with nothing to turn back to, that pilot hovers or wanders
toward whatever the model points at. The search is the pilot's own behaviour and reads only
what the pilot has (the map's known and unknown space, poses, the agents' answers), so it flies
the same with a real VLM as with the simulated one.

Policy (parameters in :class:`SearchConfig`):

1. **Triggers** (the pilot decides, :class:`SearchTrigger`): ``not_visible_streak`` decision
   answers in a row that say the target is not visible (while a goal seen moments ago is still
   being flown, only once the vehicle is at rest on it; before, the goal is flown on, and its
   timeout ends it); ``fail_streak`` decisions in a row that
   gave no goal for another reason than a verifier rejection (unparseable answers), or
   ``reject_streak`` without a goal, rejections included (a call that failed outright counts
   for nothing: with a dead model the pilot holds, the companion failsafes act); a LOST with nothing to turn back to; no progress (less than ``stall_distance_m`` of
   travel in ``stall_window_s``) while the task is not finished (a dead end), from the start
   on once the decomposition is in (a start whose every decision the verifier rejects).
2. **Scan**: turn in place through the field of regard, ``scan_step_rad`` at a time, so each new
   frame shows the decision agent a new sector; first toward where the target was last seen
   when that is known. Three quarter turns cover the rest of the horizon with a 90 deg camera;
   a heading whose sector the camera has already seen from here (unknown fraction below
   ``scan_gain_min``) is skipped, so a second search nearby goes straight to exploring.
3. **Explore**: legs at the cruise altitude (``cruise_z_m``, default the task's start
   altitude), inside the flight volume, away from places already visited: to the reachable
   place next to the most promising frontier of the map's known space (``explore_policy =
   "frontier"``, the default) or down the longest line of sight through seen free space
   (``"open_ray"``); the ring of straight legs when neither finds one. On a leg the camera
   weaves ``weave_rad`` either side of the leg's bearing (a triangle wave inside the yaw-rate
   limit), so the flight itself looks for the target over a wider field of regard than the
   camera's (off by default, see ``weave_rad``); without a weave the vehicle looks a quarter
   turn to the side that opens on the most unseen space after each leg (:func:`side_to_look`). Legs prefer the heading the search began with
   when the way ahead was open then (a route goes on), and its reverse when it was not (a dead
   end: back out).
3b. **Where the model would look** (``look_hints``): a decision answer that says the target is
   not visible may carry the point where the model would look for it instead (the decision
   prompt's ``decision/v3``: a doorway, a corridor, open space leading on). Its viewing ray's
   heading is a leg: down the longest run of seen free space within ``look_cone_rad`` of it
   (:func:`look_target`, at most ``open_ray_max_m``, at least ``look_min_leg_m``). The first such
   answer starts the search straight on that leg (no scan: the model has just looked at this
   view and said where to go), each later one re-aims the leg (within twice ``look_cone_rad``
   of the leg's first bearing: each new view has a deepest direction of its own, and following
   them one after another walks a leg round in a circle), and a leg that ends picks the
   freshest one (at most ``look_max_age_s`` old) before the map's frontiers. After a scan the
   leg is the best of the looks the model gave from each of its headings
   (:func:`best_look_target`: the longest, weighted by direction against the way kept), not
   the last one. A look point into a wall, or toward places already visited, is no leg; then
   the search goes on as above (the scan when nothing is reachable, the frontiers, a dead end
   backed out of). The episode's first search is the exception (``scan_first_search``): it
   scans before any leg, so a target beside or behind the start is seen without flying away
   from it (about 12 s of turning at the paper's 0.4 rad/s; the attribute says what it
   measured).
3c. **Glances** (``glance``): on a leg the camera faces the way of travel, and a doorway or a
   gap beside the way goes by unseen (the hard set's ``office_floor-o04``: a corridor leg past
   the copy room's door, the printer never in a frame). Every frame period the pilot checks
   both sides of the leg (:func:`side_opening`): a fan of rays that meets unseen space within
   ``glance_open_within_m``, before any seen obstacle, is an opening. The vehicle then holds,
   faces it for ``glance_dwell_s`` (one decision on a frame that shows it) and goes on with
   the same leg, at most once every ``glance_spacing_m`` and not in the leg's first
   ``glance_open_within_m`` (the walls beside its start are not yet in view). The unseen side
   of a wall already seen is no opening; a side wall the camera has not yet seen is (it may be
   a door). Look points from frames taken from a glance until the camera faces the leg again
   do not re-aim the leg (:meth:`Search.during_glance`): those views are oblique, and their
   deepest directions pull the leg sideways.
3d. **A leg that cannot be flown ends**: when the planner's goal check holds the leg's end
   back where the vehicle already is (an end behind a wall, round a corner; at any distance
   beyond arrival: :func:`leg_end_held`), or the planner finds no safe plan
   toward it while the vehicle is at rest (a gap its linearized clearance cannot thread), for
   ``leg_blocked_s``, the leg is over (:meth:`Search.leg_blocked`) and the next one is chosen,
   instead of a hover until the stall window ends. Its end is a dead end (as is the end of a
   leg the vehicle stalled on): no later leg ends within ``dead_end_radius_m`` of one
   (:attr:`Search.dead_ends`), so the next choice from the same place is another way.
3e. **A heading in the words** (``compass``): a subtask that names a compass heading (``fly
   east along the row of parked cars``, ``follow the hallway west``) says which way its route
   runs, which neither the map nor a frame does. While it is the current subtask, that heading
   is the way every search keeps (legs are valued by their direction against it, as against a
   way kept), a look leg outside its quarter of the horizon (45 deg either side) is not taken, and no look re-sets it.
   A compass word before a noun (``the north aisle``) names a thing, not a heading.
4. **Hand back**: any decision that yields a verified goal for the current subtask ends the
   search (the pilot flies that goal), except in a search that a stall started, until the
   vehicle is ``backout_m`` from where it stalled or its first leg is over
   (:meth:`Search.may_hand_back`): the model's goals led into the dead end. A goal within
   ``dead_end_radius_m`` of a place where the vehicle stalled on the current subtask is no
   goal at all (the pilot's ``goal_dead_spot`` event). A STOP from the monitor pauses it (the vehicle hovers
   while the STOP is confirmed) and a withdrawn STOP resumes it where it was; a LOST while
   searching, with no sighting to turn back to, does not interrupt it (the search is already
   the recovery).
5. **One engine**: while searching the monitoring agent runs every ``monitor_period_s`` (6 s,
   not the pilot's 2 s): on one inference engine each monitoring call delays the next
   decision, and the decision stream is the one that finds the target.

Candidate exploration points are sampled on a ring of headings at a few ranges around the
vehicle at its altitude; a candidate is *reachable* when the straight segment to it keeps the
planner's clearance in the distance field (the planner's guide search handles the rest), and
its *gain* is the unknown fraction of a fan of sample points beyond it in its direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Callable

import numpy as np

from planning.frames import wrap_angle
from planning.volume import FlightVolume

__all__ = [
    "SearchConfig",
    "SearchConfigError",
    "SearchPhase",
    "SearchTrigger",
    "Search",
    "at_dead_end",
    "leg_end_held",
    "best_look_target",
    "explore_target",
    "frontier_target",
    "known_mask",
    "look_target",
    "open_heading",
    "open_ray_target",
    "seen_obstacle_in_column",
    "seen_obstacle_near",
    "side_opening",
    "side_to_look",
    "opening_gain",
    "unknown_fraction",
]


#: a camera within this of a leg's bearing faces the leg, radians (half a 90 deg field of view)
_FACING_RAD = math.pi / 4

#: how exploration legs are chosen (:class:`SearchConfig`.explore_policy)
EXPLORE_POLICIES = ("frontier", "open_ray")


class SearchConfigError(ValueError):
    """Invalid search configuration (names the field)."""


@dataclass(frozen=True)
class SearchConfig:
    """Parameters of the pilot's search (module docstring).

    Attributes
    ----------
    enabled : False = the paper's pilot (ablation ``onfly_no_search``)
    not_visible_streak : "target not visible" answers in a row that start a search
    fail_streak : decisions in a row without a goal that start a search, not counting those
        the verifier rejected (not visible, unparseable; failed calls do not count)
    reject_streak : decisions in a row without a goal, rejections included, that start a
        search (a target the verifier keeps rejecting is usually in view and close, where the
        monitor's STOP should come first)
    scan_step_rad : yaw increment of the scan, radians (a quarter turn: one camera width)
    scan_total_rad : how far one scan turns before exploring, radians. Three quarter turns:
        the view at the start of the scan is the one that just failed to show the target, and
        a 90 deg camera turning at the paper's 0.4 rad/s sees the rest in about 12 s
    scan_yaw_tolerance_rad : a scan heading counts as reached within this
    scan_dwell_s : time held at each scan heading, seconds (decisions also run on the frames
        taken while turning: at 0.4 rad/s and 2 Hz frames the view moves 11.5 deg a frame)
    explore_ranges_m : distances of the candidate exploration points, metres
    explore_headings : number of candidate headings on the ring
    explore_clearance_m : clearance the way to a frontier or ring leg's end, and a line of
        sight's run, must keep, metres: the default planner's guide clearance (``d_safe_m`` 0.45
        plus ``guide_clearance_margin_m`` 0.1). With less, a leg can end in a pocket of the map
        that the guide search cannot enter, and the vehicle hovers there until it stalls
    explore_arrive_m : an exploration point is reached within this, metres
    explore_timeout_s : give up on one exploration point after this long, seconds
    visit_radius_m : a candidate this close to a visited place is penalized, metres
    visit_spacing_m : the vehicle's track is remembered every this many metres
    stall_window_s, stall_distance_m : less travel than this in that window is a dead end
    gain_lookahead_m : how far beyond a candidate the gain fan reaches, metres
    forward_weight : how much a leg's value depends on its direction, in [0, 1]: the value (the
        gain plus a small bonus for length) is scaled by ``1 - w + w (1 + cos d) / 2``, ``d``
        the angle to the heading the search keeps (so ``1 - w`` of it straight behind)
    side_gain_min : after a leg, look a quarter turn to the side whose opening measure
        (:func:`opening_gain`) is at least this (the camera faced forward all the leg; a target
        beside the way is missed otherwise)
    min_leg_m : frontiers nearer than this (path metres) are taken only when no farther one is
        reachable, and a leg shorter than this ends without a side look: short hops spend the
        time on turning, not on seeing new space
    scan_gain_min : a scan turns to a heading only when the unknown fraction of its fan (see
        :func:`unknown_fraction`) is at least this: a sector the camera has already seen from
        here was already shown to the decision agent (0 = every heading; the heading toward the
        last sighting is always turned to)
    weave_rad : amplitude of the yaw weave on exploration legs, radians: the camera swings this
        far either side of the leg's bearing (a triangle wave, so the turn rate is constant), and
        a 90 deg camera sweeps 90 deg + twice this of the way past it; targets beside the route
        come into view without stopping to look. 0 = face the way of travel. The bearing itself
        stays inside the camera's field of view as long as this is below half of it, so the
        vehicle never flies into space its camera does not see. Off by default: with 0.6 rad,
        one of the 69 hard-set episodes once ended on a column (``parking_garage-o06``,
        clearance 0.24 m on a 1.9 m leg beside it; 0.40 m without the weave); at ``219fba4`` it
        collides nowhere but gains nothing either (53.6 against 55.1 % SR, docs/hard_tasks.md)
    weave_period_s : period of the weave, seconds (a sweep of ``4 weave_rad`` per period: 0.3
        rad/s at the defaults, inside the paper's 0.4 rad/s yaw rate)
    cruise_z_m : altitude of exploration legs, metres (world ENU z); None = the altitude the
        task began at. A search at the height of the last low goal sees less over furniture
        and machines than one at flight height
    monitor_period_s : the monitoring agent's period while searching, seconds (the pilot's
        ``monitor_period_s`` otherwise). On one inference engine every monitoring call delays
        the next decision by its latency; while the target is not found, the decision stream is
        the one that finds it (and ends the search), and the monitor has nothing to stop at
    explore_policy : how legs are chosen: ``"frontier"`` (the reachable place next to the most
        promising frontier group, :func:`frontier_target`) or ``"open_ray"`` (down the longest
        line of sight through seen free space, :func:`open_ray_target`, the frontier choice
        when no ray is long enough); the ring of straight legs when neither finds a leg
    open_ray_max_m : the longest leg down a line of sight, metres
    look_hints : follow the point where the model would look for a target it cannot see (step
        3b of the module docstring); False = only the map chooses legs
    compass : read a compass heading in the current subtask (``fly east along the parked
        cars``, ``follow the hallway west``; :func:`vlm.compass.compass_heading`) as the way the
        search keeps (step 3e). Needs a world frame whose +y is north (ENU: the embedded world,
        onboard flight with a compass); False where the frame is arbitrary (a SLAM frame)
    look_cone_rad : half-width of the cone of headings around the look point's heading in which
        :func:`look_target` seeks the longest free run, radians (a doorway 1 m wide 4 m away
        spans 14 deg; the model's point carries a few pixels of noise)
    look_clearance_m : clearance the way to a look leg's end must keep in the map, metres
        (below the planner's: from a few metres away a doorway's frame is partly unseen, and
        unseen space is an obstacle, so a door the vehicle will fly through reads narrower than
        it is; the planner keeps its own clearance on the way, and a way that stays too narrow
        ends the leg as a stall)
    look_min_leg_m : the shortest leg toward a look point, metres. Shorter than ``min_leg_m``:
        the leg is re-aimed on every answer, so a short one grows as the camera sees further
        (outdoors, open sky clears only a few metres of the map at flight height)
    look_max_age_s : a look point older than this does not choose a new leg, seconds (on one
        inference engine a decomposition or monitoring call can hold the next decision ~3 s;
        the look's heading is in the world frame, so it stays meaningful while the vehicle
        flies a few metres)
    scan_first_search : the episode's first search, when a "not visible" answer about a
        subtask starts it (before any other search of the episode), scans all round before any
        leg, even when the answer carries a look point; later searches go straight on a look leg. The start view is a quarter of the horizon and the
        heading a vehicle starts with says nothing of where the target is, so the first turn
        looks at the other three quarters (about 12 s at the paper's 0.4 rad/s) before flying
        away from a target beside or behind the start. Measured at one code version, simulated
        VLM ``nominal``, realism ``ideal``, 1 run per task, on versus off: the paper's 150 80.7
        against 72.0 % SR (goal out of view at the start 72.7 against 33.3 %, in view 82.9 each);
        the hard set 34.8 against 46.4 % (out of view 25.5 against 39.2 %): its way on lies
        ahead (the first 3 m of the reference path within 45 deg of the start heading in 93 % of
        its tasks, 80 % of the 150's), its rooms hold look-alikes that the turn shows the
        decision agent (``parking_garage-p07`` stopped at a second level sign behind the start),
        and at 0.6 m/s the 12 s of turning is a sixth of the 70 s limit. With the look legs,
        glances and dead-end rules since, the hard set turned round: at ``219fba4`` it scores
        55.1 % SR with the scan and 47.8 % without (out of view 45.1 against 35.3 %)
    seen_place : a LOST that names the image which last showed the target (monitor prompt
        ``monitor/v3``, ``LOST keyframe 2``) is used: with no sighting of the decision agent to
        turn back to, the LOST recovery turns to that frame's heading, and a search turns the
        camera back to it (a short look, once per named frame, unless the camera already
        faces it) before it goes on, so the decision agent sees again what the frame showed.
        A frame names a direction within the camera's field of view, not a place: legs flown
        toward it were measured and lost more than they won (``docs/hard_tasks.md``). False =
        the place is ignored (the paper's recovery: the last normal point's heading)
    leg_blocked_s : a leg ends when the planner has held its end back at the vehicle, or has
        failed to plan with the vehicle at rest, this long, seconds (:meth:`Search.leg_blocked`)
    backout_m : a search that a stall started hands control back to the model's goals only once
        the vehicle is this far (horizontally) from where it stalled, or its first leg is over,
        metres (:meth:`Search.may_hand_back`): the model's goals led into the dead end, and
        from the same view they lead back into it (a wall filling the frame, the history point
        it is shown); a new view is worth asking first
    dead_end_radius_m : a place the pilot could not get on from, metres: a leg's end that the
        leg did not reach (blocked, or the vehicle stalled on it) is not chosen again within
        this (:meth:`Search.dead_ends`), and a decision goal within this of where the vehicle
        stalled is no goal for the rest of the subtask (the pilot's rule): hovering there did
        not finish it, and the model's point from a view of a wall (the history point it is
        shown, the deepest pixel of a frame that is all wall) would hand a stall's search
        straight back to the same hover
    glance : on a leg, look into an opening the vehicle passes (step 3c of the module
        docstring); False = look aside only after a leg
    glance_reach_m : how far the rays that look for an opening beside the leg reach, metres
    glance_open_within_m : a ray is an opening when the first space it meets that is not seen
        free is unseen (not a seen obstacle) and lies within this, metres: a doorway beside the
        vehicle, not the unseen side of a wall it passes
    glance_gain_min : the fan's opening measure (the mean over its rays of the unseen fraction
        of an opening ray, 0 for a blocked one) that makes a side worth a glance, in (0, 1]
    glance_spacing_m : no second glance within this of the last one, metres (one per doorway)
    glance_dwell_s : time held facing the opening, seconds: long enough for one decision on a
        frame that shows it (2 Hz frames, a 0.8 s decision call)
    look_visited_max : a leg whose end has this much of the track near it (see
        :func:`explore_target`'s visit measure: about one remembered point right there) is not
        taken: the model looks the way it came from
    """

    enabled: bool = True
    not_visible_streak: int = 2
    fail_streak: int = 4
    reject_streak: int = 10
    scan_step_rad: float = math.pi / 2
    scan_total_rad: float = 1.5 * math.pi
    scan_yaw_tolerance_rad: float = 0.15
    scan_dwell_s: float = 0.5
    explore_ranges_m: tuple[float, ...] = (2.0, 3.5, 5.0)
    explore_headings: int = 16
    explore_clearance_m: float = 0.55
    explore_arrive_m: float = 0.8
    explore_timeout_s: float = 15.0
    visit_radius_m: float = 1.5
    visit_spacing_m: float = 1.0
    stall_window_s: float = 12.0
    stall_distance_m: float = 0.6
    gain_lookahead_m: float = 4.0
    forward_weight: float = 0.8
    side_gain_min: float = 0.25
    min_leg_m: float = 2.5
    scan_gain_min: float = 0.3
    weave_rad: float = 0.0
    weave_period_s: float = 8.0
    cruise_z_m: float | None = None
    monitor_period_s: float = 6.0
    explore_policy: str = "frontier"
    open_ray_max_m: float = 6.0
    look_hints: bool = True
    compass: bool = True
    look_cone_rad: float = math.radians(20.0)
    look_clearance_m: float = 0.3
    look_min_leg_m: float = 1.5
    look_max_age_s: float = 5.0
    look_visited_max: float = 1.0
    scan_first_search: bool = True
    seen_place: bool = True
    leg_blocked_s: float = 2.0
    dead_end_radius_m: float = 1.0
    backout_m: float = 2.0
    glance: bool = True
    glance_reach_m: float = 4.0
    glance_open_within_m: float = 2.5
    glance_gain_min: float = 0.4
    glance_spacing_m: float = 2.0
    glance_dwell_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("not_visible_streak", "fail_streak", "reject_streak", "explore_headings"):
            if int(getattr(self, name)) < 1:
                raise SearchConfigError(f"SearchConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in (
            "min_leg_m",
            "scan_step_rad",
            "scan_total_rad",
            "scan_yaw_tolerance_rad",
            "explore_arrive_m",
            "explore_timeout_s",
            "visit_radius_m",
            "visit_spacing_m",
            "stall_window_s",
            "stall_distance_m",
            "gain_lookahead_m",
            "weave_period_s",
            "monitor_period_s",
            "open_ray_max_m",
            "look_min_leg_m",
            "look_max_age_s",
            "look_visited_max",
            "glance_reach_m",
            "leg_blocked_s",
            "dead_end_radius_m",
            "backout_m",
            "glance_open_within_m",
            "glance_spacing_m",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise SearchConfigError(f"SearchConfig.{name} must be positive, got {v}")
        if not (np.isfinite(self.scan_dwell_s) and self.scan_dwell_s >= 0):
            raise SearchConfigError(f"SearchConfig.scan_dwell_s must be >= 0, got {self.scan_dwell_s}")
        if not (np.isfinite(self.weave_rad) and 0.0 <= self.weave_rad < math.pi / 4):
            raise SearchConfigError(f"SearchConfig.weave_rad must be in [0, pi/4), got {self.weave_rad}")
        if self.cruise_z_m is not None and not np.isfinite(self.cruise_z_m):
            raise SearchConfigError(f"SearchConfig.cruise_z_m must be finite or None, got {self.cruise_z_m}")
        if not (np.isfinite(self.look_clearance_m) and self.look_clearance_m >= 0):
            raise SearchConfigError(f"SearchConfig.look_clearance_m must be >= 0, got {self.look_clearance_m}")
        if not (np.isfinite(self.look_cone_rad) and 0.0 <= self.look_cone_rad <= math.pi / 2):
            raise SearchConfigError(f"SearchConfig.look_cone_rad must be in [0, pi/2], got {self.look_cone_rad}")
        if self.explore_policy not in EXPLORE_POLICIES:
            raise SearchConfigError(f"SearchConfig.explore_policy must be one of {EXPLORE_POLICIES}, got {self.explore_policy!r}")
        if not (0.0 <= self.scan_gain_min <= 1.0):
            raise SearchConfigError(f"SearchConfig.scan_gain_min must be in [0, 1], got {self.scan_gain_min}")
        if not (0.0 < self.glance_gain_min <= 1.0):
            raise SearchConfigError(f"SearchConfig.glance_gain_min must be in (0, 1], got {self.glance_gain_min}")
        if not (np.isfinite(self.glance_dwell_s) and self.glance_dwell_s >= 0):
            raise SearchConfigError(f"SearchConfig.glance_dwell_s must be >= 0, got {self.glance_dwell_s}")
        if not (0.0 <= self.side_gain_min <= 1.0):
            raise SearchConfigError(f"SearchConfig.side_gain_min must be in [0, 1], got {self.side_gain_min}")
        if not (0.0 <= self.forward_weight <= 1.0):
            raise SearchConfigError(f"SearchConfig.forward_weight must be in [0, 1], got {self.forward_weight}")
        if not (np.isfinite(self.explore_clearance_m) and self.explore_clearance_m >= 0):
            raise SearchConfigError(f"SearchConfig.explore_clearance_m must be >= 0, got {self.explore_clearance_m}")
        ranges = tuple(float(r) for r in self.explore_ranges_m)
        if not ranges or any(not (np.isfinite(r) and r > 0) for r in ranges):
            raise SearchConfigError(f"SearchConfig.explore_ranges_m must be positive numbers, got {self.explore_ranges_m!r}")
        object.__setattr__(self, "explore_ranges_m", ranges)


class SearchPhase(str, Enum):
    SCAN = "scan"
    EXPLORE = "explore"


class SearchTrigger(str, Enum):
    """Why a search started (logged with the ``search_start`` event)."""

    NOT_VISIBLE = "not_visible"
    NO_GOAL = "no_goal"
    LOST = "lost"
    STALL = "stall"


def known_mask(field_map, points: np.ndarray) -> np.ndarray:
    """True where the map has observed ``points`` (n, 3), metres, world ENU.

    Uses the map's public ``known(points)`` query when it has one; a distance field without
    knownness (an analytic field in tests) knows everything.
    """
    known = getattr(field_map, "known", None)
    if callable(known):
        return np.asarray(known(points), dtype=bool)
    return np.ones(len(points), dtype=bool)


def _direction_weight(bearing: float, yaw: float | None, forward_weight: float) -> float:
    """The factor on a leg's value for its direction ``bearing`` (radians) against the heading
    to keep ``yaw``: ``1 - w + w (1 + cos d) / 2`` (1 straight on ... ``1 - w`` straight behind),
    1 for every direction when there is no heading to keep (None)."""
    if yaw is None:
        return 1.0
    return (1.0 - forward_weight) + forward_weight * 0.5 * (1.0 + float(np.cos(wrap_angle(bearing - yaw))))


def _visited_near(visited: np.ndarray, point: np.ndarray, radius_m: float) -> float:
    """How visited the place ``point`` is: the sum over remembered track points (k, 3) of
    ``max(0, 1 - d / radius_m)``, ``d`` the horizontal distance (0 with no track)."""
    vis = np.asarray(visited, dtype=float).reshape(-1, 3)
    if not len(vis):
        return 0.0
    d = np.linalg.norm(vis[:, :2] - np.asarray(point, float)[None, :2], axis=1)
    return float(np.sum(np.clip(1.0 - d / radius_m, 0.0, 1.0)))


def at_dead_end(dead_ends: np.ndarray | None, point: np.ndarray, radius_m: float) -> bool:
    """True when ``point`` lies within ``radius_m`` (horizontally) of one of ``dead_ends``
    (k, 3): the ends of legs that could not be flown (:attr:`Search.dead_ends`), or the places
    where the vehicle stalled (the pilot's dead spots)."""
    if dead_ends is None:
        return False
    ends = np.asarray(dead_ends, dtype=float).reshape(-1, 3)
    if not len(ends):
        return False
    return bool(np.min(np.linalg.norm(ends[:, :2] - np.asarray(point, float)[None, :2], axis=1)) <= radius_m)


def leg_end_held(goal_used: np.ndarray, leg_end: np.ndarray, position: np.ndarray, arrive_m: float) -> bool:
    """True when the planner holds a leg's end back where the vehicle already is: the goal it
    planned to (``goal_used``, after its goal check) lies within ``arrive_m`` of ``position``
    while the leg's end (``leg_end``) is farther than ``arrive_m`` (not reached). Horizontal
    distances, metres, world frame. Any distance of the end counts: an end held back 1.1 m off,
    round a container's corner, left the vehicle hovering until the stall window ended."""
    p = np.asarray(position, float)[:2]
    return (
        float(np.linalg.norm(np.asarray(goal_used, float)[:2] - p)) <= arrive_m
        and float(np.linalg.norm(np.asarray(leg_end, float)[:2] - p)) > arrive_m
    )


def explore_target(
    position: np.ndarray,
    yaw: float | None,
    field_map,
    *,
    config: SearchConfig,
    volume: FlightVolume | None,
    volume_margin_m: float,
    visited: np.ndarray,
    z_m: float,
    dead_ends: np.ndarray | None = None,
    prefer_yaw: float | None = None,
) -> np.ndarray | None:
    """The next exploration point, or None when no candidate is reachable.

    Parameters
    ----------
    position : (3,) metres, world ENU, the vehicle now
    yaw : radians, the heading to keep going in (the direction of travel when the search
        began): a route usually goes on the way it was going, and a search that doubles back
        re-explores where the vehicle came from; None = no heading to keep (the vehicle was
        not under way: every direction is as good)
    field_map : the distance field (``query(points) -> (d, grad)``; ``known(points)`` if it has
        knownness, see :func:`known_mask`)
    volume : the operator flight volume or None; candidates and gain samples outside it are
        worthless
    visited : (k, 3) metres, places already visited (penalized within ``visit_radius_m``)
    z_m : altitude of the candidates, metres
    dead_ends : (k, 3) metres, ends of legs that could not be flown, or None: no candidate
        within ``dead_end_radius_m`` of one (the same for every target function here)
    prefer_yaw : heading where the target was last seen, radians, or None (a bonus toward it)

    Returns
    -------
    (3,) metres, world ENU, or None.
    """
    cfg = config
    p0 = np.array([position[0], position[1], z_m], dtype=float)
    headings = (yaw or 0.0) + np.linspace(0.0, 2 * np.pi, cfg.explore_headings, endpoint=False)
    best, best_score = None, -np.inf
    for th in headings:
        d = np.array([np.cos(th), np.sin(th), 0.0])
        for r in cfg.explore_ranges_m:
            cand = p0 + r * d
            if volume is not None and not bool(volume.contains(cand, margin_m=volume_margin_m)[0]):
                continue
            if at_dead_end(dead_ends, cand, cfg.dead_end_radius_m):
                continue
            seg = p0 + np.outer(np.arange(0.25, r + 1e-9, 0.25), d)
            dist, _ = field_map.query(seg)
            if np.min(dist) < cfg.explore_clearance_m or not bool(np.all(known_mask(field_map, seg[-1:]))):
                continue
            gain = unknown_fraction(cand, th, field_map, volume, cfg.gain_lookahead_m)
            # a longer leg is worth a little even into known space (progress along the route)
            value = gain + 0.1 * r / max(cfg.explore_ranges_m)
            score = value * _direction_weight(th, yaw, cfg.forward_weight)
            score -= 0.5 * _visited_near(visited, cand, cfg.visit_radius_m)
            if prefer_yaw is not None:
                score -= 0.3 * abs(wrap_angle(th - prefer_yaw)) / np.pi
            if score > best_score:
                best, best_score = cand, score
    return best


def open_ray_target(
    position: np.ndarray,
    yaw: float | None,
    field_map,
    *,
    config: SearchConfig,
    volume: FlightVolume | None,
    volume_margin_m: float,
    visited: np.ndarray,
    z_m: float,
    dead_ends: np.ndarray | None = None,
) -> np.ndarray | None:
    """Down the longest line of sight: the point on the horizontal ray (of
    ``explore_headings`` around the vehicle, at ``z_m``) that runs furthest through seen free
    space before it meets an obstacle or unknown space, or None when no ray runs
    ``min_leg_m``.

    A corridor, a hall or a doorway with open space behind it is a long free ray; a wall or a
    cluttered corner is a short one. The ray is scored by its free run (up to
    ``open_ray_max_m``), its direction (as in :func:`explore_target`) and the places already
    visited near its end; the point is ``leg_margin`` short of where the run ends, at most
    ``open_ray_max_m`` away. With a map that treats unknown space as occupied (the default),
    a ray ends where the camera stopped seeing, so its end is a frontier the camera looked
    down, not one beside it.
    """
    cfg = config
    p0 = np.array([position[0], position[1], z_m], dtype=float)
    headings = (yaw or 0.0) + np.linspace(0.0, 2 * np.pi, cfg.explore_headings, endpoint=False)
    runs, dirs = _free_runs(p0, headings, field_map, clearance_m=cfg.explore_clearance_m, max_m=cfg.open_ray_max_m,
                            volume=volume, volume_margin_m=volume_margin_m)
    best, best_score = None, -np.inf
    for k, th in enumerate(headings):
        reach = float(runs[k])
        if reach < cfg.min_leg_m:
            continue
        tgt = p0 + reach * dirs[k]
        if at_dead_end(dead_ends, tgt, cfg.dead_end_radius_m):
            continue
        score = (reach / cfg.open_ray_max_m) * _direction_weight(th, yaw, cfg.forward_weight)
        score -= 0.3 * _visited_near(visited, tgt, cfg.visit_radius_m)
        if score > best_score:
            best, best_score = tgt, score
    return best


def _free_runs(p0: np.ndarray, headings: np.ndarray, field_map, *, clearance_m: float, max_m: float,
               volume: FlightVolume | None, volume_margin_m: float, step_m: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """How far each horizontal ray from ``p0`` (3,) runs through seen free space that keeps
    ``clearance_m`` inside the volume, up to ``max_m``. Returns ``(reach (n,), dirs (n, 3))``:
    the run in metres, ``0.5`` m short of where it ends (the whole ``max_m`` when it never
    ends), and the unit directions."""
    steps = np.arange(step_m, max_m + 1e-9, step_m)
    dirs = np.stack([np.cos(headings), np.sin(headings), np.zeros_like(headings)], axis=-1)
    pts = (p0[None, None, :] + steps[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    dist, _ = field_map.query(pts)
    ok = (np.asarray(dist) >= clearance_m) & known_mask(field_map, pts)
    if volume is not None:
        ok &= volume.contains(pts, margin_m=volume_margin_m)
    blocked = ~ok.reshape(len(headings), len(steps))
    run = np.where(blocked.any(axis=1), np.argmax(blocked, axis=1), len(steps))
    reach = run * step_m - np.where(run < len(steps), 0.5, 0.0)
    return np.minimum(reach, max_m), dirs


def look_target(
    position: np.ndarray,
    look_yaw: float,
    field_map,
    *,
    config: SearchConfig,
    volume: FlightVolume | None,
    volume_margin_m: float,
    visited: np.ndarray,
    z_m: float,
    dead_ends: np.ndarray | None = None,
) -> np.ndarray | None:
    """A leg toward where the model would look (``look_yaw``, radians, world ENU: the look
    point's viewing ray), or None.

    With a map that has a horizontal distance layer (``distance_slice``, the ESDF): the place
    reached through the map's free layer (breadth-first, keeping ``explore_clearance_m``, as
    :func:`frontier_target`, but keeping ``look_clearance_m``) that lies furthest along the look ray, at most ``open_ray_max_m``
    along it, inside the cone of ``look_cone_rad`` about it and by a path at most twice its
    distance; so a doorway or a corridor seen at an angle is a leg even when no straight line
    through it keeps the clearance. Otherwise (an analytic field): the end of the longest
    straight free run (as in :func:`open_ray_target`) among headings in the cone. Either way a
    place counts less the further it turns from the ray (a quarter less at the cone's edge);
    None when nothing reaches ``look_min_leg_m`` along the ray or the best place is where the
    vehicle has been (``look_visited_max``).

    Returns (3,) metres, world ENU, at ``z_m``, or None.
    """
    cfg = config
    p0 = np.array([position[0], position[1], z_m], dtype=float)
    if callable(getattr(field_map, "distance_slice", None)):
        tgt = _look_through_reach(p0, look_yaw, field_map, cfg, volume, volume_margin_m)
    else:
        tgt = _look_along_rays(p0, look_yaw, field_map, cfg, volume, volume_margin_m)
    if tgt is None or _visited_near(visited, tgt, cfg.visit_radius_m) >= cfg.look_visited_max:
        return None
    if at_dead_end(dead_ends, tgt, cfg.dead_end_radius_m):
        return None
    return tgt


def best_look_target(
    position: np.ndarray,
    look_yaws,
    field_map,
    *,
    config: SearchConfig,
    volume: FlightVolume | None,
    volume_margin_m: float,
    visited: np.ndarray,
    z_m: float,
    dead_ends: np.ndarray | None = None,
    keep_yaw: float | None,
) -> np.ndarray | None:
    """After a scan, the leg toward the best of the look points the model gave from its headings
    (``look_yaws``, radians, world ENU), or None when none gives a leg (:func:`look_target`).

    Each leg is worth its length scaled by its direction against ``keep_yaw`` (as
    :func:`explore_target`'s legs, ``forward_weight``; every direction alike with None). The
    freshest look alone is the one from the heading the scan ended on, which says nothing of the
    other three quarters the model has just been shown.

    Returns (3,) metres, world ENU, at ``z_m``, or None.
    """
    best, best_score = None, -np.inf
    for yaw in look_yaws:
        tgt = look_target(position, float(yaw), field_map, config=config, volume=volume, volume_margin_m=volume_margin_m,
                          visited=visited, z_m=z_m, dead_ends=dead_ends)
        if tgt is None:
            continue
        d = tgt[:2] - np.asarray(position, float)[:2]
        score = float(np.hypot(*d)) * _direction_weight(float(np.arctan2(d[1], d[0])), keep_yaw, config.forward_weight)
        if score > best_score:
            best, best_score = tgt, score
    return best


def _look_through_reach(p0, look_yaw, field_map, cfg, volume, volume_margin_m) -> np.ndarray | None:
    """:func:`look_target` on the map's reachable free layer."""
    x, y, steps = _reach_grid(field_map, p0, cfg.look_clearance_m)
    ri, rj = np.nonzero(np.isfinite(steps))
    if not len(ri):
        return None
    d = np.stack([x[ri] - p0[0], y[rj] - p0[1]], axis=-1)
    u = np.array([np.cos(look_yaw), np.sin(look_yaw)])
    along = d @ u
    off = np.abs(np.arctan2(d[:, 0] * u[1] - d[:, 1] * u[0], along))
    path = steps[ri, rj]
    ok = (along >= cfg.look_min_leg_m) & (along <= cfg.open_ray_max_m) & (off <= cfg.look_cone_rad) & (path <= 2.0 * along)
    if volume is not None:
        pts = np.stack([x[ri], y[rj], np.full(len(ri), p0[2])], axis=-1)
        ok &= volume.contains(pts, margin_m=volume_margin_m)
    if not ok.any():
        return None
    score = np.where(ok, along * (1.0 - 0.25 * off / max(cfg.look_cone_rad, 1e-9)), -np.inf)
    k = int(np.argmax(score))
    return np.array([x[ri[k]], y[rj[k]], p0[2]])


def _look_along_rays(p0, look_yaw, field_map, cfg, volume, volume_margin_m) -> np.ndarray | None:
    """:func:`look_target` along straight rays (a field without a distance layer)."""
    n = max(1, int(round(cfg.look_cone_rad / math.radians(5.0))))
    offsets = np.linspace(-cfg.look_cone_rad, cfg.look_cone_rad, 2 * n + 1)
    reach, dirs = _free_runs(p0, look_yaw + offsets, field_map, clearance_m=cfg.look_clearance_m,
                             max_m=cfg.open_ray_max_m, volume=volume, volume_margin_m=volume_margin_m)
    weight = 1.0 - 0.25 * np.abs(offsets) / max(cfg.look_cone_rad, 1e-9)
    score = np.where(reach >= cfg.look_min_leg_m, reach * weight, -np.inf)
    k = int(np.argmax(score))
    if not np.isfinite(score[k]):
        return None
    return p0 + reach[k] * dirs[k]


def _reach_grid(field_map, p0: np.ndarray, clearance_m: float, stride: int = 2):
    """Breadth-first reach over the map's horizontal layer at the vehicle's height: cells (at
    ``stride`` voxels) whose distance keeps ``clearance_m``, 8-connected, from the vehicle's
    cell. Returns ``(x (nx,), y (ny,), steps (nx, ny) float, inf where unreachable)``, steps in
    metres of path."""
    from collections import deque

    sl = field_map.distance_slice(float(p0[2]))
    x, y = sl.x_m[::stride], sl.y_m[::stride]
    free = sl.distance_m[::stride, ::stride] >= clearance_m
    h = float(x[1] - x[0]) if len(x) > 1 else 1.0
    dist = np.full(free.shape, np.inf)
    i0, j0 = int(np.argmin(np.abs(x - p0[0]))), int(np.argmin(np.abs(y - p0[1])))
    free[i0, j0] = True  # the vehicle is where it is
    dist[i0, j0] = 0.0
    queue = deque([(i0, j0)])
    nbrs = [(1, 0, 1.0), (-1, 0, 1.0), (0, 1, 1.0), (0, -1, 1.0), (1, 1, 1.414), (1, -1, 1.414), (-1, 1, 1.414), (-1, -1, 1.414)]
    nx, ny = free.shape
    while queue:
        i, j = queue.popleft()
        d0 = dist[i, j]
        for di, dj, w in nbrs:
            a, b = i + di, j + dj
            if 0 <= a < nx and 0 <= b < ny and free[a, b] and dist[a, b] > d0 + w * h + 1e-9:
                dist[a, b] = d0 + w * h
                queue.append((a, b))
    return x, y, dist


def frontier_target(
    position: np.ndarray,
    yaw: float | None,
    field_map,
    *,
    config: SearchConfig,
    volume: FlightVolume | None,
    volume_margin_m: float,
    visited: np.ndarray,
    z_m: float,
    dead_ends: np.ndarray | None = None,
) -> np.ndarray | None:
    """The reachable place next to the most promising frontier of the map's known space, or None
    (no map with frontiers, none at this height, or none reachable).

    Frontier voxels (seen free, next to unknown beside them, not above or below;
    ``field_map.frontier_points(axes=(0, 1))``) within 0.6 m
    of the flight height are grouped in 1 m cells; a group is reached through the map's free
    layer at that height (breadth-first, keeping ``explore_clearance_m``), and scored by its
    size, its direction (as in :func:`explore_target`), its path length, and the places already
    visited. The target is the reachable cell nearest the group: the camera arrives facing the
    unknown beyond it (through a doorway, round a corner), which a straight ring of candidates
    cannot reach.
    """
    frontier = getattr(field_map, "frontier_points", None)
    if not callable(frontier) or not callable(getattr(field_map, "distance_slice", None)):
        return None
    cfg = config
    F = np.asarray(frontier(axes=(0, 1)), dtype=float).reshape(-1, 3)  # the ways on at a height
    F = F[np.abs(F[:, 2] - z_m) <= 0.6]
    if volume is not None and len(F):
        F = F[volume.contains(F, margin_m=volume_margin_m)]
    if not len(F):
        return None
    p0 = np.array([position[0], position[1], z_m], dtype=float)
    x, y, steps = _reach_grid(field_map, p0, cfg.explore_clearance_m)
    reach = np.isfinite(steps)
    if reach.sum() <= 1:
        return None
    ri, rj = np.nonzero(reach)
    cells = np.stack([x[ri], y[rj]], axis=-1)
    keys = np.floor(F[:, :2]).astype(np.int64)
    groups: dict[tuple[int, int], list[int]] = {}
    for k, key in enumerate(map(tuple, keys)):
        groups.setdefault(key, []).append(k)
    best, best_score = None, -np.inf
    best_near, best_near_score = None, -np.inf  # groups closer than a leg: only if none farther
    for members in groups.values():
        if len(members) < 3:  # a few voxels of noise, not a way on
            continue
        c = F[members, :2].mean(axis=0)
        near = np.linalg.norm(cells - c[None], axis=1)
        k = int(np.argmin(near))
        if near[k] > 1.0:
            continue  # nothing reachable next to it
        tgt = np.array([cells[k, 0], cells[k, 1], z_m])
        if at_dead_end(dead_ends, tgt, cfg.dead_end_radius_m):
            continue
        path_m = float(steps[ri[k], rj[k]])
        if path_m < 1.0:
            continue  # already here: the camera sees it from where it is
        bearing = float(np.arctan2(c[1] - p0[1], c[0] - p0[0]))
        size = min(len(members), 200) / 200.0  # a doorway's band of frontier: ~100-200 voxels
        score = (0.2 + size) * _direction_weight(bearing, yaw, cfg.forward_weight) / (1.0 + path_m / 8.0)
        score -= 0.3 * _visited_near(visited, tgt, cfg.visit_radius_m)
        if path_m < cfg.min_leg_m:
            if score > best_near_score:
                best_near, best_near_score = tgt, score
        elif score > best_score:
            best, best_score = tgt, score
    return best if best is not None else best_near


def unknown_fraction(p: np.ndarray, heading: float, field_map, volume: FlightVolume | None, reach_m: float) -> float:
    """Unknown fraction of a fan of points (+-30 deg, 1 m to ``reach_m`` metres) from ``p`` (3,)
    along ``heading`` (radians, world ENU), in [0, 1]; points outside the volume count as known
    (nothing to find there)."""
    fan = heading + np.deg2rad([-30.0, 0.0, 30.0])
    steps = np.linspace(1.0, reach_m, 4)
    dirs = np.stack([np.cos(fan), np.sin(fan), np.zeros(3)], axis=-1)
    pts = (p[None, None, :] + steps[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    useful = volume.contains(pts) if volume is not None else np.ones(len(pts), dtype=bool)
    return float(np.mean(~known_mask(field_map, pts) & useful))


def side_to_look(
    position: np.ndarray, yaw: float, field_map, *, config: SearchConfig, volume: FlightVolume | None
) -> float | None:
    """After an exploration leg (camera facing the way it flew): the side heading (yaw +- 90
    deg) that opens on the most unseen space (:func:`opening_gain`, as a glance judges it: the
    unseen side of a wall seen on the way in is nothing to look at), or None when neither
    side's measure reaches ``config.side_gain_min``."""
    return _most_open_side(position, yaw, field_map, config, volume, config.side_gain_min)


def opening_gain(p: np.ndarray, heading: float, field_map, *, config: SearchConfig, volume: FlightVolume | None) -> float:
    """How much unseen space an opening toward ``heading`` (radians, world ENU) shows from
    ``p`` (3,), in [0, 1]: the mean over a fan of horizontal rays (+-20 deg, 5 cm steps out to
    ``glance_reach_m``: half the map's 0.1 m voxel, so no ray steps over a wall's surface voxel
    into the unseen space behind it) of each ray's unseen fraction, counting a ray only when the first
    sample on it that is not seen free is unseen and within ``glance_open_within_m`` (a doorway
    or a gap in a row of shelves); a ray that meets a seen obstacle first, or leaves the flight
    volume, counts 0 (the unseen side of a wall is not an opening)."""
    cfg = config
    fan = heading + np.deg2rad([-20.0, -10.0, 0.0, 10.0, 20.0])
    steps = np.arange(0.5, cfg.glance_reach_m + 1e-9, 0.05)
    dirs = np.stack([np.cos(fan), np.sin(fan), np.zeros(len(fan))], axis=-1)
    pts = (np.asarray(p, float)[None, None, :] + steps[None, :, None] * dirs[:, None, :]).reshape(-1, 3)
    known = known_mask(field_map, pts).reshape(len(fan), len(steps))
    seen_free = getattr(field_map, "observed_free", None)
    free = (np.asarray(seen_free(pts), dtype=bool) if callable(seen_free) else np.ones(len(pts), dtype=bool)).reshape(known.shape)
    inside = (volume.contains(pts) if volume is not None else np.ones(len(pts), dtype=bool)).reshape(known.shape)
    gain = 0.0
    for k in range(len(fan)):
        not_free = np.nonzero(~(known[k] & free[k]) | ~inside[k])[0]
        if not len(not_free):
            continue  # seen free all the way: nothing hidden there
        j = int(not_free[0])
        if known[k, j] or not inside[k, j] or steps[j] > cfg.glance_open_within_m:
            continue  # a seen obstacle, the volume's edge, or unseen space only far beyond
        gain += float(np.mean(~known[k, j:] & inside[k, j:]))
    return gain / len(fan)


def side_opening(
    position: np.ndarray, bearing: float, field_map, *, config: SearchConfig, volume: FlightVolume | None
) -> float | None:
    """On a leg with ``bearing`` (radians): the side heading (``bearing +- 90 deg``) through which
    the vehicle passes an opening into unseen space (:func:`opening_gain` at least
    ``glance_gain_min``; the larger when both qualify), or None."""
    return _most_open_side(position, bearing, field_map, config, volume, config.glance_gain_min)


def _most_open_side(position, heading: float, field_map, config: SearchConfig, volume, min_gain: float) -> float | None:
    """Of ``heading +- 90 deg``, the side with the larger :func:`opening_gain`, if at least
    ``min_gain``; else None."""
    p = np.asarray(position, dtype=float)
    best, best_gain = None, min_gain
    for side in (heading + np.pi / 2, heading - np.pi / 2):
        g = opening_gain(p, side, field_map, config=config, volume=volume)
        if g >= best_gain:
            best, best_gain = float(wrap_angle(side)), g
    return best


_PROBES = np.array(
    [[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
     [0.7071, 0.7071, 0], [0.7071, -0.7071, 0], [-0.7071, 0.7071, 0], [-0.7071, -0.7071, 0]],
    dtype=float,
)


def _seen_occupied(field_map, points: np.ndarray) -> np.ndarray:
    """(n,) True where ``points`` (n, 3) lie in space the map has seen and not seen free: an
    observed obstacle (needs a map with ``observed_free``)."""
    return known_mask(field_map, points) & ~np.asarray(field_map.observed_free(points), dtype=bool)


def seen_obstacle_near(field_map, points: np.ndarray, clearance_m: float) -> np.ndarray:
    """True where an *observed* obstacle lies within ``clearance_m`` of ``points`` (n, 3)
    (probed at the point and at ``clearance_m`` along the axes and the horizontal diagonals).

    A map with knownness (``observed_free``) tells seen obstacles from unknown space: unknown
    is not a wall, it is where a search goes and what a landing first turns to look at. A field
    without knownness falls back to its distance.
    """
    if not callable(getattr(field_map, "observed_free", None)):
        dist, _ = field_map.query(points)
        return dist < clearance_m
    offsets = clearance_m * _PROBES
    probe = (points[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    return _seen_occupied(field_map, probe).reshape(len(points), -1).any(axis=1)


def seen_obstacle_in_column(field_map, xy: np.ndarray, z_lo_m: float, z_hi_m: float, radius_m: float) -> np.ndarray:
    """(k,) True where an *observed* obstacle lies within ``radius_m`` of the vertical segment
    over each ``xy`` (k, 2), metres, world ENU, from height ``z_lo_m`` to ``z_hi_m``, at or above
    its foot (the ground under a landing site is not beside its column).

    Every voxel of that cylinder and of its top cap is probed: a lattice at the map's voxel
    spacing (``voxel_m``, else 0.1 m) holds a point in each voxel that lies wholly inside. A few
    probes would not do: a camera sees an obstacle's surface only (a parked car is one voxel
    of seen wall around unknown space), and a wall between the probes goes unseen. A field
    without knownness (``observed_free``) falls back to its distance along the segment.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    step = float(getattr(field_map, "voxel_m", 0.1))
    if not callable(getattr(field_map, "observed_free", None)):
        zs = np.linspace(z_lo_m, z_hi_m, max(1, int(np.ceil((z_hi_m - z_lo_m) / step - 1e-9))) + 1)
        axis = np.column_stack([np.repeat(xy, len(zs), axis=0), np.tile(zs, len(xy))])
        dist, _ = field_map.query(axis)
        return (dist < radius_m).reshape(len(xy), -1).any(axis=1)
    top = z_hi_m + radius_m
    zs = np.linspace(z_lo_m, top, max(1, int(np.ceil((top - z_lo_m) / step - 1e-9))) + 1)
    n = int(np.floor(radius_m / step + 1e-9))
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    disc = step * np.column_stack([i.ravel(), j.ravel()])
    rho = np.hypot(disc[:, 0], disc[:, 1])
    layers = []
    for z in zs:  # the cylinder, then the top cap's shrinking discs
        r_z = radius_m if z <= z_hi_m else np.sqrt(max(radius_m**2 - (z - z_hi_m) ** 2, 0.0))
        d = disc[rho <= r_z + 1e-9]
        layers.append(np.column_stack([d, np.full(len(d), z)]))
    offsets = np.concatenate(layers)  # (m, 3), z absolute
    blocked = np.zeros(len(xy), dtype=bool)
    per_chunk = max(1, 200_000 // len(offsets))  # bounds the probe arrays (a few MB)
    for start in range(0, len(xy), per_chunk):
        c = xy[start : start + per_chunk]
        probe = np.repeat(np.column_stack([c, np.zeros(len(c))]), len(offsets), axis=0) + np.tile(offsets, (len(c), 1))
        blocked[start : start + len(c)] = _seen_occupied(field_map, probe).reshape(len(c), -1).any(axis=1)
    return blocked


def open_heading(position: np.ndarray, yaw: float, field_map, *, clearance_m: float, min_free_m: float = 2.5) -> float:
    """The heading a search should keep going in: ``yaw`` when the way on is open, else the
    opposite (a dead end: back out). Unknown space counts as open (the route goes on past what
    is in front).

    Open: within 45 deg of ``yaw``, a place ``min_free_m`` to ``min_free_m + 1`` m away that the
    vehicle reaches keeping ``clearance_m``, by a path at most half again as long as the straight
    line (breadth-first over the map's layer at its height, :func:`_reach_grid`). A doorway the
    vehicle came up to obliquely is such a way on, though no straight ray through it keeps the
    clearance (the hard set's ``apartment-l01``: 30 deg off the heading, the jamb straight
    ahead). A map without a distance slice: straight on or 45 deg either side, a ray with no
    seen obstacle within ``clearance_m`` for ``min_free_m``.
    """
    p = np.asarray(position, dtype=float)
    back = float(wrap_angle(yaw + np.pi))
    if callable(getattr(field_map, "distance_slice", None)):
        x, y, steps = _reach_grid(field_map, p, clearance_m)
        X, Y = np.meshgrid(x - p[0], y - p[1], indexing="ij")
        r = np.hypot(X, Y)
        off = np.abs(wrap_angle(np.arctan2(Y, X) - yaw))
        way_on = (r >= min_free_m) & (r <= min_free_m + 1.0) & (off <= np.pi / 4) & (steps <= 1.5 * r)
        return float(yaw) if bool(np.any(way_on)) else back
    steps_m = np.arange(0.25, min_free_m + 1e-9, 0.25)
    for off in (0.0, np.pi / 4, -np.pi / 4):
        d = np.array([np.cos(yaw + off), np.sin(yaw + off), 0.0])
        if not bool(np.any(seen_obstacle_near(field_map, p + np.outer(steps_m, d), clearance_m))):
            return float(yaw)
    return back


@dataclass
class Search:
    """The search's state between ticks (owned by the pilot; one per episode).

    ``start`` begins a scan; :meth:`control` gives the pilot, each tick, the point to hold or
    fly to and the yaw reference; ``stop`` ends it. Pure bookkeeping: the pilot owns the map,
    the planner and the mode.
    """

    config: SearchConfig
    phase: SearchPhase | None = None
    trigger: SearchTrigger | None = None
    started_s: float = 0.0
    searches: int = 0
    heading0: float | None = None
    leg_kind: str | None = None  # how the current leg was chosen ("look", "frontier", ...)
    yaw0: float | None = None  # the camera's heading when this search began, radians
    _scan_yaws: list[float] = field(default_factory=list)
    _scan_reached_s: float | None = None
    _hold_p: np.ndarray | None = None
    _explore_p: np.ndarray | None = None
    _leg_start: np.ndarray | None = None
    _leg_bearing: float | None = None  # heading from the leg's start to its first end, radians
    _explore_start_s: float = 0.0
    _visited: list[np.ndarray] = field(default_factory=list)
    _track: list[tuple[float, np.ndarray]] = field(default_factory=list)
    _dwell_s: float | None = None  # this scan's dwell (None: ``scan_dwell_s``)
    _resume: tuple | None = None  # the leg a glance interrupted: (end, start, bearing, kind, t_s)
    _glanced: list[np.ndarray] = field(default_factory=list)  # where glances were taken
    _dead_ends: list[np.ndarray] = field(default_factory=list)  # ends of legs that could not be flown
    _start_p: np.ndarray | None = None  # where this search began
    _backed_out: bool = True  # a stall's search has taken the vehicle out of the dead end
    _blocked_since_s: float | None = None  # since when the planner holds the leg's end back
    _leg_over: bool = False  # the leg ends at the next tick (its end cannot be approached)
    _glance_window: tuple[float, float] = (np.inf, -np.inf)  # the last glance, (began, ended) seconds
    _last_tick_s: float = -np.inf  # the time of the last :meth:`control` call

    @property
    def active(self) -> bool:
        return self.phase is not None

    @property
    def visited(self) -> np.ndarray:
        return np.asarray(self._visited, dtype=float).reshape(-1, 3)

    @property
    def dead_ends(self) -> np.ndarray:
        """(k, 3) metres, world ENU: the ends of the episode's legs that could not be flown (the
        planner held the end back or could not plan toward it, or the vehicle stalled on the
        leg). No later leg ends within ``dead_end_radius_m`` of one: a stall's search would
        otherwise choose the same leg again from the same place (the map and the model's view
        have not changed), and hover on it to the next stall."""
        return np.asarray(self._dead_ends, dtype=float).reshape(-1, 3)

    def may_hand_back(self, position: np.ndarray) -> bool:
        """Whether a verified goal from the model may end this search now: always, unless a
        stall started it and the vehicle is still within ``backout_m`` of where it stalled
        with its first leg not over (see :class:`SearchConfig`)."""
        if not self._backed_out and self._start_p is not None:
            away = float(np.linalg.norm(np.asarray(position, float)[:2] - self._start_p[:2]))
            self._backed_out = away >= self.config.backout_m
        return self._backed_out

    def leg_failed(self) -> None:
        """The current leg could not be flown: remember its end (:attr:`dead_ends`)."""
        if self.phase is SearchPhase.EXPLORE and self._explore_p is not None:
            self._dead_ends.append(np.asarray(self._explore_p, dtype=float).copy())

    def remember(self, t_s: float, position: np.ndarray) -> None:
        """Record the vehicle's track (visited places and the stall window)."""
        p = np.asarray(position, dtype=float).copy()
        if not self._visited or np.linalg.norm(self._visited[-1][:2] - p[:2]) >= self.config.visit_spacing_m:
            self._visited.append(p)
        self._track.append((float(t_s), p))
        horizon = float(t_s) - self.config.stall_window_s - 1.0
        while len(self._track) > 2 and self._track[1][0] < horizon:
            self._track.pop(0)

    def stalled(self, t_s: float) -> bool:
        """True when the vehicle moved less than ``stall_distance_m`` over the last
        ``stall_window_s`` (the track must span the whole window)."""
        if not self._track or t_s - self._track[0][0] < self.config.stall_window_s:
            return False
        recent = np.array([p for (ts, p) in self._track if ts >= t_s - self.config.stall_window_s])
        if len(recent) < 2:
            return False
        return float(np.max(np.linalg.norm(recent - recent[-1], axis=1))) < self.config.stall_distance_m

    def travel_heading(self, t_s: float, window_s: float = 6.0, min_travel_m: float = 1.0) -> float | None:
        """Heading of the horizontal displacement over the last ``window_s`` (radians), or None
        when the vehicle moved less than ``min_travel_m``."""
        recent = [p for (ts, p) in self._track if ts >= t_s - window_s]
        if len(recent) < 2:
            return None
        d = recent[-1][:2] - recent[0][:2]
        return float(np.arctan2(d[1], d[0])) if float(np.hypot(*d)) >= min_travel_m else None

    def reset_stall(self) -> None:
        """Forget the stall window (after a state change that legitimately holds position)."""
        self._track = self._track[-1:]

    def start(
        self,
        t_s: float,
        position: np.ndarray,
        yaw: float,
        trigger: SearchTrigger,
        toward_yaw: float | None = None,
        total_rad: float | None = None,
        worth_scanning: Callable[[float], bool] | None = None,
    ) -> None:
        """Begin with a scan: first toward ``toward_yaw`` when given, then on through
        ``total_rad`` (default ``scan_total_rad``) in steps of ``scan_step_rad``. Without a
        preferred heading, successive scans alternate their direction. ``worth_scanning(yaw)``
        drops headings not worth turning to (the toward heading is always kept); with none
        left the scan is over at once (the pilot explores)."""
        if self.phase is None:
            self.yaw0 = float(yaw)
            self.heading0 = float(yaw)  # the direction of travel when this search began (the
            # pilot replaces it with its reverse in a dead end, see ``open_heading``)
        self.phase = SearchPhase.SCAN
        self.leg_kind = None
        self._resume = None
        self._dwell_s = None
        self.trigger = trigger
        self._end_glance_window()
        self.started_s = float(t_s)
        self._start_p = np.asarray(position, dtype=float).copy()
        self._backed_out = trigger is not SearchTrigger.STALL
        self.searches += 1
        self._hold_p = np.asarray(position, dtype=float).copy()
        self._scan_reached_s = None
        step = self.config.scan_step_rad
        total = self.config.scan_total_rad if total_rad is None else float(total_rad)
        n = max(1, int(np.ceil(total / step - 1e-9)))
        if toward_yaw is not None:
            sign = 1.0 if wrap_angle(toward_yaw - yaw) >= 0 else -1.0
            base = float(toward_yaw)
            yaws = [base] + [float(wrap_angle(base + sign * step * (k + 1))) for k in range(n - 1)]
        else:
            sign = 1.0 if self.searches % 2 == 1 else -1.0
            yaws = [float(wrap_angle(yaw + sign * step * (k + 1))) for k in range(n)]
        if worth_scanning is not None:
            yaws = [y for k, y in enumerate(yaws) if (k == 0 and toward_yaw is not None) or worth_scanning(y)]
        self._scan_yaws = yaws

    def leg_length_m(self, position: np.ndarray) -> float:
        """Horizontal distance from where the current exploration leg began, metres."""
        if self._leg_start is None:
            return 0.0
        return float(np.linalg.norm(np.asarray(position, float)[:2] - self._leg_start[:2]))

    def look(self, t_s: float, position: np.ndarray, yaws: list[float]) -> None:
        """A short scan of the given headings from ``position`` (then ``"scan_done"``)."""
        self.phase = SearchPhase.SCAN
        self.leg_kind = None
        self._resume = None
        self._dwell_s = None
        self._end_glance_window()
        self._hold_p = np.asarray(position, dtype=float).copy()
        self._scan_reached_s = None
        self._scan_yaws = [float(y) for y in yaws]

    @property
    def leg_end(self) -> np.ndarray | None:
        """Where the current exploration leg goes (3,), or None."""
        return self._explore_p

    @property
    def glancing(self) -> bool:
        """True while a glance holds the leg it interrupted."""
        return self._resume is not None

    def _end_glance_window(self) -> None:
        """The leg a glance interrupted is over: its window ends at the last tick (else a leg
        that ended before the camera faced it again would leave the window open for good)."""
        if self._glance_window[1] == np.inf:
            self._glance_window = (self._glance_window[0], self._last_tick_s)

    def during_glance(self, t_s: float) -> bool:
        """True if ``t_s`` (a frame's capture time) falls in the last glance, from its start
        until the camera faces the leg again (within 45 deg of the bearing to its end): the
        camera faced the side, so what the model says of those frames is no guide to where the
        leg goes."""
        return self._glance_window[0] <= t_s <= self._glance_window[1]

    def may_glance(self, position: np.ndarray) -> bool:
        """True on an exploration leg, with glances on, farther than ``glance_spacing_m`` from
        the last glance, at least ``glance_open_within_m`` from where the leg began (the camera,
        facing the way of travel, has not yet seen the walls beside the start: unseen, they
        would read as openings; and a leg mostly begins where the vehicle has just looked
        round) and more than a leg's arrival radius plus a metre from its end (where the look
        after the leg takes over)."""
        cfg = self.config
        if not cfg.glance or self.phase is not SearchPhase.EXPLORE or self._explore_p is None:
            return False
        p = np.asarray(position, dtype=float)
        if float(np.linalg.norm(self._explore_p[:2] - p[:2])) <= cfg.explore_arrive_m + 1.0:
            return False
        if self.leg_length_m(p) < cfg.glance_open_within_m:
            return False
        return not self._glanced or float(np.linalg.norm(self._glanced[-1][:2] - p[:2])) > cfg.glance_spacing_m

    def glance(self, t_s: float, position: np.ndarray, yaw: float) -> None:
        """Interrupt the leg: hold at ``position``, face ``yaw`` for ``glance_dwell_s``, then go
        on with the same leg (its timeout paused meanwhile)."""
        self._resume = (self._explore_p, self._leg_start, self._leg_bearing, self.leg_kind, float(t_s))
        self._glance_window = (float(t_s), np.inf)
        self._glanced.append(np.asarray(position, dtype=float).copy())
        self.phase = SearchPhase.SCAN
        self._hold_p = np.asarray(position, dtype=float).copy()
        self._scan_reached_s = None
        self._scan_yaws = [float(yaw)]
        self._dwell_s = self.config.glance_dwell_s

    def leg_blocked(self, t_s: float, blocked: bool) -> bool:
        """Report, each tick of a leg, whether the leg cannot be flown from here: the planner
        holds its end back at the vehicle (its goal check moved an end behind a wall or inside
        an obstacle's clearance to the nearest feasible point, and that point is where the
        vehicle already is), or it finds no safe plan toward it while the vehicle is at rest.
        After ``leg_blocked_s`` of it the leg ends (the next :meth:`control` says
        ``"explore_done"``), its end is a dead end (:attr:`dead_ends`) and True is returned
        once: the vehicle would otherwise hover there until the stall window ends."""
        if not blocked or self.phase is not SearchPhase.EXPLORE:
            self._blocked_since_s = None
            return False
        if self._blocked_since_s is None:
            self._blocked_since_s = float(t_s)
        if self._leg_over or t_s - self._blocked_since_s < self.config.leg_blocked_s:
            return False
        self.leg_failed()
        self._leg_over = True
        return True

    def _weave_yaw(self, t_s: float, to_go: np.ndarray) -> float | None:
        """Yaw reference on a leg: the bearing to the exploration point plus a triangle wave of
        amplitude ``weave_rad`` (starting at 0, first to the left); None (face the way of
        travel) without a weave or in the last ``2 weave_rad / yaw rate`` of the leg, roughly
        1.5 m, where the camera should face what the vehicle arrives at."""
        cfg = self.config
        if cfg.weave_rad <= 0.0 or float(np.hypot(*to_go)) < 1.5:
            return None
        phase = ((t_s - self._explore_start_s) / cfg.weave_period_s) % 1.0  # 0 ... 1
        tri = 4.0 * phase if phase < 0.25 else (2.0 - 4.0 * phase if phase < 0.75 else 4.0 * phase - 4.0)
        return float(wrap_angle(np.arctan2(to_go[1], to_go[0]) + cfg.weave_rad * tri))

    def stop(self) -> None:
        self.phase = None
        self.trigger = None
        self.leg_kind = None
        self._resume = None
        self._dwell_s = None
        self._end_glance_window()
        self._scan_yaws = []
        self._explore_p = None
        self.reset_stall()

    def explore_from(
        self, t_s: float, target: np.ndarray | None, position: np.ndarray, yaw: float, kind: str = "frontier"
    ) -> None:
        """Switch to exploring toward ``target`` (None: nothing reachable, scan again);
        ``kind`` says how the leg was chosen."""
        if target is None:
            self.leg_kind = None
            self.start(t_s, position, float(yaw), self.trigger or SearchTrigger.NO_GOAL)
            return
        self.phase = SearchPhase.EXPLORE
        self.leg_kind = kind
        self._resume = None
        self._dwell_s = None
        self._end_glance_window()
        self._blocked_since_s = None
        self._leg_over = False
        self._leg_start = np.asarray(position, dtype=float).copy()
        self._explore_p = np.asarray(target, dtype=float).copy()
        to = self._explore_p[:2] - self._leg_start[:2]
        self._leg_bearing = float(np.arctan2(to[1], to[0]))
        self._explore_start_s = float(t_s)
        self.reset_stall()  # the scan held position on purpose

    def reaim(self, t_s: float, target: np.ndarray) -> bool:
        """Move the current leg's end to ``target`` (a fresher look point), keeping where the leg
        began; the leg's timeout counts from now. A target whose bearing from where the leg began
        turns more than twice ``look_cone_rad`` from the leg's first bearing is not taken
        (False): each new view has a deepest direction of its own, and following them one after
        another walks the leg round in a circle (back to the start, seen in the hard set's
        ``apartment-o07``)."""
        if self._leg_start is not None and self._leg_bearing is not None:
            d1 = np.asarray(target, float)[:2] - self._leg_start[:2]
            turn = abs(wrap_angle(np.arctan2(d1[1], d1[0]) - self._leg_bearing))
            if turn > 2.0 * self.config.look_cone_rad:
                return False  # a re-aim sharpens the way the leg goes, it does not turn it round
        self._explore_p = np.asarray(target, dtype=float).copy()
        self._explore_start_s = float(t_s)
        return True

    def control(self, t_s: float, position: np.ndarray, yaw: float) -> tuple[np.ndarray, float | None, str | None]:
        """Where to be and where to look this tick.

        Returns ``(point (3,), yaw_ref or None, event)``: the point to hold (scan) or fly to
        (explore); the yaw reference (None: face the direction of travel); ``event`` is
        ``"scan_done"`` when the scan finished (the pilot picks an exploration point),
        ``"explore_done"`` when the exploration point was reached or timed out, else None.
        """
        cfg = self.config
        self._last_tick_s = float(t_s)
        if self.phase is SearchPhase.SCAN:
            while self._scan_yaws:
                target = self._scan_yaws[0]
                if abs(wrap_angle(yaw - target)) > cfg.scan_yaw_tolerance_rad:
                    self._scan_reached_s = None
                    return self._hold_p, target, None
                if self._scan_reached_s is None:
                    self._scan_reached_s = float(t_s)
                dwell = cfg.scan_dwell_s if self._dwell_s is None else self._dwell_s
                if t_s - self._scan_reached_s < dwell:
                    return self._hold_p, target, None
                self._scan_yaws.pop(0)
                self._scan_reached_s = None
            if self._resume is not None:  # a glance is over: back on the leg it interrupted
                end, start, bearing, kind, t0 = self._resume
                self._resume = None
                self._dwell_s = None
                self.phase = SearchPhase.EXPLORE
                self._explore_p, self._leg_start, self._leg_bearing, self.leg_kind = end, start, bearing, kind
                self._explore_start_s += float(t_s) - t0
                self._glance_window = (t0, np.inf)  # closed when the camera faces the leg again
                self.reset_stall()
                return self.control(t_s, position, yaw)
            return self._hold_p, None, "scan_done"
        if self.phase is SearchPhase.EXPLORE and self._explore_p is not None:
            to_go = self._explore_p[:2] - np.asarray(position, float)[:2]
            if self._glance_window[1] == np.inf and abs(wrap_angle(yaw - np.arctan2(to_go[1], to_go[0]))) <= _FACING_RAD:
                self._glance_window = (self._glance_window[0], float(t_s))
            near = float(np.hypot(*to_go)) <= cfg.explore_arrive_m
            if near or self._leg_over or t_s - self._explore_start_s > cfg.explore_timeout_s:
                self._backed_out = True
                return np.asarray(position, float).copy(), None, "explore_done"
            return self._explore_p, self._weave_yaw(t_s, to_go), None
        return np.asarray(position, float).copy(), None, None
