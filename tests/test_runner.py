"""The benchmark runner: resumption, worker-count and Ray invariance, seeds, summaries, errors."""

from __future__ import annotations

import copy
import json
import shutil

import pytest

from onfly.bench.runner import (
    EPISODES_FILE,
    BenchConfig,
    BenchConfigError,
    episode_seed,
    error_model_name,
    format_summary,
    read_records,
    run_bench,
)
from onfly.cli import main

TASKS = ["villa-o01", "corridor-p05"]


def _config(**over) -> BenchConfig:
    data = {
        "bench": {"name": "t", "methods": ["oracle"], "runs": 2, "seed": 7, "vlm": "sim:nominal", "tasks": {"ids": TASKS}},
        # short episodes and a small camera: these tests check the runner, not the flight
        "episode": {"time_limit_s": 2.0},
        "world": {"width_px": 64, "height_px": 43},
    }
    data.update(over)
    return BenchConfig.from_dict(data)


def _comparable(records):
    """Records without wall-clock figures, keyed and sorted."""
    out = []
    for r in records:
        r = copy.deepcopy(r)
        r.pop("wall_s")
        r.pop("cpu_s")
        r["method_summary"].pop("timing_ms", None)
        out.append(r)
    return sorted(out, key=lambda r: r["key"])


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    first = run_bench(_config(), out, workers=1, max_episodes=3)  # "interrupted" after 3 of 4
    second = run_bench(_config(), out, workers=1)
    return out, first, second


def test_interrupted_run_resumes_only_the_rest(serial_run):
    out, first, second = serial_run
    assert (first.ran, first.skipped) == (3, 0) and first.summary["complete"] is False
    assert (second.ran, second.skipped) == (1, 3) and second.summary["complete"] is True
    lines = read_records(out / EPISODES_FILE)
    assert len(lines) == 4 and len({r["key"] for r in lines}) == 4
    third = run_bench(_config(), out, workers=1)
    assert third.ran == 0 and third.skipped == 4
    assert _comparable(third.records) == _comparable(second.records)


def test_a_folder_other_code_flew_is_not_resumed_unless_asked(serial_run, tmp_path, monkeypatch, capsys):
    """Every record names the code that flew it; resuming a folder of another code version
    would put two versions in one table, so it is refused before anything flies."""
    import onfly.bench.runner as runner
    from onfly.bench.code_version import CodeVersion

    src, _, second = serial_run
    here = {r["code"]["digest"] for r in second.records}
    assert len(here) == 1 and second.summary["code"] == [second.records[0]["code"]]
    out = tmp_path / "mixed"
    shutil.copytree(src, out)
    lines = (out / EPISODES_FILE).read_text().splitlines()
    (out / EPISODES_FILE).write_text("\n".join(lines[:2]) + "\n")  # 2 of 4 episodes, by this code
    monkeypatch.setattr(runner, "code_version", lambda: CodeVersion("ffffffff00000000", "5678ef01"))
    with pytest.raises(runner.MixedCodeError, match="digest ffffffff00000000.*--allow-mixed-code") as info:
        run_bench(_config(), out, workers=1)
    assert str(out / EPISODES_FILE) in str(info.value) and next(iter(here)) in str(info.value)
    assert len(read_records(out / EPISODES_FILE)) == 2  # nothing flown, nothing lost
    # the command line reports it as a usage error
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[bench]\nname = "t"\nmethods = ["oracle"]\nruns = 2\nseed = 7\nvlm = "sim:nominal"\n'
        '[bench.tasks]\nids = ["villa-o01", "corridor-p05"]\n[episode]\ntime_limit_s = 2.0\n[world]\nwidth_px = 64\nheight_px = 43\n'
    )
    assert main(["bench", "--config", str(cfg), "--out", str(out), "--no-progress"]) == 2
    assert "--allow-mixed-code" in capsys.readouterr().err
    res = run_bench(_config(), out, workers=1, allow_mixed_code=True)
    assert (res.ran, res.skipped) == (2, 2)
    assert sorted(c["digest"] for c in res.summary["code"]) == sorted({"ffffffff00000000", *here})
    # records from before the runner named the code pass (nothing to compare)
    old = tmp_path / "old"
    shutil.copytree(src, old)
    bare = [json.loads(line) for line in (old / EPISODES_FILE).read_text().splitlines()[:2]]
    for r in bare:
        r.pop("code")
    (old / EPISODES_FILE).write_text("".join(json.dumps(r) + "\n" for r in bare))
    assert run_bench(_config(), old, workers=1).ran == 2


