"""Simulated detector: sees only the annotation, misses and invents boxes at its documented rates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onfly.baselines.detector import Detection, DetectorConfig, DetectorError, SimulatedDetector
from vlm.types import FrameAnnotation, VisibleObject

W, H = 160, 107


def annotation(objs) -> FrameAnnotation:
    """objs: (iid, name, label, (u0, v0, u1, v1) exclusive, aliases)."""
    ids = np.zeros((H, W), np.int32)
    for iid, _, _, (u0, v0, u1, v1), _ in objs:
        ids[v0:v1, u0:u1] = iid
    depth = np.full((H, W), 10.0, np.float32)
    objects = {iid: VisibleObject(iid, name, label, aliases) for iid, name, label, _, aliases in objs}
    objects[99] = VisibleObject(99, "hidden cone", "cone")  # annotated but without a pixel
    return FrameAnnotation(ids, depth, objects)


BIG = (1, "red van", "van", (100, 40, 140, 80), ("delivery van",))  # 1600 px > 0.2 % of the image
SMALL = (2, "fire hydrant", "hydrant", (10, 60, 14, 64), ())  # 16 px < 0.2 %
TINY = (3, "bolt", "bolt", (50, 50, 52, 52), ())  # 4 px < min_area_px


def binomial_ok(k, n, p, z=4.5):
    return abs(k / n - p) <= z * math.sqrt(max(p * (1 - p), 1e-12) / n)


def test_perfect_detector_reports_boxes_of_visible_pixels_only():
    det = SimulatedDetector(DetectorConfig(miss_prob=0.0, miss_prob_small=0.0, false_positive_prob=0.0))
    out = det.detect(annotation([BIG, SMALL, TINY]), "f0")
    assert out == [
        Detection("red van", "van", (100.0, 40.0, 139.0, 79.0), 1, ("delivery van",)),
        Detection("fire hydrant", "hydrant", (10.0, 60.0, 13.0, 63.0), 2, ()),
    ]
    assert out[0].center_uv == (119.5, 59.5) and not out[0].false_positive


@pytest.mark.parametrize("cfg", [DetectorConfig(), DetectorConfig(miss_prob=0.3, miss_prob_small=0.8)])
def test_miss_rates_follow_the_config(cfg):
    det = SimulatedDetector(cfg, seed=3)
    ann = annotation([BIG, SMALL])
    n = 1500
    seen_big = seen_small = 0
    for k in range(n):
        names = {d.name for d in det.detect(ann, f"f{k}") if not d.false_positive}
        seen_big += "red van" in names
        seen_small += "fire hydrant" in names
    assert binomial_ok(n - seen_big, n, cfg.miss_prob)
    assert binomial_ok(n - seen_small, n, cfg.miss_prob_small)


def test_same_frame_same_detections_and_seeds_differ():
    ann = annotation([BIG, SMALL])
    a = [SimulatedDetector(seed=1).detect(ann, f"f{k}") for k in range(200)]
    b = [SimulatedDetector(seed=1).detect(ann, f"f{k}") for k in range(200)]
    c = [SimulatedDetector(seed=2).detect(ann, f"f{k}") for k in range(200)]
    assert a == b and a != c


def test_false_boxes_take_known_names_at_the_documented_rate():
    cfg = DetectorConfig(miss_prob=0.0, miss_prob_small=0.0, false_positive_prob=0.2)
    det = SimulatedDetector(cfg, seed=0)
    assert [d for d in det.detect(annotation([]), "empty") if d.false_positive] == []  # nothing known yet
    det.detect(annotation([BIG]), "first")  # learns "red van"
    n, falses = 2000, 0
    for k in range(n):
        for d in det.detect(annotation([SMALL]), f"g{k}"):
            if d.false_positive:
                falses += 1
                assert d.name in ("red van", "fire hydrant") and d.instance_id == 0
                u0, v0, u1, v1 = d.box_px
                assert 0 <= u0 < u1 <= W - 1 and 0 <= v0 < v1 <= H - 1
    assert binomial_ok(falses, n, 0.2)


def test_text_queries_use_names_aliases_and_labels():
    det = SimulatedDetector(DetectorConfig(miss_prob=0.0, miss_prob_small=0.0, false_positive_prob=0.0))
    out = det.detect(annotation([BIG, SMALL, (4, "blue van", "van", (0, 0, 30, 30), ())]), "q")
    # the alias with its own modifiers names the red van; they are not the blue van's, so the
    # label inside that phrase does not name it
    assert [d.name for d in det.matching("fly to the red delivery van", out)] == ["red van"]
    assert [d.name for d in det.matching("fly to the delivery van", out)] == ["red van"]
    assert [d.name for d in det.matching("red van", out)] == ["red van"]  # exact name only
    assert {d.name for d in det.matching("the van", out)} == {"red van", "blue van"}
    assert det.matching("find the green dumpster", out) == []


def test_bad_config_and_input_errors():
    with pytest.raises(DetectorError, match="miss_prob must be in"):
        DetectorConfig(miss_prob=1.5)
    with pytest.raises(DetectorError, match="min_area_px must be an int"):
        DetectorConfig(min_area_px=0)
    with pytest.raises(DetectorError, match="needs a FrameAnnotation"):
        SimulatedDetector().detect(np.zeros((3, 3)), "x")  # type: ignore[arg-type]
