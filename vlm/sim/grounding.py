"""What the simulated VLM can read off one annotated frame: named objects, regions, open space.

Pure functions over a :class:`vlm.types.FrameAnnotation`; nothing here sees more than the frame.
The grounding rule is stated in :mod:`vlm.sim.error_model`.
"""

from __future__ import annotations

import re
import unicodedata
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from vlm.decompose import MOVEMENT_VERBS
from vlm.types import FrameAnnotation, VisibleObject

__all__ = [
    "ATTRIBUTE_WORDS",
    "PHRASE_END_WORDS",
    "NON_OBJECT_WORDS",
    "names_target",
    "Match",
    "Region",
    "words",
    "ground",
    "ENTRANCE_LABELS",
    "entrance_places",
    "place_entrance",
    "region_of",
    "visible_regions",
    "anchor_pixel",
    "exploration_point",
]

#: Words that distinguish objects of one label (colour, size, material). Like every word that
#: modifies a mention from before (:func:`_modifiers_start`), one right before an object mention
#: must belong to the object's own name, aliases or label for the mention to count; they are
#: never a head (``names_target``) nor the noun a landmark locates (``locates_head``).
ATTRIBUTE_WORDS = frozenset(
    """red orange yellow green blue purple violet pink brown black white grey gray silver gold golden
    beige cyan magenta dark light big small large little tall short tiny huge long wide narrow high low
    wooden wood metal metallic glass brick stone concrete plastic steel iron old new round square""".split()
)
#: Words that cannot continue a noun phrase: after an object word they end its phrase, so that
#: word is the phrase's head. Any other word after it (``clock`` in ``wall clock``, ``pump`` in
#: ``fuel pump``) makes it a modifier, and the object is not named. Also numbers (``door
#: 103``), ``-ly`` adverbs, and ``-ed`` / ``-ing`` participles (``the sedan parked on the
#: right``, ``the person standing by``) end a phrase; so does punctuation. Every movement verb of
#: the splitter (:data:`vlm.decompose.MOVEMENT_VERBS`: ``cut through the gallery``, ``swing
#: left``) is one: a verb is never the noun a subtask names.
PHRASE_END_WORDS = frozenset(MOVEMENT_VERBS) | frozenset(
    """a an the this that these those it its it's them they their there here i you your me my we our one ones
    and or but nor so then than as if when while until till once before after because since where which who whose
    what whether to toward towards into onto in on at of off out by near nearby next beside besides behind between
    among through past along across around over under underneath beneath above below up down from with without
    within inside outside against beyond via upon about alongside opposite front back is are was were be been being
    am has have had do does did can could will would should shall may might must let s
    go goes went going gone fly flies flew flying move moves moving head heads heading turn turns turned turning
    stop stops stopping hover hovers hovering land lands landing continue continues continuing keep keeps keeping
    proceed walk walking travel travelling traveling approach approaching climb climbing descend descending ascend
    rise rotate cross crossing enter entering exit exiting leave leaving follow following pass passing reach
    reaching return wait halt stand step veer bear circle face facing find finding look search get come carry
    finish end stay squeeze duck check take make navigate head hold see sees saw seen
    left right straight ahead forward forwards backward backwards again slowly quickly carefully directly exactly
    just only also still very really please now first second third finally last north south east west
    all both each every some any no not none other another same such more most less least much many few little bit
    close closer closest far farther further furthest nearest somewhere anywhere everywhere nowhere away home
    too instead already soon later once twice""".split()
)
#: Words that name no object to reach: the phrase-end words and places (rooms and the places a
#: building or a yard holds too, a gallery, a café, an orchard: where, not what), directions
#: and units. A building or a structure is an object, a landmark to fly by ("the trough by the
#: barn"), so ``barn``, ``house``, ``shed``, ``porch`` stay out of this list, as does a word some
#: committed scene names an object by (``terrace``, ``platform``, ``reception``, ``closet``).
#: A subtask whose words are all of these (or numbers) names no target (``fly forward``,
#: ``continue through the intersection``, ``go to the end of the corridor``).
NON_OBJECT_WORDS = PHRASE_END_WORDS | frozenset(
    """corridor hallway hall intersection junction crossing corner end middle center centre side edge lane road street
    path footpath way aisle area space spot place position room level storey story floor ground air altitude height sky top bottom
    distance direction degree metre meter foot feet yard inch m cm half halfway couple time times view sight
    zero two three four five six seven eight nine ten few
    study bedroom bathroom kitchen kitchenette laundry lobby foyer
    gallery museum shop store cafe cafeteria canteen restaurant library gym gymnasium classroom auditorium
    workshop studio lab laboratory clinic ward chapel theater theatre restroom washroom lavatory storeroom stockroom
    breakroom boardroom pantry attic basement cellar vestibule entryway atrium courtyard concourse orchard""".split()
)
_DETERMINERS = frozenset("the a an this that these those".split())
#: words that count the objects of a noun phrase; they say how many, not which
_COUNT_WORDS = frozenset("zero two three four five six seven eight nine ten few several both".split())
#: a mention after one of these is a landmark flown past, not the goal ("fly past the bench to ...")
_PAST_WORDS = frozenset("past passed beyond".split())
#: a mention after one of these is a route flown along ("continue along the wall"): a landmark,
#: and a text whose only mentions are routes names nothing to reach
_ROUTE_WORDS = frozenset(["along"])
#: labels of the objects through which one enters a place (``kitchen doorway``, ``entrance to
#: the bike cage``): what a camera shows of a room it is not in
ENTRANCE_LABELS = frozenset("doorway door gate entrance archway opening".split())
#: a place named right after one of these is where the target is or where to go ("the fridge
#: *in* the kitchen", "fly *into* the kitchen", "go *to* the storage room", "*enter* the study");
#: after any other word but those of :data:`_LEAVE_WORDS` it is a route or a place flown past
#: ("follow the hallway", "through the living room", "past the kitchen"). From inside a route
#: the entrance to it is behind the camera's side of the doorway, not the way on
_INTO_WORDS = frozenset("in inside into to enter enters entering reach reaches reaching".split())
#: a place named right after one of these (or after ``out of``) is the one the vehicle is in and
#: is to leave ("*leave* the study", "*exit* the small meeting room", "fly *out of* the
#: kitchen"): its entrance is the way out
_LEAVE_WORDS = frozenset("leave leaves leaving exit exits exiting".split())
#: prepositions by which a noun phrase says where its head is ("the charger *by* the blue car"):
#: the object named after one, when a noun comes right before it, is a landmark of that noun
_LOCATING_PREPOSITIONS = (("in", "front", "of"), ("next", "to"), ("across", "from"), ("by",), ("near",), ("beside",),
                          ("behind",), ("opposite",), ("in",), ("inside",), ("on",), ("under",), ("above",))
