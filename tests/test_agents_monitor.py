"""MonitoringAgent on a memory snapshot: the call judges the frames selected when it started,
and its outcome carries the judged frame's pose (the LOST normal point), not a later one."""

from __future__ import annotations

import numpy as np

from onfly.agents import MonitoringAgent
from onfly.memory import HybridMemory, MemoryConfig
from onfly.observation import Observation
from planning.camera import PinholeCamera
from planning.frames import body_transform, cam_transform_from_body
from vlm.prompts import MonitorPrompt, parse_prompt
from vlm.types import CallStatus, Usage, VlmResponse


class _RecordingBackend:
    """Answers ``answer`` (CONTINUE) and records the frame ids and subtask of every monitoring
    prompt."""

    name = "recording"

    def __init__(self, answer: str = "CONTINUE") -> None:
        self.seen: list[tuple[str, tuple[str, ...]]] = []
        self.answer = answer

    def complete(self, messages, images=(), **kwargs) -> VlmResponse:
        prompt = parse_prompt(messages)
        assert isinstance(prompt, MonitorPrompt)
        self.seen.append((prompt.subtask, tuple(im.frame_id for im in images)))
        return VlmResponse(CallStatus.OK, text=self.answer, usage=Usage(), latency_s=0.0)

    def features(self, image):
        return None


def _obs(i: int) -> Observation:
    cam = PinholeCamera.from_fov(64, 48, 90, 60)
    rng = np.random.default_rng(i)
    T = cam_transform_from_body(body_transform(np.array([0.5 * i, 0.1 * i, 1.5]), 0.05 * i))
    return Observation(
        t_s=0.5 * i,
        rgb=rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),
        depth_m=np.full((48, 64), 5.0, np.float32),
        T_world_cam=T,
        camera=cam,
        frame_id=f"f{i}",
    )


def test_assess_judges_the_snapshot_and_reports_its_pose():
    backend = _RecordingBackend()
    agent = MonitoringAgent(backend, HybridMemory(MemoryConfig(slots=2)), None)
    for i in range(6):
        agent.observe(_obs(i))
    snap = agent.snapshot()  # the control thread, when the call starts
    for i in range(6, 10):  # frames arrive while the call is in flight
        agent.observe(_obs(i))
    out = agent.assess("fly to the tree", snap)
    assert out.status.value == "CONTINUE"
    assert backend.seen[-1] == ("fly to the tree", snap.frame_ids) and snap.frame_ids[-1] == "f5"
    judged = _obs(5)
    assert out.judged_frame_id == "f5" and out.judged_t_s == judged.t_s
    np.testing.assert_allclose(out.judged_position, judged.position)
    assert out.judged_yaw == judged.yaw
    # Without a snapshot the call takes one itself: the newest frame is judged.
    later = agent.assess("fly to the tree")
    assert later.judged_frame_id == "f9" and backend.seen[-1][1][-1] == "f9"


def test_a_lost_that_names_an_image_carries_that_frames_pose():
    # memory [first, k1, k2, latest]: "keyframe 2" is the third image of the prompt
    backend = _RecordingBackend("LOST keyframe 2")
    agent = MonitoringAgent(backend, HybridMemory(MemoryConfig(slots=2)), None)
    for i in range(6):
        agent.observe(_obs(i))
    out = agent.assess("fly to the tree")
    ids = backend.seen[-1][1]
    assert len(ids) == 4 and out.status.value == "LOST"
    named = _obs(int(ids[2][1:]))
    assert out.seen_frame_id == ids[2] == named.frame_id
    np.testing.assert_allclose(out.seen_position, named.position)
    assert out.seen_yaw == named.yaw
    # a keyframe the prompt did not hold is no place; the status stands
    backend.answer = "LOST keyframe 3"
    out = agent.assess("fly to the tree")
    assert out.status.value == "LOST" and out.seen_frame_id is None and out.seen_position is None
    assert "keyframe 3 of 2" in out.reason
    # the first frame
    backend.answer = "**LOST first**"
    out = agent.assess("fly to the tree")
    assert out.seen_frame_id == backend.seen[-1][1][0] == "f0"
