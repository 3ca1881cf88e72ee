"""SimulatedVlm: a :class:`vlm.types.VlmBackend` that answers OnFly's prompts from annotations.

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

from vlm.decompose import split_instruction
from vlm.prompts import (
    DecisionPrompt,
    DecomposePrompt,
    MonitorPrompt,
    PromptError,
    parse_prompt,
    prompt_segments,
)
from vlm.sim.error_model import ErrorModel, ErrorModelError, LatencyModel, get_preset
from vlm.sim.features import keyed_rng, synthetic_features
from vlm.sim.grounding import Region, anchor_pixel, exploration_point, ground, region_of, visible_regions
from vlm.types import (
    CallStatus,
    ChatMessage,
    FrameAnnotation,
    Usage,
    VisionFeatures,
    VlmImage,
    VlmResponse,
)

__all__ = ["SimulatedVlm", "Perception"]

log = logging.getLogger(__name__)

_STATUSES = ("CONTINUE", "STOP", "LOST")


@dataclass(frozen=True)
class Perception:
    """What the simulated VLM perceives of the subtask's target in one frame.

    Attributes
    ----------
    named_id : int or None, best visible object the subtask names (None: none is visible)
    region : Region of that object, or None
    perceived : bool, False if there is none or it was missed
    small, far : bool, the miss conditions that applied
    """

    named_id: int | None
    region: Region | None
    perceived: bool
    small: bool = False
    far: bool = False


class SimulatedVlm:
    """Simulated VLM backend (see :mod:`vlm.sim.error_model` for everything it does).

    Parameters
    ----------
    preset : name of a preset in :data:`vlm.sim.error_model.PRESETS`, or an ErrorModel
    seed : int, the root of every random draw
    latency : LatencyModel (defaults: the paper's Jetson Orin NX numbers)
    feature_dim, patch_px : size of the synthetic features (:mod:`vlm.sim.features`)
    """

    def __init__(
        self,
        preset: str | ErrorModel = "nominal",
        seed: int = 0,
        *,
        latency: LatencyModel | None = None,
        feature_dim: int = 64,
        patch_px: int = 16,
    ) -> None:
        self.model = preset if isinstance(preset, ErrorModel) else get_preset(preset)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise ErrorModelError(f"seed must be an int, got {seed!r}")
        if feature_dim < 2 or patch_px < 1:
            raise ErrorModelError(f"feature_dim must be >= 2 and patch_px >= 1, got {feature_dim}, {patch_px}")
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
        """Synthetic patch features (:mod:`vlm.sim.features`); None for a frame without annotation."""
        if image.annotation is None:
            log.debug("frame %s has no annotation: no simulated features", image.frame_id)
            return None
        return synthetic_features(image.annotation, image.frame_id, seed=self.seed, dim=self.feature_dim, patch_px=self.patch_px)

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
        else:
            text = self._decompose(prompt, structured)
        return self._respond(prompt, images, segments, text, deadline_s, max_new_tokens, cache_key)

    # -- checks ---------------------------------------------------------------------------------
    @staticmethod
    def _check_images(prompt: object, images: Sequence[VlmImage]) -> str:
        if isinstance(prompt, DecisionPrompt) and len(images) != 1:
            return f"decision prompt needs 1 image, got {len(images)}"
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
    def perceive(self, subtask: str, image: VlmImage) -> Perception:
        """The target the subtask names in this frame, and whether it is perceived.

        The miss draw is keyed on (seed, frame id, instance id), so one frame is perceived the
        same way in every call.
        """
        ann: FrameAnnotation = image.annotation  # checked by the caller
        areas = visible_regions(ann)
        matches = ground(subtask, ann.objects, areas)
        if not matches:
            return Perception(None, None, False)
        iid = matches[0].instance_id
        region = region_of(ann, iid)
        w, h = image.size
        small = region.area_px < self.model.small_target_frac * w * h
        far = math.isfinite(region.median_depth_m) and region.median_depth_m > self.model.far_target_m
        rng = keyed_rng(self.seed, "miss", image.frame_id, iid)
        u_small, u_far = rng.random(2)
        missed = (small and u_small < self.model.miss_prob_small) or (far and u_far < self.model.miss_prob_far)
        return Perception(iid, region, not missed, small, far)

    # -- decision -------------------------------------------------------------------------------
    def _decide(self, prompt: DecisionPrompt, image: VlmImage, structured: bool) -> str:
        m = self.model
        rng = keyed_rng(self.seed, "decision", image.frame_id, prompt.subtask, prompt.history_uv)
        u_malformed, u_variety, u_confuse = rng.random(3)
        ann: FrameAnnotation = image.annotation
        w, h = image.size
        per = self.perceive(prompt.subtask, image)
        label_name = ""
        if per.perceived:
            region = per.region
            lookalikes = self._lookalikes(prompt.subtask, ann, per.named_id)
            if lookalikes and u_confuse < m.confusion_prob:
                region = region_of(ann, lookalikes[int(rng.integers(len(lookalikes)))])
            label_name = ann.objects[region.instance_id].name
            u0, v0 = anchor_pixel(region.mask)
            sigma = m.pixel_sigma_px(w, region.median_depth_m)
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
            return self._malformed_point(rng, u, v, w, h, structured)
        plain = json.dumps({"point_2d": [u, v]})
        if structured or u_variety >= m.format_variety_prob:
            return plain
        variants = (
            f"```json\n{plain}\n```",
            f"The target is here: {plain}",
            json.dumps([{"point_2d": [u, v], "label": label_name or "waypoint"}]),
        )
        return variants[int(rng.integers(len(variants)))]

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
    def _malformed_point(rng: np.random.Generator, u: int, v: int, w: int, h: int, structured: bool) -> str:
        outside = json.dumps({"point_2d": [w + 1 + int(rng.integers(w)), v]})
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
        seen = [self.perceive(prompt.subtask, img) for img in images]
        latest = seen[-1]
        window = m.lost_window_frames
        if latest.perceived and latest.region.median_depth_m < m.stop_distance_m + m.stop_offset_m + jitter:
            status = "STOP"
        elif len(seen) > window and not any(p.perceived for p in seen[-window:]) and any(p.perceived for p in seen[:-window]):
            status = "LOST"
        else:
            status = "CONTINUE"
        if u_flip < m.status_error_prob:
            others = [s for s in _STATUSES if s != status]
            status = others[int(rng.integers(2))]
        if structured:
            return json.dumps({"status": status})
        if u_malformed < m.malformed_prob:
            variants = ("The drone is still approaching the target.", "CONTINUE or STOP", "", "I am not sure.", "Status:")
            return variants[int(rng.integers(len(variants)))]
        if u_variety >= m.format_variety_prob:
            return status
        variants = (f"**{status}**", f"Status: {status}.", status.lower(), f"{status}\n")
        return variants[int(rng.integers(len(variants)))]

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
        prompt: DecisionPrompt | MonitorPrompt | DecomposePrompt,
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
        if isinstance(prompt, DecisionPrompt):
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
