"""Live camera input for the onboard loop: any observation stream, newest frame first.

The pilot ticks at 10 Hz and must never wait for a camera. :class:`CameraFeed` runs a
blocking observation iterable (a :class:`~onfly.mavlink.camera_channel.FrameClient`, a
recording played by :class:`~onfly.readers.realtime.RealtimeSource`, a RealSense, a polled
renderer) on its own thread and keeps only the newest frame; :meth:`CameraFeed.latest` hands
it out once, without blocking. Frames the pilot did not take in time are counted as skipped,
like a camera driver dropping frames for a slow consumer.

:func:`open_camera` builds the feed from a command-line spec:

=====================  ===============================================================
spec                   source
=====================  ===============================================================
``tcp://HOST:PORT``    a :class:`~onfly.mavlink.camera_channel.FrameServer` (the
                       simulated vehicle's camera, ``onfly sim-vehicle --camera``)
``realsense``          an Intel RealSense (optional extra, :mod:`onfly.sources.realsense`)
a path                 an OnFly log, TUM RGB-D folder or ROS bag played at real time
=====================  ===============================================================

:class:`PolledSource` turns any ``fn() -> Observation`` (the embedded world's renderer) into
such a stream at a fixed rate on a :class:`~onfly.readers.realtime.PlaybackClock`.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from onfly.observation import Observation
from onfly.readers.realtime import MonotonicClock, PlaybackClock, RealtimeConfig, RealtimeSource

__all__ = ["CameraError", "CameraFeed", "PolledSource", "open_camera"]

log = logging.getLogger(__name__)


class CameraError(ValueError):
    """A camera spec that names no usable source."""


class PolledSource:
    """An observation stream that calls ``fn()`` every ``period_s`` seconds of ``clock``.

    ``fn`` returns an :class:`Observation` or None (nothing this time). Iteration never ends by
    itself; stop it by closing the :class:`CameraFeed` that runs it.
    """

    kind = "polled"
    path = None

    def __init__(self, fn: Callable[[], Observation | None], period_s: float, clock: PlaybackClock | None = None) -> None:
        if not (np.isfinite(period_s) and period_s > 0):
            raise ValueError(f"PolledSource.period_s must be positive, got {period_s}")
        self.fn = fn
        self.period_s = float(period_s)
        self.clock = clock if clock is not None else MonotonicClock()
        self._closed = threading.Event()

    def __iter__(self) -> Iterator[Observation]:
        next_s = self.clock.now_s()
        while not self._closed.is_set():
            self.clock.sleep_until_s(next_s)
            if self._closed.is_set():
                return
            next_s = max(next_s + self.period_s, self.clock.now_s())
            obs = self.fn()
            if obs is not None:
                yield obs

    def close(self) -> None:
        self._closed.set()

    def __enter__(self) -> "PolledSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class CameraFeed:
    """Runs an observation iterable on a thread and keeps its newest frame.

    Parameters
    ----------
    source : iterable of :class:`Observation` (closed by :meth:`close` if it has ``close``)
    clock : the pilot's clock (seconds); used to restamp frames and for ages
    restamp : replace each frame's ``t_s`` by ``clock()`` at arrival (the companion's time;
        the frame's pose is kept). Leave False only when the source already stamps frames on
        the pilot's clock.
    name : for logs
    retry_s : after a ConnectionError (server not up yet) wait this long and read again

    Attributes
    ----------
    received : frames that arrived
    taken : frames handed out by :meth:`latest`
    skipped : frames overwritten by a newer one before the pilot took them
    timeouts : times the source reported no frame within its timeout (it is then read again)
    reconnects : ConnectionErrors retried
    ended : the source ended (end of a recording, server closed the stream)
    error : the exception that stopped the source, or None
    """

    def __init__(
        self,
        source: Iterable[Observation],
        *,
        clock: Callable[[], float] = time.monotonic,
        restamp: bool = True,
        name: str = "camera",
        retry_s: float = 0.5,
    ) -> None:
        if not (np.isfinite(retry_s) and retry_s > 0):
            raise ValueError(f"CameraFeed.retry_s must be positive, got {retry_s}")
        self.source = source
        self.retry_s = float(retry_s)
        self.reconnects = 0
        self.clock = clock
        self.restamp = bool(restamp)
        self.name = name
        self.received = 0
        self.taken = 0
        self.skipped = 0
        self.timeouts = 0
        self.ended = False
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._newest: Observation | None = None
        self._fresh = False
        self._last_arrival_s: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "CameraFeed":
        if self._thread is not None:
            raise RuntimeError(f"camera feed {self.name} already started")
        self._thread = threading.Thread(target=self._run, name=f"camera-{self.name}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop reading and close the source (idempotent)."""
        self._stop.set()
        closer = getattr(self.source, "close", None)
        if closer is not None:
            try:
                closer()
            except Exception:  # closing must never raise in a shutdown path
                log.exception("closing camera source %s failed", self.name)
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def __enter__(self) -> "CameraFeed":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def latest(self) -> Observation | None:
        """The newest frame not yet handed out, or None (never blocks)."""
        with self._lock:
            if not self._fresh:
                return None
            self._fresh = False
            self.taken += 1
            return self._newest

    def peek(self) -> Observation | None:
        """The newest frame, whether or not it was handed out already."""
        with self._lock:
            return self._newest

    def age_s(self, now_s: float | None = None) -> float:
        """Seconds since the newest frame arrived (inf before the first)."""
        with self._lock:
            t = self._last_arrival_s
        if t is None:
            return float("inf")
        return max(0.0, (self.clock() if now_s is None else now_s) - t)

    def stats(self) -> dict:
        """Counters for run summaries."""
        return {
            "received": self.received,
            "taken": self.taken,
            "skipped": self.skipped,
            "timeouts": self.timeouts,
            "reconnects": self.reconnects,
            "ended": self.ended,
            "error": None if self.error is None else repr(self.error),
        }

    def _put(self, obs: Observation) -> None:
        now = self.clock()
        if self.restamp:
            obs = dataclasses.replace(obs, t_s=float(now))
        with self._lock:
            if self._fresh:
                self.skipped += 1
            self._newest = obs
            self._fresh = True
            self._last_arrival_s = now
            self.received += 1

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                for obs in self.source:
                    if self._stop.is_set():
                        return
                    if not isinstance(obs, Observation):
                        raise TypeError(f"camera source {self.name} yielded {type(obs).__name__}, not an Observation")
                    self._put(obs)
                self.ended = True
                log.info("camera %s: stream ended after %d frames", self.name, self.received)
                return
            except TimeoutError:
                self.timeouts += 1
                log.warning("camera %s: no frame within the source's timeout; reading again", self.name)
            except ConnectionError as exc:  # the server is not up yet (or restarted): try again
                self.reconnects += 1
                log.warning("camera %s: %s; retrying in %.1f s", self.name, exc, self.retry_s)
                if self._stop.wait(self.retry_s):
                    return
            except Exception as exc:  # the feed reports, the pilot keeps flying without frames
                if self._stop.is_set():
                    return
                self.error = exc
                log.error("camera %s stopped: %r", self.name, exc)
                return


