"""Parsers: a corpus of realistic model outputs per format, and fuzzing for totality and bounds."""

from __future__ import annotations

import json
import math
import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from vlm.parsing import (
    MAX_TEXT_CHARS,
    CoordFormat,
    MonitorStatus,
    PointOutcome,
    parse_point,
    parse_point_depth,
    parse_status,
    parse_subtasks,
)

W, H = 640, 480

# (text, kwargs, expected uv) -- answers shaped like real models' output
POINT_CORPUS = [
    # our prompt's contract: JSON point_2d in pixels of the image as given
    ('{"point_2d": [320, 240]}', {}, (320, 240)),
    ('{"point_2d":[12,470]}', {}, (12, 470)),
    ('```json\n{"point_2d": [101, 57]}\n```', {}, (101, 57)),
    ('```\n{"point_2d": [101, 57]}\n```\nThis is the door.', {}, (101, 57)),
    ('The red van is on the left. {"point_2d": [88, 300]} I chose its side.', {}, (88, 300)),
    ('{"point": [5, 6]}', {}, (5, 6)),
    ('{"x": 330, "y": 111}', {}, (330, 111)),
    ('{"y": 111, "x": 330}', {"order": "yx"}, (330, 111)),  # named values are never swapped
    ('{"point_2d": ["320", "240"]}', {}, (320, 240)),
    ('{"point_2d": [320.6, 240.2]}', {}, (320.6, 240.2)),
    ('{"answer": {"point_2d": [40, 50]}}', {}, (40, 50)),
    # Qwen2.5-VL grounding lists (first point taken)
    ('[{"point_2d": [100, 200], "label": "van"}, {"point_2d": [300, 400], "label": "van"}]', {}, (100, 200)),
    ('```json\n[\n  {"bbox_2d": [100, 200, 300, 400], "label": "gate"}\n]\n```', {}, (200, 300)),
    ('{"points": [[10, 20], [30, 40]]}', {}, (10, 20)),
    ("[320, 240]", {}, (320, 240)),
    ("[[50, 60], [70, 80]]", {}, (50, 60)),
    # Qwen2.5-VL absolute pixels of the resized input (e.g. 1280x720 resized to 644x364 -> here 640x480 from 320x240)
    ('{"point_2d": [160, 120]}', {"coord_format": "resized_pixel", "model_input_size": (320, 240)}, (320.5, 240.5)),
    ('{"point_2d": [0, 0]}', {"coord_format": "resized_pixel", "model_input_size": (320, 240)}, (0.5, 0.5)),
    # Qwen3-VL 0..1000 relative
    ('{"point_2d": [500, 500]}', {"coord_format": "rel1000"}, (319.5, 239.5)),
    ('{"point_2d": [0, 1000]}', {"coord_format": CoordFormat.REL1000}, (0.0, 479.0)),
    ('[{"bbox_2d": [0, 0, 1000, 1000], "label": "all"}]', {"coord_format": "rel1000"}, (319.5, 239.5)),
    # Gemini / SPF: [y, x] order, 0..1000
    ('[{"point": [250, 750], "label": "tree"}]', {"coord_format": "rel1000", "order": "yx"}, (0.75 * 639, 0.25 * 479)),
    ('{"box_2d": [0, 0, 500, 1000]}', {"coord_format": "rel1000", "order": "yx"}, (319.5, 0.25 * 479)),
    ("[120, 40]", {"order": "yx"}, (40, 120)),
    # Molmo XML, percent
    ('<points x1="50.0" y1="25.0" x2="10.0" y2="10.0" alt="chairs">chairs</points>', {"coord_format": "rel100"}, (319.5, 119.75)),
    ('<point x="10" y="20" alt="door">door</point>', {"coord_format": "rel100"}, (63.9, 95.8)),
    ("<point>120, 340</point>", {}, (120, 340)),
    ("<point>(120,340)</point>", {}, (120, 340)),
    # Qwen2-VL box tokens (0..1000)
    ("<|object_ref_start|>gate<|object_ref_end|><|box_start|>(100,200),(300,400)<|box_end|>", {"coord_format": "rel1000"}, (0.2 * 639, 0.3 * 479)),
    # prose
    ("The target is at (412, 233).", {}, (412, 233)),
    ("I would fly to (12.5, 7) and then to (30, 30).", {}, (12.5, 7)),
    ("Point: x = 300, y = 200", {}, (300, 200)),
    ("y: 200, x: 300", {}, (300, 200)),
    ("relative coordinates (0.5, 0.25)", {"coord_format": "rel1"}, (319.5, 119.75)),
    # JSON wins over prose when both are present
    ('It is near (1, 1). {"point_2d": [300, 300]}', {}, (300, 300)),
]


