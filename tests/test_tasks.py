"""Task format, committed task files, loader errors, selection and the write/read round trip."""

from __future__ import annotations

import tomllib
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from onfly.bench.tasks import (
    KINDS,
    TaskFormatError,
    load_task_file,
    load_tasks,
    object_bounds,
    select_tasks,
    tasks_dir,
    write_task_file,
)
from onfly.bench.runner import BenchConfig
from onfly.world.geometry import SceneGeometry
from onfly.world.scene import list_scenes, load_scene, resolve_scene
from vlm.sim.grounding import words


PAPER_SCENES = ["corridor", "duplex", "factory_hall", "park", "parking_lot", "plaza", "terrace", "urban_block", "villa", "warehouse"]
HARD_SCENES = ["apartment", "office_floor", "parking_garage"]
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def tasks():
    return load_tasks()


@pytest.fixture(scope="module")
def hard():
    """The harder set of issue 16 (onfly/data/tasks/hard/): its own group, not in the default."""
    return load_tasks(sorted((tasks_dir() / "hard").glob("*.toml")))


def test_committed_tasks_have_the_papers_composition(tasks):
    assert len(tasks) == 150
    kinds = Counter(t.kind for t in tasks)
    assert kinds == {"object": 60, "precise": 60, "long_range": 30}
    per_scene = Counter(t.scene for t in tasks)
    assert sorted(per_scene) == PAPER_SCENES
    assert set(per_scene.values()) == {15}
    assert len({t.task_id for t in tasks}) == 150
    assert len({t.instruction for t in tasks}) == 150


def test_committed_tasks_are_checked_and_within_flight_range(tasks):
    for t in tasks:
        assert t.reference is not None, t.task_id
        ref = t.reference
        # 0.6 m/s and 70 s: the reference must be flyable well within the limit
        assert 7.0 <= ref.path_length_m <= 30.0, t.task_id
        np.testing.assert_allclose(ref.waypoints_m[0], t.start.position_m, atol=1e-3)
        np.testing.assert_allclose(ref.waypoints_m[-1], ref.goal_point_m, atol=1e-3)
        assert t.goal_region.distance(ref.goal_point_m) <= 1.5 + 1e-6, t.task_id
        assert t.goal_region.distance(t.start.position_m) >= 7.0 - 1e-6, t.task_id
        length = float(np.sum(np.linalg.norm(np.diff(ref.waypoints_m, axis=0), axis=1)))
        assert length == pytest.approx(ref.path_length_m, abs=0.02)


def test_long_range_tasks_are_multi_step(tasks):
    for t in tasks:
        if t.kind == "long_range":
            assert len(t.subtasks) >= 2 and len(t.targets) >= 2, t.task_id
            assert t.via, t.task_id


def test_instructions_name_their_targets_so_a_grounded_vlm_can_find_them(tasks, hard):
    """Every target's name, one of its aliases or its label appears in the instruction words."""
    scenes = {name: load_scene(resolve_scene(name)) for name in list_scenes()}
    for t in [*tasks, *hard]:
        scene = scenes[t.scene]
        text = " ".join(words(t.instruction))
        for name in t.targets:
            obj = scene.object_by_name(name)
            phrases = [obj.name, *obj.aliases, obj.label]
            assert any(" ".join(words(p)) in text for p in phrases), (t.task_id, phrases)


def test_instructions_are_varied(tasks):
    first_words = Counter(t.instruction.split()[0].lower() for t in tasks)
    assert len(first_words) >= 20
    assert first_words.most_common(1)[0][1] <= 40


def test_object_goal_is_the_objects_bounds_plus_margin(tasks):
    t = next(t for t in tasks if t.task_id == "villa-l02")
    assert t.goal.object == "pool ladder" and t.goal.margin_m == pytest.approx(0.3)
    scene = load_scene(resolve_scene("villa"))
    lo, hi = SceneGeometry(scene).object_bounds(scene.object_by_name("pool ladder").instance_id)
    np.testing.assert_allclose(t.goal.center_m, (lo + hi) / 2, atol=1e-5)
    np.testing.assert_allclose(t.goal.half_extents_m, (hi - lo) / 2 + 0.3, atol=1e-5)
    lo2, hi2 = object_bounds(scene, "pool ladder")
    np.testing.assert_allclose(lo2, lo, atol=1e-6)


