"""The OpenAI-compatible server: request parsing, status codes, headers, fault switch.

Runs the server in a thread around a recording fake backend and talks raw HTTP to it; the
end-to-end path with a real model in a separate process is in test_backend_http.py.
"""

from __future__ import annotations

import http.client
import json
import logging

import numpy as np
import pytest

from vlm.backend_http import encode_png_data_url
from vlm.server import FAULT_HEADER, RequestError, ServerConfig, VlmServer, _default_model_name, parse_chat_request
from vlm.types import CallStatus, Usage, VlmResponse


class RecordingBackend:
    """Answers from a script and records every call."""

    name = "recording"

    def __init__(self) -> None:
        self.calls: list[dict] = []
        self.next = VlmResponse(CallStatus.OK, text="CONTINUE", usage=Usage(20, 3, 12))

    def complete(self, messages, images=(), *, deadline_s=None, json_schema=None, max_new_tokens=64, cache_key=None):
        self.calls.append(dict(messages=list(messages), images=list(images), deadline_s=deadline_s,
                               json_schema=json_schema, max_new_tokens=max_new_tokens, cache_key=cache_key))
        return self.next

    def features(self, image):
        return None

    def close(self) -> None:
        pass


@pytest.fixture()
def served():
    backend = RecordingBackend()
    with VlmServer(backend, ServerConfig(model_name="fake", max_body_bytes=200_000)).start() as server:
        yield server, backend


def _post(server, body, headers=None, path="/v1/chat/completions"):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    conn.request("POST", path, body=raw, headers={"Content-Type": "application/json", **(headers or {})})
    response = conn.getresponse()
    data = response.read()
    conn.close()
    return response.status, json.loads(data) if data.startswith(b"{") else data


def _image_url(seed=0, shape=(8, 12, 3)):
    rgb = np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)
    return rgb, encode_png_data_url(rgb)


def test_chat_request_becomes_messages_images_and_options(served):
    server, backend = served
    rgb, url = _image_url()
    body = {
        "model": "fake",
        "messages": [
            {"role": "system", "content": "Monitor."},
            {"role": "user", "content": [{"type": "text", "text": "Now "}, {"type": "image_url", "image_url": {"url": url}},
                                         {"type": "text", "text": " status?"}]},
        ],
        "max_tokens": 3,
        "response_format": {"type": "json_schema", "json_schema": {"name": "a", "schema": {"type": "object"}}},
    }
    status, answer = _post(server, body, {"X-OnFly-Cache-Key": "monitor", "X-OnFly-Deadline-S": "2.5"})
    assert status == 200
    call = backend.calls[-1]
    assert [(m.role, m.content) for m in call["messages"]] == [("system", "Monitor."), ("user", "Now <image> status?")]
    assert np.array_equal(call["images"][0].rgb, rgb) and call["images"][0].frame_id.startswith("px:")
    assert call["json_schema"] == {"type": "object"} and call["max_new_tokens"] == 3
    assert call["cache_key"] == "monitor" and 0 < call["deadline_s"] <= 2.5
    assert answer["model"] == "fake" and answer["object"] == "chat.completion"
    assert answer["choices"][0]["message"] == {"role": "assistant", "content": "CONTINUE"}
    assert answer["choices"][0]["finish_reason"] == "length"  # 3 completion tokens of max 3
    assert answer["usage"] == {"prompt_tokens": 20, "completion_tokens": 3, "total_tokens": 23,
                               "prompt_tokens_details": {"cached_tokens": 12}}


def test_identical_pixels_get_identical_frame_ids(served):
    server, backend = served
    _, url = _image_url(seed=1)
    _, other = _image_url(seed=2)
    for u in (url, url, other):
        _post(server, {"messages": [{"role": "user", "content": [{"type": "image_url", "image_url": {"url": u}}]}]})
    ids = [c["images"][0].frame_id for c in backend.calls]
    assert ids[0] == ids[1] != ids[2]


