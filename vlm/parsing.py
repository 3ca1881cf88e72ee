"""Parsers for what VLMs answer: an image point, a monitoring status, a list of subtasks.

Every parser is total: it never raises on any input string and returns a frozen result with
``ok``, the parsed value and the raw text. A failure keeps the raw text and says why; it never
carries a guessed pixel.

Points
------
Real models point in several syntaxes and coordinate systems. The **syntax** is detected; the
**coordinate system** and **axis order** are configured (they cannot be inferred from the text):

syntaxes, in priority order (the first syntax that yields a candidate wins):

1. JSON anywhere in the text (code fences and prose around it are ignored): an object with
   ``point_2d`` / ``point`` / ``points`` (a pair or a list of pairs), ``bbox_2d`` / ``bbox`` /
   ``box_2d`` (four numbers, the box centre is the point), or ``{"x": .., "y": ..}``; objects
   nested in lists or other objects (``[{"point_2d": [..], "label": ".."}]``); a bare pair
   ``[x, y]`` or a list of bare pairs. Numeric strings (``"320"``) are accepted.
2. XML: Molmo ``<points x1=".." y1=".." x2=".." ...>`` / ``<point x=".." y="..">`` and
   ``<point>x, y</point>`` (two numbers inside the element).
3. Qwen2-VL box tokens ``<|box_start|>(x1,y1),(x2,y2)<|box_end|>`` (centre of the box; these
   are always x first).
4. Prose: ``x = 320, y = 240`` / ``x: 320, y: 240``, then ``(x, y)`` tuples.

Several points: **the first one is taken** (models list the most salient target first); all
valid candidates of the winning syntax are kept in :attr:`PointParse.candidates`.

coordinate systems (:class:`CoordFormat`):

- ``pixel``: pixels of the image as given (our prompts ask for this).
- ``resized_pixel``: pixels of the *resized* model input (Qwen2.5-VL); needs
  ``model_input_size=(w_in, h_in)``; rescaled to the original image.
- ``rel1000``: 0..1000 relative (Qwen3-VL, Gemini), ``rel100`` (Molmo percent), ``rel1``.

axis order ``"xy"`` (default) or ``"yx"`` (Gemini, SPF) applies to unnamed pairs and boxes
(``[y, x]``, ``[ymin, xmin, ymax, xmax]``); named values (``x=``, ``"y":``) are never swapped.

Pixel convention: as in :mod:`planning.camera`, integer coordinates are pixel centres and the
image spans ``[-0.5, W - 0.5) x [-0.5, H - 0.5)``. A point is valid only if it lies inside the
model's own coordinate range (``[-0.5, W - 0.5)`` for pixels, ``[0, R]`` for relative formats).
**A point outside is a parse failure, never clipped into the image.** Valid points are mapped
into ``[0, W - 1] x [0, H - 1]``: relative ``r`` maps to ``r / R * (W - 1)`` (0 and R name the
first and last pixel centres); pixel formats use the centre-preserving scale
``(x + 0.5) * W / w_in - 0.5`` and a final clamp that can only move a point within its border
pixel. Hence a returned ``uv`` always satisfies ``0 <= u <= W - 1`` and ``0 <= v <= H - 1``,
and ``round(uv)`` is a valid pixel index.

"Not visible"
-------------
The decision prompt lets the model answer that the subtask's target is not visible instead of
pointing. :func:`parse_point` returns such an answer as ``ok=False, uv=None,
not_visible=True`` (``outcome`` :attr:`PointOutcome.NOT_VISIBLE`), distinct from a parse
failure (``not_visible=False``, ``outcome`` :attr:`PointOutcome.FAILED`) and from a point
(``ok=True``, :attr:`PointOutcome.POINT`); callers that only read ``ok`` treat it like a
failure (hold the last goal). Accepted forms, and nothing else:

1. JSON (any syntax position of rule 1 above, fences and prose around it ignored): an object
   with ``"target_visible": false`` or ``"visible": false`` (a JSON boolean; strings such as
   ``"false"`` do not count, and make the object a failure). The flag is the model's statement and wins over a point in the
   same object (``{"target_visible": false, "point_2d": [3, 4]}`` is not visible: a point the
   model says is not on the target is not a target point). That point is where the model
   would look for the target instead (``decision/v3``): it is returned as ``look_uv`` when it
   is a valid point of the image (same rules as any point), else ``look_uv`` is None and the
   answer is still "not visible". ``"target_visible": true`` with a
   point is a point; with ``"point_2d": null`` or no point it is a failure.
2. Plain text with no point in any syntax and a whole-word statement: ``NOT_VISIBLE`` /
   ``not visible`` (any case, ``_``, ``-`` or a space between), ``cannot see`` / ``can't see`` /
   ``can not see`` / ``do not see`` / ``don't see`` / ``does not see`` / ``doesn't see``,
   ``not in view`` / ``not in the image`` / ``not in the frame``, ``out of view`` / ``out of
   sight``.

A point next to a statement that the target is not visible *outside the point's own object*
is refused as ambiguous (the model both pointed and said it cannot see the target): prose
(``not visible ... (320, 240)``), a false flag in another JSON value (either order), or a false
flag the JSON reader could not read (``{'visible': False, 'point_2d': [3, 4]}``, Python
literals; such a flag alone is a failure, never "not visible"). A flag that is neither JSON
``true`` nor ``false`` (``"false"``, ``0``, ``null``) makes its object a failure.

Truncated JSON never counts (``{"target_visible": fal`` decodes as nothing and has no statement
of rule 2), nor does a bare ``{"point_2d": null}`` or an empty list.

Statuses
--------
:func:`parse_status` finds the status words CONTINUE / STOP / LOST as whole words, ignoring
case, markdown and punctuation (``**STOP**``, ``Status: stop.``, ``{"status": "LOST"}``).
Text naming two *different* statuses (``CONTINUE or STOP``) is refused as ambiguous; text
naming none is a failure. ``STOPPED`` or ``continuing`` are not status words.

A LOST may say where the target was last visible (monitor prompt ``monitor/v3``): the image
of the prompt that showed it, ``first`` (the first frame) or ``keyframe N``
(:attr:`StatusParse.seen_image`: 0 for the first frame, N for keyframe N, the prompt's image
order). Accepted: ``first`` right after the status word (``LOST first``, ``LOST: first``),
``first frame`` / ``first image`` anywhere, ``keyframe N`` / ``key frame N`` / ``keyframe #N``
anywhere, and a JSON ``"last_seen"`` string holding one of those. The place is optional and
never decides the status: a place naming two different images, a keyframe outside ``1 ..
n_keyframes`` (when the caller says how many it sent) or a place after another status leaves
``seen_image`` None, with the status kept and the reason in :attr:`StatusParse.reason`.
"""

