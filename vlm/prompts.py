"""Versioned prompt templates for the decision agent, the monitoring agent and decomposition.

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
]

IMAGE_PLACEHOLDER = "<image>"
TEMPLATE_NAMES = ("decision", "monitor", "decompose")
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
    ``[first, *keyframes, latest]``.
    """
    tpl = load_template("monitor")
    first = _check_image(first, "first")
    latest = _check_image(latest, "latest")
    keyframes = [_check_image(k, f"keyframes[{i}]") for i, k in enumerate(keyframes)]
    parts = [tpl.render("user_head", subtask=_one_line(subtask, "subtask"))]
    if keyframes:
        parts += [tpl.render("keyframe", index=i + 1) for i in range(len(keyframes))]
    else:
        parts.append(tpl.render("no_keyframes"))
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


def _template_regex(tpl: PromptTemplate, section: str, fields: Mapping[str, str]) -> re.Pattern:
    """A regex matching a rendered section, with named groups for ``fields``."""
    pattern = re.escape(tpl.sections[section])
    for name, group in fields.items():
        pattern = pattern.replace(re.escape("$" + name), f"(?P<{name}>{group})")
    return re.compile(pattern)


def parse_prompt(messages: Sequence[ChatMessage]) -> DecisionPrompt | MonitorPrompt | DecomposePrompt | None:
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
        head = _template_regex(tpl, "user_head", {"subtask": r"[^\n]+"})
        m = head.match(user)
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
    return None


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
    """Schema of the decision answer ``{"point_2d": [x, y]}`` (integer pixels)."""
    return {
        "type": "object",
        "properties": {
            "point_2d": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 2, "maxItems": 2}
        },
        "required": ["point_2d"],
        "additionalProperties": False,
    }


def status_schema() -> dict:
    """Schema of a structured monitoring answer ``{"status": "STOP"}``."""
    return {
        "type": "object",
        "properties": {"status": {"type": "string", "enum": ["CONTINUE", "STOP", "LOST"]}},
        "required": ["status"],
        "additionalProperties": False,
    }


def subtasks_schema() -> dict:
    """Schema of the decomposition answer: a non-empty JSON array of non-empty strings."""
    return {"type": "array", "items": {"type": "string", "minLength": 1}, "minItems": 1}