@pytest.mark.parametrize("text,kwargs,expected", POINT_CORPUS)
def test_point_corpus(text, kwargs, expected):
    res = parse_point(text, (W, H), **kwargs)
    assert res.ok, res.reason
    assert res.uv == pytest.approx(expected, abs=1e-9)
    assert res.raw == text
    assert res.reason == ""


# near misses that must fail, with a fragment of the reason
POINT_FAILURES = [
    ("", "no point"),
    ("I cannot determine a point in this image.", "no point"),
    ("The target is slightly to the left of the centre.", "no point"),
    ('{"point_2d": [320, ', "no point"),  # truncated
    ('{"point_2d": "left"}', "not a pair"),
    ('{"point_2d": [320]}', "not a pair"),
    ('{"point_2d": [320, 240, 3.5]}', "not a pair"),
    ('{"point_2d": [true, false]}', "not a pair"),
    ('{"point_2d": [640, 100]}', "outside"),  # x == W is past the last pixel
    ('{"point_2d": [-1, 100]}', "outside"),
    ('{"point_2d": [100, 480]}', "outside"),
    ('{"point_2d": [1e999, 1]}', "non-finite"),
    ('{"point_2d": ["NaN", 1]}', "non-finite"),
    ('{"point_2d": [NaN, 1]}', "non-finite"),
    ('{"bbox_2d": [1, 2, 3]}', "not four numbers"),
    ('```json\n{"label": "target"}\n```', "no point"),
    ("[1, 2, 3, 4]", "no point"),  # a bare box is not a point
    ("(12, )", "no point"),
    # first point outside: a failure, never the second point instead
    ('[{"point_2d": [900, 10]}, {"point_2d": [10, 10]}]', "first point"),
]


@pytest.mark.parametrize("text,reason", POINT_FAILURES)
def test_point_failures_keep_raw_text(text, reason):
    res = parse_point(text, (W, H))
    assert not res.ok
    assert res.uv is None
    assert res.raw == text
    assert reason in res.reason


def test_relative_range_is_closed_and_outside_fails():
    assert parse_point('{"point_2d": [1000, 1000]}', (W, H), "rel1000").uv == (W - 1, H - 1)
    res = parse_point('{"point_2d": [1001, 5]}', (W, H), "rel1000")
    assert not res.ok and "relative range" in res.reason


def test_pixel_inside_extent_is_clamped_within_border_pixel():
    res = parse_point('{"point_2d": [639.4, -0.4]}', (W, H))
    assert res.ok and res.uv == (639.0, 0.0)


def test_several_points_policy_first_and_all_candidates_kept():
    res = parse_point('{"points": [[10, 20], [30, 40], [5000, 1]]}', (W, H))
    assert res.uv == (10, 20)
    assert res.candidates == ((10, 20), (30, 40))
    assert res.source == "json:points"


def test_bad_configuration_is_a_failure_naming_the_argument():
    assert "model_input_size" in parse_point("[1, 2]", (W, H), "resized_pixel").reason
    assert "coord_format" in parse_point("[1, 2]", (W, H), "furlongs").reason
    assert "order" in parse_point("[1, 2]", (W, H), order="zx").reason
    assert "image_size" in parse_point("[1, 2]", (0, H)).reason
    assert "text must be str" in parse_point(None, (W, H)).reason  # type: ignore[arg-type]


def test_too_long_text_is_refused_unread():
    res = parse_point(" " * MAX_TEXT_CHARS + '{"point_2d": [1, 2]}', (W, H))
    assert not res.ok and "longer" in res.reason