def test_write_then_load_round_trips(tmp_path, tasks):
    villa = [t for t in tasks if t.scene == "villa"]
    path = tmp_path / "villa.toml"
    write_task_file(path, "villa", villa, header="round trip")
    again = load_task_file(path)
    assert [t.task_id for t in again] == [t.task_id for t in villa]
    for a, b in zip(villa, again):
        assert (a.instruction, a.subtasks, a.targets, a.via, a.kind) == (b.instruction, b.subtasks, b.targets, b.via, b.kind)
        np.testing.assert_allclose(a.goal.center_m, b.goal.center_m, atol=1e-3)
        np.testing.assert_allclose(a.start.position_m, b.start.position_m, atol=1e-3)
        assert a.start.yaw_rad == pytest.approx(b.start.yaw_rad, abs=1e-4)
        np.testing.assert_allclose(a.reference.waypoints_m, b.reference.waypoints_m, atol=1e-3)


def test_select_by_ids_scene_kind_and_count(tasks):
    assert [t.task_id for t in select_tasks(tasks, ids=["park-o01", "villa-p02"])] == ["park-o01", "villa-p02"]
    assert {t.scene for t in select_tasks(tasks, scenes=["warehouse"])} == {"warehouse"}
    assert {t.kind for t in select_tasks(tasks, kinds=["precise"])} == {"precise"}
    sub = select_tasks(tasks, count=30)
    assert len(sub) == 30
    assert Counter(t.kind for t in sub) == {"object": 12, "precise": 12, "long_range": 6}
    per_scene = Counter(t.scene for t in sub)
    assert sorted(per_scene) == PAPER_SCENES and max(per_scene.values()) <= 5
    assert select_tasks(tasks, count=30) == sub  # deterministic
    with pytest.raises(ValueError, match=r"unknown task id\(s\) \['nope-1'\]"):
        select_tasks(tasks, ids=["nope-1"])
    with pytest.raises(ValueError, match="unknown task kind"):
        select_tasks(tasks, kinds=["hover"])
    with pytest.raises(ValueError, match="count must be a positive integer"):
        select_tasks(tasks, count=0)


