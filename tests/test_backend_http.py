"""HTTP backend against a real server process on loopback (``python -m vlm.server``).

The server serves the tiny random-weight Qwen2.5-VL through the in-process transformers
backend, so a good call must answer exactly what the in-process backend answers. Faults are
selected per request with the ``X-OnFly-Fault`` header, which the server honours only because
the test starts it with ``--allow-faults``.
"""

from __future__ import annotations

import json
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from vlm.backend_http import (
    HttpBackend,
    HttpBackendConfig,
    VlmTimeoutError,
    encode_png_data_url,
    split_image_placeholders,
)
from vlm.backend_transformers import TransformersBackend, TransformersBackendConfig
from vlm.server import FAULT_HEADER
from vlm.tiny_models import build_tiny_vlm
from vlm.types import (
    CallStatus,
    ChatMessage,
    VlmBackend,
    VlmConnectionError,
    VlmHttpError,
    VlmImage,
    VlmResponseError,
)

REPO = Path(__file__).resolve().parents[1]
SCHEMA = {"type": "object", "properties": {"status": {"enum": ["CONTINUE", "STOP", "LOST"]}}, "required": ["status"]}


def _images(n: int, seed: int = 0) -> list[VlmImage]:
    rng = np.random.default_rng(seed)
    return [VlmImage(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), f"frame-{seed}-{i}") for i in range(n)]


def _chat() -> list[ChatMessage]:
    return [ChatMessage("system", "You are the monitoring agent. Answer CONTINUE, STOP or LOST."),
            ChatMessage("user", "Start <image> now <image> Status?")]


def _read_first_line(process: subprocess.Popen, timeout_s: float) -> str:
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: lines.put(process.stdout.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout_s)
    except queue.Empty:
        return ""


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    return build_tiny_vlm(tmp_path_factory.mktemp("http_tiny"), family="qwen2_5_vl", seed=0)


@pytest.fixture(scope="module")
def server_url(tiny_dir):
    """A real ``python -m vlm.server`` process on a free loopback port; always terminated."""
    process = subprocess.Popen(
        [sys.executable, "-m", "vlm.server", "--backend", f"transformers:{tiny_dir}", "--port", "0",
         "--model-name", "tiny-qwen", "--allow-faults", "--log-level", "WARNING"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )
    try:
        line = _read_first_line(process, timeout_s=60.0)
        assert line.startswith("listening on http://127.0.0.1:"), f"server did not start: {line!r}"
        yield line.split("listening on ", 1)[1].strip()
    finally:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=10)


def _backend(url: str, fault: str | None = None, **kwargs) -> HttpBackend:
    headers = ((FAULT_HEADER, fault),) if fault else ()
    return HttpBackend(HttpBackendConfig(base_url=url, model="tiny-qwen", extra_headers=headers, **kwargs))


def _closed_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_good_call_answers_like_the_in_process_backend(server_url, tiny_dir):
    messages, images = _chat(), _images(2)
    with _backend(server_url) as backend:
        assert isinstance(backend, VlmBackend)
        response = backend.complete(messages, images, max_new_tokens=12, deadline_s=30.0)
    with TransformersBackend(TransformersBackendConfig(str(tiny_dir))) as local:
        expected = local.complete(messages, images, max_new_tokens=12)
    assert response.status is CallStatus.OK, response.error
    assert response.text == expected.text
    assert response.usage.prompt_tokens == expected.usage.prompt_tokens
    assert response.usage.completion_tokens == expected.usage.completion_tokens
    assert response.latency_s > 0


def test_cached_tokens_reported_through_http(server_url):
    messages, images = _chat(), _images(2, seed=1)
    with _backend(server_url) as backend:
        first = backend.complete(messages, images, max_new_tokens=4, cache_key="monitor", deadline_s=30.0)
        second = backend.complete(messages, images, max_new_tokens=4, cache_key="monitor", deadline_s=30.0)
    assert first.ok and second.ok
    assert first.usage.cached_tokens == 0
    assert second.usage.cached_tokens == second.usage.prompt_tokens - 1
    assert second.text == first.text


def test_json_schema_is_sent_and_accepted(server_url):
    with _backend(server_url, structured_output="json_schema") as backend:
        response = backend.complete(_chat(), _images(2), json_schema=SCHEMA, max_new_tokens=4, deadline_s=30.0)
    assert response.ok, response.error


def test_timeout_when_the_server_is_slower_than_the_deadline(server_url):
    with _backend(server_url, fault="delay=3") as backend:
        t0 = time.monotonic()
        response = backend.complete(_chat(), _images(2), deadline_s=0.5)
        elapsed = time.monotonic() - t0
        with pytest.raises(VlmTimeoutError, match="deadline"):
            backend.complete_or_raise(_chat(), _images(2), deadline_s=0.3)
    assert response.status is CallStatus.TIMEOUT
    assert response.text == "" and "within the deadline" in response.error
    assert 0.5 <= elapsed < 1.5