#: prepositions that open a phrase after a noun saying which one it is: where it is (the
#: locating ones) or what it has (``the man with the cart``)
_POSTMODIFIER_PREPOSITIONS = _LOCATING_PREPOSITIONS + (("with",),)
#: nouns that name a part of a place or a side, not a landmark (``the tree on the left side``,
#: ``the bench at the far end``): a locating phrase with one as its head says which way, not
#: next to what
_RELATIONAL_WORDS = frozenset("side end middle center centre corner edge top bottom half part front back".split())
#: prepositions that open a place phrase ("on the upper deck, stop beside the chair")
_PLACE_OPENERS = frozenset("on in at inside outside upon from".split())
#: nouns ending in -ing or -ed that are not participles (they can continue a noun phrase)
_ING_NOUNS = frozenset("building ceiling railing awning painting railing sibling shed bed sled".split())
_WORD_RE = re.compile(r"[a-z0-9]+")
_NOT_RE = re.compile(r"n['\u2019]t\b")
_IRREGULAR_NOT_RE = re.compile(r"\b(won|can|shan)['\u2019]t\b")
_IRREGULAR_NOT = {"won": "will not", "can": "can not", "shan": "shall not"}
_CLITIC_RE = re.compile(r"['\u2019](re|ll|ve|d|m)\b")
_CLITICS = {"re": "are", "ll": "will", "ve": "have", "d": "would", "m": "am"}
_BREAK_RE = re.compile(r"[^\sa-z0-9'\u2019-]")
_ES_STEMS = ("ch", "sh", "x", "z", "ss")


