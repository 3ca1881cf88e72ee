"""Where agent calls run and when their results land.

The pilot never waits for a VLM. It submits a call and keeps flying; the call's outcome is
handed back by :meth:`AgentRuntime.poll` once it has *landed*:

- :class:`ClockRuntime` (simulation): the call is computed at once, and lands when the virtual
  clock (:class:`onfly.world.clock.SimClock`) reaches ``submit time + latency``; the latency is
  the outcome's ``latency_s`` (the simulated VLM's modelled latency, a real backend's wall time).
- :class:`ThreadRuntime` (onboard): the call runs on a worker thread per kind and lands when it
  finishes. With ``honour_modelled_latency=True`` (onboard *simulation*: a simulated VLM that
  answers at once but models a latency) a finished call lands only once the runtime's clock
  reaches ``submit time + outcome.latency_s``, so the flight sees the modelled hardware's delay
  in wall time exactly as the virtual clock charges it in the benchmark.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
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


def _modelled_latency_s(outcome: Any) -> float:
    """The outcome's ``latency_s`` when it is a finite number >= 0, else 0 (land at once)."""
    latency = getattr(outcome, "latency_s", None)
    try:
        latency = float(latency)
    except (TypeError, ValueError):
        return 0.0
    return latency if math.isfinite(latency) and latency >= 0 else 0.0


class ThreadRuntime:
    """Agent calls on worker threads (one per kind, so kinds never queue behind each other).

    Parameters
    ----------
    clock : seconds, monotonic (the pilot's clock)
    honour_modelled_latency : False (default): a call lands as soon as its thread finishes.
        True: it lands at ``max(finish, submit + outcome.latency_s)`` on ``clock``, and its
        kind stays busy until then (for a simulated VLM whose answers are instant but whose
        modelled latency must pass in wall time). A call that raised lands at once. Never use
        it with a real backend: its ``latency_s`` is the wall time already spent.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic, *, honour_modelled_latency: bool = False) -> None:
        self._clock = clock
        self.honour_modelled_latency = bool(honour_modelled_latency)
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
        """True from submission until the call has landed (been returned by :meth:`poll`)."""
        return kind in self._running

    def wait_finished(self, kind: str, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` until the running ``kind`` call has finished computing (it
        may still wait for its modelled latency before landing). True if none is running or it
        finished. For shutdown and tests; the pilot never calls it."""
        entry = self._running.get(kind)
        if entry is None:
            return True
        done, _ = cf.wait([entry[0]], timeout=timeout_s)
        return bool(done)

    def _due(self, fut: cf.Future, submitted_s: float, now_s: float) -> bool:
        if not fut.done():
            return False
        if not self.honour_modelled_latency or fut.exception() is not None:
            return True
        return now_s >= submitted_s + _modelled_latency_s(fut.result())

    def poll(self) -> list[Landed]:
        """Calls that have landed since the last poll (each returned once)."""
        out = []
        now = self.now_s()
        for kind, (fut, t0) in list(self._running.items()):
            if self._due(fut, t0, now):
                del self._running[kind]
                exc = fut.exception()
                out.append(Landed(kind, exc if exc is not None else fut.result(), t0, now))
        return out

    def close(self) -> None:
        for pool in self._pools.values():
            pool.shutdown(wait=False, cancel_futures=True)
