"""The robustness table's two configs (issue 17): the same benchmark in the ideal and the
realistic world, every Table II method, SPF w/ planner and every OnFly ablation, over the
paper's 150 tasks, one run each."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from onfly.bench.onfly_method import ABLATIONS
from onfly.bench.runner import BenchConfig, check_bench

CONFIGS = Path(__file__).resolve().parents[1] / "experiments" / "configs"
TABLE_METHODS = {"typefly", "pivot", "spf", "onfly", "spf_planner"}  # Table II + the planner study


@pytest.fixture(scope="module")
def pair() -> tuple[BenchConfig, BenchConfig]:
    return BenchConfig.from_toml(CONFIGS / "robustness_ideal.toml"), BenchConfig.from_toml(CONFIGS / "robustness_realistic.toml")


def test_the_two_configs_differ_only_in_the_realism_profile(pair):
    ideal, real = pair
    assert ideal.world_settings()["realism"] == "ideal"
    assert real.world_settings()["realism"] == "realistic"
    same = lambda c: replace(c, name="", source=None, world={k: v for k, v in c.world.items() if k != "realism"})  # noqa: E731
    assert same(ideal) == same(real)
    # a realistic episode is a different run: no method's hash coincides
    assert all(ideal.method_hash(m) != real.method_hash(m) for m in ideal.methods)


def test_every_table_method_and_ablation_over_the_150_tasks_once(pair):
    ideal, _ = pair
    assert set(ideal.methods) == TABLE_METHODS | set(ABLATIONS)
    assert len(ideal.methods) == len(set(ideal.methods))
    assert ideal.runs == 1
    tasks = check_bench(ideal, reach_vlm=False)
    assert len(tasks) == 150
