"""A small OpenAI-compatible server around any in-process backend.

Serves ``POST /v1/chat/completions``, ``GET /v1/models`` and ``GET /health`` on a
``ThreadingHTTPServer`` (standard library). Use it to share one loaded model between several
processes on a machine (the agents of several benchmark workers), or as the real server the
HTTP-backend tests talk to::

    python -m vlm.server --backend transformers:/path/to/Qwen2.5-VL-3B-Instruct --port 8000
    python -m vlm.server --backend sim:nominal --port 0      # prints the port it bound

(The simulated VLM grounds on the frame annotations of the embedded world, which do not travel
over HTTP: served, it sees plain pixels only, so it is useful for text prompts such as the
task decomposition, not for pointing.)

Requests follow the OpenAI chat format: content is a string or a list of ``text`` and
``image_url`` parts (``data:`` URLs with base64 PNG/JPEG; remote URLs are refused). Each image
becomes a :class:`VlmImage` whose ``frame_id`` is a digest of its decoded pixels, so a repeated
keyframe is recognized and the transformers backend reuses its KV-cache.
``response_format`` ``json_schema`` / ``json_object`` / ``text`` is accepted (the schema is
passed to the backend). Decoding is whatever the backend does (greedy for ours);
``temperature`` is accepted and not used. The answer's ``usage`` carries
``prompt_tokens_details.cached_tokens``.

Two request headers are honoured: ``X-OnFly-Cache-Key`` names the backend's KV stream
(default: the ``user`` field, else ``"default"``), ``X-OnFly-Deadline-S`` bounds the backend
call (a backend TIMEOUT becomes HTTP 504).

Fault injection for tests exists only when the server is started with ``allow_faults=True``
(``--allow-faults``): a request header ``X-OnFly-Fault`` then selects ``delay=<seconds>``,
``status=<code>``, ``malformed=text``, ``malformed=nochoices`` or ``reject-schema``
(a 400 naming ``response_format`` as unsupported whenever one is sent).
"""

from __future__ import annotations

import argparse
import base64
import binascii
import hashlib
import io
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from vlm.backend_http import CACHE_KEY_HEADER, DEADLINE_HEADER, IMAGE_PLACEHOLDER
from vlm.types import CallStatus, ChatMessage, VlmBackend, VlmError, VlmImage

__all__ = ["FAULT_HEADER", "ServerConfig", "VlmServer", "RequestError", "main"]

log = logging.getLogger(__name__)

FAULT_HEADER = "X-OnFly-Fault"
_ROLES = ("system", "user", "assistant")


class RequestError(ValueError):
    """A request the server refuses with HTTP 400; ``param`` names the field at fault."""

    def __init__(self, message: str, param: str | None = None) -> None:
        super().__init__(message)
        self.param = param


@dataclass(frozen=True)
class ServerConfig:
    """Where and how to serve.

    Attributes
    ----------
    host : bind address (default loopback; anything else exposes the model to the network)
    port : TCP port; 0 lets the OS choose (read :attr:`VlmServer.port`)
    model_name : id reported by ``/v1/models`` and in answers
    default_max_tokens : ``max_tokens`` when a request gives none
    max_body_bytes : larger request bodies are refused with 413
    allow_faults : honour the ``X-OnFly-Fault`` test header
    """

    host: str = "127.0.0.1"
    port: int = 0
    model_name: str = "onfly"
    default_max_tokens: int = 256
    max_body_bytes: int = 64 * 1024 * 1024
    allow_faults: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ValueError(f"port must be in [0, 65535], got {self.port}")
        if not self.model_name:
            raise ValueError("model_name must be non-empty")
        if self.default_max_tokens < 1:
            raise ValueError(f"default_max_tokens must be >= 1, got {self.default_max_tokens}")
        if self.max_body_bytes < 1024:
            raise ValueError(f"max_body_bytes must be >= 1024, got {self.max_body_bytes}")


