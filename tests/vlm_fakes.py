"""Scripted VLM backends for closed-loop pilot tests (no model, fully deterministic)."""

from __future__ import annotations

from typing import Callable, Sequence

from vlm.prompts import DecisionPrompt, DecomposePrompt, MonitorPrompt, parse_prompt
from vlm.sim import SimulatedVlm
from vlm.types import CallStatus, ChatMessage, VlmImage, VlmResponse


class ScriptedVlm:
    """Wraps the simulated VLM and overrides answers per prompt kind.

    ``decision`` / ``monitor`` are callables ``(call_index, sim_response) -> VlmResponse`` (or
    None to pass the simulated answer through). Latencies default to the sim's.
    """

    name = "scripted"

    def __init__(self, preset: str = "perfect", seed: int = 0, decision: Callable | None = None, monitor: Callable | None = None):
        self.sim = SimulatedVlm(preset, seed=seed)
        self.decision = decision
        self.monitor = monitor
        self.counts = {"decision": 0, "monitor": 0, "decompose": 0}

    def features(self, image: VlmImage):
        return self.sim.features(image)

    def close(self) -> None:
        self.sim.close()

    def complete(self, messages: Sequence[ChatMessage], images: Sequence[VlmImage] = (), **kw) -> VlmResponse:
        prompt = parse_prompt(messages)
        resp = self.sim.complete(messages, images, **kw)
        if isinstance(prompt, DecisionPrompt):
            i = self.counts["decision"]
            self.counts["decision"] += 1
            if self.decision is not None:
                return self.decision(i, resp) or resp
        elif isinstance(prompt, MonitorPrompt):
            i = self.counts["monitor"]
            self.counts["monitor"] += 1
            if self.monitor is not None:
                return self.monitor(i, resp) or resp
        elif isinstance(prompt, DecomposePrompt):
            self.counts["decompose"] += 1
        return resp


def text(t: str, latency_s: float = 0.8) -> VlmResponse:
    return VlmResponse(CallStatus.OK, t, latency_s=latency_s)


def timeout(latency_s: float = 2.0) -> VlmResponse:
    return VlmResponse(CallStatus.TIMEOUT, latency_s=latency_s, error="deadline exceeded")
