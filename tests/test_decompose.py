"""Task decomposition: the fallback splitter on real human instructions, and the VLM path."""

from __future__ import annotations

import json
import re

import pytest

from vlm.decompose import (
    CONNECTIVE_WORDS,
    MOVEMENT_VERBS,
    attach_back_references,
    attach_context,
    attach_clauses,
    DecompositionError,
    count_steps,
    decompose,
    decompose_detailed,
    split_instruction,
)
from vlm.prompts import parse_prompt
from vlm.sim.grounding import names_target
from vlm.sim import SimulatedVlm
from vlm.types import CallStatus, Usage, VlmConnectionError, VlmResponse
from realdata_paths import REALDATA

R2R = REALDATA / "instructions" / "R2R_val_unseen.json"


def _content_words(text: str) -> list[str]:
    return [w for w in re.findall(r"\w+", text.lower()) if w not in CONNECTIVE_WORDS]


def _r2r_instructions() -> list[str]:
    paths = json.loads(R2R.read_text())
    return [ins for path in paths for ins in path["instructions"]]


def test_fallback_on_every_r2r_instruction_is_ordered_nonempty_and_covers_the_text():
    instructions = _r2r_instructions()
    assert len(instructions) == 2349
    n_multi = 0
    for ins in instructions:
        parts = split_instruction(ins)
        assert parts, ins
        assert all(p == p.strip() and re.search(r"\w", p) for p in parts), parts
        # together, in order, the subtasks hold exactly the instruction's words (connectives aside)
        assert [w for p in parts for w in _content_words(p)] == _content_words(ins), ins
        # each subtask is a contiguous piece of the instruction, in order
        pos = 0
        flat = " ".join(ins.split())
        for p in parts:
            found = flat.find(p, pos)
            assert found >= pos, (p, ins)
            pos = found + len(p)
        n_multi += len(parts) > 1
    assert n_multi > 0.9 * len(instructions)


def test_r2r_closing_clauses_are_cut():
    """Every R2R "... and stop/wait <where>" after a clause that names something closes a leg of
    its own: the subtask that holds the closing verb starts with it (R2R phrases it "and stop
    at ...", "and wait by ...")."""
    n = 0
    for ins in _r2r_instructions():
        flat = " ".join(ins.split())
        for m in re.finditer(r"\b(?:and|And) (stop|wait) ([a-z]+)", flat):
            before = re.findall(r"[^\W_]+", flat[: m.start()].lower())
            if before and before[-1] in MOVEMENT_VERBS:
                continue  # "stop and wait there", "go and stop in ...": one clause
            if m.group(2) in ("there", "here", "for"):
                continue  # "... and wait there": closes the same leg
            if not names_target(re.split(r"[.;,!?]|\bthen\b", flat[: m.start()])[-1]):
                continue  # "turn left and wait near the couch": the clause before names nothing
            n += 1
            parts = split_instruction(ins)
            head = f"{m.group(1)} {m.group(2)}"
            assert any(p.startswith(head) or p.lower().startswith(f"and {head}") for p in parts), (ins, parts)
    assert n > 250  # R2R closes many paths this way (272 since rooms and areas are places)


