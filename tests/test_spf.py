"""SPF-style baseline: point + travel distance, yaw then straight line, no map; zero depth stops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from baseline_harness import SMALL_CAMERA, RecordingVlm, fly, text
from onfly.baselines.common import FlightLimits
from onfly.baselines.spf import SpfConfig, SpfMethod, make_spf, make_spf_planner, parse_spf_answer
from onfly.bench.registry import get_factory
from planning.esdf import EsdfMap
from planning.frames import wrap_angle
from planning.planner import Planner
from planning.planner_config import PlannerConfig
from vlm.prompts import SpfPrompt

LIMITS = FlightLimits.from_planner(PlannerConfig())


def test_parse_answer_reads_points_depths_and_the_zero_depth_stop():
    a = parse_spf_answer('{"point_2d": [40, 20], "depth": 6}', (160, 107))
    assert a.ok and a.uv == (40, 20) and a.depth_m == 6.0 and not a.stop
    assert parse_spf_answer('```json\n{"point_2d": [40, 20], "depth": 0}\n```', (160, 107)).stop
    assert parse_spf_answer('{"point_2d": [40, 20], "depth": "0.0"}', (160, 107)).stop
    assert not parse_spf_answer('{"point_2d": [40, 20], "depth": 10}', (160, 107)).stop
    for bad in ('{"point_2d": [400, 20], "depth": 3}', '{"point_2d": [40, 20]}', "fly left", '{"point_2d": [40, '):
        assert not parse_spf_answer(bad, (160, 107)).ok


def test_never_consults_a_map(monkeypatch):
    # every ESDF entry point raises: the SPF flight must not notice
    for name in ("__init__", "integrate", "query", "is_free"):
        monkeypatch.setattr(EsdfMap, name, lambda *a, **k: (_ for _ in ()).throw(AssertionError("ESDF used")))
    monkeypatch.setattr(Planner, "step", lambda *a, **k: (_ for _ in ()).throw(AssertionError("planner used")))
    vlm = RecordingVlm("perfect")
    m = SpfMethod("sim:perfect", SpfConfig(), LIMITS, backend=vlm)
    res, _ = fly(m, "park-o01", time_limit_s=30.0)
    assert res.end_reason == "stopped" and res.metrics.success and res.error == ""
    assert m.esdf is None and m.planner is None and m.summary()["uses_map"] is False
    assert all(isinstance(p, SpfPrompt) for p, _, _ in vlm.calls)
    assert vlm.calls[-1][2].text.endswith('"depth": 0}')


def test_flies_yaw_first_then_straight():
    # the first answer points at the right image edge, 4 m: the vehicle turns on the spot, then
    # flies the straight segment; later answers repeat the same world goal
    def override(prompt, i, resp):
        return text('{"point_2d": [159, 53], "depth": 4}') if i == 0 else text("no answer")

    vlm = RecordingVlm("perfect", override=override)
    m = SpfMethod("sim:perfect", SpfConfig(), LIMITS, backend=vlm)
    res, steps = fly(m, "park-o01", time_limit_s=22.0)
    g = m.goal
    assert g is not None
    p = np.array([s.state.p for s in steps])
    yaw = np.array([s.state.yaw for s in steps])
    bearing = math.atan2(g[1] - p[0, 1], g[0] - p[0, 0])
    err = np.abs(wrap_angle(yaw - bearing))
    moved = np.linalg.norm(p[:, :2] - p[0, :2], axis=1)
    set_at = next(k for k, s in enumerate(steps) if m.goal is not None and s.t_s >= 0.81)
    # while the heading is off by more than the tolerance (after the goal arrived), no translation
    turning = [k for k in range(set_at, len(steps)) if err[k] > 0.2]
    assert len(turning) > 5 and max(moved[k] for k in turning) < 0.05
    # then it flies straight to the goal: every later position lies on the segment start-goal
    later = [k for k in range(set_at, len(steps)) if moved[k] > 0.2]
    d = (g - p[0]) / np.linalg.norm(g - p[0])
    off_line = [np.linalg.norm((p[k] - p[0]) - np.dot(p[k] - p[0], d) * d) for k in later]
    assert later and max(off_line) < 0.05
    assert np.linalg.norm(res.trace.positions[-1] - g) < 0.2
    # the goal is the pixel's ray at 4 m z-depth from the frame's camera
    assert abs(math.hypot(*(g[:2] - p[0, :2])) - math.hypot(4.0, 4.0 * (159 - SMALL_CAMERA.cx) / SMALL_CAMERA.fx)) < 0.1


def test_planner_variant_flies_the_same_goals_through_esdf_and_mpc():
    vlm = RecordingVlm("perfect")
    planner = Planner(PlannerConfig())
    m = SpfMethod("sim:perfect", SpfConfig(), LIMITS, planner=planner, backend=vlm)
    calls = []
    real_step = Planner.step

    def spy(self, state, goal, field, yaw_ref=None, volume=None):
        calls.append((np.asarray(goal, float).copy(), field, volume))
        return real_step(self, state, goal, field, yaw_ref, volume)

    import unittest.mock as um

    with um.patch.object(Planner, "step", spy):
        res, _ = fly(m, "park-o01", time_limit_s=30.0)
    assert res.end_reason == "stopped" and res.metrics.success
    assert isinstance(m.esdf, EsdfMap) and all(f is m.esdf for _, f, _ in calls)
    # the operator's flight volume (the scene bounds) reaches every planner step
    assert all(v is not None for _, _, v in calls)
    assert all(bool(v.contains(g, margin_m=0.45 - 1e-9)[0]) for g, _, v in calls)
    assert m.summary()["uses_map"] is True and len(calls) > 50


def test_factories_and_registry():
    assert get_factory("spf") is make_spf and get_factory("spf_planner") is make_spf_planner
    a = make_spf("sim:nominal", 0, planner={"v_max_mps": 0.5}, esdf={}, verifier={}, max_travel_m=5.0)
    assert a.planner is None and a.limits.v_max_mps == 0.5 and a.config.max_travel_m == 5.0 and a.name == "spf"
    b = make_spf_planner("sim:nominal", 0)
    assert isinstance(b.planner, Planner) and b.name == "spf_planner"
    with pytest.raises(ValueError, match="unknown spf option"):
        make_spf("sim:nominal", 0, step_m=1.0)
    with pytest.raises(ValueError, match="max_travel_m must be a finite number > 0"):
        make_spf("sim:nominal", 0, max_travel_m=-1.0)
