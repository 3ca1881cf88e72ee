"""Following instructions: the language rule (vlm.following), the simulated VLM's completion
rule for a following subtask, and the pilot's Follower (onfly.follow)."""

import math

import numpy as np
import pytest

from onfly.follow import FollowConfig, FollowConfigError, Follower
from vlm.decompose import decompose_detailed
from vlm.following import follow_intent
from vlm.prompts import build_monitor_prompt
from vlm.sim.backend import SimulatedVlm
from vlm.types import FrameAnnotation, VisibleObject, VlmImage

W, H = 320, 214


@pytest.mark.parametrize(
    "text, until_stop",
    [
        ("Follow the person in the red jacket around the fountain.", False),
        ("Keep up with the woman in the yellow coat as she walks around the fountain.", False),
        ("Stay behind the man with the wheelbarrow until he stops, then stop next to him.", True),
        ("Follow the woman with the stroller until she comes to a stop, then stop beside her.", True),
        ("track the jogger", False),
        ("Tail the man in the green hoodie around the statue.", False),
    ],
)
def test_following_instructions_are_recognised(text, until_stop):
    intent = follow_intent(text)
    assert intent is not None and intent.until_stop is until_stop


@pytest.mark.parametrize(
    "text",
    [
        "Follow the path up to the stone fountain.",
        "Go past the yellow robot, follow the assembly line to its end and stop at the green forklift.",
        "Fly to the person in the red jacket and stop next to them.",
        "Climb to the second floor by following the outside stairs.",
    ],
)
def test_route_following_and_plain_navigation_are_not_following(text):
    assert follow_intent(text) is None


def test_a_stop_next_to_him_leg_is_joined_to_the_following_subtask():
    from vlm.sim.backend import SimulatedVlm as Sim

    dec = decompose_detailed("Stay behind the man with the wheelbarrow until he stops, then stop next to him.", Sim("perfect", 0))
    assert len(dec.subtasks) == 1 and "stop next to him" in dec.subtasks[0]


# -- the simulated VLM's completion rule ------------------------------------------------------------


def _frame(fid: str, depth_m: float, moving: bool) -> VlmImage:
    ids = np.zeros((H, W), np.int32)
    depth = np.full((H, W), 30.0, np.float32)
    ids[60:160, 140:180] = 7
    depth[60:160, 140:180] = depth_m
    obj = VisibleObject(7, "man with the wheelbarrow", "person", (), True, moving)
    return VlmImage(np.zeros((H, W, 3), np.uint8), fid, FrameAnnotation(ids, depth, {7: obj}))


def _monitor(sim, subtask, frames):
    text = sim.complete(*build_monitor_prompt(subtask, frames[0], frames[1:-1], frames[-1]), json_schema={"type": "object"}).text
    return text


UNTIL = "Stay behind the man with the wheelbarrow until he stops, stop next to him"
ENDLESS = "Follow the man with the wheelbarrow"


def test_until_stop_is_complete_only_after_the_person_walked_and_stands_near():
    sim = SimulatedVlm("perfect", 0)
    walked = [_frame("a", 2.0, True), _frame("b", 2.0, True), _frame("c", 2.0, False)]
    assert '"STOP"' in _monitor(sim, UNTIL, walked)
    # standing from the start (not set off yet): not complete
    standing = [_frame("d", 2.0, False), _frame("e", 2.0, False), _frame("f", 2.0, False)]
    assert '"CONTINUE"' in _monitor(sim, UNTIL, standing)
    # still walking: not complete
    walking = [_frame("g", 2.0, True), _frame("h", 2.0, True), _frame("i", 2.0, True)]
    assert '"CONTINUE"' in _monitor(sim, UNTIL, walking)
    # stopped but far: not complete (the ordinary stop distance)
    far = [_frame("j", 9.0, True), _frame("k", 9.0, True), _frame("l", 9.0, False)]
    assert '"CONTINUE"' in _monitor(sim, UNTIL, far)


def test_following_without_an_end_is_never_complete():
    sim = SimulatedVlm("perfect", 0)
    walked = [_frame("a", 2.0, True), _frame("b", 2.0, True), _frame("c", 2.0, False)]
    assert '"CONTINUE"' in _monitor(sim, ENDLESS, walked)
    # the same frames under a plain approach subtask: STOP, as for any target
    assert '"STOP"' in _monitor(sim, "Fly to the man with the wheelbarrow", walked)