def _singular(w: str) -> str:
    if len(w) > 3 and w.endswith("ies"):
        return w[:-3] + "y"
    if len(w) > 3 and w.endswith("es") and w[:-2].endswith(_ES_STEMS):
        return w[:-2]
    if len(w) > 3 and w.endswith("s") and not w.endswith("ss"):
        return w[:-1]
    return w


def _is_identifier(word: str) -> bool:
    """A word that tells one of a kind from the others at the end of a name: a number or a
    single letter (``checkout 2``, ``rack A``)."""
    return word.isdigit() or (len(word) == 1 and word.isalpha())


def _lower(text: str) -> str:
    """Lower case with accents dropped (``café`` -> ``cafe``: the words are ASCII) and
    contractions spelled out (``you're`` -> ``you are``, ``don't`` -> ``do not``): a clitic is
    a word, never a noun. The possessive ``'s`` stays (its ``s`` ends a phrase)."""
    folded = "".join(ch for ch in unicodedata.normalize("NFKD", text) if not unicodedata.combining(ch))
    low = _NOT_RE.sub(" not", _IRREGULAR_NOT_RE.sub(lambda m: _IRREGULAR_NOT[m.group(1)], folded.lower()))
    return _CLITIC_RE.sub(lambda m: " " + _CLITICS[m.group(1)], low)


def words(text: str) -> list[str]:
    """Lower-case alphanumeric words with a naive singular (``trees`` -> ``tree``)."""
    return [_singular(w) for w in _WORD_RE.findall(_lower(text))]


def _tokens(text: str) -> tuple[list[str], list[bool]]:
    """Words as :func:`words`, and per word whether punctuation follows it (a phrase break)."""
    low = _lower(text)
    found = list(_WORD_RE.finditer(low))
    out = [_singular(m.group(0)) for m in found]
    breaks = [bool(_BREAK_RE.search(low[a.end() : b.start()])) for a, b in zip(found, found[1:])] + [True]
    return out, breaks


def _ends_phrase(word: str, participles: bool = True) -> bool:
    """Whether ``word`` cannot continue the noun phrase before it (see :data:`PHRASE_END_WORDS`);
    ``participles=False``: an ``-ed`` / ``-ing`` participle can (it modifies a noun after it:
    ``the parked car``)."""
    if word in PHRASE_END_WORDS or word.isdigit() or (len(word) > 4 and word.endswith("ly")):
        return True
    return participles and _is_participle(word)


def names_target(text: str) -> bool:
    """Whether ``text`` names something to reach: a word that is not a number, an attribute or
    one of :data:`NON_OBJECT_WORDS` and is the head of its noun phrase (the grounding rule: a
    word another noun follows is that noun's modifier). ``fly forward``, ``continue through the
    intersection`` and ``go into the elevator lobby`` (a lobby is a place; ``elevator`` only
    says which) name none; ``stop at the blue door`` names one (visible or not)."""
    toks, breaks = _tokens(text)
    for i, w in enumerate(toks):
        if w.isdigit() or w in NON_OBJECT_WORDS or w in ATTRIBUTE_WORDS:
            continue
        if not (breaks[i] or i + 1 == len(toks) or _ends_phrase(toks[i + 1])):
            continue
        p = _phrase_start(toks, breaks, _modifiers_start(toks, breaks, i))
        if _governing_word(toks, breaks, p) in _ROUTE_WORDS:
            continue  # a route to fly along ("continue along the wall"), not a place to reach
        return True
    return False


