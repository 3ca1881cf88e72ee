"""Monitoring memories: the paper's hybrid keyframe memory and the two ablation alternatives.

Each memory receives every observed frame (:meth:`observe`) and, at each monitoring call,
returns the ordered frame list ``M_t = [o_1, Q_t, o_t]`` (:meth:`select`). Items carry an
opaque ``payload`` (the image handed to the VLM) so this module depends on nothing but numpy.

Hybrid memory (paper, "Monitoring Agent with Hybrid Memory"), three steps per monitoring call:

1. **Keyframe maintenance.** Frames whose accumulated translation since the last candidate
   reaches ``keyframe_translation_m`` or accumulated |yaw change| reaches
   ``keyframe_rotation_rad`` become candidates ``C_t``. ``Dedup(C_t, eps)`` drops a candidate
   whose cosine distance to an already kept candidate of the set is below ``dedup_eps``.
   ``Merge(U_{t-1}, C_new, eps)``: for each new candidate, the ``nearest_l`` pool items closest
   in position are searched for the most similar feature; a cosine distance below
   ``dedup_eps`` marks a duplicate (the pool entry is kept unchanged, the candidate dropped),
   otherwise the candidate is appended to the pool.
2. **Keyframe selection.** The travelled distance ``[0, D_t]`` is split into ``S`` equal
   segments; each pool item belongs to the segment of its odometry distance. Each segment's
   winner is the previous winner if it is still in that segment (sticky rule), else the item
   closest to the segment centre, ties broken toward the most recently added item.
3. **Prefix-stable serialization.** ``Q_t`` keeps the longest prefix of ``Q_{t-1}`` whose
   items are still winners, appends the other winners (no duplicates), fills remaining slots
   with unused recent pool items (most recent first), then recent observed frames if the pool
   is still short, and is sorted chronologically. ``|Q_t| = S`` whenever at least ``S + 2``
   frames have been observed (``o_1`` and ``o_t`` are never in ``Q_t``).

Concurrency: the pilot's control thread observes every frame while the monitoring call runs on
a worker. :meth:`snapshot` (call it on the control thread when the call is started) runs the
selection and returns an immutable :class:`MemorySnapshot`; the worker reads only that. Every
memory also serializes ``observe`` / ``select`` / ``snapshot`` with a lock, so a selection can
never see a frame half-recorded (odometry advanced, ``latest`` not yet moved).

Alternatives with the same interface: :class:`SlidingWindowMemory` (``Q_t`` = the latest ``S``
frames before ``o_t``) and :class:`TimeSamplingMemory` (``Q_t`` = ``S`` frames uniformly spaced
in time between ``o_1`` and ``o_t``).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from planning.frames import wrap_angle

__all__ = [
    "MemoryConfig",
    "MemoryError",
    "FrameRecord",
    "MemorySnapshot",
    "MonitoringMemory",
    "HybridMemory",
    "SlidingWindowMemory",
    "TimeSamplingMemory",
    "make_memory",
    "MEMORY_STRATEGIES",
]

MEMORY_STRATEGIES = ("hybrid", "sliding", "time")


class MemoryError(ValueError):
    """Invalid memory configuration or input."""


@dataclass(frozen=True)
class MemoryConfig:
    """Parameters of the monitoring memory (paper default ``S = 4``).

    Attributes
    ----------
    strategy : "hybrid" | "sliding" | "time"
    slots : S, keyframes between the first and the latest frame
    keyframe_translation_m : accumulated travel that makes a frame a keyframe candidate
    keyframe_rotation_rad : accumulated |yaw change| that makes a frame a candidate
    dedup_eps : cosine-distance threshold below which two frames are duplicates
    nearest_l : L, pool items (nearest by position) searched for a duplicate
    recent_frames : how many recent observed frames are kept for filling and for the
        sliding window (>= slots)
    """

    strategy: str = "hybrid"
    slots: int = 4
    keyframe_translation_m: float = 1.0
    keyframe_rotation_rad: float = 0.35
    dedup_eps: float = 0.05
    nearest_l: int = 8
    recent_frames: int = 64

    def __post_init__(self) -> None:
        if self.strategy not in MEMORY_STRATEGIES:
            raise MemoryError(f"strategy must be one of {MEMORY_STRATEGIES}, got {self.strategy!r}")
        if self.slots < 1:
            raise MemoryError(f"slots must be >= 1, got {self.slots}")
        if self.keyframe_translation_m <= 0 or self.keyframe_rotation_rad <= 0:
            raise MemoryError("keyframe thresholds must be positive")
        if not (0.0 <= self.dedup_eps < 2.0):
            raise MemoryError(f"dedup_eps must be in [0, 2), got {self.dedup_eps}")
        if self.nearest_l < 1:
            raise MemoryError(f"nearest_l must be >= 1, got {self.nearest_l}")
        if self.recent_frames < self.slots:
            raise MemoryError(f"recent_frames ({self.recent_frames}) must be >= slots ({self.slots})")


@dataclass(frozen=True, eq=False)
class FrameRecord:
    """One observed frame as the memory sees it.

    Attributes
    ----------
    seq : int, observation order (0 for the first frame)
    frame_id : str
    t_s : float, seconds
    position : array (3,), metres, world frame
    yaw : float, radians
    odom_m : float, distance travelled when the frame was observed, metres
    feature : array (C,), unit-norm global descriptor (cosine similarity = dot product)
    payload : anything (the image the VLM gets)
    """

    seq: int
    frame_id: str
    t_s: float
    position: np.ndarray
    yaw: float
    odom_m: float
    feature: np.ndarray
    payload: Any = None


@dataclass(frozen=True)
class MemorySnapshot:
    """``M_t = [o_1, Q_t, o_t]`` as selected at one instant; immutable, safe to hand to a worker.

    Attributes
    ----------
    records : tuple of FrameRecord, oldest first (empty before the first frame)
    """

    records: tuple[FrameRecord, ...]

    @property
    def frame_ids(self) -> tuple[str, ...]:
        return tuple(r.frame_id for r in self.records)

    @property
    def judged(self) -> FrameRecord | None:
        """``o_t``, the frame the monitoring call judges (its pose is the normal point)."""
        return self.records[-1] if self.records else None


class MonitoringMemory(Protocol):
    """What the monitoring agent needs from a memory."""

    config: MemoryConfig

    def observe(self, frame_id: str, t_s: float, position, yaw: float, feature, payload: Any = None) -> FrameRecord: ...

    def select(self) -> list[FrameRecord]: ...

    def snapshot(self) -> MemorySnapshot: ...


def _unit(feature) -> np.ndarray:
    f = np.asarray(feature, dtype=float).reshape(-1)
    if f.size == 0 or not np.all(np.isfinite(f)):
        raise MemoryError("feature must be a non-empty finite vector")
    n = np.linalg.norm(f)
    return f / n if n > 0 else f


class _Base:
    def __init__(self, config: MemoryConfig | None = None) -> None:
        self.config = config or MemoryConfig()
        self.first: FrameRecord | None = None
        self.latest: FrameRecord | None = None
        self.recent: list[FrameRecord] = []
        self.odom_m = 0.0
        self._seq = 0
        self._lock = threading.RLock()

    def observe(self, frame_id: str, t_s: float, position, yaw: float, feature, payload: Any = None) -> FrameRecord:
        """Record one frame (thread-safe against :meth:`select` and :meth:`snapshot`)."""
        with self._lock:
            return self._observe(frame_id, t_s, position, yaw, feature, payload)

    def select(self) -> list[FrameRecord]:
        """``M_t = [o_1, Q_t, o_t]`` (thread-safe; updates the selection state)."""
        with self._lock:
            return self._select()

    def snapshot(self) -> MemorySnapshot:
        """Select now and freeze the result (call on the control thread, hand to the worker)."""
        with self._lock:
            return MemorySnapshot(tuple(self._select()))

    def _record(self, frame_id, t_s, position, yaw, feature, payload) -> FrameRecord:
        p = np.asarray(position, dtype=float).reshape(3)
        if not np.all(np.isfinite(p)) or not np.isfinite(yaw) or not np.isfinite(t_s):
            raise MemoryError(f"frame {frame_id!r}: position, yaw and t_s must be finite")
        if self.latest is not None:
            if t_s < self.latest.t_s:
                raise MemoryError(f"frame {frame_id!r}: time went backwards ({t_s} < {self.latest.t_s})")
            self.odom_m += float(np.linalg.norm(p - self.latest.position))
        rec = FrameRecord(self._seq, str(frame_id), float(t_s), p, float(yaw), self.odom_m, _unit(feature), payload)
        self._seq += 1
        if self.first is None:
            self.first = rec
        self.latest = rec
        self.recent.append(rec)
        if len(self.recent) > self.config.recent_frames:
            del self.recent[0]
        return rec

    def _assemble(self, queue: list[FrameRecord]) -> list[FrameRecord]:
        if self.first is None or self.latest is None:
            return []
        if self.latest is self.first:
            return [self.first]
        return [self.first, *queue, self.latest]

    def _middle_recent(self) -> list[FrameRecord]:
        """Recent frames excluding o_1 and o_t, oldest first."""
        return [r for r in self.recent if r is not self.first and r is not self.latest]


class HybridMemory(_Base):
    """The paper's first-frame + keyframes + latest-frame memory (see module docstring)."""

    def __init__(self, config: MemoryConfig | None = None) -> None:
        super().__init__(config)
        self.pool: list[FrameRecord] = []
        self.queue: list[FrameRecord] = []  # Q_{t-1}, chronological
        self.winners: dict[int, FrameRecord] = {}
        self._pending: list[FrameRecord] = []  # C_t, candidates since the last select()
        self._acc_trans = 0.0
        self._acc_rot = 0.0

    def _observe(self, frame_id: str, t_s: float, position, yaw: float, feature, payload: Any = None) -> FrameRecord:
        prev = self.latest
        rec = self._record(frame_id, t_s, position, yaw, feature, payload)
        if prev is not None:
            self._acc_trans += float(np.linalg.norm(rec.position - prev.position))
            self._acc_rot += abs(wrap_angle(rec.yaw - prev.yaw))
            if (
                self._acc_trans >= self.config.keyframe_translation_m
                or self._acc_rot >= self.config.keyframe_rotation_rad
            ):
                self._pending.append(rec)
                self._acc_trans = 0.0
                self._acc_rot = 0.0
        return rec

    # -- step 1 ------------------------------------------------------------------------------
    def dedup(self, candidates: list[FrameRecord]) -> list[FrameRecord]:
        """``Dedup(C_t, eps)``: keep a candidate unless it is within ``eps`` of a kept one."""
        kept: list[FrameRecord] = []
        for c in candidates:
            if all(1.0 - float(c.feature @ k.feature) >= self.config.dedup_eps for k in kept):
                kept.append(c)
        return kept

    def merge(self, candidates: list[FrameRecord]) -> list[FrameRecord]:
        """``Merge(U, C_new, eps)``; returns the candidates that entered the pool."""
        added = []
        for c in candidates:
            if self.pool:
                pos = np.array([u.position for u in self.pool])
                d = np.linalg.norm(pos - c.position, axis=1)
                near = np.argsort(d, kind="stable")[: self.config.nearest_l]
                sims = np.array([self.pool[i].feature @ c.feature for i in near])
                if 1.0 - float(sims.max()) < self.config.dedup_eps:
                    continue
            self.pool.append(c)
            added.append(c)
        return added

    # -- step 2 ------------------------------------------------------------------------------
    def segment_of(self, odom_m: float, total_m: float) -> int:
        """Segment index in ``[0, S)`` of a pool item at odometry distance ``odom_m``."""
        s = self.config.slots
        if total_m <= 0:
            return 0
        return int(min(s - 1, max(0, np.floor(odom_m / total_m * s))))

    def select_winners(self) -> dict[int, FrameRecord]:
        s = self.config.slots
        total = self.odom_m
        seg_len = total / s if total > 0 else 0.0
        by_seg: dict[int, list[FrameRecord]] = {}
        for u in self.pool:
            by_seg.setdefault(self.segment_of(u.odom_m, total), []).append(u)
        winners: dict[int, FrameRecord] = {}
        for k, items in by_seg.items():
            prev = self.winners.get(k)
            if prev is not None and any(prev is u for u in items):
                winners[k] = prev
                continue
            centre = (k + 0.5) * seg_len
            # closest to the centre; ties toward the most recently added (higher seq)
            winners[k] = min(items, key=lambda u: (round(abs(u.odom_m - centre), 9), -u.seq))
        self.winners = winners
        return winners

    # -- step 3 ------------------------------------------------------------------------------
    def serialize(self, winners: dict[int, FrameRecord]) -> list[FrameRecord]:
        s = self.config.slots
        win_ids = {id(w) for w in winners.values()}
        # o_1 and o_t frame the list; they never take a keyframe slot
        excluded = {id(self.first), id(self.latest)}
        q: list[FrameRecord] = []
        for item in self.queue:  # longest valid prefix of Q_{t-1}
            if id(item) not in win_ids or id(item) in excluded:
                break
            q.append(item)
        used = {id(x) for x in q}
        for w in sorted(winners.values(), key=lambda r: r.seq):
            if len(q) >= s:
                break
            if id(w) not in used and id(w) not in excluded:
                q.append(w)
                used.add(id(w))
        for pool_item in sorted(self.pool, key=lambda r: -r.seq):
            if len(q) >= s:
                break
            if id(pool_item) not in used and id(pool_item) not in excluded:
                q.append(pool_item)
                used.add(id(pool_item))
        for r in reversed(self._middle_recent()):
            if len(q) >= s:
                break
            if id(r) not in used:
                q.append(r)
                used.add(id(r))
        q.sort(key=lambda r: r.seq)
        self.queue = q
        return q

    def _select(self) -> list[FrameRecord]:
        """Run the three steps and return ``M_t = [o_1, Q_t, o_t]``."""
        cands, self._pending = self._pending, []
        self.merge(self.dedup(cands))
        return self._assemble(self.serialize(self.select_winners()))


