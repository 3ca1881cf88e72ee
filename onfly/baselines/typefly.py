"""TypeFly-style baseline: an LLM writes skill programs over an object detector's output.

After TypeFly (Chen et al. 2023): the language model never sees coordinates it must compute;
it reads a *scene description* from an object detector (names and boxes) and writes a short
program in a small skill language, which a runtime executes with the detector in the loop.
When the program ends (or a skill fails) the model is asked again with the new scene
description and the log of executed skills. There is no map and no planner: motions are
straight lines under the common dynamic limits. The only way the episode ends by the method is
the ``stop`` skill (the stop interface the OnFly paper added to TypeFly).

Skill language (one to :data:`MAX_SKILLS` skills separated by ``;``)::

    find <object>         turn left in 45-degree steps until the detector reports <object>
                          (a phrase matched by SimulatedDetector.matching), at most 8 turns
    approach <object>     yaw to the detected box centre and fly approach_step_m along its ray
    turn <degrees>        turn in place, positive = left (counter-clockwise)
    move_forward <metres> fly straight ahead along the current heading (0 < m <= max_move_m)
    stop                  end the task here

A program that does not parse is logged and the model is asked again on the next frame; the
vehicle hovers while the model thinks.
"""

from __future__ import annotations

import logging
import math
import re
from collections import Counter
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from onfly.baselines.common import (
    BaselineOptionError,
    CallOutcome,
    FlightLimits,
    PlanMemory,
    Arrival,
    ray_world,
    split_options,
    straight_plan,
    vlm_image,
    yaw_settled,
)
from onfly.baselines.detector import Detection, DetectorConfig, SimulatedDetector
from onfly.bench.method import EpisodeSpec, MethodStep
from onfly.observation import Observation
from planning.frames import wrap_angle
from planning.trajectory import VehicleState
from vlm.factory import make_backend
from vlm.prompts import SceneObject, build_typefly_prompt
from vlm.types import CallStatus, VlmBackend

__all__ = ["TypeflyConfig", "TypeflyMethod", "Skill", "ProgramError", "parse_program", "make_typefly", "MAX_SKILLS"]

log = logging.getLogger(__name__)

MAX_SKILLS = 5
PLAN = "typefly_plan"
FIND_STEP_RAD = math.radians(45.0)
FIND_TURNS = 8


class ProgramError(ValueError):
    """A skill program that does not parse (the message names the bad skill)."""