def test_resized_pixel_maps_corners_inside():
    kw = {"coord_format": "resized_pixel", "model_input_size": (1000, 700)}
    top_left = parse_point("[0, 0]", (W, H), **kw).uv
    bottom_right = parse_point("[999, 699]", (W, H), **kw).uv
    assert top_left == (0.0, 0.0)
    assert bottom_right == (W - 1.0, H - 1.0)
    assert not parse_point("[1000, 10]", (W, H), **kw).ok


# ---------------------------------------------------------------------------------------------
# statuses

STATUS_CORPUS = [
    ("CONTINUE", MonitorStatus.CONTINUE),
    ("STOP", MonitorStatus.STOP),
    ("LOST", MonitorStatus.LOST),
    ("**STOP**", MonitorStatus.STOP),
    ("Status: stop.", MonitorStatus.STOP),
    ("lost", MonitorStatus.LOST),
    ("Continue\n", MonitorStatus.CONTINUE),
    ('{"status": "LOST"}', MonitorStatus.LOST),
    ("`STOP`", MonitorStatus.STOP),
    ("The van is right in front of the drone. STOP. STOP!", MonitorStatus.STOP),
    ("Answer: **Continue**.", MonitorStatus.CONTINUE),
]


@pytest.mark.parametrize("text,status", STATUS_CORPUS)
def test_status_corpus(text, status):
    res = parse_status(text)
    assert res.ok and res.status is status and res.raw == text


@pytest.mark.parametrize(
    "text,reason",
    [
        ("CONTINUE or STOP", "ambiguous"),
        ("I would not STOP; the target is LOST.", "ambiguous"),
        ("", "no status"),
        ("The drone is still approaching the target.", "no status"),
        ("STOPPED", "no status"),
        ("continuing", "no status"),
        ("Status:", "no status"),
    ],
)
def test_status_refusals(text, reason):
    res = parse_status(text)
    assert not res.ok and res.status is None and reason in res.reason and res.raw == text


@pytest.mark.parametrize(
    "text,seen",
    [
        ("LOST first", 0),
        ("LOST: first", 0),
        ("lost, first", 0),
        ("**LOST keyframe 2**", 2),
        ("Status: LOST (first frame).", 0),
        ("LOST. The target was last visible in key frame #3.", 3),
        ("LOST keyframe1", 1),
        ('{"status": "LOST", "last_seen": "first"}', 0),
        ('```json\n{"status": "LOST", "last_seen": "keyframe 3"}\n```', 3),
        ("LOST", None),
        ('{"status": "LOST", "last_seen": null}', None),
        ('{"status": "LOST", "last_seen": "the hallway"}', None),
        ("First, the drone is LOST.", None),  # "first" as a word of the sentence names no image
    ],
)
def test_lost_names_the_image_that_last_showed_the_target(text, seen):
    res = parse_status(text, n_keyframes=3)
    assert res.ok and res.status is MonitorStatus.LOST and res.seen_image == seen and res.reason == ""


@pytest.mark.parametrize(
    "text,reason",
    [
        ("LOST keyframe 4", "keyframe 4 of 3"),  # beyond what the prompt held
        ("LOST keyframe 0", "keyframe 0"),
        ("LOST first frame, or keyframe 2", "ambiguous"),
        ('{"status": "LOST", "last_seen": "keyframe 9"}', "keyframe 9 of 3"),
    ],
)
def test_a_place_that_is_not_one_image_of_the_prompt_is_dropped_and_the_lost_kept(text, reason):
    res = parse_status(text, n_keyframes=3)
    assert res.ok and res.status is MonitorStatus.LOST and res.seen_image is None and reason in res.reason


@pytest.mark.parametrize("text", ["STOP first", "CONTINUE keyframe 2", '{"status": "CONTINUE", "last_seen": "first"}'])
def test_only_a_lost_names_a_place(text):
    res = parse_status(text, n_keyframes=3)
    assert res.ok and res.status is not MonitorStatus.LOST and res.seen_image is None


# ---------------------------------------------------------------------------------------------
# point + depth, subtasks


