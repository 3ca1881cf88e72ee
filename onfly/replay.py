"""Offline evaluation against logged depth: replay a recording open loop and report.

:func:`replay` runs every frame of an :class:`onfly.readers.ObservationSource` (an OnFly log, a
TUM RGB-D folder, a ROS 1/2 bag) through the same parts the pilot flies with, **open loop**:
the recorded camera does not respond to the plans, so what is measured is what each stage would
have computed on that footage, and how long it took.

Per processed frame (``ReplayConfig.every_n``):

1. **ESDF.** ``EsdfMap.integrate(depth, camera, T_world_cam, center_world=body position)``.
   Then the field is queried at the logged *camera* position: the **path clearance** of that
   frame. Its minimum over the log (``path_clearance_min_m``) > 0 says the logged camera was
   never inside an obstacle of the map built from the log's own depth, i.e. depth, poses and
   intrinsics agree with each other (a wrong depth scale, a pose in the wrong frame or a
   camera/body mix-up typically puts the path inside the walls). Values are clamped at
   ``EsdfConfig.max_distance_m`` (1.6 m by default). Under the default
   ``unknown_policy="occupied"`` space no frame saw counts as an obstacle too (the vehicle's
   body sphere, ``EsdfConfig.body_clear_radius_m``, is known free where the camera cannot
   see), so a clearance near that radius says "nothing seen nearer"; ``unknown_policy="free"`` counts only observed
   obstacles.
2. **Agents** (only with ``ReplayConfig.instruction``). The instruction is decomposed once
   (one VLM call, deterministic fallback splitter on failure); the monitoring memory observes
   every processed frame; the decision agent runs on every processed frame until the task
   manager reports the task finished, its pixel goes through the semantic-geometric verifier;
   the monitoring agent runs every ``monitor_period_s`` of log time and its statuses drive the
   task manager (stable STOP advances the subtask). Calls are blocking and land on the frame
   they were made on: open loop, no latency is charged to a clock (the latencies are reported
   instead).
3. **Planner.** ``Planner.step(state, goal, esdf)`` from the logged state: position and yaw of
   the logged body pose, velocity (and yaw rate) by backward finite differences of consecutive
   logged frames (zero at the first frame). The planner keeps its warm start between frames,
   as onboard. Goal per ``ReplayConfig.goal_mode``:

   - ``"future_pose"``: the logged body position ``future_pose_s`` later (linear interpolation
     between frames; the last logged position once the log ends sooner). Frames up to
     ``future_pose_s`` ahead are held in memory to know it.
   - ``"fixed"``: ``ReplayConfig.goal_world``, in the log's world frame.
   - ``"agents"``: the last goal the decision agent's verifier accepted (held until the next
     one, no timeout); before the first, the current position (hover).

VLM backends (``ReplayConfig.vlm``, a :func:`vlm.factory.make_backend` spec, plus ``tiny``):

- ``sim:<preset>``: the simulated VLM reads per-frame ground-truth annotations, which only
  OnFly logs recorded in the embedded world carry (``onfly run --log DIR``). Asking for it on a
  recording without annotations (TUM, bags, logs of real flights) is a :class:`ReplayError`.
- ``http:<url>[#model]`` / ``transformers:<dir>``: a real model, for real recordings.
- ``tiny`` / ``tiny:qwen2_5_vl`` / ``tiny:qwen3_vl``: a tiny random-weight Qwen model built
  offline into a temporary directory (:mod:`vlm.tiny_models`, ~10 s) and loaded in-process. Its
  answers are garbage, so it exercises the whole pipeline (prompts, parsing failures, memory,
  latency) but yields no meaningful goals.

VLM latencies are those the backend reports (:attr:`vlm.types.VlmResponse.latency_s`): measured
wall time for http / transformers, the *modelled* onboard latency for the simulated VLM
(``ReplayReport.vlm_latency`` says which). All other latencies are wall time on this machine.
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import numpy as np

from onfly.serialize import config_from_tables, to_jsonable
from onfly.agents import DecisionAgent, DecisionOutcome, MonitoringAgent, MonitorOutcome
from onfly.memory import MemoryConfig, make_memory
from onfly.observation import Observation
from onfly.readers.base import known_length
from onfly.task_manager import Status, TaskEvent, TaskManager
from planning.esdf import EsdfMap
from planning.esdf_config import EsdfConfig
from planning.frames import unwrap_near
from planning.movers import MoverConfig, MoverTracker
from planning.planner import Planner, PlanResult
from planning.planner_config import PlannerConfig
from planning.trajectory import VehicleState
from planning.verifier import CandidateGoal, VerifiedGoal, Verifier, VerifierConfig
from planning.volume import FlightVolume
from vlm.decompose import decompose_detailed
from vlm.feature_cache import FeatureCache
from vlm.parsing import CoordFormat
from vlm.types import VisionFeatures, VlmBackend, VlmImage

__all__ = [
    "GOAL_MODES",
    "STAGES",
    "ReplayConfig",
    "ReplayConfigError",
    "ReplayError",
    "StageLatency",
    "FrameResult",
    "DecisionRecord",
    "VerifierStats",
    "ReplayReport",
    "replay",
    "make_replay_backend",
]

log = logging.getLogger(__name__)

GOAL_MODES = ("future_pose", "fixed", "agents")
#: Latency stages, in pipeline order (a report holds those that ran).
STAGES = ("esdf", "planner", "features", "verifier", "decision_vlm", "monitoring_vlm")
TINY_PREFIX = "tiny"


class ReplayConfigError(ValueError):
    """An invalid :class:`ReplayConfig` field (the message names it)."""


class ReplayError(ValueError):
    """A replay that cannot run on this source (empty log, sim VLM without annotations, ...)."""


@dataclass(frozen=True)
class ReplayConfig:
    """Everything a replay does; nested configs are the ones the pilot flies with.

    Attributes
    ----------
    goal_mode : ``"future_pose"`` | ``"fixed"`` | ``"agents"`` (see the module docstring)
    future_pose_s : look-ahead of ``"future_pose"``, seconds of log time
    goal_world : (3,) goal in metres, the log's world frame; required by ``"fixed"`` only
    instruction : natural-language instruction; runs memory, agents and verifier when given
        (required by ``"agents"``)
    vlm : backend spec: ``sim:<preset>``, ``http:<url>[#model]``, ``transformers:<dir>``,
        ``tiny[:family]``
    seed : seed of the simulated VLM (real backends decode greedily)
    every_n : process every n-th frame of the source (others are read, used for velocity and
        the future pose, and skipped)
    max_frames : stop after this many processed frames (None: the whole source)
    monitor_period_s : monitoring-agent period, seconds of log time (paper: 2 s)
    stop_confirmations : consecutive STOPs that finish the last subtask
    intermediate_stop_confirmations : consecutive STOPs that advance past an earlier subtask
        (None = ``stop_confirmations``; the pilot's rule, :class:`onfly.pilot.PilotConfig`)
    coord_format : how the backend writes points (:class:`vlm.parsing.CoordFormat` value)
    vlm_deadline_s : per-call deadline handed to the backend (None: the backend's default)
    slack_tolerance_m : a planner step "needed slack" when its largest clearance slack exceeds
        this, metres (the QP's own tolerance leaves slacks of ~1e-4 m on clear steps)
    moved_min_px : a verified goal "moved" when its refined pixel is at least this far from the
        VLM's, pixels
    range_gated_below : a verified goal was "range-gated" when its gating factor is below this
        (default 0.95: range cut by more than 5 %)
    volume : the operator flight volume ``(xmin, ymin, zmin, xmax, ymax, zmax)``, metres in the
        log's world frame, or None; goals are clamped into it (shrunk by the planner's safety
        distance and drift margin, ``Planner.volume_goal_margin_m``) before the planner sees
        them, as in flight
    planner, esdf, verifier, memory : the nested configs
    movers : moving obstacles tracked from the logged depth, which the planner avoids besides
        the map (:mod:`planning.movers`), as in flight
    """

    goal_mode: str = "future_pose"
    future_pose_s: float = 3.0
    goal_world: tuple[float, float, float] | None = None
    instruction: str | None = None
    vlm: str = "sim:nominal"
    seed: int = 0
    every_n: int = 1
    max_frames: int | None = None
    monitor_period_s: float = 2.0
    stop_confirmations: int = 2
    intermediate_stop_confirmations: int | None = 1
    coord_format: str = CoordFormat.PIXEL.value
    vlm_deadline_s: float | None = None
    slack_tolerance_m: float = 1e-3
    moved_min_px: float = 0.5
    range_gated_below: float = 0.95
    volume: tuple[float, float, float, float, float, float] | None = None
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    esdf: EsdfConfig = field(default_factory=EsdfConfig)
    verifier: VerifierConfig = field(default_factory=VerifierConfig)
    memory: MemoryConfig = field(default_factory=MemoryConfig)
    movers: MoverConfig = field(default_factory=MoverConfig)

    @property
    def flight_volume(self) -> FlightVolume | None:
        """:attr:`volume` as a :class:`planning.volume.FlightVolume` (None when not set)."""
        return None if self.volume is None else FlightVolume(np.array(self.volume[:3]), np.array(self.volume[3:]))

    def __post_init__(self) -> None:
        if self.goal_mode not in GOAL_MODES:
            raise ReplayConfigError(f"ReplayConfig.goal_mode must be one of {GOAL_MODES}, got {self.goal_mode!r}")
        for name in ("future_pose_s", "monitor_period_s", "slack_tolerance_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ReplayConfigError(f"ReplayConfig.{name} must be a positive number, got {v!r}")
        if not (isinstance(self.moved_min_px, (int, float)) and math.isfinite(self.moved_min_px) and self.moved_min_px >= 0):
            raise ReplayConfigError(f"ReplayConfig.moved_min_px must be >= 0, got {self.moved_min_px!r}")
        if not (0 < self.range_gated_below <= 1):
            raise ReplayConfigError(f"ReplayConfig.range_gated_below must be in (0, 1], got {self.range_gated_below!r}")
        optional = tuple(n for n in ("max_frames", "intermediate_stop_confirmations") if getattr(self, n) is not None)
        for name in ("every_n", "stop_confirmations", "seed") + optional:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or (v < 1 and name != "seed"):
                raise ReplayConfigError(f"ReplayConfig.{name} must be an integer{' >= 1' if name != 'seed' else ''}, got {v!r}")
        if self.goal_world is not None:
            g = tuple(float(x) for x in np.asarray(self.goal_world, dtype=float).reshape(-1))
            if len(g) != 3 or not all(math.isfinite(x) for x in g):
                raise ReplayConfigError(f"ReplayConfig.goal_world must be three finite numbers (x, y, z), got {self.goal_world!r}")
            object.__setattr__(self, "goal_world", g)
        if self.volume is not None:
            try:
                box = FlightVolume.parse(",".join(str(float(x)) for x in self.volume))
            except (TypeError, ValueError) as exc:
                raise ReplayConfigError(f"ReplayConfig.volume: {exc}") from None
            object.__setattr__(self, "volume", tuple(box.to_list()))
        if self.goal_mode == "fixed" and self.goal_world is None:
            raise ReplayConfigError("ReplayConfig.goal_world is required when goal_mode is 'fixed'")
        if self.goal_mode != "fixed" and self.goal_world is not None:
            raise ReplayConfigError(f"ReplayConfig.goal_world is given but goal_mode is {self.goal_mode!r} (use 'fixed')")
        if self.instruction is not None and not (isinstance(self.instruction, str) and self.instruction.strip()):
            raise ReplayConfigError(f"ReplayConfig.instruction must be non-empty text, got {self.instruction!r}")
        if self.goal_mode == "agents" and self.instruction is None:
            raise ReplayConfigError("ReplayConfig.instruction is required when goal_mode is 'agents'")
        if not isinstance(self.vlm, str) or (":" not in self.vlm and self.vlm != TINY_PREFIX):
            raise ReplayConfigError(f"ReplayConfig.vlm must be a backend spec such as 'sim:nominal', 'http:URL', 'transformers:DIR' or 'tiny', got {self.vlm!r}")
        try:
            CoordFormat(self.coord_format)
        except ValueError:
            raise ReplayConfigError(
                f"ReplayConfig.coord_format must be one of {[c.value for c in CoordFormat]}, got {self.coord_format!r}"
            ) from None
        if self.vlm_deadline_s is not None and not (math.isfinite(self.vlm_deadline_s) and self.vlm_deadline_s > 0):
            raise ReplayConfigError(f"ReplayConfig.vlm_deadline_s must be positive, got {self.vlm_deadline_s!r}")

    def to_dict(self) -> dict:
        return to_jsonable(asdict(self))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ReplayConfig":
        """Build from a plain dict (e.g. a TOML ``[replay]`` table); nested tables fill the
        nested configs. Unknown keys raise :class:`ReplayConfigError` listing the valid ones."""
        nested = {"planner": PlannerConfig, "esdf": EsdfConfig, "verifier": VerifierConfig, "memory": MemoryConfig, "movers": MoverConfig}
        return config_from_tables(cls, data, nested, ReplayConfigError, "replay", convert={"goal_world": tuple})


# -- report values -------------------------------------------------------------------------------


@dataclass(frozen=True)
class StageLatency:
    """Latency of one stage over the frames (or calls) where it ran, milliseconds."""

    n: int
    median_ms: float
    p95_ms: float
    max_ms: float

    @classmethod
    def of(cls, samples_ms: Iterable[float]) -> "StageLatency":
        a = np.asarray(list(samples_ms), dtype=float)
        return cls(int(a.size), float(np.median(a)), float(np.percentile(a, 95)), float(a.max()))


@dataclass(frozen=True)
class FrameResult:
    """One processed frame.

    Attributes
    ----------
    index : index of the frame in the source (0-based, counting skipped frames)
    t_s : log time, seconds
    position_m : (3,) logged body position, world frame of the log
    speed_mps : finite-difference speed handed to the planner
    goal_m : (3,) goal the planner was given, or None
    esdf_ms, planner_ms : stage wall times (``esdf_ms`` includes the mover tracker's update)
    path_clearance_m : ESDF distance at the logged camera position after this frame's update
    planner_clearance_m : the plan's minimum predicted clearance (knots 1..N)
    slack_m : the plan's largest clearance slack
    fallback : ``"none"`` | ``"shifted"`` | ``"brake"``
    movers : moving obstacles the planner avoided at this frame (:mod:`planning.movers`)
    """

    index: int
    t_s: float
    position_m: tuple[float, float, float]
    speed_mps: float
    goal_m: tuple[float, float, float] | None
    esdf_ms: float
    planner_ms: float
    path_clearance_m: float
    planner_clearance_m: float
    slack_m: float
    fallback: str
    movers: int = 0


@dataclass(frozen=True)
class DecisionRecord:
    """One decision-agent call and what the verifier did with its pixel.

    Attributes
    ----------
    frame_index : the source frame it was made on
    subtask : the subtask asked about
    status : the backend call status (``"ok"``, ``"timeout"``, ``"error"``)
    pixel_uv : the parsed VLM pixel, or None
    refined_uv : the verifier's pixel, or None
    pixel_shift_px, gating_factor : from the verifier record (NaN when it did not run)
    refinement_note : the verifier's note, or None
    rejection : the verifier's rejection reason, or None
    goal_world_m : (3,) the accepted goal, or None
    reason : why there is no goal ("" when there is one)
    latency_ms : backend-reported call latency
    """

    frame_index: int
    subtask: str
    status: str
    pixel_uv: tuple[float, float] | None
    refined_uv: tuple[float, float] | None
    pixel_shift_px: float
    gating_factor: float
    refinement_note: str | None
    rejection: str | None
    goal_world_m: tuple[float, float, float] | None
    reason: str
    latency_ms: float


@dataclass(frozen=True)
class VerifierStats:
    """What the verifier changed over the replay.

    Attributes
    ----------
    candidates : pixels handed to the verifier
    accepted : of those, turned into goals
    moved : accepted goals whose pixel moved by at least ``moved_min_px``
    pixel_shift_median_px, pixel_shift_max_px : over the moved goals (None when none moved)
    range_gated : accepted goals with gating factor below ``range_gated_below``
    gating_factor_median : over the accepted goals (None when none)
    rejected : count per rejection reason
    refinement_notes : count per refinement note (semantic, no_features, beyond_d_max, ...)
    """

    candidates: int
    accepted: int
    moved: int
    pixel_shift_median_px: float | None
    pixel_shift_max_px: float | None
    range_gated: int
    gating_factor_median: float | None
    rejected: dict[str, int]
    refinement_notes: dict[str, int]


@dataclass(frozen=True)
class ReplayReport:
    """The result of :func:`replay` (JSON through :meth:`to_dict`).

    Attributes
    ----------
    source, kind : the source's path and kind
    frames : frames processed; frames_read : frames read from the source
    duration_s : log time from the first to the last processed frame
    goal_mode, instruction, vlm : as configured (vlm None when no agent ran)
    vlm_latency : ``"measured"`` or ``"modelled"`` (simulated VLM), None when no agent ran
    latency_ms : stage name (:data:`STAGES`) -> StageLatency, for the stages that ran
    path_clearance_min_m, path_clearance_median_m : ESDF distance at the logged camera
        positions (see the module docstring); path_clearance_min_index : frame of the minimum
    planner_clearance_min_m, planner_clearance_median_m : the plans' minimum predicted clearance
    planner_slack_steps : steps whose slack exceeded ``slack_tolerance_m``
    planner_fallbacks : count per fallback kind over the steps that did not use a fresh plan
    logged_speed_max_mps : largest finite-difference speed of the log (compare with v_max)
    subtasks, decomposition_source : the decomposition (agents only)
    decisions : decision-agent calls; decision_failures : count per failure reason
    goals_accepted : decisions that produced a goal
    monitor_calls, monitor_statuses : monitoring calls and count per status ("none" = failed)
    task_finished_frame : frame index at which the task manager finished the task, or None
    verifier : VerifierStats, None when no agent ran
    per_frame : FrameResult per processed frame; decision_log : DecisionRecord per call
    config : the ReplayConfig as a dict
    wall_s : wall time of the whole replay, seconds
    vision_runs_max_per_frame, vision_runs_mean_per_frame : vision-encoder runs per frame the
        agents and the verifier shared, from a backend that counts them (the in-process
        transformers backend: 1 when the vision pass is shared); None for other backends
    """

    source: str
    kind: str
    frames: int
    frames_read: int
    duration_s: float
    goal_mode: str
    instruction: str | None
    vlm: str | None
    vlm_latency: str | None
    latency_ms: dict[str, StageLatency]
    path_clearance_min_m: float
    path_clearance_median_m: float
    path_clearance_min_index: int
    planner_clearance_min_m: float
    planner_clearance_median_m: float
    planner_slack_steps: int
    planner_fallbacks: dict[str, int]
    logged_speed_max_mps: float
    subtasks: tuple[str, ...]
    decomposition_source: str | None
    decisions: int
    decision_failures: dict[str, int]
    goals_accepted: int
    monitor_calls: int
    monitor_statuses: dict[str, int]
    task_finished_frame: int | None
    verifier: VerifierStats | None
    per_frame: tuple[FrameResult, ...]
    decision_log: tuple[DecisionRecord, ...]
    config: dict
    wall_s: float
    vision_runs_max_per_frame: int | None = None
    vision_runs_mean_per_frame: float | None = None

    def to_dict(self, per_frame: bool = True) -> dict:
        """JSON-compatible dict (NaN and inf become None); ``per_frame=False`` drops the
        per-frame and per-decision lists."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if not per_frame:
            d.pop("per_frame")
            d.pop("decision_log")
        return to_jsonable(d)




# -- backends -----------------------------------------------------------------------------------


def _is_tiny(spec: str) -> bool:
    return spec.partition(":")[0].strip().lower() == TINY_PREFIX


class _Backend:
    """The replay's VLM backend and whatever it owns (a temporary checkpoint for ``tiny``).

    A backend passed in by the caller is used as is and not closed here.
    """

    def __init__(self, spec: str, seed: int, backend: VlmBackend | None = None) -> None:
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._owned = backend is None
        if backend is None:
            if _is_tiny(spec):
                self._tmp = tempfile.TemporaryDirectory(prefix="onfly-tiny-vlm-")
            try:
                backend = make_replay_backend(spec, seed=seed, tiny_dir=self._tmp.name if self._tmp else None)
            except BaseException:
                self.close()
                raise
        self.backend = backend
        self.spec = spec if self._owned else str(getattr(backend, "name", type(backend).__name__))
        from vlm.sim import SimulatedVlm

        self.simulated = isinstance(backend, SimulatedVlm)

    def close(self) -> None:
        try:
            if self._owned and getattr(self, "backend", None) is not None:
                self.backend.close()
        finally:
            if self._tmp is not None:
                self._tmp.cleanup()
                self._tmp = None


def make_replay_backend(spec: str, *, seed: int = 0, tiny_dir: str | Path | None = None) -> VlmBackend:
    """:func:`vlm.factory.make_backend`, plus ``tiny[:family]``: a tiny random-weight Qwen model
    (:func:`vlm.tiny_models.build_tiny_vlm`) written to ``tiny_dir`` and loaded in-process.

    Raises
    ------
    ValueError : a bad spec (lists the valid forms), or ``tiny`` without ``tiny_dir``
    vlm.types.VlmError : a backend that cannot be reached or loaded
    """
    from vlm.factory import make_backend

    if not _is_tiny(spec):
        return make_backend(spec, seed=seed)
    from vlm.tiny_models import TINY_FAMILIES, build_tiny_vlm

    family = spec.partition(":")[2].strip() or TINY_FAMILIES[0]
    if family not in TINY_FAMILIES:
        raise ValueError(f"bad VLM backend spec {spec!r}: tiny model family must be one of {TINY_FAMILIES}")
    if tiny_dir is None:
        raise ValueError(f"VLM backend spec {spec!r} needs a directory to write the tiny model to (tiny_dir)")
    log.info("building a tiny random-weight %s model in %s (its answers are garbage)", family, tiny_dir)
    path = build_tiny_vlm(tiny_dir, family=family, seed=seed)
    return make_backend(f"transformers:{path}")


# -- timing wrappers ---------------------------------------------------------------------------


class _TimedVerifier:
    """A Verifier that records the wall time of every call (the decision agent calls it)."""

    def __init__(self, verifier: Verifier, samples_ms: list[float]) -> None:
        self._verifier = verifier
        self._samples = samples_ms

    def verify(self, candidate: CandidateGoal) -> VerifiedGoal:
        t0 = time.perf_counter()
        try:
            return self._verifier.verify(candidate)
        finally:
            self._samples.append((time.perf_counter() - t0) * 1e3)


def _timed_features(backend: VlmBackend, samples_ms: list[float]):
    def compute(image: VlmImage) -> VisionFeatures | None:
        t0 = time.perf_counter()
        try:
            return backend.features(image)
        finally:
            samples_ms.append((time.perf_counter() - t0) * 1e3)

    return compute


# -- frame stream ---------------------------------------------------------------------------------


def _future_position(t_s: float, head: Observation, ahead: Iterable[Observation]) -> np.ndarray:
    """Body position at log time ``t_s`` by linear interpolation over ``head`` and the frames
    after it; the last frame's position when the log ends before ``t_s``."""
    prev = head
    for obs in ahead:
        if obs.t_s >= t_s:
            dt = obs.t_s - prev.t_s
            w = 0.0 if dt <= 0 else (t_s - prev.t_s) / dt
            return (1.0 - w) * prev.position + w * obs.position
        prev = obs
    return prev.position


def _with_future_goal(frames: Iterator[Observation], horizon_s: float | None) -> Iterator[tuple[Observation, np.ndarray | None]]:
    """``(obs, body position horizon_s later)`` for every frame (None without a horizon).

    Holds the frames of the next ``horizon_s`` seconds in memory.
    """
    if horizon_s is None:
        for obs in frames:
            yield obs, None
        return
    buf: deque[Observation] = deque()
    for obs in frames:
        buf.append(obs)
        while buf[-1].t_s >= buf[0].t_s + horizon_s:
            head = buf.popleft()
            yield head, _future_position(head.t_s + horizon_s, head, buf)
    while buf:
        head = buf.popleft()
        yield head, _future_position(head.t_s + horizon_s, head, buf)


# -- the replay -----------------------------------------------------------------------------------


class _Agents:
    """Memory, decision and monitoring agents, task manager and verifier over one backend."""

    def __init__(self, config: ReplayConfig, owner: _Backend, samples: dict[str, list[float]]) -> None:
        self.config = config
        self.owner = owner
        backend = owner.backend
        self.samples = samples
        self.features = FeatureCache(_timed_features(backend, samples["features"]), capacity=64)
        self.decision = DecisionAgent(
            backend,
            self.features,
            _TimedVerifier(Verifier(config.verifier), samples["verifier"]),  # type: ignore[arg-type]
            coord_format=config.coord_format,
            d_max_m=config.verifier.d_max_m,
            deadline_s=config.vlm_deadline_s,
        )
        self.monitor = MonitoringAgent(backend, make_memory(config.memory), self.features, deadline_s=config.vlm_deadline_s)
        dec = decompose_detailed(config.instruction, backend, deadline_s=config.vlm_deadline_s)
        self.subtasks = tuple(dec.subtasks)
        self.decomposition_source = dec.source
        self.tasks = TaskManager(list(dec.subtasks), config.stop_confirmations, config.intermediate_stop_confirmations)
        self.goal_world: np.ndarray | None = None
        self.finished_frame: int | None = None
        self.last_monitor_s = -math.inf
        self.decisions: list[DecisionRecord] = []
        self.outcomes: list[DecisionOutcome] = []
        self.monitor_statuses: Counter[str] = Counter()
        self.monitor_calls = 0
        self.frames_observed = 0

    def check_frame(self, obs: Observation) -> None:
        if self.owner.simulated and obs.annotation is None:
            raise ReplayError(
                f"the simulated VLM ({self.owner.spec}) needs per-frame annotations, which only OnFly logs of the "
                f"embedded world carry; frame {obs.frame_id!r} has none. Use a real backend (--vlm http:URL or "
                "transformers:DIR), or --vlm tiny to exercise the pipeline with a random-weight model"
            )

    def step(self, index: int, obs: Observation) -> tuple[DecisionOutcome | None, MonitorOutcome | None]:
        self.check_frame(obs)
        self.monitor.observe(obs)
        self.frames_observed += 1
        if self.tasks.finished:
            return None, None
        subtask = self.tasks.current
        out = self.decision.decide(obs, subtask, self.goal_world)
        self.outcomes.append(out)
        self.samples["decision_vlm"].append(out.latency_s * 1e3)
        self.decisions.append(_decision_record(index, out))
        if out.goal_world is not None:
            self.goal_world = np.asarray(out.goal_world, float)
        mon = None
        if obs.t_s - self.last_monitor_s >= self.config.monitor_period_s and self.frames_observed >= 2:
            self.last_monitor_s = obs.t_s
            mon = self.monitor.assess(subtask)
            self.monitor_calls += 1
            self.samples["monitoring_vlm"].append(mon.latency_s * 1e3)
            self.monitor_statuses[mon.status.value if mon.status is not None else "none"] += 1
            if mon.status is not None:
                event = self.tasks.on_status(Status(mon.status.value), obs.t_s, obs.position, obs.yaw)
                if event is TaskEvent.FINISHED:
                    self.finished_frame = index
                elif event is TaskEvent.ADVANCED:
                    self.goal_world = None
        return out, mon


def _decision_record(index: int, out: DecisionOutcome) -> DecisionRecord:
    rec = out.verified.record if out.verified is not None else None
    parse_uv = out.parse.uv if out.parse is not None and out.parse.ok else None
    return DecisionRecord(
        frame_index=index,
        subtask=out.subtask,
        status=out.response.status.value,
        pixel_uv=None if parse_uv is None else (float(parse_uv[0]), float(parse_uv[1])),
        refined_uv=None if rec is None or rec.refined_uv is None else tuple(float(x) for x in rec.refined_uv),
        pixel_shift_px=float("nan") if rec is None else float(rec.pixel_shift_px),
        gating_factor=float("nan") if rec is None else float(rec.gating_factor),
        refinement_note=None if rec is None else rec.refinement_note.value,
        rejection=None if rec is None or rec.rejection is None else rec.rejection.value,
        goal_world_m=None if out.goal_world is None else tuple(float(x) for x in out.goal_world),
        reason=out.reason,
        latency_ms=out.latency_s * 1e3,
    )


def _failure_key(reason: str) -> str:
    """``"parse: no point found"`` -> ``"parse"``; ``"rejected: ..."`` -> ``"rejected"``."""
    return reason.split(":", 1)[0].strip() or "unknown"


def _verifier_stats(records: list[DecisionRecord], config: ReplayConfig) -> VerifierStats:
    ran = [r for r in records if r.refinement_note is not None]
    accepted = [r for r in ran if r.rejection is None]
    shifts = [r.pixel_shift_px for r in accepted if r.pixel_shift_px >= config.moved_min_px]
    gating = [r.gating_factor for r in accepted]
    return VerifierStats(
        candidates=len(ran),
        accepted=len(accepted),
        moved=len(shifts),
        pixel_shift_median_px=float(np.median(shifts)) if shifts else None,
        pixel_shift_max_px=float(np.max(shifts)) if shifts else None,
        range_gated=sum(1 for g in gating if g < config.range_gated_below),
        gating_factor_median=float(np.median(gating)) if gating else None,
        rejected=dict(Counter(r.rejection for r in ran if r.rejection is not None)),
        refinement_notes=dict(Counter(r.refinement_note for r in ran)),
    )


def _state(obs: Observation, prev: Observation | None, prev_v: np.ndarray, prev_yaw_rate: float) -> VehicleState:
    """Logged body state; velocity and yaw rate by backward differences (held when dt <= 0)."""
    v, yaw_rate = prev_v, prev_yaw_rate
    if prev is not None:
        dt = obs.t_s - prev.t_s
        if dt > 0:
            v = (obs.position - prev.position) / dt
            yaw_rate = (unwrap_near(obs.yaw, prev.yaw) - prev.yaw) / dt
    return VehicleState(obs.t_s, obs.position, v, obs.yaw, yaw_rate)


def replay(
    source, config: ReplayConfig = ReplayConfig(), recorder=None, progress: bool = True, *, backend: VlmBackend | None = None
) -> ReplayReport:
    """Replay ``source`` open loop through ESDF, planner and (with an instruction) the agents.

    Parameters
    ----------
    source : an :class:`onfly.readers.ObservationSource` (or any iterable of Observation
        with optional ``path`` / ``kind`` attributes)
    config : ReplayConfig
    recorder : optional :class:`onfly.viz.RerunRecorder`; gets frames, map, logged path, plans,
        goals, VLM / verifier pixels, agent text and per-frame scalars
    progress : show a tqdm progress bar on stderr
    backend : a VLM backend object to use instead of building one from ``config.vlm``
        (used only with an instruction; the caller keeps ownership and closes it)

    Raises
    ------
    ReplayError : an empty source, or a simulated VLM on frames without annotations
    plus whatever the source raises for malformed data (reader errors name file and field)
    """
    t_wall = time.perf_counter()
    samples: dict[str, list[float]] = {name: [] for name in STAGES}
    esdf = EsdfMap(config.esdf)
    movers = MoverTracker(config.movers)
    # open loop: the recorded vehicle never flew our plans, so every plan starts at the recorded
    # state and a "tracking error" against them would be meaningless (planning/planner_config.py)
    planner = Planner(replace(config.planner, reference_start=False, tracking_margin_max_m=0.0))
    owner = _Backend(config.vlm, config.seed, backend) if config.instruction is not None else None
    frames: list[FrameResult] = []
    agents: _Agents | None = None
    speeds: list[float] = []
    frames_read = 0
    total = known_length(source)
    if total is not None:
        total = -(-total // config.every_n)
        if config.max_frames is not None:
            total = min(total, config.max_frames)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, unit="frame", desc="replay", leave=False)
    try:
        if owner is not None:
            agents = _Agents(config, owner, samples)
        horizon = config.future_pose_s if config.goal_mode == "future_pose" else None
        prev: Observation | None = None
        prev_v, prev_yaw_rate = np.zeros(3), 0.0
        for index, (obs, future) in enumerate(_with_future_goal(iter(source), horizon)):
            frames_read += 1
            state = _state(obs, prev, prev_v, prev_yaw_rate)
            prev, prev_v, prev_yaw_rate = obs, state.v, state.yaw_rate
            speeds.append(float(np.linalg.norm(state.v)))
            if index % config.every_n:
                continue
            frames.append(_process(index, obs, state, future, config, esdf, movers, planner, agents, samples, recorder))
            if bar is not None:
                bar.update(1)
            if config.max_frames is not None and len(frames) >= config.max_frames:
                break
    finally:
        if bar is not None:
            bar.close()
        runs = getattr(owner.backend, "vision_encoder_runs", None) if owner is not None else None
        if owner is not None:
            owner.close()
    if not frames:
        raise ReplayError(f"{getattr(source, 'path', source)}: no frames to replay")
    report = _report(source, config, frames, frames_read, speeds, agents, owner, samples, time.perf_counter() - t_wall)
    if isinstance(runs, dict) and runs:
        counts = list(runs.values())
        report = replace(report, vision_runs_max_per_frame=int(max(counts)), vision_runs_mean_per_frame=float(np.mean(counts)))
    return report


def _process(
    index: int,
    obs: Observation,
    state: VehicleState,
    future: np.ndarray | None,
    config: ReplayConfig,
    esdf: EsdfMap,
    movers: MoverTracker,
    planner: Planner,
    agents: _Agents | None,
    samples: dict[str, list[float]],
    recorder,
) -> FrameResult:
    t0 = time.perf_counter()
    tracked = movers.observe(float(obs.t_s), obs.depth_m, obs.camera, obs.T_world_cam, esdf)  # before the map has the frame
    mover_ms = (time.perf_counter() - t0) * 1e3
    update = esdf.integrate(obs.depth_m, obs.camera, obs.T_world_cam, center_world=obs.position)
    samples["esdf"].append(update.total_ms + mover_ms)
    cam_p = obs.T_world_cam[:3, 3]
    clearance = float(esdf.query(cam_p[None])[0][0])

    decision = monitor = None
    if agents is not None:
        decision, monitor = agents.step(index, obs)
    if config.goal_mode == "future_pose":
        goal = future
    elif config.goal_mode == "fixed":
        goal = np.asarray(config.goal_world, float)
    else:
        goal = agents.goal_world if agents is not None and agents.goal_world is not None else state.p
    if config.volume is not None:
        goal = config.flight_volume.clamp(goal, margin_m=planner.volume_goal_margin_m)
    plan = planner.step(state, goal, movers.field(esdf, float(obs.t_s)), volume=config.flight_volume)
    samples["planner"].append(plan.solve_time_ms)
    if recorder is not None:
        _record(recorder, index, obs, state, goal, plan, clearance, esdf, decision, monitor)
    return FrameResult(
        index=index,
        t_s=float(obs.t_s),
        position_m=tuple(float(x) for x in state.p),
        speed_mps=float(np.linalg.norm(state.v)),
        goal_m=tuple(float(x) for x in goal),
        esdf_ms=float(update.total_ms + mover_ms),
        planner_ms=float(plan.solve_time_ms),
        path_clearance_m=clearance,
        planner_clearance_m=float(plan.min_predicted_clearance_m),
        slack_m=float(plan.slack_max_m),
        fallback=plan.fallback.value,
        movers=len(tracked),
    )


def _record(recorder, index, obs, state, goal, plan: PlanResult, clearance, esdf, decision, monitor) -> None:
    recorder.log_frame(obs)
    recorder.log_map(obs.t_s, esdf.occupied_points())
    recorder.log_state(state)
    recorder.log_plan(obs.t_s, plan.trajectory)
    recorder.log_goal(obs.t_s, "planner", goal, color=(0, 255, 0))
    recorder.log_scalars(
        obs.t_s,
        {
            "clearance/path_m": clearance,
            "clearance/planned_min_m": plan.min_predicted_clearance_m,
            "planner/slack_m": plan.slack_max_m,
            "latency/planner_ms": plan.solve_time_ms,
        },
    )
    if decision is not None:
        rec = decision.verified.record if decision.verified is not None else None
        recorder.log_pixel(obs.t_s, "history_point", decision.history_uv, (255, 255, 0))
        recorder.log_pixel(obs.t_s, "vlm_pixel", decision.parse.uv if decision.parse is not None and decision.parse.ok else None, (255, 0, 0))
        recorder.log_pixel(obs.t_s, "refined_pixel", None if rec is None else rec.refined_uv, (0, 255, 0))
        recorder.log_goal(obs.t_s, "verified", decision.goal_world, color=(0, 255, 120))
        verdict = "goal" if decision.goal_world is not None else f"no goal ({decision.reason})"
        shift = "" if rec is None else f" shift {rec.pixel_shift_px:.1f} px gating {rec.gating_factor:.2f}"
        recorder.log_text(obs.t_s, f"frame {index} decision [{decision.subtask}] raw={decision.response.text[:120]!r} -> {verdict}{shift}")
    if monitor is not None:
        recorder.log_text(
            obs.t_s,
            f"frame {index} monitor [{monitor.subtask}] {monitor.status.value if monitor.status else 'none'} raw={monitor.response.text[:80]!r}",
            level="INFO" if monitor.status is not None else "WARN",
        )


def _report(source, config, frames, frames_read, speeds, agents, owner, samples, wall_s) -> ReplayReport:
    clear = np.array([f.path_clearance_m for f in frames])
    planned = np.array([f.planner_clearance_m for f in frames])
    fallbacks = Counter(f.fallback for f in frames if f.fallback != "none")
    latency = {name: StageLatency.of(s) for name, s in samples.items() if s}
    verifier = decisions = None
    if agents is not None:
        decisions = agents.decisions
        verifier = _verifier_stats(decisions, config)
    failures = Counter(_failure_key(d.reason) for d in decisions or () if d.goal_world_m is None)
    return ReplayReport(
        source=str(getattr(source, "path", "")),
        kind=str(getattr(source, "kind", type(source).__name__)),
        frames=len(frames),
        frames_read=frames_read,
        duration_s=frames[-1].t_s - frames[0].t_s,
        goal_mode=config.goal_mode,
        instruction=config.instruction,
        vlm=owner.spec if owner is not None else None,
        vlm_latency=None if owner is None else ("modelled" if owner.simulated else "measured"),
        latency_ms=latency,
        path_clearance_min_m=float(clear.min()),
        path_clearance_median_m=float(np.median(clear)),
        path_clearance_min_index=int(frames[int(np.argmin(clear))].index),
        planner_clearance_min_m=float(planned.min()),
        planner_clearance_median_m=float(np.median(planned)),
        planner_slack_steps=int(sum(f.slack_m > config.slack_tolerance_m for f in frames)),
        planner_fallbacks=dict(fallbacks),
        logged_speed_max_mps=float(max(speeds)),
        subtasks=agents.subtasks if agents is not None else (),
        decomposition_source=agents.decomposition_source if agents is not None else None,
        decisions=len(decisions or ()),
        decision_failures=dict(failures),
        goals_accepted=sum(1 for d in decisions or () if d.goal_world_m is not None),
        monitor_calls=agents.monitor_calls if agents is not None else 0,
        monitor_statuses=dict(agents.monitor_statuses) if agents is not None else {},
        task_finished_frame=agents.finished_frame if agents is not None else None,
        verifier=verifier,
        per_frame=tuple(frames),
        decision_log=tuple(decisions or ()),
        config=config.to_dict(),
        wall_s=wall_s,
    )
