"""Prompt templates: versions pinned to their text, builders, round trips, prefix stability."""

from __future__ import annotations

import numpy as np
import pytest

from vlm.parsing import parse_point
from vlm.prompts import (
    IMAGE_PLACEHOLDER,
    DecisionPrompt,
    DecomposePrompt,
    MonitorPrompt,
    PivotPrompt,
    PromptError,
    SceneObject,
    SpfPrompt,
    TypeflyPrompt,
    build_pivot_prompt,
    build_spf_prompt,
    build_typefly_prompt,
    pivot_schema,
    spf_schema,
    build_decision_prompt,
    build_decompose_prompt,
    build_monitor_prompt,
    count_placeholders,
    decision_schema,
    load_template,
    parse_prompt,
    prompt_segments,
    status_schema,
    subtasks_schema,
)
from vlm.types import ChatMessage, VlmImage

# Editing a template's text without a new version breaks this test on purpose: a logged
# version must name one exact text. Bump "## version:" in the file and update the pin.
PINNED = {
    "decision": ("decision/v3", "747a6933aa59ecad0d1cbcce0cb8f187cb19daf16fb7093cbd9510043b686907"),
    "monitor": ("monitor/v3", "007d38e3620cf4154e9acc23ae1bec52c789539cb9d922eff5ae00f7731b253e"),
    "decompose": ("decompose/v1", "531dcedca5041025b19524364a85a208ff85a9b1c8c2bf4598b36aff21d5aa4c"),
    "typefly": ("typefly/v1", "91e40abda5ab5999748b97cba358b7ca2d18629e22d4c1efcc17ebc8aa72a563"),
    "pivot": ("pivot/v1", "36e94787a2fcc626451c252d525b8a36cccf3b3348111317faebc2fa2667a935"),
    "spf": ("spf/v1", "70d4343d066d542bad7ece1524aea4a1409ca4413856b7f7479c985e43e0cc0b"),
}


def _img(frame_id: str, w: int = 64, h: int = 48) -> VlmImage:
    return VlmImage(np.zeros((h, w, 3), np.uint8), frame_id)


@pytest.mark.parametrize("name", sorted(PINNED))
def test_template_version_pins_text(name):
    tpl = load_template(name)
    assert (tpl.version, tpl.sha256) == PINNED[name]


def test_unknown_template_lists_valid_names():
    with pytest.raises(PromptError, match="unknown template 'chat'.*decision"):
        load_template("chat")


def test_decision_prompt_content_and_round_trip():
    messages, images = build_decision_prompt("  fly to the\n red van ", _img("f7", 640, 480), history_uv=(412.4, 233.6))
    assert [m.role for m in messages] == ["system", "user"]
    assert images[0].frame_id == "f7"
    assert count_placeholders(messages) == len(images) == 1
    system, user = messages[0].content, messages[1].content
    assert "decision agent" in system and '"point_2d": [x, y]}' in system and "integer pixel" in system
    # decision/v2: "not visible" is an answer the model is offered, in the form the parser reads;
    # v3: with the point where to look instead
    assert '{"target_visible": false, "point_2d": null}' in system
    assert parse_point('{"target_visible": false, "point_2d": null}', (640, 480)).not_visible
    assert '{"target_visible": false, "point_2d": [x, y]}' in system and "look for it" in system
    assert parse_point('{"target_visible": false, "point_2d": [5, 6]}', (640, 480)).look_uv == (5, 6)
    assert parse_point('{"target_visible": true, "point_2d": [3, 4]}', (640, 480)).uv == (3, 4)
    # subtask before the image (stable within a subtask), history point after it
    assert user.index("Current subtask: fly to the red van") < user.index(IMAGE_PLACEHOLDER) < user.index("History point: (412, 234)")
    assert "640 x 480 pixels" in user
    assert parse_prompt(messages) == DecisionPrompt("decision/v3", "fly to the red van", (640, 480), (412, 234))


def test_decision_prompt_without_history_and_bad_history():
    messages, _ = build_decision_prompt("go up", _img("a"))
    assert "History point: none" in messages[1].content
    assert parse_prompt(messages).history_uv is None
    with pytest.raises(PromptError, match="outside the 64x48 image"):
        build_decision_prompt("go up", _img("a"), history_uv=(64.0, 3.0))
    with pytest.raises(PromptError, match="outside"):
        build_decision_prompt("go up", _img("a"), history_uv=(float("nan"), 3.0))
    with pytest.raises(PromptError, match="subtask is empty"):
        build_decision_prompt(" \n ", _img("a"))
    with pytest.raises(PromptError, match="image must be a VlmImage"):
        build_decision_prompt("go", np.zeros((4, 4, 3), np.uint8))  # type: ignore[arg-type]


