"""Turns that open an instruction: the language rule that says where the way starts.

"Turn around and head down to the elevator lobby", "turn left into the kitchen and stop by the
fridge": the way on lies behind or beside the camera, and a model that answers with a pixel
cannot point there (what is behind the camera is no pixel). Spoken route instructions open this
way often: of the 2349 instructions of R2R's val-unseen split (``../shared/realdata``), 141
begin with "turn around" and 153 with "turn left" or "turn right". The pilot reads the turn an
instruction opens with and turns in place before it asks where to go
(:class:`onfly.pilot.PilotConfig` ``turn_in_words``).

A text *opens with a turn* when, after leading fillers (``now``, ``first``, ``please``,
``then``, ``and``, ``okay``), it begins with one of:

- a half turn: ``turn around`` / ``turn round`` / ``turn back`` (also with ``spin``, ``swing``,
  ``rotate``, ``yaw``, and ``yourself`` / ``the drone`` between), ``about face`` /
  ``about-face``, ``u-turn`` (``make`` / ``do`` / ``take`` / ``pull`` ``a u-turn``), ``turn 180``;
- a quarter turn: ``turn left`` / ``turn right`` (also ``to the`` / ``to your`` / ``toward your``
  and ``hard`` / ``sharp`` before the side, and the verbs above plus ``veer`` and ``bear``), or
  ``make`` / ``take`` / ``hang`` / ``do`` ``a left`` / ``a right`` (``a sharp left``); a number
  of degrees is the angle (``turn left 45 degrees``, ``turn 90 degrees right``, at most a half
  turn). A slight turn (``turn slightly right``) keeps the way in the camera's view: none;

and the turn happens now: the text ends after it, or punctuation follows, or a word of
:data:`NOW_FOLLOWERS` (``and``, ``then``, ``into``, ``toward``, ``through``, ``down``, ...).
A turn at a place (``turn left at the elevators``, ``take a right after the door``, ``turn
right when you reach the desk``) is no opening turn: it happens where the place is, which the
decision agent sees. Angles are yaws in the vehicle's frame, counter-clockwise (ENU): left
``+pi / 2``, right ``-pi / 2``, a half turn ``pi``.
"""

from __future__ import annotations

import functools
import math
import re

__all__ = ["NOW_FOLLOWERS", "opening_turn"]

#: Words after which a turn happens where the vehicle is (the turn ends its phrase, or the
#: phrase says where the turn leads, not where it is made).
NOW_FOLLOWERS = frozenset(
    """and then into to toward towards through down up along out so until till facing again""".split()
)

_FILLERS = frozenset("now first please then and okay ok so".split())
_TURN_VERBS = frozenset("turn spin swing rotate yaw veer bear".split())
_HALF_WORDS = frozenset("around round back".split())
_MAKE_VERBS = frozenset("make take hang do pull".split())
_OBJECTS = (("yourself",), ("the", "drone"), ("the", "vehicle"), ("it",))
_SIDES = {"left": math.pi / 2, "right": -math.pi / 2}
_DEGREES = frozenset("degrees degree deg".split())
_LEADS = (("toward", "your"), ("towards", "your"), ("toward", "the"), ("towards", "the"), ("to", "the"), ("to", "your"), ("to",))
_HARD = (("hard",), ("sharp",), ("sharply",))
_SLIGHT = frozenset("slightly slight a bit little".split())
_TOKEN_RE = re.compile(r"[a-z]+(?:-[a-z]+)*|[0-9]+|[^\sa-z0-9]")


def _now(tokens: list[str], i: int) -> bool:
    """Whether the turn that ends before ``tokens[i]`` happens where the vehicle is."""
    if i >= len(tokens):
        return True
    nxt = tokens[i]
    return not nxt[0].isalnum() or nxt in NOW_FOLLOWERS


def _skip(tokens: list[str], i: int, words: tuple[str, ...]) -> int:
    return i + len(words) if tuple(tokens[i : i + len(words)]) == words else i


def _skip_any(tokens: list[str], i: int, options: tuple[tuple[str, ...], ...]) -> int:
    """``i`` past the first of ``options`` (longest first) that starts at ``tokens[i]``."""
    for words in options:
        k = _skip(tokens, i, words)
        if k != i:
            return k
    return i


def _skip_angle(tokens: list[str], i: int) -> tuple[float, int]:
    """(angle in radians, index after it) for a number of degrees at ``tokens[i]`` ("90",
    "90 degrees"; at most a half turn), or (pi, i) when there is none."""
    if i >= len(tokens) or not tokens[i].isdigit():
        return math.pi, i
    angle = math.radians(min(float(tokens[i]), 180.0))
    i += 1
    return angle, (i + 1 if i < len(tokens) and tokens[i] in _DEGREES else i)


@functools.lru_cache(maxsize=256)  # a benchmark flies each instruction many times
def opening_turn(text: str) -> float | None:
    """The turn ``text`` opens with, as a yaw in the vehicle's frame (radians, counter-clockwise:
    left ``+pi / 2``, right ``-pi / 2``, around ``pi``), or None when it opens with none or the
    turn is made at a place (see the module docstring)."""
    tokens = _TOKEN_RE.findall(text.lower())
    i = 0
    while i < len(tokens) and (tokens[i] in _FILLERS or tokens[i] == ","):
        i += 1
    if i >= len(tokens):
        return None
    word = tokens[i]
    if word in ("about-face",) or tokens[i : i + 2] == ["about", "face"]:
        return math.pi if _now(tokens, i + (1 if word == "about-face" else 2)) else None
    if word in ("u-turn", "uturn"):
        return math.pi if _now(tokens, i + 1) else None
    if word in _MAKE_VERBS and tokens[i + 1 : i + 2] == ["a"]:
        k = _skip_any(tokens, i + 2, _HARD)  # "take a sharp left"
        what = tokens[k] if k < len(tokens) else None
        if what in ("u-turn", "uturn"):
            return math.pi if _now(tokens, k + 1) else None
        if what in _SIDES:
            return _SIDES[what] if _now(tokens, k + 1) else None
        return None
    if word not in _TURN_VERBS:
        return None
    j = _skip_any(tokens, i + 1, _OBJECTS)
    if j >= len(tokens):
        return None
    if tokens[j] in _HALF_WORDS:  # "turn around", "turn around 180 degrees"
        return math.pi if _now(tokens, _skip_angle(tokens, j + 1)[1]) else None
    if tokens[j].isdigit():  # "turn 180", "turn 90 degrees right"
        degrees, k = _skip_angle(tokens, j)
        if k < len(tokens) and tokens[k] in _SIDES:
            return math.copysign(degrees, _SIDES[tokens[k]]) if _now(tokens, k + 1) else None
        return math.pi if degrees == math.pi and _now(tokens, k) else None
    if tokens[j] in _SLIGHT:
        return None  # a slight turn keeps the way in the camera's view: nothing to turn first
    j = _skip_any(tokens, j, _LEADS)
    j = _skip_any(tokens, j, _HARD)
    if j < len(tokens) and tokens[j] in _SIDES:
        angle, k = _SIDES[tokens[j]], j + 1
        if k < len(tokens) and tokens[k].isdigit():  # "turn left 45 degrees"
            degrees, k = _skip_angle(tokens, k)
            angle = math.copysign(degrees, angle)
        return angle if _now(tokens, k) else None
    return None
