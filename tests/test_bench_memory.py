"""Tests of experiments/bench_memory.py: the invariants its numbers must satisfy, on a tiny run."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from experiments.bench_memory import (
    BenchConfigError,
    BenchMemoryConfig,
    common_prefix_len,
    is_prefix_stable,
    main,
    make_episode,
    make_world,
    memory_calls,
    render,
    render_episode,
    run_benchmark,
)
from onfly.memory import MEMORY_STRATEGIES
from planning.camera import PinholeCamera

# One episode of 70-80 m (the hybrid memory's early calls, while the travelled distance is short
# and segment winners still move, are the least stable; short flights would be dominated by
# them), small 112 x 80 images (12 image tokens) and 4 model calls per strategy, to stay fast.
TINY = BenchMemoryConfig(episodes=1, calls=4, seed=3, path_min_m=70.0, path_max_m=80.0,
                         image_width_px=112, image_height_px=80, image_tokens=24, advance_every=2)
TINY_CAMERA = PinholeCamera.from_fov(112, 80, 90.0, 60.0)


@pytest.fixture(scope="module")
def tiny_result(tmp_path_factory):
    return run_benchmark(TINY, work_dir=tmp_path_factory.mktemp("bench_memory"), reference=False)


def test_prefix_stability_definition():
    prev = ("a", "k1", "k2", "t1")
    assert is_prefix_stable(prev, ("a", "k1", "k2", "t2"))
    assert is_prefix_stable(("a", "t1"), ("a", "k1", "t2"))  # a keyframe appended
    assert not is_prefix_stable(prev, ("a", "k1", "k3", "t2"))
    assert not is_prefix_stable(prev, ("a", "k2", "k3", "t2"))
    assert common_prefix_len(prev, ("a", "k1", "k3", "t2")) == 2


def test_episode_respects_path_length_speed_and_yaw_rate():
    cfg = BenchMemoryConfig()
    ep = make_episode(np.random.default_rng(5), cfg)
    assert cfg.path_min_m <= ep.length_m <= cfg.path_max_m
    assert np.sum(np.linalg.norm(np.diff(ep.path_xy, axis=0), axis=1)) == pytest.approx(ep.length_m)
    step = np.linalg.norm(np.diff(ep.position, axis=0), axis=1)
    assert step.max() <= cfg.speed_mps * cfg.frame_period_s + 1e-9
    dyaw = np.abs(np.angle(np.exp(1j * np.diff(ep.yaw))))
    assert dyaw.max() <= cfg.yaw_rate_radps * cfg.frame_period_s + 1e-9
    assert np.all(ep.position[:, 2] == cfg.altitude_m)


def test_render_is_seeded_and_changes_with_pose():
    cfg = BenchMemoryConfig()
    ep = make_episode(np.random.default_rng(1), cfg)
    world = make_world(np.random.default_rng(2), ep.path_xy)
    cam = PinholeCamera.from_fov(224, 160, 90.0, 60.0)
    a = render(world, cam, ep.position[0], ep.yaw[0], np.random.default_rng(0))
    b = render(world, cam, ep.position[0], ep.yaw[0], np.random.default_rng(0))
    c = render(world, cam, ep.position[0], ep.yaw[0] + 0.5, np.random.default_rng(0))
    assert a.shape == (160, 224, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    assert np.mean(np.abs(a.astype(int) - c.astype(int))) > 10.0


def test_sliding_never_prefix_stable_once_full_and_hybrid_mostly_is(tiny_result):
    full = TINY.slots + 2
    sliding = tiny_result.memory_calls["sliding"]
    after_full = [c for k, c in enumerate(sliding) if k > 0 and len(sliding[k - 1].frame_ids) == full]
    assert len(after_full) >= len(sliding) - 2
    assert not any(c.prefix_stable for c in after_full)
    assert all(c.new_images == TINY.slots + 1 for c in after_full)  # all of Q_t and o_t are new
    hybrid = tiny_result.memory_calls["hybrid"]
    assert all(len(c.frame_ids) == full for c in hybrid[1:])
    assert hybrid[0].prefix_stable is None
    rate = np.mean([c.prefix_stable for c in hybrid[1:]])
    assert rate > 0.5
    assert tiny_result.metrics["prefix_stable_rate_hybrid"] == pytest.approx(rate)
    # a stable call shows exactly one new image (o_t); time sampling moves every slot
    assert all(c.new_images == 1 for c in hybrid if c.prefix_stable)
    assert tiny_result.metrics["prefix_stable_rate_time"] == 0.0


def test_memory_calls_are_deterministic():
    cfg = TINY
    ep = make_episode(np.random.default_rng(0), dataclasses.replace(cfg, path_min_m=20.0, path_max_m=21.0))
    world = make_world(np.random.default_rng(1), ep.path_xy)
    runs = [
        memory_calls("hybrid", ep, render_episode(ep, world, TINY_CAMERA, 0, np.random.default_rng(2)), 0, cfg)
        for _ in range(2)
    ]
    assert [c.frame_ids for c in runs[0]] == [c.frame_ids for c in runs[1]]
    assert len(runs[0]) == (len(ep.t_s) - 1) // cfg.frames_per_call


def test_tiny_run_invariants(tiny_result):
    m = tiny_result.metrics
    assert m["prefix_stable_rate_full_sliding"] == 0.0
    assert m["prefix_stable_rate_hybrid"] > 0.5
    assert m["cached_token_fraction_hybrid"] > m["cached_token_fraction_sliding"]
    assert m["modelled_cached_token_fraction_hybrid"] > m["modelled_cached_token_fraction_sliding"]
    # every model call answered; cold calls reuse nothing, warm calls reuse at least o_1's prefix
    calls = tiny_result.model_calls
    assert len(calls) == len(MEMORY_STRATEGIES) * TINY.calls
    assert all(c.status == "ok" for c in calls)
    assert all(c.cached_tokens == 0 for c in calls if c.cold)
    assert all(c.cached_tokens > 0 for c in calls if not c.cold)
    # the same prompts for every strategy have the same length (same template, S = 4)
    assert len({c.prompt_tokens for c in calls}) == 1
    # sliding: the whole Q_t and o_t are new every call, so the cached part is the head up to o_1
    sliding_warm = {c.cached_tokens for c in calls if c.strategy == "sliding" and not c.cold}
    assert len(sliding_warm) == 1
    assert 0 < m["image_tokens_per_image"] <= TINY.image_tokens


def test_subtask_advance_keeps_the_image_prefix_and_one_vision_pass_per_frame(tiny_result):
    m = tiny_result.metrics
    calls = tiny_result.advance_calls
    advances = [c for c in calls if c.advance]
    assert {c.order for c in advances} == {"v2", "v1_order"} and all(c.call >= 0 for c in advances)
    v2 = {(c.episode, c.call): c for c in advances if c.order == "v2"}
    v1 = {(c.episode, c.call): c for c in advances if c.order == "v1_order"}
    for key, c in v2.items():
        # v1 put the subtask first: an advance re-runs every image; v2 keeps every image but o_t
        # (and any keyframe appended since the last call) cached.
        img = m["image_tokens_per_image"]
        assert c.prompt_tokens == v1[key].prompt_tokens
        assert v1[key].cached_tokens + (TINY.slots + 2) * img <= v1[key].prompt_tokens  # no image cached
        assert c.cached_tokens >= v1[key].cached_tokens + img  # at least o_1 stays cached
    assert m["advance_cached_fraction_v2"] > m["advance_cached_fraction_v1_order"]
    # the decision prompt, the monitoring prompt and features() read one encoder run per frame
    assert m["vision_runs_per_frame_max"] == 1 and m["vision_runs_per_frame_mean"] == 1.0
    assert m["vision_runs_frames"] >= 2 * TINY.calls


def test_json_has_every_key(tiny_result):
    out = json.loads(json.dumps(tiny_result.to_json()))
    for s in MEMORY_STRATEGIES:
        for key in ("prefix_stable_rate_", "cached_token_fraction_", "monitor_ms_median_",
                    "modelled_monitor_ms_median_", "modelled_cached_token_fraction_"):
            assert isinstance(out[key + s], float), key + s
    assert out["latency_ratio_sliding_over_hybrid"] > 0
    assert out["modelled_latency_ratio_sliding_over_hybrid"] > 1.0  # the latency model rewards reuse
    cfg = out["config"]
    assert cfg["image_size"] == [112, 80]
    assert cfg["model"]["family"] == "qwen2_5_vl" and cfg["model"]["parameters"] > 0
    assert (cfg["episodes"], cfg["calls"], cfg["seed"]) == (1, 4, 3)


def test_config_errors():
    with pytest.raises(BenchConfigError, match="calls must be >= 2"):
        BenchMemoryConfig(calls=1)
    with pytest.raises(BenchConfigError, match="integer multiple of frame_period_s"):
        BenchMemoryConfig(monitor_period_s=1.2)
    with pytest.raises(BenchConfigError, match="family must be one of"):
        BenchMemoryConfig(family="llava")


def test_cli_rejects_more_calls_than_the_episode_has(capsys):
    assert main(["--calls", "500", "--path-min-m", "20", "--path-max-m", "21"]) == 2
    assert "fewer than calls=500" in capsys.readouterr().err