def _decode_image(url: str, where: str) -> VlmImage:
    """A ``data:image/...;base64,`` URL -> VlmImage with a pixel-digest frame id."""
    from PIL import Image, UnidentifiedImageError

    if not url.startswith("data:image/") or ";base64," not in url:
        raise RequestError("only data:image/...;base64, URLs are accepted (no remote fetching)", where)
    try:
        raw = base64.b64decode(url.split(";base64,", 1)[1], validate=True)
        with Image.open(io.BytesIO(raw)) as image:
            rgb = np.asarray(image.convert("RGB"), dtype=np.uint8)
    except (binascii.Error, ValueError, UnidentifiedImageError, OSError) as exc:
        raise RequestError(f"undecodable image: {exc}", where) from exc
    digest = hashlib.blake2b(rgb.tobytes(), digest_size=12)
    digest.update(str(rgb.shape).encode())
    return VlmImage(rgb=rgb, frame_id=f"px:{digest.hexdigest()}")


def parse_chat_request(body: Any, default_max_tokens: int) -> tuple[list[ChatMessage], list[VlmImage], dict]:
    """Messages, images and call options of a chat-completions request; RequestError if bad."""
    if not isinstance(body, dict):
        raise RequestError("the body must be a JSON object")
    raw_messages = body.get("messages")
    if not isinstance(raw_messages, list) or not raw_messages:
        raise RequestError("messages must be a non-empty list", "messages")
    messages: list[ChatMessage] = []
    images: list[VlmImage] = []
    for i, message in enumerate(raw_messages):
        where = f"messages[{i}]"
        if not isinstance(message, dict) or message.get("role") not in _ROLES:
            raise RequestError(f"each message needs a role in {_ROLES}", where)
        content = message.get("content")
        if isinstance(content, str):
            text = content
        elif isinstance(content, list):
            pieces = []
            for j, part in enumerate(content):
                part_where = f"{where}.content[{j}]"
                kind = part.get("type") if isinstance(part, dict) else None
                if kind == "text" and isinstance(part.get("text"), str):
                    pieces.append(part["text"])
                elif kind == "image_url":
                    image_url = part.get("image_url")
                    url = image_url.get("url") if isinstance(image_url, dict) else image_url
                    if not isinstance(url, str):
                        raise RequestError("image_url needs a url", part_where)
                    images.append(_decode_image(url, part_where))
                    pieces.append(IMAGE_PLACEHOLDER)
                else:
                    raise RequestError("content parts must be text or image_url", part_where)
            text = "".join(pieces)
        else:
            raise RequestError("content must be a string or a list of parts", where)
        if IMAGE_PLACEHOLDER in text and not isinstance(content, list):
            raise RequestError(f"literal {IMAGE_PLACEHOLDER} in text content is reserved", where)
        messages.append(ChatMessage(role=message["role"], content=text))

    max_tokens = body.get("max_completion_tokens", body.get("max_tokens", default_max_tokens))
    if max_tokens is None:
        max_tokens = default_max_tokens
    if not isinstance(max_tokens, int) or isinstance(max_tokens, bool) or max_tokens < 1:
        raise RequestError("max_tokens must be a positive integer", "max_tokens")
    json_schema = None
    response_format = body.get("response_format")
    if response_format is not None:
        kind = response_format.get("type") if isinstance(response_format, dict) else None
        if kind == "json_schema":
            spec = response_format.get("json_schema")
            schema = spec.get("schema") if isinstance(spec, dict) else None
            if not isinstance(schema, dict):
                raise RequestError("response_format.json_schema.schema must be an object", "response_format")
            json_schema = schema
        elif kind == "json_object":
            json_schema = {"type": "object"}
        elif kind != "text":
            raise RequestError("response_format.type must be text, json_object or json_schema", "response_format")
    if body.get("stream"):
        raise RequestError("streaming is not supported by this server", "stream")
    options = {"max_new_tokens": max_tokens, "json_schema": json_schema, "user": body.get("user")}
    return messages, images, options


