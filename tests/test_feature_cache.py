"""Feature cache: once per frame, LRU, thread-safe, shared by every reader."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from vlm.backend_transformers import TransformersBackend, TransformersBackendConfig
from vlm.feature_cache import FeatureCache, FeatureCacheStats, FrameIdCollisionError
from vlm.tiny_models import build_tiny_vlm
from vlm.types import VisionFeatures, VlmImage


def _image(frame_id: str, seed: int = 0, shape=(24, 32, 3)) -> VlmImage:
    rng = np.random.default_rng(seed)
    return VlmImage(rng.integers(0, 256, shape, dtype=np.uint8), frame_id)


class CountingSource:
    """Features = mean colour per 8 px patch; counts calls per frame."""

    def __init__(self) -> None:
        self.calls: dict[str, int] = {}
        self.lock = threading.Lock()

    def __call__(self, image: VlmImage) -> VisionFeatures:
        with self.lock:
            self.calls[image.frame_id] = self.calls.get(image.frame_id, 0) + 1
        h, w, _ = image.rgb.shape
        grid = image.rgb.reshape(h // 8, 8, w // 8, 8, 3).mean(axis=(1, 3)).astype(np.float32)
        return VisionFeatures(grid=grid, patch_px=8.0, image_size=image.size, source="test:mean")


def test_hit_never_recomputes_and_returns_the_same_object():
    source = CountingSource()
    cache = FeatureCache(source, capacity=4)
    image = _image("f1")
    first = cache.get(image)
    for _ in range(5):  # decision agent, monitoring agent, verifier, ...
        assert cache.get(image) is first
    assert source.calls == {"f1": 1}
    assert cache.stats == FeatureCacheStats(hits=5, misses=1, computations=1, evictions=0)
    np.testing.assert_array_equal(first.grid, source(image).grid)


def test_lru_eviction_keeps_recently_used_frames():
    source = CountingSource()
    cache = FeatureCache(source, capacity=2)
    a, b, c = _image("a", 1), _image("b", 2), _image("c", 3)
    cache(a)
    cache(b)
    cache(a)  # a is now the most recent
    cache(c)  # evicts b
    assert "a" in cache and "c" in cache and "b" not in cache and len(cache) == 2
    cache(b)
    assert source.calls == {"a": 1, "b": 2, "c": 1}
    assert cache.stats.evictions == 2


def test_none_is_cached_for_backends_without_features():
    class NoFeatures:
        calls = 0

        def features(self, image):
            NoFeatures.calls += 1
            return None

    cache = FeatureCache(NoFeatures(), capacity=3)
    assert cache.get(_image("x")) is None and cache.get(_image("x")) is None
    assert NoFeatures.calls == 1


def test_concurrent_requests_for_one_frame_compute_once():
    release = threading.Event()
    source = CountingSource()

    def slow(image):
        release.wait(timeout=10)
        return source(image)

    cache = FeatureCache(slow, capacity=8)
    image = _image("shared")
    results: list = [None] * 8
    threads = [threading.Thread(target=lambda k=k: results.__setitem__(k, cache.get(image))) for k in range(8)]
    for t in threads:
        t.start()
    release.set()
    for t in threads:
        t.join(timeout=10)
    assert source.calls == {"shared": 1}
    assert all(r is results[0] for r in results) and results[0] is not None
    assert cache.stats.computations == 1 and cache.stats.hits + cache.stats.misses == 8


def test_failure_reaches_every_waiter_and_is_not_cached():
    release = threading.Event()
    attempts = []

    def flaky(image):
        attempts.append(image.frame_id)
        if len(attempts) == 1:
            release.wait(timeout=10)
            raise RuntimeError("vision tower failed")
        return CountingSource()(image)

    cache = FeatureCache(flaky, capacity=2)
    image = _image("f")
    errors: list = []

    def reader():
        try:
            cache.get(image)
        except RuntimeError as exc:
            errors.append(str(exc))

    threads = [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    release.set()
    for t in threads:
        t.join(timeout=10)
    assert errors == ["vision tower failed"] * 3
    assert "f" not in cache
    assert cache.get(image).source == "test:mean"  # the next request tries again
    assert attempts == ["f", "f"]


def test_reused_frame_id_with_another_image_is_refused():
    cache = FeatureCache(CountingSource(), capacity=2)
    cache.get(_image("f", shape=(24, 32, 3)))
    with pytest.raises(FrameIdCollisionError, match="frame_id 'f'"):
        cache.get(_image("f", shape=(16, 16, 3)))


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="capacity"):
        FeatureCache(CountingSource(), capacity=0)
    with pytest.raises(TypeError, match="features"):
        FeatureCache(42)
    with pytest.raises(TypeError, match="VisionFeatures"):
        FeatureCache(lambda image: "not features").get(_image("g"))
    with pytest.raises(TypeError, match="VlmImage"):
        FeatureCache(CountingSource()).get(np.zeros((4, 4, 3), np.uint8))


def test_clear_forgets_frames_and_counters():
    source = CountingSource()
    cache = FeatureCache(source, capacity=2)
    cache.get(_image("f"))
    cache.clear()
    assert len(cache) == 0 and cache.stats == FeatureCacheStats()
    cache.get(_image("f"))
    assert source.calls == {"f": 2}


def test_shares_real_vision_tower_features(tmp_path):
    backend = TransformersBackend(TransformersBackendConfig(str(build_tiny_vlm(tmp_path / "m", seed=0))))
    calls = []
    original = backend.features

    def counted(image):
        calls.append(image.frame_id)
        return original(image)

    backend.features = counted
    cache = FeatureCache(backend, capacity=4)
    image = _image("cam-17", shape=(56, 84, 3))
    first = cache.get(image)
    assert cache.get(image) is first and calls == ["cam-17"]
    assert first.grid.shape == (2, 3, 64) and first.source == "qwen2_5_vl.visual"
    np.testing.assert_array_equal(first.grid, original(image).grid)