@pytest.mark.parametrize(
    "instruction,expected",
    [
        ("Fly through the gate, then stop next to the red van.", ["Fly through the gate", "stop next to the red van"]),
        ("Walk to the stairs, turn right and go down. Stop by the mirror.", ["Walk to the stairs", "turn right and go down", "Stop by the mirror"]),
        ("Go up 2.5 m; after that fly to the tree", ["Go up 2.5 m", "fly to the tree"]),
        ("Once you reach the top, turn left. Wait.", ["Once you reach the top, turn left", "Wait"]),
        ("At the landing, turn right, and go down the stairs.", ["At the landing, turn right", "go down the stairs"]),
        ("Walk down the hallway.Go into the room", ["Walk down the hallway", "Go into the room"]),
        ("fly to the van and then land", ["fly to the van", "land"]),
        ("Then stop.", ["stop"]),
        ("hover", ["hover"]),
        # closing clauses (rule 4): "and <stop|land|hover|...> <more words>"
        ("turn left at the yellow forklift and stop in front of the fuel pump",
         ["turn left at the yellow forklift", "stop in front of the fuel pump"]),
        ("Fly past the gate, and land next to the bench.", ["Fly past the gate", "land next to the bench"]),
        ("Walk past the sofa and wait by the door.", ["Walk past the sofa", "wait by the door"]),
        ("Go to the end of the corridor and stop about a metre from the window.",
         ["Go to the end of the corridor and stop about a metre from the window"]),  # the corridor's end is no target
        ("Follow the row to the charging station and end at the cart corral.",
         ["Follow the row to the charging station", "end at the cart corral"]),
        ("go to the bench then hover in front of the fountain", ["go to the bench", "hover in front of the fountain"]),
        ("Fly over to the operator panel and stop.", ["Fly over to the operator panel and stop"]),  # nothing after
        ("Stop and wait by the door.", ["Stop and wait by the door"]),  # one word before "and"
        # the clause before names nothing to reach: cutting would leave a subtask no monitor completes
        ("Fly back past the snack machine, then keep going and stop at the blue door.",
         ["Fly back past the snack machine", "keep going and stop at the blue door"]),
        ("after that, go on and stop next to the man in blue", ["go on and stop next to the man in blue"]),
        ("Go past the pavilion, then keep flying north and stop beside the tree.",
         ["Go past the pavilion", "keep flying north and stop beside the tree"]),
        ("Walk past the couch and end table.", ["Walk past the couch and end table"]),  # "end table" is a noun
        ("Fly to the panel, then over to the robot arm, and finally stop at the hydraulic press.",
         ["Fly to the panel", "over to the robot arm", "finally stop at the hydraulic press"]),
        ("Go past the landing and hovering drone.", ["Go past the landing and hovering drone"]),  # whole words only
        # route verbs of rule 3 beyond go / fly / turn: come, cut, duck, ...
        ("Go past the cement mixer, fly in under the concrete slab, and come out the other side to the blue container.",
         ["Go past the cement mixer", "fly in under the concrete slab", "come out the other side to the blue container"]),
        ("Go around the end of the scaffolding, cut under the concrete slab, and stop at the yellow skip.",
         ["Go around the end of the scaffolding", "cut under the concrete slab", "stop at the yellow skip"]),
        ("Go past the wheelchair ramp, duck under the platform to the blue sofa, then stop at the door.",
         ["Go past the wheelchair ramp", "duck under the platform to the blue sofa", "stop at the door"]),
    ],
)
def test_fallback_examples(instruction, expected):
    assert split_instruction(instruction) == expected


@pytest.mark.parametrize("bad", ["", "   ", "...", " ; , ", "_"])
def test_instruction_without_words_is_an_error(bad):
    with pytest.raises(DecompositionError, match="no words"):
        split_instruction(bad)
    with pytest.raises(DecompositionError, match="no words"):
        decompose(bad)


def test_non_string_instruction_is_an_error():
    with pytest.raises(DecompositionError, match="must be a str"):
        decompose(42)  # type: ignore[arg-type]


class _FakeBackend:
    """A backend answering every call with a fixed response; records the calls."""

    name = "fake"

    def __init__(self, response: VlmResponse | Exception) -> None:
        self.response = response
        self.calls: list[dict] = []

    def complete(self, messages, images=(), **kw):
        self.calls.append({"messages": messages, "images": images, **kw})
        if isinstance(self.response, Exception):
            raise self.response
        return self.response

    def features(self, image):
        return None

    def close(self):
        pass


def test_vlm_answer_is_used_when_it_parses():
    fake = _FakeBackend(VlmResponse(CallStatus.OK, text='```json\n["take off", "fly to the red van", "land"]\n```', usage=Usage(10, 5)))
    result = decompose_detailed("Take off and fly to the red van, then land.", fake, deadline_s=5.0)
    # "land" closes the van's subtask; "take off" names nothing to reach: the first leg of it
    assert result.source == "vlm" and result.subtasks == ("take off, fly to the red van, land",)
    call = fake.calls[0]
    assert parse_prompt(call["messages"]).instruction == "Take off and fly to the red van, then land."
    assert call["deadline_s"] == 5.0 and call["json_schema"]["type"] == "array" and call["images"] == []


@pytest.mark.parametrize(
    "response,reason",
    [
        (VlmResponse(CallStatus.TIMEOUT, error="deadline"), "timeout"),
        (VlmResponse(CallStatus.ERROR, error="HTTP 500"), "error: HTTP 500"),
        (VlmResponse(CallStatus.OK, text="Sure! Here are the subtasks:"), "parse: no JSON list"),
        (VlmResponse(CallStatus.OK, text="[]"), "parse: empty"),
        (VlmConnectionError("refused"), "backend raised: refused"),
    ],
)
def test_failed_calls_fall_back_to_the_splitter(response, reason):
    instruction = "Fly through the gate, then stop next to the red van."
    result = decompose_detailed(instruction, _FakeBackend(response))
    assert result.source == "fallback" and reason in result.reason
    assert list(result.subtasks) == split_instruction(instruction)


