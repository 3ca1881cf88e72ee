"""SimulatedVlm: a :class:`vlm.types.VlmBackend` that answers OnFly's prompts from annotations.

It also answers the baselines' prompts (``typefly``, ``pivot``, ``spf`` templates) with the same
preset error model; the rules are in :mod:`vlm.sim.error_model` ("Baseline prompts").

It recognises the prompt with :func:`vlm.prompts.parse_prompt` (the same text a real model
reads), looks only at each image's :class:`vlm.types.FrameAnnotation`, and answers in the text
formats a real model uses. The error model, the latency model and the randomness are stated in
:mod:`vlm.sim.error_model`.
"""

from __future__ import annotations

import json
import logging
import math
import threading
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vlm.decompose import CLOSING_ONLY_WORDS, is_context, opens_with_back_reference, split_instruction
from vlm.following import follow_intent
from vlm.prompts import (
    SPF_MAX_DEPTH_M,
    DecisionPrompt,
    DecomposePrompt,
    MonitorPrompt,
    PivotPrompt,
    PromptError,
    SceneObject,
    SpfPrompt,
    TypeflyPrompt,
    parse_prompt,
    prompt_segments,
)
from vlm.sim.error_model import ErrorModel, ErrorModelError, LatencyModel, get_preset
from vlm.sim.features import FEATURE_MODELS, degraded_features, keyed_rng, synthetic_features
from vlm.sim.grounding import (
    Region,
    anchor_pixel,
    exploration_point,
    ground,
    names_target,
    place_entrance,
    region_of,
    visible_regions,
    words,
)
from vlm.types import (
    CallStatus,
    ChatMessage,
    FrameAnnotation,
    Usage,
    VisibleObject,
    VisionFeatures,
    VlmImage,
    VlmResponse,
)

__all__ = ["SimulatedVlm", "Perception", "LegTarget"]

log = logging.getLogger(__name__)

_STATUSES = ("CONTINUE", "STOP", "LOST")
#: words by which a leg of an instruction refers back to the previous leg's target
_BACK_REFERENCES = frozenset({"it", "its", "there", "them", "that", "this", "him", "her"})
#: the TypeFly sim's exploration move after a full find turn without the target, metres
TYPEFLY_EXPLORE_M = 3.0


@dataclass(frozen=True)
class Perception:
    """What the simulated VLM perceives of the subtask's target in one frame.

    Attributes
    ----------
    named_id : int or None, best visible object the subtask names (None: none is visible)
    region : Region of that object, or None
    perceived : bool, False if there is none or it was missed
    small, far : bool, the miss conditions that applied
    moving : bool, the perceived object is moving in this frame (a walking person)
    hint : Region or None, with no target in view: a visible object the subtask locates its
        target by (``the charging station by the blue car``: the car), else the entrance to a
        place it names (``the vacuum cleaner in the storage room``: the storage room's
        doorway), where the model looks
    """

    named_id: int | None
    region: Region | None
    perceived: bool
    small: bool = False
    far: bool = False
    moving: bool = False
    hint: Region | None = None


@dataclass(frozen=True)
class LegTarget:
    """What a memoryless baseline prompt aims at in one frame (rule in :mod:`vlm.sim.error_model`).

    Attributes
    ----------
    leg : int, index of the instruction leg being pursued (``split_instruction`` order)
    perception : Perception of that leg's target, or None (explore)
    final : bool, ``leg`` is the last leg
    reached : bool, the final leg's target is perceived within the stop distance (stop)
    """

    leg: int
    perception: Perception | None
    final: bool
    reached: bool


