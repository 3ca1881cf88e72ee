"""Vision features computed once per frame and shared by every reader.

Both agents and the verifier ask for the features of the same camera frame; the vision tower
must run once. :class:`FeatureCache` wraps a backend (its ``features``) or any function
``VlmImage -> VisionFeatures | None`` and keys results on :attr:`VlmImage.frame_id`:

- a hit never recomputes (``stats`` counts computations);
- concurrent requests for one frame wait for a single computation instead of starting their
  own; a failed computation is raised to every waiter and nothing is stored, so a later
  request tries again;
- ``None`` (a backend without features) is cached like any result;
- least recently used frames are evicted beyond ``capacity``.

``frame_id`` must be unique per camera frame. A cached frame asked for again with an image of
another size is refused with :class:`FrameIdCollisionError` rather than served wrong features.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

from vlm.types import VisionFeatures, VlmBackend, VlmImage

__all__ = ["FeatureCache", "FeatureCacheStats", "FrameIdCollisionError"]


class FrameIdCollisionError(ValueError):
    """One frame id was used for two different images."""


@dataclass(frozen=True)
class FeatureCacheStats:
    """Counters since construction (or :meth:`FeatureCache.clear`)."""

    hits: int = 0
    misses: int = 0
    computations: int = 0
    evictions: int = 0


class _InFlight:
    def __init__(self) -> None:
        self.done = threading.Event()
        self.result: VisionFeatures | None = None
        self.error: BaseException | None = None


class FeatureCache:
    """LRU cache of per-frame vision features (see the module docstring). Thread-safe.

    Parameters
    ----------
    source : a backend with ``features(image)``, or a callable ``image -> VisionFeatures | None``
    capacity : frames kept (>= 1)
    """

    def __init__(self, source: VlmBackend | Callable[[VlmImage], VisionFeatures | None], capacity: int = 32) -> None:
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be an int >= 1, got {capacity!r}")
        features = getattr(source, "features", None)
        if callable(features):
            self._compute = features
        elif callable(source):
            self._compute = source
        else:
            raise TypeError(f"source must be a backend with features() or a callable, got {type(source).__name__}")
        self.capacity = capacity
        self._entries: OrderedDict[str, VisionFeatures | None] = OrderedDict()
        self._sizes: dict[str, tuple[int, int]] = {}
        self._inflight: dict[str, _InFlight] = {}
        self._lock = threading.Lock()
        self._hits = self._misses = self._computations = self._evictions = 0

    def get(self, image: VlmImage) -> VisionFeatures | None:
        """Features of ``image``, computed at most once per ``frame_id`` while it is cached."""
        if not isinstance(image, VlmImage):
            raise TypeError(f"image must be a VlmImage, got {type(image).__name__}")
        key = image.frame_id
        with self._lock:
            if key in self._entries:
                self._check_size(key, image)
                self._entries.move_to_end(key)
                self._hits += 1
                return self._entries[key]
            pending = self._inflight.get(key)
            if pending is None:
                pending = self._inflight[key] = _InFlight()
                self._misses += 1
                owner = True
            else:
                self._hits += 1
                owner = False
        if not owner:
            pending.done.wait()
            if pending.error is not None:
                raise pending.error
            return pending.result
        try:
            result = self._compute(image)
            if result is not None and not isinstance(result, VisionFeatures):
                raise TypeError(f"features source returned {type(result).__name__}, expected VisionFeatures or None")
        except BaseException as exc:
            with self._lock:
                self._computations += 1
                del self._inflight[key]
            pending.error = exc
            pending.done.set()
            raise
        with self._lock:
            self._computations += 1
            self._entries[key] = result
            self._sizes[key] = image.size
            del self._inflight[key]
            while len(self._entries) > self.capacity:
                old, _ = self._entries.popitem(last=False)
                self._sizes.pop(old, None)
                self._evictions += 1
        pending.result = result
        pending.done.set()
        return result

    __call__ = get

    def _check_size(self, key: str, image: VlmImage) -> None:
        if self._sizes.get(key) != image.size:
            raise FrameIdCollisionError(f"frame_id {key!r} was cached for an image of size {self._sizes.get(key)} "
                                        f"and is now given one of size {image.size}")

    def __contains__(self, frame_id: str) -> bool:
        with self._lock:
            return frame_id in self._entries

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    @property
    def stats(self) -> FeatureCacheStats:
        with self._lock:
            return FeatureCacheStats(self._hits, self._misses, self._computations, self._evictions)

    def clear(self) -> None:
        """Forget every frame and reset the counters (computations in flight still finish)."""
        with self._lock:
            self._entries.clear()
            self._sizes.clear()
            self._hits = self._misses = self._computations = self._evictions = 0
