"""Tracking metrics against hand-computed trajectories (onfly.bench.metrics.track_metrics)."""

import numpy as np
import pytest

from onfly.bench.metrics import EpisodeMetrics, EpisodeTrace, MetricsError, as_track_episode, summarize_track, track_metrics

BAND = (1.5, 4.0)


def _trace(d, t=None, stopped=False, collided=False):
    """Vehicle on the x axis at distances ``d`` from an actor at the origin (actor at z 0.9)."""
    d = np.asarray(d, float)
    t = np.arange(len(d), dtype=float) if t is None else np.asarray(t, float)
    P = np.stack([d, np.zeros_like(d), np.full_like(d, 1.5)], axis=1)
    A = np.tile([0.0, 0.0, 0.9], (len(d), 1))
    return EpisodeTrace(t, P, stopped, collided), A


def test_time_in_band_band_error_and_a_loss_hand_computed():
    # t = 0..9 s, one sample a second; distances in m:
    d = [2.0, 3.0, 5.0, 6.0, 7.0, 6.0, 3.0, 3.0, 1.0, 2.0]
    tr, A = _trace(d)
    m = track_metrics(tr, A, np.ones(10, bool), band_m=BAND, in_band_frac=0.5, duration_s=9.0, lost_after_s=3.0)
    # in band on [0,1) [1,2) [6,7) [7,8) = 4 s of 9; [9] is the last sample (0 s)
    assert m.in_band_frac == pytest.approx(4 / 9)
    # errors of samples 0..8: 0 0 1 2 3 2 0 0 0.5 -> 8.5 over 9 s
    assert m.band_error_m == pytest.approx(8.5 / 9)
    # out of band from t=2 to t=6 (4 s > 3 s): lost once, back in band: re-found; the 1 s dip at t=8 is not a loss
    assert (m.times_lost, m.times_refound) == (1, 1)
    assert not m.success and not m.band_ok
    assert m.stop_ok is None
    assert m.min_distance_m == pytest.approx(1.0) and m.final_distance_m == pytest.approx(2.0)


def test_short_dips_are_not_losses_and_the_fraction_passes():
    d = [2.0, 2.0, 4.5, 4.5, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0]
    tr, A = _trace(d)
    m = track_metrics(tr, A, np.ones(11, bool), band_m=BAND, in_band_frac=0.8, duration_s=10.0, lost_after_s=3.0)
    assert m.in_band_frac == pytest.approx(0.8)
    assert m.times_lost == 0 and m.success


def test_a_loss_that_lasts_to_the_end_is_lost_not_refound():
    d = [2.0, 2.0, 9.0, 9.0, 9.0, 9.0, 9.0]
    tr, A = _trace(d)
    m = track_metrics(tr, A, np.ones(7, bool), band_m=BAND, in_band_frac=0.2, duration_s=6.0, lost_after_s=3.0)
    assert (m.times_lost, m.times_refound) == (1, 0)
    assert m.in_band_frac == pytest.approx(2 / 6)


def test_acquisition_before_the_band_is_not_a_loss():
    d = [8.0, 7.0, 6.0, 5.0, 4.0, 3.0, 3.0]
    tr, A = _trace(d)
    m = track_metrics(tr, A, np.ones(7, bool), band_m=BAND, in_band_frac=0.3, duration_s=6.0, lost_after_s=1.0)
    assert m.times_lost == 0
    assert m.in_band_frac == pytest.approx(2 / 6)


def test_an_early_end_counts_the_rest_of_the_duration_as_out_of_band():
    tr, A = _trace([2.0, 2.0, 2.0], collided=True)
    m = track_metrics(tr, A, np.ones(3, bool), band_m=BAND, in_band_frac=0.5, duration_s=10.0, lost_after_s=3.0)
    assert m.in_band_frac == pytest.approx(2 / 10)
    assert m.horizon_s == 10.0 and not m.success


def test_horizontal_distance_ignores_altitude():
    t = np.arange(3.0)
    P = np.array([[3.0, 0, 10.0], [0, 3.0, -5.0], [3.0, 0, 1.5]])
    tr = EpisodeTrace(t, P, False, False)
    m = track_metrics(tr, np.zeros((3, 3)), np.ones(3, bool), band_m=BAND, in_band_frac=1.0, duration_s=2.0, lost_after_s=1.0)
    assert m.in_band_frac == 1.0 and m.success


