"""Tiny offline Qwen-VL checkpoints: loadable, deterministic, consistent token ids."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image
from safetensors.torch import load_file
from transformers import AutoImageProcessor, AutoModelForImageTextToText, AutoTokenizer

from vlm.tiny_models import QWEN_SPECIAL_TOKENS, TinyVlmSpec, build_tiny_tokenizer, build_tiny_vlm


@pytest.fixture(scope="module", params=["qwen2_5_vl", "qwen3_vl"])
def tiny_dir(request, tmp_path_factory):
    return build_tiny_vlm(tmp_path_factory.mktemp(request.param), family=request.param, seed=0)


def test_checkpoint_loads_with_auto_classes_and_ids_agree(tiny_dir):
    model = AutoModelForImageTextToText.from_pretrained(tiny_dir)
    tokenizer = AutoTokenizer.from_pretrained(tiny_dir)
    config = model.config
    assert config.model_type in ("qwen2_5_vl", "qwen3_vl")
    assert config.image_token_id == tokenizer.convert_tokens_to_ids("<|image_pad|>")
    assert config.video_token_id == tokenizer.convert_tokens_to_ids("<|video_pad|>")
    assert config.vision_start_token_id == tokenizer.convert_tokens_to_ids("<|vision_start|>")
    assert config.vision_end_token_id == tokenizer.convert_tokens_to_ids("<|vision_end|>")
    assert config.get_text_config().eos_token_id == tokenizer.convert_tokens_to_ids("<|im_end|>")
    assert config.get_text_config().vocab_size == len(tokenizer)
    assert sum(p.numel() for p in model.parameters()) < 1_000_000


def test_processor_budget_keeps_images_small(tiny_dir):
    processor = AutoImageProcessor.from_pretrained(tiny_dir)
    family = json.loads((tiny_dir / "config.json").read_text())["model_type"]
    merge_px = 28 if family == "qwen2_5_vl" else 32
    rgb = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    out = processor(images=[Image.fromarray(rgb)], return_tensors="pt")
    t, gh, gw = out["image_grid_thw"][0].tolist()
    assert t == 1
    assert (gh // 2) * (gw // 2) <= 24  # default budget: 24 merged patches = 24 image tokens
    assert processor.patch_size * processor.merge_size == merge_px


def test_tokenizer_round_trips_any_text_and_keeps_special_tokens():
    tokenizer = build_tiny_tokenizer()
    text = 'Fly to the red van — ✈ {"point_2d": [412, 233]} ünïcödé'
    assert tokenizer.decode(tokenizer(text, add_special_tokens=False)["input_ids"]) == text
    for i, token in enumerate(QWEN_SPECIAL_TOKENS):
        assert tokenizer.convert_tokens_to_ids(token) == i
        assert tokenizer(token, add_special_tokens=False)["input_ids"] == [i]
    rendered = tokenizer.apply_chat_template(
        [{"role": "user", "content": [{"type": "image"}, {"type": "text", "text": "where?"}]}],
        add_generation_prompt=True, tokenize=False)
    assert rendered == "<|im_start|>user\n<|vision_start|><|image_pad|><|vision_end|>where?<|im_end|>\n<|im_start|>assistant\n"


@pytest.mark.parametrize("family", ["qwen2_5_vl", "qwen3_vl"])
def test_same_seed_same_weights_other_seed_other_weights(tmp_path, family):
    a = load_file(build_tiny_vlm(tmp_path / "a", family=family, seed=3) / "model.safetensors")
    b = load_file(build_tiny_vlm(tmp_path / "b", family=family, seed=3) / "model.safetensors")
    c = load_file(build_tiny_vlm(tmp_path / "c", family=family, seed=4) / "model.safetensors")
    assert a.keys() == b.keys() == c.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    assert (tmp_path / "a" / "tokenizer.json").read_text() == (tmp_path / "c" / "tokenizer.json").read_text()


def test_build_leaves_the_global_torch_rng_alone(tmp_path):
    torch.manual_seed(7)
    build_tiny_vlm(tmp_path / "m", seed=1)
    after = torch.rand(4)
    torch.manual_seed(7)
    assert torch.equal(after, torch.rand(4))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"family": "llava"}, "family"),
        ({"text_hidden": 60}, "text_hidden"),
        ({"text_kv_heads": 3}, "text_kv_heads"),
        ({"vocab_size": 100}, "vocab_size"),
        ({"min_pixels": 5000, "max_pixels": 4000}, "min_pixels"),
        ({"vision_depth": 0}, "vision_depth"),
    ],
)
def test_spec_validation_names_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TinyVlmSpec(**kwargs)