from __future__ import annotations

import json
import logging
import math
import re
from dataclasses import dataclass
from enum import Enum
from typing import Any, Iterator

__all__ = [
    "CoordFormat",
    "PointOutcome",
    "MonitorStatus",
    "PointParse",
    "PointDepthParse",
    "StatusParse",
    "SubtasksParse",
    "parse_point",
    "parse_point_depth",
    "parse_status",
    "parse_subtasks",
    "MAX_TEXT_CHARS",
]

log = logging.getLogger(__name__)

#: Longer answers are refused unread (a pointing answer is a few dozen tokens); this also
#: bounds the parser's work on adversarial input.
MAX_TEXT_CHARS = 16384
_MAX_JSON_ATTEMPTS = 512


class CoordFormat(str, Enum):
    """Coordinate system a model answers in (see the module docstring)."""

    PIXEL = "pixel"
    RESIZED_PIXEL = "resized_pixel"
    REL1000 = "rel1000"
    REL100 = "rel100"
    REL1 = "rel1"


_REL_RANGE = {CoordFormat.REL1000: 1000.0, CoordFormat.REL100: 100.0, CoordFormat.REL1: 1.0}


class PointOutcome(str, Enum):
    """What a pointing answer said: a point, "the target is not visible", or nothing readable."""

    POINT = "point"
    NOT_VISIBLE = "not_visible"
    FAILED = "failed"


class MonitorStatus(str, Enum):
    """The monitoring agent's forced choice."""

    CONTINUE = "CONTINUE"
    STOP = "STOP"
    LOST = "LOST"


