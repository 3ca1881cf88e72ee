"""Play any observation source at real time (or a multiple of it) on an injectable clock.

Used onboard and in hardware-in-the-loop tests to make a recording behave like a camera:
frame ``k`` is released when ``clock.now_s() >= start + (t_k - t_0) / speed``. The clock is
passed in, so tests drive it without sleeping and a simulator can use its virtual clock.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Iterator, Protocol

from onfly.observation import Observation

__all__ = ["PlaybackClock", "MonotonicClock", "RealtimeConfig", "RealtimeSource"]

log = logging.getLogger(__name__)


class PlaybackClock(Protocol):
    """What playback needs from a clock: the time, and waiting until a time (seconds)."""

    def now_s(self) -> float: ...

    def sleep_until_s(self, t_s: float) -> None: ...


class MonotonicClock:
    """Wall-clock time from ``time.monotonic`` (the default clock for real playback)."""

    def now_s(self) -> float:
        return time.monotonic()

    def sleep_until_s(self, t_s: float) -> None:
        delay = t_s - time.monotonic()
        if delay > 0:
            time.sleep(delay)


@dataclass(frozen=True)
class RealtimeConfig:
    """Playback options.

    Attributes
    ----------
    speed : recording seconds per clock second (1 = real time, 2 = twice as fast)
    drop_late_s : a frame whose release time passed more than this many seconds ago is
        dropped, as a camera would drop it when the consumer is slow; None never drops
    restamp : give each observation the clock time at release instead of its recorded time
    """

    speed: float = 1.0
    drop_late_s: float | None = None
    restamp: bool = False

    def __post_init__(self) -> None:
        if not (self.speed > 0 and self.speed < float("inf")):
            raise ValueError(f"RealtimeConfig.speed must be positive and finite, got {self.speed}")
        if self.drop_late_s is not None and not (self.drop_late_s >= 0):
            raise ValueError(f"RealtimeConfig.drop_late_s must be >= 0 or None, got {self.drop_late_s}")


class RealtimeSource:
    """Wrap a source so iterating it releases frames at their recorded pace.

    Parameters
    ----------
    source : any :class:`onfly.readers.base.ObservationSource`
    config : :class:`RealtimeConfig`
    clock : :class:`PlaybackClock`; :class:`MonotonicClock` by default

    Attributes
    ----------
    dropped : frames dropped for lateness in the last iteration
    """

    def __init__(self, source, config: RealtimeConfig = RealtimeConfig(), clock: PlaybackClock | None = None) -> None:
        self.source = source
        self.config = config
        self.clock = clock if clock is not None else MonotonicClock()
        self.kind = getattr(source, "kind", "source")
        self.path = getattr(source, "path", None)
        self.dropped = 0

    def __enter__(self) -> "RealtimeSource":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def close(self) -> None:
        self.source.close()

    def __len__(self) -> int:
        return len(self.source)

    def __iter__(self) -> Iterator[Observation]:
        cfg = self.config
        self.dropped = 0
        start_s = None
        t0 = None
        for obs in self.source:
            if start_s is None:
                start_s, t0 = self.clock.now_s(), obs.t_s
            due_s = start_s + (obs.t_s - t0) / cfg.speed
            now = self.clock.now_s()
            if cfg.drop_late_s is not None and now - due_s > cfg.drop_late_s:
                self.dropped += 1
                log.debug("dropped late frame %s (%.3f s late)", obs.frame_id, now - due_s)
                continue
            if now < due_s:
                self.clock.sleep_until_s(due_s)
            if cfg.restamp:
                obs = dataclasses.replace(obs, t_s=self.clock.now_s())
            yield obs