def test_a_one_image_baseline_prompt_never_sees_the_person_stop():
    sim = SimulatedVlm("perfect", 0)
    img = _frame("z", 2.0, False)
    assert not sim.leg_target(UNTIL, img, 0.0).reached
    assert sim.leg_target("Fly to the man with the wheelbarrow", img, 0.0).reached


# -- the follower ------------------------------------------------------------------------------------


def test_sightings_give_the_constant_velocity_prediction_exactly():
    f = Follower(FollowConfig(window_s=6.0))
    assert f.intent("Follow the man in the green hoodie") is not None
    f.sighting(0.0, [0.0, 0.0, 1.0])
    f.sighting(2.0, [1.0, 0.0, 1.0])
    f.sighting(4.0, [2.0, 0.0, 1.0])
    np.testing.assert_allclose(f.velocity(), [0.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(f.predict(6.0), [3.0, 0.0, 1.0], atol=1e-12)
    # extrapolation is capped
    np.testing.assert_allclose(f.predict(100.0), [2.0 + 0.5 * f.config.max_extrapolation_s, 0.0, 1.0], atol=1e-12)


def test_the_standoff_goal_sits_on_the_line_to_the_vehicle_and_faces_the_person():
    f = Follower(FollowConfig(standoff_m=2.5, lead_s=0.0))
    f.intent("Follow the man in the green hoodie")
    f.sighting(0.0, [10.0, 0.0, 1.0])
    goal, yaw = f.control(0.0, np.array([4.0, 0.0, 1.5]), 1.5)
    np.testing.assert_allclose(goal, [7.5, 0.0, 1.5], atol=1e-12)
    assert yaw == pytest.approx(0.0)
    # vehicle too close, north of the person: the goal backs away north, still facing them
    goal, yaw = f.control(0.0, np.array([10.0, 1.0, 1.5]), 1.5)
    np.testing.assert_allclose(goal, [10.0, 2.5, 1.5], atol=1e-12)
    assert yaw == pytest.approx(-math.pi / 2)


def test_outliers_are_dropped_and_two_agreeing_ones_restart_the_track():
    f = Follower(FollowConfig(max_speed_change_mps=1.0, jump_slack_m=1.0))
    f.intent("Follow the man in the green hoodie")
    assert f.sighting(0.0, [0.0, 0.0, 1.0])
    assert f.sighting(1.0, [0.5, 0.0, 1.0])
    assert not f.sighting(2.0, [20.0, 0.0, 1.0])  # a look-alike 20 m away
    assert not f.sighting(3.0, [-15.0, 5.0, 1.0])  # another, not agreeing with the first: dropped
    assert f.sighting(4.0, [2.0, 0.0, 1.0])  # back on track
    assert not f.sighting(5.0, [12.0, 0.0, 1.0])
    assert f.sighting(6.0, [12.5, 0.0, 1.0])  # agrees with the previous outlier: the person is there
    np.testing.assert_allclose(f.predict(6.0), [12.5, 0.0, 1.0])
    assert f.sightings_dropped == 4


def test_a_stop_is_ignored_only_on_an_endless_following_subtask():
    f = Follower()
    assert f.ignores_stop("Follow the woman in the purple dress")
    assert not f.ignores_stop("Follow the woman with the stroller until she stops, stop next to her")
    assert not f.ignores_stop("Fly to the kiosk")
    assert not Follower(FollowConfig(enabled=False)).ignores_stop("Follow the woman in the purple dress")


def test_a_subtask_that_does_not_follow_forgets_the_sightings():
    f = Follower()
    f.intent("Follow the man in the green hoodie")
    f.sighting(0.0, [1.0, 2.0, 1.0])
    assert f.active
    f.intent("Fly to the kiosk")
    assert not f.active and f.control(1.0, np.zeros(3), 1.5) is None


def test_bad_follow_config_names_the_field():
    with pytest.raises(FollowConfigError, match="standoff_m"):
        FollowConfig(standoff_m=0.0)
    with pytest.raises(FollowConfigError, match="enabled"):
        FollowConfig(enabled="yes")
