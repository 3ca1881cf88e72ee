"""PIVOT-style baseline: iterative visual prompting over candidate motions drawn as arrows.

After PIVOT (Nasiriany et al. 2024): per decision, candidate actions are sampled from a
Gaussian, drawn on the camera image as numbered arrows, and the VLM picks the best ones; the
Gaussian is refitted around the picks and the loop repeats for a few iterations; the final
mean is executed as a short step, then the loop starts again on a new frame.

Action space: a flight direction relative to the camera at the decision frame, ``(a, e)``:
azimuth ``a`` (radians, positive = left) and elevation ``e`` (radians, positive = up), kept
inside the camera's field of view so every arrow can be drawn. The step length is fixed
(``step_m``): a pinhole image cannot show distance along a ray, so arrows encode direction
only. An arrow runs from the bottom centre of the image to the projection of its direction.
The candidates' numbers *and* endpoint pixels also go into the prompt text, as a real PIVOT
implementation's annotations would be read off the image by the model (the simulated VLM reads
them there; see :mod:`vlm.sim.error_model`).

Refit: mean and standard deviation of the picked candidates' ``(a, e)`` (std floored at
``min_std_rad``); an iteration whose answer does not parse, or names no drawn arrow, leaves
the distribution as it was. Defaults as in PIVOT: 3 iterations x 8 candidates; the model picks
up to 3. The vehicle hovers while it deliberates (3 calls, each charged its latency), then
flies the step in a straight line (no map). ``{"stop": true}`` ends the episode (the stop
interface the OnFly paper added).
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from onfly.baselines.common import (
    BaselineOptionError,
    CallOutcome,
    FlightLimits,
    PlanMemory,
    Arrival,
    split_options,
    straight_plan,
    vlm_image,
)
from onfly.bench.method import EpisodeSpec, MethodStep
from onfly.observation import Observation
from planning.camera import PinholeCamera
from planning.trajectory import VehicleState
from vlm.factory import make_backend
from vlm.prompts import build_pivot_prompt, pivot_schema
from vlm.types import CallStatus, VlmBackend

__all__ = ["PivotConfig", "PivotMethod", "Candidates", "sample_candidates", "directions_cam", "draw_arrows",
           "parse_pivot_answer", "PivotAnswer", "refit", "make_pivot"]  # fmt: skip

log = logging.getLogger(__name__)

PIVOT = "pivot"


@dataclass(frozen=True)
class PivotConfig:
    """PIVOT parameters.

    n_candidates, n_iterations, n_pick : arrows per iteration, iterations per decision, picks asked
    step_m : length of the executed step, metres
    init_std_az_rad, init_std_el_rad : initial spread of azimuth and elevation, radians
    min_std_rad : floor of the refitted std, radians
    fov_margin : fraction of the half field of view candidates may use (keeps arrows in view)
    step_timeout_s : a step not finished after this long is abandoned
    structured_output : ask the backend for schema-constrained JSON
    """

    n_candidates: int = 8
    n_iterations: int = 3
    n_pick: int = 3
    step_m: float = 2.0
    init_std_az_rad: float = 0.4
    init_std_el_rad: float = 0.12
    min_std_rad: float = 0.03
    fov_margin: float = 0.9
    step_timeout_s: float = 15.0
    structured_output: bool = False

    def __post_init__(self) -> None:
        for name in ("n_candidates", "n_iterations", "n_pick"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise BaselineOptionError(f"PivotConfig.{name} must be an int >= 1, got {v!r}")
        if self.n_pick > self.n_candidates:
            raise BaselineOptionError(f"PivotConfig.n_pick ({self.n_pick}) must not exceed n_candidates ({self.n_candidates})")
        for name in ("step_m", "init_std_az_rad", "init_std_el_rad", "min_std_rad", "step_timeout_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
                raise BaselineOptionError(f"PivotConfig.{name} must be a finite number > 0, got {v!r}")
        if not 0.0 < self.fov_margin <= 1.0:
            raise BaselineOptionError(f"PivotConfig.fov_margin must be in (0, 1], got {self.fov_margin}")


@dataclass(frozen=True, eq=False)
class Candidates:
    """One iteration's candidates.

    az_el : array (k, 2), radians (azimuth left-positive, elevation up-positive)
    end_uv : array (k, 2), endpoint pixels of the arrows
    labels : tuple of int, the numbers drawn (1..k)
    """

    az_el: np.ndarray
    end_uv: np.ndarray
    labels: tuple[int, ...]


def directions_cam(az_el: np.ndarray) -> np.ndarray:
    """Unit directions in the camera optical frame (x right, y down, z forward), shape (k, 3),
    for azimuth (left-positive) and elevation (up-positive), radians, shape (k, 2)."""
    a, e = np.asarray(az_el, float).T
    return np.stack([-np.sin(a) * np.cos(e), -np.sin(e), np.cos(a) * np.cos(e)], axis=-1)


def _limits(camera: PinholeCamera, margin: float) -> tuple[float, float]:
    """Largest |azimuth| and |elevation| whose arrows stay inside the image, radians."""
    az = math.atan((camera.width / 2.0 - 1.0) / camera.fx) * margin
    el = math.atan((camera.height / 2.0 - 1.0) / camera.fy) * margin
    return az, el


def sample_candidates(
    rng: np.random.Generator, mean: np.ndarray, std: np.ndarray, k: int, camera: PinholeCamera, fov_margin: float
) -> Candidates:
    """``k`` directions from N(mean, diag(std^2)) clipped into the field of view, with their
    arrow endpoints on ``camera``'s image."""
    az_max, el_max = _limits(camera, fov_margin)
    s = rng.normal(mean, std, size=(k, 2))
    s[:, 0] = np.clip(s[:, 0], -az_max, az_max)
    # the image row of a direction is cy - fy * tan(e) / cos(a): at azimuth a the elevation
    # limit shrinks to atan(cos(a) * tan(el_max)) so every endpoint stays in the image
    el_lim = np.arctan(np.cos(s[:, 0]) * math.tan(el_max))
    s[:, 1] = np.clip(s[:, 1], -el_lim, el_lim)
    uv, _ = camera.project(directions_cam(s))
    return Candidates(s, uv, tuple(range(1, k + 1)))