def test_server_side_deadline_stops_generation_and_is_a_timeout(server_url):
    # The tiny model never ends this answer by itself; the deadline header makes the server stop.
    with _backend(server_url) as backend:
        t0 = time.monotonic()
        response = backend.complete(_chat(), _images(2), deadline_s=1.0, max_new_tokens=100_000)
        assert response.status is CallStatus.TIMEOUT
        assert time.monotonic() - t0 < 2.0
        # The server stopped generating too: the next call is not stuck behind 100k tokens.
        after = backend.complete(_chat(), _images(2), deadline_s=10.0, max_new_tokens=4)
    assert after.ok, after.error


def test_refused_connection_is_a_clear_error():
    url = f"http://127.0.0.1:{_closed_port()}"
    with _backend(url) as backend:
        response = backend.complete(_chat(), _images(2), deadline_s=2.0)
        with pytest.raises(VlmConnectionError, match="connection refused"):
            backend.complete_or_raise(_chat(), _images(2), deadline_s=2.0)
    assert response.status is CallStatus.ERROR
    assert "connection refused" in response.error and url.split("//")[1] in response.error


def test_http_500_is_an_error_with_status_and_body(server_url):
    with _backend(server_url, fault="status=500") as backend:
        response = backend.complete(_chat(), _images(2), deadline_s=5.0)
        with pytest.raises(VlmHttpError, match="HTTP 500") as info:
            backend.complete_or_raise(_chat(), _images(2), deadline_s=5.0)
    assert response.status is CallStatus.ERROR
    assert "HTTP 500" in response.error and "injected fault" in response.error
    assert info.value.status == 500 and "injected fault" in info.value.body


@pytest.mark.parametrize(("fault", "detail"), [("malformed=text", "not JSON"), ("malformed=nochoices", "no choices")])
def test_malformed_body_is_an_error(server_url, fault, detail):
    with _backend(server_url, fault=fault) as backend:
        response = backend.complete(_chat(), _images(2), deadline_s=5.0)
        with pytest.raises(VlmResponseError, match="malformed"):
            backend.complete_or_raise(_chat(), _images(2), deadline_s=5.0)
    assert response.status is CallStatus.ERROR
    assert "malformed response body" in response.error and detail in response.error


def test_auto_structured_output_falls_back_once_on_a_server_without_it(server_url):
    with _backend(server_url, fault="reject-schema", structured_output="auto") as backend:
        assert backend.sends_json_schema
        first = backend.complete(_chat(), _images(2), json_schema=SCHEMA, max_new_tokens=4, deadline_s=30.0)
        assert first.ok, first.error
        assert not backend.sends_json_schema
        second = backend.complete(_chat(), _images(2), json_schema=SCHEMA, max_new_tokens=4, deadline_s=30.0)
        assert second.ok and second.text == first.text
    with _backend(server_url, fault="reject-schema", structured_output="json_schema") as strict:
        refused = strict.complete(_chat(), _images(2), json_schema=SCHEMA, deadline_s=30.0)
    assert refused.status is CallStatus.ERROR and "HTTP 400" in refused.error and "response_format" in refused.error


def test_list_models(server_url):
    with _backend(server_url) as backend:
        assert backend.list_models() == ["tiny-qwen"]


def test_caller_mistakes_raise_value_error(server_url):
    with _backend(server_url) as backend:
        with pytest.raises(ValueError, match="placeholders"):
            backend.complete([ChatMessage("user", "only one <image>")], _images(2))
        with pytest.raises(ValueError, match="deadline_s"):
            backend.complete(_chat(), _images(2), deadline_s=0.0)
        with pytest.raises(ValueError, match="max_new_tokens"):
            backend.complete(_chat(), _images(2), max_new_tokens=0)


