"""The simulated VLM's error model: the one place that says how, and how often, it errs.

What the simulated VLM sees
---------------------------
Only what a camera frame shows: each image's :class:`vlm.types.FrameAnnotation` (per-pixel
instance ids, z-depth, and name / label / aliases of the instances *present in the frame*) and
the prompt text. Never a map, a pose or an object that is not in the frame. An annotation entry
whose instance has no pixel in ``instance_ids`` is treated as not visible.

Grounding (which visible object the subtask names)
--------------------------------------------------
Rule in :mod:`vlm.sim.grounding` (:func:`~vlm.sim.grounding.ground`): an object is named when
its name, one of its aliases or its label occurs as contiguous words in the subtask (lower case,
naive singular) and

- the occurrence is the *head* of its noun phrase: the word after it ends the phrase
  (punctuation, a function word, verb, direction or adverb of
  :data:`vlm.sim.grounding.PHRASE_END_WORDS`, a number, an ``-ly`` adverb or an ``-ed`` /
  ``-ing`` participle). ``wall clock`` names a clock, never a wall; ``fuel pump`` a pump, never
  the fuel tank; ``the sedan parked on the right`` the sedan. English compounds are
  right-headed (E. Williams, "On the notions 'lexically related' and 'head of a word'",
  *Linguistic Inquiry* 12(2), 1981): a model reading "wall clock" looks for a clock;
- every word that modifies it from before belongs to the object's own words: an attribute
  (colour, size, material: :data:`vlm.sim.grounding.ATTRIBUTE_WORDS`) or a noun or ``-ing``
  classifier (``stairwell`` in ``the stairwell door``, ``dining`` in ``the dining table``;
  ``front`` / ``back`` right after a determiner: ``the front door`` is no side door, while
  ``in front of the door`` says where), back to a determiner, a preposition, a count word or
  an ``-ed`` state (``the parked car``).
  ``red van`` thus names the object ``red van`` (label ``van``) but not ``blue van``; ``the
  stairwell door`` names the green stairwell door but not the garage's exit shutter (label
  ``door``), so with the stairwell door out of view the model says the target is not visible
  (rule 4) instead of pointing at the shutter; ``the van`` names both vans. The head of an
  ``of`` phrase after it must be the object's own too (``the doorway of the bathroom``, ``the
  painting of a sailboat``). Look-alikes are confused only at ``confusion_prob`` (rule 2);
- when the object's own name or an alias has a phrase after its noun that says which one it
  is (``charging station by the blue car``, ``person in white shirt``, ``whiteboard on
  wheels``, ``cafe table with the red umbrella``), a prepositional phrase right after the
  mention must fit it: its head one of the object's own words, and its attributes too when
  the object's own phrases carry attributes (``the EV charger by the red car`` does not name
  the charger by the blue car, nor ``the person in white`` the person in purple; ``the plant in
  the big bedroom`` names the ``potted plant in the bedroom``). A phrase that gives a direction
  (``the bench on the left``) says nothing of which object. An object whose name has no such
  phrase (``red motorcycle``) is still named by ``the red motorcycle in the bike cage``: the
  model cannot tell from the name where it is. Before, ``charger`` named both chargers, so with
  the red car's out of view the model stopped at the blue car's every time, where a model that
  sees the blue car beside it says the target is not visible (a relational referring
  expression, as in RefCOCO below); with both in view the other one is now a look-alike,
  confused at ``confusion_prob`` (rule 2) instead of never;
- a name or alias that ends in an identifier (a number or a single letter: ``checkout 2``,
  ``rack A``, ``till 1``) names one of the kind its other words say, so those words name it
  too, as a label does (``the two checkouts``, ``the tills``, ``the racks``), except when an
  identifier follows them (``checkout 1`` is not ``checkout 2``). Before, an object named
  ``checkout 1`` with the label ``checkout counter`` was named by no plural or bare mention, and
  a model that sees two checkout counters answered that the checkouts were not visible;
- a contraction is read as its words (``you're``: ``you are``): a clitic is never a noun;
- the object is a target: scene objects with ``target = false`` (ground, walls, roofs, parked
  cars and street furniture the scene marks as background; :attr:`vlm.types.VisibleObject.target`)
  are never the goal of a subtask.

*Landmarks that locate the target*: a mention right after a locating preposition (``by``,
``near``, ``beside``, ``behind``, ``opposite``, ``next to``, ``across from``, ``in front of``,
``in``, ``inside``, ``on``, ``under``, ``above``) that itself follows a noun in the same clause
(``the charging station by the blue car``, ``the person standing by the entrance``, ``the red
motorcycle in the bike cage``) says where that noun is: it is never the subtask's target.
With the target out of view and the landmark in view, the model says the target is not visible
and looks at the landmark (rule 4, and the baselines' *Aim*): the instruction says where to
look. After a verb the same words name the goal (``stop next to the blue car``). Reading a
prepositional phrase as a modifier of the noun before it is the referring-expression task
grounding models are trained on (RefCOCO's relational expressions: L. Yu et al., "Modeling
Context in Referring Expressions", ECCV 2016), and a target that is not there is answered as
absent (gRefCOCO, rule 4).

*Places, found by their entrances*: a room is where, not what
(:data:`vlm.sim.grounding.NON_OBJECT_WORDS`), so ``the vacuum cleaner in the storage room``
names one object to reach, and the room is what locates it. What a camera shows of a room it is
not in is the room's entrance: a visible object whose label is an entrance
(:data:`vlm.sim.grounding.ENTRANCE_LABELS`) leads to the places its name or an alias says
(``doorway to the storage room``, ``kitchen doorway``, ``double doors of the large meeting
room``; :func:`vlm.sim.grounding.entrance_places`). When a subtask's target is not perceived, no
landmark that locates it is in view, and the entrance to a place the subtask names is (the place
is the head of a noun phrase with only the entrance's own modifiers, right after ``in``,
``into``, ``to``, ``enter`` or ``reach``, or the place to leave, right after ``leave``,
``exit`` or ``out of``; a place followed, crossed or flown past is none: ``follow the
hallway``, ``through the living room``, ``past the kitchen``;
:func:`vlm.sim.grounding.place_entrance`), the model looks at that entrance (rule 4); a subtask
that names a place and no target (``fly into the kitchen``, ``leave the study``) points at it
as the way (rule 5). The way out of a place is its entrance seen from inside: the model cannot
tell from the annotation which side of the entrance the camera is on, so once out it still
points back at the entrance while the leg lasts, which a model that sees it has left would not.
Like any pointed object it is confused with a visible look-alike (another doorway) at
``confusion_prob``. A model asked for the fridge in the kitchen looks toward a kitchen it sees
through a doorway: telling the kind of room a view shows is a standard recognition task for
current models (Places365: B. Zhou et al., "Places: A 10 Million Image Database for Scene
Recognition", TPAMI 2018), and instruction-following navigation agents are trained to go through
the doorway a room name in the instruction points at (R2R: P. Anderson et al.,
"Vision-and-Language Navigation", CVPR 2018). Only a place the words name is found this way:
where a target usually is (a bathtub in a bathroom) is still no prior of the simulated model.

A route is no target: the object of ``along`` (``continue along the wall``) is flown along,
not reached; a text whose only mentions are routes names nothing to reach
(:func:`vlm.sim.grounding.names_target`), and a named object along which the vehicle flies
ranks as a landmark flown past. ``past`` and ``along`` govern the ``of`` phrase after their noun
as well: in ``fly along the row of parked cars`` the cars are the route, not a car to reach
(``fly along the back of rack D`` names nothing to reach).

Among named objects: mentions after ``past`` / ``passed`` / ``beyond`` (a landmark flown past;
the preposition is read before the whole noun phrase, so ``past the kitchen table`` flies past
the table by its label too), inside an opening place phrase closed by a comma (``On the upper
deck, stop beside the chair``), and mentions made of place words only (``Go up to the second
floor and hover in front of the balcony door``: a platform's alias, read as where, not what, as
:func:`vlm.sim.grounding.names_target` reads it) rank last, then landmarks that locate the
target; then the earliest mention, the longer match, the object more of whose own
distinctive words the subtask uses (``the person standing by the entrance`` is ``person by
the entrance``), the larger visible area, the lower instance id.

Legs (one rule for every prompt)
--------------------------------
Every prompt's text, the OnFly decision and monitoring subtask as much as a baseline's whole
instruction, is cut into *legs* by :func:`vlm.decompose.split_instruction` (no merges); a leg
that only closes the one before it (``then stop``, words of
:data:`vlm.decompose.CLOSING_ONLY_WORDS`) is joined to it; a statement after the last step
(``Where's the vending machine? I could really use a coffee.``: :func:`vlm.decompose.is_context`)
is no leg; a leg naming nothing visible that
refers back (``go to it``, ``stop there``, ``in front of its middle``), or whose first reference
points back (``stop beside it, across from office 105``:
:func:`vlm.decompose.opens_with_back_reference`), means the object the previous leg names last. The subtask's target is the *last* leg's target; completion (STOP,
``depth 0``, PIVOT ``stop``, TypeFly ``stop``) is judged only on it. So ``turn left at the
yellow forklift and stop in front of the fuel pump`` is never complete at the forklift.

A leg *names a target* when it holds a word that is not a number, an attribute or one of
:data:`vlm.sim.grounding.NON_OBJECT_WORDS` (movement verbs, function words, directions,
places such as corridor / intersection / floor and rooms such as the study or the kitchen,
units): ``fly forward``, ``continue through the intersection``, ``leave the study`` and ``go to
the end of the corridor`` name none
(:func:`vlm.sim.grounding.names_target`). This is the model's language knowledge, not
perception: it needs no object in the frame.

*Not modelled: relations as goals.* A goal that is a spatial relation between objects or a part
of one (``halfway between the yellow robot and the orange robot``, ``between rack B and rack
C``, ``right in the middle of`` the crossing, ``where the ramp meets the middle terrace``) is
read as its first named object: the model points at it and says STOP beside it. A real model
would aim between; this one is harsher than reality on such tasks, for every method alike
(the paper's 150 hold about eight of them; README, Table II).

Per call, with ``sigma_px = W * (pixel_noise_frac + pixel_noise_frac_per_m * d)`` where ``W`` is
the image width and ``d`` the median z-depth of the pointed object's pixels:

Decision (``decision/v3``: ``{"target_visible": true, "point_2d": [x, y]}`` or ``{"target_visible": false, "point_2d": [x, y] | null}``)
    0. *Leg*: the leg rule of the baseline prompts below (last leg's target if perceived, else
       the furthest leg whose target is perceived and not yet within ``stop_distance_m +
       stop_offset_m``, else the leg after it; nothing perceived: the first leg). The decision
       prompt has no stop interface: no stop jitter is drawn.
    1. *Miss*: the named target is not perceived with probability ``miss_prob_small`` if its
       visible area is below ``small_target_frac`` of the image, and independently with
       ``miss_prob_far`` if ``d > far_target_m``.
    2. *Confusion*: if perceived and a look-alike is visible (same label, another name, not
       itself named by the subtask), the answer points at a uniformly chosen look-alike with
       probability ``confusion_prob``.
    3. *Point*: the pixel of the pointed object's region nearest to the region's centroid (on
       the object even for non-convex shapes), plus isotropic Gaussian noise ``sigma_px``,
       rounded and kept inside the image.
    4. *Not visible*: the pursued leg names a target (see Legs) and it is not perceived (not in
       the frame, or missed by rule 1): the answer is ``{"target_visible": false, "point_2d":
       [x, y]}`` with the point where to look instead: the exploration point of rule 5 plus
       noise ``sigma_px`` at ``d = 0``, the point every baseline prompt aims at when its target
       is not perceived (no semantic prior: the deepest open direction, whatever the target),
       or, when a landmark that locates the target is in view (Grounding), that landmark's
       anchor pixel with the same noise, else, when the entrance to a place the subtask names
       is in view (Grounding, *Places*), the entrance's; the landmark or entrance is confused
       with a visible look-alike as in rule 2;
       no target point is invented, whatever the history point. Abstaining on a referring
       expression with no referent is a trained behaviour of grounding models (gRefCOCO's
       no-target expressions: C. Liu, H. Ding, X. Jiang, "GRES: Generalized Referring
       Expression Segmentation", CVPR 2023); the miss rule decides when the model fails to
       see a present target.
    5. *No target named* (``fly forward``, ``continue through the intersection``): pointing
       into open space is the answer, since nothing is to be found: the anchor pixel of the
       entrance to a place the subtask names when one is in view (``fly into the kitchen``;
       Grounding, *Places*; confused as in rule 2), else the history point from the prompt,
       plus noise ``sigma_px`` at ``d = 0``; without one, an *exploration point*: the
       deepest open column block on the horizon band (rows 35-65 % of the height; no depth
       reading counts as open), at the middle row, plus the same noise. Ties go to the block
       nearest the centre.

Monitoring (``CONTINUE`` / ``STOP`` / ``LOST``, images ``[first, *keyframes, latest]``)
    The last leg's target (see Legs) is perceived per frame with the miss rule above (each
    frame's miss draw is keyed on the seed, the frame id and the instance, so one frame is
    perceived the same way in every call); an earlier leg's landmark never completes the
    subtask and never makes it LOST. Then:

    - STOP if perceived in the latest frame with ``d < stop_distance_m + stop_offset_m + e``,
      ``e ~ N(0, stop_jitter_m)`` per call (``stop_offset_m > 0``: early STOP; ``< 0``: late);
    - LOST if not perceived in the last ``lost_window_frames`` frames but perceived in an
      earlier frame of the memory;
    - CONTINUE otherwise (including subtasks that name no visible object at all).

    *Following* (a subtask that follows someone who moves, :func:`vlm.following.follow_intent`:
    ``follow the person in the red jacket``): being near the person does not complete it. A
    following subtask with an end (``... until he stops, then stop next to him``) is complete
    by the STOP rule above only when the target also *stands still* in the latest frame
    (:attr:`vlm.types.VisibleObject.moving` is False) after it was seen *walking* in an
    earlier image of the same prompt (it has stopped; a person who has not set off yet has
    not). A baseline prompt shows one image, so it never sees a person stop: on such a task
    its stop interface never fires. One without an end is never complete (CONTINUE or LOST). Telling a walking from a standing person is within what current video
    VLMs do (MVBench's action and moving-attribute tasks: K. Li et al., "MVBench: A
    Comprehensive Multi-modal Video Understanding Benchmark", CVPR 2024); the per-call
    ``status_error_prob`` flip applies as to every status. The same rule is the completion of
    every baseline prompt below (``depth 0``, PIVOT ``stop``, TypeFly ``stop``).

    With probability ``status_error_prob`` the answer is replaced by one of the two other
    statuses, uniformly.

    *Place* (``monitor/v3``: ``LOST keyframe 2``, ``LOST first``): a LOST names the most recent
    image before the latest in which the target was perceived (by the per-frame draws above,
    so a frame that missed the target is never named for it). With probability
    ``status_error_prob`` it names another earlier image instead, drawn uniformly: the same
    forced-choice error as the status, now among the images. That rate is an assumption, not a
    measurement: telling which of several images shows an object is a multi-image task current
    VLMs are benchmarked on and far from solve (X. Fu et al., "BLINK: Multimodal Large Language
    Models Can See but Not Perceive", ECCV 2024; F. Meng et al., "MMIU: Multimodal Multi-image
    Understanding for Evaluating Large Vision-Language Models", arXiv 2408.02718, 2024). A LOST
    that the flip made up, with no earlier image that showed the target, names an earlier image
    drawn uniformly.

Decomposition (JSON array of strings)
    The deterministic splitter :func:`vlm.decompose.split_instruction`, then each boundary
    between adjacent subtasks is merged (joined with ``" then "``) with probability
    ``merge_prob``.

Baseline prompts (``spf``, ``pivot``, ``typefly`` templates; the paper's Table II baselines)
    These prompts carry the whole instruction and no memory. The instruction is cut into legs
    as above (Legs). Per frame, with the miss rule above and one stop jitter ``e`` per call:

    - *Leg rule*: if the last leg's target is perceived, aim at it; else take the furthest leg
      whose target is perceived: aim at it, or, if it is already within the stop distance
      (below), explore for the next leg; nothing perceived: explore.
    - *Stop rule* (the stop interfaces the OnFly paper added, timed like monitoring STOP): the
      last leg's target is perceived with ``d < stop_distance_m + stop_offset_m + e``.
      ``status_error_prob`` (a monitoring forced-choice error) does not apply.
    - *Aim*: the decision rule's point (anchor pixel, confusion with ``confusion_prob``, noise
      ``sigma_px``); exploring: the exploration point plus noise at ``d = 0`` (the anchor pixel
      of a landmark that locates the leg's target, or of the entrance to a place the leg names,
      when one is in view, confused as in rule 2).

    ``spf``: ``{"point_2d": [x, y], "depth": k}`` with ``k`` the pointed object's median depth
    rounded to whole metres in ``[1, 10]`` (exploring: the median depth in a 9 x 9 px window
    at the point, no reading = 10); ``k = 0`` when the stop rule holds.
    ``pivot``: the arrows' endpoints are read from the prompt text (a real implementation
    draws the numbers on the image; a model reads them there); the answer lists the
    ``n_pick`` arrows whose endpoints lie nearest to the aimed pixel, nearest first, or
    ``{"stop": true}``. The aimed pixel and the stop jitter are drawn once per frame and
    instruction (the same belief in every PIVOT iteration on one frame); format draws per call.
    Malformed answers: prose, truncated JSON, a wrong key, or arrow numbers that were not drawn
    (the only kind a schema allows).
    ``typefly``: a skill program. Where objects are comes only from the detector's scene
    description in the prompt (grounding over its names and labels; box area as visible
    area); whether the goal is reached is judged on the frame with the stop rule. Program:
    ``stop`` when reached; else ``approach <name>`` for the detection of the last leg, or of
    the furthest leg whose target is detected and not yet within the stop distance (a
    look-alike detection, same label and another name, with ``confusion_prob``); else
    ``find <leg text>`` for the next leg (after the furthest detected one, or the first leg no
    ``approach <name>: done`` entry of the skill log names), preceded by ``move_forward 3``
    when the log's last entry is that same find failing. Malformed: prose, a skill without an
    argument, an unknown skill, an empty answer.

    All three are charged the decision latency (one image, a short answer).

Every call
    With probability ``malformed_prob`` the answer is replaced by a realistic malformed one
    (prose without coordinates, truncated JSON, wrong key, a point outside the image, an
    ambiguous or missing status, an empty list); every such text fails the strict parsers.
    With ``json_schema`` set (structured output) malformed answers are limited to what a
    schema allows: a point outside the image; statuses and subtask lists are then always
    well-formed. Otherwise, with probability ``format_variety_prob`` a well-formed answer comes
    in another real-model shape (code fence, prose around the JSON, a labelled list, markdown
    around the status).

Randomness
----------
Each call draws from ``numpy.random.default_rng`` seeded by the simulator's ``seed`` and a hash
of the call's content (prompt kind, frame ids, subtask, history point): the same input gives the
same answer, like greedy decoding, independently of call order or threads. Runs reproduce from
the seed.

Latency (:class:`LatencyModel`, defaults from the paper's Jetson Orin NX table)
----------------------------------------------------------------------------------
Decision 0.81 s. Monitoring: ``monitor_full_s - (monitor_full_s - monitor_reused_s) * f`` with
``f = min(k, n - 1) / (n - 1)`` (``f = min(k, 1)`` for ``n = 1``), where ``n`` is the number of
images and ``k`` the number of images inside the prompt prefix shared with the previous
successful monitoring call on the same ``cache_key`` (no ``cache_key``: ``k = 0``). The hybrid
memory in steady state (only the latest frame new) gives 1.15 s; a sliding window (first
image changes) gives 1.98 s. Decomposition 3.0 s is our assumption (the paper gives none).
Token usage is estimated: text ``ceil(chars / chars_per_token)``, each image
``ceil(w / image_token_px) * ceil(h / image_token_px) + 2`` tokens (Qwen2.5/3-VL merge 2x2
14-px patches into one 28-px token); ``cached_tokens`` counts the shared prefix. A call whose
modelled latency exceeds ``deadline_s`` returns TIMEOUT after ``deadline_s``. An answer longer
than ``max_new_tokens`` is cut there, as a real server would.

Presets
-------
Fixed before any method is compared; never tuned toward one. ``nominal``, ``weak`` and
``strong`` are *stand-ins* (not fits) for Qwen3-VL-4B, -2B and -30B-A3B, the backbones of the
paper's ablation; ``perfect`` errs never; ``noisy`` is a stress test. Every benchmark result
names its preset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import Mapping

__all__ = ["ErrorModel", "ErrorModelError", "LatencyModel", "PRESETS", "get_preset"]


class ErrorModelError(ValueError):
    """An error-model or latency-model field is out of range, or a preset name is unknown."""


_PROBABILITIES = (
    "confusion_prob",
    "miss_prob_small",
    "miss_prob_far",
    "status_error_prob",
    "malformed_prob",
    "format_variety_prob",
    "merge_prob",
)
_NON_NEGATIVE = ("pixel_noise_frac", "pixel_noise_frac_per_m", "small_target_frac", "stop_jitter_m")
_POSITIVE = ("far_target_m", "stop_distance_m")


@dataclass(frozen=True)
class ErrorModel:
    """How the simulated VLM errs (semantics in the module docstring).

    Attributes
    ----------
    name : str, preset name
    stand_in_for : str, what the preset imitates (documentation only)
    pixel_noise_frac : float, pointing noise std at 0 m, fraction of the image width
    pixel_noise_frac_per_m : float, growth of that std per metre of target depth, 1/m
    confusion_prob : float, chance to point at a visible look-alike instead of the target
    small_target_frac : float, visible area below this fraction of the image is "small"
    miss_prob_small : float, chance to miss a small target
    far_target_m : float, targets with median z-depth beyond this are "far", metres
    miss_prob_far : float, chance to miss a far target
    stop_distance_m : float, STOP when the target's median z-depth is below this, metres
    stop_offset_m : float, added to the stop distance (> 0 early STOP, < 0 late), metres
    stop_jitter_m : float, std of per-call Gaussian jitter of the stop distance, metres
    lost_window_frames : int, LOST when the target is absent from this many latest frames
    status_error_prob : float, chance to answer one of the two other statuses
    malformed_prob : float, chance of a malformed answer
    format_variety_prob : float, chance a well-formed answer comes in another shape
    merge_prob : float, chance to merge two adjacent subtasks in a decomposition
    """

    name: str
    stand_in_for: str
    pixel_noise_frac: float
    pixel_noise_frac_per_m: float
    confusion_prob: float
    small_target_frac: float
    miss_prob_small: float
    far_target_m: float
    miss_prob_far: float
    stop_distance_m: float
    stop_offset_m: float
    stop_jitter_m: float
    lost_window_frames: int
    status_error_prob: float
    malformed_prob: float
    format_variety_prob: float
    merge_prob: float

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("float", float) and (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)):
                raise ErrorModelError(f"ErrorModel.{f.name} must be a finite number, got {value!r}")
        for name in _PROBABILITIES:
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ErrorModelError(f"ErrorModel.{name} must be in [0, 1], got {getattr(self, name)}")
        for name in _NON_NEGATIVE:
            if getattr(self, name) < 0.0:
                raise ErrorModelError(f"ErrorModel.{name} must be >= 0, got {getattr(self, name)}")
        for name in _POSITIVE:
            if getattr(self, name) <= 0.0:
                raise ErrorModelError(f"ErrorModel.{name} must be > 0, got {getattr(self, name)}")
        if self.small_target_frac >= 1.0:
            raise ErrorModelError(f"ErrorModel.small_target_frac must be < 1, got {self.small_target_frac}")
        if isinstance(self.lost_window_frames, bool) or not isinstance(self.lost_window_frames, int) or self.lost_window_frames < 1:
            raise ErrorModelError(f"ErrorModel.lost_window_frames must be an int >= 1, got {self.lost_window_frames!r}")

    def pixel_sigma_px(self, image_width_px: int, depth_m: float) -> float:
        """Pointing noise std in pixels for a target at ``depth_m`` (non-finite depth -> 0 m)."""
        d = depth_m if math.isfinite(depth_m) and depth_m > 0.0 else 0.0
        return image_width_px * (self.pixel_noise_frac + self.pixel_noise_frac_per_m * d)


@dataclass(frozen=True)
class LatencyModel:
    """Modelled latency and token accounting of the simulated VLM (see the module docstring).

    Attributes
    ----------
    decision_s, monitor_reused_s, monitor_full_s, decompose_s : float, seconds
    chars_per_token : float, text characters per token
    image_token_px : int, side of the image area one vision token covers, pixels
    """

    decision_s: float = 0.81
    monitor_reused_s: float = 1.15
    monitor_full_s: float = 1.98
    decompose_s: float = 3.0
    chars_per_token: float = 4.0
    image_token_px: int = 28

    def __post_init__(self) -> None:
        for name in ("decision_s", "monitor_reused_s", "monitor_full_s", "decompose_s", "chars_per_token"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
                raise ErrorModelError(f"LatencyModel.{name} must be a finite number > 0, got {value!r}")
        if self.monitor_reused_s > self.monitor_full_s:
            raise ErrorModelError(
                f"LatencyModel.monitor_reused_s ({self.monitor_reused_s}) must not exceed monitor_full_s ({self.monitor_full_s})"
            )
        if isinstance(self.image_token_px, bool) or not isinstance(self.image_token_px, int) or self.image_token_px < 1:
            raise ErrorModelError(f"LatencyModel.image_token_px must be an int >= 1, got {self.image_token_px!r}")

    def monitor_s(self, n_images: int, n_cached_images: int) -> float:
        """Monitoring latency for ``n_images`` of which the first ``n_cached_images`` were reused."""
        if n_images <= 1:
            frac = float(min(n_cached_images, 1))
        else:
            frac = min(n_cached_images, n_images - 1) / (n_images - 1)
        return self.monitor_full_s - (self.monitor_full_s - self.monitor_reused_s) * frac


def _preset(**kw) -> ErrorModel:
    return ErrorModel(**kw)


PRESETS: Mapping[str, ErrorModel] = MappingProxyType(
    {
        "perfect": _preset(
            name="perfect", stand_in_for="an oracle that never errs",
            pixel_noise_frac=0.0, pixel_noise_frac_per_m=0.0, confusion_prob=0.0,
            small_target_frac=0.0005, miss_prob_small=0.0, far_target_m=30.0, miss_prob_far=0.0,
            stop_distance_m=3.0, stop_offset_m=0.0, stop_jitter_m=0.0, lost_window_frames=2,
            status_error_prob=0.0, malformed_prob=0.0, format_variety_prob=0.0, merge_prob=0.0,
        ),
        "strong": _preset(
            name="strong", stand_in_for="a larger model (stand-in for Qwen3-VL-30B-A3B, not a fit)",
            pixel_noise_frac=0.004, pixel_noise_frac_per_m=0.001, confusion_prob=0.04,
            small_target_frac=0.0003, miss_prob_small=0.3, far_target_m=35.0, miss_prob_far=0.15,
            stop_distance_m=3.0, stop_offset_m=0.0, stop_jitter_m=0.3, lost_window_frames=2,
            status_error_prob=0.02, malformed_prob=0.01, format_variety_prob=0.2, merge_prob=0.05,
        ),
        "nominal": _preset(
            name="nominal", stand_in_for="the paper's backbone (stand-in for Qwen3-VL-4B, not a fit)",
            pixel_noise_frac=0.006, pixel_noise_frac_per_m=0.0015, confusion_prob=0.08,
            small_target_frac=0.0005, miss_prob_small=0.4, far_target_m=30.0, miss_prob_far=0.25,
            stop_distance_m=3.0, stop_offset_m=0.0, stop_jitter_m=0.5, lost_window_frames=2,
            status_error_prob=0.04, malformed_prob=0.03, format_variety_prob=0.2, merge_prob=0.1,
        ),
        "weak": _preset(
            name="weak", stand_in_for="a smaller model (stand-in for Qwen3-VL-2B, not a fit)",
            pixel_noise_frac=0.010, pixel_noise_frac_per_m=0.0025, confusion_prob=0.18,
            small_target_frac=0.0008, miss_prob_small=0.6, far_target_m=25.0, miss_prob_far=0.4,
            stop_distance_m=3.0, stop_offset_m=0.8, stop_jitter_m=1.0, lost_window_frames=2,
            status_error_prob=0.10, malformed_prob=0.08, format_variety_prob=0.3, merge_prob=0.2,
        ),
        "noisy": _preset(
            name="noisy", stand_in_for="a stress test, no particular model",
            pixel_noise_frac=0.015, pixel_noise_frac_per_m=0.004, confusion_prob=0.25,
            small_target_frac=0.001, miss_prob_small=0.7, far_target_m=20.0, miss_prob_far=0.5,
            stop_distance_m=3.0, stop_offset_m=-0.5, stop_jitter_m=1.5, lost_window_frames=2,
            status_error_prob=0.15, malformed_prob=0.12, format_variety_prob=0.4, merge_prob=0.3,
        ),
    }
)  # fmt: skip


def get_preset(name: str) -> ErrorModel:
    """The named preset; an unknown name raises :class:`ErrorModelError` listing the valid ones."""
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise ErrorModelError(f"unknown simulated-VLM preset {name!r}; valid: {sorted(PRESETS)}") from None