def test_no_backend_uses_the_splitter():
    assert decompose("Fly up; land") == ["Fly up, land"]  # "land" only closes the subtask before it
    assert decompose_detailed("Fly up; land").reason == "no backend"


def test_with_the_perfect_simulated_vlm():
    with SimulatedVlm("perfect", seed=1) as sim:
        result = decompose_detailed("Fly through the gate, then stop next to the red van.", sim)
    assert result.source == "vlm"
    assert result.subtasks == ("Fly through the gate", "stop next to the red van")
    assert result.response.latency_s == pytest.approx(3.0)


def test_truncated_simulated_answer_falls_back():
    with SimulatedVlm("perfect") as sim:
        result = decompose_detailed("Fly through the gate, then stop next to the red van.", sim, max_new_tokens=3)
    assert result.source == "fallback" and result.reason.startswith("parse:")
    assert list(result.subtasks) == ["Fly through the gate", "stop next to the red van"]


# -- back-references ---------------------------------------------------------------------------


def test_a_subtask_that_only_refers_back_is_joined_to_the_one_before():
    text = "There's a vending machine somewhere along this corridor. Go to it."
    assert split_instruction(text) == ["There's a vending machine somewhere along this corridor", "Go to it"]
    assert decompose(text) == ["There's a vending machine somewhere along this corridor, Go to it"]
    got = attach_back_references(["fly to the red car", "stop there", "land right next to it", "turn left"])
    assert got == ("fly to the red car, stop there, land right next to it", "turn left")
    # a subtask that only closes the one before it names nothing a monitor could complete
    assert attach_back_references(["go through the gate", "stop", "fly up", "then land"]) == ("go through the gate, stop", "fly up, then land")
    assert attach_back_references(["stop", "fly to the bench"]) == ("stop", "fly to the bench")
    # the first reference points back; the rest only says where to stand
    assert decompose("Fly to the blue bin and stop beside it, across from office 105.") == [
        "Fly to the blue bin, stop beside it, across from office 105"
    ]
    assert attach_back_references(["fly to the tree", "go to that door"]) == ("fly to the tree", "go to that door")
    assert attach_back_references(["fly to the tree", "land near that, by the bench"]) == ("fly to the tree, land near that, by the bench",)
    # the speaker is no target: "take me there" points back, "take me to the desk" names a desk
    assert decompose("Where's the ice machine on this floor? Take me there.") == ["Where's the ice machine on this floor, Take me there"]
    assert attach_back_references(["find the bench", "take us to it"]) == ("find the bench, take us to it",)
    assert attach_back_references(["fly to the tree", "take me to the reception desk"]) == ("fly to the tree", "take me to the reception desk")
    # a distance says where to stand, not what to reach
    assert decompose("Find the fuel pump and hover about a metre above it.") == ["Find the fuel pump, hover about a metre above it"]
    assert attach_back_references(["fly to the bench", "land 2 m in front of it"]) == ("fly to the bench, land 2 m in front of it",)


@pytest.mark.parametrize(
    "subtasks",
    [
        ["fly to the tree", "go to that door"],  # "that" with a noun names a new target
        ["go to it", "fly to the bench"],  # the first subtask has nothing to refer to
        ["fly to the tree", "turn left"],
        ["fly to the tree", "then ascend to the roof"],
    ],
)
def test_subtasks_that_name_a_target_are_kept_apart(subtasks):
    assert attach_back_references(subtasks) == tuple(subtasks)


def test_back_references_in_a_model_answer_are_attached_and_no_word_is_lost():
    fake = _FakeBackend(VlmResponse(CallStatus.OK, text='["find the blue sofa", "fly up to it", "land on the roof"]', usage=Usage(10, 5)))
    dec = decompose_detailed("find the blue sofa and fly up to it, then land on the roof", fake)
    assert dec.source == "vlm"
    assert dec.subtasks == ("find the blue sofa, fly up to it", "land on the roof")
    assert re.findall(r"\w+", " ".join(dec.subtasks)) == re.findall(r"\w+", "find the blue sofa fly up to it land on the roof")