def open_camera(
    spec: str,
    *,
    clock: PlaybackClock | None = None,
    pose_source: Callable[[], np.ndarray | None] | None = None,
    speed: float = 1.0,
    timeout_s: float = 5.0,
) -> CameraFeed:
    """A (not yet started) :class:`CameraFeed` for ``spec`` (see the module docstring).

    Parameters
    ----------
    spec : ``tcp://HOST:PORT``, ``realsense`` or a recording path
    clock : the pilot's clock (:class:`~onfly.readers.realtime.MonotonicClock` by default);
        recordings are played on it and frames restamped by it
    pose_source : RealSense only: ``() -> T_world_body (4, 4)`` or None, the vehicle pose at
        capture (the bridge's state); a RealSense has no pose of its own
    speed : recordings only: playback speed (1 = real time)
    timeout_s : tcp only: a read with no frame for this long is retried (and counted)

    Raises
    ------
    CameraError : an unusable spec (naming the valid forms)
    onfly.sources.realsense.RealSenseUnavailableError : ``realsense`` without the extra
    """
    clock = clock if clock is not None else MonotonicClock()
    if not isinstance(spec, str) or not spec.strip():
        raise CameraError(f"camera spec must be tcp://HOST:PORT, 'realsense' or a recording path, got {spec!r}")
    spec = spec.strip()
    if spec.startswith("tcp://"):
        from onfly.mavlink.camera_channel import FrameChannelError, FrameClient

        try:
            client = FrameClient(spec, timeout_s=timeout_s)
        except FrameChannelError as exc:
            raise CameraError(str(exc)) from exc
        return CameraFeed(client, clock=clock.now_s, restamp=True, name=spec)
    if spec == "realsense":
        from onfly.sources.realsense import RealSenseConfig, RealSenseSource

        if pose_source is None:
            raise CameraError("a RealSense camera needs pose_source (the vehicle pose at capture, from the MAVLink bridge)")
        return CameraFeed(RealSenseSource(RealSenseConfig(), pose_source, clock=clock.now_s), clock=clock.now_s, restamp=False, name="realsense")
    if "://" in spec:
        raise CameraError(f"unsupported camera URL {spec!r}: use tcp://HOST:PORT, 'realsense' or a recording path")
    path = Path(spec).expanduser()
    from onfly.readers.base import SourceKindError, open_source

    try:
        recording = open_source(path)
    except SourceKindError as exc:
        raise CameraError(f"camera {spec!r}: {exc}") from exc
    player = RealtimeSource(recording, RealtimeConfig(speed=speed, drop_late_s=0.5, restamp=True), clock=clock)
    return CameraFeed(player, clock=clock.now_s, restamp=False, name=str(path))
