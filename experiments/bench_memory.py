"""Benchmark of the monitoring memories: prefix stability and KV-cache reuse on a real model.

Seeded long synthetic episodes: a drone flies a polyline of ``--path-min-m``..``--path-max-m``
(default 60-120 m) with turns of 30-120 deg at the paper's ``v_max`` (0.6 m/s), hovering 0-4 s
at each corner (waiting for a VLM) and turning in place at the paper's yaw rate (0.4 rad/s),
2 m above the ground, through a seeded field of textured, coloured pillars on a tiled ground.
A 224 x 160 RGB camera (90 x 60 deg FOV) renders a frame every 0.5 s (pure numpy ray casting,
content changes with position and heading; per-frame sensor noise so hovering gives
near-duplicates, not identical frames). Each frame's de-duplication descriptor is the one the
pilot uses without backend features, :func:`onfly.agents.global_descriptor` (a mean-subtracted
16 x 12 grey thumbnail). Every 2 s there is a monitoring call. Each strategy (``hybrid``,
``sliding``, ``time``; :func:`onfly.memory.make_memory`, S = 4) observes every frame.

Reported per strategy:

* ``prefix_stable_rate_<s>``: over every monitoring call of every episode except each
  episode's first, the fraction whose frame-id list ``[o_1, Q_t, o_t]`` starts with the
  previous call's list minus its latest frame (i.e. ``o_1`` and ``Q_t`` unchanged);
* with a tiny random-weight Qwen-VL (:func:`vlm.tiny_models.build_tiny_vlm`) in-process on the
  CPU (:class:`vlm.backend_transformers.TransformersBackend`, one backend and one ``cache_key``
  stream per strategy, the real monitoring prompt :func:`vlm.prompts.build_monitor_prompt` with
  the memory's images), over the last ``--calls`` monitoring calls of each episode (a
  contiguous run, so each call can reuse the previous call's cache; the first call of the run
  starts cold and is left out of both numbers):
  - ``cached_token_fraction_<s>``: sum of ``Usage.cached_tokens`` / sum of prompt tokens;
  - ``monitor_ms_median_<s>``: wall time of ``complete()`` (vision encoding of frames not yet
    in the backend's image cache, the uncached prefill, ``--max-new-tokens`` greedy tokens);
  - ``latency_ratio_sliding_over_hybrid`` = ``monitor_ms_median_sliding / monitor_ms_median_hybrid``.
  Calls of the streams are interleaved (rotating order) so machine load hits all alike.
  References in the same run (``--no-reference`` skips them): ``hybrid_no_reuse``, the hybrid
  prompts on a backend with prefix reuse off (every call a full prefill of the text; images
  still come from the vision cache), giving ``latency_ratio_no_reuse_over_hybrid``; and
  ``hybrid_vision_cached`` / ``sliding_vision_cached``, where every image of a call is encoded
  untimed before the call (as when the decision agent's shared perception already encoded the
  frame), giving ``latency_ratio_sliding_over_hybrid_vision_cached``: what KV reuse alone buys
  once the vision tower is out of the timed path.
* the same prompts through the simulated VLM (:class:`vlm.sim.SimulatedVlm`, default
  :class:`vlm.sim.LatencyModel`: the paper's Jetson Orin NX numbers, 1.98 s without reuse,
  1.15 s with full reuse, linear in the fraction of images served from cache). These are
  **modelled**, not measured: ``modelled_monitor_ms_median_<s>``,
  ``modelled_cached_token_fraction_<s>`` (its token model: 4 characters per text token, one
  token per 28 x 28 pixels of image) and ``modelled_latency_ratio_sliding_over_hybrid``.

* **across subtask advances** (``advance_*``; issue 21): one backend shared by both agents, as
  in the pilot. The hybrid memory's calls of each episode's window are replayed with the
  subtask changing every ``advance_every`` calls (default 4) (``ADVANCE_SUBTASKS``), once with the real
  monitoring prompt (``v2``: subtask after the keyframes) and once with the same texts in the
  v1 order (subtask first, ``v1_order``). Before each monitoring call a decision call on the
  latest frame (:func:`vlm.prompts.build_decision_prompt`, its own ``cache_key``) and the
  verifier's ``features()`` read the same frame. Reported per order:
  ``advance_cached_fraction_<o>`` and ``advance_ms_median_<o>`` (the calls right after an
  advance), ``steady_cached_fraction_<o>`` / ``steady_ms_median_<o>`` (the other warm calls),
  and ``vision_runs_per_frame_max`` / ``_mean`` (vision-encoder runs per frame counted by the
  backend over every frame any reader saw; one pass per frame is 1.0 / 1.0).

Diagnostics explain the cache numbers: ``prompt_tokens_mean_<s>``, ``image_tokens_per_image``,
``uncached_tokens_mean_<s>`` (the changing tail) and ``new_images_mean_<s>`` (images after the
first difference from the previous call's list); with the references,
``vision_ms_per_new_image_<s>`` (measured minus vision-cached median, per new image) and a
least-squares fit of the vision-cached call times, ``fit_fixed_ms + fit_ms_per_uncached_token *
uncached tokens`` (the fixed part is per-call overhead and decoding that no cache removes).

Targets (issue 9): ``cached_token_fraction_hybrid >= 0.8`` and
``latency_ratio_sliding_over_hybrid >= 1.5`` (the paper: 1.98 s vs 1.15 s on a Jetson Orin NX).

Run: ``.venv/bin/python experiments/bench_memory.py --json out.json`` (a few minutes on two
busy cores; ``--episodes 1 --calls 6`` for a quick look).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from onfly.agents import global_descriptor
from onfly.memory import MEMORY_STRATEGIES, MemoryConfig, make_memory
from planning.camera import PinholeCamera
from vlm.prompts import build_monitor_prompt
from vlm.sim import SimulatedVlm
from vlm.tiny_models import TINY_FAMILIES, TinyVlmSpec, build_tiny_vlm
from vlm.types import FrameAnnotation, VlmImage

REFERENCE = "hybrid_no_reuse"
VISION_CACHED = "_vision_cached"
TARGET_CACHED_FRACTION_HYBRID = 0.8
TARGET_LATENCY_RATIO = 1.5
SUBTASK = "fly past the pillars and stop next to the red van"
#: The advance experiment: a new subtask every ``advance_every`` monitoring calls, in this order.
ADVANCE_SUBTASKS = (
    "fly past the pillars",
    "turn left at the tall grey pillar",
    "fly along the row of red pillars",
    "stop next to the red van",
)
ADVANCE_ORDERS = ("v2", "v1_order")


class BenchConfigError(ValueError):
    """A benchmark option is out of range."""


@dataclass(frozen=True)
class BenchMemoryConfig:
    """Everything a run depends on (written into the JSON).

    Attributes
    ----------
    episodes : number of seeded episodes
    calls : model calls per episode and strategy (the last ``calls`` monitoring calls)
    seed : root seed (world, path, sensor noise, model weights)
    family : tiny model family, ``"qwen2_5_vl"`` or ``"qwen3_vl"``
    image_width_px, image_height_px : camera image size, pixels
    image_tokens : vision-token budget per image given to the model's processor
    path_min_m, path_max_m : range of the path length, metres
    speed_mps : flight speed along the legs, m/s
    yaw_rate_radps : turning rate in place at corners, rad/s
    hover_max_s : hover at each corner drawn uniformly in [0, hover_max_s], seconds
    altitude_m : flight height above the ground, metres
    frame_period_s, monitor_period_s : camera and monitoring periods, seconds (integer ratio)
    slots : S, keyframes between o_1 and o_t
    max_new_tokens : greedy tokens per monitoring call (the answer is one status word; a LOST that names its image takes a few more)
    threads : torch intra-op threads
    advance_every : monitoring calls per subtask in the advance experiment
    """

    episodes: int = 3
    calls: int = 15
    seed: int = 0
    family: str = "qwen2_5_vl"
    image_width_px: int = 224
    image_height_px: int = 160
    image_tokens: int = 48
    path_min_m: float = 60.0
    path_max_m: float = 120.0
    speed_mps: float = 0.6
    yaw_rate_radps: float = 0.4
    hover_max_s: float = 4.0
    altitude_m: float = 2.0
    frame_period_s: float = 0.5
    monitor_period_s: float = 2.0
    slots: int = 4
    max_new_tokens: int = 4
    threads: int = 1
    advance_every: int = 4

    def __post_init__(self) -> None:
        for name in ("episodes", "calls", "image_tokens", "slots", "max_new_tokens", "threads", "advance_every"):
            if getattr(self, name) < 1:
                raise BenchConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.calls < 2:
            raise BenchConfigError(f"calls must be >= 2 (the first call of a run starts cold), got {self.calls}")
        if self.family not in TINY_FAMILIES:
            raise BenchConfigError(f"family must be one of {TINY_FAMILIES}, got {self.family!r}")
        if self.image_width_px < 32 or self.image_height_px < 32:
            raise BenchConfigError(f"image size must be at least 32 x 32, got {self.image_width_px} x {self.image_height_px}")
        for name in ("path_min_m", "speed_mps", "yaw_rate_radps", "altitude_m", "frame_period_s", "monitor_period_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise BenchConfigError(f"{name} must be > 0, got {getattr(self, name)}")
        if not (self.path_max_m >= self.path_min_m):
            raise BenchConfigError(f"path_max_m ({self.path_max_m}) must be >= path_min_m ({self.path_min_m})")
        if not (self.hover_max_s >= 0):
            raise BenchConfigError(f"hover_max_s must be >= 0, got {self.hover_max_s}")
        ratio = self.monitor_period_s / self.frame_period_s
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise BenchConfigError(
                f"monitor_period_s ({self.monitor_period_s}) must be an integer multiple of frame_period_s "
                f"({self.frame_period_s})")

    @property
    def frames_per_call(self) -> int:
        return int(round(self.monitor_period_s / self.frame_period_s))


# -- the synthetic world ----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PillarWorld:
    """Vertical textured cylinders on a tiled ground plane (ENU, z up, metres).

    Attributes
    ----------
    centres_xy : array (N, 2), metres
    radii_m, heights_m : arrays (N,), metres
    colours : array (N, 3), float in [0, 1]
    stripe_freq : array (N,), stripes per metre of height
    stripe_phase : array (N,), radians
    tile_palette : array (64, 3), float in [0, 1], colours of the 2 m ground tiles
    """

    centres_xy: np.ndarray
    radii_m: np.ndarray
    heights_m: np.ndarray
    colours: np.ndarray
    stripe_freq: np.ndarray
    stripe_phase: np.ndarray
    tile_palette: np.ndarray


def _distance_to_polyline(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance (n,) of points (n, 2) to a polyline (m, 2), metres."""
    d = np.full(len(points), np.inf)
    for a, b in zip(polyline[:-1], polyline[1:]):
        ab = b - a
        s = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(points - (a + s[:, None] * ab), axis=1))
    return d


