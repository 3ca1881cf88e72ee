"""Where agent calls run and when their results land.

The pilot never waits for a VLM. It submits a call and keeps flying; the call's outcome is
handed back by :meth:`AgentRuntime.poll` once it has *landed*:

- :class:`ClockRuntime` (simulation): the call is computed at once, and lands when the virtual
  clock (:class:`onfly.world.clock.SimClock`) has served it: the outcome's ``latency_s`` (the
  simulated VLM's modelled latency, a real backend's wall time) is its service time on the
  clock's modelled inference engine, one queue shared by every kind by default (one GPU), so a
  call issued while another runs lands after both (``docs/inference_queue.md``).
- :class:`ThreadRuntime` (onboard): the call runs on a worker thread per kind and lands when it
  finishes (a real backend queues on its own engine: the in-process backend behind one lock, a
  server by its scheduler). With ``honour_modelled_latency=True`` (onboard *simulation*: a
  simulated VLM that answers at once but models a latency) a finished call lands only when
  the same engine model as the benchmark's, run on the runtime's clock, has served it, so the
  flight sees the modelled hardware's delay and queueing in wall time as the virtual clock
  charges them in the benchmark.
"""

from __future__ import annotations

import concurrent.futures as cf
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from onfly.world.clock import LatencyModel, SimClock

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
    """Agent calls on worker threads (one per kind, so kinds never wait for each other's
    *computation*; with ``honour_modelled_latency`` the modelled engine still serves them one
    at a time).

    Parameters
    ----------
    clock : seconds, monotonic (the pilot's clock)
    honour_modelled_latency : False (default): a call lands as soon as its thread finishes.
        True: a finished call enters a :class:`onfly.world.clock.SimClock` run on ``clock``
        with its submission time and ``outcome.latency_s`` as service time, and lands when
        that modelled engine has served it (never before its thread finished); its kind stays
        busy until then (for a simulated VLM whose answers are instant but whose modelled
        latency must pass in wall time). A call that raised lands at once. Never use it with
        a real backend: its ``latency_s`` is the wall time already spent.
    latency : the engine model used with ``honour_modelled_latency`` (default
        ``LatencyModel()``: one engine, decision first)
    """

    def __init__(
        self,
        clock: Callable[[], float] = time.monotonic,
        *,
        honour_modelled_latency: bool = False,
        latency: LatencyModel | None = None,
    ) -> None:
        self._clock = clock
        self.honour_modelled_latency = bool(honour_modelled_latency)
        self._pools: dict[str, cf.ThreadPoolExecutor] = {}
        self._running: dict[str, tuple[cf.Future, float]] = {}
        self._engine = SimClock(float(clock()), latency) if self.honour_modelled_latency else None
        self._queued: set[str] = set()  # kinds whose finished call waits in the modelled engine

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

    def poll(self) -> list[Landed]:
        """Calls that have landed since the last poll (each returned once)."""
        out = []
        now = self.now_s()
        engine = self._engine
        due = engine.advance(now - engine.now_s) if engine is not None and now > engine.now_s else []
        finished = sorted(
            ((t0, kind, fut) for kind, (fut, t0) in self._running.items() if fut.done() and kind not in self._queued),
            key=lambda x: x[0],
        )
        for t0, kind, fut in finished:
            exc = fut.exception()
            if engine is None or exc is not None:
                del self._running[kind]
                out.append(Landed(kind, exc if exc is not None else fut.result(), t0, now))
                continue
            result = fut.result()
            engine.schedule(kind, result, latency_s=_modelled_latency_s(result), submitted_s=min(t0, engine.now_s))
            self._queued.add(kind)
        if engine is not None:
            due = list(due) + engine.advance(0.0)
            for call in due:
                t0 = self._running.pop(call.kind)[1]
                self._queued.discard(call.kind)
                out.append(Landed(call.kind, call.result, t0, now))
        return out

    def close(self) -> None:
        for pool in self._pools.values():
            pool.shutdown(wait=False, cancel_futures=True)