def test_cache_key_falls_back_to_user_then_default(served):
    server, backend = served
    _post(server, {"messages": [{"role": "user", "content": "hi"}], "user": "agent-7"})
    _post(server, {"messages": [{"role": "user", "content": "hi"}]})
    assert [c["cache_key"] for c in backend.calls] == ["agent-7", "default"]
    assert backend.calls[-1]["max_new_tokens"] == 256 and backend.calls[-1]["deadline_s"] is None


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ({"messages": []}, "messages"),
        ({"messages": [{"role": "robot", "content": "x"}]}, "role"),
        ({"messages": [{"role": "user", "content": [{"type": "image_url", "image_url": {"url": "http://x/y.png"}}]}]},
         "data:image"),
        ({"messages": [{"role": "user", "content": [{"type": "image_url", "image_url": {"url": "data:image/png;base64,AAAA"}}]}]},
         "undecodable"),
        ({"messages": [{"role": "user", "content": [{"type": "audio"}]}]}, "text or image_url"),
        ({"messages": [{"role": "user", "content": "x"}], "max_tokens": 0}, "max_tokens"),
        ({"messages": [{"role": "user", "content": "x"}], "response_format": {"type": "grammar"}}, "response_format"),
        ({"messages": [{"role": "user", "content": "x"}], "stream": True}, "stream"),
        ({"messages": [{"role": "user", "content": "a literal <image>"}]}, "reserved"),
    ],
)
def test_bad_requests_are_400_naming_the_problem(served, body, match):
    server, backend = served
    status, answer = _post(server, body)
    assert status == 400 and backend.calls == []
    assert answer["error"]["type"] == "invalid_request_error"
    assert match in answer["error"]["message"]
    with pytest.raises(RequestError, match=match):
        parse_chat_request(body, 16)


def test_backend_outcomes_map_to_http_status(served):
    server, backend = served
    body = {"messages": [{"role": "user", "content": "x"}]}
    backend.next = VlmResponse(CallStatus.ERROR, error="model exploded")
    status, answer = _post(server, body)
    assert status == 500 and answer["error"]["message"] == "model exploded"
    backend.next = VlmResponse(CallStatus.TIMEOUT, error="deadline passed")
    status, answer = _post(server, body)
    assert status == 504 and answer["error"]["type"] == "timeout"


def test_routes_sizes_and_non_json(served):
    server, _ = served
    assert _post(server, {"messages": []}, path="/v1/embeddings")[0] == 404
    assert _post(server, b"{not json")[0] == 400
    assert _post(server, b"{" + b" " * 300_000 + b"}")[0] == 413
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    conn.request("GET", "/v1/models")
    models = json.loads(conn.getresponse().read())
    conn.close()
    assert [m["id"] for m in models["data"]] == ["fake"]


def test_fault_header_is_ignored_unless_allowed(served):
    server, backend = served
    status, _ = _post(server, {"messages": [{"role": "user", "content": "x"}]}, {FAULT_HEADER: "status=500"})
    assert status == 200 and len(backend.calls) == 1
    with VlmServer(backend, ServerConfig(allow_faults=True)).start() as faulty:
        assert _post(faulty, {"messages": [{"role": "user", "content": "x"}]}, {FAULT_HEADER: "status=503"})[0] == 503


def test_default_model_name():
    assert _default_model_name("transformers:/models/Qwen2.5-VL-3B-Instruct/") == "Qwen2.5-VL-3B-Instruct"
    assert _default_model_name("sim:nominal") == "sim:nominal"


@pytest.mark.parametrize(("kwargs", "match"), [({"port": 70000}, "port"), ({"model_name": ""}, "model_name"),
                                              ({"default_max_tokens": 0}, "default_max_tokens")])
def test_server_config_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ServerConfig(**kwargs)


def test_main_logs_a_bad_backend_as_an_error_and_keeps_stdout_for_the_listening_line(capsys, caplog):
    from vlm.server import main

    heard = []
    assert main(["--backend", "bogus:x", "--port", "0"], ready=heard.append) == 2
    assert capsys.readouterr().out == ""  # the first stdout line is reserved for "listening on URL"
    assert heard == []  # never announced: nothing was bound
    errors = [r for r in caplog.records if r.name == "vlm.server" and r.levelno == logging.ERROR]
    assert len(errors) == 1 and errors[0].getMessage().startswith("bad VLM backend spec 'bogus:x'")