def test_decision_schema_accepts_what_the_parser_reads():
    schema = decision_schema()
    assert schema["required"] == ["target_visible", "point_2d"]
    assert list(schema["properties"]) == ["target_visible", "point_2d"]  # the flag is decoded first
    assert schema["additionalProperties"] is False
    point, null = schema["properties"]["point_2d"]["anyOf"]
    assert point["minItems"] == 2 == point["maxItems"] and null == {"type": "null"}
    assert decision_schema() is not schema  # fresh dicts, callers may mutate
    assert status_schema()["properties"]["status"]["enum"] == ["CONTINUE", "STOP", "LOST"]
    assert subtasks_schema()["minItems"] == 1
    # every answer the schema allows is a point or "not visible", never a parse failure
    # (when the point is inside the image), and the flag decides
    assert parse_point('{"target_visible": true, "point_2d": [3, 4]}', (64, 48)).uv == (3, 4)
    assert parse_point('{"target_visible": false, "point_2d": null}', (64, 48)).not_visible
    assert parse_point('{"target_visible": false, "point_2d": [3, 4]}', (64, 48)).not_visible
    assert parse_point('{"point_2d": [3, 4]}', (64, 48)).uv == (3, 4)  # decision/v1 answers still read


def test_monitor_prompt_order_first_keyframes_latest():
    first, keys, latest = _img("o1"), [_img("k1"), _img("k2"), _img("k3")], _img("ot")
    messages, images = build_monitor_prompt("stop next to the red van", first, keys, latest)
    assert [i.frame_id for i in images] == ["o1", "k1", "k2", "k3", "ot"]
    assert count_placeholders(messages) == len(images)
    user = messages[1].content
    assert user.startswith("First frame:\n<image>")
    # what changes least first: keyframes, then the subtask, then the latest frame
    assert (user.index("Keyframe 1:") < user.index("Keyframe 3:") < user.index("Current subtask: stop next to the red van\n")
            < user.index("Latest frame:"))
    for word in ("CONTINUE", "STOP", "LOST"):
        assert word in messages[0].content
    assert parse_prompt(messages) == MonitorPrompt("monitor/v3", "stop next to the red van", 3)
    messages0, images0 = build_monitor_prompt("stop", first, [], latest)
    assert "Keyframes: none" in messages0[1].content and len(images0) == 2
    assert parse_prompt(messages0).n_keyframes == 0


def test_monitor_prefix_is_byte_stable_when_only_later_keyframes_change():
    first = _img("o1")
    a_msgs, a_imgs = build_monitor_prompt("fly to the tree", first, [_img("k1"), _img("k2")], _img("t10"))
    b_msgs, b_imgs = build_monitor_prompt("fly to the tree", first, [_img("k1"), _img("k2"), _img("k5")], _img("t12"))
    c_msgs, c_imgs = build_monitor_prompt("fly to the tree", first, [_img("k1"), _img("k2")], _img("t14"))
    a, b, c = prompt_segments(a_msgs, a_imgs), prompt_segments(b_msgs, b_imgs), prompt_segments(c_msgs, c_imgs)
    # the system text is byte-identical
    assert a_msgs[0].content == b_msgs[0].content == c_msgs[0].content
    # a and b share everything up to and including keyframe 2
    k2 = a.index("\x00image:k2")
    assert a[: k2 + 1] == b[: k2 + 1] and a[k2 + 1] != b[k2 + 1]
    # same keyframes: everything but the latest frame (and what follows) is shared
    assert a[:-3] == c[:-3] and a[-3] != c[-3]
    # the user text up to the first differing image is a byte prefix of both
    text_a, text_b = a_msgs[1].content, b_msgs[1].content
    cut = text_a.index("Keyframe 2:\n<image>") + len("Keyframe 2:\n<image>")
    assert text_a[:cut] == text_b[:cut]


def test_a_subtask_advance_keeps_every_image_but_the_latest_in_the_prefix():
    first, keys = _img("o1"), [_img("k1"), _img("k2")]
    a = prompt_segments(*build_monitor_prompt("fly to the tree", first, keys, _img("t")))
    b = prompt_segments(*build_monitor_prompt("land on the roof", first, keys, _img("t")))
    k2 = a.index("\x00image:k2")
    # every segment up to and including the last keyframe is shared; the subtask text differs
    assert a[: k2 + 1] == b[: k2 + 1] and a[k2 + 1] != b[k2 + 1]
    assert a.index("\x00image:t") > k2 + 1 and b.index("\x00image:t") > k2 + 1


def test_placeholder_count_must_equal_images():
    messages, images = build_monitor_prompt("x", _img("a"), [_img("b")], _img("c"))
    with pytest.raises(PromptError, match="3 <image> placeholders but 2 images"):
        prompt_segments(messages, images[:2])