@dataclass(frozen=True)
class PointParse:
    """Outcome of :func:`parse_point`.

    Attributes
    ----------
    ok : bool, a point was read (``uv`` is set)
    uv : (u, v) floats in pixels of the original image (centre convention), or None
    candidates : tuple of (u, v), every valid point of the winning syntax, in text order
    raw : str, the text as received
    reason : str, why no point was read ("" when ok; ``"target not visible"`` when
        ``not_visible``)
    source : str, which syntax matched (e.g. ``"json:point_2d"``, ``"xml:points"``,
        ``"json:target_visible"``, ``"prose:not_visible"``)
    not_visible : bool, the model answered that the target is not visible (then ``ok`` is
        False and ``uv`` None); never True for a parse failure
    look_uv : (u, v) floats in pixels of the original image, or None: with ``not_visible``,
        where the model would look for the target (the point in the same JSON object as the
        false flag); None otherwise
    """

    ok: bool
    uv: tuple[float, float] | None
    candidates: tuple[tuple[float, float], ...]
    raw: str
    reason: str = ""
    source: str = ""
    not_visible: bool = False
    look_uv: tuple[float, float] | None = None

    @property
    def outcome(self) -> PointOutcome:
        """:attr:`PointOutcome.POINT`, :attr:`~PointOutcome.NOT_VISIBLE` or :attr:`~PointOutcome.FAILED`."""
        if self.ok:
            return PointOutcome.POINT
        return PointOutcome.NOT_VISIBLE if self.not_visible else PointOutcome.FAILED


@dataclass(frozen=True)
class PointDepthParse:
    """Outcome of :func:`parse_point_depth`: a point plus a coarse depth in metres."""

    ok: bool
    uv: tuple[float, float] | None
    depth_m: float | None
    raw: str
    reason: str = ""


@dataclass(frozen=True)
class StatusParse:
    """Outcome of :func:`parse_status`. ``seen_image``: with a LOST, the image of the prompt
    that last showed the target (0 = the first frame, N = keyframe N), or None."""

    ok: bool
    status: MonitorStatus | None
    raw: str
    reason: str = ""
    seen_image: int | None = None


@dataclass(frozen=True)
class SubtasksParse:
    """Outcome of :func:`parse_subtasks`: non-empty ordered subtask strings, or a failure."""

    ok: bool
    subtasks: tuple[str, ...]
    raw: str
    reason: str = ""


# ---------------------------------------------------------------------------------------------
# coordinate conversion


@dataclass(frozen=True)
class _Frame:
    """The coordinate system points are read in and the image they map to."""

    width: int
    height: int
    fmt: CoordFormat
    order: str
    model_w: float
    model_h: float

    def to_pixel(self, a: float, b: float, named: bool) -> tuple[float, float] | str:
        """Map a read pair to original-image pixels, or return why it is invalid.

        ``(a, b)`` is in text order; ``named`` pairs are already ``(x, y)``.
        """
        x, y = (b, a) if (self.order == "yx" and not named) else (a, b)
        if not (math.isfinite(x) and math.isfinite(y)):
            return f"non-finite coordinate ({x}, {y})"
        if self.fmt in _REL_RANGE:
            r = _REL_RANGE[self.fmt]
            if not (0.0 <= x <= r and 0.0 <= y <= r):
                return f"point ({x:g}, {y:g}) outside the relative range [0, {r:g}]"
            return (x / r * (self.width - 1), y / r * (self.height - 1))
        if not (-0.5 <= x < self.model_w - 0.5 and -0.5 <= y < self.model_h - 0.5):
            return f"point ({x:g}, {y:g}) outside the {self.model_w:g}x{self.model_h:g} image"
        u = (x + 0.5) * self.width / self.model_w - 0.5
        v = (y + 0.5) * self.height / self.model_h - 0.5
        return (min(max(u, 0.0), self.width - 1.0), min(max(v, 0.0), self.height - 1.0))


def _make_frame(image_size, coord_format, order, model_input_size) -> _Frame | str:
    try:
        w, h = (int(image_size[0]), int(image_size[1]))
    except (TypeError, ValueError, IndexError):
        return f"image_size must be (width, height), got {image_size!r}"
    if w <= 0 or h <= 0:
        return f"image_size must be positive, got {image_size!r}"
    try:
        fmt = CoordFormat(coord_format)
    except ValueError:
        return f"unknown coord_format {coord_format!r}; valid: {[f.value for f in CoordFormat]}"
    if order not in ("xy", "yx"):
        return f"order must be 'xy' or 'yx', got {order!r}"
    mw, mh = float(w), float(h)
    if fmt is CoordFormat.RESIZED_PIXEL:
        if model_input_size is None:
            return "coord_format 'resized_pixel' needs model_input_size=(w_in, h_in)"
        try:
            mw, mh = float(model_input_size[0]), float(model_input_size[1])
        except (TypeError, ValueError, IndexError):
            return f"model_input_size must be (w_in, h_in), got {model_input_size!r}"
        if not (mw > 0 and mh > 0 and math.isfinite(mw) and math.isfinite(mh)):
            return f"model_input_size must be positive, got {model_input_size!r}"
    return _Frame(w, h, fmt, order, mw, mh)


