"""Tracking tasks: the task format's kind "track", the committed set, the checker's proof and
the oracle that follows the true position."""

from pathlib import Path

import numpy as np
import pytest

from onfly.bench.checker import TaskChecker
from onfly.bench.tasks import TaskFormatError, TrackSpec, load_task_file, load_tasks, tasks_dir, write_task_file
from onfly.world.scene import load_scene, resolve_scene

TRACK_FILES = sorted((tasks_dir() / "track").glob("*.toml"))

GOOD = """format = "onfly-tasks/1"
scene = "plaza"

[[tasks]]
id = "x-t01"
kind = "track"
instruction = "Follow the woman in the yellow coat."
subtasks = ["follow the woman in the yellow coat"]
targets = ["woman in the yellow coat"]
start = { position_m = [-3.0, -2.5, 1.5], yaw_deg = 0.0 }
track = { actor = "woman in the yellow coat", band_m = [1.5, 4.0], in_band_frac = 0.8, duration_s = 30.0 %s }
"""


def _write(tmp_path, text) -> Path:
    p = tmp_path / "t.toml"
    p.write_text(text)
    return p


def test_a_track_task_reads_and_writes_back(tmp_path):
    (t,) = load_task_file(_write(tmp_path, GOOD % ", stop_radius_m = 3.0"))
    assert t.kind == "track"
    assert t.track == TrackSpec("woman in the yellow coat", (1.5, 4.0), 0.8, 30.0, 3.0, 3.0)
    # the goal is the actor's bounds where it is at the end of the duration, grown by 0.5 m
    scene = load_scene(resolve_scene("plaza"))
    from onfly.world.actors import pose_at

    end = pose_at(scene.object_by_name("woman in the yellow coat").motion, 30.0).position_m
    assert np.hypot(*(t.goal.center_m[:2] - end[:2])) < 1e-6
    out = tmp_path / "w.toml"
    write_task_file(out, "plaza", [t])
    (back,) = load_task_file(out)
    assert back.track == t.track and np.allclose(back.start.position_m, t.start.position_m)


@pytest.mark.parametrize(
    "extra, field, match",
    [
        ("band", "band_m", "0 < lo < hi"),
        (', stop_radius_m = -1.0', "stop_radius_m", ">= 0"),
        (', speed = 3', "track.speed", "unknown field"),
    ],
)
def test_bad_track_tables_name_the_field(tmp_path, extra, field, match):
    if extra == "band":
        text = (GOOD % "").replace("band_m = [1.5, 4.0]", "band_m = [4.0, 1.5]")
    else:
        text = (GOOD % "").replace("duration_s = 30.0 ", f"duration_s = 30.0{extra} ")
    with pytest.raises(TaskFormatError, match=match) as e:
        load_task_file(_write(tmp_path, text))
    assert field in str(e.value)


def test_a_static_object_cannot_be_followed_and_a_track_task_has_no_goal_table(tmp_path):
    text = (GOOD % "").replace('actor = "woman in the yellow coat"', 'actor = "fountain"').replace(
        'targets = ["woman in the yellow coat"]', 'targets = ["fountain"]')
    with pytest.raises(TaskFormatError, match="does not move"):
        load_task_file(_write(tmp_path, text))
    text = (GOOD % "") + 'goal = { object = "fountain" }\n'
    with pytest.raises(TaskFormatError, match="no goal table"):
        load_task_file(_write(tmp_path, text))
    text = (GOOD % "").replace('kind = "track"', 'kind = "object"')
    with pytest.raises(TaskFormatError, match="only tasks of kind 'track'"):
        load_task_file(_write(tmp_path, text))


def test_the_committed_tracking_set_has_twenty_checked_tasks_over_two_scenes():
    tasks = load_tasks(TRACK_FILES)
    assert len(tasks) >= 20
    assert {t.scene for t in tasks} >= {"plaza", "duplex"}
    assert all(t.kind == "track" and t.reference is not None for t in tasks)
    assert sum(t.track.stop_radius_m is not None for t in tasks) >= 4
    # the default (paper) set does not read them
    assert not any(t.kind == "track" for t in load_tasks())


def test_the_checker_proves_a_committed_task_and_refuses_a_start_out_of_band():
    tasks = {t.task_id: t for t in load_tasks(TRACK_FILES)}
    t = tasks["plaza-t07"]
    checker = TaskChecker(load_scene(resolve_scene("plaza")))
    res = checker.check(t)
    assert res.ok, res.problems
    assert res.stats["follower_in_band"] >= t.track.in_band_frac
    assert abs(res.reference.path_length_m - t.reference.path_length_m) < 0.05
    from dataclasses import replace

    from onfly.bench.tasks import StartPose

    far = replace(t, start=StartPose(t.start.position_m + np.array([-6.0, 0.0, 0.0]), t.start.yaw_rad))
    bad = checker.check(far)
    assert not bad.ok and any("outside the band" in p for p in bad.problems)


@pytest.mark.slow
@pytest.mark.parametrize("task_id", ["plaza-t01", "plaza-t07"])
def test_the_oracle_follows_the_true_position_in_band(task_id):
    from onfly.bench.runner import fly_task

    t = {t.task_id: t for t in load_tasks(TRACK_FILES)}[task_id]
    result, extras = fly_task(t, "oracle", world={"width_px": 320, "height_px": 214})
    tr = extras["track"]
    assert result.collision is None and tr["in_band_frac"] >= 0.95 and tr["success"]
    assert extras["min_clearance_m"] > 0.25  # from the scene and every person, the followed one included
    if t.track.stop_radius_m is not None:
        assert result.end_reason == "stopped" and tr["stop_ok"]
    else:
        assert result.end_reason == "time_limit" and result.sim_s == pytest.approx(t.track.duration_s, abs=0.2)
