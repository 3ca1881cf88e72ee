"""External scenes and task files work everywhere tasks do (tasks, run, bench), with paths
resolved predictably (a task file's scene against the task file, a config's task files
against the config); ``--count`` spreads over scenes."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest

from onfly.bench.tasks import load_tasks, select_tasks, tasks_dir
from onfly.cli import main
from onfly.world.scene import scenes_dir

BENCH = """[bench]
name = "ext"
methods = ["oracle"]
runs = 1
[bench.tasks]
files = ["../tasks/mine.toml"]
[episode]
time_limit_s = 1.0
[world]
width_px = 64
height_px = 43
"""


@pytest.fixture
def external(tmp_path, monkeypatch) -> Path:
    """tmp/world/my_lot.toml (a renamed copy of parking_lot), tmp/tasks/mine.toml naming it by
    a relative path, tmp/cfg/b.toml naming the task file by a relative path; cwd elsewhere."""
    (tmp_path / "world").mkdir()
    (tmp_path / "tasks").mkdir()
    (tmp_path / "cfg").mkdir()
    (tmp_path / "elsewhere").mkdir()
    scene = (scenes_dir() / "parking_lot.toml").read_text().replace('name = "parking_lot"', 'name = "my_lot"', 1)
    (tmp_path / "world" / "my_lot.toml").write_text(scene)
    tasks = (tasks_dir() / "parking_lot.toml").read_text().replace('scene = "parking_lot"', 'scene = "../world/my_lot.toml"', 1)
    (tmp_path / "tasks" / "mine.toml").write_text(tasks.replace('id = "parking_lot-', 'id = "mine-'))
    (tmp_path / "cfg" / "b.toml").write_text(BENCH)
    monkeypatch.chdir(tmp_path / "elsewhere")
    return tmp_path


def test_task_file_names_its_scene_relative_to_itself(external):
    tasks = load_tasks([external / "tasks" / "mine.toml"])
    assert tasks[0].task_id == "mine-o01" and tasks[0].scene == "my_lot"
    assert tasks[0].scene_file == (external / "world" / "my_lot.toml").resolve()


def test_run_flies_a_task_of_an_external_file(external, capsys):
    out_json = external / "elsewhere" / "r.json"
    rc = main(["run", "--files", str(external / "tasks" / "mine.toml"), "--task", "mine-o01", "--method", "oracle",
               "--no-rrd", "--quiet", "--time-limit-s", "2", "--width", "64", "--height", "43", "--json", str(out_json)])
    assert rc == 0, capsys.readouterr().err
    r = json.loads(out_json.read_text())
    assert r["task"] == "mine-o01" and r["end_reason"] == "time_limit"
    assert r["failure_reason"].startswith("time limit reached at 2.0 s")
    assert "failed     time limit reached at 2.0 s" in capsys.readouterr().out


def test_bench_config_names_task_files_relative_to_itself(external, capsys):
    rc = main(["bench", "--config", str(external / "cfg" / "b.toml"), "--count", "1", "--no-progress", "--out", "o"])
    assert rc == 0, capsys.readouterr().err
    recs = [json.loads(line) for line in (external / "elsewhere" / "o" / "episodes.jsonl").read_text().splitlines()]
    assert [r["scene"] for r in recs] == ["my_lot"] and recs[0]["task"].startswith("mine-")
    assert recs[0]["motion"]["rms_accel_mps2"] > 0


def test_count_spreads_over_scenes():
    tasks = load_tasks()
    three = select_tasks(tasks, count=3)
    assert len({t.scene for t in three}) == 3 and Counter(t.kind for t in three) == {"object": 1, "precise": 1, "long_range": 1}
    ten = select_tasks(tasks, count=10)
    assert len({t.scene for t in ten}) == 10
    thirty = select_tasks(tasks, count=30)
    assert max(Counter(t.scene for t in thirty).values()) - min(Counter(t.scene for t in thirty).values()) <= 2


def test_run_shows_a_live_line_and_records_mesh_and_metric_plots(tmp_path, monkeypatch, capsys):
    import subprocess
    import sys

    monkeypatch.chdir(tmp_path)
    argv = ["run", "--task", "parking_lot-o01", "--method", "oracle", "--time-limit-s", "6", "--width", "64", "--height", "43"]
    assert main(argv) == 0
    out, err = capsys.readouterr()
    live = [line for line in err.splitlines() if line.startswith("t ")]
    assert live[0].startswith("t   0.0 s  goal ") and len(live) == 2  # a line every 5 s of flight (stderr is not a tty)
    rrd = tmp_path / "runs" / "parking_lot-o01-oracle-sim-nominal-s0.rrd"
    assert f"recording  runs/{rrd.name}" in out
    assert main(argv) == 0  # the same run again: a new file, the first kept
    assert f"recording  runs/parking_lot-o01-oracle-sim-nominal-s0-2.rrd" in capsys.readouterr().out
    rerun = Path(sys.executable).parent / "rerun"
    printed = subprocess.run([str(rerun), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120).stdout
    assert "world/scene" in printed  # the scene mesh
    for name in ("metrics/distance_to_goal_m", "metrics/speed_mps", "metrics/altitude_m"):
        assert name in printed


def test_writing_references_keeps_the_scene_path_of_an_external_task_file(external):
    from onfly.bench.tasks import load_task_file, write_task_file
    from onfly.commands.tasks import _scene_ref

    path = external / "tasks" / "mine.toml"
    every = load_task_file(path)
    assert _scene_ref(path) == "../world/my_lot.toml"
    write_task_file(path, every[0].scene, every, "header", scene_ref=_scene_ref(path))  # what `tasks check --write` does
    again = load_task_file(path)
    assert 'scene = "../world/my_lot.toml"' in path.read_text()
    assert [t.task_id for t in again] == [t.task_id for t in every]
    assert again[0].scene_file == every[0].scene_file and again[0].reference.path_length_m == every[0].reference.path_length_m


def test_visibility_split_reads_an_external_scene_from_its_file(external):
    from experiments.task_visibility import starts_in_view
    from planning.camera import PinholeCamera

    cam = PinholeCamera.from_fov(160, 107, 90.0, 60.0)
    mine = load_tasks([external / "tasks" / "mine.toml"])[:4]
    committed = {t.task_id: t for t in load_tasks() if t.scene == "parking_lot"}
    flags = starts_in_view(mine, cam)  # the scene is "my_lot": no committed scene of that name
    assert flags == {t.task_id: v for t, v in zip(mine, starts_in_view([committed[t.task_id.replace("mine-", "parking_lot-")] for t in mine], cam).values())}
    assert set(flags.values()) == {True, False}  # the four cover both sides, so the test can fail


def test_check_write_keeps_the_files_own_header_and_says_what_it_wrote(external, capsys):
    path = external / "tasks" / "mine.toml"
    body = path.read_text()
    body = body[body.index("format = "):]
    first = body.index("[tasks.reference]")
    body = body[:first] + body[body.index("[[tasks]]", first):]  # mine-o01 loses its reference
    path.write_text("# My lot, my tasks.\n#\n# Not the stock header.\n" + body)
    assert main(["tasks", "check", "--files", str(path), "--tasks", "mine-o01", "--no-progress"]) == 1
    assert "mine-o01               unchecked" in capsys.readouterr().out  # never checked, not stale
    rc = main(["tasks", "check", "--files", str(path), "--tasks", "mine-o01", "--write"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "mine-o01               written" in out and "1 tasks: 0 ok, 1 written (were stale or unchecked), 0 failed" in out
    text = path.read_text()
    assert text.startswith("# My lot, my tasks.\n#\n# Not the stock header.\nformat = ")
    assert load_tasks([path])[0].reference is not None
    assert main(["tasks", "check", "--files", str(path), "--tasks", "mine-o01"]) == 0
    got = capsys.readouterr()
    assert "1 tasks: 1 ok, 0 stale or unchecked, 0 failed" in got.out and "checking" in got.err  # the progress bar
    assert main(["tasks", "check", "--files", str(path), "--tasks", "mine-o01", "--no-progress"]) == 0
    assert "checking" not in capsys.readouterr().err