def _number(value: Any) -> float | None:
    """A JSON value as a float: numbers and numeric strings; never bools."""
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        try:
            return float(value)
        except OverflowError:
            return None
    if isinstance(value, str) and len(value) <= 64:
        try:
            return float(value.strip())
        except ValueError:
            return None
    return None


def _numbers(value: Any, n: int) -> list[float] | None:
    if isinstance(value, (list, tuple)) and len(value) == n:
        out = [_number(v) for v in value]
        if all(v is not None for v in out):
            return out  # type: ignore[return-value]
    return None


# ---------------------------------------------------------------------------------------------
# JSON extraction

_POINT_KEYS = ("point_2d", "point", "points")
#: keys of an explicit visibility flag (a JSON boolean; false = the target is not visible)
_VISIBLE_KEYS = ("target_visible", "visible")


@dataclass(frozen=True)
class _NotVisible:
    """What :func:`_points_in_json` yields for an object flagged not visible: the object's own
    point as the place to look (pixels), or None."""

    look: tuple[float, float] | None


def _look_point(obj: dict, frame: _Frame) -> tuple[float, float] | None:
    """The valid point of a not-visible object (``point_2d`` or ``point``), or None."""
    for key in _POINT_KEYS[:2]:
        pair = _numbers(obj.get(key), 2)
        if pair is not None:
            p = frame.to_pixel(pair[0], pair[1], False)
            return p if isinstance(p, tuple) else None
    return None
_BOX_KEYS = ("bbox_2d", "bbox", "box_2d")


def _json_values(text: str) -> Iterator[tuple[int, Any]]:
    """Every JSON object/array decodable at a ``{`` or ``[`` in ``text``, outermost first.

    After a successful decode the scan resumes after the decoded value, so nested values are
    not reported twice.
    """
    decoder = json.JSONDecoder(strict=False)  # models put raw newlines inside strings
    pos, attempts = 0, 0
    while attempts < _MAX_JSON_ATTEMPTS:
        starts = [i for i in (text.find("{", pos), text.find("[", pos)) if i >= 0]
        if not starts:
            return
        i = min(starts)
        attempts += 1
        try:
            value, end = decoder.raw_decode(text, i)
        except (ValueError, RecursionError):
            pos = i + 1
            continue
        yield i, value
        pos = end


def _points_in_json(value: Any, frame: _Frame, depth: int = 0) -> Iterator[tuple[str, Any]]:
    """Yield ``(source, (u, v) | reason)`` for the points inside one decoded JSON value."""
    if depth > 8:
        return
    if isinstance(value, dict):
        for key in _VISIBLE_KEYS:
            if key in value and value[key] is not True:
                if value[key] is False:
                    yield f"json:{key}", _NotVisible(_look_point(value, frame))
                else:
                    yield f"json:{key}", f"{key} is not a JSON boolean"
                return
        for key in _POINT_KEYS:
            if key in value:
                yield from _pairs(value[key], frame, f"json:{key}")
                return
        for key in _BOX_KEYS:
            if key in value:
                box = _numbers(value[key], 4)
                if box is not None:
                    yield f"json:{key}", frame.to_pixel((box[0] + box[2]) / 2, (box[1] + box[3]) / 2, False)
                else:
                    yield f"json:{key}", f"{key} is not four numbers"
                return
        if "x" in value and "y" in value:
            x, y = _number(value["x"]), _number(value["y"])
            if x is not None and y is not None:
                yield "json:xy", frame.to_pixel(x, y, True)
            else:
                yield "json:xy", "x/y are not numbers"
            return
        for sub in value.values():
            if isinstance(sub, (dict, list)):
                yield from _points_in_json(sub, frame, depth + 1)
    elif isinstance(value, list):
        pair = _numbers(value, 2)
        if pair is not None:
            yield "json:pair", frame.to_pixel(pair[0], pair[1], False)
            return
        for item in value:
            if isinstance(item, (dict, list)):
                yield from _points_in_json(item, frame, depth + 1)


