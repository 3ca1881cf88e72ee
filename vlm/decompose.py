"""Task decomposition: one VLM call, and a deterministic splitter when the call fails.

:func:`decompose` asks the backend once with the decomposition prompt
(:func:`vlm.prompts.build_decompose_prompt`, structured output :func:`vlm.prompts.subtasks_schema`)
and parses the answer strictly (:func:`vlm.parsing.parse_subtasks`). On any failure (no
backend, timeout, server error, unparsable or empty answer) it falls back to
:func:`split_instruction`.

The fallback splitter
---------------------
Works on the instruction with whitespace collapsed. It cuts at

1. sentence ends: ``.``, ``!`` or ``?`` followed by a space (so ``2.5 m`` stays whole) or,
   after a letter, directly by a capital (``hallway.Go``); and ``;``;
2. sequencing connectives: ``then``, ``and then``, ``after that``, ``and after that``,
   ``afterwards`` (the connective itself is dropped, with a comma around it);
3. a comma followed by a movement verb (``go``, ``turn``, ``fly``, ... see
   :data:`MOVEMENT_VERBS`, optionally after ``and``): ``walk to the stairs, turn right``.
   Not at the first comma of a clause that starts with a subordinator or a place preposition
   (``once``, ``when``, ``after``, ``before``, ``as soon as``, ``until``, ``if``, ``while``,
   ``at``, ``in``, ``on``, ``upon``, ``from``, ``inside``, ``outside``): ``once you reach the
   top, turn left`` and ``at the landing, turn right`` stay one subtask each;
4. a closing clause joined by ``and`` (with or without a comma): ``and`` followed by one of
   :data:`CLOSING_VERBS` (``stop``, ``land``, ``hover``, ``halt``, ``wait``, ``finish``,
   ``park``, and ``find``, which opens the leg to the goal) and at least one more word, or by ``end`` before a place preposition (``and end
   at the corral``; ``the couch and end table`` is no clause): ``turn left at the yellow forklift and stop
   in front of the fuel pump`` -> ``turn left at the yellow forklift`` / ``stop in front of the
   fuel pump``; ``walk past the sofa and wait by the door``; ``, and finally stop at the
   press`` (``finally`` / ``lastly`` / ``eventually`` may come between). A bare ``... and stop.`` stays
   whole (it closes the same leg), and so does a clause of one word before it (``stop and
   wait by the door``) or one that names nothing to reach (``keep going and stop at the blue
   door``, ``go on and stop next to the man``: :func:`vlm.sim.grounding.names_target`), which
   on its own would be a subtask no monitor could complete.
   ``then hover in front of ...`` is already cut by rule 2. A closing clause that only
   refers back (``and stop next to it``) is joined again by :func:`attach_back_references`.
   Rule 3's exception for clauses opening with a subordinator does not apply: ``in the
   bedroom take a left, and stop in the doorway`` is cut.

Pieces are stripped of surrounding punctuation and whitespace; pieces without a letter or
digit are dropped. Nothing else is removed, so the word tokens of the subtasks, in order, are
the instruction's word tokens minus the dropped connectives (:data:`CONNECTIVE_WORDS`); that
is the coverage property the tests check on every R2R instruction. The order is the text
order: ``before`` / ``after`` clauses are not reordered (``turn left after the tree`` stays as
written; reordering needs parsing we do not trust without a model).

Back-references
---------------
A subtask is flown and monitored on its own, so one that only points back at the previous
subtask's target (``There's a vending machine along this corridor. Go to it.`` -> ``go to it``)
names nothing the agents can find. :func:`attach_back_references` joins such a subtask to the
one before it (``"..., go to it"``); :func:`decompose_detailed` applies it to every
decomposition, the model's and the fallback's. A subtask counts as a back-reference when it
holds one of :data:`BACK_REFERENCE_WORDS` and every other word is a movement verb, a function
word (:data:`_FILLER_WORDS`, the speaker's ``me`` / ``us`` among them) or a distance: ``go to
it``, ``stop there``, ``land right next to it``, ``take me there``, ``hover about a metre above
it``; ``go to that door`` names a door and stays. So does one whose first reference points back
(:func:`opens_with_back_reference`: ``stop beside it, across from office 105``). A subtask that only closes the one before it
(every word in :data:`CLOSING_ONLY_WORDS`: ``stop``, ``then land``) is joined the same way: on
its own it names nothing a monitor could judge complete. Likewise a statement that only sets the
scene or says what the speaker wants (``You're at the end of the hall. Fly back past ...``, ``I
need a coffee. Take me to the counter ...``, ``I'm at the fish stall. Go east ...``: it opens
with one of :data:`CONTEXT_OPENERS` and holds no movement verb) has nothing to complete; it is
joined to the subtask after it, or after the last step to the one before it
(:func:`attach_context`), and a subtask that names nothing to reach is joined to the next
(``leave the study``, ``follow the hallway west``: :func:`attach_transit`): its end no
monitor can see except as arriving where the next subtask begins.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, replace

from vlm.parsing import parse_subtasks
from vlm.prompts import build_decompose_prompt, subtasks_schema
from vlm.types import VlmBackend, VlmError, VlmResponse

__all__ = [
    "DecompositionError",
    "Decomposition",
    "decompose",
    "decompose_detailed",
    "split_instruction",
    "attach_back_references",
    "opens_with_back_reference",
    "attach_context",
    "is_context",
    "attach_transit",
    "CONTEXT_OPENERS",
    "BACK_REFERENCE_WORDS",
    "MOVEMENT_VERBS",
    "CLOSING_VERBS",
    "CLOSING_ONLY_WORDS",
    "CONNECTIVE_WORDS",
]

log = logging.getLogger(__name__)

MOVEMENT_VERBS = (
    "approach", "ascend", "bear", "circle", "climb", "come", "continue", "cross", "cut",
    "descend", "drop", "duck", "enter", "exit", "face", "fly", "follow", "go", "halt", "head",
    "hover", "keep", "land", "leave", "loop", "make", "move", "navigate", "pass", "proceed",
    "return", "rise", "rotate", "stand", "step", "stop", "swing", "take", "travel", "turn",
    "veer", "wait", "walk",
)  # fmt: skip
#: Verbs that open a closing clause ("... and stop at the door"); rule 4 of the splitter.
CLOSING_VERBS = ("stop", "land", "hover", "halt", "wait", "finish", "park", "find")
#: Words of a subtask that only closes the one before it (``stop``, ``then land there``); such
#: a subtask is joined to the previous one like a back-reference.
CLOSING_ONLY_WORDS = (frozenset(CLOSING_VERBS) - {"find"}) | frozenset(
    "there here it now please right just and then immediately finally".split()
)
#: ``end`` closes only before a place (``and end at the corral``; ``and end table`` is a noun)
_END_PLACE = r"end\s+(?:up\s+)?(?:at|in|on|by|near|next|beside|between|under|above|below|behind)\b"
#: Words the splitter may drop at a cut (and only there).
CONNECTIVE_WORDS = frozenset({"then", "and", "after", "that", "afterwards"})
_SUBORDINATORS = (
    "once", "when", "after", "before", "as soon as", "until", "if", "while",
    "at", "in", "on", "upon", "from", "inside", "outside",
)  # fmt: skip

_VERBS = "|".join(MOVEMENT_VERBS)
_CUT_RE = re.compile(
    r"(?P<sentence>(?<=[.!?])\s+|(?<=[^\W\d_][.!?])(?=(?-i:[A-Z])))"
    r"|(?P<semicolon>\s*;\s*)"
    r"|(?P<connective>\s*,?\s*\b(?:and\s+then|and\s+after\s+that|after\s+that|afterwards|then)\b\s*,?\s*)"
    r"|(?P<closing>\s*,?\s+and\s+(?=(?:(?:finally|lastly|eventually)\s+)?(?:(?:" + "|".join(CLOSING_VERBS)
    + r")\b[ ,]*[^\W_]|" + _END_PLACE + r")))"
    r"|(?P<verb>\s*,\s*(?:and\s+)?(?=(?:" + _VERBS + r")\b))",
    re.IGNORECASE,
)
_STRIP = " \t,.;:!?"

#: words by which a subtask points back at the previous subtask's target
BACK_REFERENCE_WORDS = frozenset({"it", "there", "them", "that", "this", "one", "him", "her"})
_FILLER_WORDS = frozenset(MOVEMENT_VERBS) | frozenset(
    {
        "a", "about", "above", "all", "and", "around", "at", "away", "back", "behind", "below", "beside",
        "by", "close", "closer", "down", "front", "in", "into", "just", "near", "next", "now", "of", "off",
        "on", "onto", "over", "please", "right", "the", "then", "to", "toward", "towards", "under", "up",
        "with", "you", "your", "its", "me", "us",
        # a distance says where to stand, not what to reach ("hover about a metre above it")
        "metre", "metres", "meter", "meters", "m", "cm", "foot", "feet", "half", "couple", "few",
    }
)  # fmt: skip
#: openings of a statement that describes the scene instead of asking for a movement
CONTEXT_OPENERS = (
    "you're", "you are", "there's", "there is", "there are", "we're", "we are", "this is",
    "i need", "i'd like", "i would like", "i want", "we need", "we'd like", "we would like", "we want",
    "i'm", "i am", "i could", "we could",
)  # fmt: skip
_WORD_RE = re.compile(r"[^\W_]+(?:'[^\W_]+)?")


class DecompositionError(ValueError):
    """The instruction has no words to decompose."""


@dataclass(frozen=True)
class Decomposition:
    """Result of :func:`decompose_detailed`.

    Attributes
    ----------
    subtasks : tuple of str, non-empty, in execution order
    source : ``"vlm"`` or ``"fallback"``
    reason : why the fallback was used ("" for ``"vlm"``)
    response : the backend's response, if a call was made
    """

    subtasks: tuple[str, ...]
    source: str
    reason: str = ""
    response: VlmResponse | None = None


def _check_instruction(instruction: object) -> str:
    if not isinstance(instruction, str):
        raise DecompositionError(f"instruction must be a str, got {type(instruction).__name__}")
    text = " ".join(instruction.split())
    if not re.search(r"[^\W_]", text):
        raise DecompositionError(f"instruction has no words: {instruction!r}")
    return text


def split_instruction(instruction: str) -> list[str]:
    """Deterministic fallback: split ``instruction`` into ordered subtasks (rules above).

    Returns a non-empty list of non-empty strings; raises :class:`DecompositionError` if the
    instruction has no letter or digit.
    """
    text = _check_instruction(instruction)
    pieces: list[str] = []
    start = 0
    for m in _CUT_RE.finditer(text):
        clause = text[start : m.start()]
        if m.lastgroup == "verb" and _starts_with_subordinator(clause) and "," not in clause:
            continue
        if m.lastgroup == "closing" and (len(_WORD_RE.findall(clause)) < 2 or not _names_target(clause)):
            continue
        pieces.append(clause)
        start = m.end()
    pieces.append(text[start:])
    out = [p.strip(_STRIP) for p in pieces]
    out = [p for p in out if re.search(r"[^\W_]", p)]
    if not out:  # cannot happen for text with a word character; kept as a guard
        raise DecompositionError(f"instruction has no words: {instruction!r}")
    return out


def _names_target(text: str) -> bool:
    """:func:`vlm.sim.grounding.names_target` (imported here: ``vlm.sim`` imports this module)."""
    from vlm.sim.grounding import names_target

    return names_target(text)


def _is_back_reference(subtask: str) -> bool:
    words = [w.lower() for w in _WORD_RE.findall(subtask)]
    if words and all(w in CLOSING_ONLY_WORDS for w in words):
        return True  # "stop", "land there": closes the previous subtask
    return any(w in BACK_REFERENCE_WORDS for w in words) and all(
        w in BACK_REFERENCE_WORDS or _is_filler(w) for w in words
    )


def _is_filler(word: str) -> bool:
    """A word of :data:`_FILLER_WORDS` or a number (``land 2 m in front of it``)."""
    return word in _FILLER_WORDS or word.isdigit()


#: pronouns that always point back (``him`` / ``her``: the person a following leg named,
#: ``then stop next to him``; ``its`` / ``their``: ``stop in front of its middle``, a part of
#: what the previous subtask named)
_PRONOUNS = frozenset({"it", "its", "there", "them", "their", "him", "her"})


def opens_with_back_reference(subtask: str) -> bool:
    """Whether the subtask's first reference points back: movement verbs and function words,
    then ``it`` / ``its`` / ``there`` / ``them`` / ``their`` / ``him`` / ``her`` (or ``that`` / ``this`` / ``one`` closed by punctuation
    or the end). ``stop beside it, across from office 105`` does: its goal is the previous
    subtask's target, ``office 105`` only says where to stand; ``go to that door`` does not."""
    low = subtask.lower()
    found = list(_WORD_RE.finditer(low))
    for k, m in enumerate(found):
        w = m.group(0)
        if w in _PRONOUNS:
            return True
        if w in BACK_REFERENCE_WORDS:
            nxt = found[k + 1] if k + 1 < len(found) else None
            return nxt is None or bool(re.search(r"[^\w\s']", low[m.end() : nxt.start()]))
        if not _is_filler(w):
            return False
    return False


