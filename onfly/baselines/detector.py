"""A simulated open-vocabulary object detector (the YOLOE stand-in of the TypeFly baseline).

The error model, in one place
-----------------------------
The detector sees what the frame's :class:`vlm.types.FrameAnnotation` shows and nothing else:
the annotated objects that have pixels in the frame. Per frame:

- *Detection*: every visible annotated object whose visible area is at least ``min_area_px``
  is reported with its name, label and the bounding box of its visible pixels.
- *Misses*: an object is missed with probability ``miss_prob``; if its visible area is below
  ``small_area_frac`` of the image, with ``miss_prob_small`` instead. The draw is keyed on
  ``(seed, frame id, instance id)``: one frame is detected the same way every time it is asked.
- *False detections*: with probability ``false_positive_prob`` per frame one false box is
  added: a box of 4 to 20 % of the image width and height at a uniformly random place,
  named after an object the detector has reported earlier in the episode (an open-vocabulary
  detector firing one of its known classes on a wrong region). Before any real detection
  there is nothing to name and no false box.
- *Text queries*: :meth:`SimulatedDetector.matching` returns the detections a phrase names by
  the simulated VLM's grounding rule (:func:`vlm.sim.grounding.ground`: name, alias or label
  as contiguous words, attribute words must belong to the object), as YOLOE's text prompts do;
  a detection carries its object's aliases for this (a false box those of the name it took).

Defaults are our choice for a zero-shot open-vocabulary detector (not fitted to YOLOE) and are
fixed before any comparison: 15 % misses, 60 % for objects under 0.2 % of the image, 5 % of
frames with a false box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from vlm.sim.features import keyed_rng
from vlm.sim.grounding import ground, visible_regions
from vlm.types import FrameAnnotation, VisibleObject

__all__ = ["DetectorConfig", "DetectorError", "Detection", "SimulatedDetector"]


class DetectorError(ValueError):
    """Bad detector configuration or input (names the field)."""


@dataclass(frozen=True)
class DetectorConfig:
    """Error model of :class:`SimulatedDetector` (module docstring).

    miss_prob : chance to miss an object, [0, 1]
    small_area_frac : visible area below this fraction of the image is "small", [0, 1)
    miss_prob_small : chance to miss a small object, [0, 1]
    false_positive_prob : chance per frame of one false box, [0, 1]
    min_area_px : objects with fewer visible pixels are never reported
    """

    miss_prob: float = 0.15
    small_area_frac: float = 0.002
    miss_prob_small: float = 0.6
    false_positive_prob: float = 0.05
    min_area_px: int = 9

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise DetectorError(f"DetectorConfig.{f.name} must be a finite number, got {v!r}")
        for name in ("miss_prob", "miss_prob_small", "false_positive_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise DetectorError(f"DetectorConfig.{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.small_area_frac < 1.0:
            raise DetectorError(f"DetectorConfig.small_area_frac must be in [0, 1), got {self.small_area_frac}")
        if not isinstance(self.min_area_px, int) or self.min_area_px < 1:
            raise DetectorError(f"DetectorConfig.min_area_px must be an int >= 1, got {self.min_area_px!r}")


@dataclass(frozen=True)
class Detection:
    """One detected box.

    name, label : str, what the detector calls it
    box_px : (u0, v0, u1, v1) floats, pixel-centre extents of the box (u1 >= u0, v1 >= v0)
    instance_id : int, the annotated instance (0 for a false detection)
    aliases : other phrases the detector's text prompts match for it (the object's aliases)
    """

    name: str
    label: str
    box_px: tuple[float, float, float, float]
    instance_id: int
    aliases: tuple[str, ...] = ()

    @property
    def center_uv(self) -> tuple[float, float]:
        u0, v0, u1, v1 = self.box_px
        return (u0 + u1) / 2.0, (v0 + v1) / 2.0

    @property
    def false_positive(self) -> bool:
        return self.instance_id == 0


class SimulatedDetector:
    """Seeded detector over frame annotations (error model in the module docstring).

    Parameters
    ----------
    config : DetectorConfig
    seed : int, root of every draw
    """

    def __init__(self, config: DetectorConfig | None = None, seed: int = 0) -> None:
        self.config = config if config is not None else DetectorConfig()
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise DetectorError(f"seed must be an int, got {seed!r}")
        self.seed = int(seed)
        self._vocabulary: dict[str, tuple[str, tuple[str, ...]]] = {}  # name -> (label, aliases), first-seen order

    def reset(self) -> None:
        """Forget the episode's vocabulary (names seen so far)."""
        self._vocabulary.clear()

    def detect(self, annotation: FrameAnnotation, frame_id: str) -> list[Detection]:
        """Detections of one frame, real ones by instance id, then the false one if any."""
        if not isinstance(annotation, FrameAnnotation):
            raise DetectorError(f"the simulated detector needs a FrameAnnotation, got {type(annotation).__name__}")
        c = self.config
        ids = np.asarray(annotation.instance_ids)
        h, w = ids.shape
        areas = visible_regions(annotation)
        out: list[Detection] = []
        for iid in sorted(areas):
            area = areas[iid]
            if area < c.min_area_px:
                continue
            p_miss = c.miss_prob_small if area < c.small_area_frac * w * h else c.miss_prob
            if keyed_rng(self.seed, "detector-miss", frame_id, iid).random() < p_miss:
                continue
            vs, us = np.nonzero(ids == iid)
            obj = annotation.objects[iid]
            box = (float(us.min()), float(vs.min()), float(us.max()), float(vs.max()))
            out.append(Detection(obj.name, obj.label, box, int(iid), tuple(obj.aliases)))
        vocabulary = list(self._vocabulary.items())
        for d in out:
            self._vocabulary.setdefault(d.name, (d.label, d.aliases))
        rng = keyed_rng(self.seed, "detector-false", frame_id)
        if vocabulary and rng.random() < c.false_positive_prob:
            name, (label, aliases) = vocabulary[int(rng.integers(len(vocabulary)))]
            bw, bh = rng.uniform(0.04, 0.2) * w, rng.uniform(0.04, 0.2) * h
            u0, v0 = rng.uniform(0, w - 1 - bw), rng.uniform(0, h - 1 - bh)
            out.append(Detection(name, label, (float(u0), float(v0), float(u0 + bw), float(v0 + bh)), 0, aliases))
        return out

    @staticmethod
    def matching(phrase: str, detections: list[Detection]) -> list[Detection]:
        """Detections ``phrase`` names (grounding rule), best first; exact names first."""
        exact = [d for d in detections if d.name == " ".join(phrase.split())]
        objs = {k + 1: VisibleObject(k + 1, d.name, d.label, d.aliases) for k, d in enumerate(detections)}
        areas = {k + 1: max(1, int((d.box_px[2] - d.box_px[0] + 1) * (d.box_px[3] - d.box_px[1] + 1))) for k, d in enumerate(detections)}
        grounded = [detections[m.instance_id - 1] for m in ground(phrase, objs, areas)]
        return exact + [d for d in grounded if d not in exact]