def _pairs(value: Any, frame: _Frame, source: str) -> Iterator[tuple[str, Any]]:
    """A point value: ``[x, y]`` or a list of such pairs (or of point objects)."""
    pair = _numbers(value, 2)
    if pair is not None:
        yield source, frame.to_pixel(pair[0], pair[1], False)
        return
    if isinstance(value, dict):
        yield from _points_in_json(value, frame, 1)
        return
    if isinstance(value, list) and value and all(isinstance(v, (list, dict)) for v in value):
        for item in value:
            yield from _pairs(item, frame, source)
        return
    yield source, f"{source.split(':')[1]} is not a pair of numbers"


# ---------------------------------------------------------------------------------------------
# XML / token / prose extraction

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_ATTR_RE = re.compile(r"""\b([xy]\d*)\s*=\s*["']?\s*(""" + _NUM + r""")\s*["']?""", re.IGNORECASE)
_XML_TAG_RE = re.compile(r"<\s*(points?)\b([^<>]*)>", re.IGNORECASE)
_XML_BODY_RE = re.compile(r"<\s*point\s*>([^<]{0,200})<\s*/\s*point\s*>", re.IGNORECASE)
_BOX_TOKEN_RE = re.compile(
    r"<\|box_start\|>\s*\(\s*(" + _NUM + r")\s*,\s*(" + _NUM + r")\s*\)\s*,\s*\(\s*(" + _NUM + r")\s*,\s*("
    + _NUM + r")\s*\)\s*<\|box_end\|>"
)
_PROSE_XY_RE = re.compile(
    r"\bx\s*[=:]\s*(" + _NUM + r")\s*[,;]?\s*(?:and\s+)?\by\s*[=:]\s*(" + _NUM + r")", re.IGNORECASE
)
_PROSE_YX_RE = re.compile(
    r"\by\s*[=:]\s*(" + _NUM + r")\s*[,;]?\s*(?:and\s+)?\bx\s*[=:]\s*(" + _NUM + r")", re.IGNORECASE
)
_TUPLE_RE = re.compile(r"\(\s*(" + _NUM + r")\s*,\s*(" + _NUM + r")\s*\)")
_BODY_PAIR_RE = re.compile(r"^[\s(\[]*(" + _NUM + r")\s*[,\s]\s*(" + _NUM + r")[\s)\]]*$")


_NOT_VISIBLE_RE = re.compile(
    r"(?<![A-Za-z0-9])(?:not[ _-]visible|(?:cannot|can ?not|can'?t|can\u2019t|do not|don'?t|don\u2019t|does not|doesn'?t"
    r"|doesn\u2019t) see|not in (?:the )?(?:view|image|frame)|out of (?:view|sight))(?![A-Za-z0-9])",
    re.IGNORECASE,
)


_FLAG_FALSE_RE = re.compile(r"""\b(?:target_)?visible["']?\s*[:=]\s*(?!(?:true|True|TRUE)\b)\S""")
_AMBIGUOUS = "ambiguous: a point and a statement that the target is not visible"


def _float(s: str) -> float:
    try:
        return float(s)
    except (ValueError, OverflowError):
        return math.nan


def _xml_points(text: str, frame: _Frame) -> list[tuple[str, Any]]:
    found: list[tuple[int, str, Any]] = []
    for m in _XML_TAG_RE.finditer(text):
        attrs = {k.lower(): _float(v) for k, v in _ATTR_RE.findall(m.group(2))}
        if "x" in attrs and "y" in attrs:
            found.append((m.start(), "xml:point", frame.to_pixel(attrs["x"], attrs["y"], True)))
        k = 1
        while f"x{k}" in attrs and f"y{k}" in attrs:
            found.append((m.start() + k, "xml:points", frame.to_pixel(attrs[f"x{k}"], attrs[f"y{k}"], True)))
            k += 1
    for m in _XML_BODY_RE.finditer(text):
        body = _BODY_PAIR_RE.match(m.group(1))
        if body:
            found.append((m.start(), "xml:point_body", frame.to_pixel(_float(body.group(1)), _float(body.group(2)), False)))
    found.sort(key=lambda t: t[0])
    return [(s, p) for _, s, p in found]


