import numpy as np
import pytest

from onfly.bench.metrics import EpisodeTrace, GoalRegion, MetricsError, episode_metrics, summarize

GOAL = GoalRegion(center=[20.0, 0.0, 1.0], half_extents_m=[1.0, 1.0, 1.0])  # x in [19, 21]


def line_trace(xs, stopped=True, collided=False, dt=0.5):
    xs = np.asarray(xs, float)
    p = np.column_stack([xs, np.zeros_like(xs), np.ones_like(xs)])
    return EpisodeTrace(np.arange(len(xs)) * dt, p, stopped, collided)


def test_goal_region_distance_is_to_the_box_surface():
    assert GOAL.distance([20, 0, 1]) == 0.0
    assert GOAL.distance([14, 0, 1]) == pytest.approx(5.0)
    assert GOAL.distance([22, 4, 1]) == pytest.approx(np.hypot(1, 3))


def test_stop_just_inside_and_just_outside_the_radius():
    inside = episode_metrics(line_trace([0, 5, 10, 14.01]), GOAL, reference_path_m=14.0)
    assert inside.success and inside.oracle_success and not inside.collided
    assert inside.navigation_error_m == pytest.approx(4.99)
    assert inside.spl == pytest.approx(14.0 / 14.01)
    outside = episode_metrics(line_trace([0, 5, 10, 13.99]), GOAL, reference_path_m=14.0)
    assert not outside.success and not outside.oracle_success and outside.spl == 0.0
    assert outside.navigation_error_m == pytest.approx(5.01)


def test_collision_after_reaching_the_goal():
    m = episode_metrics(line_trace([0, 10, 16, 20, 22], stopped=False, collided=True), GOAL, 14.0)
    assert not m.success and m.oracle_success and m.collided
    assert m.flight_time_s == pytest.approx(2.0)


def test_contact_sample_alone_does_not_count_as_reaching():
    m = episode_metrics(line_trace([0, 10, 15], stopped=False, collided=True), GOAL, 14.0)
    assert not m.oracle_success


def test_oracle_pass_then_stop_outside():
    m = episode_metrics(line_trace([0, 10, 18, 20, 24, 28]), GOAL, 14.0)
    assert m.oracle_success and not m.success
    assert m.navigation_error_m == pytest.approx(7.0)
    assert m.path_length_m == pytest.approx(28.0)


def test_time_limit_near_goal_is_not_success():
    m = episode_metrics(line_trace([0, 10, 19], stopped=False), GOAL, 14.0)
    assert m.oracle_success and not m.success


def test_spl_penalizes_detours():
    m = episode_metrics(line_trace([0, 10, 0, 10, 16]), GOAL, reference_path_m=16.0)
    assert m.success and m.path_length_m == pytest.approx(36.0) and m.spl == pytest.approx(16 / 36)


def test_summary_means():
    ms = [
        episode_metrics(line_trace([0, 16]), GOAL, 16.0),
        episode_metrics(line_trace([0, 10], stopped=False, collided=True), GOAL, 16.0),
        episode_metrics(line_trace([0, 5, 10, 16], stopped=False), GOAL, 16.0),
    ]
    s = summarize(ms)
    assert s["episodes"] == 3
    assert s["SR"] == pytest.approx(1 / 3) and s["OSR"] == pytest.approx(2 / 3) and s["CR"] == pytest.approx(1 / 3)
    assert s["FT"] == pytest.approx((0.5 + 0.5 + 1.5) / 3)
    assert s["FT_success"] == pytest.approx(0.5)


def test_bad_traces_rejected():
    with pytest.raises(MetricsError, match="positions"):
        EpisodeTrace(np.arange(3), np.zeros((2, 3)), True, False)
    with pytest.raises(MetricsError, match="non-decreasing"):
        EpisodeTrace(np.array([0, 1, 0.5]), np.zeros((3, 3)), True, False)
    with pytest.raises(MetricsError, match="not both"):
        EpisodeTrace(np.arange(2), np.zeros((2, 3)), True, True)
    with pytest.raises(MetricsError, match="no episodes"):
        summarize([])
