"""Turns that open an instruction (vlm.turns): now or at a place; angles counter-clockwise."""

import json
import math
import re
from pathlib import Path

import pytest

from vlm.turns import opening_turn

L, R, U = math.pi / 2, -math.pi / 2, math.pi
R2R = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "instructions" / "R2R_val_unseen.json"


@pytest.mark.parametrize(
    "text, angle",
    [
        ("Turn around and head down to the elevator lobby, then go up the other hallway", U),
        ("turn right into the small meeting room and stop by the round table", R),
        ("Now turn around, walk past the first door", U),
        ("Turn to your left and fly to the sofa", L),
        ("Turn toward your left and walk to the grey fence", L),
        ("turn hard left toward the dining area", L),
        ("Take a sharp left. Walk under the chandelier", L),
        ("make a right.", R),
        ("do a u-turn and go back to the car", U),
        ("turn back to the door", U),
        ("Turn around 180 degrees.  Go through the open door", U),
        ("Turn 90 degrees right.  Go around the table", R),
        ("turn left 45 degrees and fly on", math.radians(45)),
        ("turn the drone around and fly to the gate", U),
        ("About-face, then fly to the bench", U),
        ("Turn right", R),
    ],
)
def test_a_turn_made_where_the_vehicle_is_opens_the_text(text, angle):
    assert opening_turn(text) == pytest.approx(angle)


@pytest.mark.parametrize(
    "text",
    [
        "turn left at the elevators",  # at a place the decision agent will see
        "Take a right after the door",
        "Turn right when you reach the desk",
        "turn right at the end of the hall",
        "turn around the corner and stop",
        "fly to the door and turn left",  # not the opening words
        "TURN SLIGHTLY TO THE RIGHT AND WALK THROUGH THE DOOR",  # the way stays in view
        "Turn and walk out of the room",  # no side, no half turn
        "Find the red crate.",
        "turnstile by the gate",
        "",
    ],
)
def test_turns_at_a_place_later_words_and_no_turn_give_none(text):
    assert opening_turn(text) is None


def test_every_r2r_instruction_that_opens_with_a_plain_turn_around_is_a_half_turn():
    # real instructions (R2R val-unseen): "Turn around" then a comma, "and" or a full stop
    instructions = [i.strip() for e in json.loads(R2R.read_text()) for i in e["instructions"]]
    plain = [i for i in instructions if re.match(r"(?i)turn around\s*(,|\.|and\b)", i)]
    assert len(plain) > 100
    assert all(opening_turn(i) == pytest.approx(U) for i in plain)
    sides = [i for i in instructions if re.match(r"(?i)turn (left|right)\s*(,|\.|and\b|into\b)", i)]
    assert len(sides) > 50
    for i in sides:
        assert opening_turn(i) == pytest.approx(L if i.lower().startswith("turn left") else R), i