def _box_token_points(text: str, frame: _Frame) -> list[tuple[str, Any]]:
    out = []
    for m in _BOX_TOKEN_RE.finditer(text):
        x1, y1, x2, y2 = (_float(g) for g in m.groups())
        out.append(("box_tokens", frame.to_pixel((x1 + x2) / 2, (y1 + y2) / 2, True)))
    return out


def _prose_points(text: str, frame: _Frame) -> list[tuple[str, Any]]:
    named = [(m.start(), frame.to_pixel(_float(m.group(1)), _float(m.group(2)), True)) for m in _PROSE_XY_RE.finditer(text)]
    named += [(m.start(), frame.to_pixel(_float(m.group(2)), _float(m.group(1)), True)) for m in _PROSE_YX_RE.finditer(text)]
    if named:
        named.sort(key=lambda t: t[0])
        return [("prose:xy", p) for _, p in named]
    return [("prose:tuple", frame.to_pixel(_float(m.group(1)), _float(m.group(2)), False)) for m in _TUPLE_RE.finditer(text)]


def _json_points(text: str, frame: _Frame) -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for _, value in _json_values(text):
        out.extend(_points_in_json(value, frame))
    return out


def _fail(raw: str, reason: str) -> PointParse:
    return PointParse(ok=False, uv=None, candidates=(), raw=raw, reason=reason)


def parse_point(
    text: str,
    image_size: tuple[int, int],
    coord_format: CoordFormat | str = CoordFormat.PIXEL,
    *,
    order: str = "xy",
    model_input_size: tuple[int, int] | None = None,
) -> PointParse:
    """Read the first image point in a model's answer.

    Parameters
    ----------
    text : str, the model's answer
    image_size : (width, height) of the original image in pixels
    coord_format : :class:`CoordFormat` or its value; the coordinate system of the answer
    order : ``"xy"`` or ``"yx"``, axis order of unnamed pairs and boxes
    model_input_size : (w_in, h_in), pixels of the resized model input; required for
        ``resized_pixel``

    Returns
    -------
    PointParse with ``uv`` in original-image pixels, ``0 <= u <= W - 1``, ``0 <= v <= H - 1``
    (see the module docstring for the policy on several points and points outside the image).
    Never raises; a bad configuration is reported as a failure naming the argument.
    """
    raw = text if isinstance(text, str) else repr(text)
    if not isinstance(text, str):
        return _fail(raw, f"text must be str, got {type(text).__name__}")
    frame = _make_frame(image_size, coord_format, order, model_input_size)
    if isinstance(frame, str):
        return _fail(raw, frame)
    if len(text) > MAX_TEXT_CHARS:
        return _fail(raw, f"text longer than {MAX_TEXT_CHARS} characters")
    says_not_visible = _NOT_VISIBLE_RE.search(text) is not None
    # a flag with any value but true anywhere, also one the JSON reader could not read (Python
    # ``False``, broken JSON): it never makes "not visible" by itself, but refuses a point
    flags_false = _FLAG_FALSE_RE.search(text) is not None
    for extract in (_json_points, _xml_points, _box_token_points, _prose_points):
        found = extract(text, frame)
        if not found:
            continue
        source, first = found[0]
        candidates = tuple(p for _, p in found if isinstance(p, tuple))
        if isinstance(first, _NotVisible):
            if candidates:
                return PointParse(False, None, candidates, raw, _AMBIGUOUS, source)
            return PointParse(False, None, (), raw, "target not visible", source, not_visible=True, look_uv=first.look)
        if isinstance(first, str):
            return PointParse(ok=False, uv=None, candidates=candidates, raw=raw, reason=f"first point: {first}", source=source)
        if says_not_visible or flags_false:
            return PointParse(False, None, candidates, raw, _AMBIGUOUS, source)
        return PointParse(ok=True, uv=first, candidates=candidates, raw=raw, source=source)
    if says_not_visible:
        return PointParse(False, None, (), raw, "target not visible", "prose:not_visible", not_visible=True)
    return _fail(raw, "no point found")


# ---------------------------------------------------------------------------------------------
# point + coarse depth (SPF style)