@dataclass(frozen=True)
class Match:
    """A visible object named by the subtask.

    Attributes
    ----------
    instance_id : int
    start : int, index of the first matched word (attributes included) in the subtask
    n_words : int, matched words (phrase + attributes)
    via : ``"name"``, ``"alias"`` or ``"label"``
    passed : bool, the mention follows ``past`` / ``passed`` / ``beyond`` (a landmark to fly
        past), lies in an opening place phrase closed by a comma (``on the upper deck,
        stop beside the chair``), or is made of place words only (``go up to the second floor
        and hover in front of the balcony door``: a platform's alias); where, not what: ranked
        after every other mention
    locates : bool, the mention says where an earlier noun is (``the charging station by the
        blue car``: the car; :func:`locates_head`): a landmark, never the subtask's target
    """

    instance_id: int
    start: int
    n_words: int
    via: str
    passed: bool = False
    locates: bool = False


@dataclass(frozen=True, eq=False)
class Region:
    """Pixels of one visible instance.

    Attributes
    ----------
    instance_id : int
    area_px : int, number of pixels
    median_depth_m : float, median z-depth over pixels with a reading (NaN if none)
    mask : bool array (H, W)
    """

    instance_id: int
    area_px: int
    median_depth_m: float
    mask: np.ndarray


def _occurrences(phrase: list[str], text: list[str]) -> list[int]:
    n = len(phrase)
    return [i for i in range(len(text) - n + 1) if text[i : i + n] == phrase] if n else []


def ground(subtask: str, objects: Mapping[int, VisibleObject], areas_px: Mapping[int, int]) -> list[Match]:
    """Visible objects named by ``subtask``, best first (rule in :mod:`vlm.sim.error_model`).

    An occurrence of an object's name, alias or label counts only as the head of its noun
    phrase (the next word ends the phrase, :func:`_ends_phrase`): ``wall clock`` names a clock,
    never a wall. Objects with ``target=False`` are never named.

    Parameters
    ----------
    subtask : str
    objects : instance_id -> VisibleObject, the frame's annotation
    areas_px : instance_id -> visible pixel count; objects with no pixel are skipped
    """
    text, breaks = _tokens(subtask)
    # an opening place phrase ("On the upper deck, ..."): its words up to the first comma
    opening = 0
    if text and text[0] in _PLACE_OPENERS and False in breaks[:-1]:
        opening = next((k + 1 for k, b in enumerate(breaks[:-1]) if b), 0)
    best: dict[int, Match] = {}
    for iid, obj in objects.items():
        if areas_px.get(iid, 0) <= 0 or not getattr(obj, "target", True):
            continue
        phrases = [(words(obj.name), "name")] + [(words(a), "alias") for a in obj.aliases] + [(words(obj.label), "label")]
        # a name that ends in an identifier ("checkout 2", "rack A") is one of the kind its
        # other words name: "the checkouts" names it, "checkout 1" does not
        for q, _ in phrases[:-1]:  # the label names the kind already
            if len(q) > 1 and _is_identifier(q[-1]) and all(q[:-1] != r for r, _ in phrases):
                phrases.append((q[:-1], "kind"))
        own = {w for p, _ in phrases for w in p}
        own_post = [q for p, _ in phrases for k in range(1, len(p)) if (q := _postmodifier(p, [False] * (len(p) - 1) + [True], k))]
        for phrase, via in phrases:
            for i in _occurrences(phrase, text):
                end = i + len(phrase)
                if end < len(text) and not breaks[end - 1] and not _ends_phrase(text[end]):
                    continue  # a modifier of a longer noun phrase, not its head
                if via == "kind" and end < len(text) and not breaks[end - 1] and _is_identifier(text[end]):
                    continue  # another one of the kind, by its own identifier
                j = _modifiers_start(text, breaks, i)
                if any(w not in own for w in text[j:i]):
                    continue  # a modifier says another object of the kind ("stairwell door", "palm tree")
                of = _of_head(text, breaks, end)
                if of is not None and of not in own:
                    continue  # so does an "of" phrase ("the doorway of the bathroom", "the painting of a sailboat")
                if own_post and not _postmodifier_fits(_postmodifier(text, breaks, end), own, own_post):
                    continue  # and a phrase after it, against its own name's ("by the red car", "in white")
                p = _phrase_start(text, breaks, j)
                landmark = _governing_word(text, breaks, p) in _PAST_WORDS | _ROUTE_WORDS or end <= opening or _is_place(text[j:end])
                m = Match(iid, j, len(phrase) + (i - j), via, landmark, locates_head(text, breaks, p))
                cur = best.get(iid)
                if cur is None or (m.passed, m.locates, m.start, -m.n_words) < (cur.passed, cur.locates, cur.start, -cur.n_words):
                    best[iid] = m
    # ties between mentions at one place (a label shared by look-alikes): the object more of
    # whose own distinctive words the subtask uses ("the person standing by the entrance" is
    # "person by the entrance", not "person near the railing")
    said = set(text)
    overlap = {
        iid: len({w for p in [words(objects[iid].name), *map(words, objects[iid].aliases)] for w in p
                  if w in said and w not in PHRASE_END_WORDS})
        for iid in best
    }  # fmt: skip
    return sorted(
        best.values(),
        key=lambda m: (m.passed, m.locates, m.start, -m.n_words, -overlap[m.instance_id], -areas_px[m.instance_id], m.instance_id),
    )