def test_decompose_prompt_round_trip():
    messages, images = build_decompose_prompt("Fly through the gate,\nthen stop next to the red van.")
    assert images == [] and count_placeholders(messages) == 0
    assert "JSON array of strings" in messages[0].content
    assert parse_prompt(messages) == DecomposePrompt("decompose/v1", "Fly through the gate, then stop next to the red van.")


def test_parse_prompt_refuses_foreign_chats():
    assert parse_prompt([ChatMessage("user", "hello")]) is None
    assert parse_prompt([ChatMessage("system", "You are helpful."), ChatMessage("user", "hi")]) is None
    messages, _ = build_decision_prompt("go", _img("a"))
    tampered = [messages[0], ChatMessage("user", messages[1].content.replace("History point", "Hint"))]
    assert parse_prompt(tampered) is None


# ---------------------------------------------------------------------------------------------
# baseline prompts


def test_typefly_prompt_round_trip_objects_and_history():
    objs = [SceneObject("red van", "van", 0.4234, 0.5, 0.1, 0.2), SceneObject("office 103", "door", 0.0, 1.0, 1.0, 0.05)]
    messages, images = build_typefly_prompt(" Fly to the\nred van. ", _img("t1", 320, 214), objs, ["find red van: found", "turn 45: done"])
    assert images[0].frame_id == "t1" and count_placeholders(messages) == 1
    user = messages[1].content
    assert "red van [van] x=0.42 y=0.50 w=0.10 h=0.20; office 103 [door] x=0.00 y=1.00 w=1.00 h=0.05" in user
    assert "Executed skills: find red van: found | turn 45: done" in user
    assert "stop" in messages[0].content and "find <object>" in messages[0].content
    parsed = parse_prompt(messages)
    assert parsed == TypeflyPrompt(
        "typefly/v1", "Fly to the red van.", (320, 214),
        (SceneObject("red van", "van", 0.42, 0.5, 0.1, 0.2), SceneObject("office 103", "door", 0.0, 1.0, 1.0, 0.05)),
        ("find red van: found", "turn 45: done"),
    )  # fmt: skip
    empty = parse_prompt(build_typefly_prompt("go", _img("t2"), [], [])[0])
    assert empty.objects == () and empty.history == ()


def test_typefly_prompt_errors():
    with pytest.raises(PromptError, match="SceneObject.x must be a fraction"):
        SceneObject("van", "van", 1.5, 0.0, 0.1, 0.1)
    with pytest.raises(PromptError, match="SceneObject.name must be words"):
        SceneObject("van; stop", "van", 0.5, 0.5, 0.1, 0.1)
    with pytest.raises(PromptError, match="must not contain"):
        build_typefly_prompt("go", _img("a"), [], ["a | b"])
    with pytest.raises(PromptError, match="objects must be SceneObject"):
        build_typefly_prompt("go", _img("a"), [("van", 0.5)], [])  # type: ignore[list-item]


def test_pivot_prompt_lists_labels_and_endpoints():
    messages, images = build_pivot_prompt("Fly to the tree.", _img("p1", 160, 107), [(1, 10.4, 20.6), (2, 159.2, 0.0)], 3)
    user = messages[1].content
    assert "2 numbered arrows, 160 x 107 pixels" in user
    assert "Arrow endpoints (number: x, y in pixels): 1: (10, 21); 2: (159, 0)" in user
    assert "Choose up to 3 arrows" in user and '{"stop": true}' in messages[0].content
    assert parse_prompt(messages) == PivotPrompt("pivot/v1", "Fly to the tree.", (160, 107), ((1, 10, 21), (2, 159, 0)), 3)
    with pytest.raises(PromptError, match="outside the 160x107 image"):
        build_pivot_prompt("go", _img("p", 160, 107), [(1, 160.0, 3.0)], 1)
    with pytest.raises(PromptError, match="distinct positive"):
        build_pivot_prompt("go", _img("p", 160, 107), [(1, 3.0, 3.0), (1, 4.0, 4.0)], 1)
    with pytest.raises(PromptError, match="at least one arrow"):
        build_pivot_prompt("go", _img("p", 160, 107), [], 1)
    with pytest.raises(PromptError, match="n_pick must be an int >= 1"):
        build_pivot_prompt("go", _img("p", 160, 107), [(1, 3.0, 3.0)], 0)
    assert set(pivot_schema()["properties"]) == {"arrows", "stop"}


def test_spf_prompt_round_trip_and_schema():
    messages, images = build_spf_prompt("Fly to the red van.", _img("s1", 320, 214))
    assert parse_prompt(messages) == SpfPrompt("spf/v1", "Fly to the red van.", (320, 214))
    assert "depth 0" in messages[0].content and "from 1 to 10" in messages[0].content
    assert spf_schema()["properties"]["depth"] == {"type": "integer", "minimum": 0, "maximum": 10}
    assert spf_schema()["required"] == ["point_2d", "depth"]
