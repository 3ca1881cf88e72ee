"""Where agent calls run and when their results land.

The pilot never waits for a VLM. It submits a call and keeps flying; the call's outcome is
handed back by :meth:`AgentRuntime.poll` once it has *landed*:

- :class:`ClockRuntime` (simulation): the call is computed at once, and lands when the virtual
  clock (:class:`onfly.world.clock.SimClock`) reaches ``submit time + latency``; the latency is
  the outcome's ``latency_s`` (the simulated VLM's modelled latency, a real backend's wall time).
- :class:`ThreadRuntime` (onboard): the call runs on a worker thread per kind and lands when it
  finishes.
"""

from __future__ import annotations

import concurrent.futures as cf
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from onfly.world.clock import SimClock

__all__ = ["Landed", "AgentRuntime", "ClockRuntime", "ThreadRuntime"]


@dataclass(frozen=True)
class Landed:
    """A finished call: ``kind``, its ``outcome``, when it was submitted and when it landed."""

    kind: str
    outcome: Any
    submitted_s: float
    landed_s: float


class AgentRuntime(Protocol):
    def now_s(self) -> float: ...

    def submit(self, kind: str, fn: Callable[[], Any]) -> None: ...

    def busy(self, kind: str) -> bool: ...

    def poll(self) -> list[Landed]: ...


class ClockRuntime:
    """Agent calls on a virtual clock; the episode loop advances time with :meth:`advance`."""

    def __init__(self, clock: SimClock | None = None) -> None:
        self.clock = clock if clock is not None else SimClock()
        self._landed: list[Landed] = []

    def now_s(self) -> float:
        return self.clock.now_s

    def submit(self, kind: str, fn: Callable[[], Any]) -> None:
        outcome = fn()
        latency = getattr(outcome, "latency_s", None)
        self.clock.schedule(kind, outcome, latency_s=latency if latency is not None and latency >= 0 else None)

    def busy(self, kind: str) -> bool:
        return self.clock.busy(kind)

    def advance(self, dt_s: float) -> None:
        """Advance the clock (when nothing else does) and collect what completed."""
        self.deliver(self.clock.advance(dt_s))

    def deliver(self, calls) -> None:
        """Collect calls completed by whoever advanced the clock (e.g. ``World.step``)."""
        for call in calls:
            self._landed.append(Landed(call.kind, call.result, call.submitted_s, call.done_s))

    def poll(self) -> list[Landed]:
        out, self._landed = self._landed, []
        return out


class ThreadRuntime:
    """Agent calls on worker threads (one per kind, so kinds never queue behind each other)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._pools: dict[str, cf.ThreadPoolExecutor] = {}
        self._running: dict[str, tuple[cf.Future, float]] = {}

    def now_s(self) -> float:
        return self._clock()

    def submit(self, kind: str, fn: Callable[[], Any]) -> None:
        if self.busy(kind):
            raise RuntimeError(f"a {kind} call is already running")
        pool = self._pools.setdefault(kind, cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"onfly-{kind}"))
        self._running[kind] = (pool.submit(fn), self.now_s())

    def busy(self, kind: str) -> bool:
        fut = self._running.get(kind)
        return fut is not None and not fut[0].done()

    def poll(self) -> list[Landed]:
        out = []
        for kind, (fut, t0) in list(self._running.items()):
            if fut.done():
                del self._running[kind]
                exc = fut.exception()
                out.append(Landed(kind, exc if exc is not None else fut.result(), t0, self.now_s()))
        return out

    def close(self) -> None:
        for pool in self._pools.values():
            pool.shutdown(wait=False, cancel_futures=True)
