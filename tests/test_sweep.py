"""Config sweeps: grid expansion, dotted keys, the table, resumption and errors."""

from __future__ import annotations

import json

import pytest

from onfly.bench.runner import BenchConfig, read_records
from onfly.bench.sweep import SweepConfig, SweepError, apply_setting, combinations, format_sweep, run_sweep

BASE = """
[bench]
name = "base"
methods = ["oracle"]
runs = 1
seed = 3
vlm = "sim:nominal"
[bench.tasks]
ids = ["corridor-o01"]
[episode]
time_limit_s = 1.5
[world]
width_px = 64
height_px = 43
"""


def _sweep(tmp_path, grid: str, extra: str = "") -> SweepConfig:
    (tmp_path / "base.toml").write_text(BASE)
    p = tmp_path / "sweep.toml"
    p.write_text(f'[sweep]\nname = "s"\nbase = "base.toml"\n{extra}\n[grid]\n{grid}\n')
    return SweepConfig.from_toml(p)


def test_grid_is_the_product_of_dotted_keys(tmp_path):
    sw = _sweep(tmp_path, "planner.w_yaw = [0.5, 1.0, 2.0]\nplanner.w_jerk = [1.0, 4.0]\nmethods.oracle.lookahead_m = [3.0]")
    combos = combinations(sw)
    assert len(combos) == 6
    assert combos[0] == {"planner.w_yaw": 0.5, "planner.w_jerk": 1.0, "methods.oracle.lookahead_m": 3.0}
    assert combos[-1]["planner.w_yaw"] == 2.0 and combos[-1]["planner.w_jerk"] == 4.0
    cfg = sw.base
    for k, v in combos[1].items():
        cfg = apply_setting(cfg, k, v)
    assert cfg.shared["planner"] == {"w_yaw": 0.5, "w_jerk": 4.0}
    assert cfg.method_options["oracle"] == {"lookahead_m": 3.0}
    assert cfg.method_hash("oracle") != sw.base.method_hash("oracle")
    assert sw.base.name == "s" and sw.base.task_ids == ("corridor-o01",)


def test_sweep_runs_every_combination_and_resumes(tmp_path):
    sw = _sweep(tmp_path, "planner.w_yaw = [1.0, 2.0]", extra="runs = 1")
    out = tmp_path / "out"
    rows = run_sweep(sw, out, workers=1)
    assert [r["planner.w_yaw"] for r in rows] == [1.0, 2.0]
    for r in rows:
        assert r["method"] == "oracle" and r["episodes"] == 1
        assert r["SR"] == 0.0 and r["CR"] == 0.0 and r["FT"] == pytest.approx(1.5)
        assert r["min_clearance_m"] > 0.25
    folders = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert folders == ["w_yaw=1.0", "w_yaw=2.0"]
    saved = json.loads((out / "sweep.json").read_text())
    assert saved["rows"] == rows
    table = (out / "sweep.md").read_text()
    assert table.splitlines()[0].startswith("| planner.w_yaw | method | episodes | SR % | CR % | FT s | SPL | min clearance m |")
    assert "| 2.0 | oracle | 1 | 0.0 | 0.0 | 1.5 | 0.00 |" in table
    again = run_sweep(sw, out, workers=1)  # resumes: nothing new to run
    assert again == rows
    assert sum(len(read_records(out / f / "episodes.jsonl")) for f in folders) == 2


def test_sweep_errors_name_the_key(tmp_path):
    with pytest.raises(SweepError, match=r"grid key 'w_yaw': expected <table>.<field>"):
        _sweep(tmp_path, "w_yaw = [1.0]")
    with pytest.raises(SweepError, match=r"grid key 'planner.w_yaw': expected a non-empty list"):
        _sweep(tmp_path, "planner.w_yaw = 1.0")
    with pytest.raises(SweepError, match=r"\[grid\] lists no values"):
        _sweep(tmp_path, "")
    with pytest.raises(SweepError, match=r"grid key 'episode.time_limit_s': .*must be positive"):
        _sweep(tmp_path, "episode.time_limit_s = [-1.0]")
    with pytest.raises(SweepError, match=r"\[sweep\]: unknown field\(s\) \['grid_size'\]"):
        _sweep(tmp_path, "planner.w_yaw = [1.0]", extra="grid_size = 3")


def test_committed_sweep_config_loads():
    sw = SweepConfig.from_toml("experiments/configs/sweep_planner.toml")
    assert isinstance(sw.base, BenchConfig) and sw.base.methods == ("oracle",)
    assert len(combinations(sw)) == 6 and sw.base.count == 10


def test_format_handles_missing_values():
    rows = [{"k": 1, "method": "m", "episodes": 0, "SR": None, "CR": None, "FT": None, "SPL": None, "min_clearance_m": None}]
    assert format_sweep(rows, ["k"]).splitlines()[-1] == "| 1 | m | 0 | n/a | n/a | n/a | n/a | n/a |"