GOOD = """
format = "onfly-tasks/1"
scene = "villa"

[[tasks]]
id = "t-1"
kind = "object"
instruction = "Fly to the patio umbrella."
subtasks = ["fly to the patio umbrella"]
targets = ["patio umbrella"]
goal = { object = "patio umbrella", margin_m = 0.0 }
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "t.toml"
    p.write_text(text)
    return p


def test_minimal_file_loads_with_the_scene_start(tmp_path):
    (t,) = load_task_file(_write(tmp_path, GOOD))
    scene = load_scene(resolve_scene("villa"))
    np.testing.assert_allclose(t.start.position_m, scene.start.position_m)
    assert t.reference is None and t.source == tmp_path / "t.toml"


@pytest.mark.parametrize(
    "old,new,match",
    [
        ('instruction = "Fly to the patio umbrella."\n', "", r"task 't-1': field 'instruction': missing required field"),
        ('kind = "object"', 'kind = "hover"', r"field 'kind': unknown kind 'hover'"),
        ('targets = ["patio umbrella"]', 'targets = ["red umbrella"]', r"field 'targets\[0\]': scene 'villa' has no object named 'red umbrella'"),
        ('targets = ["patio umbrella"]', 'targets = ["lawn"]', r"field 'targets\[0\]': object 'lawn' of scene 'villa' is not a target"),
        ('goal = { object = "patio umbrella", margin_m = 0.0 }', 'goal = { object = "fountain" }', r"field 'goal.object': goal object 'fountain' must be one of the targets"),
        ('goal = { object = "patio umbrella", margin_m = 0.0 }', 'goal = { center_m = [0, 0], half_extents_m = [1, 1, 1] }', r"field 'goal.center_m': expected a list of 3 finite numbers"),
        ('goal = { object = "patio umbrella", margin_m = 0.0 }', 'goal = { center_m = [0, 0, 1], half_extents_m = [1, -1, 1] }', r"field 'goal.half_extents_m': entries must be >= 0"),
        ('goal = { object = "patio umbrella", margin_m = 0.0 }', 'goal = { object = "patio umbrella", margin_m = -1 }', r"field 'goal.margin_m': must be >= 0"),
        ('kind = "object"', 'kind = "long_range"', r"field 'subtasks': expected at least 2 entries"),
        ('kind = "object"', 'kind = "object"\nstart = { position_m = [100, 0, 1.5] }', r"field 'start.position_m': start \[100.0, 0.0, 1.5\] lies outside the bounds"),
        ('kind = "object"', 'kind = "object"\ncolour = "red"', r"field 'colour': unknown field"),
        ('format = "onfly-tasks/1"', 'format = "onfly-tasks/9"', r"field 'format': unsupported format"),
        ('scene = "villa"', 'scene = "moon"', r"field 'scene': no scene named 'moon'"),
    ],
)
def test_malformed_files_name_file_task_and_field(tmp_path, old, new, match):
    assert old in GOOD
    path = _write(tmp_path, GOOD.replace(old, new))
    with pytest.raises(TaskFormatError, match=match) as info:
        load_task_file(path)
    assert str(path) in str(info.value)


def test_duplicate_ids_and_bad_toml(tmp_path):
    with pytest.raises(TaskFormatError, match=r"task 't-1': field 'id': duplicate id"):
        load_task_file(_write(tmp_path, GOOD + "\n" + GOOD[GOOD.index("[[tasks]]"):]))
    with pytest.raises(TaskFormatError, match="not valid TOML"):
        load_task_file(_write(tmp_path, "format = [unclosed"))
    with pytest.raises(FileNotFoundError, match="task file not found"):
        load_task_file(tmp_path / "missing.toml")


def test_duplicate_id_across_files(tmp_path):
    a = tmp_path / "a.toml"
    b = tmp_path / "b.toml"
    a.write_text(GOOD)
    b.write_text(GOOD)
    with pytest.raises(TaskFormatError, match=r"task 't-1': field 'id': duplicate id \(also in"):
        load_tasks([a, b])


def test_committed_files_live_in_the_package():
    assert len(list(tasks_dir().glob("*.toml"))) == 10
    assert sorted(p.stem for p in (tasks_dir() / "hard").glob("*.toml")) == HARD_SCENES


def _config_selection(name: str) -> list[str]:
    path = REPO / "experiments" / "configs" / name
    data = tomllib.loads(path.read_text())
    data.pop("paper_tables", None)  # read by experiments/paper_tables.py, not by the runner
    cfg = BenchConfig.from_dict(data, source=str(path))
    sel = select_tasks(load_tasks(cfg.task_files), ids=cfg.task_ids, scenes=cfg.scenes, kinds=cfg.kinds, count=cfg.count)
    return [t.task_id for t in sel]


def test_paper_configs_select_the_original_tasks_and_hard_selects_only_the_new(tasks, hard):
    """The default task set stays the paper's 150 (the hard files live in a subfolder the default
    does not read), so the paper's configs select what they selected before."""
    paper = [t.task_id for t in tasks]
    assert _config_selection("full.toml") == paper
    assert _config_selection("paper_tables.toml") == paper
    quick = _config_selection("quick.toml")
    assert quick == [t.task_id for t in select_tasks(tasks, count=30)] and len(quick) == 30
    assert _config_selection("paper_tables_quick.toml") == [
        "corridor-o01", "duplex-p01", "factory_hall-o04", "park-l01", "parking_lot-p02",
        "plaza-o01", "terrace-p01", "urban_block-o01", "villa-l01", "warehouse-p01"]  # fmt: skip
    assert _config_selection("hard.toml") == [t.task_id for t in hard]
    assert not set(paper) & {t.task_id for t in hard}