def test_two_workers_give_the_same_records(serial_run, tmp_path):
    _, _, serial = serial_run
    parallel = run_bench(_config(), tmp_path, workers=2)
    assert parallel.ran == 4
    assert _comparable(parallel.records) == _comparable(serial.records)


def test_records_hold_what_the_issue_asks(serial_run):
    _, _, res = serial_run
    for r in res.records:
        assert r["seed"] == episode_seed(7, r["task"], r["run"])
        assert r["method"] == "oracle" and r["error_model"] == "nominal" and r["kind"] in ("object", "precise")
        assert set(r["metrics"]) >= {"success", "oracle_success", "collided", "flight_time_s", "navigation_error_m", "spl"}
        assert r["end_reason"] == "time_limit" and r["failure"] == "time_limit"  # 2 s is too short to arrive
        assert r["sim_s"] == pytest.approx(2.0) and r["wall_s"] > 0
        assert r["min_clearance_m"] > 0.25
        assert "vlm_calls" in r and "vlm_charged_s" in r and len(r["config_hash"]) == 16
    s = res.summary
    block = s["methods"]["oracle"]
    for key in ("SR", "OSR", "CR", "FT", "NE", "SPL", "episodes", "error_model", "realtime_factor"):
        assert key in block
    assert block["episodes"] == 4 and block["SR"] == 0.0 and block["CR"] == 0.0
    assert block["FT"] == pytest.approx(2.0)
    assert block["failures"] == {"time_limit": 4}
    assert set(block["by_kind"]) == {"object", "precise"} and block["by_kind"]["object"]["episodes"] == 2
    assert s["error_model"] == "nominal" and s["realtime_factor"] > 0 and s["realtime_factor_cpu"] > 0
    table = format_summary(s)
    assert "| oracle | all | 4 |   0.0 |" in table and "| oracle | precise | 2 |" in table


def test_seeds_depend_on_base_seed_task_and_run_only():
    a = episode_seed(0, "villa-o01", 0)
    assert a == episode_seed(0, "villa-o01", 0)
    assert len({a, episode_seed(1, "villa-o01", 0), episode_seed(0, "villa-o02", 0), episode_seed(0, "villa-o01", 1)}) == 4
    assert 0 <= a < 2**31


def test_config_hash_ignores_workers_but_not_the_planner():
    base = _config()
    assert base.method_hash("oracle") == _config(bench={**{"name": "t", "methods": ["oracle"], "runs": 2, "seed": 7,
                                                         "tasks": {"ids": TASKS}}, "workers": 2}).method_hash("oracle")
    assert base.method_hash("oracle") != _config(planner={"w_yaw": 1.0}).method_hash("oracle")
    assert base.method_hash("oracle") != _config(methods={"oracle": {"lookahead_m": 3.0}}).method_hash("oracle")


def test_torn_last_line_is_skipped(serial_run, tmp_path):
    out, _, _ = serial_run
    path = tmp_path / EPISODES_FILE
    path.write_text((out / EPISODES_FILE).read_text() + '{"key": "trunc')
    assert len(read_records(path)) == 4


