"""Tiny random-weight Qwen2.5-VL and Qwen3-VL checkpoints, built offline from a config.

No weights can be downloaded on the machines this project runs on, yet the in-process
transformers backend, the loopback server and the memory benchmark need a real model of the
real architecture. :func:`build_tiny_vlm` writes a directory that ``transformers`` loads like
any Hub checkpoint (``config.json``, ``model.safetensors``, ``tokenizer.json``,
``preprocessor_config.json``, ``chat_template.jinja``), so ``"transformers:<dir>"`` works.

What it holds:

- a byte-level BPE tokenizer trained in code on a small navigation corpus (any text encodes;
  nothing is unknown), with Qwen's special tokens ``<|endoftext|>``, ``<|im_start|>``,
  ``<|im_end|>``, ``<|vision_start|>``, ``<|vision_end|>``, ``<|image_pad|>``, ``<|video_pad|>``
  and a ChatML chat template that renders image parts as
  ``<|vision_start|><|image_pad|><|vision_end|>`` like the real Qwen templates;
- a ``Qwen2VLImageProcessor`` with a small ``max_pixels`` so CPU calls take milliseconds;
- a model of a few layers (text hidden 64, vision depth 2) with seeded random weights.

The output of such a model is garbage text: that is the point (the parsers must turn it into a
clean failure). Everything is deterministic given the seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "TINY_FAMILIES",
    "TinyVlmSpec",
    "QWEN_SPECIAL_TOKENS",
    "CHATML_TEMPLATE",
    "build_tiny_tokenizer",
    "build_tiny_vlm",
]

TINY_FAMILIES = ("qwen2_5_vl", "qwen3_vl")

QWEN_SPECIAL_TOKENS = (
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|image_pad|>",
    "<|video_pad|>",
)

# ChatML as the Qwen-VL templates render it, without Qwen2.5-VL's default system prompt.
# Content is either a string or a list of {"type": "image"} / {"type": "text", "text": ...}.
CHATML_TEMPLATE = (
    "{% for message in messages %}"
    "<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}"
    "{% else %}{% for part in message['content'] %}"
    "{% if part['type'] == 'image' %}<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif part['type'] == 'text' %}{{ part['text'] }}{% endif %}"
    "{% endfor %}{% endif %}"
    "<|im_end|>\n"
    "{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

# Text the tokenizer's merges are learned from: instructions, agent prompts, the output formats
# the parsers accept. Its only job is a plausible vocabulary; it is not a data set.
_CORPUS = (
    "fly through the gate, then stop next to the red van",
    "go up the stairs and turn left at the white door, stop in front of the window",
    "You are the decision agent of a drone. Subtask: fly to the blue car.",
    "Answer with one point on the target in the image.",
    "You are the monitoring agent. Answer CONTINUE, STOP or LOST.",
    '{"point_2d": [412, 233], "label": "red van"}',
    '{"bbox_2d": [10, 20, 110, 220]}',
    '```json\n[{"point": [0.5, 0.25]}]\n```',
    '<points x1="31.5" y1="60.2" alt="tree">tree</points>',
    "STATUS: CONTINUE. The target is still far away.",
    "0123456789 ,.:;!?()[]{}<>\"'-_/",
)


@dataclass(frozen=True)
class TinyVlmSpec:
    """Sizes of a tiny model; the defaults answer a two-image call in tens of milliseconds.

    Attributes
    ----------
    family : ``"qwen2_5_vl"`` or ``"qwen3_vl"``
    text_hidden : decoder width; heads of 16 dims each
    text_layers : decoder layers
    text_heads : attention heads (``text_hidden / text_heads`` must be 16: the M-RoPE
        sections are fixed at (2, 3, 3) pairs)
    text_kv_heads : key/value heads (grouped-query attention), divides ``text_heads``
    vision_hidden, vision_depth, vision_heads : vision tower width, blocks, heads
    vocab_size : BPE vocabulary including the special tokens
    max_pixels : image processor budget in resized pixels (smaller = fewer image tokens)
    min_pixels : lower bound of the same
    seed : seeds the weights
    """

    family: str = "qwen2_5_vl"
    text_hidden: int = 64
    text_layers: int = 2
    text_heads: int = 4
    text_kv_heads: int = 2
    vision_hidden: int = 32
    vision_depth: int = 2
    vision_heads: int = 2
    vocab_size: int = 400
    max_pixels: int = 0  # 0 = the family's default: 24 merged patches
    min_pixels: int = 0  # 0 = the family's default: 4 merged patches
    seed: int = 0

    def __post_init__(self) -> None:
        if self.family not in TINY_FAMILIES:
            raise ValueError(f"family must be one of {TINY_FAMILIES}, got {self.family!r}")
        for name in ("text_hidden", "text_layers", "text_heads", "text_kv_heads", "vision_hidden",
                     "vision_depth", "vision_heads", "vocab_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.text_hidden != 16 * self.text_heads:
            raise ValueError(f"text_hidden must be 16 * text_heads (head dim 16), got "
                             f"{self.text_hidden} with {self.text_heads} heads")
        if self.text_heads % self.text_kv_heads:
            raise ValueError(f"text_kv_heads ({self.text_kv_heads}) must divide text_heads ({self.text_heads})")
        if self.vision_hidden % self.vision_heads or (self.vision_hidden // self.vision_heads) % 4:
            raise ValueError(f"vision_hidden / vision_heads must be a multiple of 4, got "
                             f"{self.vision_hidden} / {self.vision_heads}")
        if self.vocab_size < len(QWEN_SPECIAL_TOKENS) + 256:
            raise ValueError(f"vocab_size must hold 256 byte tokens and the special tokens, got {self.vocab_size}")
        if self.max_pixels < 0 or self.min_pixels < 0:
            raise ValueError("max_pixels and min_pixels must be >= 0")
        if self.max_pixels and self.min_pixels > self.max_pixels:
            raise ValueError(f"min_pixels ({self.min_pixels}) exceeds max_pixels ({self.max_pixels})")

    @property
    def patch_size(self) -> int:
        """Vision patch side in resized pixels (14 for Qwen2.5-VL, 16 for Qwen3-VL)."""
        return 14 if self.family == "qwen2_5_vl" else 16

    @property
    def merge_px(self) -> int:
        """Side of one merged (2 x 2) patch, i.e. one image token, in resized pixels."""
        return 2 * self.patch_size

    def pixel_budget(self) -> tuple[int, int]:
        """``(min_pixels, max_pixels)`` with the family defaults filled in."""
        unit = self.merge_px**2
        return (self.min_pixels or 4 * unit, self.max_pixels or 24 * unit)


def build_tiny_tokenizer(vocab_size: int = 400):
    """A byte-level BPE ``PreTrainedTokenizerFast`` with Qwen's special tokens and ChatML.

    Trained on a fixed in-code corpus, so the result is identical on every call. Special token
    ids are 0..6 in the order of :data:`QWEN_SPECIAL_TOKENS`.
    """
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import PreTrainedTokenizerFast

    tokenizer = Tokenizer(models.BPE())
    tokenizer.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tokenizer.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        special_tokens=list(QWEN_SPECIAL_TOKENS),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tokenizer.train_from_iterator(list(_CORPUS) * 4, trainer)
    return PreTrainedTokenizerFast(
        tokenizer_object=tokenizer,
        eos_token="<|im_end|>",
        pad_token="<|endoftext|>",
        additional_special_tokens=list(QWEN_SPECIAL_TOKENS[1:]),
        chat_template=CHATML_TEMPLATE,
    )


def _model_config(spec: TinyVlmSpec, tokenizer):
    """The transformers config of ``spec``, token ids taken from ``tokenizer``."""
    ids = {tok: tokenizer.convert_tokens_to_ids(tok) for tok in QWEN_SPECIAL_TOKENS}
    text = dict(
        vocab_size=len(tokenizer),
        hidden_size=spec.text_hidden,
        intermediate_size=2 * spec.text_hidden,
        num_hidden_layers=spec.text_layers,
        num_attention_heads=spec.text_heads,
        num_key_value_heads=spec.text_kv_heads,
        max_position_embeddings=4096,
        bos_token_id=ids["<|endoftext|>"],
        eos_token_id=ids["<|im_end|>"],
        pad_token_id=ids["<|endoftext|>"],
    )
    vision = dict(
        depth=spec.vision_depth,
        hidden_size=spec.vision_hidden,
        intermediate_size=2 * spec.vision_hidden,
        num_heads=spec.vision_heads,
        out_hidden_size=spec.text_hidden,
        patch_size=spec.patch_size,
        spatial_merge_size=2,
        temporal_patch_size=2,
    )
    token_ids = dict(
        image_token_id=ids["<|image_pad|>"],
        video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"],
        vision_end_token_id=ids["<|vision_end|>"],
    )
    if spec.family == "qwen2_5_vl":
        from transformers import Qwen2_5_VLConfig

        text["rope_parameters"] = {"rope_type": "default", "rope_theta": 1e6, "mrope_section": [2, 3, 3]}
        vision.update(window_size=112, fullatt_block_indexes=[spec.vision_depth - 1])
        return Qwen2_5_VLConfig(text_config=text, vision_config=vision, **token_ids)

    from transformers import Qwen3VLConfig

    text["head_dim"] = 16
    text["rope_parameters"] = {
        "rope_type": "default", "rope_theta": 5e5, "mrope_section": [2, 3, 3], "mrope_interleaved": True,
    }
    vision.update(num_position_embeddings=64, deepstack_visual_indexes=[0])
    return Qwen3VLConfig(text_config=text, vision_config=vision, **token_ids)


def _image_processor(spec: TinyVlmSpec):
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    min_pixels, max_pixels = spec.pixel_budget()
    kwargs = dict(min_pixels=min_pixels, max_pixels=max_pixels, patch_size=spec.patch_size,
                  merge_size=2, temporal_patch_size=2)
    if spec.family == "qwen3_vl":  # Qwen3-VL normalizes to [-1, 1]
        kwargs.update(image_mean=[0.5, 0.5, 0.5], image_std=[0.5, 0.5, 0.5])
    return Qwen2VLImageProcessorPil(**kwargs)


def build_tiny_vlm(out_dir: str | Path, spec: TinyVlmSpec | None = None, *, family: str | None = None,
                   seed: int | None = None) -> Path:
    """Write a tiny random-weight checkpoint to ``out_dir`` and return the directory.

    Parameters
    ----------
    out_dir : directory to create (or overwrite files in)
    spec : sizes; default ``TinyVlmSpec()``
    family, seed : shortcuts that override ``spec.family`` / ``spec.seed``

    The same spec and seed write the same weights, tokenizer and processor config. The global
    torch RNG is left as it was.
    """
    import torch

    base = spec or TinyVlmSpec()
    if family is not None or seed is not None:
        base = TinyVlmSpec(**{**base.__dict__, **({"family": family} if family is not None else {}),
                              **({"seed": seed} if seed is not None else {})})
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    tokenizer = build_tiny_tokenizer(base.vocab_size)
    config = _model_config(base, tokenizer)
    if base.family == "qwen2_5_vl":
        from transformers import Qwen2_5_VLForConditionalGeneration as model_class
    else:
        from transformers import Qwen3VLForConditionalGeneration as model_class
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(base.seed)
        model = model_class(config).eval()
    # Like the real Qwen-VL checkpoints: a turn ends at <|im_end|> or <|endoftext|>.
    model.generation_config.do_sample = False
    model.generation_config.eos_token_id = [config.get_text_config().eos_token_id,
                                            config.get_text_config().bos_token_id]
    model.generation_config.pad_token_id = config.get_text_config().pad_token_id
    model.save_pretrained(out)
    tokenizer.save_pretrained(out)
    _image_processor(base).save_pretrained(out)
    return out