@pytest.mark.parametrize(
    "text,uv,depth",
    [
        ('{"point_2d": [320, 240], "depth": 3.5}', (320, 240), 3.5),
        ('{"point": [320, 240], "depth_m": "4 m"}', (320, 240), 4.0),
        ('{"point_2d": [320, 240, 2.0]}', (320, 240), 2.0),
        ("Fly to (100, 50), depth: 6.5 m", (100, 50), 6.5),
        ("Target at (100, 50), about 7 meters away.", (100, 50), 7.0),
    ],
)
def test_point_depth_corpus(text, uv, depth):
    res = parse_point_depth(text, (W, H))
    assert res.ok, res.reason
    assert res.uv == pytest.approx(uv) and res.depth_m == pytest.approx(depth)


@pytest.mark.parametrize(
    "text,reason",
    [
        ('{"point_2d": [320, 240]}', "no depth"),
        ('{"point_2d": [320, 240], "depth": -1}', "positive"),
        ('{"point_2d": [320, 240], "depth": 0}', "positive"),
        ('{"point_2d": [900, 240], "depth": 2}', "outside"),
    ],
)
def test_point_depth_failures(text, reason):
    res = parse_point_depth(text, (W, H))
    assert not res.ok and reason in res.reason and res.raw == text


@pytest.mark.parametrize(
    "text,expected",
    [
        ('["fly through the gate", "stop next to the red van"]', ("fly through the gate", "stop next to the red van")),
        ('```json\n["a", "b"]\n```', ("a", "b")),
        ('Here you go: {"subtasks": ["go up", "land"]}', ("go up", "land")),
        ('["  fly   to\nthe tree "]', ("fly to the tree",)),
    ],
)
def test_subtasks_corpus(text, expected):
    res = parse_subtasks(text)
    assert res.ok and res.subtasks == expected


@pytest.mark.parametrize(
    "text,reason",
    [
        ("[]", "empty subtask list"),
        ('{"subtasks": []}', "empty subtask list"),
        ('["fly", 3]', "strings"),
        ('["fly", "  "]', "empty subtask"),
        ("Sure! Here are the subtasks:", "no JSON list"),
        ('["fly to the gate", ', "no JSON list"),
        (json.dumps(["x"] * 65), "more than"),
    ],
)
def test_subtasks_failures(text, reason):
    res = parse_subtasks(text)
    assert not res.ok and res.subtasks == () and reason in res.reason


# ---------------------------------------------------------------------------------------------
# "not visible": a third outcome, distinct from a point and from a failure

# (text, kwargs) -- every answer format the parsers accept, saying the target is not visible
NOT_VISIBLE_CORPUS = [
    # our prompt's contract (decision/v2) and its structured-output schema
    ('{"target_visible": false, "point_2d": null}', {}),
    ('{"target_visible":false,"point_2d":null}', {}),
    ('```json\n{"target_visible": false, "point_2d": null}\n```', {}),
    ('The van is out of the picture. {"target_visible": false, "point_2d": null}', {}),
    # the flag wins over a point in the same object (the model says it is not on the target)
    ('{"target_visible": false, "point_2d": [320, 240]}', {}),
    ('{"visible": false}', {}),
    ('[{"visible": false, "label": "red van"}]', {}),
    # the same in every coordinate system and axis order (the flag has no coordinates)
    ('{"target_visible": false, "point_2d": null}', {"coord_format": "rel1000"}),
    ('{"target_visible": false, "point_2d": null}', {"coord_format": "resized_pixel", "model_input_size": (448, 336)}),
    ('{"target_visible": false, "point_2d": null}', {"order": "yx"}),
    ('{"target_visible": false, "bbox_2d": [1, 2, 3, 4]}', {"coord_format": "rel1000"}),
    # plain text, no point anywhere
    ("NOT_VISIBLE", {}),
    ("not visible", {}),
    ("Not-visible.", {}),
    ("The red van is not visible in this image.", {}),
    ("I cannot see the target.", {}),
    ("I can't see a fuel pump here.", {}),
    ("I don't see the gate.", {}),
    ("The gate is not in view.", {}),
    ("The clock is out of sight.", {}),
    ("**NOT_VISIBLE**", {"coord_format": "rel1000", "order": "yx"}),
]


