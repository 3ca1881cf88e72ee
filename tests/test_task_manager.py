import pytest

from onfly.task_manager import Status, TaskEvent, TaskManager, TaskManagerError


def test_stable_stop_advances_then_finishes():
    tm = TaskManager(["fly through the gate", "stop next to the red van"], stop_confirmations=2)
    assert tm.on_status("CONTINUE", 0, [0, 0, 1], 0.0) is TaskEvent.NONE
    assert tm.on_status("STOP", 2, [1, 0, 1], 0.0) is TaskEvent.NONE  # not yet stable
    assert tm.current == "fly through the gate"
    assert tm.on_status("STOP", 4, [2, 0, 1], 0.0) is TaskEvent.ADVANCED
    assert tm.current == "stop next to the red van" and tm.is_last
    assert tm.on_status(Status.STOP, 6, [3, 0, 1], 0.0) is TaskEvent.NONE
    assert tm.on_status(Status.STOP, 8, [3, 0, 1], 0.0) is TaskEvent.FINISHED
    assert tm.finished
    assert tm.on_status("CONTINUE", 10, [3, 0, 1], 0.0) is TaskEvent.NONE


def test_interrupted_stops_do_not_count():
    tm = TaskManager(["a"], stop_confirmations=2)
    tm.on_status("STOP", 0, [0, 0, 0], 0)
    tm.on_status("CONTINUE", 1, [0, 0, 0], 0)
    assert tm.on_status("STOP", 2, [0, 0, 0], 0) is TaskEvent.NONE
    tm.on_status("LOST", 3, [0, 0, 0], 0)
    assert tm.on_status("STOP", 4, [0, 0, 0], 0) is TaskEvent.NONE
    assert not tm.finished


def test_lost_recovery_heading_is_last_normal_point():
    tm = TaskManager(["a"])
    assert tm.recovery_yaw(0.7) == 0.7  # nothing normal yet
    tm.on_status("CONTINUE", 0, [0, 0, 1], 1.2)
    tm.on_status("CONTINUE", 2, [1, 0, 1], 1.4)
    assert tm.on_status("LOST", 4, [2, 0, 1], -2.0) is TaskEvent.LOST
    assert tm.recovery_yaw(0.0) == pytest.approx(1.4)


def test_normal_point_belongs_to_its_subtask():
    tm = TaskManager(["a", "b"], stop_confirmations=1)
    tm.on_status("CONTINUE", 0, [0, 0, 1], 1.0)
    assert tm.on_status("STOP", 2, [1, 0, 1], 1.0) is TaskEvent.ADVANCED
    assert tm.last_normal is None
    tm.on_status("LOST", 4, [1, 0, 1], -0.5)
    assert tm.recovery_yaw(-0.5) == -0.5  # no normal point in subtask "b" yet: just stop


def test_one_recovery_per_normal_point():
    tm = TaskManager(["a", "b"], stop_confirmations=1)
    p = [0, 0, 1]
    assert tm.on_status("LOST", 0, p, 0.3) is TaskEvent.LOST  # no normal point yet: stop once
    assert tm.on_status("LOST", 2, p, 0.3) is TaskEvent.NONE
    tm.on_status("CONTINUE", 4, p, 1.0)
    assert tm.on_status("LOST", 6, p, 0.0) is TaskEvent.LOST
    # LOST again and again at the same normal point: nothing to recover to that was not tried
    assert [tm.on_status("LOST", t, p, 0.0) for t in (8, 10, 12)] == [TaskEvent.NONE] * 3
    assert tm.recovery_yaw(0.0) == pytest.approx(1.0)
    tm.on_status("CONTINUE", 14, p, 2.0)  # a new normal point re-arms recovery
    assert tm.on_status("LOST", 16, p, 0.0) is TaskEvent.LOST
    assert tm.on_status("STOP", 18, p, 0.0) is TaskEvent.ADVANCED
    assert tm.on_status("LOST", 20, p, 0.0) is TaskEvent.LOST  # a new subtask re-arms it too
    assert tm.on_status("LOST", 22, p, 0.0) is TaskEvent.NONE
    events = [e for *_, e in tm.history]
    assert events.count(TaskEvent.LOST) == 4


def test_repeated_lost_resets_pending_stops():
    tm = TaskManager(["a"], stop_confirmations=2)
    tm.on_status("LOST", 0, [0, 0, 0], 0)
    tm.on_status("STOP", 1, [0, 0, 0], 0)
    assert tm.on_status("LOST", 2, [0, 0, 0], 0) is TaskEvent.NONE
    assert tm.pending_stops == 0
    assert tm.on_status("STOP", 3, [0, 0, 0], 0) is TaskEvent.NONE and not tm.finished


def test_invalid_input():
    with pytest.raises(TaskManagerError, match="non-empty"):
        TaskManager([])
    with pytest.raises(TaskManagerError, match="non-empty"):
        TaskManager(["a", "  "])
    with pytest.raises(ValueError):
        TaskManager(["a"]).on_status("MAYBE", 0, [0, 0, 0], 0)