def test_stop_condition_needs_the_actor_stopped_and_the_vehicle_within_the_radius():
    d = [3.0, 3.0, 3.0, 2.5]
    still = np.array([True, True, False, False])  # moving flags: walked, stopped from t=2
    tr, A = _trace(d, stopped=True)
    m = track_metrics(tr, A, still, band_m=BAND, in_band_frac=0.9, duration_s=60.0, lost_after_s=3.0, stop_radius_m=3.0)
    # a stop task that the method stopped: the horizon is the flown time (3 s), all in band
    assert m.horizon_s == 3.0 and m.in_band_frac == 1.0
    assert m.stop_ok and m.success
    # stopped while the actor still walks: fails
    m2 = track_metrics(tr, A, np.ones(4, bool), band_m=BAND, in_band_frac=0.9, duration_s=60.0, lost_after_s=3.0, stop_radius_m=3.0)
    assert m2.stop_ok is False and not m2.success
    # stopped too far: fails
    m3 = track_metrics(tr, A, still, band_m=BAND, in_band_frac=0.9, duration_s=60.0, lost_after_s=3.0, stop_radius_m=2.0)
    assert m3.stop_ok is False and not m3.success
    # never stopped: the horizon is the task's duration and the stop fails
    tr4, _ = _trace(d, stopped=False)
    m4 = track_metrics(tr4, A, still, band_m=BAND, in_band_frac=0.01, duration_s=60.0, lost_after_s=3.0, stop_radius_m=3.0)
    assert m4.horizon_s == 60.0 and m4.stop_ok is False and not m4.success


def test_classic_metrics_of_a_tracking_episode_and_the_summary():
    tr, A = _trace([2.0, 2.0, 2.0])
    tm = track_metrics(tr, A, np.ones(3, bool), band_m=BAND, in_band_frac=0.9, duration_s=2.0, lost_after_s=3.0)
    base = EpisodeMetrics(False, False, False, 2.0, 1.0, 0.0, 0.0)
    em = as_track_episode(base, tm)
    assert em.success and em.oracle_success and em.spl == 1.0
    s = summarize_track([tm, tm])
    assert s["in_band"] == 1.0 and s["lost"] == 0.0 and s["stop_ok"] is None


def test_malformed_actor_arrays_are_refused():
    tr, A = _trace([2.0, 2.0])
    with pytest.raises(MetricsError, match="actor positions"):
        track_metrics(tr, A[:1], np.ones(2, bool), band_m=BAND, in_band_frac=0.5, duration_s=1.0, lost_after_s=1.0)
    with pytest.raises(MetricsError, match="bad tracking spec"):
        track_metrics(tr, A, np.ones(2, bool), band_m=(4.0, 1.0), in_band_frac=0.5, duration_s=1.0, lost_after_s=1.0)


def test_a_stop_before_the_actor_ever_walked_is_not_the_stop_asked_for():
    tr, A = _trace([3.0, 3.0, 3.0], stopped=True)
    m = track_metrics(tr, A, np.zeros(3, bool), band_m=BAND, in_band_frac=0.5, duration_s=60.0, lost_after_s=3.0, stop_radius_m=3.0)
    assert m.stop_ok is False and not m.success


def test_the_summary_has_a_tracking_table():
    from dataclasses import asdict

    from onfly.bench.runner import format_summary, summarize_records

    tr, A = _trace([2.0, 2.0, 2.0])
    tm = track_metrics(tr, A, np.ones(3, bool), band_m=BAND, in_band_frac=0.9, duration_s=2.0, lost_after_s=3.0)
    em = as_track_episode(EpisodeMetrics(False, False, False, 2.0, 1.0, 0.0, 0.0), tm)
    rec = {"method": "oracle", "kind": "track", "metrics": asdict(em), "sim_s": 2.0, "wall_s": 1.0, "failure": "", "track": asdict(tm)}
    summary = summarize_records([rec], error_model="nominal", name="t")
    assert summary["methods"]["oracle"]["by_kind"]["track"]["track"]["in_band"] == 1.0
    text = format_summary(summary)
    assert "time in band %" in text and "| oracle | 1 |" in text
