"""What the simulated VLM can read off one annotated frame: named objects, regions, open space.

Pure functions over a :class:`vlm.types.FrameAnnotation`; nothing here sees more than the frame.
The grounding rule is stated in :mod:`vlm.sim.error_model`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from vlm.types import FrameAnnotation, VisibleObject

__all__ = [
    "ATTRIBUTE_WORDS",
    "Match",
    "Region",
    "words",
    "ground",
    "region_of",
    "visible_regions",
    "anchor_pixel",
    "exploration_point",
]

#: Words that distinguish objects of one label; a subtask's attribute right before an object
#: mention must belong to the object's own name, aliases or label for the mention to count.
ATTRIBUTE_WORDS = frozenset(
    """red orange yellow green blue purple violet pink brown black white grey gray silver gold golden
    beige cyan magenta dark light big small large little tall short tiny huge long wide narrow high low
    wooden wood metal metallic glass brick stone concrete plastic steel iron old new round square""".split()
)
_WORD_RE = re.compile(r"[a-z0-9]+")
_ES_STEMS = ("ch", "sh", "x", "z", "ss")


def _singular(w: str) -> str:
    if len(w) > 3 and w.endswith("ies"):
        return w[:-3] + "y"
    if len(w) > 3 and w.endswith("es") and w[:-2].endswith(_ES_STEMS):
        return w[:-2]
    if len(w) > 3 and w.endswith("s") and not w.endswith("ss"):
        return w[:-1]
    return w


def words(text: str) -> list[str]:
    """Lower-case alphanumeric words with a naive singular (``trees`` -> ``tree``)."""
    return [_singular(w) for w in _WORD_RE.findall(text.lower())]


@dataclass(frozen=True)
class Match:
    """A visible object named by the subtask.

    Attributes
    ----------
    instance_id : int
    start : int, index of the first matched word (attributes included) in the subtask
    n_words : int, matched words (phrase + attributes)
    via : ``"name"``, ``"alias"`` or ``"label"``
    """

    instance_id: int
    start: int
    n_words: int
    via: str


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

    Parameters
    ----------
    subtask : str
    objects : instance_id -> VisibleObject, the frame's annotation
    areas_px : instance_id -> visible pixel count; objects with no pixel are skipped
    """
    text = words(subtask)
    best: dict[int, Match] = {}
    for iid, obj in objects.items():
        if areas_px.get(iid, 0) <= 0:
            continue
        phrases = [(words(obj.name), "name")] + [(words(a), "alias") for a in obj.aliases] + [(words(obj.label), "label")]
        own = {w for p, _ in phrases for w in p}
        for phrase, via in phrases:
            for i in _occurrences(phrase, text):
                j = i
                while j > 0 and text[j - 1] in ATTRIBUTE_WORDS:
                    j -= 1
                if any(w not in own for w in text[j:i]):
                    continue
                m = Match(iid, j, len(phrase) + (i - j), via)
                cur = best.get(iid)
                if cur is None or (m.start, -m.n_words) < (cur.start, -cur.n_words):
                    best[iid] = m
    return sorted(best.values(), key=lambda m: (m.start, -m.n_words, -areas_px[m.instance_id], m.instance_id))


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