def attach_back_references(subtasks: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Join every subtask that only refers back (module docstring) to the one before it.

    ``["There's a vending machine along this corridor", "Go to it"]`` ->
    ``("There's a vending machine along this corridor, Go to it",)``. The first subtask has
    nothing to refer to and stays; order and words are kept.
    """
    out: list[str] = []
    for sub in subtasks:
        if out and (_is_back_reference(sub) or opens_with_back_reference(sub)):
            out[-1] = f"{out[-1]}, {sub}"
        else:
            out.append(sub)
    return tuple(out)


def is_context(subtask: str) -> bool:
    """Whether ``subtask`` only sets the scene or says what the speaker wants: it opens with one
    of :data:`CONTEXT_OPENERS` and holds no movement verb (module docstring)."""
    low = " ".join(subtask.lower().replace("\u2019", "'").split())
    words = set(_WORD_RE.findall(low))
    return any(low == o or low.startswith(o + " ") for o in CONTEXT_OPENERS) and not (words & set(MOVEMENT_VERBS))


def attach_context(subtasks: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Join every scene-setting statement (module docstring) to the subtask after it, and one
    with no subtask after it to the one before it (a statement after the last step is no step).

    ``["You're at the end of the hall", "Fly back past the snack machine"]`` ->
    ``("You're at the end of the hall, Fly back past the snack machine",)``; ``["Where's the
    vending machine", "I could really use a coffee"]`` -> ``("Where's the vending machine, I
    could really use a coffee",)``. A statement alone stays; order and words are kept.
    """
    out = list(_join_to_next(subtasks, is_context))
    if len(out) > 1 and is_context(out[-1]):
        out[-2:] = [f"{out[-2]}, {out[-1]}"]
    return tuple(out)


def attach_transit(subtasks: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Join every subtask that names nothing to reach (:func:`vlm.sim.grounding.names_target`:
    ``leave the study``, ``follow the hallway west``, ``turn left``) to the subtask after it.

    Such a subtask is a way, not a place: no monitor can see it done except by arriving where
    the next one begins, so on its own it holds the task until the time limit. Joined, it is
    the first leg of the next subtask, whose completion is judged on that subtask's target
    (the leg rule of every prompt). ``["Leave the study", "go past the ironing board"]`` ->
    ``("Leave the study, go past the ironing board",)``. The last subtask stays (nothing after
    it to arrive at); order and words are kept.
    """
    return _join_to_next(subtasks, lambda sub: not _names_target(sub))


def _join_to_next(subtasks, joins) -> tuple[str, ...]:
    """Join every subtask for which ``joins(subtask)`` holds (after any joining before it) to
    the one after it with ``", "``; one with nothing after it stays."""
    out: list[str] = []
    carry: str | None = None
    for sub in subtasks:
        if carry is not None:
            sub = f"{carry}, {sub}"
            carry = None
        if joins(sub):
            carry = sub
        else:
            out.append(sub)
    if carry is not None:
        out.append(carry)
    return tuple(out)


def _starts_with_subordinator(clause: str) -> bool:
    """True if the current clause (since the last sentence/connective cut) opens with one."""
    low = clause.strip(_STRIP).lower()
    return any(low == s or low.startswith(s + " ") for s in _SUBORDINATORS)


def decompose_detailed(
    instruction: str,
    backend: VlmBackend | None = None,
    *,
    deadline_s: float | None = None,
    max_new_tokens: int = 512,
    structured: bool = True,
) -> Decomposition:
    """Decompose with one VLM call; fall back to :func:`split_instruction` on any failure;
    scene-setting statements and back-references are attached to the subtask they belong to
    (:func:`attach_context`, :func:`attach_back_references`) and a subtask that names nothing to
    reach to the one after it (:func:`attach_transit`), either way.

    ``structured`` passes :func:`vlm.prompts.subtasks_schema` as ``json_schema``.
    """
    dec = _decompose_raw(_check_instruction(instruction), backend, deadline_s, max_new_tokens, structured)
    return replace(dec, subtasks=attach_clauses(dec.subtasks))


def attach_clauses(subtasks: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """The subtasks as the pilot runs them: scene-setting statements, back-references and
    subtasks that name nothing to reach attached where they belong (:func:`attach_context`,
    :func:`attach_back_references`, :func:`attach_transit`, in that order)."""
    return attach_transit(attach_back_references(attach_context(subtasks)))


def count_steps(instruction: str) -> int:
    """How many subtasks the deterministic reading of ``instruction`` has
    (:func:`split_instruction`, then :func:`attach_clauses`): ``"Find the green forklift and
    stop next to it."`` has one, its closing clause only points back. Raises
    :class:`DecompositionError` for an instruction without words."""
    return len(attach_clauses(split_instruction(instruction)))


def _decompose_raw(
    text: str, backend: VlmBackend | None, deadline_s: float | None, max_new_tokens: int, structured: bool
) -> Decomposition:
    if backend is None:
        return Decomposition(tuple(split_instruction(text)), "fallback", "no backend")
    messages, images = build_decompose_prompt(text)
    try:
        response = backend.complete(
            messages,
            images,
            deadline_s=deadline_s,
            json_schema=subtasks_schema() if structured else None,
            max_new_tokens=max_new_tokens,
            cache_key="decompose",
        )
    except VlmError as exc:
        log.warning("decomposition call raised %s; using the fallback splitter", exc)
        return Decomposition(tuple(split_instruction(text)), "fallback", f"backend raised: {exc}")
    if not response.ok:
        log.warning("decomposition call failed (%s: %s); using the fallback splitter", response.status.value, response.error)
        return Decomposition(tuple(split_instruction(text)), "fallback", f"{response.status.value}: {response.error}", response)
    parsed = parse_subtasks(response.text)
    if not parsed.ok:
        log.warning("decomposition answer unparsable (%s): %r; using the fallback splitter", parsed.reason, response.text[:200])
        return Decomposition(tuple(split_instruction(text)), "fallback", f"parse: {parsed.reason}", response)
    return Decomposition(parsed.subtasks, "vlm", "", response)


def decompose(
    instruction: str,
    backend: VlmBackend | None = None,
    *,
    deadline_s: float | None = None,
    max_new_tokens: int = 512,
) -> list[str]:
    """Ordered, non-empty subtasks of ``instruction`` (see :func:`decompose_detailed`)."""
    return list(decompose_detailed(instruction, backend, deadline_s=deadline_s, max_new_tokens=max_new_tokens).subtasks)
