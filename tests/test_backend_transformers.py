"""In-process transformers backend on tiny random-weight Qwen2.5-VL and Qwen3-VL models.

The reference for every output is transformers' own ``generate`` (greedy) fed the processor's
inputs the standard way: the backend's token loop, M-RoPE positions and prefix reuse must
reproduce it token for token.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import torch
from PIL import Image
from transformers import AutoImageProcessor, AutoModelForImageTextToText, AutoTokenizer

from vlm.backend_transformers import (
    DeadlineCriteria,
    TransformersBackend,
    TransformersBackendConfig,
    TransformersBackendError,
)
from vlm.parsing import parse_point, parse_status
from vlm.tiny_models import build_tiny_vlm
from vlm.types import CallStatus, ChatMessage, VlmBackend, VlmImage

SYSTEM = ChatMessage("system", "You are the monitoring agent of a drone. Answer CONTINUE, STOP or LOST.")


def _images(n: int, seed: int = 0, shape=(120, 160, 3)) -> list[VlmImage]:
    rng = np.random.default_rng(seed)
    return [VlmImage(rng.integers(0, 256, shape, dtype=np.uint8), f"frame-{seed}-{i}") for i in range(n)]


def _two_image_chat() -> list[ChatMessage]:
    return [SYSTEM, ChatMessage("user", "First view <image> latest view <image> Subtask: stop at the red van.")]


class _Reference:
    """transformers' generate() on the standard processor inputs (no code of the backend)."""

    def __init__(self, path) -> None:
        self.model = AutoModelForImageTextToText.from_pretrained(path).eval()
        self.tokenizer = AutoTokenizer.from_pretrained(path)
        self.processor = AutoImageProcessor.from_pretrained(path)

    def prompt_ids(self, messages, images):
        hf, k = [], 0
        for m in messages:
            parts = []
            for i, text in enumerate(m.content.split("<image>")):
                if i:
                    parts.append({"type": "image"})
                    k += 1
                if text:
                    parts.append({"type": "text", "text": text})
            hf.append({"role": m.role, "content": parts})
        text = self.tokenizer.apply_chat_template(hf, add_generation_prompt=True, tokenize=False)
        vision = self.processor(images=[Image.fromarray(im.rgb) for im in images], return_tensors="pt") if images else None
        if vision is not None:
            chunks = text.split("<|image_pad|>")
            counts = (vision["image_grid_thw"].prod(-1) // 4).tolist()
            text = chunks[0] + "".join("<|image_pad|>" * n + c for n, c in zip(counts, chunks[1:]))
        ids = torch.tensor([self.tokenizer(text, add_special_tokens=False)["input_ids"]])
        return ids, vision

    def generate(self, messages, images, max_new_tokens):
        ids, vision = self.prompt_ids(messages, images)
        kwargs = {}
        if vision is not None:
            mm = (ids == self.model.config.image_token_id).to(torch.int32)
            kwargs = dict(pixel_values=vision["pixel_values"], image_grid_thw=vision["image_grid_thw"],
                          mm_token_type_ids=mm)
        with torch.inference_mode():
            out = self.model.generate(input_ids=ids, attention_mask=torch.ones_like(ids), max_new_tokens=max_new_tokens,
                                      do_sample=False, **kwargs)
        return self.tokenizer.decode(out[0, ids.shape[1]:], skip_special_tokens=True), ids.shape[1]


@pytest.fixture(scope="module", params=["qwen2_5_vl", "qwen3_vl"])
def tiny(request, tmp_path_factory):
    path = build_tiny_vlm(tmp_path_factory.mktemp(request.param), family=request.param, seed=0)
    backend = TransformersBackend(TransformersBackendConfig(str(path)))
    yield request.param, path, backend, _Reference(path)
    backend.close()


def test_backend_satisfies_the_protocol(tiny):
    _, _, backend, _ = tiny
    assert isinstance(backend, VlmBackend)
    assert backend.name.startswith("transformers:")


def test_two_image_call_returns_text_and_usage_equal_to_generate(tiny):
    _, _, backend, ref = tiny
    messages, images = _two_image_chat(), _images(2)
    response = backend.complete(messages, images, max_new_tokens=24)
    expected_text, n_prompt = ref.generate(messages, images, 24)
    assert response.status is CallStatus.OK, response.error
    assert response.text == expected_text
    assert response.usage.prompt_tokens == n_prompt
    assert 1 <= response.usage.completion_tokens <= 24
    assert response.usage.cached_tokens == 0
    assert response.latency_s > 0


def test_text_only_call_equals_generate(tiny):
    _, _, backend, ref = tiny
    messages = [ChatMessage("user", "Split: fly through the gate, then stop next to the red van.")]
    response = backend.complete(messages, (), max_new_tokens=12)
    assert response.ok, response.error
    assert response.text == ref.generate(messages, (), 12)[0]


def test_second_call_reuses_the_prefix_and_answers_exactly_as_uncached(tiny):
    _, _, backend, ref = tiny
    messages, images = _two_image_chat(), _images(2, seed=1)
    first = backend.complete(messages, images, max_new_tokens=16, cache_key="monitor")
    second = backend.complete(messages, images, max_new_tokens=16, cache_key="monitor")
    assert first.ok and second.ok
    assert first.usage.cached_tokens == 0
    assert second.usage.cached_tokens == second.usage.prompt_tokens - 1  # all but the token that yields logits
    assert second.text == first.text == ref.generate(messages, images, 16)[0]

    # Monitoring-style growth: same byte-stable head, one more keyframe appended at the end.
    grown_images = images + _images(1, seed=2)
    grown = [SYSTEM, ChatMessage("user", messages[1].content + " Newest <image> Status?")]
    third = backend.complete(grown, grown_images, max_new_tokens=16, cache_key="monitor")
    uncached = backend.complete(grown, grown_images, max_new_tokens=16, cache_key=None)
    ids_old, _ = ref.prompt_ids(messages, images)
    ids_new, _ = ref.prompt_ids(grown, grown_images)
    common = int((ids_old[0, : ids_new.shape[1]] == ids_new[0, : ids_old.shape[1]]).int().cumprod(0).sum())
    assert third.ok and uncached.ok
    assert third.usage.cached_tokens == common > 0
    assert uncached.usage.cached_tokens == 0
    assert third.text == uncached.text == ref.generate(grown, grown_images, 16)[0]


def test_a_changed_image_ends_the_reused_prefix_at_that_image(tiny):
    _, _, backend, ref = tiny
    messages, images = _two_image_chat(), _images(2, seed=3)
    backend.complete(messages, images, max_new_tokens=4, cache_key="changed")
    ids, _ = ref.prompt_ids(messages, images)
    image_token = ref.model.config.image_token_id
    second_image_start = int(np.flatnonzero(np.diff((ids[0] == image_token).int().numpy()) == 1)[1]) + 1

    repainted = VlmImage(images[1].rgb.copy(), images[1].frame_id)  # same id, other pixels
    repainted.rgb[0, 0] ^= 255
    same_pixels_new_id = VlmImage(images[1].rgb, "another-frame-id")
    for replacement in (repainted, same_pixels_new_id):
        response = backend.complete(messages, [images[0], replacement], max_new_tokens=8, cache_key="changed")
        assert response.usage.cached_tokens == second_image_start
        assert response.text == ref.generate(messages, [images[0], replacement], 8)[0]


def test_streams_keep_their_own_prefix(tiny):
    _, _, backend, _ = tiny
    a, b = _two_image_chat(), [ChatMessage("user", "Decide: <image> where is the gate?")]
    images_a, images_b = _images(2, seed=4), _images(1, seed=5)
    backend.complete(a, images_a, max_new_tokens=4, cache_key="monitor-s")
    backend.complete(b, images_b, max_new_tokens=4, cache_key="decision-s")
    again = backend.complete(a, images_a, max_new_tokens=4, cache_key="monitor-s")
    assert again.usage.cached_tokens == again.usage.prompt_tokens - 1


def test_deadline_stops_a_long_generation_in_real_time(tiny):
    family, _, backend, _ = tiny
    if family != "qwen3_vl":
        messages, images = _two_image_chat(), _images(2)
    else:  # pick a prompt this seeded model does not end early (it emits <|im_end|> on the other)
        messages, images = [ChatMessage("user", "<image>")], _images(1, seed=0)
    response = backend.complete(messages, images, deadline_s=0.3, max_new_tokens=100_000, cache_key="long")
    assert response.status is CallStatus.TIMEOUT, response
    assert response.text == ""
    assert "deadline" in response.error
    assert response.latency_s < 0.3 + 1.0
    assert response.usage.completion_tokens > 0
    # The stream stays consistent after the interruption: the next call is exact.
    after = backend.complete(messages, images, max_new_tokens=8, cache_key="long")
    assert after.ok and after.usage.cached_tokens > 0
    assert after.text == backend.complete(messages, images, max_new_tokens=8).text


def test_deadline_checked_after_every_token_on_a_driven_clock(tiny):
    _, path, _, _ = tiny
    now = [100.0]

    def clock() -> float:  # every reading advances time by 10 ms
        now[0] += 0.01
        return now[0]

    backend = TransformersBackend(TransformersBackendConfig(str(path)), clock=clock)
    messages, images = _two_image_chat(), _images(2)
    response = backend.complete(messages, images, deadline_s=0.055, max_new_tokens=1000)
    # readings: t0 = 100.01 (deadline 100.065), before the prefill 100.02, then one after each
    # token: the 5th token's reading (100.07) is the first past the deadline.
    assert response.status is CallStatus.TIMEOUT
    assert response.usage.completion_tokens == 5
    assert "after 5 tokens" in response.error
    tight = backend.complete(messages, images, deadline_s=0.005, max_new_tokens=1000)
    assert tight.status is CallStatus.TIMEOUT and "before the prefill" in tight.error


def test_deadline_criteria_is_a_stopping_criteria():
    ids = torch.zeros((2, 3), dtype=torch.long)
    assert DeadlineCriteria(None)(ids, None).tolist() == [False, False]
    assert DeadlineCriteria(5.0, clock=lambda: 5.0)(ids, None).tolist() == [True, True]
    assert DeadlineCriteria(5.0, clock=lambda: 4.9)(ids, None).tolist() == [False, False]


def test_random_weight_garbage_is_a_clean_parse_failure(tiny):
    _, _, backend, _ = tiny
    images = _images(2)
    response = backend.complete(_two_image_chat(), images, max_new_tokens=32)
    assert response.ok and response.text
    point = parse_point(response.text, images[0].size)
    status = parse_status(response.text)
    assert not point.ok and point.uv is None and point.raw == response.text
    assert not status.ok and status.status is None and status.raw == response.text


def _reference_tokens(ref, image):
    """The merged patch embeddings the standard processor + vision tower give for ``image``,
    as a (hm, wm, C) token grid (what the language model reads for the image)."""
    vision = ref.processor(images=[Image.fromarray(image.rgb)], return_tensors="pt")
    with torch.inference_mode():
        pooled = ref.model.model.get_image_features(vision["pixel_values"], vision["image_grid_thw"]).pooler_output[0]
    _, gh, gw = vision["image_grid_thw"][0].tolist()
    merge = ref.model.config.vision_config.spatial_merge_size
    return pooled.numpy().reshape(gh // merge, gw // merge, -1)


def test_features_grid_covers_the_image_and_resamples_the_prompt_tokens(tiny):
    family, _, backend, ref = tiny
    merge_px = 28 if family == "qwen2_5_vl" else 32
    for h, w in ((120, 160), (480, 640), (2 * merge_px, 3 * merge_px)):
        image = _images(1, seed=6, shape=(h, w, 3))[0]
        feats = backend.features(image)
        hp, wp, c = feats.grid.shape
        assert feats.grid.dtype == np.float32 and np.isfinite(feats.grid).all()
        assert c == 64 and feats.image_size == (w, h)
        assert feats.source == f"{family}.visual"
        # the grid covers the image, with less than one patch of padding
        assert wp * feats.patch_px >= w - 1e-6 and (wp - 1) * feats.patch_px < w
        assert hp * feats.patch_px >= h - 1e-6 and (hp - 1) * feats.patch_px < h
        tokens = _reference_tokens(ref, image)
        hm, wm = tokens.shape[:2]
        if (h, w) == (2 * merge_px, 3 * merge_px):  # no resize: one patch per token, exactly
            assert feats.patch_px == merge_px and (hp, wp) == (hm, wm)
        # every patch is exactly the token under its centre (nearest resampling, no blending)
        for i, j in ((0, 0), (hp - 1, wp - 1), (hp // 2, wp // 3)):
            cu, cv = (j + 0.5) * feats.patch_px, (i + 0.5) * feats.patch_px
            ti, tj = min(int(cv / (h / hm)), hm - 1), min(int(cu / (w / wm)), wm - 1)
            np.testing.assert_allclose(feats.grid[i, j], tokens[ti, tj], rtol=1e-5, atol=1e-6)


def test_features_match_the_vision_tower_run_directly(tiny):
    family, _, backend, ref = tiny
    merge_px = 28 if family == "qwen2_5_vl" else 32
    image = _images(1, seed=7, shape=(2 * merge_px, 3 * merge_px, 3))[0]  # no resizing needed
    vision = ref.processor(images=[Image.fromarray(image.rgb)], do_resize=False, return_tensors="pt")
    with torch.inference_mode():
        pooled = ref.model.model.get_image_features(vision["pixel_values"], vision["image_grid_thw"]).pooler_output[0]
    np.testing.assert_allclose(backend.features(image).grid.reshape(-1, 64), pooled.numpy(), rtol=1e-5, atol=1e-6)


def test_one_vision_encoder_run_per_frame_for_both_agents_and_the_verifier(tiny):
    """The decision prompt (latest frame), the monitoring prompt (first frame + latest frame)
    and the verifier's features all read one vision pass per frame. Counted with a forward hook
    on the model's own vision tower, independently of the backend's bookkeeping."""
    _, _, backend, _ = tiny
    backend.reset_cache()
    runs: list[int] = []
    handle = backend._model.model.visual.register_forward_hook(lambda *a: runs.append(1))
    try:
        first, latest = _images(2, seed=11)
        decision = [SYSTEM, ChatMessage("user", "Where next? <image>")]
        monitor = [SYSTEM, ChatMessage("user", "First view <image> latest view <image> Subtask: stop at the red van.")]
        assert backend.complete(decision, [first], max_new_tokens=2).ok
        assert backend.complete(monitor, [first, latest], max_new_tokens=2, cache_key="monitor").ok
        assert backend.complete(decision, [latest], max_new_tokens=2, cache_key="decision").ok
        f = backend.features(latest)
        assert backend.features(first).grid.shape == f.grid.shape
        assert len(runs) == 2  # two frames, two encoder runs, five readers
        counts = backend.vision_encoder_runs
        assert counts[first.frame_id] == 1 and counts[latest.frame_id] == 1
        # A new frame costs exactly one more run, whoever reads it first.
        nxt = _images(1, seed=12)[0]
        backend.features(nxt)
        backend.complete(decision, [nxt], max_new_tokens=1)
        assert len(runs) == 3 and backend.vision_encoder_runs[nxt.frame_id] == 1
    finally:
        handle.remove()


def test_concurrent_calls_are_serialized_and_exact(tiny):
    _, _, backend, _ = tiny
    messages, images = _two_image_chat(), _images(2, seed=8)
    expected = backend.complete(messages, images, max_new_tokens=8).text
    results: list = [None] * 4

    def worker(k: int) -> None:
        results[k] = backend.complete(messages, images, max_new_tokens=8, cache_key=f"thread-{k % 2}")

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert all(r is not None and r.ok and r.text == expected for r in results)


def test_caller_mistakes_raise_and_closed_backend_returns_error(tiny):
    _, path, _, _ = tiny
    backend = TransformersBackend(TransformersBackendConfig(str(path)))
    with pytest.raises(ValueError, match="placeholders"):
        backend.complete([ChatMessage("user", "<image> and <image>")], _images(1))
    with pytest.raises(ValueError, match="max_new_tokens"):
        backend.complete([ChatMessage("user", "hi")], (), max_new_tokens=0)
    with backend:
        pass
    closed = backend.complete([ChatMessage("user", "hi")], ())
    assert closed.status is CallStatus.ERROR and "closed" in closed.error


def test_load_errors_are_named(tmp_path):
    with pytest.raises(TransformersBackendError, match="cannot load"):
        TransformersBackend(TransformersBackendConfig(str(tmp_path)))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"device": "gpu"}, "device"),
        ({"dtype": "int8"}, "dtype"),
        ({"max_streams": 0}, "max_streams"),
        ({"image_max_pixels": 0}, "image_max_pixels"),
        ({"image_min_pixels": 10, "image_max_pixels": 5}, "image_min_pixels"),
        ({"model_path": ""}, "model_path"),
    ],
)
def test_config_validation_names_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TransformersBackendConfig(**{"model_path": "x", **kwargs})