def test_a_subtask_about_a_part_of_the_previous_target_is_joined_to_it():
    """``stop in front of its middle`` alone names nothing: asked alone, the door it belongs to
    is in no prompt (``factory_hall-p03`` flew 15 m along the wall for it). A possessive that
    opens the subtask's references points back as ``it`` does; one after a noun of its own
    (``follow the assembly line to its end``) does not."""
    from vlm.decompose import opens_with_back_reference

    assert opens_with_back_reference("stop in front of its middle")
    assert opens_with_back_reference("hover next to their entrance")
    assert not opens_with_back_reference("follow the assembly line to its end")
    assert attach_back_references(["Fly to the large roller door", "stop in front of its middle"]) == (
        "Fly to the large roller door, stop in front of its middle",
    )
    assert decompose_detailed("Fly to the large roller door and stop in front of its middle.", None).subtasks == (
        "Fly to the large roller door, stop in front of its middle",
    )


def test_a_scene_setting_statement_is_joined_to_the_subtask_after_it():
    text = "You're at the end of the hall. Fly back past the snack machine, then stop at the blue door."
    assert decompose(text) == ["You're at the end of the hall, Fly back past the snack machine", "stop at the blue door"]
    # a statement with a movement verb asks for something and stays; one with nothing after it stays
    assert attach_context(["There is a tree, fly to it", "land"]) == ("There is a tree, fly to it", "land")
    # what the speaker wants is context too, unless it asks for a movement
    assert decompose("I need a coffee. Take me to the counter in the café.") == ["I need a coffee, Take me to the counter in the café"]
    assert decompose("I\u2019d like to buy postcards. Find the postcard stand.") == ["I\u2019d like to buy postcards, Find the postcard stand"]
    assert attach_context(["I'd like to go to the gate", "stop there"]) == ("I'd like to go to the gate", "stop there")
    assert decompose("I'm at the fish stall. Go east along the quay to the stacked crates.") == [
        "I'm at the fish stall, Go east along the quay to the stacked crates"
    ]
    # a statement after the last step is no step: it joins the one before it
    assert attach_context(["fly to the tree", "There is a bench"]) == ("fly to the tree, There is a bench",)
    assert decompose("Where's the vending machine? I could really use a coffee.") == ["Where's the vending machine, I could really use a coffee"]
    assert attach_context(["There are two cars", "You're near the gate", "go to the gate"]) == (
        "There are two cars, You're near the gate, go to the gate",
    )


def test_a_subtask_that_names_nothing_to_reach_is_the_first_leg_of_the_next():
    """A way, not a place (``leave the study``, ``follow the hallway west``, ``turn left``): no
    monitor can see it done except by arriving where the next subtask begins, so it is joined
    to the next one; the last one stays; words and order are kept."""
    from vlm.decompose import attach_transit

    subs = ["Leave the study", "go past the ironing board in the laundry room", "follow the hallway west",
            "turn left", "stop next to the plant in the big bedroom"]
    assert attach_transit(subs) == (
        "Leave the study, go past the ironing board in the laundry room",
        "follow the hallway west, turn left, stop next to the plant in the big bedroom",
    )
    assert attach_transit(["fly to the red van", "fly forward"]) == ("fly to the red van", "fly forward")
    assert attach_transit(["turn left"]) == ("turn left",)
    assert attach_transit(["go to the kitchen table", "leave the kitchen"]) == ("go to the kitchen table", "leave the kitchen")
    # every decomposition gets the rule, the model's and the fallback's
    ins = "Leave the study, go past the ironing board in the laundry room, follow the hallway west and stop next to the plant in the big bedroom."
    assert decompose_detailed(ins, None).subtasks == (
        "Leave the study, go past the ironing board in the laundry room",
        "follow the hallway west and stop next to the plant in the big bedroom",
    )


@pytest.mark.parametrize(
    "instruction, steps",
    [
        ("Find the red crate.", 1),
        ("Find the green forklift and stop next to it.", 1),  # the closing clause points back
        ("There's a traffic cone in one of the aisles. Go to it.", 1),  # context, then a back-reference
        ("Leave the study, then go to the ironing board.", 1),  # a way with nothing to reach joins the next
        ("Fly to the blue barrel, then find the red crate.", 2),
        ("Turn left at the yellow forklift and stop in front of the fuel pump.", 2),
    ],
)
def test_count_steps_is_the_deterministic_reading_after_attaching_clauses(instruction, steps):
    assert count_steps(instruction) == steps
    assert count_steps(instruction) == len(attach_clauses(split_instruction(instruction)))