def arrow_origin(camera: PinholeCamera) -> tuple[int, int]:
    """Where every arrow starts: the bottom centre of the image, pixels."""
    return int(round((camera.width - 1) / 2.0)), camera.height - 1


def draw_arrows(rgb: np.ndarray, cand: Candidates, camera: PinholeCamera) -> np.ndarray:
    """A copy of ``rgb`` (H, W, 3) uint8 with the numbered arrows drawn (the input is untouched)."""
    out = np.ascontiguousarray(rgb).copy()
    origin = arrow_origin(camera)
    scale = max(camera.width / 640.0, 0.3)
    thick = max(1, int(round(2 * scale)))
    for label, (u, v) in zip(cand.labels, cand.end_uv):
        end = (int(round(u)), int(round(v)))
        cv2.arrowedLine(out, origin, end, (255, 255, 255), thick + 1, cv2.LINE_AA, tipLength=0.08)
        cv2.arrowedLine(out, origin, end, (220, 30, 30), thick, cv2.LINE_AA, tipLength=0.08)
        org = (min(max(end[0] + 3, 0), camera.width - 12), min(max(end[1] - 3, 10), camera.height - 2))
        cv2.putText(out, str(label), org, cv2.FONT_HERSHEY_SIMPLEX, 0.45 * scale * 2, (255, 255, 255), thick + 1, cv2.LINE_AA)
        cv2.putText(out, str(label), org, cv2.FONT_HERSHEY_SIMPLEX, 0.45 * scale * 2, (20, 20, 20), thick, cv2.LINE_AA)
    return out