def make_world(rng: np.random.Generator, path_xy: np.ndarray, density_per_m2: float = 1.0 / 50.0,
               margin_m: float = 25.0, clearance_m: float = 2.5) -> PillarWorld:
    """Pillars scattered around ``path_xy`` (m, 2), none closer than ``clearance_m`` to the path."""
    lo = path_xy.min(axis=0) - margin_m
    hi = path_xy.max(axis=0) + margin_m
    n = int(density_per_m2 * float(np.prod(hi - lo)))
    centres = rng.uniform(lo, hi, size=(n, 2))
    radii = rng.uniform(0.3, 1.5, n)
    keep = _distance_to_polyline(centres, path_xy) > radii + clearance_m
    n_kept = int(keep.sum())
    return PillarWorld(
        centres_xy=centres[keep],
        radii_m=radii[keep],
        heights_m=rng.uniform(2.0, 12.0, n)[keep],
        colours=rng.uniform(0.1, 1.0, (n, 3))[keep],
        stripe_freq=rng.uniform(0.5, 4.0, n_kept),
        stripe_phase=rng.uniform(0.0, 2 * np.pi, n_kept),
        tile_palette=rng.uniform(0.25, 0.65, (64, 3)) * np.array([0.9, 1.0, 0.8]),
    )


def render(world: PillarWorld, camera: PinholeCamera, position: np.ndarray, yaw: float,
           rng: np.random.Generator, noise_std: float = 3.0) -> np.ndarray:
    """RGB image of the world from a level forward camera.

    Parameters
    ----------
    position : array (3,), camera centre, metres, world frame (ENU)
    yaw : heading of the optical axis, radians, ENU (0 = +x, counter-clockwise)
    rng : sensor-noise generator (Gaussian, ``noise_std`` grey levels)

    Returns
    -------
    uint8 array (H, W, 3)
    """
    w, h = camera.width, camera.height
    alpha = np.arctan((np.arange(w) - camera.cx) / camera.fx)  # (W,) right of the axis
    azimuth = yaw - alpha
    dirs = np.stack([np.cos(azimuth), np.sin(azimuth)], axis=1)  # (W, 2) horizontal ray
    p_xy = np.asarray(position[:2], float)
    z_cam = float(position[2])
    # ray / circle intersection per column and pillar: |p + t d - c|^2 = r^2
    oc = p_xy[None, :] - world.centres_xy  # (N, 2)
    b = dirs @ oc.T  # (W, N)
    c = np.sum(oc * oc, axis=1) - world.radii_m**2  # (N,)
    disc = b * b - c[None, :]
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    t = np.where((disc >= 0) & (t > 0.05), t, np.inf)
    k = np.argmin(t, axis=1) if t.shape[1] else np.zeros(w, int)
    t_hit = t[np.arange(w), k] if t.shape[1] else np.full(w, np.inf)
    z_depth = t_hit * np.cos(alpha)  # (W,) optical-axis depth of the hit
    rows = (np.arange(h) - camera.cy)[:, None]  # (H, 1), + = below the axis
    has_hit = np.isfinite(z_depth)
    z_world = z_cam - rows / camera.fy * np.where(has_hit, z_depth, 0.0)[None, :]  # (H, W) pillar height
    hit = has_hit[None, :] & (z_world >= 0.0) & (z_world <= world.heights_m[k][None, :])

    img = np.empty((h, w, 3))
    # sky
    sky_t = np.clip((camera.cy - np.arange(h)) / max(camera.cy, 1.0), 0.0, 1.0)[:, None, None]
    img[:] = (1 - sky_t) * np.array([0.85, 0.88, 0.92]) + sky_t * np.array([0.35, 0.55, 0.9])
    # ground: horizontal distance along the ray for rows below the horizon
    below = rows[:, 0] > 0.5
    zg = np.where(below, z_cam * camera.fy / np.maximum(rows[:, 0], 0.5), np.inf)  # (H,)
    dist = zg[:, None] / np.cos(alpha)[None, :]  # (H, W)
    gx = p_xy[0] + dist * dirs[None, :, 0]
    gy = p_xy[1] + dist * dirs[None, :, 1]
    with np.errstate(invalid="ignore"):
        ix = np.floor(np.where(below[:, None], gx, 0.0) / 2.0).astype(np.int64)
        iy = np.floor(np.where(below[:, None], gy, 0.0) / 2.0).astype(np.int64)
    tile = world.tile_palette[((ix * 73856093) ^ (iy * 19349663)) % len(world.tile_palette)]
    fog = np.clip(dist / 60.0, 0.0, 1.0)[..., None]
    ground = (1 - fog) * tile + fog * np.array([0.8, 0.82, 0.85])
    img[below] = ground[below]
    # pillars: stripes along height and around the circumference, Lambert shading
    hit_xy = p_xy[None, :] + np.where(np.isfinite(t_hit), t_hit, 0.0)[:, None] * dirs  # (W, 2)
    normal = hit_xy - world.centres_xy[k]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    around = np.arctan2(normal[:, 1], normal[:, 0])
    shade = 0.55 + 0.45 * np.clip(normal @ np.array([0.6, 0.8]), 0.0, 1.0)  # (W,)
    stripe = 0.5 + 0.5 * np.sin(world.stripe_freq[k][None, :] * 2 * np.pi * z_world
                                + world.stripe_phase[k][None, :] + 3.0 * around[None, :])
    pillar = world.colours[k][None, :, :] * (shade[None, :, None] * (0.65 + 0.35 * stripe[..., None]))
    img[hit] = pillar[hit]
    img = img * 255.0 + rng.normal(0.0, noise_std, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


# -- episodes ------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Episode:
    """One seeded flight sampled at the camera rate.

    Attributes
    ----------
    t_s : array (n,), seconds from the start
    position : array (n, 3), metres, world frame (ENU)
    yaw : array (n,), radians, wrapped to (-pi, pi]
    path_xy : array (m, 2), the polyline's corners, metres
    length_m : float, path length, metres
    """

    t_s: np.ndarray
    position: np.ndarray
    yaw: np.ndarray
    path_xy: np.ndarray
    length_m: float


def make_episode(rng: np.random.Generator, cfg: BenchMemoryConfig) -> Episode:
    """A polyline of 8-25 m legs with 30-120 deg turns, flown leg by leg.

    Along a leg the drone moves at ``speed_mps`` facing the leg; at a corner it hovers
    U(0, ``hover_max_s``) s, then turns in place at ``yaw_rate_radps``.
    """
    total = float(rng.uniform(cfg.path_min_m, cfg.path_max_m))
    heading = float(rng.uniform(-np.pi, np.pi))
    corners = [np.zeros(2)]
    headings = []
    remaining = total
    while remaining > 1e-9:
        leg = min(float(rng.uniform(8.0, 25.0)), remaining)
        remaining -= leg
        headings.append(heading)
        corners.append(corners[-1] + leg * np.array([np.cos(heading), np.sin(heading)]))
        heading += float(rng.choice([-1.0, 1.0]) * rng.uniform(np.deg2rad(30), np.deg2rad(120)))
    # knots of a piecewise-linear timeline (position, unwrapped yaw)
    knot_t, knot_p, knot_yaw = [0.0], [corners[0]], [headings[0]]
    for i, yaw_leg in enumerate(headings):
        if i > 0:  # hover, then turn in place
            knot_t.append(knot_t[-1] + float(rng.uniform(0.0, cfg.hover_max_s)))
            knot_p.append(corners[i])
            knot_yaw.append(knot_yaw[-1])
            knot_t.append(knot_t[-1] + abs(yaw_leg - knot_yaw[-1]) / cfg.yaw_rate_radps)
            knot_p.append(corners[i])
            knot_yaw.append(yaw_leg)
        knot_t.append(knot_t[-1] + float(np.linalg.norm(corners[i + 1] - corners[i])) / cfg.speed_mps)
        knot_p.append(corners[i + 1])
        knot_yaw.append(yaw_leg)
    knot_t_arr = np.array(knot_t)
    knot_p_arr = np.array(knot_p)
    t = np.arange(0.0, knot_t_arr[-1] + 1e-9, cfg.frame_period_s)
    xy = np.stack([np.interp(t, knot_t_arr, knot_p_arr[:, j]) for j in range(2)], axis=1)
    yaw = np.interp(t, knot_t_arr, np.array(knot_yaw))
    position = np.column_stack([xy, np.full(len(t), cfg.altitude_m)])
    return Episode(t_s=t, position=position, yaw=np.angle(np.exp(1j * yaw)), path_xy=np.array(corners), length_m=total)


def make_episodes(cfg: BenchMemoryConfig) -> list[tuple[Episode, np.random.Generator, np.random.Generator]]:
    """``cfg.episodes`` seeded episodes, each with its world and sensor-noise generators.

    Raises :class:`BenchConfigError` when an episode has fewer monitoring calls than ``cfg.calls``.
    """
    out = []
    for e, child in enumerate(np.random.SeedSequence(cfg.seed).spawn(cfg.episodes)):
        world_rng, path_rng, noise_rng = (np.random.default_rng(s) for s in child.spawn(3))
        episode = make_episode(path_rng, cfg)
        n_calls = (len(episode.t_s) - 1) // cfg.frames_per_call
        if n_calls < cfg.calls:
            raise BenchConfigError(f"episode {e} ({episode.length_m:.1f} m) has {n_calls} monitoring calls, fewer "
                                   f"than calls={cfg.calls}; lengthen the path or lower --calls")
        out.append((episode, world_rng, noise_rng))
    return out


# -- memory schedules ------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MemoryCall:
    """One monitoring call's memory.

    Attributes
    ----------
    episode, call : indices (call 0 is the episode's first monitoring call)
    t_s : call time, seconds
    frame_ids : ids of ``[o_1, Q_t, o_t]``
    images : the VlmImage of each id
    prefix_stable : whether ``frame_ids`` starts with the previous call's ids minus the latest
        (None for the episode's first call)
    new_images : images after the longest common prefix with the previous call's ids
    """

    episode: int
    call: int
    t_s: float
    frame_ids: tuple[str, ...]
    images: tuple[VlmImage, ...]
    prefix_stable: bool | None
    new_images: int


def common_prefix_len(a: Sequence, b: Sequence) -> int:
    """Length of the longest common prefix of two sequences."""
    n = 0
    for x, y in zip(a, b):
        if x != y:
            break
        n += 1
    return n


def is_prefix_stable(previous: Sequence[str], current: Sequence[str]) -> bool:
    """True when ``current`` starts with ``previous`` minus its latest frame."""
    kept = list(previous[:-1])
    return list(current[: len(kept)]) == kept


def render_episode(episode: Episode, world: PillarWorld, camera: PinholeCamera, episode_index: int,
                   noise_rng: np.random.Generator) -> list[VlmImage]:
    """One VlmImage per frame; frames carry an empty annotation so the simulated VLM accepts them."""
    annotation = FrameAnnotation(
        instance_ids=np.zeros((camera.height, camera.width), np.int32),
        depth_m=np.full((camera.height, camera.width), 20.0, np.float32),
        objects={},
    )
    return [
        VlmImage(render(world, camera, p, y, noise_rng), f"ep{episode_index}/f{i:04d}", annotation)
        for i, (p, y) in enumerate(zip(episode.position, episode.yaw))
    ]


def memory_calls(strategy: str, episode: Episode, images: Sequence[VlmImage], episode_index: int,
                 cfg: BenchMemoryConfig) -> list[MemoryCall]:
    """Feed every frame to a fresh memory of ``strategy``; select at every monitoring call.

    Calls happen after the frames at ``monitor_period_s, 2 monitor_period_s, ...`` are observed.
    """
    memory = make_memory(MemoryConfig(strategy=strategy, slots=cfg.slots))
    out: list[MemoryCall] = []
    previous: tuple[str, ...] | None = None
    for i, image in enumerate(images):
        memory.observe(image.frame_id, float(episode.t_s[i]), episode.position[i], float(episode.yaw[i]),
                       global_descriptor(None, image.rgb), payload=image)
        if i == 0 or i % cfg.frames_per_call:
            continue
        records = memory.select()
        ids = tuple(r.frame_id for r in records)
        stable = None if previous is None else is_prefix_stable(previous, ids)
        new = len(ids) - (0 if previous is None else common_prefix_len(previous, ids))
        out.append(MemoryCall(episode_index, len(out), float(episode.t_s[i]), ids,
                              tuple(r.payload for r in records), stable, new))
        previous = ids
    return out


# -- model calls -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class StreamSpec:
    """One measured monitoring stream: a memory strategy on its own backend.

    Attributes
    ----------
    name : the suffix of the metric keys (``hybrid``, ``hybrid_no_reuse``, ...)
    strategy : the memory whose calls it replays
    reuse_prefix : KV prefix reuse on the backend
    vision_cached : every image of a call is encoded (untimed) before the timed call, as when
        the decision agent's shared perception already encoded the frame; the timed call then
        holds only the prefill of the uncached suffix and decoding
    """

    name: str
    strategy: str
    reuse_prefix: bool = True
    vision_cached: bool = False


def stream_specs(reference: bool) -> list[StreamSpec]:
    """The three strategies; with ``reference`` also hybrid without reuse and the vision-cached pair."""
    specs = [StreamSpec(s, s) for s in MEMORY_STRATEGIES]
    if reference:
        specs += [
            StreamSpec(REFERENCE, "hybrid", reuse_prefix=False),
            StreamSpec("hybrid" + VISION_CACHED, "hybrid", vision_cached=True),
            StreamSpec("sliding" + VISION_CACHED, "sliding", vision_cached=True),
        ]
    return specs


def _encode_untimed(backend, images: Sequence[VlmImage]) -> None:
    """Put ``images`` into the backend's vision cache with a throwaway image-only call."""
    from vlm.types import ChatMessage

    backend.complete([ChatMessage("user", "<image>" * len(images))], list(images), max_new_tokens=1)


@dataclass(frozen=True)
class ModelCall:
    """One monitoring call through the tiny model and through the simulated VLM.

    Attributes
    ----------
    strategy, episode, call : which memory call
    cold : True for the first call of a run (empty cache; excluded from the metrics)
    prompt_tokens, cached_tokens : the model's Usage
    ms : measured wall time of ``complete()``, milliseconds
    status : the model call's status value
    modelled_ms : simulated-VLM modelled latency, milliseconds
    modelled_prompt_tokens, modelled_cached_tokens : the simulated VLM's token accounting
    new_images : see :class:`MemoryCall`
    """

    strategy: str
    episode: int
    call: int
    cold: bool
    prompt_tokens: int
    cached_tokens: int
    ms: float
    status: str
    modelled_ms: float
    modelled_prompt_tokens: int
    modelled_cached_tokens: int
    new_images: int


def _prompt(call: MemoryCall):
    images = call.images
    return build_monitor_prompt(SUBTASK, images[0], list(images[1:-1]), images[-1])


def run_model_calls(specs: Sequence[StreamSpec], windows: dict[str, list[MemoryCall]], backends: dict, sims: dict,
                    cfg: BenchMemoryConfig) -> list[ModelCall]:
    """Run each stream's window through its backend and its simulated VLM, interleaved.

    ``windows`` maps a strategy to its consecutive calls (all of the same length); ``backends``
    and ``sims`` map a stream name to its backend. Each backend's caches are reset first, so
    the first call of the window is cold. The order of the streams rotates every call.
    """
    specs = list(specs)
    n = len(windows[specs[0].strategy])
    for spec in specs:
        backends[spec.name].reset_cache()
    out: list[ModelCall] = []
    for i in range(n):
        shift = i % len(specs)
        for spec in specs[shift:] + specs[:shift]:
            name = spec.name
            call = windows[spec.strategy][i]
            messages, images = _prompt(call)
            if spec.vision_cached:
                _encode_untimed(backends[name], images)
            t0 = time.perf_counter()
            resp = backends[name].complete(messages, images, max_new_tokens=cfg.max_new_tokens,
                                           cache_key=f"monitor:{name}")
            ms = (time.perf_counter() - t0) * 1e3
            sim = sims[name].complete(messages, images, max_new_tokens=cfg.max_new_tokens,
                                      cache_key=f"monitor:{name}" if spec.reuse_prefix else None)
            out.append(ModelCall(
                strategy=name, episode=call.episode, call=call.call, cold=(i == 0),
                prompt_tokens=resp.usage.prompt_tokens, cached_tokens=resp.usage.cached_tokens, ms=ms,
                status=resp.status.value, modelled_ms=sim.latency_s * 1e3,
                modelled_prompt_tokens=sim.usage.prompt_tokens, modelled_cached_tokens=sim.usage.cached_tokens,
                new_images=call.new_images,
            ))
    return out


# -- subtask advances ------------------------------------------------------------------------------


@dataclass(frozen=True)
class AdvanceCall:
    """One monitoring call of the advance experiment (see the module docstring)."""

    order: str
    episode: int
    call: int
    subtask: str
    advance: bool
    cold: bool
    prompt_tokens: int
    cached_tokens: int
    ms: float


def _v1_order(messages):
    """The same texts in the monitor/v1 layout: the subtask line first in the user message."""
    from vlm.types import ChatMessage

    system, user = messages
    lines = user.content.split("\n")
    k = next(i for i, line in enumerate(lines) if line.startswith("Current subtask: "))
    head = lines.pop(k)
    return [system, ChatMessage("user", "\n".join([head, *lines]))]


def run_advance_calls(window: Sequence[MemoryCall], backend, order: str, cfg: BenchMemoryConfig) -> list[AdvanceCall]:
    """Replay ``window`` (hybrid calls) on ``backend`` with a subtask advance every
    ``cfg.advance_every`` calls; before each monitoring call the decision agent and the verifier
    read the latest frame from the same backend."""
    from vlm.prompts import build_decision_prompt

    backend.reset_cache()
    out: list[AdvanceCall] = []
    for i, call in enumerate(window):
        subtask = ADVANCE_SUBTASKS[(i // cfg.advance_every) % len(ADVANCE_SUBTASKS)]
        images = call.images
        latest = images[-1]
        d_msgs, d_imgs = build_decision_prompt(subtask, latest, None)
        backend.complete(d_msgs, d_imgs, max_new_tokens=cfg.max_new_tokens, cache_key="decision")
        backend.features(latest)
        messages, imgs = build_monitor_prompt(subtask, images[0], list(images[1:-1]), latest)
        if order == "v1_order":
            messages = _v1_order(messages)
        t0 = time.perf_counter()
        resp = backend.complete(messages, imgs, max_new_tokens=cfg.max_new_tokens, cache_key="monitor")
        ms = (time.perf_counter() - t0) * 1e3
        out.append(AdvanceCall(order, call.episode, call.call, subtask, advance=(i > 0 and i % cfg.advance_every == 0),
                               cold=(i == 0), prompt_tokens=resp.usage.prompt_tokens,
                               cached_tokens=resp.usage.cached_tokens, ms=ms))
    return out


def _advance_metrics(calls: Sequence[AdvanceCall], runs_per_frame: Sequence[int]) -> dict:
    out: dict = {}
    for order in ADVANCE_ORDERS:
        for kind, pick in (("advance", lambda c: c.advance), ("steady", lambda c: not c.advance)):
            sel = [c for c in calls if c.order == order and not c.cold and pick(c)]
            prompt = sum(c.prompt_tokens for c in sel)
            out[f"{kind}_cached_fraction_{order}"] = sum(c.cached_tokens for c in sel) / prompt if prompt else float("nan")
            out[f"{kind}_ms_median_{order}"] = _median([c.ms for c in sel])
            out[f"{kind}_calls_{order}"] = len(sel)
    out["vision_runs_per_frame_max"] = int(max(runs_per_frame)) if runs_per_frame else 0
    out["vision_runs_per_frame_mean"] = float(np.mean(runs_per_frame)) if runs_per_frame else float("nan")
    out["vision_runs_frames"] = len(runs_per_frame)
    return out


# -- the benchmark -----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BenchResult:
    """Metrics (the JSON's flat keys), the config block, and the raw records."""

    metrics: dict
    config: dict
    memory_calls: dict[str, list[MemoryCall]]
    model_calls: list[ModelCall]
    streams: tuple[str, ...]
    advance_calls: tuple = ()

    def to_json(self) -> dict:
        return {**self.metrics, "config": self.config}


def _tokens_per_image(backend, image: VlmImage) -> int:
    """Image tokens the backend spends on ``image`` (from an image-only prompt's token count)."""
    from vlm.types import ChatMessage

    with_image = backend.complete([ChatMessage("user", "<image>")], [image], max_new_tokens=1)
    without = backend.complete([ChatMessage("user", "")], [], max_new_tokens=1)
    return with_image.usage.prompt_tokens - without.usage.prompt_tokens - 2  # vision_start / vision_end


def _merge_px(model_dir: Path) -> int:
    """Side of the image area one vision token covers, in resized pixels (patch x merge)."""
    vision = json.loads((model_dir / "config.json").read_text())["vision_config"]
    return int(vision["patch_size"]) * int(vision.get("spatial_merge_size", 2))


def _parameter_count(model_dir: Path) -> int:
    from safetensors import safe_open

    total = 0
    for shard in sorted(model_dir.glob("*.safetensors")):
        with safe_open(str(shard), framework="pt") as f:
            for key in f.keys():
                total += math.prod(f.get_slice(key).get_shape())
    return total


def _median(values: Sequence[float]) -> float:
    return float(statistics.median(values)) if values else float("nan")


def _metrics(mem: dict[str, list[MemoryCall]], model: list[ModelCall], streams: Sequence[str]) -> dict:
    """Flat metric dict (see the module docstring) from the raw records."""
    out: dict = {}
    for s in MEMORY_STRATEGIES:
        flags = [c.prefix_stable for c in mem[s] if c.prefix_stable is not None]
        full = [c.prefix_stable for c in mem[s] if c.prefix_stable is not None and len(c.frame_ids) == len(mem[s][-1].frame_ids)]
        out[f"prefix_stable_rate_{s}"] = float(np.mean(flags)) if flags else float("nan")
        out[f"prefix_stable_rate_full_{s}"] = float(np.mean(full)) if full else float("nan")
    for s in streams:
        warm = [c for c in model if c.strategy == s and not c.cold]
        prompt = sum(c.prompt_tokens for c in warm)
        out[f"cached_token_fraction_{s}"] = sum(c.cached_tokens for c in warm) / prompt if prompt else float("nan")
        out[f"monitor_ms_median_{s}"] = _median([c.ms for c in warm])
        out[f"monitor_ms_p90_{s}"] = float(np.percentile([c.ms for c in warm], 90)) if warm else float("nan")
        out[f"prompt_tokens_mean_{s}"] = float(np.mean([c.prompt_tokens for c in warm])) if warm else float("nan")
        out[f"uncached_tokens_mean_{s}"] = float(np.mean([c.prompt_tokens - c.cached_tokens for c in warm])) if warm else float("nan")
        out[f"new_images_mean_{s}"] = float(np.mean([c.new_images for c in warm])) if warm else float("nan")
        out[f"model_errors_{s}"] = sum(1 for c in model if c.strategy == s and c.status != "ok")
        mprompt = sum(c.modelled_prompt_tokens for c in warm)
        out[f"modelled_cached_token_fraction_{s}"] = (
            sum(c.modelled_cached_tokens for c in warm) / mprompt if mprompt else float("nan"))
        out[f"modelled_monitor_ms_median_{s}"] = _median([c.modelled_ms for c in warm])
    out["latency_ratio_sliding_over_hybrid"] = out["monitor_ms_median_sliding"] / out["monitor_ms_median_hybrid"]
    out["modelled_latency_ratio_sliding_over_hybrid"] = (
        out["modelled_monitor_ms_median_sliding"] / out["modelled_monitor_ms_median_hybrid"])
    if REFERENCE in streams:
        out["latency_ratio_no_reuse_over_hybrid"] = out[f"monitor_ms_median_{REFERENCE}"] / out["monitor_ms_median_hybrid"]
        out["latency_ratio_sliding_over_hybrid" + VISION_CACHED] = (
            out["monitor_ms_median_sliding" + VISION_CACHED] / out["monitor_ms_median_hybrid" + VISION_CACHED])
        # where the time goes: vision encoding per new image, and ms = fixed + per_token * tail
        for s in ("hybrid", "sliding"):
            out[f"vision_ms_per_new_image_{s}"] = (
                (out[f"monitor_ms_median_{s}"] - out[f"monitor_ms_median_{s}{VISION_CACHED}"]) / out[f"new_images_mean_{s}"])
        fit = [c for c in model if c.strategy.endswith(VISION_CACHED) and not c.cold]
        tail = np.array([c.prompt_tokens - c.cached_tokens for c in fit], float)
        if len(fit) >= 2 and np.ptp(tail) > 0:
            slope, intercept = np.polyfit(tail, np.array([c.ms for c in fit]), 1)
            out["fit_fixed_ms"] = float(intercept)
            out["fit_ms_per_uncached_token"] = float(slope)
    out["target_cached_token_fraction_hybrid_met"] = bool(out["cached_token_fraction_hybrid"] >= TARGET_CACHED_FRACTION_HYBRID)
    out["target_latency_ratio_met"] = bool(out["latency_ratio_sliding_over_hybrid"] >= TARGET_LATENCY_RATIO)
    return out


def run_benchmark(cfg: BenchMemoryConfig, *, model_path: str | Path | None = None, work_dir: str | Path | None = None,
                  reference: bool = True, progress=None) -> BenchResult:
    """Run the whole benchmark (see the module docstring).

    Parameters
    ----------
    cfg : the run's configuration
    model_path : a Qwen2.5-VL / Qwen3-VL checkpoint directory; None builds the tiny
        random-weight model of ``cfg.family`` (seeded by ``cfg.seed``) in ``work_dir``
    work_dir : where to build the tiny model (a temporary directory when None)
    reference : also run the reference streams (:func:`stream_specs`)
    progress : optional callable(str) for progress lines
    """
    from vlm.backend_transformers import TransformersBackend, TransformersBackendConfig

    say = progress or (lambda _msg: None)
    episodes = make_episodes(cfg)
    camera = PinholeCamera.from_fov(cfg.image_width_px, cfg.image_height_px, 90.0, 60.0)
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        if model_path is None:
            spec = TinyVlmSpec(family=cfg.family, seed=cfg.seed)
            t0 = time.perf_counter()
            model_dir = build_tiny_vlm(Path(work_dir or tmp) / f"tiny_{cfg.family}", spec)
            say(f"built the tiny {cfg.family} model in {time.perf_counter() - t0:.1f} s")
            model_desc = {"source": "tiny random weights (vlm.tiny_models)", **dataclasses.asdict(spec)}
        else:
            model_dir = Path(model_path)
            model_desc = {"source": str(model_dir)}
        specs = stream_specs(reference)
        streams = [spec.name for spec in specs]
        backends = {}
        merge_px = _merge_px(model_dir)
        for spec in specs:
            backends[spec.name] = TransformersBackend(TransformersBackendConfig(
                str(model_dir), num_threads=cfg.threads, reuse_prefix=spec.reuse_prefix,
                image_max_pixels=cfg.image_tokens * merge_px**2, image_min_pixels=4 * merge_px**2,
            ))
        sims = {name: SimulatedVlm("nominal", seed=cfg.seed) for name in streams}
        shared = {order: TransformersBackend(TransformersBackendConfig(
            str(model_dir), num_threads=cfg.threads, image_max_pixels=cfg.image_tokens * merge_px**2,
            image_min_pixels=4 * merge_px**2)) for order in ADVANCE_ORDERS}
        advance: list[AdvanceCall] = []
        model_desc.update(model_type=backends["hybrid"].model_type, parameters=_parameter_count(model_dir))

        mem: dict[str, list[MemoryCall]] = {s: [] for s in MEMORY_STRATEGIES}
        model: list[ModelCall] = []
        image_tokens = None
        for e, (episode, world_rng, noise_rng) in enumerate(episodes):
            world = make_world(world_rng, episode.path_xy)
            t0 = time.perf_counter()
            images = render_episode(episode, world, camera, e, noise_rng)
            say(f"episode {e}: {episode.length_m:.1f} m, {episode.t_s[-1]:.0f} s, {len(images)} frames, "
                f"{len(world.radii_m)} pillars, rendered in {time.perf_counter() - t0:.1f} s")
            if image_tokens is None:
                image_tokens = _tokens_per_image(backends["hybrid"], images[0])
            calls = {s: memory_calls(s, episode, images, e, cfg) for s in MEMORY_STRATEGIES}
            for s in MEMORY_STRATEGIES:
                mem[s].extend(calls[s])
            n_calls = len(calls["hybrid"])
            windows = {s: calls[s][-cfg.calls:] for s in MEMORY_STRATEGIES}
            t0 = time.perf_counter()
            model.extend(run_model_calls(specs, windows, backends, sims, cfg))
            say(f"episode {e}: {n_calls} monitoring calls, model calls {n_calls - cfg.calls}..{n_calls - 1} "
                f"of {len(streams)} streams in {time.perf_counter() - t0:.1f} s")
            t0 = time.perf_counter()
            for order in ADVANCE_ORDERS:
                advance.extend(run_advance_calls(windows["hybrid"], shared[order], order, cfg))
            say(f"episode {e}: subtask-advance replay ({len(ADVANCE_ORDERS)} orders) in {time.perf_counter() - t0:.1f} s")
        runs_per_frame = [n for b in shared.values() for n in b.vision_encoder_runs.values()]
        for b in [*backends.values(), *shared.values()]:
            b.close()

    metrics = _metrics(mem, model, streams)
    metrics.update(_advance_metrics(advance, runs_per_frame))
    metrics["image_tokens_per_image"] = image_tokens
    config = {
        **dataclasses.asdict(cfg),
        "image_size": [cfg.image_width_px, cfg.image_height_px],
        "model": model_desc,
        "episode_lengths_m": [round(ep.length_m, 2) for ep, _, _ in episodes],
        "monitoring_calls_per_episode": [sum(1 for c in mem["hybrid"] if c.episode == e) for e in range(cfg.episodes)],
        "memory": {k: v for k, v in dataclasses.asdict(MemoryConfig(slots=cfg.slots)).items() if k != "strategy"},
        "subtask": SUBTASK,
        "modelled_latency": "vlm.sim.SimulatedVlm('nominal') default LatencyModel (paper's Jetson Orin NX numbers)",
        "targets": {"cached_token_fraction_hybrid_min": TARGET_CACHED_FRACTION_HYBRID,
                    "latency_ratio_sliding_over_hybrid_min": TARGET_LATENCY_RATIO},
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    config["advance"] = {"every_calls": cfg.advance_every, "subtasks": list(ADVANCE_SUBTASKS), "orders": list(ADVANCE_ORDERS)}
    return BenchResult(metrics=metrics, config=config, memory_calls=mem, model_calls=model, streams=tuple(streams),
                       advance_calls=tuple(advance))


def format_table(result: BenchResult) -> str:
    """Measured and modelled columns per stream, then the ratios and targets."""
    m = result.metrics
    streams = result.streams
    rows = [
        ("prefix_stable_rate", "prefix_stable_rate_{}", "{:.3f}"),
        ("cached_token_fraction", "cached_token_fraction_{}", "{:.3f}"),
        ("monitor_ms_median", "monitor_ms_median_{}", "{:.1f}"),
        ("monitor_ms_p90", "monitor_ms_p90_{}", "{:.1f}"),
        ("prompt_tokens_mean", "prompt_tokens_mean_{}", "{:.0f}"),
        ("uncached_tokens_mean (tail)", "uncached_tokens_mean_{}", "{:.1f}"),
        ("new_images_mean", "new_images_mean_{}", "{:.2f}"),
        ("MODELLED cached_token_fraction", "modelled_cached_token_fraction_{}", "{:.3f}"),
        ("MODELLED monitor_ms_median", "modelled_monitor_ms_median_{}", "{:.0f}"),
    ]
    width, cell = 30, 20
    labels = [s.replace(REFERENCE, "hybrid/no-reuse").replace(VISION_CACHED, "/vis-cached") for s in streams]
    lines = [f"{'metric':<{width}}" + "".join(f"{s:>{cell}}" for s in labels), "-" * (width + cell * len(streams))]
    for label, key, fmt in rows:
        cells = []
        for s in streams:
            value = m.get(key.format(s))
            text = "-" if value is None or (isinstance(value, float) and math.isnan(value)) else fmt.format(value)
            cells.append(f"{text:>{cell}}")
        lines.append(f"{label:<{width}}" + "".join(cells))
    lines.append("")
    lines.append(f"image_tokens_per_image           {m['image_tokens_per_image']}")
    lines.append(f"latency_ratio_sliding_over_hybrid {m['latency_ratio_sliding_over_hybrid']:.2f}  "
                 f"(target >= {TARGET_LATENCY_RATIO}: {'met' if m['target_latency_ratio_met'] else 'MISSED'})")
    lines.append(f"cached_token_fraction_hybrid      {m['cached_token_fraction_hybrid']:.3f}  "
                 f"(target >= {TARGET_CACHED_FRACTION_HYBRID}: {'met' if m['target_cached_token_fraction_hybrid_met'] else 'MISSED'})")
    if "latency_ratio_no_reuse_over_hybrid" in m:
        lines.append(f"latency_ratio_no_reuse_over_hybrid {m['latency_ratio_no_reuse_over_hybrid']:.2f}  "
                     "(KV reuse alone, hybrid prompts, reference in the same run)")
        key = "latency_ratio_sliding_over_hybrid" + VISION_CACHED
        lines.append(f"{key} {m[key]:.2f}  (every image pre-encoded: prefill + decode only)")
        lines.append(f"vision_ms_per_new_image            hybrid {m['vision_ms_per_new_image_hybrid']:.1f}, "
                     f"sliding {m['vision_ms_per_new_image_sliding']:.1f}")
        if "fit_fixed_ms" in m:
            lines.append(f"vision-cached call time fit        {m['fit_fixed_ms']:.1f} ms + "
                         f"{m['fit_ms_per_uncached_token']:.4f} ms x uncached tokens")
    lines.append(f"MODELLED latency ratio sliding/hybrid {m['modelled_latency_ratio_sliding_over_hybrid']:.2f}  "
                 "(simulated VLM latency model, not measured)")
    lines.append("")
    lines.append(f"subtask advance every {result.config['advance']['every_calls']} calls, one backend shared with the decision agent and the verifier:")
    lines.append(f"  {'order':<10}{'advance cached':>16}{'advance ms':>12}{'steady cached':>15}{'steady ms':>11}")
    for order in ADVANCE_ORDERS:
        lines.append(f"  {order:<10}{m[f'advance_cached_fraction_{order}']:>16.3f}{m[f'advance_ms_median_{order}']:>12.1f}"
                     f"{m[f'steady_cached_fraction_{order}']:>15.3f}{m[f'steady_ms_median_{order}']:>11.1f}")
    lines.append(f"  vision-encoder runs per frame: max {m['vision_runs_per_frame_max']}, "
                 f"mean {m['vision_runs_per_frame_mean']:.2f} over {m['vision_runs_frames']} frame(s) x orders")
    return "\n".join(lines)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    d = BenchMemoryConfig()
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--episodes", type=int, default=d.episodes)
    ap.add_argument("--calls", type=int, default=d.calls, help="model calls per episode and strategy")
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--family", choices=TINY_FAMILIES, default=d.family)
    ap.add_argument("--image-tokens", type=int, default=d.image_tokens, help="vision-token budget per image")
    ap.add_argument("--max-new-tokens", type=int, default=d.max_new_tokens)
    ap.add_argument("--threads", type=int, default=d.threads, help="torch intra-op threads")
    ap.add_argument("--path-min-m", type=float, default=d.path_min_m)
    ap.add_argument("--path-max-m", type=float, default=d.path_max_m)
    ap.add_argument("--model-path", type=Path, help="a Qwen-VL checkpoint instead of the tiny random model")
    ap.add_argument("--no-reference", action="store_true", help="skip the hybrid-without-reuse reference")
    return ap.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        cfg = BenchMemoryConfig(
            episodes=args.episodes, calls=args.calls, seed=args.seed, family=args.family,
            image_tokens=args.image_tokens, max_new_tokens=args.max_new_tokens, threads=args.threads,
            path_min_m=args.path_min_m, path_max_m=args.path_max_m,
        )
        t0 = time.perf_counter()
        result = run_benchmark(cfg, model_path=args.model_path, reference=not args.no_reference,
                               progress=lambda msg: print(msg, flush=True))
    except BenchConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print()
    print(format_table(result))
    print(f"\ntotal {time.perf_counter() - t0:.1f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result.to_json(), indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
