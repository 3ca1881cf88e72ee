"""Simulated VLM: sees only the frame, points on the named target, errs at its documented rates."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass

import numpy as np
import pytest

from vlm.parsing import MonitorStatus, parse_point, parse_status, parse_subtasks
from vlm.prompts import (
    build_decision_prompt,
    build_decompose_prompt,
    build_monitor_prompt,
    decision_schema,
    status_schema,
)
from vlm.sim import PRESETS, ErrorModel, ErrorModelError, LatencyModel, SimulatedVlm, get_preset
from vlm.sim.grounding import entrance_places, exploration_point, ground, names_target, place_entrance, words
from vlm.types import CallStatus, ChatMessage, FrameAnnotation, VisibleObject, VlmBackend, VlmImage

W, H = 160, 120


@dataclass(frozen=True)
class Obj:
    iid: int
    name: str
    label: str
    depth_m: float
    rect: tuple[int, int, int, int] | None = None  # u0, v0, u1, v1 (exclusive)
    disc: tuple[float, float, float] | None = None  # cu, cv, radius
    aliases: tuple[str, ...] = ()
    target: bool = True


def frame(frame_id: str, objs=(), size=(W, H), bg_depth=30.0, open_cols: tuple[int, int] | None = None, rgb_value=0) -> VlmImage:
    """An annotated frame: background at ``bg_depth``, objects painted in order (later on top).

    ``open_cols`` marks a column range with no depth reading (open sky / far street).
    """
    w, h = size
    ids = np.zeros((h, w), np.int32)
    depth = np.full((h, w), bg_depth, np.float32)
    if open_cols is not None:
        depth[:, open_cols[0] : open_cols[1]] = np.inf
    vv, uu = np.mgrid[0:h, 0:w]
    for o in objs:
        if o.rect is not None:
            m = (uu >= o.rect[0]) & (uu < o.rect[2]) & (vv >= o.rect[1]) & (vv < o.rect[3])
        else:
            m = (uu - o.disc[0]) ** 2 + (vv - o.disc[1]) ** 2 <= o.disc[2] ** 2
        ids[m] = o.iid
        depth[m] = o.depth_m
    present = set(np.unique(ids).tolist())
    objects = {o.iid: VisibleObject(o.iid, o.name, o.label, o.aliases, o.target) for o in objs if o.iid in present}
    ann = FrameAnnotation(ids, depth, objects)
    return VlmImage(np.full((h, w, 3), rgb_value, np.uint8), frame_id, ann)


def renamed(img: VlmImage, frame_id: str) -> VlmImage:
    """The same picture as a new camera frame (fresh randomness, no repainting)."""
    return VlmImage(img.rgb, frame_id, img.annotation)


def decide(sim, subtask, img, history=None, **kw):
    return sim.complete(*build_decision_prompt(subtask, img, history), **kw)


def monitor(sim, subtask, frames, **kw):
    return sim.complete(*build_monitor_prompt(subtask, frames[0], frames[1:-1], frames[-1]), **kw)


def binomial_ok(k: int, n: int, p: float, z: float = 4.5) -> bool:
    """k successes in n trials are consistent with rate p (normal bound, z sigmas)."""
    return abs(k / n - p) <= z * math.sqrt(max(p * (1 - p), 1e-12) / n) + 1e-12


VAN = Obj(7, "red van", "van", 6.0, rect=(100, 50, 140, 90), aliases=("delivery van",))
BLUE_VAN = Obj(8, "blue van", "van", 6.0, rect=(20, 50, 60, 90))
TREE = Obj(9, "oak tree", "tree", 12.0, disc=(80, 40, 15))


# ---------------------------------------------------------------------------------------------
# protocol, presets, configuration


def test_is_a_backend_and_a_context_manager():
    with SimulatedVlm("nominal", seed=3) as sim:
        assert isinstance(sim, VlmBackend)
        assert sim.name == "sim:nominal"


def test_presets_exist_and_are_pinned():
    assert {"perfect", "nominal", "noisy", "weak", "strong"} <= set(PRESETS)
    # Presets are fixed before methods are compared: changing one must be a visible decision.
    digest = hashlib.sha256(
        json.dumps({k: dataclasses.asdict(v) for k, v in sorted(PRESETS.items())}, sort_keys=True).encode()
    ).hexdigest()
    assert digest == PINNED_PRESETS_SHA256
    assert all(isinstance(p, ErrorModel) and get_preset(name) is p and p.name == name for name, p in PRESETS.items())
    perfect = PRESETS["perfect"]
    assert perfect.confusion_prob == perfect.malformed_prob == perfect.pixel_noise_frac == 0.0
    assert PRESETS["weak"].confusion_prob > PRESETS["nominal"].confusion_prob > PRESETS["strong"].confusion_prob


PINNED_PRESETS_SHA256 = "fe73aa6d118c101a1be0127ad3a7cc23135ec55a96dfbf7f58b5c4febf94fb96"


def test_bad_configuration_errors_name_the_field():
    with pytest.raises(ErrorModelError, match="unknown simulated-VLM preset 'great'.*nominal"):
        SimulatedVlm("great")
    with pytest.raises(ErrorModelError, match="confusion_prob must be in"):
        dataclasses.replace(PRESETS["nominal"], confusion_prob=1.5)
    with pytest.raises(ErrorModelError, match="stop_distance_m must be > 0"):
        dataclasses.replace(PRESETS["nominal"], stop_distance_m=0.0)
    with pytest.raises(ErrorModelError, match="lost_window_frames"):
        dataclasses.replace(PRESETS["nominal"], lost_window_frames=0)
    with pytest.raises(ErrorModelError, match="pixel_noise_frac must be a finite"):
        dataclasses.replace(PRESETS["nominal"], pixel_noise_frac=float("nan"))
    with pytest.raises(ErrorModelError, match="monitor_reused_s"):
        LatencyModel(monitor_reused_s=3.0)
    with pytest.raises(ErrorModelError, match="seed must be an int"):
        SimulatedVlm("nominal", seed=1.5)  # type: ignore[arg-type]


def test_unrecognised_prompts_and_bad_images_are_error_responses():
    sim = SimulatedVlm("perfect")
    r = sim.complete([ChatMessage("user", "Where is the van? <image>")], [frame("a", [VAN])])
    assert r.status is CallStatus.ERROR and "unrecognised prompt" in r.error
    plain = VlmImage(np.zeros((H, W, 3), np.uint8), "raw")
    r = decide(sim, "fly to the red van", plain)
    assert r.status is CallStatus.ERROR and "no FrameAnnotation" in r.error
    img = frame("b", [VAN])
    bad = VlmImage(np.zeros((H + 1, W, 3), np.uint8), "b", img.annotation)
    r = decide(sim, "fly to the red van", bad)
    assert r.status is CallStatus.ERROR and "differ from rgb" in r.error
    messages, images = build_decision_prompt("fly to the red van", img)
    r = sim.complete(messages, images + images)
    assert r.status is CallStatus.ERROR and "placeholders" in r.error


# ---------------------------------------------------------------------------------------------
# grounding


def test_grounding_rule():
    areas = {7: 1600, 8: 1600, 9: 700}
    objs = {7: VisibleObject(7, "red van", "van", ("delivery van",)), 8: VisibleObject(8, "blue van", "van"), 9: VisibleObject(9, "oak tree", "tree")}
    best = lambda s: [m.instance_id for m in ground(s, objs, areas)]  # noqa: E731
    assert best("stop next to the red van") == [7]
    assert best("stop next to the blue van") == [8]
    assert best("approach the Delivery Van")[0] == 7  # "delivery" is no attribute word: the blue van also matches, later
    assert best("fly to the green van") == []  # an attribute the objects lack
    assert best("fly to the vans")[:2] == [7, 8]  # label match, tie -> area, then id
    assert best("fly to the tree next to the red van") == [9, 7]  # earliest mention first
    assert best("land on the roof") == []
    assert best("fly to the red van") == best("fly to the red van") and words("Benches, trees") == ["bench", "tree"]
    assert ground("the red van", objs, {7: 0, 8: 5}) == []  # annotated but no pixel: not visible


def test_grounding_on_the_head_of_the_noun_phrase():
    """A name counts only as the head of its noun phrase: "wall clock" is a clock, never a
    wall; "fuel pump" a pump, never the fuel tank; participles, numbers, adverbs and
    punctuation end a phrase."""
    objs = {
        1: VisibleObject(1, "wall", "wall"),
        2: VisibleObject(2, "wall clock", "clock"),
        3: VisibleObject(3, "fuel tank", "fuel"),
        4: VisibleObject(4, "fuel pump", "pump"),
        5: VisibleObject(5, "red sedan", "car"),
        6: VisibleObject(6, "door 103", "door"),
        7: VisibleObject(7, "fire exit", "exit"),
    }
    every = {k: 100 for k in objs}
    best = lambda s, areas=every: [m.instance_id for m in ground(s, objs, areas)]  # noqa: E731
    assert best("hover next to the wall clock") == [2]
    assert best("hover next to the wall clock", {1: 100}) == []  # the clock unseen: never the wall
    assert best("stop in front of the fuel pump", {1: 100, 3: 100}) == []
    assert best("stop in front of the fuel pump") == [4]
    assert best("fly along the wall, then stop") == [1]  # "wall" heads its phrase here
    assert best("fly to the wall.") == [1]
    assert best("head to the red sedan parked on the right") == [5]  # a participle ends the phrase
    assert best("go to the red sedan quickly") == [5]
    assert best("stop in front of door 103") == [6]
    assert best("go to the door 103 and wait") == [6]
    assert best("go to the fire exit door", {7: 100}) == []  # "fire exit" modifies "door"
    assert best("go to the fire exit") == [7]
    assert best("hover above the red sedan's roof") == [5]  # possessive: the sedan
    # a landmark flown past ranks after every other mention, whatever the order
    assert best("fly past the red sedan to door 103") == [6, 5]
    assert best("head down the lane past the red sedan until you see the fire exit") == [7, 5]
    assert best("fly to the red sedan past door 103") == [5, 6]


def test_a_name_ending_in_an_identifier_is_one_of_its_kind():
    """"checkout 2" is a checkout: "the checkouts" names both counters (their label, "checkout
    counter", never occurs), "the tills" both by their aliases; "checkout 1" and "rack B" name
    no other one of the kind; a kind word before another word is a modifier as ever."""
    objs = {
        1: VisibleObject(1, "checkout 1", "checkout counter", ("till 1", "checkout lane 1")),
        2: VisibleObject(2, "checkout 2", "checkout counter", ("till 2", "checkout lane 2")),
        3: VisibleObject(3, "rack A", "shelf"),
        4: VisibleObject(4, "checkout sign", "sign"),
    }
    every = {k: 100 + k for k in objs}
    best = lambda s, areas=every: [m.instance_id for m in ground(s, objs, areas)]  # noqa: E731
    assert best("stop in the lane between the two checkouts") == [2, 1]  # look-alikes: the larger first
    assert best("stop in the lane between the two checkouts", {1: 100, 4: 100}) == [1]
    assert best("go to the tills", {2: 100}) == [2]
    assert best("stop at checkout 2") == [2]
    assert best("stop at checkout 2", {1: 100, 3: 100}) == []  # checkout 1 is not checkout 2
    assert best("fly to rack B", {3: 100}) == []
    assert best("fly along the racks") == [3]
    assert best("hover under the checkout sign", {1: 100, 2: 100, 4: 100}) == [4]


def test_past_and_along_govern_the_of_phrase_after_their_noun():
    """``along the row of parked cars``: the cars are the route, not a car to reach. A second
    noun joined by ``and`` keeps its own governor: ``past the red car and the blue car`` ends
    the route at the blue car."""
    objs = {
        1: VisibleObject(1, "red car", "car"),
        2: VisibleObject(2, "blue car", "car"),
        3: VisibleObject(3, "rack D", "rack"),
        4: VisibleObject(4, "oak tree", "tree"),
        5: VisibleObject(5, "bench", "bench"),
    }
    every = {k: 100 for k in objs}
    flags = lambda s: [(m.instance_id, m.passed) for m in ground(s, objs, every)]  # noqa: E731
    assert flags("fly east along the row of parked cars past the red car and the blue car") == [(2, False), (1, True)]
    assert flags("fly along the back of rack D") == [(3, True)]
    assert not names_target("fly along the back of rack D")  # a route names nothing to reach
    assert names_target("fly to the back of rack D")
    assert flags("fly past the bench and stop at the oak tree") == [(4, False), (5, True)]
    assert flags("fly to the end of the row of cars") == [(1, False), (2, False)]


def test_a_landmark_flown_past_is_one_whatever_modifies_its_name():
    """``go past the kitchen table``: the bare label ``table`` sits inside the name's phrase, so
    it is flown past as the name is (it once ranked as the goal, ahead of the fridge)."""
    objs = {
        1: VisibleObject(1, "kitchen table", "table", ("big table",)),
        2: VisibleObject(2, "office fridge", "fridge", ("fridge",)),
        3: VisibleObject(3, "charging station", "charger"),
        4: VisibleObject(4, "blue car", "car"),
    }
    every = {k: 100 for k in objs}
    flags = lambda s, areas=every: [(m.instance_id, m.passed, m.locates) for m in ground(s, objs, areas)]  # noqa: E731
    assert flags("go past the kitchen table and stop in front of the fridge") == [(2, False, False), (1, True, False)]
    assert flags("go past the big kitchen table to the fridge") == [(2, False, False), (1, True, False)]
    assert flags("go past the big table", {1: 100}) == [(1, True, False)]
    assert flags("stop at the kitchen table") == [(1, False, False)]
    # a modifier between the locating preposition and the head: still a landmark of the noun before
    assert flags("land at the charging station by the parked blue car") == [(3, False, False), (4, False, True)]


def test_a_mention_made_of_place_words_says_where_not_what():
    """``Go up to the second floor and hover in front of the balcony door``: ``second floor`` is
    a platform's alias, but its words are place words (as :func:`names_target` reads them), so
    the door is the goal; alone, the platform is."""
    objs = {
        1: VisibleObject(1, "second-floor platform", "platform", ("second floor", "upper deck")),
        2: VisibleObject(2, "balcony door", "door"),
        3: VisibleObject(3, "ground floor", "floor"),
    }
    every = {k: 100 for k in objs}
    best = lambda s, areas=every: [m.instance_id for m in ground(s, objs, areas)]  # noqa: E731
    upstairs = {1: 100, 2: 100}
    assert best("Go up to the second floor and hover in front of the balcony door", upstairs) == [2, 1]
    assert best("Go up to the second floor and hover in front of the balcony door", {1: 100}) == [1]
    assert best("land on the second floor", upstairs) == [1]
    assert best("fly up to the upper deck and stop at the balcony door", upstairs) == [1, 2]  # "deck" names a thing
    assert best("stay on the ground floor") == [3]
    assert not names_target("go up to the second floor")


def test_a_noun_before_the_head_says_which_object_of_the_kind():
    """``the stairwell door`` is not the garage's exit shutter (label ``door``) and ``the palm
    tree`` is not the apple tree: a word that modifies the head must be one of the object's own,
    whatever its kind (it once held only for colours, sizes and materials, so with the named
    object out of view any other object of its label was the goal). Classifying ``-ing`` words
    count (``dining table``); an ``-ed`` state (``the parked car``) and a count (``the two
    lanterns``) do not. Nor does an ``of`` phrase after it (``the doorway of the bathroom``)."""
    objs = {
        1: VisibleObject(1, "green stairwell door", "door", ("stairwell door",)),
        2: VisibleObject(2, "garage exit shutter", "door"),
        3: VisibleObject(3, "palm tree near the pool", "tree"),
        4: VisibleObject(4, "apple tree", "tree"),
        5: VisibleObject(5, "dining table", "table"),
        6: VisibleObject(6, "coffee table", "table"),
        7: VisibleObject(7, "blue car", "car"),
        8: VisibleObject(8, "left garden lantern", "lantern"),
        9: VisibleObject(9, "right garden lantern", "lantern"),
    }
    best = lambda s, ids: [m.instance_id for m in ground(s, objs, {k: 100 for k in ids})]  # noqa: E731
    assert best("stop in front of the stairwell door", [1, 2]) == [1]
    assert best("stop in front of the stairwell door", [2]) == []  # out of view: not the shutter
    assert best("hover next to the door", [2]) == [2]  # the bare label names every door
    assert best("fly to the palm tree", [4]) == []
    assert best("land by the dining table", [6]) == []
    assert best("land by the dining table", [5, 6]) == [5]
    assert best("stop above the parked car", [7]) == [7]
    assert best("hover between the two garden lanterns", [8, 9]) == [8, 9]
    assert best("stop at the garden lantern", [9]) == [9]
    # an "of" phrase after the head says which object too
    objs[10] = VisibleObject(10, "bathroom doorway", "doorway", ("doorway of the bathroom",))
    objs[11] = VisibleObject(11, "kitchen doorway", "doorway")
    assert best("Stop in the doorway of the bathroom, looking at the tub", [10, 11]) == [10]
    assert best("Stop in the doorway of the bathroom, looking at the tub", [11]) == []
    assert best("go through the doorway", [10, 11]) == [10, 11]


def test_a_route_and_a_contraction_name_nothing_to_reach():
    """``continue along the wall`` flies a route: it names no target (walls never are), and
    along a named object the object is a landmark, ranked after the goal. ``You're at the end
    of the hall``: a clitic is a word (``are``), never a noun."""
    assert not names_target("continue along the wall")
    assert names_target("continue along the wall to the exit door")
    assert not names_target("You're at the end of the hall")
    assert not names_target("don't stop, you'll see it")
    assert words("Won't you're I'd") == ["will", "not", "you", "are", "i", "would"]
    objs = {1: VisibleObject(1, "bike cage fence", "fence"), 2: VisibleObject(2, "green gate", "gate", ("gate",))}
    flags = [(m.instance_id, m.passed) for m in ground("fly along the fence to the gate", objs, {1: 100, 2: 100})]
    assert flags == [(2, False), (1, True)]


def test_an_object_that_says_where_the_target_is_is_a_landmark():
    """``the charging station by the blue car``: the car says where the station is. Its mention
    is flagged (``locates``) and ranks after the target's; after a verb the same words name the
    goal (``stop next to the blue car``)."""
    objs = {
        1: VisibleObject(1, "charging station by the blue car", "charger", ("EV charger by the blue car",)),
        2: VisibleObject(2, "blue car", "car"),
        3: VisibleObject(3, "person", "person"),
        4: VisibleObject(4, "entrance", "entrance"),
    }
    every = {k: 100 for k in objs}
    flags = lambda s, areas=every: [(m.instance_id, m.locates) for m in ground(s, objs, areas)]  # noqa: E731
    assert flags("Stop in front of the charging station by the blue car.") == [(1, False), (2, True)]
    assert flags("Stop in front of the charging station by the blue car.", {2: 100}) == [(2, True)]
    assert flags("stop next to the blue car") == [(2, False)]
    assert flags("Go to the EV charger next to the blue car", {2: 100}) == [(2, True)]
    assert flags("fly to the person standing by the entrance", {4: 100}) == [(4, True)]  # a participle between
    assert flags("fly to the person, then by the entrance", {4: 100}) == [(4, False)]  # another clause
    assert flags("hover in front of the entrance") == [(4, False)]
    # where a thing is kept: in, inside, on, under, above a named object
    assert flags("stop by the person in the entrance", {4: 100}) == [(4, True)]
    assert flags("land on the blue car") == [(2, False)]  # after a verb, the goal
    assert flags("the person on the blue car, stop there", {2: 100}) == [(2, True)]


def test_a_phrase_after_the_name_says_which_object_when_the_object_has_one_of_its_own():
    """``the EV charger by the red car`` is not the ``charging station by the blue car``, ``the
    person in white`` not the ``person near the railing`` (alias ``person in purple``): an object
    whose own name or alias has a phrase after its noun is named only when the phrase the words
    put after the mention fits it (its head one of the object's own words, and its attributes
    too when the object's own phrases have some). An object with no such phrase of its own
    (``red motorcycle``) is still named by its label; directions say which way, not which object
    (``the bench on the left``)."""
    objs = {
        1: VisibleObject(1, "charging station by the red car", "charger", ("EV charger by the red car",)),
        2: VisibleObject(2, "charging station by the blue car", "charger", ("EV charger by the blue car",)),
        3: VisibleObject(3, "person near the railing", "person", ("person in purple",)),
        4: VisibleObject(4, "person in white shirt", "person", ("person in white",)),
        5: VisibleObject(5, "potted plant in the bedroom", "plant"),
        6: VisibleObject(6, "potted plant in the living room", "plant"),
        7: VisibleObject(7, "red motorcycle", "motorcycle"),
        8: VisibleObject(8, "white bench", "bench", ("bench on the lower lawn",)),
        9: VisibleObject(9, "mobile whiteboard", "whiteboard", ("whiteboard on wheels",)),
        10: VisibleObject(10, "whiteboard in the large meeting room", "whiteboard"),
    }
    best = lambda s, ids: [m.instance_id for m in ground(s, objs, {k: 100 for k in ids})]  # noqa: E731
    assert best("stop next to the EV charger by the red car", [2]) == []
    assert best("stop next to the EV charger by the red car", [1, 2]) == [1]
    assert best("stop at the charger", [1, 2]) == [1, 2]  # no phrase: both chargers
    assert best("approach the person in white", [3]) == []
    assert best("approach the person in purple", [3, 4]) == [3]
    assert best("fly to the person", [3, 4]) == [3, 4]
    # the head fits, an extra attribute the object's own phrase does not contradict is no objection
    assert best("stop next to the plant in the big bedroom", [5, 6]) == [5]
    assert best("stop next to the plant in the big bedroom", [6]) == []
    assert best("hover over the red motorcycle in the bike cage", [7]) == [7]  # no phrase of its own
    assert best("stop at the bench on the left", [8]) == [8]
    assert best("stop in front of the whiteboard in the small meeting room", [9, 10]) == []


def test_the_charger_by_another_car_is_neither_pointed_at_nor_stopped_at():
    """With only the charger by the blue car in view, asked for the one by the red car, the
    model says the target is not visible and the monitor does not stop 1.5 m from it; with
    both in view it points at the right one."""
    sim = SimulatedVlm("perfect", seed=0)
    red = Obj(5, "charging station by the red car", "charger", 4.0, rect=(120, 40, 130, 60), aliases=("EV charger by the red car",))
    blue = Obj(6, "charging station by the blue car", "charger", 4.0, rect=(20, 40, 30, 60), aliases=("EV charger by the blue car",))
    subtask = "Stop next to the EV charger by the red car."
    answer = json.loads(decide(sim, subtask, frame("pc1", [blue], open_cols=(200, 220))).text)
    assert answer["target_visible"] is False
    near_blue = frame("pc2", [dataclasses.replace(blue, depth_m=1.5)])
    assert parse_status(monitor(sim, subtask, [near_blue, near_blue]).text).status is MonitorStatus.CONTINUE
    u, v = json.loads(decide(sim, subtask, frame("pc3", [blue, red])).text)["point_2d"]
    assert 120 <= u < 130 and 40 <= v < 60


def test_with_only_the_landmark_in_view_the_model_looks_there_and_never_stops_at_it():
    sim = SimulatedVlm("perfect", seed=0)
    charger = Obj(5, "charging station by the blue car", "charger", 4.0, rect=(120, 40, 130, 60))
    car = Obj(6, "blue car", "car", 4.0, rect=(20, 50, 70, 100))
    subtask = "Stop in front of the charging station by the blue car."
    only_car = frame("lc1", [car], open_cols=(140, 160))
    answer = json.loads(decide(sim, subtask, only_car).text)
    assert answer["target_visible"] is False
    u, v = answer["point_2d"]
    assert 20 <= u < 70 and 50 <= v < 100  # on the car, not the deepest open direction (140-160)
    both = frame("lc2", [car, charger])
    u, v = json.loads(decide(sim, subtask, both).text)["point_2d"]
    assert 120 <= u < 130 and 40 <= v < 60
    near_car = frame("lc3", [dataclasses.replace(car, depth_m=1.5)])
    assert parse_status(monitor(sim, subtask, [near_car, near_car]).text).status is MonitorStatus.CONTINUE
    assert _spf(sim, subtask, near_car)["depth"] > 0  # the baselines' stop interface: not reached either


def test_an_entrance_leads_to_the_places_its_name_says():
    """``doorway to the storage room``, ``kitchen doorway``, ``double doors of the large meeting
    room``: a place follows ``to`` / ``of`` / ``into``, with or without its article, or ends the words before the label
    with a place word; a colour or a material names none, and only entrances lead anywhere."""
    places = lambda name, label, aliases=(): entrance_places(VisibleObject(1, name, label, aliases))  # noqa: E731
    assert places("storage room doorway", "doorway", ("doorway to the storage room",)) == (("storage", "room"),)
    assert places("kitchen doorway", "doorway") == (("kitchen",),)
    assert places("double doors of the large meeting room", "door") == (("large", "meeting", "room"),)
    assert places("bike cage gate", "gate", ("entrance to the bike cage",)) == (("bike", "cage"),)
    assert places("living room doorway", "doorway", ("doorway to the hallway",)) == (("living", "room"), ("hallway",))
    assert places("red door", "door") == places("storage door", "door") == ()
    assert places("door to the kitchen", "cabinet") == ()  # not an entrance
    # a place named without an article ("classroom A", "room 204")
    assert places("classroom A door", "door", ("doorway to classroom A",)) == (("classroom", "a"),)
    assert places("door into room 204", "door") == (("room", "204"),)
    assert places("door to the", "door") == ()  # nothing after the article


def test_a_place_the_words_name_is_found_by_its_entrance():
    """The entrance to the place the subtask names, as the head of a noun phrase, with no
    modifier the entrance does not carry, where the target is, where to go (``in``, ``into``,
    ``to``, ``enter``) or the place to leave (``leave``, ``exit``, ``out of``); never a place
    crossed, followed or flown past."""
    objs = {
        1: VisibleObject(1, "storage room doorway", "doorway", ("doorway to the storage room",)),
        2: VisibleObject(2, "kitchen doorway", "doorway", ("doorway to the kitchen",)),
        3: VisibleObject(3, "main bedroom doorway", "doorway", ("bedroom doorway",)),
    }
    every = {k: 100 for k in objs}
    find = lambda s, areas=every: place_entrance(s, objs, areas)  # noqa: E731
    assert find("There is a vacuum cleaner in the storage room. Fly to it.") == 1
    assert find("Fly into the kitchen and stop by the stove") == 2
    assert find("fly to the fridge in the kitchen, not the storage room") == 2  # the earliest mention
    assert find("Fly into the kitchen", {1: 100}) is None  # its entrance is not in view
    assert find("go to the kitchen sink") is None  # a modifier of the sink, not a place
    assert find("go into the small bedroom") is None  # another bedroom than the main one
    assert find("go into the bedroom") == 3
    assert find("enter the storage room") == 1
    # the place the vehicle is in and is to leave: its entrance is the way out
    assert find("Leave the kitchen and find the stove") == 2
    assert find("fly out of the kitchen") == 2
    assert find("exit the main bedroom, then go to the sofa") == 3
    assert find("leave the small bedroom") is None  # another bedroom than the main one
    assert find("stop in front of the kitchen") is None  # "of" without "out": no way in or out
    for route in ("come from the kitchen to the sofa", "fly past the kitchen to the sofa", "follow the kitchen to the sofa",
                  "fly through the kitchen", "the kitchen, then the sofa", "leave, then the kitchen"):  # fmt: skip
        assert find(route) is None, route  # a place flown past or along, or named with no way in


def test_with_the_entrance_to_the_named_place_in_view_the_model_looks_there():
    sim = SimulatedVlm("perfect", seed=0)
    storage = Obj(7, "storage room doorway", "doorway", 6.0, rect=(20, 30, 50, 100), aliases=("doorway to the storage room",))
    copy_room = Obj(8, "copy room doorway", "doorway", 6.0, rect=(80, 30, 110, 100), aliases=("doorway to the copy room",))
    doors = frame("pe1", [storage, copy_room], open_cols=(140, 160))
    answer = json.loads(decide(sim, "Fly to the vacuum cleaner in the storage room.", doors).text)
    assert answer["target_visible"] is False
    assert 20 <= answer["point_2d"][0] < 50  # the storage room's doorway, not the open columns 140-160
    answer = json.loads(decide(sim, "Fly to the vacuum cleaner in the server room.", doors).text)
    assert answer["target_visible"] is False and answer["point_2d"][0] >= 140  # no entrance to it: the open way
    # a place to go, no target named: its entrance is the way, whatever the history point
    answer = json.loads(decide(sim, "fly into the copy room", doors, history=(150, 60)).text)
    assert answer["target_visible"] is True and 80 <= answer["point_2d"][0] < 110
    assert 80 <= _spf(sim, "fly into the copy room", doors)["point_2d"][0] < 110  # every prompt alike
    # a place to leave: its entrance is the way out, in every prompt
    answer = json.loads(decide(sim, "Leave the storage room, then turn left", doors, history=(150, 60)).text)
    assert answer["target_visible"] is True and 20 <= answer["point_2d"][0] < 50
    assert 20 <= _spf(sim, "exit the storage room", doors)["point_2d"][0] < 50
    # the look-alike rule holds for the entrance too: at confusion_prob 1 the other doorway
    confused = SimulatedVlm(dataclasses.replace(PRESETS["perfect"], confusion_prob=1.0), seed=0)
    answer = json.loads(decide(confused, "Fly to the vacuum cleaner in the storage room.", doors).text)
    assert 80 <= answer["point_2d"][0] < 110


def test_non_target_objects_are_never_the_goal():
    """Scene objects with target = false (walls, ground, parked cars) are never grounded."""
    objs = {
        1: VisibleObject(1, "warehouse walls", "wall", target=False),
        2: VisibleObject(2, "parked car 3", "car", target=False),
        3: VisibleObject(3, "blue car", "car"),
    }
    areas = {1: 900, 2: 900, 3: 100}
    best = lambda s, a=areas: [m.instance_id for m in ground(s, objs, a)]  # noqa: E731
    assert best("fly to the car") == [3]  # the larger parked car is not a goal
    assert best("fly to the car", {1: 900, 2: 900}) == []
    assert best("stop at the wall") == []
    sim = SimulatedVlm("perfect", seed=0)
    img = frame("nt", [Obj(2, "parked car 3", "car", 4.0, rect=(10, 40, 80, 90), target=False)])
    assert json.loads(decide(sim, "fly to the car", img).text)["target_visible"] is False
    near = frame("nt2", [Obj(2, "parked car 3", "car", 1.0, rect=(10, 40, 80, 90), target=False)])
    assert monitor(sim, "stop next to the car", [near, near]).text == "CONTINUE"


def test_names_target():
    for text in ("fly forward", "continue through the intersection", "go to the end of the corridor", "turn left",
                 "go up to the second floor", "stop about a metre ahead", "fly 3 m forward then turn right",
                 "leave the study", "go into the elevator lobby", "walk into the kitchen area",
                 "cut through the modern art gallery into the sculpture hall", "swing left", "drop down", "loop round"):  # fmt: skip
        assert not names_target(text), text
    # every movement verb of the splitter ends a phrase: a verb is never the noun a subtask names
    from vlm.decompose import MOVEMENT_VERBS

    assert not [v for v in MOVEMENT_VERBS if names_target(f"{v} forward")]
    for text in ("stop at the blue door", "fly to it and hover next to the wall clock", "find the fuel pump",
                 "go to office 105", "approach the person in white", "go to the elevator", "walk to the kitchen table",
                 "go past the study lamp, then left"):  # fmt: skip
        assert names_target(text), text


def test_front_and_back_before_a_noun_say_which_one_in_front_of_says_where():
    side = VisibleObject(10, "side door", "door", ("small barn door",), True, False)
    front = VisibleObject(25, "front door", "door", ("farmhouse door",), True, False)
    both = {10: side, 25: front}
    # "the front door" names the front door, never the barn's side door when it alone is in view
    assert [m.instance_id for m in ground("stop right in front of the front door", both, {10: 500, 25: 100})] == [25]
    assert ground("stop right in front of the front door", {10: side}, {10: 500}) == []
    assert ground("fly to the back door", {10: side}, {10: 500}) == []
    # "in front of the door" and "the door at the back" say where: any door
    assert {m.instance_id for m in ground("stop in front of the door", both, {10: 500, 25: 100})} == {10, 25}
    assert {m.instance_id for m in ground("go through the door at the back", both, {10: 500, 25: 100})} == {10, 25}


def test_the_places_a_building_holds_are_where_and_accents_fold():
    # rooms and the places a building or a yard holds name no target; written with accents too
    for text in ("leave the café", "leave the cafe", "fly through the impressionist gallery", "go into the gift shop",
                 "walk through the orchard", "go out of the cafeteria and into the library"):  # fmt: skip
        assert not names_target(text), text
    # a place word before a noun is that noun's modifier; an accent is the same word
    assert names_target("fly to the café table") and names_target("stop at the gallery door")
    assert names_target("find the water trough by the barn") and names_target("head into the barn")  # a building
    table = VisibleObject(1, "cafe table", "table", (), True, False)
    assert [m.instance_id for m in ground("stop beside the café table", {1: table}, {1: 400})] == [1]


def test_exploration_point_prefers_the_deepest_open_block_near_the_centre():
    depth = np.full((H, W), 5.0, np.float32)
    depth[:, 20:30] = 50.0
    assert exploration_point(depth) == (24, (H - 1) // 2)  # block cols 20..29, centre 24.5 rounded down
    depth[:, 120:140] = np.nan  # no reading: open
    u, v = exploration_point(depth)
    assert 120 <= u < 140
    assert exploration_point(np.zeros((H, W), np.float32)) in {(74, 59), (85, 59)}  # all open: a centre block


# ---------------------------------------------------------------------------------------------
# the perfect preset


def test_perfect_points_on_the_named_target_whenever_visible():
    rng = np.random.default_rng(0)
    sim = SimulatedVlm("perfect", seed=0)
    names = [("red van", "van"), ("blue van", "van"), ("oak tree", "tree"), ("wooden gate", "gate"), ("white car", "car")]
    phrasings = ["fly to the {}", "stop next to the {}", "approach {}", "go through the {} then stop"]
    for trial in range(150):
        objs = []
        for k, (name, label) in enumerate(names):
            if rng.random() < 0.7:
                iid = 10 + k
                if rng.random() < 0.5:
                    u0, v0 = rng.integers(0, W - 4), rng.integers(0, H - 4)
                    rect = (int(u0), int(v0), int(u0 + rng.integers(1, 50)), int(v0 + rng.integers(1, 40)))
                    objs.append(Obj(iid, name, label, float(rng.uniform(1, 60)), rect=rect))
                else:
                    disc = (float(rng.uniform(0, W)), float(rng.uniform(0, H)), float(rng.uniform(0.6, 25)))
                    objs.append(Obj(iid, name, label, float(rng.uniform(1, 60)), disc=disc))
        img = frame(f"p{trial}", objs)
        visible = img.annotation.objects
        for iid, obj in visible.items():
            subtask = phrasings[trial % len(phrasings)].format(obj.name)
            r = decide(sim, subtask, img)
            res = parse_point(r.text, img.size)
            assert res.ok, r.text
            u, v = (int(round(c)) for c in res.uv)
            assert img.annotation.instance_ids[v, u] == iid, (subtask, r.text)


def test_hidden_target_is_never_seen():
    sim = SimulatedVlm("perfect", seed=0)
    # the red van is behind the tree: not in the annotation at all -> "not visible", no invented
    # point, with or without a history point
    hidden = frame("h1", [TREE, BLUE_VAN], open_cols=(0, 10))
    look = list(exploration_point(hidden.annotation.depth_m))
    r = decide(sim, "fly to the red van", hidden)
    # decision/v3: where to look instead is the exploration point every baseline prompt gets
    assert json.loads(r.text) == {"target_visible": False, "point_2d": look}
    parsed = parse_point(r.text, hidden.size)
    assert parsed.not_visible and parsed.uv is None and parsed.look_uv == tuple(look)
    r = decide(sim, "fly to the red van", hidden, history=(130.2, 70.7))
    assert json.loads(r.text) == {"target_visible": False, "point_2d": look}
    # an annotation entry without pixels is not seen either
    stale = frame("h2", [TREE])
    ann = stale.annotation
    ghost = VlmImage(stale.rgb, "h2", FrameAnnotation(ann.instance_ids, ann.depth_m, {**ann.objects, 7: VisibleObject(7, "red van", "van")}))
    assert decide(sim, "fly to the red van", ghost).text == decide(sim, "fly to the red van", frame("h2b", [TREE])).text
    # monitoring: close everywhere but never seen -> never STOP and never LOST
    near = frame("h3", [TREE], bg_depth=0.5)
    assert monitor(sim, "stop next to the red van", [near, near, near]).text == "CONTINUE"
    assert not sim.perceive("fly to the red van", hidden).perceived


def test_a_subtask_naming_no_object_points_into_open_space():
    """No target is named ("fly forward"): pointing into open space is the answer, never
    "not visible"; the history point is kept when there is one."""
    sim = SimulatedVlm("perfect", seed=0)
    img = frame("o1", [TREE, BLUE_VAN], open_cols=(0, 10))
    for subtask in ("fly forward", "continue through the intersection", "go to the end of the corridor", "turn left"):
        r = decide(sim, subtask, img)
        assert json.loads(r.text) == {"target_visible": True, "point_2d": list(exploration_point(img.annotation.depth_m))}
        assert json.loads(decide(sim, subtask, img, history=(130.2, 70.7)).text)["point_2d"] == [130, 71]


def test_not_visible_answers_parse_as_not_visible_in_every_shape():
    """Format variety and structured output: every well-formed "not visible" answer parses as
    not_visible; malformed ones (rate ``malformed_prob``) are failures, never a point."""
    model = PRESETS["nominal"]
    sim = SimulatedVlm("nominal", seed=3)
    base = frame("nv", [TREE, BLUE_VAN])
    outcomes = {"point": 0, "not_visible": 0, "failed": 0}
    shapes = set()
    for k in range(N):
        img = renamed(base, f"nv{k}")
        text = decide(sim, "fly to the red van", img).text
        outcomes[parse_point(text, img.size).outcome.value] += 1
        shapes.add(text[:12])
        structured = decide(sim, "fly to the red van", img, json_schema=decision_schema()).text
        assert parse_point(structured, img.size).outcome.value in ("not_visible", "failed")
    assert outcomes["point"] == 0
    assert binomial_ok(outcomes["failed"], N, model.malformed_prob)
    assert len(shapes) >= 4  # plain JSON, fence, NOT_VISIBLE, prose, and malformed shapes


def test_perfect_monitoring_stop_lost_continue():
    sim = SimulatedVlm("perfect", seed=0)
    far = frame("m1", [dataclasses.replace(VAN, depth_m=10.0)])
    near = frame("m2", [dataclasses.replace(VAN, depth_m=2.9)])
    edge = frame("m2b", [dataclasses.replace(VAN, depth_m=3.1)])
    gone1, gone2 = frame("m3", [TREE]), frame("m4", [TREE])
    s = lambda frames: parse_status(monitor(sim, "stop next to the red van", frames).text).status  # noqa: E731
    assert s([far, far]) is MonitorStatus.CONTINUE
    assert s([far, near]) is MonitorStatus.STOP
    assert s([far, edge]) is MonitorStatus.CONTINUE  # stop distance 3.0 m
    assert s([far, gone1, gone2]) is MonitorStatus.LOST  # seen, then absent from the last 2 frames
    assert s([far, far, gone2]) is MonitorStatus.CONTINUE  # absent from the latest frame only
    assert s([gone1, gone1, gone2]) is MonitorStatus.CONTINUE  # never seen: not lost


def test_perfect_lost_names_the_latest_image_that_showed_the_target():
    sim = SimulatedVlm("perfect", seed=0)
    far = frame("p1", [dataclasses.replace(VAN, depth_m=10.0)])
    gone = [frame(f"p{k}", [TREE]) for k in range(2, 6)]
    answer = lambda frames: parse_status(monitor(sim, "stop next to the red van", frames).text, n_keyframes=len(frames) - 2)  # noqa: E731
    # [first, k1, k2, k3, latest]: seen in keyframe 1 only
    res = answer([gone[0], far, gone[1], gone[2], gone[3]])
    assert res.status is MonitorStatus.LOST and res.seen_image == 1
    # seen in the first frame and keyframe 2: the later one
    res = answer([far, gone[0], renamed(far, "p1b"), gone[1], gone[2]])
    assert res.status is MonitorStatus.LOST and res.seen_image == 2
    res = answer([far, gone[0], gone[1]])
    assert res.status is MonitorStatus.LOST and res.seen_image == 0
    # structured output carries it as "last_seen"
    text = monitor(sim, "stop next to the red van", [gone[0], far, gone[1], gone[2]], json_schema=status_schema()).text
    assert json.loads(text) == {"status": "LOST", "last_seen": "keyframe 1"}


def test_lost_place_errs_at_the_status_error_rate():
    """Nominal: with the target perceived in keyframe 2 only, the place is keyframe 2 unless the
    forced-choice error (``status_error_prob``) names another earlier image."""
    model = dataclasses.replace(PRESETS["nominal"], malformed_prob=0.0, status_error_prob=0.2, miss_prob_far=0.0, miss_prob_small=0.0)
    sim = SimulatedVlm(model, seed=4)
    near = dataclasses.replace(VAN, depth_m=6.0)
    wrong = lost = 0
    for k in range(N):
        frames = [frame(f"q{k}a", [TREE]), frame(f"q{k}b", [TREE]), frame(f"q{k}c", [near]), frame(f"q{k}d", [TREE]), frame(f"q{k}e", [TREE])]
        res = parse_status(monitor(sim, "stop next to the red van", frames).text, n_keyframes=3)
        if res.status is MonitorStatus.LOST:
            lost += 1
            assert res.seen_image in (0, 1, 2, 3)
            wrong += res.seen_image != 2
    assert lost > 0.7 * N
    assert binomial_ok(wrong, lost, model.status_error_prob)


def test_answers_depend_only_on_the_annotation_not_the_pixels():
    sim = SimulatedVlm("noisy", seed=5)
    a = decide(sim, "fly to the red van", frame("same", [VAN, TREE], rgb_value=0))
    b = decide(sim, "fly to the red van", frame("same", [VAN, TREE], rgb_value=200))
    assert a.text == b.text


# ---------------------------------------------------------------------------------------------
# determinism


def test_identical_seeds_give_identical_answers_in_any_call_order():
    frames = [frame(f"d{k}", [VAN, BLUE_VAN, TREE]) for k in range(40)]
    calls = [("fly to the red van", f) for f in frames] + [("fly to the oak tree", f) for f in frames]
    a = [decide(SimulatedVlm("noisy", seed=11), s, f).text for s, f in calls]
    sim = SimulatedVlm("noisy", seed=11)
    b = [decide(sim, s, f).text for s, f in reversed(calls)][::-1]
    assert a == b
    c = [decide(SimulatedVlm("noisy", seed=12), s, f).text for s, f in calls]
    assert a != c


# ---------------------------------------------------------------------------------------------
# error rates match the documented parameters


N = 1000


def test_confusion_rate_matches_preset():
    model = PRESETS["noisy"]
    sim = SimulatedVlm(dataclasses.replace(model, malformed_prob=0.0), seed=2)
    hits = {7: 0, 8: 0}
    base = frame("c", [dataclasses.replace(VAN, depth_m=2.0), dataclasses.replace(BLUE_VAN, depth_m=2.0)])
    for k in range(N):
        img = renamed(base, f"c{k}")
        res = parse_point(decide(sim, "fly to the red van", img).text, img.size)
        assert res.ok
        iid = int(img.annotation.instance_ids[int(round(res.uv[1])), int(round(res.uv[0]))])
        hits[iid] = hits.get(iid, 0) + 1
    assert hits[7] + hits[8] >= N - 30  # noise rarely leaves the 40x40 boxes at 2 m
    assert binomial_ok(hits[8], hits[7] + hits[8], model.confusion_prob)


@pytest.mark.parametrize("preset", ["nominal", "noisy"])
def test_miss_rates_match_preset(preset):
    model = PRESETS[preset]
    sim = SimulatedVlm(preset, seed=4)
    small = Obj(7, "red van", "van", 5.0, rect=(100, 50, 102, 52))  # 4 px
    far = Obj(7, "red van", "van", model.far_target_m + 5.0, rect=(100, 50, 140, 90))
    both = Obj(7, "red van", "van", model.far_target_m + 5.0, rect=(100, 50, 102, 52))
    big_near = Obj(7, "red van", "van", 5.0, rect=(100, 50, 140, 90))
    counts = {}
    for tag, obj in (("small", small), ("far", far), ("both", both), ("big_near", big_near)):
        base = frame(tag, [obj])
        counts[tag] = sum(not sim.perceive("fly to the red van", renamed(base, f"{tag}{k}")).perceived for k in range(N))
    assert binomial_ok(counts["small"], N, model.miss_prob_small)
    assert binomial_ok(counts["far"], N, model.miss_prob_far)
    assert binomial_ok(counts["both"], N, 1 - (1 - model.miss_prob_small) * (1 - model.miss_prob_far))
    assert counts["big_near"] == 0


def test_missed_target_answer_is_not_visible():
    """A target in the frame that the error model misses is answered as not visible (the
    model does not perceive it), not with an invented point."""
    model = dataclasses.replace(PRESETS["perfect"], miss_prob_small=1.0)
    sim = SimulatedVlm(model)
    img = frame("x", [Obj(7, "red van", "van", 5.0, rect=(100, 50, 102, 52))], open_cols=(10, 20))
    look = list(exploration_point(img.annotation.depth_m))
    assert json.loads(decide(sim, "fly to the red van", img).text) == {"target_visible": False, "point_2d": look}
    assert json.loads(decide(sim, "fly to the red van", img, history=(50, 50)).text)["target_visible"] is False


@pytest.mark.parametrize("preset", ["nominal", "noisy", "weak"])
def test_malformed_rates_match_preset_and_always_fail_to_parse(preset):
    model = PRESETS[preset]
    sim = SimulatedVlm(preset, seed=6)
    bad_points = bad_status = 0
    base = frame("q", [VAN, TREE])
    for k in range(N):
        img = renamed(base, f"q{k}")
        bad_points += not parse_point(decide(sim, "fly to the red van", img).text, img.size).ok
        bad_status += not parse_status(monitor(sim, "fly to the red van", [img, img]).text).ok
    # every malformed answer fails, every other answer parses (noise never leaves the image)
    assert binomial_ok(bad_points, N, model.malformed_prob)
    assert binomial_ok(bad_status, N, model.malformed_prob)


def test_status_error_rate_matches_preset():
    model = dataclasses.replace(PRESETS["noisy"], malformed_prob=0.0)
    sim = SimulatedVlm(model, seed=8)
    wrong = 0
    base = frame("s", [dataclasses.replace(VAN, depth_m=15.0)])  # clearly CONTINUE
    for k in range(N):
        img = renamed(base, f"s{k}")
        wrong += parse_status(monitor(sim, "fly to the red van", [img, img]).text).status is not MonitorStatus.CONTINUE
    assert binomial_ok(wrong, N, model.status_error_prob)


def test_early_stop_follows_offset_and_jitter():
    model = dataclasses.replace(PRESETS["weak"], status_error_prob=0.0, malformed_prob=0.0)
    sim = SimulatedVlm(model, seed=9)
    d = 3.5
    base = frame("e", [dataclasses.replace(VAN, depth_m=d)])
    stops = sum(
        parse_status(monitor(sim, "fly to the red van", [renamed(base, f"e{k}")] * 2).text).status
        is MonitorStatus.STOP
        for k in range(N)
    )
    p = 0.5 * (1 + math.erf((model.stop_distance_m + model.stop_offset_m - d) / (model.stop_jitter_m * math.sqrt(2))))
    assert p > 0.5  # the weak preset stops early: STOP is likely 0.5 m before the stop distance
    assert binomial_ok(stops, N, p)


def test_pixel_noise_grows_with_distance_as_documented():
    model = dataclasses.replace(PRESETS["noisy"], malformed_prob=0.0, confusion_prob=0.0, format_variety_prob=0.0)
    sim = SimulatedVlm(model, seed=10)
    stds = []
    for d in (2.0, 15.0):
        target = Obj(7, "red van", "van", d, rect=(40, 20, 121, 101))  # anchor at (80, 60)
        base = frame("n", [target])
        us = np.array([json.loads(decide(sim, "fly to the red van", renamed(base, f"n{d}-{k}")).text)["point_2d"][0] for k in range(N)])
        sigma = model.pixel_sigma_px(W, d)
        assert 80 / sigma > 6  # clipping at the image edge is negligible
        assert abs(us.mean() - 80) < 4.5 * sigma / math.sqrt(N) + 0.5
        assert us.std() == pytest.approx(math.sqrt(sigma**2 + 1 / 12), rel=0.1)
        stds.append(us.std())
    assert stds[1] > 2 * stds[0]


def test_decomposition_merge_rate_matches_preset():
    model = dataclasses.replace(PRESETS["noisy"], malformed_prob=0.0)
    sim = SimulatedVlm(model, seed=12)
    boundaries = merged = 0
    for k in range(200):
        parts = [f"fly to marker {k}-{j}" for j in range(8)]
        res = parse_subtasks(sim.complete(*build_decompose_prompt("; ".join(parts))).text)
        assert res.ok
        assert " then ".join(res.subtasks) .replace(" then ", "; ") == "; ".join(parts)
        boundaries += 7
        merged += 7 - (len(res.subtasks) - 1)
    assert binomial_ok(merged, boundaries, model.merge_prob)


def test_structured_output_is_bare_json_and_only_schema_valid_errors():
    model = dataclasses.replace(PRESETS["noisy"], malformed_prob=0.5)
    sim = SimulatedVlm(model, seed=13)
    outside = 0
    base = frame("j", [VAN])
    for k in range(200):
        img = renamed(base, f"j{k}")
        text = decide(sim, "fly to the red van", img, json_schema=decision_schema()).text
        point = json.loads(text)["point_2d"]  # always bare JSON
        outside += not parse_point(text, img.size).ok
        assert all(isinstance(c, int) and c >= 0 for c in point)
        status = json.loads(monitor(sim, "fly to the red van", [img, img], json_schema=status_schema()).text)
        assert status["status"] in ("CONTINUE", "STOP", "LOST")
    assert binomial_ok(outside, 200, 0.5)


# ---------------------------------------------------------------------------------------------
# latency, usage, deadline


def test_decision_latency_and_usage():
    sim = SimulatedVlm("perfect")
    r = decide(sim, "fly to the red van", frame("l1", [VAN]), cache_key="decision")
    assert r.latency_s == pytest.approx(0.81)
    image_tokens = math.ceil(W / 28) * math.ceil(H / 28) + 2
    assert r.usage.prompt_tokens > image_tokens and r.usage.cached_tokens == 0
    r2 = decide(sim, "fly to the red van", frame("l2", [VAN]), cache_key="decision")
    assert 0 < r2.usage.cached_tokens < r2.usage.prompt_tokens  # system text and subtask reused
    assert r2.usage.completion_tokens == math.ceil(len(r2.text) / 4)


def test_monitoring_latency_reflects_prefix_reuse():
    sim = SimulatedVlm("perfect")
    o1, k = frame("o1", [VAN]), [frame(f"k{i}", [VAN]) for i in range(5)]
    t = [frame(f"t{i}", [VAN]) for i in range(6)]
    hybrid = lambda keys, latest: monitor(sim, "fly to the red van", [o1, *keys, latest], cache_key="monitor")  # noqa: E731
    first = hybrid(k[:4], t[0])
    assert first.latency_s == pytest.approx(1.98) and first.usage.cached_tokens == 0
    steady = hybrid(k[:4], t[1])  # hybrid memory: only the latest frame is new
    assert steady.latency_s == pytest.approx(1.15)
    assert 0 < steady.usage.cached_tokens < steady.usage.prompt_tokens
    changed = hybrid([k[0], k[1], k[2], k[4]], t[2])  # the 4th keyframe replaced: 4 of 6 images reused
    assert changed.latency_s == pytest.approx(1.98 - 0.83 * 4 / 5)
    sliding = monitor(sim, "fly to the red van", [t[1], t[2], t[3]], cache_key="window")
    sliding2 = monitor(sim, "fly to the red van", [t[2], t[3], t[4]], cache_key="window")
    assert sliding2.latency_s == pytest.approx(1.98)  # first image changed: no image reused
    image_tokens = math.ceil(W / 28) * math.ceil(H / 28) + 2
    assert 0 < sliding2.usage.cached_tokens <= sliding2.usage.prompt_tokens - 3 * image_tokens  # text only
    assert monitor(sim, "fly to the red van", [o1, *k[:4], t[5]]).latency_s == pytest.approx(1.98)  # no cache_key


def test_deadline_gives_timeout_and_does_not_touch_the_cache():
    sim = SimulatedVlm("perfect")
    img = frame("dl", [VAN])
    r = monitor(sim, "fly to the red van", [img, img], deadline_s=1.0, cache_key="m")
    assert r.status is CallStatus.TIMEOUT and r.text == "" and r.latency_s == 1.0 and "deadline" in r.error
    r = monitor(sim, "fly to the red van", [img, frame("dl2", [VAN])], cache_key="m")
    assert r.ok and r.latency_s == pytest.approx(1.98)
    assert decide(sim, "fly to the red van", img, deadline_s=1.0).ok


def test_max_new_tokens_truncates_like_a_server():
    sim = SimulatedVlm("perfect")
    r = decide(sim, "fly to the red van", frame("tr", [VAN]), max_new_tokens=2)
    assert len(r.text) == 8 and r.usage.completion_tokens == 2
    assert not parse_point(r.text, (W, H)).ok


# ---------------------------------------------------------------------------------------------
# features


def test_features_similar_within_objects_and_dissimilar_across_labels():
    sim = SimulatedVlm("nominal", seed=1, feature_model="perfect")
    img = frame("feat", [Obj(7, "red van", "van", 5.0, rect=(0, 0, 64, 64)), Obj(8, "blue van", "van", 5.0, rect=(64, 0, 128, 64)), Obj(9, "oak tree", "tree", 5.0, rect=(0, 64, 64, 120))], size=(150, 120))
    f = sim.features(img)
    assert f.grid.shape == (8, 10, 64) and f.grid.dtype == np.float32
    assert f.patch_px == 16 and f.image_size == (150, 120) and f.source == "sim:labels"
    assert np.allclose(np.linalg.norm(f.grid, axis=2), 1.0, atol=1e-5)
    cos = lambda a, b: float(f.grid[a] @ f.grid[b])  # noqa: E731
    assert cos((0, 0), (3, 3)) > 0.9  # one object
    assert 0.45 < cos((0, 0), (0, 5)) < 0.85  # two vans: same label, other instance (~0.64)
    assert abs(cos((0, 0), (5, 1))) < 0.5  # van vs tree
    assert f.patch_of(20.0, 70.0) == (4, 1)
    again = SimulatedVlm("noisy", seed=1, feature_model="perfect").features(img)
    assert np.array_equal(again.grid, f.grid)  # features depend on the seed and frame, not the preset
    assert not np.array_equal(SimulatedVlm("nominal", seed=2, feature_model="perfect").features(img).grid, f.grid)
    assert sim.features(VlmImage(np.zeros((4, 4, 3), np.uint8), "raw")) is None


def test_degraded_features_blur_boundaries_bring_look_alikes_close_and_follow_texture():
    objs = [Obj(7, "red van", "van", 5.0, rect=(0, 0, 64, 64)), Obj(8, "blue van", "van", 5.0, rect=(64, 0, 128, 64)),
            Obj(9, "oak tree", "tree", 5.0, rect=(0, 64, 64, 128)), Obj(10, "grey box", "box", 5.0, rect=(64, 64, 128, 128))]
    img = frame("deg", objs, size=(128, 128))
    rgb = np.zeros((128, 128, 3), np.uint8)
    rgb[:64, :] = (200, 30, 30)  # both vans red: a look-alike of the same colour
    rgb[64:, :64] = (30, 140, 30)
    rgb[64:, 64:] = (200, 30, 30)  # a box painted like the vans
    img = VlmImage(rgb, "deg", img.annotation)
    perfect = SimulatedVlm("nominal", seed=3, feature_model="perfect").features(img).grid
    f = SimulatedVlm("nominal", seed=3).features(img)
    assert f.source == "sim:degraded" and f.grid.shape == (8, 8, 64)
    assert np.allclose(np.linalg.norm(f.grid, axis=2), 1.0, atol=1e-5)
    g = f.grid
    cos = lambda grid, a, b: float(grid[a] @ grid[b])  # noqa: E731
    # Inside an object, away from boundaries: still close.
    assert cos(g, (1, 1), (2, 2)) > 0.85
    # Look-alikes (same label, same colour) come closer than in the perfect model, past tau.
    assert cos(g, (1, 1), (1, 6)) > cos(perfect, (1, 1), (1, 6)) + 0.05 and cos(g, (1, 1), (1, 6)) > 0.6
    # Texture: a box painted like the van is closer to it than to the green tree.
    assert cos(g, (6, 6), (1, 1)) > cos(g, (6, 6), (6, 1)) + 0.1
    assert cos(g, (6, 6), (1, 1)) > cos(perfect, (6, 6), (1, 1)) + 0.1
    # Blurred boundaries: a van patch on the border is closer to the tree than a central one.
    assert cos(g, (3, 1), (6, 1)) > cos(g, (1, 1), (6, 1)) + 0.05
    # Seeded and reproducible.
    assert np.array_equal(SimulatedVlm("noisy", seed=3).features(img).grid, g)
    assert not np.array_equal(SimulatedVlm("nominal", seed=4).features(img).grid, g)
    with pytest.raises(Exception, match="feature_model"):
        SimulatedVlm("nominal", feature_model="ideal")


# ---------------------------------------------------------------------------------------------
# baseline prompts (typefly, pivot, spf): the same error model, memoryless leg rule


def _spf(sim, instruction, img, **kw):
    from vlm.prompts import build_spf_prompt

    return json.loads(sim.complete(*build_spf_prompt(instruction, img), json_schema={}, **kw).text)


def test_spf_points_at_the_target_with_its_depth_and_says_zero_when_close():
    sim = SimulatedVlm("perfect", seed=0)
    far = frame("s1", [VAN])  # median depth 6 m
    ans = _spf(sim, "Fly to the red van.", far)
    u, v = ans["point_2d"]
    assert far.annotation.instance_ids[v, u] == VAN.iid and ans["depth"] == 6
    near = frame("s2", [dataclasses.replace(VAN, depth_m=2.9)])
    assert _spf(sim, "Fly to the red van.", near)["depth"] == 0
    # nothing named is visible: the exploration point, travel = the depth there (no reading: 10)
    empty = frame("s3", [TREE], open_cols=(0, 40))
    ans = _spf(sim, "Fly to the red van.", empty)
    assert tuple(ans["point_2d"]) == exploration_point(empty.annotation.depth_m) and ans["depth"] == 10


def test_spf_zero_depth_follows_the_monitoring_stop_rule():
    model = dataclasses.replace(PRESETS["weak"], malformed_prob=0.0, miss_prob_small=0.0, miss_prob_far=0.0)
    sim = SimulatedVlm(model, seed=5)
    d = 3.5
    base = frame("z", [dataclasses.replace(VAN, depth_m=d)])
    stops = sum(_spf(sim, "fly to the red van", renamed(base, f"z{k}"))["depth"] == 0 for k in range(N))
    p = 0.5 * (1 + math.erf((model.stop_distance_m + model.stop_offset_m - d) / (model.stop_jitter_m * math.sqrt(2))))
    assert binomial_ok(stops, N, p)


def test_memoryless_leg_rule_moves_on_after_a_reached_leg():
    sim = SimulatedVlm("perfect", seed=0)
    instruction = "Fly to the oak tree, then stop at the red van."
    # only the first leg's target, far: aim at it
    t = frame("l1", [TREE])
    assert sim.leg_target(instruction, t, 0.0).leg == 0 and not sim.leg_target(instruction, t, 0.0).reached
    u, v = _spf(sim, instruction, t)["point_2d"]
    assert t.annotation.instance_ids[v, u] == TREE.iid
    # the first target is within the stop distance: explore for the second leg, never stop
    close_tree = frame("l2", [dataclasses.replace(TREE, depth_m=2.0)], open_cols=(120, 160))
    tgt = sim.leg_target(instruction, close_tree, 0.0)
    assert (tgt.leg, tgt.perception, tgt.reached) == (1, None, False)
    assert _spf(sim, instruction, close_tree)["depth"] > 0
    # the final target visible wins over an earlier one; close -> reached
    both = frame("l3", [TREE, dataclasses.replace(VAN, depth_m=2.5)])
    tgt = sim.leg_target(instruction, both, 0.0)
    assert tgt.final and tgt.reached and tgt.perception.named_id == VAN.iid
    # "go to it" refers back to the previous leg's target
    it = frame("l4", [VAN])
    tgt = sim.leg_target("There is a red van down the road. Go to it.", it, 0.0)
    assert tgt.final and tgt.perception.named_id == VAN.iid


def _pivot(sim, instruction, img, arrows, n_pick=3, **kw):
    from vlm.prompts import build_pivot_prompt

    return sim.complete(*build_pivot_prompt(instruction, img, arrows, n_pick), **kw)


def test_pivot_picks_the_arrows_nearest_to_its_target_and_stops_when_close():
    sim = SimulatedVlm("perfect", seed=0)
    img = frame("v1", [VAN])  # van anchor near (120, 70)
    arrows = [(1, 20.0, 60.0), (2, 118.0, 72.0), (3, 100.0, 50.0), (4, 150.0, 100.0), (5, 60.0, 60.0)]
    ua, va = 119, 69  # anchor of the VAN rectangle (nearest pixel to the centroid)
    order = sorted(arrows, key=lambda a: math.hypot(a[1] - ua, a[2] - va))
    ans = json.loads(_pivot(sim, "Fly to the red van.", img, arrows).text)
    assert ans == {"arrows": [a[0] for a in order[:3]]}
    near = frame("v2", [dataclasses.replace(VAN, depth_m=2.0)])
    assert json.loads(_pivot(sim, "Fly to the red van.", near, arrows).text) == {"stop": True}


def test_pivot_belief_is_one_per_frame_whatever_arrows_are_drawn():
    sim = SimulatedVlm(dataclasses.replace(PRESETS["noisy"], malformed_prob=0.0, format_variety_prob=0.0), seed=2)
    img = frame("b1", [VAN])
    grid = [(u, v) for u in range(5, W, 10) for v in range(5, H, 10)]
    a = [(k + 1, float(u), float(v)) for k, (u, v) in enumerate(grid)]
    b = [(len(grid) - k, float(u), float(v)) for k, (u, v) in enumerate(grid)]  # same endpoints, other numbers
    pick_a = json.loads(_pivot(sim, "fly to the red van", img, a, 1).text)["arrows"][0]
    pick_b = json.loads(_pivot(sim, "fly to the red van", img, b, 1).text)["arrows"][0]
    assert a[pick_a - 1][1:] == b[len(grid) - pick_b][1:]


def test_pivot_malformed_rate_matches_preset():
    model = PRESETS["noisy"]
    sim = SimulatedVlm(model, seed=4)
    base = frame("m", [VAN])
    arrows = [(1, 20.0, 60.0), (2, 118.0, 72.0)]
    from onfly.baselines.pivot import parse_pivot_answer  # the PIVOT baseline's own reader

    bad = sum(
        not parse_pivot_answer(_pivot(sim, "fly to the red van", renamed(base, f"m{k}"), arrows).text, (1, 2)).ok
        for k in range(N)
    )
    assert binomial_ok(bad, N, model.malformed_prob)


def _typefly(sim, instruction, img, objects, history=()):
    from vlm.prompts import build_typefly_prompt

    return sim.complete(*build_typefly_prompt(instruction, img, objects, list(history))).text


def test_typefly_programs_follow_the_scene_description():
    from vlm.prompts import SceneObject

    sim = SimulatedVlm("perfect", seed=0)
    van = SceneObject("red van", "van", 0.75, 0.58, 0.25, 0.33)
    img = frame("y1", [VAN])
    assert _typefly(sim, "Fly to the red delivery van.", img, [van]) == "approach red van"
    # the detector missed it: search, then move on after a failed search
    assert _typefly(sim, "Fly to the red van.", img, []) == "find Fly to the red van"
    assert _typefly(sim, "Fly to the red van.", img, [], ["find Fly to the red van: not found"]) == "move_forward 3; find Fly to the red van"
    # reached is judged on the frame, with or without a detection
    near = frame("y2", [dataclasses.replace(VAN, depth_m=2.0)])
    assert _typefly(sim, "Fly to the red van.", near, [van]) == "stop"
    assert _typefly(sim, "Fly to the red van.", near, []) == "stop"
    # a detection the frame does not show (a false box) is approached all the same
    assert _typefly(sim, "Fly to the red van.", frame("y3", [TREE]), [van]) == "approach red van"


def test_baseline_prompts_cost_the_decision_latency():
    from vlm.prompts import build_spf_prompt

    sim = SimulatedVlm("nominal", seed=0, latency=LatencyModel(decision_s=0.5))
    img = frame("lat", [VAN])
    assert sim.complete(*build_spf_prompt("go to the van", img)).latency_s == 0.5
    assert _pivot(sim, "go to the van", img, [(1, 3.0, 3.0)]).latency_s == 0.5
    from vlm.prompts import build_typefly_prompt

    r = sim.complete(*build_typefly_prompt("go to the van", img, [], []))
    assert r.latency_s == 0.5 and r.status is CallStatus.OK


FORKLIFT = Obj(11, "yellow forklift", "forklift", 12.0, rect=(10, 40, 50, 90))
PUMP = Obj(12, "fuel pump", "pump", 12.0, rect=(110, 40, 130, 90))
LEGS = "turn left at the yellow forklift and stop in front of the fuel pump"


def test_decision_reads_a_multi_clause_subtask_as_legs():
    """The decision prompt follows the leg rule of the baselines: the last leg's target when
    seen, else the furthest seen leg not yet reached; "not visible" when nothing named is seen
    or the seen leg is reached and the next leg's target is unseen."""
    sim = SimulatedVlm("perfect", seed=0)

    def pointed(img):
        res = parse_point(decide(sim, LEGS, img).text, img.size)
        if res.not_visible:
            return "not visible"
        u, v = (int(round(c)) for c in res.uv)
        return int(img.annotation.instance_ids[v, u])

    assert pointed(frame("d1", [FORKLIFT, PUMP])) == PUMP.iid  # the last leg's target wins
    assert pointed(frame("d2", [FORKLIFT])) == FORKLIFT.iid  # an intermediate landmark, far
    assert pointed(frame("d3", [dataclasses.replace(FORKLIFT, depth_m=2.0)])) == "not visible"  # reached
    assert pointed(frame("d4", [TREE])) == "not visible"
    # a trailing bare "then stop" closes the leg before it (it is not a leg naming nothing)
    assert pointed(frame("d5", [dataclasses.replace(FORKLIFT, depth_m=2.0)])) == "not visible"
    gate = Obj(13, "wooden gate", "gate", 2.0, rect=(60, 40, 100, 90))
    img = frame("d6", [gate])
    res = parse_point(decide(sim, "go through the wooden gate then stop", img).text, img.size)
    assert img.annotation.instance_ids[int(res.uv[1]), int(res.uv[0])] == gate.iid
    assert SimulatedVlm._legs("go through the wooden gate then stop") == ["go through the wooden gate then stop"]
    assert SimulatedVlm._legs(LEGS) == ["turn left at the yellow forklift", "stop in front of the fuel pump"]
    # a statement after the last step is no leg (its "coffee" is no target); one before a step is
    assert SimulatedVlm._legs("Where's the fuel pump? I could really use a coffee.") == ["Where's the fuel pump"]
    assert SimulatedVlm._legs("There's a fuel pump by the road. Go to it.") == ["There's a fuel pump by the road", "Go to it"]
    # a leg naming no object is flown into open space; its later leg's target still counts
    open_img = frame("d7", [TREE], open_cols=(0, 10))
    assert json.loads(decide(sim, "fly forward, then stop at the fuel pump", open_img).text)["target_visible"] is True


def test_monitoring_judges_completion_on_the_last_leg():
    """The landmark of an earlier leg never completes the subtask (it used to: the earliest
    named object was grounded)."""
    sim = SimulatedVlm("perfect", seed=0)
    status = lambda frames: parse_status(monitor(sim, LEGS, frames).text).status  # noqa: E731
    near_forklift = frame("m1", [dataclasses.replace(FORKLIFT, depth_m=1.5), PUMP])
    assert status([near_forklift, near_forklift]) is MonitorStatus.CONTINUE
    near_pump = frame("m2", [FORKLIFT, dataclasses.replace(PUMP, depth_m=2.0)])
    assert status([near_forklift, near_pump]) is MonitorStatus.STOP
    # the forklift passed out of view: not LOST (it is not the subtask's target) ...
    only_tree = frame("m3", [TREE])
    forklift_only = frame("m1b", [dataclasses.replace(FORKLIFT, depth_m=1.5)])
    assert status([forklift_only, only_tree, only_tree]) is MonitorStatus.CONTINUE
    # ... the pump seen and then gone is
    far_pump = frame("m4", [PUMP])
    assert status([far_pump, only_tree, only_tree]) is MonitorStatus.LOST
    # "it" is the object the previous leg names last, even after a landmark passed
    last = "head down the lane past the oak tree until you see the yellow forklift, then stop next to it"
    both_near = frame("m6", [dataclasses.replace(TREE, depth_m=1.0), dataclasses.replace(FORKLIFT, depth_m=20.0)])
    assert parse_status(monitor(sim, last, [both_near, both_near]).text).status is MonitorStatus.CONTINUE
    assert sim.leg_target(last, both_near, 0.0).perception.named_id == FORKLIFT.iid
    # a leg whose first reference points back: the rest only says where to stand
    aside = "fly to the yellow forklift and stop beside it, across from the fuel pump"
    assert parse_status(monitor(sim, aside, [near_forklift, near_forklift]).text).status is MonitorStatus.STOP
    # "stop next to it" refers back: completion on the forklift
    back = "find the yellow forklift and stop next to it"
    assert parse_status(monitor(sim, back, [near_forklift, near_forklift]).text).status is MonitorStatus.STOP
    # "hover next to the wall clock" next to a wall, the clock unseen: never STOP
    wall = frame("m5", [Obj(14, "wall", "wall", 0.8, rect=(0, 0, 160, 120))])
    assert parse_status(monitor(sim, "hover next to the wall clock", [wall, wall]).text).status is MonitorStatus.CONTINUE


def test_every_prompt_grounds_the_same_way():
    """SPF, PIVOT and TypeFly read the same legs, heads and target flags as OnFly's prompts."""
    from vlm.prompts import SceneObject
    from vlm.sim.backend import scene_objects_as_visible

    sim = SimulatedVlm("perfect", seed=0)
    wall = Obj(14, "wall", "wall", 0.8, rect=(0, 0, 160, 120))
    img = frame("e1", [wall])
    tgt = sim.leg_target("hover next to the wall clock", img, 0.0)
    assert tgt.perception is None and not tgt.reached
    assert _spf(sim, "hover next to the wall clock", img)["depth"] > 0  # never "reached" at the wall
    car = Obj(2, "parked car 3", "car", 1.0, rect=(10, 40, 80, 90), target=False)
    img = frame("e2", [car])
    objs, _ = scene_objects_as_visible([SceneObject("parked car 3", "car", 0.3, 0.5, 0.4, 0.4)], img.annotation)
    assert objs[1].target is False
    assert _typefly(sim, "Fly to the car.", img, [SceneObject("parked car 3", "car", 0.3, 0.5, 0.4, 0.4)]).startswith("find")
