"""In-process transformers backend for Qwen2.5-VL and Qwen3-VL.

Loads ``AutoModelForImageTextToText`` with the checkpoint's image processor and tokenizer (the
combined ``AutoProcessor`` is not needed: image tokens are expanded here, so the backend also
runs where torchvision, which the Qwen video processors need, is missing).

Decoding is greedy and runs its own token loop so that three things stay under our control:

- **Deadline.** A :class:`DeadlineCriteria` (a transformers ``StoppingCriteria``) is checked
  before the prefill and after every forward pass; a call that overruns stops and returns
  ``CallStatus.TIMEOUT``. One forward pass is atomic, so the worst overrun is one pass
  (the prefill of the uncached suffix, or one token).
- **Prefix reuse.** Each ``cache_key`` names a stream (e.g. the decision or the monitoring
  agent) whose token ids and ``DynamicCache`` are kept after the call. The next call on that
  stream finds the longest common prefix with the new prompt, crops the cache to it and runs
  only the new suffix; ``Usage.cached_tokens`` is the reused length. An image token matches
  only if it belongs to an image with the same ``frame_id`` *and* the same pixel digest at the
  same offset, so reused keys and values are exactly those a full run would compute. M-RoPE
  positions are computed for the whole prompt once and sliced, so the suffix sees the same
  positions as in an uncached run.
- **Vision encoding once per frame.** Per-image vision outputs are kept in a small LRU keyed
  like the prefix (frame id + digest), so a frame shown to both agents is encoded once, and
  ``features(image)`` reads the same entry: the decision prompt, the monitoring prompt and the
  verifier share one vision pass per frame (``vision_encoder_runs`` counts them per frame).

``features(image)`` returns the merged patch embeddings the language model reads for the frame,
resampled onto a square patch grid in original-image pixels.

``json_schema`` is accepted and not enforced: there is no constrained decoding in-process; the
prompt carries the output format and the parsers judge the text.
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from transformers import StoppingCriteria

from vlm.backend_http import split_image_placeholders
from vlm.types import CallStatus, ChatMessage, Usage, VisionFeatures, VlmError, VlmImage, VlmResponse

__all__ = [
    "SUPPORTED_MODEL_TYPES",
    "TransformersBackendConfig",
    "TransformersBackend",
    "TransformersBackendError",
    "DeadlineCriteria",
]

log = logging.getLogger(__name__)

SUPPORTED_MODEL_TYPES = ("qwen2_5_vl", "qwen3_vl")
_DTYPES = ("auto", "float32", "bfloat16", "float16")
_DEVICE_RE = re.compile(r"^(cpu|cuda(:\d+)?)$")
_IMAGE_PAD = "<|image_pad|>"

# Used only when neither the tokenizer nor the checkpoint directory carries a chat template.
_FALLBACK_CHATML = (
    "{% for message in messages %}<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}{% else %}"
    "{% for part in message['content'] %}{% if part['type'] == 'image' %}"
    "<|vision_start|><|image_pad|><|vision_end|>{% elif part['type'] == 'text' %}{{ part['text'] }}"
    "{% endif %}{% endfor %}{% endif %}<|im_end|>\n{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)


class TransformersBackendError(VlmError):
    """The checkpoint cannot be loaded or is not a supported model type."""


@dataclass(frozen=True)
class TransformersBackendConfig:
    """How to load and run an in-process VLM.

    Attributes
    ----------
    model_path : checkpoint directory (or Hub id already in the local cache)
    device : ``"cpu"``, ``"cuda"`` or ``"cuda:N"``
    dtype : ``"auto"`` (float32 on CPU, bfloat16 on CUDA), ``"float32"``, ``"bfloat16"``, ``"float16"``
    max_streams : number of ``cache_key`` streams whose KV-cache is kept (LRU)
    reuse_prefix : False disables prefix reuse (every call is a full prefill)
    image_cache_size : frames whose vision outputs are kept (LRU); the prompts and ``features()``
        share them, so 0 makes every reader run the vision tower again
    image_max_pixels, image_min_pixels : override the processor's pixel budget (resized pixels)
    num_threads : torch intra-op threads; 0 leaves torch's setting alone
    """

    model_path: str
    device: str = "cpu"
    dtype: str = "auto"
    max_streams: int = 4
    reuse_prefix: bool = True
    image_cache_size: int = 16
    image_max_pixels: int | None = None
    image_min_pixels: int | None = None
    num_threads: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.model_path, str) or not self.model_path:
            raise ValueError("model_path must be a non-empty string")
        if not _DEVICE_RE.match(self.device):
            raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")
        if self.dtype not in _DTYPES:
            raise ValueError(f"dtype must be one of {_DTYPES}, got {self.dtype!r}")
        if self.max_streams < 1:
            raise ValueError(f"max_streams must be >= 1, got {self.max_streams}")
        if self.image_cache_size < 0:
            raise ValueError(f"image_cache_size must be >= 0, got {self.image_cache_size}")
        for name in ("image_max_pixels", "image_min_pixels"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1 or None, got {value}")
        if (self.image_max_pixels is not None and self.image_min_pixels is not None
                and self.image_min_pixels > self.image_max_pixels):
            raise ValueError(f"image_min_pixels ({self.image_min_pixels}) exceeds image_max_pixels "
                             f"({self.image_max_pixels})")
        if self.num_threads < 0:
            raise ValueError(f"num_threads must be >= 0, got {self.num_threads}")


class DeadlineCriteria(StoppingCriteria):
    """Stop generation once ``clock()`` passes ``deadline_mono`` (None = never).

    Usable in ``model.generate(stopping_criteria=[...])`` as well as in this backend's loop.
    ``clock`` is ``time.monotonic`` unless a test drives time itself.
    """

    def __init__(self, deadline_mono: float | None, clock: Callable[[], float] = time.monotonic) -> None:
        self.deadline_mono = deadline_mono
        self.clock = clock

    def expired(self) -> bool:
        return self.deadline_mono is not None and self.clock() >= self.deadline_mono

    def __call__(self, input_ids, scores, **kwargs):
        import torch

        return torch.full((input_ids.shape[0],), self.expired(), dtype=torch.bool, device=input_ids.device)


@dataclass
class _Stream:
    """What one cache_key stream keeps: the key of every token in the cache, and the cache."""

    keys: list = field(default_factory=list)
    cache: object = None


@dataclass(frozen=True)
class _EncodedImage:
    """Processor output and vision-tower output of one frame (all on the model's device)."""

    grid_thw: object  # LongTensor (3,)
    embeds: object  # Tensor (n_tokens, C_text)
    deepstack: tuple  # Qwen3-VL: one (n_tokens, C_text) tensor per deepstack layer; else ()

    @property
    def n_tokens(self) -> int:
        return int(self.embeds.shape[0])


def _image_key(image: VlmImage) -> tuple[str, str]:
    """Identity of an image for caching: its frame id and a digest of its pixels."""
    rgb = np.ascontiguousarray(image.rgb)
    digest = hashlib.blake2b(rgb.tobytes(), digest_size=16)
    digest.update(str(rgb.shape).encode())
    return (image.frame_id, digest.hexdigest())


class TransformersBackend:
    """A Qwen-VL model loaded in this process (see the module docstring).

    Thread-safe: calls are serialized by a lock; a call that cannot get the lock before its
    deadline returns TIMEOUT. ``clock`` (seconds, monotonic) measures deadlines and latency;
    tests may pass a clock they drive.
    """

    name = "transformers"

    def __init__(self, config: TransformersBackendConfig, *, clock: Callable[[], float] = time.monotonic) -> None:
        import torch
        from transformers import AutoImageProcessor, AutoModelForImageTextToText, AutoTokenizer

        self.config = config
        self._clock = clock
        path = config.model_path
        if config.device.startswith("cuda") and not torch.cuda.is_available():
            raise TransformersBackendError(f"device {config.device!r} requested but CUDA is not available")
        if config.num_threads:
            torch.set_num_threads(config.num_threads)
        dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}.get(
            config.dtype, torch.float32 if config.device == "cpu" else torch.bfloat16)
        try:
            self._model = AutoModelForImageTextToText.from_pretrained(path, dtype=dtype).to(config.device).eval()
            self._tokenizer = AutoTokenizer.from_pretrained(path)
            self._image_processor = AutoImageProcessor.from_pretrained(path)
        except (OSError, ValueError, KeyError) as exc:
            raise TransformersBackendError(f"cannot load a VLM from {path!r}: {exc}") from exc
        self.model_type = str(self._model.config.model_type)
        if self.model_type not in SUPPORTED_MODEL_TYPES:
            raise TransformersBackendError(
                f"{path!r} is a {self.model_type!r} model; supported: {', '.join(SUPPORTED_MODEL_TYPES)}")
        self.name = f"transformers:{Path(path).name or path}"
        self._device = torch.device(config.device)
        self._chat_template = self._find_chat_template(path)
        vision = self._model.config.vision_config
        self._merge = int(vision.spatial_merge_size)
        self._merge_px = int(vision.patch_size) * self._merge
        self._image_token_id = int(self._model.config.image_token_id)
        self._eos_ids = self._eos_token_ids()
        size = dict(self._image_processor.size)
        if config.image_max_pixels is not None:
            size["longest_edge"] = config.image_max_pixels
        if config.image_min_pixels is not None:
            size["shortest_edge"] = config.image_min_pixels
        self._size = size
        self._streams: OrderedDict[str, _Stream] = OrderedDict()
        self._images: OrderedDict[tuple[str, str], _EncodedImage] = OrderedDict()
        self._lock = threading.Lock()
        self._runs_lock = threading.Lock()
        self._vision_runs: dict[str, int] = {}
        self._closed = False

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
        """Greedy answer to the chat; see :class:`vlm.types.VlmBackend`.

        Raises ValueError for caller mistakes (placeholder count, max_new_tokens < 1); a
        timeout or a model failure is returned as TIMEOUT / ERROR.
        """
        t0 = self._clock()
        parts = split_image_placeholders(messages, len(images))
        if max_new_tokens < 1:
            raise ValueError(f"max_new_tokens must be >= 1, got {max_new_tokens}")
        if deadline_s is not None and deadline_s <= 0:
            raise ValueError(f"deadline_s must be > 0 or None, got {deadline_s}")
        if self._closed:
            return VlmResponse(CallStatus.ERROR, error="backend is closed")
        deadline = DeadlineCriteria(None if deadline_s is None else t0 + deadline_s, self._clock)
        if not self._lock.acquire(timeout=-1 if deadline_s is None else deadline_s):
            return VlmResponse(CallStatus.TIMEOUT, latency_s=self._clock() - t0,
                               error=f"backend busy past the {deadline_s:.3f} s deadline")
        try:
            return self._complete_locked(parts, images, deadline, max_new_tokens, cache_key, t0)
        except Exception as exc:  # a model fault must not take the pilot down
            log.exception("transformers backend call failed")
            if cache_key is not None:
                self._streams.pop(cache_key, None)  # its cache may be half-updated
            return VlmResponse(CallStatus.ERROR, latency_s=self._clock() - t0,
                               error=f"{type(exc).__name__}: {exc}")
        finally:
            self._lock.release()

    def features(self, image: VlmImage) -> VisionFeatures:
        """Vision features of ``image`` from the *same* vision pass the prompts use.

        The frame is encoded once (the processor's own resize, exactly as for :meth:`complete`)
        and its merged patch embeddings -- the vectors the language model reads for that image
        -- are kept in the image LRU; the decision prompt, the monitoring prompt and this call
        all read that entry, so one camera frame costs one vision-encoder run
        (:attr:`vision_encoder_runs`). The processor's resize may scale x and y slightly
        differently; the token grid is resampled (nearest token centre, nothing interpolated)
        onto square patches of the smaller token side so the grid covers the image as
        :class:`VisionFeatures` requires.

        Returns
        -------
        VisionFeatures with ``grid`` float32 (Hp, Wp, C_text), ``patch_px`` in original pixels,
        ``source`` ``"<model_type>.visual"``. These are post-merger (language-space) vectors;
        the verifier's tau = 0.5 has not been checked on them with real weights (see
        :mod:`planning.verifier_config`, "Threshold and ROI per feature source").
        """
        import torch

        w, h = image.size
        with self._lock, torch.inference_mode():
            encoded = self._encode_image(image, _image_key(image))
            embeds = encoded.embeds.float().cpu().numpy()
            _, gh, gw = (int(x) for x in encoded.grid_thw.tolist())
        merge = self._merge
        hm, wm = gh // merge, gw // merge
        tokens = embeds.reshape(hm, wm, -1)
        sx, sy = w / wm, h / hm  # original pixels per token, x and y
        patch = min(sx, sy)
        hp, wp = math.ceil(h / patch - 1e-9), math.ceil(w / patch - 1e-9)
        ti = np.minimum(((np.arange(hp) + 0.5) * patch / sy).astype(np.intp), hm - 1)
        tj = np.minimum(((np.arange(wp) + 0.5) * patch / sx).astype(np.intp), wm - 1)
        return VisionFeatures(
            grid=np.ascontiguousarray(tokens[np.ix_(ti, tj)], dtype=np.float32),
            patch_px=float(patch),
            image_size=(w, h),
            source=f"{self.model_type}.visual",
        )

    @property
    def vision_encoder_runs(self) -> dict[str, int]:
        """Vision-tower runs per frame id since construction (a copy)."""
        with self._runs_lock:
            return dict(self._vision_runs)

    def reset_cache(self, cache_key: str | None = None) -> None:
        """Drop the kept KV-cache of one stream (or of all streams, and the image cache)."""
        with self._lock:
            if cache_key is None:
                self._streams.clear()
                self._images.clear()
            else:
                self._streams.pop(cache_key, None)

    def close(self) -> None:
        with self._lock:
            self._streams.clear()
            self._images.clear()
            self._closed = True

    def __enter__(self) -> "TransformersBackend":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------------------- internals

    def _complete_locked(self, parts, images, deadline: DeadlineCriteria, max_new_tokens, cache_key, t0):
        import torch
        from transformers import DynamicCache

        with torch.inference_mode():
            image_keys = [_image_key(im) for im in images]
            encoded = [self._encode_image(im, key) for im, key in zip(images, image_keys)]
            input_ids, token_keys, spans = self._tokenize(parts, encoded, image_keys)
            n_prompt = len(token_keys)
            positions = self._positions(input_ids, encoded, spans)  # (3, 1, L)
            if deadline.expired():
                return self._timeout(t0, deadline, "before the prefill", n_prompt, 0, 0)

            stream = None
            if cache_key is not None and self.config.reuse_prefix:
                stream = self._streams.pop(cache_key, None) or _Stream()
                self._streams[cache_key] = stream
                while len(self._streams) > self.config.max_streams:
                    self._streams.popitem(last=False)
            reused = 0
            cache = None
            if stream is not None and stream.cache is not None:
                reused = _common_prefix(stream.keys, token_keys)
                reused = min(reused, n_prompt - 1)  # at least one token must run to get logits
                for start, end, _ in spans:  # never split an image
                    if start < reused < end:
                        reused = start
                cache = stream.cache
                cache.crop(-(cache.get_seq_length() - reused))
            if cache is None or reused == 0:
                cache = DynamicCache(config=self._model.config.get_text_config())
                reused = 0
            if stream is not None:  # keys follow the cache from here on
                stream.cache, stream.keys = cache, token_keys[:reused]

            suffix = [i for i, (start, _, _) in enumerate(spans) if start >= reused]
            mm = None
            if suffix:
                mm = {"image": self._vision_output([encoded[i] for i in suffix])}
            out = self._model(
                input_ids=input_ids[:, reused:],
                position_ids=positions[:, :, reused:],
                cache=cache,
                use_cache=True,
                mm_encoder_outputs=mm,
                logits_to_keep=1,
            )
            if stream is not None:
                stream.keys = token_keys[:]
            next_pos = int(positions.max()) + 1
            generated: list[int] = []
            status = CallStatus.OK
            while True:
                token = int(out.logits[0, -1].argmax())
                generated.append(token)
                if token in self._eos_ids or len(generated) >= max_new_tokens:
                    break
                if deadline(input_ids, None).item():
                    status = CallStatus.TIMEOUT
                    break
                step = torch.tensor([[token]], device=self._device)
                pos = torch.full((3, 1, 1), next_pos, dtype=torch.long, device=self._device)
                out = self._model(input_ids=step, position_ids=pos, cache=cache, use_cache=True, logits_to_keep=1)
                next_pos += 1
                if stream is not None:
                    stream.keys.append(token)
            if status is CallStatus.TIMEOUT:
                return self._timeout(t0, deadline, f"after {len(generated)} tokens", n_prompt, len(generated), reused)
            text_ids = [t for t in generated if t not in self._eos_ids]
            text = self._tokenizer.decode(text_ids, skip_special_tokens=True)
            usage = Usage(prompt_tokens=n_prompt, completion_tokens=len(generated), cached_tokens=reused)
            return VlmResponse(CallStatus.OK, text=text, usage=usage, latency_s=self._clock() - t0)

    def _timeout(self, t0, deadline, where, n_prompt, n_generated, reused) -> VlmResponse:
        budget = deadline.deadline_mono - t0 if deadline.deadline_mono is not None else float("nan")
        return VlmResponse(
            CallStatus.TIMEOUT,
            usage=Usage(prompt_tokens=n_prompt, completion_tokens=n_generated, cached_tokens=reused),
            latency_s=self._clock() - t0,
            error=f"deadline of {budget:.3f} s passed {where}",
        )

    def _encode_image(self, image: VlmImage, key) -> _EncodedImage:
        """Processor + vision tower for one frame, from the LRU when the frame was seen."""
        hit = self._images.get(key)
        if hit is not None:
            self._images.move_to_end(key)
            return hit
        from PIL import Image

        out = self._image_processor(images=[Image.fromarray(np.ascontiguousarray(image.rgb))],
                                    size=self._size, return_tensors="pt")
        grid = out["image_grid_thw"].to(self._device)
        vision = self._model.model.get_image_features(out["pixel_values"].to(self._device), grid)
        with self._runs_lock:
            self._vision_runs[image.frame_id] = self._vision_runs.get(image.frame_id, 0) + 1
        deepstack = tuple(layer[0] for layer in (getattr(vision, "deepstack_features", None) or ()))
        encoded = _EncodedImage(grid_thw=grid[0], embeds=vision.pooler_output[0], deepstack=deepstack)
        if self.config.image_cache_size:
            self._images[key] = encoded
            while len(self._images) > self.config.image_cache_size:
                self._images.popitem(last=False)
        return encoded

    def _vision_output(self, encoded: list[_EncodedImage]):
        """The model's own vision-output type holding precomputed embeddings of ``encoded``."""
        from transformers.modeling_outputs import BaseModelOutputWithPooling

        pooled = tuple(e.embeds for e in encoded)
        if encoded[0].deepstack:
            from transformers.models.qwen3_vl.modeling_qwen3_vl import BaseModelOutputWithDeepstackFeatures

            layers = [tuple(e.deepstack[i] for e in encoded) for i in range(len(encoded[0].deepstack))]
            return BaseModelOutputWithDeepstackFeatures(pooler_output=pooled, deepstack_features=layers)
        return BaseModelOutputWithPooling(pooler_output=pooled)

    def _tokenize(self, parts, encoded: list[_EncodedImage], image_keys):
        """Prompt token ids (1, L), one key per token, and each image's (start, end, index)."""
        import torch

        hf_messages = [
            {"role": role, "content": [{"type": "image"} if isinstance(p, int) else {"type": "text", "text": p}
                                       for p in pieces]}
            for role, pieces in parts
        ]
        text = self._tokenizer.apply_chat_template(hf_messages, chat_template=self._chat_template,
                                                   add_generation_prompt=True, tokenize=False)
        chunks = text.split(_IMAGE_PAD)
        if len(chunks) - 1 != len(encoded):
            raise VlmError(f"the chat template rendered {len(chunks) - 1} image slots for {len(encoded)} images")
        expanded = chunks[0] + "".join(_IMAGE_PAD * e.n_tokens + chunk for e, chunk in zip(encoded, chunks[1:]))
        ids = self._tokenizer(expanded, add_special_tokens=False)["input_ids"]
        keys: list = []
        spans: list[tuple[int, int, int]] = []
        image = -1
        for i, tok in enumerate(ids):
            if tok == self._image_token_id:
                if not spans or spans[-1][1] != i:
                    image += 1
                    spans.append((i, i, image))
                start, _, index = spans[-1]
                spans[-1] = (start, i + 1, index)
                keys.append((image_keys[index], i - start))
            else:
                keys.append(tok)
        if [end - start for start, end, _ in spans] != [e.n_tokens for e in encoded]:
            raise VlmError("image token runs do not match the images (adjacent images or a tokenizer "
                           "that merges <|image_pad|>)")
        return torch.tensor([ids], device=self._device), keys, spans

    def _positions(self, input_ids, encoded: list[_EncodedImage], spans):
        """M-RoPE position ids (3, 1, L) of the whole prompt."""
        import torch

        mm_types = torch.zeros_like(input_ids, dtype=torch.int32)
        for start, end, _ in spans:
            mm_types[0, start:end] = 1
        grids = torch.stack([e.grid_thw for e in encoded]) if encoded else None
        positions, _ = self._model.model.get_rope_index(input_ids, mm_token_type_ids=mm_types, image_grid_thw=grids)
        return positions

    def _find_chat_template(self, path: str) -> str:
        if getattr(self._tokenizer, "chat_template", None):
            return self._tokenizer.chat_template
        directory = Path(path)
        jinja = directory / "chat_template.jinja"
        if jinja.is_file():
            return jinja.read_text()
        as_json = directory / "chat_template.json"
        if as_json.is_file():
            import json

            return json.loads(as_json.read_text())["chat_template"]
        log.warning("no chat template in %s; using plain ChatML", path)
        return _FALLBACK_CHATML

    def _eos_token_ids(self) -> frozenset[int]:
        """End-of-turn ids as the checkpoint's generation config and tokenizer declare them."""
        ids: set[int] = set()
        for source in (self._model.generation_config.eos_token_id, self._model.config.get_text_config().eos_token_id,
                       self._tokenizer.eos_token_id):
            if source is None:
                continue
            ids.update([source] if isinstance(source, int) else source)
        return frozenset(ids)


def _common_prefix(a: list, b: list) -> int:
    """Length of the longest common prefix of two key lists."""
    n = min(len(a), len(b))
    for i in range(n):
        if a[i] != b[i]:
            return i
    return n
