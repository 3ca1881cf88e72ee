"""Backend specs -> backends; wrong specs fail listing the valid forms."""

from __future__ import annotations

import pytest

from vlm.backend_http import HttpBackend
from vlm.backend_transformers import TransformersBackend
from vlm.factory import VALID_SPECS, make_backend
from vlm.server import ServerConfig, VlmServer
from vlm.sim import PRESETS, SimulatedVlm
from vlm.tiny_models import build_tiny_vlm
from vlm.types import ChatMessage, VlmBackend, VlmConnectionError


@pytest.mark.parametrize(
    ("spec", "why"),
    [
        ("", "expected <kind>:<argument>"),
        ("qwen", "expected <kind>:<argument>"),
        ("openai:gpt", "unknown kind 'openai'"),
        ("sim:", "needs a preset"),
        ("sim:no-such-preset", "unknown simulated-VLM preset"),
        ("http:", "needs a server address"),
        ("http://", "needs a server address"),
        ("http:ftp://x#m", "base_url"),
        ("transformers:", "needs a checkpoint directory"),
        ("transformers:/no/such/dir/anywhere", "no checkpoint directory"),
    ],
)
def test_wrong_spec_lists_the_valid_forms(spec, why):
    with pytest.raises(ValueError, match="valid forms") as info:
        make_backend(spec)
    assert why in str(info.value) and VALID_SPECS in str(info.value)


def test_non_string_spec():
    with pytest.raises(ValueError, match="valid forms"):
        make_backend(None)


@pytest.mark.parametrize(
    ("spec", "url", "model"),
    [
        ("http:http://127.0.0.1:8000#qwen", "http://127.0.0.1:8000/v1/chat/completions", "qwen"),
        ("http://127.0.0.1:8000/v1#Qwen/Qwen2.5-VL-3B-Instruct", "http://127.0.0.1:8000/v1/chat/completions",
         "Qwen/Qwen2.5-VL-3B-Instruct"),
        ("http:localhost:11434#llava", "http://localhost:11434/v1/chat/completions", "llava"),
        ("https://api.example.org/openai#m", "https://api.example.org:443/openai/v1/chat/completions", "m"),
    ],
)
def test_http_specs(spec, url, model):
    backend = make_backend(spec, timeout_s=2.5)
    assert isinstance(backend, HttpBackend) and isinstance(backend, VlmBackend)
    assert backend.url == url and backend.config.model == model and backend.config.timeout_s == 2.5


def test_http_without_model_asks_the_server():
    class Fake:
        name = "fake"

        def complete(self, *a, **k): ...
        def features(self, image): return None
        def close(self): pass

    with VlmServer(Fake(), ServerConfig(model_name="served-model")).start() as server:
        backend = make_backend(f"http:{server.url}")
    assert backend.config.model == "served-model"


def test_http_without_model_and_no_server_is_a_connection_error():
    with pytest.raises(VlmConnectionError, match="refused"):
        make_backend("http://127.0.0.1:9")


def test_unknown_option_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown option.*'timeout'.*timeout_s"):
        make_backend("http://127.0.0.1:8000#m", timeout=3)
    with pytest.raises(ValueError, match="simulated VLM"):
        make_backend("sim:nominal", colour="red")


def test_transformers_spec_loads_a_checkpoint_directory(tmp_path):
    path = build_tiny_vlm(tmp_path / "tiny-qwen3", family="qwen3_vl")
    with make_backend(f"transformers:{path}", max_streams=2) as backend:
        assert isinstance(backend, TransformersBackend)
        assert backend.config.max_streams == 2 and backend.model_type == "qwen3_vl"
        assert backend.name == "transformers:tiny-qwen3"
        assert backend.complete([ChatMessage("user", "hello")], max_new_tokens=2).ok


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_sim_spec_builds_the_preset_with_the_seed(preset):
    backend = make_backend(f"sim:{preset}", seed=11)
    assert isinstance(backend, SimulatedVlm) and isinstance(backend, VlmBackend)
    assert backend.seed == 11 and backend.model.name == preset
