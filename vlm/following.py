"""Following instructions: the language rule that says a task follows a moving target.

One rule, read by the pilot (which turns a pointed person into a standoff goal and ignores a
STOP that does not end a following task) and by the simulated VLM (whose completion rule for a
following task is in :mod:`vlm.sim.error_model`). A real model reads the same words.

An instruction (or subtask) *follows* when it holds one of the following phrases
(:data:`FOLLOW_PATTERNS`): ``follow``, ``track``, ``tail``, ``accompany``, ``stay behind`` /
``with`` / ``close to``, ``keep up with``, ``keep pace with``, ``go after``, ``walk along
with``, and one of the next six words is an animate noun or a personal pronoun
(:data:`ANIMATE_WORDS`): ``follow the person in the red jacket`` follows someone who moves,
``follow the path to the fountain`` and ``follow the assembly line`` follow a route (a static
thing) and are ordinary navigation. It follows *until the target stops* when it also holds ``until`` / ``till`` /
``when`` / ``once`` / ``as soon as`` + a subject + ``stop(s)`` / ``halt(s)`` / ``stand(s)
still`` / ``come(s) to a stop`` (``until he stops``, ``when the man with the cart halts``).
A following task without it has no end the model can see: it lasts as long as the operator
lets it (the task's duration).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["FollowIntent", "follow_intent", "FOLLOW_PATTERNS", "ANIMATE_WORDS"]

#: Words for someone who moves by themselves (a person, an animal) and personal pronouns.
ANIMATE_WORDS = frozenset(
    """person people man men woman women boy girl child children kid kids pedestrian pedestrians walker walkers
    jogger joggers runner runners cyclist cyclists worker workers guard visitor visitors tourist tourists courier
    shopper shoppers passenger passengers lady gentleman guy officer porter vendor cleaner dog him her them""".split()
)

#: Phrases that make an instruction a following task (regular expressions on lower case text).
FOLLOW_PATTERNS = (
    r"\bfollow(?:s|ing)?\b",
    r"\btrack(?:s|ing)?\b(?!\s+(?:of|field|lane))",
    r"\btail(?:s|ing)?\b(?=\s+(?:the|a|an|him|her|them)\b)",
    r"\baccompan(?:y|ies|ying)\b",
    r"\bstay(?:s|ing)?\s+(?:right\s+|close\s+)?(?:behind|with|close\s+to|near)\b(?=\s+(?:the|a|an|him|her|them)\b)",
    r"\bkeep(?:s|ing)?\s+(?:up|pace)\s+with\b",
    r"\bgo(?:es|ing)?\s+after\b(?=\s+(?:the|a|an|him|her|them)\b)",
    r"\bwalk(?:s|ing)?\s+along\s+with\b",
)
_FOLLOW_RE = re.compile("|".join(FOLLOW_PATTERNS))
_UNTIL_STOP_RE = re.compile(
    r"\b(?:until|till|til|when|once|as\s+soon\s+as)\s+(?:he|she|they|it|(?:the|that|this)\s+[\w\s]{1,40}?)\s+"
    r"(?:stops|stop|halts|halt|stands\s+still|stand\s+still|comes\s+to\s+a\s+stop|come\s+to\s+a\s+stop|has\s+stopped|have\s+stopped)\b"
)


@dataclass(frozen=True)
class FollowIntent:
    """A following instruction.

    text : the instruction or subtask it was read from
    until_stop : True when it ends once the followed target stops ("until he stops")
    """

    text: str
    until_stop: bool


def follow_intent(text: str) -> FollowIntent | None:
    """The following intent of an instruction or subtask, or None when it does not follow.

    >>> follow_intent("Follow the person in the red jacket around the fountain").until_stop
    False
    >>> follow_intent("Stay behind the man with the cart until he stops, then stop next to him").until_stop
    True
    >>> follow_intent("Fly to the red van") is None
    True
    """
    if not isinstance(text, str):
        return None
    low = " ".join(text.lower().split())
    for m in _FOLLOW_RE.finditer(low):
        after = re.findall(r"[a-z']+", low[m.end():])[:6]
        if any(w in ANIMATE_WORDS for w in after):
            return FollowIntent(text, bool(_UNTIL_STOP_RE.search(low)))
    return None