@dataclass(frozen=True)
class PivotAnswer:
    """A parsed PIVOT answer: ``stop``, or ``picks`` (drawn labels, best first), or a failure."""

    ok: bool
    stop: bool = False
    picks: tuple[int, ...] = ()
    reason: str = ""


def parse_pivot_answer(text: str, labels: tuple[int, ...]) -> PivotAnswer:
    """Read ``{"arrows": [...]}`` or ``{"stop": true}`` (code fences and prose around the JSON
    tolerated). Numbers that were not drawn are dropped; none left is a failure."""
    if not isinstance(text, str):
        return PivotAnswer(False, reason=f"text must be str, got {type(text).__name__}")
    start = text.find("{")
    end = text.rfind("}")
    if start < 0 or end <= start:
        return PivotAnswer(False, reason="no JSON object")
    try:
        value = json.loads(text[start : end + 1])
    except json.JSONDecodeError as exc:
        return PivotAnswer(False, reason=f"bad JSON: {exc.msg}")
    if not isinstance(value, dict):
        return PivotAnswer(False, reason="not a JSON object")
    if value.get("stop") is True:
        return PivotAnswer(True, stop=True)
    arrows = value.get("arrows")
    if not isinstance(arrows, list):
        return PivotAnswer(False, reason="no 'arrows' list")
    drawn = set(labels)
    picks = []
    for a in arrows:
        if isinstance(a, bool) or not isinstance(a, (int, float)) or int(a) != a:
            continue
        if int(a) in drawn and int(a) not in picks:
            picks.append(int(a))
    if not picks:
        return PivotAnswer(False, reason="no drawn arrow chosen")
    return PivotAnswer(True, picks=tuple(picks))