def test_hard_set_composition(hard):
    assert len(hard) >= 60
    assert len({t.task_id for t in hard}) == len(hard) and len({t.instruction for t in hard}) == len(hard)
    assert sorted({t.scene for t in hard}) == HARD_SCENES
    per_scene = Counter(t.scene for t in hard)
    assert min(per_scene.values()) >= 20
    kinds = Counter(t.kind for t in hard)
    assert set(kinds) == set(KINDS) - {"track"} and kinds["long_range"] >= 15  # tracking tasks live in tasks/track/
    for t in hard:
        assert t.task_id.startswith(t.scene + "-")
        if t.kind == "long_range":
            # multi-clause: several legs, several named objects, a route through via objects
            assert len(t.subtasks) >= 2 and len(t.targets) >= 2 and t.via, t.task_id
            assert len(t.instruction.split()) >= 15, t.task_id
    first_words = Counter(t.instruction.split()[0].lower() for t in hard)
    assert len(first_words) >= 12


def test_hard_set_has_look_alike_goals(hard):
    """Look-alikes: some goals share their label with another target of the same scene, so
    they are told apart only by an attribute or a position (e.g. two chargers, two bedside
    lamps, three whiteboards)."""
    n = 0
    scenes = {name: load_scene(resolve_scene(name)) for name in HARD_SCENES}
    for t in hard:
        scene = scenes[t.scene]
        name = t.goal.object if t.goal.object is not None else t.targets[-1]
        label = scene.object_by_name(name).label
        n += sum(o.label == label for o in scene.targets) >= 2
    assert n >= 12


def test_every_hard_task_is_proven_by_the_checker(hard):
    """Every hard task holds the checker's proof, and checking again reproduces it: a
    collision-free path at the body radius (+ the proof margin) from the start through the via
    objects to a goal point within 1.5 m of the goal, the goal visible from the path and from
    the goal point, <= 30 m."""
    from onfly.bench.checker import CheckerConfig, TaskChecker, goal_target

    cfg = CheckerConfig()
    checkers = {name: TaskChecker(load_scene(resolve_scene(name)), cfg) for name in HARD_SCENES}
    for t in hard:
        r = checkers[t.scene].check(t)
        assert r.ok, (t.task_id, r.problems)
        # and the goal point itself sees the goal (no goal reached through a wall)
        assert checkers[t.scene].visible_mask(t.reference.goal_point_m[None], goal_target(t))[0], t.task_id
        ref = t.reference
        assert ref is not None, t.task_id
        assert r.reference.path_length_m == pytest.approx(ref.path_length_m, abs=0.05), t.task_id
        assert ref.min_clearance_m >= cfg.body_radius_m + cfg.proof_margin_m - 1e-3, t.task_id
        assert ref.path_length_m <= cfg.max_path_m, t.task_id
        np.testing.assert_allclose(ref.waypoints_m[0], t.start.position_m, atol=1e-3)
        np.testing.assert_allclose(ref.waypoints_m[-1], ref.goal_point_m, atol=1e-3)
        assert t.goal_region.distance(ref.goal_point_m) <= cfg.max_goal_gap_m + 1e-6, t.task_id
        assert t.goal_region.distance(t.start.position_m) >= cfg.min_goal_distance_m - 1e-6, t.task_id


def test_cli_task_lookup_finds_the_committed_groups_beside_the_paper_set():
    from onfly.bench.tasks import committed_task_files, load_tasks
    from onfly.cli import task_by_id

    paper = load_tasks()
    assert len(paper) == 150  # the default set stays the paper's 150
    every = load_tasks(committed_task_files())
    hard = [t for t in every if t.task_id not in {p.task_id for p in paper}]
    assert len(hard) >= 60
    assert task_by_id(hard[0].task_id).task_id == hard[0].task_id
