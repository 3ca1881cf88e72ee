"""Compass headings in an instruction: the language rule that says which way a route runs.

Aerial instructions name headings ("fly east along the row of parked cars", "follow the hallway
west", "keep flying north"); a model cannot read them off an image (a frame shows no compass),
but the vehicle knows its heading. The pilot's search reads them (:mod:`onfly.search`).

A compass word (``north``, ``north-east`` / ``northeast``, ... and the ``-ward`` / ``-wards``
forms, :data:`COMPASS_YAWS`) is a *heading* when it ends its phrase: the text ends after it,
or punctuation, or a word of :data:`HEADING_FOLLOWERS` (``and``, ``then``, ``along``,
``past``, ``until``, ``for``, ...). Before a noun it names a thing (``the north aisle``, ``the
south entrance``: an aisle, an entrance), and ``north of the fountain`` says where, not which
way (``of`` is no follower). Headings are read in the ENU world frame (x east, y north): yaw 0
is east, ``pi / 2`` north.

:func:`compass_heading` returns the text's heading, or None when it names none, or names
headings a right angle or more apart (``fly east, then turn north``: the route bends, and no one
heading is its way).
"""

from __future__ import annotations

import functools
import math
import re

__all__ = ["COMPASS_YAWS", "HEADING_FOLLOWERS", "compass_heading", "compass_headings"]

_Q = math.pi / 4
#: Compass words and their yaw in the ENU world frame, radians (east 0, counter-clockwise).
COMPASS_YAWS = {
    "east": 0.0,
    "northeast": _Q,
    "north": 2 * _Q,
    "northwest": 3 * _Q,
    "west": math.pi,
    "southwest": -3 * _Q,
    "south": -2 * _Q,
    "southeast": -_Q,
}

#: Words after which a compass word is a heading (it ends its phrase): conjunctions,
#: prepositions of route and extent, and adverbs that close a motion.
HEADING_FOLLOWERS = frozenset(
    """and then along past through toward towards to until till for down up into onto across over under by
    as again instead too straight ahead once when while before after""".split()
)

_TOKEN_RE = re.compile(r"[a-z]+(?:-[a-z]+)*|[0-9]+(?:\.[0-9]+)?|[^\sa-z0-9]")


def _compass_word(token: str) -> float | None:
    word = token.replace("-", "")
    for suffix in ("wards", "ward"):
        if word.endswith(suffix) and word[: -len(suffix)] in COMPASS_YAWS:
            return COMPASS_YAWS[word[: -len(suffix)]]
    return COMPASS_YAWS.get(word)


def compass_headings(text: str) -> list[float]:
    """Every heading ``text`` names, in order, as ENU yaws (radians); see the module docstring."""
    tokens = _TOKEN_RE.findall(text.lower())
    out = []
    for i, tok in enumerate(tokens):
        yaw = _compass_word(tok)
        if yaw is None:
            continue
        nxt = tokens[i + 1] if i + 1 < len(tokens) else None
        if nxt is None or not nxt[0].isalnum() or nxt in HEADING_FOLLOWERS or nxt[0].isdigit():
            out.append(yaw)
    return out


@functools.lru_cache(maxsize=256)  # the pilot asks about the same subtask text again and again
def compass_heading(text: str) -> float | None:
    """The heading ``text`` tells the vehicle to travel, as an ENU yaw (radians, in (-pi, pi]),
    or None: no heading named, or headings a right angle or more apart."""
    yaws = compass_headings(text)
    if not yaws:
        return None
    for y in yaws[1:]:
        if abs(math.remainder(y - yaws[0], 2 * math.pi)) >= math.pi / 2 - 1e-9:
            return None
    return yaws[0]
