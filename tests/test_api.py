"""The public API: the examples of docs/api.md (the README's) run as written, and the API, the
CLI and the benchmark share one set of defaults."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

import onfly
from onfly import defaults

DOCS = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOCS.read_text(), re.S)


def test_docs_examples_run_and_report_what_they_print(tmp_path, monkeypatch, capsys):
    blocks = _blocks()
    assert len(blocks) == 3
    assert all(len([line for line in b.splitlines() if line.strip()]) < 10 for b in blocks)  # "in under ten lines"
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    for block in blocks:
        exec(compile(block, str(DOCS), "exec"), ns)
    out = capsys.readouterr().out.splitlines()
    flight, res, report = ns["flight"], ns["res"], ns["report"]
    # 1. the OnFly pilot with custom planner weights flew the task and wrote a log
    assert flight.method == "onfly" and flight.vlm == defaults.VLM
    assert flight.success and flight.end_reason == "stopped" and flight.failure == ""
    assert 0 < flight.motion["rms_jerk_mps3"] < 20 and 0 <= flight.motion["yaw_error_deg"] <= 180
    assert flight.min_clearance_m > 0.25  # the body radius: never inside an obstacle
    assert out[0].startswith("success True  FT ")
    assert (tmp_path / "runs" / "parking-log" / "meta.json").is_file()
    # 2. the benchmark from Python: two oracle episodes, both successful, results on disk
    assert res.summary["episodes"] == 2 and res.summary["methods"]["oracle"]["SR"] == 1.0
    assert res.errored == ()
    assert (tmp_path / "runs" / "api-bench" / "episodes.jsonl").is_file()
    assert out[2].startswith("SR 100 %  CR 0 %")
    # 3. the replay of the log example 1 wrote
    assert report.frames == 20 and report.path_clearance_min_m > 0
    assert out[3].startswith("20 frames  path clearance")


def test_import_onfly_is_light_and_names_resolve_lazily():
    code = ("import sys, onfly, planning; heavy = {'open3d', 'casadi', 'scipy', 'torch', 'rosbags'}; "
            "print(sorted(heavy & {m.split('.')[0] for m in sys.modules}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True).stdout
    assert out.strip() == "[]"
    from onfly.bench.runner import BenchConfig
    from planning.planner_config import PlannerConfig

    assert onfly.BenchConfig is BenchConfig and onfly.PlannerConfig is PlannerConfig
    import planning

    assert planning.PlannerConfig is PlannerConfig
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        onfly.nope  # noqa: B018


def test_one_set_of_defaults_for_api_cli_and_benchmark():
    from onfly.bench.episode import EpisodeConfig
    from onfly.bench.runner import BenchConfig
    from onfly.cli import build_parser

    ep = EpisodeConfig()
    assert (ep.frame_period_s, ep.time_limit_s, ep.control_period_s, ep.success_radius_m) == (0.5, 70.0, 0.1, 5.0)
    assert BenchConfig().world_settings() == {
        "width_px": 320, "height_px": 214, "hfov_deg": 90.0, "vfov_deg": 60.0, "render_threads": 1, "realism": "ideal"
    }
    assert BenchConfig().vlm == defaults.VLM
    args = build_parser(["run"]).parse_args(["run", "--task", "x"])
    # the CLI leaves unset values to the shared defaults (None = "as the benchmark")
    assert args.frame_period_s is None and args.width is None and args.time_limit_s is None
    assert args.vlm == defaults.VLM and args.method == defaults.METHOD
    import inspect

    sig = inspect.signature(onfly.fly)
    assert sig.parameters["vlm"].default == defaults.VLM and sig.parameters["method"].default == defaults.METHOD
    # the committed quick config states the defaults explicitly, and they agree
    quick = BenchConfig.from_toml(Path(__file__).resolve().parents[1] / "experiments" / "configs" / "quick.toml")
    assert quick.world_settings() == BenchConfig().world_settings()
    assert EpisodeConfig(**quick.episode) == ep


def test_api_errors_name_the_argument(tmp_path):
    from onfly.api import ApiError
    from onfly.bench.runner import BenchConfigError

    with pytest.raises(ApiError, match="no task 'nope'"):
        onfly.fly("nope")
    with pytest.raises(ApiError, match="planner must be a config object or a dict"):
        onfly.fly("parking_lot-o01", planner=3)
    with pytest.raises(BenchConfigError, match="unknown simulated-VLM preset 'nomnal'"):
        onfly.benchmark(onfly.BenchConfig(methods=("oracle",), task_ids=("parking_lot-o01",), vlm="sim:nomnal"), tmp_path / "b")
    assert not (tmp_path / "b").exists()


def test_readme_api_example_runs_as_written(tmp_path, monkeypatch, capsys):
    readme = DOCS.parents[1] / "README.md"
    blocks = re.findall(r"```python\n(.*?)```", readme.read_text(), re.S)
    assert len(blocks) == 1 and len([line for line in blocks[0].splitlines() if line.strip()]) < 10
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(blocks[0], str(readme), "exec"), ns)
    out = capsys.readouterr().out.splitlines()
    assert ns["flight"].success and out[0].startswith("True ")
    assert out[1] == "1.0"  # both oracle episodes succeeded
    assert ns["report"].frames == 20 and float(out[2]) > 0