@pytest.mark.parametrize("text,kwargs", NOT_VISIBLE_CORPUS)
def test_not_visible_corpus(text, kwargs):
    res = parse_point(text, (W, H), **kwargs)
    assert res.not_visible and not res.ok and res.uv is None and res.candidates == ()
    assert res.outcome is PointOutcome.NOT_VISIBLE
    assert res.reason == "target not visible" and res.raw == text


# neither a point nor "not visible": a failure with not_visible False
NOT_VISIBLE_FAILURES = [
    ('{"target_visible": fal', "no point"),  # truncated
    ('{"target_visible": false, "point_2d": nu', "no point"),  # truncated
    ('{"target_visible": "false", "point_2d": null}', "not a JSON boolean"),  # a string is not the flag
    ('{"target_visible": 0, "point_2d": null}', "not a JSON boolean"),
    ('{"target_visible": "true", "point_2d": [3, 4]}', "not a JSON boolean"),
    ('{"visible": null, "point_2d": [3, 4]}', "not a JSON boolean"),
    ('{"point_2d": null}', "not a pair"),  # no flag
    ('{"target_visible": true, "point_2d": null}', "not a pair"),
    ('{"target_visible": true}', "no point"),
    ("[]", "no point"),
    ("NOT_VIS", "no point"),
    ("notvisible", "no point"),
    ("The target is visible.", "no point"),
    ("I can see the target.", "no point"),
    ("invisible", "no point"),
    # a point and a statement that the target is not visible: contradictory, refused
    ("The van is not visible; exploring toward (320, 240).", "ambiguous"),
    ('I cannot see it. {"point_2d": [320, 240]}', "ambiguous"),
    ('<point x="10" y="20">not visible</point>', "ambiguous"),
]


# decision/v3: the point beside a false flag is where the model would look (look_uv), never a
# target point; an invalid one leaves the answer "not visible" without a look point
LOOK_CASES = [
    ('{"target_visible": false, "point_2d": [320, 240]}', {}, (320.0, 240.0)),
    ('```json\n{"target_visible": false, "point_2d": [10, 20]}\n```', {}, (10.0, 20.0)),
    ('Not here. {"target_visible": false, "point_2d": [10, 20]}', {}, (10.0, 20.0)),
    ('{"visible": false, "point": [7, 9]}', {}, (7.0, 9.0)),
    ('{"target_visible": false, "point_2d": [500, 500]}', {"coord_format": "rel1000"}, (0.5 * (W - 1), 0.5 * (H - 1))),
    ('{"target_visible": false, "point_2d": [20, 10]}', {"order": "yx"}, (10.0, 20.0)),
    ('{"target_visible": false, "point_2d": null}', {}, None),
    ('{"target_visible": false, "point_2d": [9999, 10]}', {}, None),  # outside: no look point
    ('{"target_visible": false, "point_2d": [-3, 10]}', {}, None),
    ('{"target_visible": false, "point_2d": ["left", 10]}', {}, None),
    ('{"target_visible": false, "point_2d": [1, 2, 3]}', {}, None),
    ('{"target_visible": false, "bbox_2d": [1, 2, 3, 4]}', {}, None),  # a box is no look point
    ("NOT_VISIBLE", {}, None),
]


@pytest.mark.parametrize("text,kwargs,look", LOOK_CASES)
def test_not_visible_look_point(text, kwargs, look):
    res = parse_point(text, (W, H), **kwargs)
    assert res.not_visible and not res.ok and res.uv is None and res.candidates == ()
    assert res.look_uv == look
    if look is not None:
        assert 0 <= look[0] <= W - 1 and 0 <= look[1] <= H - 1


def test_look_point_is_never_read_from_another_object():
    """A point in another object than the false flag is a contradiction, not a look point."""
    for text in ('{"target_visible": false, "point_2d": null} {"point_2d": [5, 6]}',
                 '[{"target_visible": false}, {"point_2d": [5, 6]}]'):
        res = parse_point(text, (W, H))
        assert not res.ok and not res.not_visible and res.look_uv is None and "ambiguous" in res.reason


