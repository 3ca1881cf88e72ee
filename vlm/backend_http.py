"""OpenAI-compatible HTTP backend: vLLM, SGLang, llama.cpp server, Ollama (``/v1``), ours.

One call is one ``POST {base}/v1/chat/completions`` over the standard library's
``http.client`` (no third-party HTTP client). Images go inline as
``data:image/png;base64,...`` ``image_url`` parts, placed where the ``<image>`` placeholders
stand in :attr:`ChatMessage.content`, in order.

Behaviour a pilot can rely on:

- **One deadline per call** (``deadline_s``, else :attr:`HttpBackendConfig.timeout_s`) covers
  connect, send, waiting for the answer and reading it: the socket timeout is set to what is
  left before every blocking step, so a slow or stalled server yields ``CallStatus.TIMEOUT``
  at the deadline, never a hang. The remaining budget is also sent as the
  ``X-OnFly-Deadline-S`` header so our own server stops generating when the client gives up.
- **No blind retries.** A request is sent once. The one exception is the structured-output
  fallback below, which sends a *different* request.
- **Structured output.** With ``structured_output="json_schema"`` a ``json_schema`` argument
  becomes ``response_format={"type": "json_schema", ...}``; with ``"none"`` it is never sent
  (the prompt carries the format); with ``"auto"`` it is sent until a server answers 400/422
  naming ``response_format`` / ``json_schema`` as unsupported, after which the same call is
  sent once without it and later calls skip it.
- **Clear errors.** A refused connection, an HTTP error status (code and the start of the
  body) and a malformed body each give ``CallStatus.ERROR`` with ``error`` saying which;
  HTTP 504 (a server or gateway that gave up within the deadline) is a TIMEOUT.
  :meth:`HttpBackend.complete_or_raise` raises the matching named error instead.
- **Prefix caching.** ``usage.prompt_tokens_details.cached_tokens`` (vLLM, SGLang, ours) or
  llama.cpp's ``timings.cache_n`` become :attr:`Usage.cached_tokens`. ``cache_key`` is sent as
  the ``X-OnFly-Cache-Key`` header (our server keeps one KV stream per key; others ignore it).
  Encoded images are kept in a small LRU so repeated keyframes are byte-identical and cheap.
"""

from __future__ import annotations

import base64
import hashlib
import http.client
import io
import json
import logging
import socket
import threading
import time
import urllib.parse
from collections import OrderedDict
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vlm.types import (
    CallStatus,
    ChatMessage,
    Usage,
    VisionFeatures,
    VlmConnectionError,
    VlmError,
    VlmHttpError,
    VlmImage,
    VlmResponse,
    VlmResponseError,
)

__all__ = [
    "IMAGE_PLACEHOLDER",
    "CACHE_KEY_HEADER",
    "DEADLINE_HEADER",
    "STRUCTURED_OUTPUT_MODES",
    "HttpBackendConfig",
    "HttpBackend",
    "VlmTimeoutError",
    "split_image_placeholders",
    "encode_png_data_url",
]

log = logging.getLogger(__name__)

IMAGE_PLACEHOLDER = "<image>"
CACHE_KEY_HEADER = "X-OnFly-Cache-Key"
DEADLINE_HEADER = "X-OnFly-Deadline-S"
STRUCTURED_OUTPUT_MODES = ("json_schema", "none", "auto")
_BODY_SNIPPET = 300
_MAX_RESPONSE_BYTES = 16 * 1024 * 1024
_UNSUPPORTED_WORDS = ("unsupported", "not supported", "unknown", "unrecognized", "not allowed",
                      "extra", "invalid", "not implemented")


class VlmTimeoutError(VlmError, TimeoutError):
    """No complete answer arrived before the call's deadline."""


