"""The two agents of the paper's dual-agent system.

- :class:`DecisionAgent` (high rate): prompt with the current subtask and the *history point*
  (the previous 3D goal reprojected into the current image), VLM -> pixel -> candidate goal
  ``G_c = [px, py, depth_t, f_t, pose_t]`` -> semantic-geometric verifier -> navigation goal.
- :class:`MonitoringAgent` (low rate): forced choice over CONTINUE / STOP / LOST from its
  memory ``M_t = [o_1, Q_t, o_t]``.

Both read the same per-frame :class:`vlm.feature_cache.FeatureCache` (shared perception) and
keep their own prompt, memory and KV-cache stream (``cache_key``). An agent call is a pure
function of its inputs and returns an outcome value; *when* the outcome takes effect is the
pilot's business (virtual-clock latency in simulation, a worker thread onboard).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from onfly.memory import FrameRecord, HybridMemory, MemorySnapshot, SlidingWindowMemory, TimeSamplingMemory
from onfly.observation import Observation
from planning.frames import invert_transform, transform_points
from planning.verifier import CandidateGoal, RejectionReason, VerifiedGoal, Verifier, VerifierInputError
from vlm.feature_cache import FeatureCache
from vlm.parsing import CoordFormat, MonitorStatus, PointParse, StatusParse, parse_point, parse_status
from vlm.prompts import build_decision_prompt, build_monitor_prompt, decision_schema, status_schema
from vlm.types import CallStatus, VisionFeatures, VlmBackend, VlmImage, VlmResponse

__all__ = [
    "DecisionOutcome",
    "MonitorOutcome",
    "DecisionAgent",
    "MonitoringAgent",
    "history_point",
    "vlm_image",
    "global_descriptor",
    "unverified_goal",
]

log = logging.getLogger(__name__)

DECISION_STREAM = "decision"
#: patch size handed to the verifier when there are no features (it then ignores patches)
GEOMETRIC_PATCH_PX = 16.0
MONITOR_STREAM = "monitoring"


def vlm_image(obs: Observation) -> VlmImage:
    """The VLM's view of an observation (the world's annotation rides along for the sim VLM)."""
    return VlmImage(rgb=obs.rgb, frame_id=obs.frame_id, annotation=obs.annotation)


def history_point(goal_world, obs: Observation) -> tuple[float, float] | None:
    """The previous 3D goal reprojected into the current image.

    Returns pixel ``(u, v)``, or None when there is no goal, it is behind the camera, or it
    projects outside the image.
    """
    if goal_world is None:
        return None
    p_cam = transform_points(invert_transform(obs.T_world_cam), np.asarray(goal_world, float))
    uv, in_front = obs.camera.project(p_cam)
    if not in_front or not bool(obs.camera.in_image(uv[None])[0]):
        return None
    return float(uv[0]), float(uv[1])


def global_descriptor(features: VisionFeatures | None, rgb: np.ndarray) -> np.ndarray:
    """Unit-norm frame descriptor for keyframe de-duplication (cosine distance).

    The mean of the frame's patch features when the backend has them; otherwise a
    mean-subtracted 16 x 12 grey thumbnail (documented fallback for feature-less backends).
    """
    if features is not None:
        f = np.asarray(features.grid, dtype=np.float64).reshape(-1, features.grid.shape[-1]).mean(axis=0)
    else:
        import cv2

        grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        f = cv2.resize(grey, (16, 12), interpolation=cv2.INTER_AREA).astype(np.float64).reshape(-1)
        f = f - f.mean()
    n = np.linalg.norm(f)
    return f / n if n > 0 else np.full_like(f, 1.0 / np.sqrt(f.size))


def unverified_goal(uv, obs: Observation, d_max_m: float) -> np.ndarray | None:
    """The "without verification" ablation: lift the raw pixel at its own depth (capped at
    ``d_max_m``), no refinement, no gating. None when the pixel has no depth reading."""
    u, v = int(round(uv[0])), int(round(uv[1]))
    d = float(obs.depth_m[v, u])
    if not np.isfinite(d) or d <= 0:
        return None
    p_cam = obs.camera.back_project(np.array([uv[0], uv[1]], float), min(d, d_max_m))
    return transform_points(obs.T_world_cam, p_cam)


@dataclass(frozen=True, eq=False)
class DecisionOutcome:
    """One decision-agent call.

    Attributes
    ----------
    frame_id : the frame the decision was made on
    subtask : the subtask it was asked about
    response : the backend's response
    history_uv : the history point shown in the prompt, or None
    parse : the parsed point (None when the call failed)
    verified : the verifier's result (None when there was no pixel or verification is off)
    goal_world : (3,) navigation goal in metres, world ENU, or None (hold the last goal)
    reason : why there is no goal ("" when there is one)
    pixel_yaw : world heading (radians) of the parsed pixel's viewing ray, or None; a
        rejected candidate still says which way the target is
    not_visible : the model answered that the target is not visible in this frame (no goal;
        the pilot's search counts these)
    target_world : (3,) metres, world ENU, or None: the pointed object itself, the model's
        pixel lifted at its depth (:func:`pointed_point`; the verifier's refined pixel may lie
        beside the object, where the goal is safe). None when there is no goal (the verifier
        rejected the pixel) or no reading. A follower (:mod:`onfly.follow`) tracks a moving
        person with it
    frame_t_s : capture time of the frame the decision was made on, seconds (NaN if unknown)
    look_yaw : with ``not_visible``, the world heading (radians) of the viewing ray of the point
        where the model would look for the target instead (``decision/v3``), or None
    blocked_target_world : (3,) metres, world ENU, or None: when the verifier rejected the
        pixel because no pixel of the target has a clear straight ray (``no_feasible_pixel``:
        something stands in between), the pointed object's point (:func:`pointed_point`); the
        pilot may route around what is in between (:func:`planning.approach.approach_point`)
    """

    frame_id: str
    subtask: str
    response: VlmResponse
    history_uv: tuple[float, float] | None
    parse: PointParse | None
    verified: VerifiedGoal | None
    goal_world: np.ndarray | None
    reason: str = ""
    pixel_yaw: float | None = None
    not_visible: bool = False
    target_world: np.ndarray | None = None
    frame_t_s: float = float("nan")
    look_yaw: float | None = None
    blocked_target_world: np.ndarray | None = None

    @property
    def latency_s(self) -> float:
        return self.response.latency_s


def pointed_point(uv, obs: Observation, half_px: int = 3, percentile: float = 20.0) -> np.ndarray | None:
    """The point a pixel ``uv`` of ``obs`` shows: the ``percentile`` of the valid z-depths of the
    ``(2 half_px + 1)^2`` window around it (a low percentile: a pointed person stands in front
    of the background, and a pixel near their outline must not take the background's depth),
    lifted to (3,) metres, world ENU; None when the window has no reading or the pixel is
    outside the image."""
    h, w = obs.depth_m.shape
    u, v = int(round(uv[0])), int(round(uv[1]))
    if not (0 <= u < w and 0 <= v < h):
        return None
    win = np.asarray(obs.depth_m[max(v - half_px, 0) : v + half_px + 1, max(u - half_px, 0) : u + half_px + 1], float)
    vals = win[np.isfinite(win) & (win > 0)]
    if vals.size == 0:
        return None
    p_cam = obs.camera.back_project(np.array([float(uv[0]), float(uv[1])]), float(np.percentile(vals, percentile)))
    return transform_points(obs.T_world_cam, p_cam)


def pixel_yaw(uv, obs: Observation) -> float:
    """World heading (radians) of the viewing ray through pixel ``uv`` of ``obs``."""
    ray_cam = obs.camera.K_inv @ np.array([uv[0], uv[1], 1.0])
    ray_world = obs.T_world_cam[:3, :3] @ ray_cam
    return float(np.arctan2(ray_world[1], ray_world[0]))


@dataclass(frozen=True, eq=False)
class MonitorOutcome:
    """One monitoring-agent call: the status, or None when the call or the parse failed.

    ``judged_*`` describe ``o_t``, the latest frame of the memory snapshot the call judged: a
    CONTINUE makes *that* pose the normal point (not the pose when the answer lands, up to one
    call later). None / NaN when the memory was empty.

    ``seen_*`` describe the frame a LOST names as the last to show the target (``LOST keyframe
    2``, :attr:`vlm.parsing.StatusParse.seen_image`): its id, and the pose it was taken from
    (metres and radians, world). None / NaN when the answer named none.
    """

    subtask: str
    response: VlmResponse
    parse: StatusParse | None
    status: MonitorStatus | None
    memory_frame_ids: tuple[str, ...]
    reason: str = ""
    judged_frame_id: str | None = None
    judged_t_s: float = float("nan")
    judged_position: np.ndarray | None = None
    judged_yaw: float = float("nan")
    seen_frame_id: str | None = None
    seen_position: np.ndarray | None = None
    seen_yaw: float = float("nan")

    @property
    def latency_s(self) -> float:
        return self.response.latency_s


@dataclass
class DecisionAgent:
    """The high-rate agent: pixel goal from the VLM, verified into a 3D navigation goal.

    Parameters
    ----------
    backend : VlmBackend
    features : FeatureCache shared with the monitoring agent (and the verifier)
    verifier : Verifier, or None for the "without verification" ablation
    coord_format : how the backend writes points (see :class:`vlm.parsing.CoordFormat`)
    d_max_m : depth cap used by the unverified ablation
    deadline_s : per-call deadline handed to the backend
    """

    backend: VlmBackend
    features: FeatureCache | None
    verifier: Verifier | None
    coord_format: CoordFormat | str = CoordFormat.PIXEL
    model_input_size: tuple[int, int] | None = None
    d_max_m: float = 7.0
    deadline_s: float | None = None
    max_new_tokens: int = 48
    structured_output: bool = True
    calls: int = field(default=0, init=False)

    def decide(self, obs: Observation, subtask: str, last_goal_world=None) -> DecisionOutcome:
        """Run one decision call on ``obs`` (blocking; the pilot decides when it lands)."""
        self.calls += 1
        image = vlm_image(obs)
        hist = history_point(last_goal_world, obs)
        messages, images = build_decision_prompt(subtask, image, hist)
        response = self.backend.complete(
            messages,
            images,
            deadline_s=self.deadline_s,
            json_schema=decision_schema() if self.structured_output else None,
            max_new_tokens=self.max_new_tokens,
            cache_key=DECISION_STREAM,
        )

        def out(parse=None, verified=None, goal=None, reason="", not_visible=False):
            yaw = pixel_yaw(parse.uv, obs) if parse is not None and parse.ok else None
            target = pointed_point(parse.uv, obs) if goal is not None else None
            look = getattr(parse, "look_uv", None) if not_visible else None
            blocked = verified is not None and verified.record.rejection is RejectionReason.NO_FEASIBLE_PIXEL
            return DecisionOutcome(obs.frame_id, subtask, response, hist, parse, verified, goal, reason, yaw, not_visible,
                                   target, float(obs.t_s), pixel_yaw(look, obs) if look is not None else None,
                                   pointed_point(parse.uv, obs) if blocked else None)

        if response.status is not CallStatus.OK:
            log.info("decision call %s: %s", response.status.value, response.error)
            return out(reason=f"call {response.status.value}: {response.error}")
        parse = parse_point(
            response.text, image.size, self.coord_format, model_input_size=self.model_input_size
        )
        if getattr(parse, "not_visible", False):
            return out(parse=parse, reason="not visible", not_visible=True)
        if not parse.ok:
            log.info("decision parse failed (%s): %r", parse.reason, response.text[:200])
            return out(parse=parse, reason=f"parse: {parse.reason}")
        if self.verifier is None:
            goal = unverified_goal(parse.uv, obs, self.d_max_m)
            return out(parse=parse, goal=goal, reason="" if goal is not None else "no depth at the pixel")
        feats = self.features.get(image) if self.features is not None else None
        candidate = self._candidate(parse.uv, obs, feats)
        verified = self.verifier.verify(candidate)
        if not verified.accepted:
            return out(parse=parse, verified=verified, reason=f"rejected: {verified.record.rejection}")
        return out(parse=parse, verified=verified, goal=np.asarray(verified.goal_world, float))

    @staticmethod
    def _candidate(uv, obs: Observation, feats: VisionFeatures | None) -> CandidateGoal:
        """``G_c`` for the verifier. Features whose patch grid does not tile the depth image
        (a backend whose resized input differs from the camera's) drop to geometric-only."""
        common = dict(pixel_uv=uv, depth_m=obs.depth_m, T_world_cam=obs.T_world_cam, camera=obs.camera)
        if feats is not None:
            try:
                return CandidateGoal(features=feats.grid, patch_px=feats.patch_px, **common)
            except VerifierInputError as exc:
                log.warning("features unusable by the verifier (%s); geometric-only mode", exc)
        return CandidateGoal(features=None, patch_px=GEOMETRIC_PATCH_PX, **common)


@dataclass
class MonitoringAgent:
    """The low-rate agent: CONTINUE / STOP / LOST over its memory.

    Parameters
    ----------
    backend : VlmBackend
    memory : HybridMemory, SlidingWindowMemory or TimeSamplingMemory
    features : the shared FeatureCache (frame descriptors for keyframe de-duplication)
    """

    backend: VlmBackend
    memory: HybridMemory | SlidingWindowMemory | TimeSamplingMemory
    features: FeatureCache | None
    deadline_s: float | None = None
    max_new_tokens: int = 16
    structured_output: bool = False
    calls: int = field(default=0, init=False)

    def observe(self, obs: Observation) -> FrameRecord:
        """Add a frame to the memory (its descriptor comes from the shared feature cache)."""
        image = vlm_image(obs)
        feats = self.features.get(image) if self.features is not None else None
        return self.memory.observe(
            obs.frame_id, obs.t_s, obs.position, obs.yaw, global_descriptor(feats, obs.rgb), payload=image
        )

    def snapshot(self) -> MemorySnapshot:
        """Select ``M_t`` now and freeze it: call on the control thread when the monitoring call
        starts, and hand the result to :meth:`assess` on the worker."""
        return self.memory.snapshot()

    def assess(self, subtask: str, snapshot: MemorySnapshot | None = None) -> MonitorOutcome:
        """Run one monitoring call over ``M_t`` (blocking). ``snapshot`` from :meth:`snapshot`
        (taken on the control thread); None takes one now."""
        self.calls += 1
        if snapshot is None:
            snapshot = self.memory.snapshot()
        records = snapshot.records
        ids = snapshot.frame_ids
        judged = snapshot.judged
        where = {} if judged is None else dict(
            judged_frame_id=judged.frame_id, judged_t_s=judged.t_s, judged_position=judged.position.copy(),
            judged_yaw=judged.yaw,
        )
        if len(records) < 2:
            resp = VlmResponse(CallStatus.ERROR, error="memory holds fewer than two frames")
            return MonitorOutcome(subtask, resp, None, None, ids, reason="memory too short", **where)
        images = [r.payload for r in records]
        messages, imgs = build_monitor_prompt(subtask, images[0], images[1:-1], images[-1])
        response = self.backend.complete(
            messages,
            imgs,
            deadline_s=self.deadline_s,
            json_schema=status_schema() if self.structured_output else None,
            max_new_tokens=self.max_new_tokens,
            cache_key=MONITOR_STREAM,
        )
        if response.status is not CallStatus.OK:
            return MonitorOutcome(subtask, response, None, None, ids, reason=f"call {response.status.value}: {response.error}", **where)
        parse = parse_status(response.text, n_keyframes=len(records) - 2)
        if not parse.ok:
            log.info("monitor parse failed (%s): %r", parse.reason, response.text[:200])
            return MonitorOutcome(subtask, response, parse, None, ids, reason=f"parse: {parse.reason}", **where)
        if parse.seen_image is not None:
            seen = records[parse.seen_image]  # the prompt's images are the records, in order
            where.update(seen_frame_id=seen.frame_id, seen_position=seen.position.copy(), seen_yaw=float(seen.yaw))
        return MonitorOutcome(subtask, response, parse, parse.status, ids, reason=parse.reason, **where)