class SlidingWindowMemory(_Base):
    """``Q_t`` = the latest ``S`` observed frames before ``o_t`` (ablation)."""

    def _observe(self, frame_id: str, t_s: float, position, yaw: float, feature, payload: Any = None) -> FrameRecord:
        return self._record(frame_id, t_s, position, yaw, feature, payload)

    def _select(self) -> list[FrameRecord]:
        return self._assemble(self._middle_recent()[-self.config.slots :])


class TimeSamplingMemory(_Base):
    """``Q_t`` = ``S`` frames closest to uniformly spaced times in ``(t_1, t_now)`` (ablation).

    All observed frames are kept (only their small records; payloads of frames that can no
    longer be chosen are still referenced, so callers should pass light payloads).
    """

    def __init__(self, config: MemoryConfig | None = None) -> None:
        super().__init__(config)
        self.history: list[FrameRecord] = []

    def _observe(self, frame_id: str, t_s: float, position, yaw: float, feature, payload: Any = None) -> FrameRecord:
        rec = self._record(frame_id, t_s, position, yaw, feature, payload)
        self.history.append(rec)
        return rec

    def _select(self) -> list[FrameRecord]:
        if self.first is None or self.latest is None:
            return []
        middle = self.history[1:-1]
        s = self.config.slots
        if len(middle) <= s:
            return self._assemble(middle)
        t0, t1 = self.first.t_s, self.latest.t_s
        times = np.array([r.t_s for r in middle])
        chosen: list[int] = []
        for j in range(1, s + 1):
            target = t0 + (t1 - t0) * j / (s + 1)
            order = np.argsort(np.abs(times - target), kind="stable")
            for i in order:
                if int(i) not in chosen:
                    chosen.append(int(i))
                    break
        return self._assemble([middle[i] for i in sorted(chosen)])


def make_memory(config: MemoryConfig | None = None) -> HybridMemory | SlidingWindowMemory | TimeSamplingMemory:
    """The memory named by ``config.strategy``."""
    config = config or MemoryConfig()
    return {"hybrid": HybridMemory, "sliding": SlidingWindowMemory, "time": TimeSamplingMemory}[config.strategy](config)
