"""Virtual time with modelled VLM latency.

A VLM call in simulation is computed at once (the simulated VLM answers from the frame it
was given) but its result is *delivered* only when virtual time reaches the call's completion
time ``submitted_s + latency_s``. Meanwhile the world keeps stepping and the vehicle keeps
flying the last plan, so stop-and-go costs show in flight time as they would on the drone.
Nothing here sleeps: time moves only through :meth:`SimClock.advance`.

Latency of a call, in order of precedence: the ``latency_s`` given to
:meth:`SimClock.schedule`; the ``latency_s`` of a :class:`vlm.types.VlmResponse` result when
positive (the simulated VLM reports its modelled latency, a real backend its wall time);
the :class:`LatencyModel` value for the call's kind.
"""

from __future__ import annotations

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
    """Modelled VLM latency per call kind, seconds.

    Defaults are the paper's Jetson Orin NX measurements: decision 0.81 s; monitoring 1.15 s
    when the server reuses the cached prompt prefix, 1.98 s without.
    """

    decision_s: float = 0.81
    monitoring_prefix_s: float = 1.15
    monitoring_full_s: float = 1.98

    def __post_init__(self) -> None:
        for name in ("decision_s", "monitoring_prefix_s", "monitoring_full_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"LatencyModel.{name} must be finite and >= 0, got {v}")

    def latency_s(self, kind: str, prefix_reused: bool = True) -> float:
        """Latency of one call of ``kind`` ("decision" or "monitoring")."""
        if kind == DECISION:
            return self.decision_s
        if kind == MONITORING:
            return self.monitoring_prefix_s if prefix_reused else self.monitoring_full_s
        raise ClockError(f"no modelled latency for call kind {kind!r} (known: {DECISION}, {MONITORING}); pass latency_s")


@dataclass(frozen=True, eq=False)
class PendingCall:
    """A scheduled call: its ``result`` is delivered once the clock reaches ``done_s``."""

    call_id: int
    kind: str
    submitted_s: float
    done_s: float
    result: Any

    @property
    def latency_s(self) -> float:
        return self.done_s - self.submitted_s


class SimClock:
    """Virtual clock that holds pending VLM calls until their modelled completion time.

    Parameters
    ----------
    t0_s : start time, seconds
    latency : LatencyModel used when neither the caller nor the response gives a latency
    """

    def __init__(self, t0_s: float = 0.0, latency: LatencyModel | None = None) -> None:
        if not np.isfinite(t0_s):
            raise ClockError(f"t0_s must be finite, got {t0_s}")
        self._now = float(t0_s)
        self.latency = latency if latency is not None else LatencyModel()
        self._pending: list[PendingCall] = []
        self._next_id = 0
        self._charged: dict[str, float] = {}
        self._counts: dict[str, int] = {}

    @property
    def now_s(self) -> float:
        return self._now

    def schedule(self, kind: str, result: Any, *, latency_s: float | None = None, prefix_reused: bool = True) -> PendingCall:
        """Start a call now; its ``result`` is delivered by :meth:`advance` after its latency.

        Returns the PendingCall (``done_s`` says when it completes).
        """
        if latency_s is None:
            if isinstance(result, VlmResponse) and result.latency_s > 0:
                latency_s = float(result.latency_s)
            else:
                latency_s = self.latency.latency_s(kind, prefix_reused)
        if not (np.isfinite(latency_s) and latency_s >= 0):
            raise ClockError(f"latency_s must be finite and >= 0, got {latency_s}")
        call = PendingCall(self._next_id, kind, self._now, self._now + float(latency_s), result)
        self._next_id += 1
        self._pending.append(call)
        self._charged[kind] = self._charged.get(kind, 0.0) + float(latency_s)
        self._counts[kind] = self._counts.get(kind, 0) + 1
        return call

    def pending(self, kind: str | None = None) -> tuple[PendingCall, ...]:
        """Calls not yet delivered (of one kind, or all)."""
        return tuple(c for c in self._pending if kind is None or c.kind == kind)

    def busy(self, kind: str) -> bool:
        """True while a call of ``kind`` is pending."""
        return any(c.kind == kind for c in self._pending)

    def cancel(self, call_id: int) -> bool:
        """Drop a pending call (its latency stays charged). True if it was pending."""
        n = len(self._pending)
        self._pending = [c for c in self._pending if c.call_id != call_id]
        return len(self._pending) < n

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
        return done

    @property
    def charged_s(self) -> dict[str, float]:
        """Total latency charged per call kind, seconds."""
        return dict(self._charged)

    @property
    def call_counts(self) -> dict[str, int]:
        """Number of calls scheduled per kind."""
        return dict(self._counts)