def split_image_placeholders(messages: Sequence[ChatMessage], n_images: int) -> list[tuple[str, list[str | int]]]:
    """Split each message at its ``<image>`` placeholders.

    Returns one ``(role, pieces)`` per message, where a piece is a non-empty text string or the
    int index of the image standing there (images numbered in placeholder order across all
    messages). Raises ValueError if the placeholders do not number exactly ``n_images``.
    """
    out: list[tuple[str, list[str | int]]] = []
    index = 0
    for message in messages:
        if not isinstance(message, ChatMessage):
            raise ValueError(f"messages must be ChatMessage values, got {type(message).__name__}")
        pieces: list[str | int] = []
        for k, text in enumerate(message.content.split(IMAGE_PLACEHOLDER)):
            if k > 0:
                pieces.append(index)
                index += 1
            if text:
                pieces.append(text)
        out.append((message.role, pieces))
    if index != n_images:
        raise ValueError(f"the messages hold {index} {IMAGE_PLACEHOLDER} placeholders but {n_images} images were given")
    return out


def encode_png_data_url(rgb: np.ndarray) -> str:
    """``data:image/png;base64,...`` of a uint8 (H, W, 3) image (lossless, deterministic)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buffer, format="PNG", compress_level=1)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode("ascii")


@dataclass(frozen=True)
class HttpBackendConfig:
    """Where the server is and how to talk to it.

    Attributes
    ----------
    base_url : ``http(s)://host:port`` with or without a trailing ``/v1``
    model : model name the server serves (``/v1/models`` lists them)
    api_key : sent as ``Authorization: Bearer <api_key>`` when set
    timeout_s : deadline of a call that passes no ``deadline_s``
    structured_output : ``"json_schema"``, ``"none"`` or ``"auto"`` (see the module docstring)
    temperature : sampling temperature sent to the server (0 = greedy)
    seed : sent as ``seed`` when set (servers that sample use it)
    image_cache_size : encoded images kept, keyed by frame id and pixel digest
    extra_headers : additional ``(name, value)`` request headers (proxies, auth, test faults)
    """

    base_url: str
    model: str
    api_key: str | None = None
    timeout_s: float = 10.0
    structured_output: str = "auto"
    temperature: float = 0.0
    seed: int | None = None
    image_cache_size: int = 16
    extra_headers: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        parsed = urllib.parse.urlsplit(self.base_url)
        if parsed.scheme not in ("http", "https") or not parsed.hostname:
            raise ValueError(f"base_url must look like http://host:port[/v1], got {self.base_url!r}")
        try:
            parsed.port
        except ValueError as exc:
            raise ValueError(f"base_url has a bad port: {self.base_url!r}") from exc
        if not isinstance(self.model, str) or not self.model:
            raise ValueError("model must be a non-empty string")
        if not self.timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {self.timeout_s}")
        if self.structured_output not in STRUCTURED_OUTPUT_MODES:
            raise ValueError(f"structured_output must be one of {STRUCTURED_OUTPUT_MODES}, "
                             f"got {self.structured_output!r}")
        if not 0.0 <= self.temperature <= 2.0:
            raise ValueError(f"temperature must be in [0, 2], got {self.temperature}")
        if self.image_cache_size < 0:
            raise ValueError(f"image_cache_size must be >= 0, got {self.image_cache_size}")
        for header in self.extra_headers:
            if len(header) != 2 or not all(isinstance(x, str) for x in header):
                raise ValueError(f"extra_headers must be (name, value) string pairs, got {header!r}")

    @property
    def endpoint_prefix(self) -> str:
        """URL path prefix of the API, always ending in ``/v1``."""
        path = urllib.parse.urlsplit(self.base_url).path.rstrip("/")
        return path if path.endswith("/v1") else path + "/v1"


class HttpBackend:
    """Client of an OpenAI-compatible chat-completions server (see the module docstring).

    Each call opens its own connection, so one backend may be shared by several threads.

    The OpenAI API returns no vision features. ``feature_source`` gives the verifier features
    anyway: any object with ``features(image)`` (e.g. a :class:`vlm.backend_transformers.
    TransformersBackend` of the served model's family, loaded in process for its vision tower)
    or a callable ``image -> VisionFeatures | None`` (any configured image encoder). Without
    one, :meth:`features` returns None and the verifier refines on the target's depth surface
    (:mod:`planning.verifier`).
    """

    def __init__(self, config: HttpBackendConfig, *, feature_source=None) -> None:
        self.config = config
        if feature_source is None:
            self._feature_fn = None
        elif callable(getattr(feature_source, "features", None)):
            self._feature_fn = feature_source.features
        elif callable(feature_source):
            self._feature_fn = feature_source
        else:
            raise TypeError(f"feature_source must have features(image) or be callable, got {type(feature_source).__name__}")
        self.name = f"http:{config.model}"
        parsed = urllib.parse.urlsplit(config.base_url)
        self._https = parsed.scheme == "https"
        self._host = parsed.hostname
        self._port = parsed.port or (443 if self._https else 80)
        self._prefix = config.endpoint_prefix
        self._send_schema = config.structured_output != "none"
        self._images: OrderedDict[tuple[str, str], str] = OrderedDict()
        self._lock = threading.Lock()
        self._closed = False

    @property
    def url(self) -> str:
        """The chat-completions URL."""
        scheme = "https" if self._https else "http"
        return f"{scheme}://{self._host}:{self._port}{self._prefix}/chat/completions"

    @property
    def sends_json_schema(self) -> bool:
        """Whether the next call with a ``json_schema`` sends ``response_format``."""
        return self._send_schema

    # ----------------------------------------------------------------------------- public API

    def complete(
        self,
        messages: Sequence[ChatMessage],
        images: Sequence[VlmImage] = (),
        *,
        deadline_s: float | None = None,
        json_schema: dict | None = None,
        max_new_tokens: int = 64,
        cache_key: str | None = None,
    ) -> VlmResponse:
        """Ask the server; TIMEOUT / ERROR responses instead of exceptions for call failures.

        Raises ValueError only for caller mistakes (placeholder count, bad arguments).
        """
        t0 = time.monotonic()
        try:
            return self._complete(messages, images, deadline_s, json_schema, max_new_tokens, cache_key, t0)
        except VlmTimeoutError as exc:
            return VlmResponse(CallStatus.TIMEOUT, latency_s=time.monotonic() - t0, error=str(exc))
        except VlmError as exc:
            return VlmResponse(CallStatus.ERROR, latency_s=time.monotonic() - t0, error=str(exc))

    def complete_or_raise(
        self,
        messages: Sequence[ChatMessage],
        images: Sequence[VlmImage] = (),
        *,
        deadline_s: float | None = None,
        json_schema: dict | None = None,
        max_new_tokens: int = 64,
        cache_key: str | None = None,
    ) -> VlmResponse:
        """Like :meth:`complete`, but a failed call raises :class:`VlmTimeoutError`,
        :class:`VlmConnectionError`, :class:`VlmHttpError` or :class:`VlmResponseError`."""
        return self._complete(messages, images, deadline_s, json_schema, max_new_tokens, cache_key, time.monotonic())

    def list_models(self, timeout_s: float = 2.0) -> list[str]:
        """Model ids from ``GET /v1/models``; raises the named errors on failure."""
        body = self._request("GET", f"{self._prefix}/models", None, time.monotonic() + timeout_s, {})
        try:
            return [str(entry["id"]) for entry in body["data"]]
        except (KeyError, TypeError) as exc:
            raise VlmResponseError(f"malformed /v1/models body from {self._host}:{self._port}: "
                                   f"{_snippet(json.dumps(body))}") from exc

    def features(self, image: VlmImage) -> VisionFeatures | None:
        """Features from the local ``feature_source``; None without one (the API has none)."""
        if self._feature_fn is None:
            return None
        result = self._feature_fn(image)
        if result is not None and not isinstance(result, VisionFeatures):
            raise TypeError(f"feature_source returned {type(result).__name__}, expected VisionFeatures or None")
        return result

    def close(self) -> None:
        with self._lock:
            self._images.clear()
            self._closed = True

    def __enter__(self) -> "HttpBackend":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------------------- internals

    def _complete(self, messages, images, deadline_s, json_schema, max_new_tokens, cache_key, t0) -> VlmResponse:
        parts = split_image_placeholders(messages, len(images))
        if max_new_tokens < 1:
            raise ValueError(f"max_new_tokens must be >= 1, got {max_new_tokens}")
        if deadline_s is not None and not deadline_s > 0:
            raise ValueError(f"deadline_s must be > 0 or None, got {deadline_s}")
        if json_schema is not None and not isinstance(json_schema, dict):
            raise ValueError(f"json_schema must be a dict or None, got {type(json_schema).__name__}")
        if self._closed:
            raise VlmConnectionError("backend is closed")
        deadline_mono = t0 + (deadline_s if deadline_s is not None else self.config.timeout_s)
        urls = [self._data_url(image) for image in images]
        body = {
            "model": self.config.model,
            "messages": [_message_json(role, pieces, urls) for role, pieces in parts],
            "max_tokens": int(max_new_tokens),
            "temperature": self.config.temperature,
            "stream": False,
        }
        if self.config.seed is not None:
            body["seed"] = self.config.seed
        headers = {CACHE_KEY_HEADER: cache_key} if cache_key else {}
        with_schema = json_schema is not None and self._send_schema
        if with_schema:
            body["response_format"] = {
                "type": "json_schema",
                "json_schema": {"name": "answer", "schema": json_schema, "strict": True},
            }
        path = f"{self._prefix}/chat/completions"
        try:
            answer = self._request("POST", path, body, deadline_mono, headers)
        except VlmHttpError as exc:
            if not (with_schema and self.config.structured_output == "auto" and _rejects_schema(exc)):
                raise
            log.warning("%s does not accept response_format json_schema (HTTP %d); sending the format "
                        "in the prompt only from now on", self.url, exc.status)
            self._send_schema = False
            del body["response_format"]
            answer = self._request("POST", path, body, deadline_mono, headers)
        text, usage = _parse_completion(answer, self.url)
        return VlmResponse(CallStatus.OK, text=text, usage=usage, latency_s=time.monotonic() - t0)

    def _data_url(self, image: VlmImage) -> str:
        if not isinstance(image, VlmImage):
            raise ValueError(f"images must be VlmImage values, got {type(image).__name__}")
        if not self.config.image_cache_size:
            return encode_png_data_url(image.rgb)
        rgb = np.ascontiguousarray(image.rgb)
        digest = hashlib.blake2b(rgb.tobytes(), digest_size=16)
        digest.update(str(rgb.shape).encode())
        key = (image.frame_id, digest.hexdigest())
        with self._lock:
            url = self._images.get(key)
            if url is not None:
                self._images.move_to_end(key)
                return url
        url = encode_png_data_url(rgb)
        with self._lock:
            self._images[key] = url
            while len(self._images) > self.config.image_cache_size:
                self._images.popitem(last=False)
        return url

    def _request(self, method: str, path: str, body: dict | None, deadline_mono: float, headers: dict) -> dict:
        """One HTTP exchange inside the deadline; returns the decoded JSON object."""
        where = f"{self._host}:{self._port}"

        def remaining() -> float:
            left = deadline_mono - time.monotonic()
            if left <= 0:
                raise VlmTimeoutError(f"no complete answer from {where} within the deadline")
            return left

        payload = None if body is None else json.dumps(body).encode("utf-8")
        all_headers = {"Accept": "application/json", "User-Agent": "onfly-vlm"}
        if payload is not None:
            all_headers["Content-Type"] = "application/json"
        if self.config.api_key:
            all_headers["Authorization"] = f"Bearer {self.config.api_key}"
        all_headers.update(dict(self.config.extra_headers))
        all_headers.update(headers)
        conn_class = http.client.HTTPSConnection if self._https else http.client.HTTPConnection
        conn = conn_class(self._host, self._port, timeout=remaining())
        try:
            conn.connect()
            sock = conn.sock
            all_headers[DEADLINE_HEADER] = f"{remaining():.3f}"
            sock.settimeout(remaining())
            conn.request(method, path, body=payload, headers=all_headers)
            sock.settimeout(remaining())
            response = conn.getresponse()
            chunks: list[bytes] = []
            size = 0
            while True:
                sock.settimeout(remaining())
                chunk = response.read1(65536)
                if not chunk:
                    break
                chunks.append(chunk)
                size += len(chunk)
                if size > _MAX_RESPONSE_BYTES:
                    raise VlmResponseError(f"response from {where} exceeds {_MAX_RESPONSE_BYTES} bytes")
            raw = b"".join(chunks)
        except ConnectionRefusedError as exc:
            raise VlmConnectionError(f"connection refused by {where} (is the server running?)") from exc
        except (socket.timeout, TimeoutError) as exc:
            raise VlmTimeoutError(f"no complete answer from {where} within the deadline") from exc
        except http.client.RemoteDisconnected as exc:
            raise VlmConnectionError(f"{where} closed the connection without answering") from exc
        except http.client.HTTPException as exc:
            raise VlmResponseError(f"bad HTTP response from {where}: {type(exc).__name__}: {exc}") from exc
        except OSError as exc:  # DNS failure, reset, unreachable network
            raise VlmConnectionError(f"cannot reach {where}: {exc}") from exc
        finally:
            conn.close()
        text = raw.decode("utf-8", errors="replace")
        if response.status == 504:  # the server (ours, or a gateway) gave up within the deadline
            raise VlmTimeoutError(f"HTTP 504 from {where}{path}: {_snippet(text)}")
        if response.status >= 400:
            raise VlmHttpError(f"HTTP {response.status} {response.reason} from {where}{path}: {_snippet(text)}",
                               status=response.status, body=text)
        try:
            decoded = json.loads(text)
        except json.JSONDecodeError as exc:
            raise VlmResponseError(f"malformed response body from {where}{path} (not JSON: {exc.msg}): "
                                   f"{_snippet(text)}") from exc
        if not isinstance(decoded, dict):
            raise VlmResponseError(f"malformed response body from {where}{path} (not a JSON object): {_snippet(text)}")
        return decoded


def _message_json(role: str, pieces: list[str | int], urls: list[str]) -> dict:
    """One OpenAI chat message; plain string content when it holds no image."""
    if all(isinstance(p, str) for p in pieces):
        return {"role": role, "content": "".join(pieces)}
    content = [
        {"type": "image_url", "image_url": {"url": urls[p]}} if isinstance(p, int) else {"type": "text", "text": p}
        for p in pieces
    ]
    return {"role": role, "content": content}


def _parse_completion(answer: dict, url: str) -> tuple[str, Usage]:
    """Text and usage of a chat-completions body; VlmResponseError if it is not one."""
    try:
        message = answer["choices"][0]["message"]
        content = message.get("content")
    except (KeyError, IndexError, TypeError, AttributeError) as exc:
        raise VlmResponseError(f"malformed response body from {url} (no choices[0].message): "
                               f"{_snippet(json.dumps(answer))}") from exc
    if content is None:
        content = ""
    elif isinstance(content, list):  # some servers return content parts
        content = "".join(part.get("text", "") for part in content if isinstance(part, dict))
    elif not isinstance(content, str):
        raise VlmResponseError(f"malformed response body from {url} (content is {type(content).__name__})")
    usage_json = answer.get("usage") or {}
    details = usage_json.get("prompt_tokens_details") or {}
    timings = answer.get("timings") or {}
    cached = details.get("cached_tokens") if isinstance(details, dict) else None
    if cached is None and isinstance(timings, dict):
        cached = timings.get("cache_n")
    try:
        usage = Usage(
            prompt_tokens=int(usage_json.get("prompt_tokens") or 0),
            completion_tokens=int(usage_json.get("completion_tokens") or 0),
            cached_tokens=int(cached or 0),
        )
    except (TypeError, ValueError, AttributeError) as exc:
        raise VlmResponseError(f"malformed usage in the response from {url}: {usage_json!r}") from exc
    return content, usage


def _rejects_schema(exc: VlmHttpError) -> bool:
    """Whether an HTTP error says the server does not take ``response_format`` json_schema."""
    if exc.status not in (400, 422):
        return False
    body = exc.body.lower()
    names_field = "response_format" in body or "json_schema" in body
    return names_field and any(word in body for word in _UNSUPPORTED_WORDS)


def _snippet(text: str) -> str:
    text = " ".join(text.split())
    return text if len(text) <= _BODY_SNIPPET else text[:_BODY_SNIPPET] + "..."