_DEPTH_KEYS = ("depth", "depth_m", "distance", "distance_m")
_DEPTH_PROSE_RE = re.compile(
    r"\b(?:depth|distance)\b\s*(?:of|is|=|:)?\s*(?:about|approximately|~)?\s*(" + _NUM + r")\s*(?:m\b|meters?\b|metres?\b)?",
    re.IGNORECASE,
)
_DEPTH_UNIT_RE = re.compile(r"(" + _NUM + r")\s*(?:m|meters?|metres?)\b", re.IGNORECASE)


def _depth_value(value: Any) -> float | None:
    if isinstance(value, str):
        m = re.fullmatch(r"\s*(" + _NUM + r")\s*(?:m|meters?|metres?)?\s*", value, re.IGNORECASE)
        return _float(m.group(1)) if m else None
    return _number(value)


def _find_depth_json(value: Any, depth: int = 0) -> float | None:
    if depth > 8:
        return None
    if isinstance(value, dict):
        for key in _DEPTH_KEYS:
            if key in value:
                return _depth_value(value[key])
        for key in _POINT_KEYS:
            triple = _numbers(value.get(key), 3)
            if triple is not None:
                return triple[2]
        for sub in value.values():
            if isinstance(sub, (dict, list)):
                d = _find_depth_json(sub, depth + 1)
                if d is not None:
                    return d
    elif isinstance(value, list):
        for item in value:
            if isinstance(item, (dict, list)):
                d = _find_depth_json(item, depth + 1)
                if d is not None:
                    return d
    return None


def parse_point_depth(
    text: str,
    image_size: tuple[int, int],
    coord_format: CoordFormat | str = CoordFormat.PIXEL,
    *,
    order: str = "xy",
    model_input_size: tuple[int, int] | None = None,
) -> PointDepthParse:
    """Read a point and a coarse depth in metres (See-Point-Fly style answers).

    Accepted: JSON with a point (any syntax of :func:`parse_point`) and a ``depth`` /
    ``depth_m`` / ``distance`` / ``distance_m`` value (a number or ``"3.5 m"``); a point given
    as a triple ``[x, y, depth]``; prose ``depth: 3.5 m`` / ``distance is 3.5 meters`` next to a
    point. The depth must be finite and positive; the point follows :func:`parse_point`'s rules.
    """
    raw = text if isinstance(text, str) else repr(text)
    if not isinstance(text, str):
        return PointDepthParse(False, None, None, raw, f"text must be str, got {type(text).__name__}")
    if len(text) > MAX_TEXT_CHARS:
        return PointDepthParse(False, None, None, raw, f"text longer than {MAX_TEXT_CHARS} characters")
    depth: float | None = None
    point_text = text
    for _, value in _json_values(text):
        depth = _find_depth_json(value)
        if depth is not None:
            if isinstance(value, dict):
                # a triple [x, y, d] under a point key: re-read it as the pair [x, y]
                for key in _POINT_KEYS:
                    triple = _numbers(value.get(key), 3)
                    if triple is not None:
                        point_text = json.dumps({key: triple[:2]})
            break
    if depth is None:
        m = _DEPTH_PROSE_RE.search(text)
        if m is None:
            m = _DEPTH_UNIT_RE.search(text)
        if m is not None:
            depth = _float(m.group(1))
    if depth is None:
        return PointDepthParse(False, None, None, raw, "no depth found")
    if not (math.isfinite(depth) and depth > 0.0):
        return PointDepthParse(False, None, None, raw, f"depth {depth} is not finite and positive")
    point = parse_point(point_text, image_size, coord_format, order=order, model_input_size=model_input_size)
    if not point.ok:
        return PointDepthParse(False, None, None, raw, point.reason)
    return PointDepthParse(True, point.uv, float(depth), raw)


# ---------------------------------------------------------------------------------------------
# status

_STATUS_RE = re.compile(r"(?<![A-Za-z0-9_])(continue|stop|lost)(?![A-Za-z0-9_])", re.IGNORECASE)


_PLACE_FIRST_AFTER_RE = re.compile(r"(?<![A-Za-z0-9_])lost[\s:,.;\-\u2013\u2014(*\"']*first(?![A-Za-z0-9_])", re.IGNORECASE)
_PLACE_FIRST_RE = re.compile(r"(?<![A-Za-z0-9_])first[\s_-]*(?:frame|image)(?![A-Za-z0-9_])", re.IGNORECASE)
_PLACE_KEYFRAME_RE = re.compile(r"(?<![A-Za-z0-9_])key[\s_-]?frame[\s_]*#?\s*(\d{1,3})(?![A-Za-z0-9_])", re.IGNORECASE)