def entrance_places(obj: VisibleObject) -> tuple[tuple[str, ...], ...]:
    """The places an entrance leads to, as word tuples (:func:`words`), read off its name and
    aliases; none if its label is not one of :data:`ENTRANCE_LABELS`.

    A place is what follows ``to``, ``into`` or ``of`` in a name or alias, with or without
    its article (``doorway to the storage room``, ``double doors of the large meeting room``,
    ``entrance to the bike cage``, ``doorway to classroom A``), or the words before the label
    when the last of them is a place word of :data:`NON_OBJECT_WORDS` (``kitchen doorway``, ``kid's room doorway``,
    ``elevator lobby doorway``). ``red door`` and ``storage door`` lead nowhere the words could
    name: a colour or a material is no place."""
    label = words(obj.label)
    if not label or label[-1] not in ENTRANCE_LABELS:
        return ()
    found: list[tuple[str, ...]] = []
    for phrase in (obj.name, *obj.aliases):
        toks = words(phrase)
        for k in range(len(toks) - 1):
            if toks[k] in ("to", "into", "of"):  # the place, with or without its article
                found.append(tuple(toks[k + 2 :] if toks[k + 1] in _DETERMINERS else toks[k + 1 :]))
                break
        else:
            if len(toks) > 1 and toks[-1] == label[-1] and toks[-2] in NON_OBJECT_WORDS and toks[-2] not in PHRASE_END_WORDS:
                found.append(tuple(toks[:-1]))
    return tuple(dict.fromkeys(p for p in found if p))


def place_entrance(subtask: str, objects: Mapping[int, VisibleObject], areas_px: Mapping[int, int]) -> int | None:
    """The visible entrance to a place ``subtask`` names to look in, or None.

    A place is named when its words (:func:`entrance_places`) are the head of a noun phrase of
    the subtask (``the vacuum cleaner in the storage room``, ``fly into the kitchen``; not
    ``the kitchen sink``) whose modifiers are the entrance's own words (``the small bedroom``
    is not the ``main bedroom doorway``'s), right after a word that makes it where the target
    is or where to go (:data:`_INTO_WORDS`: ``in``, ``into``, ``to``, ``enter`` ...), or the
    place to leave (:data:`_LEAVE_WORDS` or ``out of``: ``leave the study``, ``exit the meeting
    room``, ``out of the kitchen``), whose entrance is the way out. The simulated model cannot
    tell from a frame on which side of the entrance the camera is: once out, it still points at
    the entrance while the leg is current, harsher than a model that sees it has left. A place
    followed, crossed or flown past (``follow the hallway``, ``through the living room``,
    ``past the kitchen``) is not looked for. The earliest mention wins; then the larger visible
    area, the lower instance id. Rule in :mod:`vlm.sim.error_model` (*Places*).
    """
    text, breaks = _tokens(subtask)
    best: tuple[tuple[int, int, int], int] | None = None
    for iid, obj in objects.items():
        if areas_px.get(iid, 0) <= 0:
            continue
        places = entrance_places(obj)
        if not places:
            continue
        own = {w for p in (obj.name, *obj.aliases) for w in words(p)}
        for place in places:
            for i in _occurrences(list(place), text):
                end = i + len(place)
                if end < len(text) and not breaks[end - 1] and not _ends_phrase(text[end]):
                    continue  # a modifier of a longer noun phrase ("the kitchen sink")
                j = _modifiers_start(text, breaks, i)
                if any(w not in own for w in text[j:i]):
                    continue  # another place of the kind ("the small bedroom")
                p = _phrase_start(text, breaks, j)
                if p == 0 or breaks[p - 1] or not _looked_for(text, p):
                    continue  # a route, or a place flown past
                key = (j, -areas_px[iid], iid)
                if best is None or key < best[0]:
                    best = (key, iid)
    return None if best is None else best[1]