def test_an_intermediate_subtask_advances_on_fewer_stops_than_the_last_one_finishes():
    tm = TaskManager(["fly to the gate", "fly to the tree", "stop at the van"], stop_confirmations=2, intermediate_confirmations=1)
    assert tm.on_status("STOP", 1, [0, 0, 1], 0.0) is TaskEvent.ADVANCED  # one STOP past "the gate"
    assert tm.on_status("STOP", 2, [1, 0, 1], 0.0) is TaskEvent.ADVANCED
    assert tm.is_last
    assert tm.on_status("STOP", 3, [2, 0, 1], 0.0) is TaskEvent.NONE  # the last needs two
    assert tm.on_status("CONTINUE", 4, [2, 0, 1], 0.0) is TaskEvent.NONE
    assert tm.on_status("STOP", 5, [2, 0, 1], 0.0) is TaskEvent.NONE  # interrupted: counts from one again
    assert tm.on_status("STOP", 6, [2, 0, 1], 0.0) is TaskEvent.FINISHED
    # the default: every subtask needs stop_confirmations
    same = TaskManager(["a", "b"], stop_confirmations=2)
    assert same.on_status("STOP", 1, [0, 0, 1], 0.0) is TaskEvent.NONE
    assert same.on_status("STOP", 2, [0, 0, 1], 0.0) is TaskEvent.ADVANCED
    with pytest.raises(TaskManagerError):
        TaskManager(["a"], intermediate_confirmations=0)


def test_with_next_reads_the_next_subtasks_as_later_steps_until_the_last():
    tm = TaskManager(["Fly along the aisle between the desks.", "Stop beside the whiteboard", "land"], stop_confirmations=1)
    assert tm.with_next(0) == "Fly along the aisle between the desks."
    assert tm.with_next(1) == "Fly along the aisle between the desks, then stop beside the whiteboard"
    assert tm.with_next(5) == "Fly along the aisle between the desks, then stop beside the whiteboard, then land"
    tm.on_status("STOP", 0, [0, 0, 1], 0.0)
    assert tm.with_next(1) == "Stop beside the whiteboard, then land"
    tm.on_status("STOP", 1, [0, 0, 1], 0.0)
    assert tm.is_last and tm.with_next(1) == "land"
    with pytest.raises(TaskManagerError):
        tm.with_next(-1)


def test_the_joined_text_splits_back_into_the_same_legs():
    from vlm.decompose import split_instruction

    tm = TaskManager(["Leave the living room through the doorway by the dining table", "stop in front of the storage cabinet"])
    assert split_instruction(tm.with_next(1)) == tm.subtasks


def test_a_stop_on_the_joined_text_advances_and_counts_toward_the_last_subtask():
    tm = TaskManager(["a", "b"], stop_confirmations=2, intermediate_confirmations=1)
    assert tm.on_status("STOP", 0, [0, 0, 1], 0.0, joined=True) is TaskEvent.ADVANCED
    assert tm.is_last and tm.pending_stops == 1
    assert tm.on_status("STOP", 1, [0, 0, 1], 0.0) is TaskEvent.FINISHED
    # not joined (the paper's prompts): the last subtask needs both of its own STOPs
    tm = TaskManager(["a", "b"], stop_confirmations=2, intermediate_confirmations=1)
    assert tm.on_status("STOP", 0, [0, 0, 1], 0.0) is TaskEvent.ADVANCED
    assert tm.pending_stops == 0
    assert tm.on_status("STOP", 1, [0, 0, 1], 0.0) is TaskEvent.NONE
    # a CONTINUE between them resets the carried STOP
    tm = TaskManager(["a", "b", "c"], stop_confirmations=2, intermediate_confirmations=1)
    assert tm.on_status("STOP", 0, [0, 0, 1], 0.0, joined=True) is TaskEvent.ADVANCED
    assert tm.pending_stops == 0  # "b" is not the last: its own STOP advances it
    assert tm.on_status("STOP", 1, [0, 0, 1], 0.0, joined=True) is TaskEvent.ADVANCED
    assert tm.pending_stops == 1
    tm.on_status("CONTINUE", 2, [0, 0, 1], 0.0)
    assert tm.on_status("STOP", 3, [0, 0, 1], 0.0) is TaskEvent.NONE and not tm.finished


def test_with_one_confirmation_a_joined_stop_finishes_the_last_subtask_at_once():
    tm = TaskManager(["a", "b"], stop_confirmations=1)
    assert tm.on_status("STOP", 0, [0, 0, 1], 0.0, joined=True) is TaskEvent.FINISHED
    assert tm.finished and tm.pending_stops == 0


def test_same_subtask_ignores_case_spacing_and_closing_punctuation_only():
    from onfly.task_manager import same_subtask

    # a decomposition returns "Fly to the yellow car" for "Fly to the yellow car."
    assert same_subtask("Fly to the yellow car.", "Fly to the yellow car")
    assert same_subtask("  fly to the  Yellow car!", "Fly to the yellow car")
    assert same_subtask(None, None)
    # any other difference is another subtask
    assert not same_subtask("Fly to the yellow car", "Fly to the yellow cart")
    assert not same_subtask("Fly to the car, then stop", "Fly to the car")
    assert not same_subtask("Fly to the yellow car", None)