@dataclass(frozen=True)
class TypeflyConfig:
    """TypeFly baseline parameters.

    approach_step_m : length of one ``approach`` move, metres
    max_move_m : the longest ``move_forward`` accepted, metres
    skill_timeout_s : a move or turn that has not finished after this long is abandoned
    history_items : how many executed skills the prompt shows (latest)
    detector : DetectorConfig fields as a table
    """

    approach_step_m: float = 3.0
    max_move_m: float = 5.0
    skill_timeout_s: float = 20.0
    history_items: int = 6
    detector: dict | None = None

    def __post_init__(self) -> None:
        for name in ("approach_step_m", "max_move_m", "skill_timeout_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise BaselineOptionError(f"TypeflyConfig.{name} must be a finite number > 0, got {v!r}")
        if isinstance(self.history_items, bool) or not isinstance(self.history_items, int) or self.history_items < 0:
            raise BaselineOptionError(f"TypeflyConfig.history_items must be an int >= 0, got {self.history_items!r}")
        if self.detector is not None and not isinstance(self.detector, dict):
            raise BaselineOptionError(f"TypeflyConfig.detector must be a table of DetectorConfig fields, got {self.detector!r}")

    def detector_config(self) -> DetectorConfig:
        data = dict(self.detector or {})
        valid = {f.name for f in fields(DetectorConfig)}
        bad = sorted(set(data) - valid)
        if bad:
            raise BaselineOptionError(f"unknown detector option(s) {bad}; valid: {sorted(valid)}")
        return DetectorConfig(**data)


@dataclass(frozen=True)
class Skill:
    """One parsed skill: ``name`` in find / approach / turn / move_forward / stop; ``arg`` is
    the object phrase (str), degrees or metres (float), or None for stop."""

    name: str
    arg: str | float | None = None

    def text(self) -> str:
        if self.arg is None:
            return self.name
        return f"{self.name} {self.arg:g}" if isinstance(self.arg, float) else f"{self.name} {self.arg}"


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_SKILL_RES = (
    ("find", re.compile(r"find\s+(.+)", re.IGNORECASE)),
    ("approach", re.compile(r"approach\s+(.+)", re.IGNORECASE)),
    ("turn", re.compile(rf"turn\s+({_NUM})", re.IGNORECASE)),
    ("move_forward", re.compile(rf"move_forward\s+({_NUM})", re.IGNORECASE)),
    ("stop", re.compile(r"stop", re.IGNORECASE)),
)


def parse_program(text: str, *, max_move_m: float = 5.0) -> list[Skill]:
    """Parse a skill program (module docstring); raises :class:`ProgramError`.

    Whitespace, a trailing ``;`` and a code fence around the program are tolerated; any
    unknown skill, missing argument, turn outside [-360, 360] degrees or move outside
    (0, ``max_move_m``] metres rejects the whole program.
    """
    if not isinstance(text, str):
        raise ProgramError(f"program must be a str, got {type(text).__name__}")
    body = text.strip().strip("`").strip()
    if body.lower().startswith("program:"):
        body = body[len("program:") :]
    parts = [p.strip() for p in body.replace("\n", ";").split(";")]
    parts = [p for p in parts if p]
    if not parts:
        raise ProgramError("empty program")
    if len(parts) > MAX_SKILLS:
        raise ProgramError(f"{len(parts)} skills, more than {MAX_SKILLS}")
    skills = []
    for part in parts:
        for name, rx in _SKILL_RES:
            m = rx.fullmatch(part)
            if m is None:
                continue
            if name in ("find", "approach"):
                skills.append(Skill(name, " ".join(m.group(1).split())))
            elif name == "turn":
                deg = float(m.group(1))
                if not -360.0 <= deg <= 360.0:
                    raise ProgramError(f"turn {deg:g}: outside [-360, 360] degrees")
                skills.append(Skill(name, deg))
            elif name == "move_forward":
                dist = float(m.group(1))
                if not 0.0 < dist <= max_move_m:
                    raise ProgramError(f"move_forward {dist:g}: outside (0, {max_move_m:g}] metres")
                skills.append(Skill(name, dist))
            else:
                skills.append(Skill("stop"))
            break
        else:
            raise ProgramError(f"unknown skill {part!r}")
    return skills


def scene_description(detections: list[Detection], width: int, height: int) -> list[SceneObject]:
    """Detections as the prompt's scene description (fractions of the image)."""
    out = []
    for d in detections:
        u0, v0, u1, v1 = d.box_px
        clip = lambda x: float(min(max(x, 0.0), 1.0))  # noqa: E731
        name = " ".join(re.sub(r"[^A-Za-z0-9 '/.-]", " ", d.name).split()) or "object"
        label = " ".join(re.sub(r"[^A-Za-z0-9 '/.-]", " ", d.label).split()) or "object"
        out.append(SceneObject(name, label, clip((u0 + u1) / 2 / width), clip((v0 + v1) / 2 / height),
                               clip((u1 - u0 + 1) / width), clip((v1 - v0 + 1) / height)))  # fmt: skip
    return out


class TypeflyMethod:
    """The TypeFly-style baseline (module docstring).

    Parameters
    ----------
    vlm_spec : backend spec (``sim:nominal`` ...), the same VLM as every method
    config : TypeflyConfig
    limits : FlightLimits (the shared planner table's limits)
    backend : a VLM backend to use instead of building one from ``vlm_spec`` per episode
    """

    name = "typefly"
    privileged = False

    def __init__(self, vlm_spec: str, config: TypeflyConfig, limits: FlightLimits, backend: VlmBackend | None = None) -> None:
        self.vlm_spec = vlm_spec
        self._backend = backend
        self.config = config
        self.limits = limits
        self._detector_config = config.detector_config()

    # -- lifecycle --------------------------------------------------------------------------------
    def reset(self, spec: EpisodeSpec) -> None:
        self.plans = PlanMemory()  # straight-line plans start from the last one's reference
        self.spec = spec
        self.backend = self._backend if self._backend is not None else make_backend(self.vlm_spec, seed=spec.seed)
        self.runtime = spec.runtime
        self.detector = SimulatedDetector(self._detector_config, seed=spec.seed)
        self.latest: Observation | None = None
        self.queue: list[Skill] = []
        self.active: _Active | None = None
        self.history: list[str] = []
        self.hold_p = spec.start_state.p.copy()
        self.hold_yaw = float(spec.start_state.yaw)
        self._planned_frame: str | None = None
        self.stats: Counter = Counter()
        self.programs: list[str] = []

    def _log(self, item: str) -> None:
        """Append ``"<skill> <arg>: <outcome>"`` to the skill log and count ``<skill>:<outcome>``."""
        self.history.append(item)
        head, _, outcome = item.partition(": ")
        self.stats[f"{head.split(' ')[0]}:{outcome}" if outcome else head] += 1

    # -- the loop ---------------------------------------------------------------------------------
    def step(self, t_s: float, state: VehicleState, obs: Observation | None) -> MethodStep:
        if obs is not None:
            self.latest = obs
        for landed in self.runtime.poll():
            self._on_plan(landed.outcome)
        if self.active is None and self.queue:
            skill = self.queue.pop(0)
            if skill.name == "stop":
                self._log("stop")
                return MethodStep(None, True, {"skill": "stop"})
            self.active = self._start(skill, t_s, state)
        if self.active is not None:
            traj = self._run(t_s, state)
            if traj is not None:
                return MethodStep(traj, False, {"skill": self.active.skill.text() if self.active else None})
        # no skill running: hover where we are, ask for a program on a new frame
        idle = not self.queue and not self.runtime.busy(PLAN)
        if idle and self.latest is not None and self.latest.frame_id != self._planned_frame:
            self._plan(self.latest)
        return MethodStep(straight_plan(state, self.hold_p, self.limits, yaw_ref=self.hold_yaw, memory=self.plans), False)

    def _plan(self, obs: Observation) -> None:
        self._planned_frame = obs.frame_id
        dets = self.detector.detect(obs.annotation, obs.frame_id) if obs.annotation is not None else []
        h, w = obs.depth_m.shape
        objects = scene_description(dets, w, h)
        items = self.history[-self.config.history_items :] if self.config.history_items else []
        messages, images = build_typefly_prompt(self.spec.instruction, vlm_image(obs), objects, items)
        backend = self.backend
        self.stats["plans"] += 1

        def call() -> CallOutcome:
            return CallOutcome(PLAN, obs.frame_id, backend.complete(messages, images, max_new_tokens=64))

        self.runtime.submit(PLAN, call)

    def _on_plan(self, out) -> None:
        if not isinstance(out, CallOutcome):
            log.error("TypeFly plan call raised: %r", out)
            self.stats["plan_errors"] += 1
            return
        if out.response.status is not CallStatus.OK:
            self.stats["plan_failures"] += 1
            return
        try:
            skills = parse_program(out.response.text, max_move_m=self.config.max_move_m)
        except ProgramError as exc:
            log.info("TypeFly program rejected (%s): %r", exc, out.response.text[:120])
            self.stats["program_rejected"] += 1
            return
        self.programs.append("; ".join(s.text() for s in skills))
        self.queue = skills

    # -- skills -----------------------------------------------------------------------------------
    def _start(self, skill: Skill, t_s: float, state: VehicleState) -> "_Active | None":
        if skill.name == "turn":
            return _Active(skill, t_s, yaw=float(state.yaw + math.radians(float(skill.arg))), p=state.p.copy())
        if skill.name == "move_forward":
            d = float(skill.arg)
            goal = state.p + d * np.array([math.cos(state.yaw), math.sin(state.yaw), 0.0])
            return _Active(skill, t_s, p=goal)
        if skill.name == "find":
            return _Active(skill, t_s, p=state.p.copy(), yaw=float(state.yaw), turns=0, check_after_s=t_s)
        # approach: the latest frame's detection of the object, or fail
        obs = self.latest
        dets = self.detector.detect(obs.annotation, obs.frame_id) if obs is not None and obs.annotation is not None else []
        found = SimulatedDetector.matching(str(skill.arg), dets)
        if not found:
            self._log(f"approach {skill.arg}: not detected")
            self.queue = []  # a failed skill ends the program: ask again
            return None
        ray = ray_world(obs, found[0].center_uv)
        goal = state.p + self.config.approach_step_m * ray
        return _Active(skill, t_s, p=goal)

    def _run(self, t_s: float, state: VehicleState):
        a = self.active
        timed_out = t_s - a.t0_s > self.config.skill_timeout_s
        if a.skill.name == "turn":
            if yaw_settled(state, a.yaw) or timed_out:
                return self._finish(f"turn {a.skill.arg:g}: done", state)
            return straight_plan(state, a.p, self.limits, yaw_ref=a.yaw, memory=self.plans)
        if a.skill.name in ("move_forward", "approach"):
            if a.arrival(t_s, state, a.p, self.plans.last) or timed_out:
                return self._finish(f"{a.skill.text()}: done", state)
            return straight_plan(state, a.p, self.limits, yaw_first=True, memory=self.plans)
        # find: after each settled turn, look at a frame taken after it settled
        if yaw_settled(state, a.yaw) or timed_out:
            if a.check_after_s is None:
                a.check_after_s = t_s
            obs = self.latest
            if obs is not None and obs.t_s >= a.check_after_s - 1e-9:
                dets = self.detector.detect(obs.annotation, obs.frame_id) if obs.annotation is not None else []
                if SimulatedDetector.matching(str(a.skill.arg), dets):
                    return self._finish(f"find {a.skill.arg}: found", state)
                if a.turns >= FIND_TURNS - 1:
                    self.queue = []
                    return self._finish(f"find {a.skill.arg}: not found", state)
                a.turns += 1
                a.yaw = float(wrap_angle(a.yaw + FIND_STEP_RAD))
                a.t0_s = t_s
                a.check_after_s = None
        return straight_plan(state, a.p, self.limits, yaw_ref=a.yaw, memory=self.plans)

    def _finish(self, item: str, state: VehicleState):
        self._log(item)
        self.active = None
        self.hold_p = state.p.copy()
        self.hold_yaw = float(state.yaw)
        return None

    def summary(self) -> dict[str, Any]:
        return {
            "plans": int(self.stats.get("plans", 0)),
            "program_rejected": int(self.stats.get("program_rejected", 0)),
            "plan_failures": int(self.stats.get("plan_failures", 0)),
            "skills": {k: int(v) for k, v in self.stats.items() if k not in ("plans", "program_rejected", "plan_failures", "plan_errors")},
            "last_programs": self.programs[-5:],
            "history_tail": self.history[-8:],
        }


@dataclass
class _Active:
    """The skill being executed and its progress (mutable, internal)."""

    skill: Skill
    t0_s: float
    p: np.ndarray | None = None
    yaw: float = 0.0
    turns: int = 0
    check_after_s: float | None = None
    arrival: Arrival = field(default_factory=Arrival)


def make_typefly(vlm_spec: str, seed: int, **options) -> TypeflyMethod:
    """Registry factory. Options: the shared ``planner`` table (limits), ``esdf`` / ``verifier``
    (accepted, unused: no map) and :class:`TypeflyConfig` fields (``detector`` as a table)."""
    planner, _, cfg = split_options(options, TypeflyConfig, "typefly")
    cfg.detector_config()  # validate now, not at the first episode
    return TypeflyMethod(vlm_spec, cfg, FlightLimits.from_planner(planner))
