"""Closed-loop harness for the baseline tests: a committed scene, a small camera, short episodes."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from onfly.bench.episode import EpisodeConfig, EpisodeStep, run_episode
from onfly.bench.tasks import Task, load_tasks
from onfly.world.scene import load_scene, resolve_scene
from onfly.world.world import World
from planning.camera import PinholeCamera
from planning.trajectory import VehicleState
from vlm.prompts import parse_prompt
from vlm.sim import SimulatedVlm
from vlm.types import ChatMessage, VlmImage, VlmResponse

SMALL_CAMERA = PinholeCamera.from_fov(160, 107)


def task(task_id: str) -> Task:
    return {t.task_id: t for t in load_tasks(None)}[task_id]


def world_for(t: Task, camera: PinholeCamera = SMALL_CAMERA) -> World:
    start = VehicleState(0.0, t.start.position_m.copy(), np.zeros(3), float(t.start.yaw_rad))
    return World(load_scene(resolve_scene(t.scene)), camera=camera, initial_state=start)


def fly(method, task_id: str, time_limit_s: float = 20.0, seed: int = 0, error_model: str = "perfect"):
    """Fly ``method`` on a committed task; returns (EpisodeResult, [EpisodeStep ...])."""
    t = task(task_id)
    steps: list[EpisodeStep] = []
    res = run_episode(
        world_for(t),
        method,
        instruction=t.instruction,
        goal=t.goal_region,
        reference_path_m=t.reference.path_length_m,
        seed=seed,
        error_model=error_model,
        config=EpisodeConfig(time_limit_s=time_limit_s, frame_period_s=0.5),
        observer=steps.append,
    )
    return res, steps


class RecordingVlm:
    """The simulated VLM, recording every prompt and answer; ``override(kind_prompt, index,
    response) -> VlmResponse | None`` may replace answers."""

    name = "recording"

    def __init__(self, preset: str = "perfect", seed: int = 0, override=None) -> None:
        self.sim = SimulatedVlm(preset, seed=seed)
        self.override = override
        self.calls: list[tuple[object, Sequence[VlmImage], VlmResponse]] = []

    def features(self, image: VlmImage):
        return self.sim.features(image)

    def close(self) -> None:
        self.sim.close()

    def complete(self, messages: Sequence[ChatMessage], images: Sequence[VlmImage] = (), **kw) -> VlmResponse:
        prompt = parse_prompt(messages)
        resp = self.sim.complete(messages, images, **kw)
        if self.override is not None:
            resp = self.override(prompt, len(self.calls), resp) or resp
        self.calls.append((prompt, list(images), resp))
        return resp


def text(t: str, latency_s: float = 0.81) -> VlmResponse:
    from vlm.types import CallStatus, Usage

    return VlmResponse(CallStatus.OK, text=t, usage=Usage(0, 0, 0), latency_s=latency_s)