@pytest.mark.parametrize("text,reason", NOT_VISIBLE_FAILURES)
def test_not_visible_near_misses_are_failures(text, reason):
    res = parse_point(text, (W, H))
    assert not res.ok and not res.not_visible and res.uv is None
    assert res.outcome is PointOutcome.FAILED
    assert reason in res.reason


def test_points_read_as_before_with_or_without_the_flag():
    for text in ('{"target_visible": true, "point_2d": [320, 240]}', '{"point_2d": [320, 240]}',
                 '[{"point_2d": [320, 240], "label": "van", "visible": true}]'):  # fmt: skip
        res = parse_point(text, (W, H))
        assert res.ok and res.uv == (320, 240) and not res.not_visible
        assert res.outcome is PointOutcome.POINT
    # a flag in another JSON value than the point, in either order, or one the JSON reader
    # cannot read (Python literals): contradictory, refused
    for text in ('{"point_2d": [1, 2]} {"target_visible": false}', '{"target_visible": false} {"point_2d": [1, 2]}',
                 "{'target_visible': False, 'point_2d': [1, 2]}", '{"target_visible": False, "point_2d": [1, 2]}'):  # fmt: skip
        res = parse_point(text, (W, H))
        assert res.outcome is PointOutcome.FAILED and "ambiguous" in res.reason
    assert parse_point('{"target_visible": False, "point_2d": None}', (W, H)).outcome is PointOutcome.FAILED


def test_not_visible_is_not_a_point_for_point_depth():
    res = parse_point_depth('{"target_visible": false, "point_2d": null, "depth": 3}', (W, H))
    assert not res.ok and res.uv is None


# ---------------------------------------------------------------------------------------------
# fuzzing: total functions, never a pixel outside the image

_num = st.one_of(
    st.integers(-5000, 5000),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from(["1e999", "-0", "NaN", "320", "9" * 400, "0x10", "1_000"]),
)
_key = st.sampled_from(["point_2d", "point", "points", "bbox_2d", "box_2d", "bbox", "x", "pt", "label", "status"])


@st.composite
def _near_misses(draw) -> str:
    """Real-model-shaped answers with random damage."""
    a, b, c, d = (draw(_num) for _ in range(4))
    shape = draw(
        st.sampled_from(
            [
                '{{"{k}": [{a}, {b}]}}',
                '{{"{k}": [{a}, {b}, {c}, {d}]}}',
                '[{{"{k}": [{a}, {b}], "label": "van"}}]',
                '{{"x": {a}, "y": {b}}}',
                '```json\n{{"{k}": [{a}, {b}]}}\n```',
                "The point is ({a}, {b}).",
                "x = {a}, y = {b}",
                '<points x1="{a}" y1="{b}" x2="{c}" y2="{d}">t</points>',
                "<point>{a}, {b}</point>",
                "<|box_start|>({a},{b}),({c},{d})<|box_end|>",
                "[{a}, {b}]",
                "[[{a}, {b}], [{c}, {d}]]",
                '{{"{k}": {{"{k}": [{a}, {b}]}}}}',
                "{a} {b}",
            ]
        )
    )
    text = shape.format(k=draw(_key), a=a, b=b, c=c, d=d)
    cut = draw(st.integers(0, len(text)))
    if draw(st.booleans()):
        text = text[:cut]  # truncated generation
    prefix = draw(st.sampled_from(["", "Sure. ", "[", "{", "((", "```", "<point "]))
    return prefix + text + draw(st.sampled_from(["", " ", "}", "]]", "```", " (1, 2"]))


_any_text = st.one_of(st.text(max_size=200), _near_misses(), st.text(alphabet="[]{}(),:\"0123456789.-e xy<>=/", max_size=300))
_format = st.sampled_from(list(CoordFormat))
_size = st.tuples(st.integers(1, 4000), st.integers(1, 4000))


