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
    assert table.splitlines()[0] == (
        "| planner.w_yaw | method | episodes | SR % | CR % | FT s | SPL | RMS acc m/s² | RMS jerk m/s³ | path m "
        "| min clearance m | time to goal s | yaw error ° |"
    )
    assert "| 2.0 | oracle | 1 | 0.0 | 0.0 | 1.5 | 0.00 |" in table
    for r in rows:  # what the weights change, beside SR / CR / FT
        assert r["rms_accel_mps2"] > 0 and r["rms_jerk_mps3"] > 0 and r["path_length_m"] > 0
        assert r["time_to_goal_s"] is None  # 1.5 s never reaches the goal
        assert 0 <= r["yaw_error_deg"] <= 180
    page = (out / "sweep.html").read_text()
    assert page.count("<svg") == 10  # one plot per metric for the one key
    assert "RMS jerk m/s³" in page and "planner.w_yaw" in page
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
    with pytest.raises(SweepError, match=r"\[sweep\]: unknown key\(s\) \['grid_size'\]"):
        _sweep(tmp_path, "planner.w_yaw = [1.0]", extra="grid_size = 3")


def test_committed_sweep_config_loads():
    sw = SweepConfig.from_toml("experiments/configs/sweep_planner.toml")
    assert isinstance(sw.base, BenchConfig) and sw.base.methods == ("oracle",)
    assert len(combinations(sw)) == 6 and sw.base.count == 10


def test_format_handles_missing_values():
    rows = [{"k": 1, "method": "m", "episodes": 0, "SR": None, "CR": None, "FT": None, "SPL": None, "min_clearance_m": None}]
    assert format_sweep(rows, ["k"]).splitlines()[-1] == "| 1 | m | 0 | n/a | n/a | n/a | n/a | n/a | n/a | n/a | n/a | n/a | n/a |"


def test_committed_tune_config_is_a_search_over_three_planner_weights():
    sw = SweepConfig.from_toml("experiments/configs/tune_planner.toml")
    assert sw.search is not None and sw.grid == ()
    assert sw.keys == ["planner.w_accel", "planner.w_jerk", "planner.w_yaw"]
    assert sw.search.objectives == (("SR", "max"), ("rms_jerk_mps3", "min"))
    assert sw.base.methods == ("onfly",) and sw.base.count == 8


def test_base_resolves_next_to_the_file_then_in_the_committed_configs(tmp_path):
    """A copied sweep file keeps working: a bare base name falls back to experiments/configs."""
    p = tmp_path / "copy.toml"
    p.write_text('[sweep]\nbase = "quick.toml"\n[grid]\nplanner.w_yaw = [1.0]\n')
    sw = SweepConfig.from_toml(p)
    assert sw.base.methods == ("oracle", "onfly") and sw.base.count == 30
    (tmp_path / "quick.toml").write_text(BASE)  # a file next to the sweep wins
    assert SweepConfig.from_toml(p).base.task_ids == ("corridor-o01",)
    p.write_text('[sweep]\nbase = "sub/quick.toml"\n[grid]\nplanner.w_yaw = [1.0]\n')
    with pytest.raises(SweepError, match=r"base 'sub/quick.toml' not found \(looked at .*/sub/quick.toml\)"):
        SweepConfig.from_toml(p)


SEARCH = """
[search]
trials = 2
sampler = "random"
seed = 4
objectives = ["SR:max", "rms_jerk_mps3:min"]
[search.space]
planner.w_jerk = { low = 0.5, high = 8.0, log = true }
planner.horizon_steps = { low = 10, high = 20, int = true }
"""


def test_sampled_search_resumes_from_sqlite_and_draws(tmp_path, capsys):
    (tmp_path / "base.toml").write_text(BASE)
    p = tmp_path / "search.toml"
    p.write_text('[sweep]\nname = "srch"\nbase = "base.toml"\nruns = 1\n' + SEARCH)
    sw = SweepConfig.from_toml(p)
    out = tmp_path / "out"
    rows = run_sweep(sw, out, workers=1, progress=True)
    err = capsys.readouterr().err
    assert len(rows) == 2 and {r["trial"] for r in rows} == {0, 1}
    for r in rows:
        assert 0.5 <= r["planner.w_jerk"] <= 8.0 and isinstance(r["planner.horizon_steps"], int)
        assert r["rms_jerk_mps3"] > 0
    # the live line names the combination
    first = rows[0]
    assert f"[1/2] planner.w_jerk={first['planner.w_jerk']:.4g} planner.horizon_steps={first['planner.horizon_steps']}: episode 1/1 oracle corridor-o01" in err
    assert (out / "study.db").is_file() and (out / "sweep.html").is_file()
    # a rerun reads the study back: no new trial, no new episode
    again = run_sweep(SweepConfig.from_toml(p), out, workers=1)
    assert again == rows
    # one more trial continues the sampler's sequence instead of repeating its start
    more = run_sweep(SweepConfig.from_toml(p), out, workers=1, trials=1)
    assert len(more) == 3 and more[:2] == rows
    assert (more[2]["planner.w_jerk"], more[2]["planner.horizon_steps"]) not in {(r["planner.w_jerk"], r["planner.horizon_steps"]) for r in rows}
    import optuna

    study = optuna.load_study(study_name="srch", storage=f"sqlite:///{out / 'study.db'}")
    assert len(study.trials) == 3 and all(len(t.values) == 2 for t in study.trials)


def test_same_seed_same_trials(tmp_path):
    """Determinism: the sampler takes the [search] seed; only suggestions are compared (no flight)."""
    import optuna

    def draws(seed):
        study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=seed))
        return [study.ask().suggest_float("w", 0.5, 8.0, log=True) for _ in range(3)]

    assert draws(4) == draws(4) and draws(4) != draws(5)
