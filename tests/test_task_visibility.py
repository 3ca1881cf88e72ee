"""experiments/task_visibility.py: start-in-view flags against the geometry, and the split."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from experiments.task_visibility import main, reference_times, split_by_length, split_by_view, starts_in_view
from onfly.bench.tasks import load_tasks
from planning.camera import PinholeCamera

CAM = PinholeCamera.from_fov(160, 107, 90.0, 60.0)
REPO = Path(__file__).resolve().parent.parent


def test_flags_follow_the_bearing_to_the_goal():
    tasks = {t.task_id: t for t in load_tasks()}
    # warehouse-o01: the forklift is ~80 deg to the right of the start heading, outside the
    # 45 deg half field of view; urban_block-o02: the hydrant is about 40 deg left of it
    for tid, expect in (("warehouse-o01", False), ("urban_block-o02", True)):
        t = tasks[tid]
        c = t.goal_region.center - t.start.position_m
        bearing = np.degrees(np.arctan2(c[1], c[0]) - t.start.yaw_rad)
        assert (abs((bearing + 180) % 360 - 180) < 45) == expect
        assert starts_in_view([t], CAM) == {tid: expect}


def rec(key, method, task, success, collided=False, failure="", flight_s=30.0):
    return {"key": key, "method": method, "task": task, "error_model": "nominal", "failure": failure,
            "metrics": {"success": success, "collided": collided, "flight_time_s": flight_s}}  # fmt: skip


def test_split_counts_the_latest_record_of_each_episode_per_side():
    flags = {"a": True, "b": False}
    records = [
        rec("1", "m", "a", False, failure="time_limit"),
        rec("1", "m", "a", True),  # a rerun of episode 1: the latest counts
        rec("2", "m", "b", False, True, "collision"),
        rec("3", "m", "b", True),
        rec("4", "m", "zzz", True),  # a task not in the flags: skipped
        {"key": "5", "method": "m"},  # a torn record without metrics: skipped
    ]
    (row,) = split_by_view(records, flags)
    assert row["episodes"] == 3 and row["sr_pct"] == 200 / 3 and row["cr_pct"] == 100 / 3
    assert (row["sr_in_view_pct"], row["in_view_episodes"]) == (100.0, 1)
    assert (row["sr_out_of_view_pct"], row["out_of_view_episodes"]) == (50.0, 2)
    assert row["out_of_view_failures"] == {"collision": 1}


def test_hard_config_selects_the_hard_set_and_most_start_out_of_view():
    """experiments/configs/hard.toml: the 69 tasks of onfly/data/tasks/hard/, and at least half
    of them (measured as the script measures it, at the config's camera) start with the goal
    out of view; some start in view, so the split has two sides."""
    from experiments.task_visibility import config_tasks
    from onfly.bench.runner import BenchConfig
    from onfly.bench.tasks import tasks_dir

    bench = BenchConfig.from_toml(REPO / "experiments" / "configs" / "hard.toml")
    tasks = config_tasks(bench)
    hard_ids = [t.task_id for t in load_tasks(sorted((tasks_dir() / "hard").glob("*.toml")))]
    assert [t.task_id for t in tasks] == hard_ids and len(tasks) >= 60
    w = bench.world_settings()
    cam = PinholeCamera.from_fov(int(w["width_px"]), int(w["height_px"]), float(w["hfov_deg"]), float(w["vfov_deg"]))
    flags = starts_in_view(tasks, cam)
    out_of_view = sum(not v for v in flags.values())
    assert out_of_view >= len(tasks) / 2
    assert out_of_view < len(tasks)
    # a task built to start in view (the fridge straight ahead through the kitchen doorway) and
    # one built to start out of view (the bathtub two rooms away)
    assert flags["apartment-o01"] and not flags["apartment-o02"]


def test_reference_times_average_the_successes_of_one_method():
    ref = reference_times(
        [
            rec("o/a/0", "oracle", "a", True, flight_s=20.0),
            rec("o/a/1", "oracle", "a", True, flight_s=30.0),
            rec("o/b/0", "oracle", "b", False, flight_s=70.0),  # a failed reference: no time
            rec("o/c/0", "oracle", "c", True, flight_s=99.0),
            rec("o/c/0", "oracle", "c", True, flight_s=40.0),  # the latest record counts
        ]
    )
    assert ref == {"a": 25.0, "c": 40.0}
    with pytest.raises(ValueError, match="one method"):
        reference_times([rec("1", "oracle", "a", True), rec("2", "onfly", "a", True)])


def test_split_by_length_bins_each_side_by_the_reference_time():
    flags = {"short_in": True, "short_out": False, "edge_out": False, "long_out": False, "unref": False}
    ref = {"short_in": 12.0, "short_out": 29.0, "edge_out": 30.0, "long_out": 50.0}
    records = [
        rec("1", "m", "short_in", True),
        rec("2", "m", "short_out", True),
        rec("3", "m", "short_out", False),
        rec("4", "m", "edge_out", True),  # 30 s is in the bin that ends at 30
        rec("5", "m", "long_out", False),
        rec("6", "m", "unref", True),  # no reference time: left out
    ]
    rows = split_by_length(records, flags, ref, [30.0])
    assert [r["reference_s"] for r in rows] == ["0-30", "> 30"]
    short, long = rows
    assert (short["sr_in_view_pct"], short["in_view_episodes"]) == (100.0, 1)
    assert (short["sr_out_of_view_pct"], short["out_of_view_episodes"]) == (200 / 3, 3)
    assert (long["sr_in_view_pct"], long["in_view_episodes"]) == (None, 0)
    assert (long["sr_out_of_view_pct"], long["out_of_view_episodes"]) == (0.0, 1)
    for bad in ([30.0, 20.0], [0.0], [float("nan")]):
        with pytest.raises(ValueError, match="edges"):
            split_by_length(records, flags, ref, bad)


def test_reference_without_runs_or_with_bad_edges_exits_2():
    cfg = str(REPO / "experiments" / "configs" / "hard.toml")
    for argv in (["--config", cfg, "--reference", "x"], ["--config", cfg, "--runs", "x", "--edges", "a,b"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2


def test_main_splits_a_run_by_its_reference_and_refuses_an_empty_one(tmp_path, capsys):
    """The CLI path: a run and an oracle run as folders of episodes.jsonl, the hard set's
    camera; one in-view task (apartment-o01) and one out of view (apartment-o02)."""
    import json

    cfg = str(REPO / "experiments" / "configs" / "hard.toml")

    def write(folder, recs):
        folder.mkdir()
        (folder / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))

    write(tmp_path / "run", [rec("a", "onfly", "apartment-o01", True), rec("b", "onfly", "apartment-o02", False)])
    write(tmp_path / "oracle", [rec("c", "oracle", "apartment-o01", True, flight_s=12.0),
                                rec("d", "oracle", "apartment-o02", True, flight_s=40.0)])  # fmt: skip
    out = tmp_path / "split.json"
    argv = ["--config", cfg, "--runs", str(tmp_path / "run"), "--reference", str(tmp_path / "oracle"), "--json", str(out)]
    assert main(argv) == 0
    data = json.loads(out.read_text())
    assert data["reference_s"] == {"apartment-o01": 12.0, "apartment-o02": 40.0}
    short, long = data["length_rows"]
    assert (short["reference_s"], short["sr_in_view_pct"], short["out_of_view_episodes"]) == ("0-30", 100.0, 0)
    assert (long["reference_s"], long["sr_out_of_view_pct"], long["in_view_episodes"]) == ("> 36", 0.0, 0)
    write(tmp_path / "empty", [rec("e", "oracle", "apartment-o01", False)])
    argv[5] = str(tmp_path / "empty")
    assert main(argv[:6]) == 2
    assert "no successful episode" in capsys.readouterr().err