def _check_parse_point(text, size, fmt, order, model):
    res = parse_point(text, size, fmt, order=order, model_input_size=model)
    assert res.raw == text
    w, h = size
    if res.ok:
        u, v = res.uv
        assert math.isfinite(u) and math.isfinite(v)
        assert 0.0 <= u <= w - 1 and 0.0 <= v <= h - 1
        assert res.uv == res.candidates[0]
    else:
        assert res.uv is None and res.reason
    assert not (res.ok and res.not_visible)
    if res.not_visible:  # only ever from an explicit statement
        assert re.search(r"visible|see|view|sight|image|frame", text, re.IGNORECASE)
    for u, v in res.candidates:
        assert 0.0 <= u <= w - 1 and 0.0 <= v <= h - 1


_point_args = dict(text=_any_text, size=_size, fmt=_format, order=st.sampled_from(["xy", "yx"]), model=_size)


# the default run draws 1000 cases; the slow run 10000 (``-m slow``)
@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(**_point_args)
def test_fuzz_parse_point_never_raises_and_stays_inside(text, size, fmt, order, model):
    _check_parse_point(text, size, fmt, order, model)


@pytest.mark.slow
@settings(max_examples=10000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(**_point_args)
def test_fuzz_parse_point_never_raises_and_stays_inside_long(text, size, fmt, order, model):
    _check_parse_point(text, size, fmt, order, model)


_flag_shapes = st.sampled_from(
    [
        '{{"target_visible": {f}, "point_2d": {p}}}',
        '{{"visible": {f}}}',
        '[{{"target_visible": {f}, "point_2d": {p}}}]',
        "```json\n{{\"target_visible\": {f}, \"point_2d\": {p}}}\n```",
    ]
)


@settings(max_examples=1500, deadline=None)
@given(shape=_flag_shapes, flag=st.sampled_from(["false", "true", '"false"', "0", "null", "False", "no"]),
       point=st.sampled_from(["null", "[3, 4]", "[3]", '"here"', "[9999, 4]"]), cut=st.integers(0, 200),
       truncate=st.booleans(), size=_size)  # fmt: skip
def test_fuzz_not_visible_only_from_a_whole_false_flag(shape, flag, point, cut, truncate, size):
    """Damaged flag answers: "not visible" only when a complete JSON object carries the JSON
    boolean false; truncated or mistyped flags are failures (or a point, for a true flag)."""
    text = shape.format(f=flag, p=point)
    if truncate:
        text = text[:cut]
    res = parse_point(text, size)
    # the reference: the first JSON object in the text, decoded only if it is complete (a list
    # around it may be cut off: '[{"target_visible": false, ...}' still holds a whole object)
    try:
        obj = json.JSONDecoder().raw_decode(text, text.index("{"))[0]
    except ValueError:
        obj = None
    whole_false = isinstance(obj, dict) and any(obj.get(k) is False for k in ("target_visible", "visible"))
    assert res.not_visible == whole_false
    if res.ok:  # a point only under a true flag, or where the flag's value was cut off
        assert flag == "true" or not re.search(r'visible"\s*:\s*\S', text)


@settings(max_examples=1500, deadline=None)
@given(text=_any_text, size=_size)
def test_fuzz_point_depth_status_subtasks_are_total(text, size):
    pd = parse_point_depth(text, size)
    if pd.ok:
        assert 0 <= pd.uv[0] <= size[0] - 1 and 0 <= pd.uv[1] <= size[1] - 1
        assert math.isfinite(pd.depth_m) and pd.depth_m > 0
    s = parse_status(text, n_keyframes=4)
    assert s.ok == (s.status is not None) and s.raw == text
    assert s.seen_image is None or (s.status is MonitorStatus.LOST and 0 <= s.seen_image <= 4)
    t = parse_subtasks(text)
    assert t.ok == bool(t.subtasks)


@settings(max_examples=40, deadline=None)
@given(depth=st.integers(1, 3000), bracket=st.sampled_from("[{"))
def test_fuzz_deep_nesting_is_a_clean_failure(depth, bracket):
    res = parse_point(bracket * depth + "1, 2", (W, H))
    assert res.raw.endswith("1, 2")
    assert not res.ok or res.uv == (1.0, 2.0)