def _looked_for(text: list[str], p: int) -> bool:
    """Whether the words before the place phrase starting at word ``p`` (> 0) make it one to
    go into or to leave (:data:`_INTO_WORDS`, :data:`_LEAVE_WORDS`, ``out of``)."""
    before = text[p - 1]
    return before in _INTO_WORDS or before in _LEAVE_WORDS or (before == "of" and p >= 2 and text[p - 2] == "out")


def _modifiers_start(text: list[str], breaks: list[bool], i: int) -> int:
    """Index of the first pre-modifier of the head that a mention starting at word ``i`` has:
    back over attributes and nouns used as modifiers (``stairwell`` in ``the stairwell door``,
    ``palm`` in ``the palm tree``, ``dining`` in ``the dining table``: :func:`_is_premodifier`),
    to a determiner, a preposition or another word that ends a phrase, a count word (``the two
    garden lanterns``) or punctuation. Each of those words must be one of the object's own for the mention to name it."""
    j = i
    while j > 0 and not breaks[j - 1] and (_is_premodifier(text[j - 1]) or _side_premodifier(text, breaks, j - 1)):
        j -= 1
    return j


#: words that say where a thing is (``in front of``, ``at the back``) but, between a
#: determiner and a noun, which one it is (``the front door``, ``the back gate``)
_SIDE_WORDS = frozenset("front back".split())


def _side_premodifier(text: list[str], breaks: list[bool], k: int) -> bool:
    """Whether ``text[k]`` is a side word used as a pre-modifier: right after a determiner,
    with no punctuation between (``the front door`` names a front door, not any door)."""
    return text[k] in _SIDE_WORDS and k > 0 and text[k - 1] in _DETERMINERS and not breaks[k - 1]


def _of_head(text: list[str], breaks: list[bool], end: int) -> str | None:
    """The head of an ``of`` phrase right after a mention that ends before word ``end`` (``the
    doorway of the bathroom``: ``bathroom``; ``the painting of a sailboat``: ``sailboat``), or
    None when none follows. Like a modifier before it, it says which object of the kind."""
    if end >= len(text) or text[end] != "of" or breaks[end - 1]:
        return None
    found = _noun_phrase_words(text, breaks, end + 1)
    return found[-1] if found else None


def _noun_phrase_words(text: list[str], breaks: list[bool], start: int) -> list[str]:
    """The words of the noun phrase that begins at word ``start`` (after a preposition),
    determiners left out, up to a word that ends the phrase or punctuation; its head is last."""
    found: list[str] = []
    for k in range(start, len(text)):
        w = text[k]
        if w not in _DETERMINERS:
            if _ends_phrase(w) and not _is_premodifier(w):
                break
            found.append(w)
        if breaks[k]:
            break
    return found


def _postmodifier(text: list[str], breaks: list[bool], end: int) -> list[str]:
    """The noun phrase of a prepositional phrase right after a mention that ends before word
    ``end``, which says which object the mention is: where it is or what it has (``the
    charger by the red car``: ``red``, ``car``; ``the whiteboard in the small meeting room``:
    ``small``, ``meeting``, ``room``; ``the person in white``: ``white``; ``the man with the
    cart``: ``cart``). Empty when no such preposition (:data:`_POSTMODIFIER_PREPOSITIONS`)
    follows, or when its phrase says which way and not next to what (``the tree on the left``,
    ``the bench at the far end``: a head of :data:`_RELATIONAL_WORDS` or none). Determiners and
    words that end a phrase are not read."""
    if end >= len(text) or breaks[end - 1]:
        return []
    for prep in _POSTMODIFIER_PREPOSITIONS:
        if text[end : end + len(prep)] != list(prep) or any(breaks[end : end + len(prep) - 1]):
            continue
        found = _noun_phrase_words(text, breaks, end + len(prep))
        return [] if not found or found[-1] in _RELATIONAL_WORDS else found
    return []


