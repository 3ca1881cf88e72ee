"""Virtual time with modelled VLM latency and one modelled inference engine.

A VLM call in simulation is computed at once (the simulated VLM answers from the frame it
was given) but its result is *delivered* only when virtual time reaches the call's completion
time. Meanwhile the world keeps stepping and the vehicle keeps flying the last plan, so
stop-and-go costs show in flight time as they would on the drone. Nothing here sleeps: time
moves only through :meth:`SimClock.advance`.

Service time of a call (how long it occupies the engine), in order of precedence: the
``latency_s`` given to :meth:`SimClock.schedule`; the ``latency_s`` of a
:class:`vlm.types.VlmResponse` result when positive (the simulated VLM reports its modelled
latency, a real backend its wall time); the :class:`LatencyModel` value for the call's kind.

**One inference engine** (default, ``LatencyModel.single_engine=True``): the paper's Jetson Orin
NX has one GPU, and one model instance on it generates for one request at a time (the
in-process backend serializes every call behind one lock), so calls share one FIFO queue: a
call starts when the engine is free and occupies it for its service time; two calls issued
together finish one after the other. Calls of the kinds in ``LatencyModel.priority_kinds``
(default the decision stream) are served before *waiting* calls of other kinds, but never
preempt the call that is running (a generation in progress is not interrupted). A call's
``done_s`` is therefore ``start_s + service_s`` and its latency ``done_s - submitted_s``
includes the wait. With ``single_engine=False`` every call starts at once (the old model:
decision and monitoring in parallel, as on two accelerators). ``docs/inference_queue.md``
has the model, its sources and how to switch it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from vlm.types import VlmResponse

__all__ = ["LatencyModel", "PendingCall", "SimClock", "ClockError", "DECISION", "MONITORING"]

DECISION = "decision"
MONITORING = "monitoring"


class ClockError(ValueError):
    """A negative step, an unknown call kind without a latency, or a bad latency."""


@dataclass(frozen=True)
class LatencyModel:
    """Modelled VLM latency per call kind (seconds) and how calls share the accelerator.

    Latency defaults are the paper's Jetson Orin NX measurements: decision 0.81 s; monitoring
    1.15 s when the server reuses the cached prompt prefix, 1.98 s without.

    single_engine : True (default): all calls share one queue on one engine (one GPU, one
        model instance, one generation at a time). False: every call runs at once, in
        parallel with any other (an idealization: two accelerators).
    priority_kinds : call kinds served before waiting calls of other kinds (non-preemptive;
        FIFO within a class). Default the decision stream, whose answer the vehicle is waiting
        for; ``()`` is plain FIFO.
    """

    decision_s: float = 0.81
    monitoring_prefix_s: float = 1.15
    monitoring_full_s: float = 1.98
    single_engine: bool = True
    priority_kinds: tuple[str, ...] = (DECISION,)

    def __post_init__(self) -> None:
        for name in ("decision_s", "monitoring_prefix_s", "monitoring_full_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ValueError(f"LatencyModel.{name} must be finite and >= 0, got {v}")
        if not isinstance(self.single_engine, bool):
            raise ValueError(f"LatencyModel.single_engine must be true or false, got {self.single_engine!r}")
        kinds = self.priority_kinds
        if isinstance(kinds, str) or not all(isinstance(k, str) and k for k in kinds):
            raise ValueError(f"LatencyModel.priority_kinds must be a list of call kinds, got {kinds!r}")
        object.__setattr__(self, "priority_kinds", tuple(kinds))

    def latency_s(self, kind: str, prefix_reused: bool = True) -> float:
        """Service time of one call of ``kind`` ("decision" or "monitoring")."""
        if kind == DECISION:
            return self.decision_s
        if kind == MONITORING:
            return self.monitoring_prefix_s if prefix_reused else self.monitoring_full_s
        raise ClockError(f"no modelled latency for call kind {kind!r} (known: {DECISION}, {MONITORING}); pass latency_s")


@dataclass(frozen=True, eq=False)
class PendingCall:
    """A scheduled call: its ``result`` is delivered once the clock reaches ``done_s``.

    ``start_s`` is when the engine starts serving it (``submitted_s`` unless it waits in the
    queue). While a call waits, a later call of a priority kind may move its ``start_s`` and
    ``done_s`` later: :meth:`SimClock.pending` has the current schedule.
    """

    call_id: int
    kind: str
    submitted_s: float
    done_s: float
    result: Any
    start_s: float | None = None

    def __post_init__(self) -> None:
        if self.start_s is None:
            object.__setattr__(self, "start_s", self.submitted_s)

    @property
    def latency_s(self) -> float:
        """Submission to completion, seconds (queue wait included)."""
        return self.done_s - self.submitted_s

    @property
    def service_s(self) -> float:
        """Time the call occupies the engine, seconds."""
        return self.done_s - self.start_s

    @property
    def wait_s(self) -> float:
        """Time the call waits in the queue before the engine serves it, seconds."""
        return self.start_s - self.submitted_s


class SimClock:
    """Virtual clock that holds pending VLM calls until their modelled completion time.

    Parameters
    ----------
    t0_s : start time, seconds
    latency : LatencyModel (service times and the engine model) used when neither the caller
        nor the response gives a latency
    """

    def __init__(self, t0_s: float = 0.0, latency: LatencyModel | None = None) -> None:
        if not np.isfinite(t0_s):
            raise ClockError(f"t0_s must be finite, got {t0_s}")
        self._now = float(t0_s)
        self.latency = latency if latency is not None else LatencyModel()
        if not isinstance(self.latency, LatencyModel):
            raise ClockError(f"latency must be a LatencyModel, got {type(self.latency).__name__}")
        self._pending: list[PendingCall] = []
        self._next_id = 0
        self._charged: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._waited: dict[str, float] = {}
        self._placed: set[int] = set()  # ids of pending calls the engine queue has placed
        self._engine_free_s = -np.inf  # when the last delivered (or cancelled running) call freed the engine

    @property
    def now_s(self) -> float:
        return self._now

    def schedule(
        self,
        kind: str,
        result: Any,
        *,
        latency_s: float | None = None,
        prefix_reused: bool = True,
        submitted_s: float | None = None,
    ) -> PendingCall:
        """Submit a call; its ``result`` is delivered by :meth:`advance` once served.

        ``latency_s`` is the call's service time (see the module doc for the default).
        ``submitted_s`` (default now, never later than now) is when the call reached the
        engine's queue, for a caller that learns of a call after it was issued (the onboard
        runtime). Returns the PendingCall (``done_s`` says when it completes, as scheduled now).
        """
        if latency_s is None:
            if isinstance(result, VlmResponse) and result.latency_s > 0:
                latency_s = float(result.latency_s)
            else:
                latency_s = self.latency.latency_s(kind, prefix_reused)
        if not (np.isfinite(latency_s) and latency_s >= 0):
            raise ClockError(f"latency_s must be finite and >= 0, got {latency_s}")
        t_sub = self._now if submitted_s is None else float(submitted_s)
        if not (np.isfinite(t_sub) and t_sub <= self._now + 1e-9):
            raise ClockError(f"submitted_s must be finite and not after now ({self._now}), got {submitted_s}")
        call = PendingCall(self._next_id, kind, t_sub, t_sub + float(latency_s), result, t_sub)
        self._next_id += 1
        self._pending.append(call)
        self._charged[kind] = self._charged.get(kind, 0.0) + float(latency_s)
        self._counts[kind] = self._counts.get(kind, 0) + 1
        if self.latency.single_engine:
            self._reschedule()
        return next(c for c in self._pending if c.call_id == call.call_id)

    def _reschedule(self) -> None:
        """Place the waiting calls on the engine, one after the other after the running one.

        A call is *running* once placed with ``start_s <= now`` (it holds the engine until
        ``done_s``); every other pending call waits and is (re)placed in priority order.
        """
        now = self._now + 1e-9
        running = [c for c in self._pending if c.call_id in self._placed and c.start_s <= now]
        run_ids = {c.call_id for c in running}
        waiting = [c for c in self._pending if c.call_id not in run_ids]
        prio = self.latency.priority_kinds
        waiting.sort(key=lambda c: (c.kind not in prio, c.call_id))
        free = max([self._engine_free_s] + [c.done_s for c in running])
        placed = {c.call_id: c for c in running}
        for c in waiting:
            start = max(free, c.submitted_s)
            done = start + c.service_s
            if c.start_s != start or c.done_s != done:
                c = dataclasses.replace(c, start_s=start, done_s=done)
            placed[c.call_id] = c
            free = done
        self._placed = set(placed)
        self._pending = sorted(placed.values(), key=lambda c: c.call_id)

    def pending(self, kind: str | None = None) -> tuple[PendingCall, ...]:
        """Calls not yet delivered (of one kind, or all)."""
        return tuple(c for c in self._pending if kind is None or c.kind == kind)

    def busy(self, kind: str) -> bool:
        """True while a call of ``kind`` is pending (waiting or being served)."""
        return any(c.kind == kind for c in self._pending)

    def cancel(self, call_id: int) -> bool:
        """Drop a pending call (its service time stays charged; the engine is freed at once,
        as a server aborts a cancelled request). True if it was pending."""
        gone = [c for c in self._pending if c.call_id == call_id]
        if not gone:
            return False
        self._pending = [c for c in self._pending if c.call_id != call_id]
        if self.latency.single_engine:
            if gone[0].call_id in self._placed and gone[0].start_s <= self._now + 1e-9:
                self._engine_free_s = max(self._engine_free_s, self._now)  # the running call, aborted now
            self._reschedule()
        return True

    def advance(self, dt_s: float) -> list[PendingCall]:
        """Move time forward by ``dt_s`` and return the calls completed by the new time,
        ordered by completion time (then by submission order)."""
        if not (np.isfinite(dt_s) and dt_s >= 0):
            raise ClockError(f"dt_s must be finite and >= 0, got {dt_s}")
        self._now += float(dt_s)
        done = [c for c in self._pending if c.done_s <= self._now + 1e-9]
        if done:
            self._pending = [c for c in self._pending if c.done_s > self._now + 1e-9]
            done.sort(key=lambda c: (c.done_s, c.call_id))
            for c in done:
                self._waited[c.kind] = self._waited.get(c.kind, 0.0) + c.wait_s
                self._engine_free_s = max(self._engine_free_s, c.done_s)
        return done

    @property
    def charged_s(self) -> dict[str, float]:
        """Total service time charged per call kind, seconds (queue waits not included)."""
        return dict(self._charged)

    @property
    def waited_s(self) -> dict[str, float]:
        """Total queue wait of the delivered calls per kind, seconds (0 with parallel engines)."""
        return dict(self._waited)

    @property
    def call_counts(self) -> dict[str, int]:
        """Number of calls scheduled per kind."""
        return dict(self._counts)