def refit(cand: Candidates, picks: tuple[int, ...], min_std: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian (mean (2,), std (2,)) of the picked candidates' (azimuth, elevation)."""
    idx = [cand.labels.index(p) for p in picks]
    chosen = cand.az_el[idx]
    mean = chosen.mean(axis=0)
    std = np.maximum(chosen.std(axis=0), min_std)
    return mean, std


class PivotMethod:
    """The PIVOT-style baseline (module docstring).

    Parameters
    ----------
    vlm_spec : backend spec; config : PivotConfig; limits : FlightLimits
    backend : a VLM backend to use instead of building one from ``vlm_spec`` per episode
    """

    name = "pivot"
    privileged = False

    def __init__(self, vlm_spec: str, config: PivotConfig, limits: FlightLimits, backend: VlmBackend | None = None) -> None:
        self.vlm_spec = vlm_spec
        self._backend = backend
        self.config = config
        self.limits = limits

    def reset(self, spec: EpisodeSpec) -> None:
        self.plans = PlanMemory()  # straight-line plans start from the last one's reference
        self.arrival = Arrival()
        self.spec = spec
        self.backend = self._backend if self._backend is not None else make_backend(self.vlm_spec, seed=spec.seed)
        self.runtime = spec.runtime
        self.rng = np.random.default_rng([spec.seed, 0x9170])
        self.latest: Observation | None = None
        self.hold_p = spec.start_state.p.copy()
        self.hold_yaw = float(spec.start_state.yaw)
        self.frame: Observation | None = None  # the frame being deliberated on
        self.iteration = 0
        self.mean = np.zeros(2)
        self.std = np.array([self.config.init_std_az_rad, self.config.init_std_el_rad])
        self.refits = 0
        self.goal: np.ndarray | None = None
        self.goal_t_s = 0.0
        self.next_after_s = -math.inf
        self.stats: Counter = Counter()
        #: per decision: the (mean, std) after each iteration (for tests and summaries)
        self.trace: list[list[tuple[np.ndarray, np.ndarray]]] = []
        self.last_drawn: np.ndarray | None = None

    # -- the loop ---------------------------------------------------------------------------------
    def step(self, t_s: float, state: VehicleState, obs: Observation | None) -> MethodStep:
        if obs is not None:
            self.latest = obs
        for landed in self.runtime.poll():
            if self._on_answer(landed.outcome, state):
                return MethodStep(None, True, {"stop": True})
        if self.goal is not None:
            if self.arrival(t_s, state, self.goal, self.plans.last) or t_s - self.goal_t_s > self.config.step_timeout_s:
                self.stats["steps"] += 1
                self.hold_p = state.p.copy()
                self.hold_yaw = float(state.yaw)
                self.goal = None
                self.next_after_s = t_s
            else:
                return MethodStep(straight_plan(state, self.goal, self.limits, memory=self.plans), False)
        if self.frame is None and not self.runtime.busy(PIVOT):
            obs = self.latest
            if obs is not None and obs.t_s >= self.next_after_s - 1e-9:
                self._begin(obs)
        return MethodStep(straight_plan(state, self.hold_p, self.limits, yaw_ref=self.hold_yaw, memory=self.plans), False)

    def _begin(self, obs: Observation) -> None:
        self.frame = obs
        self.iteration = 0
        self.mean = np.zeros(2)
        self.std = np.array([self.config.init_std_az_rad, self.config.init_std_el_rad])
        self.refits = 0
        self.trace.append([])
        self.stats["decisions"] += 1
        self._ask()

    def _ask(self) -> None:
        c, obs = self.config, self.frame
        cand = sample_candidates(self.rng, self.mean, self.std, c.n_candidates, obs.camera, c.fov_margin)
        drawn = draw_arrows(obs.rgb, cand, obs.camera)
        self.last_drawn = drawn
        arrows = [(lab, float(u), float(v)) for lab, (u, v) in zip(cand.labels, cand.end_uv)]
        messages, images = build_pivot_prompt(self.spec.instruction, vlm_image(obs, drawn), arrows, c.n_pick)
        backend, schema = self.backend, pivot_schema() if c.structured_output else None
        self.stats["calls"] += 1

        def call() -> CallOutcome:
            return CallOutcome(PIVOT, obs.frame_id, backend.complete(messages, images, json_schema=schema, max_new_tokens=32), cand)

        self.runtime.submit(PIVOT, call)

    def _on_answer(self, out, state: VehicleState) -> bool:
        """Apply one landed answer; True when the model said stop."""
        c = self.config
        if not isinstance(out, CallOutcome):
            log.error("PIVOT call raised: %r", out)
            self.stats["call_errors"] += 1
            ans = PivotAnswer(False, reason="call raised")
        elif out.response.status is not CallStatus.OK:
            ans = PivotAnswer(False, reason=out.response.status.value)
        else:
            ans = parse_pivot_answer(out.response.text, out.payload.labels)
        if ans.stop:
            self.stats["stop"] += 1
            return True
        if ans.ok:
            self.mean, self.std = refit(out.payload, ans.picks, c.min_std_rad)
            self.refits += 1
        else:
            self.stats["unreadable"] += 1
        self.trace[-1].append((self.mean.copy(), self.std.copy()))
        self.iteration += 1
        if self.iteration < c.n_iterations:
            self._ask()
            return False
        # decision made: fly the final mean direction for one step, from the decision frame
        obs = self.frame
        self.frame = None
        if self.refits == 0:
            self.stats["no_decision"] += 1
            self.next_after_s = obs.t_s + 1e-6  # try again on a newer frame
            return False
        d_world = obs.T_world_cam[:3, :3] @ directions_cam(self.mean[None])[0]
        self.goal = state.p + c.step_m * d_world
        self.goal_t_s = state.t_s
        self.arrival.reset()
        return False

    def summary(self) -> dict[str, Any]:
        return {k: int(v) for k, v in self.stats.items()}


def make_pivot(vlm_spec: str, seed: int, **options) -> PivotMethod:
    """Registry factory. Options: the shared ``planner`` table (limits), ``esdf`` / ``verifier``
    (accepted, unused: no map) and :class:`PivotConfig` fields."""
    planner, _, cfg = split_options(options, PivotConfig, "pivot")
    return PivotMethod(vlm_spec, cfg, FlightLimits.from_planner(planner))