def test_bad_configs_name_the_field(tmp_path):
    with pytest.raises(BenchConfigError, match=r"unknown table\(s\) \['planer'\]"):
        BenchConfig.from_dict({"planer": {}})
    with pytest.raises(BenchConfigError, match="bench.runs must be a positive integer"):
        BenchConfig.from_dict({"bench": {"runs": 0}})
    with pytest.raises(BenchConfigError, match=r"\[episode\]: .*unexpected keyword argument 'limit_s'"):
        BenchConfig.from_dict({"episode": {"limit_s": 3}})
    with pytest.raises(BenchConfigError, match=r"\[world\]: unknown field\(s\) \['fov'\]"):
        BenchConfig.from_dict({"world": {"fov": 3}})
    with pytest.raises(BenchConfigError, match=r"unknown method\(s\) \['no_such_method'\]; registered methods: .*oracle"):
        run_bench(_config(bench={"methods": ["no_such_method"], "tasks": {"ids": TASKS}}), tmp_path)
    with pytest.raises(ValueError, match=r"unknown task id\(s\) \['nope'\]"):
        run_bench(_config(bench={"methods": ["oracle"], "tasks": {"ids": ["nope"]}}), tmp_path)
    bad = tmp_path / "bad.toml"
    bad.write_text("[bench]\nruns = [")
    with pytest.raises(BenchConfigError, match="bad.toml: not valid TOML"):
        BenchConfig.from_toml(bad)
    assert error_model_name("sim:weak") == "weak" and error_model_name("http://x:8000") == "real:http://x:8000"


def test_cli_resumes_and_writes_the_summary_json(serial_run, tmp_path, capsys):
    out, _, _ = serial_run
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[bench]\nname = "t"\nmethods = ["oracle"]\nruns = 2\nseed = 7\nvlm = "sim:nominal"\n'
        '[bench.tasks]\nids = ["villa-o01", "corridor-p05"]\n[episode]\ntime_limit_s = 2.0\n[world]\nwidth_px = 64\nheight_px = 43\n'
    )
    js = tmp_path / "s.json"
    assert main(["bench", "--config", str(cfg), "--out", str(out), "--json", str(js), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "0 episodes run, 4 already done (resumed)" in printed and "| oracle | all | 4 |" in printed
    summary = json.loads(js.read_text())
    assert summary["methods"]["oracle"]["episodes"] == 4 and summary["error_model"] == "nominal"


@pytest.mark.slow
def test_ray_gives_the_same_records(serial_run, tmp_path):
    _, _, serial = serial_run
    res = run_bench(_config(), tmp_path, workers=2, ray_address="local")
    assert res.ran == 4
    assert _comparable(res.records) == _comparable(serial.records)


def _children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid``, from /proc."""
    out = []
    for stat in __import__("pathlib").Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    from pathlib import Path

    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_terminated_bench_stops_its_workers_and_keeps_its_episodes(tmp_path):
    """``kill`` (TERM) on ``onfly bench --workers 2`` ends the workers with it: before, the pool's
    workers flew on, orphaned, through the episodes already queued to them (two ran for 20 min
    after their parent had gone). The finished episodes stay on disk, whole."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "onfly.cli", "bench", "--config", "experiments/configs/quick.toml", "--methods", "oracle",
           "--count", "8", "--workers", "2", "--out", str(out), "--no-progress"]  # fmt: skip
    # stderr to a file: orphaned workers would hold a pipe open, and reading it would hang
    log = (tmp_path / "stderr.txt").open("w")
    proc = subprocess.Popen(cmd, cwd=repo, stdout=subprocess.DEVNULL, stderr=log, text=True)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 180.0
        episodes = out / "episodes.jsonl"
        while time.monotonic() < deadline and proc.poll() is None:
            workers = sorted(set(workers) | set(_children(proc.pid)))
            if len(workers) >= 2 and episodes.exists() and episodes.read_text().count("\n") >= 1:
                break
            time.sleep(0.1)
        assert proc.poll() is None and len(workers) >= 2, "the run ended before two workers had flown an episode"
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
        log.close()
    err = (tmp_path / "stderr.txt").read_text()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.1)
    survivors = [w for w in workers if _alive(w)]
    for w in survivors:  # leave no orphan behind, whatever the outcome
        os.kill(w, signal.SIGKILL)
    assert not survivors, "workers outlived the terminated bench"
    assert proc.returncode == 128 + signal.SIGTERM, err
    lines = episodes.read_text().splitlines()
    assert 1 <= len(lines) < 8 and all(json.loads(line)["method"] == "oracle" for line in lines)