def _postmodifier_fits(said: list[str], own: set[str], own_post: list[list[str]]) -> bool:
    """Whether the phrase ``said`` after a mention (:func:`_postmodifier`; empty: none) can be
    said of an object whose own words are ``own`` and whose name or aliases have the phrases
    ``own_post`` after their noun. Its head must be one of the object's own words (``by the red
    car``, ``in white``, ``with the cart``; ``in the big bedroom`` fits ``potted plant in the
    bedroom``), and an attribute in it one of the object's own words when the object's own
    phrases carry attributes (``red`` against ``charger by the blue car``)."""
    if not said:
        return True
    if said[-1] not in own:
        return False
    attributed = any(w in ATTRIBUTE_WORDS for q in own_post for w in q)
    return not attributed or all(w in own for w in said if w in ATTRIBUTE_WORDS)


def _is_premodifier(word: str) -> bool:
    """Whether ``word``, right before a noun, can modify it: any word that does not end a
    phrase, and an ``-ing`` word that is not a verb of :data:`PHRASE_END_WORDS` (before a noun
    it classifies it: ``dining table``, ``charging station``, ``meeting room``). Not a count
    word, and not an ``-ed`` participle (``the parked car``: a state, not which car)."""
    if word in _COUNT_WORDS:
        return False
    if not _ends_phrase(word):
        return True
    return word not in PHRASE_END_WORDS and word.endswith("ing") and _is_participle(word)


def _phrase_start(text: list[str], breaks: list[bool], j: int) -> int:
    """Index of the first word of the noun phrase whose pre-modifiers begin at word ``j``:
    back over determiners and any other modifier, participles included (:func:`_ends_phrase`
    with ``participles=False``; no punctuation after it).
    ``past the kitchen table``: the phrase of ``table`` begins at ``the``, so the preposition
    before it (``past``) is seen from the bare label too; so is ``by`` in ``by the parked blue
    car``."""
    p = j
    while p > 0 and not breaks[p - 1]:
        w = text[p - 1]
        if w not in _DETERMINERS and _ends_phrase(w, participles=False):
            break
        p -= 1
    return p


def _governing_word(text: list[str], breaks: list[bool], p: int) -> str:
    """The word that governs the noun phrase starting at word ``p``: the one before it, or,
    for the complement of an ``of`` phrase, the one before the noun it complements (``along
    the row of parked cars``: ``along`` governs ``cars`` too, so the cars are a route; ``past
    the end of the pier``: ``past``). Empty at the start of the text or after punctuation. A
    second noun joined by ``and`` keeps its own (``past the red car and the blue car``: the blue
    car is the leg's target, reached as the last landmark of the route)."""
    while p > 1 and text[p - 1] == "of" and not breaks[p - 2] and not breaks[p - 1]:
        p = _phrase_start(text, breaks, _modifiers_start(text, breaks, p - 2))
    return text[p - 1] if p > 0 and not breaks[p - 1] else ""


def _is_place(mention: list[str]) -> bool:
    """Whether a mention's words are all place words (:data:`NON_OBJECT_WORDS`) or numbers:
    ``the second floor``, the alias of a platform, says where, not what (the rule of
    :func:`names_target`)."""
    return all(w.isdigit() or w in NON_OBJECT_WORDS for w in mention)


