"""PIVOT-style baseline: arrows drawn on the image, picks refit the sampler, short steps, no map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from baseline_harness import SMALL_CAMERA, RecordingVlm, fly, task, text
from onfly.baselines.common import FlightLimits
from onfly.baselines.pivot import (
    PivotConfig,
    PivotMethod,
    arrow_origin,
    directions_cam,
    draw_arrows,
    make_pivot,
    parse_pivot_answer,
    refit,
    sample_candidates,
)
from onfly.bench.registry import get_factory
from planning.esdf import EsdfMap
from planning.planner import Planner
from planning.planner_config import PlannerConfig
from vlm.prompts import PivotPrompt

LIMITS = FlightLimits.from_planner(PlannerConfig())


def method(backend, **cfg) -> PivotMethod:
    return PivotMethod("sim:perfect", PivotConfig(**cfg), LIMITS, backend=backend)


def test_candidates_stay_in_view_and_project_to_their_endpoints():
    rng = np.random.default_rng(0)
    cand = sample_candidates(rng, np.zeros(2), np.array([2.0, 2.0]), 200, SMALL_CAMERA, 0.9)
    assert cand.labels == tuple(range(1, 201))
    assert SMALL_CAMERA.in_image(cand.end_uv).all()
    # each endpoint back-projects to its direction
    rays = SMALL_CAMERA.back_project(cand.end_uv, 1.0)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    np.testing.assert_allclose(rays, directions_cam(cand.az_el), atol=1e-9)
    # left-positive azimuth lands left of the centre, up-positive elevation above it
    uv, _ = SMALL_CAMERA.project(directions_cam(np.array([[0.3, 0.2]]))[0])
    assert uv[0] < SMALL_CAMERA.cx and uv[1] < SMALL_CAMERA.cy


def test_arrows_are_drawn_on_a_copy_with_their_numbers():
    rgb = np.full((SMALL_CAMERA.height, SMALL_CAMERA.width, 3), 90, np.uint8)
    cand = sample_candidates(np.random.default_rng(1), np.zeros(2), np.array([0.4, 0.12]), 8, SMALL_CAMERA, 0.9)
    drawn = draw_arrows(rgb, cand, SMALL_CAMERA)
    assert (rgb == 90).all()  # the input is untouched
    changed = np.any(drawn != rgb, axis=2)
    u0, v0 = arrow_origin(SMALL_CAMERA)
    assert changed[v0, u0]
    for (u, v) in cand.end_uv:  # each arrow reaches its endpoint
        ui, vi = int(round(u)), int(round(v))
        assert changed[max(vi - 1, 0) : vi + 2, max(ui - 1, 0) : ui + 2].any()
    # the midpoint of each arrow shaft is painted too
    for (u, v) in cand.end_uv:
        um, vm = int(round((u + u0) / 2)), int(round((v + v0) / 2))
        assert changed[max(vm - 1, 0) : vm + 2, max(um - 1, 0) : um + 2].any()


def test_parse_answer():
    labels = (1, 2, 3, 4)
    assert parse_pivot_answer('{"arrows": [3, 1]}', labels).picks == (3, 1)
    assert parse_pivot_answer('```json\n{"arrows": [9, 2, 2]}\n```', labels).picks == (2,)  # undrawn and repeats dropped
    assert parse_pivot_answer('Best arrows: {"stop": true}', labels).stop
    for bad, why in [('{"arrows": [9]}', "no drawn arrow"), ('{"arrows": [', "no JSON object"), ('{"arrow": "left"}', "no 'arrows'"), ("", "no JSON")]:
        ans = parse_pivot_answer(bad, labels)
        assert not ans.ok and why in ans.reason


def test_refit_is_the_mean_and_std_of_the_picks():
    cand = sample_candidates(np.random.default_rng(2), np.zeros(2), np.array([0.4, 0.1]), 8, SMALL_CAMERA, 0.9)
    mean, std = refit(cand, (2, 5, 7), 0.03)
    chosen = cand.az_el[[1, 4, 6]]
    np.testing.assert_allclose(mean, chosen.mean(axis=0))
    np.testing.assert_allclose(std, np.maximum(chosen.std(axis=0), 0.03))


def test_each_decision_draws_arrows_and_narrows_the_distribution_around_the_target():
    vlm = RecordingVlm("perfect")
    m = method(vlm)
    res, steps = fly(m, "park-o01", time_limit_s=12.0)
    pivot_calls = [(p, imgs) for p, imgs, _ in vlm.calls]
    assert all(isinstance(p, PivotPrompt) for p, _ in pivot_calls) and len(pivot_calls) >= 6
    # 3 iterations x 8 arrows per decision, the drawn image differs from the camera frame
    first, imgs = pivot_calls[0]
    assert len(first.arrows) == 8 and first.n_pick == 3
    assert m.last_drawn is not None and m.last_drawn.shape == (SMALL_CAMERA.height, SMALL_CAMERA.width, 3)
    # the three prompts of one decision share the frame; the distribution narrows
    frames = [imgs[0].frame_id for _, imgs in pivot_calls[:3]]
    assert frames[0] == frames[1] == frames[2]
    for dec in m.trace[:2]:
        assert len(dec) == 3
        spreads = [float(np.linalg.norm(std)) for _, std in dec]
        assert spreads[-1] < math.hypot(0.4, 0.12) and spreads[-1] <= spreads[0] + 1e-12
    # the arrows of a later iteration cluster where the picks of the first were
    arrows1 = np.array([a[1:] for a in pivot_calls[0][0].arrows], float)
    arrows3 = np.array([a[1:] for a in pivot_calls[2][0].arrows], float)
    assert arrows3.std(axis=0).sum() < arrows1.std(axis=0).sum()
    # it moved toward the bench (a step per decision, hovering while it thinks)
    start_gap = float(task("park-o01").goal_region.distance(steps[0].state.p))
    assert m.summary()["steps"] >= 1 and res.metrics.navigation_error_m < start_gap - 1.0


def test_stop_answer_ends_the_episode_and_nothing_else_does():
    vlm = RecordingVlm("perfect", override=lambda p, i, r: text('{"stop": true}') if i == 4 else text('{"arrows": []}'))
    m = method(vlm)
    res, _ = fly(m, "park-o01", time_limit_s=20.0)
    assert res.end_reason == "stopped" and len(vlm.calls) == 5
    assert m.summary()["unreadable"] == 4 and m.summary()["no_decision"] == 1


def test_holds_no_map_and_no_planner():
    m = method(RecordingVlm("perfect"))
    fly(m, "park-o01", time_limit_s=3.0)
    assert not any(isinstance(v, (EsdfMap, Planner)) for v in vars(m).values())


def test_factory_options_and_registry():
    m = make_pivot("sim:nominal", 0, planner={"v_max_mps": 0.5}, n_candidates=10, n_pick=2)
    assert (m.config.n_candidates, m.config.n_iterations, m.config.n_pick, m.limits.v_max_mps) == (10, 3, 2, 0.5)
    assert get_factory("pivot") is make_pivot
    with pytest.raises(ValueError, match="n_pick .* must not exceed n_candidates"):
        make_pivot("sim:nominal", 0, n_candidates=2, n_pick=3)
    with pytest.raises(ValueError, match="unknown pivot option"):
        make_pivot("sim:nominal", 0, arrows=8)


def _plan_at(goal, t_s, p=None, v=(0.0, 0.0, 0.0)):
    """A straight-line plan made at ``t_s`` from a vehicle at ``p`` (default: the goal)."""
    from planning.straight_line import straight_line_plan
    from planning.trajectory import VehicleState

    state = VehicleState(t_s=t_s, p=np.asarray(goal if p is None else p, float), v=np.asarray(v, float), yaw=0.0)
    return straight_line_plan(state, np.asarray(goal, float), v_max_mps=0.6, a_max_mps2=0.6, yaw_rate_max_rps=0.4)


def test_a_move_ends_when_its_setpoint_has_held_the_goal_with_the_vehicle_nearby_not_only_when_still():
    from onfly.baselines.common import ARRIVE_SETTLE_RADIUS_M, ARRIVE_SETTLE_S, Arrival
    from planning.trajectory import VehicleState

    goal = np.array([2.0, 1.0, 1.5])
    arrival = Arrival()
    # at the goal and still: over at once (the only rule the ideal world ever needs)
    assert arrival(0.0, VehicleState(t_s=0.0, p=goal, v=np.zeros(3), yaw=0.0), goal, None)
    # a gust holds the vehicle 0.3 m off at 0.3 m/s while the setpoint stands at the goal
    off = VehicleState(t_s=0.0, p=goal + [0.3, 0.0, 0.0], v=np.array([0.3, 0.0, 0.0]), yaw=0.0)
    arrival = Arrival()
    ts = np.arange(0.0, ARRIVE_SETTLE_S + 0.25, 0.1)
    over = [arrival(t, off, goal, _plan_at(goal, t - 0.1)) for t in ts]
    first = ts[over.index(True)]
    assert first == pytest.approx(ARRIVE_SETTLE_S, abs=0.11) and not any(over[: over.index(True)])
    # farther than the settle radius: never over, however long the setpoint has stood there
    far = VehicleState(t_s=0.0, p=goal + [ARRIVE_SETTLE_RADIUS_M + 0.1, 0.0, 0.0], v=np.zeros(3), yaw=0.0)
    arrival = Arrival()
    assert not any(arrival(t, far, goal, _plan_at(goal, t - 0.1)) for t in np.arange(0.0, 5.0, 0.1))
    # the setpoint still on its way (a plan from 2 m back): no settling starts; a stale plan neither
    arrival = Arrival()
    assert not any(arrival(t, off, goal, _plan_at(goal, t - 0.1, p=goal - [2.0, 0.0, 0.0])) for t in np.arange(0.0, 3.0, 0.1))
    assert not any(arrival(t, off, goal, _plan_at(goal, 0.0)) for t in np.arange(1.0, 4.0, 0.1))