def test_request_body_places_images_where_the_placeholders_stand(monkeypatch):
    backend = _backend("http://127.0.0.1:9")
    captured = {}

    def fake_request(method, path, body, deadline_mono, headers):
        captured.update(method=method, path=path, body=body, headers=headers)
        return {"choices": [{"message": {"role": "assistant", "content": "ok"}}],
                "usage": {"prompt_tokens": 10, "completion_tokens": 1, "prompt_tokens_details": {"cached_tokens": 7}}}

    monkeypatch.setattr(backend, "_request", fake_request)
    images = _images(2)
    response = backend.complete(_chat(), images, json_schema=SCHEMA, max_new_tokens=5, cache_key="decision")
    body = captured["body"]
    assert captured["path"] == "/v1/chat/completions" and captured["headers"] == {"X-OnFly-Cache-Key": "decision"}
    assert body["messages"][0] == {"role": "system", "content": _chat()[0].content}
    assert body["messages"][1]["content"] == [
        {"type": "text", "text": "Start "},
        {"type": "image_url", "image_url": {"url": encode_png_data_url(images[0].rgb)}},
        {"type": "text", "text": " now "},
        {"type": "image_url", "image_url": {"url": encode_png_data_url(images[1].rgb)}},
        {"type": "text", "text": " Status?"},
    ]
    assert body["response_format"]["type"] == "json_schema"
    assert body["response_format"]["json_schema"]["schema"] == SCHEMA
    assert body["max_tokens"] == 5 and body["temperature"] == 0.0
    assert response.usage.cached_tokens == 7 and response.text == "ok"


def test_llama_cpp_cache_count_is_read(monkeypatch):
    backend = _backend("http://127.0.0.1:9")
    monkeypatch.setattr(backend, "_request", lambda *a: {
        "choices": [{"message": {"content": "STOP"}}],
        "usage": {"prompt_tokens": 50, "completion_tokens": 2}, "timings": {"cache_n": 42}})
    assert backend.complete([ChatMessage("user", "hi")]).usage.cached_tokens == 42


def test_png_data_url_is_lossless():
    from vlm.server import _decode_image

    rgb = _images(1, seed=4)[0].rgb
    assert np.array_equal(_decode_image(encode_png_data_url(rgb), "x").rgb, rgb)


def test_split_image_placeholders():
    parts = split_image_placeholders([ChatMessage("system", "s"), ChatMessage("user", "<image>a<image><image>b")], 3)
    assert parts == [("system", ["s"]), ("user", [0, "a", 1, 2, "b"])]
    with pytest.raises(ValueError, match="2 <image> placeholders but 1 images"):
        split_image_placeholders([ChatMessage("user", "<image><image>")], 1)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"base_url": "ftp://x"}, "base_url"),
        ({"base_url": "http://h:99999"}, "port"),
        ({"model": ""}, "model"),
        ({"timeout_s": 0.0}, "timeout_s"),
        ({"structured_output": "grammar"}, "structured_output"),
        ({"temperature": -1.0}, "temperature"),
        ({"extra_headers": (("X-A",),)}, "extra_headers"),
    ],
)
def test_config_validation_names_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HttpBackendConfig(**{"base_url": "http://127.0.0.1:8000", "model": "m", **kwargs})


def test_base_url_with_or_without_v1():
    for base in ("http://127.0.0.1:8000", "http://127.0.0.1:8000/", "http://127.0.0.1:8000/v1", "http://127.0.0.1:8000/v1/"):
        assert HttpBackend(HttpBackendConfig(base, "m")).url == "http://127.0.0.1:8000/v1/chat/completions"
    assert HttpBackend(HttpBackendConfig("https://api.example.org/openai", "m")).url == \
        "https://api.example.org:443/openai/v1/chat/completions"
    assert json.dumps(HttpBackendConfig("http://h:1", "m").endpoint_prefix) == '"/v1"'


def test_local_feature_source_gives_features_where_the_server_gives_none():
    from vlm.factory import make_backend
    from vlm.types import VisionFeatures

    image = _images(1, seed=3)[0]
    plain = HttpBackend(HttpBackendConfig(base_url="http://127.0.0.1:9", model="m"))
    assert plain.features(image) is None
    calls: list[str] = []

    def encoder(im: VlmImage) -> VisionFeatures:
        calls.append(im.frame_id)
        return VisionFeatures(np.ones((8, 10, 4), np.float32), 16.0, im.size, "test-encoder")

    with_source = HttpBackend(HttpBackendConfig(base_url="http://127.0.0.1:9", model="m"), feature_source=encoder)
    f = with_source.features(image)
    assert f.source == "test-encoder" and calls == [image.frame_id]

    class Tower:  # anything with features(), e.g. an in-process TransformersBackend
        def features(self, im):
            return encoder(im)

    via_factory = make_backend("http://127.0.0.1:9#m", feature_source=Tower())
    assert via_factory.features(image).source == "test-encoder" and len(calls) == 2
    with pytest.raises(TypeError, match="feature_source"):
        HttpBackend(HttpBackendConfig(base_url="http://127.0.0.1:9", model="m"), feature_source=3)
    bad = HttpBackend(HttpBackendConfig(base_url="http://127.0.0.1:9", model="m"), feature_source=lambda im: "grid")
    with pytest.raises(TypeError, match="expected VisionFeatures"):
        bad.features(image)