def locates_head(text: list[str], breaks: list[bool], p: int) -> bool:
    """Whether the noun phrase starting at word ``p`` of ``text`` (determiners included) says
    where an earlier noun is: a locating preposition (``by``, ``near``, ``next to``, ``in front
    of`` ...: :data:`_LOCATING_PREPOSITIONS`) right before it, and before that, in the same
    clause, a noun: a word that is not a number, an attribute or one of
    :data:`NON_OBJECT_WORDS`, optionally followed by one participle (``the person standing by
    the entrance``, ``the van parked next to the kiosk``). ``stop next to the blue car`` has a
    verb before the preposition, so the car is the goal; ``the charging station by the blue
    car`` a noun, so the car only says where the station is."""
    for prep in _LOCATING_PREPOSITIONS:
        q = p - len(prep)
        if q < 1 or text[q:p] != list(prep) or any(breaks[q - 1 : p - 1]):
            continue
        k = q - 1
        if _is_participle(text[k]) and k >= 1 and not breaks[k - 1]:
            k -= 1
        w = text[k]
        return not (w.isdigit() or w in NON_OBJECT_WORDS or w in ATTRIBUTE_WORDS or _is_participle(w))
    return False


def _is_participle(word: str) -> bool:
    """An ``-ing`` / ``-ed`` word that is not one of the nouns of :data:`_ING_NOUNS`."""
    return len(word) > 4 and word.endswith(("ing", "ed")) and word not in _ING_NOUNS


def _valid_depth(depth_m: np.ndarray) -> np.ndarray:
    return np.isfinite(depth_m) & (depth_m > 0.0)


def region_of(annotation: FrameAnnotation, instance_id: int) -> Region:
    """The pixels of one instance in the frame (area 0 if it has none)."""
    mask = np.asarray(annotation.instance_ids) == instance_id
    depth = np.asarray(annotation.depth_m, dtype=np.float32)
    vals = depth[mask & _valid_depth(depth)]
    med = float(np.median(vals)) if vals.size else float("nan")
    return Region(int(instance_id), int(mask.sum()), med, mask)


def visible_regions(annotation: FrameAnnotation) -> dict[int, int]:
    """instance_id -> pixel count for the annotated objects that have pixels in the frame."""
    ids, counts = np.unique(np.asarray(annotation.instance_ids), return_counts=True)
    present = dict(zip(ids.tolist(), counts.tolist()))
    return {iid: int(present[iid]) for iid in annotation.objects if iid in present}


def anchor_pixel(mask: np.ndarray) -> tuple[int, int]:
    """``(u, v)`` of the mask pixel nearest to the mask's centroid (on the object).

    Ties go to the first in row-major order. ``mask`` must have at least one pixel.
    """
    vs, us = np.nonzero(mask)
    if us.size == 0:
        raise ValueError("anchor_pixel: empty mask")
    cu, cv = us.mean(), vs.mean()
    k = int(np.argmin((us - cu) ** 2 + (vs - cv) ** 2))
    return int(us[k]), int(vs[k])


def exploration_point(depth_m: np.ndarray, n_blocks: int = 16, band: tuple[float, float] = (0.35, 0.65)) -> tuple[int, int]:
    """Where to look for an unseen target: the deepest open column block on the horizon band.

    Parameters
    ----------
    depth_m : float array (H, W), z-depth in metres; 0 / NaN / inf (no reading) count as open
    n_blocks : number of equal column blocks (at most W)
    band : rows ``[band[0] * H, band[1] * H)`` form the horizon band of a level camera

    Returns
    -------
    (u, v) : block centre column (rounded down), middle row ``(H - 1) // 2``. Ties go to the
    block nearest the image centre.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    h, w = depth.shape
    r0 = min(int(band[0] * h), h - 1)
    r1 = max(int(np.ceil(band[1] * h)), r0 + 1)
    rows = depth[r0:r1]
    rows = np.where(_valid_depth(rows), rows, np.inf)
    n = max(1, min(n_blocks, w))
    edges = np.linspace(0, w, n + 1).round().astype(int)
    scores = np.array([np.median(rows[:, edges[b] : edges[b + 1]]) for b in range(n)])
    centres = (edges[:-1] + edges[1:] - 1) / 2.0
    best = scores == scores.max()
    b = int(np.flatnonzero(best)[np.argmin(np.abs(centres[best] - (w - 1) / 2.0))])
    return int(centres[b]), (h - 1) // 2