def _seen_image(text: str, n_keyframes: int | None) -> tuple[int | None, str]:
    """The image a LOST answer names as the last to show the target (see the module
    docstring), and why there is none when a place was named but not taken."""
    texts = [text]
    if "last_seen" in text:
        texts += [
            "LOST " + value["last_seen"] for _, value in _json_values(text)
            if isinstance(value, dict) and isinstance(value.get("last_seen"), str)
        ]  # fmt: skip
    named: set[int] = set()
    for t in texts:
        named |= {0 for _ in _PLACE_FIRST_AFTER_RE.finditer(t)} | {0 for _ in _PLACE_FIRST_RE.finditer(t)}
        named |= {int(m.group(1)) for m in _PLACE_KEYFRAME_RE.finditer(t)}
    if not named:
        return None, ""
    if len(named) > 1:
        return None, f"place ambiguous: names images {sorted(named)}"
    index = named.pop()
    if index == 0 and _PLACE_KEYFRAME_RE.search(text) is not None:
        return None, "place: keyframe 0 does not exist"
    if n_keyframes is not None and index > n_keyframes:
        return None, f"place: keyframe {index} of {n_keyframes}"
    return index, ""


def parse_status(text: str, n_keyframes: int | None = None) -> StatusParse:
    """Read CONTINUE / STOP / LOST from a monitoring answer, and with a LOST the image that
    last showed the target (rules in the module docstring). ``n_keyframes``: how many
    keyframes the prompt held (a place beyond them is not taken); None: not checked."""
    raw = text if isinstance(text, str) else repr(text)
    if not isinstance(text, str):
        return StatusParse(False, None, raw, f"text must be str, got {type(text).__name__}")
    if len(text) > MAX_TEXT_CHARS:
        return StatusParse(False, None, raw, f"text longer than {MAX_TEXT_CHARS} characters")
    named = {m.group(1).upper() for m in _STATUS_RE.finditer(text)}
    if not named:
        return StatusParse(False, None, raw, "no status word (CONTINUE, STOP, LOST)")
    if len(named) > 1:
        return StatusParse(False, None, raw, f"ambiguous: names {sorted(named)}")
    status = MonitorStatus(named.pop())
    if status is not MonitorStatus.LOST:
        return StatusParse(True, status, raw)
    seen, why = _seen_image(text, n_keyframes)
    return StatusParse(True, status, raw, why, seen_image=seen)


# ---------------------------------------------------------------------------------------------
# subtasks

MAX_SUBTASKS = 64


def _subtask_list(value: Any) -> list | None:
    if isinstance(value, list):
        return value
    if isinstance(value, dict):
        for key in ("subtasks", "steps", "tasks"):
            if isinstance(value.get(key), list):
                return value[key]
    return None


def parse_subtasks(text: str) -> SubtasksParse:
    """Read a JSON list of subtask strings (bare, or under ``"subtasks"``; fences and prose
    around it ignored). The first JSON array/object found decides; it must hold 1 to
    ``MAX_SUBTASKS`` strings, each with at least one letter or digit. Anything else fails."""
    raw = text if isinstance(text, str) else repr(text)
    if not isinstance(text, str):
        return SubtasksParse(False, (), raw, f"text must be str, got {type(text).__name__}")
    if len(text) > MAX_TEXT_CHARS:
        return SubtasksParse(False, (), raw, f"text longer than {MAX_TEXT_CHARS} characters")
    for _, value in _json_values(text):
        items = _subtask_list(value)
        if items is None:
            continue
        if not items:
            return SubtasksParse(False, (), raw, "empty subtask list")
        if len(items) > MAX_SUBTASKS:
            return SubtasksParse(False, (), raw, f"{len(items)} subtasks, more than {MAX_SUBTASKS}")
        if not all(isinstance(s, str) for s in items):
            return SubtasksParse(False, (), raw, "subtasks must all be strings")
        cleaned = tuple(" ".join(s.split()) for s in items)
        if not all(re.search(r"\w", s) for s in cleaned):
            return SubtasksParse(False, (), raw, "an empty subtask")
        return SubtasksParse(True, cleaned, raw)
    return SubtasksParse(False, (), raw, "no JSON list of subtasks")
