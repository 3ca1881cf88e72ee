"""Versioned prompt templates: OnFly's agents, decomposition, and the baselines' prompts.

Templates: ``decision``, ``monitor`` and ``decompose`` (OnFly); ``typefly`` (a skill program
over a detector's scene description), ``pivot`` (numbered arrows drawn on the image) and
``spf`` (a point and a travel distance) for the baselines of the paper's Table II.

The texts live in ``vlm/prompts/<name>.txt`` (package data). File format: lines starting with
``##`` are comments, one of them ``## version: <name>/v<k>``; a line ``[section]`` starts a
section; sections are :class:`string.Template` texts (``$subtask``). Any change of the text
must come with a new version (``tests/test_prompts.py`` pins each version's hash), so logs
that name a version name one exact text.

Builders return ``(messages, images)``: ``messages`` hold one ``<image>`` placeholder per image,
in the order of ``images``. Free text (subtask, instruction) is put on one line (runs of
whitespace collapse to one space) so the prompt's line structure cannot be broken by it.

Monitoring prompts are prefix-stable: system text, subtask, first frame, keyframes oldest
first, then the latest frame and the question. Between two calls of one subtask whose
keyframe lists share a prefix, the serialized prompts (:func:`prompt_segments`) share every
segment up to the first keyframe that differs, so a server with prefix caching reuses the
KV-cache of that part.

:func:`parse_prompt` inverts the builders; the simulated VLM uses it to know which prompt it
got (a real model reads the same text).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.resources
import math
import re
from dataclasses import dataclass
from string import Template
from typing import Mapping, Sequence

from vlm.types import ChatMessage, VlmImage

__all__ = [
    "IMAGE_PLACEHOLDER",
    "PromptError",
    "PromptTemplate",
    "load_template",
    "build_decision_prompt",
    "build_monitor_prompt",
    "build_decompose_prompt",
    "DecisionPrompt",
    "MonitorPrompt",
    "DecomposePrompt",
    "parse_prompt",
    "prompt_segments",
    "count_placeholders",
    "decision_schema",
    "status_schema",
    "subtasks_schema",
    "TEMPLATE_NAMES",
    "SceneObject",
    "build_typefly_prompt",
    "build_pivot_prompt",
    "build_spf_prompt",
    "TypeflyPrompt",
    "PivotPrompt",
    "SpfPrompt",
    "pivot_schema",
    "spf_schema",
    "SPF_MAX_DEPTH_M",
]

IMAGE_PLACEHOLDER = "<image>"
TEMPLATE_NAMES = ("decision", "monitor", "decompose", "typefly", "pivot", "spf")
#: the largest travel distance the ``spf`` template asks for, metres (its text says "1 to 10")
SPF_MAX_DEPTH_M = 10
_VERSION_RE = re.compile(r"^##\s*version:\s*(\S+)\s*$")
_SECTION_RE = re.compile(r"^\[([a-z_]+)\]\s*$")


class PromptError(ValueError):
    """A template file is malformed, or a builder got input it cannot put in a prompt."""


@dataclass(frozen=True)
class PromptTemplate:
    """One loaded template file.

    Attributes
    ----------
    name : str, e.g. ``"decision"``
    version : str, e.g. ``"decision/v1"``
    sections : mapping section name -> template text (no trailing newline)
    sha256 : str, hex digest of the file's bytes
    """

    name: str
    version: str
    sections: Mapping[str, str]
    sha256: str

    def render(self, section: str, **values: object) -> str:
        """Substitute ``values`` into one section; a missing value raises :class:`PromptError`."""
        try:
            return Template(self.sections[section]).substitute(**values)
        except KeyError as exc:
            raise PromptError(f"template {self.version}: section {section!r} needs value {exc}") from None


@functools.lru_cache(maxsize=None)
def load_template(name: str) -> PromptTemplate:
    """Load ``vlm/prompts/<name>.txt``; raises :class:`PromptError` naming the file and fault."""
    if name not in TEMPLATE_NAMES:
        raise PromptError(f"unknown template {name!r}; valid: {list(TEMPLATE_NAMES)}")
    resource = importlib.resources.files("vlm").joinpath("prompts", f"{name}.txt")
    data = resource.read_bytes()
    version = None
    sections: dict[str, list[str]] = {}
    current: list[str] | None = None
    for lineno, line in enumerate(data.decode("utf-8").splitlines(), start=1):
        if line.startswith("##"):
            m = _VERSION_RE.match(line)
            if m:
                version = m.group(1)
            continue
        m = _SECTION_RE.match(line)
        if m:
            if m.group(1) in sections:
                raise PromptError(f"{name}.txt line {lineno}: section [{m.group(1)}] defined twice")
            current = sections.setdefault(m.group(1), [])
            continue
        if current is None:
            if line.strip():
                raise PromptError(f"{name}.txt line {lineno}: text before the first [section]")
            continue
        current.append(line)
    if version is None or not version.startswith(f"{name}/"):
        raise PromptError(f"{name}.txt: missing '## version: {name}/v<k>' line")
    return PromptTemplate(
        name=name,
        version=version,
        sections={k: "\n".join(v).strip("\n") for k, v in sections.items()},
        sha256=hashlib.sha256(data).hexdigest(),
    )


def _one_line(text: object, what: str) -> str:
    if not isinstance(text, str):
        raise PromptError(f"{what} must be a str, got {type(text).__name__}")
    line = " ".join(text.split())
    if not line:
        raise PromptError(f"{what} is empty")
    return line


def _check_image(image: object, what: str) -> VlmImage:
    if not isinstance(image, VlmImage):
        raise PromptError(f"{what} must be a VlmImage, got {type(image).__name__}")
    return image


# ---------------------------------------------------------------------------------------------
# builders


def build_decision_prompt(
    subtask: str, image: VlmImage, history_uv: tuple[float, float] | None = None
) -> tuple[list[ChatMessage], list[VlmImage]]:
    """Decision-agent prompt for one camera frame.

    Parameters
    ----------
    subtask : str, the current subtask
    image : VlmImage, the current camera frame
    history_uv : optional (u, v), pixels of ``image``: the previous 3D goal reprojected into
        this frame. Must lie inside the image (``[-0.5, W - 0.5)``); it is written rounded.
    """
    image = _check_image(image, "image")
    tpl = load_template("decision")
    w, h = image.size
    if history_uv is None:
        history = "none"
    else:
        try:
            u, v = float(history_uv[0]), float(history_uv[1])
        except (TypeError, ValueError, IndexError):
            raise PromptError(f"history_uv must be (u, v), got {history_uv!r}") from None
        if not (math.isfinite(u) and math.isfinite(v) and -0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5):
            raise PromptError(f"history_uv {history_uv!r} is outside the {w}x{h} image; pass None instead")
        history = f"({min(max(round(u), 0), w - 1)}, {min(max(round(v), 0), h - 1)})"
    messages = [
        ChatMessage("system", tpl.render("system")),
        ChatMessage("user", tpl.render("user", width=w, height=h, subtask=_one_line(subtask, "subtask"), history=history)),
    ]
    return messages, [image]


def build_monitor_prompt(
    subtask: str, first: VlmImage, keyframes: Sequence[VlmImage], latest: VlmImage
) -> tuple[list[ChatMessage], list[VlmImage]]:
    """Monitoring-agent prompt over the hybrid memory ``[o_1, Q_t, o_t]``.

    ``keyframes`` must already be in time order, oldest first. Images are returned as
    ``[first, *keyframes, latest]``. What changes least comes first (system, first frame,
    keyframes, subtask, latest frame): a subtask advance keeps the cached image prefix.
    """
    tpl = load_template("monitor")
    first = _check_image(first, "first")
    latest = _check_image(latest, "latest")
    keyframes = [_check_image(k, f"keyframes[{i}]") for i, k in enumerate(keyframes)]
    subtask = _one_line(subtask, "subtask")
    parts = [tpl.render("user_head")]
    if keyframes:
        parts += [tpl.render("keyframe", index=i + 1) for i in range(len(keyframes))]
    else:
        parts.append(tpl.render("no_keyframes"))
    parts.append(tpl.render("subtask", subtask=subtask))
    parts.append(tpl.render("user_tail"))
    messages = [ChatMessage("system", tpl.render("system")), ChatMessage("user", "\n".join(parts))]
    return messages, [first, *keyframes, latest]


def build_decompose_prompt(instruction: str) -> tuple[list[ChatMessage], list[VlmImage]]:
    """Task-decomposition prompt (text only)."""
    tpl = load_template("decompose")
    messages = [
        ChatMessage("system", tpl.render("system")),
        ChatMessage("user", tpl.render("user", instruction=_one_line(instruction, "instruction"))),
    ]
    return messages, []


@dataclass(frozen=True)
class SceneObject:
    """One detection as a TypeFly-style scene description writes it.

    Attributes
    ----------
    name : str, the detector's name for it (e.g. ``"red van"``)
    label : str, its class (e.g. ``"van"``)
    x, y : float, box centre as fractions of the image width and height, in [0, 1]
    w, h : float, box size as fractions of the image width and height, in [0, 1]
    """

    name: str
    label: str
    x: float
    y: float
    w: float
    h: float

    def __post_init__(self) -> None:
        for f in ("name", "label"):
            text = getattr(self, f)
            if not isinstance(text, str) or not _OBJECT_WORD_RE.fullmatch(" ".join(text.split())):
                raise PromptError(f"SceneObject.{f} must be words (letters, digits, spaces, - ' . /), got {text!r}")
            object.__setattr__(self, f, " ".join(text.split()))
        for f in ("x", "y", "w", "h"):
            v = getattr(self, f)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise PromptError(f"SceneObject.{f} must be a fraction in [0, 1], got {v!r}")

    def text(self) -> str:
        return f"{self.name} [{self.label}] x={self.x:.2f} y={self.y:.2f} w={self.w:.2f} h={self.h:.2f}"


_OBJECT_WORD_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9 '/.-]*")
_OBJECT_ITEM_RE = re.compile(
    r"(?P<name>[A-Za-z0-9][A-Za-z0-9 '/.-]*?) \[(?P<label>[A-Za-z0-9][A-Za-z0-9 '/.-]*)\] "
    r"x=(?P<x>[0-9.]+) y=(?P<y>[0-9.]+) w=(?P<w>[0-9.]+) h=(?P<h>[0-9.]+)"
)
_HISTORY_SEP = " | "


def build_typefly_prompt(
    instruction: str, image: VlmImage, objects: Sequence[SceneObject], history: Sequence[str] = ()
) -> tuple[list[ChatMessage], list[VlmImage]]:
    """TypeFly-style planning prompt: instruction, frame, detector scene description, skill log.

    Parameters
    ----------
    instruction : str, the whole navigation instruction
    image : VlmImage, the current camera frame
    objects : the detector's detections of this frame (written in order)
    history : executed skills with their outcome, oldest first (e.g. ``"find red van: found"``);
        each item is put on one line and must not contain ``" | "``
    """
    image = _check_image(image, "image")
    tpl = load_template("typefly")
    objs = list(objects)
    if not all(isinstance(o, SceneObject) for o in objs):
        raise PromptError("objects must be SceneObject values")
    items = [_one_line(h, f"history[{i}]") for i, h in enumerate(history)]
    if any(_HISTORY_SEP.strip() in h for h in items):
        raise PromptError("history items must not contain '|'")
    w, h = image.size
    user = tpl.render(
        "user",
        instruction=_one_line(instruction, "instruction"),
        width=w,
        height=h,
        objects="; ".join(o.text() for o in objs) if objs else "none",
        history=_HISTORY_SEP.join(items) if items else "none",
    )
    return [ChatMessage("system", tpl.render("system")), ChatMessage("user", user)], [image]


def build_pivot_prompt(
    instruction: str, image: VlmImage, arrows: Sequence[tuple[int, float, float]], n_pick: int
) -> tuple[list[ChatMessage], list[VlmImage]]:
    """PIVOT-style prompt: ``image`` already shows the numbered arrows; their endpoints are
    written as text too (what a reader of the drawn labels sees).

    Parameters
    ----------
    instruction : str
    image : VlmImage, the frame with the arrows drawn on it
    arrows : (label, u, v) per arrow: its number (distinct positive ints) and endpoint pixel
        inside the image; written rounded
    n_pick : int >= 1, how many arrows to choose at most
    """
    image = _check_image(image, "image")
    tpl = load_template("pivot")
    w, h = image.size
    if isinstance(n_pick, bool) or not isinstance(n_pick, int) or n_pick < 1:
        raise PromptError(f"n_pick must be an int >= 1, got {n_pick!r}")
    parts, labels = [], set()
    for a in arrows:
        try:
            label, u, v = int(a[0]), float(a[1]), float(a[2])
        except (TypeError, ValueError, IndexError):
            raise PromptError(f"arrows must be (label, u, v), got {a!r}") from None
        if label < 1 or label in labels:
            raise PromptError(f"arrow labels must be distinct positive ints, got {label}")
        if not (math.isfinite(u) and math.isfinite(v) and -0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5):
            raise PromptError(f"arrow {label} endpoint ({u}, {v}) is outside the {w}x{h} image")
        labels.add(label)
        parts.append(f"{label}: ({min(max(round(u), 0), w - 1)}, {min(max(round(v), 0), h - 1)})")
    if not parts:
        raise PromptError("a PIVOT prompt needs at least one arrow")
    user = tpl.render(
        "user", instruction=_one_line(instruction, "instruction"), count=len(parts), width=w, height=h,
        arrows="; ".join(parts), n_pick=n_pick,
    )  # fmt: skip
    return [ChatMessage("system", tpl.render("system")), ChatMessage("user", user)], [image]


def build_spf_prompt(instruction: str, image: VlmImage) -> tuple[list[ChatMessage], list[VlmImage]]:
    """See-Point-Fly-style prompt: point where to fly and how far (0 = the goal is reached)."""
    image = _check_image(image, "image")
    tpl = load_template("spf")
    w, h = image.size
    user = tpl.render("user", instruction=_one_line(instruction, "instruction"), width=w, height=h)
    return [ChatMessage("system", tpl.render("system")), ChatMessage("user", user)], [image]


# ---------------------------------------------------------------------------------------------
# reading prompts back


@dataclass(frozen=True)
class DecisionPrompt:
    """Fields of a decision prompt. ``image_size`` is (width, height) as written."""

    version: str
    subtask: str
    image_size: tuple[int, int]
    history_uv: tuple[int, int] | None


@dataclass(frozen=True)
class MonitorPrompt:
    """Fields of a monitoring prompt; its images are ``[first, *keyframes, latest]``."""

    version: str
    subtask: str
    n_keyframes: int


@dataclass(frozen=True)
class DecomposePrompt:
    """Fields of a decomposition prompt."""

    version: str
    instruction: str


@dataclass(frozen=True)
class TypeflyPrompt:
    """Fields of a TypeFly planning prompt (``objects`` as written, rounded to 2 decimals)."""

    version: str
    instruction: str
    image_size: tuple[int, int]
    objects: tuple[SceneObject, ...]
    history: tuple[str, ...]


@dataclass(frozen=True)
class PivotPrompt:
    """Fields of a PIVOT prompt: ``arrows`` as written, ``(label, u, v)`` integer pixels."""

    version: str
    instruction: str
    image_size: tuple[int, int]
    arrows: tuple[tuple[int, int, int], ...]
    n_pick: int


@dataclass(frozen=True)
class SpfPrompt:
    """Fields of a See-Point-Fly prompt."""

    version: str
    instruction: str
    image_size: tuple[int, int]


def _template_regex(tpl: PromptTemplate, section: str, fields: Mapping[str, str]) -> re.Pattern:
    """A regex matching a rendered section, with named groups for ``fields``."""
    pattern = re.escape(tpl.sections[section])
    for name, group in fields.items():
        pattern = pattern.replace(re.escape("$" + name), f"(?P<{name}>{group})")
    return re.compile(pattern)


def parse_prompt(
    messages: Sequence[ChatMessage],
) -> DecisionPrompt | MonitorPrompt | DecomposePrompt | TypeflyPrompt | PivotPrompt | SpfPrompt | None:
    """Which template built ``messages`` and with what values; None for any other chat."""
    if len(messages) != 2 or messages[0].role != "system" or messages[1].role != "user":
        return None
    system, user = messages[0].content, messages[1].content
    tpl = load_template("decision")
    if system == tpl.render("system"):
        m = _template_regex(tpl, "user", {"width": r"\d+", "height": r"\d+", "subtask": r"[^\n]+", "history": r"[^\n]+"}).fullmatch(user)
        if m is None:
            return None
        hist = re.fullmatch(r"\((\d+), (\d+)\)", m.group("history"))
        if hist is None and m.group("history") != "none":
            return None
        return DecisionPrompt(
            version=tpl.version,
            subtask=m.group("subtask"),
            image_size=(int(m.group("width")), int(m.group("height"))),
            history_uv=(int(hist.group(1)), int(hist.group(2))) if hist else None,
        )
    tpl = load_template("monitor")
    if system == tpl.render("system"):
        if not user.startswith(tpl.render("user_head")):
            return None
        m = re.search("^" + _template_regex(tpl, "subtask", {"subtask": r"[^\n]+"}).pattern + "$", user, re.MULTILINE)
        if m is None:
            return None
        n_keyframes = len(re.findall(_template_regex(tpl, "keyframe", {"index": r"\d+"}).pattern, user))
        return MonitorPrompt(version=tpl.version, subtask=m.group("subtask"), n_keyframes=n_keyframes)
    tpl = load_template("decompose")
    if system == tpl.render("system"):
        m = _template_regex(tpl, "user", {"instruction": r"[^\n]+"}).fullmatch(user)
        if m is None:
            return None
        return DecomposePrompt(version=tpl.version, instruction=m.group("instruction"))
    for name, reader in (("typefly", _read_typefly), ("pivot", _read_pivot), ("spf", _read_spf)):
        tpl = load_template(name)
        if system == tpl.render("system"):
            return reader(tpl, user)
    return None


def _read_typefly(tpl: PromptTemplate, user: str) -> TypeflyPrompt | None:
    fields_ = {"instruction": r"[^\n]+", "width": r"\d+", "height": r"\d+", "objects": r"[^\n]+", "history": r"[^\n]+"}
    m = _template_regex(tpl, "user", fields_).fullmatch(user)
    if m is None:
        return None
    objects: list[SceneObject] = []
    if m.group("objects") != "none":
        for item in m.group("objects").split("; "):
            om = _OBJECT_ITEM_RE.fullmatch(item)
            if om is None:
                return None
            try:
                objects.append(SceneObject(om.group("name"), om.group("label"), *(float(om.group(k)) for k in "xywh")))
            except (PromptError, ValueError):
                return None
    history = () if m.group("history") == "none" else tuple(m.group("history").split(_HISTORY_SEP))
    return TypeflyPrompt(
        tpl.version, m.group("instruction"), (int(m.group("width")), int(m.group("height"))), tuple(objects), history
    )


def _read_pivot(tpl: PromptTemplate, user: str) -> PivotPrompt | None:
    fields_ = {"instruction": r"[^\n]+", "count": r"\d+", "width": r"\d+", "height": r"\d+", "arrows": r"[^\n]+", "n_pick": r"\d+"}
    m = _template_regex(tpl, "user", fields_).fullmatch(user)
    if m is None:
        return None
    arrows = []
    for item in m.group("arrows").split("; "):
        am = re.fullmatch(r"(\d+): \((\d+), (\d+)\)", item)
        if am is None:
            return None
        arrows.append((int(am.group(1)), int(am.group(2)), int(am.group(3))))
    if len(arrows) != int(m.group("count")) or int(m.group("n_pick")) < 1:
        return None
    return PivotPrompt(
        tpl.version, m.group("instruction"), (int(m.group("width")), int(m.group("height"))), tuple(arrows), int(m.group("n_pick"))
    )


def _read_spf(tpl: PromptTemplate, user: str) -> SpfPrompt | None:
    m = _template_regex(tpl, "user", {"instruction": r"[^\n]+", "width": r"\d+", "height": r"\d+"}).fullmatch(user)
    if m is None:
        return None
    return SpfPrompt(tpl.version, m.group("instruction"), (int(m.group("width")), int(m.group("height"))))


def count_placeholders(messages: Sequence[ChatMessage]) -> int:
    """Number of ``<image>`` placeholders across all messages."""
    return sum(m.content.count(IMAGE_PLACEHOLDER) for m in messages)


def prompt_segments(messages: Sequence[ChatMessage], images: Sequence[VlmImage]) -> tuple[str, ...]:
    """The prompt as a sequence of segments, as a prefix cache sees it.

    Text pieces become ``"<role>:" + text`` segments, each image becomes
    ``"\\x00image:" + frame_id``. Two prompts share a KV-cache prefix exactly as far as their
    segment tuples share a prefix. Raises :class:`PromptError` if the placeholder count differs
    from ``len(images)``.
    """
    n = count_placeholders(messages)
    if n != len(images):
        raise PromptError(f"{n} <image> placeholders but {len(images)} images")
    out: list[str] = []
    it = iter(images)
    for msg in messages:
        pieces = msg.content.split(IMAGE_PLACEHOLDER)
        for k, piece in enumerate(pieces):
            if piece:
                out.append(f"{msg.role}:{piece}")
            if k < len(pieces) - 1:
                out.append("\x00image:" + next(it).frame_id)
        out.append("\x00end")
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# JSON schemas for structured output (fresh dicts: callers may mutate them)


def decision_schema() -> dict:
    """Schema of the decision answer (``decision/v3``): ``{"target_visible": true, "point_2d":
    [x, y]}`` (integer pixels) or ``{"target_visible": false, "point_2d": [x, y] | null}``.

    Both keys are required and nothing else is allowed (the form OpenAI-style ``strict``
    structured output needs); the flag comes first, so a constrained decoder commits to
    visibility before it writes a point. :func:`vlm.parsing.parse_point` reads a false flag as
    ``not_visible`` whatever ``point_2d`` holds; a valid point beside it is where the model
    would look for the target (``look_uv``).
    """
    return {
        "type": "object",
        "properties": {
            "target_visible": {"type": "boolean"},
            "point_2d": {
                "anyOf": [
                    {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 2, "maxItems": 2},
                    {"type": "null"},
                ]
            },
        },
        "required": ["target_visible", "point_2d"],
        "additionalProperties": False,
    }


def status_schema() -> dict:
    """Schema of a structured monitoring answer ``{"status": "STOP"}``; a LOST may add where the
    target was last visible, ``{"status": "LOST", "last_seen": "keyframe 2"}`` (``"first"`` or
    ``"keyframe N"``, read and checked by :func:`vlm.parsing.parse_status`: a plain string, since
    string ``pattern`` is a JSON-Schema keyword not every guided-decoding engine compiles)."""
    return {
        "type": "object",
        "properties": {
            "status": {"type": "string", "enum": ["CONTINUE", "STOP", "LOST"]},
            "last_seen": {"type": "string"},
        },
        "required": ["status"],
        "additionalProperties": False,
    }


def pivot_schema() -> dict:
    """Schema of a PIVOT answer: ``{"arrows": [3, 5]}`` or ``{"stop": true}``."""
    return {
        "type": "object",
        "properties": {
            "arrows": {"type": "array", "items": {"type": "integer", "minimum": 1}},
            "stop": {"type": "boolean"},
        },
        "additionalProperties": False,
    }


def spf_schema() -> dict:
    """Schema of a See-Point-Fly answer ``{"point_2d": [x, y], "depth": d}`` (d in 0..10 m)."""
    return {
        "type": "object",
        "properties": {
            "point_2d": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 2, "maxItems": 2},
            "depth": {"type": "integer", "minimum": 0, "maximum": SPF_MAX_DEPTH_M},
        },
        "required": ["point_2d", "depth"],
        "additionalProperties": False,
    }


def subtasks_schema() -> dict:
    """Schema of the decomposition answer: a non-empty JSON array of non-empty strings."""
    return {"type": "array", "items": {"type": "string", "minLength": 1}, "minItems": 1}
