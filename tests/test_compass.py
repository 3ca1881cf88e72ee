"""Compass headings in an instruction (vlm.compass): headings, not names; ENU yaws."""

import math

import pytest

from vlm.compass import COMPASS_YAWS, compass_heading, compass_headings

E, N, W, S = 0.0, math.pi / 2, math.pi, -math.pi / 2


@pytest.mark.parametrize(
    "text, yaw",
    [
        ("Fly east along the row of parked cars past the red car", E),
        ("follow the hallway west and stop next to the plant in the big bedroom", W),
        ("Head back west along the south aisle, past the level sign", W),  # "south aisle" is a name
        ("Go past the pavilion, then keep flying north and stop beside the tree", N),
        ("fly northward for 20 m", N),
        ("Head north-east.", math.pi / 4),
        ("fly 20 m south", S),
        ("Go southwest until you see the fountain", -3 * math.pi / 4),
        ("Fly eastwards, then stop at the gate", E),
    ],
)
def test_a_compass_word_that_ends_its_phrase_is_a_heading_in_the_enu_frame(text, yaw):
    assert compass_heading(text) == pytest.approx(yaw)


@pytest.mark.parametrize(
    "text",
    [
        "follow the north aisle under the duct past the fire hose cabinet",  # an aisle, named
        "Fly to the white car in the north row",
        "stop at the south entrance",
        "fly to the north of the fountain",  # where, not which way
        "hover by the north-facing window",
        "Find the red crate.",
        "the Northampton sign",  # a word that begins with a compass word is no compass word
        "fly east, then turn north",  # the route bends: no one heading
        "go west and then back east",
    ],
)
def test_names_places_and_bent_routes_give_no_heading(text):
    assert compass_heading(text) is None


def test_every_heading_is_read_in_order_and_agreeing_ones_give_the_first():
    assert compass_headings("fly north, then north-east along the wall") == pytest.approx([N, math.pi / 4])
    assert compass_heading("fly north, then north-east along the wall") == pytest.approx(N)
    assert compass_headings("the north aisle") == []


def test_the_compass_rose_is_counter_clockwise_from_east():
    for word, yaw in COMPASS_YAWS.items():
        assert -math.pi < yaw <= math.pi
        assert compass_heading(f"fly {word}") == pytest.approx(yaw), word
    # opposite words are half a turn apart
    for a, b in (("north", "south"), ("east", "west"), ("northeast", "southwest"), ("northwest", "southeast")):
        assert abs(math.remainder(COMPASS_YAWS[a] - COMPASS_YAWS[b], 2 * math.pi)) == pytest.approx(math.pi)
