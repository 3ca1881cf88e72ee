"""Following a moving person: the pilot's follow mode (ours; the paper flies it, issue 19).

A subtask *follows* when :func:`vlm.following.follow_intent` says so ("follow the person in the
red jacket", "stay behind the man with the cart until he stops, then stop next to him"). The
decision agent and the verifier work as for a static goal: each decision points at the person,
the verifier accepts or rejects the pixel, and the history point is the last goal reprojected.
What changes (:class:`Follower`):

- **the goal is the person**: an accepted decision's pointed point
  (:attr:`onfly.agents.DecisionOutcome.target_world`, the person's pixel lifted at its depth)
  is a *sighting* at the frame's capture time. The decision agent's goal (what the history
  point reprojects, what LOST recovery turns toward) is the person predicted to the time the
  answer lands, from a constant-velocity fit over the sightings of the last ``window_s``;
- **the vehicle flies to a standoff, not onto the person**: every control period the planner's
  goal is the point ``standoff_m`` from the person (predicted ``lead_s`` ahead, which covers
  the decision latency) on the line toward the vehicle, at the altitude the vehicle had when
  the following began, and the yaw
  reference faces the person, so the camera keeps them in view even while the vehicle backs
  away from a person walking toward it;
- **LOST**: the recovery turns toward where the person is predicted to be now, not where
  they were last seen;
- **STOP**: a following subtask without an end ignores the monitor's STOP (being near the
  person is not completion); one that follows *until the person stops* takes it as usual.

A sighting farther from the prediction than ``jump_slack_m + max_speed_change_mps * dt``
(``dt`` since the last sighting: a walker changes speed and heading gradually) is dropped (a
look-alike the model confused, a pixel on the background); two such in a row that agree with
each other (within the same reach) restart the track from the newest one (the person really
is there). The planner keeps its clearance from every person,
the followed one included: they are in the ESDF like any obstacle, and the standoff goal is
``standoff_m`` from them.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from vlm.following import FollowIntent, follow_intent

__all__ = ["FollowConfig", "FollowConfigError", "Follower"]

log = logging.getLogger(__name__)


class FollowConfigError(ValueError):
    """An invalid follow-mode parameter (names the field)."""


@dataclass(frozen=True)
class FollowConfig:
    """Parameters of the follow mode.

    enabled : False = a following subtask is flown like any other (goal on the person, every
        STOP heard)
    standoff_m : horizontal distance kept from the followed person, metres (the middle of the
        1.5-4.0 m band our tracking tasks ask for; the paper's real-world tracking flight gives
        no number)
    lead_s : the person is predicted this far ahead of now for the standoff goal, seconds
        (about one decision latency, 0.81 s on the paper's Orin NX, plus half a frame period)
    window_s : sightings older than this are not used for the velocity fit, seconds (decisions
        land about every 2.5 s when they share the accelerator with the monitor: two to three
        sightings)
    max_speed_mps : the velocity estimate is capped at this, m/s. Fast walking is about 2 m/s
        (Bohannon 1997, "Comfortable and maximum walking speed of adults aged 20-79 years",
        Age and Ageing 26(1): maximum gait speeds 1.75-2.53 m/s)
    max_speed_change_mps : how far the person may depart from the constant-velocity prediction
        per second since the last sighting (setting off from standing, turning), m/s
    jump_slack_m : position noise allowed on top of that, metres
    max_extrapolation_s : the prediction never runs further than this past the last sighting,
        seconds. Decisions land about every 2.5 s (they share the accelerator with the monitor);
        when the person is out of view (behind a kiosk) the vehicle keeps following where they
        are predicted to walk, which brings them back into view, until the pilot's goal timeout
        (8 s) hands over to its search
    """

    enabled: bool = True
    standoff_m: float = 2.75
    lead_s: float = 1.0
    window_s: float = 6.0
    max_speed_mps: float = 2.5
    max_speed_change_mps: float = 1.0
    jump_slack_m: float = 1.0
    max_extrapolation_s: float = 8.0

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name == "enabled":
                if not isinstance(self.enabled, bool):
                    raise FollowConfigError(f"FollowConfig.enabled must be true or false, got {self.enabled!r}")
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise FollowConfigError(f"FollowConfig.{f.name} must be a number >= 0, got {v!r}")
        if self.standoff_m <= 0 or self.window_s <= 0 or self.max_speed_mps <= 0:
            raise FollowConfigError("FollowConfig.standoff_m, window_s and max_speed_mps must be positive")


class Follower:
    """The follow mode's state: the followed person's sightings and the standoff goal.

    Times are seconds on the pilot's clock; positions (3,) metres, world ENU.
    """

    def __init__(self, config: FollowConfig | None = None) -> None:
        self.config = config if config is not None else FollowConfig()
        self._subtask: str | None = None
        self._intent: FollowIntent | None = None
        self._sightings: list[tuple[float, np.ndarray]] = []
        self._rejected: tuple[float, np.ndarray] | None = None
        self._z_m: float | None = None  # the following altitude (set on the first control)
        self.stops_ignored = 0
        self.sightings_dropped = 0

    # -- which subtask follows ---------------------------------------------------------------
    def intent(self, subtask: str | None) -> FollowIntent | None:
        """The following intent of ``subtask`` (None: not following, or the mode is off). A
        subtask that does not follow forgets the sightings."""
        if not self.config.enabled or subtask is None:
            return None
        if subtask != self._subtask:
            was = self._intent
            self._subtask = subtask
            self._intent = follow_intent(subtask)
            if self._intent is None or was is None:
                # the sightings of a following subtask carry over to the next following one (the
                # early decisions on the whole instruction, then its decomposition)
                self._sightings = []
                self._rejected = None
                self._z_m = None
        return self._intent

    @property
    def active(self) -> bool:
        """Following a subtask right now with at least one sighting."""
        return self._intent is not None and bool(self._sightings)

    def ignores_stop(self, subtask: str) -> bool:
        """A STOP on ``subtask`` that does not end it: it follows, and not until the person stops."""
        intent = self.intent(subtask)
        if intent is not None and not intent.until_stop:
            self.stops_ignored += 1
            return True
        return False

    # -- sightings and prediction --------------------------------------------------------------
    def sighting(self, t_s: float, position) -> bool:
        """Record the person at ``position`` (3,) seen at ``t_s``; False when dropped as a jump."""
        p = np.asarray(position, float).reshape(3)
        if not np.all(np.isfinite(p)):
            return False
        c = self.config
        if self._sightings:
            last_t = self._sightings[-1][0]
            pred = self.predict(t_s)
            reach = c.max_speed_change_mps * max(t_s - last_t, 0.0) + c.jump_slack_m
            if pred is not None and np.linalg.norm(p[:2] - pred[:2]) > reach:
                prev = self._rejected
                self._rejected = (float(t_s), p)
                self.sightings_dropped += 1
                agree = prev is not None and np.linalg.norm(p[:2] - prev[1][:2]) <= c.max_speed_change_mps * max(t_s - prev[0], 0.0) + c.jump_slack_m
                if not agree:
                    return False
                self._sightings = [prev]  # two in a row that agree: the person is there, restart the track
        self._rejected = None
        self._sightings.append((float(t_s), p))
        self._sightings = [(ts, q) for ts, q in self._sightings if ts >= t_s - 2 * c.window_s]
        return True

    def velocity(self) -> np.ndarray:
        """Horizontal velocity (3,) m/s (z = 0) of a least-squares line through the sightings of
        the last ``window_s`` (the last two within ``2 window_s`` when the window holds fewer);
        zeros with fewer than two sightings or no time spread."""
        if len(self._sightings) < 2:
            return np.zeros(3)
        t_last = self._sightings[-1][0]
        recent = [s for s in self._sightings if s[0] >= t_last - self.config.window_s]
        if len(recent) < 2:
            recent = self._sightings[-2:]
        t = np.array([s[0] for s in recent])
        P = np.array([s[1] for s in recent])
        dt = t - t.mean()
        den = float(np.sum(dt * dt))
        if den < 1e-6:
            return np.zeros(3)
        v = (dt[:, None] * (P - P.mean(axis=0))).sum(axis=0) / den
        v[2] = 0.0
        speed = float(np.linalg.norm(v))
        if speed > self.config.max_speed_mps:
            v *= self.config.max_speed_mps / speed
        return v

    def predict(self, t_s: float) -> np.ndarray | None:
        """The person's predicted position (3,) at ``t_s``, or None without a sighting."""
        if not self._sightings:
            return None
        t_last, p_last = self._sightings[-1]
        ahead = min(max(t_s - t_last, 0.0), self.config.max_extrapolation_s)
        return p_last + self.velocity() * ahead

    # -- the pilot's hooks -----------------------------------------------------------------------
    def on_decision(self, t_s: float, out: Any) -> Any:
        """An applied decision (:class:`onfly.agents.DecisionOutcome`) landing at ``t_s``: on a
        following subtask with a goal, record its sighting and return it with ``goal_world`` on
        the person predicted to ``t_s`` (unchanged otherwise)."""
        if self.intent(out.subtask) is None or out.goal_world is None:
            return out
        seen = out.target_world if out.target_world is not None else out.goal_world
        t_seen = out.frame_t_s if math.isfinite(out.frame_t_s) else t_s
        self.sighting(t_seen, seen)
        pred = self.predict(t_s)
        return out if pred is None else replace(out, goal_world=pred)

    def control(self, t_s: float, position, z_m: float) -> tuple[np.ndarray, float] | None:
        """The standoff goal (3,) and the yaw (radians) facing the person for this control
        period, or None when not following. ``position`` (3,): the vehicle; ``z_m``: its
        altitude floor now. The goal keeps the altitude the vehicle had when the following
        began (raised to ``z_m``): a goal at the current altitude would ratchet down with every
        dip the planner takes to keep its clearance."""
        if not self.active:
            return None
        c = self.config
        if self._z_m is None:
            self._z_m = float(np.asarray(position, float)[2])
        z_m = max(self._z_m, float(z_m))
        p = np.asarray(position, float)
        q = self.predict(t_s + c.lead_s)
        now = self.predict(t_s)
        away = p[:2] - q[:2]
        dist = float(np.hypot(*away))
        if dist < 1e-6:  # on top of the person: back off against their motion
            v = self.velocity()[:2]
            away = -v if np.linalg.norm(v) > 1e-6 else np.array([1.0, 0.0])
            dist = float(np.linalg.norm(away))
        goal = np.array([*(q[:2] + c.standoff_m * away / dist), float(z_m)])
        face = now[:2] - p[:2]
        yaw = float(np.arctan2(face[1], face[0])) if np.hypot(*face) > 1e-6 else float(np.arctan2(-away[1], -away[0]))
        return goal, yaw

    def where_now(self, t_s: float, fallback):
        """Where to look for the person now (LOST recovery): the prediction on a following
        subtask with sightings, else ``fallback`` (where the target was last pointed at)."""
        if not self.active:
            return fallback
        return self.predict(t_s)

    def summary(self) -> dict:
        return {"stops_ignored": self.stops_ignored, "sightings_dropped": self.sightings_dropped}