class SimulatedVlm:
    """Simulated VLM backend (see :mod:`vlm.sim.error_model` for everything it does).

    Parameters
    ----------
    preset : name of a preset in :data:`vlm.sim.error_model.PRESETS`, or an ErrorModel
    seed : int, the root of every random draw
    latency : LatencyModel (defaults: the paper's Jetson Orin NX numbers)
    feature_dim, patch_px : size of the synthetic features (:mod:`vlm.sim.features`)
    feature_model : ``"degraded"`` (default: features that err like a real ViT's,
        :func:`vlm.sim.features.degraded_features`) or ``"perfect"`` (ground-truth instance ids)
    """

    def __init__(
        self,
        preset: str | ErrorModel = "nominal",
        seed: int = 0,
        *,
        latency: LatencyModel | None = None,
        feature_dim: int = 64,
        patch_px: int = 16,
        feature_model: str = "degraded",
    ) -> None:
        self.model = preset if isinstance(preset, ErrorModel) else get_preset(preset)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise ErrorModelError(f"seed must be an int, got {seed!r}")
        if feature_dim < 2 or patch_px < 1:
            raise ErrorModelError(f"feature_dim must be >= 2 and patch_px >= 1, got {feature_dim}, {patch_px}")
        if feature_model not in FEATURE_MODELS:
            raise ErrorModelError(f"feature_model must be one of {FEATURE_MODELS}, got {feature_model!r}")
        self.feature_model = feature_model
        self.seed = int(seed)
        self.latency = latency if latency is not None else LatencyModel()
        self.feature_dim = int(feature_dim)
        self.patch_px = int(patch_px)
        self.name = f"sim:{self.model.name}"
        self._prefix: dict[str, tuple[str, ...]] = {}
        self._lock = threading.Lock()

    # -- protocol -----------------------------------------------------------------------------
    def __enter__(self) -> "SimulatedVlm":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with self._lock:
            self._prefix.clear()

    def features(self, image: VlmImage) -> VisionFeatures | None:
        """Synthetic patch features (:mod:`vlm.sim.features`, ``feature_model``); None for a frame
        without annotation."""
        if image.annotation is None:
            log.debug("frame %s has no annotation: no simulated features", image.frame_id)
            return None
        if self.feature_model == "perfect":
            return synthetic_features(image.annotation, image.frame_id, seed=self.seed, dim=self.feature_dim, patch_px=self.patch_px)
        return degraded_features(image.annotation, image.rgb, image.frame_id, seed=self.seed, dim=self.feature_dim,
                                 patch_px=self.patch_px)

    def complete(
        self,
        messages: Sequence[ChatMessage],
        images: Sequence[VlmImage] = (),
        *,
        deadline_s: float | None = None,
        json_schema: dict | None = None,
        max_new_tokens: int = 64,
        cache_key: str | None = None,
    ) -> VlmResponse:
        """Answer an OnFly prompt; unknown prompts and bad images give an ERROR response."""
        bad = [type(img).__name__ for img in images if not isinstance(img, VlmImage)]
        if bad:
            return VlmResponse(CallStatus.ERROR, error=f"images must be VlmImage values, got {bad}")
        try:
            segments = prompt_segments(messages, images)
        except PromptError as exc:
            return VlmResponse(CallStatus.ERROR, error=str(exc))
        prompt = parse_prompt(messages)
        if prompt is None:
            return VlmResponse(CallStatus.ERROR, error="simulated VLM: unrecognised prompt (build it with vlm.prompts)")
        problem = self._check_images(prompt, images)
        if problem:
            return VlmResponse(CallStatus.ERROR, error=f"simulated VLM: {problem}")
        structured = json_schema is not None
        if isinstance(prompt, DecisionPrompt):
            text = self._decide(prompt, images[0], structured)
        elif isinstance(prompt, MonitorPrompt):
            text = self._monitor(prompt, images, structured)
        elif isinstance(prompt, SpfPrompt):
            text = self._spf(prompt, images[0], structured)
        elif isinstance(prompt, PivotPrompt):
            text = self._pivot(prompt, images[0], structured)
        elif isinstance(prompt, TypeflyPrompt):
            text = self._typefly(prompt, images[0])
        else:
            text = self._decompose(prompt, structured)
        return self._respond(prompt, images, segments, text, deadline_s, max_new_tokens, cache_key)

    # -- checks ---------------------------------------------------------------------------------
    @staticmethod
    def _check_images(prompt: object, images: Sequence[VlmImage]) -> str:
        if isinstance(prompt, (DecisionPrompt, SpfPrompt, PivotPrompt, TypeflyPrompt)) and len(images) != 1:
            kind = type(prompt).__name__.removesuffix("Prompt").lower()
            return f"{kind} prompt needs 1 image, got {len(images)}"
        if isinstance(prompt, MonitorPrompt) and len(images) != prompt.n_keyframes + 2:
            return f"monitoring prompt with {prompt.n_keyframes} keyframes needs {prompt.n_keyframes + 2} images, got {len(images)}"
        for img in images:
            ann = img.annotation
            if ann is None:
                return f"frame {img.frame_id!r} has no FrameAnnotation (the simulated VLM sees only annotated frames)"
            shape = img.rgb.shape[:2]
            if np.shape(ann.instance_ids) != shape or np.shape(ann.depth_m) != shape:
                return f"frame {img.frame_id!r}: annotation shapes {np.shape(ann.instance_ids)}, {np.shape(ann.depth_m)} differ from rgb {shape}"
        return ""

    # -- perception -----------------------------------------------------------------------------
    def perceive(self, subtask: str, image: VlmImage, *, last_mention: bool = False) -> Perception:
        """The target the subtask names in this frame, and whether it is perceived.

        ``last_mention``: the object named last instead of the grounding order (what "it" in
        the next leg refers to). The miss draw is keyed on (seed, frame id, instance id), so one
        frame is perceived the same way in every call.
        """
        ann: FrameAnnotation = image.annotation  # checked by the caller
        areas = visible_regions(ann)
        matches = ground(subtask, ann.objects, areas)
        targets = [mt for mt in matches if not mt.locates]  # a landmark of the target is never it
        if not targets:
            # where to look: a landmark that locates the target, else the entrance to a place named
            hint = matches[0].instance_id if matches else place_entrance(subtask, ann.objects, areas)
            return Perception(None, None, False, hint=None if hint is None else region_of(ann, hint))
        iid = (max(targets, key=_mention_end) if last_mention else targets[0]).instance_id
        region = region_of(ann, iid)
        w, h = image.size
        small = region.area_px < self.model.small_target_frac * w * h
        far = math.isfinite(region.median_depth_m) and region.median_depth_m > self.model.far_target_m
        rng = keyed_rng(self.seed, "miss", image.frame_id, iid)
        u_small, u_far = rng.random(2)
        missed = (small and u_small < self.model.miss_prob_small) or (far and u_far < self.model.miss_prob_far)
        return Perception(iid, region, not missed, small, far, bool(getattr(ann.objects[iid], "moving", False)))

    # -- decision -------------------------------------------------------------------------------
    def _decide(self, prompt: DecisionPrompt, image: VlmImage, structured: bool) -> str:
        m = self.model
        rng = keyed_rng(self.seed, "decision", image.frame_id, prompt.subtask, prompt.history_uv)
        u_malformed, u_variety, u_confuse = rng.random(3)
        ann: FrameAnnotation = image.annotation
        w, h = image.size
        legs = self._legs(prompt.subtask)
        # the leg rule of every prompt; the decision prompt has no stop interface, so an
        # intermediate leg counts as reached at the stop distance without jitter
        tgt = self.leg_target(prompt.subtask, image, 0.0)
        leg = min(tgt.leg, len(legs) - 1)
        per = tgt.perception
        label_name = ""
        hint = self._pointed(legs[leg], ann, None if per is None else per.hint, rng, u_confuse)
        if per is not None and per.perceived:
            region = self._pointed(legs[leg], ann, per.region, rng, u_confuse)
            label_name = ann.objects[region.instance_id].name
            u0, v0 = anchor_pixel(region.mask)
            sigma = m.pixel_sigma_px(w, region.median_depth_m)
        elif _leg_names_target(legs, leg):
            return self._not_visible(rng, u_malformed, u_variety, structured, ann.depth_m, hint)
        elif hint is not None:  # a place to go ("fly into the kitchen"): its entrance in view
            u0, v0 = anchor_pixel(hint.mask)
            sigma = m.pixel_sigma_px(w, 0.0)
        elif prompt.history_uv is not None:
            u0, v0 = prompt.history_uv
            sigma = m.pixel_sigma_px(w, 0.0)
        else:
            u0, v0 = exploration_point(ann.depth_m)
            sigma = m.pixel_sigma_px(w, 0.0)
        du, dv = rng.normal(0.0, sigma, 2) if sigma > 0 else (0.0, 0.0)
        u = int(np.clip(round(u0 + du), 0, w - 1))
        v = int(np.clip(round(v0 + dv), 0, h - 1))
        if u_malformed < m.malformed_prob:
            return self._malformed_point(rng, u, v, w, h, structured, flag=True)
        plain = json.dumps({"target_visible": True, "point_2d": [u, v]})
        if structured or u_variety >= m.format_variety_prob:
            return plain
        variants = (
            f"```json\n{plain}\n```",
            f"The target is here: {plain}",
            json.dumps([{"point_2d": [u, v], "label": label_name or "waypoint"}]),
        )
        return variants[int(rng.integers(len(variants)))]

    def _not_visible(
        self, rng: np.random.Generator, u_malformed: float, u_variety: float, structured: bool, depth_m: np.ndarray,
        hint: Region | None = None,
    ) -> str:
        """The decision answer "the target is not visible" (decision/v3) with the point where
        the model would look instead: the exploration point (the anchor pixel of ``hint``, a
        landmark in view that locates the target, when given) plus the pixel noise at ``d = 0``,
        the point every baseline prompt is given for an unperceived target (one rule for
        every prompt). In a real model's shapes (one of them, ``NOT_VISIBLE``, carries no
        point); malformed with ``malformed_prob`` like any answer."""
        m = self.model
        h, w = depth_m.shape
        u0, v0 = exploration_point(depth_m) if hint is None else anchor_pixel(hint.mask)
        sigma = m.pixel_sigma_px(w, 0.0)
        du, dv = rng.normal(0.0, sigma, 2) if sigma > 0 else (0.0, 0.0)
        u = int(np.clip(round(u0 + du), 0, w - 1))
        v = int(np.clip(round(v0 + dv), 0, h - 1))
        if u_malformed < m.malformed_prob:
            return self._malformed_point(rng, w // 2, h // 2, w, h, structured, flag=True)
        plain = json.dumps({"target_visible": False, "point_2d": [u, v]})
        if structured or u_variety >= m.format_variety_prob:
            return plain
        variants = (f"```json\n{plain}\n```", "NOT_VISIBLE", f"The target is not visible in this image. {plain}")
        return variants[int(rng.integers(len(variants)))]

    def _pointed(
        self, leg_text: str, ann: FrameAnnotation, region: Region | None, rng: np.random.Generator, u_confuse: float
    ) -> Region | None:
        """The region an answer points at: ``region`` (the perceived target, or the landmark or
        entrance where the model looks for an unseen one), or with ``confusion_prob`` a
        uniformly chosen visible look-alike of it (rule 2; ``u_confuse`` is the call's draw).
        None for None (nothing to point at)."""
        if region is None:
            return None
        lookalikes = self._lookalikes(leg_text, ann, region.instance_id)
        if lookalikes and u_confuse < self.model.confusion_prob:
            return region_of(ann, lookalikes[int(rng.integers(len(lookalikes)))])
        return region

    @staticmethod
    def _lookalikes(subtask: str, ann: FrameAnnotation, target_id: int) -> list[int]:
        """Visible objects with the target's label and another name, not named by the subtask."""
        areas = visible_regions(ann)
        named = {mt.instance_id for mt in ground(subtask, ann.objects, areas)}
        target = ann.objects[target_id]
        return sorted(
            iid for iid, obj in ann.objects.items()
            if iid in areas and iid not in named and obj.label == target.label and obj.name != target.name
        )  # fmt: skip

    @staticmethod
    def _malformed_point(
        rng: np.random.Generator, u: int, v: int, w: int, h: int, structured: bool, flag: bool = False
    ) -> str:
        """A malformed pointing answer; ``flag`` for the decision prompt's form (``target_visible``)."""
        head = {"target_visible": True} if flag else {}
        outside = json.dumps({**head, "point_2d": [w + 1 + int(rng.integers(w)), v]})
        if structured:
            return outside
        variants = (
            "I cannot determine a point in this image.",
            f'{{"point_2d": [{u}, ',
            '{"point_2d": "left"}',
            "The target is slightly to the left of the centre.",
            outside,
            '```json\n{"label": "target"}\n```',
        )
        return variants[int(rng.integers(len(variants)))]

    # -- monitoring -----------------------------------------------------------------------------
    def _monitor(self, prompt: MonitorPrompt, images: Sequence[VlmImage], structured: bool) -> str:
        m = self.model
        rng = keyed_rng(self.seed, "monitor", tuple(img.frame_id for img in images), prompt.subtask)
        u_malformed, u_variety, u_flip = rng.random(3)
        jitter = float(rng.normal(0.0, m.stop_jitter_m)) if m.stop_jitter_m > 0 else 0.0
        # completion is judged on the last leg's target (the leg rule of every prompt)
        legs = self._legs(prompt.subtask)
        seen = [self._leg_perceptions(legs, img)[-1] for img in images]
        latest = seen[-1]
        window = m.lost_window_frames
        if self._complete(prompt.subtask, latest, jitter, seen[:-1]):
            status = "STOP"
        elif len(seen) > window and not any(p.perceived for p in seen[-window:]) and any(p.perceived for p in seen[:-window]):
            status = "LOST"
        else:
            status = "CONTINUE"
        if u_flip < m.status_error_prob:
            others = [s for s in _STATUSES if s != status]
            status = others[int(rng.integers(2))]
        place = self._lost_place(seen, rng) if status == "LOST" else None
        if structured:
            return json.dumps({"status": status} if place is None else {"status": status, "last_seen": place})
        if u_malformed < m.malformed_prob:
            variants = ("The drone is still approaching the target.", "CONTINUE or STOP", "", "I am not sure.", "Status:")
            return variants[int(rng.integers(len(variants)))]
        answer = status if place is None else f"{status} {place}"
        if u_variety >= m.format_variety_prob:
            return answer
        variants = (f"**{answer}**", f"Status: {answer}.", answer.lower(), f"{answer}\n")
        return variants[int(rng.integers(len(variants)))]

    def _lost_place(self, seen: Sequence[Perception], rng: np.random.Generator) -> str:
        """Where a LOST says the target was last visible (monitoring, rule *Place*): the most
        recent earlier image in which it was perceived; with ``status_error_prob`` (or when no
        earlier image showed it: a LOST the status flip made up) another earlier image, drawn
        uniformly. Images are ``[first, *keyframes, latest]``; the latest is never named."""
        earlier = len(seen) - 1
        hits = [i for i in range(earlier) if seen[i].perceived]
        u_wrong = rng.random()
        index = hits[-1] if hits else None
        if index is None or (u_wrong < self.model.status_error_prob and earlier > 1):
            choices = [i for i in range(earlier) if i != index]
            index = choices[int(rng.integers(len(choices)))]
        return "first" if index == 0 else f"keyframe {index}"

    # -- baseline prompts: shared rules -----------------------------------------------------------
    def _close(self, per: Perception | None, jitter_m: float) -> bool:
        """The common stop rule: perceived and nearer than the (offset, jittered) stop distance."""
        m = self.model
        return bool(
            per is not None and per.perceived and per.region.median_depth_m < m.stop_distance_m + m.stop_offset_m + jitter_m
        )

    def _complete(self, text: str, per: Perception | None, jitter_m: float, earlier: Sequence[Perception] = ()) -> bool:
        """The completion rule of a text's last leg (monitoring STOP and every baseline's stop
        interface): the stop rule (:meth:`_close`); for a following text
        (:func:`vlm.following.follow_intent`) only when it follows *until the target stops*,
        the target stands still in this frame and was seen walking in an ``earlier`` frame of
        the same prompt (a prompt with one image cannot tell that a standing person has
        stopped). A following task without an end is never complete."""
        if not self._close(per, jitter_m):
            return False
        intent = follow_intent(text)
        if intent is None:
            return True
        return intent.until_stop and not per.moving and any(p.perceived and p.moving for p in earlier)

    @staticmethod
    def _legs(instruction: str) -> list[str]:
        """The instruction's legs: :func:`vlm.decompose.split_instruction`, with a leg that
        only closes the one before it (``then stop``, ``then land there``: words of
        :data:`vlm.decompose.CLOSING_ONLY_WORDS`) joined back to it, and a statement after the
        last step (``Where's the vending machine? I could really use a coffee.``:
        :func:`vlm.decompose.is_context`) left out: it is no step, and its words no target."""
        legs: list[str] = []
        for piece in split_instruction(instruction):
            if legs and set(words(piece)) <= CLOSING_ONLY_WORDS:
                legs[-1] = f"{legs[-1]} then {piece}"
            else:
                legs.append(piece)
        while len(legs) > 1 and is_context(legs[-1]):
            legs.pop()
        return legs

    def _leg_perceptions(self, legs: list[str], image: VlmImage) -> list[Perception]:
        """Perception of each leg's target; a leg whose first reference points back ("stop
        beside it, across from office 105") or naming nothing visible that refers back ("go to
        it", "stop there") means the object the previous leg names last."""
        out = []
        for k, leg in enumerate(legs):
            if k > 0 and opens_with_back_reference(leg):
                per = self.perceive(legs[k - 1], image, last_mention=True)
            else:
                per = self.perceive(leg, image)
                if per.named_id is None and k > 0 and _BACK_REFERENCES & set(words(leg)):
                    per = self.perceive(legs[k - 1], image, last_mention=True)
            out.append(per)
        return out

    def leg_target(self, instruction: str, image: VlmImage, jitter_m: float) -> LegTarget:
        """The memoryless leg rule of the baseline prompts (see :mod:`vlm.sim.error_model`)."""
        legs = self._legs(instruction)
        pers = self._leg_perceptions(legs, image)
        final = len(legs) - 1
        if pers[final].perceived:
            return LegTarget(final, pers[final], True, self._complete(instruction, pers[final], jitter_m))
        seen = [k for k, p in enumerate(pers) if p.perceived]

        def unseen(k: int) -> Perception | None:  # a leg to explore for: where its landmark is, if one shows
            return pers[k] if pers[k].hint is not None else None

        if not seen:
            return LegTarget(0, unseen(0), final == 0, False)
        j = max(seen)
        if self._close(pers[j], jitter_m):
            return LegTarget(j + 1, unseen(j + 1), j + 1 == final, False)
        return LegTarget(j, pers[j], False, False)

    def _aim(self, leg_text: str, image: VlmImage, per: Perception | None, rng: np.random.Generator, u_confuse: float):
        """Noisy pixel the model aims at: the perceived target (or a confused look-alike) or
        the exploration point. Returns ``(u, v, region_or_None)`` before rounding."""
        m = self.model
        ann: FrameAnnotation = image.annotation
        w, _ = image.size
        if per is not None and per.perceived:
            region = self._pointed(leg_text, ann, per.region, rng, u_confuse)
            u0, v0 = anchor_pixel(region.mask)
            sigma = m.pixel_sigma_px(w, region.median_depth_m)
        else:
            region = None
            hint = self._pointed(leg_text, ann, None if per is None else per.hint, rng, u_confuse)
            u0, v0 = exploration_point(ann.depth_m) if hint is None else anchor_pixel(hint.mask)
            sigma = m.pixel_sigma_px(w, 0.0)
        du, dv = rng.normal(0.0, sigma, 2) if sigma > 0 else (0.0, 0.0)
        return u0 + du, v0 + dv, region

    # -- See-Point-Fly ------------------------------------------------------------------------------
    def _spf(self, prompt: SpfPrompt, image: VlmImage, structured: bool) -> str:
        m = self.model
        rng = keyed_rng(self.seed, "spf", image.frame_id, prompt.instruction)
        u_malformed, u_variety, u_confuse = rng.random(3)
        jitter = float(rng.normal(0.0, m.stop_jitter_m)) if m.stop_jitter_m > 0 else 0.0
        w, h = image.size
        tgt = self.leg_target(prompt.instruction, image, jitter)
        legs = self._legs(prompt.instruction)
        uf, vf, region = self._aim(legs[min(tgt.leg, len(legs) - 1)], image, tgt.perception, rng, u_confuse)
        u = int(np.clip(round(uf), 0, w - 1))
        v = int(np.clip(round(vf), 0, h - 1))
        if tgt.reached:
            depth = 0
        elif region is not None:
            depth = int(np.clip(round(region.median_depth_m), 1, SPF_MAX_DEPTH_M))
        else:
            depth = _open_depth(image.annotation.depth_m, u, v)
        if u_malformed < m.malformed_prob:
            return self._malformed_point(rng, u, v, w, h, structured)
        plain = json.dumps({"point_2d": [u, v], "depth": depth})
        if structured or u_variety >= m.format_variety_prob:
            return plain
        variants = (f"```json\n{plain}\n```", f"Next waypoint: {plain}")
        return variants[int(rng.integers(len(variants)))]

    # -- PIVOT --------------------------------------------------------------------------------------
    def _pivot(self, prompt: PivotPrompt, image: VlmImage, structured: bool) -> str:
        m = self.model
        # the model's belief about the frame (target pixel, stop) is one draw per frame and
        # instruction; only the output-format draws change with the arrows shown
        belief = keyed_rng(self.seed, "pivot-belief", image.frame_id, prompt.instruction)
        u_confuse = belief.random()
        jitter = float(belief.normal(0.0, m.stop_jitter_m)) if m.stop_jitter_m > 0 else 0.0
        call = keyed_rng(self.seed, "pivot", image.frame_id, prompt.instruction, prompt.arrows, prompt.n_pick)
        u_malformed, u_variety = call.random(2)
        tgt = self.leg_target(prompt.instruction, image, jitter)
        if tgt.reached:
            text = json.dumps({"stop": True})
        else:
            legs = self._legs(prompt.instruction)
            uf, vf, _ = self._aim(legs[min(tgt.leg, len(legs) - 1)], image, tgt.perception, belief, u_confuse)
            ends = np.array([[a[1], a[2]] for a in prompt.arrows], float)
            dist = np.hypot(ends[:, 0] - uf, ends[:, 1] - vf)
            order = np.lexsort((np.array([a[0] for a in prompt.arrows]), dist))
            text = json.dumps({"arrows": [int(prompt.arrows[i][0]) for i in order[: prompt.n_pick]]})
        if u_malformed < m.malformed_prob:
            undrawn = max(a[0] for a in prompt.arrows) + 1 + int(call.integers(5))
            if structured:
                return json.dumps({"arrows": [undrawn]})
            variants = (
                "I would take the arrow that points toward the target.",
                '{"arrows": [',
                '{"arrow": "left"}',
                json.dumps({"arrows": [undrawn]}),
                "",
            )
            return variants[int(call.integers(len(variants)))]
        if structured or u_variety >= m.format_variety_prob:
            return text
        variants = (f"```json\n{text}\n```", f"Best arrows: {text}")
        return variants[int(call.integers(len(variants)))]

    # -- TypeFly ------------------------------------------------------------------------------------
    def _typefly(self, prompt: TypeflyPrompt, image: VlmImage) -> str:
        m = self.model
        rng = keyed_rng(self.seed, "typefly", image.frame_id, prompt.instruction, prompt.objects, prompt.history)
        u_malformed, u_confuse = rng.random(2)
        jitter = float(rng.normal(0.0, m.stop_jitter_m)) if m.stop_jitter_m > 0 else 0.0
        legs = self._legs(prompt.instruction)
        final = len(legs) - 1
        # "reached" is judged on the frame (common stop rule); where things are comes from the
        # detector's scene description only
        reached = self._leg_perceptions(legs, image)
        detected = _detected_per_leg(legs, prompt.objects, image.annotation)
        if self._complete(prompt.instruction, reached[final], jitter):
            program = "stop"
        else:
            seen = [k for k, d in enumerate(detected) if d is not None]
            target = None
            if detected[final] is not None:
                target = final
            elif seen and not self._close(reached[max(seen)], jitter):
                target = max(seen)
            if target is not None:
                obj = detected[target]
                same = [o for o in prompt.objects if o.label == obj.label and o.name != obj.name]
                if same and u_confuse < m.confusion_prob:
                    obj = same[int(rng.integers(len(same)))]
                program = f"approach {obj.name}"
            else:
                nxt = max(seen) + 1 if seen else _first_unapproached(legs, prompt.history)
                phrase = _skill_text(legs[min(nxt, final)])
                failed = bool(prompt.history) and prompt.history[-1] == f"find {phrase}: not found"
                program = f"move_forward {TYPEFLY_EXPLORE_M:g}; find {phrase}" if failed else f"find {phrase}"
        if u_malformed < m.malformed_prob:
            variants = ("I will fly toward the target now.", "approach", "fly_to target; stop", "find;", "")
            return variants[int(rng.integers(len(variants)))]
        return program

    # -- decomposition --------------------------------------------------------------------------
    def _decompose(self, prompt: DecomposePrompt, structured: bool) -> str:
        m = self.model
        rng = keyed_rng(self.seed, "decompose", prompt.instruction)
        u_malformed, u_variety = rng.random(2)
        parts = split_instruction(prompt.instruction)
        merged = [parts[0]]
        for p in parts[1:]:
            if rng.random() < m.merge_prob:
                merged[-1] = f"{merged[-1]} then {p}"
            else:
                merged.append(p)
        plain = json.dumps(merged)
        if structured:
            return plain
        if u_malformed < m.malformed_prob:
            variants = ("Sure! Here are the subtasks:", f'["{merged[0][:20]}", ', "[]", '{"subtasks": []}')
            return variants[int(rng.integers(len(variants)))]
        if u_variety < m.format_variety_prob:
            return f"```json\n{plain}\n```"
        return plain

    # -- latency and usage ----------------------------------------------------------------------
    def _tokens(self, segment: str, images: dict[str, VlmImage]) -> int:
        lat = self.latency
        if segment.startswith("\x00image:"):
            w, h = images[segment[len("\x00image:") :]].size
            return math.ceil(w / lat.image_token_px) * math.ceil(h / lat.image_token_px) + 2
        if segment == "\x00end":
            return 1
        return math.ceil(len(segment) / lat.chars_per_token)

    def _respond(
        self,
        prompt: DecisionPrompt | MonitorPrompt | DecomposePrompt | SpfPrompt | PivotPrompt | TypeflyPrompt,
        images: Sequence[VlmImage],
        segments: tuple[str, ...],
        text: str,
        deadline_s: float | None,
        max_new_tokens: int,
        cache_key: str | None,
    ) -> VlmResponse:
        """Charge the modelled latency, account tokens, apply the deadline and the token cap."""
        by_id = {img.frame_id: img for img in images}
        with self._lock:
            previous = self._prefix.get(cache_key, ()) if cache_key is not None else ()
        shared = 0
        for a, b in zip(segments, previous):
            if a != b:
                break
            shared += 1
        prompt_tokens = sum(self._tokens(s, by_id) for s in segments)
        cached_tokens = sum(self._tokens(s, by_id) for s in segments[:shared])
        if isinstance(prompt, (DecisionPrompt, SpfPrompt, PivotPrompt, TypeflyPrompt)):
            latency_s = self.latency.decision_s
        elif isinstance(prompt, MonitorPrompt):
            cached_images = sum(1 for s in segments[:shared] if s.startswith("\x00image:"))
            latency_s = self.latency.monitor_s(len(images), cached_images)
        else:
            latency_s = self.latency.decompose_s
        if deadline_s is not None and latency_s > deadline_s:
            return VlmResponse(
                CallStatus.TIMEOUT,
                latency_s=float(max(deadline_s, 0.0)),
                error=f"modelled latency {latency_s:.2f} s exceeds the deadline {deadline_s:.2f} s",
            )
        max_chars = int(max(max_new_tokens, 0) * self.latency.chars_per_token)
        if len(text) > max_chars:
            text = text[:max_chars]
        if cache_key is not None:
            with self._lock:
                self._prefix[cache_key] = segments
        usage = Usage(
            prompt_tokens=prompt_tokens,
            completion_tokens=min(math.ceil(len(text) / self.latency.chars_per_token), max(max_new_tokens, 0)),
            cached_tokens=cached_tokens,
        )
        return VlmResponse(CallStatus.OK, text=text, usage=usage, latency_s=float(latency_s))


def _open_depth(depth_m: np.ndarray, u: int, v: int, half_px: int = 4) -> int:
    """Travel distance toward open space at ``(u, v)``: the median z-depth of readings in a
    small window, whole metres in ``[1, SPF_MAX_DEPTH_M]``; no reading counts as far."""
    h, w = depth_m.shape
    win = np.asarray(depth_m[max(v - half_px, 0) : v + half_px + 1, max(u - half_px, 0) : u + half_px + 1], float)
    vals = win[np.isfinite(win) & (win > 0)]
    if vals.size == 0:
        return SPF_MAX_DEPTH_M
    return int(np.clip(round(float(np.median(vals))), 1, SPF_MAX_DEPTH_M))


def scene_objects_as_visible(
    objects: Sequence[SceneObject], annotation: FrameAnnotation | None = None
) -> tuple[dict[int, VisibleObject], dict[int, int]]:
    """A scene description as grounding input: pseudo instance ids 1..n and box areas (in
    ten-thousandths of the image) as the visible areas. With ``annotation``, a detection whose
    name an object of the frame has gets that object's aliases and target flag (the model's
    knowledge of synonyms and of what is structure; it adds no object and no position)."""
    known: dict[str, tuple[tuple[str, ...], bool]] = {}
    if annotation is not None:
        for obj in annotation.objects.values():
            known.setdefault(obj.name, (tuple(obj.aliases), obj.target))
    objs = {
        k + 1: VisibleObject(k + 1, o.name, o.label, *known.get(o.name, ((), True))) for k, o in enumerate(objects)
    }
    areas = {k + 1: max(1, int(round(o.w * o.h * 1e4))) for k, o in enumerate(objects)}
    return objs, areas


def _detected_per_leg(
    legs: list[str], objects: Sequence[SceneObject], annotation: FrameAnnotation | None
) -> list[SceneObject | None]:
    """The detection each leg names (grounding rule), with the back-reference rule of the legs."""
    objs, areas = scene_objects_as_visible(objects, annotation)
    out: list[SceneObject | None] = []
    for k, leg in enumerate(legs):
        matches = [] if k > 0 and opens_with_back_reference(leg) else [m for m in ground(leg, objs, areas) if not m.locates]
        if not matches and k > 0 and _BACK_REFERENCES & set(words(leg)):
            matches = sorted((m for m in ground(legs[k - 1], objs, areas) if not m.locates), key=_mention_end, reverse=True)
        out.append(objects[matches[0].instance_id - 1] if matches else None)
    return out


def _mention_end(m) -> tuple[int, int]:
    """Order of mentions by where they end, then by length: the last-named object is the
    greatest (``the white delivery van`` ends where a bare ``van`` label match does, and is
    longer)."""
    return (m.start + m.n_words, m.n_words)


def _leg_names_target(legs: list[str], k: int) -> bool:
    """Whether leg ``k`` names something to reach (:func:`vlm.sim.grounding.names_target`); a
    leg that refers back ("stop next to it") names the previous leg's target."""
    if k > 0 and opens_with_back_reference(legs[k]):
        return names_target(legs[k - 1])
    if names_target(legs[k]):
        return True
    return k > 0 and bool(_BACK_REFERENCES & set(words(legs[k]))) and names_target(legs[k - 1])


def _skill_text(text: str) -> str:
    """A leg as a skill argument: one line without the program separator."""
    return " ".join(text.replace(";", " ").split())


def _first_unapproached(legs: list[str], history: Sequence[str]) -> int:
    """Index of the first leg whose target no ``approach <name>: done`` entry names."""
    approached = set()
    for item in history:
        if item.startswith("approach ") and item.endswith(": done"):
            name = item[len("approach ") : -len(": done")]
            objs = {1: VisibleObject(1, name, name.split()[-1] if name.split() else name)}
            for k, leg in enumerate(legs):
                if ground(leg, objs, {1: 1}):
                    approached.add(k)
    for k in range(len(legs)):
        if k not in approached:
            return k
    return len(legs) - 1