class VlmServer:
    """An OpenAI-compatible HTTP front of one backend. Context manager; ``close`` stops it.

    The backend is called from one request at a time (in-process models gain nothing from
    concurrent calls on one device); requests wait for their turn within their deadline.
    """

    def __init__(self, backend: VlmBackend, config: ServerConfig | None = None) -> None:
        self.backend = backend
        self.config = config or ServerConfig()
        self._call_lock = threading.Lock()
        self._counter = 0
        self._httpd = ThreadingHTTPServer((self.config.host, self.config.port), _make_handler(self))
        self._httpd.daemon_threads = True
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self._httpd.server_address[1])

    @property
    def url(self) -> str:
        """Base URL clients use (``http://host:port``)."""
        return f"http://{self.config.host}:{self.port}"

    def serve_forever(self) -> None:
        """Serve in this thread until :meth:`close` is called from another one."""
        self._httpd.serve_forever(poll_interval=0.05)

    def start(self) -> "VlmServer":
        """Serve in a background daemon thread; returns self."""
        self._thread = threading.Thread(target=self.serve_forever, name="vlm-server", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread is not None:
            self._httpd.shutdown()
            self._thread.join()
            self._thread = None
        self._httpd.server_close()

    def __enter__(self) -> "VlmServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------- request logic

    def handle_chat(self, body: Any, headers) -> tuple[int, dict]:
        """HTTP status and JSON answer for one chat-completions request."""
        try:
            messages, images, options = parse_chat_request(body, self.config.default_max_tokens)
        except RequestError as exc:
            return 400, _error_json(str(exc), "invalid_request_error", exc.param)
        deadline_s = None
        if headers.get(DEADLINE_HEADER):
            try:
                deadline_s = float(headers[DEADLINE_HEADER])
            except ValueError:
                return 400, _error_json(f"{DEADLINE_HEADER} must be a number of seconds", "invalid_request_error")
            if not deadline_s > 0:
                return 504, _error_json("the client's deadline had already passed", "timeout")
        cache_key = headers.get(CACHE_KEY_HEADER) or options["user"] or "default"
        t0 = time.monotonic()
        if not self._call_lock.acquire(timeout=-1 if deadline_s is None else deadline_s):
            return 504, _error_json("server busy past the client's deadline", "timeout")
        try:
            remaining = None if deadline_s is None else max(1e-3, deadline_s - (time.monotonic() - t0))
            response = self.backend.complete(
                messages, images, deadline_s=remaining, json_schema=options["json_schema"],
                max_new_tokens=options["max_new_tokens"], cache_key=str(cache_key),
            )
        except ValueError as exc:  # the backend refused the request shape
            return 400, _error_json(str(exc), "invalid_request_error")
        finally:
            self._call_lock.release()
        if response.status is CallStatus.TIMEOUT:
            return 504, _error_json(response.error or "backend timeout", "timeout")
        if response.status is CallStatus.ERROR:
            return 500, _error_json(response.error or "backend error", "server_error")
        with self._call_lock:
            self._counter += 1
            number = self._counter
        usage = response.usage
        finish = "length" if usage.completion_tokens >= options["max_new_tokens"] else "stop"
        return 200, {
            "id": f"chatcmpl-{number}",
            "object": "chat.completion",
            "created": int(time.time()),
            "model": self.config.model_name,
            "choices": [{"index": 0, "message": {"role": "assistant", "content": response.text},
                         "finish_reason": finish}],
            "usage": {
                "prompt_tokens": usage.prompt_tokens,
                "completion_tokens": usage.completion_tokens,
                "total_tokens": usage.prompt_tokens + usage.completion_tokens,
                "prompt_tokens_details": {"cached_tokens": usage.cached_tokens},
            },
        }

    def models_json(self) -> dict:
        return {"object": "list",
                "data": [{"id": self.config.model_name, "object": "model", "created": 0, "owned_by": "onfly"}]}


def _error_json(message: str, kind: str, param: str | None = None) -> dict:
    return {"error": {"message": message, "type": kind, "param": param, "code": None}}


def _parse_fault(value: str) -> tuple[str, str]:
    name, _, arg = value.strip().partition("=")
    return name.strip().lower(), arg.strip()


def _fault_number(arg: str) -> float | None:
    try:
        return float(arg)
    except ValueError:
        return None


def _make_handler(server: VlmServer):
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"
        server_version = "onfly-vlm"

        def log_message(self, fmt: str, *args) -> None:  # route access logs to logging
            log.debug("%s " + fmt, self.address_string(), *args)

        def _send(self, status: int, payload: dict | bytes, content_type: str = "application/json") -> None:
            data = payload if isinstance(payload, bytes) else json.dumps(payload).encode("utf-8")
            try:
                self.send_response(status)
                self.send_header("Content-Type", content_type)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)
            except (BrokenPipeError, ConnectionResetError):
                log.info("client %s left before the answer", self.address_string())

        def do_GET(self) -> None:
            path = self.path.split("?", 1)[0].rstrip("/")
            if path in ("/v1/models", "/models"):
                self._send(200, server.models_json())
            elif path == "/health":
                self._send(200, {"status": "ok"})
            else:
                self._send(404, _error_json(f"no route {self.path}", "not_found"))

        def do_POST(self) -> None:
            path = self.path.split("?", 1)[0].rstrip("/")
            length = self.headers.get("Content-Length")
            try:
                n = int(length)
            except (TypeError, ValueError):
                self._send(411, _error_json("Content-Length required", "invalid_request_error"))
                return
            if n > server.config.max_body_bytes:
                self.close_connection = True
                self._send(413, _error_json(f"body exceeds {server.config.max_body_bytes} bytes",
                                            "invalid_request_error"))
                return
            raw = self.rfile.read(n)
            if path not in ("/v1/chat/completions", "/chat/completions"):
                self._send(404, _error_json(f"no route {self.path}", "not_found"))
                return
            fault = self.headers.get(FAULT_HEADER) if server.config.allow_faults else None
            try:
                body = json.loads(raw.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                self._send(400, _error_json(f"body is not JSON: {exc}", "invalid_request_error"))
                return
            if fault:
                name, arg = _parse_fault(fault)
                number = _fault_number(arg)
                if name == "delay" and number is not None:
                    threading.Event().wait(number)  # test fault: a server that is slow to answer
                elif name == "status" and number is not None and 400 <= number < 600:
                    self._send(int(number), _error_json(f"injected fault: HTTP {int(number)}", "server_error"))
                    return
                elif name == "malformed" and arg == "text":
                    self._send(200, b"<html>this is not JSON {", "text/html")
                    return
                elif name == "malformed" and arg == "nochoices":
                    self._send(200, {"id": "chatcmpl-x", "object": "chat.completion", "choices": []})
                    return
                elif name == "reject-schema" and isinstance(body, dict) and "response_format" in body:
                    self._send(400, _error_json("response_format is not supported by this server",
                                                "invalid_request_error", "response_format"))
                    return
            status, answer = server.handle_chat(body, self.headers)
            self._send(status, answer)

    return Handler


def _default_model_name(spec: str) -> str:
    """``sim:nominal`` stays; ``transformers:/a/b/Qwen2.5-VL-3B`` becomes ``Qwen2.5-VL-3B``."""
    kind, _, rest = spec.partition(":")
    if kind == "transformers":
        return rest.rstrip("/").rsplit("/", 1)[-1] or spec
    return spec


def main(argv: list[str] | None = None, ready: Callable[[str], None] | None = None) -> int:
    """``python -m vlm.server``: serve a backend spec until interrupted. ``ready`` gets the
    server's URL once it is bound (the script entry writes it to stdout); a bad option, backend
    or port is logged as an error and returns 2."""
    from vlm.factory import VALID_SPECS, make_backend

    parser = argparse.ArgumentParser(prog="python -m vlm.server", description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", required=True, help=f"backend spec: {VALID_SPECS}")
    parser.add_argument("--host", default="127.0.0.1", help="bind address (default: loopback only)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port; 0 picks a free one")
    parser.add_argument("--model-name", default=None, help="id in /v1/models (default: from the spec)")
    parser.add_argument("--seed", type=int, default=0, help="seed of a simulated backend")
    parser.add_argument("--max-tokens", type=int, default=256, help="default max_tokens of a request")
    parser.add_argument("--allow-faults", action="store_true",
                        help=f"honour the {FAULT_HEADER} request header (tests only)")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        backend = make_backend(args.backend, seed=args.seed)
        config = ServerConfig(host=args.host, port=args.port,
                              model_name=args.model_name or _default_model_name(args.backend),
                              default_max_tokens=args.max_tokens, allow_faults=args.allow_faults)
        server = VlmServer(backend, config)
    except (ValueError, OSError, VlmError) as exc:
        log.error("%s", exc)
        return 2
    log.info("listening on %s", server.url)
    if ready is not None:
        ready(server.url)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
        backend.close()
    return 0


if __name__ == "__main__":
    # The first stdout line is the contract with scripts and tests that start the server.
    raise SystemExit(main(ready=lambda url: print(f"listening on {url}", flush=True)))
